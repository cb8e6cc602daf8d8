//! Step "neighbour" (not in the paper; issues #11, #12; docs/measurements.md, twenty-seventh and
//! twenty-eighth sessions): one more hypothesis of a frame's pose, from a frame already registered
//! that sees the same part of the scene. The two frames' query images are matched by the very
//! steps of a coarse view ([`correspond_view`], [`solve_view`]) with the neighbour's query image
//! in place of a rendering, its pixels lifted onto the model rendered at its registered pose: the
//! same world photographed twice, so the model's missing details do not bias the matches (house
//! s1: photo-to-photo flow 67 % within 2 px, photo-to-ASG 30 %). The model still decides
//! ([`check_neighbour_pose`]): the pose must pass the edge gates every accept passes and the
//! rival-basin test, or, where the edges clear chance but do not fix the pose, agree with another
//! lender's pose (two photos matched independently: [`NeighbourPoseConfig::two_lenders_confirm`],
//! docs/measurements.md, forty-first session), or, where they are above chance but not clear of
//! it, with two more lenders' poses ([`NeighbourPoseConfig::quorum_lenders`], forty-second
//! session; such a quorum also outweighs a rival basin the edges support as well,
//! [`NeighbourPoseConfig::quorum_outweighs_rival`], forty-third). A neighbour's photo seen from
//! a pose of the frame is seen again from the pose it gave until that stops moving
//! ([`NeighbourPoseConfig::warp_rounds`]). It accepts a frame its own registration did not,
//! and rejects an accepted frame whose pose it contradicts; it never replaces an accepted pose.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::correspond::DEPTH_EDGE_RELATIVE_STEP;
use super::decide::{reject, rival_rejection, EdgeGates};
use super::refine::{rival_ends, seen_steps_at_pose, support_at_pose, RefineWorkspace};
use super::{
    correspond_view, query_features, solve_view, CorrespondWorkspace, IntrinsicsMode,
    RegistrationConfig, ViewRef,
};
use crate::core::camera::{nearest_pixel, pixel_center, Camera};
use crate::core::edge_align::{apply_pose_step, bilinear, pose_step_between, SupportPeak};
use crate::core::flow_consistency::QueryFeatures;
use crate::core::image::{Image, ImageView};
use crate::core::mesh::Mesh;
use crate::core::raster::{Rasterizer, RenderBuffers, NO_FACE};
use crate::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};
use crate::core::rigid::Rigid3;
use crate::core::verify::{PoseHypothesis, RejectionReason, Verdict};

/// Settings of step "neighbour".
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NeighbourPoseConfig {
    /// Whether the step runs (by default): after a batch is registered (`register`, `eval`;
    /// `--no-neighbours` turns it off), and in the pipeline's verify
    /// (`registration.neighbour_pose.enabled`).
    pub enabled: bool,
    /// A registered frame is a candidate neighbour when its optical axis is within this angle of
    /// the frame's prior axis, degrees.
    pub max_axis_angle_deg: f64,
    /// The nearest this many candidates (camera centres, the frame's prior against the
    /// neighbour's registered pose) are tried, nearest first; the first confirmed pose decides.
    pub candidates: usize,
    /// A frame accepted through a neighbour lends its pose to others only while the chain back
    /// to a frame the model accepted on its own is shorter than this (1: only frames accepted on
    /// their own are neighbours). Each step carries the neighbour's error over. Measured over
    /// 14 cells (docs/measurements.md, twenty-eighth session): 2 accepted 5 more frames than 1,
    /// none wrong; the nearest 2 candidates decided every accept that 4 did.
    pub max_steps: usize,
    /// The neighbour's pose needs at least this RANSAC consensus (inlier matches).
    pub min_consensus: usize,
    /// ... and this share of its matches as inliers.
    pub min_inlier_share: f64,
    /// A frame may take the pose of the accepted frames at most this many frames before it in
    /// the feed ([`feed_neighbours`]); the pipeline's verify keeps their query images (0.5 MB
    /// each at 505 × 275) and decides a frame's step once every frame of its window has its
    /// result.
    pub window_frames: usize,
    /// A frame may also take the pose of the frames at most this many after it that the model
    /// accepted on its own ([`feed_neighbours`]): their own decisions do not depend on step
    /// "neighbour", so the rule stays one result whatever the order frames complete in. The
    /// pipeline's verify holds a frame's result until those frames are decided on their own:
    /// this many frames of latency. Without it a pass whose first frames fail and later ones
    /// register lends nothing to its first frames.
    pub lookahead_frames: usize,
    /// In which order batch registration offers frames as neighbours
    /// (`batch::neighbour_pass`); the pipeline's verify always follows [`NeighbourOrder::Feed`].
    pub order: NeighbourOrder,
    /// Whether the neighbour's photo is also brought to the frame's viewpoint through the model
    /// and matched again when as photographed its pose is not confirmed ([`NeighbourWarp`]).
    /// Default [`NeighbourWarp::OwnAndNeighbourPose`]: measured over 14 cells
    /// (docs/measurements.md, thirty-first session) 185 accepted, 146 within 2 px, mean δ
    /// 1.55 px, no false accept, against 169 / 131 / 1.60 px without (`OwnPose` alone: 178 /
    /// 140 / 1.56 px), for 3 % more CPU.
    pub warp: NeighbourWarp,
    /// How many times, at most, a warped view is matched ([`NeighbourWarp`]): seen from the
    /// pose it starts from, then from the pose that gave, while the pose moves at least
    /// [`WARP_STILL_PX`] (1: once). The flow bridges only part of the start's error, so the
    /// pose a warped view gives lies between its start and the truth. Measured over 14 cells
    /// (docs/measurements.md, forty-third session), 3 rounds against 1: 228 → 240 accepted,
    /// 186 → 199 within 2 px, 222 → 234 within 5 px, mean δ 1.33 → 1.26 px, no false accept.
    pub warp_rounds: usize,
    /// What an accepted frame's pose becomes when a confirmed neighbour's pose agrees with it
    /// ([`NeighbourAgreement`]). Default [`NeighbourAgreement::Mean`]: measured over 14 cells
    /// (docs/measurements.md, thirty-second session) 185 accepted, 153 within 2 px, mean δ
    /// 1.41 px, no false accept, against 185 / 146 / 1.55 px keeping the own pose
    /// (`LeastSeen`, over the 13 cells it finished: 125 within 2 px and 1.50 px against 127 and
    /// 1.55 px keeping, 131 and 1.42 px `Mean`).
    pub agreement: NeighbourAgreement,
    /// Whether two lenders that agree confirm a pose the photo's edges clear of chance but do
    /// not fix ([`try_neighbours`]): the pose from one lender, failing only the gate that the
    /// edges fix it, is confirmed when the pose from another lender, failing only that gate
    /// too and not also matched from the frame's own pose ([`Witness::independent_of`]), lies
    /// within the centres' agreement distance of it and no rival basin is supported about as
    /// well. Two photos matched independently place the frame at one pose along the directions
    /// the model's edges leave open. Measured over 14 cells (docs/measurements.md,
    /// forty-first session): 193 → 226 accepted, 167 → 185 within 2 px, mean δ 1.22 → 1.39 px,
    /// no false accept.
    pub two_lenders_confirm: bool,
    /// How many lenders whose poses agree confirm a pose the photo's edges see above chance but
    /// not clear of it (0: never; at least 2 otherwise): each pose from its own lender, at most
    /// one matched from the frame's own pose, every two within the centres' agreement distance,
    /// each with its edge support above chance by at least `quorum_support_share` of the margin
    /// one pose needs alone (`confidence.min_support_above_chance`), and (without
    /// `quorum_outweighs_rival`) no rival basin supported about as well. Independent photos that agree stand in for the margin each
    /// lacks alone: wrong lender poses scatter, correct ones gather at the truth. Measured over
    /// 14 cells (docs/measurements.md, forty-second session), with the group's mean as output:
    /// 226 → 228 accepted, 185 → 186 within 2 px, 215 → 222 within 5 px, mean δ 1.39 → 1.33
    /// px, no false accept (3 lenders, the last witness's pose as output: 229 / 186 / 217 /
    /// 1.42 px; 2 lenders: 232 accepted but 184 within 2 px, 1.48 px). Clear witnesses (failing
    /// only "fixed") count too, so `two_lenders_confirm` false and `quorum_lenders` 2 still
    /// confirm two clear ones. In batch's `set` order the lenders of every round count; in
    /// `feed` order (the pipeline, `register` by default) a frame meets `candidates` lenders,
    /// so 3 needs `candidates` ≥ 3.
    pub quorum_lenders: usize,
    /// The share of `confidence.min_support_above_chance` each pose of a quorum
    /// (`quorum_lenders`) keeps above chance.
    pub quorum_support_share: f64,
    /// Whether a quorum (`quorum_lenders` lenders whose poses agree) confirms its pose without
    /// the rival-basin test, and a try failing only that test (a distinct pose the alignment
    /// reaches from around it is supported about as well) is a witness too. The rival test says
    /// the photo's edges cannot tell two basins apart; independent photos that place the frame
    /// in one of them can. Measured over 14 cells (docs/measurements.md, forty-third session),
    /// with `warp_rounds` 3: 240 → 252 accepted, 199 → 202 within 2 px, 234 → 241 within 5 px,
    /// mean δ 1.26 → 1.41 px (the frames it adds are 2–10 px off), no false accept.
    pub quorum_outweighs_rival: bool,
}

/// What an accepted pose becomes when a confirmed neighbour's pose agrees with it (within the
/// centres' agreement distance): two witnesses of one pose, the own one fixed by the photo's
/// edges (least along the direction they see least), the neighbour's by the photo-to-photo
/// matches through the lender's pose.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NeighbourAgreement {
    /// The own pose stays.
    Keep,
    /// Halfway between the two (rotation and translation steps halved): neither witness's
    /// precision is known per direction, so both weigh the same.
    #[default]
    Mean,
    /// The own pose, moved along the direction its edges see least to where the neighbour's
    /// pose lies along it (the other five directions stay the edges').
    LeastSeen,
}

/// Whether step "neighbour" also matches the neighbour's photo seen from a pose of the frame.
/// As photographed, the flow must bridge the whole viewpoint change between the two frames
/// (SIFT flow bridges a few tens of pixels; Brighton's consecutive photos are 70–300 px apart).
/// Projected onto the model and seen from a pose of the frame ([`warp_to_view`]), the flow
/// bridges only that pose's error, as with a coarse view's rendering, and the neighbour's photo
/// keeps what the model's shading lacks. The photo as photographed is always tried first; the
/// other views ([`NeighbourView`]) only when its pose is not confirmed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NeighbourWarp {
    /// The neighbour's photo as photographed only.
    Off,
    /// Then seen from the frame's own pose (accepted, or would-be when rejected).
    OwnPose,
    /// Then seen from the frame's own pose, and from the pose the photo as photographed gave.
    #[default]
    OwnAndNeighbourPose,
}

/// Where a neighbour's photo was matched from ([`NeighbourWarp`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NeighbourView {
    /// As photographed, at the neighbour's pose.
    #[default]
    AsPhotographed,
    /// Seen from the frame's own pose.
    OwnPose,
    /// Seen from the pose the photo as photographed gave.
    NeighbourPose,
}

/// The order in which a batch's frames lend their poses (step "neighbour").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NeighbourOrder {
    /// A feed: a frame borrows from the frames before it ([`feed_neighbours`]), as the
    /// pipeline's verify does, so `register` and `run` give one result.
    #[default]
    Feed,
    /// A collection without an order: every accepted frame lends to every other, in rounds of
    /// steps from the frames the model accepted on their own.
    Set,
}

impl Default for NeighbourPoseConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            max_axis_angle_deg: 40.0,
            candidates: 2,
            max_steps: 2,
            min_consensus: 60,
            min_inlier_share: 0.25,
            window_frames: 64,
            lookahead_frames: 4,
            order: NeighbourOrder::Feed,
            warp: NeighbourWarp::OwnAndNeighbourPose,
            warp_rounds: 3,
            agreement: NeighbourAgreement::Mean,
            two_lenders_confirm: true,
            quorum_lenders: 3,
            quorum_support_share: 0.5,
            quorum_outweighs_rival: true,
        }
    }
}

/// A frame registered before, as step "neighbour" reads it: its query image (0..1, as
/// [`super::query_gradient`] made it), its camera and its registered pose.
#[derive(Clone, Copy, Debug)]
pub struct RegisteredNeighbour<'a> {
    /// Which frame it is, as the caller numbers them: two lenders are one when their ids are,
    /// across every call of [`try_neighbours`] that shares a pool of [`Witness`]es.
    pub id: usize,
    pub query: ImageView<'a, f32>,
    pub camera: &'a Camera,
    pub cam_from_world: Rigid3,
}

/// The coarse index the neighbour's view is matched and solved under (its own random stream).
pub const NEIGHBOUR_VIEW_INDEX: usize = 1000;

/// The coarse index of the neighbour's photo seen from a pose of the frame ([`warp_to_view`]).
pub const WARPED_NEIGHBOUR_VIEW_INDEX: usize = 1001;

/// Buffers of step "neighbour", reused across frames.
pub struct NeighbourWorkspace {
    /// Depth and faces only: the step reads no normal map and no ASG of its renderings.
    rasterizer: Rasterizer,
    /// The model rendered at the neighbour's pose.
    neighbour_render: RenderBuffers,
    correspond: CorrespondWorkspace,
    refine: RefineWorkspace,
    warped: WarpedView,
    /// For δ between two poses of the frame ([`apart_px`]; the warped rounds' moves).
    reprojection: ReprojectionWorkspace,
}

impl Default for NeighbourWorkspace {
    fn default() -> Self {
        Self {
            rasterizer: Rasterizer::depth_and_faces_only(),
            neighbour_render: RenderBuffers::default(),
            correspond: CorrespondWorkspace::default(),
            refine: RefineWorkspace::default(),
            warped: WarpedView::default(),
            reprojection: ReprojectionWorkspace::default(),
        }
    }
}

/// The neighbour's photo seen from a pose of the frame ([`warp_to_view`]).
#[derive(Default)]
pub struct WarpedView {
    /// The model rendered at the frame's pose.
    render: RenderBuffers,
    /// The neighbour's query image at the pixels of `render` the neighbour sees, else 0.
    image: Image<f32>,
    /// `render`'s faces at those pixels, else [`NO_FACE`] (the lift drops matches there).
    face_index: Image<u32>,
}

/// A model point seen by the view counts as seen by the neighbour when its depth there is within
/// this fraction of the neighbour's rendered depth at its projection (the lift's depth-step
/// threshold, [`super::correspond::DEPTH_EDGE_RELATIVE_STEP`], doubled for the nearest-pixel lookup).
const WARP_VISIBILITY_RELATIVE_DEPTH: f64 = 2.0 * DEPTH_EDGE_RELATIVE_STEP as f64;

/// Brings `neighbour`'s query image to the view of `out.render` (the caller's rendering of the
/// model through `camera` at `cam_from_world`): each pixel's model point is projected into the
/// neighbour; where the neighbour sees that point (its rendering `neighbour_render` has it in
/// front, within [`WARP_VISIBILITY_RELATIVE_DEPTH`]) the pixel takes the neighbour's query image
/// there (bilinear), elsewhere 0 and no face. Returns how many pixels the neighbour sees.
pub fn warp_to_view(
    camera: &Camera,
    cam_from_world: &Rigid3,
    neighbour: &RegisteredNeighbour<'_>,
    neighbour_render: &RenderBuffers,
    out: &mut WarpedView,
) -> usize {
    let (width_px, height_px) = (camera.width_px as usize, camera.height_px as usize);
    out.image.reset(width_px, height_px, 0.0);
    out.face_index.reset(width_px, height_px, NO_FACE);
    let neighbour_from_cam = neighbour.cam_from_world.compose(&cam_from_world.inverse());
    let (neighbour_width_px, neighbour_height_px) = neighbour.query.size();
    let depth_m = out.render.depth_m().data();
    let faces = out.render.face_index().data();
    let neighbour_depth_m = neighbour_render.depth_m().data();
    let neighbour_faces = neighbour_render.face_index().data();
    let mut seen = 0;
    for row in 0..height_px {
        for col in 0..width_px {
            let pixel = row * width_px + col;
            if faces[pixel] == NO_FACE {
                continue;
            }
            let normalized = camera
                .intrinsics
                .pixel_to_normalized(pixel_center(col, row));
            let point_cam =
                Vector3::new(normalized.x, normalized.y, 1.0) * f64::from(depth_m[pixel]);
            let point_neighbour = neighbour_from_cam.transform_point(&point_cam);
            let Some(position_px) = neighbour.camera.intrinsics.project(&point_neighbour) else {
                continue;
            };
            let Some((ncol, nrow)) =
                nearest_pixel(position_px, neighbour_width_px, neighbour_height_px)
            else {
                continue;
            };
            let npixel = nrow * neighbour_width_px + ncol;
            let seen_depth_m = f64::from(neighbour_depth_m[npixel]);
            if neighbour_faces[npixel] == NO_FACE
                || (point_neighbour.z - seen_depth_m).abs()
                    > WARP_VISIBILITY_RELATIVE_DEPTH * point_neighbour.z
            {
                continue;
            }
            if let Some(value) = bilinear(&neighbour.query, position_px) {
                out.image.data_mut()[pixel] = value;
                out.face_index.data_mut()[pixel] = faces[pixel];
                seen += 1;
            }
        }
    }
    seen
}

/// The frame's pose from `neighbour`: the frame's query `features` matched with the neighbour's
/// query image, the neighbour's pixels lifted onto the model rendered with its camera at its
/// registered pose, RANSAC and refinement with the frame's `camera` (`intrinsics` as the frame's
/// own views are solved); or, with `seen_from`, matched with the neighbour's photo seen from that
/// pose of the frame ([`warp_to_view`]). `Err` says why there is none.
#[allow(clippy::too_many_arguments)]
pub fn pose_from_neighbour(
    mesh: &Mesh,
    camera: &Camera,
    intrinsics: IntrinsicsMode,
    features: &QueryFeatures,
    neighbour: &RegisteredNeighbour<'_>,
    seen_from: Option<&Rigid3>,
    config: &RegistrationConfig,
    seed: u64,
    workspace: &mut NeighbourWorkspace,
) -> Result<PoseHypothesis, String> {
    render_neighbour(mesh, camera, neighbour, config, workspace)?;
    pose_from_rendered_neighbour(
        mesh, camera, intrinsics, features, neighbour, seen_from, config, seed, workspace,
    )
}

/// The model rendered at the neighbour's pose into `workspace.neighbour_render`, after checking
/// that the neighbour shares the frame's working size.
fn render_neighbour(
    mesh: &Mesh,
    camera: &Camera,
    neighbour: &RegisteredNeighbour<'_>,
    config: &RegistrationConfig,
    workspace: &mut NeighbourWorkspace,
) -> Result<(), String> {
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
    workspace
        .neighbour_render
        .resize(neighbour_size.0, neighbour_size.1);
    workspace.rasterizer.render(
        mesh,
        &neighbour.camera.intrinsics,
        &neighbour.cam_from_world,
        &config.render,
        &mut workspace.neighbour_render,
    );
    Ok(())
}

/// One match of [`pose_from_rendered_neighbour`]: the neighbour's photo as photographed
/// (`seen_from` `None`: lifted on the neighbour's rendering) or seen from `seen_from`
/// ([`warp_to_view`]: lifted on the model rendered there).
#[allow(clippy::too_many_arguments)]
fn pose_from_view_once(
    mesh: &Mesh,
    camera: &Camera,
    intrinsics: IntrinsicsMode,
    features: &QueryFeatures,
    neighbour: &RegisteredNeighbour<'_>,
    seen_from: Option<&Rigid3>,
    config: &RegistrationConfig,
    seed: u64,
    workspace: &mut NeighbourWorkspace,
) -> Result<PoseHypothesis, String> {
    let NeighbourWorkspace {
        rasterizer,
        neighbour_render,
        correspond,
        warped,
        ..
    } = workspace;
    let (view, lift_camera) = match seen_from {
        None => (
            ViewRef::new(
                NEIGHBOUR_VIEW_INDEX,
                neighbour.cam_from_world,
                neighbour.query,
                neighbour_render.depth_m().view(),
                neighbour_render.face_index().view(),
            ),
            neighbour.camera,
        ),
        Some(cam_from_world) => {
            warped
                .render
                .resize(camera.width_px as usize, camera.height_px as usize);
            rasterizer.render(
                mesh,
                &camera.intrinsics,
                cam_from_world,
                &config.render,
                &mut warped.render,
            );
            if warp_to_view(camera, cam_from_world, neighbour, neighbour_render, warped) == 0 {
                return Err("the neighbour sees none of the model seen from there".to_string());
            }
            (
                ViewRef::new(
                    WARPED_NEIGHBOUR_VIEW_INDEX,
                    *cam_from_world,
                    warped.image.view(),
                    warped.render.depth_m().view(),
                    warped.face_index.view(),
                ),
                camera,
            )
        }
    };
    let view = view.map_err(|e| e.to_string())?;
    let correspondences = correspond_view(mesh, lift_camera, features, &view, config, correspond)
        .map_err(|e| e.to_string())?;
    solve_view(&correspondences, camera, intrinsics, config, seed).hypothesis
}

/// A warped view's pose that moved less than this from the pose it was seen from (mutual
/// reprojection, px) ends its rounds ([`NeighbourPoseConfig::warp_rounds`]).
pub const WARP_STILL_PX: f64 = 1.0;

/// [`pose_from_neighbour`] once the neighbour is rendered ([`render_neighbour`]): its photo as
/// photographed (`seen_from` `None`), or seen from `seen_from`, then from the pose that gave,
/// and so on while the pose moves at least [`WARP_STILL_PX`], at most
/// `neighbour_pose.warp_rounds` rounds in all: the last pose a round gave (a round without one
/// ends the rounds).
#[allow(clippy::too_many_arguments)]
fn pose_from_rendered_neighbour(
    mesh: &Mesh,
    camera: &Camera,
    intrinsics: IntrinsicsMode,
    features: &QueryFeatures,
    neighbour: &RegisteredNeighbour<'_>,
    seen_from: Option<&Rigid3>,
    config: &RegistrationConfig,
    seed: u64,
    workspace: &mut NeighbourWorkspace,
) -> Result<PoseHypothesis, String> {
    let once = |from: Option<&Rigid3>, workspace: &mut NeighbourWorkspace| {
        pose_from_view_once(
            mesh, camera, intrinsics, features, neighbour, from, config, seed, workspace,
        )
    };
    let Some(seen_from) = seen_from else {
        return once(None, workspace);
    };
    let mut from = *seen_from;
    let mut last = once(Some(&from), workspace)?;
    for _ in 1..config.neighbour_pose.warp_rounds {
        let moved_px = mutual_reprojection_error_px(
            mesh,
            camera,
            &from,
            camera,
            &last.cam_from_world,
            &mut workspace.reprojection,
        );
        if moved_px.is_none_or(|moved_px| moved_px < WARP_STILL_PX) {
            break;
        }
        from = last.cam_from_world;
        match once(Some(&from), workspace) {
            Ok(hypothesis) => last = hypothesis,
            Err(_) => break,
        }
    }
    Ok(last)
}

/// What the model says of a neighbour's pose ([`check_neighbour_pose`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NeighbourCheck {
    pub hypothesis: PoseHypothesis,
    /// The photo's edge support at the pose and its peak; `None` when it could not be measured.
    pub peak: Option<SupportPeak>,
    /// δ between it and the frame's own pose (accepted or would-be), px; `None` without one.
    pub apart_px: Option<f64>,
    /// Confirmed, or the first gate it failed (for a pose confirmed by another lender's agreeing
    /// pose but then not by the rival test, the rival test's reason).
    pub confirmed: Result<(), String>,
    /// `Some(id)` when confirmed by the agreeing pose of the lender whose
    /// [`RegisteredNeighbour::id`] is `id` rather than by the photo's edges alone
    /// ([`NeighbourPoseConfig::two_lenders_confirm`]).
    #[serde(default)]
    pub agreeing_neighbour: Option<usize>,
}

/// What a neighbour's pose does to the frame's own decision.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum NeighbourDecision {
    /// The frame's own decision stands (the neighbour's pose is not confirmed, or it agrees with
    /// the accepted pose and `neighbour_pose.agreement` keeps the own, or it is confirmed only
    /// by another lender's agreeing pose and lies near the accepted pose).
    Keep,
    /// The frame, not accepted on its own, is accepted at the neighbour's pose.
    Accept,
    /// The accepted pose and the confirmed neighbour's agree; the frame's pose becomes
    /// `cam_from_world`, both combined ([`NeighbourAgreement`]).
    Combine { cam_from_world: Rigid3 },
    /// The accepted pose and the confirmed neighbour's pose are `apart_px` apart (at least the
    /// centres' agreement distance): two confirmed poses contradict each other, the frame is
    /// rejected.
    Contradicted { apart_px: f64 },
}

/// δ between two poses of the frame ([`mutual_reprojection_error_px`]), px; `None` when
/// neither sees the model.
fn apart_px(
    mesh: &Mesh,
    a: &PoseHypothesis,
    b: &PoseHypothesis,
    workspace: &mut ReprojectionWorkspace,
) -> Option<f64> {
    mutual_reprojection_error_px(
        mesh,
        &a.camera,
        &a.cam_from_world,
        &b.camera,
        &b.cam_from_world,
        workspace,
    )
}

/// Two poses of a frame at least this far apart (mutual reprojection, px) are distinct: the
/// pose search's centres' agreement distance.
fn min_apart_px(config: &RegistrationConfig, camera: &Camera) -> f64 {
    config.pose_search.centre_agreement_share * config.verify.compatibility_threshold_px(camera)
}

/// Checks one neighbour's pose `hypothesis` of a frame, alone (another lender's agreeing pose
/// may still confirm it: [`confirm_by_agreement`]), against the model and the frame's own
/// decision (`own`: its accepted pose, or its would-be pose when rejected, `None` without one);
/// returns the check and the gate it failed first, if any ([`neighbour_decision`] says what it
/// does to the frame).
/// Confirmed when its RANSAC consensus reaches `neighbour_pose.min_consensus` and
/// `neighbour_pose.min_inlier_share`, the photo's edges at it pass the gates every accept
/// passes ([`EdgeGates`]: clear of chance, fixing the pose; [`confirm`]) and no distinct pose
/// the alignment reaches from around it is supported about as well ([`rival_rejection`], the
/// same test as an accepted pose's). Distinct means at least `pose_search.centre_agreement_share`
/// of the compatibility threshold apart, as across the pose search's centres.
fn check_neighbour_pose(
    mesh: &Mesh,
    query: ImageView<'_, f32>,
    intrinsics: IntrinsicsMode,
    hypothesis: &PoseHypothesis,
    own: Result<&PoseHypothesis, Option<&PoseHypothesis>>,
    config: &RegistrationConfig,
    workspace: &mut NeighbourWorkspace,
) -> (NeighbourCheck, Option<FailedGate>) {
    let apart_px = own_pose(own)
        .and_then(|pose| apart_px(mesh, pose, hypothesis, &mut workspace.reprojection));
    let (peak, confirmed) = confirm(
        mesh,
        query,
        intrinsics,
        hypothesis,
        min_apart_px(config, &hypothesis.camera),
        config,
        workspace,
    );
    let (confirmed, failed) = match confirmed {
        Ok(()) => (Ok(()), None),
        Err((why, gate)) => (Err(why), Some(gate)),
    };
    let check = NeighbourCheck {
        hypothesis: *hypothesis,
        peak,
        apart_px,
        confirmed,
        agreeing_neighbour: None,
    };
    (check, failed)
}

/// What a checked neighbour's pose does to the frame's own decision `own`.
fn neighbour_decision(
    mesh: &Mesh,
    query: ImageView<'_, f32>,
    own: Result<&PoseHypothesis, Option<&PoseHypothesis>>,
    check: &NeighbourCheck,
    config: &RegistrationConfig,
    workspace: &mut NeighbourWorkspace,
) -> NeighbourDecision {
    match (own, &check.confirmed) {
        (_, Err(_)) => NeighbourDecision::Keep,
        (Err(_), Ok(())) => NeighbourDecision::Accept,
        (Ok(accepted), Ok(())) => match check.apart_px {
            Some(apart_px) if apart_px >= min_apart_px(config, &check.hypothesis.camera) => {
                NeighbourDecision::Contradicted { apart_px }
            }
            // A pose the photo's edges do not fix does not move one they fix.
            _ if check.agreeing_neighbour.is_some() => NeighbourDecision::Keep,
            _ => combined(mesh, query, accepted, &check.hypothesis, config, workspace)
                .map_or(NeighbourDecision::Keep, |cam_from_world| {
                    NeighbourDecision::Combine { cam_from_world }
                }),
        },
    }
}

/// The gate of [`confirm`] a neighbour's pose failed first.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum FailedGate {
    /// Too few RANSAC inliers, or no measurable edge support.
    Evidence,
    /// The photo's edges at it are not clear of chance.
    NotClear,
    /// The photo's edges are clear of chance at it but do not fix it.
    NotFixed,
    /// A distinct pose the alignment reaches from around it is supported about as well.
    Rival,
}

/// A pose of the frame from one lender's photo that the photo's edges support but do not
/// confirm alone: clear of chance but not fixed ([`NeighbourPoseConfig::two_lenders_confirm`]),
/// or only above chance ([`NeighbourPoseConfig::quorum_lenders`]); `lender` is the
/// [`RegisteredNeighbour::id`].
#[derive(Clone, Copy, Debug)]
pub struct Witness {
    lender: usize,
    view: NeighbourView,
    hypothesis: PoseHypothesis,
    /// What the photo's edges say of its pose alone.
    support: WitnessSupport,
}

/// What the photo's edges say of a witness's pose alone: the gate of [`confirm`] it failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum WitnessSupport {
    /// Above chance by `quorum_support_share` of the margin, not clear of chance.
    AboveChance,
    /// Clear of chance, not fixed.
    Clear,
    /// Clear of chance and fixed, but a distinct pose the alignment reaches from around it is
    /// supported about as well (the rival-basin test).
    Contested,
}

impl Witness {
    /// Whether `self` and `other` are independent witnesses: from two lenders, and not both
    /// matched from the frame's own pose ([`NeighbourView::OwnPose`]: where the flow bridges
    /// nothing, both end at the own pose, so their agreement would only repeat it).
    fn independent_of(&self, other: &Witness) -> bool {
        self.lender != other.lender
            && !(self.view == NeighbourView::OwnPose && other.view == NeighbourView::OwnPose)
    }
}

/// The witness `check` makes, if any: a pose that failed only the "fixed" gate (when
/// `two_lenders_confirm` or `quorum_lenders` is set), failed the "clear of chance" gate with
/// its support above chance by the quorum's share of the margin (when `quorum_lenders` is set),
/// or failed only the rival-basin test (when `quorum_lenders` and `quorum_outweighs_rival` are).
fn witness_of(
    check: &NeighbourCheck,
    failed: Option<FailedGate>,
    lender: usize,
    view: NeighbourView,
    config: &RegistrationConfig,
) -> Option<Witness> {
    let settings = &config.neighbour_pose;
    let quorum = settings.quorum_lenders >= 2;
    let support = match failed? {
        FailedGate::NotFixed if settings.two_lenders_confirm || quorum => WitnessSupport::Clear,
        FailedGate::NotClear if quorum => {
            let peak = check.peak.as_ref()?;
            let margin = settings.quorum_support_share * config.confidence.min_support_above_chance;
            if peak.above_chance() < margin {
                return None;
            }
            WitnessSupport::AboveChance
        }
        FailedGate::Rival if quorum && settings.quorum_outweighs_rival => WitnessSupport::Contested,
        _ => return None,
    };
    Some(Witness {
        lender,
        view,
        hypothesis: check.hypothesis,
        support,
    })
}

/// A group of independent witnesses from `witnesses` that agree with `witness` and with each
/// other (every two within `min_apart_px`), `witness` first:
/// each from its own lender, at most one matched from the frame's own pose. Taken in the order
/// given (earliest first); only the witnesses whose support `admits` accepts join.
fn agreeing_group(
    mesh: &Mesh,
    witness: &Witness,
    witnesses: &[Witness],
    min_apart_px: f64,
    admits: impl Fn(WitnessSupport) -> bool,
    wanted: usize,
    reprojection: &mut ReprojectionWorkspace,
) -> Vec<Witness> {
    let mut group = vec![*witness];
    for other in witnesses {
        if group.len() >= wanted {
            break;
        }
        if !admits(other.support) {
            continue;
        }
        // Pairwise independence also keeps at most one view matched from the own pose.
        let joins = group.iter().all(|member| {
            member.independent_of(other)
                && apart_px(mesh, &member.hypothesis, &other.hypothesis, reprojection)
                    .is_some_and(|apart_px| apart_px < min_apart_px)
        });
        if joins {
            group.push(*other);
        }
    }
    group
}

/// The mean of a group's poses: each pose's step from the first ([`pose_step_between`]),
/// averaged and applied to it; `None` for an empty group.
fn mean_pose(group: &[Witness]) -> Option<Rigid3> {
    let first = group.first()?.hypothesis.cam_from_world;
    let sum = group
        .iter()
        .map(|member| pose_step_between(&first, &member.hypothesis.cam_from_world))
        .fold(nalgebra::Vector6::zeros(), |sum, step| sum + step);
    Some(apply_pose_step(&first, &(sum / group.len() as f64)))
}

/// The frame's own pose: accepted, or would-be when rejected; `None` without one.
fn own_pose<'a>(
    own: Result<&'a PoseHypothesis, Option<&'a PoseHypothesis>>,
) -> Option<&'a PoseHypothesis> {
    match own {
        Ok(pose) => Some(pose),
        Err(candidate) => candidate,
    }
}

/// Confirmation by agreement for `check`, the pose of `witness` (its lender's try from its
/// view), which the photo's edges support but do not confirm alone; `witnesses` holds the
/// earlier tries' witnesses of this frame. Confirmed, in this order, when independent witnesses
/// that agree with it and with each other ([`agreeing_group`]) make
/// - a group of `quorum_lenders` of any witnesses, contested ones included, without the rival
///   test ([`NeighbourPoseConfig::quorum_outweighs_rival`]);
/// - a group of two failing only "fixed" ([`NeighbourPoseConfig::two_lenders_confirm`]) or of
///   `quorum_lenders` but no contested ones ([`NeighbourPoseConfig::quorum_lenders`]; the
///   quorum alone without `quorum_outweighs_rival`), when no distinct pose the alignment
///   reaches from around it is supported about as well (the rival test every confirmed pose
///   passes).
///
/// The check's pose becomes the group's mean ([`mean_pose`]; over 14 cells, against the last
/// witness's own pose: mean δ 1.42 → 1.33 px, 217 → 222 within 5 px, one accept fewer;
/// docs/measurements.md, forty-second session). Else it joins `witnesses`, unless the rival
/// test rejected an above-chance one; a clear one the rival test rejected joins as contested
/// (with `quorum_outweighs_rival`). A witness within the centres' agreement distance of an
/// accepted own pose (`own`) is never confirmed: it could only keep that pose, and the lenders
/// after it may still give a pose the edges fix.
#[allow(clippy::too_many_arguments)]
fn confirm_by_agreement(
    mesh: &Mesh,
    query: ImageView<'_, f32>,
    intrinsics: IntrinsicsMode,
    own: Result<&PoseHypothesis, Option<&PoseHypothesis>>,
    mut witness: Witness,
    check: &mut NeighbourCheck,
    witnesses: &mut Vec<Witness>,
    config: &RegistrationConfig,
    workspace: &mut NeighbourWorkspace,
) {
    let hypothesis = witness.hypothesis;
    let min_apart_px = min_apart_px(config, &hypothesis.camera);
    // Near an accepted pose it could only keep it: left unconfirmed, the lenders after it may
    // still give a pose the edges fix, to combine with.
    if own.is_ok()
        && check
            .apart_px
            .is_some_and(|apart_px| apart_px < min_apart_px)
    {
        witnesses.push(witness);
        return;
    }
    let settings = &config.neighbour_pose;
    let quorum = settings.quorum_lenders;
    let confirmed_by =
        |group: &[Witness], check: &mut NeighbourCheck, workspace: &mut NeighbourWorkspace| {
            check.confirmed = Ok(());
            check.agreeing_neighbour = group.get(1).map(|member| member.lender);
            // Independent poses of one frame, averaged: the output is their mean.
            if let Some(mean) = mean_pose(group) {
                check.hypothesis.cam_from_world = mean;
                check.apart_px = own_pose(own).and_then(|pose| {
                    apart_px(mesh, pose, &check.hypothesis, &mut workspace.reprojection)
                });
            }
        };
    let mut group_of = |admits: &dyn Fn(WitnessSupport) -> bool, wanted: usize| {
        let group = agreeing_group(
            mesh,
            &witness,
            witnesses,
            min_apart_px,
            admits,
            wanted,
            &mut workspace.reprojection,
        );
        (group.len() >= wanted).then_some(group)
    };
    // Independent photos that place the frame in one basin decide what the edges cannot.
    if quorum >= 2 && settings.quorum_outweighs_rival {
        if let Some(group) = group_of(&|_| true, quorum) {
            confirmed_by(&group, check, workspace);
            return;
        }
    }
    if witness.support == WitnessSupport::Contested {
        witnesses.push(witness);
        return;
    }
    let pair = (witness.support == WitnessSupport::Clear && settings.two_lenders_confirm)
        .then(|| group_of(&|support| support == WitnessSupport::Clear, 2))
        .flatten();
    let group = pair.or_else(|| {
        (quorum >= 2)
            .then(|| group_of(&|support| support != WitnessSupport::Contested, quorum))
            .flatten()
    });
    // A try that failed "fixed" or "clear" had its edge support measured: `peak` is there.
    let (Some(group), Some(peak)) = (group, check.peak.as_ref()) else {
        witnesses.push(witness);
        return;
    };
    match rival_reason(
        mesh,
        query,
        intrinsics,
        &hypothesis,
        min_apart_px,
        peak,
        config,
        workspace,
    ) {
        Some(why) => {
            check.confirmed = Err(why);
            if witness.support == WitnessSupport::Clear && settings.quorum_outweighs_rival {
                witness.support = WitnessSupport::Contested;
                witnesses.push(witness);
            }
        }
        None => confirmed_by(&group, check, workspace),
    }
}

/// Why `hypothesis` (whose edge support peaks as `peak`) is not confirmed for a rival basin
/// ([`rival_ends`], [`rival_rejection`]), if it is not.
#[allow(clippy::too_many_arguments)]
fn rival_reason(
    mesh: &Mesh,
    query: ImageView<'_, f32>,
    intrinsics: IntrinsicsMode,
    hypothesis: &PoseHypothesis,
    min_apart_px: f64,
    peak: &SupportPeak,
    config: &RegistrationConfig,
    workspace: &mut NeighbourWorkspace,
) -> Option<String> {
    let ends = rival_ends(
        mesh,
        query,
        intrinsics,
        hypothesis,
        config,
        &mut workspace.refine,
    );
    rival_rejection(
        &ends,
        min_apart_px,
        peak,
        config.edge_align.rival_share_above_chance,
    )
    .map(|reason| reason.to_string())
}

/// The accepted pose combined with the agreeing confirmed neighbour's pose as
/// `neighbour_pose.agreement` asks; `None` for [`NeighbourAgreement::Keep`] or when the own
/// pose's edge directions cannot be measured.
fn combined(
    mesh: &Mesh,
    query: ImageView<'_, f32>,
    accepted: &PoseHypothesis,
    neighbours: &PoseHypothesis,
    config: &RegistrationConfig,
    workspace: &mut NeighbourWorkspace,
) -> Option<Rigid3> {
    let own = &accepted.cam_from_world;
    let step = || pose_step_between(own, &neighbours.cam_from_world);
    match config.neighbour_pose.agreement {
        NeighbourAgreement::Keep => None,
        NeighbourAgreement::Mean => Some(apply_pose_step(own, &(step() * 0.5))),
        NeighbourAgreement::LeastSeen => {
            let steps = seen_steps_at_pose(
                mesh,
                &accepted.camera,
                query,
                own,
                config,
                &mut workspace.refine,
            )
            .ok()?;
            let basis = nalgebra::Matrix6::from_columns(&steps);
            let along = basis.try_inverse()? * step();
            Some(apply_pose_step(own, &(steps[0] * along[0])))
        }
    }
}

/// The gates of [`check_neighbour_pose`], the photo's edges judged at the neighbour's pose
/// itself ([`support_at_pose`]): a pose the edges confirm there sits on their sharp peak. Judged
/// instead where the alignment's short schedule from it ends (the peak of its basin, as the
/// frame's own refined poses are judged), 12 more frames were accepted over 14 cells (176
/// against 164) but fewer within 2 px (125 against 127), at a mean δ of 2.01 against 1.60 px
/// (docs/measurements.md, twenty-eighth session): the gates at the pose keep only the
/// neighbour poses that are precise.
/// Returns the support peak when measured, and whether confirmed, else why and the first gate
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
) -> (Option<SupportPeak>, Result<(), (String, FailedGate)>) {
    let settings = &config.neighbour_pose;
    let inlier_share = hypothesis.consensus as f64 / hypothesis.correspondence_count.max(1) as f64;
    if hypothesis.consensus < settings.min_consensus || inlier_share < settings.min_inlier_share {
        let why = format!(
            "{} of {} matches agree with it ({:.0} %); at least {} and {:.0} % asked",
            hypothesis.consensus,
            hypothesis.correspondence_count,
            100.0 * inlier_share,
            settings.min_consensus,
            100.0 * settings.min_inlier_share
        );
        return (None, Err((why, FailedGate::Evidence)));
    }
    let peak = match support_at_pose(
        mesh,
        &hypothesis.camera,
        query,
        &hypothesis.cam_from_world,
        config,
        &mut workspace.refine,
    ) {
        Ok(peak) => peak,
        Err(why) => return (None, Err((why, FailedGate::Evidence))),
    };
    let gates = EdgeGates::of(Some(&peak), &config.confidence);
    if !gates.clear {
        let why = format!(
            "the photo does not confirm it: {:.0} % of the model's edges on a photo edge, \
             {:.0} % by chance, {:.0} points above chance asked",
            100.0 * peak.at_pose,
            100.0 * peak.far,
            100.0 * config.confidence.min_support_above_chance
        );
        return (Some(peak), Err((why, FailedGate::NotClear)));
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
        return (Some(peak), Err((why, FailedGate::NotFixed)));
    }
    let rival = rival_reason(
        mesh,
        query,
        intrinsics,
        hypothesis,
        min_apart_px,
        &peak,
        config,
        workspace,
    );
    (
        Some(peak),
        rival.map_or(Ok(()), |why| Err((why, FailedGate::Rival))),
    )
}

/// One neighbour tried by [`try_neighbours`], from one view: its pose of the frame and the
/// model's check, or why there is no pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NeighbourTry {
    /// Which of the neighbours it is (their index).
    pub neighbour: usize,
    /// Where the neighbour's photo was matched from.
    pub view: NeighbourView,
    pub check: Result<NeighbourCheck, String>,
    pub decision: NeighbourDecision,
}

impl NeighbourTry {
    /// A try of neighbour `neighbour` from `view` that gave no pose, and why.
    fn failed(neighbour: usize, view: NeighbourView, why: String) -> Self {
        Self {
            neighbour,
            view,
            check: Err(why),
            decision: NeighbourDecision::Keep,
        }
    }

    pub fn confirmed(&self) -> bool {
        self.check
            .as_ref()
            .is_ok_and(|check| check.confirmed.is_ok())
    }

    /// The [`RegisteredNeighbour::id`] of the lender whose agreeing pose confirmed this one
    /// ([`NeighbourCheck::agreeing_neighbour`]), if any.
    pub fn agreeing_neighbour(&self) -> Option<usize> {
        self.check
            .as_ref()
            .ok()
            .and_then(|check| check.agreeing_neighbour)
    }
}

/// Step "neighbour" for one frame: `neighbours` (nearest first, [`nearest_neighbours`]) tried in
/// order until one's pose is confirmed ([`pose_from_neighbour`], [`check_neighbour_pose`]); each
/// neighbour's photo as photographed first, then from the views `neighbour_pose.warp` adds
/// ([`NeighbourView`]) while none is confirmed. A pose the photo's edges support but do not
/// confirm alone is a [`Witness`] ([`witness_of`]), confirmed when independent lenders' witnesses
/// agree with it ([`confirm_by_agreement`]: [`NeighbourPoseConfig::two_lenders_confirm`],
/// [`NeighbourPoseConfig::quorum_lenders`]): `witnesses` holds those poses of the frame's
/// earlier calls (batch's rounds in [`NeighbourOrder::Set`]; a frame tried once starts
/// empty) and gets this call's. Every try, the deciding one last. `query` is the frame's query
/// image, `own` its own decision's pose (accepted, or would-be when rejected). The one sequence
/// that batch registration and the pipeline's verify run.
#[allow(clippy::too_many_arguments)]
pub fn try_neighbours(
    mesh: &Mesh,
    camera: &Camera,
    intrinsics: IntrinsicsMode,
    query: ImageView<'_, f32>,
    own: Result<&PoseHypothesis, Option<&PoseHypothesis>>,
    neighbours: &[RegisteredNeighbour<'_>],
    witnesses: &mut Vec<Witness>,
    config: &RegistrationConfig,
    seed: u64,
    workspace: &mut NeighbourWorkspace,
) -> Vec<NeighbourTry> {
    let mut tries = Vec::with_capacity(neighbours.len());
    if neighbours.is_empty() {
        return tries;
    }
    let features = match query_features(query, config) {
        Ok(features) => features,
        Err(error) => {
            tries.push(NeighbourTry::failed(
                0,
                NeighbourView::AsPhotographed,
                error.to_string(),
            ));
            return tries;
        }
    };
    let own_pose = own_pose(own).map(|pose| pose.cam_from_world);
    let warp = config.neighbour_pose.warp;
    for (index, neighbour) in neighbours.iter().enumerate() {
        // The neighbour's rendering serves all its views.
        if let Err(why) = render_neighbour(mesh, camera, neighbour, config, workspace) {
            tries.push(NeighbourTry::failed(
                index,
                NeighbourView::AsPhotographed,
                why,
            ));
            continue;
        }
        // Tries the neighbour from `view`; whether it is confirmed, and its pose if any.
        let mut attempt = |view: NeighbourView, seen_from: Option<&Rigid3>| {
            let tried = match pose_from_rendered_neighbour(
                mesh, camera, intrinsics, &features, neighbour, seen_from, config, seed, workspace,
            ) {
                Ok(hypothesis) => {
                    let (mut check, failed) = check_neighbour_pose(
                        mesh,
                        query,
                        intrinsics,
                        &hypothesis,
                        own,
                        config,
                        workspace,
                    );
                    if let Some(witness) = witness_of(&check, failed, neighbour.id, view, config) {
                        confirm_by_agreement(
                            mesh, query, intrinsics, own, witness, &mut check, witnesses, config,
                            workspace,
                        );
                    }
                    let decision = neighbour_decision(mesh, query, own, &check, config, workspace);
                    NeighbourTry {
                        neighbour: index,
                        view,
                        check: Ok(check),
                        decision,
                    }
                }
                Err(why) => NeighbourTry::failed(index, view, why),
            };
            let confirmed = tried.confirmed();
            let pose = tried
                .check
                .as_ref()
                .ok()
                .map(|check| check.hypothesis.cam_from_world);
            tries.push(tried);
            (confirmed, pose)
        };
        let (confirmed, photographed_pose) = attempt(NeighbourView::AsPhotographed, None);
        if confirmed {
            break;
        }
        if warp != NeighbourWarp::Off {
            if let Some(own_pose) = own_pose {
                if attempt(NeighbourView::OwnPose, Some(&own_pose)).0 {
                    break;
                }
            }
        }
        if warp == NeighbourWarp::OwnAndNeighbourPose {
            if let Some(pose) = photographed_pose {
                if attempt(NeighbourView::NeighbourPose, Some(&pose)).0 {
                    break;
                }
            }
        }
    }
    tries
}

/// A neighbour's decision applied to the frame's verdict: accepted at the neighbour's pose
/// ([`NeighbourDecision::Accept`]), or rejected
/// ([`RejectionReason::ContradictedByNeighbour`], naming `neighbour`); else unchanged.
pub fn apply_to_verdict(verdict: &mut Verdict, tried: &NeighbourTry, neighbour: &str) {
    match (tried.decision, &tried.check) {
        (NeighbourDecision::Accept, Ok(check)) => verdict.decision = Ok(check.hypothesis),
        (NeighbourDecision::Combine { cam_from_world }, _) => {
            if let Ok(accepted) = &mut verdict.decision {
                accepted.cam_from_world = cam_from_world;
            }
        }
        (NeighbourDecision::Contradicted { apart_px }, _) => reject(
            verdict,
            RejectionReason::ContradictedByNeighbour {
                neighbour: neighbour.to_string(),
                apart_px,
            },
        ),
        _ => {}
    }
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

/// A frame that may lend its pose: its place in the feed, its registered pose and its steps from
/// a frame the model accepted on its own (0: it is one).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FeedLender {
    pub index: usize,
    pub cam_from_world: Rigid3,
    pub steps: usize,
}

/// The rule batch registration and the pipeline share (one result whatever the order frames
/// complete in): frame `index` of a feed may take the pose of the accepted frames before it,
/// at most `config.window_frames` before, whose chain to a frame the model accepted on its own
/// is shorter than `config.max_steps`, and of the frames at most `config.lookahead_frames`
/// after it that the model accepted on their own (steps 0); the nearest looking its way first
/// ([`nearest_neighbours`]). Every frame of the window must have its final result, and every
/// frame of the look-ahead its own decision, before the frame's step runs: then the lenders,
/// and so the frame's result, do not depend on timing. `accepted` holds the frames' current
/// steps: a frame after `index` has only its own decision yet.
pub fn feed_neighbours(
    index: usize,
    prior: &Rigid3,
    accepted: impl IntoIterator<Item = FeedLender>,
    config: &NeighbourPoseConfig,
) -> Vec<usize> {
    let first = index.saturating_sub(config.window_frames);
    let last = index.saturating_add(config.lookahead_frames);
    let lends = |lender: &FeedLender| {
        let before = (first..index).contains(&lender.index) && lender.steps < config.max_steps;
        let after = (index + 1..=last).contains(&lender.index) && lender.steps == 0;
        before || after
    };
    let lenders: Vec<(usize, Rigid3)> = accepted
        .into_iter()
        .filter(lends)
        .map(|lender| (lender.index, lender.cam_from_world))
        .collect();
    nearest_neighbours(prior, &lenders, config)
}

#[cfg(test)]
mod tests {
    use nalgebra::{UnitQuaternion, Vector3};

    use super::*;
    use crate::core::frame::query_features;
    use crate::core::frame::tests::{house_and_poses, ideal_query};

    /// The house seen from its true pose and from two neighbours, each query the model's own
    /// ASG there (the ASG of two viewpoints differs a little: each shows the model's edges as
    /// seen from it).
    struct Scene {
        mesh: Mesh,
        camera: Camera,
        truth: Rigid3,
        query: crate::core::image::Image<f32>,
        config: RegistrationConfig,
    }

    impl Scene {
        fn new() -> Self {
            let (mesh, camera, truth, _) = house_and_poses();
            let config = RegistrationConfig::default();
            let query = ideal_query(&mesh, &camera, &truth, &config);
            Self {
                mesh,
                camera,
                truth,
                query,
                config,
            }
        }

        /// The neighbour's pose of the frame from a neighbour at its true pose turned by
        /// `turn_rad` about the world's y axis and moved by `shift_m`, and its δ to the truth.
        fn pose_from(
            &self,
            turn_rad: f64,
            shift_m: Vector3<f64>,
            workspace: &mut NeighbourWorkspace,
        ) -> (PoseHypothesis, f64) {
            self.pose_seen_from(turn_rad, shift_m, None, workspace)
                .unwrap()
        }

        /// As [`Self::pose_from`], the neighbour's photo seen from `seen_from` (as photographed
        /// when `None`), the δ of the pose to the truth; `None` without a pose.
        fn delta_from(
            &self,
            turn_rad: f64,
            shift_m: Vector3<f64>,
            seen_from: Option<&Rigid3>,
            workspace: &mut NeighbourWorkspace,
        ) -> Option<f64> {
            self.pose_seen_from(turn_rad, shift_m, seen_from, workspace)
                .map(|(_, delta_px)| delta_px)
        }

        /// The pose and its δ of [`Self::pose_from`] and [`Self::delta_from`].
        fn pose_seen_from(
            &self,
            turn_rad: f64,
            shift_m: Vector3<f64>,
            seen_from: Option<&Rigid3>,
            workspace: &mut NeighbourWorkspace,
        ) -> Option<(PoseHypothesis, f64)> {
            let neighbour_pose = Rigid3::new(
                UnitQuaternion::from_scaled_axis(Vector3::new(0.0, turn_rad, 0.0))
                    * self.truth.rotation,
                self.truth.translation + shift_m,
            );
            let neighbour_query =
                ideal_query(&self.mesh, &self.camera, &neighbour_pose, &self.config);
            let features = query_features(self.query.view(), &self.config).unwrap();
            let neighbour = RegisteredNeighbour {
                id: 0,
                query: neighbour_query.view(),
                camera: &self.camera,
                cam_from_world: neighbour_pose,
            };
            let pose = pose_from_neighbour(
                &self.mesh,
                &self.camera,
                IntrinsicsMode::Known,
                &features,
                &neighbour,
                seen_from,
                &self.config,
                7,
                workspace,
            )
            .ok()?;
            let delta_px = self.delta_to_truth(&pose.cam_from_world)?;
            Some((pose, delta_px))
        }

        /// δ between `cam_from_world` and the true pose, px.
        fn delta_to_truth(&self, cam_from_world: &Rigid3) -> Option<f64> {
            mutual_reprojection_error_px(
                &self.mesh,
                &self.camera,
                cam_from_world,
                &self.camera,
                &self.truth,
                &mut ReprojectionWorkspace::new(),
            )
        }

        fn decide(
            &self,
            pose: &PoseHypothesis,
            own: Result<&PoseHypothesis, Option<&PoseHypothesis>>,
            workspace: &mut NeighbourWorkspace,
        ) -> (NeighbourCheck, NeighbourDecision) {
            let (check, _) = check_neighbour_pose(
                &self.mesh,
                self.query.view(),
                IntrinsicsMode::Known,
                pose,
                own,
                &self.config,
                workspace,
            );
            let decision = neighbour_decision(
                &self.mesh,
                self.query.view(),
                own,
                &check,
                &self.config,
                workspace,
            );
            (check, decision)
        }
    }

    /// The frame's own query warped to its own pose through the model is the query itself at
    /// every pixel the model covers; a neighbour on the far side of the house sees none of the
    /// front the frame sees, so nothing of it is warped there.
    #[test]
    fn warping_a_photo_to_its_own_pose_gives_it_back_and_hidden_points_stay_empty() {
        let scene = Scene::new();
        let mut workspace = NeighbourWorkspace::default();
        let size = (
            scene.camera.width_px as usize,
            scene.camera.height_px as usize,
        );
        workspace.warped.render.resize(size.0, size.1);
        let mut rasterizer = Rasterizer::new();
        rasterizer.render(
            &scene.mesh,
            &scene.camera.intrinsics,
            &scene.truth,
            &scene.config.render,
            &mut workspace.warped.render,
        );
        let itself = RegisteredNeighbour {
            id: 0,
            query: scene.query.view(),
            camera: &scene.camera,
            cam_from_world: scene.truth,
        };
        let own_render = workspace.warped.render.clone();
        let seen = warp_to_view(
            &scene.camera,
            &scene.truth,
            &itself,
            &own_render,
            &mut workspace.warped,
        );
        let covered = own_render.valid_count();
        assert!(
            seen + covered / 100 >= covered,
            "{seen} of {covered} pixels"
        );
        let worst = workspace
            .warped
            .image
            .data()
            .iter()
            .zip(scene.query.data())
            .zip(workspace.warped.face_index.data())
            .filter(|(_, face)| **face != NO_FACE)
            .map(|((warped, query), _)| (warped - query).abs())
            .fold(0.0_f32, f32::max);
        assert!(worst < 1e-4, "largest difference {worst}");
        // Behind the house, looking back at the frame (turned by π about the house's centre).
        let centre = own_render_centre(&scene);
        let turn = UnitQuaternion::from_scaled_axis(Vector3::new(0.0, std::f64::consts::PI, 0.0));
        let world_from_cam = scene.truth.inverse();
        let behind_world_from_cam = Rigid3::new(
            turn * world_from_cam.rotation,
            centre + turn * (world_from_cam.translation - centre),
        );
        let behind = behind_world_from_cam.inverse();
        let mut behind_render = own_render.clone();
        rasterizer.render(
            &scene.mesh,
            &scene.camera.intrinsics,
            &behind,
            &scene.config.render,
            &mut behind_render,
        );
        let neighbour = RegisteredNeighbour {
            id: 0,
            query: scene.query.view(),
            camera: &scene.camera,
            cam_from_world: behind,
        };
        let seen_from_behind = warp_to_view(
            &scene.camera,
            &scene.truth,
            &neighbour,
            &behind_render,
            &mut workspace.warped,
        );
        assert!(
            seen_from_behind * 10 < covered,
            "{seen_from_behind} of {covered} pixels seen from behind"
        );
    }

    /// The world point at the middle of the frame's rendering at its true pose.
    fn own_render_centre(scene: &Scene) -> Vector3<f64> {
        let (width_px, height_px) = (
            scene.camera.width_px as usize,
            scene.camera.height_px as usize,
        );
        let mut render = RenderBuffers::new(width_px, height_px);
        Rasterizer::new().render(
            &scene.mesh,
            &scene.camera.intrinsics,
            &scene.truth,
            &scene.config.render,
            &mut render,
        );
        let (col, row) = (width_px / 2, height_px / 2);
        let depth_m = f64::from(render.depth_m().data()[row * width_px + col]);
        assert!(depth_m > 0.0, "the model covers the middle of the frame");
        let normalized = scene
            .camera
            .intrinsics
            .pixel_to_normalized(pixel_center(col, row));
        scene
            .truth
            .inverse()
            .transform_point(&(Vector3::new(normalized.x, normalized.y, 1.0) * depth_m))
    }

    /// A neighbour 2 m and 15° away from the frame: as photographed its photo gives a pose 42 px
    /// off; seen from the frame's own pose (5.6 px off the truth) it gives the pose to under a
    /// pixel (0.77 px; a neighbour 4 m and 29° away: 111 px against 2.4 px).
    #[test]
    fn a_far_neighbours_photo_seen_from_the_frames_pose_gives_the_pose() {
        let scene = Scene::new();
        let mut workspace = NeighbourWorkspace::default();
        let (turn_rad, shift_m) = (0.26, Vector3::new(2.0, 0.3, -0.5));
        let own = Rigid3::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.035, 0.0, 0.0)) * scene.truth.rotation,
            scene.truth.translation,
        );
        let start_px = scene.delta_to_truth(&own).unwrap();
        assert!(
            start_px > 5.0,
            "the frame's own pose is {start_px:.2} px off"
        );
        let direct = scene.delta_from(turn_rad, shift_m, None, &mut workspace);
        assert!(
            direct.is_none_or(|px| px > 20.0),
            "as photographed: {direct:?} px"
        );
        let warped = scene
            .delta_from(turn_rad, shift_m, Some(&own), &mut workspace)
            .unwrap();
        assert!(warped < 1.0, "seen from the frame's pose: {warped:.2} px");
    }

    /// The far neighbour above, its photo seen from a pose of the frame 12.8 px off: once, the
    /// flow bridges only part of that (8.2 px left); seen again from the pose each round gave,
    /// it ends nearer the truth (2.5 px after 3 rounds, 0.9 after 5).
    #[test]
    fn a_warped_view_seen_again_from_the_pose_it_gave_ends_nearer_the_truth() {
        let mut scene = Scene::new();
        let mut workspace = NeighbourWorkspace::default();
        let (turn_rad, shift_m) = (0.26, Vector3::new(2.0, 0.3, -0.5));
        let own = Rigid3::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.08, 0.0, 0.0)) * scene.truth.rotation,
            scene.truth.translation,
        );
        let start_px = scene.delta_to_truth(&own).unwrap();
        assert!(start_px > 10.0, "seen from {start_px:.2} px off");
        let mut delta_px = |rounds| {
            scene.config.neighbour_pose.warp_rounds = rounds;
            scene
                .delta_from(turn_rad, shift_m, Some(&own), &mut workspace)
                .unwrap()
        };
        let (once, thrice) = (delta_px(1), delta_px(3));
        assert!(once > 5.0, "one round: {once:.2} px");
        assert!(
            thrice < 0.5 * once,
            "three rounds: {thrice:.2} px, one: {once:.2} px"
        );
    }

    /// Step "neighbour" with the far neighbour above: its photo as photographed gives no
    /// confirmed pose, so with [`NeighbourWarp::OwnPose`] it is tried again seen from the frame's
    /// would-be pose, which the model confirms and the frame is accepted at; without the warp
    /// the frame's rejection stands.
    #[test]
    fn a_far_neighbour_is_tried_again_from_the_frames_own_pose() {
        let scene = Scene::new();
        let mut workspace = NeighbourWorkspace::default();
        let (near, _) = scene.pose_from(0.0, Vector3::new(0.3, 0.12, -0.18), &mut workspace);
        let would_be = PoseHypothesis {
            cam_from_world: Rigid3::new(
                UnitQuaternion::from_scaled_axis(Vector3::new(0.035, 0.0, 0.0))
                    * scene.truth.rotation,
                scene.truth.translation,
            ),
            ..near
        };
        let neighbour_pose = Rigid3::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.26, 0.0)) * scene.truth.rotation,
            scene.truth.translation + Vector3::new(2.0, 0.3, -0.5),
        );
        let neighbour_query =
            ideal_query(&scene.mesh, &scene.camera, &neighbour_pose, &scene.config);
        let neighbours = [RegisteredNeighbour {
            id: 0,
            query: neighbour_query.view(),
            camera: &scene.camera,
            cam_from_world: neighbour_pose,
        }];
        let run = |warp: NeighbourWarp, workspace: &mut NeighbourWorkspace| {
            let mut config = scene.config.clone();
            config.neighbour_pose.warp = warp;
            try_neighbours(
                &scene.mesh,
                &scene.camera,
                IntrinsicsMode::Known,
                scene.query.view(),
                Err(Some(&would_be)),
                &neighbours,
                &mut Vec::new(),
                &config,
                7,
                workspace,
            )
        };
        let plain = run(NeighbourWarp::Off, &mut workspace);
        assert_eq!(plain.len(), 1);
        assert!(!plain[0].confirmed(), "{plain:?}");
        let warped = run(NeighbourWarp::OwnPose, &mut workspace);
        let views: Vec<NeighbourView> = warped.iter().map(|tried| tried.view).collect();
        assert_eq!(
            views,
            [NeighbourView::AsPhotographed, NeighbourView::OwnPose]
        );
        assert!(warped.iter().all(|tried| tried.neighbour == 0));
        assert!(warped[1].confirmed(), "{:?}", warped[1]);
        assert_eq!(warped[1].decision, NeighbourDecision::Accept);
    }

    /// A neighbour 0.3 m away (5 px of δ), registered at its true pose, gives the frame's pose
    /// to about a pixel; the model confirms it, so a frame not accepted on its own is accepted,
    /// an accepted pose it agrees with is combined with it, and one 16 px from it is contradicted.
    #[test]
    fn a_registered_neighbour_gives_the_true_pose_and_the_model_decides_with_it() {
        let scene = Scene::new();
        let mut workspace = NeighbourWorkspace::default();
        let (pose, delta_px) = scene.pose_from(0.0, Vector3::new(0.3, 0.12, -0.18), &mut workspace);
        assert!(delta_px < 1.5, "δ {delta_px:.2} px");
        let (check, decision) = scene.decide(&pose, Err(None), &mut workspace);
        assert_eq!(check.confirmed, Ok(()), "{check:?}");
        assert_eq!(decision, NeighbourDecision::Accept);
        let agreeing = PoseHypothesis {
            cam_from_world: scene.truth,
            ..pose
        };
        assert!(
            matches!(
                scene.decide(&pose, Ok(&agreeing), &mut workspace).1,
                NeighbourDecision::Combine { .. }
            ),
            "an agreeing confirmed pose is combined with the accepted one"
        );
        // An accepted pose 16 px away: beyond the centres' agreement distance (12.6 px).
        let far = PoseHypothesis {
            cam_from_world: Rigid3::new(
                UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.1, 0.0))
                    * scene.truth.rotation,
                scene.truth.translation,
            ),
            ..pose
        };
        let (check, decision) = scene.decide(&pose, Ok(&far), &mut workspace);
        assert!(
            matches!(decision, NeighbourDecision::Contradicted { apart_px } if apart_px > 15.0),
            "{decision:?} {check:?}"
        );
    }

    /// Two lenders near the frame, registered at their true poses, each give the frame's pose to
    /// a pixel or two. With a confidence whose "fixed" gate no pose passes (0 px of image
    /// uncertainty asked), the first lender's pose alone is not confirmed and the second's,
    /// agreeing with it, is: a frame rejected on its own is accepted at it, an accepted pose 16 px
    /// away is contradicted, an agreeing accepted pose is kept as it is (a pose the edges do not
    /// fix does not move one they fix). Without `two_lenders_confirm`, or with the second lender
    /// registered 0.1 rad off (its pose of the frame far from the first's), none is confirmed.
    #[test]
    fn two_lenders_that_agree_confirm_a_pose_the_edges_do_not_fix() {
        let mut scene = Scene::new();
        scene.config.confidence.max_image_uncertainty_px = 0.0;
        let mut workspace = NeighbourWorkspace::default();
        let at = |shift_m: Vector3<f64>| {
            Rigid3::new(scene.truth.rotation, scene.truth.translation + shift_m)
        };
        let (first, second) = (
            at(Vector3::new(0.3, 0.12, -0.18)),
            at(Vector3::new(-0.3, 0.1, 0.15)),
        );
        let photos = [first, second]
            .map(|pose| ideal_query(&scene.mesh, &scene.camera, &pose, &scene.config));
        let lenders = |registered: [Rigid3; 2]| {
            [0, 1].map(|i| RegisteredNeighbour {
                id: i,
                query: photos[i].view(),
                camera: &scene.camera,
                cam_from_world: registered[i],
            })
        };
        let run = |config: &RegistrationConfig,
                   own: Result<&PoseHypothesis, Option<&PoseHypothesis>>,
                   neighbours: &[RegisteredNeighbour<'_>],
                   workspace: &mut NeighbourWorkspace| {
            let mut config = config.clone();
            config.neighbour_pose.warp = NeighbourWarp::Off;
            try_neighbours(
                &scene.mesh,
                &scene.camera,
                IntrinsicsMode::Known,
                scene.query.view(),
                own,
                neighbours,
                &mut Vec::new(),
                &config,
                7,
                workspace,
            )
        };
        let both = lenders([first, second]);
        let tries = run(&scene.config, Err(None), &both, &mut workspace);
        assert_eq!(tries.len(), 2, "{tries:?}");
        assert!(!tries[0].confirmed(), "{:?}", tries[0]);
        let check = tries[0].check.as_ref().unwrap();
        assert!(
            check.confirmed.as_ref().unwrap_err().contains("do not fix"),
            "{check:?}"
        );
        assert!(tries[1].confirmed(), "{:?}", tries[1]);
        let confirmed = tries[1].check.as_ref().unwrap();
        assert_eq!(confirmed.agreeing_neighbour, Some(0));
        assert_eq!(tries[1].decision, NeighbourDecision::Accept);
        let delta_px = scene
            .delta_to_truth(&confirmed.hypothesis.cam_from_world)
            .unwrap();
        assert!(delta_px < 2.0, "δ {delta_px:.2} px");

        // An accepted pose 16 px away is contradicted by the two lenders; near the true pose
        // (accepted) their agreement is not asked: both stay unconfirmed and it is kept.
        let far = PoseHypothesis {
            cam_from_world: Rigid3::new(
                UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.1, 0.0))
                    * scene.truth.rotation,
                scene.truth.translation,
            ),
            ..confirmed.hypothesis
        };
        let tries = run(&scene.config, Ok(&far), &both, &mut workspace);
        assert_eq!(tries.len(), 2, "{tries:?}");
        let contradicted = tries[1].check.as_ref().unwrap();
        assert_eq!(contradicted.agreeing_neighbour, Some(0));
        let decision = tries[1].decision;
        assert!(
            matches!(decision, NeighbourDecision::Contradicted { apart_px } if apart_px > 15.0),
            "{tries:?}"
        );
        let agreeing = PoseHypothesis {
            cam_from_world: scene.truth,
            ..confirmed.hypothesis
        };
        let tries = run(&scene.config, Ok(&agreeing), &both, &mut workspace);
        assert_eq!(tries.len(), 2, "{tries:?}");
        assert!(tries.iter().all(|tried| !tried.confirmed()), "{tries:?}");
        assert!(tries
            .iter()
            .all(|tried| tried.decision == NeighbourDecision::Keep));

        // Off: neither is confirmed.
        let mut off = scene.config.clone();
        off.neighbour_pose.two_lenders_confirm = false;
        let tries = run(&off, Err(None), &both, &mut workspace);
        assert!(tries.iter().all(|tried| !tried.confirmed()), "{tries:?}");

        // The second lender registered 0.1 rad off: its pose of the frame disagrees with the
        // first's. (Every pose clears chance here, so that it is a witness and it is the
        // distance that keeps the two apart.)
        let wrong = Rigid3::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.1, 0.0)) * second.rotation,
            second.translation,
        );
        let mut lenient = scene.config.clone();
        lenient.confidence.min_support_above_chance = -1.0;
        let tries = run(
            &lenient,
            Err(None),
            &lenders([first, wrong]),
            &mut workspace,
        );
        assert!(tries.iter().all(|tried| !tried.confirmed()), "{tries:?}");
        let second_try = tries[1].check.as_ref().unwrap();
        let why = second_try.confirmed.as_ref().unwrap_err();
        assert!(why.contains("do not fix"), "{why}");
        let apart_px = mutual_reprojection_error_px(
            &scene.mesh,
            &scene.camera,
            &second_try.hypothesis.cam_from_world,
            &scene.camera,
            &tries[0].check.as_ref().unwrap().hypothesis.cam_from_world,
            &mut ReprojectionWorkspace::new(),
        )
        .unwrap();
        assert!(
            apart_px > 12.6,
            "the two lenders' poses {apart_px:.1} px apart"
        );
    }

    /// Three lenders whose poses agree confirm a pose the photo's edges see above chance but not
    /// clear of it (here nothing is clear: the margin one pose needs alone is set to 1); two do
    /// not, nor three when the quorum is off or asks each pose for the whole margin.
    #[test]
    fn three_lenders_that_agree_confirm_a_pose_the_edges_do_not_clear() {
        let scene = Scene::new();
        let mut workspace = NeighbourWorkspace::default();
        let at = |shift_m: Vector3<f64>| {
            Rigid3::new(scene.truth.rotation, scene.truth.translation + shift_m)
        };
        let registered = [
            at(Vector3::new(0.3, 0.12, -0.18)),
            at(Vector3::new(-0.3, 0.1, 0.15)),
            at(Vector3::new(0.1, -0.25, 0.1)),
        ];
        let photos =
            registered.map(|pose| ideal_query(&scene.mesh, &scene.camera, &pose, &scene.config));
        let lenders: Vec<RegisteredNeighbour<'_>> = (0..3)
            .map(|i| RegisteredNeighbour {
                id: i,
                query: photos[i].view(),
                camera: &scene.camera,
                cam_from_world: registered[i],
            })
            .collect();
        let mut strict = scene.config.clone();
        strict.neighbour_pose.warp = NeighbourWarp::Off;
        strict.confidence.min_support_above_chance = 1.0;
        strict.neighbour_pose.quorum_support_share = 0.0;
        let mut run = |config: &RegistrationConfig, neighbours: &[RegisteredNeighbour<'_>]| {
            try_neighbours(
                &scene.mesh,
                &scene.camera,
                IntrinsicsMode::Known,
                scene.query.view(),
                Err(None),
                neighbours,
                &mut Vec::new(),
                config,
                7,
                &mut workspace,
            )
        };
        let tries = run(&strict, &lenders);
        assert_eq!(tries.len(), 3, "{tries:?}");
        for tried in &tries[..2] {
            let check = tried.check.as_ref().unwrap();
            let why = check.confirmed.as_ref().unwrap_err();
            assert!(why.contains("does not confirm"), "{why}");
            let peak = check.peak.as_ref().unwrap();
            assert!(peak.at_pose > peak.far, "{peak:?}");
        }
        assert!(tries[2].confirmed(), "{:?}", tries[2]);
        assert_eq!(tries[2].decision, NeighbourDecision::Accept);
        let confirmed = tries[2].check.as_ref().unwrap();
        assert_eq!(confirmed.agreeing_neighbour, Some(0));
        let delta_px = scene
            .delta_to_truth(&confirmed.hypothesis.cam_from_world)
            .unwrap();
        assert!(delta_px < 2.0, "δ {delta_px:.2} px");

        // Two lenders are not a quorum of three.
        let tries = run(&strict, &lenders[..2]);
        assert!(tries.iter().all(|tried| !tried.confirmed()), "{tries:?}");
        // Off, or each pose asked for the whole margin: none is confirmed.
        let mut off = strict.clone();
        off.neighbour_pose.quorum_lenders = 0;
        let mut whole = strict.clone();
        whole.neighbour_pose.quorum_support_share = 1.0;
        for config in [off, whole] {
            let tries = run(&config, &lenders);
            assert!(tries.iter().all(|tried| !tried.confirmed()), "{tries:?}");
        }
    }

    /// Three lenders whose poses each fail only the rival-basin test and agree confirm their mean
    /// without it (`quorum_outweighs_rival`); not with it off, nor two lenders (one lending
    /// twice), nor three whose third pose lies in another basin.
    #[test]
    fn three_agreeing_lenders_outweigh_a_rival_basin_the_edges_support_as_well() {
        let scene = Scene::new();
        let mut workspace = NeighbourWorkspace::default();
        let hypothesis = |shift_m: Vector3<f64>| PoseHypothesis {
            camera: scene.camera,
            cam_from_world: Rigid3::new(scene.truth.rotation, scene.truth.translation + shift_m),
            consensus: 100,
            inlier_rms_px: 1.0,
            correspondence_count: 200,
            coarse_cam_from_world: scene.truth,
        };
        let near = [
            Vector3::new(0.1, 0.0, 0.0),
            Vector3::new(-0.1, 0.05, 0.0),
            Vector3::new(0.0, -0.05, 0.0),
        ];
        // Each try as `try_neighbours` makes it: checked, failed only the rival test.
        let mut run = |config: &RegistrationConfig, lenders: [(usize, Vector3<f64>); 3]| {
            let mut witnesses = Vec::new();
            lenders.map(|(lender, shift_m)| {
                let mut check = NeighbourCheck {
                    hypothesis: hypothesis(shift_m),
                    peak: None,
                    apart_px: None,
                    confirmed: Err("a rival basin".to_string()),
                    agreeing_neighbour: None,
                };
                let view = NeighbourView::AsPhotographed;
                if let Some(witness) =
                    witness_of(&check, Some(FailedGate::Rival), lender, view, config)
                {
                    confirm_by_agreement(
                        &scene.mesh,
                        scene.query.view(),
                        IntrinsicsMode::Known,
                        Err(None),
                        witness,
                        &mut check,
                        &mut witnesses,
                        config,
                        &mut workspace,
                    );
                }
                check
            })
        };
        let checks = run(&scene.config, [(0, near[0]), (1, near[1]), (2, near[2])]);
        assert!(checks[..2].iter().all(|check| check.confirmed.is_err()));
        assert_eq!(checks[2].confirmed, Ok(()));
        assert_eq!(checks[2].agreeing_neighbour, Some(0));
        let mean_delta_px = scene
            .delta_to_truth(&checks[2].hypothesis.cam_from_world)
            .unwrap();
        let third_delta_px = scene
            .delta_to_truth(&hypothesis(near[2]).cam_from_world)
            .unwrap();
        assert!(
            mean_delta_px < third_delta_px,
            "the group's mean {mean_delta_px:.2} px from the truth, its last pose {third_delta_px:.2} px"
        );

        let mut off = scene.config.clone();
        off.neighbour_pose.quorum_outweighs_rival = false;
        let unconfirmed = |checks: [NeighbourCheck; 3]| checks.iter().all(|c| c.confirmed.is_err());
        assert!(unconfirmed(run(
            &off,
            [(0, near[0]), (1, near[1]), (2, near[2])]
        )));
        assert!(unconfirmed(run(
            &scene.config,
            [(0, near[0]), (0, near[1]), (1, near[2])]
        )));
        let elsewhere = Vector3::new(5.0, 0.0, 0.0);
        let elsewhere_px = scene
            .delta_to_truth(&hypothesis(elsewhere).cam_from_world)
            .unwrap();
        assert!(elsewhere_px > 30.0, "{elsewhere_px:.1} px");
        assert!(unconfirmed(run(
            &scene.config,
            [(0, near[0]), (1, near[1]), (2, elsewhere)]
        )));
    }

    /// Witnesses are independent only from two lenders and not both matched from the frame's own
    /// pose.
    #[test]
    fn witnesses_from_one_lender_or_both_from_the_own_pose_are_not_independent() {
        let (_, camera, truth, _) = house_and_poses();
        let hypothesis = PoseHypothesis {
            camera,
            cam_from_world: truth,
            consensus: 100,
            inlier_rms_px: 1.0,
            correspondence_count: 200,
            coarse_cam_from_world: truth,
        };
        let witness = |lender, view| Witness {
            lender,
            view,
            hypothesis,
            support: WitnessSupport::Clear,
        };
        use NeighbourView::{AsPhotographed, NeighbourPose, OwnPose};
        assert!(witness(0, AsPhotographed).independent_of(&witness(1, OwnPose)));
        assert!(witness(0, OwnPose).independent_of(&witness(1, NeighbourPose)));
        assert!(!witness(0, AsPhotographed).independent_of(&witness(0, NeighbourPose)));
        assert!(!witness(0, OwnPose).independent_of(&witness(1, OwnPose)));
        assert!(witness(1, OwnPose).independent_of(&witness(0, AsPhotographed)));
    }

    /// An accepted pose 2 px off along the direction its edges see least, and an agreeing
    /// confirmed neighbour's pose about a pixel off: `keep` leaves the own pose, `mean` and
    /// `least-seen` move it nearer the truth.
    #[test]
    fn an_agreeing_neighbour_pose_moves_the_accepted_pose_along_what_its_edges_see_least() {
        let mut scene = Scene::new();
        let mut workspace = NeighbourWorkspace::default();
        let (pose, _) = scene.pose_from(0.0, Vector3::new(0.3, 0.12, -0.18), &mut workspace);
        let steps = seen_steps_at_pose(
            &scene.mesh,
            &scene.camera,
            scene.query.view(),
            &scene.truth,
            &scene.config,
            &mut workspace.refine,
        )
        .unwrap();
        let own = PoseHypothesis {
            cam_from_world: apply_pose_step(&scene.truth, &(steps[0] * 3.0)),
            ..pose
        };
        let own_delta_px = scene.delta_to_truth(&own.cam_from_world).unwrap();
        // 3 px RMS of the visible model's motion; δ (the mutual reprojection) reads 2.2 px.
        assert!(own_delta_px > 1.5, "δ {own_delta_px:.2} px");
        scene.config.neighbour_pose.agreement = NeighbourAgreement::Keep;
        assert_eq!(
            scene.decide(&pose, Ok(&own), &mut workspace).1,
            NeighbourDecision::Keep
        );
        for agreement in [NeighbourAgreement::Mean, NeighbourAgreement::LeastSeen] {
            scene.config.neighbour_pose.agreement = agreement;
            let (check, decision) = scene.decide(&pose, Ok(&own), &mut workspace);
            let NeighbourDecision::Combine { cam_from_world } = decision else {
                panic!("{agreement:?}: {decision:?} {check:?}");
            };
            let combined_px = scene.delta_to_truth(&cam_from_world).unwrap();
            assert!(
                combined_px < 0.7 * own_delta_px,
                "{agreement:?}: δ {combined_px:.2} px from {own_delta_px:.2} px"
            );
        }
    }

    /// A neighbour 0.6 m and 2° away (10 px) gives a pose 2.4 px off, beside the edges' sharp
    /// peak: the model does not confirm it, and the frame's own decision stands.
    #[test]
    fn a_neighbours_pose_off_the_edges_peak_is_not_confirmed() {
        let scene = Scene::new();
        let mut workspace = NeighbourWorkspace::default();
        let (pose, delta_px) = scene.pose_from(0.035, Vector3::new(0.5, 0.2, -0.3), &mut workspace);
        assert!(delta_px > 2.0 && delta_px < 3.0, "δ {delta_px:.2} px");
        let (check, decision) = scene.decide(&pose, Err(None), &mut workspace);
        assert!(check.confirmed.is_err(), "{check:?}");
        assert_eq!(decision, NeighbourDecision::Keep);
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

    /// A feed's frame borrows only from accepted frames before it within the window whose chain
    /// is shorter than `max_steps`, nearest first.
    #[test]
    fn feed_neighbours_come_from_the_window_before_the_frame_and_own_accepts_after_it() {
        let at = |x: f64| Rigid3::new(UnitQuaternion::identity(), Vector3::new(-x, 0.0, 0.0));
        let lender = |index: usize, x: f64, steps: usize| FeedLender {
            index,
            cam_from_world: at(x),
            steps,
        };
        let accepted = [
            lender(2, 0.1, 0),   // before the window (10 − 3 = 7)
            lender(7, 4.0, 0),   // first of the window
            lender(8, 0.2, 2),   // too many steps
            lender(9, 1.0, 1),   // nearest allowed before
            lender(10, 0.0, 0),  // the frame itself
            lender(11, 0.3, 1),  // after the frame, accepted through a neighbour
            lender(12, 2.0, 0),  // after the frame, accepted on its own
            lender(13, 0.05, 0), // beyond the look-ahead (10 + 2)
        ];
        let config = NeighbourPoseConfig {
            window_frames: 3,
            lookahead_frames: 2,
            max_steps: 2,
            candidates: 3,
            ..NeighbourPoseConfig::default()
        };
        assert_eq!(
            feed_neighbours(10, &at(0.0), accepted, &config),
            vec![9, 12, 7]
        );
        let no_lookahead = NeighbourPoseConfig {
            lookahead_frames: 0,
            ..config.clone()
        };
        assert_eq!(
            feed_neighbours(10, &at(0.0), accepted, &no_lookahead),
            vec![9, 7]
        );
        // The first frame of a feed: only the look-ahead.
        assert_eq!(feed_neighbours(0, &at(0.0), accepted, &config), vec![2]);
    }
}
