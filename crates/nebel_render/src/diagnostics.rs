//! Frame timings and per-effect counters of nebel's systems.
//!
//! Every per-frame nebel system in the main world joins the [`NebelSystems`]
//! set, in [`Update`] (systems that move or animate: camera paths, fire,
//! clouds) or in [`PostUpdate`] (systems that build view-dependent batches:
//! they must see this frame's propagated transforms, camera projections and
//! visibility, so the set runs there after [`TransformSystems::Propagate`],
//! [`CameraUpdateSystems`] and [`VisibilitySystems::VisibilityPropagate`]).
//! [`NebelDiagnosticsPlugin`] brackets the set with two marker systems in
//! each schedule and records, each frame, the summed wall time between them
//! in [`NebelFrameTimings`]. With Bevy's multi-threaded executor an unrelated
//! system may run beside the set, so the figure is an upper bound of nebel's
//! own CPU time; with no nebel system it is the cost of the markers alone
//! (microseconds).
//!
//! [`EffectCounters`] holds one group of named counters per effect (cells drawn,
//! update time, ...). Effects write their group each frame; `nebel render
//! --stats` reports them. A scene without an effect has no group for it.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use bevy::camera::CameraUpdateSystems;
use bevy::camera::visibility::VisibilitySystems;
use bevy::prelude::*;
use bevy::transform::TransformSystems;

/// The set every per-frame nebel system belongs to, in [`Update`] or
/// [`PostUpdate`] (see the module docs).
#[derive(SystemSet, Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct NebelSystems;

/// Per-frame wall time of the [`NebelSystems`] set, one entry per frame, oldest
/// first.
#[derive(Resource, Clone, Debug, Default, Reflect)]
#[reflect(Resource, Default)]
pub struct NebelFrameTimings {
    /// Time from the start to the end of the set, per frame.
    pub frames: Vec<Duration>,
    /// Keep at most this many frames (the oldest are dropped). Default: 0, no limit.
    pub capacity: usize,
    #[reflect(ignore)]
    frame_start: Option<Instant>,
    /// Time spent in the set so far this frame (the [`Update`] part).
    #[reflect(ignore)]
    frame_so_far: Duration,
}

impl NebelFrameTimings {
    /// The median and the maximum frame time, `None` before the first frame.
    pub fn median_and_max(&self) -> Option<(Duration, Duration)> {
        let mut sorted = self.frames.clone();
        sorted.sort_unstable();
        let max = *sorted.last()?;
        let middle = sorted.len() / 2;
        let median = if sorted.len() % 2 == 1 {
            sorted[middle]
        } else {
            (sorted[middle - 1] + sorted[middle]) / 2
        };
        Some((median, max))
    }
}

/// Named counters per effect: effect name → counter name → value.
#[derive(Resource, Clone, Debug, Default, Reflect)]
#[reflect(Resource, Default)]
pub struct EffectCounters(pub BTreeMap<String, BTreeMap<String, f64>>);

impl EffectCounters {
    /// Sets one counter of one effect, creating the effect's group if needed.
    pub fn set(&mut self, effect: &str, counter: &str, value: f64) {
        self.0
            .entry(effect.to_owned())
            .or_default()
            .insert(counter.to_owned(), value);
    }
}

/// Adds [`NebelSystems`], [`NebelFrameTimings`] and [`EffectCounters`].
#[derive(Default)]
pub struct NebelDiagnosticsPlugin;

impl Plugin for NebelDiagnosticsPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<NebelFrameTimings>()
            .init_resource::<EffectCounters>()
            .configure_sets(
                PostUpdate,
                NebelSystems
                    .after(TransformSystems::Propagate)
                    .after(CameraUpdateSystems)
                    .after(VisibilitySystems::VisibilityPropagate),
            )
            .add_systems(
                Update,
                (
                    start_frame_timing.before(NebelSystems),
                    pause_frame_timing.after(NebelSystems),
                ),
            )
            .add_systems(
                PostUpdate,
                (
                    start_frame_timing.before(NebelSystems),
                    end_frame_timing.after(NebelSystems),
                ),
            );
    }
}

fn start_frame_timing(mut timings: ResMut<NebelFrameTimings>) {
    timings.frame_start = Some(Instant::now());
}

/// Ends the [`Update`] part of the frame's measurement.
fn pause_frame_timing(mut timings: ResMut<NebelFrameTimings>) {
    if let Some(start) = timings.frame_start.take() {
        timings.frame_so_far += start.elapsed();
    }
}

fn end_frame_timing(mut timings: ResMut<NebelFrameTimings>) {
    let Some(start) = timings.frame_start.take() else {
        return;
    };
    let frame = std::mem::take(&mut timings.frame_so_far) + start.elapsed();
    timings.frames.push(frame);
    let capacity = timings.capacity;
    if capacity > 0 && timings.frames.len() > capacity {
        let excess = timings.frames.len() - capacity;
        timings.frames.drain(..excess);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn timings(millis: &[u64]) -> NebelFrameTimings {
        NebelFrameTimings {
            frames: millis.iter().map(|m| Duration::from_millis(*m)).collect(),
            ..default()
        }
    }

    #[test]
    fn median_and_max_of_odd_and_even_counts() {
        assert_eq!(timings(&[]).median_and_max(), None);
        let ms = Duration::from_millis;
        assert_eq!(timings(&[5, 1, 3]).median_and_max(), Some((ms(3), ms(5))));
        assert_eq!(
            timings(&[4, 1, 2, 9]).median_and_max(),
            Some((ms(3), ms(9)))
        );
    }

    #[test]
    fn plugin_records_one_timing_per_frame_and_keeps_capacity() {
        let mut app = App::new();
        app.add_plugins(NebelDiagnosticsPlugin);
        app.world_mut().resource_mut::<NebelFrameTimings>().capacity = 2;
        for _ in 0..3 {
            app.update();
        }
        assert_eq!(app.world().resource::<NebelFrameTimings>().frames.len(), 2);
    }

    #[test]
    fn counters_group_by_effect() {
        let mut counters = EffectCounters::default();
        counters.set("volume", "cells_drawn", 10.0);
        counters.set("volume", "cells_drawn", 12.0);
        counters.set("terrain", "triangles", 5.0);
        assert_eq!(counters.0["volume"]["cells_drawn"], 12.0);
        assert_eq!(counters.0.len(), 2);
    }
}
