//! Batch registration of a folder of photos: loads each frame's inputs, registers it, and turns
//! every per-frame problem (a missing or corrupt photo, a size mismatch, an invisible model) into a
//! failed frame with its reason, so one bad frame never stops the others. `asgreg register` and
//! `asgreg eval` are built on this. Frames are registered with their working camera
//! (`frame_files`: undistorted, at the working width) and reported with their own camera.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::core::camera::Camera;
use crate::core::confidence::FrameEvidence;
use crate::core::frame::{
    feed_neighbours, nearest_neighbours, query_gradient, register_frame, try_neighbours,
    FeedLender, FrameInput, IntrinsicsMode, NeighbourCheck, NeighbourDecision, NeighbourOrder,
    NeighbourView, NeighbourWorkspace, Pass, PoseRefinement, RegisteredNeighbour,
    RegistrationConfig, StageTimings, Witness,
};
use crate::core::image::Image;
use crate::core::mesh::Mesh;
use crate::core::rigid::Rigid3;
use crate::core::verify::{PoseHypothesis, RejectionReason, Verdict};
use crate::frame_files::{frame_seed, FrameFiles, FrameFilesError, FrameLoader};

/// Where one frame's inputs are.
#[derive(Clone, Debug)]
pub struct BatchFrame {
    pub image_id: u32,
    pub camera_id: u32,
    pub name: String,
    pub image_path: PathBuf,
    /// The photo's depth map (PFM), when registering with [`crate::core::frame::QueryMode::DepthAsg`].
    pub depth_path: Option<PathBuf>,
    pub camera: Camera,
    /// Whether `camera`'s intrinsics are trusted or estimated.
    pub intrinsics: IntrinsicsMode,
    pub initial_cam_from_world: Rigid3,
}

/// What happened to one frame; exactly one per input frame.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FrameReport {
    pub image_id: u32,
    pub name: String,
    pub accepted: bool,
    /// Why the frame was not accepted (input problem, or the verification's reason).
    pub reason: Option<String>,
    pub confidence: f64,
    /// RANSAC consensus of the chosen pose.
    pub consensus: usize,
    /// Size of the largest group of compatible refined poses.
    pub component_size: usize,
    /// Refined poses directly compatible with the chosen one, itself included.
    pub direct_support: usize,
    /// Spread of the agreeing refined poses over the spread of their coarse poses (small:
    /// converged; near 1: they stayed where they started).
    pub convergence_ratio: Option<f64>,
    /// Refined poses obtained from the coarse poses.
    pub hypotheses: usize,
    /// Mean δ from the chosen pose to the rest of its group, px.
    pub mean_delta_to_chosen_px: f64,
    pub inlier_rms_px: Option<f64>,
    /// The refined camera (estimated intrinsics when unknown) and pose, when accepted.
    pub camera: Option<Camera>,
    pub cam_from_world: Option<Rigid3>,
    /// A rejected frame's would-be output (the verification's chosen hypothesis), kept as
    /// evidence for diagnosing the verification; never a result. None for accepted frames and
    /// for frames without hypotheses.
    pub rejected_candidate: Option<RejectedCandidate>,
    /// The final refinement of the chosen pose (already applied to `cam_from_world` when kept:
    /// its evidence before and after), or why there was none.
    pub refinement: Result<PoseRefinement, String>,
    /// What the decision rests on (None when the frame was not registered).
    pub evidence: Option<FrameEvidence>,
    pub timings: StageTimings,
    /// When the full-circle heading fallback ran: both registrations, and which one the fields
    /// above carry (`core::frame::decide_passes`).
    #[serde(default)]
    pub heading_sweep: Option<HeadingSweepReport>,
    /// Step "neighbour" ([`neighbour_pass`]): each registered neighbour tried, in order; empty
    /// when the step did not run for the frame.
    #[serde(default)]
    pub neighbours: Vec<NeighbourReport>,
}

/// One registered neighbour tried for a frame by [`neighbour_pass`].
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct NeighbourReport {
    /// The neighbour frame's name.
    pub neighbour: String,
    /// Neighbours between this frame and one the model accepted on its own (1: the neighbour
    /// was).
    pub steps: usize,
    /// Where the neighbour's photo was matched from (files written before it: as photographed).
    #[serde(default)]
    pub view: NeighbourView,
    /// The neighbour's pose of this frame and what the model said of it, or why there is none.
    pub check: Result<NeighbourCheck, String>,
    pub decision: NeighbourDecision,
    /// The other lender whose agreeing pose confirmed this one, by name
    /// (`NeighbourCheck::agreeing_neighbour`; `NeighbourPoseConfig::two_lenders_confirm`).
    #[serde(default)]
    pub agreeing_neighbour: Option<String>,
}

impl NeighbourReport {
    /// Whether the try's pose was confirmed.
    pub fn confirmed(&self) -> bool {
        self.check
            .as_ref()
            .is_ok_and(|check| check.confirmed.is_ok())
    }

    /// What became of the try, in words: "confirmed" (by the photo's edges, or by the named
    /// lender's agreeing pose), "not confirmed: …" or "no pose: …".
    pub fn outcome(&self) -> String {
        match &self.check {
            Ok(check) => match (&check.confirmed, &self.agreeing_neighbour) {
                (Err(why), _) => format!("not confirmed: {why}"),
                (Ok(()), Some(lender)) => format!("confirmed by {lender}'s agreeing pose"),
                (Ok(()), None) => "confirmed".to_string(),
            },
            Err(why) => format!("no pose: {why}"),
        }
    }
}

/// What the full-circle heading fallback did for a frame (`core::frame::HeadingSweepOutcome`
/// with the frame's reported cameras).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct HeadingSweepReport {
    pub first: PassReport,
    /// The retry, or why it gave nothing.
    pub retry: Result<PassReport, String>,
    /// Which of the two the frame's result carries.
    pub carried: Pass,
    /// The retry's wall time, ms.
    pub sweep_ms: f64,
}

/// One registration of a frame: its verdict and its output (or would-be output) pose.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PassReport {
    pub accepted: bool,
    pub confidence: f64,
    /// Why it was not accepted.
    pub reason: Option<String>,
    /// Its output pose when accepted, else its would-be output (None without any).
    pub pose: Option<RejectedCandidate>,
}

impl PassReport {
    fn of(verdict: &Verdict, reported_camera: impl Fn(&Camera) -> Camera) -> Self {
        Self {
            accepted: verdict.accepted(),
            confidence: verdict.confidence,
            reason: verdict.rejection().map(|r| r.to_string()),
            pose: verdict.chosen().map(|h| RejectedCandidate {
                camera: reported_camera(&h.camera),
                cam_from_world: h.cam_from_world,
            }),
        }
    }
}

/// The pose a rejected frame would have output (or, in [`PassReport`], a registration's output).
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct RejectedCandidate {
    pub camera: Camera,
    pub cam_from_world: Rigid3,
}

impl FrameReport {
    fn failed(frame: &BatchFrame, reason: String) -> Self {
        Self {
            image_id: frame.image_id,
            name: frame.name.clone(),
            accepted: false,
            reason: Some(reason),
            confidence: 0.0,
            consensus: 0,
            component_size: 0,
            direct_support: 0,
            convergence_ratio: None,
            hypotheses: 0,
            mean_delta_to_chosen_px: 0.0,
            inlier_rms_px: None,
            camera: None,
            cam_from_world: None,
            rejected_candidate: None,
            refinement: Err("the frame was not registered".to_string()),
            evidence: None,
            timings: StageTimings::default(),
            heading_sweep: None,
            neighbours: Vec::new(),
        }
    }
}

impl BatchFrame {
    /// Reads the frame's photo and depth map, checked against its camera, at the default working
    /// width (a folder of frames should share one loader: [`Self::load_with`]).
    pub fn load(&self) -> Result<FrameFiles, FrameFilesError> {
        self.load_with(&FrameLoader::default())
    }

    /// Reads the frame's photo and depth map, checked against its camera, as `loader`'s working
    /// camera sees them.
    pub fn load_with(&self, loader: &FrameLoader) -> Result<FrameFiles, FrameFilesError> {
        loader.load(
            &self.image_path,
            self.camera_id,
            &self.camera,
            self.depth_path.as_deref(),
        )
    }

    /// The camera to report for a camera registration returned with the working camera: the
    /// frame's own when the intrinsics are known, else the estimate taken back to the photo's
    /// size and lens (`WorkingCamera::source_camera_for`).
    pub fn reported_camera(&self, files: &FrameFiles, registered: &Camera) -> Camera {
        match self.intrinsics {
            IntrinsicsMode::Known => self.camera,
            IntrinsicsMode::Unknown => files.working.source_camera_for(registered),
        }
    }

    /// The frame as registration's input, from its loaded files (with their working camera); `seed` is the run's seed (the
    /// frame's own is derived from it and the image id).
    pub fn input<'a>(&'a self, files: &'a FrameFiles, seed: u64) -> FrameInput<'a> {
        FrameInput {
            photo: files.photo.view(),
            depth_m: files.depth_m.as_ref().map(Image::view),
            camera: &files.camera,
            intrinsics: self.intrinsics,
            initial_cam_from_world: self.initial_cam_from_world,
            seed: frame_seed(seed, self.image_id),
        }
    }
}

/// Registers one frame at the default working width; never fails: problems become a failed
/// report naming the file or reason.
pub fn register_batch_frame(
    mesh: &Mesh,
    frame: &BatchFrame,
    config: &RegistrationConfig,
    seed: u64,
) -> FrameReport {
    register_batch_frame_with(mesh, frame, &FrameLoader::default(), config, seed)
}

/// [`register_batch_frame`] with the frames' loader (its working width, and each camera's
/// plan built once). Poses are the same for the working camera and the frame's own; the
/// reported cameras are the frame's own ([`BatchFrame::reported_camera`]).
pub fn register_batch_frame_with(
    mesh: &Mesh,
    frame: &BatchFrame,
    loader: &FrameLoader,
    config: &RegistrationConfig,
    seed: u64,
) -> FrameReport {
    let files = match frame.load_with(loader) {
        Ok(files) => files,
        Err(error) => return FrameReport::failed(frame, error.to_string()),
    };
    match register_frame(mesh, &frame.input(&files, seed), config) {
        Ok(result) => {
            let verdict = &result.verdict;
            let reported = |camera: &Camera| frame.reported_camera(&files, camera);
            let heading_sweep = result
                .heading_sweep
                .as_ref()
                .map(|sweep| HeadingSweepReport {
                    first: PassReport::of(&sweep.first.verdict, reported),
                    retry: sweep
                        .retry
                        .as_ref()
                        .map(|retry| PassReport::of(&retry.verdict, reported))
                        .map_err(Clone::clone),
                    carried: sweep.carried,
                    sweep_ms: sweep.sweep_ms,
                });
            let chosen = verdict.chosen();
            let accepted = verdict.accepted_pose();
            FrameReport {
                image_id: frame.image_id,
                name: frame.name.clone(),
                accepted: verdict.accepted(),
                reason: verdict.rejection().map(|r| r.to_string()),
                confidence: verdict.confidence,
                consensus: chosen.map_or(0, |h| h.consensus),
                component_size: verdict.component.len(),
                direct_support: verdict.direct_support,
                convergence_ratio: verdict.convergence_ratio,
                hypotheses: verdict.hypothesis_count,
                mean_delta_to_chosen_px: verdict.mean_delta_to_chosen_px,
                inlier_rms_px: chosen.map(|h| h.inlier_rms_px),
                camera: accepted.map(|h| frame.reported_camera(&files, &h.camera)),
                cam_from_world: accepted.map(|h| h.cam_from_world),
                rejected_candidate: verdict
                    .decision
                    .as_ref()
                    .err()
                    .and_then(|rejection| rejection.candidate)
                    .map(|h| RejectedCandidate {
                        camera: frame.reported_camera(&files, &h.camera),
                        cam_from_world: h.cam_from_world,
                    }),
                refinement: result.refinement,
                evidence: Some(result.evidence),
                timings: result.timings,
                heading_sweep,
                neighbours: Vec::new(),
            }
        }
        Err(error) => FrameReport::failed(frame, format!("{}: {error}", frame.name)),
    }
}

/// A frame's inputs for step "neighbour": its files and query image, loaded once per pass.
struct LoadedQuery {
    files: FrameFiles,
    query: Image<f32>,
}

/// Step "neighbour" over a batch already registered frame by frame (`reports[i]` is
/// `frames[i]`'s), in the order `config.neighbour_pose.order` says: a frame is tried against
/// the poses of accepted frames ([`try_neighbours`]), checked by the model; a frame not accepted
/// is accepted at a confirmed neighbour's pose and lends it in turn (up to `max_steps` from a
/// frame the model accepted on its own); an accepted frame a confirmed neighbour's pose
/// contradicts is rejected.
///
/// - [`NeighbourOrder::Feed`]: frame `i` borrows from the frames before it and from the own
///   accepts of the few after it ([`feed_neighbours`]), each decided before the next — the
///   rule the pipeline's verify follows, so `register` and `run` give one result.
/// - [`NeighbourOrder::Set`]: a collection without an order; round `r` lends the poses of frames
///   accepted `r − 1` neighbours away from one the model accepted on its own to every other
///   frame ([`nearest_neighbours`]), each round decided on the reports as they were when it
///   began, so the order of the frames does not matter.
///
/// Frames with unknown intrinsics, and those whose files cannot be read, are left as they
/// are. Returns the indices of the frames whose decision or pose changed, ascending.
pub fn neighbour_pass(
    mesh: &Mesh,
    frames: &[BatchFrame],
    reports: &mut [FrameReport],
    loader: &FrameLoader,
    config: &RegistrationConfig,
    seed: u64,
) -> Vec<usize> {
    let mut pass = NeighbourPass {
        mesh,
        frames,
        loader,
        config,
        seed,
        steps: reports
            .iter()
            .map(|report| report.accepted.then_some(0))
            .collect(),
        loaded: frames.iter().map(|_| None).collect(),
        workspace: NeighbourWorkspace::default(),
        witnesses: frames.iter().map(|_| Vec::new()).collect(),
        changed: Vec::new(),
    };
    let settings = &config.neighbour_pose;
    let known = |index: usize| frames[index].intrinsics == IntrinsicsMode::Known;
    match settings.order {
        NeighbourOrder::Feed => {
            for index in (0..frames.len()).filter(|&i| known(i)) {
                // Frames after `index` have only their own decision yet.
                let lenders = (0..frames.len()).filter(|&i| known(i)).filter_map(|i| {
                    Some(FeedLender {
                        index: i,
                        cam_from_world: reports[i].cam_from_world?,
                        steps: pass.steps[i]?,
                    })
                });
                let prior = &frames[index].initial_cam_from_world;
                let candidates = feed_neighbours(index, prior, lenders, settings);
                if let Some(tried) = pass.try_frame(index, &candidates, reports) {
                    pass.apply(index, tried, reports);
                }
                // Query images no later frame can borrow are dropped.
                if let Some(old) = (index + 1).checked_sub(settings.window_frames + 1) {
                    pass.loaded[old] = None;
                }
            }
        }
        NeighbourOrder::Set => {
            for round in 1..=settings.max_steps {
                let lenders: Vec<(usize, Rigid3)> = (0..frames.len())
                    .filter(|&index| known(index) && pass.steps[index] == Some(round - 1))
                    .filter_map(|index| Some((index, reports[index].cam_from_world?)))
                    .collect();
                if lenders.is_empty() {
                    break;
                }
                let mut decided = Vec::new();
                for index in (0..frames.len()).filter(|&i| known(i)) {
                    // Round 1 checks every frame; later rounds only those still not accepted.
                    if round > 1 && pass.steps[index].is_some() {
                        continue;
                    }
                    let others: Vec<(usize, Rigid3)> = lenders
                        .iter()
                        .copied()
                        .filter(|&(i, _)| i != index)
                        .collect();
                    let prior = &frames[index].initial_cam_from_world;
                    let candidates = nearest_neighbours(prior, &others, settings);
                    decided.extend(
                        pass.try_frame(index, &candidates, reports)
                            .map(|tried| (index, tried)),
                    );
                }
                for (index, tried) in decided {
                    pass.apply(index, tried, reports);
                }
            }
        }
    }
    let mut changed = pass.changed;
    changed.sort_unstable();
    changed.dedup();
    changed
}

/// The state of one [`neighbour_pass`].
struct NeighbourPass<'a> {
    mesh: &'a Mesh,
    frames: &'a [BatchFrame],
    loader: &'a FrameLoader,
    config: &'a RegistrationConfig,
    seed: u64,
    /// Per frame: steps from a frame the model accepted on its own (`None`: not accepted).
    steps: Vec<Option<usize>>,
    /// Per frame: its files and query image, once loaded.
    loaded: Vec<Option<LoadedQuery>>,
    workspace: NeighbourWorkspace,
    /// Per frame: the lenders' poses of it the edges support but do not confirm alone
    /// (`neighbour::Witness`), over its rounds
    /// (`NeighbourOrder::Set` tries a frame once per round; `Feed` once).
    witnesses: Vec<Vec<Witness>>,
    changed: Vec<usize>,
}

impl NeighbourPass<'_> {
    /// Tries frame `index` against `candidates` (nearest first; [`try_neighbours`]), each try
    /// recorded in its report; returns the confirmed one, if any.
    fn try_frame(
        &mut self,
        index: usize,
        candidates: &[usize],
        reports: &mut [FrameReport],
    ) -> Option<NeighbourReport> {
        let (frames, config) = (self.frames, self.config);
        let frame = &frames[index];
        if candidates.is_empty()
            || load_query(frame, self.loader, config, &mut self.loaded[index]).is_err()
        {
            return None;
        }
        let candidates: Vec<usize> = candidates
            .iter()
            .copied()
            .filter(|&c| load_query(&frames[c], self.loader, config, &mut self.loaded[c]).is_ok())
            .collect();
        let own = self.loaded[index].as_ref()?;
        let (lenders, neighbours): (Vec<usize>, Vec<RegisteredNeighbour>) = candidates
            .iter()
            .filter_map(|&c| {
                let lender = self.loaded[c].as_ref()?;
                Some((
                    c,
                    RegisteredNeighbour {
                        id: c,
                        query: lender.query.view(),
                        camera: &lender.files.camera,
                        cam_from_world: reports[c].cam_from_world?,
                    },
                ))
            })
            .unzip();
        let (accepted, candidate) = own_poses(&reports[index], frame, own.files.camera);
        let own_pose = match (&accepted, &candidate) {
            (Some(pose), _) => Ok(pose),
            (None, candidate) => Err(candidate.as_ref()),
        };
        let tries = try_neighbours(
            self.mesh,
            &own.files.camera,
            frame.intrinsics,
            own.query.view(),
            own_pose,
            &neighbours,
            &mut self.witnesses[index],
            config,
            crate::frame_files::frame_seed(self.seed, frame.image_id),
            &mut self.workspace,
        );
        let mut decisive = None;
        for tried in tries {
            let c = lenders[tried.neighbour];
            let confirmed = tried.confirmed();
            let agreeing_neighbour = tried.agreeing_neighbour().map(|id| frames[id].name.clone());
            let report = NeighbourReport {
                agreeing_neighbour,
                neighbour: frames[c].name.clone(),
                steps: self.steps[c].unwrap_or(0) + 1,
                view: tried.view,
                check: tried.check,
                decision: tried.decision,
            };
            reports[index].neighbours.push(report.clone());
            if confirmed {
                decisive = Some(report);
            }
        }
        decisive
    }

    /// A confirmed try's decision applied to frame `index`'s report.
    fn apply(&mut self, index: usize, tried: NeighbourReport, reports: &mut [FrameReport]) {
        let report = &mut reports[index];
        match (tried.decision, tried.check) {
            (NeighbourDecision::Accept, Ok(check)) => {
                report.accepted = true;
                report.reason = None;
                report.camera = Some(self.frames[index].camera);
                report.cam_from_world = Some(check.hypothesis.cam_from_world);
                report.consensus = check.hypothesis.consensus;
                report.inlier_rms_px = Some(check.hypothesis.inlier_rms_px);
                report.rejected_candidate = None;
                self.steps[index] = Some(tried.steps);
                self.changed.push(index);
            }
            (NeighbourDecision::Combine { cam_from_world }, _) => {
                report.cam_from_world = Some(cam_from_world);
                self.changed.push(index);
            }
            (NeighbourDecision::Contradicted { apart_px }, _) => {
                report.accepted = false;
                report.reason = Some(
                    RejectionReason::ContradictedByNeighbour {
                        neighbour: tried.neighbour.clone(),
                        apart_px,
                    }
                    .to_string(),
                );
                report.rejected_candidate =
                    report
                        .camera
                        .zip(report.cam_from_world)
                        .map(|(camera, cam_from_world)| RejectedCandidate {
                            camera,
                            cam_from_world,
                        });
                report.camera = None;
                report.cam_from_world = None;
                self.steps[index] = None;
                self.changed.push(index);
            }
            _ => {}
        }
    }
}

/// Loads `frame`'s files and query image into `slot` once.
fn load_query(
    frame: &BatchFrame,
    loader: &FrameLoader,
    config: &RegistrationConfig,
    slot: &mut Option<LoadedQuery>,
) -> Result<(), String> {
    if slot.is_some() {
        return Ok(());
    }
    let files = frame.load_with(loader).map_err(|e| e.to_string())?;
    let query = query_gradient(&frame.input(&files, 0), config).map_err(|e| e.to_string())?;
    *slot = Some(LoadedQuery { files, query });
    Ok(())
}

/// A frame's own poses as step "neighbour" reads them from its report (with its working
/// `camera`, which known intrinsics share with the report's): its accepted pose, and its
/// would-be pose when rejected.
fn own_poses(
    report: &FrameReport,
    frame: &BatchFrame,
    camera: Camera,
) -> (Option<PoseHypothesis>, Option<PoseHypothesis>) {
    let as_hypothesis = |cam_from_world: Rigid3| PoseHypothesis {
        camera,
        cam_from_world,
        consensus: report.consensus,
        inlier_rms_px: report.inlier_rms_px.unwrap_or(0.0),
        correspondence_count: 0,
        coarse_cam_from_world: frame.initial_cam_from_world,
    };
    (
        report.cam_from_world.map(as_hypothesis),
        report
            .rejected_candidate
            .map(|candidate| as_hypothesis(candidate.cam_from_world)),
    )
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;
    use crate::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};
    use crate::io::colmap::{read_cameras_txt, read_images_txt};
    use crate::io::images::{load_rgb, save_rgb_png};
    use crate::io::mesh_file::read_mesh;
    use crate::synth::{generate_scene, SynthConfig};

    /// The pose a report gives: the accepted one, else the rejected candidate.
    fn output_pose(report: &FrameReport) -> Option<Rigid3> {
        report
            .cam_from_world
            .or(report.rejected_candidate.map(|c| c.cam_from_world))
    }

    /// A photo 3× as large (each pixel repeated 3×3), registered at the original width, gives
    /// the result of the original photo: the working resolution is resizing the photo
    /// beforehand, and the poses are written for the large photo's own camera.
    #[test]
    fn working_width_registers_a_large_photo_like_the_photo_resized() {
        const FACTOR: usize = 3;
        let dir = tempfile::tempdir().unwrap();
        let synth = SynthConfig {
            seed: 5,
            width_px: 160,
            height_px: 88,
            image_count: 6,
            initial_levels_px: vec![8.0],
            supersampling: 1,
            model_voxel_m: 0.35,
            ..SynthConfig::default()
        };
        generate_scene(&synth, dir.path()).unwrap();
        let mesh = read_mesh(&dir.path().join("model.ply")).unwrap();
        let cameras = read_cameras_txt(&dir.path().join("gt/cameras.txt")).unwrap();
        let images = read_images_txt(&dir.path().join("initial/8/images.txt")).unwrap();
        let config = RegistrationConfig {
            coarse_pose_count: 5,
            ..RegistrationConfig::default()
        };
        let mut workspace = ReprojectionWorkspace::new();
        let mut compared = 0;
        for image in &images {
            let camera = cameras[&image.camera_id];
            let small_path = dir.path().join("images").join(&image.name);
            let rgb = load_rgb(&small_path).unwrap();
            let (width, height) = rgb.size();
            let large = Image::from_fn(width * FACTOR, height * FACTOR, |col, row| {
                *rgb.get(col / FACTOR, row / FACTOR).unwrap()
            });
            let large_path = dir.path().join(format!("large_{}.png", image.image_id));
            save_rgb_png(&large_path, large.view()).unwrap();
            let small_frame = BatchFrame {
                image_id: image.image_id,
                camera_id: image.camera_id,
                name: image.name.clone(),
                image_path: small_path,
                depth_path: None,
                camera,
                intrinsics: IntrinsicsMode::Known,
                initial_cam_from_world: image.cam_from_world,
            };
            let large_camera = camera.resized((width * FACTOR) as u32, (height * FACTOR) as u32);
            let large_frame = BatchFrame {
                image_path: large_path,
                camera: large_camera,
                ..small_frame.clone()
            };
            let small =
                register_batch_frame_with(&mesh, &small_frame, &FrameLoader::new(None), &config, 1);
            let large = register_batch_frame_with(
                &mesh,
                &large_frame,
                &FrameLoader::new(Some(width as u32)),
                &config,
                1,
            );
            assert_eq!(large.accepted, small.accepted, "{}", image.name);
            assert_eq!(large.hypotheses, small.hypotheses, "{}", image.name);
            if large.accepted {
                assert_eq!(large.camera, Some(large_camera));
            }
            let (Some(small_pose), Some(large_pose)) = (output_pose(&small), output_pose(&large))
            else {
                assert_eq!(output_pose(&small), output_pose(&large), "{}", image.name);
                continue;
            };
            let delta_px = mutual_reprojection_error_px(
                &mesh,
                &camera,
                &small_pose,
                &camera,
                &large_pose,
                &mut workspace,
            )
            .unwrap();
            eprintln!(
                "{}: δ(large photo, resized photo) {delta_px:.2e} px",
                image.name
            );
            assert!(delta_px < 1e-3, "{}: δ {delta_px} px", image.name);
            compared += 1;
        }
        assert!(compared >= 1, "no frame gave a pose to compare");
    }

    /// The shared Brighton set as the distortion tests use it: the mesh, the SIMPLE_RADIAL camera
    /// of the distorted photos, the PINHOLE camera of the undistorted ones and the true poses.
    struct BrightonPair {
        data: std::path::PathBuf,
        mesh: Mesh,
        distorted_camera: Camera,
        undistorted_camera: Camera,
        truth: Vec<crate::io::colmap::ImagePose>,
    }

    impl BrightonPair {
        fn load() -> Self {
            let data = crate::test_data::shared_data("brighton_beach");
            let camera_of = |folder: &str| {
                read_cameras_txt(&data.join(folder).join("cameras.txt")).unwrap()[&1]
            };
            Self {
                mesh: read_mesh(&data.join("mesh.ply")).unwrap(),
                distorted_camera: camera_of("gt_simple_radial"),
                undistorted_camera: camera_of("gt_undistorted"),
                truth: read_images_txt(&data.join("gt_undistorted/images.txt")).unwrap(),
                data,
            }
        }

        /// `image` (its prior) as a batch frame of the photo in `folder` with `camera`.
        fn frame(
            &self,
            image: &crate::io::colmap::ImagePose,
            folder: &str,
            camera: Camera,
        ) -> BatchFrame {
            BatchFrame {
                image_id: image.image_id,
                camera_id: image.camera_id,
                name: image.name.clone(),
                image_path: self.data.join(folder).join(&image.name),
                depth_path: None,
                camera,
                intrinsics: IntrinsicsMode::Known,
                initial_cam_from_world: image.cam_from_world,
            }
        }

        /// δ between two poses of the undistorted camera (995 px wide), px.
        fn delta_px(&self, a: &Rigid3, b: &Rigid3, workspace: &mut ReprojectionWorkspace) -> f64 {
            let camera = &self.undistorted_camera;
            mutual_reprojection_error_px(&self.mesh, camera, a, camera, b, workspace).unwrap()
        }

        /// The true pose of the photo `name`.
        fn truth_of(&self, name: &str) -> Rigid3 {
            self.truth
                .iter()
                .find(|image| image.name == name)
                .unwrap()
                .cam_from_world
        }
    }

    /// The EXIF priors of the shared Brighton set (`NAME QW QX QY QZ TX TY TZ`) of `names`, with
    /// the image and camera ids of `gt_images`.
    fn brighton_priors(data: &Path, names: &[&str]) -> Vec<crate::io::colmap::ImagePose> {
        let text = std::fs::read_to_string(data.join("prior_pose_from_exif.txt")).unwrap();
        let gt = read_images_txt(&data.join("gt_undistorted/images.txt")).unwrap();
        names
            .iter()
            .map(|name| {
                let line = text
                    .lines()
                    .find(|line| line.split_whitespace().next() == Some(name))
                    .unwrap();
                let v: Vec<f64> = line
                    .split_whitespace()
                    .skip(1)
                    .map(|value| value.parse().unwrap())
                    .collect();
                let image = gt.iter().find(|image| image.name == *name).unwrap();
                crate::io::colmap::ImagePose {
                    cam_from_world: Rigid3::from_colmap(
                        [v[0], v[1], v[2], v[3]],
                        [v[4], v[5], v[6]],
                    ),
                    ..image.clone()
                }
            })
            .collect()
    }

    /// A photo whose EXIF heading is 180° off (DJI_0027, the return leg) registers from that
    /// prior: its photo shows none of the mesh's edges, so the pose search is blind and the
    /// prior's flip becomes a centre whose fifteen refined poses agree; the check's own pose is
    /// the output (the alignment's gain there is chance). Before the flip centre the frame was
    /// rejected 548 px off (docs/measurements.md, thirty-ninth session). A sane-heading frame
    /// (DJI_0032), whose search is blind too, stays accepted beside its flip centre.
    #[test]
    #[ignore = "needs ../shared/data/brighton_beach (the shared data set beside the repo)"]
    fn shared_data_brighton_flipped_heading_registers_from_its_exif_prior() {
        const NAMES: [&str; 2] = ["DJI_0027.JPG", "DJI_0032.JPG"];
        let brighton = BrightonPair::load();
        let config = RegistrationConfig::default();
        let loader = FrameLoader::default();
        let mut workspace = ReprojectionWorkspace::new();
        for image in brighton_priors(&brighton.data, &NAMES) {
            let frame = brighton.frame(&image, "images_undistorted", brighton.undistorted_camera);
            let report = register_batch_frame_with(&brighton.mesh, &frame, &loader, &config, 1);
            let truth = brighton.truth_of(&image.name);
            let prior_px = brighton.delta_px(&image.cam_from_world, &truth, &mut workspace);
            let pose = output_pose(&report).expect("a pose");
            let delta_px = brighton.delta_px(&pose, &truth, &mut workspace);
            eprintln!(
                "{}: prior {prior_px:.1} px, accepted {} ({:.2}, {:?}), {delta_px:.2} px from the truth",
                image.name, report.accepted, report.confidence, report.reason
            );
            assert!(report.accepted, "{}: {:?}", image.name, report.reason);
            assert!(delta_px < 5.0, "{}: {delta_px} px", image.name);
            let refinement = report.refinement.as_ref().expect("refined");
            assert!(
                refinement.peak.at_chance_everywhere(),
                "{:?}",
                refinement.peak
            );
            assert!(!refinement.kept);
        }
    }

    /// Diagnosis of the gap between the distorted and the undistorted Brighton photos (issue #16
    /// item 1), printed, asserting nothing: the two working cameras and images, both frames'
    /// poses, and how far the final refinement moves the pose when only its start, only the
    /// image, or a faint perturbation of the image changes (δ at the photos' 995 px width;
    /// `image_uncertainty_px` is at the working width).
    #[test]
    #[ignore = "measurement: needs ../shared/data/brighton_beach; run by hand with --nocapture"]
    fn shared_data_brighton_distortion_gap_diagnosis() {
        use crate::core::edge_align::AlignedParameters;
        use crate::core::frame::{query_gradient, refine_pose, register_query, RefineWorkspace};
        let names: Vec<String> = std::env::var("ASGREG_DIAG_FRAMES")
            .unwrap_or_else(|_| "DJI_0032.JPG".into())
            .split(',')
            .map(str::to_string)
            .collect();
        let names: Vec<&str> = names.iter().map(String::as_str).collect();
        let brighton = BrightonPair::load();
        let (mesh, distorted_camera, undistorted_camera) = (
            &brighton.mesh,
            brighton.distorted_camera,
            brighton.undistorted_camera,
        );
        let config = RegistrationConfig::default();
        let loader = FrameLoader::default();
        let mut workspace = ReprojectionWorkspace::new();
        let mut refine_workspace = RefineWorkspace::default();
        for image in brighton_priors(&brighton.data, &names) {
            let frame = |folder: &str, camera: Camera| brighton.frame(&image, folder, camera);
            let truth = brighton.truth_of(&image.name);
            let frame_u = frame("images_undistorted", undistorted_camera);
            let frame_d = frame("images_distorted", distorted_camera);
            let files_u = frame_u.load_with(&loader).unwrap();
            let files_d = frame_d.load_with(&loader).unwrap();
            eprintln!(
                "{}: working camera undistorted set {:?}\n  distorted set {:?}",
                image.name, files_u.camera, files_d.camera
            );
            if files_u.photo.size() == files_d.photo.size() {
                let (a, b) = (files_u.photo.data(), files_d.photo.data());
                let mean = a
                    .iter()
                    .zip(b)
                    .map(|(x, y)| f64::from((x - y).abs()))
                    .sum::<f64>()
                    / a.len() as f64;
                eprintln!("  mean |working photo difference| {mean:.4} (grey 0..1)");
                // The other order: undistorted at the photo's size, then averaged down.
                let full = crate::core::undistort::WorkingCamera::new(&distorted_camera, None)
                    .unwrap()
                    .photo(
                        crate::io::images::load_gray(&frame_d.image_path)
                            .unwrap()
                            .view(),
                    )
                    .unwrap();
                let mut other_order = Image::default();
                crate::core::undistort::resize_area(
                    full.view(),
                    files_u.photo.width_px(),
                    files_u.photo.height_px(),
                    &mut other_order,
                );
                let mean = a
                    .iter()
                    .zip(other_order.data())
                    .map(|(x, y)| f64::from((x - y).abs()))
                    .sum::<f64>()
                    / a.len() as f64;
                eprintln!("  undistorted at the photo's size, then averaged down: {mean:.4}");
                if let Ok(dir) = std::env::var("ASGREG_DIAG_DUMP") {
                    let dir = Path::new(&dir);
                    for (label, photo) in [
                        ("undistorted_set", &files_u.photo),
                        ("distorted_set", &files_d.photo),
                        ("distorted_set_other_order", &other_order),
                    ] {
                        crate::io::pfm::write_pfm(
                            &dir.join(format!("{}_{label}.pfm", image.name)),
                            photo.view(),
                        )
                        .unwrap();
                    }
                }
            }
            let input_u = frame_u.input(&files_u, 1);
            let input_d = frame_d.input(&files_d, 1);
            let query_u = query_gradient(&input_u, &config).unwrap();
            let query_d = query_gradient(&input_d, &config).unwrap();
            let register = |camera: &Camera, query: &Image<f32>| {
                register_query(
                    mesh,
                    camera,
                    IntrinsicsMode::Known,
                    &image.cam_from_world,
                    query.view(),
                    &config,
                    input_u.seed,
                )
                .unwrap()
            };
            let result_u = register(&files_u.camera, &query_u);
            let result_d = register(&files_d.camera, &query_d);
            let pose = |result: &crate::core::frame::FrameResult| {
                result.verdict.chosen().unwrap().cam_from_world
            };
            let start = |result: &crate::core::frame::FrameResult| {
                result.refinement.as_ref().unwrap().verified_cam_from_world
            };
            let uncertainty = |result: &crate::core::frame::FrameResult| {
                result
                    .evidence
                    .edges
                    .map_or(f64::NAN, |e| e.image_uncertainty_px)
            };
            let mut delta_px = |a: &Rigid3, b: &Rigid3| brighton.delta_px(a, b, &mut workspace);
            let (pose_u, pose_d) = (pose(&result_u), pose(&result_d));
            eprintln!(
                "  undistorted: accepted {} confidence {:.3} uncertainty {:.3} working px, δ truth {:.2} px; distorted: accepted {} confidence {:.3} uncertainty {:.3}, δ truth {:.2} px",
                result_u.verdict.accepted(),
                result_u.verdict.confidence,
                uncertainty(&result_u),
                delta_px(&pose_u, &truth),
                result_d.verdict.accepted(),
                result_d.verdict.confidence,
                uncertainty(&result_d),
                delta_px(&pose_d, &truth),
            );
            eprintln!(
                "  δ(distorted, undistorted) final {:.3} px, verified (before refinement) {:.3} px",
                delta_px(&pose_d, &pose_u),
                delta_px(&start(&result_d), &start(&result_u))
            );
            // The aligned pose whether kept or not (the refinement keeps it only when its edge
            // support is higher than the start's).
            let mut refine_with = |config: &RegistrationConfig,
                                   camera: &Camera,
                                   query: &Image<f32>,
                                   from: &Rigid3| {
                let refinement = refine_pose(
                    mesh,
                    camera,
                    query.view(),
                    from,
                    AlignedParameters::Pose,
                    config,
                    &mut refine_workspace,
                )
                .unwrap();
                (refinement.aligned_cam_from_world, refinement.kept)
            };
            let mut variants = vec![("default", config.clone())];
            let mut longer = config.clone();
            longer.edge_align.iterations_per_level = 16;
            variants.push(("16 steps per level", longer));
            let mut no_rounding = config.clone();
            no_rounding.edge_align.estimate_rounding = false;
            variants.push(("no rounding estimate", no_rounding));
            let mut both = config.clone();
            both.edge_align.iterations_per_level = 16;
            both.edge_align.estimate_rounding = false;
            variants.push(("16 steps, no rounding", both));
            let [(_, noisy_photo), _] = faint_perturbations(&files_u.photo);
            let noisy_query = query_gradient(
                &FrameInput {
                    photo: noisy_photo.view(),
                    ..input_u
                },
                &config,
            )
            .unwrap();
            let starts = [
                ("own start", start(&result_u)),
                ("distorted run's start", start(&result_d)),
                ("truth", truth),
            ];
            for (label, variant) in &variants {
                let ends: Vec<(Rigid3, bool)> = starts
                    .iter()
                    .map(|(_, from)| refine_with(variant, &files_u.camera, &query_u, from))
                    .collect();
                let again = refine_with(variant, &files_u.camera, &query_u, &ends[0].0);
                let distorted_image = refine_with(variant, &files_d.camera, &query_d, &starts[0].1);
                let noisy = refine_with(variant, &files_u.camera, &noisy_query, &starts[0].1);
                eprintln!(
                    "  refinement ({label}) on the undistorted image: ends from {} / {} / {} (kept {} {} {}): {:.3} / {:.3} px apart (vs own start's end); refined again moves {:.3} px; truth {:.3} px from the end; same start on the distorted image {:.3} px, on the photo + noise 1/255 {:.3} px",
                    starts[0].0,
                    starts[1].0,
                    starts[2].0,
                    ends[0].1,
                    ends[1].1,
                    ends[2].1,
                    delta_px(&ends[1].0, &ends[0].0),
                    delta_px(&ends[2].0, &ends[0].0),
                    delta_px(&again.0, &ends[0].0),
                    delta_px(&truth, &ends[0].0),
                    delta_px(&distorted_image.0, &ends[0].0),
                    delta_px(&noisy.0, &ends[0].0),
                );
            }
            let mut refine = |camera: &Camera, query: &Image<f32>, from: &Rigid3| {
                let (pose, kept) = refine_with(&config, camera, query, from);
                if kept {
                    pose
                } else {
                    *from
                }
            };
            for (label, photo) in faint_perturbations(&files_u.photo) {
                let input = FrameInput {
                    photo: photo.view(),
                    ..input_u
                };
                let query = query_gradient(&input, &config).unwrap();
                let from_same_start = refine(&files_u.camera, &query, &start(&result_u));
                let result = register(&files_u.camera, &query);
                eprintln!(
                    "  {label}: refinement from the same start moves {:.3} px; whole registration moves {:.3} px (verified {:.3} px), confidence {:.3}",
                    delta_px(&from_same_start, &pose_u),
                    delta_px(&pose(&result), &pose_u),
                    delta_px(&start(&result), &start(&result_u)),
                    result.verdict.confidence,
                );
            }
        }
    }

    /// Two faint perturbations of a working photo that a person could not see: seeded noise of
    /// one grey level (σ = 1/255), and a shift by a tenth of a pixel to the right (bilinear).
    /// How far they move a pose is the method's own repeatability on that photo.
    fn faint_perturbations(photo: &Image<f32>) -> [(&'static str, Image<f32>); 2] {
        use rand::SeedableRng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let (width_px, height_px) = photo.size();
        let noisy = Image::from_fn(width_px, height_px, |c, r| {
            let noise: f32 =
                rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut rng);
            photo.get(c, r).unwrap() + noise / 255.0
        });
        let shifted = Image::from_fn(width_px, height_px, |c, r| {
            let left = *photo.get(c.saturating_sub(1), r).unwrap();
            0.9 * photo.get(c, r).unwrap() + 0.1 * left
        });
        [("noise 1/255", noisy), ("shift 0.1 px", shifted)]
    }

    /// The shared Brighton Beach photos with lens distortion (SIMPLE_RADIAL, `images_distorted`)
    /// register, from the photos' EXIF priors at the default working width, like the photos
    /// COLMAP undistorted (`images_undistorted`, PINHOLE): both get the same working camera
    /// (505×283 px, `core::undistort`), so their working photos differ only by resampling and
    /// JPEG (mean |difference| 0.005 of the grey range). Issue #16 asks for the same poses to
    /// 0.1 px; measured (docs/measurements.md, branch `distort`): δ between the two 0.77 px
    /// (DJI_0031) and 1.83 px (DJI_0032), while the pose of the undistorted photo itself moves
    /// by 2.1–3.5 px when that photo gets invisible noise (1/255) or moves by a tenth of a pixel
    /// (its `image_uncertainty_px`, 0.14–0.18 working px, is 10× too optimistic): the method's
    /// repeatability (the final edge alignment does not converge on these photos), not the lens,
    /// sets the gap, and 0.1 px is out of reach. What the test holds: the gap is within the
    /// pose's spread under those perturbations of the undistorted photo; both photos give a
    /// pose; an accepted distorted photo is reported with its own camera. (Acceptance is not
    /// compared: the frames sit at confidence 0.85–0.91 around the 0.9 threshold, and a tenth
    /// of a pixel of shift took the undistorted DJI_0031 from 0.879 to 0.905.)
    #[test]
    #[ignore = "needs ../shared/data/brighton_beach (the shared data set beside the repo)"]
    fn shared_data_brighton_distorted_photos_register_like_the_undistorted_ones() {
        const NAMES: [&str; 2] = ["DJI_0031.JPG", "DJI_0032.JPG"];
        let brighton = BrightonPair::load();
        let (mesh, distorted_camera, undistorted_camera) = (
            &brighton.mesh,
            brighton.distorted_camera,
            brighton.undistorted_camera,
        );
        let config = RegistrationConfig::default();
        let loader = FrameLoader::default();
        let mut workspace = ReprojectionWorkspace::new();
        for image in brighton_priors(&brighton.data, &NAMES) {
            let frame = |folder: &str, camera: Camera| brighton.frame(&image, folder, camera);
            let frame_d = frame("images_distorted", distorted_camera);
            let frame_u = frame("images_undistorted", undistorted_camera);
            let distorted = register_batch_frame_with(mesh, &frame_d, &loader, &config, 1);
            let undistorted = register_batch_frame_with(mesh, &frame_u, &loader, &config, 1);
            let files_d = frame_d.load_with(&loader).unwrap();
            let files_u = frame_u.load_with(&loader).unwrap();
            assert_eq!(files_d.camera, files_u.camera, "one working camera");
            let (Some(distorted_pose), Some(undistorted_pose)) =
                (output_pose(&distorted), output_pose(&undistorted))
            else {
                panic!(
                    "{}: no pose: distorted {:?}, undistorted {:?}",
                    image.name, distorted.reason, undistorted.reason
                );
            };
            if distorted.accepted {
                // The output keeps the photo's camera.
                assert_eq!(distorted.camera, Some(distorted_camera));
            }
            let truth = brighton.truth_of(&image.name);
            let mut delta_px = |a: &Rigid3, b: &Rigid3| brighton.delta_px(a, b, &mut workspace);
            let between_px = delta_px(&distorted_pose, &undistorted_pose);
            eprintln!(
                "{}: accepted distorted {} ({:.3}), undistorted {} ({:.3}); δ(distorted, undistorted) {between_px:.2} px; to the truth {:.2} / {:.2} px",
                image.name,
                distorted.accepted,
                distorted.confidence,
                undistorted.accepted,
                undistorted.confidence,
                delta_px(&distorted_pose, &truth),
                delta_px(&undistorted_pose, &truth),
            );
            let mut spread_px: f64 = 0.0;
            for (label, photo) in faint_perturbations(&files_u.photo) {
                let input = FrameInput {
                    photo: photo.view(),
                    ..frame_u.input(&files_u, 1)
                };
                let result = register_frame(mesh, &input, &config).unwrap();
                let pose = result.verdict.chosen().unwrap().cam_from_world;
                let moved_px = delta_px(&pose, &undistorted_pose);
                eprintln!(
                    "  undistorted photo, {label}: the pose moves {moved_px:.2} px (confidence {:.3})",
                    result.verdict.confidence
                );
                spread_px = spread_px.max(moved_px);
            }
            assert!(
                between_px <= spread_px,
                "{}: δ(distorted, undistorted) {between_px} px, beyond the pose's own spread {spread_px} px",
                image.name
            );
        }
    }
}
