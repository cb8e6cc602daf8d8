//! What the photos show and the model never contains: trees, cars, a fence, people and bushes,
//! placed around the buildings and clear of the cameras.

use glam::{Vec2, Vec3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::{Frame, PartKind, Scene};
use crate::synth::texture::Material;

/// Adds the clutter: trees near and far, cars on paved ground, a fence, people and bushes.
/// Nothing is put within `keep_clear_m` of a camera position.
pub fn add_clutter(
    scene: &mut Scene,
    rng: &mut ChaCha8Rng,
    camera_positions_m: &[Vec3],
    keep_clear_m: f32,
) {
    let noise_seed: u64 = rng.random();
    let clear_of_cameras = |p: Vec2, radius: f32| {
        camera_positions_m
            .iter()
            .all(|c| (Vec2::new(c.x, c.y) - p).length() > keep_clear_m + radius)
    };
    let extent = scene
        .footprints
        .iter()
        .map(|f| f.frame.centre_m.length() + f.half_x_m.max(f.half_y_m))
        .fold(0.0f32, f32::max);
    let on_pavement = |scene: &Scene, p: Vec2, margin: f32| {
        scene
            .ground
            .asphalt
            .iter()
            .chain(&scene.ground.concrete)
            .chain(&scene.ground.gravel)
            .any(|&(a, b, w)| {
                let ab = b - a;
                let t = ((p - a).dot(ab) / ab.length_squared().max(1e-9)).clamp(0.0, 1.0);
                (p - (a + ab * t)).length() < w + margin
            })
    };

    // Trees near the buildings.
    let near_tree_count = rng.random_range(7..12);
    let mut placed = 0;
    for _ in 0..400 {
        if placed >= near_tree_count {
            break;
        }
        let angle = rng.random_range(0.0..std::f32::consts::TAU);
        let radius = rng.random_range(extent + 3.0..extent + 22.0);
        let p = Vec2::new(angle.cos(), angle.sin()) * radius;
        let crown_radius = rng.random_range(1.5..3.2f32);
        if scene.distance_to_buildings_m(p) < crown_radius + 1.0
            || !clear_of_cameras(p, crown_radius)
            || on_pavement(scene, p, 0.5)
        {
            continue;
        }
        add_tree(scene, rng, p, crown_radius, noise_seed ^ placed as u64, 4);
        placed += 1;
    }
    // A ring of trees far away: the horizon of a real photo is not empty.
    for k in 0..40 {
        let angle = k as f32 / 40.0 * std::f32::consts::TAU + rng.random_range(-0.05..0.05);
        let radius = rng.random_range(extent + 45.0..extent + 90.0);
        let p = Vec2::new(angle.cos(), angle.sin()) * radius;
        let crown_radius = rng.random_range(3.0..5.5f32);
        if on_pavement(scene, p, crown_radius) {
            continue;
        }
        add_tree(scene, rng, p, crown_radius, noise_seed ^ (1000 + k), 2);
    }
    // Bushes along the walls.
    for _ in 0..rng.random_range(5..10) {
        let footprint = scene.footprints[rng.random_range(0..scene.footprints.len())];
        let side = rng.random_range(0..4);
        let t = rng.random_range(-1.0..1.0f32);
        let local = match side {
            0 => Vec3::new(t * footprint.half_x_m, -footprint.half_y_m - 0.8, 0.0),
            1 => Vec3::new(t * footprint.half_x_m, footprint.half_y_m + 0.8, 0.0),
            2 => Vec3::new(footprint.half_x_m + 0.8, t * footprint.half_y_m, 0.0),
            _ => Vec3::new(-footprint.half_x_m - 0.8, t * footprint.half_y_m, 0.0),
        };
        let w = footprint.frame.to_world(local);
        let p = Vec2::new(w.x, w.y);
        if on_pavement(scene, p, 0.6) || !clear_of_cameras(p, 1.0) {
            continue;
        }
        let object_id = scene.new_object();
        let r = rng.random_range(0.5..0.9f32);
        scene.add_blob(
            Vec3::new(p.x, p.y, r * 0.7),
            Vec3::new(r * 1.2, r, r * 0.9),
            0.3,
            2,
            Material::Foliage {
                palette: rng.random_range(0..3),
            },
            noise_seed ^ u64::from(object_id),
            object_id,
        );
    }
    // Cars on asphalt.
    let asphalt = scene.ground.asphalt.clone();
    let mut cars = 0;
    for _ in 0..200 {
        if cars >= 4 {
            break;
        }
        let &(a, b, half_width) = &asphalt[rng.random_range(0..asphalt.len())];
        let t = rng.random_range(0.0..1.0f32);
        let along = (b - a).normalize_or_zero();
        let across = along.perp();
        let p = a + (b - a) * t + across * rng.random_range(-0.4..0.4f32) * half_width;
        if p.length() > extent + 30.0
            || !clear_of_cameras(p, 2.5)
            || scene.distance_to_buildings_m(p) < 2.5
        {
            continue;
        }
        add_car(scene, rng, p, along.y.atan2(along.x));
        cars += 1;
    }
    // A fence along part of the plot.
    let fence_id = scene.new_object();
    let fence_y = -(extent + rng.random_range(3.0..6.0f32));
    let fence_frame = Frame {
        centre_m: Vec2::new(0.0, 0.0),
        yaw_rad: rng.random_range(0.0..std::f32::consts::TAU),
        base_z_m: 0.0,
    };
    let fence_half_length = extent + 4.0;
    let mut x = -fence_half_length;
    while x <= fence_half_length {
        let world = fence_frame.to_world(Vec3::new(x, fence_y, 0.0));
        if clear_of_cameras(Vec2::new(world.x, world.y), 0.5)
            && !on_pavement(scene, Vec2::new(world.x, world.y), 0.3)
        {
            scene.add_box(
                fence_frame,
                Vec3::new(x - 0.05, fence_y - 0.05, 0.0),
                Vec3::new(x + 0.05, fence_y + 0.05, 1.2),
                Material::FenceWood,
                Material::FenceWood,
                PartKind::Clutter,
                fence_id,
            );
            for rail_z in [0.35f32, 0.95] {
                scene.add_box(
                    fence_frame,
                    Vec3::new(x, fence_y - 0.02, rail_z),
                    Vec3::new(x + 2.0, fence_y + 0.02, rail_z + 0.1),
                    Material::FenceWood,
                    Material::FenceWood,
                    PartKind::Clutter,
                    fence_id,
                );
            }
        }
        x += 2.0;
    }
    // People standing around.
    for _ in 0..rng.random_range(2..5) {
        let angle = rng.random_range(0.0..std::f32::consts::TAU);
        let radius = rng.random_range(extent + 1.5..extent + 10.0);
        let p = Vec2::new(angle.cos(), angle.sin()) * radius;
        if scene.distance_to_buildings_m(p) < 0.8 || !clear_of_cameras(p, 0.5) {
            continue;
        }
        add_person(scene, rng, p);
    }
}

fn add_tree(
    scene: &mut Scene,
    rng: &mut ChaCha8Rng,
    p: Vec2,
    crown_radius_m: f32,
    noise_seed: u64,
    subdivisions: u32,
) {
    let object_id = scene.new_object();
    let trunk_height = rng.random_range(1.5..3.0f32) + crown_radius_m * 0.5;
    scene.add_cylinder(
        Vec3::new(p.x, p.y, 0.0),
        Vec3::new(
            rng.random_range(-0.2..0.2),
            rng.random_range(-0.2..0.2),
            trunk_height + crown_radius_m * 0.5,
        ),
        0.12 + 0.04 * crown_radius_m,
        7,
        Material::Bark,
        false,
        object_id,
    );
    let palette = rng.random_range(0..3u8);
    let centre = Vec3::new(p.x, p.y, trunk_height + crown_radius_m * 0.8);
    scene.add_blob(
        centre,
        Vec3::new(
            crown_radius_m,
            crown_radius_m * rng.random_range(0.8..1.1),
            crown_radius_m * rng.random_range(0.9..1.3),
        ),
        0.35,
        subdivisions,
        Material::Foliage { palette },
        noise_seed,
        object_id,
    );
    // Lobes make the outline irregular.
    for lobe in 0..rng.random_range(3..7) {
        let direction = Vec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-0.3..0.8),
        )
        .normalize_or_zero();
        let r = crown_radius_m * rng.random_range(0.45..0.7);
        scene.add_blob(
            centre + direction * crown_radius_m * 0.75,
            Vec3::splat(r),
            0.4,
            subdivisions.saturating_sub(1).max(1),
            Material::Foliage { palette },
            noise_seed ^ (lobe as u64 + 17),
            object_id,
        );
    }
}

fn add_car(scene: &mut Scene, rng: &mut ChaCha8Rng, p: Vec2, yaw_rad: f32) {
    let object_id = scene.new_object();
    let frame = Frame {
        centre_m: p,
        yaw_rad,
        base_z_m: 0.0,
    };
    let paint = Material::CarPaint {
        palette: rng.random_range(0..6),
    };
    let half_length = rng.random_range(2.0..2.4f32);
    let half_width = 0.9;
    scene.add_box(
        frame,
        Vec3::new(-half_length, -half_width, 0.3),
        Vec3::new(half_length, half_width, 0.95),
        paint,
        paint,
        PartKind::Clutter,
        object_id,
    );
    // Cabin: a trapezoid in (x, z), extruded across the car (frame rotated by 90°).
    let cabin_frame = Frame {
        yaw_rad: yaw_rad + std::f32::consts::FRAC_PI_2,
        ..frame
    };
    // In the cabin frame local y is the car's -x.
    let rear = half_length * 0.75;
    let front = -half_length * 0.25;
    let polygon = [
        Vec2::new(-rear, 0.95),
        Vec2::new(-front, 0.95),
        Vec2::new(-front - 0.5, 1.45),
        Vec2::new(-rear + 0.3, 1.45),
    ];
    let mut polygon = polygon.to_vec();
    let area: f32 = (0..4)
        .map(|i| polygon[i].perp_dot(polygon[(i + 1) % 4]))
        .sum();
    if area < 0.0 {
        polygon.reverse();
    }
    let materials: Vec<Material> = (0..4)
        .map(|i| {
            let a = polygon[i];
            let b = polygon[(i + 1) % 4];
            // Roof and floor of the cabin are painted, the slanted and side faces are glass.
            let horizontal = (a.y - b.y).abs() < 1e-3;
            if horizontal {
                paint
            } else {
                Material::CarGlass
            }
        })
        .collect();
    scene.add_prism(
        cabin_frame,
        &polygon,
        half_width * 0.92,
        &materials,
        Material::CarGlass,
        PartKind::Clutter,
        object_id,
    );
    for (wx, wy) in [(1.0f32, 1.0f32), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
        let centre = frame.to_world(Vec3::new(
            wx * (half_length - 0.7),
            wy * (half_width - 0.05),
            0.33,
        ));
        let axis = frame.direction_to_world(Vec3::new(0.0, wy * 0.22, 0.0));
        scene.add_cylinder(
            centre - axis * 0.5,
            axis,
            0.33,
            10,
            Material::Tyre,
            true,
            object_id,
        );
    }
}

fn add_person(scene: &mut Scene, rng: &mut ChaCha8Rng, p: Vec2) {
    let object_id = scene.new_object();
    let frame = Frame {
        centre_m: p,
        yaw_rad: rng.random_range(0.0..std::f32::consts::TAU),
        base_z_m: 0.0,
    };
    let height = rng.random_range(1.6..1.9f32);
    let legs = Material::Clothing {
        palette: rng.random_range(0..5),
    };
    let torso = Material::Clothing {
        palette: rng.random_range(0..5),
    };
    scene.add_box(
        frame,
        Vec3::new(-0.12, -0.18, 0.0),
        Vec3::new(0.12, 0.18, height * 0.47),
        legs,
        legs,
        PartKind::Clutter,
        object_id,
    );
    scene.add_box(
        frame,
        Vec3::new(-0.14, -0.23, height * 0.47),
        Vec3::new(0.14, 0.23, height * 0.85),
        torso,
        torso,
        PartKind::Clutter,
        object_id,
    );
    let head = frame.to_world(Vec3::new(0.0, 0.0, height * 0.93));
    scene.add_blob(
        head,
        Vec3::new(0.1, 0.1, 0.12),
        0.05,
        2,
        Material::Skin,
        u64::from(object_id),
        object_id,
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::geometry::build_house;
    use rand::SeedableRng;

    #[test]
    fn clutter_keeps_clear_of_cameras() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut scene = build_house(&mut rng);
        let camera = Vec3::new(0.0, -18.0, 2.0);
        let before = scene.faces.len();
        add_clutter(&mut scene, &mut rng, &[camera], 3.0);
        assert!(scene.faces.len() > before + 1000);
        for (face, tag) in scene.faces.iter().zip(&scene.tags) {
            if tag.part != PartKind::Clutter {
                continue;
            }
            for &v in face {
                let p = scene.positions_m[v as usize];
                let horizontal = Vec2::new(p.x - camera.x, p.y - camera.y).length();
                assert!(horizontal > 1.5, "clutter vertex {p} near the camera");
            }
        }
    }
}
