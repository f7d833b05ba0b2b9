//! nebel's volume plugin: clouds, smoke, fire and search lights.
//!
//! They are density grids or cells, drawn by the cell-projection render
//! system.
//!
//! Spawn a [`Volume`] (or a [`Campfire`] or a [`CloudVolume`], which fill and
//! animate one); [`VolumePlugin`] turns it into a [`CellBatch`] on the same
//! entity: the full-resolution grid (Kuhn's six tetrahedra per voxel), ray
//! cast whole, or as projected cells with [`ProjectedCells`]; or with
//! [`VolumeLod`] the octree C-LOD of Röttger and Ertl 2003, lit as a cloud with
//! [`VolumeLighting`]. The render system is the same for all of them. With
//! [`CloudShadowPlugin`], lit clouds shade the meshes below them.
//!
//! Papers are cited by author and year; `docs/references.md` in the repository lists them.

pub mod batching;
pub mod campfire;
pub mod cloud;
pub mod cloud_primitive;
pub mod cloud_shadow;
pub mod cloud_weather_map;
pub mod flickering_light;
pub mod grid;
pub mod grid_loader;
pub mod lighting;
pub mod lod;
pub mod status;
#[cfg(test)]
mod test_support;
pub mod volume;

pub use campfire::Campfire;
pub use cloud::CloudVolume;
pub use cloud_primitive::CloudPrimitive;
pub use cloud_shadow::{
    CloudShadowCaster, CloudShadowExtension, CloudShadowMaterial, CloudShadowPlugin,
    CloudShadowReceiver, CloudShadowSettings,
};
pub use cloud_weather_map::CloudWeatherMap;
pub use flickering_light::{FlickeringLight, FlickeringLightPlugin};
pub use grid::VolumeGrid;
pub use grid_loader::{VolumeGridLoadError, VolumeGridLoader, VolumeGridSettings};
pub use lighting::{CloudLightModel, VolumeLighting};
pub use lod::{LodCriterion, VolumeLod};
pub use status::{VolumeError, VolumeStatus};
pub use volume::{ProjectedCells, Volume, VolumeField, VolumePlugin};

pub use nebel_render::CellBatch;
