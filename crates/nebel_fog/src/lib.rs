//! nebel's fog plugins: ground fog in the terrain's valleys, and fog layers.
//!
//! Volumetric ground fog lies in the valleys of the C-LOD terrain (Röttger and
//! Ertl 2003 §6; Röttger 2004 §10.4). Fog layers, height fog exact along every
//! ray in one full-screen pass, are its far and cheap partner (Röttger 2004
//! §5.3; [`fog_layers`], [`FogLayers`] on a camera, [`FogLayersPlugin`]).
//!
//! Put a [`GroundFog`] on a [`Terrain`](nebel_terrain::Terrain) entity;
//! [`GroundFogPlugin`] then
//!
//! - takes the fog's thickness above the ground from a grayscale map, noise
//!   patches or the valleys filled to an altitude ([`FogThickness`]), and
//!   adds its roughness to the terrain quadtree's d2 on the task pool
//!   ([`map`]), so the terrain also refines where the fog's top varies;
//! - after every refinement of the terrain, gives every triangle drawn a
//!   vertical prism up to the fog's top, morphed with the terrain so the top
//!   never pops, split into conforming tetrahedra and, for the sorted mode,
//!   in exact back-to-front order for the eye ([`nebel_lod::ground_fog`]),
//!   and hands them to the cell projection as the entity's `CellBatch`
//!   ([`batch`]);
//! - with a sun colour, lights a sorted fog by the first `DirectionalLight`,
//!   dimmed by the fog above and cut by the terrain's shadow ([`sunlight`]);
//! - reports [`GroundFogStatus`], [`GroundFogStats`] and the `nebel/fog/*`
//!   diagnostics, and draws the cells' edges as lines in the debug view.
//!
//! A terrain without fog, a fog of no thickness or density, or a hidden one
//! costs nothing per frame: no cells, no batch, no pass.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use nebel_core::field::ValleyFog;
//! use nebel_fog::{FogThickness, GroundFog};
//! use nebel_terrain::Terrain;
//!
//! fn spawn(mut commands: Commands) {
//!     commands.spawn((
//!         Terrain::default(),
//!         GroundFog {
//!             // Fill every valley up to 80 m, the shore ragged by ±10 m.
//!             thickness: FogThickness::Valley(ValleyFog {
//!                 altitude: 80.0,
//!                 edge: 10.0,
//!                 ..default()
//!             }),
//!             density: 0.02, // extinction at the ground, 1/m
//!             ..default()
//!         },
//!     ));
//! }
//! # let _ = spawn;
//! ```
//!
//! Papers are cited by author and year; `docs/references.md` in the repository lists them.

pub mod batch;
pub mod error;
pub mod fog_layers;
pub mod ground_fog;
pub mod map;
pub mod sunlight;

pub use error::GroundFogError;
pub use fog_layers::{FogLayers, FogLayersError, FogLayersPlugin, FogLayersStatus};
pub use ground_fog::{
    FogThickness, GroundFog, GroundFogDebug, GroundFogPlugin, GroundFogStats, GroundFogStatus,
};

pub use nebel_core::field::{FogNoise, ValleyFog};
pub use nebel_core::height_fog::HeightFogLayer;

#[cfg(test)]
mod tests;
