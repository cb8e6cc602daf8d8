//! `asgreg launch`: the ground-station supervisor. It starts one process per stage worker
//! (`asgreg stage <name> --config F --worker K`) over iceoryx2 or zenoh, restarts a stage that
//! dies (its unfinished jobs are redone by the dispatcher that gave them out), collects the
//! results, and stops the stages when every frame has its result. Stale iceoryx2 resources of
//! killed processes are cleaned before anything starts. A stage is restarted as long as it does
//! not crash more than `launch.max_restarts` times within `launch.restart_window_s`
//! ([`RestartIntensity`]). With zenoh and `launch.zenoh_router_listen`, the router is one more
//! supervised process ([`start_router`]): restarted under the same intensity, the stages' zenoh
//! clients reconnect to it by themselves, and it is stopped last. A stage that exits with
//! [`super::EXIT_NEEDS_OPERATOR`] (a damaged or unreadable results journal) is not restarted:
//! the launch stops with that reason. The launcher holds the stage-only output topics open for
//! the run ([`hold_outputs`]), so a stage killed mid-start never leaves one half made.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use crate::transport::Transport;

use super::collect::{Collected, Collector, Delivered};
use super::config::PipelineConfig;
use super::RuntimeError;

/// The restart intensity of one stage worker (Erlang's MaxR in MaxT, systemd's
/// StartLimitBurst in StartLimitIntervalSec): at most `max_restarts` restarts within any
/// `window`. A worker that crashes once an hour is restarted for ever; one that crashes faster
/// than it can work makes the supervisor give up. Times are given, so it is tested without
/// waiting.
#[derive(Clone, Debug)]
pub struct RestartIntensity {
    max_restarts: u32,
    window: Duration,
    /// When the restarts within the window happened, oldest first.
    recent: VecDeque<Instant>,
    /// Every restart of the run (for the log).
    pub total: u64,
}

impl RestartIntensity {
    pub fn new(max_restarts: u32, window: Duration) -> Self {
        Self {
            max_restarts,
            window,
            recent: VecDeque::new(),
            total: 0,
        }
    }

    /// A crash at `now`: `Ok(n)` when it may be restarted (the n-th restart within the
    /// window, counted), `Err(n)` when `n` restarts within the window are already spent.
    pub fn on_crash(&mut self, now: Instant) -> Result<u32, u32> {
        while self
            .recent
            .front()
            .is_some_and(|&at| now.saturating_duration_since(at) >= self.window)
        {
            self.recent.pop_front();
        }
        let in_window = self.recent.len() as u32;
        if in_window >= self.max_restarts {
            return Err(in_window);
        }
        self.recent.push_back(now);
        self.total += 1;
        Ok(in_window + 1)
    }
}

/// One stage worker process under supervision.
struct Supervised {
    stage: &'static str,
    worker: u32,
    child: Child,
    restarts: RestartIntensity,
    /// Ended on its own with success (ingest, at the end of its source).
    done: bool,
}

/// How to start a stage process.
pub struct StageCommand {
    /// The asgreg executable.
    pub program: PathBuf,
    pub config_path: PathBuf,
    /// Extra arguments before the subcommand (e.g. `-v`).
    pub global_args: Vec<String>,
    /// Extra arguments of `asgreg stage` (e.g. `--max-mesh-mib 512`).
    pub stage_args: Vec<String>,
}

/// The name the router goes by among the supervised processes (logs, `on_started`).
pub const ROUTER: &str = "router";

impl StageCommand {
    /// `asgreg zenoh-router` on `launch.zenoh_router_listen`, from `launch.zenoh_router_config`
    /// when set (TLS, access control).
    fn spawn_router(&self, config: &PipelineConfig) -> Result<Child, RuntimeError> {
        let mut command = Command::new(&self.program);
        command.args(&self.global_args).arg("zenoh-router");
        for endpoint in &config.launch.zenoh_router_listen {
            command.arg("--listen").arg(endpoint);
        }
        if let Some(file) = &config.launch.zenoh_router_config {
            command.arg("--config").arg(file);
        }
        command.spawn().map_err(|error| {
            RuntimeError::Launch(format!(
                "cannot start the zenoh router ({}): {error}",
                self.program.display()
            ))
        })
    }

    fn spawn(&self, stage: &str, worker: u32) -> Result<Child, RuntimeError> {
        Command::new(&self.program)
            .args(&self.global_args)
            .arg("stage")
            .arg(stage)
            .arg("--config")
            .arg(&self.config_path)
            .arg("--worker")
            .arg(worker.to_string())
            .args(&self.stage_args)
            .spawn()
            .map_err(|error| {
                RuntimeError::Launch(format!(
                    "cannot start stage {stage} worker {worker} ({}): {error}",
                    self.program.display()
                ))
            })
    }
}

/// The stage workers a configuration asks for on this host, downstream first.
pub fn local_stages(config: &PipelineConfig) -> Vec<(&'static str, u32)> {
    let mut stages = Vec::new();
    if config.changes_enabled() {
        stages.push(("fusion", 0));
        stages.extend((0..config.workers.change).map(|w| ("change", w)));
    }
    stages.push(("verify", 0));
    stages.extend((0..config.workers.pose).map(|w| ("pose", w)));
    let flow_local = config.workers.flow_local.unwrap_or(config.workers.flow);
    stages.extend((0..flow_local).map(|w| ("flow", w)));
    stages.extend((0..config.workers.render).map(|w| ("render", w)));
    stages.push(("ingest", 0));
    stages
}

/// Starts the launcher's zenoh router when the configuration asks for one (zenoh backend and
/// `launch.zenoh_router_listen`) and waits until its first endpoint accepts connections; hand
/// it to [`launch`], which supervises it. Before the launcher opens its own transport.
pub fn start_router(
    config: &PipelineConfig,
    command: &StageCommand,
) -> Result<Option<Child>, RuntimeError> {
    if config.backend != crate::transport::Backend::Zenoh
        || config.launch.zenoh_router_listen.is_empty()
    {
        return Ok(None);
    }
    let mut child = command.spawn_router(config)?;
    let address = config
        .launch
        .zenoh_router_listen
        .first()
        .and_then(|endpoint| {
            let rest = endpoint.split_once('/').map(|(_, rest)| rest)?;
            rest.split(['?', '#']).next().map(str::to_string)
        });
    let started = Instant::now();
    if let Some(address) = address {
        while std::net::TcpStream::connect(address.as_str()).is_err() {
            let exited = child.try_wait().map_err(|error| {
                RuntimeError::Launch(format!("cannot poll the zenoh router: {error}"))
            })?;
            if let Some(status) = exited {
                return Err(RuntimeError::Launch(format!(
                    "the zenoh router exited ({status}) before listening on {address} (launch.zenoh_router_listen, launch.zenoh_router_config): see its log above"
                )));
            }
            if started.elapsed() > Duration::from_secs(20) {
                let _ = child.kill();
                let _ = child.wait();
                return Err(RuntimeError::Launch(format!(
                    "the zenoh router did not listen on {address} within 20 s (launch.zenoh_router_listen)"
                )));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    Ok(Some(child))
}

/// Runs a launch: starts the stages, supervises them (and `router`, from [`start_router`]),
/// returns what the collector saw. `on_started` is told each (stage, worker, pid) as it starts
/// (the log, and tests that kill one); the router is ([`ROUTER`], 0, pid).
pub fn launch(
    config: &PipelineConfig,
    transport: &dyn Transport,
    command: &StageCommand,
    router: Option<Child>,
    on_started: &mut dyn FnMut(&str, u32, u32),
    on_result: &mut dyn FnMut(Delivered<'_>),
) -> Result<Collected, RuntimeError> {
    // A new run: the results journals start empty (restarted stages resume from them).
    super::journal::reset_all(config)?;
    reset_views(config)?;
    let window = Duration::from_secs_f64(config.launch.restart_window_s);
    let mut processes: Vec<Supervised> = Vec::new();
    if let Some(child) = router {
        on_started(ROUTER, 0, child.id());
        processes.push(Supervised {
            stage: ROUTER,
            worker: 0,
            child,
            restarts: RestartIntensity::new(config.launch.max_restarts, window),
            done: false,
        });
    }
    let mut collector = match Collector::open(transport, config.changes_enabled(), true) {
        Ok(collector) => collector,
        Err(error) => {
            stop_all(&mut processes, config);
            return Err(error.into());
        }
    };
    let _held = match hold_outputs(config, transport) {
        Ok(held) => held,
        Err(error) => {
            stop_all(&mut processes, config);
            return Err(error);
        }
    };
    let _held_topics = match hold_topics(config, transport) {
        Ok(held) => held,
        Err(error) => {
            stop_all(&mut processes, config);
            return Err(error);
        }
    };
    for (stage, worker) in local_stages(config) {
        // A stage that cannot start stops those already started (router included): nothing is
        // left running behind an error.
        let child = match command.spawn(stage, worker) {
            Ok(child) => child,
            Err(error) => {
                stop_all(&mut processes, config);
                return Err(error);
            }
        };
        on_started(stage, worker, child.id());
        tracing::info!("started {stage} worker {worker} (pid {})", child.id());
        processes.push(Supervised {
            stage,
            worker,
            child,
            restarts: RestartIntensity::new(config.launch.max_restarts, window),
            done: false,
        });
    }
    let mut failure: Option<RuntimeError> = None;
    let deadline = Duration::from_secs_f64(config.launch.deadline_s);
    let started = Instant::now();
    let outcome = collector.collect(deadline, on_result, &mut || {
        for process in processes.iter_mut().filter(|p| !p.done) {
            let status = match process.child.try_wait() {
                Ok(Some(status)) => status,
                Ok(None) => continue,
                Err(error) => {
                    tracing::error!("cannot poll {} worker {}: {error}", process.stage, process.worker);
                    continue;
                }
            };
            if status.success() && process.stage == "ingest" {
                process.done = true;
                continue;
            }
            if process.stage != ROUTER
                && status.code() == Some(i32::from(super::EXIT_NEEDS_OPERATOR))
            {
                // A restart would meet the same error: give up now, naming it.
                let reason = match super::journal::check(config) {
                    Err(error) => error.to_string(),
                    Ok(()) => "see its error above".to_string(),
                };
                failure = Some(RuntimeError::Launch(format!(
                    "stage {} worker {} stopped on an error a restart cannot mend ({status}); giving up without restarting it: {reason}",
                    process.stage, process.worker
                )));
                return false;
            }
            let in_window = match process.restarts.on_crash(Instant::now()) {
                Ok(in_window) => in_window,
                Err(in_window) => {
                    failure = Some(RuntimeError::Launch(format!(
                        "stage {} worker {} died again ({status}) after {in_window} restarts within {:.0} s (launch.max_restarts, launch.restart_window_s); giving up — see its log above",
                        process.stage, process.worker, config.launch.restart_window_s
                    )));
                    return false;
                }
            };
            tracing::warn!(
                "stage {} worker {} exited ({status}) after {:.1} s; restarting (restart {} of the run, {in_window} of at most {} within {:.0} s)",
                process.stage,
                process.worker,
                started.elapsed().as_secs_f64(),
                process.restarts.total,
                config.launch.max_restarts,
                config.launch.restart_window_s
            );
            let respawned = if process.stage == ROUTER {
                command.spawn_router(config)
            } else {
                command.spawn(process.stage, process.worker)
            };
            match respawned {
                Ok(child) => {
                    on_started(process.stage, process.worker, child.id());
                    process.child = child;
                }
                Err(error) => {
                    failure = Some(error);
                    return false;
                }
            }
        }
        true
    });
    // Give the stages a moment to send their final metrics, then stop them.
    if outcome.is_ok() {
        std::thread::sleep(Duration::from_millis(1200));
    }
    stop_all(&mut processes, config);
    let mut collected = outcome?;
    collector.drain_metrics(&mut collected)?;
    if let Some(error) = failure {
        return Err(error);
    }
    let changes_complete = !config.changes_enabled() || collected.missing_changes().is_empty();
    if collected.frame_count.is_some() && collected.missing().is_empty() && changes_complete {
        // Complete: nothing to resume.
        super::journal::reset_all(config)?;
        reset_views(config)?;
    }
    Ok(collected)
}

/// Opens (and the caller holds for the run, never sending) a publisher on each output topic that
/// only one stage publishes and no stage or launcher subscribes to: the JSON results, change
/// results and change set for outside consumers. Their services then live as long as the launch
/// instead of being made again by each restarted verify or fusion; found by the soak: over
/// iceoryx2, a fusion SIGKILLed while it was making `changeset/json` left the service half made
/// (`HangsInCreation`), and every restart of fusion failed on it until the launch gave up.
fn hold_outputs(
    config: &PipelineConfig,
    transport: &dyn Transport,
) -> Result<Vec<Box<dyn crate::transport::Publisher>>, RuntimeError> {
    let mut topics = vec![crate::transport::keys::RESULTS_JSON];
    if config.changes_enabled() {
        topics.extend([
            crate::transport::keys::CHANGES_JSON,
            crate::transport::keys::CHANGE_SET_JSON,
        ]);
    }
    topics
        .into_iter()
        .map(|topic| {
            transport
                .publisher(topic)
                .map_err(|error| RuntimeError::Launch(format!("cannot hold {topic} open: {error}")))
        })
        .collect()
}

/// Makes (and the caller holds for the run) the services of every topic the stages open
/// ([`crate::transport::Transport::hold_topic`]), so that a stage SIGKILLed while it starts
/// never leaves one half made: found by the soak over iceoryx2, a change worker killed while it
/// made `change/jobs/0!attached` left it so, and every restart failed on it until the launch
/// gave up.
fn hold_topics(
    config: &PipelineConfig,
    transport: &dyn Transport,
) -> Result<Vec<Box<dyn std::any::Any>>, RuntimeError> {
    use crate::transport::keys;
    let workers = &config.workers;
    let mut topics: Vec<String> = [
        keys::RESULTS,
        keys::RESULTS_ACK,
        keys::VERIFY_IN,
        keys::METRICS,
    ]
    .map(String::from)
    .to_vec();
    topics.extend((0..workers.pose).map(keys::pose_in));
    topics.extend((0..workers.render).map(|w| keys::jobs(keys::FRAMES_LINK, w)));
    topics.push(keys::credits(keys::FRAMES_LINK));
    for render in 0..workers.render.max(1) {
        topics.push(keys::credits(&keys::flow_link(render)));
    }
    topics.extend(
        (0..workers.flow).map(|w| keys::jobs(&keys::flow_link_of_worker(w, workers.render), w)),
    );
    if config.changes_enabled() {
        topics.extend([keys::FUSION_IN, keys::CHANGES, keys::CHANGES_ACK].map(String::from));
        topics.extend((0..workers.change).map(|w| keys::jobs(keys::CHANGE_LINK, w)));
        topics.push(keys::credits(keys::CHANGE_LINK));
    }
    topics
        .iter()
        .map(|topic| {
            transport.hold_topic(topic).map_err(|error| {
                RuntimeError::Launch(format!("cannot hold the services of {topic}: {error}"))
            })
        })
        .collect()
}

/// Stops the stages gracefully, then the router (the stages hand their jobs back through it).
fn stop_all(processes: &mut [Supervised], config: &PipelineConfig) {
    let grace = Duration::from_secs_f64(config.launch.stop_grace_s);
    for routers in [false, true] {
        let mut children: Vec<(String, &mut Child)> = processes
            .iter_mut()
            .filter(|p| (p.stage == ROUTER) == routers)
            .map(|p| (format!("{} worker {}", p.stage, p.worker), &mut p.child))
            .collect();
        stop_gracefully(&mut children, grace);
    }
}

/// Stops processes the way an operator's `systemctl stop` does: SIGTERM to each (a stage then
/// finishes or hands back its job, flushes and closes its shared memory), SIGKILL to those still
/// running after `grace`. Returns the names of the processes that had to be killed.
pub fn stop_gracefully(children: &mut [(String, &mut Child)], grace: Duration) -> Vec<String> {
    for (name, child) in children.iter_mut() {
        if matches!(child.try_wait(), Ok(None)) {
            if let Err(error) = terminate(child) {
                tracing::warn!(
                    "cannot send SIGTERM to {name} (pid {}): {error}",
                    child.id()
                );
            }
        }
    }
    let started = Instant::now();
    let mut killed = Vec::new();
    for (name, child) in children.iter_mut() {
        loop {
            match child.try_wait() {
                Ok(Some(status)) => {
                    tracing::debug!("{name} stopped ({status})");
                    break;
                }
                Ok(None) if started.elapsed() < grace => {
                    std::thread::sleep(Duration::from_millis(20));
                }
                _ => {
                    tracing::warn!(
                        "{name} (pid {}) did not stop within {:.1} s of SIGTERM (launch.stop_grace_s); sending SIGKILL",
                        child.id(),
                        grace.as_secs_f64()
                    );
                    let _ = child.kill();
                    let _ = child.wait();
                    killed.push(name.clone());
                    break;
                }
            }
        }
    }
    killed
}

/// Sends SIGTERM to a child process.
fn terminate(child: &Child) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        let pid = libc::pid_t::try_from(child.id())
            .map_err(|_| std::io::Error::other("pid out of range"))?;
        // SAFETY: kill(2) with a pid of our own child, which has not been reaped yet (try_wait
        // said it is running), so the pid cannot name another process.
        if unsafe { libc::kill(pid, libc::SIGTERM) } != 0 {
            return Err(std::io::Error::last_os_error());
        }
        Ok(())
    }
    #[cfg(not(unix))]
    {
        let _ = child;
        Err(std::io::Error::other("SIGTERM needs a unix system"))
    }
}

/// The config file path as given, made absolute (stage processes may run elsewhere).
pub fn absolute(path: &Path) -> PathBuf {
    std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf())
}

/// Starts a run over (or ends a complete one): verify's stereo views, pose lenders and received
/// messages and fusion's sights go with the journals.
fn reset_views(config: &PipelineConfig) -> Result<(), RuntimeError> {
    super::lenders::reset(config).map_err(|error| {
        RuntimeError::Launch(format!(
            "{}: cannot remove the pose lenders of an earlier run: {error}",
            super::lenders::dir(config).display()
        ))
    })?;
    super::received::reset(config).map_err(|error| {
        RuntimeError::Launch(format!(
            "{}: cannot remove the received messages of an earlier run: {error}",
            super::received::dir(config).display()
        ))
    })?;
    super::views::reset(config).map_err(|error| {
        RuntimeError::Launch(format!(
            "{}: cannot remove the stereo views of an earlier run: {error}",
            super::views::dir(config).display()
        ))
    })?;
    super::sights::reset(config).map_err(|error| {
        RuntimeError::Launch(format!(
            "{}: cannot remove the sights of an earlier run: {error}",
            super::sights::dir(config).display()
        ))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn restart_intensity_counts_restarts_within_the_window_only() {
        let start = Instant::now();
        let at = |s: u64| start + Duration::from_secs(s);
        let mut intensity = RestartIntensity::new(3, Duration::from_secs(10));
        // Three quick crashes are restarted, the fourth within 10 s is refused.
        assert_eq!(intensity.on_crash(at(0)), Ok(1));
        assert_eq!(intensity.on_crash(at(1)), Ok(2));
        assert_eq!(intensity.on_crash(at(2)), Ok(3));
        assert_eq!(intensity.on_crash(at(9)), Err(3));
        // Once the first has left the window there is room for one more.
        assert_eq!(intensity.on_crash(at(10)), Ok(3));
        assert_eq!(intensity.on_crash(at(10)), Err(3));
        assert_eq!(intensity.total, 4);
    }

    #[test]
    fn crashes_slower_than_the_window_are_restarted_for_ever() {
        let start = Instant::now();
        let mut intensity = RestartIntensity::new(2, Duration::from_secs(60));
        // A crash every 9 s would exhaust a lifetime cap of 2 at once; at 40 s apart never
        // more than 2 fall in one minute.
        for k in 0..100u64 {
            let now = start + Duration::from_secs(40 * k);
            assert!(intensity.on_crash(now).is_ok(), "crash {k} refused");
        }
        assert_eq!(intensity.total, 100);
        // A lifetime's worth faster than the window is refused.
        let mut fast = RestartIntensity::new(2, Duration::from_secs(60));
        let results: Vec<_> = (0..4u64)
            .map(|k| fast.on_crash(start + Duration::from_secs(9 * k)))
            .collect();
        assert_eq!(results, vec![Ok(1), Ok(2), Err(2), Err(2)]);
    }

    #[test]
    fn stopping_sends_sigterm_first_and_sigkill_after_the_grace_period() {
        // A process that exits on SIGTERM stops within the grace; one that ignores it is killed.
        let polite = Command::new("sleep").arg("30").spawn().unwrap();
        let mut stubborn = Command::new("sleep");
        stubborn.arg("30");
        // SAFETY: only `signal` (async-signal-safe) between fork and exec; an ignored signal
        // stays ignored across exec, so the child ignores SIGTERM from its first instruction.
        unsafe {
            std::os::unix::process::CommandExt::pre_exec(&mut stubborn, || {
                libc::signal(libc::SIGTERM, libc::SIG_IGN);
                Ok(())
            });
        }
        let (mut polite, mut stubborn) = (polite, stubborn.spawn().unwrap());
        let mut children = vec![
            ("polite".to_string(), &mut polite),
            ("stubborn".to_string(), &mut stubborn),
        ];
        let killed = stop_gracefully(&mut children, Duration::from_millis(500));
        assert_eq!(killed, vec!["stubborn".to_string()]);
        use std::os::unix::process::ExitStatusExt;
        assert_eq!(polite.wait().unwrap().signal(), Some(libc::SIGTERM));
        assert_eq!(stubborn.wait().unwrap().signal(), Some(libc::SIGKILL));
    }

    #[test]
    fn zero_restarts_means_never_restart() {
        let mut intensity = RestartIntensity::new(0, Duration::from_secs(60));
        assert_eq!(intensity.on_crash(Instant::now()), Err(0));
        assert_eq!(intensity.total, 0);
    }
}
