//! `asgreg launch`: the ground-station supervisor. It starts one process per stage worker
//! (`asgreg stage <name> --config F --worker K`) over iceoryx2 or zenoh, restarts a stage that
//! dies (its unfinished jobs are redone by the dispatcher that gave them out), collects the
//! results, and stops the stages when every frame has its result. Stale iceoryx2 resources of
//! killed processes are cleaned before anything starts.

use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use crate::msg::{Header, PoseResult};
use crate::transport::Transport;

use super::collect::{Collected, Collector};
use super::config::PipelineConfig;
use super::RuntimeError;

/// One stage worker process under supervision.
struct Supervised {
    stage: &'static str,
    worker: u32,
    child: Child,
    restarts: u32,
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
}

impl StageCommand {
    fn spawn(&self, stage: &str, worker: u32) -> Result<Child, RuntimeError> {
        Command::new(&self.program)
            .args(&self.global_args)
            .arg("stage")
            .arg(stage)
            .arg("--config")
            .arg(&self.config_path)
            .arg("--worker")
            .arg(worker.to_string())
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
    let mut stages = vec![("verify", 0), ("pose", 0)];
    let flow_local = config.workers.flow_local.unwrap_or(config.workers.flow);
    stages.extend((0..flow_local).map(|w| ("flow", w)));
    stages.extend((0..config.workers.render).map(|w| ("render", w)));
    stages.push(("ingest", 0));
    stages
}

/// Runs a launch: starts the stages, supervises them, returns what the collector saw.
/// `on_started` is told each (stage, worker, pid) as it starts (the log, and tests that kill one).
pub fn launch(
    config: &PipelineConfig,
    transport: &dyn Transport,
    command: &StageCommand,
    on_started: &mut dyn FnMut(&str, u32, u32),
    on_result: &mut dyn FnMut(&Header, &PoseResult),
) -> Result<Collected, RuntimeError> {
    let mut collector = Collector::open(transport)?;
    let mut processes: Vec<Supervised> = Vec::new();
    for (stage, worker) in local_stages(config) {
        let child = command.spawn(stage, worker)?;
        on_started(stage, worker, child.id());
        tracing::info!("started {stage} worker {worker} (pid {})", child.id());
        processes.push(Supervised {
            stage,
            worker,
            child,
            restarts: 0,
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
            if process.restarts >= config.launch.max_restarts {
                failure = Some(RuntimeError::Launch(format!(
                    "stage {} worker {} died {} times (last: {status}); giving up — see its log above",
                    process.stage, process.worker, process.restarts + 1
                )));
                return false;
            }
            process.restarts += 1;
            tracing::warn!(
                "stage {} worker {} exited ({status}) after {:.1} s; restarting (restart {} of at most {})",
                process.stage,
                process.worker,
                started.elapsed().as_secs_f64(),
                process.restarts,
                config.launch.max_restarts
            );
            match command.spawn(process.stage, process.worker) {
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
    let mut collected = outcome?;
    std::thread::sleep(Duration::from_millis(1200));
    collector.drain_metrics(&mut collected)?;
    for process in &mut processes {
        if !process.done {
            let _ = process.child.kill();
        }
        let _ = process.child.wait();
    }
    if let Some(error) = failure {
        return Err(error);
    }
    Ok(collected)
}

/// The config file path as given, made absolute (stage processes may run elsewhere).
pub fn absolute(path: &Path) -> PathBuf {
    std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf())
}
