//! `asgreg changes`: change detection on registered photos against the model (`core::change`):
//! per image a mask PNG (grey levels of `ChangeClass::mask_value`) and an overlay PNG (added
//! red, removed blue over the photo), `changes.geojson` (fused footprints in the model's
//! georeferenced frame, with kind, area, height, frames, confirmed) and `report.json` (per-frame
//! summary, fused objects, the free-space test of the `added` ones
//! (`core::change::free_space`), settings, time per frame) and `report.html` (`report_html`: per
//! frame the model and the change classes over the photo). `eval --changes` runs the same
//! function.
//! Depth: the given maps (`--depth`, e.g. MVS) or, without `--depth`, plane-sweep stereo of each
//! frame against its nearest registered frames (`core::change::stereo`), written to `depth/`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use asgreg::core::change::free_space::{fuse_and_check, FreeSpaceCheck, SeenFrame};
use asgreg::core::change::fusion::{FusedChange, FusionConfig};
use asgreg::core::change::stereo::{
    choose_neighbours, depth_from_neighbours, NeighbourConfig, PosedCamera, RankingPhotos,
    StereoConfig, StereoView,
};
use asgreg::core::change::{
    classes_to_mask, detect_changes, BeyondTheModel, ChangeClass, ChangeConfig, ChangeRegion,
    ChangeWorkspace, ClassCounts, DepthEvidence,
};
use asgreg::core::image::Image;
use asgreg::frame_files::{depth_path_for, FrameFiles, FrameLoader};
use asgreg::io::images::{save_gray_png, save_rgb_png};
use asgreg::io::pfm::write_pfm;
use serde::Serialize;

use asgreg::report_html::{
    write_report_html, FrameVerdict, Picture, ReportFrame, ReportPage, THUMBNAIL_WIDTH_PX,
};

use super::inputs::load_posed_inputs;
use super::overlay::{working_overlays, OverlayView};
use super::register::REPORT_HTML;

#[derive(clap::Args, Debug, Clone)]
pub struct ChangesArgs {
    /// The model (PLY or OBJ; georeferenced coordinates are kept in f64).
    #[arg(long)]
    pub mesh: PathBuf,
    /// Folder of the photos (names as in the poses).
    #[arg(long)]
    pub images: PathBuf,
    /// COLMAP cameras (cameras.txt/.bin or a model folder).
    #[arg(long)]
    pub cameras: PathBuf,
    /// COLMAP poses of the photos, registered (images.txt/.bin or a model folder).
    #[arg(long)]
    pub poses: PathBuf,
    /// Folder of depth maps `<image stem>.pfm` (MVS, metres along the optical axis, holes 0).
    /// Without it, each frame's depth is computed by plane-sweep stereo against its nearest
    /// registered frames (written to OUT/depth/).
    #[arg(long)]
    pub depth: Option<PathBuf>,
    #[command(flatten)]
    pub stereo: StereoArgs,
    /// Output folder (created): masks/, overlays/, changes.geojson, report.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Least surface area of a region, m².
    #[arg(long, default_value_t = ChangeConfig::default().min_area_m2)]
    pub min_area_m2: f64,
    /// A region must extend at least this far in two of: vertical extent, footprint width,
    /// footprint length (m).
    #[arg(long, default_value_t = ChangeConfig::default().min_extent_m)]
    pub min_extent_m: f64,
    /// Threshold in standard deviations of the depth-difference noise model.
    #[arg(long, default_value_t = ChangeConfig::default().threshold_sigmas)]
    pub threshold_sigmas: f32,
    /// Relative depth error of the depth maps (σ_rel).
    #[arg(long, default_value_t = ChangeConfig::default().relative_sigma)]
    pub relative_sigma: f32,
    /// The model's deviation from the world, metres (σ_model).
    #[arg(long, default_value_t = ChangeConfig::default().model_sigma_m)]
    pub model_sigma_m: f32,
    /// A changed pixel whose depth agrees with the model's within this many pixels is
    /// unchanged (MVS edge fattening, a pose a pixel off); 0: pixel by pixel.
    #[arg(long, default_value_t = ChangeConfig::default().edge_tolerance_px)]
    pub edge_tolerance_px: usize,
    /// The poses' error as an image displacement u, px, for every frame: each pixel's
    /// threshold gets the depth difference a pose u px off could cause (|∇ model depth|·u) in
    /// quadrature; 0: exact poses (ground truth). A frame listed in --registration-report
    /// takes its own u from there instead.
    #[arg(long, default_value_t = ChangeConfig::default().pose_sigma_px)]
    pub pose_sigma_px: f32,
    /// The report.json of the `asgreg register` run that made --poses: each frame's u (see
    /// --pose-sigma-px) is its registration's own uncertainty
    /// (`core::change::pose_sigma_px_of_registration`).
    #[arg(long)]
    pub registration_report: Option<PathBuf>,
    /// Keep the registration's u (--pose-sigma-px, --registration-report) instead of measuring
    /// it per frame from the depth maps (the shift that aligns the model's rendered depth with
    /// the photo's, `core::change::depth_misalignment`; registered poses only).
    #[arg(long)]
    pub no_pose_sigma_from_depth: bool,
    /// Footprints closer than this are one object, metres.
    #[arg(long, default_value_t = FusionConfig::default().merge_distance_m)]
    pub merge_distance_m: f64,
    /// Frames needed to confirm an object.
    #[arg(long, default_value_t = FusionConfig::default().min_frames)]
    pub min_frames: usize,
    /// Use only the first N images of the poses.
    #[arg(long)]
    pub limit: Option<usize>,
}

pub use asgreg::core::change::stereo::DEFAULT_DISPARITY_SIGMA_PX;

/// The stereo depth's settings (`changes` without `--depth`, `eval --changes --depth-source
/// stereo`): one declaration flattened into both commands, so their flags and defaults are the
/// same.
#[derive(clap::Args, Debug, Clone, PartialEq)]
pub struct StereoArgs {
    /// Stereo depth: neighbour frames per stereo depth map (1–4).
    #[arg(long, default_value_t = NeighbourConfig::default().count)]
    pub stereo_neighbours: usize,
    /// Stereo depth: rank this many candidate neighbours (the nearest qualifying frames) by their
    /// agreement with the model (each swept against the frame alone, its depth's inverse-depth
    /// spread against the model's) and keep the best --stereo-neighbours of them, so a frame is
    /// not matched against a neighbour whose registered pose is pixels off relative to it
    /// (`core::change::stereo::rank_by_model_agreement`; 0 or not above --stereo-neighbours:
    /// off, the nearest; at most 12; each candidate costs a plane sweep).
    #[arg(long, default_value_t = NeighbourConfig::default().candidates)]
    pub stereo_candidates: usize,
    /// Stereo depth: integer downsampling of the photos for the plane sweep (1 = full size).
    #[arg(long, default_value_t = StereoConfig::default().downsample)]
    pub stereo_downsample: usize,
    /// Stereo depth: half side of the ZNCC window, working pixels.
    #[arg(long, default_value_t = StereoConfig::default().window_radius_px)]
    pub stereo_window_radius_px: usize,
    /// Stereo depth: a second cost minimum must be this much above the best (1 − ZNCC).
    #[arg(long, default_value_t = StereoConfig::default().uniqueness_margin)]
    pub stereo_uniqueness_margin: f32,
    /// Stereo depth: least grey standard deviation of a window (0..1 grey).
    #[arg(long, default_value_t = StereoConfig::default().min_texture)]
    pub stereo_min_texture: f32,
    /// Stereo depth: the texture test against the photo's noise, one-sided normal quantile of
    /// its χ² test over the window and over its centre (3.09: p = 0.001; 0: no test).
    #[arg(long, default_value_t = StereoConfig::default().sweep_texture_z)]
    pub stereo_sweep_texture_z: f32,
    /// Stereo depth: half side of the centre window of that test, working pixels (0: the
    /// whole window only).
    #[arg(long, default_value_t = StereoConfig::default().centre_radius_px)]
    pub stereo_centre_radius_px: usize,
    /// Stereo depth: the model test's texture test against the photo's noise (normal
    /// quantile; 0: min_texture only).
    #[arg(long, default_value_t = StereoConfig::default().model_test_texture_z)]
    pub stereo_model_test_texture_z: f32,
    /// Stereo depth: the model test judges a pixel on its own model surface only, this far
    /// (working px) from the model's depth edges (0: the whole visible window, as before).
    #[arg(long, default_value_t = StereoConfig::default().model_test_edge_px)]
    pub stereo_model_test_edge_px: usize,
    /// Stereo depth: largest accepted cost 1 − ZNCC.
    #[arg(long, default_value_t = StereoConfig::default().max_cost)]
    pub stereo_max_cost: f32,
    /// Stereo depth: keep depths the left-right check cannot confirm (drop only contradicted).
    #[arg(long)]
    pub stereo_keep_unconfirmed: bool,
    /// Stereo depth: fill holes from their (2r+1)² working neighbourhood when it agrees.
    #[arg(long, default_value_t = StereoConfig::default().fill_radius_px)]
    pub stereo_fill_radius_px: usize,
    /// Stereo depth: skip the left-right check against the neighbours' own depths.
    #[arg(long)]
    pub stereo_no_left_right: bool,
    /// Stereo depth: how many neighbours (the first ones) get a sweep back for the
    /// left-right check; a depth stays when one of them confirms it and none sees through it
    /// (default: all; 1: the first neighbour only, see docs/measurements.md, branches `change13`,
    /// `change12`).
    #[arg(long, default_value_t = StereoConfig::default().consistency_neighbours)]
    pub stereo_consistency_neighbours: usize,
    /// Stereo depth: keep depths no neighbour confirms but one sees occluded (and none sees
    /// through); off by default (a depth too far looks occluded too).
    #[arg(long)]
    pub stereo_keep_occluded: bool,
    /// Stereo depth: the model test's threshold, standard errors of Fisher's z: no change
    /// where the sweep's cost at the photo's depth does not beat its cost at the model's depth
    /// by more (0: no test).
    #[arg(long, default_value_t = StereoConfig::default().model_test_sigmas)]
    pub stereo_model_test_sigmas: f32,
    /// Stereo depth: disparity error of the stereo depth, working pixels; sets the change
    /// threshold's stereo term σ_quad = σ_disparity / (f·B) per frame.
    #[arg(long, default_value_t = DEFAULT_DISPARITY_SIGMA_PX)]
    pub stereo_disparity_sigma_px: f64,
    /// Stereo depth: keep the stereo term σ_quad of the disparity error alone under
    /// registered poses instead of raising it to the stereo map's own inverse-depth spread
    /// against the model (`core::change::inverse_depth_spread_per_m`: the neighbours' pose
    /// errors are disparity errors too).
    #[arg(long, alias = "change-no-stereo-sigma-from-depth")]
    pub no_stereo_sigma_from_depth: bool,
    /// Stereo depth: σ_rel of the stereo depth maps (--relative-sigma is the given maps').
    #[arg(long, alias = "change-stereo-relative-sigma", default_value_t = ChangeConfig::default().stereo_relative_sigma)]
    pub stereo_relative_sigma: f32,
}

impl Default for StereoArgs {
    fn default() -> Self {
        let stereo = StereoConfig::default();
        let change = ChangeConfig::default();
        Self {
            stereo_neighbours: NeighbourConfig::default().count,
            stereo_candidates: NeighbourConfig::default().candidates,
            stereo_downsample: stereo.downsample,
            stereo_window_radius_px: stereo.window_radius_px,
            stereo_uniqueness_margin: stereo.uniqueness_margin,
            stereo_min_texture: stereo.min_texture,
            stereo_sweep_texture_z: stereo.sweep_texture_z,
            stereo_centre_radius_px: stereo.centre_radius_px,
            stereo_model_test_texture_z: stereo.model_test_texture_z,
            stereo_model_test_edge_px: stereo.model_test_edge_px,
            stereo_max_cost: stereo.max_cost,
            stereo_keep_unconfirmed: stereo.keep_unconfirmed,
            stereo_fill_radius_px: stereo.fill_radius_px,
            stereo_no_left_right: !stereo.left_right_check,
            stereo_consistency_neighbours: stereo.consistency_neighbours,
            stereo_keep_occluded: stereo.keep_occluded,
            stereo_model_test_sigmas: stereo.model_test_sigmas,
            stereo_disparity_sigma_px: DEFAULT_DISPARITY_SIGMA_PX,
            no_stereo_sigma_from_depth: !change.stereo_sigma_from_depth,
            stereo_relative_sigma: change.stereo_relative_sigma,
        }
    }
}

impl StereoArgs {
    pub fn stereo_config(&self) -> StereoConfig {
        StereoConfig {
            downsample: self.stereo_downsample,
            window_radius_px: self.stereo_window_radius_px,
            uniqueness_margin: self.stereo_uniqueness_margin,
            min_texture: self.stereo_min_texture,
            sweep_texture_z: self.stereo_sweep_texture_z,
            model_test_texture_z: self.stereo_model_test_texture_z,
            model_test_edge_px: self.stereo_model_test_edge_px,
            centre_radius_px: self.stereo_centre_radius_px,
            max_cost: self.stereo_max_cost,
            left_right_check: !self.stereo_no_left_right,
            consistency_neighbours: self.stereo_consistency_neighbours,
            keep_unconfirmed: self.stereo_keep_unconfirmed,
            keep_occluded: self.stereo_keep_occluded,
            model_test_sigmas: self.stereo_model_test_sigmas,
            fill_radius_px: self.stereo_fill_radius_px,
            ..StereoConfig::default()
        }
    }

    pub fn neighbour_config(&self) -> NeighbourConfig {
        NeighbourConfig {
            count: self.stereo_neighbours,
            candidates: self.stereo_candidates,
            ..NeighbourConfig::default()
        }
    }
}

impl ChangesArgs {
    /// The same settings with every other option at its default.
    pub fn with_defaults(
        mesh: PathBuf,
        images: PathBuf,
        cameras: PathBuf,
        poses: PathBuf,
        depth: Option<PathBuf>,
        out: PathBuf,
    ) -> Self {
        let change = ChangeConfig::default();
        let fusion = FusionConfig::default();
        Self {
            mesh,
            images,
            cameras,
            poses,
            depth,
            stereo: StereoArgs::default(),
            out,
            min_area_m2: change.min_area_m2,
            min_extent_m: change.min_extent_m,
            threshold_sigmas: change.threshold_sigmas,
            relative_sigma: change.relative_sigma,
            model_sigma_m: change.model_sigma_m,
            edge_tolerance_px: change.edge_tolerance_px,
            pose_sigma_px: change.pose_sigma_px,
            registration_report: None,
            no_pose_sigma_from_depth: false,
            merge_distance_m: fusion.merge_distance_m,
            min_frames: fusion.min_frames,
            limit: None,
        }
    }

    pub fn change_config(&self) -> ChangeConfig {
        ChangeConfig {
            min_area_m2: self.min_area_m2,
            min_extent_m: self.min_extent_m,
            threshold_sigmas: self.threshold_sigmas,
            relative_sigma: self.relative_sigma,
            model_sigma_m: self.model_sigma_m,
            edge_tolerance_px: self.edge_tolerance_px,
            pose_sigma_px: self.pose_sigma_px,
            stereo_relative_sigma: self.stereo.stereo_relative_sigma,
            pose_sigma_from_depth: !self.no_pose_sigma_from_depth,
            stereo_sigma_from_depth: !self.stereo.no_stereo_sigma_from_depth,
            ..ChangeConfig::default()
        }
    }

    pub fn fusion_config(&self) -> FusionConfig {
        FusionConfig {
            merge_distance_m: self.merge_distance_m,
            min_frames: self.min_frames,
        }
    }
}

/// The names of report frames by index, comma-separated.
fn frame_names(frames: &[FrameChangeReport], indices: &[usize]) -> String {
    indices
        .iter()
        .filter_map(|&i| frames.get(i).map(|f| f.name.as_str()))
        .collect::<Vec<_>>()
        .join(", ")
}

/// One frame's summary in report.json.
#[derive(Clone, Debug, Serialize)]
pub struct FrameChangeReport {
    pub name: String,
    /// None when the frame has a result; else why there is none.
    pub failure: Option<String>,
    pub counts: ClassCounts,
    pub regions: Vec<ChangeRegion>,
    /// Render + compare + regions, milliseconds.
    pub detect_ms: f64,
    /// The pose error u the threshold allowed for (`--pose-sigma-px`, `--registration-report`).
    pub pose_sigma_px: f32,
    /// The stereo term σ_quad the threshold used, per metre (0: given depth;
    /// `core::change::frame_quadratic_sigma_per_m`).
    pub quadratic_sigma_per_m: f32,
    /// `removed` regions dropped as below the model's ground (`core::change::beyond_the_model`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub beyond_the_model: Vec<BeyondTheModel>,
    /// How the frame's depth was computed, when by stereo.
    pub stereo: Option<FrameStereoReport>,
}

/// A frame's stereo depth in report.json.
#[derive(Clone, Debug, Serialize)]
pub struct FrameStereoReport {
    pub neighbours: Vec<String>,
    /// With --stereo-candidates: every candidate ranked, best first, with its stereo depth's
    /// inverse-depth spread against the model (per metre; null: no depth to compare).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub ranked_candidates: Vec<(String, Option<f32>)>,
    pub planes: usize,
    pub working_size_px: (usize, usize),
    pub mean_baseline_m: f64,
    pub valid_fraction: f64,
    pub holes: asgreg::core::change::stereo::HoleCounts,
    /// Working pixels whose depth differs from the model's and of those the ones the model
    /// test finds the model as plausible at (no change there) or cannot judge.
    pub model_test: asgreg::core::change::stereo::ModelTestCounts,
    /// σ_quad used for this frame's change threshold, per metre.
    pub quadratic_sigma_per_m: f64,
    pub stereo_ms: f64,
}

/// What `changes` found.
#[derive(Clone, Debug, Serialize)]
pub struct ChangesReport {
    pub config: ChangeConfig,
    pub fusion: FusionConfig,
    pub frames: Vec<FrameChangeReport>,
    /// Fused objects; `frames` index into [`Self::frames`].
    pub objects: Vec<FusedChange>,
    /// The free-space test of each `added` object fusion confirmed
    /// (`core::change::free_space`): the frames that see through it and those that agree;
    /// `object` indexes [`Self::objects`], the frames index [`Self::frames`].
    pub free_space: Vec<FreeSpaceCheck>,
    pub mean_detect_ms: f64,
    /// "given" (--depth) or "stereo".
    pub depth_source: &'static str,
    /// Stereo depth per frame, mean over the frames that have one, milliseconds.
    pub mean_stereo_ms: Option<f64>,
}

/// The stereo depth file of an image in `out` (written when `--depth` is not given).
pub fn stereo_depth_path(out: &Path, image_name: &str) -> PathBuf {
    depth_path_for(&out.join("depth"), image_name)
}

/// The mask file of an image in `out`.
pub fn mask_path(out: &Path, image_name: &str) -> PathBuf {
    out.join("masks")
        .join(Path::new(image_name).with_extension("png"))
}

/// Runs change detection over every posed image and writes the outputs into `args.out`; the
/// report, and the mesh, cameras and poses it read (for a caller that measures them further).
pub fn detect_all(
    args: &ChangesArgs,
) -> anyhow::Result<(ChangesReport, super::inputs::PosedInputs)> {
    let config = args.change_config();
    config
        .validate()
        .context("check --min-area-m2, --threshold-sigmas, --relative-sigma, --model-sigma-m")?;
    let stereo_config = args.stereo.stereo_config();
    if args.depth.is_none() {
        stereo_config
            .validate()
            .context("check the --stereo-* options")?;
        args.stereo
            .neighbour_config()
            .validate()
            .context("check --stereo-neighbours and --stereo-candidates")?;
    }
    let fusion = args.fusion_config();
    let inputs = load_posed_inputs(&args.mesh, &args.cameras, &args.poses)?;
    let registered_pose_sigmas = match &args.registration_report {
        Some(path) => registration_pose_sigmas(path)?,
        None => std::collections::HashMap::new(),
    };
    let mut dirs = vec!["masks", "overlays"];
    if args.depth.is_none() {
        dirs.push("depth");
    }
    for dir in dirs {
        let dir = args.out.join(dir);
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create the output folder {}", dir.display()))?;
    }
    let loader = FrameLoader::new(None);
    // Stereo: every posed frame's photo, loaded once (the neighbours of each reference).
    let posed_frames: Vec<Result<FrameFiles, String>> = if args.depth.is_none() {
        inputs
            .images
            .iter()
            .map(|image| {
                let camera = inputs.cameras.get(&image.camera_id).ok_or_else(|| {
                    format!(
                        "camera {} is not in {}",
                        image.camera_id,
                        args.cameras.display()
                    )
                })?;
                loader
                    .load(
                        &args.images.join(&image.name),
                        image.camera_id,
                        camera,
                        None,
                    )
                    .map_err(|e| e.to_string())
            })
            .collect()
    } else {
        Vec::new()
    };
    let posed_cameras: Vec<Option<PosedCamera>> = posed_frames
        .iter()
        .zip(&inputs.images)
        .map(|(files, image)| {
            files.as_ref().ok().map(|files| PosedCamera {
                intrinsics: files.camera.intrinsics,
                width_px: files.photo.width_px(),
                height_px: files.photo.height_px(),
                cam_from_world: image.cam_from_world,
            })
        })
        .collect();
    let mut workspace = ChangeWorkspace::new();
    let mut classes: Image<ChangeClass> = Image::default();
    let mut mask = Image::default();
    let mut frames = Vec::new();
    // What each frame with a change map saw, for the free-space test of the fused objects.
    let mut seen: Vec<(usize, SeenFrame)> = Vec::new();
    let mut page_pictures: Vec<(String, Vec<Picture>)> = Vec::new();
    let limit = args.limit.unwrap_or(usize::MAX);
    for (index, image) in inputs.images.iter().enumerate().take(limit) {
        let failed = |why: String| FrameChangeReport {
            name: image.name.clone(),
            failure: Some(why),
            counts: ClassCounts::default(),
            regions: Vec::new(),
            detect_ms: 0.0,
            pose_sigma_px: 0.0,
            quadratic_sigma_per_m: 0.0,
            beyond_the_model: Vec::new(),
            stereo: None,
        };
        let Some(camera) = inputs.cameras.get(&image.camera_id) else {
            frames.push(failed(format!(
                "camera {} is not in {}",
                image.camera_id,
                args.cameras.display()
            )));
            continue;
        };
        let image_path = args.images.join(&image.name);
        let mut loaded: Option<FrameFiles> = None;
        let config = ChangeConfig {
            pose_sigma_px: registered_pose_sigmas
                .get(&image.name)
                .copied()
                .unwrap_or(config.pose_sigma_px),
            ..config
        };
        let (depth, stereo, model_plausible, frame_config) = match &args.depth {
            Some(depth_dir) => {
                let depth_path = depth_path_for(depth_dir, &image.name);
                let mut files = match loader.load(
                    &image_path,
                    image.camera_id,
                    camera,
                    Some(depth_path.as_path()),
                ) {
                    Ok(files) => files,
                    Err(error) => {
                        tracing::warn!("{}: no change result: {error}", image.name);
                        frames.push(failed(error.to_string()));
                        continue;
                    }
                };
                let Some(depth) = files.depth_m.take() else {
                    frames.push(failed(format!("no depth map at {}", depth_path.display())));
                    continue;
                };
                loaded = Some(files);
                (depth, None, None, config)
            }
            None => {
                if let Err(error) = &posed_frames[index] {
                    tracing::warn!("{}: no change result: {error}", image.name);
                    frames.push(failed(error.clone()));
                    continue;
                }
                match stereo_depth(
                    args,
                    &inputs,
                    &posed_frames,
                    &posed_cameras,
                    index,
                    &stereo_config,
                ) {
                    Ok((depth, plausible, report)) => {
                        let path = stereo_depth_path(&args.out, &image.name);
                        write_pfm(&path, depth.view())
                            .with_context(|| format!("cannot write {}", path.display()))?;
                        let frame_config = config.for_stereo(report.quadratic_sigma_per_m as f32);
                        (depth, Some(report), Some(plausible), frame_config)
                    }
                    Err(why) => {
                        tracing::warn!("{}: no change result: {why}", image.name);
                        frames.push(failed(why));
                        continue;
                    }
                }
            }
        };
        let files = match (&loaded, &posed_frames.get(index)) {
            (Some(files), _) | (None, Some(Ok(files))) => files,
            _ => continue,
        };
        let started = Instant::now();
        let result = detect_changes(
            &inputs.mesh,
            &files.camera.intrinsics,
            &image.cam_from_world,
            depth.view(),
            &DepthEvidence {
                model_plausible: model_plausible.as_ref().map(|m| m.view()),
            },
            &frame_config,
            &mut workspace,
            &mut classes,
        );
        let detect_ms = started.elapsed().as_secs_f64() * 1e3;
        let changes = match result {
            Ok(changes) => changes,
            Err(error) => {
                frames.push(failed(error.to_string()));
                continue;
            }
        };
        classes_to_mask(classes.view(), &mut mask);
        let mask_grey = mask.map(|v| f32::from(*v) / 255.0);
        let path = mask_path(&args.out, &image.name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        save_gray_png(&path, mask_grey.view())?;
        let overlay = asgreg::viz::overlay_changes(files.photo.view(), classes.view(), 0.55)
            .with_context(|| format!("{}: overlay", image.name))?;
        let overlay_path = args
            .out
            .join("overlays")
            .join(Path::new(&image.name).with_extension("png"));
        if let Some(parent) = overlay_path.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        save_rgb_png(&overlay_path, overlay.view())?;
        let mut pictures = Vec::new();
        match working_overlays(
            &inputs.mesh,
            &loader,
            &image_path,
            image.camera_id,
            camera,
            &[OverlayView {
                label: "model",
                camera: None,
                cam_from_world: image.cam_from_world,
            }],
        ) {
            Ok(model) => {
                for (label, picture) in &model {
                    pictures.push(Picture::from_rgb(
                        &image.name,
                        label,
                        picture.view(),
                        THUMBNAIL_WIDTH_PX,
                    )?);
                }
            }
            Err(error) => tracing::warn!("{}: no model overlay: {error:#}", image.name),
        }
        pictures.push(Picture::from_rgb(
            &image.name,
            "changes",
            overlay.view(),
            THUMBNAIL_WIDTH_PX,
        )?);
        page_pictures.push((image.name.clone(), pictures));
        tracing::info!(
            "{}: {} regions ({} added, {} removed px, u {:.1} px) in {detect_ms:.1} ms",
            image.name,
            changes.regions.len(),
            changes.counts.added,
            changes.counts.removed,
            changes.pose_sigma_px
        );
        for dropped in &changes.beyond_the_model {
            tracing::info!(
                "{}: removed region of {} px at ({:.1}, {:.1}) dropped: its photo depth lies \
                 {:.1} m (median) under the model's ground at z {:.1} m, {:.1} m beyond it \
                 along the ray ({:.0} % of its pixels beyond the threshold)",
                image.name,
                dropped.pixel_count,
                dropped.centroid_m[0],
                dropped.centroid_m[1],
                dropped.median_below_ground_m,
                dropped.ground_z_m,
                dropped.median_beyond_ground_m,
                100.0 * dropped.share_below
            );
        }
        seen.push((
            frames.len(),
            SeenFrame::new(
                files.camera.intrinsics,
                image.cam_from_world,
                depth,
                workspace.model_rendering().depth_m().clone(),
                changes.settings(&frame_config),
            ),
        ));
        frames.push(FrameChangeReport {
            name: image.name.clone(),
            failure: None,
            counts: changes.counts,
            regions: changes.regions,
            detect_ms,
            pose_sigma_px: changes.pose_sigma_px,
            quadratic_sigma_per_m: changes.quadratic_sigma_per_m,
            beyond_the_model: changes.beyond_the_model,
            stereo,
        });
    }
    let regions: Vec<(usize, &ChangeRegion)> = frames
        .iter()
        .enumerate()
        .flat_map(|(index, frame)| frame.regions.iter().map(move |r| (index, r)))
        .collect();
    let (objects, free_space) = fuse_and_check(&regions, &fusion, seen.as_mut_slice());
    for check in free_space.iter().filter(|c| c.refuted) {
        tracing::info!(
            "added object at ({:.1}, {:.1}, {:.1}) not confirmed: {} frames see through it ({}), {} agree ({})",
            check.centroid_m[0],
            check.centroid_m[1],
            check.centroid_m[2],
            check.seen_through_by.len(),
            frame_names(&frames, &check.seen_through_by),
            check.agreed_by.len(),
            frame_names(&frames, &check.agreed_by),
        );
    }
    let timed: Vec<f64> = frames
        .iter()
        .filter(|f| f.failure.is_none())
        .map(|f| f.detect_ms)
        .collect();
    let stereo_ms: Vec<f64> = frames
        .iter()
        .filter_map(|f| f.stereo.as_ref().map(|s| s.stereo_ms))
        .collect();
    let report = ChangesReport {
        config,
        fusion,
        depth_source: if args.depth.is_some() {
            "given"
        } else {
            "stereo"
        },
        mean_stereo_ms: (!stereo_ms.is_empty())
            .then(|| stereo_ms.iter().sum::<f64>() / stereo_ms.len() as f64),
        mean_detect_ms: timed.iter().sum::<f64>() / timed.len().max(1) as f64,
        frames,
        objects,
        free_space,
    };
    let geojson = geojson(&report);
    let geojson_path = args.out.join("changes.geojson");
    std::fs::write(&geojson_path, serde_json::to_string_pretty(&geojson)?)
        .with_context(|| format!("cannot write {}", geojson_path.display()))?;
    let report_path = args.out.join("report.json");
    std::fs::write(&report_path, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("cannot write {}", report_path.display()))?;
    write_report_html(
        &args.out.join(REPORT_HTML),
        &report_page(args, &report, page_pictures),
    )?;
    Ok((report, inputs))
}

/// Each frame's pose error u (px) from the report.json of the `asgreg register` run that made
/// the poses: `core::change::pose_sigma_px_of_registration` of its verify group's spread.
fn registration_pose_sigmas(path: &Path) -> anyhow::Result<std::collections::HashMap<String, f32>> {
    #[derive(serde::Deserialize)]
    struct Report {
        frames: Vec<Frame>,
    }
    #[derive(serde::Deserialize)]
    struct Frame {
        name: String,
        mean_delta_to_chosen_px: f64,
    }
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the registration report {}", path.display()))?;
    let report: Report = serde_json::from_str(&text).with_context(|| {
        format!(
            "{} is not an `asgreg register` report.json (frames with name and mean_delta_to_chosen_px)",
            path.display()
        )
    })?;
    Ok(report
        .frames
        .into_iter()
        .map(|f| {
            (
                f.name,
                asgreg::core::change::pose_sigma_px_of_registration(f.mean_delta_to_chosen_px),
            )
        })
        .collect())
}

/// Frame `index`'s depth by plane-sweep stereo against its nearest registered frames; the
/// error says why there is none.
fn stereo_depth(
    args: &ChangesArgs,
    inputs: &super::inputs::PosedInputs,
    frames: &[Result<FrameFiles, String>],
    cameras: &[Option<PosedCamera>],
    index: usize,
    config: &StereoConfig,
) -> Result<(Image<f32>, Image<bool>, FrameStereoReport), String> {
    let name = &inputs.images[index].name;
    let (Some(reference), Ok(files)) = (&cameras[index], &frames[index]) else {
        return Err(format!("{name}: the photo could not be loaded"));
    };
    let (candidate_index, candidates): (Vec<usize>, Vec<PosedCamera>) = cameras
        .iter()
        .enumerate()
        .filter(|(other, _)| *other != index)
        .filter_map(|(other, camera)| camera.map(|c| (other, c)))
        .unzip();
    let photos = RankingPhotos {
        reference: files.photo.view(),
        candidates: candidate_index
            .iter()
            .map(|&k| frames[k].as_ref().ok().map(|f| f.photo.view()))
            .collect(),
        sweep: *config,
        prepared: None,
    };
    let choice = choose_neighbours(
        &inputs.mesh,
        reference,
        &candidates,
        &args.stereo.neighbour_config(),
        Some(&photos),
    )
    .map_err(|error| format!("{error}: give --depth or more frames"))?;
    let chosen: Vec<usize> = choice.chosen.iter().map(|&k| candidate_index[k]).collect();
    let ranked_candidates: Vec<(String, Option<f32>)> = choice
        .ranked
        .iter()
        .map(|&(k, score)| (inputs.images[candidate_index[k]].name.clone(), score))
        .collect();
    let view = |k: usize| -> Option<StereoView<'_>> {
        let files = frames[k].as_ref().ok()?;
        Some(StereoView {
            photo: files.photo.view(),
            intrinsics: files.camera.intrinsics,
            cam_from_world: inputs.images[k].cam_from_world,
        })
    };
    let neighbours: Vec<StereoView<'_>> = chosen.iter().filter_map(|&k| view(k)).collect();
    let reference_view = StereoView {
        photo: files.photo.view(),
        intrinsics: files.camera.intrinsics,
        cam_from_world: inputs.images[index].cam_from_world,
    };
    let started = Instant::now();
    let depth = depth_from_neighbours(&inputs.mesh, &reference_view, &neighbours, config)
        .map_err(|e| format!("stereo depth: {e}"))?;
    let stereo_ms = started.elapsed().as_secs_f64() * 1e3;
    tracing::info!(
        "{name}: stereo depth from {} neighbours, {} planes, {:.0} % valid in {stereo_ms:.0} ms; {} px off the model, {} of them model-plausible, {} untestable",
        neighbours.len(),
        depth.planes,
        100.0 * depth.valid_fraction,
        depth.model_test.differing,
        depth.model_test.plausible,
        depth.model_test.untestable
    );
    let report = FrameStereoReport {
        neighbours: chosen
            .iter()
            .map(|&k| inputs.images[k].name.clone())
            .collect(),
        ranked_candidates,
        planes: depth.planes,
        working_size_px: depth.working_size_px,
        mean_baseline_m: depth.mean_baseline_m,
        valid_fraction: depth.valid_fraction,
        holes: depth.holes,
        model_test: depth.model_test,
        quadratic_sigma_per_m: depth.quadratic_sigma_per_m(args.stereo.stereo_disparity_sigma_px),
        stereo_ms,
    };
    Ok((depth.depth_m, depth.model_plausible, report))
}

/// report.html of a change detection run: per frame the pixel counts, regions and time, the
/// model over the photo under its pose and the change classes over it (a slider between them).
fn report_page(
    args: &ChangesArgs,
    report: &ChangesReport,
    mut pictures: Vec<(String, Vec<Picture>)>,
) -> ReportPage {
    let frames = report
        .frames
        .iter()
        .map(|frame| {
            let index = pictures.iter().position(|(name, _)| *name == frame.name);
            let frame_pictures = index.map(|i| pictures.swap_remove(i).1).unwrap_or_default();
            ReportFrame {
                name: frame.name.clone(),
                group: None,
                verdict: if frame.failure.is_some() {
                    FrameVerdict::Failed
                } else {
                    FrameVerdict::Done
                },
                reason: frame.failure.clone(),
                confidence: None,
                initial_delta_px: None,
                delta_px: None,
                timings_ms: vec![("total (change map)".to_string(), frame.detect_ms)],
                details: vec![
                    ("regions".to_string(), frame.regions.len().to_string()),
                    ("added px".to_string(), frame.counts.added.to_string()),
                    ("removed px".to_string(), frame.counts.removed.to_string()),
                    ("unknown px".to_string(), frame.counts.unknown.to_string()),
                ],
                pictures: frame_pictures,
            }
        })
        .collect();
    ReportPage {
        command: "changes".to_string(),
        subject: args.images.display().to_string(),
        summary: vec![
            ("mesh".to_string(), args.mesh.display().to_string()),
            ("poses".to_string(), args.poses.display().to_string()),
            (
                "objects".to_string(),
                format!(
                    "{} ({} confirmed by ≥ {} frames), in changes.geojson",
                    report.objects.len(),
                    report.objects.iter().filter(|o| o.confirmed).count(),
                    report.fusion.min_frames
                ),
            ),
            (
                "change map".to_string(),
                format!("{:.1} ms per frame", report.mean_detect_ms),
            ),
        ],
        plots_svg: Vec::new(),
        frames,
    }
}

/// The fused objects as a GeoJSON FeatureCollection (coordinates: the model's frame).
fn geojson(report: &ChangesReport) -> serde_json::Value {
    let features: Vec<serde_json::Value> = report
        .objects
        .iter()
        .enumerate()
        .map(|(id, object)| {
            let mut ring: Vec<[f64; 2]> = object.footprint_m.clone();
            if let Some(first) = ring.first().copied() {
                ring.push(first);
            }
            let frames: Vec<&str> = object
                .frames
                .iter()
                .filter_map(|&f| report.frames.get(f).map(|r| r.name.as_str()))
                .collect();
            serde_json::json!({
                "type": "Feature",
                "id": id,
                "geometry": { "type": "Polygon", "coordinates": [ring] },
                "properties": {
                    "kind": object.kind.name(),
                    "area_m2": object.footprint_area_m2,
                    "height_m": object.height_m,
                    "centroid_m": object.centroid_m,
                    "frames": frames,
                    "frame_count": object.frames.len(),
                    "confirmed": object.confirmed,
                    "confidence": object.confidence,
                }
            })
        })
        .collect();
    serde_json::json!({ "type": "FeatureCollection", "features": features })
}

pub fn run(args: &ChangesArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let (report, _) = detect_all(args)?;
    let failed = report.frames.iter().filter(|f| f.failure.is_some()).count();
    println!(
        "{} frames ({} without a result), {:.1} ms per frame for the change map; {} objects ({} confirmed) in {:.1} s",
        report.frames.len(),
        failed,
        report.mean_detect_ms,
        report.objects.len(),
        report.objects.iter().filter(|o| o.confirmed).count(),
        started.elapsed().as_secs_f64()
    );
    for object in report.objects.iter().filter(|o| o.confirmed) {
        println!(
            "  {:<7} {:>7.1} m² footprint, {:>5.1} m high, at ({:.1}, {:.1}), {} frames, confidence {:.2}",
            object.kind.name(),
            object.footprint_area_m2,
            object.height_m,
            object.centroid_m[0],
            object.centroid_m[1],
            object.frames.len(),
            object.confidence
        );
    }
    if let Some(ms) = report.mean_stereo_ms {
        println!("depth by plane-sweep stereo: {ms:.0} ms per frame (written to depth/)");
    }
    println!(
        "wrote {}/masks, overlays, changes.geojson, report.json, report.html",
        args.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::super::{Cli, Command};
    use super::StereoArgs;

    /// Every stereo flag, each away from its default.
    const STEREO_FLAGS: [&str; 26] = [
        "--stereo-neighbours",
        "2",
        "--stereo-candidates",
        "9",
        "--stereo-downsample",
        "3",
        "--stereo-window-radius-px",
        "3",
        "--stereo-uniqueness-margin",
        "0.05",
        "--stereo-min-texture",
        "0.01",
        "--stereo-sweep-texture-z",
        "3.09",
        "--stereo-model-test-texture-z",
        "3.09",
        "--stereo-model-test-edge-px",
        "0",
        "--stereo-consistency-neighbours",
        "1",
        "--stereo-keep-occluded",
        "--stereo-no-left-right",
        "--no-stereo-sigma-from-depth",
        "--stereo-relative-sigma",
        "0.01",
        "--stereo-keep-unconfirmed",
    ];

    fn stereo_of(args: &[&str]) -> StereoArgs {
        let cli = Cli::try_parse_from(args).unwrap_or_else(|e| panic!("{args:?}: {e}"));
        match cli.command {
            Command::Changes(changes) => changes.stereo,
            Command::Eval(eval) => eval.stereo,
            other => panic!("parsed as {other:?}"),
        }
    }

    #[test]
    fn changes_and_eval_accept_the_same_stereo_flags_with_the_same_defaults() {
        let changes = [
            "asgreg",
            "changes",
            "--mesh",
            "m.ply",
            "--images",
            "i",
            "--cameras",
            "c.txt",
            "--poses",
            "p.txt",
            "--out",
            "o",
        ];
        let eval = ["asgreg", "eval", "--scene", "s", "--out", "o", "--changes"];
        // Defaults: the library's.
        assert_eq!(stereo_of(&changes), StereoArgs::default());
        assert_eq!(stereo_of(&eval), StereoArgs::default());
        // Every flag, both commands, the same values.
        let with = |base: &[&'static str]| -> Vec<&'static str> {
            base.iter().chain(STEREO_FLAGS.iter()).copied().collect()
        };
        let from_changes = stereo_of(&with(&changes));
        let from_eval = stereo_of(&with(&eval));
        assert_eq!(from_changes, from_eval);
        assert_ne!(from_changes, StereoArgs::default());
        assert_eq!(from_changes.stereo_neighbours, 2);
        assert_eq!(from_changes.neighbour_config().candidates, 9);
        assert_eq!(from_changes.stereo_consistency_neighbours, 1);
        assert!(from_changes.stereo_keep_occluded && from_changes.no_stereo_sigma_from_depth);
        let config = from_eval.stereo_config();
        assert_eq!(config.downsample, 3);
        assert!(!config.left_right_check && config.keep_unconfirmed);
        // eval's former names stay accepted.
        let old = stereo_of(
            &eval
                .iter()
                .chain(&[
                    "--change-stereo-relative-sigma",
                    "0.02",
                    "--change-no-stereo-sigma-from-depth",
                ])
                .copied()
                .collect::<Vec<_>>(),
        );
        assert_eq!(old.stereo_relative_sigma, 0.02);
        assert!(old.no_stereo_sigma_from_depth);
    }
}
