//! Transport latency and throughput per backend (crossbeam, iceoryx2, zenoh over TCP loopback):
//! one message sent, delivered, received and decoded per iteration, for a 4 MB frame (1024×1024
//! grey f32), a render → flow job at 505×275 (2.2 MB) and a coarse pose's correspondences
//! (5,000 2D–3D pairs, 220 kB). Criterion reports time per message; bytes/s is set as throughput.

use std::borrow::Cow;
use std::time::{Duration, Instant};

use asgreg::core::camera::{Camera, PinholeIntrinsics};
use asgreg::core::rigid::Rigid3;
use asgreg::msg::{
    decode, encode, Body, Correspondences, CorrespondencesMeta, Envelope, FlowJob, FlowJobMeta,
    Frame, FrameInfo, GridArrays, Header,
};
use asgreg::transport::{self, Backend, Transport, TransportConfig};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};

fn info(width_px: u32, height_px: u32) -> FrameInfo {
    FrameInfo {
        name: "bench.png".to_string(),
        camera_id: 1,
        camera: Camera::pinhole(
            width_px,
            height_px,
            PinholeIntrinsics::centered(800.0, width_px, height_px),
        ),
        intrinsics_known: true,
        initial_cam_from_world: Rigid3::identity(),
        seed: 1,
    }
}

fn messages() -> Vec<(&'static str, Vec<u8>)> {
    let header = Header::default();
    let frame_pixels = 1024 * 1024;
    let frame = Envelope {
        header,
        body: Body::Frame(Frame {
            info: info(1024, 1024),
            image: Cow::Owned((0..frame_pixels).map(|i| (i % 255) as f32).collect()),
            depth_m: Cow::Owned(Vec::new()),
        }),
    };
    let job_pixels = 505 * 275;
    let job = Envelope {
        header,
        body: Body::FlowJob(FlowJob {
            meta: FlowJobMeta {
                info: info(505, 275),
                coarse_index: 3,
                coarse_count: 15,
                coarse_cam_from_world: Rigid3::identity(),
                render_ms: 1.0,
            },
            query: Cow::Owned(vec![0.5; job_pixels]),
            asg: Cow::Owned(vec![0.25; job_pixels]),
            depth_m: Cow::Owned(vec![10.0; job_pixels]),
            face_index: Cow::Owned((0..job_pixels as u32).collect()),
        }),
    };
    let pairs = 5000;
    let grid_samples = asgreg::core::reprojection::GridSamples::sample_count(505, 275, 4);
    let correspondences = Envelope {
        header,
        body: Body::Correspondences(Correspondences {
            meta: CorrespondencesMeta {
                info: info(505, 275),
                coarse_index: 3,
                coarse_count: 15,
                coarse_cam_from_world: Rigid3::identity(),
                render_ms: 1.0,
                flow_ms: 300.0,
                flow_worker: 0,
                grid_stride_px: 4,
            },
            image_points_px: Cow::Owned(vec![100.5; 2 * pairs]),
            world_points_m: Cow::Owned(vec![3.25; 3 * pairs]),
            // The coarse view on δ's 4-px grid, as flow sends it on for verify.
            grid: GridArrays {
                face_index: Cow::Owned(vec![7; grid_samples]),
                depth_m: Cow::Owned(vec![10.0; grid_samples]),
            },
        }),
    };
    vec![
        ("frame_4MB", encode(&frame).unwrap().to_vec()),
        ("flow_job_505x275", encode(&job).unwrap().to_vec()),
        (
            "correspondences_5k",
            encode(&correspondences).unwrap().to_vec(),
        ),
    ]
}

/// The backends to compare; zenoh goes through a router on a free loopback port.
/// A backend, whatever keeps it alive (a zenoh router), and its transport.
type BackendUnderTest = (
    Backend,
    Box<dyn std::any::Any>,
    std::sync::Arc<dyn Transport>,
);

fn backends() -> Vec<BackendUnderTest> {
    let mut list = Vec::new();
    let config = |name: &str| TransportConfig {
        pipeline: format!("bench-{name}-{}", std::process::id()),
        max_message_bytes: 8 << 20,
        queue_depth: 4,
    };
    let zenoh = transport::zenoh::ZenohSettings::default();
    let crossbeam = transport::open(Backend::Crossbeam, &config("crossbeam"), &zenoh)
        .expect("crossbeam transport");
    list.push((
        Backend::Crossbeam,
        Box::new(()) as Box<dyn std::any::Any>,
        crossbeam,
    ));
    let iceoryx2 = transport::open(Backend::Iceoryx2, &config("iceoryx2"), &zenoh)
        .expect("iceoryx2 transport");
    list.push((
        Backend::Iceoryx2,
        Box::new(()) as Box<dyn std::any::Any>,
        iceoryx2,
    ));
    // zenoh over TCP loopback, peer to peer: the subscribers' session listens, the publishers'
    // session connects (no router in between; `launch` deployments add one hop through it).
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|listener| listener.local_addr())
        .expect("a free loopback port")
        .port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let listening = transport::zenoh::ZenohSettings {
        mode: transport::zenoh::ZenohMode::Peer,
        listen: Some(vec![endpoint.clone()]),
        connect: Some(Vec::new()),
        ..transport::zenoh::ZenohSettings::default()
    };
    let connecting = transport::zenoh::ZenohSettings {
        mode: transport::zenoh::ZenohMode::Peer,
        listen: Some(Vec::new()),
        connect: Some(vec![endpoint]),
        ..transport::zenoh::ZenohSettings::default()
    };
    let zenoh_config = config("zenoh");
    let subscribers = transport::open(Backend::Zenoh, &zenoh_config, &listening)
        .expect("zenoh transport (listening)");
    let publishers = transport::open(Backend::Zenoh, &zenoh_config, &connecting)
        .expect("zenoh transport (connecting)");
    list.push((
        Backend::Zenoh,
        Box::new(publishers) as Box<dyn std::any::Any>,
        subscribers,
    ));
    list
}

fn transport_benches(c: &mut Criterion) {
    let messages = messages();
    for (backend, guard, transport) in backends() {
        // zenoh: publishers on the connecting session (the guard), subscribers on the listening one.
        let publishing: std::sync::Arc<dyn Transport> = guard
            .downcast_ref::<std::sync::Arc<dyn Transport>>()
            .cloned()
            .unwrap_or_else(|| transport.clone());
        let mut group = c.benchmark_group(format!("transport/{}", backend.name()));
        group.sample_size(20);
        group.measurement_time(Duration::from_secs(3));
        for (name, bytes) in &messages {
            let topic = format!("bench/{name}");
            let mut subscriber = transport.subscriber(&topic).expect("subscriber");
            let mut publisher = publishing.publisher(&topic).expect("publisher");
            assert!(publisher
                .wait_for_subscriber(Duration::from_secs(10))
                .expect("wait"));
            group.throughput(Throughput::Bytes(bytes.len() as u64));
            group.bench_function(*name, |b| {
                b.iter_custom(|iterations| {
                    let started = Instant::now();
                    for _ in 0..iterations {
                        publisher.send(bytes).expect("send");
                        let mut received = false;
                        while !received {
                            subscriber
                                .receive(Duration::from_secs(5), &mut |payload| {
                                    let message = decode(payload).expect("decode");
                                    std::hint::black_box(&message);
                                    received = true;
                                })
                                .expect("receive");
                        }
                    }
                    started.elapsed()
                })
            });
        }
        group.finish();
    }
}

criterion_group!(benches, transport_benches);
criterion_main!(benches);
