//! The systems that keep every [`Volume`]'s [`CellBatch`] current: thin glue
//! between Bevy and [`nebel_lod::VolumeBatcher`], which owns the batching
//! itself (full resolution with bricks, the octree C-LOD, or a cell mesh in
//! visibility order) and decides when the view changes the batch.
//!
//! 1. `build_batchers`: the source (the grid asset's shared grid or the
//!    cells) and the [`BatchSettings`] (order from the optical mode, the
//!    octree's `C` from [`VolumeLod`], the light field from
//!    [`VolumeLighting`] and the sun in the volume's frame) are compared with
//!    what the batcher was built from; a difference starts a new
//!    [`VolumeBatcher`] on the task pool (padding, light field, hierarchy:
//!    up to a second for the 513 × 65 × 513 layer). One build runs per volume
//!    at a time: inputs that change while it runs (a fire's grid every
//!    frame, a moving sun) are built next, from their latest state, so every
//!    build lands. A finished batcher replaces the old one, which drew
//!    meanwhile.
//! 2. `update_batches`: each visible volume's batcher is updated for the view
//!    of the LOD camera ([`LodCameras`]) and the frame's inputs (the transfer
//!    function, the criterion of [`VolumeLod`] scaled by the quality preset);
//!    the entity's `CellBatch` is written only
//!    when the batch, the optical mode or the scattering changed, so the
//!    render world uploads only then. An octree's refinement (the camera
//!    moved, the criterion or the transfer function changed) is made on the
//!    task pool (`VolumeBatcher::refinement_step`) while the last batch is
//!    drawn, and taken in the first frame after it is done, even if the
//!    camera has moved on meanwhile; the next starts from the newest view.
//!    A windy cloud or a volume under a moving sun is drawn from its
//!    keyframe track (`crate::keyframes`), with its `CellBlend` and, lit, its
//!    `CellSunlight` written when they change; a still camera's refinement
//!    step for the track's advancing blend and the next pair's first batch
//!    (`VolumeBatcher::first_build`) are made ahead on the task pool too, and
//!    so is the first pair's first batch while the volume's own batch (or
//!    nothing) is drawn: the track draws a pair, and hands over to the next,
//!    once its batch is made, so that no frame builds one. The other kinds
//!    (a grid at full resolution, a cell mesh) rebuild on the frame.
//! 3. `report_status` derives [`VolumeStatus`] from the stages' failures (the
//!    generator's, the grid asset's, the build's, the last update's, in that
//!    order) and logs a failure once per entity when it appears; a failed
//!    build is not retried until its inputs change.
//! 4. `measure_volumes`: the `nebel/volume/*` diagnostics.
//!
//! A hidden volume (its [`InheritedVisibility`] false) has no batch and
//! builds nothing. The systems run in `PostUpdate`, after transform
//! propagation, the camera's projection update and visibility propagation, so
//! a refinement starts from the eye of the frame (under
//! [`HeavyBuilds::Blocking`] it is drawn in that frame). In the background an
//! octree batch is drawn a build or two after the eye it was refined and
//! ordered for: its order stays a visibility order while the eye keeps to the
//! same side of every face's plane between cells, and only rays across a
//! face whose plane the eye crossed composite two cells out of order
//! (`nebel_lod`'s octree tests measure the image cost of an order a frame
//! old). The systems that change volumes (campfire, clouds) run in `Update`.

use std::sync::Arc;
use std::time::Instant;

use bevy::diagnostic::Diagnostics;
use bevy::math::DVec3;
use bevy::prelude::*;
use nebel_core::optics::OpticalMode;
use nebel_lod::octree::keyframe::REFINEMENT_SPAN;
use nebel_lod::{
    BatchLighting, BatchSettings, BuiltRefinementStep, CellOrder, FrameInputs, Frustum,
    OctreeSettings, View, VolumeBatchError, VolumeBatcher, VolumeSource,
};
use nebel_render::camera::to_double_affine;
use nebel_render::{
    CellBatch, CellBlend, CellSunlight, EffectiveQuality, HeavyBuild, HeavyBuilds, LodCameras,
    free_in_background,
};

use crate::cloud::{CloudGeneration, CloudVolume};
use crate::grid::VolumeGrid;
use crate::keyframes::{KeyframeRecipe, KeyframeSource, KeyframeTrack, SunMotion, is_windy};
use crate::lighting::sun_in_local_frame;
use crate::status::{VolumeError, VolumeStatus};
use crate::volume::{Volume, VolumeField, VolumePlugin};
use crate::{LodCriterion, VolumeLighting, VolumeLod};

/// A finished background build: the batcher and how long it took.
type BuiltBatcher = Result<(VolumeBatcher, f64), VolumeBatchError>;

/// What a batcher is built from: its source (the shared grid or cells,
/// compared by identity) and settings (compared bit for bit, so a NaN
/// setting equals itself and is not rebuilt every frame).
#[derive(Clone, Debug)]
struct BuildKey {
    source: VolumeSource,
    settings: BatchSettings,
}

impl BuildKey {
    fn same_as(&self, other: &Self) -> bool {
        let source = match (&self.source, &other.source) {
            (VolumeSource::Grid(a), VolumeSource::Grid(b)) => Arc::ptr_eq(a, b),
            (VolumeSource::Cells(a), VolumeSource::Cells(b)) => Arc::ptr_eq(a, b),
            _ => false,
        };
        source && settings_bits(&self.settings) == settings_bits(&other.settings)
    }
}

/// The bits of every value of `settings` (0 for the parts it lacks, with a
/// flag for each part).
pub(crate) fn settings_bits(settings: &BatchSettings) -> [u64; 12] {
    let octree = settings.octree.map(|octree| octree.min_accuracy.to_bits());
    let mut bits = [0; 12];
    bits[0] = u64::from(settings.order == CellOrder::BackToFront);
    bits[1] = u64::from(octree.is_some());
    bits[2] = octree.unwrap_or(0);
    if let Some(BatchLighting { light, scalars }) = settings.lighting {
        bits[3] = 1;
        bits[4] = u64::from(light.ambient.to_bits());
        bits[5] = u64::from(light.diffuse.to_bits());
        bits[6] = u64::from(light.shadow_extinction.to_bits());
        bits[7] = u64::from(light.lambert);
        bits[8] = scalars as u64;
        bits[9..].copy_from_slice(&light.sun_direction.to_array().map(f64::to_bits));
    }
    bits
}

/// A volume's batcher, the build in flight and the failures of its stages
/// (internal).
#[derive(Component, Default)]
pub(crate) struct VolumeBatching {
    /// A windy cloud's keyframes, drawn instead of `batcher`.
    keyframes: Option<KeyframeTrack>,
    /// Why the keyframe track's last build failed.
    keyframe_failure: Option<VolumeError>,
    /// The sun in the volume's frame at the last frame, and that frame's
    /// time.
    last_sun: Option<(DVec3, f64)>,
    /// When the sun last moved.
    sun_moved_at: Option<f64>,
    /// The keyframe pair (its first keyframe's index) the last batch
    /// written came from; `None`: the volume's own batcher.
    wrote_pair: Option<i64>,
    /// The octree's refinement in flight: for the frame's view and inputs
    /// when the drawn batch is older, or a still camera's next step of the
    /// keyframes' advancing blend, made ahead.
    refinement_step: Option<HeavyBuild<BuiltRefinementStep>>,
    /// A finished refinement waiting for the blend to reach it.
    ready_step: Option<BuiltRefinementStep>,
    /// The next keyframe pair's first batch, made ahead, in flight.
    next_pair_batch: Option<HeavyBuild<BuiltRefinementStep>>,
    /// The first keyframe pair's first batch, made while the volume's own
    /// batch (or nothing) is drawn, in flight.
    first_pair_batch: Option<HeavyBuild<BuiltRefinementStep>>,
    /// What the batcher was built from.
    built: Option<BuildKey>,
    /// The build in flight and what it builds from.
    build: Option<(BuildKey, HeavyBuild<BuiltBatcher>)>,
    /// What the last failed build was built from: not retried until the
    /// inputs differ.
    failed: Option<BuildKey>,
    batcher: Option<VolumeBatcher>,
    /// The grid asset is loading.
    loading: bool,
    /// Why the grid asset is unusable.
    source_failure: Option<VolumeError>,
    /// Why the last build failed.
    build_failure: Option<VolumeError>,
    /// Why the last update failed.
    update_failure: Option<VolumeError>,
}

impl VolumeBatching {
    /// The batcher drawn: the keyframe track's pair when it has one.
    fn drawn(&self) -> Option<&VolumeBatcher> {
        self.keyframes
            .as_ref()
            .and_then(KeyframeTrack::batcher)
            .or(self.batcher.as_ref())
    }

    /// Whether the keyframe track's pair is drawn: once it has a batch.
    fn draws_keyframes(&self) -> bool {
        self.keyframes
            .as_ref()
            .and_then(KeyframeTrack::batcher)
            .is_some_and(VolumeBatcher::is_built)
    }

    /// No build in flight.
    #[cfg(test)]
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

/// Takes finished batcher builds and starts new ones, and advances the
/// keyframe tracks of windy clouds (see the module docs).
pub(crate) fn build_batchers(
    mut volumes: Query<(
        &Volume,
        &GlobalTransform,
        Option<&VolumeLod>,
        Option<&VolumeLighting>,
        &InheritedVisibility,
        Option<(&CloudVolume, &CloudGeneration)>,
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
    let now = time.elapsed_secs_f64();
    for (volume, transform, lod, lighting, visibility, cloud, mut batching) in &mut volumes {
        let batching = &mut *batching;
        let sun = observe_sun(batching, lighting, sun_world, transform, now);
        let windy = cloud
            .map(|(cloud, _)| cloud)
            .filter(|cloud| is_windy(cloud));
        // A windy cloud, or a lit grid whose sun moved lately, is drawn
        // from keyframes (see crate::keyframes).
        let keyframed = match (windy, lighting) {
            (Some(cloud), _) => Some((
                KeyframeSource::Cloud(cloud.clone()),
                cloud.keyframe_interval,
            )),
            (None, Some(lighting)) => {
                let interval = f64::from(lighting.keyframe_interval).max(1e-3);
                let moving = batching
                    .sun_moved_at
                    .is_some_and(|moved| now - moved <= 2.0 * interval);
                match moving.then(|| source(volume, &grids, &asset_server)) {
                    Some(Ok(Some(VolumeSource::Grid(grid)))) => {
                        Some((KeyframeSource::Grid(grid), lighting.keyframe_interval))
                    }
                    _ => None,
                }
            }
            (None, None) => None,
        };
        if let Some((source, interval)) = keyframed {
            if visibility.get() {
                let recipe = KeyframeRecipe {
                    source,
                    settings: batch_settings(volume, lod, lighting, sun_world, transform),
                    interval,
                };
                advance_keyframes(batching, recipe, sun, &time, *mode, &mut diagnostics);
            }
            continue;
        }
        batching.keyframe_failure = None;
        let generation = cloud.map(|(_, generation)| generation);
        // A build started last frame may be done (always under Blocking).
        finish_build(batching, *mode, &mut diagnostics);
        // A cloud's field is its generator's to fill first.
        let awaiting_grid = generation.is_some_and(|generation| !generation.has_grid());
        if !visibility.get() || batching.build.is_some() || awaiting_grid {
            continue;
        }
        let source = match source(volume, &grids, &asset_server) {
            Ok(source) => {
                batching.source_failure = None;
                source
            }
            Err(error) => {
                batching.source_failure = Some(error);
                None
            }
        };
        batching.loading = source.is_none() && batching.source_failure.is_none();
        let Some(source) = source else {
            continue;
        };
        let key = BuildKey {
            source,
            settings: batch_settings(volume, lod, lighting, sun_world, transform),
        };
        let unchanged = |last: &Option<BuildKey>| last.as_ref().is_some_and(|k| k.same_as(&key));
        if unchanged(&batching.built) {
            // Built for the volume as it is: the keyframes are done with.
            if let Some(track) = batching.keyframes.take() {
                free_in_background(track);
            }
            continue;
        }
        if unchanged(&batching.failed) {
            continue;
        }
        let (source, settings) = (key.source.clone(), key.settings);
        let build = HeavyBuild::spawn(move || {
            let started = Instant::now();
            VolumeBatcher::new(source, &settings)
                .map(|batcher| (batcher, started.elapsed().as_secs_f64() * 1e3))
        });
        batching.build = Some((key, build));
        finish_build(batching, *mode, &mut diagnostics);
    }
}

/// The sun's motion in a lit volume's frame from its last frame to this one
/// (`now`), noting when it last moved; a still sun straight up for an unlit
/// volume.
fn observe_sun(
    batching: &mut VolumeBatching,
    lighting: Option<&VolumeLighting>,
    sun_world: Option<Vec3>,
    transform: &GlobalTransform,
    now: f64,
) -> SunMotion {
    if lighting.is_none() {
        return SunMotion::still(DVec3::Y, now);
    }
    let direction = sun_in_local_frame(sun_world, &transform.affine()).as_dvec3();
    let motion = match batching.last_sun {
        Some((last, last_time)) => SunMotion::between(last, last_time, direction, now),
        None => SunMotion::still(direction, now),
    };
    if batching.last_sun.is_some_and(|(last, _)| last != direction) {
        batching.sun_moved_at = Some(now);
    }
    batching.last_sun = Some((direction, now));
    motion
}

/// Starts the keyframe track of `recipe` unless it runs already (a new
/// recipe starts over), lights it by `sun` and advances it by the frame's
/// time.
fn advance_keyframes(
    batching: &mut VolumeBatching,
    recipe: KeyframeRecipe,
    sun: SunMotion,
    time: &Time,
    mode: HeavyBuilds,
    diagnostics: &mut Diagnostics,
) {
    if !batching
        .keyframes
        .as_ref()
        .is_some_and(|track| track.is_for(&recipe))
    {
        batching.keyframes = Some(KeyframeTrack::new(
            recipe,
            sun,
            time.elapsed_secs_f64(),
            mode,
        ));
        batching.keyframe_failure = None;
    }
    let track = batching.keyframes.as_mut().expect("started above");
    track.set_sun(sun);
    // The next pair takes over once its first batch is made (`make_ahead`).
    match track.advance(time.elapsed_secs_f64(), mode, VolumeBatcher::is_built) {
        Ok(built_ms) => {
            if let Some(ms) = built_ms {
                diagnostics.add_measurement(&VolumePlugin::KEYFRAME_MS, || ms);
            }
        }
        Err(error) => batching.keyframe_failure = Some(error.into()),
    }
}

/// Takes the build in flight if it is done (waiting for it under
/// [`HeavyBuilds::Blocking`]).
fn finish_build(batching: &mut VolumeBatching, mode: HeavyBuilds, diagnostics: &mut Diagnostics) {
    let Some((key, build)) = batching.build.as_mut() else {
        return;
    };
    let Some(result) = build.poll(mode) else {
        return;
    };
    let key = key.clone();
    batching.build = None;
    match result {
        Ok((batcher, build_ms)) => {
            diagnostics.add_measurement(&VolumePlugin::BUILD_MS, || build_ms);
            if let Some(old) = batching.batcher.replace(batcher) {
                free_in_background(old);
            }
            batching.built = Some(key);
            batching.failed = None;
            batching.build_failure = None;
            batching.update_failure = None;
        }
        Err(error) => {
            if let Some(old) = batching.batcher.take() {
                free_in_background(old);
            }
            batching.built = None;
            batching.failed = Some(key);
            batching.build_failure = Some(error.into());
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
    let sunlight = CellSunlight {
        colour: sun.map_or(Vec3::ONE, |(_, light)| sunlight(light)),
    };
    let started = Instant::now();
    let mut rebuilt = false;
    for (entity, volume, transform, lod, lighting, visibility, drawn, parameters, mut batching) in
        &mut volumes
    {
        if !visibility.get() || batching.drawn().is_none() {
            if drawn.is_some() {
                // Hidden or failed: nothing to upload or draw.
                commands
                    .entity(entity)
                    .remove::<(CellBatch, CellBlend, CellSunlight)>();
            }
            continue;
        }
        let batching = &mut *batching;
        let view = camera.map(|camera| View {
            frustum: frustum.clone(),
            clip_from_world: Some(camera.clip_from_world),
            ..View::new(to_double_affine(transform), camera.eye, camera.viewport)
        });
        // Read by the octree alone, which every volume with a `VolumeLod` has.
        let criterion = lod.map_or_else(LodCriterion::default, |lod| {
            lod.criterion.scaled(accuracy_scale)
        });
        // The first pair's first batch is made on the task pool while the
        // volume's own batch, if any, is drawn.
        if let (Some(view), Some(track)) = (&view, batching.keyframes.as_mut()) {
            let first = FrameInputs {
                transfer: &volume.transfer_function,
                criterion,
                blend: track.refinement_blend(),
                blend_span: REFINEMENT_SPAN,
            };
            if let Err(error) = make_ahead(
                track.batcher_mut().filter(|pair| !pair.is_built()),
                &mut batching.first_pair_batch,
                view,
                &first,
                *mode,
            ) {
                batching.update_failure = Some(error.into());
            }
        }
        // The keyframes once their first pair has a batch, the volume's own
        // batcher until then and after.
        let from_keyframes = batching.draws_keyframes();
        let pair = batching
            .keyframes
            .as_ref()
            .and_then(KeyframeTrack::pair_index)
            .filter(|_| from_keyframes);
        // A new pair (or the switch to or from the keyframes) writes its
        // batch even when it was made ahead for this very view.
        let switched = pair != batching.wrote_pair;
        let blend = batching
            .keyframes
            .as_ref()
            .filter(|_| from_keyframes)
            .map(|track| (track.blend(), track.refinement_blend()));
        let batcher = match &mut batching.keyframes {
            Some(track) if from_keyframes => track.batcher_mut(),
            _ => batching.batcher.as_mut(),
        };
        let (Some(view), Some(batcher)) = (view, batcher) else {
            continue;
        };
        // The sunlight, written when it changes.
        let (drawn_blend, drawn_sunlight) = parameters;
        write_if_changed(
            &mut commands,
            entity,
            lighting.map(|_| sunlight),
            drawn_sunlight,
        );
        let inputs = FrameInputs {
            transfer: &volume.transfer_function,
            criterion,
            blend: blend.map_or(0.0, |(_, refined_for)| refined_for),
            blend_span: blend.map_or(0.0, |_| REFINEMENT_SPAN),
        };
        let scattering =
            lighting.and_then(|lighting| lighting.cell_scattering(sun_world.unwrap_or(Vec3::Y)));
        // A still camera's refinement steps for the advancing blend run on
        // the task pool while the current batch is drawn, each made ahead
        // and taking over when the blend reaches it.
        let step = StepInputs {
            view: &view,
            inputs: &inputs,
            next: blend.map(|_| FrameInputs {
                blend: inputs.blend + REFINEMENT_SPAN,
                ..inputs
            }),
        };
        let updated = step_batch(
            batcher,
            &mut batching.refinement_step,
            &mut batching.ready_step,
            &step,
            *mode,
        );
        // While the next step's batch is being made, the clock waits at the
        // end of the drawn one's span.
        let hold = step.next.filter(|next| {
            next.blend < 1.0
                && batching.refinement_step.is_some()
                && batcher.is_built_for(&view, &inputs)
        });
        // The blend as the mix of the drawn batch's two ends.
        let mix = blend.map(|(blend, _)| CellBlend {
            factor: batcher.batch().mix_factor(blend.factor),
        });
        let hold = hold.map(|next| next.blend);
        write_if_changed(&mut commands, entity, mix, drawn_blend);
        match updated {
            Ok(changed) => {
                batching.update_failure = None;
                let current = drawn.is_some_and(|batch| {
                    batch.mode == volume.mode
                        && batch.scattering == scattering
                        && batch
                            .transfer_function
                            .as_ref()
                            .is_some_and(|tf| Arc::ptr_eq(tf, &volume.transfer_function))
                });
                if changed || !current || switched {
                    batching.wrote_pair = pair;
                    rebuilt = true;
                    let mut batch = CellBatch::new(
                        batcher.batch().clone(),
                        volume.transfer_function.clone(),
                        volume.mode,
                    );
                    batch.scattering = scattering;
                    commands.entity(entity).insert(batch);
                }
            }
            Err(error) => batching.update_failure = Some(error.into()),
        }
        if let Some(track) = batching.keyframes.as_mut().filter(|_| from_keyframes) {
            track.hold_at(hold);
            let next = FrameInputs {
                blend: 0.0,
                ..inputs
            };
            if let Err(error) = make_ahead(
                track.next_batcher_mut(),
                &mut batching.next_pair_batch,
                &view,
                &next,
                *mode,
            ) {
                batching.update_failure = Some(error.into());
            }
        }
    }
    if rebuilt {
        let ms = started.elapsed().as_secs_f64() * 1e3;
        diagnostics.add_measurement(&VolumePlugin::UPDATE_MS, || ms);
    }
}

/// The view and inputs of a frame's batch, and for a keyframe pair those of
/// the next refinement step.
struct StepInputs<'a> {
    view: &'a View,
    inputs: &'a FrameInputs<'a>,
    next: Option<FrameInputs<'a>>,
}

/// Brings `batcher`'s batch up to date for the frame (`step`); returns
/// whether it changed. An octree's refinement is made on the task pool
/// (`in_flight`) while the current batch is drawn: for this frame's view and
/// inputs when the batch is older, else, for a keyframe pair under a still
/// camera, the next step ahead. A finished one (`ready`) is taken when it is
/// for this frame's inputs, also when the camera has moved on since it was
/// started (it is newer than the drawn batch; the next starts from the
/// current view), or, made ahead, once the blend reaches it. The other kinds
/// rebuild at once.
fn step_batch(
    batcher: &mut VolumeBatcher,
    in_flight: &mut Option<HeavyBuild<BuiltRefinementStep>>,
    ready: &mut Option<BuiltRefinementStep>,
    step: &StepInputs,
    mode: HeavyBuilds,
) -> Result<bool, VolumeBatchError> {
    let StepInputs { view, inputs, next } = *step;
    let mut updated = Ok(false);
    let mut take = |ready: &mut Option<BuiltRefinementStep>, batcher: &mut VolumeBatcher| {
        if let Some(built) = ready.take_if(|built| built.is_for_inputs(inputs)) {
            updated = batcher.adopt(built);
        }
    };
    if let Some(built) = in_flight.as_mut().and_then(|build| build.poll(mode)) {
        *in_flight = None;
        *ready = Some(built);
    }
    take(ready, batcher);
    let current = batcher.is_built_for(view, inputs);
    let wanted = if current {
        next.as_ref().filter(|next| next.blend < 1.0)
    } else {
        Some(inputs)
    };
    let wanted_step =
        wanted.and_then(|wanted| Some((wanted, batcher.refinement_step(view, wanted)?)));
    match wanted_step {
        Some((wanted, refinement)) => {
            if ready
                .as_ref()
                .is_some_and(|built| !built.is_for(view, wanted))
            {
                *ready = None;
            }
            if in_flight.is_none() && ready.is_none() {
                let mut build = HeavyBuild::spawn_in(mode, true, move || refinement.build());
                // Done at once under `HeavyBuilds::Blocking`.
                match build.poll(mode) {
                    Some(built) => *ready = Some(built),
                    None => *in_flight = Some(build),
                }
            }
            take(ready, batcher);
            updated
        }
        None if current => updated,
        None => batcher.update(view, inputs),
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

/// Makes the first batch of a keyframe pair not yet drawn (`pair`: the next
/// pair, made for the blend 0, or the first pair, while the volume's own
/// batch or nothing is drawn) for this frame's view and inputs on the task
/// pool (`build` holds it in flight), so that no frame builds it: the track
/// hands over to the next pair, and draws the first, once it has its batch.
/// One made for another view is made again in the frame it is drawn; a
/// failed one is the error (the volume's update failure), and is made again
/// the next frame.
fn make_ahead(
    pair: Option<&mut VolumeBatcher>,
    build: &mut Option<HeavyBuild<BuiltRefinementStep>>,
    view: &View,
    inputs: &FrameInputs,
    mode: HeavyBuilds,
) -> Result<(), VolumeBatchError> {
    let Some(pair) = pair else {
        *build = None;
        return Ok(());
    };
    if build.is_none() {
        *build = pair
            .first_build(view, inputs)
            .map(|step| HeavyBuild::spawn_in(mode, true, move || step.build()));
    }
    if let Some(built) = build.as_mut().and_then(|build| build.poll(mode)) {
        *build = None;
        pair.adopt(built)?;
    }
    Ok(())
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
    for (entity, batching, generation, mut status) in &mut volumes {
        let failure = generation
            .and_then(CloudGeneration::failure)
            .or(batching.keyframe_failure.as_ref())
            .or(batching.source_failure.as_ref())
            .or(batching.build_failure.as_ref())
            .or(batching.update_failure.as_ref());
        let pending = !batching.draws_keyframes()
            && (batching.batcher.is_none()
                || batching.loading
                || (batching.keyframes.is_none()
                    && generation.is_some_and(|generation| !generation.has_grid())));
        match failure {
            Some(error) => {
                VolumeStatus::fail(status.reborrow(), "volume", entity, error.clone());
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
            .drawn()
            .map_or(0, VolumeBatcher::full_resolution_cells);
    }
    let count = volumes.iter().len();
    diagnostics.add_measurement(&VolumePlugin::VOLUMES, || count as f64);
    diagnostics.add_measurement(&VolumePlugin::CELLS_DRAWN, || drawn as f64);
    diagnostics.add_measurement(&VolumePlugin::CELLS_FULL_RESOLUTION, || full as f64);
}
