//! Reference renderer cost per pixel: a small trilinear grid
//! (17³ points of fBm noise, 3 scalar tolerances) and a small cell list (the
//! 8³ cells of a 9³ grid as 2560 tetrahedra), both over the box [−1, 1]³ seen
//! from outside so every pixel's ray crosses the volume. Criterion reports
//! throughput in pixels per second; the cost per pixel is its inverse. Each
//! image uses every core (the renderer splits rows with `std::thread::scope`).
//!
//! Run: `cargo bench -p nebel_reference --bench reference`.

use std::hint::black_box;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use glam::DVec3;
use nebel_core::field::{DensityGrid, ProceduralNoise};
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_reference::{ReferenceCamera, ReferenceScene, ReferenceVolume, render};

/// Image side, pixels.
const SIDE: u32 = 32;

fn camera() -> ReferenceCamera {
    ReferenceCamera {
        position: DVec3::new(1.5, 1.0, 2.5),
        width: SIDE,
        height: SIDE,
        vertical_fov: 0.6,
        ..Default::default()
    }
    .looking_at(DVec3::ZERO, DVec3::Y)
}

fn noise_grid(points: usize) -> DensityGrid {
    let noise = ProceduralNoise {
        seed: 7,
        frequency: 1.3,
        ..Default::default()
    };
    let spacing = DVec3::splat(2.0 / (points - 1) as f64);
    DensityGrid::procedural([points; 3], spacing, DVec3::splat(-1.0), &noise).expect("valid grid")
}

fn reference(c: &mut Criterion) {
    let transfer_function = TransferFunction::preset(TransferPreset::Cloud)
        .scale_density(4.0)
        .expect("valid scale");
    let mut group = c.benchmark_group("reference_per_pixel");
    group.sample_size(10);
    group.throughput(Throughput::Elements(u64::from(SIDE * SIDE)));

    let grid = noise_grid(17);
    for tolerance in [1e-3, 1e-5, 1e-7] {
        let mut scene = ReferenceScene::new(
            camera(),
            ReferenceVolume::Grid(grid.clone()),
            transfer_function.clone(),
            OpticalMode::Sorted,
        );
        scene.scalar_tolerance = tolerance;
        group.bench_with_input(
            BenchmarkId::new("grid_17", tolerance),
            &scene,
            |b, scene| b.iter(|| render(black_box(scene), None).expect("valid scene")),
        );
    }

    let cells = noise_grid(9).tetrahedra();
    for mode in [OpticalMode::Sorted, OpticalMode::Emissive] {
        let scene = ReferenceScene::new(
            camera(),
            ReferenceVolume::Cells(cells.clone()),
            transfer_function.clone(),
            mode,
        );
        let name = format!("cells_{}", cells.len());
        group.bench_with_input(
            BenchmarkId::new(name, format!("{mode:?}")),
            &scene,
            |b, scene| b.iter(|| render(black_box(scene), None).expect("valid scene")),
        );
    }
    group.finish();
}

criterion_group!(benches, reference);
criterion_main!(benches);
