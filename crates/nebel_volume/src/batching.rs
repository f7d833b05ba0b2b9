//! The systems that keep every [`Volume`]'s [`CellBatch`] current: glue
//! between Bevy and [`nebel_lod::VolumeBatching`], which owns the batching
//! (the batcher, its builds on the task pool, an animated volume's keyframes
//! and the refinements made ahead).
//!
//! 1. `build_batchers` hands each volume's batching the frame's source (the
//!    grid asset's shared grid, the cells, or none while the asset loads or
//!    a cloud's generator runs), its [`BatchSettings`] (the order from the
//!    optical mode, the octree's `C` from [`VolumeLod`], the light field
//!    from [`VolumeLighting`] and the sun in the volume's frame) and, for a
//!    windy [`CloudVolume`], its wind.
//! 2. `update_batches` updates each visible volume's batch for the view of
//!    the LOD camera ([`LodCameras`]) under its transfer function and the
//!    criterion of [`VolumeLod`] scaled by the quality preset, and writes the
//!    entity's `CellBatch` only when the batch, the optical mode or the
//!    scattering changed, so the render world uploads only then; a keyframe
//!    pair's `CellBlend` and a lit volume's `CellSunlight` are written when
//!    they change.
//! 3. `report_status` derives [`VolumeStatus`] from the stages' failures (the
//!    generator's, the grid asset's, the batching's) and logs a failure once
//!    per entity when it appears.
//! 4. `measure_volumes`: the `nebel/volume/*` diagnostics.
//!
//! A hidden volume (its [`InheritedVisibility`] false) has no batch and
//! builds nothing. The systems run in `PostUpdate`, after transform
//! propagation, the camera's projection update and visibility propagation, so
//! a refinement starts from the eye of the frame (under
//! [`HeavyBuilds::Blocking`] it is drawn in that frame). The systems that
//! change volumes (campfire, clouds) run in `Update`.

use std::sync::Arc;
use std::time::Instant;

use bevy::diagnostic::Diagnostics;
use bevy::prelude::*;
use nebel_core::optics::OpticalMode;
use nebel_lod::{
    AnimatedGrid, BatchLighting, BatchSettings, BuildRequest, CellOrder, Frustum, GridDrawing,
    OctreeSettings, View, VolumeSource,
};
use nebel_render::camera::to_double_affine;
use nebel_render::{CellBatch, CellBlend, CellSunlight, EffectiveQuality, HeavyBuilds, LodCameras};

use crate::cloud::{CloudGeneration, CloudVolume, animates};
use crate::grid::VolumeGrid;
use crate::lighting::in_local_frame;
use crate::status::{VolumeError, VolumeStatus};
use crate::volume::{ProjectedCells, Volume, VolumeField, VolumePlugin};
use crate::{LodCriterion, VolumeLighting, VolumeLod};

/// A volume's batching and the state of its source (internal).
#[derive(Component, Default)]
pub(crate) struct VolumeBatching {
    batching: nebel_lod::VolumeBatching<HeavyBuilds>,
    /// The grid asset is loading.
    loading: bool,
    /// Why the grid asset is unusable.
    source_failure: Option<VolumeError>,
}

impl VolumeBatching {
    /// No build in flight.
    #[cfg(test)]
    pub(crate) fn is_idle(&self) -> bool {
        self.batching.is_idle()
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

/// The view-independent settings of a volume's batch.
fn batch_settings(
    volume: &Volume,
    lod: Option<&VolumeLod>,
    lighting: Option<&VolumeLighting>,
    sun_world: Option<Vec3>,
    transform: &GlobalTransform,
    projected: bool,
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
            light: lighting.light_field_settings(
                in_local_frame(sun_world, &transform.affine()),
                in_local_frame(Some(Vec3::Y), &transform.affine()),
            ),
            scalars: lighting.model.cell_scalars(),
        }),
        drawing: if projected {
            GridDrawing::ProjectedCells
        } else {
            GridDrawing::RayCast
        },
    }
}

/// Hands every volume's batching the frame's source and settings: it takes
/// finished builds and starts new ones, and advances the keyframes of
/// animated volumes (see the module docs).
pub(crate) fn build_batchers(
    mut volumes: Query<(
        &Volume,
        &GlobalTransform,
        Option<&VolumeLod>,
        Option<&VolumeLighting>,
        &InheritedVisibility,
        Option<(&CloudVolume, &CloudGeneration)>,
        Has<ProjectedCells>,
        &mut VolumeBatching,
    )>,
    suns: Query<&GlobalTransform, With<DirectionalLight>>,
    grids: Res<Assets<VolumeGrid>>,
    asset_server: Res<AssetServer>,
    mode: Res<HeavyBuilds>,
    time: Res<Time>,
    mut diagnostics: Diagnostics,
) {
    let sun_world = suns.iter().next().map(|sun| sun.back().as_vec3());
    for (volume, transform, lod, lighting, visibility, cloud, projected, mut batching) in
        &mut volumes
    {
        // A cloud's field is its generator's to fill first.
        let awaiting_grid = cloud.is_some_and(|(_, generation)| !generation.has_grid());
        let source = if awaiting_grid {
            Ok(None)
        } else {
            source(volume, &grids, &asset_server)
        };
        batching.loading = !awaiting_grid && matches!(source, Ok(None));
        batching.source_failure = source.as_ref().err().cloned();
        let animation = cloud
            .filter(|(cloud, generation)| animates(cloud) && generation.weather_is_ready())
            .and_then(|(cloud, generation)| {
                let field: Arc<dyn AnimatedGrid> = generation.animation.clone()?;
                Some((field, cloud.keyframe_interval))
            });
        let request = BuildRequest {
            now: time.elapsed_secs_f64(),
            visible: visibility.get(),
            source: source.ok().flatten(),
            settings: batch_settings(volume, lod, lighting, sun_world, transform, projected),
            sun_keyframe_interval: lighting.map(|lighting| lighting.keyframe_interval),
            animation,
        };
        let landed = batching.batching.build(*mode, request);
        if let Some(ms) = landed.batcher_ms {
            diagnostics.add_measurement(&VolumePlugin::BUILD_MS, || ms);
        }
        if let Some(ms) = landed.keyframes_ms {
            diagnostics.add_measurement(&VolumePlugin::KEYFRAME_MS, || ms);
        }
    }
}

/// Updates every visible volume's batch for this frame's view and writes it
/// when it changed (see the module docs).
pub(crate) fn update_batches(
    mut commands: Commands,
    cameras: LodCameras,
    mut volumes: Query<(
        Entity,
        &Volume,
        &GlobalTransform,
        Option<&VolumeLod>,
        Option<&VolumeLighting>,
        &InheritedVisibility,
        Option<&CellBatch>,
        (Option<&CellBlend>, Option<&CellSunlight>),
        &mut VolumeBatching,
    )>,
    suns: Query<(&GlobalTransform, &DirectionalLight)>,
    ambient: Option<Res<GlobalAmbientLight>>,
    quality: Option<Res<EffectiveQuality>>,
    mode: Res<HeavyBuilds>,
    mut diagnostics: Diagnostics,
) {
    let camera = cameras.view();
    let accuracy_scale = quality.map_or(1.0, |quality| quality.volume_accuracy_scale());
    // A degenerate projection culls nothing rather than everything.
    let frustum =
        camera.and_then(|camera| Frustum::from_view_projection(camera.clip_from_world).ok());
    let sun = suns.iter().next();
    let sun_world = sun.map(|(transform, _)| transform.back().as_vec3());
    let sun_shadows = sun.is_some_and(|(_, light)| light.shadow_maps_enabled);
    // The sky's colour tints the ambient light of single scattering.
    let sky = ambient.map_or(Vec3::ONE, |ambient| ambient.color.to_linear().to_vec3());
    let sunlight = CellSunlight {
        colour: sun.map_or(Vec3::ONE, |(_, light)| sunlight(light)),
    };
    let started = Instant::now();
    let mut rebuilt = false;
    for (entity, volume, transform, lod, lighting, visibility, drawn, parameters, mut batching) in
        &mut volumes
    {
        let batching = &mut batching.batching;
        if !visibility.get() || batching.drawn().is_none() {
            if drawn.is_some() {
                // Hidden or failed: nothing to upload or draw.
                commands
                    .entity(entity)
                    .remove::<(CellBatch, CellBlend, CellSunlight)>();
            }
            continue;
        }
        let view = camera.map(|camera| View {
            frustum: frustum.clone(),
            clip_from_world: Some(camera.clip_from_world),
            ..View::new(to_double_affine(transform), camera.eye, camera.viewport)
        });
        // Read by the octree alone, which every volume with a `VolumeLod` has.
        let criterion = lod.map_or_else(LodCriterion::default, |lod| {
            lod.criterion.scaled(accuracy_scale)
        });
        let Some(frame) =
            batching.update(*mode, view.as_ref(), &volume.transfer_function, criterion)
        else {
            continue;
        };
        let (drawn_blend, drawn_sunlight) = parameters;
        write_if_changed(
            &mut commands,
            entity,
            lighting.map(|_| sunlight),
            drawn_sunlight,
        );
        let blend = frame.blend.map(|factor| CellBlend { factor });
        write_if_changed(&mut commands, entity, blend, drawn_blend);
        let scattering = lighting.and_then(|lighting| {
            lighting.cell_scattering(sun_world.unwrap_or(Vec3::Y), sky, sun_shadows)
        });
        let current = drawn.is_some_and(|batch| {
            batch.mode == volume.mode
                && batch.scattering == scattering
                && batch.light_response.checked() == volume.light_response.checked()
                && batch
                    .transfer_function
                    .as_ref()
                    .is_some_and(|tf| Arc::ptr_eq(tf, &volume.transfer_function))
        });
        if frame.changed || !current {
            rebuilt = true;
            let mut batch =
                CellBatch::new(frame.cells, volume.transfer_function.clone(), volume.mode);
            batch.scattering = scattering;
            batch.light_response = volume.light_response;
            commands.entity(entity).insert(batch);
        }
    }
    if rebuilt {
        let ms = started.elapsed().as_secs_f64() * 1e3;
        diagnostics.add_measurement(&VolumePlugin::UPDATE_MS, || ms);
    }
}

/// Inserts `wanted` on `entity` where it differs from the `drawn` component,
/// and removes the component where none is wanted, so that the render world
/// sees a change only when there is one.
fn write_if_changed<C: Component + PartialEq>(
    commands: &mut Commands,
    entity: Entity,
    wanted: Option<C>,
    drawn: Option<&C>,
) {
    match (wanted, drawn) {
        (Some(wanted), drawn) if drawn != Some(&wanted) => {
            commands.entity(entity).insert(wanted);
        }
        (None, Some(_)) => {
            commands.entity(entity).remove::<C>();
        }
        _ => {}
    }
}

/// The factor a lit volume's colours take under `sun`: its colour (linear)
/// times its illuminance over the default `DirectionalLight`'s, the strength
/// the transfer functions' colours are made for.
fn sunlight(sun: &DirectionalLight) -> Vec3 {
    let reference = DirectionalLight::default().illuminance;
    let linear = sun.color.to_linear();
    Vec3::new(linear.red, linear.green, linear.blue) * (sun.illuminance / reference)
}

/// Derives every volume's [`VolumeStatus`] from its stages and logs a new
/// failure once (see the module docs).
pub(crate) fn report_status(
    mut volumes: Query<(
        Entity,
        &VolumeBatching,
        Option<&CloudGeneration>,
        &mut VolumeStatus,
    )>,
) {
    for (entity, volume_batching, generation, mut status) in &mut volumes {
        let batching = &volume_batching.batching;
        let failure = generation
            .and_then(CloudGeneration::failure)
            .or(volume_batching.source_failure.as_ref())
            .cloned()
            .or_else(|| batching.failure().cloned().map(VolumeError::from));
        let pending = !batching.draws_keyframes()
            && (!batching.has_batcher()
                || volume_batching.loading
                || (!batching.is_animated()
                    && generation.is_some_and(|generation| !generation.has_grid())));
        match failure {
            Some(error) => {
                VolumeStatus::fail(status.reborrow(), "volume", entity, error);
            }
            None if pending => {
                status.set_if_neq(VolumeStatus::Pending);
            }
            None => {
                status.set_if_neq(VolumeStatus::Ready);
            }
        }
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
            .batching
            .drawn()
            .map_or(0, nebel_lod::VolumeBatcher::full_resolution_cells);
    }
    let count = volumes.iter().len();
    diagnostics.add_measurement(&VolumePlugin::VOLUMES, || count as f64);
    diagnostics.add_measurement(&VolumePlugin::CELLS_DRAWN, || drawn as f64);
    diagnostics.add_measurement(&VolumePlugin::CELLS_FULL_RESOLUTION, || full as f64);
}
