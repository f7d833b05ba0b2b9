//! nebel: volumetric effects for Bevy.
//!
//! Terrain with continuous level of detail (Röttger's quadtree C-LOD), cloud
//! volumes refined by a view-dependent octree and lit by a light field, and
//! emissive fire and search lights, drawn by cell projection with
//! pre-integrated transfer functions, exact per pixel (Röttger and Ertl,
//! "A Volumetric Cloud Rendering Method", 2003; Röttger, "Volumetric
//! Natural Phenomena", 2004). This umbrella crate is the plugin group
//! [`NebelPlugins`], the [`prelude`] and the re-exported crates; each effect is
//! a cargo feature.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use nebel::prelude::*;
//!
//! App::new().add_plugins((DefaultPlugins, NebelPlugins)).run();
//! ```
//!
//! A cloud from a density grid and an animated campfire:
//!
//! ```no_run
//! use std::sync::Arc;
//! use bevy::{math::DVec3, prelude::*};
//! use nebel::nebel_core::field::{DensityGrid, ProceduralNoise};
//! use nebel::nebel_core::optics::OpticalMode;
//! use nebel::nebel_core::transfer::{TransferFunction, TransferPreset};
//! use nebel::prelude::*;
//!
//! fn spawn_cloud(mut commands: Commands, mut grids: ResMut<Assets<VolumeGrid>>) {
//!     let grid = DensityGrid::procedural([33, 17, 33], DVec3::splat(0.25), DVec3::ZERO, &ProceduralNoise::default())
//!         .expect("valid grid");
//!     commands.spawn((
//!         Volume {
//!             field: VolumeField::Grid(grids.add(VolumeGrid::from(grid))),
//!             transfer_function: Arc::new(TransferFunction::preset(TransferPreset::Cloud)),
//!             mode: OpticalMode::Sorted,
//!         },
//!         Transform::from_xyz(-4.0, 10.0, -4.0),
//!     ));
//!     // An animated fire: emissive, 16³ cells regenerated every frame.
//!     commands.spawn((Campfire::default(), Transform::from_scale(Vec3::splat(2.0))));
//! }
//!
//! App::new()
//!     .add_plugins((DefaultPlugins, NebelPlugins))
//!     .add_systems(Startup, spawn_cloud)
//!     .run();
//! ```
//!
//! A lit cloud layer drawn through the octree C-LOD, drifting with the wind:
//!
//! ```no_run
//! use bevy::{math::DVec3, prelude::*};
//! use nebel::nebel_core::field::CloudNoise;
//! use nebel::prelude::*;
//!
//! fn spawn_clouds(mut commands: Commands) {
//!     commands.spawn((
//!         CloudVolume {
//!             dims: UVec3::new(129, 17, 129),
//!             min: Vec3::new(-2560.0, 600.0, -2560.0),
//!             max: Vec3::new(2560.0, 1240.0, 2560.0),
//!             noise: CloudNoise { coverage: 0.45, octaves: 5, wavelength: 1800.0,
//!                                 wind: DVec3::new(8.0, 0.0, 0.0), ..default() },
//!         },
//!         VolumeLod { accuracy: 16.0, min_accuracy: 4.0 },
//!         VolumeLighting { shadow_extinction: 0.008, ..default() },
//!     ));
//! }
//! ```
//!
//! A terrain from a 16-bit grayscale height map (`assets/valley.png`, black
//! 0 m, white 400 m, a grid point every 10 m) drawn through the quadtree
//! C-LOD with geomorphing, or a procedural one:
//!
//! ```no_run
//! use bevy::prelude::*;
//! use nebel::prelude::*;
//!
//! fn spawn_terrain(mut commands: Commands, assets: Res<AssetServer>) {
//!     commands.spawn(Terrain {
//!         source: TerrainSource::Heights(assets.load::<TerrainHeights>("valley.png")),
//!         spacing: 10.0,
//!         vertical_scale: 400.0,
//!         accuracy: 300.0,   // c: larger draws more triangles
//!         min_accuracy: 2.0, // C
//!         ..default()
//!     });
//!     // 513 × 513 points of fBm noise with wide valleys, 7 km east of the origin.
//!     commands.spawn((
//!         Terrain {
//!             source: TerrainSource::Procedural {
//!                 size: 513,
//!                 noise: TerrainNoise { seed: 7, exponent: 1.8, ..default() },
//!             },
//!             debug: TerrainDebug { lod_colours: true, ..default() },
//!             ..default()
//!         },
//!         Transform::from_xyz(7000.0, 0.0, 0.0),
//!     ));
//! }
//!
//! App::new()
//!     .add_plugins((DefaultPlugins, NebelPlugins))
//!     .add_systems(Startup, spawn_terrain)
//!     .run();
//! ```

use bevy::app::{PluginGroup, PluginGroupBuilder};

pub use nebel_core;
pub use nebel_render;
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
            .add(nebel_render::CellProjectionPlugin);
        #[cfg(feature = "volume")]
        let group = group
            .add(nebel_volume::VolumePlugin)
            .add(nebel_volume::FlickeringLightPlugin);
        #[cfg(feature = "terrain")]
        let group = group.add(nebel_terrain::TerrainPlugin);
        group
    }
}

/// `use nebel::prelude::*;` brings the plugins and the components a game spawns.
pub mod prelude {
    pub use crate::NebelPlugins;
    pub use nebel_render::{CellBatch, HeavyBuilds, LodCamera, NebelSystems};
    #[cfg(feature = "terrain")]
    pub use nebel_terrain::{
        Terrain, TerrainBuildError, TerrainDebug, TerrainHeights, TerrainLodStats, TerrainNoise,
        TerrainPlugin, TerrainSource, TerrainStatus,
    };
    #[cfg(feature = "volume")]
    pub use nebel_volume::{
        Campfire, CloudLightModel, CloudVolume, FlickeringLight, FlickeringLightPlugin, Volume,
        VolumeError, VolumeField, VolumeGrid, VolumeLighting, VolumeLod, VolumeStatus,
    };
}
