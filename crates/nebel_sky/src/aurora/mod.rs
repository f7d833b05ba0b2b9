//! The [`Aurora`] component, its status and statistics, and
//! [`AuroraPlugin`].
//!
//! An aurora is a footprint of curtain strengths in [0, 1] over a square of
//! [`Aurora::extent`] centred on its entity (in the entity's frame: place
//! and turn it with its `Transform`), raised into curtains between the
//! plane at [`Aurora::bottom`] and, where the strength is 1,
//! [`Aurora::top`] (Röttger 2004 §10.4; the geometry is
//! [`nebel_lod::AuroraShape`]'s). The curtains emit light only (the thesis's
//! emissive PCP mode, §10.3): each ray adds `∫ κ(s) ρ(s) dl` over its path
//! through them, with `s` the altitude above the bottom over `top − bottom`
//! and ρ scaled by [`Aurora::brightness`], additively over the night sky and
//! whatever lies behind. So the order of the cells does not matter and the
//! aurora is right from below (the usual view), from inside and from above.
//! The default transfer function is the `Aurora` preset: green low (atomic
//! oxygen's 557.7 nm line, brightest just above the bottom), red high (its
//! 630.0 nm line above about 220 km), a pink-violet fringe at the bottom.
//!
//! # Animation
//!
//! A procedural footprint ([`AuroraFootprint::Curtains`]) is sampled at the
//! virtual time times [`Aurora::speed`]: its arcs sway, fold and pulse
//! smoothly (`nebel_core::field::AuroraCurtains`), and the quadtree, refined
//! along the curtains, is built again for each new footprint, on a worker,
//! one build at a time, so as often as the builds keep up (their cost,
//! footprint and quadtree together, is [`AuroraStats::build_ms`]). A map footprint ([`AuroraFootprint::Map`]) is
//! still: it is built once and refined again only when the eye moves. A
//! speed of 0 stops the animation.
//!
//! # Levels of detail
//!
//! The quadtree over the footprint refines where the curtains' top bends
//! (its roughness is the thickness's, Röttger's d2) and near the eye, with
//! the criterion's accuracy [`Aurora::accuracy`] (times the terrain factor
//! of `nebel_render::EffectiveQuality`), and morphs the tops, so curtains
//! never pop as the eye moves; culled to the view frustum.

mod batch;

use std::sync::Arc;

use bevy::diagnostic::DiagnosticPath;
use bevy::prelude::*;
use nebel_core::field::AuroraCurtains;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_render::{EffectStatus, GrayscaleMap};

use crate::SkyLayerError;
use crate::sky_layer::{SkyLayerStats, add_sky_layer};
use batch::AuroraState;

/// Adds [`Aurora`] and its systems (in [`PostUpdate`], after the camera's
/// transform) and diagnostics. Needs the cell projection
/// (`nebel_render::CellProjectionPlugin`) to draw; adds the map asset's
/// plugin (`nebel_render::GrayscaleMapPlugin`) for map footprints. A world
/// without an [`Aurora`] runs no aurora work.
#[derive(Default)]
pub struct AuroraPlugin;

impl AuroraPlugin {
    /// Auroras in the world that draw cells.
    pub const AURORAS: DiagnosticPath = DiagnosticPath::const_new("nebel/aurora/auroras");
    /// Tetrahedra drawn, all auroras.
    pub const TETRAHEDRA: DiagnosticPath = DiagnosticPath::const_new("nebel/aurora/tetrahedra");
    /// Time of the builds that landed in a frame (footprint, quadtree,
    /// refinement and prisms, on a worker), ms.
    pub const UPDATE_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/aurora/update_ms");
}

impl Plugin for AuroraPlugin {
    fn build(&self, app: &mut App) {
        app.register_type::<Aurora>()
            .register_type::<AuroraStatus>()
            .register_type::<AuroraStats>();
        add_sky_layer::<Aurora>(app);
    }
}

/// Where an aurora's curtains stand.
#[derive(Clone, Debug, PartialEq, Reflect)]
#[reflect(Clone)]
pub enum AuroraFootprint {
    /// Procedural arcs with folds and rays that drift, fold and pulse.
    Curtains(AuroraCurtains),
    /// A grayscale map asset (`asset_server.load::<GrayscaleMap>("aurora.png")`:
    /// black no curtain, white the strongest; values clamped to [0, 1]),
    /// covering the footprint from corner to corner (first row at −z),
    /// resampled bilinearly onto [`Aurora::resolution`] points. Still.
    Map(Handle<GrayscaleMap>),
}

impl Default for AuroraFootprint {
    fn default() -> Self {
        Self::Curtains(AuroraCurtains::default())
    }
}

/// An aurora over its entity (see the module docs). Lengths are metres in
/// the entity's frame.
#[derive(Component, Clone, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(AuroraStatus, AuroraStats, AuroraState, Transform, Visibility)]
pub struct Aurora {
    /// Where the curtains stand. Default: [`AuroraCurtains::default()`]
    /// (three arcs).
    pub footprint: AuroraFootprint,
    /// Side of the square footprint, centred on the entity, finite and > 0.
    /// Default 600 km.
    pub extent: f32,
    /// Altitude of the curtains' bottom above the entity, finite. Default
    /// 100 km (where real auroras end below).
    pub bottom: f32,
    /// Altitude the strongest curtains reach, finite and above `bottom`.
    /// Default 300 km.
    pub top: f32,
    /// Points per side of the footprint's grid, `2^k + 1` from 9 to 2049
    /// (else the status is `Failed`). Default 257 (a 2.3 km grid over the
    /// default extent).
    pub resolution: u32,
    /// Multiplies the transfer function's ρ, finite and ≥ 0: the emission
    /// per metre of path, 1/m. 0 draws nothing. Default 6e-6 (60 km of a
    /// curtain's bright base add about 0.36 of κ).
    pub brightness: f32,
    /// κ (emission colour) and ρ over the altitude in the curtains (0 at
    /// `bottom`, 1 at `top`). Default: the `Aurora` preset.
    #[reflect(ignore, default = "aurora_transfer_function")]
    pub transfer_function: Arc<TransferFunction>,
    /// Animation seconds per virtual second, finite and ≥ 0; 0 holds the
    /// curtains still. Default 1.
    pub speed: f32,
    /// Accuracy `c` of the quadtree's criterion, finite and > 0: larger
    /// refines the curtains more. Default 12.
    pub accuracy: f32,
}

fn aurora_transfer_function() -> Arc<TransferFunction> {
    Arc::new(TransferFunction::preset(TransferPreset::Aurora))
}

impl Default for Aurora {
    fn default() -> Self {
        Self {
            footprint: AuroraFootprint::default(),
            extent: 600e3,
            bottom: 100e3,
            top: 300e3,
            resolution: 257,
            brightness: 6e-6,
            transfer_function: aurora_transfer_function(),
            speed: 1.0,
            accuracy: 12.0,
        }
    }
}

/// What became of an [`Aurora`]: pending, ready, or failed and why.
pub type AuroraStatus = EffectStatus<SkyLayerError>;

/// Statistics of an [`Aurora`], updated by the plugin.
pub type AuroraStats = SkyLayerStats;

impl Aurora {
    /// Checks the settings the footprint and layer do not check themselves.
    pub fn validate(&self) -> Result<(), SkyLayerError> {
        let check = |ok, setting, value, requirement| {
            SkyLayerError::check(ok, "aurora", setting, value, requirement)
        };
        let resolution = self.resolution as f32;
        let layer_side = nebel_lod::is_layer_side(self.resolution);
        check(layer_side, "resolution", resolution, nebel_lod::LAYER_SIDES)?;
        for (setting, value, ok, requirement) in [
            (
                "brightness",
                self.brightness,
                self.brightness >= 0.0,
                "finite and >= 0",
            ),
            ("speed", self.speed, self.speed >= 0.0, "finite and >= 0"),
            (
                "accuracy",
                self.accuracy,
                self.accuracy > 0.0,
                "finite and > 0",
            ),
        ] {
            check(value.is_finite() && ok, setting, value, requirement)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
