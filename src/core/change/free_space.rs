//! Free space across frames: an `added` object is a surface standing where the model has none,
//! so no photo can see past it. [`fusion`](super::fusion) confirms an object when two frames
//! found it, counting only the frames that saw something; this counts the frames that looked at
//! the same place and saw past it. A frame *sees through* an object when its photo depth at an
//! inner point of the object lies beyond that point by more than the frame's change threshold
//! (the same threshold, in the same unit, that made the finding frames call it `added`); it
//! *agrees* when its depth there is within the threshold and the model's surface lies beyond
//! the point by more (it would call the point `added` too). An `added` object that more frames
//! see through than agree with is a depth error of the frames that found it, not a new
//! building, and is not confirmed ([`check_free_space`]). Batch `asgreg changes` and the
//! pipeline's fusion stage both keep a [`SeenFrame`] per frame with a change map and call it
//! after `fuse_regions` (the pipeline's change workers send their frame's depths to fusion for
//! it).
//!
//! Why: under registered poses, a frame whose own pose is a few pixels off gets a stereo depth
//! that is off the same way with each of its neighbours (they share its pose), and two such
//! frames of the same flight line place the same false surface at the same world position
//! (block seed 2: a 9 m² "building" 4.8 m above open ground, found by view_018 and view_037,
//! seen through by 15 other frames; docs/measurements.md, branch `change22`). Agreement in
//! position and height cannot tell it from a building; only the frames that see the ground
//! behind it can.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::fusion::{fuse_regions, FusedChange, FusionConfig};
use super::{pose_error_sigma_m, ChangeConfig, ChangeKind, ChangeRegion};
use crate::core::camera::{nearest_pixel, PinholeIntrinsics};
use crate::core::image::{Image, ImageView};
use crate::core::rigid::Rigid3;

/// What one frame saw, to test world points against: its photo depth and the model's depth
/// under its pose (camera z, metres, 0 = none), its per-pixel pose term
/// ([`super::pose_error_sigma_m`]; `None`: exact pose) and the change settings its map was
/// made with (σ_quad and u as [`super::detect_changes`] used them).
#[derive(Clone, Copy, Debug)]
pub struct FrameSight<'a> {
    /// The frame's number, as the fused objects' `frames` number it.
    pub frame: usize,
    pub intrinsics: PinholeIntrinsics,
    /// World = the model's georeferenced frame, as the objects' coordinates.
    pub cam_from_world: Rigid3,
    pub photo_depth_m: ImageView<'a, f32>,
    pub model_depth_m: ImageView<'a, f32>,
    pub pose_sigma_m: Option<ImageView<'a, f32>>,
    pub config: ChangeConfig,
}

/// What one frame saw, owned until fusion (batch `changes` keeps one per frame with a change
/// map; the pipeline's fusion stage one per frame from its change worker's message): the maps
/// and settings a [`FrameSight`] borrows. The pose term is not kept apart: it is the model
/// depth's local range under the frame's u ([`pose_error_sigma_m`] of `config.pose_sigma_px`),
/// made again here exactly as [`super::detect_changes`] made it.
#[derive(Clone, Debug)]
pub struct SeenFrame {
    pub intrinsics: PinholeIntrinsics,
    pub cam_from_world: Rigid3,
    pub photo_depth_m: Image<f32>,
    pub model_depth_m: Image<f32>,
    pose_sigma_m: Image<f32>,
    /// The settings the frame's change map was made with (its u and σ_quad included:
    /// [`super::FrameChanges::settings`]).
    pub config: ChangeConfig,
}

impl SeenFrame {
    /// A frame's photo depth and the model's depth under its pose (camera z, metres, 0 = none;
    /// the same size) with the settings its change map was made with.
    pub fn new(
        intrinsics: PinholeIntrinsics,
        cam_from_world: Rigid3,
        photo_depth_m: Image<f32>,
        model_depth_m: Image<f32>,
        config: ChangeConfig,
    ) -> Self {
        let mut pose_sigma_m = Image::default();
        pose_error_sigma_m(
            model_depth_m.view(),
            config.pose_sigma_px,
            &mut pose_sigma_m,
            &mut Vec::new(),
        );
        Self {
            intrinsics,
            cam_from_world,
            photo_depth_m,
            model_depth_m,
            pose_sigma_m,
            config,
        }
    }

    /// The frame as the free-space test reads it, numbered `frame` (as the fused objects'
    /// `frames` number it).
    pub fn sight(&self, frame: usize) -> FrameSight<'_> {
        FrameSight {
            frame,
            intrinsics: self.intrinsics,
            cam_from_world: self.cam_from_world,
            photo_depth_m: self.photo_depth_m.view(),
            model_depth_m: self.model_depth_m.view(),
            pose_sigma_m: Some(self.pose_sigma_m.view()),
            config: self.config,
        }
    }
}

/// How one frame sees one world point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sight {
    /// Outside the photo, behind the camera, or no photo depth there.
    Unseen,
    /// Something nearer stands in front of it (the model's surface, or the photo's).
    Hidden,
    /// The model's surface on the point's ray lies within the change threshold of the point,
    /// or there is none (past the model's edge): this frame could not call the point `added`,
    /// so its agreeing depth says nothing of it.
    Indistinct,
    /// The photo's depth there is the point's, within the change threshold, and the model's
    /// surface lies beyond it by more: this frame would call the point `added` too.
    Agrees,
    /// The photo's depth lies beyond the point by more than the change threshold: the photo
    /// sees past it, so nothing stands there.
    Through,
}

impl FrameSight<'_> {
    /// How this frame sees `point_m` (world, metres): the photo's and the model's depth at the
    /// point's pixel against the point's own depth, with the frame's change threshold at that
    /// depth (and the pixel's pose term). A frame whose threshold is wider than the gap between
    /// the point and the model's surface behind it cannot agree (its depth would fit the model
    /// as well), but it can still see through: a depth beyond the point by more than the
    /// threshold is past it whatever the model.
    pub fn sight(&self, point_m: &Vector3<f64>) -> Sight {
        let point_cam = self.cam_from_world.transform_point(point_m);
        let (w, h) = self.photo_depth_m.size();
        if self.model_depth_m.size() != (w, h) {
            return Sight::Unseen;
        }
        let Some((col, row)) = self
            .intrinsics
            .project(&point_cam)
            .and_then(|px| nearest_pixel(px, w, h))
        else {
            return Sight::Unseen;
        };
        let index = row * w + col;
        let depth_m = point_cam.z as f32;
        let pose_sigma_m = self
            .pose_sigma_m
            .and_then(|s| s.data().get(index).copied())
            .unwrap_or(0.0);
        let threshold_m = self.config.threshold_with_pose_m(depth_m, pose_sigma_m);
        let model_m = self.model_depth_m.data()[index];
        if model_m.is_finite() && model_m > 0.0 && model_m < depth_m - threshold_m {
            return Sight::Hidden;
        }
        let photo_m = self.photo_depth_m.data()[index];
        if !(photo_m.is_finite() && photo_m > 0.0) {
            Sight::Unseen
        } else if photo_m > depth_m + threshold_m {
            Sight::Through
        } else if photo_m >= depth_m - threshold_m {
            // No model surface on the ray (past the model's edge): the frame has no change
            // map there, so it cannot call the point `added` either.
            let model_beyond =
                model_m.is_finite() && model_m > 0.0 && model_m > depth_m + threshold_m;
            if model_beyond {
                Sight::Agrees
            } else {
                Sight::Indistinct
            }
        } else {
            Sight::Hidden
        }
    }
}

/// The points an object is tested at: its centroid and its footprint's corners moved halfway
/// to the centroid, all at the centroid's height (world, metres). Inner points: a frame a few
/// pixels off sees past an object's edge, never past its middle; and the centroid's height is
/// the mean of the seen surface (roof and walls), inside a solid object.
pub fn inner_points_m(object: &FusedChange) -> Vec<Vector3<f64>> {
    let [cx, cy, cz] = object.centroid_m;
    std::iter::once(Vector3::new(cx, cy, cz))
        .chain(
            object
                .footprint_m
                .iter()
                .map(|p| Vector3::new(0.5 * (p[0] + cx), 0.5 * (p[1] + cy), cz)),
        )
        .collect()
}

/// The free-space test of one `added` object.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FreeSpaceCheck {
    /// Index of the object in the fused list.
    pub object: usize,
    pub centroid_m: [f64; 3],
    /// Frames that see through more of its inner points than they agree with (sorted).
    pub seen_through_by: Vec<usize>,
    /// Frames with at least one agreeing inner point and no more seen through (sorted).
    pub agreed_by: Vec<usize>,
    /// More frames see through it than agree: it was confirmed and no longer is.
    pub refuted: bool,
}

/// The change set's objects, as batch `asgreg changes` and the pipeline's fusion stage make
/// them: every frame's regions fused into objects ([`fuse_regions`]), then the confirmed `added`
/// ones tested against the free space of every frame in `seen` ([`check_free_space`]).
/// `regions` and `seen` number the frames alike (the objects' `frames`).
pub fn fuse_and_check<'a>(
    regions: &[(usize, &ChangeRegion)],
    config: &FusionConfig,
    seen: impl IntoIterator<Item = (usize, &'a SeenFrame)>,
) -> (Vec<FusedChange>, Vec<FreeSpaceCheck>) {
    let mut objects = fuse_regions(regions, config);
    let sights: Vec<FrameSight<'_>> = seen
        .into_iter()
        .map(|(frame, seen)| seen.sight(frame))
        .collect();
    let free_space = check_free_space(&mut objects, &sights);
    (objects, free_space)
}

/// Tests each confirmed `added` object against every frame's sight of its inner points
/// ([`inner_points_m`]): a frame votes `through` when more of the points it sees are
/// [`Sight::Through`] than [`Sight::Agrees`], `agrees` when it has at least one agreeing and no
/// more through, and abstains otherwise (hidden, unseen or indistinct everywhere: a frame whose
/// threshold there is wider than the object stands off the model cannot vote for it). An
/// object that more frames see through than agree with is no longer confirmed. Returns the
/// test of every confirmed `added` object; `removed` objects are not touched (the ground
/// bounds those, [`super::model_ground_z_m`]).
pub fn check_free_space(
    objects: &mut [FusedChange],
    frames: &[FrameSight<'_>],
) -> Vec<FreeSpaceCheck> {
    let mut checks = Vec::new();
    for (index, object) in objects.iter_mut().enumerate() {
        if object.kind != ChangeKind::Added || !object.confirmed {
            continue;
        }
        let points = inner_points_m(object);
        let mut seen_through_by = Vec::new();
        let mut agreed_by = Vec::new();
        for frame in frames {
            let (mut through, mut agrees) = (0usize, 0usize);
            for point in &points {
                match frame.sight(point) {
                    Sight::Through => through += 1,
                    Sight::Agrees => agrees += 1,
                    Sight::Hidden | Sight::Unseen | Sight::Indistinct => {}
                }
            }
            if through > agrees {
                seen_through_by.push(frame.frame);
            } else if agrees > 0 {
                agreed_by.push(frame.frame);
            }
        }
        seen_through_by.sort_unstable();
        seen_through_by.dedup();
        agreed_by.sort_unstable();
        agreed_by.dedup();
        let refuted = seen_through_by.len() > agreed_by.len();
        if refuted {
            object.confirmed = false;
        }
        checks.push(FreeSpaceCheck {
            object: index,
            centroid_m: object.centroid_m,
            seen_through_by,
            agreed_by,
            refuted,
        });
    }
    checks
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::core::change::fusion::{fuse_regions, FusionConfig};
    use crate::core::change::tests::mesh_of;
    use crate::core::change::{
        detect_changes, ChangeClass, ChangeRegion, ChangeWorkspace, DepthEvidence,
    };
    use crate::core::image::Image;
    use crate::core::mesh::Mesh;
    use crate::core::raster::{Rasterizer, RenderBuffers, RenderOptions};

    pub(crate) const SIZE_PX: u32 = 200;

    pub(crate) fn ground() -> [[f64; 3]; 4] {
        [
            [-60.0, -60.0, 0.0],
            [60.0, -60.0, 0.0],
            [60.0, 60.0, 0.0],
            [-60.0, 60.0, 0.0],
        ]
    }

    /// A 4 × 3 m box 5 m high centred on the origin: its roof and four walls.
    pub(crate) fn box_quads() -> Vec<[[f64; 3]; 4]> {
        let (x, y, z) = (2.0, 1.5, 5.0);
        vec![
            [[-x, -y, z], [x, -y, z], [x, y, z], [-x, y, z]],
            [[-x, -y, 0.0], [x, -y, 0.0], [x, -y, z], [-x, -y, z]],
            [[x, -y, 0.0], [x, y, 0.0], [x, y, z], [x, -y, z]],
            [[x, y, 0.0], [-x, y, 0.0], [-x, y, z], [x, y, z]],
            [[-x, y, 0.0], [-x, -y, 0.0], [-x, -y, z], [-x, y, z]],
        ]
    }

    /// Oblique cameras 40 m up, 30 m out, looking at the origin from around it.
    pub(crate) fn camera(azimuth_deg: f64) -> (PinholeIntrinsics, Rigid3) {
        let a = azimuth_deg.to_radians();
        let eye = Vector3::new(30.0 * a.cos(), 30.0 * a.sin(), 40.0);
        let pose = Rigid3::look_at(&eye, &Vector3::zeros(), &Vector3::z()).expect("a valid pose");
        (PinholeIntrinsics::centered(200.0, SIZE_PX, SIZE_PX), pose)
    }

    pub(crate) fn depth_of(
        mesh: &Mesh,
        intrinsics: &PinholeIntrinsics,
        pose: &Rigid3,
    ) -> Image<f32> {
        let mut buffers = RenderBuffers::new(SIZE_PX as usize, SIZE_PX as usize);
        Rasterizer::new().render(
            mesh,
            intrinsics,
            pose,
            &RenderOptions::default(),
            &mut buffers,
        );
        buffers.depth_m().clone()
    }

    /// One frame's change map against the ground-only model: its regions, its photo depth and
    /// the model's depth under its pose.
    struct Frame {
        intrinsics: PinholeIntrinsics,
        pose: Rigid3,
        regions: Vec<ChangeRegion>,
        photo: Image<f32>,
        model: Image<f32>,
    }

    fn frame(model: &Mesh, photographed: &Mesh, azimuth_deg: f64) -> Frame {
        let (intrinsics, pose) = camera(azimuth_deg);
        let photo = depth_of(photographed, &intrinsics, &pose);
        let mut workspace = ChangeWorkspace::new();
        let mut classes: Image<ChangeClass> = Image::default();
        let changes = detect_changes(
            model,
            &intrinsics,
            &pose,
            photo.view(),
            &DepthEvidence::default(),
            &ChangeConfig::default(),
            &mut workspace,
            &mut classes,
        )
        .expect("sizes match");
        Frame {
            intrinsics,
            pose,
            regions: changes.regions,
            model: workspace.model_rendering().depth_m().clone(),
            photo,
        }
    }

    /// What frame number `frame` of a test saw (exact pose, default settings).
    fn sight_of(frame: usize, f: &Frame) -> FrameSight<'_> {
        FrameSight {
            frame,
            intrinsics: f.intrinsics,
            cam_from_world: f.pose,
            photo_depth_m: f.photo.view(),
            model_depth_m: f.model.view(),
            pose_sigma_m: None,
            config: ChangeConfig::default(),
        }
    }

    /// Fuses the frames' regions and runs the free-space test: the objects and the tests.
    fn fused_and_checked(
        frames: &[Frame],
    ) -> (Vec<FusedChange>, Vec<FusedChange>, Vec<FreeSpaceCheck>) {
        let regions: Vec<(usize, &ChangeRegion)> = frames
            .iter()
            .enumerate()
            .flat_map(|(i, f)| f.regions.iter().map(move |r| (i, r)))
            .collect();
        let fused = fuse_regions(&regions, &FusionConfig::default());
        let sights: Vec<FrameSight<'_>> = frames
            .iter()
            .enumerate()
            .map(|(i, f)| sight_of(i, f))
            .collect();
        let mut checked = fused.clone();
        let checks = check_free_space(&mut checked, &sights);
        (fused, checked, checks)
    }

    #[test]
    fn a_surface_other_frames_see_through_is_not_confirmed_and_a_box_they_see_stays() {
        let model = mesh_of(&[ground()]);
        let mut quads = vec![ground()];
        quads.extend(box_quads());
        let with_box = mesh_of(&quads);
        // The false surface: the box's roof alone, floating 5 m over the open ground, in the
        // depth of two frames of one flight line only (their shared depth error).
        let roof = box_quads()[0];
        let floating = mesh_of(&[ground(), roof]);
        let bare = mesh_of(&[ground()]);
        let azimuths = [200.0, 220.0, 20.0, 110.0, 300.0];

        // A new building: every frame photographs it.
        let frames: Vec<Frame> = azimuths
            .iter()
            .map(|&a| frame(&model, &with_box, a))
            .collect();
        let (fused, checked, checks) = fused_and_checked(&frames);
        let confirmed = |objects: &[FusedChange]| {
            objects
                .iter()
                .filter(|o| o.kind == ChangeKind::Added && o.confirmed)
                .count()
        };
        assert_eq!(confirmed(&fused), 1, "{fused:?}");
        assert_eq!(confirmed(&checked), 1, "{checks:?}");
        assert_eq!(checks.len(), 1);
        assert!(checks[0].seen_through_by.is_empty(), "{checks:?}");
        assert_eq!(checks[0].agreed_by.len(), azimuths.len(), "{checks:?}");

        // The false surface: frames 0 and 1 have it, the other three see the ground there.
        let frames: Vec<Frame> = azimuths
            .iter()
            .enumerate()
            .map(|(i, &a)| frame(&model, if i < 2 { &floating } else { &bare }, a))
            .collect();
        let (fused, checked, checks) = fused_and_checked(&frames);
        // Fusion alone confirms it: two frames agree in position and height.
        assert_eq!(confirmed(&fused), 1, "{fused:?}");
        assert_eq!(confirmed(&checked), 0, "{checks:?}");
        assert_eq!(checks.len(), 1);
        assert!(checks[0].refuted);
        assert_eq!(checks[0].seen_through_by, vec![2, 3, 4]);
        assert_eq!(checks[0].agreed_by, vec![0, 1]);
    }

    #[test]
    fn a_frame_agrees_only_where_it_could_tell_the_point_from_the_model() {
        let roof = box_quads()[0];
        // A new roof the model lacks.
        let new = frame(&mesh_of(&[ground()]), &mesh_of(&[ground(), roof]), 200.0);
        let sight = sight_of(0, &new);
        assert_eq!(sight.sight(&Vector3::new(0.0, 0.0, 5.0)), Sight::Agrees);
        // Under it: the photo's roof is in front.
        assert_eq!(sight.sight(&Vector3::new(0.5, 0.3, 3.0)), Sight::Hidden);
        // On the open ground: the frame cannot tell it from the model.
        assert_eq!(
            sight.sight(&Vector3::new(-12.0, -8.0, 0.0)),
            Sight::Indistinct
        );
        // In the air over the open ground the photo sees: through.
        assert_eq!(sight.sight(&Vector3::new(-12.0, -8.0, 5.0)), Sight::Through);
        // Far outside the photo.
        assert_eq!(sight.sight(&Vector3::new(500.0, 0.0, 5.0)), Sight::Unseen);
        // The model has the roof: under it the model hides the point, on it the frame cannot
        // tell the point from the model.
        let old = mesh_of(&[ground(), roof]);
        let known = frame(&old, &old, 200.0);
        let sight = sight_of(0, &known);
        assert_eq!(sight.sight(&Vector3::new(0.5, 0.3, 3.0)), Sight::Hidden);
        assert_eq!(sight.sight(&Vector3::new(0.0, 0.0, 5.0)), Sight::Indistinct);
    }
}
