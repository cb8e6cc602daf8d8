//! Benchmark of the final refinement's consensus step (`core::edge_consensus::consensus_step`):
//! RANSAC over every photo ridge near each model edge sample, 20 000 draws by default, once per
//! refined frame (about 7 % of a block frame's CPU in a profile of `asgreg eval`, thirty-sixth
//! session). The constraints are made, not rendered: `CONSTRAINTS` rows shaped like a pinhole
//! camera's pose Jacobian rows (a sample 20–40 m in front of a 360 px focal camera, image normal
//! in any direction), a known step, and on each line the ridge the step predicts (within 0.3 px,
//! for 60 % of the samples) among one to three decoy ridges within ±10 px, as a cluttered photo
//! gives them.
//!
//! `cargo bench --bench consensus` runs criterion and then prints, from its own loop, the median
//! and minimum CPU ms per step (process CPU, one thread: the figure least disturbed by other load on
//! a shared machine), the step's inliers and its distance from the
//! known step; `cargo bench --bench consensus -- no_such_bench` prints only that summary.

use std::hint::black_box;
use std::time::Instant;

use asgreg::core::camera::PinholeIntrinsics;
use asgreg::core::edge_align::pose_jacobian_rows;
use asgreg::core::edge_consensus::{consensus_step, EdgeConsensusConfig, RidgeConstraints};
use asgreg::core::frame::process_cpu_ms;
use criterion::Criterion;
use nalgebra::{Vector2, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Constraints in the set: about a frame's edge samples with a ridge on their line.
const CONSTRAINTS: usize = 400;
/// Share of constraints with the true ridge on their line.
const INLIER_SHARE: f64 = 0.6;
const FOCAL_PX: f64 = 360.0;

/// `jᵀ` of a point at `point_cam` seen along image normal `normal`, as the refinement makes it.
fn jacobian_row(point_cam: Vector3<f64>, normal: Vector2<f64>) -> Vector6<f64> {
    let intrinsics = PinholeIntrinsics {
        fx_px: FOCAL_PX,
        fy_px: FOCAL_PX,
        cx_px: 252.5,
        cy_px: 137.5,
        skew_px: 0.0,
    };
    let (row_u, row_v) = pose_jacobian_rows(&intrinsics, &point_cam);
    row_u * normal.x + row_v * normal.y
}

/// The constraint set and the step it was made from (about 4 px of image motion).
fn constraints() -> (RidgeConstraints, Vector6<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(36);
    let truth = Vector6::new(0.004, -0.006, 0.003, 0.3, -0.2, 0.4);
    let mut set = RidgeConstraints::default();
    for _ in 0..CONSTRAINTS {
        let point_cam = Vector3::new(
            rng.random_range(-15.0..15.0),
            rng.random_range(-8.0..8.0),
            rng.random_range(20.0..40.0),
        );
        let angle: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        let jacobian = jacobian_row(point_cam, Vector2::new(angle.cos(), angle.sin()));
        let mut offsets_px: Vec<f64> = (0..rng.random_range(1..=3))
            .map(|_| rng.random_range(-10.0..10.0))
            .collect();
        if rng.random_bool(INLIER_SHARE) {
            let predicted = jacobian.dot(&truth) + rng.random_range(-0.3..0.3);
            if predicted.abs() <= 10.0 {
                offsets_px.push(predicted);
            }
        }
        offsets_px.sort_by(f64::total_cmp);
        set.push(jacobian, &offsets_px);
    }
    (set, truth)
}

fn step(set: &RidgeConstraints, config: &EdgeConsensusConfig) -> Option<Vector6<f64>> {
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    consensus_step(set, config, &mut rng).map(|found| found.step)
}

fn summary(set: &RidgeConstraints, truth: &Vector6<f64>, config: &EdgeConsensusConfig) {
    let repeats = 20;
    let mut times_ms: Vec<f64> = (0..repeats)
        .map(|_| {
            let started = process_cpu_ms();
            black_box(step(black_box(set), config));
            process_cpu_ms() - started
        })
        .collect();
    times_ms.sort_by(f64::total_cmp);
    let wall = Instant::now();
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let found = consensus_step(set, config, &mut rng);
    let wall_ms = wall.elapsed().as_secs_f64() * 1e3;
    let (inliers, error) = found.map_or((0, f64::NAN), |found| {
        (found.inliers, (found.step - truth).norm())
    });
    println!(
        "consensus step, {} constraints, {} draws: CPU ms per step median {:.2}, min {:.2} ({} runs); one run {:.1} ms wall; {} inliers, |step − truth| {:.2e}",
        set.len(),
        config.draws,
        times_ms[repeats / 2],
        times_ms[0],
        repeats,
        wall_ms,
        inliers,
        error
    );
}

fn main() {
    let (set, truth) = constraints();
    let config = EdgeConsensusConfig::default();
    let mut criterion = Criterion::default().configure_from_args();
    criterion.bench_function("consensus_step", |b| {
        b.iter(|| step(black_box(&set), &config))
    });
    criterion.final_summary();
    summary(&set, &truth, &config);
}
