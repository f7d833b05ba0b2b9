//! nebel's volume plugin: clouds, smoke, fire and search lights as density
//! grids or cells, drawn by the cell-projection render system
//! (DESIGN.md §3, §5; paper 000 §4, paper 001 ch. 10).
//!
//! Spawn a [`Volume`] (or a [`Campfire`] or a [`CloudVolume`], which fill and
//! animate one); [`VolumePlugin`] turns it into a [`CellBatch`] on the same
//! entity: the full-resolution grid (five tetrahedra per voxel, alternating),
//! or with [`VolumeLod`] the octree C-LOD of paper 000, lit as a cloud with
//! [`VolumeLighting`]. The render system is the same for all of them.

pub mod batching;
mod campfire;
mod cloud;
mod flickering_light;
pub mod grid;
pub mod grid_loader;
mod lighting;
mod lod;
mod status;
mod volume;

pub use campfire::Campfire;
pub use cloud::CloudVolume;
pub use flickering_light::{FlickeringLight, FlickeringLightPlugin};
pub use grid::VolumeGrid;
pub use grid_loader::{VolumeGridLoadError, VolumeGridLoader, VolumeGridSettings};
pub use lighting::{CloudLightModel, VolumeLighting};
pub use lod::VolumeLod;
pub use status::{VolumeError, VolumeStatus};
pub use volume::{Volume, VolumeField, VolumePlugin};

pub use nebel_render::CellBatch;
