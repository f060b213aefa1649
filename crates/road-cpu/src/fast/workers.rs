//! The fast engine's threads: helper threads kept between calls, the barrier at which the
//! workers that split one batch meet, and the exchange of their attention projections.
//!
//! Why helpers kept between calls: one evaluation of a 7-agent scene takes ≈ 1 ms and a tick
//! makes 8 of them, back to back. A thread spawned per call costs tens of microseconds, and
//! on this VM's scheduler it starts on its parent's core and waits there until the parent
//! blocks (measured: 0.2–0.5 ms from `spawn` to its first instruction while the parent
//! computes). A helper that spins for a while after each job picks the next one up within a
//! microsecond, and sleeps when no call follows.

use std::panic::{AssertUnwindSafe, catch_unwind, resume_unwind};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, RwLock, RwLockReadGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How long a helper spins for its next job before it sleeps: longer than the gap between the
/// evaluations of a tick (a Heun update), far shorter than the gap between ticks.
const HELPER_SPIN: Duration = Duration::from_micros(500);

/// How long a worker spins at a barrier, or the caller for its helpers' results, before it
/// sleeps: longer than workers of equal shares drift apart within a stage.
const MEETING_SPIN: Duration = Duration::from_micros(200);

/// Spins until `ready()` or until `limit` has passed; whether it got ready. It yields its
/// core now and then, to a thread of another call (another engine) that waits for one.
fn spin_until(ready: impl Fn() -> bool, limit: Duration) -> bool {
    let start = Instant::now();
    loop {
        for _ in 0..64 {
            if ready() {
                return true;
            }
            std::hint::spin_loop();
        }
        if start.elapsed() > limit {
            return false;
        }
        std::thread::yield_now();
    }
}

/// A job for a helper: it gets the helper's own state `L` (buffers kept between calls).
pub(super) type Job<L, R> = Box<dyn FnOnce(&mut L) -> R + Send>;

/// Helper threads, started with it and kept until dropped; each keeps its own `L`.
pub(super) struct Helpers<L, R> {
    helpers: Vec<Helper<L, R>>,
}

struct Helper<L, R> {
    shared: Arc<HelperShared<L, R>>,
    /// Jobs posted so far (the helper's `finished` reaches it when the last is done).
    posted: usize,
    thread: Option<JoinHandle<()>>,
}

struct HelperShared<L, R> {
    state: Mutex<HelperState<L, R>>,
    /// Wakes the helper (a job, or stop) and the caller (a result).
    wake: Condvar,
    /// Jobs posted and finished, read by the spinning side without the lock.
    posted: AtomicUsize,
    finished: AtomicUsize,
}

struct HelperState<L, R> {
    job: Option<Job<L, R>>,
    done: Option<std::thread::Result<R>>,
    helper_sleeping: bool,
    caller_sleeping: bool,
    stop: bool,
}

impl<L, R> std::fmt::Debug for Helpers<L, R> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Helpers")
            .field("threads", &self.helpers.len())
            .finish()
    }
}

impl<L: Default + 'static, R: Send + 'static> Helpers<L, R> {
    /// `count` helper threads, started now: a thread's first wake-up goes to an idle core,
    /// while a thread started in the middle of a call would wait on its parent's core.
    pub(super) fn new(count: usize) -> Self {
        Self {
            helpers: (0..count).map(Helper::spawn).collect(),
        }
    }

    /// Runs `jobs[i]` on helper i and `own` on the calling thread, all at once; returns the
    /// jobs' results in order once all are done. A panic in any of them is raised here, after
    /// all have finished.
    pub(super) fn run(&mut self, jobs: Vec<Job<L, R>>, own: impl FnOnce()) -> Vec<R> {
        assert!(
            jobs.len() <= self.helpers.len(),
            "{} jobs for {} helpers",
            jobs.len(),
            self.helpers.len()
        );
        let count = jobs.len();
        for (helper, job) in self.helpers.iter_mut().zip(jobs) {
            helper.post(job);
        }
        let own = catch_unwind(AssertUnwindSafe(own));
        let results: Vec<_> = self.helpers[..count].iter_mut().map(Helper::wait).collect();
        if let Err(panic) = own {
            resume_unwind(panic);
        }
        results
            .into_iter()
            .map(|result| result.unwrap_or_else(|panic| resume_unwind(panic)))
            .collect()
    }
}

impl<L: Default + 'static, R: Send + 'static> Helper<L, R> {
    fn spawn(index: usize) -> Self {
        let shared = Arc::new(HelperShared {
            state: Mutex::new(HelperState {
                job: None,
                done: None,
                helper_sleeping: false,
                caller_sleeping: false,
                stop: false,
            }),
            wake: Condvar::new(),
            posted: AtomicUsize::new(0),
            finished: AtomicUsize::new(0),
        });
        let thread = std::thread::Builder::new()
            .name(format!("road-fast-{index}"))
            .spawn({
                let shared = Arc::clone(&shared);
                move || serve(&shared)
            })
            .expect("spawn a worker thread of the fast engine");
        Self {
            shared,
            posted: 0,
            thread: Some(thread),
        }
    }

    fn post(&mut self, job: Job<L, R>) {
        let mut state = self.shared.state.lock().expect("helper lock");
        state.job = Some(job);
        self.posted += 1;
        self.shared.posted.store(self.posted, Ordering::Release);
        if state.helper_sleeping {
            self.shared.wake.notify_all();
        }
    }

    fn wait(&mut self) -> std::thread::Result<R> {
        let posted = self.posted;
        let finished = &self.shared.finished;
        spin_until(|| finished.load(Ordering::Acquire) == posted, MEETING_SPIN);
        let mut state = self.shared.state.lock().expect("helper lock");
        loop {
            if let Some(done) = state.done.take() {
                return done;
            }
            state.caller_sleeping = true;
            state = self.shared.wake.wait(state).expect("helper lock");
            state.caller_sleeping = false;
        }
    }
}

impl<L, R> Drop for Helpers<L, R> {
    fn drop(&mut self) {
        for helper in &self.helpers {
            if let Ok(mut state) = helper.shared.state.lock() {
                state.stop = true;
            }
            helper.shared.wake.notify_all();
        }
        for helper in &mut self.helpers {
            if let Some(thread) = helper.thread.take() {
                // A helper's panics are caught and handed to the caller: it exits cleanly.
                let _ = thread.join();
            }
        }
    }
}

/// A helper's loop: wait for a job (asleep for the first, then spinning a while after each
/// before it sleeps), run it, hand back its result.
fn serve<L: Default, R>(shared: &HelperShared<L, R>) {
    let mut local = L::default();
    let mut served = 0;
    loop {
        if served > 0 {
            spin_until(
                || shared.posted.load(Ordering::Acquire) != served,
                HELPER_SPIN,
            );
        }
        let job = {
            let mut state = shared.state.lock().expect("helper lock");
            loop {
                if state.stop {
                    return;
                }
                if let Some(job) = state.job.take() {
                    break job;
                }
                state.helper_sleeping = true;
                state = shared.wake.wait(state).expect("helper lock");
                state.helper_sleeping = false;
            }
        };
        served += 1;
        let result = catch_unwind(AssertUnwindSafe(|| job(&mut local)));
        if result.is_err() {
            // A job cut short may leave its buffers (the agent-map memo) half written.
            local = L::default();
        }
        let mut state = shared.state.lock().expect("helper lock");
        state.done = Some(result);
        shared.finished.store(served, Ordering::Release);
        if state.caller_sleeping {
            shared.wake.notify_all();
        }
    }
}

/// A barrier for the workers of one call that spins before it sleeps: the workers reach each
/// meeting within microseconds of each other, while a sleep and a wake-up cost tens of
/// microseconds, every meeting. Spinning is bounded, so a worker whose partner waits for a
/// core (a loaded machine) goes to sleep.
#[derive(Debug)]
pub(super) struct StageBarrier {
    parties: usize,
    /// Meetings completed (read by spinning workers without the lock).
    generation: AtomicUsize,
    state: Mutex<BarrierState>,
    wake: Condvar,
    /// Set when a worker panics: the others would wait for it forever.
    broken: AtomicBool,
    /// Nanoseconds the workers spent waiting for each other, all meetings together.
    waited_ns: AtomicU64,
}

#[derive(Debug, Default)]
struct BarrierState {
    arrived: usize,
    sleeping: usize,
}

impl StageBarrier {
    fn new(parties: usize) -> Self {
        Self {
            parties,
            generation: AtomicUsize::new(0),
            state: Mutex::new(BarrierState::default()),
            wake: Condvar::new(),
            broken: AtomicBool::new(false),
            waited_ns: AtomicU64::new(0),
        }
    }

    fn wait(&self) {
        let arrived = Instant::now();
        let generation = self.generation.load(Ordering::Acquire);
        {
            let mut state = self.state.lock().expect("barrier lock");
            state.arrived += 1;
            if state.arrived == self.parties {
                state.arrived = 0;
                self.generation.store(generation + 1, Ordering::Release);
                if state.sleeping > 0 {
                    state.sleeping = 0;
                    self.wake.notify_all();
                }
                return;
            }
        }
        let met = || {
            self.generation.load(Ordering::Acquire) != generation
                || self.broken.load(Ordering::Acquire)
        };
        if !spin_until(met, MEETING_SPIN) {
            let mut state = self.state.lock().expect("barrier lock");
            while !met() {
                state.sleeping += 1;
                state = self.wake.wait(state).expect("barrier lock");
            }
        }
        let waited = u64::try_from(arrived.elapsed().as_nanos()).unwrap_or(u64::MAX);
        self.waited_ns.fetch_add(waited, Ordering::Relaxed);
        assert!(
            !self.broken.load(Ordering::Acquire),
            "another worker of the call panicked"
        );
    }
}

/// Releases the other workers of a call (with a panic of their own) when dropped while its
/// thread panics, instead of leaving them waiting at the barrier.
pub(super) struct BreakOnPanic<'a>(&'a StageBarrier);

impl Drop for BreakOnPanic<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.broken.store(true, Ordering::Release);
            let _state = self.0.state.lock();
            self.0.wake.notify_all();
        }
    }
}

/// A worker's two projection slots, by the parity of the meeting.
pub(super) type Slots = [RwLock<Vec<f32>>; 2];

/// How the workers that split a batch's tokens meet. The attention stages read other tokens'
/// keys: time attention an agent's other slots, agent attention a slot's other agents, and
/// those may be another worker's (every other stage works token by token). Before each, every
/// worker writes its tokens' `[q; k; v]` into its own slot, waits at the barrier for the
/// others, then reads every slot: two meetings per block. Two slots per worker, by the parity
/// of the meeting: a worker that runs ahead writes the next meeting's projections while a
/// slower one still reads this one's (it cannot run two meetings ahead: the next barrier
/// holds it). The locks are never contended; they let safe code share the slots.
#[derive(Debug)]
pub(super) struct Exchange {
    /// Per worker, `[tokens, 3D]` by parity, indexed by compact token over the batch (a
    /// worker fills only its own rows).
    slots: Arc<[Slots]>,
    /// The compact token where each worker's rows end.
    token_ends: Vec<usize>,
    barrier: StageBarrier,
}

impl Exchange {
    /// The workers whose tokens end at `token_ends`, with slots `0..token_ends.len()`.
    pub(super) fn new(slots: Arc<[Slots]>, token_ends: Vec<usize>) -> Self {
        let barrier = StageBarrier::new(token_ends.len());
        Self {
            slots,
            token_ends,
            barrier,
        }
    }

    /// Whether the workers of a call that took `call` spent over a third of their time
    /// waiting for each other at the meetings (read after the call). Measured on a quiet
    /// machine: 1–2 % (median), 4–5 % (p90), single calls up to 36 %; with a busy process
    /// beside them, where a worker waits for a core and keeps the others waiting a scheduler
    /// slice: 43–49 % for one scene.
    pub(super) fn contended(&self, call: Duration) -> bool {
        let waited = Duration::from_nanos(self.barrier.waited_ns.load(Ordering::Relaxed));
        let workers = u32::try_from(self.token_ends.len()).unwrap_or(u32::MAX);
        waited * 3 > call * workers
    }

    /// A guard for worker threads: see [`BreakOnPanic`].
    pub(super) fn break_on_panic(&self) -> BreakOnPanic<'_> {
        BreakOnPanic(&self.barrier)
    }

    /// Lets `write` fill worker `worker`'s slot of `parity`, at least `len` values long.
    pub(super) fn publish(
        &self,
        worker: usize,
        parity: usize,
        len: usize,
        write: impl FnOnce(&mut [f32]),
    ) {
        let mut slot = self.slots[worker][parity]
            .write()
            .expect("projections lock");
        if slot.len() < len {
            slot.resize(len, 0.0);
        }
        write(&mut slot);
    }

    /// Every worker's slot of `parity`, once all have published theirs.
    pub(super) fn gather(&self, parity: usize) -> Published<'_> {
        self.barrier.wait();
        let guards = self.slots[..self.token_ends.len()]
            .iter()
            .map(|slots| slots[parity].read().expect("projections lock"))
            .collect();
        Published {
            guards,
            token_ends: &self.token_ends,
        }
    }
}

/// Every worker's projections of one meeting (read-locked until dropped).
pub(super) struct Published<'a> {
    guards: Vec<RwLockReadGuard<'a, Vec<f32>>>,
    token_ends: &'a [usize],
}

impl Published<'_> {
    /// `(end of the worker's tokens, its projections)` per worker, in order.
    pub(super) fn parts(&self) -> Vec<(usize, &[f32])> {
        self.token_ends
            .iter()
            .zip(&self.guards)
            .map(|(&end, slot)| (end, slot.as_slice()))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Helpers run their jobs beside the caller's own work, keep their state between calls,
    /// and hand a job's panic to the caller, staying usable afterwards.
    #[test]
    fn helpers_run_jobs_keep_state_and_report_panics() {
        let mut helpers: Helpers<Vec<usize>, usize> = Helpers::new(2);
        for call in 0..3 {
            let jobs: Vec<Job<Vec<usize>, usize>> = (0..2)
                .map(|i| -> Job<Vec<usize>, usize> {
                    Box::new(move |seen: &mut Vec<usize>| {
                        seen.push(call);
                        i * 10 + seen.len()
                    })
                })
                .collect();
            let mut own_ran = false;
            let results = helpers.run(jobs, || own_ran = true);
            assert!(own_ran);
            assert_eq!(results, vec![call + 1, 10 + call + 1]);
        }
        let jobs: Vec<Job<Vec<usize>, usize>> = vec![Box::new(|_| panic!("a job fails"))];
        let caught = catch_unwind(AssertUnwindSafe(|| helpers.run(jobs, || ())));
        assert!(caught.is_err());
        let jobs: Vec<Job<Vec<usize>, usize>> = vec![Box::new(|seen| seen.len())];
        assert_eq!(
            helpers.run(jobs, || ()),
            vec![0],
            "state reset after a panic"
        );
    }

    /// A barrier meets as many times as asked, and a worker that panics releases the others.
    #[test]
    fn barrier_meets_and_breaks() {
        let barrier = StageBarrier::new(3);
        let count = AtomicUsize::new(0);
        std::thread::scope(|scope| {
            for _ in 0..3 {
                scope.spawn(|| {
                    for round in 0..100 {
                        count.fetch_add(1, Ordering::SeqCst);
                        barrier.wait();
                        assert!(count.load(Ordering::SeqCst) >= 3 * (round + 1));
                        barrier.wait();
                    }
                });
            }
        });

        // A partner late for most of the call: contention.
        let exchange = Exchange::new(Arc::new([Slots::default(), Slots::default()]), vec![1, 2]);
        std::thread::scope(|scope| {
            scope.spawn(|| {
                while exchange.barrier.state.lock().expect("barrier lock").arrived == 0 {
                    std::thread::yield_now();
                }
                std::thread::sleep(MEETING_SPIN * 5);
                exchange.barrier.wait();
            });
            exchange.barrier.wait();
        });
        assert!(exchange.contended(MEETING_SPIN * 5));
        assert!(!exchange.contended(MEETING_SPIN * 100));

        let barrier = StageBarrier::new(2);
        let outcome = catch_unwind(AssertUnwindSafe(|| {
            std::thread::scope(|scope| {
                scope.spawn(|| {
                    let _release = BreakOnPanic(&barrier);
                    panic!("a worker fails before the meeting");
                });
                barrier.wait();
            })
        }));
        assert!(outcome.is_err(), "the waiting worker panics too");
    }
}
