//! The pose step for one coarse pose (docs/design.md §2 step 6), end to end: look at the 3D points'
//! shape, pick the solver, run RANSAC, refine on the inliers, re-score.
//!
//! Solver choice and the planar policy:
//! - **known intrinsics** → EPnP (or P3P, [`FixedIntrinsicsSolver`]) inside RANSAC — EPnP switches
//!   to its planar variant for planar samples — then Levenberg–Marquardt on the pose (6 DoF);
//! - **unknown focal length** (principal point, aspect known, no skew) → EPnP with unknown focal
//!   length ([`super::epnpf`]) on 6 points, then Levenberg–Marquardt on the focal length and the
//!   pose (7 DoF); the same planar policy as the DLT's below;
//! - **unknown intrinsics** → the paper's normalised DLT on 6 points, then Levenberg–Marquardt on
//!   `fx, fy, cx, cy` and the pose, from skew 0 (`zero_skew`, the default) or the DLT's skew.
//!   A DLT needs relief: when the planarity ratio of all 3D points (smallest over largest
//!   principal standard deviation, [`PointCloudShape`]) is below
//!   [`PoseEstimationConfig::dlt_min_planarity_ratio`], intrinsics are not observable from one
//!   view and the DLT's `K` is noise. Then, if the caller gave `planar_fallback` intrinsics (for
//!   example the initial guess or the camera's nominal values), the pose is solved with them fixed
//!   ([`IntrinsicsSource::PlanarFallback`], the fixed-intrinsics solver above); otherwise the step
//!   refuses with [`PoseError::NearPlanar`], naming the ratio, instead of returning a made-up
//!   camera.
//!
//! The shape is always reported, so the verification can say "near-planar view" when it fails.

use rand::Rng;
use serde::{Deserialize, Serialize};

use super::epnpf::FocalPrior;
use super::planarity::{point_cloud_shape, PointCloudShape};
use super::ransac::{
    ransac_camera, Consensus, DltEstimator, EpnpEstimator, EpnpFocalEstimator, P3pEstimator,
    RansacConfig, ReprojectionConsensus,
};
use super::refine::{refine_camera, RefineConfig, RefinedParameters, RefinementSummary};
use super::{CameraPose, Correspondences, PoseError};
use crate::core::camera::PinholeIntrinsics;

/// What is known about the intrinsics of the photo.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum IntrinsicsPrior {
    /// Calibrated camera: only the pose is estimated.
    Known(PinholeIntrinsics),
    /// Uncalibrated: intrinsics and pose are estimated (DLT). `planar_fallback` is used, fixed,
    /// when the 3D points are too close to a plane for a DLT; `None` makes such frames fail.
    Unknown {
        planar_fallback: Option<PinholeIntrinsics>,
    },
    /// Only the focal length is unknown (principal point, aspect ratio known, no skew): EPnP
    /// with unknown focal length ([`super::epnpf`]), then refinement of focal length and pose.
    /// `planar_fallback` as for `Unknown`.
    UnknownFocal {
        prior: FocalPrior,
        planar_fallback: Option<PinholeIntrinsics>,
    },
}

/// Settings of the pose step.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseEstimationConfig {
    pub ransac: RansacConfig,
    pub refinement: RefineConfig,
    /// Solver for fixed intrinsics (known, or the planar fallback).
    pub fixed_intrinsics_solver: FixedIntrinsicsSolver,
    /// Correspondences per EPnP sample, 4–6 (see [`super::ransac`] for why 5).
    pub epnp_sample_size: usize,
    /// Smallest planarity ratio (dimensionless, see [`PointCloudShape::planarity_ratio`]) at which
    /// the DLT is used for unknown intrinsics. 0.02: a flat town 100 m across with 5–10 m of relief
    /// is about 0.03–0.05 and passes; a façade seen head-on, or a patch of ground, does not.
    /// Measured (test `dlt_accuracy_against_planarity`, 300 inliers at 0.5 px, camera 60 m away):
    /// the DLT + LM focal length error (median–worst of 5) grows about as 0.08 % / ratio: 0.2 % at
    /// 0.5, 1.5–2 % at 0.05, 3–3.6 % at 0.025, 6–6.6 % at 0.013, 14–16 % at 0.005, 40–85 % at 0.0013.
    pub dlt_min_planarity_ratio: f64,
    /// With estimated intrinsics, refine from skew 0 and keep it there, so the result is a physical
    /// camera (COLMAP PINHOLE cannot store skew); false keeps the DLT's (noisy) skew. Only applies
    /// when refinement runs.
    pub zero_skew: bool,
}

impl Default for PoseEstimationConfig {
    fn default() -> Self {
        Self {
            ransac: RansacConfig::default(),
            refinement: RefineConfig::default(),
            fixed_intrinsics_solver: FixedIntrinsicsSolver::default(),
            epnp_sample_size: EpnpEstimator::DEFAULT_SAMPLE_SIZE,
            dlt_min_planarity_ratio: 0.02,
            zero_skew: true,
        }
    }
}

impl PoseEstimationConfig {
    pub fn validate(&self) -> Result<(), PoseError> {
        self.ransac.validate()?;
        self.refinement.validate()?;
        if !(4..=6).contains(&self.epnp_sample_size) {
            return Err(PoseError::InvalidConfig {
                field: "epnp_sample_size",
                why: "must be 4, 5 or 6",
            });
        }
        if !(self.dlt_min_planarity_ratio.is_finite() && self.dlt_min_planarity_ratio >= 0.0) {
            return Err(PoseError::InvalidConfig {
                field: "dlt_min_planarity_ratio",
                why: "must be a non-negative number",
            });
        }
        Ok(())
    }
}

/// Which solver produced the camera (inside RANSAC).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum SolverKind {
    /// Normalised DLT on 6 points (intrinsics estimated).
    Dlt,
    /// EPnP on `epnp_sample_size` points (intrinsics fixed).
    Epnp,
    /// P3P on 3 + 1 points (intrinsics fixed).
    P3p,
    /// EPnP with unknown focal length on 6 points (focal length estimated).
    EpnpFocal,
}

/// The solver used when the intrinsics are fixed (known, or the planar fallback).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum FixedIntrinsicsSolver {
    /// EPnP (the paper's choice for known intrinsics).
    #[default]
    Epnp,
    /// Grunert's P3P with a fourth point to choose: smaller samples, same accuracy after LO and LM.
    P3p,
}

/// Where the intrinsics of the result come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum IntrinsicsSource {
    /// Estimated with the pose (DLT, then refinement).
    Estimated,
    /// Given as known.
    Known,
    /// The caller's fallback, because the points were too planar for a DLT.
    PlanarFallback,
}

/// How the RANSAC stage went (before refinement).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RansacSummary {
    pub iterations: usize,
    pub degenerate_samples: usize,
    pub inlier_count: usize,
    pub inlier_rms_px: f64,
    pub reached_stop_ratio: bool,
}

/// The camera found for one set of correspondences, and how.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseEstimate {
    /// Intrinsics (estimated, known or fallback) and `cam_from_world`.
    pub camera: CameraPose,
    pub solver: SolverKind,
    pub intrinsics_source: IntrinsicsSource,
    /// Inliers of the final camera at the RANSAC threshold, one entry per correspondence.
    pub inlier_mask: Vec<bool>,
    /// The consensus size the plausibility check ranks poses by.
    pub inlier_count: usize,
    /// RMS reprojection error over the final inliers, px.
    pub inlier_rms_px: f64,
    pub ransac: RansacSummary,
    /// `None` when refinement was switched off or impossible (then `camera` is RANSAC's).
    pub refinement: Option<RefinementSummary>,
    /// Shape of all 3D points, for reporting near-planar views.
    pub point_cloud_shape: PointCloudShape,
}

/// Estimates the camera from correspondences: see the module documentation for the policy.
pub fn estimate_pose<R: Rng + ?Sized>(
    data: &Correspondences,
    prior: &IntrinsicsPrior,
    config: &PoseEstimationConfig,
    rng: &mut R,
) -> Result<PoseEstimate, PoseError> {
    config.validate()?;
    let point_cloud_shape = point_cloud_shape(data.world_points())?;
    let fixed_intrinsics_ransac =
        |intrinsics: &PinholeIntrinsics, rng: &mut R| match config.fixed_intrinsics_solver {
            FixedIntrinsicsSolver::Epnp => {
                let estimator = EpnpEstimator::new(*intrinsics, config.epnp_sample_size)?;
                Ok::<_, PoseError>((
                    ransac_camera(&estimator, data, &config.ransac, rng)?,
                    SolverKind::Epnp,
                ))
            }
            FixedIntrinsicsSolver::P3p => {
                let estimator = P3pEstimator::new(*intrinsics)?;
                Ok((
                    ransac_camera(&estimator, data, &config.ransac, rng)?,
                    SolverKind::P3p,
                ))
            }
        };
    let (ransac_output, solver, intrinsics_source) = match prior {
        IntrinsicsPrior::Known(intrinsics) => {
            let (output, solver) = fixed_intrinsics_ransac(intrinsics, rng)?;
            (output, solver, IntrinsicsSource::Known)
        }
        IntrinsicsPrior::Unknown { planar_fallback }
        | IntrinsicsPrior::UnknownFocal {
            planar_fallback, ..
        } => {
            if point_cloud_shape.planarity_ratio >= config.dlt_min_planarity_ratio {
                match prior {
                    IntrinsicsPrior::UnknownFocal { prior, .. } => (
                        ransac_camera(
                            &EpnpFocalEstimator::new(*prior)?,
                            data,
                            &config.ransac,
                            rng,
                        )?,
                        SolverKind::EpnpFocal,
                        IntrinsicsSource::Estimated,
                    ),
                    _ => (
                        ransac_camera(&DltEstimator, data, &config.ransac, rng)?,
                        SolverKind::Dlt,
                        IntrinsicsSource::Estimated,
                    ),
                }
            } else if let Some(intrinsics) = planar_fallback {
                let (output, solver) = fixed_intrinsics_ransac(intrinsics, rng)?;
                (output, solver, IntrinsicsSource::PlanarFallback)
            } else {
                return Err(PoseError::NearPlanar {
                    planarity_ratio: point_cloud_shape.planarity_ratio,
                    min_ratio: config.dlt_min_planarity_ratio,
                });
            }
        }
    };
    let refined_parameters = match intrinsics_source {
        IntrinsicsSource::Estimated if solver == SolverKind::EpnpFocal => {
            RefinedParameters::FocalAndPose
        }
        IntrinsicsSource::Estimated => RefinedParameters::IntrinsicsAndPose,
        IntrinsicsSource::Known | IntrinsicsSource::PlanarFallback => RefinedParameters::Pose,
    };
    let ransac = RansacSummary {
        iterations: ransac_output.iterations,
        degenerate_samples: ransac_output.degenerate_samples,
        inlier_count: ransac_output.inlier_count,
        inlier_rms_px: ransac_output.inlier_rms_px,
        reached_stop_ratio: ransac_output.reached_stop_ratio,
    };
    let consensus = ReprojectionConsensus {
        threshold_px: config.ransac.threshold_px,
    };
    let mut camera = ransac_output.model;
    let mut inlier_mask = ransac_output.inlier_mask;
    let mut score = consensus.score(&camera.projection_matrix(), data, &mut inlier_mask);
    let mut refinement = None;
    if config.refinement.max_iterations > 0 {
        let (inlier_image, inlier_world): (Vec<_>, Vec<_>) = data
            .image_points_px()
            .iter()
            .zip(data.world_points())
            .zip(&inlier_mask)
            .filter(|(_, &inlier)| inlier)
            .map(|((image_point, world_point), _)| (*image_point, *world_point))
            .unzip();
        let mut start = camera;
        if config.zero_skew && intrinsics_source == IntrinsicsSource::Estimated {
            start.intrinsics.skew_px = 0.0;
        }
        if let Ok((refined, summary)) = refine_camera(
            &start,
            &inlier_image,
            &inlier_world,
            refined_parameters,
            &config.refinement,
        ) {
            let mut refined_mask = vec![false; data.len()];
            let refined_score =
                consensus.score(&refined.projection_matrix(), data, &mut refined_mask);
            // Refinement lowers the error on the old inliers; keep it unless it loses support.
            if refined_score.inlier_count >= score.inlier_count {
                camera = refined;
                inlier_mask = refined_mask;
                score = refined_score;
                refinement = Some(summary);
            }
        }
    }
    Ok(PoseEstimate {
        camera,
        solver,
        intrinsics_source,
        inlier_mask,
        inlier_count: score.inlier_count,
        inlier_rms_px: score.inlier_rms_px(),
        ransac,
        refinement,
        point_cloud_shape,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::pose::test_scenes::{
        corrupt, random_scene, rotation_error_deg, test_intrinsics, Scene,
    };
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn scene(seed: u64, relief_m: f64) -> Scene {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut scene = random_scene(&mut rng, test_intrinsics(), 600, relief_m);
        corrupt(&mut scene, &mut rng, 0.5, 300);
        scene
    }

    #[test]
    fn unknown_intrinsics_recover_camera_and_refinement_reaches_the_noise_floor() {
        for seed in 0..3 {
            let scene = scene(200 + seed, 15.0);
            let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
            let prior = IntrinsicsPrior::Unknown {
                planar_fallback: None,
            };
            let estimate = estimate_pose(
                &data,
                &prior,
                &PoseEstimationConfig::default(),
                &mut ChaCha8Rng::seed_from_u64(seed),
            )
            .unwrap();
            assert_eq!(estimate.solver, SolverKind::Dlt);
            assert_eq!(estimate.intrinsics_source, IntrinsicsSource::Estimated);
            assert_eq!(estimate.camera.intrinsics.skew_px, 0.0);
            let refinement = estimate.refinement.unwrap();
            assert!(refinement.final_rms_px <= refinement.initial_rms_px);
            // 0.5 px per axis: the RMS distance of a 2D Gaussian is 0.71 px.
            assert!(estimate.inlier_rms_px < 0.75, "{}", estimate.inlier_rms_px);
            let truth = &scene.camera;
            assert!(
                rotation_error_deg(&estimate.camera.cam_from_world, &truth.cam_from_world) < 0.5
            );
            assert!(
                (estimate.camera.cam_from_world.camera_center()
                    - truth.cam_from_world.camera_center())
                .norm()
                    < 0.4
            );
            assert!(
                (estimate.camera.intrinsics.fx_px - truth.intrinsics.fx_px).abs()
                    < 0.02 * truth.intrinsics.fx_px
            );
            assert!(
                (295..=310).contains(&estimate.inlier_count),
                "{}",
                estimate.inlier_count
            );
            assert!(estimate.point_cloud_shape.planarity_ratio > 0.1);
        }
    }

    #[test]
    fn unknown_focal_length_is_recovered_with_outliers_and_noise() {
        for seed in 0..3 {
            let scene = scene(210 + seed, 15.0);
            let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
            let truth = &scene.camera;
            // Principal point and aspect ratio known, the nominal focal length 20 % off.
            let prior = IntrinsicsPrior::UnknownFocal {
                prior: FocalPrior::centred(
                    &PinholeIntrinsics {
                        fx_px: 1.2 * truth.intrinsics.fx_px,
                        fy_px: 1.2 * truth.intrinsics.fy_px,
                        ..truth.intrinsics
                    },
                    nalgebra::Vector2::new(truth.intrinsics.cx_px, truth.intrinsics.cy_px),
                ),
                planar_fallback: None,
            };
            let estimate = estimate_pose(
                &data,
                &prior,
                &PoseEstimationConfig::default(),
                &mut ChaCha8Rng::seed_from_u64(seed),
            )
            .unwrap();
            assert_eq!(estimate.solver, SolverKind::EpnpFocal);
            assert_eq!(estimate.intrinsics_source, IntrinsicsSource::Estimated);
            let k = &estimate.camera.intrinsics;
            assert_eq!((k.cx_px, k.cy_px, k.skew_px), (330.0, 235.0, 0.0));
            assert!(estimate.inlier_rms_px < 0.75, "{}", estimate.inlier_rms_px);
            assert!(
                (k.fx_px - truth.intrinsics.fx_px).abs() < 0.01 * truth.intrinsics.fx_px,
                "focal {} vs {}",
                k.fx_px,
                truth.intrinsics.fx_px
            );
            assert!(
                rotation_error_deg(&estimate.camera.cam_from_world, &truth.cam_from_world) < 0.3
            );
            assert!((295..=310).contains(&estimate.inlier_count));
        }
    }

    #[test]
    fn zero_skew_can_be_turned_off() {
        let scene = scene(205, 15.0);
        let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
        let prior = IntrinsicsPrior::Unknown {
            planar_fallback: None,
        };
        let config = PoseEstimationConfig {
            zero_skew: false,
            ..PoseEstimationConfig::default()
        };
        let estimate =
            estimate_pose(&data, &prior, &config, &mut ChaCha8Rng::seed_from_u64(0)).unwrap();
        // The DLT's skew is noise, never exactly zero, and refinement keeps it.
        assert_ne!(estimate.camera.intrinsics.skew_px, 0.0);
        assert!(estimate.camera.intrinsics.skew_px.abs() < 10.0);
    }

    #[test]
    fn known_intrinsics_recover_the_pose_with_either_solver() {
        let scene = scene(210, 15.0);
        let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
        let prior = IntrinsicsPrior::Known(scene.camera.intrinsics);
        for (choice, solver) in [
            (FixedIntrinsicsSolver::Epnp, SolverKind::Epnp),
            (FixedIntrinsicsSolver::P3p, SolverKind::P3p),
        ] {
            let config = PoseEstimationConfig {
                fixed_intrinsics_solver: choice,
                ..PoseEstimationConfig::default()
            };
            let estimate =
                estimate_pose(&data, &prior, &config, &mut ChaCha8Rng::seed_from_u64(1)).unwrap();
            assert_eq!(estimate.solver, solver);
            assert_eq!(estimate.intrinsics_source, IntrinsicsSource::Known);
            assert_eq!(estimate.camera.intrinsics, scene.camera.intrinsics);
            assert!(
                rotation_error_deg(
                    &estimate.camera.cam_from_world,
                    &scene.camera.cam_from_world
                ) < 0.1
            );
            assert!(
                (estimate.camera.cam_from_world.camera_center()
                    - scene.camera.cam_from_world.camera_center())
                .norm()
                    < 0.1
            );
            assert!(estimate.inlier_rms_px < 0.75);
        }
    }

    #[test]
    fn near_planar_points_are_refused_for_a_dlt_or_solved_with_fallback_intrinsics() {
        // 0.2 m of relief over 40 m: planarity ratio about 0.005.
        let scene = scene(220, 0.2);
        let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
        let config = PoseEstimationConfig::default();
        let refused = estimate_pose(
            &data,
            &IntrinsicsPrior::Unknown {
                planar_fallback: None,
            },
            &config,
            &mut ChaCha8Rng::seed_from_u64(1),
        );
        match refused {
            Err(PoseError::NearPlanar {
                planarity_ratio,
                min_ratio,
            }) => {
                assert!(
                    planarity_ratio < 0.01 && min_ratio == 0.02,
                    "{planarity_ratio}"
                );
            }
            other => panic!("expected NearPlanar, got {other:?}"),
        }
        // Fallback intrinsics 2 % off in focal length: the pose is still close.
        let fallback = PinholeIntrinsics {
            fx_px: 1.02 * scene.camera.intrinsics.fx_px,
            fy_px: 1.02 * scene.camera.intrinsics.fy_px,
            ..scene.camera.intrinsics
        };
        let estimate = estimate_pose(
            &data,
            &IntrinsicsPrior::Unknown {
                planar_fallback: Some(fallback),
            },
            &config,
            &mut ChaCha8Rng::seed_from_u64(1),
        )
        .unwrap();
        assert_eq!(estimate.solver, SolverKind::Epnp);
        assert_eq!(estimate.intrinsics_source, IntrinsicsSource::PlanarFallback);
        assert_eq!(estimate.camera.intrinsics, fallback);
        assert!(
            rotation_error_deg(
                &estimate.camera.cam_from_world,
                &scene.camera.cam_from_world
            ) < 0.5
        );
        assert!(estimate.inlier_count >= 290);
        // Known intrinsics on exactly planar points: EPnP's planar variant.
        let planar = scene_with_relief_exactly_zero();
        let data = Correspondences::new(&planar.image_points_px, &planar.world_points).unwrap();
        let estimate = estimate_pose(
            &data,
            &IntrinsicsPrior::Known(planar.camera.intrinsics),
            &config,
            &mut ChaCha8Rng::seed_from_u64(2),
        )
        .unwrap();
        assert!(estimate.point_cloud_shape.planarity_ratio < 1e-6);
        assert!(
            rotation_error_deg(
                &estimate.camera.cam_from_world,
                &planar.camera.cam_from_world
            ) < 0.2
        );
    }

    fn scene_with_relief_exactly_zero() -> Scene {
        scene(230, 0.0)
    }

    /// Prints how the DLT's intrinsics degrade as the scene flattens (the reason for the default
    /// `dlt_min_planarity_ratio`); asserts only that well-spread scenes are accurate.
    #[test]
    fn dlt_accuracy_against_planarity() {
        let config = PoseEstimationConfig {
            dlt_min_planarity_ratio: 0.0,
            ..PoseEstimationConfig::default()
        };
        for relief_m in [20.0, 5.0, 2.0, 1.0, 0.5, 0.2, 0.05] {
            let mut focal_errors = Vec::new();
            let mut ratio = 0.0;
            for seed in 0..5 {
                let scene = scene(300 + seed, relief_m);
                let data =
                    Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
                let prior = IntrinsicsPrior::Unknown {
                    planar_fallback: None,
                };
                let estimate =
                    estimate_pose(&data, &prior, &config, &mut ChaCha8Rng::seed_from_u64(seed));
                ratio = point_cloud_shape(&scene.world_points)
                    .unwrap()
                    .planarity_ratio;
                let error = estimate.map_or(f64::INFINITY, |e| {
                    (e.camera.intrinsics.fx_px / scene.camera.intrinsics.fx_px - 1.0).abs()
                });
                focal_errors.push(error);
            }
            focal_errors.sort_by(f64::total_cmp);
            println!(
                "relief {relief_m:5.2} m, planarity ratio {ratio:.4}: DLT focal error median {:.2} %, worst {:.2} %",
                100.0 * focal_errors[2],
                100.0 * focal_errors[4]
            );
            if relief_m >= 5.0 {
                assert!(
                    focal_errors[4] < 0.02,
                    "relief {relief_m}: {focal_errors:?}"
                );
            }
        }
    }

    #[test]
    fn bad_config_and_nan_input_are_rejected() {
        let scene = scene(240, 15.0);
        assert!(matches!(
            Correspondences::new(&scene.image_points_px, &scene.world_points[1..]),
            Err(PoseError::LengthMismatch { .. })
        ));
        let mut nan_points = scene.world_points.clone();
        nan_points[17].z = f64::NAN;
        assert_eq!(
            Correspondences::new(&scene.image_points_px, &nan_points).unwrap_err(),
            PoseError::NonFinite { index: 17 }
        );
        let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
        let prior = IntrinsicsPrior::Unknown {
            planar_fallback: None,
        };
        for config in [
            PoseEstimationConfig {
                epnp_sample_size: 3,
                ..PoseEstimationConfig::default()
            },
            PoseEstimationConfig {
                dlt_min_planarity_ratio: f64::NAN,
                ..PoseEstimationConfig::default()
            },
        ] {
            assert!(matches!(
                estimate_pose(&data, &prior, &config, &mut ChaCha8Rng::seed_from_u64(0)),
                Err(PoseError::InvalidConfig { .. })
            ));
        }
        assert!(serde_json::from_str::<PoseEstimationConfig>(
            r#"{"ransac": {"max_iterations": 10}, "extra": 1}"#
        )
        .is_err());
        let parsed: PoseEstimationConfig =
            serde_json::from_str(r#"{"ransac": {"max_iterations": 10}}"#).unwrap();
        assert_eq!(parsed.ransac.max_iterations, 10);
        assert_eq!(parsed.ransac.stop_inlier_ratio, 0.65);
    }
}
