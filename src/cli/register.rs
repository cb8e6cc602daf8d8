//! `asgreg register`: refines the initial poses of a folder of photos against a mesh and writes
//! the accepted poses (COLMAP text and binary, omega-phi-kappa CSV), a per-frame report and
//! before/after overlays (loose PNGs and report.html, `report_html`). Photos are registered with their working camera (undistorted, at the
//! working width: `frame_files`) and the poses are written for their own camera.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use asgreg::batch::{neighbour_pass, register_batch_frame_with, BatchFrame, FrameReport};
use asgreg::core::confidence::ConfidenceConfig;
use asgreg::core::edge_align::{AlignedKinds, EdgeAlignConfig};
use asgreg::core::flow_consistency::MatchConfig;
use asgreg::core::frame::{
    IntrinsicsMode, NeighbourAgreement, NeighbourPoseConfig, NeighbourWarp, QueryMode,
    RegistrationConfig, UnknownIntrinsics,
};
use asgreg::core::image::Image;
use asgreg::core::pose_search::PoseSearchConfig;
use asgreg::core::shading::AsgOptions;
use asgreg::core::verify::{ConvergenceMeasure, OutputChoice, VerifyConfig};
use asgreg::frame_files::{depth_path_for, FrameLoader, DEFAULT_WORKING_WIDTH_PX};
use asgreg::io::colmap::{ColmapModel, ImagePose};
use asgreg::io::colmap_model::write_model_dir;
use asgreg::io::images::save_rgb_png;
use asgreg::io::mesh_file::check_mesh_fits;
use asgreg::io::opk::{write_opk_csv, OPK_FILE};
use asgreg::io::output::prepare_output_dir;
use asgreg::report_html::{
    write_report_html, FrameVerdict, Picture, ReportFrame, ReportPage, THUMBNAIL_WIDTH_PX,
};

use super::inputs::load_posed_inputs;
use super::overlay::{working_overlays, OverlayView};

#[derive(clap::Args, Debug)]
pub struct RegisterArgs {
    /// The untextured mesh (PLY or OBJ).
    #[arg(long)]
    pub mesh: PathBuf,
    /// Folder with the photos named in the poses file.
    #[arg(long)]
    pub images: PathBuf,
    /// COLMAP cameras.txt or cameras.bin, or a model folder (known intrinsics, or the nominal ones when unknown).
    #[arg(long)]
    pub cameras: PathBuf,
    /// COLMAP images.txt or images.bin, or a model folder, with the initial poses.
    #[arg(long)]
    pub poses: PathBuf,
    /// Known intrinsics (EPnP), unknown (DLT, estimated per image) or only the focal length
    /// unknown (principal point at the centre, no skew).
    #[arg(long, value_enum, default_value_t = IntrinsicsArg::Known)]
    pub intrinsics: IntrinsicsArg,
    /// Folder of the photos' depth maps (`<image stem>.pfm`): the query becomes the ASG of the
    /// depth's normals (the paper's mode) instead of the photo's gradient, unless --query says.
    #[arg(long)]
    pub depth: Option<PathBuf>,
    /// The image standing for the photo: `depth` when --depth is given, else `gradient`;
    /// `depth` and `mixed` need --depth.
    #[arg(long, value_enum)]
    pub query: Option<QueryArg>,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of the random draws (coarse poses, RANSAC): the same seed gives the same poses.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[command(flatten)]
    pub coarse: CoarseArgs,
    /// Width (px) at which photos are registered: wider ones are averaged down to it (height in
    /// proportion) and the poses are written for the photo's own camera; 0 registers every
    /// photo at its own size. The default is the paper's 505 px width. Photos whose camera has
    /// lens distortion (SIMPLE_RADIAL, RADIAL, OPENCV) are also undistorted to a PINHOLE camera
    /// the way COLMAP's image_undistorter does it; the output keeps their camera.
    #[arg(long, default_value_t = DEFAULT_WORKING_WIDTH_PX, value_name = "PX")]
    pub working_width: u32,
    /// Register only the first N frames of the poses file.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Skip the overlay pictures.
    #[arg(long)]
    pub no_overlays: bool,
    /// Refuse a mesh that would take more memory than this to load (MiB), judged from its header
    /// before loading it (PLY: declared vertices and faces; OBJ: the file's size).
    #[arg(long, value_name = "MIB")]
    pub max_mesh_mib: Option<u64>,
    /// A COLMAP model (folder, text or binary) with the true poses of (some of) the photos, matched
    /// by name: each frame's δ to the truth before and after (under the truth's camera) goes into
    /// the output, report.json and report.html. For a data set with surveyed or SfM poses.
    #[arg(long, value_name = "MODEL")]
    pub truth: Option<PathBuf>,
    /// With --truth: also run each frame's steps one by one against its true pose (the
    /// diagnosis of `eval --diagnose`: flow and correspondence errors within 1/2/5 px, lifting,
    /// solver and its oracle, choice, refinement, the pose search) and write diagnosis.md,
    /// diagnosis.json (and search_diagnosis.md/json). Runs each frame a second time.
    #[arg(long, requires = "truth")]
    pub diagnose: bool,
}

/// A frame's mutual reprojection error δ to its true pose, px: under the initial pose and under
/// the accepted one.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct TruthDelta {
    pub initial_px: Option<f64>,
    pub final_px: Option<f64>,
    /// A rejected frame's would-be output (never a result).
    pub rejected_candidate_px: Option<f64>,
    /// When the heading fallback ran: both registrations against the truth.
    pub heading_sweep: Option<asgreg::eval::SweepEval>,
}

/// δ of each frame's initial and accepted pose to the truth of `truth_path` (`None` for frames
/// the truth does not hold), each pair of poses under the truth's camera.
fn truth_deltas(
    truth_path: &Path,
    mesh: &asgreg::core::mesh::Mesh,
    frames: &[BatchFrame],
    reports: &[FrameReport],
) -> anyhow::Result<Vec<Option<TruthDelta>>> {
    use asgreg::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};
    let (cameras, cameras_file) = asgreg::io::colmap_model::read_cameras_at(truth_path)?;
    let (images, images_file) = asgreg::io::colmap_model::read_images_at(truth_path)?;
    let mut workspace = ReprojectionWorkspace::new();
    let mut deltas = Vec::with_capacity(frames.len());
    for (frame, report) in frames.iter().zip(reports) {
        let Some(truth) = images.iter().find(|t| t.name == frame.name) else {
            tracing::warn!("{}: not in {}, no δ", frame.name, images_file.display());
            deltas.push(None);
            continue;
        };
        let camera = cameras.get(&truth.camera_id).with_context(|| {
            format!(
                "{}: {} uses camera {}, which {} does not define",
                images_file.display(),
                truth.name,
                truth.camera_id,
                cameras_file.display()
            )
        })?;
        let mut delta_of = |pose: &asgreg::batch::RejectedCandidate| {
            mutual_reprojection_error_px(
                mesh,
                &pose.camera,
                &pose.cam_from_world,
                camera,
                &truth.cam_from_world,
                &mut workspace,
            )
        };
        let rejected_candidate_px = report.rejected_candidate.as_ref().and_then(&mut delta_of);
        let heading_sweep = report
            .heading_sweep
            .as_ref()
            .map(|sweep| super::eval::sweep_eval(sweep, &mut delta_of));
        let mut delta = |pose: &asgreg::core::rigid::Rigid3| {
            mutual_reprojection_error_px(
                mesh,
                camera,
                pose,
                camera,
                &truth.cam_from_world,
                &mut workspace,
            )
        };
        deltas.push(Some(TruthDelta {
            initial_px: delta(&frame.initial_cam_from_world),
            final_px: report
                .cam_from_world
                .filter(|_| report.accepted)
                .and_then(|pose| delta(&pose)),
            rejected_candidate_px,
            heading_sweep,
        }));
    }
    Ok(deltas)
}

/// `--diagnose`: each frame the truth holds run step by step against its true pose
/// (`asgreg::diagnose`, as `eval --diagnose`), the tables written to `diagnosis.md` /
/// `search_diagnosis.md` (and JSON) in the output folder and printed.
fn diagnose_frames(
    args: &RegisterArgs,
    truth_path: &Path,
    mesh: &asgreg::core::mesh::Mesh,
    frames: &[BatchFrame],
    config: &RegistrationConfig,
    loader: &FrameLoader,
) -> anyhow::Result<()> {
    use asgreg::diagnose::{diagnose_frame, DiagnosisSummary, FrameDiagnosis};
    let (images, images_file) = asgreg::io::colmap_model::read_images_at(truth_path)?;
    const RUN: &str = "register";
    let mut diagnoses: BTreeMap<(&str, &str), Vec<(String, FrameDiagnosis)>> = BTreeMap::new();
    let mut search_diagnoses: super::eval::SearchDiagnosesBy<&str> = BTreeMap::new();
    let bar = progress_bar(frames.len(), "diagnosing");
    for frame in frames {
        bar.inc(1);
        let Some(truth) = images.iter().find(|t| t.name == frame.name) else {
            tracing::warn!(
                "{}: not in {}, no diagnosis",
                frame.name,
                images_file.display()
            );
            continue;
        };
        let files = match frame.load_with(loader) {
            Ok(files) => files,
            Err(error) => {
                tracing::warn!("{}: no diagnosis: {error}", frame.name);
                continue;
            }
        };
        match diagnose_frame(
            mesh,
            &frame.input(&files, args.seed),
            &truth.cam_from_world,
            config,
        ) {
            Ok(mut diagnosis) => {
                super::eval::take_search_diagnoses(
                    &mut diagnosis,
                    &frame.name,
                    search_diagnoses.entry((RUN, "ASG")).or_default(),
                );
                diagnoses
                    .entry((RUN, "ASG"))
                    .or_default()
                    .push((frame.name.clone(), diagnosis));
            }
            Err(error) => tracing::warn!("{}: no diagnosis: {error}", frame.name),
        }
    }
    bar.finish_and_clear();
    let json = serde_json::json!({
        "truth": truth_path.display().to_string(),
        "summary": DiagnosisSummary::of(diagnoses.values().flatten().map(|(_, d)| d)),
        "frames": diagnoses.values().flatten().map(|(name, d)| serde_json::json!({"name": name, "diagnosis": d})).collect::<Vec<_>>(),
    });
    super::eval::write_diagnosis(
        &args.out,
        "diagnosis",
        &super::eval::diagnosis_markdown(&diagnoses),
        &json,
    )?;
    if !search_diagnoses.is_empty() {
        let json = serde_json::json!({
            "frames": search_diagnoses.values().flatten().map(|(name, accepted, d)| serde_json::json!({"name": name, "accepted": accepted, "search": d})).collect::<Vec<_>>(),
        });
        super::eval::write_diagnosis(
            &args.out,
            "search_diagnosis",
            &super::eval::search_diagnosis_markdown(&search_diagnoses),
            &json,
        )?;
    }
    Ok(())
}

/// "mean M px, max X px (N frames)" of the values present, or "none".
fn delta_summary(values: impl Iterator<Item = f64>) -> String {
    let values: Vec<f64> = values.collect();
    if values.is_empty() {
        return "none".to_string();
    }
    format!(
        "mean {:.2} px, max {:.2} px ({} frames)",
        values.iter().sum::<f64>() / values.len() as f64,
        values.iter().copied().fold(0.0, f64::max),
        values.len()
    )
}

/// How the coarse poses are drawn around the initial pose, and how far their refined poses must
/// converge to be accepted. Every default is the library's (`RegistrationConfig::default()`).
#[derive(clap::Args, Debug, Clone, Copy)]
pub struct CoarseArgs {
    /// Coarse poses per frame.
    #[arg(long, default_value_t = RegistrationConfig::default().coarse_pose_count)]
    pub coarse_poses: usize,
    /// Coarse poses about the second centre of a frame whose pose search gives it two (at most
    /// --coarse-poses; default: --coarse-poses).
    #[arg(long)]
    pub other_centre_coarse_poses: Option<usize>,
    /// SIFT flow: belief-propagation iterations at the coarsest level (default: the
    /// registration's flow schedule, `SiftFlowConfig::fast`).
    #[arg(long, default_value_t = RegistrationConfig::default().matching.sift_flow.top_iterations)]
    pub flow_top_iterations: usize,
    /// Rotation noise of the coarse poses, degrees (σ per axis).
    #[arg(long, default_value_t = RegistrationConfig::default().coarse_rotation_sigma_deg)]
    pub coarse_rotation_deg: f64,
    /// Camera-centre noise of the coarse poses, as a fraction of the median scene depth (σ per axis).
    #[arg(long, default_value_t = RegistrationConfig::default().coarse_translation_sigma_fraction)]
    pub coarse_translation_fraction: f64,
    /// Verification: the agreeing refined poses' spread may be at most this fraction of their
    /// coarse poses' spread (1 or more turns the convergence test off).
    #[arg(long, default_value_t = RegistrationConfig::default().verify.max_convergence_ratio)]
    pub max_convergence_ratio: f64,
    /// Verification: what --max-convergence-ratio bounds: the refined poses' spread over their
    /// coarse poses' (`spread`), or the share of the coarse poses' differences the refined poses
    /// keep (`carried`: the flow's noise averages out of it).
    #[arg(long, value_enum, default_value_t = ConvergenceMeasureArg::Spread)]
    pub convergence_measure: ConvergenceMeasureArg,
    /// Lifting: matches within this many px of a depth discontinuity of the rendering are not
    /// lifted (0: every match is).
    #[arg(long, default_value_t = RegistrationConfig::default().lift_edge_margin_px)]
    pub lift_edge_margin_px: usize,
    /// Skip the final refinement (alignment of the chosen pose with the photo's edges).
    #[arg(long)]
    pub no_edge_align: bool,
    /// Final refinement: search half-length of its first level, px (levels halve it down to 2).
    #[arg(long, default_value_t = RegistrationConfig::default().edge_align.initial_search_radius_px)]
    pub edge_search_px: f64,
    /// Final refinement: also align from the chosen pose with only the levels from this search
    /// half-length down, px, its end kept as --edge-short-schedule-rule says (0: one schedule).
    #[arg(long, default_value_t = RegistrationConfig::default().edge_align.short_schedule_radius_px)]
    pub edge_short_schedule_px: f64,
    /// Final refinement: what decides whether the short schedule's end replaces the full one's.
    #[arg(long, value_enum, default_value_t = KeepRuleArg::SupportAndCorrelation)]
    pub edge_short_schedule_rule: KeepRuleArg,
    /// Final refinement: how many starting poses (the chosen one and other refined poses of its
    /// agreeing group); the other starts run the short schedule and win as its rule says (without
    /// one: the full schedule, and the most edge support wins).
    #[arg(long, default_value_t = RegistrationConfig::default().edge_align.starts)]
    pub edge_starts: usize,
    /// Final refinement: with several centres of the pose search, each centre's refinement also
    /// starts from the other centres' outputs within its reach (`--edge-centre-starts false`:
    /// each centre on its own).
    #[arg(long, default_value_t = RegistrationConfig::default().edge_align.centre_starts, action = clap::ArgAction::Set)]
    pub edge_centre_starts: bool,
    /// Final refinement: undo a level whose result lowers the edge support.
    #[arg(long)]
    pub edge_check_levels: bool,
    /// Final refinement: the rounding undone on each pose's edges when the support judges
    /// levels, starts and the kept pose: the alignment's estimate on both (`shared`), none
    /// (`as-rendered`), or each pose's own fit (`each-own`).
    #[arg(long, value_enum, default_value_t = RoundingJudgeArg::Shared)]
    pub edge_rounding_judge: RoundingJudgeArg,
    /// Final refinement: moving edges (default), the dense feature-metric alignment, or both in
    /// turn (`edges-then-dense`).
    #[arg(long, value_enum, default_value_t = RefineMethodArg::Edges)]
    pub refine_method: RefineMethodArg,
    /// Final refinement: which photo ridge on a sample's search line it is matched to: the
    /// strongest (weighed with the distance, default) or the nearest (multiple-hypothesis moving
    /// edges).
    #[arg(long, value_enum, default_value_t = RidgeChoiceArg::Strongest)]
    pub edge_ridge_choice: RidgeChoiceArg,
    /// Final refinement: weigh each edge match by its distinctiveness (1 − second-best ridge's
    /// score / best's on its search line).
    #[arg(long)]
    pub edge_distinct_weights: bool,
    /// Final refinement: do not estimate the model's edge rounding radius with the pose (by
    /// default it is: a smoothed, Poisson-like model rounds its edges, and the photo's edges lie
    /// where the sharp ones would).
    #[arg(long)]
    pub no_edge_rounding: bool,
    /// Flow: a rendering pixel takes part only where a model edge (ASG at least the final
    /// refinement's model-edge threshold) lies within its descriptor's support.
    #[arg(long)]
    pub flow_near_model_edges: bool,
    /// Final refinement: the coarse levels (search radius above the evidence's 4 px) turn the
    /// camera only; the fine levels estimate the whole pose.
    #[arg(long)]
    pub edge_coarse_rotation_only: bool,
    /// Final refinement: what decides whether the aligned pose replaces the verified one: a
    /// higher edge support (default), that and a correlation with the photo not lower, or a
    /// higher correlation alone.
    #[arg(long, value_enum, default_value_t = KeepRuleArg::Support)]
    pub edge_keep: KeepRuleArg,
    /// Renderings: occlusion contours from the depth count as edges (a share of the nearer
    /// depth, e.g. 0.1: two surfaces whose depths differ by more lie on two sides of a contour),
    /// also where both surfaces have the same normal (a flat roof against the ground behind it).
    #[arg(long, value_name = "DEPTH_RATIO")]
    pub asg_occlusion_contours: Option<f32>,
    /// Final refinement: which model edges the estimated rounding is undone on.
    #[arg(long, value_enum, default_value_t = EdgeKindsArg::All)]
    pub edge_rounding_kinds: EdgeKindsArg,
    /// Final refinement: which model edges its steps use (the evidence uses all).
    #[arg(long, value_enum, default_value_t = EdgeKindsArg::All)]
    pub edge_kinds: EdgeKindsArg,
    /// Skip the pose search before the coarse poses (heading, pitch, roll grid scored on the
    /// photo's oriented edges, beams refined by edge alignment): the paper's method alone.
    #[arg(long)]
    pub no_pose_search: bool,
    /// Pose search: the grid's best distinct candidates aligned render-free on their heading
    /// rendering's edge samples before the best beams are refined (0: the grid's best beams are
    /// refined directly).
    #[arg(long, default_value_t = PoseSearchConfig::default().screened_candidates)]
    pub screened_candidates: usize,
    /// Pose search: the grid's best candidates distinct by the screening's own capture (its first
    /// search radius as an angle) also screened, beside the `--screened-candidates` distinct by
    /// the beam separation (0: none).
    #[arg(long, default_value_t = PoseSearchConfig::default().capture_candidates)]
    pub capture_candidates: usize,
    /// Pose search: camera-centre offsets tried around the grid's best candidates, metres either
    /// side along each camera axis (0: the rotation grid alone).
    #[arg(long, default_value_t = PoseSearchConfig::default().position_half_range_m)]
    pub search_position_m: f64,
    /// Pose search: at most this many centre offsets either side per axis.
    #[arg(long, default_value_t = PoseSearchConfig::default().position_max_steps)]
    pub search_position_steps: usize,
    /// Pose search: the grid's best distinct candidates whose centre is searched (the
    /// `--screened-candidates` best after that are screened).
    #[arg(long, default_value_t = PoseSearchConfig::default().positioned_candidates)]
    pub positioned_candidates: usize,
    /// Pose search: when a beam replaces the prior, the prior stays a centre of its own coarse
    /// poses too and verification across the centres decides (`--keep-prior-centre false`: the
    /// beam is the only centre unless the search is ambiguous).
    #[arg(long, default_value_t = PoseSearchConfig::default().keep_prior_centre, action = clap::ArgAction::Set)]
    pub keep_prior_centre: bool,
    /// Pose search: roll (about the camera's optical axis) searched either side of the prior's,
    /// degrees.
    #[arg(long, default_value_t = PoseSearchConfig::default().roll_half_range_deg)]
    pub search_roll_deg: f64,
    /// Pose search: pitch (about the camera's x axis) searched either side of the prior's,
    /// degrees.
    #[arg(long, default_value_t = PoseSearchConfig::default().pitch_half_range_deg)]
    pub search_pitch_deg: f64,
    /// The prior's pitch and roll are known within this many degrees (a drone's IMU: gravity):
    /// the pose search's pitch and roll ranges shrink to cover that, overriding
    /// --search-pitch-deg/--search-roll-deg (0: not known, those ranges).
    #[arg(long, default_value_t = 0.0)]
    pub prior_tilt_deg: f64,
    /// Verification across the pose search's centres: two centres' confirmed poses count as one
    /// only when they lie less than this share of the compatibility threshold apart; farther,
    /// the frame is rejected as ambiguous (0..1; 1: the threshold itself).
    #[arg(long, default_value_t = PoseSearchConfig::default().centre_agreement_share)]
    pub centre_agreement_share: f64,
    /// Pose search: when no pose is accepted, register the frame once more with headings swept
    /// over the full circle at this step, degrees (0: no fallback).
    #[arg(long, default_value_t = PoseSearchConfig::default().heading_sweep_step_deg)]
    pub heading_sweep_deg: f64,
    /// Which pose of the agreeing refined poses verification outputs (and the final refinement
    /// starts from).
    #[arg(long, value_enum, default_value_t = VerifyOutputArg::Medoid)]
    pub verify_output: VerifyOutputArg,
    /// Accept a pose only when the visible model could move at most this much (δ, px) per px of
    /// edge noise given the photo's edges that support it (the δ uncertainty).
    #[arg(long, default_value_t = ConfidenceConfig::default().max_delta_uncertainty_px)]
    pub max_delta_uncertainty_px: f64,
    /// Accept a pose only when moving it 12 px (δ) along the direction its edges see least loses
    /// at least this share of its edge support above chance (0..1; 0: no such test).
    #[arg(long, default_value_t = ConfidenceConfig::default().min_least_seen_drop)]
    pub min_least_seen_drop: f64,
    /// Accept a pose only when moving it 3 px (δ) along the direction its edges see least loses
    /// at least this share of its edge support above chance (0..1; 0: no such test).
    #[arg(long, default_value_t = ConfidenceConfig::default().min_least_seen_near_drop)]
    pub min_least_seen_near_drop: f64,
    /// Accept a pose the plausibility check rejected on the photo's evidence only when its edge
    /// support exceeds chance by at least this share, when the frame's refined poses contradict
    /// it (0..1; 0: off).
    #[arg(long, default_value_t = ConfidenceConfig::default().min_overrule_margin)]
    pub min_overrule_margin: f64,
    /// Accept a pose only when its edge support exceeds chance by at least this share, whatever
    /// the frame's refined poses agree on (0..1; 0: off).
    #[arg(long, default_value_t = ConfidenceConfig::default().min_support_above_chance)]
    pub min_support_above_chance: f64,
    /// Where the photo shows none of the model's edges (at chance at the pose, near it and over
    /// shifts of 64 px), accept a pose on the paper's check alone when every coarse pose refined
    /// into one agreeing group that converged to at most this share of its coarse spread (0..1;
    /// 0: never).
    #[arg(long, default_value_t = ConfidenceConfig::default().max_convergence_at_chance)]
    pub max_convergence_at_chance: f64,
    /// No consensus step after the final refinement (the pose step most model edges agree with
    /// over every photo ridge near them, aligned from there; on by default).
    #[arg(long)]
    pub no_edge_consensus: bool,
    /// The rival-basin test of an accepted pose: the alignment also runs from the output moved
    /// by --rival-reach-px of δ either way along this many directions its edges see least, and
    /// a distinct end that keeps --rival-share of the output's edge support above chance
    /// rejects the frame (0..6; 0: no runs of its own; the other centres' outputs still count
    /// unless --no-rival-centres).
    #[arg(long, default_value_t = EdgeAlignConfig::default().rival_directions)]
    pub rival_directions: usize,
    /// The other centres' outputs of the pose search do not count as rival ends in the
    /// rival-basin test (they do by default: a distinct centre output the photo's edges support
    /// at least as well rejects the chosen pose).
    #[arg(long)]
    pub no_rival_centres: bool,
    /// Without step "neighbour" (on by default: after the frames are registered one by one,
    /// each frame's pose also from its nearest accepted frames' photos (photo-to-photo flow,
    /// lifted on the model at the neighbour's pose), checked by the model's edges; it accepts a
    /// frame not accepted on its own and rejects an accepted one it contradicts; known
    /// intrinsics only).
    #[arg(long)]
    pub no_neighbours: bool,
    /// Step "neighbour": how many neighbours away from a frame the model accepted on its own a
    /// pose may be lent (1: only those frames lend).
    #[arg(long, default_value_t = NeighbourPoseConfig::default().max_steps)]
    pub neighbour_steps: usize,
    /// Step "neighbour": the nearest this many accepted frames are tried, nearest first.
    #[arg(long, default_value_t = NeighbourPoseConfig::default().candidates)]
    pub neighbour_candidates: usize,
    /// Step "neighbour": `feed` — a frame borrows from the frames before it in images.txt and
    /// from the own accepts of the few after it (as the pipeline does, so `register` and `run`
    /// agree); `set` — photos without an order, every accepted frame lends to every other (in
    /// rounds of steps). Default: `feed` in `register`; in `eval`, `feed` for a scene made
    /// along a flight path and `set` for one whose photos were drawn one by one (scene.json).
    #[arg(long, value_enum)]
    pub neighbour_order: Option<NeighbourOrderArg>,
    /// Step "neighbour" in feed order: a frame may also borrow the pose of the frames at most
    /// this many after it that the model accepted on their own (the pipeline's latency, in
    /// frames).
    #[arg(long, default_value_t = NeighbourPoseConfig::default().lookahead_frames)]
    pub neighbour_lookahead: usize,
    /// Step "neighbour": `off` — the neighbour's photo matched as photographed only; when its
    /// pose is not confirmed, also seen from a pose of the frame (projected onto the model):
    /// `own-pose` — the frame's own (would-be) pose; `own-and-neighbour-pose` — also the pose the
    /// photo as photographed gave.
    #[arg(long, value_enum, default_value_t = NeighbourWarpArg::from(NeighbourPoseConfig::default().warp))]
    pub neighbour_warp: NeighbourWarpArg,
    /// Step "neighbour": how many times at most a warped view is matched, each round seen from
    /// the pose the last gave, while that pose still moves a pixel (1: once).
    #[arg(long, default_value_t = NeighbourPoseConfig::default().warp_rounds)]
    pub neighbour_warp_rounds: usize,
    /// Step "neighbour", an accepted frame whose pose a confirmed neighbour's pose agrees with:
    /// `keep` — the own pose stays; `mean` — halfway between the two; `least-seen` — the own
    /// pose moved along the direction its edges see least to the neighbour's.
    #[arg(long, value_enum, default_value_t = NeighbourAgreementArg::from(NeighbourPoseConfig::default().agreement))]
    pub neighbour_agreement: NeighbourAgreementArg,
    /// Step "neighbour": a pose the photo's edges clear of chance but do not fix is no longer
    /// confirmed by another lender's agreeing pose (by default it is: two photos matched
    /// independently place the frame at one pose along what the model's edges leave open);
    /// such poses still count towards `--quorum-lenders` (0 turns that off too).
    #[arg(long)]
    pub no_two_lenders: bool,
    /// Step "neighbour": how many agreeing lenders confirm a pose the photo's edges see above
    /// chance but not clear of it (0: never).
    #[arg(long, default_value_t = NeighbourPoseConfig::default().quorum_lenders)]
    pub quorum_lenders: usize,
    /// Step "neighbour": the share of the margin above chance one pose needs alone that each
    /// pose of such a quorum keeps.
    #[arg(long, default_value_t = NeighbourPoseConfig::default().quorum_support_share)]
    pub quorum_support_share: f64,
    /// Step "neighbour": lenders whose poses the photo's edges each see clear of chance no
    /// longer confirm their agreeing pose without the rival-basin test (by default
    /// `--quorum-lenders` of them do: independent photos decide between two basins the edges
    /// support about as well).
    #[arg(long)]
    pub no_quorum_over_rival: bool,
    /// How far the rival-basin test's starts lie from the output, px of δ.
    #[arg(long, default_value_t = EdgeAlignConfig::default().rival_reach_px)]
    pub rival_reach_px: f64,
    /// The share of the output's edge support above chance a distinct rival must keep to reject
    /// it (1: as much support as the output).
    #[arg(long, default_value_t = EdgeAlignConfig::default().rival_share_above_chance)]
    pub rival_share: f64,
}

/// What the convergence test bounds ([`ConvergenceMeasure`]).
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConvergenceMeasureArg {
    Spread,
    Carried,
}

impl From<ConvergenceMeasureArg> for ConvergenceMeasure {
    fn from(arg: ConvergenceMeasureArg) -> Self {
        match arg {
            ConvergenceMeasureArg::Spread => Self::Spread,
            ConvergenceMeasureArg::Carried => Self::Carried,
        }
    }
}

/// Which pose of the agreeing refined poses a frame outputs.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum VerifyOutputArg {
    /// The paper's rule: the largest RANSAC consensus.
    Consensus,
    /// The member with the smallest total δ to the others.
    Medoid,
    /// The members' mean pose.
    Mean,
}

impl From<VerifyOutputArg> for OutputChoice {
    fn from(arg: VerifyOutputArg) -> Self {
        match arg {
            VerifyOutputArg::Consensus => Self::LargestConsensus,
            VerifyOutputArg::Medoid => Self::Medoid,
            VerifyOutputArg::Mean => Self::Mean,
        }
    }
}

impl Default for CoarseArgs {
    fn default() -> Self {
        let defaults = RegistrationConfig::default();
        Self {
            coarse_poses: defaults.coarse_pose_count,
            other_centre_coarse_poses: defaults.other_centre_coarse_pose_count,
            flow_top_iterations: defaults.matching.sift_flow.top_iterations,
            coarse_rotation_deg: defaults.coarse_rotation_sigma_deg,
            coarse_translation_fraction: defaults.coarse_translation_sigma_fraction,
            max_convergence_ratio: defaults.verify.max_convergence_ratio,
            convergence_measure: ConvergenceMeasureArg::Spread,
            lift_edge_margin_px: defaults.lift_edge_margin_px,
            no_edge_align: false,
            edge_search_px: defaults.edge_align.initial_search_radius_px,
            edge_starts: defaults.edge_align.starts,
            edge_centre_starts: defaults.edge_align.centre_starts,
            edge_short_schedule_px: defaults.edge_align.short_schedule_radius_px,
            edge_short_schedule_rule: KeepRuleArg::SupportAndCorrelation,
            refine_method: RefineMethodArg::Edges,
            edge_check_levels: false,
            edge_rounding_judge: RoundingJudgeArg::Shared,
            edge_ridge_choice: RidgeChoiceArg::Strongest,
            edge_distinct_weights: defaults.edge_align.distinct_weights,
            no_edge_rounding: !defaults.edge_align.estimate_rounding,
            flow_near_model_edges: defaults.matching.min_rendering_edge.is_some(),
            edge_coarse_rotation_only: defaults.edge_align.coarse_rotation_only,
            edge_keep: KeepRuleArg::Support,
            asg_occlusion_contours: defaults.asg.occlusion_depth_ratio,
            edge_kinds: EdgeKindsArg::All,
            edge_rounding_kinds: EdgeKindsArg::All,
            no_pose_search: false,
            screened_candidates: PoseSearchConfig::default().screened_candidates,
            capture_candidates: PoseSearchConfig::default().capture_candidates,
            search_position_m: PoseSearchConfig::default().position_half_range_m,
            search_position_steps: PoseSearchConfig::default().position_max_steps,
            positioned_candidates: PoseSearchConfig::default().positioned_candidates,
            keep_prior_centre: PoseSearchConfig::default().keep_prior_centre,
            search_roll_deg: PoseSearchConfig::default().roll_half_range_deg,
            search_pitch_deg: PoseSearchConfig::default().pitch_half_range_deg,
            prior_tilt_deg: 0.0,
            centre_agreement_share: PoseSearchConfig::default().centre_agreement_share,
            heading_sweep_deg: PoseSearchConfig::default().heading_sweep_step_deg,
            verify_output: VerifyOutputArg::Medoid,
            max_delta_uncertainty_px: ConfidenceConfig::default().max_delta_uncertainty_px,
            min_least_seen_drop: ConfidenceConfig::default().min_least_seen_drop,
            min_least_seen_near_drop: ConfidenceConfig::default().min_least_seen_near_drop,
            min_overrule_margin: ConfidenceConfig::default().min_overrule_margin,
            min_support_above_chance: ConfidenceConfig::default().min_support_above_chance,
            max_convergence_at_chance: ConfidenceConfig::default().max_convergence_at_chance,
            no_edge_consensus: !EdgeAlignConfig::default().consensus.enabled,
            rival_directions: EdgeAlignConfig::default().rival_directions,
            no_rival_centres: !EdgeAlignConfig::default().rival_centres,
            no_neighbours: !NeighbourPoseConfig::default().enabled,
            neighbour_steps: NeighbourPoseConfig::default().max_steps,
            neighbour_candidates: NeighbourPoseConfig::default().candidates,
            neighbour_order: None,
            neighbour_lookahead: NeighbourPoseConfig::default().lookahead_frames,
            neighbour_warp: NeighbourPoseConfig::default().warp.into(),
            neighbour_warp_rounds: NeighbourPoseConfig::default().warp_rounds,
            neighbour_agreement: NeighbourPoseConfig::default().agreement.into(),
            no_two_lenders: !NeighbourPoseConfig::default().two_lenders_confirm,
            quorum_lenders: NeighbourPoseConfig::default().quorum_lenders,
            quorum_support_share: NeighbourPoseConfig::default().quorum_support_share,
            no_quorum_over_rival: !NeighbourPoseConfig::default().quorum_outweighs_rival,
            rival_reach_px: EdgeAlignConfig::default().rival_reach_px,
            rival_share: EdgeAlignConfig::default().rival_share_above_chance,
        }
    }
}

/// The order step "neighbour" lends poses in (`--neighbour-order`; `core::frame::NeighbourOrder`).
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum NeighbourOrderArg {
    Feed,
    Set,
}

impl From<NeighbourOrderArg> for asgreg::core::frame::NeighbourOrder {
    fn from(arg: NeighbourOrderArg) -> Self {
        match arg {
            NeighbourOrderArg::Feed => Self::Feed,
            NeighbourOrderArg::Set => Self::Set,
        }
    }
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum NeighbourAgreementArg {
    Keep,
    Mean,
    LeastSeen,
}

impl From<NeighbourAgreementArg> for NeighbourAgreement {
    fn from(arg: NeighbourAgreementArg) -> Self {
        match arg {
            NeighbourAgreementArg::Keep => Self::Keep,
            NeighbourAgreementArg::Mean => Self::Mean,
            NeighbourAgreementArg::LeastSeen => Self::LeastSeen,
        }
    }
}

impl From<NeighbourAgreement> for NeighbourAgreementArg {
    fn from(agreement: NeighbourAgreement) -> Self {
        match agreement {
            NeighbourAgreement::Keep => Self::Keep,
            NeighbourAgreement::Mean => Self::Mean,
            NeighbourAgreement::LeastSeen => Self::LeastSeen,
        }
    }
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum NeighbourWarpArg {
    Off,
    OwnPose,
    OwnAndNeighbourPose,
}

impl From<NeighbourWarpArg> for NeighbourWarp {
    fn from(arg: NeighbourWarpArg) -> Self {
        match arg {
            NeighbourWarpArg::Off => Self::Off,
            NeighbourWarpArg::OwnPose => Self::OwnPose,
            NeighbourWarpArg::OwnAndNeighbourPose => Self::OwnAndNeighbourPose,
        }
    }
}

impl From<NeighbourWarp> for NeighbourWarpArg {
    fn from(warp: NeighbourWarp) -> Self {
        match warp {
            NeighbourWarp::Off => Self::Off,
            NeighbourWarp::OwnPose => Self::OwnPose,
            NeighbourWarp::OwnAndNeighbourPose => Self::OwnAndNeighbourPose,
        }
    }
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum KeepRuleArg {
    Support,
    SupportAndCorrelation,
    Correlation,
}

impl From<KeepRuleArg> for asgreg::core::edge_align::KeepRule {
    fn from(arg: KeepRuleArg) -> Self {
        match arg {
            KeepRuleArg::Support => Self::Support,
            KeepRuleArg::SupportAndCorrelation => Self::SupportAndCorrelation,
            KeepRuleArg::Correlation => Self::Correlation,
        }
    }
}

/// Which rounding the final refinement's judge undoes on each pose's edges.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum RoundingJudgeArg {
    Shared,
    AsRendered,
    EachOwn,
}

impl From<RoundingJudgeArg> for asgreg::core::edge_align::RoundingJudge {
    fn from(arg: RoundingJudgeArg) -> Self {
        match arg {
            RoundingJudgeArg::Shared => Self::Shared,
            RoundingJudgeArg::AsRendered => Self::AsRendered,
            RoundingJudgeArg::EachOwn => Self::EachOwn,
        }
    }
}

/// Which photo ridge the final refinement matches a model edge sample to.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum RidgeChoiceArg {
    Strongest,
    Nearest,
}

impl From<RidgeChoiceArg> for asgreg::core::edge_align::RidgeChoice {
    fn from(arg: RidgeChoiceArg) -> Self {
        match arg {
            RidgeChoiceArg::Strongest => Self::Strongest,
            RidgeChoiceArg::Nearest => Self::Nearest,
        }
    }
}

/// Which alignment the final refinement runs.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum RefineMethodArg {
    Edges,
    Dense,
    EdgesThenDense,
}

impl From<RefineMethodArg> for asgreg::core::edge_align::RefineMethod {
    fn from(arg: RefineMethodArg) -> Self {
        match arg {
            RefineMethodArg::Edges => Self::Edges,
            RefineMethodArg::Dense => Self::Dense,
            RefineMethodArg::EdgesThenDense => Self::EdgesThenDense,
        }
    }
}

/// Which model edges the final refinement's steps use.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum EdgeKindsArg {
    /// Occluding contours and creases.
    All,
    /// Occluding contours (depth steps) only.
    Contours,
    /// Creases only.
    Creases,
}

impl From<EdgeKindsArg> for AlignedKinds {
    fn from(kinds: EdgeKindsArg) -> Self {
        match kinds {
            EdgeKindsArg::All => Self::All,
            EdgeKindsArg::Contours => Self::Contours,
            EdgeKindsArg::Creases => Self::Creases,
        }
    }
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum IntrinsicsArg {
    /// Calibrated: only the pose is estimated (EPnP).
    Known,
    /// Uncalibrated: focal lengths, principal point and pose (the paper's 11-DoF DLT).
    Unknown,
    /// Only the focal length is unknown; principal point at the image centre, no skew (EPnP
    /// with unknown focal length): a drone's EXIF camera.
    Focal,
}

impl IntrinsicsArg {
    pub fn mode(self) -> IntrinsicsMode {
        match self {
            IntrinsicsArg::Known => IntrinsicsMode::Known,
            IntrinsicsArg::Unknown | IntrinsicsArg::Focal => IntrinsicsMode::Unknown,
        }
    }

    /// What an unknown calibration estimates under this argument.
    pub fn unknown_intrinsics(self) -> UnknownIntrinsics {
        match self {
            IntrinsicsArg::Focal => UnknownIntrinsics::Focal,
            IntrinsicsArg::Known | IntrinsicsArg::Unknown => UnknownIntrinsics::Dlt,
        }
    }
}

/// Which image stands for the photo in the flow.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum QueryArg {
    /// The photo's gradient magnitude.
    Gradient,
    /// The ASG of the photo's depth map (the paper's mode; needs depth maps).
    Depth,
    /// Depth-ASG where the depth is valid and trustworthy, the photo's gradient elsewhere.
    Mixed,
}

impl QueryArg {
    pub fn mode(self) -> QueryMode {
        match self {
            QueryArg::Gradient => QueryMode::ImageGradient,
            QueryArg::Depth => QueryMode::DepthAsg,
            QueryArg::Mixed => QueryMode::Mixed,
        }
    }
}

/// The registration settings the command line selects.
pub fn registration_config(
    query_mode: QueryMode,
    intrinsics: IntrinsicsArg,
    coarse: &CoarseArgs,
) -> RegistrationConfig {
    // Every setting the command line does not name is the library's default: the nested
    // structs too (`MatchConfig::default()` is the reference flow's schedule, not the one
    // registration runs with).
    let defaults = RegistrationConfig::default();
    RegistrationConfig {
        query_mode,
        unknown_intrinsics: intrinsics.unknown_intrinsics(),
        coarse_pose_count: coarse.coarse_poses,
        other_centre_coarse_pose_count: coarse.other_centre_coarse_poses,
        coarse_rotation_sigma_deg: coarse.coarse_rotation_deg,
        coarse_translation_sigma_fraction: coarse.coarse_translation_fraction,
        lift_edge_margin_px: coarse.lift_edge_margin_px,
        matching: MatchConfig {
            min_rendering_edge: coarse
                .flow_near_model_edges
                .then_some(EdgeAlignConfig::default().min_model_ridge),
            sift_flow: asgreg::core::sift_flow::SiftFlowConfig {
                top_iterations: coarse.flow_top_iterations,
                ..defaults.matching.sift_flow.clone()
            },
            ..defaults.matching.clone()
        },
        verify: VerifyConfig {
            max_convergence_ratio: coarse.max_convergence_ratio,
            convergence_measure: coarse.convergence_measure.into(),
            output: coarse.verify_output.into(),
            ..defaults.verify
        },
        confidence: ConfidenceConfig {
            max_delta_uncertainty_px: coarse.max_delta_uncertainty_px,
            min_least_seen_drop: coarse.min_least_seen_drop,
            min_least_seen_near_drop: coarse.min_least_seen_near_drop,
            min_overrule_margin: coarse.min_overrule_margin,
            min_support_above_chance: coarse.min_support_above_chance,
            max_convergence_at_chance: coarse.max_convergence_at_chance,
            ..defaults.confidence
        },
        asg: AsgOptions {
            occlusion_depth_ratio: coarse.asg_occlusion_contours,
            ..defaults.asg
        },
        edge_align: EdgeAlignConfig {
            enabled: !coarse.no_edge_align,
            initial_search_radius_px: coarse.edge_search_px,
            starts: coarse.edge_starts,
            centre_starts: coarse.edge_centre_starts,
            short_schedule_radius_px: coarse.edge_short_schedule_px,
            short_schedule_rule: coarse.edge_short_schedule_rule.into(),
            method: coarse.refine_method.into(),
            check_levels: coarse.edge_check_levels,
            ridge_choice: coarse.edge_ridge_choice.into(),
            distinct_weights: coarse.edge_distinct_weights,
            coarse_rotation_only: coarse.edge_coarse_rotation_only,
            keep_rule: coarse.edge_keep.into(),
            estimate_rounding: !coarse.no_edge_rounding,
            rounding_judge: coarse.edge_rounding_judge.into(),
            rounding_kinds: coarse.edge_rounding_kinds.into(),
            aligned_kinds: coarse.edge_kinds.into(),
            rival_directions: coarse.rival_directions,
            rival_centres: !coarse.no_rival_centres,
            rival_reach_px: coarse.rival_reach_px,
            rival_share_above_chance: coarse.rival_share,
            consensus: asgreg::core::edge_consensus::EdgeConsensusConfig {
                enabled: !coarse.no_edge_consensus,
                ..defaults.edge_align.consensus
            },
            ..defaults.edge_align
        },
        pose_search: PoseSearchConfig {
            enabled: !coarse.no_pose_search,
            screened_candidates: coarse.screened_candidates,
            capture_candidates: coarse.capture_candidates,
            position_half_range_m: coarse.search_position_m,
            position_max_steps: coarse.search_position_steps,
            positioned_candidates: coarse.positioned_candidates,
            keep_prior_centre: coarse.keep_prior_centre,
            roll_half_range_deg: coarse.search_roll_deg,
            pitch_half_range_deg: coarse.search_pitch_deg,
            centre_agreement_share: coarse.centre_agreement_share,
            heading_sweep_step_deg: coarse.heading_sweep_deg,
            ..defaults.pose_search
        }
        .with_trusted_tilt_deg(coarse.prior_tilt_deg),
        neighbour_pose: NeighbourPoseConfig {
            enabled: !coarse.no_neighbours,
            max_steps: coarse.neighbour_steps,
            candidates: coarse.neighbour_candidates,
            order: coarse
                .neighbour_order
                .unwrap_or(NeighbourOrderArg::Feed)
                .into(),
            lookahead_frames: coarse.neighbour_lookahead,
            warp: coarse.neighbour_warp.into(),
            warp_rounds: coarse.neighbour_warp_rounds,
            agreement: coarse.neighbour_agreement.into(),
            two_lenders_confirm: !coarse.no_two_lenders,
            quorum_lenders: coarse.quorum_lenders,
            quorum_support_share: coarse.quorum_support_share,
            quorum_outweighs_rival: !coarse.no_quorum_over_rival,
            ..defaults.neighbour_pose
        },
        ..defaults
    }
}

/// A progress bar on stderr for `count` frames.
pub fn progress_bar(count: usize, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(count as u64);
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "{msg} [{bar:30}] {pos}/{len} frames, {elapsed} elapsed, ETA {eta}",
    ) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_message(what.to_string());
    bar
}

pub fn run(args: &RegisterArgs) -> anyhow::Result<()> {
    // The environment first: an output folder that cannot be written, or a mesh too large for the
    // memory given, fail in a second, not after the registration.
    prepare_output_dir(&args.out)?;
    if let Some(limit_mib) = args.max_mesh_mib {
        check_mesh_fits(&args.mesh, limit_mib)?;
    }
    let inputs = load_posed_inputs(&args.mesh, &args.cameras, &args.poses)?;
    let query = args.query.unwrap_or(if args.depth.is_some() {
        QueryArg::Depth
    } else {
        QueryArg::Gradient
    });
    if query.mode().needs_depth() && args.depth.is_none() {
        anyhow::bail!(
            "--query {query:?} needs the photos' depth maps: pass --depth <folder>, or --query gradient"
        );
    }
    let config = registration_config(query.mode(), args.intrinsics, &args.coarse);
    config.validate()?;
    let mut frames = Vec::new();
    for image in inputs.images.iter().take(args.limit.unwrap_or(usize::MAX)) {
        let camera = inputs.cameras.get(&image.camera_id).with_context(|| {
            format!(
                "image '{}' in {} uses camera {}, which {} does not define",
                image.name,
                args.poses.display(),
                image.camera_id,
                args.cameras.display()
            )
        })?;
        frames.push(BatchFrame {
            image_id: image.image_id,
            camera_id: image.camera_id,
            name: image.name.clone(),
            image_path: args.images.join(&image.name),
            depth_path: args
                .depth
                .as_ref()
                .map(|dir| depth_path_for(dir, &image.name)),
            camera: *camera,
            intrinsics: args.intrinsics.mode(),
            initial_cam_from_world: image.cam_from_world,
        });
    }

    let loader = FrameLoader::new((args.working_width > 0).then_some(args.working_width));
    let bar = progress_bar(frames.len(), "registering");
    let mut reports = Vec::with_capacity(frames.len());
    for frame in &frames {
        let report = register_batch_frame_with(&inputs.mesh, frame, &loader, &config, args.seed);
        bar.println(format!(
            "{}: {}",
            report.name,
            if report.accepted {
                format!(
                    "accepted (confidence {:.2}, {} of {} poses agree, consensus {}, {:.0} ms)",
                    report.confidence,
                    report.component_size,
                    report.hypotheses,
                    report.consensus,
                    report.timings.total_ms
                )
            } else {
                format!("FAILED: {}", report.reason.as_deref().unwrap_or("unknown"))
            }
        ));
        bar.inc(1);
        reports.push(report);
    }
    bar.finish_and_clear();
    if config.neighbour_pose.enabled {
        let changed = neighbour_pass(
            &inputs.mesh,
            &frames,
            &mut reports,
            &loader,
            &config,
            args.seed,
        );
        for &index in &changed {
            let report = &reports[index];
            println!(
                "{}: step \"neighbour\": {}",
                report.name,
                match &report.reason {
                    None => format!(
                        "accepted at the pose from {}",
                        report
                            .neighbours
                            .last()
                            .map_or("a neighbour", |n| n.neighbour.as_str())
                    ),
                    Some(reason) => format!("FAILED: {reason}"),
                }
            );
        }
    }

    let deltas = match &args.truth {
        Some(truth) => truth_deltas(truth, &inputs.mesh, &frames, &reports)?,
        None => vec![None; frames.len()],
    };
    if args.truth.is_some() {
        for (report, delta) in reports.iter().zip(&deltas) {
            let Some(delta) = delta else { continue };
            let show = |d: Option<f64>| d.map_or("-".to_string(), |d| format!("{d:.2} px"));
            println!(
                "{}: {}, δ to the truth {} → {}{}",
                report.name,
                if report.accepted {
                    "accepted"
                } else {
                    "not accepted"
                },
                show(delta.initial_px),
                show(delta.final_px.or(delta.rejected_candidate_px)),
                if report.accepted {
                    ""
                } else {
                    " (its rejected candidate)"
                }
            );
            if let Some(sweep) = &delta.heading_sweep {
                println!("  {}", super::eval::sweep_line(sweep));
            }
        }
        println!(
            "δ to the truth: accepted {}; initial (all frames) {}",
            delta_summary(deltas.iter().flatten().filter_map(|d| d.final_px)),
            delta_summary(deltas.iter().flatten().filter_map(|d| d.initial_px))
        );
    }
    if let (true, Some(truth)) = (args.diagnose, &args.truth) {
        diagnose_frames(args, truth, &inputs.mesh, &frames, &config, &loader)?;
    }
    write_outputs(
        args,
        &inputs.mesh,
        &frames,
        &reports,
        &deltas,
        &config,
        &loader,
    )?;
    let accepted = reports.iter().filter(|r| r.accepted).count();
    let (_, peak_rss_mib) = super::bench_mesh::rss_mib();
    println!(
        "registered {accepted} of {} frames (peak RSS {peak_rss_mib:.0} MiB); poses in {}, report in {} (open {} in a browser)",
        reports.len(),
        args.out.join("images.txt").display(),
        args.out.join("report.json").display(),
        args.out.join(REPORT_HTML).display()
    );
    Ok(())
}

fn write_outputs(
    args: &RegisterArgs,
    mesh: &asgreg::core::mesh::Mesh,
    frames: &[BatchFrame],
    reports: &[FrameReport],
    deltas: &[Option<TruthDelta>],
    config: &RegistrationConfig,
    loader: &FrameLoader,
) -> anyhow::Result<()> {
    let mut cameras = BTreeMap::new();
    let mut poses = Vec::new();
    for (frame, report) in frames.iter().zip(reports) {
        let (Some(camera), Some(cam_from_world)) = (report.camera, report.cam_from_world) else {
            continue;
        };
        // Unknown intrinsics: one camera per image (its id is the image id).
        let camera_id = if args.intrinsics.mode() == IntrinsicsMode::Unknown {
            let mut camera = camera;
            camera.intrinsics.skew_px = 0.0;
            cameras.insert(frame.image_id, camera);
            frame.image_id
        } else {
            cameras.insert(frame.camera_id, frame.camera);
            frame.camera_id
        };
        poses.push(ImagePose {
            image_id: frame.image_id,
            camera_id,
            name: frame.name.clone(),
            cam_from_world,
        });
    }
    // The accepted poses as a COLMAP model, text and binary, and as omega-phi-kappa for GIS.
    write_opk_csv(&args.out.join(OPK_FILE), &poses)?;
    write_model_dir(
        &args.out,
        &ColmapModel {
            cameras,
            images: poses,
        },
    )?;
    let report_path = args.out.join("report.json");
    let json = serde_json::json!({
        "config": config,
        "intrinsics": args.intrinsics.mode(),
        "working_width_px": (args.working_width > 0).then_some(args.working_width),
        "frames": reports,
        "peak_rss_mib": super::bench_mesh::rss_mib().1,
        "truth": args.truth.as_ref().map(|truth| serde_json::json!({
            "model": truth.display().to_string(),
            "delta_px": frames
                .iter()
                .zip(deltas)
                .map(|(frame, delta)| serde_json::json!({"name": frame.name, "delta": delta}))
                .collect::<Vec<_>>(),
        })),
    });
    std::fs::write(&report_path, serde_json::to_string_pretty(&json)?)
        .with_context(|| format!("writing {}", report_path.display()))?;

    let overlay_dir = args.out.join("overlays");
    if !args.no_overlays {
        std::fs::create_dir_all(&overlay_dir)
            .with_context(|| format!("creating {}", overlay_dir.display()))?;
    }
    let mut page_frames = Vec::with_capacity(reports.len());
    for ((frame, report), delta) in frames.iter().zip(reports).zip(deltas) {
        let mut pictures = Vec::new();
        if !args.no_overlays {
            match frame_overlays(mesh, frame, report, loader) {
                Ok(overlays) => {
                    for (label, picture) in overlays {
                        let path =
                            overlay_dir.join(format!("{}_{label}.png", file_stem(&frame.name)));
                        save_rgb_png(&path, picture.view())?;
                        pictures.push(Picture::from_rgb(
                            &frame.name,
                            &label,
                            picture.view(),
                            THUMBNAIL_WIDTH_PX,
                        )?);
                    }
                }
                Err(error) => tracing::warn!("{}: no overlay: {error:#}", frame.name),
            }
        }
        page_frames.push(report_frame(
            report,
            None,
            delta.as_ref().and_then(|d| d.initial_px),
            delta.as_ref().and_then(|d| d.final_px),
            pictures,
        ));
    }
    let accepted = reports.iter().filter(|r| r.accepted).count();
    let page = ReportPage {
        command: "register".to_string(),
        subject: args.images.display().to_string(),
        summary: vec![
            ("mesh".to_string(), args.mesh.display().to_string()),
            (
                "initial poses".to_string(),
                args.poses.display().to_string(),
            ),
            (
                "intrinsics".to_string(),
                format!("{:?}", args.intrinsics.mode()),
            ),
            (
                "working width".to_string(),
                if args.working_width > 0 {
                    format!("{} px", args.working_width)
                } else {
                    "the photos' own".to_string()
                },
            ),
            (
                "accepted".to_string(),
                format!("{accepted} of {} frames", reports.len()),
            ),
        ]
        .into_iter()
        .chain(args.truth.as_ref().map(|truth| {
            (
                format!("δ to the truth ({})", truth.display()),
                format!(
                    "accepted: {}; initial: {}",
                    delta_summary(deltas.iter().flatten().filter_map(|d| d.final_px)),
                    delta_summary(deltas.iter().flatten().filter_map(|d| d.initial_px))
                ),
            )
        }))
        .collect(),
        plots_svg: Vec::new(),
        frames: page_frames,
    };
    write_report_html(&args.out.join(REPORT_HTML), &page)?;
    Ok(())
}

/// The page's file name in a command's output folder.
pub const REPORT_HTML: &str = "report.html";

/// A file name without its folder and extension.
pub fn file_stem(name: &str) -> String {
    Path::new(name)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| name.to_string())
}

/// The model over the frame's photo under the initial pose ("before") and under the output pose
/// ("after" when accepted, "rejected" for a refused frame's would-be pose).
pub fn frame_overlays(
    mesh: &asgreg::core::mesh::Mesh,
    frame: &BatchFrame,
    report: &FrameReport,
    loader: &FrameLoader,
) -> anyhow::Result<Vec<(String, Image<[u8; 3]>)>> {
    let mut views = vec![OverlayView {
        label: "before",
        camera: None,
        cam_from_world: frame.initial_cam_from_world,
    }];
    if let (Some(camera), Some(pose)) = (report.camera, report.cam_from_world) {
        views.push(OverlayView {
            label: "after",
            camera: Some(camera),
            cam_from_world: pose,
        });
    } else if let Some(candidate) = report.rejected_candidate {
        views.push(OverlayView {
            label: "rejected",
            camera: Some(candidate.camera),
            cam_from_world: candidate.cam_from_world,
        });
    }
    working_overlays(
        mesh,
        loader,
        &frame.image_path,
        frame.camera_id,
        &frame.camera,
        &views,
    )
}

/// A registered frame's row of report.html; `group`, the δs (to a ground truth) when known.
pub fn report_frame(
    report: &FrameReport,
    group: Option<String>,
    initial_delta_px: Option<f64>,
    delta_px: Option<f64>,
    pictures: Vec<Picture>,
) -> ReportFrame {
    let verdict = if report.accepted {
        FrameVerdict::Accepted
    } else if report.hypotheses > 0 || report.rejected_candidate.is_some() {
        FrameVerdict::Rejected
    } else {
        FrameVerdict::Failed
    };
    let t = &report.timings;
    let timings_ms = [
        ("query", t.query_ms),
        ("pose search", t.search_ms),
        ("heading sweep (fallback)", t.heading_sweep_ms),
        ("render", t.render_ms),
        ("flow", t.flow_ms),
        ("pose", t.pose_ms),
        ("verify + refine", t.verify_ms),
        ("total", t.total_ms),
    ]
    .into_iter()
    .map(|(name, ms)| (name.to_string(), ms))
    .collect();
    let mut details = vec![
        (
            "agreeing poses".to_string(),
            format!("{} of {}", report.component_size, report.hypotheses),
        ),
        ("RANSAC consensus".to_string(), report.consensus.to_string()),
    ];
    if let Some(rms) = report.inlier_rms_px {
        details.push(("inlier RMS".to_string(), format!("{rms:.2} px")));
    }
    if let Some(sweep) = &report.heading_sweep {
        let pass = |p: &asgreg::batch::PassReport| {
            format!(
                "{} ({:.2})",
                if p.accepted { "accepted" } else { "rejected" },
                p.confidence
            )
        };
        details.push((
            "heading sweep (fallback)".to_string(),
            format!(
                "first pass {}, retry {}; carried: {}",
                pass(&sweep.first),
                sweep
                    .retry
                    .as_ref()
                    .map_or_else(|why| format!("failed ({why})"), pass),
                sweep.carried
            ),
        ));
    }
    ReportFrame {
        name: report.name.clone(),
        group,
        verdict,
        reason: report.reason.clone(),
        confidence: (verdict != FrameVerdict::Failed).then_some(report.confidence),
        initial_delta_px,
        delta_px,
        timings_ms,
        details,
        pictures,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The command line's defaults are the library's, nested settings included: `register`,
    /// `eval` and `demo` register a frame as the pipeline does (a `MatchConfig::default()` here
    /// once ran the reference flow's 30/60/20 iterations instead of the registration's 4/20/4).
    #[test]
    fn the_parsed_command_line_defaults_are_the_library_defaults() {
        #[derive(clap::Parser)]
        struct Wrapper {
            #[command(flatten)]
            coarse: CoarseArgs,
        }
        let parsed = <Wrapper as clap::Parser>::try_parse_from(["asgreg"]).unwrap();
        let config = registration_config(
            QueryMode::ImageGradient,
            IntrinsicsArg::Known,
            &parsed.coarse,
        );
        assert_eq!(config, RegistrationConfig::default());
    }

    #[test]
    fn the_command_line_defaults_are_the_library_defaults() {
        let config = registration_config(
            QueryMode::ImageGradient,
            IntrinsicsArg::Known,
            &CoarseArgs::default(),
        );
        assert_eq!(config, RegistrationConfig::default());
    }
}
