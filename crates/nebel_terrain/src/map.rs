//! A map over the terrain that its level of detail carries: an effect on
//! the terrain's entity (the ground fog of Röttger and Ertl 2003 §6) gives the
//! terrain a [`TerrainMapLod`], and the terrain then refines the map's
//! quadtree (its own, with the map's roughness added to d2) and morphs the
//! map's values with its heights into the mesh it keeps
//! ([`TerrainLod::mesh`](crate::build::TerrainLod::mesh)), so the effect's
//! cells sit on exactly the triangles drawn.

use std::sync::Arc;

use bevy::prelude::*;
use nebel_lod::TerrainHierarchy;
use nebel_lod::quadtree::TerrainMap;

/// A map for the terrain on the same entity to carry (see the
/// [module docs](self)); written by the effect that owns the map, read by
/// the terrain's systems. Without one (the default) the terrain refines its
/// own quadtree alone.
#[derive(Component, Clone, Debug, Default, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct TerrainMapLod {
    /// The terrain's quadtree with the map's roughness added
    /// (`TerrainHierarchy::add_map_roughness`), and the map: one value
    /// per grid point of that quadtree. Used only while the terrain's own
    /// quadtree is still the one it was derived from (`base`); `None`: no
    /// map.
    #[reflect(ignore)]
    pub quadtree: Option<MappedQuadtree>,
    /// The most grid spacings the eye may move before the terrain refines
    /// again, whatever `Terrain::update_distance` says: a sorted map's cells
    /// are ordered for the eye the terrain was refined for. `None` (the
    /// default): the terrain's own.
    pub max_update_distance: Option<f32>,
}

/// A quadtree with a map, derived from a terrain's own quadtree.
#[derive(Clone, Debug)]
pub struct MappedQuadtree {
    /// The terrain's own quadtree it was derived from.
    pub base: Arc<TerrainHierarchy>,
    /// `base` with the map's roughness added.
    pub hierarchy: Arc<TerrainHierarchy>,
    /// The map's values per grid point.
    pub map: Arc<TerrainMap>,
}
