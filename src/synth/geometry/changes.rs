//! Changed objects for `asgreg synth --changes`: new buildings and extensions (they will be in the
//! photos only) and buildings that will be demolished (in the model only), placed on free ground
//! (or against a wall, for an extension) clear of the other buildings and of the cameras. This
//! file only builds their geometry; `synth::changes` decides which scene keeps which object.

use glam::{Vec2, Vec3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::primitives::{add_gable_building, GableBuilding};
use super::{Footprint, Frame, PartKind, Scene};
use crate::synth::texture::Material;

/// What a changed object is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ChangeWhat {
    /// A free-standing new building: in the photos only.
    NewBuilding,
    /// A box built against an existing building's wall: in the photos only.
    Extension,
    /// A free-standing building in the model that is gone from the photos.
    Demolished,
    /// A building part in the photos that the degraded model leaves out by design (a rooftop
    /// structure, a dormer, a porch roof): not placed as a change, but a real difference.
    ModelOmission,
}

impl ChangeWhat {
    /// Whether the object is in the photos (added) rather than in the model (removed).
    pub fn is_added(self) -> bool {
        !matches!(self, ChangeWhat::Demolished)
    }
}

/// One placed changed object.
#[derive(Clone, Debug)]
pub struct PlacedChange {
    pub what: ChangeWhat,
    /// The object id of its faces ([`super::FaceTag::object_id`]).
    pub object_id: u32,
    pub footprint: Footprint,
    /// Indices of its solids in [`Scene::building_solids`].
    pub solid_indices: std::ops::Range<usize>,
}

impl PlacedChange {
    /// The footprint's corners in world coordinates, counter-clockwise.
    pub fn corners_m(&self) -> [Vec2; 4] {
        let f = &self.footprint;
        [(-1.0f32, -1.0f32), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(sx, sy)| {
            let w = f
                .frame
                .to_world(Vec3::new(sx * f.half_x_m, sy * f.half_y_m, 0.0));
            Vec2::new(w.x, w.y)
        })
    }
}

/// How many changed objects of each kind to place, and where free-standing ones may go.
#[derive(Clone, Copy, Debug)]
pub struct ChangePlan {
    pub new_buildings: usize,
    pub extensions: usize,
    pub demolished: usize,
    /// Free-standing objects' centres lie this far from the scene centre, metres.
    pub ring_m: (f32, f32),
    /// Least horizontal distance from a free-standing object to other buildings, metres.
    pub clearance_m: f32,
    /// Least horizontal distance from any object to a camera, metres.
    pub camera_clearance_m: f32,
}

/// Points spread over a footprint rectangle (a 5 × 5 grid incl. the border).
fn footprint_samples(frame: &Frame, half_x_m: f32, half_y_m: f32) -> Vec<Vec2> {
    let mut points = Vec::with_capacity(25);
    for i in 0..5 {
        for j in 0..5 {
            let x = (i as f32 / 4.0 * 2.0 - 1.0) * half_x_m;
            let y = (j as f32 / 4.0 * 2.0 - 1.0) * half_y_m;
            let w = frame.to_world(Vec3::new(x, y, 0.0));
            points.push(Vec2::new(w.x, w.y));
        }
    }
    points
}

fn inside_any_solid(scene: &Scene, p: Vec2, top_m: f32) -> bool {
    [0.3f32, 0.5, 0.8].iter().any(|f| {
        let q = Vec3::new(p.x, p.y, f * top_m);
        scene
            .building_solids
            .iter()
            .chain(&scene.detail_solids)
            .any(|s| s.contains(q))
    })
}

fn clear_of_cameras(points: &[Vec2], eyes_m: &[Vec3], clearance_m: f32) -> bool {
    points.iter().all(|p| {
        eyes_m
            .iter()
            .all(|e| (Vec2::new(e.x, e.y) - *p).length() > clearance_m)
    })
}

/// Places the objects of `plan` into `scene` (faces tagged [`PartKind::Building`], solids,
/// footprints) and returns them; objects that find no free place after many draws are left out.
pub fn add_change_objects(
    scene: &mut Scene,
    plan: &ChangePlan,
    eyes_m: &[Vec3],
    rng: &mut ChaCha8Rng,
) -> Vec<PlacedChange> {
    let mut placed = Vec::new();
    let free_standing = std::iter::repeat_n(ChangeWhat::NewBuilding, plan.new_buildings)
        .chain(std::iter::repeat_n(ChangeWhat::Demolished, plan.demolished));
    for what in free_standing {
        for _attempt in 0..400 {
            let angle = rng.random_range(0.0..std::f32::consts::TAU);
            let radius = rng.random_range(plan.ring_m.0..plan.ring_m.1);
            let frame = Frame {
                centre_m: Vec2::new(angle.cos(), angle.sin()) * radius,
                yaw_rad: rng.random_range(-0.6..0.6f32),
                base_z_m: 0.0,
            };
            let half_x = rng.random_range(1.7..3.2f32);
            let half_y = rng.random_range(1.6..2.6f32);
            let samples = footprint_samples(&frame, half_x, half_y);
            if samples
                .iter()
                .any(|p| scene.distance_to_buildings_m(*p) < plan.clearance_m)
                || !clear_of_cameras(&samples, eyes_m, plan.camera_clearance_m)
                || samples.iter().any(|p| {
                    p.x.abs() > scene.ground_patch_half_m - 2.0
                        || p.y.abs() > scene.ground_patch_half_m - 2.0
                })
            {
                continue;
            }
            let wall_height = rng.random_range(2.6..4.2f32);
            let rise = rng.random_range(1.0..1.8f32);
            placed.push(add_small_building(
                scene,
                what,
                frame,
                half_x,
                half_y,
                wall_height,
                rise,
                rng,
            ));
            break;
        }
    }
    for _ in 0..plan.extensions {
        if scene.footprints.is_empty() {
            break;
        }
        for _attempt in 0..400 {
            let parent = scene.footprints[rng.random_range(0..scene.footprints.len())];
            if parent.height_m < 5.0 {
                continue;
            }
            // Side of the parent: outward direction in its frame.
            let side = rng.random_range(0..4u32);
            let width = rng.random_range(3.2..5.0f32);
            let depth = rng.random_range(3.0..4.2f32);
            let (along_half, offset) = match side {
                0 | 1 => (parent.half_x_m, parent.half_y_m),
                _ => (parent.half_y_m, parent.half_x_m),
            };
            if width * 0.5 > along_half - 0.3 {
                continue;
            }
            let along = rng.random_range(-(along_half - width * 0.5)..=(along_half - width * 0.5));
            let distance = offset + 0.02 + depth * 0.5;
            let (local_centre, half_x, half_y) = match side {
                0 => (Vec2::new(along, -distance), width * 0.5, depth * 0.5),
                1 => (Vec2::new(along, distance), width * 0.5, depth * 0.5),
                2 => (Vec2::new(-distance, along), depth * 0.5, width * 0.5),
                _ => (Vec2::new(distance, along), depth * 0.5, width * 0.5),
            };
            let centre = parent
                .frame
                .to_world(Vec3::new(local_centre.x, local_centre.y, 0.0));
            let frame = Frame {
                centre_m: Vec2::new(centre.x, centre.y),
                yaw_rad: parent.frame.yaw_rad,
                base_z_m: 0.0,
            };
            let height = rng.random_range(2.8..3.6f32);
            let samples = footprint_samples(&frame, half_x, half_y);
            let others_clear = scene
                .footprints
                .iter()
                .filter(|f| f.frame.centre_m != parent.frame.centre_m)
                .all(|f| samples.iter().all(|p| f.distance_m(*p) > 1.0));
            if !others_clear
                || samples.iter().any(|p| inside_any_solid(scene, *p, height))
                || !clear_of_cameras(&samples, eyes_m, plan.camera_clearance_m)
            {
                continue;
            }
            let object_id = scene.new_object();
            let first_solid = scene.building_solids.len();
            scene.add_box(
                frame,
                Vec3::new(-half_x, -half_y, 0.0),
                Vec3::new(half_x, half_y, height),
                Material::Plaster {
                    palette: rng.random_range(0..4),
                },
                Material::FlatRoof,
                PartKind::Building,
                object_id,
            );
            let footprint = Footprint {
                frame,
                half_x_m: half_x,
                half_y_m: half_y,
                height_m: height,
            };
            scene.footprints.push(footprint);
            placed.push(PlacedChange {
                what: ChangeWhat::Extension,
                object_id,
                footprint,
                solid_indices: first_solid..scene.building_solids.len(),
            });
            break;
        }
    }
    placed
}

/// A small gable-roofed (or flat-roofed) building on `frame`.
#[allow(clippy::too_many_arguments)]
fn add_small_building(
    scene: &mut Scene,
    what: ChangeWhat,
    frame: Frame,
    half_x_m: f32,
    half_y_m: f32,
    wall_height_m: f32,
    rise_m: f32,
    rng: &mut ChaCha8Rng,
) -> PlacedChange {
    let first_solid = scene.building_solids.len();
    let wall_material = if rng.random_bool(0.5) {
        Material::Brick {
            palette: rng.random_range(0..3),
        }
    } else {
        Material::Plaster {
            palette: rng.random_range(0..4),
        }
    };
    let flat = rng.random_bool(0.4);
    let (object_id, height_m) = if flat {
        let object_id = scene.new_object();
        scene.add_box(
            frame,
            Vec3::new(-half_x_m, -half_y_m, 0.0),
            Vec3::new(half_x_m, half_y_m, wall_height_m),
            wall_material,
            Material::FlatRoof,
            PartKind::Building,
            object_id,
        );
        (object_id, wall_height_m)
    } else {
        add_gable_building(
            scene,
            &GableBuilding {
                frame,
                half_x_m,
                half_y_m,
                wall_height_m,
                roof_rise_m: rise_m,
                eave_overhang_m: 0.3,
                gable_overhang_m: 0.2,
                roof_thickness_m: 0.25,
                wall_material,
                roof_material: Material::RoofTile {
                    palette: rng.random_range(0..3),
                },
            },
        );
        (scene.next_object_id, wall_height_m + rise_m)
    };
    let footprint = Footprint {
        frame,
        half_x_m,
        half_y_m,
        height_m,
    };
    scene.footprints.push(footprint);
    PlacedChange {
        what,
        object_id,
        footprint,
        solid_indices: first_solid..scene.building_solids.len(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::geometry::build_house;
    use rand::SeedableRng;

    #[test]
    fn objects_are_placed_on_free_ground_with_their_own_faces_and_solids() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut scene = build_house(&mut rng);
        let buildings_before = scene.footprints.clone();
        let plan = ChangePlan {
            new_buildings: 1,
            extensions: 1,
            demolished: 1,
            ring_m: (9.0, 14.0),
            clearance_m: 1.5,
            camera_clearance_m: 3.0,
        };
        let placed = add_change_objects(&mut scene, &plan, &[], &mut rng);
        assert_eq!(placed.len(), 3, "{placed:?}");
        for change in &placed {
            assert!(
                change.footprint.half_x_m * 2.0 >= 3.0 && change.footprint.half_y_m * 2.0 >= 3.0
            );
            assert!(!change.solid_indices.is_empty());
            let faces = scene
                .tags
                .iter()
                .filter(|t| t.object_id == change.object_id)
                .count();
            assert!(faces >= 6, "{:?}: {faces} faces", change.what);
            if change.what != ChangeWhat::Extension {
                let c = change.footprint.frame.centre_m;
                assert!(buildings_before.iter().all(|f| f.distance_m(c) > 1.5));
            }
        }
    }
}
