//! Where the synthetic photos are taken from. House: like the paper's data set, the building seen
//! from three sides at about 2, 8 and 15 m height, 12–25 m away, aimed at the building with some
//! jitter in aim and roll. Block: oblique views from 30–60 m height all around.
//!
//! Two ways to place them. By default ([`draw_viewpoint`]) each photo is drawn on its own, so
//! consecutive photos are far apart (the house cycles sides and heights, the block draws a random
//! azimuth per photo). With `synth --flight-path` ([`flight_path_viewpoints`]) the photos are
//! taken in flight order along a continuous path, a few metres apart, as a drone shooting every
//! second or two does: the case where a frame's registered neighbours are close (step
//! "neighbour", issues #11, #12).

use glam::Vec3;
use nalgebra::{UnitQuaternion, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::geometry::Scene;
use crate::core::rigid::Rigid3;

/// Which kind of scene is generated.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum SceneKind {
    /// One free-standing house with an annex, photographed from three sides at 2, 8 and 15 m.
    #[default]
    House,
    /// Several buildings with flat, gable and hip roofs, seen obliquely from 30–60 m.
    Block,
}

/// One planned photo.
#[derive(Clone, Debug)]
pub struct Viewpoint {
    pub name: String,
    pub cam_from_world: Rigid3,
    pub eye_m: Vec3,
    /// Short description for the summary ("front, 8 m").
    pub label: String,
}

/// Heights of the house views, metres (the paper's 2, 8 and 15 m).
pub const HOUSE_HEIGHTS_M: [f32; 3] = [2.0, 8.0, 15.0];

fn to_vector(p: Vec3) -> Vector3<f64> {
    Vector3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z))
}

/// A candidate viewpoint for image `index`; draw again for a different jitter.
pub fn draw_viewpoint(
    scene: &Scene,
    kind: SceneKind,
    index: usize,
    rng: &mut ChaCha8Rng,
) -> Option<Viewpoint> {
    let (eye, target, label) = match kind {
        SceneKind::House => {
            let main = scene.footprints.first()?;
            // Sides in the house frame: front (-y), left gable (-x), back (+y).
            const SIDES: [(&str, f32); 3] = [
                ("front", -std::f32::consts::FRAC_PI_2),
                ("left", std::f32::consts::PI),
                ("back", std::f32::consts::FRAC_PI_2),
            ];
            let (side_name, side_angle) = SIDES[index % 3];
            let height = HOUSE_HEIGHTS_M[(index / 3) % 3] + rng.random_range(-0.4..0.4f32);
            let azimuth = main.frame.yaw_rad + side_angle + rng.random_range(-0.45..0.45f32);
            let distance = rng.random_range(12.0..25.0f32) + main.half_x_m.max(main.half_y_m) * 0.5;
            let centre = main.frame.to_world(Vec3::new(0.0, 0.0, 0.0));
            let eye =
                centre + Vec3::new(azimuth.cos() * distance, azimuth.sin() * distance, height);
            let target = centre
                + Vec3::new(
                    rng.random_range(-1.5..1.5),
                    rng.random_range(-1.5..1.5),
                    rng.random_range(2.5..5.0),
                );
            (
                eye,
                target,
                format!("{side_name}, {:.0} m", HOUSE_HEIGHTS_M[(index / 3) % 3]),
            )
        }
        SceneKind::Block => {
            let azimuth = rng.random_range(0.0..std::f32::consts::TAU);
            let distance = rng.random_range(40.0..70.0f32);
            let height = rng.random_range(30.0..60.0f32);
            let eye = Vec3::new(azimuth.cos() * distance, azimuth.sin() * distance, height);
            let target = Vec3::new(
                rng.random_range(-15.0..15.0),
                rng.random_range(-15.0..15.0),
                rng.random_range(0.0..8.0),
            );
            (eye, target, format!("oblique, {height:.0} m"))
        }
    };
    if scene.distance_to_buildings_m(glam::Vec2::new(eye.x, eye.y)) < MIN_CLEARANCE_M {
        return None;
    }
    aimed_viewpoint(eye, target, index, label, rng)
}

/// Least horizontal distance from a camera to any building's footprint, metres.
const MIN_CLEARANCE_M: f32 = 2.0;

/// The photo `index` taken from `eye` aimed at `target`, rolled by a small random angle (the one
/// draw from `rng`, after the aim is known to exist: the order the default scenes were made in).
fn aimed_viewpoint(
    eye: Vec3,
    target: Vec3,
    index: usize,
    label: String,
    rng: &mut ChaCha8Rng,
) -> Option<Viewpoint> {
    let look = Rigid3::look_at(&to_vector(eye), &to_vector(target), &Vector3::z())?;
    let roll =
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.random_range(-0.05..0.05f64));
    let cam_from_world = Rigid3::new(roll * look.rotation, roll * look.translation);
    Some(Viewpoint {
        name: format!("view_{index:03}.jpg"),
        cam_from_world,
        eye_m: eye,
        label,
    })
}

/// Every photo of a scene, in order. Without `flight_path` each is drawn on its own by
/// [`draw_viewpoint`] (again, up to 50 times, while the eye falls within 2 m of a building), which
/// is how every scene before `--flight-path` was made, random draw for random draw; with it, along
/// [`flight_path_viewpoints`]. `Err` says why no plan was found.
pub fn plan_viewpoints(
    scene: &Scene,
    kind: SceneKind,
    count: usize,
    flight_path: bool,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<Viewpoint>, String> {
    if flight_path {
        return flight_path_viewpoints(scene, kind, count, rng);
    }
    let mut views = Vec::with_capacity(count);
    for index in 0..count {
        let mut attempt = 0;
        let view = loop {
            attempt += 1;
            if let Some(view) = draw_viewpoint(scene, kind, index, rng) {
                break Some(view);
            }
            if attempt > 50 {
                break None;
            }
        };
        views.push(view.ok_or_else(|| format!("no valid viewpoint found for image {index}"))?);
    }
    Ok(views)
}

/// House passes' azimuth range around each side's normal, radians (±26°, as [`draw_viewpoint`]).
const HOUSE_SIDE_HALF_RANGE_RAD: f32 = 0.45;
/// Distance between consecutive photos of a pass, metres: a drone at about 3 m/s shooting every
/// second (shorter when a pass's photos would not fit its side's azimuth range).
const HOUSE_SPACING_M: std::ops::Range<f32> = 2.5..3.5;
/// How far a pass's distance to the house may drift from its start to its end, metres.
const HOUSE_DISTANCE_DRIFT_M: f32 = 4.0;
/// Block: photos per leg of the orbit (a leg is one stretch flown at its own height and radius).
const BLOCK_PHOTOS_PER_LEG: usize = 16;
/// Block: distance between consecutive photos along a leg, metres.
const BLOCK_SPACING_M: std::ops::Range<f32> = 3.0..5.0;
/// Block: how far the aim point wanders from one photo to the next, metres per axis.
const BLOCK_AIM_STEP_M: f32 = 2.0;
/// How far an eye that falls within [`MIN_CLEARANCE_M`] of a building is moved outwards per try,
/// and how many tries, before the plan gives up.
const NUDGE_STEP_M: f32 = 1.0;
const NUDGE_TRIES: usize = 40;

/// `eye` moved horizontally away from `centre` by [`NUDGE_STEP_M`] at a time until it clears every
/// building by [`MIN_CLEARANCE_M`]; `None` when it does not within [`NUDGE_TRIES`] steps.
fn nudged_clear(scene: &Scene, eye: Vec3, centre: Vec3) -> Option<Vec3> {
    let outwards = glam::Vec2::new(eye.x - centre.x, eye.y - centre.y).normalize_or(glam::Vec2::X);
    (0..=NUDGE_TRIES)
        .map(|step| {
            let shift = outwards * (step as f32 * NUDGE_STEP_M);
            Vec3::new(eye.x + shift.x, eye.y + shift.y, eye.z)
        })
        .find(|e| scene.distance_to_buildings_m(glam::Vec2::new(e.x, e.y)) >= MIN_CLEARANCE_M)
}

/// `count` split into `parts` shares as equal as possible, the larger ones first.
fn split_evenly(count: usize, parts: usize) -> Vec<usize> {
    (0..parts)
        .map(|k| count / parts + usize::from(k < count % parts))
        .collect()
}

/// The photos in flight order along a continuous path (`synth --flight-path`), consecutive ones a
/// few metres apart.
///
/// House: nine passes, one per side (front, left gable, back) and height (2, 8, 15 m), flown as
/// a lawn-mower around the house: at 2 m front → left → back with the azimuth falling, climb, at
/// 8 m back → left → front, climb, at 15 m front → left → back. Each pass sweeps part of its
/// side's ±26° azimuth range continuously, 2.5–3.5 m between photos (less when the pass's photos
/// would not fit the range), at a distance that drifts within 12–25 m (+ half the house) and
/// starts where the previous pass ended; between passes the drone turns the corner or climbs
/// without shooting. Aim (±1.5 m around the house, 2.5–5 m up) and roll (±0.05 rad) are jittered
/// per photo as in [`draw_viewpoint`]. The photos are spread over the passes as evenly as they go.
///
/// Block: legs of up to 16 photos, each an arc of an orbit at its own height (30–60 m) and radius
/// (40–70 m), both drifting a little along the leg, 3–5 m between photos, counter-clockwise; the
/// legs start at azimuths spread evenly around the block, so the block is seen from all sides.
/// The aim point wanders from photo to photo (at most 2 m per axis) within the box
/// [`draw_viewpoint`] draws it from (±15 m, 0–8 m up).
///
/// An eye within 2 m of a building is moved outwards until it clears them; the photo count is
/// always `count`.
pub fn flight_path_viewpoints(
    scene: &Scene,
    kind: SceneKind,
    count: usize,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<Viewpoint>, String> {
    match kind {
        SceneKind::House => house_flight_path(scene, count, rng),
        SceneKind::Block => block_flight_path(scene, count, rng),
    }
}

fn house_flight_path(
    scene: &Scene,
    count: usize,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<Viewpoint>, String> {
    use std::f32::consts::{FRAC_PI_2, PI};
    let main = scene
        .footprints
        .first()
        .ok_or("the house scene has no building")?;
    let centre = main.frame.to_world(Vec3::ZERO);
    let distance_extra_m = main.half_x_m.max(main.half_y_m) * 0.5;
    let (min_distance_m, max_distance_m) = (12.0 + distance_extra_m, 25.0 + distance_extra_m);
    // Sides in the house frame, unwrapped so that front → left → back is a falling azimuth.
    const SIDES: [(&str, f32); 3] = [
        ("front", -FRAC_PI_2),
        ("left", -PI),
        ("back", -PI - FRAC_PI_2),
    ];
    let mut passes = Vec::with_capacity(9);
    for (height_index, &height_m) in HOUSE_HEIGHTS_M.iter().enumerate() {
        let falling = height_index % 2 == 0;
        for k in 0..SIDES.len() {
            let side = if falling { k } else { SIDES.len() - 1 - k };
            passes.push((SIDES[side], height_m, falling));
        }
    }
    let counts = split_evenly(count, passes.len());
    let mut distance_m = rng.random_range(min_distance_m..max_distance_m);
    let mut views = Vec::with_capacity(count);
    for (((side_name, side_angle), height_m, falling), photos) in passes.into_iter().zip(counts) {
        if photos == 0 {
            continue;
        }
        let start_distance_m = distance_m;
        let end_distance_m = (start_distance_m
            + rng.random_range(-HOUSE_DISTANCE_DRIFT_M..HOUSE_DISTANCE_DRIFT_M))
        .clamp(min_distance_m, max_distance_m);
        distance_m = end_distance_m;
        let mean_distance_m = 0.5 * (start_distance_m + end_distance_m);
        let full_range = 2.0 * HOUSE_SIDE_HALF_RANGE_RAD;
        let intervals = (photos - 1) as f32;
        let mut step_rad = rng.random_range(HOUSE_SPACING_M) / mean_distance_m;
        if intervals * step_rad > full_range {
            step_rad = full_range / intervals;
        }
        // The pass's span placed at random within its side's range (jitter below stays inside).
        let span = intervals * step_rad;
        let slack = (full_range - span).max(0.0);
        let offset = rng.random_range(0.0..=slack);
        let direction = if falling { -1.0 } else { 1.0 };
        let start_azimuth = main.frame.yaw_rad + side_angle - direction * HOUSE_SIDE_HALF_RANGE_RAD
            + direction * offset;
        let pass_height_m = height_m + rng.random_range(-0.3..0.3f32);
        for i in 0..photos {
            let along = i as f32;
            let t = if photos > 1 { along / intervals } else { 0.5 };
            let azimuth =
                start_azimuth + direction * step_rad * (along + rng.random_range(-0.1..0.1f32));
            let distance = start_distance_m
                + t * (end_distance_m - start_distance_m)
                + rng.random_range(-0.2..0.2f32);
            let eye = centre
                + Vec3::new(
                    azimuth.cos() * distance,
                    azimuth.sin() * distance,
                    pass_height_m + rng.random_range(-0.15..0.15f32),
                );
            let target = centre
                + Vec3::new(
                    rng.random_range(-1.5..1.5),
                    rng.random_range(-1.5..1.5),
                    rng.random_range(2.5..5.0),
                );
            let index = views.len();
            let eye = nudged_clear(scene, eye, centre)
                .ok_or_else(|| format!("no clear eye found for image {index} on the path"))?;
            let label = format!("{side_name}, {height_m:.0} m");
            views.push(
                aimed_viewpoint(eye, target, index, label, rng)
                    .ok_or_else(|| format!("image {index}: the eye is its aim point"))?,
            );
        }
    }
    Ok(views)
}

fn block_flight_path(
    scene: &Scene,
    count: usize,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<Viewpoint>, String> {
    let legs = count.div_ceil(BLOCK_PHOTOS_PER_LEG).max(1);
    let first_azimuth = rng.random_range(0.0..std::f32::consts::TAU);
    let mut target = Vec3::new(
        rng.random_range(-15.0..15.0),
        rng.random_range(-15.0..15.0),
        rng.random_range(0.0..8.0),
    );
    let mut views = Vec::with_capacity(count);
    for (leg, photos) in split_evenly(count, legs).into_iter().enumerate() {
        let start_azimuth = first_azimuth
            + leg as f32 * std::f32::consts::TAU / legs as f32
            + rng.random_range(-0.3..0.3f32);
        let start_height_m = rng.random_range(30.0..60.0f32);
        let end_height_m = (start_height_m + rng.random_range(-5.0..5.0f32)).clamp(30.0, 60.0);
        let start_radius_m = rng.random_range(40.0..70.0f32);
        let end_radius_m = (start_radius_m + rng.random_range(-5.0..5.0f32)).clamp(40.0, 70.0);
        let spacing_m = rng.random_range(BLOCK_SPACING_M);
        let mut azimuth = start_azimuth;
        for i in 0..photos {
            let t = if photos > 1 {
                i as f32 / (photos - 1) as f32
            } else {
                0.5
            };
            let radius_m = start_radius_m + t * (end_radius_m - start_radius_m);
            let height_m = start_height_m + t * (end_height_m - start_height_m);
            if i > 0 {
                azimuth += spacing_m * rng.random_range(0.9..1.1f32) / radius_m;
            }
            let eye = Vec3::new(azimuth.cos() * radius_m, azimuth.sin() * radius_m, height_m);
            if i > 0 {
                target += Vec3::new(
                    rng.random_range(-BLOCK_AIM_STEP_M..BLOCK_AIM_STEP_M),
                    rng.random_range(-BLOCK_AIM_STEP_M..BLOCK_AIM_STEP_M),
                    rng.random_range(-BLOCK_AIM_STEP_M..BLOCK_AIM_STEP_M),
                );
                target = target.clamp(Vec3::new(-15.0, -15.0, 0.0), Vec3::new(15.0, 15.0, 8.0));
            }
            let index = views.len();
            let eye = nudged_clear(scene, eye, Vec3::ZERO)
                .ok_or_else(|| format!("no clear eye found for image {index} on the path"))?;
            let label = format!("oblique, {height_m:.0} m");
            views.push(
                aimed_viewpoint(eye, target, index, label, rng)
                    .ok_or_else(|| format!("image {index}: the eye is its aim point"))?,
            );
        }
    }
    Ok(views)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::geometry::build_house;
    use rand::SeedableRng;

    #[test]
    fn house_views_cycle_sides_and_heights_and_look_at_the_house() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let scene = build_house(&mut rng);
        for index in 0..9 {
            let view = draw_viewpoint(&scene, SceneKind::House, index, &mut rng).unwrap();
            let expected = HOUSE_HEIGHTS_M[(index / 3) % 3];
            assert!((view.eye_m.z - expected).abs() < 0.5, "{}", view.eye_m.z);
            let centre_cam = view
                .cam_from_world
                .transform_point(&Vector3::new(0.0, 0.0, 3.0));
            assert!(centre_cam.z > 10.0);
            assert!((centre_cam.x / centre_cam.z).abs() < 0.3);
            assert!((view.cam_from_world.camera_center() - to_vector(view.eye_m)).norm() < 1e-4);
        }
    }

    /// Distances between consecutive eyes, metres.
    fn steps_m(views: &[Viewpoint]) -> Vec<f32> {
        views
            .windows(2)
            .map(|pair| pair[0].eye_m.distance(pair[1].eye_m))
            .collect()
    }

    #[test]
    fn house_flight_path_is_short_steps_over_three_sides_and_heights_looking_at_the_house() {
        for seed in [1, 2, 5] {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let scene = build_house(&mut rng);
            let views = plan_viewpoints(&scene, SceneKind::House, 48, true, &mut rng).unwrap();
            assert_eq!(views.len(), 48);
            // Within a pass (same side and height) consecutive photos are a few metres apart;
            // the only longer steps are the eight turns and climbs between the nine passes.
            let steps = steps_m(&views);
            for (k, step) in steps.iter().enumerate() {
                if views[k].label == views[k + 1].label {
                    assert!(
                        (1.0..=6.0).contains(step),
                        "seed {seed}: {} → {}: {step} m",
                        views[k].name,
                        views[k + 1].name
                    );
                }
            }
            let changes = (0..steps.len())
                .filter(|&k| views[k].label != views[k + 1].label)
                .count();
            assert_eq!(
                changes, 8,
                "seed {seed}: the passes are not contiguous sets"
            );
            let mut labels: Vec<&str> = views.iter().map(|v| v.label.as_str()).collect();
            labels.dedup();
            labels.sort_unstable();
            labels.dedup();
            assert_eq!(labels.len(), 9, "seed {seed}: {labels:?}");
            let main = &scene.footprints[0];
            let centre = main.frame.to_world(Vec3::ZERO);
            let extra_m = main.half_x_m.max(main.half_y_m) * 0.5;
            for view in &views {
                let (side, height) = view.label.split_once(", ").unwrap();
                let height_m: f32 = height.trim_end_matches(" m").parse().unwrap();
                assert!(HOUSE_HEIGHTS_M.contains(&height_m));
                assert!((view.eye_m.z - height_m).abs() < 0.5, "{}", view.eye_m.z);
                let offset = view.eye_m - centre;
                let distance_m = offset.truncate().length();
                assert!(
                    (12.0 + extra_m - 0.3..=25.0 + extra_m + 0.3).contains(&distance_m),
                    "{distance_m}"
                );
                // The eye's azimuth in the house frame is within ±0.5 rad of its side's normal.
                let azimuth = offset.y.atan2(offset.x) - main.frame.yaw_rad;
                let normal = match side {
                    "front" => -std::f32::consts::FRAC_PI_2,
                    "left" => std::f32::consts::PI,
                    "back" => std::f32::consts::FRAC_PI_2,
                    other => panic!("side {other}"),
                };
                let off = (azimuth - normal).sin().atan2((azimuth - normal).cos());
                assert!(off.abs() < 0.5, "{}: {off} rad off its side", view.name);
                let centre_cam = view
                    .cam_from_world
                    .transform_point(&Vector3::new(0.0, 0.0, 3.0));
                assert!(centre_cam.z > 10.0);
                assert!((centre_cam.x / centre_cam.z).abs() < 0.3);
                assert!(
                    (view.cam_from_world.camera_center() - to_vector(view.eye_m)).norm() < 1e-4
                );
            }
            let names: Vec<String> = (0..48).map(|k| format!("view_{k:03}.jpg")).collect();
            assert!(views.iter().map(|v| &v.name).eq(names.iter()));
        }
    }

    #[test]
    fn block_flight_path_is_short_steps_all_around_looking_at_the_block() {
        for seed in [1, 2, 5] {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let scene = crate::synth::geometry::build_block(&mut rng);
            let views = plan_viewpoints(&scene, SceneKind::Block, 48, true, &mut rng).unwrap();
            assert_eq!(views.len(), 48);
            // Three legs of 16: the only long steps are the two jumps between legs.
            let steps = steps_m(&views);
            let long = steps.iter().filter(|s| **s > 6.0).count();
            assert!(long <= 2, "seed {seed}: {steps:?}");
            assert!(steps.iter().all(|s| *s > 1.0), "seed {seed}: {steps:?}");
            let mut quadrants = [false; 4];
            for view in &views {
                assert!((30.0..=60.0).contains(&view.eye_m.z), "{}", view.eye_m.z);
                let out_m = view.eye_m.truncate().length();
                // 40–70 m out, or further where an eye was moved clear of a building.
                assert!((40.0..=80.0).contains(&out_m), "{out_m}");
                assert!(scene.distance_to_buildings_m(view.eye_m.truncate()) >= MIN_CLEARANCE_M);
                let azimuth = view.eye_m.y.atan2(view.eye_m.x);
                let quadrant = ((azimuth + std::f32::consts::PI) / std::f32::consts::FRAC_PI_2)
                    .floor()
                    .clamp(0.0, 3.0) as usize;
                quadrants[quadrant] = true;
                // The block's middle is in the picture (70° wide field of view).
                let middle_cam = view
                    .cam_from_world
                    .transform_point(&Vector3::new(0.0, 0.0, 4.0));
                assert!(middle_cam.z > 30.0);
                assert!((middle_cam.x / middle_cam.z).abs() < 0.6);
                assert!((middle_cam.y / middle_cam.z).abs() < 0.6);
            }
            assert_eq!(quadrants, [true; 4], "seed {seed}: not seen from all sides");
        }
    }

    #[test]
    fn flight_paths_keep_the_photo_count_for_few_and_many_photos() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let house = build_house(&mut rng);
        let block = crate::synth::geometry::build_block(&mut rng);
        for count in [1, 2, 5, 9, 10, 100] {
            for (scene, kind) in [(&house, SceneKind::House), (&block, SceneKind::Block)] {
                let views = plan_viewpoints(scene, kind, count, true, &mut rng).unwrap();
                assert_eq!(views.len(), count, "{kind:?}");
                let steps = steps_m(&views);
                assert!(
                    steps.iter().all(|s| *s > 0.3),
                    "{kind:?} {count}: {steps:?}"
                );
            }
        }
    }
}
