//! The settings of a frame's registration (one struct, validated once) and why a frame cannot be
//! registered at all. Whether the intrinsics are known is a property of the frame
//! ([`super::FrameInput::intrinsics`]), not of the settings.

use serde::{Deserialize, Serialize};

use crate::core::confidence::ConfidenceConfig;
use crate::core::edge_align::EdgeAlignConfig;
use crate::core::flow_consistency::MatchConfig;
use crate::core::pose::estimate::PoseEstimationConfig;
use crate::core::pose_search::PoseSearchConfig;
use crate::core::raster::RenderOptions;
use crate::core::shading::AsgOptions;
use crate::core::verify::VerifyConfig;

/// Which gradient image stands for the photo (docs/design.md §2 step 3).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum QueryMode {
    /// Gradient magnitude of the photo (Plötz & Roth's choice).
    #[default]
    ImageGradient,
    /// ASG of the normals of the photo's depth map (the paper's choice); needs a depth map.
    DepthAsg,
    /// Depth-ASG where the photo's depth is valid and trustworthy (a full neighbourhood of valid
    /// depth), the photo's gradient elsewhere, each on the 0..1 scale; needs a depth map. Real
    /// MVS depth has holes on plain walls, grass and roofs, where the depth query alone is blank.
    Mixed,
}

impl QueryMode {
    /// Whether the mode reads the photo's depth map.
    pub fn needs_depth(self) -> bool {
        matches!(self, Self::DepthAsg | Self::Mixed)
    }
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

/// What "unknown intrinsics" ([`IntrinsicsMode::Unknown`]) estimates. A setting of the
/// registration, not of the frame: the frame only says that its calibration is not to be trusted
/// (the wire's `intrinsics_known`), and every stage reads the same settings.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum UnknownIntrinsics {
    /// The paper's 11-DoF DLT: focal lengths, principal point, (skew) and pose.
    #[default]
    Dlt,
    /// Only the focal length (fx = fy · aspect of the nominal camera), principal point at the
    /// image centre, no skew: what a drone's EXIF leaves open (EPnP with unknown focal length).
    Focal,
}

impl IntrinsicsMode {
    /// The mode of a frame whose intrinsics are (`true`) or are not known.
    pub fn from_known(known: bool) -> Self {
        if known {
            Self::Known
        } else {
            Self::Unknown
        }
    }
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
    /// Coarse poses about the second centre of a frame whose pose search gives it two (the prior
    /// kept beside the beam that replaced it, `pose_search.keep_prior_centre`, or a rival beam);
    /// `None`: `coarse_pose_count`, as about the first. Its first `n` are the first `n` of the
    /// `coarse_pose_count` it would have (the same draws). At most `coarse_pose_count`: the
    /// verdict splits a frame's outcomes into groups of `coarse_pose_count`
    /// ([`super::decide::decide_frame`]), which finds the two centres' groups only when the
    /// second is not larger; for the same reason a frame with three centres keeps
    /// `coarse_pose_count` about each. Measured (docs/measurements.md, branch `speed25`; `eval`,
    /// 24 frames, known K, gradient query): 5 cuts a block frame's CPU by 15–20 % (26–30 → 19–21
    /// views) and 10 by 4–12 %, but both lose block-2's 30 px view_021 (accepted at 5.4 px) and
    /// move house-1's view_021 from 1.1 to 7.6 px: not the default.
    pub other_centre_coarse_pose_count: Option<usize>,
    /// Standard deviation of the coarse poses' rotation noise, degrees (per axis).
    pub coarse_rotation_sigma_deg: f64,
    /// Standard deviation of the coarse poses' camera-centre noise, as a fraction of the median
    /// scene depth seen from the initial pose (dimensionless; 0.02 at 40 m is 0.8 m).
    pub coarse_translation_sigma_fraction: f64,
    pub query_mode: QueryMode,
    /// What a frame with unknown intrinsics estimates (`--intrinsics unknown|focal`).
    pub unknown_intrinsics: UnknownIntrinsics,
    /// [`QueryMode::DepthAsg`]: radius of the discontinuity-aware smoothing of the photo's depth
    /// before normals are taken, px (0: none). MVS depth is noisy per pixel; normals of raw depth
    /// are noise (a 0.7 % depth error at 20 m is 14 cm, more than the 5 cm pixel footprint).
    pub query_depth_smoothing_radius_px: usize,
    /// Neighbours whose depth differs by more than this fraction from the centre's are not
    /// averaged (they are across an occlusion edge), dimensionless.
    pub query_depth_max_relative_step: f32,
    /// [`QueryMode::Mixed`]: a pixel's depth-ASG is trusted when at least this share of the
    /// pixels within the smoothing radius + 1 have depth (and all of its 3×3 neighbours do);
    /// between this share and 1 the query blends from the photo's gradient to the depth-ASG.
    pub query_mixed_min_valid_share: f32,
    pub render: RenderOptions,
    pub asg: AsgOptions,
    /// Dense matching of the query against each rendering (pixel pairs; paper §3.2).
    pub matching: MatchConfig,
    /// At most this many correspondences per coarse pose go to RANSAC (an even subsample).
    pub max_correspondences_per_pose: usize,
    /// Matches whose rendering pixel has a neighbour within this many px on another surface
    /// (a depth discontinuity, where the depth lookup picks foreground or background by chance)
    /// are not lifted; 0 lifts every match.
    pub lift_edge_margin_px: usize,
    /// Fewer consistent correspondences than this: the coarse pose gives no hypothesis.
    pub min_correspondences_per_pose: usize,
    pub pose: PoseEstimationConfig,
    pub verify: VerifyConfig,
    /// The final refinement of the chosen pose against the photo's edges (step "refine").
    pub edge_align: EdgeAlignConfig,
    /// The calibrated confidence and the accept threshold (step "decide").
    pub confidence: ConfidenceConfig,
    /// The pose search before the coarse poses (step "search"): its region in degrees, its
    /// edge map's pyramid level and blur in px, how many beams, when a beam replaces the prior.
    pub pose_search: PoseSearchConfig,
    /// One more hypothesis from a registered neighbour frame (step "neighbour", batch only).
    pub neighbour_pose: super::neighbour::NeighbourPoseConfig,
}

impl Default for RegistrationConfig {
    fn default() -> Self {
        let matching = MatchConfig {
            sift_flow: crate::core::sift_flow::SiftFlowConfig::fast(),
            ..MatchConfig::default()
        };
        Self {
            coarse_pose_count: 15,
            other_centre_coarse_pose_count: None,
            coarse_rotation_sigma_deg: 1.0,
            coarse_translation_sigma_fraction: 0.02,
            query_mode: QueryMode::ImageGradient,
            unknown_intrinsics: UnknownIntrinsics::Dlt,
            query_depth_smoothing_radius_px: 3,
            query_depth_max_relative_step: 0.03,
            query_mixed_min_valid_share: 0.8,
            render: RenderOptions::default(),
            asg: AsgOptions::default(),
            matching,
            max_correspondences_per_pose: 3000,
            lift_edge_margin_px: 0,
            min_correspondences_per_pose: 30,
            pose: PoseEstimationConfig::default(),
            verify: VerifyConfig::default(),
            edge_align: EdgeAlignConfig::default(),
            confidence: ConfidenceConfig::default(),
            pose_search: PoseSearchConfig::default(),
            neighbour_pose: super::neighbour::NeighbourPoseConfig::default(),
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
    #[error("query mode {mode:?} needs the photo's depth map, and none was given: give the depth folder, or use the gradient query")]
    MissingDepth { mode: QueryMode },
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
    #[error("dense matching failed: {0}")]
    Flow(String),
    #[error(transparent)]
    Image(#[from] crate::core::image::ImageError),
}

impl RegistrationConfig {
    /// The most coarse views a frame can have: `coarse_pose_count` per centre of the pose search.
    pub fn max_coarse_views(&self) -> usize {
        let centres = if self.pose_search.enabled {
            self.pose_search.max_centres
        } else {
            1
        };
        self.coarse_pose_count * centres
    }

    /// How many coarse views each of a frame's `centres` centres gets, in the centres' order
    /// (`coarse_pose_count` each, but the second of two `other_centre_coarse_pose_count`).
    pub fn coarse_views_per_centre(&self, centres: usize) -> Vec<usize> {
        let mut counts = vec![self.coarse_pose_count; centres];
        if let (2, Some(other)) = (centres, self.other_centre_coarse_pose_count) {
            counts[1] = other.min(self.coarse_pose_count);
        }
        counts
    }

    pub fn validate(&self) -> Result<(), RegistrationError> {
        let bad =
            |field: &'static str, why: String| Err(RegistrationError::InvalidConfig { field, why });
        if self.coarse_pose_count == 0 {
            return bad("coarse_pose_count", "must be at least 1".into());
        }
        if let Some(other) = self.other_centre_coarse_pose_count {
            if other == 0 || other > self.coarse_pose_count {
                return bad(
                    "other_centre_coarse_pose_count",
                    format!(
                        "{other} is outside 1..={} (coarse_pose_count)",
                        self.coarse_pose_count
                    ),
                );
            }
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
        let neighbour = &self.neighbour_pose;
        if !(0.0..=180.0).contains(&neighbour.max_axis_angle_deg) {
            return bad(
                "neighbour_pose.max_axis_angle_deg",
                format!("{} is outside 0..=180", neighbour.max_axis_angle_deg),
            );
        }
        if !(0.0..=1.0).contains(&neighbour.min_inlier_share) {
            return bad(
                "neighbour_pose.min_inlier_share",
                format!("{} is outside 0..=1", neighbour.min_inlier_share),
            );
        }
        if neighbour.quorum_lenders == 1 {
            return bad(
                "neighbour_pose.quorum_lenders",
                "is 1: a quorum needs at least 2 lenders (0 turns it off)".into(),
            );
        }
        if neighbour.warp_rounds == 0 {
            return bad(
                "neighbour_pose.warp_rounds",
                "is 0: a warped view is matched at least once (1: once, no further rounds)".into(),
            );
        }
        if !(0.0..=1.0).contains(&neighbour.quorum_support_share) {
            return bad(
                "neighbour_pose.quorum_support_share",
                format!("{} is outside 0..=1", neighbour.quorum_support_share),
            );
        }
        if neighbour.enabled && (neighbour.candidates == 0 || neighbour.max_steps == 0) {
            return bad(
                "neighbour_pose",
                "candidates and max_steps must be at least 1 when the step is enabled".into(),
            );
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
        if let Some(ratio) = self.asg.occlusion_depth_ratio {
            if !(ratio.is_finite() && ratio > 0.0) {
                return bad(
                    "asg.occlusion_depth_ratio",
                    format!(
                        "{ratio} is not a positive number (a share of the nearer depth, e.g. 0.1)"
                    ),
                );
            }
        }
        if !(0.0..1.0).contains(&self.query_mixed_min_valid_share) {
            return bad(
                "query_mixed_min_valid_share",
                format!("{} is outside [0, 1)", self.query_mixed_min_valid_share),
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
        self.matching
            .validate()
            .map_err(|e| RegistrationError::InvalidConfig {
                field: "matching",
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
        self.edge_align
            .validate()
            .map_err(|e| RegistrationError::InvalidConfig {
                field: "edge_align",
                why: e.to_string(),
            })?;
        self.confidence
            .validate()
            .map_err(|e| RegistrationError::InvalidConfig {
                field: "confidence",
                why: e.to_string(),
            })?;
        self.pose_search
            .validate()
            .map_err(|e| RegistrationError::InvalidConfig {
                field: "pose_search",
                why: e.to_string(),
            })?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The step "neighbour" settings a run cannot mean are refused by name: a quorum of one
    /// lender, a support share outside 0..=1, no match of a warped view.
    #[test]
    fn neighbour_settings_that_mean_nothing_are_refused_by_name() {
        assert!(RegistrationConfig::default().validate().is_ok());
        let refused = |change: fn(&mut RegistrationConfig)| {
            let mut config = RegistrationConfig::default();
            change(&mut config);
            match config.validate() {
                Err(RegistrationError::InvalidConfig { field, .. }) => field,
                other => panic!("{other:?}"),
            }
        };
        assert_eq!(
            refused(|c| c.neighbour_pose.quorum_lenders = 1),
            "neighbour_pose.quorum_lenders"
        );
        assert_eq!(
            refused(|c| c.neighbour_pose.quorum_support_share = 1.5),
            "neighbour_pose.quorum_support_share"
        );
        assert_eq!(
            refused(|c| c.neighbour_pose.warp_rounds = 0),
            "neighbour_pose.warp_rounds"
        );
    }
}
