//! The evaluation protocol of docs/design.md §3, as numbers and tables: per initial-error level, the share
//! of accepted frames, mean ± std and range of δ(P_out, P_gt) over accepted frames, and false
//! accepts (accepted, but δ to ground truth above a fraction of the long side). Kept apart from
//! the command line so the statistics are tested on their own.

use serde::{Deserialize, Serialize};

use crate::core::confidence::FrameEvidence;
use crate::core::frame::{Pass, StageTimings};

/// One frame of one evaluation run.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalFrame {
    pub name: String,
    /// δ(P_in, P_gt), px.
    pub initial_delta_px: f64,
    pub accepted: bool,
    /// δ(P_out, P_gt) of the output pose, px (also for rejected frames that had one; None when
    /// there was no pose at all).
    pub final_delta_px: Option<f64>,
    pub confidence: f64,
    /// What the decision rested on (for calibrating the confidence); None for baselines and
    /// frames that were not registered.
    pub evidence: Option<FrameEvidence>,
    pub reason: Option<String>,
    pub total_ms: f64,
    /// When the full-circle heading fallback ran: both registrations against the truth, and
    /// which one the fields above are.
    #[serde(default)]
    pub heading_sweep: Option<SweepEval>,
    /// The registration's time per step and its number of coarse views (None for baselines
    /// and frames that were not registered).
    #[serde(default)]
    pub timings: Option<StageTimings>,
    /// Step "neighbour" (on unless `--no-neighbours`): each registered neighbour tried for the frame.
    #[serde(default)]
    pub neighbours: Vec<NeighbourEval>,
}

/// One registered neighbour tried for an [`EvalFrame`] (step "neighbour").
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct NeighbourEval {
    pub neighbour: String,
    /// Neighbours away from a frame the model accepted on its own.
    pub steps: usize,
    /// Where the neighbour's photo was matched from.
    #[serde(default)]
    pub view: crate::core::frame::NeighbourView,
    /// δ of the neighbour's pose of the frame to the truth, px (None without a pose).
    pub delta_px: Option<f64>,
    /// δ between it and the frame's own pose, px.
    pub apart_px: Option<f64>,
    /// The photo's edge support at it and its peak.
    pub peak: Option<crate::core::edge_align::SupportPeak>,
    /// RANSAC consensus and matches of the neighbour's pose.
    pub consensus: Option<(usize, usize)>,
    /// What the model said of it.
    pub outcome: String,
}

/// The heading fallback's two registrations of an [`EvalFrame`].
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SweepEval {
    pub first: PassEval,
    /// None when the retry gave no result (an error, in `reason` of the frame's log).
    pub retry: Option<PassEval>,
    pub carried: Pass,
    pub sweep_ms: f64,
}

/// One registration of a frame against the truth.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PassEval {
    pub accepted: bool,
    pub confidence: f64,
    /// δ(its output or would-be output, P_gt), px.
    pub delta_px: Option<f64>,
    pub reason: Option<String>,
}

impl PassEval {
    /// The verdict as tables print it: "accepted" or the reason, and the confidence.
    pub fn verdict_text(&self) -> String {
        format!(
            "{} ({:.2})",
            if self.accepted {
                "accepted"
            } else {
                self.reason.as_deref().unwrap_or("rejected")
            },
            self.confidence
        )
    }
}

/// Statistics of one (level, method) cell.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CellStats {
    pub frames: usize,
    pub accepted: usize,
    pub accepted_percent: f64,
    /// Over accepted frames, px.
    pub mean_px: Option<f64>,
    pub std_px: Option<f64>,
    pub min_px: Option<f64>,
    pub max_px: Option<f64>,
    /// Accepted frames whose δ to ground truth exceeds the false-accept threshold.
    pub false_accepts: usize,
    pub mean_initial_px: f64,
    pub mean_ms_per_frame: f64,
}

/// Statistics of a set of frames; `false_accept_px` is the δ above which an accepted frame is a
/// false accept.
pub fn cell_stats(frames: &[EvalFrame], false_accept_px: f64) -> CellStats {
    let accepted: Vec<f64> = frames
        .iter()
        .filter(|f| f.accepted)
        .filter_map(|f| f.final_delta_px)
        .collect();
    let n = accepted.len();
    let mean = (n > 0).then(|| accepted.iter().sum::<f64>() / n as f64);
    let std =
        mean.map(|m| (accepted.iter().map(|d| (d - m).powi(2)).sum::<f64>() / n as f64).sqrt());
    let count = frames.len().max(1) as f64;
    CellStats {
        frames: frames.len(),
        accepted: frames.iter().filter(|f| f.accepted).count(),
        accepted_percent: 100.0 * frames.iter().filter(|f| f.accepted).count() as f64 / count,
        mean_px: mean,
        std_px: std,
        min_px: accepted.iter().copied().reduce(f64::min),
        max_px: accepted.iter().copied().reduce(f64::max),
        false_accepts: accepted.iter().filter(|d| **d > false_accept_px).count(),
        mean_initial_px: frames.iter().map(|f| f.initial_delta_px).sum::<f64>() / count,
        mean_ms_per_frame: frames.iter().map(|f| f.total_ms).sum::<f64>() / count,
    }
}

/// One confidence bin of a calibration table: frames with an output pose (accepted or not) whose
/// confidence lies in `[lower, upper)` (the last bin includes 1), and how many of them are
/// correct (δ to ground truth at most the false-accept threshold).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationBin {
    pub lower: f64,
    pub upper: f64,
    pub frames: usize,
    pub correct: usize,
    /// Of these frames, how many were accepted.
    pub accepted: usize,
}

/// The share of correct poses per confidence bin (`bins` equal bins over 0..1), over every frame
/// that has an output pose: a calibrated confidence has about `(lower + upper) / 2` correct.
pub fn calibration_bins<'a>(
    frames: impl IntoIterator<Item = &'a EvalFrame>,
    false_accept_px: f64,
    bins: usize,
) -> Vec<CalibrationBin> {
    let bins = bins.max(1);
    let mut table: Vec<CalibrationBin> = (0..bins)
        .map(|i| CalibrationBin {
            lower: i as f64 / bins as f64,
            upper: (i + 1) as f64 / bins as f64,
            frames: 0,
            correct: 0,
            accepted: 0,
        })
        .collect();
    for frame in frames {
        let Some(delta_px) = frame.final_delta_px else {
            continue;
        };
        let index = ((frame.confidence.clamp(0.0, 1.0) * bins as f64) as usize).min(bins - 1);
        let bin = &mut table[index];
        bin.frames += 1;
        bin.correct += usize::from(delta_px <= false_accept_px);
        bin.accepted += usize::from(frame.accepted);
    }
    table
}

/// A `results.json` of `asgreg eval`, as `calibrate` and `compare` read it back.
#[derive(Clone, Debug, Deserialize)]
pub struct EvalResults {
    pub false_accept_threshold_px: f64,
    pub cells: Vec<EvalCell>,
}

/// One (level, method) cell of an [`EvalResults`].
#[derive(Clone, Debug, Deserialize)]
pub struct EvalCell {
    /// The initial-error level: px, or a named level such as `"heading"`.
    #[serde(default)]
    pub level_px: serde_json::Value,
    pub method: String,
    pub frames: Vec<EvalFrame>,
}

impl EvalCell {
    /// The level as tables print it (`30`, `heading`).
    pub fn level_text(&self) -> String {
        match &self.level_px {
            serde_json::Value::String(text) => text.clone(),
            serde_json::Value::Null => "?".to_string(),
            other => other.to_string(),
        }
    }
}

/// Two evaluations of the same frames, frame by frame: what a change to the method did. The
/// cells' own statistics move with every frame that flips between accepted and rejected, so the
/// comparison also gives the paired figure (δ of the frames both accepted) and each frame that
/// changed.
#[derive(Clone, Debug, PartialEq)]
pub struct Comparison {
    /// Frames present in both (by name).
    pub frames: usize,
    pub base: ComparedSide,
    pub new: ComparedSide,
    /// Frames both accepted, and their mean δ before and after, px.
    pub both_accepted: usize,
    pub both_accepted_mean_px: Option<(f64, f64)>,
    /// Frames whose acceptance flipped or whose δ moved by more than the comparison's
    /// `changed_px`, in name order.
    pub changed: Vec<FrameChange>,
}

/// One side of a [`Comparison`], over the frames both evaluations hold.
#[derive(Clone, Debug, PartialEq)]
pub struct ComparedSide {
    pub accepted: usize,
    /// Mean δ of the accepted frames within the false-accept threshold, px.
    pub correct_mean_px: Option<f64>,
    /// δ of each false accept, px.
    pub false_accepts_px: Vec<f64>,
}

/// A frame that changed between two evaluations.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameChange {
    pub name: String,
    pub base: (bool, Option<f64>),
    pub new: (bool, Option<f64>),
    /// The new evaluation's reason for rejecting it.
    pub new_reason: Option<String>,
}

/// Compares two evaluations of the same frames (matched by name; frames only one holds are left
/// out). A frame "changed" when its acceptance flipped or its δ moved by more than `changed_px`.
pub fn compare_frames(
    base: &[EvalFrame],
    new: &[EvalFrame],
    false_accept_px: f64,
    changed_px: f64,
) -> Comparison {
    let by_name: std::collections::BTreeMap<&str, &EvalFrame> =
        new.iter().map(|f| (f.name.as_str(), f)).collect();
    let mut pairs: Vec<(&EvalFrame, &EvalFrame)> = base
        .iter()
        .filter_map(|b| by_name.get(b.name.as_str()).map(|n| (b, *n)))
        .collect();
    pairs.sort_by(|a, b| a.0.name.cmp(&b.0.name));
    let both: Vec<(f64, f64)> = pairs
        .iter()
        .filter(|(b, n)| b.accepted && n.accepted)
        .filter_map(|(b, n)| b.final_delta_px.zip(n.final_delta_px))
        .collect();
    let both_accepted_mean_px = mean(&both.iter().map(|p| p.0).collect::<Vec<_>>())
        .zip(mean(&both.iter().map(|p| p.1).collect::<Vec<_>>()));
    let changed = pairs
        .iter()
        .filter(|(b, n)| {
            b.accepted != n.accepted
                || match (b.final_delta_px, n.final_delta_px) {
                    (Some(x), Some(y)) => (x - y).abs() > changed_px,
                    (x, y) => x.is_some() != y.is_some(),
                }
        })
        .map(|(b, n)| FrameChange {
            name: b.name.clone(),
            base: (b.accepted, b.final_delta_px),
            new: (n.accepted, n.final_delta_px),
            new_reason: n.reason.clone(),
        })
        .collect();
    Comparison {
        frames: pairs.len(),
        base: compared_side(pairs.iter().map(|p| p.0), false_accept_px),
        new: compared_side(pairs.iter().map(|p| p.1), false_accept_px),
        both_accepted: both.len(),
        both_accepted_mean_px,
        changed,
    }
}

/// One side of a comparison over its `frames`.
fn compared_side<'a>(
    frames: impl Iterator<Item = &'a EvalFrame>,
    false_accept_px: f64,
) -> ComparedSide {
    let accepted: Vec<&EvalFrame> = frames.filter(|f| f.accepted).collect();
    let deltas_px: Vec<f64> = accepted.iter().filter_map(|f| f.final_delta_px).collect();
    let correct: Vec<f64> = deltas_px
        .iter()
        .copied()
        .filter(|d| *d <= false_accept_px)
        .collect();
    ComparedSide {
        accepted: accepted.len(),
        correct_mean_px: mean(&correct),
        false_accepts_px: deltas_px
            .into_iter()
            .filter(|d| *d > false_accept_px)
            .collect(),
    }
}

/// The mean of `values`; `None` when empty.
fn mean(values: &[f64]) -> Option<f64> {
    (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
}

/// `mean ± std (min–max)` or `–` when nothing was accepted.
pub fn format_accuracy(stats: &CellStats) -> String {
    match (stats.mean_px, stats.std_px, stats.min_px, stats.max_px) {
        (Some(mean), Some(std), Some(min), Some(max)) => {
            format!("{mean:.2} ± {std:.2} ({min:.2}–{max:.2})")
        }
        _ => "–".to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(accepted: bool, final_delta_px: Option<f64>) -> EvalFrame {
        EvalFrame {
            name: "f".into(),
            initial_delta_px: 30.0,
            accepted,
            final_delta_px,
            confidence: 0.5,
            evidence: None,
            reason: None,
            total_ms: 100.0,
            heading_sweep: None,
            timings: None,
            neighbours: Vec::new(),
        }
    }

    #[test]
    fn calibration_bins_count_correct_poses_per_confidence() {
        let mut frames = vec![
            frame(true, Some(1.0)),
            frame(false, Some(40.0)),
            frame(true, Some(30.0)),
            frame(false, None),
        ];
        frames[0].confidence = 0.95;
        frames[1].confidence = 0.05;
        frames[2].confidence = 1.0;
        let table = calibration_bins(&frames, 25.25, 10);
        assert_eq!(table.len(), 10);
        assert_eq!(
            (table[0].frames, table[0].correct, table[0].accepted),
            (1, 0, 0)
        );
        assert_eq!(
            (table[9].frames, table[9].correct, table[9].accepted),
            (2, 1, 2)
        );
        assert_eq!(table.iter().map(|b| b.frames).sum::<usize>(), 3);
    }

    fn named(name: &str, accepted: bool, final_delta_px: Option<f64>) -> EvalFrame {
        EvalFrame {
            name: name.into(),
            ..frame(accepted, final_delta_px)
        }
    }

    #[test]
    fn a_comparison_pairs_frames_by_name_and_lists_what_changed() {
        let base = [
            named("a", true, Some(1.0)),
            named("b", true, Some(4.0)),
            named("c", false, Some(3.0)),
            named("d", true, Some(40.0)),
            named("only-in-base", true, Some(2.0)),
        ];
        let mut new = vec![
            named("d", true, Some(41.0)),
            named("c", true, Some(2.0)),
            named("b", true, Some(2.0)),
            named("a", true, Some(1.2)),
            named("only-in-new", false, None),
        ];
        new[0].reason = None;
        let comparison = compare_frames(&base, &new, 25.25, 0.5);
        assert_eq!(comparison.frames, 4);
        assert_eq!(comparison.base.accepted, 3);
        assert_eq!(comparison.new.accepted, 4);
        assert_eq!(comparison.base.correct_mean_px, Some(2.5));
        assert!((comparison.new.correct_mean_px.unwrap() - 5.2 / 3.0).abs() < 1e-12);
        assert_eq!(comparison.base.false_accepts_px, vec![40.0]);
        assert_eq!(comparison.new.false_accepts_px, vec![41.0]);
        // a, b and d were accepted by both.
        assert_eq!(comparison.both_accepted, 3);
        let (before, after) = comparison.both_accepted_mean_px.unwrap();
        assert!((before - 15.0).abs() < 1e-12 && (after - 44.2 / 3.0).abs() < 1e-12);
        // a moved 0.2 px (not a change); b 2 px; c flipped; d moved 1 px.
        let names: Vec<&str> = comparison.changed.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(names, ["b", "c", "d"]);
        assert_eq!(comparison.changed[1].base, (false, Some(3.0)));
        assert_eq!(comparison.changed[1].new, (true, Some(2.0)));
    }

    #[test]
    fn statistics_cover_accepted_frames_only_and_count_false_accepts() {
        let frames = [
            frame(true, Some(1.0)),
            frame(true, Some(3.0)),
            frame(true, Some(40.0)),
            frame(false, Some(2.0)),
            frame(false, None),
        ];
        let stats = cell_stats(&frames, 25.25);
        assert_eq!(stats.frames, 5);
        assert_eq!(stats.accepted, 3);
        assert!((stats.accepted_percent - 60.0).abs() < 1e-12);
        let mean = 44.0 / 3.0;
        assert!((stats.mean_px.unwrap() - mean).abs() < 1e-12);
        let variance = ((1.0 - mean).powi(2) + (3.0 - mean).powi(2) + (40.0 - mean).powi(2)) / 3.0;
        assert!((stats.std_px.unwrap() - variance.sqrt()).abs() < 1e-12);
        assert_eq!((stats.min_px, stats.max_px), (Some(1.0), Some(40.0)));
        assert_eq!(stats.false_accepts, 1);
        assert_eq!(format_accuracy(&cell_stats(&frames[3..], 25.0)), "–");
    }
}
