//! A cloud layer in the wind drawn between keyframes (`octree::keyframe`):
//! what a keyframe costs on one core, what a frame costs, and how the blend
//! looks, on the CPU without a GPU.
//!
//! - Cost, the paper's 513 × 65 × 513 layer (the field of
//!   `assets/scenes/cloud_flythrough.ron`, in a wind of 10 m/s): one
//!   keyframe's grid generation, light field with the shadow sweep and
//!   hierarchy, each on one thread, and the pair's hierarchy; the same
//!   keyframe as the renderer builds it (the grid, then
//!   `VolumeBatcher::new`, on one thread as a paced build); then, for a
//!   still camera at the flight's start (640 × 400, the default screen
//!   error 0.1), the pair's batch (refinement and emission of both
//!   keyframes, the work of each refinement step; the fastest of three runs,
//!   as a step reuses the memory the last one freed) against a single
//!   keyframe's. The mean cost per frame at 60 frames per second for an
//!   interval `T` is `(keyframe + REFINEMENT_STEPS · step) / (60 T)`; the
//!   bench prints the `T` that makes it 2 ms.
//! - Images, the same layer at 129 × 17 × 129 points seen across from its
//!   edge (the view of `lod_criteria`'s `cloud_layer_129`), the default
//!   screen error, exact CPU cell reference at 320 × 200, for keyframe
//!   intervals of 2, 8 and 32 s: the largest per-pixel change between two
//!   consecutive frames at 60 frames per second inside a refinement step
//!   (β = 1/2 and 1/2 + 1/(60 T), the same cells), across one (the octree
//!   refined for the span of blends a step of 1/`REFINEMENT_STEPS` later,
//!   taking over at its start; half way and at a pair's first step; and the
//!   two refinements at the very blend where one takes over) and across a
//!   hand-over (the last step of one pair, the first of the next), and the
//!   error of the blend half way against a full rebuild at that time. For scale, the
//!   largest change between two frames of a single keyframe over 32 frames
//!   of a camera flying toward the layer at 100 m/s (1.7 m per frame), which
//!   is what the octree's refinement changes between frames of a moving
//!   camera anyway.
//!
//! Writes `target/nebel/wind_keyframes.csv`. Run: `cargo bench -p nebel_lod
//! --bench wind_keyframes` (about a minute and a half here).

use std::rc::Rc;
use std::sync::Arc;
use std::time::Instant;

use glam::DVec3;
use nebel_core::field::{
    CloudLighting, CloudNoise, CloudShape, DensityGrid, light_field_with_threads,
};
use nebel_core::pacing::with_pacer;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_lod::octree::keyframe::{REFINEMENT_SPAN, REFINEMENT_STEPS};
use nebel_lod::octree::{CellScalars, LodCriterion, RefinementSettings, lod_batch_with, refine};
use nebel_lod::{
    BatchLighting, BatchSettings, Cells, OctreeSettings, View, VolumeBatcher, VolumeHierarchy,
    VolumeSource,
};
use nebel_reference::image_metrics::{LinearImage, compare};

mod support;

/// The wind of the first octave, m/s; finer octaves 1.5 times faster each.
const WIND: DVec3 = DVec3::new(10.0, 0.0, 4.0);

/// The layer of `cloud_flythrough.ron` at `dims` points with `octaves`.
fn noise(octaves: usize) -> CloudNoise {
    CloudNoise {
        seed: 11,
        coverage: 0.42,
        octaves,
        wavelength: 1800.0,
        wind: WIND,
        ..CloudNoise::default()
    }
}

fn lighting(shadow_extinction: f32) -> CloudLighting {
    CloudLighting {
        ambient: 0.2,
        diffuse: 0.8,
        sun_direction: DVec3::new(0.45, 0.6, 0.3),
        shadow_extinction,
        lambert: true,
        ..CloudLighting::default()
    }
}

fn transfer() -> TransferFunction {
    TransferFunction::preset(TransferPreset::CloudLight)
        .scale_density(0.03)
        .expect("a finite scale")
}

fn elapsed_ms(started: Instant) -> f64 {
    started.elapsed().as_secs_f64() * 1e3
}

/// A keyframe at `time` on one thread, and the times of its grid, light
/// field and hierarchy (ms).
fn keyframe(
    dims: [usize; 3],
    octaves: usize,
    shadow_extinction: f32,
    time: f64,
) -> (VolumeHierarchy, [f64; 3]) {
    let spacing = DVec3::splat(5120.0 / (dims[0] - 1) as f64);
    let origin = DVec3::new(-2560.0, 600.0, -2560.0);
    let started = Instant::now();
    let shape = CloudShape::default();
    let grid =
        DensityGrid::cloud_with_threads(dims, spacing, origin, &noise(octaves), &shape, time, 1)
            .expect("valid cloud");
    let grid_ms = elapsed_ms(started);
    let started = Instant::now();
    let light =
        light_field_with_threads(&grid, &lighting(shadow_extinction), 1).expect("valid light");
    let light_ms = elapsed_ms(started);
    let started = Instant::now();
    let hierarchy = VolumeHierarchy::with_light(&grid, &light, 4.0).expect("2^n+1 grid");
    (hierarchy, [grid_ms, light_ms, elapsed_ms(started)])
}

/// What the renderer does for a keyframe on one thread, in ms: the grid at
/// time 0, then the lit octree batcher built from it (`VolumeBatcher::new`,
/// the light field and hierarchy with whatever else it does).
fn renderer_keyframe_ms(dims: [usize; 3], octaves: usize, shadow_extinction: f32) -> f64 {
    let spacing = DVec3::splat(5120.0 / (dims[0] - 1) as f64);
    let origin = DVec3::new(-2560.0, 600.0, -2560.0);
    let settings = BatchSettings {
        octree: Some(OctreeSettings::default()),
        lighting: Some(BatchLighting {
            light: lighting(shadow_extinction),
            scalars: CellScalars::LightModulatedByDensity,
        }),
        ..BatchSettings::default()
    };
    // One thread, as a paced build runs.
    let single_threaded: Rc<dyn Fn()> = Rc::new(|| {});
    with_pacer(single_threaded, || {
        let started = Instant::now();
        let grid =
            DensityGrid::cloud(dims, spacing, origin, &noise(octaves), 0.0).expect("valid cloud");
        let batcher = VolumeBatcher::new(VolumeSource::Grid(Arc::new(grid)), &settings)
            .expect("valid batcher");
        let ms = elapsed_ms(started);
        drop(batcher);
        ms
    })
}

/// The lit batch of `hierarchy` for `view` at the default screen error,
/// refined for the keyframe blends from `blend` on (`REFINEMENT_SPAN`, as the
/// renderer's steps), and its time (ms).
fn batch(
    hierarchy: &VolumeHierarchy,
    view: &View,
    transfer: &TransferFunction,
    blend: f32,
) -> (Cells, f64) {
    let (batch, [refine_ms, emit_ms]) = timed_batch(hierarchy, view, transfer, blend);
    (batch, refine_ms + emit_ms)
}

/// [`batch`] and the times of its refinement and its emission (ms).
fn timed_batch(
    hierarchy: &VolumeHierarchy,
    view: &View,
    transfer: &TransferFunction,
    blend: f32,
) -> (Cells, [f64; 2]) {
    let scalars = CellScalars::LightModulatedByDensity;
    let settings = RefinementSettings {
        criterion: LodCriterion::default(),
        scalars,
        blend,
        blend_span: REFINEMENT_SPAN,
    };
    let started = Instant::now();
    let refinement = refine(hierarchy, view, transfer, &settings).expect("valid settings");
    let refine_ms = elapsed_ms(started);
    let started = Instant::now();
    let batch = lod_batch_with(hierarchy, &refinement, view, scalars).expect("valid view");
    (batch, [refine_ms, elapsed_ms(started)])
}

fn main() {
    let mut csv = String::from("measure,interval_s,value\n");
    let transfer = transfer();

    // Cost on the 513 layer.
    let dims = [513, 65, 513];
    let (first, first_ms) = keyframe(dims, 6, 0.02, 0.0);
    let (second, second_ms) = keyframe(dims, 6, 0.02, 8.0);
    let started = Instant::now();
    let pair = first
        .with_next_keyframe(&second)
        .expect("matching keyframes");
    let pair_ms = elapsed_ms(started);
    let keyframe_ms = first_ms.iter().sum::<f64>().max(second_ms.iter().sum()) + pair_ms;
    let (eye, target) = (
        DVec3::new(-3600.0, 1700.0, -1800.0),
        DVec3::new(0.0, 900.0, 0.0),
    );
    let (still, _) = support::view(eye, target, [640, 400]);
    // Each the fastest of three runs: a refinement step reuses the memory
    // the last one freed, the first run pays for fresh pages.
    let fastest = |hierarchy: &VolumeHierarchy, blend: f32| {
        let runs = [0; 3].map(|_| timed_batch(hierarchy, &still, &transfer, blend));
        let [refine_ms, emit_ms] = [0, 1].map(|i| {
            runs.iter()
                .map(|(_, times)| times[i])
                .fold(f64::INFINITY, f64::min)
        });
        let [(batch, _), ..] = runs;
        (batch, [refine_ms, emit_ms])
    };
    let (single, single_times) = fastest(&first, 0.0);
    let single_ms = single_times[0] + single_times[1];
    let (blended, [step_refine_ms, step_emit_ms]) = fastest(&pair, 0.5);
    let step_ms = step_refine_ms + step_emit_ms;
    println!(
        "513 layer, one keyframe on one thread: grid {:.0} ms, light field {:.0} ms, hierarchy {:.0} ms; the pair's hierarchy {pair_ms:.0} ms; {keyframe_ms:.0} ms a keyframe",
        first_ms[0], first_ms[1], first_ms[2]
    );
    println!(
        "still camera: a keyframe's batch {single_ms:.1} ms ({} cells), the pair's {step_ms:.1} ms ({} cells, both keyframes; once per refinement step: refinement {step_refine_ms:.1} ms, emission {step_emit_ms:.1} ms), {:.1} bytes per grid point",
        single.len(),
        blended.len(),
        pair.bytes_per_point()
    );
    // Per interval: one keyframe and the refinement steps.
    let per_interval = keyframe_ms + f64::from(REFINEMENT_STEPS) * step_ms;
    let per_frame = |interval: f64| per_interval / (60.0 * interval);
    let interval_for_2ms = per_interval / (60.0 * 2.0);
    println!(
        "mean per frame at 60 fps: {:.2} ms at T = 8 s, {:.2} ms at T = 32 s; 2 ms needs T = {interval_for_2ms:.1} s",
        per_frame(8.0),
        per_frame(32.0)
    );
    for (measure, value) in [
        ("grid_ms", first_ms[0]),
        ("light_ms", first_ms[1]),
        ("hierarchy_ms", first_ms[2]),
        ("pair_ms", pair_ms),
        ("keyframe_batch_ms", single_ms),
        ("pair_batch_ms", step_ms),
        ("interval_for_2ms_s", interval_for_2ms),
    ] {
        csv.push_str(&format!("{measure},,{value}\n"));
    }
    drop((first, second, pair));
    let renderer_ms = renderer_keyframe_ms(dims, 6, 0.02);
    println!(
        "the renderer's keyframe on one thread (the grid, then `VolumeBatcher::new`): {renderer_ms:.0} ms"
    );
    csv.push_str(&format!("renderer_keyframe_ms,,{renderer_ms}\n"));

    // Images on the 129 layer.
    let dims = [129, 17, 129];
    let (eye, target) = (
        DVec3::new(-3300.0, 1000.0, -900.0),
        DVec3::new(0.0, 850.0, 300.0),
    );
    let (view, camera) = support::view(eye, target, [320, 200]);
    let (still_keyframe, _) = keyframe(dims, 4, 0.008, 0.0);
    // 32 frames of a flight toward the layer at 100 m/s, 60 frames per second.
    let flight: Vec<LinearImage> = (0..=32)
        .map(|frame| {
            let eye = eye + (target - eye).normalize() * (100.0 / 60.0 * f64::from(frame));
            let (view, camera) = support::view(eye, target, [320, 200]);
            support::image(
                &batch(&still_keyframe, &view, &transfer, 0.0).0,
                camera,
                &transfer,
            )
        })
        .collect();
    let flying = flight
        .windows(2)
        .map(|pair| compare(&pair[1], &pair[0]).expect("same size").max_abs)
        .collect::<Vec<_>>();
    let flying_max = flying.iter().copied().fold(0.0, f64::max);
    let mut sorted = flying.clone();
    sorted.sort_by(f64::total_cmp);
    println!(
        "129 layer, one keyframe, camera flying 1.7 m per frame: largest change between frames {flying_max:.2e} over 32 frames (median frame {:.2e})",
        sorted[sorted.len() / 2]
    );
    csv.push_str(&format!("flying_frame_change_max,,{flying_max}\n"));
    for interval in [2.0, 8.0, 32.0] {
        let [(a, _), (b, _), (c, _)] =
            [0.0, interval, 2.0 * interval].map(|t| keyframe(dims, 4, 0.008, t));
        let (mid, _) = keyframe(dims, 4, 0.008, interval / 2.0);
        let [first_pair, next_pair] = [(&a, &b), (&b, &c)]
            .map(|(k, next)| k.with_next_keyframe(next).expect("matching keyframes"));
        // The image of `pair` refined for `refined` and drawn at `blend`.
        let at = |pair: &VolumeHierarchy, refined: f32, blend: f32| {
            let (cells, _) = batch(pair, &view, &transfer, refined);
            support::image(&cells.blended(blend), camera, &transfer)
        };
        let frame = (1.0 / (60.0 * interval)) as f32;
        let steps = REFINEMENT_STEPS as f32;
        // Two frames inside a refinement step, and two across one.
        let (half, step_before) = (0.5, 0.5 - 1.0 / steps);
        let half_image = at(&first_pair, half, half);
        let inside = compare(&at(&first_pair, half, half + frame), &half_image).expect("same size");
        let across =
            compare(&at(&first_pair, step_before, half - frame), &half_image).expect("same size");
        // The two refinements at the blend where one takes over from the
        // other: what the switch itself changes.
        let boundary =
            compare(&at(&first_pair, step_before, half), &half_image).expect("same size");
        // Across the first step of a pair, where clouds that form between
        // its keyframes start to be drawn.
        let first_step = compare(
            &at(&next_pair, 1.0 / steps, 1.0 / steps),
            &at(&next_pair, 0.0, 1.0 / steps - frame),
        )
        .expect("same size");
        let hand_over = compare(
            &at(&next_pair, 0.0, 0.0),
            &at(&first_pair, 1.0 - 1.0 / steps, 1.0 - frame),
        )
        .expect("same size");
        let rebuilt = support::image(&batch(&mid, &view, &transfer, 0.0).0, camera, &transfer);
        let error = compare(&half_image, &rebuilt).expect("same size");
        println!(
            "129 layer, T = {interval} s: largest change between frames {:.2e} inside a refinement step, {:.2e} across one ({:.2e} at the switch itself; {:.2e} across a pair's first), {:.2e} at a hand-over; half way RMSE {:.2e} (largest {:.2e}) against a rebuild then",
            inside.max_abs,
            across.max_abs,
            boundary.max_abs,
            first_step.max_abs,
            hand_over.max_abs,
            error.rmse,
            error.max_abs
        );
        for (measure, value) in [
            ("frame_change_max", inside.max_abs),
            ("refinement_step_change_max", across.max_abs),
            ("refinement_switch_change_max", boundary.max_abs),
            ("first_step_change_max", first_step.max_abs),
            ("hand_over_change_max", hand_over.max_abs),
            ("half_way_rmse", error.rmse),
            ("half_way_max", error.max_abs),
        ] {
            csv.push_str(&format!("{measure},{interval},{value}\n"));
        }
    }

    let out = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/nebel");
    std::fs::create_dir_all(&out).expect("target/nebel is writable");
    std::fs::write(out.join("wind_keyframes.csv"), csv).expect("CSV written");
    println!("wrote {}", out.join("wind_keyframes.csv").display());
}
