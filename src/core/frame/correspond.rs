//! Steps "match" and "lift" of one coarse view: SIFT flow between the query and the view's ASG
//! both ways (consistent pixel pairs only), then each pair's rendering pixel lifted onto the mesh
//! (paper §3.2, docs/design.md §2 steps 4–5). The query's features are computed once per frame
//! ([`query_features`]) and serve all its views.

use nalgebra::{Vector2, Vector3};

use super::{CoarseView, RegistrationConfig, RegistrationError, ViewCorrespondences};
use crate::core::camera::Camera;
use crate::core::dense_sift::DenseSiftWorkspace;
use crate::core::flow_consistency::{match_rendering, MatchWorkspace, PixelMatches, QueryFeatures};
use crate::core::image::{ImageError, ImageView};
use crate::core::mesh::Mesh;
use crate::core::raster::NO_FACE;
use crate::core::reprojection::ray_plane_point_cam;
use crate::core::rigid::Rigid3;

/// A coarse view as the flow step reads it: borrowed from a [`CoarseView`] in one process, or
/// from a received flow job in the pipeline. Its three images have the same size (checked by
/// [`ViewRef::new`]).
#[derive(Clone, Copy, Debug)]
pub struct ViewRef<'a> {
    pub coarse_index: usize,
    pub cam_from_world: Rigid3,
    asg: ImageView<'a, f32>,
    depth_m: ImageView<'a, f32>,
    face_index: ImageView<'a, u32>,
}

impl<'a> ViewRef<'a> {
    /// A view of a rendering: its ASG image (0..1), depth along the optical axis (metres) and
    /// face per pixel ([`NO_FACE`] where nothing was hit), all of the same size.
    pub fn new(
        coarse_index: usize,
        cam_from_world: Rigid3,
        asg: ImageView<'a, f32>,
        depth_m: ImageView<'a, f32>,
        face_index: ImageView<'a, u32>,
    ) -> Result<Self, ImageError> {
        let (width_px, height_px) = asg.size();
        depth_m.check_size("the rendered depth", width_px, height_px)?;
        face_index.check_size("the rendered face index", width_px, height_px)?;
        Ok(Self {
            coarse_index,
            cam_from_world,
            asg,
            depth_m,
            face_index,
        })
    }

    pub fn width_px(&self) -> usize {
        self.asg.width_px()
    }

    pub fn height_px(&self) -> usize {
        self.asg.height_px()
    }

    /// ASG image, 0..1.
    pub fn asg(&self) -> ImageView<'a, f32> {
        self.asg
    }

    /// Rendered depth along the optical axis, metres.
    pub fn depth_m(&self) -> ImageView<'a, f32> {
        self.depth_m
    }

    /// Rendered face per pixel ([`NO_FACE`] where nothing was hit).
    pub fn face_index(&self) -> ImageView<'a, u32> {
        self.face_index
    }
}

impl CoarseView {
    /// The view as the flow step reads it.
    pub fn as_ref(&self) -> Result<ViewRef<'_>, ImageError> {
        ViewRef::new(
            self.coarse_index,
            self.cam_from_world,
            self.asg.view(),
            self.render.depth_m().view(),
            self.render.face_index().view(),
        )
    }
}

/// Buffers the flow step reuses from view to view.
#[derive(Debug, Default)]
pub struct CorrespondWorkspace {
    matching: MatchWorkspace,
    matches: PixelMatches,
}

/// The query's features for matching (dense SIFT and pyramid), once per frame.
pub fn query_features(
    query: ImageView<'_, f32>,
    config: &RegistrationConfig,
) -> Result<QueryFeatures, RegistrationError> {
    QueryFeatures::compute(query, &config.matching, &mut DenseSiftWorkspace::default())
        .map_err(|e| RegistrationError::Flow(e.to_string()))
}

/// Steps "match" and "lift" of one view: its 2D–3D correspondences.
pub fn correspond_view(
    mesh: &Mesh,
    camera: &Camera,
    query: &QueryFeatures,
    view: &ViewRef<'_>,
    config: &RegistrationConfig,
    workspace: &mut CorrespondWorkspace,
) -> Result<ViewCorrespondences, RegistrationError> {
    // The validity mask is not passed: with it, SIFT flow lost the true match on every ASG pair
    // with 30–55 px displacement (0 % of pixels within 2 px of the true flow, against 85–96 %
    // without). Invalid pixels have zero ASG, and lifting drops matches that land on them.
    match_rendering(
        query,
        view.asg,
        None,
        &config.matching,
        &mut workspace.matching,
        &mut workspace.matches,
    )
    .map_err(|e| RegistrationError::Flow(e.to_string()))?;
    Ok(lift_matches(mesh, camera, view, &workspace.matches))
}

/// Step "lift": each consistent pixel pair becomes (query pixel, 3D model point): the rendering
/// pixel's ray (through the sub-pixel flow target) meets the plane of the face rendered there.
pub fn lift_matches(
    mesh: &Mesh,
    camera: &Camera,
    view: &ViewRef<'_>,
    dense: &PixelMatches,
) -> ViewCorrespondences {
    let (width, height) = view.asg.size();
    let (face_index, depth_m) = (view.face_index.data(), view.depth_m.data());
    let world_from_cam = view.cam_from_world.inverse();
    let mut out = ViewCorrespondences {
        coarse_index: view.coarse_index,
        coarse_cam_from_world: view.cam_from_world,
        ..ViewCorrespondences::default()
    };
    for pair in &dense.matches {
        let col = pair.rendering_x_px.round();
        let row = pair.rendering_y_px.round();
        if col < 0.0 || row < 0.0 || col >= width as f32 || row >= height as f32 {
            continue;
        }
        let pixel = row as usize * width + col as usize;
        let face_index = face_index[pixel];
        if face_index == NO_FACE {
            continue;
        }
        let normalized = camera.intrinsics.pixel_to_normalized(Vector2::new(
            f64::from(pair.rendering_x_px) + 0.5,
            f64::from(pair.rendering_y_px) + 0.5,
        ));
        let ray_cam = Vector3::new(normalized.x, normalized.y, 1.0);
        let depth_m = f64::from(depth_m[pixel]);
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
        out.world_points_m
            .push(world_from_cam.transform_point(&point_cam));
    }
    out
}
