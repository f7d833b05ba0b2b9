//! Cost of building the volume C-LOD hierarchy (`VolumeHierarchy::new`: u8
//! quantisation, Δ with `K_max` propagation and the scalar ranges of every node)
//! for a 129³ fBm field and for the paper's 513 × 513 × 65 cumulus-like fBm
//! field (a forest of 8 × 8 × 1 roots of 65³ points, 17.1 million points).
//!
//! Criterion reports the throughput in grid points per second ("elem/s").
//!
//! `octree_refine`: one per-frame refinement (`refine`, no morphing, no
//! emission) of the 513 × 513 × 65 field under the paper's cloud transfer
//! function for c in {1, 4, 16, 64}, eye outside (above a corner, about one
//! field width away, looking at the field) and inside (in the middle of the
//! slab). The leaf counts are printed once per case.
//!
//! `octree_emit`: the emission of one refinement as a morphed, back-to-front
//! cell batch (`lod_batch`, refinement done beforehand) of the same field,
//! eye inside, for c in {16, 64}. Criterion's "elem/s" is cells per second
//! (divide by 1000 for cells per ms); the cell counts are printed once per
//! case.
//!
//! `octree_refresh`: how often a moving camera's batch is refined again
//! (`octree::refresh`: after half a voxel or a turn out of the widened
//! frustum), along 240 frames of a camera inside the 513 × 513 × 65 field
//! flying at 0.01 to 1 voxel a frame and turning 0.05° a frame, under the
//! default screen error at 1920 × 1080 (`VolumeBatcher::update` on one
//! thread): the refinements (before the thresholds, every frame the camera
//! moved refined) and the mean time per frame, printed once per speed.
//!
//! Run: `cargo bench -p nebel_lod --bench octree`.

use std::hint::black_box;
use std::sync::Arc;
use std::time::Instant;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::{DAffine3, DMat4, DQuat, DVec3, UVec2};
use nebel_core::field::{DensityGrid, ProceduralNoise};
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_lod::octree::{LodCriterion, RefinementSettings, lod_batch, refine};
use nebel_lod::{
    BatchSettings, FrameInputs, OctreeSettings, View, VolumeBatcher, VolumeHierarchy, VolumeSource,
};

/// Minimum accuracy C of the benches (`K_max` ≈ 0.638).
const MIN_ACCURACY: f64 = 2.0;

/// The views' render target, pixels (read only for being non-empty).
const VIEWPORT: UVec2 = UVec2::new(1920, 1080);

/// The benches' fBm field: one world unit per grid point, the first octave
/// spans 128 points, six octaves down to 4 points, like the paper's cumulus
/// field.
fn fbm_grid(dims: [usize; 3]) -> DensityGrid {
    let noise = ProceduralNoise {
        seed: 5,
        octaves: 6,
        frequency: 1.0 / 128.0,
        ..Default::default()
    };
    DensityGrid::procedural(dims, DVec3::ONE, DVec3::ZERO, &noise).expect("valid grid")
}

fn octree_build(c: &mut Criterion) {
    let mut group = c.benchmark_group("octree_build");
    group.sample_size(10);
    for dims in [[129, 129, 129], [513, 513, 65]] {
        let grid = fbm_grid(dims);
        group.throughput(Throughput::Elements(grid.values().len() as u64));
        let name = format!("{}x{}x{}", dims[0], dims[1], dims[2]);
        group.bench_function(name, |b| {
            b.iter(|| VolumeHierarchy::new(black_box(&grid), MIN_ACCURACY).expect("2^n+1 grid"));
        });
    }
    group.finish();
}

fn octree_refine(c: &mut Criterion) {
    let hierarchy =
        VolumeHierarchy::new(&fbm_grid([513, 513, 65]), MIN_ACCURACY).expect("2^n+1 grid");
    let transfer = TransferFunction::preset(TransferPreset::Cloud);
    let eyes = [
        ("outside", DVec3::new(-256.0, -256.0, 512.0)),
        ("inside", DVec3::new(256.0, 256.0, 32.0)),
    ];
    let mut group = c.benchmark_group("octree_refine");
    group.sample_size(20);
    for (place, eye) in eyes {
        let view = View::new(DAffine3::IDENTITY, eye, VIEWPORT);
        for accuracy in [1.0, 4.0, 16.0, 64.0] {
            let settings = RefinementSettings::new(LodCriterion::distance(accuracy));
            let run = || {
                refine(black_box(&hierarchy), &view, &transfer, &settings).expect("valid settings")
            };
            let stats = run().stats;
            println!(
                "octree_refine {place} c={accuracy}: {} leaves ({} tetrahedra, {} voxels), {} nodes visited, {} culled transparent",
                stats.leaves,
                6 * stats.leaves,
                stats.full_resolution_leaves,
                stats.nodes_visited,
                stats.culled_transparent
            );
            group.bench_function(format!("{place}/c={accuracy}"), |b| b.iter(run));
        }
    }
    group.finish();
}

fn octree_emit(c: &mut Criterion) {
    let hierarchy =
        VolumeHierarchy::new(&fbm_grid([513, 513, 65]), MIN_ACCURACY).expect("2^n+1 grid");
    let transfer = TransferFunction::preset(TransferPreset::Cloud);
    let view = View::new(DAffine3::IDENTITY, DVec3::new(256.0, 256.0, 32.0), VIEWPORT);
    let mut group = c.benchmark_group("octree_emit");
    group.sample_size(20);
    for accuracy in [16.0, 64.0] {
        let refinement = refine(
            &hierarchy,
            &view,
            &transfer,
            &RefinementSettings::new(LodCriterion::distance(accuracy)),
        )
        .expect("valid settings");
        let run = || {
            lod_batch(black_box(&hierarchy), black_box(&refinement), &view)
                .expect("valid transform and eye")
        };
        let cells = run().len();
        println!(
            "octree_emit inside c={accuracy}: {cells} cells from {} leaves, {} refined nodes",
            refinement.leaves.len(),
            refinement.refined.len()
        );
        group.throughput(Throughput::Elements(cells as u64));
        group.bench_function(format!("inside/c={accuracy}"), |b| b.iter(run));
    }
    group.finish();
}

fn octree_refresh(_: &mut Criterion) {
    let grid = Arc::new(fbm_grid([513, 513, 65]));
    let settings = BatchSettings {
        octree: Some(OctreeSettings {
            min_accuracy: MIN_ACCURACY,
        }),
        ..BatchSettings::default()
    };
    let transfer = TransferFunction::preset(TransferPreset::Cloud);
    let inputs = FrameInputs {
        transfer: &transfer,
        criterion: LodCriterion::default(),
        blend: 0.0,
        blend_span: 0.0,
    };
    const FRAMES: u32 = 240;
    for speed in [0.01, 0.1, 0.3, 1.0] {
        // Inside the slab, flying diagonally and turning left.
        let view = |frame: u32| {
            let eye = DVec3::new(100.0, 100.0, 32.0)
                + DVec3::new(1.0, 1.0, 0.0).normalize() * speed * f64::from(frame);
            let turn = DQuat::from_rotation_z((0.05 * f64::from(frame)).to_radians());
            let forward = turn * DVec3::new(1.0, 0.6, -0.1);
            let clip_from_world = DMat4::perspective_infinite_reverse_rh(1.0, 16.0 / 9.0, 0.1)
                * DMat4::look_to_rh(eye, forward, DVec3::Z);
            View::new(DAffine3::IDENTITY, eye, VIEWPORT).with_projection(clip_from_world)
        };
        let source = VolumeSource::Grid(grid.clone());
        let mut batcher = VolumeBatcher::new(source, &settings).expect("valid settings");
        let started = Instant::now();
        let refinements = (0..FRAMES)
            .filter(|frame| batcher.update(&view(*frame), &inputs).expect("valid view"))
            .count();
        println!(
            "octree_refresh {speed} voxels a frame: {refinements} refinements in {FRAMES} frames, {:.2} ms a frame",
            started.elapsed().as_secs_f64() * 1e3 / f64::from(FRAMES)
        );
    }
}

criterion_group!(
    benches,
    octree_build,
    octree_refine,
    octree_emit,
    octree_refresh
);
criterion_main!(benches);
