//! Keyframes of an animated volume: a cloud in the wind or a lit grid under a
//! moving sun, built ahead and blended on the GPU, so the image moves at
//! frame rate instead of stepping at every rebuild.
//!
//! An animated field's density is a pure function of time ([`AnimatedGrid`];
//! a cloud's `nebel_core::field::CloudNoise` drifts every octave with its own
//! wind after Schpok et al. 2003 §5.3). The track samples it at the keyframe
//! times `t_k = k·T` and draws `f(t) = (1 − β) f(t_k) + β f(t_{k+1})`,
//! `β = (t − t_k) / T`, through one octree of both keyframes
//! ([`crate::octree::keyframe`]): each frame only `β` changes, and the octree
//! is refined again [`REFINEMENT_STEPS`] times per interval. A lit grid under a
//! moving sun is drawn the same way from keyframes of its light field, each lit
//! by the sun extrapolated to the keyframe's time as a turn at a constant rate
//! (`SunMotion`).
//!
//! While a pair is drawn, the next is built on the [`BuildPool`]; at `β = 1`
//! both draw the same field, so the hand-over changes nothing but the batch.
//! The clock waits at the end of a pair or refinement step whose successor is
//! not ready, so a slow build slows the animation instead of stepping it.
//! Between keyframes the field is a cross-fade, not a drift (see
//! `docs/wind-keyframes.md`).

use std::sync::Arc;
use std::time::Instant;

use glam::{DQuat, DVec3};
use nebel_core::field::{DensityGrid, FieldError};

use crate::builds::{BuildKind, BuildPool};
use crate::octree::keyframe::{REFINEMENT_STEPS, keyframe_index, keyframe_time};
use crate::volume_batching::settings_bits;
use crate::{BatchSettings, VolumeBatchError, VolumeBatcher, VolumeSource};

/// A density field that moves with time, sampled on a grid at any time (a
/// cloud in the wind). Two are the same animation when they are the same
/// `Arc`: hand the track the one you made until the animation changes.
pub trait AnimatedGrid: std::fmt::Debug + Send + Sync {
    /// The grid at `time` seconds.
    fn grid_at(&self, time: f64) -> Result<DensityGrid, FieldError>;
}

/// What a volume's keyframes sample.
#[derive(Clone, Debug)]
pub(crate) enum KeyframeSource {
    /// A field in motion: its grid at each keyframe's time.
    Animated(Arc<dyn AnimatedGrid>),
    /// A grid that does not move (lit under a moving sun).
    Grid(Arc<DensityGrid>),
}

/// The sun seen from a volume, turning at a constant rate: where it is at
/// any time, extrapolated from its last two frames.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct SunMotion {
    /// Unit direction toward the sun at `time`, the volume's local frame.
    pub(crate) direction: DVec3,
    /// The application time of `direction`, seconds.
    pub(crate) time: f64,
    /// The unit axis it turns about.
    pub(crate) axis: DVec3,
    /// How fast it turns, radians per second.
    pub(crate) rate: f64,
}

impl SunMotion {
    /// A sun standing still at `direction`.
    pub(crate) fn still(direction: DVec3, time: f64) -> Self {
        Self {
            direction,
            time,
            axis: DVec3::Y,
            rate: 0.0,
        }
    }

    /// The motion of a sun that was at `last` at `last_time` and is at
    /// `direction` at `time` (unit vectors): turning about their common
    /// normal at the rate between the two frames; still when they agree or
    /// the time did not advance.
    pub(crate) fn between(last: DVec3, last_time: f64, direction: DVec3, time: f64) -> Self {
        let angle = last.angle_between(direction);
        let axis = last.cross(direction).normalize_or_zero();
        let elapsed = time - last_time;
        if !(angle > 0.0 && elapsed > 0.0) || axis == DVec3::ZERO {
            return Self::still(direction, time);
        }
        Self {
            direction,
            time,
            axis,
            rate: angle / elapsed,
        }
    }

    /// The direction toward the sun at `time`.
    pub(crate) fn at(&self, time: f64) -> DVec3 {
        let angle = self.rate * (time - self.time);
        if angle == 0.0 || !angle.is_finite() {
            return self.direction;
        }
        DQuat::from_axis_angle(self.axis, angle) * self.direction
    }
}

/// What a keyframe is built from, but its time and sun.
#[derive(Clone, Debug)]
pub(crate) struct KeyframeRecipe {
    /// What is sampled.
    pub(crate) source: KeyframeSource,
    /// The batch settings; a lit volume's sun is replaced by the track's.
    pub(crate) settings: BatchSettings,
    /// Seconds between keyframes.
    pub(crate) interval: f32,
}

impl KeyframeRecipe {
    /// The keyframe at time `t` under `sun`: the source's grid then, lit
    /// by the sun then, and everything the batcher builds from it.
    fn keyframe(&self, t: f64, sun: &SunMotion) -> Result<VolumeBatcher, VolumeBatchError> {
        let grid = match &self.source {
            KeyframeSource::Animated(field) => Arc::new(field.grid_at(t)?),
            KeyframeSource::Grid(grid) => grid.clone(),
        };
        let mut settings = self.settings;
        if let Some(lighting) = &mut settings.lighting {
            lighting.light.sun_direction = sun.at(t);
        }
        VolumeBatcher::new(VolumeSource::Grid(grid), &settings)
    }

    /// Equality of what the keyframes depend on but the sun, bit for bit (a
    /// NaN setting equals itself, so a track that failed on it is not
    /// started again every frame), and the animation's or grid's identity.
    fn same_as(&self, other: &Self) -> bool {
        let without_sun = |recipe: &Self| {
            let mut settings = recipe.settings;
            if let Some(lighting) = &mut settings.lighting {
                lighting.light.sun_direction = DVec3::ZERO;
            }
            (settings_bits(&settings), recipe.interval.to_bits())
        };
        let source = match (&self.source, &other.source) {
            (KeyframeSource::Animated(a), KeyframeSource::Animated(b)) => Arc::ptr_eq(a, b),
            (KeyframeSource::Grid(a), KeyframeSource::Grid(b)) => Arc::ptr_eq(a, b),
            _ => false,
        };
        source && without_sun(self) == without_sun(other)
    }
}

/// A pair of keyframes ready to draw.
#[derive(Debug)]
struct Pair {
    /// The blending batcher of keyframes `index` and `index + 1`.
    batcher: VolumeBatcher,
    /// The first keyframe's index `k`: its time is `k·T`.
    index: i64,
    /// The second keyframe alone, the first of the next pair.
    second: Arc<VolumeBatcher>,
}

/// A finished build: a pair and the CPU time it took, ms.
type BuiltPair = Result<(Pair, f64), VolumeBatchError>;

/// One animated volume's keyframes (see the module docs).
pub(crate) struct KeyframeTrack<P: BuildPool> {
    recipe: KeyframeRecipe,
    /// Seconds between keyframes.
    interval: f64,
    /// The animation time.
    clock: f64,
    /// The application time of the last [`KeyframeTrack::advance`].
    last_time: f64,
    /// The pair drawn now.
    drawn: Option<Pair>,
    /// The next pair, built and waiting for the clock.
    next: Option<Pair>,
    /// The build in flight: the first pair, or the one after the last.
    build: Option<P::Pending<BuiltPair>>,
    /// The sun the keyframes built from now on are lit by.
    sun: SunMotion,
    /// A build failed: none is started again (the recipe must change).
    failed: bool,
    /// The blend of the drawn pair (its first keyframe's index) at which
    /// the clock waits: the end of the drawn refinement step while the next
    /// step's batch is not made yet.
    hold: Option<(i64, f32)>,
}

impl<P: BuildPool> KeyframeTrack<P> {
    /// A track of `recipe` whose clock starts at `now` (seconds, the
    /// application's time), in the pair of keyframes around it, built on
    /// `pool`; nothing to draw until that pair is built.
    pub(crate) fn new(recipe: KeyframeRecipe, sun: SunMotion, now: f64, pool: P) -> Self {
        // NaN and anything below a millisecond count as a millisecond.
        let interval = f64::from(recipe.interval).max(1e-3);
        let index = keyframe_index(now, interval);
        let first = {
            let recipe = recipe.clone();
            pool.spawn(BuildKind::Keyframes, move || {
                let started = Instant::now();
                let first = recipe.keyframe(keyframe_time(index, interval), &sun)?;
                let second = recipe.keyframe(keyframe_time(index + 1, interval), &sun)?;
                let pair = pair(&first, Arc::new(second), index)?;
                Ok((pair, started.elapsed().as_secs_f64() * 1e3))
            })
        };
        Self {
            recipe,
            interval,
            clock: now,
            last_time: now,
            drawn: None,
            next: None,
            build: Some(first),
            sun,
            failed: false,
            hold: None,
        }
    }

    /// Whether the track draws `recipe`'s keyframes.
    pub(crate) fn is_for(&self, recipe: &KeyframeRecipe) -> bool {
        self.recipe.same_as(recipe)
    }

    /// Makes the clock wait at `blend` of the drawn pair (the end of the
    /// drawn refinement step, whose successor is not made yet) from the next
    /// [`KeyframeTrack::advance`] on; `None` lets it run.
    pub(crate) fn hold_at(&mut self, blend: Option<f32>) {
        self.hold = blend
            .zip(self.pair_index())
            .map(|(blend, index)| (index, blend));
    }

    /// Lights the keyframes built from now on by `sun`.
    pub(crate) fn set_sun(&mut self, sun: SunMotion) {
        self.sun = sun;
    }

    /// Advances the clock by the application time since the last call (`now`
    /// in seconds), takes a finished build (its CPU time in ms is returned),
    /// hands over to the next pair at the end of the drawn one when
    /// `next_ready` says it may (its first batch is made), holds the clock
    /// at a refinement step's end while [`KeyframeTrack::hold_at`] says so,
    /// and starts building the pair after it. A failed
    /// build is returned as the error; the track keeps what it draws and
    /// builds nothing more.
    pub(crate) fn advance(
        &mut self,
        now: f64,
        pool: P,
        next_ready: impl Fn(&VolumeBatcher) -> bool,
    ) -> Result<Option<f64>, VolumeBatchError> {
        let delta = now - self.last_time;
        self.last_time = now;
        let mut built_ms = None;
        // Under Blocking the build the last frame started lands now.
        if let Some(result) = self.build.as_mut().and_then(|build| pool.poll(build)) {
            self.build = None;
            self.failed = result.is_err();
            let (pair, ms) = result?;
            built_ms = Some(ms);
            if self.drawn.is_none() {
                self.drawn = Some(pair);
            } else {
                self.next = Some(pair);
            }
        }
        let Some(drawn) = &self.drawn else {
            return Ok(built_ms);
        };
        // Past the drawn pair's end the next one takes over once it is
        // ready, or the clock waits for it.
        let end = keyframe_time(drawn.index + 1, self.interval);
        // Time runs forward only; a NaN frame time adds nothing.
        let before = self.clock;
        self.clock += delta.max(0.0);
        if self.clock >= end {
            match self.next.take_if(|next| next_ready(&next.batcher)) {
                Some(next) => {
                    // The old pair: its first keyframe's 5 bytes per grid
                    // point (its second is the new pair's first).
                    if let Some(old) = self.drawn.replace(next) {
                        pool.free(old);
                    }
                }
                None => self.clock = end,
            }
        }
        let end = self.drawn.as_ref().map_or(end, |pair| {
            // A refinement step whose successor is not made holds the clock
            // at its end, so the drawn blend never leaves the cells' span.
            let step_end = self
                .hold
                .filter(|&(index, _)| index == pair.index)
                .map(|(_, blend)| {
                    let start = keyframe_time(pair.index, self.interval);
                    (start + f64::from(blend) * self.interval).max(before)
                });
            let end = keyframe_time(pair.index + 1, self.interval);
            step_end.map_or(end, |step_end| step_end.min(end))
        });
        self.clock = self.clock.min(end);
        if self.next.is_none() && self.build.is_none() && !self.failed {
            let drawn = self.drawn.as_ref().expect("a pair is drawn");
            let (first, index) = (drawn.second.clone(), drawn.index + 1);
            let (recipe, interval, sun) = (self.recipe.clone(), self.interval, self.sun);
            self.build = Some(pool.spawn(BuildKind::Keyframes, move || {
                let started = Instant::now();
                let second = recipe.keyframe(keyframe_time(index + 1, interval), &sun)?;
                let pair = pair(&first, Arc::new(second), index)?;
                Ok((pair, started.elapsed().as_secs_f64() * 1e3))
            }));
        }
        Ok(built_ms)
    }

    /// The drawn pair's batcher, `None` until the first pair is built.
    pub(crate) fn batcher_mut(&mut self) -> Option<&mut VolumeBatcher> {
        self.drawn.as_mut().map(|pair| &mut pair.batcher)
    }

    /// The next pair's batcher, once built and waiting for the clock.
    pub(crate) fn next_batcher_mut(&mut self) -> Option<&mut VolumeBatcher> {
        self.next.as_mut().map(|pair| &mut pair.batcher)
    }

    /// The index of the drawn pair's first keyframe; `None` until the first
    /// pair is built.
    pub(crate) fn pair_index(&self) -> Option<i64> {
        self.drawn.as_ref().map(|pair| pair.index)
    }

    /// The drawn pair's batcher, `None` until the first pair is built.
    pub(crate) fn batcher(&self) -> Option<&VolumeBatcher> {
        self.drawn.as_ref().map(|pair| &pair.batcher)
    }

    /// The blend toward the drawn pair's second keyframe.
    pub(crate) fn blend(&self) -> f32 {
        let factor = self.drawn.as_ref().map_or(0.0, |pair| {
            let start = keyframe_time(pair.index, self.interval);
            ((self.clock - start) / self.interval).clamp(0.0, 1.0)
        });
        factor as f32
    }

    /// The blend the octree is refined for: the blend rounded down to a
    /// step of 1/[`REFINEMENT_STEPS`].
    pub(crate) fn refinement_blend(&self) -> f32 {
        let steps = REFINEMENT_STEPS as f32;
        (self.blend() * steps).floor() / steps
    }

    /// The animation time the drawn field shows.
    #[cfg(test)]
    fn clock(&self) -> f64 {
        self.clock
    }
}

/// The pair of keyframes `index` (`first`) and `index + 1` (`second`).
fn pair(
    first: &VolumeBatcher,
    second: Arc<VolumeBatcher>,
    index: i64,
) -> Result<Pair, VolumeBatchError> {
    Ok(Pair {
        batcher: first.with_next_keyframe(&second)?,
        index,
        second,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DAffine3, UVec2};
    use nebel_core::field::{CloudLighting, CloudNoise};
    use nebel_core::transfer::{TransferFunction, TransferPreset};

    use crate::builds::LocalBuilds;
    use crate::octree::keyframe::REFINEMENT_SPAN;
    use crate::octree::{CellScalars, LodCriterion};
    use crate::{BatchLighting, CellOrder, FrameInputs, OctreeSettings, View};

    /// A 17 × 9 × 17 cloud over 16 × 4 × 16 in the wind.
    #[derive(Debug)]
    struct Wind(CloudNoise);

    impl AnimatedGrid for Wind {
        fn grid_at(&self, time: f64) -> Result<DensityGrid, FieldError> {
            let min = DVec3::new(-8.0, 0.0, -8.0);
            DensityGrid::cloud([17, 9, 17], DVec3::new(1.0, 0.5, 1.0), min, &self.0, time)
        }
    }

    fn recipe() -> KeyframeRecipe {
        KeyframeRecipe {
            source: KeyframeSource::Animated(Arc::new(Wind(CloudNoise {
                wavelength: 12.0,
                wind: DVec3::new(1.5, 0.0, 0.5),
                octaves: 3,
                ..CloudNoise::default()
            }))),
            settings: BatchSettings {
                order: CellOrder::BackToFront,
                octree: Some(OctreeSettings { min_accuracy: 2.0 }),
                lighting: Some(BatchLighting {
                    light: CloudLighting {
                        shadow_extinction: 0.5,
                        ..CloudLighting::default()
                    },
                    scalars: CellScalars::LightModulatedByDensity,
                }),
                ..BatchSettings::default()
            },
            interval: 2.0,
        }
    }

    fn sun() -> SunMotion {
        SunMotion::still(DVec3::new(0.4, 1.0, 0.3).normalize(), 0.0)
    }

    fn batch_of(batcher: &mut VolumeBatcher, blend: f32) -> Arc<crate::Cells> {
        let transfer = TransferFunction::preset(TransferPreset::CloudLight);
        let view = View::new(
            DAffine3::IDENTITY,
            DVec3::new(3.0, 9.0, 14.0),
            UVec2::new(160, 120),
        );
        let inputs = FrameInputs {
            transfer: &transfer,
            criterion: LodCriterion::distance(8.0),
            blend,
            blend_span: REFINEMENT_SPAN,
        };
        batcher.update(&view, &inputs).unwrap();
        batcher.batch().clone()
    }

    /// The blend rises with the clock and starts again at each hand-over;
    /// after five of them the drawn pair is exactly the full rebuild of its
    /// two keyframes at their times: nothing drifts, however long it runs.
    #[test]
    fn after_any_number_of_hand_overs_the_pair_is_the_full_rebuild_of_its_keyframes() {
        let recipe = recipe();
        // The first pair is (10 s, 12 s); the clock starts at 11 s.
        let mut track = KeyframeTrack::new(recipe.clone(), sun(), 11.0, LocalBuilds::Blocking);
        let mut blends = Vec::new();
        let mut builds = 0;
        // 0.3 s frames: the hand-overs fall between frames.
        for frame in 0..=35 {
            let now = 11.0 + 0.3 * f64::from(frame);
            builds += usize::from(
                track
                    .advance(now, LocalBuilds::Blocking, |_| true)
                    .unwrap()
                    .is_some(),
            );
            blends.push(track.blend());
        }
        assert!((track.clock() - 21.5).abs() < 1e-9, "{}", track.clock());
        assert!((blends[0] - 0.5).abs() < 1e-6);
        let hand_overs = blends.windows(2).filter(|w| w[1] < w[0]).count();
        assert_eq!(hand_overs, 5, "{blends:?}");
        // The first pair, one per hand-over and the one ahead of the drawn.
        assert_eq!(builds, 7);
        assert!(blends.iter().all(|b| (0.0..=1.0).contains(b)));
        let start = keyframe_time(track.drawn.as_ref().unwrap().index, 2.0);
        assert_eq!(start, 20.0);
        assert!((track.blend() - 0.75).abs() < 1e-6);

        let mut rebuilt = recipe
            .keyframe(start, &sun())
            .unwrap()
            .with_next_keyframe(&recipe.keyframe(start + 2.0, &sun()).unwrap())
            .unwrap();
        let blend = track.refinement_blend();
        assert_eq!(blend, 0.75);
        let drawn = batch_of(track.batcher_mut().unwrap(), blend);
        assert!(drawn.is_blended());
        assert_eq!(*drawn, *batch_of(&mut rebuilt, blend));
    }

    /// A build that has not landed holds the clock at the drawn pair's end:
    /// the wind slows down, the field does not step.
    #[test]
    fn the_clock_waits_for_a_late_pair() {
        let mut track = KeyframeTrack::new(recipe(), sun(), 0.0, LocalBuilds::Blocking);
        track.advance(0.0, LocalBuilds::Blocking, |_| true).unwrap();
        assert_eq!(track.blend(), 0.0);
        // The next pair is started but never polled to completion: the
        // background mode does not wait for it, and it is taken away here.
        track.build = None;
        track.advance(5.0, LocalBuilds::Deferred, |_| true).unwrap();
        assert_eq!(track.clock(), 2.0);
        assert_eq!(track.blend(), 1.0);
        assert!(track.build.is_some(), "the next pair is built again");
        // It lands: the clock goes on from where it waited.
        track.advance(6.0, LocalBuilds::Blocking, |_| true).unwrap();
        track.advance(6.5, LocalBuilds::Blocking, |_| true).unwrap();
        assert!((track.clock() - 3.5).abs() < 1e-9, "{}", track.clock());
        assert!((track.blend() - 0.75).abs() < 1e-6);
    }

    /// A refinement step whose successor is not made holds the clock at the
    /// step's end (never back); lifted, the clock goes on from there.
    #[test]
    fn the_clock_waits_at_the_end_of_a_step_whose_successor_is_not_made() {
        // Pairs of 2 s; the clock starts at 0.2 s (blend 0.1).
        let mut track = KeyframeTrack::new(recipe(), sun(), 0.2, LocalBuilds::Blocking);
        track.advance(0.2, LocalBuilds::Blocking, |_| true).unwrap();
        track.hold_at(Some(0.25));
        track.advance(1.2, LocalBuilds::Blocking, |_| true).unwrap();
        assert_eq!(track.clock(), 0.5);
        assert_eq!(track.blend(), 0.25);
        // A hold behind the clock does not move it back.
        track.hold_at(Some(0.125));
        track.advance(1.3, LocalBuilds::Blocking, |_| true).unwrap();
        assert_eq!(track.clock(), 0.5);
        track.hold_at(None);
        track.advance(1.5, LocalBuilds::Blocking, |_| true).unwrap();
        assert!((track.clock() - 0.7).abs() < 1e-9, "{}", track.clock());
    }

    /// A next pair that is built but not ready (its first batch not made)
    /// holds the clock at the drawn pair's end like a late one; once ready
    /// it takes over.
    #[test]
    fn the_next_pair_takes_over_once_ready() {
        let mut track = KeyframeTrack::new(recipe(), sun(), 0.0, LocalBuilds::Blocking);
        track.advance(0.0, LocalBuilds::Blocking, |_| true).unwrap();
        track.advance(1.0, LocalBuilds::Blocking, |_| true).unwrap();
        assert!(track.next.is_some(), "the next pair is built");
        track
            .advance(3.0, LocalBuilds::Blocking, |_| false)
            .unwrap();
        assert_eq!(track.clock(), 2.0);
        assert_eq!(track.pair_index(), Some(0));
        assert_eq!(track.blend(), 1.0);
        track.advance(3.5, LocalBuilds::Blocking, |_| true).unwrap();
        assert_eq!(track.pair_index(), Some(1));
        assert!((track.clock() - 2.5).abs() < 1e-9, "{}", track.clock());
        assert!((track.blend() - 0.25).abs() < 1e-6);
    }

    /// A sun turning at a constant rate is extrapolated exactly; a still or
    /// reversed one stands still; keyframes of a grid under it are lit by it.
    #[test]
    fn the_sun_is_extrapolated_at_its_rate() {
        let turn = |angle: f64| DQuat::from_rotation_z(angle) * DVec3::X;
        let motion = SunMotion::between(turn(0.1), 1.0, turn(0.15), 1.5);
        assert!((motion.rate - 0.1).abs() < 1e-12);
        for time in [1.5, 4.0, 10.0, -3.0] {
            let expected = turn(0.15 + 0.1 * (time - 1.5));
            assert!(motion.at(time).distance(expected) < 1e-12, "{time}");
        }
        assert_eq!(SunMotion::between(turn(0.1), 1.0, turn(0.1), 2.0).rate, 0.0);
        assert_eq!(SunMotion::between(turn(0.1), 1.0, turn(0.2), 1.0).rate, 0.0);
        let opposite = SunMotion::between(DVec3::X, 0.0, DVec3::NEG_X, 1.0);
        assert_eq!(opposite.at(5.0), DVec3::NEG_X, "no axis: still");

        // A still grid's keyframes differ by their sun alone.
        let KeyframeSource::Animated(cloud) = recipe().source else {
            unreachable!("an animated recipe")
        };
        let grid = Arc::new(cloud.grid_at(0.0).unwrap());
        let lit = KeyframeRecipe {
            source: KeyframeSource::Grid(grid.clone()),
            ..recipe()
        };
        let turning = SunMotion::between(turn(1.0), 0.0, turn(1.1), 1.0);
        let [mut early, mut late] = [0.0, 5.0].map(|t| lit.keyframe(t, &turning).unwrap());
        let (early, late) = (batch_of(&mut early, 0.0), batch_of(&mut late, 0.0));
        assert_ne!(early.tetrahedra, late.tetrahedra, "lit from elsewhere");
        // Lit by the sun at the keyframe's time.
        let mut settings = lit.settings;
        if let Some(lighting) = &mut settings.lighting {
            lighting.light.sun_direction = turn(1.5);
        }
        let mut expected = VolumeBatcher::new(VolumeSource::Grid(grid.clone()), &settings).unwrap();
        assert_eq!(late, batch_of(&mut expected, 0.0));
        // The sun's motion is not part of what the track is for.
        let mut moved = lit.clone();
        if let Some(lighting) = &mut moved.settings.lighting {
            lighting.light.sun_direction = DVec3::Z;
        }
        let track = KeyframeTrack::new(lit.clone(), turning, 0.0, LocalBuilds::Blocking);
        assert!(track.is_for(&moved));
        let other = KeyframeRecipe {
            source: KeyframeSource::Grid(Arc::new(cloud.grid_at(1.0).unwrap())),
            ..lit
        };
        assert!(!track.is_for(&other), "another grid");
    }
}
