//! `nebel bench-lod`: run time against image error of a grid volume drawn
//! through the octree C-LOD, along a sweep of the accuracy `c` (Röttger and
//! Ertl, "Fast Volumetric Display of Natural Gaseous Phenomena", 2003, §3).
//!
//! For each `c` the scene's one grid volume is rendered with
//! `lod: (accuracy: c)` (the scene's `min_accuracy`, default 4) and once at
//! full resolution (a lit volume, which is always drawn through the octree,
//! with `c = ∞`, which draws exactly the full-resolution cells), with
//! tonemapping and MSAA off; every image is scored against the
//! full-resolution image and against the exact reference of the full
//! trilinear field. The result is a CSV (`c, cells drawn, frame median ms,
//! RMSE against full resolution, RMSE, max abs, PSNR` against the reference)
//! and an SVG plot of the median frame time (x, ms, from 0) against the RMSE
//! (y, logarithmic), with axes, ticks, labels and a legend: one labelled dot
//! per `c` joined in sweep order, the full-resolution point in red (the
//! comparison image of `--comparison-accuracy` scores 0 against itself and
//! has no dot). SVG needs no font files: the labels are SVG text.

use std::path::Path;

use nebel_lod::OctreeSettings;
use nebel_reference::image_metrics::{ImageErrorMetrics, compare};
use nebel_scene::reference::{reference_image, save_reference};
use nebel_scene::{LodDescription, SceneDescription};
use plotters::coord::combinators::IntoLogRange;
use plotters::prelude::*;

use crate::error::CommandError;
use crate::headless::HeadlessOptions;
use crate::progress::reference_bar;
use crate::scene_setup::SceneSetupPlugin;

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

/// Runs the sweep and writes `DIR/lod_sweep.csv`, `DIR/lod_sweep.svg` and the
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
) -> Result<Vec<SweepPoint>, CommandError> {
    if scene.volumes.len() != 1 {
        return Err(CommandError::Unsuitable {
            path: scene_path.to_owned(),
            reason: format!(
                "bench-lod sweeps exactly one volume, the scene has {}",
                scene.volumes.len()
            ),
        });
    }
    scene.camera.tonemapping = false;
    scene.camera.msaa = 1;
    std::fs::create_dir_all(out_dir).map_err(CommandError::write(out_dir))?;
    let min_accuracy = scene.volumes[0]
        .lod
        .map_or(OctreeSettings::DEFAULT_MIN_ACCURACY, |lod| lod.min_accuracy);

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
            let volumes = full.build_volumes(scene_path)?;
            let (bar, report) = reference_bar(true);
            let reference = reference_image(&full, volumes, Some(&report))?;
            bar.finish_and_clear();
            save_reference(&reference, &out_dir.join("reference.png"))?;
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
        let setup = SceneSetupPlugin::new(variant, scene_path)?;
        let options = HeadlessOptions {
            progress: true,
            ..HeadlessOptions::default()
        };
        let stats = setup.render_headless(options, &image_path)?;
        let image = nebel_reference::image_metrics::load_png_linear(&image_path)?;
        let metrics = match &reference {
            Some(reference) => compare(&image, reference)?,
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
            point.rmse_full = compare(image, full_image)?.rmse;
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
    std::fs::write(&csv_path, csv).map_err(CommandError::write(&csv_path))?;
    let plot_path = out_dir.join("lod_sweep.svg");
    let svg = plot(&points, comparison_accuracy).map_err(|reason| CommandError::Plot {
        path: plot_path.clone(),
        reason,
    })?;
    std::fs::write(&plot_path, svg).map_err(CommandError::write(&plot_path))?;
    Ok(points)
}

/// Plot size, SVG pixels.
const PLOT_SIZE: (u32, u32) = (640, 420);

/// The SVG plot of the sweep (see the module docs); `comparison_accuracy`
/// names the last point when it is not full resolution.
pub fn plot(points: &[SweepPoint], comparison_accuracy: Option<f64>) -> Result<String, String> {
    let shown: Vec<&SweepPoint> = points
        .iter()
        .filter(|p| p.frame_ms.is_finite() && p.error().is_finite() && p.error() > 0.0)
        .collect();
    let max_ms = shown.iter().map(|p| p.frame_ms).fold(1.0, f64::max) * 1.1;
    let (low, high) = shown
        .iter()
        .map(|p| p.error())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), e| {
            (lo.min(e), hi.max(e))
        });
    let (low, high) = if low <= high {
        (low / 2.0, high * 2.0)
    } else {
        (1e-4, 1.0)
    };
    let error_label = if points.iter().any(|p| p.rmse.is_finite()) {
        "RMSE against the exact reference (linear RGB)"
    } else {
        "RMSE against the comparison image (linear RGB)"
    };
    let full_label = match comparison_accuracy {
        Some(c) => format!("comparison, c = {c}"),
        None => String::from("full resolution"),
    };
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, PLOT_SIZE).into_drawing_area();
        let error = |e: DrawingAreaErrorKind<_>| e.to_string();
        root.fill(&WHITE).map_err(error)?;
        let mut chart = ChartBuilder::on(&root)
            .caption("Frame time against image error along c", ("sans-serif", 18))
            .margin(16)
            .x_label_area_size(40)
            .y_label_area_size(64)
            .build_cartesian_2d(0.0..max_ms, (low..high).log_scale())
            .map_err(error)?;
        chart
            .configure_mesh()
            .x_desc("median frame time (ms)")
            .y_desc(error_label)
            .y_label_formatter(&|v| format!("{v:.0e}"))
            .draw()
            .map_err(error)?;
        let swept: Vec<(f64, f64)> = shown
            .iter()
            .filter(|p| p.accuracy.is_some())
            .map(|p| (p.frame_ms, p.error()))
            .collect();
        chart
            .draw_series(LineSeries::new(swept.iter().copied(), &BLACK))
            .map_err(error)?
            .label("octree C-LOD, one dot per c")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
        chart
            .draw_series(shown.iter().filter_map(|p| {
                let c = p.accuracy?;
                Some(
                    EmptyElement::at((p.frame_ms, p.error()))
                        + Circle::new((0, 0), 4, BLACK.filled())
                        + Text::new(format!("c = {c}"), (6, -14), ("sans-serif", 12)),
                )
            }))
            .map_err(error)?;
        // The comparison image scores 0 against itself: no dot on a log axis.
        let full: Vec<&&SweepPoint> = shown.iter().filter(|p| p.accuracy.is_none()).collect();
        if !full.is_empty() {
            chart
                .draw_series(
                    full.iter()
                        .map(|p| Circle::new((p.frame_ms, p.error()), 5, RED.filled())),
                )
                .map_err(error)?
                .label(full_label)
                .legend(|(x, y)| Circle::new((x + 10, y), 5, RED.filled()));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.9))
            .border_style(BLACK)
            .draw()
            .map_err(error)?;
        root.present().map_err(error)?;
    }
    Ok(svg)
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
    fn the_plot_has_axes_labels_a_legend_and_a_dot_per_point() {
        let points = [
            point(Some(1.0), 10.0, 1e-1),
            point(Some(64.0), 50.0, 1e-2),
            point(None, 100.0, 1e-3),
        ];
        let svg = plot(&points, None).unwrap();
        for text in [
            "median frame time (ms)",
            "RMSE against the exact reference",
            "c = 64",
            "full resolution",
            "octree C-LOD, one dot per c",
        ] {
            assert!(svg.contains(text), "the plot lacks {text:?}");
        }
        // Two black dots, the red one and the legend's red dot.
        assert_eq!(svg.matches("<circle").count(), 4, "{svg}");
        // The sweep's dots are left of the full-resolution one, the slower.
        let circles: Vec<(f64, String)> = svg
            .split("<circle")
            .skip(1)
            .map(|circle| {
                let attribute = |name: &str| {
                    let start = circle.find(&format!("{name}=\"")).unwrap() + name.len() + 2;
                    circle[start..].split('"').next().unwrap().to_owned()
                };
                (attribute("cx").parse().unwrap(), attribute("fill"))
            })
            .collect();
        let rightmost = |fill: &str| {
            circles
                .iter()
                .filter(|(_, f)| f == fill)
                .map(|(x, _)| *x)
                .fold(f64::NEG_INFINITY, f64::max)
        };
        assert!(rightmost("#000000") < rightmost("#FF0000"), "{circles:?}");
    }

    #[test]
    fn a_sweep_without_finite_errors_still_plots_empty_axes() {
        let svg = plot(&[point(None, f64::NAN, f64::NAN)], Some(128.0)).unwrap();
        assert!(svg.contains("median frame time (ms)"));
        assert!(
            !svg.contains("comparison, c = 128"),
            "no dot, no legend entry"
        );
    }
}
