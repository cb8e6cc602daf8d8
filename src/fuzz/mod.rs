//! Fuzzing of every reader of user files and every message decoder (issue #15 item 4): mutated
//! inputs from valid seeds, each parsed under `catch_unwind`, timed (an input that takes longer
//! than the limit is a hang) and measured by the allocation guard (an input that makes the parser
//! allocate far more than its size is a blow-up), so that a panic, a hang or an allocation for a
//! count nobody checked is *found*. Deterministic: the inputs follow from the seed, the target and
//! the input's index, so a finding is reproduced with `asgreg fuzz --target T --seed S --from I`.
//!
//! Used by `asgreg fuzz` (the full form, ≥ 10⁴ inputs per target) and by the library's tests (a
//! short form on every `cargo test`). Needs [`alloc_guard::GuardedAllocator`] as the global
//! allocator of the binary, which [`run_target`] checks before it starts.

pub mod alloc_guard;
pub mod mutate;
pub mod targets;

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

pub use targets::{all_targets, SeedError, Target};

/// How a fuzz run goes.
#[derive(Clone, Debug)]
pub struct FuzzOptions {
    /// Mutated inputs per target (the seeds themselves are run once more, before them).
    pub inputs_per_target: usize,
    /// The run's seed: with the target's name and the input's index it fixes every input.
    pub seed: u64,
    /// The first input index (to reproduce one finding: its index, with `inputs_per_target` 1).
    pub first_input: usize,
    /// An input that takes longer is a hang.
    pub time_limit: Duration,
    /// Where the inputs are written (one file per target, rewritten per input) and the findings
    /// saved (`findings/`).
    pub work_dir: PathBuf,
    /// A single allocation above this stops the process with the input's path (see
    /// [`alloc_guard`]).
    pub hard_limit_bytes: usize,
    /// Allowed peak allocation per input: this base plus the target's allowance per input byte;
    /// more is a blow-up.
    /// (The per-byte part is the target's, [`Target::allocation_per_input_byte`].)
    pub allocation_base_bytes: usize,
}

impl FuzzOptions {
    pub fn new(inputs_per_target: usize, seed: u64, work_dir: PathBuf) -> Self {
        Self {
            inputs_per_target,
            seed,
            first_input: 0,
            time_limit: Duration::from_secs(1),
            work_dir,
            hard_limit_bytes: 8 << 30,
            allocation_base_bytes: 16 << 20,
        }
    }

    fn allocation_budget(&self, target: &Target, input_len: usize) -> usize {
        self.allocation_base_bytes
            .saturating_add(target.allocation_per_input_byte.saturating_mul(input_len))
    }
}

/// Where fuzz inputs go by default: `/dev/shm` (memory) where there is one, the temporary folder
/// otherwise. Every input is written as a file, and on a disk each write costs milliseconds.
pub fn default_work_root() -> PathBuf {
    let shm = Path::new("/dev/shm");
    if shm.is_dir() {
        shm.to_path_buf()
    } else {
        std::env::temp_dir()
    }
}

/// What went wrong with one input.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum FindingKind {
    /// A valid seed was refused (the mutations would not start from valid inputs).
    SeedRefused,
    Panic,
    /// Took longer than the time limit (or never finished: then the target stops there).
    Hang,
    /// Allocated more than the budget for its size.
    Blowup,
    /// An error of a file reader that does not name the file (its path).
    ErrorWithoutFile,
    /// An error of a file reader that names no place in the file ([`Target::names_place`]).
    ErrorWithoutPlace,
}

/// One finding, with the input saved where `saved_to` says.
#[derive(Clone, Debug)]
pub struct Finding {
    pub kind: FindingKind,
    /// The input's index (`None`: a seed, `seeds[i]` given in `detail`).
    pub input_index: Option<usize>,
    pub detail: String,
    pub input: Vec<u8>,
    pub saved_to: Option<PathBuf>,
}

/// One target's figures.
#[derive(Clone, Debug, Default)]
pub struct TargetReport {
    pub name: String,
    /// Mutated inputs run (seeds not counted).
    pub inputs: usize,
    /// Inputs the reader accepted (a mutation can leave a valid file).
    pub accepted: usize,
    /// Inputs refused with an error.
    pub refused: usize,
    /// Findings by kind (all of them counted; the first few of each kind kept in `findings`).
    pub counts: BTreeMap<String, usize>,
    pub findings: Vec<Finding>,
    /// A few distinct errors, to read whether they name the field or line.
    pub sample_errors: Vec<String>,
    pub slowest: Duration,
    pub largest_peak_bytes: usize,
    pub elapsed: Duration,
    /// The target stopped early: an input never finished.
    pub stuck: bool,
}

impl TargetReport {
    pub fn count(&self, kind: FindingKind) -> usize {
        self.counts.get(&format!("{kind:?}")).copied().unwrap_or(0)
    }

    pub fn total_findings(&self) -> usize {
        self.counts.values().sum()
    }
}

/// The fuzz run could not start.
#[derive(Debug, thiserror::Error)]
pub enum FuzzError {
    #[error("fuzz: the allocation guard is not this binary's global allocator (a self-check allocating 1 MiB counted {counted_bytes} bytes); declare `#[global_allocator] static A: asgreg::fuzz::alloc_guard::GuardedAllocator`")]
    GuardMissing { counted_bytes: usize },
    #[error("fuzz: {}: {source}", path.display())]
    WorkDir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("fuzz: the worker thread of target {target} could not start: {source}")]
    Thread {
        target: String,
        #[source]
        source: std::io::Error,
    },
}

/// Keeps this many findings of each kind per target (all are counted).
const KEPT_PER_KIND: usize = 5;
/// An input that has not finished after this many time limits is stuck: the target stops there.
const STUCK_FACTOR: u32 = 20;

thread_local! {
    static IS_FUZZ_THREAD: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
    static LAST_PANIC: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Installs (once) a panic hook that records the message and location of panics on fuzz threads
/// instead of printing them, and passes all others to the previous hook.
fn install_panic_hook() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if IS_FUZZ_THREAD.with(std::cell::Cell::get) {
                let message = if let Some(text) = info.payload().downcast_ref::<&str>() {
                    (*text).to_string()
                } else if let Some(text) = info.payload().downcast_ref::<String>() {
                    text.clone()
                } else {
                    "(a panic without a message)".to_string()
                };
                let location = info
                    .location()
                    .map(|l| format!("{}:{}", l.file(), l.line()))
                    .unwrap_or_default();
                LAST_PANIC.with(|last| *last.borrow_mut() = Some(format!("{location}: {message}")));
            } else {
                previous(info);
            }
        }));
    });
}

/// Checks that the guard counts this binary's allocations, and arms it.
pub fn arm_guard(options: &FuzzOptions) -> Result<(), FuzzError> {
    alloc_guard::arm(options.hard_limit_bytes);
    let figures = std::thread::scope(|scope| {
        scope
            .spawn(|| {
                alloc_guard::track_this_thread();
                alloc_guard::reset_thread_counters();
                let block = std::hint::black_box(vec![1u8; 1 << 20]);
                drop(block);
                alloc_guard::thread_figures()
            })
            .join()
            .unwrap_or_default()
    });
    if figures.largest_request_bytes < 1 << 20 {
        return Err(FuzzError::GuardMissing {
            counted_bytes: figures.largest_request_bytes,
        });
    }
    Ok(())
}

/// The outcome of one input, as the worker sends it.
struct Outcome {
    index: Option<usize>,
    input: Vec<u8>,
    result: Result<Result<(), String>, String>,
    elapsed: Duration,
    figures: alloc_guard::AllocationFigures,
}

/// The input of `index` for `target`: a mutation of one of its seeds.
pub fn input_for(target: &Target, seed: u64, index: usize) -> Vec<u8> {
    let name_hash = target
        .name
        .bytes()
        .fold(0xcbf2_9ce4_8422_2325_u64, |hash, byte| {
            (hash ^ u64::from(byte)).wrapping_mul(0x0100_0000_01b3)
        });
    let input_seed = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15)
        ^ name_hash
        ^ (index as u64).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    let mut mutator = mutate::Mutator::new(input_seed);
    let seed_input = &target.seeds[index % target.seeds.len()];
    let mut input = mutator.mutate(seed_input, target.text);
    if let Some(fixup) = target.fixup {
        fixup(&mut input);
    }
    input
}

/// Runs one input on the current thread: writes it to `path`, parses under `catch_unwind`.
fn run_one(target: &Target, path: &Path, index: Option<usize>, input: Vec<u8>) -> Outcome {
    if let Err(error) = std::fs::write(path, &input) {
        return Outcome {
            index,
            input,
            result: Ok(Err(format!(
                "fuzz: could not write the input {}: {error}",
                path.display()
            ))),
            elapsed: Duration::ZERO,
            figures: alloc_guard::AllocationFigures::default(),
        };
    }
    alloc_guard::reset_thread_counters();
    let start = Instant::now();
    let result = std::panic::catch_unwind(AssertUnwindSafe(|| (target.parse)(path, &input)));
    let elapsed = start.elapsed();
    let figures = alloc_guard::thread_figures();
    let result = result.map_err(|_| {
        LAST_PANIC
            .with(|last| last.borrow_mut().take())
            .unwrap_or_else(|| "(panic message not recorded)".to_string())
    });
    Outcome {
        index,
        input,
        result,
        elapsed,
        figures,
    }
}

/// Runs the seeds, then `options.inputs_per_target` mutated inputs of one target.
pub fn run_target(target: &Target, options: &FuzzOptions) -> Result<TargetReport, FuzzError> {
    install_panic_hook();
    arm_guard(options)?;
    let dir = options.work_dir.join(&target.name);
    std::fs::create_dir_all(&dir).map_err(|source| FuzzError::WorkDir {
        path: dir.clone(),
        source,
    })?;
    let path = dir.join(target.file_name);
    alloc_guard::set_current_input(&path);

    let (sender, receiver) = mpsc::sync_channel::<Outcome>(64);
    let worker_target = Target {
        name: target.name.clone(),
        file_name: target.file_name,
        seeds: target.seeds.clone(),
        text: target.text,
        names_file: target.names_file,
        names_place: target.names_place,
        allocation_per_input_byte: target.allocation_per_input_byte,
        fixup: target.fixup,
        parse: target.parse,
    };
    let worker_path = path.clone();
    let seed = options.seed;
    let range = options.first_input..options.first_input + options.inputs_per_target;
    let start = Instant::now();
    std::thread::Builder::new()
        .name(format!("fuzz-{}", target.name))
        .spawn(move || {
            IS_FUZZ_THREAD.with(|flag| flag.set(true));
            alloc_guard::track_this_thread();
            for seed_input in worker_target.seeds.clone() {
                let outcome = run_one(&worker_target, &worker_path, None, seed_input);
                if sender.send(outcome).is_err() {
                    return;
                }
            }
            for index in range {
                let input = input_for(&worker_target, seed, index);
                let outcome = run_one(&worker_target, &worker_path, Some(index), input);
                if sender.send(outcome).is_err() {
                    return;
                }
            }
        })
        .map_err(|source| FuzzError::Thread {
            target: target.name.clone(),
            source,
        })?;

    let mut report = TargetReport {
        name: target.name.clone(),
        ..TargetReport::default()
    };
    let findings_dir = options.work_dir.join("findings");
    let mut seen_errors: BTreeMap<String, ()> = BTreeMap::new();
    let mut seed_number = 0;
    loop {
        let outcome = match receiver.recv_timeout(options.time_limit * STUCK_FACTOR) {
            Ok(outcome) => outcome,
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
            Err(mpsc::RecvTimeoutError::Timeout) => {
                // The worker is stuck in one input: record it (the file at `path` is that input)
                // and leave the thread behind.
                let input = std::fs::read(&path).unwrap_or_default();
                report.stuck = true;
                record(
                    &mut report,
                    &findings_dir,
                    target,
                    Finding {
                        kind: FindingKind::Hang,
                        input_index: None,
                        detail: format!(
                            "never finished (waited {:?}); the input is the last one written",
                            options.time_limit * STUCK_FACTOR
                        ),
                        input,
                        saved_to: None,
                    },
                );
                break;
            }
        };
        let Some(index) = outcome.index else {
            // A seed: it must be accepted.
            if let Ok(Err(message)) | Err(message) = &outcome.result {
                record(
                    &mut report,
                    &findings_dir,
                    target,
                    Finding {
                        kind: FindingKind::SeedRefused,
                        input_index: None,
                        detail: format!("seed {seed_number}: {message}"),
                        input: outcome.input.clone(),
                        saved_to: None,
                    },
                );
            }
            seed_number += 1;
            continue;
        };
        report.inputs += 1;
        report.slowest = report.slowest.max(outcome.elapsed);
        report.largest_peak_bytes = report.largest_peak_bytes.max(outcome.figures.peak_bytes);
        let mut findings = Vec::new();
        match &outcome.result {
            Ok(Ok(())) => report.accepted += 1,
            Ok(Err(message)) => {
                report.refused += 1;
                let path_text = path.display().to_string();
                if target.names_file && !message.contains(&path_text) {
                    findings.push((FindingKind::ErrorWithoutFile, message.clone()));
                }
                if !names_place(target, &message.replace(&path_text, "")) {
                    findings.push((FindingKind::ErrorWithoutPlace, message.clone()));
                }
                let key: String = message
                    .replace(&path.display().to_string(), "")
                    .chars()
                    .filter(|c| !c.is_ascii_digit())
                    .take(60)
                    .collect();
                if report.sample_errors.len() < 8 && seen_errors.insert(key, ()).is_none() {
                    report.sample_errors.push(message.clone());
                }
            }
            Err(panic) => findings.push((FindingKind::Panic, panic.clone())),
        }
        if outcome.elapsed > options.time_limit {
            findings.push((
                FindingKind::Hang,
                format!(
                    "took {:.2} s (limit {:?})",
                    outcome.elapsed.as_secs_f64(),
                    options.time_limit
                ),
            ));
        }
        let budget = options.allocation_budget(target, outcome.input.len());
        if outcome.figures.peak_bytes > budget {
            findings.push((
                FindingKind::Blowup,
                format!(
                    "a {} B input made it allocate {:.1} MiB at once (largest single request {:.1} MiB; budget {:.1} MiB)",
                    outcome.input.len(),
                    mib(outcome.figures.peak_bytes),
                    mib(outcome.figures.largest_request_bytes),
                    mib(budget)
                ),
            ));
        }
        for (kind, detail) in findings {
            record(
                &mut report,
                &findings_dir,
                target,
                Finding {
                    kind,
                    input_index: Some(index),
                    detail,
                    input: outcome.input.clone(),
                    saved_to: None,
                },
            );
        }
    }
    report.elapsed = start.elapsed();
    Ok(report)
}

/// Whether an error (without the file's path) says where in the file, by the target's rule; a
/// path followed by `:<line>` (as compilers write `file:12:`) names the line too.
pub fn names_place(target: &Target, message_without_path: &str) -> bool {
    let lower = message_without_path.to_lowercase();
    let path_then_line = lower
        .split(':')
        .nth(1)
        .is_some_and(|part| !part.is_empty() && part.bytes().all(|byte| byte.is_ascii_digit()));
    target.names_place.is_empty()
        || path_then_line && target.names_place.contains(&"line")
        || target.names_place.iter().any(|word| lower.contains(word))
}

fn mib(bytes: usize) -> f64 {
    bytes as f64 / (1024.0 * 1024.0)
}

/// Counts a finding, and keeps and saves the first few of each kind.
fn record(report: &mut TargetReport, findings_dir: &Path, target: &Target, mut finding: Finding) {
    let count = report
        .counts
        .entry(format!("{:?}", finding.kind))
        .or_insert(0);
    *count += 1;
    if *count > KEPT_PER_KIND {
        return;
    }
    let index = finding
        .input_index
        .map_or_else(|| "seed".to_string(), |index| index.to_string());
    let file = findings_dir.join(format!(
        "{}-{:?}-{index}-{}",
        target.name, finding.kind, target.file_name
    ));
    if std::fs::create_dir_all(findings_dir).is_ok()
        && std::fs::write(&file, &finding.input).is_ok()
    {
        finding.saved_to = Some(file);
    }
    report.findings.push(finding);
}

/// Makes a panicking input smaller while it still panics (chunks removed, halving their size);
/// at most `max_attempts` parses. For the regression tests: the minimised bytes go in the test.
pub fn minimise_panic(target: &Target, path: &Path, input: &[u8], max_attempts: usize) -> Vec<u8> {
    install_panic_hook();
    let was_fuzz_thread = IS_FUZZ_THREAD.with(|flag| flag.replace(true));
    let panics = |candidate: &[u8]| {
        std::fs::write(path, candidate).is_ok()
            && std::panic::catch_unwind(AssertUnwindSafe(|| (target.parse)(path, candidate)))
                .is_err()
    };
    let mut best = input.to_vec();
    let mut attempts = 0;
    let mut chunk = best.len().div_ceil(2).max(1);
    while chunk >= 1 && attempts < max_attempts {
        let mut start = 0;
        let mut shrunk = false;
        while start < best.len() && attempts < max_attempts {
            let end = (start + chunk).min(best.len());
            let mut candidate = best[..start].to_vec();
            candidate.extend_from_slice(&best[end..]);
            attempts += 1;
            if panics(&candidate) {
                best = candidate;
                shrunk = true;
            } else {
                start += chunk;
            }
        }
        if !shrunk {
            if chunk == 1 {
                break;
            }
            chunk /= 2;
        }
    }
    LAST_PANIC.with(|last| last.borrow_mut().take());
    IS_FUZZ_THREAD.with(|flag| flag.set(was_fuzz_thread));
    best
}

/// The report as a Markdown table row: target, inputs, accepted, refused, panics, hangs,
/// blow-ups, errors without the file, errors without a place in it, slowest input, largest
/// peak allocation, time.
pub fn markdown_row(report: &TargetReport) -> String {
    format!(
        "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {:.1} ms | {:.2} MiB | {:.1} s |",
        report.name,
        report.inputs,
        report.accepted,
        report.refused,
        report.count(FindingKind::Panic),
        report.count(FindingKind::Hang),
        report.count(FindingKind::Blowup),
        report.count(FindingKind::ErrorWithoutFile) + report.count(FindingKind::SeedRefused),
        report.count(FindingKind::ErrorWithoutPlace),
        report.slowest.as_secs_f64() * 1e3,
        mib(report.largest_peak_bytes),
        report.elapsed.as_secs_f64(),
    )
}

pub const MARKDOWN_HEADER: &str = "| target | inputs | accepted | refused | panics | hangs | blow-ups | errors without the file (+ seeds refused) | errors without the line or field | slowest input | largest peak allocation | time |\n|---|---|---|---|---|---|---|---|---|---|---|---|";

#[cfg(test)]
mod regressions;
#[cfg(test)]
mod tests;
