//! nebel: volumetric effects for Bevy.
//!
//! Terrain with continuous level of detail (Röttger's quadtree C-LOD), ground
//! fog lying in its valleys as prisms on that level of detail, fog layers
//! (height fog exact along every ray, one full-screen pass), cloud
//! volumes refined by a view-dependent octree and lit by a light field,
//! emissive fire and search lights, an aurora (emissive curtains between two
//! surfaces) and a cloud layer between two surfaces, drawn by cell projection with pre-integrated transfer
//! functions, exact per pixel. This umbrella crate is the plugin group
//! [`NebelPlugins`], the [`prelude`] and the re-exported crates; each effect
//! is a cargo feature (`volume`, `terrain`, `fog`, `sky`, all default; `fog`
//! needs `terrain`).
//!
//! ```no_run
//! use bevy::prelude::*;
//! use nebel::prelude::*;
//!
//! App::new().add_plugins((DefaultPlugins, NebelPlugins)).run();
//! ```
//!
//! The guides in the repository's `docs/guides/` show how to add each effect
//! to a game; their Rust snippets, and the README's, are compiled as doctests
//! of this crate. The papers nebel implements are listed in
//! `docs/references.md`.

use bevy::app::{PluginGroup, PluginGroupBuilder};

pub use nebel_core;
#[cfg(feature = "fog")]
pub use nebel_fog;
pub use nebel_lod;
pub use nebel_render;
#[cfg(feature = "sky")]
pub use nebel_sky;
#[cfg(feature = "terrain")]
pub use nebel_terrain;
#[cfg(feature = "volume")]
pub use nebel_volume;

/// Every nebel plugin this build was compiled with.
///
/// Add it after Bevy's `DefaultPlugins`. Each plugin costs nothing in a scene
/// without its components.
pub struct NebelPlugins;

impl PluginGroup for NebelPlugins {
    fn build(self) -> PluginGroupBuilder {
        let group = PluginGroupBuilder::start::<Self>()
            .add(nebel_render::NebelDiagnosticsPlugin)
            .add(nebel_render::NebelQualityPlugin)
            .add(nebel_render::CellProjectionPlugin);
        #[cfg(feature = "volume")]
        let group = group
            .add(nebel_volume::VolumePlugin)
            .add(nebel_volume::CloudShadowPlugin)
            .add(nebel_volume::FlickeringLightPlugin);
        #[cfg(feature = "terrain")]
        let group = group.add(nebel_terrain::TerrainPlugin);
        #[cfg(feature = "fog")]
        let group = group
            .add(nebel_fog::GroundFogPlugin)
            .add(nebel_fog::FogLayersPlugin);
        #[cfg(feature = "sky")]
        let group = group
            .add(nebel_sky::AuroraPlugin)
            .add(nebel_sky::CloudLayerPlugin);
        group
    }
}

/// `use nebel::prelude::*;` brings the plugins and the components a game spawns.
pub mod prelude {
    pub use crate::NebelPlugins;
    #[cfg(feature = "fog")]
    pub use nebel_fog::{
        FogLayers, FogLayersError, FogLayersPlugin, FogLayersStatus, FogNoise, FogThickness,
        GroundFog, GroundFogDebug, GroundFogError, GroundFogPlugin, GroundFogStats,
        GroundFogStatus, HeightFogLayer, ValleyFog,
    };
    pub use nebel_render::{
        AutoQuality, CellBatch, CellProjection, CellResolution, GrayscaleMap, HeavyBuilds,
        LodCamera, NebelQuality, NebelSystems, QualityPreset,
    };
    #[cfg(feature = "sky")]
    pub use nebel_sky::{
        Aurora, AuroraCurtains, AuroraFootprint, AuroraPlugin, AuroraStats, AuroraStatus,
        CloudLayer, CloudLayerPlugin, CloudLayerSource, CloudLayerStats, CloudLayerStatus,
        SkyLayerError,
    };
    #[cfg(feature = "terrain")]
    pub use nebel_terrain::{
        Terrain, TerrainBuildError, TerrainDebug, TerrainLodStats, TerrainMaterial, TerrainNoise,
        TerrainPlugin, TerrainSource, TerrainStatus,
    };
    #[cfg(feature = "volume")]
    pub use nebel_volume::{
        Campfire, CloudLightModel, CloudPrimitive, CloudShadowCaster, CloudShadowPlugin,
        CloudShadowReceiver, CloudShadowSettings, CloudVolume, CloudWeatherMap, FlickeringLight,
        FlickeringLightPlugin, LodCriterion, ProjectedCells, Volume, VolumeError, VolumeField,
        VolumeGrid, VolumeLighting, VolumeLod, VolumeStatus,
    };
}

/// The Rust snippets of the README and the guides, compiled as doctests so
/// they stay true.
#[cfg(all(
    doctest,
    feature = "volume",
    feature = "terrain",
    feature = "fog",
    feature = "sky"
))]
mod doctests {
    #[doc = include_str!("../README.md")]
    pub struct Readme;
    #[doc = include_str!("../docs/guides/volumes.md")]
    pub struct Volumes;
    #[doc = include_str!("../docs/guides/terrain.md")]
    pub struct Terrain;
    #[doc = include_str!("../docs/guides/ground-fog.md")]
    pub struct GroundFog;
    #[doc = include_str!("../docs/guides/fog-layers.md")]
    pub struct FogLayers;
    #[doc = include_str!("../docs/guides/aurora.md")]
    pub struct Aurora;
    #[doc = include_str!("../docs/guides/cloud-layer.md")]
    pub struct CloudLayer;
    #[doc = include_str!("../docs/guides/runtime.md")]
    pub struct Runtime;
}
