//! Building a [`VolumeHierarchy`]: quantisation, then Δ and scalar ranges level
//! by level from the voxels up (Röttger and Ertl 2003 §2.2, §2.4; the rules are in the
//! module docs of [`super`]).
//!
//! A yield point for a paced build ([`nebel_core::pacing`]) follows every
//! 65,536 values quantised and every layer of nodes of each level.

use std::sync::Arc;

use nebel_core::field::DensityGrid;
use nebel_core::pacing::pace;

use super::{HierarchyError, VolumeHierarchy, k_max};
use crate::full_resolution::DECOMPOSITIONS;

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
            words: Arc::new(vec![0; points]),
            morph: Arc::new(vec![0; points]),
        };
        let diagonals = face_diagonals();
        if root_level >= 1 {
            hierarchy.build_first_level(&diagonals);
        }
        for level in 2..=root_level {
            hierarchy.build_level(level, &diagonals);
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
    fn build_first_level(&mut self, diagonals: &FaceDiagonals) {
        let [nx, ny, nz] = self.dims;
        let plane = nx * ny;
        let mut level = FirstLevel {
            kinds: PointKinds::new(diagonals, [1, nx, plane]),
            dims: self.dims,
            density: &self.density,
            light: &self.light,
            words: Arc::make_mut(&mut self.words).as_mut_slice(),
            planes: [0; 3].map(|_| vec![0u16; plane]),
            scratch: vec![0; 4 * nx],
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
    fn build_level(&mut self, level: u32, diagonals: &FaceDiagonals) {
        let [nx, ny, _] = self.dims;
        let size = 1usize << level;
        let half = size / 2;
        let counts = self.dims.map(|n| (n - 1) >> level);
        // Flat offset of local point (a, b, c) ∈ {0, 1, 2}³ in steps of `half`.
        let step = [half, half * nx, half * nx * ny];
        let offset = |a: usize, b: usize, c: usize| a * step[0] + b * step[1] + c * step[2];
        let corner_offsets: [usize; 8] =
            std::array::from_fn(|v| offset(2 * (v & 1), 2 * ((v >> 1) & 1), 2 * ((v >> 2) & 1)));
        // Per parity, the midpoints of the twelve edges and six face
        // diagonals as flat offsets, with the two corners they lie between.
        let at_mid = |(mid, ends): ([usize; 3], [usize; 2])| (offset(mid[0], mid[1], mid[2]), ends);
        let midpoints: [[(usize, [usize; 2]); 18]; 2] = std::array::from_fn(|parity| {
            let mut all = [(0, [0; 2]); 18];
            for (slot, &edge) in all
                .iter_mut()
                .zip(edge_table().iter().chain(&diagonals.faces[parity]))
            {
                *slot = at_mid(edge);
            }
            all
        });
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
                    let parity = (x + y + z) & 1;
                    // Deviations in units of 1/1020 (4 · 255), so exact.
                    let local_deviation = |field: &[u8]| {
                        let d = |off: usize| i32::from(field[base + off]);
                        let corners = corner_offsets.map(d);
                        let mut deviation = 0;
                        for &(mid, [v0, v1]) in &midpoints[parity] {
                            deviation =
                                deviation.max(2 * (2 * d(mid) - corners[v0] - corners[v1]).abs());
                        }
                        let central: i32 =
                            diagonals.central[parity].iter().map(|&v| corners[v]).sum();
                        deviation.max((4 * d(centre) - central).abs())
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
    /// A row of deviations per residue ([`PointKinds::deviation_row`]).
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
/// coordinates are odd, and the flat offsets of the points its coarse value
/// averages; the deviations along a row of points (units of 1/1020, as
/// [`VolumeHierarchy::build_level`]).
struct PointKinds {
    /// Per odd-coordinate mask (bit `a` for axis `a`) and node parity, the
    /// offsets of the corners averaged: two for an edge midpoint or a face
    /// centre, four for a node centre; none for a corner.
    averaged: [[Averaged; 2]; 8],
}

/// The corners a point's coarse value averages, as flat offsets.
#[derive(Clone, Copy, Default)]
enum Averaged {
    /// A node corner: no coarse value, deviation 0.
    #[default]
    Corner,
    /// An edge midpoint or face centre: twice `|2 v − a − b|`.
    Two([isize; 2]),
    /// A node centre: `|4 v − a − b − c − d|`.
    Four([isize; 4]),
}

impl PointKinds {
    /// The kinds for a grid whose axes step by `strides` in flat index.
    fn new(diagonals: &FaceDiagonals, strides: [usize; 3]) -> Self {
        // The flat offset of corner `v` of the 2 × 2 × 2 box around a point
        // with odd coordinates `odd`: ±1 along each odd axis, 0 along the
        // others (where the point lies on the corner's face or edge).
        let corner = |v: usize, odd: usize| -> isize {
            (0..3)
                .filter(|a| (odd >> a) & 1 == 1)
                .map(|a| {
                    let stride = strides[a] as isize;
                    if (v >> a) & 1 == 1 { stride } else { -stride }
                })
                .sum()
        };
        let averaged = std::array::from_fn(|odd: usize| {
            std::array::from_fn(|parity| match odd.count_ones() {
                0 => Averaged::Corner,
                1 => Averaged::Two([corner(0, odd), corner(7, odd)]),
                2 => {
                    // The face with the even axis as its normal; a face
                    // centre lies on the low face of the node above it
                    // along that axis (the node below, of the other parity,
                    // has the same diagonal on it).
                    let normal = (0..3).find(|a| (odd >> a) & 1 == 0).unwrap_or(0);
                    let (_, ends) = diagonals.faces[parity][2 * normal];
                    Averaged::Two(ends.map(|v| corner(v, odd)))
                }
                _ => Averaged::Four(diagonals.central[parity].map(|v| corner(v, odd))),
            })
        });
        Self { averaged }
    }

    /// The deviations of `field` at the points of row `(y, z)` (`out.len()`
    /// points from flat index `row`) into `out`, or their maximum with what
    /// `out` holds (`combine`); `scratch` holds four rows.
    ///
    /// A point's node parity is that of the level-1 node whose low corner is
    /// the point with its coordinates rounded down to even ones, so along a
    /// row the kind of a point repeats every four points: one pass over the
    /// row per residue of `x` modulo 4, each the same operations on every
    /// point (vector instructions), of which that residue's are kept.
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
        let (row_odd, row_parity) = ((y & 1) << 1 | (z & 1) << 2, (y / 2 + z / 2) & 1);
        let mut passes = scratch.chunks_exact_mut(nx);
        let passes: [&mut [u16]; 4] = std::array::from_fn(|residue| {
            let deviations = passes.next().expect("four rows of scratch");
            let kind = self.averaged[row_odd | (residue & 1)][row_parity ^ (residue >> 1)];
            // Points with odd x are inside the row: their corners at x ± 1
            // are in it too.
            let (first, last) = if residue & 1 == 1 {
                (1, nx - 1)
            } else {
                (0, nx)
            };
            let start = row + first;
            let len = last - first;
            let points = &field[start..start + len];
            let shifted = |offset: isize| &field[start.wrapping_add_signed(offset)..][..len];
            let kept = &mut deviations[first..last];
            match kind {
                Averaged::Corner => kept.fill(0),
                Averaged::Two([a, b]) => {
                    let pairs = shifted(a).iter().zip(shifted(b));
                    for ((d, &v), (&a, &b)) in kept.iter_mut().zip(points).zip(pairs) {
                        let twice = 2 * i16::from(v) - i16::from(a) - i16::from(b);
                        *d = 2 * twice.unsigned_abs();
                    }
                }
                Averaged::Four([a, b, c, e]) => {
                    let corners = shifted(a)
                        .iter()
                        .zip(shifted(b))
                        .zip(shifted(c).iter().zip(shifted(e)));
                    for ((d, &v), ((&a, &b), (&c, &e))) in kept.iter_mut().zip(points).zip(corners)
                    {
                        let sum = i16::from(a) + i16::from(b) + i16::from(c) + i16::from(e);
                        *d = (4 * i16::from(v) - sum).unsigned_abs();
                    }
                }
            }
            deviations
        });
        // Point x takes pass x mod 4.
        let keep = |out: &mut u16, deviation: u16| {
            *out = if combine {
                (*out).max(deviation)
            } else {
                deviation
            };
        };
        let whole = nx / 4 * 4;
        let [p0, p1, p2, p3] = passes.map(|pass| pass.split_at(whole));
        let quads = p0.0.chunks_exact(4).zip(p1.0.chunks_exact(4));
        let quads = quads.zip(p2.0.chunks_exact(4).zip(p3.0.chunks_exact(4)));
        for (out, ((a, b), (c, d))) in out.chunks_exact_mut(4).zip(quads) {
            keep(&mut out[0], a[0]);
            keep(&mut out[1], b[1]);
            keep(&mut out[2], c[2]);
            keep(&mut out[3], d[3]);
        }
        let rest = [p0.1, p1.1, p2.1, p3.1];
        for (x, out) in out[whole..].iter_mut().enumerate() {
            keep(out, rest[x][x]);
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

/// Per parity (0 even, 1 odd), the coarse interpolation's corners on the faces
/// and of the central tetrahedron, read off the full-resolution
/// decomposition tables.
struct FaceDiagonals {
    /// Per face (axis `a`, side `b`): the face centre in local half-steps and
    /// the two corners of the face diagonal (the central tetrahedron's edge on
    /// that face).
    faces: [[([usize; 3], [usize; 2]); 6]; 2],
    /// The central tetrahedron's corners.
    central: [[usize; 4]; 2],
}

/// The face diagonals of both parities.
fn face_diagonals() -> FaceDiagonals {
    let central = [DECOMPOSITIONS[0].central, DECOMPOSITIONS[1].central];
    let faces = central.map(|central| {
        std::array::from_fn(|face| {
            let (axis, side) = (face / 2, face % 2);
            let mut on_face = central.iter().copied().filter(|v| (v >> axis) & 1 == side);
            let diagonal = [on_face.next(), on_face.next()]
                .map(|v| v.expect("the central tetrahedron has one edge on every cube face"));
            let mut mid = [1; 3];
            mid[axis] = 2 * side;
            (mid, diagonal)
        })
    });
    FaceDiagonals { faces, central }
}

/// The twelve cube edges: midpoint in local half-steps and the two corners.
fn edge_table() -> [([usize; 3], [usize; 2]); 12] {
    let mut edges = [([0; 3], [0; 2]); 12];
    let mut n = 0;
    for axis in 0..3 {
        for v in (0..8).filter(|v| (v >> axis) & 1 == 0) {
            let mid = std::array::from_fn(|a| if a == axis { 1 } else { 2 * ((v >> a) & 1) });
            edges[n] = (mid, [v, v | 1 << axis]);
            n += 1;
        }
    }
    edges
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
