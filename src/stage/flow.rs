//! Stage "flow": one FlowJob (a frame's query and one coarse view) becomes that coarse pose's
//! 2D–3D correspondences by the frame sequence's match and lift steps (`core::frame`). This is
//! the expensive stage that runs as N workers; each keeps the query features of its latest
//! frames, so a frame's query is described once per worker, not once per job.

use std::time::Instant;

use crate::core::flow_consistency::QueryFeatures;
use crate::core::frame::{
    coarse_view_samples, correspond_view, query_features, CorrespondWorkspace, RegistrationConfig,
    RegistrationError, ViewCorrespondences,
};
use crate::core::mesh::Mesh;
use crate::msg::{Correspondences, CorrespondencesMeta, FlowJob};

use super::elapsed_ms;
use super::simulate::{spend_ms, SimulatedWork};

/// Query features kept per worker: a worker takes jobs of at most a few frames at a time.
const CACHED_FRAMES: usize = 2;

pub struct FlowStage<'m> {
    mesh: &'m Mesh,
    config: RegistrationConfig,
    worker_index: u32,
    workspace: CorrespondWorkspace,
    /// (frame id, its query features), most recent last.
    features: Vec<(u64, QueryFeatures)>,
    /// Jobs whose frame's features were already here.
    pub feature_cache_hits: u64,
    /// `bench pipeline --simulate`: sleep per job instead of computing (no correspondences).
    simulated: Option<SimulatedWork>,
}

impl<'m> FlowStage<'m> {
    pub fn new(mesh: &'m Mesh, config: RegistrationConfig, worker_index: u32) -> Self {
        Self {
            mesh,
            config,
            worker_index,
            workspace: CorrespondWorkspace::default(),
            features: Vec::with_capacity(CACHED_FRAMES),
            feature_cache_hits: 0,
            simulated: None,
        }
    }

    /// Sleeps the given time per job instead of matching (the job's correspondences are empty).
    pub fn with_simulated_work(mut self, work: Option<SimulatedWork>) -> Self {
        self.simulated = work;
        self
    }

    /// The job's correspondences; a flow error leaves them empty (the pose stage then reports
    /// too few correspondences for this coarse pose), with the error logged. With them go the
    /// view's grid samples (`core::frame::coarse_view_samples`), which verify's convergence test
    /// reads instead of rendering the coarse pose again.
    pub fn process(&mut self, frame_id: u64, job: &FlowJob) -> Correspondences<'static> {
        let started = Instant::now();
        let meta = &job.meta;
        let grid = job
            .view()
            .ok()
            .and_then(|view| coarse_view_samples(&view, &self.config));
        let correspondences = self.correspond(frame_id, job).unwrap_or_else(|error| {
            tracing::warn!(
                "frame '{}' coarse pose {}: {error}",
                meta.info.name,
                meta.coarse_index
            );
            ViewCorrespondences {
                coarse_index: meta.coarse_index as usize,
                coarse_cam_from_world: meta.coarse_cam_from_world,
                ..ViewCorrespondences::default()
            }
        });
        Correspondences::from_view(
            CorrespondencesMeta {
                info: meta.info.clone(),
                coarse_index: meta.coarse_index,
                coarse_count: meta.coarse_count,
                coarse_cam_from_world: meta.coarse_cam_from_world,
                render_ms: meta.render_ms,
                flow_ms: elapsed_ms(started),
                flow_worker: self.worker_index,
                grid_stride_px: 0,
            },
            &correspondences,
            grid,
        )
    }

    fn correspond(
        &mut self,
        frame_id: u64,
        job: &FlowJob,
    ) -> Result<ViewCorrespondences, RegistrationError> {
        if let Some(work) = self.simulated {
            spend_ms(work.flow_job_ms);
            return Ok(ViewCorrespondences {
                coarse_index: job.meta.coarse_index as usize,
                coarse_cam_from_world: job.meta.coarse_cam_from_world,
                ..ViewCorrespondences::default()
            });
        }
        let view = job.view()?;
        let position = match self.features.iter().position(|(id, _)| *id == frame_id) {
            Some(position) => {
                self.feature_cache_hits += 1;
                position
            }
            None => {
                let features = query_features(job.query_image()?, &self.config)?;
                if self.features.len() == CACHED_FRAMES {
                    self.features.remove(0);
                }
                self.features.push((frame_id, features));
                self.features.len() - 1
            }
        };
        correspond_view(
            self.mesh,
            &job.meta.info.camera,
            &self.features[position].1,
            &view,
            &self.config,
            &mut self.workspace,
        )
    }
}
