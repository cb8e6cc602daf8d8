//! A city-size mesh for the memory and speed measurements of issue #16 (`asgreg bench mesh`): a
//! square grid of lots, each a flat ground quad and a box building (four walls and a roof, each
//! split into 4×4 quads, so triangles are as dense as a photogrammetric mesh's), heights from a
//! hash of the lot. It is written straight to a binary little-endian PLY in georeferenced
//! coordinates (UTM-like, [`CITY_ORIGIN_M`]) without ever being held in memory, so a 10^7-triangle
//! city is made in bounded memory like the one it is meant to test.
//!
//! [`generate_city_scene`] (`asgreg synth --scene city`) makes a whole scene folder of it, laid out
//! like the other synthetic scenes (`model.ply`, `images/`, `depth/`, `gt/`, `initial/<level>/`,
//! `scene.json`) so that `register` and `eval` run on a city-size mesh end to end. Its photos are
//! aerial obliques shaded from the mesh itself with procedural materials that the mesh does not
//! have (roads and lawns, windows, roof fixtures, per-building colours), sun and sky light, sensor
//! noise and JPEG; unlike the house and block scenes the model is the true geometry (no
//! degradation, no cast shadows, no clutter): the scene tests scale, not robustness.

use std::io::Write as _;
use std::path::Path;
use std::time::Instant;

use glam::Vec3;
use nalgebra::Vector3;
use rand::{Rng as _, SeedableRng as _};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution as _, StandardNormal};
use serde::{Deserialize, Serialize};

use super::initial::{self, LevelCalibration};
use super::texture::{fbm, hash_unit};
use super::{io_error, write_colmap, write_initial_poses, write_jpeg, SynthError};
use crate::core::camera::{Camera, PinholeIntrinsics};
use crate::core::image::Image;
use crate::core::mesh::Mesh;
use crate::core::raster::{Rasterizer, RenderBuffers, RenderOptions, NO_FACE};
use crate::core::rigid::Rigid3;
use crate::io::mesh_file::MeshIoError;

/// Where the city lies: easting, northing, height of its south-west corner (m), a UTM zone 30U
/// position (Brighton), so f32 alone could not keep its millimetres.
pub const CITY_ORIGIN_M: [f64; 3] = [699_000.0, 5_633_000.0, 0.0];
/// Side of one lot, m.
pub const LOT_M: f64 = 30.0;
/// Quads along each side of a wall or roof.
const SPLITS: usize = 4;
/// Triangles of one lot: 2 for the ground, 5 faces of `SPLITS`² quads for the building.
pub const TRIANGLES_PER_LOT: u64 = 2 + 5 * 2 * (SPLITS * SPLITS) as u64;
const VERTICES_PER_LOT: u64 = 4 + 5 * ((SPLITS + 1) * (SPLITS + 1)) as u64;

/// What [`write_city_ply`] wrote.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CityMesh {
    /// Lots per side.
    pub lots_per_side: usize,
    pub triangles: u64,
    pub vertices: u64,
    /// Side of the city, m.
    pub side_m: f64,
}

impl CityMesh {
    /// The city's layout for about `target_triangles` triangles (at least one lot).
    pub fn for_triangles(target_triangles: u64) -> Self {
        let lots = (target_triangles as f64 / TRIANGLES_PER_LOT as f64)
            .sqrt()
            .round()
            .max(1.0) as usize;
        let lot_count = (lots * lots) as u64;
        Self {
            lots_per_side: lots,
            triangles: lot_count * TRIANGLES_PER_LOT,
            vertices: lot_count * VERTICES_PER_LOT,
            side_m: lots as f64 * LOT_M,
        }
    }

    /// Height of the building on lot (`col`, `row`), m (8..60 m, from a hash of the lot).
    pub fn building_height_m(col: usize, row: usize) -> f64 {
        let mut h = (col as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (row as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        h ^= h >> 29;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 32;
        8.0 + (h % 5200) as f64 / 100.0
    }
}

/// The building box of a lot: min and max corners in world coordinates.
fn building_box(col: usize, row: usize) -> ([f64; 3], [f64; 3]) {
    let x0 = CITY_ORIGIN_M[0] + col as f64 * LOT_M + 5.0;
    let y0 = CITY_ORIGIN_M[1] + row as f64 * LOT_M + 5.0;
    let z1 = CITY_ORIGIN_M[2] + CityMesh::building_height_m(col, row);
    ([x0, y0, CITY_ORIGIN_M[2]], [x0 + 20.0, y0 + 20.0, z1])
}

/// The five faces of a box (walls and roof) as (corner, edge u, edge v), outward by right hand.
fn box_faces(min: [f64; 3], max: [f64; 3]) -> [([f64; 3], [f64; 3], [f64; 3]); 5] {
    let (dx, dy, dz) = (max[0] - min[0], max[1] - min[1], max[2] - min[2]);
    [
        // South wall (y = min), normal -y.
        (min, [dx, 0.0, 0.0], [0.0, 0.0, dz]),
        // North wall (y = max), normal +y.
        ([max[0], max[1], min[2]], [-dx, 0.0, 0.0], [0.0, 0.0, dz]),
        // West wall (x = min), normal -x.
        ([min[0], max[1], min[2]], [0.0, -dy, 0.0], [0.0, 0.0, dz]),
        // East wall (x = max), normal +x.
        ([max[0], min[1], min[2]], [0.0, dy, 0.0], [0.0, 0.0, dz]),
        // Roof (z = max), normal +z.
        ([min[0], min[1], max[2]], [dx, 0.0, 0.0], [0.0, dy, 0.0]),
    ]
}

/// Writes the city of about `target_triangles` triangles as a binary PLY (`double x y z`,
/// `list uchar int vertex_indices`) at `path`, streamed lot by lot.
pub fn write_city_ply(path: &Path, target_triangles: u64) -> Result<CityMesh, MeshIoError> {
    let city = CityMesh::for_triangles(target_triangles);
    let write_error = |source| MeshIoError::Write {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::create(path).map_err(write_error)?;
    let mut out = std::io::BufWriter::with_capacity(1 << 20, file);
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment asgreg synthetic city, {} x {} lots of {LOT_M} m, UTM-like origin {:?}\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        city.lots_per_side, city.lots_per_side, CITY_ORIGIN_M, city.vertices, city.triangles
    )
    .map_err(write_error)?;
    let lots = city.lots_per_side;
    let mut buffer: Vec<u8> = Vec::with_capacity(VERTICES_PER_LOT as usize * 24);
    for row in 0..lots {
        for col in 0..lots {
            buffer.clear();
            let mut push = |p: [f64; 3]| {
                for c in p {
                    buffer.extend_from_slice(&c.to_le_bytes());
                }
            };
            let gx = CITY_ORIGIN_M[0] + col as f64 * LOT_M;
            let gy = CITY_ORIGIN_M[1] + row as f64 * LOT_M;
            let gz = CITY_ORIGIN_M[2];
            for (dx, dy) in [(0.0, 0.0), (LOT_M, 0.0), (LOT_M, LOT_M), (0.0, LOT_M)] {
                push([gx + dx, gy + dy, gz]);
            }
            let (min, max) = building_box(col, row);
            for (corner, u, v) in box_faces(min, max) {
                for j in 0..=SPLITS {
                    for i in 0..=SPLITS {
                        let (s, t) = (i as f64 / SPLITS as f64, j as f64 / SPLITS as f64);
                        push(std::array::from_fn(|k| corner[k] + s * u[k] + t * v[k]));
                    }
                }
            }
            out.write_all(&buffer).map_err(write_error)?;
        }
    }
    let face = |out: &mut std::io::BufWriter<std::fs::File>, a: u64, b: u64, c: u64| {
        let mut record = [3u8; 13];
        for (k, v) in [a, b, c].into_iter().enumerate() {
            record[1 + 4 * k..5 + 4 * k].copy_from_slice(&(v as i32).to_le_bytes());
        }
        out.write_all(&record)
    };
    for lot in 0..(lots * lots) as u64 {
        let base = lot * VERTICES_PER_LOT;
        face(&mut out, base, base + 1, base + 2).map_err(write_error)?;
        face(&mut out, base, base + 2, base + 3).map_err(write_error)?;
        for box_face in 0..5u64 {
            let start = base + 4 + box_face * ((SPLITS + 1) * (SPLITS + 1)) as u64;
            let stride = (SPLITS + 1) as u64;
            for j in 0..SPLITS as u64 {
                for i in 0..SPLITS as u64 {
                    let a = start + j * stride + i;
                    let (b, c, d) = (a + 1, a + stride + 1, a + stride);
                    face(&mut out, a, b, c).map_err(write_error)?;
                    face(&mut out, a, c, d).map_err(write_error)?;
                }
            }
        }
    }
    out.flush().map_err(write_error)?;
    Ok(city)
}

/// What shapes a synthetic city scene; same config → same files (except timings).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CityConfig {
    pub seed: u64,
    /// Triangles of the city mesh aimed at ([`CityMesh::for_triangles`]).
    pub triangles: u64,
    pub width_px: u32,
    pub height_px: u32,
    pub image_count: usize,
    /// Horizontal field of view of the PINHOLE camera, degrees.
    pub horizontal_fov_deg: f64,
    /// Target mean δ(P_in, P_gt) of each initial-pose level, pixels.
    pub initial_levels_px: Vec<f64>,
    /// Also write the drone-like `initial/heading/` level.
    pub heading_level: bool,
    /// Rendered samples per pixel along each axis (antialiasing by box downsampling).
    pub supersampling: u32,
    /// Sensor noise at mid-grey, 8-bit digital numbers.
    pub noise_sigma_dn: f32,
    pub jpeg_quality: u8,
    /// Multiplicative depth noise (standard deviation, relative).
    pub depth_relative_noise: f32,
}

impl Default for CityConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            triangles: 1_000_000,
            width_px: 505,
            height_px: 275,
            image_count: 8,
            horizontal_fov_deg: 60.0,
            initial_levels_px: vec![30.0],
            heading_level: true,
            supersampling: 2,
            noise_sigma_dn: 2.0,
            jpeg_quality: 90,
            depth_relative_noise: 0.003,
        }
    }
}

impl CityConfig {
    fn validate(&self) -> Result<(), SynthError> {
        let invalid = |message: String| Err(SynthError::InvalidConfig(message));
        if self.width_px < 16 || self.height_px < 16 {
            return invalid(format!(
                "image size {}×{} px is below 16×16",
                self.width_px, self.height_px
            ));
        }
        if self.image_count == 0 || self.triangles == 0 {
            return invalid("a city needs at least one image and one triangle".into());
        }
        if self.triangles > i32::MAX as u64 / 2 {
            return invalid(format!(
                "{} triangles: binary PLY indices are i32; at most {}",
                self.triangles,
                i32::MAX / 2
            ));
        }
        if !(self.horizontal_fov_deg > 5.0 && self.horizontal_fov_deg < 150.0) {
            return invalid(format!(
                "horizontal_fov_deg {} is outside (5, 150)",
                self.horizontal_fov_deg
            ));
        }
        if !(1..=4).contains(&self.supersampling) || !(1..=100).contains(&self.jpeg_quality) {
            return invalid("supersampling must be 1..=4 and jpeg_quality 1..=100".into());
        }
        if self
            .initial_levels_px
            .iter()
            .any(|l| !(l.is_finite() && *l > 0.0))
        {
            return invalid(format!(
                "initial_levels_px must be positive: {:?}",
                self.initial_levels_px
            ));
        }
        Ok(())
    }

    fn camera(&self) -> Camera {
        let focal =
            f64::from(self.width_px) * 0.5 / (self.horizontal_fov_deg.to_radians() * 0.5).tan();
        Camera::pinhole(
            self.width_px,
            self.height_px,
            PinholeIntrinsics::centered(focal, self.width_px, self.height_px),
        )
    }
}

/// One photo of a city scene.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct CityImage {
    pub name: String,
    pub camera_centre_m: [f64; 3],
    /// Fraction of the pixels showing the city (the rest is sky or beyond its edge).
    pub surface_fraction: f64,
}

/// Seconds spent per stage of [`generate_city_scene`].
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct CityTimings {
    pub mesh_write_s: f64,
    pub mesh_load_s: f64,
    pub photos_s: f64,
    pub initial_s: f64,
    pub total_s: f64,
}

/// What [`generate_city_scene`] wrote: the content of `scene.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CitySceneSummary {
    /// "city" (the house and block scenes write a `SceneSummary`).
    pub scene: String,
    pub config: CityConfig,
    pub lots_per_side: usize,
    pub side_m: f64,
    pub origin_m: [f64; 3],
    pub model_vertices: u64,
    pub model_faces: u64,
    pub camera_fx_px: f64,
    pub images: Vec<CityImage>,
    pub initial_levels: Vec<LevelCalibration>,
    #[serde(default)]
    pub heading_level_px: Option<[f64; 3]>,
    pub timings: CityTimings,
}

/// An aerial oblique view of the city: a ground point inside it seen from 120–180 m up and
/// 180–240 m away horizontally, heading anywhere.
fn city_viewpoint(side_m: f64, rng: &mut ChaCha8Rng) -> Option<Rigid3> {
    let target = Vector3::new(
        CITY_ORIGIN_M[0] + side_m * rng.random_range(0.2..0.8),
        CITY_ORIGIN_M[1] + side_m * rng.random_range(0.2..0.8),
        CITY_ORIGIN_M[2],
    );
    let heading = rng.random_range(0.0..std::f64::consts::TAU);
    let distance_m = rng.random_range(180.0..240.0);
    let height_m = rng.random_range(120.0..180.0);
    let eye = target
        + Vector3::new(
            -distance_m * heading.cos(),
            -distance_m * heading.sin(),
            height_m,
        );
    Rigid3::look_at(&eye, &target, &Vector3::new(0.0, 0.0, 1.0))
}

/// Linear-light albedo of the city's surface at `p` (metres from [`CITY_ORIGIN_M`]) with world
/// normal `n`: materials the mesh does not model, so the photo's gradients are not the mesh's.
fn city_albedo(p: Vec3, n: Vec3, seed: u64) -> Vec3 {
    let lot = LOT_M as f32;
    let (col, row) = ((p.x / lot).floor(), (p.y / lot).floor());
    let (lx, ly) = (p.x - col * lot, p.y - row * lot);
    let lot_hash = |k: i64| hash_unit(seed, col as i64, row as i64, k);
    let grain = 1.0 + 0.4 * fbm(seed ^ 7, p, 2.0, 3, 0.1);
    if n.z > 0.9 && p.z < 0.5 {
        // Ground: a road along two sides of each lot (lane dashes), a lawn or paving inside.
        let road = lx < 4.0 || ly < 4.0;
        if road {
            let dash = (lx < 4.0 && (1.8..2.2).contains(&lx) && (ly % 6.0) < 3.0)
                || (ly < 4.0 && (1.8..2.2).contains(&ly) && (lx % 6.0) < 3.0);
            return if dash {
                Vec3::splat(0.7)
            } else {
                Vec3::splat(0.09) * grain
            };
        }
        return if lot_hash(1) < 0.6 {
            Vec3::new(0.12, 0.2, 0.07) * grain
        } else {
            Vec3::new(0.32, 0.3, 0.27) * grain
        };
    }
    if n.z > 0.9 {
        // Roof: one colour per building, a fixture (a dark square the model lacks) on some.
        let base = Vec3::new(0.25, 0.22, 0.2)
            + Vec3::new(0.25, 0.2, 0.15) * lot_hash(2)
            + Vec3::splat(0.1 * lot_hash(3));
        let (fx, fy) = (9.0 + 8.0 * lot_hash(4), 9.0 + 8.0 * lot_hash(5));
        if lot_hash(6) < 0.5 && (fx..fx + 3.0).contains(&lx) && (fy..fy + 3.0).contains(&ly) {
            return Vec3::splat(0.06);
        }
        return base * grain;
    }
    // Walls: a facade colour per building and a grid of windows, 3.2 m floors.
    let along = if n.x.abs() > n.y.abs() { ly } else { lx };
    let floor_z = p.z % 3.2;
    let window = (1.0..2.6).contains(&floor_z) && (along % 3.0) > 0.8 && (along % 3.0) < 2.2;
    if window {
        return Vec3::new(0.05, 0.07, 0.1);
    }
    (Vec3::new(0.35, 0.32, 0.28) + Vec3::new(0.3, 0.2, 0.15) * lot_hash(7)) * grain
}

/// Renders one photo (8-bit sRGB) of `mesh` from `pose`, `config.supersampling`² samples per
/// pixel, and the true depth map at the photo's size; also the fraction of pixels showing the city.
fn city_photo(
    mesh: &Mesh,
    camera: &Camera,
    pose: &Rigid3,
    config: &CityConfig,
    image_seed: u64,
    rasterizer: &mut Rasterizer,
) -> (Image<[u8; 3]>, Image<f32>, f64) {
    let (width, height) = (camera.width_px as usize, camera.height_px as usize);
    let ss = config.supersampling.max(1) as usize;
    let intrinsics = camera.intrinsics.scaled(ss as f64);
    let mut buffers = RenderBuffers::new(width * ss, height * ss);
    rasterizer.render(
        mesh,
        &intrinsics,
        pose,
        &RenderOptions::default(),
        &mut buffers,
    );
    let sun = Vec3::new(-0.57, -0.4, 0.72).normalize();
    let world_from_cam = pose.inverse();
    let origin = Vector3::new(CITY_ORIGIN_M[0], CITY_ORIGIN_M[1], CITY_ORIGIN_M[2]);
    let mut rng = ChaCha8Rng::seed_from_u64(image_seed);
    let exposure = 1.0 + 0.05 * rng.random_range(-1.0f32..1.0);
    let sample = |col: usize, row: usize| -> Vec3 {
        let face = buffers.face_index().data()[row * width * ss + col];
        let depth = f64::from(buffers.depth_m().data()[row * width * ss + col]);
        if face == NO_FACE || depth <= 0.0 {
            // Sky above the horizon, dark haze beyond the city's edge below it.
            let up = 1.0 - row as f32 / (height * ss) as f32;
            return Vec3::new(0.45, 0.55, 0.7) * (0.6 + 0.4 * up);
        }
        let normalized = intrinsics
            .pixel_to_normalized(nalgebra::Vector2::new(col as f64 + 0.5, row as f64 + 0.5));
        let point_cam = Vector3::new(normalized.x * depth, normalized.y * depth, depth);
        let world = world_from_cam.transform_point(&point_cam) - origin;
        let p = Vec3::new(world.x as f32, world.y as f32, world.z as f32);
        let n = mesh.face_normal(face as usize);
        let albedo = city_albedo(p, n, config.seed);
        let light = Vec3::new(3.0, 2.9, 2.7) * n.dot(sun).max(0.0) + Vec3::new(0.45, 0.5, 0.62);
        albedo * light
    };
    let mut surface = 0usize;
    for &face in buffers.face_index().data() {
        if face != NO_FACE {
            surface += 1;
        }
    }
    let mut photo = Image::from_fn(width, height, |col, row| {
        let mut sum = Vec3::ZERO;
        for dy in 0..ss {
            for dx in 0..ss {
                sum += sample(col * ss + dx, row * ss + dy);
            }
        }
        sum / (ss * ss) as f32
    })
    .map(|linear| {
        let tone = |v: f32| (v * exposure * 0.8).clamp(0.0, 1.0).powf(1.0 / 2.2) * 255.0;
        [tone(linear.x), tone(linear.y), tone(linear.z)]
    })
    .map(|c| c.map(|v| v.round().clamp(0.0, 255.0) as u8));
    for pixel in photo.data_mut() {
        for channel in pixel.iter_mut() {
            let noise: f32 = StandardNormal.sample(&mut rng);
            *channel = (f32::from(*channel) + noise * config.noise_sigma_dn)
                .round()
                .clamp(0.0, 255.0) as u8;
        }
    }
    let mut depth_buffers = RenderBuffers::new(width, height);
    rasterizer.render(
        mesh,
        &camera.intrinsics,
        pose,
        &RenderOptions::default(),
        &mut depth_buffers,
    );
    let mut depth = depth_buffers.depth_m().clone();
    for d in depth.data_mut() {
        if *d > 0.0 {
            let noise: f32 = StandardNormal.sample(&mut rng);
            *d *= 1.0 + noise * config.depth_relative_noise;
        }
    }
    let surface_fraction = surface as f64 / (width * height * ss * ss) as f64;
    (photo, depth, surface_fraction)
}

/// Writes a synthetic city scene to `out_dir`: `model.ply` (the city, streamed), `images/*.jpg`,
/// `depth/*.pfm`, `gt/` and `initial/<level>/` (COLMAP text), `scene.json`
/// ([`CitySceneSummary`]). Memory: the loaded mesh and one rendering at a time.
pub fn generate_city_scene(
    config: &CityConfig,
    out_dir: &Path,
) -> Result<CitySceneSummary, SynthError> {
    config.validate()?;
    let started = Instant::now();
    for dir in [
        out_dir.to_path_buf(),
        out_dir.join("images"),
        out_dir.join("depth"),
        out_dir.join("gt"),
    ] {
        std::fs::create_dir_all(&dir).map_err(io_error(&dir))?;
    }
    let stream_rng = |stream: u64| {
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        rng.set_stream(stream);
        rng
    };
    let model_path = out_dir.join("model.ply");
    let city = write_city_ply(&model_path, config.triangles)?;
    let mesh_write_s = started.elapsed().as_secs_f64();
    let load_started = Instant::now();
    let mesh = crate::io::mesh_file::read_mesh(&model_path)?;
    let mesh_load_s = load_started.elapsed().as_secs_f64();

    let camera = config.camera();
    let mut view_rng = stream_rng(2);
    let mut rasterizer = Rasterizer::new();
    let mut poses = Vec::with_capacity(config.image_count);
    let mut names = Vec::with_capacity(config.image_count);
    let mut images = Vec::with_capacity(config.image_count);
    let photos_started = Instant::now();
    for index in 0..config.image_count {
        let pose = city_viewpoint(city.side_m, &mut view_rng)
            .ok_or_else(|| SynthError::InvalidConfig(format!("no viewpoint for image {index}")))?;
        let name = format!("city_{index:04}.jpg");
        let image_seed = super::texture::hash_u64(config.seed ^ (index as u64 + 1));
        let (photo, depth, surface_fraction) =
            city_photo(&mesh, &camera, &pose, config, image_seed, &mut rasterizer);
        write_jpeg(
            &out_dir.join("images").join(&name),
            &photo,
            config.jpeg_quality,
        )?;
        let depth_path = out_dir
            .join("depth")
            .join(Path::new(&name).with_extension("pfm"));
        crate::io::pfm::write_pfm(&depth_path, depth.view())?;
        let centre = pose.camera_center();
        images.push(CityImage {
            name: name.clone(),
            camera_centre_m: [centre.x, centre.y, centre.z],
            surface_fraction,
        });
        poses.push(pose);
        names.push(name);
    }
    let photos_s = photos_started.elapsed().as_secs_f64();

    let initial_started = Instant::now();
    write_colmap(&out_dir.join("gt"), &camera, &names, &poses)?;
    let noise = initial::draw_unit_noise(poses.len(), 10.0, &mut stream_rng(5));
    let heading_noise = initial::HeadingNoise::default();
    let (initial_levels, heading_level_px) = write_initial_poses(
        out_dir,
        &mesh,
        &camera,
        &names,
        &poses,
        &noise,
        &config.initial_levels_px,
        0.02,
        config
            .heading_level
            .then(|| (&heading_noise, stream_rng(6))),
    )?;
    let initial_s = initial_started.elapsed().as_secs_f64();

    let summary = CitySceneSummary {
        scene: "city".to_string(),
        config: config.clone(),
        lots_per_side: city.lots_per_side,
        side_m: city.side_m,
        origin_m: CITY_ORIGIN_M,
        model_vertices: city.vertices,
        model_faces: city.triangles,
        camera_fx_px: camera.intrinsics.fx_px,
        images,
        initial_levels,
        heading_level_px,
        timings: CityTimings {
            mesh_write_s,
            mesh_load_s,
            photos_s,
            initial_s,
            total_s: started.elapsed().as_secs_f64(),
        },
    };
    let json_path = out_dir.join("scene.json");
    let json = serde_json::to_string_pretty(&summary).map_err(|e| SynthError::Encode {
        path: json_path.clone(),
        message: e.to_string(),
    })?;
    std::fs::write(&json_path, json).map_err(io_error(&json_path))?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::camera::PinholeIntrinsics;
    use crate::core::raster::{Rasterizer, RenderBuffers, RenderOptions};
    use crate::core::rigid::Rigid3;
    use nalgebra::Vector3;

    #[test]
    fn a_city_scene_has_photos_of_the_city_poses_and_calibrated_initial_levels() {
        let dir = tempfile::tempdir().unwrap();
        let config = CityConfig {
            triangles: 30_000,
            width_px: 160,
            height_px: 90,
            image_count: 2,
            heading_level: false,
            ..CityConfig::default()
        };
        let summary = generate_city_scene(&config, dir.path()).unwrap();
        assert_eq!(summary.images.len(), 2);
        for image in &summary.images {
            assert!(dir.path().join("images").join(&image.name).is_file());
            let depth = crate::io::pfm::read_pfm(
                &dir.path()
                    .join("depth")
                    .join(Path::new(&image.name).with_extension("pfm")),
            )
            .unwrap();
            assert_eq!(depth.size(), (160, 90));
            assert!(
                image.surface_fraction > 0.5,
                "{} sees the city on {:.2} of its pixels",
                image.name,
                image.surface_fraction
            );
        }
        let (gt, _) = crate::io::colmap_model::read_images_at(&dir.path().join("gt")).unwrap();
        assert_eq!(gt.len(), 2);
        let level = &summary.initial_levels[0];
        assert!(
            (level.mean_px - 30.0).abs() < 3.0,
            "initial level 30 px reached {} px",
            level.mean_px
        );
        assert!(dir.path().join("initial/30/images.txt").is_file());
        // The model is the georeferenced city.
        let mesh = crate::io::mesh_file::read_mesh(&dir.path().join("model.ply")).unwrap();
        assert_eq!(mesh.face_count() as u64, summary.model_faces);
        // Same config, same photos.
        let again = tempfile::tempdir().unwrap();
        generate_city_scene(&config, again.path()).unwrap();
        let name = &summary.images[0].name;
        assert_eq!(
            std::fs::read(dir.path().join("images").join(name)).unwrap(),
            std::fs::read(again.path().join("images").join(name)).unwrap()
        );
    }

    #[test]
    fn a_small_city_reads_back_georeferenced_and_renders_only_what_the_camera_sees() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("city.ply");
        let city = write_city_ply(&path, 40_000).unwrap();
        let mesh = crate::io::mesh_file::read_mesh(&path).unwrap();
        assert_eq!(mesh.face_count() as u64, city.triangles);
        assert_eq!(mesh.vertex_count() as u64, city.vertices);
        let (min, max) = mesh.bounds_world_m();
        assert!((min.x - CITY_ORIGIN_M[0]).abs() < 1e-6 && (min.y - CITY_ORIGIN_M[1]).abs() < 1e-6);
        assert!((max.x - (CITY_ORIGIN_M[0] + city.side_m)).abs() < 1e-6);
        assert!(
            mesh.grid().cells().len() > 4,
            "the city is split into cells"
        );

        // A camera 120 m above one corner, looking down obliquely: most of the city is outside.
        let eye = Vector3::new(CITY_ORIGIN_M[0] + 20.0, CITY_ORIGIN_M[1] - 40.0, 120.0);
        let target = Vector3::new(CITY_ORIGIN_M[0] + 60.0, CITY_ORIGIN_M[1] + 60.0, 0.0);
        let pose = Rigid3::look_at(&eye, &target, &Vector3::new(0.0, 0.0, 1.0)).unwrap();
        let intrinsics = PinholeIntrinsics::centered(300.0, 320, 180);
        let mut culled = RenderBuffers::new(320, 180);
        let mut rasterizer = Rasterizer::new();
        rasterizer.render(
            &mesh,
            &intrinsics,
            &pose,
            &RenderOptions::default(),
            &mut culled,
        );
        assert!(
            culled.valid_count() > 320 * 180 / 2,
            "the camera sees the city"
        );
        let visible = rasterizer.visible_face_count();
        assert!(
            visible * 2 < mesh.face_count(),
            "frustum culling keeps {visible} of {} faces",
            mesh.face_count()
        );
        // The same picture as with every face drawn (one cell holding the whole mesh).
        let whole = mesh.clone().with_single_grid_cell();
        let mut all = RenderBuffers::new(320, 180);
        Rasterizer::new().render(
            &whole,
            &intrinsics,
            &pose,
            &RenderOptions::default(),
            &mut all,
        );
        assert_eq!(culled.face_index().data(), all.face_index().data());
        assert_eq!(culled.depth_m().data(), all.depth_m().data());
    }
}
