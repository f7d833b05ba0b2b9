//! Cost of building a full-resolution cell batch: cells per millisecond of
//! `full_resolution_batch` for a 64³-voxel noise grid (1.57 million cells, every
//! brick kept), eye outside and inside the grid, back-to-front against
//! unordered, the one-off cost of its `BrickTable`, the batch of the same grid
//! ray cast whole (`CellGrid` with its brick occupancy, built once per
//! placement and transfer function instead of per eye), and a campfire-sized 16³
//! grid (24 576 cells); and MPVO (`CellAdjacency::back_to_front`, plus the
//! one-off `CellAdjacency::new`) on the default 16 × 4 × 32 search-light cone
//! and on the tetrahedra of a 16³ grid.
//!
//! Criterion reports the throughput in cells per second ("elem/s"):
//! 1 Melem/s = 1 000 cells per ms.
//!
//! Run: `cargo bench -p nebel_lod --bench full_resolution` (MPVO alone: add
//! `-- mpvo`).

use std::hint::black_box;
use std::sync::Arc;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use glam::{DAffine3, DQuat, DVec3, UVec2};
use nebel_core::cell::Tetrahedron;
use nebel_core::field::{DensityGrid, ProceduralNoise, search_light_cells};
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_lod::{BrickTable, CellAdjacency, CellGrid, CellOrder, View, full_resolution_batch};

/// Points per axis: 64³ voxels.
const POINTS: usize = 65;

/// The views' render target, pixels (read only for being non-empty).
const VIEWPORT: UVec2 = UVec2::new(1920, 1080);

fn full_resolution(c: &mut Criterion) {
    let noise = ProceduralNoise {
        seed: 11,
        frequency: 1.7,
        ..Default::default()
    };
    for points in [POINTS, 17] {
        bench_grid(c, &noise, points);
    }
}

fn bench_grid(c: &mut Criterion, noise: &ProceduralNoise, points: usize) {
    let grid = DensityGrid::procedural(
        [points; 3],
        DVec3::splat(1.0 / (points - 1) as f64),
        DVec3::ZERO,
        noise,
    )
    .expect("valid grid");
    // ρ > 0 for every s > 0: no brick is transparent, every voxel is emitted.
    let transfer = TransferFunction::preset(TransferPreset::GroundFog);
    let world_from_grid = DAffine3::from_scale_rotation_translation(
        DVec3::splat(8.0),
        DQuat::from_rotation_y(0.3),
        DVec3::new(-4.0, 0.0, -4.0),
    );
    let bricks = BrickTable::new(&grid, BrickTable::DEFAULT_BRICK_SIZE);
    let cells = 6 * (points - 1).pow(3);

    let mut group = c.benchmark_group(format!("full_resolution_{}", points - 1));
    group.sample_size(20);
    group.throughput(Throughput::Elements(cells as u64));
    let eyes = [
        ("eye_outside", DVec3::new(20.0, 12.0, 25.0)),
        (
            "eye_inside",
            world_from_grid.transform_point3(DVec3::new(0.4, 0.55, 0.6)),
        ),
    ];
    for (name, eye) in eyes {
        for order in [CellOrder::BackToFront, CellOrder::Unordered] {
            group.bench_with_input(
                BenchmarkId::new(name, format!("{order:?}")),
                &(eye, order),
                |b, &(eye, order)| {
                    b.iter(|| {
                        let batch = full_resolution_batch(
                            black_box(&grid),
                            &bricks,
                            &View::new(world_from_grid, eye, VIEWPORT),
                            &transfer,
                            order,
                        )
                        .expect("valid input");
                        assert_eq!(batch.len(), cells);
                        batch
                    });
                },
            );
        }
    }
    group.finish();

    let mut group = c.benchmark_group(format!("ray_cast_grid_{}", points - 1));
    group.throughput(Throughput::Elements(cells as u64));
    let shared = Arc::new(grid.clone());
    group.bench_function("new_with_occupancy", |b| {
        b.iter(|| {
            CellGrid::new(black_box(shared.clone()), world_from_grid)
                .and_then(|grid| grid.with_occupancy(&bricks, &transfer))
                .expect("valid input")
        });
    });
    group.finish();

    let mut group = c.benchmark_group(format!("brick_table_{}", points - 1));
    group.throughput(Throughput::Elements(points.pow(3) as u64));
    group.bench_function("new", |b| {
        b.iter(|| BrickTable::new(black_box(&grid), BrickTable::DEFAULT_BRICK_SIZE));
    });
    group.finish();
}

fn mpvo(c: &mut Criterion) {
    let cone = search_light_cells(8.0, 0.3, [16, 4, 32]).expect("the cone fits the memory budget");
    let cone_eyes = [
        ("eye_outside", DVec3::new(6.0, 3.0, 2.0)),
        ("eye_inside", DVec3::new(0.3, -0.2, -5.0)),
    ];
    // Dyadic spacing and origin: the grid's tetrahedra share vertices bit for bit.
    let grid = DensityGrid::procedural(
        [17; 3],
        DVec3::splat(0.5),
        DVec3::splat(-4.0),
        &ProceduralNoise::default(),
    )
    .expect("valid grid");
    let grid_eyes = [
        ("eye_outside", DVec3::new(20.0, 12.0, 25.0)),
        ("eye_inside", DVec3::new(0.3, 1.1, -0.7)),
    ];
    bench_mpvo(c, "mpvo_search_light_16x4x32", &cone, &cone_eyes);
    bench_mpvo(c, "mpvo_grid_16", &grid.tetrahedra(), &grid_eyes);
}

fn bench_mpvo(c: &mut Criterion, name: &str, cells: &[Tetrahedron], eyes: &[(&str, DVec3)]) {
    let adjacency = CellAdjacency::new(cells);
    let mut group = c.benchmark_group(name);
    group.throughput(Throughput::Elements(cells.len() as u64));
    for &(eye_name, eye) in eyes {
        group.bench_with_input(
            BenchmarkId::new("back_to_front", eye_name),
            &eye,
            |b, &eye| b.iter(|| adjacency.back_to_front(black_box(cells), eye)),
        );
    }
    group.bench_function("adjacency_new", |b| {
        b.iter(|| CellAdjacency::new(black_box(cells)));
    });
    group.finish();
}

criterion_group!(benches, full_resolution, mpvo);
criterion_main!(benches);
