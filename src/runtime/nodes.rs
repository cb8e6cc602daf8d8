//! The loop of each stage: receive, call the stage adapter, send. The same functions run as
//! threads (`asgreg run`) or as processes (`asgreg stage`, `asgreg launch`); `main` only wires.
//! Every loop checks the stop flag, reports metrics once a second, and returns its metrics.
//! A stage process's stop flag is set by SIGTERM or SIGINT ([`termination_flag`]): the loop
//! finishes the message in hand, sends what it produced, hands back the jobs it was given and
//! not finished (flow, render), and returns, so its bus ports close cleanly.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::core::mesh::Mesh;
use crate::msg::{
    change_result_json, change_set_json, pose_result_json, Body, FrameFailed, Header, JobKey,
    StageMetrics, StreamEnd,
};
use crate::stage::change::{ChangeStage, StereoDepthSettings};
use crate::stage::flow::FlowStage;
use crate::stage::fusion::{seen_frame, FusionStage};
use crate::stage::ingest::{FolderSource, SourceError};
use crate::stage::pose::PoseStage;
use crate::stage::render::RenderStage;
use crate::stage::verify::{ChangeWork, DecidedFrame, ReadyFrame, VerifyStage, VerifyWorkspace};
use crate::transport::{keys, Transport};

use super::ack::Resender;
use super::bus::{encode_to_vec, unix_time_ns, BusError, Inbox, Outbox};
use super::config::{BackpressurePolicy, PipelineConfig};
use super::dispatch::{Dispatcher, WorkerPort};
use super::journal::{self, Journal, JournalError};
use super::lenders::LenderStore;
use super::received::ReceivedStore;
use super::sights::{self, SightStore};
use super::views::ViewStore;

/// How long a loop waits for a message before checking the stop flag.
const POLL: Duration = Duration::from_millis(20);
/// Messages verify takes from its inbox in one pass before its bookkeeping.
const VERIFY_DRAIN_MAX: usize = 256;
/// Change jobs verify queues for the change workers (verify never waits for them: a change job
/// is a few ms of work per frame, far less than a frame's registration).
const CHANGE_JOBS_QUEUED: usize = 1024;
/// How long verify waits for a change result to be published after no change worker holds its
/// job any more (or after sending a frame's result to fusion) before it issues the work again.
const CHANGE_RESEND_AFTER: Duration = Duration::from_secs(3);
/// How often verify and fusion repeat the end of their stream once it is complete.
const END_REPEAT: Duration = Duration::from_secs(2);
/// Most compute samples a metrics message carries (the most recent ones).
const MAX_SAMPLES: usize = 4096;

#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error(transparent)]
    Bus(#[from] BusError),
    #[error(transparent)]
    Source(#[from] SourceError),
    #[error("cannot install the SIGTERM/SIGINT handler of the stage: {0}")]
    Signal(std::io::Error),
    #[error(transparent)]
    Journal(#[from] JournalError),
    #[error("{stage}: stopped by a signal before the end of the stream: {detail}")]
    Stopped { stage: &'static str, detail: String },
}

impl NodeError {
    /// True when a restart of the stage cannot help ([`JournalError::needs_operator`]): the
    /// stage process then exits with [`super::EXIT_NEEDS_OPERATOR`].
    pub fn needs_operator(&self) -> bool {
        matches!(self, NodeError::Journal(error) if error.needs_operator())
    }
}

/// Set by SIGTERM or SIGINT in a stage process.
static TERMINATION_REQUESTED: AtomicBool = AtomicBool::new(false);

#[cfg(unix)]
extern "C" fn on_termination_signal(_signal: libc::c_int) {
    // A store to a lock-free atomic is async-signal-safe.
    TERMINATION_REQUESTED.store(true, Ordering::Relaxed);
}

/// The stop flag of a stage process: SIGTERM or SIGINT sets it and the stage stops cleanly at
/// its next poll (within a message's compute time) instead of dying with its shared memory open.
/// The launcher sends SIGTERM first and SIGKILL only after `launch.stop_grace_s`.
pub fn termination_flag() -> Result<&'static AtomicBool, NodeError> {
    #[cfg(unix)]
    for signal in [libc::SIGTERM, libc::SIGINT] {
        let handler = on_termination_signal as extern "C" fn(libc::c_int);
        // SAFETY: the handler only stores to an atomic; `signal` installs it process-wide.
        let previous = unsafe { libc::signal(signal, handler as libc::sighandler_t) };
        if previous == libc::SIG_ERR {
            return Err(NodeError::Signal(std::io::Error::last_os_error()));
        }
    }
    Ok(&TERMINATION_REQUESTED)
}

/// What every stage loop gets.
pub struct NodeContext<'a> {
    pub transport: &'a dyn Transport,
    pub config: &'a PipelineConfig,
    pub worker_index: u32,
    pub stop: &'a AtomicBool,
}

impl NodeContext<'_> {
    fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    fn startup(&self) -> Duration {
        Duration::from_secs_f64(self.config.timeouts.startup_s)
    }

    fn metrics(&self, stage: &str) -> StageMetrics {
        StageMetrics {
            stage: stage.to_string(),
            worker_index: self.worker_index,
            incarnation: process_incarnation(),
            ..StageMetrics::default()
        }
    }
}

/// Sends a stage's metrics on the metrics topic once a second.
struct MetricsReporter {
    outbox: Outbox,
    last: Instant,
}

impl MetricsReporter {
    fn open(transport: &dyn Transport) -> Result<Self, BusError> {
        Ok(Self {
            outbox: Outbox::open(transport, keys::METRICS)?,
            last: Instant::now(),
        })
    }

    fn tick(&mut self, metrics: &StageMetrics, force: bool) {
        if !force && self.last.elapsed() < Duration::from_secs(1) {
            return;
        }
        self.last = Instant::now();
        // Metrics are best effort: a failure to report, or a monitor that does not read, never
        // stops a stage (with many workers every stage both sends and reads metrics: a
        // blocking send could wait in a cycle).
        if let Err(error) = self.outbox.send_lossy(Body::Metrics(metrics.clone())) {
            tracing::debug!("metrics not sent: {error}");
        }
    }
}

/// A value that differs between two starts of a process (so a restart is visible in metrics).
fn process_incarnation() -> u64 {
    static INCARNATION: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *INCARNATION.get_or_init(|| unix_time_ns() ^ (u64::from(std::process::id()) << 32))
}

/// What ingest keeps of a frame until its result is out.
enum Kept {
    Frame(std::sync::Arc<Vec<u8>>),
    Failed(FrameFailed, u64),
}

/// A kept frame and how long it has gone unanswered.
struct KeptFrame {
    kept: Kept,
    /// When render handed it on (its jobs left render's queue) or, for a frame failed at ingest,
    /// when it went to verify; `None` while the dispatcher holds it.
    handed_on: Option<Instant>,
    /// How long it may go without a result before it is sent again (doubles each time).
    wait: Duration,
}

impl KeptFrame {
    /// Sends the frame down the pipeline (the first time or again): a frame to the render
    /// workers (its wait starts once render has taken it), a frame failed at ingest to verify
    /// (its wait starts now).
    fn send(
        &mut self,
        frame_id: u64,
        dispatcher: &mut Dispatcher,
        verify: &mut Outbox,
        metrics: &mut StageMetrics,
    ) -> Result<(), BusError> {
        match &self.kept {
            Kept::Frame(bytes) => {
                self.handed_on = None;
                dispatcher.push_shared(
                    JobKey {
                        frame_id,
                        coarse_index: 0,
                    },
                    std::sync::Arc::clone(bytes),
                );
            }
            Kept::Failed(failed, capture) => {
                self.handed_on = Some(Instant::now());
                verify.send(
                    frame_id,
                    *capture,
                    Body::FrameFailed(failed.clone()),
                    metrics,
                )?;
            }
        }
        Ok(())
    }
}

/// The longest wait before an unanswered frame is sent again, as a multiple of the first.
const REDO_UNANSWERED_MAX_FACTOR: u32 = 8;

/// Ingest's memory of every frame until its result is out (with change detection: its pose
/// result and its change result), so that the frames a crashed pose or verify process took with
/// it are redone (render and flow have the dispatcher's redo; fusion's restarts are verify's
/// to repair, see [`ChangeRecovery`]).
struct Recovery {
    results: Inbox,
    /// With change detection: the published change results.
    changes: Option<Inbox>,
    metrics: Inbox,
    kept: std::collections::BTreeMap<u64, KeptFrame>,
    /// `timeouts.redo_unanswered_after_s`; `None`: never.
    redo_unanswered_after: Option<Duration>,
    /// With step "neighbour": its window and look-ahead
    /// (`registration.neighbour_pose.window_frames`, `lookahead_frames`). Verify holds a frame's
    /// result until every frame of its window has one, so a frame with an earlier frame of its
    /// window unanswered is waiting for it, not lost — unless that frame waits for it in turn
    /// (its look-ahead).
    neighbour_frames: Option<(u64, u64)>,
    /// When a frame last got all its results (or the start).
    last_finished_at: Instant,
    /// Frames with both results out (the pose result alone without change detection).
    finished: std::collections::BTreeSet<u64>,
    /// Frames with their pose result out, and (change detection) with their change result out.
    posed: std::collections::BTreeSet<u64>,
    changed: std::collections::BTreeSet<u64>,
    incarnations: HashMap<(String, u32), u64>,
    /// The results journals (path, header) and when they were last read: they also list
    /// results published while this process was not there to receive them.
    journals: Vec<(journal::Kind, std::path::PathBuf, String)>,
    journal_read: Instant,
    /// Frames in the source: ids at or above it in a journal are not this run's.
    frame_count: u64,
    /// Whether verify has announced the end of the stream on the results topic: it knows the
    /// frame count, so the end ingest sent it was not lost.
    verify_knows_end: bool,
}

impl Recovery {
    /// Subscribes to results first, then reads the journals, so a result is either in a
    /// journal or arrives on the bus.
    fn open(
        transport: &dyn Transport,
        config: &PipelineConfig,
        frame_count: u64,
    ) -> Result<Self, NodeError> {
        let kinds: &[journal::Kind] = if config.changes_enabled() {
            &[journal::Kind::Pose, journal::Kind::Change]
        } else {
            &[journal::Kind::Pose]
        };
        let mut recovery = Self {
            results: Inbox::open(transport, keys::RESULTS, "ingest")?,
            changes: if config.changes_enabled() {
                Some(Inbox::open(transport, keys::CHANGES, "ingest")?)
            } else {
                None
            },
            metrics: Inbox::open(transport, keys::METRICS, "ingest")?,
            kept: std::collections::BTreeMap::new(),
            redo_unanswered_after: (config.timeouts.redo_unanswered_after_s > 0.0)
                .then(|| Duration::from_secs_f64(config.timeouts.redo_unanswered_after_s)),
            neighbour_frames: config.registration.neighbour_pose.enabled.then_some((
                config.registration.neighbour_pose.window_frames as u64,
                config.registration.neighbour_pose.lookahead_frames as u64,
            )),
            last_finished_at: Instant::now(),
            finished: std::collections::BTreeSet::new(),
            posed: std::collections::BTreeSet::new(),
            changed: std::collections::BTreeSet::new(),
            incarnations: HashMap::new(),
            journals: kinds
                .iter()
                .map(|&kind| {
                    (
                        kind,
                        journal::path(config, kind),
                        journal::header(config, kind),
                    )
                })
                .collect(),
            journal_read: Instant::now(),
            frame_count,
            verify_knows_end: false,
        };
        recovery.read_journals(true)?;
        Ok(recovery)
    }

    /// A result of `kind` is out for `frame_id`; the frame is finished once all are.
    fn on_published(&mut self, kind: journal::Kind, frame_id: u64) {
        if frame_id >= self.frame_count {
            return;
        }
        match kind {
            journal::Kind::Pose => self.posed.insert(frame_id),
            journal::Kind::Change => self.changed.insert(frame_id),
            // Ingest reads only the journals of published results.
            journal::Kind::PoseAcked | journal::Kind::ChangeAcked => return,
        };
        let needs_change = self.changes.is_some();
        if self.posed.contains(&frame_id) && (!needs_change || self.changed.contains(&frame_id)) {
            self.kept.remove(&frame_id);
            if self.finished.insert(frame_id) {
                self.last_finished_at = Instant::now();
            }
        }
    }

    /// Reads the results journals; at the start, says when one ends in a line cut short (a crash
    /// mid-write; later reads may meet a line being written).
    fn read_journals(&mut self, at_start: bool) -> Result<(), JournalError> {
        let mut published = Vec::new();
        for (kind, path, header) in &self.journals {
            let contents = journal::read(path, header)?;
            if at_start && contents.cut_bytes > 0 {
                tracing::warn!(
                    "ingest: {}: the last line ({} bytes) was cut short by a crash mid-write; resuming from the {} complete lines before it",
                    path.display(),
                    contents.cut_bytes,
                    contents.entries.len()
                );
            }
            for frame_id in contents.entries.into_keys() {
                published.push((*kind, frame_id));
            }
        }
        self.journal_read = Instant::now();
        for (kind, frame_id) in published {
            self.on_published(kind, frame_id);
        }
        Ok(())
    }

    /// Takes the results and metrics that arrived; true when pose or verify restarted.
    fn poll(&mut self) -> Result<bool, NodeError> {
        if self.journal_read.elapsed() >= Duration::from_secs(1) {
            self.read_journals(false)?;
        }
        let mut scratch = StageMetrics::default();
        let mut published = Vec::new();
        let frame_count = self.frame_count;
        let verify_knows_end = &mut self.verify_knows_end;
        while self.results.receive(
            Duration::ZERO,
            &mut scratch,
            &mut |message, _| match message.body {
                Body::PoseResult(result) => {
                    published.push((journal::Kind::Pose, result.frame_id));
                }
                Body::StreamEnd(end) if end.frame_count == frame_count => {
                    *verify_knows_end = true;
                }
                _ => {}
            },
        )? {}
        if let Some(changes) = &mut self.changes {
            while changes.receive(Duration::ZERO, &mut scratch, &mut |message, _| {
                if let Body::ChangeResult(result) = message.body {
                    published.push((journal::Kind::Change, result.frame_id));
                }
            })? {}
        }
        for (kind, frame_id) in published {
            self.on_published(kind, frame_id);
        }
        let mut restarted = false;
        let incarnations = &mut self.incarnations;
        while self
            .metrics
            .receive(Duration::ZERO, &mut scratch, &mut |message, _| {
                if let Body::Metrics(metrics) = message.body {
                    if metrics.stage == "pose" || metrics.stage == "verify" {
                        let key = (metrics.stage.clone(), metrics.worker_index);
                        if let Some(previous) = incarnations.insert(key, metrics.incarnation) {
                            if previous != metrics.incarnation {
                                tracing::warn!(
                                    "ingest: the {} stage restarted; redoing the frames without a result",
                                    metrics.stage
                                );
                                restarted = true;
                            }
                        }
                    }
                }
            })?
        {}
        Ok(restarted)
    }

    /// Keeps `frame_id` until its result is out and sends it ([`KeptFrame::send`]).
    fn keep_and_send(
        &mut self,
        frame_id: u64,
        kept: Kept,
        dispatcher: &mut Dispatcher,
        verify: &mut Outbox,
        metrics: &mut StageMetrics,
    ) -> Result<(), BusError> {
        let mut frame = KeptFrame {
            kept,
            handed_on: None,
            wait: self.redo_unanswered_after.unwrap_or(Duration::ZERO),
        };
        let sent = frame.send(frame_id, dispatcher, verify, metrics);
        self.kept.insert(frame_id, frame);
        sent
    }

    /// Takes what arrived; when pose or verify restarted, redoes the frames without a result,
    /// and otherwise the frames gone unanswered for too long.
    fn service(
        &mut self,
        dispatcher: &mut Dispatcher,
        verify: &mut Outbox,
        stream_end: Option<u64>,
        metrics: &mut StageMetrics,
    ) -> Result<(), NodeError> {
        if self.poll()? {
            self.redo(dispatcher, verify, stream_end, metrics)?;
        } else {
            self.redo_unanswered(dispatcher, verify, metrics)?;
        }
        Ok(())
    }

    /// Sends again each frame that render handed on (or that went to verify failed) and that has
    /// no pose result after its wait, when a later frame already has its result or no frame got
    /// one for as long: all its messages were lost in flight (the zenoh router restarting), so
    /// verify never heard of it and nothing else would ever give it a result (the acks test's
    /// launch ran into its deadline with 39 of 40 results). A frame still on its way only costs
    /// a repeat that verify ignores; the wait doubles each time. A frame posed but without its
    /// change result is not sent again: that is verify's `ChangeRecovery`. With step
    /// "neighbour", neither is a frame with an unanswered earlier frame in its window: verify
    /// holds it for that frame (only the oldest of such a chain can be lost, and the frames of
    /// its look-ahead, whose own decisions it waits for).
    fn redo_unanswered(
        &mut self,
        dispatcher: &mut Dispatcher,
        verify: &mut Outbox,
        metrics: &mut StageMetrics,
    ) -> Result<(), BusError> {
        let Some(first_wait) = self.redo_unanswered_after else {
            return Ok(());
        };
        let now = Instant::now();
        let quiet = now.duration_since(self.last_finished_at);
        // With step "neighbour"'s look-ahead a frame's result cannot come before the frames
        // after it were through (verify waits for their own decisions): its wait counts from
        // the last of them that render took; none while one is still to be taken.
        let lookahead = self.neighbour_frames.map_or(0, |(_, lookahead)| lookahead);
        let last_ahead_handed_on = |frame_id: u64| {
            let until = frame_id
                .saturating_add(lookahead)
                .min(self.frame_count.saturating_sub(1));
            (frame_id..=until).try_fold(None, |latest: Option<Instant>, id| {
                match self.kept.get(&id).map(|frame| frame.handed_on) {
                    Some(Some(at)) => Some(Some(latest.map_or(at, |l| l.max(at)))),
                    // Finished (no longer kept): through.
                    None if self.finished.contains(&id) => Some(latest),
                    // Still with the dispatcher, or not read from the source yet.
                    _ => None,
                }
            })
        };
        // Decided on the frames as they are, then applied: (frame, how long it waited and
        // whether a later frame has its result, when it is to be sent again; `None`: render has
        // just taken it).
        let mut due: Vec<(u64, Option<(Duration, bool)>)> = Vec::new();
        let mut unposed_before: Option<u64> = None;
        let mut oldest_of_chain = 0;
        for (&frame_id, frame) in &self.kept {
            if self.posed.contains(&frame_id) {
                continue;
            }
            let in_chain = unposed_before
                .zip(self.neighbour_frames)
                .is_some_and(|(earlier, (window, _))| frame_id - earlier <= window);
            if !in_chain {
                oldest_of_chain = frame_id;
            }
            let held = in_chain
                && self
                    .neighbour_frames
                    .is_some_and(|(_, lookahead)| frame_id - oldest_of_chain > lookahead);
            unposed_before = Some(frame_id);
            if held {
                continue;
            }
            if frame.handed_on.is_none() {
                if !dispatcher.holds(frame_id) {
                    due.push((frame_id, None));
                }
                continue;
            }
            let Some(Some(expected_from)) = last_ahead_handed_on(frame_id) else {
                continue;
            };
            let waited = now.duration_since(expected_from);
            let overtaken = self.finished.range(frame_id + 1..).next().is_some();
            if waited >= frame.wait && (overtaken || quiet >= frame.wait) {
                due.push((frame_id, Some((waited, overtaken))));
            }
        }
        for (frame_id, waited) in due {
            let Some(frame) = self.kept.get_mut(&frame_id) else {
                continue;
            };
            let Some((waited, overtaken)) = waited else {
                frame.handed_on = Some(now);
                continue;
            };
            tracing::warn!(
                "ingest: frame {frame_id} has no result {:.0} s after render took it (and the frames of its look-ahead) and {}; its messages were lost in flight: sending it again",
                waited.as_secs_f64(),
                if overtaken {
                    "a later frame has its result"
                } else {
                    "no frame got a result since"
                }
            );
            metrics.redispatched += 1;
            frame.wait = (frame.wait * 2).min(first_wait * REDO_UNANSWERED_MAX_FACTOR);
            frame.send(frame_id, dispatcher, verify, metrics)?;
        }
        Ok(())
    }

    fn finished_frames(&self) -> Vec<u64> {
        self.finished.iter().copied().collect()
    }

    /// Sends every frame without a result again (verify ignores what it already has).
    fn redo(
        &mut self,
        dispatcher: &mut Dispatcher,
        verify: &mut Outbox,
        stream_end: Option<u64>,
        metrics: &mut StageMetrics,
    ) -> Result<(), BusError> {
        for (&frame_id, frame) in &mut self.kept {
            if matches!(frame.kept, Kept::Frame(_)) {
                metrics.redispatched += 1;
            }
            frame.send(frame_id, dispatcher, verify, metrics)?;
        }
        if let Some(frame_count) = stream_end {
            verify.send(
                0,
                0,
                Body::StreamEnd(StreamEnd {
                    frame_count,
                    finished_frames: self.finished_frames(),
                }),
                metrics,
            )?;
        }
        Ok(())
    }
}

fn record_compute(metrics: &mut StageMetrics, started: Instant) {
    record_compute_ms(metrics, started.elapsed().as_secs_f64() * 1e3);
}

fn record_compute_ms(metrics: &mut StageMetrics, ms: f64) {
    metrics.compute_ms += ms;
    if metrics.compute_samples_ms.len() >= MAX_SAMPLES {
        metrics.compute_samples_ms.remove(0);
    }
    metrics.compute_samples_ms.push(ms);
}

fn unexpected(stage: &str, kind: crate::msg::MessageKind, frame_id: u64) {
    tracing::error!("{stage}: ignored an unexpected {kind:?} message (frame {frame_id})");
}

/// Ingest stops early: drops its subscriptions (no stage's last metrics wait on them), sends
/// its last metrics and says why.
fn stop_ingest(
    reporter: &mut MetricsReporter,
    metrics: &StageMetrics,
    recovery: Recovery,
    frame_count: u64,
) -> NodeError {
    let error = stopped_early(&recovery, frame_count);
    drop(recovery);
    reporter.tick(metrics, true);
    error
}

/// Ingest stopped (SIGTERM) before every frame had its result: an error, so that the
/// supervisor restarts it (a clean exit of ingest means the stream is complete).
fn stopped_early(recovery: &Recovery, frame_count: u64) -> NodeError {
    NodeError::Stopped {
        stage: "ingest",
        detail: format!(
            "{} of {frame_count} frames have their result; a restart resumes from the results journal",
            recovery.finished.len()
        ),
    }
}

/// Stage "ingest": reads the source, dispatches frames to render workers by the backpressure
/// policy, sends failures and the end of the stream to verify, and stays until every frame has
/// its result: it redoes the frames of a render worker that died (dispatcher) and, when pose or
/// verify restarts, every frame still without a result (`Recovery`).
pub fn run_ingest(ctx: &NodeContext) -> Result<StageMetrics, NodeError> {
    let config = ctx.config;
    let mut metrics = ctx.metrics("ingest");
    let mut reporter = MetricsReporter::open(ctx.transport)?;
    let mut source = FolderSource::open(&config.source)?;
    let mut dispatcher = Dispatcher::open(
        ctx.transport,
        keys::FRAMES_LINK,
        config.backpressure.frames_queued,
        Duration::from_secs_f64(config.timeouts.worker_silence_s),
    )?;
    let mut verify = Outbox::open(ctx.transport, keys::VERIFY_IN)?;
    verify.wait_for_reader("verify", ctx.startup())?;
    let frame_count = source.len() as u64;
    let mut recovery = Recovery::open(ctx.transport, config, frame_count)?;
    if !recovery.finished.is_empty() {
        // A restart: resume instead of replaying what already has its result.
        tracing::info!(
            "ingest: resuming: {} of {frame_count} frames already have their published result ({}); sending the other {}",
            recovery.finished.len(),
            recovery
                .journals
                .iter()
                .map(|(_, path, _)| path.display().to_string())
                .collect::<Vec<_>>()
                .join(", "),
            frame_count - recovery.finished.len() as u64
        );
    }
    let period =
        (config.source.rate_hz > 0.0).then(|| Duration::from_secs_f64(1.0 / config.source.rate_hz));
    let mut next_emit = Instant::now();
    let mut names: HashMap<u64, (String, u64)> = HashMap::new();
    while let Some((frame_id, frame)) = source.next_frame_except(&recovery.finished) {
        if ctx.stopped() {
            return Err(stop_ingest(&mut reporter, &metrics, recovery, frame_count));
        }
        recovery.service(&mut dispatcher, &mut verify, None, &mut metrics)?;
        if let Some(period) = period {
            while Instant::now() < next_emit {
                dispatcher.pump((next_emit - Instant::now()).min(POLL))?;
                recovery.service(&mut dispatcher, &mut verify, None, &mut metrics)?;
            }
            next_emit += period;
        }
        let capture_time_ns = unix_time_ns();
        let started = Instant::now();
        match frame {
            Err(failed) => {
                tracing::warn!("frame {frame_id} '{}': {}", failed.name, failed.reason);
                recovery.keep_and_send(
                    frame_id,
                    Kept::Failed(failed, capture_time_ns),
                    &mut dispatcher,
                    &mut verify,
                    &mut metrics,
                )?;
            }
            Ok(frame) => {
                names.insert(frame_id, (frame.info.name.clone(), capture_time_ns));
                let bytes = std::sync::Arc::new(encode_to_vec(
                    frame_id,
                    capture_time_ns,
                    Body::Frame(frame),
                )?);
                record_compute(&mut metrics, started);
                while !dispatcher.has_room() {
                    match config.backpressure.policy {
                        BackpressurePolicy::Block => {
                            if ctx.stopped() {
                                return Err(stop_ingest(
                                    &mut reporter,
                                    &metrics,
                                    recovery,
                                    frame_count,
                                ));
                            }
                            dispatcher.pump(POLL)?;
                            recovery.service(&mut dispatcher, &mut verify, None, &mut metrics)?;
                        }
                        BackpressurePolicy::DropOldest => {
                            recovery.service(&mut dispatcher, &mut verify, None, &mut metrics)?;
                            if let Some(dropped) = dispatcher.drop_oldest() {
                                metrics.dropped += 1;
                                let (name, capture) =
                                    names.get(&dropped.frame_id).cloned().unwrap_or_default();
                                recovery.kept.remove(&dropped.frame_id);
                                tracing::warn!("frame {} '{name}' dropped: the pipeline is full (backpressure policy drop-oldest)", dropped.frame_id);
                                verify.send(
                                    dropped.frame_id,
                                    capture,
                                    Body::FrameFailed(FrameFailed {
                                        name,
                                        stage: "ingest".to_string(),
                                        reason: "dropped: the pipeline was full (backpressure policy drop-oldest)".to_string(),
                                    }),
                                    &mut metrics,
                                )?;
                            }
                        }
                    }
                }
                // Kept from when the dispatcher holds it (its wait for a result starts once
                // render has taken it).
                recovery.keep_and_send(
                    frame_id,
                    Kept::Frame(bytes),
                    &mut dispatcher,
                    &mut verify,
                    &mut metrics,
                )?;
                metrics.messages_out += 1;
                dispatcher.pump(Duration::ZERO)?;
            }
        }
        metrics.max_queue_depth = metrics.max_queue_depth.max(dispatcher.queued() as u64);
        reporter.tick(&metrics, false);
    }
    recovery.poll()?;
    // Until every frame has its result: redo what a crashed stage took with it. The end of the
    // stream is repeated until verify announces it: over zenoh one sent while the router is
    // down is lost, and verify (and with it the collector) would never learn the frame count
    // (the acks test's launch ran into its deadline with every result delivered).
    let mut end_sent: Option<Instant> = None;
    loop {
        if !recovery.verify_knows_end && end_sent.is_none_or(|at| at.elapsed() >= END_REPEAT) {
            verify.send(
                0,
                0,
                Body::StreamEnd(StreamEnd {
                    frame_count,
                    finished_frames: recovery.finished_frames(),
                }),
                &mut metrics,
            )?;
            end_sent = Some(Instant::now());
        }
        let complete = dispatcher.is_idle()
            && recovery.finished.len() as u64 >= frame_count
            && recovery.verify_knows_end;
        if complete {
            break;
        }
        if ctx.stopped() {
            return Err(stop_ingest(&mut reporter, &metrics, recovery, frame_count));
        }
        dispatcher.pump(POLL)?;
        recovery.service(
            &mut dispatcher,
            &mut verify,
            Some(frame_count),
            &mut metrics,
        )?;
        reporter.tick(&metrics, false);
    }
    metrics.redispatched += dispatcher.metrics.redispatched;
    metrics.bytes_out += dispatcher.metrics.bytes_out;
    metrics.send_ms += dispatcher.metrics.send_ms;
    // Its subscriptions go first: the other stages' last metrics must not wait on them.
    drop(recovery);
    reporter.tick(&metrics, true);
    Ok(metrics)
}

/// Stage "render": takes a frame when the flow queue has room for its coarse poses, renders them
/// and dispatches the flow jobs to the flow workers. A frame is reported finished to ingest only
/// once all its jobs have left render's queue, so if render dies before that, ingest hands the
/// frame to the restarted render and nothing is lost.
pub fn run_render(ctx: &NodeContext, mesh: &Mesh) -> Result<StageMetrics, NodeError> {
    let config = ctx.config;
    let mut metrics = ctx.metrics("render");
    let mut reporter = MetricsReporter::open(ctx.transport)?;
    // Two frames: one whose jobs are being handed out, one being rendered.
    let mut port = WorkerPort::open(
        ctx.transport,
        keys::FRAMES_LINK,
        ctx.worker_index,
        2,
        "render",
    )?;
    // Each render worker feeds its own share of the flow workers (`keys::flow_link`).
    let mut dispatcher = Dispatcher::open(
        ctx.transport,
        &keys::flow_link(ctx.worker_index),
        config.backpressure.flow_jobs_queued,
        Duration::from_secs_f64(config.timeouts.worker_silence_s),
    )?;
    let mut verify = Outbox::open(ctx.transport, keys::VERIFY_IN)?;
    verify.wait_for_reader("verify", ctx.startup())?;
    let mut stage =
        RenderStage::new(mesh, config.registration.clone()).with_simulated_work(config.simulate);
    if config.changes_enabled() {
        stage = stage.with_depth_forwarding();
    }
    // Room for a whole frame's jobs before taking it (soft: a frame may bring more than the queue
    // holds when the pose search gives it several centres).
    let frame_room = config
        .registration
        .max_coarse_views()
        .min(config.backpressure.flow_jobs_queued);
    // Frames whose jobs are still (partly) in render's queue.
    let mut handing_out: Vec<u64> = Vec::new();
    while !ctx.stopped() {
        dispatcher.pump(Duration::ZERO)?;
        let (handed_out, waiting): (Vec<u64>, Vec<u64>) = handing_out
            .iter()
            .partition(|frame_id| !dispatcher.has_queued(**frame_id));
        handing_out = waiting;
        for frame_id in handed_out {
            port.finished(JobKey {
                frame_id,
                coarse_index: 0,
            })?;
        }
        if dispatcher.queued() + frame_room > config.backpressure.flow_jobs_queued {
            port.heartbeat()?;
            dispatcher.pump(POLL)?;
            continue;
        }
        let mut finished: Option<Result<(JobKey, bool), BusError>> = None;
        port.receive(POLL, &mut metrics, &mut |message, metrics| {
            let frame_id = message.header.frame_id;
            let capture = message.header.capture_time_ns;
            let Body::Frame(frame) = message.body else {
                unexpected("render", message.body.kind(), frame_id);
                return;
            };
            let started = Instant::now();
            // Each job is encoded as it is rendered (it borrows the stage's buffers); encoding
            // counts as transport time, like every Outbox send.
            let mut encoded: Result<(), BusError> = Ok(());
            let mut encode_ms = 0.0;
            // The query goes to verify (its send time is counted by the Outbox).
            let mut query_sent: Result<(), BusError> = Ok(());
            let mut query_ms = 0.0;
            let outcome = stage.process(
                &frame,
                &mut |query| {
                    let send_started = Instant::now();
                    query_sent = verify
                        .send(frame_id, capture, Body::FrameQuery(query), metrics)
                        .map(|_| ());
                    query_ms += send_started.elapsed().as_secs_f64() * 1e3;
                },
                &mut |job| {
                    let encode_started = Instant::now();
                    let key = JobKey {
                        frame_id,
                        coarse_index: job.meta.coarse_index,
                    };
                    // Each job is handed out as soon as its view is rendered (a flow worker
                    // with a free slot starts on it while the next view renders).
                    let pushed =
                        encode_to_vec(frame_id, capture, Body::FlowJob(job)).map(|bytes| {
                            dispatcher.push(key, bytes);
                        });
                    if let Err(error) = pushed.and_then(|()| dispatcher.pump(Duration::ZERO)) {
                        if encoded.is_ok() {
                            encoded = Err(error);
                        }
                    }
                    encode_ms += encode_started.elapsed().as_secs_f64() * 1e3;
                },
            );
            if let Err(error) = query_sent {
                if encoded.is_ok() {
                    encoded = Err(error);
                }
            }
            record_compute_ms(
                metrics,
                started.elapsed().as_secs_f64() * 1e3 - encode_ms - query_ms,
            );
            metrics.send_ms += encode_ms;
            let key = JobKey {
                frame_id,
                coarse_index: 0,
            };
            finished = Some(match outcome {
                Ok(_) => encoded.map(|()| (key, false)),
                Err(failed) => {
                    tracing::warn!("frame {frame_id} '{}': {}", failed.name, failed.reason);
                    verify
                        .send(frame_id, capture, Body::FrameFailed(failed), metrics)
                        .map(|_| (key, true))
                }
            });
        })?;
        match finished {
            // A failed frame is done; a rendered one once its jobs are handed out.
            Some(Ok((key, true))) => port.finished(key)?,
            Some(Ok((key, false))) => handing_out.push(key.frame_id),
            Some(Err(error)) => return Err(error.into()),
            None => {}
        }
        metrics.max_queue_depth = metrics.max_queue_depth.max(dispatcher.queued() as u64);
        metrics.redispatched = dispatcher.metrics.redispatched;
        reporter.tick(&metrics, false);
    }
    // Frames not yet handed out to flow go back to ingest, which gives them to another start.
    if let Err(error) = port.leave() {
        tracing::debug!("jobs not handed back (their producer is gone too): {error}");
    }
    metrics.messages_out += dispatcher.metrics.messages_out;
    metrics.bytes_out += dispatcher.metrics.bytes_out;
    metrics.send_ms += dispatcher.metrics.send_ms;
    reporter.tick(&metrics, true);
    Ok(metrics)
}

/// Stage "flow" (N workers): one (frame, coarse pose) job at a time, correspondences to pose.
pub fn run_flow(ctx: &NodeContext, mesh: &Mesh) -> Result<StageMetrics, NodeError> {
    // One outbox per pose worker: each job's correspondences go to the pose worker that solves
    // them, so a flow worker waits only when that pose worker's queue is full.
    let pose_workers = ctx.config.workers.pose.max(1);
    let mut pose = (0..pose_workers)
        .map(|w| Outbox::open(ctx.transport, &keys::pose_in(w)))
        .collect::<Result<Vec<_>, _>>()?;
    for outbox in &mut pose {
        outbox.wait_for_reader("pose", ctx.startup())?;
    }
    let mut stage = FlowStage::new(mesh, ctx.config.registration.clone(), ctx.worker_index)
        .with_simulated_work(ctx.config.simulate);
    let link = keys::flow_link_of_worker(ctx.worker_index, ctx.config.workers.render);
    serve_jobs(ctx, "flow", &link, &mut |message, metrics| {
        let frame_id = message.header.frame_id;
        let Body::FlowJob(job) = message.body else {
            unexpected("flow", message.body.kind(), frame_id);
            return None;
        };
        let started = Instant::now();
        // The job's images are read where they arrived (shared memory for iceoryx2).
        let correspondences = stage.process(frame_id, &job);
        record_compute(metrics, started);
        let key = JobKey {
            frame_id,
            coarse_index: job.meta.coarse_index,
        };
        let pose_worker = pose_worker_of(frame_id, job.meta.coarse_index, pose_workers);
        Some(
            pose[pose_worker as usize]
                .send(
                    frame_id,
                    message.header.capture_time_ns,
                    Body::Correspondences(correspondences),
                    metrics,
                )
                .map(|_| key),
        )
    })
}

/// What a dispatched worker does with one message: `None` when it is not a job, else the
/// job's key once its output is sent (or the send's error).
type JobHandler<'a> =
    dyn FnMut(crate::msg::Envelope<'_>, &mut StageMetrics) -> Option<Result<JobKey, BusError>> + 'a;

/// The loop of a worker that the dispatcher feeds over `link` (flow, change): each job is
/// handed to `work`, which processes it, sends its output on and returns the job's key (or
/// `None` for a message that is not a job); the job is then reported finished. On stop, jobs
/// given to this worker after its last one are handed back to be redone elsewhere at once.
fn serve_jobs(
    ctx: &NodeContext,
    stage: &str,
    link: &str,
    work: &mut JobHandler<'_>,
) -> Result<StageMetrics, NodeError> {
    let mut metrics = ctx.metrics(stage);
    let mut reporter = MetricsReporter::open(ctx.transport)?;
    let mut port = WorkerPort::open(
        ctx.transport,
        link,
        ctx.worker_index,
        ctx.config.workers.slots,
        stage,
    )?;
    while !ctx.stopped() {
        let mut finished: Option<Result<JobKey, BusError>> = None;
        port.receive(POLL, &mut metrics, &mut |message, metrics| {
            finished = work(message, metrics);
        })?;
        if let Some(finished) = finished {
            port.finished(finished?)?;
        }
        reporter.tick(&metrics, false);
    }
    if let Err(error) = port.leave() {
        tracing::debug!("jobs not handed back (their producer is gone too): {error}");
    }
    reporter.tick(&metrics, true);
    Ok(metrics)
}

/// The pose worker that solves a frame's coarse pose: flow sends each coarse pose's
/// correspondences to that worker's own topic (`keys::pose_in`), so each is solved once without
/// a dispatcher (a restarted pose worker's lost share is redone by ingest, as with one pose
/// worker).
pub fn pose_worker_of(frame_id: u64, coarse_index: u32, workers: u32) -> u32 {
    let workers = u64::from(workers.max(1));
    // Consecutive coarse poses of a frame go to consecutive workers.
    ((frame_id.wrapping_mul(7) + u64::from(coarse_index)) % workers) as u32
}

/// Stage "pose" (one or more workers, each its share by [`pose_worker_of`] on its own topic):
/// correspondences of one coarse pose → refined pose hypothesis → verify.
pub fn run_pose(ctx: &NodeContext) -> Result<StageMetrics, NodeError> {
    let mut metrics = ctx.metrics("pose");
    let mut reporter = MetricsReporter::open(ctx.transport)?;
    let mut inbox = Inbox::open(ctx.transport, &keys::pose_in(ctx.worker_index), "pose")?;
    let mut verify = Outbox::open(ctx.transport, keys::VERIFY_IN)?;
    verify.wait_for_reader("verify", ctx.startup())?;
    let mut stage =
        PoseStage::new(ctx.config.registration.clone()).with_simulated_work(ctx.config.simulate);
    // Everything on this worker's topic is its share: flow sent it here.
    while !ctx.stopped() {
        let mut sent: Result<(), BusError> = Ok(());
        inbox.receive(POLL, &mut metrics, &mut |message, metrics| {
            let frame_id = message.header.frame_id;
            let Body::Correspondences(set) = message.body else {
                unexpected("pose", message.body.kind(), frame_id);
                return;
            };
            let started = Instant::now();
            let hypothesis = stage.process(&set);
            record_compute(metrics, started);
            sent = verify
                .send(
                    frame_id,
                    message.header.capture_time_ns,
                    Body::Hypothesis(hypothesis),
                    metrics,
                )
                .map(|_| ());
        })?;
        sent?;
        reporter.tick(&metrics, false);
    }
    reporter.tick(&metrics, true);
    Ok(metrics)
}

/// Verify's memory of each frame's change work (an accepted frame's change job, or the change
/// result of a frame without a pose) until the frame's change result is published (seen on
/// `changes`, or in the change journal). When fusion restarts, the change results it had
/// received but not yet published are gone with it, so verify issues the work of every frame
/// still without a published change result again (fusion keeps the first change result per
/// frame, across its restarts by the change journal); and work that no change worker holds any
/// more and whose result is still not published [`CHANGE_RESEND_AFTER`] later is issued again
/// (a fusion restart verify did not see, e.g. while verify itself restarted). A change worker's restart is the
/// dispatcher's redo; a restart of verify itself is ingest's ([`Recovery`]: a frame is finished
/// for ingest only once its change result is out too).
struct ChangeRecovery<'t> {
    dispatcher: Dispatcher<'t>,
    fusion: Outbox,
    changes: Inbox,
    metrics: Inbox,
    fusion_incarnation: Option<u64>,
    /// Encoded change work per frame: (is a job for the change workers, the message, since
    /// when it is out of the dispatcher's hands).
    pending: std::collections::BTreeMap<u64, (bool, std::sync::Arc<Vec<u8>>, Instant)>,
    /// Frames whose change result is published.
    published: std::collections::BTreeSet<u64>,
    journal: (std::path::PathBuf, String),
    journal_read: Option<Instant>,
    /// Change work issued again after a restart of fusion.
    reissued: u64,
}

impl<'t> ChangeRecovery<'t> {
    fn open(ctx: &NodeContext<'t>) -> Result<Self, NodeError> {
        let config = ctx.config;
        let dispatcher = Dispatcher::open(
            ctx.transport,
            keys::CHANGE_LINK,
            CHANGE_JOBS_QUEUED,
            Duration::from_secs_f64(config.timeouts.worker_silence_s),
        )?;
        let mut fusion = Outbox::open(ctx.transport, keys::FUSION_IN)?;
        fusion.wait_for_reader("fusion", ctx.startup())?;
        let mut recovery = Self {
            dispatcher,
            fusion,
            changes: Inbox::open(ctx.transport, keys::CHANGES, "verify")?,
            metrics: Inbox::open(ctx.transport, keys::METRICS, "verify")?,
            fusion_incarnation: None,
            pending: std::collections::BTreeMap::new(),
            published: std::collections::BTreeSet::new(),
            journal: (
                journal::path(config, journal::Kind::Change),
                journal::header(config, journal::Kind::Change),
            ),
            journal_read: None,
            reissued: 0,
        };
        recovery.read_journal()?;
        Ok(recovery)
    }

    fn read_journal(&mut self) -> Result<(), JournalError> {
        for frame_id in journal::read_published(&self.journal.0, &self.journal.1)? {
            self.on_published(frame_id);
        }
        self.journal_read = Some(Instant::now());
        Ok(())
    }

    fn on_published(&mut self, frame_id: u64) {
        self.pending.remove(&frame_id);
        self.published.insert(frame_id);
    }

    /// Issues a frame's change work (unless its change result is already published).
    fn issue(
        &mut self,
        work: ChangeWork,
        capture: u64,
        metrics: &mut StageMetrics,
    ) -> Result<(), BusError> {
        let (frame_id, is_job, body) = match work {
            ChangeWork::Job(frame_id, job) => (frame_id, true, Body::ChangeJob(*job)),
            ChangeWork::Result(result) => (result.frame_id, false, Body::ChangeResult(result)),
        };
        if self.published.contains(&frame_id) {
            tracing::debug!("verify: frame {frame_id} already has its published change result");
            return Ok(());
        }
        let bytes = std::sync::Arc::new(encode_to_vec(frame_id, capture, body)?);
        self.pending.insert(
            frame_id,
            (is_job, std::sync::Arc::clone(&bytes), Instant::now()),
        );
        self.send(frame_id, is_job, bytes, metrics)
    }

    fn send(
        &mut self,
        frame_id: u64,
        is_job: bool,
        bytes: std::sync::Arc<Vec<u8>>,
        metrics: &mut StageMetrics,
    ) -> Result<(), BusError> {
        if is_job {
            let key = JobKey {
                frame_id,
                coarse_index: 0,
            };
            self.dispatcher.push_shared(key, bytes);
            Ok(())
        } else {
            self.fusion.send_encoded(&bytes, metrics).map(|_| ())
        }
    }

    /// Takes the published change results and fusion's metrics; when fusion restarted, issues
    /// the work of every frame without a published change result again. Then hands out jobs.
    fn service(&mut self, metrics: &mut StageMetrics) -> Result<(), NodeError> {
        if self
            .journal_read
            .is_none_or(|at| at.elapsed() >= Duration::from_secs(1))
        {
            self.read_journal()?;
        }
        let mut scratch = StageMetrics::default();
        let mut published = Vec::new();
        while self
            .changes
            .receive(Duration::ZERO, &mut scratch, &mut |message, _| {
                if let Body::ChangeResult(result) = message.body {
                    published.push(result.frame_id);
                }
            })?
        {}
        for frame_id in published {
            self.on_published(frame_id);
        }
        let mut fusion_restarted = false;
        let incarnation = &mut self.fusion_incarnation;
        while self
            .metrics
            .receive(Duration::ZERO, &mut scratch, &mut |message, _| {
                if let Body::Metrics(m) = message.body {
                    if m.stage == "fusion" {
                        if incarnation.is_some_and(|previous| previous != m.incarnation) {
                            fusion_restarted = true;
                        }
                        *incarnation = Some(m.incarnation);
                    }
                }
            })?
        {}
        if fusion_restarted {
            tracing::warn!(
                "verify: the fusion stage restarted; issuing the change work of the {} frame(s) without a published change result again",
                self.pending.len()
            );
        }
        let now = Instant::now();
        let mut resend = Vec::new();
        for (frame_id, (is_job, bytes, since)) in &mut self.pending {
            if *is_job && self.dispatcher.holds(*frame_id) {
                *since = now;
            } else if fusion_restarted || now.duration_since(*since) >= CHANGE_RESEND_AFTER {
                *since = now;
                resend.push((*frame_id, *is_job, std::sync::Arc::clone(bytes)));
            }
        }
        if !fusion_restarted && !resend.is_empty() {
            tracing::warn!(
                "verify: {} frame(s) still without a published change result {:.0} s after their change work was done; issuing it again",
                resend.len(),
                CHANGE_RESEND_AFTER.as_secs_f64()
            );
        }
        for (frame_id, is_job, bytes) in resend {
            self.reissued += 1;
            self.send(frame_id, is_job, bytes, metrics)?;
        }
        self.dispatcher.pump(Duration::ZERO)?;
        Ok(())
    }
}

/// Stage "verify": gathers hypotheses and failures, emits one PoseResult per frame (bincode on
/// `results`, JSON on `results/json`), and the end of the stream once every frame has its result.
pub fn run_verify(ctx: &NodeContext, mesh: &Mesh) -> Result<StageMetrics, NodeError> {
    let config = ctx.config;
    let mut metrics = ctx.metrics("verify");
    let mut reporter = MetricsReporter::open(ctx.transport)?;
    let mut inbox = Inbox::open(ctx.transport, keys::VERIFY_IN, "verify")?;
    let mut results = Outbox::open(ctx.transport, keys::RESULTS)?;
    let mut results_json = Outbox::open(ctx.transport, keys::RESULTS_JSON)?;
    let mut stage = VerifyStage::new(
        mesh,
        Duration::from_secs_f64(config.timeouts.frame_timeout_s),
    )
    .with_simulated_work(config.simulate)
    .with_neighbour_poses(config.registration.neighbour_pose.clone());
    // Complete frames are decided on `verify_threads` threads beside this loop, one too: a
    // decision takes ~1 s, and a loop that decided in its own receive stopped reading its inbox
    // for that long, so the pose workers (then the flow workers) waited in their sends to it.
    let threads = config.workers.verify_threads.max(1);
    // With change detection: accepted frames' change jobs go to the change workers, the other
    // frames' change results (why there is none) and the end of the stream to fusion.
    let mut changes = if config.changes_enabled() {
        stage = stage.with_changes(config.stereo.neighbours, config.stereo.window_frames);
        Some(ChangeRecovery::open(ctx)?)
    } else {
        None
    };
    // The stereo views accepted before a restart are neighbours again (runtime::views).
    let mut views = changes.as_ref().map(|_| {
        let (store, restored) = ViewStore::open_and_restore(config, &mut stage);
        if restored > 0 {
            tracing::info!(
                "verify: {restored} stereo views of frames accepted before a restart restored"
            );
        }
        store
    });
    // The pose lenders accepted before a restart lend again (runtime::lenders).
    let mut lenders = config.registration.neighbour_pose.enabled.then(|| {
        let (store, restored) = LenderStore::open_and_restore(config, &mut stage);
        if restored > 0 {
            tracing::info!(
                "verify: {restored} pose lenders of frames accepted before a restart restored"
            );
        }
        store
    });
    let mut fusion_told_end: Option<Instant> = None;
    let mut capture_times: HashMap<u64, u64> = HashMap::new();
    let mut stream_ended: Option<Instant> = None;
    // Results published before a restart of this stage are not published again; those the
    // collector has not acknowledged are sent again as they were (runtime::ack).
    let mut results_ack = Resender::open(
        ctx.transport,
        keys::RESULTS_ACK,
        "verify",
        Duration::from_secs_f64(config.timeouts.resend_after_s),
    )?;
    let (mut journal, journaled, mut health) = open_journal(config, journal::Kind::Pose, "verify");
    let mut acks = AckJournal::open(config, journal::Kind::PoseAcked, "verify");
    let mut published: std::collections::BTreeSet<u64> = journaled.keys().copied().collect();
    stage.published_before_restart(published.iter().copied());
    restore_unacked(&mut results_ack, &journaled, &acks, journal.path());
    // The queries and hypotheses received before a restart, of frames without a published
    // result, come back as if they had just arrived (runtime::received).
    let (mut received, restored) = ReceivedStore::open_and_restore(config, &mut stage, &published);
    if restored > 0 {
        tracing::info!(
            "verify: the received messages of {restored} frames without a published result restored"
        );
    }
    // Complete frames are decided by a pool of threads (each with its own refinement
    // workspace) and concluded here, one result per frame as before.
    let (ready_tx, ready_rx) = std::sync::mpsc::channel::<ReadyFrame>();
    let ready_rx = std::sync::Mutex::new(ready_rx);
    let (decided_tx, decided_rx) = std::sync::mpsc::channel::<DecidedFrame>();
    std::thread::scope(|scope| {
        let ready_tx = ready_tx;
        for _ in 0..threads {
            let ready_rx = &ready_rx;
            let decided_tx = decided_tx.clone();
            let registration = &config.registration;
            scope.spawn(move || {
                let mut workspace = VerifyWorkspace::default();
                loop {
                    let next = match ready_rx.lock() {
                        Ok(queue) => queue.recv(),
                        Err(_) => return,
                    };
                    let Ok(ready) = next else { return };
                    if decided_tx
                        .send(ready.decide(mesh, registration, &mut workspace))
                        .is_err()
                    {
                        return;
                    }
                }
            });
        }
        drop(decided_tx);
        let mut waiting_for_pool: std::collections::BTreeMap<u64, ReadyFrame> =
            std::collections::BTreeMap::new();
        let mut in_pool = 0usize;
        while !ctx.stopped() {
            let mut produced = Vec::new();
            // Everything waiting is taken before the bookkeeping below (results, acks, change
            // work, metrics), which would otherwise run once per message: with many pose workers
            // the hypotheses arrive faster than one message per pass drains them, and pose
            // workers (then flow workers) wait on this inbox.
            let mut wait = POLL;
            let mut taken = 0;
            while taken < VERIFY_DRAIN_MAX
                && inbox.receive(wait, &mut metrics, &mut |message, metrics| {
                    let frame_id = message.header.frame_id;
                    let started = Instant::now();
                    match message.body {
                        Body::Hypothesis(hypothesis) => {
                            capture_times
                                .entry(frame_id)
                                .or_insert(message.header.capture_time_ns);
                            let takes = stage.takes_messages_of(frame_id);
                            stage.on_hypothesis(frame_id, &hypothesis);
                            if takes {
                                received.keep(frame_id, Body::Hypothesis(hypothesis));
                            }
                        }
                        Body::FrameFailed(failure) => {
                            capture_times
                                .entry(frame_id)
                                .or_insert(message.header.capture_time_ns);
                            produced.extend(stage.on_failure(frame_id, &failure));
                        }
                        Body::FrameQuery(query) => {
                            capture_times
                                .entry(frame_id)
                                .or_insert(message.header.capture_time_ns);
                            let takes = stage.takes_messages_of(frame_id);
                            stage.on_query(frame_id, &query);
                            if takes {
                                received.keep(frame_id, Body::FrameQuery(query));
                            }
                        }
                        Body::StreamEnd(end) => {
                            stage.on_stream_end(end.frame_count, &end.finished_frames)
                        }
                        other => unexpected("verify", other.kind(), frame_id),
                    }
                    record_compute(metrics, started);
                })?
            {
                wait = Duration::ZERO;
                taken += 1;
            }
            produced.extend(stage.expire(Instant::now()));
            // The pool takes the lowest frame first, one more than it has threads: a frame's
            // step "neighbour" (its result) comes before the own decisions of frames after its
            // look-ahead. In arrival order, a restarted verify that got back a few dozen frames
            // at once decided them all before publishing the first, and one killed sooner
            // published nothing (runtime::received).
            for ready in stage.take_ready() {
                waiting_for_pool.insert(ready.frame_id(), ready);
            }
            while in_pool <= threads as usize {
                let Some((_, ready)) = waiting_for_pool.pop_first() else {
                    break;
                };
                // The pool's threads end only with this loop.
                let _ = ready_tx.send(ready);
                in_pool += 1;
            }
            while let Ok(decided) = decided_rx.try_recv() {
                in_pool = in_pool.saturating_sub(1);
                produced.extend(stage.conclude(decided));
            }
            // Durable before the results go out: a frame with both results is not sent again.
            if let Some(views) = &mut views {
                views.sync(&stage);
            }
            if let Some(lenders) = &mut lenders {
                lenders.sync(&stage);
            }
            let mut change_captures = Vec::new();
            for mut result in produced {
                let capture = capture_times.remove(&result.frame_id).unwrap_or(0);
                change_captures.push((result.frame_id, capture));
                if published.contains(&result.frame_id) {
                    tracing::info!(
                    "verify: frame {} already has its published result (before a restart); not publishing it again",
                    result.frame_id
                );
                    stage.late_messages += 1;
                    continue;
                }
                if capture > 0 {
                    result.times.latency_ms = unix_time_ns().saturating_sub(capture) as f64 / 1e6;
                }
                let header = crate::msg::Header {
                    frame_id: result.frame_id,
                    sequence: 0,
                    capture_time_ns: capture,
                    sent_time_ns: unix_time_ns(),
                };
                let frame_id = result.frame_id;
                // Encoded once: the bytes journaled, published and (until acknowledged) sent again.
                let mut json = pose_result_json(&header, &result);
                let mut bytes = encode_to_vec(frame_id, capture, Body::PoseResult(result.clone()))?;
                // Written ahead (runtime::journal): a result the station cannot record is not
                // given out as it is; the frame's one result is failed, naming the journal and why.
                let written = journal.append_with(frame_id, &journal::to_hex(&bytes));
                health.report(frame_id, &written);
                if let Err(error) = written {
                    let failed = stage.withdraw(result, &format!("verify: {error}"));
                    json = pose_result_json(&header, &failed);
                    bytes = encode_to_vec(frame_id, capture, Body::PoseResult(failed))?;
                    // Best effort (the disk may have room for a shorter line): journaled, a
                    // restart knows the frame has its result.
                    let _ = journal.append_with(frame_id, &journal::to_hex(&bytes));
                }
                acks.take(&mut results_ack, &mut metrics)?;
                results.send_encoded(&bytes, &mut metrics)?;
                results_json.send_raw(json.as_bytes())?;
                published.insert(frame_id);
                received.forget(frame_id);
                let first_after = results_ack.first_after();
                results_ack.track(frame_id, bytes, json, first_after);
            }
            acks.take(&mut results_ack, &mut metrics)?;
            for (frame_id, bytes, json) in results_ack.due(Instant::now()) {
                tracing::info!(
                "verify: the result of frame {frame_id} is not acknowledged by the collector; sending it again"
            );
                results.send_encoded(&bytes, &mut metrics)?;
                results_json.send_raw(json.as_bytes())?;
            }
            if let Some(recovery) = &mut changes {
                stage.release_stereo_jobs();
                // Also for a frame published before a restart of verify (ingest sends it again while
                // its change result is not out).
                for work in stage.change_work.drain(..) {
                    let frame_id = match &work {
                        ChangeWork::Job(frame_id, _) => *frame_id,
                        ChangeWork::Result(result) => result.frame_id,
                    };
                    let capture = change_captures
                        .iter()
                        .find(|(id, _)| *id == frame_id)
                        .map_or(0, |(_, capture)| *capture);
                    recovery.issue(work, capture, &mut metrics)?;
                }
                recovery.service(&mut metrics)?;
                if let Some(frame_count) = stage.stream_complete() {
                    // Repeated now and then: fusion takes the first, and a restarted one learns it.
                    if fusion_told_end.is_none_or(|at| at.elapsed() >= Duration::from_secs(2)) {
                        recovery.fusion.send(
                            0,
                            0,
                            Body::StreamEnd(StreamEnd {
                                frame_count,
                                finished_frames: Vec::new(),
                            }),
                            &mut metrics,
                        )?;
                        fusion_told_end = Some(Instant::now());
                    }
                }
            }
            metrics.redispatched = changes.as_ref().map_or(0, |recovery| {
                recovery.dispatcher.metrics.redispatched + recovery.reissued
            }) + results_ack.resent;
            // The end of the stream is repeated now and then (a lost one would leave the
            // collector waiting; a repeat is harmless).
            if stream_ended.is_none_or(|at| at.elapsed() >= END_REPEAT) {
                if let Some(frame_count) = stage.stream_complete() {
                    if stream_ended.is_none() {
                        tracing::info!("verify: all {frame_count} frames have their result");
                    }
                    stream_ended = Some(Instant::now());
                    results.send(
                        0,
                        0,
                        Body::StreamEnd(StreamEnd {
                            frame_count,
                            finished_frames: Vec::new(),
                        }),
                        &mut metrics,
                    )?;
                }
            }
            metrics.max_queue_depth = metrics.max_queue_depth.max(stage.pending_frames() as u64);
            reporter.tick(&metrics, false);
        }
        // The acknowledgements that arrived while the last pass ran are journaled too (a
        // restart would otherwise send those results again); best effort while stopping.
        if let Err(error) = acks.take(&mut results_ack, &mut metrics) {
            tracing::debug!("verify: the last acknowledgements: {error}");
        }
        // The change recovery's subscriptions (metrics, changes) go first: the other stages' last
        // metrics must not wait on a queue this stage no longer reads.
        drop(changes);
        reporter.tick(&metrics, true);
        Ok(metrics)
    })
}

/// Stage "change" (N workers): one accepted frame's change job at a time, its change result
/// with the frame's sight (a ChangeSight: the depths fusion's free-space test reads) to fusion.
pub fn run_change(ctx: &NodeContext, mesh: &Mesh) -> Result<StageMetrics, NodeError> {
    let mut fusion = Outbox::open(ctx.transport, keys::FUSION_IN)?;
    fusion.wait_for_reader("fusion", ctx.startup())?;
    let stereo = StereoDepthSettings {
        neighbours: ctx.config.stereo.neighbours,
        sweep: ctx.config.stereo.sweep,
        disparity_sigma_px: ctx.config.stereo.disparity_sigma_px,
    };
    let mut stage = ChangeStage::new(mesh, ctx.config.change, stereo, ctx.worker_index);
    serve_jobs(ctx, "change", keys::CHANGE_LINK, &mut |message, metrics| {
        let frame_id = message.header.frame_id;
        let Body::ChangeJob(job) = message.body else {
            unexpected("change", message.body.kind(), frame_id);
            return None;
        };
        let started = Instant::now();
        let sight = stage.process(frame_id, &job);
        record_compute(metrics, started);
        Some(
            fusion
                .send(
                    frame_id,
                    message.header.capture_time_ns,
                    Body::ChangeSight(sight),
                    metrics,
                )
                .map(|_| JobKey {
                    frame_id,
                    coarse_index: 0,
                }),
        )
    })
}

/// The acknowledgement journal of verify or fusion (`journal::Kind::PoseAcked`,
/// `journal::Kind::ChangeAcked`): each frame whose result the collector acknowledged, so that a
/// restart sends only the others again.
struct AckJournal {
    journal: Journal,
    acked: std::collections::BTreeSet<u64>,
    stage: &'static str,
    failed: bool,
}

impl AckJournal {
    /// Never fails: a journal that cannot be opened is tried again at each append.
    fn open(config: &PipelineConfig, kind: journal::Kind, stage: &'static str) -> Self {
        let path = journal::path(config, kind);
        let (journal, acked, error) = Journal::open_or_retry(&path, &journal::header(config, kind));
        if let Some(error) = &error {
            tracing::error!("{stage}: {error}; a restart sends acknowledged results again");
        }
        Self {
            journal,
            acked: acked.into_keys().collect(),
            stage,
            failed: error.is_some(),
        }
    }

    /// Takes the acks that arrived at `resender` and journals them (a failure to write is
    /// reported once: a restart then only sends some results again).
    fn take(
        &mut self,
        resender: &mut Resender,
        metrics: &mut StageMetrics,
    ) -> Result<(), BusError> {
        for frame_id in resender.take_acks(metrics)? {
            self.acked.insert(frame_id);
            if let Err(error) = self.journal.append(frame_id) {
                if !self.failed {
                    tracing::error!(
                        "{}: {error}; a restart sends acknowledged results again",
                        self.stage
                    );
                    self.failed = true;
                }
            }
        }
        Ok(())
    }
}

/// Whether a stage's results journal is being written, for its log: the first failure is an
/// error, each further frame a warning, a recovery news.
struct JournalHealth {
    stage: &'static str,
    failing: bool,
}

impl JournalHealth {
    fn report(&mut self, frame_id: u64, written: &Result<(), JournalError>) {
        match written {
            Ok(()) if self.failing => {
                tracing::info!("{}: the results journal is written again", self.stage);
                self.failing = false;
            }
            Ok(()) => {}
            Err(error) if !self.failing => {
                tracing::error!(
                    "{}: {error}; frame {frame_id} and every frame until it can be written get a failed result saying so",
                    self.stage
                );
                self.failing = true;
            }
            Err(error) => tracing::warn!("{}: frame {frame_id}: {error}", self.stage),
        }
    }
}

/// A stage's results journal (pose: verify; change: fusion) and what it lists. A journal that
/// cannot be opened stops nothing (a stage that failed here would only be restarted into the
/// same failure): the stage starts, and each result fails with the reason until it can be written.
fn open_journal(
    config: &PipelineConfig,
    kind: journal::Kind,
    stage: &'static str,
) -> (
    Journal,
    std::collections::BTreeMap<u64, String>,
    JournalHealth,
) {
    let (journal, journaled, error) =
        Journal::open_or_retry(&journal::path(config, kind), &journal::header(config, kind));
    if let Some(error) = &error {
        tracing::error!(
            "{stage}: {error}; every frame gets a failed result saying so until it can be written"
        );
    }
    let health = JournalHealth {
        stage,
        failing: error.is_some(),
    };
    (journal, journaled, health)
}

/// A journaled result message (PoseResult or ChangeResult of `frame_id`) back: its bytes, sent
/// again as they are, and its JSON twin.
fn journaled_result(frame_id: u64, payload: &str) -> Result<(Vec<u8>, String), String> {
    let bytes = journal::from_hex(payload).ok_or("not hex")?;
    let message = crate::msg::decode(&bytes).map_err(|error| error.to_string())?;
    let json = match &message.body {
        Body::PoseResult(result) if result.frame_id == frame_id => {
            pose_result_json(&message.header, result)
        }
        Body::ChangeResult(result) if result.frame_id == frame_id => {
            change_result_json(&message.header, result)
        }
        other => {
            return Err(format!(
                "it holds a {:?} message of frame {}",
                other.kind(),
                message.header.frame_id
            ))
        }
    };
    drop(message);
    Ok((bytes, json))
}

/// After a restart: the journaled results the collector has not acknowledged go back into
/// `resender`, due at once (the collector takes a repeat as re-delivery).
fn restore_unacked(
    resender: &mut Resender,
    journaled: &std::collections::BTreeMap<u64, String>,
    acks: &AckJournal,
    path: &std::path::Path,
) {
    if journaled.is_empty() {
        return;
    }
    let mut restored = 0usize;
    for (frame_id, payload) in journaled {
        if acks.acked.contains(frame_id) {
            continue;
        }
        match journaled_result(*frame_id, payload) {
            Ok((bytes, json)) => {
                resender.restore(*frame_id, bytes, json);
                restored += 1;
            }
            Err(why) => tracing::error!(
                "{}: {}: the line of frame {frame_id} is damaged ({why}); its result cannot be sent again",
                acks.stage,
                path.display()
            ),
        }
    }
    tracing::info!(
        "{}: {} frames already have their published result ({}); none is published again, the {restored} not acknowledged by the collector are sent again",
        acks.stage,
        journaled.len(),
        path.display()
    );
}

/// A change result back from its change journal line.
fn restore_change_result(frame_id: u64, payload: &str) -> Result<crate::msg::ChangeResult, String> {
    let bytes = journal::from_hex(payload).ok_or("not hex")?;
    let message = crate::msg::decode(&bytes).map_err(|error| error.to_string())?;
    match message.body {
        Body::ChangeResult(result) if result.frame_id == frame_id => Ok(result),
        Body::ChangeResult(result) => Err(format!("it holds frame {}", result.frame_id)),
        other => Err(format!("it holds a {:?} message", other.kind())),
    }
}

/// Stage "fusion": publishes each frame's first change result (bincode on `changes`, JSON on
/// `changes/json`), the fused change set now and then while frames arrive, and, once every
/// frame has its change result, the final set (`changeset/json` too) and the end of the change
/// stream.
pub fn run_fusion(ctx: &NodeContext) -> Result<StageMetrics, NodeError> {
    let mut metrics = ctx.metrics("fusion");
    let mut reporter = MetricsReporter::open(ctx.transport)?;
    let mut inbox = Inbox::open(ctx.transport, keys::FUSION_IN, "fusion")?;
    let mut changes = Outbox::open(ctx.transport, keys::CHANGES)?;
    let mut changes_json = Outbox::open(ctx.transport, keys::CHANGES_JSON)?;
    let mut set_json = Outbox::open(ctx.transport, keys::CHANGE_SET_JSON)?;
    // Every frame's footprint, at most fusion.max_sights_in_memory_mb of their maps.
    let mut stage = FusionStage::with_sights(ctx.config.fusion.merge(), sights::kept(ctx.config));
    // Change results published before a restart of this stage: fused, not published again.
    let (mut journal, journaled, mut health) =
        open_journal(ctx.config, journal::Kind::Change, "fusion");
    let mut changes_ack = Resender::open(
        ctx.transport,
        keys::CHANGES_ACK,
        "fusion",
        Duration::from_secs_f64(ctx.config.timeouts.resend_after_s),
    )?;
    let mut acks = AckJournal::open(ctx.config, journal::Kind::ChangeAcked, "fusion");
    restore_unacked(&mut changes_ack, &journaled, &acks, journal.path());
    let restored = journaled.len();
    for (frame_id, payload) in journaled {
        match restore_change_result(frame_id, &payload) {
            Ok(result) => stage.restore(result),
            Err(why) => tracing::error!(
                "fusion: {}: the line of frame {frame_id} is damaged ({why}); that frame's change result is left out of the change set (delete the file to start the run over)",
                journal.path().display()
            ),
        }
    }
    // What the frames published before the restart saw, for the free-space test (on disk, so
    // held in memory only within the bound).
    let mut sights = SightStore::open_and_restore(ctx.config, &mut |frame_id, seen| {
        stage.restore_sight(frame_id, seen)
    });
    if restored > 0 {
        tracing::info!(
            "fusion: {restored} change results restored from the change journal, {} of them with a sight",
            stage.sight_memory().frames
        );
    }
    // When the final change set and the end of the change stream were last sent (repeated
    // now and then: a lost one would leave the collector waiting).
    let mut completed: Option<Instant> = None;
    // Results since the last published set, and when it was published.
    let mut unpublished = 0usize;
    let mut last_set = Instant::now();
    while !ctx.stopped() {
        let mut sent: Result<(), BusError> = Ok(());
        inbox.receive(POLL, &mut metrics, &mut |message, metrics| {
            let frame_id = message.header.frame_id;
            let capture = message.header.capture_time_ns;
            let started = Instant::now();
            // A change worker's result comes with its frame's sight (kept on disk before the
            // result is journaled); a frame without a pose has verify's result alone.
            let first = match message.body {
                Body::ChangeResult(result) => stage.on_result(result, None).cloned(),
                Body::ChangeSight(sight) => {
                    let seen = seen_frame(&sight).unwrap_or_else(|why| {
                        tracing::warn!(
                            "fusion: frame {frame_id}: {why}; it does not vote in the free-space test"
                        );
                        None
                    });
                    let has_sight = seen.is_some();
                    let first = stage.on_result(sight.meta.result.clone(), seen).cloned();
                    // On disk, the sight may leave memory (read back when it is needed).
                    if first.is_some() && has_sight && sights.write(frame_id, sight) {
                        stage.sight_on_disk(frame_id);
                    }
                    first
                }
                Body::StreamEnd(end) => {
                    stage.on_stream_end(end.frame_count);
                    None
                }
                other => {
                    unexpected("fusion", other.kind(), frame_id);
                    None
                }
            };
            if let Some(result) = first {
                let header = Header {
                    frame_id,
                    sequence: 0,
                    capture_time_ns: capture,
                    sent_time_ns: unix_time_ns(),
                };
                if sent.is_ok() {
                    // Encoded once: the bytes journaled, published and (until
                    // acknowledged) sent again; written ahead, and a change result the
                    // station cannot record is given out failed, naming the journal.
                    sent = encode_to_vec(
                        frame_id,
                        capture,
                        Body::ChangeResult(result.clone()),
                    )
                    .and_then(|bytes| {
                        let written =
                            journal.append_with(frame_id, &journal::to_hex(&bytes));
                        health.report(frame_id, &written);
                        let (bytes, json) = match written {
                            Ok(()) => (bytes, change_result_json(&header, &result)),
                            Err(error) => {
                                let failed = stage
                                    .withdraw(frame_id, &format!("fusion: {error}"))
                                    .cloned()
                                    .unwrap_or(result);
                                let bytes = encode_to_vec(
                                    frame_id,
                                    capture,
                                    Body::ChangeResult(failed.clone()),
                                )?;
                                // Best effort, as in verify.
                                let _ =
                                    journal.append_with(frame_id, &journal::to_hex(&bytes));
                                (bytes, change_result_json(&header, &failed))
                            }
                        };
                        acks.take(&mut changes_ack, metrics)?;
                        changes.send_encoded(&bytes, metrics)?;
                        changes_json.send_raw(json.as_bytes())?;
                        let first_after = changes_ack.first_after();
                        changes_ack.track(frame_id, bytes, json, first_after);
                        Ok(())
                    });
                }
                unpublished += 1;
            }
            record_compute(metrics, started);
        })?;
        sent?;
        acks.take(&mut changes_ack, &mut metrics)?;
        for (frame_id, bytes, json) in changes_ack.due(Instant::now()) {
            tracing::info!(
                "fusion: the change result of frame {frame_id} is not acknowledged by the collector; sending it again"
            );
            changes.send_encoded(&bytes, &mut metrics)?;
            changes_json.send_raw(json.as_bytes())?;
        }
        metrics.redispatched = changes_ack.resent;
        let complete = stage.is_complete() && completed.is_none_or(|at| at.elapsed() >= END_REPEAT);
        if complete || (unpublished > 0 && last_set.elapsed() >= Duration::from_secs(1)) {
            let started = Instant::now();
            let set = stage.change_set();
            record_compute(&mut metrics, started);
            let header = Header {
                frame_id: 0,
                sequence: 0,
                capture_time_ns: 0,
                sent_time_ns: unix_time_ns(),
            };
            let json = change_set_json(&header, &set);
            if complete && completed.is_none() {
                let memory = stage.sight_memory();
                tracing::info!(
                    "fusion: all {} frames have their change result: {} objects ({} confirmed); sights: {} frames, {} held, {:.1} MB held, peak {:.1} MB (bound {:.0} MB), {} read back, {} lost",
                    stage.result_count(),
                    set.objects.len(),
                    set.objects.iter().filter(|o| o.confirmed).count(),
                    memory.frames,
                    memory.frames_held,
                    memory.held_bytes as f64 / 1e6,
                    memory.peak_bytes as f64 / 1e6,
                    memory.max_bytes.map_or(f64::INFINITY, |b| b as f64 / 1e6),
                    memory.loads,
                    memory.lost.len()
                );
            }
            changes.send(0, 0, Body::ChangeSet(set), &mut metrics)?;
            set_json.send_raw(json.as_bytes())?;
            unpublished = 0;
            last_set = Instant::now();
            if complete {
                completed = Some(Instant::now());
                changes.send(
                    0,
                    0,
                    Body::StreamEnd(StreamEnd {
                        frame_count: stage.result_count() as u64,
                        finished_frames: Vec::new(),
                    }),
                    &mut metrics,
                )?;
            }
        }
        reporter.tick(&metrics, false);
    }
    // The acknowledgements that arrived while the last pass ran are journaled too (best effort
    // while stopping).
    if let Err(error) = acks.take(&mut changes_ack, &mut metrics) {
        tracing::debug!("fusion: the last acknowledgements: {error}");
    }
    reporter.tick(&metrics, true);
    Ok(metrics)
}
