//! Step "verify": the plausibility check over all of a frame's coarse outcomes (paper §3.4,
//! docs/design.md §2 step 7); the verdict carries the chosen pose itself.

use super::{CoarseOutcome, RegistrationConfig};
use crate::core::camera::Camera;
use crate::core::mesh::Mesh;
use crate::core::reprojection::ReprojectionWorkspace;
use crate::core::verify::{verify_hypotheses, PoseHypothesis, Verdict};

/// The verdict over a frame's coarse outcomes (in coarse order); `camera` is the one the coarse
/// poses were rendered with.
pub fn decide_frame(
    mesh: &Mesh,
    camera: &Camera,
    outcomes: &[CoarseOutcome],
    config: &RegistrationConfig,
) -> Verdict {
    let hypotheses: Vec<PoseHypothesis> = outcomes
        .iter()
        .filter_map(|o| o.hypothesis.as_ref().ok().copied())
        .collect();
    verify_hypotheses(
        mesh,
        &hypotheses,
        Some(camera),
        &config.verify,
        &mut ReprojectionWorkspace::new(),
    )
}
