//! Stage "fusion": gathers the frames' change results (one per frame: the first kept, repeats
//! from redone change jobs ignored) and fuses their regions across frames into a ChangeSet by
//! `core::change::fusion::fuse_regions` (the function `asgreg changes` calls). The set is made
//! in frame order, so it does not depend on which worker finished first. After a restart, the
//! results published before it come back from the change journal (`restore`), so none is
//! published twice and the set is the same as without the restart.

use std::collections::BTreeMap;

use crate::core::change::fusion::{fuse_regions, FusionConfig};
use crate::core::change::ChangeRegion;
use crate::msg::{ChangeResult, ChangeSet};

pub struct FusionStage {
    config: FusionConfig,
    results: BTreeMap<u64, ChangeResult>,
    frame_count: Option<u64>,
    /// Change results for frames that already had one (redone jobs), ignored.
    pub late_messages: u64,
}

impl FusionStage {
    pub fn new(config: FusionConfig) -> Self {
        Self {
            config,
            results: BTreeMap::new(),
            frame_count: None,
            late_messages: 0,
        }
    }

    /// A frame's change result: `Some` (to publish) when it is the frame's first.
    pub fn on_result(&mut self, result: ChangeResult) -> Option<&ChangeResult> {
        let frame_id = result.frame_id;
        if self.results.contains_key(&frame_id) {
            self.late_messages += 1;
            return None;
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
        Some(result)
    }

    /// A change result published before a restart of this stage (from the change journal):
    /// kept, so it is fused and not published again.
    pub fn restore(&mut self, result: ChangeResult) {
        self.results.entry(result.frame_id).or_insert(result);
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

    /// The regions of every frame so far fused into objects (their `frames` are frame ids).
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
        ChangeSet {
            complete: self.is_complete(),
            frame_count: self.frame_count,
            frames_with_result: self.results.len() as u64,
            frames_with_map: self
                .results
                .values()
                .filter(|r| r.failure.is_none())
                .count() as u64,
            objects: fuse_regions(&regions, &self.config),
            fusion: self.config,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
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
            assert!(forward.on_result(r).is_some());
        }
        for r in arrivals.iter().rev().cloned() {
            assert!(backward.on_result(r).is_some());
        }
        // A redone job's second result is ignored.
        assert!(forward.on_result(result(2, Vec::new())).is_none());
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

    #[test]
    fn a_stream_with_a_frame_missing_is_not_complete() {
        let mut stage = FusionStage::new(FusionConfig::default());
        stage.on_stream_end(2);
        stage.on_result(result(1, Vec::new()));
        assert!(!stage.is_complete());
        assert!(!stage.change_set().complete);
    }
}
