//! Building a [`VolumeHierarchy`]: quantisation, then Δ and scalar ranges level
//! by level from the voxels up (Röttger and Ertl 2003 §2.2, §2.4; the rules are in the
//! module docs of [`super`]).

use std::sync::Arc;

use nebel_core::field::DensityGrid;

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
        for level in 1..=root_level {
            hierarchy.build_level(level, &diagonals);
        }
        Ok(hierarchy)
    }

    /// Computes Δ (propagated from level − 1, already built) and the scalar
    /// range of every node of `level ≥ 1`.
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
        // The 27 points of a level-1 node.
        let points: [usize; 27] = std::array::from_fn(|n| offset(n % 3, (n / 3) % 3, n / 9));
        // Children: their centres and the centres of their +x faces, relative
        // to the node's origin, for level ≥ 2 (quarter = half / 2).
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
                    // 65535 / 1020 = 257 / 4, rounded up.
                    let mut delta = ((deviation as u32 * 257).div_ceil(4)) as u16;

                    let range = if level == 1 {
                        let mut range = [u8::MAX, u8::MIN];
                        for &point in &points {
                            let value = density[base + point];
                            range = [range[0].min(value), range[1].max(value)];
                        }
                        range
                    } else {
                        let mut range = [u8::MAX, u8::MIN];
                        for v in 0..8 {
                            let child = words[base + child_centres[v]];
                            // Eq. 5 on the stored values, rounded up.
                            let propagated = (k_max * f64::from(child)).ceil() as u16;
                            delta = delta.max(propagated);
                            let [min, max] = words[base + child_ranges[v]].to_le_bytes();
                            range = [range[0].min(min), range[1].max(max)];
                        }
                        range
                    };
                    words[base + centre] = delta;
                    words[base + range_slot] = u16::from_le_bytes(range);
                }
            }
        }
    }
}

/// The field quantised to u8, `round(255 · s)`.
fn quantise(grid: &DensityGrid) -> Vec<u8> {
    grid.values().iter().map(|&s| quantised(s)).collect()
}

/// `(255 · s).round() as u8` for `s` in [0, 1], without a call to `round`
/// (the x86-64 baseline has no rounding instruction): `x = 255 · s` (f32, as
/// there) plus ½ is exact in f64 for every `x ≥ 2⁻²⁹` (and below 1 for the
/// smaller ones, which round to 0), and truncation is the floor of a
/// non-negative value, so this is `⌊x + ½⌋`, the half-up rounding of a
/// non-negative `x` (checked once over every f32 in [0, 1]; the test below
/// checks the values next to every boundary).
fn quantised(s: f32) -> u8 {
    (f64::from(s * 255.0) + 0.5) as u8
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
