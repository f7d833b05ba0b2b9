//! nebel's volume plugin: clouds, smoke, fire and search lights as density
//! grids or cells, drawn by the cell-projection render system.
//!
//! Spawn a [`Volume`] (or a [`Campfire`] or a [`CloudVolume`], which fill and
//! animate one); [`VolumePlugin`] turns it into a [`CellBatch`] on the same
//! entity: the full-resolution grid (Kuhn's six tetrahedra per voxel),
//! or with [`VolumeLod`] the octree C-LOD of Röttger and Ertl 2003, lit as a cloud with
//! [`VolumeLighting`]. The render system is the same for all of them.
//!
//! # References
//!
//! Papers are cited by author and year:
//!
//! - Röttger and Ertl 2003: Stefan Röttger and Thomas Ertl, "Fast Volumetric Display of
//!   Natural Gaseous Phenomena", Computer Graphics International, 2003.
//! - Nes 2008: Gisle Nes, "Physically Plausible Weather Visualization", master's thesis,
//!   University of Bergen, 2008.
//! - Williams 1992: Peter L. Williams, "Visibility Ordering Meshed Polyhedra", ACM
//!   Transactions on Graphics 11(2), 1992.

pub mod batching;
pub mod campfire;
pub mod cloud;
pub mod flickering_light;
pub mod grid;
pub mod grid_loader;
pub mod keyframes;
pub mod lighting;
pub mod lod;
pub mod status;
pub mod volume;

pub use campfire::Campfire;
pub use cloud::CloudVolume;
pub use flickering_light::{FlickeringLight, FlickeringLightPlugin};
pub use grid::VolumeGrid;
pub use grid_loader::{VolumeGridLoadError, VolumeGridLoader, VolumeGridSettings};
pub use lighting::{CloudLightModel, VolumeLighting};
pub use lod::{LodCriterion, VolumeLod};
pub use status::{VolumeError, VolumeStatus};
pub use volume::{Volume, VolumeField, VolumePlugin};

pub use nebel_render::CellBatch;
