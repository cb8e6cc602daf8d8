//! Stage "change": an accepted frame's ChangeJob (registered camera and pose, the photo's depth
//! map, or without one the photo and its candidate stereo neighbours) becomes its ChangeResult
//! by the change detection of one frame (`core::change::detect_changes`, the same function
//! `asgreg changes` calls). Runs as N workers, dispatched like flow. [`photo_depth`] is the one
//! place that decides where a frame's depth comes from; it also chooses the stereo neighbours
//! among the candidates verify sent (`core::change::stereo::choose_neighbours`, as `asgreg
//! changes` does), because ranking them by their agreement with the model sweeps each one: work
//! that scales with the change workers instead of holding up verify's poses.

use std::borrow::Cow;
use std::time::Instant;

use crate::core::change::stereo::{
    choose_neighbours, depth_from_neighbours, depth_from_prepared, NeighbourConfig, PosedCamera,
    PreparedReference, RankingPhotos, StereoConfig, StereoView,
};
use crate::core::change::{
    detect_changes, ChangeClass, ChangeConfig, ChangeWorkspace, DepthEvidence,
};
use crate::core::image::{Image, ImageView};
use crate::core::mesh::Mesh;
use crate::msg::{ChangeJob, ChangeResult, ChangeSight, ChangeSightMeta, SightView};

use super::elapsed_ms;

/// How the change stage computes the depth of a frame without a given depth map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StereoDepthSettings {
    /// How the neighbours are chosen among the candidates that come with the job.
    pub neighbours: NeighbourConfig,
    pub sweep: StereoConfig,
    /// Disparity error of the stereo depth, working pixels (the threshold's stereo term).
    pub disparity_sigma_px: f64,
}

/// A frame's depth map for its change map: the given one, or computed by stereo.
pub enum PhotoDepth<'j> {
    Given(ImageView<'j, f32>),
    /// Plane-sweep stereo from the job's neighbours, with the threshold's stereo term
    /// σ_quad (per metre) of this frame's baseline.
    Stereo {
        depth_m: Image<f32>,
        /// Where the sweep finds the model's depth as plausible as the photo's (no change).
        model_plausible: Image<bool>,
        quadratic_sigma_per_m: f64,
    },
}

/// The depth map a frame's change map compares with the model: the given one (MVS, as
/// `asgreg changes --depth`) when the frame carries it; otherwise plane-sweep stereo
/// (`core::change::stereo::depth_from_neighbours`, as `asgreg changes` without `--depth`) of the
/// frame's photo against the neighbours chosen (`choose_neighbours`, ranked when
/// `stereo.neighbours` asks for it) among the registered candidates verify sent with it.
pub fn photo_depth<'j>(
    mesh: &Mesh,
    job: &'j ChangeJob,
    stereo: &StereoDepthSettings,
) -> Result<PhotoDepth<'j>, String> {
    match job.depth() {
        Ok(Some(depth)) => return Ok(PhotoDepth::Given(depth)),
        Ok(None) => {}
        Err(error) => return Err(format!("depth map unusable: {error}")),
    }
    let photo = match job.photo() {
        Ok(Some(photo)) => photo,
        Ok(None) => return Err(NO_DEPTH.to_string()),
        Err(error) => return Err(format!("photo unusable: {error}")),
    };
    let neighbours = job
        .neighbours()
        .map_err(|error| format!("neighbour photo unusable: {error}"))?;
    if neighbours.is_empty() {
        return Err(format!(
            "{NO_DEPTH}; no registered neighbour came with the frame"
        ));
    }
    let reference = StereoView {
        photo,
        intrinsics: job.meta.camera.intrinsics,
        cam_from_world: job.meta.cam_from_world,
    };
    let posed = |intrinsics, photo: &ImageView<'_, f32>, cam_from_world| PosedCamera {
        intrinsics,
        width_px: photo.width_px(),
        height_px: photo.height_px(),
        cam_from_world,
    };
    let candidates: Vec<PosedCamera> = neighbours
        .iter()
        .map(|(meta, photo)| posed(meta.camera.intrinsics, photo, meta.cam_from_world))
        .collect();
    // Prepared once: for the ranking's sweep of every candidate and the final sweep. When it
    // cannot be, `depth_from_neighbours` below meets (and reports) the same reason.
    let prepared = PreparedReference::new(mesh, &reference, &stereo.sweep).ok();
    let photos = RankingPhotos {
        reference: photo,
        candidates: neighbours.iter().map(|(_, photo)| Some(*photo)).collect(),
        sweep: stereo.sweep,
        prepared: prepared.as_ref(),
    };
    let choice = choose_neighbours(
        mesh,
        &posed(job.meta.camera.intrinsics, &photo, job.meta.cam_from_world),
        &candidates,
        &stereo.neighbours,
        Some(&photos),
    )
    .map_err(|error| {
        format!(
            "no depth: the source has no depth map for this frame and stereo chose no neighbour among the {} candidates sent: {error}",
            candidates.len()
        )
    })?;
    let views: Vec<StereoView<'_>> = choice
        .chosen
        .iter()
        .map(|&k| {
            let (meta, photo) = &neighbours[k];
            StereoView {
                photo: *photo,
                intrinsics: meta.camera.intrinsics,
                cam_from_world: meta.cam_from_world,
            }
        })
        .collect();
    let depth = match &prepared {
        Some(prepared) => depth_from_prepared(mesh, prepared, &views, &stereo.sweep),
        None => depth_from_neighbours(mesh, &reference, &views, &stereo.sweep),
    }
    .map_err(|error| format!("stereo depth: {error}"))?;
    Ok(PhotoDepth::Stereo {
        quadratic_sigma_per_m: depth.quadratic_sigma_per_m(stereo.disparity_sigma_px),
        depth_m: depth.depth_m,
        model_plausible: depth.model_plausible,
    })
}

/// Why a frame has no change map although it was registered.
pub const NO_DEPTH: &str = "no depth: the source has no depth map for this frame (set source.depth to a folder of <image stem>.pfm) and no photo came for stereo";

pub struct ChangeStage<'m> {
    mesh: &'m Mesh,
    config: ChangeConfig,
    stereo: StereoDepthSettings,
    worker_index: u32,
    workspace: ChangeWorkspace,
    classes: Image<ChangeClass>,
}

impl<'m> ChangeStage<'m> {
    pub fn new(
        mesh: &'m Mesh,
        config: ChangeConfig,
        stereo: StereoDepthSettings,
        worker_index: u32,
    ) -> Self {
        Self {
            mesh,
            config,
            stereo,
            worker_index,
            workspace: ChangeWorkspace::new(),
            classes: Image::default(),
        }
    }

    /// The frame's change result with what the frame saw (for fusion's free-space test); a
    /// frame without usable depth gets one saying why, and no sight.
    pub fn process(&mut self, frame_id: u64, job: &ChangeJob) -> ChangeSight<'static> {
        let started = Instant::now();
        let meta = &job.meta;
        // The frame's own pose error (verify's measure of its registration) for the threshold.
        let frame_config = ChangeConfig {
            pose_sigma_px: meta.pose_sigma_px as f32,
            ..self.config
        };
        let detected = photo_depth(self.mesh, job, &self.stereo).and_then(|depth| {
            let (depth, evidence, config) = match &depth {
                PhotoDepth::Given(depth) => (*depth, DepthEvidence::default(), frame_config),
                PhotoDepth::Stereo {
                    depth_m,
                    model_plausible,
                    quadratic_sigma_per_m,
                } => (
                    depth_m.view(),
                    DepthEvidence {
                        model_plausible: Some(model_plausible.view()),
                    },
                    frame_config.for_stereo(*quadratic_sigma_per_m as f32),
                ),
            };
            let changes = detect_changes(
                self.mesh,
                &meta.camera.intrinsics,
                &meta.cam_from_world,
                depth,
                &evidence,
                &config,
                &mut self.workspace,
                &mut self.classes,
            )
            .map_err(|error| error.to_string())?;
            let settings = changes.settings(&config);
            Ok((changes, depth.data().to_vec(), settings))
        });
        let mut sight = ChangeSight {
            meta: ChangeSightMeta {
                result: ChangeResult {
                    frame_id,
                    name: meta.info.name.clone(),
                    failure: None,
                    counts: Default::default(),
                    regions: Vec::new(),
                    change_ms: 0.0,
                    change_worker: Some(self.worker_index),
                },
                view: None,
            },
            photo_depth_m: Cow::Owned(Vec::new()),
            model_depth_m: Cow::Owned(Vec::new()),
        };
        match detected {
            Ok((changes, photo_depth_m, config)) => {
                let result = &mut sight.meta.result;
                result.counts = changes.counts;
                result.regions = changes.regions;
                sight.meta.view = Some(SightView {
                    camera: meta.camera,
                    cam_from_world: meta.cam_from_world,
                    config,
                });
                sight.photo_depth_m = Cow::Owned(photo_depth_m);
                sight.model_depth_m =
                    Cow::Owned(self.workspace.model_rendering().depth_m().data().to_vec());
            }
            Err(why) => sight.meta.result.failure = Some(why),
        }
        sight.meta.result.change_ms = elapsed_ms(started);
        sight
    }
}

/// The change result of a frame that has no pose: why there is no change map.
pub fn not_registered(frame_id: u64, name: &str, failure: Option<&str>) -> ChangeResult {
    ChangeResult {
        frame_id,
        name: name.to_string(),
        failure: Some(format!(
            "not registered: {}",
            failure.unwrap_or("the pose was rejected")
        )),
        counts: Default::default(),
        regions: Vec::new(),
        change_ms: 0.0,
        change_worker: None,
    }
}
