//! `asgreg eval`: the evaluation protocol of docs/design.md §3 on a scene folder (as `asgreg synth` writes
//! it): registration from every initial level with known and unknown intrinsics, δ to ground truth,
//! acceptance and false accepts; tables laid out like the paper's, JSON, an SVG plot, and
//! report.html (`report_html`: the plot and every frame run with its overlays).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use asgreg::baseline::icp::{
    register_depth_to_mesh, IcpConfig, IcpVariant, ICP_SUCCESS_THRESHOLD_PX,
};
use asgreg::batch::{
    neighbour_pass, register_batch_frame, BatchFrame, FrameReport, HeadingSweepReport, PassReport,
    RejectedCandidate,
};
use asgreg::core::camera::Camera;
use asgreg::core::confidence::FrameEvidence;
use asgreg::core::frame::{
    FrameInput, IntrinsicsMode, Pass, RegistrationConfig, RegistrationError, StageTimings,
};
use asgreg::core::mesh::Mesh;
use asgreg::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};
use asgreg::core::rigid::Rigid3;
use asgreg::diagnose::{
    diagnose_frame, diagnose_search, DiagnosisSummary, FrameDiagnosis, SearchDiagnosis, SearchLoss,
    ORACLE_MAX_ERROR_PX, REACH_RANK_LIMIT,
};
use asgreg::eval::{
    calibration_bins, cell_stats, format_accuracy, CalibrationBin, CellStats, EvalFrame,
    NeighbourEval, PassEval, SweepEval,
};
use asgreg::frame_files::depth_path_for;
use asgreg::io::colmap::{read_cameras_txt, read_images_txt, ImagePose};
use asgreg::io::mesh_file::read_mesh;
use asgreg::io::pfm::read_pfm;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use asgreg::frame_files::FrameLoader;
use asgreg::report_html::{write_report_html, FrameVerdict, Picture, ReportFrame, ReportPage};

use super::register::{
    frame_overlays, progress_bar, registration_config, report_frame, CoarseArgs, IntrinsicsArg,
    NeighbourOrderArg, QueryArg, REPORT_HTML,
};

/// The scene model registration is given ([`EvalArgs::model`]).
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ModelArg {
    Degraded,
    Lod,
    True,
}

impl ModelArg {
    /// The model's file in a scene folder written by `asgreg synth`; for the clean and the true
    /// model an error that says what to do when the scene has none (written before they were).
    pub fn path(self, scene: &std::path::Path) -> anyhow::Result<PathBuf> {
        let path = scene.join(match self {
            ModelArg::Degraded => "model.ply",
            ModelArg::Lod => "model_lod.ply",
            ModelArg::True => "model_true.ply",
        });
        if self != ModelArg::Degraded && !path.is_file() {
            bail!(
                "{} does not exist: --model {} needs a scene written by this version of `asgreg synth` (run it again), or pass --model degraded",
                path.display(),
                format!("{self:?}").to_lowercase()
            );
        }
        Ok(path)
    }
}

/// Width of eval's embedded overlays, px: a run has many frames (levels × methods).
const EVAL_THUMBNAIL_WIDTH_PX: usize = 320;

#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Scene folder: model.ply, images/, gt/, initial/<level>/images.txt, optionally depth/.
    #[arg(long)]
    pub scene: PathBuf,
    /// Which of the scene's models registration is given: the degraded, Poisson-like mesh
    /// (`model.ply`), the clean LoD2-like one (`model_lod.ply`: exact walls and roofs, no small
    /// parts) or the exact geometry (`model_true.ply`, a reference).
    #[arg(long, value_enum, default_value_t = ModelArg::Degraded)]
    pub model: ModelArg,
    /// Output folder for results.md, results.json and results.svg.
    #[arg(long)]
    pub out: PathBuf,
    /// Initial-error levels to run (folders under initial/): mean δ in px, or `heading` (a
    /// drone's prior: heading 10–40° or 180° off, GPS-like position; written by `asgreg synth`).
    #[arg(long, value_delimiter = ',', value_parser = parse_level, default_values_t = [Level::Px(30), Level::Px(57), Level::Px(80), Level::Px(104)])]
    pub levels: Vec<Level>,
    /// Intrinsics modes to run.
    #[arg(long, value_delimiter = ',', value_enum, default_values_t = [IntrinsicsArg::Known, IntrinsicsArg::Unknown])]
    pub intrinsics: Vec<IntrinsicsArg>,
    /// Query gradient image: the photo's gradient, the ASG of its depth map (needs depth/), or
    /// depth-ASG where the depth is valid and trustworthy and the photo's gradient elsewhere.
    #[arg(long, value_enum, default_value_t = QueryArg::Depth)]
    pub query: QueryArg,
    /// Use only the first N images of each level.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Use only these images (names as in the level's images.txt, comma-separated), e.g. one
    /// frame under --diagnose; applied before --limit.
    #[arg(long, value_delimiter = ',')]
    pub frames: Vec<String>,
    /// Seed of the registration's random draws.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[command(flatten)]
    pub coarse: CoarseArgs,
    /// Do not trust the `heading` level's pitch and roll: by default that level, a drone's prior,
    /// registers with its tilt trusted within the IMU error the scene was made with (scene.json's
    /// `config.heading_noise.tilt_max_deg`), as `register --prior-tilt-deg` does for a drone
    /// whose IMU is known; --prior-tilt-deg, when given, is used instead.
    #[arg(long)]
    pub untrusted_heading_tilt: bool,
    /// Skip the ICP baselines (point-to-plane and point-to-point on the photos' depth maps).
    #[arg(long)]
    pub no_icp: bool,
    /// Also split each registered frame's error into its parts against the ground truth (flow,
    /// lifting near depth edges, solver with an outlier-free oracle, choice in verification):
    /// diagnosis.md and diagnosis.json. The verdicts are the registration's own; slower (views
    /// one at a time, each solved twice).
    #[arg(long)]
    pub diagnose: bool,
    /// Run only each frame's pose search and measure it against the ground truth (its beams,
    /// centres, what a rotation-only search can reach, the truth's edge support and grid score):
    /// search_diagnosis.md and .json. No registration, so no verdicts; fast.
    #[arg(long, conflicts_with = "diagnose")]
    pub diagnose_search: bool,
    /// Evaluate change detection instead (a scene from `synth --changes`): pixel and object
    /// precision/recall against changes_gt/ and changes.json (eval_changes.rs).
    #[arg(long)]
    pub changes: bool,
    /// With --changes: the poses to detect under (a COLMAP images file or model folder, e.g.
    /// registered poses); the ground truth gt/ when not given.
    #[arg(long)]
    pub changes_poses: Option<PathBuf>,
    /// With --changes: the photos' depth: the scene's given MVS-like maps (depth/), or plane-sweep
    /// stereo from each frame's registered neighbours (also measured against depth/).
    #[arg(long, value_enum, default_value_t = DepthSourceArg::Given)]
    pub depth_source: DepthSourceArg,
    /// With --changes: `asgreg changes --edge-tolerance-px` (0: pixel by pixel).
    #[arg(long, default_value_t = asgreg::core::change::ChangeConfig::default().edge_tolerance_px)]
    pub change_edge_tolerance_px: usize,
    /// With --changes: `asgreg changes --pose-sigma-px` (the poses' error u, px; 0 = exact).
    #[arg(long, default_value_t = asgreg::core::change::ChangeConfig::default().pose_sigma_px)]
    pub change_pose_sigma_px: f32,
    /// With --changes: `asgreg changes --registration-report` (each frame's u from the
    /// registration that made --changes-poses); by default the report.json beside
    /// --changes-poses when there is one.
    #[arg(long)]
    pub change_registration_report: Option<PathBuf>,
    /// With --changes: `asgreg changes --no-pose-sigma-from-depth`.
    #[arg(long)]
    pub change_no_pose_sigma_from_depth: bool,
    /// With --changes --depth-source stereo: the stereo depth's settings, as `asgreg changes`'s.
    #[command(flatten)]
    pub stereo: super::changes::StereoArgs,
}

/// Where `eval --changes` takes the photos' depth from.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthSourceArg {
    Given,
    Stereo,
}

/// One initial-error level: a folder under `initial/`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Level {
    /// Gaussian noise on all six degrees of freedom with this mean δ, px (the paper's protocol).
    Px(u32),
    /// A drone's prior (`initial/heading/`).
    Heading,
}

impl std::fmt::Display for Level {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Level::Px(px) => f.pad(&px.to_string()),
            Level::Heading => f.pad(asgreg::synth::HEADING_LEVEL_DIR),
        }
    }
}

impl serde::Serialize for Level {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match self {
            Level::Px(px) => serializer.serialize_u32(*px),
            Level::Heading => serializer.serialize_str(asgreg::synth::HEADING_LEVEL_DIR),
        }
    }
}

fn parse_level(text: &str) -> Result<Level, String> {
    if text == asgreg::synth::HEADING_LEVEL_DIR {
        return Ok(Level::Heading);
    }
    text.parse::<u32>().map(Level::Px).map_err(|_| {
        format!(
            "{text:?} is not a level: a mean δ in whole pixels (30) or {:?}",
            asgreg::synth::HEADING_LEVEL_DIR
        )
    })
}

/// The tilt the `heading` level's prior is trusted within, degrees: --prior-tilt-deg when given,
/// else the IMU error the scene was made with (`config.heading_noise.tilt_max_deg` in
/// scene.json), none with --untrusted-heading-tilt or when the level is not run. A drone's pitch
/// and roll come from its IMU (gravity), so the level is registered as a drone would be; the
/// Gaussian px levels disturb all six degrees of freedom and trust nothing.
fn heading_level_tilt_deg(args: &EvalArgs) -> anyhow::Result<Option<f64>> {
    if !args.levels.contains(&Level::Heading) || args.untrusted_heading_tilt {
        return Ok(None);
    }
    if args.coarse.prior_tilt_deg > 0.0 {
        return Ok(Some(args.coarse.prior_tilt_deg));
    }
    let path = args.scene.join("scene.json");
    let text = std::fs::read_to_string(&path).with_context(|| {
        format!(
            "reading {} for the heading level's IMU tilt: pass --prior-tilt-deg (the prior's pitch/roll error, degrees) or --untrusted-heading-tilt",
            path.display()
        )
    })?;
    let summary: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{} is not JSON", path.display()))?;
    let tilt_deg = summary["config"]["heading_noise"]["tilt_max_deg"]
        .as_f64()
        .filter(|t| t.is_finite() && *t > 0.0)
        .with_context(|| {
            format!(
                "{} has no positive config.heading_noise.tilt_max_deg: pass --prior-tilt-deg (the heading level's pitch/roll error, degrees) or --untrusted-heading-tilt",
                path.display()
            )
        })?;
    eprintln!(
        "heading level: the prior's pitch and roll trusted within {tilt_deg}° (the scene's IMU error, {}; --untrusted-heading-tilt to search them as the px levels do)",
        path.display()
    );
    Ok(Some(tilt_deg))
}

/// Every name of --frames is among a level's images (read from `path`): a misspelt frame is an
/// error naming it and the file, not an empty evaluation.
fn check_frames_exist(frames: &[String], images: &[ImagePose], path: &Path) -> anyhow::Result<()> {
    if let Some(missing) = frames
        .iter()
        .find(|name| !images.iter().any(|image| &image.name == *name))
    {
        bail!(
            "--frames: {missing:?} is not in {} ({} images, e.g. {:?}); give names as that file spells them",
            path.display(),
            images.len(),
            images.first().map_or("none", |image| image.name.as_str())
        );
    }
    Ok(())
}

/// Step "neighbour"'s order for the scene (`--neighbour-order` when given): `feed` for a scene
/// made along a flight path (scene.json's `config.flight_path`, `synth --flight-path`: its
/// images.txt is the order the photos were taken in), else `set` — the photos of the other
/// scenes are drawn one by one, a collection without an order, and a scene without that key
/// says nothing of one.
fn scene_neighbour_order(args: &EvalArgs) -> anyhow::Result<NeighbourOrderArg> {
    if let Some(order) = args.coarse.neighbour_order {
        return Ok(order);
    }
    let path = args.scene.join("scene.json");
    let flight_path = match std::fs::read_to_string(&path) {
        Ok(text) => {
            let summary: serde_json::Value = serde_json::from_str(&text)
                .with_context(|| format!("{} is not JSON", path.display()))?;
            summary["config"]["flight_path"].as_bool().unwrap_or(false)
        }
        Err(error) if error.kind() == std::io::ErrorKind::NotFound => false,
        Err(error) => return Err(error).with_context(|| format!("reading {}", path.display())),
    };
    let (order, name, why) = if flight_path {
        (
            NeighbourOrderArg::Feed,
            "feed",
            "the scene's photos were taken along a flight path, in images.txt's order",
        )
    } else {
        (
            NeighbourOrderArg::Set,
            "set",
            "the scene's photos are a collection without an order: scene.json has no flight_path",
        )
    };
    eprintln!("step \"neighbour\": {name} order ({why}; --neighbour-order to choose)");
    Ok(order)
}

/// The coarse settings `level` registers with: the heading level's trusted tilt
/// ([`heading_level_tilt_deg`]) on it, the command line's elsewhere.
fn level_coarse(coarse: &CoarseArgs, level: Level, heading_tilt_deg: Option<f64>) -> CoarseArgs {
    match (level, heading_tilt_deg) {
        (Level::Heading, Some(tilt_deg)) => CoarseArgs {
            prior_tilt_deg: tilt_deg,
            ..*coarse
        },
        _ => *coarse,
    }
}

/// What registers a frame in an evaluation run.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Method {
    Asg(IntrinsicsArg),
    Icp(IcpVariant),
}

impl Method {
    fn name(self) -> &'static str {
        match self {
            Method::Asg(IntrinsicsArg::Known) => "known K",
            Method::Asg(IntrinsicsArg::Unknown) => "unknown K",
            Method::Asg(IntrinsicsArg::Focal) => "unknown focal",
            Method::Icp(IcpVariant::PointToPlane) => "ICP point-to-plane",
            Method::Icp(IcpVariant::PointToPoint) => "ICP point-to-point",
        }
    }
}

pub fn run(args: &EvalArgs) -> anyhow::Result<()> {
    if args.changes {
        if !args.frames.is_empty() {
            bail!("--frames selects frames to register; eval --changes uses --limit");
        }
        return super::eval_changes::run(args);
    }
    let model_path = args.model.path(&args.scene)?;
    let mesh = read_mesh(&model_path)?;
    let gt_cameras = read_cameras_txt(&args.scene.join("gt/cameras.txt"))?;
    let gt_images = read_images_txt(&args.scene.join("gt/images.txt"))?;
    let depth_dir = args.scene.join("depth");
    let query_mode = args.query.mode();
    let with_depth = query_mode.needs_depth();
    if with_depth && !depth_dir.is_dir() {
        bail!(
            "--query depth and --query mixed need the photos' depth maps in {}; pass --query gradient to use the photos' gradients",
            depth_dir.display()
        );
    }
    let longest_side_px = gt_cameras
        .values()
        .map(|c| c.longest_side_px())
        .max()
        .context("gt/cameras.txt defines no camera")?;
    let false_accept_px = 0.05 * f64::from(longest_side_px);

    let heading_tilt_deg = heading_level_tilt_deg(args)?;
    let neighbour_order = scene_neighbour_order(args)?;
    let mut jobs = Vec::new();
    for &level in &args.levels {
        let poses_path = args.scene.join(format!("initial/{level}/images.txt"));
        let initial = read_images_txt(&poses_path)?;
        check_frames_exist(&args.frames, &initial, &poses_path)?;
        let mut methods: Vec<Method> = args.intrinsics.iter().map(|i| Method::Asg(*i)).collect();
        if !args.no_icp && depth_dir.is_dir() {
            methods.push(Method::Icp(IcpVariant::PointToPlane));
            methods.push(Method::Icp(IcpVariant::PointToPoint));
        }
        for method in methods {
            for image in initial
                .iter()
                .filter(|image| args.frames.is_empty() || args.frames.contains(&image.name))
                .take(args.limit.unwrap_or(usize::MAX))
            {
                jobs.push((level, method, image.clone()));
            }
        }
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;

    let bar = progress_bar(jobs.len(), "evaluating");
    let mut workspace = ReprojectionWorkspace::new();
    let mut results: BTreeMap<(Level, &'static str), Vec<EvalFrame>> = BTreeMap::new();
    let mut diagnoses: BTreeMap<(Level, &'static str), Vec<(String, FrameDiagnosis)>> =
        BTreeMap::new();
    let mut search_diagnoses: SearchDiagnoses = BTreeMap::new();
    let mut methods_seen: Vec<Method> = Vec::new();
    let mut search_ms: BTreeMap<(Level, &'static str), f64> = BTreeMap::new();
    // The full-circle heading fallback's time and the frames it ran on.
    let mut sweep_ms: BTreeMap<(Level, &'static str), (f64, usize)> = BTreeMap::new();
    // report.html: one row per frame run, the ASG rows with their overlays (the loader's working
    // camera, as registration saw the photo).
    let loader = FrameLoader::default();
    let mut page_frames: Vec<ReportFrame> = Vec::new();
    let mut neighbour_batches: BTreeMap<(Level, &'static str), NeighbourBatch> = BTreeMap::new();
    for (level, method, initial) in jobs {
        let coarse = CoarseArgs {
            neighbour_order: Some(neighbour_order),
            ..level_coarse(&args.coarse, level, heading_tilt_deg)
        };
        if !methods_seen.contains(&method) {
            methods_seen.push(method);
        }
        let gt = gt_images
            .iter()
            .find(|g| g.name == initial.name)
            .with_context(|| format!("{} has no ground truth in gt/images.txt", initial.name))?;
        let camera = *gt_cameras.get(&gt.camera_id).with_context(|| {
            format!(
                "gt/images.txt: {} uses camera {}, not in gt/cameras.txt",
                gt.name, gt.camera_id
            )
        })?;
        let initial_delta_px = mutual_reprojection_error_px(
            &mesh,
            &camera,
            &initial.cam_from_world,
            &camera,
            &gt.cam_from_world,
            &mut workspace,
        )
        .unwrap_or(f64::NAN);
        let mut asg_row = None;
        // The registered frame and its report, for step "neighbour" after the loop.
        let mut registered: Option<(BatchFrame, FrameReport, RegistrationConfig)> = None;
        let outcome = match method {
            Method::Asg(intrinsics) if args.diagnose_search => {
                let config = registration_config(query_mode, intrinsics, &coarse);
                let started = std::time::Instant::now();
                let diagnosis = with_scene_frame(
                    &args.scene,
                    &initial,
                    gt,
                    camera,
                    intrinsics.mode(),
                    with_depth,
                    args.seed,
                    |input| diagnose_search(&mesh, input, &gt.cam_from_world, &config),
                )
                .and_then(|d| d.ok_or_else(|| "the pose search is off".to_string()));
                let elapsed_ms = started.elapsed().as_secs_f64() * 1e3;
                let outcome = FrameOutcome {
                    accepted: false,
                    final_delta_px: diagnosis
                        .as_ref()
                        .ok()
                        .and_then(|d| d.centres_delta_px.first().copied().flatten()),
                    confidence: 0.0,
                    evidence: None,
                    reason: Some(match &diagnosis {
                        Ok(_) => "search only (--diagnose-search): δ of the first centre".into(),
                        Err(why) => why.clone(),
                    }),
                    total_ms: elapsed_ms,
                    search_ms: diagnosis.as_ref().map_or(0.0, |d| d.search_ms),
                    heading_sweep_ms: 0.0,
                    heading_sweep: None,
                    timings: None,
                };
                if let Ok(diagnosis) = diagnosis {
                    search_diagnoses
                        .entry((level, method.name()))
                        .or_default()
                        .push((initial.name.clone(), None, diagnosis));
                }
                outcome
            }
            Method::Asg(intrinsics) if args.diagnose => {
                let config = registration_config(query_mode, intrinsics, &coarse);
                let started = std::time::Instant::now();
                match with_scene_frame(
                    &args.scene,
                    &initial,
                    gt,
                    camera,
                    intrinsics.mode(),
                    with_depth,
                    args.seed,
                    |input| diagnose_frame(&mesh, input, &gt.cam_from_world, &config),
                ) {
                    Ok(mut diagnosis) => {
                        take_search_diagnoses(
                            &mut diagnosis,
                            &initial.name,
                            search_diagnoses.entry((level, method.name())).or_default(),
                        );
                        let verdict = diagnosis.frame_verdict();
                        let carried = diagnosis.carried();
                        let outcome = FrameOutcome {
                            accepted: verdict.accepted(),
                            final_delta_px: carried.chosen_delta_px,
                            confidence: verdict.confidence,
                            evidence: Some(carried.evidence),
                            reason: verdict.rejection().map(|r| r.to_string()),
                            total_ms: started.elapsed().as_secs_f64() * 1e3,
                            search_ms: 0.0,
                            heading_sweep_ms: 0.0,
                            heading_sweep: sweep_eval_of_diagnosis(&diagnosis),
                            timings: None,
                        };
                        diagnoses
                            .entry((level, method.name()))
                            .or_default()
                            .push((initial.name.clone(), diagnosis));
                        outcome
                    }
                    Err(reason) => FrameOutcome {
                        accepted: false,
                        final_delta_px: None,
                        confidence: 0.0,
                        evidence: None,
                        reason: Some(reason),
                        total_ms: started.elapsed().as_secs_f64() * 1e3,
                        search_ms: 0.0,
                        heading_sweep_ms: 0.0,
                        heading_sweep: None,
                        timings: None,
                    },
                }
            }
            Method::Asg(intrinsics) => {
                let config = registration_config(query_mode, intrinsics, &coarse);
                let (report, final_delta_px) = register_scene_frame(
                    &mesh,
                    &args.scene,
                    &initial,
                    gt,
                    camera,
                    intrinsics.mode(),
                    with_depth,
                    &config,
                    args.seed,
                    &mut workspace,
                );
                let frame = scene_batch_frame(
                    &args.scene,
                    &initial,
                    gt,
                    camera,
                    intrinsics.mode(),
                    with_depth,
                );
                let pictures = match frame_overlays(&mesh, &frame, &report, &loader) {
                    Ok(overlays) => overlays
                        .iter()
                        .map(|(label, picture)| {
                            Picture::from_rgb(
                                &frame.name,
                                label,
                                picture.view(),
                                EVAL_THUMBNAIL_WIDTH_PX,
                            )
                        })
                        .collect::<Result<Vec<_>, _>>()?,
                    Err(error) => {
                        tracing::warn!("{}: no overlay: {error:#}", frame.name);
                        Vec::new()
                    }
                };
                if config.neighbour_pose.enabled {
                    registered = Some((frame.clone(), report.clone(), config.clone()));
                }
                asg_row = Some(report_frame(
                    &report,
                    Some(format!("level {level}, {}", method.name())),
                    Some(initial_delta_px),
                    final_delta_px,
                    pictures,
                ));
                FrameOutcome {
                    accepted: report.accepted,
                    final_delta_px,
                    confidence: report.confidence,
                    evidence: report.evidence,
                    reason: report.reason,
                    total_ms: report.timings.total_ms,
                    search_ms: report.timings.search_ms,
                    heading_sweep_ms: report.timings.heading_sweep_ms,
                    timings: Some(report.timings),
                    heading_sweep: report.heading_sweep.as_ref().map(|sweep| {
                        sweep_eval(sweep, |pose| {
                            mutual_reprojection_error_px(
                                &mesh,
                                &pose.camera,
                                &pose.cam_from_world,
                                &camera,
                                &gt.cam_from_world,
                                &mut workspace,
                            )
                        })
                    }),
                }
            }
            Method::Icp(variant) => {
                let started = std::time::Instant::now();
                let config = IcpConfig {
                    variant,
                    ..IcpConfig::default()
                };
                let mut rng = ChaCha8Rng::seed_from_u64(args.seed ^ u64::from(initial.image_id));
                let result = read_pfm(&depth_path_for(&depth_dir, &initial.name))
                    .map_err(|e| e.to_string())
                    .and_then(|depth| {
                        register_depth_to_mesh(
                            &mesh,
                            &camera,
                            &depth,
                            &initial.cam_from_world,
                            &config,
                            &mut rng,
                        )
                        .map_err(|e| e.to_string())
                    });
                match result {
                    Ok(icp) => {
                        let final_delta_px = mutual_reprojection_error_px(
                            &mesh,
                            &camera,
                            &icp.cam_from_world,
                            &camera,
                            &gt.cam_from_world,
                            &mut workspace,
                        );
                        let success = final_delta_px.is_some_and(|d| d < ICP_SUCCESS_THRESHOLD_PX);
                        FrameOutcome {
                            accepted: success,
                            final_delta_px,
                            confidence: 0.0,
                            evidence: None,
                            reason: (!success).then(|| {
                                format!("δ to ground truth not below {ICP_SUCCESS_THRESHOLD_PX} px")
                            }),
                            total_ms: started.elapsed().as_secs_f64() * 1e3,
                            search_ms: 0.0,
                            heading_sweep_ms: 0.0,
                            heading_sweep: None,
                            timings: None,
                        }
                    }
                    Err(reason) => FrameOutcome {
                        accepted: false,
                        final_delta_px: None,
                        confidence: 0.0,
                        evidence: None,
                        reason: Some(reason),
                        total_ms: started.elapsed().as_secs_f64() * 1e3,
                        search_ms: 0.0,
                        heading_sweep_ms: 0.0,
                        heading_sweep: None,
                        timings: None,
                    },
                }
            }
        };
        let line = format!(
            "level {level:>3} {:<18} {}: initial δ {initial_delta_px:6.1} px → {} [{:.1} s, search {:.2} s]",
            method.name(),
            initial.name,
            match (outcome.accepted, outcome.final_delta_px) {
                (true, Some(d)) => format!(
                    "accepted, δ {d:.2} px (confidence {:.2})",
                    outcome.confidence
                ),
                (false, Some(d)) => format!(
                    "rejected (its pose: δ {d:.1} px): {}",
                    outcome.reason.as_deref().unwrap_or("-")
                ),
                _ => format!("failed: {}", outcome.reason.as_deref().unwrap_or("-")),
            },
            outcome.total_ms / 1e3,
            outcome.search_ms / 1e3
        ) + &outcome
            .heading_sweep
            .as_ref()
            .map_or(String::new(), |sweep| format!(" {}", sweep_line(sweep)));
        *search_ms.entry((level, method.name())).or_insert(0.0) += outcome.search_ms;
        let sweep = sweep_ms.entry((level, method.name())).or_insert((0.0, 0));
        if outcome.heading_sweep_ms > 0.0 {
            *sweep = (sweep.0 + outcome.heading_sweep_ms, sweep.1 + 1);
        }
        if bar.is_hidden() {
            println!("{line}");
        } else {
            bar.println(line);
        }
        bar.inc(1);
        page_frames.push(asg_row.unwrap_or_else(|| ReportFrame {
            name: initial.name.clone(),
            group: Some(format!("level {level}, {}", method.name())),
            verdict: if outcome.accepted {
                FrameVerdict::Accepted
            } else if outcome.final_delta_px.is_some() {
                FrameVerdict::Rejected
            } else {
                FrameVerdict::Failed
            },
            reason: outcome.reason.clone(),
            confidence: matches!(method, Method::Asg(_)).then_some(outcome.confidence),
            initial_delta_px: Some(initial_delta_px),
            delta_px: outcome.final_delta_px,
            timings_ms: vec![("total".to_string(), outcome.total_ms)],
            details: Vec::new(),
            pictures: Vec::new(),
        }));
        let cell = results.entry((level, method.name())).or_default();
        if let Some((frame, report, config)) = registered {
            neighbour_batches
                .entry((level, method.name()))
                .or_insert_with(|| NeighbourBatch {
                    config,
                    ..NeighbourBatch::default()
                })
                .push(
                    cell.len(),
                    page_frames.len() - 1,
                    frame,
                    report,
                    gt.cam_from_world,
                    camera,
                );
        }
        cell.push(EvalFrame {
            name: initial.name.clone(),
            initial_delta_px,
            accepted: outcome.accepted,
            final_delta_px: outcome.final_delta_px,
            confidence: outcome.confidence,
            evidence: outcome.evidence,
            reason: outcome.reason,
            total_ms: outcome.total_ms,
            heading_sweep: outcome.heading_sweep,
            timings: outcome.timings,
            neighbours: Vec::new(),
        });
    }
    bar.finish_and_clear();
    for (key, batch) in neighbour_batches {
        if let Some(frames) = results.get_mut(&key) {
            batch.run(
                &mesh,
                &loader,
                args.seed,
                frames,
                &mut page_frames,
                &mut workspace,
            );
        }
    }

    let stats: BTreeMap<(Level, &str), CellStats> = results
        .iter()
        .map(|(key, frames)| (*key, cell_stats(frames, false_accept_px)))
        .collect();
    let methods: Vec<&str> = methods_seen.iter().map(|m| m.name()).collect();
    let mut table = results_markdown(args, &stats, &methods, false_accept_px, heading_tilt_deg);
    let calibration: BTreeMap<&str, Vec<CalibrationBin>> = methods
        .iter()
        .filter(|method| !method.starts_with("ICP"))
        .map(|&method| {
            let frames = results
                .iter()
                .filter(|((_, m), _)| *m == method)
                .flat_map(|(_, frames)| frames.iter());
            (
                method,
                calibration_bins(frames, false_accept_px, CALIBRATION_BINS),
            )
        })
        .collect();
    table.push_str(&calibration_markdown(&calibration, false_accept_px));
    table.push_str(&sweep_markdown(&results, false_accept_px));
    std::fs::write(args.out.join("results.md"), &table)
        .with_context(|| format!("writing {}", args.out.join("results.md").display()))?;
    let json = serde_json::json!({
        "scene": args.scene,
        "query": format!("{:?}", args.query),
        "false_accept_threshold_px": false_accept_px,
        "heading_tilt_trusted_deg": heading_tilt_deg,
        "calibration": calibration,
        "cells": stats.iter().map(|((level, method), s)| serde_json::json!({
            "level_px": level, "method": method, "stats": s,
            "frames": results.get(&(*level, *method)),
        })).collect::<Vec<_>>(),
    });
    std::fs::write(
        args.out.join("results.json"),
        serde_json::to_string_pretty(&json)?,
    )
    .with_context(|| format!("writing {}", args.out.join("results.json").display()))?;
    let plot = plot_svg(&stats, &methods);
    std::fs::write(args.out.join("results.svg"), &plot)
        .with_context(|| format!("writing {}", args.out.join("results.svg").display()))?;
    let accepted: usize = stats.values().map(|s| s.accepted).sum();
    let page = ReportPage {
        command: "eval".to_string(),
        subject: args.scene.display().to_string(),
        summary: vec![
            ("query".to_string(), format!("{:?}", args.query)),
            (
                "levels (initial δ, px)".to_string(),
                args.levels
                    .iter()
                    .map(ToString::to_string)
                    .collect::<Vec<_>>()
                    .join(", "),
            ),
            ("methods".to_string(), methods.join(", ")),
            (
                "false accept".to_string(),
                format!("accepted with δ > {false_accept_px:.2} px"),
            ),
            (
                "accepted".to_string(),
                format!("{accepted} of {} frame runs", page_frames.len()),
            ),
            ("tables".to_string(), "results.md, results.json".to_string()),
        ],
        plots_svg: vec![(
            "mean δ of the accepted frames and the share accepted, per initial δ".to_string(),
            plot,
        )],
        frames: page_frames,
    };
    write_report_html(&args.out.join(REPORT_HTML), &page)?;
    if args.diagnose {
        // A pose within the final refinement's first search radius of the truth is in its reach.
        let near_truth_px = args.coarse.edge_search_px;
        let json = serde_json::json!({
            "scene": args.scene,
            "query": format!("{:?}", args.query),
            "cells": diagnoses.iter().map(|((level, method), frames)| serde_json::json!({
                "level_px": level,
                "method": method,
                "summary": DiagnosisSummary::of(frames.iter().map(|(_, d)| d)),
                "frames": frames.iter().map(|(name, d)| serde_json::json!({
                    "name": name,
                    "lost_at": carried_search(&search_diagnoses, &(*level, *method), name, d)
                        .map(|s| s.loss(d.registered_within(false_accept_px), near_truth_px)),
                    "diagnosis": d,
                })).collect::<Vec<_>>(),
            })).collect::<Vec<_>>(),
        });
        let mut text = diagnosis_markdown(&diagnoses);
        text.push_str(&search_loss_markdown(
            &diagnoses,
            &search_diagnoses,
            near_truth_px,
            false_accept_px,
        ));
        write_diagnosis(&args.out, "diagnosis", &text, &json)?;
    }
    if !search_diagnoses.is_empty() {
        let json = serde_json::json!({
            "scene": args.scene,
            "cells": search_diagnoses.iter().map(|((level, method), frames)| serde_json::json!({
                "level_px": level,
                "method": method,
                "frames": frames.iter().map(|(name, accepted, d)| serde_json::json!({"name": name, "accepted": accepted, "search": d})).collect::<Vec<_>>(),
            })).collect::<Vec<_>>(),
        });
        write_diagnosis(
            &args.out,
            "search_diagnosis",
            &search_diagnosis_markdown(&search_diagnoses),
            &json,
        )?;
    }
    println!("{table}");
    for ((level, method), total_search_ms) in &search_ms {
        if let (Some(frames), true) = (results.get(&(*level, *method)), *total_search_ms > 0.0) {
            let total_ms: f64 = frames.iter().map(|f| f.total_ms).sum();
            println!(
                "pose search, level {level} {method}: {:.2} s/frame of {:.2} s/frame ({:.0} %)",
                total_search_ms / frames.len().max(1) as f64 / 1e3,
                total_ms / frames.len().max(1) as f64 / 1e3,
                100.0 * total_search_ms / total_ms.max(1e-9)
            );
        }
    }
    for ((level, method), (total_sweep_ms, swept)) in &sweep_ms {
        if let (Some(frames), true) = (results.get(&(*level, *method)), *swept > 0) {
            let total_ms: f64 = frames.iter().map(|f| f.total_ms).sum();
            println!(
                "heading sweep (fallback), level {level} {method}: ran on {swept} of {} frames, {:.2} s per frame it ran on ({:.0} % of the level's time)",
                frames.len(),
                total_sweep_ms / *swept as f64 / 1e3,
                100.0 * total_sweep_ms / total_ms.max(1e-9)
            );
        }
    }
    println!(
        "wrote {}, {}, {} and {}",
        args.out.join("results.md").display(),
        args.out.join("results.json").display(),
        args.out.join("results.svg").display(),
        args.out.join(REPORT_HTML).display()
    );
    Ok(())
}

/// Runs `run` on the frame `initial` of a scene folder (the same inputs as
/// [`register_scene_frame`]; the diagnoses); a frame whose files cannot be used, or whose run
/// fails, is an error message.
#[allow(clippy::too_many_arguments)]
fn with_scene_frame<T>(
    scene: &Path,
    initial: &ImagePose,
    gt: &ImagePose,
    camera: Camera,
    intrinsics: IntrinsicsMode,
    with_depth: bool,
    seed: u64,
    run: impl FnOnce(&FrameInput<'_>) -> Result<T, RegistrationError>,
) -> Result<T, String> {
    let frame = scene_batch_frame(scene, initial, gt, camera, intrinsics, with_depth);
    let files = frame.load().map_err(|e| e.to_string())?;
    run(&frame.input(&files, seed)).map_err(|e| e.to_string())
}

/// The frame `initial` of a scene folder (photo in `images/`, depth in `depth/` when
/// `with_depth`) with the camera of its ground truth `gt`.
fn scene_batch_frame(
    scene: &Path,
    initial: &ImagePose,
    gt: &ImagePose,
    camera: Camera,
    intrinsics: IntrinsicsMode,
    with_depth: bool,
) -> BatchFrame {
    BatchFrame {
        image_id: initial.image_id,
        camera_id: gt.camera_id,
        name: initial.name.clone(),
        image_path: scene.join("images").join(&initial.name),
        depth_path: with_depth.then(|| depth_path_for(&scene.join("depth"), &initial.name)),
        camera,
        intrinsics,
        initial_cam_from_world: initial.cam_from_world,
    }
}

/// Writes a diagnosis table to `<stem>.md` and its data to `<stem>.json` in `out`, then prints the
/// table (`eval --diagnose`, `register --diagnose`).
pub(super) fn write_diagnosis(
    out: &Path,
    stem: &str,
    text: &str,
    json: &serde_json::Value,
) -> anyhow::Result<()> {
    let path = out.join(format!("{stem}.md"));
    std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
    let path = out.join(format!("{stem}.json"));
    std::fs::write(&path, serde_json::to_string_pretty(json)?)
        .with_context(|| format!("writing {}", path.display()))?;
    println!("{text}");
    Ok(())
}

/// The diagnosis tables: one row per (level, method), then one line per frame (`register
/// --diagnose` keys its one cell by the run's name instead of a level).
pub(super) fn diagnosis_markdown<K: std::fmt::Display + Ord>(
    diagnoses: &BTreeMap<(K, &str), Vec<(String, FrameDiagnosis)>>,
) -> String {
    let px = |value: Option<f64>| value.map_or("–".to_string(), |v| format!("{v:.2}"));
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# asgreg eval --diagnose\n\nWhere the error comes from (ground truth known). Correspondence error: \
|π_true(X) − p| of each 2D–3D pair, query px; flow error: the matched rendering point against where the \
true pose puts the query pixel's model point, rendering px; near edge: lifted within a pixel of a depth \
discontinuity. Medians per view, averaged. Solver: δ of the refined poses (mean over views), and of an \
oracle pose solved from only the pairs within {ORACLE_MAX_ERROR_PX} px. Choice: δ of the output against the \
best hypothesis. At truth: a view rendered at the true pose, its flow-error median and the δ of \
the pose solved from it (the floor for a refinement that re-renders at its current pose). Refinement: \
δ of the verified pose, of where the edge alignment ended (kept or not; the share kept), of the output, \
and of the alignment started at the true pose (its own bias).\n"
    );
    let _ = writeln!(
        out,
        "| level | method | frames | corr. median | near edge (share) | away from edge | flow median | ≤1 / ≤2 / ≤5 px | hypotheses δ | oracle δ | best δ | output δ | at truth: flow median, δ | verified δ | aligned δ (kept) | aligned from truth δ |"
    );
    let _ = writeln!(
        out,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for ((level, method), frames) in diagnoses {
        let s = DiagnosisSummary::of(frames.iter().map(|(_, d)| d));
        let _ = writeln!(
            out,
            "| {level} | {method} | {} | {} | {} ({:.0} %) | {} | {} | {:.0} / {:.0} / {:.0} % | {} | {} | {} | {} | {}, {} | {} | {} ({:.0} %) | {} |",
            s.frames,
            px(s.correspondence_median_px),
            px(s.near_edge_median_px),
            100.0 * s.near_edge_share,
            px(s.away_from_edge_median_px),
            px(s.flow_median_px),
            100.0 * s.within_1px,
            100.0 * s.within_2px,
            100.0 * s.within_5px,
            px(s.hypothesis_delta_px),
            px(s.oracle_delta_px),
            px(s.best_delta_px),
            px(s.chosen_delta_px),
            px(s.at_truth_flow_median_px),
            px(s.at_truth_delta_px),
            px(s.verified_delta_px),
            px(s.aligned_delta_px),
            100.0 * s.refinement_kept_share,
            px(s.aligned_from_truth_delta_px),
        );
    }
    let _ = writeln!(
        out,
        "\n## Edge bias at the true pose\n\nModel edge samples of a rendering at the true pose searched in \
the query (unblurred, the evidence's radius). Outward offset: signed distance to the photo's ridge along \
the search line, positive towards where a sharp edge lies from a rounded one (the far side of a contour, \
the faces' bisector of a convex crease, inward of a concave one). Rounding fit: the rounding radius that \
best explains the offsets within 3 px (least squares). Then the alignment started at the truth: δ of only \
its translation along the view axis and of the rest (lateral translation and rotation), its mean signed \
axial and lateral translation errors, and the rounding radius it estimated.\n"
    );
    let _ = writeln!(
        out,
        "| level | method | group | samples | matched | outward mean | outward median | mean abs | rounding fit |"
    );
    let _ = writeln!(out, "|---|---|---|---|---|---|---|---|---|");
    for ((level, method), frames) in diagnoses {
        let s = DiagnosisSummary::of(frames.iter().map(|(_, d)| d));
        for g in &s.edge_bias {
            let _ = writeln!(
                out,
                "| {level} | {method} | {} | {} | {:.0} % | {} | {} | {} | {} |",
                g.group,
                g.samples,
                if g.samples == 0 {
                    0.0
                } else {
                    100.0 * g.matched as f64 / g.samples as f64
                },
                px(g.mean_outward_px),
                px(g.median_outward_px),
                px(g.mean_abs_px),
                g.rounding_fit_m
                    .map_or("–".to_string(), |v| format!("{v:.3} m")),
            );
        }
    }
    let _ = writeln!(
        out,
        "\n| level | method | from truth δ | axial part δ | lateral + rotation δ | axial error | lateral error | rounding | from truth δ by first search radius | edges at the truth: px per px of model motion, least / most seen direction |\n|---|---|---|---|---|---|---|---|---|---|"
    );
    for ((level, method), frames) in diagnoses {
        let s = DiagnosisSummary::of(frames.iter().map(|(_, d)| d));
        let m = |value: Option<f64>| value.map_or("–".to_string(), |v| format!("{v:.3} m"));
        let _ = writeln!(
            out,
            "| {level} | {method} | {} | {} | {} | {} | {} | {} | {} | {} / {} |",
            px(s.aligned_from_truth_delta_px),
            px(s.from_truth_along_axis_delta_px),
            px(s.from_truth_lateral_and_rotation_delta_px),
            m(s.from_truth_along_axis_m),
            m(s.from_truth_lateral_m),
            m(s.from_truth_rounding_m),
            s.from_truth_by_first_radius
                .iter()
                .map(|(radius_px, delta_px)| format!("{radius_px:.0} px: {}", px(*delta_px)))
                .collect::<Vec<_>>()
                .join(", "),
            px(s.observability_least),
            px(s.observability_most),
        );
    }
    let _ = writeln!(out, "\n## Frames\n");
    let _ = writeln!(
        out,
        "| level | method | frame | verdict | corr. median | flow median | ≤2 px | hypotheses δ | oracle δ | best δ | verified δ | aligned δ | kept | output δ | edge support before → after | at truth: support, near, far (best confidence) | correlation at truth: pose, near, far; at output |"
    );
    let _ = writeln!(
        out,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for ((level, method), frames) in diagnoses {
        for (name, diagnosis) in with_retries(frames) {
            let s = DiagnosisSummary::of(std::slice::from_ref(diagnosis));
            let _ = writeln!(
                out,
                "| {level} | {method} | {name} | {} | {} | {} | {:.0} % | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                if diagnosis.verdict.accepted() {
                    "accepted"
                } else {
                    "rejected"
                },
                px(s.correspondence_median_px),
                px(s.flow_median_px),
                100.0 * s.within_2px,
                px(s.hypothesis_delta_px),
                px(s.oracle_delta_px),
                px(s.best_delta_px),
                px(s.verified_delta_px),
                px(s.aligned_delta_px),
                match &diagnosis.refinement {
                    Ok(r) if r.kept => "yes",
                    Ok(_) => "no",
                    Err(_) => "–",
                },
                px(s.chosen_delta_px),
                match &diagnosis.refinement {
                    Ok(r) => format!(
                        "{:.0} % → {:.0} %",
                        100.0 * r.verified.support_fraction(),
                        100.0 * r.aligned.support_fraction()
                    ),
                    Err(why) => why.clone(),
                },
                match (diagnosis.truth_edges, diagnosis.truth_best_confidence) {
                    (Some(peak), Some(confidence)) => format!(
                        "{:.0} %, {:.0} %, {:.0} % ({confidence:.2})",
                        100.0 * peak.at_pose,
                        100.0 * peak.near,
                        100.0 * peak.far
                    ),
                    _ => "–".to_string(),
                },
                [diagnosis.truth_correlation, diagnosis.output_correlation]
                    .iter()
                    .map(|peak| peak.map_or("–".to_string(), |p| format!(
                        "{:.3}, {:.3}, {:.3}",
                        p.at_pose, p.near, p.far
                    )))
                    .collect::<Vec<_>>()
                    .join("; "),
            );
        }
    }
    let _ = writeln!(
        out,
        "\n## Centres\n\nPer frame with more than one centre of coarse poses: each centre's own decision before \
verification across the centres chose (δ px against the truth; support: edge support at its output; correlation: \
the dense correlation there; median matched / supported: median distance, px, of the model edge samples matched within the \
evidence radius / supported within `support_px` to their photo ridges; support ½: the share within half of `support_px`; \
check: the paper's plausibility check of its refined poses; apart: δ from its output to the frame's, px).\n"
    );
    let _ = writeln!(
        out,
        "| level | method | frame | centre | centre δ | best δ | verified δ | output δ | support | correlation | median matched | median supported | support ½ | check | apart | confidence | verdict |"
    );
    let _ = writeln!(
        out,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for ((level, method), frames) in diagnoses {
        for (name, diagnosis) in with_retries(frames)
            .into_iter()
            .filter(|(_, d)| d.centres.len() > 1)
        {
            for (index, centre) in diagnosis.centres.iter().enumerate() {
                let _ = writeln!(
                    out,
                    "| {level} | {method} | {name} | {index} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {:.2} | {} |",
                    px(centre.centre_delta_px),
                    px(centre.best_delta_px),
                    px(centre.verified_delta_px),
                    px(centre.output_delta_px),
                    centre
                        .edge_support
                        .map_or("–".to_string(), |v| format!("{:.0} %", 100.0 * v)),
                    centre
                        .correlation
                        .map_or("–".to_string(), |v| format!("{v:.3}")),
                    centre
                        .evidence
                        .map_or("–".to_string(), |e| format!("{:.2}", e.median_distance_px)),
                    centre
                        .evidence
                        .map_or("–".to_string(), |e| format!("{:.2}", e.supported_median_px)),
                    centre.evidence.map_or("–".to_string(), |e| format!(
                        "{:.0} %",
                        100.0 * e.tight_support_fraction()
                    )),
                    if centre.check_passed { "passed" } else { "failed" },
                    px(centre.apart_from_output_px),
                    centre.confidence,
                    centre.reason.as_deref().unwrap_or("accepted"),
                );
            }
        }
    }
    let _ = writeln!(
        out,
        "\n## Rival basins\n\nPer frame the rival-basin test ran on (a pose accepted before it): where each of its \
alignment runs, started around the output along the directions its edges see least, ended (in the test's order): δ px \
from the output, edge support, δ px to the truth. The frame is rejected when an end at least the centres' agreement \
distance from the output keeps the output's edge support above chance (`--rival-share`).\n"
    );
    let _ = writeln!(
        out,
        "| level | method | frame | output δ | output support | ends: apart px (support, δ to the truth px) | verdict |"
    );
    let _ = writeln!(out, "|---|---|---|---|---|---|---|");
    for ((level, method), frames) in diagnoses {
        for (name, diagnosis) in with_retries(frames)
            .into_iter()
            .filter(|(_, d)| !d.rival_ends.is_empty())
        {
            let ends = diagnosis
                .rival_ends
                .iter()
                .map(|end| {
                    format!(
                        "{:.1} ({:.0} %, {})",
                        end.apart_px,
                        100.0 * end.support,
                        px(end.delta_px)
                    )
                })
                .collect::<Vec<_>>()
                .join(", ");
            let _ = writeln!(
                out,
                "| {level} | {method} | {name} | {} | {} | {ends} | {} |",
                px(diagnosis.chosen_delta_px),
                diagnosis
                    .evidence
                    .edges
                    .map_or("–".to_string(), |peak| format!(
                        "{:.0} %",
                        100.0 * peak.at_pose
                    )),
                diagnosis
                    .verdict
                    .rejection()
                    .map_or("accepted".to_string(), |r| r.to_string()),
            );
        }
    }
    let swept: Vec<(String, &FrameDiagnosis, SweepEval)> = diagnoses
        .iter()
        .flat_map(|((level, method), frames)| {
            frames.iter().filter_map(move |(name, d)| {
                sweep_eval_of_diagnosis(d).map(|e| (format!("| {level} | {method} | {name}"), d, e))
            })
        })
        .collect();
    if !swept.is_empty() {
        let _ = writeln!(
            out,
            "\n## Heading sweep (fallback)\n\nFrames whose first pass was not accepted, diagnosed once more with headings \
swept over the full circle (rows \"(sweep)\" above): each registration's output (or would-be output) δ to the \
truth, its verdict and confidence, the first centre's δ of the retry's search, and which registration the frame's \
result carries (an accepted retry, else the more confident rejection).\n"
        );
        let _ = writeln!(
            out,
            "| level | method | frame | first pass δ | first pass verdict (confidence) | retry's first centre δ | retry δ | retry verdict (confidence) | carried | the frame's verdict |\n|---|---|---|---|---|---|---|---|---|---|"
        );
        for (key, diagnosis, sweep) in &swept {
            let verdict = PassEval::verdict_text;
            let retry = diagnosis
                .heading_sweep
                .as_ref()
                .and_then(|s| s.retry.as_deref().ok());
            let _ = writeln!(
                out,
                "{key} | {} | {} | {} | {} | {} | {} | {} |",
                px(sweep.first.delta_px),
                verdict(&sweep.first),
                px(retry
                    .and_then(|r| r.centres.first())
                    .and_then(|c| c.centre_delta_px)),
                px(sweep.retry.as_ref().and_then(|r| r.delta_px)),
                sweep.retry.as_ref().map_or_else(
                    || match diagnosis.heading_sweep.as_ref().map(|s| &s.retry) {
                        Some(Err(why)) => format!("no result: {why}"),
                        _ => "no result".to_string(),
                    },
                    verdict
                ),
                sweep.carried,
                diagnosis
                    .frame_verdict()
                    .rejection()
                    .map_or("accepted".to_string(), |r| r.to_string()),
            );
        }
    }
    out
}

/// A cell's frames and, after each whose heading fallback ran, the retry as "<name> (sweep)".
fn with_retries(frames: &[(String, FrameDiagnosis)]) -> Vec<(String, &FrameDiagnosis)> {
    frames
        .iter()
        .flat_map(|(name, diagnosis)| {
            let retry = diagnosis
                .heading_sweep
                .as_ref()
                .and_then(|s| s.retry.as_deref().ok())
                .map(|retry| (format!("{name} (sweep)"), retry));
            std::iter::once((name.clone(), diagnosis)).chain(retry)
        })
        .collect()
}

/// Each frame's pose search against the truth, by (level, method): name, the verdict when the
/// frame was registered too, the diagnosis.
type SearchDiagnoses = SearchDiagnosesBy<Level>;

/// [`SearchDiagnoses`] keyed by anything shown in the level's column (`register --diagnose`: the
/// run's name).
pub(super) type SearchDiagnosesBy<K> =
    BTreeMap<(K, &'static str), Vec<(String, Option<bool>, SearchDiagnosis)>>;

/// The pose-search table of `eval --diagnose` / `--diagnose-search`: one line per frame.
pub(super) fn search_diagnosis_markdown<K: std::fmt::Display + Ord>(
    diagnoses: &SearchDiagnosesBy<K>,
) -> String {
    let px = |value: Option<f64>| value.map_or("–".to_string(), |v| format!("{v:.2}"));
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# Pose search against the truth\n\nPer frame: δ of the prior, its centre's error, δ of the true rotation at the \
prior's centre (the reach of a rotation-only search), the edge support at the truth, the grid score of a \
candidate at the truth and at the rotation reach, whether a beam replaced the prior, δ of each centre of \
the coarse poses, and each refined beam as δ px (edge support %, grid score, edge support after the \
screening %, image uncertainty px; the prior first); and the grid candidate nearest the rotation reach: its \
angle to it, its rank among the distinct candidates the search screens (best grid score first) and δ \
(edge support) after the screening from it.\n"
    );
    let _ = writeln!(
        out,
        "| level | frame | verdict | prior δ | centre error m | rotation reach δ | support at truth | grid score at truth / rotation reach | moved | centres δ | search from the true centre δ | reach in grid: angle, rank, screened δ (support) | beams δ (support, grid score, screened support, image uncertainty) |"
    );
    let _ = writeln!(out, "|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    let mut first_centre_within_5px = 0usize;
    let mut frames = 0usize;
    for ((level, _), rows) in diagnoses {
        for (name, accepted, search) in rows {
            frames += 1;
            if search
                .centres_delta_px
                .first()
                .copied()
                .flatten()
                .is_some_and(|d| d <= 5.0)
            {
                first_centre_within_5px += 1;
            }
            let _ = writeln!(
                out,
                "| {level} | {name} | {} | {} | {:.2} | {} | {} | {:.3} / {:.3} | {} | {} | {} | {} | {} |",
                match accepted {
                    Some(true) => "accepted",
                    Some(false) => "rejected",
                    None => "–",
                },
                px(search.prior_delta_px),
                search.prior_centre_error_m,
                px(search.rotation_reach_delta_px),
                search
                    .truth_support
                    .map_or("–".to_string(), |s| format!("{:.0} %", 100.0 * s)),
                search.truth_grid_score,
                search.rotation_reach_grid_score,
                if search.moved { "yes" } else { "no" },
                search
                    .centres_delta_px
                    .iter()
                    .map(|d| px(*d))
                    .collect::<Vec<_>>()
                    .join(", "),
                px(search.true_centre_search_delta_px),
                search.reach_in_grid.as_ref().map_or("–".to_string(), |r| format!(
                    "{:.1}°, {}, {} ({:.0} %)",
                    r.angle_deg,
                    r.distinct_rank
                        .map_or(format!("> {REACH_RANK_LIMIT}"), |rank| rank.to_string()),
                    px(r.screened_delta_px),
                    100.0 * r.screened_support
                )),
                search
                    .beams
                    .iter()
                    .map(|b| format!(
                        "{} ({:.0} %, {:.3}, {:.0} %, u {:.2} px)",
                        px(b.delta_px),
                        100.0 * b.support,
                        b.grid_score,
                        100.0 * b.screened_support,
                        b.image_uncertainty_px
                    ))
                    .collect::<Vec<_>>()
                    .join(", "),
            );
        }
    }
    let _ = writeln!(
        out,
        "\nFirst centre within 5 px of the truth: {first_centre_within_5px} of {frames} frames."
    );
    out
}

/// The table of where each frame was lost (`FrameDiagnosis::search_loss`): per cell the count
/// of each class with its frames, then one line per frame that was not registered, with the
/// nearest pose to the truth at each step of the search.
pub(super) fn search_loss_markdown<K: std::fmt::Display + Ord + Clone>(
    diagnoses: &BTreeMap<(K, &'static str), Vec<(String, FrameDiagnosis)>>,
    searches: &SearchDiagnosesBy<K>,
    near_truth_px: f64,
    false_accept_px: f64,
) -> String {
    let loss = |key: &(K, &'static str), name: &str, d: &FrameDiagnosis| {
        carried_search(searches, key, name, d).map(|s| {
            (
                s.loss(d.registered_within(false_accept_px), near_truth_px),
                s,
            )
        })
    };
    let px = |value: Option<f64>| value.map_or("–".to_string(), |v| format!("{v:.2}"));
    let nearest =
        |deltas: &mut dyn Iterator<Item = Option<f64>>| px(deltas.flatten().min_by(f64::total_cmp));
    let mut out = String::new();
    let _ = writeln!(
        out,
        "\n## Where the frame was lost\n\nEach frame not accepted within {false_accept_px:.2} px of the truth, by the \
first step of the pose search after which no pose within {near_truth_px:.0} px of the truth (the final refinement's \
first search radius) was left: (a) grid: no start of the screening ended near it; (a′) screening: one did, but \
better-supported starts took the beams; (b) beam refinement: a beam (or the prior) started near it and its \
refinement ended away; (c) search decision: a refined beam lay near it, no centre did; (d) after the search: a \
centre lay near it, and flow, pose, verification or the final refinement lost it.\n"
    );
    let _ = writeln!(
        out,
        "| level | method | frames | {} |",
        SearchLoss::ALL.map(|l| l.label()).join(" | ")
    );
    let _ = writeln!(out, "|---|---|---|{}", "---|".repeat(SearchLoss::ALL.len()));
    for (key, frames) in diagnoses {
        let (level, method) = key;
        let cells: Vec<String> = SearchLoss::ALL
            .iter()
            .map(|class| {
                let names: Vec<&str> = frames
                    .iter()
                    .filter(|(name, d)| loss(key, name, d).map(|(l, _)| l) == Some(*class))
                    .map(|(name, _)| name.trim_end_matches(".jpg"))
                    .collect();
                if names.is_empty() || *class == SearchLoss::Registered {
                    names.len().to_string()
                } else {
                    format!("{} ({})", names.len(), names.join(", "))
                }
            })
            .collect();
        let _ = writeln!(
            out,
            "| {level} | {method} | {} | {} |",
            frames.len(),
            cells.join(" | ")
        );
    }
    let _ = writeln!(
        out,
        "\n| level | method | frame | lost at | verdict | output δ | nearest screened δ | nearest beam start δ | nearest beam δ | nearest centre δ | rotation reach δ | from the true centre δ |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for (key, frames) in diagnoses {
        let (level, method) = key;
        for (name, diagnosis) in frames {
            let Some((loss, search)) = loss(key, name, diagnosis) else {
                continue;
            };
            if loss == SearchLoss::Registered {
                continue;
            }
            let carried = diagnosis.carried();
            let _ = writeln!(
                out,
                "| {level} | {method} | {name} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                loss.label(),
                if diagnosis.frame_verdict().accepted() {
                    "accepted"
                } else {
                    "rejected"
                },
                px(carried.chosen_delta_px),
                nearest(&mut search.screened.iter().map(|s| s.delta_px)),
                nearest(&mut search.beams.iter().map(|b| b.start_delta_px)),
                nearest(&mut search.beams.iter().map(|b| b.delta_px)),
                nearest(&mut search.centres_delta_px.iter().copied()),
                px(search.rotation_reach_delta_px),
                px(search.true_centre_search_delta_px),
            );
        }
    }
    out
}

/// The search diagnosis of the registration a frame's result carries (the retry's, "<name>
/// (sweep)", when the heading fallback's is carried), from `searches`, where
/// [`take_search_diagnoses`] put it.
fn carried_search<'a, K: Ord + Clone>(
    searches: &'a SearchDiagnosesBy<K>,
    key: &(K, &'static str),
    name: &str,
    diagnosis: &FrameDiagnosis,
) -> Option<&'a SearchDiagnosis> {
    let wanted = if std::ptr::eq(diagnosis.carried(), diagnosis) {
        name.to_string()
    } else {
        format!("{name} (sweep)")
    };
    searches
        .get(key)?
        .iter()
        .find(|(n, _, _)| *n == wanted)
        .map(|(_, _, s)| s)
}

/// Registers the frame `initial` of a scene folder (photo in `images/`, depth in `depth/` when
/// `with_depth`) and returns its report and δ to `gt` of the output pose, or of a rejected frame's
/// would-be output (None when there is no pose at all).
#[allow(clippy::too_many_arguments)]
pub fn register_scene_frame(
    mesh: &Mesh,
    scene: &Path,
    initial: &ImagePose,
    gt: &ImagePose,
    camera: Camera,
    intrinsics: IntrinsicsMode,
    with_depth: bool,
    config: &RegistrationConfig,
    seed: u64,
    workspace: &mut ReprojectionWorkspace,
) -> (FrameReport, Option<f64>) {
    let frame = scene_batch_frame(scene, initial, gt, camera, intrinsics, with_depth);
    let report = register_batch_frame(mesh, &frame, config, seed);
    let output = match (report.camera, report.cam_from_world) {
        (Some(out_camera), Some(out_pose)) => Some((out_camera, out_pose)),
        _ => report
            .rejected_candidate
            .map(|candidate| (candidate.camera, candidate.cam_from_world)),
    };
    let final_delta_px = output.and_then(|(out_camera, out_pose)| {
        mutual_reprojection_error_px(
            mesh,
            &out_camera,
            &out_pose,
            &camera,
            &gt.cam_from_world,
            workspace,
        )
    });
    (report, final_delta_px)
}

/// One cell's registered frames kept for step "neighbour" (on unless `--no-neighbours`), which runs over the
/// cell once every frame is registered ([`neighbour_pass`]).
#[derive(Default)]
struct NeighbourBatch {
    config: RegistrationConfig,
    /// Each frame's position in the cell's results and its row of the page, inputs, report,
    /// true pose and camera.
    positions: Vec<usize>,
    page_rows: Vec<usize>,
    frames: Vec<BatchFrame>,
    reports: Vec<FrameReport>,
    truths: Vec<(Rigid3, Camera)>,
}

impl NeighbourBatch {
    #[allow(clippy::too_many_arguments)]
    fn push(
        &mut self,
        position: usize,
        page_row: usize,
        frame: BatchFrame,
        report: FrameReport,
        truth: Rigid3,
        camera: Camera,
    ) {
        self.positions.push(position);
        self.page_rows.push(page_row);
        self.frames.push(frame);
        self.reports.push(report);
        self.truths.push((truth, camera));
    }

    /// Runs step "neighbour" over the cell and writes what it decided into the cell's results
    /// (`frames`): every frame's neighbour tries (with δ of each neighbour's pose to the truth),
    /// and the new decision of those it changed, also in their rows of the page (`page`; the
    /// pictures stay those of the frame's own pose, as a detail says).
    fn run(
        mut self,
        mesh: &Mesh,
        loader: &FrameLoader,
        seed: u64,
        frames: &mut [EvalFrame],
        page: &mut [ReportFrame],
        workspace: &mut ReprojectionWorkspace,
    ) {
        let changed = neighbour_pass(
            mesh,
            &self.frames,
            &mut self.reports,
            loader,
            &self.config,
            seed,
        );
        for (index, report) in self.reports.iter().enumerate() {
            let Some(frame) = frames.get_mut(self.positions[index]) else {
                continue;
            };
            let (truth, camera) = self.truths[index];
            let mut delta_to_truth = |pose_camera: &Camera, pose: &Rigid3| {
                mutual_reprojection_error_px(mesh, pose_camera, pose, &camera, &truth, workspace)
            };
            frame.neighbours = report
                .neighbours
                .iter()
                .map(|tried| NeighbourEval {
                    neighbour: tried.neighbour.clone(),
                    steps: tried.steps,
                    view: tried.view,
                    delta_px: tried.check.as_ref().ok().and_then(|check| {
                        delta_to_truth(&check.hypothesis.camera, &check.hypothesis.cam_from_world)
                    }),
                    apart_px: tried.check.as_ref().ok().and_then(|check| check.apart_px),
                    peak: tried.check.as_ref().ok().and_then(|check| check.peak),
                    consensus: tried.check.as_ref().ok().map(|check| {
                        (
                            check.hypothesis.consensus,
                            check.hypothesis.correspondence_count,
                        )
                    }),
                    outcome: if tried.confirmed() {
                        format!("{}: {:?}", tried.outcome(), tried.decision)
                    } else {
                        tried.outcome()
                    },
                })
                .collect();
            if changed.contains(&index) {
                frame.accepted = report.accepted;
                frame.reason = report.reason.clone();
                let output = match (report.camera, report.cam_from_world) {
                    (Some(camera), Some(pose)) => Some((camera, pose)),
                    _ => report
                        .rejected_candidate
                        .map(|candidate| (candidate.camera, candidate.cam_from_world)),
                };
                frame.final_delta_px =
                    output.and_then(|(pose_camera, pose)| delta_to_truth(&pose_camera, &pose));
                let line = format!(
                    "step \"neighbour\": {} → {}, δ {}",
                    frame.name,
                    if frame.accepted {
                        "accepted"
                    } else {
                        "rejected"
                    },
                    frame
                        .final_delta_px
                        .map_or("-".to_string(), |d| format!("{d:.2} px"))
                );
                println!("{line}");
                if let Some(row) = page.get_mut(self.page_rows[index]) {
                    row.verdict = if frame.accepted {
                        FrameVerdict::Accepted
                    } else {
                        FrameVerdict::Rejected
                    };
                    row.reason = frame.reason.clone();
                    row.delta_px = frame.final_delta_px;
                    let lender = report
                        .neighbours
                        .last()
                        .map_or("-", |n| n.neighbour.as_str());
                    row.details.push((
                        "step \"neighbour\"".to_string(),
                        format!(
                            "{} by the pose from {lender}; the pictures show the frame's own pose",
                            if frame.accepted {
                                "accepted"
                            } else {
                                "rejected"
                            }
                        ),
                    ));
                }
            }
        }
    }
}

/// Confidence bins of the calibration table.
const CALIBRATION_BINS: usize = 10;

/// The calibration table of each method: per confidence bin, frames with an output pose, the
/// share of them that is correct, and how many were accepted.
fn calibration_markdown(
    calibration: &BTreeMap<&str, Vec<CalibrationBin>>,
    false_accept_px: f64,
) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "\n## Calibration: share of correct poses per confidence bin (all levels)\n\n\
Every frame with an output pose, accepted or not; correct = δ to ground truth ≤ {false_accept_px:.2} px.\n"
    );
    for (method, bins) in calibration {
        let _ = writeln!(
            out,
            "| {method}: confidence | frames | correct | share correct | accepted |\n|---|---|---|---|---|"
        );
        for bin in bins.iter().filter(|b| b.frames > 0) {
            let _ = writeln!(
                out,
                "| {:.1}–{:.1} | {} | {} | {:.0} % | {} |",
                bin.lower,
                bin.upper,
                bin.frames,
                bin.correct,
                100.0 * bin.correct as f64 / bin.frames as f64,
                bin.accepted
            );
        }
        out.push('\n');
    }
    out
}

/// The heading fallback's two registrations against the truth (`delta`: δ of a pose to it).
pub(super) fn sweep_eval(
    sweep: &HeadingSweepReport,
    mut delta: impl FnMut(&RejectedCandidate) -> Option<f64>,
) -> SweepEval {
    let mut pass = |report: &PassReport| PassEval {
        accepted: report.accepted,
        confidence: report.confidence,
        delta_px: report.pose.as_ref().and_then(&mut delta),
        reason: report.reason.clone(),
    };
    SweepEval {
        first: pass(&sweep.first),
        retry: sweep.retry.as_ref().ok().map(&mut pass),
        carried: sweep.carried,
        sweep_ms: sweep.sweep_ms,
    }
}

/// [`SweepEval`] of a diagnosis whose fallback ran (its first pass and its retry, as diagnosed).
pub(super) fn sweep_eval_of_diagnosis(diagnosis: &FrameDiagnosis) -> Option<SweepEval> {
    let sweep = diagnosis.heading_sweep.as_ref()?;
    let pass = |d: &FrameDiagnosis| PassEval {
        accepted: d.verdict.accepted(),
        confidence: d.verdict.confidence,
        delta_px: d.chosen_delta_px,
        reason: d.verdict.rejection().map(|r| r.to_string()),
    };
    Some(SweepEval {
        first: pass(diagnosis),
        retry: sweep.retry.as_deref().ok().map(pass),
        carried: sweep.carried,
        sweep_ms: 0.0,
    })
}

/// A frame's search diagnoses moved into `into`: the first pass's, then the heading fallback's
/// retry's as "<name> (sweep)".
pub(super) fn take_search_diagnoses(
    diagnosis: &mut FrameDiagnosis,
    name: &str,
    into: &mut Vec<(String, Option<bool>, SearchDiagnosis)>,
) {
    if let Some(search) = diagnosis.search.take() {
        into.push((name.to_string(), Some(diagnosis.verdict.accepted()), search));
    }
    if let Some(Ok(retry)) = diagnosis.heading_sweep.as_mut().map(|s| s.retry.as_mut()) {
        if let Some(search) = retry.search.take() {
            into.push((
                format!("{name} (sweep)"),
                Some(retry.verdict.accepted()),
                search,
            ));
        }
    }
}

/// "a pass: δ D px, accepted|rejected (confidence C)".
fn pass_text(pass: &PassEval) -> String {
    format!(
        "δ {} px, {} ({:.2})",
        pass.delta_px.map_or("–".to_string(), |d| format!("{d:.1}")),
        if pass.accepted {
            "accepted"
        } else {
            "rejected"
        },
        pass.confidence
    )
}

/// The heading fallback on a frame's log line.
pub(super) fn sweep_line(sweep: &SweepEval) -> String {
    format!(
        "[heading sweep: first pass {}; retry {}; carried: {}]",
        pass_text(&sweep.first),
        sweep
            .retry
            .as_ref()
            .map_or("gave no result".to_string(), pass_text),
        sweep.carried
    )
}

/// results.md's table of the heading fallback: one line per frame it ran on.
fn sweep_markdown(
    results: &BTreeMap<(Level, &'static str), Vec<EvalFrame>>,
    false_accept_px: f64,
) -> String {
    let rows: Vec<(&Level, &str, &EvalFrame, &SweepEval)> = results
        .iter()
        .flat_map(|((level, method), frames)| {
            frames
                .iter()
                .filter_map(move |f| f.heading_sweep.as_ref().map(|s| (level, *method, f, s)))
        })
        .collect();
    if rows.is_empty() {
        return String::new();
    }
    let mut out = String::new();
    let _ = writeln!(
        out,
        "\n## Heading sweep (fallback)\n\nFrames the first pass did not accept, registered once more with headings over the \
full circle: each registration's output (or would-be output) δ to the truth, its verdict and confidence, and \
which one the frame's result carries (an accepted retry, else the more confident rejection). Near: the retry's \
pose within {false_accept_px:.2} px of the truth.\n"
    );
    let _ = writeln!(
        out,
        "| level | method | frame | initial δ | first pass δ | first pass verdict (confidence) | retry δ | retry verdict (confidence) | near | carried | the frame's verdict |\n|---|---|---|---|---|---|---|---|---|---|---|"
    );
    let px = |d: Option<f64>| d.map_or("–".to_string(), |d| format!("{d:.2}"));
    let verdict = PassEval::verdict_text;
    let mut near = 0;
    for (level, method, frame, sweep) in &rows {
        let retry_near = sweep
            .retry
            .as_ref()
            .and_then(|r| r.delta_px)
            .is_some_and(|d| d <= false_accept_px);
        near += usize::from(retry_near);
        let _ = writeln!(
            out,
            "| {level} | {method} | {} | {:.1} | {} | {} | {} | {} | {} | {} | {} |",
            frame.name,
            frame.initial_delta_px,
            px(sweep.first.delta_px),
            verdict(&sweep.first),
            px(sweep.retry.as_ref().and_then(|r| r.delta_px)),
            sweep
                .retry
                .as_ref()
                .map_or("no result".to_string(), verdict),
            if retry_near { "yes" } else { "no" },
            match sweep.carried {
                Pass::First => "first pass",
                Pass::HeadingSweep => "retry",
            },
            if frame.accepted {
                "accepted".to_string()
            } else {
                frame.reason.clone().unwrap_or_else(|| "rejected".into())
            },
        );
    }
    let _ = writeln!(
        out,
        "\nThe sweep ran on {} frames; its pose was near the truth on {near}, accepted on {}.",
        rows.len(),
        rows.iter()
            .filter(|(_, _, _, s)| s.retry.as_ref().is_some_and(|r| r.accepted))
            .count()
    );
    out
}

/// One frame's result under one method.
struct FrameOutcome {
    accepted: bool,
    final_delta_px: Option<f64>,
    confidence: f64,
    evidence: Option<FrameEvidence>,
    reason: Option<String>,
    total_ms: f64,
    /// The pose search's share of `total_ms` (0 when it did not run).
    search_ms: f64,
    /// The full-circle heading fallback's share of `total_ms` (0 when it did not run).
    heading_sweep_ms: f64,
    /// The fallback's two registrations against the truth, when it ran.
    heading_sweep: Option<SweepEval>,
    /// The registration's time per step (None for baselines and the diagnoses).
    timings: Option<StageTimings>,
}

fn results_markdown(
    args: &EvalArgs,
    stats: &BTreeMap<(Level, &str), CellStats>,
    methods: &[&str],
    false_accept_px: f64,
    heading_tilt_deg: Option<f64>,
) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# asgreg eval: {}\n\nQuery: {:?}. δ = mutual reprojection error (paper eq. 5) to ground truth, px. \
False accept: accepted with δ > {false_accept_px:.2} px (5 % of the long side). \
ICP has no self-check: its 'accepted' is the paper's success criterion δ < 20 px, measured against ground truth.\n",
        args.scene.display(),
        args.query
    );
    if let Some(tilt_deg) = heading_tilt_deg {
        let _ = writeln!(
            out,
            "The heading level registers with its prior's pitch and roll trusted within {tilt_deg}° (a drone's IMU; `register --prior-tilt-deg`).\n"
        );
    }
    let _ = writeln!(out, "## Accuracy of accepted frames (paper Table 1)\n");
    let _ = write!(out, "| initial δ (px) |");
    for method in methods {
        let _ = write!(out, " {method}: δ mean ± std (range) |");
    }
    let _ = writeln!(out);
    let _ = writeln!(out, "|---|{}", "---|".repeat(methods.len()));
    for &level in &args.levels {
        let initial = methods
            .iter()
            .filter_map(|m| stats.get(&(level, *m)))
            .map(|s| s.mean_initial_px)
            .next()
            .unwrap_or(f64::NAN);
        let _ = write!(out, "| {level} (measured {initial:.1}) |");
        for method in methods {
            let cell = stats
                .get(&(level, *method))
                .map(format_accuracy)
                .unwrap_or_default();
            let _ = write!(out, " {cell} |");
        }
        let _ = writeln!(out);
    }
    let _ = writeln!(out, "\n## Acceptance and false accepts\n");
    let _ = write!(out, "| initial δ (px) |");
    for method in methods {
        let _ = write!(
            out,
            " {method}: accepted | {method}: false accepts | {method}: s/frame |"
        );
    }
    let _ = writeln!(out);
    let _ = writeln!(out, "|---|{}", "---|---|---|".repeat(methods.len()));
    for &level in &args.levels {
        let _ = write!(out, "| {level} |");
        for method in methods {
            match stats.get(&(level, *method)) {
                Some(s) => {
                    let _ = write!(
                        out,
                        " {}/{} ({:.0} %) | {} | {:.1} |",
                        s.accepted,
                        s.frames,
                        s.accepted_percent,
                        s.false_accepts,
                        s.mean_ms_per_frame / 1e3
                    );
                }
                None => {
                    let _ = write!(out, " – | – | – |");
                }
            }
        }
        let _ = writeln!(out);
    }
    out
}

/// Two small line charts side by side: mean δ of accepted frames and acceptance, per level
/// (results.svg, and inline in report.html).
fn plot_svg(stats: &BTreeMap<(Level, &str), CellStats>, methods: &[&str]) -> String {
    const COLOURS: [&str; 4] = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd"];
    // The px levels only: the heading level has no place on the δ axis.
    let levels: Vec<u32> = {
        let mut l: Vec<u32> = stats
            .keys()
            .filter_map(|(level, _)| match level {
                Level::Px(px) => Some(*px),
                Level::Heading => None,
            })
            .collect();
        l.dedup();
        l
    };
    let max_level = f64::from(levels.iter().copied().max().unwrap_or(1).max(1));
    let max_delta = stats
        .values()
        .filter_map(|s| s.mean_px)
        .fold(1.0f64, f64::max)
        * 1.2;
    let mut svg = String::from(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"760\" height=\"320\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"760\" height=\"320\" fill=\"white\"/>\n",
    );
    let panels = [
        ("mean δ of accepted frames (px)", max_delta, 0usize),
        ("accepted (%)", 100.0, 1),
    ];
    for (panel_index, (title, y_max, kind)) in panels.iter().enumerate() {
        let x0 = 60.0 + 370.0 * panel_index as f64;
        let (width, height, y0) = (280.0, 220.0, 40.0);
        let _ = writeln!(
            svg,
            "<text x=\"{:.0}\" y=\"24\">{title}</text><rect x=\"{x0}\" y=\"{y0}\" width=\"{width}\" height=\"{height}\" fill=\"none\" stroke=\"#888\"/>",
            x0
        );
        let _ = writeln!(
            svg,
            "<text x=\"{:.0}\" y=\"{:.0}\">initial δ (px)</text><text x=\"{:.0}\" y=\"{:.0}\">{y_max:.1}</text><text x=\"{:.0}\" y=\"{:.0}\">0</text>",
            x0 + 100.0,
            y0 + height + 34.0,
            x0 - 45.0,
            y0 + 4.0,
            x0 - 20.0,
            y0 + height
        );
        for level in &levels {
            let x = x0 + width * f64::from(*level) / max_level;
            let _ = writeln!(
                svg,
                "<text x=\"{:.0}\" y=\"{:.0}\" text-anchor=\"middle\">{level}</text>",
                x,
                y0 + height + 16.0
            );
        }
        for (method_index, method) in methods.iter().enumerate() {
            let colour = COLOURS[method_index % COLOURS.len()];
            let points: Vec<String> = levels
                .iter()
                .filter_map(|level| {
                    let s = stats.get(&(Level::Px(*level), *method))?;
                    let value = if *kind == 0 {
                        s.mean_px?
                    } else {
                        s.accepted_percent
                    };
                    let x = x0 + width * f64::from(*level) / max_level;
                    let y = y0 + height * (1.0 - value / y_max);
                    Some(format!("{x:.1},{y:.1}"))
                })
                .collect();
            let _ = writeln!(
                svg,
                "<polyline points=\"{}\" fill=\"none\" stroke=\"{colour}\" stroke-width=\"2\"/>",
                points.join(" ")
            );
            let _ = writeln!(
                svg,
                "<text x=\"{:.0}\" y=\"{:.0}\" fill=\"{colour}\">{method}</text>",
                x0 + 8.0,
                y0 + 16.0 + 14.0 * method_index as f64
            );
        }
    }
    svg.push_str("</svg>\n");
    svg
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Parser)]
    struct Command {
        #[command(flatten)]
        eval: EvalArgs,
    }

    fn eval_args(scene: &Path, extra: &[&str]) -> EvalArgs {
        let mut argv = vec![
            "eval",
            "--scene",
            scene.to_str().unwrap(),
            "--out",
            "unused",
        ];
        argv.extend_from_slice(extra);
        Command::try_parse_from(argv).unwrap().eval
    }

    /// Step "neighbour" follows the scene: a flight's photos in their order (`feed`, as the
    /// pipeline), a collection's in rounds (`set`); `--neighbour-order` overrides it.
    #[test]
    fn step_neighbour_follows_the_scenes_order() {
        let scene = tempfile::tempdir().unwrap();
        let order =
            |extra: &[&str]| scene_neighbour_order(&eval_args(scene.path(), extra)).unwrap();
        assert_eq!(order(&[]), NeighbourOrderArg::Set, "no scene.json");
        std::fs::write(
            scene.path().join("scene.json"),
            r#"{"config": {"flight_path": true}}"#,
        )
        .unwrap();
        assert_eq!(order(&[]), NeighbourOrderArg::Feed);
        assert_eq!(order(&["--neighbour-order", "set"]), NeighbourOrderArg::Set);
        std::fs::write(scene.path().join("scene.json"), r#"{"config": {}}"#).unwrap();
        assert_eq!(order(&[]), NeighbourOrderArg::Set);
        assert_eq!(
            order(&["--neighbour-order", "feed"]),
            NeighbourOrderArg::Feed
        );
        std::fs::write(scene.path().join("scene.json"), "not json").unwrap();
        assert!(scene_neighbour_order(&eval_args(scene.path(), &[])).is_err());
    }

    /// The heading level, a drone's prior, registers with the IMU tilt the scene was made with;
    /// the px levels, Gaussian on all six degrees of freedom, trust no tilt.
    #[test]
    fn the_heading_level_trusts_the_tilt_the_scene_was_made_with() {
        let scene = tempfile::tempdir().unwrap();
        std::fs::write(
            scene.path().join("scene.json"),
            r#"{"config": {"heading_noise": {"tilt_max_deg": 1.5}}}"#,
        )
        .unwrap();
        let args = eval_args(scene.path(), &["--levels", "30,heading"]);
        let tilt = heading_level_tilt_deg(&args).unwrap();
        assert_eq!(tilt, Some(1.5));
        assert_eq!(
            level_coarse(&args.coarse, Level::Heading, tilt).prior_tilt_deg,
            1.5
        );
        assert_eq!(
            level_coarse(&args.coarse, Level::Px(30), tilt).prior_tilt_deg,
            0.0
        );

        let given = eval_args(
            scene.path(),
            &["--levels", "heading", "--prior-tilt-deg", "3"],
        );
        assert_eq!(heading_level_tilt_deg(&given).unwrap(), Some(3.0));
        let untrusted = eval_args(
            scene.path(),
            &["--levels", "heading", "--untrusted-heading-tilt"],
        );
        assert_eq!(heading_level_tilt_deg(&untrusted).unwrap(), None);
        let px_only = eval_args(scene.path(), &["--levels", "30"]);
        assert_eq!(heading_level_tilt_deg(&px_only).unwrap(), None);

        std::fs::write(scene.path().join("scene.json"), r#"{"config": {}}"#).unwrap();
        let message = format!("{:#}", heading_level_tilt_deg(&args).unwrap_err());
        assert!(
            message.contains("config.heading_noise.tilt_max_deg")
                && message.contains("--untrusted-heading-tilt"),
            "{message}"
        );
    }

    /// --frames names frames of the levels' images.txt; a misspelt one is an error naming it
    /// and the file.
    #[test]
    fn a_frame_asked_for_must_be_in_every_level() {
        let scene = tempfile::tempdir().unwrap();
        let level_dir = scene.path().join("initial/30");
        std::fs::create_dir_all(&level_dir).unwrap();
        std::fs::write(
            level_dir.join("images.txt"),
            "1 1 0 0 0 0 0 0 1 view_000.jpg\n\n2 1 0 0 0 0 0 0 1 view_001.jpg\n\n",
        )
        .unwrap();
        let path = level_dir.join("images.txt");
        let images = read_images_txt(&path).unwrap();
        let one = eval_args(
            scene.path(),
            &["--levels", "30", "--frames", "view_001.jpg"],
        );
        check_frames_exist(&one.frames, &images, &path).unwrap();
        let misspelt = eval_args(scene.path(), &["--levels", "30", "--frames", "view_01.jpg"]);
        let message = format!(
            "{:#}",
            check_frames_exist(&misspelt.frames, &images, &path).unwrap_err()
        );
        assert!(
            message.contains("\"view_01.jpg\"") && message.contains("initial/30/images.txt"),
            "{message}"
        );
    }
}
