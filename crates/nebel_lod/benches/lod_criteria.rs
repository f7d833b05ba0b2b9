//! The octree's two refinement criteria on the lit cumulus layer of
//! `assets/scenes/cloud_flythrough.ron`, measured in images: cells drawn,
//! update time and image error against full resolution, on the CPU, without
//! a GPU.
//!
//! - `cloud_layer_129`: the layer at 129 × 17 × 129 points seen across from
//!   its edge (the view of `benches/scenes/cloud_layer_129.ron`), scored
//!   against the full-resolution batch (`c = ∞`, 1.57 million cells before
//!   culling).
//! - `cloud_flythrough`: the paper's 513 × 65 × 513 field at four moments of
//!   the scene's flight (a quarter, half, three quarters, the end inside a
//!   cloud), scored against the distance criterion at `c = 256` (1.7 to 2.1
//!   million cells; full resolution, 100.7 million, does not fit).
//!
//! Per setting of each criterion (the distance criterion of Röttger and Ertl
//! 2003 Eq. 1 along `c`, the screen error along its tolerance): the cells of
//! the lit batch, the update (`refine` and `lod_batch_with`, one thread) and
//! the RMSE and largest error over linear RGB of the exact CPU cell
//! reference (`nebel_reference::render`: sorted emission-absorption with the
//! light as segment-length modulator, the scene's sky behind) at 320 × 200
//! against the reference image. Writes `target/nebel/lod_criteria.csv`.
//!
//! Run: `cargo bench -p nebel_lod --bench lod_criteria` (about two minutes
//! here, most of it the 513 field and the reference images).

use std::time::Instant;

use glam::DVec3;
use nebel_core::field::{CloudLighting, CloudNoise, DensityGrid, light_field};
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_lod::octree::{CellScalars, LodCriterion, RefinementSettings, lod_batch_with, refine};
use nebel_lod::{Cells, View, VolumeHierarchy};
use nebel_reference::image_metrics::compare;

mod support;

/// The image size of every measurement.
const SIZE: [u32; 2] = [320, 200];

const ACCURACIES: [f64; 7] = [0.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0];
const TOLERANCES: [f64; 6] = [0.3, 0.1, 0.03, 0.01, 0.003, 0.001];

/// The lit layer and what draws it.
struct Layer {
    hierarchy: VolumeHierarchy,
    transfer: TransferFunction,
}

impl Layer {
    /// The cumulus layer of `cloud_flythrough.ron` at `dims` points over its
    /// 5120 × 640 × 5120 m box, `octaves` of detail, lit as `lighting`.
    fn new(dims: [usize; 3], octaves: usize, lighting: CloudLighting) -> Self {
        let noise = CloudNoise {
            seed: 11,
            coverage: 0.42,
            octaves,
            wavelength: 1800.0,
            ..CloudNoise::default()
        };
        let spacing = DVec3::splat(5120.0 / (dims[0] - 1) as f64);
        let origin = DVec3::new(-2560.0, 600.0, -2560.0);
        let grid = DensityGrid::cloud(dims, spacing, origin, &noise, 0.0).expect("valid cloud");
        let light = light_field(&grid, &lighting).expect("valid lighting");
        Self {
            hierarchy: VolumeHierarchy::with_light(&grid, &light, 4.0).expect("2^n+1 grid"),
            transfer: TransferFunction::preset(TransferPreset::CloudLight)
                .scale_density(0.03)
                .expect("a finite scale"),
        }
    }

    /// The lit batch for `view` by `criterion`, and the update's time (ms).
    fn batch(&self, view: &View, criterion: LodCriterion) -> (Cells, f64) {
        let settings = RefinementSettings {
            criterion,
            scalars: CellScalars::LightModulatedByDensity,
            ..RefinementSettings::default()
        };
        let started = Instant::now();
        let refinement =
            refine(&self.hierarchy, view, &self.transfer, &settings).expect("valid settings");
        let batch = lod_batch_with(
            &self.hierarchy,
            &refinement,
            view,
            CellScalars::LightModulatedByDensity,
        )
        .expect("valid view");
        (batch, started.elapsed().as_secs_f64() * 1e3)
    }
}

/// Sweeps both criteria on one view against `reference` and appends the
/// rows to `csv`.
fn sweep(
    csv: &mut String,
    name: &str,
    layer: &Layer,
    eye: DVec3,
    target: DVec3,
    reference: LodCriterion,
) {
    let (view, camera) = support::view(eye, target, SIZE);
    let (full, _) = layer.batch(&view, reference);
    let reference_image = support::image(&full, camera, &layer.transfer);
    println!("{name}: reference {reference:?}, {} cells", full.len());
    let criteria = ACCURACIES
        .iter()
        .map(|&c| LodCriterion::distance(c))
        .chain(TOLERANCES.iter().map(|&t| LodCriterion::screen_error(t)));
    for criterion in criteria {
        let (batch, update_ms) = layer.batch(&view, criterion);
        let error = compare(
            &support::image(&batch, camera, &layer.transfer),
            &reference_image,
        )
        .expect("same size");
        let (kind, value) = match criterion {
            LodCriterion::Distance { accuracy } => ("distance", accuracy),
            LodCriterion::ScreenError { image_error } => ("screen_error", image_error),
        };
        println!(
            "{name}: {kind} {value:>6}: {:>8} cells, update {update_ms:7.2} ms, RMSE {:.2e}, max {:.2e}",
            batch.len(),
            error.rmse,
            error.max_abs
        );
        csv.push_str(&format!(
            "{name},{kind},{value},{},{update_ms},{},{}\n",
            batch.len(),
            error.rmse,
            error.max_abs
        ));
    }
}

fn main() {
    let mut csv = String::from("view,criterion,value,cells,update_ms,rmse,max_abs\n");

    let layer = Layer::new(
        [129, 17, 129],
        4,
        CloudLighting {
            ambient: 0.3,
            diffuse: 0.7,
            sun_direction: DVec3::new(0.45, 0.6, 0.3),
            shadow_extinction: 0.008,
            lambert: true,
            ..CloudLighting::default()
        },
    );
    sweep(
        &mut csv,
        "cloud_layer_129",
        &layer,
        DVec3::new(-3300.0, 1000.0, -900.0),
        DVec3::new(0.0, 850.0, 300.0),
        LodCriterion::distance(f64::INFINITY),
    );

    let layer = Layer::new(
        [513, 65, 513],
        6,
        CloudLighting {
            ambient: 0.2,
            diffuse: 0.8,
            sun_direction: DVec3::new(0.45, 0.6, 0.3),
            shadow_extinction: 0.02,
            lambert: true,
            ..CloudLighting::default()
        },
    );
    for t in [0.25, 0.5, 0.75, 1.0] {
        let eye = DVec3::new(-3600.0, 1700.0, -1800.0).lerp(DVec3::new(-1200.0, 900.0, -600.0), t);
        let target = DVec3::new(0.0, 900.0, 0.0).lerp(DVec3::new(600.0, 850.0, 300.0), t);
        sweep(
            &mut csv,
            &format!("cloud_flythrough_t{t}"),
            &layer,
            eye,
            target,
            LodCriterion::distance(256.0),
        );
    }

    let out = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/nebel");
    std::fs::create_dir_all(&out).expect("target/nebel is writable");
    std::fs::write(out.join("lod_criteria.csv"), csv).expect("CSV written");
    println!("wrote {}", out.join("lod_criteria.csv").display());
}
