//! A pipeline's results checked against the one-process registration of the same frames
//! (`register`, [`crate::batch::register_batch_frame`]): kills, restarts, re-sends and the work
//! split must not change what a frame's result says. The soak (`asgreg soak`) and the pipeline
//! tests use it, so both hold a pipeline to the same standard.

use crate::batch::{neighbour_pass, register_batch_frame, FrameReport};
use crate::core::mesh::Mesh;
use crate::frame_files::FrameLoader;
use crate::msg::{PoseNumbers, PoseResult};
use crate::stage::ingest::{FolderSource, SourceError};

use super::config::PipelineConfig;

/// A frame whose pipeline result differs from `register`'s, or that has none.
#[derive(Clone, Debug, PartialEq)]
pub struct Mismatch {
    pub frame_id: u64,
    pub name: String,
    /// What differs, both values named.
    pub what: String,
}

impl std::fmt::Display for Mismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "frame {} ({}): {}", self.frame_id, self.name, self.what)
    }
}

/// Registers every frame of `config.source` in this process as `register` does and compares
/// each with the pipeline's result of that frame (`results`, any order; [`differences`]).
/// Costs one registration per frame.
pub fn differences_from_register(
    config: &PipelineConfig,
    mesh: &Mesh,
    results: &[PoseResult],
) -> Result<Vec<Mismatch>, SourceError> {
    Ok(differences(&register_reference(config, mesh)?, results))
}

/// Every frame of `config.source` registered in this process as `register` does (with step
/// "neighbour" when on: [`neighbour_pass`], the feed's rule the pipeline's verify follows), by
/// frame id.
pub fn register_reference(
    config: &PipelineConfig,
    mesh: &Mesh,
) -> Result<Vec<(u64, FrameReport)>, SourceError> {
    let source = FolderSource::open(&config.source)?;
    let (frame_ids, frames): (Vec<u64>, Vec<_>) = source.batch_frames().into_iter().unzip();
    let mut references: Vec<_> = frames
        .iter()
        .map(|frame| register_batch_frame(mesh, frame, &config.registration, config.source.seed))
        .collect();
    if config.registration.neighbour_pose.enabled {
        neighbour_pass(
            mesh,
            &frames,
            &mut references,
            &FrameLoader::default(),
            &config.registration,
            config.source.seed,
        );
    }
    Ok(frame_ids.into_iter().zip(references).collect())
}

/// Each frame's pipeline result against its reference ([`register_reference`]): accepted or
/// not, the confidence, the number of refined poses and the output pose must be equal (bit for
/// bit: the same steps on the same inputs). Frames without a result are mismatches too.
pub fn differences(references: &[(u64, FrameReport)], results: &[PoseResult]) -> Vec<Mismatch> {
    let mut mismatches = Vec::new();
    for (frame_id, reference) in references {
        let frame_id = *frame_id;
        let mismatch = |what: String| Mismatch {
            frame_id,
            name: reference.name.clone(),
            what,
        };
        let Some(result) = results.iter().find(|r| r.frame_id == frame_id) else {
            mismatches.push(mismatch("no pipeline result".to_string()));
            continue;
        };
        let pose = reference.cam_from_world.as_ref().map(PoseNumbers::from);
        let differences = [
            (result.name != reference.name)
                .then(|| format!("name {} against {}", result.name, reference.name)),
            (result.accepted != reference.accepted).then(|| {
                format!(
                    "accepted {} against register's {}",
                    result.accepted, reference.accepted
                )
            }),
            (result.confidence.to_bits() != reference.confidence.to_bits()).then(|| {
                format!(
                    "confidence {} against register's {}",
                    result.confidence, reference.confidence
                )
            }),
            (result.evidence.hypotheses as usize != reference.hypotheses).then(|| {
                format!(
                    "{} refined poses against register's {}",
                    result.evidence.hypotheses, reference.hypotheses
                )
            }),
            (result.cam_from_world != pose).then(|| {
                format!(
                    "pose {:?} against register's {:?} ({})",
                    result.cam_from_world,
                    pose,
                    how_each_decided(reference, result)
                )
            }),
        ];
        let what: Vec<String> = differences.into_iter().flatten().collect();
        if !what.is_empty() {
            mismatches.push(mismatch(what.join("; ")));
        }
    }
    mismatches
}

/// What a frame's two decisions rested on, for a pose that differs: register's tries of step
/// "neighbour" (lender, view, decision, whether the photo confirmed it) and both sides' own
/// evidence, so that a soak's failure on a machine that is gone says which step differed.
fn how_each_decided(reference: &FrameReport, result: &PoseResult) -> String {
    let tries: Vec<String> = reference
        .neighbours
        .iter()
        .map(|tried| {
            format!(
                "{} {:?} {:?} ({})",
                tried.neighbour,
                tried.view,
                tried.decision,
                tried.outcome()
            )
        })
        .collect();
    let evidence = &result.evidence;
    format!(
        "register's own: component {}, refinement kept {:?}, rejected candidate {:?}; its step \"neighbour\" tried [{}]; the pipeline's own: component {}, refinement {:?}",
        reference.component_size,
        reference.refinement.as_ref().map(|r| r.kept).ok(),
        reference
            .rejected_candidate
            .as_ref()
            .map(|c| PoseNumbers::from(&c.cam_from_world)),
        tries.join("; "),
        evidence.component_size,
        evidence.refinement,
    )
}
