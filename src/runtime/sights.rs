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
//! (fusion tests every frame that can see an object); reset with the journals by `launch`. The
//! folder is also what bounds fusion's memory: fusion holds at most
//! `fusion.max_sights_in_memory_mb` of maps and reads the others back from here
//! ([`kept`]) when the free-space test needs them; a sight that could not be
//! written stays in memory.
//! Writing is best effort: a sight that cannot be written costs only that frame's vote after a
//! restart, so it is a warning, not a failed frame.

use std::path::PathBuf;

use crate::core::change::free_space::SeenFrame;
use crate::msg::{Body, ChangeSight};
use crate::stage::fusion::{seen_frame, KeptSights, SightReader};

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

/// A sight file's message as the free-space test reads it (an error: not a sight, no change
/// map, or its maps are unusable).
fn seen_of(body: &Body<'_>) -> Result<SeenFrame, String> {
    match body {
        Body::ChangeSight(sight) => {
            seen_frame(sight)?.ok_or_else(|| "it holds no change map".to_string())
        }
        other => Err(format!("it holds a {:?} message", other.kind())),
    }
}

/// Fusion's durable sights.
pub struct SightStore {
    folder: FrameFolder,
}

impl SightStore {
    /// Opens the configuration's sights folder and hands this run's sights to `restore` (frame
    /// id and sight, one at a time; a file that cannot be read is removed with a warning: that
    /// frame does not vote after this restart). Another run's sights are removed.
    pub fn open_and_restore(
        config: &PipelineConfig,
        restore: &mut dyn FnMut(u64, SeenFrame),
    ) -> Self {
        let folder =
            FrameFolder::open_and_restore(config, SIGHTS, &mut |frame_id, body| match body {
                Body::ChangeSight(sight) => {
                    if let Some(seen) = seen_frame(sight)? {
                        restore(frame_id, seen);
                    }
                    Ok(())
                }
                other => Err(format!("it holds a {:?} message", other.kind())),
            });
        Self { folder }
    }

    /// Keeps `sight` (a frame's first change result with a change map) on disk; best effort:
    /// whether it was written (so fusion may read it back instead of holding it).
    pub fn write(&mut self, frame_id: u64, sight: ChangeSight<'_>) -> bool {
        self.folder.write(frame_id, Body::ChangeSight(sight))
    }
}

/// Fusion's sights as configured (`fusion.max_sights_in_memory_mb`): at most that many MB of
/// maps in memory, the others read back from the configuration's sights folder.
pub fn kept(config: &PipelineConfig) -> KeptSights {
    let max_bytes = config
        .fusion
        .max_sights_in_memory_mb
        .saturating_mul(1_000_000);
    KeptSights::bounded(
        usize::try_from(max_bytes).unwrap_or(usize::MAX),
        Box::new(SightFiles { dir: dir(config) }),
    )
}

/// Reads fusion's sights back from its folder.
struct SightFiles {
    dir: PathBuf,
}

impl SightReader for SightFiles {
    fn read(&mut self, frame_id: u64) -> Result<SeenFrame, String> {
        let path = frame_folder::path_in(&self.dir, &SIGHTS, frame_id);
        let mut seen = None;
        frame_folder::read_message(&path, frame_id, &mut |_, body| {
            seen = Some(seen_of(body)?);
            Ok(())
        })
        .and_then(|()| seen.ok_or_else(|| "nothing read".to_string()))
        .map_err(|why| format!("{}: {why}", path.display()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::change::fusion::FusionConfig;
    use crate::msg::ChangeSet;
    use crate::stage::fusion::tests::floating_roof_sights;
    use crate::stage::fusion::FusionStage;

    fn config_in(state: &std::path::Path, max_sights_in_memory_mb: u64) -> PipelineConfig {
        let mut config = PipelineConfig {
            state_dir: Some(state.to_path_buf()),
            ..PipelineConfig::default()
        };
        config.transport.pipeline = "sights-test".to_string();
        config.fusion.max_sights_in_memory_mb = max_sights_in_memory_mb;
        config
    }

    /// The fusion stage after the floating roof's frames, fed as the fusion node feeds them
    /// (each sight written, then marked on disk), with the configuration's bound.
    fn fed_through_the_folder(config: &PipelineConfig) -> FusionStage {
        let sights = floating_roof_sights();
        let mut store = SightStore::open_and_restore(config, &mut |_, _| {});
        let mut stage = FusionStage::with_sights(config.fusion.merge(), kept(config));
        for (frame_id, sight) in sights.iter().enumerate() {
            let frame_id = frame_id as u64;
            let seen = seen_frame(sight).unwrap();
            assert!(stage.on_result(sight.meta.result.clone(), seen).is_some());
            if store.write(frame_id, sight.clone()) {
                stage.sight_on_disk(frame_id);
            }
        }
        stage.on_stream_end(sights.len() as u64);
        stage
    }

    /// [`fed_through_the_folder`] and its change set.
    fn fused_through_the_folder(config: &PipelineConfig) -> (ChangeSet, FusionStage) {
        let mut stage = fed_through_the_folder(config);
        (stage.change_set(), stage)
    }

    /// A restarted fusion gets back what the frames published before the restart saw: the
    /// change set made from the journaled results and the restored sights is the one made
    /// without the restart (the object three frames see through stays unconfirmed), with every
    /// sight in memory and with none held beyond the test (read back from the folder). Another
    /// run's sights are removed, not restored.
    #[test]
    fn a_restarted_fusion_tests_the_change_set_against_the_sights_from_before_it() {
        let state = tempfile::tempdir().unwrap();
        let mut config = config_in(state.path(), 256);
        let sights = floating_roof_sights();
        let (before, _) = fused_through_the_folder(&config);
        assert_eq!(before.free_space.len(), 1);
        assert!(before.free_space[0].refuted, "{:?}", before.free_space);

        for max_mb in [256, 0] {
            config.fusion.max_sights_in_memory_mb = max_mb;
            let mut after = FusionStage::with_sights(config.fusion.merge(), kept(&config));
            for sight in &sights {
                after.restore(sight.meta.result.clone());
            }
            let mut restored = 0;
            SightStore::open_and_restore(&config, &mut |frame_id, seen| {
                restored += 1;
                after.restore_sight(frame_id, seen)
            });
            assert_eq!(restored, sights.len());
            after.on_stream_end(sights.len() as u64);
            assert_eq!(after.change_set(), before, "bound {max_mb} MB");
            let memory = after.sight_memory();
            assert_eq!(memory.frames, sights.len());
            if max_mb == 0 {
                assert_eq!((memory.held_bytes, memory.frames_held), (0, 0));
                assert_eq!(memory.loads, 5, "{memory:?}");
            } else {
                assert_eq!(memory.loads, 0, "{memory:?}");
            }
        }

        config.source.max_frames = 3;
        let mut restored = 0;
        SightStore::open_and_restore(&config, &mut |_, _| restored += 1);
        assert_eq!(restored, 0, "another run's sights");
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

    /// Bounded to 0–3 frames' maps, fusion reads the sights it needs back from the folder and
    /// gives the change set of the run with every map in memory, holding at most the bound (one
    /// frame more while it reads).
    #[test]
    fn fusion_bounded_to_a_few_sights_gives_the_change_set_of_every_sight_in_memory() {
        let state = tempfile::tempdir().unwrap();
        let sights = floating_roof_sights();
        let mut unbounded = FusionStage::new(FusionConfig::default());
        for sight in &sights {
            unbounded.on_result(sight.meta.result.clone(), seen_frame(sight).unwrap());
        }
        unbounded.on_stream_end(sights.len() as u64);
        let reference = unbounded.change_set();
        assert!(reference.free_space[0].refuted, "{reference:?}");
        let frame_bytes = unbounded.sight_memory().peak_bytes / sights.len();
        // 200 × 200 px: three f32 maps.
        assert_eq!(frame_bytes, 3 * 4 * 200 * 200);

        // The bound in MB: 0 (none held), 1 (two frames of 0.48 MB), 2 (four frames).
        for max_mb in [0u64, 1, 2] {
            let mut config = config_in(state.path(), max_mb);
            config.transport.pipeline = format!("bound-{max_mb}");
            let (set, mut stage) = fused_through_the_folder(&config);
            assert_eq!(set, reference, "bound {max_mb} MB");
            let memory = stage.sight_memory();
            let max_bytes = (max_mb * 1_000_000) as usize;
            assert!(memory.held_bytes <= max_bytes, "{memory:?}");
            assert!(memory.peak_bytes <= max_bytes + frame_bytes, "{memory:?}");
            let held = max_bytes / frame_bytes;
            assert_eq!(memory.frames_held, held, "{memory:?}");
            assert_eq!(memory.loads as usize, sights.len() - held, "{memory:?}");
            // Asked again, the same set (the held ones first, the others read again).
            assert_eq!(stage.change_set(), reference);
            assert!(stage.sight_memory().lost.is_empty());
        }
    }

    /// A sight file deleted or damaged after it was written, before the free-space test read
    /// it: the test goes on without that frame's vote, and says which frame and which file;
    /// every frame keeps its change result.
    #[test]
    fn a_missing_or_damaged_sight_file_costs_only_that_frames_vote() {
        let state = tempfile::tempdir().unwrap();
        let config = config_in(state.path(), 0);
        let mut stage = fed_through_the_folder(&config);
        let folder = dir(&config);
        std::fs::remove_file(folder.join("2.sight")).unwrap();
        std::fs::write(folder.join("3.sight"), b"not a message").unwrap();

        let set = stage.change_set();
        assert_eq!(stage.sight_memory().loads, 3, "frames 0, 1, 4");
        assert_eq!(set.frames_with_result, 5);
        assert!(set.complete);
        assert_eq!(set.free_space.len(), 1);
        assert_eq!(set.free_space[0].seen_through_by, vec![4]);
        assert_eq!(set.free_space[0].agreed_by, vec![0, 1]);
        assert!(!set.free_space[0].refuted, "two frames fewer: {set:?}");
        let lost = stage.sight_memory().lost;
        assert_eq!(lost.keys().copied().collect::<Vec<_>>(), vec![2, 3]);
        assert!(
            lost[&2].contains(&folder.join("2.sight").display().to_string()),
            "{lost:?}"
        );
        assert!(
            lost[&3].contains(&folder.join("3.sight").display().to_string()),
            "{lost:?}"
        );
        // Asked again: the lost frames are not read again (warned once), the set stays.
        assert_eq!(stage.change_set(), set);
        assert_eq!(stage.sight_memory().loads, 3);
    }

    /// The votes are kept by the objects' inner points: a second change set of the same objects
    /// reads nothing back; a new frame that adds no region is read alone (its vote is new); a
    /// frame whose region moves the object makes every frame that sees it vote again. Each set
    /// is the one of an unbounded fusion fed the same frames.
    #[test]
    fn kept_votes_spare_the_reads_of_objects_that_did_not_move() {
        let state = tempfile::tempdir().unwrap();
        let config = config_in(state.path(), 0);
        let sights = floating_roof_sights();
        let mut stage = fed_through_the_folder(&config);
        let mut unbounded = FusionStage::new(FusionConfig::default());
        for sight in &sights {
            unbounded.on_result(sight.meta.result.clone(), seen_frame(sight).unwrap());
        }
        let loads = |stage: &FusionStage| stage.sight_memory().loads;
        // The objects and their tests (the stage fed here has seen the end of the stream).
        let tested = |set: ChangeSet| (set.objects, set.free_space);
        assert_eq!(tested(stage.change_set()), tested(unbounded.change_set()));
        assert_eq!(loads(&stage), 5);
        assert_eq!(tested(stage.change_set()), tested(unbounded.change_set()));
        assert_eq!(loads(&stage), 5, "the same objects: no read");

        let mut store = SightStore::open_and_restore(&config, &mut |_, _| {});
        let mut feed = |stage: &mut FusionStage, unbounded: &mut FusionStage, from: usize, id| {
            let mut sight = sights[from].clone();
            sight.meta.result.frame_id = id;
            let seen = seen_frame(&sight).unwrap();
            unbounded.on_result(sight.meta.result.clone(), seen.clone());
            stage.on_result(sight.meta.result.clone(), seen);
            assert!(store.write(id, sight));
            stage.sight_on_disk(id);
        };
        // Bare ground, no region: the object does not move.
        feed(&mut stage, &mut unbounded, 2, 5);
        assert_eq!(tested(stage.change_set()), tested(unbounded.change_set()));
        assert_eq!(loads(&stage), 6, "only the new frame");
        // The floating roof again: its region moves the object's centroid.
        feed(&mut stage, &mut unbounded, 0, 6);
        let set = stage.change_set();
        assert_eq!(tested(set.clone()), tested(unbounded.change_set()));
        assert_eq!(
            loads(&stage),
            6 + 7,
            "every frame that sees the moved object"
        );
        assert_eq!(set.free_space[0].seen_through_by, vec![2, 3, 4, 5]);
        assert_eq!(set.free_space[0].agreed_by, vec![0, 1, 6]);
    }

    /// The cost of the bound on a longer stream (a measurement, run by hand with
    /// `-- --ignored --nocapture`): the floating roof's five frames repeated as 200 frames
    /// (0.48 MB of maps each), every one of which sees the object (the worst case: each change
    /// set reads back every frame not held), unbounded and bounded to 8 MB.
    #[test]
    #[ignore = "a measurement"]
    fn measure_fusion_memory_and_time_on_200_frames() {
        let state = tempfile::tempdir().unwrap();
        let sights = floating_roof_sights();
        let frames = 200u64;
        let mut sets = Vec::new();
        for max_mb in [None, Some(8u64)] {
            let mut config = config_in(state.path(), max_mb.unwrap_or(0));
            config.transport.pipeline = format!("measure-{max_mb:?}");
            let mut store = SightStore::open_and_restore(&config, &mut |_, _| {});
            let mut stage = match max_mb {
                Some(_) => FusionStage::with_sights(config.fusion.merge(), kept(&config)),
                None => FusionStage::new(config.fusion.merge()),
            };
            let started = std::time::Instant::now();
            for frame_id in 0..frames {
                let mut sight = sights[(frame_id % 5) as usize].clone();
                sight.meta.result.frame_id = frame_id;
                let seen = seen_frame(&sight).unwrap();
                stage.on_result(sight.meta.result.clone(), seen);
                if store.write(frame_id, sight) {
                    stage.sight_on_disk(frame_id);
                }
            }
            let taking_s = started.elapsed().as_secs_f64();
            stage.on_stream_end(frames);
            let started = std::time::Instant::now();
            let set = stage.change_set();
            let set_s = started.elapsed().as_secs_f64();
            let first_loads = stage.sight_memory().loads;
            let started = std::time::Instant::now();
            assert_eq!(stage.change_set(), set);
            let again_s = started.elapsed().as_secs_f64();
            let memory = stage.sight_memory();
            println!(
                "bound {max_mb:?} MB: {frames} frames taken in {taking_s:.2} s (sight written, pose term made), a first change set in {set_s:.3} s ({first_loads} read back), the same again in {again_s:.4} s; held {:.1} MB ({} frames), peak {:.1} MB, {} read back in all; free space {:?}",
                memory.held_bytes as f64 / 1e6,
                memory.frames_held,
                memory.peak_bytes as f64 / 1e6,
                memory.loads,
                set.free_space
                    .iter()
                    .map(|c| (c.seen_through_by.len(), c.agreed_by.len(), c.refuted))
                    .collect::<Vec<_>>()
            );
            sets.push(set);
        }
        assert_eq!(sets[0], sets[1]);
    }
}
