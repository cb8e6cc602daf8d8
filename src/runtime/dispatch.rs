//! Work sharing over a broadcast bus (docs/design.md §5 "horizontal scaling"): the producer of a link
//! (ingest for frames, render for flow jobs) owns a [`Dispatcher`]; each worker owns a
//! [`WorkerPort`]. Workers announce themselves with credits (worker index, incarnation, jobs
//! finished, slots); the dispatcher sends each job to exactly one worker with a free slot, on
//! that worker's own topic. It keeps every job until the worker reports it finished, so:
//! - a worker that restarts (new incarnation, e.g. after SIGKILL and the supervisor's restart)
//!   gets its unfinished jobs redone — by whichever worker is free first;
//! - a worker silent for longer than the silence limit with jobs outstanding has them redone
//!   elsewhere (a remote host that vanished);
//! - a job lost on the way (e.g. while the zenoh router restarted) is redone once it has been
//!   out longer than the silence limit, and a worker repeats its finished jobs in its credits
//!   for a few seconds, so a lost credit loses no completion.
//!
//! Redone jobs can produce duplicates downstream; verify keeps the first per (frame, coarse pose).
//! Backpressure: the dispatcher's queue is bounded; the producer asks [`Dispatcher::has_room`]
//! and blocks or drops by its policy.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::msg::{Body, Credit, JobKey, StageMetrics};
use crate::transport::{keys, Transport};

use super::bus::{BusError, Inbox, Outbox};

/// How often an idle worker repeats its credit (a heartbeat; lost credits are harmless).
pub const CREDIT_INTERVAL: Duration = Duration::from_millis(250);

/// How long a worker repeats a finished job in its credits (longer than a router restart).
const COMPLETED_REPEAT: Duration = Duration::from_secs(5);

type Job = (JobKey, Arc<Vec<u8>>);

struct WorkerState {
    incarnation: u64,
    slots: u32,
    outstanding: Vec<Job>,
    /// When each outstanding job was sent (same order as `outstanding`).
    sent_at: Vec<Instant>,
    last_heard: Instant,
    /// Silent past the limit: gets no new work until heard from again.
    presumed_dead: bool,
    jobs_done: u64,
}

pub struct Dispatcher<'t> {
    transport: &'t dyn Transport,
    link: String,
    credits: Inbox,
    outboxes: BTreeMap<u32, Outbox>,
    workers: BTreeMap<u32, WorkerState>,
    queue: VecDeque<Job>,
    capacity: usize,
    silence_limit: Duration,
    /// Counters of the dispatcher itself (jobs sent, redone).
    pub metrics: StageMetrics,
}

impl<'t> Dispatcher<'t> {
    /// `capacity`: jobs waiting for a worker before `has_room` says no.
    pub fn open(
        transport: &'t dyn Transport,
        link: &str,
        capacity: usize,
        silence_limit: Duration,
    ) -> Result<Self, BusError> {
        Ok(Self {
            transport,
            link: link.to_string(),
            credits: Inbox::open(transport, &keys::credits(link), link)?,
            outboxes: BTreeMap::new(),
            workers: BTreeMap::new(),
            queue: VecDeque::new(),
            capacity: capacity.max(1),
            silence_limit,
            metrics: StageMetrics {
                stage: format!("dispatch:{link}"),
                ..StageMetrics::default()
            },
        })
    }

    pub fn has_room(&self) -> bool {
        self.queue.len() < self.capacity
    }

    /// Jobs waiting for a worker.
    pub fn queued(&self) -> usize {
        self.queue.len()
    }

    /// Whether any job of `frame_id` still waits for a worker.
    pub fn has_queued(&self, frame_id: u64) -> bool {
        self.queue.iter().any(|(key, _)| key.frame_id == frame_id)
    }

    /// Whether a job of `frame_id` waits for a worker or is with one (not yet finished).
    pub fn holds(&self, frame_id: u64) -> bool {
        self.has_queued(frame_id)
            || self.workers.values().any(|w| {
                w.outstanding
                    .iter()
                    .any(|(key, _)| key.frame_id == frame_id)
            })
    }

    /// Jobs sent and not yet reported finished.
    pub fn outstanding(&self) -> usize {
        self.workers.values().map(|w| w.outstanding.len()).sum()
    }

    /// Nothing queued and nothing outstanding.
    pub fn is_idle(&self) -> bool {
        self.queue.is_empty() && self.outstanding() == 0
    }

    /// Jobs finished per worker (the work split).
    pub fn jobs_done(&self) -> BTreeMap<u32, u64> {
        self.workers
            .iter()
            .map(|(index, worker)| (*index, worker.jobs_done))
            .collect()
    }

    /// Queues an encoded job message.
    pub fn push(&mut self, key: JobKey, message: Vec<u8>) {
        self.push_shared(key, Arc::new(message));
    }

    /// Queues an encoded job message the caller also keeps.
    pub fn push_shared(&mut self, key: JobKey, message: Arc<Vec<u8>>) {
        self.queue.push_back((key, message));
        self.metrics.max_queue_depth = self.metrics.max_queue_depth.max(self.queue.len() as u64);
    }

    /// Removes the oldest job still waiting for a worker (drop-oldest backpressure).
    pub fn drop_oldest(&mut self) -> Option<JobKey> {
        let (key, _) = self.queue.pop_front()?;
        self.metrics.dropped += 1;
        Some(key)
    }

    /// Takes credits for up to `wait` (returns early once one arrived and the rest are drained),
    /// redoes the jobs of restarted or silent workers, and sends queued jobs to free workers.
    pub fn pump(&mut self, wait: Duration) -> Result<(), BusError> {
        let mut credits = Vec::new();
        let mut scratch = StageMetrics::default();
        let mut timeout = wait;
        while self
            .credits
            .receive(timeout, &mut scratch, &mut |message, _| {
                if let Body::Credit(credit) = message.body {
                    credits.push(credit);
                }
            })?
        {
            timeout = Duration::ZERO;
        }
        self.metrics.rejected += scratch.rejected;
        let now = Instant::now();
        for credit in credits {
            self.on_credit(credit, now);
        }
        self.redo_silent(now);
        self.assign()
    }

    fn requeue(&mut self, jobs: Vec<Job>) {
        self.metrics.redispatched += jobs.len() as u64;
        for job in jobs.into_iter().rev() {
            self.queue.push_front(job);
        }
    }

    fn on_credit(&mut self, credit: Credit, now: Instant) {
        let worker = self
            .workers
            .entry(credit.worker_index)
            .or_insert(WorkerState {
                incarnation: credit.incarnation,
                slots: credit.free_slots,
                outstanding: Vec::new(),
                sent_at: Vec::new(),
                last_heard: now,
                presumed_dead: false,
                jobs_done: 0,
            });
        if worker.incarnation != credit.incarnation {
            let lost = std::mem::take(&mut worker.outstanding);
            worker.sent_at.clear();
            let level_warn = !lost.is_empty();
            if level_warn {
                tracing::warn!(
                    "{}: worker {} restarted; redoing its {} unfinished job(s)",
                    self.link,
                    credit.worker_index,
                    lost.len()
                );
            } else {
                tracing::debug!(
                    "{}: worker {} restarted or left with no unfinished job",
                    self.link,
                    credit.worker_index
                );
            }
            worker.incarnation = credit.incarnation;
            worker.last_heard = now;
            worker.presumed_dead = false;
            worker.slots = credit.free_slots;
            self.requeue(lost);
            return;
        }
        worker.last_heard = now;
        worker.presumed_dead = false;
        worker.slots = credit.free_slots;
        for key in &credit.completed {
            if let Some(position) = worker.outstanding.iter().position(|(k, _)| k == key) {
                worker.outstanding.remove(position);
                worker.sent_at.remove(position);
                worker.jobs_done += 1;
            }
        }
    }

    fn redo_silent(&mut self, now: Instant) {
        let mut lost = Vec::new();
        for (index, worker) in &mut self.workers {
            if !worker.presumed_dead && now.duration_since(worker.last_heard) > self.silence_limit {
                worker.presumed_dead = true;
                if !worker.outstanding.is_empty() {
                    tracing::warn!(
                        "{}: worker {index} silent for {:.0} s; redoing its {} job(s) elsewhere",
                        self.link,
                        now.duration_since(worker.last_heard).as_secs_f64(),
                        worker.outstanding.len()
                    );
                    lost.append(&mut worker.outstanding);
                    worker.sent_at.clear();
                }
            } else if !worker.presumed_dead {
                // A job out longer than the silence limit (longer than the slowest job) with
                // its worker alive was lost on the way (e.g. while the zenoh router restarted):
                // redone (a late finish is harmless: downstream keeps the first).
                let mut kept = 0;
                while kept < worker.outstanding.len() {
                    if now.duration_since(worker.sent_at[kept]) > self.silence_limit {
                        tracing::warn!(
                            "{}: job {:?} of worker {index} unfinished after {:.0} s; redoing it",
                            self.link,
                            worker.outstanding[kept].0,
                            self.silence_limit.as_secs_f64()
                        );
                        lost.push(worker.outstanding.remove(kept));
                        worker.sent_at.remove(kept);
                    } else {
                        kept += 1;
                    }
                }
            }
        }
        if !lost.is_empty() {
            self.requeue(lost);
        }
    }

    fn assign(&mut self) -> Result<(), BusError> {
        while !self.queue.is_empty() {
            // The free worker with the fewest jobs outstanding (lowest index on ties).
            let Some(index) = self
                .workers
                .iter()
                .filter(|(_, w)| !w.presumed_dead && (w.outstanding.len() as u32) < w.slots)
                .min_by_key(|(index, w)| (w.outstanding.len(), **index))
                .map(|(index, _)| *index)
            else {
                return Ok(());
            };
            let Some(job) = self.queue.pop_front() else {
                return Ok(());
            };
            if !self.outboxes.contains_key(&index) {
                let mut outbox = Outbox::open(self.transport, &keys::jobs(&self.link, index))?;
                outbox.wait_for_reader("worker", Duration::from_secs(10))?;
                self.outboxes.insert(index, outbox);
            }
            if let Some(outbox) = self.outboxes.get_mut(&index) {
                outbox.send_encoded(&job.1, &mut self.metrics)?;
            }
            if let Some(worker) = self.workers.get_mut(&index) {
                worker.outstanding.push(job);
                worker.sent_at.push(Instant::now());
            }
        }
        Ok(())
    }
}

/// The worker side of a dispatched link.
pub struct WorkerPort {
    jobs: Inbox,
    credits: Outbox,
    worker_index: u32,
    incarnation: u64,
    slots: u32,
    /// Jobs finished within [`COMPLETED_REPEAT`], repeated in every credit (a credit lost on
    /// the way, e.g. while the zenoh router restarts, would leave the job outstanding for ever).
    completed: VecDeque<(JobKey, Instant)>,
    last_credit: Option<Instant>,
}

impl WorkerPort {
    pub fn open(
        transport: &dyn Transport,
        link: &str,
        worker_index: u32,
        slots: u32,
        stage: &str,
    ) -> Result<Self, BusError> {
        // A new value per start, so the dispatcher can tell a restart from a slow worker.
        let incarnation = super::bus::unix_time_ns() ^ u64::from(std::process::id()) << 32;
        Ok(Self {
            jobs: Inbox::open(transport, &keys::jobs(link, worker_index), stage)?,
            credits: Outbox::open(transport, &keys::credits(link))?,
            worker_index,
            incarnation,
            slots: slots.max(1),
            completed: VecDeque::new(),
            last_credit: None,
        })
    }

    fn send_credit(&mut self) -> Result<(), BusError> {
        while self
            .completed
            .front()
            .is_some_and(|(_, at)| at.elapsed() > COMPLETED_REPEAT)
        {
            self.completed.pop_front();
        }
        let credit = Credit {
            worker_index: self.worker_index,
            incarnation: self.incarnation,
            completed: self.completed.iter().map(|(key, _)| *key).collect(),
            free_slots: self.slots,
        };
        let mut scratch = StageMetrics::default();
        self.credits
            .send(0, 0, Body::Credit(credit), &mut scratch)?;
        self.last_credit = Some(Instant::now());
        Ok(())
    }

    /// Tells the dispatcher this worker is alive while it is not taking jobs.
    pub fn heartbeat(&mut self) -> Result<(), BusError> {
        if self
            .last_credit
            .is_none_or(|at| at.elapsed() >= CREDIT_INTERVAL)
        {
            self.send_credit()?;
        }
        Ok(())
    }

    /// Reports a finished job at once (so the dispatcher can send the next).
    pub fn finished(&mut self, key: JobKey) -> Result<(), BusError> {
        self.completed.push_back((key, Instant::now()));
        self.send_credit()
    }

    /// A worker that stops (SIGTERM) hands back the jobs it was given and has not finished: it
    /// reports its finished ones and announces a new incarnation with no free slot, which the
    /// dispatcher treats like a restart (the unfinished jobs are redone elsewhere at once) and
    /// sends it nothing more.
    pub fn leave(&mut self) -> Result<(), BusError> {
        self.incarnation = self.incarnation.wrapping_add(1);
        self.slots = 0;
        self.send_credit()
    }

    /// Waits up to `timeout` for a job (sending heartbeat credits meanwhile).
    pub fn receive(
        &mut self,
        timeout: Duration,
        metrics: &mut StageMetrics,
        handle: &mut dyn FnMut(crate::msg::Envelope<'_>, &mut StageMetrics),
    ) -> Result<bool, BusError> {
        if self
            .last_credit
            .is_none_or(|at| at.elapsed() >= CREDIT_INTERVAL)
        {
            self.send_credit()?;
        }
        self.jobs
            .receive(timeout.min(CREDIT_INTERVAL), metrics, handle)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::StreamEnd;
    use crate::runtime::bus::encode_to_vec;
    use crate::transport::conformance::config;
    use crate::transport::crossbeam::CrossbeamTransport;

    fn job(frame_id: u64) -> (JobKey, Vec<u8>) {
        let key = JobKey {
            frame_id,
            coarse_index: 0,
        };
        let bytes = encode_to_vec(
            frame_id,
            0,
            Body::StreamEnd(StreamEnd {
                frame_count: 0,
                finished_frames: Vec::new(),
            }),
        )
        .unwrap();
        (key, bytes)
    }

    /// The frame id of the next job a worker receives (pumping the dispatcher meanwhile).
    fn next_job(worker: &mut WorkerPort, dispatcher: &mut Dispatcher) -> u64 {
        let mut metrics = StageMetrics::default();
        for _ in 0..500 {
            dispatcher.pump(Duration::from_millis(2)).unwrap();
            let mut got = None;
            worker
                .receive(Duration::from_millis(2), &mut metrics, &mut |message, _| {
                    got = Some(message.header.frame_id)
                })
                .unwrap();
            if let Some(frame_id) = got {
                return frame_id;
            }
        }
        panic!("no job arrived");
    }

    #[test]
    fn each_job_goes_to_one_worker_and_a_restarted_workers_jobs_are_redone() {
        let transport = CrossbeamTransport::new(config("dispatch"));
        let mut dispatcher =
            Dispatcher::open(&transport, "link", 10, Duration::from_secs(60)).unwrap();
        let mut first = WorkerPort::open(&transport, "link", 0, 1, "test").unwrap();
        let mut second = WorkerPort::open(&transport, "link", 1, 1, "test").unwrap();
        for frame_id in 0..3 {
            let (key, bytes) = job(frame_id);
            dispatcher.push(key, bytes);
        }
        // One slot each: the first two jobs go one to each worker, the third waits.
        let a = next_job(&mut first, &mut dispatcher);
        let b = next_job(&mut second, &mut dispatcher);
        assert_ne!(a, b);
        dispatcher.pump(Duration::from_millis(20)).unwrap();
        assert_eq!(dispatcher.queued(), 1);
        assert_eq!(dispatcher.outstanding(), 2);

        // Worker 0 dies holding job `a`; its restart announces a new incarnation.
        drop(first);
        std::thread::sleep(Duration::from_millis(2));
        let mut restarted = WorkerPort::open(&transport, "link", 0, 1, "test").unwrap();
        let redone = next_job(&mut restarted, &mut dispatcher);
        assert_eq!(redone, a, "the dead worker's job is redone first");
        assert_eq!(dispatcher.metrics.redispatched, 1);

        // Both finish; the waiting job goes to whichever is free; then all is done.
        second
            .finished(JobKey {
                frame_id: b,
                coarse_index: 0,
            })
            .unwrap();
        let c = next_job(&mut second, &mut dispatcher);
        assert_eq!(
            [a, b, c]
                .iter()
                .collect::<std::collections::BTreeSet<_>>()
                .len(),
            3
        );
        for (worker, frame_id) in [(&mut restarted, a), (&mut second, c)] {
            worker
                .finished(JobKey {
                    frame_id,
                    coarse_index: 0,
                })
                .unwrap();
        }
        for _ in 0..100 {
            dispatcher.pump(Duration::from_millis(5)).unwrap();
            if dispatcher.is_idle() {
                break;
            }
        }
        assert!(dispatcher.is_idle());
        assert_eq!(dispatcher.jobs_done().values().sum::<u64>(), 3);
    }

    /// Work sharing without relying on the scheduler: a worker whose every slot holds an
    /// unfinished job gets nothing more, so the other worker takes every job meanwhile, and the
    /// busy one gets work again as soon as it finishes.
    #[test]
    fn while_one_worker_is_busy_the_other_takes_every_job() {
        let transport = CrossbeamTransport::new(config("busy"));
        let mut dispatcher =
            Dispatcher::open(&transport, "link", 10, Duration::from_secs(600)).unwrap();
        let mut busy = WorkerPort::open(&transport, "link", 0, 1, "test").unwrap();
        let mut free = WorkerPort::open(&transport, "link", 1, 1, "test").unwrap();
        let (key, bytes) = job(0);
        dispatcher.push(key, bytes);
        assert_eq!(next_job(&mut busy, &mut dispatcher), 0);
        for frame_id in 1..5 {
            let (key, bytes) = job(frame_id);
            dispatcher.push(key, bytes);
            assert_eq!(next_job(&mut free, &mut dispatcher), frame_id);
            free.finished(JobKey {
                frame_id,
                coarse_index: 0,
            })
            .unwrap();
        }
        // The busy worker finishes; the next job may go to either, and one of them takes it.
        busy.finished(JobKey {
            frame_id: 0,
            coarse_index: 0,
        })
        .unwrap();
        let (key, bytes) = job(5);
        dispatcher.push(key, bytes);
        for _ in 0..100 {
            dispatcher.pump(Duration::from_millis(5)).unwrap();
            if dispatcher.queued() == 0 && dispatcher.outstanding() == 1 {
                break;
            }
        }
        assert_eq!((dispatcher.queued(), dispatcher.outstanding()), (0, 1));
        assert_eq!(
            dispatcher.jobs_done().into_iter().collect::<Vec<_>>(),
            vec![(0, 1), (1, 4)]
        );
        assert_eq!(dispatcher.metrics.redispatched, 0);
    }

    #[test]
    fn a_silent_workers_jobs_are_redone_elsewhere() {
        let transport = CrossbeamTransport::new(config("silence"));
        let mut dispatcher =
            Dispatcher::open(&transport, "link", 10, Duration::from_millis(300)).unwrap();
        let mut silent = WorkerPort::open(&transport, "link", 0, 1, "test").unwrap();
        let (key, bytes) = job(7);
        dispatcher.push(key, bytes);
        assert_eq!(next_job(&mut silent, &mut dispatcher), 7);
        // Worker 0 goes quiet (no credits); worker 1 appears and gets the job after the limit.
        let mut other = WorkerPort::open(&transport, "link", 1, 1, "test").unwrap();
        let started = Instant::now();
        assert_eq!(next_job(&mut other, &mut dispatcher), 7);
        assert!(started.elapsed() >= Duration::from_millis(250));
        assert_eq!(dispatcher.metrics.redispatched, 1);
    }

    #[test]
    fn a_leaving_worker_hands_back_its_jobs_at_once() {
        let transport = CrossbeamTransport::new(config("leave"));
        // A silence limit far beyond the test: only the hand-back can move the job.
        let mut dispatcher =
            Dispatcher::open(&transport, "link", 10, Duration::from_secs(600)).unwrap();
        let mut leaving = WorkerPort::open(&transport, "link", 0, 1, "test").unwrap();
        let (key, bytes) = job(3);
        dispatcher.push(key, bytes);
        assert_eq!(next_job(&mut leaving, &mut dispatcher), 3);
        leaving.leave().unwrap();
        let mut other = WorkerPort::open(&transport, "link", 1, 1, "test").unwrap();
        assert_eq!(next_job(&mut other, &mut dispatcher), 3);
        assert_eq!(dispatcher.metrics.redispatched, 1);
        // The leaver gets nothing more.
        let (key, bytes) = job(4);
        dispatcher.push(key, bytes);
        dispatcher.pump(Duration::from_millis(20)).unwrap();
        assert_eq!(dispatcher.queued(), 1, "a job went to the worker that left");
    }
}
