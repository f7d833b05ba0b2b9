//! nebel's system set and the CPU time it takes per frame, as a Bevy
//! diagnostic.
//!
//! Every per-frame nebel system in the main world joins the [`NebelSystems`]
//! set, in [`Update`] (systems that move or animate: camera paths, fire,
//! clouds) or in [`PostUpdate`] (systems that build view-dependent batches:
//! they must see this frame's propagated transforms, camera projections and
//! visibility, so the set runs there after [`TransformSystems::Propagate`],
//! [`CameraUpdateSystems`] and [`VisibilitySystems::VisibilityPropagate`]).
//! [`NebelDiagnosticsPlugin`] brackets the set with two marker systems in
//! each schedule and records, each frame, the summed wall time between them
//! as the diagnostic [`NebelDiagnosticsPlugin::SYSTEMS_MS`]. With Bevy's
//! multi-threaded executor an unrelated system may run beside the set, so the
//! figure is an upper bound of nebel's own CPU time; with no nebel system it is
//! the cost of the markers alone (microseconds).
//!
//! Each effect plugin registers its own counters as diagnostics under
//! `nebel/<effect>/<counter>` (for example `nebel/volume/cells_drawn`), each
//! with Bevy's bounded history, so `LogDiagnosticsPlugin` shows them and
//! `nebel render --stats` reports them. An effect absent from a scene
//! measures nothing, so its diagnostics have no value.

use std::time::{Duration, Instant};

use bevy::camera::CameraUpdateSystems;
use bevy::camera::visibility::VisibilitySystems;
use bevy::diagnostic::{Diagnostic, DiagnosticPath, Diagnostics, RegisterDiagnostic};
use bevy::prelude::*;
use bevy::transform::TransformSystems;

/// The set every per-frame nebel system belongs to, in [`Update`] or
/// [`PostUpdate`] (see the module docs).
#[derive(SystemSet, Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct NebelSystems;

/// Adds [`NebelSystems`] and its per-frame CPU time
/// ([`NebelDiagnosticsPlugin::SYSTEMS_MS`]).
#[derive(Default)]
pub struct NebelDiagnosticsPlugin;

impl NebelDiagnosticsPlugin {
    /// Wall time of the [`NebelSystems`] set per frame, milliseconds.
    pub const SYSTEMS_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/systems_ms");
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
                    start_timing.before(NebelSystems),
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::diagnostic::DiagnosticsStore;

    #[test]
    fn one_bounded_measurement_per_frame() {
        let mut app = App::new();
        app.add_plugins(NebelDiagnosticsPlugin);
        let frames = 3;
        for _ in 0..frames {
            app.update();
        }
        let store = app.world().resource::<DiagnosticsStore>();
        let diagnostic = store.get(&NebelDiagnosticsPlugin::SYSTEMS_MS).unwrap();
        assert_eq!(diagnostic.history_len(), frames);
        // A duration: finite and not negative (its size is the benches' business).
        assert!(diagnostic.values().all(|ms| ms.is_finite() && *ms >= 0.0));
        assert!(diagnostic.get_max_history_length() < 1000, "bounded");
    }
}
