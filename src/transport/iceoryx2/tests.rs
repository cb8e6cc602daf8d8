//! What the conformance suite cannot see of the iceoryx2 backend: zero-copy alignment, the attach
//! handshake that works around iceoryx2's silent drops, publishers that leave early, and dead
//! processes (a child process of this test binary that is SIGKILLed).

use std::borrow::Cow;
use std::io::{BufRead, BufReader};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

use ::iceoryx2::config::Config;
use ::iceoryx2::prelude::{FileName, SemanticString};

use super::{clean_stale_resources_with, Iceoryx2Transport};
use crate::core::camera::{Camera, PinholeIntrinsics};
use crate::core::rigid::Rigid3;
use crate::msg::{self, Body, Envelope, Frame, FrameInfo, Header};
use crate::transport::conformance::unique_pipeline;
use crate::transport::{Publisher, Subscriber, Transport, TransportConfig};

const WAIT: Duration = Duration::from_secs(10);

fn small_config(test: &str) -> TransportConfig {
    TransportConfig {
        pipeline: unique_pipeline(test),
        max_message_bytes: 64 << 10,
        queue_depth: 2,
    }
}

fn transport(config: TransportConfig) -> Iceoryx2Transport {
    Iceoryx2Transport::new(config).expect("iceoryx2 transport")
}

/// Receives one message (retrying short waits up to [`WAIT`]) and returns a copy.
fn receive(subscriber: &mut dyn Subscriber) -> Vec<u8> {
    let deadline = Instant::now() + WAIT;
    loop {
        let mut got = None;
        subscriber
            .receive(Duration::from_millis(100), &mut |bytes| {
                got = Some(bytes.to_vec())
            })
            .expect("receive");
        if let Some(bytes) = got {
            return bytes;
        }
        assert!(Instant::now() < deadline, "no message within {WAIT:?}");
    }
}

fn frame_message() -> Vec<u8> {
    let camera = Camera::pinhole(4, 3, PinholeIntrinsics::centered(5.0, 4, 3));
    let message = Envelope {
        header: Header {
            frame_id: 3,
            ..Header::default()
        },
        body: Body::Frame(Frame {
            info: FrameInfo {
                name: "odd-length-name.jpg".to_string(),
                camera_id: 1,
                camera,
                intrinsics_known: true,
                initial_cam_from_world: Rigid3::identity(),
                seed: 5,
            },
            image: Cow::Owned((0..12).map(|i| i as f32).collect()),
            depth_m: Cow::Owned(vec![2.5; 12]),
        }),
    };
    msg::encode(&message).expect("encode").to_vec()
}

#[test]
fn received_bytes_are_8_aligned_and_decode_borrows_them() {
    let transport = transport(small_config("aligned"));
    let mut subscriber = transport.subscriber("a").unwrap();
    let mut publisher = transport.publisher("a").unwrap();
    assert!(publisher.wait_for_subscriber(WAIT).unwrap());
    let frame = frame_message();
    for len in [1usize, 7, 13, 4097] {
        publisher.send(&vec![len as u8; len]).unwrap();
        let deadline = Instant::now() + WAIT;
        let mut checked = false;
        while !checked && Instant::now() < deadline {
            subscriber
                .receive(Duration::from_millis(100), &mut |bytes| {
                    assert_eq!(bytes.len(), len);
                    assert_eq!(bytes.as_ptr() as usize % 8, 0, "payload not 8-byte aligned");
                    checked = true;
                })
                .unwrap();
        }
        assert!(checked, "message of {len} bytes did not arrive");
    }
    publisher
        .send_with(frame.len(), &mut |buffer| buffer.copy_from_slice(&frame))
        .unwrap();
    let deadline = Instant::now() + WAIT;
    let mut checked = false;
    while !checked && Instant::now() < deadline {
        subscriber
            .receive(Duration::from_millis(100), &mut |bytes| {
                assert_eq!(bytes.as_ptr() as usize % 8, 0);
                let decoded = msg::decode(bytes).expect("decode");
                let Body::Frame(frame) = decoded.body else {
                    panic!("wrong kind")
                };
                let Cow::Borrowed(image) = frame.image else {
                    panic!("the image was copied, not borrowed from the sample")
                };
                let start = bytes.as_ptr() as usize;
                let at = image.as_ptr() as usize;
                assert!(at > start && at < start + bytes.len());
                assert_eq!(image[11], 11.0);
                checked = true;
            })
            .unwrap();
    }
    assert!(checked, "the frame did not arrive");
}

/// iceoryx2 0.10 drops a sample silently when the queue of a subscriber that has not attached yet
/// is full; the attach handshake must make the publisher wait instead.
#[test]
fn publisher_after_an_idle_subscriber_loses_nothing() {
    let transport = transport(small_config("idle"));
    let mut subscriber = transport.subscriber("t").unwrap();
    std::thread::scope(|scope| {
        scope.spawn(|| {
            let mut publisher = transport.publisher("t").unwrap();
            assert!(publisher.wait_for_subscriber(WAIT).unwrap());
            for sequence in 0..12u8 {
                publisher.send(&[sequence; 100]).unwrap();
            }
        });
        // The subscriber does not call `receive` while the publisher fills its queue (depth 2).
        std::thread::sleep(Duration::from_millis(300));
        for sequence in 0..12u8 {
            assert_eq!(receive(subscriber.as_mut()), vec![sequence; 100]);
        }
    });
}

/// A publisher that sends fewer messages than the queue holds and goes away before the subscriber
/// has attached: its connection (and messages) must outlive it.
#[test]
fn messages_outlive_a_publisher_that_leaves_at_once() {
    let transport = transport(small_config("leaves"));
    let mut subscriber = transport.subscriber("t").unwrap();
    std::thread::scope(|scope| {
        let sender = scope.spawn(|| {
            let mut publisher = transport.publisher("t").unwrap();
            assert!(publisher.wait_for_subscriber(WAIT).unwrap());
            publisher.send(&[7; 1000]).unwrap();
            // Dropped here: it waits until the subscriber has attached.
        });
        std::thread::sleep(Duration::from_millis(300));
        assert!(
            !sender.is_finished(),
            "the publisher left before the subscriber attached"
        );
        assert_eq!(receive(subscriber.as_mut()), vec![7; 1000]);
    });
}

/// Metrics are sent lossy: a subscriber that never reads (its queue of 2 full, never attached)
/// must not hold the sender up. Before the backend had its own `send_lossy` this waited for ever.
#[test]
fn a_lossy_send_never_waits_for_a_subscriber_that_does_not_read() {
    let config = small_config("lossy");
    let transport = transport(config.clone());
    let mut subscriber = transport.subscriber("m").unwrap();
    let (done, finished) = std::sync::mpsc::channel();
    // Not a scoped thread: a send that waits for ever must fail the test, not hang it.
    let sender = std::thread::spawn(move || {
        let mut publisher = self::transport(config).publisher("m").unwrap();
        assert!(publisher.wait_for_subscriber(WAIT).unwrap());
        for sequence in 0..20u8 {
            publisher.send_lossy(&[sequence; 64]).unwrap();
        }
        done.send(()).unwrap();
        // A lossless send afterwards still reaches the subscriber once it reads.
        publisher.send(&[99; 64]).unwrap();
    });
    assert!(
        finished.recv_timeout(WAIT).is_ok(),
        "20 lossy sends to a full queue did not return within {WAIT:?}"
    );
    // The queue kept the first messages and dropped the rest; the lossless one comes last.
    let mut got = Vec::new();
    while got.last() != Some(&99) {
        got.push(receive(subscriber.as_mut())[0]);
    }
    assert!(got.len() >= 2 && got.len() < 21, "{got:?}");
    assert!(got.windows(2).all(|pair| pair[0] < pair[1]), "{got:?}");
    sender.join().unwrap();
}

// ---- Dead processes: a child process of this test binary, SIGKILLed. ----

const CHILD_ENV: &str = "ASGREG_IOX2_TEST_CHILD";
const CHILD_TEST: &str = "transport::iceoryx2::tests::child_process";

/// An iceoryx2 configuration whose files carry their own prefix: the nodes and services of one
/// test are invisible to every other test (whose node creation would otherwise clean up the dead
/// node first).
fn isolated(prefix: &str) -> Config {
    let mut config = Config::default();
    config.global.prefix = FileName::new(prefix.as_bytes()).expect("file name prefix");
    config
}

/// A file prefix of one test; dropped last, it removes what is left under it in `/dev/shm`
/// (iceoryx2 keeps a small management segment per prefix).
struct Prefix(String);

impl Prefix {
    fn new(test: &str) -> Self {
        Self(format!("asgt_{test}_{}_", std::process::id()))
    }
}

impl Drop for Prefix {
    fn drop(&mut self) {
        for name in shm_files(&self.0) {
            let _ = std::fs::remove_file(std::path::Path::new("/dev/shm").join(name));
        }
    }
}

/// The child: opens a publisher or a subscriber, says READY, and waits to be killed (it exits on
/// its own after a minute in case the parent failed).
#[test]
fn child_process() {
    let Ok(spec) = std::env::var(CHILD_ENV) else {
        return; // an ordinary test run: nothing to do
    };
    let mut parts = spec.splitn(3, ' ');
    let (role, prefix, pipeline) = (
        parts.next().unwrap().to_string(),
        parts.next().unwrap().to_string(),
        parts.next().unwrap().to_string(),
    );
    let mut config = small_config("child");
    config.pipeline = pipeline;
    let transport = Iceoryx2Transport::with_iceoryx_config(config, isolated(&prefix)).unwrap();
    let mut publisher: Option<Box<dyn Publisher>> = None;
    let mut subscriber: Option<Box<dyn Subscriber>> = None;
    match role.as_str() {
        "publisher" => publisher = Some(transport.publisher("t").unwrap()),
        "subscriber" => subscriber = Some(transport.subscriber("t").unwrap()),
        other => panic!("unknown child role {other}"),
    }
    println!("READY");
    if let Some(subscriber) = subscriber.as_mut() {
        // Take one message, then never again: the queue fills and the publisher blocks.
        receive(subscriber.as_mut());
        println!("RECEIVED");
    }
    let _keep = (publisher, subscriber);
    std::thread::sleep(Duration::from_secs(60));
}

/// Kills the child when dropped (also when the test fails).
struct ChildProcess {
    child: Child,
    stdout: BufReader<ChildStdout>,
}

impl ChildProcess {
    fn spawn(role: &str, prefix: &str, pipeline: &str) -> Self {
        let mut child = Command::new(std::env::current_exe().expect("test binary"))
            .args([CHILD_TEST, "--exact", "--nocapture", "--test-threads=1"])
            .env(CHILD_ENV, format!("{role} {prefix} {pipeline}"))
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn the child process");
        let stdout = BufReader::new(child.stdout.take().expect("child stdout"));
        Self { child, stdout }
    }

    fn wait_for(&mut self, word: &str) {
        let mut line = String::new();
        loop {
            line.clear();
            let read = self.stdout.read_line(&mut line).expect("child output");
            assert!(read > 0, "the child exited before saying {word}");
            // libtest prints "test <name> ... " without a line break before the child's output.
            if line.trim_end().ends_with(word) {
                return;
            }
        }
    }

    fn kill(&mut self) {
        self.child.kill().expect("SIGKILL the child"); // std sends SIGKILL on Unix
        self.child.wait().expect("reap the child");
    }
}

impl Drop for ChildProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn shm_files(prefix: &str) -> Vec<String> {
    std::fs::read_dir("/dev/shm")
        .map(|entries| {
            entries
                .filter_map(|entry| entry.ok())
                .map(|entry| entry.file_name().to_string_lossy().into_owned())
                .filter(|name| name.starts_with(prefix))
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn stale_resources_of_a_killed_process_are_removed() {
    let files = Prefix::new("stale"); // dropped last
    let prefix = files.0.as_str();
    let config = isolated(prefix);
    let mut child = ChildProcess::spawn("publisher", prefix, &unique_pipeline("stale"));
    child.wait_for("READY");
    assert_eq!(
        clean_stale_resources_with(&config).unwrap(),
        0,
        "a live node is not stale"
    );
    let data_segments =
        |files: &[String]| files.iter().filter(|name| name.ends_with(".data")).count();
    assert!(
        data_segments(&shm_files(prefix)) > 0,
        "the child's publisher has a data segment"
    );
    child.kill();
    assert_eq!(
        clean_stale_resources_with(&config).unwrap(),
        1,
        "the child's one node"
    );
    assert_eq!(clean_stale_resources_with(&config).unwrap(), 0);
    let left = shm_files(prefix);
    assert_eq!(
        data_segments(&left),
        0,
        "shared memory left behind: {left:?}"
    );
}

#[test]
fn a_killed_subscriber_releases_a_blocked_publisher() {
    let files = Prefix::new("killed"); // dropped last
    let prefix = files.0.as_str();
    let config = isolated(prefix);
    let pipeline = unique_pipeline("killed");
    let mut child = ChildProcess::spawn("subscriber", prefix, &pipeline);
    child.wait_for("READY");
    let mut transport_config = small_config("killed");
    transport_config.pipeline = pipeline;
    let queue_depth = transport_config.queue_depth;
    let transport = Iceoryx2Transport::with_iceoryx_config(transport_config, config).unwrap();
    let mut publisher = transport.publisher("t").unwrap();
    assert!(publisher.wait_for_subscriber(WAIT).unwrap());
    publisher.send(&[1; 100]).unwrap();
    child.wait_for("RECEIVED");
    child.kill();
    // The queue fills; the next send blocks on the dead subscriber until the publisher removes it.
    let started = Instant::now();
    for _ in 0..queue_depth + 2 {
        publisher.send(&[2; 100]).unwrap();
    }
    let waited = started.elapsed();
    assert!(waited < WAIT, "the publisher stayed blocked for {waited:?}");
    println!("a killed subscriber blocked the publisher for {waited:?}");
}

/// Figures, not checks: `cargo test --lib iceoryx2::tests::timing -- --ignored --nocapture`.
#[test]
#[ignore]
fn timing_of_4_mib_and_small_messages() {
    const MESSAGES: usize = 300;
    const BYTES: usize = 4 << 20;
    const SMALL_MESSAGES: usize = 20_000;
    let transport = transport(TransportConfig {
        pipeline: unique_pipeline("timing"),
        max_message_bytes: 8 << 20,
        queue_depth: 4,
    });
    let mut subscriber = transport.subscriber("t").unwrap();
    let source: Vec<u8> = (0..BYTES).map(|i| (i % 251) as u8).collect();
    for (label, read_all) in [("read fully", true), ("first byte only", false)] {
        let started = Instant::now();
        std::thread::scope(|scope| {
            scope.spawn(|| {
                let mut publisher = transport.publisher("t").unwrap();
                assert!(publisher.wait_for_subscriber(WAIT).unwrap());
                for _ in 0..MESSAGES {
                    publisher.send(&source).unwrap();
                }
            });
            let mut checksum = 0u64;
            for _ in 0..MESSAGES {
                let deadline = Instant::now() + WAIT;
                let mut got = false;
                while !got {
                    assert!(Instant::now() < deadline);
                    subscriber
                        .receive(Duration::from_millis(100), &mut |bytes| {
                            checksum = if read_all {
                                let words: &[u64] = bytemuck::cast_slice(bytes);
                                words.iter().fold(checksum, |sum, &w| sum.wrapping_add(w))
                            } else {
                                checksum.wrapping_add(u64::from(bytes[0]))
                            };
                            got = true;
                        })
                        .unwrap();
                }
            }
            std::hint::black_box(checksum);
        });
        let seconds = started.elapsed().as_secs_f64();
        println!(
            "iceoryx2: {MESSAGES} × 4 MiB written by the publisher, {label} by the subscriber: \
             {:.0} msg/s ({:.2} GB/s, {:.2} ms/msg)",
            MESSAGES as f64 / seconds,
            (MESSAGES * BYTES) as f64 / seconds / 1e9,
            seconds * 1e3 / MESSAGES as f64
        );
    }
    let started = Instant::now();
    std::thread::scope(|scope| {
        scope.spawn(|| {
            let mut publisher = transport.publisher("small").unwrap();
            assert!(publisher.wait_for_subscriber(WAIT).unwrap());
            for sequence in 0..SMALL_MESSAGES {
                publisher.send(&(sequence as u64).to_le_bytes()).unwrap();
            }
        });
        let mut small = transport.subscriber("small").unwrap();
        for sequence in 0..SMALL_MESSAGES {
            assert_eq!(
                receive(small.as_mut()),
                (sequence as u64).to_le_bytes().to_vec()
            );
        }
    });
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "iceoryx2: {SMALL_MESSAGES} × 8 B (publisher and subscriber opened in parallel): \
         {:.0} msg/s ({:.1} µs/msg)",
        SMALL_MESSAGES as f64 / seconds,
        seconds * 1e6 / SMALL_MESSAGES as f64
    );
}
