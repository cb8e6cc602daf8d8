//! Alignment of the model's edges with the photo's, the final refinement of a pose (issue #11
//! item 3; not in the paper). SIFT flow between a photo's gradients and an ASG rendering is
//! biased by several pixels even at the true pose (`eval --diagnose`, "at truth"), so iterating
//! render → flow → PnP cannot reach a pixel. Edges can: where the model has a crease or an
//! occluding contour the photo has an intensity step, and the ridge of its gradient magnitude lies
//! on the edge itself.
//!
//! Method: "moving edges" (P. Bouthemy, 1989; A. Comport, E. Marchand, M. Pressigout,
//! F. Chaumette, "Real-time markerless tracking for augmented reality: the virtual visual servoing
//! framework", IEEE TVCG 2006, as in ViSP's model-based tracker):
//! 1. model edge samples: ridges of the ASG rendering at the current pose (local maxima across the
//!    ridge, whose direction comes from the ASG's Hessian), one per `sample_spacing_px` cell,
//!    lifted to 3D with the rendering's nearest depth (the occluding side of a contour);
//! 2. for each sample, a 1-D search along its 2D normal in the query image (the photo's gradient
//!    magnitude, or its depth's ASG, 0..1) for the ridge crossing the search line, sub-pixel by a
//!    parabola, line-like (curved across, flat along);
//! 3. a robust Gauss–Newton step (Tukey weights, scale from the MAD) on the pose minimising the
//!    point-to-line distances `n·(π(X) − m)`; search again from the new projections;
//! 4. coarse to fine: a blurred query and a wide search first, sharp and narrow last; the caller
//!    re-renders between levels (visibility and contours move with the pose).
//!
//! The evidence of a pose ([`EdgeEvidence`]) is the share of model edge samples with a photo ridge
//! within `support_px`, measured the same way at any pose, so a refined pose can be compared with
//! the one it started from. Preconditions: a pinhole camera (distortion is not modelled here), the
//! query and the rendering on the camera's pixel grid (COLMAP convention, centres at +0.5).

use nalgebra::{Matrix6, UnitQuaternion, Vector2, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use super::camera::{nearest_pixel, pixel_center, Camera, PinholeIntrinsics, MIN_DEPTH_M};
use super::dense_sift::{gaussian_taps, separable_filter_clamped};
use super::image::{Image, ImageView};
use super::raster::RenderBuffers;
use super::rigid::Rigid3;

/// Settings of the edge alignment.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EdgeAlignConfig {
    /// Run the refinement at all.
    pub enabled: bool,
    /// A model edge is an ASG ridge at least this strong (ASG on its 0..1 scale).
    pub min_model_ridge: f32,
    /// At most one model edge sample per square cell of this side, px.
    pub sample_spacing_px: usize,
    /// A photo ridge must reach this value of the query image (0..1) to be matched.
    pub min_query_ridge: f32,
    /// Search half-length of the first (coarsest) level, px; the query is blurred with a quarter
    /// of it as σ.
    pub initial_search_radius_px: f64,
    /// Search half-length of the last level, px (levels halve the radius down to this).
    pub final_search_radius_px: f64,
    /// Search → Gauss–Newton steps per level.
    pub iterations_per_level: usize,
    /// The evidence counts a model edge as supported when a photo ridge lies within this distance
    /// of its projection, px.
    pub support_px: f64,
    /// Search half-length when measuring the evidence, px.
    pub evidence_radius_px: f64,
    /// Fewer matched model edge samples than this: no step is taken.
    pub min_samples: usize,
    /// Estimate the model's edge rounding radius with the pose (see [`EdgeSample::rounding`]).
    pub estimate_rounding: bool,
    /// The kinds of model edge the estimated rounding is undone on.
    pub rounding_kinds: AlignedKinds,
    /// Which rounding is undone on each pose's samples when the support judges a level, a
    /// start's end and the kept pose (see [`RoundingJudge`]).
    pub rounding_judge: RoundingJudge,
    /// Which model edge samples the Gauss–Newton steps use (the evidence always uses all).
    pub aligned_kinds: AlignedKinds,
    /// Starting poses of the final refinement: the chosen pose and up to `starts − 1` other
    /// refined poses of its agreeing group (largest consensus first, each at least
    /// `final_search_radius_px` from the starts before it). With a short schedule
    /// (`short_schedule_radius_px`) the other starts run it and their end replaces the output as
    /// `short_schedule_rule` says; without one they run the full schedule and the highest edge
    /// support wins. Default 3: with the short schedule, 3 starts against 1 (docs/measurements.md,
    /// sixteenth session) gave block s1 LoD 30 px 1.06 → 0.94 px, house s2 LoD 1.88 → 1.43,
    /// house s1 LoD 8.28 → 7.69 (15 → 13 accepted), the degraded files ±0.1 px, no false accept;
    /// without the short schedule 3 starts had made a false accept (48.7 px) on house s2.
    pub starts: usize,
    /// After each level, keep its result only when the edge support (measured as the evidence
    /// is, fine, with the current rounding undone) is not lower than at the level's start;
    /// else return to the level's start and go on with the next, finer level.
    pub check_levels: bool,
    /// Which alignment the final refinement runs: moving edges (the default), the dense
    /// feature-metric alignment of [`crate::core::feature_align`], or both in turn.
    pub method: RefineMethod,
    /// Settings of the dense alignment (used when `method` includes it).
    pub dense: crate::core::feature_align::DenseAlignConfig,
    /// Which photo ridge on a sample's search line the alignment's steps match it to.
    pub ridge_choice: RidgeChoice,
    /// Weigh each match in the Gauss–Newton steps by its distinctiveness, `1 − s₂/s₁` (the
    /// second-best ridge's score over the best's on the search line): a sample whose search line
    /// crosses two ridges of similar strength (clutter, texture next to the edge) says little
    /// about where its edge is.
    pub distinct_weights: bool,
    /// Levels whose search radius exceeds `evidence_radius_px` (the coarse ones) turn the camera
    /// only (3 DoF); the finer levels estimate everything. A wide search in a cluttered photo
    /// matches many samples to the wrong ridges, and with six degrees of freedom the pose then
    /// trades rotation against lateral translation (started at the truth of the house, the 16 px
    /// level moved it 3–11° and 1–3 m); the pose search's beams are rotations too.
    pub coarse_rotation_only: bool,
    /// The consensus step after the alignment's ends are decided ([`super::edge_consensus`]):
    /// from the output, the pose step most model edges agree with over every photo ridge near
    /// them, aligned from there with the final level; its end replaces the output as
    /// `short_schedule_rule` says.
    pub consensus: super::edge_consensus::EdgeConsensusConfig,
    /// What decides whether the aligned pose replaces the one the alignment started from.
    pub keep_rule: KeepRule,
    /// The first search radius of a second, shorter schedule from the same start, px (0: none):
    /// the alignment also runs with only the levels from this radius down, and its end replaces
    /// the full schedule's as `short_schedule_rule` says. The coarse levels are needed to reach a start several px
    /// off, but on a model simpler than the world they also drift from a good one (started at
    /// the truth of the clean house s1, the schedule from 16 px ends 7.46 px off on average over
    /// 24 frames, from 8 px 3.51 px, from 4 px 0.92 px):
    /// the two schedules end in different basins exactly when the coarse level moved the pose
    /// by more than the fine levels can tell apart.
    /// Default 8 px (docs/measurements.md, sixteenth session: LoD house seed 2 at 30 px 4.35 →
    /// 1.88 px mean δ, the blocks unchanged).
    pub short_schedule_radius_px: f64,
    /// What decides whether the short schedule's end replaces the full schedule's (the full
    /// schedule's end is the verified pose when its alignment was not kept). Measured
    /// (docs/measurements.md): the edge support alone picks the better end on the clean models
    /// and the worse one on the Poisson-like house, where the correlation picks well; both
    /// witnesses must agree by default.
    pub short_schedule_rule: KeepRule,
    /// With several centres of the pose search, each centre's refinement also starts from the
    /// other centres' refined outputs that lie within its reach (at least
    /// `final_search_radius_px` and less than `initial_search_radius_px` from its own output),
    /// each run and decided as the other starts are
    /// ([`crate::core::frame::refine_from_other_centres`]). Default on (docs/measurements.md,
    /// seventeenth session: LoD house s2 at 30 px 1.43 → 0.31 px mean δ, degraded block s3
    /// 2.00 → 1.75 px, house s1 7.69 → 7.65, the other cells unchanged, no false accept).
    pub centre_starts: bool,
    /// The rival-basin test of an accepted pose ([`crate::core::frame::refine::rival_basin`]):
    /// the alignment also runs from the output moved by `rival_reach_px` of δ either way along
    /// each of this many directions its supported edges see least ([`least_seen_starts`]); an
    /// end at least the centres' agreement distance away that keeps `rival_share_above_chance`
    /// of the output's edge support above chance rejects the frame: the photo's edges support a
    /// distinct pose about as well. 0: no runs of its own (the other centres' outputs still
    /// count with `rival_centres`). Default 3 directions, 30 px, share 1 (a rival
    /// at least as well supported; docs/measurements.md, twenty-first session: over 12 cells of
    /// 24 frames (LoD block and house, 30/104 px and heading) it removed the house s4 false
    /// accept (44.0 px) and four accepts 14–25 px off, and no accept within 10 px of the truth;
    /// house s1 30 px 5.64 → 3.49 px mean δ, the blocks unchanged; +0.3 s of CPU per accepted
    /// frame).
    pub rival_directions: usize,
    /// How far the rival starts lie from the output, px of δ.
    pub rival_reach_px: f64,
    /// The share of the output's edge support above chance (`at_pose − far` of its
    /// [`SupportPeak`]) a distinct rival must keep to reject the output (1: as much support as
    /// the output).
    pub rival_share_above_chance: f64,
    /// Whether the other centres' outputs of the pose search count as rival ends in the
    /// rival-basin test (with the same distance and share): a centre that ended in a distinct
    /// basin the photo's edges support at least as well rejects the chosen pose, whatever
    /// `rival_directions` (docs/measurements.md, twenty-seventh session). Default on.
    pub rival_centres: bool,
}

/// What decides whether the final refinement's aligned pose replaces the verified one it started
/// from. The edge support alone is biased where the model is simpler than the world (a clean
/// model without eaves, a photo full of edges the model lacks): more samples land on some photo
/// ridge at a pose a few px off than at the truth (`eval --diagnose`, "at truth" support below
/// the aligned pose's on the clean house). The dense correlation of the rendering with the photo
/// ([`crate::core::correlation`]) weighs the whole rendering against the whole photo instead.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum KeepRule {
    /// Kept when its edge support is higher.
    #[default]
    Support,
    /// Kept when its edge support is higher and its correlation with the photo not lower.
    SupportAndCorrelation,
    /// Kept when its correlation with the photo is higher.
    Correlation,
}

impl KeepRule {
    /// Whether [`KeepRule::keeps`] reads the correlations (else they need not be computed).
    pub fn reads_correlation(self) -> bool {
        self != Self::Support
    }

    /// Whether the aligned pose is kept, from both poses' edge support shares and correlations
    /// (`None`: the model shows no pixel, or either image is constant there).
    pub fn keeps(self, support: (f64, f64), correlation: (Option<f64>, Option<f64>)) -> bool {
        let (verified_support, aligned_support) = support;
        let support_rises = aligned_support > verified_support;
        let correlation_rises = |strictly: bool| match correlation {
            (Some(verified), Some(aligned)) => {
                if strictly {
                    aligned > verified
                } else {
                    aligned >= verified
                }
            }
            (None, Some(_)) => true,
            (_, None) => false,
        };
        match self {
            Self::Support => support_rises,
            Self::SupportAndCorrelation => support_rises && correlation_rises(false),
            Self::Correlation => correlation_rises(true),
        }
    }
}

/// Which rounding radius the support that judges the refinement's poses undoes. The alignment
/// estimates the radius jointly with the aligned pose; undoing that radius on the pose the
/// alignment started from too judges it under a radius fitted to the other (on the clean house
/// s1, view_007: 0.81 against 0.52 so, 0.62 against 0.64 on each pose's edges as rendered;
/// docs/measurements.md, twenty-fifth session).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum RoundingJudge {
    /// The alignment's estimate, undone on both poses.
    #[default]
    Shared,
    /// None: each pose's edges as rendered.
    AsRendered,
    /// Each pose's own: the radius fitted with that pose held ([`fit_rounding`]).
    EachOwn,
}

/// Which photo ridge on a search line a model edge sample is matched to.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum RidgeChoice {
    /// The strongest, weighed down with the distance (a Gaussian prior of half the search
    /// radius for the nearest).
    #[default]
    Strongest,
    /// The nearest line-like ridge at least `min_query_ridge` strong (the multiple-hypothesis
    /// moving edges of L. Vacchetti, V. Lepetit, P. Fua, "Combining edge and texture information
    /// for real-time accurate 3D camera tracking", ISMAR 2004: each sample follows the
    /// hypothesis closest to where the current pose puts it).
    Nearest,
}

/// Which alignment the final refinement runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum RefineMethod {
    /// Moving edges only.
    #[default]
    Edges,
    /// The dense feature-metric alignment only.
    Dense,
    /// Moving edges, then the dense alignment from where they ended.
    EdgesThenDense,
}

impl RefineMethod {
    pub fn runs_edges(self) -> bool {
        self != Self::Dense
    }
    pub fn runs_dense(self) -> bool {
        self != Self::Edges
    }
}

/// Which kinds of model edge samples the alignment's steps use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum AlignedKinds {
    /// Contours and creases.
    #[default]
    All,
    /// Occluding contours (depth steps) only.
    Contours,
    /// Creases only.
    Creases,
}

impl AlignedKinds {
    pub fn includes(self, kind: EdgeKind) -> bool {
        match self {
            Self::All => true,
            Self::Contours => kind == EdgeKind::Contour,
            Self::Creases => kind != EdgeKind::Contour,
        }
    }
}

impl Default for EdgeAlignConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            min_model_ridge: 0.2,
            sample_spacing_px: 3,
            min_query_ridge: 0.05,
            initial_search_radius_px: 16.0,
            final_search_radius_px: 2.0,
            iterations_per_level: 4,
            support_px: 1.0,
            evidence_radius_px: 4.0,
            min_samples: 40,
            estimate_rounding: true,
            rounding_kinds: AlignedKinds::All,
            rounding_judge: RoundingJudge::Shared,
            aligned_kinds: AlignedKinds::All,
            starts: 3,
            check_levels: false,
            method: RefineMethod::Edges,
            dense: crate::core::feature_align::DenseAlignConfig::default(),
            ridge_choice: RidgeChoice::Strongest,
            distinct_weights: false,
            coarse_rotation_only: false,
            consensus: super::edge_consensus::EdgeConsensusConfig::default(),
            keep_rule: KeepRule::Support,
            short_schedule_radius_px: 8.0,
            short_schedule_rule: KeepRule::SupportAndCorrelation,
            centre_starts: true,
            rival_directions: 3,
            rival_reach_px: 30.0,
            rival_share_above_chance: 1.0,
            rival_centres: true,
        }
    }
}

/// Why a setting of [`EdgeAlignConfig`] is unusable.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("edge_align.{field}: {why}")]
pub struct EdgeAlignConfigError {
    pub field: &'static str,
    pub why: String,
}

impl EdgeAlignConfig {
    pub fn validate(&self) -> Result<(), EdgeAlignConfigError> {
        let bad = |field: &'static str, why: String| Err(EdgeAlignConfigError { field, why });
        for (field, value) in [
            ("min_model_ridge", f64::from(self.min_model_ridge)),
            ("min_query_ridge", f64::from(self.min_query_ridge)),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(field, format!("{value} is not a non-negative number"));
            }
        }
        for (field, value) in [
            ("initial_search_radius_px", self.initial_search_radius_px),
            ("final_search_radius_px", self.final_search_radius_px),
            ("support_px", self.support_px),
            ("evidence_radius_px", self.evidence_radius_px),
            ("rival_reach_px", self.rival_reach_px),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return bad(field, format!("{value} is not a positive number"));
            }
        }
        if self.final_search_radius_px > self.initial_search_radius_px {
            return bad(
                "final_search_radius_px",
                "must not exceed initial_search_radius_px".into(),
            );
        }
        if self.sample_spacing_px == 0 {
            return bad("sample_spacing_px", "must be at least 1".into());
        }
        if self.min_samples < 6 {
            return bad("min_samples", "must be at least 6 (six unknowns)".into());
        }
        if !(self.rival_share_above_chance.is_finite() && self.rival_share_above_chance > 0.0) {
            return bad(
                "rival_share_above_chance",
                format!("{} is not a positive number", self.rival_share_above_chance),
            );
        }
        if self.rival_directions > 6 {
            return bad(
                "rival_directions",
                format!("{} exceeds the pose's 6 directions", self.rival_directions),
            );
        }
        if self.starts == 0 {
            return bad("starts", "must be at least 1 (the chosen pose)".into());
        }
        if let Some((field, why)) = self.consensus.invalid() {
            return bad(field, why);
        }
        if self.consensus.then_search_radius_px < self.final_search_radius_px {
            return bad(
                "consensus.then_search_radius_px",
                "must not be below final_search_radius_px".into(),
            );
        }
        let short_px = self.short_schedule_radius_px;
        if !(short_px == 0.0
            || (short_px >= self.final_search_radius_px
                && short_px < self.initial_search_radius_px))
        {
            return bad(
                "short_schedule_radius_px",
                format!(
                    "{short_px} is neither 0 (no second schedule) nor within \
                     [final_search_radius_px, initial_search_radius_px)"
                ),
            );
        }
        Ok(())
    }

    /// The settings of the second, shorter schedule (levels from `short_schedule_radius_px`
    /// down), `None` when there is none.
    pub fn short_schedule(&self) -> Option<EdgeAlignConfig> {
        (self.short_schedule_radius_px > 0.0).then_some(EdgeAlignConfig {
            initial_search_radius_px: self.short_schedule_radius_px,
            short_schedule_radius_px: 0.0,
            ..*self
        })
    }

    /// The settings of the alignment from the consensus step's pose: the levels from
    /// `consensus.then_search_radius_px` down, no second schedule.
    pub fn after_consensus(&self) -> EdgeAlignConfig {
        EdgeAlignConfig {
            initial_search_radius_px: self.consensus.then_search_radius_px,
            short_schedule_radius_px: 0.0,
            ..*self
        }
    }

    /// The search half-lengths of the levels, coarse to fine (px).
    pub fn level_radii_px(&self) -> Vec<f64> {
        let mut radii = vec![self.initial_search_radius_px];
        while let Some(&last) = radii.last() {
            let next = last / 2.0;
            if next < self.final_search_radius_px * 0.999 {
                break;
            }
            radii.push(next);
        }
        if let Some(last) = radii.last_mut() {
            *last = last.max(self.final_search_radius_px);
        }
        radii
    }
}

/// What kind of model edge a sample lies on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum EdgeKind {
    /// An occluding contour: the surface on one side, a farther one (or none) on the other.
    Contour,
    /// A crease whose faces meet at an outward (convex) angle.
    ConvexCrease,
    /// A crease whose faces meet at an inward (concave) angle.
    ConcaveCrease,
}

/// One model edge sample: a 3D point on a crease or occluding contour and the direction across
/// the edge in the image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EdgeSample {
    pub world_m: Vector3<f64>,
    /// Unit vector across the edge in the image (the search direction).
    pub normal: Vector2<f64>,
    pub kind: EdgeKind,
    /// Where the sharp edge lies from this sample per metre of the model's edge rounding radius
    /// ρ (world frame, m/m): a model made by smoothing (Poisson-like) rounds every edge with a
    /// roughly constant radius, so its ASG ridge lies mid-arc and its contour inside the sharp
    /// one. For two faces with unit normals n₁, n₂ tangent to an arc of radius ρ, the sharp edge
    /// lies ρ·(1/cos(φ/2) − 1) from mid-arc along the faces' bisector b (φ: the angle between
    /// the normals; outward for a convex crease, inward for a concave one); a contour whose
    /// tangent normal u (⟂ the ray) makes angle α with the visible face's normal lies
    /// ρ·(cos α + sin α − 1) inside the sharp edge's, along u (right-angled edges). Zero when the
    /// rendering cannot tell.
    pub rounding: Vector3<f64>,
    /// Unit direction (world) from the sample towards where the sharp edge lies (the sign of
    /// [`EdgeSample::rounding`], also where its factor is 0); zero when unknown.
    pub outward: Vector3<f64>,
}

impl EdgeSample {
    /// [`EdgeSample::rounding`] when the rounding is undone on `kinds`' samples, else zero.
    pub fn rounding_on(&self, kinds: AlignedKinds) -> Vector3<f64> {
        if kinds.includes(self.kind) {
            self.rounding
        } else {
            Vector3::zeros()
        }
    }

    /// The sample's point with the model's edge rounding `rounding_m` undone (on `kinds`).
    pub fn sharp_point_m(&self, rounding_m: f64, kinds: AlignedKinds) -> Vector3<f64> {
        self.world_m + self.rounding_on(kinds) * rounding_m
    }
}

/// How well a pose's model edges are seen in the photo.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EdgeEvidence {
    /// Model edge samples at the pose.
    pub samples: usize,
    /// Samples with a photo ridge within the evidence radius.
    pub matched: usize,
    /// Samples with a photo ridge within `support_px`.
    pub supported: usize,
    /// Median distance to the matched photo ridges, px (0 when none matched).
    pub median_distance_px: f64,
    /// Median distance to the photo ridges of the supported samples, px (0 when none is
    /// supported): how precisely the supported edges sit on their ridges (a pose a few px off
    /// supported by coincidental ridges spreads them over `0..support_px`; results written before
    /// it existed read as 0).
    #[serde(default)]
    pub supported_median_px: f64,
    /// Samples with a photo ridge within half of `support_px` (support at a tighter radius;
    /// results written before it existed read as 0).
    #[serde(default)]
    pub tightly_supported: usize,
}

impl EdgeEvidence {
    /// Share of model edge samples with a photo ridge within half of `support_px` (0 when there
    /// are none).
    pub fn tight_support_fraction(&self) -> f64 {
        self.share_of_samples(self.tightly_supported)
    }

    /// `count` over the model edge samples (0 when there are none).
    fn share_of_samples(&self, count: usize) -> f64 {
        if self.samples == 0 {
            0.0
        } else {
            count as f64 / self.samples as f64
        }
    }

    /// Share of model edge samples supported by a photo ridge (0 when there are none).
    pub fn support_fraction(&self) -> f64 {
        self.share_of_samples(self.supported)
    }
}

/// `samples` with the model's edge rounding `rounding_m` undone (each point moved to
/// [`EdgeSample::sharp_point_m`]) into `out` (cleared first).
pub fn sharpened_samples(
    samples: &[EdgeSample],
    rounding_m: f64,
    kinds: AlignedKinds,
    out: &mut Vec<EdgeSample>,
) {
    out.clear();
    out.extend(samples.iter().map(|sample| EdgeSample {
        world_m: sample.sharp_point_m(rounding_m, kinds),
        ..*sample
    }));
}

/// A cell's strongest ridge pixel: (strength, position px, normal, depth m, pixel).
type CellRidge = (f32, Vector2<f64>, Vector2<f64>, f32, (usize, usize));

/// The model edge samples of a rendering at `cam_from_world` into `out` (cleared first).
/// `asg` is the rendering's ASG (0..1), `render` its depth and normals.
pub fn model_edge_samples(
    asg: ImageView<'_, f32>,
    render: &RenderBuffers,
    camera: &Camera,
    cam_from_world: &Rigid3,
    config: &EdgeAlignConfig,
    out: &mut Vec<EdgeSample>,
) {
    out.clear();
    let (width_px, height_px) = asg.size();
    let depth_m = render.depth_m().view();
    if depth_m.size() != (width_px, height_px) || width_px < 5 || height_px < 5 {
        return;
    }
    let world_from_cam = cam_from_world.inverse();
    let spacing = config.sample_spacing_px;
    let cells_x = width_px.div_ceil(spacing);
    let cells_y = height_px.div_ceil(spacing);
    let mut best: Vec<Option<CellRidge>> = vec![None; cells_x * cells_y];
    let at = |col: usize, row: usize| asg.data()[row * width_px + col];
    for row in 2..height_px - 2 {
        for col in 2..width_px - 2 {
            let centre = at(col, row);
            if centre < config.min_model_ridge {
                continue;
            }
            let Some(normal) = ridge_normal(&asg, col, row) else {
                continue;
            };
            let position = pixel_center(col, row);
            let (Some(ahead), Some(behind)) = (
                bilinear(&asg, position + normal),
                bilinear(&asg, position - normal),
            ) else {
                continue;
            };
            if centre < ahead || centre <= behind {
                continue;
            }
            let cell = (row / spacing) * cells_x + col / spacing;
            if best[cell].is_some_and(|(strength, ..)| centre <= strength) {
                continue;
            }
            let ridge_px =
                position + normal * parabola_peak(behind, centre, ahead).clamp(-0.5, 0.5);
            // The ridge at the occluding side's depth. (Moving a rounded crease's sample to where
            // its faces' planes meet was measured worse on the degraded block: 2.79 → 3.06 px.)
            let depth = nearest_depth_m(&depth_m, col, row);
            if depth > 0.0 {
                best[cell] = Some((centre, ridge_px, normal, depth, (col, row)));
            }
        }
    }
    for (_, position_px, normal, depth, pixel) in best.into_iter().flatten() {
        let Some(ray) = camera.unproject(position_px) else {
            continue;
        };
        let point_cam = ray * f64::from(depth);
        let geometry = edge_geometry(render, camera, pixel, &point_cam, normal);
        out.push(EdgeSample {
            world_m: world_from_cam.transform_point(&point_cam),
            normal,
            kind: geometry.kind,
            rounding: world_from_cam.transform_vector(&geometry.rounding_cam),
            outward: world_from_cam.transform_vector(&geometry.outward_cam),
        });
    }
}

/// Distance either side of a ridge at which its two surfaces are read, px.
const EDGE_PROBE_PX: f64 = 3.0;
/// A depth ratio across the ridge above this makes it an occluding contour.
const CONTOUR_DEPTH_RATIO: f32 = 1.1;

/// The kind and rounding geometry of an edge (camera frame) of [`EdgeSample`].
struct EdgeGeometry {
    kind: EdgeKind,
    rounding_cam: Vector3<f64>,
    outward_cam: Vector3<f64>,
}

/// Reads the rendering [`EDGE_PROBE_PX`] either side of the ridge at `pixel` (across `normal`):
/// a depth step or no surface on one side is a contour, else a crease between the two sides'
/// faces.
fn edge_geometry(
    render: &RenderBuffers,
    camera: &Camera,
    pixel: (usize, usize),
    point_cam: &Vector3<f64>,
    normal: Vector2<f64>,
) -> EdgeGeometry {
    let unknown = EdgeGeometry {
        kind: EdgeKind::ConvexCrease,
        rounding_cam: Vector3::zeros(),
        outward_cam: Vector3::zeros(),
    };
    let centre = pixel_center(pixel.0, pixel.1);
    let (width_px, height_px) = (render.width_px(), render.height_px());
    let side = |sign: f64| -> Option<(f32, Vector3<f64>, Vector3<f64>)> {
        let (col, row) = nearest_pixel(
            centre + normal * (sign * EDGE_PROBE_PX),
            width_px,
            height_px,
        )?;
        let depth = render.depth_m().data()[row * width_px + col];
        if depth <= 0.0 {
            return None;
        }
        let n = render.normal_cam().data()[row * width_px + col];
        let ray = camera.unproject(pixel_center(col, row))?;
        Some((
            depth,
            ray * f64::from(depth),
            Vector3::new(f64::from(n.x), f64::from(n.y), f64::from(n.z)),
        ))
    };
    let (ahead, behind) = (side(1.0), side(-1.0));
    // The contour's outward side (+1: along `normal`), and its visible face's normal.
    let contour = match (ahead, behind) {
        (None, None) => return unknown,
        (None, Some((_, _, n))) => Some((1.0, n)),
        (Some((_, _, n)), None) => Some((-1.0, n)),
        (Some((da, _, na)), Some((db, _, nb))) => {
            if da > db * CONTOUR_DEPTH_RATIO {
                Some((1.0, nb))
            } else if db > da * CONTOUR_DEPTH_RATIO {
                Some((-1.0, na))
            } else {
                None
            }
        }
    };
    if let Some((sign, face_normal)) = contour {
        // The lateral direction (⟂ the ray) whose projection moves along ±normal.
        let ray = point_cam.normalize();
        let along = Vector3::new(sign * normal.x, sign * normal.y, 0.0);
        let lateral = along - ray * along.dot(&ray);
        let Some(u) = lateral.try_normalize(1e-12) else {
            return unknown;
        };
        let cos_alpha = face_normal.dot(&u).clamp(0.0, 1.0);
        let sin_alpha = (1.0 - cos_alpha * cos_alpha).sqrt();
        return EdgeGeometry {
            kind: EdgeKind::Contour,
            rounding_cam: u * (cos_alpha + sin_alpha - 1.0).max(0.0),
            outward_cam: u,
        };
    }
    let (Some((_, point_a, normal_a)), Some((_, point_b, normal_b))) = (ahead, behind) else {
        return unknown;
    };
    let Some(bisector) = (normal_a + normal_b).try_normalize(1e-9) else {
        return unknown;
    };
    let cos_phi = normal_a.dot(&normal_b).clamp(-1.0, 1.0);
    let factor = (2.0 / (1.0 + cos_phi)).sqrt() - 1.0;
    // Convex: each side lies behind the other side's face plane.
    let convex = (point_a - point_b).dot(&(normal_b - normal_a)) < 0.0;
    let (kind, outward) = if convex {
        (EdgeKind::ConvexCrease, bisector)
    } else {
        (EdgeKind::ConcaveCrease, -bisector)
    };
    EdgeGeometry {
        kind,
        rounding_cam: outward * factor,
        outward_cam: outward,
    }
}

/// The query image blurred for a level whose search half-length is `radius_px` (σ = radius / 4;
/// below 0.5 px σ the query is used as it is).
pub fn blurred_query(query: ImageView<'_, f32>, radius_px: f64, out: &mut Image<f32>) {
    let (width_px, height_px) = query.size();
    let sigma_px = (radius_px / 4.0) as f32;
    out.resize(width_px, height_px, 0.0);
    if sigma_px < 0.5 || query.is_empty() {
        out.data_mut().copy_from_slice(query.data());
        return;
    }
    let taps_radius = (3.0 * sigma_px).ceil() as usize;
    let taps = gaussian_taps(sigma_px, taps_radius);
    let mut scratch = vec![0.0f32; width_px * height_px];
    separable_filter_clamped(
        query.data(),
        width_px,
        height_px,
        1,
        &taps,
        taps_radius,
        &mut scratch,
        out.data_mut(),
    );
}

/// The photo ridge a search line crosses: its signed distance along the normal, and how
/// distinct it is from the other ridges on the line.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RidgeMatch {
    /// Signed distance along the search normal from the sample's projection, px.
    pub offset_px: f64,
    /// `1 − s₂/s₁`: 1 when it is the only ridge on the line, 0 when another is as strong (scores
    /// as [`RidgeChoice::Strongest`] weighs them, whichever ridge was chosen).
    pub distinctiveness: f64,
}

/// Signed distance along `normal` from `at_px` to the photo ridge crossing the search line, px;
/// `None` when no line-like ridge of at least `min_ridge` lies within `radius_px`. Among several
/// the strongest wins, weighed down with the distance (a prior for the nearest).
pub fn search_ridge(
    query: &ImageView<'_, f32>,
    at_px: Vector2<f64>,
    normal: Vector2<f64>,
    radius_px: f64,
    min_ridge: f32,
) -> Option<f64> {
    find_ridge(
        query,
        at_px,
        normal,
        radius_px,
        min_ridge,
        RidgeChoice::Strongest,
    )
    .map(|found| found.offset_px)
}

/// The photo ridge crossing the search line through `at_px` along `normal` within `radius_px`
/// that `choice` picks among the line-like ridges of at least `min_ridge`, with its
/// distinctiveness; `None` when there is none.
pub fn find_ridge(
    query: &ImageView<'_, f32>,
    at_px: Vector2<f64>,
    normal: Vector2<f64>,
    radius_px: f64,
    min_ridge: f32,
    choice: RidgeChoice,
) -> Option<RidgeMatch> {
    // The lattice of the search line ends within 2·64 + 3 values (radius 32 px).
    if 2 * ridge_lattice_steps(radius_px) + 1 > 2 * 64 + 3 {
        return None;
    }
    let tangent = Vector2::new(-normal.y, normal.x);
    // (score, offset) of the strongest and second-strongest ridges, and the nearest's offset.
    let mut best: Option<(f64, f64)> = None;
    let mut second_score = 0.0_f64;
    let mut nearest: Option<f64> = None;
    let width = 0.5 * radius_px;
    for_each_lattice_peak(
        query,
        at_px,
        normal,
        radius_px,
        min_ridge,
        |t, _, centre, _| {
            if t.abs() > radius_px {
                return;
            }
            // Line-like: curved across the search line, flatter along the ridge (1 px either way).
            let peak = at_px + normal * t;
            let (Some(across_a), Some(across_b), Some(along_a), Some(along_b)) = (
                bilinear(query, peak + normal),
                bilinear(query, peak - normal),
                bilinear(query, peak + tangent),
                bilinear(query, peak - tangent),
            ) else {
                return;
            };
            let curvature_across = across_a + across_b - 2.0 * centre;
            let curvature_along = along_a + along_b - 2.0 * centre;
            if !(curvature_across < 0.0 && curvature_across < 2.0 * curvature_along.min(0.0)) {
                return;
            }
            // Sub-pixel: a parabola through the logarithms 1 px either side (exact for a Gaussian
            // profile, which a blurred step's gradient magnitude is close to).
            let offset = t + log_parabola_peak(across_b, centre, across_a).clamp(-0.5, 0.5);
            let score = f64::from(centre) * (-(offset * offset) / (2.0 * width * width)).exp();
            match best {
                Some((best_score, _)) if score <= best_score => {
                    second_score = second_score.max(score)
                }
                _ => {
                    if let Some((best_score, _)) = best {
                        second_score = second_score.max(best_score);
                    }
                    best = Some((score, offset));
                }
            }
            if nearest.is_none_or(|n: f64| offset.abs() < n.abs()) {
                nearest = Some(offset);
            }
        },
    );
    let (best_score, strongest) = best?;
    let offset_px = match choice {
        RidgeChoice::Strongest => strongest,
        RidgeChoice::Nearest => nearest.unwrap_or(strongest),
    };
    Some(RidgeMatch {
        offset_px,
        distinctiveness: (1.0 - second_score / best_score).clamp(0.0, 1.0),
    })
}

/// Step of the lattice the ridge searches sample along a search line, px.
pub const RIDGE_LATTICE_STEP_PX: f64 = 0.5;

/// Lattice points either side of the search line's centre for a search within `radius_px`.
fn ridge_lattice_steps(radius_px: f64) -> i32 {
    (radius_px / RIDGE_LATTICE_STEP_PX).ceil() as i32 + 1
}

/// The one scan of a search line for ridges ([`find_ridge`], `edge_consensus::ridge_offsets`):
/// `query` sampled every [`RIDGE_LATTICE_STEP_PX`] along the line through `at_px` along `normal`
/// out to just beyond `radius_px`, and `visit(t_px, before, centre, after)` called for each local
/// maximum at least `min_ridge` strong (its lattice offset and the three values around it);
/// values off the image are NaN, so no peak lies next to the border.
pub fn for_each_lattice_peak(
    query: &ImageView<'_, f32>,
    at_px: Vector2<f64>,
    normal: Vector2<f64>,
    radius_px: f64,
    min_ridge: f32,
    mut visit: impl FnMut(f64, f32, f32, f32),
) {
    let steps = ridge_lattice_steps(radius_px);
    let value = |i: i32| {
        bilinear(
            query,
            at_px + normal * (f64::from(i) * RIDGE_LATTICE_STEP_PX),
        )
        .unwrap_or(f32::NAN)
    };
    let (mut before, mut centre) = (value(-steps), value(-steps + 1));
    for i in -steps + 1..steps {
        let after = value(i + 1);
        if centre >= min_ridge && centre >= before && centre > after {
            visit(f64::from(i) * RIDGE_LATTICE_STEP_PX, before, centre, after);
        }
        (before, centre) = (centre, after);
    }
}

/// Each sample of `samples` that projects into the image at `cam_from_world`, with its point in
/// the camera frame and the photo ridge's offset along its normal within
/// `config.evidence_radius_px` ([`search_ridge`]; `None` when there is none): the one loop of
/// [`edge_evidence`] and [`image_uncertainty_px`].
fn for_each_ridge(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    config: &EdgeAlignConfig,
    mut visit: impl FnMut(&EdgeSample, &Vector3<f64>, Option<f64>),
) {
    for sample in samples {
        let point_cam = cam_from_world.transform_point(&sample.world_m);
        let Some(projected) = camera.project(&point_cam) else {
            continue;
        };
        let offset = search_ridge(
            query,
            projected,
            sample.normal,
            config.evidence_radius_px,
            config.min_query_ridge,
        );
        visit(sample, &point_cam, offset);
    }
}

/// The evidence of the pose whose model edge samples are `samples`: searched in `query` (as it is)
/// within `config.evidence_radius_px`.
pub fn edge_evidence(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    config: &EdgeAlignConfig,
) -> EdgeEvidence {
    let mut distances: Vec<f64> = Vec::with_capacity(samples.len());
    for_each_ridge(
        samples,
        query,
        camera,
        cam_from_world,
        config,
        |_, _, offset| {
            if let Some(offset) = offset {
                distances.push(offset.abs());
            }
        },
    );
    let tightly_supported = distances
        .iter()
        .filter(|d| **d <= 0.5 * config.support_px)
        .count();
    let matched = distances.len();
    let median_distance_px = median_of(&mut distances);
    distances.retain(|d| *d <= config.support_px);
    let supported = distances.len();
    let supported_median_px = median_of(&mut distances);
    EdgeEvidence {
        samples: samples.len(),
        matched,
        supported,
        median_distance_px,
        supported_median_px,
        tightly_supported,
    }
}

/// The median of `values` (the upper one of an even count; 0 when empty); reorders them.
fn median_of(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let middle = values.len() / 2;
    let (_, median, _) = values.select_nth_unstable_by(middle, f64::total_cmp);
    *median
}

/// How sharply a pose's edge support peaks: the support at the pose, and at poses turned so that
/// the image moves by a few pixels (where a correct pose's edges leave their photo ridges) and by
/// many (where only chance keeps them: the photo's clutter). A wrong pose that several coarse
/// poses agree on is a basin of the flow, not of the photo's edges; its support is near chance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SupportPeak {
    /// Share of model edge samples supported at the pose (as [`EdgeEvidence::support_fraction`]).
    pub at_pose: f64,
    /// Mean share at the eight poses whose image moves by `near_shift_px`.
    pub near: f64,
    /// Mean share at the eight poses whose image moves by `far_shift_px` (chance level).
    pub far: f64,
    pub near_shift_px: f64,
    pub far_shift_px: f64,
    /// [`image_uncertainty_px`] at the pose: how far the frame's image may move per px of edge
    /// noise given the supported edges ([`UNBOUNDED_IMAGE_UNCERTAINTY_PX`] when they leave a
    /// direction free; results written before it existed read as 0).
    #[serde(default)]
    pub image_uncertainty_px: f64,
    /// [`delta_uncertainty_px`] at the pose: the visible model's expected motion (δ) per px of
    /// edge noise given the supported edges ([`UNBOUNDED_IMAGE_UNCERTAINTY_PX`] when a direction
    /// is free or the model's rendering was not at hand; results written before it existed read
    /// as 0).
    #[serde(default)]
    pub delta_uncertainty_px: f64,
    /// Mean share supported at the two poses the direction the edges see least
    /// ([`least_seen_step`]) reaches when the visible model moves by `near_shift_px` (and by
    /// `far_shift_px`, next) either way; 0 without the model's rendering (or in older files).
    #[serde(default)]
    pub least_seen_near: f64,
    #[serde(default)]
    pub least_seen_far: f64,
    /// The highest support over image shifts of the model's edges within a wide reach
    /// ([`widest_support`]); measured only for a pose whose support is near chance, to tell a
    /// photo that shows none of the model's edges from one that shows them elsewhere (`None`:
    /// not measured).
    #[serde(default)]
    pub widest: Option<WidestSupport>,
}

/// [`SupportPeak::widest`]: the highest share of supported samples over the shifts tried, and
/// how many samples were moved (the shares' noise).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WidestSupport {
    pub support: f64,
    pub samples: usize,
}

/// How far above chance, in standard errors of one share at chance over the samples
/// [`widest_support`] moved, a support may lie and still be chance
/// ([`SupportPeak::at_chance_everywhere`]). The highest of thousands of shares at chance lies
/// a few standard errors above it (Brighton's frames, whose photos show none of the mesh's
/// edges: 3.3–4.2); a photo that shows the model's edges gives far more where they are
/// (the synthetic block s1's view_006 at 104 px, 0.22 above chance over 512 samples: 11).
pub const AT_CHANCE_SIGMAS: f64 = 6.0;

impl SupportPeak {
    /// Whether no support measured near the pose (at it, on both rings and along the least
    /// seen direction) exceeds chance (`far`) by `min_above_chance` (a cheap first test before
    /// the wide one, [`Self::at_chance_everywhere`]).
    pub fn at_chance_near(&self, min_above_chance: f64) -> bool {
        [
            self.at_pose,
            self.near,
            self.least_seen_near,
            self.least_seen_far,
        ]
        .iter()
        .all(|support| support - self.far < min_above_chance)
    }

    /// Whether the photo shows none of the model's edges wherever they were moved: no support
    /// measured — at the pose, on both rings, along the least seen direction and over the wide
    /// reach ([`Self::widest`], which must have been measured) — lies more than
    /// [`AT_CHANCE_SIGMAS`] standard errors of a share at chance above chance (`far`).
    pub fn at_chance_everywhere(&self) -> bool {
        let Some(widest) = self.widest else {
            return false;
        };
        let chance = self.far.clamp(0.0, 1.0);
        let sigma = (chance * (1.0 - chance) / widest.samples.max(1) as f64).sqrt();
        [
            self.at_pose,
            self.near,
            self.least_seen_near,
            self.least_seen_far,
            widest.support,
        ]
        .iter()
        .all(|support| support - self.far <= AT_CHANCE_SIGMAS * sigma)
    }

    /// The share of the support above chance (`at_pose − far`) lost where the least seen
    /// direction moves the model by the far ring's shift: 1 when the support there is at
    /// chance, 0 (or less) when it is as high as at the pose. 0 without support above chance.
    pub fn least_seen_drop(&self) -> f64 {
        self.drop_to(self.least_seen_far)
    }

    /// [`Self::least_seen_drop`] at the near ring's shift (`least_seen_near`).
    pub fn least_seen_near_drop(&self) -> f64 {
        self.drop_to(self.least_seen_near)
    }

    /// The support at the pose above chance (the far ring's): the margin the edge gates judge.
    pub fn above_chance(&self) -> f64 {
        self.at_pose - self.far
    }

    /// The share of the support above chance lost where the support is `moved`; 0 without
    /// support above chance.
    fn drop_to(&self, moved: f64) -> f64 {
        let above_chance = self.above_chance();
        if above_chance <= 0.0 {
            return 0.0;
        }
        (self.at_pose - moved) / above_chance
    }
}

/// Image shifts of [`support_peak`]'s two rings, px: the near one just beyond the final search
/// radius (a correct pose loses most support), the far one beyond the evidence radius (only
/// chance supports).
pub const SUPPORT_PEAK_SHIFTS_PX: [f64; 2] = [3.0, 12.0];

/// The edge support of `samples` (lifted at `cam_from_world`, whose own evidence is `at_pose`)
/// at poses turned about the camera's x and y axes so that the image moves by each of
/// [`SUPPORT_PEAK_SHIFTS_PX`] in eight directions (no re-rendering: the samples are kept).
pub fn support_peak(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    at_pose: &EdgeEvidence,
    model_metric: Option<&Matrix6<f64>>,
    config: &EdgeAlignConfig,
) -> SupportPeak {
    let ring = |shift_px: f64| {
        let mut total = 0.0;
        for direction in 0..8 {
            let angle = direction as f64 * std::f64::consts::FRAC_PI_4;
            let turned = turned_by_image_shift(
                cam_from_world,
                camera,
                shift_px * angle.cos(),
                shift_px * angle.sin(),
            );
            total += edge_evidence(samples, query, camera, &turned, config).support_fraction();
        }
        total / 8.0
    };
    let [near_shift_px, far_shift_px] = SUPPORT_PEAK_SHIFTS_PX;
    let supported = supported_information(samples, query, camera, cam_from_world, config);
    let delta_uncertainty_px = model_metric.map_or(UNBOUNDED_IMAGE_UNCERTAINTY_PX, |metric| {
        delta_uncertainty_px(&supported.information, metric)
    });
    // Support where the least seen direction moves the model by each ring's shift (both ways).
    let least_seen =
        model_metric.and_then(|metric| least_seen_step(&supported.information, metric));
    let along_least_seen = |shift_px: f64| {
        least_seen.map_or(0.0, |step| {
            [1.0, -1.0]
                .iter()
                .map(|sign| {
                    let moved = apply_pose_step(cam_from_world, &(step * (sign * shift_px)));
                    edge_evidence(samples, query, camera, &moved, config).support_fraction()
                })
                .sum::<f64>()
                / 2.0
        })
    };
    SupportPeak {
        at_pose: at_pose.support_fraction(),
        near: ring(near_shift_px),
        far: ring(far_shift_px),
        near_shift_px,
        far_shift_px,
        least_seen_near: along_least_seen(near_shift_px),
        least_seen_far: along_least_seen(far_shift_px),
        image_uncertainty_px: image_uncertainty_of(supported, camera),
        delta_uncertainty_px,
        widest: None,
    }
}

/// `cam_from_world` turned about the camera's x and y axes so that the image near the principal
/// point moves by (`dx_px`, `dy_px`) (no re-rendering: what [`support_peak`]'s rings and
/// [`widest_support`] move the samples by).
fn turned_by_image_shift(
    cam_from_world: &Rigid3,
    camera: &Camera,
    dx_px: f64,
    dy_px: f64,
) -> Rigid3 {
    let focal_px = 0.5 * (camera.intrinsics.fx_px + camera.intrinsics.fy_px);
    // A small turn ω moves a point on the axis by (f ω_y, −f ω_x) in the image.
    let turn = Vector3::new(-dy_px / focal_px, dx_px / focal_px, 0.0);
    let delta = UnitQuaternion::from_scaled_axis(turn);
    Rigid3::new(
        delta * cam_from_world.rotation,
        delta * cam_from_world.translation,
    )
}

/// At most this many of a pose's edge samples (evenly taken) are moved by [`widest_support`]: a
/// share over 512 samples has a standard error of at most 0.022, so the [`AT_CHANCE_SIGMAS`]
/// bound is at most 0.13 above chance, well below the 0.23 an accept asks of the edges, at a
/// fraction of the cost of thousands (Brighton's frames: 6–9 s of CPU a frame with all their
/// samples).
pub const WIDEST_SUPPORT_MAX_SAMPLES: usize = 512;

/// The highest edge support of `samples` (lifted at `cam_from_world`; at most
/// [`WIDEST_SUPPORT_MAX_SAMPLES`] of them, evenly taken) over image shifts within `reach_px` of
/// the pose, on a square grid of `config.support_px`·√2 (so that every shift in the reach lies
/// within `support_px` of a grid point: a peak as sharp as the support's own tolerance is not
/// stepped over). Cost: about (2·reach / (√2·support_px))² evaluations of the evidence, so it
/// is measured only where it decides something ([`SupportPeak::widest`]). The maximum over
/// thousands of shifts lies above chance by a few hundredths even where the photo shows none
/// of the model's edges (the noise of the shares).
pub fn widest_support(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    reach_px: f64,
    config: &EdgeAlignConfig,
) -> WidestSupport {
    let stride = samples.len().div_ceil(WIDEST_SUPPORT_MAX_SAMPLES).max(1);
    let taken: Vec<EdgeSample> = samples.iter().step_by(stride).copied().collect();
    let samples = taken.as_slice();
    let step_px = config.support_px.max(0.25) * std::f64::consts::SQRT_2;
    let count = (reach_px.max(0.0) / step_px).floor() as i64;
    let mut widest = 0.0f64;
    for i in -count..=count {
        for j in -count..=count {
            let (dx_px, dy_px) = (i as f64 * step_px, j as f64 * step_px);
            if dx_px.hypot(dy_px) > reach_px {
                continue;
            }
            let shifted = turned_by_image_shift(cam_from_world, camera, dx_px, dy_px);
            let share = edge_evidence(samples, query, camera, &shifted, config).support_fraction();
            widest = widest.max(share);
        }
    }
    WidestSupport {
        support: widest,
        samples: samples.len(),
    }
}

/// [`image_uncertainty_px`] of a pose its supported edges do not fix (a finite stand-in for
/// infinity, so that JSON keeps it).
pub const UNBOUNDED_IMAGE_UNCERTAINTY_PX: f64 = 1e6;

/// How firmly the photo's edges fix the pose: the RMS image motion, px, of a 5 × 5 grid of points
/// spread over the frame (at the samples' median depth) under the pose covariance that the
/// *supported* model edge samples give when each is measured with 1 px of noise along its
/// normal (Gauss–Newton information `Σ JᵀJ` of the 1-D residuals, inverted). A pose whose support
/// comes from a sliver of the model in a corner, or from parallel lines only, leaves most of the
/// frame free: its figure is large (infinite when the information is singular), however high its
/// support share. A correct pose of a well-seen model is fixed to a fraction of a pixel.
/// [`UNBOUNDED_IMAGE_UNCERTAINTY_PX`] when a direction is free.
pub fn image_uncertainty_px(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    config: &EdgeAlignConfig,
) -> f64 {
    image_uncertainty_of(
        supported_information(samples, query, camera, cam_from_world, config),
        camera,
    )
}

/// [`image_uncertainty_px`] from the supported edges' information.
fn image_uncertainty_of(supported: SupportedInformation, camera: &Camera) -> f64 {
    let intrinsics = &camera.intrinsics;
    let SupportedInformation {
        information,
        mut depths_m,
        ..
    } = supported;
    if depths_m.is_empty() {
        return UNBOUNDED_IMAGE_UNCERTAINTY_PX;
    }
    let middle = depths_m.len() / 2;
    let (_, depth_m, _) = depths_m.select_nth_unstable_by(middle, f64::total_cmp);
    let depth_m = *depth_m;
    // Scale the rotation and translation parts alike (ω in rad and t in m differ by the depth)
    // before inverting, so that a well-posed pose does not look singular by units alone.
    let scale =
        nalgebra::Matrix6::from_diagonal(&Vector6::new(1.0, 1.0, 1.0, depth_m, depth_m, depth_m));
    let scaled = scale * information * scale;
    let Some(covariance_scaled) = scaled.try_inverse() else {
        return UNBOUNDED_IMAGE_UNCERTAINTY_PX;
    };
    let eigen = scaled.symmetric_eigenvalues();
    if eigen.min() <= eigen.max() * 1e-12 {
        return UNBOUNDED_IMAGE_UNCERTAINTY_PX;
    }
    let covariance = scale * covariance_scaled * scale;
    const GRID: usize = 5;
    let mut total = 0.0;
    for row in 0..GRID {
        for col in 0..GRID {
            let pixel = Vector2::new(
                (col as f64 + 0.5) / GRID as f64 * f64::from(camera.width_px),
                (row as f64 + 0.5) / GRID as f64 * f64::from(camera.height_px),
            );
            let normalized = intrinsics.pixel_to_normalized(pixel);
            let point_cam = Vector3::new(normalized.x, normalized.y, 1.0) * depth_m;
            let (row_u, row_v) = pose_jacobian_rows(intrinsics, &point_cam);
            total += (row_u.transpose() * covariance * row_u)[0]
                + (row_v.transpose() * covariance * row_v)[0];
        }
    }
    (total / (GRID * GRID) as f64)
        .max(0.0)
        .sqrt()
        .min(UNBOUNDED_IMAGE_UNCERTAINTY_PX)
}

/// What one level of alignment did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LevelSummary {
    pub search_radius_px: f64,
    pub steps: usize,
    /// Matched samples at the last step.
    pub matched: usize,
    /// Robust scale of the distances at the last step, px.
    pub scale_px: f64,
    /// The model's edge rounding radius after the level, m (0 unless estimated).
    #[serde(default)]
    pub rounding_m: f64,
    /// The level's result lowered the edge support and was undone (`check_levels`).
    #[serde(default)]
    pub reverted: bool,
}

/// What the alignment may change.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum AlignedParameters {
    /// Rotation and translation (known intrinsics).
    Pose,
    /// The pose and one focal scale for `fx` and `fy` together (intrinsics estimated by the DLT:
    /// the focal length is what a drone's EXIF leaves most uncertain); the principal point and
    /// skew stay.
    PoseAndFocal,
}

/// One level of alignment from `camera` at `cam_from_world`: `iterations` rounds of search in
/// `query` (already blurred for the level) and a robust Gauss–Newton step. With
/// `config.estimate_rounding` the model's edge rounding radius `rounding_m` (each sample's point
/// is [`EdgeSample::sharp_point_m`]) is estimated with the pose, else it is used as it is.
/// Returns the new camera and pose and what happened; they are unchanged when too few samples
/// match.
#[allow(clippy::too_many_arguments)]
pub fn align_level(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    parameters: AlignedParameters,
    radius_px: f64,
    config: &EdgeAlignConfig,
    rounding_m: &mut f64,
) -> (Camera, Rigid3, LevelSummary) {
    let mut pose = *cam_from_world;
    let mut camera = *camera;
    let mut summary = LevelSummary {
        search_radius_px: radius_px,
        ..LevelSummary::default()
    };
    let mut matches: Vec<EdgeMatch> = Vec::with_capacity(samples.len());
    let rotation_only = config.coarse_rotation_only && radius_px > config.evidence_radius_px;
    for _ in 0..config.iterations_per_level {
        matches.clear();
        for sample in samples {
            if !config.aligned_kinds.includes(sample.kind) {
                continue;
            }
            let point_cam =
                pose.transform_point(&sample.sharp_point_m(*rounding_m, config.rounding_kinds));
            let Some(projected) = camera.project(&point_cam) else {
                continue;
            };
            if let Some(found) = find_ridge(
                query,
                projected,
                sample.normal,
                radius_px,
                config.min_query_ridge,
                config.ridge_choice,
            ) {
                let rounding_cam = pose.rotation * sample.rounding_on(config.rounding_kinds);
                let distinct_weight = if config.distinct_weights {
                    found.distinctiveness
                } else {
                    1.0
                };
                matches.push(EdgeMatch {
                    point_cam,
                    projected,
                    normal: sample.normal,
                    offset_px: found.offset_px,
                    rounding_cam,
                    distinct_weight,
                });
            }
        }
        summary.matched = matches.len();
        if matches.len() < config.min_samples {
            break;
        }
        let mut magnitudes: Vec<f64> = matches.iter().map(|m| m.offset_px.abs()).collect();
        let tukey = Tukey::of_offsets(&mut magnitudes);
        summary.scale_px = tukey.scale_px;
        let k = camera.intrinsics;
        let mut normal_matrix = Matrix8::zeros();
        let mut gradient = Vector8::zeros();
        for EdgeMatch {
            point_cam,
            projected,
            normal,
            offset_px: offset,
            rounding_cam,
            distinct_weight,
        } in &matches
        {
            let Some(weight) = tukey.weight(*offset) else {
                continue;
            };
            let weight = weight * distinct_weight;
            let (row_u, row_v) = pose_jacobian_rows(&k, point_cam);
            let mut g = Vector8::zeros();
            g.fixed_rows_mut::<6>(0)
                .copy_from(&(row_u * normal.x + row_v * normal.y));
            if rotation_only {
                g.fixed_rows_mut::<3>(3).fill(0.0);
            } else if parameters == AlignedParameters::PoseAndFocal {
                // u = fx·(1 + s)·x + skew·y + cx: du/ds = u − cx − skew·y ≈ u − cx.
                g[6] = (projected.x - k.cx_px) * normal.x + (projected.y - k.cy_px) * normal.y;
            }
            if config.estimate_rounding && !rotation_only {
                // The point moves with ρ along the rounding direction: the translation's rows.
                g[7] = (row_u.fixed_rows::<3>(3).dot(rounding_cam)) * normal.x
                    + (row_v.fixed_rows::<3>(3).dot(rounding_cam)) * normal.y;
            }
            normal_matrix += g * g.transpose() * weight;
            gradient += g * (weight * offset);
        }
        for i in 0..8 {
            normal_matrix[(i, i)] = normal_matrix[(i, i)] * (1.0 + 1e-3) + 1e-9;
        }
        let Some(step) = normal_matrix.cholesky().map(|c| c.solve(&gradient)) else {
            break;
        };
        if !step.iter().all(|v| v.is_finite()) {
            break;
        }
        pose = apply_pose_step(&pose, &step.fixed_rows::<6>(0).into_owned());
        if parameters == AlignedParameters::PoseAndFocal && !rotation_only {
            let scale = (1.0 + step[6]).clamp(0.8, 1.25);
            camera.intrinsics.fx_px *= scale;
            camera.intrinsics.fy_px *= scale;
        }
        if config.estimate_rounding && !rotation_only {
            // A rounding radius is not negative (smoothing only rounds).
            *rounding_m = (*rounding_m + step[7]).max(0.0);
        }
        summary.steps += 1;
    }
    summary.rounding_m = *rounding_m;
    (camera, pose, summary)
}

/// The robust weights of the alignment's Gauss–Newton steps: Tukey's biweight at 4.685 robust
/// standard deviations of the offsets (1.4826 × their median magnitude).
struct Tukey {
    scale_px: f64,
    c_px: f64,
}

impl Tukey {
    /// From the offsets' magnitudes (reordered).
    fn of_offsets(magnitudes_px: &mut [f64]) -> Self {
        // Floor: the search quantises to sub-pixel, no finer than ~0.2 px.
        let scale_px = (1.4826 * median_of(magnitudes_px)).max(0.2);
        Self {
            scale_px,
            c_px: 4.685 * scale_px,
        }
    }

    /// The weight of an offset; `None` beyond the cut-off.
    fn weight(&self, offset_px: f64) -> Option<f64> {
        let ratio = offset_px / self.c_px;
        (ratio.abs() < 1.0).then(|| (1.0 - ratio * ratio).powi(2))
    }
}

/// The model's edge rounding radius (m, ≥ 0) that best explains the offsets of `samples` to the
/// photo's ridges with the pose held at `cam_from_world`: the rounding unknown of
/// [`align_level`]'s steps alone, by the same robust (Tukey) Gauss–Newton at the last level's
/// search radius on `query` as it is, `config.iterations_per_level` steps from 0. 0 when fewer
/// than `config.min_samples` samples match.
pub fn fit_rounding(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    config: &EdgeAlignConfig,
) -> f64 {
    let mut rounding_m: f64 = 0.0;
    // (offset px, offset per metre of rounding px/m) per matched sample.
    let mut matches: Vec<(f64, f64)> = Vec::with_capacity(samples.len());
    let k = camera.intrinsics;
    for _ in 0..config.iterations_per_level {
        matches.clear();
        for sample in samples {
            let rounding = sample.rounding_on(config.rounding_kinds);
            if rounding == Vector3::zeros() {
                continue;
            }
            let point_cam = cam_from_world
                .transform_point(&sample.sharp_point_m(rounding_m, config.rounding_kinds));
            let Some(projected) = camera.project(&point_cam) else {
                continue;
            };
            let Some(found) = find_ridge(
                query,
                projected,
                sample.normal,
                config.final_search_radius_px,
                config.min_query_ridge,
                config.ridge_choice,
            ) else {
                continue;
            };
            let rounding_cam = cam_from_world.rotation * rounding;
            let (row_u, row_v) = pose_jacobian_rows(&k, &point_cam);
            let per_m = row_u.fixed_rows::<3>(3).dot(&rounding_cam) * sample.normal.x
                + row_v.fixed_rows::<3>(3).dot(&rounding_cam) * sample.normal.y;
            matches.push((found.offset_px, per_m));
        }
        if matches.len() < config.min_samples {
            return 0.0;
        }
        let mut magnitudes: Vec<f64> = matches.iter().map(|(offset, _)| offset.abs()).collect();
        let tukey = Tukey::of_offsets(&mut magnitudes);
        let (mut information, mut gradient) = (1e-9, 0.0);
        for &(offset, per_m) in &matches {
            let Some(weight) = tukey.weight(offset) else {
                continue;
            };
            information += weight * per_m * per_m;
            gradient += weight * per_m * offset;
        }
        let step = gradient / information;
        if !step.is_finite() {
            break;
        }
        rounding_m = (rounding_m + step).max(0.0);
    }
    rounding_m
}

/// The image-motion metric of a rendering's visible model: the mean over its surface pixels
/// (every `stride_px`-th row and column) of `JᵀJ`, `J` the 2 × 6 Jacobian of the pixel's
/// projection for the pose perturbation of [`pose_jacobian_rows`]; `ξᵀ M ξ` is then the mean
/// squared image motion of the model's visible points under a small step `ξ` (about δ², the
/// evaluation's measure). `None` when the rendering shows no surface.
pub fn image_motion_metric(
    render: &RenderBuffers,
    camera: &Camera,
    stride_px: usize,
) -> Option<Matrix6<f64>> {
    let depth_m = render.depth_m().view();
    let faces = render.face_index().view();
    let (width_px, height_px) = depth_m.size();
    let stride_px = stride_px.max(1);
    let mut metric = Matrix6::zeros();
    let mut count = 0usize;
    for row in (stride_px / 2..height_px).step_by(stride_px) {
        for col in (stride_px / 2..width_px).step_by(stride_px) {
            let depth = depth_m.data()[row * width_px + col];
            if faces.data()[row * width_px + col] == super::raster::NO_FACE || depth <= 0.0 {
                continue;
            }
            let Some(ray) = camera.unproject(pixel_center(col, row)) else {
                continue;
            };
            let (row_u, row_v) = pose_jacobian_rows(&camera.intrinsics, &(ray * f64::from(depth)));
            metric += row_u * row_u.transpose() + row_v * row_v.transpose();
            count += 1;
        }
    }
    (count > 0).then(|| metric / count as f64)
}

/// How well a pose's edges see each direction of pose motion: the generalized eigenvalues λ of
/// the edge samples' Gauss–Newton `information` (`Σ gᵀg` of the 1-D residuals along the normals,
/// over `samples` samples) against the model's image-motion `metric` ([`image_motion_metric`]),
/// as `√(λ / samples)`: along each eigen-direction, scaled to move the visible model by 1 px
/// RMS, how far the edges move along their normals (px RMS), ascending. A direction with a small
/// figure moves the model (the ground, the far side) while its edges barely move: an edge error
/// of ε px shifts the pose along it by ε / figure px of δ. `None` when the metric is singular or
/// there are no samples.
pub fn edge_observability(
    information: &Matrix6<f64>,
    samples: usize,
    metric: &Matrix6<f64>,
) -> Option<Vector6<f64>> {
    if samples == 0 {
        return None;
    }
    let eigenvalues = generalized_eigenvalues(information, metric)?;
    let mut figures: Vec<f64> = eigenvalues
        .iter()
        .map(|lambda| (lambda.max(0.0) / samples as f64).sqrt())
        .collect();
    figures.sort_by(f64::total_cmp);
    Some(Vector6::from_vec(figures))
}

/// The generalized eigenvalues λ of `information` against `metric` (`information v = λ metric v`):
/// per eigen-direction scaled to move the visible model by 1 px RMS, the information the edges
/// hold about it. `None` when the metric cannot be factorised.
fn generalized_eigenvalues(
    information: &Matrix6<f64>,
    metric: &Matrix6<f64>,
) -> Option<Vector6<f64>> {
    generalized_eigen(information, metric).map(|(eigen, _)| eigen.eigenvalues)
}

/// The eigen-decomposition of `information` whitened by `metric` (`L⁻¹ I L⁻ᵀ`, `metric = L Lᵀ`)
/// and `L⁻¹`: an eigenvector `u` is the pose step `L⁻ᵀ u` of the generalized problem.
fn generalized_eigen(
    information: &Matrix6<f64>,
    metric: &Matrix6<f64>,
) -> Option<(nalgebra::SymmetricEigen<f64, nalgebra::U6>, Matrix6<f64>)> {
    // Rotation (rad) and translation (m) differ in scale by orders of magnitude; a relative
    // floor keeps the factorisation of a near-singular metric (a planar view) stable.
    let floor = metric.diagonal().max() * 1e-12;
    let lower = (metric + Matrix6::identity() * floor).cholesky()?.l();
    let lower_inverse = lower.try_inverse()?;
    let whitened = lower_inverse * information * lower_inverse.transpose();
    Some((
        nalgebra::SymmetricEigen::new((whitened + whitened.transpose()) * 0.5),
        lower_inverse,
    ))
}

/// The direction of pose motion the edges see least: the step `ξ` (as [`apply_pose_step`] takes
/// it) of the smallest generalized eigenvalue of `information` against `metric`, scaled so that
/// it moves the visible model by 1 px RMS (`ξᵀ M ξ = 1`). `None` when the metric cannot be
/// factorised.
pub fn least_seen_step(information: &Matrix6<f64>, metric: &Matrix6<f64>) -> Option<Vector6<f64>> {
    seen_steps(information, metric)?.into_iter().next()
}

/// Every generalized eigen-direction of `information` against `metric` as a pose step scaled to
/// move the visible model by 1 px RMS, least seen first ([`least_seen_step`] is the first).
/// `None` when the metric cannot be factorised.
pub fn seen_steps(information: &Matrix6<f64>, metric: &Matrix6<f64>) -> Option<Vec<Vector6<f64>>> {
    let (eigen, lower_inverse) = generalized_eigen(information, metric)?;
    let mut order: Vec<usize> = (0..6).collect();
    order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
    Some(
        order
            .into_iter()
            .map(|index| lower_inverse.transpose() * eigen.eigenvectors.column(index))
            .collect(),
    )
}

/// [`seen_steps`] of the pose `cam_from_world` from its model edge `samples` that a photo ridge
/// supports (as [`supported_edge_observability`] counts them) against the model's image-motion
/// `metric`: pose steps that each move the visible model by 1 px RMS, least seen first. `None`
/// when the metric cannot be factorised.
pub fn supported_seen_steps(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    metric: &Matrix6<f64>,
    config: &EdgeAlignConfig,
) -> Option<Vec<Vector6<f64>>> {
    let supported = supported_information(samples, query, camera, cam_from_world, config);
    seen_steps(&supported.information, metric)
}

/// Start poses for a search of other basins of the edge support around `cam_from_world`: the
/// pose moved either way along each of the `directions` directions its supported edges see
/// least ([`seen_steps`] of [`supported_information`] against the model's image-motion `metric`),
/// by `reach_px` of visible-model motion (δ). A wrong pose the edges support (a local maximum)
/// sits along such a direction from the right one: the edges barely move along it while the
/// rest of the model does. Empty when the metric cannot be factorised.
#[allow(clippy::too_many_arguments)]
pub fn least_seen_starts(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    metric: &Matrix6<f64>,
    config: &EdgeAlignConfig,
    directions: usize,
    reach_px: f64,
) -> Vec<Rigid3> {
    let Some(steps) = supported_seen_steps(samples, query, camera, cam_from_world, metric, config)
    else {
        return Vec::new();
    };
    steps
        .iter()
        .take(directions)
        .flat_map(|step| {
            [1.0, -1.0].map(|sign| apply_pose_step(cam_from_world, &(step * (sign * reach_px))))
        })
        .collect()
}

/// How firmly the photo's edges fix the evaluation's own measure: the expected δ, px RMS, of the
/// visible model (its image-motion `metric`, [`image_motion_metric`]) under the pose covariance
/// that the supported edges' Gauss–Newton `information` gives with 1 px of noise per sample,
/// `√tr(M Σ)` = `√Σ 1/λ` over the generalized eigenvalues. Unlike [`image_uncertainty_px`] (a
/// fronto-parallel grid at the edges' median depth) it weighs the model where it is: the near
/// ground of a low view, which an orbit about the building moves most while its edges barely
/// move. [`UNBOUNDED_IMAGE_UNCERTAINTY_PX`] when a direction is free or the metric is singular.
pub fn delta_uncertainty_px(information: &Matrix6<f64>, metric: &Matrix6<f64>) -> f64 {
    let Some(eigenvalues) = generalized_eigenvalues(information, metric) else {
        return UNBOUNDED_IMAGE_UNCERTAINTY_PX;
    };
    let largest = eigenvalues.max();
    if largest <= 0.0 || eigenvalues.min() <= largest * 1e-12 {
        return UNBOUNDED_IMAGE_UNCERTAINTY_PX;
    }
    eigenvalues
        .iter()
        .map(|lambda| 1.0 / lambda)
        .sum::<f64>()
        .sqrt()
        .min(UNBOUNDED_IMAGE_UNCERTAINTY_PX)
}

/// [`edge_observability`] of the pose `cam_from_world` from its model edge `samples` that a photo
/// ridge supports (within `support_px`, as the evidence counts them) and the model's
/// `render` at that pose.
pub fn supported_edge_observability(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    render: &RenderBuffers,
    camera: &Camera,
    cam_from_world: &Rigid3,
    config: &EdgeAlignConfig,
) -> Option<Vector6<f64>> {
    let SupportedInformation {
        information,
        supported,
        ..
    } = supported_information(samples, query, camera, cam_from_world, config);
    let metric = image_motion_metric(render, camera, MOTION_METRIC_STRIDE_PX)?;
    edge_observability(&information, supported, &metric)
}

/// The Gauss–Newton information `Σ gᵀg` of the 1-D edge residuals of the samples a photo ridge
/// supports (within `support_px`), how many they are, and the depths of all samples that
/// project: what [`image_uncertainty_px`] and [`supported_edge_observability`] start from.
struct SupportedInformation {
    information: Matrix6<f64>,
    supported: usize,
    depths_m: Vec<f64>,
}

fn supported_information(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    config: &EdgeAlignConfig,
) -> SupportedInformation {
    let mut out = SupportedInformation {
        information: Matrix6::zeros(),
        supported: 0,
        depths_m: Vec::with_capacity(samples.len()),
    };
    for_each_ridge(
        samples,
        query,
        camera,
        cam_from_world,
        config,
        |sample, point_cam, offset| {
            out.depths_m.push(point_cam.z);
            if offset.is_some_and(|offset| offset.abs() <= config.support_px) {
                let (row_u, row_v) = pose_jacobian_rows(&camera.intrinsics, point_cam);
                let row = row_u * sample.normal.x + row_v * sample.normal.y;
                out.information += row * row.transpose();
                out.supported += 1;
            }
        },
    );
    out
}

/// Every how many pixels (rows and columns) a rendering's surface is sampled for its image-motion
/// metric: ~2,000 points at 505×275.
pub const MOTION_METRIC_STRIDE_PX: usize = 8;

/// A model edge sample matched to a photo ridge in one step of [`align_level`].
struct EdgeMatch {
    point_cam: Vector3<f64>,
    projected: Vector2<f64>,
    /// Search direction (the sample's 2D normal).
    normal: Vector2<f64>,
    /// Offset to the photo ridge along `normal`, px.
    offset_px: f64,
    /// Rounding direction in the camera frame.
    rounding_cam: Vector3<f64>,
    /// The match's weight from its distinctiveness (1 unless `distinct_weights`).
    distinct_weight: f64,
}
type Matrix8 = nalgebra::SMatrix<f64, 8, 8>;
type Vector8 = nalgebra::SVector<f64, 8>;

/// `d(u)/dξ` and `d(v)/dξ` of a pinhole projection of `point_cam` for the left perturbation
/// `ξ = (ω, δt)`: `point_cam' = exp([ω]×) point_cam + δt`.
pub fn pose_jacobian_rows(
    intrinsics: &PinholeIntrinsics,
    point_cam: &Vector3<f64>,
) -> (Vector6<f64>, Vector6<f64>) {
    let k = intrinsics;
    let inverse_depth = 1.0 / point_cam.z.max(MIN_DEPTH_M);
    let x = point_cam.x * inverse_depth;
    let y = point_cam.y * inverse_depth;
    let du = Vector3::new(
        k.fx_px * inverse_depth,
        k.skew_px * inverse_depth,
        -(k.fx_px * x + k.skew_px * y) * inverse_depth,
    );
    let dv = Vector3::new(0.0, k.fy_px * inverse_depth, -k.fy_px * y * inverse_depth);
    let mut row_u = Vector6::zeros();
    let mut row_v = Vector6::zeros();
    for axis in 0..3 {
        let derivative = Vector3::ith(axis, 1.0).cross(point_cam);
        row_u[axis] = du.dot(&derivative);
        row_v[axis] = dv.dot(&derivative);
        row_u[3 + axis] = du[axis];
        row_v[3 + axis] = dv[axis];
    }
    (row_u, row_v)
}

/// `exp([ω]×) · pose` with the translation step added: the update of [`pose_jacobian_rows`].
pub fn apply_pose_step(pose: &Rigid3, step: &Vector6<f64>) -> Rigid3 {
    let rotation_step = UnitQuaternion::from_scaled_axis(Vector3::new(step[0], step[1], step[2]));
    Rigid3::new(
        rotation_step * pose.rotation,
        rotation_step * pose.translation + Vector3::new(step[3], step[4], step[5]),
    )
}

/// The step that [`apply_pose_step`] takes from `from` to `to` exactly (its inverse).
pub fn pose_step_between(from: &Rigid3, to: &Rigid3) -> Vector6<f64> {
    let rotation_step = to.rotation * from.rotation.inverse();
    let turn = rotation_step.scaled_axis();
    let shift = to.translation - rotation_step * from.translation;
    Vector6::new(turn.x, turn.y, turn.z, shift.x, shift.y, shift.z)
}

/// The direction across a ridge of `image` at pixel `(col, row)`: the eigenvector of the Hessian
/// with the most negative eigenvalue, when the ridge is line-like (that curvature at least twice
/// the other's magnitude). The pixel must be at least one pixel from the border.
fn ridge_normal(image: &ImageView<'_, f32>, col: usize, row: usize) -> Option<Vector2<f64>> {
    let width_px = image.width_px();
    let data = image.data();
    let at = |c: usize, r: usize| f64::from(data[r * width_px + c]);
    let centre = at(col, row);
    let xx = at(col + 1, row) + at(col - 1, row) - 2.0 * centre;
    let yy = at(col, row + 1) + at(col, row - 1) - 2.0 * centre;
    let xy = 0.25
        * (at(col + 1, row + 1) - at(col + 1, row - 1) - at(col - 1, row + 1)
            + at(col - 1, row - 1));
    let mean = 0.5 * (xx + yy);
    let radius = (0.25 * (xx - yy).powi(2) + xy * xy).sqrt();
    let (across, along) = (mean - radius, mean + radius);
    if !(across < 0.0 && across.abs() >= 2.0 * along.abs()) {
        return None;
    }
    let candidates = [Vector2::new(xy, across - xx), Vector2::new(across - yy, xy)];
    let direction = if candidates[0].norm_squared() >= candidates[1].norm_squared() {
        candidates[0]
    } else {
        candidates[1]
    };
    let norm = direction.norm();
    if norm > 1e-12 {
        Some(direction / norm)
    } else if xx <= yy {
        Some(Vector2::new(1.0, 0.0))
    } else {
        Some(Vector2::new(0.0, 1.0))
    }
}

/// The nearest surface depth in the 3×3 neighbourhood (the occluding side of a contour), metres;
/// 0 when none of the nine pixels shows a surface.
fn nearest_depth_m(depth_m: &ImageView<'_, f32>, col: usize, row: usize) -> f32 {
    let width_px = depth_m.width_px();
    let data = depth_m.data();
    let mut nearest = f32::INFINITY;
    for r in row - 1..=row + 1 {
        for c in col - 1..=col + 1 {
            let depth = data[r * width_px + c];
            if depth > 0.0 && depth < nearest {
                nearest = depth;
            }
        }
    }
    if nearest.is_finite() {
        nearest
    } else {
        0.0
    }
}

/// [`parabola_peak`] of the logarithms (values floored at a tiny positive number).
fn log_parabola_peak(before: f32, centre: f32, after: f32) -> f64 {
    let ln = |v: f32| f64::from(v.max(1e-6)).ln();
    let (before, centre, after) = (ln(before), ln(centre), ln(after));
    let denominator = before - 2.0 * centre + after;
    if denominator.abs() < 1e-12 {
        0.0
    } else {
        0.5 * (before - after) / denominator
    }
}

/// Offset of the vertex of the parabola through `(−1, before), (0, centre), (1, after)`.
pub(crate) fn parabola_peak(before: f32, centre: f32, after: f32) -> f64 {
    let denominator = f64::from(before) - 2.0 * f64::from(centre) + f64::from(after);
    if denominator.abs() < 1e-12 {
        0.0
    } else {
        0.5 * (f64::from(before) - f64::from(after)) / denominator
    }
}

/// Bilinear sample at an image position (COLMAP convention); `None` outside the pixel centres.
pub fn bilinear(image: &ImageView<'_, f32>, position_px: Vector2<f64>) -> Option<f32> {
    let (width_px, height_px) = image.size();
    let x = position_px.x - 0.5;
    let y = position_px.y - 0.5;
    if !(x >= 0.0 && y >= 0.0 && x <= (width_px - 1) as f64 && y <= (height_px - 1) as f64) {
        return None;
    }
    let col = (x as usize).min(width_px.saturating_sub(2));
    let row = (y as usize).min(height_px.saturating_sub(2));
    let fx = (x - col as f64) as f32;
    let fy = (y - row as f64) as f32;
    let data = image.data();
    let top = data[row * width_px + col] * (1.0 - fx) + data[row * width_px + col + 1] * fx;
    let bottom =
        data[(row + 1) * width_px + col] * (1.0 - fx) + data[(row + 1) * width_px + col + 1] * fx;
    Some(top * (1.0 - fy) + bottom * fy)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ridge_image(width_px: usize, height_px: usize, line_x_px: f64) -> Image<f32> {
        Image::from_fn(width_px, height_px, |col, _| {
            let d = col as f64 + 0.5 - line_x_px;
            (-(d * d) / 2.0).exp() as f32
        })
    }

    /// The evidence's precision figures: samples projected 0.1, 0.3, 0.8, 2.5 and 10 px beside
    /// a vertical photo ridge: four matched within the evidence radius (median 0.8 px), three
    /// supported within 1 px (median 0.3 px), two within half of it.
    #[test]
    fn evidence_measures_how_closely_the_supported_edges_sit_on_their_ridges() {
        let (width_px, height_px) = (60, 40);
        let ridge_x_px = 20.0;
        let image = ridge_image(width_px, height_px, ridge_x_px);
        let camera = Camera::pinhole(
            width_px as u32,
            height_px as u32,
            PinholeIntrinsics::centered(100.0, width_px as u32, height_px as u32),
        );
        let cx_px = camera.intrinsics.cx_px;
        let samples: Vec<EdgeSample> = [0.1, -0.3, 0.8, -2.5, 10.0]
            .iter()
            .map(|offset_px: &f64| EdgeSample {
                // At depth 1 m, x m lands 100·x px right of the principal point.
                world_m: Vector3::new((ridge_x_px + offset_px - cx_px) / 100.0, 0.0, 1.0),
                normal: Vector2::new(1.0, 0.0),
                kind: EdgeKind::Contour,
                rounding: Vector3::zeros(),
                outward: Vector3::zeros(),
            })
            .collect();
        let config = EdgeAlignConfig::default();
        let evidence = edge_evidence(
            &samples,
            &image.view(),
            &camera,
            &Rigid3::identity(),
            &config,
        );
        assert_eq!(
            (
                evidence.samples,
                evidence.matched,
                evidence.supported,
                evidence.tightly_supported
            ),
            (5, 4, 3, 2),
            "{evidence:?}"
        );
        assert!(
            (evidence.median_distance_px - 0.8).abs() < 0.1,
            "{evidence:?}"
        );
        assert!(
            (evidence.supported_median_px - 0.3).abs() < 0.1,
            "{evidence:?}"
        );
        assert!((evidence.tight_support_fraction() - 0.4).abs() < 1e-12);
        assert!((evidence.support_fraction() - 0.6).abs() < 1e-12);
    }

    /// Known directions `v` with `vᵀMv = 1` and `vᵀHv = λ` (an information matrix against a
    /// metric, neither diagonal): the observability figures are `√(λ / samples)`, ascending.
    #[test]
    fn edge_observability_is_the_edge_motion_per_px_of_model_motion() {
        let basis = Matrix6::from_fn(|row, col| {
            if row == col {
                1.0 + row as f64
            } else {
                0.1 * (row as f64 - col as f64)
            }
        });
        let inverse = basis.try_inverse().unwrap();
        let metric = inverse.transpose() * inverse;
        let samples = 100;
        let per_px = [1.0, 0.9, 0.5, 0.3, 0.1, 0.05];
        let lambdas = Vector6::from_iterator(per_px.iter().map(|e| e * e * samples as f64));
        let information = inverse.transpose() * Matrix6::from_diagonal(&lambdas) * inverse;
        let figures = edge_observability(&information, samples, &metric).unwrap();
        let expected = Vector6::new(0.05, 0.1, 0.3, 0.5, 0.9, 1.0);
        assert!(
            (figures - expected).norm() < 1e-9,
            "{figures} vs {expected}"
        );
        assert_eq!(edge_observability(&information, 0, &metric), None);
        // The expected δ under the covariance is √tr(M Σ): dominated by the least seen direction.
        let expected_delta_px = per_px
            .iter()
            .map(|e| 1.0 / (e * e * samples as f64))
            .sum::<f64>()
            .sqrt();
        let trace_px = (metric * information.try_inverse().unwrap()).trace().sqrt();
        let delta_px = delta_uncertainty_px(&information, &metric);
        assert!((delta_px - expected_delta_px).abs() < 1e-9 * expected_delta_px);
        assert!(
            (delta_px - trace_px).abs() < 1e-6 * trace_px,
            "{delta_px} vs {trace_px}"
        );
        // The least seen step moves the model by 1 px RMS and the edges by the least figure.
        let step = least_seen_step(&information, &metric).unwrap();
        assert!(((step.transpose() * metric * step)[0] - 1.0).abs() < 1e-9);
        let edge_motion_px = ((step.transpose() * information * step)[0] / samples as f64).sqrt();
        assert!((edge_motion_px - 0.05).abs() < 1e-9, "{edge_motion_px}");
        // A direction the edges do not see at all leaves δ unbounded.
        let blind = inverse.transpose()
            * Matrix6::from_diagonal(&Vector6::new(100.0, 81.0, 25.0, 9.0, 1.0, 0.0))
            * inverse;
        assert_eq!(
            delta_uncertainty_px(&blind, &metric),
            UNBOUNDED_IMAGE_UNCERTAINTY_PX
        );
    }

    #[test]
    fn search_finds_a_vertical_ridge_to_a_tenth_of_a_pixel() {
        let image = ridge_image(40, 20, 23.3);
        let found = search_ridge(
            &image.view(),
            Vector2::new(20.0, 10.0),
            Vector2::new(1.0, 0.0),
            6.0,
            0.05,
        )
        .expect("a ridge");
        assert!((found - 3.3).abs() < 0.1, "found {found}");
        // Searched the other way round, the offset changes sign.
        let found = search_ridge(
            &image.view(),
            Vector2::new(20.0, 10.0),
            Vector2::new(-1.0, 0.0),
            6.0,
            0.05,
        )
        .expect("a ridge");
        assert!((found + 3.3).abs() < 0.1, "found {found}");
        // Out of reach.
        assert!(search_ridge(
            &image.view(),
            Vector2::new(10.0, 10.0),
            Vector2::new(1.0, 0.0),
            6.0,
            0.05
        )
        .is_none());
    }

    #[test]
    fn two_ridges_on_a_line_the_choice_and_its_distinctiveness() {
        // A weaker ridge 2 px to the right of the projection, a stronger one 5 px to the left.
        let image = Image::from_fn(40, 20, |col, _| {
            let x = col as f64 + 0.5;
            let near = 0.5 * (-((x - 22.0) * (x - 22.0)) / 2.0).exp();
            let far = (-((x - 15.0) * (x - 15.0)) / 2.0).exp();
            near.max(far) as f32
        });
        let at = Vector2::new(20.0, 10.0);
        let along_x = Vector2::new(1.0, 0.0);
        let strongest = find_ridge(
            &image.view(),
            at,
            along_x,
            8.0,
            0.05,
            RidgeChoice::Strongest,
        )
        .expect("a ridge");
        let nearest = find_ridge(&image.view(), at, along_x, 8.0, 0.05, RidgeChoice::Nearest)
            .expect("a ridge");
        assert!((strongest.offset_px + 5.0).abs() < 0.1, "{strongest:?}");
        assert!((nearest.offset_px - 2.0).abs() < 0.1, "{nearest:?}");
        // Scores weighed with the distance prior (σ = 4 px): 1·e^(−25/32) = 0.458 and
        // 0.5·e^(−4/32) = 0.441: nearly as strong, so barely distinct, whichever was chosen.
        let expected = 1.0 - (0.5 * (-4.0_f64 / 32.0).exp()) / (-25.0_f64 / 32.0).exp();
        for found in [strongest, nearest] {
            assert!(
                (found.distinctiveness - expected).abs() < 0.03,
                "{found:?} vs {expected}"
            );
        }
        // Alone on its line a ridge is fully distinct.
        let single = find_ridge(
            &ridge_image(40, 20, 23.3).view(),
            at,
            along_x,
            6.0,
            0.05,
            RidgeChoice::Nearest,
        )
        .expect("a ridge");
        assert_eq!(single.distinctiveness, 1.0);
    }

    #[test]
    fn a_ridge_along_the_search_line_is_not_matched() {
        // A horizontal ridge searched along x: flat along the line, not line-like across it.
        let image = Image::from_fn(40, 20, |_, row| {
            let d = row as f64 + 0.5 - 10.0;
            (-(d * d) / 2.0).exp() as f32
        });
        assert!(search_ridge(
            &image.view(),
            Vector2::new(20.0, 10.0),
            Vector2::new(1.0, 0.0),
            6.0,
            0.05
        )
        .is_none());
    }

    #[test]
    fn ridge_normals_point_across_the_ridge() {
        let image = ridge_image(20, 20, 10.0);
        let normal = ridge_normal(&image.view(), 9, 10).expect("a ridge");
        assert!(normal.x.abs() > 0.99, "{normal:?}");
        let flat = Image::filled(20, 20, 1.0f32);
        assert!(ridge_normal(&flat.view(), 9, 10).is_none());
    }

    #[test]
    fn level_radii_halve_down_to_the_final_radius() {
        let config = EdgeAlignConfig::default();
        assert_eq!(config.level_radii_px(), vec![16.0, 8.0, 4.0, 2.0]);
        let short = config
            .short_schedule()
            .expect("a short schedule by default");
        assert_eq!(short.level_radii_px(), vec![8.0, 4.0, 2.0]);
        assert!(short.short_schedule().is_none());
        let config = EdgeAlignConfig {
            initial_search_radius_px: 5.0,
            final_search_radius_px: 2.0,
            short_schedule_radius_px: 0.0,
            ..config
        };
        assert_eq!(config.level_radii_px(), vec![5.0, 2.5]);
        assert!(config.validate().is_ok());
        assert!(config.short_schedule().is_none());
        let bad = EdgeAlignConfig {
            final_search_radius_px: 9.0,
            ..config
        };
        assert!(bad.validate().is_err());
        // The short schedule must start below the full one and not below its last level.
        for short_px in [5.0, 1.0, 16.0] {
            let bad = EdgeAlignConfig {
                short_schedule_radius_px: short_px,
                ..config
            };
            assert!(bad.validate().is_err(), "{short_px}");
        }
    }

    #[test]
    fn the_pose_step_matches_its_jacobian() {
        let intrinsics = PinholeIntrinsics::centered(500.0, 640, 480);
        let pose = Rigid3::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.1, -0.2, 0.05)),
            Vector3::new(0.3, -0.1, 4.0),
        );
        let world = Vector3::new(0.4, 0.2, 1.0);
        let project = |p: &Rigid3| {
            let c = p.transform_point(&world);
            Vector2::new(
                intrinsics.fx_px * c.x / c.z + intrinsics.cx_px,
                intrinsics.fy_px * c.y / c.z + intrinsics.cy_px,
            )
        };
        let (row_u, row_v) = pose_jacobian_rows(&intrinsics, &pose.transform_point(&world));
        for axis in 0..6 {
            let mut step = Vector6::zeros();
            step[axis] = 1e-6;
            let numeric = (project(&apply_pose_step(&pose, &step)) - project(&pose)) / 1e-6;
            assert!((numeric.x - row_u[axis]).abs() < 1e-2 * (1.0 + row_u[axis].abs()));
            assert!((numeric.y - row_v[axis]).abs() < 1e-2 * (1.0 + row_v[axis].abs()));
        }
    }

    #[test]
    fn the_step_between_two_poses_takes_one_to_the_other() {
        let from = Rigid3::new(
            UnitQuaternion::from_euler_angles(0.2, -0.4, 1.1),
            Vector3::new(0.3, -0.1, 4.0),
        );
        let to = Rigid3::new(
            UnitQuaternion::from_euler_angles(0.25, -0.38, 1.0),
            Vector3::new(0.5, 0.2, 3.7),
        );
        let reached = apply_pose_step(&from, &pose_step_between(&from, &to));
        assert!(reached.rotation_angle_to_rad(&to) < 1e-12);
        assert!((reached.translation - to.translation).norm() < 1e-12);
        assert!(pose_step_between(&to, &to).norm() < 1e-12);
    }

    /// The keep rules: support alone follows the support; the correlation vetoes a pose it
    /// correlates worse with; the correlation alone follows the correlation; a pose without
    /// correlation (no model pixel) is never kept by a rule that reads it.
    #[test]
    fn keep_rules_read_support_and_correlation() {
        let rises = (0.5, 0.7);
        let falls = (0.7, 0.5);
        let better = (Some(0.3), Some(0.4));
        let worse = (Some(0.4), Some(0.3));
        assert!(KeepRule::Support.keeps(rises, worse));
        assert!(!KeepRule::Support.keeps(falls, better));
        assert!(KeepRule::SupportAndCorrelation.keeps(rises, better));
        assert!(KeepRule::SupportAndCorrelation.keeps(rises, (Some(0.4), Some(0.4))));
        assert!(!KeepRule::SupportAndCorrelation.keeps(rises, worse));
        assert!(!KeepRule::SupportAndCorrelation.keeps(falls, better));
        assert!(KeepRule::Correlation.keeps(falls, better));
        assert!(!KeepRule::Correlation.keeps(rises, worse));
        assert!(!KeepRule::Correlation.keeps(rises, (Some(0.4), None)));
        assert!(KeepRule::Correlation.keeps(falls, (None, Some(0.1))));
        // Only the support rule decides without the correlations.
        assert!(!KeepRule::Support.reads_correlation());
        assert!(KeepRule::SupportAndCorrelation.reads_correlation());
        assert!(KeepRule::Correlation.reads_correlation());
    }
}
