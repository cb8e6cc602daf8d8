//! Network transport between hosts (zenoh): the stages of one pipeline spread over several
//! machines (a ground station and remote flow-worker hosts), and any outside subscriber (Python,
//! C, ROS 2 via zenoh) reading the results as `asgreg/v9/<pipeline>/results/json` (docs/design.md §5).
//!
//! **Topology.** The ground station runs one zenoh *router* (the launcher runs it as a process of
//! its own that calls [`open_router`]; `deploy/zenoh/router.json5` is the same as a file). Every
//! stage process, local or remote, is a zenoh *client* of that router
//! ([`ZenohSettings::default`] connects to `tcp/127.0.0.1:7447`): one well-known endpoint to
//! open in a firewall, one place for TLS and access control, and no discovery at all. Peer mode
//! is supported for small set-ups but every peer then needs explicit `connect`/`listen`
//! endpoints. Scouting is never used: every config built here forces
//! `scouting/multicast/enabled: false` and `scouting/gossip/enabled: false`, even on top of a
//! user's `config_file` (zenoh's defaults multicast to 224.0.0.224 and listen on all interfaces,
//! docs/design.md §7), and listen endpoints on an unspecified address (`0.0.0.0`, `[::]`) are refused:
//! name the interface.
//!
//! **How the contract of `transport` is kept.**
//! - Lossless and ordered: publishers put with [`CongestionControl::Block`] (zenoh's default for
//!   puts is Drop) on reliable links (zenoh 1.10's default reliability; choosing it per publisher
//!   needs zenoh's `unstable` feature, which we do not build). A subscriber is a bounded FIFO of
//!   [`TransportConfig::queue_depth`] samples: when it is full, zenoh's receive task waits in the
//!   callback, the TCP window closes and the publisher's `put` blocks (backpressure, end to end,
//!   through the router).
//! - zenoh closes a link when a blocking send waits longer than `wait_before_close` (zenoh's
//!   default 5 s, shorter than one slow frame): we set it from
//!   [`ZenohSettings::blocked_send_limit_ms`] (router included).
//! - Head-of-line blocking: a full subscriber queue holds one of the process's zenoh receive
//!   threads (two by default) until it is drained. It stalls every subscriber of the same
//!   [`ZenohTransport`] (one session, one TCP link), and two full queues stall every zenoh
//!   subscriber of the process. This is safe as long as each subscriber is drained by a thread
//!   that does not itself wait for another zenoh subscriber of the same process; a stage that must
//!   read a control topic while its data queue is full needs that topic on another transport.
//! - **The router runs in a process of its own** (one that opens no [`ZenohTransport`]): zenoh
//!   forwards a lossless message on one of the process's receive threads and blocks that thread
//!   while the next hop's queue is full. With subscribers in the same process, two such blocked
//!   forwards starve the subscribers' own receive task and nothing moves until zenoh closes the
//!   links after [`ZenohSettings::blocked_send_limit_ms`] (reproduced while writing this: three
//!   slow subscribers of 4 MiB messages deadlocked an in-process router; the tests therefore run
//!   their router as a child process). A router alone in its process only stalls: every flow
//!   through it waits while two consumers are slow. `ZENOH_RUNTIME='(rx: (worker_threads: 4))'`
//!   in the router's environment gives it more receive threads.
//! - The "ready" handshake ([`Publisher::wait_for_subscriber`]) polls the publisher's *matching
//!   status* (stable in zenoh 1.10): true once the router has told this session that a subscriber
//!   of the key exists, so a put made after that reaches it.
//! - Bytes: a received payload is lent as one slice; zenoh copies it only when it arrived in
//!   several pieces (a large, fragmented message).
//!
//! **Links.** `tcp/` and `tls/` endpoints are compiled in (zenoh's `transport_tcp` and
//! `transport_tls` features; rustls with ring, no OpenSSL); other protocols are refused here with
//! a message saying so. TLS with mutual authentication and access control by the certificate's
//! common name: `deploy/zenoh/router-tls.json5`, `client-tls.json5`, `router-tls-acl.json5`
//! (the tests in `tls_tests.rs` run those very files with certificates made in the test).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use ::zenoh::handlers::{FifoChannel, FifoChannelHandler};
use ::zenoh::qos::CongestionControl;
use ::zenoh::sample::Sample;
use ::zenoh::{Config, Session, Wait};
use serde::{Deserialize, Serialize};

use super::{keys, Publisher, Subscriber, Transport, TransportConfig, TransportError};

const BACKEND: &str = "zenoh";

/// Where a client connects when neither its settings nor its config file say: the router on
/// this host.
pub const DEFAULT_ROUTER: &str = "tcp/127.0.0.1:7447";

/// The link protocols this build opens (zenoh features in Cargo.toml).
const COMPILED_LINKS: [&str; 2] = ["tcp", "tls"];

/// How often [`Publisher::wait_for_subscriber`] asks zenoh for the matching status.
const MATCHING_POLL: Duration = Duration::from_millis(2);

/// The role of this process in the zenoh network.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ZenohMode {
    /// Talks to the others directly (every peer needs explicit `listen`/`connect` endpoints).
    Peer,
    /// Connects to a router and talks only through it (the stage processes).
    #[default]
    Client,
    /// Routes between clients and other routers (the ground station).
    Router,
}

impl ZenohMode {
    fn as_str(self) -> &'static str {
        match self {
            Self::Peer => "peer",
            Self::Client => "client",
            Self::Router => "router",
        }
    }
}

/// How a process joins the zenoh network (the `[transport.zenoh]` part of a pipeline config).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ZenohSettings {
    /// `client` (the default: connect to the ground station's router), `peer` or `router`.
    pub mode: ZenohMode,
    /// Endpoints to listen on, e.g. `["tcp/192.168.10.1:7447"]`: explicit interface addresses and
    /// ports (an unspecified address such as `0.0.0.0` is refused). Needed in router mode; unused
    /// in client mode. Omitted (`None`): the `config_file`'s, or none.
    pub listen: Option<Vec<String>>,
    /// Endpoints to connect to, e.g. the router's `["tcp/192.168.10.1:7447"]`. Needed in client
    /// mode. Omitted (`None`): the `config_file`'s, or without a file the router on this host
    /// ([`DEFAULT_ROUTER`]) in client mode and none in the other modes.
    pub connect: Option<Vec<String>>,
    /// A zenoh json5 configuration to start from (TLS, access control, tuning: see
    /// `deploy/zenoh/`). `mode`, `listen`/`connect` when given and `blocked_send_limit_ms` are
    /// applied on top of it, and multicast and gossip scouting are always forced off.
    pub config_file: Option<PathBuf>,
    /// How long one send may stay blocked by a full queue downstream before zenoh gives up and
    /// closes the link, milliseconds (zenoh's `wait_before_close`; its own default of 5 s is
    /// shorter than one slow frame). Must be at least 1.
    pub blocked_send_limit_ms: u64,
}

impl Default for ZenohSettings {
    fn default() -> Self {
        Self {
            mode: ZenohMode::Client,
            listen: None,
            connect: None,
            config_file: None,
            blocked_send_limit_ms: 60_000,
        }
    }
}

fn setup_error(detail: impl Into<String>) -> TransportError {
    TransportError::Setup {
        backend: BACKEND,
        detail: detail.into(),
    }
}

impl ZenohSettings {
    /// Checks the settings (and the `config_file` they start from) without opening anything.
    pub fn validate(&self) -> Result<(), TransportError> {
        self.zenoh_config().map(|_| ())
    }

    /// The zenoh configuration these settings open a session with: `config_file` (or zenoh's
    /// defaults), then our settings, then scouting forced off; checked for endpoints that this
    /// build can open and that name an interface.
    pub fn zenoh_config(&self) -> Result<Config, TransportError> {
        if self.blocked_send_limit_ms == 0 {
            return Err(setup_error(
                "zenoh.blocked_send_limit_ms is 0: set how long a send may wait for a full queue \
                 downstream (e.g. 60000)",
            ));
        }
        let mut config = match &self.config_file {
            Some(path) => Config::from_file(path).map_err(|error| {
                setup_error(format!(
                    "cannot read the zenoh config file {} (zenoh.config_file): {error}",
                    path.display()
                ))
            })?,
            None => Config::default(),
        };
        let source = self
            .config_file
            .as_ref()
            .map(|path| format!(" (config file {})", path.display()))
            .unwrap_or_default();
        let mut set = |key: &str, value: String| {
            config.insert_json5(key, &value).map_err(|error| {
                setup_error(format!(
                    "cannot set zenoh config '{key}' to {value}{source}: {error}"
                ))
            })
        };
        set("mode", json_string(self.mode.as_str()))?;
        // Without a file, empty lists are written too: zenoh's defaults would listen on all
        // interfaces (`tcp/[::]:7447` for a router, `tcp/[::]:0` for a peer).
        let listen = match (&self.listen, &self.config_file) {
            (Some(listen), _) => Some(listen.clone()),
            (None, Some(_)) => None,
            (None, None) => Some(Vec::new()),
        };
        let connect = match (&self.connect, &self.config_file) {
            (Some(connect), _) => Some(connect.clone()),
            (None, Some(_)) => None,
            (None, None) if self.mode == ZenohMode::Client => Some(vec![DEFAULT_ROUTER.into()]),
            (None, None) => Some(Vec::new()),
        };
        if let Some(listen) = listen {
            set("listen/endpoints", json_list(&listen))?;
        }
        if let Some(connect) = connect {
            set("connect/endpoints", json_list(&connect))?;
        }
        set("scouting/multicast/enabled", "false".to_string())?;
        set("scouting/gossip/enabled", "false".to_string())?;
        set(
            "transport/link/tx/queue/congestion_control/block/wait_before_close",
            (self.blocked_send_limit_ms.saturating_mul(1000)).to_string(),
        )?;
        check_endpoints(&config, self.mode, &source)?;
        Ok(config)
    }
}

fn json_string(text: &str) -> String {
    serde_json::Value::String(text.to_string()).to_string()
}

fn json_list(items: &[String]) -> String {
    serde_json::Value::from(items.to_vec()).to_string()
}

/// The endpoints of `key` (`listen/endpoints` or `connect/endpoints`) that apply in `mode`.
fn endpoints_for_mode(
    config: &Config,
    key: &str,
    mode: ZenohMode,
) -> Result<Vec<String>, TransportError> {
    let text = config
        .get_json(key)
        .map_err(|error| setup_error(format!("cannot read zenoh config '{key}': {error}")))?;
    let value: serde_json::Value = serde_json::from_str(&text)
        .map_err(|error| setup_error(format!("zenoh config '{key}' is not JSON: {error}")))?;
    // A mode-dependent value is an object {router: [...], peer: [...], client: [...]}.
    let list = match &value {
        serde_json::Value::Object(by_mode) => by_mode
            .get(mode.as_str())
            .cloned()
            .unwrap_or(serde_json::Value::Null),
        other => other.clone(),
    };
    let mut endpoints = Vec::new();
    for item in list.as_array().into_iter().flatten() {
        match item {
            serde_json::Value::String(endpoint) => endpoints.push(endpoint.clone()),
            // `connect` also takes {strategy, locators: [...]} groups.
            serde_json::Value::Object(group) => endpoints.extend(
                group
                    .get("locators")
                    .and_then(|locators| locators.as_array())
                    .into_iter()
                    .flatten()
                    .filter_map(|locator| locator.as_str().map(str::to_string)),
            ),
            _ => {}
        }
    }
    Ok(endpoints)
}

/// Refuses what this build cannot open or what would listen on every interface, and a mode
/// without the endpoints it needs.
fn check_endpoints(config: &Config, mode: ZenohMode, source: &str) -> Result<(), TransportError> {
    let listen = endpoints_for_mode(config, "listen/endpoints", mode)?;
    let connect = endpoints_for_mode(config, "connect/endpoints", mode)?;
    for endpoint in listen.iter().chain(&connect) {
        let protocol = endpoint.split('/').next().unwrap_or_default();
        if !COMPILED_LINKS.contains(&protocol) {
            return Err(setup_error(format!(
                "endpoint '{endpoint}'{source}: this build of asgreg has zenoh's TCP and TLS \
                 transports only; '{protocol}/' needs zenoh's transport_{protocol} feature \
                 (Cargo.toml), or use a tcp/<address>:<port> or tls/<address>:<port> endpoint"
            )));
        }
    }
    for endpoint in &listen {
        let address = endpoint
            .split_once('/')
            .map(|(_, rest)| rest)
            .unwrap_or_default();
        let address = address.split(['?', '#']).next().unwrap_or_default();
        if let Ok(socket) = address.parse::<std::net::SocketAddr>() {
            if socket.ip().is_unspecified() {
                return Err(setup_error(format!(
                    "listen endpoint '{endpoint}'{source} listens on every interface: name the \
                     interface's address instead (e.g. tcp/192.168.10.1:7447, or \
                     tcp/127.0.0.1:7447 for this host only)"
                )));
            }
        }
    }
    match mode {
        ZenohMode::Client if connect.is_empty() => Err(setup_error(format!(
            "client mode without a router to connect to{source}: set zenoh.connect to the \
             router's endpoint, e.g. [\"tcp/127.0.0.1:7447\"]"
        ))),
        ZenohMode::Peer if connect.is_empty() && listen.is_empty() => Err(setup_error(format!(
            "peer mode with neither listen nor connect endpoints{source}: set zenoh.connect to \
             the other peers' (or a router's) endpoints and/or zenoh.listen to this host's, e.g. \
             [\"tcp/192.168.10.2:7447\"] (scouting is off, so nothing is found by itself)"
        ))),
        ZenohMode::Router if listen.is_empty() => Err(setup_error(format!(
            "router mode without listen endpoints{source}: set zenoh.listen to the interface the \
             stages connect to, e.g. [\"tcp/192.168.10.1:7447\"]"
        ))),
        _ => Ok(()),
    }
}

fn open_session(settings: &ZenohSettings) -> Result<(Session, Config), TransportError> {
    let config = settings.zenoh_config()?;
    let listen = endpoints_for_mode(&config, "listen/endpoints", settings.mode)?;
    let connect = endpoints_for_mode(&config, "connect/endpoints", settings.mode)?;
    let session = ::zenoh::open(config.clone()).wait().map_err(|error| {
        let hint = match settings.mode {
            ZenohMode::Client if connect.iter().any(|e| e.starts_with("tls/")) => format!(
                "is the router running and reachable at {connect:?} (zenoh.connect), does this \
                 host's certificate (transport/link/tls/connect_certificate) come from the CA \
                 the router trusts, and does the router's certificate, signed by \
                 root_ca_certificate, name the address connected to?"
            ),
            ZenohMode::Client => {
                format!("is the router running and reachable at {connect:?} (zenoh.connect)?")
            }
            ZenohMode::Peer | ZenohMode::Router => format!(
                "are the listen endpoints {listen:?} this host's own addresses and their ports \
                 free (zenoh.listen)?"
            ),
        };
        setup_error(format!(
            "cannot open a {} session: {error}; {hint}",
            settings.mode.as_str()
        ))
    })?;
    Ok((session, config))
}

/// The network bus of one process: one zenoh session, shared (it is `Send + Sync`) by every
/// stage thread of the process.
pub struct ZenohTransport {
    config: TransportConfig,
    session: Session,
    zenoh_config: Config,
}

impl ZenohTransport {
    /// Opens the session described by `settings` (in client mode, fails at once when the router
    /// cannot be reached).
    pub fn new(config: TransportConfig, settings: &ZenohSettings) -> Result<Self, TransportError> {
        let (session, zenoh_config) = open_session(settings)?;
        Ok(Self {
            config,
            session,
            zenoh_config,
        })
    }

    /// The zenoh configuration the session was opened with (as handed to `zenoh::open`).
    pub fn zenoh_config(&self) -> &Config {
        &self.zenoh_config
    }

    fn key(&self, topic: &str) -> String {
        keys::key(&self.config.pipeline, topic)
    }
}

impl Transport for ZenohTransport {
    fn backend(&self) -> &'static str {
        BACKEND
    }

    fn publisher(&self, topic: &str) -> Result<Box<dyn Publisher>, TransportError> {
        let key = self.key(topic);
        let publisher = self
            .session
            .declare_publisher(key.clone())
            .congestion_control(CongestionControl::Block)
            .wait()
            .map_err(|error| TransportError::OpenPublisher {
                backend: BACKEND,
                topic: topic.to_string(),
                detail: format!(
                    "key '{key}': {error} (a pipeline name must not contain '*', '$', '?' or '#')"
                ),
            })?;
        Ok(Box::new(ZenohPublisher {
            topic: topic.to_string(),
            publisher,
            max_message_bytes: self.config.max_message_bytes,
            _session: self.session.clone(),
        }))
    }

    fn subscriber(&self, topic: &str) -> Result<Box<dyn Subscriber>, TransportError> {
        let key = self.key(topic);
        let subscriber = self
            .session
            .declare_subscriber(key.clone())
            .with(FifoChannel::new(self.config.queue_depth.max(1)))
            .wait()
            .map_err(|error| TransportError::OpenSubscriber {
                backend: BACKEND,
                topic: topic.to_string(),
                detail: format!(
                    "key '{key}': {error} (a pipeline name must not contain '*', '$', '?' or '#')"
                ),
            })?;
        Ok(Box::new(ZenohSubscriber {
            topic: topic.to_string(),
            subscriber,
            _session: self.session.clone(),
        }))
    }
}

struct ZenohPublisher {
    topic: String,
    publisher: ::zenoh::pubsub::Publisher<'static>,
    max_message_bytes: usize,
    /// Keeps the session open as long as the publisher lives.
    _session: Session,
}

impl Publisher for ZenohPublisher {
    fn topic(&self) -> &str {
        &self.topic
    }

    fn send_with(
        &mut self,
        len: usize,
        write: &mut dyn FnMut(&mut [u8]),
    ) -> Result<(), TransportError> {
        super::check_message_size(BACKEND, &self.topic, len, self.max_message_bytes)?;
        let mut message = vec![0u8; len];
        write(&mut message);
        // The Vec becomes the payload without a copy.
        self.publisher
            .put(message)
            .wait()
            .map_err(|error| TransportError::Send {
                backend: BACKEND,
                topic: self.topic.clone(),
                detail: format!(
                    "key '{}': {error} (the session is closed or its link to the router broke)",
                    self.publisher.key_expr()
                ),
            })
    }

    fn wait_for_subscriber(&mut self, timeout: Duration) -> Result<bool, TransportError> {
        let deadline = Instant::now() + timeout;
        loop {
            let status =
                self.publisher
                    .matching_status()
                    .wait()
                    .map_err(|error| TransportError::Send {
                        backend: BACKEND,
                        topic: self.topic.clone(),
                        detail: format!(
                            "key '{}': cannot read the matching status: {error}",
                            self.publisher.key_expr()
                        ),
                    })?;
            if status.matching() {
                return Ok(true);
            }
            if Instant::now() >= deadline {
                return Ok(false);
            }
            std::thread::sleep(MATCHING_POLL);
        }
    }
}

struct ZenohSubscriber {
    topic: String,
    subscriber: ::zenoh::pubsub::Subscriber<FifoChannelHandler<Sample>>,
    /// Keeps the session open as long as the subscriber lives.
    _session: Session,
}

impl Subscriber for ZenohSubscriber {
    fn topic(&self) -> &str {
        &self.topic
    }

    fn receive(
        &mut self,
        timeout: Duration,
        on_message: &mut dyn FnMut(&[u8]),
    ) -> Result<bool, TransportError> {
        match self.subscriber.recv_timeout(timeout) {
            Ok(Some(sample)) => {
                on_message(&sample.payload().to_bytes());
                Ok(true)
            }
            Ok(None) => Ok(false),
            Err(error) => Err(TransportError::Receive {
                backend: BACKEND,
                topic: self.topic.clone(),
                detail: format!(
                    "key '{}': {error} (the zenoh session was closed)",
                    self.subscriber.key_expr()
                ),
            }),
        }
    }
}

/// A zenoh router running inside this process (the ground station's); it routes until dropped.
/// Open it in a process that opens no [`ZenohTransport`] (see the module comment: a router and
/// slow subscribers in one process can deadlock).
pub struct RouterHandle {
    session: Session,
    zenoh_config: Config,
}

impl RouterHandle {
    /// Opens a router from `settings` (`mode` must be `router`; e.g. with
    /// `config_file = deploy/zenoh/access-control.json5`).
    pub fn open(settings: &ZenohSettings) -> Result<Self, TransportError> {
        if settings.mode != ZenohMode::Router {
            return Err(setup_error(format!(
                "a router needs zenoh.mode = \"router\", not \"{}\"",
                settings.mode.as_str()
            )));
        }
        let (session, zenoh_config) = open_session(settings)?;
        Ok(Self {
            session,
            zenoh_config,
        })
    }

    /// The zenoh configuration the router was opened with.
    pub fn zenoh_config(&self) -> &Config {
        &self.zenoh_config
    }

    /// Stops routing now (dropping the handle does the same).
    pub fn close(self) -> Result<(), TransportError> {
        self.session
            .close()
            .wait()
            .map_err(|error| setup_error(format!("closing the router failed: {error}")))
    }
}

/// Opens a router listening on `listen` (explicit endpoints such as `tcp/192.168.10.1:7447`),
/// with scouting off and the default [`ZenohSettings::blocked_send_limit_ms`]. Call it in a
/// process of its own (the launcher's router process), not next to zenoh stages.
pub fn open_router(listen: &[String]) -> Result<RouterHandle, TransportError> {
    RouterHandle::open(&ZenohSettings {
        mode: ZenohMode::Router,
        listen: Some(listen.to_vec()),
        connect: None,
        ..ZenohSettings::default()
    })
}

#[cfg(test)]
mod tests {
    use std::io::{BufRead, BufReader, Read};
    use std::path::Path;
    use std::process::{Command, Stdio};
    use std::sync::OnceLock;

    use super::*;

    /// A port on 127.0.0.1 that was free a moment ago.
    pub(super) fn free_port() -> u16 {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind 127.0.0.1:0");
        listener.local_addr().expect("local address").port()
    }

    const ROUTER_PROCESS_ENV: &str = "ASGREG_TEST_ZENOH_ROUTER_LISTEN";

    /// The router of this test process's tests: a child process (this test binary running
    /// [`router_process`]) listening on a free loopback port; it exits when this process does.
    ///
    /// Not in-process: zenoh forwards a lossless message on one of the process's two receive
    /// threads and blocks that thread while the next hop's queue is full. With the router in the
    /// same process as the subscribers, two such blocked forwards starve the subscribers' own
    /// receive task: a deadlock (seen here with three slow subscribers of 4 MiB messages).
    pub(super) fn shared_router_endpoint() -> &'static str {
        static ROUTER: OnceLock<(std::process::Child, String)> = OnceLock::new();
        &ROUTER
            .get_or_init(|| {
                let endpoint = format!("tcp/127.0.0.1:{}", free_port());
                let mut child = Command::new(std::env::current_exe().expect("test binary"))
                    .args([
                        "--exact",
                        "transport::zenoh::tests::router_process",
                        "--ignored",
                        "--nocapture",
                        "--test-threads=1",
                    ])
                    .env(ROUTER_PROCESS_ENV, &endpoint)
                    // The child reads its stdin until this process ends and closes it.
                    .stdin(Stdio::piped())
                    .stdout(Stdio::piped())
                    .spawn()
                    .expect("start the router process");
                let stdout = child.stdout.take().expect("router stdout");
                let ready = BufReader::new(stdout)
                    .lines()
                    .map_while(Result::ok)
                    .any(|line| line.ends_with("router ready"));
                assert!(
                    ready,
                    "the router process did not start (its stderr is above)"
                );
                (child, endpoint)
            })
            .1
    }

    /// Not a test: the router process of [`shared_router_endpoint`] (does nothing without it).
    #[test]
    #[ignore = "helper: the zenoh tests' router process"]
    fn router_process() {
        let Ok(endpoint) = std::env::var(ROUTER_PROCESS_ENV) else {
            return;
        };
        let router = open_router(&[endpoint]).expect("open router");
        println!("router ready");
        let _ = std::io::stdin().read_to_end(&mut Vec::new());
        router.close().expect("close router");
        // Before the harness prints its summary into the parent's closed pipe.
        std::process::exit(0);
    }

    #[test]
    fn slow_subscribers_on_several_flows_do_not_deadlock() {
        let endpoint = shared_router_endpoint();
        std::thread::scope(|scope| {
            for flow in 0..3 {
                scope.spawn(move || {
                    let mut config = crate::transport::conformance::config("several-slow");
                    config.queue_depth = 1;
                    let subscribers =
                        ZenohTransport::new(config.clone(), &client_settings(endpoint)).unwrap();
                    let publishers =
                        ZenohTransport::new(config, &client_settings(endpoint)).unwrap();
                    let mut subscriber = subscribers.subscriber("slow").unwrap();
                    std::thread::scope(|inner| {
                        inner.spawn(|| {
                            let mut publisher = publishers.publisher("slow").unwrap();
                            assert!(publisher
                                .wait_for_subscriber(Duration::from_secs(10))
                                .unwrap());
                            for index in 0..8u8 {
                                publisher
                                    .send_with(4 << 20, &mut |buffer| buffer[0] = index)
                                    .unwrap();
                            }
                        });
                        // Every queue on the way fills while the subscriber sleeps.
                        std::thread::sleep(Duration::from_millis(500));
                        for index in 0..8u8 {
                            let mut first = None;
                            let got = subscriber
                                .receive(Duration::from_secs(20), &mut |bytes| {
                                    first = Some(bytes[0])
                                })
                                .unwrap();
                            assert!(got, "flow {flow}: message {index} stuck for 20 s");
                            assert_eq!(first, Some(index), "flow {flow}");
                        }
                    });
                });
            }
        });
    }

    pub(super) fn client_settings(endpoint: &str) -> ZenohSettings {
        ZenohSettings {
            mode: ZenohMode::Client,
            connect: Some(vec![endpoint.to_string()]),
            ..ZenohSettings::default()
        }
    }

    fn get(config: &Config, key: &str) -> String {
        config.get_json(key).expect(key)
    }

    #[test]
    fn sessions_are_opened_with_scouting_off_and_explicit_endpoints() {
        let endpoint = shared_router_endpoint();
        let transport = ZenohTransport::new(
            crate::transport::conformance::config("scouting"),
            &client_settings(endpoint),
        )
        .expect("client");
        for config in [
            transport.zenoh_config(),
            &ZenohSettings::default().zenoh_config().unwrap(),
        ] {
            assert_eq!(get(config, "scouting/multicast/enabled"), "false");
            assert_eq!(get(config, "scouting/gossip/enabled"), "false");
            assert_eq!(get(config, "mode"), "\"client\"");
            assert_eq!(get(config, "listen/endpoints"), "[]");
        }
        assert_eq!(
            get(transport.zenoh_config(), "connect/endpoints"),
            format!("[\"{endpoint}\"]")
        );
        assert_eq!(
            get(
                transport.zenoh_config(),
                "transport/link/tx/queue/congestion_control/block/wait_before_close"
            ),
            "60000000"
        );
        let router = open_router(&[format!("tcp/127.0.0.1:{}", free_port())]).expect("router");
        assert_eq!(
            get(router.zenoh_config(), "scouting/multicast/enabled"),
            "false"
        );
        assert_eq!(
            get(router.zenoh_config(), "scouting/gossip/enabled"),
            "false"
        );
        router.close().expect("close");
    }

    #[test]
    fn settings_without_endpoints_or_on_every_interface_are_refused() {
        let client = ZenohSettings {
            connect: Some(Vec::new()),
            ..ZenohSettings::default()
        };
        let error = client.validate().unwrap_err().to_string();
        assert!(error.contains("zenoh.connect"), "{error}");
        let peer = ZenohSettings {
            mode: ZenohMode::Peer,
            connect: None,
            ..ZenohSettings::default()
        };
        let error = peer.validate().unwrap_err().to_string();
        assert!(error.contains("zenoh.listen"), "{error}");
        let error = open_router(&[])
            .err()
            .expect("router without listen")
            .to_string();
        assert!(error.contains("zenoh.listen"), "{error}");
        let error = open_router(&["tcp/0.0.0.0:7447".to_string()])
            .err()
            .expect("router on every interface")
            .to_string();
        assert!(error.contains("every interface"), "{error}");
        let tls = ZenohSettings {
            connect: Some(vec!["tls/127.0.0.1:7447".to_string()]),
            ..ZenohSettings::default()
        };
        tls.validate().expect("tls/ is compiled in");
        let quic = ZenohSettings {
            connect: Some(vec!["quic/127.0.0.1:7447".to_string()]),
            ..ZenohSettings::default()
        };
        let error = quic.validate().unwrap_err().to_string();
        assert!(error.contains("transport_quic"), "{error}");
        let unknown: Result<ZenohSettings, _> = toml::from_str("mode = \"client\"\nlisen = []");
        assert!(unknown.is_err());
        let parsed: ZenohSettings =
            toml::from_str("mode = \"peer\"\nlisten = [\"tcp/127.0.0.1:7450\"]\nconnect = []")
                .expect("settings");
        assert_eq!(parsed.mode, ZenohMode::Peer);
        parsed.validate().expect("peer listening on loopback");
    }

    #[test]
    fn omitted_endpoints_come_from_the_file_or_the_local_router() {
        let default = ZenohSettings::default().zenoh_config().expect("default");
        assert_eq!(
            get(&default, "connect/endpoints"),
            format!("[\"{DEFAULT_ROUTER}\"]")
        );
        let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/zenoh/peer-remote.json5");
        let from_file: ZenohSettings =
            toml::from_str(&format!("config_file = {:?}", file.display().to_string()))
                .expect("settings");
        let config = from_file.zenoh_config().expect("peer-remote.json5");
        assert_eq!(
            get(&config, "connect/endpoints"),
            "[\"tcp/192.168.10.1:7447\"]"
        );
        assert_eq!(get(&config, "scouting/multicast/enabled"), "false");
    }

    #[test]
    fn a_client_without_router_fails_with_a_hint() {
        let settings = client_settings(&format!("tcp/127.0.0.1:{}", free_port()));
        let error = ZenohTransport::new(TransportConfig::default(), &settings)
            .err()
            .expect("no router there")
            .to_string();
        assert!(error.contains("is the router running"), "{error}");
    }

    #[test]
    fn one_session_delivers_to_its_own_subscribers() {
        let transport = ZenohTransport::new(
            crate::transport::conformance::config("local"),
            &client_settings(shared_router_endpoint()),
        )
        .expect("client");
        let mut subscriber = transport.subscriber("local").expect("subscriber");
        let mut publisher = transport.publisher("local").expect("publisher");
        assert!(publisher
            .wait_for_subscriber(Duration::from_secs(10))
            .unwrap());
        publisher.send(b"same session").expect("send");
        let mut got = Vec::new();
        assert!(subscriber
            .receive(Duration::from_secs(10), &mut |bytes| got = bytes.to_vec())
            .unwrap());
        assert_eq!(got, b"same session");
    }

    /// A measured figure, not a check: session set-up and 4 MiB messages through the router.
    #[test]
    fn four_mib_messages_cross_the_router() {
        let endpoint = shared_router_endpoint();
        let started = Instant::now();
        let config = crate::transport::conformance::config("throughput");
        let subscriber_side =
            ZenohTransport::new(config.clone(), &client_settings(endpoint)).expect("client");
        let publisher_side =
            ZenohTransport::new(config, &client_settings(endpoint)).expect("client");
        let clients_s = started.elapsed().as_secs_f64();
        let mut subscriber = subscriber_side.subscriber("big").expect("subscriber");
        const COUNT: usize = 20;
        const BYTES: usize = 4 << 20;
        let received = std::thread::scope(|scope| {
            scope.spawn(|| {
                let mut publisher = publisher_side.publisher("big").expect("publisher");
                assert!(publisher
                    .wait_for_subscriber(Duration::from_secs(10))
                    .unwrap());
                for index in 0..COUNT {
                    publisher
                        .send_with(BYTES, &mut |buffer| buffer[0] = index as u8)
                        .expect("send");
                }
            });
            let mut first: Option<Instant> = None;
            let mut received = 0;
            while received < COUNT {
                assert!(subscriber
                    .receive(Duration::from_secs(10), &mut |bytes| {
                        assert_eq!((bytes.len(), bytes[0]), (BYTES, received as u8));
                    })
                    .unwrap());
                first.get_or_insert_with(Instant::now);
                received += 1;
            }
            (received, first.map(|first| first.elapsed()))
        });
        let (count, after_first) = received;
        let after_first = after_first.expect("received").as_secs_f64();
        println!(
            "zenoh over TCP loopback via a router process: two clients opened in \
             {clients_s:.3} s, {count} x 4 MiB: {:.0} msg/s after the first",
            (count - 1) as f64 / after_first
        );
    }

    fn deploy_files() -> Vec<std::path::PathBuf> {
        let folder = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/zenoh");
        let mut files: Vec<_> = std::fs::read_dir(&folder)
            .expect("deploy/zenoh")
            .map(|entry| entry.expect("entry").path())
            .filter(|path| path.extension().is_some_and(|ext| ext == "json5"))
            .collect();
        files.sort();
        files
    }

    #[test]
    fn shipped_configs_parse_and_keep_scouting_off() {
        let files = deploy_files();
        assert!(files.len() >= 5, "deploy/zenoh has {files:?}");
        for path in &files {
            let name = path.file_name().unwrap().to_string_lossy().to_string();
            let config = Config::from_file(path).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(
                get(&config, "scouting/multicast/enabled"),
                "false",
                "{name}"
            );
            assert_eq!(get(&config, "scouting/gossip/enabled"), "false", "{name}");
            let settings = ZenohSettings {
                mode: serde_json::from_str(&get(&config, "mode")).expect("mode"),
                listen: None,
                connect: None,
                config_file: Some(path.clone()),
                ..ZenohSettings::default()
            };
            settings
                .validate()
                .unwrap_or_else(|e| panic!("{name}: {e}"));
        }
    }

    #[test]
    fn shipped_access_control_lets_pipeline_keys_through_only() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/zenoh/access-control.json5");
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        // The file's listen endpoint is a placeholder address; the test listens on loopback,
        // which the file's "ground-station" subject (interface lo) covers.
        let router = RouterHandle::open(&ZenohSettings {
            mode: ZenohMode::Router,
            listen: Some(vec![endpoint.clone()]),
            connect: None,
            config_file: Some(path),
            ..ZenohSettings::default()
        })
        .expect("router with the shipped access control");
        let subscriber_side = ZenohTransport::new(
            crate::transport::conformance::config("acl"),
            &client_settings(&endpoint),
        )
        .expect("client");
        let publisher_side =
            ZenohTransport::new(subscriber_side.config.clone(), &client_settings(&endpoint))
                .expect("client");
        let mut allowed = subscriber_side.subscriber("results").expect("subscriber");
        let mut publisher = publisher_side.publisher("results").expect("publisher");
        assert!(publisher
            .wait_for_subscriber(Duration::from_secs(10))
            .unwrap());
        publisher.send(b"allowed").expect("send");
        assert!(allowed
            .receive(Duration::from_secs(10), &mut |bytes| assert_eq!(
                bytes,
                b"allowed"
            ))
            .unwrap());
        // A key outside asgreg/v9/** is not routed.
        let outside = subscriber_side
            .session
            .declare_subscriber("other/results")
            .with(FifoChannel::new(4))
            .wait()
            .expect("subscriber outside");
        let other = publisher_side
            .session
            .declare_publisher("other/results")
            .wait()
            .expect("publisher outside");
        std::thread::sleep(Duration::from_millis(300));
        assert!(!other.matching_status().wait().unwrap().matching());
        other.put("denied").wait().expect("put");
        assert!(outside
            .recv_timeout(Duration::from_millis(300))
            .unwrap()
            .is_none());
        drop((outside, other, allowed, publisher));
        router.close().expect("close");
    }

    #[test]
    #[ignore = "needs python3 with eclipse-zenoh (.ci/run installs it)"]
    fn python_subscriber_prints_published_results_and_the_change_set() {
        let python_has_zenoh = Command::new("python3")
            .args(["-c", "import zenoh"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|status| status.success());
        assert!(
            python_has_zenoh,
            "python3 cannot import zenoh: pip install eclipse-zenoh==1.10.2 (this test is \
             #[ignore]d because it needs that package)"
        );
        let endpoint = shared_router_endpoint();
        let config = crate::transport::conformance::config("python");
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/subscribe.py");
        let out_dir = tempfile::tempdir().expect("temporary folder");
        let geojson_path = out_dir.path().join("changes.geojson");
        let mut child = Command::new("python3")
            .arg(&script)
            .args([
                "--connect",
                endpoint,
                "--pipeline",
                &config.pipeline,
                "--count",
                "2",
                "--until-change-set",
                "--changes-out",
            ])
            .arg(&geojson_path)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start python3");
        let transport = ZenohTransport::new(config, &client_settings(endpoint)).expect("client");
        let mut publisher = transport.publisher(keys::RESULTS_JSON).expect("publisher");
        let subscribed = publisher
            .wait_for_subscriber(Duration::from_secs(30))
            .unwrap();
        if !subscribed {
            let _ = child.kill();
        }
        assert!(
            subscribed,
            "the Python subscriber did not subscribe within 30 s"
        );
        for (index, name) in ["frame_0001.jpg", "frame_0002.jpg"].into_iter().enumerate() {
            let header = crate::msg::Header {
                frame_id: index as u64,
                sequence: index as u64,
                capture_time_ns: 1_700_000_000_000_000_000,
                sent_time_ns: 1_700_000_000_500_000_000,
            };
            let result = crate::msg::PoseResult {
                frame_id: index as u64,
                name: name.to_string(),
                accepted: index == 0,
                failure: (index == 1).then(|| "verify: too few inliers".to_string()),
                confidence: 0.93 - index as f64 * 0.5,
                camera: None,
                cam_from_world: (index == 0).then_some(crate::msg::PoseNumbers {
                    qvec_wxyz: [1.0, 0.0, 0.0, 0.0],
                    tvec_m: [1.5, -2.0, 310.25],
                }),
                evidence: Default::default(),
                times: Default::default(),
                flow_workers: vec![0, 1],
            };
            publisher
                .send(crate::msg::pose_result_json(&header, &result).as_bytes())
                .expect("send");
        }
        // The change stream: one frame's change result and the final fused set.
        let header = crate::msg::Header::default();
        let region = crate::core::change::ChangeRegion {
            kind: crate::core::change::ChangeKind::Added,
            pixel_count: 120,
            surface_area_m2: 40.0,
            footprint_area_m2: 16.0,
            height_m: 6.0,
            vertical_extent_m: 6.0,
            footprint_width_m: 4.0,
            footprint_length_m: 4.0,
            depth_difference_m: -6.0,
            centroid_m: [2.0, 2.0, 3.0],
            footprint_m: vec![[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]],
            confidence: 0.9,
            bbox_px: [1, 2, 30, 40],
        };
        let change = crate::msg::ChangeResult {
            frame_id: 0,
            name: "frame_0001.jpg".to_string(),
            failure: None,
            counts: Default::default(),
            regions: vec![region.clone()],
            change_ms: 4.5,
            change_worker: Some(0),
        };
        let set = crate::msg::ChangeSet {
            complete: true,
            frame_count: Some(2),
            frames_with_result: 2,
            frames_with_map: 1,
            objects: crate::core::change::fusion::fuse_regions(
                &[(0, &region)],
                &Default::default(),
            ),
            fusion: Default::default(),
            // As fusion's free-space test reports an `added` object three frames see through.
            free_space: vec![crate::core::change::free_space::FreeSpaceCheck {
                object: 0,
                centroid_m: region.centroid_m,
                seen_through_by: vec![1, 2, 3],
                agreed_by: vec![0],
                refuted: true,
            }],
        };
        // The final set first: the two keys are not ordered with each other, so a subscriber
        // that stops at the final set must still take the change results on their way (a CI run
        // lost the change line when the set overtook it).
        for (topic, text) in [
            (
                keys::CHANGE_SET_JSON,
                crate::msg::change_set_json(&header, &set),
            ),
            (
                keys::CHANGES_JSON,
                crate::msg::change_result_json(&header, &change),
            ),
        ] {
            let mut publisher = transport.publisher(topic).expect("publisher");
            assert!(publisher
                .wait_for_subscriber(Duration::from_secs(30))
                .unwrap());
            publisher.send(text.as_bytes()).expect("send");
        }
        let deadline = Instant::now() + Duration::from_secs(30);
        let status = loop {
            if let Some(status) = child.try_wait().expect("wait python") {
                break status;
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                panic!("the Python subscriber did not exit within 30 s");
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let mut stdout = String::new();
        let mut stderr = String::new();
        child
            .stdout
            .take()
            .unwrap()
            .read_to_string(&mut stdout)
            .unwrap();
        child
            .stderr
            .take()
            .unwrap()
            .read_to_string(&mut stderr)
            .unwrap();
        assert!(status.success(), "python: {status}\n{stdout}\n{stderr}");
        assert!(stdout.contains("frame_0001.jpg"), "{stdout}");
        assert!(stdout.contains("frame_0002.jpg"), "{stdout}");
        assert!(stdout.contains("1 change regions"), "{stdout}");
        assert!(
            stdout.contains("change set (final): 1 objects, 0 confirmed"),
            "{stdout}"
        );
        assert!(
            stdout.contains("free space: seen through by frames [1, 2, 3], agreed by [0], refuted"),
            "{stdout}"
        );
        let geojson: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(&geojson_path).expect("the GeoJSON the subscriber wrote"),
        )
        .expect("GeoJSON");
        assert_eq!(geojson["features"].as_array().map(Vec::len), Some(1));
        assert_eq!(geojson["features"][0]["properties"]["refuted"], true);
        assert_eq!(
            geojson["features"][0]["properties"]["seen_through_by"],
            serde_json::json!([1, 2, 3])
        );
        println!("{stdout}");
    }
}

/// The conformance suite over TCP loopback: publishers come from one client session and
/// subscribers from another, both connected to this process's router, so every message goes
/// client → router → client through the network stack.
#[cfg(test)]
mod conformance {
    use super::tests::{client_settings, shared_router_endpoint};
    use super::*;

    struct AcrossRouter {
        publishers: ZenohTransport,
        subscribers: ZenohTransport,
    }

    impl Transport for AcrossRouter {
        fn backend(&self) -> &'static str {
            BACKEND
        }
        fn publisher(&self, topic: &str) -> Result<Box<dyn Publisher>, TransportError> {
            self.publishers.publisher(topic)
        }
        fn subscriber(&self, topic: &str) -> Result<Box<dyn Subscriber>, TransportError> {
            self.subscribers.subscriber(topic)
        }
    }

    fn across_router(config: TransportConfig) -> AcrossRouter {
        let settings = client_settings(shared_router_endpoint());
        AcrossRouter {
            publishers: ZenohTransport::new(config.clone(), &settings).expect("publisher side"),
            subscribers: ZenohTransport::new(config, &settings).expect("subscriber side"),
        }
    }

    crate::conformance_suite!(|config| Box::new(across_router(config)));
}
