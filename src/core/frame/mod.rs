//! One frame end to end (Schmitz et al. §3; docs/design.md §2), written once as a sequence of steps:
//!
//! | step | runs | function | pipeline stage |
//! |---|---|---|---|
//! | query | once per frame | [`query::query_gradient`] | render |
//! | search | once per frame, before the views | [`search::search_pose`] (inside `render_views`) | render |
//! | plan + render | once per frame, a view at a time | [`views::render_views`] | render |
//! | features | once per frame | [`correspond::query_features`] | flow (cached per frame) |
//! | match + lift | per coarse view | [`correspond::correspond_view`] | flow (N workers) |
//! | solve | per coarse view | [`solve::solve_view`] | pose |
//! | verify + refine | once per frame, over all views | [`decide::decide_frame`] (plausibility check, then [`refine::refine_verdict`]) | verify |
//! | neighbour | once per frame, after its decision, with a registered neighbour | [`neighbour::pose_from_neighbour`], [`neighbour::try_neighbours`] | batch (`batch::neighbour_pass`) and verify (`stage::verify`), on by default |
//!
//! [`register_frame`] (one process), the stage adapters (`stage::*`) and batch registration all
//! call these functions and nothing else; none re-derives a step. A new step is one function
//! here, called from the one place in this sequence where it belongs (a per-frame step before
//! the views inside `render_views`' caller or after them inside `decide_frame`; a per-view step
//! inside `correspond_view` or `solve_view`); see ARCHITECTURE.md.
//!
//! Determinism: every random draw comes from a ChaCha8 stream derived from the frame seed and the
//! coarse pose's index, so results do not depend on thread scheduling or on which worker ran which
//! coarse pose.

pub mod config;
pub mod correspond;
pub mod decide;
pub mod neighbour;
pub mod query;
pub mod refine;
pub mod search;
pub mod solve;
pub mod sweep;
pub mod views;

use std::time::Instant;

use nalgebra::{Vector2, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

pub use config::{
    IntrinsicsMode, QueryMode, RegistrationConfig, RegistrationError, UnknownIntrinsics,
};
pub use correspond::{correspond_view, lift_pixel, query_features, CorrespondWorkspace, ViewRef};
pub use decide::{decide_frame, decide_frame_and_centres, Decision};
pub use neighbour::{
    apply_to_verdict, feed_neighbours, nearest_neighbours, pose_from_neighbour, try_neighbours,
    FeedLender, NeighbourAgreement, NeighbourCheck, NeighbourDecision, NeighbourOrder,
    NeighbourPoseConfig, NeighbourTry, NeighbourView, NeighbourWarp, NeighbourWorkspace,
    RegisteredNeighbour, Witness,
};
pub use query::{query_gradient, smooth_depth};
pub use refine::{
    refine_from_other_centres, refine_pose, refine_verdict, PoseRefinement, RefineWorkspace,
};
pub use search::{search_pose, Beam, PoseSearchOutcome};
pub use solve::solve_view;
pub use sweep::{
    apply_passes_decision, decide_passes, register_with_fallback, sweep_needed, FallbackRun,
    HeadingSweepOutcome, Pass, PassOutcome, WithFallback,
};
pub use views::{
    coarse_poses, median_scene_depth_m, render_coarse_view, render_views, RenderedViews,
};

use super::camera::Camera;
use super::confidence::FrameEvidence;
use super::image::{Image, ImageView};
use super::mesh::Mesh;
use super::raster::{Rasterizer, RenderBuffers};
use super::reprojection::{
    visible_points_from_samples, GridSamples, ReprojectionOptions, VisiblePoints,
};
use super::rigid::Rigid3;
use super::verify::{PoseHypothesis, Verdict};

/// Photo gradients and ASG images are both scaled so that this percentile of their positive
/// values is 1 (values above are clamped): they then live on the same 0..1 scale, which the
/// texture threshold of the flow assumes.
const GRADIENT_SCALE_PERCENTILE: f64 = 0.99;

/// The photo side of a frame.
#[derive(Clone, Copy, Debug)]
pub struct FrameInput<'a> {
    /// Grey photo, values 0..1.
    pub photo: ImageView<'a, f32>,
    /// The photo's depth map (metres along the optical axis, holes 0), for [`QueryMode::DepthAsg`]
    /// and [`QueryMode::Mixed`].
    pub depth_m: Option<ImageView<'a, f32>>,
    /// The camera: known intrinsics, or the nominal ones coarse poses are rendered with.
    pub camera: &'a Camera,
    /// Whether `camera`'s intrinsics are trusted (EPnP) or estimated (DLT).
    pub intrinsics: IntrinsicsMode,
    pub initial_cam_from_world: Rigid3,
    /// Seed of this frame's random draws.
    pub seed: u64,
}

/// One coarse pose's rendering: what the flow step needs and what lifts matches to 3D.
#[derive(Clone, Debug, Default)]
pub struct CoarseView {
    pub coarse_index: usize,
    pub cam_from_world: Rigid3,
    /// ASG image scaled to 0..1.
    pub asg: Image<f32>,
    pub render: RenderBuffers,
}

/// The 2D–3D correspondences of one coarse view.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ViewCorrespondences {
    pub coarse_index: usize,
    /// The coarse pose the rendering was made from.
    pub coarse_cam_from_world: Rigid3,
    /// Query image points, pixels (COLMAP convention: pixel centres at +0.5).
    pub image_points_px: Vec<Vector2<f64>>,
    /// The model points they see, world frame, metres.
    pub world_points_m: Vec<Vector3<f64>>,
}

/// What became of one coarse view.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CoarseOutcome {
    pub coarse_index: usize,
    pub consistent_matches: usize,
    /// The refined pose, or why there is none.
    pub hypothesis: Result<PoseHypothesis, String>,
}

/// Time spent in each step of a frame, ms (wall time in one process).
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
pub struct StageTimings {
    pub query_ms: f64,
    /// The pose search's own time (part of `render_ms`).
    #[serde(default)]
    pub search_ms: f64,
    pub render_ms: f64,
    pub flow_ms: f64,
    pub pose_ms: f64,
    /// Verification and the final refinement.
    pub verify_ms: f64,
    /// The full-circle heading fallback's whole second registration, when it ran (part of
    /// `total_ms`; the other fields are the first registration's).
    #[serde(default)]
    pub heading_sweep_ms: f64,
    pub total_ms: f64,
    /// CPU time of each step, ms: the process's CPU time during the step (all its threads),
    /// which is the step's own where one frame at a time runs in the process (`register`,
    /// `eval`); `verify_cpu_ms` excludes the final refinement (`edge_align_cpu_ms`) and
    /// `render_cpu_ms` the search (`search_cpu_ms`).
    #[serde(default)]
    pub cpu: StepCpuMs,
    /// The coarse views the times above were spent on (`coarse_pose_count` per centre of the
    /// pose search): what render, flow and pose scale with.
    #[serde(default)]
    pub views: usize,
}

/// CPU time per step of a frame, ms (see [`StageTimings::cpu`]).
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
pub struct StepCpuMs {
    pub query: f64,
    pub search: f64,
    pub render: f64,
    pub features: f64,
    pub flow: f64,
    pub pose: f64,
    pub verify: f64,
    pub edge_align: f64,
    pub total: f64,
}

/// CPU time the process has used so far, ms (all threads; `CLOCK_PROCESS_CPUTIME_ID`).
pub fn process_cpu_ms() -> f64 {
    let mut now = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `now` is a valid, writable timespec; the clock id is a constant the C library
    // knows. On failure `now` stays zero and the step's CPU time reads 0.
    unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut now) };
    now.tv_sec as f64 * 1e3 + now.tv_nsec as f64 * 1e-6
}

/// The result of one frame: the verdict (the pose when accepted) and the evidence.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FrameResult {
    pub verdict: Verdict,
    pub coarse: Vec<CoarseOutcome>,
    /// The final refinement of the chosen pose (already applied to the verdict when kept), or why
    /// there was none.
    pub refinement: Result<PoseRefinement, String>,
    /// What the decision rests on.
    pub evidence: FrameEvidence,
    pub timings: StageTimings,
    /// When the full-circle heading fallback ran: both registrations' own verdicts and which one
    /// this result carries ([`sweep::decide_passes`], whose rejection, if any, `verdict` already
    /// holds); `None` when it did not run.
    #[serde(default)]
    pub heading_sweep: Option<HeadingSweepOutcome>,
}

fn elapsed_ms(started: Instant) -> f64 {
    started.elapsed().as_secs_f64() * 1e3
}

/// A ChaCha8 stream for one purpose of one frame (stream ids keep purposes independent).
fn frame_rng(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

/// A coarse view's rendering sampled on the grid of δ's visible points
/// ([`GridSamples`]): what the convergence test needs of the view to know its coarse pose's
/// visible points without rendering it again ([`coarse_points`]). `None` when the views are
/// rendered with other options than δ renders with (the test then renders the coarse pose).
/// One process samples its own views; in the pipeline the flow stage samples its job's view and
/// the samples travel with the correspondences and the hypothesis to verify.
pub fn coarse_view_samples(view: &ViewRef<'_>, config: &RegistrationConfig) -> Option<GridSamples> {
    let reprojection = ReprojectionOptions::default();
    if config.render != reprojection.render_options {
        return None;
    }
    GridSamples::from_render(
        view.depth_m(),
        view.face_index(),
        reprojection.grid_stride_px,
    )
}

/// The coarse poses' visible points from their views' samples ([`coarse_view_samples`]), each
/// with its coarse pose, for [`decide_frame`]'s `coarse_points`: the very sets a
/// rendering of each coarse pose would give. Samples of another grid stride or size than δ's
/// under `camera` are left out (the test then renders that coarse pose).
pub fn coarse_points(
    mesh: &Mesh,
    camera: &Camera,
    samples: &[(Rigid3, &GridSamples)],
) -> Vec<VisiblePoints> {
    let stride_px = ReprojectionOptions::default().grid_stride_px;
    samples
        .par_iter()
        .filter(|(_, samples)| samples.stride_px() == stride_px)
        .filter_map(|(cam_from_world, samples)| {
            visible_points_from_samples(mesh, camera, cam_from_world, samples)
        })
        .collect()
}

/// Registers one frame: the steps of the sequence above, in one process.
pub fn register_frame(
    mesh: &Mesh,
    input: &FrameInput,
    config: &RegistrationConfig,
) -> Result<FrameResult, RegistrationError> {
    let started = Instant::now();
    let started_cpu_ms = process_cpu_ms();
    config.validate()?;
    let query = query_gradient(input, config)?;
    let query_ms = elapsed_ms(started);
    let query_cpu_ms = process_cpu_ms() - started_cpu_ms;
    let mut result = register_query(
        mesh,
        input.camera,
        input.intrinsics,
        &input.initial_cam_from_world,
        query.view(),
        config,
        input.seed,
    )?;
    result.timings.query_ms = query_ms;
    result.timings.total_ms = elapsed_ms(started);
    result.timings.cpu.query = query_cpu_ms;
    result.timings.cpu.total = process_cpu_ms() - started_cpu_ms;
    Ok(result)
}

/// Registers a frame whose query gradient image (0..1, [`query_gradient`]) is already made:
/// every step after "query". `config` must be valid. When the pose search's full-circle heading
/// fallback is on ([`crate::core::pose_search::PoseSearchConfig::heading_sweep`]) and the first
/// pass accepted nothing, or a pose only the photo's edges confirm ([`sweep::sweep_needed`]), the
/// frame is registered once more with headings swept over the full circle; both outcomes are
/// kept in [`FrameResult::heading_sweep`] and the frame is decided across them
/// ([`sweep::decide_passes`]).
pub fn register_query(
    mesh: &Mesh,
    camera: &Camera,
    intrinsics: IntrinsicsMode,
    initial_cam_from_world: &Rigid3,
    query: ImageView<'_, f32>,
    config: &RegistrationConfig,
    seed: u64,
) -> Result<FrameResult, RegistrationError> {
    let started = Instant::now();
    let register = |config: &RegistrationConfig| {
        register_region(
            config,
            mesh,
            camera,
            intrinsics,
            initial_cam_from_world,
            query,
            seed,
        )
    };
    let pass = |result: &FrameResult| PassOutcome {
        verdict: result.verdict.clone(),
        evidence: result.evidence,
    };
    let run = register_with_fallback(mesh, config, register, pass)?;
    let Some(fallback) = run.fallback else {
        return Ok(run.first);
    };
    let FallbackRun {
        retry,
        outcome,
        rejection,
    } = fallback;
    let timings = run.first.timings;
    let mut result = match (outcome.carried, retry) {
        (Pass::HeadingSweep, Ok(retry)) => retry,
        _ => run.first,
    };
    apply_passes_decision(&mut result.verdict, rejection);
    result.timings = timings;
    result.timings.heading_sweep_ms = outcome.sweep_ms;
    result.timings.total_ms = elapsed_ms(started);
    result.heading_sweep = Some(outcome);
    Ok(result)
}

/// [`register_query`] within the pose search's region of `config` alone (no fallback).
fn register_region(
    config: &RegistrationConfig,
    mesh: &Mesh,
    camera: &Camera,
    intrinsics: IntrinsicsMode,
    initial_cam_from_world: &Rigid3,
    query: ImageView<'_, f32>,
    seed: u64,
) -> Result<FrameResult, RegistrationError> {
    let started = Instant::now();
    let mut timings = StageTimings::default();

    let stage = Instant::now();
    let mut cpu_ms = process_cpu_ms();
    // The CPU time since the last call (the step just done).
    let mut step_cpu_ms = || {
        let now_ms = process_cpu_ms();
        let step_ms = now_ms - cpu_ms;
        cpu_ms = now_ms;
        step_ms
    };
    let mut views: Vec<CoarseView> = Vec::with_capacity(config.coarse_pose_count);
    let rendered = render_views(
        mesh,
        camera,
        initial_cam_from_world,
        query,
        config,
        seed,
        &mut Rasterizer::new(),
        &mut CoarseView::default(),
        &mut |view, _| views.push(std::mem::take(view)),
    )?;
    timings.render_ms = elapsed_ms(stage);
    timings.views = rendered.count;
    timings.search_ms = rendered.search.as_ref().map_or(0.0, |s| s.search_ms);
    timings.cpu.search = rendered.search.as_ref().map_or(0.0, |s| s.search_cpu_ms);
    timings.cpu.render = step_cpu_ms() - timings.cpu.search;

    let stage = Instant::now();
    let features = query_features(query, config)?;
    timings.cpu.features = step_cpu_ms();
    let correspondences: Vec<ViewCorrespondences> = views
        .par_iter()
        .map_init(CorrespondWorkspace::default, |workspace, view| {
            correspond_view(mesh, camera, &features, &view.as_ref()?, config, workspace)
        })
        .collect::<Result<_, _>>()?;
    timings.flow_ms = elapsed_ms(stage);
    timings.cpu.flow = step_cpu_ms();

    let stage = Instant::now();
    let outcomes: Vec<CoarseOutcome> = correspondences
        .par_iter()
        .map(|set| solve_view(set, camera, intrinsics, config, seed))
        .collect();
    timings.pose_ms = elapsed_ms(stage);
    timings.cpu.pose = step_cpu_ms();

    let stage = Instant::now();
    // The convergence test's coarse poses are these views: their visible points come from the
    // views' own renderings (sampled as the pipeline's flow stage samples them for verify)
    // instead of rendering the coarse poses again.
    let samples: Vec<(Rigid3, GridSamples)> = views
        .par_iter()
        .filter_map(|view| {
            let samples = coarse_view_samples(&view.as_ref().ok()?, config)?;
            Some((view.cam_from_world, samples))
        })
        .collect();
    let samples: Vec<(Rigid3, &GridSamples)> = samples.iter().map(|(p, s)| (*p, s)).collect();
    let coarse_points = coarse_points(mesh, camera, &samples);
    drop(views);
    let Decision {
        verdict,
        refinement,
        evidence,
        refine_cpu_ms,
        ..
    } = decide_frame(
        mesh,
        camera,
        &outcomes,
        Some(query),
        intrinsics,
        config,
        &mut RefineWorkspace::default(),
        &coarse_points,
    );
    timings.verify_ms = elapsed_ms(stage);
    timings.cpu.edge_align = refine_cpu_ms;
    timings.cpu.verify = step_cpu_ms() - refine_cpu_ms;
    timings.total_ms = elapsed_ms(started);
    Ok(FrameResult {
        verdict,
        coarse: outcomes,
        refinement,
        evidence,
        timings,
        heading_sweep: None,
    })
}

#[cfg(test)]
pub(crate) mod tests;
