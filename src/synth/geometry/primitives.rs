//! The shapes every part of a scene is built from: polygons, prisms, boxes, cylinders, blobs,
//! window and door panels, and the walled, roofed volumes (gable, hip) of a building. Each adds its
//! faces with their tags and, for building parts, its solid.

use glam::{Vec2, Vec3};

use super::{FaceTag, Frame, PartKind, Scene, Solid, NO_PANEL};
use crate::synth::texture::{fbm, Material, Panel, PanelKind};

impl Scene {
    /// Adds a convex polygon (fan), oriented so its normal points along `outward` when given.
    pub(super) fn add_polygon(&mut self, corners: &[Vec3], tag: FaceTag, outward: Option<Vec3>) {
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
    pub(super) fn add_convex_faces(&mut self, faces: &[(Vec<Vec3>, FaceTag)], centre: Vec3) {
        for (corners, tag) in faces {
            let face_centre = corners.iter().copied().sum::<Vec3>() / corners.len() as f32;
            self.add_polygon(corners, *tag, Some(face_centre - centre));
        }
    }

    /// Adds a prism solid (convex polygon in local (y, z), extruded along local x) with one material
    /// per polygon edge and one for both caps.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn add_prism(
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
    pub(super) fn add_box(
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
    pub(super) fn add_cylinder(
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
    pub(super) fn add_blob(
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
    pub(super) fn add_opening(
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
pub(super) struct GableBuilding {
    pub(super) frame: Frame,
    pub(super) half_x_m: f32,
    pub(super) half_y_m: f32,
    pub(super) wall_height_m: f32,
    pub(super) roof_rise_m: f32,
    pub(super) eave_overhang_m: f32,
    pub(super) gable_overhang_m: f32,
    pub(super) roof_thickness_m: f32,
    pub(super) wall_material: Material,
    pub(super) roof_material: Material,
}

/// Adds walls, gable infill and the roof slab (ridge along local x) as building solids.
pub(super) fn add_gable_building(scene: &mut Scene, building: &GableBuilding) {
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
pub(super) fn add_hip_building(
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
