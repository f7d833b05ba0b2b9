//! What the aurora's and the cloud layer's systems share: a transfer
//! function scaled by a density and cached, a grayscale map resampled onto
//! a layer's grid, a layer's cells for the LOD camera, the batch handed to
//! the cell projection (or taken away when there are no cells), and the
//! totals of the diagnostics.

use std::sync::Arc;

use bevy::asset::AssetLoadError;
use bevy::math::DAffine3;
use bevy::prelude::*;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferError, TransferFunction};
use nebel_lod::{
    CellOrder, Cells, FogProfile, Frustum, GpuCell, LayerStats, LayerView, LodSettings,
    PrismScalar, SurfaceLayer, SurfaceLayerError, TerrainError, TerrainMap, TerrainMesh,
};
use nebel_render::CellBatch;
use nebel_render::GrayscaleMap;
use nebel_render::camera::LodView;

/// A transfer function with ρ times a factor, kept while neither changes.
#[derive(Default)]
pub(crate) struct ScaledTransfer(Option<(u64, u32, Arc<TransferFunction>)>);

impl ScaledTransfer {
    /// `transfer` with ρ times `factor`, from the cache when both are the
    /// same as last time.
    pub(crate) fn get(
        &mut self,
        transfer: &TransferFunction,
        factor: f32,
    ) -> Result<Arc<TransferFunction>, TransferError> {
        let key = (transfer.content_hash(), factor.to_bits());
        if let Some((hash, bits, scaled)) = &self.0
            && (*hash, *bits) == key
        {
            return Ok(scaled.clone());
        }
        let scaled = Arc::new(transfer.scale_density(factor)?);
        self.0 = Some((key.0, key.1, scaled.clone()));
        Ok(scaled)
    }
}

/// Why a map could not be read onto a layer's grid.
pub(crate) enum MapError {
    /// The asset failed to load: its path and the asset server's error.
    NotLoaded(String, Arc<AssetLoadError>),
    /// Its values were refused (NaN, no values).
    Values(TerrainError),
}

/// A map's values resampled onto `side²` points (bilinear, corner to
/// corner), `None` while it loads.
pub(crate) fn map_values(
    handle: &Handle<GrayscaleMap>,
    side: usize,
    maps: &Assets<GrayscaleMap>,
    asset_server: &AssetServer,
) -> Result<Option<Vec<f32>>, MapError> {
    if let Some((path, error)) = GrayscaleMap::load_failure(handle, asset_server) {
        return Err(MapError::NotLoaded(path, error));
    }
    let Some(map) = maps.get(handle) else {
        return Ok(None);
    };
    let dims = [map.dims.x as usize, map.dims.y as usize];
    let layer = TerrainMap::resample(&map.values, dims, side).map_err(MapError::Values)?;
    Ok(Some(layer.values().to_vec()))
}

/// How a layer is drawn: its prisms' levels and scalar, and their order.
pub(crate) struct LayerDrawing<'a> {
    pub(crate) profile: &'a FogProfile,
    pub(crate) scalar: PrismScalar,
    pub(crate) order: CellOrder,
}

/// `layer`'s cells for `camera` (culled by its frustum in the layer's frame)
/// with the quadtree at `accuracy`, the layer's bottom placed by
/// `world_from_field`; `mesh` is the refinement's reused mesh.
pub(crate) fn layer_cells(
    layer: &SurfaceLayer,
    mesh: &mut TerrainMesh,
    camera: &LodView,
    world_from_field: DAffine3,
    accuracy: f32,
    drawing: LayerDrawing,
) -> Result<(Vec<GpuCell>, LayerStats), SurfaceLayerError> {
    // A degenerate projection culls nothing rather than everything.
    let frustum = Frustum::from_view_projection(camera.clip_from_world)
        .ok()
        .map(|frustum| frustum.in_local_frame(&world_from_field));
    let view = LayerView {
        world_from_field,
        eye: camera.eye,
        frustum: frustum.as_ref(),
        lod: LodSettings {
            accuracy,
            ..LodSettings::default()
        },
        order: drawing.order,
        profile: drawing.profile,
        scalar: drawing.scalar,
    };
    let mut cells = Vec::new();
    let counts = layer.cells(&view, mesh, &mut cells)?;
    Ok((cells, counts))
}

/// Gives `entity` the batch of `cells` (or takes its batch away when there
/// are none).
pub(crate) fn publish_cells(
    commands: &mut Commands,
    entity: Entity,
    has_batch: bool,
    cells: Vec<GpuCell>,
    transfer: Arc<TransferFunction>,
    mode: OpticalMode,
) {
    if cells.is_empty() {
        if has_batch {
            commands.entity(entity).remove::<CellBatch>();
        }
    } else {
        commands.entity(entity).insert(CellBatch::new(
            Arc::new(Cells::with_bounds(cells)),
            transfer,
            mode,
        ));
    }
}

/// The number of layers drawn and their tetrahedra, from each layer's
/// tetrahedra and whether it has a batch.
pub(crate) fn totals(layers: impl Iterator<Item = (u32, bool)>) -> (f64, f64) {
    layers
        .filter(|(_, has_batch)| *has_batch)
        .fold((0.0, 0.0), |(drawn, tetrahedra), (count, _)| {
            (drawn + 1.0, tetrahedra + f64::from(count))
        })
}
