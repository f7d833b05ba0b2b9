//! Ground fog benchmarks (`nebel_lod::ground_fog`): the per-frame work of
//! the paper's scene size (Röttger and Ertl 2003 §6: a 2049² terrain and fog
//! map, 10 m spacing) along a flight, on one core: the quadtree's refinement
//! with the fog's thickness as its map, then the prisms over every fogged
//! triangle, back to front for the eye.
//!
//! # Scenario
//!
//! Terrain: 2049² points 10 m apart (20.5 km square), fBm of hashed value
//! noise (8 octaves from 5120 m, gain 0.5) rescaled to 0..1000 m, squared
//! (`h²/1000`, wide valley floors). Fog: the valleys filled up to 150 m
//! (`nebel_core::field::ValleyFog`, ±15 m edge), its roughness in d2 with
//! weight `w`. Flight: 120 frames from the terrain's south-west quarter
//! toward its centre, 8 m per frame, from 900 m above sea level down to
//! 120 m (into the fog where the valleys are), looking ahead 20° down, 60°
//! vertical field of view, aspect 4/3, frustum culling with the fog's
//! raised boxes. Each frame: `update_with_map` (morphing on, no normals,
//! grid points, front to back, as the terrain plugin refines) and
//! `fog_prisms` (the mesh read backwards: back to front; the paper's
//! profile). 5 warm-up frames.
//!
//! # Output
//!
//! `target/nebel/ground_fog_flight.csv` (per frame: eye height, triangles,
//! prisms, tetrahedra, refine ms, prisms ms) and
//! `target/nebel/ground_fog_sweep.csv` (per accuracy `c` and weight `w`: the
//! medians and the largest frame along the flight), then criterion's report
//! of one frame at the default setting. Times are wall times of the calling
//! thread.
//!
//! Run: `cargo bench -p nebel_lod --bench ground_fog`.

use std::fmt::Write as _;
use std::hint::black_box;
use std::path::PathBuf;
use std::time::Instant;

use criterion::{Criterion, criterion_group};
use glam::{DAffine3, DMat4, DVec2, DVec3};
use nebel_core::field::{HeightField, ValleyFog, ValueNoise};
use nebel_lod::quadtree::TerrainMap;
use nebel_lod::{
    CellOrder, FogProfile, Frustum, GpuCell, LodSettings, PrismInput, PrismScalar,
    TerrainHierarchy, TerrainMesh, TriangleOrder, fog_prisms,
};

const SIDE: usize = 2049;
const SPACING: f64 = 10.0;
const WARM_UP: usize = 5;
const FRAMES: usize = 120;

/// The scenario's terrain and fog thickness (see the module docs).
fn scene() -> (HeightField, TerrainMap) {
    let half = (SIDE - 1) as f64 * SPACING / 2.0;
    let noise = HeightField::value_noise(
        [SIDE, SIDE],
        DVec2::splat(SPACING),
        DVec2::splat(-half),
        &ValueNoise::default(),
        1000.0,
    )
    .expect("valid field");
    let squared = noise.heights().iter().map(|h| h * h / 1000.0).collect();
    let field = HeightField::new(
        [SIDE, SIDE],
        DVec2::splat(SPACING),
        DVec2::splat(-half),
        squared,
    )
    .expect("valid field");
    let valley = ValleyFog {
        altitude: 150.0,
        edge: 15.0,
        ..ValleyFog::default()
    };
    let thickness = valley.thickness(&field).expect("valid fog");
    (
        field,
        TerrainMap::new(SIDE, thickness).expect("valid layer"),
    )
}

/// The eye and frustum of frame `frame` (see the module docs).
fn view(frame: usize) -> (DVec3, Frustum) {
    let t = frame as f64 / (WARM_UP + FRAMES - 1) as f64;
    let start = DVec3::new(-5000.0, 900.0, -5000.0);
    let direction = DVec3::new(1.0, 0.0, 1.0).normalize();
    let eye = start + direction * (8.0 * frame as f64) + DVec3::new(0.0, -780.0 * t, 0.0);
    let forward = (direction + DVec3::new(0.0, -(20f64.to_radians().tan()), 0.0)).normalize();
    let view = DMat4::look_to_rh(eye, forward, DVec3::Y);
    let projection = DMat4::perspective_infinite_reverse_rh(60f64.to_radians(), 4.0 / 3.0, 1.0);
    let frustum = Frustum::from_view_projection(projection * view).expect("valid frustum");
    (eye, frustum)
}

/// One frame's counters and times.
struct Frame {
    eye_height: f64,
    triangles: usize,
    prisms: usize,
    tetrahedra: usize,
    refine_ms: f64,
    prisms_ms: f64,
}

fn settings(accuracy: f32) -> LodSettings {
    LodSettings {
        accuracy,
        morph: true,
        normals: false,
        grid_points: true,
        order: TriangleOrder::FrontToBack,
    }
}

/// The prisms' input for `eye` over a mesh refined front to back (as the
/// terrain plugin refines), back to front.
fn prism_input<'a>(
    hierarchy: &TerrainHierarchy,
    eye: DVec3,
    profile: &'a FogProfile,
) -> PrismInput<'a> {
    PrismInput {
        world_from_mesh: DAffine3::from_translation(hierarchy.origin()),
        eye: eye - hierarchy.origin(),
        mesh_order: TriangleOrder::FrontToBack,
        order: CellOrder::BackToFront,
        profile,
        scalar: PrismScalar::Profile,
        beyond: None,
    }
}

/// The flight through `hierarchy` at accuracy `c`.
fn fly(hierarchy: &TerrainHierarchy, layer: &TerrainMap, accuracy: f32) -> Vec<Frame> {
    let profile = FogProfile::default();
    let mut mesh = TerrainMesh::new();
    let mut cells: Vec<GpuCell> = Vec::new();
    let mut frames = Vec::new();
    for frame in 0..WARM_UP + FRAMES {
        let (eye, frustum) = view(frame);
        let started = Instant::now();
        let lod = hierarchy
            .update_with_map(
                eye,
                Some(&frustum),
                &settings(accuracy),
                Some(layer),
                &mut mesh,
            )
            .expect("valid view");
        let refined = Instant::now();
        let stats = fog_prisms(&mesh, &prism_input(hierarchy, eye, &profile), &mut cells)
            .expect("a fog mesh");
        let done = Instant::now();
        if frame >= WARM_UP {
            frames.push(Frame {
                eye_height: eye.y,
                triangles: lod.triangles,
                prisms: stats.prisms,
                tetrahedra: stats.tetrahedra,
                refine_ms: (refined - started).as_secs_f64() * 1e3,
                prisms_ms: (done - refined).as_secs_f64() * 1e3,
            });
        }
    }
    frames
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

fn write_csvs(field: &HeightField, layer: &TerrainMap) {
    let mut sweep = String::from(
        "c,weight,triangles_median,prisms_median,tetrahedra_median,tetrahedra_max,refine_ms_median,prisms_ms_median,frame_ms_median,frame_ms_max\n",
    );
    let mut flight = String::new();
    for weight in [0.0_f32, 1.0, 4.0] {
        let started = Instant::now();
        let hierarchy = TerrainHierarchy::new(field.clone(), 2.0)
            .and_then(|h| h.with_map_roughness(layer, weight))
            .expect("valid hierarchy");
        eprintln!(
            "hierarchy with weight {weight}: {:.0} ms",
            started.elapsed().as_secs_f64() * 1e3
        );
        for accuracy in [100.0_f32, 200.0, 300.0, 600.0] {
            let frames = fly(&hierarchy, layer, accuracy);
            let column = |f: &dyn Fn(&Frame) -> f64| median(frames.iter().map(f).collect());
            let largest = |f: &dyn Fn(&Frame) -> f64| frames.iter().map(f).fold(0.0, f64::max);
            writeln!(
                sweep,
                "{accuracy},{weight},{},{},{},{},{:.3},{:.3},{:.3},{:.3}",
                column(&|f| f.triangles as f64),
                column(&|f| f.prisms as f64),
                column(&|f| f.tetrahedra as f64),
                largest(&|f| f.tetrahedra as f64),
                column(&|f| f.refine_ms),
                column(&|f| f.prisms_ms),
                column(&|f| f.refine_ms + f.prisms_ms),
                largest(&|f| f.refine_ms + f.prisms_ms),
            )
            .unwrap();
            if accuracy == 300.0 && weight == 1.0 {
                flight.push_str(
                    "frame,eye_height_m,triangles,prisms,tetrahedra,refine_ms,prisms_ms\n",
                );
                for (index, f) in frames.iter().enumerate() {
                    writeln!(
                        flight,
                        "{index},{:.1},{},{},{},{:.3},{:.3}",
                        f.eye_height, f.triangles, f.prisms, f.tetrahedra, f.refine_ms, f.prisms_ms
                    )
                    .unwrap();
                }
            }
        }
    }
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../target/nebel");
    std::fs::create_dir_all(&dir).expect("cannot create target/nebel");
    for (name, csv) in [
        ("ground_fog_sweep.csv", &sweep),
        ("ground_fog_flight.csv", &flight),
    ] {
        let path = dir.join(name);
        std::fs::write(&path, csv).expect("cannot write CSV");
        eprintln!("wrote {}", path.display());
    }
    eprintln!("{sweep}");
}

fn one_frame(c: &mut Criterion) {
    let (field, layer) = scene();
    let hierarchy = TerrainHierarchy::new(field, 2.0)
        .and_then(|h| h.with_map_roughness(&layer, 1.0))
        .expect("valid hierarchy");
    let (eye, frustum) = view(60);
    let profile = FogProfile::default();
    let (mut mesh, mut cells) = (TerrainMesh::new(), Vec::new());
    c.bench_function("ground_fog_2049_frame_c300", |b| {
        b.iter(|| {
            hierarchy
                .update_with_map(
                    black_box(eye),
                    Some(&frustum),
                    &settings(300.0),
                    Some(&layer),
                    &mut mesh,
                )
                .expect("valid view");
            fog_prisms(&mesh, &prism_input(&hierarchy, eye, &profile), &mut cells)
                .expect("a fog mesh")
        });
    });
}

criterion_group!(benches, one_frame);

fn main() {
    let (field, layer) = scene();
    write_csvs(&field, &layer);
    benches();
    Criterion::default().configure_from_args().final_summary();
}
