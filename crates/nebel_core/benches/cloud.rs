//! Procedural cumulus clouds and their light field (Röttger and Ertl 2003 §5, Schpok et al. 2003):
//! generation time of the paper's 513 × 513 × 65 field (here 513 × 65 × 513,
//! grid axis y up: 17.1 million points, default 5 octaves) and of its light
//! intensity γ with and without the shadow sweep (the sun's largest
//! component in index units along y, and along x), on one thread and on every
//! core (fastest of a few runs, printed), then criterion on a small grid. For
//! scale, the same octave sums on one thread point by point through
//! `noise::Perlin::get` (what the generator evaluates row by row, bit for bit,
//! skipping the octaves that cannot make a point cloud).
//!
//! Run: `cargo bench -p nebel_core --bench cloud`.

use std::hint::black_box;
use std::num::NonZeroUsize;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group};
use glam::DVec3;
use nebel_core::field::{
    CloudLighting, CloudNoise, CloudShape, DensityGrid, NOISE_OFFSET, light_field_with_threads,
};
use noise::{NoiseFn, Perlin};

/// The paper's cloud field, y up.
const PAPER_DIMS: [usize; 3] = [513, 65, 513];

/// 10 m horizontally, 20 m vertically: a 5.12 km × 1.28 km × 5.12 km box.
const SPACING: DVec3 = DVec3::new(10.0, 20.0, 10.0);

fn noise() -> CloudNoise {
    CloudNoise {
        seed: 3,
        wind: DVec3::new(8.0, 0.0, 3.0),
        ..Default::default()
    }
}

fn shadowed() -> CloudLighting {
    CloudLighting {
        shadow_extinction: 0.01,
        lambert: true,
        ..Default::default()
    }
}

/// [`shadowed`] under a sun whose largest component in index units is x
/// (`0.045, 0.03, 0.03` per point with this spacing): the sweep steps along x,
/// where a slice's points are a grid row apart.
fn shadowed_along_x() -> CloudLighting {
    CloudLighting {
        sun_direction: DVec3::new(0.45, 0.6, 0.3),
        ..shadowed()
    }
}

/// Fastest wall time of `runs` calls.
fn fastest<T>(runs: u32, mut f: impl FnMut() -> T) -> Duration {
    (0..runs)
        .map(|_| {
            let start = Instant::now();
            black_box(f());
            start.elapsed()
        })
        .min()
        .unwrap_or_default()
}

/// The sum `Σ a_i P_i(x_i)` of the octaves (unnormalised) at every point of
/// the paper's grid but the top and bottom layers, point by point.
fn pointwise_octave_sums(noise: &CloudNoise, time: f64) -> f64 {
    let octaves: Vec<(Perlin, f64, DVec3, f64)> = (0..noise.octaves)
        .map(|i| {
            let frequency = noise.lacunarity.powi(i as i32) / noise.wavelength;
            let drift = noise.wind * (time * noise.detail_wind.powi(i as i32));
            let offset = DVec3::from(NOISE_OFFSET) - drift * frequency;
            let perlin = Perlin::new(noise.seed.wrapping_add(i as u32));
            (perlin, frequency, offset, noise.persistence.powi(i as i32))
        })
        .collect();
    let [nx, ny, nz] = PAPER_DIMS;
    let mut total = 0.0;
    for k in 0..nz {
        for j in 1..ny - 1 {
            for i in 0..nx {
                let p = DVec3::new(i as f64, j as f64, k as f64) * SPACING;
                for (perlin, frequency, offset, amplitude) in &octaves {
                    total += amplitude * perlin.get((p * *frequency + *offset).to_array());
                }
            }
        }
    }
    total
}

/// The paper-size field of `noise` at 10 s on `threads` threads.
fn generate(noise: &CloudNoise, threads: usize) -> DensityGrid {
    let shape = CloudShape::default();
    DensityGrid::cloud_with_threads(
        PAPER_DIMS,
        SPACING,
        DVec3::ZERO,
        noise,
        &shape,
        10.0,
        threads,
    )
    .expect("valid cloud")
}

fn paper_field() {
    let all = std::thread::available_parallelism().map_or(1, NonZeroUsize::get);
    let [nx, ny, nz] = PAPER_DIMS;
    eprintln!(
        "{nx}×{ny}×{nz} = {} points, {} octaves",
        nx * ny * nz,
        noise().octaves
    );
    let turned = CloudNoise {
        torque: DVec3::new(0.0, 0.01, 0.0),
        ..noise()
    };
    for (label, noise) in [("", noise()), (" under torque", turned)] {
        for threads in [1, all] {
            let time = fastest(2, || generate(&noise, threads));
            eprintln!(
                "cloud generation{label}, {threads} thread(s): {:.2} s",
                time.as_secs_f64()
            );
        }
    }
    let time = fastest(1, || pointwise_octave_sums(&noise(), 10.0));
    eprintln!(
        "for scale: the octaves point by point through noise::Perlin, 1 thread: {:.2} s",
        time.as_secs_f64()
    );
    let grid = generate(&noise(), all);
    let covered = grid.values().iter().filter(|&&v| v > 0.0).count() as f64;
    eprintln!(
        "non-zero fraction {:.3}",
        covered / grid.values().len() as f64
    );
    for (label, lighting) in [
        ("no shadow", CloudLighting::default()),
        ("shadow sweep", shadowed()),
        ("shadow sweep along x", shadowed_along_x()),
        (
            "shadow sweep, 3 scattering octaves",
            CloudLighting {
                scattering_octaves: 3,
                ..shadowed()
            },
        ),
        (
            "shadow sweep, sky occlusion",
            CloudLighting {
                sky_occlusion: true,
                ..shadowed()
            },
        ),
        (
            "shadow sweep, 3 scattering octaves, sky occlusion",
            CloudLighting {
                scattering_octaves: 3,
                sky_occlusion: true,
                ..shadowed()
            },
        ),
    ] {
        for threads in [1, all] {
            let time = fastest(3, || {
                light_field_with_threads(&grid, &lighting, threads).expect("valid lighting")
            });
            eprintln!(
                "light field ({label}), {threads} thread(s): {:.3} s",
                time.as_secs_f64()
            );
        }
    }
}

fn small_grid(c: &mut Criterion) {
    let dims = [65, 17, 65];
    let spacing = DVec3::new(80.0, 80.0, 80.0);
    let mut group = c.benchmark_group("cloud_65x17x65");
    group.sample_size(10);
    group.bench_function("generate", |b| {
        b.iter(|| DensityGrid::cloud(dims, spacing, DVec3::ZERO, &noise(), 0.0));
    });
    let grid = DensityGrid::cloud(dims, spacing, DVec3::ZERO, &noise(), 0.0).expect("valid");
    group.bench_function("light_field_shadow", |b| {
        b.iter(|| nebel_core::field::light_field(&grid, &shadowed()));
    });
    group.finish();
}

criterion_group!(benches, small_grid);

fn main() {
    paper_field();
    benches();
    Criterion::default().configure_from_args().final_summary();
}
