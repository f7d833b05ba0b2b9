//! `nebel bench-lod`: run time against image error of a grid volume drawn
//! through the octree C-LOD, along a sweep of the accuracy `c` (DESIGN.md §8,
//! paper 000 §3).
//!
//! For each `c` the scene's one grid volume is rendered with
//! `lod: (accuracy: c)` (the scene's `min_accuracy`, default 4) and once at
//! full resolution (a lit volume, which is always drawn through the octree,
//! with `c = ∞`, which draws exactly the full-resolution cells), with
//! tonemapping and MSAA off; every image is scored against the
//! full-resolution image and against the exact reference of the full
//! trilinear field. The result is a CSV (`c, cells drawn, frame median ms,
//! RMSE against full resolution, RMSE, max abs, PSNR` against the reference)
//! and a PNG plot
//! of frame time (x, linear from 0) against RMSE (y, log10), one dot per `c`
//! joined in order, the full-resolution point in red. The plot has no text:
//! the CSV beside it has the numbers.

use std::path::Path;

use image::{Rgb, RgbImage};
use nebel_reference::image_metrics::{ImageErrorMetrics, compare};
use nebel_scene::{LodDescription, SceneDescription};

use crate::headless::render_headless;
use crate::scene_setup::SceneSetupPlugin;
use nebel_scene::reference::{reference_image, save_reference};

/// One point of the sweep.
#[derive(Clone, Debug, PartialEq)]
pub struct SweepPoint {
    /// The accuracy `c`; `None` for full resolution.
    pub accuracy: Option<f64>,
    /// Cells in the batch of the last frame.
    pub cells_drawn: f64,
    /// Median wall time per frame, ms.
    pub frame_ms: f64,
    /// RMSE over linear RGB against the full-resolution image.
    pub rmse_full: f64,
    /// RMSE over linear RGB against the exact reference.
    pub rmse: f64,
    /// Largest absolute error over linear RGB.
    pub max_abs: f64,
    /// PSNR, dB.
    pub psnr: f64,
}

impl SweepPoint {
    /// The error the plot shows: the RMSE against the exact reference, or
    /// against the full-resolution (comparison) image when there is none.
    pub fn error(&self) -> f64 {
        if self.rmse.is_nan() {
            self.rmse_full
        } else {
            self.rmse
        }
    }
}

/// Runs the sweep and writes `DIR/lod_sweep.csv`, `DIR/lod_sweep.png` and the
/// images. `scene` must have exactly one volume, with a grid source.
///
/// `comparison_accuracy`: for a volume too large to draw at full resolution
/// (the paper's 513 × 65 × 513 field), the image every `c` is scored against
/// is drawn at this `c` instead, and the exact reference is skipped (its
/// columns are NaN); the plot then shows the RMSE against that image.
pub fn run_lod_sweep(
    scene_path: &Path,
    mut scene: SceneDescription,
    accuracies: &[f64],
    comparison_accuracy: Option<f64>,
    out_dir: &Path,
) -> Result<Vec<SweepPoint>, String> {
    if scene.volumes.len() != 1 {
        return Err(format!(
            "{}: bench-lod sweeps exactly one volume, the scene has {}",
            scene_path.display(),
            scene.volumes.len()
        ));
    }
    scene.camera.tonemapping = false;
    scene.camera.msaa = 1;
    std::fs::create_dir_all(out_dir).map_err(|e| format!("{}: {e}", out_dir.display()))?;
    let min_accuracy = scene.volumes[0].lod.map_or(4.0, |lod| lod.min_accuracy);

    let lit = scene.volumes[0].lighting.is_some();
    let full_lod = lit.then_some(LodDescription {
        accuracy: f64::INFINITY,
        min_accuracy,
    });
    let comparison_lod = match comparison_accuracy {
        Some(accuracy) => Some(LodDescription {
            accuracy,
            min_accuracy,
        }),
        None => full_lod,
    };
    let reference = match comparison_accuracy {
        Some(_) => None,
        None => {
            let mut full = scene.clone();
            full.volumes[0].lod = full_lod;
            let volumes = full.build_volumes(scene_path).map_err(|e| e.to_string())?;
            let reference = reference_image(&full, volumes, true).map_err(|e| e.to_string())?;
            save_reference(&reference, &out_dir.join("reference.png"))
                .map_err(|e| e.to_string())?;
            Some(reference)
        }
    };

    let mut points = Vec::with_capacity(accuracies.len() + 1);
    let mut images = Vec::with_capacity(accuracies.len() + 1);
    let runs = accuracies.iter().map(|c| Some(*c)).chain([None]);
    for accuracy in runs {
        let mut variant = scene.clone();
        variant.volumes[0].lod = match accuracy {
            Some(accuracy) => Some(LodDescription {
                accuracy,
                min_accuracy,
            }),
            None => comparison_lod,
        };
        let name = match (accuracy, comparison_accuracy) {
            (Some(c), _) => format!("c_{c}"),
            (None, Some(c)) => format!("comparison_c_{c}"),
            (None, None) => String::from("full_resolution"),
        };
        let image_path = out_dir.join(format!("{name}.png"));
        let setup = SceneSetupPlugin::new(variant, scene_path).map_err(|e| e.to_string())?;
        let stats = render_headless(setup, &image_path, true).map_err(|e| e.to_string())?;
        let image = nebel_reference::image_metrics::load_png_linear(&image_path)
            .map_err(|e| e.to_string())?;
        let metrics = match &reference {
            Some(reference) => compare(&image, reference).map_err(|e| e.to_string())?,
            None => ImageErrorMetrics {
                rmse: f64::NAN,
                max_abs: f64::NAN,
                psnr: f64::NAN,
            },
        };
        let cells_drawn = stats
            .effects
            .get("volume")
            .and_then(|volume| volume.get("cells_drawn"))
            .copied()
            .unwrap_or(0.0);
        points.push(SweepPoint {
            accuracy,
            cells_drawn,
            frame_ms: stats.frame_wall_ms.median,
            rmse_full: 0.0,
            rmse: metrics.rmse,
            max_abs: metrics.max_abs,
            psnr: metrics.psnr,
        });
        images.push(image);
    }

    // The full-resolution (or comparison) image is the last one.
    if let Some(full_image) = images.last() {
        for (point, image) in points.iter_mut().zip(&images) {
            point.rmse_full = compare(image, full_image).map_err(|e| e.to_string())?.rmse;
        }
    }
    let mut csv = String::from("c,cells_drawn,frame_ms_median,rmse_vs_full,rmse,max_abs,psnr_db\n");
    for point in &points {
        let c = match (point.accuracy, comparison_accuracy) {
            (Some(c), _) => c.to_string(),
            (None, Some(c)) => format!("comparison {c}"),
            (None, None) => String::from("full"),
        };
        csv.push_str(&format!(
            "{c},{},{},{},{},{},{}\n",
            point.cells_drawn,
            point.frame_ms,
            point.rmse_full,
            point.rmse,
            point.max_abs,
            point.psnr
        ));
    }
    let csv_path = out_dir.join("lod_sweep.csv");
    std::fs::write(&csv_path, csv).map_err(|e| format!("{}: {e}", csv_path.display()))?;
    let plot_path = out_dir.join("lod_sweep.png");
    plot(&points)
        .save(&plot_path)
        .map_err(|e| format!("{}: {e}", plot_path.display()))?;
    Ok(points)
}

const PLOT_WIDTH: u32 = 480;
const PLOT_HEIGHT: u32 = 320;
const PLOT_MARGIN: u32 = 24;

/// Frame time (x) against log10 RMSE (y): grey axes, black dots joined in
/// sweep order, the full-resolution dot red.
pub fn plot(points: &[SweepPoint]) -> RgbImage {
    let mut image = RgbImage::from_pixel(PLOT_WIDTH, PLOT_HEIGHT, Rgb([255, 255, 255]));
    let left = PLOT_MARGIN as f64;
    let right = f64::from(PLOT_WIDTH - PLOT_MARGIN);
    let top = PLOT_MARGIN as f64;
    let bottom = f64::from(PLOT_HEIGHT - PLOT_MARGIN);
    let grey = Rgb([160, 160, 160]);
    line(&mut image, (left, bottom), (right, bottom), grey);
    line(&mut image, (left, bottom), (left, top), grey);

    let finite: Vec<&SweepPoint> = points
        .iter()
        .filter(|p| p.frame_ms.is_finite() && p.error() > 0.0)
        .collect();
    let Some(max_ms) = finite.iter().map(|p| p.frame_ms).reduce(f64::max) else {
        return image;
    };
    let logs: Vec<f64> = finite.iter().map(|p| p.error().log10()).collect();
    let (low, high) = logs
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(*v), hi.max(*v))
        });
    let span = (high - low).max(1e-9);
    let position = |point: &SweepPoint| {
        let x = left + (right - left) * point.frame_ms / max_ms.max(1e-9);
        let y = bottom - (bottom - top) * (point.error().log10() - low) / span;
        (x, y)
    };
    let swept: Vec<(f64, f64)> = finite
        .iter()
        .filter(|p| p.accuracy.is_some())
        .map(|p| position(p))
        .collect();
    for pair in swept.windows(2) {
        line(&mut image, pair[0], pair[1], Rgb([0, 0, 0]));
    }
    for point in &finite {
        let colour = if point.accuracy.is_some() {
            Rgb([0, 0, 0])
        } else {
            Rgb([220, 30, 30])
        };
        dot(&mut image, position(point), colour);
    }
    image
}

fn dot(image: &mut RgbImage, (x, y): (f64, f64), colour: Rgb<u8>) {
    for dy in -2..=2 {
        for dx in -2..=2 {
            put(image, x + f64::from(dx), y + f64::from(dy), colour);
        }
    }
}

fn line(image: &mut RgbImage, from: (f64, f64), to: (f64, f64), colour: Rgb<u8>) {
    let steps = (to.0 - from.0)
        .abs()
        .max((to.1 - from.1).abs())
        .ceil()
        .max(1.0) as u32;
    for step in 0..=steps {
        let t = f64::from(step) / f64::from(steps);
        put(
            image,
            from.0 + (to.0 - from.0) * t,
            from.1 + (to.1 - from.1) * t,
            colour,
        );
    }
}

fn put(image: &mut RgbImage, x: f64, y: f64, colour: Rgb<u8>) {
    let (x, y) = (x.round(), y.round());
    if x >= 0.0 && y >= 0.0 && x < f64::from(image.width()) && y < f64::from(image.height()) {
        image.put_pixel(x as u32, y as u32, colour);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(accuracy: Option<f64>, frame_ms: f64, rmse: f64) -> SweepPoint {
        SweepPoint {
            accuracy,
            cells_drawn: 0.0,
            frame_ms,
            rmse_full: rmse,
            rmse,
            max_abs: rmse,
            psnr: 0.0,
        }
    }

    #[test]
    fn plot_puts_fast_coarse_points_left_and_high() {
        let points = [
            point(Some(1.0), 10.0, 1e-1),
            point(Some(64.0), 50.0, 1e-2),
            point(None, 100.0, 1e-3),
        ];
        let image = plot(&points);
        let black = Rgb([0, 0, 0]);
        let red = Rgb([220, 30, 30]);
        // The coarsest point: x = 24 + 432·0.1, y = the top margin.
        assert_eq!(*image.get_pixel(24 + 43, 24), black);
        // Full resolution: the right edge, the bottom axis, red.
        assert_eq!(*image.get_pixel(480 - 24 - 1, 320 - 24 - 1), red);
        assert_eq!(*image.get_pixel(470, 10), Rgb([255, 255, 255]));
    }

    #[test]
    fn plot_of_nothing_is_blank_axes() {
        let image = plot(&[]);
        assert_eq!(*image.get_pixel(100, 100), Rgb([255, 255, 255]));
        assert_eq!(*image.get_pixel(24, 200), Rgb([160, 160, 160]));
    }
}
