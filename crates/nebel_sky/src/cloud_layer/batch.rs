//! The cloud layer's cells frame after frame: its layer between two
//! surfaces built once per source and settings, then, whenever the eye, the
//! view, the sun, the placement or the drawing settings change, refined for
//! the eye, lit and sorted back to front
//! ([`nebel_lod::SurfaceLayer::cells`]) as the entity's [`CellBatch`].
//!
//! A hidden layer, one of no density or a transparent transfer function
//! has no batch; removing the `CloudLayer` removes its batch and state.

use std::sync::Arc;
use std::time::Instant;

use bevy::diagnostic::Diagnostics;
use bevy::math::DAffine3;
use bevy::prelude::*;
use nebel_core::optics::OpticalMode;
use nebel_lod::quadtree::DEFAULT_MIN_RESOLUTION;
use nebel_lod::{
    CellOrder, CloudLayerShape, LayerTop, PrismScalar, SurfaceLayer, SurfaceLayerError, TerrainMesh,
};
use nebel_render::GrayscaleMap;
use nebel_render::camera::to_double;
use nebel_render::{CellBatch, EffectiveQuality, LodCameras};

use crate::layer_batch::{
    LayerDrawing, MapError, ScaledTransfer, layer_cells, map_values, publish_cells, totals,
};

use super::{
    CloudLayer, CloudLayerError, CloudLayerPlugin, CloudLayerSource, CloudLayerStats,
    CloudLayerStatus,
};

/// What a cloud layer's layer was built from.
#[derive(Clone, Debug, PartialEq)]
struct LayerKey {
    source: CloudLayerSource,
    shape: CloudLayerShape,
    resolution: u32,
    /// The maps' values (by identity), for map surfaces.
    maps: [Option<usize>; 2],
}

/// What a cloud layer's cells were built from.
#[derive(Clone, Debug, PartialEq)]
struct CellsKey {
    builds: u64,
    clip_from_world: [u64; 16],
    transform: GlobalTransform,
    sun: [u32; 3],
    accuracy: u32,
}

/// A cloud layer's quadtree, buffers and caches.
#[derive(Component, Default)]
pub struct CloudLayerState {
    layer: Option<(LayerKey, SurfaceLayer)>,
    builds: u64,
    cells: Option<CellsKey>,
    transfer: ScaledTransfer,
    mesh: TerrainMesh,
}

/// A map's unit values on `side²` points, `None` while it loads.
fn unit_values(
    handle: &Handle<GrayscaleMap>,
    side: usize,
    maps: &Assets<GrayscaleMap>,
    asset_server: &AssetServer,
) -> Result<Option<Vec<f32>>, CloudLayerError> {
    map_values(handle, side, maps, asset_server).map_err(|error| match error {
        MapError::NotLoaded(path, error) => CloudLayerError::MapNotLoaded { path, error },
        MapError::Values(error) => SurfaceLayerError::from(error).into(),
    })
}

/// The layer of `layer`'s source, `None` while a map loads.
fn build_layer(
    layer: &CloudLayer,
    shape: &CloudLayerShape,
    maps: &Assets<GrayscaleMap>,
    asset_server: &AssetServer,
) -> Result<Option<SurfaceLayer>, CloudLayerError> {
    let side = layer.resolution as usize;
    match &layer.source {
        CloudLayerSource::Noise(noise) => {
            let thickness = noise.thickness(side, shape.extent / (side - 1) as f64)?;
            Ok(Some(shape.layer(
                side,
                &thickness,
                DEFAULT_MIN_RESOLUTION,
                1.0,
            )?))
        }
        CloudLayerSource::Maps { bottom, top, scale } => {
            let (Some(bottom), Some(top)) = (
                unit_values(bottom, side, maps, asset_server)?,
                unit_values(top, side, maps, asset_server)?,
            ) else {
                return Ok(None);
            };
            let surface = |unit: Vec<f32>| -> Vec<f32> {
                unit.iter().map(|u| layer.base + scale * u).collect()
            };
            let bottom = shape
                .field(side, surface(bottom))
                .map_err(|error| CloudLayerError::from(SurfaceLayerError::from(error)))?;
            let top = surface(top);
            Ok(Some(SurfaceLayer::new(
                bottom,
                LayerTop::Surface(&top),
                None,
                DEFAULT_MIN_RESOLUTION,
                1.0,
            )?))
        }
    }
}

/// A `CloudLayer` removed from an entity that lives on: its batch and
/// state go with it.
pub(super) fn remove_cloud_layers(
    mut commands: Commands,
    mut removed: RemovedComponents<CloudLayer>,
) {
    for entity in removed.read() {
        if let Ok(mut entity) = commands.get_entity(entity) {
            entity.remove::<(
                CellBatch,
                CloudLayerState,
                CloudLayerStatus,
                CloudLayerStats,
            )>();
        }
    }
}

/// Builds every visible cloud layer's cells (see the module docs).
pub(super) fn update_cloud_layers(
    mut commands: Commands,
    cameras: LodCameras,
    suns: Query<&GlobalTransform, With<DirectionalLight>>,
    mut layers: Query<(
        Entity,
        Ref<CloudLayer>,
        Ref<GlobalTransform>,
        &InheritedVisibility,
        Has<CellBatch>,
        &mut CloudLayerState,
        &mut CloudLayerStatus,
        &mut CloudLayerStats,
    )>,
    maps: Res<Assets<GrayscaleMap>>,
    asset_server: Res<AssetServer>,
    quality: Option<Res<EffectiveQuality>>,
    mut diagnostics: Diagnostics,
) {
    if layers.is_empty() {
        return;
    }
    let Some(camera) = cameras.view() else {
        return;
    };
    let accuracy_scale = quality
        .as_ref()
        .map_or(1.0, |quality| quality.terrain_accuracy_scale());
    // Toward the sun, world space: straight up without a directional light.
    let toward_sun = suns
        .iter()
        .next()
        .map_or(Vec3::Y, |sun| -sun.forward().as_vec3());
    let mut frame_ms = None;
    for (entity, layer, transform, visibility, has_batch, mut state, mut status, mut stats) in
        &mut layers
    {
        let state = &mut *state;
        let clear = |commands: &mut Commands, state: &mut CloudLayerState| {
            if has_batch {
                commands.entity(entity).remove::<CellBatch>();
            }
            state.cells = None;
        };
        if let Err(error) = layer.validate() {
            clear(&mut commands, state);
            status.fail("cloud layer", entity, error);
            continue;
        }
        if !visibility.get()
            || layer.density == 0.0
            || layer.transfer_function.is_transparent(0.0, 1.0)
        {
            clear(&mut commands, state);
            status.set_if_neq(CloudLayerStatus::Ready);
            continue;
        }
        let started = Instant::now();
        let layer_key = LayerKey {
            source: layer.source.clone(),
            shape: CloudLayerShape {
                extent: f64::from(layer.extent),
                base: f64::from(layer.base),
                sag: f64::from(layer.sag),
            },
            resolution: layer.resolution,
            maps: match &layer.source {
                CloudLayerSource::Maps { bottom, top, .. } => [bottom, top]
                    .map(|map| maps.get(map).map(|map| Arc::as_ptr(&map.values) as usize)),
                CloudLayerSource::Noise(_) => [None, None],
            },
        };
        let mut built_ms = None;
        if state.layer.as_ref().map(|(key, _)| key) != Some(&layer_key) {
            if matches!(*status, CloudLayerStatus::Failed(_))
                && state.layer.is_none()
                && !layer.is_changed()
            {
                continue;
            }
            match build_layer(&layer, &layer_key.shape, &maps, &asset_server) {
                Ok(Some(built)) => {
                    state.layer = Some((layer_key, built));
                    state.builds += 1;
                    built_ms = Some(started.elapsed().as_secs_f32() * 1e3);
                }
                Ok(None) => {
                    status.set_if_neq(CloudLayerStatus::Pending);
                    continue;
                }
                Err(error) => {
                    state.layer = None;
                    clear(&mut commands, state);
                    status.fail("cloud layer", entity, error);
                    continue;
                }
            }
        }
        let world_from_field = DAffine3::from_mat4(to_double(transform.to_matrix()));
        let sun_local = world_from_field
            .inverse()
            .transform_vector3(toward_sun.as_dvec3())
            .normalize_or(bevy::math::DVec3::Y);
        let accuracy = (f64::from(layer.accuracy) * accuracy_scale) as f32;
        let cells_key = CellsKey {
            builds: state.builds,
            clip_from_world: camera.clip_from_world.to_cols_array().map(f64::to_bits),
            transform: *transform,
            sun: toward_sun.to_array().map(f32::to_bits),
            accuracy: accuracy.to_bits(),
        };
        if state.cells.as_ref() == Some(&cells_key) && !layer.is_changed() {
            continue;
        }
        let transfer = match state.transfer.get(&layer.transfer_function, layer.density) {
            Ok(transfer) => transfer,
            Err(error) => {
                status.fail("cloud layer", entity, error.into());
                continue;
            }
        };
        let Some((_, surface_layer)) = &state.layer else {
            continue;
        };
        let drawing = LayerDrawing {
            profile: &CloudLayerShape::profile(),
            scalar: PrismScalar::Sunlit {
                extinction: layer.shadow_extinction,
                sun_height: sun_local.y as f32,
                ambient: layer.ambient,
                diffuse: layer.diffuse,
            },
            order: CellOrder::BackToFront,
        };
        let (cells, counts) = match layer_cells(
            surface_layer,
            &mut state.mesh,
            &camera,
            world_from_field,
            accuracy,
            drawing,
        ) {
            Ok(drawn) => drawn,
            Err(error) => {
                status.fail("cloud layer", entity, error.into());
                continue;
            }
        };
        state.cells = Some(cells_key);
        status.set_if_neq(CloudLayerStatus::Ready);
        publish_cells(
            &mut commands,
            entity,
            has_batch,
            cells,
            transfer,
            OpticalMode::Sorted,
        );
        let update_ms = started.elapsed().as_secs_f32() * 1e3;
        *stats = CloudLayerStats {
            triangles: counts.triangles as u32,
            prisms: counts.prisms as u32,
            tetrahedra: counts.tetrahedra as u32,
            updates: stats.updates + 1,
            build_ms: built_ms.unwrap_or(stats.build_ms),
            update_ms,
        };
        *frame_ms.get_or_insert(0.0) += f64::from(update_ms);
    }
    if let Some(ms) = frame_ms {
        diagnostics.add_measurement(&CloudLayerPlugin::UPDATE_MS, || ms);
    }
}

/// Measures the cloud layers' totals; nothing in a world without one.
pub(super) fn measure_cloud_layers(
    layers: Query<(&CloudLayerStats, Has<CellBatch>), With<CloudLayer>>,
    mut diagnostics: Diagnostics,
) {
    if layers.is_empty() {
        return;
    }
    let (drawn, tetrahedra) = totals(
        layers
            .iter()
            .map(|(stats, has_batch)| (stats.tetrahedra, has_batch)),
    );
    diagnostics.add_measurement(&CloudLayerPlugin::LAYERS, || drawn);
    diagnostics.add_measurement(&CloudLayerPlugin::TETRAHEDRA, || tetrahedra);
}
