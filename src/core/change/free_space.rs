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
//! it). Only the frames whose [`FrameFootprint`] (camera, pose, image size: where its pixels
//! look) holds an object's inner point can vote on it; [`FreeSpaceTest`] asks a
//! [`SightSource`] for those frames' sights alone, so a caller may keep the footprints in memory
//! and the maps elsewhere (the pipeline's fusion: on disk, a few in memory) with the same votes.
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

    /// Where the frame's pixels look: what tells whether it can see a point at all.
    pub fn footprint(&self) -> FrameFootprint {
        let (width_px, height_px) = self.photo_depth_m.size();
        FrameFootprint {
            intrinsics: self.intrinsics,
            cam_from_world: self.cam_from_world,
            width_px,
            height_px,
        }
    }

    /// Bytes its maps hold (photo depth, model depth, pose term).
    pub fn map_bytes(&self) -> usize {
        std::mem::size_of::<f32>()
            * (self.photo_depth_m.data().len()
                + self.model_depth_m.data().len()
                + self.pose_sigma_m.data().len())
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

/// Where a frame's pixels look: its camera, pose and depth map size, a few hundred bytes. A
/// frame sees no point outside it (every [`Sight`] but `Unseen` needs the point's pixel), so
/// the frames whose footprint holds none of an object's inner points cannot vote on it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameFootprint {
    pub intrinsics: PinholeIntrinsics,
    pub cam_from_world: Rigid3,
    pub width_px: usize,
    pub height_px: usize,
}

impl FrameFootprint {
    /// Whether any of `points_m` (world, metres) falls on one of the frame's pixels, in front of
    /// it: the one projection [`FrameSight::sight`] reads its pixel by.
    pub fn sees_any(&self, points_m: &[Vector3<f64>]) -> bool {
        points_m.iter().any(|point| {
            pixel_of(
                &self.intrinsics,
                &self.cam_from_world,
                self.width_px,
                self.height_px,
                point,
            )
            .is_some()
        })
    }
}

/// The pixel (column, row) of `point_m` in a frame's `width_px` × `height_px` map and the
/// point in the camera's frame; `None` behind the camera or outside the map.
fn pixel_of(
    intrinsics: &PinholeIntrinsics,
    cam_from_world: &Rigid3,
    width_px: usize,
    height_px: usize,
    point_m: &Vector3<f64>,
) -> Option<((usize, usize), Vector3<f64>)> {
    let point_cam = cam_from_world.transform_point(point_m);
    intrinsics
        .project(&point_cam)
        .and_then(|px| nearest_pixel(px, width_px, height_px))
        .map(|pixel| (pixel, point_cam))
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
        let (w, h) = self.photo_depth_m.size();
        if self.model_depth_m.size() != (w, h) {
            return Sight::Unseen;
        }
        let Some(((col, row), point_cam)) =
            pixel_of(&self.intrinsics, &self.cam_from_world, w, h, point_m)
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

/// A frame's vote on one object.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Vote {
    /// More of the object's inner points it sees are [`Sight::Through`] than [`Sight::Agrees`].
    Through,
    /// At least one agreeing point and no more seen through.
    Agrees,
    /// Hidden, unseen or indistinct everywhere.
    Abstains,
}

impl FrameSight<'_> {
    /// This frame's vote on an object tested at `points_m` (its inner points): the one rule of
    /// the free-space test.
    pub fn vote(&self, points_m: &[Vector3<f64>]) -> Vote {
        let (mut through, mut agrees) = (0usize, 0usize);
        for point in points_m {
            match self.sight(point) {
                Sight::Through => through += 1,
                Sight::Agrees => agrees += 1,
                Sight::Hidden | Sight::Unseen | Sight::Indistinct => {}
            }
        }
        if through > agrees {
            Vote::Through
        } else if agrees > 0 {
            Vote::Agrees
        } else {
            Vote::Abstains
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

/// Where the free-space test gets the frames' sights: every frame's footprint, and the sight
/// of each frame the test [`wants`](FreeSpaceTest::wants) (batch `changes`: all in memory; the
/// pipeline's fusion: loaded from the state folder when not in memory). A frame whose sight
/// cannot be had is left out of the vote (the source says why, naming it).
pub trait SightSource {
    /// Hands `test` ([`FreeSpaceTest::add`]) the sight of every frame whose footprint it
    /// wants, each once, in any order (the votes do not depend on it).
    fn visit(&mut self, test: &mut FreeSpaceTest);
}

/// Frames with a change map, all in memory, numbered as the fused objects' `frames`.
impl SightSource for [(usize, SeenFrame)] {
    fn visit(&mut self, test: &mut FreeSpaceTest) {
        for (frame, seen) in self.iter() {
            if test.wants(&seen.footprint()) {
                test.add(&seen.sight(*frame));
            }
        }
    }
}

/// The change set's objects, as batch `asgreg changes` and the pipeline's fusion stage make
/// them: every frame's regions fused into objects ([`fuse_regions`]), then the confirmed `added`
/// ones tested against the free space of every frame `sights` has ([`FreeSpaceTest`]).
/// `regions` and `sights` number the frames alike (the objects' `frames`).
pub fn fuse_and_check<S: SightSource + ?Sized>(
    regions: &[(usize, &ChangeRegion)],
    config: &FusionConfig,
    sights: &mut S,
) -> (Vec<FusedChange>, Vec<FreeSpaceCheck>) {
    let mut objects = fuse_regions(regions, config);
    let mut test = FreeSpaceTest::new(&objects);
    if !test.is_empty() {
        sights.visit(&mut test);
    }
    let free_space = test.finish(&mut objects);
    (objects, free_space)
}

/// The free-space test of a fused list's confirmed `added` objects, frame by frame: each frame
/// ([`FreeSpaceTest::add`]) votes on every object whose inner points ([`inner_points_m`]) it
/// sees. A frame votes `through` when more of the points it sees are [`Sight::Through`] than
/// [`Sight::Agrees`], `agrees` when it has at least one agreeing and no more through, and
/// abstains otherwise (hidden, unseen or indistinct everywhere: a frame whose threshold there is
/// wider than the object stands off the model cannot vote for it). An object that more frames
/// see through than agree with is no longer confirmed ([`FreeSpaceTest::finish`]). `removed`
/// objects are not touched (the ground bounds those, [`super::model_ground_z_m`]). A frame's
/// vote on one object does not depend on the other frames, so frames may come in any order and
/// a frame whose footprint holds none of the points may be left out: the result is the same.
#[derive(Clone, Debug)]
pub struct FreeSpaceTest {
    /// Per tested object: its index in the fused list, its inner points, the frames that see
    /// through it and those that agree.
    tested: Vec<TestedObject>,
}

#[derive(Clone, Debug)]
struct TestedObject {
    object: usize,
    centroid_m: [f64; 3],
    points_m: Vec<Vector3<f64>>,
    seen_through_by: Vec<usize>,
    agreed_by: Vec<usize>,
}

impl FreeSpaceTest {
    /// The test of `objects`' confirmed `added` objects, no frame counted yet.
    pub fn new(objects: &[FusedChange]) -> Self {
        let tested = objects
            .iter()
            .enumerate()
            .filter(|(_, object)| object.kind == ChangeKind::Added && object.confirmed)
            .map(|(object, fused)| TestedObject {
                object,
                centroid_m: fused.centroid_m,
                points_m: inner_points_m(fused),
                seen_through_by: Vec::new(),
                agreed_by: Vec::new(),
            })
            .collect();
        Self { tested }
    }

    /// No object to test.
    pub fn is_empty(&self) -> bool {
        self.tested.is_empty()
    }

    /// Whether a frame with this footprint could vote on any tested object (one of its inner
    /// points falls on the frame's pixels).
    pub fn wants(&self, footprint: &FrameFootprint) -> bool {
        self.tested
            .iter()
            .any(|tested| footprint.sees_any(&tested.points_m))
    }

    /// The tested objects' inner points, by slot (the order [`FreeSpaceTest::count`] numbers
    /// them in).
    pub fn points_m(&self) -> impl Iterator<Item = &[Vector3<f64>]> {
        self.tested.iter().map(|tested| tested.points_m.as_slice())
    }

    /// Counts `frame`'s vote on the tested object in `slot` ([`FrameSight::vote`] on its
    /// points; a vote kept from an earlier test of the same points is the same vote).
    pub fn count(&mut self, slot: usize, frame: usize, vote: Vote) {
        let Some(tested) = self.tested.get_mut(slot) else {
            return;
        };
        match vote {
            Vote::Through => tested.seen_through_by.push(frame),
            Vote::Agrees => tested.agreed_by.push(frame),
            Vote::Abstains => {}
        }
    }

    /// Counts `frame`'s votes on every tested object.
    pub fn add(&mut self, frame: &FrameSight<'_>) {
        for slot in 0..self.tested.len() {
            let vote = frame.vote(&self.tested[slot].points_m);
            self.count(slot, frame.frame, vote);
        }
    }

    /// The test of every tested object; an object more frames see through than agree with is
    /// no longer confirmed in `objects` (the list the test was made from).
    pub fn finish(self, objects: &mut [FusedChange]) -> Vec<FreeSpaceCheck> {
        self.tested
            .into_iter()
            .map(|mut tested| {
                tested.seen_through_by.sort_unstable();
                tested.seen_through_by.dedup();
                tested.agreed_by.sort_unstable();
                tested.agreed_by.dedup();
                let refuted = tested.seen_through_by.len() > tested.agreed_by.len();
                if let Some(object) = objects.get_mut(tested.object).filter(|_| refuted) {
                    object.confirmed = false;
                }
                FreeSpaceCheck {
                    object: tested.object,
                    centroid_m: tested.centroid_m,
                    seen_through_by: tested.seen_through_by,
                    agreed_by: tested.agreed_by,
                    refuted,
                }
            })
            .collect()
    }
}

/// Tests each confirmed `added` object against every frame's sight ([`FreeSpaceTest`], every
/// frame given): the test of every confirmed `added` object.
pub fn check_free_space(
    objects: &mut [FusedChange],
    frames: &[FrameSight<'_>],
) -> Vec<FreeSpaceCheck> {
    let mut test = FreeSpaceTest::new(objects);
    for frame in frames {
        test.add(frame);
    }
    test.finish(objects)
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

    /// A frame sees no point outside its footprint: where `sees_any` is false the sight is
    /// `Unseen`, so the frames a footprint rules out could not have voted. Over a grid of points
    /// around and far from the frame, both cases occur.
    #[test]
    fn a_frame_sees_no_point_outside_its_footprint() {
        let roof = box_quads()[0];
        let f = frame(&mesh_of(&[ground()]), &mesh_of(&[ground(), roof]), 200.0);
        let sight = sight_of(0, &f);
        let footprint = SeenFrame::new(
            f.intrinsics,
            f.pose,
            f.photo.clone(),
            f.model.clone(),
            ChangeConfig::default(),
        )
        .footprint();
        let (mut inside, mut outside) = (0, 0);
        for x in (-100..=100).step_by(4) {
            for y in (-100..=100).step_by(4) {
                for z in [0.0, 5.0, 60.0] {
                    let point = Vector3::new(f64::from(x), f64::from(y), z);
                    if footprint.sees_any(&[point]) {
                        inside += 1;
                    } else {
                        outside += 1;
                        assert_eq!(sight.sight(&point), Sight::Unseen, "{point:?}");
                    }
                }
            }
        }
        assert!(inside > 100 && outside > 100, "{inside} / {outside}");
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
