//! Stage "fusion": gathers the frames' change results (one per frame: the first kept, repeats
//! from redone change jobs ignored) and fuses their regions across frames into a ChangeSet,
//! the confirmed `added` objects tested against every frame's free space, by
//! `core::change::free_space::fuse_and_check` (what `asgreg changes` calls). The frames'
//! sights (their photo's and the model's depth, from the change workers' ChangeSight messages:
//! [`seen_frame`]) are kept until the end of the stream. The set is made in frame order, so it
//! does not depend on which worker finished first. After a restart, the results published
//! before it come back from the change journal and their sights from the state folder
//! (`restore`), so none is published twice and the set is the same as without the restart.

use std::collections::BTreeMap;

use crate::core::change::free_space::{fuse_and_check, SeenFrame};
use crate::core::change::fusion::FusionConfig;
use crate::core::change::ChangeRegion;
use crate::core::image::ImageView;
use crate::msg::{ChangeResult, ChangeSet, ChangeSight};

/// What a change worker's message says its frame saw, for the free-space test: `None` without a
/// change map; an error when its depths are not of its camera's size.
pub fn seen_frame(sight: &ChangeSight<'_>) -> Result<Option<SeenFrame>, String> {
    let Some(view) = &sight.meta.view else {
        return Ok(None);
    };
    let (photo, model) = match sight.depths() {
        Ok(Some(depths)) => depths,
        Ok(None) => return Ok(None),
        Err(error) => return Err(format!("its depth maps are unusable: {error}")),
    };
    Ok(Some(SeenFrame::new(
        view.camera.intrinsics,
        view.cam_from_world,
        ImageView::to_image(&photo),
        ImageView::to_image(&model),
        view.config,
    )))
}

pub struct FusionStage {
    config: FusionConfig,
    results: BTreeMap<u64, ChangeResult>,
    /// What each frame with a change map saw (its change worker's ChangeSight).
    seen: BTreeMap<u64, SeenFrame>,
    frame_count: Option<u64>,
    /// Change results for frames that already had one (redone jobs), ignored.
    pub late_messages: u64,
}

impl FusionStage {
    pub fn new(config: FusionConfig) -> Self {
        Self {
            config,
            results: BTreeMap::new(),
            seen: BTreeMap::new(),
            frame_count: None,
            late_messages: 0,
        }
    }

    /// A frame's change result and what the frame saw (`None`: no change map, or a frame
    /// without a pose, whose result verify sends): `Some` (to publish) when it is the frame's
    /// first.
    pub fn on_result(
        &mut self,
        result: ChangeResult,
        seen: Option<SeenFrame>,
    ) -> Option<&ChangeResult> {
        let frame_id = result.frame_id;
        if self.results.contains_key(&frame_id) {
            self.late_messages += 1;
            return None;
        }
        if let Some(seen) = seen {
            self.seen.insert(frame_id, seen);
        }
        Some(self.results.entry(frame_id).or_insert(result))
    }

    /// The frame's change result (kept by [`FusionStage::on_result`], not yet published) cannot
    /// be given out as it is (its journal line could not be written: `reason`): it becomes a
    /// failed change result with that reason and no regions, so the change set leaves it out too.
    pub fn withdraw(&mut self, frame_id: u64, reason: &str) -> Option<&ChangeResult> {
        let result = self.results.get_mut(&frame_id)?;
        result.failure = Some(match result.failure.take() {
            Some(earlier) => format!("{reason} (and before: {earlier})"),
            None => reason.to_string(),
        });
        result.regions.clear();
        result.counts = Default::default();
        self.seen.remove(&frame_id);
        Some(result)
    }

    /// A change result published before a restart of this stage (from the change journal)
    /// and what its frame saw (from the state folder): kept, so it is fused and tested and not
    /// published again.
    pub fn restore(&mut self, result: ChangeResult, seen: Option<SeenFrame>) {
        let frame_id = result.frame_id;
        if self.results.contains_key(&frame_id) {
            return;
        }
        if let Some(seen) = seen.filter(|_| result.failure.is_none()) {
            self.seen.insert(frame_id, seen);
        }
        self.results.insert(frame_id, result);
    }

    /// The source produced `frame_count` frames (ids 0..frame_count).
    pub fn on_stream_end(&mut self, frame_count: u64) {
        self.frame_count = Some(frame_count);
    }

    /// Frames with a change result.
    pub fn result_count(&self) -> usize {
        self.results.len()
    }

    /// Whether the end of the stream is known and every frame has its change result.
    pub fn is_complete(&self) -> bool {
        self.frame_count
            .is_some_and(|count| (0..count).all(|id| self.results.contains_key(&id)))
    }

    /// The regions of every frame so far fused into objects (their `frames` are frame ids),
    /// the confirmed `added` ones tested against every frame's free space.
    pub fn change_set(&self) -> ChangeSet {
        let regions: Vec<(usize, &ChangeRegion)> = self
            .results
            .iter()
            .flat_map(|(frame_id, result)| {
                result
                    .regions
                    .iter()
                    .map(move |region| (*frame_id as usize, region))
            })
            .collect();
        let (objects, free_space) = fuse_and_check(
            &regions,
            &self.config,
            self.seen
                .iter()
                .map(|(frame_id, seen)| (*frame_id as usize, seen)),
        );
        ChangeSet {
            complete: self.is_complete(),
            frame_count: self.frame_count,
            frames_with_result: self.results.len() as u64,
            frames_with_map: self
                .results
                .values()
                .filter(|r| r.failure.is_none())
                .count() as u64,
            objects,
            fusion: self.config,
            free_space,
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::core::change::free_space::FreeSpaceCheck;
    use crate::core::change::fusion::FusedChange;
    use crate::core::change::{ChangeKind, ClassCounts};
    use crate::stage::change::not_registered;

    fn square(x: f64) -> ChangeRegion {
        ChangeRegion {
            kind: ChangeKind::Added,
            pixel_count: 100,
            surface_area_m2: 30.0,
            footprint_area_m2: 16.0,
            height_m: 5.0,
            vertical_extent_m: 5.0,
            footprint_width_m: 4.0,
            footprint_length_m: 4.0,
            depth_difference_m: -5.0,
            centroid_m: [x + 2.0, 2.0, 2.5],
            footprint_m: vec![[x, 0.0], [x + 4.0, 0.0], [x + 4.0, 4.0], [x, 4.0]],
            confidence: 0.8,
            bbox_px: [0, 0, 10, 10],
        }
    }

    fn result(frame_id: u64, regions: Vec<ChangeRegion>) -> ChangeResult {
        ChangeResult {
            frame_id,
            name: format!("view_{frame_id}"),
            failure: None,
            counts: ClassCounts::default(),
            regions,
            change_ms: 1.0,
            change_worker: Some(0),
        }
    }

    #[test]
    fn one_result_per_frame_and_the_set_does_not_depend_on_arrival_order() {
        let arrivals = [
            result(2, vec![square(0.2)]),
            result(0, vec![square(0.0), square(50.0)]),
            not_registered(1, "view_1", Some("verify: too few inliers")),
        ];
        let mut forward = FusionStage::new(FusionConfig::default());
        let mut backward = FusionStage::new(FusionConfig::default());
        for r in arrivals.iter().cloned() {
            assert!(forward.on_result(r, None).is_some());
        }
        for r in arrivals.iter().rev().cloned() {
            assert!(backward.on_result(r, None).is_some());
        }
        // A redone job's second result is ignored.
        assert!(forward.on_result(result(2, Vec::new()), None).is_none());
        assert_eq!(forward.late_messages, 1);
        assert!(!forward.is_complete());
        forward.on_stream_end(3);
        backward.on_stream_end(3);
        assert!(forward.is_complete());
        let set = forward.change_set();
        assert_eq!(set, backward.change_set());
        assert!(set.complete);
        assert_eq!((set.frames_with_result, set.frames_with_map), (3, 2));
        assert_eq!(set.objects.len(), 2, "{:?}", set.objects);
        let confirmed: Vec<_> = set.objects.iter().filter(|o| o.confirmed).collect();
        assert_eq!(confirmed.len(), 1);
        assert_eq!(confirmed[0].frames, vec![0, 2]);
    }

    /// The azimuths of the free-space test's five oblique cameras around the origin.
    const AZIMUTHS_DEG: [f64; 5] = [200.0, 220.0, 20.0, 110.0, 300.0];

    /// The five change workers' messages of `core::change::free_space`'s test scene, as the
    /// change stage makes them from given depth maps and fusion receives them (through the
    /// wire): a ground-only model; a roof floating 5 m over the open ground in the depth of
    /// frames 0 and 1 only (their shared depth error), bare ground in frames 2–4.
    pub(crate) fn floating_roof_sights() -> Vec<ChangeSight<'static>> {
        use crate::core::camera::Camera;
        use crate::core::change::free_space::tests::{box_quads, camera, depth_of, ground};
        use crate::core::change::stereo::{NeighbourConfig, StereoConfig};
        use crate::core::change::tests::mesh_of;
        use crate::core::change::ChangeConfig;
        use crate::msg::{decode, encode, Body, ChangeJob, ChangeJobMeta, Envelope, FrameInfo};
        use crate::stage::change::{ChangeStage, StereoDepthSettings};
        use std::borrow::Cow;

        let model = mesh_of(&[ground()]);
        let floating = mesh_of(&[ground(), box_quads()[0]]);
        let stereo = StereoDepthSettings {
            neighbours: NeighbourConfig::default(),
            sweep: StereoConfig::default(),
            disparity_sigma_px: 0.5,
        };
        let mut change = ChangeStage::new(&model, ChangeConfig::default(), stereo, 0);
        AZIMUTHS_DEG
            .iter()
            .enumerate()
            .map(|(index, &azimuth_deg)| {
                let (intrinsics, pose) = camera(azimuth_deg);
                let photographed = if index < 2 { &floating } else { &model };
                let depth = depth_of(photographed, &intrinsics, &pose);
                let (w, h) = depth.size();
                let camera = Camera::pinhole(w as u32, h as u32, intrinsics);
                let job = ChangeJob {
                    meta: ChangeJobMeta {
                        info: FrameInfo {
                            name: format!("view_{index}"),
                            camera_id: 1,
                            camera,
                            intrinsics_known: true,
                            initial_cam_from_world: pose,
                            seed: 1,
                        },
                        camera,
                        cam_from_world: pose,
                        neighbours: Vec::new(),
                        pose_sigma_px: 0.0,
                    },
                    depth_m: Cow::Borrowed(depth.data()),
                    photo: Cow::Owned(Vec::new()),
                    neighbour_photos: Cow::Owned(Vec::new()),
                };
                let message = Envelope {
                    header: Default::default(),
                    body: Body::ChangeSight(change.process(index as u64, &job)),
                };
                let bytes = encode(&message).expect("encodes").to_vec();
                match decode(&bytes).expect("decodes").body {
                    Body::ChangeSight(sight) => ChangeSight {
                        meta: sight.meta,
                        photo_depth_m: Cow::Owned(sight.photo_depth_m.into_owned()),
                        model_depth_m: Cow::Owned(sight.model_depth_m.into_owned()),
                    },
                    other => panic!("a {:?}", other.kind()),
                }
            })
            .collect()
    }

    /// The fused `added` objects of `stage`'s change set and its free-space tests.
    fn added(stage: &FusionStage) -> (Vec<FusedChange>, Vec<FreeSpaceCheck>) {
        let set = stage.change_set();
        let objects = set
            .objects
            .into_iter()
            .filter(|o| o.kind == ChangeKind::Added)
            .collect();
        (objects, set.free_space)
    }

    /// The pipeline's fusion leaves unconfirmed an `added` object that more frames see through
    /// than agree with, as `asgreg changes` does: each change worker's ChangeSight carries its
    /// frame's depths through the wire into the fusion stage, which runs the same
    /// `check_free_space` after `fuse_regions`. Without the frames' sights (the ChangeResults
    /// alone, as before schema v7) fusion confirms the object: two frames agree in position and
    /// height.
    #[test]
    fn fusion_does_not_confirm_an_added_object_other_frames_see_through() {
        let sights = floating_roof_sights();
        let mut with_sights = FusionStage::new(FusionConfig::default());
        let mut results_only = FusionStage::new(FusionConfig::default());
        for sight in &sights {
            let seen = seen_frame(sight).expect("usable depths");
            assert!(seen.is_some(), "{:?}", sight.meta.result);
            assert!(with_sights
                .on_result(sight.meta.result.clone(), seen)
                .is_some());
            results_only.on_result(sight.meta.result.clone(), None);
        }
        with_sights.on_stream_end(5);
        results_only.on_stream_end(5);

        let (objects, checks) = added(&results_only);
        assert_eq!(objects.len(), 1, "{objects:?}");
        assert_eq!(objects[0].frames, vec![0, 1]);
        assert!(objects[0].confirmed, "fusion alone confirms it");
        assert!(
            checks
                .iter()
                .all(|c| !c.refuted && c.seen_through_by.is_empty() && c.agreed_by.is_empty()),
            "no sight, no vote: {checks:?}"
        );

        let (objects, checks) = added(&with_sights);
        assert_eq!(objects.len(), 1, "{objects:?}");
        assert_eq!(objects[0].frames, vec![0, 1]);
        assert!(!objects[0].confirmed, "{checks:?}");
        assert_eq!(checks.len(), 1);
        assert!(checks[0].refuted);
        assert_eq!(checks[0].seen_through_by, vec![2, 3, 4]);
        assert_eq!(checks[0].agreed_by, vec![0, 1]);
    }

    #[test]
    fn a_stream_with_a_frame_missing_is_not_complete() {
        let mut stage = FusionStage::new(FusionConfig::default());
        stage.on_stream_end(2);
        stage.on_result(result(1, Vec::new()), None);
        assert!(!stage.is_complete());
        assert!(!stage.change_set().complete);
    }
}
