//! The [`CloudLayer`] component, its status and statistics, and
//! [`CloudLayerPlugin`].
//!
//! A cloud layer lies between two surfaces over a square of
//! [`CloudLayer::extent`] centred on its entity (Röttger 2004 §10.4 and
//! Fig. 10.6: a cloud layer as prisms between two height fields, drawn with
//! the ground fog's machinery). Procedurally ([`CloudLayerSource::Noise`])
//! the clouds are noise patches of thickness `t` that grow from
//! [`CloudLayer::base`]: their bottom hangs `sag · t` below it, their top
//! rises `(1 − sag) · t` above it ([`nebel_lod::CloudLayerShape`]); from two
//! grayscale maps ([`CloudLayerSource::Maps`]) the bottom and top are
//! `base + scale · map` each, the clouds where the top lies above the
//! bottom.
//!
//! The layer is drawn sorted (emission and absorption, back to front for
//! the eye: its quadtree refines and its prisms are ordered again whenever
//! the eye moves) and lit like a cloud volume: each level of the prisms
//! carries the light that reaches it, `ambient + diffuse · e^{−σ d / sin
//! e}`, with `d` the cloud above it in its column, `e` the sun's elevation
//! (the first `DirectionalLight`; straight up without one) and `σ`
//! [`CloudLayer::shadow_extinction`] (Beer-Lambert through a plane-parallel
//! layer of the column's local thickness; optionally with multiple
//! scattering and the sky dimmed by the cloud above,
//! [`CloudLayer::scattering_octaves`], [`CloudLayer::sky_occlusion`]), read
//! by a transfer function over
//! light (default the `CloudLight` preset); the view rays see the extinction
//! [`CloudLayer::density`].
//!
//! The layer's quadtree is built once per source and settings, and its
//! cells whenever the view changes, on a worker (see the crate's shared
//! sky-layer skeleton); the last cells draw meanwhile.

mod batch;

use std::sync::Arc;

use bevy::diagnostic::DiagnosticPath;
use bevy::prelude::*;
use nebel_core::field::{CloudLighting, FogNoise, TerrainNoise};
use nebel_core::local_light::LightResponse;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_render::{EffectStatus, GrayscaleMap};

use crate::SkyLayerError;
use crate::sky_layer::{SkyLayerStats, add_sky_layer};
use batch::CloudLayerState;

/// Adds [`CloudLayer`] and its systems (in [`PostUpdate`], after the
/// camera's transform) and diagnostics. Needs the cell projection to draw;
/// adds the map asset's plugin (`nebel_render::GrayscaleMapPlugin`) for map
/// sources. A world without a [`CloudLayer`] runs no cloud-layer work.
#[derive(Default)]
pub struct CloudLayerPlugin;

impl CloudLayerPlugin {
    /// Cloud layers in the world that draw cells.
    pub const LAYERS: DiagnosticPath = DiagnosticPath::const_new("nebel/cloud_layer/layers");
    /// Tetrahedra drawn, all cloud layers.
    pub const TETRAHEDRA: DiagnosticPath =
        DiagnosticPath::const_new("nebel/cloud_layer/tetrahedra");
    /// Time of the builds that landed in a frame (quadtree when built,
    /// refinement and sorted prisms, on a worker), ms.
    pub const UPDATE_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/cloud_layer/update_ms");
}

impl Plugin for CloudLayerPlugin {
    fn build(&self, app: &mut App) {
        app.register_type::<CloudLayer>()
            .register_type::<CloudLayerStatus>()
            .register_type::<CloudLayerStats>();
        add_sky_layer::<CloudLayer>(app);
    }
}

/// Where a cloud layer's clouds come from.
#[derive(Clone, Debug, PartialEq, Reflect)]
#[reflect(Clone)]
pub enum CloudLayerSource {
    /// Noise patches of thickness (their `thickness` at the noise's peaks,
    /// their `coverage` the part of the sky they cover).
    Noise(FogNoise),
    /// Two grayscale map assets (`asset_server.load::<GrayscaleMap>(…)`:
    /// black 0, white 1), the bottom and the top surface at `base + scale ·
    /// value`, each resampled bilinearly onto [`CloudLayer::resolution`]
    /// points from corner to corner.
    Maps {
        /// The bottom surface's map.
        bottom: Handle<GrayscaleMap>,
        /// The top surface's map.
        top: Handle<GrayscaleMap>,
        /// Metres of a white pixel, finite and ≥ 0.
        scale: f32,
    },
}

impl Default for CloudLayerSource {
    fn default() -> Self {
        Self::Noise(FogNoise {
            noise: TerrainNoise {
                octaves: 5,
                wavelength: 4000.0,
                ..TerrainNoise::default()
            },
            thickness: 700.0,
            coverage: 0.45,
        })
    }
}

/// A cloud layer over its entity (see the module docs). Lengths are metres
/// in the entity's frame.
#[derive(Component, Clone, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(
    CloudLayerStatus,
    CloudLayerStats,
    CloudLayerState,
    Transform,
    Visibility
)]
pub struct CloudLayer {
    /// Where the clouds are. Default: noise patches up to 700 m thick, 5
    /// octaves from 4 km, covering 45 % of the sky.
    pub source: CloudLayerSource,
    /// Side of the square layer, centred on the entity, finite and > 0.
    /// Default 40 km.
    pub extent: f32,
    /// The altitude the clouds grow from, finite. Default 1500 m.
    pub base: f32,
    /// The part of a procedural cloud's thickness below `base`, in [0, 1].
    /// Default 0.2.
    pub sag: f32,
    /// Part of the side, in [0, 0.5], over which a procedural layer's
    /// thickness falls to 0 toward its four edges, so no cloud is cut flat
    /// by them ([`nebel_lod::CloudLayerShape::edge_fade`]); maps are drawn
    /// as they are. Default 0.1.
    pub edge_fade: f32,
    /// Points per side of the layer's grid, `2^k + 1` from 9 to 2049.
    /// Default 257.
    pub resolution: u32,
    /// Multiplies the transfer function's ρ, finite and ≥ 0: with the
    /// default transfer function the extinction of the view rays, 1/m. 0
    /// draws nothing. Default 0.01 (100 m to fade to 1/e).
    pub density: f32,
    /// Light every point receives, in [0, 1]. Default 0.3.
    pub ambient: f32,
    /// Light of the unshadowed sun, in [0, 1]. Default 0.7.
    pub diffuse: f32,
    /// Extinction toward the sun, 1/m, finite and ≥ 0; 0 casts no shadow.
    /// Default 0.004.
    pub shadow_extinction: f32,
    /// Octaves of multiple scattering of the sunlight through the cloud
    /// above (Wrenninge et al. 2013; `nebel_core::field::ScatteringOctaves`),
    /// 1 to 8: more light reaches a thick cloud's lower levels. Default 1
    /// (single scattering).
    pub scattering_octaves: u32,
    /// Whether the cloud above a point dims its ambient sky light, so thick
    /// clouds get dark bases (`nebel_lod::PrismScalar::Sunlit`). Default
    /// false.
    pub sky_occlusion: bool,
    /// How it scatters the point and spot lights with Bevy's
    /// `VolumetricLight` that reach it (`nebel_render::local_lights`), taken
    /// when its cells are built: the phase's asymmetry and a factor on its
    /// colour. Default: isotropic, 1.
    pub light_response: LightResponse,
    /// κ and ρ over the light. Default: the `CloudLight` preset.
    #[reflect(ignore, default = "cloud_layer_transfer_function")]
    pub transfer_function: Arc<TransferFunction>,
    /// Accuracy `c` of the quadtree's criterion, finite and > 0. Default 40.
    pub accuracy: f32,
}

fn cloud_layer_transfer_function() -> Arc<TransferFunction> {
    Arc::new(TransferFunction::preset(TransferPreset::CloudLight))
}

impl Default for CloudLayer {
    fn default() -> Self {
        Self {
            source: CloudLayerSource::default(),
            extent: 40e3,
            base: 1500.0,
            sag: 0.2,
            edge_fade: 0.1,
            resolution: 257,
            density: 0.01,
            ambient: CloudLighting::DEFAULT_AMBIENT,
            diffuse: CloudLighting::DEFAULT_DIFFUSE,
            shadow_extinction: 0.004,
            scattering_octaves: 1,
            sky_occlusion: false,
            light_response: LightResponse::default(),
            transfer_function: cloud_layer_transfer_function(),
            accuracy: 40.0,
        }
    }
}

/// What became of a [`CloudLayer`]: pending, ready, or failed and why.
pub type CloudLayerStatus = EffectStatus<SkyLayerError>;

/// Statistics of a [`CloudLayer`], updated by the plugin.
pub type CloudLayerStats = SkyLayerStats;

impl CloudLayer {
    /// Checks the settings the layer's builders do not check themselves.
    pub fn validate(&self) -> Result<(), SkyLayerError> {
        let check = |ok, setting, value, requirement| {
            SkyLayerError::check(ok, "cloud layer", setting, value, requirement)
        };
        let resolution = self.resolution as f32;
        let layer_side = nebel_lod::is_layer_side(self.resolution);
        check(layer_side, "resolution", resolution, nebel_lod::LAYER_SIDES)?;
        for (setting, value, ok, requirement) in [
            (
                "density",
                self.density,
                self.density >= 0.0,
                "finite and >= 0",
            ),
            (
                "shadow_extinction",
                self.shadow_extinction,
                self.shadow_extinction >= 0.0,
                "finite and >= 0",
            ),
            (
                "accuracy",
                self.accuracy,
                self.accuracy > 0.0,
                "finite and > 0",
            ),
            (
                "ambient",
                self.ambient,
                (0.0..=1.0).contains(&self.ambient),
                "in [0, 1]",
            ),
            (
                "diffuse",
                self.diffuse,
                (0.0..=1.0).contains(&self.diffuse),
                "in [0, 1]",
            ),
        ] {
            check(value.is_finite() && ok, setting, value, requirement)?;
        }
        let octaves = self.scattering_octaves;
        let octaves_ok = (1..=CloudLighting::MAX_SCATTERING_OCTAVES).contains(&octaves);
        check(
            octaves_ok,
            "scattering_octaves",
            octaves as f32,
            "between 1 and 8",
        )?;
        if let CloudLayerSource::Maps { scale, .. } = self.source {
            check(
                scale.is_finite() && scale >= 0.0,
                "scale",
                scale,
                "finite and >= 0",
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
