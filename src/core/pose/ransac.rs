//! RANSAC for camera solvers (docs/design.md §2 step 6): SIFT flow hands over thousands of 2D–3D
//! correspondences of which many are wrong; a minimal solver inside RANSAC finds the camera the
//! correct ones agree on.
//!
//! References: M. Fischler, R. Bolles, "Random Sample Consensus", CACM 24(6), 1981; local
//! optimisation after O. Chum, J. Matas, J. Kittler, "Locally Optimized RANSAC", DAGM 2003 (here
//! the simple variant: re-fit a new best model on its inliers, twice). Structure after kornia-rs:
//! an [`Estimator`] (the solver), a [`Sampler`] (distinct indices drawn with the RNG passed in, so
//! a seed reproduces a run exactly) and a [`Consensus`] (inliers by reprojection error in pixels).
//!
//! The stopping rule is the paper's (§3, "Pose Estimation"): stop as soon as the best consensus
//! holds 65 % of all correspondences, otherwise after 500 iterations. No adaptive
//! (confidence-based) stop: the paper did not use one, and a fixed rule keeps runs comparable.
//!
//! Estimators: [`DltEstimator`] (unknown intrinsics, 6 points, the paper's), [`EpnpEstimator`]
//! (known intrinsics, 4–6 points, default 5: four is minimal but EPnP's `N = 4` case is its least
//! stable one — [`super::epnp`] adds P3P candidates to make it exact on exact data — while five
//! costs little in iterations: at 50 % outliers a clean sample has probability 1/32 rather than
//! 1/16, still 1 − 10⁻⁷ over 500 iterations; six makes it 1/64) and [`P3pEstimator`] (known
//! intrinsics, P3P on 3 points + 1 to choose among its solutions: the smallest sample).

use nalgebra::{Matrix3x4, Vector2, Vector3};
use rand::Rng;
use serde::{Deserialize, Serialize};

use super::{dlt, epnp, epnpf, p3p, project_with_matrix, CameraPose, Correspondences, PoseError};
use crate::core::camera::PinholeIntrinsics;

/// Settings of the RANSAC loop. Defaults are the paper's stopping rule.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RansacConfig {
    /// A correspondence supports a model when its reprojection error is at most this, in pixels.
    /// The paper does not state its value; 4 px allows for SIFT flow's integer flow and a noisy
    /// mesh.
    pub threshold_px: f64,
    /// Iterations (samples drawn) at most. Paper: 500.
    pub max_iterations: usize,
    /// Stop as soon as the best consensus holds this fraction of all correspondences, in (0, 1].
    /// Paper: 0.65.
    pub stop_inlier_ratio: f64,
    /// Iterations always run before the stop rule may end the loop (0: the paper's rule as is).
    pub min_iterations: usize,
    /// Rounds of local optimisation (re-fit on the inliers, keep if the consensus grows) whenever a
    /// new best model is found; 0 turns it off (plain RANSAC, as in the paper).
    pub local_optimization_rounds: usize,
}

impl Default for RansacConfig {
    fn default() -> Self {
        Self {
            threshold_px: 4.0,
            max_iterations: 500,
            stop_inlier_ratio: 0.65,
            min_iterations: 0,
            local_optimization_rounds: 2,
        }
    }
}

impl RansacConfig {
    pub fn validate(&self) -> Result<(), PoseError> {
        if !(self.threshold_px.is_finite() && self.threshold_px > 0.0) {
            return Err(PoseError::InvalidConfig {
                field: "ransac.threshold_px",
                why: "must be a positive number of pixels",
            });
        }
        if self.max_iterations == 0 {
            return Err(PoseError::InvalidConfig {
                field: "ransac.max_iterations",
                why: "must be at least 1",
            });
        }
        if !(self.stop_inlier_ratio > 0.0 && self.stop_inlier_ratio <= 1.0) {
            return Err(PoseError::InvalidConfig {
                field: "ransac.stop_inlier_ratio",
                why: "must be in (0, 1]",
            });
        }
        if self.min_iterations > self.max_iterations {
            return Err(PoseError::InvalidConfig {
                field: "ransac.min_iterations",
                why: "must not exceed max_iterations",
            });
        }
        Ok(())
    }
}

/// A solver RANSAC can run: fits a model to a sample (or, for local optimisation, to all inliers).
pub trait Estimator {
    type Model: Clone;
    /// Correspondences per random sample.
    fn sample_size(&self) -> usize;
    /// Fits a model to the given correspondences (at least `sample_size` of them). Degenerate
    /// samples return an error; RANSAC counts and skips them.
    fn fit(
        &self,
        image_points_px: &[Vector2<f64>],
        world_points: &[Vector3<f64>],
    ) -> Result<Self::Model, PoseError>;
    /// The model as `P = K [R | t]` (third row = depth), for scoring.
    fn projection_matrix(&self, model: &Self::Model) -> Matrix3x4<f64>;
}

/// Draws the indices of a sample.
pub trait Sampler {
    /// Writes `sample_size` distinct indices below `population` into `indices` (cleared first).
    /// Callers guarantee `sample_size <= population`.
    fn sample<R: Rng + ?Sized>(
        &mut self,
        population: usize,
        sample_size: usize,
        rng: &mut R,
        indices: &mut Vec<usize>,
    );
}

/// Every correspondence equally likely; distinct indices by rejection (samples are tiny).
#[derive(Clone, Copy, Debug, Default)]
pub struct UniformSampler;

impl Sampler for UniformSampler {
    fn sample<R: Rng + ?Sized>(
        &mut self,
        population: usize,
        sample_size: usize,
        rng: &mut R,
        indices: &mut Vec<usize>,
    ) {
        indices.clear();
        while indices.len() < sample_size.min(population) {
            let index = rng.random_range(0..population);
            if !indices.contains(&index) {
                indices.push(index);
            }
        }
    }
}

/// The support of a model.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct ConsensusScore {
    pub inlier_count: usize,
    /// Sum over inliers of the squared reprojection error, px².
    pub inlier_squared_error_sum_px2: f64,
}

impl ConsensusScore {
    /// More inliers wins; equal counts go to the smaller error.
    pub fn is_better_than(&self, other: &ConsensusScore) -> bool {
        self.inlier_count > other.inlier_count
            || (self.inlier_count == other.inlier_count
                && self.inlier_squared_error_sum_px2 < other.inlier_squared_error_sum_px2)
    }

    pub fn inlier_rms_px(&self) -> f64 {
        if self.inlier_count == 0 {
            f64::INFINITY
        } else {
            (self.inlier_squared_error_sum_px2 / self.inlier_count as f64).sqrt()
        }
    }
}

/// Decides which correspondences support a model.
pub trait Consensus {
    /// Marks the inliers of `projection` in `inlier_mask` (one entry per correspondence).
    fn score(
        &self,
        projection: &Matrix3x4<f64>,
        data: &Correspondences,
        inlier_mask: &mut [bool],
    ) -> ConsensusScore;
}

/// Inlier when the point is in front of the camera and reprojects within `threshold_px`.
#[derive(Clone, Copy, Debug)]
pub struct ReprojectionConsensus {
    pub threshold_px: f64,
}

impl Consensus for ReprojectionConsensus {
    fn score(
        &self,
        projection: &Matrix3x4<f64>,
        data: &Correspondences,
        inlier_mask: &mut [bool],
    ) -> ConsensusScore {
        let threshold_px2 = self.threshold_px * self.threshold_px;
        let mut score = ConsensusScore::default();
        for ((image_point, world_point), inlier) in data
            .image_points_px()
            .iter()
            .zip(data.world_points())
            .zip(inlier_mask.iter_mut())
        {
            *inlier = match project_with_matrix(projection, world_point) {
                Some(projected) => {
                    let error_px2 = (projected - image_point).norm_squared();
                    let is_inlier = error_px2 <= threshold_px2;
                    if is_inlier {
                        score.inlier_count += 1;
                        score.inlier_squared_error_sum_px2 += error_px2;
                    }
                    is_inlier
                }
                None => false,
            };
        }
        score
    }
}

/// The result of a RANSAC run.
#[derive(Clone, Debug, PartialEq)]
pub struct RansacOutput<M> {
    /// The model with the largest consensus.
    pub model: M,
    /// One entry per correspondence: whether it supports `model`.
    pub inlier_mask: Vec<bool>,
    pub inlier_count: usize,
    /// RMS reprojection error over the inliers, px.
    pub inlier_rms_px: f64,
    /// Samples drawn.
    pub iterations: usize,
    /// Samples on which the estimator found no model.
    pub degenerate_samples: usize,
    /// Whether the consensus reached `stop_inlier_ratio` (rather than running out of iterations).
    pub reached_stop_ratio: bool,
}

/// Runs RANSAC with the given parts. Errors: invalid config, fewer correspondences than a sample,
/// or no model at all (every sample degenerate).
pub fn run_ransac<E, S, C, R>(
    estimator: &E,
    sampler: &mut S,
    consensus: &C,
    data: &Correspondences,
    config: &RansacConfig,
    rng: &mut R,
) -> Result<RansacOutput<E::Model>, PoseError>
where
    E: Estimator,
    S: Sampler,
    C: Consensus,
    R: Rng + ?Sized,
{
    config.validate()?;
    let sample_size = estimator.sample_size();
    if data.len() < sample_size {
        return Err(PoseError::TooFewPoints {
            solver: "RANSAC",
            needed: sample_size,
            got: data.len(),
        });
    }
    let stop_inlier_count = ((config.stop_inlier_ratio * data.len() as f64).ceil() as usize).max(1);
    let mut indices = Vec::with_capacity(sample_size);
    let mut sample_image = Vec::with_capacity(sample_size);
    let mut sample_world = Vec::with_capacity(sample_size);
    let mut mask = vec![false; data.len()];
    let mut best_mask = vec![false; data.len()];
    let mut best: Option<(E::Model, ConsensusScore)> = None;
    let mut degenerate_samples = 0;
    let mut iterations = 0;
    let mut reached_stop_ratio = false;

    while iterations < config.max_iterations {
        iterations += 1;
        sampler.sample(data.len(), sample_size, rng, &mut indices);
        if indices.len() != sample_size || indices.iter().any(|&i| i >= data.len()) {
            // A sampler breaking its contract wastes the iteration instead of panicking.
            degenerate_samples += 1;
            continue;
        }
        gather(data, &indices, &mut sample_image, &mut sample_world);
        let Ok(model) = estimator.fit(&sample_image, &sample_world) else {
            degenerate_samples += 1;
            continue;
        };
        let score = consensus.score(&estimator.projection_matrix(&model), data, &mut mask);
        if best
            .as_ref()
            .is_none_or(|(_, best_score)| score.is_better_than(best_score))
        {
            std::mem::swap(&mut mask, &mut best_mask);
            let mut new_best = (model, score);
            for _ in 0..config.local_optimization_rounds {
                if new_best.1.inlier_count <= sample_size {
                    break;
                }
                let inlier_indices: Vec<usize> =
                    (0..data.len()).filter(|&i| best_mask[i]).collect();
                gather(data, &inlier_indices, &mut sample_image, &mut sample_world);
                let Ok(refit) = estimator.fit(&sample_image, &sample_world) else {
                    break;
                };
                let refit_score =
                    consensus.score(&estimator.projection_matrix(&refit), data, &mut mask);
                if !refit_score.is_better_than(&new_best.1) {
                    break;
                }
                std::mem::swap(&mut mask, &mut best_mask);
                new_best = (refit, refit_score);
            }
            best = Some(new_best);
        }
        if let Some((_, best_score)) = &best {
            if iterations >= config.min_iterations && best_score.inlier_count >= stop_inlier_count {
                reached_stop_ratio = true;
                break;
            }
        }
    }
    let (model, score) = best.ok_or(PoseError::NoModel {
        iterations,
        degenerate_samples,
    })?;
    Ok(RansacOutput {
        model,
        inlier_mask: best_mask,
        inlier_count: score.inlier_count,
        inlier_rms_px: score.inlier_rms_px(),
        iterations,
        degenerate_samples,
        reached_stop_ratio,
    })
}

/// RANSAC with the uniform sampler and reprojection consensus at `config.threshold_px`.
pub fn ransac_camera<E, R>(
    estimator: &E,
    data: &Correspondences,
    config: &RansacConfig,
    rng: &mut R,
) -> Result<RansacOutput<E::Model>, PoseError>
where
    E: Estimator,
    R: Rng + ?Sized,
{
    let consensus = ReprojectionConsensus {
        threshold_px: config.threshold_px,
    };
    run_ransac(
        estimator,
        &mut UniformSampler,
        &consensus,
        data,
        config,
        rng,
    )
}

fn gather(
    data: &Correspondences,
    indices: &[usize],
    image_points_px: &mut Vec<Vector2<f64>>,
    world_points: &mut Vec<Vector3<f64>>,
) {
    image_points_px.clear();
    world_points.clear();
    image_points_px.extend(indices.iter().map(|&i| data.image_points_px()[i]));
    world_points.extend(indices.iter().map(|&i| data.world_points()[i]));
}

/// Unknown intrinsics: the normalised DLT on 6 points, decomposed into `K`, `R`, `t` (the paper's).
#[derive(Clone, Copy, Debug, Default)]
pub struct DltEstimator;

impl Estimator for DltEstimator {
    type Model = CameraPose;

    fn sample_size(&self) -> usize {
        dlt::DLT_MIN_POINTS
    }

    fn fit(
        &self,
        image_points_px: &[Vector2<f64>],
        world_points: &[Vector3<f64>],
    ) -> Result<CameraPose, PoseError> {
        let (intrinsics, cam_from_world) = dlt::solve(image_points_px, world_points)?;
        Ok(CameraPose {
            intrinsics,
            cam_from_world,
        })
    }

    fn projection_matrix(&self, model: &CameraPose) -> Matrix3x4<f64> {
        model.projection_matrix()
    }
}

/// Known intrinsics: EPnP on `sample_size` (4–6) points.
#[derive(Clone, Copy, Debug)]
pub struct EpnpEstimator {
    intrinsics: PinholeIntrinsics,
    sample_size: usize,
}

impl EpnpEstimator {
    /// Default sample size: see the module documentation.
    pub const DEFAULT_SAMPLE_SIZE: usize = 5;

    pub fn new(intrinsics: PinholeIntrinsics, sample_size: usize) -> Result<Self, PoseError> {
        intrinsics.validate()?;
        if !(epnp::EPNP_MIN_POINTS..=6).contains(&sample_size) {
            return Err(PoseError::InvalidConfig {
                field: "epnp_sample_size",
                why: "must be 4, 5 or 6",
            });
        }
        Ok(Self {
            intrinsics,
            sample_size,
        })
    }

    pub fn intrinsics(&self) -> &PinholeIntrinsics {
        &self.intrinsics
    }
}

impl Estimator for EpnpEstimator {
    type Model = CameraPose;

    fn sample_size(&self) -> usize {
        self.sample_size
    }

    fn fit(
        &self,
        image_points_px: &[Vector2<f64>],
        world_points: &[Vector3<f64>],
    ) -> Result<CameraPose, PoseError> {
        Ok(CameraPose {
            intrinsics: self.intrinsics,
            cam_from_world: epnp::solve(&self.intrinsics, image_points_px, world_points)?,
        })
    }

    fn projection_matrix(&self, model: &CameraPose) -> Matrix3x4<f64> {
        model.projection_matrix()
    }
}

/// Unknown focal length (principal point, aspect ratio known, no skew): EPnP with unknown focal
/// length on 6 points ([`epnpf`]).
#[derive(Clone, Copy, Debug)]
pub struct EpnpFocalEstimator {
    prior: epnpf::FocalPrior,
}

impl EpnpFocalEstimator {
    pub fn new(prior: epnpf::FocalPrior) -> Result<Self, PoseError> {
        prior.validate()?;
        Ok(Self { prior })
    }
}

impl Estimator for EpnpFocalEstimator {
    type Model = CameraPose;

    fn sample_size(&self) -> usize {
        epnpf::EPNPF_MIN_POINTS
    }

    fn fit(
        &self,
        image_points_px: &[Vector2<f64>],
        world_points: &[Vector3<f64>],
    ) -> Result<CameraPose, PoseError> {
        epnpf::solve(&self.prior, image_points_px, world_points)
    }

    fn projection_matrix(&self, model: &CameraPose) -> Matrix3x4<f64> {
        model.projection_matrix()
    }
}

/// Known intrinsics: P3P (Grunert) on 3 points with a 4th choosing among its solutions; refits
/// on more points (local optimisation) use EPnP, since P3P uses only three.
#[derive(Clone, Copy, Debug)]
pub struct P3pEstimator {
    intrinsics: PinholeIntrinsics,
}

impl P3pEstimator {
    pub fn new(intrinsics: PinholeIntrinsics) -> Result<Self, PoseError> {
        intrinsics.validate()?;
        Ok(Self { intrinsics })
    }
}

impl Estimator for P3pEstimator {
    type Model = CameraPose;

    fn sample_size(&self) -> usize {
        4
    }

    fn fit(
        &self,
        image_points_px: &[Vector2<f64>],
        world_points: &[Vector3<f64>],
    ) -> Result<CameraPose, PoseError> {
        let cam_from_world = if image_points_px.len() <= 4 {
            p3p::solve_with_check(&self.intrinsics, image_points_px, world_points)?
        } else {
            epnp::solve(&self.intrinsics, image_points_px, world_points)?
        };
        Ok(CameraPose {
            intrinsics: self.intrinsics,
            cam_from_world,
        })
    }

    fn projection_matrix(&self, model: &CameraPose) -> Matrix3x4<f64> {
        model.projection_matrix()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::pose::test_scenes::{
        corrupt, random_scene, rotation_error_deg, test_intrinsics, Scene,
    };
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use std::time::Instant;

    /// 50 % outliers (the first half), 0.5 px noise on the rest.
    fn contaminated_scene(seed: u64, count: usize) -> Scene {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut scene = random_scene(&mut rng, test_intrinsics(), count, 15.0);
        corrupt(&mut scene, &mut rng, 0.5, count / 2);
        scene
    }

    fn check_recovery(scene: &Scene, output: &RansacOutput<CameraPose>, label: &str) {
        let truth = &scene.camera.cam_from_world;
        let rotation_error = rotation_error_deg(&output.model.cam_from_world, truth);
        let centre_error_m =
            (output.model.cam_from_world.camera_center() - truth.camera_center()).norm();
        let scene_size_m = 40.0;
        assert!(
            rotation_error < 0.5,
            "{label}: rotation error {rotation_error} deg"
        );
        assert!(
            centre_error_m < 0.01 * scene_size_m,
            "{label}: centre error {centre_error_m} m"
        );
        // The true inliers are the second half; a few outliers may land within the threshold.
        let half = scene.world_points.len() / 2;
        let true_inliers_found = output.inlier_mask[half..].iter().filter(|&&m| m).count();
        let outliers_accepted = output.inlier_mask[..half].iter().filter(|&&m| m).count();
        assert!(
            true_inliers_found as f64 >= 0.98 * half as f64,
            "{label}: {true_inliers_found}/{half}"
        );
        assert!(
            outliers_accepted as f64 <= 0.02 * half as f64,
            "{label}: {outliers_accepted} outliers"
        );
        assert_eq!(
            output.inlier_count,
            output.inlier_mask.iter().filter(|&&m| m).count()
        );
        assert!(
            output.inlier_rms_px < 1.0,
            "{label}: {}",
            output.inlier_rms_px
        );
    }

    #[test]
    fn dlt_ransac_recovers_the_camera_despite_noise_and_half_outliers() {
        for seed in 0..3 {
            let scene = contaminated_scene(50 + seed, 400);
            let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let output =
                ransac_camera(&DltEstimator, &data, &RansacConfig::default(), &mut rng).unwrap();
            check_recovery(&scene, &output, &format!("DLT seed {seed}"));
            let focal_error = (output.model.intrinsics.fx_px - scene.camera.intrinsics.fx_px).abs();
            assert!(
                focal_error < 0.05 * scene.camera.intrinsics.fx_px,
                "focal off by {focal_error}"
            );
        }
    }

    #[test]
    fn epnp_ransac_recovers_the_pose_despite_noise_and_half_outliers() {
        for sample_size in 4..=6 {
            for seed in 0..3 {
                let scene = contaminated_scene(60 + seed, 400);
                let data =
                    Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
                let estimator = EpnpEstimator::new(scene.camera.intrinsics, sample_size).unwrap();
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                let output =
                    ransac_camera(&estimator, &data, &RansacConfig::default(), &mut rng).unwrap();
                check_recovery(&scene, &output, &format!("EPnP-{sample_size} seed {seed}"));
            }
        }
    }

    #[test]
    fn p3p_ransac_recovers_the_pose_despite_noise_and_half_outliers() {
        for seed in 0..3 {
            let scene = contaminated_scene(65 + seed, 400);
            let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
            let estimator = P3pEstimator::new(scene.camera.intrinsics).unwrap();
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let output =
                ransac_camera(&estimator, &data, &RansacConfig::default(), &mut rng).unwrap();
            check_recovery(&scene, &output, &format!("P3P seed {seed}"));
        }
    }

    #[test]
    fn the_same_seed_gives_the_same_result_and_the_stop_rule_applies() {
        let scene = contaminated_scene(70, 300);
        let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
        let run = |seed: u64, config: &RansacConfig| {
            ransac_camera(
                &DltEstimator,
                &data,
                config,
                &mut ChaCha8Rng::seed_from_u64(seed),
            )
            .unwrap()
        };
        let config = RansacConfig::default();
        assert_eq!(run(1, &config), run(1, &config));
        // Half the correspondences are outliers: 65 % is out of reach, all 500 iterations run.
        let full = run(1, &config);
        assert_eq!(full.iterations, 500);
        assert!(!full.reached_stop_ratio);
        // At 40 % the first clean sample (plus LO) reaches it and the loop stops early.
        let early = run(
            1,
            &RansacConfig {
                stop_inlier_ratio: 0.4,
                ..config
            },
        );
        assert!(early.reached_stop_ratio);
        assert!(early.iterations < 500);
        assert!(early.inlier_count >= 120);
        let at_least = run(
            1,
            &RansacConfig {
                stop_inlier_ratio: 0.4,
                min_iterations: 300,
                ..config
            },
        );
        assert!(at_least.iterations == 300 && at_least.reached_stop_ratio);
    }

    #[test]
    fn local_optimisation_does_not_lose_inliers() {
        let scene = contaminated_scene(80, 400);
        let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
        let estimator = EpnpEstimator::new(scene.camera.intrinsics, 5).unwrap();
        let plain = RansacConfig {
            local_optimization_rounds: 0,
            max_iterations: 200,
            stop_inlier_ratio: 1.0,
            ..RansacConfig::default()
        };
        let with_lo = RansacConfig {
            local_optimization_rounds: 2,
            ..plain
        };
        let plain_output =
            ransac_camera(&estimator, &data, &plain, &mut ChaCha8Rng::seed_from_u64(3)).unwrap();
        let lo_output = ransac_camera(
            &estimator,
            &data,
            &with_lo,
            &mut ChaCha8Rng::seed_from_u64(3),
        )
        .unwrap();
        println!(
            "inliers: plain {} / LO {}",
            plain_output.inlier_count, lo_output.inlier_count
        );
        assert!(lo_output.inlier_count >= plain_output.inlier_count);
    }

    #[test]
    fn bad_configs_and_too_few_points_are_rejected() {
        let scene = contaminated_scene(90, 20);
        let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        for config in [
            RansacConfig {
                threshold_px: 0.0,
                ..RansacConfig::default()
            },
            RansacConfig {
                threshold_px: f64::NAN,
                ..RansacConfig::default()
            },
            RansacConfig {
                max_iterations: 0,
                ..RansacConfig::default()
            },
            RansacConfig {
                stop_inlier_ratio: 1.5,
                ..RansacConfig::default()
            },
            RansacConfig {
                min_iterations: 501,
                ..RansacConfig::default()
            },
        ] {
            assert!(
                matches!(
                    ransac_camera(&DltEstimator, &data, &config, &mut rng),
                    Err(PoseError::InvalidConfig { .. })
                ),
                "{config:?}"
            );
        }
        let few =
            Correspondences::new(&scene.image_points_px[..5], &scene.world_points[..5]).unwrap();
        assert!(matches!(
            ransac_camera(&DltEstimator, &few, &RansacConfig::default(), &mut rng),
            Err(PoseError::TooFewPoints { needed: 6, .. })
        ));
        assert!(EpnpEstimator::new(test_intrinsics(), 3).is_err());
        assert!(EpnpEstimator::new(test_intrinsics(), 7).is_err());
        assert!(serde_json::from_str::<RansacConfig>(r#"{"threshold": 2}"#).is_err());
        let parsed: RansacConfig = serde_json::from_str(r#"{"threshold_px": 2.5}"#).unwrap();
        assert_eq!(
            parsed,
            RansacConfig {
                threshold_px: 2.5,
                ..RansacConfig::default()
            }
        );
    }

    #[test]
    fn all_degenerate_samples_give_no_model() {
        // Every world point on one line: no sample can be solved.
        let camera = random_scene(
            &mut ChaCha8Rng::seed_from_u64(4),
            test_intrinsics(),
            6,
            10.0,
        )
        .camera;
        let world_points: Vec<Vector3<f64>> = (0..30)
            .map(|i| Vector3::new(0.5, -0.3, 0.1) * i as f64)
            .collect();
        let image_points_px: Vec<Vector2<f64>> = world_points
            .iter()
            .map(|p| camera.project(p).unwrap())
            .collect();
        let data = Correspondences::new(&image_points_px, &world_points).unwrap();
        let config = RansacConfig {
            max_iterations: 50,
            ..RansacConfig::default()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        assert_eq!(
            ransac_camera(&DltEstimator, &data, &config, &mut rng),
            Err(PoseError::NoModel {
                iterations: 50,
                degenerate_samples: 50
            })
        );
        let estimator = EpnpEstimator::new(camera.intrinsics, 5).unwrap();
        assert!(matches!(
            ransac_camera(&estimator, &data, &config, &mut rng),
            Err(PoseError::NoModel { .. })
        ));
    }

    #[test]
    fn a_sampler_returning_bad_indices_costs_iterations_not_a_panic() {
        struct OutOfRange;
        impl Sampler for OutOfRange {
            fn sample<R: Rng + ?Sized>(
                &mut self,
                population: usize,
                sample_size: usize,
                _: &mut R,
                indices: &mut Vec<usize>,
            ) {
                indices.clear();
                indices.extend((0..sample_size).map(|i| population + i));
            }
        }
        let scene = contaminated_scene(95, 50);
        let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
        let config = RansacConfig {
            max_iterations: 10,
            ..RansacConfig::default()
        };
        let consensus = ReprojectionConsensus { threshold_px: 4.0 };
        assert_eq!(
            run_ransac(
                &DltEstimator,
                &mut OutOfRange,
                &consensus,
                &data,
                &config,
                &mut ChaCha8Rng::seed_from_u64(0)
            ),
            Err(PoseError::NoModel {
                iterations: 10,
                degenerate_samples: 10
            })
        );
    }

    #[test]
    fn sampler_draws_distinct_indices() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let mut indices = Vec::new();
        for _ in 0..1000 {
            UniformSampler.sample(7, 6, &mut rng, &mut indices);
            let mut sorted = indices.clone();
            sorted.sort_unstable();
            sorted.dedup();
            assert_eq!(sorted.len(), 6);
            assert!(sorted.iter().all(|&i| i < 7));
        }
    }

    /// Prints (does not assert) the time of 500 iterations per estimator on 2,000 correspondences.
    #[test]
    fn timing_of_500_iterations_on_2000_correspondences() {
        let scene = contaminated_scene(99, 2000);
        let data = Correspondences::new(&scene.image_points_px, &scene.world_points).unwrap();
        // Out of reach at 50 % outliers, so every run draws all 500 samples.
        let config = RansacConfig {
            stop_inlier_ratio: 1.0,
            ..RansacConfig::default()
        };
        let epnp5 = EpnpEstimator::new(scene.camera.intrinsics, 5).unwrap();
        let epnp6 = EpnpEstimator::new(scene.camera.intrinsics, 6).unwrap();
        type TimedRun<'a> = (
            &'a str,
            &'a dyn Fn(&mut ChaCha8Rng) -> RansacOutput<CameraPose>,
        );
        let p3p = P3pEstimator::new(scene.camera.intrinsics).unwrap();
        let runs: [TimedRun; 4] = [
            ("DLT-6", &|rng| {
                ransac_camera(&DltEstimator, &data, &config, rng).unwrap()
            }),
            ("EPnP-5", &|rng| {
                ransac_camera(&epnp5, &data, &config, rng).unwrap()
            }),
            ("P3P+1", &|rng| {
                ransac_camera(&p3p, &data, &config, rng).unwrap()
            }),
            ("EPnP-6", &|rng| {
                ransac_camera(&epnp6, &data, &config, rng).unwrap()
            }),
        ];
        for (label, run) in runs {
            let start = Instant::now();
            let output = run(&mut ChaCha8Rng::seed_from_u64(1));
            let elapsed = start.elapsed();
            assert_eq!(output.iterations, 500);
            check_recovery(&scene, &output, label);
            println!(
                "RANSAC {label}: 500 iterations on 2000 correspondences in {:.1} ms ({} inliers, {:.3} px RMS)",
                elapsed.as_secs_f64() * 1e3,
                output.inlier_count,
                output.inlier_rms_px
            );
        }
    }
}
