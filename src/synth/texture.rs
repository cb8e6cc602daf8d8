//! Procedural materials for the synthetic photos: bricks with mortar, plaster with stains, windows
//! with frames and reflective panes, roof tiles in rows, grass / asphalt / gravel ground, bark,
//! foliage, car paint. Everything is evaluated in world coordinates from a hash-based value noise,
//! so a surface looks the same from every viewpoint (as a real facade does) and rendering needs no
//! texture images. Patterns finer than the pixel footprint fade to their mean colour (a cheap
//! stand-in for mip-mapping) so that supersampling does not have to fight aliasing alone.

use glam::{Vec2, Vec3};

/// Mixes a 64-bit value (SplitMix64 finaliser): the root of every procedural pattern.
pub fn hash_u64(mut value: u64) -> u64 {
    value = value.wrapping_add(0x9E37_79B9_7F4A_7C15);
    value = (value ^ (value >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    value = (value ^ (value >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    value ^ (value >> 31)
}

/// A uniform number in `[0, 1)` from integer lattice coordinates and a seed.
pub fn hash_unit(seed: u64, x: i64, y: i64, z: i64) -> f32 {
    let h = hash_u64(
        seed ^ hash_u64(x as u64 ^ hash_u64((y as u64) ^ hash_u64(z as u64).rotate_left(17))),
    );
    (h >> 40) as f32 / (1u64 << 24) as f32
}

fn smooth(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

/// Trilinear value noise in `[0, 1)` with a smoothstep fade; period 1 in each axis' lattice.
pub fn value_noise(seed: u64, p: Vec3) -> f32 {
    let base = p.floor();
    let f = p - base;
    let (x, y, z) = (base.x as i64, base.y as i64, base.z as i64);
    let (u, v, w) = (smooth(f.x), smooth(f.y), smooth(f.z));
    let corner = |dx: i64, dy: i64, dz: i64| hash_unit(seed, x + dx, y + dy, z + dz);
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), u);
    let x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), u);
    let x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), u);
    let x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), u);
    lerp(lerp(x00, x10, v), lerp(x01, x11, v), w)
}

/// Fractal sum of value noise, centred on 0 (roughly in `[-0.5, 0.5]`). `base_scale_m` is the
/// feature size of the first octave; octaves finer than `footprint_m` are skipped.
pub fn fbm(seed: u64, p: Vec3, base_scale_m: f32, octaves: u32, footprint_m: f32) -> f32 {
    let mut sum = 0.0;
    let mut amplitude = 0.5;
    let mut total = 0.0;
    let mut scale = base_scale_m;
    for octave in 0..octaves {
        if scale < footprint_m * 0.7 {
            break;
        }
        sum += amplitude * (value_noise(seed.wrapping_add(octave as u64 * 7919), p / scale) - 0.5);
        total += amplitude;
        amplitude *= 0.5;
        scale *= 0.5;
    }
    if total > 0.0 {
        sum / total * 0.9
    } else {
        0.0
    }
}

/// What a surface is made of. Variants that need a colour choice carry a small palette index.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Material {
    Brick {
        palette: u8,
    },
    Plaster {
        palette: u8,
    },
    /// Wood under the roof overhang and on gable boards.
    Soffit,
    RoofTile {
        palette: u8,
    },
    /// Gravel-covered flat roof.
    FlatRoof,
    Concrete,
    /// A window, door or garage door described by a [`Panel`] (the face's panel index).
    Opening,
    /// The ground: its look comes from the [`GroundLayout`] at the point.
    Ground,
    Bark,
    Foliage {
        palette: u8,
    },
    CarPaint {
        palette: u8,
    },
    CarGlass,
    Tyre,
    FenceWood,
    Clothing {
        palette: u8,
    },
    Skin,
}

/// What a surface point looks like before lighting.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceSample {
    /// Diffuse reflectance, linear RGB.
    pub albedo: Vec3,
    /// Mirror reflectance at normal incidence (windows, car glass, paint).
    pub mirror: f32,
}

/// The kinds of opening a [`Panel`] can be.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PanelKind {
    /// A window split into `columns` × `rows` panes by mullions.
    Window {
        columns: u8,
        rows: u8,
    },
    Door,
    GarageDoor,
}

/// A rectangle on a wall in world coordinates: `origin_m` is its lower-left corner seen from
/// outside, `u_axis` runs along the wall, `v_axis` up.
#[derive(Clone, Copy, Debug)]
pub struct Panel {
    pub origin_m: Vec3,
    pub u_axis: Vec3,
    pub v_axis: Vec3,
    pub width_m: f32,
    pub height_m: f32,
    pub kind: PanelKind,
    /// Frame colour choice and curtain pattern seed.
    pub style: u32,
}

/// Paved and gravel areas of the ground; everything else is grass.
#[derive(Clone, Debug, Default)]
pub struct GroundLayout {
    /// Asphalt strips: segment end points and half width, metres.
    pub asphalt: Vec<(Vec2, Vec2, f32)>,
    /// Gravel paths.
    pub gravel: Vec<(Vec2, Vec2, f32)>,
    /// Concrete slabs (patio, pavement).
    pub concrete: Vec<(Vec2, Vec2, f32)>,
}

fn distance_to_segment(p: Vec2, a: Vec2, b: Vec2) -> f32 {
    let ab = b - a;
    let t = ((p - a).dot(ab) / ab.length_squared().max(1e-9)).clamp(0.0, 1.0);
    (p - (a + ab * t)).length()
}

fn srgb(r: u8, g: u8, b: u8) -> Vec3 {
    let to_linear = |c: u8| (c as f32 / 255.0).powf(2.2);
    Vec3::new(to_linear(r), to_linear(g), to_linear(b))
}

/// A smooth 0→1 ramp that also fades a line pattern of width `line_m` when the footprint is
/// larger: returns the line coverage in `[0, 1]`.
fn line_coverage(distance_to_line_m: f32, line_half_width_m: f32, footprint_m: f32) -> f32 {
    let soft = footprint_m.max(1e-4);
    let edge = ((line_half_width_m - distance_to_line_m) / soft + 0.5).clamp(0.0, 1.0);
    // When the footprint exceeds the line spacing the pattern averages out; callers blend with the
    // mean using `pattern_visibility`.
    edge
}

/// 1 when a pattern of period `period_m` is resolved at this footprint, falling to 0 when the
/// footprint is a full period (the pattern then shows its mean colour).
fn pattern_visibility(period_m: f32, footprint_m: f32) -> f32 {
    (1.5 - 1.5 * footprint_m / period_m).clamp(0.0, 1.0)
}

/// Horizontal unit vector along a surface with normal `normal` (for walls and roof slopes).
fn along_surface(normal: Vec3) -> Vec3 {
    let horizontal = Vec3::new(-normal.y, normal.x, 0.0);
    if horizontal.length_squared() < 1e-6 {
        Vec3::X
    } else {
        horizontal.normalize()
    }
}

/// Evaluates a material at a world point.
///
/// `normal` is the face normal (world), `footprint_m` the size of one rendered sample on the
/// surface, `seed` the scene seed, `object_id` varies colours between objects of one material.
#[allow(clippy::too_many_arguments)]
pub fn evaluate(
    material: Material,
    panel: Option<&Panel>,
    ground: &GroundLayout,
    p: Vec3,
    normal: Vec3,
    footprint_m: f32,
    seed: u64,
    object_id: u32,
) -> SurfaceSample {
    let object_seed = hash_u64(seed ^ (u64::from(object_id) << 20));
    let diffuse = |albedo: Vec3| SurfaceSample {
        albedo,
        mirror: 0.0,
    };
    match material {
        Material::Brick { palette } => {
            diffuse(brick(seed, object_seed, palette, p, normal, footprint_m))
        }
        Material::Plaster { palette } => diffuse(plaster(seed, palette, p, normal, footprint_m)),
        Material::Soffit => {
            let grain = fbm(seed ^ 11, p * Vec3::new(1.0, 1.0, 8.0), 0.4, 4, footprint_m);
            diffuse(srgb(150, 120, 90) * (1.0 + 0.5 * grain))
        }
        Material::RoofTile { palette } => diffuse(roof_tile(seed, palette, p, normal, footprint_m)),
        Material::FlatRoof => {
            let coarse = fbm(seed ^ 21, p, 3.0, 3, footprint_m);
            let fine = fbm(seed ^ 22, p, 0.08, 3, footprint_m);
            diffuse(srgb(120, 118, 112) * (1.0 + 0.6 * coarse + 0.5 * fine))
        }
        Material::Concrete => {
            let stain = fbm(seed ^ 31, p, 1.5, 4, footprint_m);
            diffuse(srgb(165, 162, 155) * (1.0 + 0.5 * stain))
        }
        Material::Opening => match panel {
            Some(panel) => opening(seed, panel, p, footprint_m),
            None => diffuse(srgb(60, 60, 60)),
        },
        Material::Ground => diffuse(ground_albedo(seed, ground, p, footprint_m)),
        Material::Bark => {
            let stripes = fbm(seed ^ 41, p * Vec3::new(6.0, 6.0, 0.7), 0.5, 4, footprint_m);
            diffuse(srgb(80, 65, 50) * (1.0 + 0.8 * stripes))
        }
        Material::Foliage { palette } => {
            let clumps = fbm(seed ^ 51, p, 0.6, 5, footprint_m);
            let leaves = value_noise(seed ^ 52, p / 0.07);
            let leaf_mix = pattern_visibility(0.07, footprint_m);
            let base = match palette % 3 {
                0 => srgb(70, 95, 45),
                1 => srgb(55, 80, 40),
                _ => srgb(95, 105, 50),
            };
            let brightness =
                (1.0 + 1.2 * clumps) * (1.0 + leaf_mix * 0.7 * (leaves - 0.5)).max(0.1);
            diffuse(base * brightness)
        }
        Material::CarPaint { palette } => {
            let base = match palette % 6 {
                0 => srgb(200, 200, 205),
                1 => srgb(25, 25, 30),
                2 => srgb(140, 20, 25),
                3 => srgb(30, 50, 110),
                4 => srgb(120, 125, 130),
                _ => srgb(220, 215, 200),
            };
            SurfaceSample {
                albedo: base,
                mirror: 0.08,
            }
        }
        Material::CarGlass => SurfaceSample {
            albedo: srgb(20, 24, 28),
            mirror: 0.3,
        },
        Material::Tyre => diffuse(srgb(25, 25, 25)),
        Material::FenceWood => {
            let grain = fbm(seed ^ 61, p * Vec3::new(1.0, 1.0, 5.0), 0.3, 4, footprint_m);
            diffuse(srgb(125, 100, 75) * (1.0 + 0.6 * grain))
        }
        Material::Clothing { palette } => diffuse(match palette % 5 {
            0 => srgb(40, 50, 90),
            1 => srgb(150, 40, 40),
            2 => srgb(200, 200, 190),
            3 => srgb(40, 40, 40),
            _ => srgb(90, 120, 70),
        }),
        Material::Skin => diffuse(srgb(200, 160, 130)),
    }
}

fn brick(
    seed: u64,
    object_seed: u64,
    palette: u8,
    p: Vec3,
    normal: Vec3,
    footprint_m: f32,
) -> Vec3 {
    const COURSE_M: f32 = 0.075;
    const BRICK_M: f32 = 0.225;
    const MORTAR_HALF_M: f32 = 0.006;
    let along = along_surface(normal);
    let s = p.dot(along);
    let t = p.z;
    let course = (t / COURSE_M).floor();
    let shifted = s + if (course as i64) % 2 == 0 {
        0.0
    } else {
        BRICK_M * 0.5
    };
    let brick_index = (shifted / BRICK_M).floor();
    let (base, mortar) = match palette % 3 {
        0 => (srgb(150, 70, 50), srgb(190, 185, 175)),
        1 => (srgb(170, 110, 75), srgb(200, 195, 185)),
        _ => (srgb(120, 55, 45), srgb(160, 155, 150)),
    };
    let variation = hash_unit(object_seed, brick_index as i64, course as i64, 3) - 0.5;
    let tone = hash_unit(object_seed, brick_index as i64, course as i64, 4) - 0.5;
    let grain = fbm(seed ^ 71, p, 0.05, 2, footprint_m);
    let brick_colour =
        base * (1.0 + 0.45 * variation + 0.3 * grain) + Vec3::new(0.02, 0.0, -0.01) * tone;
    let dt = (t - course * COURSE_M).min((course + 1.0) * COURSE_M - t);
    let ds = (shifted - brick_index * BRICK_M).min((brick_index + 1.0) * BRICK_M - shifted);
    let mortar_cover = line_coverage(dt, MORTAR_HALF_M, footprint_m).max(line_coverage(
        ds,
        MORTAR_HALF_M,
        footprint_m,
    ));
    let detailed = brick_colour.lerp(mortar, mortar_cover);
    let mean = base.lerp(mortar, 0.2);
    let weathering = fbm(seed ^ 72, p, 2.0, 3, footprint_m);
    let colour = mean.lerp(detailed, pattern_visibility(COURSE_M, footprint_m));
    colour * (1.0 + 0.35 * weathering)
}

fn plaster(seed: u64, palette: u8, p: Vec3, normal: Vec3, footprint_m: f32) -> Vec3 {
    let base = match palette % 4 {
        0 => srgb(225, 215, 190),
        1 => srgb(200, 195, 185),
        2 => srgb(215, 190, 160),
        _ => srgb(185, 200, 195),
    };
    let along = along_surface(normal);
    let coarse = fbm(seed ^ 81, p, 1.8, 4, footprint_m);
    let fine = fbm(seed ^ 82, p, 0.04, 3, footprint_m);
    // Rain stains: streaks stretched vertically, stronger near the bottom of the wall.
    let streak_coord = Vec3::new(p.dot(along) * 4.0, 0.0, p.z * 0.4);
    let streaks = (fbm(seed ^ 83, streak_coord, 0.6, 3, footprint_m) - 0.1).max(0.0);
    let bottom_dirt = (1.0 - (p.z / 0.6)).clamp(0.0, 1.0);
    let darkening = 1.0 - 0.7 * streaks - 0.3 * bottom_dirt;
    // Patches of repair and weathering at the metre scale.
    let patches = fbm(seed ^ 84, p, 0.7, 3, footprint_m);
    base * (1.0 + 0.45 * coarse + 0.3 * fine + 0.2 * patches) * darkening
}

fn roof_tile(seed: u64, palette: u8, p: Vec3, normal: Vec3, footprint_m: f32) -> Vec3 {
    const ROW_M: f32 = 0.3;
    const TILE_M: f32 = 0.22;
    let along = along_surface(normal);
    let down_slope = normal.cross(along).normalize_or_zero();
    let s = p.dot(along);
    let t = p.dot(down_slope);
    let row = (t / ROW_M).floor();
    let shifted = s + if (row as i64) % 2 == 0 {
        0.0
    } else {
        TILE_M * 0.5
    };
    let tile = (shifted / TILE_M).floor();
    let base = match palette % 3 {
        0 => srgb(140, 60, 45),
        1 => srgb(70, 70, 75),
        _ => srgb(110, 75, 60),
    };
    let variation = hash_unit(seed ^ 91, tile as i64, row as i64, 0) - 0.5;
    // Within a row the tile is shaded by its curvature and the lower edge of the row above
    // throws a dark line.
    let in_row = (t - row * ROW_M) / ROW_M;
    let in_tile = (shifted - tile * TILE_M) / TILE_M;
    let curvature = 0.85 + 0.3 * (in_tile * std::f32::consts::PI).sin();
    let overlap_shadow = if in_row < 0.12 { 0.45 } else { 1.0 };
    let detailed = base * (1.0 + 0.35 * variation) * curvature * overlap_shadow;
    let mean = base * 0.9;
    let moss = (fbm(seed ^ 92, p, 1.5, 4, footprint_m) - 0.15).max(0.0) * 2.0;
    let colour = mean.lerp(detailed, pattern_visibility(ROW_M * 0.5, footprint_m));
    colour.lerp(srgb(80, 85, 50), moss.min(0.6))
}

fn opening(seed: u64, panel: &Panel, p: Vec3, footprint_m: f32) -> SurfaceSample {
    let local = p - panel.origin_m;
    let a = local.dot(panel.u_axis);
    let b = local.dot(panel.v_axis);
    let frame_colour = match panel.style % 3 {
        0 => srgb(235, 235, 230),
        1 => srgb(60, 55, 50),
        _ => srgb(120, 80, 50),
    };
    match panel.kind {
        PanelKind::Window { columns, rows } => {
            const FRAME_M: f32 = 0.07;
            const MULLION_HALF_M: f32 = 0.03;
            let edge_distance = a.min(panel.width_m - a).min(b).min(panel.height_m - b);
            let pane_w = panel.width_m / f32::from(columns.max(1));
            let pane_h = panel.height_m / f32::from(rows.max(1));
            let column = (a / pane_w).floor().clamp(0.0, f32::from(columns) - 1.0);
            let row = (b / pane_h).floor().clamp(0.0, f32::from(rows) - 1.0);
            let mullion_distance = {
                let da = (a - (a / pane_w).round() * pane_w).abs();
                let db = (b - (b / pane_h).round() * pane_h).abs();
                da.min(db)
            };
            let frame = line_coverage(edge_distance, FRAME_M, footprint_m).max(line_coverage(
                mullion_distance,
                MULLION_HALF_M,
                footprint_m,
            ));
            // Behind the glass: dark interior, sometimes a light curtain in the upper part.
            let curtain_seed = hash_u64(seed ^ u64::from(panel.style) << 8);
            let has_curtain = hash_unit(curtain_seed, column as i64, row as i64, 1) < 0.4;
            let curtain_height = 0.5 + 0.5 * hash_unit(curtain_seed, column as i64, row as i64, 2);
            let interior = if has_curtain && b > panel.height_m * (1.0 - curtain_height * 0.6) {
                srgb(170, 165, 150) * (0.8 + 0.2 * value_noise(curtain_seed, p / 0.05))
            } else {
                srgb(18, 18, 20)
            };
            let glass = SurfaceSample {
                albedo: interior,
                mirror: 0.35,
            };
            SurfaceSample {
                albedo: glass.albedo.lerp(frame_colour, frame),
                mirror: glass.mirror * (1.0 - frame),
            }
        }
        PanelKind::Door => {
            let inset = (a - panel.width_m * 0.5).abs() < panel.width_m * 0.3
                && (b > 0.3 && b < panel.height_m - 0.3);
            let grain = fbm(
                seed ^ 101,
                p * Vec3::new(1.0, 1.0, 6.0),
                0.3,
                4,
                footprint_m,
            );
            let wood = srgb(100, 60, 35) * (1.0 + 0.5 * grain);
            let handle = (a - panel.width_m * 0.85).abs() < 0.03 && (b - 1.0).abs() < 0.08;
            let colour = if handle {
                srgb(200, 190, 150)
            } else if inset {
                wood * 0.8
            } else {
                wood
            };
            SurfaceSample {
                albedo: colour,
                mirror: 0.0,
            }
        }
        PanelKind::GarageDoor => {
            const SLAT_M: f32 = 0.5;
            let slat = b - (b / SLAT_M).floor() * SLAT_M;
            let groove =
                line_coverage(slat, 0.02, footprint_m) * pattern_visibility(SLAT_M, footprint_m);
            let dirt = fbm(seed ^ 111, p, 1.0, 3, footprint_m);
            SurfaceSample {
                albedo: frame_colour.lerp(srgb(200, 200, 195), 0.5)
                    * (1.0 - 0.6 * groove)
                    * (1.0 + 0.2 * dirt),
                mirror: 0.0,
            }
        }
    }
}

/// What covers the ground at a point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GroundKind {
    Asphalt,
    Concrete,
    Gravel,
    /// Everything not paved: grass with dirt patches.
    Grass,
}

/// What covers the ground at a world point (borders between kinds are noisy).
pub fn ground_kind(seed: u64, layout: &GroundLayout, p: Vec3, footprint_m: f32) -> GroundKind {
    let xy = Vec2::new(p.x, p.y);
    let border_jitter = 0.08 * fbm(seed ^ 121, p, 0.5, 2, footprint_m);
    let within = |segments: &[(Vec2, Vec2, f32)]| {
        segments
            .iter()
            .any(|&(a, b, half_width)| distance_to_segment(xy, a, b) < half_width + border_jitter)
    };
    if within(&layout.asphalt) {
        GroundKind::Asphalt
    } else if within(&layout.concrete) {
        GroundKind::Concrete
    } else if within(&layout.gravel) {
        GroundKind::Gravel
    } else {
        GroundKind::Grass
    }
}

/// The ground's albedo at a world point: asphalt, gravel, concrete or grass with dirt patches.
pub fn ground_albedo(seed: u64, layout: &GroundLayout, p: Vec3, footprint_m: f32) -> Vec3 {
    let kind = ground_kind(seed, layout, p, footprint_m);
    let large = fbm(seed ^ 122, p, 6.0, 3, footprint_m);
    if kind == GroundKind::Asphalt {
        let grain = fbm(seed ^ 123, p, 0.05, 3, footprint_m);
        let patches = fbm(seed ^ 124, p, 1.2, 3, footprint_m);
        return srgb(75, 75, 78) * (1.0 + 0.5 * large + 0.35 * grain + 0.4 * patches);
    }
    if kind == GroundKind::Concrete {
        // Square slabs with joints.
        const SLAB_M: f32 = 0.6;
        let ds = (p.x - (p.x / SLAB_M).round() * SLAB_M).abs();
        let dt = (p.y - (p.y / SLAB_M).round() * SLAB_M).abs();
        let joint =
            line_coverage(ds.min(dt), 0.01, footprint_m) * pattern_visibility(SLAB_M, footprint_m);
        let slab = hash_unit(
            seed ^ 125,
            (p.x / SLAB_M).floor() as i64,
            (p.y / SLAB_M).floor() as i64,
            0,
        ) - 0.5;
        return srgb(170, 168, 160) * (1.0 + 0.3 * large + 0.15 * slab) * (1.0 - 0.5 * joint);
    }
    if kind == GroundKind::Gravel {
        let stones = value_noise(seed ^ 126, p / 0.03) - 0.5;
        let visibility = pattern_visibility(0.03, footprint_m);
        return srgb(160, 150, 135) * (1.0 + 0.4 * large + 0.8 * visibility * stones);
    }
    let patches = fbm(seed ^ 127, p, 3.0, 4, footprint_m);
    let blades = value_noise(seed ^ 128, Vec3::new(p.x / 0.02, p.y / 0.02, 0.0)) - 0.5;
    let blade_visibility = pattern_visibility(0.02, footprint_m);
    let tufts = fbm(seed ^ 129, p, 0.25, 3, footprint_m);
    let green = srgb(90, 110, 58);
    let dry = srgb(150, 142, 100);
    let dirt = srgb(110, 90, 65);
    let dryness = (0.5 + 1.6 * patches).clamp(0.0, 1.0);
    let dirt_amount = ((large - 0.2) * 3.0).clamp(0.0, 0.7);
    green.lerp(dry, dryness * 0.6).lerp(dirt, dirt_amount)
        * (1.0 + 0.7 * large + 0.6 * tufts + 0.6 * blade_visibility * blades)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_deterministic_and_bounded() {
        let p = Vec3::new(1.3, -2.7, 0.4);
        assert_eq!(value_noise(5, p), value_noise(5, p));
        assert_ne!(value_noise(5, p), value_noise(6, p));
        for i in 0..1000 {
            let q = Vec3::new(i as f32 * 0.37, i as f32 * -0.11, i as f32 * 0.05);
            let v = value_noise(3, q);
            assert!((0.0..1.0).contains(&v), "{v}");
            assert!(fbm(3, q, 1.0, 4, 0.0).abs() <= 0.5);
        }
    }

    #[test]
    fn bricks_show_mortar_lines_up_close_and_average_out_far_away() {
        let ground = GroundLayout::default();
        let normal = Vec3::Y;
        let sample = |z: f32, footprint_m: f32| {
            evaluate(
                Material::Brick { palette: 0 },
                None,
                &ground,
                Vec3::new(0.1, 0.0, z),
                normal,
                footprint_m,
                1,
                0,
            )
            .albedo
        };
        // On a course boundary (z = 0.075) versus the middle of a brick.
        let on_mortar = sample(0.075, 0.001);
        let on_brick = sample(0.0375, 0.001);
        assert!((on_mortar - on_brick).length() > 0.05);
        let far_a = sample(0.075, 0.5);
        let far_b = sample(0.0375, 0.5);
        assert!((far_a - far_b).length() < 0.02);
    }
}
