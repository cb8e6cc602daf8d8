//! Stage "flow": one FlowJob (a frame's query and one coarse view) becomes that coarse pose's
//! 2D–3D correspondences: SIFT flow both ways, consistent pairs, lifted onto the mesh. This is the
//! expensive stage that runs as N workers.

use std::borrow::Cow;
use std::time::Instant;

use crate::core::flow_consistency::{
    match_query_to_rendering, DenseCorrespondence, DenseCorrespondenceWorkspace, GreyImage,
};
use crate::core::mesh::Mesh;
use crate::core::register::{lift_correspondences, RegistrationConfig, ViewGeometry};
use crate::msg::{Correspondences, CorrespondencesMeta, FlowJob};

use super::elapsed_ms;

pub struct FlowStage<'m> {
    mesh: &'m Mesh,
    config: RegistrationConfig,
    worker_index: u32,
    workspace: DenseCorrespondenceWorkspace,
    dense: DenseCorrespondence,
}

impl<'m> FlowStage<'m> {
    pub fn new(mesh: &'m Mesh, config: RegistrationConfig, worker_index: u32) -> Self {
        Self {
            mesh,
            config,
            worker_index,
            workspace: DenseCorrespondenceWorkspace::default(),
            dense: DenseCorrespondence::default(),
        }
    }

    /// The job's correspondences; a flow error leaves them empty (the pose stage then reports
    /// too few correspondences for this coarse pose), with the error logged.
    pub fn process(&mut self, job: &FlowJob) -> Correspondences<'static> {
        let started = Instant::now();
        let meta = &job.meta;
        let (width_px, height_px) = (
            meta.info.camera.width_px as usize,
            meta.info.camera.height_px as usize,
        );
        let grey = |pixels| GreyImage {
            width_px,
            height_px,
            pixels,
        };
        let mut image_points_px = Vec::new();
        let mut world_points_m = Vec::new();
        let mut matching_costs = Vec::new();
        // As in one-process registration (core::register::match_views), no validity mask.
        match match_query_to_rendering(
            grey(&job.query),
            grey(&job.asg),
            None,
            &self.config.correspondence,
            &mut self.workspace,
            &mut self.dense,
        ) {
            Ok(()) => {
                let geometry = ViewGeometry {
                    coarse_index: meta.coarse_index as usize,
                    cam_from_world: meta.coarse_cam_from_world,
                    width_px,
                    height_px,
                    depth_m: &job.depth_m,
                    face_index: &job.face_index,
                };
                let lifted =
                    lift_correspondences(self.mesh, &meta.info.camera, geometry, &self.dense);
                image_points_px.reserve(2 * lifted.image_points_px.len());
                for point in &lifted.image_points_px {
                    image_points_px.extend_from_slice(&[point.x, point.y]);
                }
                world_points_m.reserve(3 * lifted.world_points.len());
                for point in &lifted.world_points {
                    world_points_m.extend_from_slice(&[point.x, point.y, point.z]);
                }
                matching_costs = lifted.matching_costs;
            }
            Err(error) => tracing::warn!(
                "frame '{}' coarse pose {}: SIFT flow failed: {error}",
                meta.info.name,
                meta.coarse_index
            ),
        }
        Correspondences {
            meta: CorrespondencesMeta {
                info: meta.info.clone(),
                coarse_index: meta.coarse_index,
                coarse_count: meta.coarse_count,
                coarse_cam_from_world: meta.coarse_cam_from_world,
                render_ms: meta.render_ms,
                flow_ms: elapsed_ms(started),
                flow_worker: self.worker_index,
            },
            image_points_px: Cow::Owned(image_points_px),
            world_points_m: Cow::Owned(world_points_m),
            matching_costs: Cow::Owned(matching_costs),
        }
    }
}
