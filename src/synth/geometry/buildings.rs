//! The two scenes' buildings and the ground they stand on: the paper's single house (gable roof,
//! chimney, dormer, garage, porch) and a town block of several buildings on a street grid.

use glam::{Vec2, Vec3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::primitives::{add_gable_building, add_hip_building, GableBuilding};
use super::{FaceTag, Footprint, Frame, PartKind, Scene, NO_PANEL};
use crate::synth::texture::{Material, PanelKind};

/// Adds rows of windows on the four walls of a box building.
#[allow(clippy::too_many_arguments)]
fn add_facade_windows(
    scene: &mut Scene,
    rng: &mut ChaCha8Rng,
    frame: Frame,
    half_x_m: f32,
    half_y_m: f32,
    storeys: u32,
    storey_height_m: f32,
    skip_front_centre: bool,
    style: u32,
) {
    let window_width = rng.random_range(1.0..1.4f32);
    let window_height = rng.random_range(1.2..1.5f32);
    let columns = if window_width > 1.2 { 2 } else { 1 };
    let kind = PanelKind::Window { columns, rows: 2 };
    for (outward, half_along, offset) in [
        (Vec2::new(0.0, -1.0), half_x_m, half_y_m),
        (Vec2::new(0.0, 1.0), half_x_m, half_y_m),
        (Vec2::new(1.0, 0.0), half_y_m, half_x_m),
        (Vec2::new(-1.0, 0.0), half_y_m, half_x_m),
    ] {
        let spacing = rng.random_range(2.4..3.2f32);
        let count = ((2.0 * half_along - 1.0) / spacing).floor().max(1.0) as i32;
        for storey in 0..storeys {
            let bottom = storey as f32 * storey_height_m + 0.9;
            for i in 0..count {
                let along = (i as f32 - (count - 1) as f32 * 0.5) * spacing;
                let is_front = outward.y < -0.5;
                if skip_front_centre && is_front && storey == 0 && along.abs() < spacing * 0.6 {
                    continue;
                }
                scene.add_opening(
                    frame,
                    outward,
                    offset,
                    along,
                    bottom,
                    window_width,
                    window_height,
                    kind,
                    style,
                );
            }
        }
    }
}

/// The single free-standing house of the paper's experiment (≈ 10 × 8 m, gable roof with
/// overhang, chimney, dormer, garage annex, porch with posts and railing).
pub fn build_house(rng: &mut ChaCha8Rng) -> Scene {
    let mut scene = Scene {
        ground_patch_half_m: 16.0,
        ..Scene::default()
    };
    let yaw = rng.random_range(-0.3..0.3f32);
    let frame = Frame {
        centre_m: Vec2::ZERO,
        yaw_rad: yaw,
        base_z_m: 0.0,
    };
    let half_x = rng.random_range(4.6..5.4f32);
    let half_y = rng.random_range(3.7..4.3f32);
    let wall_height = rng.random_range(5.4..6.0f32);
    let rise = rng.random_range(2.8..3.6f32);
    let brick_palette = rng.random_range(0..3u8);
    let plaster_palette = rng.random_range(0..4u8);
    let roof_palette = rng.random_range(0..3u8);
    let main_wall = if rng.random_bool(0.5) {
        Material::Brick {
            palette: brick_palette,
        }
    } else {
        Material::Plaster {
            palette: plaster_palette,
        }
    };
    let roof = Material::RoofTile {
        palette: roof_palette,
    };
    add_gable_building(
        &mut scene,
        &GableBuilding {
            frame,
            half_x_m: half_x,
            half_y_m: half_y,
            wall_height_m: wall_height,
            roof_rise_m: rise,
            eave_overhang_m: 0.55,
            gable_overhang_m: 0.35,
            roof_thickness_m: 0.3,
            wall_material: main_wall,
            roof_material: roof,
        },
    );
    scene.footprints.push(Footprint {
        frame,
        half_x_m: half_x,
        half_y_m: half_y,
        height_m: wall_height + rise,
    });
    let style = rng.random_range(0..3u32);
    add_facade_windows(
        &mut scene,
        rng,
        frame,
        half_x,
        half_y,
        2,
        wall_height * 0.5,
        true,
        style,
    );
    // Attic windows in the gables.
    for outward in [Vec2::new(1.0, 0.0), Vec2::new(-1.0, 0.0)] {
        scene.add_opening(
            frame,
            outward,
            half_x,
            0.0,
            wall_height + 0.4,
            0.9,
            1.0,
            PanelKind::Window {
                columns: 1,
                rows: 1,
            },
            style,
        );
    }
    // Front door (front = local -y).
    scene.add_opening(
        frame,
        Vec2::new(0.0, -1.0),
        half_y,
        0.0,
        0.0,
        1.05,
        2.15,
        PanelKind::Door,
        style,
    );

    // Garage annex on the +x side: lower gable roof with its ridge along local y.
    let annex_half_x = rng.random_range(1.8..2.3f32);
    let annex_half_y = rng.random_range(2.8..3.3f32);
    let annex_centre_local = Vec3::new(half_x + annex_half_x, -half_y + annex_half_y + 0.2, 0.0);
    let annex_centre = frame.to_world(annex_centre_local);
    let annex_frame = Frame {
        centre_m: Vec2::new(annex_centre.x, annex_centre.y),
        yaw_rad: yaw + std::f32::consts::FRAC_PI_2,
        base_z_m: 0.0,
    };
    let annex_wall = Material::Plaster {
        palette: (plaster_palette + 1) % 4,
    };
    add_gable_building(
        &mut scene,
        &GableBuilding {
            frame: annex_frame,
            // Ridge along the annex frame's x = the house's y.
            half_x_m: annex_half_y,
            half_y_m: annex_half_x,
            wall_height_m: 2.9,
            roof_rise_m: 1.3,
            eave_overhang_m: 0.35,
            gable_overhang_m: 0.25,
            roof_thickness_m: 0.3,
            wall_material: annex_wall,
            roof_material: roof,
        },
    );
    scene.footprints.push(Footprint {
        frame: annex_frame,
        half_x_m: annex_half_y,
        half_y_m: annex_half_x,
        height_m: 4.2,
    });
    // Garage door on the annex's front (house -y = annex frame -x).
    scene.add_opening(
        annex_frame,
        Vec2::new(-1.0, 0.0),
        annex_half_y,
        0.0,
        0.0,
        2.6,
        2.2,
        PanelKind::GarageDoor,
        style,
    );
    scene.add_opening(
        annex_frame,
        Vec2::new(0.0, 1.0),
        annex_half_x,
        0.0,
        1.0,
        0.9,
        0.9,
        PanelKind::Window {
            columns: 1,
            rows: 1,
        },
        style,
    );

    // Chimney: through the roof near one gable, on the back slope.
    let detail_id = scene.new_object();
    let chimney_x = -half_x * 0.55;
    let chimney_y = half_y * 0.35;
    let ridge_z = wall_height + rise;
    let chimney_top = ridge_z + 0.9;
    let chimney_min = Vec3::new(chimney_x - 0.3, chimney_y - 0.3, wall_height);
    let chimney_max = Vec3::new(chimney_x + 0.3, chimney_y + 0.3, chimney_top);
    scene.add_box(
        frame,
        chimney_min,
        chimney_max,
        Material::Brick {
            palette: (brick_palette + 2) % 3,
        },
        Material::Concrete,
        PartKind::Detail,
        detail_id,
    );
    let roof_z_at_chimney = ridge_z - (chimney_y - 0.3) / half_y * rise;
    {
        let a = frame.to_world(Vec3::new(
            chimney_x - 0.3,
            chimney_y - 0.3,
            roof_z_at_chimney,
        ));
        let b = frame.to_world(Vec3::new(chimney_x + 0.3, chimney_y + 0.3, chimney_top));
        scene.chimney_bounds_m = Some((a.min(b).with_z(roof_z_at_chimney + 0.35), a.max(b)));
    }

    // Dormer on the front slope: a box with a small gable roof and a window.
    let dormer_half = 0.8;
    let dormer_y = -half_y * 0.45;
    let dormer_floor = ridge_z - (half_y * 0.45 + 0.9) / half_y * rise;
    let dormer_top = dormer_floor + 1.5;
    let dormer_x = half_x * 0.35;
    scene.add_box(
        frame,
        Vec3::new(dormer_x - dormer_half, dormer_y - 0.9, dormer_floor),
        Vec3::new(dormer_x + dormer_half, dormer_y + 1.0, dormer_top),
        main_wall,
        main_wall,
        PartKind::Detail,
        detail_id,
    );
    let dormer_frame = Frame {
        centre_m: {
            let c = frame.to_world(Vec3::new(dormer_x, dormer_y, 0.0));
            Vec2::new(c.x, c.y)
        },
        yaw_rad: yaw + std::f32::consts::FRAC_PI_2,
        base_z_m: 0.0,
    };
    for side in [-1.0f32, 1.0] {
        let mut polygon = vec![
            Vec2::new(0.0, dormer_top + 0.6),
            Vec2::new(side * (dormer_half + 0.2), dormer_top - 0.1),
            Vec2::new(side * (dormer_half + 0.2), dormer_top + 0.05),
            Vec2::new(0.0, dormer_top + 0.75),
        ];
        let area: f32 = (0..4)
            .map(|i| polygon[i].perp_dot(polygon[(i + 1) % 4]))
            .sum();
        if area < 0.0 {
            polygon.reverse();
        }
        scene.add_prism(
            dormer_frame,
            &polygon,
            1.0,
            &[roof],
            Material::Soffit,
            PartKind::Detail,
            detail_id,
        );
    }
    scene.add_opening(
        frame,
        Vec2::new(0.0, -1.0),
        -dormer_y + 0.9,
        dormer_x,
        dormer_floor + 0.3,
        0.9,
        0.9,
        PanelKind::Window {
            columns: 1,
            rows: 2,
        },
        style,
    );

    // Porch in front of the door: slab, two posts, a thin roof, a railing.
    let porch_depth = 1.6;
    let porch_half_w = 1.4;
    scene.add_box(
        frame,
        Vec3::new(-porch_half_w, -half_y - porch_depth, 0.0),
        Vec3::new(porch_half_w, -half_y, 0.18),
        Material::Concrete,
        Material::Concrete,
        PartKind::Detail,
        detail_id,
    );
    for px in [-porch_half_w + 0.1, porch_half_w - 0.1] {
        scene.add_box(
            frame,
            Vec3::new(px - 0.07, -half_y - porch_depth + 0.03, 0.18),
            Vec3::new(px + 0.07, -half_y - porch_depth + 0.17, 2.55),
            Material::Soffit,
            Material::Soffit,
            PartKind::Detail,
            detail_id,
        );
    }
    scene.add_box(
        frame,
        Vec3::new(-porch_half_w - 0.1, -half_y - porch_depth - 0.1, 2.55),
        Vec3::new(porch_half_w + 0.1, -half_y, 2.67),
        Material::Soffit,
        roof,
        PartKind::Detail,
        detail_id,
    );
    for side in [-1.0f32, 1.0] {
        let x = side * (porch_half_w - 0.1);
        scene.add_box(
            frame,
            Vec3::new(x.min(x - side * 0.04), -half_y - porch_depth + 0.05, 0.9),
            Vec3::new(x.max(x - side * 0.04), -half_y - 0.05, 0.96),
            Material::Soffit,
            Material::Soffit,
            PartKind::Detail,
            detail_id,
        );
        for k in 0..6 {
            let y = -half_y - porch_depth + 0.1 + k as f32 * (porch_depth - 0.2) / 5.0;
            scene.add_box(
                frame,
                Vec3::new(x - 0.02, y - 0.02, 0.18),
                Vec3::new(x + 0.02, y + 0.02, 0.9),
                Material::Soffit,
                Material::Soffit,
                PartKind::Detail,
                detail_id,
            );
        }
    }

    // Ground: road in front, driveway to the garage, gravel path to the door, patio at the back.
    let road_y = -half_y - rng.random_range(9.0..12.0f32);
    let to_xy = |local: Vec3| {
        let w = frame.to_world(local);
        Vec2::new(w.x, w.y)
    };
    scene.ground.asphalt.push((
        to_xy(Vec3::new(-200.0, road_y, 0.0)),
        to_xy(Vec3::new(200.0, road_y, 0.0)),
        3.2,
    ));
    scene.ground.asphalt.push((
        to_xy(annex_centre_local - Vec3::new(0.0, annex_half_y, 0.0)),
        to_xy(Vec3::new(annex_centre_local.x, road_y, 0.0)),
        1.6,
    ));
    scene.ground.gravel.push((
        to_xy(Vec3::new(0.0, -half_y - porch_depth, 0.0)),
        to_xy(Vec3::new(0.0, road_y, 0.0)),
        0.6,
    ));
    scene.ground.concrete.push((
        to_xy(Vec3::new(-half_x * 0.5, half_y + 1.5, 0.0)),
        to_xy(Vec3::new(half_x * 0.3, half_y + 1.5, 0.0)),
        1.5,
    ));
    scene.ground.concrete.push((
        to_xy(Vec3::new(-100.0, road_y - 4.2, 0.0)),
        to_xy(Vec3::new(100.0, road_y - 4.2, 0.0)),
        0.9,
    ));
    add_ground(&mut scene);
    scene
}

/// A block of several buildings (flat, gable and hip roofs) on a street grid.
pub fn build_block(rng: &mut ChaCha8Rng) -> Scene {
    let mut scene = Scene {
        ground_patch_half_m: 45.0,
        ..Scene::default()
    };
    const SPACING_M: f32 = 26.0;
    for gx in -1..=1 {
        for gy in -1..=1 {
            if rng.random_bool(0.15) && (gx, gy) != (0, 0) {
                continue;
            }
            let centre = Vec2::new(gx as f32 * SPACING_M, gy as f32 * SPACING_M)
                + Vec2::new(rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0));
            let frame = Frame {
                centre_m: centre,
                yaw_rad: rng.random_range(-0.15..0.15),
                base_z_m: 0.0,
            };
            let half_x = rng.random_range(5.0..9.0f32);
            let half_y = rng.random_range(4.0..7.0f32);
            let storeys = rng.random_range(2..6u32);
            let storey_height = 3.0;
            let wall_height = storeys as f32 * storey_height;
            let wall_material = if rng.random_bool(0.5) {
                Material::Brick {
                    palette: rng.random_range(0..3),
                }
            } else {
                Material::Plaster {
                    palette: rng.random_range(0..4),
                }
            };
            let roof_material = Material::RoofTile {
                palette: rng.random_range(0..3),
            };
            let roof_kind = rng.random_range(0..3u32);
            let object_id = scene.new_object();
            let height_m = match roof_kind {
                0 => {
                    // Flat roof with a parapet (the parapet is a detail).
                    scene.add_box(
                        frame,
                        Vec3::new(-half_x, -half_y, 0.0),
                        Vec3::new(half_x, half_y, wall_height),
                        wall_material,
                        Material::FlatRoof,
                        PartKind::Building,
                        object_id,
                    );
                    for (min, max) in [
                        (
                            Vec3::new(-half_x, -half_y, wall_height),
                            Vec3::new(half_x, -half_y + 0.25, wall_height + 0.6),
                        ),
                        (
                            Vec3::new(-half_x, half_y - 0.25, wall_height),
                            Vec3::new(half_x, half_y, wall_height + 0.6),
                        ),
                        (
                            Vec3::new(-half_x, -half_y + 0.25, wall_height),
                            Vec3::new(-half_x + 0.25, half_y - 0.25, wall_height + 0.6),
                        ),
                        (
                            Vec3::new(half_x - 0.25, -half_y + 0.25, wall_height),
                            Vec3::new(half_x, half_y - 0.25, wall_height + 0.6),
                        ),
                    ] {
                        scene.add_box(
                            frame,
                            min,
                            max,
                            wall_material,
                            Material::Concrete,
                            PartKind::Detail,
                            object_id,
                        );
                    }
                    // A roof structure (lift housing / AC unit): a detail.
                    scene.add_box(
                        frame,
                        Vec3::new(-1.2, -1.0, wall_height),
                        Vec3::new(1.2, 1.0, wall_height + 1.8),
                        Material::Concrete,
                        Material::Concrete,
                        PartKind::Detail,
                        object_id,
                    );
                    wall_height + 1.8
                }
                1 => {
                    let rise = half_y * rng.random_range(0.5..0.9);
                    add_gable_building(
                        &mut scene,
                        &GableBuilding {
                            frame,
                            half_x_m: half_x,
                            half_y_m: half_y,
                            wall_height_m: wall_height,
                            roof_rise_m: rise,
                            eave_overhang_m: 0.5,
                            gable_overhang_m: 0.3,
                            roof_thickness_m: 0.3,
                            wall_material,
                            roof_material,
                        },
                    );
                    wall_height + rise
                }
                _ => {
                    let rise_per_m = rng.random_range(0.5..0.8f32);
                    add_hip_building(
                        &mut scene,
                        frame,
                        half_x,
                        half_y,
                        wall_height,
                        rise_per_m,
                        0.5,
                        wall_material,
                        roof_material,
                    );
                    wall_height + rise_per_m * half_y
                }
            };
            scene.footprints.push(Footprint {
                frame,
                half_x_m: half_x,
                half_y_m: half_y,
                height_m,
            });
            let style = rng.random_range(0..3u32);
            add_facade_windows(
                &mut scene,
                rng,
                frame,
                half_x,
                half_y,
                storeys,
                storey_height,
                true,
                style,
            );
            scene.add_opening(
                frame,
                Vec2::new(0.0, -1.0),
                half_y,
                0.0,
                0.0,
                1.4,
                2.3,
                PanelKind::Door,
                style,
            );
        }
    }
    // Streets between the blocks, pavements along them.
    for k in [-1.5f32, -0.5, 0.5, 1.5] {
        let c = k * SPACING_M;
        scene
            .ground
            .asphalt
            .push((Vec2::new(-300.0, c), Vec2::new(300.0, c), 3.5));
        scene
            .ground
            .asphalt
            .push((Vec2::new(c, -300.0), Vec2::new(c, 300.0), 3.5));
        for side in [-1.0f32, 1.0] {
            scene.ground.concrete.push((
                Vec2::new(-300.0, c + side * 4.5),
                Vec2::new(300.0, c + side * 4.5),
                1.0,
            ));
            scene.ground.concrete.push((
                Vec2::new(c + side * 4.5, -300.0),
                Vec2::new(c + side * 4.5, 300.0),
                1.0,
            ));
        }
    }
    add_ground(&mut scene);
    scene
}

/// The ground plane: the model's square patch, and four quads out to the horizon.
fn add_ground(scene: &mut Scene) {
    let object_id = scene.new_object();
    let h = scene.ground_patch_half_m;
    let far = 3000.0;
    let tag = |part| FaceTag {
        material: Material::Ground,
        object_id,
        panel: NO_PANEL,
        part,
    };
    let up = Some(Vec3::Z);
    // The patch, split into 2 m cells so the model's trimmed ground stays local.
    let cells = (2.0 * h / 2.0).ceil() as i32;
    let cell = 2.0 * h / cells as f32;
    let quad = |x0: f32, y0: f32, x1: f32, y1: f32| {
        [
            Vec3::new(x0, y0, 0.0),
            Vec3::new(x1, y0, 0.0),
            Vec3::new(x1, y1, 0.0),
            Vec3::new(x0, y1, 0.0),
        ]
    };
    for i in 0..cells {
        for j in 0..cells {
            let x0 = -h + i as f32 * cell;
            let y0 = -h + j as f32 * cell;
            scene.add_polygon(
                &quad(x0, y0, x0 + cell, y0 + cell),
                tag(PartKind::NearGround),
                up,
            );
        }
    }
    // Around it, 10 m cells out to 250 m (huge triangles lose depth precision in the
    // rasteriser, which shows as stripes in the shadow test), then four quads to the horizon.
    const RING_CELL_M: f32 = 10.0;
    const RING_CELLS: i32 = 25;
    let mut lines: Vec<f32> = (0..=RING_CELLS)
        .rev()
        .map(|k| -h - k as f32 * RING_CELL_M)
        .collect();
    lines.extend((0..=RING_CELLS).map(|k| h + k as f32 * RING_CELL_M));
    for i in 0..lines.len() - 1 {
        for j in 0..lines.len() - 1 {
            let (x0, x1, y0, y1) = (lines[i], lines[i + 1], lines[j], lines[j + 1]);
            if x0 >= -h && x1 <= h && y0 >= -h && y1 <= h {
                continue;
            }
            scene.add_polygon(&quad(x0, y0, x1, y1), tag(PartKind::FarGround), up);
        }
    }
    let r = h + RING_CELLS as f32 * RING_CELL_M;
    for corners in [
        quad(-far, -far, far, -r),
        quad(-far, r, far, far),
        quad(-far, -r, -r, r),
        quad(r, -r, far, r),
    ] {
        scene.add_polygon(&corners, tag(PartKind::FarGround), up);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn house_has_building_details_ground_and_solids() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let scene = build_house(&mut rng);
        let count = |kind: PartKind| scene.tags.iter().filter(|t| t.part == kind).count();
        assert!(count(PartKind::Building) > 20);
        assert!(count(PartKind::Detail) > 50);
        assert!(count(PartKind::NearGround) > 0 && count(PartKind::FarGround) > 0);
        assert!(scene.building_solids.len() >= 6);
        // The middle of the house is inside, a point far above it is not.
        assert!(scene
            .building_solids
            .iter()
            .any(|s| s.contains(Vec3::new(0.0, 0.0, 2.0))));
        assert!(!scene
            .building_solids
            .iter()
            .any(|s| s.contains(Vec3::new(0.0, 0.0, 30.0))));
        let (min, max) = scene.chimney_bounds_m.unwrap();
        let top = (min + max) * 0.5;
        assert!(scene.detail_solids.iter().any(|s| s.contains(top)));
        assert!(!scene.building_solids.iter().any(|s| s.contains(top)));
    }
}
