//! A pose step chosen by consensus over every photo ridge near each model edge (issue #11 item 3,
//! the final refinement; not in the paper). The moving-edges alignment ([`super::edge_align`])
//! matches each model edge sample to one ridge on its search line and lets a robust Gauss–Newton
//! average the matches; where the photo shows several ridges near most edges (clutter, texture, a
//! model simpler than the world), the matches it starts with decide the basin, and the alignment
//! can settle a few pixels off along directions the edges see well: a wrong association, not a
//! weak constraint (house s5 at 30 px: accepted frames 4–6 px off, docs/measurements.md,
//! thirty-third session). Here every ridge near a sample is a hypothesis, and the step most
//! samples agree on wins: the multiple-hypothesis moving edges of L. Vacchetti, V. Lepetit,
//! P. Fua ("Combining edge and texture information for real-time accurate 3D camera tracking",
//! ISMAR 2004) decided globally by RANSAC (M. Fischler, R. Bolles, CACM 24(6), 1981) instead of
//! sample by sample.
//!
//! Method: at the pose `P` each model edge sample `X` with 2D normal `n` gives a constraint
//! `jᵀξ = o`, `j = Jᵀn` ([`pose_jacobian_rows`]) for every ridge offset `o` found along `n`
//! within `radius_px` ([`ridge_offsets`]): moving the pose by the left step `ξ` moves the sample's
//! projection along its normal by `jᵀξ` to first order. RANSAC as estimator / sampler / consensus:
//! the sampler draws 6 constraints and one offset of each (the RNG is the caller's), the estimator
//! solves the 6×6 system exactly, the consensus is MSAC's truncated quadratic (each constraint
//! charged its squared distance to its nearest offset, at most `inlier_px`²); the best step is
//! refitted by least squares on its inliers (each one's nearest offset) while the cost falls. Preconditions: a pinhole camera; the linearisation holds
//! for steps of a few pixels (the radius bounds them); the caller re-renders at the stepped pose
//! and aligns from there (visibility and contours move with the pose).

use nalgebra::{Matrix6, Vector2, Vector6};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use super::camera::Camera;
use super::edge_align::{
    for_each_lattice_peak, pose_jacobian_rows, EdgeSample, RIDGE_LATTICE_STEP_PX,
};
use super::image::ImageView;
use super::pose::ransac::{Sampler, UniformSampler};
use super::rigid::Rigid3;

/// Settings of the consensus step of the final refinement.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EdgeConsensusConfig {
    /// Run the step at all (after the alignment's ends are decided, from the output).
    pub enabled: bool,
    /// Half-length of the line along each sample's normal searched for ridges, px.
    pub radius_px: f64,
    /// Random samples drawn (6 constraints with ~3 offsets each: one draw in 3⁶ = 729 picks the
    /// right offset of all six when all six constraints are right).
    pub draws: usize,
    /// A constraint agrees with a step when one of its offsets lies within this of the motion the
    /// step predicts, px.
    pub inlier_px: f64,
    /// Fewer constraints (samples with a ridge on their line) than this: no step.
    pub min_constraints: usize,
    /// Least-squares refits of the best step on its inliers.
    pub refits: usize,
    /// The alignment from the stepped pose runs its levels from this search radius down, px (the
    /// final level's radius: the step already chose the basin).
    pub then_search_radius_px: f64,
    /// Seed of the RNG the refinement hands the sampler (the same frame gives the same step in
    /// every process).
    pub seed: u64,
}

impl Default for EdgeConsensusConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            radius_px: 10.0,
            draws: 20_000,
            inlier_px: 1.0,
            min_constraints: 12,
            refits: 3,
            then_search_radius_px: 2.0,
            seed: 7,
        }
    }
}

impl EdgeConsensusConfig {
    /// The first unusable setting: its field and why.
    pub fn invalid(&self) -> Option<(&'static str, String)> {
        for (field, value) in [
            ("consensus.radius_px", self.radius_px),
            ("consensus.inlier_px", self.inlier_px),
            (
                "consensus.then_search_radius_px",
                self.then_search_radius_px,
            ),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Some((field, format!("{value} is not a positive number")));
            }
        }
        if self.min_constraints < 6 {
            return Some((
                "consensus.min_constraints",
                "must be at least 6 (six unknowns)".into(),
            ));
        }
        None
    }
}

/// The model edge samples' constraints on the pose step: for sample `i`, `jacobian(i) · ξ` is
/// the motion of its projection along its normal, px, and `offsets_px(i)` where the photo has a
/// ridge along that normal (at least one). Laid out flat — the Jacobian rows side by side and
/// every offset in one array, `ends[i]` closing sample `i`'s — because every RANSAC draw reads
/// them all ([`consensus_step`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RidgeConstraints {
    jacobians: Vec<Vector6<f64>>,
    offsets_px: Vec<f64>,
    ends: Vec<usize>,
}

impl RidgeConstraints {
    pub fn clear(&mut self) {
        self.jacobians.clear();
        self.offsets_px.clear();
        self.ends.clear();
    }

    /// Adds a sample's constraint; a sample without a ridge on its line constrains nothing
    /// and is not added.
    pub fn push(&mut self, jacobian: Vector6<f64>, offsets_px: &[f64]) {
        if offsets_px.is_empty() {
            return;
        }
        self.jacobians.push(jacobian);
        self.offsets_px.extend_from_slice(offsets_px);
        self.ends.push(self.offsets_px.len());
    }

    pub fn len(&self) -> usize {
        self.jacobians.len()
    }

    pub fn is_empty(&self) -> bool {
        self.jacobians.is_empty()
    }

    /// Sample `index`'s Jacobian row and ridge offsets.
    pub fn get(&self, index: usize) -> (&Vector6<f64>, &[f64]) {
        let first = index.checked_sub(1).map_or(0, |before| self.ends[before]);
        (
            &self.jacobians[index],
            &self.offsets_px[first..self.ends[index]],
        )
    }

    /// Every sample's Jacobian row and ridge offsets, in order.
    pub fn iter(&self) -> impl Iterator<Item = (&Vector6<f64>, &[f64])> {
        let starts = std::iter::once(0).chain(self.ends.iter().copied());
        self.jacobians
            .iter()
            .zip(starts.zip(&self.ends))
            .map(|(jacobian, (first, &end))| (jacobian, &self.offsets_px[first..end]))
    }

    /// MSAC's truncated quadratic (P. Torr, A. Zisserman, "MLESAC: a new robust estimator with
    /// application to estimating image geometry", CVIU 78(1), 2000): each constraint costs its
    /// squared distance from `step`'s motion to its nearest offset, at most `inlier_px`² (the
    /// cost of an outlier), so that among steps most constraints agree with the tighter fit wins
    /// and a refit on the inliers is judged by how well it fits, not by a count at the band's
    /// edge. The cost and the count of constraints within the band; `None` as soon as the cost
    /// reaches `below` (every term is ≥ 0, so the sum cannot fall back under it: a draw that
    /// cannot win stops early, one that can is summed as in full).
    fn cost_below(&self, step: &Vector6<f64>, inlier_px: f64, below: f64) -> Option<(f64, usize)> {
        let (mut total, mut inliers) = (0.0, 0);
        for (jacobian, offsets_px) in self.iter() {
            let (_, nearest_px) = nearest_offset(jacobian, offsets_px, step);
            let charged_px = nearest_px.min(inlier_px);
            total += charged_px * charged_px;
            inliers += usize::from(nearest_px <= inlier_px);
            if total >= below {
                return None;
            }
        }
        Some((total, inliers))
    }

    /// [`Self::cost_below`] in full.
    fn cost(&self, step: &Vector6<f64>, inlier_px: f64) -> (f64, usize) {
        self.cost_below(step, inlier_px, f64::INFINITY)
            .unwrap_or((f64::INFINITY, 0))
    }
}

/// The offset of `offsets_px` nearest the motion `jacobian · step` predicts (the first of equals)
/// and its distance from it, px; distance ∞ without offsets.
#[inline(always)]
fn nearest_offset(jacobian: &Vector6<f64>, offsets_px: &[f64], step: &Vector6<f64>) -> (f64, f64) {
    let predicted = jacobian.dot(step);
    offsets_px
        .iter()
        .fold((f64::NAN, f64::INFINITY), |nearest, &offset| {
            let distance_px = (offset - predicted).abs();
            if distance_px < nearest.1 {
                (offset, distance_px)
            } else {
                nearest
            }
        })
}

/// Every ridge of `query` on the line through `at_px` along `normal` within `radius_px`: the
/// lattice peaks at least `min_ridge` strong ([`for_each_lattice_peak`], the alignment's scan),
/// each refined by the parabola through its lattice neighbours, as offsets along `normal`, px.
pub fn ridge_offsets(
    query: &ImageView<'_, f32>,
    at_px: Vector2<f64>,
    normal: Vector2<f64>,
    radius_px: f64,
    min_ridge: f32,
    out: &mut Vec<f64>,
) {
    out.clear();
    for_each_lattice_peak(
        query,
        at_px,
        normal,
        radius_px,
        min_ridge,
        |t_px, before, centre, after| {
            // Sub-lattice by the parabola through the three values (its vertex within ±½ step).
            let curvature = f64::from(before) - 2.0 * f64::from(centre) + f64::from(after);
            let vertex = if curvature < 0.0 {
                (0.5 * f64::from(before - after) / curvature).clamp(-0.5, 0.5)
            } else {
                0.0
            };
            let offset_px = t_px + vertex * RIDGE_LATTICE_STEP_PX;
            if offset_px.abs() <= radius_px {
                out.push(offset_px);
            }
        },
    );
}

/// The constraints of `samples` at `cam_from_world`: one per sample in front of the camera with
/// at least one ridge on its line ([`ridge_offsets`]). Written into `out` (cleared first).
pub fn ridge_constraints(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    radius_px: f64,
    min_ridge: f32,
    out: &mut RidgeConstraints,
) {
    out.clear();
    let mut offsets = Vec::new();
    for sample in samples {
        let point_cam = cam_from_world.transform_point(&sample.world_m);
        let Some(projected_px) = camera.project(&point_cam) else {
            continue;
        };
        ridge_offsets(
            query,
            projected_px,
            sample.normal,
            radius_px,
            min_ridge,
            &mut offsets,
        );
        if offsets.is_empty() {
            continue;
        }
        let (row_u, row_v) = pose_jacobian_rows(&camera.intrinsics, &point_cam);
        out.push(row_u * sample.normal.x + row_v * sample.normal.y, &offsets);
    }
}

/// The step the consensus chose and how many constraints agree with it (within `inlier_px`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConsensusStep {
    /// The left pose step (`apply_pose_step`'s ξ = (ω, δt)).
    pub step: Vector6<f64>,
    pub inliers: usize,
    /// How many constraints agreed with no step at all.
    pub inliers_at_rest: usize,
}

/// The sampler: 6 distinct constraints (the pose RANSAC's [`UniformSampler`]), one offset of
/// each (uniform), as a 6×6 system.
fn draw_system<R: Rng + ?Sized>(
    constraints: &RidgeConstraints,
    rng: &mut R,
    indices: &mut Vec<usize>,
) -> (Matrix6<f64>, Vector6<f64>) {
    UniformSampler.sample(constraints.len(), 6, rng, indices);
    let mut a = Matrix6::zeros();
    let mut b = Vector6::zeros();
    for (row, &index) in indices.iter().enumerate() {
        let (jacobian, offsets_px) = constraints.get(index);
        a.set_row(row, &jacobian.transpose());
        b[row] = offsets_px[rng.random_range(0..offsets_px.len())];
    }
    (a, b)
}

/// The estimator: the step solving a drawn system exactly, `None` when it is degenerate.
fn solve_system(a: Matrix6<f64>, b: &Vector6<f64>) -> Option<Vector6<f64>> {
    a.lu()
        .solve(b)
        .filter(|step| step.iter().all(|value| value.is_finite()))
}

/// The step most constraints agree with (RANSAC over `config.draws` samples with `rng`, the
/// lowest [`RidgeConstraints::cost_below`], then refitted by least squares on its inliers while
/// that lowers the cost);
/// `None` with fewer than `config.min_constraints` constraints, or when no step costs less than
/// staying where the pose is.
pub fn consensus_step<R: Rng + ?Sized>(
    constraints: &RidgeConstraints,
    config: &EdgeConsensusConfig,
    rng: &mut R,
) -> Option<ConsensusStep> {
    if constraints.len() < config.min_constraints.max(6) {
        return None;
    }
    let at_rest = constraints.cost(&Vector6::zeros(), config.inlier_px);
    let mut best = (Vector6::zeros(), at_rest);
    let mut indices = Vec::with_capacity(6);
    for _ in 0..config.draws {
        let (a, b) = draw_system(constraints, rng, &mut indices);
        let Some(step) = solve_system(a, &b) else {
            continue;
        };
        if let Some(scored) = constraints.cost_below(&step, config.inlier_px, best.1 .0) {
            best = (step, scored);
        }
    }
    if best.1 .0 >= at_rest.0 {
        return None;
    }
    // Least squares on the inliers, each with its offset nearest the prediction.
    for _ in 0..config.refits {
        let mut normal = Matrix6::zeros();
        let mut rhs = Vector6::zeros();
        for (jacobian, offsets_px) in constraints.iter() {
            let (offset, distance_px) = nearest_offset(jacobian, offsets_px, &best.0);
            if distance_px <= config.inlier_px {
                normal += jacobian * jacobian.transpose();
                rhs += jacobian * offset;
            }
        }
        let Some(step) = solve_system(normal, &rhs) else {
            break;
        };
        let scored = constraints.cost(&step, config.inlier_px);
        if scored.0 >= best.1 .0 {
            break;
        }
        best = (step, scored);
    }
    Some(ConsensusStep {
        step: best.0,
        inliers: best.1 .1,
        inliers_at_rest: at_rest.1,
    })
}

/// The consensus step of `samples` at `cam_from_world`: their constraints
/// ([`ridge_constraints`], written into `constraints`) and the step ([`consensus_step`]) with
/// an RNG seeded from `settings.seed`, so every process and the diagnosis take the same step.
pub fn consensus_step_at(
    samples: &[EdgeSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    settings: &EdgeConsensusConfig,
    min_ridge: f32,
    constraints: &mut RidgeConstraints,
) -> Option<ConsensusStep> {
    ridge_constraints(
        samples,
        query,
        camera,
        cam_from_world,
        settings.radius_px,
        min_ridge,
        constraints,
    );
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(settings.seed);
    consensus_step(constraints, settings, &mut rng)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::camera::PinholeIntrinsics;
    use crate::core::edge_align::{apply_pose_step, EdgeKind};
    use crate::core::image::Image;
    use nalgebra::Vector3;
    use rand::SeedableRng;

    fn camera() -> Camera {
        Camera::pinhole(
            320,
            240,
            PinholeIntrinsics {
                fx_px: 300.0,
                fy_px: 300.0,
                cx_px: 160.0,
                cy_px: 120.0,
                skew_px: 0.0,
            },
        )
    }

    /// Edge samples on the 12 edges of a box 3.5–5 m in front of the camera, each with its
    /// image normal at `pose`.
    fn box_samples(camera: &Camera, pose: &Rigid3) -> Vec<EdgeSample> {
        let corner = |i: usize| {
            Vector3::new(
                if i & 1 == 0 { -1.0 } else { 1.0 },
                if i & 2 == 0 { -0.7 } else { 0.7 },
                if i & 4 == 0 { 3.5 } else { 5.0 },
            )
        };
        let edges = [
            (0, 1),
            (2, 3),
            (4, 5),
            (6, 7),
            (0, 2),
            (1, 3),
            (4, 6),
            (5, 7),
            (0, 4),
            (1, 5),
            (2, 6),
            (3, 7),
        ];
        let project = |p: Vector3<f64>| camera.project(&pose.transform_point(&p)).unwrap();
        let mut samples = Vec::new();
        for (a, b) in edges {
            let along = project(corner(b)) - project(corner(a));
            let normal = Vector2::new(-along.y, along.x).normalize();
            for k in 1..20 {
                let t = f64::from(k) / 20.0;
                samples.push(EdgeSample {
                    world_m: corner(a) * (1.0 - t) + corner(b) * t,
                    normal,
                    kind: EdgeKind::Contour,
                    rounding: Vector3::zeros(),
                    outward: Vector3::zeros(),
                });
            }
        }
        samples
    }

    /// A query with a ridge along every edge of the box at `truth` (value 1) and a decoy ridge
    /// parallel to it, `decoy_px` away (value 0.9): each pixel's value from its distance to the
    /// nearest projected segment.
    fn query_with_decoys(
        camera: &Camera,
        truth: &Rigid3,
        samples: &[EdgeSample],
        decoy_px: f64,
    ) -> Image<f32> {
        // The segments: each run of 19 samples is one box edge; its ends extended half a step.
        let at = |sample: &EdgeSample| {
            camera
                .project(&truth.transform_point(&sample.world_m))
                .unwrap()
        };
        let segments: Vec<(Vector2<f64>, Vector2<f64>, Vector2<f64>)> = samples
            .chunks(19)
            .map(|edge| {
                let (first, last) = (at(&edge[0]), at(&edge[18]));
                let step = (last - first) / 18.0;
                (first - step, last + step, edge[0].normal)
            })
            .collect();
        let distance = |p: Vector2<f64>, a: Vector2<f64>, b: Vector2<f64>| {
            let t = ((p - a).dot(&(b - a)) / (b - a).norm_squared()).clamp(0.0, 1.0);
            (p - (a + (b - a) * t)).norm()
        };
        Image::from_fn(
            camera.width_px as usize,
            camera.height_px as usize,
            |col, row| {
                let p = Vector2::new(col as f64 + 0.5, row as f64 + 0.5);
                segments
                    .iter()
                    .map(|&(a, b, normal)| {
                        let shift = normal * decoy_px;
                        let edge = (-distance(p, a, b).powi(2) / 2.0).exp();
                        let decoy = 0.9 * (-distance(p, a + shift, b + shift).powi(2) / 2.0).exp();
                        edge.max(decoy)
                    })
                    .fold(0.0f64, f64::max) as f32
            },
        )
    }

    fn constraints_at(pose: &Rigid3) -> RidgeConstraints {
        let camera = camera();
        let truth = Rigid3::identity();
        let samples = box_samples(&camera, &truth);
        let query = query_with_decoys(&camera, &truth, &samples, 4.0);
        let mut constraints = RidgeConstraints::default();
        ridge_constraints(
            &samples,
            &query.view(),
            &camera,
            pose,
            10.0,
            0.05,
            &mut constraints,
        );
        constraints
    }

    #[test]
    fn a_known_offset_is_undone_where_every_edge_has_a_decoy_ridge() {
        // The pose to refine: the truth moved by a small turn and shift (a few px).
        let offset = Vector6::new(0.006, -0.009, 0.0045, 0.045, -0.03, 0.075);
        let start = apply_pose_step(&Rigid3::identity(), &offset);
        let constraints = constraints_at(&start);
        assert!(constraints.len() > 100, "{}", constraints.len());
        // Most see both ridges (a decoy may fall off the image or onto another edge's ridge).
        let with_decoy = constraints
            .iter()
            .filter(|(_, offsets_px)| offsets_px.len() >= 2)
            .count();
        assert!(with_decoy * 5 >= constraints.len() * 4, "{with_decoy}");
        let config = EdgeConsensusConfig::default();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let found = consensus_step(&constraints, &config, &mut rng).expect("a step");
        // Undone to within the linearisation and the 0.5 px lattice of the ridge offsets: the
        // samples' mean distance from where the truth projects them.
        let camera = camera();
        let samples = box_samples(&camera, &Rigid3::identity());
        let mean_px = |pose: &Rigid3| {
            samples
                .iter()
                .map(|sample| {
                    let at = |pose: &Rigid3| {
                        camera
                            .project(&pose.transform_point(&sample.world_m))
                            .unwrap()
                    };
                    (at(pose) - at(&Rigid3::identity())).norm()
                })
                .sum::<f64>()
                / samples.len() as f64
        };
        let recovered = apply_pose_step(&start, &found.step);
        println!("{:.2} px → {:.3} px", mean_px(&start), mean_px(&recovered));
        assert!(mean_px(&start) > 3.0, "{}", mean_px(&start));
        assert!(mean_px(&recovered) < 0.2, "{}", mean_px(&recovered));
        assert!(found.inliers > found.inliers_at_rest, "{found:?}");
        assert!(found.inliers * 10 >= constraints.len() * 9, "{found:?}");
    }

    /// The draws that stop early (their partial cost already at the best's) change no choice:
    /// the straightforward RANSAC — every draw's cost summed in full — takes the very same step,
    /// bit for bit, from the same RNG.
    #[test]
    fn the_early_stop_takes_the_step_full_costs_take() {
        let offset = Vector6::new(0.006, -0.009, 0.0045, 0.045, -0.03, 0.075);
        let constraints = constraints_at(&apply_pose_step(&Rigid3::identity(), &offset));
        let config = EdgeConsensusConfig {
            refits: 0,
            draws: 3000,
            ..EdgeConsensusConfig::default()
        };
        let full_cost = |step: &Vector6<f64>| {
            constraints
                .iter()
                .fold((0.0, 0), |(total, inliers), (jacobian, offsets_px)| {
                    let predicted = jacobian.dot(step);
                    let nearest_px = offsets_px
                        .iter()
                        .map(|offset| (offset - predicted).abs())
                        .fold(f64::INFINITY, f64::min);
                    let charged_px = nearest_px.min(config.inlier_px);
                    (
                        total + charged_px * charged_px,
                        inliers + usize::from(nearest_px <= config.inlier_px),
                    )
                })
        };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut best = (Vector6::zeros(), full_cost(&Vector6::zeros()));
        let mut indices = Vec::new();
        let mut improvements = 0;
        for _ in 0..config.draws {
            let (a, b) = draw_system(&constraints, &mut rng, &mut indices);
            if let Some(step) = solve_system(a, &b) {
                let scored = full_cost(&step);
                if scored.0 < best.1 .0 {
                    best = (step, scored);
                    improvements += 1;
                }
            }
        }
        assert!(improvements > 1, "{improvements}");
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let found = consensus_step(&constraints, &config, &mut rng).expect("a step");
        assert_eq!(found.step, best.0);
        assert_eq!(found.inliers, best.1 .1);
    }

    #[test]
    fn at_the_truth_the_step_stays_within_the_ridges_noise() {
        let constraints = constraints_at(&Rigid3::identity());
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        // Every constraint already agrees at rest, up to the ridges' sub-pixel noise (the
        // bilinear lookup of a narrow ridge): a step, if any, fits that noise, moving the samples
        // along their normals by less than a fifth of a pixel on average (0.13 px here).
        let found = consensus_step(&constraints, &EdgeConsensusConfig::default(), &mut rng);
        let moved_px = found.map_or(0.0, |found| {
            constraints
                .iter()
                .map(|(jacobian, _)| jacobian.dot(&found.step).abs())
                .sum::<f64>()
                / constraints.len() as f64
        });
        assert!(moved_px < 0.2, "{moved_px} {found:?}");
    }

    #[test]
    fn too_few_constraints_give_no_step() {
        let mut constraints = RidgeConstraints::default();
        for _ in 0..5 {
            constraints.push(Vector6::new(1.0, 0.0, 0.0, 0.0, 0.0, 0.0), &[1.0]);
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        assert_eq!(
            consensus_step(&constraints, &EdgeConsensusConfig::default(), &mut rng),
            None
        );
    }

    #[test]
    fn ridges_are_found_on_both_sides_of_the_sample() {
        let mut query = Image::filled(40, 10, 0.0f32);
        for row in 0..10 {
            *query.get_mut(10, row).unwrap() = 0.5;
            *query.get_mut(25, row).unwrap() = 0.8;
        }
        let mut offsets = Vec::new();
        // From x = 20.5 along +x: ridges at 10.5 (−10) and 25.5 (+5).
        ridge_offsets(
            &query.view(),
            Vector2::new(20.5, 5.5),
            Vector2::new(1.0, 0.0),
            10.0,
            0.05,
            &mut offsets,
        );
        assert_eq!(offsets, vec![-10.0, 5.0]);
    }
}
