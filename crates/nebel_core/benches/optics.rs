//! Optics benchmarks: pre-integration table build time against table size, with
//! the error each size reaches, and the cost of one exact segment integral.
//!
//! Besides criterion's report, every run writes `target/nebel/preintegration.csv`
//! (relative to the workspace root), one row per transfer function, size and
//! thread count: build time (fastest wall time of several builds, and the
//! calling thread's on-CPU time when Linux reports it, which a busy machine
//! does not inflate) and the largest errors against the f64 integral, at the
//! table nodes and at random interpolated lookups (optical depths log-uniform
//! in [`LOOKUP_DEPTHS`]).
//!
//! Run: `cargo bench -p nebel_core --bench optics`.

use std::fmt::Write as _;
use std::hint::black_box;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use criterion::{BenchmarkId, Criterion, criterion_group};
use nebel_core::optics::OpticalMode;
use nebel_core::preintegration::{PreintegrationConfig, PreintegrationTable};
use nebel_core::segment::exact_segment;
use nebel_core::transfer::{TransferFunction, TransferPreset};

/// Table sizes swept: (scalar side, depth side).
const SIZES: [(u32, u32); 5] = [(16, 32), (32, 64), (64, 64), (64, 128), (128, 256)];

/// Optical depths of the interpolated lookups (log-uniform): every length a
/// segment can have, from nearly transparent to opaque.
const LOOKUP_DEPTHS: std::ops::RangeInclusive<f64> = 1e-3..=1e3;

/// Samples for each error measurement.
const ERROR_SAMPLES: usize = 4000;

fn config(scalar_size: u32, depth_size: u32) -> PreintegrationConfig {
    PreintegrationConfig {
        scalar_size,
        depth_size,
    }
}

/// The calling thread's on-CPU time (Linux `schedstat`), if available.
fn thread_cpu_time() -> Option<Duration> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let nanos: u64 = text.split_whitespace().next()?.parse().ok()?;
    Some(Duration::from_nanos(nanos))
}

/// Fastest wall time and mean on-CPU time of `runs` builds.
fn time_build(
    tf: &TransferFunction,
    config: PreintegrationConfig,
    threads: usize,
    runs: u32,
) -> (Duration, Option<Duration>) {
    let mut fastest = Duration::MAX;
    let cpu_start = thread_cpu_time();
    for _ in 0..runs {
        let start = Instant::now();
        black_box(PreintegrationTable::build_with_threads(tf, config, threads).unwrap());
        fastest = fastest.min(start.elapsed());
    }
    let cpu = match (cpu_start, thread_cpu_time()) {
        // Only the calling thread's time means something for one thread.
        (Some(a), Some(b)) if threads == 1 => Some((b - a) / runs),
        _ => None,
    };
    (fastest, cpu)
}

fn write_csv() {
    let mut csv = String::from(
        "transfer,scalar_size,depth_size,threads,build_ms_fastest,build_ms_cpu,\
         node_colour,node_chromaticity,node_opacity,node_emission,node_maximum,\
         lookup_colour,lookup_chromaticity,lookup_opacity,lookup_emission,lookup_maximum\n",
    );
    let mut rows: Vec<(TransferPreset, (u32, u32), usize)> = SIZES
        .iter()
        .map(|&size| (TransferPreset::Cloud, size, 1))
        .collect();
    rows.push((TransferPreset::Cloud, (64, 128), 2));
    rows.extend(
        TransferPreset::ALL
            .iter()
            .skip(1)
            .map(|&preset| (preset, (64, 128), 1)),
    );
    for (preset, (n, m), threads) in rows {
        let tf = TransferFunction::preset(preset);
        let config = config(n, m);
        let runs = if n >= 128 { 3 } else { 10 };
        let (fastest, cpu) = time_build(&tf, config, threads, runs);
        let table = PreintegrationTable::build(&tf, config).unwrap();
        let node = table.node_error(ERROR_SAMPLES);
        let lookup = table.interpolation_error(ERROR_SAMPLES, LOOKUP_DEPTHS);
        let cpu = cpu.map_or(String::new(), |c| format!("{:.3}", c.as_secs_f64() * 1e3));
        writeln!(
            csv,
            "{preset:?},{n},{m},{threads},{:.3},{cpu},{:.3e},{:.3e},{:.3e},{:.3e},{:.3e},{:.3e},{:.3e},{:.3e},{:.3e},{:.3e}",
            fastest.as_secs_f64() * 1e3,
            node.colour,
            node.chromaticity,
            node.opacity,
            node.emission,
            node.maximum,
            lookup.colour,
            lookup.chromaticity,
            lookup.opacity,
            lookup.emission,
            lookup.maximum,
        )
        .unwrap();
    }
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../target/nebel");
    std::fs::create_dir_all(&dir).expect("cannot create target/nebel");
    let path = dir.join("preintegration.csv");
    std::fs::write(&path, &csv).expect("cannot write preintegration.csv");
    eprintln!("wrote {}:\n{csv}", path.display());
}

fn table_build(c: &mut Criterion) {
    let tf = TransferFunction::preset(TransferPreset::Cloud);
    let mut group = c.benchmark_group("preintegration_build_one_thread");
    group.sample_size(10);
    for (n, m) in SIZES {
        group.bench_with_input(
            BenchmarkId::from_parameter(format!("{n}x{n}x{m}")),
            &config(n, m),
            |b, &config| b.iter(|| PreintegrationTable::build_with_threads(&tf, config, 1)),
        );
    }
    group.finish();
    c.bench_function("preintegration_build_all_threads/64x64x128", |b| {
        b.iter(|| PreintegrationTable::build(&tf, config(64, 128)));
    });
}

fn segment_integral(c: &mut Criterion) {
    let tf = TransferFunction::preset(TransferPreset::Cloud);
    let mut group = c.benchmark_group("exact_segment");
    for mode in [OpticalMode::Sorted, OpticalMode::Emissive, OpticalMode::Mip] {
        group.bench_function(format!("{mode:?}"), |b| {
            b.iter(|| exact_segment(&tf, mode, black_box(0.2), black_box(0.9), black_box(2.0)));
        });
    }
    group.bench_function("Sorted_optical_depth_1000", |b| {
        b.iter(|| {
            exact_segment(
                &tf,
                OpticalMode::Sorted,
                black_box(0.2),
                black_box(0.9),
                black_box(2000.0),
            )
        });
    });
    group.finish();
}

criterion_group!(benches, table_build, segment_integral);

fn main() {
    write_csv();
    benches();
    Criterion::default().configure_from_args().final_summary();
}
