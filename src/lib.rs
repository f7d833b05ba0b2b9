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
//! and `sky` need `terrain`).
//!
//! ```no_run
//! use bevy::prelude::*;
//! use nebel::prelude::*;
//!
//! App::new().add_plugins((DefaultPlugins, NebelPlugins)).run();
//! ```
//!
//! The README shows how to add each effect to a game; its Rust snippets are
//! compiled as doctests of this crate.
//!
//! # References
//!
//! - Röttger and Ertl 2003: Stefan Röttger and Thomas Ertl, "Fast Volumetric
//!   Display of Natural Gaseous Phenomena", Computer Graphics International,
//!   2003.
//! - Röttger 2004: Stefan Röttger, "Volumetric Methods for the Real-Time
//!   Display of Natural Gaseous Phenomena", doctoral thesis, University of
//!   Stuttgart, 2004.

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
        AutoQuality, CellBatch, CellProjection, CellResolution, HeavyBuilds, LodCamera,
        NebelQuality, NebelSystems, QualityPreset,
    };
    #[cfg(feature = "sky")]
    pub use nebel_sky::{
        Aurora, AuroraCurtains, AuroraError, AuroraFootprint, AuroraPlugin, AuroraStats,
        AuroraStatus, CloudLayer, CloudLayerError, CloudLayerPlugin, CloudLayerSource,
        CloudLayerStats, CloudLayerStatus,
    };
    #[cfg(feature = "terrain")]
    pub use nebel_terrain::{
        Terrain, TerrainBuildError, TerrainDebug, TerrainHeights, TerrainLodStats, TerrainNoise,
        TerrainPlugin, TerrainSource, TerrainStatus,
    };
    #[cfg(feature = "volume")]
    pub use nebel_volume::{
        Campfire, CloudLightModel, CloudVolume, FlickeringLight, FlickeringLightPlugin,
        LodCriterion, Volume, VolumeError, VolumeField, VolumeGrid, VolumeLighting, VolumeLod,
        VolumeStatus,
    };
}

/// The README's Rust snippets, compiled as doctests so they stay true.
#[doc = include_str!("../README.md")]
#[cfg(all(
    doctest,
    feature = "volume",
    feature = "terrain",
    feature = "fog",
    feature = "sky"
))]
pub struct ReadmeDoctests;
