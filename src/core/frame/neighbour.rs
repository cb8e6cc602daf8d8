//! Step "neighbour" (not in the paper; issues #11, #12; docs/measurements.md, twenty-seventh and
//! twenty-eighth sessions): one more hypothesis of a frame's pose, from a frame already registered
//! that sees the same part of the scene. The two frames' query images are matched by the very
//! steps of a coarse view ([`correspond_view`], [`solve_view`]) with the neighbour's query image
//! in place of a rendering, its pixels lifted onto the model rendered at its registered pose: the
//! same world photographed twice, so the model's missing details do not bias the matches (house
//! s1: photo-to-photo flow 67 % within 2 px, photo-to-ASG 30 %). The model still decides
//! ([`check_neighbour_pose`]): the pose must pass the edge gates every accept passes and the
//! rival-basin test. It accepts a frame its own registration did not, and rejects an accepted
//! frame whose pose it contradicts; it never replaces an accepted pose.

use serde::{Deserialize, Serialize};

use super::decide::{rival_rejection, EdgeGates};
use super::refine::{
    aligned_parameters, refine_pose, rival_ends, short_schedule_config, RefineWorkspace,
};
use super::{
    correspond_view, render_coarse_view, solve_view, CoarseView, CorrespondWorkspace,
    IntrinsicsMode, RegistrationConfig, ViewRef,
};
use crate::core::camera::Camera;
use crate::core::edge_align::SupportPeak;
use crate::core::flow_consistency::QueryFeatures;
use crate::core::image::ImageView;
use crate::core::mesh::Mesh;
use crate::core::raster::Rasterizer;
use crate::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};
use crate::core::rigid::Rigid3;
use crate::core::verify::PoseHypothesis;

/// Settings of step "neighbour".
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NeighbourPoseConfig {
    /// Whether batch registration (`register`, `eval`) runs the step (`--neighbours`).
    pub enabled: bool,
    /// A registered frame is a candidate neighbour when its optical axis is within this angle of
    /// the frame's prior axis, degrees.
    pub max_axis_angle_deg: f64,
    /// The nearest this many candidates (camera centres, the frame's prior against the
    /// neighbour's registered pose) are tried, nearest first; the first confirmed pose decides.
    pub candidates: usize,
    /// A frame accepted through a neighbour lends its pose to others only while the chain back
    /// to a frame the model accepted on its own is shorter than this (1: only frames accepted on
    /// their own are neighbours). Each step carries the neighbour's error over.
    pub max_steps: usize,
    /// The neighbour's pose needs at least this RANSAC consensus (inlier matches).
    pub min_consensus: usize,
    /// ... and this share of its matches as inliers.
    pub min_inlier_share: f64,
}

impl Default for NeighbourPoseConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            max_axis_angle_deg: 40.0,
            candidates: 2,
            max_steps: 1,
            min_consensus: 60,
            min_inlier_share: 0.25,
        }
    }
}

/// A frame registered before, as step "neighbour" reads it: its query image (0..1, as
/// [`super::query_gradient`] made it), its camera and its registered pose.
#[derive(Clone, Copy, Debug)]
pub struct RegisteredNeighbour<'a> {
    pub query: ImageView<'a, f32>,
    pub camera: &'a Camera,
    pub cam_from_world: Rigid3,
}

/// The coarse index the neighbour's view is matched and solved under (its own random stream).
pub const NEIGHBOUR_VIEW_INDEX: usize = 1000;

/// Buffers of step "neighbour", reused across frames.
#[derive(Default)]
pub struct NeighbourWorkspace {
    rasterizer: Rasterizer,
    view: CoarseView,
    correspond: CorrespondWorkspace,
    refine: RefineWorkspace,
}

/// The frame's pose from `neighbour`: the frame's query `features` matched with the neighbour's
/// query image, the neighbour's pixels lifted onto the model rendered with its camera at its
/// registered pose, RANSAC and refinement with the frame's `camera` (`intrinsics` as the frame's
/// own views are solved). `Err` says why there is none.
#[allow(clippy::too_many_arguments)]
pub fn pose_from_neighbour(
    mesh: &Mesh,
    camera: &Camera,
    intrinsics: IntrinsicsMode,
    features: &QueryFeatures,
    neighbour: &RegisteredNeighbour<'_>,
    config: &RegistrationConfig,
    seed: u64,
    workspace: &mut NeighbourWorkspace,
) -> Result<PoseHypothesis, String> {
    let size = (camera.width_px as usize, camera.height_px as usize);
    let neighbour_size = (
        neighbour.camera.width_px as usize,
        neighbour.camera.height_px as usize,
    );
    if neighbour.query.size() != neighbour_size || neighbour_size != size {
        return Err(format!(
            "the neighbour's query is {}x{} px and its camera {}x{} px, the frame's {}x{} px: \
             neighbours must share the frame's working size",
            neighbour.query.width_px(),
            neighbour.query.height_px(),
            neighbour_size.0,
            neighbour_size.1,
            size.0,
            size.1
        ));
    }
    render_coarse_view(
        mesh,
        neighbour.camera,
        NEIGHBOUR_VIEW_INDEX,
        &neighbour.cam_from_world,
        config,
        &mut workspace.rasterizer,
        &mut workspace.view,
    );
    let view = ViewRef::new(
        NEIGHBOUR_VIEW_INDEX,
        neighbour.cam_from_world,
        neighbour.query,
        workspace.view.render.depth_m().view(),
        workspace.view.render.face_index().view(),
    )
    .map_err(|e| e.to_string())?;
    let correspondences = correspond_view(
        mesh,
        neighbour.camera,
        features,
        &view,
        config,
        &mut workspace.correspond,
    )
    .map_err(|e| e.to_string())?;
    solve_view(&correspondences, camera, intrinsics, config, seed).hypothesis
}

/// What the model says of a neighbour's pose ([`check_neighbour_pose`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NeighbourCheck {
    pub hypothesis: PoseHypothesis,
    /// Where the photo's edges judged it: the alignment's end from the pose, its support peak
    /// and distance; `None` when it could not be measured.
    pub edges: Option<EdgeEnd>,
    /// δ between it and the frame's own pose (accepted or would-be), px; `None` without one.
    pub apart_px: Option<f64>,
    /// Confirmed, or the first gate it failed.
    pub confirmed: Result<(), String>,
}

/// Where the alignment's short schedule from a neighbour's pose ended, and how the photo's edges
/// see it there.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EdgeEnd {
    pub camera: Camera,
    pub cam_from_world: Rigid3,
    /// δ between it and the neighbour's pose, px.
    pub apart_px: f64,
    pub peak: SupportPeak,
}

/// What a neighbour's pose does to the frame's own decision.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum NeighbourDecision {
    /// The frame's own decision stands (the neighbour's pose is not confirmed, or it agrees with
    /// the accepted pose).
    Keep,
    /// The frame, not accepted on its own, is accepted at the neighbour's pose.
    Accept,
    /// The accepted pose and the confirmed neighbour's pose are `apart_px` apart (at least the
    /// centres' agreement distance): two witnesses contradict each other, the frame is rejected.
    Contradicted { apart_px: f64 },
}

/// Checks a neighbour's pose `hypothesis` of a frame against the model and the frame's own
/// decision (`own`: its accepted pose, or its would-be pose when rejected, `None` without one).
/// Confirmed when its RANSAC consensus reaches `neighbour.min_consensus` and
/// `neighbour.min_inlier_share`, and the photo's edges, where the alignment from it ends
/// ([`confirm`]), pass the gates every accept passes ([`EdgeGates`]: clear of chance, fixing
/// the pose) with no distinct pose the alignment reaches from around that end supported about
/// as well ([`rival_rejection`], the same test as an accepted pose's). The output stays the
/// neighbour's pose: the edges confirm its basin, the photo-to-photo matches place it. Distinct means at least `pose_search.centre_agreement_share` of the compatibility
/// threshold apart, as across the pose search's centres.
#[allow(clippy::too_many_arguments)]
pub fn check_neighbour_pose(
    mesh: &Mesh,
    query: ImageView<'_, f32>,
    intrinsics: IntrinsicsMode,
    hypothesis: &PoseHypothesis,
    own: Result<&PoseHypothesis, Option<&PoseHypothesis>>,
    config: &RegistrationConfig,
    workspace: &mut NeighbourWorkspace,
) -> (NeighbourCheck, NeighbourDecision) {
    let min_apart_px = config.pose_search.centre_agreement_share
        * config.verify.compatible_fraction_of_long_side
        * f64::from(hypothesis.camera.longest_side_px());
    let own_pose = match own {
        Ok(pose) => Some(pose),
        Err(candidate) => candidate,
    };
    let apart_px = own_pose.and_then(|pose| {
        mutual_reprojection_error_px(
            mesh,
            &pose.camera,
            &pose.cam_from_world,
            &hypothesis.camera,
            &hypothesis.cam_from_world,
            &mut ReprojectionWorkspace::new(),
        )
    });
    let mut check = NeighbourCheck {
        hypothesis: *hypothesis,
        edges: None,
        apart_px,
        confirmed: Ok(()),
    };
    check.confirmed = confirm(mesh, query, intrinsics, hypothesis, min_apart_px, config, workspace)
        .map(|end| check.edges = Some(end))
        .map_err(|(end, why)| {
            check.edges = end;
            why
        });
    let decision = match (own, &check.confirmed) {
        (_, Err(_)) => NeighbourDecision::Keep,
        (Err(_), Ok(())) => NeighbourDecision::Accept,
        (Ok(_), Ok(())) => match apart_px {
            Some(apart_px) if apart_px >= min_apart_px => {
                NeighbourDecision::Contradicted { apart_px }
            }
            _ => NeighbourDecision::Keep,
        },
    };
    (check, decision)
}

/// The gates of [`check_neighbour_pose`]. The photo's edges are judged where the alignment's
/// short schedule from the neighbour's pose ends (within `edge_align.short_schedule_radius_px`:
/// the edge support's peak in its basin), as every accepted pose is judged at its refinement's
/// end: a pose off the LoD model's edge peak by the model's own bias (2–5 px on the house), as
/// the neighbour's can be while nearer the truth, would fail the sharpness gates at itself.
/// The end must lie within the centres' agreement distance of the neighbour's pose. Returns
/// the end's support peak and pose when confirmed, else what was measured and the first gate
/// failed.
#[allow(clippy::too_many_arguments)]
fn confirm(
    mesh: &Mesh,
    query: ImageView<'_, f32>,
    intrinsics: IntrinsicsMode,
    hypothesis: &PoseHypothesis,
    min_apart_px: f64,
    config: &RegistrationConfig,
    workspace: &mut NeighbourWorkspace,
) -> Result<EdgeEnd, (Option<EdgeEnd>, String)> {
    let settings = &config.neighbour_pose;
    let inlier_share = hypothesis.consensus as f64 / hypothesis.correspondence_count.max(1) as f64;
    if hypothesis.consensus < settings.min_consensus || inlier_share < settings.min_inlier_share {
        return Err((
            None,
            format!(
                "{} of {} matches agree with it ({:.0} %); at least {} and {:.0} % asked",
                hypothesis.consensus,
                hypothesis.correspondence_count,
                100.0 * inlier_share,
                settings.min_consensus,
                100.0 * settings.min_inlier_share
            ),
        ));
    }
    let short = short_schedule_config(config);
    let refinement = refine_pose(
        mesh,
        &hypothesis.camera,
        query,
        &hypothesis.cam_from_world,
        aligned_parameters(intrinsics),
        short.as_ref().unwrap_or(config),
        &mut workspace.refine,
    )
    .map_err(|why| (None, why))?;
    let (camera, cam_from_world) = refinement.output_pose();
    let end = EdgeEnd {
        peak: refinement.peak,
        apart_px: mutual_reprojection_error_px(
            mesh,
            &hypothesis.camera,
            &hypothesis.cam_from_world,
            &camera,
            &cam_from_world,
            &mut ReprojectionWorkspace::new(),
        )
        .unwrap_or(f64::INFINITY),
        camera,
        cam_from_world,
    };
    if end.apart_px >= min_apart_px {
        let why = format!(
            "the photo's edges fit a pose {:.0} px from it best ({:.0} px make two poses \
             distinct)",
            end.apart_px, min_apart_px
        );
        return Err((Some(end), why));
    }
    let peak = end.peak;
    let gates = EdgeGates::of(Some(&peak), &config.confidence);
    if !gates.clear {
        let why = format!(
            "the photo does not confirm it: {:.0} % of the model's edges on a photo edge, \
             {:.0} % by chance, {:.0} points above chance asked",
            100.0 * peak.at_pose,
            100.0 * peak.far,
            100.0 * config.confidence.min_support_above_chance
        );
        return Err((Some(end), why));
    }
    if !gates.fixed {
        let why = format!(
            "the photo's edges do not fix it (image uncertainty {:.1} px, model {:.2} px, \
             support drop along the least seen direction {:.2} at 12 px, {:.2} at 3 px)",
            gates.image_uncertainty_px,
            gates.delta_uncertainty_px,
            gates.least_seen_drop,
            gates.least_seen_near_drop
        );
        return Err((Some(end), why));
    }
    let at_end = PoseHypothesis {
        camera,
        cam_from_world,
        ..*hypothesis
    };
    let ends = rival_ends(mesh, query, intrinsics, &at_end, config, &mut workspace.refine);
    if let Some(reason) = rival_rejection(
        &ends,
        min_apart_px,
        &peak,
        config.edge_align.rival_share_above_chance,
    ) {
        return Err((Some(end), reason.to_string()));
    }
    Ok(end)
}

/// The registered frames a frame may take a neighbour's pose from, nearest first: those whose
/// optical axis is within `neighbour.max_axis_angle_deg` of the frame's `prior` axis, by the
/// distance between their registered camera centre and the prior's; at most
/// `neighbour.candidates`. `registered` holds (index, pose) of the frames that may lend.
pub fn nearest_neighbours(
    prior: &Rigid3,
    registered: &[(usize, Rigid3)],
    config: &NeighbourPoseConfig,
) -> Vec<usize> {
    let axis = |pose: &Rigid3| pose.rotation.inverse() * nalgebra::Vector3::z();
    let prior_axis = axis(prior);
    let prior_centre = prior.camera_center();
    let max_cos = config.max_axis_angle_deg.to_radians().cos();
    let mut near: Vec<(f64, usize)> = registered
        .iter()
        .filter(|(_, pose)| axis(pose).dot(&prior_axis) >= max_cos)
        .map(|(index, pose)| ((pose.camera_center() - prior_centre).norm(), *index))
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    near.into_iter()
        .take(config.candidates)
        .map(|(_, index)| index)
        .collect()
}

#[cfg(test)]
mod tests {
    use nalgebra::{UnitQuaternion, Vector3};

    use super::*;
    use crate::core::frame::query_features;
    use crate::core::frame::tests::{house_and_poses, ideal_query};

    /// The house seen from its true pose and from a neighbour's about 0.6 m and 2° away (10 px of
    /// δ), each query the model's own ASG there: the neighbour's pose of the frame, with the
    /// neighbour at its true pose, is the truth to a few pixels; the model confirms it, so a frame not accepted on
    /// its own is accepted, an accepted pose it agrees with stands, and one far from it is
    /// contradicted.
    #[test]
    fn a_registered_neighbour_gives_the_true_pose_and_the_model_decides_with_it() {
        let (mesh, camera, truth, _) = house_and_poses();
        let config = RegistrationConfig::default();
        let neighbour_pose = Rigid3::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.035, 0.0)) * truth.rotation,
            truth.translation + Vector3::new(0.5, 0.2, -0.3),
        );
        let query = ideal_query(&mesh, &camera, &truth, &config);
        let neighbour_query = ideal_query(&mesh, &camera, &neighbour_pose, &config);
        let features = query_features(query.view(), &config).unwrap();
        let neighbour = RegisteredNeighbour {
            query: neighbour_query.view(),
            camera: &camera,
            cam_from_world: neighbour_pose,
        };
        let mut workspace = NeighbourWorkspace::default();
        let pose = pose_from_neighbour(
            &mesh,
            &camera,
            IntrinsicsMode::Known,
            &features,
            &neighbour,
            &config,
            7,
            &mut workspace,
        )
        .unwrap();
        let mut reprojection = ReprojectionWorkspace::new();
        let delta_px = mutual_reprojection_error_px(
            &mesh,
            &camera,
            &pose.cam_from_world,
            &camera,
            &truth,
            &mut reprojection,
        )
        .unwrap();
        // The ASG of two viewpoints differs a little (each shows the model's edges as seen from
        // it): about 2 px from a neighbour 2–24 px away, 0.01 px from the true pose itself.
        assert!(delta_px < 3.0, "δ {delta_px:.2} px");

        let decide = |own: Result<&PoseHypothesis, Option<&PoseHypothesis>>,
                      workspace: &mut NeighbourWorkspace| {
            check_neighbour_pose(
                &mesh,
                query.view(),
                IntrinsicsMode::Known,
                &pose,
                own,
                &config,
                workspace,
            )
        };
        let (check, decision) = decide(Err(None), &mut workspace);
        assert_eq!(check.confirmed, Ok(()), "{check:?}");
        assert_eq!(decision, NeighbourDecision::Accept);
        let agreeing = PoseHypothesis {
            cam_from_world: truth,
            ..pose
        };
        assert_eq!(
            decide(Ok(&agreeing), &mut workspace).1,
            NeighbourDecision::Keep
        );
        // An accepted pose 16 px away: beyond the centres' agreement distance (12.6 px).
        let far = PoseHypothesis {
            cam_from_world: Rigid3::new(
                UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.1, 0.0)) * truth.rotation,
                truth.translation,
            ),
            ..pose
        };
        let (check, decision) = decide(Ok(&far), &mut workspace);
        assert!(
            matches!(decision, NeighbourDecision::Contradicted { apart_px } if apart_px > 15.0),
            "{decision:?} {check:?}"
        );
    }

    /// Candidates are the registered frames looking the frame's way, nearest first, at most
    /// `candidates` of them.
    #[test]
    fn nearest_neighbours_look_the_same_way_and_come_nearest_first() {
        let at = |x: f64, yaw_deg: f64| {
            Rigid3::new(
                UnitQuaternion::from_scaled_axis(Vector3::new(0.0, yaw_deg.to_radians(), 0.0)),
                Vector3::new(-x, 0.0, 0.0),
            )
        };
        let prior = at(0.0, 0.0);
        let registered = [
            (0, at(5.0, 0.0)),
            (1, at(1.0, 10.0)),
            (2, at(0.5, 90.0)),
            (3, at(3.0, -20.0)),
        ];
        let config = NeighbourPoseConfig {
            candidates: 2,
            ..NeighbourPoseConfig::default()
        };
        assert_eq!(nearest_neighbours(&prior, &registered, &config), vec![1, 3]);
    }
}
