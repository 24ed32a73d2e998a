//! `VecEnv`: N independent PushT environments stepped in parallel.
//!
//! Every environment owns its physics world, and a step of one environment is the same
//! computation whichever thread runs it, so results do not depend on the number of threads
//! or on scheduling (a test checks 1 thread against several). From [`PARALLEL_MIN_ENVS`]
//! environments on, `threads - 1` worker threads live as long as the `VecEnv` (the count is
//! rayon's at construction, so `RAYON_NUM_THREADS` and `ThreadPool::install` set it); at
//! each tick the calling thread and the workers claim environments one at a time from a
//! shared counter, so a thread whose environments are in contact (slower physics) does not
//! hold the others up.
//!
//! A tick is 5-20 µs of physics per environment, so waking a thread must cost far less:
//! starting one (or waking a sleeping pool) costs about as much as a tick. A worker therefore
//! spins for [`WORKER_SPIN`] after its last tick, waiting for the next with no system call,
//! and only then parks; a control loop that ticks continuously never pays a wake-up, and an
//! idle `VecEnv` costs nothing after that window.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::env::{PhysicsConfig, PushT, State, StepInfo};
use crate::error::SimError;
use crate::rng::ResetStream;

/// The fewest environments stepped on several threads; fewer run on the calling thread
/// (`benches/step.rs`, `vec_env_tick` against `plain_loop_tick`).
pub const PARALLEL_MIN_ENVS: usize = 8;

/// How long an idle worker waits for the next job by spinning before it parks.
pub const WORKER_SPIN: Duration = Duration::from_micros(200);

/// A batch of PushT environments.
pub struct VecEnv {
    shared: Arc<Shared>,
    workers: Vec<JoinHandle<()>>,
}

/// One environment with its input and output of the current tick.
struct Slot {
    env: PushT,
    job: Job,
    done: Done,
}

/// One environment's input of a tick.
#[derive(Clone, Copy)]
enum Job {
    Idle,
    Step([f64; 2]),
    Reset(u64, ResetStream),
}

/// One environment's result of a tick.
enum Done {
    Empty,
    Step(Result<StepInfo, SimError>),
    Reset(Result<State, SimError>),
}

impl Slot {
    fn run(&mut self) {
        self.done = match std::mem::replace(&mut self.job, Job::Idle) {
            Job::Idle => Done::Empty,
            Job::Step(a) => Done::Step(self.env.step(a)),
            Job::Reset(seed, stream) => Done::Reset(self.env.reset(seed, stream)),
        };
    }
}

/// What the calling thread and the workers share.
struct Shared {
    slots: Vec<Mutex<Slot>>,
    /// Ticks posted so far; a worker joins in whenever it moves.
    posted: AtomicU64,
    /// The next environment to claim in the current tick.
    next: AtomicUsize,
    /// Environments finished in the current tick.
    finished: AtomicUsize,
    stop: AtomicBool,
}

impl Shared {
    /// Slot `i`, also after a panic elsewhere (a poisoned lock holds consistent data here: a
    /// result replaces the previous one whole).
    fn slot(&self, i: usize) -> MutexGuard<'_, Slot> {
        self.slots[i].lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Claims and runs environments until none is left in this tick.
    fn claim(&self) {
        loop {
            let i = self.next.fetch_add(1, Ordering::AcqRel);
            if i >= self.slots.len() {
                return;
            }
            self.slot(i).run();
            self.finished.fetch_add(1, Ordering::Release);
        }
    }
}

/// A worker's loop: join each posted tick, spin for the next for [`WORKER_SPIN`], then park.
fn work(shared: &Shared) {
    let mut seen = 0u64;
    let mut idle_since = Instant::now();
    loop {
        if shared.stop.load(Ordering::Acquire) {
            return;
        }
        let posted = shared.posted.load(Ordering::Acquire);
        if posted == seen {
            if idle_since.elapsed() < WORKER_SPIN {
                std::hint::spin_loop();
            } else {
                std::thread::park();
            }
            continue;
        }
        seen = posted;
        shared.claim();
        idle_since = Instant::now();
    }
}

impl VecEnv {
    /// `n` environments with the same physics configuration; from [`PARALLEL_MIN_ENVS`] on,
    /// stepped by as many threads as rayon's current count.
    pub fn new(n: usize, config: PhysicsConfig) -> Self {
        let slots = (0..n)
            .map(|_| {
                Mutex::new(Slot {
                    env: PushT::new(config),
                    job: Job::Idle,
                    done: Done::Empty,
                })
            })
            .collect();
        let shared = Arc::new(Shared {
            slots,
            posted: AtomicU64::new(0),
            next: AtomicUsize::new(0),
            finished: AtomicUsize::new(0),
            stop: AtomicBool::new(false),
        });
        let threads = rayon::current_num_threads();
        let workers = if n < PARALLEL_MIN_ENVS || threads < 2 {
            Vec::new()
        } else {
            (1..threads)
                .map(|_| {
                    let theirs = Arc::clone(&shared);
                    std::thread::spawn(move || work(&theirs))
                })
                .collect()
        };
        VecEnv { shared, workers }
    }

    /// Number of environments.
    pub fn len(&self) -> usize {
        self.shared.slots.len()
    }

    /// True when the batch is empty.
    pub fn is_empty(&self) -> bool {
        self.shared.slots.is_empty()
    }

    /// Threads that step the environments (the calling one included).
    pub fn threads(&self) -> usize {
        1 + self.workers.len()
    }

    /// `f(environment)` for every environment, in order (to read observations).
    pub fn observe<R>(&self, mut f: impl FnMut(&PushT) -> R) -> Vec<R> {
        (0..self.len())
            .map(|i| f(&self.shared.slot(i).env))
            .collect()
    }

    /// `f(index, environment)` for every environment, in order, with mutable access.
    pub fn for_each_mut(&mut self, mut f: impl FnMut(usize, &mut PushT)) {
        for i in 0..self.len() {
            f(i, &mut self.shared.slot(i).env);
        }
    }

    /// Reset environment `i` with seed `seeds[i]`.
    pub fn reset(&mut self, seeds: &[u64], stream: ResetStream) -> Result<Vec<State>, SimError> {
        self.check_len(seeds.len())?;
        let done = self.tick(|i| Job::Reset(seeds[i], stream));
        results(done, |d| match d {
            Done::Reset(r) => Some(r),
            _ => None,
        })
    }

    /// Step environment `i` towards `actions[i]`. On error no environment is stepped.
    pub fn step(&mut self, actions: &[[f64; 2]]) -> Result<Vec<StepInfo>, SimError> {
        self.check_len(actions.len())?;
        if let Some(a) = actions.iter().find(|a| !a.iter().all(|v| v.is_finite())) {
            return Err(SimError::NonFiniteAction { action: *a });
        }
        let done = self.tick(|i| Job::Step(actions[i]));
        results(done, |d| match d {
            Done::Step(r) => Some(r),
            _ => None,
        })
    }

    /// Posts `job(i)` to every environment, claims environments beside the workers until
    /// all are done, and takes the results in order.
    fn tick(&mut self, job: impl Fn(usize) -> Job) -> Vec<Done> {
        let shared = Arc::clone(&self.shared);
        let s = &*shared;
        for i in 0..s.slots.len() {
            s.slot(i).job = job(i);
        }
        // `finished` before `next`, and `next` released: a worker that claims index 0 of this
        // tick sees the zeroed count, so its completion is not lost.
        s.finished.store(0, Ordering::Relaxed);
        s.next.store(0, Ordering::Release);
        s.posted.fetch_add(1, Ordering::Release);
        for w in &self.workers {
            w.thread().unpark(); // no system call unless the worker is parked
        }
        s.claim();
        let start = Instant::now();
        while s.finished.load(Ordering::Acquire) < s.slots.len() {
            if start.elapsed() < WORKER_SPIN {
                std::hint::spin_loop();
            } else {
                self.resume_dead_worker();
                std::thread::yield_now();
            }
        }
        (0..s.slots.len())
            .map(|i| std::mem::replace(&mut s.slot(i).done, Done::Empty))
            .collect()
    }

    /// A worker that died (a bug in the physics, which panicked mid-step) resumes its panic
    /// here, rather than leaving the tick waiting for its environment forever.
    fn resume_dead_worker(&mut self) {
        if let Some(k) = self.workers.iter().position(JoinHandle::is_finished)
            && let Err(p) = self.workers.swap_remove(k).join()
        {
            std::panic::resume_unwind(p);
        }
    }

    fn check_len(&self, given: usize) -> Result<(), SimError> {
        if given == self.len() {
            Ok(())
        } else {
            Err(SimError::BatchSize {
                actions: given,
                envs: self.len(),
            })
        }
    }
}

/// The results of a tick in order, `pick` taking each environment's of the expected kind; an
/// environment without one is [`SimError::NoResult`].
fn results<T>(
    done: Vec<Done>,
    pick: impl Fn(Done) -> Option<Result<T, SimError>>,
) -> Result<Vec<T>, SimError> {
    done.into_iter()
        .enumerate()
        .map(|(index, d)| pick(d).unwrap_or(Err(SimError::NoResult { index })))
        .collect()
}

impl Drop for VecEnv {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
        for w in self.workers.drain(..) {
            w.thread().unpark();
            let _ = w.join(); // a worker's panic was already resumed by the tick that saw it
        }
    }
}
