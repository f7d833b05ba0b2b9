//! Terrain shadows in the air: per column, the height below which a height
//! field hides the sun.
//!
//! A point `(p, y)` over the horizontal position `p` sees the sun when the
//! line toward it stays above the ground, `y + t tan α > H(p + t d)` for
//! every `t > 0` (`d` the horizontal unit direction toward the sun, `α` its
//! elevation, `H` the bilinear surface). So the shadowed part of every
//! vertical column is one interval from the ground up to the *shadow
//! height* `h_s(p) = max_{t ≥ 0} H(p + t d) − t tan α` (at `t = 0` the
//! ground itself), and a point is lit exactly when `y ≥ h_s(p)`. Along a
//! line a bilinear surface is a quadratic in `t` inside each grid cell,
//! so [`shadow_height`] walks the cells the line crosses (Amanatides and
//! Woo 1987) and takes each quadratic's maximum in closed form: exact for
//! the bilinear field, stopping where the field ends (no terrain beyond it)
//! or where its highest point, lowered by `t tan α`, cannot beat the best,
//! and crossing a block of 64² or 8² cells at once where the block's
//! highest point cannot.
//!
//! [`TerrainShadow`] stores `h_s` at the points of a regular grid over the
//! field's extent, bilinear in between (what the GPU samples). The sun
//! below [`TerrainShadow::MIN_SUN_SINE`] casts no map: the fog it would
//! light is then unlit.

use glam::{DVec2, DVec3};

use super::HeightField;
use crate::pacing::{fill_slices, worker_threads};

/// The shadow heights of a terrain for one sun (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct TerrainShadow {
    /// `h_s` over the field's extent.
    pub heights: HeightField,
    /// At the same points, the horizontal distance `t*` toward the sun of
    /// the terrain that casts the shadow (0 where none does): the sun a
    /// little higher or lower, at `tan α'`, moves `h_s` by `−t* (tan α' −
    /// tan α)` while that point stays the one that casts it (and the
    /// shadow height is never below that), so a map can follow a rising
    /// or setting sun between builds.
    pub distances: HeightField,
    /// Unit direction toward the sun in the field's frame.
    pub sun: DVec3,
}

impl TerrainShadow {
    /// The lowest sine of the sun's elevation that casts a map (about 0.6°,
    /// where the sunlight is nearly gone).
    pub const MIN_SUN_SINE: f64 = 0.01;

    /// The most points along either side of the map a terrain's sunlit fog
    /// builds ([`TerrainShadow::of_field`]; a larger terrain is sampled
    /// bilinearly at fewer).
    pub const MAX_POINTS: usize = 513;

    /// The map a sunlit fog draws with: [`TerrainShadow::compute`] at the
    /// field's points up to [`TerrainShadow::MAX_POINTS`] a side, on every
    /// core a build may use ([`worker_threads`]).
    pub fn of_field(field: &HeightField, sun: DVec3) -> Option<Self> {
        let points = field.dims().map(|n| n.min(Self::MAX_POINTS));
        Self::compute(field, sun, points, worker_threads())
    }

    /// The shadow heights of `field` for the sun in direction `sun` (toward
    /// it, in the field's frame) at `points` grid points along x and z
    /// spanning the field's extent (each clamped to 2 ..= the field's own
    /// points along that axis), filled on up to `threads` threads. `None`
    /// where the sun is lower than [`TerrainShadow::MIN_SUN_SINE`] or not
    /// finite.
    pub fn compute(
        field: &HeightField,
        sun: DVec3,
        points: [usize; 2],
        threads: usize,
    ) -> Option<Self> {
        let sun = sun.try_normalize()?;
        if sun.y < Self::MIN_SUN_SINE {
            return None;
        }
        let dims = field.dims();
        let points = [points[0].clamp(2, dims[0]), points[1].clamp(2, dims[1])];
        let extent = field.spacing() * DVec2::new((dims[0] - 1) as f64, (dims[1] - 1) as f64);
        let spacing = extent / DVec2::new((points[0] - 1) as f64, (points[1] - 1) as f64);
        let blocks = Blocks::new(field);
        let mut marched = vec![(0.0f32, 0.0f32); points[0] * points[1]];
        fill_slices(&mut marched, points[0], threads, |first_row, rows| {
            for (n, h) in rows.iter_mut().enumerate() {
                let (i, j) = (n % points[0], first_row + n / points[0]);
                let p = field.origin() + DVec2::new(i as f64, j as f64) * spacing;
                let (height, distance) = march(field, &blocks, p, sun);
                *h = (height as f32, distance as f32);
            }
        });
        let grid =
            |values: Vec<f32>| HeightField::new(points, spacing, field.origin(), values).ok();
        Some(Self {
            heights: grid(marched.iter().map(|m| m.0).collect())?,
            distances: grid(marched.iter().map(|m| m.1).collect())?,
            sun,
        })
    }

    /// Whether the point `p` (the field's frame) sees the sun past the
    /// terrain, by the map (bilinear between its points).
    pub fn sees_sun(&self, p: DVec3) -> bool {
        p.y >= self.heights.sample(DVec2::new(p.x, p.z))
    }
}

/// The exact shadow height `h_s` over the horizontal position `p` of
/// `field` (module docs) for the unit direction `sun` toward the sun
/// (`sun.y` > 0); positions outside the field are clamped onto it.
pub fn shadow_height(field: &HeightField, p: DVec2, sun: DVec3) -> f64 {
    march(field, &Blocks::new(field), p, sun).0
}

/// Cells per side of the blocks the march may cross at once, coarse to
/// fine.
const BLOCKS: [usize; 2] = [64, 8];

/// The highest point of each block of cells, per size in [`BLOCKS`], and of
/// the field.
struct Blocks {
    /// Per size: blocks along x, and the highest point of each.
    levels: [(usize, Vec<f64>); 2],
    top: f64,
}

impl Blocks {
    fn new(field: &HeightField) -> Self {
        let [nx, nz] = field.dims();
        let levels = BLOCKS.map(|size| {
            let (across, down) = ((nx - 1).div_ceil(size), (nz - 1).div_ceil(size));
            let mut highest = vec![f64::MIN; across * down];
            for j in 0..nz {
                for i in 0..nx {
                    let h = f64::from(field.height(i, j));
                    // A point bounds the cells on either side of it.
                    for bj in [j.saturating_sub(1) / size, j.min(nz - 2) / size] {
                        for bi in [i.saturating_sub(1) / size, i.min(nx - 2) / size] {
                            let block = &mut highest[bi + across * bj];
                            *block = block.max(h);
                        }
                    }
                }
            }
            (across, highest)
        });
        let top = levels[0].1.iter().copied().fold(f64::MIN, f64::max);
        Self { levels, top }
    }

    /// The block of size `BLOCKS[level]` that holds `cell`, and its highest
    /// point.
    fn of(&self, level: usize, cell: DVec2) -> (usize, f64) {
        let (across, highest) = &self.levels[level];
        let size = BLOCKS[level];
        let index = cell.x as usize / size + across * (cell.y as usize / size);
        (index, highest[index])
    }
}

/// The cell the line `g(t) = start + t e` (grid units) enters at `g`: on a
/// cell's edge moving backward, the cell below. `None` outside the field.
fn cell_at(g: DVec2, e: DVec2, last: DVec2) -> Option<DVec2> {
    let mut cell = g.floor();
    for axis in 0..2 {
        if e[axis] < 0.0 && g[axis] == cell[axis] {
            cell[axis] -= 1.0;
        }
    }
    let inside = |axis: usize| cell[axis] >= 0.0 && cell[axis] <= last[axis] - 1.0;
    (inside(0) && inside(1)).then_some(cell)
}

/// `max_t H(p + t d) − t tan α` cell by cell along the line (module docs),
/// and the `t` where it is reached (the first such).
fn march(field: &HeightField, blocks: &Blocks, p: DVec2, sun: DVec3) -> (f64, f64) {
    let dims = field.dims();
    let last = DVec2::new((dims[0] - 1) as f64, (dims[1] - 1) as f64);
    let start = ((p - field.origin()) / field.spacing()).clamp(DVec2::ZERO, last);
    let mut best = (field.sample_grid(start), 0.0);
    let horizontal = DVec2::new(sun.x, sun.z);
    let run = horizontal.length();
    if run <= 1e-12 * sun.y {
        return best;
    }
    let slope = sun.y / run;
    // The line in grid units: g(t) = start + t e, t in world units along d.
    let e = horizontal / run / field.spacing();
    // A start on the field's far edges lies in the last cell.
    let Some(mut cell) = cell_at(start.min(last - 1e-9 * last), e, last)
        .or_else(|| cell_at(start.floor().min(last - 1.0), DVec2::ZERO, last))
    else {
        return best;
    };
    let mut t = 0.0;
    // Where the line leaves the box from `lo` to `hi` (grid units).
    let exit = |lo: DVec2, hi: DVec2, axis: usize| {
        if e[axis] > 0.0 {
            (hi[axis] - start[axis]) / e[axis]
        } else if e[axis] < 0.0 {
            (lo[axis] - start[axis]) / e[axis]
        } else {
            f64::INFINITY
        }
    };
    loop {
        if blocks.top - t * slope <= best.0 {
            return best;
        }
        // The coarsest block that nothing from here on in it beats the
        // best, crossed whole.
        let skip = (0..BLOCKS.len()).find_map(|level| {
            let (block, highest) = blocks.of(level, cell);
            if highest - t * slope > best.0 {
                return None;
            }
            let size = BLOCKS[level] as f64;
            let lo = (cell / size).floor() * size;
            let hi = (lo + size).min(last);
            let t_exit = exit(lo, hi, 0).min(exit(lo, hi, 1)).max(t);
            Some((level, block, t_exit, cell_at(start + t_exit * e, e, last)))
        });
        match skip {
            Some((_, _, _, None)) => return best,
            Some((level, block, t_exit, Some(next))) if blocks.of(level, next).0 != block => {
                (cell, t) = (next, t_exit);
                continue;
            }
            _ => {}
        }
        let (tx, tz) = (exit(cell, cell + 1.0, 0), exit(cell, cell + 1.0, 1));
        let t_end = tx.min(tz).max(t);
        let candidate = cell_maximum(field, cell, start, e, slope, t, t_end);
        if candidate.0 > best.0 {
            best = candidate;
        }
        let mut next = cell;
        if tx <= t_end {
            next.x += e.x.signum();
        }
        if tz <= t_end {
            next.y += e.y.signum();
        }
        if next.x < 0.0 || next.y < 0.0 || next.x > last.x - 1.0 || next.y > last.y - 1.0 {
            return best;
        }
        cell = next;
        t = t_end;
    }
}

/// The maximum of `H(g(t)) − t · slope` over `[t0, t1]` inside `cell`,
/// where the bilinear `H` along the line is a quadratic, and its `t`.
fn cell_maximum(
    field: &HeightField,
    cell: DVec2,
    start: DVec2,
    e: DVec2,
    slope: f64,
    t0: f64,
    t1: f64,
) -> (f64, f64) {
    let (i, j) = (cell.x as usize, cell.y as usize);
    let h = |di: usize, dj: usize| f64::from(field.height(i + di, j + dj));
    let (a, b, c, k) = (
        h(0, 0),
        h(1, 0) - h(0, 0),
        h(0, 1) - h(0, 0),
        h(1, 1) - h(1, 0) - h(0, 1) + h(0, 0),
    );
    // Local coordinates fx = x0 + t ex, fz = z0 + t ez.
    let (x0, z0) = (start.x - cell.x, start.y - cell.y);
    let f = |t: f64| {
        let (fx, fz) = (x0 + t * e.x, z0 + t * e.y);
        a + b * fx + c * fz + k * fx * fz - t * slope
    };
    let mut best = if f(t1) > f(t0) {
        (f(t1), t1)
    } else {
        (f(t0), t0)
    };
    // f(t) = A t² + B t + const.
    let quadratic = k * e.x * e.y;
    let linear = b * e.x + c * e.y + k * (x0 * e.y + z0 * e.x) - slope;
    if quadratic < 0.0 {
        let vertex = -linear / (2.0 * quadratic);
        if vertex > t0 && vertex < t1 && f(vertex) > best.0 {
            best = (f(vertex), vertex);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn field(dims: [usize; 2], spacing: f64, height: impl Fn(f64, f64) -> f64) -> HeightField {
        let mut heights = Vec::new();
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                heights.push(height(i as f64 * spacing, j as f64 * spacing) as f32);
            }
        }
        HeightField::new(dims, DVec2::splat(spacing), DVec2::ZERO, heights).unwrap()
    }

    /// `max_t H(p + t d) − t tan α` by a fine march along the line to the
    /// field's edge.
    fn brute_force(field: &HeightField, p: DVec2, sun: DVec3) -> f64 {
        let dims = field.dims();
        let max = field.origin()
            + field.spacing() * DVec2::new((dims[0] - 1) as f64, (dims[1] - 1) as f64);
        let d = DVec2::new(sun.x, sun.z);
        let run = d.length();
        let slope = sun.y / run;
        let d = d / run;
        let mut best = field.sample(p);
        let step = 1e-3 * field.spacing().min_element();
        let mut t = 0.0;
        loop {
            t += step;
            let q = p + t * d;
            if q.x < field.origin().x || q.y < field.origin().y || q.x > max.x || q.y > max.y {
                return best;
            }
            best = best.max(field.sample(q) - t * slope);
        }
    }

    #[test]
    fn a_flat_field_shades_nothing_above_its_ground() {
        let flat = field([9, 7], 10.0, |_, _| 25.0);
        let shadow = TerrainShadow::compute(&flat, DVec3::new(1.0, 0.2, -0.5), [9, 7], 2).unwrap();
        assert!(shadow.heights.heights().iter().all(|&h| h == 25.0));
        assert!(shadow.sees_sun(DVec3::new(31.0, 25.0, 12.0)));
        assert!(!shadow.sees_sun(DVec3::new(31.0, 24.9, 12.0)));
    }

    #[test]
    fn a_slope_facing_away_from_the_sun_is_shaded_by_its_top_edge() {
        // H = 0.5 x rises toward a sun at tan α = 0.25 along +x: every column
        // is shaded up to the line from the field's top edge, closed form
        // h_s = 0.5 x_max − (x_max − x) · 0.25.
        let slope = field([11, 5], 4.0, |x, _| 0.5 * x);
        let sun = DVec3::new(4.0, 1.0, 0.0).normalize();
        let shadow = TerrainShadow::compute(&slope, sun, [11, 5], 1).unwrap();
        for j in 0..5 {
            for i in 0..11 {
                let x = 4.0 * i as f64;
                let expected = 0.5 * 40.0 - (40.0 - x) * 0.25;
                let h = f64::from(shadow.heights.height(i, j));
                assert!(
                    (h - expected).abs() < 1e-5,
                    "{i} {j}: {h} against {expected}"
                );
            }
        }
        // The top edge casts it: t* = 40 − x, and a sun a little higher
        // (tan α' = 0.3) moves every height by −t* (0.3 − 0.25), exactly.
        let higher = DVec3::new(1.0, 0.3, 0.0).normalize();
        for i in 0..11 {
            let x = 4.0 * i as f64;
            let distance = f64::from(shadow.distances.height(i, 2));
            assert!((distance - (40.0 - x)).abs() < 1e-4, "{i}: {distance}");
            let moved = f64::from(shadow.heights.height(i, 2)) - distance * (0.3 - 0.25);
            let exact = shadow_height(&slope, DVec2::new(x, 8.0), higher);
            assert!((moved - exact).abs() < 1e-4, "{i}: {moved} against {exact}");
        }
        // Facing the sun, a gentler slope shades nothing but the ground.
        let gentle = field([11, 5], 4.0, |x, _| 0.1 * x);
        let shadow = TerrainShadow::compute(&gentle, sun, [11, 5], 1).unwrap();
        for i in 0..11 {
            let h = f64::from(shadow.heights.height(i, 2));
            assert!((h - 0.4 * i as f64).abs() < 1e-5);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// The march is the exact maximum: never below a fine march along
        /// the line, and above it by less than the fine march's step times
        /// the surface's slope, on random fields, suns and points (an axis-
        /// aligned sun crosses cell corners and edges exactly; fields of up
        /// to five blocks a side, which the march crosses whole where it
        /// can).
        #[test]
        fn the_march_is_the_exact_maximum_over_random_fields_and_suns(
            dims in prop::array::uniform2(3usize..40),
            values in prop::collection::vec(0.0f64..30.0, 1600),
            azimuth in 0.0f64..std::f64::consts::TAU,
            elevation in 0.05f64..1.4,
            axis_aligned in any::<bool>(),
            at in prop::array::uniform2(0.0f64..=1.0),
        ) {
            let bumps = field(dims, 5.0, |x, z| values[(x / 5.0) as usize + 40 * (z / 5.0) as usize]);
            let sun = DVec3::new(
                elevation.cos() * azimuth.cos(),
                elevation.sin(),
                if axis_aligned { 0.0 } else { elevation.cos() * azimuth.sin() },
            )
            .normalize();
            let extent = 5.0 * DVec2::new((dims[0] - 1) as f64, (dims[1] - 1) as f64);
            let p = DVec2::from_array(at) * extent;
            let exact = shadow_height(&bumps, p, sun);
            let fine = brute_force(&bumps, p, sun);
            prop_assert!(exact >= fine - 1e-9 && exact - fine < 0.05, "{exact} against {fine}");
            // The height moved by its caster's distance for a sun 0.02 rad
            // higher is never above that sun's own.
            let (height, distance) = march(&bumps, &Blocks::new(&bumps), p, sun);
            let tan = |s: DVec3| s.y / DVec2::new(s.x, s.z).length();
            let higher = DVec3::new(sun.x, 0.0, sun.z).normalize() * (elevation + 0.02).cos()
                + DVec3::Y * (elevation + 0.02).sin();
            let moved = height - distance * (tan(higher) - tan(sun));
            prop_assert!(moved <= shadow_height(&bumps, p, higher) + 1e-9);
        }
    }

    /// A field of several 64² blocks with ridges of every height: crossing
    /// whole blocks changes nothing against the fine march.
    #[test]
    fn crossing_blocks_whole_keeps_the_exact_maximum_on_a_large_field() {
        let hills = field([150, 140], 5.0, |x, z| {
            60.0 * (0.013 * x).sin() * (0.021 * z + 1.0).cos() + 9.0 * (0.11 * x + 0.07 * z).sin()
        });
        for k in 0..24 {
            let k = f64::from(k);
            let azimuth = 0.7 + 2.39 * k;
            let elevation = 0.04 + 0.05 * (k % 6.0);
            let sun = DVec3::new(
                elevation.cos() * azimuth.cos(),
                elevation.sin(),
                elevation.cos() * azimuth.sin(),
            );
            let p = DVec2::new((37.0 * k) % 745.0, (53.0 * k + 11.0) % 695.0);
            let exact = shadow_height(&hills, p, sun);
            let fine = brute_force(&hills, p, sun);
            assert!(
                exact >= fine - 1e-9 && exact - fine < 0.05,
                "{k}: {exact} against {fine}"
            );
        }
    }

    #[test]
    fn the_map_holds_the_exact_heights_at_its_points_and_a_low_sun_casts_none() {
        let bumps = field([17, 9], 2.0, |x, z| {
            10.0 * (0.3 * x).sin() * (0.2 * z).cos() + (0.7 * x * z).sin()
        });
        let sun = DVec3::new(-0.6, 0.3, 0.7).normalize();
        let shadow = TerrainShadow::compute(&bumps, sun, [9, 5], 2).unwrap();
        for (j, i) in [(0, 0), (2, 3), (4, 8), (1, 5)] {
            let p = DVec2::new(4.0 * i as f64, 4.0 * j as f64);
            let exact = shadow_height(&bumps, p, sun) as f32;
            assert_eq!(shadow.heights.height(i, j), exact);
        }
        for sun in [
            DVec3::new(1.0, 0.005, 0.0),
            DVec3::new(0.0, -1.0, 0.0),
            DVec3::NAN,
        ] {
            assert!(TerrainShadow::compute(&bumps, sun, [9, 5], 1).is_none());
        }
        // Straight overhead: the ground.
        let overhead = TerrainShadow::compute(&bumps, DVec3::Y, [17, 9], 1).unwrap();
        assert_eq!(overhead.heights.heights(), bumps.heights());
    }
}
