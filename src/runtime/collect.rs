//! The end of a pipeline as its operator sees it: a results subscriber that checks every frame
//! gets exactly one PoseResult (and hands on only the first of each frame; an identical repeat
//! is a re-delivery, counted apart, a different second result a duplicate), acknowledges each
//! result it holds to the publisher (`runtime::ack`, the station's collector only), and the summary (frames/s, latency percentiles, per-stage
//! compute, transport bytes and time, drops, rejections, redone jobs, the work split).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::msg::{same_body, Body, ChangeResult, ChangeSet, Header, PoseResult, StageMetrics};
use crate::transport::{keys, Transport};

use super::ack::{Acker, RESEND_MAX};

/// How long the collector waits after the end of the stream for results still missing: two of
/// the longest waits between re-sends.
const END_GRACE: Duration = Duration::from_secs(2 * RESEND_MAX.as_secs());
use super::bus::{BusError, Inbox};

/// Results as they arrived, checked for exactly-once delivery.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Collected {
    /// The first result of each frame, in arrival order.
    pub results: Vec<PoseResult>,
    /// Frames that received a second, different result (must stay empty); the repeats are not
    /// in `results`.
    pub duplicates: Vec<u64>,
    /// Results that arrived again identical to the first of their frame (sent again because
    /// their ack was late or lost; harmless).
    pub redelivered: u64,
    /// Frame count announced by the end of the stream.
    pub frame_count: Option<u64>,
    pub wall_s: f64,
    /// Latest metrics of every stage worker, by (stage, worker).
    pub metrics: BTreeMap<(String, u32), StageMetrics>,
    pub rejected_messages: u64,
    /// With change detection: the first change result of each frame, in arrival order.
    pub change_results: Vec<ChangeResult>,
    /// Frames that received a second, different change result (must stay empty).
    pub change_duplicates: Vec<u64>,
    /// Change results that arrived again identical to the first of their frame.
    pub change_redelivered: u64,
    /// The final (complete) change set, once the change stream ended.
    pub change_set: Option<ChangeSet>,
}

/// What the collector hands on as it arrives.
#[derive(Clone, Copy, Debug)]
pub enum Delivered<'a> {
    /// A frame's (first) PoseResult.
    Pose(&'a Header, &'a PoseResult),
    /// A frame's (first) ChangeResult.
    Change(&'a ChangeResult),
    /// The final change set.
    ChangeSet(&'a ChangeSet),
}

impl Collected {
    /// Frame ids without a result (must be empty after a complete stream).
    pub fn missing(&self) -> Vec<u64> {
        let Some(count) = self.frame_count else {
            return Vec::new();
        };
        let seen: std::collections::BTreeSet<u64> =
            self.results.iter().map(|r| r.frame_id).collect();
        (0..count).filter(|id| !seen.contains(id)).collect()
    }

    /// Results per second of the run.
    pub fn frames_per_s(&self) -> f64 {
        self.results.len() as f64 / self.wall_s.max(1e-9)
    }

    /// Capture → result latency of every result that has one, ms.
    pub fn latencies_ms(&self) -> Vec<f64> {
        self.results
            .iter()
            .filter(|r| r.times.latency_ms > 0.0)
            .map(|r| r.times.latency_ms)
            .collect()
    }

    /// Encode, send and decode time of every stage over their compute time, percent.
    pub fn transport_share_percent(&self) -> f64 {
        let compute_ms: f64 = self.metrics.values().map(|m| m.compute_ms).sum();
        let transport_ms: f64 = self.metrics.values().map(|m| m.send_ms + m.decode_ms).sum();
        100.0 * transport_ms / compute_ms.max(1e-9)
    }

    /// Flow jobs done per flow worker (the work split).
    pub fn flow_split(&self) -> BTreeMap<u32, usize> {
        let mut split = BTreeMap::new();
        for worker in self.results.iter().flat_map(|r| r.flow_workers.iter()) {
            *split.entry(*worker).or_default() += 1;
        }
        split
    }

    /// Frame ids without a change result (must be empty after a complete stream with change
    /// detection).
    pub fn missing_changes(&self) -> Vec<u64> {
        let Some(count) = self.frame_count else {
            return Vec::new();
        };
        let seen: std::collections::BTreeSet<u64> =
            self.change_results.iter().map(|r| r.frame_id).collect();
        (0..count).filter(|id| !seen.contains(id)).collect()
    }

    /// Change results in frame order.
    pub fn changes_by_frame(&self) -> Vec<&ChangeResult> {
        let mut results: Vec<&ChangeResult> = self.change_results.iter().collect();
        results.sort_by_key(|r| r.frame_id);
        results
    }

    pub fn accepted(&self) -> usize {
        self.results.iter().filter(|r| r.accepted).count()
    }

    /// Results in frame order.
    pub fn by_frame(&self) -> Vec<&PoseResult> {
        let mut results: Vec<&PoseResult> = self.results.iter().collect();
        results.sort_by_key(|r| r.frame_id);
        results
    }
}

/// A subscriber to the results (and change results) and metrics of a pipeline, opened before
/// the stages start.
pub struct Collector {
    results: Inbox,
    metrics: Inbox,
    /// With change detection: the change stream (change results, change sets, its end).
    changes: Option<Inbox>,
    /// The acks of results and change results, when this collector is the station's.
    results_ack: Option<Acker>,
    changes_ack: Option<Acker>,
}

impl Collector {
    /// `changes`: also collect the change stream (the pipeline runs change detection), and
    /// wait for its end as well. `ack`: acknowledge each result held (the station's collector,
    /// of `launch` and `run`; one per pipeline: verify and fusion send a result again until
    /// some collector acknowledges it).
    pub fn open(transport: &dyn Transport, changes: bool, ack: bool) -> Result<Self, BusError> {
        Ok(Self {
            results_ack: if ack {
                Some(Acker::open(transport, keys::RESULTS_ACK)?)
            } else {
                None
            },
            changes_ack: if ack && changes {
                Some(Acker::open(transport, keys::CHANGES_ACK)?)
            } else {
                None
            },
            results: Inbox::open(transport, keys::RESULTS, "collector")?,
            metrics: Inbox::open(transport, keys::METRICS, "collector")?,
            changes: if changes {
                Some(Inbox::open(transport, keys::CHANGES, "collector")?)
            } else {
                None
            },
        })
    }

    /// Receives until the end of the stream (and of the change stream, when collecting it) or
    /// `deadline`, calling `on_result` for each result. `keep_going` is polled; returning false
    /// ends the wait early (e.g. all stages died).
    pub fn collect(
        &mut self,
        deadline: Duration,
        on_result: &mut dyn FnMut(Delivered<'_>),
        keep_going: &mut dyn FnMut() -> bool,
    ) -> Result<Collected, BusError> {
        let started = Instant::now();
        let mut collected = Collected::default();
        // Where each frame's first result is in `collected` (to tell a re-delivery).
        let mut seen: BTreeMap<u64, usize> = BTreeMap::new();
        let mut seen_changes: BTreeMap<u64, usize> = BTreeMap::new();
        let mut changes_ended = self.changes.is_none();
        let mut scratch = StageMetrics::default();
        // The end of the stream says every frame's result was published, not that each arrived:
        // one lost in flight is re-sent (runtime::ack) up to `RESEND_MAX` apart, so a frame still
        // missing at the end is waited for a while longer.
        let mut ended_at: Option<Instant> = None;
        let collecting_changes = self.changes.is_some();
        let complete =
            |collected: &Collected, changes_ended: bool, ended_at: &mut Option<Instant>| {
                if collected.frame_count.is_none() || !changes_ended {
                    return false;
                }
                let ended = *ended_at.get_or_insert_with(Instant::now);
                let all_in = collected.missing().is_empty()
                    && (!collecting_changes || collected.missing_changes().is_empty());
                all_in || ended.elapsed() >= END_GRACE
            };
        while !complete(&collected, changes_ended, &mut ended_at)
            && started.elapsed() < deadline
            && keep_going()
        {
            let results_ack = &mut self.results_ack;
            self.results.receive(
                Duration::from_millis(50),
                &mut scratch,
                &mut |message, _| match message.body {
                    // Idempotent by frame id: a second result for a frame is counted (the
                    // exactly-once check; an identical one as re-delivery) but neither handed on
                    // nor kept.
                    Body::PoseResult(result) => {
                        let frame_id = result.frame_id;
                        match seen.get(&frame_id) {
                            None => {
                                seen.insert(frame_id, collected.results.len());
                                on_result(Delivered::Pose(&message.header, &result));
                                collected.results.push(result);
                            }
                            Some(&first) if same_body(&collected.results[first], &result) => {
                                tracing::debug!("frame {frame_id}: its result arrived again (re-delivery)");
                                collected.redelivered += 1;
                            }
                            Some(_) => {
                                tracing::warn!(
                                    "frame {frame_id} '{}': a second, different result arrived; ignored",
                                    result.name
                                );
                                collected.duplicates.push(frame_id);
                            }
                        }
                        if let Some(acker) = results_ack {
                            acker.hold(frame_id);
                        }
                    }
                    Body::StreamEnd(end) => collected.frame_count = Some(end.frame_count),
                    _ => {}
                },
            )?;
            // After the results: a frame's change result is printed after its pose.
            if let Some(changes) = &mut self.changes {
                let changes_ack = &mut self.changes_ack;
                while changes.receive(
                    Duration::ZERO,
                    &mut scratch,
                    &mut |message, _| match message.body {
                        Body::ChangeResult(result) => {
                            let frame_id = result.frame_id;
                            match seen_changes.get(&frame_id) {
                                None => {
                                    seen_changes.insert(frame_id, collected.change_results.len());
                                    on_result(Delivered::Change(&result));
                                    collected.change_results.push(result);
                                }
                                Some(&first)
                                    if same_body(&collected.change_results[first], &result) =>
                                {
                                    collected.change_redelivered += 1;
                                }
                                Some(_) => {
                                    tracing::warn!(
                                        "frame {frame_id} '{}': a second, different change result arrived; ignored",
                                        result.name
                                    );
                                    collected.change_duplicates.push(frame_id);
                                }
                            }
                            if let Some(acker) = changes_ack {
                                acker.hold(frame_id);
                            }
                        }
                        // The first final set is handed on (fusion repeats it now and then).
                        Body::ChangeSet(set) if set.complete && collected.change_set.is_none() => {
                            on_result(Delivered::ChangeSet(&set));
                            collected.change_set = Some(set);
                        }
                        Body::StreamEnd(_) => changes_ended = true,
                        _ => {}
                    },
                )? {}
            }
            for acker in [&mut self.results_ack, &mut self.changes_ack]
                .into_iter()
                .flatten()
            {
                acker.flush(false)?;
            }
            self.drain_metrics(&mut collected)?;
        }
        for acker in [&mut self.results_ack, &mut self.changes_ack]
            .into_iter()
            .flatten()
        {
            acker.flush(true)?;
        }
        collected.wall_s = started.elapsed().as_secs_f64();
        collected.rejected_messages = scratch.rejected;
        Ok(collected)
    }

    /// Takes the metrics that have arrived (stages send theirs once a second and when stopping).
    pub fn drain_metrics(&mut self, collected: &mut Collected) -> Result<(), BusError> {
        let mut scratch = StageMetrics::default();
        while self
            .metrics
            .receive(Duration::ZERO, &mut scratch, &mut |message, _| {
                if let Body::Metrics(metrics) = message.body {
                    collected
                        .metrics
                        .insert((metrics.stage.clone(), metrics.worker_index), metrics);
                }
            })?
        {}
        Ok(())
    }
}

/// Value at quantile `q` (0..1) of `values` (nearest rank); NaN when empty.
pub fn percentile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}

/// The operator's summary of a run, as text.
pub fn summary(collected: &Collected, backend: &str) -> String {
    use std::fmt::Write;
    let mut text = String::new();
    let frames = collected.results.len();
    let accepted = collected.accepted();
    let dropped = collected
        .results
        .iter()
        .filter(|r| r.failure.as_deref().is_some_and(|f| f.contains("dropped")))
        .count();
    let latencies = collected.latencies_ms();
    let _ = writeln!(
        text,
        "{frames} results ({accepted} accepted, {} failed, {dropped} dropped) in {:.1} s over {backend}: {:.2} frames/s",
        frames - accepted,
        collected.wall_s,
        collected.frames_per_s()
    );
    let _ = writeln!(
        text,
        "latency capture→result: p50 {:.0} ms, p90 {:.0} ms, p99 {:.0} ms, max {:.0} ms",
        percentile(&latencies, 0.5),
        percentile(&latencies, 0.9),
        percentile(&latencies, 0.99),
        percentile(&latencies, 1.0)
    );
    let missing = collected.missing();
    let _ = writeln!(
        text,
        "exactly one result per frame: {} (missing {:?}, duplicated {:?}; re-delivered identical: {})",
        if missing.is_empty() && collected.duplicates.is_empty() {
            "yes"
        } else {
            "NO"
        },
        missing,
        collected.duplicates,
        collected.redelivered
    );
    let _ = writeln!(
        text,
        "{:<10} {:>6} {:>7} {:>7} {:>9} {:>9} {:>9} {:>10} {:>9} {:>8} {:>6} {:>6}",
        "stage",
        "worker",
        "in",
        "out",
        "compute_s",
        "p50_ms",
        "p90_ms",
        "sent_MB",
        "send_ms",
        "decode_ms",
        "drops",
        "redo"
    );
    for ((stage, worker), m) in &collected.metrics {
        let _ = writeln!(
            text,
            "{:<10} {:>6} {:>7} {:>7} {:>9.2} {:>9.1} {:>9.1} {:>10.1} {:>9.1} {:>8.1} {:>6} {:>6}",
            stage,
            worker,
            m.messages_in,
            m.messages_out,
            m.compute_ms / 1e3,
            percentile(&m.compute_samples_ms, 0.5),
            percentile(&m.compute_samples_ms, 0.9),
            m.bytes_out as f64 / 1e6,
            m.send_ms,
            m.decode_ms,
            m.dropped,
            m.redispatched
        );
    }
    let _ = writeln!(
        text,
        "transport time (encode+send+decode) / compute time: {:.2} %",
        collected.transport_share_percent()
    );
    let _ = writeln!(text, "flow jobs per worker: {:?}", collected.flow_split());
    if !collected.change_results.is_empty() || collected.change_set.is_some() {
        let missing = collected.missing_changes();
        let _ = writeln!(
            text,
            "exactly one change result per frame: {} (missing {:?}, duplicated {:?}; re-delivered identical: {})",
            if missing.is_empty() && collected.change_duplicates.is_empty() {
                "yes"
            } else {
                "NO"
            },
            missing,
            collected.change_duplicates,
            collected.change_redelivered
        );
        let mapped: Vec<f64> = collected
            .change_results
            .iter()
            .filter(|r| r.failure.is_none())
            .map(|r| r.change_ms)
            .collect();
        let registration: Vec<f64> = collected
            .results
            .iter()
            .filter(|r| r.accepted)
            .map(|r| r.times.render_ms + r.times.flow_ms + r.times.pose_ms + r.times.verify_ms)
            .collect();
        let _ = writeln!(
            text,
            "change maps: {} of {} frames; change stage per frame p50 {:.1} ms, p90 {:.1} ms (registration's compute per accepted frame: p50 {:.0} ms)",
            mapped.len(),
            collected.change_results.len(),
            percentile(&mapped, 0.5),
            percentile(&mapped, 0.9),
            percentile(&registration, 0.5)
        );
        match &collected.change_set {
            Some(set) => {
                let _ = writeln!(
                    text,
                    "change set: {} objects ({} confirmed by ≥ {} frames; {} added seen through by more frames than agree, not confirmed)",
                    set.objects.len(),
                    set.objects.iter().filter(|o| o.confirmed).count(),
                    set.fusion.min_frames,
                    set.free_space.iter().filter(|c| c.refuted).count()
                );
            }
            None => {
                let _ = writeln!(text, "change set: NONE (the change stream did not end)");
            }
        }
    }
    if collected.rejected_messages > 0 {
        let _ = writeln!(
            text,
            "rejected messages at the collector: {}",
            collected.rejected_messages
        );
    }
    text
}
