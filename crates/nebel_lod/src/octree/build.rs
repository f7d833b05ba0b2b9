//! Building a [`VolumeHierarchy`]: quantisation, then Δ and scalar ranges level
//! by level from the voxels up (Röttger and Ertl 2003 §2.2, §2.4; the rules are in the
//! module docs of [`super`]).
//!
//! A yield point for a paced build ([`nebel_core::pacing`]) follows every
//! 65,536 values quantised and every layer of nodes of each level.

use std::sync::Arc;

use nebel_core::field::DensityGrid;
use nebel_core::pacing::{filled_paced, pace};

use super::{HierarchyError, VolumeHierarchy, k_max};

impl VolumeHierarchy {
    /// Builds the hierarchy of `grid` for the minimum accuracy `C`
    /// (`min_accuracy`, > √3; the per-frame refinement must use the same `C`).
    ///
    /// Errors: [`HierarchyError::NotPowerOfTwoPlusOne`] unless every axis has
    /// `2^n + 1` points, [`HierarchyError::InvalidMinAccuracy`] unless `C` is
    /// finite and > √3, [`HierarchyError::OverBudget`] when the hierarchy
    /// (4 bytes per point, [`VolumeHierarchy::check_budget`]) exceeds the
    /// memory budget, before anything is allocated. The grid's values are
    /// finite and in [0, 1] by construction ([`DensityGrid::new`] rejects
    /// NaN), so they need no check.
    pub fn new(grid: &DensityGrid, min_accuracy: f64) -> Result<Self, HierarchyError> {
        Self::build(grid, None, min_accuracy)
    }

    /// Builds the hierarchy of a lit cloud (Röttger and Ertl 2003 §5): the density `grid`
    /// and its light field γ (`light`, sampled at the same points, e.g. from
    /// `nebel_core::field::light_field`). Both are quantised to u8 and Δ is the
    /// maximum deviation of **either** field, so the mesh is refined where the
    /// density or the light varies (§5.1: "driven by the maximum deviation of
    /// both scalar fields"); the scalar ranges stay those of the density (the
    /// zero-opacity test is on the opacity). Five bytes per grid point, checked
    /// against the memory budget like [`VolumeHierarchy::new`].
    ///
    /// Errors: as [`VolumeHierarchy::new`], and
    /// [`HierarchyError::LightDimsMismatch`] when the two grids differ in
    /// points per axis.
    pub fn with_light(
        grid: &DensityGrid,
        light: &DensityGrid,
        min_accuracy: f64,
    ) -> Result<Self, HierarchyError> {
        if light.dims() != grid.dims() {
            return Err(HierarchyError::LightDimsMismatch {
                density: grid.dims(),
                light: light.dims(),
            });
        }
        Self::build(grid, Some(light), min_accuracy)
    }

    fn build(
        grid: &DensityGrid,
        light: Option<&DensityGrid>,
        min_accuracy: f64,
    ) -> Result<Self, HierarchyError> {
        let k_max = k_max(min_accuracy)?;
        let dims = grid.dims();
        let exponents =
            dims.map(|n| (n >= 2 && (n - 1).is_power_of_two()).then(|| (n - 1).trailing_zeros()));
        let [Some(ex), Some(ey), Some(ez)] = exponents else {
            return Err(HierarchyError::NotPowerOfTwoPlusOne { dims });
        };
        Self::check_budget(dims, light.is_some())?;
        let root_level = ex.min(ey).min(ez);
        let points = grid.values().len();
        let mut hierarchy = Self {
            dims,
            spacing: grid.spacing(),
            origin: grid.origin(),
            root_level,
            root_counts: dims.map(|n| (n - 1) >> root_level),
            min_accuracy,
            k_max,
            density: Arc::new(quantise(grid)),
            light: Arc::new(light.map(quantise).unwrap_or_default()),
            next_density: Arc::default(),
            next_light: Arc::default(),
            next_words: Arc::default(),
            words: Arc::new(filled_paced(points, 0)),
            morph: Arc::new(filled_paced(points, 0)),
        };
        if root_level >= 1 {
            hierarchy.build_first_level();
        }
        for level in 2..=root_level {
            hierarchy.build_level(level);
        }
        Ok(hierarchy)
    }

    /// Computes Δ and the scalar range of every node of level 1 (eight
    /// voxels, 27 points) along grid rows: the deviation of every point from
    /// its coarse value, a plane of points at a time (each point once, where
    /// a node-by-node pass reads the shared ones up to four times), then per
    /// node the maximum over its 27 points (0 at its corners) and the range
    /// of its densities, pooled over rows and then along them. Each layer of
    /// nodes is compiled for the vector instructions the CPU has (`pulp`'s
    /// runtime dispatch; integer operations, so the same on every CPU).
    fn build_first_level(&mut self) {
        let [nx, ny, nz] = self.dims;
        let plane = nx * ny;
        let mut level = FirstLevel {
            kinds: PointKinds::new([1, nx, plane]),
            dims: self.dims,
            density: &self.density,
            light: &self.light,
            words: Arc::make_mut(&mut self.words).as_mut_slice(),
            planes: [0; 3].map(|_| vec![0u16; plane]),
            scratch: vec![0; 2 * nx],
            deviation: vec![0; nx],
            low: vec![0; nx],
            high: vec![0; nx],
        };
        let mut first_plane = std::mem::take(&mut level.planes[0]);
        level.deviation_plane(0, &mut first_plane);
        level.planes[0] = first_plane;
        let arch = pulp::Arch::new();
        for z in (0..nz - 1).step_by(2) {
            arch.dispatch(FirstLevelLayer {
                level: &mut level,
                z,
            });
            pace();
        }
    }

    /// Computes Δ (propagated from level − 1, already built) and the scalar
    /// range of every node of `level ≥ 2`.
    fn build_level(&mut self, level: u32) {
        let [nx, ny, _] = self.dims;
        let size = 1usize << level;
        let half = size / 2;
        let counts = self.dims.map(|n| (n - 1) >> level);
        // Flat offset of local point (a, b, c) ∈ {0, 1, 2}³ in steps of `half`.
        let step = [half, half * nx, half * nx * ny];
        let offset = |a: usize, b: usize, c: usize| a * step[0] + b * step[1] + c * step[2];
        let corner_offsets: [usize; 8] =
            std::array::from_fn(|v| offset(2 * (v & 1), 2 * ((v >> 1) & 1), 2 * ((v >> 2) & 1)));
        // The nineteen points born at this level as flat offsets, with the
        // two corners their coarse value averages.
        let midpoints = BORN_POINTS.map(|(mid, ends)| (offset(mid[0], mid[1], mid[2]), ends));
        // Children: their centres and the centres of their +x faces, relative
        // to the node's origin (quarter = half / 2).
        let quarter = half / 2;
        let child_offset = |v: usize, dx: usize| {
            let o = [v & 1, (v >> 1) & 1, (v >> 2) & 1];
            (o[0] * half + dx) + nx * ((o[1] * half + quarter) + ny * (o[2] * half + quarter))
        };
        let child_centres: [usize; 8] = std::array::from_fn(|v| child_offset(v, quarter));
        let child_ranges: [usize; 8] = std::array::from_fn(|v| child_offset(v, half));
        let centre = offset(1, 1, 1);
        let range_slot = offset(2, 1, 1);
        let k_max = self.k_max;
        // Nothing shares the arrays of a hierarchy being built: no copy.
        let (density, light) = (&self.density, &self.light);
        let words = Arc::make_mut(&mut self.words);

        for z in 0..counts[2] {
            for y in 0..counts[1] {
                for x in 0..counts[0] {
                    let base = x * size + nx * (y * size + ny * (z * size));
                    // Deviations in units of 1/1020 (4 · 255), so exact.
                    let local_deviation = |field: &[u8]| {
                        let d = |off: usize| i32::from(field[base + off]);
                        let corners = corner_offsets.map(d);
                        let mut deviation = 0;
                        for &(mid, [v0, v1]) in &midpoints {
                            deviation =
                                deviation.max(2 * (2 * d(mid) - corners[v0] - corners[v1]).abs());
                        }
                        deviation
                    };
                    let mut deviation = local_deviation(density);
                    if !light.is_empty() {
                        deviation = deviation.max(local_deviation(light));
                    }
                    let mut delta = quantised_deviation(deviation as u16);
                    let mut range = [u8::MAX, u8::MIN];
                    for v in 0..8 {
                        let child = words[base + child_centres[v]];
                        // Eq. 5 on the stored values, rounded up.
                        let propagated = (k_max * f64::from(child)).ceil() as u16;
                        delta = delta.max(propagated);
                        let [min, max] = words[base + child_ranges[v]].to_le_bytes();
                        range = [range[0].min(min), range[1].max(max)];
                    }
                    words[base + centre] = delta;
                    words[base + range_slot] = u16::from_le_bytes(range);
                }
            }
            pace();
        }
    }
}

/// A local deviation in units of 1/1020 (4 · 255, so the integer sums are
/// exact) as a stored Δ in units of 1/65535: `65535 / 1020 = 257 / 4`,
/// rounded up.
fn quantised_deviation(deviation: u16) -> u16 {
    (u32::from(deviation) * 257).div_ceil(4) as u16
}

/// The level-1 pass of [`VolumeHierarchy::build`]: the quantised fields
/// read, the Δ and range words written, and the rows it keeps.
struct FirstLevel<'a> {
    kinds: PointKinds,
    dims: [usize; 3],
    density: &'a [u8],
    /// Empty for an unlit hierarchy.
    light: &'a [u8],
    words: &'a mut [u16],
    /// The combined point deviations of the planes `z`, `z + 1`, `z + 2` of
    /// the layer of nodes at `z`.
    planes: [Vec<u16>; 3],
    /// A row of deviations per parity of x ([`PointKinds::deviation_row`]).
    scratch: Vec<u16>,
    /// Per point of a row, the largest deviation and the density range over
    /// the nine rows of a row of nodes.
    deviation: Vec<u16>,
    low: Vec<u8>,
    high: Vec<u8>,
}

impl FirstLevel<'_> {
    /// The combined deviation of both fields at every point of plane `z`.
    #[inline(always)]
    fn deviation_plane(&mut self, z: usize, out: &mut [u16]) {
        let [nx, ny, _] = self.dims;
        for (y, out) in out.chunks_exact_mut(nx).enumerate() {
            let row = nx * (y + ny * z);
            let kinds = &self.kinds;
            kinds.deviation_row(self.density, [y, z], row, out, &mut self.scratch, false);
            if !self.light.is_empty() {
                kinds.deviation_row(self.light, [y, z], row, out, &mut self.scratch, true);
            }
        }
    }

    /// Δ and the range of every node of the layer whose low corners are in
    /// plane `z` (even), with the deviations of plane `z` in `planes[0]`;
    /// leaves those of plane `z + 2` there for the next layer.
    #[inline(always)]
    fn layer(&mut self, z: usize) {
        let [nx, ny, _] = self.dims;
        let plane = nx * ny;
        let [bottom, mut middle, mut top] = std::mem::take(&mut self.planes);
        self.deviation_plane(z + 1, &mut middle);
        self.deviation_plane(z + 2, &mut top);
        let planes = [&bottom, &middle, &top];
        for y in (0..ny - 1).step_by(2) {
            self.deviation.fill(0);
            self.low.fill(u8::MAX);
            self.high.fill(u8::MIN);
            for (dz, points) in planes.iter().enumerate() {
                for dy in 0..3 {
                    let start = (y + dy) * nx;
                    for (d, &p) in self.deviation.iter_mut().zip(&points[start..start + nx]) {
                        *d = (*d).max(p);
                    }
                    let start = start + (z + dz) * plane;
                    let values = &self.density[start..start + nx];
                    let ranges = self.low.iter_mut().zip(self.high.iter_mut());
                    for ((low, high), &v) in ranges.zip(values) {
                        (*low, *high) = ((*low).min(v), (*high).max(v));
                    }
                }
            }
            let (deviation, low, high) = (&self.deviation, &self.low, &self.high);
            let row = nx * (y + ny * z);
            for x in (0..nx - 1).step_by(2) {
                let node_deviation = deviation[x].max(deviation[x + 1]).max(deviation[x + 2]);
                let range = [
                    low[x].min(low[x + 1]).min(low[x + 2]),
                    high[x].max(high[x + 1]).max(high[x + 2]),
                ];
                // The node's centre and the centre of its +x face, as in
                // `build_level`.
                let centre = row + x + 1 + nx * (1 + ny);
                self.words[centre] = quantised_deviation(node_deviation);
                self.words[centre + 1] = u16::from_le_bytes(range);
            }
        }
        self.planes = [top, middle, bottom];
    }
}

/// [`FirstLevel::layer`] compiled for the vector instructions the CPU has.
struct FirstLevelLayer<'l, 'a> {
    level: &'l mut FirstLevel<'a>,
    z: usize,
}

impl pulp::WithSimd for FirstLevelLayer<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        self.level.layer(self.z);
    }
}

/// What a grid point is in the level-1 nodes that hold it, by which of its
/// coordinates are odd, and the flat offsets of the two points its coarse
/// value averages; the deviations along a row of points (units of 1/1020, as
/// [`VolumeHierarchy::build_level`]).
struct PointKinds {
    /// Per odd-coordinate mask (bit `a` for axis `a`, the set `S`), the flat
    /// offsets of `p ∓ 1_S`, the ends of the Kuhn edge through `p` (an edge,
    /// a face diagonal or the node's diagonal); `None` for a node corner.
    averaged: [Option<[isize; 2]>; 8],
}

impl PointKinds {
    /// The kinds for a grid whose axes step by `strides` in flat index.
    fn new(strides: [usize; 3]) -> Self {
        let averaged = std::array::from_fn(|odd: usize| {
            let step: isize = (0..3)
                .filter(|a| (odd >> a) & 1 == 1)
                .map(|a| strides[a] as isize)
                .sum();
            (odd != 0).then_some([-step, step])
        });
        Self { averaged }
    }

    /// The deviations of `field` at the points of row `(y, z)` (`out.len()`
    /// points from flat index `row`) into `out`, or their maximum with what
    /// `out` holds (`combine`); `scratch` holds two rows.
    ///
    /// Along a row the kind of a point alternates with the parity of `x`: one
    /// pass over the row for even and one for odd `x`, each the same
    /// operations on every point (vector instructions), of which that
    /// parity's are kept.
    #[inline(always)]
    fn deviation_row(
        &self,
        field: &[u8],
        [y, z]: [usize; 2],
        row: usize,
        out: &mut [u16],
        scratch: &mut [u16],
        combine: bool,
    ) {
        let nx = out.len();
        let row_odd = (y & 1) << 1 | (z & 1) << 2;
        let mut passes = scratch.chunks_exact_mut(nx);
        let passes: [&mut [u16]; 2] = std::array::from_fn(|residue| {
            let deviations = passes.next().expect("two rows of scratch");
            // Points with odd x are inside the row: their ends at x ± 1 are
            // in it too.
            let (first, last) = if residue == 1 { (1, nx - 1) } else { (0, nx) };
            let kept = &mut deviations[first..last];
            let Some([a, b]) = self.averaged[row_odd | residue] else {
                kept.fill(0);
                return deviations;
            };
            let start = row + first;
            let len = last - first;
            let points = &field[start..start + len];
            let shifted = |offset: isize| &field[start.wrapping_add_signed(offset)..][..len];
            let pairs = shifted(a).iter().zip(shifted(b));
            for ((d, &v), (&a, &b)) in kept.iter_mut().zip(points).zip(pairs) {
                let twice = 2 * i16::from(v) - i16::from(a) - i16::from(b);
                *d = 2 * twice.unsigned_abs();
            }
            deviations
        });
        // Point x takes pass x mod 2.
        let keep = |out: &mut u16, deviation: u16| {
            *out = if combine {
                (*out).max(deviation)
            } else {
                deviation
            };
        };
        let whole = nx / 2 * 2;
        let [even, odd] = passes.map(|pass| pass.split_at(whole));
        let pairs = even.0.chunks_exact(2).zip(odd.0.chunks_exact(2));
        for (out, (a, b)) in out.chunks_exact_mut(2).zip(pairs) {
            keep(&mut out[0], a[0]);
            keep(&mut out[1], b[1]);
        }
        if whole < nx {
            keep(&mut out[whole], even.1[0]);
        }
    }
}

/// The field quantised to u8, `round(255 · s)`, with a yield point after
/// every [`QUANTISED_PER_PACE`] values.
fn quantise(grid: &DensityGrid) -> Vec<u8> {
    let mut quantised_values = Vec::with_capacity(grid.values().len());
    for chunk in grid.values().chunks(QUANTISED_PER_PACE) {
        quantised_values.extend(chunk.iter().map(|&s| quantised(s)));
        pace();
    }
    quantised_values
}

/// How many values [`quantise`] converts between two yield points (a
/// fraction of a millisecond).
const QUANTISED_PER_PACE: usize = 1 << 16;

/// `(255 · s).round() as u8` for `s` in [0, 1] in operations that
/// vectorise (no call to `round`, which the x86-64 baseline lacks, and no
/// float-to-integer conversion, which saturates element by element): for
/// `0 ≤ x < 2²³` (`x = 255 · s`, f32 as there), `x + 2²³` rounds `x` to the
/// nearest integer, ties to even, into the low bits of the sum; where that
/// went down from a tie (`x` exactly half above it) half-up rounding adds
/// one. Checked once over every f32 in [0, 1]; the test below checks the
/// values next to every boundary.
fn quantised(s: f32) -> u8 {
    const SHIFT: f32 = 8_388_608.0;
    let x = s * 255.0;
    let shifted = x + SHIFT;
    let nearest = shifted.to_bits().wrapping_sub(SHIFT.to_bits()) as u8;
    nearest + u8::from(x - (shifted - SHIFT) == 0.5)
}

/// The nineteen points of a node's 3 × 3 × 3 lattice other than its corners
/// (local half-steps `(a, b, c)`, some odd; `a` fastest), each with the two
/// corners (`x + 2y + 4z`) at the ends of the Kuhn edge through it: `p ∓ 1_S`
/// for `S` its odd axes (an edge midpoint, a face centre on the face's
/// diagonal from its lowest corner, or the centre on the node's diagonal from
/// corner 0 to corner 7). The build measures Δ at them and the emission morphs
/// them.
pub(super) const BORN_POINTS: [([usize; 3], [usize; 2]); 19] = born_points();

const fn born_points() -> [([usize; 3], [usize; 2]); 19] {
    let mut points = [([0; 3], [0; 2]); 19];
    let (mut n, mut point) = (0, 0);
    while point < 27 {
        let steps = [point % 3, point / 3 % 3, point / 9];
        let (mut high, mut odd, mut axis) = (0, 0, 0);
        while axis < 3 {
            match steps[axis] {
                1 => odd |= 1 << axis,
                2 => high |= 1 << axis,
                _ => {}
            }
            axis += 1;
        }
        if odd != 0 {
            points[n] = (steps, [high, high | odd]);
            n += 1;
        }
        point += 1;
    }
    points
}

#[cfg(test)]
mod tests {
    use super::quantised;

    /// Every value within 64 ulps of each rounding boundary `(k + ½) / 255`
    /// and of each level `k / 255`, the ends, the smallest values and a
    /// sweep over [0, 1] quantise as `(255 · s).round()`.
    #[test]
    fn quantisation_rounds_as_round() {
        let mut values = vec![
            0.0f32,
            1.0,
            f32::MIN_POSITIVE,
            1e-30,
            1.0 - f32::EPSILON / 2.0,
        ];
        for k in 0..=255u32 {
            for centre in [(k as f32 + 0.5) / 255.0, k as f32 / 255.0] {
                for ulps in -64i32..=64 {
                    let bits = centre.to_bits() as i32 + ulps;
                    values.push(f32::from_bits(bits.max(0) as u32));
                }
            }
        }
        values.extend((0..=1_000_000).map(|i| i as f32 / 1e6));
        for s in values.into_iter().filter(|s| (0.0..=1.0).contains(s)) {
            assert_eq!(quantised(s), (s * 255.0).round() as u8, "{s:e}");
        }
    }
}
