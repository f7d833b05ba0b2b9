//! Heavy builds in the background: terrain quadtrees, cloud grids, light
//! fields and volume octrees take from milliseconds to a second, so nebel's
//! plugins run them on Bevy's [`AsyncComputeTaskPool`] instead of in the
//! frame that needs them, and keep drawing what they had until the result is
//! ready. [`HeavyBuilds`] chooses whether a frame waits for its builds.

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
}

/// A heavy build in flight.
#[derive(Debug)]
pub struct HeavyBuild<T>(Task<T>);

impl<T: Send + 'static> HeavyBuild<T> {
    /// Starts `work` on the [`AsyncComputeTaskPool`].
    pub fn spawn(work: impl FnOnce() -> T + Send + 'static) -> Self {
        Self(AsyncComputeTaskPool::get().spawn(async move { work() }))
    }

    /// The result if the build is done, waiting for it under
    /// [`HeavyBuilds::Blocking`]; `None` while it runs in the background.
    pub fn poll(&mut self, mode: HeavyBuilds) -> Option<T> {
        match mode {
            HeavyBuilds::Background => check_ready(&mut self.0),
            HeavyBuilds::Blocking => Some(block_on(&mut self.0)),
        }
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
            .recv_timeout(std::time::Duration::from_secs(10))
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
}
