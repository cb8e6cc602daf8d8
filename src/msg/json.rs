//! PoseResults, ChangeResults and ChangeSets as JSON for subscribers that do not speak bincode
//! (Python, C, a web page); the shapes are `schemas/v9/pose_result.schema.json`,
//! `change_result.schema.json` and `change_set.schema.json`.

use serde::Serialize;

use super::types::{ChangeResult, ChangeSet, Header, PoseResult};
use super::SCHEMA_VERSION;

#[derive(Serialize)]
struct WithHeader<'a, T: Serialize> {
    schema_version: u16,
    sequence: u64,
    capture_time_ns: u64,
    sent_time_ns: u64,
    #[serde(flatten)]
    body: &'a T,
}

fn json_with_header<T: Serialize>(header: &Header, body: &T) -> String {
    let value = WithHeader {
        schema_version: SCHEMA_VERSION,
        sequence: header.sequence,
        capture_time_ns: header.capture_time_ns,
        sent_time_ns: header.sent_time_ns,
        body,
    };
    // Serialising plain numbers, strings and options cannot fail; NaN becomes null.
    serde_json::to_string(&value).unwrap_or_else(|error| format!("{{\"error\":\"{error}\"}}"))
}

/// The JSON text of a PoseResult and its header.
pub fn pose_result_json(header: &Header, result: &PoseResult) -> String {
    json_with_header(header, result)
}

/// The JSON text of a ChangeResult and its header.
pub fn change_result_json(header: &Header, result: &ChangeResult) -> String {
    json_with_header(header, result)
}

/// The JSON text of a ChangeSet and its header.
pub fn change_set_json(header: &Header, set: &ChangeSet) -> String {
    json_with_header(header, set)
}
