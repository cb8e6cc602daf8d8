//! Shared-memory transport between processes on one host (iceoryx2 0.10, `ipc::Service`): the
//! stages of a pipeline run as separate processes and hand images over without copying them
//! (the publisher writes into a loaned shared-memory sample, the subscriber reads that same
//! memory).
//!
//! Each topic is three iceoryx2 services named after its key (`keys::key`,
//! `asgreg/v9/<pipeline>/<topic>`): the publish-subscribe service that carries the messages
//! (payload `[u64]`, user header [`MessageBytes`] with the message's length in bytes), an event
//! service of the same name (the messaging pattern is part of a service's identity, so they do
//! not collide) and a small publish-subscribe service `<key>!attached` for the attach handshake
//! below.
//!
//! iceoryx2's defaults are wrong for this pipeline (docs/design.md §7); what is set instead and why:
//! - **Lossless**: `enable_safe_overflow(false)` (the default overwrites the oldest queued
//!   sample) and the publisher's `BackpressureStrategy::RetryUntilDelivered` (0.10's name for
//!   "block"): a full subscriber queue (`TransportConfig::queue_depth`) blocks the publisher;
//!   after a few retries the blocked publisher sleeps between them instead of yielding the CPU
//!   thousands of times ([`BLOCKED_SEND_YIELDS`]).
//! - **Attach handshake**: iceoryx2 0.10 still drops samples silently when a subscriber's queue is
//!   full *before the subscriber has attached* to the publisher's connection
//!   (`NoConnectedReceiverAndBufferIsFull`, upstream issue #305). A subscriber attaches when it is
//!   created (to the publishers that exist then) and otherwise only when it next calls
//!   `receive`; so a publisher created after an idle subscriber loses its `queue_depth + 1`-th
//!   message, and everything it sent if it goes away before the subscriber attached. Hence:
//!   every subscriber acknowledges, on `<key>!attached`, each publisher it has attached to; a
//!   publisher counts what it sent to each subscriber that has not acknowledged it yet and,
//!   before a send could overrun such a subscriber's queue, waits for the acknowledgement (as it
//!   would wait on a full queue), asking for it with an event (a subscriber looks for that event
//!   while it waits for messages, and every [`EVENT_CHECK`] while it is busy). When dropped, a publisher waits
//!   (up to [`LINGER`]) until every subscriber it sent to has attached, so that its last messages
//!   outlive it. [`Publisher::wait_for_subscriber`] returns once a subscriber is registered.
//! - **Waking**: publish-subscribe wakes nobody. Every publisher notifies the topic's event
//!   service after each send; a subscriber first drains its queue and only then sleeps on its
//!   event listener (with the caller's timeout), so it never busy-spins and never misses a sample
//!   (an event sent between the drain and the wait is latched and ends the wait at once).
//! - **Zero copy**: the payload is a `[u64]` slice (the message bytes, padded to whole words), so
//!   it is 8-byte aligned and `msg::decode` borrows the f32/f64 arrays straight from the
//!   shared-memory sample. (A `[u8]` payload with `payload_alignment(8)` would do too, but
//!   iceoryx2 then reserves 8 bytes per byte: it pads each element to the alignment.)
//! - **Static memory**: each publisher reserves `MAX_SUBSCRIBERS × (queue_depth + 1) + 1` samples
//!   of `max_message_bytes` (`AllocationStrategy::Static`). The growing strategies map their
//!   later segments lazily on the subscriber side, and a segment whose publisher has gone before
//!   the subscriber mapped it is lost ("Lost chunk"). The reservation is sparse: tmpfs pages
//!   exist only once written, and the sample pool hands out the most recently freed sample
//!   first, so the memory used is that of the samples in flight. (With the defaults, 64 MiB
//!   messages and a queue of 16, a publisher's segment is 18 GB of address space; 20 messages of
//!   16 MiB through it occupied 17 MB of `/dev/shm`.)
//! - **Stale resources**: services live in `/dev/shm` and `/tmp/iceoryx2` beyond the processes
//!   that use them. A process that is SIGKILLed (or crashes, or is stopped by Ctrl-C: nodes are
//!   created without iceoryx2's signal handling, so signals keep their default effect) leaves
//!   its nodes behind; its subscribers would still count as ready and, worse, their full queues
//!   would block lossless publishers forever. [`clean_stale_resources`] removes every dead
//!   node's resources; it runs in [`Iceoryx2Transport::new`], and a publisher that has waited
//!   [`DEAD_PEER_CHECK`] on a subscriber runs it too, so a killed subscriber releases it. What
//!   iceoryx2's own cleanup cannot remove (a node killed while being created or half removed
//!   by a cleanup that was itself killed) is removed by file ([`leftovers`]).
//!
//! Ports are created on the thread that calls `publisher()`/`subscriber()` (iceoryx2's `ipc`
//! ports are not `Send`); each port has its own iceoryx2 node, dropped with it.

use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use ::iceoryx2::config::Config;
use ::iceoryx2::node::NodeView;
use ::iceoryx2::port::listener::Listener;
use ::iceoryx2::port::notifier::Notifier;
use ::iceoryx2::port::update_connections::UpdateConnections;
use ::iceoryx2::port::{BackpressureAction, BackpressureInfo};
use ::iceoryx2::prelude::{
    ipc, AllocationStrategy, BackpressureStrategy, CallbackProgression, EventActivation, EventId,
    Node, NodeBuilder, NodeName, NodeState, PortFactory as _, ServiceName, SignalHandlingMode,
    ZeroCopySend,
};
use ::iceoryx2::service::port_factory::{event, publish_subscribe};

use super::{keys, Publisher, Subscriber, Transport, TransportConfig, TransportError};

const BACKEND: &str = "iceoryx2";

/// Publishers one topic supports: a dispatched link's credits topic has one per worker, and
/// every stage worker publishes metrics (64 flow workers with the other stages need > 64).
pub const MAX_PUBLISHERS: usize = 128;
/// Subscribers one topic supports: results and metrics have a few monitors besides the pipeline.
/// Each costs every publisher of the topic `queue_depth + 1` reserved (sparse) samples.
pub const MAX_SUBSCRIBERS: usize = 128;
/// Every port has its own node, so a service sees at most one node per port.
const MAX_NODES: usize = MAX_PUBLISHERS + MAX_SUBSCRIBERS;
/// Samples a subscriber holds at once: `receive` lends one and drops it before returning.
const SUBSCRIBER_MAX_BORROWED: usize = 1;
/// Samples a publisher loans at once: `send_with` loans one and sends it before returning.
const PUBLISHER_MAX_LOANED: usize = 1;
/// The event a publisher sends after each message.
const DATA_EVENT: EventId = EventId::new(0);
/// The event a publisher sends to ask subscribers to (re)acknowledge their attachment.
const ACK_REQUEST_EVENT: EventId = EventId::new(1);
/// Acknowledgements a publisher's queue holds (it reads them before every send; an overwritten
/// one is asked for again).
const ACK_QUEUE: usize = 64;
/// How often a waiting publisher looks for acknowledgements.
const ACK_POLL: Duration = Duration::from_millis(1);
/// How often a waiting publisher repeats its request for acknowledgements.
const ACK_REQUEST_REPEAT: Duration = Duration::from_millis(100);
/// How often a subscriber that always finds a message looks for requests to acknowledge.
pub const EVENT_CHECK: Duration = Duration::from_millis(10);
/// How long a dropped publisher waits for subscribers it sent to but that have not attached.
pub const LINGER: Duration = Duration::from_secs(5);
/// How long a publisher waits on a subscriber before it checks for dead processes (and again
/// after every further such period).
pub const DEAD_PEER_CHECK: Duration = Duration::from_secs(1);
/// How long the cleanup waits for another process that is cleaning up the same dead node.
const CLEANUP_WAIT: Duration = Duration::from_millis(100);
/// How old a node directory without a monitor token must be before it counts as left by a
/// process killed while creating the node (creation writes the token right after the details).
const UNBORN_MIN_AGE: Duration = Duration::from_secs(5);
/// A send blocked on a full queue: iceoryx2's own wait between retries yields the CPU 10 000
/// times before it sleeps (`iceoryx2_bb_posix::config::ADAPTIVE_WAIT_YIELD_REPETITIONS`), and a
/// pipeline stage's queue stays full for a whole job of its reader (tens to thousands of ms), so
/// every blocked send spent several ms of CPU yielding, on cores the stages share. After this
/// many retries the handler sleeps [`BLOCKED_SEND_SLEEP`] before each further retry.
const BLOCKED_SEND_YIELDS: u64 = 64;
/// How long a blocked send sleeps between retries once past [`BLOCKED_SEND_YIELDS`]: a slot
/// freed in the queue is taken at most this late (a flow job is ~50–150 ms).
const BLOCKED_SEND_SLEEP: Duration = Duration::from_micros(200);

/// The user header of every message: its length in bytes (the `[u64]` payload is padded).
#[derive(Debug, Default, Clone, Copy, ZeroCopySend)]
#[type_name("asgreg::transport::iceoryx2::MessageBytes")]
#[repr(C)]
pub struct MessageBytes {
    pub len: u64,
}

/// A subscriber's acknowledgement: it has attached to this publisher's connection.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("asgreg::transport::iceoryx2::Attached")]
#[repr(C)]
struct Attached {
    publisher: u128,
    subscriber: u128,
}

/// Factory of shared-memory publishers and subscribers of one pipeline. It holds only settings
/// (so it is `Send + Sync`); every port is opened on the calling thread.
#[derive(Clone, Debug)]
pub struct Iceoryx2Transport {
    config: TransportConfig,
    iceoryx: Config,
}

impl Iceoryx2Transport {
    /// Removes what dead processes left behind (see [`clean_stale_resources`]) and checks that the
    /// pipeline name gives valid iceoryx2 service names. Uses iceoryx2's global configuration
    /// (its config file if there is one, else the defaults).
    pub fn new(config: TransportConfig) -> Result<Self, TransportError> {
        // iceoryx2 warns on stderr that it found no config file (we use its defaults on purpose);
        // keep its own log to errors unless IOX2_LOG_LEVEL says otherwise.
        iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
        Self::with_iceoryx_config(config, Config::global_config().clone())
    }

    /// As [`Iceoryx2Transport::new`], with an explicit iceoryx2 configuration (e.g. another
    /// file prefix, which isolates a set of processes from all others).
    pub fn with_iceoryx_config(
        config: TransportConfig,
        iceoryx: Config,
    ) -> Result<Self, TransportError> {
        let removed = clean_stale_resources_with(&iceoryx)?;
        if removed > 0 {
            tracing::info!("{BACKEND}: removed the resources of {removed} dead node(s)");
        }
        for name in [
            keys::key(&config.pipeline, "probe"),
            ack_service_name(&keys::key(&config.pipeline, "probe")),
        ] {
            service_name(&name).map_err(|detail| TransportError::Setup {
                backend: BACKEND,
                detail: format!("pipeline '{}': {detail}", config.pipeline),
            })?;
        }
        Ok(Self { config, iceoryx })
    }
}

/// Removes the shared memory, files and service registrations of every iceoryx2 node (of the
/// global configuration) whose process has died (SIGKILL, crash, Ctrl-C) and returns how many
/// dead nodes it removed. Nodes that cannot be removed (another user's, or being removed by
/// another process right now) are skipped with a warning.
pub fn clean_stale_resources() -> Result<usize, TransportError> {
    clean_stale_resources_with(Config::global_config())
}

fn clean_stale_resources_with(config: &Config) -> Result<usize, TransportError> {
    clean_and_report_unborn(config).map(|(removed, _)| removed)
}

/// [`clean_stale_resources_with`], also returning how long until the youngest unborn node left
/// in place is old enough to go.
fn clean_and_report_unborn(config: &Config) -> Result<(usize, Option<Duration>), TransportError> {
    let layout = leftovers::Layout::of(config);
    let mut removed = 0;
    let mut half_removed = HashSet::new();
    let mut failed = Vec::new();
    for_each_dead_node(config, &mut |dead| {
        let id = *dead.id();
        let details_gone = dead.details().is_none();
        match dead.blocking_remove_stale_resources(CLEANUP_WAIT) {
            Ok(()) => removed += 1,
            // See `leftovers`: its tags are removed below and the cleanup tried once more.
            Err(_) if details_gone => {
                half_removed.insert(id.value());
            }
            Err(error) => failed.push((id, error)),
        }
    })?;
    let mut retry = HashSet::new();
    for &id in &half_removed {
        match leftovers::remove_tags_of_half_removed(&layout, id) {
            Ok(_) => {
                retry.insert(id);
            }
            Err(error) => tracing::warn!(
                "{BACKEND}: could not remove the tags left by dead node {id}: {error}"
            ),
        }
    }
    if !retry.is_empty() {
        for_each_dead_node(config, &mut |dead| {
            let id = *dead.id();
            if retry.contains(&id.value()) {
                match dead.blocking_remove_stale_resources(CLEANUP_WAIT) {
                    Ok(()) => removed += 1,
                    Err(error) => failed.push((id, error)),
                }
            }
        })?;
    }
    let unborn_next_in = match leftovers::remove_unborn_nodes(&layout, UNBORN_MIN_AGE) {
        Ok(unborn) => {
            removed += unborn.removed;
            unborn.next_in
        }
        Err(error) => {
            tracing::warn!(
                "{BACKEND}: could not remove the files of nodes killed while being created: {error}"
            );
            None
        }
    };
    for (id, error) in &failed {
        tracing::warn!("{BACKEND}: could not remove the resources of dead node {id:?}: {error:?}");
    }
    if !failed.is_empty() {
        tracing::warn!("{BACKEND}: {} dead node(s) left in place", failed.len());
    }
    Ok((removed, unborn_next_in))
}

/// As [`clean_stale_resources`], for a launcher whose processes have all exited: a node killed
/// while being created less than [`UNBORN_MIN_AGE`] ago is waited for, not left behind.
pub fn clean_stale_resources_after_exit() -> Result<usize, TransportError> {
    let config = Config::global_config();
    let (mut removed, unborn_next_in) = clean_and_report_unborn(config)?;
    if let Some(wait) = unborn_next_in {
        std::thread::sleep(wait);
        removed += clean_stale_resources_with(config)?;
    }
    Ok(removed)
}

fn for_each_dead_node(
    config: &Config,
    each: &mut dyn FnMut(::iceoryx2::node::DeadNodeView<ipc::Service>),
) -> Result<(), TransportError> {
    Node::<ipc::Service>::list(config, |state| {
        if let NodeState::Dead(dead) = state {
            each(dead);
        }
        CallbackProgression::Continue
    })
    .map_err(|error| TransportError::Setup {
        backend: BACKEND,
        detail: format!("could not list the nodes to find dead ones: {error:?}"),
    })
}

/// Cleanup from inside a waiting publisher: errors are only logged.
fn release_dead_peers(config: &Config, waited: Duration) {
    match clean_stale_resources_with(config) {
        Ok(0) => {}
        Ok(removed) => tracing::warn!(
            "{BACKEND}: a publisher waiting for {waited:?} removed {removed} dead node(s)"
        ),
        Err(error) => tracing::warn!("{error}"),
    }
}

/// iceoryx2 accepts 1..=255 ASCII characters without NUL and reserves the prefix `iox2://`
/// (which a key never has).
fn service_name(name: &str) -> Result<ServiceName, String> {
    ServiceName::new(name).map_err(|error| {
        format!(
            "'{name}' is not a valid iceoryx2 service name ({error}: at most {} ASCII characters)",
            ServiceName::max_len()
        )
    })
}

/// The handshake service of a topic (no topic of `keys` contains `!`).
fn ack_service_name(key: &str) -> String {
    format!("{key}!attached")
}

type DataService = publish_subscribe::PortFactory<ipc::Service, [u64], MessageBytes>;
type AckService = publish_subscribe::PortFactory<ipc::Service, Attached, ()>;
type EventService = event::PortFactory<ipc::Service>;

/// A node plus the topic's services, as both ends open them.
struct Topic {
    data: DataService,
    acks: AckService,
    events: EventService,
    node: Node<ipc::Service>,
}

impl Iceoryx2Transport {
    fn open_topic(&self, topic: &str) -> Result<Topic, String> {
        let key = keys::key(&self.config.pipeline, topic);
        let name = service_name(&key)?;
        let ack_name = service_name(&ack_service_name(&key))?;
        let node = NodeBuilder::new()
            .name(&NodeName::new("asgreg").map_err(|error| format!("node name: {error:?}"))?)
            .config(&self.iceoryx)
            // iceoryx2 would otherwise install SIGINT/SIGTERM handlers for `Node::wait`, which
            // this crate does not use: signals keep their default effect.
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|error| format!("could not create a node: {error}"))?;
        let data = node
            .service_builder(&name)
            .publish_subscribe::<[u64]>()
            .user_header::<MessageBytes>()
            .enable_safe_overflow(false)
            .history_size(0)
            .subscriber_max_buffer_size(self.config.queue_depth.max(1))
            .subscriber_max_borrowed_samples(SUBSCRIBER_MAX_BORROWED)
            .max_publishers(MAX_PUBLISHERS)
            .max_subscribers(MAX_SUBSCRIBERS)
            .max_nodes(MAX_NODES)
            .open_or_create()
            .map_err(|error| {
                format!(
                    "could not open or create the publish-subscribe service '{name}': {error} \
                     (a service created with other settings, e.g. another queue_depth, cannot \
                     be opened)"
                )
            })?;
        // Acknowledgements go from subscribers (their publishers) to publishers (their
        // subscribers). Losing one is harmless (it is asked for again), so they may overflow.
        let acks = node
            .service_builder(&ack_name)
            .publish_subscribe::<Attached>()
            .enable_safe_overflow(true)
            .history_size(0)
            .subscriber_max_buffer_size(ACK_QUEUE)
            .subscriber_max_borrowed_samples(1)
            .max_publishers(MAX_SUBSCRIBERS)
            .max_subscribers(MAX_PUBLISHERS)
            .max_nodes(MAX_NODES)
            .open_or_create()
            .map_err(|error| {
                format!("could not open or create the handshake service '{ack_name}': {error}")
            })?;
        let events = node
            .service_builder(&name)
            .event()
            .max_notifiers(MAX_PUBLISHERS)
            .max_listeners(MAX_SUBSCRIBERS)
            .max_nodes(MAX_NODES)
            .open_or_create()
            .map_err(|error| {
                format!("could not open or create the event service '{name}': {error}")
            })?;
        Ok(Topic {
            data,
            acks,
            events,
            node,
        })
    }
}

impl Transport for Iceoryx2Transport {
    fn backend(&self) -> &'static str {
        BACKEND
    }

    fn hold_topic(&self, topic: &str) -> Result<Box<dyn std::any::Any>, TransportError> {
        let topic_services = self
            .open_topic(topic)
            .map_err(|detail| TransportError::Setup {
                backend: BACKEND,
                detail: format!("topic '{topic}': could not hold its services: {detail}"),
            })?;
        Ok(Box::new(topic_services))
    }

    fn publisher(&self, topic: &str) -> Result<Box<dyn Publisher>, TransportError> {
        let open_error = |detail: String| TransportError::OpenPublisher {
            backend: BACKEND,
            topic: topic.to_string(),
            detail,
        };
        let Topic {
            data,
            acks,
            events,
            node,
        } = self.open_topic(topic).map_err(open_error)?;
        // Before the publisher registers: a subscriber may acknowledge it right away.
        let ack_subscriber = acks
            .subscriber_builder()
            .buffer_size(ACK_QUEUE)
            .create()
            .map_err(|error| open_error(format!("could not create the handshake port: {error}")))?;
        let notifier = events
            .notifier_builder()
            .default_event_id(DATA_EVENT)
            .create()
            .map_err(|error| open_error(format!("could not create the notifier port: {error}")))?;
        let iceoryx = self.iceoryx.clone();
        let checks_done = AtomicU64::new(0);
        let lossy = Arc::new(AtomicBool::new(false));
        let lossy_in_handler = Arc::clone(&lossy);
        let publisher = data
            .publisher_builder()
            .initial_max_slice_len(self.config.max_message_bytes.div_ceil(8).max(1))
            .allocation_strategy(AllocationStrategy::Static)
            .max_loaned_samples(PUBLISHER_MAX_LOANED)
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            .set_backpressure_handler(move |info: &BackpressureInfo| {
                // A lossy send skips a full queue; a lossless one keeps retrying, but looks for
                // dead subscribers every DEAD_PEER_CHECK of one blocked send.
                if lossy_in_handler.load(Ordering::Relaxed) {
                    return BackpressureAction::DiscardData;
                }
                if info.retries == 0 {
                    checks_done.store(0, Ordering::Relaxed);
                } else {
                    let due = (info.elapsed_time.as_nanos() / DEAD_PEER_CHECK.as_nanos()) as u64;
                    if due > checks_done.load(Ordering::Relaxed) {
                        checks_done.store(due, Ordering::Relaxed);
                        release_dead_peers(&iceoryx, info.elapsed_time);
                    }
                    if info.retries >= BLOCKED_SEND_YIELDS {
                        std::thread::sleep(BLOCKED_SEND_SLEEP);
                    }
                }
                BackpressureAction::Retry
            })
            .create()
            .map_err(|error| open_error(format!("could not create the publisher port: {error}")))?;
        Ok(Box::new(Iceoryx2Publisher {
            topic: topic.to_string(),
            max_message_bytes: self.config.max_message_bytes,
            iceoryx: self.iceoryx.clone(),
            id: publisher.id().value(),
            lossy,
            confirmed: HashSet::new(),
            unconfirmed: HashMap::new(),
            publisher,
            ack_subscriber,
            notifier,
            data,
            _acks: acks,
            _events: events,
            _node: node,
        }))
    }

    fn subscriber(&self, topic: &str) -> Result<Box<dyn Subscriber>, TransportError> {
        let open_error = |detail: String| TransportError::OpenSubscriber {
            backend: BACKEND,
            topic: topic.to_string(),
            detail,
        };
        let Topic {
            data,
            acks,
            events,
            node,
        } = self.open_topic(topic).map_err(open_error)?;
        // The listener and the handshake port first: once the subscriber is registered,
        // publishers may wake it and wait for its acknowledgement.
        let listener = events
            .listener_builder()
            .create()
            .map_err(|error| open_error(format!("could not create the listener port: {error}")))?;
        let ack_publisher = acks
            .publisher_builder()
            .max_loaned_samples(1)
            .create()
            .map_err(|error| open_error(format!("could not create the handshake port: {error}")))?;
        let subscriber = data
            .subscriber_builder()
            .buffer_size(self.config.queue_depth.max(1))
            .create()
            .map_err(|error| {
                open_error(format!("could not create the subscriber port: {error}"))
            })?;
        let mut subscriber = Iceoryx2Subscriber {
            topic: topic.to_string(),
            acknowledged: HashSet::new(),
            last_event_check: Instant::now(),
            subscriber,
            ack_publisher,
            listener,
            data,
            _acks: acks,
            _events: events,
            _node: node,
        };
        subscriber.acknowledge_new_publishers()?;
        Ok(Box::new(subscriber))
    }
}

// Fields drop in declaration order: ports before their services, services before the node.
struct Iceoryx2Publisher {
    topic: String,
    max_message_bytes: usize,
    iceoryx: Config,
    /// This publisher's iceoryx2 id, as subscribers acknowledge it.
    id: u128,
    /// Set for the duration of a lossy send: the backpressure handler then discards the sample
    /// for a subscriber whose queue is full instead of retrying.
    lossy: Arc<AtomicBool>,
    /// Subscribers that have attached to this publisher.
    confirmed: HashSet<u128>,
    /// Subscribers that have not (yet): how many messages each may hold from this publisher.
    unconfirmed: HashMap<u128, usize>,
    publisher: ::iceoryx2::port::publisher::Publisher<ipc::Service, [u64], MessageBytes>,
    ack_subscriber: ::iceoryx2::port::subscriber::Subscriber<ipc::Service, Attached, ()>,
    notifier: Notifier<ipc::Service>,
    data: DataService,
    _acks: AckService,
    _events: EventService,
    _node: Node<ipc::Service>,
}

/// A registered subscriber as a publisher sees it: id and queue size.
struct Peer {
    id: u128,
    buffer_size: usize,
}

impl Iceoryx2Publisher {
    fn send_error(&self, detail: String) -> TransportError {
        TransportError::Send {
            backend: BACKEND,
            topic: self.topic.clone(),
            detail,
        }
    }

    fn subscribers(&self) -> Vec<Peer> {
        let mut peers = Vec::new();
        self.data.dynamic_config().list_subscribers(|details| {
            peers.push(Peer {
                id: details.subscriber_id.value(),
                buffer_size: details.buffer_size,
            });
            CallbackProgression::Continue
        });
        peers
    }

    /// Reads the acknowledgements that arrived and forgets subscribers that have gone.
    fn update_attachments(&mut self) -> Result<Vec<Peer>, TransportError> {
        loop {
            let sample = self.ack_subscriber.receive().map_err(|error| {
                self.send_error(format!("could not read attach acknowledgements: {error}"))
            })?;
            let Some(sample) = sample else { break };
            let ack = *sample.payload();
            if ack.publisher == self.id {
                self.unconfirmed.remove(&ack.subscriber);
                self.confirmed.insert(ack.subscriber);
            }
        }
        let peers = self.subscribers();
        self.unconfirmed
            .retain(|id, _| peers.iter().any(|peer| peer.id == *id));
        self.confirmed
            .retain(|id| peers.iter().any(|peer| peer.id == *id));
        Ok(peers)
    }

    /// Waits until no subscriber that has not attached holds more than `limit(queue size)`
    /// messages of this publisher (or until `deadline`, returning `Ok(false)`).
    fn wait_for_attachments(
        &mut self,
        limit: fn(usize) -> usize,
        deadline: Option<Instant>,
    ) -> Result<bool, TransportError> {
        let started = Instant::now();
        let mut last_request: Option<Instant> = None;
        let mut last_cleanup = started;
        loop {
            let peers = self.update_attachments()?;
            let blocked = peers.iter().any(|peer| {
                self.unconfirmed
                    .get(&peer.id)
                    .is_some_and(|&sent| sent > limit(peer.buffer_size))
            });
            if !blocked {
                return Ok(true);
            }
            let now = Instant::now();
            if deadline.is_some_and(|deadline| now >= deadline) {
                return Ok(false);
            }
            if last_request.is_none_or(|at| now - at >= ACK_REQUEST_REPEAT) {
                // Wakes subscribers sleeping in `receive`; they attach and acknowledge.
                self.notifier
                    .notify_with_custom_event_id(ACK_REQUEST_EVENT)
                    .map_err(|error| {
                        self.send_error(format!("could not ask subscribers to attach: {error}"))
                    })?;
                last_request = Some(now);
            }
            if now - last_cleanup >= DEAD_PEER_CHECK {
                last_cleanup = now;
                release_dead_peers(&self.iceoryx, now - started);
            }
            std::thread::sleep(ACK_POLL);
        }
    }
}

impl Publisher for Iceoryx2Publisher {
    fn topic(&self) -> &str {
        &self.topic
    }

    fn wait_for_subscriber(&mut self, timeout: Duration) -> Result<bool, TransportError> {
        let deadline = Instant::now() + timeout;
        loop {
            if self.data.dynamic_config().number_of_subscribers() > 0 {
                // Connect now, so that the first send does not have to.
                self.publisher.update_connections().map_err(|error| {
                    self.send_error(format!("could not connect to the subscribers: {error:?}"))
                })?;
                return Ok(true);
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(false);
            }
            std::thread::sleep((deadline - now).min(ACK_POLL));
        }
    }

    fn send_with(
        &mut self,
        len: usize,
        write: &mut dyn FnMut(&mut [u8]),
    ) -> Result<(), TransportError> {
        super::check_message_size(BACKEND, &self.topic, len, self.max_message_bytes)?;
        // A subscriber that has not attached must not be sent a message its full queue would
        // drop: wait for it as for a full queue.
        self.wait_for_attachments(|queue| queue.saturating_sub(1), None)?;
        self.deliver(len, write)
    }

    /// Never waits: neither for a subscriber to attach nor for room in a full queue (the
    /// backpressure handler discards the sample for that subscriber). Before this override the
    /// default `send` waited for ever on a subscriber that does not read.
    fn send_lossy(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        super::check_message_size(BACKEND, &self.topic, bytes.len(), self.max_message_bytes)?;
        self.lossy.store(true, Ordering::Relaxed);
        let sent = self.deliver(bytes.len(), &mut |buffer| buffer.copy_from_slice(bytes));
        self.lossy.store(false, Ordering::Relaxed);
        sent
    }
}

impl Iceoryx2Publisher {
    /// Loans a sample, lets `write` fill it and sends it (the backpressure handler decides what a
    /// full queue does); counts it against every subscriber not yet attached, lossy or not: a
    /// later lossless send must wait for such a subscriber whose queue it may have filled.
    fn deliver(
        &mut self,
        len: usize,
        write: &mut dyn FnMut(&mut [u8]),
    ) -> Result<(), TransportError> {
        let words = len.div_ceil(8);
        let mut sample = self.publisher.loan_slice_uninit(words).map_err(|error| {
            self.send_error(format!("could not loan a sample of {len} bytes: {error}"))
        })?;
        sample.user_header_mut().len = len as u64;
        let payload = sample.payload_mut();
        debug_assert!(payload.len() * 8 >= len);
        // SAFETY: the payload is `words` u64 (at least `len` bytes) of a shared-memory segment
        // that iceoryx2 mapped from a file (zero-filled by the kernel when created, and written
        // only as whole bytes since), so every byte is initialised and viewing `len` of them as
        // `[u8]` reads no uninitialised memory. The slice lives only for the `write` call, while
        // `sample` exclusively owns the chunk.
        let bytes =
            unsafe { std::slice::from_raw_parts_mut(payload.as_mut_ptr().cast::<u8>(), len) };
        write(bytes);
        // SAFETY: see above; every byte of the payload is initialised (`write` has filled the
        // first `len`, the padding holds what the memory held).
        let sample = unsafe { sample.assume_init() };
        sample
            .send()
            .map_err(|error| self.send_error(format!("could not deliver the sample: {error}")))?;
        // Every subscriber registered now may have received it (one that registered after the
        // send is counted too: an overestimate only makes the next wait come earlier).
        for peer in self.subscribers() {
            if !self.confirmed.contains(&peer.id) {
                *self.unconfirmed.entry(peer.id).or_insert(0) += 1;
            }
        }
        self.notifier.notify().map_err(|error| {
            self.send_error(format!("sent, but could not wake the subscribers: {error}"))
        })?;
        Ok(())
    }
}

impl Drop for Iceoryx2Publisher {
    /// A connection dies with its publisher unless the subscriber has attached to it: wait (a
    /// while) for every subscriber that may hold a message of this publisher.
    fn drop(&mut self) {
        match self.wait_for_attachments(|_| 0, Some(Instant::now() + LINGER)) {
            Ok(true) => {}
            Ok(false) => tracing::warn!(
                "{BACKEND}: topic '{}': closing the publisher although {} subscriber(s) have not \
                 attached within {LINGER:?}: they lose its last messages",
                self.topic,
                self.unconfirmed.len()
            ),
            Err(error) => tracing::warn!("{error}"),
        }
    }
}

// Fields drop in declaration order: ports before their services, services before the node.
struct Iceoryx2Subscriber {
    topic: String,
    /// Publishers this subscriber has attached to and acknowledged.
    acknowledged: HashSet<u128>,
    /// When the listener's events were last read.
    last_event_check: Instant,
    subscriber: ::iceoryx2::port::subscriber::Subscriber<ipc::Service, [u64], MessageBytes>,
    ack_publisher: ::iceoryx2::port::publisher::Publisher<ipc::Service, Attached, ()>,
    listener: Listener<ipc::Service>,
    data: DataService,
    _acks: AckService,
    _events: EventService,
    _node: Node<ipc::Service>,
}

impl Iceoryx2Subscriber {
    fn receive_error(&self, detail: String) -> TransportError {
        TransportError::Receive {
            backend: BACKEND,
            topic: self.topic.clone(),
            detail,
        }
    }

    /// Reads the listener's events, waiting up to `timeout` for one (not at all for `None`). A
    /// request to acknowledge makes the next [`Self::acknowledge_new_publishers`] acknowledge
    /// every publisher again (an acknowledgement may have been overwritten).
    fn read_events(&mut self, timeout: Option<Duration>) -> Result<(), TransportError> {
        let mut asked_to_acknowledge = false;
        let mut on_event = |activation: EventActivation| {
            asked_to_acknowledge |= activation.id == ACK_REQUEST_EVENT
        };
        let waited = match timeout {
            Some(timeout) => self.listener.timed_wait(&mut on_event, timeout),
            None => self.listener.try_wait(&mut on_event),
        };
        match waited {
            // A signal (SIGTERM stopping a stage) cut the wait short: a wake-up, not an error;
            // the stage's loop sees its stop flag next.
            Ok(_) | Err(::iceoryx2::port::listener::ListenerWaitError::InterruptSignal) => {}
            Err(error) => {
                return Err(self.receive_error(format!("waiting for a message: {error}")));
            }
        }
        self.last_event_check = Instant::now();
        if asked_to_acknowledge {
            self.acknowledged.clear();
        }
        Ok(())
    }

    /// Attaches to every registered publisher and acknowledges those not acknowledged yet.
    fn acknowledge_new_publishers(&mut self) -> Result<(), TransportError> {
        let mut publishers = Vec::new();
        self.data.dynamic_config().list_publishers(|details| {
            publishers.push(details.publisher_id.value());
            CallbackProgression::Continue
        });
        self.acknowledged.retain(|id| publishers.contains(id));
        if publishers.iter().all(|id| self.acknowledged.contains(id)) {
            return Ok(());
        }
        // Every publisher listed above is registered by now, so this attaches to all of them.
        self.subscriber.update_connections().map_err(|error| {
            self.receive_error(format!("could not attach to the publishers: {error:?}"))
        })?;
        let subscriber = self.subscriber.id().value();
        for publisher in publishers {
            if !self.acknowledged.contains(&publisher) {
                self.ack_publisher
                    .send_copy(Attached {
                        publisher,
                        subscriber,
                    })
                    .map_err(|error| {
                        self.receive_error(format!("could not acknowledge a publisher: {error}"))
                    })?;
                self.acknowledged.insert(publisher);
            }
        }
        Ok(())
    }
}

impl Subscriber for Iceoryx2Subscriber {
    fn topic(&self) -> &str {
        &self.topic
    }

    fn receive(
        &mut self,
        timeout: Duration,
        on_message: &mut dyn FnMut(&[u8]),
    ) -> Result<bool, TransportError> {
        let deadline = Instant::now() + timeout;
        loop {
            if self.last_event_check.elapsed() >= EVENT_CHECK {
                self.read_events(None)?;
            }
            self.acknowledge_new_publishers()?;
            let sample = self
                .subscriber
                .receive()
                .map_err(|error| self.receive_error(format!("{error}")))?;
            if let Some(sample) = sample {
                // The shared-memory sample itself: no copy.
                let bytes: &[u8] = bytemuck::cast_slice(sample.payload());
                let len = usize::try_from(sample.user_header().len).unwrap_or(usize::MAX);
                let Some(message) = bytes.get(..len) else {
                    return Err(self.receive_error(format!(
                        "a sample says it holds {len} bytes but has {}",
                        bytes.len()
                    )));
                };
                on_message(message);
                return Ok(true);
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(false);
            }
            // Wakes at the next notification (or at once for one sent since the drain above).
            self.read_events(Some(deadline - now))?;
        }
    }
}

mod leftovers;

#[cfg(test)]
mod conformance {
    crate::conformance_suite!(|config| Box::new(
        super::Iceoryx2Transport::new(config).expect("iceoryx2 transport")
    ));
}

#[cfg(test)]
mod tests;
