//! nebel's system set and the time it takes per frame, as Bevy diagnostics.
//!
//! Every per-frame nebel system in the main world joins the [`NebelSystems`]
//! set, in [`Update`] (systems that move or animate: camera paths, fire,
//! clouds) or in [`PostUpdate`] (systems that build view-dependent batches:
//! they must see this frame's propagated transforms, camera projections and
//! visibility, so the set runs there after [`TransformSystems::Propagate`],
//! [`CameraUpdateSystems`] and [`VisibilitySystems::VisibilityPropagate`]),
//! each wrapped in [`cpu_timed`]. [`NebelDiagnosticsPlugin`] records two
//! figures per frame:
//!
//! - [`NebelDiagnosticsPlugin::SYSTEMS_CPU_MS`]: the CPU time the systems
//!   wrapped in [`cpu_timed`] ran, each measured by its thread's CPU clock,
//!   summed over the frame: nebel's own work, whichever threads the executor
//!   ran it on, not counting time the threads waited for a core or for a
//!   build (`HeavyBuilds::Blocking`), nor the commands the systems queued
//!   (on a platform without a thread CPU clock, the systems' wall time).
//!   The sum is kept per process: in a process that runs several apps at
//!   once (tests) each app's figure includes the others' systems.
//! - [`NebelDiagnosticsPlugin::SYSTEMS_MS`]: the wall time between two marker
//!   systems that bracket the set in each schedule. With Bevy's multi-threaded
//!   executor an unrelated system may run beside the set, and on a machine
//!   whose cores are busy (the task pool's builds, a software GPU) the
//!   set's threads wait for a core, so it is an upper bound.
//!
//! - [`NebelDiagnosticsPlugin::BUILDS_CPU_MS`]: the CPU time of nebel's heavy
//!   builds on the task pool ([`crate::HeavyBuild::spawn`]) that ended since
//!   the frame before: the work nebel does beside the frame (a build's whole
//!   time lands in the frame it ends in, so its mean over frames is what
//!   counts).
//!
//! With no nebel system the first two are the cost of the markers alone
//! (microseconds).
//!
//! Each effect plugin registers its own counters as diagnostics under
//! `nebel/<effect>/<counter>` (for example `nebel/volume/cells_drawn`), each
//! with Bevy's bounded history, so `LogDiagnosticsPlugin` shows them and
//! `nebel render --stats` reports them. An effect absent from a scene
//! measures nothing, so its diagnostics have no value.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use bevy::camera::CameraUpdateSystems;
use bevy::camera::visibility::VisibilitySystems;
use bevy::diagnostic::{Diagnostic, DiagnosticPath, Diagnostics, RegisterDiagnostic};
use bevy::ecs::system::{Adapt, IntoAdapterSystem, RunSystemError, SystemIn, SystemInput};
use bevy::prelude::*;
use bevy::transform::TransformSystems;

/// The set every per-frame nebel system belongs to, in [`Update`] or
/// [`PostUpdate`] (see the module docs).
#[derive(SystemSet, Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct NebelSystems;

/// CPU time of the systems wrapped in [`cpu_timed`] since the frame's
/// figure was last taken, nanoseconds.
static SYSTEMS_CPU_NANOS: AtomicU64 = AtomicU64::new(0);

/// `system`, its CPU time counted in
/// [`NebelDiagnosticsPlugin::SYSTEMS_CPU_MS`] (see the module docs).
pub fn cpu_timed<S, I, O, M>(system: S) -> IntoAdapterSystem<CpuTimed, S>
where
    S: IntoSystem<I, O, M>,
    I: SystemInput,
{
    IntoAdapterSystem::new(CpuTimed, system)
}

/// The adapter of [`cpu_timed`]: runs the system and adds the CPU time its
/// thread spent on it.
#[derive(Clone, Copy, Debug, Default)]
pub struct CpuTimed;

impl<S: System> Adapt<S> for CpuTimed {
    type In = S::In;
    type Out = S::Out;

    fn adapt(
        &mut self,
        input: <S::In as SystemInput>::Inner<'_>,
        run_system: impl FnOnce(SystemIn<'_, S>) -> Result<S::Out, RunSystemError>,
    ) -> Result<S::Out, RunSystemError> {
        let started = crate::frame_budget::thread_time();
        let result = run_system(input);
        let spent = crate::frame_budget::thread_time().saturating_sub(started);
        SYSTEMS_CPU_NANOS.fetch_add(
            u64::try_from(spent.as_nanos()).unwrap_or(u64::MAX),
            Ordering::Relaxed,
        );
        result
    }
}

/// Adds [`NebelSystems`] and its time per frame
/// ([`NebelDiagnosticsPlugin::SYSTEMS_CPU_MS`],
/// [`NebelDiagnosticsPlugin::SYSTEMS_MS`]).
#[derive(Default)]
pub struct NebelDiagnosticsPlugin;

impl NebelDiagnosticsPlugin {
    /// Wall time of the [`NebelSystems`] set per frame, milliseconds: an
    /// upper bound (see the module docs).
    pub const SYSTEMS_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/systems_ms");
    /// CPU time of nebel's systems per frame, milliseconds (see the module
    /// docs).
    pub const SYSTEMS_CPU_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/systems_cpu_ms");
    /// CPU time of nebel's builds on the task pool that ended since the
    /// frame before, milliseconds (see the module docs).
    pub const BUILDS_CPU_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/builds_cpu_ms");
}

/// When the set started this frame and how long it ran so far.
#[derive(Resource, Default)]
struct SetTimer {
    started: Option<Instant>,
    so_far: Duration,
}

impl Plugin for NebelDiagnosticsPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<SetTimer>()
            .register_diagnostic(Diagnostic::new(Self::SYSTEMS_MS).with_suffix(" ms"))
            .register_diagnostic(Diagnostic::new(Self::SYSTEMS_CPU_MS).with_suffix(" ms"))
            .register_diagnostic(Diagnostic::new(Self::BUILDS_CPU_MS).with_suffix(" ms"))
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
                    start_timing.before(NebelSystems),
                    pause_timing.after(NebelSystems),
                ),
            )
            .add_systems(
                PostUpdate,
                (
                    // Not before what the set waits for: Bevy's propagation
                    // is not nebel's time.
                    start_timing
                        .before(NebelSystems)
                        .after(TransformSystems::Propagate)
                        .after(CameraUpdateSystems)
                        .after(VisibilitySystems::VisibilityPropagate),
                    end_timing.after(NebelSystems),
                ),
            );
    }
}

fn start_timing(mut timer: ResMut<SetTimer>) {
    timer.started = Some(Instant::now());
}

/// Ends the [`Update`] part of the frame's measurement.
fn pause_timing(mut timer: ResMut<SetTimer>) {
    if let Some(started) = timer.started.take() {
        timer.so_far += started.elapsed();
    }
}

fn end_timing(mut timer: ResMut<SetTimer>, mut diagnostics: Diagnostics) {
    let Some(started) = timer.started.take() else {
        return;
    };
    let frame = std::mem::take(&mut timer.so_far) + started.elapsed();
    diagnostics.add_measurement(&NebelDiagnosticsPlugin::SYSTEMS_MS, || {
        frame.as_secs_f64() * 1e3
    });
    let cpu = SYSTEMS_CPU_NANOS.swap(0, Ordering::Relaxed);
    diagnostics.add_measurement(&NebelDiagnosticsPlugin::SYSTEMS_CPU_MS, || cpu as f64 / 1e6);
    let builds = crate::builds::take_builds_cpu_time();
    diagnostics.add_measurement(&NebelDiagnosticsPlugin::BUILDS_CPU_MS, || {
        builds.as_secs_f64() * 1e3
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::diagnostic::DiagnosticsStore;
    use bevy::tasks::{AsyncComputeTaskPool, TaskPool};

    /// Works `ms` of its thread's CPU time.
    fn spin(ms: u64) {
        let started = crate::frame_budget::thread_time();
        while crate::frame_budget::thread_time() - started < Duration::from_millis(ms) {}
    }

    // One test: the sum of CPU time is per process, and each app's last
    // marker takes it.
    #[test]
    fn bounded_measurements_per_frame_and_cpu_time_counts_work_not_waiting() {
        let mut app = App::new();
        app.add_plugins(NebelDiagnosticsPlugin);
        let frames = 3;
        for _ in 0..frames {
            app.update();
        }
        let store = app.world().resource::<DiagnosticsStore>();
        for path in [
            NebelDiagnosticsPlugin::SYSTEMS_MS,
            NebelDiagnosticsPlugin::SYSTEMS_CPU_MS,
            NebelDiagnosticsPlugin::BUILDS_CPU_MS,
        ] {
            let diagnostic = store.get(&path).unwrap();
            assert_eq!(diagnostic.history_len(), frames);
            // A duration: finite and not negative (its size is the benches' business).
            assert!(diagnostic.values().all(|ms| ms.is_finite() && *ms >= 0.0));
            assert!(diagnostic.get_max_history_length() < 1000, "bounded");
        }

        // Timed systems in both schedules: 3 ms of work, 20 ms asleep.
        app.add_systems(Update, cpu_timed(|| spin(2)).in_set(NebelSystems))
            .add_systems(
                PostUpdate,
                (
                    cpu_timed(|| spin(1)),
                    cpu_timed(|| std::thread::sleep(Duration::from_millis(20))),
                )
                    .in_set(NebelSystems),
            );
        for _ in 0..frames {
            app.update();
            let store = app.world().resource::<DiagnosticsStore>();
            let latest = |path| store.get_measurement(&path).unwrap().value;
            let cpu = latest(NebelDiagnosticsPlugin::SYSTEMS_CPU_MS);
            let wall = latest(NebelDiagnosticsPlugin::SYSTEMS_MS);
            assert!(cpu >= 3.0, "{cpu} ms");
            assert!(wall >= 20.0 && wall >= cpu, "{wall} ms");
            #[cfg(unix)]
            assert!(cpu < 15.0, "asleep is not work: {cpu} ms");
        }

        // A build of 4 ms on the task pool counts in the frame after it ends.
        AsyncComputeTaskPool::get_or_init(TaskPool::new);
        let mut build = crate::HeavyBuild::spawn(|| spin(4));
        build.poll(crate::HeavyBuilds::Blocking);
        app.update();
        let store = app.world().resource::<DiagnosticsStore>();
        let builds = store
            .get_measurement(&NebelDiagnosticsPlugin::BUILDS_CPU_MS)
            .unwrap()
            .value;
        assert!(builds >= 4.0, "{builds} ms");
    }
}
