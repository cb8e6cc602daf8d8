//! A stage's view of the bus: an `Outbox` encodes a message straight into the transport's buffer
//! (loan → write → send) and stamps the header; an `Inbox` decodes what arrives, and a message it
//! cannot decode (wrong schema version, corrupt bytes) is logged, counted and skipped: it never
//! stops the receiver. Both count bytes and time for the metrics.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use crate::msg::{decode, encode, Body, Envelope, Header, StageMetrics};
use crate::transport::{Publisher, Subscriber, Transport, TransportError};

#[derive(Debug, thiserror::Error)]
pub enum BusError {
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error("cannot encode a message for topic '{topic}': {detail}")]
    Encode { topic: String, detail: String },
    #[error("no subscriber on topic '{topic}' after {waited_s:.0} s: is the {stage} stage running (same pipeline name and transport)?")]
    NoSubscriber {
        topic: String,
        stage: &'static str,
        waited_s: f64,
    },
}

/// Unix time now, ns.
pub fn unix_time_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

pub struct Outbox {
    publisher: Box<dyn Publisher>,
    sequence: u64,
}

impl Outbox {
    pub fn open(transport: &dyn Transport, topic: &str) -> Result<Self, BusError> {
        Ok(Self {
            publisher: transport.publisher(topic)?,
            sequence: 0,
        })
    }

    /// Waits until the stage that reads this topic is there (`stage` names it in the error).
    pub fn wait_for_reader(
        &mut self,
        stage: &'static str,
        timeout: Duration,
    ) -> Result<(), BusError> {
        let started = Instant::now();
        let mut warned = false;
        loop {
            if self
                .publisher
                .wait_for_subscriber(Duration::from_millis(500))?
            {
                return Ok(());
            }
            if !warned && started.elapsed() > Duration::from_secs(2) {
                tracing::info!(
                    "waiting for the {stage} stage to subscribe to '{}'",
                    self.publisher.topic()
                );
                warned = true;
            }
            if started.elapsed() > timeout {
                return Err(BusError::NoSubscriber {
                    topic: self.publisher.topic().to_string(),
                    stage,
                    waited_s: timeout.as_secs_f64(),
                });
            }
        }
    }

    /// Sends `body` for `frame_id` (capture time carried from the frame); returns the bytes sent.
    pub fn send(
        &mut self,
        frame_id: u64,
        capture_time_ns: u64,
        body: Body<'_>,
        metrics: &mut StageMetrics,
    ) -> Result<usize, BusError> {
        let started = Instant::now();
        self.sequence += 1;
        let message = Envelope {
            header: Header {
                frame_id,
                sequence: self.sequence,
                capture_time_ns,
                sent_time_ns: unix_time_ns(),
            },
            body,
        };
        let encoded = encode(&message).map_err(|error| BusError::Encode {
            topic: self.publisher.topic().to_string(),
            detail: error.to_string(),
        })?;
        let len = encoded.len();
        self.publisher
            .send_with(len, &mut |buffer| encoded.write_to(buffer))?;
        metrics.messages_out += 1;
        metrics.bytes_out += len as u64;
        metrics.send_ms += started.elapsed().as_secs_f64() * 1e3;
        Ok(len)
    }

    /// Sends bytes that are already an encoded message (a job kept for a possible redo).
    pub fn send_encoded(
        &mut self,
        bytes: &[u8],
        metrics: &mut StageMetrics,
    ) -> Result<(), BusError> {
        let started = Instant::now();
        self.publisher.send(bytes)?;
        metrics.messages_out += 1;
        metrics.bytes_out += bytes.len() as u64;
        metrics.send_ms += started.elapsed().as_secs_f64() * 1e3;
        Ok(())
    }

    /// Sends an arbitrary byte string (tests of the receivers' rejection of bad messages).
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), BusError> {
        Ok(self.publisher.send(bytes)?)
    }

    /// Encodes and sends a message best effort: a subscriber with a full queue misses it and
    /// nobody waits (metrics: a stage never stops on a monitor that does not read).
    pub fn send_lossy(&mut self, body: Body<'_>) -> Result<(), BusError> {
        let bytes = encode_to_vec(0, 0, body)?;
        Ok(self.publisher.send_lossy(&bytes)?)
    }
}

/// Encodes a message into a new byte vector (jobs that a dispatcher may have to send again).
pub fn encode_to_vec(
    frame_id: u64,
    capture_time_ns: u64,
    body: Body<'_>,
) -> Result<Vec<u8>, BusError> {
    let message = Envelope {
        header: Header {
            frame_id,
            sequence: 0,
            capture_time_ns,
            sent_time_ns: unix_time_ns(),
        },
        body,
    };
    encode(&message)
        .map(|encoded| encoded.to_vec())
        .map_err(|error| BusError::Encode {
            topic: String::new(),
            detail: error.to_string(),
        })
}

pub struct Inbox {
    subscriber: Box<dyn Subscriber>,
    stage: String,
}

impl Inbox {
    pub fn open(transport: &dyn Transport, topic: &str, stage: &str) -> Result<Self, BusError> {
        Ok(Self {
            subscriber: transport.subscriber(topic)?,
            stage: stage.to_string(),
        })
    }

    /// Waits up to `timeout` for a message and hands the decoded message (borrowing the
    /// transport's buffer) to `handle`. Undecodable messages are logged with the reason, counted
    /// in `metrics.rejected` and skipped. Returns whether a message arrived.
    pub fn receive(
        &mut self,
        timeout: Duration,
        metrics: &mut StageMetrics,
        handle: &mut dyn FnMut(Envelope<'_>, &mut StageMetrics),
    ) -> Result<bool, BusError> {
        let topic = self.subscriber.topic().to_string();
        let stage = &self.stage;
        Ok(self.subscriber.receive(timeout, &mut |bytes| {
            let started = Instant::now();
            let decoded = decode(bytes);
            metrics.decode_ms += started.elapsed().as_secs_f64() * 1e3;
            match decoded {
                Ok(message) => {
                    metrics.messages_in += 1;
                    handle(message, metrics);
                }
                Err(error) => {
                    metrics.rejected += 1;
                    tracing::error!(
                        "{stage}: rejected a message of {} bytes on '{topic}': {error}",
                        bytes.len()
                    );
                }
            }
        })?)
    }
}
