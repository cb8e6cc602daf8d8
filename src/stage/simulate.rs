//! Simulated work for `asgreg bench pipeline --simulate`: each stage adapter, given a
//! `SimulatedWork`, sleeps a measured time per job instead of computing, so that the real loops,
//! dispatchers and transports can be driven by 1…64 flow workers on a machine with two cores.
//! The stages stay the same adapters (render still emits one flow job per coarse view, verify
//! still gathers and decides each frame); only the compute step is replaced by the sleep.

use std::time::Duration;

use serde::{Deserialize, Serialize};

/// Per-job compute times a simulated pipeline sleeps. The defaults are the p50 stage times of a
/// real `asgreg bench pipeline --backends iceoryx2 --flow-workers 2` run at 505×275, 15 coarse
/// poses, on the 2-core development machine under load (docs/measurements.md, "Simulated
/// scaling"): render 5.6 s per frame (its pose search included) over 15 views.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimulatedWork {
    /// Render time per coarse view, ms (the query's own step is computed for real).
    pub render_view_ms: f64,
    /// Coarse views per frame render emits.
    pub coarse_views: u32,
    /// Flow time per (frame, coarse pose) job, ms.
    pub flow_job_ms: f64,
    /// Pose time per coarse pose, ms.
    pub pose_job_ms: f64,
    /// Verify's decision (plausibility check, final refinement) per frame, ms.
    pub verify_frame_ms: f64,
}

impl Default for SimulatedWork {
    fn default() -> Self {
        Self {
            render_view_ms: 373.0,
            coarse_views: 15,
            flow_job_ms: 953.0,
            pose_job_ms: 75.0,
            verify_frame_ms: 2867.0,
        }
    }
}

impl SimulatedWork {
    /// Every time multiplied by `factor` (shorter runs; the ratios between stages are kept).
    pub fn scaled(self, factor: f64) -> Self {
        Self {
            render_view_ms: self.render_view_ms * factor,
            flow_job_ms: self.flow_job_ms * factor,
            pose_job_ms: self.pose_job_ms * factor,
            verify_frame_ms: self.verify_frame_ms * factor,
            ..self
        }
    }
}

/// Sleeps `ms` milliseconds (the simulated compute of one job).
pub fn spend_ms(ms: f64) {
    if ms > 0.0 {
        std::thread::sleep(Duration::from_secs_f64(ms / 1e3));
    }
}
