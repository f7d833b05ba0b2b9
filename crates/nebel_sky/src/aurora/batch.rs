//! The aurora's cells frame after frame: the footprint at the animation
//! time, the layer between the plane and the curtains' tops
//! ([`AuroraShape::layer`]), refined for the eye and culled to the view
//! ([`nebel_lod::SurfaceLayer::cells`]), as the entity's emissive
//! [`CellBatch`].
//!
//! The layer is built again when its footprint changed (every frame while a
//! procedural footprint is animated; when the settings or the map change
//! otherwise), the cells when the layer, the eye, the view, the placement
//! or the drawing settings changed. A hidden or dark aurora (no brightness,
//! a transparent transfer function) has no batch and costs a few
//! comparisons per frame; removing the `Aurora` removes its batch and
//! state.

use std::sync::Arc;
use std::time::Instant;

use bevy::diagnostic::Diagnostics;
use bevy::math::DAffine3;
use bevy::prelude::*;
use nebel_core::optics::OpticalMode;
use nebel_lod::quadtree::DEFAULT_MIN_RESOLUTION;
use nebel_lod::{AuroraShape, CellOrder, SurfaceLayer, SurfaceLayerError, TerrainMesh};
use nebel_render::GrayscaleMap;
use nebel_render::camera::to_double;
use nebel_render::{CellBatch, EffectiveQuality, LodCameras};

use super::{Aurora, AuroraError, AuroraFootprint, AuroraPlugin, AuroraStats, AuroraStatus};
use crate::layer_batch::{
    LayerDrawing, MapError, ScaledTransfer, layer_cells, map_values, publish_cells, totals,
};

/// What an aurora's layer was built from.
#[derive(Clone, Debug, PartialEq)]
struct LayerKey {
    footprint: AuroraFootprint,
    shape: AuroraShape,
    resolution: u32,
    /// The animation time, seconds (bits), for a procedural footprint.
    time: Option<u64>,
    /// The map's values (by identity), for a map footprint.
    map: Option<usize>,
}

/// What an aurora's cells were built from.
#[derive(Clone, Debug, PartialEq)]
struct CellsKey {
    /// Layer builds so far.
    builds: u64,
    /// The camera's world-from-clip transform and its eye.
    clip_from_world: [u64; 16],
    /// The aurora's placement.
    transform: GlobalTransform,
    /// The refinement's accuracy (bits).
    accuracy: u32,
}

/// An aurora's layer, buffers and caches.
#[derive(Component, Default)]
pub struct AuroraState {
    layer: Option<(LayerKey, SurfaceLayer)>,
    builds: u64,
    cells: Option<CellsKey>,
    transfer: ScaledTransfer,
    mesh: TerrainMesh,
}

/// The footprint's strengths on `side²` points, `None` while its map loads.
fn footprint(
    aurora: &Aurora,
    side: usize,
    time: f64,
    maps: &Assets<GrayscaleMap>,
    asset_server: &AssetServer,
) -> Result<Option<Vec<f32>>, AuroraError> {
    match &aurora.footprint {
        AuroraFootprint::Curtains(curtains) => Ok(Some(curtains.map(side, time)?)),
        AuroraFootprint::Map(handle) => {
            map_values(handle, side, maps, asset_server).map_err(|error| match error {
                MapError::NotLoaded(path, error) => AuroraError::MapNotLoaded { path, error },
                MapError::Values(error) => SurfaceLayerError::from(error).into(),
            })
        }
    }
}

/// An `Aurora` removed from an entity that lives on: its batch and state go
/// with it.
pub(super) fn remove_auroras(mut commands: Commands, mut removed: RemovedComponents<Aurora>) {
    for entity in removed.read() {
        if let Ok(mut entity) = commands.get_entity(entity) {
            entity.remove::<(CellBatch, AuroraState, AuroraStatus, AuroraStats)>();
        }
    }
}

/// Builds every visible aurora's layer and cells (see the module docs).
pub(super) fn update_auroras(
    mut commands: Commands,
    cameras: LodCameras,
    time: Res<Time<Virtual>>,
    mut auroras: Query<(
        Entity,
        Ref<Aurora>,
        Ref<GlobalTransform>,
        &InheritedVisibility,
        Has<CellBatch>,
        &mut AuroraState,
        &mut AuroraStatus,
        &mut AuroraStats,
    )>,
    maps: Res<Assets<GrayscaleMap>>,
    asset_server: Res<AssetServer>,
    quality: Option<Res<EffectiveQuality>>,
    mut diagnostics: Diagnostics,
) {
    if auroras.is_empty() {
        return;
    }
    let Some(camera) = cameras.view() else {
        return;
    };
    let accuracy_scale = quality
        .as_ref()
        .map_or(1.0, |quality| quality.terrain_accuracy_scale());
    let mut frame_ms = None;
    for (entity, aurora, transform, visibility, has_batch, mut state, mut status, mut stats) in
        &mut auroras
    {
        let state = &mut *state;
        let dark = !visibility.get()
            || aurora.brightness == 0.0
            || aurora.transfer_function.is_transparent(0.0, 1.0);
        if let Err(error) = aurora.validate() {
            if has_batch {
                commands.entity(entity).remove::<CellBatch>();
            }
            state.cells = None;
            status.fail("aurora", entity, error);
            continue;
        }
        if dark {
            if has_batch {
                commands.entity(entity).remove::<CellBatch>();
            }
            state.cells = None;
            status.set_if_neq(AuroraStatus::Ready);
            continue;
        }
        let started = Instant::now();
        let side = aurora.resolution as usize;
        let animated = matches!(aurora.footprint, AuroraFootprint::Curtains(_));
        let seconds = time.elapsed_secs_f64() * f64::from(aurora.speed);
        let shape = AuroraShape {
            extent: f64::from(aurora.extent),
            bottom: f64::from(aurora.bottom),
            top: f64::from(aurora.top),
        };
        let layer_key = LayerKey {
            footprint: aurora.footprint.clone(),
            shape,
            resolution: aurora.resolution,
            time: animated.then_some(seconds.to_bits()),
            map: match &aurora.footprint {
                AuroraFootprint::Map(handle) => maps
                    .get(handle)
                    .map(|map| Arc::as_ptr(&map.values) as usize),
                AuroraFootprint::Curtains(_) => None,
            },
        };
        let mut built_ms = None;
        if state.layer.as_ref().map(|(key, _)| key) != Some(&layer_key) {
            // Not again until something changes, also after a failure.
            let failed = matches!(*status, AuroraStatus::Failed(_))
                && state.layer.is_none()
                && !aurora.is_changed();
            if failed {
                continue;
            }
            let built =
                footprint(&aurora, side, seconds, &maps, &asset_server).and_then(|strength| {
                    strength
                        .map(|strength| {
                            shape
                                .layer(side, &strength, DEFAULT_MIN_RESOLUTION, 1.0)
                                .map_err(AuroraError::from)
                        })
                        .transpose()
                });
            match built {
                Ok(Some(layer)) => {
                    state.layer = Some((layer_key, layer));
                    state.builds += 1;
                    built_ms = Some(started.elapsed().as_secs_f32() * 1e3);
                }
                Ok(None) => {
                    status.set_if_neq(AuroraStatus::Pending);
                    continue;
                }
                Err(error) => {
                    state.layer = None;
                    state.cells = None;
                    if has_batch {
                        commands.entity(entity).remove::<CellBatch>();
                    }
                    status.fail("aurora", entity, error);
                    continue;
                }
            }
        }
        let accuracy = (f64::from(aurora.accuracy) * accuracy_scale) as f32;
        let cells_key = CellsKey {
            builds: state.builds,
            clip_from_world: camera.clip_from_world.to_cols_array().map(f64::to_bits),
            transform: *transform,
            accuracy: accuracy.to_bits(),
        };
        let transfer_changed = aurora.is_changed();
        if state.cells.as_ref() == Some(&cells_key) && !transfer_changed {
            continue;
        }
        let transfer = match state
            .transfer
            .get(&aurora.transfer_function, aurora.brightness)
        {
            Ok(transfer) => transfer,
            Err(error) => {
                status.fail("aurora", entity, error.into());
                continue;
            }
        };
        let Some((_, layer)) = &state.layer else {
            continue;
        };
        let world_from_field = DAffine3::from_mat4(to_double(transform.to_matrix()));
        let drawing = LayerDrawing {
            profile: &AuroraShape::profile(),
            scalar: shape.scalar(),
            order: CellOrder::Unordered,
        };
        let (cells, counts) = match layer_cells(
            layer,
            &mut state.mesh,
            &camera,
            world_from_field,
            accuracy,
            drawing,
        ) {
            Ok(drawn) => drawn,
            Err(error) => {
                status.fail("aurora", entity, error.into());
                continue;
            }
        };
        state.cells = Some(cells_key);
        status.set_if_neq(AuroraStatus::Ready);
        publish_cells(
            &mut commands,
            entity,
            has_batch,
            cells,
            transfer,
            OpticalMode::Emissive,
        );
        let update_ms = started.elapsed().as_secs_f32() * 1e3;
        *stats = AuroraStats {
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
        diagnostics.add_measurement(&AuroraPlugin::UPDATE_MS, || ms);
    }
}

/// Measures the auroras' totals; nothing in a world without one.
pub(super) fn measure_auroras(
    auroras: Query<(&AuroraStats, Has<CellBatch>), With<Aurora>>,
    mut diagnostics: Diagnostics,
) {
    if auroras.is_empty() {
        return;
    }
    let (drawn, tetrahedra) = totals(
        auroras
            .iter()
            .map(|(stats, has_batch)| (stats.tetrahedra, has_batch)),
    );
    diagnostics.add_measurement(&AuroraPlugin::AURORAS, || drawn);
    diagnostics.add_measurement(&AuroraPlugin::TETRAHEDRA, || tetrahedra);
}
