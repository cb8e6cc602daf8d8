//! The soak (issue #15 item 3) through the `asgreg soak` command: small synthetic frames that
//! register (240×132, initial poses 10 px off), with the change stage on, through `launch` while
//! a chaos loop SIGKILLs a random stage process (ingest, change and fusion included), flow worker
//! or the zenoh router every few seconds; the command itself checks exactly one PoseResult and
//! one change result per frame, each pose result equal to `register`'s on the same frame (and at
//! least one accepted), the complete fused change set,
//! resident memory after warm-up vs the end, and the shared-memory and socket counts, and exits
//! non-zero when one fails. Both forms are `#[ignore]`d (minutes of chaos); `.ci/run`
//! runs the short ones by name (`soak_short_`), the long ones are run by hand and their figures
//! go to docs/measurements.md.

use std::path::Path;

use crate::util::*;

/// Frames of the CI forms: registering 240×132 frames takes ~1 s each on the CI machine, so the
/// two short forms stay near the 100 s they took with 200 unregistered 64×48 frames.
const SHORT_FRAMES: usize = 40;

/// Seconds between kills of the CI forms. On an idle machine the 40 results come within a few
/// seconds (a kill every 2 s killed once: the test's ≥ 2 kills failed on CI); under load they
/// take ~50 s, where 1 s still stays below the launch's 20 restarts of one process a minute
/// (9 processes share the kills).
const SHORT_KILL_EVERY_S: f64 = 1.0;

/// Largest RSS growth the CI forms allow (the long forms keep the command's 10 %). In 40 frames
/// with a kill a second the warm-up window is results 4–8 and the end 36–40, a few samples
/// each; the command sums each (stage, worker) slot's largest sample so a slot just restarted
/// (mesh not loaded) does not lower a window, but which slots were killed still moves the
/// figure (sums per sample measured +10.8 % and, on a loaded CI machine, +32.2 % with no leak;
/// the long forms −0.4 % / +4.8 % over 1000 frames, docs/measurements.md). 25 % still catches
/// a leak that grows with the frames.
const SHORT_MAX_RSS_GROWTH: f64 = 0.25;

/// The long forms' bound: the command's default.
const LONG_MAX_RSS_GROWTH: f64 = 0.10;

fn soak(dir: &Path, transport: &str, frames: usize, kill_every_s: f64, max_rss_growth: f64) {
    let output = asgreg(&[
        "soak",
        "--frames",
        &frames.to_string(),
        "--kill-every-s",
        &kill_every_s.to_string(),
        "--transport",
        transport,
        "--out",
        path_str(dir),
        "--max-rss-growth",
        &max_rss_growth.to_string(),
    ]);
    let (stdout, stderr) = (stdout(&output), stderr(&output));
    assert!(
        output.status.success(),
        "soak over {transport} failed:\n{stdout}\n{stderr}"
    );
    let figures: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("soak.json")).unwrap()).unwrap();
    assert_eq!(figures["results"], frames, "{figures}");
    assert_eq!(figures["duplicated"], 0, "{figures}");
    assert_eq!(figures["change_results"], frames, "{figures}");
    assert_eq!(figures["change_duplicated"], 0, "{figures}");
    assert_eq!(figures["change_set_complete"], true, "{figures}");
    assert!(figures["accepted"].as_u64().unwrap() > 0, "{figures}");
    assert_eq!(figures["differing_from_register"], 0, "{figures}");
    assert!(figures["change_maps"].as_u64().unwrap() > 0, "{figures}");
    let kills: u64 = figures["kills"]
        .as_object()
        .unwrap()
        .values()
        .map(|n| n.as_u64().unwrap())
        .sum();
    assert!(
        kills >= 2,
        "the chaos loop killed {kills} processes: {figures}"
    );
    // Every kill is followed by a restart, but for one in the run's last moments (the launcher
    // was already shutting down: a CI run had 47 kills and 46 restarts, nothing lost).
    let not_restarted = figures["kills_not_restarted_at_end"].as_u64().unwrap();
    assert!(
        not_restarted <= 1,
        "{not_restarted} killed processes never restarted: {figures}"
    );
    assert!(
        figures["restarts"].as_u64().unwrap() + not_restarted >= kills,
        "fewer restarts than kills: {figures}"
    );
    println!(
        "{}",
        stdout
            .lines()
            .filter(|l| l.starts_with("soak figures"))
            .collect::<Vec<_>>()
            .join("\n")
    );
}

#[test]
#[ignore = "40 frames, a kill every second over iceoryx2 (~1 min); .ci/run runs it (soak_short_)"]
fn soak_short_iceoryx2_every_frame_one_result_under_kills() {
    let dir = tempfile::tempdir().unwrap();
    soak(
        dir.path(),
        "iceoryx2",
        SHORT_FRAMES,
        SHORT_KILL_EVERY_S,
        SHORT_MAX_RSS_GROWTH,
    );
}

#[test]
#[ignore = "40 frames, a kill every second over zenoh, router included (~1 min); .ci/run runs it (soak_short_)"]
fn soak_short_zenoh_every_frame_one_result_under_kills() {
    let dir = tempfile::tempdir().unwrap();
    soak(
        dir.path(),
        "zenoh",
        SHORT_FRAMES,
        SHORT_KILL_EVERY_S,
        SHORT_MAX_RSS_GROWTH,
    );
}

#[test]
#[ignore = "the long form: 1000 frames, minutes; run by hand, figures in docs/measurements.md"]
fn soak_long_iceoryx2_1000_frames() {
    let dir = tempfile::tempdir().unwrap();
    soak(dir.path(), "iceoryx2", 1000, 3.0, LONG_MAX_RSS_GROWTH);
}

#[test]
#[ignore = "the long form: 1000 frames, minutes; run by hand, figures in docs/measurements.md"]
fn soak_long_zenoh_1000_frames() {
    let dir = tempfile::tempdir().unwrap();
    soak(dir.path(), "zenoh", 1000, 3.0, LONG_MAX_RSS_GROWTH);
}
