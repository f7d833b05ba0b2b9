//! The paper's cloud layer (Röttger and Ertl 2003 §5, thesis ch. 11): a lit 513 × 513 × 65
//! procedural cumulus field (100.7 million tetrahedra at full resolution), the
//! one of `assets/scenes/cloud_flythrough.ron`, refined and emitted along that
//! scene's flight into the layer for a sweep of the accuracy `c`.
//!
//! Per setting of each criterion (the distance criterion of Röttger and
//! Ertl 2003 Eq. 1 along `c`, the screen error along its tolerance): the
//! per-frame update (`refine` with the view frustum and the zero-opacity
//! test, then `lod_batch_with` for the lit cells: morphed light as scalar,
//! morphed density as modulator), median and maximum over 40 frames of the
//! path on a 640 × 400 target (the scene's), and the cells drawn (median,
//! maximum); the default tolerance also on a 1920 × 1200 target. Also the
//! one-off costs (cloud generation, light field with the shadow sweep,
//! hierarchy) and the hierarchy's bytes per grid point. Writes
//! `target/nebel/cloud_layer_sweep.csv`.
//!
//! Image error against full resolution cannot be measured on this field
//! here (100.7 million cells do not fit a software rasterizer); `nebel
//! bench-lod benches/scenes/cloud_layer_129.ron` measures it on the same
//! layer at a quarter of the resolution per horizontal axis.
//!
//! Run: `cargo bench -p nebel_lod --bench cloud_layer`.

use std::time::Instant;

use glam::{DAffine3, DMat4, DVec3, UVec2};
use nebel_core::field::{CloudLighting, CloudNoise, DensityGrid, light_field};
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_lod::octree::{CellScalars, LodCriterion, RefinementSettings, lod_batch_with, refine};
use nebel_lod::{View, VolumeHierarchy};

const DIMS: [usize; 3] = [513, 65, 513];
const FRAMES: usize = 40;
const ACCURACIES: [f64; 7] = [0.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0];
const TOLERANCES: [f64; 6] = [10.0, 3.0, 1.0, 0.3, 0.1, 0.03];

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
        ambient: 0.2,
        diffuse: 0.8,
        sun_direction: DVec3::new(0.45, 0.6, 0.3),
        shadow_extinction: 0.02,
        lambert: true,
        ..CloudLighting::default()
    };
    let started = Instant::now();
    let light = light_field(&grid, &lighting).expect("valid lighting");
    let light_ms = started.elapsed().as_secs_f64() * 1e3;
    let started = Instant::now();
    let hierarchy = VolumeHierarchy::with_light(&grid, &light, 4.0).expect("2^n+1 grid");
    let hierarchy_ms = started.elapsed().as_secs_f64() * 1e3;
    let full_cells = 6 * (DIMS[0] - 1) * (DIMS[1] - 1) * (DIMS[2] - 1);
    println!(
        "cloud layer {DIMS:?}: generation {generation_ms:.0} ms, light field {light_ms:.0} ms, hierarchy {hierarchy_ms:.0} ms, {:.1} bytes per grid point, {full_cells} cells at full resolution",
        hierarchy.bytes_per_point()
    );

    // The scene's transfer function (the isotropic lit cloud, density scale 0.03).
    let transfer = TransferFunction::preset(TransferPreset::CloudLight)
        .scale_density(0.03)
        .expect("a finite scale");
    // The flight of cloud_flythrough.ron: 4 s, fov 60°, aspect 1.6.
    let (start, end) = (
        DVec3::new(-3600.0, 1700.0, -1800.0),
        DVec3::new(-1200.0, 900.0, -600.0),
    );
    let (look_start, look_end) = (DVec3::new(0.0, 900.0, 0.0), DVec3::new(600.0, 850.0, 300.0));
    let projection = DMat4::perspective_infinite_reverse_rh(60f64.to_radians(), 1.6, 1.0);

    let mut csv = String::from(
        "criterion,value,width,height,update_ms_median,update_ms_max,cells_median,cells_max,full_resolution_cells,bytes_per_point\n",
    );
    let scene_size = UVec2::new(640, 400);
    let runs = ACCURACIES
        .iter()
        .map(|&c| (LodCriterion::distance(c), scene_size))
        .chain(
            TOLERANCES
                .iter()
                .map(|&t| (LodCriterion::screen_error(t), scene_size)),
        )
        .chain([(LodCriterion::default(), UVec2::new(1920, 1200))]);
    for (criterion, viewport) in runs {
        let settings = RefinementSettings {
            criterion,
            scalars: CellScalars::LightModulatedByDensity,
            ..RefinementSettings::default()
        };
        let (mut times, mut cells) = (Vec::new(), Vec::new());
        for frame in 0..FRAMES {
            let t = frame as f64 / (FRAMES - 1) as f64;
            let eye = start.lerp(end, t);
            let camera = DMat4::look_at_rh(eye, look_start.lerp(look_end, t), DVec3::Y);
            let view =
                View::new(DAffine3::IDENTITY, eye, viewport).with_projection(projection * camera);
            let started = Instant::now();
            let refinement =
                refine(&hierarchy, &view, &transfer, &settings).expect("valid settings");
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
        let (name, value) = match criterion {
            LodCriterion::Distance { accuracy } => ("distance", accuracy),
            LodCriterion::ScreenError { image_error } => ("screen_error", image_error),
        };
        println!(
            "{name} {value:>6} at {}x{}: update {time_median:7.2} ms median, {time_max:7.2} ms max; cells {cells_median:>8} median, {cells_max:>8} max",
            viewport.x, viewport.y
        );
        csv.push_str(&format!(
            "{name},{value},{},{},{time_median},{time_max},{cells_median},{cells_max},{full_cells},{}\n",
            viewport.x,
            viewport.y,
            hierarchy.bytes_per_point()
        ));
    }
    let out = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/nebel");
    std::fs::create_dir_all(&out).expect("target/nebel is writable");
    std::fs::write(out.join("cloud_layer_sweep.csv"), csv).expect("CSV written");
    println!("wrote {}", out.join("cloud_layer_sweep.csv").display());
}
