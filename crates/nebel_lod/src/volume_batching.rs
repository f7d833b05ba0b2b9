//! One volume's batching from frame to frame: [`VolumeBatching`] owns its
//! [`VolumeBatcher`], its keyframes and the builds it runs on a
//! [`BuildPool`], so that an engine's system only hands it the frame's inputs
//! and draws what it returns.
//!
//! - [`VolumeBatching::build`] takes finished batcher builds and starts a new
//!   one when the source or settings changed (one at a time: inputs that
//!   change while it runs are built next, from their latest state, so every
//!   build lands; a failed build is not retried until its inputs change). An
//!   animated field, or a lit grid whose sun moved in the last two keyframe
//!   intervals, is drawn from its keyframes instead (`keyframe_track`).
//! - [`VolumeBatching::update`] brings the drawn batch up to date for the
//!   frame's view and inputs. An octree's refinement is made on the pool
//!   ([`VolumeBatcher::refinement_step`]) while the last batch is drawn and
//!   taken in the first frame after it is done, even if the camera moved on
//!   meanwhile; the next starts from the newest view. A keyframe pair's
//!   refinement steps for the advancing blend, the next pair's first batch and
//!   the first pair's first batch are made ahead on the pool too, so that no
//!   frame builds one; the clock waits at the end of a step whose successor is
//!   not made. A grid at full resolution or a cell mesh rebuilds on the
//!   caller's thread.
//!
//! An octree batch is kept until the eye moved half a voxel or left its
//! widened frustum ([`crate::octree::refresh`]), and is drawn a build or two
//! after the eye it was ordered for: it stays a visibility order while the
//! eye keeps to the same side of every face's plane between cells; only rays
//! across a face whose plane the eye crossed composite two cells out of order
//! (the octree tests measure the image cost).

use std::sync::Arc;
use std::time::Instant;

use glam::DVec3;
use nebel_core::field::CloudLighting;
use nebel_core::transfer::TransferFunction;

use crate::builds::{BuildKind, BuildPool};
use crate::keyframe_track::{
    AnimatedGrid, KeyframeRecipe, KeyframeSource, KeyframeTrack, SunMotion,
};
use crate::octree::LodCriterion;
use crate::octree::keyframe::REFINEMENT_SPAN;
use crate::octree::refresh::Latency;
use crate::{
    BatchLighting, BatchSettings, BuiltRefinementStep, CellOrder, Cells, FrameInputs, GridDrawing,
    View, VolumeBatchError, VolumeBatcher, VolumeSource,
};

/// A finished batcher build: the batcher and how long it took, ms.
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
/// flag for each part). The lighting is taken apart field by field, so a new
/// setting cannot be left out.
pub(crate) fn settings_bits(settings: &BatchSettings) -> [u64; 18] {
    let octree = settings.octree.map(|octree| octree.min_accuracy.to_bits());
    let mut bits = [0; 18];
    bits[0] = u64::from(settings.order == CellOrder::BackToFront);
    bits[12] = u64::from(settings.drawing == GridDrawing::ProjectedCells);
    bits[1] = u64::from(octree.is_some());
    bits[2] = octree.unwrap_or(0);
    if let Some(BatchLighting { light, scalars }) = settings.lighting {
        let CloudLighting {
            ambient,
            diffuse,
            sun_direction,
            shadow_extinction,
            lambert,
            scattering_octaves,
            sky_occlusion,
            sky_direction,
        } = light;
        bits[3] = 1;
        bits[4] = u64::from(ambient.to_bits());
        bits[5] = u64::from(diffuse.to_bits());
        bits[6] = u64::from(shadow_extinction.to_bits());
        bits[7] = u64::from(lambert);
        bits[8] = scalars as u64;
        bits[9..12].copy_from_slice(&sun_direction.to_array().map(f64::to_bits));
        bits[13] = u64::from(scattering_octaves);
        bits[14] = u64::from(sky_occlusion);
        bits[15..18].copy_from_slice(&sky_direction.to_array().map(f64::to_bits));
    }
    bits
}

/// What a volume is batched from in a frame ([`VolumeBatching::build`]).
#[derive(Clone, Debug)]
pub struct BuildRequest {
    /// The application's time, seconds: the keyframes' clock runs with it.
    pub now: f64,
    /// Whether the volume is drawn: a hidden one builds nothing and its
    /// keyframes' clock waits.
    pub visible: bool,
    /// Its source; `None` while it is not available (an asset loading, a
    /// generator not done).
    pub source: Option<VolumeSource>,
    /// Its settings, a lit volume's with the sun of this frame.
    pub settings: BatchSettings,
    /// A lit volume's keyframe interval under a moving sun, seconds;
    /// `None` for an unlit one.
    pub sun_keyframe_interval: Option<f32>,
    /// A field in motion and its keyframe interval, seconds: drawn from
    /// keyframes of it instead of `source`. A new `Arc` is a new animation
    /// (its keyframes are made again): pass the same one while it is
    /// unchanged.
    pub animation: Option<(Arc<dyn AnimatedGrid>, f32)>,
}

/// The builds that landed in a [`VolumeBatching::build`], ms each.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LandedBuilds {
    /// A new batcher.
    pub batcher_ms: Option<f64>,
    /// A pair of keyframes.
    pub keyframes_ms: Option<f64>,
}

/// The frame's batch ([`VolumeBatching::update`]).
#[derive(Clone, Debug)]
pub struct FrameBatch {
    /// The batch to draw.
    pub cells: Arc<Cells>,
    /// Whether it is another batch than last frame's (rebuilt, or another
    /// keyframe pair's): upload it again.
    pub changed: bool,
    /// For a keyframe pair, the mix of the batch's two ends to draw.
    pub blend: Option<f32>,
}

/// One volume's batcher, keyframes and builds in flight (see the module
/// docs).
pub struct VolumeBatching<P: BuildPool> {
    /// An animated volume's keyframes, drawn instead of `batcher`.
    keyframes: Option<KeyframeTrack<P>>,
    /// Why the keyframe track's last build failed.
    keyframe_failure: Option<VolumeBatchError>,
    /// The sun in the volume's frame at the last frame, and that frame's
    /// time.
    last_sun: Option<(DVec3, f64)>,
    /// When the sun last moved.
    sun_moved_at: Option<f64>,
    /// The keyframe pair (its first keyframe's index) the last batch
    /// returned came from; `None`: the volume's own batcher.
    returned_pair: Option<i64>,
    /// The octree's refinement in flight: for the frame's view and inputs
    /// when the drawn batch is older, or a still camera's next step of the
    /// keyframes' advancing blend, made ahead.
    refinement_step: Option<P::Pending<BuiltRefinementStep>>,
    /// A finished refinement waiting for the blend to reach it.
    ready_step: Option<BuiltRefinementStep>,
    /// Twice how far the view changed while the last refinement was made:
    /// the next culls wider by as much.
    latency: Latency,
    /// The next keyframe pair's first batch, made ahead, in flight.
    next_pair_batch: Option<P::Pending<BuiltRefinementStep>>,
    /// The first keyframe pair's first batch, made while the volume's own
    /// batch (or nothing) is drawn, in flight.
    first_pair_batch: Option<P::Pending<BuiltRefinementStep>>,
    /// What the batcher was built from.
    built: Option<BuildKey>,
    /// The build in flight and what it builds from.
    build: Option<(BuildKey, P::Pending<BuiltBatcher>)>,
    /// What the last failed build was built from: not retried until the
    /// inputs differ.
    failed: Option<BuildKey>,
    batcher: Option<VolumeBatcher>,
    /// Why the last build failed.
    build_failure: Option<VolumeBatchError>,
    /// Why the last update failed.
    update_failure: Option<VolumeBatchError>,
}

impl<P: BuildPool> Default for VolumeBatching<P> {
    fn default() -> Self {
        Self {
            keyframes: None,
            keyframe_failure: None,
            last_sun: None,
            sun_moved_at: None,
            returned_pair: None,
            refinement_step: None,
            ready_step: None,
            latency: Latency::default(),
            next_pair_batch: None,
            first_pair_batch: None,
            built: None,
            build: None,
            failed: None,
            batcher: None,
            build_failure: None,
            update_failure: None,
        }
    }
}

impl<P: BuildPool> VolumeBatching<P> {
    /// The batcher drawn: the keyframe track's pair when it has one.
    pub fn drawn(&self) -> Option<&VolumeBatcher> {
        self.keyframes
            .as_ref()
            .and_then(KeyframeTrack::batcher)
            .or(self.batcher.as_ref())
    }

    /// Whether the keyframes are drawn: once their first pair has a batch.
    pub fn draws_keyframes(&self) -> bool {
        self.keyframes
            .as_ref()
            .and_then(KeyframeTrack::batcher)
            .is_some_and(VolumeBatcher::is_built)
    }

    /// Whether the volume's own batcher is built (it may not be drawn, the
    /// keyframes are then).
    pub fn has_batcher(&self) -> bool {
        self.batcher.is_some()
    }

    /// Whether the volume is drawn from keyframes, or their first pair is
    /// being built.
    pub fn is_animated(&self) -> bool {
        self.keyframes.is_some()
    }

    /// No batcher build in flight.
    pub fn is_idle(&self) -> bool {
        self.build.is_none()
    }

    /// The first failure of the keyframes, the last build and the last
    /// update, in that order.
    pub fn failure(&self) -> Option<&VolumeBatchError> {
        self.keyframe_failure
            .as_ref()
            .or(self.build_failure.as_ref())
            .or(self.update_failure.as_ref())
    }

    /// Takes finished builds and starts new ones for the frame's `request`,
    /// and advances the keyframes (see the module docs); returns the builds
    /// that landed.
    pub fn build(&mut self, pool: P, request: BuildRequest) -> LandedBuilds {
        let now = request.now;
        let sun = self.observe_sun(request.settings.lighting.as_ref(), now);
        let keyframed = match (request.animation, request.sun_keyframe_interval) {
            (Some((field, interval)), _) => Some((KeyframeSource::Animated(field), interval)),
            (None, Some(interval)) => {
                let span = 2.0 * f64::from(interval).max(1e-3);
                let moving = self.sun_moved_at.is_some_and(|moved| now - moved <= span);
                match (moving, &request.source) {
                    (true, Some(VolumeSource::Grid(grid))) => {
                        Some((KeyframeSource::Grid(grid.clone()), interval))
                    }
                    _ => None,
                }
            }
            (None, None) => None,
        };
        let mut landed = LandedBuilds::default();
        if let Some((source, interval)) = keyframed {
            if request.visible {
                let recipe = KeyframeRecipe {
                    source,
                    settings: request.settings,
                    interval,
                };
                landed.keyframes_ms = self.advance_keyframes(pool, recipe, sun, now);
            }
            return landed;
        }
        self.keyframe_failure = None;
        // A build started last frame may be done (always when the pool waits).
        landed.batcher_ms = self.finish_build(pool);
        if !request.visible || self.build.is_some() {
            return landed;
        }
        let Some(source) = request.source else {
            return landed;
        };
        let key = BuildKey {
            source,
            settings: request.settings,
        };
        let unchanged = |last: &Option<BuildKey>| last.as_ref().is_some_and(|k| k.same_as(&key));
        if !unchanged(&self.built) && !unchanged(&self.failed) {
            let (source, settings) = (key.source.clone(), key.settings);
            let build = pool.spawn(BuildKind::Batcher, move || {
                let started = Instant::now();
                VolumeBatcher::new(source, &settings)
                    .map(|batcher| (batcher, started.elapsed().as_secs_f64() * 1e3))
            });
            self.build = Some((key.clone(), build));
            landed.batcher_ms = landed.batcher_ms.or(self.finish_build(pool));
        }
        if self.built.as_ref().is_some_and(|built| built.same_as(&key)) {
            // Built for the volume as it is: the keyframes are done with.
            if let Some(track) = self.keyframes.take() {
                pool.free(track);
            }
        }
        landed
    }

    /// The sun's motion in a lit volume's frame from its last frame to this
    /// one (`now`), noting when it last moved; a still sun straight up for
    /// an unlit volume.
    fn observe_sun(&mut self, lighting: Option<&BatchLighting>, now: f64) -> SunMotion {
        let Some(lighting) = lighting else {
            return SunMotion::still(DVec3::Y, now);
        };
        let direction = lighting.light.sun_direction;
        let motion = match self.last_sun {
            Some((last, last_time)) => SunMotion::between(last, last_time, direction, now),
            None => SunMotion::still(direction, now),
        };
        if self.last_sun.is_some_and(|(last, _)| last != direction) {
            self.sun_moved_at = Some(now);
        }
        self.last_sun = Some((direction, now));
        motion
    }

    /// Starts the keyframe track of `recipe` unless it runs already (a new
    /// recipe starts over), lights it by `sun` and advances it to `now`;
    /// returns the time of a pair that landed.
    fn advance_keyframes(
        &mut self,
        pool: P,
        recipe: KeyframeRecipe,
        sun: SunMotion,
        now: f64,
    ) -> Option<f64> {
        if !self
            .keyframes
            .as_ref()
            .is_some_and(|track| track.is_for(&recipe))
        {
            self.keyframes = Some(KeyframeTrack::new(recipe, sun, now, pool));
            self.keyframe_failure = None;
        }
        let track = self.keyframes.as_mut().expect("started above");
        track.set_sun(sun);
        // The next pair takes over once its first batch is made (`make_ahead`).
        match track.advance(now, pool, VolumeBatcher::is_built) {
            Ok(built_ms) => built_ms,
            Err(error) => {
                self.keyframe_failure = Some(error);
                None
            }
        }
    }

    /// Takes the build in flight if it is done; returns its time.
    fn finish_build(&mut self, pool: P) -> Option<f64> {
        let (key, build) = self.build.as_mut()?;
        let result = pool.poll(build)?;
        let key = key.clone();
        self.build = None;
        match result {
            Ok((batcher, build_ms)) => {
                if let Some(old) = self.batcher.replace(batcher) {
                    pool.free(old);
                }
                self.built = Some(key);
                self.failed = None;
                self.build_failure = None;
                self.update_failure = None;
                Some(build_ms)
            }
            Err(error) => {
                if let Some(old) = self.batcher.take() {
                    pool.free(old);
                }
                self.built = None;
                self.failed = Some(key);
                self.build_failure = Some(error);
                None
            }
        }
    }

    /// Brings the drawn batch up to date for `view` (`None`: no camera, the
    /// batch stays) under `transfer` and `criterion` (read by the octree
    /// alone); `None` while nothing is drawn.
    pub fn update(
        &mut self,
        pool: P,
        view: Option<&View>,
        transfer: &TransferFunction,
        criterion: LodCriterion,
    ) -> Option<FrameBatch> {
        // The first pair's first batch is made on the pool while the
        // volume's own batch, if any, is drawn.
        if let (Some(view), Some(track)) = (view, self.keyframes.as_mut()) {
            let first = FrameInputs {
                transfer,
                criterion,
                blend: track.refinement_blend(),
                blend_span: REFINEMENT_SPAN,
            };
            if let Err(error) = make_ahead(
                pool,
                track.batcher_mut().filter(|pair| !pair.is_built()),
                &mut self.first_pair_batch,
                view,
                &first,
            ) {
                self.update_failure = Some(error);
            }
        }
        // The keyframes once their first pair has a batch, the volume's own
        // batcher until then and after.
        let from_keyframes = self.draws_keyframes();
        let track = self.keyframes.as_mut().filter(|_| from_keyframes);
        let pair = track.as_ref().and_then(|track| track.pair_index());
        // A new pair (or the switch to or from the keyframes) is a new batch
        // even when it was made ahead for this very view.
        let switched = pair != self.returned_pair;
        let blend = track
            .as_ref()
            .map(|track| (track.blend(), track.refinement_blend()));
        let batcher = match track {
            Some(track) => track.batcher_mut(),
            None => self.batcher.as_mut(),
        };
        let (Some(view), Some(batcher)) = (view, batcher) else {
            return None;
        };
        let inputs = FrameInputs {
            transfer,
            criterion,
            blend: blend.map_or(0.0, |(_, refined_for)| refined_for),
            blend_span: blend.map_or(0.0, |_| REFINEMENT_SPAN),
        };
        // A still camera's refinement steps for the advancing blend run on
        // the pool while the current batch is drawn, each made ahead and
        // taking over when the blend reaches it.
        let step = StepInputs {
            view,
            inputs: &inputs,
            next: blend.map(|_| FrameInputs {
                blend: inputs.blend + REFINEMENT_SPAN,
                ..inputs
            }),
        };
        let updated = step_batch(
            pool,
            batcher,
            &mut self.refinement_step,
            &mut self.ready_step,
            &mut self.latency,
            &step,
        );
        // While the next step's batch is being made, the clock waits at the
        // end of the drawn one's span.
        let hold = step.next.filter(|next| {
            next.blend < 1.0
                && self.refinement_step.is_some()
                && batcher.is_built_for(view, &inputs)
        });
        let frame = FrameBatch {
            cells: batcher.batch().clone(),
            changed: false,
            // The blend as the mix of the drawn batch's two ends.
            blend: blend.map(|(blend, _)| batcher.batch().mix_factor(blend)),
        };
        let frame = match updated {
            Ok(changed) => {
                self.update_failure = None;
                if changed || switched {
                    self.returned_pair = pair;
                }
                FrameBatch {
                    changed: changed || switched,
                    ..frame
                }
            }
            Err(error) => {
                self.update_failure = Some(error);
                frame
            }
        };
        if let Some(track) = self.keyframes.as_mut().filter(|_| from_keyframes) {
            track.hold_at(hold.map(|next| next.blend));
            let next = FrameInputs {
                blend: 0.0,
                ..inputs
            };
            if let Err(error) = make_ahead(
                pool,
                track.next_batcher_mut(),
                &mut self.next_pair_batch,
                view,
                &next,
            ) {
                self.update_failure = Some(error);
            }
        }
        Some(frame)
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
/// whether it changed. An octree's refinement is made on the pool
/// (`in_flight`) while the current batch is drawn: for this frame's view and
/// inputs when the batch is older, else, for a keyframe pair under a still
/// camera, the next step ahead. A finished one (`ready`) is taken when it is
/// for this frame's inputs, also when the camera has moved on since it was
/// started (it is newer than the drawn batch; the next starts from the
/// current view), or, made ahead, once the blend reaches it. A step culls
/// wider by `latency`, twice how far the view changed while the last one
/// was made. The other kinds rebuild at once.
fn step_batch<P: BuildPool>(
    pool: P,
    batcher: &mut VolumeBatcher,
    in_flight: &mut Option<P::Pending<BuiltRefinementStep>>,
    ready: &mut Option<BuiltRefinementStep>,
    latency: &mut Latency,
    step: &StepInputs,
) -> Result<bool, VolumeBatchError> {
    let StepInputs { view, inputs, next } = *step;
    let mut updated = Ok(false);
    let mut take = |ready: &mut Option<BuiltRefinementStep>, batcher: &mut VolumeBatcher| {
        if let Some(built) = ready.take_if(|built| built.is_for_inputs(inputs)) {
            updated = batcher.adopt(built);
        }
    };
    if let Some(built) = in_flight.as_mut().and_then(|build| pool.poll(build)) {
        let change = built.latency_to(view);
        *latency = Latency {
            distance: 2.0 * change.distance,
            angle: 2.0 * change.angle,
        };
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
                let refinement = refinement.with_latency(*latency);
                let mut build = pool.spawn(BuildKind::Refinement, move || refinement.build());
                // Done at once when the pool waits.
                match pool.poll(&mut build) {
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

/// Makes the first batch of a keyframe pair not yet drawn (`pair`: the next
/// pair, made for the blend 0, or the first pair, while the volume's own
/// batch or nothing is drawn) for this frame's view and inputs on the pool
/// (`build` holds it in flight), so that no frame builds it: the track hands
/// over to the next pair, and draws the first, once it has its batch. One
/// made for another view is made again in the frame it is drawn; a failed
/// one is the error (the volume's update failure), and is made again the
/// next frame. A pair whose batch does not depend on the view (a ray-cast
/// grid: its keyframes' fields and occupancy, no refinement) is made here.
fn make_ahead<P: BuildPool>(
    pool: P,
    pair: Option<&mut VolumeBatcher>,
    build: &mut Option<P::Pending<BuiltRefinementStep>>,
    view: &View,
    inputs: &FrameInputs,
) -> Result<(), VolumeBatchError> {
    let Some(pair) = pair else {
        *build = None;
        return Ok(());
    };
    if !pair.is_built() && !pair.is_view_dependent() {
        pair.update(view, inputs)?;
        return Ok(());
    }
    if build.is_none() {
        *build = pair
            .first_build(view, inputs)
            .map(|step| pool.spawn(BuildKind::Refinement, move || step.build()));
    }
    if let Some(built) = build.as_mut().and_then(|build| pool.poll(build)) {
        *build = None;
        pair.adopt(built)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use glam::{DAffine3, UVec2};
    use nebel_core::field::{CloudLighting, DensityGrid};
    use nebel_core::transfer::TransferPreset;

    use super::*;
    use crate::LocalBuilds::{self, Blocking, Deferred};
    use crate::OctreeSettings;
    use crate::octree::CellScalars;

    fn grid() -> Arc<DensityGrid> {
        let n = 9;
        let values = (0..n * n * n)
            .map(|i| {
                let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
                (0.5 + 0.5 * ((x as f32) * 0.9).sin() * ((y + 2 * z) as f32 * 0.7).cos()).max(0.0)
            })
            .collect();
        Arc::new(DensityGrid::new([n; 3], DVec3::ONE, DVec3::ZERO, values).unwrap())
    }

    fn settings(lit: Option<DVec3>) -> BatchSettings {
        BatchSettings {
            order: CellOrder::BackToFront,
            octree: Some(OctreeSettings { min_accuracy: 2.0 }),
            lighting: lit.map(|sun_direction| BatchLighting {
                light: CloudLighting {
                    sun_direction,
                    shadow_extinction: 0.5,
                    ..CloudLighting::default()
                },
                scalars: CellScalars::LightModulatedByDensity,
            }),
            ..BatchSettings::default()
        }
    }

    fn request(now: f64, grid: &Arc<DensityGrid>, settings: BatchSettings) -> BuildRequest {
        BuildRequest {
            now,
            visible: true,
            source: Some(VolumeSource::Grid(grid.clone())),
            settings,
            sun_keyframe_interval: settings.lighting.map(|_| 1.0),
            animation: None,
        }
    }

    fn view(eye: DVec3) -> View {
        View::new(DAffine3::IDENTITY, eye, UVec2::new(160, 120))
    }

    fn update<P: BuildPool>(
        batching: &mut VolumeBatching<P>,
        pool: P,
        eye: DVec3,
    ) -> Option<FrameBatch> {
        let transfer = TransferFunction::preset(TransferPreset::CloudLight);
        batching.update(
            pool,
            Some(&view(eye)),
            &transfer,
            LodCriterion::distance(8.0),
        )
    }

    /// The batch of a batcher built anew for `settings` and updated for `eye`.
    fn fresh(grid: &Arc<DensityGrid>, settings: BatchSettings, eye: DVec3) -> Arc<Cells> {
        let mut batcher = VolumeBatcher::new(VolumeSource::Grid(grid.clone()), &settings).unwrap();
        let transfer = TransferFunction::preset(TransferPreset::CloudLight);
        let inputs = FrameInputs {
            transfer: &transfer,
            criterion: LodCriterion::distance(8.0),
            blend: 0.0,
            blend_span: 0.0,
        };
        batcher.update(&view(eye), &inputs).unwrap();
        batcher.batch().clone()
    }

    /// A batcher is built once per change of its inputs, one build at a
    /// time; a failed one is not started again until they change.
    #[test]
    fn a_batcher_is_built_once_per_change_and_a_failed_one_waits_for_new_inputs() {
        let grid = grid();
        let eye = DVec3::new(4.0, 12.0, -14.0);
        let mut batching = VolumeBatching::default();
        assert!(
            update(&mut batching, Blocking, eye).is_none(),
            "nothing built"
        );
        let landed = batching.build(Blocking, request(0.0, &grid, settings(None)));
        assert!(landed.batcher_ms.is_some() && landed.keyframes_ms.is_none());
        let frame = update(&mut batching, Blocking, eye).unwrap();
        assert!(frame.changed && frame.blend.is_none());
        assert_eq!(*frame.cells, *fresh(&grid, settings(None), eye));
        let again = batching.build(Blocking, request(0.1, &grid, settings(None)));
        assert_eq!(again, LandedBuilds::default());
        assert!(!update(&mut batching, Blocking, eye).unwrap().changed);

        // Scalars without light fail; the same inputs start nothing.
        let mut unlit = settings(Some(DVec3::Y));
        if let Some(lighting) = &mut unlit.lighting {
            lighting.scalars = CellScalars::Density;
        }
        let failing = BuildRequest {
            sun_keyframe_interval: None,
            ..request(0.2, &grid, unlit)
        };
        batching.build(Deferred, failing.clone());
        assert!(!batching.is_idle());
        batching.build(Blocking, failing.clone());
        assert!(matches!(
            batching.failure(),
            Some(VolumeBatchError::UnlitScalars)
        ));
        assert!(batching.drawn().is_none(), "a failed build draws nothing");
        batching.build(Deferred, failing);
        assert!(batching.is_idle(), "not started again");
        let landed = batching.build(Blocking, request(0.3, &grid, settings(None)));
        assert!(landed.batcher_ms.is_some());
        assert!(batching.failure().is_none());
    }

    #[test]
    fn every_light_setting_builds_again_and_the_same_ones_do_not() {
        let grid = grid();
        let mut batching = VolumeBatching::default();
        let changes: [fn(&mut CloudLighting); 5] = [
            |light| light.ambient = 0.1,
            |light| light.lambert = false,
            |light| light.scattering_octaves = 3,
            |light| light.sky_occlusion = true,
            |light| light.sky_direction = DVec3::X,
        ];
        let mut lit = settings(Some(DVec3::Y));
        batching.build(Blocking, request(0.0, &grid, lit));
        for (n, change) in changes.into_iter().enumerate() {
            if let Some(lighting) = &mut lit.lighting {
                change(&mut lighting.light);
            }
            let now = n as f64 + 1.0;
            let landed = batching.build(Blocking, request(now, &grid, lit));
            assert_ne!(landed, LandedBuilds::default(), "change {n} builds");
            let again = batching.build(Blocking, request(now + 0.5, &grid, lit));
            assert_eq!(again, LandedBuilds::default(), "change {n} again");
        }
    }

    /// An octree's refinement is made beside the frames that draw the last
    /// batch, and taken once done even for a camera that moved on; the next
    /// then starts from the newest view and ends in the batch a batcher built
    /// for that view has.
    #[test]
    fn a_refinement_is_made_beside_the_frame_and_taken_when_done() {
        let grid = grid();
        let eyes = [-14.0, -20.0, -26.0].map(|z| DVec3::new(4.0, 12.0, z));
        let mut batching = VolumeBatching::default();
        batching.build(Blocking, request(0.0, &grid, settings(None)));
        let first = update(&mut batching, Blocking, eyes[0]).unwrap();
        let late = update(&mut batching, Deferred, eyes[1]).unwrap();
        assert!(!late.changed && Arc::ptr_eq(&late.cells, &first.cells));
        let later = update(&mut batching, Deferred, eyes[2]).unwrap();
        assert!(!later.changed && Arc::ptr_eq(&later.cells, &first.cells));
        let landed = update(&mut batching, Blocking, eyes[2]).unwrap();
        assert!(landed.changed);
        assert_eq!(*landed.cells, *fresh(&grid, settings(None), eyes[2]));
        assert!(!update(&mut batching, Blocking, eyes[2]).unwrap().changed);
    }

    /// A refinement drawn a frame late, while the camera turned, makes the
    /// next one cull wider by twice the turn, so that a camera turning at
    /// that rate stays inside what the batch holds until the next lands.
    #[test]
    fn a_refinement_drawn_while_the_camera_turned_culls_wider_next() {
        let grid = grid();
        let eye = DVec3::new(4.0, 4.0, -14.0);
        let turned = |degrees: f64| {
            let forward = glam::DQuat::from_rotation_y(degrees.to_radians()) * DVec3::Z;
            let clip_from_world = glam::DMat4::perspective_infinite_reverse_rh(0.8, 4.0 / 3.0, 0.1)
                * glam::DMat4::look_to_rh(eye, forward, DVec3::Y);
            view(eye).with_projection(clip_from_world)
        };
        let transfer = TransferFunction::preset(TransferPreset::CloudLight);
        let criterion = LodCriterion::distance(8.0);
        let frame = |batching: &mut VolumeBatching<LocalBuilds>, pool, degrees| {
            let view = turned(degrees);
            let drawn = batching.update(pool, Some(&view), &transfer, criterion);
            drawn.unwrap().changed
        };
        let mut batching = VolumeBatching::default();
        batching.build(Blocking, request(0.0, &grid, settings(None)));
        assert!(frame(&mut batching, Blocking, 0.0));
        // Made for 10°, drawn at 20°: the next, for 20°, culls 20° wider.
        assert!(!frame(&mut batching, Deferred, 10.0));
        assert!(frame(&mut batching, Blocking, 20.0));
        assert!(
            !frame(&mut batching, Blocking, 35.0),
            "inside the wider culling"
        );
        assert!(frame(&mut batching, Blocking, 65.0), "beyond it");
        // Without the latency, a turn of 15° refines again.
        let mut still = VolumeBatching::default();
        still.build(Blocking, request(0.0, &grid, settings(None)));
        assert!(frame(&mut still, Blocking, 20.0));
        assert!(frame(&mut still, Blocking, 35.0));
    }

    /// A lit grid whose sun moves is drawn from keyframes, blended, through
    /// the octree or ray cast; two intervals after the sun rests it is built
    /// once for where it stopped.
    #[test]
    fn a_moving_sun_draws_keyframes_until_it_rests() {
        let ray_cast = |sun: DVec3| BatchSettings {
            octree: None,
            drawing: GridDrawing::RayCast,
            ..settings(Some(sun))
        };
        let octree = |sun: DVec3| settings(Some(sun));
        for settings in [octree, ray_cast] {
            let grid = grid();
            let eye = DVec3::new(4.0, 12.0, -14.0);
            let sun = |angle: f64| DVec3::new(angle.sin(), angle.cos(), 0.0);
            let mut batching = VolumeBatching::default();
            batching.build(Blocking, request(0.0, &grid, settings(sun(0.2))));
            update(&mut batching, Blocking, eye).unwrap();
            assert!(!batching.is_animated());
            let mut keyframes = 0;
            for frame in 1..=10 {
                let now = 0.1 * f64::from(frame);
                let landed =
                    batching.build(Blocking, request(now, &grid, settings(sun(0.2 + now))));
                keyframes += usize::from(landed.keyframes_ms.is_some());
                let drawn = update(&mut batching, Blocking, eye).unwrap();
                assert!(batching.draws_keyframes(), "frame {frame}");
                assert!(drawn.cells.is_blended() && !drawn.cells.is_empty());
                assert!(
                    drawn
                        .blend
                        .is_some_and(|blend| (0.0..=1.0).contains(&blend))
                );
            }
            assert!(keyframes >= 1);
            // The sun rests at 1.2 from 1.0 s on: keyframes until 3 s.
            let rest = settings(sun(1.2));
            batching.build(Blocking, request(2.9, &grid, rest));
            assert!(batching.is_animated());
            batching.build(Blocking, request(3.1, &grid, rest));
            assert!(!batching.is_animated());
            let drawn = update(&mut batching, Blocking, eye).unwrap();
            assert!(drawn.changed && drawn.blend.is_none());
            assert_eq!(*drawn.cells, *fresh(&grid, rest, eye));
        }
    }
}
