//! Stage "render": a Frame becomes one FlowJob per coarse pose: the photo's query gradient and
//! the ASG rendering, depth and face index of each coarse pose around the initial pose.

use std::borrow::Cow;
use std::time::Instant;

use crate::core::flow_consistency::GreyImage;
use crate::core::mesh::Mesh;
use crate::core::raster::Rasterizer;
use crate::core::register::{
    coarse_poses, median_scene_depth_m, query_gradient, render_coarse_view, CoarseView, FrameInput,
    RegistrationConfig,
};
use crate::msg::{FlowJob, FlowJobMeta, Frame, FrameFailed};

use super::{elapsed_ms, frame_config};

pub struct RenderStage<'m> {
    mesh: &'m Mesh,
    config: RegistrationConfig,
    rasterizer: Rasterizer,
    view: CoarseView,
}

impl<'m> RenderStage<'m> {
    pub fn new(mesh: &'m Mesh, config: RegistrationConfig) -> Self {
        Self {
            mesh,
            config,
            rasterizer: Rasterizer::new(),
            view: CoarseView::default(),
        }
    }

    /// Renders the frame's coarse views and hands each flow job, in coarse-pose order, to
    /// `emit`; the job borrows the stage's buffers (the caller encodes it straight away, so no
    /// image is copied twice). Returns the number of jobs, or why the frame cannot be registered.
    /// A job's `render_ms` is the frame's render time up to and including that view.
    pub fn process(
        &mut self,
        frame: &Frame,
        emit: &mut dyn FnMut(FlowJob<'_>),
    ) -> Result<usize, FrameFailed> {
        let started = Instant::now();
        let info = &frame.info;
        let failed = |reason: String| FrameFailed {
            name: info.name.clone(),
            stage: "render".to_string(),
            reason,
        };
        if !info.initial_cam_from_world.is_finite() {
            return Err(failed(
                "the initial pose is not finite (NaN or infinity)".to_string(),
            ));
        }
        let config = frame_config(&self.config, info);
        let (width_px, height_px) = (
            info.camera.width_px as usize,
            info.camera.height_px as usize,
        );
        let input = FrameInput {
            photo: GreyImage {
                width_px,
                height_px,
                pixels: &frame.image,
            },
            depth_m: (!frame.depth_m.is_empty()).then_some(GreyImage {
                width_px,
                height_px,
                pixels: &frame.depth_m,
            }),
            camera: &info.camera,
            initial_cam_from_world: info.initial_cam_from_world,
            seed: info.seed,
        };
        let query = query_gradient(&input, &config).map_err(|e| failed(e.to_string()))?;
        // The initial pose's view gives the scene depth that scales the other coarse poses.
        render_coarse_view(
            self.mesh,
            &info.camera,
            0,
            &info.initial_cam_from_world,
            &config,
            &mut self.rasterizer,
            &mut self.view,
        );
        let median_depth_m = median_scene_depth_m(&self.view.render).ok_or_else(|| {
            failed("the model is not visible from the initial pose (check the pose and the mesh's coordinate frame)".to_string())
        })?;
        let poses = coarse_poses(
            &info.initial_cam_from_world,
            median_depth_m,
            &config,
            info.seed,
        );
        for (coarse_index, pose) in poses.iter().enumerate() {
            if coarse_index > 0 {
                render_coarse_view(
                    self.mesh,
                    &info.camera,
                    coarse_index,
                    pose,
                    &config,
                    &mut self.rasterizer,
                    &mut self.view,
                );
            }
            emit(FlowJob {
                meta: FlowJobMeta {
                    info: info.clone(),
                    coarse_index: coarse_index as u32,
                    coarse_count: poses.len() as u32,
                    coarse_cam_from_world: *pose,
                    render_ms: elapsed_ms(started),
                },
                query: Cow::Borrowed(&query.pixels),
                asg: Cow::Borrowed(&self.view.asg),
                depth_m: Cow::Borrowed(&self.view.render.depth_m),
                face_index: Cow::Borrowed(&self.view.render.face_index),
            });
        }
        Ok(poses.len())
    }
}
