//! Stage "fusion": gathers the frames' change results (one per frame: the first kept, repeats
//! from redone change jobs ignored) and fuses their regions across frames into a ChangeSet,
//! the confirmed `added` objects tested against every frame's free space, by
//! `core::change::free_space::fuse_and_check` (what `asgreg changes` calls). The set is made in
//! frame order, so it does not depend on which worker finished first. After a restart, the
//! results published before it come back from the change journal and their sights from the
//! state folder (`restore`, `restore_sight`), so none is published twice and the set is the
//! same as without the restart.
//!
//! The frames' sights (their photo's and the model's depth, from the change workers'
//! ChangeSight messages: [`seen_frame`]) are 1–2 MB each, so a live stream cannot keep them all:
//! [`KeptSights`] keeps every frame's footprint (camera, pose, map size; a few hundred bytes),
//! and the maps of at most `max_bytes` of frames in memory, the least recently used leaving
//! first once they are on disk (`runtime::sights` writes them; a [`SightReader`] reads them
//! back when the free-space test needs a frame whose footprint sees an object). Each frame's
//! vote on an object is kept by the object's inner points (a frame's sight never changes), so a
//! change set reads only the frames that see an object whose points moved since the last one
//! and the frames new since. The votes, and so the change set, are the same as with every map in
//! memory.

use std::collections::{BTreeMap, HashMap};

use nalgebra::Vector3;

use crate::core::change::free_space::{
    fuse_and_check, FrameFootprint, FreeSpaceTest, SeenFrame, SightSource, Vote,
};
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

/// Where fusion finds a sight it no longer holds in memory (`runtime::sights`: the state
/// folder).
pub trait SightReader {
    /// Frame `frame_id`'s sight as it was kept; the error names the file and what is wrong
    /// with it (missing, unreadable, another frame's, no change map).
    fn read(&mut self, frame_id: u64) -> Result<SeenFrame, String>;
}

/// One frame's maps held in memory.
struct HeldSight {
    seen: SeenFrame,
    /// Its file can give it back ([`SightReader`]): it may leave memory.
    on_disk: bool,
    /// When the free-space test last read it (or it came), for least-recently-used eviction.
    last_used: u64,
}

/// What fusion knows of the frames' sights and how much of them it holds.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SightMemory {
    /// Frames with a sight (footprints kept).
    pub frames: usize,
    /// Of them, frames whose maps are in memory now.
    pub frames_held: usize,
    /// Bytes of maps in memory now, and at most so far.
    pub held_bytes: usize,
    pub peak_bytes: usize,
    /// The bound (`None`: unbounded, nothing leaves memory).
    pub max_bytes: Option<usize>,
    /// Sights read back from disk for the free-space test.
    pub loads: u64,
    /// Frames whose sight could not be read back, and why (they no longer vote).
    pub lost: BTreeMap<u64, String>,
}

/// Every frame's footprint, and the maps of the frames the memory bound allows (the others
/// read back from disk by a [`SightReader`] when the free-space test wants them). Without a
/// reader every sight stays in memory.
pub struct KeptSights {
    footprints: BTreeMap<u64, FrameFootprint>,
    held: BTreeMap<u64, HeldSight>,
    reader: Option<Box<dyn SightReader>>,
    clock: u64,
    /// Frames that could not leave memory while over the bound, warned once.
    warned_pinned: bool,
    /// Each frame's vote on the objects of the last test, by the object's inner points (their
    /// f64 bits: the same points, the same vote).
    votes: HashMap<Vec<u64>, BTreeMap<u64, Vote>>,
    memory: SightMemory,
}

/// The key of an object's inner points in the kept votes: their exact bits.
fn points_key(points_m: &[Vector3<f64>]) -> Vec<u64> {
    points_m
        .iter()
        .flat_map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
        .collect()
}

impl KeptSights {
    /// Every sight in memory.
    pub fn unbounded() -> Self {
        Self {
            footprints: BTreeMap::new(),
            held: BTreeMap::new(),
            reader: None,
            clock: 0,
            warned_pinned: false,
            votes: HashMap::new(),
            memory: SightMemory::default(),
        }
    }

    /// At most `max_bytes` of maps in memory (0: only while the test reads them); the others
    /// read back by `reader`.
    pub fn bounded(max_bytes: usize, reader: Box<dyn SightReader>) -> Self {
        let mut kept = Self::unbounded();
        kept.reader = Some(reader);
        kept.memory.max_bytes = Some(max_bytes);
        kept
    }

    /// How much is held, read back and lost.
    pub fn memory(&self) -> SightMemory {
        SightMemory {
            frames: self.footprints.len(),
            frames_held: self.held.len(),
            ..self.memory.clone()
        }
    }

    fn tick(&mut self) -> u64 {
        self.clock += 1;
        self.clock
    }

    /// Keeps `frame_id`'s sight (`on_disk`: its file can give it back).
    fn insert(&mut self, frame_id: u64, seen: SeenFrame, on_disk: bool) {
        self.footprints.insert(frame_id, seen.footprint());
        self.memory.lost.remove(&frame_id);
        let last_used = self.tick();
        self.memory.held_bytes += seen.map_bytes();
        if let Some(old) = self.held.insert(
            frame_id,
            HeldSight {
                seen,
                on_disk,
                last_used,
            },
        ) {
            self.memory.held_bytes -= old.seen.map_bytes();
        }
        self.memory.peak_bytes = self.memory.peak_bytes.max(self.memory.held_bytes);
        self.evict();
    }

    /// `frame_id`'s sight is on disk now: it may leave memory.
    fn mark_on_disk(&mut self, frame_id: u64) {
        if let Some(held) = self.held.get_mut(&frame_id) {
            held.on_disk = true;
            self.evict();
        }
    }

    fn remove(&mut self, frame_id: u64) {
        self.footprints.remove(&frame_id);
        for votes in self.votes.values_mut() {
            votes.remove(&frame_id);
        }
        if let Some(old) = self.held.remove(&frame_id) {
            self.memory.held_bytes -= old.seen.map_bytes();
        }
    }

    /// Drops the least recently used maps that are on disk until the held bytes are within the
    /// bound (none without a reader: nothing could read them back).
    fn evict(&mut self) {
        let Some(max_bytes) = self.memory.max_bytes.filter(|_| self.reader.is_some()) else {
            return;
        };
        while self.memory.held_bytes > max_bytes {
            let oldest = self
                .held
                .iter()
                .filter(|(_, held)| held.on_disk)
                .min_by_key(|(_, held)| held.last_used)
                .map(|(frame_id, _)| *frame_id);
            let Some(frame_id) = oldest else {
                if !self.warned_pinned {
                    tracing::warn!(
                        "fusion: {:.1} MB of sights in memory, over the bound of {:.1} MB (fusion.max_sights_in_memory_mb): the sights that could not be written to the state folder stay in memory",
                        self.memory.held_bytes as f64 / 1e6,
                        max_bytes as f64 / 1e6
                    );
                    self.warned_pinned = true;
                }
                return;
            };
            if let Some(old) = self.held.remove(&frame_id) {
                self.memory.held_bytes -= old.seen.map_bytes();
            }
        }
    }
}

impl SightSource for KeptSights {
    /// Per frame, the tested objects its footprint sees. A frame whose votes on them are all
    /// kept counts them without its sight. Otherwise the frames in memory are voted first (no
    /// read), then the others read back one at a time (each may push out a frame already
    /// counted). A frame that cannot be read back is warned (naming it and its file) and no
    /// longer votes. The votes of objects no longer tested are dropped.
    fn visit(&mut self, test: &mut FreeSpaceTest) {
        let points: Vec<Vec<Vector3<f64>>> = test.points_m().map(|p| p.to_vec()).collect();
        let keys: Vec<Vec<u64>> = points.iter().map(|p| points_key(p)).collect();
        self.votes.retain(|key, _| keys.contains(key));
        for key in &keys {
            self.votes.entry(key.clone()).or_default();
        }
        let mut in_memory = Vec::new();
        let mut to_read = Vec::new();
        for (&frame_id, footprint) in &self.footprints {
            let slots: Vec<usize> = (0..points.len())
                .filter(|&slot| footprint.sees_any(&points[slot]))
                .collect();
            if slots.is_empty() {
                continue;
            }
            let kept: Option<Vec<Vote>> = slots
                .iter()
                .map(|&slot| {
                    self.votes
                        .get(&keys[slot])
                        .and_then(|votes| votes.get(&frame_id).copied())
                })
                .collect();
            match kept {
                Some(kept) => {
                    for (&slot, vote) in slots.iter().zip(kept) {
                        test.count(slot, frame_id as usize, vote);
                    }
                }
                None if self.held.contains_key(&frame_id) => in_memory.push((frame_id, slots)),
                None => to_read.push((frame_id, slots)),
            }
        }
        let vote = |votes: &mut HashMap<Vec<u64>, BTreeMap<u64, Vote>>,
                    test: &mut FreeSpaceTest,
                    frame_id: u64,
                    slots: &[usize],
                    seen: &SeenFrame| {
            let sight = seen.sight(frame_id as usize);
            for &slot in slots {
                let vote = sight.vote(&points[slot]);
                test.count(slot, frame_id as usize, vote);
                if let Some(kept) = votes.get_mut(&keys[slot]) {
                    kept.insert(frame_id, vote);
                }
            }
        };
        for (frame_id, slots) in in_memory {
            let now = self.tick();
            if let Some(held) = self.held.get_mut(&frame_id) {
                held.last_used = now;
                vote(&mut self.votes, test, frame_id, &slots, &held.seen);
            }
        }
        for (frame_id, slots) in to_read {
            let read = match self.reader.as_mut() {
                Some(reader) => reader.read(frame_id),
                None => Err("no sight file to read it from".to_string()),
            };
            match read {
                Ok(seen) => {
                    self.memory.loads += 1;
                    vote(&mut self.votes, test, frame_id, &slots, &seen);
                    self.insert(frame_id, seen, true);
                }
                Err(why) => {
                    tracing::warn!(
                        "fusion: frame {frame_id}: its sight cannot be read back ({why}); it no longer votes in the free-space test (its change result stands)"
                    );
                    self.remove(frame_id);
                    self.memory.lost.insert(frame_id, why);
                }
            }
        }
    }
}

pub struct FusionStage {
    config: FusionConfig,
    results: BTreeMap<u64, ChangeResult>,
    /// What each frame with a change map saw (its change worker's ChangeSight).
    sights: KeptSights,
    frame_count: Option<u64>,
    /// Change results for frames that already had one (redone jobs), ignored.
    pub late_messages: u64,
}

impl FusionStage {
    /// Every sight kept in memory.
    pub fn new(config: FusionConfig) -> Self {
        Self::with_sights(config, KeptSights::unbounded())
    }

    /// The sights kept as `sights` says (bounded: [`KeptSights::bounded`]).
    pub fn with_sights(config: FusionConfig, sights: KeptSights) -> Self {
        Self {
            config,
            results: BTreeMap::new(),
            sights,
            frame_count: None,
            late_messages: 0,
        }
    }

    /// Whether `frame_id` has its change result.
    pub fn has_result(&self, frame_id: u64) -> bool {
        self.results.contains_key(&frame_id)
    }

    /// A frame's change result and what the frame saw (`None`: no change map, or a frame
    /// without a pose, whose result verify sends): `Some` (to publish) when it is the frame's
    /// first. Its sight stays in memory until [`FusionStage::sight_on_disk`].
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
            self.sights.insert(frame_id, seen, false);
        }
        Some(self.results.entry(frame_id).or_insert(result))
    }

    /// The sight of `frame_id` is on disk: it may leave memory (read back when needed).
    pub fn sight_on_disk(&mut self, frame_id: u64) {
        self.sights.mark_on_disk(frame_id);
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
        self.sights.remove(frame_id);
        Some(result)
    }

    /// A change result published before a restart of this stage (from the change journal):
    /// kept, so it is fused and tested and not published again.
    pub fn restore(&mut self, result: ChangeResult) {
        self.results.entry(result.frame_id).or_insert(result);
    }

    /// What a frame whose change result was restored saw (from the state folder, so on disk):
    /// kept when its result has a change map; ignored for a frame without a restored result
    /// (its change work is redone and brings its sight again).
    pub fn restore_sight(&mut self, frame_id: u64, seen: SeenFrame) {
        let usable = self
            .results
            .get(&frame_id)
            .is_some_and(|result| result.failure.is_none());
        if usable && !self.sights.footprints.contains_key(&frame_id) {
            self.sights.insert(frame_id, seen, true);
        }
    }

    /// The source produced `frame_count` frames (ids 0..frame_count).
    pub fn on_stream_end(&mut self, frame_count: u64) {
        self.frame_count = Some(frame_count);
    }

    /// Frames with a change result.
    pub fn result_count(&self) -> usize {
        self.results.len()
    }

    /// How much of the frames' sights is in memory, read back and lost.
    pub fn sight_memory(&self) -> SightMemory {
        self.sights.memory()
    }

    /// Whether the end of the stream is known and every frame has its change result.
    pub fn is_complete(&self) -> bool {
        self.frame_count
            .is_some_and(|count| (0..count).all(|id| self.results.contains_key(&id)))
    }

    /// The regions of every frame so far fused into objects (their `frames` are frame ids),
    /// the confirmed `added` ones tested against the free space of every frame that can see
    /// them (sights not in memory read back).
    pub fn change_set(&mut self) -> ChangeSet {
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
        let (objects, free_space) = fuse_and_check(&regions, &self.config, &mut self.sights);
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
    fn added(stage: &mut FusionStage) -> (Vec<FusedChange>, Vec<FreeSpaceCheck>) {
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

        let (objects, checks) = added(&mut results_only);
        assert_eq!(objects.len(), 1, "{objects:?}");
        assert_eq!(objects[0].frames, vec![0, 1]);
        assert!(objects[0].confirmed, "fusion alone confirms it");
        assert!(
            checks
                .iter()
                .all(|c| !c.refuted && c.seen_through_by.is_empty() && c.agreed_by.is_empty()),
            "no sight, no vote: {checks:?}"
        );

        let (objects, checks) = added(&mut with_sights);
        assert_eq!(objects.len(), 1, "{objects:?}");
        assert_eq!(objects[0].frames, vec![0, 1]);
        assert!(!objects[0].confirmed, "{checks:?}");
        assert_eq!(checks.len(), 1);
        assert!(checks[0].refuted);
        assert_eq!(checks[0].seen_through_by, vec![2, 3, 4]);
        assert_eq!(checks[0].agreed_by, vec![0, 1]);
    }

    /// Sights kept as wire messages (as the state folder keeps them), each read counted.
    struct CountingReader {
        messages: BTreeMap<u64, Vec<u8>>,
        reads: std::rc::Rc<std::cell::RefCell<BTreeMap<u64, usize>>>,
    }

    impl SightReader for CountingReader {
        fn read(&mut self, frame_id: u64) -> Result<SeenFrame, String> {
            *self.reads.borrow_mut().entry(frame_id).or_default() += 1;
            let bytes = self
                .messages
                .get(&frame_id)
                .ok_or_else(|| format!("no message of frame {frame_id}"))?;
            match crate::msg::decode(bytes).map_err(|e| e.to_string())?.body {
                crate::msg::Body::ChangeSight(sight) => {
                    seen_frame(&sight)?.ok_or_else(|| "no map".to_string())
                }
                other => Err(format!("a {:?}", other.kind())),
            }
        }
    }

    /// The bounded fusion reads back only the frames whose footprint holds one of the object's
    /// inner points, and its change set is the one of `check_free_space` over every frame's
    /// sight (today's test, no footprint in it): a sixth frame looking at open ground 300 m
    /// away is never read, and with every sight in memory it does not vote either.
    #[test]
    fn a_bounded_fusion_reads_only_the_frames_that_can_see_an_object() {
        use crate::core::change::free_space::{check_free_space, FrameSight};
        use crate::core::change::fusion::fuse_regions;
        use crate::core::rigid::Rigid3;
        use nalgebra::Vector3;

        let mut sights = floating_roof_sights();
        let mut away = sights[2].clone();
        away.meta.result.frame_id = 5;
        away.meta.result.name = "view_5".to_string();
        if let Some(view) = away.meta.view.as_mut() {
            view.cam_from_world = Rigid3::look_at(
                &Vector3::new(330.0, 0.0, 40.0),
                &Vector3::new(300.0, 0.0, 0.0),
                &Vector3::z(),
            )
            .expect("a valid pose");
        }
        sights.push(away);
        let seen: Vec<SeenFrame> = sights
            .iter()
            .map(|s| seen_frame(s).expect("usable").expect("a map"))
            .collect();

        // Today's test: every frame's sight, no footprint.
        let regions: Vec<(usize, &ChangeRegion)> = sights
            .iter()
            .enumerate()
            .flat_map(|(i, s)| s.meta.result.regions.iter().map(move |r| (i, r)))
            .collect();
        let mut objects = fuse_regions(&regions, &FusionConfig::default());
        let frames: Vec<FrameSight<'_>> =
            seen.iter().enumerate().map(|(i, s)| s.sight(i)).collect();
        let checks = check_free_space(&mut objects, &frames);
        assert_eq!(checks.len(), 1);
        assert_eq!(checks[0].seen_through_by, vec![2, 3, 4]);

        let reads = std::rc::Rc::new(std::cell::RefCell::new(BTreeMap::new()));
        let reader = CountingReader {
            messages: sights
                .iter()
                .enumerate()
                .map(|(i, sight)| {
                    let bytes = crate::msg::encode(&crate::msg::Envelope {
                        header: Default::default(),
                        body: crate::msg::Body::ChangeSight(sight.clone()),
                    })
                    .expect("encodes")
                    .to_vec();
                    (i as u64, bytes)
                })
                .collect(),
            reads: reads.clone(),
        };
        let mut bounded = FusionStage::with_sights(
            FusionConfig::default(),
            KeptSights::bounded(0, Box::new(reader)),
        );
        let mut unbounded = FusionStage::new(FusionConfig::default());
        for (i, (sight, seen)) in sights.iter().zip(&seen).enumerate() {
            bounded.on_result(sight.meta.result.clone(), Some(seen.clone()));
            bounded.sight_on_disk(i as u64);
            unbounded.on_result(sight.meta.result.clone(), Some(seen.clone()));
        }
        bounded.on_stream_end(6);
        unbounded.on_stream_end(6);
        let set = bounded.change_set();
        assert_eq!(set.objects, objects);
        assert_eq!(set.free_space, checks);
        assert_eq!(unbounded.change_set(), set);
        let reads = reads.borrow();
        assert_eq!(reads.get(&5), None, "the frame looking away was read");
        assert_eq!(reads.len(), 5, "{reads:?}");
        assert_eq!(bounded.sight_memory().held_bytes, 0);
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
