//! `nebel bench-lod`: run time against image error of a grid volume drawn
//! through the octree C-LOD, along a sweep of each refinement criterion: the
//! distance criterion's accuracy `c` (Röttger and Ertl, "Fast Volumetric
//! Display of Natural Gaseous Phenomena", 2003, Eq. 1) and the screen
//! error's tolerance (`nebel_lod::octree::screen_error`).
//!
//! For each setting the scene's one grid volume is rendered with
//! `lod: (accuracy: c)` or `lod: (image_error: t)` (the scene's
//! `min_accuracy`, default 4) and once at full resolution (a lit volume
//! through the octree with `c = ∞`, which draws exactly the
//! full-resolution cells), with tonemapping and MSAA off; every
//! image is scored against the full-resolution image and against the exact
//! reference of the full trilinear field. The result is a CSV (`criterion,
//! value, cells drawn, frame median ms, RMSE against full resolution, RMSE,
//! max abs, PSNR` against the reference) and an SVG plot of the median frame
//! time (x, ms, from 0) against the RMSE (y, logarithmic), with axes, ticks,
//! labels and a legend: one labelled dot per setting joined in sweep order,
//! one series per criterion, the full-resolution point in red (the
//! comparison image of `--comparison-accuracy` scores 0 against itself and
//! has no dot). SVG needs no font files: the labels are SVG text.
//!
//! A scene without volumes whose terrain has ground fog sweeps the terrain's
//! accuracy `c` instead (the quadtree of terrain and fog prisms, Röttger and
//! Ertl 2003 §6) and, as its screen-error tolerances, the terrain's pixel
//! error (`nebel_lod::quadtree::accuracy_for_pixel_error`), full resolution
//! being `c` = [`FULL_TERRAIN_ACCURACY`]
//! (every node whose roughness is not zero refined); the cells counted are
//! the fog's tetrahedra, the reference is the scene's
//! ([`crate::reference::scene_reference`]: the full-resolution fog's cells on
//! the full-resolution triangles).

use std::path::Path;

use nebel_lod::OctreeSettings;
use nebel_reference::image_metrics::{ImageErrorMetrics, compare};
use nebel_scene::reference::save_reference;
use nebel_scene::{LodDescription, SceneDescription};
use plotters::style::colors::{BLACK, BLUE, RED};

use crate::time_error_chart::{ChartSeries, time_error_chart};

use crate::error::CommandError;
use crate::headless::HeadlessOptions;
use crate::reference::scene_reference;
use crate::scene_setup::SceneSetupPlugin;

/// The terrain accuracy `c` a ground fog sweep takes as full resolution: a
/// node whose roughness is above 1e-6 is refined anywhere on a terrain of
/// up to 8193 points.
pub const FULL_TERRAIN_ACCURACY: f64 = 1e7;

/// What a sweep varies.
#[derive(Clone, Copy, Debug)]
enum Swept {
    /// The octree of the scene's one grid volume.
    Volume { min_accuracy: f64 },
    /// The terrain's quadtree, with its ground fog.
    TerrainFog,
}

/// One setting of a criterion.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SweepSetting {
    /// The distance criterion's accuracy `c`.
    Accuracy(f64),
    /// The screen error's tolerance.
    ImageError(f64),
}

impl SweepSetting {
    /// The CSV's criterion and value.
    fn columns(self) -> (&'static str, f64) {
        match self {
            SweepSetting::Accuracy(c) => ("distance", c),
            SweepSetting::ImageError(t) => ("screen_error", t),
        }
    }

    /// The dot's label in the plot.
    fn label(self) -> String {
        match self {
            SweepSetting::Accuracy(c) => format!("c = {c}"),
            SweepSetting::ImageError(t) => format!("{t}"),
        }
    }
}

impl Swept {
    /// `scene` with `setting` (`None`: the comparison `lod`, or full
    /// resolution for the terrain).
    fn at(
        self,
        scene: &SceneDescription,
        setting: Option<SweepSetting>,
        lod: Option<LodDescription>,
    ) -> SceneDescription {
        let mut variant = scene.clone();
        match self {
            Swept::Volume { min_accuracy } => {
                variant.volumes[0].lod = match setting {
                    Some(SweepSetting::Accuracy(c)) => Some(LodDescription {
                        min_accuracy,
                        ..LodDescription::distance(c)
                    }),
                    Some(SweepSetting::ImageError(t)) => Some(LodDescription {
                        min_accuracy,
                        ..LodDescription::screen_error(t)
                    }),
                    None => lod,
                };
            }
            Swept::TerrainFog => {
                if let Some(terrain) = &mut variant.terrain {
                    let full = lod.and_then(|lod| lod.accuracy);
                    (terrain.accuracy, terrain.pixel_error) = match setting {
                        Some(SweepSetting::Accuracy(c)) => (Some(c as f32), None),
                        Some(SweepSetting::ImageError(pixels)) => (None, Some(pixels as f32)),
                        None => (Some(full.unwrap_or(FULL_TERRAIN_ACCURACY) as f32), None),
                    };
                }
            }
        }
        variant
    }

    /// The effect and counter the cells drawn are read from.
    fn cells(self) -> (&'static str, &'static str) {
        match self {
            Swept::Volume { .. } => ("volume", "cells_drawn"),
            Swept::TerrainFog => ("fog", "tetrahedra"),
        }
    }
}

/// One point of the sweep.
#[derive(Clone, Debug, PartialEq)]
pub struct SweepPoint {
    /// The setting; `None` for full resolution (or the comparison image).
    pub setting: Option<SweepSetting>,
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

/// Runs the sweep of `accuracies` and `image_errors` (a terrain's pixel
/// errors) and
/// writes `DIR/lod_sweep.csv`, `DIR/lod_sweep.svg` and the images. `scene`
/// must have exactly one volume, with a grid source, or no volume and a
/// terrain with fog (see the module docs).
///
/// `comparison_accuracy`: for a volume too large to draw at full resolution
/// (the paper's 513 × 65 × 513 field), the image every `c` is scored against
/// is drawn at this `c` instead, and the exact reference is skipped (its
/// columns are NaN); the plot then shows the RMSE against that image.
pub fn run_lod_sweep(
    scene_path: &Path,
    mut scene: SceneDescription,
    accuracies: &[f64],
    image_errors: &[f64],
    comparison_accuracy: Option<f64>,
    out_dir: &Path,
) -> Result<Vec<SweepPoint>, CommandError> {
    let fogged = scene
        .terrain
        .as_ref()
        .is_some_and(|terrain| terrain.fog.is_some());
    let swept = match scene.volumes.len() {
        1 => Swept::Volume {
            min_accuracy: scene.volumes[0]
                .lod
                .map_or(OctreeSettings::DEFAULT_MIN_ACCURACY, |lod| lod.min_accuracy),
        },
        0 if fogged => Swept::TerrainFog,
        count => {
            return Err(CommandError::Unsuitable {
                path: scene_path.to_owned(),
                reason: format!(
                    "bench-lod sweeps exactly one volume, or a terrain with fog and no volume; the scene has {count} volumes"
                ),
            });
        }
    };
    scene.camera.tonemapping = false;
    scene.camera.msaa = 1;
    std::fs::create_dir_all(out_dir).map_err(CommandError::write(out_dir))?;
    let min_accuracy = match swept {
        Swept::Volume { min_accuracy } => min_accuracy,
        Swept::TerrainFog => 0.0,
    };
    let lit = scene.volumes.first().is_some_and(|v| v.lighting.is_some());
    let full_lod = lit.then_some(LodDescription {
        min_accuracy,
        ..LodDescription::distance(f64::INFINITY)
    });
    let comparison_lod = match comparison_accuracy {
        Some(accuracy) => Some(LodDescription {
            min_accuracy,
            ..LodDescription::distance(accuracy)
        }),
        None => full_lod,
    };
    let reference = match comparison_accuracy {
        Some(_) => None,
        None => {
            let full = swept.at(&scene, None, full_lod);
            let reference = scene_reference(scene_path, &full, true)?;
            save_reference(&reference, &out_dir.join("reference.png"))?;
            Some(reference)
        }
    };

    let runs: Vec<Option<SweepSetting>> = accuracies
        .iter()
        .map(|&c| Some(SweepSetting::Accuracy(c)))
        .chain(
            image_errors
                .iter()
                .map(|&t| Some(SweepSetting::ImageError(t))),
        )
        .chain([None])
        .collect();
    let mut points = Vec::with_capacity(runs.len());
    let mut images = Vec::with_capacity(runs.len());
    for setting in runs {
        let variant = swept.at(&scene, setting, comparison_lod);
        let name = match (setting, comparison_accuracy) {
            (Some(SweepSetting::Accuracy(c)), _) => format!("c_{c}"),
            (Some(SweepSetting::ImageError(t)), _) => format!("image_error_{t}"),
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
        let (effect, counter) = swept.cells();
        let cells_drawn = stats
            .effects
            .get(effect)
            .and_then(|effect| effect.get(counter))
            .copied()
            .unwrap_or(0.0);
        points.push(SweepPoint {
            setting,
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
    let mut csv = String::from(
        "criterion,value,cells_drawn,frame_ms_median,rmse_vs_full,rmse,max_abs,psnr_db\n",
    );
    for point in &points {
        let (criterion, value) = match (point.setting, comparison_accuracy) {
            (Some(setting), _) => {
                let (criterion, value) = setting.columns();
                (criterion, value.to_string())
            }
            (None, Some(c)) => ("comparison", c.to_string()),
            (None, None) => ("full", String::new()),
        };
        csv.push_str(&format!(
            "{criterion},{value},{},{},{},{},{},{}\n",
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

/// The SVG plot of the sweep (see the module docs); `comparison_accuracy`
/// names the last point when it is not full resolution.
pub fn plot(points: &[SweepPoint], comparison_accuracy: Option<f64>) -> Result<String, String> {
    let shown: Vec<&SweepPoint> = points
        .iter()
        .filter(|p| p.frame_ms.is_finite() && p.error().is_finite() && p.error() > 0.0)
        .collect();
    let error_label = if points.iter().any(|p| p.rmse.is_finite()) {
        "RMSE against the exact reference (linear RGB)"
    } else {
        "RMSE against the comparison image (linear RGB)"
    };
    let full_label = match comparison_accuracy {
        Some(c) => format!("comparison, c = {c}"),
        None => String::from("full resolution"),
    };
    let series_of = |legend: &str, colour, of: fn(SweepSetting) -> bool| ChartSeries {
        legend: Some(String::from(legend)),
        points: shown
            .iter()
            .filter_map(|p| {
                let setting = p.setting.filter(|s| of(*s))?;
                Some((p.frame_ms, p.error(), Some(setting.label())))
            })
            .collect(),
        line: true,
        colour,
        radius: 4,
    };
    let distance = series_of("distance criterion, one dot per c", BLACK, |s| {
        matches!(s, SweepSetting::Accuracy(_))
    });
    let screen = series_of("screen error, one dot per tolerance", BLUE, |s| {
        matches!(s, SweepSetting::ImageError(_))
    });
    // The comparison image scores 0 against itself: no dot on a log axis.
    let full = ChartSeries {
        legend: Some(full_label),
        points: shown
            .iter()
            .filter(|p| p.setting.is_none())
            .map(|p| (p.frame_ms, p.error(), None))
            .collect(),
        line: false,
        colour: RED,
        radius: 5,
    };
    let series: Vec<ChartSeries> = [distance, screen, full]
        .into_iter()
        .filter(|series| !series.points.is_empty())
        .collect();
    time_error_chart(
        "Frame time against image error along each criterion",
        error_label,
        &series,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(setting: Option<SweepSetting>, frame_ms: f64, rmse: f64) -> SweepPoint {
        SweepPoint {
            setting,
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
            point(Some(SweepSetting::Accuracy(1.0)), 10.0, 1e-1),
            point(Some(SweepSetting::Accuracy(64.0)), 50.0, 1e-2),
            point(Some(SweepSetting::ImageError(0.03)), 30.0, 5e-3),
            point(None, 100.0, 1e-3),
        ];
        let svg = plot(&points, None).unwrap();
        for text in [
            "median frame time (ms)",
            "RMSE against the exact reference",
            "c = 64",
            "0.03",
            "full resolution",
            "distance criterion, one dot per c",
            "screen error, one dot per tolerance",
        ] {
            assert!(svg.contains(text), "the plot lacks {text:?}");
        }
        // Two black dots, a blue one, the red one and the legend's red dot.
        assert_eq!(svg.matches("<circle").count(), 5, "{svg}");
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
