//! The message bodies: what each stage sends to the next (docs/design.md §5 data flow
//! frame → render → flow → pose → verify → pose result) plus control messages (credits,
//! metrics, end of stream).

use std::borrow::Cow;

use serde::{Deserialize, Serialize};

use crate::core::camera::Camera;
use crate::core::change::free_space::FreeSpaceCheck;
use crate::core::change::fusion::{FusedChange, FusionConfig};
use crate::core::change::{ChangeConfig, ChangeRegion, ClassCounts};
use nalgebra::{Vector2, Vector3};

use crate::core::frame::{CoarseOutcome, ViewCorrespondences, ViewRef};
use crate::core::image::{ImageError, ImageView};
use crate::core::reprojection::GridSamples;
use crate::core::rigid::Rigid3;

/// Bulk data of a message: borrowed from the received bytes when possible, owned otherwise.
/// Per-pixel blobs are read as images through their message's accessors (`Frame::photo`,
/// `FlowJob::view`, ...), which check their length against the frame's camera.
pub type Blob<'a, T> = Cow<'a, [T]>;

/// The fixed header of every message.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct Header {
    pub frame_id: u64,
    pub sequence: u64,
    /// Unix time (ns) the frame was captured or ingested; carried unchanged through the stages.
    pub capture_time_ns: u64,
    /// Unix time (ns) this message was sent (set by the sender).
    pub sent_time_ns: u64,
}

/// Discriminant of a message body on the wire (header bytes 6..8).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u16)]
pub enum MessageKind {
    Frame = 1,
    FlowJob = 2,
    Correspondences = 3,
    Hypothesis = 4,
    FrameFailed = 5,
    PoseResult = 6,
    Credit = 7,
    Metrics = 8,
    StreamEnd = 9,
    FrameQuery = 10,
    ChangeJob = 11,
    ChangeResult = 12,
    ChangeSet = 13,
    ChangeSight = 14,
    PoseLender = 15,
}

impl MessageKind {
    pub fn from_wire(value: u16) -> Option<Self> {
        Some(match value {
            1 => Self::Frame,
            2 => Self::FlowJob,
            3 => Self::Correspondences,
            4 => Self::Hypothesis,
            5 => Self::FrameFailed,
            6 => Self::PoseResult,
            7 => Self::Credit,
            8 => Self::Metrics,
            9 => Self::StreamEnd,
            10 => Self::FrameQuery,
            11 => Self::ChangeJob,
            12 => Self::ChangeResult,
            13 => Self::ChangeSet,
            14 => Self::ChangeSight,
            15 => Self::PoseLender,
            _ => return None,
        })
    }
}

/// A message: header and body.
#[derive(Clone, Debug, PartialEq)]
pub struct Envelope<'a> {
    pub header: Header,
    pub body: Body<'a>,
}

/// Every message body of the schema.
#[derive(Clone, Debug, PartialEq)]
pub enum Body<'a> {
    Frame(Frame<'a>),
    FlowJob(FlowJob<'a>),
    Correspondences(Correspondences<'a>),
    Hypothesis(Hypothesis<'a>),
    FrameFailed(FrameFailed),
    PoseResult(PoseResult),
    Credit(Credit),
    Metrics(StageMetrics),
    StreamEnd(StreamEnd),
    FrameQuery(FrameQuery<'a>),
    ChangeJob(ChangeJob<'a>),
    ChangeResult(ChangeResult),
    ChangeSet(ChangeSet),
    ChangeSight(ChangeSight<'a>),
    PoseLender(PoseLender<'a>),
}

impl Body<'_> {
    pub fn kind(&self) -> MessageKind {
        match self {
            Body::Frame(_) => MessageKind::Frame,
            Body::FlowJob(_) => MessageKind::FlowJob,
            Body::Correspondences(_) => MessageKind::Correspondences,
            Body::Hypothesis(_) => MessageKind::Hypothesis,
            Body::FrameFailed(_) => MessageKind::FrameFailed,
            Body::PoseResult(_) => MessageKind::PoseResult,
            Body::Credit(_) => MessageKind::Credit,
            Body::Metrics(_) => MessageKind::Metrics,
            Body::StreamEnd(_) => MessageKind::StreamEnd,
            Body::FrameQuery(_) => MessageKind::FrameQuery,
            Body::ChangeJob(_) => MessageKind::ChangeJob,
            Body::ChangeResult(_) => MessageKind::ChangeResult,
            Body::ChangeSet(_) => MessageKind::ChangeSet,
            Body::ChangeSight(_) => MessageKind::ChangeSight,
            Body::PoseLender(_) => MessageKind::PoseLender,
        }
    }
}

/// What every per-frame message carries about its frame (small; repeated in each job so that any
/// worker can do any job without other state).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameInfo {
    /// The image name (as in images.txt).
    pub name: String,
    pub camera_id: u32,
    pub camera: Camera,
    /// True: intrinsics known (EPnP); false: estimate them (DLT).
    pub intrinsics_known: bool,
    pub initial_cam_from_world: Rigid3,
    /// Seed of the frame's random choices (coarse poses, RANSAC): same seed, same result.
    pub seed: u64,
}

impl FrameInfo {
    /// The frame's image size, `(width_px, height_px)`: the camera's.
    pub fn image_size(&self) -> (usize, usize) {
        (
            self.camera.width_px as usize,
            self.camera.height_px as usize,
        )
    }

    /// `data` as an image of the frame's size.
    fn image<'a, T>(&self, data: &'a [T]) -> Result<ImageView<'a, T>, ImageError> {
        let (width_px, height_px) = self.image_size();
        ImageView::new(width_px, height_px, data)
    }
}

/// A photo to register (ingest → render).
#[derive(Clone, Debug, PartialEq)]
pub struct Frame<'a> {
    pub info: FrameInfo,
    /// Grey photo, row-major, `camera.width_px × camera.height_px`, values 0..1.
    pub image: Blob<'a, f32>,
    /// The photo's depth map in metres (0 = hole), same size; empty when there is none.
    pub depth_m: Blob<'a, f32>,
}

impl Frame<'_> {
    /// The grey photo (0..1) as an image of the camera's size.
    pub fn photo(&self) -> Result<ImageView<'_, f32>, ImageError> {
        self.info.image(&self.image)
    }

    /// The photo's depth map (metres along the optical axis, 0 = hole) as an image of the
    /// camera's size; `None` when the frame carries none.
    pub fn depth(&self) -> Result<Option<ImageView<'_, f32>>, ImageError> {
        if self.depth_m.is_empty() {
            return Ok(None);
        }
        self.info.image(&self.depth_m).map(Some)
    }
}

/// A frame's query gradient image (render → verify): what the final refinement aligns the chosen
/// pose with; and the photo's depth map (or, without one, the grey photo for stereo), which
/// verify hands to the change stage with the pose.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameQuery<'a> {
    pub info: FrameInfo,
    /// The photo's gradient image (query), 0..1, `camera.width_px × camera.height_px`.
    pub query: Blob<'a, f32>,
    /// The photo's depth map in metres (0 = hole), same size; empty when the source has none.
    pub depth_m: Blob<'a, f32>,
    /// The grey photo (0..1), same size: sent only with change detection and no depth map (the
    /// change stage computes depth by stereo from it and its registered neighbours); else empty.
    pub photo: Blob<'a, f32>,
}

impl FrameQuery<'_> {
    /// The query as an image of the camera's size.
    pub fn query_image(&self) -> Result<ImageView<'_, f32>, ImageError> {
        self.info.image(&self.query)
    }

    /// The photo's depth map as an image of the camera's size; `None` when there is none.
    pub fn depth(&self) -> Result<Option<ImageView<'_, f32>>, ImageError> {
        if self.depth_m.is_empty() {
            return Ok(None);
        }
        self.info.image(&self.depth_m).map(Some)
    }

    /// The grey photo as an image of the camera's size; `None` when it was not sent.
    pub fn photo(&self) -> Result<Option<ImageView<'_, f32>>, ImageError> {
        if self.photo.is_empty() {
            return Ok(None);
        }
        self.info.image(&self.photo).map(Some)
    }
}

/// An accepted frame's change detection job (verify → change workers, dispatched): the
/// registered camera and pose and the photo's depth map; without a depth map, the grey photo
/// and its candidate stereo neighbours (registered frames of the stream; verify sends them, the
/// change worker chooses the neighbours among them) with theirs.
#[derive(Clone, Debug, PartialEq)]
pub struct ChangeJob<'a> {
    pub meta: ChangeJobMeta,
    /// The photo's depth map in metres (0 = hole), `camera.width_px × camera.height_px`; empty
    /// when the source has none (the change stage then computes it by stereo).
    pub depth_m: Blob<'a, f32>,
    /// Without a depth map: the grey photo (0..1), same size; else empty.
    pub photo: Blob<'a, f32>,
    /// The neighbours' grey photos one after the other (each of its camera's size, in the order
    /// of `meta.neighbours`); empty without neighbours.
    pub neighbour_photos: Blob<'a, f32>,
}

impl ChangeJob<'_> {
    /// The grey photo as an image of the registered camera's size; `None` when there is none.
    pub fn photo(&self) -> Result<Option<ImageView<'_, f32>>, ImageError> {
        if self.photo.is_empty() {
            return Ok(None);
        }
        let camera = &self.meta.camera;
        ImageView::new(
            camera.width_px as usize,
            camera.height_px as usize,
            &self.photo,
        )
        .map(Some)
    }

    /// Each neighbour with its photo, in the order of `meta.neighbours`.
    pub fn neighbours(&self) -> Result<Vec<(&NeighbourMeta, ImageView<'_, f32>)>, ImageError> {
        let mut offset = 0;
        let mut out = Vec::with_capacity(self.meta.neighbours.len());
        for neighbour in &self.meta.neighbours {
            let (w, h) = (
                neighbour.camera.width_px as usize,
                neighbour.camera.height_px as usize,
            );
            let end = (offset + w * h).min(self.neighbour_photos.len());
            out.push((
                neighbour,
                ImageView::new(w, h, &self.neighbour_photos[offset..end])?,
            ));
            offset = end;
        }
        Ok(out)
    }

    /// The photo's depth map as an image of the registered camera's size; `None` when there is
    /// none.
    pub fn depth(&self) -> Result<Option<ImageView<'_, f32>>, ImageError> {
        if self.depth_m.is_empty() {
            return Ok(None);
        }
        let camera = &self.meta.camera;
        ImageView::new(
            camera.width_px as usize,
            camera.height_px as usize,
            &self.depth_m,
        )
        .map(Some)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChangeJobMeta {
    pub info: FrameInfo,
    /// The registered camera (estimated intrinsics when they were unknown).
    pub camera: Camera,
    /// The registered pose (the frame's PoseResult).
    pub cam_from_world: Rigid3,
    /// Without a depth map: the registered frames whose photos come with the job for stereo, the
    /// candidates the change worker chooses the neighbours among
    /// (`core::change::stereo::neighbour_candidates`, nearest first).
    pub neighbours: Vec<NeighbourMeta>,
    /// The registered pose's error as an image displacement, px: the change threshold's pose
    /// term (`core::change::ChangeConfig::pose_sigma_px`), from the registration's own
    /// uncertainty (`core::change::pose_sigma_px_of_registration` of its verify group's spread).
    pub pose_sigma_px: f64,
}

/// An accepted frame verify keeps to lend its pose (step "neighbour"), written to verify's state
/// folder (`runtime::lenders`) so that a restarted verify still has it; never on the bus.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseLender<'a> {
    pub meta: PoseLenderMeta,
    /// The frame's query image (0..1, as render sent it in its FrameQuery), `info.camera`'s size.
    pub query: Blob<'a, f32>,
}

impl PoseLender<'_> {
    /// The query image of the frame's camera size.
    pub fn query(&self) -> Result<ImageView<'_, f32>, ImageError> {
        let camera = &self.meta.info.camera;
        ImageView::new(
            camera.width_px as usize,
            camera.height_px as usize,
            &self.query,
        )
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseLenderMeta {
    pub info: FrameInfo,
    /// The registered camera and pose (the frame's PoseResult).
    pub camera: Camera,
    pub cam_from_world: Rigid3,
    /// Neighbours away from a frame the model accepted on its own (0: it is one).
    pub steps: u32,
}

/// A registered frame of the stream sent with a change job as a candidate stereo neighbour.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NeighbourMeta {
    pub frame_id: u64,
    pub name: String,
    /// Its registered camera and pose.
    pub camera: Camera,
    pub cam_from_world: Rigid3,
}

/// One frame's change detection (verify for a frame without a pose, change workers inside a
/// [`ChangeSight`] → fusion → subscribers); also published as JSON
/// (`schemas/v9/change_result.schema.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChangeResult {
    pub frame_id: u64,
    pub name: String,
    /// Why there is no change map: the frame was not registered (its rejection), or it has no
    /// depth, or the depth map is unusable. `None`: `counts` and `regions` are the frame's.
    pub failure: Option<String>,
    /// Pixels per class (all zero when there is no change map).
    pub counts: ClassCounts,
    /// Changed regions in the model's georeferenced frame.
    pub regions: Vec<ChangeRegion>,
    /// Time the change stage spent on the frame (render + compare + regions), ms.
    pub change_ms: f64,
    /// Which change worker made it; `None` when no worker was needed (no pose).
    pub change_worker: Option<u32>,
}

/// The changes of every frame so far fused into objects (fusion → subscribers); published now
/// and then while frames arrive and once, `complete`, when every frame has its change result.
/// Also published as JSON (`schemas/v9/change_set.schema.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChangeSet {
    /// Whether every frame of the stream has its change result (the final set).
    pub complete: bool,
    /// Frames of the stream, when its end is known.
    pub frame_count: Option<u64>,
    /// Frames with a change result, and of those with a change map.
    pub frames_with_result: u64,
    pub frames_with_map: u64,
    /// Fused objects; their `frames` are frame ids. Confirmed when seen by at least
    /// `fusion.min_frames` frames and, for an `added` one, not seen through by more frames than
    /// agree with it (`free_space`).
    pub objects: Vec<FusedChange>,
    pub fusion: FusionConfig,
    /// The free-space test of every `added` object fusion confirmed
    /// (`core::change::free_space::check_free_space`): its index in `objects`, the frames (ids)
    /// that see through it and those that agree, and whether it was refuted (then it is not
    /// confirmed in `objects`).
    pub free_space: Vec<FreeSpaceCheck>,
}

/// A change worker's change result with what its frame saw (change worker → fusion; never
/// published further): the photo's depth map and the model's depth under the registered pose,
/// so that fusion can test the fused `added` objects against every frame's free space
/// (`core::change::free_space`, as `asgreg changes` does). Fusion publishes `meta.result` alone,
/// as a ChangeResult. Without a change map (`meta.view` `None`) both arrays are empty.
#[derive(Clone, Debug, PartialEq)]
pub struct ChangeSight<'a> {
    pub meta: ChangeSightMeta,
    /// The depth map the change map compared with the model (given or stereo), metres along the
    /// optical axis (0 = hole), `meta.view.camera`'s size.
    pub photo_depth_m: Blob<'a, f32>,
    /// The model's rendered depth under the registered pose, metres (0 = no surface), same size.
    pub model_depth_m: Blob<'a, f32>,
}

impl ChangeSight<'_> {
    /// The photo's and the model's depth as images of the registered camera's size; `None`
    /// without a change map.
    #[allow(clippy::type_complexity)]
    pub fn depths(&self) -> Result<Option<(ImageView<'_, f32>, ImageView<'_, f32>)>, ImageError> {
        let Some(view) = &self.meta.view else {
            return Ok(None);
        };
        let (w, h) = (
            view.camera.width_px as usize,
            view.camera.height_px as usize,
        );
        Ok(Some((
            ImageView::new(w, h, &self.photo_depth_m)?,
            ImageView::new(w, h, &self.model_depth_m)?,
        )))
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChangeSightMeta {
    pub result: ChangeResult,
    /// How the frame looked, when it has a change map.
    pub view: Option<SightView>,
}

/// The registered camera and pose of a frame's change map and the settings it was made with
/// (its own u, `pose_sigma_px`, and σ_quad included).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SightView {
    pub camera: Camera,
    pub cam_from_world: Rigid3,
    pub config: ChangeConfig,
}

/// Identifies a unit of parallel work: one coarse pose of one frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct JobKey {
    pub frame_id: u64,
    pub coarse_index: u32,
}

/// The render output for one coarse pose (render → flow): the query gradient image and the ASG
/// rendering, depth and face index of the coarse view.
#[derive(Clone, Debug, PartialEq)]
pub struct FlowJob<'a> {
    pub meta: FlowJobMeta,
    /// The photo's gradient image (query), 0..1.
    pub query: Blob<'a, f32>,
    /// ASG rendering of the coarse pose, 0..1.
    pub asg: Blob<'a, f32>,
    /// Rendered depth along the optical axis, metres (0 where nothing was hit).
    pub depth_m: Blob<'a, f32>,
    /// Rendered face per pixel (u32::MAX where nothing was hit).
    pub face_index: Blob<'a, u32>,
}

impl FlowJob<'_> {
    /// The photo's gradient image (query, 0..1) as an image of the camera's size.
    pub fn query_image(&self) -> Result<ImageView<'_, f32>, ImageError> {
        self.meta.info.image(&self.query)
    }

    /// The coarse view (its ASG, depth and face index as images of the camera's size) as the
    /// flow step reads it.
    pub fn view(&self) -> Result<ViewRef<'_>, ImageError> {
        let info = &self.meta.info;
        ViewRef::new(
            self.meta.coarse_index as usize,
            self.meta.coarse_cam_from_world,
            info.image(&self.asg)?,
            info.image(&self.depth_m)?,
            info.image(&self.face_index)?,
        )
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FlowJobMeta {
    pub info: FrameInfo,
    pub coarse_index: u32,
    pub coarse_count: u32,
    pub coarse_cam_from_world: Rigid3,
    /// Time the render stage spent on this frame, ms (all coarse views).
    pub render_ms: f64,
}

/// 2D–3D correspondences of one coarse pose (flow → pose), with the coarse view's rendering on
/// δ's grid for verify's convergence test.
#[derive(Clone, Debug, PartialEq)]
pub struct Correspondences<'a> {
    pub meta: CorrespondencesMeta,
    /// Query pixel positions (x, y) in COLMAP pixel coordinates, interleaved.
    pub image_points_px: Blob<'a, f64>,
    /// World points (x, y, z) in metres, interleaved.
    pub world_points_m: Blob<'a, f64>,
    /// The coarse view's grid samples (stride `meta.grid_stride_px`); the pose stage passes them
    /// on to verify with the hypothesis.
    pub grid: GridArrays<'a>,
}

impl Correspondences<'_> {
    /// The message of one view's correspondences; `meta.grid_stride_px` is set from `grid`.
    pub fn from_view(
        mut meta: CorrespondencesMeta,
        view: &ViewCorrespondences,
        grid: Option<GridSamples>,
    ) -> Correspondences<'static> {
        let (grid_stride_px, grid) = GridArrays::from_samples(grid);
        meta.grid_stride_px = grid_stride_px;
        Correspondences {
            meta,
            grid,
            image_points_px: Cow::Owned(
                view.image_points_px
                    .iter()
                    .flat_map(|p| [p.x, p.y])
                    .collect(),
            ),
            world_points_m: Cow::Owned(
                view.world_points_m
                    .iter()
                    .flat_map(|p| [p.x, p.y, p.z])
                    .collect(),
            ),
        }
    }

    /// The view's correspondences the message carries.
    pub fn to_view(&self) -> ViewCorrespondences {
        ViewCorrespondences {
            coarse_index: self.meta.coarse_index as usize,
            coarse_cam_from_world: self.meta.coarse_cam_from_world,
            image_points_px: self
                .image_points_px
                .chunks_exact(2)
                .map(|p| Vector2::new(p[0], p[1]))
                .collect(),
            world_points_m: self
                .world_points_m
                .chunks_exact(3)
                .map(|p| Vector3::new(p[0], p[1], p[2]))
                .collect(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CorrespondencesMeta {
    pub info: FrameInfo,
    pub coarse_index: u32,
    pub coarse_count: u32,
    pub coarse_cam_from_world: Rigid3,
    pub render_ms: f64,
    pub flow_ms: f64,
    /// Which flow worker made them (for the work-split report).
    pub flow_worker: u32,
    /// The grid stride of `Correspondences::grid`, px; 0: no grid samples.
    pub grid_stride_px: u32,
}

/// A coarse view's rendering sampled on the grid of δ's visible points
/// (`core::reprojection::GridSamples`, made by `core::frame::coarse_view_samples` in the flow
/// stage, which has the view's rendering): flow → pose → verify, so that verify's convergence
/// test has the coarse pose's visible points (`core::frame::coarse_points`) without rendering it
/// again. Two arrays of `GridSamples::sample_count(camera size, stride)` values each, the stride
/// in the message's meta; both empty (stride 0) when there are none (the views rendered with
/// other options than δ's, or, from pose on, a coarse pose without a hypothesis).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GridArrays<'a> {
    /// Rendered face per sample (u32::MAX where nothing was hit), row by row.
    pub face_index: Blob<'a, u32>,
    /// Rendered depth along the optical axis per sample, metres.
    pub depth_m: Blob<'a, f32>,
}

impl GridArrays<'_> {
    /// The arrays of `samples` and their stride (0 without samples).
    pub fn from_samples(samples: Option<GridSamples>) -> (u32, GridArrays<'static>) {
        let Some(samples) = samples else {
            return (0, GridArrays::default());
        };
        let stride_px = u32::try_from(samples.stride_px()).unwrap_or(0);
        let (face_index, depth_m) = samples.into_parts();
        (
            stride_px,
            GridArrays {
                face_index: Cow::Owned(face_index),
                depth_m: Cow::Owned(depth_m),
            },
        )
    }

    /// The samples of a coarse view of `camera`'s size at `stride_px`; `None` without samples
    /// (stride 0) or when their counts do not fit the grid (the decoder has checked them).
    pub fn samples(&self, stride_px: u32, camera: &Camera) -> Option<GridSamples> {
        if stride_px == 0 {
            return None;
        }
        GridSamples::from_parts(
            camera.width_px as usize,
            camera.height_px as usize,
            stride_px as usize,
            self.face_index.to_vec(),
            self.depth_m.to_vec(),
        )
        .ok()
    }
}

/// The refined pose of one coarse pose, or why there is none (pose → verify), with its coarse
/// view's grid samples when there is a pose.
#[derive(Clone, Debug, PartialEq)]
pub struct Hypothesis<'a> {
    pub meta: HypothesisMeta,
    /// The coarse view's grid samples (stride `meta.grid_stride_px`) for verify's convergence
    /// test; empty without a pose.
    pub grid: GridArrays<'a>,
}

impl Hypothesis<'_> {
    /// The coarse view's grid samples, when they came.
    pub fn grid_samples(&self) -> Option<GridSamples> {
        self.grid
            .samples(self.meta.grid_stride_px, &self.meta.info.camera)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HypothesisMeta {
    pub info: FrameInfo,
    pub coarse_count: u32,
    pub outcome: CoarseOutcome,
    pub render_ms: f64,
    pub flow_ms: f64,
    pub pose_ms: f64,
    pub flow_worker: u32,
    /// The grid stride of `Hypothesis::grid`, px; 0: no grid samples.
    pub grid_stride_px: u32,
}

/// A frame that cannot be registered at all (bad input, model not visible, dropped by
/// backpressure): any stage sends this to verify, which turns it into the frame's one result.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameFailed {
    pub name: String,
    /// The stage that gave up ("ingest", "render", ...).
    pub stage: String,
    pub reason: String,
}

/// A camera in plain numbers (for JSON subscribers): pinhole intrinsics in pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraNumbers {
    pub width_px: u32,
    pub height_px: u32,
    pub fx_px: f64,
    pub fy_px: f64,
    pub cx_px: f64,
    pub cy_px: f64,
    pub skew_px: f64,
}

impl From<&Camera> for CameraNumbers {
    fn from(camera: &Camera) -> Self {
        let k = &camera.intrinsics;
        Self {
            width_px: camera.width_px,
            height_px: camera.height_px,
            fx_px: k.fx_px,
            fy_px: k.fy_px,
            cx_px: k.cx_px,
            cy_px: k.cy_px,
            skew_px: k.skew_px,
        }
    }
}

/// A `cam_from_world` pose in plain numbers: COLMAP's quaternion (w, x, y, z) and translation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseNumbers {
    pub qvec_wxyz: [f64; 4],
    pub tvec_m: [f64; 3],
}

impl From<&Rigid3> for PoseNumbers {
    fn from(pose: &Rigid3) -> Self {
        let q = pose.rotation.quaternion();
        Self {
            qvec_wxyz: [q.w, q.i, q.j, q.k],
            tvec_m: [pose.translation.x, pose.translation.y, pose.translation.z],
        }
    }
}

/// Why the verdict is what it is: the numbers behind it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Evidence {
    /// Refined poses obtained from the coarse poses.
    pub hypotheses: u32,
    /// Largest group of mutually compatible refined poses.
    pub component_size: u32,
    /// Refined poses directly compatible with the chosen one, itself included.
    pub direct_support: u32,
    /// RANSAC consensus (inliers) of the chosen pose.
    pub consensus: u32,
    pub inlier_rms_px: Option<f64>,
    pub mean_delta_to_chosen_px: f64,
    pub convergence_ratio: Option<f64>,
    /// The final refinement of the chosen pose; `None` when there was none (no pose, disabled).
    pub refinement: Option<RefinementNumbers>,
}

/// What the final refinement (edge alignment) found.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RefinementNumbers {
    /// Share of the model's edge samples a photo edge supports within a pixel, at the verified
    /// pose and at the aligned one (0..1).
    pub verified_edge_support: f64,
    pub aligned_edge_support: f64,
    /// Whether the aligned pose is the output (its support is higher, and the photo shows the
    /// model's edges at one of the two poses).
    pub kept: bool,
}

impl From<&crate::core::frame::PoseRefinement> for RefinementNumbers {
    fn from(refinement: &crate::core::frame::PoseRefinement) -> Self {
        Self {
            verified_edge_support: refinement.verified.support_fraction(),
            aligned_edge_support: refinement.aligned.support_fraction(),
            kept: refinement.kept,
        }
    }
}

/// Time spent per stage on a frame, ms; `latency_ms` is capture → result.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StageTimesMs {
    pub render_ms: f64,
    /// Sum over the frame's coarse poses (they may run on several workers at once).
    pub flow_ms: f64,
    pub pose_ms: f64,
    /// Verification and the final refinement.
    pub verify_ms: f64,
    pub latency_ms: f64,
}

/// The one result of a frame (verify → subscribers); also published as JSON
/// (`schemas/v9/pose_result.schema.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseResult {
    pub frame_id: u64,
    pub name: String,
    pub accepted: bool,
    /// Why not accepted: the stage and the reason.
    pub failure: Option<String>,
    /// 0..1, threshold it to trade recall for precision.
    pub confidence: f64,
    /// The refined camera (estimated intrinsics when they were unknown), when accepted.
    pub camera: Option<CameraNumbers>,
    pub cam_from_world: Option<PoseNumbers>,
    pub evidence: Evidence,
    pub times: StageTimesMs,
    /// Flow worker of each coarse pose, by coarse index (how the work was split).
    pub flow_workers: Vec<u32>,
}

/// A worker of a dispatched link says it is ready for more work and which jobs it finished.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Credit {
    pub worker_index: u32,
    /// Changes every time the worker process starts: a new value means the old one died and its
    /// unfinished jobs must be redone.
    pub incarnation: u64,
    /// Jobs finished since the last credit.
    pub completed: Vec<JobKey>,
    /// Jobs the worker can take now.
    pub free_slots: u32,
}

/// A stage's counters (sent now and then and at the end of the stream).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StageMetrics {
    pub stage: String,
    pub worker_index: u32,
    /// Changes every time the process starts (a restart is seen as a new value).
    pub incarnation: u64,
    pub messages_in: u64,
    pub messages_out: u64,
    pub dropped: u64,
    pub rejected: u64,
    /// Jobs redone because a worker died or went silent.
    pub redispatched: u64,
    pub max_queue_depth: u64,
    pub bytes_out: u64,
    /// Time spent encoding and sending, ms.
    pub send_ms: f64,
    /// Time spent decoding received messages, ms.
    pub decode_ms: f64,
    /// Time spent computing, ms.
    pub compute_ms: f64,
    /// Per-message compute times, ms (for percentiles).
    pub compute_samples_ms: Vec<f64>,
}

/// The source has sent all its frames (ingest → verify → results).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct StreamEnd {
    /// Frames the source produced (ids 0..frame_count).
    pub frame_count: u64,
    /// Frames whose result the source has already seen (a restarted verify learns them here).
    pub finished_frames: Vec<u64>,
}

#[cfg(test)]
mod image_accessor_tests {
    use super::*;
    use crate::core::camera::PinholeIntrinsics;

    fn info() -> FrameInfo {
        FrameInfo {
            name: "a.jpg".into(),
            camera_id: 1,
            camera: Camera::pinhole(3, 2, PinholeIntrinsics::centered(4.0, 3, 2)),
            intrinsics_known: true,
            initial_cam_from_world: Rigid3::identity(),
            seed: 1,
        }
    }

    #[test]
    fn frame_blobs_read_as_images_of_the_camera_size() {
        let mut frame = Frame {
            info: info(),
            image: Cow::Owned(vec![0.5; 6]),
            depth_m: Cow::Owned(Vec::new()),
        };
        assert_eq!(frame.photo().unwrap().size(), (3, 2));
        assert_eq!(frame.depth().unwrap(), None);
        frame.depth_m = Cow::Owned(vec![2.0; 6]);
        assert_eq!(frame.depth().unwrap().unwrap().get(2, 1), Some(&2.0));
        frame.image = Cow::Owned(vec![0.5; 5]);
        let error = frame.photo().unwrap_err();
        assert!(matches!(
            error,
            ImageError::DataLength {
                expected: 6,
                found: 5,
                ..
            }
        ));
    }

    #[test]
    fn a_flow_job_reads_as_a_checked_view() {
        let asg = [0.25f32; 6];
        let mut job = FlowJob {
            meta: FlowJobMeta {
                info: info(),
                coarse_index: 4,
                coarse_count: 15,
                coarse_cam_from_world: Rigid3::identity(),
                render_ms: 1.0,
            },
            query: Cow::Borrowed(&asg),
            asg: Cow::Borrowed(&asg),
            depth_m: Cow::Borrowed(&asg),
            face_index: Cow::Owned(vec![7; 6]),
        };
        assert_eq!(job.query_image().unwrap().size(), (3, 2));
        let view = job.view().unwrap();
        assert_eq!(view.coarse_index, 4);
        assert_eq!((view.width_px(), view.height_px()), (3, 2));
        assert_eq!(view.face_index().get(1, 1), Some(&7));
        job.face_index = Cow::Owned(vec![7; 4]);
        assert!(job.view().is_err());
        job.query = Cow::Owned(Vec::new());
        assert!(job.query_image().is_err());
    }
}
