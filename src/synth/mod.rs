//! Honest synthetic test scenes (docs/design.md §4): a true scene (buildings, ground, clutter) rendered
//! into photo-like JPEGs with materials, sun and sky light, cast shadows and camera effects; MVS-like
//! depth maps; a Poisson-like degraded model for registration; ground-truth and noisy initial poses
//! calibrated to the paper's initial-error levels. The photos and the model differ the way real
//! photos and a reconstructed mesh do, so registration on them is not made easy.
//!
//! Entry point: [`generate_scene`] with a [`SynthConfig`]; it writes
//! `model.ply` (degraded, Poisson-like), `model_lod.ply` (clean, LoD2-like: the buildings' exact
//! walls and roofs and the ground, without small parts), `model_true.ply`, `images/*.jpg`, `depth/*.pfm` (MVS-like), `depth_exact/*.pfm`
//! (exact, for tests and comparisons), `gt/{cameras,images,points3D}.txt`,
//! `initial/<level>/{cameras,images,points3D}.txt` and `scene.json`; with `changes`, also the
//! change ground truth of `changes.rs` (`changes_gt/*.png`, `changes.json`).

pub mod changes;
pub mod city;
pub mod degrade;
pub mod depth;
pub mod geometry;
pub mod initial;
pub mod photo;
pub mod texture;
pub mod viewpoints;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::Vec3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::core::camera::{Camera, PinholeIntrinsics};
use crate::core::image::Image;
use crate::core::mesh::{Mesh, MeshError};
use crate::core::rigid::Rigid3;
use crate::io::colmap::{self, ImagePose};
pub use depth::DepthParams;
use geometry::{PartKind, Scene};
use initial::LevelCalibration;
use photo::{PhotoParams, PhotoRenderer};
pub use viewpoints::SceneKind;

/// Folder of the exact depth maps (next to `depth/`, the MVS-like ones).
pub const EXACT_DEPTH_DIR: &str = "depth_exact";

/// Everything that shapes a synthetic scene. Same config (and seed) → byte-identical files
/// (except the timings in `scene.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SynthConfig {
    /// Seed of every random choice (geometry, clutter, viewpoints, noise, initial poses).
    pub seed: u64,
    /// Width of the written images, pixels.
    pub width_px: u32,
    /// Height of the written images, pixels.
    pub height_px: u32,
    /// Number of photos.
    pub image_count: usize,
    /// Which scene: one free-standing house (the paper's setting) or a block of buildings.
    pub scene: SceneKind,
    /// Target mean δ(P_in, P_gt) of each initial-pose level, pixels at the written size.
    pub initial_levels_px: Vec<f64>,
    /// Accepted relative deviation of the achieved mean δ from the level (the generator aims for
    /// it and reports what it reached).
    pub initial_tolerance: f64,
    /// Camera-centre noise per radian of rotation noise, metres per radian (1° ↔ 0.17 m at 10).
    pub initial_metres_per_radian: f64,
    /// Also write the drone-like `initial/heading/` level ([`initial::heading_poses`]).
    pub heading_level: bool,
    /// How the `heading` level disturbs the poses.
    pub heading_noise: initial::HeadingNoise,
    /// Horizontal field of view of the PINHOLE camera, degrees.
    pub horizontal_fov_deg: f64,
    /// Sun elevation above the horizon, degrees.
    pub sun_elevation_deg: f32,
    /// Sun azimuth, degrees counter-clockwise from world +x.
    pub sun_azimuth_deg: f32,
    /// Rendered samples per pixel along each axis (antialiasing by box downsampling).
    pub supersampling: u32,
    /// Gaussian lens blur of the photos, pixels.
    pub blur_sigma_px: f32,
    /// Sensor noise at mid-grey, 8-bit digital numbers (signal-dependent).
    pub noise_sigma_dn: f32,
    /// Relative darkening in the image corners.
    pub vignetting: f32,
    /// Per-photo exposure variation (standard deviation, relative).
    pub exposure_jitter: f32,
    /// JPEG quality, 1–100.
    pub jpeg_quality: u8,
    /// The MVS-like depth maps (`depth.rs`): the stereo they imitate.
    pub depth: DepthParams,
    /// Whether to add clutter (trees, cars, fences, people, bushes) to the photos.
    pub clutter: bool,
    /// Voxel size of the model's remeshing (≈ triangle size), metres.
    pub model_voxel_m: f32,
    /// Edge-rounding blur of the model, metres.
    pub model_smoothing_sigma_m: f32,
    /// Taubin smoothing iterations on the model.
    pub model_taubin_iterations: u32,
    /// Per-vertex noise of the model, metres (standard deviation).
    pub model_vertex_noise_m: f32,
    /// Low-frequency warp of the model along its normals, metres (amplitude).
    pub model_warp_m: f32,
    /// Holes cut into the model.
    pub model_hole_count: u32,
    /// Largest hole radius, metres.
    pub model_hole_radius_m: f32,
    /// Ground kept in the model around the buildings, metres.
    pub model_ground_margin_m: f32,
    /// Whether the model and the photographed world differ by known objects (new buildings and
    /// extensions in the photos only, demolished buildings in the model only), with the true
    /// change masks and objects written (`changes.rs`).
    pub changes: bool,
    /// Whether the photos are taken in flight order along a continuous path, consecutive ones a
    /// few metres apart (`synth --flight-path`, [`viewpoints::flight_path_viewpoints`]), instead
    /// of each drawn on its own. Left out of `scene.json` when false, so that the scenes made
    /// without it are byte for byte those made before it existed.
    #[serde(skip_serializing_if = "is_false")]
    pub flight_path: bool,
}

fn is_false(value: &bool) -> bool {
    !*value
}

impl Default for SynthConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            width_px: 505,
            height_px: 275,
            image_count: 48,
            scene: SceneKind::House,
            initial_levels_px: vec![30.0, 57.0, 80.0, 104.0],
            initial_tolerance: 0.01,
            initial_metres_per_radian: 10.0,
            heading_level: true,
            heading_noise: initial::HeadingNoise::default(),
            horizontal_fov_deg: 70.0,
            sun_elevation_deg: 40.0,
            sun_azimuth_deg: 215.0,
            supersampling: 2,
            blur_sigma_px: 0.65,
            noise_sigma_dn: 2.5,
            vignetting: 0.25,
            exposure_jitter: 0.06,
            jpeg_quality: 85,
            depth: DepthParams::default(),
            clutter: true,
            model_voxel_m: 0.25,
            model_smoothing_sigma_m: 0.15,
            model_taubin_iterations: 4,
            model_vertex_noise_m: 0.01,
            model_warp_m: 0.04,
            model_hole_count: 6,
            model_hole_radius_m: 0.9,
            model_ground_margin_m: 6.0,
            changes: false,
            flight_path: false,
        }
    }
}

impl SynthConfig {
    /// Checks ranges once, before anything is generated.
    pub fn validate(&self) -> Result<(), SynthError> {
        let invalid = |message: String| Err(SynthError::InvalidConfig(message));
        if self.width_px < 16 || self.height_px < 16 {
            return invalid(format!(
                "image size {}×{} px is below 16×16",
                self.width_px, self.height_px
            ));
        }
        if self.image_count == 0 {
            return invalid("image_count must be at least 1".into());
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
        if !(self.horizontal_fov_deg > 5.0 && self.horizontal_fov_deg < 150.0) {
            return invalid(format!(
                "horizontal_fov_deg {} is outside (5, 150)",
                self.horizontal_fov_deg
            ));
        }
        if !(1..=100).contains(&self.jpeg_quality) {
            return invalid(format!(
                "jpeg_quality {} is outside 1..=100",
                self.jpeg_quality
            ));
        }
        if !(1..=4).contains(&self.supersampling) {
            return invalid(format!(
                "supersampling {} is outside 1..=4",
                self.supersampling
            ));
        }
        if !(0.0..5.0).contains(&self.sun_elevation_deg)
            && !(5.0..=90.0).contains(&self.sun_elevation_deg)
        {
            return invalid(format!(
                "sun_elevation_deg {} is outside 0..=90",
                self.sun_elevation_deg
            ));
        }
        if !(self.model_voxel_m >= 0.05 && self.model_voxel_m <= 2.0) {
            return invalid(format!(
                "model_voxel_m {} is outside [0.05, 2]",
                self.model_voxel_m
            ));
        }
        self.depth.validate().map_err(SynthError::InvalidConfig)?;
        if !(self.initial_tolerance > 0.0 && self.initial_tolerance < 0.5) {
            return invalid(format!(
                "initial_tolerance {} is outside (0, 0.5)",
                self.initial_tolerance
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

/// Errors of scene generation.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error("invalid synth config: {0}")]
    InvalidConfig(String),
    #[error("cannot write {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot encode {path}: {message}")]
    Encode { path: PathBuf, message: String },
    #[error("the generated mesh is invalid: {0}")]
    Mesh(#[from] MeshError),
    #[error(transparent)]
    MeshFile(#[from] crate::io::mesh_file::MeshIoError),
    #[error(transparent)]
    Colmap(#[from] crate::io::colmap::ColmapError),
    #[error(transparent)]
    Pfm(#[from] crate::io::pfm::PfmError),
}

pub(crate) fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> SynthError + '_ {
    move |source| SynthError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// One written photo.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ImageSummary {
    pub name: String,
    /// Side and height class ("front, 8 m").
    pub label: String,
    pub camera_centre_m: [f64; 3],
    /// Fraction of the pixels showing the buildings (true geometry, after clutter occlusion).
    pub building_fraction: f64,
    /// Fraction of the pixels showing clutter.
    pub clutter_fraction: f64,
    /// Fraction of the pixels with a depth value.
    pub depth_valid_fraction: f64,
}

/// Seconds spent per stage.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct Timings {
    pub scene_s: f64,
    pub model_s: f64,
    pub shadow_map_s: f64,
    pub photos_s: f64,
    pub initial_s: f64,
    pub total_s: f64,
}

/// What was generated: the content of `scene.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneSummary {
    pub config: SynthConfig,
    pub camera_fx_px: f64,
    pub camera_fy_px: f64,
    pub camera_cx_px: f64,
    pub camera_cy_px: f64,
    pub true_faces: usize,
    pub true_building_faces: usize,
    pub true_detail_faces: usize,
    pub clutter_faces: usize,
    pub model_vertices: usize,
    pub model_faces: usize,
    pub model_holes: u32,
    pub model_faces_removed_by_holes: usize,
    /// Mean distance from model vertices to the true building and ground surfaces, metres.
    pub model_mean_deviation_m: f64,
    pub images: Vec<ImageSummary>,
    pub initial_levels: Vec<LevelCalibration>,
    /// The `heading` level's mean δ to the ground truth, px (min, mean, max); absent when not written.
    #[serde(default)]
    pub heading_level_px: Option<[f64; 3]>,
    pub timings: Timings,
}

/// The degraded model of `scene` as `generate_scene` writes it (`model.ply`): the degradation's
/// output and the mesh made from it, with vertex normals.
fn degraded_model(
    scene: &geometry::Scene,
    config: &SynthConfig,
    rng: &mut ChaCha8Rng,
) -> Result<(degrade::DegradedModel, Mesh), SynthError> {
    let degraded = degrade::degrade(
        scene,
        &degrade::DegradeParams {
            voxel_m: config.model_voxel_m,
            smoothing_sigma_m: config.model_smoothing_sigma_m,
            taubin_iterations: config.model_taubin_iterations,
            vertex_noise_m: config.model_vertex_noise_m,
            warp_m: config.model_warp_m,
            hole_count: config.model_hole_count,
            hole_radius_m: config.model_hole_radius_m,
            ground_margin_m: config.model_ground_margin_m,
        },
        rng,
    );
    let positions: Vec<nalgebra::Vector3<f64>> = degraded
        .positions_m
        .iter()
        .map(|p| nalgebra::Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z)))
        .collect();
    let mut model = Mesh::from_world(&positions, degraded.faces.clone(), None)?;
    model.compute_vertex_normals();
    Ok((degraded, model))
}

/// Generates a complete synthetic data set in `out_dir` (created if needed).
pub fn generate_scene(config: &SynthConfig, out_dir: &Path) -> Result<SceneSummary, SynthError> {
    config.validate()?;
    let started = Instant::now();
    for dir in [
        out_dir.to_path_buf(),
        out_dir.join("images"),
        out_dir.join("depth"),
        out_dir.join(EXACT_DEPTH_DIR),
        out_dir.join("gt"),
    ] {
        std::fs::create_dir_all(&dir).map_err(io_error(&dir))?;
    }
    let stream_rng = |stream: u64| {
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        rng.set_stream(stream);
        rng
    };
    let camera = config.camera();
    let (width, height) = (config.width_px as usize, config.height_px as usize);

    // 1. The true scene without clutter, then the viewpoints, then clutter clear of the cameras.
    let mut scene_rng = stream_rng(1);
    let mut scene = match config.scene {
        SceneKind::House => geometry::build_house(&mut scene_rng),
        SceneKind::Block => geometry::build_block(&mut scene_rng),
    };
    let views = viewpoints::plan_viewpoints(
        &scene,
        config.scene,
        config.image_count,
        config.flight_path,
        &mut stream_rng(2),
    )
    .map_err(SynthError::InvalidConfig)?;
    let eyes: Vec<Vec3> = views.iter().map(|v| v.eye_m).collect();
    let placed_changes = if config.changes {
        geometry::add_change_objects(
            &mut scene,
            &changes::plan_for(config.scene),
            &eyes,
            &mut stream_rng(6),
        )
    } else {
        Vec::new()
    };
    if config.clutter {
        geometry::add_clutter(&mut scene, &mut stream_rng(3), &eyes, 3.0);
    }
    // With changes, the photos and the model see different worlds.
    let worlds = config
        .changes
        .then(|| changes::split_worlds(&scene, &placed_changes));
    let (photo_scene, model_scene) = match &worlds {
        Some(worlds) => (&worlds.photo, &worlds.model),
        None => (&scene, &scene),
    };
    let scene_s = started.elapsed().as_secs_f64();

    // 2. The degraded model and the true reference model.
    let model_started = Instant::now();
    let (degraded, model) = degraded_model(model_scene, config, &mut stream_rng(4))?;
    let true_model = model_scene.to_mesh(|t| {
        matches!(
            t.part,
            PartKind::Building | PartKind::Detail | PartKind::NearGround
        )
    })?;
    let model_mean_deviation_m = f64::from(degrade::mean_nearest_distance_m(
        &degraded.positions_m,
        &sample_surface(model_scene, 0.1),
        1.0,
    ));
    // A city model's view of the same world (issue #11: registration given a clean model): the
    // main volumes' exact planar faces and the ground, without the small parts a Poisson mesh
    // also loses, and without its rounding, noise and holes.
    let lod_model =
        model_scene.to_mesh(|t| matches!(t.part, PartKind::Building | PartKind::NearGround))?;
    write_mesh(&out_dir.join("model.ply"), &model)?;
    write_mesh(&out_dir.join("model_lod.ply"), &lod_model)?;
    write_mesh(&out_dir.join("model_true.ply"), &true_model)?;
    let model_s = model_started.elapsed().as_secs_f64();

    // 3. Photos and depth maps.
    let shadow_started = Instant::now();
    let photo_params = PhotoParams {
        sun_elevation_deg: config.sun_elevation_deg,
        sun_azimuth_deg: config.sun_azimuth_deg,
        supersampling: config.supersampling,
        blur_sigma_px: config.blur_sigma_px,
        noise_sigma_dn: config.noise_sigma_dn,
        vignetting: config.vignetting,
        exposure_jitter: config.exposure_jitter,
        seed: config.seed,
    };
    let mut renderer = PhotoRenderer::new(photo_scene, photo_params)?;
    let mut truth = match &worlds {
        Some(worlds) => {
            let dir = out_dir.join(changes::MASK_DIR);
            std::fs::create_dir_all(&dir).map_err(io_error(&dir))?;
            let omitted = changes::omitted_parts(&worlds.photo);
            let first_omission_id = scene.tags.iter().map(|t| t.object_id).max().unwrap_or(0) + 1;
            let file = changes::ChangesFile::new(&placed_changes, &omitted, first_omission_id);
            Some((
                changes::TruthRenderer::new(
                    worlds,
                    &placed_changes,
                    (first_omission_id..).zip(omitted).collect(),
                )?,
                file,
            ))
        }
        None => None,
    };
    let shadow_map_s = shadow_started.elapsed().as_secs_f64();
    let photos_started = Instant::now();
    let mut images = Vec::with_capacity(views.len());
    for (index, view) in views.iter().enumerate() {
        let image_seed =
            texture::hash_u64(config.seed ^ (index as u64 + 1).wrapping_mul(0x9E37_79B9));
        let (building_fraction, clutter_fraction) = {
            let buffers =
                renderer.render_visibility(&camera.intrinsics, width, height, &view.cam_from_world);
            let faces = buffers.face_index().data().to_vec();
            let mut building = 0usize;
            let mut clutter = 0usize;
            for face in faces {
                match renderer.tag(face).map(|t| t.part) {
                    Some(PartKind::Building | PartKind::Detail) => building += 1,
                    Some(PartKind::Clutter) => clutter += 1,
                    _ => {}
                }
            }
            let n = (width * height) as f64;
            (building as f64 / n, clutter as f64 / n)
        };
        let photo = renderer.render_photo(
            &camera.intrinsics,
            width,
            height,
            &view.cam_from_world,
            image_seed,
        );
        let (depth, exact_depth) = renderer.depth_maps(
            &camera.intrinsics,
            &photo,
            &view.cam_from_world,
            &config.depth,
            image_seed,
        );
        let image_path = out_dir.join("images").join(&view.name);
        write_jpeg(&image_path, &photo, config.jpeg_quality)?;
        let depth_path = out_dir
            .join("depth")
            .join(Path::new(&view.name).with_extension("pfm"));
        let depth_valid_fraction =
            depth.data().iter().filter(|d| **d > 0.0).count() as f64 / (width * height) as f64;
        crate::io::pfm::write_pfm(&depth_path, depth.view())?;
        let exact_path = out_dir
            .join(EXACT_DEPTH_DIR)
            .join(Path::new(&view.name).with_extension("pfm"));
        crate::io::pfm::write_pfm(&exact_path, exact_depth.view())?;
        if let Some((renderer, file)) = &mut truth {
            let (mask, counts) =
                renderer.mask(&camera.intrinsics, width, height, &view.cam_from_world);
            let mask_path = out_dir
                .join(changes::MASK_DIR)
                .join(Path::new(&view.name).with_extension("png"));
            write_grey_png(&mask_path, &mask)?;
            for object in file.objects.iter_mut().chain(&mut file.model_omissions) {
                if let Some(&pixels) = counts.get(&object.id) {
                    object.pixels_per_image.insert(view.name.clone(), pixels);
                }
            }
        }
        let centre = view.cam_from_world.camera_center();
        images.push(ImageSummary {
            name: view.name.clone(),
            label: view.label.clone(),
            camera_centre_m: [centre.x, centre.y, centre.z],
            building_fraction,
            clutter_fraction,
            depth_valid_fraction,
        });
    }
    let photos_s = photos_started.elapsed().as_secs_f64();

    // 4. Ground truth and initial poses.
    let initial_started = Instant::now();
    let ground_truth: Vec<Rigid3> = views.iter().map(|v| v.cam_from_world).collect();
    let names: Vec<String> = views.iter().map(|v| v.name.clone()).collect();
    write_colmap(&out_dir.join("gt"), &camera, &names, &ground_truth)?;
    let noise = initial::draw_unit_noise(
        views.len(),
        config.initial_metres_per_radian,
        &mut stream_rng(5),
    );
    let (initial_levels, heading_level_px) = write_initial_poses(
        out_dir,
        &model,
        &camera,
        &names,
        &ground_truth,
        &noise,
        &config.initial_levels_px,
        config.initial_tolerance,
        config
            .heading_level
            .then(|| (&config.heading_noise, stream_rng(6))),
    )?;
    let initial_s = initial_started.elapsed().as_secs_f64();

    let count = |kind: PartKind| scene.tags.iter().filter(|t| t.part == kind).count();
    let summary = SceneSummary {
        config: config.clone(),
        camera_fx_px: camera.intrinsics.fx_px,
        camera_fy_px: camera.intrinsics.fy_px,
        camera_cx_px: camera.intrinsics.cx_px,
        camera_cy_px: camera.intrinsics.cy_px,
        true_faces: scene.faces.len(),
        true_building_faces: count(PartKind::Building),
        true_detail_faces: count(PartKind::Detail),
        clutter_faces: count(PartKind::Clutter),
        model_vertices: model.vertex_count(),
        model_faces: model.face_count(),
        model_holes: degraded.holes_cut,
        model_faces_removed_by_holes: degraded.faces_removed_by_holes,
        model_mean_deviation_m,
        images,
        initial_levels,
        heading_level_px,
        timings: Timings {
            scene_s,
            model_s,
            shadow_map_s,
            photos_s,
            initial_s,
            total_s: started.elapsed().as_secs_f64(),
        },
    };
    if let Some((_, file)) = &truth {
        let path = out_dir.join(changes::OBJECTS_FILE);
        let json = serde_json::to_string_pretty(file).map_err(|e| SynthError::Encode {
            path: path.clone(),
            message: e.to_string(),
        })?;
        std::fs::write(&path, json).map_err(io_error(&path))?;
    }
    let json_path = out_dir.join("scene.json");
    let json = serde_json::to_string_pretty(&summary).map_err(|e| SynthError::Encode {
        path: json_path.clone(),
        message: e.to_string(),
    })?;
    std::fs::write(&json_path, json).map_err(io_error(&json_path))?;
    Ok(summary)
}

/// The folder of the drone-like initial level under `initial/`.
pub const HEADING_LEVEL_DIR: &str = "heading";

/// The folder name of an initial level: the level in whole pixels ("30"), or with decimals.
pub fn level_dir_name(level_px: f64) -> String {
    if (level_px - level_px.round()).abs() < 1e-9 {
        format!("{}", level_px.round() as i64)
    } else {
        format!("{level_px}")
    }
}

/// Points densely sampled on the true building and near-ground faces.
fn sample_surface(scene: &Scene, spacing_m: f32) -> Vec<Vec3> {
    let mut points = Vec::new();
    for (f, tag) in scene.faces.iter().zip(&scene.tags) {
        if !matches!(tag.part, PartKind::Building | PartKind::NearGround) {
            continue;
        }
        let [a, b, c] = f.map(|v| scene.positions_m[v as usize]);
        let n = (((b - a).length().max((c - a).length())) / spacing_m)
            .ceil()
            .max(1.0) as usize;
        for s in 0..=n {
            for t in 0..=(n - s) {
                let (u, v) = (s as f32 / n as f32, t as f32 / n as f32);
                points.push(a + (b - a) * u + (c - a) * v);
            }
        }
    }
    points
}

fn write_mesh(path: &Path, mesh: &Mesh) -> Result<(), SynthError> {
    Ok(crate::io::ply::write_ply(
        path,
        mesh,
        crate::io::ply::PlyEncoding::BinaryLittleEndian,
    )?)
}

/// Writes a scene's initial poses: one folder per level of `levels_px` (`initial/<level>/`,
/// noise `noise` scaled so that the mean δ to `ground_truth` hits the level within `tolerance`)
/// and, when `heading` is given, `initial/heading/` (a drone's compass-like prior). Returns each
/// level's calibration and the heading level's δ [min, mean, max], px.
#[allow(clippy::too_many_arguments)]
pub(crate) fn write_initial_poses(
    out_dir: &Path,
    model: &Mesh,
    camera: &Camera,
    names: &[String],
    ground_truth: &[Rigid3],
    noise: &[initial::UnitNoise],
    levels_px: &[f64],
    tolerance: f64,
    heading: Option<(&initial::HeadingNoise, ChaCha8Rng)>,
) -> Result<(Vec<LevelCalibration>, Option<[f64; 3]>), SynthError> {
    let mut workspace = crate::core::reprojection::ReprojectionWorkspace::new();
    let mut initial_levels = Vec::with_capacity(levels_px.len());
    for &level in levels_px {
        let calibration = initial::calibrate_level(
            model,
            camera,
            ground_truth,
            noise,
            level,
            tolerance,
            &mut workspace,
        );
        let dir = out_dir.join("initial").join(level_dir_name(level));
        std::fs::create_dir_all(&dir).map_err(io_error(&dir))?;
        write_colmap(&dir, camera, names, &calibration.poses)?;
        initial_levels.push(calibration);
    }
    let heading_level_px = match heading {
        Some((heading_noise, mut rng)) => {
            let poses = initial::heading_poses(ground_truth, heading_noise, &mut rng);
            let dir = out_dir.join("initial").join(HEADING_LEVEL_DIR);
            std::fs::create_dir_all(&dir).map_err(io_error(&dir))?;
            write_colmap(&dir, camera, names, &poses)?;
            let deltas: Vec<f64> = poses
                .iter()
                .zip(ground_truth)
                .filter_map(|(pose, gt)| {
                    crate::core::reprojection::mutual_reprojection_error_px(
                        model,
                        camera,
                        pose,
                        camera,
                        gt,
                        &mut workspace,
                    )
                })
                .collect();
            let mean = deltas.iter().sum::<f64>() / deltas.len().max(1) as f64;
            let min = deltas.iter().copied().fold(f64::INFINITY, f64::min);
            let max = deltas.iter().copied().fold(0.0, f64::max);
            Some([min, mean, max])
        }
        None => None,
    };
    Ok((initial_levels, heading_level_px))
}

pub(crate) fn write_colmap(
    dir: &Path,
    camera: &Camera,
    names: &[String],
    poses: &[Rigid3],
) -> Result<(), SynthError> {
    let cameras: BTreeMap<u32, Camera> = [(1, *camera)].into_iter().collect();
    colmap::write_cameras_txt(&dir.join(colmap::CAMERAS_FILE), &cameras)?;
    let images: Vec<ImagePose> = names
        .iter()
        .zip(poses)
        .enumerate()
        .map(|(index, (name, pose))| ImagePose {
            image_id: index as u32 + 1,
            camera_id: 1,
            name: name.clone(),
            cam_from_world: *pose,
        })
        .collect();
    colmap::write_images_txt(&dir.join(colmap::IMAGES_FILE), &images)?;
    colmap::write_empty_points3d_txt(&dir.join(colmap::POINTS3D_FILE))?;
    Ok(())
}

/// Writes an 8-bit grey image as a PNG.
fn write_grey_png(path: &Path, image: &Image<u8>) -> Result<(), SynthError> {
    image::save_buffer(
        path,
        image.data(),
        image.width_px() as u32,
        image.height_px() as u32,
        image::ExtendedColorType::L8,
    )
    .map_err(|e| SynthError::Encode {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// Writes an 8-bit sRGB photo as a JPEG.
pub(crate) fn write_jpeg(
    path: &Path,
    photo: &Image<[u8; 3]>,
    quality: u8,
) -> Result<(), SynthError> {
    let file = std::fs::File::create(path).map_err(io_error(path))?;
    let mut writer = std::io::BufWriter::new(file);
    let mut encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut writer, quality);
    encoder
        .encode(
            photo.data().as_flattened(),
            photo.width_px() as u32,
            photo.height_px() as u32,
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| SynthError::Encode {
            path: path.to_path_buf(),
            message: e.to_string(),
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::image::{Image, ImageView};
    use crate::core::raster::{NormalSource, Rasterizer, RenderBuffers, RenderOptions};
    use rand::SeedableRng;

    fn tiny_config(seed: u64) -> SynthConfig {
        SynthConfig {
            seed,
            width_px: 160,
            height_px: 88,
            image_count: 3,
            initial_levels_px: vec![8.0, 20.0],
            supersampling: 1,
            model_voxel_m: 0.35,
            ..SynthConfig::default()
        }
    }

    fn files_under(dir: &Path) -> Vec<PathBuf> {
        let mut files = Vec::new();
        let mut stack = vec![dir.to_path_buf()];
        while let Some(d) = stack.pop() {
            for entry in std::fs::read_dir(&d).unwrap() {
                let path = entry.unwrap().path();
                if path.is_dir() {
                    stack.push(path);
                } else {
                    files.push(path.strip_prefix(dir).unwrap().to_path_buf());
                }
            }
        }
        files.sort();
        files
    }

    #[test]
    fn a_tiny_run_writes_the_complete_layout_and_hits_the_levels() {
        let dir = tempfile::tempdir().unwrap();
        let config = tiny_config(5);
        let summary = generate_scene(&config, dir.path()).unwrap();
        let files = files_under(dir.path());
        let mut expected: Vec<PathBuf> = [
            "model.ply",
            "model_lod.ply",
            "model_true.ply",
            "scene.json",
            "gt/cameras.txt",
            "gt/images.txt",
            "gt/points3D.txt",
            "initial/8/cameras.txt",
            "initial/8/images.txt",
            "initial/8/points3D.txt",
            "initial/20/cameras.txt",
            "initial/20/images.txt",
            "initial/20/points3D.txt",
            "initial/heading/cameras.txt",
            "initial/heading/images.txt",
            "initial/heading/points3D.txt",
        ]
        .iter()
        .map(PathBuf::from)
        .collect();
        for k in 0..3 {
            expected.push(PathBuf::from(format!("images/view_{k:03}.jpg")));
            expected.push(PathBuf::from(format!("depth/view_{k:03}.pfm")));
            expected.push(PathBuf::from(format!("depth_exact/view_{k:03}.pfm")));
        }
        expected.sort();
        assert_eq!(files, expected);
        // The files read back with the library's own readers.
        let gt = crate::io::colmap::read_model(&dir.path().join("gt")).unwrap();
        assert_eq!(gt.images.len(), 3);
        assert_eq!(gt.cameras[&1].width_px, 160);
        let model = crate::io::ply::read_ply(&dir.path().join("model.ply")).unwrap();
        assert_eq!(model.face_count(), summary.model_faces);
        // The LoD-like model is a clean subset of the true geometry: every vertex exactly one of
        // the true model's (no rounding, noise or warp), and fewer faces (no small parts).
        let lod = crate::io::ply::read_ply(&dir.path().join("model_lod.ply")).unwrap();
        let exact = crate::io::ply::read_ply(&dir.path().join("model_true.ply")).unwrap();
        assert!(
            lod.face_count() > 0 && lod.face_count() < exact.face_count(),
            "{} LoD faces, {} true",
            lod.face_count(),
            exact.face_count()
        );
        let world = |mesh: &Mesh| -> Vec<nalgebra::Vector3<f64>> {
            mesh.positions_local_m()
                .iter()
                .map(|p| {
                    mesh.origin_m()
                        + nalgebra::Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z))
                })
                .collect()
        };
        let cell = |p: &nalgebra::Vector3<f64>| p.map(|v| (v / 0.01).floor() as i64);
        let mut true_cells: std::collections::HashMap<_, Vec<nalgebra::Vector3<f64>>> =
            std::collections::HashMap::new();
        for p in world(&exact) {
            true_cells.entry(cell(&p)).or_default().push(p);
        }
        let on_true_vertex = |p: &nalgebra::Vector3<f64>| {
            let c = cell(p);
            (-1..=1).any(|i| {
                (-1..=1).any(|j| {
                    (-1..=1).any(|k| {
                        true_cells
                            .get(&(c + nalgebra::Vector3::new(i, j, k)))
                            .is_some_and(|ps| ps.iter().any(|q| (q - p).norm() < 1e-3))
                    })
                })
            })
        };
        assert!(world(&lod).iter().all(on_true_vertex));
        let depth = crate::io::pfm::read_pfm(&dir.path().join("depth/view_000.pfm")).unwrap();
        assert_eq!(depth.size(), (160, 88));
        let valid = crate::io::pfm::valid_depth_count(depth.view()) as f64 / (160.0 * 88.0);
        assert!(valid > 0.2 && valid < 0.95, "depth valid fraction {valid}");
        let photo = image::open(dir.path().join("images/view_000.jpg")).unwrap();
        assert_eq!((photo.width(), photo.height()), (160, 88));
        // Initial levels: the mean δ is within 5 % of each level.
        for level in &summary.initial_levels {
            println!(
                "level {} px: mean {:.2} px ({} evaluations)",
                level.target_px, level.mean_px, level.evaluations
            );
            assert!(level.relative_error < 0.05, "{level:?}");
            assert_eq!(level.unmeasurable_images, 0);
        }
        let initial = crate::io::colmap::read_model(&dir.path().join("initial/20")).unwrap();
        for (a, b) in initial.images.iter().zip(&gt.images) {
            assert_eq!(a.name, b.name);
            assert!((a.cam_from_world.translation - b.cam_from_world.translation).norm() > 1e-6);
        }
    }

    #[test]
    fn the_same_seed_gives_identical_files_and_another_seed_does_not() {
        let config = tiny_config(9);
        let runs: Vec<tempfile::TempDir> = (0..2).map(|_| tempfile::tempdir().unwrap()).collect();
        let summaries: Vec<SceneSummary> = runs
            .iter()
            .map(|d| generate_scene(&config, d.path()).unwrap())
            .collect();
        let files = files_under(runs[0].path());
        assert_eq!(files, files_under(runs[1].path()));
        for file in &files {
            let a = std::fs::read(runs[0].path().join(file)).unwrap();
            let b = std::fs::read(runs[1].path().join(file)).unwrap();
            if file == Path::new("scene.json") {
                // Identical apart from the timings.
                let strip = |bytes: &[u8]| {
                    let mut value: serde_json::Value = serde_json::from_slice(bytes).unwrap();
                    value["timings"] = serde_json::Value::Null;
                    value
                };
                assert_eq!(strip(&a), strip(&b));
            } else {
                assert!(a == b, "{} differs between runs", file.display());
            }
        }
        assert_eq!(summaries[0].model_faces, summaries[1].model_faces);
        let other = tempfile::tempdir().unwrap();
        generate_scene(&tiny_config(10), other.path()).unwrap();
        let a = std::fs::read(runs[0].path().join("images/view_000.jpg")).unwrap();
        let b = std::fs::read(other.path().join("images/view_000.jpg")).unwrap();
        assert_ne!(a, b);
    }

    #[test]
    fn flight_path_is_recorded_when_set_and_left_out_of_older_configs() {
        // Scenes made without it write the config they wrote before the option existed.
        let plain = serde_json::to_string(&SynthConfig::default()).unwrap();
        assert!(!plain.contains("flight_path"));
        let old: SynthConfig = serde_json::from_str(r#"{"seed": 3}"#).unwrap();
        assert!(!old.flight_path);
        let path = SynthConfig {
            flight_path: true,
            ..SynthConfig::default()
        };
        let written = serde_json::to_string(&path).unwrap();
        assert!(written.contains(r#""flight_path":true"#));
        assert_eq!(serde_json::from_str::<SynthConfig>(&written).unwrap(), path);
    }

    #[test]
    fn invalid_configs_are_rejected_and_unknown_fields_too() {
        let bad = SynthConfig {
            jpeg_quality: 0,
            ..SynthConfig::default()
        };
        assert!(matches!(bad.validate(), Err(SynthError::InvalidConfig(_))));
        let bad = SynthConfig {
            image_count: 0,
            ..SynthConfig::default()
        };
        assert!(bad.validate().is_err());
        assert!(serde_json::from_str::<SynthConfig>(r#"{"seed": 3, "sun_elevation": 4}"#).is_err());
        let parsed: SynthConfig = serde_json::from_str(r#"{"seed": 3, "scene": "Block"}"#).unwrap();
        assert_eq!(parsed.seed, 3);
        assert_eq!(parsed.scene, SceneKind::Block);
        assert_eq!(parsed.width_px, 505);
    }

    /// Pearson correlation of two images.
    fn correlation(a: &[f32], b: &[f32]) -> f64 {
        let n = a.len() as f64;
        let mean_a = a.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
        let mean_b = b.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
        let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
        for (&x, &y) in a.iter().zip(b) {
            let (x, y) = (f64::from(x) - mean_a, f64::from(y) - mean_b);
            ab += x * y;
            aa += x * x;
            bb += y * y;
        }
        ab / (aa * bb).sqrt().max(1e-12)
    }

    fn asg_of(
        mesh: &Mesh,
        camera: &Camera,
        pose: &Rigid3,
        normal_source: NormalSource,
    ) -> Vec<f32> {
        let (w, h) = (camera.width_px as usize, camera.height_px as usize);
        let mut buffers = RenderBuffers::new(w, h);
        let options = RenderOptions {
            normal_source,
            ..RenderOptions::default()
        };
        Rasterizer::new().render(mesh, &camera.intrinsics, pose, &options, &mut buffers);
        let mut asg = Image::default();
        crate::core::shading::asg_from_normals(
            buffers.normal_cam().view(),
            &crate::core::shading::AsgOptions::default(),
            &mut asg,
        );
        asg.into_data()
    }

    /// docs/design.md §4: the photo's gradients must differ substantially from the model's ASG (textures,
    /// shadows, clutter, noise), yet line up with it under the ground-truth pose.
    #[test]
    fn photo_gradients_differ_from_the_asg_but_line_up_under_the_true_pose() {
        let config = SynthConfig::default();
        let camera = config.camera();
        let (w, h) = (camera.width_px as usize, camera.height_px as usize);
        let stream = |k: u64| {
            let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
            rng.set_stream(k);
            rng
        };
        let mut scene = geometry::build_house(&mut stream(1));
        let mut view_rng = stream(2);
        // Image 3: the front at 8 m.
        let views: Vec<viewpoints::Viewpoint> = (0..6)
            .map(|k| {
                viewpoints::draw_viewpoint(&scene, SceneKind::House, k, &mut view_rng).unwrap()
            })
            .collect();
        let eyes: Vec<Vec3> = views.iter().map(|v| v.eye_m).collect();
        geometry::add_clutter(&mut scene, &mut stream(3), &eyes, 3.0);
        let gt = views[3].cam_from_world;
        let params = PhotoParams {
            sun_elevation_deg: config.sun_elevation_deg,
            sun_azimuth_deg: config.sun_azimuth_deg,
            supersampling: config.supersampling,
            blur_sigma_px: config.blur_sigma_px,
            noise_sigma_dn: config.noise_sigma_dn,
            vignetting: config.vignetting,
            exposure_jitter: config.exposure_jitter,
            seed: config.seed,
        };
        let mut renderer = PhotoRenderer::new(&scene, params).unwrap();
        let photo = renderer.render_photo(&camera.intrinsics, w, h, &gt, 77);
        // Through JPEG, like the written files.
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, config.jpeg_quality)
            .encode(
                photo.data().as_flattened(),
                w as u32,
                h as u32,
                image::ExtendedColorType::Rgb8,
            )
            .unwrap();
        let decoded = image::load_from_memory(&jpeg).unwrap().to_luma32f();
        let luma: Vec<f32> = decoded.as_raw().iter().map(|v| v * 255.0).collect();
        let mut photo_gradient = Image::default();
        crate::core::shading::gradient_magnitude(
            ImageView::new(w, h, &luma).unwrap(),
            &mut photo_gradient,
        );
        let photo_gradient = photo_gradient.into_data();

        let mut true_model = scene
            .to_mesh(|t| {
                matches!(
                    t.part,
                    PartKind::Building | PartKind::Detail | PartKind::NearGround
                )
            })
            .unwrap();
        true_model.clear_vertex_normals();
        // The degraded model the registration gets, with its vertex normals.
        let (_, model) = degraded_model(&scene, &config, &mut stream(4)).unwrap();

        // Poses: ground truth, turned by 8 px about the camera's y axis, and the 104 px level's
        // initial pose.
        let turn = nalgebra::UnitQuaternion::from_axis_angle(
            &nalgebra::Vector3::y_axis(),
            8.0 / camera.intrinsics.fx_px,
        );
        let shifted = Rigid3::new(turn * gt.rotation, turn * gt.translation);
        let noise = initial::draw_unit_noise(1, config.initial_metres_per_radian, &mut stream(5));
        let mut workspace = crate::core::reprojection::ReprojectionWorkspace::new();
        let level =
            initial::calibrate_level(&model, &camera, &[gt], &noise, 104.0, 0.02, &mut workspace);
        let initial_pose = level.poses[0];

        // Raw correlation of thin edges punishes any sub-edge offset; the blurred one (σ 1.5 px)
        // asks whether the structures line up.
        let photo_blurred = blur(&photo_gradient, w, h, 1.5);
        // Where the buildings are under the true pose (dilated by 4 px).
        let buildings = scene
            .to_mesh(|t| matches!(t.part, PartKind::Building | PartKind::Detail))
            .unwrap();
        let mut buffers = RenderBuffers::new(w, h);
        Rasterizer::new().render(
            &buildings,
            &camera.intrinsics,
            &gt,
            &RenderOptions::default(),
            &mut buffers,
        );
        let mask: Vec<bool> = (0..w * h)
            .map(|index| {
                let (row, col) = ((index / w) as i64, (index % w) as i64);
                (-4..=4).any(|dr| {
                    (-4..=4).any(|dc| {
                        let (r, c) = (row + dr, col + dc);
                        r >= 0
                            && c >= 0
                            && r < h as i64
                            && c < w as i64
                            && buffers.is_valid(c as usize, r as usize)
                    })
                })
            })
            .collect();
        let masked = |values: &[f32]| -> Vec<f32> {
            values
                .iter()
                .zip(&mask)
                .filter(|(_, m)| **m)
                .map(|(v, _)| *v)
                .collect()
        };
        let photo_masked = masked(&photo_blurred);
        let scores = |mesh: &Mesh, source: NormalSource, pose: &Rigid3| {
            let asg = asg_of(mesh, &camera, pose, source);
            let asg_blurred = blur(&asg, w, h, 1.5);
            (
                correlation(&photo_gradient, &asg),
                correlation(&photo_blurred, &asg_blurred),
                correlation(&photo_masked, &masked(&asg_blurred)),
            )
        };
        let true_gt = scores(&true_model, NormalSource::Face, &gt);
        let true_shift = scores(&true_model, NormalSource::Face, &shifted);
        let true_initial = scores(&true_model, NormalSource::Face, &initial_pose);
        let model_gt = scores(&model, NormalSource::Vertex, &gt);
        let model_shift = scores(&model, NormalSource::Vertex, &shifted);
        let model_initial = scores(&model, NormalSource::Vertex, &initial_pose);
        println!(
            "correlation of the photo's gradients with the ASG (raw / blurred σ 1.5 px / blurred on the buildings), initial pose δ {:.1} px:",
            level.mean_px
        );
        for (name, gt, shift, initial) in [
            (
                "true model, face normals",
                true_gt,
                true_shift,
                true_initial,
            ),
            (
                "degraded model, vertex normals",
                model_gt,
                model_shift,
                model_initial,
            ),
        ] {
            println!(
                "  {name}: GT {:.3} / {:.3} / {:.3}, 8 px off {:.3} / {:.3} / {:.3}, 104 px initial {:.3} / {:.3} / {:.3}",
                gt.0, gt.1, gt.2, shift.0, shift.1, shift.2, initial.0, initial.1, initial.2
            );
        }
        // Query mode (b), the paper's: ASG of the normals of the photo's MVS-like depth map.
        let (depth, _) = renderer.depth_maps(&camera.intrinsics, &photo, &gt, &config.depth, 77);
        let mut depth_normals = Image::default();
        crate::core::shading::normals_from_depth(
            depth.view(),
            &camera.intrinsics,
            &mut depth_normals,
        );
        let mut depth_asg = Image::default();
        crate::core::shading::asg_from_normals(
            depth_normals.view(),
            &crate::core::shading::AsgOptions::default(),
            &mut depth_asg,
        );
        let depth_asg = blur(depth_asg.data(), w, h, 1.5);
        let depth_scores: Vec<f64> = [gt, shifted, initial_pose]
            .iter()
            .map(|pose| {
                correlation(
                    &depth_asg,
                    &blur(
                        &asg_of(&model, &camera, pose, NormalSource::Vertex),
                        w,
                        h,
                        1.5,
                    ),
                )
            })
            .collect();
        println!(
            "photo-depth ASG vs degraded-model ASG (blurred): GT {:.3}, 8 px off {:.3}, 104 px initial {:.3}",
            depth_scores[0], depth_scores[1], depth_scores[2]
        );
        assert!(depth_scores[0] < 0.8, "{depth_scores:?}");
        assert!(depth_scores[0] > depth_scores[2], "{depth_scores:?}");
        // The degraded model sits where the true one is: its ASG correlates with the true
        // model's ASG under the true pose, not under the 104 px initial pose.
        let true_asg = blur(
            &asg_of(&true_model, &camera, &gt, NormalSource::Face),
            w,
            h,
            1.5,
        );
        let model_vs_true_gt = correlation(
            &true_asg,
            &blur(
                &asg_of(&model, &camera, &gt, NormalSource::Vertex),
                w,
                h,
                1.5,
            ),
        );
        let model_vs_true_initial = correlation(
            &true_asg,
            &blur(
                &asg_of(&model, &camera, &initial_pose, NormalSource::Vertex),
                w,
                h,
                1.5,
            ),
        );
        println!(
            "degraded-model ASG vs true-model ASG (blurred): {model_vs_true_gt:.3} at GT, {model_vs_true_initial:.3} at the initial pose"
        );
        // Substantially different images…
        assert!(true_gt.0 < 0.6 && true_gt.1 < 0.7, "{true_gt:?}");
        assert!(model_gt.0 < 0.6 && model_gt.1 < 0.7, "{model_gt:?}");
        // …that line up under the true pose (the true geometry's edges; the degraded model's
        // rounded edges correlate with the photo only at the level of noise, see the figures).
        assert!(
            true_gt.1 > true_shift.1 + 0.05,
            "{true_gt:?} vs {true_shift:?}"
        );
        assert!(
            true_gt.1 > 2.0 * true_initial.1.max(0.01),
            "{true_gt:?} vs {true_initial:?}"
        );
        assert!(
            true_gt.2 > true_shift.2 + 0.05,
            "{true_gt:?} vs {true_shift:?}"
        );
        assert!(
            model_vs_true_gt > 0.2 && model_vs_true_gt > 2.5 * model_vs_true_initial.max(0.01),
            "{model_vs_true_gt} vs {model_vs_true_initial}"
        );
    }

    /// Separable Gaussian blur of a grey image (borders clamp).
    fn blur(values: &[f32], w: usize, h: usize, sigma_px: f32) -> Vec<f32> {
        let radius = (3.0 * sigma_px).ceil() as i64;
        let kernel: Vec<f32> = (-radius..=radius)
            .map(|d| (-(d * d) as f32 / (2.0 * sigma_px * sigma_px)).exp())
            .collect();
        let total: f32 = kernel.iter().sum();
        let pass = |input: &[f32], horizontal: bool| -> Vec<f32> {
            (0..w * h)
                .map(|index| {
                    let (row, col) = ((index / w) as i64, (index % w) as i64);
                    kernel
                        .iter()
                        .enumerate()
                        .map(|(q, k)| {
                            let d = q as i64 - radius;
                            let (r, c) = if horizontal {
                                (row, (col + d).clamp(0, w as i64 - 1))
                            } else {
                                ((row + d).clamp(0, h as i64 - 1), col)
                            };
                            input[(r as usize) * w + c as usize] * k
                        })
                        .sum::<f32>()
                        / total
                })
                .collect()
        };
        pass(&pass(values, true), false)
    }

    /// Generates a full default scene into `$ASGREG_SYNTH_OUT` (for inspection and timing):
    /// `ASGREG_SYNTH_OUT=/tmp/scene cargo test --lib synth::tests::default_scene -- --ignored --nocapture`
    #[test]
    #[ignore]
    fn default_scene() {
        let out = std::env::var("ASGREG_SYNTH_OUT")
            .unwrap_or_else(|_| "/tmp/asgreg_synth_default".into());
        let images: usize = std::env::var("ASGREG_SYNTH_IMAGES")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(48);
        let scene = match std::env::var("ASGREG_SYNTH_SCENE").as_deref() {
            Ok("Block") => SceneKind::Block,
            _ => SceneKind::House,
        };
        let config = SynthConfig {
            image_count: images,
            scene,
            ..SynthConfig::default()
        };
        let summary = generate_scene(&config, Path::new(&out)).unwrap();
        println!(
            "{}",
            serde_json::to_string_pretty(&summary.timings).unwrap()
        );
        for level in &summary.initial_levels {
            println!(
                "level {:>5.1}: mean {:.2} px (min {:.1}, max {:.1}), scale {:.5}, {} evaluations, {} unmeasurable",
                level.target_px, level.mean_px, level.min_px, level.max_px, level.scale, level.evaluations, level.unmeasurable_images
            );
        }
        println!(
            "model: {} faces, deviation {:.3} m",
            summary.model_faces, summary.model_mean_deviation_m
        );
        // A 3 × 3 contact sheet of the first photos (or of `$ASGREG_SYNTH_SHEET`, e.g. "0,4,8"),
        // as PNG, for looking at them.
        let (w, h) = (config.width_px, config.height_px);
        let chosen: Vec<usize> = std::env::var("ASGREG_SYNTH_SHEET")
            .map(|list| {
                list.split(',')
                    .filter_map(|k| k.trim().parse().ok())
                    .collect()
            })
            .unwrap_or_else(|_| (0..9).collect());
        let columns = chosen.len().clamp(1, 3) as u32;
        let rows = chosen.len().div_ceil(3).max(1) as u32;
        let mut sheet = image::RgbImage::new(w * columns, h * rows);
        for (k, &index) in chosen.iter().enumerate() {
            let Some(info) = summary.images.get(index) else {
                continue;
            };
            let photo = image::open(Path::new(&out).join("images").join(&info.name))
                .unwrap()
                .to_rgb8();
            let k = k as u32;
            image::imageops::replace(
                &mut sheet,
                &photo,
                i64::from(w * (k % columns)),
                i64::from(h * (k / columns)),
            );
        }
        sheet
            .save(Path::new(&out).join("contact_sheet.png"))
            .unwrap();
        // The first chosen image's depth map and the degraded model's ASG under its true pose.
        let first = &summary.images[chosen
            .first()
            .copied()
            .unwrap_or(0)
            .min(summary.images.len() - 1)];
        let depth = crate::io::pfm::read_pfm(
            &Path::new(&out)
                .join("depth")
                .join(Path::new(&first.name).with_extension("pfm")),
        )
        .unwrap();
        let max_depth = depth
            .data()
            .iter()
            .copied()
            .fold(0.0f32, f32::max)
            .max(1e-3);
        let depth_png = image::GrayImage::from_fn(w, h, |c, r| {
            let d = depth.data()[(r * w + c) as usize];
            image::Luma([if d > 0.0 {
                (255.0 * (1.0 - d / max_depth)).clamp(1.0, 255.0) as u8
            } else {
                0
            }])
        });
        depth_png
            .save(Path::new(&out).join("depth_first.png"))
            .unwrap();
        let model = crate::io::ply::read_ply(&Path::new(&out).join("model.ply")).unwrap();
        let gt = crate::io::colmap::read_model(&Path::new(&out).join("gt")).unwrap();
        let pose = gt.image_by_name(&first.name).unwrap().cam_from_world;
        let asg = asg_of(&model, &config.camera(), &pose, NormalSource::Vertex);
        let max_asg = asg.iter().copied().fold(0.0f32, f32::max).max(1e-6);
        let asg_png = image::GrayImage::from_fn(w, h, |c, r| {
            image::Luma([(255.0 * (asg[(r * w + c) as usize] / max_asg * 3.0).min(1.0)) as u8])
        });
        asg_png
            .save(Path::new(&out).join("model_asg_first.png"))
            .unwrap();
    }
}
