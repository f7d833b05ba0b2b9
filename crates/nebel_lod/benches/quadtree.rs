//! Terrain C-LOD benchmarks (`nebel_lod::quadtree`): the per-frame update
//! (refinement, geomorphing and triangle output in one pass) of 1025², 2049²
//! and 4097² height fields, against the author's C++ libMini 8.8.6.
//!
//! # The peer scenario (libMini's published one, so the figures compare)
//!
//! Height field: 10 m spacing, fBm of hashed value noise (8 octaves,
//! wavelengths 5120 m down to 40 m, gain 0.5, smoothstep interpolation,
//! fixed seed) rescaled to 0..1000 m, centred on the world origin. Eye at
//! `x = −(half width)/2, z = 0`, 2000 m above the ground height below it at
//! the start (bilinear height there + 2000 m; the eye's height then stays
//! fixed), looking along +x, 60° vertical field of view, aspect 4/3 (a
//! frustum from `perspective_infinite_reverse_rh` × `look_to_rh`, near plane
//! 1 m), moving (+10, 0, +5) m per frame; 5 warm-up frames, then the median
//! of 50 frames. One thread. libMini's figures (measured on a two-core
//! machine like the development machine, single core):
//!
//! | field | libMini C | triangles | ms per frame |
//! |---|---|---|---|
//! | 2049² | 1 | 51,794 | 2.09 |
//! | 4097² | 1 | 114,996 | 9.8 |
//! | 2049² | 9 (default) | 1,109 | 0.07 |
//!
//! Memory: 5.0 bytes per grid point with f32 heights, 3.0 with 16-bit.
//!
//! This bench finds by bisection on the accuracy `c` the setting that gives
//! libMini's triangle counts (median over the 50 frames) and times the update
//! there; it also times the default settings (`c` = 300, `C` = 2), and sweeps
//! `c` (and `C` at the matched counts). Every update runs with morphing on and
//! frustum culling; the peer columns use [`TriangleOrder::Unordered`] without
//! normals (what libMini's fans carry), the extra columns back-to-front order
//! with normals.
//!
//! # Output
//!
//! `target/nebel/quadtree_peer.csv` and `target/nebel/quadtree_sweep.csv`
//! (relative to the workspace root), then criterion's report of the update at
//! the matched 2049² setting and of the hierarchy build. Times: median wall
//! time and median on-CPU time of the calling thread (Linux `schedstat`; a
//! busy machine does not inflate it).
//!
//! Run: `cargo bench -p nebel_lod --bench quadtree`.

use std::fmt::Write as _;
use std::hint::black_box;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group};
use glam::{DMat4, DVec2, DVec3};
use nebel_core::field::{HeightField, ValueNoise};
use nebel_lod::Frustum;
use nebel_lod::quadtree::{
    DEFAULT_ACCURACY, DEFAULT_MIN_RESOLUTION, LodSettings, TerrainHierarchy, TerrainMesh,
    TriangleOrder,
};

/// Grid spacing, m.
const SPACING: f64 = 10.0;
/// Warm-up frames, then measured frames.
const WARM_UP: usize = 5;
const FRAMES: usize = 50;
/// libMini's figures to match: (size, libMini's C, triangles, ms per frame).
const PEER: [(usize, u32, usize, f64); 3] = [
    (2049, 1, 51_794, 2.09),
    (2049, 9, 1_109, 0.07),
    (4097, 1, 114_996, 9.8),
];

/// The peer scenario's height field of `n × n` points (see the module docs).
fn peer_field(n: usize) -> HeightField {
    let half_width = (n - 1) as f64 * SPACING / 2.0;
    HeightField::value_noise(
        [n, n],
        DVec2::splat(SPACING),
        DVec2::splat(-half_width),
        &ValueNoise::default(),
        1000.0,
    )
    .expect("valid field")
}

/// The eye of frame `frame` and its frustum.
fn peer_view(field: &HeightField, frame: usize) -> (DVec3, Frustum) {
    let half_width = (field.dims()[0] - 1) as f64 * SPACING / 2.0;
    let start = DVec2::new(-half_width / 2.0, 0.0);
    let height = field.sample(start) + 2000.0;
    let eye = DVec3::new(start.x, height, start.y) + frame as f64 * DVec3::new(10.0, 0.0, 5.0);
    let view = DMat4::look_to_rh(eye, DVec3::X, DVec3::Y);
    let projection = DMat4::perspective_infinite_reverse_rh(60f64.to_radians(), 4.0 / 3.0, 1.0);
    let frustum = Frustum::from_view_projection(projection * view).expect("valid camera");
    (eye, frustum)
}

/// The calling thread's on-CPU time (Linux `schedstat`), if available.
fn thread_cpu_time() -> Option<Duration> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let nanos: u64 = text.split_whitespace().next()?.parse().ok()?;
    Some(Duration::from_nanos(nanos))
}

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        (values[n / 2 - 1] + values[n / 2]) / 2.0
    }
}

/// Figures of the measured frames of the path: medians of wall time,
/// triangles and vertices, and the mean on-CPU time per frame.
struct PathFigures {
    wall_ms: f64,
    cpu_ms: Option<f64>,
    triangles: f64,
    vertices: f64,
}

/// Runs the peer path (warm-up, then [`FRAMES`] measured frames); with
/// `time == false` only counts triangles. The on-CPU time is the thread's
/// `schedstat` over repeated passes of the measured frames (at least 0.3 s;
/// the counter moves in scheduler ticks), divided by the frames run.
fn run_path(
    hierarchy: &TerrainHierarchy,
    views: &[(DVec3, Frustum)],
    settings: &LodSettings,
    mesh: &mut TerrainMesh,
    time: bool,
) -> PathFigures {
    let mut wall = Vec::with_capacity(FRAMES);
    let mut triangles = Vec::with_capacity(FRAMES);
    let mut vertices = Vec::with_capacity(FRAMES);
    let first = if time { 0 } else { WARM_UP };
    for (frame, (eye, frustum)) in views.iter().enumerate().skip(first) {
        let start = Instant::now();
        let stats = hierarchy
            .update(*eye, Some(frustum), settings, mesh)
            .expect("valid view");
        let elapsed = start.elapsed();
        black_box(&mesh);
        if frame < WARM_UP {
            continue;
        }
        wall.push(elapsed.as_secs_f64() * 1e3);
        triangles.push(stats.triangles as f64);
        vertices.push(stats.vertices as f64);
    }
    let mut cpu_ms = None;
    if time {
        let (start, cpu_start) = (Instant::now(), thread_cpu_time());
        let mut frames = 0usize;
        while frames == 0 || start.elapsed() < Duration::from_millis(300) {
            for (eye, frustum) in &views[WARM_UP..] {
                hierarchy
                    .update(*eye, Some(frustum), settings, mesh)
                    .expect("valid view");
                black_box(&mesh);
                frames += 1;
            }
        }
        if let (Some(a), Some(b)) = (cpu_start, thread_cpu_time()) {
            cpu_ms = Some((b - a).as_secs_f64() * 1e3 / frames as f64);
        }
    }
    PathFigures {
        wall_ms: median(&mut wall),
        cpu_ms,
        triangles: median(&mut triangles),
        vertices: median(&mut vertices),
    }
}

fn peer_settings(accuracy: f32) -> LodSettings {
    LodSettings {
        accuracy,
        morph: true,
        normals: false,
        grid_points: false,
        order: TriangleOrder::Unordered,
    }
}

fn full_settings(accuracy: f32) -> LodSettings {
    LodSettings {
        accuracy,
        ..LodSettings::default()
    }
}

/// The accuracy `c` whose median triangle count over the path is closest to
/// `target`, by bisection on log c (the count never falls as c grows).
fn match_triangles(
    hierarchy: &TerrainHierarchy,
    views: &[(DVec3, Frustum)],
    mesh: &mut TerrainMesh,
    target: usize,
) -> f32 {
    let count = |c: f32, mesh: &mut TerrainMesh| {
        run_path(hierarchy, views, &peer_settings(c), mesh, false).triangles
    };
    let (mut lo, mut hi) = (0.01f64.ln(), 1e6f64.ln());
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        if count(mid.exp() as f32, mesh) < target as f64 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let (a, b) = (lo.exp() as f32, hi.exp() as f32);
    if (count(a, mesh) - target as f64).abs() <= (count(b, mesh) - target as f64).abs() {
        a
    } else {
        b
    }
}

fn cpu(ms: Option<f64>) -> String {
    ms.map_or(String::new(), |v| format!("{v:.4}"))
}

/// One CSV row of the peer table.
fn peer_row(
    csv: &mut String,
    n: usize,
    case: &str,
    min_resolution: f32,
    accuracy: f32,
    peer: Option<(usize, f64)>,
    fast: &PathFigures,
    full: &PathFigures,
    bytes_per_point: f64,
) {
    let (peer_triangles, peer_ms) = peer.map_or((String::new(), String::new()), |(t, ms)| {
        (t.to_string(), format!("{ms}"))
    });
    writeln!(
        csv,
        "{n},{case},{min_resolution},{accuracy:.4},{:.0},{:.0},{:.4},{},{:.4},{},{bytes_per_point:.4},{peer_triangles},{peer_ms}",
        fast.triangles,
        fast.vertices,
        fast.wall_ms,
        cpu(fast.cpu_ms),
        full.wall_ms,
        cpu(full.cpu_ms),
    )
    .unwrap();
    eprintln!(
        "{n}² {case}: C = {min_resolution}, c = {accuracy:.3}: {:.0} triangles, {:.3} ms wall / {} ms cpu (unordered, no normals), {:.3} ms (back to front + normals), {bytes_per_point:.3} B/point{}",
        fast.triangles,
        fast.wall_ms,
        cpu(fast.cpu_ms),
        full.wall_ms,
        peer.map_or(String::new(), |(t, ms)| format!(
            "; libMini: {t} triangles in {ms} ms"
        )),
    );
}

fn write_csvs() {
    let mut peer_csv = String::from(
        "size,case,C,c,triangles,vertices,update_ms_wall_median,update_ms_cpu_mean,update_ms_wall_median_btf_normals,update_ms_cpu_mean_btf_normals,bytes_per_point,libmini_triangles,libmini_ms\n",
    );
    let mut sweep_csv = String::from(
        "size,C,c,triangles,vertices,update_ms_wall_median,update_ms_cpu_mean,update_ms_wall_median_btf_normals,update_ms_cpu_mean_btf_normals,build_ms,bytes_per_point\n",
    );
    let mut mesh = TerrainMesh::new();
    // NEBEL_QUADTREE_SIZES=2049,4097 runs only those sizes.
    let sizes: Vec<usize> = std::env::var("NEBEL_QUADTREE_SIZES")
        .ok()
        .map(|s| s.split(',').filter_map(|v| v.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![1025, 2049, 4097]);
    for n in sizes {
        let field = peer_field(n);
        let views: Vec<(DVec3, Frustum)> = (0..WARM_UP + FRAMES)
            .map(|frame| peer_view(&field, frame))
            .collect();
        let start = Instant::now();
        let hierarchy = TerrainHierarchy::new(field, DEFAULT_MIN_RESOLUTION).expect("2^k+1");
        let build_ms = start.elapsed().as_secs_f64() * 1e3;
        let bytes = hierarchy.bytes_per_point();
        eprintln!("{n}²: hierarchy built in {build_ms:.0} ms, {bytes:.3} bytes per point");
        // libMini-equal triangle counts.
        for (_, libmini_c, target, peer_ms) in PEER.into_iter().filter(|p| p.0 == n) {
            for min_resolution in [DEFAULT_MIN_RESOLUTION, 4.0, 9.0] {
                let other;
                let h = if min_resolution == DEFAULT_MIN_RESOLUTION {
                    &hierarchy
                } else {
                    other = TerrainHierarchy::new(hierarchy.field().clone(), min_resolution)
                        .expect("2^k+1");
                    &other
                };
                let c = match_triangles(h, &views, &mut mesh, target);
                let fast = run_path(h, &views, &peer_settings(c), &mut mesh, true);
                let full = run_path(h, &views, &full_settings(c), &mut mesh, true);
                peer_row(
                    &mut peer_csv,
                    n,
                    &format!("libmini_C{libmini_c}_triangles"),
                    min_resolution,
                    c,
                    Some((target, peer_ms)),
                    &fast,
                    &full,
                    h.bytes_per_point(),
                );
            }
        }
        // Defaults.
        let fast = run_path(
            &hierarchy,
            &views,
            &peer_settings(DEFAULT_ACCURACY),
            &mut mesh,
            true,
        );
        let full = run_path(
            &hierarchy,
            &views,
            &full_settings(DEFAULT_ACCURACY),
            &mut mesh,
            true,
        );
        peer_row(
            &mut peer_csv,
            n,
            "defaults",
            DEFAULT_MIN_RESOLUTION,
            DEFAULT_ACCURACY,
            None,
            &fast,
            &full,
            bytes,
        );
        // Sweep of c.
        for accuracy in [3.0f32, 10.0, 30.0, 100.0, 300.0, 1000.0] {
            let fast = run_path(
                &hierarchy,
                &views,
                &peer_settings(accuracy),
                &mut mesh,
                true,
            );
            let full = run_path(
                &hierarchy,
                &views,
                &full_settings(accuracy),
                &mut mesh,
                true,
            );
            writeln!(
                sweep_csv,
                "{n},{DEFAULT_MIN_RESOLUTION},{accuracy},{:.0},{:.0},{:.4},{},{:.4},{},{build_ms:.1},{bytes:.4}",
                fast.triangles,
                fast.vertices,
                fast.wall_ms,
                cpu(fast.cpu_ms),
                full.wall_ms,
                cpu(full.cpu_ms),
            )
            .unwrap();
            eprintln!(
                "{n}² sweep c = {accuracy}: {:.0} triangles, {:.3} ms ({:.3} ms back to front + normals)",
                fast.triangles, fast.wall_ms, full.wall_ms
            );
        }
    }
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../target/nebel");
    std::fs::create_dir_all(&dir).expect("cannot create target/nebel");
    for (name, csv) in [
        ("quadtree_peer.csv", &peer_csv),
        ("quadtree_sweep.csv", &sweep_csv),
    ] {
        let path = dir.join(name);
        std::fs::write(&path, csv).expect("cannot write CSV");
        eprintln!("wrote {}:\n{csv}", path.display());
    }
}

fn update_and_build(c: &mut Criterion) {
    let field = peer_field(2049);
    let views: Vec<(DVec3, Frustum)> = (0..WARM_UP + FRAMES)
        .map(|frame| peer_view(&field, frame))
        .collect();
    let mut group = c.benchmark_group("quadtree_build");
    group.sample_size(10);
    group.bench_function("2049", |b| {
        b.iter(|| {
            TerrainHierarchy::new(black_box(field.clone()), DEFAULT_MIN_RESOLUTION).expect("2^k+1")
        });
    });
    group.finish();
    let hierarchy = TerrainHierarchy::new(field, DEFAULT_MIN_RESOLUTION).expect("2^k+1");
    let mut mesh = TerrainMesh::new();
    let accuracy = match_triangles(&hierarchy, &views, &mut mesh, PEER[0].2);
    let (eye, frustum) = &views[WARM_UP + FRAMES / 2];
    let mut group = c.benchmark_group("quadtree_update_2049_peer_triangles");
    group.sample_size(50);
    for (name, settings) in [
        ("unordered", peer_settings(accuracy)),
        ("back_to_front_normals", full_settings(accuracy)),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| {
                hierarchy
                    .update(black_box(*eye), Some(frustum), &settings, &mut mesh)
                    .expect("valid view")
            });
        });
    }
    group.finish();
}

criterion_group!(benches, update_and_build);

fn main() {
    write_csvs();
    benches();
    Criterion::default().configure_from_args().final_summary();
}
