//! Quality: which method and how much detail each effect draws, after the
//! decision chart of Röttger, "Volumetric Methods for the Real-Time Display
//! of Natural Gaseous Phenomena", 2004, §12.1.
//!
//! The chart orders the methods by cost: fog layers (one pass, no cells) for
//! global fog, pre-integrated cell projection for quality, and the level of
//! detail's accuracy `c` as the knob in between. [`NebelQuality`] picks a
//! [`QualityPreset`]; each maps to every effect's method and accuracy:
//!
//! | | `Low` | `Medium` | `High` (default) |
//! |---|---|---|---|
//! | clouds and volumes with an octree (`c` of `VolumeLod`) | × 0.25 | × 0.5 | × 1 |
//! | terrain (`c` of `Terrain`) | × 0.5 | × 0.75 | × 1 |
//! | ground fog | no prisms: the camera's fog layers draw the fog from the eye on | prisms | prisms |
//! | cells ([`CellProjection`] of a camera without its own) | a quarter of the resolution, interpolation error up to 0.2 | half, up to 0.05 | half, up to 0.004 |
//!
//! Fire and search lights keep their mode and resolution: their cells are
//! few, and MIP costs what emission does per fragment.
//!
//! With [`NebelQuality::auto`] the detail also follows the frame time: the
//! [`DetailController`] lowers a factor on both accuracies (down to
//! [`AutoQuality::min_detail`]) while the smoothed frame time stays above
//! the target by more than a fifth, and raises it again (up to the preset)
//! while it stays below seven tenths of it; the gap between the two, the
//! steps of × 0.8 and × 1.25 and a pause after each change keep it from
//! hunting, and the geomorphing of the terrain and the octree makes every
//! change of `c` a smooth one rather than a pop.
//!
//! The effects read [`EffectiveQuality`], which [`NebelQualityPlugin`]
//! writes only when it changes (so its change detection tells them to
//! refine again). Without the plugin they draw at `High`.

use std::time::Instant;

use bevy::diagnostic::{Diagnostic, DiagnosticPath, Diagnostics, RegisterDiagnostic};
use bevy::prelude::*;

use crate::cell_projection::CellProjection;

/// The quality the effects draw at (see the module docs).
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Resource, Default, Debug, Clone)]
pub struct NebelQuality {
    /// The preset. Default [`QualityPreset::High`].
    pub preset: QualityPreset,
    /// Hold a frame time by lowering the detail below the preset's; `None`
    /// keeps the preset's. Default `None`.
    pub auto: Option<AutoQuality>,
}

/// The presets of [`NebelQuality`] (the module docs list what each does).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect)]
#[reflect(Default, Debug, Clone)]
pub enum QualityPreset {
    /// Fog layers only, coarse clouds and terrain.
    Low,
    /// Volumetric ground fog; clouds at half, terrain at three quarters of
    /// their accuracy.
    Medium,
    /// Every effect at the accuracy it asks for.
    #[default]
    High,
}

impl QualityPreset {
    /// The factor on every volume octree's accuracy `c`.
    pub fn volume_accuracy_scale(self) -> f64 {
        match self {
            Self::Low => 0.25,
            Self::Medium => 0.5,
            Self::High => 1.0,
        }
    }

    /// The factor on every terrain quadtree's accuracy `c`.
    pub fn terrain_accuracy_scale(self) -> f64 {
        match self {
            Self::Low => 0.5,
            Self::Medium => 0.75,
            Self::High => 1.0,
        }
    }

    /// Whether ground fog draws its prisms (`Low` leaves the fog to the
    /// camera's fog layers, from the eye on).
    pub fn ground_fog_prisms(self) -> bool {
        self != Self::Low
    }

    /// How a camera without its own [`CellProjection`] draws cells.
    pub fn cell_projection(self) -> CellProjection {
        match self {
            Self::Low => CellProjection::LOW,
            Self::Medium => CellProjection::MEDIUM,
            Self::High => CellProjection::HIGH,
        }
    }
}

/// The automatic mode of [`NebelQuality`].
#[derive(Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Default, Debug, Clone)]
pub struct AutoQuality {
    /// The frame time to hold, ms. A value that is not finite and positive
    /// turns the automatic mode off (logged once). Default 16.7 (60 Hz).
    pub target_frame_ms: f32,
    /// The lowest detail factor, clamped to [0.01, 1]. Default 0.25.
    pub min_detail: f32,
}

impl Default for AutoQuality {
    fn default() -> Self {
        Self {
            target_frame_ms: 16.7,
            min_detail: 0.25,
        }
    }
}

/// What the effects draw at this frame: the preset's methods and accuracy
/// factors times the automatic detail.
#[derive(Resource, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Resource, Default, Debug, Clone)]
pub struct EffectiveQuality {
    /// The preset in use.
    pub preset: QualityPreset,
    /// The automatic mode's factor in (0, 1]; 1 without it.
    pub detail: f32,
}

impl Default for EffectiveQuality {
    fn default() -> Self {
        Self {
            preset: QualityPreset::High,
            detail: 1.0,
        }
    }
}

impl EffectiveQuality {
    /// The factor on every volume octree's accuracy `c`.
    pub fn volume_accuracy_scale(&self) -> f64 {
        self.preset.volume_accuracy_scale() * f64::from(self.detail)
    }

    /// The factor on every terrain quadtree's accuracy `c`.
    pub fn terrain_accuracy_scale(&self) -> f64 {
        self.preset.terrain_accuracy_scale() * f64::from(self.detail)
    }

    /// Whether ground fog draws its prisms.
    pub fn ground_fog_prisms(&self) -> bool {
        self.preset.ground_fog_prisms()
    }
}

/// The automatic mode's state: the smoothed frame time and the detail
/// factor (see the module docs).
#[derive(Resource, Clone, Copy, Debug, PartialEq)]
pub struct DetailController {
    detail: f32,
    smoothed_ms: Option<f32>,
    /// Frames to wait before the next change.
    pause: u32,
}

impl Default for DetailController {
    fn default() -> Self {
        Self {
            detail: 1.0,
            smoothed_ms: None,
            pause: 0,
        }
    }
}

impl DetailController {
    /// Weight of each new frame in the smoothed frame time.
    const SMOOTHING: f32 = 0.1;
    /// Above this share of the target the detail goes down...
    const HIGH: f32 = 1.2;
    /// ...below this share it goes up.
    const LOW: f32 = 0.7;
    /// Frames without a change after one.
    const PAUSE: u32 = 30;

    /// The detail factor.
    pub fn detail(&self) -> f32 {
        self.detail
    }

    /// Takes one frame of `frame_ms` and returns the detail for `auto`.
    /// Frame times that are not finite and positive are skipped.
    pub fn update(&mut self, frame_ms: f32, auto: &AutoQuality) -> f32 {
        if !(frame_ms.is_finite() && frame_ms > 0.0) {
            return self.detail;
        }
        let smoothed = self.smoothed_ms.map_or(frame_ms, |smoothed| {
            smoothed + Self::SMOOTHING * (frame_ms - smoothed)
        });
        self.smoothed_ms = Some(smoothed);
        let min = auto.min_detail.clamp(0.01, 1.0);
        if self.pause > 0 {
            self.pause -= 1;
            return self.detail;
        }
        let next = if smoothed > Self::HIGH * auto.target_frame_ms {
            (self.detail * 0.8).max(min)
        } else if smoothed < Self::LOW * auto.target_frame_ms {
            (self.detail * 1.25).min(1.0)
        } else {
            self.detail
        };
        if next != self.detail {
            self.detail = next;
            self.pause = Self::PAUSE;
        }
        self.detail
    }
}

/// Adds [`NebelQuality`] (default `High`) and keeps [`EffectiveQuality`].
#[derive(Default)]
pub struct NebelQualityPlugin;

impl NebelQualityPlugin {
    /// The automatic mode's detail factor, each frame it is on.
    pub const DETAIL: DiagnosticPath = DiagnosticPath::const_new("nebel/quality/detail");
}

impl Plugin for NebelQualityPlugin {
    fn build(&self, app: &mut App) {
        app.register_type::<NebelQuality>()
            .register_type::<EffectiveQuality>()
            .init_resource::<NebelQuality>()
            .init_resource::<EffectiveQuality>()
            .init_resource::<DetailController>()
            .register_diagnostic(Diagnostic::new(Self::DETAIL))
            .add_systems(First, update_effective_quality);
    }
}

/// Writes [`EffectiveQuality`] from the preset and, in the automatic mode,
/// the last frame's wall time (measured here between two runs of this
/// system, so it holds under any `TimeUpdateStrategy`, headless renders
/// included).
pub fn update_effective_quality(
    quality: Res<NebelQuality>,
    mut last_frame: Local<Option<Instant>>,
    mut controller: ResMut<DetailController>,
    mut effective: ResMut<EffectiveQuality>,
    mut diagnostics: Diagnostics,
    mut warned: Local<bool>,
) {
    let auto = quality.auto.filter(|auto| {
        let valid = auto.target_frame_ms.is_finite() && auto.target_frame_ms > 0.0;
        if !valid && !*warned {
            warn!(
                "nebel: NebelQuality::auto target_frame_ms = {} is not a positive time; the automatic mode is off",
                auto.target_frame_ms
            );
            *warned = true;
        }
        valid
    });
    let now = Instant::now();
    let frame_ms = last_frame
        .replace(now)
        .map_or(0.0, |last| now.duration_since(last).as_secs_f32() * 1e3);
    let detail = match auto {
        Some(auto) => {
            let detail = controller.update(frame_ms, &auto);
            diagnostics.add_measurement(&NebelQualityPlugin::DETAIL, || f64::from(detail));
            detail
        }
        None => {
            *controller = DetailController::default();
            1.0
        }
    };
    effective.set_if_neq(EffectiveQuality {
        preset: quality.preset,
        detail,
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A scene whose frame time is proportional to the detail.
    fn settle(cost_at_full_detail: f32, auto: &AutoQuality, frames: usize) -> (f32, usize) {
        let mut controller = DetailController::default();
        let mut changes = 0;
        let mut detail = controller.detail();
        for _ in 0..frames {
            let next = controller.update(cost_at_full_detail * detail, auto);
            changes += usize::from(next != detail);
            detail = next;
        }
        (detail, changes)
    }

    #[test]
    fn the_detail_drops_to_hold_the_target_and_then_stays() {
        let auto = AutoQuality {
            target_frame_ms: 10.0,
            min_detail: 0.1,
        };
        // Twice the target at full detail: settles where the frame fits
        // the band [0.7, 1.2] × target.
        let (detail, changes) = settle(20.0, &auto, 2000);
        let frame = 20.0 * detail;
        assert!((7.0..=12.0).contains(&frame), "{detail} → {frame} ms");
        // The few changes happened on the way down; settled, it stays.
        assert!(changes <= 6, "{changes} changes");
        let mut controller = DetailController::default();
        let mut detail = 1.0;
        for _ in 0..2000 {
            detail = controller.update(20.0 * detail, &auto);
        }
        for _ in 0..2000 {
            assert_eq!(controller.update(20.0 * detail, &auto), detail);
        }
        // Cheap scenes keep full detail; hopeless ones stop at the minimum.
        assert_eq!(settle(3.0, &auto, 500).0, 1.0);
        assert_eq!(settle(1000.0, &auto, 2000).0, 0.1);
    }

    #[test]
    fn bad_frame_times_and_settings_are_clamped() {
        let mut controller = DetailController::default();
        let auto = AutoQuality {
            target_frame_ms: 10.0,
            min_detail: -3.0,
        };
        for frame_ms in [f32::NAN, -1.0, 0.0, f32::INFINITY] {
            assert_eq!(controller.update(frame_ms, &auto), 1.0);
        }
        for _ in 0..5000 {
            controller.update(1e6, &auto);
        }
        assert_eq!(controller.detail(), 0.01);
    }

    #[test]
    fn the_plugin_lowers_the_detail_of_a_slow_app_and_reports_it() {
        let mut app = App::new();
        app.add_plugins((MinimalPlugins, NebelQualityPlugin));
        app.update();
        assert_eq!(
            *app.world().resource::<EffectiveQuality>(),
            EffectiveQuality::default()
        );
        // Any frame is slower than a target of a nanosecond.
        app.insert_resource(NebelQuality {
            preset: QualityPreset::Medium,
            auto: Some(AutoQuality {
                target_frame_ms: 1e-6,
                min_detail: 0.5,
            }),
        });
        for _ in 0..100 {
            app.update();
        }
        let effective = *app.world().resource::<EffectiveQuality>();
        assert_eq!(effective.preset, QualityPreset::Medium);
        assert!((0.5..1.0).contains(&effective.detail), "{effective:?}");
        assert_eq!(
            effective.volume_accuracy_scale(),
            0.5 * f64::from(effective.detail)
        );
        let reported = app
            .world()
            .resource::<bevy::diagnostic::DiagnosticsStore>()
            .get(&NebelQualityPlugin::DETAIL)
            .and_then(Diagnostic::value);
        assert_eq!(reported, Some(f64::from(effective.detail)));
        // Off again: the preset's detail.
        app.world_mut().resource_mut::<NebelQuality>().auto = None;
        app.update();
        assert_eq!(app.world().resource::<EffectiveQuality>().detail, 1.0);
    }

    #[test]
    fn presets_map_to_methods_and_accuracy() {
        let low = EffectiveQuality {
            preset: QualityPreset::Low,
            detail: 0.5,
        };
        assert_eq!(low.volume_accuracy_scale(), 0.125);
        assert_eq!(low.terrain_accuracy_scale(), 0.25);
        assert!(!low.ground_fog_prisms());
        let high = EffectiveQuality::default();
        assert_eq!(high.volume_accuracy_scale(), 1.0);
        assert!(high.ground_fog_prisms());
    }
}
