//! Steps "plan" and "render": the coarse poses around the initial pose (paper §3.1; their spread
//! scales with the scene depth seen from the initial pose) and the ASG rendering of each, and
//! [`render_views`], the order in which a frame's views are made (one process and the render
//! stage both run it): step "search" first ([`super::search::search_pose`]), which may move the
//! centre of the coarse poses away from the initial pose.

use nalgebra::{UnitQuaternion, Vector3};
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

use super::search::{search_pose, PoseSearchOutcome};
use super::{
    frame_rng, CoarseView, RegistrationConfig, RegistrationError, GRADIENT_SCALE_PERCENTILE,
};
use crate::core::camera::Camera;
use crate::core::image::ImageView;
use crate::core::mesh::Mesh;
use crate::core::raster::{Rasterizer, RenderBuffers, NO_FACE};
use crate::core::rigid::Rigid3;
use crate::core::shading::{asg_of_rendering, scale_to_percentile};

/// What [`render_views`] made.
#[derive(Clone, Debug)]
pub struct RenderedViews {
    /// The number of views (`config.coarse_views_per_centre`: `coarse_pose_count` per centre of
    /// the search, the second of two `other_centre_coarse_pose_count`).
    pub count: usize,
    /// What the pose search found (`None` when it is disabled).
    pub search: Option<PoseSearchOutcome>,
    /// The renderings made after the search: one per view (a centre's rendering, made first for
    /// the scene depth that scales its coarse poses, is also its group's first view).
    pub renderings: usize,
}

/// Searches for the centre of the coarse poses (step "search", on the frame's `query`), then
/// plans and renders a frame's coarse views in coarse-pose order, handing each to `emit` with the
/// number of views. `view` is rendered into again for the next one: `emit` reads it, or takes it
/// (`std::mem::take`) to keep it, and the next view is then rendered into fresh buffers.
/// The views come in groups of `config.coarse_pose_count`, one group per centre of the search
/// (one centre unless the search moved, was ambiguous or was blind, [`super::decide`] splits
/// them the same way; the second of two centres has `other_centre_coarse_pose_count` when set); a
/// group's first view is its centre itself (the initial pose unless the search moved it). Each
/// centre's rendering gives the scene depth that scales its coarse poses and is its group's first
/// view (each view is rendered once).
#[allow(clippy::too_many_arguments)]
pub fn render_views(
    mesh: &Mesh,
    camera: &Camera,
    initial_cam_from_world: &Rigid3,
    query: ImageView<'_, f32>,
    config: &RegistrationConfig,
    seed: u64,
    rasterizer: &mut Rasterizer,
    view: &mut CoarseView,
    emit: &mut dyn FnMut(&mut CoarseView, usize),
) -> Result<RenderedViews, RegistrationError> {
    if !initial_cam_from_world.is_finite() {
        return Err(RegistrationError::NonFiniteInitialPose);
    }
    let search = search_pose(
        mesh,
        camera,
        initial_cam_from_world,
        query,
        config,
        rasterizer,
        view,
    );
    let centres = search
        .as_ref()
        .map_or_else(|| vec![*initial_cam_from_world], |s| s.centres.clone());
    // Each centre's own rendering gives the scene depth that scales its coarse poses, and the
    // prior's coarse poses are drawn with the frame's seed wherever it stands among the centres:
    // a prior kept beside a beam gets exactly the coarse poses it has without the search. The
    // first centre is rendered last, so that `view` holds it for the first `emit`.
    // The other centres' renderings are kept: each is also its group's first coarse view.
    let mut median_depths_m = vec![0.0; centres.len()];
    let mut centre_views: Vec<Option<CoarseView>> = vec![None; centres.len()];
    for index in (0..centres.len()).rev() {
        render_coarse_view(mesh, camera, 0, &centres[index], config, rasterizer, view);
        median_depths_m[index] = match median_scene_depth_m(&view.render) {
            Some(depth_m) => depth_m,
            None if index == 0 => return Err(RegistrationError::ModelNotVisible),
            // A centre that sees no surface keeps the first centre's scale (filled below).
            None => f64::NAN,
        };
        if index > 0 {
            centre_views[index] = Some(std::mem::take(view));
        }
    }
    let mut renderings = centres.len();
    let first_depth_m = median_depths_m[0];
    let views_per_centre = config.coarse_views_per_centre(centres.len());
    // Where each centre's group of views starts, in coarse order.
    let group_starts: Vec<usize> = views_per_centre
        .iter()
        .scan(0, |start, count| {
            let this = *start;
            *start += count;
            Some(this)
        })
        .collect();
    let poses: Vec<Rigid3> = centres
        .iter()
        .zip(&median_depths_m)
        .zip(&views_per_centre)
        .enumerate()
        .flat_map(|(index, ((centre, depth_m), &views))| {
            let depth_m = if depth_m.is_finite() {
                *depth_m
            } else {
                first_depth_m
            };
            let centre_seed = if centre == initial_cam_from_world {
                seed
            } else {
                seed.wrapping_add(index as u64)
            };
            let mut poses = coarse_poses(centre, depth_m, config, centre_seed);
            poses.truncate(views);
            poses
        })
        .collect();
    emit(view, poses.len());
    // The other views are rendered a batch at a time, one view per thread (each rendering is
    // parallel inside too, but its bands alone leave the threads waiting on each other), and
    // handed to `emit` in coarse-pose order.
    // A group's first view is its centre (`coarse_poses` starts with it), rendered above.
    let batch_len = rayon::current_num_threads().max(1);
    let mut batch: Vec<(Rasterizer, CoarseView)> = Vec::new();
    for first in (1..poses.len()).step_by(batch_len) {
        let indices = first..(first + batch_len).min(poses.len());
        batch.resize_with(indices.len(), Default::default);
        let mut rendered: Vec<Option<CoarseView>> = indices
            .clone()
            .map(|coarse_index| {
                let centre = group_starts.binary_search(&coarse_index).ok()?;
                centre_views.get_mut(centre)?.take()
            })
            .collect();
        renderings += rendered.iter().filter(|view| view.is_none()).count();
        batch
            .par_iter_mut()
            .zip(rendered.par_iter_mut())
            .zip(indices)
            .for_each(|(((batch_rasterizer, out), centre_view), coarse_index)| {
                match centre_view.take() {
                    Some(centre_view) => {
                        *out = centre_view;
                        out.coarse_index = coarse_index;
                    }
                    None => render_coarse_view(
                        mesh,
                        camera,
                        coarse_index,
                        &poses[coarse_index],
                        config,
                        batch_rasterizer,
                        out,
                    ),
                }
            });
        for (_, rendered) in &mut batch {
            std::mem::swap(view, rendered);
            emit(view, poses.len());
        }
    }
    Ok(RenderedViews {
        count: poses.len(),
        search,
        renderings,
    })
}

/// Median depth of the surface in a rendering, metres; `None` when it shows no surface.
pub fn median_scene_depth_m(buffers: &RenderBuffers) -> Option<f64> {
    let mut depths: Vec<f32> = buffers
        .depth_m()
        .data()
        .iter()
        .zip(buffers.face_index().data())
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

/// Step "plan": the coarse poses around the initial pose (the first is the initial pose).
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

/// Step "render": the ASG rendering of one coarse pose, into a reused view.
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
    asg_of_rendering(
        out.render.normal_cam().view(),
        out.render.depth_m().view(),
        &config.asg,
        &mut out.asg,
    );
    scale_to_percentile(out.asg.data_mut(), GRADIENT_SCALE_PERCENTILE);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::frame::tests::{house_and_poses, ideal_query};
    use crate::core::pose_search::turned_pose;

    /// A prior turned 30° from the truth: the search moves and keeps the prior as a second centre,
    /// so the views come in two groups. Each view is the rendering of its own coarse pose, bit for
    /// bit, and each is rendered once: the second centre's rendering for its scene depth is its
    /// group's first view, not rendered again (one rendering more without that reuse).
    #[test]
    fn each_view_is_its_coarse_pose_rendered_once() {
        let (mesh, camera, truth, _) = house_and_poses();
        let config = RegistrationConfig::default();
        let query = ideal_query(&mesh, &camera, &truth, &config);
        let prior = turned_pose(&truth, 30.0, 0.0, 0.0);
        let mut views: Vec<CoarseView> = Vec::new();
        let rendered = render_views(
            &mesh,
            &camera,
            &prior,
            query.view(),
            &config,
            7,
            &mut Rasterizer::new(),
            &mut CoarseView::default(),
            &mut |view, _| views.push(view.clone()),
        )
        .expect("the house is in view");
        let centres = rendered.search.as_ref().map_or(0, |s| s.centres.len());
        assert_eq!(centres, 2);
        assert_eq!(rendered.count, 2 * config.coarse_pose_count);
        assert_eq!(views.len(), rendered.count);
        assert_eq!(rendered.renderings, rendered.count);
        let mut rasterizer = Rasterizer::new();
        let mut fresh = CoarseView::default();
        for (index, view) in views.iter().enumerate() {
            assert_eq!(view.coarse_index, index);
            render_coarse_view(
                &mesh,
                &camera,
                index,
                &view.cam_from_world,
                &config,
                &mut rasterizer,
                &mut fresh,
            );
            assert_eq!(view.asg.data(), fresh.asg.data(), "view {index}");
            assert_eq!(
                view.render.depth_m().data(),
                fresh.render.depth_m().data(),
                "view {index}"
            );
            assert_eq!(
                view.render.face_index().data(),
                fresh.render.face_index().data(),
                "view {index}"
            );
        }
        let second_centre = &views[config.coarse_pose_count];
        assert_eq!(
            Some(second_centre.cam_from_world),
            rendered.search.map(|s| s.centres[1])
        );
    }

    /// With `other_centre_coarse_pose_count`, the second of two centres gets that many views,
    /// the first of those it has by default (the same poses, bit for bit), each rendered once;
    /// the first centre's group is unchanged.
    #[test]
    fn the_second_centre_gets_its_own_count_of_the_same_poses() {
        let (mesh, camera, truth, _) = house_and_poses();
        let full = RegistrationConfig::default();
        let fewer = RegistrationConfig {
            other_centre_coarse_pose_count: Some(5),
            ..full.clone()
        };
        fewer.validate().expect("5 of 15 is valid");
        let query = ideal_query(&mesh, &camera, &truth, &full);
        let prior = turned_pose(&truth, 30.0, 0.0, 0.0);
        let views_of = |config: &RegistrationConfig| {
            let mut poses: Vec<(usize, Rigid3)> = Vec::new();
            let rendered = render_views(
                &mesh,
                &camera,
                &prior,
                query.view(),
                config,
                7,
                &mut Rasterizer::new(),
                &mut CoarseView::default(),
                &mut |view, _| poses.push((view.coarse_index, view.cam_from_world)),
            )
            .expect("the house is in view");
            (rendered, poses)
        };
        let (rendered_full, poses_full) = views_of(&full);
        let (rendered, poses) = views_of(&fewer);
        assert_eq!(rendered_full.count, 30);
        assert_eq!(rendered.count, 15 + 5);
        assert_eq!(rendered.renderings, rendered.count);
        assert_eq!(poses.len(), rendered.count);
        for (index, (coarse_index, _)) in poses.iter().enumerate() {
            assert_eq!(*coarse_index, index);
        }
        assert_eq!(poses[..20], poses_full[..20]);
        assert_eq!(
            fewer.coarse_views_per_centre(3),
            vec![15, 15, 15],
            "three centres keep the full count (the verdict's groups)"
        );
        let too_many = RegistrationConfig {
            other_centre_coarse_pose_count: Some(16),
            ..full
        };
        assert!(too_many.validate().is_err());
    }
}
