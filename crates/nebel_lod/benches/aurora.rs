//! Aurora benchmarks (`nebel_lod::aurora`): the per-frame work of an
//! animated aurora on one core, split into its three steps: the curtains'
//! footprint at the frame's time (`nebel_core::field::AuroraCurtains::map`),
//! the layer's quadtree over it (`AuroraShape::layer`: the thickness and its
//! roughness), and the cells for the eye (`SurfaceLayer::cells`: refinement
//! with morphing, frustum culling, the prisms, unordered for the emissive
//! mode).
//!
//! # Scenario
//!
//! The `aurora` scene's: four arcs (seed 3, width 0.006) over a 600 km
//! square centred 350 km north of the eye, from 100 km up to 300 km where
//! strongest, at 257 (the default) and 513 points per side, c = 12; the eye 1.1 km up,
//! looking north 12° up, 70° vertical field of view, aspect 16/9. Frames at
//! 30 Hz from t = 0.
//!
//! Run: `cargo bench -p nebel_lod --bench aurora`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use glam::{DAffine3, DMat4, DVec3};
use nebel_core::field::AuroraCurtains;
use nebel_lod::quadtree::DEFAULT_MIN_RESOLUTION;
use nebel_lod::{AuroraShape, CellOrder, Frustum, LayerView, LodSettings, TerrainMesh};

const SHAPE: AuroraShape = AuroraShape {
    extent: 600e3,
    bottom: 100e3,
    top: 300e3,
};

fn curtains() -> AuroraCurtains {
    AuroraCurtains {
        seed: 3,
        count: 4,
        width: 0.006,
        ..AuroraCurtains::default()
    }
}

fn bench_aurora(c: &mut Criterion) {
    let eye = DVec3::new(0.0, 1100.0, 2500.0);
    let target = DVec3::new(0.0, 70e3, -300e3);
    let clip_from_world =
        DMat4::perspective_infinite_reverse_rh(70f64.to_radians(), 16.0 / 9.0, 1.0)
            * DMat4::look_at_rh(eye, target, DVec3::Y);
    let world_from_field = DAffine3::from_translation(DVec3::new(0.0, 0.0, -350e3));
    let frustum = Frustum::from_view_projection(clip_from_world)
        .expect("a view")
        .in_local_frame(&world_from_field);
    let profile = AuroraShape::profile();
    let curtains = curtains();
    for side in [257, 513] {
        let mut group = c.benchmark_group(format!("aurora_{side}"));
        let mut frame = 0u32;
        group.bench_function("footprint", |b| {
            b.iter(|| {
                frame += 1;
                black_box(curtains.map(side, f64::from(frame) / 30.0).unwrap())
            });
        });
        let strength = curtains.map(side, 2.0).unwrap();
        group.bench_function("layer", |b| {
            b.iter(|| {
                black_box(
                    SHAPE
                        .layer(side, &strength, DEFAULT_MIN_RESOLUTION, 1.0)
                        .unwrap(),
                )
            });
        });
        let layer = SHAPE
            .layer(side, &strength, DEFAULT_MIN_RESOLUTION, 1.0)
            .unwrap();
        let view = LayerView {
            world_from_field,
            eye,
            frustum: Some(&frustum),
            lod: LodSettings {
                accuracy: 12.0,
                ..LodSettings::default()
            },
            order: CellOrder::Unordered,
            profile: &profile,
            scalar: SHAPE.scalar(),
        };
        let mut mesh = TerrainMesh::new();
        let mut cells = Vec::new();
        let stats = layer.cells(&view, &mut mesh, &mut cells).unwrap();
        println!("aurora_{side}: {stats:?}");
        group.bench_function("cells", |b| {
            b.iter(|| black_box(layer.cells(&view, &mut mesh, &mut cells).unwrap()));
        });
        group.finish();
    }
}

criterion_group!(benches, bench_aurora);
criterion_main!(benches);
