//! Cost of building the volume C-LOD hierarchy (`VolumeHierarchy::new`: u8
//! quantisation, Δ with K_max propagation and the scalar ranges of every node)
//! for a 129³ fBm field and for the paper's 513 × 513 × 65 cumulus-like fBm
//! field (a forest of 8 × 8 × 1 roots of 65³ points, 17.1 million points).
//!
//! Criterion reports the throughput in grid points per second ("elem/s").
//!
//! Run: `cargo bench -p nebel_lod --bench octree`.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::DVec3;
use nebel_core::field::{DensityGrid, ProceduralNoise};
use nebel_lod::VolumeHierarchy;

/// Minimum accuracy C of the benches (K_max ≈ 0.638).
const MIN_ACCURACY: f64 = 2.0;

fn octree_build(c: &mut Criterion) {
    let noise = ProceduralNoise {
        seed: 5,
        octaves: 6,
        frequency: 1.0 / 128.0,
        ..Default::default()
    };
    let mut group = c.benchmark_group("octree_build");
    group.sample_size(10);
    for dims in [[129, 129, 129], [513, 513, 65]] {
        // One world unit per grid point: the first octave spans 128 points,
        // six octaves down to 4 points, like the paper's cumulus field.
        let grid =
            DensityGrid::procedural(dims, DVec3::ONE, DVec3::ZERO, &noise).expect("valid grid");
        group.throughput(Throughput::Elements(grid.values().len() as u64));
        let name = format!("{}x{}x{}", dims[0], dims[1], dims[2]);
        group.bench_function(name, |b| {
            b.iter(|| VolumeHierarchy::new(black_box(&grid), MIN_ACCURACY).expect("2^n+1 grid"))
        });
    }
    group.finish();
}

criterion_group!(benches, octree_build);
criterion_main!(benches);
