//! The view-independent half: [`TerrainHierarchy`] (quantised, propagated d2
//! per node and a height bound per level) and the padding helper.

use glam::{DVec2, DVec3};
use nebel_core::budget::{BudgetError, Dims, check_bytes};
use nebel_core::field::HeightField;

use super::{
    MIN_RESOLUTION_LOWER_BOUND, NEIGHBOUR_FACTOR_DISTANCE, PARENT_FACTOR_DISTANCE, TerrainError,
    TerrainMap, propagation_factor,
};

/// log2 of the smallest non-zero d2 code (code 1).
const D2_LOG2_MIN: f32 = -16.0;
/// log2 step between consecutive d2 codes (7.2 % per code).
const D2_LOG2_STEP: f32 = 0.1;
/// The largest level count accepted (`n ≤ 2^24 + 1`, far beyond memory).
const MAX_LEVELS: u32 = 24;

/// The view-independent terrain quadtree of a height field (see the
/// [module docs](super) for the formulas): the heights, one quantised d2 byte
/// per node and one height bound per level, built once by
/// [`TerrainHierarchy::new`]; [`TerrainHierarchy::update`] reads it every
/// frame.
#[derive(Clone, Debug)]
pub struct TerrainHierarchy {
    /// The heights (kept, 4 bytes per point).
    pub(super) field: HeightField,
    /// Points per side, `2^levels + 1`.
    pub(super) size: usize,
    /// Levels `k`: level 0 is the root, level `k − 1` has nodes of 2 cells.
    pub(super) levels: u32,
    /// The minimum resolution `C` d2 was propagated with.
    pub(super) min_resolution: f32,
    /// Quantised d2 per node, level by level from the root, x fastest in a
    /// level: node `(a, b)` of level `L` at `level_offset(L) + a + b·2^L`.
    pub(super) d2: Vec<u8>,
    /// d2 of each code (code 0 = 0, code q ≥ 1 = 2^(−16 + 0.1 (q − 1))).
    pub(super) d2_table: [f32; 256],
    /// Per level, the largest `|h − h_centre|` over the points of any node.
    pub(super) height_bound: Vec<f32>,
    /// Smallest and largest height of the field.
    pub(super) height_range: [f32; 2],
}

/// First index of level `level`'s nodes in the d2 array: `(4^L − 1) / 3`.
pub(super) fn level_offset(level: u32) -> usize {
    ((1usize << (2 * level)) - 1) / 3
}

impl TerrainHierarchy {
    /// Builds the hierarchy of `field` (square, `2^k + 1` points per side,
    /// `k ≥ 1`) for the minimum resolution `min_resolution` (`C`, finite and
    /// at least [`MIN_RESOLUTION_LOWER_BOUND`]; see
    /// [`super::DEFAULT_MIN_RESOLUTION`]). The field is kept; its spacing and
    /// origin place the mesh. Errors: [`TerrainError::InvalidParameter`] for
    /// `C`, [`TerrainError::NotPowerOfTwoPlusOne`], and
    /// [`TerrainError::OverBudget`] when building would exceed the memory
    /// budget ([`TerrainHierarchy::check_budget`]), before anything is
    /// allocated.
    pub fn new(field: HeightField, min_resolution: f32) -> Result<Self, TerrainError> {
        TerrainError::check(
            min_resolution.is_finite() && min_resolution >= MIN_RESOLUTION_LOWER_BOUND,
            "min_resolution C",
            min_resolution,
            "finite and at least 1.6 (the one-level rule needs C > √10/2)",
        )?;
        let [nx, nz] = field.dims();
        let levels = (nx.max(2) - 1).trailing_zeros();
        if nx != nz || nx < 3 || (nx - 1) != 1 << levels || levels > MAX_LEVELS {
            return Err(TerrainError::NotPowerOfTwoPlusOne {
                dims: field.dims(),
                padded: padded_side(nx.max(nz)),
            });
        }
        Self::check_budget(nx)?;
        let nodes = level_offset(levels);
        let mut hierarchy = Self {
            size: nx,
            levels,
            min_resolution,
            d2: vec![0; nodes],
            d2_table: d2_table(),
            height_bound: vec![0.0; levels as usize],
            height_range: [0.0; 2],
            field,
        };
        hierarchy.compute_height_bounds();
        // A flat field has no roughness: every d2 stays 0 (the bottom of a
        // layer between two surfaces often is one).
        if hierarchy.height_range[0] != hierarchy.height_range[1] {
            let shape = hierarchy.shape();
            propagate(&mut hierarchy.d2, &shape, hierarchy.field.heights(), 1.0);
        }
        Ok(hierarchy)
    }

    /// The bytes [`TerrainHierarchy::new`] allocates for a field of `side ×
    /// side` points (`2^k + 1`; another side counts as the next such one)
    /// besides the heights it keeps: one d2 code per node and, while the
    /// height bounds are merged, the height ranges of the two finest levels
    /// (8 bytes per node; see `docs/quadtree-lod.md`), checked against the memory
    /// budget without building anything. Errors name a `terrain quadtree of
    /// side × side points`.
    pub fn check_budget(side: usize) -> Result<u64, BudgetError> {
        // k with 2^(k−1) + 1 < side ≤ 2^k + 1.
        let levels = usize::BITS - (side.max(3) - 2).leading_zeros();
        let nodes = |level: u32| 1u128.checked_shl(2 * level).unwrap_or(u128::MAX);
        let codes = (nodes(levels) - 1) / 3;
        let finest_two =
            nodes(levels - 1).saturating_add(if levels >= 2 { nodes(levels - 2) } else { 0 });
        let ranges = finest_two.saturating_mul(size_of::<[f32; 2]>() as u128);
        check_bytes(
            || format!("terrain quadtree of {} points", Dims(&[side, side])),
            codes.saturating_add(ranges),
        )
    }

    /// [`TerrainHierarchy::new`] from raw heights: `size × size` heights, x
    /// fastest (`i + size·j`), spacing and origin as in [`HeightField::new`].
    /// A NaN or infinite height is a [`TerrainError::NonFiniteHeight`] naming
    /// its grid point.
    pub fn from_heights(
        size: usize,
        spacing: DVec2,
        origin: DVec2,
        heights: Vec<f32>,
        min_resolution: f32,
    ) -> Result<Self, TerrainError> {
        if let Some(index) = heights.iter().position(|h| !h.is_finite()) {
            let n = size.max(1);
            return Err(TerrainError::NonFiniteHeight {
                i: index % n,
                j: index / n,
                index,
                value: heights[index],
            });
        }
        let field = HeightField::new([size, size], spacing, origin, heights)?;
        Self::new(field, min_resolution)
    }

    /// Adds a roughness source: `weight` (finite, ≥ 0) times the local d2 of
    /// `field`'s values (same points as the terrain; spacing and origin are
    /// ignored, the terrain's node sizes apply) enters every node's d2 as a
    /// maximum, then propagates like the terrain's own (see the module docs).
    /// A fog thickness map, say, so the mesh also refines where the fog's
    /// top varies.
    pub fn with_extra_roughness(
        mut self,
        field: &HeightField,
        weight: f32,
    ) -> Result<Self, TerrainError> {
        self.add_extra_roughness(field, weight)?;
        Ok(self)
    }

    /// [`TerrainHierarchy::with_extra_roughness`] in place.
    pub fn add_extra_roughness(
        &mut self,
        field: &HeightField,
        weight: f32,
    ) -> Result<(), TerrainError> {
        self.add_roughness_source(field.dims(), field.heights(), weight)
    }

    /// [`TerrainHierarchy::with_extra_roughness`] of a [`TerrainMap`]'s
    /// values (the fog thickness the mesh also carries).
    pub fn with_map_roughness(
        mut self,
        map: &TerrainMap,
        weight: f32,
    ) -> Result<Self, TerrainError> {
        self.add_map_roughness(map, weight)?;
        Ok(self)
    }

    /// [`TerrainHierarchy::with_map_roughness`] in place.
    pub fn add_map_roughness(&mut self, map: &TerrainMap, weight: f32) -> Result<(), TerrainError> {
        self.add_roughness_source([map.side(); 2], map.values(), weight)
    }

    /// Adds `weight` times the local d2 of `values` (`dims` points) and
    /// propagates it.
    fn add_roughness_source(
        &mut self,
        dims: [usize; 2],
        values: &[f32],
        weight: f32,
    ) -> Result<(), TerrainError> {
        let weight_ok = weight.is_finite() && weight >= 0.0;
        let requirement = "finite and not negative";
        TerrainError::check(weight_ok, "extra roughness weight", weight, requirement)?;
        if dims != self.field.dims() {
            return Err(TerrainError::DimsMismatch {
                terrain: self.field.dims(),
                extra: dims,
            });
        }
        let shape = self.shape();
        propagate(&mut self.d2, &shape, values, weight);
        Ok(())
    }

    /// The height field.
    pub fn field(&self) -> &HeightField {
        &self.field
    }

    /// Points per side, `2^levels() + 1`.
    pub fn size(&self) -> usize {
        self.size
    }

    /// Levels `k` (root = level 0, nodes of two cells = level `k − 1`).
    pub fn levels(&self) -> u32 {
        self.levels
    }

    /// The minimum resolution `C` d2 was propagated with and the criterion
    /// uses.
    pub fn min_resolution(&self) -> f32 {
        self.min_resolution
    }

    /// World position of the mesh's local origin: (field origin x, 0, field
    /// origin z). Place the mesh of [`TerrainHierarchy::update`] with a
    /// translation by this.
    pub fn origin(&self) -> DVec3 {
        let o = self.field.origin();
        DVec3::new(o.x, 0.0, o.y)
    }

    /// Node size in world units at `level`: `2^(k − level)` cells times the
    /// larger spacing.
    pub fn node_size(&self, level: u32) -> f32 {
        let cells = ((self.size - 1) >> level) as f64;
        (cells * self.field.spacing().max_element()) as f32
    }

    /// The stored (quantised, propagated) d2 of node `(a, b)` of `level`, a
    /// dimensionless slope ratio; `None` when there is no such node. Never
    /// below the node's own local d2 (up to the largest code, about 676) and
    /// never below `K` times a child's or a neighbour's child's.
    pub fn roughness(&self, level: u32, a: usize, b: usize) -> Option<f32> {
        let side = 1usize << level.min(31);
        (level < self.levels && a < side && b < side)
            .then(|| self.d2_table[usize::from(self.d2[level_offset(level) + a + b * side])])
    }

    /// The level's height bound: the largest `|h − h_centre|` over the points
    /// of any node of `level` (0 for a level that does not exist).
    pub fn height_bound(&self, level: u32) -> f32 {
        self.height_bound
            .get(level as usize)
            .copied()
            .unwrap_or(0.0)
    }

    /// Smallest and largest height.
    pub fn height_range(&self) -> [f32; 2] {
        self.height_range
    }

    /// Bytes held: heights, d2 codes, the per-level bounds and the code table.
    pub fn memory_bytes(&self) -> usize {
        size_of_val(self.field.heights())
            + self.d2.len()
            + size_of_val(self.height_bound.as_slice())
            + size_of_val(&self.d2_table)
            + size_of::<Self>()
    }

    /// [`TerrainHierarchy::memory_bytes`] per grid point (about 4.33: 4 for
    /// the f32 heights, 1/3 for the d2 codes).
    pub fn bytes_per_point(&self) -> f64 {
        self.memory_bytes() as f64 / (self.size * self.size) as f64
    }

    /// Per level, the largest `|h − h_centre|` over a node's points, from
    /// per-node ranges merged bottom-up; also the global range.
    fn compute_height_bounds(&mut self) {
        let n = self.size;
        let h = self.field.heights();
        let mut ranges: Vec<[f32; 2]> = Vec::new();
        for level in (0..self.levels).rev() {
            let side = 1usize << level;
            let s = (n - 1) >> level;
            let half = s / 2;
            let mut next = Vec::with_capacity(side * side);
            let mut bound = 0.0f32;
            for b in 0..side {
                for a in 0..side {
                    let range = if level + 1 == self.levels {
                        let mut r = [f32::INFINITY, f32::NEG_INFINITY];
                        for j in b * s..=(b + 1) * s {
                            for i in a * s..=(a + 1) * s {
                                let v = h[i + n * j];
                                r = [r[0].min(v), r[1].max(v)];
                            }
                        }
                        r
                    } else {
                        let child_side = side * 2;
                        let mut r = [f32::INFINITY, f32::NEG_INFINITY];
                        for (ca, cb) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                            let c = ranges[2 * a + ca + (2 * b + cb) * child_side];
                            r = [r[0].min(c[0]), r[1].max(c[1])];
                        }
                        r
                    };
                    let centre = h[a * s + half + n * (b * s + half)];
                    bound = bound.max(range[1] - centre).max(centre - range[0]);
                    next.push(range);
                }
            }
            self.height_bound[level as usize] = bound;
            ranges = next;
        }
        self.height_range = ranges[0];
    }

    /// What a propagation pass needs besides the codes.
    fn shape(&self) -> Shape {
        Shape {
            size: self.size,
            levels: self.levels,
            min_resolution: self.min_resolution,
            spacing: self.field.spacing().max_element(),
            table: self.d2_table,
        }
    }
}

/// The geometry and code table of a propagation pass.
struct Shape {
    size: usize,
    levels: u32,
    min_resolution: f32,
    spacing: f64,
    table: [f32; 256],
}

/// One bottom-up pass over the codes `d2`: every node's d2 becomes the maximum
/// of its stored d2, `weight ·` the local d2 of `source`, and the propagated
/// d2 of its children and its neighbours' adjacent children (all rounded up to
/// a code). With all codes 0 this is the initial build.
fn propagate(d2: &mut [u8], shape: &Shape, source: &[f32], weight: f32) {
    let n = shape.size;
    let table = &shape.table;
    let k_parent = propagation_factor(shape.min_resolution, PARENT_FACTOR_DISTANCE);
    let k_neighbour = propagation_factor(shape.min_resolution, NEIGHBOUR_FACTOR_DISTANCE);
    for level in (0..shape.levels).rev() {
        let side = 1usize << level;
        let s = (n - 1) >> level;
        let half = s / 2;
        let inv_size = (1.0 / (s as f64 * shape.spacing)) as f32;
        let offset = level_offset(level);
        let child_side = side * 2;
        let child_offset = level_offset(level + 1);
        for b in 0..side {
            for a in 0..side {
                let index = offset + a + b * side;
                let mut value = table[usize::from(d2[index])];
                if weight > 0.0 {
                    let second = local_second_difference(source, n, a, b, s, half);
                    value = value.max(weight * second * inv_size);
                }
                if level + 1 < shape.levels {
                    let code = |ca: usize, cb: usize| {
                        table[usize::from(d2[child_offset + ca + cb * child_side])]
                    };
                    let (ca, cb) = (2 * a, 2 * b);
                    let children = code(ca, cb)
                        .max(code(ca + 1, cb))
                        .max(code(ca, cb + 1))
                        .max(code(ca + 1, cb + 1));
                    let mut neighbours = 0.0f32;
                    if a > 0 {
                        neighbours = neighbours.max(code(ca - 1, cb)).max(code(ca - 1, cb + 1));
                    }
                    if a + 1 < side {
                        neighbours = neighbours.max(code(ca + 2, cb)).max(code(ca + 2, cb + 1));
                    }
                    if b > 0 {
                        neighbours = neighbours.max(code(ca, cb - 1)).max(code(ca + 1, cb - 1));
                    }
                    if b + 1 < side {
                        neighbours = neighbours.max(code(ca, cb + 2)).max(code(ca + 1, cb + 2));
                    }
                    value = value.max(k_parent * children).max(k_neighbour * neighbours);
                }
                d2[index] = quantise_up(value, table);
            }
        }
    }
}

/// The largest `|a + b − 2m|` of node `(a, b)` (size `s`, half `half`) over its
/// four edges and its parity diagonal (see `docs/quadtree-lod.md`).
fn local_second_difference(h: &[f32], n: usize, a: usize, b: usize, s: usize, half: usize) -> f32 {
    let (i0, j0) = (a * s, b * s);
    let (i1, j1) = (i0 + s, j0 + s);
    let (im, jm) = (i0 + half, j0 + half);
    let at = |i: usize, j: usize| h[i + n * j];
    let second = |p: f32, q: f32, m: f32| (p + q - 2.0 * m).abs();
    let (sw, se, ne, nw) = (at(i0, j0), at(i1, j0), at(i1, j1), at(i0, j1));
    let diagonal = if (a + b).is_multiple_of(2) {
        second(sw, ne, at(im, jm))
    } else {
        second(nw, se, at(im, jm))
    };
    diagonal
        .max(second(sw, se, at(im, j0)))
        .max(second(nw, ne, at(im, j1)))
        .max(second(sw, nw, at(i0, jm)))
        .max(second(se, ne, at(i1, jm)))
}

/// The d2 of every code: 0, then `2^(−16 + 0.1 (q − 1))` for q = 1..=255.
fn d2_table() -> [f32; 256] {
    std::array::from_fn(|q| {
        if q == 0 {
            0.0
        } else {
            (D2_LOG2_MIN + D2_LOG2_STEP * (q - 1) as f32).exp2()
        }
    })
}

/// The smallest code whose d2 is at least `x` (code 255 for anything beyond
/// the largest; 0 for 0, negative or NaN).
fn quantise_up(x: f32, table: &[f32; 256]) -> u8 {
    if x.is_nan() || x <= 0.0 {
        return 0;
    }
    if x >= table[255] {
        return 255;
    }
    let guess = ((x.log2() - D2_LOG2_MIN) / D2_LOG2_STEP).ceil() + 1.0;
    let mut q = guess.clamp(1.0, 255.0) as usize;
    while q < 255 && table[q] < x {
        q += 1;
    }
    while q > 1 && table[q - 1] >= x {
        q -= 1;
    }
    q as u8
}

/// The side `2^k + 1 ≥ n` (at least 3).
fn padded_side(n: usize) -> usize {
    let n = n.max(3);
    (n - 1)
        .checked_next_power_of_two()
        .and_then(|p| p.checked_add(1))
        .unwrap_or(n)
}

/// Pads `field` to the smallest square of `2^k + 1` points per side (at least
/// 3) that holds it, at its high ends (`i ≥ nx` and `j ≥ nz`), replicating the
/// nearest original height (the terrain continues flat). Spacing, origin and
/// every original height are kept; a field that already fits is returned as
/// it is. The mesh then covers the padded square. Errors:
/// [`TerrainError::OverBudget`] when the padded heights exceed the memory
/// budget, before they are allocated.
pub fn pad_to_power_of_two_plus_one(field: &HeightField) -> Result<HeightField, TerrainError> {
    let [nx, nz] = field.dims();
    let side = padded_side(nx.max(nz));
    if [nx, nz] == [side, side] {
        return Ok(field.clone());
    }
    HeightField::check_budget([side, side])?;
    let mut heights = Vec::with_capacity(side * side);
    for j in 0..side {
        for i in 0..side {
            heights.push(field.height(i.min(nx - 1), j.min(nz - 1)));
        }
    }
    Ok(HeightField::new(
        [side, side],
        field.spacing(),
        field.origin(),
        heights,
    )?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_round_up_and_cover_the_range() {
        let table = d2_table();
        assert_eq!(quantise_up(0.0, &table), 0);
        assert_eq!(quantise_up(f32::NAN, &table), 0);
        assert_eq!(quantise_up(1e-9, &table), 1);
        assert_eq!(quantise_up(1e9, &table), 255);
        assert_eq!(quantise_up(f32::INFINITY, &table), 255);
        for i in 0..2000 {
            let x = (-17.0 + i as f32 * 0.0137).exp2();
            let q = quantise_up(x, &table);
            if x < table[255] {
                assert!(table[usize::from(q)] >= x, "{x} -> {q}");
                assert!(q <= 1 || table[usize::from(q) - 1] < x, "{x} -> {q}");
            }
        }
        assert!((table[255] - 2f32.powf(9.4)).abs() < 0.01);
    }

    #[test]
    fn level_offsets() {
        assert_eq!(level_offset(0), 0);
        assert_eq!(level_offset(1), 1);
        assert_eq!(level_offset(2), 5);
        assert_eq!(level_offset(3), 21);
        assert_eq!(padded_side(2), 3);
        assert_eq!(padded_side(100), 129);
        assert_eq!(padded_side(129), 129);
    }
}
