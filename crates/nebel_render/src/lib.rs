//! nebel's Bevy render plumbing.
//!
//! Every nebel effect plugin depends on this crate. It owns what the effects
//! share on the Bevy side:
//!
//! - [`cell_batch`]: the [`CellBatch`] component, the cells an effect wants drawn.
//! - [`cell_projection`]: the render feature that draws them, exact per pixel.
//! - [`fog_layers`]: height fog on the GPU, shared by the fog-layer pass and
//!   the cell projection ([`ViewFogLayers`]).
//! - [`quality`]: [`NebelQuality`], presets and the automatic mode that map
//!   to every effect's method and accuracy.
//! - [`builds`]: heavy builds on the task pool or in a per-frame budget
//!   ([`HeavyBuilds`]).
//! - [`camera`]: the camera that drives the level of detail ([`LodCamera`]).
//! - [`grayscale_map`]: [`GrayscaleMap`], a grayscale PNG as unit values on a
//!   grid: terrain heights, fog thickness, a sky layer's surfaces.
//! - [`fog_sunlight`]: the sun in ground fog, dimmed by the fog above and cut
//!   by the terrain's shadow ([`CellFogSunlight`]).
//! - [`local_lights`]: point and spot lights (opted in with `VolumetricLight`)
//!   scattered by sorted batches.
//! - [`light_shadows`]: their Bevy shadow maps in nebel's passes (light shafts).
//! - [`effect`]: what every effect plugin shares ([`EffectStatus`]).
//! - [`diagnostics`]: the [`NebelSystems`] set that every per-frame nebel system
//!   joins and the CPU time that set takes each frame.
//!
//! Papers are cited by author and year; `docs/references.md` in the repository lists them.

pub mod builds;
pub mod camera;
pub mod cell_batch;
pub mod cell_projection;
pub mod cloud_shadow_maps;
pub mod data_texture;
pub mod diagnostics;
pub mod effect;
pub mod fog_layers;
pub mod fog_sunlight;
mod frame_budget;
pub mod grayscale_map;
pub mod headless;
pub mod light_shadows;
pub mod local_lights;
pub mod quality;

pub use builds::{HeavyBuild, HeavyBuilds, free_in_background};
pub use camera::{LodCamera, LodCameras, LodView};
pub use cell_batch::{CellBatch, CellBlend, CellScattering, CellSunlight};
pub use cell_projection::{
    CellProjection, CellProjectionPlugin, CellProjectionStats, CellProjectionSystems,
    CellResolution, CountCellFragments,
};
pub use cloud_shadow_maps::{CloudShadowMapUniform, CloudShadowMaps};
pub use diagnostics::{NebelDiagnosticsPlugin, NebelSystems, cpu_timed};
pub use effect::{EffectStatus, InvalidSetting, register_diagnostics};
pub use fog_layers::{FogLayersUniform, ViewFogLayers};
pub use fog_sunlight::CellFogSunlight;
pub use grayscale_map::{GrayscaleMap, GrayscaleMapError, GrayscaleMapLoader, GrayscaleMapPlugin};
pub use quality::{AutoQuality, EffectiveQuality, NebelQuality, NebelQualityPlugin, QualityPreset};
