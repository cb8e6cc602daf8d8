//! Fusion of change regions across frames: regions of the same kind whose footprints (in the
//! model's georeferenced x, y) overlap or lie within `merge_distance_m` are one object (merged
//! transitively); an object seen by at least `min_frames` distinct frames is confirmed, the
//! rest stay unconfirmed. This is what makes a change map robust to one frame's depth noise
//! and clutter.

use serde::{Deserialize, Serialize};

use super::polygon::{convex_distance, convex_hull, polygon_area};
use super::{ChangeKind, ChangeRegion};

/// How regions are merged.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionConfig {
    /// Footprints closer than this are one object, metres.
    pub merge_distance_m: f64,
    /// Distinct frames needed to confirm an object.
    pub min_frames: usize,
}

impl Default for FusionConfig {
    fn default() -> Self {
        Self {
            merge_distance_m: 1.0,
            min_frames: 2,
        }
    }
}

/// One fused changed object.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FusedChange {
    pub kind: ChangeKind,
    /// Indices of the frames that saw it (sorted, distinct), as the caller numbered them.
    pub frames: Vec<usize>,
    pub confirmed: bool,
    /// Convex hull of the merged footprints, counter-clockwise, metres (georeferenced).
    pub footprint_m: Vec<[f64; 2]>,
    pub footprint_area_m2: f64,
    /// Median of the regions' heights, metres.
    pub height_m: f64,
    /// Pixel-weighted mean of the regions' centroids, metres (georeferenced).
    pub centroid_m: [f64; 3],
    /// 1 − Π(1 − confidence) over the frames' best regions.
    pub confidence: f64,
    /// How many regions were merged.
    pub region_count: usize,
}

/// Union-find root of `i` (with path halving).
pub(crate) fn find(parent: &mut [usize], mut i: usize) -> usize {
    while parent[i] != i {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    i
}

/// Merges `(frame index, region)` pairs into objects, ordered by kind, then by decreasing
/// number of frames.
pub fn fuse_regions(regions: &[(usize, &ChangeRegion)], config: &FusionConfig) -> Vec<FusedChange> {
    let n = regions.len();
    let mut parent: Vec<usize> = (0..n).collect();
    for i in 0..n {
        for j in i + 1..n {
            let (a, b) = (regions[i].1, regions[j].1);
            if a.kind != b.kind {
                continue;
            }
            if convex_distance(&a.footprint_m, &b.footprint_m) <= config.merge_distance_m {
                let (ri, rj) = (find(&mut parent, i), find(&mut parent, j));
                if ri != rj {
                    parent[rj] = ri;
                }
            }
        }
    }
    let mut groups: std::collections::BTreeMap<usize, Vec<usize>> = Default::default();
    for i in 0..n {
        let root = find(&mut parent, i);
        groups.entry(root).or_default().push(i);
    }
    let mut fused: Vec<FusedChange> = groups
        .values()
        .map(|members| {
            let kind = regions[members[0]].1.kind;
            let mut frames: Vec<usize> = members.iter().map(|&m| regions[m].0).collect();
            frames.sort_unstable();
            frames.dedup();
            let points: Vec<[f64; 2]> = members
                .iter()
                .flat_map(|&m| regions[m].1.footprint_m.iter().copied())
                .collect();
            let footprint = convex_hull(&points);
            let mut heights: Vec<f64> = members.iter().map(|&m| regions[m].1.height_m).collect();
            heights.sort_by(f64::total_cmp);
            let weight: f64 = members
                .iter()
                .map(|&m| regions[m].1.pixel_count as f64)
                .sum::<f64>()
                .max(1.0);
            let mut centroid = [0.0; 3];
            for &m in members {
                let w = regions[m].1.pixel_count as f64 / weight;
                for (c, v) in centroid.iter_mut().zip(regions[m].1.centroid_m) {
                    *c += w * v;
                }
            }
            // Best confidence per frame, then combined as independent evidence.
            let miss: f64 = frames
                .iter()
                .map(|&f| {
                    let best = members
                        .iter()
                        .filter(|&&m| regions[m].0 == f)
                        .map(|&m| regions[m].1.confidence)
                        .fold(0.0f64, f64::max);
                    1.0 - best.clamp(0.0, 1.0)
                })
                .product();
            FusedChange {
                kind,
                confirmed: frames.len() >= config.min_frames,
                frames,
                footprint_area_m2: polygon_area(&footprint),
                footprint_m: footprint,
                height_m: heights[heights.len() / 2],
                centroid_m: centroid,
                confidence: 1.0 - miss,
                region_count: members.len(),
            }
        })
        .collect();
    fused.sort_by(|a, b| {
        a.kind
            .cmp(&b.kind)
            .then(b.frames.len().cmp(&a.frames.len()))
            .then(a.centroid_m[0].total_cmp(&b.centroid_m[0]))
    });
    fused
}

#[cfg(test)]
mod tests {
    use super::*;

    fn region(kind: ChangeKind, cx: f64, cy: f64, half: f64) -> ChangeRegion {
        let footprint = convex_hull(&[
            [cx - half, cy - half],
            [cx + half, cy - half],
            [cx + half, cy + half],
            [cx - half, cy + half],
        ]);
        ChangeRegion {
            kind,
            pixel_count: 100,
            surface_area_m2: 4.0 * half * half,
            footprint_area_m2: polygon_area(&footprint),
            height_m: 3.0,
            vertical_extent_m: 3.0,
            footprint_width_m: 2.0 * half,
            footprint_length_m: 2.0 * half,
            depth_difference_m: 3.0,
            centroid_m: [cx, cy, 1.5],
            footprint_m: footprint,
            confidence: 0.5,
            bbox_px: [0, 0, 10, 10],
        }
    }

    #[test]
    fn overlapping_regions_of_two_frames_are_one_confirmed_object() {
        let a = region(ChangeKind::Added, 10.0, 10.0, 2.0);
        let b = region(ChangeKind::Added, 11.0, 10.5, 2.0);
        let c = region(ChangeKind::Added, 40.0, 10.0, 2.0);
        let d = region(ChangeKind::Removed, 10.0, 10.0, 2.0);
        let e = region(ChangeKind::Added, 10.5, 10.0, 1.0);
        let fused = fuse_regions(
            &[(0, &a), (1, &b), (1, &c), (2, &d), (0, &e)],
            &FusionConfig::default(),
        );
        assert_eq!(fused.len(), 3, "{fused:?}");
        let first = &fused[0];
        assert_eq!(first.kind, ChangeKind::Added);
        assert_eq!(first.frames, vec![0, 1]);
        assert!(first.confirmed);
        assert_eq!(first.region_count, 3);
        assert!((first.confidence - 0.75).abs() < 1e-12);
        // Hull of [8, 12]² and [9, 13] × [8.5, 12.5]: 5 × 4.5 less two corner triangles.
        assert!((first.footprint_area_m2 - 22.0).abs() < 1e-9);
        let lonely = fused
            .iter()
            .find(|f| f.kind == ChangeKind::Added && f.frames == vec![1])
            .expect("the far region alone");
        assert!(!lonely.confirmed);
        let removed = fused
            .iter()
            .find(|f| f.kind == ChangeKind::Removed)
            .expect("removed kept apart");
        assert!(!removed.confirmed);
    }
}
