//! The ICP baseline the paper compares its method against (paper §4, "Comparison to an ICP
//! Implementation"; docs/design.md §3: "ICP baseline on the same frames and initial poses").
//!
//! The paper used PCL's ICP (Rusu & Cousins 2011): the photo's depth map and intrinsics give a
//! point cloud in the camera frame, ICP aligns it with the model, and the camera pose follows from
//! the alignment. A registration counts as a success when δ(P_icp, P_gt) < 20 px
//! ([`ICP_SUCCESS_THRESHOLD_PX`], [`delta_to_ground_truth_px`]). This module reproduces that
//! baseline without PCL:
//!
//! - **Photo points** ([`back_project_depth`]): the depth map (metres along the optical axis,
//!   holes `0.0`, see [`crate::io::pfm`]) is sampled on a regular pixel grid (every
//!   [`IcpConfig::depth_grid_stride_px`] pixels, pixel centres at `(col + 0.5, row + 0.5)`) and
//!   back-projected with the camera (pinhole intrinsics; lens distortion is inverted when the
//!   camera has one): `points_cam`.
//! - **Model points** ([`sample_mesh_in_view`]): area-weighted uniform samples on the mesh surface
//!   (seeded RNG passed in), each with its face normal, in the mesh's local frame (docs/design.md §6: the
//!   f64 origin is kept apart so georeferenced meshes keep their precision). Only what is
//!   *plausibly visible* is sampled: the surface inside the initial view's frustum enlarged by
//!   [`IcpConfig::view_margin_fraction`] of the image size on every side (a generous region, since
//!   the initial pose is off by tens of pixels), not farther than
//!   [`IcpConfig::view_max_depth_factor`] × the farthest photo point, and (optionally) facing the
//!   initial camera (back faces cannot be seen from anywhere near it). Occlusion is not tested:
//!   hidden surface facing the camera is kept, and correspondence rejection copes with it; a
//!   render-based visibility test would drop surface that the *true* pose sees but the initial
//!   one does not.
//! - **Alignment** ([`align_to_model`]): starting from the initial pose, each iteration pairs every
//!   photo point (moved into the world by the current `world_from_cam`) with its nearest model
//!   sample (kd-tree, kiddo), rejects pairs farther than a maximum correspondence distance that
//!   shrinks geometrically over the iterations (from
//!   [`IcpConfig::initial_max_correspondence_distance_m`] to
//!   [`IcpConfig::final_max_correspondence_distance_m`]), keeps the closest
//!   [`IcpConfig::trim_fraction`] of the rest (trimmed ICP, Chetverikov et al. 2002), and solves
//!   for the rigid update:
//!   - [`IcpVariant::PointToPoint`]: Besl & McKay (1992), in closed form by the SVD of the
//!     cross-covariance (Umeyama 1991 without scale; Arun et al. 1987);
//!   - [`IcpVariant::PointToPlane`]: Chen & Medioni (1992), residuals along the model normals,
//!     linearised for small angles (Low 2004) and solved as a 6×6 least-squares system; the
//!     rotation is then applied exactly (axis-angle), so the estimate stays a rigid transform.
//!
//!   It stops, converged, once the rejection distance has reached its final value and the new
//!   estimate lies within [`IcpConfig::translation_tolerance_m`] (camera centre) and
//!   [`IcpConfig::rotation_tolerance_rad`] of the previous one, or of one of the last few (the
//!   trimmed correspondence set can flip between a few states forever, a limit cycle whose poses
//!   differ by well under a millimetre); otherwise it stops after [`IcpConfig::max_iterations`].
//!
//! Measurements (point-to-plane against point-to-point, against the paper's PCL ICP):
//! docs/measurements.md#baselineicp.
//!
//! **Convention.** Photo points live in the camera frame, the model in the world frame, so ICP
//! estimates `world_from_cam`; the pose returned is its inverse, `cam_from_world` (docs/design.md §6).
//!
//! References: P. J. Besl, N. D. McKay, "A method for registration of 3-D shapes", TPAMI 1992;
//! Y. Chen, G. Medioni, "Object modelling by registration of multiple range images", IVC 1992;
//! S. Umeyama, "Least-squares estimation of transformation parameters between two point patterns",
//! TPAMI 1991; D. Chetverikov et al., "The Trimmed Iterative Closest Point algorithm", ICPR 2002;
//! K.-L. Low, "Linear least-squares optimization for point-to-plane ICP surface registration",
//! TR04-004, UNC 2004; R. B. Rusu, S. Cousins, "3D is here: Point Cloud Library (PCL)", ICRA 2011.

use std::collections::VecDeque;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Matrix3, Matrix6, UnitQuaternion, Vector2, Vector3, Vector6};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::core::camera::{Camera, CameraError, MIN_DEPTH_M};
use crate::core::image::Image;
use crate::core::mesh::Mesh;
use crate::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};
use crate::core::rigid::Rigid3;
use crate::io::pfm::{depth_at, valid_depth_count};

/// The paper's success criterion for ICP: δ(P_icp, P_gt) below this many pixels (at 505×275).
pub const ICP_SUCCESS_THRESHOLD_PX: f64 = 20.0;

/// Fewest correspondences a rigid update is solved from (6 unknowns; a margin against
/// near-degenerate sets).
pub const MIN_CORRESPONDENCES: usize = 12;

/// How many past estimates a new one is compared with to detect a cycle of the correspondence
/// assignment (the estimate returning, within the tolerances, to where it was).
const CYCLE_MEMORY: usize = 4;

/// Errors of the ICP baseline.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum IcpError {
    #[error("invalid ICP config: {0}")]
    InvalidConfig(String),
    #[error("invalid camera: {0}")]
    Camera(#[from] CameraError),
    #[error("the depth map ({width_px}x{height_px} px) has no valid depth")]
    EmptyDepth { width_px: usize, height_px: usize },
    #[error("only {found} photo points (at least {required} needed); use a smaller depth_grid_stride_px or a denser depth map")]
    TooFewPoints { found: usize, required: usize },
    #[error("the {which} pose is not finite")]
    NonFinitePose { which: &'static str },
    #[error("no mesh surface lies in the initial view (enlarged by the view margin); the initial pose does not look at the model")]
    NoMeshSamples,
    #[error("{count} model points and {normal_count} normals: they must pair up, and be finite")]
    BadModelCloud { count: usize, normal_count: usize },
    #[error("iteration {iteration}: only {found} correspondences within {max_distance_m:.3} m (at least {required} needed)")]
    TooFewCorrespondences {
        iteration: usize,
        found: usize,
        required: usize,
        max_distance_m: f64,
    },
    #[error("iteration {iteration}: the {variant:?} update cannot be solved (degenerate correspondences)")]
    DegenerateUpdate {
        iteration: usize,
        variant: IcpVariant,
    },
}

/// Which error ICP minimises.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum IcpVariant {
    /// Sum of squared point distances (Besl & McKay 1992), closed form by SVD.
    PointToPoint,
    /// Sum of squared distances along the model normals (Chen & Medioni 1992), linearised.
    PointToPlane,
}

/// Everything that shapes an ICP run. Distances are in metres of the world frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IcpConfig {
    /// The error minimised.
    pub variant: IcpVariant,
    /// Distance between the depth pixels back-projected, along rows and columns, pixels (≥ 1).
    pub depth_grid_stride_px: usize,
    /// Number of model points sampled on the mesh surface in the initial view.
    pub mesh_sample_count: usize,
    /// How far beyond the image border the sampled region reaches, as a fraction of the image
    /// width (left/right) and height (top/bottom) on each side (0.5: a view twice as wide and high).
    pub view_margin_fraction: f64,
    /// Model surface farther from the initial camera (along its optical axis) than this factor
    /// times the farthest photo point is not sampled (dimensionless, ≥ 1).
    pub view_max_depth_factor: f64,
    /// Whether model faces turned away from the initial camera are left out of the sampling.
    pub cull_back_faces: bool,
    /// Most ICP iterations.
    pub max_iterations: usize,
    /// Maximum correspondence distance in the first iteration, metres (covers the initial error).
    pub initial_max_correspondence_distance_m: f64,
    /// Smallest maximum correspondence distance, reached by shrinking, metres (covers depth noise
    /// and model deviation).
    pub final_max_correspondence_distance_m: f64,
    /// Factor the maximum correspondence distance is multiplied by after each iteration (0, 1].
    pub correspondence_distance_shrink: f64,
    /// Fraction of the correspondences within the distance that are kept, the closest first
    /// (trimmed ICP), (0, 1].
    pub trim_fraction: f64,
    /// Converged when an update moves the camera by less than this, metres.
    pub translation_tolerance_m: f64,
    /// Converged when an update rotates by less than this, radians.
    pub rotation_tolerance_rad: f64,
}

impl Default for IcpConfig {
    fn default() -> Self {
        Self {
            variant: IcpVariant::PointToPlane,
            depth_grid_stride_px: 4,
            mesh_sample_count: 30_000,
            view_margin_fraction: 0.5,
            view_max_depth_factor: 1.5,
            cull_back_faces: true,
            max_iterations: 60,
            initial_max_correspondence_distance_m: 5.0,
            final_max_correspondence_distance_m: 0.75,
            correspondence_distance_shrink: 0.85,
            trim_fraction: 0.9,
            translation_tolerance_m: 1e-4,
            rotation_tolerance_rad: 1e-5,
        }
    }
}

impl IcpConfig {
    /// Checks every field once, before anything is computed.
    pub fn validate(&self) -> Result<(), IcpError> {
        let invalid = |message: String| Err(IcpError::InvalidConfig(message));
        if self.depth_grid_stride_px == 0 {
            return invalid("depth_grid_stride_px must be at least 1".into());
        }
        if self.mesh_sample_count < MIN_CORRESPONDENCES {
            return invalid(format!(
                "mesh_sample_count {} is below {MIN_CORRESPONDENCES}",
                self.mesh_sample_count
            ));
        }
        if !(self.view_margin_fraction.is_finite() && self.view_margin_fraction >= 0.0) {
            return invalid(format!(
                "view_margin_fraction {} must be finite and ≥ 0",
                self.view_margin_fraction
            ));
        }
        if !(self.view_max_depth_factor.is_finite() && self.view_max_depth_factor >= 1.0) {
            return invalid(format!(
                "view_max_depth_factor {} must be finite and ≥ 1",
                self.view_max_depth_factor
            ));
        }
        if self.max_iterations == 0 {
            return invalid("max_iterations must be at least 1".into());
        }
        let positive = |value: f64| value.is_finite() && value > 0.0;
        if !positive(self.final_max_correspondence_distance_m)
            || !positive(self.initial_max_correspondence_distance_m)
            || self.initial_max_correspondence_distance_m < self.final_max_correspondence_distance_m
        {
            return invalid(format!(
                "max correspondence distances must be positive with initial ≥ final (got {} m → {} m)",
                self.initial_max_correspondence_distance_m, self.final_max_correspondence_distance_m
            ));
        }
        if !(self.correspondence_distance_shrink > 0.0
            && self.correspondence_distance_shrink <= 1.0)
        {
            return invalid(format!(
                "correspondence_distance_shrink {} is outside (0, 1]",
                self.correspondence_distance_shrink
            ));
        }
        if !(self.trim_fraction > 0.0 && self.trim_fraction <= 1.0) {
            return invalid(format!(
                "trim_fraction {} is outside (0, 1]",
                self.trim_fraction
            ));
        }
        let non_negative = |value: f64| value.is_finite() && value >= 0.0;
        if !non_negative(self.translation_tolerance_m) || !non_negative(self.rotation_tolerance_rad)
        {
            return invalid("tolerances must be finite and ≥ 0".into());
        }
        Ok(())
    }

    /// The maximum correspondence distance of iteration `iteration` (0-based), metres.
    pub fn max_correspondence_distance_m(&self, iteration: usize) -> f64 {
        let exponent = i32::try_from(iteration).unwrap_or(i32::MAX);
        (self.initial_max_correspondence_distance_m
            * self.correspondence_distance_shrink.powi(exponent))
        .max(self.final_max_correspondence_distance_m)
    }
}

/// What an ICP run produced.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct IcpResult {
    /// The refined pose, `x_cam = R · x_world + t`.
    pub cam_from_world: Rigid3,
    /// Iterations run (updates solved).
    pub iterations: usize,
    /// Whether the updates fell below the tolerances before `max_iterations`.
    pub converged: bool,
    /// RMS distance between the final inlier pairs (photo point to its nearest model sample),
    /// metres.
    pub rms_m: f64,
    /// RMS distance of the final inlier photo points to the planes of their model samples, metres.
    pub rms_point_to_plane_m: f64,
    /// Final inliers (within the final correspondence distance, after trimming) over all photo
    /// points.
    pub inlier_fraction: f64,
    /// Photo points that took part.
    pub photo_point_count: usize,
    /// Model samples that took part.
    pub model_point_count: usize,
}

/// Back-projects the valid depths on a grid of pixel centres (every `grid_stride_px` pixels,
/// starting at `grid_stride_px / 2`) into camera-frame points, metres. The camera is rescaled
/// to the depth map's size when they differ. Pixels whose ray cannot be computed are skipped.
/// `depth` is metres along the optical axis, holes 0 (`io::pfm`).
pub fn back_project_depth(
    camera: &Camera,
    depth: &Image<f32>,
    grid_stride_px: usize,
) -> Result<Vec<Vector3<f64>>, IcpError> {
    camera.validate()?;
    if grid_stride_px == 0 {
        return Err(IcpError::InvalidConfig(
            "depth_grid_stride_px must be at least 1".into(),
        ));
    }
    if depth.is_empty() || valid_depth_count(depth.view()) == 0 {
        return Err(IcpError::EmptyDepth {
            width_px: depth.width_px(),
            height_px: depth.height_px(),
        });
    }
    let (Ok(width_px), Ok(height_px)) = (
        u32::try_from(depth.width_px()),
        u32::try_from(depth.height_px()),
    ) else {
        return Err(IcpError::EmptyDepth {
            width_px: depth.width_px(),
            height_px: depth.height_px(),
        });
    };
    let camera = if (camera.width_px, camera.height_px) == (width_px, height_px) {
        *camera
    } else {
        camera.resized(width_px, height_px)
    };
    let start = grid_stride_px / 2;
    let mut points_cam_m = Vec::new();
    for row in (start..depth.height_px()).step_by(grid_stride_px) {
        for col in (start..depth.width_px()).step_by(grid_stride_px) {
            let Some(depth_m) = depth_at(depth.view(), col, row) else {
                continue;
            };
            let pixel = Vector2::new(col as f64 + 0.5, row as f64 + 0.5);
            let Some(ray_cam) = camera.unproject(pixel) else {
                continue;
            };
            let point_cam = ray_cam * f64::from(depth_m);
            if point_cam.iter().all(|v| v.is_finite()) {
                points_cam_m.push(point_cam);
            }
        }
    }
    Ok(points_cam_m)
}

/// Model points with normals, in a local frame (`world = origin_m + local`), with the kd-tree
/// ICP searches them by.
pub struct ModelCloud {
    origin_m: Vector3<f64>,
    points_local_m: Vec<Vector3<f64>>,
    normals: Vec<Vector3<f64>>,
    tree: ImmutableKdTree<f64, 3>,
}

impl std::fmt::Debug for ModelCloud {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ModelCloud")
            .field("origin_m", &self.origin_m)
            .field("len", &self.points_local_m.len())
            .finish()
    }
}

impl ModelCloud {
    /// A cloud from points relative to `origin_m` and their unit normals (same length, finite).
    pub fn new(
        origin_m: Vector3<f64>,
        points_local_m: Vec<Vector3<f64>>,
        normals: Vec<Vector3<f64>>,
    ) -> Result<Self, IcpError> {
        let bad = IcpError::BadModelCloud {
            count: points_local_m.len(),
            normal_count: normals.len(),
        };
        if points_local_m.is_empty() {
            return Err(IcpError::NoMeshSamples);
        }
        let all_finite = origin_m.iter().all(|v| v.is_finite())
            && points_local_m
                .iter()
                .chain(&normals)
                .all(|p| p.iter().all(|v| v.is_finite()));
        if normals.len() != points_local_m.len() || !all_finite {
            return Err(bad);
        }
        let coordinates: Vec<[f64; 3]> = points_local_m.iter().map(|p| [p.x, p.y, p.z]).collect();
        let tree = ImmutableKdTree::<f64, 3>::new_from_slice(&coordinates).map_err(|_| bad)?;
        Ok(Self {
            origin_m,
            points_local_m,
            normals,
            tree,
        })
    }

    /// A cloud from world points (the origin is their first point, so local values stay small).
    pub fn from_world(
        points_world_m: &[Vector3<f64>],
        normals: Vec<Vector3<f64>>,
    ) -> Result<Self, IcpError> {
        let origin_m = points_world_m
            .first()
            .copied()
            .unwrap_or_else(Vector3::zeros);
        let local = points_world_m.iter().map(|p| p - origin_m).collect();
        Self::new(origin_m, local, normals)
    }

    pub fn origin_m(&self) -> Vector3<f64> {
        self.origin_m
    }

    pub fn points_local_m(&self) -> &[Vector3<f64>] {
        &self.points_local_m
    }

    pub fn normals(&self) -> &[Vector3<f64>] {
        &self.normals
    }

    pub fn len(&self) -> usize {
        self.points_local_m.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points_local_m.is_empty()
    }

    /// The nearest sample to a local point: its index and squared distance (m²).
    fn nearest(&self, point_local: &Vector3<f64>) -> (usize, f64) {
        let nearest = self
            .tree
            .query(&[point_local.x, point_local.y, point_local.z])
            .nearest_one::<SquaredEuclidean<f64>>()
            .execute();
        (nearest.item as usize, nearest.distance)
    }
}

/// The half-spaces (camera frame) of the initial view's enlarged frustum: a point `p` is inside
/// when `plane · p ≥ 0` for the four side planes, `z ≥ near` and `z ≤ far`.
struct ViewFrustum {
    side_planes: [Vector3<f64>; 4],
    near_m: f64,
    far_m: f64,
}

impl ViewFrustum {
    fn new(camera: &Camera, margin_fraction: f64, far_m: f64) -> Self {
        let width = f64::from(camera.width_px);
        let height = f64::from(camera.height_px);
        let (u0, u1) = (-margin_fraction * width, (1.0 + margin_fraction) * width);
        let (v0, v1) = (-margin_fraction * height, (1.0 + margin_fraction) * height);
        // Normalised bounds of the enlarged image (pinhole; skew folded in conservatively).
        let corners = [(u0, v0), (u1, v0), (u0, v1), (u1, v1)]
            .map(|(u, v)| camera.intrinsics.pixel_to_normalized(Vector2::new(u, v)));
        let x_min = corners.iter().map(|c| c.x).fold(f64::INFINITY, f64::min);
        let x_max = corners
            .iter()
            .map(|c| c.x)
            .fold(f64::NEG_INFINITY, f64::max);
        let y_min = corners.iter().map(|c| c.y).fold(f64::INFINITY, f64::min);
        let y_max = corners
            .iter()
            .map(|c| c.y)
            .fold(f64::NEG_INFINITY, f64::max);
        let unit = |v: Vector3<f64>| v / v.norm();
        Self {
            side_planes: [
                unit(Vector3::new(1.0, 0.0, -x_min)),
                unit(Vector3::new(-1.0, 0.0, x_max)),
                unit(Vector3::new(0.0, 1.0, -y_min)),
                unit(Vector3::new(0.0, -1.0, y_max)),
            ],
            near_m: MIN_DEPTH_M,
            far_m,
        }
    }

    /// Whether a sphere (camera frame) reaches into the frustum (conservative).
    fn touches_sphere(&self, centre_cam: &Vector3<f64>, radius_m: f64) -> bool {
        centre_cam.z + radius_m >= self.near_m
            && centre_cam.z - radius_m <= self.far_m
            && self
                .side_planes
                .iter()
                .all(|plane| plane.dot(centre_cam) >= -radius_m)
    }

    fn contains(&self, point_cam: &Vector3<f64>) -> bool {
        self.touches_sphere(point_cam, 0.0)
    }
}

/// Samples `config.mesh_sample_count` points uniformly by area on the mesh surface that is
/// plausibly visible from `cam_from_world` (see the module documentation), each with its face
/// normal. `max_photo_depth_m` is the farthest photo point's depth (it bounds the region).
pub fn sample_mesh_in_view(
    mesh: &Mesh,
    camera: &Camera,
    cam_from_world: &Rigid3,
    max_photo_depth_m: f64,
    config: &IcpConfig,
    rng: &mut impl Rng,
) -> Result<ModelCloud, IcpError> {
    config.validate()?;
    camera.validate()?;
    if !cam_from_world.is_finite() {
        return Err(IcpError::NonFinitePose { which: "initial" });
    }
    if !(max_photo_depth_m.is_finite() && max_photo_depth_m > 0.0) {
        return Err(IcpError::EmptyDepth {
            width_px: camera.width_px as usize,
            height_px: camera.height_px as usize,
        });
    }
    let origin_m = mesh.origin_m();
    // x_cam = R (origin + x_local) + t: fold the origin into the translation in f64.
    let cam_from_local = Rigid3::new(
        cam_from_world.rotation,
        cam_from_world.rotation * origin_m + cam_from_world.translation,
    );
    let camera_centre_local = cam_from_local.camera_center();
    let frustum = ViewFrustum::new(
        camera,
        config.view_margin_fraction,
        config.view_max_depth_factor * max_photo_depth_m,
    );
    let local = |v: u32| {
        let p = mesh.positions_local_m()[v as usize];
        Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z))
    };

    // Candidate faces and their cumulative areas.
    let mut candidates: Vec<([Vector3<f64>; 3], Vector3<f64>)> = Vec::new();
    let mut cumulative_area_m2: Vec<f64> = Vec::new();
    let mut total_area_m2 = 0.0;
    for face in mesh.faces() {
        let [a, b, c] = face.map(local);
        let cross = (b - a).cross(&(c - a));
        let double_area = cross.norm();
        if !(double_area > 0.0 && double_area.is_finite()) {
            continue;
        }
        let normal = cross / double_area;
        let centroid = (a + b + c) / 3.0;
        if config.cull_back_faces && normal.dot(&(camera_centre_local - centroid)) <= 0.0 {
            continue;
        }
        let radius_m = [a, b, c]
            .iter()
            .map(|v| (v - centroid).norm())
            .fold(0.0, f64::max);
        if !frustum.touches_sphere(&cam_from_local.transform_point(&centroid), radius_m) {
            continue;
        }
        total_area_m2 += 0.5 * double_area;
        candidates.push(([a, b, c], normal));
        cumulative_area_m2.push(total_area_m2);
    }
    if candidates.is_empty() {
        return Err(IcpError::NoMeshSamples);
    }

    // Area-weighted sampling; samples outside the frustum (parts of large faces) are redrawn.
    let wanted = config.mesh_sample_count;
    let max_draws = wanted.saturating_mul(20);
    let mut points_local_m = Vec::with_capacity(wanted);
    let mut normals = Vec::with_capacity(wanted);
    let mut draws = 0;
    while points_local_m.len() < wanted && draws < max_draws {
        draws += 1;
        let target = rng.random::<f64>() * total_area_m2;
        let index = cumulative_area_m2
            .partition_point(|&area| area <= target)
            .min(candidates.len() - 1);
        let ([a, b, c], normal) = candidates[index];
        // Uniform barycentric sample (Osada et al. 2002).
        let r1 = rng.random::<f64>().sqrt();
        let r2 = rng.random::<f64>();
        let point = a * (1.0 - r1) + b * (r1 * (1.0 - r2)) + c * (r1 * r2);
        if frustum.contains(&cam_from_local.transform_point(&point)) {
            points_local_m.push(point);
            normals.push(normal);
        }
    }
    if points_local_m.len() < MIN_CORRESPONDENCES {
        return Err(IcpError::NoMeshSamples);
    }
    ModelCloud::new(origin_m, points_local_m, normals)
}

/// One correspondence: photo point index, model sample index, squared distance (m²).
#[derive(Clone, Copy)]
struct Pair {
    photo_index: usize,
    model_index: usize,
    distance2_m2: f64,
}

/// Pairs each moved photo point with its nearest model sample, keeps those within
/// `max_distance_m`, then the closest `trim_fraction` of them.
fn correspondences(
    points_local_m: &[Vector3<f64>],
    model: &ModelCloud,
    max_distance_m: f64,
    trim_fraction: f64,
    pairs: &mut Vec<Pair>,
) {
    pairs.clear();
    let max_distance2_m2 = max_distance_m * max_distance_m;
    for (photo_index, point) in points_local_m.iter().enumerate() {
        let (model_index, distance2_m2) = model.nearest(point);
        if distance2_m2 <= max_distance2_m2 {
            pairs.push(Pair {
                photo_index,
                model_index,
                distance2_m2,
            });
        }
    }
    if trim_fraction < 1.0 && !pairs.is_empty() {
        let keep = ((pairs.len() as f64 * trim_fraction).ceil() as usize).clamp(1, pairs.len());
        if keep < pairs.len() {
            pairs
                .select_nth_unstable_by(keep - 1, |a, b| a.distance2_m2.total_cmp(&b.distance2_m2));
            pairs.truncate(keep);
        }
    }
}

/// The rigid update `Δ` (local frame) that best maps the paired photo points onto the model
/// points, point-to-point (Umeyama without scale). `None` when the SVD fails.
fn solve_point_to_point(
    points_local_m: &[Vector3<f64>],
    model: &ModelCloud,
    pairs: &[Pair],
) -> Option<Rigid3> {
    let count = pairs.len() as f64;
    let mut photo_mean = Vector3::zeros();
    let mut model_mean = Vector3::zeros();
    for pair in pairs {
        photo_mean += points_local_m[pair.photo_index];
        model_mean += model.points_local_m[pair.model_index];
    }
    photo_mean /= count;
    model_mean /= count;
    let mut cross_covariance = Matrix3::zeros();
    for pair in pairs {
        let photo = points_local_m[pair.photo_index] - photo_mean;
        let target = model.points_local_m[pair.model_index] - model_mean;
        cross_covariance += photo * target.transpose();
    }
    let svd = cross_covariance.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let v = v_t.transpose();
    let mut correction = Matrix3::identity();
    if (v * u.transpose()).determinant() < 0.0 {
        correction[(2, 2)] = -1.0;
    }
    let rotation = v * correction * u.transpose();
    let translation = model_mean - rotation * photo_mean;
    let update = Rigid3::from_rotation_matrix(&rotation, translation);
    update.is_finite().then_some(update)
}

/// The rigid update minimising the linearised point-to-plane error (Chen & Medioni; Low 2004).
/// The rotation is about the centroid of the paired photo points (better conditioned).
/// `None` when the 6×6 system cannot be solved.
fn solve_point_to_plane(
    points_local_m: &[Vector3<f64>],
    model: &ModelCloud,
    pairs: &[Pair],
) -> Option<Rigid3> {
    let mut centroid = Vector3::zeros();
    for pair in pairs {
        centroid += points_local_m[pair.photo_index];
    }
    centroid /= pairs.len() as f64;
    let mut normal_matrix = Matrix6::zeros();
    let mut right_side = Vector6::zeros();
    for pair in pairs {
        let photo = points_local_m[pair.photo_index];
        let target = model.points_local_m[pair.model_index];
        let normal = model.normals[pair.model_index];
        // r = n · (c + (I + [ω]×)(p − c) + t − m) = n·(p − m) + ω·((p − c) × n) + t·n
        let arm = (photo - centroid).cross(&normal);
        let row = Vector6::new(arm.x, arm.y, arm.z, normal.x, normal.y, normal.z);
        let residual = normal.dot(&(photo - target));
        normal_matrix += row * row.transpose();
        right_side -= row * residual;
    }
    // A whisper of Tikhonov damping keeps degenerate geometry (a single plane) solvable: the
    // unconstrained directions then simply do not move.
    let damping = 1e-9 * normal_matrix.trace().max(f64::MIN_POSITIVE) / 6.0;
    let damped = normal_matrix + Matrix6::identity() * damping;
    let solution = damped.cholesky()?.solve(&right_side);
    let rotation_vector = Vector3::new(solution[0], solution[1], solution[2]);
    let translation = Vector3::new(solution[3], solution[4], solution[5]);
    let rotation = UnitQuaternion::from_scaled_axis(rotation_vector);
    // x ↦ c + R (x − c) + t
    let update = Rigid3::new(rotation, centroid - rotation * centroid + translation);
    update.is_finite().then_some(update)
}

/// RMS point-to-point and point-to-plane distances of the pairs, metres.
fn pair_rms_m(points_local_m: &[Vector3<f64>], model: &ModelCloud, pairs: &[Pair]) -> (f64, f64) {
    if pairs.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let (mut sum_point, mut sum_plane) = (0.0, 0.0);
    for pair in pairs {
        sum_point += pair.distance2_m2;
        let offset = points_local_m[pair.photo_index] - model.points_local_m[pair.model_index];
        sum_plane += model.normals[pair.model_index].dot(&offset).powi(2);
    }
    let count = pairs.len() as f64;
    ((sum_point / count).sqrt(), (sum_plane / count).sqrt())
}

/// Aligns camera-frame photo points with a model cloud by ICP, starting from
/// `initial_cam_from_world`; returns the refined `cam_from_world` (see the module docs).
pub fn align_to_model(
    points_cam_m: &[Vector3<f64>],
    model: &ModelCloud,
    initial_cam_from_world: &Rigid3,
    config: &IcpConfig,
) -> Result<IcpResult, IcpError> {
    config.validate()?;
    if !initial_cam_from_world.is_finite() {
        return Err(IcpError::NonFinitePose { which: "initial" });
    }
    if points_cam_m.len() < MIN_CORRESPONDENCES {
        return Err(IcpError::TooFewPoints {
            found: points_cam_m.len(),
            required: MIN_CORRESPONDENCES,
        });
    }
    if model.len() < MIN_CORRESPONDENCES {
        return Err(IcpError::NoMeshSamples);
    }
    // local_from_cam = translate(−origin) ∘ world_from_cam, composed in f64.
    let world_from_cam = initial_cam_from_world.inverse();
    let mut local_from_cam = Rigid3::new(
        world_from_cam.rotation,
        world_from_cam.translation - model.origin_m,
    );
    let mut points_local_m: Vec<Vector3<f64>> = Vec::with_capacity(points_cam_m.len());
    let mut pairs = Vec::with_capacity(points_cam_m.len());
    let move_points = |local_from_cam: &Rigid3, out: &mut Vec<Vector3<f64>>| {
        out.clear();
        out.extend(
            points_cam_m
                .iter()
                .map(|p| local_from_cam.transform_point(p)),
        );
    };
    let mut iterations = 0;
    let mut converged = false;
    let mut recent_estimates: VecDeque<Rigid3> = VecDeque::with_capacity(CYCLE_MEMORY);
    recent_estimates.push_back(local_from_cam);
    for iteration in 0..config.max_iterations {
        let max_distance_m = config.max_correspondence_distance_m(iteration);
        move_points(&local_from_cam, &mut points_local_m);
        correspondences(
            &points_local_m,
            model,
            max_distance_m,
            config.trim_fraction,
            &mut pairs,
        );
        if pairs.len() < MIN_CORRESPONDENCES {
            return Err(IcpError::TooFewCorrespondences {
                iteration,
                found: pairs.len(),
                required: MIN_CORRESPONDENCES,
                max_distance_m,
            });
        }
        let update = match config.variant {
            IcpVariant::PointToPoint => solve_point_to_point(&points_local_m, model, &pairs),
            IcpVariant::PointToPlane => solve_point_to_plane(&points_local_m, model, &pairs),
        }
        .ok_or(IcpError::DegenerateUpdate {
            iteration,
            variant: config.variant,
        })?;
        local_from_cam = update.compose(&local_from_cam);
        if !local_from_cam.is_finite() {
            return Err(IcpError::NonFinitePose { which: "estimated" });
        }
        iterations = iteration + 1;
        // `local_from_cam.translation` is the camera centre (local frame).
        let within_tolerance = |earlier: &Rigid3| {
            (local_from_cam.translation - earlier.translation).norm()
                <= config.translation_tolerance_m
                && local_from_cam.rotation.angle_to(&earlier.rotation)
                    <= config.rotation_tolerance_rad
        };
        let at_final_distance = max_distance_m <= config.final_max_correspondence_distance_m;
        // A step below the tolerances, or a return to a recent estimate (the correspondence
        // assignment cycles; more iterations would only repeat the cycle).
        if at_final_distance && recent_estimates.iter().any(within_tolerance) {
            converged = true;
            break;
        }
        if recent_estimates.len() == CYCLE_MEMORY {
            recent_estimates.pop_front();
        }
        recent_estimates.push_back(local_from_cam);
    }
    // Report on the final pose with the final rejection.
    let final_distance_m = config.max_correspondence_distance_m(iterations);
    move_points(&local_from_cam, &mut points_local_m);
    correspondences(
        &points_local_m,
        model,
        final_distance_m,
        config.trim_fraction,
        &mut pairs,
    );
    let (rms_m, rms_point_to_plane_m) = pair_rms_m(&points_local_m, model, &pairs);
    let world_from_cam = Rigid3::new(
        local_from_cam.rotation,
        local_from_cam.translation + model.origin_m,
    );
    let cam_from_world = world_from_cam.inverse();
    if !cam_from_world.is_finite() {
        return Err(IcpError::NonFinitePose { which: "estimated" });
    }
    Ok(IcpResult {
        cam_from_world,
        iterations,
        converged,
        rms_m,
        rms_point_to_plane_m,
        inlier_fraction: pairs.len() as f64 / points_cam_m.len() as f64,
        photo_point_count: points_cam_m.len(),
        model_point_count: model.len(),
    })
}

/// The whole baseline for one photo: back-project its depth map, sample the mesh in the initial
/// view, align by ICP. `rng` drives the mesh sampling only.
pub fn register_depth_to_mesh(
    mesh: &Mesh,
    camera: &Camera,
    depth: &Image<f32>,
    initial_cam_from_world: &Rigid3,
    config: &IcpConfig,
    rng: &mut impl Rng,
) -> Result<IcpResult, IcpError> {
    config.validate()?;
    if !initial_cam_from_world.is_finite() {
        return Err(IcpError::NonFinitePose { which: "initial" });
    }
    let points_cam_m = back_project_depth(camera, depth, config.depth_grid_stride_px)?;
    if points_cam_m.len() < MIN_CORRESPONDENCES {
        return Err(IcpError::TooFewPoints {
            found: points_cam_m.len(),
            required: MIN_CORRESPONDENCES,
        });
    }
    let max_photo_depth_m = points_cam_m.iter().map(|p| p.z).fold(0.0, f64::max);
    let model = sample_mesh_in_view(
        mesh,
        camera,
        initial_cam_from_world,
        max_photo_depth_m,
        config,
        rng,
    )?;
    align_to_model(&points_cam_m, &model, initial_cam_from_world, config)
}

/// δ(P_icp, P_gt) (paper eq. 5) in pixels, through [`mutual_reprojection_error_px`]; the paper
/// counts an ICP registration as a success below [`ICP_SUCCESS_THRESHOLD_PX`]. `None` when
/// neither pose sees the model.
pub fn delta_to_ground_truth_px(
    mesh: &Mesh,
    camera: &Camera,
    cam_from_world_icp: &Rigid3,
    cam_from_world_gt: &Rigid3,
    workspace: &mut ReprojectionWorkspace,
) -> Option<f64> {
    mutual_reprojection_error_px(
        mesh,
        camera,
        cam_from_world_icp,
        camera,
        cam_from_world_gt,
        workspace,
    )
}

/// Whether an ICP result is a success by the paper's criterion (δ to ground truth < 20 px).
pub fn is_success(delta_to_ground_truth_px: Option<f64>) -> bool {
    delta_to_ground_truth_px.is_some_and(|delta| delta < ICP_SUCCESS_THRESHOLD_PX)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::camera::PinholeIntrinsics;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};
    use std::time::Instant;

    const UTM_OFFSET_M: Vector3<f64> = Vector3::new(512_345.0, 5_401_234.0, 250.0);

    /// A box with outward faces (winding fixed against its centre), rotated about z.
    fn push_box(
        positions: &mut Vec<Vector3<f64>>,
        faces: &mut Vec<[u32; 3]>,
        centre: Vector3<f64>,
        half_size: Vector3<f64>,
        yaw_rad: f64,
    ) {
        let base = positions.len() as u32;
        let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_rad);
        for corner in 0..8u32 {
            let sign = |bit: u32| if corner & bit == 0 { -1.0 } else { 1.0 };
            let offset = Vector3::new(
                sign(1) * half_size.x,
                sign(2) * half_size.y,
                sign(4) * half_size.z,
            );
            positions.push(centre + rotation * offset);
        }
        // Two triangles per side (bottom side included: it faces the ground and is culled).
        let quads = [
            [0, 1, 3, 2],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 3, 7, 6],
            [0, 2, 6, 4],
            [1, 3, 7, 5],
        ];
        for [a, b, c, d] in quads {
            for triangle in [[a, b, c], [a, c, d]] {
                let [p, q, r] = triangle.map(|v: u32| positions[(base + v) as usize]);
                let outward = (q - p).cross(&(r - p)).dot(&((p + q + r) / 3.0 - centre)) > 0.0;
                let [i, j, k] = triangle.map(|v| base + v);
                faces.push(if outward { [i, j, k] } else { [i, k, j] });
            }
        }
    }

    /// Ground with three boxes of different sizes and orientations: constrains all six DoF.
    fn town(offset: Vector3<f64>) -> Mesh {
        let mut positions = [(-40.0, -40.0), (40.0, -40.0), (40.0, 40.0), (-40.0, 40.0)]
            .map(|(x, y)| Vector3::new(x, y, 0.0))
            .to_vec();
        let mut faces = vec![[0, 1, 2], [0, 2, 3]];
        push_box(
            &mut positions,
            &mut faces,
            Vector3::new(0.0, 0.0, 5.0),
            Vector3::new(8.0, 5.0, 5.0),
            0.3,
        );
        push_box(
            &mut positions,
            &mut faces,
            Vector3::new(-15.0, 12.0, 3.5),
            Vector3::new(4.0, 6.0, 3.5),
            -0.2,
        );
        push_box(
            &mut positions,
            &mut faces,
            Vector3::new(14.0, 10.0, 8.0),
            Vector3::new(3.0, 3.0, 8.0),
            0.7,
        );
        let positions: Vec<Vector3<f64>> = positions.iter().map(|p| p + offset).collect();
        Mesh::from_world(&positions, faces, None).unwrap()
    }

    fn test_camera() -> Camera {
        Camera::pinhole(200, 120, PinholeIntrinsics::centered(150.0, 200, 120))
    }

    fn true_pose(offset: Vector3<f64>) -> Rigid3 {
        Rigid3::look_at(
            &(offset + Vector3::new(35.0, -45.0, 40.0)),
            &(offset + Vector3::new(0.0, 0.0, 3.0)),
            &Vector3::z(),
        )
        .unwrap()
    }

    /// `pose` moved by a small rotation (about the camera centre) and camera displacement.
    fn perturbed(
        pose: &Rigid3,
        axis: Vector3<f64>,
        angle_rad: f64,
        shift_m: Vector3<f64>,
    ) -> Rigid3 {
        let world_from_cam = pose.inverse();
        let rotation = UnitQuaternion::from_scaled_axis(axis.normalize() * angle_rad);
        Rigid3::new(
            rotation * world_from_cam.rotation,
            world_from_cam.translation + shift_m,
        )
        .inverse()
    }

    /// Surface samples of `mesh` seen by the true camera, in its frame (occlusion ignored).
    fn photo_points_from_samples(
        mesh: &Mesh,
        camera: &Camera,
        cam_from_world: &Rigid3,
        count: usize,
        seed: u64,
    ) -> Vec<Vector3<f64>> {
        let config = IcpConfig {
            mesh_sample_count: count,
            view_margin_fraction: 0.0,
            ..IcpConfig::default()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let cloud =
            sample_mesh_in_view(mesh, camera, cam_from_world, 500.0, &config, &mut rng).unwrap();
        cloud
            .points_local_m()
            .iter()
            .map(|p| cam_from_world.transform_point(&(cloud.origin_m() + p)))
            .collect()
    }

    fn pose_errors(estimate: &Rigid3, truth: &Rigid3) -> (f64, f64) {
        (
            (estimate.camera_center() - truth.camera_center()).norm(),
            estimate.rotation_angle_to_rad(truth),
        )
    }

    #[test]
    fn exact_points_recover_a_known_rigid_transform_with_both_variants() {
        let camera = test_camera();
        for offset in [Vector3::zeros(), UTM_OFFSET_M] {
            let mesh = town(offset);
            let truth = true_pose(offset);
            let initial = perturbed(
                &truth,
                Vector3::new(0.3, -1.0, 0.5),
                1.5f64.to_radians(),
                Vector3::new(0.4, -0.3, 0.25),
            );
            let mut rng = ChaCha8Rng::seed_from_u64(7);
            let config = IcpConfig {
                mesh_sample_count: 20_000,
                max_iterations: 200,
                translation_tolerance_m: 1e-7,
                rotation_tolerance_rad: 1e-8,
                ..IcpConfig::default()
            };
            let model =
                sample_mesh_in_view(&mesh, &camera, &initial, 500.0, &config, &mut rng).unwrap();
            // The photo points are a subset of the model samples (those the true camera sees), so
            // an exact alignment (every distance zero) exists for both error measures.
            let exact_subset: Vec<Vector3<f64>> = model
                .points_local_m()
                .iter()
                .step_by(4)
                .map(|p| truth.transform_point(&(model.origin_m() + p)))
                .filter(|p| {
                    camera
                        .intrinsics
                        .project(p)
                        .is_some_and(|px| camera.contains(&px))
                })
                .collect();
            for variant in [IcpVariant::PointToPoint, IcpVariant::PointToPlane] {
                let config = IcpConfig { variant, ..config };
                let result = align_to_model(&exact_subset, &model, &initial, &config).unwrap();
                let (before_m, before_rad) = pose_errors(&initial, &truth);
                let (centre_m, angle_rad) = pose_errors(&result.cam_from_world, &truth);
                let translation_m = (result.cam_from_world.translation - truth.translation).norm();
                println!(
                    "{variant:?} offset {:.0}: {} iterations, converged {}, centre {before_m:.3} → {centre_m:.2e} m, \
                     angle {before_rad:.4} → {angle_rad:.2e} rad, rms {:.2e} m, inliers {:.3}",
                    offset.norm(),
                    result.iterations,
                    result.converged,
                    result.rms_m,
                    result.inlier_fraction
                );
                assert!(result.converged, "{variant:?}: {result:?}");
                assert!(
                    centre_m < 1e-4 && translation_m < 1e-4,
                    "{variant:?}: {centre_m} m, {translation_m} m"
                );
                assert!(angle_rad < 1e-4, "{variant:?}: {angle_rad} rad");
            }
        }
    }

    #[test]
    fn noisy_points_with_outliers_still_come_close() {
        // Independent surface samples (not the model's), 5 cm Gaussian noise per axis, 10 % gross
        // outliers (clutter 5–20 % of the depth in front of the surface).
        let camera = test_camera();
        let mesh = town(Vector3::zeros());
        let truth = true_pose(Vector3::zeros());
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let noise = Normal::new(0.0, 0.05).unwrap();
        let mut points_cam = photo_points_from_samples(&mesh, &camera, &truth, 8_000, 5);
        for point in &mut points_cam {
            *point += Vector3::new(
                noise.sample(&mut rng),
                noise.sample(&mut rng),
                noise.sample(&mut rng),
            );
        }
        let noisy_cam = points_cam.clone();
        let outlier_count = points_cam.len() / 10;
        for point in points_cam.iter_mut().take(outlier_count) {
            *point *= 1.0 - rng.random_range(0.05..0.2);
        }
        let small = perturbed(
            &truth,
            Vector3::new(-0.5, 0.2, 1.0),
            0.5f64.to_radians(),
            Vector3::new(-0.15, 0.12, -0.08),
        );
        let large = perturbed(
            &truth,
            Vector3::new(-0.5, 0.2, 1.0),
            2f64.to_radians(),
            Vector3::new(-0.6, 0.5, -0.3),
        );
        for (variant, initial, points_cam) in [
            (IcpVariant::PointToPoint, &small, &noisy_cam),
            (IcpVariant::PointToPoint, &large, &points_cam),
            (IcpVariant::PointToPlane, &small, &points_cam),
            (IcpVariant::PointToPlane, &large, &points_cam),
        ] {
            let config = IcpConfig {
                variant,
                mesh_sample_count: 60_000,
                max_iterations: 200,
                ..IcpConfig::default()
            };
            let mut sample_rng = ChaCha8Rng::seed_from_u64(3);
            let model =
                sample_mesh_in_view(&mesh, &camera, initial, 500.0, &config, &mut sample_rng)
                    .unwrap();
            let result = align_to_model(points_cam, &model, initial, &config).unwrap();
            let (before_m, before_rad) = pose_errors(initial, &truth);
            let (centre_m, angle_rad) = pose_errors(&result.cam_from_world, &truth);
            let mut workspace = ReprojectionWorkspace::new();
            let delta_before_px =
                delta_to_ground_truth_px(&mesh, &camera, initial, &truth, &mut workspace).unwrap();
            let delta_after_px = delta_to_ground_truth_px(
                &mesh,
                &camera,
                &result.cam_from_world,
                &truth,
                &mut workspace,
            )
            .unwrap();
            println!(
                "{variant:?}: δ {delta_before_px:.2} → {delta_after_px:.3} px, centre {before_m:.3} → {centre_m:.4} m, angle {before_rad:.4} → {angle_rad:.5} rad, \
                 {} iterations, rms {:.3} m, inliers {:.3}",
                result.iterations, result.rms_m, result.inlier_fraction
            );
            match variant {
                // Point-to-plane: noise and outliers cost a few millimetres and a hundredth of a
                // pixel.
                IcpVariant::PointToPlane => {
                    assert!(centre_m < 0.02, "{variant:?}: {centre_m} m");
                    assert!(angle_rad < 2e-4, "{variant:?}: {angle_rad} rad");
                    assert!(delta_after_px < 0.1, "{variant:?}: {delta_after_px} px");
                }
                // Point-to-point against independent samples barely moves here: on the ground
                // (most of the points) the nearest-sample residuals are quantisation noise with
                // no tangential pull, and the few wall pairs are the ones trimming drops. What it
                // must not do is diverge under noise and outliers.
                IcpVariant::PointToPoint => {
                    assert!(
                        delta_after_px < 1.1 * delta_before_px,
                        "{variant:?}: {delta_before_px} → {delta_after_px} px"
                    );
                }
            }
        }
    }

    #[test]
    fn depth_maps_back_project_to_camera_points_at_pixel_centres() {
        let camera = Camera::pinhole(
            8,
            6,
            PinholeIntrinsics {
                fx_px: 10.0,
                fy_px: 12.0,
                cx_px: 4.0,
                cy_px: 3.0,
                skew_px: 0.0,
            },
        );
        let mut depth = Image::filled(8, 6, 0.0);
        *depth.get_mut(5, 3).unwrap() = 2.0;
        *depth.get_mut(1, 1).unwrap() = f32::NAN; // a hole in another notation
        let points = back_project_depth(&camera, &depth, 1).unwrap();
        assert_eq!(points.len(), 1);
        let expected = Vector3::new((5.5 - 4.0) / 10.0 * 2.0, (3.5 - 3.0) / 12.0 * 2.0, 2.0);
        assert!((points[0] - expected).norm() < 1e-12, "{:?}", points[0]);
        // Stride 2 samples (1, 1), (3, 1), … (5, 3) included.
        assert_eq!(back_project_depth(&camera, &depth, 2).unwrap().len(), 1);
        // A depth map at half the camera's size uses the rescaled intrinsics.
        let half = Image::filled(4, 3, 1.0);
        let points = back_project_depth(&camera, &half, 1).unwrap();
        assert_eq!(points.len(), 12);
        assert!(
            (points[0] - Vector3::new((0.5 - 2.0) / 5.0, (0.5 - 1.5) / 6.0, 1.0)).norm() < 1e-12
        );
    }

    #[test]
    fn degenerate_inputs_are_errors_not_panics() {
        let camera = test_camera();
        let mesh = town(Vector3::zeros());
        let truth = true_pose(Vector3::zeros());
        let config = IcpConfig::default();
        let mut rng = ChaCha8Rng::seed_from_u64(1);

        let empty = Image::filled(200, 120, 0.0);
        assert_eq!(
            register_depth_to_mesh(&mesh, &camera, &empty, &truth, &config, &mut rng),
            Err(IcpError::EmptyDepth {
                width_px: 200,
                height_px: 120
            })
        );
        let mut sparse = Image::filled(200, 120, 0.0);
        for col in 0..5 {
            *sparse.get_mut(2 + col * 4, 62).unwrap() = 30.0;
        }
        assert_eq!(
            register_depth_to_mesh(&mesh, &camera, &sparse, &truth, &config, &mut rng),
            Err(IcpError::TooFewPoints {
                found: 5,
                required: MIN_CORRESPONDENCES
            })
        );
        let full = Image::filled(200, 120, 40.0);
        let nan_pose = Rigid3::new(truth.rotation, Vector3::new(f64::NAN, 0.0, 0.0));
        assert_eq!(
            register_depth_to_mesh(&mesh, &camera, &full, &nan_pose, &config, &mut rng),
            Err(IcpError::NonFinitePose { which: "initial" })
        );
        // Looking away from the model: nothing to sample.
        let away = Rigid3::look_at(
            &Vector3::new(0.0, 0.0, 60.0),
            &Vector3::new(0.0, 0.0, 100.0),
            &Vector3::y(),
        )
        .unwrap();
        assert_eq!(
            register_depth_to_mesh(&mesh, &camera, &full, &away, &config, &mut rng),
            Err(IcpError::NoMeshSamples)
        );
        // Photo points nowhere near the model: no correspondence survives.
        let far_points = vec![Vector3::new(0.0, 0.0, 5_000.0); 50];
        let model = sample_mesh_in_view(&mesh, &camera, &truth, 100.0, &config, &mut rng).unwrap();
        assert!(matches!(
            align_to_model(&far_points, &model, &truth, &config),
            Err(IcpError::TooFewCorrespondences { iteration: 0, .. })
        ));
        assert!(matches!(
            ModelCloud::new(Vector3::zeros(), vec![Vector3::zeros()], vec![]),
            Err(IcpError::BadModelCloud { .. })
        ));
        assert!(matches!(
            ModelCloud::new(Vector3::zeros(), vec![], vec![]),
            Err(IcpError::NoMeshSamples)
        ));
    }

    #[test]
    fn a_single_plane_does_not_blow_up_point_to_plane() {
        // Only three DoF are constrained by a plane; damping keeps the others where they are.
        let positions = [(-50.0, -50.0), (50.0, -50.0), (50.0, 50.0), (-50.0, 50.0)]
            .map(|(x, y)| Vector3::new(x, y, 0.0));
        let mesh = Mesh::from_world(&positions, vec![[0, 1, 2], [0, 2, 3]], None).unwrap();
        let camera = test_camera();
        let truth = true_pose(Vector3::zeros());
        let points_cam = photo_points_from_samples(&mesh, &camera, &truth, 3_000, 8);
        let initial = perturbed(&truth, Vector3::x(), 0.01, Vector3::new(0.0, 0.0, 0.5));
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let config = IcpConfig::default();
        let model =
            sample_mesh_in_view(&mesh, &camera, &initial, 500.0, &config, &mut rng).unwrap();
        let result = align_to_model(&points_cam, &model, &initial, &config).unwrap();
        assert!(result.cam_from_world.is_finite());
        assert!(result.rms_point_to_plane_m < 1e-6, "{result:?}");
    }

    #[test]
    fn config_is_validated_and_rejects_unknown_fields() {
        assert_eq!(IcpConfig::default().validate(), Ok(()));
        for bad in [
            IcpConfig {
                depth_grid_stride_px: 0,
                ..IcpConfig::default()
            },
            IcpConfig {
                trim_fraction: 0.0,
                ..IcpConfig::default()
            },
            IcpConfig {
                final_max_correspondence_distance_m: 10.0,
                ..IcpConfig::default()
            },
            IcpConfig {
                correspondence_distance_shrink: f64::NAN,
                ..IcpConfig::default()
            },
            IcpConfig {
                max_iterations: 0,
                ..IcpConfig::default()
            },
        ] {
            assert!(
                matches!(bad.validate(), Err(IcpError::InvalidConfig(_))),
                "{bad:?}"
            );
        }
        let config = IcpConfig::default();
        assert_eq!(config.max_correspondence_distance_m(0), 5.0);
        assert_eq!(config.max_correspondence_distance_m(1_000), 0.75);
        let json = serde_json::to_string(&config).unwrap();
        assert_eq!(serde_json::from_str::<IcpConfig>(&json).unwrap(), config);
        let partial: IcpConfig = serde_json::from_str(r#"{"variant": "PointToPoint"}"#).unwrap();
        assert_eq!(partial.variant, IcpVariant::PointToPoint);
        assert!(serde_json::from_str::<IcpConfig>(r#"{"max_iter": 3}"#).is_err());
    }

    #[test]
    fn icp_improves_initial_poses_on_a_synthetic_scene() {
        use crate::io::{colmap, pfm, ply};
        use crate::synth::{generate_scene, SynthConfig};
        let dir = tempfile::tempdir().unwrap();
        let synth = SynthConfig {
            seed: 4,
            image_count: 4,
            supersampling: 1,
            initial_levels_px: vec![30.0],
            ..SynthConfig::default()
        };
        let started = Instant::now();
        generate_scene(&synth, dir.path()).unwrap();
        println!(
            "scene generated in {:.1} s",
            started.elapsed().as_secs_f64()
        );
        let mesh = ply::read_ply(&dir.path().join("model.ply")).unwrap();
        let gt = colmap::read_model(&dir.path().join("gt")).unwrap();
        let initial = colmap::read_model(&dir.path().join("initial/30")).unwrap();
        let mut workspace = ReprojectionWorkspace::new();
        for variant in [IcpVariant::PointToPlane, IcpVariant::PointToPoint] {
            let config = IcpConfig {
                variant,
                ..IcpConfig::default()
            };
            let (mut sum_before, mut sum_after, mut improved) = (0.0, 0.0, 0);
            for (image_gt, image_initial) in gt.images.iter().zip(&initial.images) {
                assert_eq!(image_gt.name, image_initial.name);
                let camera = gt.camera_of(image_gt).unwrap();
                // The exact depth: this tests ICP's mechanics. On the MVS-like depth/ (a third
                // of the pixels, fattened edges) point-to-point ICP only went 120 → 62 px here.
                let depth_path = dir
                    .path()
                    .join(crate::synth::EXACT_DEPTH_DIR)
                    .join(std::path::Path::new(&image_gt.name).with_extension("pfm"));
                let depth = pfm::read_pfm(&depth_path).unwrap();
                // The steps of `register_depth_to_mesh`, timed one by one.
                let initial_pose = &image_initial.cam_from_world;
                let started = Instant::now();
                let points_cam =
                    back_project_depth(camera, &depth, config.depth_grid_stride_px).unwrap();
                let max_depth_m = points_cam.iter().map(|p| p.z).fold(0.0, f64::max);
                let mut rng = ChaCha8Rng::seed_from_u64(u64::from(image_gt.image_id));
                let model = sample_mesh_in_view(
                    &mesh,
                    camera,
                    initial_pose,
                    max_depth_m,
                    &config,
                    &mut rng,
                )
                .unwrap();
                let prepared = Instant::now();
                let result = align_to_model(&points_cam, &model, initial_pose, &config).unwrap();
                let prepare_s = (prepared - started).as_secs_f64();
                let align_s = prepared.elapsed().as_secs_f64();
                let seconds = prepare_s + align_s;
                // The one-call entry point does exactly the same.
                let mut rng = ChaCha8Rng::seed_from_u64(u64::from(image_gt.image_id));
                assert_eq!(
                    register_depth_to_mesh(&mesh, camera, &depth, initial_pose, &config, &mut rng),
                    Ok(result)
                );
                let before = delta_to_ground_truth_px(
                    &mesh,
                    camera,
                    &image_initial.cam_from_world,
                    &image_gt.cam_from_world,
                    &mut workspace,
                )
                .unwrap();
                let after = delta_to_ground_truth_px(
                    &mesh,
                    camera,
                    &result.cam_from_world,
                    &image_gt.cam_from_world,
                    &mut workspace,
                )
                .unwrap();
                println!(
                    "{variant:?} {}: δ {before:.1} → {after:.1} px (success {}), {} iterations, converged {}, \
                     rms {:.3} m, inliers {:.2}, {} photo / {} model points, {:.3} s ({:.3} s points + samples, {:.3} s ICP)",
                    image_gt.name,
                    is_success(Some(after)),
                    result.iterations,
                    result.converged,
                    result.rms_m,
                    result.inlier_fraction,
                    result.photo_point_count,
                    result.model_point_count,
                    seconds,
                    prepare_s,
                    align_s
                );
                sum_before += before;
                sum_after += after;
                improved += usize::from(after < before);
            }
            let count = gt.images.len() as f64;
            println!(
                "{variant:?}: mean δ {:.1} → {:.1} px, {improved} of {} improved",
                sum_before / count,
                sum_after / count,
                gt.images.len()
            );
            assert!(
                sum_after < 0.5 * sum_before,
                "{variant:?}: {sum_before} → {sum_after}"
            );
            assert!(
                2 * improved > gt.images.len(),
                "{variant:?}: {improved} improved"
            );
        }
    }
}
