//! The one conformance suite every transport backend must pass (the contract in `transport`'s
//! module comment): lossless and ordered per publisher, broadcast, many publishers, large
//! messages, backpressure without loss, timeouts, size limits, isolated topics and pipelines.
//! Each backend instantiates it with [`conformance_suite!`].

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use super::{Publisher, Subscriber, Transport, TransportConfig, TransportError};

/// A pipeline name no other test (in this or another process) uses: iceoryx2 services are
/// machine-global and zenoh keys are shared by every session on the router.
pub fn unique_pipeline(test: &str) -> String {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    format!(
        "conf-{test}-{}-{}",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    )
}

pub fn config(test: &str) -> TransportConfig {
    TransportConfig {
        pipeline: unique_pipeline(test),
        max_message_bytes: 8 << 20,
        queue_depth: 4,
    }
}

const WAIT: Duration = Duration::from_secs(10);

/// A message that carries its publisher, its sequence number and a checkable body.
fn message(publisher: u8, sequence: u32, len: usize) -> Vec<u8> {
    let mut bytes = vec![0u8; len.max(9)];
    bytes[0] = publisher;
    bytes[1..5].copy_from_slice(&sequence.to_le_bytes());
    bytes[5..9].copy_from_slice(&(len.max(9) as u32).to_le_bytes());
    for (i, byte) in bytes.iter_mut().enumerate().skip(9) {
        *byte = (i as u32)
            .wrapping_mul(2_654_435_761)
            .wrapping_add(sequence) as u8;
    }
    bytes
}

fn check(bytes: &[u8]) -> (u8, u32) {
    let sequence = u32::from_le_bytes([bytes[1], bytes[2], bytes[3], bytes[4]]);
    let len = u32::from_le_bytes([bytes[5], bytes[6], bytes[7], bytes[8]]) as usize;
    assert_eq!(bytes.len(), len, "message length changed in transit");
    for (i, byte) in bytes.iter().enumerate().skip(9) {
        assert_eq!(
            *byte,
            (i as u32)
                .wrapping_mul(2_654_435_761)
                .wrapping_add(sequence) as u8,
            "byte {i} of message {sequence} changed in transit"
        );
    }
    (bytes[0], sequence)
}

fn receive_one(subscriber: &mut dyn Subscriber) -> (u8, u32) {
    let mut got = None;
    let deadline = Instant::now() + WAIT;
    while got.is_none() {
        assert!(Instant::now() < deadline, "no message within {WAIT:?}");
        subscriber
            .receive(Duration::from_millis(200), &mut |bytes| {
                got = Some(check(bytes))
            })
            .expect("receive");
    }
    got.unwrap()
}

fn ready(publisher: &mut dyn Publisher) {
    assert!(
        publisher.wait_for_subscriber(WAIT).expect("wait"),
        "no subscriber connected within {WAIT:?}"
    );
}

pub fn ordered_and_lossless(transport: &dyn Transport) {
    let mut subscriber = transport.subscriber("a").unwrap();
    std::thread::scope(|scope| {
        // Ports are opened on the thread that uses them (iceoryx2's are not `Send`).
        scope.spawn(|| {
            let mut publisher = transport.publisher("a").unwrap();
            ready(publisher.as_mut());
            for sequence in 0..300u32 {
                let len = 9 + (sequence as usize * 37) % 5000;
                publisher.send(&message(0, sequence, len)).unwrap();
            }
        });
        for expected in 0..300u32 {
            assert_eq!(receive_one(subscriber.as_mut()), (0, expected));
        }
    });
}

pub fn broadcast_to_every_subscriber(transport: &dyn Transport) {
    let mut first = transport.subscriber("b").unwrap();
    let mut second = transport.subscriber("b").unwrap();
    let mut publisher = transport.publisher("b").unwrap();
    ready(publisher.as_mut());
    // Both subscribers must be attached; the second may need a moment on networked backends.
    std::thread::sleep(Duration::from_millis(200));
    for sequence in 0..3u32 {
        publisher.send(&message(0, sequence, 100)).unwrap();
    }
    for expected in 0..3u32 {
        assert_eq!(receive_one(first.as_mut()), (0, expected));
        assert_eq!(receive_one(second.as_mut()), (0, expected));
    }
}

pub fn many_publishers_one_topic(transport: &dyn Transport) {
    let mut subscriber = transport.subscriber("c").unwrap();
    std::thread::scope(|scope| {
        for publisher_index in 0..3u8 {
            scope.spawn(move || {
                let mut publisher = transport.publisher("c").unwrap();
                ready(publisher.as_mut());
                for sequence in 0..40u32 {
                    publisher
                        .send(&message(publisher_index, sequence, 64))
                        .unwrap();
                }
            });
        }
        let mut next = [0u32; 3];
        for _ in 0..120 {
            let (publisher_index, sequence) = receive_one(subscriber.as_mut());
            assert_eq!(
                sequence, next[publisher_index as usize],
                "publisher {publisher_index}'s messages out of order or lost"
            );
            next[publisher_index as usize] += 1;
        }
    });
}

pub fn large_messages_intact(transport: &dyn Transport) {
    let mut subscriber = transport.subscriber("d").unwrap();
    std::thread::scope(|scope| {
        // Ports are opened on the thread that uses them (iceoryx2's are not `Send`).
        scope.spawn(|| {
            let mut publisher = transport.publisher("d").unwrap();
            ready(publisher.as_mut());
            for sequence in 0..6u32 {
                publisher.send(&message(0, sequence, 4 << 20)).unwrap();
            }
        });
        for expected in 0..6u32 {
            assert_eq!(receive_one(subscriber.as_mut()), (0, expected));
        }
    });
}

pub fn slow_subscriber_blocks_without_loss(transport: &dyn Transport) {
    let mut subscriber = transport.subscriber("e").unwrap();
    std::thread::scope(|scope| {
        // Ports are opened on the thread that uses them (iceoryx2's are not `Send`).
        scope.spawn(|| {
            let mut publisher = transport.publisher("e").unwrap();
            ready(publisher.as_mut());
            for sequence in 0..60u32 {
                publisher.send(&message(0, sequence, 20_000)).unwrap();
            }
        });
        for expected in 0..60u32 {
            if expected % 10 == 0 {
                // The queue (depth 4) fills while the subscriber sleeps.
                std::thread::sleep(Duration::from_millis(50));
            }
            assert_eq!(receive_one(subscriber.as_mut()), (0, expected));
        }
    });
}

pub fn receive_times_out(transport: &dyn Transport) {
    let mut subscriber = transport.subscriber("f").unwrap();
    let started = Instant::now();
    let got = subscriber
        .receive(Duration::from_millis(100), &mut |_| {})
        .unwrap();
    assert!(!got);
    assert!(started.elapsed() >= Duration::from_millis(90));
}

pub fn too_large_is_refused_and_publisher_survives(transport: &dyn Transport) {
    let mut subscriber = transport.subscriber("g").unwrap();
    let mut publisher = transport.publisher("g").unwrap();
    ready(publisher.as_mut());
    let error = publisher.send(&message(0, 0, (8 << 20) + 1)).unwrap_err();
    assert!(
        matches!(error, TransportError::TooLarge { .. }),
        "unexpected error {error}"
    );
    assert!(error.to_string().contains("max_message_bytes"));
    publisher.send(&message(0, 1, 100)).unwrap();
    assert_eq!(receive_one(subscriber.as_mut()), (0, 1));
}

pub fn topics_are_isolated(transport: &dyn Transport) {
    let mut other = transport.subscriber("h/other").unwrap();
    let mut subscriber = transport.subscriber("h").unwrap();
    let mut publisher = transport.publisher("h").unwrap();
    ready(publisher.as_mut());
    publisher.send(&message(0, 7, 50)).unwrap();
    assert_eq!(receive_one(subscriber.as_mut()), (0, 7));
    assert!(!other
        .receive(Duration::from_millis(200), &mut |_| {})
        .unwrap());
}

/// Instantiates every conformance case as a `#[test]` for one backend; `$make` turns a
/// [`TransportConfig`] into a `Box<dyn Transport>`.
#[macro_export]
#[doc(hidden)]
macro_rules! conformance_suite {
    ($make:expr) => {
        $crate::conformance_suite!(@case $make, ordered_and_lossless);
        $crate::conformance_suite!(@case $make, broadcast_to_every_subscriber);
        $crate::conformance_suite!(@case $make, many_publishers_one_topic);
        $crate::conformance_suite!(@case $make, large_messages_intact);
        $crate::conformance_suite!(@case $make, slow_subscriber_blocks_without_loss);
        $crate::conformance_suite!(@case $make, receive_times_out);
        $crate::conformance_suite!(@case $make, too_large_is_refused_and_publisher_survives);
        $crate::conformance_suite!(@case $make, topics_are_isolated);
    };
    (@case $make:expr, $case:ident) => {
        #[test]
        fn $case() {
            let make: fn(
                $crate::transport::TransportConfig,
            ) -> Box<dyn $crate::transport::Transport> = $make;
            let transport = make($crate::transport::conformance::config(stringify!($case)));
            $crate::transport::conformance::$case(transport.as_ref());
        }
    };
}
