//! The full-circle heading fallback's outcome beside the first pass's (issue #12 item 1). When
//! a frame's search region gave no accepted pose, [`super::register_query`] registers it once
//! more with headings swept over the whole circle
//! ([`crate::core::pose_search::PoseSearchConfig::heading_sweep`]). Both registrations' verdicts
//! are kept (so that a report can tell whether the sweep found the right heading even when it was
//! not accepted), and which of the two the frame's result carries is decided here, once, for
//! registration and the diagnosis alike ([`carried_pass`]).

use serde::{Deserialize, Serialize};

use crate::core::confidence::FrameEvidence;
use crate::core::verify::Verdict;

/// One of a frame's registrations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Pass {
    /// Within the pose search's region around the prior.
    First,
    /// The full-circle heading fallback's retry.
    HeadingSweep,
}

impl std::fmt::Display for Pass {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Pass::First => "first pass",
            Pass::HeadingSweep => "heading sweep",
        })
    }
}

/// One registration's verdict (its output or would-be output pose, its calibrated confidence and
/// reason) and the evidence it rests on.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PassOutcome {
    pub verdict: Verdict,
    pub evidence: FrameEvidence,
}

/// What the heading fallback did for a frame: both registrations, and which one the frame's
/// result carries.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct HeadingSweepOutcome {
    pub first: PassOutcome,
    /// The retry's outcome, or why it gave none (an error of the frame's steps).
    pub retry: Result<PassOutcome, String>,
    /// The registration whose verdict, coarse outcomes, refinement and evidence are the frame's.
    pub carried: Pass,
    /// The retry's wall time, ms.
    pub sweep_ms: f64,
}

impl HeadingSweepOutcome {
    /// The verdict of `pass` (`None` for a retry that failed).
    pub fn verdict(&self, pass: Pass) -> Option<&Verdict> {
        match pass {
            Pass::First => Some(&self.first.verdict),
            Pass::HeadingSweep => self.retry.as_ref().ok().map(|r| &r.verdict),
        }
    }
}

/// Which registration a frame's result carries, given the first pass's verdict and the retry's
/// (`None`: the retry did not run or failed):
/// - an accepted first pass stands (the fallback runs only after a rejection);
/// - an accepted retry wins over the rejected first pass: verification accepted it on its own
///   terms, over a region that contains the first pass's;
/// - when neither is accepted the frame stays rejected, and its would-be output is the one with
///   the higher calibrated confidence (the probability that the pose is correct; the first pass
///   on a tie), so that the report shows the more plausible of the two candidates. A rejected
///   retry never turns a rejection into an accept: the carried verdict is a rejection whichever
///   it is.
pub fn carried_pass(first: &Verdict, retry: Option<&Verdict>) -> Pass {
    let Some(retry) = retry else {
        return Pass::First;
    };
    if first.accepted() {
        return Pass::First;
    }
    if retry.accepted() {
        return Pass::HeadingSweep;
    }
    let retry_more_likely = retry.chosen().is_some()
        && (first.chosen().is_none() || retry.confidence > first.confidence);
    if retry_more_likely {
        Pass::HeadingSweep
    } else {
        Pass::First
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::camera::{Camera, PinholeIntrinsics};
    use crate::core::rigid::Rigid3;
    use crate::core::verify::{PoseHypothesis, Rejection, RejectionReason};

    fn hypothesis() -> PoseHypothesis {
        PoseHypothesis {
            camera: Camera::pinhole(100, 80, PinholeIntrinsics::centered(90.0, 100, 80)),
            cam_from_world: Rigid3::identity(),
            consensus: 40,
            inlier_rms_px: 1.0,
            correspondence_count: 100,
            coarse_cam_from_world: Rigid3::identity(),
        }
    }

    fn verdict(accepted: bool, confidence: f64, candidate: bool) -> Verdict {
        Verdict {
            decision: if accepted {
                Ok(hypothesis())
            } else {
                Err(Rejection {
                    reason: RejectionReason::NotConfirmed {
                        confidence,
                        threshold: 0.9,
                        edge_support: 0.2,
                        edge_support_chance: 0.2,
                    },
                    candidate: candidate.then(hypothesis),
                })
            },
            component: Vec::new(),
            direct_support: 0,
            convergence_ratio: None,
            hypothesis_count: 15,
            threshold_px: 25.0,
            mean_delta_to_chosen_px: 0.0,
            confidence,
        }
    }

    /// The rule's cases, each of which a wrong rule fails: an accepted pass wins, an unaccepted
    /// retry never makes an accept, and between two rejections the more confident candidate is
    /// the frame's.
    #[test]
    fn the_carried_pass_is_the_accepted_one_else_the_more_confident_rejection() {
        let rejected = |confidence| verdict(false, confidence, true);
        // No retry, or an accepted first pass: the first pass.
        assert_eq!(carried_pass(&rejected(0.5), None), Pass::First);
        assert_eq!(
            carried_pass(&verdict(true, 0.95, true), Some(&verdict(true, 0.99, true))),
            Pass::First
        );
        // An accepted retry after a rejection, even a less confident one.
        assert_eq!(
            carried_pass(&rejected(0.95), Some(&verdict(true, 0.91, true))),
            Pass::HeadingSweep
        );
        // Two rejections: the more confident candidate, the first on a tie; never an accept.
        let first = rejected(0.3);
        let retry = rejected(0.8);
        assert_eq!(carried_pass(&first, Some(&retry)), Pass::HeadingSweep);
        assert!(!retry.accepted());
        assert_eq!(carried_pass(&retry, Some(&first)), Pass::First);
        assert_eq!(carried_pass(&first, Some(&rejected(0.3))), Pass::First);
        // A retry without a candidate never replaces one; a candidate replaces none.
        assert_eq!(
            carried_pass(&first, Some(&verdict(false, 0.9, false))),
            Pass::First
        );
        assert_eq!(
            carried_pass(&verdict(false, 0.0, false), Some(&rejected(0.1))),
            Pass::HeadingSweep
        );
    }
}
