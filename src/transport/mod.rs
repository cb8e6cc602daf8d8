//! Transports move encoded messages between stages. This module is the only code that names
//! crossbeam, iceoryx2 or zenoh (docs/design.md §5): one trait, three backends, one conformance suite
//! (`conformance`) that every backend must pass.
//!
//! The contract every backend keeps (and the conformance suite checks):
//! - **Lossless and ordered per publisher**: a subscriber that exists when `send` is called
//!   receives the message, in the order the publisher sent them. A full subscriber queue blocks
//!   the publisher (backpressure); nothing is overwritten or dropped silently.
//! - **Broadcast**: every subscriber of a topic receives every message. Work sharing between
//!   workers is built above the transport (`runtime::dispatch`), not in it.
//! - **Many publishers** may send on one topic.
//! - **Bytes in, bytes out**: messages are opaque byte strings of up to
//!   [`TransportConfig::max_message_bytes`]; `msg` encodes and decodes them.

pub mod crossbeam;
pub mod iceoryx2;
pub mod keys;
pub mod zenoh;

#[cfg(test)]
pub(crate) mod conformance;

use std::time::Duration;

use serde::{Deserialize, Serialize};

/// What went wrong in a transport; each names the topic (and backend) involved.
#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    #[error("{backend}: topic '{topic}': could not open a publisher: {detail}")]
    OpenPublisher {
        backend: &'static str,
        topic: String,
        detail: String,
    },
    #[error("{backend}: topic '{topic}': could not open a subscriber: {detail}")]
    OpenSubscriber {
        backend: &'static str,
        topic: String,
        detail: String,
    },
    #[error("{backend}: topic '{topic}': message of {bytes} bytes exceeds the limit of {limit} bytes (raise transport.max_message_bytes)")]
    TooLarge {
        backend: &'static str,
        topic: String,
        bytes: usize,
        limit: usize,
    },
    #[error("{backend}: topic '{topic}': send failed: {detail}")]
    Send {
        backend: &'static str,
        topic: String,
        detail: String,
    },
    #[error("{backend}: topic '{topic}': receive failed: {detail}")]
    Receive {
        backend: &'static str,
        topic: String,
        detail: String,
    },
    #[error("{backend}: {detail}")]
    Setup {
        backend: &'static str,
        detail: String,
    },
}

/// The size check every backend makes before it sends: `len` must not exceed `limit`.
pub(crate) fn check_message_size(
    backend: &'static str,
    topic: &str,
    len: usize,
    limit: usize,
) -> Result<(), TransportError> {
    if len > limit {
        return Err(TransportError::TooLarge {
            backend,
            topic: topic.to_string(),
            bytes: len,
            limit,
        });
    }
    Ok(())
}

/// Settings shared by all backends.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct TransportConfig {
    /// Name space of this pipeline instance: two pipelines with different names never see each
    /// other's messages (iceoryx2 services and zenoh keys are prefixed with it).
    pub pipeline: String,
    /// Largest message a topic carries, bytes (a 4 MP float image is 16 MB).
    pub max_message_bytes: usize,
    /// Messages a subscriber queues before its publishers block.
    pub queue_depth: usize,
}

impl Default for TransportConfig {
    fn default() -> Self {
        Self {
            pipeline: "default".to_string(),
            max_message_bytes: 64 << 20,
            queue_depth: 16,
        }
    }
}

/// One side that sends on a topic.
pub trait Publisher {
    /// The topic this publisher sends on.
    fn topic(&self) -> &str;
    /// Sends one message of exactly `len` bytes, written by `write` straight into the transport's
    /// buffer (loan → write → send; shared memory for iceoryx2). Blocks while a subscriber's queue
    /// is full.
    fn send_with(
        &mut self,
        len: usize,
        write: &mut dyn FnMut(&mut [u8]),
    ) -> Result<(), TransportError>;
    /// Waits until at least one subscriber is connected (the "ready" handshake: iceoryx2 and
    /// zenoh drop messages sent before a subscriber has attached). Returns `Ok(false)` on timeout.
    fn wait_for_subscriber(&mut self, timeout: Duration) -> Result<bool, TransportError>;
    /// Sends a message that is already a byte string.
    fn send(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        self.send_with(bytes.len(), &mut |buffer| buffer.copy_from_slice(bytes))
    }
    /// Sends best effort (metrics): never waits for a full subscriber queue; a subscriber whose
    /// queue is full misses the message. The default is `send` (zenoh's, which waits at most its
    /// `blocked_send_limit_ms` on a congested link); crossbeam and iceoryx2, whose `send` waits
    /// for a full queue, override it.
    fn send_lossy(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        self.send(bytes)
    }
}

/// One side that receives from a topic.
pub trait Subscriber {
    /// The topic this subscriber receives from.
    fn topic(&self) -> &str;
    /// Waits up to `timeout` for the next message and lends its bytes to `on_message` (for
    /// iceoryx2 they are the shared-memory sample itself: no copy). Returns `Ok(false)` when
    /// nothing arrived in time.
    fn receive(
        &mut self,
        timeout: Duration,
        on_message: &mut dyn FnMut(&[u8]),
    ) -> Result<bool, TransportError>;
}

/// A backend: opens publishers and subscribers on named topics. Endpoints are opened on the
/// thread that uses them (iceoryx2's ports are not `Send`); the factory itself is shared.
pub trait Transport: Send + Sync {
    /// "crossbeam", "iceoryx2" or "zenoh".
    fn backend(&self) -> &'static str;
    fn publisher(&self, topic: &str) -> Result<Box<dyn Publisher>, TransportError>;
    fn subscriber(&self, topic: &str) -> Result<Box<dyn Subscriber>, TransportError>;
    /// Keeps `topic`'s services in existence while the returned value lives, with no publisher
    /// or subscriber. iceoryx2: a process SIGKILLed while it creates a service leaves it half
    /// made, and every later open fails (`HangsInCreation`) until the launch gives up; the
    /// launcher makes every topic's services first and holds them, so a stage only opens them.
    /// The other backends have nothing to hold.
    fn hold_topic(&self, _topic: &str) -> Result<Box<dyn std::any::Any>, TransportError> {
        Ok(Box::new(()))
    }
}

/// Which backend carries the pipeline's messages.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// Threads of one process.
    #[default]
    Crossbeam,
    /// Processes on one host, shared memory.
    Iceoryx2,
    /// Processes on several hosts, TCP.
    Zenoh,
}

impl Backend {
    pub fn name(self) -> &'static str {
        match self {
            Backend::Crossbeam => "crossbeam",
            Backend::Iceoryx2 => "iceoryx2",
            Backend::Zenoh => "zenoh",
        }
    }
}

/// Opens the configured backend. `zenoh` settings are used only by the zenoh backend.
pub fn open(
    backend: Backend,
    config: &TransportConfig,
    zenoh_settings: &zenoh::ZenohSettings,
) -> Result<std::sync::Arc<dyn Transport>, TransportError> {
    Ok(match backend {
        Backend::Crossbeam => {
            std::sync::Arc::new(crossbeam::CrossbeamTransport::new(config.clone()))
        }
        Backend::Iceoryx2 => std::sync::Arc::new(iceoryx2::Iceoryx2Transport::new(config.clone())?),
        Backend::Zenoh => {
            std::sync::Arc::new(zenoh::ZenohTransport::new(config.clone(), zenoh_settings)?)
        }
    })
}

/// Removes shared-memory resources left by dead processes (iceoryx2); returns how many.
pub fn clean_stale_resources() -> Result<usize, TransportError> {
    iceoryx2::clean_stale_resources()
}

/// As [`clean_stale_resources`], once every process of a pipeline has exited (a launcher's
/// last step).
pub fn clean_stale_resources_after_exit() -> Result<usize, TransportError> {
    iceoryx2::clean_stale_resources_after_exit()
}
