//! The paper's cloud layer (Röttger and Ertl 2003 §5, thesis ch. 11): a lit 513 × 513 × 65
//! procedural cumulus field (83.9 million tetrahedra at full resolution), the
//! one of `assets/scenes/cloud_flythrough.ron`, refined and emitted along that
//! scene's flight into the layer for a sweep of the accuracy `c`.
//!
//! Per `c`: the per-frame update (`refine` with the view frustum and the
//! zero-opacity test, then `lod_batch_with` for the lit cells: morphed light
//! as scalar, morphed density as modulator), median and maximum over 40
//! frames of the path, and the cells drawn (median, maximum). Also the
//! one-off costs (cloud generation, light field with the shadow sweep,
//! hierarchy) and the hierarchy's bytes per grid point. Writes
//! `target/nebel/cloud_layer_sweep.csv`.
//!
//! Image error against full resolution cannot be measured on this field
//! here (83.9 million cells do not fit a software rasterizer); `nebel
//! bench-lod benches/scenes/cloud_layer_129.ron` measures it on the same
//! layer at a quarter of the resolution per horizontal axis.
//!
//! Run: `cargo bench -p nebel_lod --bench cloud_layer`.

use std::time::Instant;

use glam::{DAffine3, DMat4, DVec3, UVec2};
use nebel_core::field::{CloudLighting, CloudNoise, DensityGrid, light_field};
use nebel_core::transfer::{ControlPoint, TransferFunction};
use nebel_lod::octree::{CellScalars, RefinementSettings, lod_batch_with, refine};
use nebel_lod::{Frustum, View, VolumeHierarchy};

const DIMS: [usize; 3] = [513, 65, 513];
const FRAMES: usize = 40;
const ACCURACIES: [f64; 7] = [0.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0];

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

fn main() {
    let noise = CloudNoise {
        seed: 11,
        coverage: 0.42,
        octaves: 6,
        wavelength: 1800.0,
        ..CloudNoise::default()
    };
    let origin = DVec3::new(-2560.0, 600.0, -2560.0);
    let started = Instant::now();
    let grid =
        DensityGrid::cloud(DIMS, DVec3::splat(10.0), origin, &noise, 0.0).expect("valid cloud");
    let generation_ms = started.elapsed().as_secs_f64() * 1e3;
    let lighting = CloudLighting {
        ambient: 0.3,
        diffuse: 0.7,
        sun_direction: DVec3::new(0.45, 0.6, 0.3),
        shadow_extinction: 0.008,
        lambert: true,
    };
    let started = Instant::now();
    let light = light_field(&grid, &lighting).expect("valid lighting");
    let light_ms = started.elapsed().as_secs_f64() * 1e3;
    let started = Instant::now();
    let hierarchy = VolumeHierarchy::with_light(&grid, &light, 4.0).expect("2^n+1 grid");
    let hierarchy_ms = started.elapsed().as_secs_f64() * 1e3;
    let full_cells = 5 * (DIMS[0] - 1) * (DIMS[1] - 1) * (DIMS[2] - 1);
    println!(
        "cloud layer {DIMS:?}: generation {generation_ms:.0} ms, light field {light_ms:.0} ms, hierarchy {hierarchy_ms:.0} ms, {:.1} bytes per grid point, {full_cells} cells at full resolution",
        hierarchy.bytes_per_point()
    );

    // The opacity is the density itself (ρ = f): only density 0 is empty.
    let point = |s: f32| ControlPoint {
        s,
        kappa: [0.0; 3],
        rho: s,
    };
    let opacity = TransferFunction::new([point(0.0), point(1.0)]).expect("valid");
    // The flight of cloud_flythrough.ron: 4 s, fov 60°, 640 × 400.
    let (start, end) = (
        DVec3::new(-3600.0, 1150.0, -400.0),
        DVec3::new(-700.0, 930.0, -60.0),
    );
    let (look_start, look_end) = (DVec3::new(0.0, 900.0, 0.0), DVec3::new(800.0, 900.0, 150.0));
    let projection = DMat4::perspective_infinite_reverse_rh(60f64.to_radians(), 1.6, 1.0);

    let mut csv = String::from(
        "c,update_ms_median,update_ms_max,cells_median,cells_max,full_resolution_cells,bytes_per_point\n",
    );
    for accuracy in ACCURACIES {
        let settings = RefinementSettings { accuracy };
        let (mut times, mut cells) = (Vec::new(), Vec::new());
        for frame in 0..FRAMES {
            let t = frame as f64 / (FRAMES - 1) as f64;
            let eye = start.lerp(end, t);
            let camera = DMat4::look_at_rh(eye, look_start.lerp(look_end, t), DVec3::Y);
            let frustum = Frustum::from_view_projection(projection * camera).expect("a view");
            // A 1920 × 1200 target, the projection's aspect ratio of 1.6.
            let view =
                View::new(DAffine3::IDENTITY, eye, UVec2::new(1920, 1200)).with_frustum(frustum);
            let started = Instant::now();
            let refinement =
                refine(&hierarchy, &view, &opacity, &settings).expect("valid settings");
            let batch = lod_batch_with(
                &hierarchy,
                &refinement,
                &view,
                CellScalars::LightModulatedByDensity,
            )
            .expect("valid eye");
            times.push(started.elapsed().as_secs_f64() * 1e3);
            cells.push(batch.len() as f64);
        }
        let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        let (time_max, cells_max) = (max(&times), max(&cells));
        let (time_median, cells_median) = (median(&mut times), median(&mut cells));
        println!(
            "c = {accuracy:>5}: update {time_median:7.2} ms median, {time_max:7.2} ms max; cells {cells_median:>8} median, {cells_max:>8} max"
        );
        csv.push_str(&format!(
            "{accuracy},{time_median},{time_max},{cells_median},{cells_max},{full_cells},{}\n",
            hierarchy.bytes_per_point()
        ));
    }
    let out = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/nebel");
    std::fs::create_dir_all(&out).expect("target/nebel is writable");
    std::fs::write(out.join("cloud_layer_sweep.csv"), csv).expect("CSV written");
    println!("wrote {}", out.join("cloud_layer_sweep.csv").display());
}
