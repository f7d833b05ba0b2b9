//! nebel's level-of-detail and cell-batch builders, without Bevy.
//!
//! Every volumetric effect ends as a [`Cells`]: tetrahedra in world space
//! with a scalar per vertex, in the order the GPU draws them. This crate builds
//! those batches on the CPU, in plain Rust, so they are tested and benchmarked
//! without a GPU; the Bevy crates only upload them.
//!
//! - [`aurora`]: the aurora's curtains as a layer between a plane and a
//!   top raised by their strength ([`AuroraShape`], Röttger 2004 §10.4).
//! - [`batch`]: [`GpuCell`] (the GPU layout of one tetrahedron) and [`Cells`].
//! - [`cell_grid`]: a density grid drawn whole, by ray casting through its
//!   voxels' Kuhn tetrahedra ([`CellGrid`]), exact like the sorted cells.
//! - [`cloud_layer`]: a cloud layer between two surfaces, lit by the sun
//!   through the layer above each point ([`CloudLayerShape`], Röttger 2004
//!   §10.4).
//! - [`frustum`]: view frusta from planes or a view-projection matrix, and the
//!   conservative box test used to cull bricks and nodes.
//! - [`full_resolution`]: a density grid as Kuhn's six tetrahedra per voxel in
//!   exact back-to-front order for an eye, with per-brick zero-opacity test and
//!   frustum culling ([`BrickTable`], [`full_resolution_batch`]), and
//!   [`order_key`], which tells when a new eye position changes that order.
//! - [`ground_fog`]: ground fog as vertical prisms on the terrain's level of
//!   detail (Röttger and Ertl 2003 §6): [`fog_prisms`] turns a terrain mesh
//!   refined with the fog's thickness into conforming tetrahedra, back to
//!   front for any eye or unordered, with a vertical [`FogProfile`].
//! - [`octree`]: the volume C-LOD of Röttger and Ertl 2003 §2-3 and §5: the
//!   view-independent hierarchy ([`VolumeHierarchy`], with a lit cloud's light
//!   field), the per-frame refinement ([`fn@octree::refine`]) and the morphed,
//!   conforming cell batch ([`octree::lod_batch`], [`octree::lod_batch_with`]).
//! - [`quadtree`]: the terrain C-LOD of Röttger 2004 §3.5.3 (Röttger's
//!   quadtree, libMini's semantics): [`TerrainHierarchy`] and
//!   [`TerrainHierarchy::update`], one pass per frame that refines, geomorphs
//!   and writes crack-free triangle fans ([`TerrainMesh`]).
//! - [`surface_layer`]: a layer between two surfaces over one grid
//!   (Röttger 2004 §10.4: aurora curtains, a cloud layer): [`SurfaceLayer`]
//!   builds the quadtree over the bottom with the thickness's roughness and
//!   gives, per eye, the morphed conforming prisms between the surfaces.
//! - [`view`]: [`View`], what every builder reads of the camera for one
//!   volume and frame: the volume's placement, the eye, the frustum and the
//!   viewport (an empty viewport sees nothing).
//! - [`visibility`]: back-to-front order for any conforming tetrahedral mesh
//!   (MPVO, Williams 1992): [`CellAdjacency`] once per mesh, then
//!   [`CellAdjacency::back_to_front`] or [`sorted_batch`] per eye.
//! - [`volume_batcher`]: [`VolumeBatcher`], one volume's batch frame after
//!   frame, rebuilt only when the view or the inputs change it.
//!
//! Papers are cited by author and year; `docs/references.md` in the repository lists them.

pub mod aurora;
pub mod batch;
pub mod builds;
pub mod cell_grid;
pub mod cloud_layer;
pub mod frustum;
pub mod full_resolution;
pub mod ground_fog;
mod keyframe_track;
pub mod octree;
pub mod quadtree;
pub mod surface_layer;
pub mod view;
pub mod visibility;
pub mod volume_batcher;
pub mod volume_batching;

pub use aurora::AuroraShape;
pub use batch::{Cells, GpuCell};
pub use builds::{BuildKind, BuildPool, LocalBuilds};
pub use cell_grid::CellGrid;
pub use cloud_layer::CloudLayerShape;
pub use frustum::{Frustum, FrustumError};
pub use full_resolution::{BatchError, BrickTable, CellOrder, full_resolution_batch, order_key};
pub use ground_fog::{FogProfile, PrismError, PrismInput, PrismScalar, PrismStats, fog_prisms};
pub use keyframe_track::AnimatedGrid;
pub use octree::{HierarchyError, Node, VolumeHierarchy};
pub use quadtree::{
    LodSettings, TerrainError, TerrainHierarchy, TerrainMap, TerrainMesh, TriangleOrder,
};
pub use surface_layer::{
    LAYER_SIDES, LayerStats, LayerTop, LayerView, SurfaceLayer, SurfaceLayerError, is_layer_side,
};
pub use view::View;
pub use visibility::{CellAdjacency, sorted_batch};
pub use volume_batcher::{
    BatchLighting, BatchSettings, BuiltRefinementStep, FrameInputs, GridDrawing, OctreeSettings,
    RefinementStep, VolumeBatchError, VolumeBatcher, VolumeSource,
};
pub use volume_batching::{BuildRequest, FrameBatch, LandedBuilds, VolumeBatching};
