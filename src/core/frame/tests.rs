//! The whole frame on an ideal query, and its input checks.

use nalgebra::UnitQuaternion;

use super::*;
use crate::core::camera::PinholeIntrinsics;
use crate::core::reprojection::mutual_reprojection_error_px;
use crate::core::reprojection::ReprojectionWorkspace;
use crate::synth::geometry::build_house;

/// The synthetic house as a mesh (seed 3), shared by the tests of whole frames.
pub(crate) fn house_mesh() -> Mesh {
    let scene = build_house(&mut ChaCha8Rng::seed_from_u64(3));
    let positions: Vec<Vector3<f64>> = scene
        .positions_m
        .iter()
        .map(|p| Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z)))
        .collect();
    Mesh::from_world(&positions, scene.faces.clone(), None).unwrap()
}

/// The whole chain on an ideal query (the model's own ASG under the true pose): from an initial
/// pose tens of pixels off, the accepted pose must be the true one to about a pixel. This
/// checks rendering, flow, lifting, RANSAC, refinement and verification together; photos make it
/// harder, which `asgreg eval` measures.
/// The house seen by a 505×275 camera: (mesh, camera, true pose, an initial pose about 20 px off).
pub(crate) fn house_and_poses() -> (Mesh, Camera, Rigid3, Rigid3) {
    let camera = Camera::pinhole(505, 275, PinholeIntrinsics::centered(360.0, 505, 275));
    let truth = Rigid3::look_at(
        &Vector3::new(18.0, -14.0, 9.0),
        &Vector3::new(0.0, 0.0, 3.0),
        &Vector3::z(),
    )
    .unwrap();
    let initial = Rigid3::new(
        UnitQuaternion::from_scaled_axis(Vector3::new(0.04, -0.05, 0.02)) * truth.rotation,
        truth.translation + Vector3::new(1.0, -0.6, 0.4),
    );
    (house_mesh(), camera, truth, initial)
}

/// The coarse view (ASG and render buffers) of the model at a pose, as the frame's steps render it.
pub(crate) fn view_at(
    mesh: &Mesh,
    camera: &Camera,
    pose: &Rigid3,
    config: &RegistrationConfig,
) -> CoarseView {
    let mut view = CoarseView::default();
    render_coarse_view(
        mesh,
        camera,
        0,
        pose,
        config,
        &mut Rasterizer::new(),
        &mut view,
    );
    view
}

/// A photo of the test house's size that shows none of the model's edges: smooth random
/// texture (uniform noise blurred with σ 1.5 px), whose ridges lie anywhere.
pub(crate) fn photo_without_the_model(camera: &Camera) -> Image<f32> {
    use rand::{Rng, SeedableRng};
    let (width_px, height_px) = (camera.width_px as usize, camera.height_px as usize);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(33);
    let noise = Image::new(
        width_px,
        height_px,
        (0..width_px * height_px)
            .map(|_| rng.random::<f32>())
            .collect(),
    )
    .unwrap();
    let mut photo = Image::default();
    crate::core::edge_align::blurred_query(noise.view(), 6.0, &mut photo);
    photo
}

/// The ideal query of a pose: the model's own ASG rendered there.
pub(crate) fn ideal_query(
    mesh: &Mesh,
    camera: &Camera,
    pose: &Rigid3,
    config: &RegistrationConfig,
) -> Image<f32> {
    view_at(mesh, camera, pose, config).asg
}

#[test]
fn ideal_query_recovers_the_true_pose_from_tens_of_pixels_off() {
    let (mesh, camera, truth, initial) = house_and_poses();
    let config = RegistrationConfig::default();
    let mut workspace = ReprojectionWorkspace::new();
    let initial_delta =
        mutual_reprojection_error_px(&mesh, &camera, &initial, &camera, &truth, &mut workspace)
            .unwrap();
    let query = ideal_query(&mesh, &camera, &truth, &config);
    let result = register_query(
        &mesh,
        &camera,
        IntrinsicsMode::Known,
        &initial,
        query.view(),
        &config,
        7,
    )
    .unwrap();
    let output = result.verdict.accepted_pose().expect("accepted");
    let final_delta = mutual_reprojection_error_px(
        &mesh,
        &output.camera,
        &output.cam_from_world,
        &camera,
        &truth,
        &mut workspace,
    )
    .unwrap();
    println!(
        "ideal query: δ {initial_delta:.1} px → {final_delta:.3} px, {} of {} poses agree",
        result.verdict.component.len(),
        result.verdict.hypothesis_count
    );
    assert!(
        initial_delta > 15.0,
        "the start must be far off: {initial_delta}"
    );
    // Issue #11's target for the ideal query is 0.5 px. Measured with seed 7: 0.89 px from
    // 22.6 px before the final edge alignment (the flow's sub-pixel error on thin ASG edges and
    // the coarse views' perspective differences), 0.077 px with it.
    assert!(final_delta < 0.5, "{final_delta}");
    // Same seed, same result.
    let again = register_query(
        &mesh,
        &camera,
        IntrinsicsMode::Known,
        &initial,
        query.view(),
        &config,
        7,
    )
    .unwrap();
    assert_eq!(again.verdict.decision, result.verdict.decision);
}

/// The full-circle heading fallback (issue #12 item 1): a prior whose heading is 100° off lies
/// outside the search's region (±45° around the prior's heading and around its flip), so the
/// frame is not registered at the truth; with the fallback (`heading_sweep_step_deg`) the second
/// registration sweeps the whole circle and the accepted pose is the truth's to a few pixels.
#[test]
fn the_heading_sweep_recovers_a_prior_turned_a_hundred_degrees() {
    use crate::core::pose_search::{turned_pose, PoseSearchConfig};
    let (mesh, camera, truth, _) = house_and_poses();
    let config = RegistrationConfig::default();
    let query = ideal_query(&mesh, &camera, &truth, &config);
    let turned = turned_pose(&truth, 100.0, 0.0, 0.0);
    let centre = turned.camera_center() + Vector3::new(0.4, -0.3, 0.2);
    let prior = Rigid3::new(turned.rotation, -(turned.rotation * centre));
    let mut workspace = ReprojectionWorkspace::new();
    let mut register = |config: &RegistrationConfig| {
        let result = register_query(
            &mesh,
            &camera,
            IntrinsicsMode::Known,
            &prior,
            query.view(),
            config,
            7,
        )
        .unwrap();
        let delta_px = result.verdict.accepted_pose().map(|pose| {
            mutual_reprojection_error_px(
                &mesh,
                &pose.camera,
                &pose.cam_from_world,
                &camera,
                &truth,
                &mut workspace,
            )
            .unwrap_or(f64::INFINITY)
        });
        println!(
            "sweep step {}°: accepted δ {delta_px:?} px, sweep {:.0} ms of {:.0} ms",
            config.pose_search.heading_sweep_step_deg,
            result.timings.heading_sweep_ms,
            result.timings.total_ms
        );
        // Both registrations are kept beside each other, and the frame is decided across them.
        if let Some(sweep) = &result.heading_sweep {
            assert!(!sweep.first.verdict.accepted());
            let retry = sweep.retry.as_ref().unwrap();
            let (carried, rejection) = decide_passes(
                &mesh,
                &sweep.first,
                Some(retry),
                config.pose_search.centre_agreement_share,
            );
            assert_eq!(sweep.carried, carried);
            let mut verdict = sweep.verdict(carried).unwrap().clone();
            apply_passes_decision(&mut verdict, rejection);
            assert_eq!(verdict.decision, result.verdict.decision);
        }
        (
            delta_px,
            result.timings.heading_sweep_ms,
            result.heading_sweep,
        )
    };
    let (without, _, no_sweep) = register(&config);
    assert!(without.is_none_or(|d| d > 25.0), "{without:?}");
    assert!(no_sweep.is_none());
    let swept = RegistrationConfig {
        pose_search: PoseSearchConfig {
            heading_sweep_step_deg: 4.0,
            ..config.pose_search
        },
        ..config.clone()
    };
    let (with, sweep_ms, sweep) = register(&swept);
    assert!(sweep_ms > 0.0);
    assert!(with.is_some_and(|d| d < 5.0), "{with:?}");
    let sweep = sweep.unwrap();
    assert_eq!(sweep.carried, Pass::HeadingSweep);
    assert!(sweep.first.verdict.chosen().is_none_or(|first| {
        mutual_reprojection_error_px(
            &mesh,
            &first.camera,
            &first.cam_from_world,
            &camera,
            &truth,
            &mut ReprojectionWorkspace::new(),
        )
        .is_none_or(|d| d > 25.0)
    }));
}

#[test]
fn depth_smoothing_averages_within_surfaces_and_keeps_edges_and_holes() {
    // Left half a wall at 10 m with ±0.1 m alternating noise, right half at 20 m, one hole.
    let (width, height) = (10, 5);
    let mut depth = Image::from_fn(width, height, |col, row| {
        let i = row * width + col;
        if col < 5 {
            10.0 + if i % 2 == 0 { 0.1 } else { -0.1 }
        } else {
            20.0
        }
    });
    *depth.get_mut(7, 2).unwrap() = 0.0;
    let mut out = Image::default();
    smooth_depth(depth.view(), 1, 0.03, &mut out);
    let out = out.data();
    assert_eq!(out[2 * width + 7], 0.0, "a hole stays a hole");
    assert_eq!(
        out[2 * width + 8],
        20.0,
        "the far wall is not pulled towards the near one"
    );
    // The noise alternates by column: a 3x3 window inside the wall holds columns -,+,- (mean
    // 10 - 0.1/3); at the wall's edge the window keeps only columns 3 and 4 (-,+: mean 10).
    assert!(
        (out[2 * width + 2] - (10.0 - 0.1 / 3.0)).abs() < 1e-5,
        "{}",
        out[2 * width + 2]
    );
    assert!(
        (out[2 * width + 4] - 10.0).abs() < 1e-5,
        "{}",
        out[2 * width + 4]
    );
}

#[test]
fn bad_inputs_are_reported_not_panicked() {
    let mesh = house_mesh();
    let camera = Camera::pinhole(64, 48, PinholeIntrinsics::centered(50.0, 64, 48));
    let query = Image::filled(64, 48, 0.0);
    let query = query.view();
    let config = RegistrationConfig::default();
    let nan_pose = Rigid3::new(UnitQuaternion::identity(), Vector3::new(f64::NAN, 0.0, 0.0));
    assert_eq!(
        register_query(
            &mesh,
            &camera,
            IntrinsicsMode::Known,
            &nan_pose,
            query,
            &config,
            1
        )
        .unwrap_err(),
        RegistrationError::NonFiniteInitialPose
    );
    // Looking away from the house.
    let away = Rigid3::look_at(
        &Vector3::new(0.0, 0.0, 50.0),
        &Vector3::new(0.0, 0.0, 100.0),
        &Vector3::x(),
    )
    .unwrap();
    assert_eq!(
        register_query(
            &mesh,
            &camera,
            IntrinsicsMode::Known,
            &away,
            query,
            &config,
            1
        )
        .unwrap_err(),
        RegistrationError::ModelNotVisible
    );
    let photo = Image::filled(10, 10, 0.5f32);
    let input = FrameInput {
        photo: photo.view(),
        depth_m: None,
        camera: &camera,
        intrinsics: IntrinsicsMode::Known,
        initial_cam_from_world: Rigid3::identity(),
        seed: 1,
    };
    assert!(matches!(
        query_gradient(&input, &config),
        Err(RegistrationError::PhotoSize { .. })
    ));
}

#[test]
fn the_matching_settings_are_read_under_their_name() {
    let config: RegistrationConfig = toml::from_str(
        "coarse_pose_count = 5\n[matching]\nmin_support_gradient = 0.004\n[matching.sift_flow]\nbp_bands = 1\n",
    )
    .unwrap();
    assert_eq!(config.coarse_pose_count, 5);
    assert_eq!(config.matching.min_support_gradient, 0.004);
    assert_eq!(config.matching.sift_flow.bp_bands, 1);
    assert!(config.validate().is_ok());
    // The old name of the section is an unknown field, not silently ignored.
    let error =
        toml::from_str::<RegistrationConfig>("[correspondence]\nmin_support_gradient = 0.004\n")
            .unwrap_err();
    assert!(error.to_string().contains("correspondence"), "{error}");
}

/// The whole result of a frame but its timings, as text: equal text is equal bits (`{:?}`
/// prints every float with the shortest representation that reads back to the same bits).
fn result_bits(result: &FrameResult) -> String {
    format!(
        "{:?}\n{:?}\n{:?}\n{:?}",
        result.verdict, result.coarse, result.refinement, result.evidence
    )
}

/// Registration is reproducible bit for bit: the same frame registered twice with two worker
/// threads, and with one (which change which worker runs which coarse view, and what each worker's
/// reused buffers held before), gives the same verdict, coarse outcomes, refinement and evidence.
/// The query is photo-like (the model's ASG under the true pose with seeded noise), so that the
/// flow and the refinement meet ties and near-ties as on photos.
#[test]
fn a_frame_registers_to_the_same_bits_twice_and_on_any_thread_count() {
    let (mesh, camera, truth, initial) = house_and_poses();
    let config = RegistrationConfig::default();
    let mut query = ideal_query(&mesh, &camera, &truth, &config);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for value in query.data_mut() {
        let noise: f32 = rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut rng);
        *value = (*value * 0.7 + 0.15 + 0.08 * noise).clamp(0.0, 1.0);
    }
    let register_on = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            register_query(
                &mesh,
                &camera,
                IntrinsicsMode::Known,
                &initial,
                query.view(),
                &config,
                5,
            )
            .unwrap()
        })
    };
    let first = result_bits(&register_on(2));
    let again = result_bits(&register_on(2));
    let one_thread = result_bits(&register_on(1));
    // Three threads: the coarse views are rendered in batches of three (of two above, one at
    // a time on one thread) and verification's renderings split differently.
    let three_threads = result_bits(&register_on(3));
    assert!(first == again, "two runs differ:\n{first}\n---\n{again}");
    assert!(
        first == three_threads,
        "2 threads vs 3:\n{first}\n---\n{three_threads}"
    );
    assert!(
        first == one_thread,
        "2 threads vs 1:\n{first}\n---\n{one_thread}"
    );
}
