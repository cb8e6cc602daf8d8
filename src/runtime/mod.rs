//! Wiring from a configuration (docs/design.md §5): the stage loops (`nodes`), work sharing with redo
//! (`dispatch`), the bus wrappers (`bus`), the results collector and summary (`collect`), the
//! one-process runner (`run_in_process`), the process supervisor (`launch`), the results
//! journal that makes "has a result" survive a crash (`journal`), verify's durable stereo views
//! (`views`), pose lenders (`lenders`) and received messages (`received`) and fusion's durable
//! sights (`sights`), all in a `frame_folder`, the end-to-end acks that make a result lost in flight be sent again (`ack`) and the
//! process's heap settings (`heap`).

pub mod ack;
pub mod bus;
pub mod collect;
pub mod config;
pub mod dispatch;
pub mod frame_folder;
pub mod heap;
pub mod journal;
pub mod launch;
pub mod lenders;
pub mod nodes;
pub mod received;
pub mod reference;
pub mod sights;
pub mod views;

#[cfg(test)]
mod tests;

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use crate::core::mesh::Mesh;
use crate::transport::Transport;

use collect::{Collected, Collector, Delivered};
use config::PipelineConfig;
use nodes::{NodeContext, NodeError};

/// The exit status of a stage process that stopped on an error a restart cannot mend (a
/// damaged or unreadable results journal): `launch` does not restart it (as systemd's
/// `RestartPreventExitStatus`); 78 is sysexits' `EX_CONFIG`.
pub const EXIT_NEEDS_OPERATOR: u8 = 78;

#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    #[error(transparent)]
    Node(#[from] NodeError),
    #[error(transparent)]
    Bus(#[from] bus::BusError),
    #[error("stage {stage} worker {worker} failed: {detail}")]
    Stage {
        stage: &'static str,
        worker: u32,
        detail: String,
    },
    #[error("stage {stage} worker {worker} panicked")]
    Panicked { stage: &'static str, worker: u32 },
    #[error("{0}")]
    Launch(String),
    #[error(transparent)]
    Journal(#[from] journal::JournalError),
}

/// Runs the whole pipeline as threads of this process on `transport` (crossbeam for the
/// embedded default; any backend works) until every frame has its result.
pub fn run_in_process(
    config: &PipelineConfig,
    transport: &dyn Transport,
    mesh: &Mesh,
    deadline: Duration,
    on_result: &mut dyn FnMut(Delivered<'_>),
) -> Result<Collected, RuntimeError> {
    // Threads do not restart, so nothing resumes: the run keeps its results journal in a folder
    // of its own (never shared with another run of the same pipeline name) under `state_dir`
    // (unset: the temporary folder), removed at the end.
    let mut config = config.clone();
    let state_dir = run_state_parent(&config).join(format!(
        "asgreg-run-{}-{}",
        std::process::id(),
        bus::unix_time_ns()
    ));
    config.state_dir = Some(state_dir.clone());
    let collected = run_stage_threads(&config, transport, mesh, deadline, on_result);
    if let Err(error) = std::fs::remove_dir_all(&state_dir) {
        if error.kind() != std::io::ErrorKind::NotFound {
            tracing::warn!("{}: cannot remove: {error}", state_dir.display());
        }
    }
    collected
}

/// The folder `run_in_process` makes its own state folder in (check it with
/// [`journal::prepare_state_dir`] before a run).
pub fn run_state_parent(config: &PipelineConfig) -> std::path::PathBuf {
    config.state_dir.clone().unwrap_or_else(std::env::temp_dir)
}

/// Every stage as a thread, continuing the results journal as it is (the frames it lists are
/// neither sent nor published again, as after a restart of ingest and verify).
fn run_stage_threads(
    config: &PipelineConfig,
    transport: &dyn Transport,
    mesh: &Mesh,
    deadline: Duration,
    on_result: &mut dyn FnMut(Delivered<'_>),
) -> Result<Collected, RuntimeError> {
    let stop = AtomicBool::new(false);
    let mut collector = Collector::open(transport, config.changes_enabled(), true)?;
    let context = |worker_index| NodeContext {
        transport,
        config,
        worker_index,
        stop: &stop,
    };
    std::thread::scope(|scope| {
        type Handle<'s> =
            std::thread::ScopedJoinHandle<'s, Result<crate::msg::StageMetrics, NodeError>>;
        let mut handles: Vec<(&'static str, u32, Handle)> = Vec::new();
        // Downstream first, so every stage finds its reader.
        if config.changes_enabled() {
            handles.push(("fusion", 0, scope.spawn(|| nodes::run_fusion(&context(0)))));
            for worker in 0..config.workers.change {
                let ctx = context(worker);
                handles.push((
                    "change",
                    worker,
                    scope.spawn(move || nodes::run_change(&ctx, mesh)),
                ));
            }
        }
        handles.push((
            "verify",
            0,
            scope.spawn(|| nodes::run_verify(&context(0), mesh)),
        ));
        for worker in 0..config.workers.pose {
            let ctx = context(worker);
            handles.push(("pose", worker, scope.spawn(move || nodes::run_pose(&ctx))));
        }
        for worker in 0..config.workers.flow {
            let ctx = context(worker);
            handles.push((
                "flow",
                worker,
                scope.spawn(move || nodes::run_flow(&ctx, mesh)),
            ));
        }
        for worker in 0..config.workers.render {
            let ctx = context(worker);
            handles.push((
                "render",
                worker,
                scope.spawn(move || nodes::run_render(&ctx, mesh)),
            ));
        }
        handles.push(("ingest", 0, scope.spawn(|| nodes::run_ingest(&context(0)))));

        let outcome = collector.collect(deadline, on_result, &mut || {
            // Stop waiting if a stage thread ended with an error.
            !handles
                .iter()
                .any(|(name, _, h)| h.is_finished() && *name != "ingest")
        });
        stop.store(true, Ordering::Relaxed);
        // Every stage sends its last metrics as it stops: keep reading them, so that none of
        // them waits on the collector's full metrics queue (crossbeam blocks a full queue).
        let mut late = Collected::default();
        let mut outcome = outcome;
        while handles.iter().any(|(_, _, handle)| !handle.is_finished()) {
            let into = match outcome.as_mut() {
                Ok(collected) => collected,
                Err(_) => &mut late,
            };
            if let Err(error) = collector.drain_metrics(into) {
                tracing::debug!("metrics not read while stopping: {error}");
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let mut first_error = None;
        let mut finals = Vec::new();
        for (name, worker, handle) in handles {
            match handle.join() {
                Ok(Ok(metrics)) => finals.push(metrics),
                // Ingest stopped with the others before its stream was complete (deadline or
                // a stage error): the collected results say what is missing.
                Ok(Err(NodeError::Stopped { .. })) => {}
                Ok(Err(error)) => {
                    first_error.get_or_insert(RuntimeError::Stage {
                        stage: name,
                        worker,
                        detail: error.to_string(),
                    });
                }
                Err(_) => {
                    first_error.get_or_insert(RuntimeError::Panicked {
                        stage: name,
                        worker,
                    });
                }
            }
        }
        let mut collected = outcome?;
        if let Some(error) = first_error {
            return Err(error);
        }
        for metrics in finals {
            collected
                .metrics
                .insert((metrics.stage.clone(), metrics.worker_index), metrics);
        }
        Ok(collected)
    })
}
