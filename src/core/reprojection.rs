//! The mutual reprojection error δ(P, P') of paper eq. 5: how far apart, in pixels, two poses put
//! the model points they see. It is both the evaluation metric (docs/design.md §3: every reported error)
//! and the verification measure (docs/design.md §2 step 7: poses with δ below 5 % of the longest image
//! side are compatible), so it lives in one place.
//!
//! `δ(P, P') = ½ (mean_{x∈V} |P(x) − P'(x)| + mean_{x∈V'} |P(x) − P'(x)|)`, where `V` (`V'`) are
//! the model points visible under `P` (`P'`). Choices the paper leaves open:
//! - **Visible points**: the mesh is rendered under the pose (pinhole, the camera's size; lens
//!   distortion is not rasterised, so the visible set is that of the undistorted image); the
//!   surface points seen at the pixel centres of a regular grid (every
//!   [`ReprojectionOptions::grid_stride_px`] pixels, default 4: ~8,700 points at 505×275, dense
//!   enough that δ changes by far less than a pixel against a denser grid, cheap enough for 15
//!   poses per frame) are back-projected to world points in f64. Each point is the exact
//!   intersection of the pixel ray with the plane of the visible triangle (the rendered f32
//!   depth only when that fails), so δ has no depth-quantisation error.
//! - **Projection** uses the full camera ([`Camera::project`], distortion included); the two
//!   poses may have different cameras (unknown intrinsics).
//! - **Points that do not project** under the other pose (behind it or on its image plane) count
//!   with a fixed penalty: the diagonal of the larger of the two images, in pixels. Every
//!   per-point distance is also capped at that penalty: a point off by more than an image
//!   diagonal is simply "nowhere near", and one point near the other camera's image plane must not
//!   make the mean meaningless. So δ can never look small because points failed to project, and
//!   δ ≤ penalty always.
//! - **Empty sets**: when one pose sees nothing, δ is the other term alone (its points are
//!   penalised where they fail); when neither sees the model, there is no δ (`None`).
//!
//! Verification of N poses needs N renderings, not N², through [`visible_points`] once per pose
//! and [`delta_between`] per pair.

use nalgebra::{Vector2, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::camera::Camera;
use super::image::ImageView;
use super::mesh::Mesh;
use super::raster::{Rasterizer, RenderBuffers, RenderOptions, SampleGrid, NO_FACE};
use super::rigid::Rigid3;

/// Errors of the reprojection-error configuration.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ReprojectionError {
    #[error("grid_stride_px must be at least 1 (got 0)")]
    ZeroGridStride,
    #[error("grid samples: {faces} face indices and {depths} depths, expected {expected} of each")]
    GridSampleCount {
        expected: usize,
        faces: usize,
        depths: usize,
    },
}

/// How visible points are sampled.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReprojectionOptions {
    /// Distance between sampled pixel centres along rows and columns, pixels (≥ 1). The grid
    /// starts at `grid_stride_px / 2` in both directions so that it is centred.
    pub grid_stride_px: usize,
    /// How the visibility rendering is done (near plane in metres, culling).
    pub render_options: RenderOptions,
}

impl Default for ReprojectionOptions {
    fn default() -> Self {
        Self {
            grid_stride_px: 4,
            render_options: RenderOptions::default(),
        }
    }
}

impl ReprojectionOptions {
    pub fn validate(&self) -> Result<(), ReprojectionError> {
        if self.grid_stride_px == 0 {
            return Err(ReprojectionError::ZeroGridStride);
        }
        Ok(())
    }
}

/// What computing δ needs between calls: a rasteriser with its scratch (depth and faces only:
/// visible points need no normals) and the render buffers.
pub struct ReprojectionWorkspace {
    rasterizer: Rasterizer,
    buffers: RenderBuffers,
    options: ReprojectionOptions,
}

impl Default for ReprojectionWorkspace {
    fn default() -> Self {
        Self {
            rasterizer: Rasterizer::depth_and_faces_only(),
            buffers: RenderBuffers::default(),
            options: ReprojectionOptions::default(),
        }
    }
}

impl ReprojectionWorkspace {
    /// A workspace with [`ReprojectionOptions::default`].
    pub fn new() -> Self {
        Self::default()
    }

    pub fn with_options(options: ReprojectionOptions) -> Result<Self, ReprojectionError> {
        options.validate()?;
        Ok(Self {
            options,
            ..Self::default()
        })
    }

    pub fn options(&self) -> &ReprojectionOptions {
        &self.options
    }
}

/// The model points one pose sees, with their projections under that pose.
#[derive(Clone, Debug)]
pub struct VisiblePoints {
    camera: Camera,
    cam_from_world: Rigid3,
    points_world_m: Vec<Vector3<f64>>,
    /// `P(x)` for each point, pixels (full camera, distortion included).
    projections_px: Vec<Vector2<f64>>,
}

impl VisiblePoints {
    /// An empty set for `camera` at `cam_from_world` (fill it with [`visible_points_into`]).
    pub fn new(camera: Camera, cam_from_world: Rigid3) -> Self {
        Self {
            camera,
            cam_from_world,
            points_world_m: Vec::new(),
            projections_px: Vec::new(),
        }
    }

    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    pub fn cam_from_world(&self) -> &Rigid3 {
        &self.cam_from_world
    }

    /// The visible model points in world coordinates, metres.
    pub fn points_world_m(&self) -> &[Vector3<f64>] {
        &self.points_world_m
    }

    pub fn len(&self) -> usize {
        self.points_world_m.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points_world_m.is_empty()
    }
}

/// The visible points of each of `poses` (camera, cam_from_world), in order: one rendering each,
/// the renderings in parallel (each thread with a workspace of `workspace`'s options). The sets
/// are those [`visible_points`] gives one at a time.
pub fn visible_points_of_poses(
    mesh: &Mesh,
    poses: &[(&Camera, &Rigid3)],
    workspace: &ReprojectionWorkspace,
) -> Vec<VisiblePoints> {
    poses
        .par_iter()
        .map_init(
            || ReprojectionWorkspace {
                options: workspace.options,
                ..ReprojectionWorkspace::default()
            },
            |thread_workspace, (camera, cam_from_world)| {
                visible_points(mesh, camera, cam_from_world, thread_workspace)
            },
        )
        .collect()
}

/// The visible points of a pose (one rendering).
pub fn visible_points(
    mesh: &Mesh,
    camera: &Camera,
    cam_from_world: &Rigid3,
    workspace: &mut ReprojectionWorkspace,
) -> VisiblePoints {
    let mut visible = VisiblePoints::new(*camera, *cam_from_world);
    visible_points_into(mesh, camera, cam_from_world, workspace, &mut visible);
    visible
}

/// [`visible_points`] into an existing set, reusing its storage.
pub fn visible_points_into(
    mesh: &Mesh,
    camera: &Camera,
    cam_from_world: &Rigid3,
    workspace: &mut ReprojectionWorkspace,
    out: &mut VisiblePoints,
) {
    let (width_px, height_px) = (camera.width_px as usize, camera.height_px as usize);
    let grid = Grid::new(width_px, height_px, workspace.options.grid_stride_px);
    let buffers = &mut workspace.buffers;
    buffers.resize(width_px, height_px);
    // Only the grid's pixels are read: the rendering draws those alone (the same values).
    workspace.rasterizer.render_grid_points(
        mesh,
        &camera.intrinsics,
        cam_from_world,
        &workspace.options.render_options,
        grid.sample,
        buffers,
    );
    let (face_index, depth_m) = (buffers.face_index().data(), buffers.depth_m().data());
    sample_visible_points(mesh, camera, cam_from_world, &grid, out, |pixel, _| {
        (face_index[pixel], depth_m[pixel])
    });
}

/// The visible points of a pose whose rendering is already made: `render` must be `mesh` rendered
/// under `cam_from_world` through `camera`'s intrinsics at its size with `options.render_options`
/// (as the coarse views are), and the set is then the very one [`visible_points`] gives.
/// `None` when `render` does not have the camera's size.
pub fn visible_points_from_render(
    mesh: &Mesh,
    camera: &Camera,
    cam_from_world: &Rigid3,
    render: &RenderBuffers,
    options: &ReprojectionOptions,
) -> Option<VisiblePoints> {
    let samples = GridSamples::from_render(
        render.depth_m().view(),
        render.face_index().view(),
        options.grid_stride_px,
    )?;
    visible_points_from_samples(mesh, camera, cam_from_world, &samples)
}

/// The visible points of a pose from its rendering's [`GridSamples`]: the set
/// [`visible_points_from_render`] gives from that rendering with the samples' grid stride, to
/// the bit (the same sampling, reading the samples instead of the rendering). `None` when the
/// samples are not of the camera's size.
pub fn visible_points_from_samples(
    mesh: &Mesh,
    camera: &Camera,
    cam_from_world: &Rigid3,
    samples: &GridSamples,
) -> Option<VisiblePoints> {
    if (samples.grid.width_px, samples.grid.height_px)
        != (camera.width_px as usize, camera.height_px as usize)
    {
        return None;
    }
    let mut visible = VisiblePoints::new(*camera, *cam_from_world);
    sample_visible_points(
        mesh,
        camera,
        cam_from_world,
        &samples.grid,
        &mut visible,
        |_, sample| (samples.face_index[sample], samples.depth_m[sample]),
    );
    Some(visible)
}

/// The pixel grid visible points are sampled on: the pixel centres of a `width_px × height_px`
/// rendering on the centred [`SampleGrid`] of `stride_px`, row by row.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Grid {
    width_px: usize,
    height_px: usize,
    sample: SampleGrid,
}

impl Grid {
    fn new(width_px: usize, height_px: usize, stride_px: usize) -> Self {
        Self {
            width_px,
            height_px,
            sample: SampleGrid::centred(stride_px),
        }
    }

    /// The rows (or columns) of the grid along a side of `side_px` pixels.
    fn count(&self, side_px: usize) -> usize {
        side_px
            .saturating_sub(self.sample.first_px())
            .div_ceil(self.sample.stride_px())
    }

    /// Grid points in all.
    fn len(&self) -> usize {
        self.count(self.width_px) * self.count(self.height_px)
    }

    /// Each grid point's `(row, col, pixel index, sample index)`, row by row.
    fn points(&self) -> impl Iterator<Item = (usize, usize, usize, usize)> + '_ {
        let (first, stride) = (self.sample.first_px(), self.sample.stride_px());
        let width = self.width_px;
        let cols = self.count(width);
        (first..self.height_px)
            .step_by(stride)
            .enumerate()
            .flat_map(move |(grid_row, row)| {
                (first..width)
                    .step_by(stride)
                    .enumerate()
                    .map(move |(grid_col, col)| {
                        (row, col, row * width + col, grid_row * cols + grid_col)
                    })
            })
    }
}

/// A rendering's face index and depth at the pixel centres of the visible-point grid (every
/// `stride_px`, from `stride_px / 2`, row by row): all that the visible points read of a
/// rendering, so they can be made where the rendering is not ([`visible_points_from_samples`]):
/// the pipeline's flow stage, which has a coarse view's rendering, sends them on to verify for
/// the convergence test, which then renders nothing for that coarse pose.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GridSamples {
    grid: Grid,
    /// Face per sample ([`NO_FACE`] where nothing was hit).
    face_index: Vec<u32>,
    /// Rendered depth along the optical axis per sample, metres.
    depth_m: Vec<f32>,
}

impl GridSamples {
    /// The samples of a rendering's depth and face index (of the same size); `None` when their
    /// sizes differ.
    pub fn from_render(
        depth_m: ImageView<'_, f32>,
        face_index: ImageView<'_, u32>,
        stride_px: usize,
    ) -> Option<Self> {
        let (width_px, height_px) = depth_m.size();
        if face_index.size() != (width_px, height_px) {
            return None;
        }
        let grid = Grid::new(width_px, height_px, stride_px);
        let (faces, depths) = (face_index.data(), depth_m.data());
        let (face_index, depth_m) = grid
            .points()
            .map(|(_, _, pixel, _)| (faces[pixel], depths[pixel]))
            .unzip();
        Some(Self {
            grid,
            face_index,
            depth_m,
        })
    }

    /// Samples received from elsewhere: `face_index` and `depth_m` must each hold
    /// [`GridSamples::sample_count`] values.
    pub fn from_parts(
        width_px: usize,
        height_px: usize,
        stride_px: usize,
        face_index: Vec<u32>,
        depth_m: Vec<f32>,
    ) -> Result<Self, ReprojectionError> {
        if stride_px == 0 {
            return Err(ReprojectionError::ZeroGridStride);
        }
        let grid = Grid::new(width_px, height_px, stride_px);
        let expected = grid.len();
        if face_index.len() != expected || depth_m.len() != expected {
            return Err(ReprojectionError::GridSampleCount {
                expected,
                faces: face_index.len(),
                depths: depth_m.len(),
            });
        }
        Ok(Self {
            grid,
            face_index,
            depth_m,
        })
    }

    /// How many grid samples a `width_px × height_px` rendering has at `stride_px` (≥ 1).
    pub fn sample_count(width_px: usize, height_px: usize, stride_px: usize) -> usize {
        Grid::new(width_px, height_px, stride_px).len()
    }

    pub fn width_px(&self) -> usize {
        self.grid.width_px
    }

    pub fn height_px(&self) -> usize {
        self.grid.height_px
    }

    pub fn stride_px(&self) -> usize {
        self.grid.sample.stride_px()
    }

    /// Face per sample ([`NO_FACE`] where nothing was hit), row by row.
    pub fn face_index(&self) -> &[u32] {
        &self.face_index
    }

    /// Rendered depth per sample, metres, row by row.
    pub fn depth_m(&self) -> &[f32] {
        &self.depth_m
    }

    /// The face indices and depths, row by row.
    pub fn into_parts(self) -> (Vec<u32>, Vec<f32>) {
        (self.face_index, self.depth_m)
    }
}

/// The surface points a rendering shows at the points of `grid`; `sample(pixel index, sample
/// index)` reads the rendering's face index and depth there (from the rendering or from its
/// [`GridSamples`]: one sampling for both, so their sets are the same).
fn sample_visible_points(
    mesh: &Mesh,
    camera: &Camera,
    cam_from_world: &Rigid3,
    grid: &Grid,
    out: &mut VisiblePoints,
    sample: impl Fn(usize, usize) -> (u32, f32),
) {
    out.camera = *camera;
    out.cam_from_world = *cam_from_world;
    out.points_world_m.clear();
    out.projections_px.clear();
    let world_from_cam = cam_from_world.inverse();
    for (row, col, pixel, index) in grid.points() {
        let (face_index, depth_m) = sample(pixel, index);
        if face_index == NO_FACE {
            continue;
        }
        let normalized = camera
            .intrinsics
            .pixel_to_normalized(Vector2::new(col as f64 + 0.5, row as f64 + 0.5));
        let ray_cam = Vector3::new(normalized.x, normalized.y, 1.0);
        let depth_m = f64::from(depth_m);
        let point_cam =
            ray_plane_point_cam(mesh, face_index as usize, cam_from_world, &ray_cam, depth_m)
                .unwrap_or(ray_cam * depth_m);
        let point_world = world_from_cam.transform_point(&point_cam);
        let Some(projection) = project_finite(camera, cam_from_world, &point_world) else {
            continue;
        };
        out.points_world_m.push(point_world);
        out.projections_px.push(projection);
    }
}

/// The point where the camera ray `ray_cam` (z = 1) meets the plane of face `face_index`, in
/// the camera frame; `None` when the ray is (nearly) parallel to the plane or the intersection
/// strays from the rendered depth by more than 1 % (a degenerate face).
pub(crate) fn ray_plane_point_cam(
    mesh: &Mesh,
    face_index: usize,
    cam_from_world: &Rigid3,
    ray_cam: &Vector3<f64>,
    rendered_depth_m: f64,
) -> Option<Vector3<f64>> {
    let face = mesh.faces().get(face_index)?;
    let [a, b, c] = face.map(|v| cam_from_world.transform_point(&mesh.world_position(v as usize)));
    let normal = (b - a).cross(&(c - a));
    let denominator = normal.dot(ray_cam);
    if denominator.abs() <= 1e-12 * normal.norm() * ray_cam.norm() {
        return None;
    }
    let depth_m = normal.dot(&a) / denominator;
    let agrees = (depth_m - rendered_depth_m).abs() <= 0.01 * rendered_depth_m.abs();
    (depth_m.is_finite() && depth_m > 0.0 && agrees).then(|| ray_cam * depth_m)
}

/// `camera.project(cam_from_world · point)`, `None` when behind the camera or not finite.
pub(crate) fn project_finite(
    camera: &Camera,
    cam_from_world: &Rigid3,
    point_world: &Vector3<f64>,
) -> Option<Vector2<f64>> {
    camera
        .project(&cam_from_world.transform_point(point_world))
        .filter(|p| p.x.is_finite() && p.y.is_finite())
}

/// The per-point distance for a point that does not project (and the cap of every distance):
/// the diagonal of the larger image, pixels.
pub fn unprojectable_penalty_px(camera_a: &Camera, camera_b: &Camera) -> f64 {
    let diagonal = |c: &Camera| f64::from(c.width_px).hypot(f64::from(c.height_px));
    diagonal(camera_a).max(diagonal(camera_b))
}

/// Mean over `from`'s points of the distance between their projection under `from`'s pose and
/// under `to`'s pose (penalised/capped as documented in the module); `None` for an empty set.
fn mean_distance_px(from: &VisiblePoints, to: &VisiblePoints, penalty_px: f64) -> Option<f64> {
    if from.is_empty() {
        return None;
    }
    let sum: f64 = from
        .points_world_m
        .iter()
        .zip(&from.projections_px)
        .map(
            |(point, own)| match project_finite(&to.camera, &to.cam_from_world, point) {
                Some(other) => (other - own).norm().min(penalty_px),
                None => penalty_px,
            },
        )
        .sum();
    Some(sum / from.len() as f64)
}

/// δ (paper eq. 5) between two poses from their precomputed visible points; `None` when neither
/// sees the model. Symmetric: `delta_between(a, b) == delta_between(b, a)`.
pub fn delta_between(a: &VisiblePoints, b: &VisiblePoints) -> Option<f64> {
    let penalty_px = unprojectable_penalty_px(&a.camera, &b.camera);
    match (
        mean_distance_px(a, b, penalty_px),
        mean_distance_px(b, a, penalty_px),
    ) {
        (Some(forward), Some(backward)) => Some(0.5 * (forward + backward)),
        (Some(one_way), None) | (None, Some(one_way)) => Some(one_way),
        (None, None) => None,
    }
}

/// The mutual reprojection error δ(P, P') (paper eq. 5) in pixels; `None` when neither pose
/// sees the model. Two renderings; for many poses use [`visible_points`] + [`delta_between`].
pub fn mutual_reprojection_error_px(
    mesh: &Mesh,
    camera_a: &Camera,
    cam_from_world_a: &Rigid3,
    camera_b: &Camera,
    cam_from_world_b: &Rigid3,
    workspace: &mut ReprojectionWorkspace,
) -> Option<f64> {
    let visible_a = visible_points(mesh, camera_a, cam_from_world_a, workspace);
    let visible_b = visible_points(mesh, camera_b, cam_from_world_b, workspace);
    delta_between(&visible_a, &visible_b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::camera::{Distortion, PinholeIntrinsics};
    use nalgebra::{UnitQuaternion, Vector3};

    /// A 200 m × 200 m plane at z = `depth_m` facing a camera at the origin looking along +z,
    /// shifted by `offset` (both the plane and the cameras move with it in georeferenced tests).
    fn fronto_parallel_plane(depth_m: f64, offset: Vector3<f64>) -> Mesh {
        let corners = [
            (-100.0, -100.0),
            (100.0, -100.0),
            (100.0, 100.0),
            (-100.0, 100.0),
        ]
        .map(|(x, y)| Vector3::new(x, y, depth_m) + offset);
        Mesh::from_world(&corners, vec![[0, 2, 1], [0, 3, 2]], None).unwrap()
    }

    /// A ground plane with a box on it, seen obliquely: depth varies, occlusions exist.
    fn box_on_ground() -> Mesh {
        let mut positions = vec![
            Vector3::new(-60.0, -60.0, 0.0),
            Vector3::new(60.0, -60.0, 0.0),
            Vector3::new(60.0, 60.0, 0.0),
            Vector3::new(-60.0, 60.0, 0.0),
        ];
        let mut faces = vec![[0, 1, 2], [0, 2, 3]];
        let (lo, hi, top) = (-8.0, 8.0, 12.0);
        let base = positions.len() as u32;
        for z in [0.0, top] {
            positions.extend([
                Vector3::new(lo, lo, z),
                Vector3::new(hi, lo, z),
                Vector3::new(hi, hi, z),
                Vector3::new(lo, hi, z),
            ]);
        }
        faces.push([base + 4, base + 5, base + 6]);
        faces.push([base + 4, base + 6, base + 7]);
        for i in 0..4u32 {
            let j = (i + 1) % 4;
            faces.push([base + i, base + j, base + 4 + j]);
            faces.push([base + i, base + 4 + j, base + 4 + i]);
        }
        Mesh::from_world(&positions, faces, None).unwrap()
    }

    fn oblique_pose(eye: Vector3<f64>) -> Rigid3 {
        Rigid3::look_at(&eye, &Vector3::new(0.0, 0.0, 0.0), &Vector3::z()).unwrap()
    }

    fn camera(width: u32, height: u32, focal_px: f64) -> Camera {
        Camera::pinhole(
            width,
            height,
            PinholeIntrinsics::centered(focal_px, width, height),
        )
    }

    #[test]
    fn identical_poses_have_zero_error() {
        let mesh = box_on_ground();
        let camera = camera(160, 90, 120.0);
        let pose = oblique_pose(Vector3::new(40.0, -50.0, 60.0));
        let mut workspace = ReprojectionWorkspace::new();
        let delta =
            mutual_reprojection_error_px(&mesh, &camera, &pose, &camera, &pose, &mut workspace)
                .unwrap();
        assert_eq!(delta, 0.0);
        assert!(visible_points(&mesh, &camera, &pose, &mut workspace).len() > 500);
    }

    #[test]
    fn sideways_translation_over_a_fronto_parallel_plane_gives_f_delta_over_z() {
        let (focal_px, depth_m, shift_m) = (100.0, 8.0, 0.37);
        for offset in [
            Vector3::zeros(),
            Vector3::new(512_345.0, 5_401_234.0, 250.0),
        ] {
            let mesh = fronto_parallel_plane(depth_m, offset);
            let camera = camera(120, 80, focal_px);
            let pose_a = Rigid3::new(UnitQuaternion::identity(), -offset);
            let centre_b = offset + Vector3::new(shift_m, 0.0, 0.0);
            let pose_b = Rigid3::new(UnitQuaternion::identity(), -centre_b);
            let mut workspace = ReprojectionWorkspace::new();
            let delta = mutual_reprojection_error_px(
                &mesh,
                &camera,
                &pose_a,
                &camera,
                &pose_b,
                &mut workspace,
            )
            .unwrap();
            let expected = focal_px * shift_m / depth_m;
            // Georeferenced coordinates cost precision in the f64 pose (5e6 m · 1e-16).
            let tolerance = if offset == Vector3::zeros() {
                1e-9
            } else {
                1e-7
            };
            assert!(
                ((delta - expected) / expected).abs() < tolerance,
                "offset {offset:?}: {delta} vs {expected}"
            );
            // Every grid pixel sees the plane: 30 × 20 points at stride 4.
            assert_eq!(
                visible_points(&mesh, &camera, &pose_a, &mut workspace).len(),
                600
            );
        }
    }

    #[test]
    fn delta_is_symmetric_also_between_different_cameras() {
        let mesh = box_on_ground();
        let camera_a = camera(160, 90, 120.0);
        let mut camera_b = Camera::pinhole(
            150,
            100,
            PinholeIntrinsics {
                fx_px: 130.0,
                fy_px: 128.0,
                cx_px: 74.0,
                cy_px: 51.0,
                skew_px: 0.3,
            },
        );
        camera_b.distortion = Distortion::Radial2 {
            k1: -0.05,
            k2: 0.01,
        };
        let pose_a = oblique_pose(Vector3::new(40.0, -50.0, 60.0));
        let pose_b = oblique_pose(Vector3::new(45.0, -42.0, 63.0));
        let mut workspace = ReprojectionWorkspace::new();
        let ab = mutual_reprojection_error_px(
            &mesh,
            &camera_a,
            &pose_a,
            &camera_b,
            &pose_b,
            &mut workspace,
        )
        .unwrap();
        let ba = mutual_reprojection_error_px(
            &mesh,
            &camera_b,
            &pose_b,
            &camera_a,
            &pose_a,
            &mut workspace,
        )
        .unwrap();
        assert_eq!(ab, ba);
        assert!(ab > 1.0, "{ab}");
        // The precomputed path gives the same number.
        let visible_a = visible_points(&mesh, &camera_a, &pose_a, &mut workspace);
        let visible_b = visible_points(&mesh, &camera_b, &pose_b, &mut workspace);
        assert_eq!(delta_between(&visible_a, &visible_b), Some(ab));
    }

    #[test]
    fn a_rotation_about_the_camera_centre_matches_the_homography_directly() {
        // Under a pure rotation the displacement of a point depends only on its pixel:
        // P'(x) = K R K^-1 p. So δ is a mean over the sampled pixel centres, no depth involved.
        let mesh = fronto_parallel_plane(10.0, Vector3::zeros());
        let (width, height, focal_px) = (120u32, 80u32, 90.0);
        let camera = camera(width, height, focal_px);
        let pose_a = Rigid3::identity();
        let rotation = UnitQuaternion::from_euler_angles(0.02, -0.03, 0.05);
        let pose_b = Rigid3::new(rotation, Vector3::zeros());
        let mut workspace = ReprojectionWorkspace::new();
        let delta =
            mutual_reprojection_error_px(&mesh, &camera, &pose_a, &camera, &pose_b, &mut workspace)
                .unwrap();

        let k = camera.intrinsics;
        let mean_shift = |r: &UnitQuaternion<f64>| {
            let mut sum = 0.0;
            let mut count = 0;
            for row in (2..height as usize).step_by(4) {
                for col in (2..width as usize).step_by(4) {
                    let pixel = Vector2::new(col as f64 + 0.5, row as f64 + 0.5);
                    let ray = k.pixel_to_normalized(pixel);
                    let rotated = r * Vector3::new(ray.x, ray.y, 1.0);
                    let moved = k.project(&rotated).unwrap();
                    sum += (moved - pixel).norm();
                    count += 1;
                }
            }
            sum / f64::from(count)
        };
        // V: a's pixels mapped by R; V': b's pixels mapped back by R^-1.
        let expected = 0.5 * (mean_shift(&rotation) + mean_shift(&rotation.inverse()));
        assert!(
            ((delta - expected) / expected).abs() < 1e-9,
            "{delta} vs {expected}"
        );
        assert!(expected > 3.0);
    }

    #[test]
    fn points_behind_the_other_camera_count_with_the_full_penalty() {
        // A small square in front of camera a; camera b at the same place looks the other way:
        // it sees nothing, and everything a sees is behind it.
        let mesh = fronto_parallel_plane(5.0, Vector3::zeros());
        let camera = camera(100, 60, 80.0);
        let pose_a = Rigid3::identity();
        let pose_b = Rigid3::new(
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI),
            Vector3::zeros(),
        );
        let mut workspace = ReprojectionWorkspace::new();
        assert!(visible_points(&mesh, &camera, &pose_b, &mut workspace).is_empty());
        let delta =
            mutual_reprojection_error_px(&mesh, &camera, &pose_a, &camera, &pose_b, &mut workspace)
                .unwrap();
        let penalty = unprojectable_penalty_px(&camera, &camera);
        assert_eq!(penalty, 100f64.hypot(60.0));
        assert!(
            (delta - penalty).abs() < 1e-9 * penalty,
            "{delta} vs {penalty}"
        );
    }

    #[test]
    fn no_delta_when_neither_pose_sees_the_model() {
        let mesh = fronto_parallel_plane(5.0, Vector3::zeros());
        let camera = camera(100, 60, 80.0);
        let away = Rigid3::new(
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI),
            Vector3::zeros(),
        );
        let also_away = Rigid3::new(
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI - 0.1),
            Vector3::zeros(),
        );
        let mut workspace = ReprojectionWorkspace::new();
        assert_eq!(
            mutual_reprojection_error_px(
                &mesh,
                &camera,
                &away,
                &camera,
                &also_away,
                &mut workspace
            ),
            None
        );
    }

    #[test]
    fn a_zero_grid_stride_is_rejected_and_options_round_trip() {
        let options = ReprojectionOptions {
            grid_stride_px: 0,
            ..ReprojectionOptions::default()
        };
        assert_eq!(
            ReprojectionWorkspace::with_options(options).err(),
            Some(ReprojectionError::ZeroGridStride)
        );
        let json = serde_json::to_string(&ReprojectionOptions::default()).unwrap();
        let back: ReprojectionOptions = serde_json::from_str(&json).unwrap();
        assert_eq!(back, ReprojectionOptions::default());
        assert!(serde_json::from_str::<ReprojectionOptions>(r#"{"grid_stride":4}"#).is_err());
    }

    #[test]
    fn a_denser_grid_changes_delta_by_a_small_fraction() {
        let mesh = box_on_ground();
        let camera = camera(200, 110, 150.0);
        let pose_a = oblique_pose(Vector3::new(40.0, -50.0, 60.0));
        let pose_b = oblique_pose(Vector3::new(43.0, -47.0, 61.0));
        let delta_with_stride = |grid_stride_px| {
            let mut workspace = ReprojectionWorkspace::with_options(ReprojectionOptions {
                grid_stride_px,
                ..ReprojectionOptions::default()
            })
            .unwrap();
            mutual_reprojection_error_px(&mesh, &camera, &pose_a, &camera, &pose_b, &mut workspace)
                .unwrap()
        };
        let coarse = delta_with_stride(4);
        let dense = delta_with_stride(1);
        println!("delta stride 4: {coarse:.4} px, stride 1: {dense:.4} px");
        assert!(
            ((coarse - dense) / dense).abs() < 0.02,
            "{coarse} vs {dense}"
        );
    }

    /// The visible points made from a rendering's grid samples (as the pipeline's verify makes
    /// them from the flow stage's) are the rendered pose's, to the bit, for any stride and size;
    /// samples of the wrong count or size are refused.
    #[test]
    fn grid_samples_give_the_visible_points_of_the_rendering() {
        let mesh = box_on_ground();
        let narrower = camera(160, 91, 120.0);
        let camera = camera(161, 91, 120.0);
        let pose = oblique_pose(Vector3::new(40.0, -50.0, 60.0));
        let mut render = RenderBuffers::new(161, 91);
        for grid_stride_px in [1, 3, 4, 7] {
            let options = ReprojectionOptions {
                grid_stride_px,
                ..ReprojectionOptions::default()
            };
            let mut workspace = ReprojectionWorkspace::with_options(options).unwrap();
            let rendered = visible_points(&mesh, &camera, &pose, &mut workspace);
            Rasterizer::new().render(
                &mesh,
                &camera.intrinsics,
                &pose,
                &options.render_options,
                &mut render,
            );
            let samples = GridSamples::from_render(
                render.depth_m().view(),
                render.face_index().view(),
                grid_stride_px,
            )
            .unwrap();
            let loops = (grid_stride_px / 2..91).step_by(grid_stride_px).count()
                * (grid_stride_px / 2..161).step_by(grid_stride_px).count();
            assert_eq!(samples.face_index().len(), loops);
            assert_eq!(GridSamples::sample_count(161, 91, grid_stride_px), loops);
            let (face_index, depth_m) = samples.clone().into_parts();
            let received =
                GridSamples::from_parts(161, 91, grid_stride_px, face_index, depth_m).unwrap();
            let from_samples =
                visible_points_from_samples(&mesh, &camera, &pose, &received).unwrap();
            assert!(rendered.len() > 100, "{}", rendered.len());
            assert_eq!(format!("{rendered:?}"), format!("{from_samples:?}"));
            assert!(visible_points_from_samples(&mesh, &narrower, &pose, &received).is_none());
        }
        assert_eq!(
            GridSamples::from_parts(161, 91, 4, vec![0; 3], vec![1.0; 3]),
            Err(ReprojectionError::GridSampleCount {
                expected: 920,
                faces: 3,
                depths: 3,
            })
        );
        assert_eq!(
            GridSamples::from_parts(161, 91, 0, Vec::new(), Vec::new()),
            Err(ReprojectionError::ZeroGridStride)
        );
    }
}
