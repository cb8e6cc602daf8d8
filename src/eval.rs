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
