//! A layer over the terrain that its level of detail carries: an effect on
//! the terrain's entity (the ground fog of Röttger and Ertl 2003 §6) gives the
//! terrain a [`TerrainLayerLod`], and the terrain then refines the layer's
//! quadtree (its own, with the layer's roughness added to d2) and morphs the
//! layer's values with its heights into the mesh it keeps
//! ([`TerrainLod::mesh`](crate::build::TerrainLod::mesh)), so the effect's
//! cells sit on exactly the triangles drawn.

use std::sync::Arc;

use bevy::prelude::*;
use nebel_lod::TerrainHierarchy;
use nebel_lod::quadtree::TerrainLayer;

/// A layer for the terrain on the same entity to carry (see the
/// [module docs](self)); written by the effect that owns the layer, read by
/// the terrain's systems. Without one (the default) the terrain refines its
/// own quadtree alone.
#[derive(Component, Clone, Debug, Default, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct TerrainLayerLod {
    /// The terrain's quadtree with the layer's roughness added
    /// (`TerrainHierarchy::add_layer_roughness`), and the layer: one value
    /// per grid point of that quadtree. Used only while the terrain's own
    /// quadtree is still the one it was derived from (`base`); `None`: no
    /// layer.
    #[reflect(ignore)]
    pub quadtree: Option<LayeredQuadtree>,
    /// Refine whenever the eye moves at all (a sorted layer's cell order
    /// depends on the exact eye), not only after `Terrain::update_distance`.
    /// Default false.
    pub refine_on_every_move: bool,
}

/// A quadtree with a layer, derived from a terrain's own quadtree.
#[derive(Clone, Debug)]
pub struct LayeredQuadtree {
    /// The terrain's own quadtree it was derived from.
    pub base: Arc<TerrainHierarchy>,
    /// `base` with the layer's roughness added.
    pub hierarchy: Arc<TerrainHierarchy>,
    /// The layer's values per grid point.
    pub layer: Arc<TerrainLayer>,
}
