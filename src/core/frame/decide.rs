//! Steps "verify" and "refine", once per frame after its views: the plausibility check over all of
//! a frame's coarse outcomes (paper §3.4, docs/design.md §2 step 7) and the final refinement of the
//! chosen pose against the query ([`super::refine`]); the verdict carries the chosen pose itself.

use super::refine::{refine_verdict, PoseRefinement, RefineWorkspace};
use super::{CoarseOutcome, IntrinsicsMode, RegistrationConfig};
use crate::core::camera::Camera;
use crate::core::image::ImageView;
use crate::core::mesh::Mesh;
use crate::core::reprojection::ReprojectionWorkspace;
use crate::core::verify::{verify_hypotheses, PoseHypothesis, Verdict};

/// A frame's decision: the verdict (with the refined pose when the refinement kept it) and what
/// the refinement did.
#[derive(Clone, Debug)]
pub struct Decision {
    pub verdict: Verdict,
    /// The final refinement, or why there was none.
    pub refinement: Result<PoseRefinement, String>,
}

/// The verdict over a frame's coarse outcomes (in coarse order), then the final refinement of its
/// chosen pose against `query` (the frame's query gradient image; `None` when it is not at hand,
/// e.g. lost in the pipeline: the verdict is then unrefined). `camera` is the one the coarse
/// poses were rendered with.
pub fn decide_frame(
    mesh: &Mesh,
    camera: &Camera,
    outcomes: &[CoarseOutcome],
    query: Option<ImageView<'_, f32>>,
    intrinsics: IntrinsicsMode,
    config: &RegistrationConfig,
    workspace: &mut RefineWorkspace,
) -> Decision {
    let hypotheses: Vec<PoseHypothesis> = outcomes
        .iter()
        .filter_map(|o| o.hypothesis.as_ref().ok().copied())
        .collect();
    let mut verdict = verify_hypotheses(
        mesh,
        &hypotheses,
        Some(camera),
        &config.verify,
        &mut ReprojectionWorkspace::new(),
    );
    let refinement = match query {
        Some(query) => refine_verdict(mesh, query, intrinsics, &mut verdict, config, workspace),
        None => Err("the frame's query is not at hand".to_string()),
    };
    Decision {
        verdict,
        refinement,
    }
}
