//! The systems that keep every [`Volume`]'s [`CellBatch`] current: thin glue
//! between Bevy and [`nebel_lod::VolumeBatcher`], which owns the batching
//! itself (full resolution with bricks, the octree C-LOD, or a cell mesh in
//! visibility order) and decides when the view changes the batch.
//!
//! 1. `start_volume_builds`: the source (the grid asset's shared grid or
//!    the cells) and the [`BatchSettings`] (order from the optical mode, the
//!    octree's `C` from [`VolumeLod`], the light field from
//!    [`VolumeLighting`] and the sun in the volume's frame) are compared with
//!    what the batcher was built from; a difference starts a new
//!    [`VolumeBatcher`] on the task pool (padding, light field, hierarchy:
//!    up to a second for the 513 × 65 × 513 layer).
//! 2. `finish_volume_builds`: a finished batcher replaces the old one,
//!    which drew meanwhile; a failure is kept in [`VolumeStatus::Failed`],
//!    logged once for the entity, and not retried until the inputs change.
//! 3. `update_volume_batches`: each visible volume's batcher is updated for
//!    the view of the LOD camera ([`LodCameras`]) and the frame's inputs (the
//!    transfer function, the accuracy `c`); the entity's `CellBatch` is
//!    written only when the batch changed, so the render world uploads only
//!    then. A hidden volume (its [`InheritedVisibility`] false) has no batch
//!    and builds nothing.
//! 4. `measure_volumes`: the `nebel/volume/*` diagnostics.
//!
//! They run in `PostUpdate`, after transform propagation, the camera's
//! projection update and visibility propagation, so a batch is built for the
//! eye of the frame it is drawn in (a batch one frame behind a moving camera
//! is ordered and refined for the wrong eye). The systems that change volumes
//! (campfire, clouds) run in `Update`.

use std::sync::Arc;
use std::time::Instant;

use bevy::diagnostic::Diagnostics;
use bevy::math::DAffine3;
use bevy::prelude::*;
use nebel_core::optics::OpticalMode;
use nebel_lod::{
    BatchLighting, BatchSettings, CellOrder, FrameInputs, Frustum, OctreeSettings, View,
    VolumeBatchError, VolumeBatcher, VolumeSource,
};
use nebel_render::camera::to_double;
use nebel_render::{CellBatch, HeavyBuild, HeavyBuilds, LodCameras};

use crate::grid::VolumeGrid;
use crate::lighting::sun_in_local_frame;
use crate::status::{VolumeError, VolumeStatus};
use crate::volume::{Volume, VolumeField, VolumePlugin};
use crate::{VolumeLighting, VolumeLod};

/// A finished background build: the batcher and how long it took.
type BuiltBatcher = Result<(VolumeBatcher, f64), VolumeBatchError>;

/// What a volume's batcher was built from: its source (by identity) and
/// settings.
#[derive(Clone, Debug, PartialEq)]
struct BuildKey {
    /// The address of the shared grid or cell list.
    source: usize,
    settings: BatchSettings,
}

/// A volume's batcher and the build in flight (internal).
#[derive(Component, Default)]
pub(crate) struct VolumeBatching {
    /// What the batcher (or the failure, or the build in flight) is for.
    key: Option<BuildKey>,
    build: Option<HeavyBuild<BuiltBatcher>>,
    batcher: Option<VolumeBatcher>,
}

#[cfg(test)]
impl VolumeBatching {
    /// No build in flight.
    pub(crate) fn is_idle(&self) -> bool {
        self.build.is_none()
    }
}

/// The source of `volume`, `Ok(None)` while its grid asset loads.
fn source(
    volume: &Volume,
    grids: &Assets<VolumeGrid>,
    asset_server: &AssetServer,
) -> Result<Option<VolumeSource>, VolumeError> {
    match &volume.field {
        VolumeField::Cells(cells) => Ok(Some(VolumeSource::Cells(cells.clone()))),
        VolumeField::Grid(handle) => match grids.get(handle) {
            Some(grid) => Ok(Some(VolumeSource::Grid(grid.0.clone()))),
            None => match asset_server.get_load_state(handle.id()) {
                Some(bevy::asset::LoadState::Failed(error)) => Err(VolumeError::GridNotLoaded {
                    path: handle
                        .path()
                        .map_or_else(|| String::from("(no path)"), ToString::to_string),
                    error,
                }),
                _ => Ok(None),
            },
        },
    }
}

fn source_address(source: &VolumeSource) -> usize {
    match source {
        VolumeSource::Grid(grid) => Arc::as_ptr(grid) as usize,
        VolumeSource::Cells(cells) => Arc::as_ptr(cells) as usize,
    }
}

/// The view-independent settings of a volume's batch.
fn batch_settings(
    volume: &Volume,
    lod: Option<&VolumeLod>,
    lighting: Option<&VolumeLighting>,
    sun_world: Option<Vec3>,
    transform: &GlobalTransform,
) -> BatchSettings {
    BatchSettings {
        order: match volume.mode {
            OpticalMode::Sorted => CellOrder::BackToFront,
            OpticalMode::Emissive | OpticalMode::Mip => CellOrder::Unordered,
        },
        octree: lod.map(|lod| OctreeSettings {
            min_accuracy: lod.min_accuracy,
        }),
        lighting: lighting.map(|lighting| BatchLighting {
            light: lighting
                .light_field_settings(sun_in_local_frame(sun_world, &transform.affine())),
            scalars: lighting.model.cell_scalars(),
        }),
    }
}

/// Starts a batcher build for every visible volume whose source or settings
/// changed (see the module docs).
pub(crate) fn start_volume_builds(
    mut volumes: Query<(
        Entity,
        &Volume,
        &GlobalTransform,
        Option<&VolumeLod>,
        Option<&VolumeLighting>,
        &InheritedVisibility,
        &mut VolumeStatus,
        &mut VolumeBatching,
    )>,
    suns: Query<&GlobalTransform, With<DirectionalLight>>,
    grids: Res<Assets<VolumeGrid>>,
    asset_server: Res<AssetServer>,
) {
    let sun_world = suns.iter().next().map(|sun| sun.back().as_vec3());
    for (entity, volume, transform, lod, lighting, visibility, mut status, mut batching) in
        &mut volumes
    {
        if !visibility.get() {
            continue;
        }
        let source = match source(volume, &grids, &asset_server) {
            Ok(Some(source)) => source,
            Ok(None) => continue,
            Err(error) => {
                status.fail(entity, error);
                continue;
            }
        };
        let key = BuildKey {
            source: source_address(&source),
            settings: batch_settings(volume, lod, lighting, sun_world, transform),
        };
        if batching.key.as_ref() == Some(&key) {
            continue;
        }
        let settings = key.settings;
        batching.key = Some(key);
        batching.build = Some(HeavyBuild::spawn(move || {
            let started = Instant::now();
            VolumeBatcher::new(source, &settings)
                .map(|batcher| (batcher, started.elapsed().as_secs_f64() * 1e3))
        }));
        if batching.batcher.is_none() {
            *status = VolumeStatus::Pending;
        }
    }
}

/// Takes the finished batcher builds (see the module docs).
pub(crate) fn finish_volume_builds(
    mut commands: Commands,
    mode: Res<HeavyBuilds>,
    mut volumes: Query<(Entity, &mut VolumeStatus, &mut VolumeBatching)>,
    mut diagnostics: Diagnostics,
) {
    for (entity, mut status, mut batching) in &mut volumes {
        let Some(result) = batching.build.as_mut().and_then(|build| build.poll(*mode)) else {
            continue;
        };
        batching.build = None;
        match result {
            Ok((batcher, build_ms)) => {
                diagnostics.add_measurement(&VolumePlugin::BUILD_MS, || build_ms);
                batching.batcher = Some(batcher);
                *status = VolumeStatus::Ready;
            }
            Err(error) => {
                batching.batcher = None;
                commands.entity(entity).remove::<CellBatch>();
                status.fail(entity, error.into());
            }
        }
    }
}

/// The world-from-local map of `transform` in f64.
fn world_from_local(transform: &GlobalTransform) -> DAffine3 {
    DAffine3::from_mat4(to_double(transform.to_matrix()))
}

/// Updates every visible volume's batch for this frame's view and writes it
/// when it changed (see the module docs).
pub(crate) fn update_volume_batches(
    mut commands: Commands,
    cameras: LodCameras,
    mut volumes: Query<(
        Entity,
        &Volume,
        &GlobalTransform,
        Option<&VolumeLod>,
        Option<&VolumeLighting>,
        &InheritedVisibility,
        Has<CellBatch>,
        &mut VolumeStatus,
        &mut VolumeBatching,
    )>,
    suns: Query<&GlobalTransform, With<DirectionalLight>>,
    mut diagnostics: Diagnostics,
) {
    let Some(camera) = cameras.view() else {
        return;
    };
    // A degenerate projection culls nothing rather than everything.
    let frustum = Frustum::from_view_projection(camera.clip_from_world).ok();
    let sun_world = suns.iter().next().map(|sun| sun.back().as_vec3());
    let started = Instant::now();
    let mut rebuilt = false;
    for (entity, volume, transform, lod, lighting, visibility, drawn, mut status, mut batching) in
        &mut volumes
    {
        if !visibility.get() {
            if drawn {
                // Hidden: nothing to upload or draw.
                commands.entity(entity).remove::<CellBatch>();
            }
            continue;
        }
        let Some(batcher) = batching.batcher.as_mut() else {
            continue;
        };
        let mut view = View::new(world_from_local(transform), camera.eye, camera.viewport);
        view.frustum = frustum.clone();
        let inputs = FrameInputs {
            transfer: &volume.transfer_function,
            accuracy: lod.map_or(0.0, |lod| lod.accuracy),
        };
        match batcher.update(&view, &inputs) {
            Ok(false) if drawn => {}
            Ok(_) => {
                rebuilt = true;
                let mut batch = CellBatch::new(
                    batcher.batch().clone(),
                    volume.transfer_function.clone(),
                    volume.mode,
                );
                batch.scattering = lighting
                    .and_then(|lighting| lighting.cell_scattering(sun_world.unwrap_or(Vec3::Y)));
                commands.entity(entity).insert(batch);
                if matches!(*status, VolumeStatus::Failed(_)) {
                    *status = VolumeStatus::Ready;
                }
            }
            Err(error) => status.fail(entity, error.into()),
        }
    }
    if rebuilt {
        let ms = started.elapsed().as_secs_f64() * 1e3;
        diagnostics.add_measurement(&VolumePlugin::UPDATE_MS, || ms);
    }
}

/// Measures the volumes' totals; nothing in a world without a volume.
pub(crate) fn measure_volumes(
    volumes: Query<(&VolumeBatching, Option<&CellBatch>), With<Volume>>,
    mut diagnostics: Diagnostics,
) {
    if volumes.is_empty() {
        return;
    }
    let (mut drawn, mut full) = (0, 0);
    for (batching, batch) in &volumes {
        drawn += batch.map_or(0, |batch| batch.cells.len());
        full += batching
            .batcher
            .as_ref()
            .map_or(0, VolumeBatcher::full_resolution_cells);
    }
    let count = volumes.iter().len();
    diagnostics.add_measurement(&VolumePlugin::VOLUMES, || count as f64);
    diagnostics.add_measurement(&VolumePlugin::CELLS_DRAWN, || drawn as f64);
    diagnostics.add_measurement(&VolumePlugin::CELLS_FULL_RESOLUTION, || full as f64);
}
