//! Every topic name and every zenoh key expression of the bus, in one place and versioned
//! (`asgreg/v9/...`): a subscriber in any language builds its keys from this file's rules.
//!
//! A topic is a `/`-separated name relative to a pipeline (`results`, `flow/jobs/3`); its key is
//! `asgreg/v9/<pipeline>/<topic>`. iceoryx2 service names are the same string.

/// The version segment of every key; it changes with `msg::SCHEMA_VERSION`.
pub const KEY_VERSION: &str = "v9";
/// The first segment of every key.
pub const KEY_ROOT: &str = "asgreg";

/// Final results, one `PoseResult` per frame (bincode).
pub const RESULTS: &str = "results";
/// The same results as JSON (`schemas/v9/pose_result.schema.json`) for non-Rust subscribers.
pub const RESULTS_JSON: &str = "results/json";
/// Acknowledgements of the results by the station's collector (a `Credit` message whose
/// `completed` lists the frames it holds): verify sends each PoseResult again, with backoff,
/// until it is acknowledged here (a result lost in flight, e.g. while the zenoh router restarts).
pub const RESULTS_ACK: &str = "results/ack";
/// The prefix of the pose workers' topics ([`pose_in`]).
pub const POSE_IN: &str = "pose/in";
/// Correspondences from flow workers to pose worker `pose_worker` (`pose/in/<worker>`): each
/// pose worker has its own topic and receives only the coarse poses it solves
/// (`runtime::nodes::pose_worker_of`), so that a busy pose worker's queue never holds up a flow
/// worker whose correspondences go to another.
pub fn pose_in(pose_worker: u32) -> String {
    format!("{POSE_IN}/{pose_worker}")
}
/// Pose hypotheses and whole-frame failures to the verify stage.
pub const VERIFY_IN: &str = "verify/in";
/// Change results from the change workers (and verify, for frames without a pose) and the
/// end of the stream (from verify) to the fusion stage.
pub const FUSION_IN: &str = "fusion/in";
/// Change results (one per frame), fused change sets and the end of the change stream (bincode).
pub const CHANGES: &str = "changes";
/// The change results as JSON (`schemas/v9/change_result.schema.json`).
pub const CHANGES_JSON: &str = "changes/json";
/// The fused change sets as JSON (`schemas/v9/change_set.schema.json`).
pub const CHANGE_SET_JSON: &str = "changeset/json";
/// Acknowledgements of the change results by the station's collector (as [`RESULTS_ACK`]):
/// fusion sends each ChangeResult again until it is acknowledged here.
pub const CHANGES_ACK: &str = "changes/ack";
/// Per-stage metrics snapshots.
pub const METRICS: &str = "metrics";

/// The dispatched link ingest → render (frames).
pub const FRAMES_LINK: &str = "frames";
/// The dispatched link render → flow workers ((frame, coarse pose) jobs).
pub const FLOW_LINK: &str = "flow";

/// The dispatched link of render worker `render_index` to its flow workers: with several render
/// workers each has its own link (`flow`, `flow/r1`, `flow/r2`, ...), and flow worker `w` serves
/// render worker `w % render_workers` ([`flow_link_of_worker`]).
pub fn flow_link(render_index: u32) -> String {
    if render_index == 0 {
        FLOW_LINK.to_string()
    } else {
        format!("{FLOW_LINK}/r{render_index}")
    }
}
/// The flow link flow worker `flow_worker` serves when there are `render_workers` render workers.
pub fn flow_link_of_worker(flow_worker: u32, render_workers: u32) -> String {
    flow_link(flow_worker % render_workers.max(1))
}
/// The dispatched link verify → change workers (one job per accepted frame).
pub const CHANGE_LINK: &str = "change";

/// Jobs of a dispatched link for one worker (`<link>/jobs/<worker>`).
pub fn jobs(link: &str, worker_index: u32) -> String {
    format!("{link}/jobs/{worker_index}")
}

/// Credits (ready / done notes) of a dispatched link's workers (`<link>/credits`).
pub fn credits(link: &str) -> String {
    format!("{link}/credits")
}

/// The full key of a topic in a pipeline: `asgreg/v9/<pipeline>/<topic>`.
pub fn key(pipeline: &str, topic: &str) -> String {
    format!("{KEY_ROOT}/{KEY_VERSION}/{pipeline}/{topic}")
}

/// Key expression matching every topic of a pipeline (for a router's access rules or a monitor).
pub fn pipeline_wildcard(pipeline: &str) -> String {
    format!("{KEY_ROOT}/{KEY_VERSION}/{pipeline}/**")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_versioned_and_scoped_by_pipeline() {
        assert_eq!(key("gs1", RESULTS), "asgreg/v9/gs1/results");
        assert_eq!(key("gs1", &jobs("flow", 3)), "asgreg/v9/gs1/flow/jobs/3");
        assert_eq!(key("gs1", &credits("flow")), "asgreg/v9/gs1/flow/credits");
        assert_eq!(pipeline_wildcard("gs1"), "asgreg/v9/gs1/**");
        assert_eq!(key("gs1", RESULTS_ACK), "asgreg/v9/gs1/results/ack");
        assert_eq!(key("gs1", CHANGES_ACK), "asgreg/v9/gs1/changes/ack");
        assert_eq!(flow_link(0), FLOW_LINK);
        assert_eq!(
            key("gs1", &jobs(&flow_link(2), 5)),
            "asgreg/v9/gs1/flow/r2/jobs/5"
        );
        assert_eq!(flow_link_of_worker(5, 2), flow_link(1));
        assert_eq!(flow_link_of_worker(5, 1), FLOW_LINK);
        assert_eq!(key("gs1", &pose_in(3)), "asgreg/v9/gs1/pose/in/3");
    }
}
