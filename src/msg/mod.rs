//! The wire types of the bus and the one place that encodes and decodes them (docs/design.md §5).
//! `schemas/v9/` describes the same layout for subscribers in other languages.
//!
//! Layout of every message (all integers little-endian):
//! ```text
//! 0   magic "ASGR"            4 bytes
//! 4   schema_version          u16   (SCHEMA_VERSION; a receiver rejects any other)
//! 6   kind                    u16   (MessageKind)
//! 8   frame_id                u64
//! 16  sequence                u64   (per sender, for ordering and loss checks)
//! 24  capture_time_ns         u64   (Unix ns when the frame was captured or ingested)
//! 32  sent_time_ns            u64   (Unix ns when this message was sent)
//! 40  meta_len                u32   (bytes of the bincode-2 body that follows)
//! 44  array_count             u32
//! 48  meta                    bincode 2 (standard config) of the kind's body struct
//! ..  padding to 8
//! ..  array_count × u64        byte length of each array
//! ..  arrays, each starting on an 8-byte boundary (f32/u32/f64 little-endian)
//! ```
//! Bulk data (images, depth, correspondence arrays) sits in the aligned arrays, so a receiver
//! reads it in place: [`decode`] borrows it from the received bytes (the iceoryx2 sample) when
//! they are aligned and copies only when they are not.

mod json;
mod types;
mod wire;

#[cfg(test)]
mod tests;

pub use json::{change_result_json, change_set_json, pose_result_json};
pub use types::*;
pub use wire::{decode, encode, same_body, DecodeError, EncodeError, Encoded, HEADER_BYTES, MAGIC};

/// The schema version in every header; bump it (and add `schemas/v<N>/`) on any layout change.
/// v4: change detection (ChangeJob, ChangeResult, ChangeSet; FrameQuery carries the depth map).
/// v5: depth in the pipeline (FrameQuery carries the grey photo; ChangeJob the photo and its
/// stereo neighbours).
/// v6: a ChangeJob's meta ends with the registered pose's error (`pose_sigma_px`) for the change
/// threshold's pose term.
/// v7: a change worker sends fusion a ChangeSight (its ChangeResult with the photo's and the
/// model's depth, the camera, pose and change settings) for the free-space test; a ChangeSet
/// ends with `free_space`, that test of every confirmed `added` object.
/// v8: Correspondences and Hypothesis carry the coarse view's rendering sampled on δ's grid
/// (`GridArrays`: face index and depth, the stride in their meta), so that verify's convergence
/// test does not render the coarse poses again.
/// v9: a new kind, PoseLender (15): an accepted frame verify keeps for step "neighbour" (its
/// query image, registered camera and pose, steps), written to verify's state folder only.
pub const SCHEMA_VERSION: u16 = 9;
