//! Fusion's sights made durable: what each frame with a change map saw (its change worker's
//! ChangeSight: the change result with the photo's and the model's depth), written to the state
//! folder when fusion takes the frame's first change result, before its journal line, so that a
//! restarted fusion tests the fused objects against the free space of the frames published
//! before the restart too (their change results come back from the change journal, which holds
//! only the published ChangeResult). Without it, a fusion restart would drop those frames' votes
//! and the change set could differ from the run without the restart.
//!
//! Each sight is the ChangeSight message in the one wire encoding, in
//! `<state_dir>/<pipeline>.sights/<frame id>.sight` (a `frame_folder`), kept until the run ends
//! (fusion tests every frame against every object); reset with the journals by `launch`.
//! Writing is best effort: a sight that cannot be written costs only that frame's vote after a
//! restart, so it is a warning, not a failed frame.

use std::collections::BTreeMap;
use std::path::PathBuf;

use crate::core::change::free_space::SeenFrame;
use crate::msg::{Body, ChangeSight};
use crate::stage::fusion::seen_frame;

use super::config::PipelineConfig;
use super::frame_folder::{self, FolderKind, FrameFolder};

const SIGHTS: FolderKind = FolderKind {
    stage: "fusion",
    name: "sights",
    extension: "sight",
    what: "sight",
    loss: "the frame's vote in the free-space test",
};

/// The folder of a configuration's sights.
pub fn dir(config: &PipelineConfig) -> PathBuf {
    frame_folder::dir_of(config, SIGHTS.name)
}

/// Starts a run over: removes the sights folder (none is fine).
pub fn reset(config: &PipelineConfig) -> std::io::Result<()> {
    frame_folder::reset(config, &SIGHTS)
}

/// Fusion's durable sights.
pub struct SightStore {
    folder: FrameFolder,
}

impl SightStore {
    /// Opens the configuration's sights folder and reads back this run's sights (a file that
    /// cannot be read is removed with a warning: that frame does not vote after this restart).
    /// Another run's sights are removed.
    pub fn open_and_restore(config: &PipelineConfig) -> (Self, BTreeMap<u64, SeenFrame>) {
        let mut restored = BTreeMap::new();
        let folder =
            FrameFolder::open_and_restore(config, SIGHTS, &mut |frame_id, body| match body {
                Body::ChangeSight(sight) => {
                    if let Some(seen) = seen_frame(sight)? {
                        restored.insert(frame_id, seen);
                    }
                    Ok(())
                }
                other => Err(format!("it holds a {:?} message", other.kind())),
            });
        (Self { folder }, restored)
    }

    /// Keeps `sight` (a frame's first change result with a change map) on disk; best effort.
    pub fn write(&mut self, frame_id: u64, sight: ChangeSight<'_>) {
        self.folder.write(frame_id, Body::ChangeSight(sight));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::change::fusion::FusionConfig;
    use crate::stage::fusion::tests::floating_roof_sights;
    use crate::stage::fusion::FusionStage;

    /// A restarted fusion gets back what the frames published before the restart saw: the
    /// change set made from the journaled results and the restored sights is the one made
    /// without the restart (the object three frames see through stays unconfirmed). Another
    /// run's sights are removed, not restored.
    #[test]
    fn a_restarted_fusion_tests_the_change_set_against_the_sights_from_before_it() {
        let state = tempfile::tempdir().unwrap();
        let mut config = PipelineConfig {
            state_dir: Some(state.path().to_path_buf()),
            ..PipelineConfig::default()
        };
        config.transport.pipeline = "sights-test".to_string();
        let sights = floating_roof_sights();
        let (mut store, restored) = SightStore::open_and_restore(&config);
        assert!(restored.is_empty());
        let mut before = FusionStage::new(FusionConfig::default());
        for (frame_id, sight) in sights.iter().enumerate() {
            let seen = seen_frame(sight).unwrap();
            before.on_result(sight.meta.result.clone(), seen);
            store.write(frame_id as u64, sight.clone());
        }
        before.on_stream_end(sights.len() as u64);

        let (_, mut restored) = SightStore::open_and_restore(&config);
        assert_eq!(restored.len(), sights.len());
        let mut after = FusionStage::new(FusionConfig::default());
        for (frame_id, sight) in sights.iter().enumerate() {
            after.restore(
                sight.meta.result.clone(),
                restored.remove(&(frame_id as u64)),
            );
        }
        after.on_stream_end(sights.len() as u64);
        let set = after.change_set();
        assert_eq!(set, before.change_set());
        assert_eq!(set.free_space.len(), 1);
        assert!(set.free_space[0].refuted, "{:?}", set.free_space);

        config.source.max_frames = 3;
        let (_, restored) = SightStore::open_and_restore(&config);
        assert!(restored.is_empty(), "another run's sights");
        let left = std::fs::read_dir(dir(&config))
            .unwrap()
            .filter(|entry| {
                entry
                    .as_ref()
                    .is_ok_and(|e| e.path().extension().is_some_and(|x| x == "sight"))
            })
            .count();
        assert_eq!(left, 0);
    }
}
