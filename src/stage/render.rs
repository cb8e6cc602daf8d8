//! Stage "render": a Frame becomes its FrameQuery (the query gradient, for verify's final
//! refinement, and with change detection the frame's depth map, or without one its grey photo
//! for stereo, which verify hands on) and one FlowJob per coarse pose (the query gradient and the ASG rendering, depth
//! and face index of the view), by the frame sequence's own query, plan and render steps
//! (`core::frame`).

use std::borrow::Cow;
use std::time::Instant;

use crate::core::frame::{
    query_gradient, render_views, CoarseView, FrameInput, IntrinsicsMode, RegistrationConfig,
};
use crate::core::mesh::Mesh;
use crate::core::raster::Rasterizer;
use crate::msg::{FlowJob, FlowJobMeta, Frame, FrameFailed, FrameQuery};

use super::elapsed_ms;
use super::simulate::{spend_ms, SimulatedWork};

pub struct RenderStage<'m> {
    mesh: &'m Mesh,
    config: RegistrationConfig,
    rasterizer: Rasterizer,
    view: CoarseView,
    /// Whether the frame's depth map goes to verify with the query (for the change stage).
    forward_depth: bool,
    /// `bench pipeline --simulate`: sleep per view instead of rendering.
    simulated: Option<SimulatedWork>,
}

impl<'m> RenderStage<'m> {
    pub fn new(mesh: &'m Mesh, config: RegistrationConfig) -> Self {
        Self {
            mesh,
            config,
            rasterizer: Rasterizer::new(),
            view: CoarseView::default(),
            forward_depth: false,
            simulated: None,
        }
    }

    /// Sleeps the given time per coarse view instead of rendering it (empty renderings of the
    /// photo's size are sent, so the messages keep their size).
    pub fn with_simulated_work(mut self, work: Option<SimulatedWork>) -> Self {
        self.simulated = work;
        self
    }

    /// Sends each frame's depth map to verify with its query (the change stage runs).
    pub fn with_depth_forwarding(mut self) -> Self {
        self.forward_depth = true;
        self
    }

    /// Hands the frame's query to `emit_query`, then renders the frame's coarse views and hands
    /// each flow job, in coarse-pose order, to `emit`; both borrow the stage's buffers (the
    /// caller encodes them straight away, so no image is copied twice). Returns the number of
    /// jobs, or why the frame cannot be registered. A job's `render_ms` is the frame's render
    /// time up to and including that view.
    pub fn process(
        &mut self,
        frame: &Frame,
        emit_query: &mut dyn FnMut(FrameQuery<'_>),
        emit: &mut dyn FnMut(FlowJob<'_>),
    ) -> Result<usize, FrameFailed> {
        let started = Instant::now();
        let info = &frame.info;
        let failed = |reason: String| FrameFailed {
            name: info.name.clone(),
            stage: "render".to_string(),
            reason,
        };
        let input = FrameInput {
            photo: frame.photo().map_err(|e| failed(format!("photo: {e}")))?,
            depth_m: frame
                .depth()
                .map_err(|e| failed(format!("depth map: {e}")))?,
            camera: &info.camera,
            intrinsics: IntrinsicsMode::from_known(info.intrinsics_known),
            initial_cam_from_world: info.initial_cam_from_world,
            seed: info.seed,
        };
        let query = query_gradient(&input, &self.config).map_err(|e| failed(e.to_string()))?;
        emit_query(FrameQuery {
            info: info.clone(),
            query: Cow::Borrowed(query.data()),
            depth_m: if self.forward_depth {
                Cow::Borrowed(&frame.depth_m[..])
            } else {
                Cow::Borrowed(&[])
            },
            // Without a depth map the change stage computes it by stereo from the photo.
            photo: if self.forward_depth && frame.depth_m.is_empty() {
                Cow::Borrowed(&frame.image[..])
            } else {
                Cow::Borrowed(&[])
            },
        });
        if let Some(work) = self.simulated {
            let pixels = query.data().len();
            let zeros = vec![0.0f32; pixels];
            let no_face = vec![u32::MAX; pixels];
            for coarse_index in 0..work.coarse_views {
                spend_ms(work.render_view_ms);
                emit(FlowJob {
                    meta: FlowJobMeta {
                        info: info.clone(),
                        coarse_index,
                        coarse_count: work.coarse_views,
                        coarse_cam_from_world: info.initial_cam_from_world,
                        render_ms: elapsed_ms(started),
                    },
                    query: Cow::Borrowed(query.data()),
                    asg: Cow::Borrowed(&zeros),
                    depth_m: Cow::Borrowed(&zeros),
                    face_index: Cow::Borrowed(&no_face),
                });
            }
            return Ok(work.coarse_views as usize);
        }
        render_views(
            self.mesh,
            &info.camera,
            &info.initial_cam_from_world,
            query.view(),
            &self.config,
            info.seed,
            &mut self.rasterizer,
            &mut self.view,
            &mut |view, coarse_count| {
                emit(FlowJob {
                    meta: FlowJobMeta {
                        info: info.clone(),
                        coarse_index: view.coarse_index as u32,
                        coarse_count: coarse_count as u32,
                        coarse_cam_from_world: view.cam_from_world,
                        render_ms: elapsed_ms(started),
                    },
                    query: Cow::Borrowed(query.data()),
                    asg: Cow::Borrowed(view.asg.data()),
                    depth_m: Cow::Borrowed(view.render.depth_m().data()),
                    face_index: Cow::Borrowed(view.render.face_index().data()),
                })
            },
        )
        .map(|rendered| rendered.count)
        .map_err(|e| failed(e.to_string()))
    }
}
