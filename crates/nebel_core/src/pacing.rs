//! Yield points that let a long build share a per-frame time budget.
//!
//! A cloud's keyframe (its grid, light field and octree) takes hundreds of
//! milliseconds of one core, and a refinement step some milliseconds. A
//! game that gives nebel a fixed slice of each frame runs such a build on a
//! worker that stops it once the frame's slice is used and resumes it in the
//! next frame. The builds here cannot be cut into frames by their callers,
//! so they call [`pace`] between small units of their work (a plane of a
//! grid, a slice of the light field's sweep, a layer of the octree's
//! levels, a node of a refinement or of its emission, the freeing of a
//! large field); the worker installs
//! a pacer on its thread ([`with_pacer`]) that blocks there while the frame
//! has no budget left. Without a pacer, [`pace`] does nothing but read a
//! thread-local slot.
//!
//! A build that finds a pacer on its thread runs there alone
//! ([`worker_threads`] is 1): threads it spawned would not be paced. Pacing
//! only delays the work, so a paced build's result is the unpaced one, bit
//! for bit.
//!
//! The decision: a blocking yield point, rather than builds split into
//! resumable steps, so that the algorithms keep their loops and recursions
//! (the octree's refinement is a recursion, the shadow sweep a loop over
//! blocks of slices with state) and a unit of work is bounded by where the
//! calls sit, not by how the work is cut.

use std::cell::RefCell;
use std::num::NonZeroUsize;
use std::rc::Rc;

thread_local! {
    /// The pacer of this thread's build, if any.
    static PACER: RefCell<Option<Rc<dyn Fn()>>> = const { RefCell::new(None) };
}

/// A yield point: calls the pacer installed on this thread, if any (which
/// may block until the next frame), and does nothing otherwise.
#[inline]
pub fn pace() {
    // The pacer is cloned out of the slot so that it runs without a borrow.
    if let Some(pacer) = PACER.with(|slot| slot.borrow().clone()) {
        pacer();
    }
}

/// `len` copies of `value`, written a mebibyte at a time with a yield
/// point after each. `vec![value; len]` is one unit of work however large:
/// where the allocator hands back memory a build freed before (as it does
/// for the tens of megabytes of a keyframe's arrays once one was freed), it
/// writes all of it at once, several milliseconds on a busy core.
pub fn filled_paced<T: Clone>(len: usize, value: T) -> Vec<T> {
    let piece = ((1 << 20) / size_of::<T>().max(1)).max(1);
    let mut values = Vec::with_capacity(len);
    while values.len() < len {
        let end = (values.len() + piece).min(len);
        values.resize(end, value.clone());
        pace();
    }
    values
}

/// Drops `value`, then yields: freeing a large field (tens of megabytes)
/// takes a millisecond or more, a unit of work of its own.
pub fn drop_paced<T>(value: T) {
    drop(value);
    pace();
}

/// Whether a pacer is installed on this thread.
pub fn is_paced() -> bool {
    PACER.with(|slot| slot.borrow().is_some())
}

/// Runs `work` with `pacer` called at every [`pace`] on this thread, then
/// puts back the pacer that was there before (also when `work` panics).
pub fn with_pacer<R>(pacer: Rc<dyn Fn()>, work: impl FnOnce() -> R) -> R {
    /// Restores the previous pacer when dropped.
    struct Restore(Option<Rc<dyn Fn()>>);
    impl Drop for Restore {
        fn drop(&mut self) {
            let previous = self.0.take();
            PACER.with(|slot| *slot.borrow_mut() = previous);
        }
    }
    let _restore = Restore(PACER.with(|slot| slot.borrow_mut().replace(pacer)));
    work()
}

/// How many threads a build that may use every core takes: every core the
/// machine has, or 1 on a paced thread (see the module docs).
pub fn worker_threads() -> usize {
    if is_paced() {
        1
    } else {
        std::thread::available_parallelism().map_or(2, NonZeroUsize::get)
    }
}

/// Runs `fill(first_slice, chunk)` over `values`, `slices` slices of
/// `slice_len` values each, split into runs of whole slices on up to
/// `threads` scoped threads (on this thread alone for 1).
pub fn fill_slices<T: Send>(
    values: &mut [T],
    slice_len: usize,
    threads: usize,
    fill: impl Fn(usize, &mut [T]) + Sync,
) {
    let slices = values.len() / slice_len.max(1);
    let threads = threads.clamp(1, slices.max(1));
    if threads == 1 {
        fill(0, values);
        return;
    }
    let slices_per_thread = slices.div_ceil(threads);
    std::thread::scope(|scope| {
        for (t, chunk) in values.chunks_mut(slice_len * slices_per_thread).enumerate() {
            let fill = &fill;
            scope.spawn(move || fill(t * slices_per_thread, chunk));
        }
    });
}

#[cfg(test)]
mod tests {
    use std::cell::Cell;

    use super::*;

    #[test]
    fn filled_paced_is_the_filled_vector_a_mebibyte_per_yield_point() {
        let piece = (1 << 20) / size_of::<u16>();
        for len in [0, 1, piece - 1, piece, piece + 1, 3 * piece + 7] {
            let calls = Rc::new(Cell::new(0));
            let counter = calls.clone();
            let values = with_pacer(Rc::new(move || counter.set(counter.get() + 1)), || {
                filled_paced(len, 7u16)
            });
            assert_eq!(values, vec![7u16; len], "length {len}");
            assert_eq!(calls.get(), len.div_ceil(piece), "length {len}");
        }
    }

    #[test]
    fn a_pacer_sees_every_yield_point_of_its_work_and_no_other() {
        let calls = Rc::new(Cell::new(0));
        pace();
        assert!(!is_paced());
        let counter = calls.clone();
        let threads = with_pacer(Rc::new(move || counter.set(counter.get() + 1)), || {
            assert!(is_paced());
            for _ in 0..5 {
                pace();
            }
            // Threads spawned by the work have no pacer.
            let spawned = std::thread::spawn(|| {
                pace();
                is_paced()
            });
            assert!(!spawned.join().unwrap());
            worker_threads()
        });
        assert_eq!(calls.get(), 5);
        assert_eq!(threads, 1);
        pace();
        assert_eq!(calls.get(), 5);
        assert!(!is_paced());
        assert!(worker_threads() >= 1);
    }

    #[test]
    fn nested_pacers_restore_the_outer_one_also_after_a_panic() {
        let outer_calls = Rc::new(Cell::new(0));
        let inner_calls = Rc::new(Cell::new(0));
        let (outer, inner) = (outer_calls.clone(), inner_calls.clone());
        with_pacer(Rc::new(move || outer.set(outer.get() + 1)), || {
            pace();
            let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                with_pacer(Rc::new(move || inner.set(inner.get() + 1)), || {
                    pace();
                    panic!("a failing build");
                })
            }));
            assert!(result.is_err());
            pace();
        });
        assert_eq!((outer_calls.get(), inner_calls.get()), (2, 1));
        assert!(!is_paced());
    }

    #[test]
    fn fill_slices_gives_each_slice_its_own_index_on_any_number_of_threads() {
        for (slices, threads) in [(1, 1), (5, 1), (5, 2), (5, 3), (7, 16), (8, 4)] {
            let mut values = vec![usize::MAX; slices * 3];
            fill_slices(&mut values, 3, threads, |first, chunk: &mut [usize]| {
                for (n, value) in chunk.iter_mut().enumerate() {
                    *value = first + n / 3;
                }
            });
            let expected: Vec<usize> = (0..slices * 3).map(|n| n / 3).collect();
            assert_eq!(values, expected, "{slices} slices on {threads} threads");
        }
    }
}
