//! Where a volume's batching runs its heavy builds: [`BuildPool`], the
//! interface a game engine's task pool implements (nebel's Bevy plugins use
//! Bevy's), and [`LocalBuilds`], which runs them on the calling thread.
//!
//! A build is started once and polled every frame until it yields its result;
//! a pool may run it at once, on another thread, or when polled. What it
//! builds ([`BuildKind`]) lets a pool that shares a fixed CPU budget per
//! frame put refinements first and keep one-off batchers out of the budget.

use std::sync::Mutex;

/// What a build makes, for a pool that schedules by kind.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BuildKind {
    /// A volume's batcher from its source and settings (padding, light
    /// field, hierarchy): once per change of the volume.
    Batcher,
    /// A pair of keyframes of an animated volume: one per keyframe interval.
    Keyframes,
    /// An octree refinement for a view: what the next frames draw, wanted
    /// first.
    Refinement,
}

/// Runs builds off the frame and hands their results back when polled.
///
/// A pool is a small value (a mode, a handle) passed to every call, so the
/// same builds can be polled in another mode, for example waited for in a
/// frame that must show them.
pub trait BuildPool: Copy + Send + Sync + 'static {
    /// A build in flight.
    type Pending<T: Send + 'static>: Send + Sync;

    /// Starts `work`.
    fn spawn<T: Send + 'static>(
        self,
        kind: BuildKind,
        work: impl FnOnce() -> T + Send + 'static,
    ) -> Self::Pending<T>;

    /// The result once `pending` is done (a pool that waits returns it
    /// always), `None` while it runs. Called again after it returned the
    /// result, it may panic.
    fn poll<T: Send + 'static>(self, pending: &mut Self::Pending<T>) -> Option<T>;

    /// Drops `value`, which may be large (a 513 × 65 × 513 volume's octrees
    /// take hundreds of megabytes and tens of milliseconds to free), where
    /// no frame waits for it; at once by default.
    fn free<T: Send + 'static>(self, value: T) {
        drop(value);
    }
}

/// Builds run on the thread that polls them, when it polls them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LocalBuilds {
    /// A poll runs the build: every frame shows what it asked for.
    #[default]
    Blocking,
    /// A poll leaves the build waiting: a frame that does not wait for a
    /// build, as on a busy worker.
    Deferred,
}

/// A build of [`LocalBuilds`] not yet run (behind a lock only to be `Sync`).
pub struct LocalBuild<T>(Mutex<Option<Box<dyn FnOnce() -> T + Send>>>);

impl<T> std::fmt::Debug for LocalBuild<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("LocalBuild")
    }
}

impl BuildPool for LocalBuilds {
    type Pending<T: Send + 'static> = LocalBuild<T>;

    fn spawn<T: Send + 'static>(
        self,
        _kind: BuildKind,
        work: impl FnOnce() -> T + Send + 'static,
    ) -> LocalBuild<T> {
        LocalBuild(Mutex::new(Some(Box::new(work))))
    }

    fn poll<T: Send + 'static>(self, pending: &mut LocalBuild<T>) -> Option<T> {
        match self {
            Self::Blocking => {
                let work = pending
                    .0
                    .get_mut()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .take()
                    .expect("a local build is polled after its result");
                Some(work())
            }
            Self::Deferred => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_deferred_build_runs_when_a_blocking_poll_asks() {
        let ran = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let flag = ran.clone();
        let mut build = LocalBuilds::Deferred.spawn(BuildKind::Batcher, move || {
            flag.store(true, std::sync::atomic::Ordering::SeqCst);
            7
        });
        assert_eq!(LocalBuilds::Deferred.poll(&mut build), None);
        assert!(!ran.load(std::sync::atomic::Ordering::SeqCst));
        assert_eq!(LocalBuilds::Blocking.poll(&mut build), Some(7));
        assert!(ran.load(std::sync::atomic::Ordering::SeqCst));
    }
}
