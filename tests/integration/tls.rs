//! Security that runs (issue #15 item 1): the shipped zenoh configs `deploy/zenoh/router-tls.json5`,
//! `client-tls.json5` and `router-tls-acl.json5`, with only their certificate paths and
//! addresses replaced, on 127.0.0.1 (scouting off in every file: nothing multicasts), with
//! certificates made here (a station CA, a router, a stage host, an observer, and a second CA):
//! a flow worker holding a certificate of the station's CA joins the router over mutual TLS and
//! does every flow job of a `launch`; a client without a certificate or with another CA's is
//! refused; under the access-control file an observer's identity receives results but can
//! neither publish frames nor read flow jobs.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use asgreg::transport::zenoh::{ZenohMode, ZenohSettings, ZenohTransport};
use asgreg::transport::{Transport, TransportConfig};
use rcgen::{
    BasicConstraints, Certificate, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa,
    KeyPair, KeyUsagePurpose,
};

use crate::util::*;

/// The certificate paths of the shipped files, replaced by the test's folder.
const SHIPPED_TLS_DIR: &str = "/etc/asgreg/tls/";
/// The placeholder address of the shipped files.
const SHIPPED_ADDRESS: &str = "192.168.10.1:7447";

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A certificate authority: its certificate (to sign with) and key.
struct Authority {
    certificate: Certificate,
    key: KeyPair,
}

impl Authority {
    /// A new CA named `name`; its certificate is written to `dir/<file>`.
    fn new(name: &str, dir: &Path, file: &str) -> Self {
        let key = KeyPair::generate().unwrap();
        let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
        params.distinguished_name.push(DnType::CommonName, name);
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        params.key_usages = vec![
            KeyUsagePurpose::KeyCertSign,
            KeyUsagePurpose::CrlSign,
            KeyUsagePurpose::DigitalSignature,
        ];
        let certificate = params.self_signed(&key).unwrap();
        std::fs::write(dir.join(file), certificate.pem()).unwrap();
        Self { certificate, key }
    }

    /// A certificate with common name `common_name` for 127.0.0.1 and localhost, signed by
    /// this CA, written as `dir/<name>-cert.pem` and `dir/<name>-key.pem`.
    fn issue(&self, common_name: &str, dir: &Path, name: &str) {
        let key = KeyPair::generate().unwrap();
        let mut params =
            CertificateParams::new(vec!["127.0.0.1".to_string(), "localhost".to_string()]).unwrap();
        params
            .distinguished_name
            .push(DnType::CommonName, common_name);
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        params.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        let certificate = params
            .signed_by(&key, &self.certificate, &self.key)
            .unwrap();
        std::fs::write(dir.join(format!("{name}-cert.pem")), certificate.pem()).unwrap();
        std::fs::write(dir.join(format!("{name}-key.pem")), key.serialize_pem()).unwrap();
    }
}

/// The station's certificates in `dir` (the names the shipped files use): `ca.pem`,
/// `router-*.pem`, `worker-*.pem` (CN asgreg-stage), `observer-*.pem` (CN asgreg-observer); and
/// `rogue-*.pem`, a stage certificate from another CA.
fn make_certificates(dir: &Path) {
    let station = Authority::new("asgreg station CA", dir, "ca.pem");
    station.issue("asgreg-router", dir, "router");
    station.issue("asgreg-stage", dir, "worker");
    station.issue("asgreg-observer", dir, "observer");
    let other = Authority::new("someone else's CA", dir, "other-ca.pem");
    other.issue("asgreg-stage", dir, "rogue");
}

/// `deploy/zenoh/<name>` with the certificate folder replaced by `pki`, the placeholder address
/// by `address`, then each of `edits` (from, to); written into `dir` and returned.
fn shipped(name: &str, dir: &Path, pki: &Path, address: &str, edits: &[(&str, &str)]) -> PathBuf {
    let source = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("deploy/zenoh")
        .join(name);
    let mut text = std::fs::read_to_string(&source).unwrap();
    assert!(
        text.contains(SHIPPED_TLS_DIR) && text.contains(SHIPPED_ADDRESS),
        "{name} no longer names {SHIPPED_TLS_DIR} and {SHIPPED_ADDRESS}: update this test"
    );
    text = text
        .replace(SHIPPED_TLS_DIR, &format!("{}/", pki.display()))
        .replace(SHIPPED_ADDRESS, address);
    for (from, to) in edits {
        assert!(text.contains(from), "{name} has no '{from}'");
        text = text.replace(from, to);
    }
    let path = dir.join(format!("{}-{name}", edits.len()));
    std::fs::write(&path, text).unwrap();
    path
}

/// A client config from `client-tls.json5` presenting `who`'s certificate (`worker`,
/// `observer`, `rogue`), or none.
fn client_file(dir: &Path, pki: &Path, tls_port: u16, who: Option<&str>) -> PathBuf {
    let address = format!("127.0.0.1:{tls_port}");
    match who {
        Some("worker") => shipped("client-tls.json5", dir, pki, &address, &[]),
        Some(other) => shipped(
            "client-tls.json5",
            dir,
            pki,
            &address,
            &[("/worker-", &format!("/{other}-"))],
        ),
        None => shipped(
            "client-tls.json5",
            dir,
            pki,
            &address,
            &[
                ("connect_private_key:", "// connect_private_key:"),
                ("connect_certificate:", "// connect_certificate:"),
                ("enable_mtls: true", "enable_mtls: false"),
            ],
        ),
    }
}

/// `asgreg zenoh-router --config <file>` listening on plain TCP (the station's own stages) and
/// TLS ports of 127.0.0.1; killed when dropped.
struct Router {
    child: Child,
    tcp_port: u16,
    tls_port: u16,
}

impl Router {
    fn start(file: &Path) -> Self {
        let (tcp_port, tls_port) = (free_port(), free_port());
        let child = Command::new(env!("CARGO_BIN_EXE_asgreg"))
            .args(["zenoh-router", "--config", path_str(file)])
            .args(["--listen", &format!("tcp/127.0.0.1:{tcp_port}")])
            .args(["--listen", &format!("tls/127.0.0.1:{tls_port}")])
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        let mut router = Self {
            child,
            tcp_port,
            tls_port,
        };
        let started = Instant::now();
        for port in [tcp_port, tls_port] {
            while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
                assert!(
                    router.child.try_wait().unwrap().is_none(),
                    "the router exited (its log is above)"
                );
                assert!(
                    started.elapsed() < Duration::from_secs(20),
                    "the router did not listen on port {port} within 20 s"
                );
                std::thread::sleep(Duration::from_millis(50));
            }
        }
        router
    }

    fn tls_endpoint(&self) -> String {
        format!("tls/127.0.0.1:{}", self.tls_port)
    }

    fn tcp_endpoint(&self) -> String {
        format!("tcp/127.0.0.1:{}", self.tcp_port)
    }
}

impl Drop for Router {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn client(pipeline: &str, endpoint: &str, file: Option<&Path>) -> Result<ZenohTransport, String> {
    ZenohTransport::new(
        TransportConfig {
            pipeline: pipeline.to_string(),
            ..TransportConfig::default()
        },
        &ZenohSettings {
            mode: ZenohMode::Client,
            connect: Some(vec![endpoint.to_string()]),
            listen: None,
            config_file: file.map(Path::to_path_buf),
            ..ZenohSettings::default()
        },
    )
    .map_err(|error| error.to_string())
}

/// Whether a message sent by `from` on `topic` reaches a subscriber of `to` on it (the
/// subscriber is declared first; the publisher waits up to `wait` for it to be routed).
fn reaches(from: &ZenohTransport, to: &ZenohTransport, topic: &str, wait: Duration) -> bool {
    let mut subscriber = to.subscriber(topic).unwrap();
    let mut publisher = from.publisher(topic).unwrap();
    let matched = publisher.wait_for_subscriber(wait).unwrap();
    publisher.send(b"message").unwrap();
    let received = subscriber
        .receive(Duration::from_millis(700), &mut |bytes| {
            assert_eq!(bytes, b"message")
        })
        .unwrap();
    assert!(
        matched || !received,
        "{topic}: delivered without a routed subscriber"
    );
    received
}

#[test]
fn mutual_tls_admits_the_station_ca_s_certificates_only() {
    let dir = tempfile::tempdir().unwrap();
    let pki = dir.path().join("tls");
    std::fs::create_dir(&pki).unwrap();
    make_certificates(&pki);
    let router_file = shipped(
        "router-tls.json5",
        dir.path(),
        &pki,
        "127.0.0.1:1", // replaced by --listen
        &[],
    );
    let router = Router::start(&router_file);
    let pipeline = format!("tls-{}", std::process::id());
    let tls_port = router.tls_port;

    let worker = client(
        &pipeline,
        &router.tls_endpoint(),
        Some(&client_file(dir.path(), &pki, tls_port, Some("worker"))),
    )
    .expect("a client with the station CA's certificate is admitted");
    let station = client(&pipeline, &router.tcp_endpoint(), None).expect("loopback client");
    assert!(
        reaches(&worker, &station, "results", Duration::from_secs(10)),
        "nothing crossed the TLS link"
    );

    let without = client(
        &pipeline,
        &router.tls_endpoint(),
        Some(&client_file(dir.path(), &pki, tls_port, None)),
    );
    let error = without
        .err()
        .expect("a client without a certificate was admitted by a mutual-TLS router");
    assert!(error.contains("tls"), "{error}");
    let rogue = client(
        &pipeline,
        &router.tls_endpoint(),
        Some(&client_file(dir.path(), &pki, tls_port, Some("rogue"))),
    );
    let error = rogue
        .err()
        .expect("a client with another CA's certificate was admitted");
    assert!(error.contains("certificate"), "{error}");

    // The same refusal from the command line: a flow worker with the other CA's certificate
    // exits with an error that names the router and what to check.
    let scene_dir = dir.path().join("no-scene");
    let config = dir.path().join("rogue.toml");
    std::fs::write(
        &config,
        format!(
            "mesh = \"{}\"\nbackend = \"zenoh\"\n[transport]\npipeline = \"{pipeline}\"\n[zenoh]\nmode = \"client\"\nconnect = [\"{}\"]\nconfig_file = \"{}\"\n",
            scene_dir.join("model.ply").display(),
            router.tls_endpoint(),
            client_file(dir.path(), &pki, tls_port, Some("rogue")).display()
        ),
    )
    .unwrap();
    let output = asgreg(&["stage", "flow", "--config", path_str(&config)]);
    assert!(!output.status.success(), "the rogue worker ran");
    let log = stderr(&output);
    assert!(
        log.contains(&router.tls_endpoint()) && log.contains("certificate"),
        "{log}"
    );
}

#[test]
fn access_control_by_certificate_keeps_an_observer_to_results() {
    let dir = tempfile::tempdir().unwrap();
    let pki = dir.path().join("tls");
    std::fs::create_dir(&pki).unwrap();
    make_certificates(&pki);
    let router_file = shipped("router-tls-acl.json5", dir.path(), &pki, "127.0.0.1:1", &[]);
    let router = Router::start(&router_file);
    let pipeline = format!("acl-{}", std::process::id());
    let tls_port = router.tls_port;
    let station = client(&pipeline, &router.tcp_endpoint(), None).expect("loopback stage");
    let worker = client(
        &pipeline,
        &router.tls_endpoint(),
        Some(&client_file(dir.path(), &pki, tls_port, Some("worker"))),
    )
    .expect("stage host");
    let observer = client(
        &pipeline,
        &router.tls_endpoint(),
        Some(&client_file(dir.path(), &pki, tls_port, Some("observer"))),
    )
    .expect("an observer's certificate is from the station's CA: it connects");
    let frames = asgreg::transport::keys::jobs(asgreg::transport::keys::FRAMES_LINK, 0);
    let flow_jobs = asgreg::transport::keys::jobs(asgreg::transport::keys::FLOW_LINK, 0);
    let wait = Duration::from_secs(10);
    // The observer receives results and metrics...
    for topic in [
        asgreg::transport::keys::RESULTS,
        asgreg::transport::keys::RESULTS_JSON,
        asgreg::transport::keys::METRICS,
    ] {
        assert!(
            reaches(&station, &observer, topic, wait),
            "the observer did not receive {topic}"
        );
    }
    // ...while a stage host's certificate moves frames and flow jobs (the same keys below are
    // refused for the observer because of its identity, not the keys)...
    assert!(reaches(&worker, &station, &frames, wait));
    assert!(reaches(&station, &worker, &flow_jobs, wait));
    // ...and the observer can neither publish frames (nor forge results) nor read flow jobs.
    let short = Duration::from_secs(2);
    assert!(
        !reaches(&observer, &station, &frames, short),
        "the observer published a frame"
    );
    assert!(
        !reaches(&observer, &station, asgreg::transport::keys::RESULTS, short),
        "the observer published a result"
    );
    assert!(
        !reaches(&station, &observer, &flow_jobs, short),
        "the observer read a flow job"
    );
    assert!(
        !reaches(&worker, &observer, &frames, short),
        "the observer read a frame"
    );
}

#[test]
fn a_flow_worker_with_the_station_s_certificate_does_the_flow_jobs_of_a_launch_over_tls() {
    let dir = tempfile::tempdir().unwrap();
    let pki = dir.path().join("tls");
    std::fs::create_dir(&pki).unwrap();
    make_certificates(&pki);
    let scene = synth_scene(dir.path(), 160, 88, 2);
    let router_file = shipped("router-tls.json5", dir.path(), &pki, "127.0.0.1:1", &[]);
    let (tcp_port, tls_port) = (free_port(), free_port());
    let pipeline = format!("tls-launch-{}", std::process::id());
    let common = format!(
        "synthetic_scene = \"{}\"\nbackend = \"zenoh\"\n\n[transport]\npipeline = \"{pipeline}\"\n\n[registration]\ncoarse_pose_count = 3\n\n[registration.pose_search]\nenabled = false\n\n[backpressure]\nflow_jobs_queued = 10\n\n[timeouts]\nframe_timeout_s = 120.0\n",
        scene.display()
    );
    // The station: every stage but the flow worker, and the router with TLS.
    let station = dir.path().join("station.toml");
    std::fs::write(
        &station,
        format!(
            "{common}\n[workers]\nflow = 1\nflow_local = 0\n\n[zenoh]\nmode = \"client\"\nconnect = [\"tcp/127.0.0.1:{tcp_port}\"]\n\n[launch]\ndeadline_s = 300.0\nzenoh_router_listen = [\"tcp/127.0.0.1:{tcp_port}\", \"tls/127.0.0.1:{tls_port}\"]\nzenoh_router_config = \"{}\"\n",
            router_file.display()
        ),
    )
    .unwrap();
    // The remote flow worker: client-tls.json5 with the stage certificate.
    let remote = dir.path().join("remote.toml");
    std::fs::write(
        &remote,
        format!(
            "{common}\n[workers]\nflow = 1\n\n[zenoh]\nmode = \"client\"\nconfig_file = \"{}\"\n",
            client_file(dir.path(), &pki, tls_port, Some("worker")).display()
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    let launcher = Command::new(env!("CARGO_BIN_EXE_asgreg"))
        .args(["launch", path_str(&station), "--out", path_str(&out)])
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let started = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", tls_port)).is_err() {
        assert!(started.elapsed() < Duration::from_secs(30), "no router");
        std::thread::sleep(Duration::from_millis(50));
    }
    let mut worker = Command::new(env!("CARGO_BIN_EXE_asgreg"))
        .args([
            "stage",
            "flow",
            "--config",
            path_str(&remote),
            "--worker",
            "0",
        ])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let output = wait_with_limit(launcher, Duration::from_secs(240));
    let _ = worker.kill();
    let worker_log =
        String::from_utf8_lossy(&worker.wait_with_output().unwrap().stderr).into_owned();
    let (stdout, stderr) = (stdout(&output), stderr(&output));
    assert!(
        output.status.success(),
        "launch with the TLS worker failed:\n{stdout}\n{stderr}\nworker:\n{worker_log}"
    );
    assert!(
        stdout.contains("exactly one result per frame: yes"),
        "{stdout}"
    );
    let results = std::fs::read_to_string(out.join("results.jsonl")).unwrap();
    let results: Vec<serde_json::Value> = results
        .lines()
        .map(|line| serde_json::from_str(line).unwrap())
        .collect();
    assert_eq!(results.len(), 2);
    // Flow worker 0, the only one, is the TLS client: it did every job of every frame.
    for result in &results {
        let workers = result["flow_workers"].as_array().unwrap();
        assert!(
            !workers.is_empty() && workers.iter().all(|w| w == 0),
            "{result}"
        );
    }
}

/// Waits for a child with a time limit (killed and reported past it).
fn wait_with_limit(mut child: Child, limit: Duration) -> std::process::Output {
    let started = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > limit {
            let _ = child.kill();
            let output = child.wait_with_output().unwrap();
            panic!(
                "timed out after {limit:?}:\n{}\n{}",
                String::from_utf8_lossy(&output.stdout),
                String::from_utf8_lossy(&output.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().unwrap()
}
