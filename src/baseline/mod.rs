//! Evaluation baselines, not part of registration: methods the paper compares against, run on the
//! same frames and initial poses so that `asgreg eval` can report them next to ours.

pub mod icp;
