//! nebel's sky plugins: the aurora and a lit cloud layer.
//!
//! The aurora ("polar light", Röttger 2004 §10.4) is emissive curtains between
//! two surfaces; the cloud layer lies between two surfaces, sorted and lit
//! ([`CloudLayer`], [`CloudLayerPlugin`]). Both are drawn by cell projection.
//!
//! Put an [`Aurora`] on an entity; [`AuroraPlugin`] then, every frame,
//!
//! - samples the curtains' footprint at the animation time (procedural arcs
//!   that drift, fold and pulse, [`AuroraCurtains`], or a grayscale map);
//! - raises each curtain from the plane at [`Aurora::bottom`] as high as it
//!   is strong, up to [`Aurora::top`], as a layer between two surfaces over
//!   a quadtree C-LOD that refines along the curtains
//!   ([`nebel_lod::AuroraShape`], [`nebel_lod::SurfaceLayer`]);
//! - hands the layer's prisms, coloured by altitude, to the cell
//!   projection as the entity's emissive `CellBatch` (additive, order
//!   independent, so it is right from below and from above);
//! - reports [`AuroraStatus`], [`AuroraStats`] and the `nebel/aurora/*`
//!   diagnostics.
//!
//! A world without an aurora, or with a hidden, dark or transparent one,
//! runs no aurora work: no footprint, no cells, no pass.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use nebel_sky::{Aurora, AuroraCurtains, AuroraFootprint};
//!
//! fn spawn(mut commands: Commands) {
//!     commands.spawn(Aurora {
//!         footprint: AuroraFootprint::Curtains(AuroraCurtains {
//!             count: 4,     // arcs
//!             drift: 0.02, // sways across the sky per second
//!             ..default()
//!         }),
//!         ..default()
//!     });
//! }
//! # let _ = spawn;
//! ```
//!
//! Papers are cited by author and year; `docs/references.md` in the repository lists them.

pub mod aurora;
pub mod cloud_layer;
mod error;
mod sky_layer;

pub use aurora::{Aurora, AuroraFootprint, AuroraPlugin, AuroraStats, AuroraStatus};
pub use cloud_layer::{
    CloudLayer, CloudLayerPlugin, CloudLayerSource, CloudLayerStats, CloudLayerStatus,
};
pub use error::SkyLayerError;
pub use nebel_core::field::{AuroraCurtains, FogNoise};
pub use sky_layer::SkyLayerStats;
