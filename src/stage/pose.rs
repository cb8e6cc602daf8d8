//! Stage "pose": one coarse pose's correspondences become a refined pose hypothesis (RANSAC with
//! EPnP or DLT, then Levenberg–Marquardt), or the reason there is none.

use std::time::Instant;

use nalgebra::{Vector2, Vector3};

use crate::core::register::{
    solve_coarse_pose, CoarseOutcome, Correspondences2d3d, RegistrationConfig,
};
use crate::msg::{Correspondences, Hypothesis};

use super::{elapsed_ms, frame_config};

pub struct PoseStage {
    config: RegistrationConfig,
}

impl PoseStage {
    pub fn new(config: RegistrationConfig) -> Self {
        Self { config }
    }

    pub fn process(&mut self, set: &Correspondences) -> Hypothesis {
        let started = Instant::now();
        let meta = &set.meta;
        let config = frame_config(&self.config, &meta.info);
        let lifted = Correspondences2d3d {
            coarse_index: meta.coarse_index as usize,
            coarse_cam_from_world: meta.coarse_cam_from_world,
            image_points_px: set
                .image_points_px
                .chunks_exact(2)
                .map(|p| Vector2::new(p[0], p[1]))
                .collect(),
            world_points: set
                .world_points_m
                .chunks_exact(3)
                .map(|p| Vector3::new(p[0], p[1], p[2]))
                .collect(),
            matching_costs: set.matching_costs.to_vec(),
        };
        let consistent_matches = lifted.image_points_px.len();
        let outcome = match solve_coarse_pose(&lifted, &meta.info.camera, &config, meta.info.seed) {
            Ok((hypothesis, _)) => CoarseOutcome {
                coarse_index: lifted.coarse_index,
                consistent_matches,
                hypothesis: Some(hypothesis),
                failure: None,
            },
            Err(error) => CoarseOutcome {
                coarse_index: lifted.coarse_index,
                consistent_matches,
                hypothesis: None,
                failure: Some(error.to_string()),
            },
        };
        Hypothesis {
            info: meta.info.clone(),
            coarse_count: meta.coarse_count,
            outcome,
            render_ms: meta.render_ms,
            flow_ms: meta.flow_ms,
            pose_ms: elapsed_ms(started),
            flow_worker: meta.flow_worker,
        }
    }
}
