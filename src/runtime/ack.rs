//! End-to-end acknowledgement of published results (issue #15): a result lost in flight — the
//! zenoh router killed while it carried it, or published while no router was there (zenoh drops
//! a put that reaches no subscriber) — is sent again until the station's collector says it holds
//! it. One implementation for both publishers of results, verify (PoseResults) and fusion
//! (ChangeResults): [`Resender`]; and one for the consumer that acknowledges them: [`Acker`].
//!
//! An ack is a `Credit` message on `results/ack` or `changes/ack` (`keys::RESULTS_ACK`,
//! `keys::CHANGES_ACK`; no new message kind, so the wire schema stays v5): `worker_index` 0,
//! `incarnation` the acknowledging process's, `completed` the frames it holds (`coarse_index`
//! 0), `free_slots` 0. Only the station's collector acknowledges (`launch`, `run`); `asgreg
//! subscribe` and the Python example do not, and the access-control config does not let an
//! observer publish at all, so a display cannot silence the re-sending.
//!
//! Re-sending is idempotent: what is sent again is the very message first published (the same
//! bytes, so the same body), and every consumer keeps the first result per frame id and counts an
//! identical repeat as re-delivery ([`super::collect::Collector`]), not as a second result. The
//! first re-send comes `timeouts.resend_after_s` after the publication, then the wait doubles up
//! to [`RESEND_MAX`]. Acks are batched (one message per [`ACK_EVERY`]) and the publisher drains
//! its acks before each send, so the collector blocked on a full ack queue and the publisher
//! blocked on a full results queue cannot wait for each other for long.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::msg::{Body, Credit, JobKey, StageMetrics};
use crate::transport::Transport;

use super::bus::{unix_time_ns, BusError, Inbox, Outbox};

/// The longest wait between two re-sends of one unacknowledged result.
pub const RESEND_MAX: Duration = Duration::from_secs(16);
/// How often the collector sends what it acknowledges (one message for all frames since).
pub const ACK_EVERY: Duration = Duration::from_millis(100);
/// Most results a publisher sends again in one pass (the rest at its next pass).
const RESEND_BATCH: usize = 16;

/// A published result not yet acknowledged.
struct Pending {
    /// The encoded message as first published.
    message: Arc<Vec<u8>>,
    /// Its JSON twin (`results/json`, `changes/json`).
    json: Arc<String>,
    next_at: Instant,
    interval: Duration,
    /// Tracked due at once (a restarted publisher's journaled result, which a crash may have
    /// kept from being published: the journal is written ahead): sent once even when
    /// re-sending is off.
    restored: bool,
}

/// What one re-send pass hands back to be sent again: frame id, message, JSON.
pub type Resend = (u64, Arc<Vec<u8>>, Arc<String>);

/// The publisher's side: the results published and not yet acknowledged, and their acks.
pub struct Resender {
    acks: Inbox,
    pending: BTreeMap<u64, Pending>,
    /// Zero: never re-send (acks are still taken).
    first_after: Duration,
    /// Results sent again (metrics, log).
    pub resent: u64,
}

impl Resender {
    /// Subscribes to `ack_topic` (before the first publication, so no ack is missed).
    pub fn open(
        transport: &dyn Transport,
        ack_topic: &str,
        stage: &str,
        first_after: Duration,
    ) -> Result<Self, BusError> {
        Ok(Self {
            acks: Inbox::open(transport, ack_topic, stage)?,
            pending: BTreeMap::new(),
            first_after,
            resent: 0,
        })
    }

    /// Keeps a published result until it is acknowledged; its first re-send is due after
    /// `due_in`.
    pub fn track(&mut self, frame_id: u64, message: Vec<u8>, json: String, due_in: Duration) {
        self.insert(frame_id, message, json, due_in, false);
    }

    /// Keeps a restarted publisher's journaled, unacknowledged result, due at once (also when
    /// re-sending is off: once, as the crash may have kept it from being published).
    pub fn restore(&mut self, frame_id: u64, message: Vec<u8>, json: String) {
        self.insert(frame_id, message, json, Duration::ZERO, true);
    }

    fn insert(
        &mut self,
        frame_id: u64,
        message: Vec<u8>,
        json: String,
        due_in: Duration,
        restored: bool,
    ) {
        let now = Instant::now();
        self.pending.insert(
            frame_id,
            Pending {
                message: Arc::new(message),
                json: Arc::new(json),
                next_at: now + due_in,
                interval: self.first_after,
                restored,
            },
        );
    }

    /// The wait before a fresh result's first re-send.
    pub fn first_after(&self) -> Duration {
        self.first_after
    }

    /// Results published and not yet acknowledged.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Takes the acks that arrived; returns the frames acknowledged now (each once).
    pub fn take_acks(&mut self, metrics: &mut StageMetrics) -> Result<Vec<u64>, BusError> {
        let mut acked = Vec::new();
        let pending = &mut self.pending;
        while self
            .acks
            .receive(Duration::ZERO, metrics, &mut |message, _| {
                if let Body::Credit(credit) = message.body {
                    for key in credit.completed {
                        if pending.remove(&key.frame_id).is_some() {
                            acked.push(key.frame_id);
                        }
                    }
                }
            })?
        {}
        Ok(acked)
    }

    /// The results whose re-send is due at `now` (at most a batch; the wait before each one's
    /// next re-send doubles, up to [`RESEND_MAX`]). When re-sending is off: only the restored
    /// ones, once.
    pub fn due(&mut self, now: Instant) -> Vec<Resend> {
        let off = self.first_after.is_zero();
        let mut due = Vec::new();
        for (frame_id, pending) in &mut self.pending {
            if due.len() >= RESEND_BATCH {
                break;
            }
            if off && !pending.restored {
                continue;
            }
            if pending.next_at <= now {
                pending.restored = false;
                pending.interval = (pending.interval * 2).min(RESEND_MAX);
                pending.next_at = now + pending.interval;
                due.push((
                    *frame_id,
                    Arc::clone(&pending.message),
                    Arc::clone(&pending.json),
                ));
            }
        }
        self.resent += due.len() as u64;
        due
    }
}

/// The consumer's side: acknowledges the frames whose result it holds, batched.
pub struct Acker {
    outbox: Outbox,
    incarnation: u64,
    unsent: Vec<u64>,
    last: Instant,
}

impl Acker {
    pub fn open(transport: &dyn Transport, ack_topic: &str) -> Result<Self, BusError> {
        Ok(Self {
            outbox: Outbox::open(transport, ack_topic)?,
            incarnation: unix_time_ns() ^ (u64::from(std::process::id()) << 32),
            unsent: Vec::new(),
            last: Instant::now(),
        })
    }

    /// `frame_id`'s result is here (first delivery or a repeat: a repeat means the ack was lost).
    pub fn hold(&mut self, frame_id: u64) {
        self.unsent.push(frame_id);
    }

    /// Sends the acks gathered since the last send, at most once per [`ACK_EVERY`] (`now`: at
    /// once, e.g. at the end of the collection).
    pub fn flush(&mut self, now: bool) -> Result<(), BusError> {
        if self.unsent.is_empty() || (!now && self.last.elapsed() < ACK_EVERY) {
            return Ok(());
        }
        self.last = Instant::now();
        let completed = self
            .unsent
            .drain(..)
            .map(|frame_id| JobKey {
                frame_id,
                coarse_index: 0,
            })
            .collect();
        let mut scratch = StageMetrics::default();
        self.outbox.send(
            0,
            0,
            Body::Credit(Credit {
                worker_index: 0,
                incarnation: self.incarnation,
                completed,
                free_slots: 0,
            }),
            &mut scratch,
        )?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::crossbeam::CrossbeamTransport;
    use crate::transport::TransportConfig;

    #[test]
    fn a_result_is_sent_again_with_backoff_until_it_is_acknowledged() {
        let transport = CrossbeamTransport::new(TransportConfig {
            pipeline: "ack-unit".to_string(),
            ..TransportConfig::default()
        });
        let mut resender =
            Resender::open(&transport, "results/ack", "verify", Duration::from_secs(2)).unwrap();
        let mut acker = Acker::open(&transport, "results/ack").unwrap();
        let mut metrics = StageMetrics::default();
        resender.track(3, vec![1, 2, 3], "{}".to_string(), Duration::from_secs(2));
        resender.restore(5, vec![5], "{}".to_string());
        let start = Instant::now();
        // Not due yet: only the restored one (due at once).
        let due = resender.due(start);
        assert_eq!(due.len(), 1);
        assert_eq!(due[0].0, 5);
        assert_eq!(*due[0].1, vec![5]);
        // Backoff: 2 s, then 4 s, ... capped.
        assert!(resender.due(start + Duration::from_millis(3900)).len() == 1);
        assert!(resender.due(start + Duration::from_millis(4100)).len() == 1);
        assert!(resender
            .due(start + Duration::from_secs(60))
            .iter()
            .all(|(_, message, _)| !message.is_empty()));
        assert_eq!(resender.resent, 5);
        // Acks: frame 3 is acknowledged (twice: counted once), 5 stays pending.
        acker.hold(3);
        acker.flush(true).unwrap();
        acker.hold(3);
        acker.flush(true).unwrap();
        assert_eq!(resender.take_acks(&mut metrics).unwrap(), vec![3]);
        assert_eq!(resender.pending(), 1);
        let later = start + Duration::from_secs(600);
        assert_eq!(
            resender
                .due(later)
                .iter()
                .map(|(id, ..)| *id)
                .collect::<Vec<_>>(),
            vec![5]
        );
        // Off: a fresh result is never due; a restored one (journaled ahead, maybe never
        // published) once.
        let mut off = Resender::open(&transport, "results/ack", "verify", Duration::ZERO).unwrap();
        off.restore(1, vec![1], String::new());
        off.restore(2, vec![2], String::new());
        off.track(3, vec![3], String::new(), off.first_after());
        let once: Vec<u64> = off.due(later).iter().map(|(id, ..)| *id).collect();
        assert_eq!(once, vec![1, 2]);
        assert!(off.due(later + Duration::from_secs(600)).is_empty());
    }
}
