//! A layer between two surfaces over one grid, as prisms on a quadtree C-LOD
//! (Röttger 2004 §10.4: the aurora's curtains and a cloud layer, drawn with
//! the ground fog's machinery of Röttger and Ertl 2003 §6).
//!
//! A [`SurfaceLayer`] holds a quadtree over the bottom surface (a
//! [`HeightField`] of `2^k + 1` points per side) and the layer's thickness
//! above it, `top − bottom` per grid point ([`LayerTop`]). Where the
//! surfaces cross (the top below the bottom) the thickness is clamped to 0:
//! the layer is empty there and gives no cells (a documented clamp, not an
//! error). A NaN or infinite height or thickness, or a top or value map with
//! another number of points than the bottom, is an error.
//!
//! # Refinement
//!
//! The quadtree's d2 is the bottom's own roughness with the thickness's,
//! times `roughness_weight`, entered as a maximum
//! ([`TerrainHierarchy::add_map_roughness`]), so the mesh refines where
//! either surface bends (the top's second differences are at most the sum
//! of the bottom's and the thickness's). Every frame,
//! [`SurfaceLayer::cells`] refines for the eye, morphs the thickness (and
//! an optional value map) with the quadtree's weights, so neither surface
//! pops, and writes the prisms of [`fog_prisms`]: conforming, in exact
//! back-to-front order for [`CellOrder::BackToFront`] (the sorted mode) or
//! in mesh order for [`CellOrder::Unordered`] (emissive and MIP), with the
//! scalar of [`PrismScalar`]: the relative height inside the layer, a value
//! from the map, or the height above the bottom over a fixed span.

use glam::{DAffine3, DVec3};
use nebel_core::field::HeightField;
use thiserror::Error;

use crate::batch::GpuCell;
use crate::frustum::Frustum;
use crate::full_resolution::CellOrder;
use crate::ground_fog::{FogProfile, PrismError, PrismInput, PrismScalar, fog_prisms};
use crate::quadtree::{
    LodSettings, TerrainError, TerrainHierarchy, TerrainMap, TerrainMesh, TriangleOrder,
};

/// Grid sides a layer's settings may ask for: `2^k + 1` from 9 to 2049
/// points (the aurora's and the cloud layer's `resolution`).
pub const LAYER_SIDES: &str = "2^k + 1 from 9 to 2049";

/// Whether `side` is one of [`LAYER_SIDES`].
pub fn is_layer_side(side: u32) -> bool {
    (9..=2049).contains(&side) && (side - 1).is_power_of_two()
}

/// The top of a [`SurfaceLayer`], one value per grid point of the bottom
/// (index `i + n·j`).
#[derive(Clone, Copy, Debug)]
pub enum LayerTop<'a> {
    /// The top surface's heights, in the bottom's frame.
    Surface(&'a [f32]),
    /// The thickness above the bottom.
    Thickness(&'a [f32]),
}

/// Why a [`SurfaceLayer`] could not be built or give its cells.
#[derive(Debug, Error)]
pub enum SurfaceLayerError {
    /// The quadtree, a surface or a map is invalid (see [`TerrainError`]).
    #[error(transparent)]
    Terrain(#[from] TerrainError),
    /// The prisms could not be built (see [`PrismError`]).
    #[error(transparent)]
    Prisms(#[from] PrismError),
}

/// How [`SurfaceLayer::cells`] sees and draws the layer.
#[derive(Clone, Copy, Debug)]
pub struct LayerView<'a> {
    /// The bottom's frame (that of its [`HeightField`]) to world space.
    pub world_from_field: DAffine3,
    /// The eye, world space.
    pub eye: DVec3,
    /// The view frustum in the bottom's frame
    /// ([`Frustum::in_local_frame`]); `None` keeps every node.
    pub frustum: Option<&'a Frustum>,
    /// The quadtree's accuracy and morphing (its normals, grid points and
    /// triangle order are chosen here).
    pub lod: LodSettings,
    /// Back to front for the sorted mode, mesh order otherwise.
    pub order: CellOrder,
    /// The levels of the stacked prisms (and their scalar, with
    /// [`PrismScalar::Profile`]).
    pub profile: &'a FogProfile,
    /// Where the cells' scalar comes from.
    pub scalar: PrismScalar,
}

/// Counters of one [`SurfaceLayer::cells`] call.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LayerStats {
    /// Triangles of the refined bottom.
    pub triangles: usize,
    /// Triangles with a layer above at least one vertex (each a column of
    /// prisms).
    pub prisms: usize,
    /// Tetrahedra written.
    pub tetrahedra: usize,
}

/// A layer between two surfaces (see the [module docs](self)).
#[derive(Clone, Debug)]
pub struct SurfaceLayer {
    hierarchy: TerrainHierarchy,
    thickness: TerrainMap,
    values: Option<TerrainMap>,
}

impl SurfaceLayer {
    /// The layer between `bottom` and `top`, with an optional value per grid
    /// point (the scalar of [`PrismScalar::Values`]), its quadtree built for
    /// the minimum resolution `min_resolution` (`C`) with the thickness's
    /// roughness weighted by `roughness_weight` (finite, ≥ 0).
    pub fn new(
        bottom: HeightField,
        top: LayerTop,
        values: Option<&[f32]>,
        min_resolution: f32,
        roughness_weight: f32,
    ) -> Result<Self, SurfaceLayerError> {
        let side = bottom.dims()[0];
        let thickness = match top {
            LayerTop::Thickness(thickness) => TerrainMap::new(side, thickness.to_vec())?,
            LayerTop::Surface(top) => {
                if top.len() != bottom.heights().len() {
                    return Err(TerrainError::MapLength {
                        side,
                        len: top.len(),
                    }
                    .into());
                }
                let difference = top
                    .iter()
                    .zip(bottom.heights())
                    .map(|(top, bottom)| top - bottom)
                    .collect();
                TerrainMap::new(side, difference)?
            }
        };
        let values = values
            .map(|values| TerrainMap::new(side, values.to_vec()))
            .transpose()?;
        let mut hierarchy = TerrainHierarchy::new(bottom, min_resolution)?;
        hierarchy.add_map_roughness(&thickness, roughness_weight)?;
        Ok(Self {
            hierarchy,
            thickness,
            values,
        })
    }

    /// The quadtree over the bottom, with the thickness's roughness.
    pub fn hierarchy(&self) -> &TerrainHierarchy {
        &self.hierarchy
    }

    /// The thickness per grid point, clamped to ≥ 0.
    pub fn thickness(&self) -> &TerrainMap {
        &self.thickness
    }

    /// The value map, if the layer has one.
    pub fn values(&self) -> Option<&TerrainMap> {
        self.values.as_ref()
    }

    /// Whether the layer has no thickness anywhere (no cells for any eye).
    pub fn is_empty(&self) -> bool {
        self.thickness.is_zero()
    }

    /// Refines the quadtree for `view.eye` into `mesh` (reused across
    /// frames) and writes the layer's cells, in world space, into `out`
    /// (cleared first).
    pub fn cells(
        &self,
        view: &LayerView,
        mesh: &mut TerrainMesh,
        out: &mut Vec<GpuCell>,
    ) -> Result<LayerStats, SurfaceLayerError> {
        out.clear();
        let sorted = view.order == CellOrder::BackToFront;
        let mesh_order = if sorted {
            TriangleOrder::BackToFront
        } else {
            TriangleOrder::Unordered
        };
        let settings = LodSettings {
            normals: false,
            grid_points: true,
            order: mesh_order,
            ..view.lod
        };
        let field_from_world = view.world_from_field.inverse();
        let eye = field_from_world.transform_point3(view.eye);
        let lod = self.hierarchy.update_with_maps(
            eye,
            view.frustum,
            &settings,
            Some(&self.thickness),
            self.values.as_ref(),
            mesh,
        )?;
        let origin = self.hierarchy.origin();
        let input = PrismInput {
            world_from_mesh: view.world_from_field * DAffine3::from_translation(origin),
            eye: eye - origin,
            mesh_order,
            order: view.order,
            profile: view.profile,
            scalar: view.scalar,
            beyond: None,
        };
        let prisms = fog_prisms(mesh, &input, out)?;
        Ok(LayerStats {
            triangles: lod.triangles,
            prisms: prisms.prisms,
            tetrahedra: prisms.tetrahedra,
        })
    }
}
