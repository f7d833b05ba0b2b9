//! The chart the benchmark commands draw: median frame time (linear, from 0)
//! against an image error (logarithmic), as an SVG string, with plotters.

use plotters::coord::combinators::IntoLogRange;
use plotters::prelude::*;

/// Plot size, SVG pixels.
const PLOT_SIZE: (u32, u32) = (640, 420);

/// One series of a [`time_error_chart`].
#[derive(Clone, Debug)]
pub struct ChartSeries {
    /// Its entry in the legend; `None`: not in the legend.
    pub legend: Option<String>,
    /// Frame time (ms), error and the dot's label. Points whose values are
    /// not finite and positive are left out.
    pub points: Vec<(f64, f64, Option<String>)>,
    /// Join the dots with a line.
    pub line: bool,
    /// Dot and line colour.
    pub colour: RGBColor,
    /// Dot radius, pixels.
    pub radius: i32,
}

/// The chart of `series` (see the module docs), titled `caption`, with the
/// error axis `error_label`; returns the SVG.
pub fn time_error_chart(
    caption: &str,
    error_label: &str,
    series: &[ChartSeries],
) -> Result<String, String> {
    let shown = |s: &ChartSeries| -> Vec<(f64, f64, Option<String>)> {
        s.points
            .iter()
            .filter(|(ms, error, _)| ms.is_finite() && error.is_finite() && *error > 0.0)
            .cloned()
            .collect()
    };
    let all: Vec<(f64, f64)> = series
        .iter()
        .flat_map(|s| shown(s).into_iter().map(|(ms, error, _)| (ms, error)))
        .collect();
    let max_ms = all.iter().map(|(ms, _)| *ms).fold(1.0, f64::max) * 1.2;
    let (low, high) = all
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (_, e)| {
            (lo.min(*e), hi.max(*e))
        });
    let (low, high) = if low <= high {
        (low / 2.0, high * 2.0)
    } else {
        (1e-4, 1.0)
    };
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, PLOT_SIZE).into_drawing_area();
        let error = |e: DrawingAreaErrorKind<_>| e.to_string();
        root.fill(&WHITE).map_err(error)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(caption, ("sans-serif", 18))
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
        for series in series {
            let points = shown(series);
            let (colour, radius) = (series.colour, series.radius);
            if series.line {
                chart
                    .draw_series(LineSeries::new(
                        points.iter().map(|(ms, e, _)| (*ms, *e)),
                        &colour,
                    ))
                    .map_err(error)?;
            }
            let dots = chart
                .draw_series(points.iter().map(|(ms, e, label)| {
                    EmptyElement::at((*ms, *e))
                        + Circle::new((0, 0), radius, colour.filled())
                        + Text::new(
                            label.clone().unwrap_or_default(),
                            (6, -14),
                            ("sans-serif", 12),
                        )
                }))
                .map_err(error)?;
            // A line series shows as a line in the legend, dots as a dot.
            match (&series.legend, series.line) {
                (Some(legend), true) => {
                    dots.label(legend.as_str())
                        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour));
                }
                (Some(legend), false) => {
                    dots.label(legend.as_str())
                        .legend(move |(x, y)| Circle::new((x + 10, y), radius, colour.filled()));
                }
                (None, _) => {}
            }
        }
        if series.iter().any(|s| s.legend.is_some()) {
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.9))
                .border_style(BLACK)
                .draw()
                .map_err(error)?;
        }
        root.present().map_err(error)?;
    }
    Ok(svg)
}
