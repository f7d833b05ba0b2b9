//! The worker threads of [`HeavyBuilds::Budgeted`](crate::HeavyBuilds):
//! builds that share a fixed slice of each frame.
//!
//! Two threads, started with the first budgeted build: one for urgent builds
//! (a refinement step, needed within a fraction of a second) and one for the
//! rest (keyframes, needed within seconds), each taking its builds in the
//! order they came. Both run their builds with a pacer
//! ([`nebel_core::pacing`]) that counts the CPU time a build ran since its
//! last yield point against the current frame's budget, shared by the two,
//! and blocks once the budget is exceeded until [`open_frame`] opens the
//! next frame's (so a budget of zero still runs one unit per frame). CPU
//! time, not wall time: what a build costs the game is the core it
//! occupies, whatever else the operating system runs on that core
//! meanwhile (wall time where the platform has no per-thread clock). The
//! pacer looks at the budget at most every [`BUDGET_CHECK_INTERVAL`] of
//! wall time, as the refinement's yield points, one per node, come every
//! microsecond or so. A background build also waits while an urgent one is
//! queued or running, so a refinement step is never held up by a keyframe.
//! The work of a frame is therefore at most the budget plus the longest unit
//! between two yield points (a grid plane, a slice of the light field, a
//! layer of octree nodes: a fraction of a millisecond to a millisecond or
//! two), and whatever a build does before its first yield point.
//!
//! The workers start with no budget: a build runs its first unit, then
//! waits for a frame to open one. A frame that is not budgeted (another
//! [`HeavyBuilds`](crate::HeavyBuilds) mode) opens an unlimited budget, so a
//! build started under a budget never waits for a frame that does not come.
//! Where no thread can be started, budgeted builds run on the task pool
//! instead, unbudgeted.

use std::cell::Cell;
use std::collections::VecDeque;
use std::panic::AssertUnwindSafe;
use std::rc::Rc;
use std::sync::mpsc::{Receiver, channel};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock, PoisonError};
use std::time::{Duration, Instant};

use nebel_core::pacing::with_pacer;

/// A build queued for a worker.
type Job = Box<dyn FnOnce() + Send>;

/// What the workers share.
struct Shared {
    state: Mutex<State>,
    /// Signalled when a frame opens, a build is queued or an urgent one ends.
    changed: Condvar,
}

#[derive(Default)]
struct State {
    /// The queues of the urgent and the background worker.
    queues: [VecDeque<Job>; 2],
    /// The current frame's budget.
    budget: Duration,
    /// The work done in the current frame so far.
    used: Duration,
    /// Urgent builds queued or running.
    urgent: usize,
}

/// The wall time a build runs between two looks at the budget: a yield
/// point in between costs a read of the wall clock (nanoseconds) instead of
/// one of the thread's CPU clock (a system call) and the lock. A frame's
/// work may exceed its budget by this much more.
const BUDGET_CHECK_INTERVAL: Duration = Duration::from_micros(50);

/// Which worker runs a build.
const URGENT: usize = 0;
const BACKGROUND: usize = 1;

/// The workers, once started; `None` where no thread could be started.
static WORKERS: OnceLock<Option<Arc<Shared>>> = OnceLock::new();

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        // A build that panicked did so outside the lock: the state is whole.
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// Queues `work` on the urgent or the background worker (see the module
/// docs); the receiver gets its result, or its panic. Gives `work` back
/// where the workers could not be started.
pub(crate) fn submit<T: Send + 'static, Work: FnOnce() -> T + Send + 'static>(
    urgent: bool,
    work: Work,
) -> Result<Receiver<std::thread::Result<T>>, Work> {
    let Some(shared) = WORKERS.get_or_init(start_workers) else {
        return Err(work);
    };
    let (sender, receiver) = channel();
    let worker = if urgent { URGENT } else { BACKGROUND };
    let job: Job = Box::new(move || {
        let result = std::panic::catch_unwind(AssertUnwindSafe(work));
        // The build was dropped: nobody waits for the result.
        sender.send(result).ok();
    });
    let mut state = shared.lock();
    state.queues[worker].push_back(job);
    state.urgent += usize::from(urgent);
    drop(state);
    shared.changed.notify_all();
    Ok(receiver)
}

/// Opens the next frame's budget (`None`: unlimited) and returns the work
/// the budgeted builds did in the frame before (zero before the workers
/// started).
pub(crate) fn open_frame(budget: Option<Duration>) -> Duration {
    let Some(shared) = WORKERS.get().and_then(Option::as_ref) else {
        return Duration::ZERO;
    };
    let mut state = shared.lock();
    let used = std::mem::take(&mut state.used);
    state.budget = budget.unwrap_or(Duration::MAX);
    drop(state);
    shared.changed.notify_all();
    used
}

/// Starts the two workers; `None` where the platform starts no thread.
fn start_workers() -> Option<Arc<Shared>> {
    let shared = Arc::new(Shared {
        // No budget until the first frame opens one (see the module docs).
        state: Mutex::new(State::default()),
        changed: Condvar::new(),
    });
    for (worker, name) in [
        (URGENT, "nebel urgent builds"),
        (BACKGROUND, "nebel builds"),
    ] {
        let shared = shared.clone();
        std::thread::Builder::new()
            .name(name.into())
            .spawn(move || run_worker(&shared, worker))
            .ok()?;
    }
    Some(shared)
}

/// Runs the builds of `worker` as they come, paced.
fn run_worker(shared: &Arc<Shared>, worker: usize) {
    loop {
        let mut state = shared.lock();
        let job = loop {
            match state.queues[worker].pop_front() {
                Some(job) => break job,
                None => {
                    state = shared
                        .changed
                        .wait(state)
                        .unwrap_or_else(PoisonError::into_inner);
                }
            }
        };
        drop(state);
        let since = Rc::new(Cell::new(thread_time()));
        let checked = Cell::new(Instant::now());
        let pacer = {
            let (shared, since) = (shared.clone(), since.clone());
            Rc::new(move || {
                if checked.get().elapsed() < BUDGET_CHECK_INTERVAL {
                    return;
                }
                let mut state = shared.lock();
                state.used = state
                    .used
                    .saturating_add(thread_time().saturating_sub(since.get()));
                while state.used > state.budget || (worker == BACKGROUND && state.urgent > 0) {
                    state = shared
                        .changed
                        .wait(state)
                        .unwrap_or_else(PoisonError::into_inner);
                }
                drop(state);
                since.set(thread_time());
                checked.set(Instant::now());
            })
        };
        with_pacer(pacer, job);
        let mut state = shared.lock();
        state.used = state
            .used
            .saturating_add(thread_time().saturating_sub(since.get()));
        state.urgent -= usize::from(worker == URGENT);
        drop(state);
        shared.changed.notify_all();
    }
}

/// The CPU time the calling thread has run.
#[cfg(unix)]
pub(crate) fn thread_time() -> Duration {
    let time = rustix::time::clock_gettime(rustix::time::ClockId::ThreadCPUTime);
    Duration::new(
        u64::try_from(time.tv_sec).unwrap_or(0),
        u32::try_from(time.tv_nsec).unwrap_or(0),
    )
}

/// The wall time since the first call, where the platform has no clock of a
/// thread's CPU time.
#[cfg(not(unix))]
pub(crate) fn thread_time() -> Duration {
    static START: OnceLock<std::time::Instant> = OnceLock::new();
    START.get_or_init(std::time::Instant::now).elapsed()
}
