//! In-process transport over crossbeam channels: every stage is a thread of one process (the
//! embedded default, `asgreg run`). Each subscriber owns a bounded channel; a publisher sends a
//! copy of each message to every live subscriber of its topic and blocks while one is full.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crossbeam_channel::{bounded, Receiver, RecvTimeoutError, SendError, Sender};

use super::{Publisher, Subscriber, Transport, TransportConfig, TransportError};

const BACKEND: &str = "crossbeam";

type Registry = Arc<Mutex<HashMap<String, Vec<Sender<Vec<u8>>>>>>;

/// The in-process bus: clone it (cheaply) into every stage thread.
#[derive(Clone)]
pub struct CrossbeamTransport {
    config: TransportConfig,
    subscribers: Registry,
}

impl CrossbeamTransport {
    pub fn new(config: TransportConfig) -> Self {
        Self {
            config,
            subscribers: Arc::default(),
        }
    }
}

impl Transport for CrossbeamTransport {
    fn backend(&self) -> &'static str {
        BACKEND
    }

    fn publisher(&self, topic: &str) -> Result<Box<dyn Publisher>, TransportError> {
        Ok(Box::new(CrossbeamPublisher {
            topic: topic.to_string(),
            subscribers: Arc::clone(&self.subscribers),
            max_message_bytes: self.config.max_message_bytes,
        }))
    }

    fn subscriber(&self, topic: &str) -> Result<Box<dyn Subscriber>, TransportError> {
        let (sender, receiver) = bounded(self.config.queue_depth.max(1));
        self.subscribers
            .lock()
            .map_err(|_| TransportError::OpenSubscriber {
                backend: BACKEND,
                topic: topic.to_string(),
                detail: "the topic registry is poisoned (a stage thread panicked)".to_string(),
            })?
            .entry(topic.to_string())
            .or_default()
            .push(sender);
        Ok(Box::new(CrossbeamSubscriber {
            topic: topic.to_string(),
            receiver,
        }))
    }
}

struct CrossbeamPublisher {
    topic: String,
    subscribers: Registry,
    max_message_bytes: usize,
}

impl CrossbeamPublisher {
    /// The topic's subscribers' senders, cloned out of the lock (a blocking send must not hold
    /// the registry).
    fn senders(&self) -> Result<Vec<Sender<Vec<u8>>>, TransportError> {
        Ok(self
            .subscribers
            .lock()
            .map_err(|_| TransportError::Send {
                backend: BACKEND,
                topic: self.topic.clone(),
                detail: "the topic registry is poisoned (a stage thread panicked)".to_string(),
            })?
            .get(&self.topic)
            .cloned()
            .unwrap_or_default())
    }
}

impl Publisher for CrossbeamPublisher {
    fn topic(&self) -> &str {
        &self.topic
    }

    fn wait_for_subscriber(&mut self, timeout: Duration) -> Result<bool, TransportError> {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            let connected = self
                .subscribers
                .lock()
                .map(|registry| {
                    registry
                        .get(&self.topic)
                        .is_some_and(|list| !list.is_empty())
                })
                .unwrap_or(false);
            if connected {
                return Ok(true);
            }
            if std::time::Instant::now() >= deadline {
                return Ok(false);
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    fn send_lossy(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        super::check_message_size(BACKEND, &self.topic, bytes.len(), self.max_message_bytes)?;
        let senders = self.senders()?;
        for sender in senders {
            // A full or dropped subscriber misses this message; nobody waits.
            let _ = sender.try_send(bytes.to_vec());
        }
        Ok(())
    }

    fn send_with(
        &mut self,
        len: usize,
        write: &mut dyn FnMut(&mut [u8]),
    ) -> Result<(), TransportError> {
        super::check_message_size(BACKEND, &self.topic, len, self.max_message_bytes)?;
        let mut message = vec![0u8; len];
        write(&mut message);
        let senders = self.senders()?;
        let mut dead: Vec<&Sender<Vec<u8>>> = Vec::new();
        // Every subscriber but the last gets a copy; the last gets the message itself.
        if let Some((last, others)) = senders.split_last() {
            for sender in others {
                if let Err(SendError(_)) = sender.send(message.clone()) {
                    dead.push(sender);
                }
            }
            if let Err(SendError(_)) = last.send(message) {
                dead.push(last);
            }
        }
        if !dead.is_empty() {
            // A dropped subscriber is forgotten so that no publisher ever waits on it.
            if let Ok(mut registry) = self.subscribers.lock() {
                if let Some(list) = registry.get_mut(&self.topic) {
                    list.retain(|sender| !dead.iter().any(|gone| gone.same_channel(sender)));
                }
            }
        }
        Ok(())
    }
}

struct CrossbeamSubscriber {
    topic: String,
    receiver: Receiver<Vec<u8>>,
}

impl Subscriber for CrossbeamSubscriber {
    fn topic(&self) -> &str {
        &self.topic
    }

    fn receive(
        &mut self,
        timeout: Duration,
        on_message: &mut dyn FnMut(&[u8]),
    ) -> Result<bool, TransportError> {
        match self.receiver.recv_timeout(timeout) {
            Ok(message) => {
                on_message(&message);
                Ok(true)
            }
            Err(RecvTimeoutError::Timeout) => Ok(false),
            Err(RecvTimeoutError::Disconnected) => Err(TransportError::Receive {
                backend: BACKEND,
                topic: self.topic.clone(),
                detail: "the bus was shut down".to_string(),
            }),
        }
    }
}

#[cfg(test)]
mod conformance {
    crate::conformance_suite!(|config| Box::new(super::CrossbeamTransport::new(config)));
}
