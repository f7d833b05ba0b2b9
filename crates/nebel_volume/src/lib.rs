//! nebel's volume plugin: clouds, smoke, fire and search lights as density
//! grids or cells, drawn by the cell-projection render system
//! (DESIGN.md §3, §5; paper 000 §4, paper 001 ch. 10).
//!
//! Spawn a [`Volume`] (or a [`Campfire`], which animates one); [`VolumePlugin`]
//! turns it into a [`CellBatch`] on the same entity. Today the batch is the full-resolution grid (five tetrahedra
//! per voxel, alternating); the octree C-LOD replaces that source without
//! changing the render system.

mod campfire;
mod lighting;
mod lod;
mod volume;

pub use campfire::Campfire;
pub use lighting::{CloudLightModel, VolumeLighting};
pub use lod::VolumeLod;
pub use volume::{Volume, VolumeField, VolumePlugin};

pub use nebel_render::CellBatch;
