//! Heavy builds in the background: terrain quadtrees, cloud grids, light
//! fields, volume octrees and pre-integration tables take from milliseconds
//! to a second, so nebel's plugins run them on Bevy's
//! [`AsyncComputeTaskPool`] instead of in the frame that needs them, and keep
//! drawing what they had until the result is ready. [`HeavyBuilds`] chooses whether a frame waits for its builds, or
//! gives the builds of animated volumes a fixed slice of each frame. The CPU
//! time the builds on the task pool worked is summed for the diagnostic
//! `nebel/builds_cpu_ms` ([`crate::NebelDiagnosticsPlugin::BUILDS_CPU_MS`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, TryRecvError};
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

use bevy::prelude::*;
use bevy::tasks::futures::check_ready;
use bevy::tasks::{AsyncComputeTaskPool, Task, block_on};

/// Whether a frame waits for the heavy builds it started (see the module
/// docs). Insert it to change the default.
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq, Eq, Reflect)]
#[reflect(Resource, Default, Clone)]
pub enum HeavyBuilds {
    /// Builds run on the task pool and their results appear in the first
    /// frame after they are ready; until then the entity keeps drawing its
    /// previous result (or nothing, the first time). No frame stalls. The
    /// default.
    #[default]
    Background,
    /// Builds run on the task pool, but the frame that needs a result waits
    /// for it: every frame shows the scene as it is at that frame's time.
    /// For headless renders, tests and comparisons against a reference.
    Blocking,
    /// As [`HeavyBuilds::Background`], but the builds started with
    /// [`HeavyBuild::spawn_in`] (an animated volume's keyframes and
    /// refinement steps) share at most this much CPU time per frame, on two
    /// worker threads of nebel's (`frame_budget`): a game that gives nebel a
    /// fixed slice of each frame on one core. A frame's work may exceed it
    /// by one unit of a build (at most a millisecond or two for the
    /// 513 × 65 × 513 layer). Builds slower than the budget allows take more
    /// frames: a windy cloud's wind then slows instead of stepping. A build
    /// whose result is no longer wanted (its volume despawned or changed)
    /// still runs to its end in the budget, before the builds queued after
    /// it.
    Budgeted(Duration),
}

/// CPU time of the builds on the task pool that ended since the sum was last
/// taken, nanoseconds.
static BUILDS_CPU_NANOS: AtomicU64 = AtomicU64::new(0);

/// The CPU time the builds on the task pool worked (those that ended since
/// the last call), and a new sum from zero.
pub(crate) fn take_builds_cpu_time() -> Duration {
    Duration::from_nanos(BUILDS_CPU_NANOS.swap(0, Ordering::Relaxed))
}

/// A heavy build in flight.
#[derive(Debug)]
pub struct HeavyBuild<T>(Running<T>);

/// Where a build runs.
#[derive(Debug)]
enum Running<T> {
    Task(Task<T>),
    /// Behind a lock only to be `Sync`, as components are: only the
    /// build's owner polls it.
    Budgeted(Mutex<Receiver<std::thread::Result<T>>>),
}

impl<T: Send + 'static> HeavyBuild<T> {
    /// Starts `work` on the [`AsyncComputeTaskPool`].
    pub fn spawn(work: impl FnOnce() -> T + Send + 'static) -> Self {
        Self(Running::Task(AsyncComputeTaskPool::get().spawn(
            async move {
                let started = crate::frame_budget::thread_time();
                let result = work();
                let spent = crate::frame_budget::thread_time().saturating_sub(started);
                BUILDS_CPU_NANOS.fetch_add(
                    u64::try_from(spent.as_nanos()).unwrap_or(u64::MAX),
                    Ordering::Relaxed,
                );
                result
            },
        )))
    }

    /// Starts `work` on the budgeted workers under [`HeavyBuilds::Budgeted`]
    /// (before the other budgeted builds when `urgent`), on the task pool
    /// otherwise.
    pub fn spawn_in(
        mode: HeavyBuilds,
        urgent: bool,
        work: impl FnOnce() -> T + Send + 'static,
    ) -> Self {
        match mode {
            HeavyBuilds::Budgeted(_) => match crate::frame_budget::submit(urgent, work) {
                Ok(receiver) => Self(Running::Budgeted(Mutex::new(receiver))),
                Err(work) => Self::spawn(work),
            },
            HeavyBuilds::Background | HeavyBuilds::Blocking => Self::spawn(work),
        }
    }

    /// The result if the build is done, waiting for it under
    /// [`HeavyBuilds::Blocking`]; `None` while it runs in the background.
    /// A build that panicked panics here.
    pub fn poll(&mut self, mode: HeavyBuilds) -> Option<T> {
        let result = match (&mut self.0, mode) {
            (Running::Task(task), HeavyBuilds::Blocking) => return Some(block_on(task)),
            (Running::Task(task), _) => return check_ready(task),
            (Running::Budgeted(receiver), HeavyBuilds::Blocking) => {
                // The frame waits for the build: no budget holds it back.
                crate::frame_budget::open_frame(None);
                lock(receiver).recv().ok()
            }
            (Running::Budgeted(receiver), _) => match lock(receiver).try_recv() {
                Ok(result) => Some(result),
                Err(TryRecvError::Empty) => return None,
                Err(TryRecvError::Disconnected) => None,
            },
        };
        match result {
            Some(Ok(value)) => Some(value),
            Some(Err(panic)) => std::panic::resume_unwind(panic),
            None => panic!("a budgeted build's worker stopped"),
        }
    }
}

/// What is behind `mutex`, poisoned or not (nothing of nebel's panics
/// holding one).
fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

impl HeavyBuilds {
    /// Opens the next frame's budget for the builds of
    /// [`HeavyBuilds::Budgeted`] (unlimited in the other modes, so a build
    /// started under a budget finishes), and returns the CPU time they
    /// worked in the frame before (zero when none ran). Call once per frame.
    pub fn open_frame(self) -> Duration {
        let budget = match self {
            Self::Budgeted(budget) => Some(budget),
            Self::Background | Self::Blocking => None,
        };
        crate::frame_budget::open_frame(budget)
    }
}

/// nebel's volumes batch on the task pool: a new batcher outside any budget,
/// keyframes in it, refinements first in it (see [`HeavyBuild::spawn_in`]).
impl nebel_lod::BuildPool for HeavyBuilds {
    type Pending<T: Send + 'static> = HeavyBuild<T>;

    fn spawn<T: Send + 'static>(
        self,
        kind: nebel_lod::BuildKind,
        work: impl FnOnce() -> T + Send + 'static,
    ) -> HeavyBuild<T> {
        match kind {
            nebel_lod::BuildKind::Batcher => HeavyBuild::spawn(work),
            nebel_lod::BuildKind::Keyframes => HeavyBuild::spawn_in(self, false, work),
            nebel_lod::BuildKind::Refinement => HeavyBuild::spawn_in(self, true, work),
        }
    }

    fn poll<T: Send + 'static>(self, pending: &mut HeavyBuild<T>) -> Option<T> {
        pending.poll(self)
    }

    fn free<T: Send + 'static>(self, value: T) {
        free_in_background(value);
    }
}

/// Drops `value` on the [`AsyncComputeTaskPool`]: freeing what a large build
/// made (hundreds of megabytes for a 513 × 65 × 513 volume's octrees) can take
/// tens of milliseconds, which no frame should wait for.
pub fn free_in_background<T: Send + 'static>(value: T) {
    AsyncComputeTaskPool::get()
        .spawn(async move { drop(value) })
        .detach();
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::tasks::TaskPool;

    /// Sends the id of the thread it is dropped on.
    struct ReportsDrop(std::sync::mpsc::Sender<std::thread::ThreadId>);

    impl Drop for ReportsDrop {
        fn drop(&mut self) {
            self.0.send(std::thread::current().id()).ok();
        }
    }

    #[test]
    fn freeing_in_the_background_drops_on_the_task_pool() {
        AsyncComputeTaskPool::get_or_init(TaskPool::new);
        let (sender, receiver) = std::sync::mpsc::channel();
        free_in_background(ReportsDrop(sender));
        let dropped_on = receiver
            .recv_timeout(Duration::from_secs(10))
            .expect("dropped");
        assert_ne!(dropped_on, std::thread::current().id());
    }

    #[test]
    fn blocking_waits_and_background_does_not() {
        AsyncComputeTaskPool::get_or_init(TaskPool::new);
        let (sender, receiver) = std::sync::mpsc::channel::<()>();
        let mut build = HeavyBuild::spawn(move || {
            receiver.recv().unwrap();
            7
        });
        assert_eq!(build.poll(HeavyBuilds::Background), None, "still running");
        sender.send(()).unwrap();
        assert_eq!(build.poll(HeavyBuilds::Blocking), Some(7));
    }

    /// Waits for `done` to reach `count` (a bounded number of checks a
    /// millisecond apart: a guard against a hang).
    fn wait_for(done: &std::sync::atomic::AtomicUsize, count: usize) {
        for _ in 0..10_000 {
            if done.load(Ordering::SeqCst) >= count {
                return;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        panic!("stuck below {count}");
    }

    /// The budgeted workers and their budget are global: one test at a time.
    static BUDGETED_WORKERS: Mutex<()> = Mutex::new(());

    #[test]
    fn a_budgeted_build_works_one_unit_per_frame_under_a_zero_budget() {
        use std::sync::Arc;
        use std::sync::atomic::{AtomicUsize, Ordering};

        let _alone = lock(&BUDGETED_WORKERS);
        let budgeted = HeavyBuilds::Budgeted(Duration::ZERO);
        // Workers that run already get a frame of no budget; new ones start
        // with none.
        budgeted.open_frame();
        let units = Arc::new(AtomicUsize::new(0));
        let done = units.clone();
        let mut build = HeavyBuild::spawn_in(budgeted, false, move || {
            for _ in 0..4 {
                // A unit of work that takes CPU time (so at least as much wall
                // time, more than the pacer waits between two looks at the
                // budget), then a yield point.
                let started = crate::frame_budget::thread_time();
                while crate::frame_budget::thread_time() - started < Duration::from_micros(100) {}
                done.fetch_add(1, Ordering::SeqCst);
                nebel_core::pacing::pace();
            }
            7
        });
        for frame in 1..4 {
            wait_for(&units, frame);
            // The frame's budget is spent: no more units until the next.
            std::thread::sleep(Duration::from_millis(30));
            assert_eq!(units.load(Ordering::SeqCst), frame);
            assert_eq!(build.poll(budgeted), None);
            let worked = budgeted.open_frame();
            assert!(worked >= Duration::from_micros(100), "{worked:?}");
        }
        wait_for(&units, 4);
        // Outside a budget a build finishes, and its result arrives.
        HeavyBuilds::Background.open_frame();
        assert_eq!(build.poll(HeavyBuilds::Blocking), Some(7));
    }

    #[test]
    fn a_budgeted_build_that_panics_panics_where_it_is_polled() {
        let _alone = lock(&BUDGETED_WORKERS);
        let budgeted = HeavyBuilds::Budgeted(Duration::from_secs(1));
        let mut build = HeavyBuild::spawn_in(budgeted, true, || -> u8 { panic!("a bad build") });
        let polled = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            build.poll(HeavyBuilds::Blocking)
        }));
        let message = polled.expect_err("the panic reaches the poll");
        assert_eq!(message.downcast_ref::<&str>(), Some(&"a bad build"));
        // The workers live on.
        let mut next = HeavyBuild::spawn_in(budgeted, true, || 3);
        assert_eq!(next.poll(HeavyBuilds::Blocking), Some(3));
    }
}
