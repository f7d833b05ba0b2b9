//! 3D Perlin noise (Perlin 2002, "Improving noise": quintic fade, twelve edge
//! gradients) along a row of grid points, equal to [`noise::Perlin`]'s
//! pointwise `get` up to rounding.
//!
//! A grid row varies only in x, so the lattice cell's y and z, their fades and
//! the corners' hashes stay the same along it, and the hashes change only where
//! the row crosses a lattice plane (every `1 / (frequency · spacing)` points:
//! about 100 for the first cloud octave at 10 m spacing). Neighbouring rows
//! share the lattice row (the y and z corners) for many points too (every
//! `1 / (frequency · spacing)` rows), and the grid's rows all have the same
//! x: a [`RowLattice`] splits the row's points into their lattice cells once
//! per grid, with each point's distance from its cell's lower x plane and
//! its quintic fade, and keeps each cell's eight corner hashes for the lattice
//! rows met since the z corner last changed, so a grid's rows are hashed
//! once per lattice row, not once per row.
//!
//! On a row, each corner's gradient dot product is linear in x (`s · x + c`
//! with the sign `s ∈ {−1, 0, 1}` of its gradient's x component and a
//! constant y–z part `c`), so the y–z interpolation of a cell face's four
//! corners is one line per face and row ([`PlaneLine`]), made once for the
//! two cells on either side of the face. [`PerlinRow`]
//! evaluates the points of a cell in one branch-free loop of two lines, the
//! fade-weighted mean and `noise`'s clamp: about a quarter of the arithmetic
//! of interpolating the eight dot products point by point as `noise` does,
//! with which it agrees to a few units in the last place.
//!
//! A row turned in noise space (a cloud octave under torque) is a line in any
//! direction: [`PerlinRow::add_line`] interpolates each point's eight dot
//! products as `noise` does, hashing a lattice cell's corners once for the
//! run of points in it.

use std::ops::Range;

use glam::DVec3;

use noise::permutationtable::{NoiseHasher, PermutationTable};

/// `2 / √3`, `noise`'s scale from the unscaled range `±√3 / 2` to ±1.
const SCALE_FACTOR: f64 = 1.154_700_538_379_251_5;

/// The gradient dot products of one lattice corner: `x_sign · x + yz` at a
/// point `x` along the row from the corner.
#[derive(Clone, Copy)]
struct CornerGradient {
    x_sign: f64,
    yz: f64,
}

/// The twelve edge gradients of Perlin 2002 as `noise` picks them by the low
/// four bits of a corner's hash (four of them twice), as `[x, y, z]`.
const GRADIENTS: [[f64; 3]; 16] = [
    [1.0, 1.0, 0.0],
    [-1.0, 1.0, 0.0],
    [1.0, -1.0, 0.0],
    [-1.0, -1.0, 0.0],
    [1.0, 0.0, 1.0],
    [-1.0, 0.0, 1.0],
    [1.0, 0.0, -1.0],
    [-1.0, 0.0, -1.0],
    [0.0, 1.0, 1.0],
    [0.0, -1.0, 1.0],
    [0.0, 1.0, -1.0],
    [0.0, -1.0, -1.0],
    [1.0, 1.0, 0.0],
    [-1.0, 1.0, 0.0],
    [0.0, -1.0, 1.0],
    [0.0, -1.0, -1.0],
];

impl CornerGradient {
    /// The gradient picked by `hash` at the corner, for the point at `y`, `z`
    /// from it: a table lookup, no branch (the hashes are random, so a
    /// `match` mispredicts).
    #[inline(always)]
    fn new(hash: usize, y: f64, z: f64) -> Self {
        let [x_sign, y_sign, z_sign] = GRADIENTS[hash & 0b1111];
        Self {
            x_sign,
            yz: y_sign * y + z_sign * z,
        }
    }
}

/// `noise`'s lattice corner below `v`: `v` truncated, one less at or below 0
/// (so 0 itself lies at the top of the cell below). Saturates far outside
/// `isize`, where `noise` panics.
fn lattice_corner(v: f64) -> isize {
    if v <= 0.0 { v as isize - 1 } else { v as isize }
}

/// `noise`'s quintic fade `6t⁵ − 15t⁴ + 10t³` of `t` clamped to [0, 1].
fn quintic(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// `noise`'s `linear(a, b, alpha)`.
fn linear(a: f64, b: f64, alpha: f64, one_minus_alpha: f64) -> f64 {
    b * alpha + a * one_minus_alpha
}

/// One axis of the row's lattice cell that is the same for every point.
#[derive(Clone, Copy)]
struct FixedAxis {
    corner: isize,
    /// Distance from the lower corner plane, in [0, 1].
    near: f64,
    /// Distance from the upper corner plane, `near − 1`.
    far: f64,
    fade: f64,
    one_minus_fade: f64,
}

impl FixedAxis {
    fn new(v: f64) -> Self {
        let corner = lattice_corner(v);
        let near = v - corner as f64;
        let fade = quintic(near);
        Self {
            corner,
            near,
            far: near - 1.0,
            fade,
            one_minus_fade: 1.0 - fade,
        }
    }
}

/// One seeded 3D Perlin noise, evaluated along rows (see the module
/// documentation). Equal to `noise::Perlin::new(seed)`.
pub(super) struct PerlinRow {
    table: PermutationTable,
}

/// The points of a row in noise coordinates, split into the lattice cells
/// they lie in, and the corner hashes of those cells, kept for the rows
/// that share a lattice row (a y and z corner): one per octave and thread.
pub(super) struct RowLattice {
    /// Per point, its place along the x axis of its lattice cell: the
    /// distance from the cell's lower x plane and its fade, the same for
    /// every row of a grid.
    points: RowPoints,
    /// Per lattice cell the row crosses: its lower x corner and the range of
    /// the points in it.
    cells: Vec<(isize, Range<usize>)>,
    /// The cells' corner hashes.
    hashes: LatticeRowHashes,
}

/// The x axis of the points of a row in their lattice cells, as `noise`
/// computes it for each point: `near = x − corner` and its quintic fade
/// (`far = near − 1` and `1 − fade` are one subtraction away).
struct RowPoints {
    near: Vec<f64>,
    fade: Vec<f64>,
}

/// Per cell of a [`RowLattice`], the hashes of its lower and upper planes'
/// corners in the lattice rows met since the z corner last changed.
#[derive(Default)]
struct LatticeRowHashes {
    /// The z corner the hashes are for.
    z_corner: Option<isize>,
    /// Per y corner: per cell, the two planes' hashes once computed.
    by_y_corner: Vec<(isize, Vec<Option<[PlaneHashes; 2]>>)>,
}

/// The hashes of a lattice plane's four corners `(dy, dz)` = (0, 0), (1, 0),
/// (0, 1), (1, 1).
type PlaneHashes = [usize; 4];

impl RowLattice {
    /// The lattice cells of the increasing noise x coordinates `xs`.
    pub(super) fn new(xs: Vec<f64>) -> Self {
        let mut cells = Vec::new();
        let mut start = 0;
        while start < xs.len() {
            let corner = lattice_corner(xs[start]);
            let end = start
                + xs[start..]
                    .iter()
                    .position(|&x| lattice_corner(x) != corner)
                    .unwrap_or(xs.len() - start);
            cells.push((corner, start..end));
            start = end;
        }
        let corners = cells
            .iter()
            .flat_map(|(corner, range)| range.clone().map(|_| *corner as f64));
        let near: Vec<f64> = xs
            .iter()
            .zip(corners)
            .map(|(x, corner)| x - corner)
            .collect();
        let fade = near.iter().map(|&near| quintic(near)).collect();
        Self {
            points: RowPoints { near, fade },
            cells,
            hashes: LatticeRowHashes::default(),
        }
    }
}

impl LatticeRowHashes {
    /// The `cells` hash slots of the lattice row of corners `y` and `z`; the
    /// slots of the last z corner are dropped when it changes.
    fn slots(&mut self, y: isize, z: isize, cells: usize) -> &mut [Option<[PlaneHashes; 2]>] {
        if self.z_corner != Some(z) {
            self.z_corner = Some(z);
            self.by_y_corner.clear();
        }
        let slot = match self.by_y_corner.iter().position(|(corner, _)| *corner == y) {
            Some(slot) => slot,
            None => {
                self.by_y_corner.push((y, vec![None; cells]));
                self.by_y_corner.len() - 1
            }
        };
        &mut self.by_y_corner[slot].1
    }
}

impl PerlinRow {
    pub(super) fn new(seed: u32) -> Self {
        Self {
            table: PermutationTable::new(seed),
        }
    }

    /// Adds `shape(amplitude · P(x, y, z))` to `sums[i]` for the points of
    /// `lattice` with `live(i)` in a lattice cell (cells without such a point
    /// are skipped; every point of a cell with one is added). `sums` is as
    /// long as the lattice's points; `P` is `noise`'s `get` at the same
    /// point to rounding (see [`PlaneLine`]). The corners of a lattice cell
    /// are hashed once for all the rows of its lattice row while `z`'s
    /// corner stays the same. Always inlined (with the cell loop), so that it
    /// is compiled for the instruction set its caller dispatches to.
    #[inline(always)]
    pub(super) fn add_row(
        &self,
        lattice: &mut RowLattice,
        y: f64,
        z: f64,
        amplitude: f64,
        sums: &mut [f64],
        live: impl Fn(usize) -> bool,
        shape: impl Fn(f64) -> f64 + Copy,
    ) {
        debug_assert_eq!(lattice.points.near.len(), sums.len());
        let y = FixedAxis::new(y);
        let z = FixedAxis::new(z);
        let cell_hashes = |corner: isize| [corner, corner + 1].map(|x| self.plane_hashes(x, y, z));
        let RowLattice {
            points,
            cells,
            hashes,
        } = lattice;
        let scale = amplitude * SCALE_FACTOR;
        // The upper face of a cell is the lower face of the next: its line,
        // with the x corner of its plane.
        let mut last_upper: Option<(isize, PlaneLine)> = None;
        for ((corner, range), slot) in
            cells
                .iter()
                .zip(hashes.slots(y.corner, z.corner, cells.len()))
        {
            if !range.clone().any(&live) {
                continue;
            }
            let [lower, upper] = *slot.get_or_insert_with(|| cell_hashes(*corner));
            let lower = match last_upper {
                Some((plane, line)) if plane == *corner => line,
                _ => PlaneLine::new(lower, y, z, scale),
            };
            let upper = PlaneLine::new(upper, y, z, scale);
            last_upper = Some((corner + 1, upper));
            add_cell(
                [lower, upper],
                amplitude,
                points,
                range.clone(),
                &mut sums[range.clone()],
                shape,
            );
        }
    }

    /// Adds `shape(amplitude · P(base + x · direction))` to `sums[i]` for the
    /// `x = xs[i]` with `live(i)`, `P` as [`PerlinRow::add_row`]'s: a row
    /// along any direction in noise space. Each point interpolates its
    /// cell's eight gradient dot products as `noise` does; the corners'
    /// gradients are looked up once for a run of points in one cell.
    #[inline(always)]
    pub(super) fn add_line(
        &self,
        (base, direction): (DVec3, DVec3),
        xs: &[f64],
        amplitude: f64,
        sums: &mut [f64],
        live: impl Fn(usize) -> bool,
        shape: impl Fn(f64) -> f64,
    ) {
        debug_assert_eq!(xs.len(), sums.len());
        let mut cell: Option<([isize; 3], [[f64; 3]; 8])> = None;
        for (i, (sum, &x)) in sums.iter_mut().zip(xs).enumerate() {
            if !live(i) {
                continue;
            }
            let point = (base + x * direction).to_array();
            let corner = point.map(lattice_corner);
            let gradients = match cell {
                Some((at, gradients)) if at == corner => gradients,
                _ => {
                    let gradients = std::array::from_fn(|c| {
                        let offset = [c >> 2, (c >> 1) & 1, c & 1].map(|o| o as isize);
                        let at: [isize; 3] =
                            std::array::from_fn(|axis| corner[axis] + offset[axis]);
                        GRADIENTS[self.table.hash(&at) & 0b1111]
                    });
                    cell = Some((corner, gradients));
                    gradients
                }
            };
            // As `noise`: the distances from the corner, each corner's
            // gradient dot product, the fades.
            let near: [f64; 3] = std::array::from_fn(|axis| point[axis] - corner[axis] as f64);
            let dot = |c: usize| {
                let g = gradients[c];
                let d = [c >> 2, (c >> 1) & 1, c & 1].map(|o| o as f64);
                g[0] * (near[0] - d[0]) + g[1] * (near[1] - d[1]) + g[2] * (near[2] - d[2])
            };
            let [fx, fy, fz] = near.map(quintic);
            let lerp = |a: f64, b: f64, t: f64| linear(a, b, t, 1.0 - t);
            // Along z, then y, then x, as `noise` interpolates.
            let face = |x: usize| {
                let along_z = |y: usize| lerp(dot(x << 2 | y << 1), dot(x << 2 | y << 1 | 1), fz);
                lerp(along_z(0), along_z(1), fy)
            };
            let value = lerp(face(0), face(1), fx);
            *sum += shape(amplitude * (value * SCALE_FACTOR).clamp(-1.0, 1.0));
        }
    }

    /// The hashes of the four corners of the lattice plane at `x` of the
    /// lattice row of `y` and `z`.
    fn plane_hashes(&self, x: isize, y: FixedAxis, z: FixedAxis) -> PlaneHashes {
        [(0, 0), (1, 0), (0, 1), (1, 1)]
            .map(|(dy, dz)| self.table.hash(&[x, y.corner + dy, z.corner + dz]))
    }
}

/// The noise of a lattice cell's x face along a row, scaled: its four
/// corners' gradient dot products `s · d + c` (`d` the distance from the
/// face along x), interpolated over the row's fixed y and z with `noise`'s
/// fades, are one line `slope · d + constant`, times `scale`. Perlin's
/// value is the fade-weighted mean of the lower face's line at `near` and
/// the upper face's at `far`. `noise` interpolates the eight dot products
/// point by point instead; the line is the same polynomial, so the two
/// differ by rounding only (a few units in the last place of values of
/// order 1: the tests allow 1e-13).
#[derive(Clone, Copy)]
struct PlaneLine {
    slope: f64,
    constant: f64,
}

impl PlaneLine {
    /// The line of the face whose corners `(dy, dz)` = (0, 0), (1, 0), (0,
    /// 1), (1, 1) have `hashes`, on the row at `y` and `z`, times `scale`.
    #[inline(always)]
    fn new(hashes: PlaneHashes, y: FixedAxis, z: FixedAxis, scale: f64) -> Self {
        let [h00, h10, h01, h11] = hashes;
        let along_z = |near_z: CornerGradient, far_z: CornerGradient| {
            [
                linear(near_z.x_sign, far_z.x_sign, z.fade, z.one_minus_fade),
                linear(near_z.yz, far_z.yz, z.fade, z.one_minus_fade),
            ]
        };
        let [near_slope, near_constant] = along_z(
            CornerGradient::new(h00, y.near, z.near),
            CornerGradient::new(h01, y.near, z.far),
        );
        let [far_slope, far_constant] = along_z(
            CornerGradient::new(h10, y.far, z.near),
            CornerGradient::new(h11, y.far, z.far),
        );
        Self {
            slope: scale * linear(near_slope, far_slope, y.fade, y.one_minus_fade),
            constant: scale * linear(near_constant, far_constant, y.fade, y.one_minus_fade),
        }
    }
}

/// [`PerlinRow::add_row`] for the points `range` of one lattice cell:
/// `lower` and `upper` the lines of its x faces, scaled by `amplitude` times
/// `noise`'s scale, whose fade-weighted mean `noise` clamps to ±1 before the
/// amplitude, then through `shape`.
#[inline(always)]
fn add_cell(
    [lower, upper]: [PlaneLine; 2],
    amplitude: f64,
    points: &RowPoints,
    range: Range<usize>,
    sums: &mut [f64],
    shape: impl Fn(f64) -> f64,
) {
    let near = &points.near[range.clone()];
    let fade = &points.fade[range];
    for ((sum, &near), &fade) in sums.iter_mut().zip(near).zip(fade) {
        let lower = lower.slope * near + lower.constant;
        let upper = upper.slope * (near - 1.0) + upper.constant;
        *sum += shape(linear(lower, upper, fade, 1.0 - fade).clamp(-amplitude, amplitude));
    }
}

#[cfg(test)]
mod tests {
    use noise::{NoiseFn, Perlin};
    use proptest::prelude::*;

    use super::*;

    /// The largest difference allowed from `noise`'s `get` for values of
    /// order 1: a few units in the last place.
    const ROUNDING: f64 = 1e-13;

    proptest! {
        /// Rows crossing zero and lattice planes, from a hundredth of a cell
        /// to several cells per point, at integer and fractional y and z;
        /// slices of rows through one lattice, as a grid is filled (y
        /// corners met again after z moved on, z corners kept or changed),
        /// so the kept hashes are reused and dropped.
        #[test]
        fn rows_equal_noise_perlin_to_rounding(
            seed in any::<u32>(),
            points in 1usize..300,
            step in prop_oneof![1e-3..0.05, 0.05..1.0, 1.0..7.0, Just(0.25)],
            start in prop_oneof![-40.0..40.0, (-40i32..40).prop_map(f64::from)],
            y in prop_oneof![-9.0..9.0, (-9i32..9).prop_map(f64::from)],
            z in prop_oneof![-1e3..1e3, Just(0.0)],
            row_step in prop_oneof![0.0..0.5, 0.5..2.0, Just(1.0)],
            amplitude in 0.1..3.0,
        ) {
            let perlin = Perlin::new(seed);
            let row = PerlinRow::new(seed);
            let xs: Vec<f64> = (0..points).map(|i| start + i as f64 * step).collect();
            let mut lattice = RowLattice::new(xs.clone());
            for slice in 0..3 {
                for j in 0..4 {
                    let (y, z): (f64, f64) = (y + f64::from(j) * row_step, z + f64::from(slice) * row_step);
                    let initial: Vec<f64> = xs.iter().map(|&x| (x + y).sin()).collect();
                    let mut sums = initial.clone();
                    row.add_row(&mut lattice, y, z, amplitude, &mut sums, |_| true, |n| n);
                    for (i, (&x, &sum)) in xs.iter().zip(&sums).enumerate() {
                        let expected = initial[i] + amplitude * perlin.get([x, y, z]);
                        prop_assert!((sum - expected).abs() <= ROUNDING, "point {} at ({}, {}, {}): {} against {}", i, x, y, z, sum, expected);
                    }
                }
            }
        }
    }

    #[test]
    fn cells_without_a_live_point_are_skipped() {
        let row = PerlinRow::new(3);
        let perlin = Perlin::new(3);
        // Cells [0, 1), [1, 2), [2, 3): four points each.
        let xs: Vec<f64> = (0..12).map(|i| 0.125 + i as f64 * 0.25).collect();
        let mut sums = vec![0.0; xs.len()];
        let mut lattice = RowLattice::new(xs.clone());
        row.add_row(&mut lattice, 0.3, 0.6, 1.0, &mut sums, |i| i == 5, |n| n);
        for (i, (&x, &sum)) in xs.iter().zip(&sums).enumerate() {
            if (4..8).contains(&i) {
                assert!(
                    (sum - perlin.get([x, 0.3, 0.6])).abs() <= ROUNDING,
                    "point {i}"
                );
                assert_ne!(sum, 0.0);
            } else {
                assert_eq!(sum, 0.0, "point {i} lies in a cell without a live point");
            }
        }
    }

    proptest! {
        /// Lines in every direction, from a hundredth of a cell to several
        /// cells per point, some points skipped.
        #[test]
        fn lines_equal_noise_perlin_to_rounding(
            seed in any::<u32>(),
            points in 1usize..200,
            base in prop::array::uniform3(-40.0..40.0f64),
            direction in prop::array::uniform3(-3.0..3.0f64),
            step in prop_oneof![1e-3..0.05, 0.05..1.0, 1.0..4.0],
            amplitude in 0.1..3.0,
        ) {
            let perlin = Perlin::new(seed);
            let row = PerlinRow::new(seed);
            let (base, direction) = (DVec3::from(base), DVec3::from(direction));
            let xs: Vec<f64> = (0..points).map(|i| i as f64 * step - 5.0).collect();
            let mut sums = vec![0.5; points];
            row.add_line((base, direction), &xs, amplitude, &mut sums, |i| i % 7 != 3, |n| n);
            for (i, (&x, &sum)) in xs.iter().zip(&sums).enumerate() {
                let p = base + x * direction;
                let expected = if i % 7 == 3 { 0.5 } else { 0.5 + amplitude * perlin.get(p.to_array()) };
                prop_assert!((sum - expected).abs() <= ROUNDING, "point {} at {}: {} against {}", i, p, sum, expected);
            }
        }
    }
}
