//! The true 3D scene of a synthetic data set: buildings built from solid primitives (walls, gable
//! and hip roofs with overhangs, chimneys, dormers, annexes, porches with posts and railings),
//! window and door panels, the ground, and clutter that the model will never contain (trees,
//! cars, fences, people, bushes).
//!
//! Every face carries a [`FaceTag`] (material, object, panel, part) in arrays of our own, because
//! [`Mesh`] has no attributes. Building parts are also kept as solids with an inside test, from
//! which `degrade.rs` derives the Poisson-like model.

mod buildings;
mod changes;
mod clutter;
mod primitives;

use glam::{Vec2, Vec3};

use super::texture::{GroundLayout, Material, Panel};
use crate::core::mesh::{Mesh, MeshError};
pub use buildings::{build_block, build_house};
pub use changes::{add_change_objects, ChangePlan, ChangeWhat, PlacedChange};
pub use clutter::add_clutter;

/// Which part of the scene a face belongs to; decides what the degraded model keeps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PartKind {
    /// Main building volumes: in the model (smoothed, noisy).
    Building,
    /// Small building parts (chimney, dormer, porch, railings, window frames): in the true model,
    /// missing from the degraded one.
    Detail,
    /// Ground inside the model's patch.
    NearGround,
    /// Ground out to the horizon.
    FarGround,
    /// Trees, cars, fences, people, bushes: only in the photos.
    Clutter,
}

/// No panel for this face.
pub const NO_PANEL: u32 = u32::MAX;

/// The attributes of one face.
#[derive(Clone, Copy, Debug)]
pub struct FaceTag {
    pub material: Material,
    pub object_id: u32,
    pub panel: u32,
    pub part: PartKind,
}

/// Placement of a local frame on the ground: `world = centre + R(yaw) · local.xy`, `z + base`.
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub centre_m: Vec2,
    pub yaw_rad: f32,
    pub base_z_m: f32,
}

impl Frame {
    pub fn to_world(&self, local: Vec3) -> Vec3 {
        let (s, c) = self.yaw_rad.sin_cos();
        Vec3::new(
            self.centre_m.x + c * local.x - s * local.y,
            self.centre_m.y + s * local.x + c * local.y,
            self.base_z_m + local.z,
        )
    }

    pub fn direction_to_world(&self, local: Vec3) -> Vec3 {
        let (s, c) = self.yaw_rad.sin_cos();
        Vec3::new(
            c * local.x - s * local.y,
            s * local.x + c * local.y,
            local.z,
        )
    }

    pub fn to_local(&self, world: Vec3) -> Vec3 {
        let (s, c) = self.yaw_rad.sin_cos();
        let d = Vec2::new(world.x, world.y) - self.centre_m;
        Vec3::new(
            c * d.x + s * d.y,
            -s * d.x + c * d.y,
            world.z - self.base_z_m,
        )
    }
}

/// A solid with an inside test, for the occupancy from which the degraded model is made.
#[derive(Clone, Debug)]
pub enum Solid {
    /// A convex polygon in the local (y, z) plane, extruded along local x over `|x| <= half_length`.
    Prism {
        frame: Frame,
        polygon_yz: Vec<Vec2>,
        half_length_m: f32,
    },
    /// A hip roof: `base <= z <= base + rise_per_m · min(hx - |x|, hy - |y|)`.
    HipRoof {
        frame: Frame,
        half_x_m: f32,
        half_y_m: f32,
        rise_per_m: f32,
    },
}

impl Solid {
    pub fn contains(&self, p: Vec3) -> bool {
        match self {
            Solid::Prism {
                frame,
                polygon_yz,
                half_length_m,
            } => {
                let local = frame.to_local(p);
                if local.x.abs() > *half_length_m {
                    return false;
                }
                let q = Vec2::new(local.y, local.z);
                let n = polygon_yz.len();
                (0..n).all(|i| {
                    let a = polygon_yz[i];
                    let b = polygon_yz[(i + 1) % n];
                    (b - a).perp_dot(q - a) >= 0.0
                })
            }
            Solid::HipRoof {
                frame,
                half_x_m,
                half_y_m,
                rise_per_m,
            } => {
                let local = frame.to_local(p);
                let margin = (half_x_m - local.x.abs()).min(half_y_m - local.y.abs());
                local.z >= 0.0 && margin >= 0.0 && local.z <= rise_per_m * margin
            }
        }
    }

    /// Signed distance bound (negative inside): the largest signed distance to the solid's
    /// bounding planes. Exact on faces and along face normals, an underestimate near outer
    /// corners; its zero level is exactly the solid's surface, and it is linear on each side of
    /// a face, so an iso-surface of it has no voxel terraces.
    pub fn signed_distance_m(&self, p: Vec3) -> f32 {
        match self {
            Solid::Prism {
                frame,
                polygon_yz,
                half_length_m,
            } => {
                let local = frame.to_local(p);
                let q = Vec2::new(local.y, local.z);
                let mut distance = local.x.abs() - half_length_m;
                let n = polygon_yz.len();
                for i in 0..n {
                    let a = polygon_yz[i];
                    let edge = polygon_yz[(i + 1) % n] - a;
                    let outward = Vec2::new(edge.y, -edge.x).normalize_or_zero();
                    distance = distance.max(outward.dot(q - a));
                }
                distance
            }
            Solid::HipRoof {
                frame,
                half_x_m,
                half_y_m,
                rise_per_m,
            } => {
                let local = frame.to_local(p);
                let norm = (1.0 + rise_per_m * rise_per_m).sqrt();
                let slope_x = (local.z + rise_per_m * (local.x.abs() - half_x_m)) / norm;
                let slope_y = (local.z + rise_per_m * (local.y.abs() - half_y_m)) / norm;
                (-local.z).max(slope_x).max(slope_y)
            }
        }
    }

    /// The footprint rectangle's corners in world x, y (exact for a rotated solid), and its two
    /// horizontal sides, metres.
    pub fn footprint_m(&self) -> ([Vec2; 4], (f32, f32)) {
        let (frame, x_range, y_range) = match self {
            Solid::Prism {
                frame,
                polygon_yz,
                half_length_m,
            } => {
                let (y_min, y_max) = polygon_yz
                    .iter()
                    .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), q| {
                        (lo.min(q.x), hi.max(q.x))
                    });
                (frame, (-half_length_m, *half_length_m), (y_min, y_max))
            }
            Solid::HipRoof {
                frame,
                half_x_m,
                half_y_m,
                ..
            } => (frame, (-half_x_m, *half_x_m), (-half_y_m, *half_y_m)),
        };
        let corners = [
            (x_range.0, y_range.0),
            (x_range.1, y_range.0),
            (x_range.1, y_range.1),
            (x_range.0, y_range.1),
        ]
        .map(|(x, y)| {
            let w = frame.to_world(Vec3::new(x, y, 0.0));
            Vec2::new(w.x, w.y)
        });
        (corners, (x_range.1 - x_range.0, y_range.1 - y_range.0))
    }

    /// World-axis bounding box `(min, max)`.
    pub fn bounds_m(&self) -> (Vec3, Vec3) {
        let corners: Vec<Vec3> = match self {
            Solid::Prism {
                frame,
                polygon_yz,
                half_length_m,
            } => polygon_yz
                .iter()
                .flat_map(|q| {
                    [-1.0f32, 1.0].map(|sx| frame.to_world(Vec3::new(sx * half_length_m, q.x, q.y)))
                })
                .collect(),
            Solid::HipRoof {
                frame,
                half_x_m,
                half_y_m,
                rise_per_m,
            } => {
                let top = rise_per_m * half_x_m.min(*half_y_m);
                [(-1.0f32, -1.0f32), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
                    .iter()
                    .flat_map(|&(sx, sy)| {
                        [0.0, top]
                            .map(|z| frame.to_world(Vec3::new(sx * half_x_m, sy * half_y_m, z)))
                    })
                    .collect()
            }
        };
        let mut min = Vec3::splat(f32::INFINITY);
        let mut max = Vec3::splat(f32::NEG_INFINITY);
        for c in corners {
            min = min.min(c);
            max = max.max(c);
        }
        (min, max)
    }
}

/// Footprint of one building, for viewpoint planning, clutter placement and the ground patch.
#[derive(Clone, Copy, Debug)]
pub struct Footprint {
    pub frame: Frame,
    pub half_x_m: f32,
    pub half_y_m: f32,
    /// Highest point (ridge), metres above the ground.
    pub height_m: f32,
}

impl Footprint {
    /// Horizontal distance from a point to the footprint rectangle (0 inside).
    pub fn distance_m(&self, p: Vec2) -> f32 {
        let local = self.frame.to_local(Vec3::new(p.x, p.y, 0.0));
        let dx = (local.x.abs() - self.half_x_m).max(0.0);
        let dy = (local.y.abs() - self.half_y_m).max(0.0);
        (dx * dx + dy * dy).sqrt()
    }
}

/// The whole true scene.
#[derive(Clone, Debug, Default)]
pub struct Scene {
    pub positions_m: Vec<Vec3>,
    pub faces: Vec<[u32; 3]>,
    pub tags: Vec<FaceTag>,
    pub panels: Vec<Panel>,
    /// Solids of the parts the degraded model keeps ([`PartKind::Building`]).
    pub building_solids: Vec<Solid>,
    /// Solids of small parts (for tests and counts).
    pub detail_solids: Vec<Solid>,
    pub footprints: Vec<Footprint>,
    pub ground: GroundLayout,
    /// Half size of the square ground patch of the model around the origin, metres.
    pub ground_patch_half_m: f32,
    /// Axis-aligned box of the chimney above the roof, if the scene has one (for tests).
    pub chimney_bounds_m: Option<(Vec3, Vec3)>,
    next_object_id: u32,
}

impl Scene {
    fn new_object(&mut self) -> u32 {
        self.next_object_id += 1;
        self.next_object_id
    }

    /// Converts the scene (or the faces selected by `keep`) to a [`Mesh`].
    pub fn to_mesh(&self, keep: impl Fn(&FaceTag) -> bool) -> Result<Mesh, MeshError> {
        let mut remap = vec![u32::MAX; self.positions_m.len()];
        let mut positions = Vec::new();
        let mut faces = Vec::new();
        for (face, tag) in self.faces.iter().zip(&self.tags) {
            if !keep(tag) {
                continue;
            }
            faces.push(face.map(|v| {
                let slot = &mut remap[v as usize];
                if *slot == u32::MAX {
                    *slot = positions.len() as u32;
                    let p = self.positions_m[v as usize];
                    positions.push(nalgebra::Vector3::new(
                        f64::from(p.x),
                        f64::from(p.y),
                        f64::from(p.z),
                    ));
                }
                *slot
            }));
        }
        Mesh::from_world(&positions, faces, None)
    }

    /// Horizontal distance from a point to the nearest building footprint.
    pub fn distance_to_buildings_m(&self, p: Vec2) -> f32 {
        self.footprints
            .iter()
            .map(|f| f.distance_m(p))
            .fold(f32::INFINITY, f32::min)
    }
}
