//! PoseResults as JSON for subscribers that do not speak bincode (Python, C, a web page); the
//! shape is `schemas/v3/pose_result.schema.json`.

use serde::Serialize;

use super::types::{Header, PoseResult};
use super::SCHEMA_VERSION;

#[derive(Serialize)]
struct PoseResultJson<'a> {
    schema_version: u16,
    sequence: u64,
    capture_time_ns: u64,
    sent_time_ns: u64,
    #[serde(flatten)]
    result: &'a PoseResult,
}

/// The JSON text of a PoseResult and its header.
pub fn pose_result_json(header: &Header, result: &PoseResult) -> String {
    let value = PoseResultJson {
        schema_version: SCHEMA_VERSION,
        sequence: header.sequence,
        capture_time_ns: header.capture_time_ns,
        sent_time_ns: header.sent_time_ns,
        result,
    };
    // Serialising plain numbers, strings and options cannot fail; NaN becomes null.
    serde_json::to_string(&value).unwrap_or_else(|error| format!("{{\"error\":\"{error}\"}}"))
}
