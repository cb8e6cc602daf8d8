//! The true 3D scene of a synthetic data set: buildings built from solid primitives (walls, gable
//! and hip roofs with overhangs, chimneys, dormers, annexes, porches with posts and railings),
//! window and door panels, the ground, and clutter that the model will never contain (trees,
//! cars, fences, people, bushes).
//!
//! Every face carries a [`FaceTag`] (material, object, panel, part) in arrays of our own, because
//! [`Mesh`] has no attributes. Building parts are also kept as solids with an inside test, from
//! which `degrade.rs` derives the Poisson-like model.

use glam::{Vec2, Vec3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::texture::{fbm, GroundLayout, Material, Panel, PanelKind};
use crate::core::mesh::{Mesh, MeshError};

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

    /// Adds a convex polygon (fan), oriented so its normal points along `outward` when given.
    fn add_polygon(&mut self, corners: &[Vec3], tag: FaceTag, outward: Option<Vec3>) {
        if corners.len() < 3 {
            return;
        }
        let normal = (corners[1] - corners[0]).cross(corners[2] - corners[0]);
        let flip = outward.is_some_and(|o| normal.dot(o) < 0.0);
        let base = self.positions_m.len() as u32;
        self.positions_m.extend_from_slice(corners);
        for i in 1..corners.len() as u32 - 1 {
            let face = if flip {
                [base, base + i + 1, base + i]
            } else {
                [base, base + i, base + i + 1]
            };
            self.faces.push(face);
            self.tags.push(tag);
        }
    }

    /// Adds a convex solid given by its faces (lists of corners), oriented outwards from `centre`.
    fn add_convex_faces(&mut self, faces: &[(Vec<Vec3>, FaceTag)], centre: Vec3) {
        for (corners, tag) in faces {
            let face_centre = corners.iter().copied().sum::<Vec3>() / corners.len() as f32;
            self.add_polygon(corners, *tag, Some(face_centre - centre));
        }
    }

    /// Adds a prism solid (convex polygon in local (y, z), extruded along local x) with one material
    /// per polygon edge and one for both caps.
    #[allow(clippy::too_many_arguments)]
    fn add_prism(
        &mut self,
        frame: Frame,
        polygon_yz: &[Vec2],
        half_length_m: f32,
        edge_materials: &[Material],
        cap_material: Material,
        part: PartKind,
        object_id: u32,
    ) {
        let tag = |material| FaceTag {
            material,
            object_id,
            panel: NO_PANEL,
            part,
        };
        let at = |x: f32, q: Vec2| frame.to_world(Vec3::new(x, q.x, q.y));
        let centroid_yz = polygon_yz.iter().copied().sum::<Vec2>() / polygon_yz.len() as f32;
        let centre = at(0.0, centroid_yz);
        let n = polygon_yz.len();
        let mut faces = Vec::with_capacity(n + 2);
        for i in 0..n {
            let a = polygon_yz[i];
            let b = polygon_yz[(i + 1) % n];
            let material = edge_materials
                .get(i)
                .copied()
                .unwrap_or(edge_materials.last().copied().unwrap_or(cap_material));
            faces.push((
                vec![
                    at(-half_length_m, a),
                    at(half_length_m, a),
                    at(half_length_m, b),
                    at(-half_length_m, b),
                ],
                tag(material),
            ));
        }
        for x in [-half_length_m, half_length_m] {
            faces.push((
                polygon_yz.iter().map(|&q| at(x, q)).collect(),
                tag(cap_material),
            ));
        }
        self.add_convex_faces(&faces, centre);
        let solid = Solid::Prism {
            frame,
            polygon_yz: polygon_yz.to_vec(),
            half_length_m,
        };
        match part {
            PartKind::Building => self.building_solids.push(solid),
            PartKind::Detail => self.detail_solids.push(solid),
            _ => {}
        }
    }

    /// An axis-aligned (in the frame) box from `min` to `max` local corners.
    #[allow(clippy::too_many_arguments)]
    fn add_box(
        &mut self,
        frame: Frame,
        min: Vec3,
        max: Vec3,
        side_material: Material,
        top_material: Material,
        part: PartKind,
        object_id: u32,
    ) {
        let centre_x = (min.x + max.x) * 0.5;
        let box_frame = Frame {
            centre_m: {
                let c = frame.to_world(Vec3::new(centre_x, 0.0, 0.0));
                Vec2::new(c.x, c.y)
            },
            ..frame
        };
        // Polygon in (y, z), counter-clockwise: bottom, right side, top, left side.
        let polygon = [
            Vec2::new(min.y, min.z),
            Vec2::new(max.y, min.z),
            Vec2::new(max.y, max.z),
            Vec2::new(min.y, max.z),
        ];
        self.add_prism(
            box_frame,
            &polygon,
            (max.x - min.x) * 0.5,
            &[side_material, side_material, top_material, side_material],
            side_material,
            part,
            object_id,
        );
    }

    /// A vertical or tilted cylinder (no caps needed for trunks; wheels get caps).
    #[allow(clippy::too_many_arguments)]
    fn add_cylinder(
        &mut self,
        base: Vec3,
        axis: Vec3,
        radius_m: f32,
        segments: u32,
        material: Material,
        caps: bool,
        object_id: u32,
    ) {
        let tag = FaceTag {
            material,
            object_id,
            panel: NO_PANEL,
            part: PartKind::Clutter,
        };
        let direction = axis.normalize_or_zero();
        let helper = if direction.z.abs() < 0.9 {
            Vec3::Z
        } else {
            Vec3::X
        };
        let e1 = direction.cross(helper).normalize_or_zero();
        let e2 = direction.cross(e1);
        let ring = |t: f32| -> Vec<Vec3> {
            (0..segments)
                .map(|i| {
                    let angle = i as f32 / segments as f32 * std::f32::consts::TAU;
                    base + axis * t + (e1 * angle.cos() + e2 * angle.sin()) * radius_m
                })
                .collect()
        };
        let bottom = ring(0.0);
        let top = ring(1.0);
        let centre = base + axis * 0.5;
        let mut faces = Vec::new();
        for i in 0..segments as usize {
            let j = (i + 1) % segments as usize;
            faces.push((vec![bottom[i], bottom[j], top[j], top[i]], tag));
        }
        if caps {
            faces.push((bottom.clone(), tag));
            faces.push((top.clone(), tag));
        }
        self.add_convex_faces(&faces, centre);
    }

    /// An irregular blob (crown, bush): a subdivided octahedron displaced by noise, scaled.
    #[allow(clippy::too_many_arguments)]
    fn add_blob(
        &mut self,
        centre: Vec3,
        radii_m: Vec3,
        roughness: f32,
        subdivisions: u32,
        material: Material,
        noise_seed: u64,
        object_id: u32,
    ) {
        let tag = FaceTag {
            material,
            object_id,
            panel: NO_PANEL,
            part: PartKind::Clutter,
        };
        let (unit_positions, faces) = unit_sphere(subdivisions);
        let base = self.positions_m.len() as u32;
        for d in &unit_positions {
            let bump = fbm(noise_seed, *d * 2.5, 1.0, 3, 0.0)
                + 0.6 * fbm(noise_seed ^ 9, *d * 7.0, 1.0, 2, 0.0);
            let scale = (1.0 + roughness * 2.0 * bump).max(0.3);
            self.positions_m.push(centre + *d * radii_m * scale);
        }
        for f in faces {
            self.faces.push(f.map(|v| v + base));
            self.tags.push(tag);
        }
    }

    /// A window, door or garage door on a wall: a quad just in front of the wall, plus a sill
    /// under windows. `wall_frame` is the building frame, `outward_local` the wall's outward
    /// normal in it, `wall_offset_m` the wall plane's distance from the frame centre along it,
    /// `along_centre_m` the opening's centre along the wall (local coordinate).
    #[allow(clippy::too_many_arguments)]
    fn add_opening(
        &mut self,
        wall_frame: Frame,
        outward_local: Vec2,
        wall_offset_m: f32,
        along_centre_m: f32,
        bottom_m: f32,
        width_m: f32,
        height_m: f32,
        kind: PanelKind,
        style: u32,
    ) {
        let n_local = Vec3::new(outward_local.x, outward_local.y, 0.0);
        let u_local = Vec3::new(-outward_local.y, outward_local.x, 0.0);
        let origin_local = n_local * (wall_offset_m + 0.03)
            + u_local * (along_centre_m - width_m * 0.5)
            + Vec3::Z * bottom_m;
        let origin = wall_frame.to_world(origin_local);
        let u_axis = wall_frame.direction_to_world(u_local);
        let v_axis = Vec3::Z;
        let panel_index = self.panels.len() as u32;
        self.panels.push(Panel {
            origin_m: origin,
            u_axis,
            v_axis,
            width_m,
            height_m,
            kind,
            style,
        });
        let object_id = self.new_object();
        let corners = [
            origin,
            origin + u_axis * width_m,
            origin + u_axis * width_m + v_axis * height_m,
            origin + v_axis * height_m,
        ];
        self.add_polygon(
            &corners,
            FaceTag {
                material: Material::Opening,
                object_id,
                panel: panel_index,
                part: PartKind::Detail,
            },
            Some(wall_frame.direction_to_world(n_local)),
        );
        if matches!(kind, PanelKind::Window { .. }) {
            // Sill: 8 cm out from the wall, 6 cm thick, a little wider than the window.
            let sill_centre = n_local * (wall_offset_m + 0.04) + u_local * along_centre_m;
            let sill_frame = Frame {
                centre_m: {
                    let c = wall_frame.to_world(sill_centre);
                    Vec2::new(c.x, c.y)
                },
                yaw_rad: wall_frame.yaw_rad + outward_local.y.atan2(outward_local.x),
                base_z_m: wall_frame.base_z_m,
            };
            // In the sill frame, local x is the outward normal and y runs along the wall.
            self.add_box(
                sill_frame,
                Vec3::new(-0.05, -width_m * 0.5 - 0.05, bottom_m - 0.06),
                Vec3::new(0.05, width_m * 0.5 + 0.05, bottom_m),
                Material::Concrete,
                Material::Concrete,
                PartKind::Detail,
                object_id,
            );
        }
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

/// Unit sphere from a subdivided octahedron: `(vertices, faces)` with outward winding.
fn unit_sphere(subdivisions: u32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let mut vertices = vec![Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z];
    let mut faces: Vec<[u32; 3]> = vec![
        [0, 2, 4],
        [2, 1, 4],
        [1, 3, 4],
        [3, 0, 4],
        [2, 0, 5],
        [1, 2, 5],
        [3, 1, 5],
        [0, 3, 5],
    ];
    for _ in 0..subdivisions {
        let mut midpoints = std::collections::HashMap::new();
        let mut midpoint = |a: u32, b: u32, vertices: &mut Vec<Vec3>| {
            let key = (a.min(b), a.max(b));
            *midpoints.entry(key).or_insert_with(|| {
                vertices.push(((vertices[a as usize] + vertices[b as usize]) * 0.5).normalize());
                vertices.len() as u32 - 1
            })
        };
        let mut next = Vec::with_capacity(faces.len() * 4);
        for [a, b, c] in faces {
            let ab = midpoint(a, b, &mut vertices);
            let bc = midpoint(b, c, &mut vertices);
            let ca = midpoint(c, a, &mut vertices);
            next.extend_from_slice(&[[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
        }
        faces = next;
    }
    (vertices, faces)
}

/// Parameters of one gabled building volume.
struct GableBuilding {
    frame: Frame,
    half_x_m: f32,
    half_y_m: f32,
    wall_height_m: f32,
    roof_rise_m: f32,
    eave_overhang_m: f32,
    gable_overhang_m: f32,
    roof_thickness_m: f32,
    wall_material: Material,
    roof_material: Material,
}

/// Adds walls, gable infill and the roof slab (ridge along local x) as building solids.
fn add_gable_building(scene: &mut Scene, building: &GableBuilding) {
    let object_id = scene.new_object();
    let b = building;
    scene.add_box(
        b.frame,
        Vec3::new(-b.half_x_m, -b.half_y_m, 0.0),
        Vec3::new(b.half_x_m, b.half_y_m, b.wall_height_m),
        b.wall_material,
        b.wall_material,
        PartKind::Building,
        object_id,
    );
    let ridge_z = b.wall_height_m + b.roof_rise_m;
    // Gable infill (triangle in y-z, extruded along x).
    scene.add_prism(
        b.frame,
        &[
            Vec2::new(-b.half_y_m, b.wall_height_m),
            Vec2::new(b.half_y_m, b.wall_height_m),
            // Below the roof slab's top surface (not coplanar with it: no z-fighting).
            Vec2::new(0.0, ridge_z - b.roof_thickness_m * 0.5),
        ],
        b.half_x_m,
        &[b.wall_material],
        b.wall_material,
        PartKind::Building,
        object_id,
    );
    // Roof slabs: two convex quads (one per slope) extended by the overhangs.
    let slope = b.roof_rise_m / b.half_y_m;
    let eave_y = b.half_y_m + b.eave_overhang_m;
    let eave_z = b.wall_height_m - b.eave_overhang_m * slope;
    let t = b.roof_thickness_m;
    for side in [-1.0f32, 1.0] {
        let mut polygon = vec![
            Vec2::new(0.0, ridge_z - t),
            Vec2::new(side * eave_y, eave_z - t),
            Vec2::new(side * eave_y, eave_z),
            Vec2::new(0.0, ridge_z),
        ];
        if side < 0.0 {
            polygon.reverse();
        }
        // Counter-clockwise in (y, z): make sure of it.
        let area: f32 = (0..4)
            .map(|i| polygon[i].perp_dot(polygon[(i + 1) % 4]))
            .sum();
        if area < 0.0 {
            polygon.reverse();
        }
        let materials: Vec<Material> = (0..4)
            .map(|i| {
                let a = polygon[i];
                let c = polygon[(i + 1) % 4];
                let mid = (a + c) * 0.5;
                let edge_normal = Vec2::new(c.y - a.y, a.x - c.x);
                if edge_normal.y > 0.3 && mid.y > eave_z - t * 0.5 {
                    b.roof_material
                } else {
                    Material::Soffit
                }
            })
            .collect();
        scene.add_prism(
            b.frame,
            &polygon,
            b.half_x_m + b.gable_overhang_m,
            &materials,
            Material::Soffit,
            PartKind::Building,
            object_id,
        );
    }
}

/// Adds a hip roof (with a thin eave slab under it) on top of walls.
#[allow(clippy::too_many_arguments)]
fn add_hip_building(
    scene: &mut Scene,
    frame: Frame,
    half_x_m: f32,
    half_y_m: f32,
    wall_height_m: f32,
    rise_per_m: f32,
    overhang_m: f32,
    wall_material: Material,
    roof_material: Material,
) {
    let object_id = scene.new_object();
    scene.add_box(
        frame,
        Vec3::new(-half_x_m, -half_y_m, 0.0),
        Vec3::new(half_x_m, half_y_m, wall_height_m),
        wall_material,
        wall_material,
        PartKind::Building,
        object_id,
    );
    let roof_frame = Frame {
        base_z_m: frame.base_z_m + wall_height_m - overhang_m * rise_per_m,
        ..frame
    };
    let hx = half_x_m + overhang_m;
    let hy = half_y_m + overhang_m;
    let ridge_half = (hx - hy).max(0.0);
    let top = rise_per_m * hx.min(hy);
    let tag = |material| FaceTag {
        material,
        object_id,
        panel: NO_PANEL,
        part: PartKind::Building,
    };
    let at = |x: f32, y: f32, z: f32| roof_frame.to_world(Vec3::new(x, y, z));
    let (r0, r1) = if hx >= hy {
        (at(-ridge_half, 0.0, top), at(ridge_half, 0.0, top))
    } else {
        let ridge_half_y = hy - hx;
        (at(0.0, -ridge_half_y, top), at(0.0, ridge_half_y, top))
    };
    let c00 = at(-hx, -hy, 0.0);
    let c10 = at(hx, -hy, 0.0);
    let c11 = at(hx, hy, 0.0);
    let c01 = at(-hx, hy, 0.0);
    let centre = at(0.0, 0.0, top * 0.3);
    let roof = tag(roof_material);
    let faces = if hx >= hy {
        vec![
            (vec![c00, c10, r1, r0], roof),
            (vec![c11, c01, r0, r1], roof),
            (vec![c10, c11, r1], roof),
            (vec![c01, c00, r0], roof),
            (vec![c00, c01, c11, c10], tag(Material::Soffit)),
        ]
    } else {
        vec![
            (vec![c10, c11, r1, r0], roof),
            (vec![c01, c00, r0, r1], roof),
            (vec![c00, c10, r0], roof),
            (vec![c11, c01, r1], roof),
            (vec![c00, c01, c11, c10], tag(Material::Soffit)),
        ]
    };
    scene.add_convex_faces(&faces, centre);
    scene.building_solids.push(Solid::HipRoof {
        frame: roof_frame,
        half_x_m: hx,
        half_y_m: hy,
        rise_per_m,
    });
}

/// Adds rows of windows on the four walls of a box building.
#[allow(clippy::too_many_arguments)]
fn add_facade_windows(
    scene: &mut Scene,
    rng: &mut ChaCha8Rng,
    frame: Frame,
    half_x_m: f32,
    half_y_m: f32,
    storeys: u32,
    storey_height_m: f32,
    skip_front_centre: bool,
    style: u32,
) {
    let window_width = rng.random_range(1.0..1.4f32);
    let window_height = rng.random_range(1.2..1.5f32);
    let columns = if window_width > 1.2 { 2 } else { 1 };
    let kind = PanelKind::Window { columns, rows: 2 };
    for (outward, half_along, offset) in [
        (Vec2::new(0.0, -1.0), half_x_m, half_y_m),
        (Vec2::new(0.0, 1.0), half_x_m, half_y_m),
        (Vec2::new(1.0, 0.0), half_y_m, half_x_m),
        (Vec2::new(-1.0, 0.0), half_y_m, half_x_m),
    ] {
        let spacing = rng.random_range(2.4..3.2f32);
        let count = ((2.0 * half_along - 1.0) / spacing).floor().max(1.0) as i32;
        for storey in 0..storeys {
            let bottom = storey as f32 * storey_height_m + 0.9;
            for i in 0..count {
                let along = (i as f32 - (count - 1) as f32 * 0.5) * spacing;
                let is_front = outward.y < -0.5;
                if skip_front_centre && is_front && storey == 0 && along.abs() < spacing * 0.6 {
                    continue;
                }
                scene.add_opening(
                    frame,
                    outward,
                    offset,
                    along,
                    bottom,
                    window_width,
                    window_height,
                    kind,
                    style,
                );
            }
        }
    }
}

/// The single free-standing house of the paper's experiment (≈ 10 × 8 m, gable roof with
/// overhang, chimney, dormer, garage annex, porch with posts and railing).
pub fn build_house(rng: &mut ChaCha8Rng) -> Scene {
    let mut scene = Scene {
        ground_patch_half_m: 16.0,
        ..Scene::default()
    };
    let yaw = rng.random_range(-0.3..0.3f32);
    let frame = Frame {
        centre_m: Vec2::ZERO,
        yaw_rad: yaw,
        base_z_m: 0.0,
    };
    let half_x = rng.random_range(4.6..5.4f32);
    let half_y = rng.random_range(3.7..4.3f32);
    let wall_height = rng.random_range(5.4..6.0f32);
    let rise = rng.random_range(2.8..3.6f32);
    let brick_palette = rng.random_range(0..3u8);
    let plaster_palette = rng.random_range(0..4u8);
    let roof_palette = rng.random_range(0..3u8);
    let main_wall = if rng.random_bool(0.5) {
        Material::Brick {
            palette: brick_palette,
        }
    } else {
        Material::Plaster {
            palette: plaster_palette,
        }
    };
    let roof = Material::RoofTile {
        palette: roof_palette,
    };
    add_gable_building(
        &mut scene,
        &GableBuilding {
            frame,
            half_x_m: half_x,
            half_y_m: half_y,
            wall_height_m: wall_height,
            roof_rise_m: rise,
            eave_overhang_m: 0.55,
            gable_overhang_m: 0.35,
            roof_thickness_m: 0.3,
            wall_material: main_wall,
            roof_material: roof,
        },
    );
    scene.footprints.push(Footprint {
        frame,
        half_x_m: half_x,
        half_y_m: half_y,
        height_m: wall_height + rise,
    });
    let style = rng.random_range(0..3u32);
    add_facade_windows(
        &mut scene,
        rng,
        frame,
        half_x,
        half_y,
        2,
        wall_height * 0.5,
        true,
        style,
    );
    // Attic windows in the gables.
    for outward in [Vec2::new(1.0, 0.0), Vec2::new(-1.0, 0.0)] {
        scene.add_opening(
            frame,
            outward,
            half_x,
            0.0,
            wall_height + 0.4,
            0.9,
            1.0,
            PanelKind::Window {
                columns: 1,
                rows: 1,
            },
            style,
        );
    }
    // Front door (front = local -y).
    scene.add_opening(
        frame,
        Vec2::new(0.0, -1.0),
        half_y,
        0.0,
        0.0,
        1.05,
        2.15,
        PanelKind::Door,
        style,
    );

    // Garage annex on the +x side: lower gable roof with its ridge along local y.
    let annex_half_x = rng.random_range(1.8..2.3f32);
    let annex_half_y = rng.random_range(2.8..3.3f32);
    let annex_centre_local = Vec3::new(half_x + annex_half_x, -half_y + annex_half_y + 0.2, 0.0);
    let annex_centre = frame.to_world(annex_centre_local);
    let annex_frame = Frame {
        centre_m: Vec2::new(annex_centre.x, annex_centre.y),
        yaw_rad: yaw + std::f32::consts::FRAC_PI_2,
        base_z_m: 0.0,
    };
    let annex_wall = Material::Plaster {
        palette: (plaster_palette + 1) % 4,
    };
    add_gable_building(
        &mut scene,
        &GableBuilding {
            frame: annex_frame,
            // Ridge along the annex frame's x = the house's y.
            half_x_m: annex_half_y,
            half_y_m: annex_half_x,
            wall_height_m: 2.9,
            roof_rise_m: 1.3,
            eave_overhang_m: 0.35,
            gable_overhang_m: 0.25,
            roof_thickness_m: 0.3,
            wall_material: annex_wall,
            roof_material: roof,
        },
    );
    scene.footprints.push(Footprint {
        frame: annex_frame,
        half_x_m: annex_half_y,
        half_y_m: annex_half_x,
        height_m: 4.2,
    });
    // Garage door on the annex's front (house -y = annex frame -x).
    scene.add_opening(
        annex_frame,
        Vec2::new(-1.0, 0.0),
        annex_half_y,
        0.0,
        0.0,
        2.6,
        2.2,
        PanelKind::GarageDoor,
        style,
    );
    scene.add_opening(
        annex_frame,
        Vec2::new(0.0, 1.0),
        annex_half_x,
        0.0,
        1.0,
        0.9,
        0.9,
        PanelKind::Window {
            columns: 1,
            rows: 1,
        },
        style,
    );

    // Chimney: through the roof near one gable, on the back slope.
    let detail_id = scene.new_object();
    let chimney_x = -half_x * 0.55;
    let chimney_y = half_y * 0.35;
    let ridge_z = wall_height + rise;
    let chimney_top = ridge_z + 0.9;
    let chimney_min = Vec3::new(chimney_x - 0.3, chimney_y - 0.3, wall_height);
    let chimney_max = Vec3::new(chimney_x + 0.3, chimney_y + 0.3, chimney_top);
    scene.add_box(
        frame,
        chimney_min,
        chimney_max,
        Material::Brick {
            palette: (brick_palette + 2) % 3,
        },
        Material::Concrete,
        PartKind::Detail,
        detail_id,
    );
    let roof_z_at_chimney = ridge_z - (chimney_y - 0.3) / half_y * rise;
    {
        let a = frame.to_world(Vec3::new(
            chimney_x - 0.3,
            chimney_y - 0.3,
            roof_z_at_chimney,
        ));
        let b = frame.to_world(Vec3::new(chimney_x + 0.3, chimney_y + 0.3, chimney_top));
        scene.chimney_bounds_m = Some((a.min(b).with_z(roof_z_at_chimney + 0.35), a.max(b)));
    }

    // Dormer on the front slope: a box with a small gable roof and a window.
    let dormer_half = 0.8;
    let dormer_y = -half_y * 0.45;
    let dormer_floor = ridge_z - (half_y * 0.45 + 0.9) / half_y * rise;
    let dormer_top = dormer_floor + 1.5;
    let dormer_x = half_x * 0.35;
    scene.add_box(
        frame,
        Vec3::new(dormer_x - dormer_half, dormer_y - 0.9, dormer_floor),
        Vec3::new(dormer_x + dormer_half, dormer_y + 1.0, dormer_top),
        main_wall,
        main_wall,
        PartKind::Detail,
        detail_id,
    );
    let dormer_frame = Frame {
        centre_m: {
            let c = frame.to_world(Vec3::new(dormer_x, dormer_y, 0.0));
            Vec2::new(c.x, c.y)
        },
        yaw_rad: yaw + std::f32::consts::FRAC_PI_2,
        base_z_m: 0.0,
    };
    for side in [-1.0f32, 1.0] {
        let mut polygon = vec![
            Vec2::new(0.0, dormer_top + 0.6),
            Vec2::new(side * (dormer_half + 0.2), dormer_top - 0.1),
            Vec2::new(side * (dormer_half + 0.2), dormer_top + 0.05),
            Vec2::new(0.0, dormer_top + 0.75),
        ];
        let area: f32 = (0..4)
            .map(|i| polygon[i].perp_dot(polygon[(i + 1) % 4]))
            .sum();
        if area < 0.0 {
            polygon.reverse();
        }
        scene.add_prism(
            dormer_frame,
            &polygon,
            1.0,
            &[roof],
            Material::Soffit,
            PartKind::Detail,
            detail_id,
        );
    }
    scene.add_opening(
        frame,
        Vec2::new(0.0, -1.0),
        -dormer_y + 0.9,
        dormer_x,
        dormer_floor + 0.3,
        0.9,
        0.9,
        PanelKind::Window {
            columns: 1,
            rows: 2,
        },
        style,
    );

    // Porch in front of the door: slab, two posts, a thin roof, a railing.
    let porch_depth = 1.6;
    let porch_half_w = 1.4;
    scene.add_box(
        frame,
        Vec3::new(-porch_half_w, -half_y - porch_depth, 0.0),
        Vec3::new(porch_half_w, -half_y, 0.18),
        Material::Concrete,
        Material::Concrete,
        PartKind::Detail,
        detail_id,
    );
    for px in [-porch_half_w + 0.1, porch_half_w - 0.1] {
        scene.add_box(
            frame,
            Vec3::new(px - 0.07, -half_y - porch_depth + 0.03, 0.18),
            Vec3::new(px + 0.07, -half_y - porch_depth + 0.17, 2.55),
            Material::Soffit,
            Material::Soffit,
            PartKind::Detail,
            detail_id,
        );
    }
    scene.add_box(
        frame,
        Vec3::new(-porch_half_w - 0.1, -half_y - porch_depth - 0.1, 2.55),
        Vec3::new(porch_half_w + 0.1, -half_y, 2.67),
        Material::Soffit,
        roof,
        PartKind::Detail,
        detail_id,
    );
    for side in [-1.0f32, 1.0] {
        let x = side * (porch_half_w - 0.1);
        scene.add_box(
            frame,
            Vec3::new(x.min(x - side * 0.04), -half_y - porch_depth + 0.05, 0.9),
            Vec3::new(x.max(x - side * 0.04), -half_y - 0.05, 0.96),
            Material::Soffit,
            Material::Soffit,
            PartKind::Detail,
            detail_id,
        );
        for k in 0..6 {
            let y = -half_y - porch_depth + 0.1 + k as f32 * (porch_depth - 0.2) / 5.0;
            scene.add_box(
                frame,
                Vec3::new(x - 0.02, y - 0.02, 0.18),
                Vec3::new(x + 0.02, y + 0.02, 0.9),
                Material::Soffit,
                Material::Soffit,
                PartKind::Detail,
                detail_id,
            );
        }
    }

    // Ground: road in front, driveway to the garage, gravel path to the door, patio at the back.
    let road_y = -half_y - rng.random_range(9.0..12.0f32);
    let to_xy = |local: Vec3| {
        let w = frame.to_world(local);
        Vec2::new(w.x, w.y)
    };
    scene.ground.asphalt.push((
        to_xy(Vec3::new(-200.0, road_y, 0.0)),
        to_xy(Vec3::new(200.0, road_y, 0.0)),
        3.2,
    ));
    scene.ground.asphalt.push((
        to_xy(annex_centre_local - Vec3::new(0.0, annex_half_y, 0.0)),
        to_xy(Vec3::new(annex_centre_local.x, road_y, 0.0)),
        1.6,
    ));
    scene.ground.gravel.push((
        to_xy(Vec3::new(0.0, -half_y - porch_depth, 0.0)),
        to_xy(Vec3::new(0.0, road_y, 0.0)),
        0.6,
    ));
    scene.ground.concrete.push((
        to_xy(Vec3::new(-half_x * 0.5, half_y + 1.5, 0.0)),
        to_xy(Vec3::new(half_x * 0.3, half_y + 1.5, 0.0)),
        1.5,
    ));
    scene.ground.concrete.push((
        to_xy(Vec3::new(-100.0, road_y - 4.2, 0.0)),
        to_xy(Vec3::new(100.0, road_y - 4.2, 0.0)),
        0.9,
    ));
    add_ground(&mut scene);
    scene
}

/// A block of several buildings (flat, gable and hip roofs) on a street grid.
pub fn build_block(rng: &mut ChaCha8Rng) -> Scene {
    let mut scene = Scene {
        ground_patch_half_m: 45.0,
        ..Scene::default()
    };
    const SPACING_M: f32 = 26.0;
    for gx in -1..=1 {
        for gy in -1..=1 {
            if rng.random_bool(0.15) && (gx, gy) != (0, 0) {
                continue;
            }
            let centre = Vec2::new(gx as f32 * SPACING_M, gy as f32 * SPACING_M)
                + Vec2::new(rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0));
            let frame = Frame {
                centre_m: centre,
                yaw_rad: rng.random_range(-0.15..0.15),
                base_z_m: 0.0,
            };
            let half_x = rng.random_range(5.0..9.0f32);
            let half_y = rng.random_range(4.0..7.0f32);
            let storeys = rng.random_range(2..6u32);
            let storey_height = 3.0;
            let wall_height = storeys as f32 * storey_height;
            let wall_material = if rng.random_bool(0.5) {
                Material::Brick {
                    palette: rng.random_range(0..3),
                }
            } else {
                Material::Plaster {
                    palette: rng.random_range(0..4),
                }
            };
            let roof_material = Material::RoofTile {
                palette: rng.random_range(0..3),
            };
            let roof_kind = rng.random_range(0..3u32);
            let object_id = scene.new_object();
            let height_m = match roof_kind {
                0 => {
                    // Flat roof with a parapet (the parapet is a detail).
                    scene.add_box(
                        frame,
                        Vec3::new(-half_x, -half_y, 0.0),
                        Vec3::new(half_x, half_y, wall_height),
                        wall_material,
                        Material::FlatRoof,
                        PartKind::Building,
                        object_id,
                    );
                    for (min, max) in [
                        (
                            Vec3::new(-half_x, -half_y, wall_height),
                            Vec3::new(half_x, -half_y + 0.25, wall_height + 0.6),
                        ),
                        (
                            Vec3::new(-half_x, half_y - 0.25, wall_height),
                            Vec3::new(half_x, half_y, wall_height + 0.6),
                        ),
                        (
                            Vec3::new(-half_x, -half_y + 0.25, wall_height),
                            Vec3::new(-half_x + 0.25, half_y - 0.25, wall_height + 0.6),
                        ),
                        (
                            Vec3::new(half_x - 0.25, -half_y + 0.25, wall_height),
                            Vec3::new(half_x, half_y - 0.25, wall_height + 0.6),
                        ),
                    ] {
                        scene.add_box(
                            frame,
                            min,
                            max,
                            wall_material,
                            Material::Concrete,
                            PartKind::Detail,
                            object_id,
                        );
                    }
                    // A roof structure (lift housing / AC unit): a detail.
                    scene.add_box(
                        frame,
                        Vec3::new(-1.2, -1.0, wall_height),
                        Vec3::new(1.2, 1.0, wall_height + 1.8),
                        Material::Concrete,
                        Material::Concrete,
                        PartKind::Detail,
                        object_id,
                    );
                    wall_height + 1.8
                }
                1 => {
                    let rise = half_y * rng.random_range(0.5..0.9);
                    add_gable_building(
                        &mut scene,
                        &GableBuilding {
                            frame,
                            half_x_m: half_x,
                            half_y_m: half_y,
                            wall_height_m: wall_height,
                            roof_rise_m: rise,
                            eave_overhang_m: 0.5,
                            gable_overhang_m: 0.3,
                            roof_thickness_m: 0.3,
                            wall_material,
                            roof_material,
                        },
                    );
                    wall_height + rise
                }
                _ => {
                    let rise_per_m = rng.random_range(0.5..0.8f32);
                    add_hip_building(
                        &mut scene,
                        frame,
                        half_x,
                        half_y,
                        wall_height,
                        rise_per_m,
                        0.5,
                        wall_material,
                        roof_material,
                    );
                    wall_height + rise_per_m * half_y
                }
            };
            scene.footprints.push(Footprint {
                frame,
                half_x_m: half_x,
                half_y_m: half_y,
                height_m,
            });
            let style = rng.random_range(0..3u32);
            add_facade_windows(
                &mut scene,
                rng,
                frame,
                half_x,
                half_y,
                storeys,
                storey_height,
                true,
                style,
            );
            scene.add_opening(
                frame,
                Vec2::new(0.0, -1.0),
                half_y,
                0.0,
                0.0,
                1.4,
                2.3,
                PanelKind::Door,
                style,
            );
        }
    }
    // Streets between the blocks, pavements along them.
    for k in [-1.5f32, -0.5, 0.5, 1.5] {
        let c = k * SPACING_M;
        scene
            .ground
            .asphalt
            .push((Vec2::new(-300.0, c), Vec2::new(300.0, c), 3.5));
        scene
            .ground
            .asphalt
            .push((Vec2::new(c, -300.0), Vec2::new(c, 300.0), 3.5));
        for side in [-1.0f32, 1.0] {
            scene.ground.concrete.push((
                Vec2::new(-300.0, c + side * 4.5),
                Vec2::new(300.0, c + side * 4.5),
                1.0,
            ));
            scene.ground.concrete.push((
                Vec2::new(c + side * 4.5, -300.0),
                Vec2::new(c + side * 4.5, 300.0),
                1.0,
            ));
        }
    }
    add_ground(&mut scene);
    scene
}

/// The ground plane: the model's square patch, and four quads out to the horizon.
fn add_ground(scene: &mut Scene) {
    let object_id = scene.new_object();
    let h = scene.ground_patch_half_m;
    let far = 3000.0;
    let tag = |part| FaceTag {
        material: Material::Ground,
        object_id,
        panel: NO_PANEL,
        part,
    };
    let up = Some(Vec3::Z);
    // The patch, split into 2 m cells so the model's trimmed ground stays local.
    let cells = (2.0 * h / 2.0).ceil() as i32;
    let cell = 2.0 * h / cells as f32;
    let quad = |x0: f32, y0: f32, x1: f32, y1: f32| {
        [
            Vec3::new(x0, y0, 0.0),
            Vec3::new(x1, y0, 0.0),
            Vec3::new(x1, y1, 0.0),
            Vec3::new(x0, y1, 0.0),
        ]
    };
    for i in 0..cells {
        for j in 0..cells {
            let x0 = -h + i as f32 * cell;
            let y0 = -h + j as f32 * cell;
            scene.add_polygon(
                &quad(x0, y0, x0 + cell, y0 + cell),
                tag(PartKind::NearGround),
                up,
            );
        }
    }
    // Around it, 10 m cells out to 250 m (huge triangles lose depth precision in the
    // rasteriser, which shows as stripes in the shadow test), then four quads to the horizon.
    const RING_CELL_M: f32 = 10.0;
    const RING_CELLS: i32 = 25;
    let mut lines: Vec<f32> = (0..=RING_CELLS)
        .rev()
        .map(|k| -h - k as f32 * RING_CELL_M)
        .collect();
    lines.extend((0..=RING_CELLS).map(|k| h + k as f32 * RING_CELL_M));
    for i in 0..lines.len() - 1 {
        for j in 0..lines.len() - 1 {
            let (x0, x1, y0, y1) = (lines[i], lines[i + 1], lines[j], lines[j + 1]);
            if x0 >= -h && x1 <= h && y0 >= -h && y1 <= h {
                continue;
            }
            scene.add_polygon(&quad(x0, y0, x1, y1), tag(PartKind::FarGround), up);
        }
    }
    let r = h + RING_CELLS as f32 * RING_CELL_M;
    for corners in [
        quad(-far, -far, far, -r),
        quad(-far, r, far, far),
        quad(-far, -r, -r, r),
        quad(r, -r, far, r),
    ] {
        scene.add_polygon(&corners, tag(PartKind::FarGround), up);
    }
}

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
    use rand::SeedableRng;

    #[test]
    fn house_has_building_details_ground_and_solids() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let scene = build_house(&mut rng);
        let count = |kind: PartKind| scene.tags.iter().filter(|t| t.part == kind).count();
        assert!(count(PartKind::Building) > 20);
        assert!(count(PartKind::Detail) > 50);
        assert!(count(PartKind::NearGround) > 0 && count(PartKind::FarGround) > 0);
        assert!(scene.building_solids.len() >= 6);
        // The middle of the house is inside, a point far above it is not.
        assert!(scene
            .building_solids
            .iter()
            .any(|s| s.contains(Vec3::new(0.0, 0.0, 2.0))));
        assert!(!scene
            .building_solids
            .iter()
            .any(|s| s.contains(Vec3::new(0.0, 0.0, 30.0))));
        let (min, max) = scene.chimney_bounds_m.unwrap();
        let top = (min + max) * 0.5;
        assert!(scene.detail_solids.iter().any(|s| s.contains(top)));
        assert!(!scene.building_solids.iter().any(|s| s.contains(top)));
    }

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
