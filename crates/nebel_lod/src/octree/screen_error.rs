//! The octree's screen-error criterion: the colour a node would get wrong.
//!
//! It estimates how much colour a node would get wrong in the pixels it covers
//! if it were drawn unrefined. Röttger and Ertl 2003 Eq. 1 refines by the
//! geometric error `s · Δ / d`, which knows neither how many pixels a node
//! covers, what the transfer function makes of the deviation Δ, nor whether
//! anything in front hides it. Like Jang et al. 2002 this criterion adds the
//! screen extent, and with it the optics and the occlusion:
//!
//! - **The estimate.** Δ (see [`super`]) is carried through the transfer
//!   function's slopes over the node's scalar range, bounded by the function's
//!   range there, into a first-order colour error `ε` of a ray through the
//!   node's longest edge `L` (emission absorption, its own light depth
//!   included), times the transmittance `T` in front of it. For a lit cloud the
//!   light's deviation adds as the cells draw it (Röttger and Ertl 2003 §5.1
//!   and §5.2).
//! - **The metric.** With `a` the fraction of the viewport the node's projected
//!   rectangle covers (widened, so nodes entering or leaving the view change
//!   continuously) and `P` its larger side in pixels,
//!   `e = min(ε · √a / ε_tol, P / 1 px)` for the tolerance `ε_tol` of
//!   [`super::LodCriterion::ScreenError`], raised near the eye so the nodes
//!   around it are refined. `ε · √a` is the image RMSE the node alone would
//!   cause, so the refinement spends cells where they lower the RMSE most and
//!   does not change with the resolution; `e' = clamp(e − 1, 0, 1)` (Eq. 6),
//!   clamped to the parent's. The view frustum prunes nothing: a node off
//!   screen has no error and fades to a leaf.
//! - **Occlusion.** The traversal runs front to back over a coarse grid of
//!   screen tiles holding the mean optical depth of the leaves chosen so far;
//!   `T` is the mean transmittance over a node's tiles. Nodes add their depth
//!   weighted by the morph, so the occlusion changes continuously too. It is an
//!   estimate, not a bound.
//!
//! The formulas, why each term is there and the limits of the estimate are in
//! `docs/octree-screen-error.md` in the repository.

use glam::{DAffine3, DMat4, DVec3, DVec4};
use nebel_core::transfer::TransferFunction;

use super::emit::CellScalars;

/// Intervals between the 256 quantised densities.
const INTERVALS: usize = 255;

/// Samples per interval for the slopes, besides the control points.
const SAMPLES_PER_INTERVAL: usize = 8;

/// The smallest tile side, pixels.
const MIN_TILE_PIXELS: u32 = 4;

/// The most tiles along the longer side of the viewport.
const MAX_TILES_ACROSS: u32 = 128;

/// `w_min` of a footprint relative to the box's largest clip coordinate.
const NEAR_W: f64 = 1e-9;

/// The largest optical depth one leaf adds to a tile (transmittance 1e-13).
const MAX_OPTICAL_DEPTH: f64 = 30.0;

/// Range maxima over the intervals in O(1) per query (a sparse table).
#[derive(Clone, Debug)]
struct RangeMax {
    /// `levels[k][i]`: the maximum of intervals `i .. i + 2^k`.
    levels: Vec<Vec<f64>>,
}

impl RangeMax {
    fn new(values: Vec<f64>) -> Self {
        let mut levels = vec![values];
        let mut width = 1;
        while 2 * width <= INTERVALS {
            let previous = levels.last().expect("one level at least");
            let next = (0..=INTERVALS - 2 * width)
                .map(|i| previous[i].max(previous[i + width]))
                .collect();
            levels.push(next);
            width *= 2;
        }
        Self { levels }
    }

    /// The maximum over intervals `first ..= last`.
    fn max(&self, first: usize, last: usize) -> f64 {
        let count = last - first + 1;
        let k = (usize::BITS - 1 - count.leading_zeros()) as usize;
        let level = &self.levels[k];
        level[first].max(level[last + 1 - (1 << k)])
    }
}

/// What the criterion reads of the transfer function, per density interval
/// (see `docs/octree-screen-error.md`).
#[derive(Clone, Debug)]
pub(crate) struct NodeOptics {
    rho_max: RangeMax,
    /// Negated minima.
    rho_min: RangeMax,
    emission_max: RangeMax,
    /// Negated minima.
    emission_min: RangeMax,
    rho_slope: RangeMax,
    emission_slope: RangeMax,
    /// The largest chromaticity channel.
    kappa_max: f64,
    /// How the light's deviation adds to the errors.
    light: LightTerm,
}

/// The light's share of a lit node's error (see
/// `docs/octree-screen-error.md`).
#[derive(Clone, Copy, Debug)]
enum LightTerm {
    /// An unlit volume.
    None,
    /// The light modulates the segment length.
    ModulatesLength,
    /// The light indexes the colour: `ρ_max · κ'`.
    IndexesColour { emission_per_density: f64 },
}

impl NodeOptics {
    /// The tables for cells drawn as `scalars` with `transfer`.
    pub(crate) fn new(transfer: &TransferFunction, scalars: CellScalars) -> Self {
        let kappa_max = f64::from(transfer.max_chromaticity());
        let rho_peak = f64::from(transfer.max_density());
        // The functions over the density the tables are indexed by.
        let (rho, emission): (Box<dyn Fn(f64) -> f64>, Box<dyn Fn(f64) -> f64>) = match scalars {
            CellScalars::LightModulatedByDensity => (
                Box::new(move |f| rho_peak * f),
                Box::new(move |f| kappa_max * rho_peak * f),
            ),
            CellScalars::Density | CellScalars::DensityModulatedByLight => (
                Box::new(|s| transfer.evaluate(s).rho),
                Box::new(|s| transfer.evaluate(s).emission().max_element()),
            ),
        };
        let controls: Vec<f64> = transfer.points().iter().map(|p| f64::from(p.s)).collect();
        let mut columns: [Vec<f64>; 6] = Default::default();
        let mut samples = Vec::with_capacity(SAMPLES_PER_INTERVAL + 4);
        for interval in 0..INTERVALS {
            let (lo, hi) = (interval as f64 / 255.0, (interval + 1) as f64 / 255.0);
            samples.clear();
            samples.extend(
                (0..=SAMPLES_PER_INTERVAL)
                    .map(|i| lo + (hi - lo) * i as f64 / SAMPLES_PER_INTERVAL as f64),
            );
            samples.extend(controls.iter().filter(|&&s| s > lo && s < hi));
            samples.sort_by(f64::total_cmp);
            let values: Vec<(f64, f64, f64)> =
                samples.iter().map(|&s| (s, rho(s), emission(s))).collect();
            let (mut rho_lo, mut rho_hi) = (f64::INFINITY, 0.0f64);
            let (mut e_lo, mut e_hi) = (f64::INFINITY, 0.0f64);
            let (mut rho_slope, mut e_slope) = (0.0f64, 0.0f64);
            for (index, &(s, r, e)) in values.iter().enumerate() {
                rho_lo = rho_lo.min(r);
                rho_hi = rho_hi.max(r);
                e_lo = e_lo.min(e);
                e_hi = e_hi.max(e);
                if let Some(&(s1, r1, e1)) = values.get(index + 1)
                    && s1 > s
                {
                    rho_slope = rho_slope.max((r1 - r).abs() / (s1 - s));
                    e_slope = e_slope.max((e1 - e).abs() / (s1 - s));
                }
            }
            for (column, value) in columns
                .iter_mut()
                .zip([rho_hi, -rho_lo, e_hi, -e_lo, rho_slope, e_slope])
            {
                column.push(value);
            }
        }
        let [
            rho_max,
            rho_min,
            emission_max,
            emission_min,
            rho_slope,
            emission_slope,
        ] = columns.map(RangeMax::new);
        let light = match scalars {
            CellScalars::Density => LightTerm::None,
            CellScalars::DensityModulatedByLight => LightTerm::ModulatesLength,
            CellScalars::LightModulatedByDensity => LightTerm::IndexesColour {
                emission_per_density: rho_peak * colour_slope(transfer),
            },
        };
        Self {
            rho_max,
            rho_min,
            emission_max,
            emission_min,
            rho_slope,
            emission_slope,
            kappa_max,
            light,
        }
    }

    /// The smallest extinction over the scalar range `[q_min, q_max]`
    /// (units of 1/255).
    pub(crate) fn min_extinction(&self, [q_min, q_max]: [u8; 2]) -> f64 {
        let (first, last) = intervals(q_min, q_max);
        -self.rho_min.max(first, last)
    }

    /// The colour error `ε / T` of a ray through a node of scalar range
    /// `[q_min, q_max]` (units of 1/255), deviation `delta` and longest edge
    /// `length` (world units).
    pub(crate) fn error(&self, [q_min, q_max]: [u8; 2], delta: f64, length: f64) -> f64 {
        let (first, last) = intervals(q_min, q_max);
        let rho_hi = self.rho_max.max(first, last);
        let rho_lo = -self.rho_min.max(first, last);
        let e_hi = self.emission_max.max(first, last);
        let e_lo = -self.emission_min.max(first, last);
        let mut delta_rho = (self.rho_slope.max(first, last) * delta).min(rho_hi - rho_lo);
        let mut delta_e = (self.emission_slope.max(first, last) * delta).min(e_hi - e_lo);
        match self.light {
            LightTerm::None => {}
            LightTerm::ModulatesLength => {
                delta_rho += rho_hi * delta;
                delta_e += e_hi * delta;
            }
            LightTerm::IndexesColour {
                emission_per_density,
            } => delta_e += emission_per_density * f64::from(q_max) / 255.0 * delta,
        }
        let depth = rho_lo * length;
        let effective_length = if depth > 1e-9 {
            -(-depth).exp_m1() / rho_lo
        } else {
            length
        };
        effective_length * delta_e + length * (-depth).exp() * (self.kappa_max + 1.0) * delta_rho
    }
}

/// The intervals `first ..= last` between quantised densities that the
/// range `[q_min, q_max]` spans (one for a single value).
fn intervals(q_min: u8, q_max: u8) -> (usize, usize) {
    let first = usize::from(q_min).min(INTERVALS - 1);
    let last = usize::from(q_max)
        .saturating_sub(1)
        .clamp(first, INTERVALS - 1);
    (first, last)
}

/// The largest slope of any chromaticity channel over [0, 1].
fn colour_slope(transfer: &TransferFunction) -> f64 {
    transfer
        .points()
        .windows(2)
        .filter(|pair| pair[1].s > pair[0].s)
        .map(|pair| {
            let ds = f64::from(pair[1].s - pair[0].s);
            (0..3)
                .map(|c| f64::from((pair[1].kappa[c] - pair[0].kappa[c]).abs()) / ds)
                .fold(0.0, f64::max)
        })
        .fold(0.0, f64::max)
}

/// A node's footprint on the screen: the bounding rectangle in pixels of
/// its box's part in front of the eye, `[x0, y0, x1, y1]`, y down (module
/// docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Footprint(pub(crate) [f64; 4]);

impl Footprint {
    /// The larger side in pixels.
    pub(crate) fn pixels(&self) -> f64 {
        let [x0, y0, x1, y1] = self.0;
        (x1 - x0).max(y1 - y0)
    }
}

/// The projection of index space into the viewport and the occlusion tiles
/// (see `docs/octree-screen-error.md`).
#[derive(Clone, Debug)]
pub(crate) struct ScreenTiles {
    /// Grid index coordinates to clip space.
    clip_from_index: DMat4,
    viewport: [f64; 2],
    tile_pixels: f64,
    tiles: [usize; 2],
    /// Mean optical depth in front, per tile, row by row.
    optical_depth: Vec<f32>,
    /// `exp(−τ)` of each tile, kept with it (read far more often).
    transmittance: Vec<f32>,
    /// Whether any leaf darkened a tile yet.
    occluded: bool,
}

impl ScreenTiles {
    /// Tiles for a viewport of `viewport` pixels seen through
    /// `clip_from_world`, with grid index coordinates mapped to world space
    /// by `world_from_index`.
    pub(crate) fn new(
        clip_from_world: DMat4,
        world_from_index: DAffine3,
        viewport: [u32; 2],
    ) -> Self {
        let tile = MIN_TILE_PIXELS.max(viewport[0].max(viewport[1]).div_ceil(MAX_TILES_ACROSS));
        Self::with_tile_pixels(clip_from_world, world_from_index, viewport, tile)
    }

    /// [`ScreenTiles::new`] with tiles of `tile` pixels.
    fn with_tile_pixels(
        clip_from_world: DMat4,
        world_from_index: DAffine3,
        viewport: [u32; 2],
        tile: u32,
    ) -> Self {
        let tiles = viewport.map(|side| side.div_ceil(tile).max(1) as usize);
        Self {
            clip_from_index: clip_from_world * DMat4::from(world_from_index),
            viewport: viewport.map(f64::from),
            tile_pixels: f64::from(tile),
            tiles,
            optical_depth: vec![0.0; tiles[0] * tiles[1]],
            transmittance: vec![1.0; tiles[0] * tiles[1]],
            occluded: false,
        }
    }

    /// The footprint of the box `[lo, lo + size]` (grid index coordinates):
    /// the rectangle of its corners in front of the eye and of the points
    /// where its edges cross the plane `w = w_min` just in front of the eye
    /// (the box clipped there), so it grows continuously to the whole
    /// viewport as the box reaches the eye. `None` when the box lies wholly
    /// behind that plane.
    pub(crate) fn footprint(&self, lo: DVec3, size: f64) -> Option<Footprint> {
        let m = &self.clip_from_index;
        let base = *m * lo.extend(1.0);
        let axes = [m.x_axis * size, m.y_axis * size, m.z_axis * size];
        let corners: [DVec4; 8] = std::array::from_fn(|corner| {
            (0..3)
                .filter(|axis| corner & (1 << axis) != 0)
                .fold(base, |clip, axis| clip + axes[axis])
        });
        let scale = corners
            .iter()
            .map(|c| c.abs().max_element())
            .fold(0.0, f64::max);
        let w_min = NEAR_W * scale;
        if w_min.is_nan() || w_min <= 0.0 || corners.iter().all(|c| c.w.is_nan() || c.w < w_min) {
            return None;
        }
        let [width, height] = self.viewport;
        let mut rect = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        let mut add = |clip: DVec4| {
            let x = (0.5 + 0.5 * clip.x / clip.w) * width;
            let y = (0.5 - 0.5 * clip.y / clip.w) * height;
            rect = [
                rect[0].min(x),
                rect[1].min(y),
                rect[2].max(x),
                rect[3].max(y),
            ];
        };
        for (corner, clip) in corners.iter().enumerate() {
            if clip.w >= w_min {
                add(*clip);
            }
            // The edges to the corners with one more bit set.
            for axis in 0..3 {
                let other = corner | (1 << axis);
                if other == corner {
                    continue;
                }
                let (a, b) = (*clip, corners[other]);
                if (a.w >= w_min) != (b.w >= w_min) {
                    let t = (w_min - a.w) / (b.w - a.w);
                    add(a + (b - a) * t);
                }
            }
        }
        rect.iter()
            .all(|v| v.is_finite())
            .then_some(Footprint(rect))
    }

    /// `√(A / A_view)`: the square root of the area of the rectangle's part
    /// on the viewport widened by half the rectangle's size (at most half
    /// the viewport's) on every side, over the viewport's area (module
    /// docs).
    pub(crate) fn visible_share(&self, Footprint([x0, y0, x1, y1]): Footprint) -> f64 {
        let [width, height] = self.viewport;
        let margin_x = (0.5 * (x1 - x0)).min(0.5 * width);
        let margin_y = (0.5 * (y1 - y0)).min(0.5 * height);
        let w = (x1.min(width + margin_x) - x0.max(-margin_x)).max(0.0);
        let h = (y1.min(height + margin_y) - y0.max(-margin_y)).max(0.0);
        (w * h / (width * height)).sqrt()
    }

    /// The tiles `[tx0, ty0, tx1, ty1)` a pixel rectangle meets; `None` off
    /// the viewport.
    fn tiles_meeting(&self, [x0, y0, x1, y1]: [f64; 4]) -> Option<[usize; 4]> {
        let [width, height] = self.viewport;
        if x1 < 0.0 || y1 < 0.0 || x0 > width || y0 > height {
            return None;
        }
        let tile = |v: f64, count: usize| {
            ((v / self.tile_pixels).floor().max(0.0) as usize).min(count - 1)
        };
        Some([
            tile(x0, self.tiles[0]),
            tile(y0, self.tiles[1]),
            tile(x1, self.tiles[0]) + 1,
            tile(y1, self.tiles[1]) + 1,
        ])
    }

    /// The mean transmittance in front of a node with this footprint: the
    /// tiles' `exp(−τ)` weighted by how much of each its rectangle covers
    /// on the viewport; a rectangle off the viewport reads the tiles of the
    /// viewport's edge nearest to it (its share may not be 0 yet).
    pub(crate) fn transmittance(&self, Footprint(rect): Footprint) -> f64 {
        let [width, height] = self.viewport;
        let clipped = [
            rect[0].clamp(0.0, width),
            rect[1].clamp(0.0, height),
            rect[2].clamp(0.0, width),
            rect[3].clamp(0.0, height),
        ];
        let Some([tx0, ty0, tx1, ty1]) = self.tiles_meeting(clipped) else {
            return 0.0;
        };
        if !self.occluded {
            return 1.0;
        }
        // A rectangle of no area still weighs its tiles.
        let mut covered_x = [0.0; MAX_TILES_ACROSS as usize];
        for tx in tx0..tx1 {
            covered_x[tx - tx0] = self.overlap(clipped[0], clipped[2], tx).max(1e-9);
        }
        let covered_x = &covered_x[..tx1 - tx0];
        let columns: f64 = covered_x.iter().sum();
        let (mut light, mut area) = (0.0, 0.0);
        for ty in ty0..ty1 {
            let covered_y = self.overlap(clipped[1], clipped[3], ty).max(1e-9);
            let row = &self.transmittance[ty * self.tiles[0] + tx0..ty * self.tiles[0] + tx1];
            let row_light: f64 = row
                .iter()
                .zip(covered_x)
                .map(|(&t, &c)| c * f64::from(t))
                .sum();
            light += covered_y * row_light;
            area += covered_y * columns;
        }
        light / area
    }

    /// The fraction of tile `tile`'s side that `[lo, hi]` covers.
    fn overlap(&self, lo: f64, hi: f64, tile: usize) -> f64 {
        let t = self.tile_pixels;
        (hi.min(t * (tile + 1) as f64) - lo.max(t * tile as f64)).max(0.0) / t
    }

    /// Lets a leaf of this footprint and optical depth `tau` darken the
    /// tiles behind it: each tile's mean optical depth grows by `f · tau`,
    /// `f` the fraction of the tile the rectangle covers.
    pub(crate) fn occlude(&mut self, Footprint(rect): Footprint, tau: f64) {
        let tau = tau.clamp(0.0, MAX_OPTICAL_DEPTH);
        let Some([tx0, ty0, tx1, ty1]) = self.tiles_meeting(rect).filter(|_| tau > 0.0) else {
            return;
        };
        for ty in ty0..ty1 {
            let covered_y = self.overlap(rect[1], rect[3], ty);
            for tx in tx0..tx1 {
                let covered = self.overlap(rect[0], rect[2], tx) * covered_y;
                if covered > 0.0 {
                    let index = ty * self.tiles[0] + tx;
                    self.optical_depth[index] += (covered * tau) as f32;
                    self.transmittance[index] = (-self.optical_depth[index]).exp();
                    self.occluded = true;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::DVec3;
    use nebel_core::transfer::{ControlPoint, TransferPreset};

    use super::*;

    fn ramp(rho: f32) -> TransferFunction {
        TransferFunction::new([
            ControlPoint {
                s: 0.0,
                kappa: [1.0; 3],
                rho: 0.0,
            },
            ControlPoint {
                s: 1.0,
                kappa: [1.0; 3],
                rho,
            },
        ])
        .unwrap()
    }

    #[test]
    fn range_maxima_match_a_scan() {
        let values: Vec<f64> = (0..INTERVALS).map(|i| ((i * 37) % 101) as f64).collect();
        let table = RangeMax::new(values.clone());
        for (first, last) in [(0, 0), (0, 254), (3, 17), (100, 101), (254, 254), (17, 200)] {
            let scan = values[first..=last]
                .iter()
                .copied()
                .fold(f64::MIN, f64::max);
            assert_eq!(table.max(first, last), scan, "{first}..={last}");
        }
    }

    /// A linear ramp ρ = 2s, κ = 1: slopes 2 everywhere, the error of a thin
    /// transparent-ish node is `L (δE + 2 δρ)` with `δ = 2Δ`, capped by the
    /// ranges.
    #[test]
    fn a_linear_ramp_gives_the_closed_form() {
        let optics = NodeOptics::new(&ramp(2.0), CellScalars::Density);
        let (q0, q1) = (51u8, 153u8);
        let delta = 0.01;
        let error = optics.error([q0, q1], delta, 1e-6);
        let rho_min = optics.min_extinction([q0, q1]);
        let (length, rho): (f64, f64) = (1e-6, 2.0 * 51.0 / 255.0);
        let expected = -(-rho * length).exp_m1() / rho * 2.0 * delta
            + length * (-rho * length).exp() * 2.0 * 2.0 * delta;
        assert!(
            (error - expected).abs() < 1e-12 * expected,
            "{error} {expected}"
        );
        assert!((rho_min - 2.0 * 51.0 / 255.0).abs() < 1e-12);
        // A deviation larger than the range is capped by the range.
        let capped = optics.error([q0, q1], 10.0, 1e-6);
        let range = 2.0 * 102.0 / 255.0;
        assert!((capped - 1e-6 * 3.0 * range).abs() < 1e-9);
        // Dense and long: the opacity term vanishes, the emission term
        // saturates at δE / ρ_min.
        let deep = optics.error([q0, q1], delta, 1e4);
        assert!((deep - 2.0 * delta / rho_min).abs() < 1e-9, "{deep}");
    }

    #[test]
    fn a_zero_deviation_or_a_flat_function_gives_no_error() {
        let cloud = NodeOptics::new(
            &TransferFunction::preset(TransferPreset::Cloud),
            CellScalars::Density,
        );
        assert_eq!(cloud.error([0, 255], 0.0, 10.0), 0.0);
        // The cloud preset is transparent below its threshold: a range there
        // has no error whatever Δ is.
        assert_eq!(cloud.error([0, 2], 0.5, 10.0), 0.0);
        assert!(cloud.error([0, 255], 0.1, 10.0) > 0.0);
        for scalars in [
            CellScalars::LightModulatedByDensity,
            CellScalars::DensityModulatedByLight,
        ] {
            let lit = NodeOptics::new(&TransferFunction::preset(TransferPreset::Cloud), scalars);
            let error = lit.error([10, 200], 0.05, 10.0);
            assert!(error.is_finite() && error > 0.0);
            assert_eq!(lit.error([10, 200], 0.0, 10.0), 0.0);
        }
    }

    fn tiles() -> ScreenTiles {
        // Eye at the origin looking down −z, 90° vertical field of view, 64 × 32 px.
        let projection =
            DMat4::perspective_infinite_reverse_rh(std::f64::consts::FRAC_PI_2, 2.0, 0.1);
        ScreenTiles::with_tile_pixels(projection, DAffine3::IDENTITY, [64, 32], 8)
    }

    #[test]
    fn footprints_are_the_projected_rectangles() {
        let screen = tiles();
        assert_eq!(screen.tiles, [8, 4]);
        // A unit cube centred on the axis 10 units away: its near face, 9.5
        // units away, is 16/9.5 px tall and wide (16 px per unit at distance
        // 1 for a 32 px tall 90° view, 64 px wide at aspect 2).
        let footprint = screen
            .footprint(DVec3::new(-0.5, -0.5, -10.5), 1.0)
            .expect("in front of the eye");
        let [x0, y0, x1, y1] = footprint.0;
        assert!((x0 + x1 - 64.0).abs() < 1e-9 && (y0 + y1 - 32.0).abs() < 1e-9);
        assert!(
            (footprint.pixels() - 16.0 / 9.5).abs() < 1e-9,
            "{footprint:?}"
        );
        assert!(
            (screen.visible_share(footprint) - 16.0 / 9.5 / (64.0f64 * 32.0).sqrt()).abs() < 1e-9
        );
        // A box around the eye: the whole viewport and far beyond, counted
        // over the viewport widened by half its size on every side (a share
        // of 2); one reaching behind the eye in the lower left quadrant of
        // the view: that quadrant widened to the left and down, the area of
        // the viewport (a share of 1).
        for (lo, size, share) in [
            (DVec3::splat(-1.0), 2.0, 2.0),
            (DVec3::new(-1.0, -1.0, -0.5), 1.0, 1.0),
        ] {
            let around = screen.footprint(lo, size).expect("partly in front");
            assert!(around.pixels() > 1e6, "{around:?}");
            assert!((screen.visible_share(around) - share).abs() < 1e-9);
        }
        // Behind the eye entirely: no footprint.
        assert_eq!(screen.footprint(DVec3::new(0.0, 0.0, 5.0), 1.0), None);
        // Off to the side: a rectangle outside the viewport, nothing visible.
        let aside = screen
            .footprint(DVec3::new(100.0, 0.0, -10.0), 1.0)
            .unwrap();
        assert_eq!(screen.visible_share(aside), 0.0);
        // Its transmittance is that of the viewport's nearest edge.
        assert_eq!(screen.transmittance(aside), 1.0);
    }

    /// As a box slides back through the eye's plane its rectangle changes
    /// without a jump: the share of the viewport grows past the point where
    /// the box reaches behind the eye and falls to 0 as its last part passes.
    #[test]
    fn footprints_change_continuously_through_the_eye_plane() {
        let screen = tiles();
        let (mut last, mut largest): (Option<f64>, f64) = (None, 0.0);
        for step in 0..=4000 {
            // A unit box right of the axis, its near face moving from 2 units
            // in front of the eye to 2 units behind it.
            let z = -3.0 + step as f64 * 0.001;
            let Some(footprint) = screen.footprint(DVec3::new(0.3, -0.5, z), 1.0) else {
                assert!(z >= 0.0, "{z}");
                continue;
            };
            // The area fraction, share squared, is Lipschitz in the motion
            // while the box's far face is not at the eye (where its image
            // sweeps across the view as 1/distance).
            let share = screen.visible_share(footprint);
            if let Some(last) = last.filter(|_| z < -0.2) {
                assert!(
                    (share * share - last * last).abs() < 0.02,
                    "{z}: jumps from {last} to {share}"
                );
            }
            last = Some(share);
            largest = largest.max(share);
        }
        assert!(largest > 0.6 && last.unwrap() < 0.05, "{largest} {last:?}");
    }

    #[test]
    fn occlusion_adds_the_covered_optical_depth_of_leaves_in_front() {
        let mut screen = tiles();
        // Over x 0..16, every row: tiles 0 and 1 of each row wholly covered
        // by an optical depth of 2, the rest not at all.
        screen.occlude(Footprint([0.0, 0.0, 16.0, 32.0]), 2.0);
        let left = Footprint([1.0, 1.0, 15.0, 30.0]);
        let right = Footprint([40.0, 1.0, 60.0, 30.0]);
        assert!((screen.transmittance(left) - (-2f64).exp()).abs() < 1e-6);
        assert_eq!(screen.transmittance(right), 1.0);
        // A node straddling both: the mean over its pixels, here 15 of 19
        // columns behind the leaf.
        let straddling = screen.transmittance(Footprint([1.0, 1.0, 20.0, 5.0]));
        let expected = (15.0 * (-2f64).exp() + 4.0) / 19.0;
        assert!(
            (straddling - expected).abs() < 1e-6,
            "{straddling} {expected}"
        );
        // Half a tile covered: half the depth; the other half covered by a
        // neighbour: the whole depth; an infinite depth is capped.
        let mut screen = tiles();
        let tile = Footprint([41.0, 1.0, 46.0, 7.0]);
        screen.occlude(Footprint([40.0, 0.0, 44.0, 8.0]), 4.0);
        assert!((screen.transmittance(tile) - (-2f64).exp()).abs() < 1e-6);
        screen.occlude(Footprint([44.0, 0.0, 48.0, 8.0]), 4.0);
        assert!((screen.transmittance(tile) - (-4f64).exp()).abs() < 1e-6);
        screen.occlude(Footprint([40.0, 0.0, 48.0, 8.0]), f64::INFINITY);
        assert!((screen.transmittance(tile) - (-34f64).exp()).abs() < 1e-12);
        // A NaN depth adds nothing.
        screen.occlude(Footprint([0.0, 0.0, 8.0, 8.0]), f64::NAN);
        assert_eq!(screen.transmittance(Footprint([1.0, 1.0, 7.0, 7.0])), 1.0);
    }
}
