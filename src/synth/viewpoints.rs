//! Where the synthetic photos are taken from. House: like the paper's data set, the building seen
//! from three sides at about 2, 8 and 15 m height, 12–25 m away, aimed at the building with some
//! jitter in aim and roll. Block: oblique views from 30–60 m height all around.

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
    if scene.distance_to_buildings_m(glam::Vec2::new(eye.x, eye.y)) < 2.0 {
        return None;
    }
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
}
