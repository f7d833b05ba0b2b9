//! The soak flight, `nebel soak`: a scene flown headless for many frames
//! along a seeded random path, every frame checked for non-finite values.
//!
//! The path visits waypoints drawn uniformly (from `seed`) in the box
//! around everything the scene draws as cells (the union of the cell
//! batches' bounds after the first frame, grown by a tenth on every side),
//! so it enters and leaves the volumes, the fog and the layers; the camera
//! moves a 400th of the box's diagonal per frame and looks along the path.
//! Every frame:
//!
//! - every `CellBatch` in the world is read: a vertex with a NaN or
//!   infinite position or scalar counts as a non-finite cell;
//! - the frame is read back from its render target, an `Rgba16Float` image
//!   (so a NaN or infinity the HDR passes produced survives to the check),
//!   and every channel is checked;
//! - whether the eye is inside a batch's bounds is counted, so the report
//!   says how often the path entered the volumes.
//!
//! The report (JSON) has the counts, the frames whose read-back came back,
//! the frame times and the process's resident memory (`VmRSS` of
//! `/proc/self/status`, KiB; absent where there is no such file) at frame
//! 1, every 1,000th and the last, with its growth per frame after the
//! warm-up (from frame 1,000 on).

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use bevy::prelude::*;
use bevy::render::render_resource::TextureFormat;
use bevy::render::view::screenshot::{Screenshot, ScreenshotCaptured};
use nebel_render::{CellBatch, HeavyBuilds};
use serde::Serialize;

use crate::headless::{HeadlessApp, HeadlessError, HeadlessOptions};
use crate::scene_setup::{SceneCamera, SceneSetupPlugin};
use crate::stats::{AdapterSummary, TimeSummary};

/// What one soak flight found.
#[derive(Clone, Debug, Serialize)]
pub struct SoakReport {
    /// What it rendered on.
    pub adapter: AdapterSummary,
    /// Frames flown.
    pub frames: u32,
    /// The path's seed.
    pub seed: u64,
    /// Cells with a non-finite vertex, summed over every frame.
    pub non_finite_cells: u64,
    /// Frames with at least one such cell.
    pub frames_with_non_finite_cells: u32,
    /// Channels of the read-back frames that were NaN or infinite.
    pub non_finite_channels: u64,
    /// Read-back frames with at least one such channel.
    pub frames_with_non_finite_channels: u32,
    /// Frames whose read-back came back and was checked.
    pub frames_read_back: u32,
    /// The most cells in the world in one frame.
    pub max_cells: u64,
    /// Frames with the eye inside a batch's bounds.
    pub frames_inside_volumes: u32,
    /// Times the eye went from outside every batch's bounds to inside one.
    pub entries_into_volumes: u32,
    /// Frame wall times, ms.
    pub frame_wall_ms: TimeSummary,
    /// Resident memory in KiB at frame 1, every 1,000th frame and the last,
    /// by frame number.
    pub memory_kib: BTreeMap<u32, u64>,
    /// Growth of the resident memory per frame after the warm-up, from
    /// frame 1,000 to the last, KiB; `None` for a flight of 1,000 frames or
    /// fewer.
    pub growth_kib_per_frame: Option<f64>,
}

impl SoakReport {
    /// Whether the flight found nothing non-finite.
    pub fn is_clean(&self) -> bool {
        self.non_finite_cells == 0 && self.non_finite_channels == 0
    }
}

/// The read-back counters, filled by the screenshot observers.
#[derive(Default)]
struct ReadBacks {
    frames: u32,
    non_finite: u64,
    frames_with_non_finite: u32,
}

/// The process's resident memory, KiB, where `/proc/self/status` says it.
fn resident_kib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|line| line.starts_with("VmRSS:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// NaN and infinite channels of an `Rgba16Float` image's bytes: half floats
/// whose exponent bits are all ones.
fn non_finite_halves(bytes: &[u8]) -> u64 {
    bytes
        .chunks_exact(2)
        .filter(|half| u16::from_le_bytes([half[0], half[1]]) & 0x7c00 == 0x7c00)
        .count() as u64
}

/// A seeded random path through `bounds`, as a polyline of waypoints from
/// `start`.
struct SoakPath {
    waypoints: Vec<Vec3>,
    /// The length of one round through the waypoints.
    length: f32,
    step: f32,
}

impl SoakPath {
    fn new(start: Vec3, bounds: (Vec3, Vec3), seed: u64) -> Self {
        let (min, max) = bounds;
        let mut state = seed ^ 0x0005_0ac0_ffee;
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut waypoints = vec![start];
        waypoints.extend((0..64).map(|_| min + (max - min) * Vec3::new(next(), next(), next())));
        let length = (0..waypoints.len())
            .map(|k| waypoints[k].distance(waypoints[(k + 1) % waypoints.len()]))
            .sum();
        Self {
            waypoints,
            length,
            step: (max - min).length() / 400.0,
        }
    }

    /// The point `distance` along the path, which runs through its
    /// waypoints and back to the first, again and again.
    fn at(&self, distance: f32) -> Vec3 {
        let count = self.waypoints.len();
        let segment = |k: usize| (self.waypoints[k], self.waypoints[(k + 1) % count]);
        if self.length.is_nan() || self.length <= 0.0 {
            return self.waypoints[0];
        }
        let mut left = distance.rem_euclid(self.length);
        for k in 0..count {
            let (a, b) = segment(k);
            let length = a.distance(b);
            if left <= length && length > 0.0 {
                return a.lerp(b, left / length);
            }
            left -= length;
        }
        self.waypoints[0]
    }
}

/// The union of every cell batch's bounds, grown by a tenth on every side.
fn batch_bounds(world: &mut World) -> Option<(Vec3, Vec3)> {
    let mut batches = world.query::<&CellBatch>();
    let (min, max) = batches
        .iter(world)
        .filter(|batch| !batch.cells.is_empty())
        .fold(None, |bounds: Option<(Vec3, Vec3)>, batch| {
            let (lo, hi) = (batch.cells.bounds_min, batch.cells.bounds_max);
            Some(bounds.map_or((lo, hi), |(min, max)| (min.min(lo), max.max(hi))))
        })?;
    let margin = (max - min) * 0.1;
    Some((min - margin, max + margin))
}

/// Flies `setup`'s scene for `frames` frames along the path of `seed` (see
/// the module docs).
pub fn soak(
    setup: SceneSetupPlugin,
    frames: u32,
    seed: u64,
    progress: bool,
) -> Result<SoakReport, HeadlessError> {
    let output = setup.scene.output.clone();
    let options = HeadlessOptions {
        progress,
        ..HeadlessOptions::default()
    };
    let mut headless = HeadlessApp::new(&output, options, TextureFormat::Rgba16Float, |app| {
        app.add_plugins(setup);
    })?;
    headless.start_time(&output);
    let world = headless.app.world_mut();
    let mut cameras = world.query::<(&mut SceneCamera, &Transform)>();
    let start = cameras
        .iter_mut(world)
        .next()
        .map_or(Vec3::ZERO, |(mut camera, transform)| {
            camera.follows_path = false;
            transform.translation
        });
    let bounds = batch_bounds(world).unwrap_or((start - 100.0, start + 100.0));
    let path = SoakPath::new(start, bounds, seed);

    let read_backs: Arc<Mutex<ReadBacks>> = Arc::default();
    let mut report = SoakReport {
        adapter: headless.adapter(),
        frames,
        seed,
        non_finite_cells: 0,
        frames_with_non_finite_cells: 0,
        non_finite_channels: 0,
        frames_with_non_finite_channels: 0,
        frames_read_back: 0,
        max_cells: 0,
        frames_inside_volumes: 0,
        entries_into_volumes: 0,
        frame_wall_ms: TimeSummary::default(),
        memory_kib: BTreeMap::new(),
        growth_kib_per_frame: None,
    };
    let mut frame_times = Vec::with_capacity(frames as usize);
    let mut was_inside = false;
    let bar = crate::progress::bar(progress, "frame", u64::from(frames));
    for frame in 1..=frames {
        let world = headless.app.world_mut();
        let distance = frame as f32 * path.step;
        let (eye, ahead) = (path.at(distance), path.at(distance + 5.0 * path.step));
        let mut cameras = world.query_filtered::<&mut Transform, With<SceneCamera>>();
        for mut transform in cameras.iter_mut(world) {
            *transform = Transform::from_translation(eye).looking_at(ahead, Vec3::Y);
        }
        let slot = read_backs.clone();
        world
            .spawn(Screenshot::image(headless.target.clone()))
            .observe(move |capture: On<ScreenshotCaptured>| {
                let bad = capture.image.data.as_deref().map_or(0, non_finite_halves);
                let mut counts = slot.lock().expect("read-back counters");
                counts.frames += 1;
                counts.non_finite += bad;
                counts.frames_with_non_finite += u32::from(bad > 0);
            });
        let started = Instant::now();
        headless.update();
        frame_times.push(started.elapsed());

        let world = headless.app.world_mut();
        let mut batches = world.query::<&CellBatch>();
        let (mut cells, mut bad, mut inside) = (0u64, 0u64, false);
        for batch in batches.iter(world) {
            cells += batch.cells.len() as u64;
            bad += batch
                .cells
                .tetrahedra
                .iter()
                .filter(|cell| cell.vertices.iter().flatten().any(|c| !c.is_finite()))
                .count() as u64;
            let (lo, hi) = (batch.cells.bounds_min, batch.cells.bounds_max);
            inside |= !batch.cells.is_empty() && eye.cmpge(lo).all() && eye.cmple(hi).all();
        }
        report.max_cells = report.max_cells.max(cells);
        report.non_finite_cells += bad;
        report.frames_with_non_finite_cells += u32::from(bad > 0);
        report.frames_inside_volumes += u32::from(inside);
        report.entries_into_volumes += u32::from(inside && !was_inside);
        was_inside = inside;
        if (frame == 1 || frame % 1000 == 0 || frame == frames)
            && let Some(kib) = resident_kib()
        {
            report.memory_kib.insert(frame, kib);
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    // Let the last read-backs come back.
    headless.app.insert_resource(HeavyBuilds::Blocking);
    for _ in 0..8 {
        if read_backs.lock().expect("read-back counters").frames >= frames {
            break;
        }
        headless.update();
    }
    let counts = read_backs.lock().expect("read-back counters");
    report.frames_read_back = counts.frames;
    report.non_finite_channels = counts.non_finite;
    report.frames_with_non_finite_channels = counts.frames_with_non_finite;
    report.frame_wall_ms = TimeSummary::of(&frame_times);
    report.growth_kib_per_frame = growth_after_warm_up(&report.memory_kib);
    Ok(report)
}

/// The growth per frame from frame 1,000 to the last sample of `memory`
/// (KiB by frame), `None` without samples on both sides.
fn growth_after_warm_up(memory: &BTreeMap<u32, u64>) -> Option<f64> {
    const WARM_UP: u32 = 1000;
    let start = *memory.get(&WARM_UP)?;
    let (&last, &end) = memory.last_key_value()?;
    (last > WARM_UP).then(|| (end as f64 - start as f64) / f64::from(last - WARM_UP))
}

/// Writes `report` as pretty JSON to `out`.
pub fn write_report(report: &SoakReport, out: &Path) -> std::io::Result<()> {
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)?;
    }
    let text = serde_json::to_string_pretty(report).map_err(std::io::Error::other)?;
    std::fs::write(out, text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_path_is_seeded_inside_its_bounds_and_continuous() {
        let bounds = (Vec3::new(-100.0, 0.0, -50.0), Vec3::new(100.0, 40.0, 50.0));
        let a = SoakPath::new(Vec3::ZERO, bounds, 7);
        let b = SoakPath::new(Vec3::ZERO, bounds, 7);
        let c = SoakPath::new(Vec3::ZERO, bounds, 8);
        assert_eq!(a.waypoints, b.waypoints);
        assert_ne!(a.waypoints, c.waypoints);
        let mut previous = a.at(0.0);
        assert_eq!(previous, Vec3::ZERO);
        for k in 1..5000 {
            let point = a.at(k as f32 * a.step);
            assert!(
                point.cmpge(bounds.0).all() && point.cmple(bounds.1).all(),
                "{point}"
            );
            assert!(point.distance(previous) <= a.step * 1.001, "a jump at {k}");
            previous = point;
        }
    }

    #[test]
    fn non_finite_halves_are_counted() {
        let halves: Vec<u8> = [0x3c00u16, 0x7c00, 0xfc00, 0x7e00, 0x0001, 0x7bff]
            .iter()
            .flat_map(|h| h.to_le_bytes())
            .collect();
        // 1.0, +inf, −inf, NaN, the smallest subnormal, the largest finite.
        assert_eq!(non_finite_halves(&halves), 3);
    }

    #[test]
    fn the_growth_is_measured_after_the_warm_up() {
        let memory = BTreeMap::from([(1, 100), (1000, 400), (2000, 500), (3000, 700)]);
        assert_eq!(growth_after_warm_up(&memory), Some(0.15));
        // Shrinking counts as negative growth.
        let memory = BTreeMap::from([(1000, 400), (2000, 300)]);
        assert_eq!(growth_after_warm_up(&memory), Some(-0.1));
        // Not past the warm-up: nothing to say.
        assert_eq!(
            growth_after_warm_up(&BTreeMap::from([(1, 100), (1000, 400)])),
            None
        );
        assert_eq!(
            growth_after_warm_up(&BTreeMap::from([(1, 100), (40, 400)])),
            None
        );
    }

    #[test]
    fn resident_memory_is_read_where_the_system_reports_it() {
        if Path::new("/proc/self/status").exists() {
            assert!(resident_kib().is_some_and(|kib| kib > 0));
        }
    }
}
