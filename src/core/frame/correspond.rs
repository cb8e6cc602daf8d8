//! Steps "match" and "lift" of one coarse view: SIFT flow between the query and the view's ASG
//! both ways (consistent pixel pairs only), then each pair's rendering pixel lifted onto the mesh
//! (paper §3.2, docs/design.md §2 steps 4–5). The query's features are computed once per frame
//! ([`query_features`]) and serve all its views.

use nalgebra::{Vector2, Vector3};

use super::{CoarseView, RegistrationConfig, RegistrationError, ViewCorrespondences};
use crate::core::camera::{nearest_pixel, Camera};
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
    Ok(lift_matches(
        mesh,
        camera,
        view,
        &workspace.matches,
        config.lift_edge_margin_px,
    ))
}

/// Step "lift": each consistent pixel pair becomes (query pixel, 3D model point): the rendering
/// pixel's ray (through the sub-pixel flow target) meets the plane of the face rendered there.
pub fn lift_matches(
    mesh: &Mesh,
    camera: &Camera,
    view: &ViewRef<'_>,
    dense: &PixelMatches,
    edge_margin_px: usize,
) -> ViewCorrespondences {
    let world_from_cam = view.cam_from_world.inverse();
    let mut out = ViewCorrespondences {
        coarse_index: view.coarse_index,
        coarse_cam_from_world: view.cam_from_world,
        ..ViewCorrespondences::default()
    };
    for pair in &dense.matches {
        let rendering_px = Vector2::new(
            f64::from(pair.rendering_x_px) + 0.5,
            f64::from(pair.rendering_y_px) + 0.5,
        );
        if edge_margin_px > 0 && is_near_depth_edge(view, rendering_px, edge_margin_px) {
            continue;
        }
        if let Some(point_world) = lift_pixel(mesh, camera, view, &world_from_cam, rendering_px) {
            out.image_points_px.push(Vector2::new(
                f64::from(pair.query_x_px) + 0.5,
                f64::from(pair.query_y_px) + 0.5,
            ));
            out.world_points_m.push(point_world);
        }
    }
    out
}

/// The model point a view sees through `pixel_px` (COLMAP pixel coordinates, sub-pixel): the
/// pixel's ray meets the plane of the face rendered at the nearest pixel centre; world frame.
/// `None` outside the image or where the view shows no surface. `world_from_cam` is the inverse
/// of the view's pose (passed in so that callers lifting many pixels invert it once).
pub fn lift_pixel(
    mesh: &Mesh,
    camera: &Camera,
    view: &ViewRef<'_>,
    world_from_cam: &Rigid3,
    pixel_px: Vector2<f64>,
) -> Option<Vector3<f64>> {
    let (col, row) = nearest_pixel(pixel_px, view.width_px(), view.height_px())?;
    let pixel = row * view.width_px() + col;
    let face_index = view.face_index().data()[pixel];
    if face_index == NO_FACE {
        return None;
    }
    let normalized = camera.intrinsics.pixel_to_normalized(pixel_px);
    let ray_cam = Vector3::new(normalized.x, normalized.y, 1.0);
    let depth_m = f64::from(view.depth_m().data()[pixel]);
    let point_cam = ray_plane_point_cam(
        mesh,
        face_index as usize,
        &view.cam_from_world,
        &ray_cam,
        depth_m,
    )
    .unwrap_or(ray_cam * depth_m);
    Some(world_from_cam.transform_point(&point_cam))
}

/// A depth step above this fraction of the depth between neighbouring rendering pixels is a
/// discontinuity (an occlusion edge), not a slanted surface.
pub const DEPTH_EDGE_RELATIVE_STEP: f32 = 0.02;

/// Whether the rendering pixel nearest `pixel_px` (COLMAP coordinates) has a neighbour within
/// `radius_px` (Chebyshev) on another surface: no surface there, or a depth step above
/// [`DEPTH_EDGE_RELATIVE_STEP`]. Outside the image counts as near an edge.
pub fn is_near_depth_edge(view: &ViewRef<'_>, pixel_px: Vector2<f64>, radius_px: usize) -> bool {
    let (width, height) = (view.width_px(), view.height_px());
    let Some((col, row)) = nearest_pixel(pixel_px, width, height) else {
        return true;
    };
    let (depth_m, face_index) = (view.depth_m().data(), view.face_index().data());
    let centre = depth_m[row * width + col];
    for r in row.saturating_sub(radius_px)..(row + radius_px + 1).min(height) {
        for c in col.saturating_sub(radius_px)..(col + radius_px + 1).min(width) {
            let pixel = r * width + c;
            if face_index[pixel] == NO_FACE
                || (depth_m[pixel] - centre).abs() > DEPTH_EDGE_RELATIVE_STEP * centre
            {
                return true;
            }
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_edges_are_found_within_the_margin_and_not_on_slanted_surfaces() {
        // 8 × 4: columns 0..4 a wall receding from 10.0 m by 0.5 % per pixel (slanted, not an
        // edge), columns 4..7 a wall at 20 m, column 7 shows nothing.
        let (width, height) = (8usize, 4usize);
        let depth_m: Vec<f32> = (0..width * height)
            .map(|i| match i % width {
                c @ 0..4 => 10.0 * (1.0 + 0.005 * c as f32),
                4..7 => 20.0,
                _ => 0.0,
            })
            .collect();
        let face_index: Vec<u32> = (0..width * height)
            .map(|i| if i % width == 7 { NO_FACE } else { 0 })
            .collect();
        let asg = vec![0.0; width * height];
        let image = |data| ImageView::new(width, height, data).unwrap();
        let view = ViewRef::new(
            0,
            Rigid3::identity(),
            image(&asg),
            image(&depth_m),
            ImageView::new(width, height, &face_index).unwrap(),
        )
        .unwrap();
        let at = |col: usize| Vector2::new(col as f64 + 0.5, 1.5);
        assert!(!is_near_depth_edge(&view, at(0), 1));
        assert!(
            !is_near_depth_edge(&view, at(2), 1),
            "a slanted wall is no edge"
        );
        assert!(is_near_depth_edge(&view, at(3), 1), "next to the 20 m wall");
        assert!(is_near_depth_edge(&view, at(2), 2), "two pixels from it");
        assert!(!is_near_depth_edge(&view, at(5), 1));
        assert!(
            is_near_depth_edge(&view, at(6), 1),
            "next to the background"
        );
        assert!(
            is_near_depth_edge(&view, Vector2::new(-3.0, 1.5), 1),
            "outside"
        );
    }
}

#[cfg(test)]
mod workspace_tests {
    use nalgebra::{UnitQuaternion, Vector3};

    use super::*;
    use crate::core::frame::tests::{house_and_poses, ideal_query, view_at};

    /// A view's correspondences do not depend on what the workspace matched before: the
    /// pipeline's flow stage keeps one workspace for every job, one process one per rayon task.
    #[test]
    fn correspondences_do_not_depend_on_the_workspaces_past() {
        let (mesh, camera, truth, initial) = house_and_poses();
        let config = RegistrationConfig::default();
        let query = ideal_query(&mesh, &camera, &truth, &config);
        let features = query_features(query.view(), &config).unwrap();
        let other = Rigid3::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.2, 0.05)) * truth.rotation,
            truth.translation + Vector3::new(2.0, 1.0, 0.0),
        );
        let first = view_at(&mesh, &camera, &other, &config);
        let second = view_at(&mesh, &camera, &initial, &config);
        let fresh = correspond_view(
            &mesh,
            &camera,
            &features,
            &second.as_ref().unwrap(),
            &config,
            &mut CorrespondWorkspace::default(),
        )
        .unwrap();
        let mut reused = CorrespondWorkspace::default();
        correspond_view(
            &mesh,
            &camera,
            &features,
            &first.as_ref().unwrap(),
            &config,
            &mut reused,
        )
        .unwrap();
        let after = correspond_view(
            &mesh,
            &camera,
            &features,
            &second.as_ref().unwrap(),
            &config,
            &mut reused,
        )
        .unwrap();
        assert_eq!(fresh.image_points_px.len(), after.image_points_px.len());
        assert!(fresh == after, "the reused workspace changed the matches");
    }
}
