//! The full-circle heading fallback's outcome beside the first pass's (issue #12 item 1). When
//! a frame's search region gave no accepted pose, or an accept that rests on the photo's edges
//! alone ([`sweep_needed`]), [`super::register_query`] registers it once more with headings
//! swept over the whole circle ([`crate::core::pose_search::PoseSearchConfig::heading_sweep`]).
//! Both registrations' verdicts are kept (so that a report can tell whether the sweep found the
//! right heading even when it was not accepted), and the decision across the two is made here,
//! once, for registration and the diagnosis alike ([`decide_passes`]).

use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::decide::{distinct_confirmed_rival, reject};
use super::RegistrationConfig;
use crate::core::confidence::FrameEvidence;
use crate::core::mesh::Mesh;
use crate::core::verify::{RejectionReason, Verdict};

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

/// A frame registered with the fallback: its first pass and, when the fallback ran, the retry and
/// the decision across the two.
pub struct WithFallback<T> {
    pub first: T,
    /// `None` when the fallback is off or was not needed ([`sweep_needed`]).
    pub fallback: Option<FallbackRun<T>>,
}

/// The fallback's retry and the decision across the passes.
pub struct FallbackRun<T> {
    /// The retry's registration, or why it gave none.
    pub retry: Result<T, String>,
    /// Both passes' outcomes, the carried pass and the retry's time.
    pub outcome: HeadingSweepOutcome,
    /// The rejection [`decide_passes`] gives the carried pass's verdict, if any
    /// ([`apply_passes_decision`]).
    pub rejection: Option<RejectionReason>,
}

/// The fallback's one sequence, for registration and its diagnosis alike: `register` within the
/// pose search's region of `config`; when the fallback is on and [`sweep_needed`], `register`
/// again with headings swept over the whole circle, and [`decide_passes`] across the two.
/// `outcome` reads a registration's verdict and evidence. An error of the first pass is the
/// frame's; an error of the retry is kept as its reason.
pub fn register_with_fallback<T, E: std::fmt::Display>(
    mesh: &Mesh,
    config: &RegistrationConfig,
    register: impl Fn(&RegistrationConfig) -> Result<T, E>,
    outcome: impl Fn(&T) -> PassOutcome,
) -> Result<WithFallback<T>, E> {
    let first = register(config)?;
    let first_outcome = outcome(&first);
    let Some(sweep) = config.pose_search.heading_sweep() else {
        return Ok(WithFallback {
            first,
            fallback: None,
        });
    };
    if !sweep_needed(&first_outcome.verdict, &first_outcome.evidence) {
        return Ok(WithFallback {
            first,
            fallback: None,
        });
    }
    let sweep_started = Instant::now();
    let retry = register(&RegistrationConfig {
        pose_search: sweep,
        ..config.clone()
    })
    .map_err(|error| error.to_string());
    let sweep_ms = sweep_started.elapsed().as_secs_f64() * 1e3;
    let retry_outcome = retry.as_ref().map(&outcome).map_err(Clone::clone);
    let (carried, rejection) = decide_passes(
        mesh,
        &first_outcome,
        retry_outcome.as_ref().ok(),
        config.pose_search.centre_agreement_share,
    );
    Ok(WithFallback {
        first,
        fallback: Some(FallbackRun {
            retry,
            outcome: HeadingSweepOutcome {
                first: first_outcome,
                retry: retry_outcome,
                carried,
                sweep_ms,
            },
            rejection,
        }),
    })
}

/// Whether the fallback's retry runs after the first pass: when the first pass accepted nothing,
/// and when its accept rests on the photo's edges alone (the paper's plausibility check failed,
/// [`FrameEvidence::check_passed`]). The edge support is what the search maximised over its
/// region around the prior; when the fallback is on, the prior's heading is not trusted, so such
/// a pose is final only if no other heading of the circle is confirmed too
/// ([`decide_passes`]). A pose the flow's agreement also confirms needs no retry.
pub fn sweep_needed(first: &Verdict, evidence: &FrameEvidence) -> bool {
    !first.accepted() || !evidence.check_passed
}

/// The decision across a frame's two registrations: which one the result carries, and the
/// rejection that replaces its decision, if any. With `retry` `None` (it did not run or failed)
/// the first pass stands. The retry's own accept counts only when its plausibility check passed
/// too: over the whole circle the search picks the pose whose edges fit best among many more
/// look-alikes than in the region the confidence was calibrated on, so edge support alone no
/// longer confirms a pose there ([`RejectionReason::SweepUnchecked`]). Then:
/// - First pass accepted (only on its edges, or the retry would not run): it stands unless the
///   retry confirms a pose at least `agreement_share` of the compatibility threshold away, in
///   which case the photo confirms two distinct poses and the frame is rejected as ambiguous
///   (the rule across the search's centres, `decide::distinct_confirmed_rival`).
/// - First pass rejected, retry accepted: the retry.
/// - Otherwise the frame stays rejected and carries the more confident of the two (the first on
///   a tie): an unaccepted or unchecked retry never makes an accept.
pub fn decide_passes(
    mesh: &Mesh,
    first: &PassOutcome,
    retry: Option<&PassOutcome>,
    agreement_share: f64,
) -> (Pass, Option<RejectionReason>) {
    let Some(retry) = retry else {
        return (Pass::First, None);
    };
    let unchecked = (retry.verdict.accepted() && !retry.evidence.check_passed).then_some(
        RejectionReason::SweepUnchecked {
            confidence: retry.verdict.confidence,
        },
    );
    let mut admitted = retry.verdict.clone();
    if let Some(reason) = unchecked.clone() {
        reject(&mut admitted, reason);
    }
    if first.verdict.accepted() {
        let rival = distinct_confirmed_rival(
            mesh,
            &first.verdict,
            std::slice::from_ref(&admitted),
            agreement_share,
        );
        return (Pass::First, rival);
    }
    if admitted.accepted() {
        return (Pass::HeadingSweep, None);
    }
    let retry_more_likely = retry.verdict.chosen().is_some()
        && (first.verdict.chosen().is_none()
            || retry.verdict.confidence > first.verdict.confidence);
    if retry_more_likely {
        (Pass::HeadingSweep, unchecked)
    } else {
        (Pass::First, None)
    }
}

/// The verdict a frame carries after [`decide_passes`]: `verdict` with its decision replaced by
/// `rejection` when there is one.
pub fn apply_passes_decision(verdict: &mut Verdict, rejection: Option<RejectionReason>) {
    if let Some(reason) = rejection {
        reject(verdict, reason);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::frame::tests::house_and_poses;
    use crate::core::pose_search::turned_pose;
    use crate::core::rigid::Rigid3;
    use crate::core::verify::{PoseHypothesis, Rejection};

    /// A pass whose pose is `pose` (a rejection's candidate when not `accepted`; no pose at all
    /// when `pose` is `None`), with the plausibility check passed or not.
    fn pass(
        camera: &crate::core::camera::Camera,
        pose: Option<Rigid3>,
        accepted: bool,
        confidence: f64,
        check_passed: bool,
    ) -> PassOutcome {
        let hypothesis = pose.map(|cam_from_world| PoseHypothesis {
            camera: *camera,
            cam_from_world,
            consensus: 40,
            inlier_rms_px: 1.0,
            correspondence_count: 100,
            coarse_cam_from_world: cam_from_world,
        });
        let decision = match (accepted, hypothesis) {
            (true, Some(h)) => Ok(h),
            (_, candidate) => Err(Rejection {
                reason: RejectionReason::NotConfirmed {
                    confidence,
                    threshold: 0.9,
                    edge_support: 0.2,
                    edge_support_chance: 0.2,
                    min_above_chance: 0.0,
                },
                candidate,
            }),
        };
        PassOutcome {
            verdict: Verdict {
                decision,
                component: Vec::new(),
                direct_support: 0,
                convergence_ratio: None,
                hypothesis_count: 15,
                threshold_px: 25.25,
                mean_delta_to_chosen_px: 0.0,
                confidence,
            },
            evidence: FrameEvidence {
                check_passed,
                ..FrameEvidence::default()
            },
        }
    }

    /// The decision across the two registrations, case by case; each assertion fails under a
    /// rule that lets a retry turn a rejection into an accept without the plausibility check,
    /// that keeps an edges-only accept when the whole circle confirms another pose, or that
    /// carries the less confident of two rejections.
    #[test]
    fn passes_are_decided_by_acceptance_the_check_and_distinct_confirmed_poses() {
        let (mesh, camera, truth, _) = house_and_poses();
        // The same pose seen 40° about the vertical: far more than 25 px apart.
        let other = turned_pose(&truth, 40.0, 0.0, 0.0);
        let nearby = turned_pose(&truth, 0.1, 0.0, 0.0);
        let decide = |first: &PassOutcome, retry: Option<&PassOutcome>| {
            let (carried, rejection) = decide_passes(&mesh, first, retry, 0.5);
            let mut verdict = match carried {
                Pass::First => first.verdict.clone(),
                Pass::HeadingSweep => retry.unwrap().verdict.clone(),
            };
            apply_passes_decision(&mut verdict, rejection);
            (carried, verdict)
        };
        let p = |pose: Rigid3, accepted, confidence, check| {
            pass(&camera, Some(pose), accepted, confidence, check)
        };

        // When the retry runs at all.
        assert!(sweep_needed(
            &p(truth, false, 0.5, true).verdict,
            &FrameEvidence::default()
        ));
        let edges_only = p(truth, true, 0.95, false);
        assert!(sweep_needed(&edges_only.verdict, &edges_only.evidence));
        let checked = p(truth, true, 0.95, true);
        assert!(!sweep_needed(&checked.verdict, &checked.evidence));

        // No retry: the first pass stands.
        let (carried, verdict) = decide(&edges_only, None);
        assert_eq!(carried, Pass::First);
        assert!(verdict.accepted());

        // An edges-only accept against a retry confirming a distinct pose: ambiguous.
        let (carried, verdict) = decide(&edges_only, Some(&p(other, true, 0.99, true)));
        assert_eq!(carried, Pass::First);
        assert!(
            matches!(verdict.rejection(), Some(RejectionReason::Ambiguous { .. })),
            "{verdict:?}"
        );
        // ... a distinct pose the retry confirms on its edges alone is no rival.
        let (_, verdict) = decide(&edges_only, Some(&p(other, true, 0.99, false)));
        assert!(verdict.accepted(), "{verdict:?}");
        // ... confirming the same pose, or nothing: the first pass's accept stands.
        let (_, verdict) = decide(&edges_only, Some(&p(nearby, true, 0.99, true)));
        assert!(verdict.accepted());
        let (_, verdict) = decide(&edges_only, Some(&p(other, false, 0.6, false)));
        assert!(verdict.accepted());

        // A rejection, then a checked accept of the retry: the retry.
        let rejected = p(other, false, 0.86, false);
        let (carried, verdict) = decide(&rejected, Some(&p(truth, true, 0.95, true)));
        assert_eq!(carried, Pass::HeadingSweep);
        assert!(verdict.accepted());
        // ... an accept of the retry on its edges alone: carried, but rejected.
        let (carried, verdict) = decide(&rejected, Some(&p(truth, true, 0.99, false)));
        assert_eq!(carried, Pass::HeadingSweep);
        assert!(
            matches!(
                verdict.rejection(),
                Some(RejectionReason::SweepUnchecked { .. })
            ),
            "{verdict:?}"
        );

        // Two rejections: the more confident candidate, the first on a tie; never an accept.
        let (carried, verdict) = decide(&rejected, Some(&p(truth, false, 0.9, true)));
        assert_eq!((carried, verdict.accepted()), (Pass::HeadingSweep, false));
        let (carried, _) = decide(&rejected, Some(&p(truth, false, 0.5, true)));
        assert_eq!(carried, Pass::First);
        let (carried, _) = decide(&rejected, Some(&p(truth, false, 0.86, true)));
        assert_eq!(carried, Pass::First);
        // A retry without a pose never replaces one; a pose replaces none.
        let nothing = pass(&camera, None, false, 0.0, false);
        let (carried, _) = decide(&rejected, Some(&nothing));
        assert_eq!(carried, Pass::First);
        let (carried, verdict) = decide(&nothing, Some(&p(truth, false, 0.1, false)));
        assert_eq!((carried, verdict.accepted()), (Pass::HeadingSweep, false));
    }
}
