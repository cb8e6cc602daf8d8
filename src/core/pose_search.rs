//! The pose search before the paper's coarse poses (issue #12; not in the paper). The paper's
//! method only refines: its coarse poses sit within a degree or two of the prior and SIFT flow
//! bridges a few tens of pixels, while drones give priors 100+ px off or with the heading 20–40°
//! or 180° wrong. This module finds the few most plausible poses in a wide region, cheaply, without
//! a rendering per candidate:
//! 1. model edge samples ([`crate::core::edge_align::model_edge_samples`]: ASG ridges lifted to 3D
//!    with their 2D normals) from a rendering at the prior's centre, one per rendered heading;
//! 2. an orientation-aware edge map of the query ([`OrientedEdgeMap`]): the query blurred and
//!    decimated to a coarse pyramid level, its ridges (Hessian) split into orientation bins and
//!    blurred again, so that a model edge scores where a photo ridge of the same direction lies
//!    nearby;
//! 3. every candidate rotation of the grid (heading about the world's up axis, densely; pitch and
//!    roll about the camera's axes, narrowly) scored by projecting the samples' points and their
//!    tangents and reading the map at their projected direction ([`score_rotations`]);
//! 4. the top-scoring candidates that differ by more than a separation angle ([`select_beams`])
//!    are screened: each is aligned with the photo's edges on its rendering's samples, without a
//!    rendering of its own (6 DoF, so the prior's position error is taken up too), and the best
//!    by edge support after that alignment are the beams; the frame step refines each against
//!    the photo with re-rendering and decides among them.
//!
//! Only the rotation is gridded: at the priors' position errors (1–2 m at 30–60 m) a camera
//! translation moves the image mostly like a small rotation, and the beams' refinement (edge
//! alignment in 6 DoF) takes up the rest. Preconditions: a pinhole working camera (no distortion);
//! world up is +z.

use nalgebra::{Matrix3, UnitQuaternion, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::camera::{Camera, MIN_DEPTH_M};
use super::dense_sift::{gaussian_taps, separable_filter_clamped};
use super::edge_align::{bilinear, blurred_query, EdgeSample};
use super::image::{Image, ImageView};
use super::rigid::Rigid3;

/// Orientation bins of the edge map over half a turn (a ridge's normal has no sign).
pub const ORIENTATION_BINS: usize = 8;

/// Settings of the pose search. Angles in degrees, distances in pixels of the working camera
/// unless named otherwise. The default region covers the `asgreg synth` levels up to 104 px
/// (Gaussian on all axes: about 10° per axis at f = 360 px) and the `heading` level (heading ±10–40° or 180°,
/// pitch/roll within 1°, 1–2 m).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseSearchConfig {
    /// Run the search at all (`--no-pose-search` turns it off).
    pub enabled: bool,
    /// Headings searched either side of the prior's, degrees.
    pub yaw_half_range_deg: f64,
    /// Also search the same range around the prior's heading + 180° (a flipped compass). Where
    /// the flip is searched (so, or by the full-circle fallback) but the photo's edges show the
    /// model nowhere in the region (the search is blind, `core::frame::search::is_blind`), the
    /// prior's flip becomes a centre of its own coarse poses (within `max_centres`, and when the
    /// model is in view from it), so that the flow's verified agreement decides the heading the
    /// edges could not.
    pub include_flipped_heading: bool,
    pub yaw_step_deg: f64,
    /// Pitch (about the camera's x axis) searched either side of the prior's, degrees.
    pub pitch_half_range_deg: f64,
    pub pitch_step_deg: f64,
    /// Roll (about the camera's optical axis) searched either side of the prior's, degrees.
    /// The 104 px level's rotation noise (about 11.7° per camera axis on the block), expressed
    /// as heading about world up, then pitch and roll, puts a third of the frames beyond ±15° of
    /// roll (the camera looks down obliquely: a turn about its own y axis is part heading, part
    /// roll); on `synth` block seed 1, 26 of 48 frames lie within ±15°, 45 within ±30°
    /// (docs/measurements.md, branch `reach4`). ±30° (`--search-roll-deg 30`) lands the first
    /// centre within 5 px of the truth on 20 of block s1's first 24 frames at 104 px against 15
    /// (`eval --diagnose-search`) and, with `min_overrule_margin` 0.4, accepts 21 of 24 with no
    /// false accept (docs/measurements.md, nineteenth session). The default since the
    /// twentieth session, with the margin asked only of poses the flow contradicts (its false
    /// accepts came with a margin of 0 and were such poses). A prior whose tilt is known (a
    /// drone's IMU: the `heading` level) narrows the range with
    /// [`PoseSearchConfig::with_trusted_tilt_deg`].
    pub roll_half_range_deg: f64,
    pub roll_step_deg: f64,
    /// Camera-centre offsets tried around each of the grid's best candidates, metres either
    /// side along each of the candidate camera's axes (0: the rotation grid alone, the
    /// default). The rotation grid turns the camera about the prior's centre, which explains a
    /// position error only where the scene is far compared with its depth range: the `synth`
    /// 104 px level puts the centres 2.3–3.2 m off (median; up to 6.1 m), tens of px of
    /// parallax on the house seen from 8 m up. Each offset turns the camera back onto the
    /// candidate's pivot (the point on its optical axis at the samples' median depth,
    /// [`position_offsets_m`]); the moved candidates are screened beside the unmoved ones.
    /// Measured at 6 m (`--search-position-m 6`; docs/measurements.md, twenty-second session):
    /// the first centre lands within 5 px of the truth on 14 of block s2's 24 frames at 104 px
    /// against 12 (15 from the true centre), but over four 104 px cells the accepts are 45
    /// against 45 and house s1 gains a false accept (47 px): more starts give the wrong basins
    /// of the house and the repeated facades more chances too. Not the default.
    pub position_half_range_m: f64,
    /// At most this many offsets either side per axis; the step is the one at which a
    /// neighbouring offset moves the samples by at most the screening's first search radius
    /// (`refine_initial_radius_px`), widened to reach the range with this many.
    pub position_max_steps: usize,
    /// The grid's best distinct candidates whose camera centre is searched; the
    /// `screened_candidates` best after that are screened.
    pub positioned_candidates: usize,
    /// The model is rendered at headings this far apart (the parts in view change with the
    /// heading); each candidate uses the nearest rendering's samples, degrees.
    pub render_heading_step_deg: f64,
    /// Pyramid level of the edge map: the query is decimated by 2^level.
    pub map_level: u32,
    /// Blur of the query before decimation, σ in full-resolution px.
    pub map_blur_px: f64,
    /// Blur of each orientation bin at the coarse level, σ in coarse px (the capture range).
    pub bin_blur_px: f64,
    /// At most one model edge sample per square cell of this side, full-resolution px.
    pub sample_spacing_px: usize,
    /// Grid candidates (best grid score first, distinct by `beam_separation_deg`) screened by a
    /// render-free edge alignment: the grid score ranks the truth among the top few dozen but not
    /// reliably first (measured: `eval --diagnose-search`), while the edge support after an
    /// alignment separates it clearly; this many are aligned, cheaply, on the samples of their
    /// heading's rendering. 0: no screening, the grid's best `beams` are refined directly.
    /// Default 24, with `keep_prior_centre`; measured (`eval`, first 24 frames, seed 1, gradient,
    /// known K, same build) screening 24 + kept prior vs 0: block 104 px 16/24 vs 12/24, heading
    /// 21/24 vs 17/24, house 30 px 12/24 vs 10/24, 0 false accepts everywhere (docs/measurements.md,
    /// branch `reach3`). Screening alone lost house frames to wrong beams that beat a weak prior.
    pub screened_candidates: usize,
    /// Grid candidates (best grid score first) distinct by the screening's own capture, screened
    /// beside the `screened_candidates` distinct by `beam_separation_deg`: two candidates are one
    /// start for the screening only when its alignment from one reaches the other, i.e. when they
    /// differ by less than its first search radius (`refine_initial_radius_px`) turned into an
    /// angle by the focal length ([`screening_capture_deg`]: 2.5° at f = 360 px), not by the
    /// beams' 6°; the screened starts then give their beams distinct by `beam_separation_deg`
    /// (several starts that the screening took into one basin are one beam). Why: a
    /// better-scoring candidate up to 6° away speaks for the truth's candidate and screens
    /// elsewhere (the heading level's house s1 and s5 view_018: the grid candidate nearest the
    /// true rotation screens to 0.8 / 2.8 px with the best support of the frame but was never
    /// screened). Measured at 24 (`--capture-candidates 24`; docs/measurements.md, branch
    /// `reach25`): on house s1/s5 heading the frames whose screening left nothing within 16 px of
    /// the truth fall from 12 to 10 (2 to 4 screened near it but lost the beams), correct
    /// accepts 45 → 46 over four cells and house s5's
    /// false accept (view_009) rejected, but 4 accepts lost against 5 gained (block s2 heading
    /// view_018 1.17 px → a wrong beam, 375 px, rejected): the frames it gains fail later
    /// (verification's gates), so registration churns rather than gains. Not the default (0:
    /// the basins' best alone).
    pub capture_candidates: usize,
    /// Beams kept after the screening, best screened edge support first, each then refined with
    /// re-rendering (besides the prior, which is always one).
    pub beams: usize,
    /// Two beams are distinct when their rotations differ by more than this, degrees.
    pub beam_separation_deg: f64,
    /// First search half-length of a beam's edge alignment, px (halved per level down to
    /// `edge_align.final_search_radius_px`).
    pub refine_initial_radius_px: f64,
    /// A beam replaces the prior only when its edge support (share of model edges supported by
    /// photo ridges, 0..1) beats the prior's by at least this much.
    pub min_support_gain: f64,
    /// ... and reaches at least this support (0..1).
    pub min_support: f64,
    /// A beam distinct from the best one that reaches this share of the best one's support
    /// makes the search ambiguous (dimensionless, 0..1; above 1 never): the photo's edges
    /// alone cannot choose, so each of them (and the prior) becomes the centre of its own coarse
    /// poses and verification decides among them.
    pub ambiguity_ratio: f64,
    /// At most this many centres of coarse poses when the search is ambiguous (the best beam,
    /// the prior, then the rivals by support); each costs a frame's coarse-pose work.
    pub max_centres: usize,
    /// When a beam replaces the prior, the prior stays a centre of its own coarse poses too
    /// (within `max_centres`), and verification across the centres decides: a wrong beam that
    /// beats a weak prior's edge support can then no longer take the frame's only centre
    /// (issue #12). Costs a second set of coarse poses on the frames where the search moves.
    /// Default on (measured with the screening, see `screened_candidates`).
    pub keep_prior_centre: bool,
    /// Verification across the centres: two centres' confirmed output poses are the same pose
    /// (the more confident one is output) only when they lie less than this share of the
    /// compatibility threshold (`verify.threshold_px`, the false-accept line) apart; farther apart
    /// the photo confirms two distinct poses and the frame is rejected as ambiguous
    /// (dimensionless, 0..1). At 0.5, whichever of the two confirmed poses is within half the
    /// line of the truth, the output is within the line: the choice between two compatible
    /// poses cannot make a false accept out of a correct one. At 1 (the earlier rule) two poses
    /// 18–25 px apart counted as one, and the house at 30 px gave a false accept (view_010 with
    /// roll ±30°: a centre's pose 8.4 px from the truth and another's 26.6 px, the latter output
    /// on its higher edge support; docs/measurements.md, branch `reach5`).
    pub centre_agreement_share: f64,
    /// The full-circle heading fallback (issue #12 item 1): when a frame's search region gave no
    /// accepted pose, or one only the photo's edges confirm (the plausibility check failed), the
    /// frame is registered once more with headings swept over the full circle at this step,
    /// degrees ([`PoseSearchConfig::heading_sweep`]), and decided across both registrations
    /// (`core::frame::sweep::decide_passes`); the region's other settings stay. 0: no fallback (default: not yet measured on the synthetic levels, and a
    /// rejected frame's time doubles; `register_query` runs it, the pipeline's stages do not).
    pub heading_sweep_step_deg: f64,
}

impl Default for PoseSearchConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            yaw_half_range_deg: 45.0,
            include_flipped_heading: true,
            yaw_step_deg: 2.0,
            pitch_half_range_deg: 22.5,
            pitch_step_deg: 2.5,
            roll_half_range_deg: 30.0,
            roll_step_deg: 3.0,
            position_half_range_m: 0.0,
            position_max_steps: 3,
            positioned_candidates: 48,
            render_heading_step_deg: 45.0,
            map_level: 2,
            map_blur_px: 3.0,
            bin_blur_px: 1.5,
            sample_spacing_px: 6,
            screened_candidates: 24,
            capture_candidates: 0,
            beams: 4,
            beam_separation_deg: 6.0,
            refine_initial_radius_px: 16.0,
            min_support_gain: 0.05,
            min_support: 0.15,
            ambiguity_ratio: 0.9,
            max_centres: 3,
            keep_prior_centre: true,
            centre_agreement_share: 0.5,
            heading_sweep_step_deg: 0.0,
        }
    }
}

/// Why a setting of [`PoseSearchConfig`] is unusable.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("pose_search.{field}: {why}")]
pub struct PoseSearchConfigError {
    pub field: &'static str,
    pub why: String,
}

impl PoseSearchConfig {
    pub fn validate(&self) -> Result<(), PoseSearchConfigError> {
        let bad = |field: &'static str, why: String| Err(PoseSearchConfigError { field, why });
        for (field, value) in [
            ("yaw_half_range_deg", self.yaw_half_range_deg),
            ("pitch_half_range_deg", self.pitch_half_range_deg),
            ("roll_half_range_deg", self.roll_half_range_deg),
            ("min_support_gain", self.min_support_gain),
            ("min_support", self.min_support),
            ("ambiguity_ratio", self.ambiguity_ratio),
            ("beam_separation_deg", self.beam_separation_deg),
            ("position_half_range_m", self.position_half_range_m),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(field, format!("{value} is not a non-negative number"));
            }
        }
        for (field, value) in [
            ("yaw_step_deg", self.yaw_step_deg),
            ("pitch_step_deg", self.pitch_step_deg),
            ("roll_step_deg", self.roll_step_deg),
            ("render_heading_step_deg", self.render_heading_step_deg),
            ("map_blur_px", self.map_blur_px),
            ("bin_blur_px", self.bin_blur_px),
            ("refine_initial_radius_px", self.refine_initial_radius_px),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return bad(field, format!("{value} is not a positive number"));
            }
        }
        if self.yaw_half_range_deg > 180.0 {
            return bad(
                "yaw_half_range_deg",
                format!("{} exceeds 180 (a full turn)", self.yaw_half_range_deg),
            );
        }
        if self.refine_initial_radius_px > 31.0 {
            return bad(
                "refine_initial_radius_px",
                "the ridge search reaches at most 31 px".into(),
            );
        }
        if self.map_level > 4 {
            return bad("map_level", "at most 4 (a 16× smaller map)".into());
        }
        if self.sample_spacing_px == 0 {
            return bad("sample_spacing_px", "must be at least 1".into());
        }
        if self.screened_candidates != 0 && self.screened_candidates < self.beams {
            return bad(
                "screened_candidates",
                format!(
                    "{} is fewer than the {} beams kept after the screening",
                    self.screened_candidates, self.beams
                ),
            );
        }
        if !(self.centre_agreement_share.is_finite()
            && self.centre_agreement_share > 0.0
            && self.centre_agreement_share <= 1.0)
        {
            return bad(
                "centre_agreement_share",
                format!("{} is not in (0, 1]", self.centre_agreement_share),
            );
        }
        if !(self.heading_sweep_step_deg.is_finite() && self.heading_sweep_step_deg >= 0.0) {
            return bad(
                "heading_sweep_step_deg",
                format!(
                    "{} is not a non-negative number",
                    self.heading_sweep_step_deg
                ),
            );
        }
        if self.position_half_range_m > 0.0 && self.position_max_steps == 0 {
            return bad(
                "position_max_steps",
                "must be at least 1 when position_half_range_m is above 0".into(),
            );
        }
        if self.position_max_steps > MAX_POSITION_STEPS {
            return bad(
                "position_max_steps",
                format!(
                    "{} exceeds {MAX_POSITION_STEPS} ((2·n + 1)³ offsets per candidate)",
                    self.position_max_steps
                ),
            );
        }
        if self.max_centres == 0 {
            return bad("max_centres", "must be at least 1".into());
        }
        Ok(())
    }

    /// The region for a prior whose pitch and roll are known within `tilt_deg` (a drone's IMU
    /// measures gravity; its compass, not the tilt, is what goes wrong): the pitch and roll ranges
    /// shrink to three times that, rounded up to whole grid steps and at least one step either
    /// side (the screening's 6-DoF alignment takes up the position error's apparent rotation).
    /// `tilt_deg` 0 (not known) or a range that would grow keeps `self`'s ranges.
    pub fn with_trusted_tilt_deg(self, tilt_deg: f64) -> Self {
        if !(tilt_deg.is_finite() && tilt_deg > 0.0) {
            return self;
        }
        let covered = |step_deg: f64, half_range_deg: f64| {
            ((TRUSTED_TILT_COVERAGE * tilt_deg / step_deg)
                .ceil()
                .max(1.0)
                * step_deg)
                .min(half_range_deg)
        };
        Self {
            pitch_half_range_deg: covered(self.pitch_step_deg, self.pitch_half_range_deg),
            roll_half_range_deg: covered(self.roll_step_deg, self.roll_half_range_deg),
            ..self
        }
    }

    /// The region of the full-circle heading fallback: headings over the whole circle at
    /// `heading_sweep_step_deg` (the flipped range is then part of it), the rest as `self`;
    /// `None` when the fallback is off or the region already covers the circle.
    pub fn heading_sweep(&self) -> Option<PoseSearchConfig> {
        let covered = self.yaw_half_range_deg >= 180.0
            || (self.include_flipped_heading && self.yaw_half_range_deg >= 90.0);
        (self.enabled && self.heading_sweep_step_deg > 0.0 && !covered).then_some(Self {
            yaw_half_range_deg: 180.0,
            include_flipped_heading: false,
            yaw_step_deg: self.heading_sweep_step_deg,
            ..*self
        })
    }

    /// The candidate headings relative to the prior's, degrees: the range around the prior and,
    /// when asked, around the flipped heading (each once, in (−180, 180]).
    pub fn candidate_yaws_deg(&self) -> Vec<f64> {
        let steps = (self.yaw_half_range_deg / self.yaw_step_deg).floor() as i64;
        let mut yaws: Vec<f64> = Vec::new();
        let centres: &[f64] = if self.include_flipped_heading {
            &[0.0, 180.0]
        } else {
            &[0.0]
        };
        for centre in centres {
            for step in -steps..=steps {
                let yaw = wrap_deg(centre + step as f64 * self.yaw_step_deg);
                if !yaws.iter().any(|y| (wrap_deg(y - yaw)).abs() < 1e-9) {
                    yaws.push(yaw);
                }
            }
        }
        yaws
    }

    fn axis_offsets_deg(half_range_deg: f64, step_deg: f64) -> Vec<f64> {
        let steps = (half_range_deg / step_deg).floor() as i64;
        (-steps..=steps).map(|s| s as f64 * step_deg).collect()
    }
}

/// The rotation the screening's alignment reaches from a start, degrees: its first search radius
/// (`refine_initial_radius_px`) turned into an angle by the camera's focal length (the image
/// motion of a turn about the camera centre, `f·θ` px at the principal point).
pub fn screening_capture_deg(camera: &Camera, config: &PoseSearchConfig) -> f64 {
    let k = &camera.intrinsics;
    let focal_px = k.fx_px.max(k.fy_px).max(1.0);
    (config.refine_initial_radius_px / focal_px)
        .atan()
        .to_degrees()
}

/// The most offsets either side per axis of the position search (`position_max_steps`).
pub const MAX_POSITION_STEPS: usize = 8;

/// The pitch and roll ranges of a trusted tilt ([`PoseSearchConfig::with_trusted_tilt_deg`])
/// cover this many times the tilt.
pub const TRUSTED_TILT_COVERAGE: f64 = 3.0;

/// An angle in (−180, 180] degrees.
pub fn wrap_deg(angle_deg: f64) -> f64 {
    let wrapped = (angle_deg + 180.0).rem_euclid(360.0) - 180.0;
    if wrapped <= -180.0 {
        wrapped + 360.0
    } else {
        wrapped
    }
}

/// The prior turned by `yaw_deg` about the world's up axis (+z) through its centre, then by
/// `pitch_deg` and `roll_deg` about its own x and z axes: `T · R · yaw⁻¹`, centre kept.
pub fn turned_pose(prior: &Rigid3, yaw_deg: f64, pitch_deg: f64, roll_deg: f64) -> Rigid3 {
    let yaw = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw_deg.to_radians());
    let tilt = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), pitch_deg.to_radians())
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll_deg.to_radians());
    let rotation = tilt * prior.rotation * yaw.inverse();
    let centre = prior.camera_center();
    Rigid3::new(rotation, -(rotation * centre))
}

/// The query's ridges by orientation at a coarse pyramid level: per coarse pixel,
/// [`ORIENTATION_BINS`] values (interleaved), each the blurred strength of the ridges whose normal
/// lies in that bin, on a 0..1 scale.
#[derive(Clone, Debug, Default)]
pub struct OrientedEdgeMap {
    width_px: usize,
    height_px: usize,
    /// Coarse px per full-resolution px (1 / 2^level).
    scale: f64,
    bins: Vec<f32>,
}

impl OrientedEdgeMap {
    /// Builds the map of `query` (0..1) with the settings' blur and level.
    pub fn build(query: ImageView<'_, f32>, config: &PoseSearchConfig) -> Self {
        let (full_width_px, full_height_px) = query.size();
        let factor = 1usize << config.map_level;
        let width_px = full_width_px / factor;
        let height_px = full_height_px / factor;
        let scale = 1.0 / factor as f64;
        if width_px < 5 || height_px < 5 {
            return Self {
                width_px: 0,
                height_px: 0,
                scale,
                bins: Vec::new(),
            };
        }
        let mut blurred = Image::default();
        blurred_query(query, 4.0 * config.map_blur_px, &mut blurred);
        let blurred_view = blurred.view();
        // Decimate: a coarse pixel centre (c + 0.5) is the full-resolution position (c + 0.5)·f.
        let coarse = Image::from_fn(width_px, height_px, |col, row| {
            let at = Vector2::new(
                (col as f64 + 0.5) * factor as f64,
                (row as f64 + 0.5) * factor as f64,
            );
            bilinear(&blurred_view, at).unwrap_or(0.0)
        });
        let at = |col: usize, row: usize| f64::from(coarse.data()[row * width_px + col]);
        let mut bins = vec![0.0f32; width_px * height_px * ORIENTATION_BINS];
        let mut strengths: Vec<f32> = Vec::new();
        for row in 1..height_px - 1 {
            for col in 1..width_px - 1 {
                let centre = at(col, row);
                let xx = at(col + 1, row) + at(col - 1, row) - 2.0 * centre;
                let yy = at(col, row + 1) + at(col, row - 1) - 2.0 * centre;
                let xy = 0.25
                    * (at(col + 1, row + 1) - at(col + 1, row - 1) - at(col - 1, row + 1)
                        + at(col - 1, row - 1));
                let mean = 0.5 * (xx + yy);
                let radius = (0.25 * (xx - yy).powi(2) + xy * xy).sqrt();
                let (across, along) = (mean - radius, mean + radius);
                // Ridges only: curved across, flatter along.
                if !(across < 0.0 && across.abs() > along.max(0.0)) {
                    continue;
                }
                let strength = (-across - along.max(0.0)) as f32;
                // The eigenvector of `across`: the ridge's normal.
                let direction = if xy.abs() > 1e-12 {
                    Vector2::new(xy, across - xx)
                } else if xx <= yy {
                    Vector2::new(1.0, 0.0)
                } else {
                    Vector2::new(0.0, 1.0)
                };
                let (lower, upper, weight) = bin_weights(direction.y.atan2(direction.x));
                let weight = weight as f32;
                let base = (row * width_px + col) * ORIENTATION_BINS;
                bins[base + lower] += strength * (1.0 - weight);
                bins[base + upper] += strength * weight;
                strengths.push(strength);
            }
        }
        // Scale so that the 95th percentile of the ridge strengths is 1, then clamp.
        if !strengths.is_empty() {
            let index = ((strengths.len() - 1) as f64 * 0.95) as usize;
            let (_, reference, _) = strengths.select_nth_unstable_by(index, f32::total_cmp);
            let reference = reference.max(1e-9);
            bins.iter_mut().for_each(|v| *v = (*v / reference).min(1.0));
        }
        let sigma = config.bin_blur_px as f32;
        let radius = (3.0 * sigma).ceil() as usize;
        let taps = gaussian_taps(sigma, radius);
        let mut scratch = vec![0.0f32; bins.len()];
        let mut out = vec![0.0f32; bins.len()];
        separable_filter_clamped(
            &bins,
            width_px,
            height_px,
            ORIENTATION_BINS,
            &taps,
            radius,
            &mut scratch,
            &mut out,
        );
        // A ridge blurred by σ keeps 1/(σ√(2π)) of its peak: bring it back near 1.
        let gain = (sigma * (2.0 * std::f32::consts::PI).sqrt()).max(1.0);
        out.iter_mut().for_each(|v| *v = (*v * gain).min(1.0));
        Self {
            width_px,
            height_px,
            scale,
            bins: out,
        }
    }

    /// The map's value at a full-resolution position for an edge whose normal has angle
    /// `normal_angle_rad`; 0 outside the map.
    pub fn value(&self, position_px: Vector2<f64>, normal_angle_rad: f64) -> f32 {
        let x = position_px.x * self.scale - 0.5;
        let y = position_px.y * self.scale - 0.5;
        if !(x >= 0.0
            && y >= 0.0
            && x < (self.width_px - 1) as f64
            && y < (self.height_px - 1) as f64)
        {
            return 0.0;
        }
        let (col, row) = (x as usize, y as usize);
        let (fx, fy) = ((x - col as f64) as f32, (y - row as f64) as f32);
        let (lower, upper, weight) = bin_weights(normal_angle_rad);
        let weight = weight as f32;
        let at = |c: usize, r: usize| {
            let base = (r * self.width_px + c) * ORIENTATION_BINS;
            self.bins[base + lower] * (1.0 - weight) + self.bins[base + upper] * weight
        };
        let top = at(col, row) * (1.0 - fx) + at(col + 1, row) * fx;
        let bottom = at(col, row + 1) * (1.0 - fx) + at(col + 1, row + 1) * fx;
        top * (1.0 - fy) + bottom * fy
    }
}

/// The two orientation bins an angle falls between and the weight of the upper one.
fn bin_weights(angle_rad: f64) -> (usize, usize, f64) {
    let half_turn = std::f64::consts::PI;
    let position = angle_rad.rem_euclid(half_turn) / half_turn * ORIENTATION_BINS as f64;
    let lower = (position.floor() as usize) % ORIENTATION_BINS;
    let upper = (lower + 1) % ORIENTATION_BINS;
    (lower, upper, position - position.floor())
}

/// A model edge sample prepared for scoring from one rendering: its point and a point one pixel
/// along the edge, both in that rendering's camera frame.
#[derive(Clone, Copy, Debug)]
pub struct SearchSample {
    pub point_cam: Vector3<f64>,
    pub along_cam: Vector3<f64>,
}

/// Prepares the edge samples of the rendering at `rendered_from`.
pub fn search_samples(
    samples: &[EdgeSample],
    camera: &Camera,
    rendered_from: &Rigid3,
) -> Vec<SearchSample> {
    samples
        .iter()
        .filter_map(|sample| {
            let point_cam = rendered_from.transform_point(&sample.world_m);
            let projected = camera.project(&point_cam)?;
            let tangent = Vector2::new(-sample.normal.y, sample.normal.x);
            let ray = camera.unproject(projected + tangent)?;
            Some(SearchSample {
                point_cam,
                along_cam: ray * point_cam.z,
            })
        })
        .collect()
}

/// One scored candidate of the grid.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    pub cam_from_world: Rigid3,
    /// Heading, pitch and roll relative to the prior, degrees.
    pub yaw_deg: f64,
    pub pitch_deg: f64,
    pub roll_deg: f64,
    /// Mean edge-map value over the rendering's samples (0..1).
    pub score: f64,
}

/// The score of the rotation `rotation_from_rendered` (a candidate's camera from the rendering's
/// camera, same centre): the mean map value at the samples' projections for their projected
/// directions; samples behind the camera or outside the map count 0.
pub fn score_rotation(
    samples: &[SearchSample],
    map: &OrientedEdgeMap,
    camera: &Camera,
    rotation_from_rendered: &Matrix3<f64>,
) -> f64 {
    score_relative(
        samples,
        map,
        camera,
        rotation_from_rendered,
        &Vector3::zeros(),
    )
}

/// [`score_rotation`] of a candidate whose camera is `rotation · x + translation` of the
/// rendering's camera `x` (another centre too).
pub fn score_relative(
    samples: &[SearchSample],
    map: &OrientedEdgeMap,
    camera: &Camera,
    rotation: &Matrix3<f64>,
    translation: &Vector3<f64>,
) -> f64 {
    if samples.is_empty() {
        return 0.0;
    }
    let k = &camera.intrinsics;
    let project = |p: Vector3<f64>| {
        (p.z > MIN_DEPTH_M).then(|| {
            let (x, y) = (p.x / p.z, p.y / p.z);
            Vector2::new(k.fx_px * x + k.skew_px * y + k.cx_px, k.fy_px * y + k.cy_px)
        })
    };
    let mut sum = 0.0f64;
    for sample in samples {
        let (Some(at), Some(along)) = (
            project(rotation * sample.point_cam + translation),
            project(rotation * sample.along_cam + translation),
        ) else {
            continue;
        };
        let tangent = along - at;
        // The normal's angle is the tangent's plus a quarter turn.
        let normal_angle = tangent.y.atan2(tangent.x) + std::f64::consts::FRAC_PI_2;
        sum += f64::from(map.value(at, normal_angle));
    }
    sum / samples.len() as f64
}

/// The camera-centre offsets the position search tries around a candidate and the pivot they
/// turn onto ([`position_offsets_m`]).
#[derive(Clone, Debug, PartialEq)]
pub struct CentreOffsets {
    /// In the candidate camera's axes, metres; zero included.
    pub offsets_m: Vec<Vector3<f64>>,
    /// The samples' (lower) median depth: the pivot is `(0, 0, pivot_depth_m)` in the
    /// candidate's camera.
    pub pivot_depth_m: f64,
}

/// The camera-centre offsets the position search tries around a candidate, given the
/// rendering's samples as the candidate sees them (`relative`: the candidate's camera from the
/// rendering's). An offset `o` moves the centre and turns the camera back onto the pivot
/// `(0, 0, Z_med)` (the samples' median depth on the optical axis), so what it changes in the
/// image is what no rotation does:
/// - sideways (x, y), the parallax of the near samples against the pivot, `f·|o|·(1/Z_near −
///   1/Z_med)` px (`Z_near` the samples' 10th depth percentile);
/// - along the axis (z), the scaling about the pivot, `r·|o|/Z_med` px (`r` the samples' 90th
///   percentile of distance from the principal point).
///
/// Each axis's step moves the samples by `step_px` (the screening's first search radius, its
/// capture), widened to reach `half_range_m` with `max_steps` either side. `None` when there is
/// nothing to search (range 0, or no sample in front of the camera).
pub fn position_offsets_m(
    samples: &[SearchSample],
    camera: &Camera,
    relative: &Rigid3,
    half_range_m: f64,
    max_steps: usize,
    step_px: f64,
) -> Option<CentreOffsets> {
    if !(half_range_m.is_finite() && half_range_m > 0.0 && step_px.is_finite() && step_px > 0.0)
        || max_steps == 0
    {
        return None;
    }
    let k = &camera.intrinsics;
    let mut depths_m: Vec<f64> = Vec::with_capacity(samples.len());
    let mut radii_px: Vec<f64> = Vec::with_capacity(samples.len());
    for sample in samples {
        let p = relative.transform_point(&sample.point_cam);
        if p.z > MIN_DEPTH_M {
            depths_m.push(p.z);
            radii_px.push(k.fx_px.max(k.fy_px) * (p.x * p.x + p.y * p.y).sqrt() / p.z);
        }
    }
    if depths_m.is_empty() {
        return None;
    }
    let quantile = |values: &mut Vec<f64>, q: f64| {
        let index = ((values.len() - 1) as f64 * q).round() as usize;
        *values.select_nth_unstable_by(index, f64::total_cmp).1
    };
    let near_m = quantile(&mut depths_m, 0.1);
    let median_m = quantile(&mut depths_m, 0.5);
    // The pivot: the lower median.
    let lower_middle = (depths_m.len() - 1) / 2;
    let pivot_depth_m = *depths_m
        .select_nth_unstable_by(lower_middle, f64::total_cmp)
        .1;
    let radius_px = quantile(&mut radii_px, 0.9);
    let focal_px = 0.5 * (k.fx_px + k.fy_px);
    let sideways_px_per_m = focal_px * (1.0 / near_m - 1.0 / median_m);
    let along_px_per_m = radius_px / median_m;
    let axis = |px_per_m: f64| -> Vec<f64> {
        let wanted = if px_per_m > 0.0 {
            (half_range_m * px_per_m / step_px).ceil() as usize
        } else {
            1
        };
        let steps = wanted.clamp(1, max_steps);
        let step_m = half_range_m / steps as f64;
        (-(steps as i64)..=steps as i64)
            .map(|i| i as f64 * step_m)
            .collect()
    };
    let (sideways, along) = (axis(sideways_px_per_m), axis(along_px_per_m));
    let mut offsets_m = Vec::with_capacity(sideways.len() * sideways.len() * along.len());
    for &z in &along {
        for &y in &sideways {
            for &x in &sideways {
                offsets_m.push(Vector3::new(x, y, z));
            }
        }
    }
    Some(CentreOffsets {
        offsets_m,
        pivot_depth_m,
    })
}

/// `pose` with its centre moved by `offset_cam_m` (in its camera's axes) and turned by the
/// smallest rotation that brings `pivot_cam` (a point in its camera frame, in front of it)
/// back onto the same ray.
pub fn moved_onto_pivot(
    pose: &Rigid3,
    offset_cam_m: &Vector3<f64>,
    pivot_cam: &Vector3<f64>,
) -> Rigid3 {
    let seen_from_moved = pivot_cam - offset_cam_m;
    let turn = UnitQuaternion::rotation_between(&seen_from_moved, pivot_cam)
        .unwrap_or_else(UnitQuaternion::identity);
    let rotation = turn * pose.rotation;
    let centre = pose.camera_center() + pose.rotation.inverse() * offset_cam_m;
    Rigid3::new(rotation, -(rotation * centre))
}

/// The position search of one grid candidate: every offset of [`position_offsets_m`] scored as
/// the grid scores (the rendering's samples, `rendered` its pose), and the candidate moved to
/// the best; `None` when no offset scores higher than the candidate itself.
pub fn position_candidate(
    samples: &[SearchSample],
    map: &OrientedEdgeMap,
    camera: &Camera,
    rendered: &Rigid3,
    candidate: &Candidate,
    config: &PoseSearchConfig,
) -> Option<Candidate> {
    let rendered_inverse = rendered.inverse();
    let relative = candidate.cam_from_world.compose(&rendered_inverse);
    let CentreOffsets {
        offsets_m,
        pivot_depth_m,
    } = position_offsets_m(
        samples,
        camera,
        &relative,
        config.position_half_range_m,
        config.position_max_steps,
        config.refine_initial_radius_px,
    )?;
    let pivot_cam = Vector3::new(0.0, 0.0, pivot_depth_m);
    let mut best: Option<Candidate> = None;
    for offset in offsets_m.iter().filter(|o| o.norm() > 0.0) {
        let pose = moved_onto_pivot(&candidate.cam_from_world, offset, &pivot_cam);
        let moved = pose.compose(&rendered_inverse);
        let score = score_relative(
            samples,
            map,
            camera,
            &moved.rotation.to_rotation_matrix().into_inner(),
            &moved.translation,
        );
        if score > best.map_or(candidate.score, |b| b.score) {
            best = Some(Candidate {
                cam_from_world: pose,
                score,
                ..*candidate
            });
        }
    }
    best
}

/// Scores the grid rotations with the headings `yaws_deg` (relative to the prior), from the
/// samples rendered at the heading `rendered_yaw_deg` (the nearest rendering to those headings).
pub fn score_rotations(
    samples: &[SearchSample],
    map: &OrientedEdgeMap,
    camera: &Camera,
    prior: &Rigid3,
    (rendered_yaw_deg, yaws_deg): (f64, &[f64]),
    config: &PoseSearchConfig,
) -> Vec<Candidate> {
    let mut out = Vec::new();
    let rendered = turned_pose(prior, rendered_yaw_deg, 0.0, 0.0);
    let rendered_inverse = rendered
        .rotation
        .inverse()
        .to_rotation_matrix()
        .into_inner();
    let pitches =
        PoseSearchConfig::axis_offsets_deg(config.pitch_half_range_deg, config.pitch_step_deg);
    let rolls =
        PoseSearchConfig::axis_offsets_deg(config.roll_half_range_deg, config.roll_step_deg);
    for &yaw_deg in yaws_deg {
        for &pitch_deg in &pitches {
            for &roll_deg in &rolls {
                let pose = turned_pose(prior, yaw_deg, pitch_deg, roll_deg);
                let relative = pose.rotation.to_rotation_matrix().into_inner() * rendered_inverse;
                out.push(Candidate {
                    cam_from_world: pose,
                    yaw_deg,
                    pitch_deg,
                    roll_deg,
                    score: score_rotation(samples, map, camera, &relative),
                });
            }
        }
    }
    out
}

/// The best candidates, each differing from every better one by more than the separation
/// (rotation angle), at most `count`.
pub fn select_beams(candidates: &[Candidate], count: usize, separation_deg: f64) -> Vec<Candidate> {
    let mut order: Vec<&Candidate> = candidates.iter().collect();
    order.sort_by(|a, b| b.score.total_cmp(&a.score));
    first_distinct(order, count, separation_deg, |c| &c.cam_from_world)
        .into_iter()
        .copied()
        .collect()
}

/// The first `count` of `ordered` (best first) whose pose differs from every one kept before it
/// by more than the separation (rotation angle).
pub fn first_distinct<T>(
    ordered: impl IntoIterator<Item = T>,
    count: usize,
    separation_deg: f64,
    pose: impl Fn(&T) -> &Rigid3,
) -> Vec<T> {
    let separation_rad = separation_deg.to_radians();
    let mut kept: Vec<T> = Vec::with_capacity(count);
    for item in ordered {
        if kept.len() >= count {
            break;
        }
        if kept
            .iter()
            .all(|k| pose(k).rotation_angle_to_rad(pose(&item)) > separation_rad)
        {
            kept.push(item);
        }
    }
    kept
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A trusted tilt narrows pitch and roll to whole steps covering three times it (at least a
    /// step either side), never widens them, and an unknown one (0) keeps the region.
    #[test]
    fn a_trusted_tilt_narrows_pitch_and_roll_only() {
        let default = PoseSearchConfig::default();
        let imu = default.with_trusted_tilt_deg(1.0);
        assert_eq!(imu.pitch_half_range_deg, 2.0 * default.pitch_step_deg);
        assert_eq!(imu.roll_half_range_deg, default.roll_step_deg);
        assert_eq!(imu.yaw_half_range_deg, default.yaw_half_range_deg);
        assert_eq!(
            PoseSearchConfig::axis_offsets_deg(imu.roll_half_range_deg, imu.roll_step_deg),
            vec![-3.0, 0.0, 3.0]
        );
        let tiny = default.with_trusted_tilt_deg(0.1);
        assert_eq!(tiny.pitch_half_range_deg, default.pitch_step_deg);
        assert_eq!(tiny.roll_half_range_deg, default.roll_step_deg);
        assert_eq!(default.with_trusted_tilt_deg(0.0), default);
        assert_eq!(default.with_trusted_tilt_deg(f64::NAN), default);
        let loose = default.with_trusted_tilt_deg(40.0);
        assert_eq!(loose.pitch_half_range_deg, default.pitch_half_range_deg);
        assert_eq!(loose.roll_half_range_deg, default.roll_half_range_deg);
    }

    #[test]
    fn angles_wrap_and_yaws_cover_both_headings_once() {
        assert!((wrap_deg(190.0) + 170.0).abs() < 1e-9);
        assert!((wrap_deg(-180.0) - 180.0).abs() < 1e-9);
        let config = PoseSearchConfig::default();
        let yaws = config.candidate_yaws_deg();
        // ±45° in 2° steps: −44..44, around the prior and the flipped heading.
        assert_eq!(yaws.len(), 2 * 45);
        assert!(yaws.iter().any(|y| (y - 180.0).abs() < 1e-9));
        assert!(yaws.iter().any(|y| y.abs() < 1e-9));
        let full = PoseSearchConfig {
            yaw_half_range_deg: 180.0,
            ..config
        };
        assert_eq!(full.candidate_yaws_deg().len(), 180);
        assert!(config.validate().is_ok());
        let bad = PoseSearchConfig {
            yaw_step_deg: 0.0,
            ..config
        };
        assert!(bad.validate().is_err());
    }

    /// The screening's capture is its first search radius seen from the camera centre: 16 px at
    /// f = 360 px is 2.5°; a longer focal length narrows it.
    #[test]
    fn the_screening_capture_is_its_first_radius_as_an_angle() {
        use crate::core::camera::PinholeIntrinsics;
        let camera = Camera::pinhole(505, 275, PinholeIntrinsics::centered(360.0, 505, 275));
        let config = PoseSearchConfig::default();
        let capture_deg = screening_capture_deg(&camera, &config);
        assert!((capture_deg - 2.545).abs() < 0.01, "{capture_deg}");
        let long = Camera::pinhole(505, 275, PinholeIntrinsics::centered(720.0, 505, 275));
        assert!(screening_capture_deg(&long, &config) < 0.51 * capture_deg);
    }

    #[test]
    fn turned_pose_keeps_the_centre_and_turns_the_heading() {
        let prior = Rigid3::look_at(
            &Vector3::new(30.0, 0.0, 20.0),
            &Vector3::zeros(),
            &Vector3::z(),
        )
        .unwrap();
        let turned = turned_pose(&prior, 90.0, 0.0, 0.0);
        assert!((turned.camera_center() - prior.camera_center()).norm() < 1e-9);
        let axis = |p: &Rigid3| p.inverse().transform_vector(&Vector3::z());
        let (a, b) = (axis(&prior), axis(&turned));
        let turn_deg = wrap_deg((b.y.atan2(b.x) - a.y.atan2(a.x)).to_degrees());
        assert!((turn_deg - 90.0).abs() < 1e-6, "{turn_deg}");
        assert!((a.z - b.z).abs() < 1e-9);
    }

    /// A vertical ridge in the query scores for a vertical model edge on it, not for a horizontal
    /// one, and less a few coarse pixels away.
    #[test]
    fn the_edge_map_is_orientation_aware() {
        let query = Image::from_fn(200, 120, |col, _| {
            let d = col as f64 + 0.5 - 100.0;
            (-(d * d) / 2.0).exp() as f32
        });
        let map = OrientedEdgeMap::build(query.view(), &PoseSearchConfig::default());
        let on = map.value(Vector2::new(100.0, 60.0), 0.0);
        let across = map.value(Vector2::new(100.0, 60.0), std::f64::consts::FRAC_PI_2);
        let aside = map.value(Vector2::new(120.0, 60.0), 0.0);
        assert!(on > 0.5, "{on}");
        assert!(across < 0.1 * on, "{across} vs {on}");
        assert!(aside < 0.5 * on, "{aside} vs {on}");
    }
    /// A scene of line segments 5–15 m away: a candidate whose centre is 2 m off sideways but
    /// turned onto the scene (the best a rotation can do) is moved by the position search to
    /// within a step of the true centre, and scores higher there; with the range 0 it is not moved.
    #[test]
    fn the_position_search_moves_a_candidate_back_to_the_centre_a_rotation_cannot_reach() {
        use crate::core::camera::PinholeIntrinsics;
        use crate::core::edge_align::{EdgeKind, EdgeSample};
        let (width_px, height_px) = (400u32, 300u32);
        let camera = Camera::pinhole(
            width_px,
            height_px,
            PinholeIntrinsics::centered(300.0, width_px, height_px),
        );
        let target = Vector3::new(0.0, 0.0, 1.0);
        let truth =
            Rigid3::look_at(&Vector3::new(0.0, -10.0, 4.0), &target, &Vector3::z()).unwrap();
        // Vertical and horizontal segments at depths from 5 to 15 m (a fixed pseudo-random set).
        let mut state = 7u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) as f64) / f64::from(1u32 << 31)
        };
        let mut segments: Vec<(Vector3<f64>, Vector3<f64>)> = Vec::new();
        for i in 0..40 {
            let start = Vector3::new(8.0 * next() - 4.0, 10.0 * next() - 5.0, 3.0 * next());
            let direction = match i % 3 {
                0 => Vector3::z(),
                1 => Vector3::x(),
                _ => Vector3::y(),
            };
            segments.push((start, start + direction * (0.8 + 1.2 * next())));
        }
        // The query: each segment a ridge (σ 1 px) as the true camera sees it.
        let (w, h) = (width_px as usize, height_px as usize);
        let mut pixels = vec![0.0f32; w * h];
        for (a, b) in &segments {
            for step in 0..=400 {
                let point = a + (b - a) * (f64::from(step) / 400.0);
                let Some(at) = camera.project(&truth.transform_point(&point)) else {
                    continue;
                };
                for dy in -3i64..=3 {
                    for dx in -3i64..=3 {
                        let (col, row) = (at.x.floor() as i64 + dx, at.y.floor() as i64 + dy);
                        if col < 0 || row < 0 || col >= w as i64 || row >= h as i64 {
                            continue;
                        }
                        let d = Vector2::new(col as f64 + 0.5, row as f64 + 0.5) - at;
                        let value = (-d.norm_squared() / 2.0).exp() as f32;
                        let pixel = &mut pixels[row as usize * w + col as usize];
                        *pixel = pixel.max(value);
                    }
                }
            }
        }
        let query = Image::new(w, h, pixels).unwrap();
        let config = PoseSearchConfig {
            position_half_range_m: 3.0,
            position_max_steps: 3,
            ..PoseSearchConfig::default()
        };
        let map = OrientedEdgeMap::build(query.view(), &config);
        // The candidate: 2 m to the camera's side and 1 m back, looking at the same target.
        let offset_world = truth
            .inverse()
            .transform_vector(&Vector3::new(2.0, 0.0, -1.0));
        let off = Rigid3::look_at(
            &(truth.camera_center() + offset_world),
            &target,
            &Vector3::z(),
        )
        .unwrap();
        let edge_samples: Vec<EdgeSample> = segments
            .iter()
            .flat_map(|(a, b)| {
                (0..=12).filter_map(move |step| {
                    let point = a + (b - a) * (f64::from(step) / 12.0);
                    let here = camera.project(&off.transform_point(&point))?;
                    let there = camera.project(&off.transform_point(&(point + (b - a) * 0.01)))?;
                    let tangent = (there - here).normalize();
                    Some(EdgeSample {
                        world_m: point,
                        normal: Vector2::new(-tangent.y, tangent.x),
                        kind: EdgeKind::ConvexCrease,
                        rounding: Vector3::zeros(),
                        outward: Vector3::zeros(),
                    })
                })
            })
            .collect();
        let samples = search_samples(&edge_samples, &camera, &off);
        let candidate = Candidate {
            cam_from_world: off,
            yaw_deg: 0.0,
            pitch_deg: 0.0,
            roll_deg: 0.0,
            score: score_rotation(&samples, &map, &camera, &Matrix3::identity()),
        };
        let moved = position_candidate(&samples, &map, &camera, &off, &candidate, &config)
            .expect("an offset scores higher than the candidate");
        let miss_m = (moved.cam_from_world.camera_center() - truth.camera_center()).norm();
        assert!(
            moved.score > candidate.score + 0.1,
            "{} vs {}",
            moved.score,
            candidate.score
        );
        assert!(
            miss_m < 0.75,
            "the moved centre is {miss_m} m from the truth"
        );
        // Off, the candidate stays as it is.
        let without = PoseSearchConfig {
            position_half_range_m: 0.0,
            ..config
        };
        assert_eq!(
            position_candidate(&samples, &map, &camera, &off, &candidate, &without),
            None
        );
    }
}
