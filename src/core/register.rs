//! One frame end to end (Schmitz et al. §3; DESIGN §2): coarse poses around the initial pose →
//! ASG renderings → SIFT flow both ways → 2D–3D correspondences → RANSAC per coarse pose →
//! plausibility check. Written as the stage functions the streaming pipeline runs one by one
//! (render, flow, pose, verify); [`register_frame`] chains them in one process.
//!
//! Determinism: every random draw comes from a ChaCha8 stream derived from the frame seed and the
//! coarse pose's index, so results do not depend on thread scheduling or on which worker ran which
//! coarse pose.

use std::time::Instant;

use nalgebra::{UnitQuaternion, Vector2, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::camera::Camera;
use super::flow_consistency::{
    match_query_to_renderings, DenseCorrespondence, DenseCorrespondenceConfig, GreyImage,
};
use super::mesh::Mesh;
use super::pose::estimate::{estimate_pose, IntrinsicsPrior, PoseEstimate, PoseEstimationConfig};
use super::pose::{Correspondences, PoseError};
use super::raster::{Rasterizer, RenderBuffers, RenderOptions, NO_FACE};
use super::reprojection::{ray_plane_point_cam, ReprojectionWorkspace};
use super::rigid::Rigid3;
use super::shading::{
    asg_from_normals, gradient_magnitude_with_filter, normals_from_depth, scale_to_percentile,
    AsgOptions,
};

/// Photo gradients and ASG images are both scaled so that this percentile of their positive
/// values is 1 (values above are clamped): they then live on the same 0..1 scale, which the
/// texture threshold of the flow assumes.
const GRADIENT_SCALE_PERCENTILE: f64 = 0.99;
use super::verify::{verify_hypotheses, PoseHypothesis, Verdict, VerifyConfig};

/// Which gradient image stands for the photo (DESIGN §2 step 3).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum QueryMode {
    /// Gradient magnitude of the photo (Plötz & Roth's choice).
    #[default]
    ImageGradient,
    /// ASG of the normals of the photo's depth map (the paper's choice); needs a depth map.
    DepthAsg,
}

/// Whether the photo's intrinsics are known.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum IntrinsicsMode {
    /// Calibrated: EPnP, only the pose is estimated.
    #[default]
    Known,
    /// Uncalibrated: DLT, focal lengths, principal point and pose are estimated.
    Unknown,
}

/// Settings of the registration of one frame; `Default` is the paper's setup.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RegistrationConfig {
    /// Coarse poses per frame (paper: 15). The first is the initial pose itself. The spread below
    /// is not in the paper. Measured trade-off (synthetic house, depth query): at 1° / 2 % an ideal
    /// query reaches 0.9 px, but on photos no frame's refined poses converge measurably, so the
    /// convergence test rejects them all; at 3° / 6 % the ideal query only reaches 4.1 px (far
    /// coarse views flow less accurately) while photo frames start to pass the test.
    pub coarse_pose_count: usize,
    /// Standard deviation of the coarse poses' rotation noise, degrees (per axis).
    pub coarse_rotation_sigma_deg: f64,
    /// Standard deviation of the coarse poses' camera-centre noise, as a fraction of the median
    /// scene depth seen from the initial pose (dimensionless; 0.02 at 40 m is 0.8 m).
    pub coarse_translation_sigma_fraction: f64,
    pub query_mode: QueryMode,
    /// [`QueryMode::DepthAsg`]: radius of the discontinuity-aware smoothing of the photo's depth
    /// before normals are taken, px (0: none). MVS depth is noisy per pixel; normals of raw depth
    /// are noise (a 0.7 % depth error at 20 m is 14 cm, more than the 5 cm pixel footprint).
    pub query_depth_smoothing_radius_px: usize,
    /// Neighbours whose depth differs by more than this fraction from the centre's are not
    /// averaged (they are across an occlusion edge), dimensionless.
    pub query_depth_max_relative_step: f32,
    pub intrinsics: IntrinsicsMode,
    pub render: RenderOptions,
    pub asg: AsgOptions,
    pub correspondence: DenseCorrespondenceConfig,
    /// At most this many correspondences per coarse pose go to RANSAC (an even subsample).
    pub max_correspondences_per_pose: usize,
    /// Fewer consistent correspondences than this: the coarse pose gives no hypothesis.
    pub min_correspondences_per_pose: usize,
    pub pose: PoseEstimationConfig,
    pub verify: VerifyConfig,
}

impl Default for RegistrationConfig {
    fn default() -> Self {
        let correspondence = DenseCorrespondenceConfig {
            sift_flow: super::sift_flow::SiftFlowConfig::fast(),
            ..DenseCorrespondenceConfig::default()
        };
        Self {
            coarse_pose_count: 15,
            coarse_rotation_sigma_deg: 1.0,
            coarse_translation_sigma_fraction: 0.02,
            query_mode: QueryMode::ImageGradient,
            query_depth_smoothing_radius_px: 3,
            query_depth_max_relative_step: 0.03,
            intrinsics: IntrinsicsMode::Known,
            render: RenderOptions::default(),
            asg: AsgOptions::default(),
            correspondence,
            max_correspondences_per_pose: 3000,
            min_correspondences_per_pose: 30,
            pose: PoseEstimationConfig::default(),
            verify: VerifyConfig::default(),
        }
    }
}

/// Why a frame could not be registered at all (as opposed to a rejection by verification).
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RegistrationError {
    #[error("registration config: {field}: {why}")]
    InvalidConfig { field: &'static str, why: String },
    #[error("the photo is {photo_width_px}x{photo_height_px} px but its camera is {camera_width_px}x{camera_height_px} px")]
    PhotoSize {
        photo_width_px: usize,
        photo_height_px: usize,
        camera_width_px: u32,
        camera_height_px: u32,
    },
    #[error("query mode DepthAsg needs the photo's depth map, and none was given")]
    MissingDepth,
    #[error("the depth map is {depth_width_px}x{depth_height_px} px, the photo {photo_width_px}x{photo_height_px} px")]
    DepthSize {
        depth_width_px: usize,
        depth_height_px: usize,
        photo_width_px: usize,
        photo_height_px: usize,
    },
    #[error("the initial pose is not finite (NaN or infinity in its rotation or translation)")]
    NonFiniteInitialPose,
    #[error("the model is not visible from the initial pose: check the pose convention (cam_from_world) and the mesh's coordinate frame")]
    ModelNotVisible,
    #[error("dense correspondence failed: {0}")]
    Flow(String),
}

impl RegistrationConfig {
    pub fn validate(&self) -> Result<(), RegistrationError> {
        let bad =
            |field: &'static str, why: String| Err(RegistrationError::InvalidConfig { field, why });
        if self.coarse_pose_count == 0 {
            return bad("coarse_pose_count", "must be at least 1".into());
        }
        for (field, value) in [
            ("coarse_rotation_sigma_deg", self.coarse_rotation_sigma_deg),
            (
                "coarse_translation_sigma_fraction",
                self.coarse_translation_sigma_fraction,
            ),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(field, format!("{value} is not a non-negative number"));
            }
        }
        if !(self.query_depth_max_relative_step.is_finite()
            && self.query_depth_max_relative_step >= 0.0)
        {
            return bad(
                "query_depth_max_relative_step",
                format!(
                    "{} is not a non-negative number",
                    self.query_depth_max_relative_step
                ),
            );
        }
        if self.min_correspondences_per_pose < 6 {
            return bad(
                "min_correspondences_per_pose",
                "must be at least 6 (a DLT sample)".into(),
            );
        }
        if self.max_correspondences_per_pose < self.min_correspondences_per_pose {
            return bad(
                "max_correspondences_per_pose",
                "must not be below min_correspondences_per_pose".into(),
            );
        }
        self.correspondence
            .validate()
            .map_err(|e| RegistrationError::InvalidConfig {
                field: "correspondence",
                why: e.to_string(),
            })?;
        self.pose
            .validate()
            .map_err(|e| RegistrationError::InvalidConfig {
                field: "pose",
                why: e.to_string(),
            })?;
        self.verify
            .validate()
            .map_err(|e| RegistrationError::InvalidConfig {
                field: "verify",
                why: e.to_string(),
            })?;
        Ok(())
    }
}

/// The photo side of a frame.
#[derive(Clone, Copy, Debug)]
pub struct FrameInput<'a> {
    /// Grey photo, row major, values 0..1.
    pub photo: GreyImage<'a>,
    /// The photo's depth map (metres along the optical axis, holes 0), for [`QueryMode::DepthAsg`].
    pub depth_m: Option<GreyImage<'a>>,
    /// The camera: known intrinsics, or the nominal ones coarse poses are rendered with.
    pub camera: &'a Camera,
    pub initial_cam_from_world: Rigid3,
    /// Seed of this frame's random draws.
    pub seed: u64,
}

/// The query's gradient image, scaled to 0..1.
#[derive(Clone, Debug, Default)]
pub struct QueryGradient {
    pub width_px: usize,
    pub height_px: usize,
    pub pixels: Vec<f32>,
}

/// One coarse pose's rendering: what the flow stage needs and what lifts matches to 3D.
#[derive(Clone, Debug, Default)]
pub struct CoarseView {
    pub coarse_index: usize,
    pub cam_from_world: Rigid3,
    /// ASG image scaled to 0..1.
    pub asg: Vec<f32>,
    /// Pixels that show the model.
    pub valid: Vec<bool>,
    pub render: RenderBuffers,
}

/// 2D–3D correspondences of one coarse pose.
#[derive(Clone, Debug, Default)]
pub struct Correspondences2d3d {
    pub coarse_index: usize,
    /// The coarse pose the rendering was made from.
    pub coarse_cam_from_world: Rigid3,
    /// Query image points, pixels (COLMAP convention: pixel centres at +0.5).
    pub image_points_px: Vec<Vector2<f64>>,
    pub world_points: Vec<Vector3<f64>>,
    /// Descriptor matching cost of each correspondence.
    pub matching_costs: Vec<f32>,
}

/// What became of one coarse pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CoarseOutcome {
    pub coarse_index: usize,
    pub consistent_matches: usize,
    /// The refined pose, or why there is none.
    pub hypothesis: Option<PoseHypothesis>,
    pub failure: Option<String>,
}

/// Time spent in each stage of a frame.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
pub struct StageTimings {
    pub query_ms: f64,
    pub render_ms: f64,
    pub flow_ms: f64,
    pub pose_ms: f64,
    pub verify_ms: f64,
    pub total_ms: f64,
}

/// The result of one frame: a verdict, the pose when accepted, and the evidence.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FrameResult {
    pub accepted: bool,
    /// The chosen refined camera (intrinsics may be estimated) and pose; present when accepted.
    pub camera: Option<Camera>,
    pub cam_from_world: Option<Rigid3>,
    pub verdict: Verdict,
    pub coarse: Vec<CoarseOutcome>,
    pub timings: StageTimings,
}

fn elapsed_ms(started: Instant) -> f64 {
    started.elapsed().as_secs_f64() * 1e3
}

/// Stage "query": the photo's gradient image (either mode), scaled to 0..1.
pub fn query_gradient(
    input: &FrameInput,
    config: &RegistrationConfig,
) -> Result<QueryGradient, RegistrationError> {
    let photo = input.photo;
    if photo.width_px != input.camera.width_px as usize
        || photo.height_px != input.camera.height_px as usize
    {
        return Err(RegistrationError::PhotoSize {
            photo_width_px: photo.width_px,
            photo_height_px: photo.height_px,
            camera_width_px: input.camera.width_px,
            camera_height_px: input.camera.height_px,
        });
    }
    let (width_px, height_px) = (photo.width_px, photo.height_px);
    let mut pixels = vec![0.0f32; width_px * height_px];
    match config.query_mode {
        QueryMode::ImageGradient => gradient_magnitude_with_filter(
            photo.pixels,
            width_px,
            height_px,
            config.asg.derivative_filter,
            &mut pixels,
        ),
        QueryMode::DepthAsg => {
            let depth = input.depth_m.ok_or(RegistrationError::MissingDepth)?;
            if depth.width_px != width_px || depth.height_px != height_px {
                return Err(RegistrationError::DepthSize {
                    depth_width_px: depth.width_px,
                    depth_height_px: depth.height_px,
                    photo_width_px: width_px,
                    photo_height_px: height_px,
                });
            }
            let mut smoothed = vec![0.0f32; width_px * height_px];
            smooth_depth(
                depth.pixels,
                width_px,
                height_px,
                config.query_depth_smoothing_radius_px,
                config.query_depth_max_relative_step,
                &mut smoothed,
            );
            let mut normals = vec![glam::Vec3::ZERO; width_px * height_px];
            normals_from_depth(
                &smoothed,
                width_px,
                height_px,
                &input.camera.intrinsics,
                &mut normals,
            );
            asg_from_normals(&normals, width_px, height_px, &config.asg, &mut pixels);
        }
    }
    scale_to_percentile(&mut pixels, GRADIENT_SCALE_PERCENTILE);
    Ok(QueryGradient {
        width_px,
        height_px,
        pixels,
    })
}

/// Discontinuity-aware box smoothing of a depth map (holes are 0 and stay 0): each valid pixel
/// becomes the mean of the valid pixels within `radius_px` whose depth is within
/// `max_relative_step` of its own. Rows in parallel.
pub fn smooth_depth(
    depth_m: &[f32],
    width_px: usize,
    height_px: usize,
    radius_px: usize,
    max_relative_step: f32,
    out: &mut [f32],
) {
    out.par_chunks_mut(width_px.max(1))
        .enumerate()
        .for_each(|(row, out_row)| {
            for (col, out_value) in out_row.iter_mut().enumerate() {
                let centre = depth_m[row * width_px + col];
                if !(centre.is_finite() && centre > 0.0) {
                    *out_value = 0.0;
                    continue;
                }
                let (mut sum, mut count) = (0.0f32, 0u32);
                for r in row.saturating_sub(radius_px)..(row + radius_px + 1).min(height_px) {
                    for c in col.saturating_sub(radius_px)..(col + radius_px + 1).min(width_px) {
                        let d = depth_m[r * width_px + c];
                        if d.is_finite()
                            && d > 0.0
                            && (d - centre).abs() <= max_relative_step * centre
                        {
                            sum += d;
                            count += 1;
                        }
                    }
                }
                *out_value = sum / count.max(1) as f32;
            }
        });
}

/// Median depth of the surface in a rendering, metres; `None` when it shows no surface.
pub fn median_scene_depth_m(buffers: &RenderBuffers) -> Option<f64> {
    let mut depths: Vec<f32> = buffers
        .depth_m
        .iter()
        .zip(&buffers.face_index)
        .filter(|(_, f)| **f != NO_FACE)
        .map(|(d, _)| *d)
        .collect();
    if depths.is_empty() {
        return None;
    }
    let middle = depths.len() / 2;
    let (_, median, _) = depths.select_nth_unstable_by(middle, f32::total_cmp);
    Some(f64::from(*median))
}

/// A ChaCha8 stream for one purpose of one frame (stream ids keep purposes independent).
fn frame_rng(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

/// Stage "plan": the coarse poses around the initial pose (the first is the initial pose).
/// Rotation noise is applied about the camera centre, centre noise in world coordinates.
pub fn coarse_poses(
    initial_cam_from_world: &Rigid3,
    median_depth_m: f64,
    config: &RegistrationConfig,
    seed: u64,
) -> Vec<Rigid3> {
    let mut rng = frame_rng(seed, 1);
    let rotation_sigma_rad = config.coarse_rotation_sigma_deg.to_radians();
    let centre_sigma_m = config.coarse_translation_sigma_fraction * median_depth_m;
    let centre = initial_cam_from_world.camera_center();
    let mut normal3 = |sigma: f64| {
        Vector3::new(
            StandardNormal.sample(&mut rng),
            StandardNormal.sample(&mut rng),
            StandardNormal.sample(&mut rng),
        ) * sigma
    };
    let mut poses = vec![*initial_cam_from_world];
    for _ in 1..config.coarse_pose_count {
        let rotation = UnitQuaternion::from_scaled_axis(normal3(rotation_sigma_rad))
            * initial_cam_from_world.rotation;
        let new_centre = centre + normal3(centre_sigma_m);
        poses.push(Rigid3::new(rotation, -(rotation * new_centre)));
    }
    poses
}

/// Stage "render": the ASG rendering of one coarse pose, into a reused view.
pub fn render_coarse_view(
    mesh: &Mesh,
    camera: &Camera,
    coarse_index: usize,
    cam_from_world: &Rigid3,
    config: &RegistrationConfig,
    rasterizer: &mut Rasterizer,
    out: &mut CoarseView,
) {
    let (width_px, height_px) = (camera.width_px as usize, camera.height_px as usize);
    out.coarse_index = coarse_index;
    out.cam_from_world = *cam_from_world;
    out.render.resize(width_px, height_px);
    rasterizer.render(
        mesh,
        &camera.intrinsics,
        cam_from_world,
        &config.render,
        &mut out.render,
    );
    out.asg.resize(width_px * height_px, 0.0);
    asg_from_normals(
        &out.render.normal_cam,
        width_px,
        height_px,
        &config.asg,
        &mut out.asg,
    );
    scale_to_percentile(&mut out.asg, GRADIENT_SCALE_PERCENTILE);
    out.valid.clear();
    out.valid
        .extend(out.render.face_index.iter().map(|f| *f != NO_FACE));
}

/// Stage "flow": SIFT flow from the query to every view and back, consistent pairs only.
pub fn match_views(
    query: &QueryGradient,
    views: &[CoarseView],
    config: &RegistrationConfig,
) -> Result<Vec<DenseCorrespondence>, RegistrationError> {
    let query_image = GreyImage {
        width_px: query.width_px,
        height_px: query.height_px,
        pixels: &query.pixels,
    };
    let renderings: Vec<(GreyImage, Option<&[bool]>)> = views
        .iter()
        .map(|view| {
            (
                GreyImage {
                    width_px: view.render.width_px(),
                    height_px: view.render.height_px(),
                    pixels: &view.asg,
                },
                // The validity mask is not passed: with it, SIFT flow lost the true match on
                // every ASG pair with 30–55 px displacement (0 % of pixels within 2 px of the
                // true flow, against 85–96 % without; examples in the eval note). Invalid pixels
                // have zero ASG, and lifting drops matches that land on them.
                None,
            )
        })
        .collect();
    match_query_to_renderings(query_image, &renderings, &config.correspondence)
        .map_err(|e| RegistrationError::Flow(e.to_string()))
}

/// What lifting needs of a coarse view: its pose and the rendered depth and face per pixel (borrowed
/// from a [`CoarseView`] in one process, or from a received message in the pipeline).
#[derive(Clone, Copy, Debug)]
pub struct ViewGeometry<'a> {
    pub coarse_index: usize,
    pub cam_from_world: Rigid3,
    pub width_px: usize,
    pub height_px: usize,
    pub depth_m: &'a [f32],
    pub face_index: &'a [u32],
}

impl CoarseView {
    /// The view's geometry for [`lift_correspondences`].
    pub fn geometry(&self) -> ViewGeometry<'_> {
        ViewGeometry {
            coarse_index: self.coarse_index,
            cam_from_world: self.cam_from_world,
            width_px: self.render.width_px(),
            height_px: self.render.height_px(),
            depth_m: &self.render.depth_m,
            face_index: &self.render.face_index,
        }
    }
}

/// Stage "lift": each consistent pixel pair becomes (query pixel, 3D model point): the rendering
/// pixel's ray (through the sub-pixel flow target) meets the plane of the face rendered there.
pub fn lift_correspondences(
    mesh: &Mesh,
    camera: &Camera,
    view: ViewGeometry<'_>,
    dense: &DenseCorrespondence,
) -> Correspondences2d3d {
    let width = view.width_px;
    let height = view.height_px;
    let world_from_cam = view.cam_from_world.inverse();
    let mut out = Correspondences2d3d {
        coarse_index: view.coarse_index,
        coarse_cam_from_world: view.cam_from_world,
        ..Correspondences2d3d::default()
    };
    for pair in &dense.correspondences {
        let col = pair.rendering_x_px.round();
        let row = pair.rendering_y_px.round();
        if col < 0.0 || row < 0.0 || col >= width as f32 || row >= height as f32 {
            continue;
        }
        let pixel = row as usize * width + col as usize;
        let face_index = view.face_index[pixel];
        if face_index == NO_FACE {
            continue;
        }
        let normalized = camera.intrinsics.pixel_to_normalized(Vector2::new(
            f64::from(pair.rendering_x_px) + 0.5,
            f64::from(pair.rendering_y_px) + 0.5,
        ));
        let ray_cam = Vector3::new(normalized.x, normalized.y, 1.0);
        let depth_m = f64::from(view.depth_m[pixel]);
        let point_cam = ray_plane_point_cam(
            mesh,
            face_index as usize,
            &view.cam_from_world,
            &ray_cam,
            depth_m,
        )
        .unwrap_or(ray_cam * depth_m);
        out.image_points_px.push(Vector2::new(
            f64::from(pair.query_x_px) + 0.5,
            f64::from(pair.query_y_px) + 0.5,
        ));
        out.world_points
            .push(world_from_cam.transform_point(&point_cam));
        out.matching_costs.push(pair.matching_cost);
    }
    out
}

/// Stage "pose": RANSAC (EPnP or DLT) and refinement on one coarse pose's correspondences.
pub fn solve_coarse_pose(
    correspondences: &Correspondences2d3d,
    camera: &Camera,
    config: &RegistrationConfig,
    seed: u64,
) -> Result<(PoseHypothesis, PoseEstimate), PoseError> {
    let count = correspondences.image_points_px.len();
    if count < config.min_correspondences_per_pose {
        return Err(PoseError::TooFewPoints {
            solver: "consistent correspondences of a coarse pose",
            needed: config.min_correspondences_per_pose,
            got: count,
        });
    }
    // An even subsample keeps RANSAC's cost bounded without favouring any image region.
    let step = count.div_ceil(config.max_correspondences_per_pose).max(1);
    let image_points: Vec<Vector2<f64>> = correspondences
        .image_points_px
        .iter()
        .step_by(step)
        .copied()
        .collect();
    let world_points: Vec<Vector3<f64>> = correspondences
        .world_points
        .iter()
        .step_by(step)
        .copied()
        .collect();
    let data = Correspondences::new(&image_points, &world_points)?;
    let prior = match config.intrinsics {
        IntrinsicsMode::Known => IntrinsicsPrior::Known(camera.intrinsics),
        IntrinsicsMode::Unknown => IntrinsicsPrior::Unknown {
            planar_fallback: Some(camera.intrinsics),
        },
    };
    let mut rng = frame_rng(seed, 100 + correspondences.coarse_index as u64);
    let estimate = estimate_pose(&data, &prior, &config.pose, &mut rng)?;
    let refined_camera = Camera {
        intrinsics: estimate.camera.intrinsics,
        ..Camera::pinhole(
            camera.width_px,
            camera.height_px,
            estimate.camera.intrinsics,
        )
    };
    let hypothesis = PoseHypothesis {
        camera: refined_camera,
        cam_from_world: estimate.camera.cam_from_world,
        consensus: estimate.inlier_count,
        inlier_rms_px: estimate.inlier_rms_px,
        correspondence_count: data.len(),
        coarse_cam_from_world: correspondences.coarse_cam_from_world,
    };
    Ok((hypothesis, estimate))
}

/// Registers one frame: all stages in one process.
pub fn register_frame(
    mesh: &Mesh,
    input: &FrameInput,
    config: &RegistrationConfig,
) -> Result<FrameResult, RegistrationError> {
    let started = Instant::now();
    config.validate()?;
    let query = query_gradient(input, config)?;
    let query_ms = elapsed_ms(started);
    let mut result = register_query(
        mesh,
        input.camera,
        &input.initial_cam_from_world,
        &query,
        config,
        input.seed,
    )?;
    result.timings.query_ms = query_ms;
    result.timings.total_ms = elapsed_ms(started);
    Ok(result)
}

/// Registers a frame whose query gradient image is already made: plan, render, flow, pose and
/// verify. `config` must be valid.
pub fn register_query(
    mesh: &Mesh,
    camera: &Camera,
    initial_cam_from_world: &Rigid3,
    query: &QueryGradient,
    config: &RegistrationConfig,
    seed: u64,
) -> Result<FrameResult, RegistrationError> {
    let started = Instant::now();
    if !initial_cam_from_world.is_finite() {
        return Err(RegistrationError::NonFiniteInitialPose);
    }
    let mut timings = StageTimings::default();

    let stage = Instant::now();
    let mut rasterizer = Rasterizer::new();
    // The first coarse view is the initial pose itself: its rendering also gives the scene depth
    // that scales the other coarse poses.
    let mut initial_view = CoarseView::default();
    render_coarse_view(
        mesh,
        camera,
        0,
        initial_cam_from_world,
        config,
        &mut rasterizer,
        &mut initial_view,
    );
    let median_depth_m =
        median_scene_depth_m(&initial_view.render).ok_or(RegistrationError::ModelNotVisible)?;
    let poses = coarse_poses(initial_cam_from_world, median_depth_m, config, seed);
    let mut views: Vec<CoarseView> = Vec::with_capacity(poses.len());
    views.push(initial_view);
    for (coarse_index, pose) in poses.iter().enumerate().skip(1) {
        let mut view = CoarseView::default();
        render_coarse_view(
            mesh,
            camera,
            coarse_index,
            pose,
            config,
            &mut rasterizer,
            &mut view,
        );
        views.push(view);
    }
    timings.render_ms = elapsed_ms(stage);

    let stage = Instant::now();
    let dense = match_views(query, &views, config)?;
    timings.flow_ms = elapsed_ms(stage);

    let stage = Instant::now();
    let outcomes: Vec<CoarseOutcome> = views
        .par_iter()
        .zip(dense.par_iter())
        .map(|(view, dense)| {
            let lifted = lift_correspondences(mesh, camera, view.geometry(), dense);
            let consistent_matches = lifted.image_points_px.len();
            match solve_coarse_pose(&lifted, camera, config, seed) {
                Ok((hypothesis, _)) => CoarseOutcome {
                    coarse_index: view.coarse_index,
                    consistent_matches,
                    hypothesis: Some(hypothesis),
                    failure: None,
                },
                Err(error) => CoarseOutcome {
                    coarse_index: view.coarse_index,
                    consistent_matches,
                    hypothesis: None,
                    failure: Some(error.to_string()),
                },
            }
        })
        .collect();
    timings.pose_ms = elapsed_ms(stage);

    let stage = Instant::now();
    let (result_camera, result_pose, verdict) = verify_outcomes(mesh, camera, &outcomes, config);
    timings.verify_ms = elapsed_ms(stage);
    timings.total_ms = elapsed_ms(started);
    Ok(FrameResult {
        accepted: verdict.accepted,
        camera: result_camera,
        cam_from_world: result_pose,
        verdict,
        coarse: outcomes,
        timings,
    })
}

/// Stage "verify": the plausibility check over the coarse outcomes of a frame; returns the chosen
/// camera and pose (when accepted) and the verdict.
pub fn verify_outcomes(
    mesh: &Mesh,
    camera: &Camera,
    outcomes: &[CoarseOutcome],
    config: &RegistrationConfig,
) -> (Option<Camera>, Option<Rigid3>, Verdict) {
    let hypotheses: Vec<PoseHypothesis> = outcomes.iter().filter_map(|o| o.hypothesis).collect();
    let mut workspace = ReprojectionWorkspace::new();
    let verdict = verify_hypotheses(
        mesh,
        &hypotheses,
        Some(camera),
        &config.verify,
        &mut workspace,
    );
    let chosen = verdict
        .chosen
        .filter(|_| verdict.accepted)
        .map(|i| hypotheses[i]);
    (
        chosen.map(|h| h.camera),
        chosen.map(|h| h.cam_from_world),
        verdict,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::camera::PinholeIntrinsics;
    use crate::core::reprojection::mutual_reprojection_error_px;
    use crate::synth::geometry::build_house;

    fn house_mesh() -> Mesh {
        let scene = build_house(&mut ChaCha8Rng::seed_from_u64(3));
        let positions: Vec<Vector3<f64>> = scene
            .positions_m
            .iter()
            .map(|p| Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z)))
            .collect();
        Mesh::from_world(&positions, scene.faces.clone(), None).unwrap()
    }

    /// The whole chain on an ideal query (the model's own ASG under the true pose): from an initial
    /// pose tens of pixels off, the accepted pose must be the true one to about a pixel. This
    /// checks rendering, flow, lifting, RANSAC, refinement and verification together; photos make it
    /// harder, which `asgreg eval` measures.
    #[test]
    fn ideal_query_recovers_the_true_pose_from_tens_of_pixels_off() {
        let mesh = house_mesh();
        let camera = Camera::pinhole(505, 275, PinholeIntrinsics::centered(360.0, 505, 275));
        let truth = Rigid3::look_at(
            &Vector3::new(18.0, -14.0, 9.0),
            &Vector3::new(0.0, 0.0, 3.0),
            &Vector3::z(),
        )
        .unwrap();
        let initial = Rigid3::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.04, -0.05, 0.02)) * truth.rotation,
            truth.translation + Vector3::new(1.0, -0.6, 0.4),
        );
        let config = RegistrationConfig::default();
        let mut workspace = ReprojectionWorkspace::new();
        let initial_delta =
            mutual_reprojection_error_px(&mesh, &camera, &initial, &camera, &truth, &mut workspace)
                .unwrap();
        let mut rasterizer = Rasterizer::new();
        let mut truth_view = CoarseView::default();
        render_coarse_view(
            &mesh,
            &camera,
            0,
            &truth,
            &config,
            &mut rasterizer,
            &mut truth_view,
        );
        let query = QueryGradient {
            width_px: 505,
            height_px: 275,
            pixels: truth_view.asg.clone(),
        };
        let result = register_query(&mesh, &camera, &initial, &query, &config, 7).unwrap();
        assert!(result.accepted, "{:?}", result.verdict);
        let final_delta = mutual_reprojection_error_px(
            &mesh,
            &result.camera.unwrap(),
            &result.cam_from_world.unwrap(),
            &camera,
            &truth,
            &mut workspace,
        )
        .unwrap();
        println!(
            "ideal query: δ {initial_delta:.1} px → {final_delta:.3} px, {} of {} poses agree",
            result.verdict.component.len(),
            result.verdict.hypothesis_count
        );
        assert!(
            initial_delta > 15.0,
            "the start must be far off: {initial_delta}"
        );
        // The target for known intrinsics at 30 px is 1.5 px; an ideal query must meet it
        // (measured: 0.89 px from 22.6 px with seed 7, after the flow's banded BP landed; 1.12 px before; the residual is the flow's sub-pixel error on
        // thin ASG edges and the coarse views' perspective differences).
        assert!(final_delta < 1.5, "{final_delta}");
        // Same seed, same result.
        let again = register_query(&mesh, &camera, &initial, &query, &config, 7).unwrap();
        assert_eq!(again.cam_from_world, result.cam_from_world);
    }

    #[test]
    fn depth_smoothing_averages_within_surfaces_and_keeps_edges_and_holes() {
        // Left half a wall at 10 m with ±0.1 m alternating noise, right half at 20 m, one hole.
        let (width, height) = (10, 5);
        let mut depth: Vec<f32> = (0..width * height)
            .map(|i| {
                if i % width < 5 {
                    10.0 + if i % 2 == 0 { 0.1 } else { -0.1 }
                } else {
                    20.0
                }
            })
            .collect();
        depth[2 * width + 7] = 0.0;
        let mut out = vec![0.0; width * height];
        smooth_depth(&depth, width, height, 1, 0.03, &mut out);
        assert_eq!(out[2 * width + 7], 0.0, "a hole stays a hole");
        assert_eq!(
            out[2 * width + 8],
            20.0,
            "the far wall is not pulled towards the near one"
        );
        // The noise alternates by column: a 3x3 window inside the wall holds columns -,+,- (mean
        // 10 - 0.1/3); at the wall's edge the window keeps only columns 3 and 4 (-,+: mean 10).
        assert!(
            (out[2 * width + 2] - (10.0 - 0.1 / 3.0)).abs() < 1e-5,
            "{}",
            out[2 * width + 2]
        );
        assert!(
            (out[2 * width + 4] - 10.0).abs() < 1e-5,
            "{}",
            out[2 * width + 4]
        );
    }

    #[test]
    fn bad_inputs_are_reported_not_panicked() {
        let mesh = house_mesh();
        let camera = Camera::pinhole(64, 48, PinholeIntrinsics::centered(50.0, 64, 48));
        let query = QueryGradient {
            width_px: 64,
            height_px: 48,
            pixels: vec![0.0; 64 * 48],
        };
        let config = RegistrationConfig::default();
        let nan_pose = Rigid3::new(UnitQuaternion::identity(), Vector3::new(f64::NAN, 0.0, 0.0));
        assert_eq!(
            register_query(&mesh, &camera, &nan_pose, &query, &config, 1).unwrap_err(),
            RegistrationError::NonFiniteInitialPose
        );
        // Looking away from the house.
        let away = Rigid3::look_at(
            &Vector3::new(0.0, 0.0, 50.0),
            &Vector3::new(0.0, 0.0, 100.0),
            &Vector3::x(),
        )
        .unwrap();
        assert_eq!(
            register_query(&mesh, &camera, &away, &query, &config, 1).unwrap_err(),
            RegistrationError::ModelNotVisible
        );
        let photo = vec![0.5f32; 10 * 10];
        let input = FrameInput {
            photo: GreyImage {
                width_px: 10,
                height_px: 10,
                pixels: &photo,
            },
            depth_m: None,
            camera: &camera,
            initial_cam_from_world: Rigid3::identity(),
            seed: 1,
        };
        assert!(matches!(
            query_gradient(&input, &config),
            Err(RegistrationError::PhotoSize { .. })
        ));
    }
}
