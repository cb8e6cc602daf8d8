//! Ground truth for change detection (`asgreg synth --changes`): the photographed world and the
//! model's world differ by known objects. New buildings and extensions are in the photos (and
//! their depth maps) only; demolished buildings are in the model only. Per photo, a true change
//! mask (`changes_gt/<stem>.png`, grey levels of [`ChangeClass::mask_value`]) and, for the whole
//! scene, the list of changed objects with the pixels each covers in each photo
//! (`changes.json`).
//!
//! True classes of a pixel: `added` where the photo's visible surface is an added object;
//! `removed` where the model's world shows a demolished object and the photo sees a surface
//! behind it (not where clutter in front hides the place); `unchanged` elsewhere.

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use super::geometry::{ChangePlan, ChangeWhat, PlacedChange, Scene};
use super::viewpoints::SceneKind;
use crate::core::camera::PinholeIntrinsics;
use crate::core::change::ChangeClass;
use crate::core::image::Image;
use crate::core::mesh::{Mesh, MeshError};
use crate::core::raster::{Rasterizer, RenderBuffers, RenderOptions, NO_FACE};
use crate::core::rigid::Rigid3;

/// Folder of the true masks in a scene folder.
pub const MASK_DIR: &str = "changes_gt";
/// File of the changed objects in a scene folder.
pub const OBJECTS_FILE: &str = "changes.json";
/// A removed object's pixel counts only where the photo's surface is this much behind it, m.
const BEHIND_MARGIN_M: f32 = 0.3;

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

/// A building part in the photos that the degraded model leaves out by design (a "Detail":
/// rooftop stair house, dormer, porch); not a change, but a real difference a change map may
/// show. `eval --changes` names detections on them apart from the other false ones.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelOmission {
    /// Axis-aligned bounds in x, y as a counter-clockwise rectangle, metres.
    pub footprint_m: Vec<[f64; 2]>,
    pub z_min_m: f64,
    pub z_max_m: f64,
}

/// The content of `changes.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChangesFile {
    /// How the masks encode classes (grey level per class).
    pub mask_levels: BTreeMap<String, u8>,
    pub objects: Vec<TrueChange>,
    /// Detail parts of at least 1 × 1 m that the model omits (not changes).
    #[serde(default)]
    pub model_omissions: Vec<ModelOmission>,
}

impl ChangesFile {
    pub fn new(scene: &Scene, placed: &[PlacedChange]) -> Self {
        let model_omissions = scene
            .detail_solids
            .iter()
            .map(|solid| solid.bounds_m())
            .filter(|(min, max)| max.x - min.x >= 1.0 && max.y - min.y >= 1.0)
            .map(|(min, max)| {
                let (x0, y0, x1, y1) = (
                    f64::from(min.x),
                    f64::from(min.y),
                    f64::from(max.x),
                    f64::from(max.y),
                );
                ModelOmission {
                    footprint_m: vec![[x0, y0], [x1, y0], [x1, y1], [x0, y1]],
                    z_min_m: f64::from(min.z),
                    z_max_m: f64::from(max.z),
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
    added: BTreeSet<u32>,
    removed: BTreeSet<u32>,
    rasterizer: Rasterizer,
    photo_buffers: RenderBuffers,
    model_buffers: RenderBuffers,
}

impl TruthRenderer {
    pub fn new(worlds: &ChangeWorlds, placed: &[PlacedChange]) -> Result<Self, MeshError> {
        let objects = |scene: &Scene| scene.tags.iter().map(|t| t.object_id).collect();
        Ok(Self {
            photo_mesh: worlds.photo.to_mesh(|_| true)?,
            photo_objects: objects(&worlds.photo),
            model_mesh: worlds.model.to_mesh(|_| true)?,
            model_objects: objects(&worlds.model),
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
            rasterizer: Rasterizer::new(),
            photo_buffers: RenderBuffers::default(),
            model_buffers: RenderBuffers::default(),
        })
    }

    /// The true classes of one photo, and the pixel count of each changed object in it.
    pub fn mask(
        &mut self,
        intrinsics: &PinholeIntrinsics,
        width_px: usize,
        height_px: usize,
        cam_from_world: &Rigid3,
    ) -> (Image<u8>, BTreeMap<u32, usize>) {
        let options = RenderOptions::default();
        self.photo_buffers.resize(width_px, height_px);
        self.model_buffers.resize(width_px, height_px);
        self.rasterizer.render(
            &self.photo_mesh,
            intrinsics,
            cam_from_world,
            &options,
            &mut self.photo_buffers,
        );
        self.rasterizer.render(
            &self.model_mesh,
            intrinsics,
            cam_from_world,
            &options,
            &mut self.model_buffers,
        );
        let mut counts = BTreeMap::new();
        let photo_faces = self.photo_buffers.face_index().data();
        let photo_depth = self.photo_buffers.depth_m().data();
        let model_faces = self.model_buffers.face_index().data();
        let model_depth = self.model_buffers.depth_m().data();
        let object = |faces: &[u32], objects: &[u32], index: usize| {
            let face = faces[index];
            (face != NO_FACE)
                .then(|| objects.get(face as usize).copied())
                .flatten()
        };
        let mask = Image::from_fn(width_px, height_px, |col, row| {
            let index = row * width_px + col;
            if let Some(id) = object(photo_faces, &self.photo_objects, index) {
                if self.added.contains(&id) {
                    *counts.entry(id).or_insert(0) += 1;
                    return ChangeClass::Added.mask_value();
                }
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
                .filter(|o| o.kind == kind)
                .flat_map(|o| o.pixels_per_image.values())
                .sum()
        };
        assert_eq!(added, counted(crate::core::change::ChangeKind::Added));
        assert_eq!(removed, counted(crate::core::change::ChangeKind::Removed));
        assert!(
            file.objects.iter().all(|o| !o.pixels_per_image.is_empty()),
            "{file:?}"
        );
    }
}
