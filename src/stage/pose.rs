//! Stage "pose": one coarse pose's correspondences become a refined pose hypothesis, or the
//! reason there is none, by the frame sequence's solve step (`core::frame::solve_view`).

use std::time::Instant;

use crate::core::frame::{solve_view, IntrinsicsMode, RegistrationConfig};
use crate::msg::{Correspondences, GridArrays, Hypothesis, HypothesisMeta};

use super::elapsed_ms;
use super::simulate::{spend_ms, SimulatedWork};

pub struct PoseStage {
    config: RegistrationConfig,
    /// `bench pipeline --simulate`: sleep per job before solving (the simulated
    /// correspondences are empty, so the solve itself fails at once).
    simulated: Option<SimulatedWork>,
}

impl PoseStage {
    pub fn new(config: RegistrationConfig) -> Self {
        Self {
            config,
            simulated: None,
        }
    }

    /// Sleeps the given time per coarse pose (simulated pipeline).
    pub fn with_simulated_work(mut self, work: Option<SimulatedWork>) -> Self {
        self.simulated = work;
        self
    }

    /// The coarse pose's hypothesis; the view's grid samples go on with it to verify when it
    /// has a pose (the convergence test reads only those; in a simulated run always, so that
    /// the messages keep their size).
    pub fn process<'a>(&mut self, set: &Correspondences<'a>) -> Hypothesis<'a> {
        let started = Instant::now();
        let meta = &set.meta;
        if let Some(work) = self.simulated {
            spend_ms(work.pose_job_ms);
        }
        let outcome = solve_view(
            &set.to_view(),
            &meta.info.camera,
            IntrinsicsMode::from_known(meta.info.intrinsics_known),
            &self.config,
            meta.info.seed,
        );
        let (grid_stride_px, grid) = if outcome.hypothesis.is_ok() || self.simulated.is_some() {
            (meta.grid_stride_px, set.grid.clone())
        } else {
            (0, GridArrays::default())
        };
        Hypothesis {
            meta: HypothesisMeta {
                info: meta.info.clone(),
                coarse_count: meta.coarse_count,
                outcome,
                render_ms: meta.render_ms,
                flow_ms: meta.flow_ms,
                pose_ms: elapsed_ms(started),
                flow_worker: meta.flow_worker,
                grid_stride_px,
            },
            grid,
        }
    }
}
