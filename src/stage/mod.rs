//! Stage adapters: message in → `core` → message out (docs/design.md §5). Each stage is a plain struct
//! with a `process` method, testable without any transport; `runtime` runs them as threads or
//! processes and moves their messages. No transport, no async, no I/O of the bus here.

pub mod change;
pub mod flow;
pub mod fusion;
pub mod ingest;
pub mod pose;
pub mod render;
pub mod simulate;
pub mod verify;

/// Milliseconds since `started`.
pub(crate) fn elapsed_ms(started: std::time::Instant) -> f64 {
    started.elapsed().as_secs_f64() * 1e3
}
