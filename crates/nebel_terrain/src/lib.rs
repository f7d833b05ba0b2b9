//! nebel's terrain plugin: height fields drawn through Röttger's quadtree.
//!
//! The quadtree C-LOD with geomorphing of Röttger 2004 §3.5.3 (Eq. 3.2); the
//! algorithm is [`nebel_lod::quadtree`].
//!
//! Spawn a [`Terrain`]; [`TerrainPlugin`] gives the entity a Bevy [`Mesh`]
//! (`Mesh3d`) and a material:
//!
//! - the heights come from a 16-bit grayscale PNG through the `AssetServer`
//!   (`nebel_render::GrayscaleMap`) or from a procedural
//!   generator ([`TerrainSource::Procedural`]), times the vertical scale, on
//!   a grid `spacing` apart centred on the entity ([`terrain`]);
//! - the quadtree refines where `f = l² / (d² · max(c · d2, C)²) < 1` for the
//!   camera's eye, morphs every new vertex in from the coarse mesh (heights
//!   and normals) and culls by the view frustum; the mesh's positions are
//!   relative to the entity, whose `Transform` places the terrain, so a
//!   terrain 100 km from the world origin keeps its precision;
//! - the quadtree is built on Bevy's task pool and appears when ready
//!   ([`build`]);
//! - the mesh is rebuilt only when the eye moved or turned enough or the
//!   terrain changed, into the same buffers ([`update`]);
//! - the mesh carries UVs over the terrain, fixed under geomorphing; the
//!   default material shades by height and slope (grass, rock, snow) in
//!   vertex colours, or a `StandardMaterial` or any `Material` of the
//!   user's draws it ([`TerrainMaterial`]); debug views colour the quadtree
//!   levels or darken the triangle edges ([`TerrainDebug`], [`shading`]).
//!
//! - an effect on the terrain's entity can give the level of detail a map
//!   to carry ([`TerrainMapLod`], [`map`]): the ground fog's thickness,
//!   morphed with the heights, refined by its roughness too.
//!
//! [`TerrainStatus`] tells whether the terrain is loading, drawn or failed
//! (and why: [`TerrainBuildError`]), [`TerrainLodStats`] its triangles and
//! timings; the `nebel/terrain/*` diagnostics of [`TerrainPlugin`] sum them.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use nebel_render::GrayscaleMap;
//! use nebel_terrain::{Terrain, TerrainPlugin, TerrainSource};
//!
//! fn spawn_terrain(mut commands: Commands, assets: Res<AssetServer>) {
//!     commands.spawn(Terrain {
//!         source: TerrainSource::Heights(assets.load::<GrayscaleMap>("valley.png")),
//!         spacing: 10.0,         // metres between grid points
//!         vertical_scale: 400.0, // metres of a white pixel
//!         ..default()
//!     });
//! }
//! # let _ = spawn_terrain;
//! ```
//!
//! [`Mesh`]: bevy::prelude::Mesh
//!
//! Papers are cited by author and year; `docs/references.md` in the repository lists them.

pub mod build;
pub mod error;
pub mod map;
pub mod shading;
pub mod terrain;
pub mod update;

pub use build::TerrainLod;
pub use error::TerrainBuildError;
pub use map::{MappedQuadtree, TerrainMapLod};
pub use terrain::{
    Terrain, TerrainDebug, TerrainLodStats, TerrainMaterial, TerrainPlugin, TerrainSource,
    TerrainStatus, TerrainSystems,
};

pub use nebel_core::field::TerrainNoise;
