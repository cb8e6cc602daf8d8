//! Ground truth for change detection (`asgreg synth --changes`): the photographed world and the
//! model's world differ by known objects. New buildings and extensions are in the photos (and
//! their depth maps) only; demolished buildings are in the model only. Per photo, a true change
//! mask (`changes_gt/<stem>.png`, grey levels of [`ChangeClass::mask_value`]) and, for the whole
//! scene, the list of changed objects with the pixels each covers in each photo
//! (`changes.json`).
//!
//! Besides the placed changes, the photographed world differs from the model by the building
//! parts the degraded model leaves out by design (rooftop structures, dormers, porch roofs:
//! synth's "Detail" solids of at least 1 m × 1 m, touching ones joined into one part). They are
//! real differences a surveyor wants reported, so they are truth too: listed as
//! `model_omissions` (kind `added`, what `model_omission`, footprint, heights, pixels per photo)
//! and marked `added` in the masks.
//!
//! True classes of a pixel: `added` where the photo's visible surface is an added object, or an
//! omitted part standing at least [`BEHIND_MARGIN_M`] in front of the modelled surfaces (the
//! model's world without its details: what the degraded model was made from); `removed` where
//! the model's world shows a demolished object and the photo sees a surface behind it (not where
//! clutter in front hides the place); `unchanged` elsewhere. Clutter (trees, cars) is not truth.

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use super::geometry::{ChangePlan, ChangeWhat, PartKind, PlacedChange, Scene, Solid};
use super::viewpoints::SceneKind;
use crate::core::camera::{pixel_center, PinholeIntrinsics};
use crate::core::change::polygon::{convex_hull, polygon_area};
use crate::core::change::ChangeClass;
use crate::core::image::Image;
use crate::core::mesh::{Mesh, MeshError};
use crate::core::raster::{Rasterizer, RenderBuffers, RenderOptions, NO_FACE};
use crate::core::rigid::Rigid3;

/// Folder of the true masks in a scene folder.
pub const MASK_DIR: &str = "changes_gt";
/// File of the changed objects in a scene folder.
pub const OBJECTS_FILE: &str = "changes.json";
/// A removed object's pixel counts only where the photo's surface is this much behind it, and
/// an omitted part's only where it stands this much in front of the modelled surfaces, m.
pub const BEHIND_MARGIN_M: f32 = 0.3;
/// Least horizontal side of a detail solid that makes part of a model omission, m: thinner
/// details (parapets, sills, posts, railings, chimneys) are below any change's size.
const OMISSION_MIN_SIDE_M: f32 = 1.0;
/// Detail solids whose world boxes are this close form one omitted part, m.
const OMISSION_TOUCH_M: f32 = 0.05;
/// A photo pixel's visible point, moved on along its ray by this much, lies inside the solid
/// whose surface it is on, m.
const INSIDE_STEP_M: f64 = 0.02;

/// How many changed objects each scene gets and where they may stand.
pub fn plan_for(kind: SceneKind) -> ChangePlan {
    match kind {
        SceneKind::House => ChangePlan {
            new_buildings: 1,
            extensions: 1,
            demolished: 1,
            ring_m: (9.0, 14.0),
            clearance_m: 1.5,
            camera_clearance_m: 4.0,
        },
        SceneKind::Block => ChangePlan {
            new_buildings: 2,
            extensions: 1,
            demolished: 2,
            ring_m: (8.0, 38.0),
            clearance_m: 2.0,
            camera_clearance_m: 4.0,
        },
    }
}

/// One changed object as written to `changes.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrueChange {
    /// Object id of its faces in the true scene.
    pub id: u32,
    /// "added" or "removed" (the detector's kinds).
    pub kind: crate::core::change::ChangeKind,
    pub what: ChangeWhat,
    /// Footprint corners (x, y), counter-clockwise, metres, the model's frame.
    pub footprint_m: Vec<[f64; 2]>,
    pub footprint_area_m2: f64,
    /// Highest point above the ground, metres.
    pub height_m: f64,
    /// Centre of the footprint at half the height, metres.
    pub centroid_m: [f64; 3],
    /// Pixels of its true mask in each photo that shows it.
    pub pixels_per_image: BTreeMap<String, usize>,
}

/// A building part in the photos that the degraded model leaves out by design: touching
/// "Detail" solids of at least [`OMISSION_MIN_SIDE_M`] on both horizontal sides.
#[derive(Clone, Debug)]
pub struct OmittedPart {
    solids: Vec<Solid>,
    /// World boxes of `solids`, for a quick test before the exact one.
    bounds_m: Vec<(glam::Vec3, glam::Vec3)>,
    /// Convex hull of the solids' footprint rectangles, counter-clockwise, metres.
    pub footprint_m: Vec<[f64; 2]>,
    pub z_min_m: f64,
    pub z_max_m: f64,
}

impl OmittedPart {
    fn contains(&self, p: glam::Vec3) -> bool {
        self.solids
            .iter()
            .zip(&self.bounds_m)
            .any(|(solid, (min, max))| {
                p.cmpge(*min - 0.01).all() && p.cmple(*max + 0.01).all() && solid.contains(p)
            })
    }
}

/// The parts of `scene` (the photographed world) that the degraded model omits by design.
pub fn omitted_parts(scene: &Scene) -> Vec<OmittedPart> {
    let solids: Vec<&Solid> = scene
        .detail_solids
        .iter()
        .filter(|solid| {
            let (_, (a, b)) = solid.footprint_m();
            a.min(b) >= OMISSION_MIN_SIDE_M
        })
        .collect();
    let bounds: Vec<_> = solids.iter().map(|s| s.bounds_m()).collect();
    // Union-find over touching world boxes.
    let mut parent: Vec<usize> = (0..solids.len()).collect();
    let root = crate::core::change::fusion::find;
    for i in 0..solids.len() {
        for j in i + 1..solids.len() {
            let ((a0, a1), (b0, b1)) = (bounds[i], bounds[j]);
            let touch =
                (a0 - OMISSION_TOUCH_M).cmple(b1).all() && (b0 - OMISSION_TOUCH_M).cmple(a1).all();
            if touch {
                let (ri, rj) = (root(&mut parent, i), root(&mut parent, j));
                parent[ri] = rj;
            }
        }
    }
    let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for i in 0..solids.len() {
        let r = root(&mut parent, i);
        groups.entry(r).or_default().push(i);
    }
    groups
        .into_values()
        .map(|members| {
            let corners: Vec<[f64; 2]> = members
                .iter()
                .flat_map(|&i| solids[i].footprint_m().0)
                .map(|c| [f64::from(c.x), f64::from(c.y)])
                .collect();
            let z_min = members
                .iter()
                .map(|&i| bounds[i].0.z)
                .fold(f32::INFINITY, f32::min);
            let z_max = members
                .iter()
                .map(|&i| bounds[i].1.z)
                .fold(f32::NEG_INFINITY, f32::max);
            OmittedPart {
                solids: members.iter().map(|&i| solids[i].clone()).collect(),
                bounds_m: members.iter().map(|&i| bounds[i]).collect(),
                footprint_m: convex_hull(&corners),
                z_min_m: f64::from(z_min),
                z_max_m: f64::from(z_max),
            }
        })
        .collect()
}

/// The content of `changes.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChangesFile {
    /// How the masks encode classes (grey level per class).
    pub mask_levels: BTreeMap<String, u8>,
    /// The placed changes (new buildings, extensions, demolished buildings).
    pub objects: Vec<TrueChange>,
    /// The building parts the degraded model omits by design (what `model_omission`, kind
    /// `added`): real differences too, listed apart so that figures can show them apart.
    #[serde(default)]
    pub model_omissions: Vec<TrueChange>,
}

impl ChangesFile {
    /// `omitted` from [`omitted_parts`]; their ids follow `first_omission_id`.
    pub fn new(placed: &[PlacedChange], omitted: &[OmittedPart], first_omission_id: u32) -> Self {
        let model_omissions = omitted
            .iter()
            .zip(first_omission_id..)
            .map(|(part, id)| {
                let n = part.footprint_m.len().max(1) as f64;
                let centre = part
                    .footprint_m
                    .iter()
                    .fold([0.0, 0.0], |acc, c| [acc[0] + c[0] / n, acc[1] + c[1] / n]);
                TrueChange {
                    id,
                    kind: crate::core::change::ChangeKind::Added,
                    what: ChangeWhat::ModelOmission,
                    footprint_area_m2: polygon_area(&part.footprint_m),
                    footprint_m: part.footprint_m.clone(),
                    height_m: part.z_max_m,
                    centroid_m: [centre[0], centre[1], 0.5 * (part.z_min_m + part.z_max_m)],
                    pixels_per_image: BTreeMap::new(),
                }
            })
            .collect();
        let mask_levels = [
            ChangeClass::Unknown,
            ChangeClass::Unchanged,
            ChangeClass::Added,
            ChangeClass::Removed,
        ]
        .into_iter()
        .map(|c| {
            let name = serde_json::to_value(c)
                .ok()
                .and_then(|v| v.as_str().map(str::to_owned))
                .unwrap_or_default();
            (name, c.mask_value())
        })
        .collect();
        let objects = placed
            .iter()
            .map(|p| {
                let footprint: Vec<[f64; 2]> = p
                    .corners_m()
                    .iter()
                    .map(|c| [f64::from(c.x), f64::from(c.y)])
                    .collect();
                let centre = p.footprint.frame.centre_m;
                TrueChange {
                    id: p.object_id,
                    kind: if p.what.is_added() {
                        crate::core::change::ChangeKind::Added
                    } else {
                        crate::core::change::ChangeKind::Removed
                    },
                    what: p.what,
                    footprint_area_m2: crate::core::change::polygon::polygon_area(&footprint),
                    footprint_m: footprint,
                    height_m: f64::from(p.footprint.height_m),
                    centroid_m: [
                        f64::from(centre.x),
                        f64::from(centre.y),
                        f64::from(p.footprint.height_m) * 0.5,
                    ],
                    pixels_per_image: BTreeMap::new(),
                }
            })
            .collect();
        Self {
            mask_levels,
            objects,
            model_omissions,
        }
    }
}

/// A copy of `scene` without the faces of `objects` (positions are kept; meshes made from it
/// drop unused vertices).
fn without_faces(scene: &Scene, objects: &BTreeSet<u32>) -> Scene {
    let mut copy = scene.clone();
    let (faces, tags): (Vec<_>, Vec<_>) = scene
        .faces
        .iter()
        .zip(&scene.tags)
        .filter(|(_, t)| !objects.contains(&t.object_id))
        .map(|(f, t)| (*f, *t))
        .unzip();
    copy.faces = faces;
    copy.tags = tags;
    copy
}

/// The two worlds of a changes scene: what the photos see, and what the model was made from.
pub struct ChangeWorlds {
    /// The photographed world: without the demolished objects' faces.
    pub photo: Scene,
    /// The model's world: without the added objects' faces and solids (their footprints stay,
    /// so the model keeps the ground they were built on).
    pub model: Scene,
}

/// Splits the full scene (every changed object in it) into the two worlds.
pub fn split_worlds(scene: &Scene, placed: &[PlacedChange]) -> ChangeWorlds {
    let ids = |added: bool| -> BTreeSet<u32> {
        placed
            .iter()
            .filter(|p| p.what.is_added() == added)
            .map(|p| p.object_id)
            .collect()
    };
    let photo = without_faces(scene, &ids(false));
    let mut model = without_faces(scene, &ids(true));
    let dropped: BTreeSet<usize> = placed
        .iter()
        .filter(|p| p.what.is_added())
        .flat_map(|p| p.solid_indices.clone())
        .collect();
    model.building_solids = scene
        .building_solids
        .iter()
        .enumerate()
        .filter(|(i, _)| !dropped.contains(i))
        .map(|(_, s)| s.clone())
        .collect();
    ChangeWorlds { photo, model }
}

/// Renders the true change masks of the photos.
pub struct TruthRenderer {
    photo_mesh: Mesh,
    photo_objects: Vec<u32>,
    model_mesh: Mesh,
    model_objects: Vec<u32>,
    /// The model's world without its details and clutter: the surfaces the degraded model was
    /// made from, in front of which an omitted part stands.
    modelled_mesh: Mesh,
    added: BTreeSet<u32>,
    removed: BTreeSet<u32>,
    /// The omitted parts with their ids in `changes.json`.
    omitted: Vec<(u32, OmittedPart)>,
    rasterizer: Rasterizer,
    photo_buffers: RenderBuffers,
    model_buffers: RenderBuffers,
    modelled_buffers: RenderBuffers,
}

impl TruthRenderer {
    /// `omitted` from [`omitted_parts`] of the photo world, with their ids.
    pub fn new(
        worlds: &ChangeWorlds,
        placed: &[PlacedChange],
        omitted: Vec<(u32, OmittedPart)>,
    ) -> Result<Self, MeshError> {
        let objects = |scene: &Scene| scene.tags.iter().map(|t| t.object_id).collect();
        Ok(Self {
            photo_mesh: worlds.photo.to_mesh(|_| true)?,
            photo_objects: objects(&worlds.photo),
            model_mesh: worlds.model.to_mesh(|_| true)?,
            model_objects: objects(&worlds.model),
            modelled_mesh: worlds.model.to_mesh(|t| {
                matches!(
                    t.part,
                    PartKind::Building | PartKind::NearGround | PartKind::FarGround
                )
            })?,
            added: placed
                .iter()
                .filter(|p| p.what.is_added())
                .map(|p| p.object_id)
                .collect(),
            removed: placed
                .iter()
                .filter(|p| !p.what.is_added())
                .map(|p| p.object_id)
                .collect(),
            omitted,
            rasterizer: Rasterizer::new(),
            photo_buffers: RenderBuffers::default(),
            model_buffers: RenderBuffers::default(),
            modelled_buffers: RenderBuffers::default(),
        })
    }

    /// The true classes of one photo, and the pixel count of each changed object and omitted
    /// part in it.
    pub fn mask(
        &mut self,
        intrinsics: &PinholeIntrinsics,
        width_px: usize,
        height_px: usize,
        cam_from_world: &Rigid3,
    ) -> (Image<u8>, BTreeMap<u32, usize>) {
        let options = RenderOptions::default();
        for (mesh, buffers) in [
            (&self.photo_mesh, &mut self.photo_buffers),
            (&self.model_mesh, &mut self.model_buffers),
            (&self.modelled_mesh, &mut self.modelled_buffers),
        ] {
            buffers.resize(width_px, height_px);
            self.rasterizer
                .render(mesh, intrinsics, cam_from_world, &options, buffers);
        }
        let world_from_cam = cam_from_world.inverse();
        let mut counts = BTreeMap::new();
        let photo_faces = self.photo_buffers.face_index().data();
        let photo_depth = self.photo_buffers.depth_m().data();
        let model_faces = self.model_buffers.face_index().data();
        let model_depth = self.model_buffers.depth_m().data();
        let modelled_depth = self.modelled_buffers.depth_m().data();
        let object = |faces: &[u32], objects: &[u32], index: usize| {
            let face = faces[index];
            (face != NO_FACE)
                .then(|| objects.get(face as usize).copied())
                .flatten()
        };
        // The omitted part whose surface the photo sees at a pixel, where it stands in front of
        // the modelled surfaces by the margin.
        let omitted_at = |col: usize, row: usize, index: usize| -> Option<u32> {
            let depth = photo_depth[index];
            let modelled = modelled_depth[index];
            if depth <= 0.0 || (modelled > 0.0 && depth > modelled - BEHIND_MARGIN_M) {
                return None;
            }
            let ray = intrinsics.pixel_to_normalized(pixel_center(col, row));
            let z = f64::from(depth) + INSIDE_STEP_M;
            let point =
                world_from_cam.transform_point(&nalgebra::Vector3::new(ray.x * z, ray.y * z, z));
            let point = glam::Vec3::new(point.x as f32, point.y as f32, point.z as f32);
            self.omitted
                .iter()
                .find(|(_, part)| part.contains(point))
                .map(|(id, _)| *id)
        };
        let mask = Image::from_fn(width_px, height_px, |col, row| {
            let index = row * width_px + col;
            if let Some(id) = object(photo_faces, &self.photo_objects, index) {
                if self.added.contains(&id) {
                    *counts.entry(id).or_insert(0) += 1;
                    return ChangeClass::Added.mask_value();
                }
            }
            if let Some(id) = omitted_at(col, row, index) {
                *counts.entry(id).or_insert(0) += 1;
                return ChangeClass::Added.mask_value();
            }
            if let Some(id) = object(model_faces, &self.model_objects, index) {
                let behind = photo_depth[index] <= 0.0
                    || photo_depth[index] > model_depth[index] + BEHIND_MARGIN_M;
                if self.removed.contains(&id) && behind {
                    *counts.entry(id).or_insert(0) += 1;
                    return ChangeClass::Removed.mask_value();
                }
            }
            ChangeClass::Unchanged.mask_value()
        });
        (mask, counts)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{generate_scene, SynthConfig};

    #[test]
    fn a_tiny_changes_scene_writes_masks_and_objects_that_the_photos_show() {
        let dir = tempfile::tempdir().expect("a temporary folder");
        let config = SynthConfig {
            seed: 4,
            width_px: 200,
            height_px: 110,
            image_count: 6,
            initial_levels_px: vec![20.0],
            supersampling: 1,
            model_voxel_m: 0.35,
            changes: true,
            ..SynthConfig::default()
        };
        let summary = generate_scene(&config, dir.path()).expect("the scene is generated");
        let text = std::fs::read_to_string(dir.path().join(OBJECTS_FILE)).expect("changes.json");
        let file: ChangesFile = serde_json::from_str(&text).expect("changes.json parses");
        assert_eq!(file.objects.len(), 3, "{file:?}");
        for what in [
            ChangeWhat::NewBuilding,
            ChangeWhat::Extension,
            ChangeWhat::Demolished,
        ] {
            assert!(file.objects.iter().any(|o| o.what == what), "{what:?}");
        }
        for object in &file.objects {
            assert!(object.footprint_area_m2 >= 9.0, "{object:?}");
        }
        // Every object shows in at least one photo, and the masks hold the counted pixels.
        let mut added = 0usize;
        let mut removed = 0usize;
        for image in &summary.images {
            let path = dir
                .path()
                .join(MASK_DIR)
                .join(std::path::Path::new(&image.name).with_extension("png"));
            let mask = image::open(&path).expect("the mask reads").to_luma8();
            for value in mask.as_raw() {
                match ChangeClass::from_mask_value(*value) {
                    ChangeClass::Added => added += 1,
                    ChangeClass::Removed => removed += 1,
                    _ => {}
                }
            }
        }
        let counted = |kind| -> usize {
            file.objects
                .iter()
                .chain(&file.model_omissions)
                .filter(|o| o.kind == kind)
                .flat_map(|o| o.pixels_per_image.values())
                .sum()
        };
        // The house's parts the model omits (dormer, porch roof, ...) are listed as added
        // differences of at least 1 × 1 m, and at least one of them shows in the masks.
        assert!(!file.model_omissions.is_empty(), "{file:?}");
        for omission in &file.model_omissions {
            assert_eq!(omission.what, ChangeWhat::ModelOmission);
            assert_eq!(omission.kind, crate::core::change::ChangeKind::Added);
            let (width, _) = crate::core::change::polygon::width_and_length(&omission.footprint_m);
            assert!(width >= 1.0 - 1e-3, "{omission:?}");
            assert!(file.objects.iter().all(|o| o.id != omission.id));
        }
        assert!(file
            .model_omissions
            .iter()
            .any(|o| o.pixels_per_image.values().sum::<usize>() > 0));
        assert_eq!(added, counted(crate::core::change::ChangeKind::Added));
        assert_eq!(removed, counted(crate::core::change::ChangeKind::Removed));
        assert!(
            file.objects.iter().all(|o| !o.pixels_per_image.is_empty()),
            "{file:?}"
        );
    }
}
