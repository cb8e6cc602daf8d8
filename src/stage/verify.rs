//! Stage "verify": gathers a frame's hypotheses (from whichever pose/flow workers made them,
//! duplicates from redone jobs ignored) and its query (from render), runs the plausibility check
//! and the final refinement and emits the frame's one PoseResult. A frame that a stage gave up on, or that never completes within the timeout,
//! also gets exactly one (failed) result with the reason.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use std::sync::Arc;

use crate::core::camera::Camera;
use crate::core::change::pose_sigma_px_of_registration;
use crate::core::change::stereo::{neighbour_candidates, NeighbourConfig, PosedCamera};
use crate::core::frame::{
    apply_to_verdict, coarse_points, decide_frame, feed_neighbours, try_neighbours, CoarseOutcome,
    Decision, FeedLender, IntrinsicsMode, NeighbourDecision, NeighbourPoseConfig,
    NeighbourWorkspace, RefineWorkspace, RegisteredNeighbour, RegistrationConfig,
};
use crate::core::image::Image;
use crate::core::mesh::Mesh;
use crate::core::reprojection::GridSamples;
use crate::msg::{
    CameraNumbers, ChangeJob, ChangeJobMeta, ChangeResult, Evidence, FrameFailed, FrameInfo,
    FrameQuery, Hypothesis, HypothesisMeta, NeighbourMeta, PoseNumbers, PoseResult,
    RefinementNumbers, StageTimesMs,
};

use super::change::not_registered;
use super::elapsed_ms;
use super::simulate::{spend_ms, SimulatedWork};

/// What the change stage gets of a decided frame.
#[derive(Clone, Debug, PartialEq)]
pub enum ChangeWork {
    /// An accepted frame: its change job (to the change workers).
    Job(u64, Box<ChangeJob<'static>>),
    /// A frame without a pose: its change result, saying why there is no change map.
    Result(ChangeResult),
}

/// What an accepted frame brings to its change work.
struct Decided {
    info: FrameInfo,
    camera: Camera,
    cam_from_world: crate::core::rigid::Rigid3,
    depth_m: Option<Image<f32>>,
    photo: Option<Image<f32>>,
}

/// An accepted frame kept as a stereo reference or neighbour.
struct RegisteredView {
    info: FrameInfo,
    camera: Camera,
    cam_from_world: crate::core::rigid::Rigid3,
    /// The pose's error for the change threshold (`ChangeJobMeta::pose_sigma_px`).
    pose_sigma_px: f64,
    photo: Arc<Image<f32>>,
}

impl RegisteredView {
    fn posed(&self) -> PosedCamera {
        PosedCamera {
            intrinsics: self.camera.intrinsics,
            width_px: self.photo.width_px(),
            height_px: self.photo.height_px(),
            cam_from_world: self.cam_from_world,
        }
    }
}

/// An accepted frame kept to lend its pose to the frames after it (step "neighbour",
/// `registration.neighbour_pose`): its query image, camera and pose, and how many neighbours
/// away from a frame the model accepted on its own it is (0: it is one).
#[derive(Clone)]
struct PoseLender {
    info: FrameInfo,
    query: Arc<Image<f32>>,
    camera: Camera,
    cam_from_world: crate::core::rigid::Rigid3,
    steps: usize,
}

struct PendingFrame {
    info: FrameInfo,
    name: String,
    camera: Camera,
    intrinsics: IntrinsicsMode,
    /// Known from the first hypothesis.
    coarse_count: Option<u32>,
    hypotheses: BTreeMap<u32, HypothesisMeta>,
    /// The coarse views' grid samples that came with the hypotheses (those with a pose), by
    /// coarse index: the convergence test's coarse poses, not rendered again.
    grids: BTreeMap<u32, GridSamples>,
    /// The frame's query gradient image (render sends it before the flow jobs).
    query: Option<Arc<Image<f32>>>,
    /// The photo's depth map (render sends it with the query), for the change stage.
    depth_m: Option<Image<f32>>,
    /// Without a depth map: the grey photo (render sends it with the query), for stereo.
    photo: Option<Image<f32>>,
    first_seen: Instant,
}

impl PendingFrame {
    fn new(info: &FrameInfo) -> Self {
        Self {
            info: info.clone(),
            name: info.name.clone(),
            camera: info.camera,
            intrinsics: IntrinsicsMode::from_known(info.intrinsics_known),
            coarse_count: None,
            hypotheses: BTreeMap::new(),
            grids: BTreeMap::new(),
            query: None,
            depth_m: None,
            photo: None,
            first_seen: Instant::now(),
        }
    }

    fn has_every_hypothesis(&self) -> bool {
        self.coarse_count
            .is_some_and(|count| self.hypotheses.len() >= count as usize)
    }
}

pub struct VerifyStage<'m> {
    mesh: &'m Mesh,
    frame_timeout: Duration,
    pending: BTreeMap<u64, PendingFrame>,
    /// Every frame id below this has its result.
    finished_below: u64,
    /// Frame ids at or above `finished_below` that have their result.
    finished_above: BTreeSet<u64>,
    stream_frame_count: Option<u64>,
    /// Messages for frames that already had their result (redone jobs), ignored.
    pub late_messages: u64,
    /// Whether decided frames make change work (the change stage runs).
    changes: bool,
    /// Stereo neighbours: how they are chosen, and the window (frames before and after).
    neighbour_config: NeighbourConfig,
    window_frames: u64,
    /// Accepted frames with a photo and no depth map (stereo references and neighbours) within
    /// the window of a frame still waiting.
    registered_views: BTreeMap<u64, RegisteredView>,
    /// Accepted frames whose change job waits for the frames after them (their neighbours).
    stereo_waiting: BTreeSet<u64>,
    /// Change work of the frames decided so far, oldest first (the runtime takes it).
    pub change_work: Vec<ChangeWork>,
    /// Complete frames waiting for the runtime to decide them on its threads
    /// ([`VerifyStage::take_ready`], [`ReadyFrame::decide`], [`VerifyStage::conclude`]).
    ready: Vec<ReadyFrame>,
    /// Frames handed out to be decided and not concluded yet.
    deciding: BTreeSet<u64>,
    /// `bench pipeline --simulate`: sleep per frame's decision.
    simulated: Option<SimulatedWork>,
    /// Step "neighbour" (when `enabled`): its settings, the accepted frames that may still lend
    /// their poses (those within `window_frames` before a frame without its result), and the
    /// frames decided on their own that wait for every frame of their window to have its result
    /// ([`feed_neighbours`]: then a frame's lenders do not depend on the order frames complete
    /// in).
    neighbour_pose: NeighbourPoseConfig,
    pose_lenders: BTreeMap<u64, PoseLender>,
    awaiting_neighbours: BTreeMap<u64, AwaitingNeighbours>,
    /// Frames whose result was published before this stage restarted: they count as having
    /// their result for step "neighbour"'s windows even when their messages do not come again.
    published_before: BTreeSet<u64>,
}

/// A frame decided on its own, waiting for the frames of its window (step "neighbour").
struct AwaitingNeighbours {
    decided: DecidedFrame,
    since: Instant,
}

/// Buffers of a thread that decides frames ([`ReadyFrame::decide`]), reused across frames: the
/// final refinement's and step "neighbour"'s.
#[derive(Default)]
pub struct VerifyWorkspace {
    refine: RefineWorkspace,
    neighbour: NeighbourWorkspace,
}

/// A frame with every hypothesis (and its query, or timed out waiting for it): what deciding it
/// needs, owned, so that it can be decided on another thread.
pub struct ReadyFrame {
    frame_id: u64,
    simulated: Option<SimulatedWork>,
    step: DecideStep,
}

/// What deciding a ready frame runs.
enum DecideStep {
    /// The frame's own decision (`core::frame::decide_frame`).
    Own(Box<PendingFrame>),
    /// Step "neighbour" on the frame's own decision: the accepted frames to try, nearest first.
    Neighbours {
        own: Box<DecidedFrame>,
        lenders: Vec<PoseLender>,
    },
}

/// A frame's decision, to be concluded by the stage ([`VerifyStage::conclude`]).
pub struct DecidedFrame {
    frame_id: u64,
    frame: PendingFrame,
    decision: Decision,
    verify_ms: f64,
    /// When accepted: neighbours away from a frame the model accepted on its own (0: accepted
    /// on its own; step "neighbour").
    lender_steps: Option<usize>,
    /// Whether step "neighbour" has run on the decision (or cannot: then the decision is final).
    neighbours_tried: bool,
}

impl DecidedFrame {
    /// Whether the frame lends its pose as decided so far, and as what: accepted, with its query
    /// image and known intrinsics (as in batch registration); its steps and accepted pose.
    fn lends(&self) -> Option<(usize, &crate::core::verify::PoseHypothesis)> {
        if self.frame.intrinsics != IntrinsicsMode::Known || self.frame.query.is_none() {
            return None;
        }
        Some((self.lender_steps?, self.decision.verdict.accepted_pose()?))
    }

    /// The frame as a lender of its pose ([`DecidedFrame::lends`]).
    fn as_lender(&self) -> Option<PoseLender> {
        let (steps, pose) = self.lends()?;
        Some(PoseLender {
            info: self.frame.info.clone(),
            query: self.frame.query.clone()?,
            camera: pose.camera,
            cam_from_world: pose.cam_from_world,
            steps,
        })
    }
}

impl ReadyFrame {
    pub fn frame_id(&self) -> u64 {
        self.frame_id
    }

    /// The frame's decision (`core::frame::decide_frame`, with the coarse poses'
    /// visible points made from the grid samples that came with the hypotheses, so none is
    /// rendered again); needs no stage state, so any thread with the mesh and a workspace can
    /// run it.
    pub fn decide(
        self,
        mesh: &Mesh,
        config: &RegistrationConfig,
        workspace: &mut VerifyWorkspace,
    ) -> DecidedFrame {
        let started = Instant::now();
        let ReadyFrame {
            frame_id,
            simulated,
            step,
        } = self;
        let frame = match step {
            DecideStep::Own(frame) => *frame,
            DecideStep::Neighbours { own, lenders } => {
                let mut decided = *own;
                decided.lender_steps = decide_with_neighbours(
                    mesh,
                    &decided.frame,
                    &lenders,
                    config,
                    &mut decided.decision,
                    &mut workspace.neighbour,
                );
                decided.neighbours_tried = true;
                decided.verify_ms += elapsed_ms(started);
                return decided;
            }
        };
        if let Some(work) = simulated {
            spend_ms(work.verify_frame_ms);
        }
        let outcomes: Vec<CoarseOutcome> = frame
            .hypotheses
            .values()
            .map(|h| h.outcome.clone())
            .collect();
        // The coarse poses' visible points from the flow stage's samples of their views, as
        // one process makes them from its own views (`core::frame::register_frame`).
        let samples: Vec<_> = frame
            .hypotheses
            .iter()
            .filter_map(|(coarse_index, h)| {
                let coarse_cam_from_world =
                    h.outcome.hypothesis.as_ref().ok()?.coarse_cam_from_world;
                Some((coarse_cam_from_world, frame.grids.get(coarse_index)?))
            })
            .collect();
        let coarse_points = coarse_points(mesh, &frame.camera, &samples);
        let decision = decide_frame(
            mesh,
            &frame.camera,
            &outcomes,
            frame.query.as_ref().map(|query| query.view()),
            frame.intrinsics,
            config,
            &mut workspace.refine,
            &coarse_points,
        );
        // Step "neighbour" needs the query and known intrinsics; without them this is final.
        let neighbours_tried = !(config.neighbour_pose.enabled
            && simulated.is_none()
            && frame.query.is_some()
            && frame.intrinsics == IntrinsicsMode::Known);
        DecidedFrame {
            frame_id,
            lender_steps: decision.verdict.accepted().then_some(0),
            frame,
            decision,
            verify_ms: elapsed_ms(started),
            neighbours_tried,
        }
    }
}

/// Step "neighbour" on a decided frame ([`try_neighbours`], as batch registration runs it):
/// the decisive try applied to the verdict. Returns the accepted frame's steps from a frame
/// the model accepted on its own (`None` when not accepted).
fn decide_with_neighbours(
    mesh: &Mesh,
    frame: &PendingFrame,
    neighbours: &[PoseLender],
    config: &RegistrationConfig,
    decision: &mut Decision,
    workspace: &mut NeighbourWorkspace,
) -> Option<usize> {
    let own_steps = decision.verdict.accepted().then_some(0);
    let Some(query) = frame.query.as_ref() else {
        return own_steps;
    };
    if neighbours.is_empty() || frame.intrinsics != IntrinsicsMode::Known {
        return own_steps;
    }
    let registered: Vec<RegisteredNeighbour> = neighbours
        .iter()
        .enumerate()
        .map(|(id, lender)| RegisteredNeighbour {
            id,
            query: lender.query.view(),
            camera: &lender.camera,
            cam_from_world: lender.cam_from_world,
        })
        .collect();
    let verdict = &decision.verdict;
    let own = match verdict.accepted_pose() {
        Some(pose) => Ok(pose),
        None => Err(verdict.chosen()),
    };
    let tries = try_neighbours(
        mesh,
        &frame.camera,
        frame.intrinsics,
        query.view(),
        own,
        &registered,
        &mut Vec::new(),
        config,
        frame.info.seed,
        workspace,
    );
    // `try_neighbours` stops at the first confirmed pose: the last try decides, if any does.
    let Some(last) = tries.last() else {
        return own_steps;
    };
    let lender = &neighbours[last.neighbour];
    if !last.confirmed() {
        return own_steps;
    }
    apply_to_verdict(&mut decision.verdict, last, &lender.info.name);
    let agreeing = last.agreeing_neighbour().map_or(String::new(), |id| {
        format!(
            ", confirmed by '{}''s agreeing pose",
            neighbours[id].info.name
        )
    });
    match last.decision {
        NeighbourDecision::Accept => {
            tracing::info!(
                "frame '{}': accepted at the pose from its neighbour '{}'{agreeing} (step \"neighbour\")",
                frame.name,
                lender.info.name
            );
            Some(lender.steps + 1)
        }
        NeighbourDecision::Contradicted { apart_px } => {
            tracing::info!(
                "frame '{}': rejected, its neighbour '{}' gives a pose {apart_px:.0} px away{agreeing}",
                frame.name,
                lender.info.name
            );
            None
        }
        NeighbourDecision::Combine { .. } => {
            tracing::info!(
                "frame '{}': its pose combined with the pose from its neighbour '{}' (step \"neighbour\")",
                frame.name,
                lender.info.name
            );
            own_steps
        }
        NeighbourDecision::Keep => own_steps,
    }
}

impl<'m> VerifyStage<'m> {
    pub fn new(mesh: &'m Mesh, frame_timeout: Duration) -> Self {
        Self {
            mesh,
            frame_timeout,
            pending: BTreeMap::new(),
            finished_below: 0,
            finished_above: BTreeSet::new(),
            stream_frame_count: None,
            late_messages: 0,
            changes: false,
            neighbour_config: NeighbourConfig::default(),
            window_frames: 0,
            registered_views: BTreeMap::new(),
            stereo_waiting: BTreeSet::new(),
            change_work: Vec::new(),
            ready: Vec::new(),
            deciding: BTreeSet::new(),
            simulated: None,
            neighbour_pose: NeighbourPoseConfig::default(),
            pose_lenders: BTreeMap::new(),
            awaiting_neighbours: BTreeMap::new(),
            published_before: BTreeSet::new(),
        }
    }

    /// Sleeps the given time per frame's decision (simulated pipeline).
    pub fn with_simulated_work(mut self, work: Option<SimulatedWork>) -> Self {
        self.simulated = work;
        self
    }

    /// Runs step "neighbour" after each frame's own decision (`config.enabled`; not in a
    /// simulated pipeline): once every frame of its window has its result, a frame is tried
    /// against the accepted frames before it ([`feed_neighbours`], as batch registration
    /// does), so its result does not depend on the order frames complete in. A frame whose
    /// window is still incomplete after the frame timeout is tried against the lenders there
    /// are (a warning says so).
    pub fn with_neighbour_poses(mut self, config: NeighbourPoseConfig) -> Self {
        self.neighbour_pose = config;
        self
    }

    /// After a restart: the frames whose results were published before it (the journal's).
    /// Step "neighbour" does not wait for them.
    pub fn published_before_restart(&mut self, frame_ids: impl IntoIterator<Item = u64>) {
        self.published_before.extend(frame_ids);
    }

    /// The complete frames waiting to be decided; each must come back to
    /// [`VerifyStage::conclude`] (a frame counts as pending until then). With step
    /// "neighbour" each carries its candidate neighbours.
    pub fn take_ready(&mut self) -> Vec<ReadyFrame> {
        self.release_awaiting(Instant::now());
        let ready = std::mem::take(&mut self.ready);
        self.deciding.extend(ready.iter().map(|r| r.frame_id));
        ready
    }

    /// The frames decided on their own whose window has every result, and whose look-ahead
    /// every own decision (or that waited longer than the frame timeout), go to be tried
    /// against their lenders ([`feed_neighbours`]).
    fn release_awaiting(&mut self, now: Instant) {
        let window = self.neighbour_pose.window_frames as u64;
        let lookahead = self.neighbour_pose.lookahead_frames as u64;
        let last = self.stream_frame_count.map(|count| count.saturating_sub(1));
        let has_result = |id: u64| self.is_finished(id) || self.published_before.contains(&id);
        let releasable: Vec<u64> = self
            .awaiting_neighbours
            .iter()
            .filter(|(&frame_id, awaiting)| {
                let until = frame_id.saturating_add(lookahead);
                let until = last.map_or(until, |last| until.min(last));
                let complete = (frame_id.saturating_sub(window)..frame_id).all(has_result)
                    && (frame_id + 1..=until)
                        .all(|id| has_result(id) || self.awaiting_neighbours.contains_key(&id));
                if !complete && now.duration_since(awaiting.since) > self.frame_timeout {
                    tracing::warn!(
                        "frame {frame_id} '{}': frames of its window still have no result (or, after it, no decision) after {:.0} s; step \"neighbour\" tries the neighbours there are (its result may differ from a run without the delay)",
                        awaiting.decided.frame.name,
                        self.frame_timeout.as_secs_f64()
                    );
                    return true;
                }
                complete
            })
            .map(|(&frame_id, _)| frame_id)
            .collect();
        for frame_id in releasable {
            let Some(AwaitingNeighbours { decided, .. }) =
                self.awaiting_neighbours.remove(&frame_id)
            else {
                continue;
            };
            // The frames after it lend their own decisions (`feed_neighbours` takes only
            // their own accepts).
            let ahead = |id: u64| self.awaiting_neighbours.get(&id)?.decided.as_lender();
            let lenders = self
                .pose_lenders
                .iter()
                .map(|(&id, lender)| (id, lender.steps, lender.cam_from_world))
                .chain(self.awaiting_neighbours.range(frame_id + 1..).filter_map(
                    |(&id, awaiting)| {
                        let (steps, pose) = awaiting.decided.lends()?;
                        Some((id, steps, pose.cam_from_world))
                    },
                ))
                .map(|(id, steps, cam_from_world)| FeedLender {
                    index: id as usize,
                    cam_from_world,
                    steps,
                });
            let lenders = feed_neighbours(
                frame_id as usize,
                &decided.frame.info.initial_cam_from_world,
                lenders,
                &self.neighbour_pose,
            )
            .into_iter()
            .filter_map(|id| {
                let id = id as u64;
                self.pose_lenders.get(&id).cloned().or_else(|| ahead(id))
            })
            .collect();
            self.ready.push(ReadyFrame {
                frame_id,
                simulated: None,
                step: DecideStep::Neighbours {
                    own: Box::new(decided),
                    lenders,
                },
            });
        }
    }

    /// Makes every decided frame also give its change work (`change_work`). A frame without a
    /// depth map gets candidate stereo neighbours: those of the accepted frames within
    /// `window_frames` of it (before and after) that `core::change::stereo::neighbour_candidates`
    /// gives (the nearest that qualify, as many as `neighbours.candidates` when it ranks); the
    /// change worker chooses among them (`stage::change::photo_depth`), so the ranking's sweeps
    /// do not hold up the poses here. Its change job waits until the frames after it are decided.
    pub fn with_changes(mut self, neighbours: NeighbourConfig, window_frames: u64) -> Self {
        self.changes = true;
        self.neighbour_config = neighbours;
        self.window_frames = window_frames;
        self
    }

    /// Queues the change work of a frame decided as `result` (accepted: with its registered
    /// camera and pose from `decided`); an accepted frame without depth but with its photo waits
    /// for its stereo neighbours ([`VerifyStage::release_stereo_jobs`]).
    fn queue_change_work(&mut self, result: &PoseResult, decided: Option<Decided>) {
        if !self.changes {
            return;
        }
        let pose_sigma_px = f64::from(pose_sigma_px_of_registration(
            result.evidence.mean_delta_to_chosen_px,
        ));
        let work = match decided {
            Some(decided) if result.accepted => {
                if decided.depth_m.is_none() {
                    if let Some(photo) = decided.photo {
                        self.registered_views.insert(
                            result.frame_id,
                            RegisteredView {
                                info: decided.info,
                                camera: decided.camera,
                                cam_from_world: decided.cam_from_world,
                                pose_sigma_px,
                                photo: Arc::new(photo),
                            },
                        );
                        self.stereo_waiting.insert(result.frame_id);
                        return;
                    }
                }
                ChangeWork::Job(
                    result.frame_id,
                    Box::new(ChangeJob {
                        meta: ChangeJobMeta {
                            info: decided.info,
                            camera: decided.camera,
                            cam_from_world: decided.cam_from_world,
                            neighbours: Vec::new(),
                            pose_sigma_px,
                        },
                        depth_m: std::borrow::Cow::Owned(
                            decided.depth_m.map(Image::into_data).unwrap_or_default(),
                        ),
                        photo: std::borrow::Cow::Owned(Vec::new()),
                        neighbour_photos: std::borrow::Cow::Owned(Vec::new()),
                    }),
                )
            }
            _ => ChangeWork::Result(not_registered(
                result.frame_id,
                &result.name,
                result.failure.as_deref(),
            )),
        };
        self.change_work.push(work);
    }

    /// The change jobs of the frames waiting for stereo neighbours whose window is decided (the
    /// `window_frames` frames after them, or the end of the stream): each with its candidate
    /// neighbours among the accepted frames within the window (the change worker chooses among
    /// them), or, when there is none, its change result saying why. Frames no waiting frame can
    /// use are forgotten.
    pub fn release_stereo_jobs(&mut self) {
        let window = self.window_frames;
        let last = self.stream_frame_count.map(|count| count.saturating_sub(1));
        let complete = self.stream_complete().is_some();
        let ready: Vec<u64> = self
            .stereo_waiting
            .iter()
            .copied()
            .filter(|&frame_id| {
                let until = frame_id.saturating_add(window);
                let until = last.map_or(until, |last| until.min(last));
                complete || (frame_id + 1..=until).all(|id| self.is_finished(id))
            })
            .collect();
        for frame_id in ready {
            self.stereo_waiting.remove(&frame_id);
            let work = self.stereo_job(frame_id);
            self.change_work.push(work);
        }
        // Keep what a waiting frame, or one still to be decided, may choose.
        let keep_from = self
            .stereo_waiting
            .first()
            .copied()
            .unwrap_or(self.finished_below)
            .min(self.finished_below)
            .saturating_sub(window);
        self.registered_views = self.registered_views.split_off(&keep_from);
    }

    fn stereo_job(&self, frame_id: u64) -> ChangeWork {
        let Some(reference) = self.registered_views.get(&frame_id) else {
            return ChangeWork::Result(not_registered(frame_id, "", None));
        };
        let window = self.window_frames;
        let candidates: Vec<(u64, &RegisteredView)> = self
            .registered_views
            .range(frame_id.saturating_sub(window)..=frame_id.saturating_add(window))
            .filter(|(id, _)| **id != frame_id)
            .map(|(id, view)| (*id, view))
            .collect();
        let posed: Vec<PosedCamera> = candidates.iter().map(|(_, v)| v.posed()).collect();
        match neighbour_candidates(
            self.mesh,
            &reference.posed(),
            &posed,
            &self.neighbour_config,
        ) {
            Ok(nearest) => {
                let mut neighbour_photos = Vec::new();
                let neighbours = nearest
                    .iter()
                    .map(|&k| {
                        let (id, view) = candidates[k];
                        neighbour_photos.extend_from_slice(view.photo.data());
                        NeighbourMeta {
                            frame_id: id,
                            name: view.info.name.clone(),
                            camera: view.camera,
                            cam_from_world: view.cam_from_world,
                        }
                    })
                    .collect();
                ChangeWork::Job(
                    frame_id,
                    Box::new(ChangeJob {
                        meta: ChangeJobMeta {
                            info: reference.info.clone(),
                            camera: reference.camera,
                            cam_from_world: reference.cam_from_world,
                            neighbours,
                            pose_sigma_px: reference.pose_sigma_px,
                        },
                        depth_m: std::borrow::Cow::Owned(Vec::new()),
                        photo: std::borrow::Cow::Owned(reference.photo.data().to_vec()),
                        neighbour_photos: std::borrow::Cow::Owned(neighbour_photos),
                    }),
                )
            }
            Err(error) => ChangeWork::Result(ChangeResult {
                frame_id,
                name: reference.info.name.clone(),
                failure: Some(format!(
                    "no depth: the source has no depth map for this frame and stereo found none: {error} (within {window} frames of it in the stream)"
                )),
                counts: Default::default(),
                regions: Vec::new(),
                change_ms: 0.0,
                change_worker: None,
            }),
        }
    }

    /// The accepted frames kept as stereo views (references still waiting and neighbours a
    /// waiting or coming frame may choose), oldest first.
    pub fn stereo_view_ids(&self) -> impl Iterator<Item = u64> + '_ {
        self.registered_views.keys().copied()
    }

    /// A kept stereo view as a change job without neighbours (its frame, registered camera and
    /// pose, and grey photo): what a restart of this stage needs to have the frame as a stereo
    /// neighbour again (the runtime keeps it durable, [`VerifyStage::restore_stereo_view`]).
    pub fn stereo_view(&self, frame_id: u64) -> Option<ChangeJob<'_>> {
        let view = self.registered_views.get(&frame_id)?;
        Some(ChangeJob {
            meta: ChangeJobMeta {
                info: view.info.clone(),
                camera: view.camera,
                cam_from_world: view.cam_from_world,
                neighbours: Vec::new(),
                pose_sigma_px: view.pose_sigma_px,
            },
            depth_m: std::borrow::Cow::Owned(Vec::new()),
            photo: std::borrow::Cow::Borrowed(view.photo.data()),
            neighbour_photos: std::borrow::Cow::Owned(Vec::new()),
        })
    }

    /// After a restart: an accepted frame kept before it (from [`VerifyStage::stereo_view`])
    /// is a stereo neighbour again; its own change job is not made again from it (a frame whose
    /// change result is not out is sent again and decided again). A view the stage already has
    /// is kept; a job whose photo is not its camera's size is an error.
    pub fn restore_stereo_view(
        &mut self,
        frame_id: u64,
        job: &ChangeJob<'_>,
    ) -> Result<(), String> {
        if !self.changes || self.registered_views.contains_key(&frame_id) {
            return Ok(());
        }
        let photo = job
            .photo()
            .map_err(|error| error.to_string())?
            .ok_or("it has no photo")?;
        self.registered_views.insert(
            frame_id,
            RegisteredView {
                info: job.meta.info.clone(),
                camera: job.meta.camera,
                cam_from_world: job.meta.cam_from_world,
                pose_sigma_px: job.meta.pose_sigma_px,
                photo: Arc::new(photo.to_image()),
            },
        );
        Ok(())
    }

    /// The frames kept as lenders of their poses (step "neighbour"), for
    /// `runtime::lenders` to keep on disk.
    pub fn lender_ids(&self) -> impl Iterator<Item = u64> + '_ {
        self.pose_lenders.keys().copied()
    }

    /// A kept lender as the message `runtime::lenders` writes (`None`: not kept).
    pub fn lender(&self, frame_id: u64) -> Option<crate::msg::PoseLender<'_>> {
        let lender = self.pose_lenders.get(&frame_id)?;
        Some(crate::msg::PoseLender {
            meta: crate::msg::PoseLenderMeta {
                info: lender.info.clone(),
                camera: lender.camera,
                cam_from_world: lender.cam_from_world,
                steps: lender.steps as u32,
            },
            query: std::borrow::Cow::Borrowed(lender.query.data()),
        })
    }

    /// After a restart: a frame kept as a lender before it (from [`VerifyStage::lender`]) lends
    /// its pose again. A lender the stage already has is kept; a query image that is not its
    /// camera's size is an error.
    pub fn restore_lender(
        &mut self,
        frame_id: u64,
        lender: &crate::msg::PoseLender<'_>,
    ) -> Result<(), String> {
        if self.pose_lenders.contains_key(&frame_id) {
            return Ok(());
        }
        let query = lender.query().map_err(|error| error.to_string())?;
        let meta = &lender.meta;
        self.pose_lenders.insert(
            frame_id,
            PoseLender {
                info: meta.info.clone(),
                query: Arc::new(query.to_image()),
                camera: meta.camera,
                cam_from_world: meta.cam_from_world,
                steps: meta.steps as usize,
            },
        );
        Ok(())
    }

    fn is_finished(&self, frame_id: u64) -> bool {
        frame_id < self.finished_below || self.finished_above.contains(&frame_id)
    }

    /// Whether a query or hypothesis of the frame arriving now is taken in (the frame is neither
    /// complete nor finished here, nor published before a restart): what is worth keeping
    /// across a restart (`runtime::received`); later copies are late.
    pub fn takes_messages_of(&self, frame_id: u64) -> bool {
        !self.is_taken(frame_id) && !self.published_before.contains(&frame_id)
    }

    /// Finished, or complete and waiting for (or in) its decision: later messages are late.
    fn is_taken(&self, frame_id: u64) -> bool {
        self.is_finished(frame_id)
            || self.deciding.contains(&frame_id)
            || self.awaiting_neighbours.contains_key(&frame_id)
            || self.ready.iter().any(|r| r.frame_id == frame_id)
    }

    fn mark_finished(&mut self, frame_id: u64) {
        self.pending.remove(&frame_id);
        self.finished_above.insert(frame_id);
        while self.finished_above.remove(&self.finished_below) {
            self.finished_below += 1;
        }
    }

    /// Frames still waiting for hypotheses or for their decision.
    pub fn pending_frames(&self) -> usize {
        self.pending.len() + self.ready.len() + self.deciding.len() + self.awaiting_neighbours.len()
    }

    /// One coarse pose's hypothesis; the frame waits in [`VerifyStage::take_ready`] when it was
    /// the last thing missing.
    pub fn on_hypothesis(&mut self, frame_id: u64, hypothesis: &Hypothesis) {
        if self.is_taken(frame_id) {
            self.late_messages += 1;
            return;
        }
        let meta = &hypothesis.meta;
        let coarse_index = meta.outcome.coarse_index as u32;
        let pending = self
            .pending
            .entry(frame_id)
            .or_insert_with(|| PendingFrame::new(&meta.info));
        pending.coarse_count = Some(meta.coarse_count);
        match hypothesis.grid_samples() {
            Some(grid) => pending.grids.insert(coarse_index, grid),
            None => pending.grids.remove(&coarse_index),
        };
        if pending
            .hypotheses
            .insert(coarse_index, meta.clone())
            .is_some()
        {
            self.late_messages += 1;
        }
        self.decide_if_complete(frame_id)
    }

    /// The frame's query; the frame waits in [`VerifyStage::take_ready`] when it was the last
    /// thing missing.
    pub fn on_query(&mut self, frame_id: u64, query: &FrameQuery) {
        if self.is_taken(frame_id) {
            self.late_messages += 1;
            return;
        }
        let image = match query.query_image() {
            Ok(image) => image.to_image(),
            Err(error) => {
                tracing::warn!(
                    "frame {frame_id} '{}': query image unusable ({error}); the frame is decided without the final refinement",
                    query.info.name
                );
                return;
            }
        };
        let pending = self
            .pending
            .entry(frame_id)
            .or_insert_with(|| PendingFrame::new(&query.info));
        if pending.query.replace(Arc::new(image)).is_some() {
            self.late_messages += 1;
        }
        if self.changes {
            match query.depth() {
                Ok(depth) => pending.depth_m = depth.map(|d| d.to_image()),
                Err(error) => tracing::warn!(
                    "frame {frame_id} '{}': depth map unusable ({error}); its change result will say no depth",
                    query.info.name
                ),
            }
            match query.photo() {
                Ok(photo) => pending.photo = photo.map(|p| p.to_image()),
                Err(error) => tracing::warn!(
                    "frame {frame_id} '{}': photo unusable ({error}); no stereo depth for it",
                    query.info.name
                ),
            }
        }
        self.decide_if_complete(frame_id)
    }

    fn decide_if_complete(&mut self, frame_id: u64) {
        let complete = self
            .pending
            .get(&frame_id)
            .is_some_and(|pending| pending.has_every_hypothesis() && pending.query.is_some());
        if let Some(pending) = complete.then(|| self.pending.remove(&frame_id)).flatten() {
            self.queue_ready(frame_id, pending);
        }
    }

    /// A stage gave up on the frame: its result is that failure (unless it already has one).
    pub fn on_failure(&mut self, frame_id: u64, failure: &FrameFailed) -> Option<PoseResult> {
        if self.is_taken(frame_id) {
            self.late_messages += 1;
            return None;
        }
        self.mark_finished(frame_id);
        let result = failed_result(
            frame_id,
            &failure.name,
            format!("{}: {}", failure.stage, failure.reason),
        );
        self.queue_change_work(&result, None);
        Some(result)
    }

    /// The source produced `frame_count` frames (ids 0..frame_count), of which `finished_frames`
    /// already have their result (told again after this stage restarted).
    pub fn on_stream_end(&mut self, frame_count: u64, finished_frames: &[u64]) {
        self.stream_frame_count = Some(frame_count);
        for &frame_id in finished_frames {
            if !self.is_finished(frame_id) {
                self.mark_finished(frame_id);
            }
        }
    }

    /// Results for frames that waited longer than the timeout (a job was lost for good).
    pub fn expire(&mut self, now: Instant) -> Vec<PoseResult> {
        let expired: Vec<u64> = self
            .pending
            .iter()
            .filter(|(_, frame)| now.duration_since(frame.first_seen) > self.frame_timeout)
            .map(|(frame_id, _)| *frame_id)
            .collect();
        let mut results = Vec::new();
        for frame_id in expired {
            let Some(frame) = self.pending.remove(&frame_id) else {
                continue;
            };
            if frame.has_every_hypothesis() {
                // Only the query is missing: decided without the final refinement.
                self.queue_ready(frame_id, frame);
                continue;
            }
            let coarse_count = frame.coarse_count.unwrap_or(0);
            let missing: Vec<String> = (0..coarse_count)
                .filter(|i| !frame.hypotheses.contains_key(i))
                .map(|i| i.to_string())
                .collect();
            let waited_for = if frame.coarse_count.is_some() {
                format!("coarse poses {} of {coarse_count}", missing.join(", "))
            } else {
                "every coarse pose".to_string()
            };
            let result = failed_result(
                frame_id,
                &frame.name,
                format!(
                    "verify: timed out after {:.0} s waiting for {waited_for} (a stage lost them; see its log)",
                    self.frame_timeout.as_secs_f64(),
                ),
            );
            self.queue_change_work(&result, None);
            results.push(result);
            self.mark_finished(frame_id);
        }
        results
    }

    /// `result` (this stage's, not yet published) cannot be given out as it is (its journal
    /// line could not be written: `reason`): it becomes a failed result with that reason, without
    /// a pose (the evidence and times stay, saying what registration found), and an accepted
    /// frame's change work becomes a change result saying why there is none (it is no stereo
    /// neighbour either).
    pub fn withdraw(&mut self, mut result: PoseResult, reason: &str) -> PoseResult {
        let frame_id = result.frame_id;
        result.accepted = false;
        result.confidence = 0.0;
        result.camera = None;
        result.cam_from_world = None;
        result.failure = Some(match result.failure.take() {
            Some(earlier) => format!("{reason} (the frame was rejected: {earlier})"),
            None => reason.to_string(),
        });
        self.pose_lenders.remove(&frame_id);
        if self.changes {
            self.registered_views.remove(&frame_id);
            self.stereo_waiting.remove(&frame_id);
            let replacement = || {
                ChangeWork::Result(not_registered(
                    frame_id,
                    &result.name,
                    result.failure.as_deref(),
                ))
            };
            let mut replaced = false;
            for work in &mut self.change_work {
                let matches = match work {
                    ChangeWork::Job(id, _) => *id == frame_id,
                    ChangeWork::Result(change) => change.frame_id == frame_id,
                };
                if matches {
                    *work = replacement();
                    replaced = true;
                }
            }
            // An accepted frame waiting for its stereo neighbours has no work queued yet.
            if !replaced {
                self.change_work.push(replacement());
            }
        }
        result
    }

    /// When the source has ended and every frame has its result: the frame count.
    pub fn stream_complete(&self) -> Option<u64> {
        self.stream_frame_count.filter(|&count| {
            self.finished_below >= count
                && self.pending.is_empty()
                && self.ready.is_empty()
                && self.deciding.is_empty()
                && self.awaiting_neighbours.is_empty()
        })
    }

    /// A complete frame, queued for [`VerifyStage::take_ready`].
    fn queue_ready(&mut self, frame_id: u64, frame: PendingFrame) {
        self.ready.push(ReadyFrame {
            frame_id,
            simulated: self.simulated,
            step: DecideStep::Own(Box::new(frame)),
        });
    }

    /// A decided frame's one result (and its change work); the frame is finished. A frame
    /// decided on its own that step "neighbour" is still to try waits for its window instead
    /// (`None`; [`VerifyStage::take_ready`] hands it out again).
    pub fn conclude(&mut self, decided: DecidedFrame) -> Option<PoseResult> {
        self.deciding.remove(&decided.frame_id);
        if !decided.neighbours_tried {
            self.awaiting_neighbours.insert(
                decided.frame_id,
                AwaitingNeighbours {
                    decided,
                    since: Instant::now(),
                },
            );
            return None;
        }
        let lender = self
            .neighbour_pose
            .enabled
            .then(|| decided.as_lender())
            .flatten();
        let DecidedFrame {
            frame_id,
            frame,
            decision:
                Decision {
                    verdict,
                    refinement,
                    ..
                },
            verify_ms,
            ..
        } = decided;
        self.mark_finished(frame_id);
        if let Err(why) = &refinement {
            tracing::debug!(
                "frame {frame_id} '{}': no final refinement: {why}",
                frame.name
            );
        }
        let chosen = verdict.chosen();
        let accepted = verdict.accepted_pose();
        let mut times = StageTimesMs::default();
        for hypothesis in frame.hypotheses.values() {
            // Each job carries the render time up to its view: the frame's is the largest.
            times.render_ms = times.render_ms.max(hypothesis.render_ms);
            times.flow_ms += hypothesis.flow_ms;
            times.pose_ms += hypothesis.pose_ms;
        }
        times.verify_ms = verify_ms;
        let registered = accepted.map(|h| (h.camera, h.cam_from_world));
        let result = PoseResult {
            frame_id,
            name: frame.name,
            accepted: verdict.accepted(),
            failure: verdict
                .rejection()
                .map(|reason| format!("verify: {reason}")),
            confidence: verdict.confidence,
            camera: accepted.map(|h| CameraNumbers::from(&h.camera)),
            cam_from_world: accepted.map(|h| PoseNumbers::from(&h.cam_from_world)),
            evidence: Evidence {
                hypotheses: verdict.hypothesis_count as u32,
                component_size: verdict.component.len() as u32,
                direct_support: verdict.direct_support as u32,
                consensus: chosen.map_or(0, |h| h.consensus as u32),
                inlier_rms_px: chosen.map(|h| h.inlier_rms_px),
                mean_delta_to_chosen_px: verdict.mean_delta_to_chosen_px,
                convergence_ratio: verdict.convergence_ratio,
                refinement: refinement.as_ref().ok().map(RefinementNumbers::from),
            },
            times,
            flow_workers: frame.hypotheses.values().map(|h| h.flow_worker).collect(),
        };
        let PendingFrame {
            info,
            depth_m,
            photo,
            ..
        } = frame;
        if let Some(lender) = lender {
            self.lend_pose(frame_id, lender);
        }
        self.queue_change_work(
            &result,
            registered.map(|(camera, cam_from_world)| Decided {
                info,
                camera,
                cam_from_world,
                depth_m,
                photo,
            }),
        );
        Some(result)
    }
}

impl VerifyStage<'_> {
    /// Keeps an accepted frame as a lender of its pose (step "neighbour") while a frame without
    /// its result may borrow it.
    fn lend_pose(&mut self, frame_id: u64, lender: PoseLender) {
        self.pose_lenders.insert(frame_id, lender);
        // The first frame without its result (published before a restart counts as having it).
        let mut first_without = self.finished_below;
        while self.is_finished(first_without) || self.published_before.contains(&first_without) {
            first_without += 1;
        }
        let oldest_borrowable =
            first_without.saturating_sub(self.neighbour_pose.window_frames as u64);
        self.pose_lenders = self.pose_lenders.split_off(&oldest_borrowable);
    }
}

fn failed_result(frame_id: u64, name: &str, reason: String) -> PoseResult {
    PoseResult {
        frame_id,
        name: name.to_string(),
        accepted: false,
        failure: Some(reason),
        confidence: 0.0,
        camera: None,
        cam_from_world: None,
        evidence: Evidence::default(),
        times: StageTimesMs::default(),
        flow_workers: Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{UnitQuaternion, Vector3};

    use super::*;
    use crate::core::frame::tests::{house_and_poses, ideal_query};
    use crate::core::rigid::Rigid3;

    fn info(name: &str, camera: Camera, prior: Rigid3) -> FrameInfo {
        FrameInfo {
            name: name.to_string(),
            camera_id: 1,
            camera,
            intrinsics_known: true,
            initial_cam_from_world: prior,
            // The seed of `core::frame::neighbour`'s test of the same neighbour (RANSAC's draws
            // decide whether the ideal query's pose lands on the edges' sharp peak).
            seed: 7,
        }
    }

    /// The names of the lenders a ready frame is to try (empty for its own decision).
    fn lender_names(ready: &ReadyFrame) -> Vec<&str> {
        match &ready.step {
            DecideStep::Own(_) => Vec::new(),
            DecideStep::Neighbours { lenders, .. } => {
                lenders.iter().map(|n| n.info.name.as_str()).collect()
            }
        }
    }

    /// Registration with step "neighbour" on, its window and look-ahead as given.
    fn neighbour_config(window_frames: usize, lookahead_frames: usize) -> RegistrationConfig {
        RegistrationConfig {
            neighbour_pose: NeighbourPoseConfig {
                enabled: true,
                window_frames,
                lookahead_frames,
                ..NeighbourPoseConfig::default()
            },
            ..RegistrationConfig::default()
        }
    }

    /// `frame` queued as frame `frame_id`, taken and decided on its own (not concluded).
    fn decide_own(
        stage: &mut VerifyStage,
        config: &RegistrationConfig,
        frame_id: u64,
        frame: PendingFrame,
    ) -> DecidedFrame {
        stage.queue_ready(frame_id, frame);
        let mut ready = stage.take_ready();
        assert_eq!(ready.len(), 1);
        ready
            .remove(0)
            .decide(stage.mesh, config, &mut VerifyWorkspace::default())
    }

    /// `own` (a frame decided on its own) taken as accepted on its own at `pose`.
    fn accept_on_its_own(own: &mut DecidedFrame, pose: Rigid3) {
        own.decision.verdict.decision = Ok(crate::core::verify::PoseHypothesis {
            camera: own.frame.camera,
            cam_from_world: pose,
            consensus: 500,
            inlier_rms_px: 1.0,
            correspondence_count: 800,
            coarse_cam_from_world: pose,
        });
        own.lender_steps = Some(0);
    }

    /// The one frame ready for step "neighbour", with `lender` its only lender, decided: it is
    /// accepted at the pose from it, one step from a frame accepted on its own.
    fn accepted_through(
        stage: &mut VerifyStage,
        config: &RegistrationConfig,
        lender: &str,
    ) -> DecidedFrame {
        let mut ready = stage.take_ready();
        assert_eq!(ready.len(), 1);
        assert_eq!(lender_names(&ready[0]), [lender]);
        let decided = ready
            .remove(0)
            .decide(stage.mesh, config, &mut VerifyWorkspace::default());
        assert!(
            decided.decision.verdict.accepted(),
            "{:?}",
            decided.decision.verdict.rejection()
        );
        assert_eq!(decided.lender_steps, Some(1));
        decided
    }

    /// Step "neighbour" in verify: a frame whose own registration gave nothing (no hypotheses)
    /// is decided on its own, then handed out again with the nearest lender looking its way
    /// (not the one facing away, nor one before its window), and accepted at the pose from
    /// that neighbour, one step from a frame accepted on its own; concluded, it lends its own
    /// pose in turn.
    #[test]
    fn a_frame_without_hypotheses_is_accepted_at_its_neighbours_pose() {
        let (mesh, camera, truth, _) = house_and_poses();
        let config = neighbour_config(2, NeighbourPoseConfig::default().lookahead_frames);
        let lender_at = |name: &str, pose: Rigid3| PoseLender {
            info: info(name, camera, pose),
            query: Arc::new(ideal_query(&mesh, &camera, &pose, &config)),
            camera,
            cam_from_world: pose,
            steps: 0,
        };
        let near = Rigid3::new(
            truth.rotation,
            truth.translation + Vector3::new(0.3, 0.12, -0.18),
        );
        let away = Rigid3::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 1.5, 0.0)) * truth.rotation,
            truth.translation,
        );
        let mut stage = VerifyStage::new(&mesh, Duration::from_secs(60))
            .with_neighbour_poses(config.neighbour_pose.clone());
        stage.mark_finished(0);
        for (id, name, pose) in [(1, "dropped", near), (2, "near", near), (3, "away", away)] {
            stage.mark_finished(id);
            stage.lend_pose(id, lender_at(name, pose));
        }
        assert_eq!(
            stage.pose_lenders.len(),
            2,
            "frame 1 is before every window"
        );
        // The stream ends with the frame: no frame after it to wait for.
        stage.on_stream_end(5, &[]);
        let mut frame = PendingFrame::new(&info("frame", camera, truth));
        frame.query = Some(Arc::new(ideal_query(&mesh, &camera, &truth, &config)));
        stage.queue_ready(4, frame);
        let mut ready = stage.take_ready();
        assert_eq!(ready.len(), 1);
        assert!(lender_names(&ready[0]).is_empty());
        let own = ready
            .remove(0)
            .decide(&mesh, &config, &mut VerifyWorkspace::default());
        assert!(!own.decision.verdict.accepted());
        assert!(
            stage.conclude(own).is_none(),
            "it waits for step \"neighbour\""
        );
        assert_eq!(stage.pending_frames(), 1);
        let decided = accepted_through(&mut stage, &config, "near");
        let result = stage.conclude(decided).expect("the frame's result");
        assert!(result.accepted && result.cam_from_world.is_some());
        assert_eq!(stage.pose_lenders.get(&4).map(|l| l.steps), Some(1));
        assert_eq!(stage.pending_frames(), 0);
    }

    /// A lender written as its message and read back (what `runtime::lenders` does across a
    /// restart) lends the same pose, query and steps.
    #[test]
    fn a_lender_survives_its_message() {
        let (mesh, camera, truth, _) = house_and_poses();
        let config = NeighbourPoseConfig::default();
        let mut query = Image::filled(camera.width_px as usize, camera.height_px as usize, 0.0);
        query.data_mut()[17] = 0.5;
        let mut before =
            VerifyStage::new(&mesh, Duration::from_secs(60)).with_neighbour_poses(config.clone());
        before.lend_pose(
            3,
            PoseLender {
                info: info("lender", camera, truth),
                query: Arc::new(query),
                camera,
                cam_from_world: truth,
                steps: 1,
            },
        );
        let bytes = crate::msg::encode(&crate::msg::Envelope {
            header: crate::msg::Header {
                frame_id: 3,
                sequence: 0,
                capture_time_ns: 0,
                sent_time_ns: 0,
            },
            body: crate::msg::Body::PoseLender(before.lender(3).unwrap()),
        })
        .unwrap()
        .to_vec();
        let decoded = crate::msg::decode(&bytes).unwrap();
        let crate::msg::Body::PoseLender(message) = &decoded.body else {
            panic!("{:?}", decoded.body.kind());
        };
        let mut after =
            VerifyStage::new(&mesh, Duration::from_secs(60)).with_neighbour_poses(config);
        after.restore_lender(3, message).unwrap();
        assert_eq!(after.lender_ids().collect::<Vec<_>>(), [3]);
        let (was, now) = (&before.pose_lenders[&3], &after.pose_lenders[&3]);
        assert_eq!(now.info, was.info);
        assert_eq!(now.query.data(), was.query.data());
        assert_eq!(
            (now.camera, now.cam_from_world),
            (was.camera, was.cam_from_world)
        );
        assert_eq!(now.steps, 1);
        let mut short = message.clone();
        short.query = std::borrow::Cow::Owned(vec![0.0; 5]);
        assert!(after.restore_lender(4, &short).is_err());
    }

    /// A frame decided on its own waits for step "neighbour" until every frame of its window
    /// has its result and every frame of its look-ahead its own decision (then its lenders do
    /// not depend on the order frames complete in), or, with a frame missing, until the frame
    /// timeout; frames published before a restart count as having their result.
    #[test]
    fn step_neighbour_waits_for_the_frames_of_its_window() {
        let (mesh, camera, truth, _) = house_and_poses();
        let config = neighbour_config(3, 2);
        let own_decision = |stage: &mut VerifyStage, frame_id: u64| {
            let mut frame = PendingFrame::new(&info("frame", camera, truth));
            frame.query = Some(Arc::new(Image::filled(
                camera.width_px as usize,
                camera.height_px as usize,
                0.0,
            )));
            let own = decide_own(stage, &config, frame_id, frame);
            assert!(stage.conclude(own).is_none());
        };
        let failure = FrameFailed {
            name: "lost".into(),
            stage: "render".into(),
            reason: "test".into(),
        };

        let mut stage = VerifyStage::new(&mesh, Duration::from_secs(60))
            .with_neighbour_poses(config.neighbour_pose.clone());
        stage.published_before_restart([2]);
        own_decision(&mut stage, 4);
        assert!(
            stage.take_ready().is_empty(),
            "frames 1 and 3 have no result"
        );
        assert!(stage.on_failure(3, &failure).is_some());
        assert!(stage.take_ready().is_empty(), "frame 1 has no result");
        assert!(stage.on_failure(1, &failure).is_some());
        assert!(
            stage.take_ready().is_empty(),
            "frames 5 and 6 have no decision"
        );
        own_decision(&mut stage, 5);
        assert!(stage.take_ready().is_empty(), "frame 6 has no decision");
        stage.on_stream_end(6, &[]);
        let ready = stage.take_ready();
        assert_eq!(ready.iter().map(|r| r.frame_id).collect::<Vec<_>>(), [4]);

        let mut stage = VerifyStage::new(&mesh, Duration::ZERO)
            .with_neighbour_poses(config.neighbour_pose.clone());
        own_decision(&mut stage, 4);
        std::thread::sleep(Duration::from_millis(2));
        assert_eq!(stage.take_ready().len(), 1, "released after the timeout");
    }

    /// Step "neighbour"'s look-ahead in verify: a frame borrows the pose of a frame after it
    /// that the model accepted on its own, once that frame is decided on its own (and before
    /// its step, which waits for the frame); the pose it is accepted at lends in turn to the
    /// frame after it.
    #[test]
    fn a_frame_borrows_the_own_accept_of_a_frame_after_it() {
        let (mesh, camera, truth, _) = house_and_poses();
        let config = neighbour_config(2, 2);
        let near = Rigid3::new(
            truth.rotation,
            truth.translation + Vector3::new(0.3, 0.12, -0.18),
        );
        let mut stage = VerifyStage::new(&mesh, Duration::from_secs(60))
            .with_neighbour_poses(config.neighbour_pose.clone());
        for id in 0..4 {
            stage.mark_finished(id);
        }
        // Frames 4 (at the truth) and 5 (near it) decided on their own: neither has
        // hypotheses, so both are rejected; frame 5 is then taken as accepted on its own at its
        // pose (its own decision is not this test's subject).
        let own_decision =
            |stage: &mut VerifyStage, frame_id: u64, name: &str, pose: Rigid3, accept: bool| {
                let mut frame = PendingFrame::new(&info(name, camera, pose));
                frame.query = Some(Arc::new(ideal_query(&mesh, &camera, &pose, &config)));
                let mut own = decide_own(stage, &config, frame_id, frame);
                assert!(!own.decision.verdict.accepted());
                if accept {
                    accept_on_its_own(&mut own, pose);
                }
                assert!(stage.conclude(own).is_none());
            };
        own_decision(&mut stage, 4, "frame", truth, false);
        assert!(stage.take_ready().is_empty(), "frames 5 and 6 undecided");
        own_decision(&mut stage, 5, "after", near, true);
        assert!(stage.take_ready().is_empty(), "frame 6 undecided");
        stage.on_stream_end(7, &[]);
        assert!(stage.take_ready().is_empty(), "frame 6 undecided");
        let failure = FrameFailed {
            name: "lost".into(),
            stage: "render".into(),
            reason: "test".into(),
        };
        assert!(stage.on_failure(6, &failure).is_some());
        // Frame 4 only: frame 5 waits for frame 4's result.
        let decided = accepted_through(&mut stage, &config, "after");
        assert!(stage.conclude(decided).expect("frame 4's result").accepted);
        let ready = stage.take_ready();
        assert_eq!(ready.iter().map(|r| r.frame_id).collect::<Vec<_>>(), [5]);
        assert_eq!(lender_names(&ready[0]), ["frame"]);
    }

    /// A frame registered with unknown intrinsics lends no pose (batch registration offers only
    /// frames with known intrinsics): not kept when concluded, not offered while held.
    #[test]
    fn a_frame_with_unknown_intrinsics_does_not_lend() {
        let (mesh, camera, truth, _) = house_and_poses();
        let config = neighbour_config(2, 2);
        let mut stage = VerifyStage::new(&mesh, Duration::from_secs(60))
            .with_neighbour_poses(config.neighbour_pose.clone());
        let mut unknown = info("unknown", camera, truth);
        unknown.intrinsics_known = false;
        let mut frame = PendingFrame::new(&unknown);
        frame.query = Some(Arc::new(ideal_query(&mesh, &camera, &truth, &config)));
        let mut own = decide_own(&mut stage, &config, 0, frame);
        assert!(own.neighbours_tried, "no step without known intrinsics");
        accept_on_its_own(&mut own, truth);
        assert!(own.as_lender().is_none());
        assert!(stage.conclude(own).expect("its result").accepted);
        assert!(stage.pose_lenders.is_empty());
    }
}
