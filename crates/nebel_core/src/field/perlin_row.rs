//! 3D Perlin noise (Perlin 2002, "Improving noise": quintic fade, twelve edge
//! gradients) along a row of grid points, equal bit for bit to
//! [`noise::Perlin`]'s pointwise `get`.
//!
//! A grid row varies only in x, so the lattice cell's y and z, their fades and
//! the corners' hashes stay the same along it, and the hashes change only where
//! the row crosses a lattice plane (every `1 / (frequency · spacing)` points:
//! about 100 for the first cloud octave at 10 m spacing). [`PerlinRow`] hashes
//! the four corners of each lattice plane the row crosses once (a cell's
//! upper face is the next cell's lower face) and evaluates the points of a
//! cell in one branch-free loop: each corner's gradient dot product is
//! `s · x + c` with the sign `s ∈ {−1, 0, 1}` of its x component and the
//! row's constant y–z part `c`, which rounds exactly as `noise`'s
//! `±x ± y`, `±x ± z`, `±y ± z` (negation and multiplication by ±1 or 0 are
//! exact), followed by `noise`'s fade, interpolation order and clamp.

use noise::permutationtable::{NoiseHasher, PermutationTable};

/// `2 / √3`, `noise`'s scale from the unscaled range `±√3 / 2` to ±1.
const SCALE_FACTOR: f64 = 1.154_700_538_379_251_5;

/// The gradient dot products of one lattice corner: `x_sign · x + yz` at a
/// point `x` along the row from the corner (the twelve gradients of Perlin
/// 2002, `noise`'s hash-to-gradient table).
#[derive(Clone, Copy)]
struct CornerGradient {
    x_sign: f64,
    yz: f64,
}

impl CornerGradient {
    /// The gradient picked by `hash` at the corner, for the point at `y`, `z`
    /// from it.
    fn new(hash: usize, y: f64, z: f64) -> Self {
        let (x_sign, yz) = match hash & 0b1111 {
            0 | 12 => (1.0, y),
            1 | 13 => (-1.0, y),
            2 => (1.0, -y),
            3 => (-1.0, -y),
            4 => (1.0, z),
            5 => (-1.0, z),
            6 => (1.0, -z),
            7 => (-1.0, -z),
            8 => (0.0, y + z),
            9 | 14 => (0.0, -y + z),
            10 => (0.0, y - z),
            _ => (0.0, -y - z),
        };
        Self { x_sign, yz }
    }

    fn dot(self, x: f64) -> f64 {
        self.x_sign * x + self.yz
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

impl PerlinRow {
    pub(super) fn new(seed: u32) -> Self {
        Self {
            table: PermutationTable::new(seed),
        }
    }

    /// Adds `amplitude · P(xs[i], y, z)` to `sums[i]` for every `i` with
    /// `live(i)` in a lattice cell (cells without such a point are skipped;
    /// every point of a cell with one is added). `xs` must be increasing (a
    /// grid row) and as long as `sums`; `noise`'s `get` at the same point
    /// gives the same `P` bit for bit.
    pub(super) fn add_row(
        &self,
        xs: &[f64],
        y: f64,
        z: f64,
        amplitude: f64,
        sums: &mut [f64],
        live: impl Fn(usize) -> bool,
    ) {
        debug_assert_eq!(xs.len(), sums.len());
        let y = FixedAxis::new(y);
        let z = FixedAxis::new(z);
        // The last lattice plane hashed: its x and its corners' gradients.
        let mut last_plane: Option<(isize, PlaneGradients)> = None;
        let mut start = 0;
        while start < xs.len() {
            let corner = lattice_corner(xs[start]);
            let end = start
                + xs[start..]
                    .iter()
                    .position(|&x| lattice_corner(x) != corner)
                    .unwrap_or(xs.len() - start);
            if (start..end).any(&live) {
                let lower = match last_plane {
                    Some((plane, gradients)) if plane == corner => gradients,
                    _ => self.plane_gradients(corner, y, z),
                };
                let upper = self.plane_gradients(corner + 1, y, z);
                last_plane = Some((corner + 1, upper));
                add_cell(
                    corner as f64,
                    [lower, upper],
                    [y, z],
                    amplitude,
                    &xs[start..end],
                    &mut sums[start..end],
                );
            }
            start = end;
        }
    }

    /// The gradients of the row's cell corners on the lattice plane `x`.
    fn plane_gradients(&self, x: isize, y: FixedAxis, z: FixedAxis) -> PlaneGradients {
        let gradient = |dy: isize, dz: isize| {
            let hash = self.table.hash(&[x, y.corner + dy, z.corner + dz]);
            let y = if dy == 0 { y.near } else { y.far };
            let z = if dz == 0 { z.near } else { z.far };
            CornerGradient::new(hash, y, z)
        };
        [
            gradient(0, 0),
            gradient(1, 0),
            gradient(0, 1),
            gradient(1, 1),
        ]
    }
}

/// The gradients of a cell's four corners on one x lattice plane, in the order
/// (dy, dz) = 00, 10, 01, 11.
type PlaneGradients = [CornerGradient; 4];

/// [`PerlinRow::add_row`] for the points `xs` of one lattice cell: `corner`
/// its lower x, `planes` the gradients on its lower and upper x faces, `[y,
/// z]` the row's fixed axes.
fn add_cell(
    corner: f64,
    planes: [PlaneGradients; 2],
    [y, z]: [FixedAxis; 2],
    amplitude: f64,
    xs: &[f64],
    sums: &mut [f64],
) {
    let [[g000, g010, g001, g011], [g100, g110, g101, g111]] = planes;
    let (fz, gz) = (z.fade, z.one_minus_fade);
    let (fy, gy) = (y.fade, y.one_minus_fade);
    for (&x, sum) in xs.iter().zip(sums.iter_mut()) {
        let near = x - corner;
        let far = near - 1.0;
        let fade = quintic(near);
        let lower_x = linear(
            linear(g000.dot(near), g001.dot(near), fz, gz),
            linear(g010.dot(near), g011.dot(near), fz, gz),
            fy,
            gy,
        );
        let upper_x = linear(
            linear(g100.dot(far), g101.dot(far), fz, gz),
            linear(g110.dot(far), g111.dot(far), fz, gz),
            fy,
            gy,
        );
        let noise = (linear(lower_x, upper_x, fade, 1.0 - fade) * SCALE_FACTOR).clamp(-1.0, 1.0);
        *sum += amplitude * noise;
    }
}

#[cfg(test)]
mod tests {
    use noise::{NoiseFn, Perlin};
    use proptest::prelude::*;

    use super::*;

    proptest! {
        /// Rows crossing zero and lattice planes, from a hundredth of a cell
        /// to several cells per point, at integer and fractional y and z.
        #[test]
        fn rows_equal_noise_perlin_bit_for_bit(
            seed in any::<u32>(),
            points in 1usize..300,
            step in prop_oneof![1e-3..0.05, 0.05..1.0, 1.0..7.0, Just(0.25)],
            start in prop_oneof![-40.0..40.0, (-40i32..40).prop_map(f64::from)],
            y in prop_oneof![-9.0..9.0, (-9i32..9).prop_map(f64::from)],
            z in prop_oneof![-1e3..1e3, Just(0.0)],
            amplitude in 0.1..3.0,
        ) {
            let perlin = Perlin::new(seed);
            let xs: Vec<f64> = (0..points).map(|i| start + i as f64 * step).collect();
            let initial: Vec<f64> = xs.iter().map(|x| x.sin()).collect();
            let mut sums = initial.clone();
            PerlinRow::new(seed).add_row(&xs, y, z, amplitude, &mut sums, |_| true);
            for (i, (&x, &sum)) in xs.iter().zip(&sums).enumerate() {
                let expected = initial[i] + amplitude * perlin.get([x, y, z]);
                prop_assert_eq!(sum.to_bits(), expected.to_bits(), "point {} at ({}, {}, {})", i, x, y, z);
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
        row.add_row(&xs, 0.3, 0.6, 1.0, &mut sums, |i| i == 5);
        for (i, (&x, &sum)) in xs.iter().zip(&sums).enumerate() {
            if (4..8).contains(&i) {
                assert_eq!(sum, perlin.get([x, 0.3, 0.6]), "point {i}");
                assert_ne!(sum, 0.0);
            } else {
                assert_eq!(sum, 0.0, "point {i} lies in a cell without a live point");
            }
        }
    }
}
