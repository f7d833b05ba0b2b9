//! Volume C-LOD: an octree over a density grid, refined and morphed per frame.
//!
//! The hierarchy is the view-independent half of Röttger and Ertl 2003 (§2.1,
//! §2.2, §2.4 and §3). [`VolumeHierarchy::new`] builds, once per grid of
//! `2^n + 1` points per axis, a forest of octrees (cubic roots of `2^m` voxels,
//! `m` the smallest exponent, tiling the grid) with per node:
//!
//! - the deviation Δ: the largest change of any of its 19 non-corner points
//!   between its own value and the node's coarse field, propagated bottom-up as
//!   `Δ := max(Δ_local, K_max · Δ_child)` with [`k_max`] (Eq. 4 and 5), so a
//!   node is refined whenever one of its children would be;
//! - its scalar range, for the zero-opacity test;
//! - a slot for its morph factor e'.
//!
//! A node drawn unrefined is Kuhn's six tetrahedra around its diagonal
//! (`nebel_core::cell::KUHN_TETRAHEDRA`, as every voxel at full resolution);
//! the paper's five alternating tetrahedra (§2.1) are not nested, Kuhn's are,
//! so a node refined at `e' = 0` draws exactly its unrefined field.
//!
//! Storage follows Röttger and Ertl 2003 §5: four bytes per grid point (density
//! u8, Δ or scalar range u16, e' u8), five with a lit cloud's light γ
//! ([`VolumeHierarchy::with_light`], §5.1), checked against the memory budget
//! first ([`VolumeHierarchy::check_budget`]). Δ and the ranges are computed
//! from the quantised values the LOD mesh draws
//! ([`VolumeHierarchy::quantised_grid`]). The arrays are shared (`Arc`), not
//! copied, by clones and by a pair of keyframes
//! ([`VolumeHierarchy::with_next_keyframe`]).
//!
//! - [`Node`]: a node by level and minimum grid point, its corners, centre and
//!   children.
//! - [`refine()`] (in [`mod@refine`]): the per-frame refinement, by the screen
//!   error ([`mod@screen_error`]) or the paper's distance criterion.
//! - [`lod_batch`] (in [`mod@emit`]): a refinement as a morphed, back-to-front
//!   [`crate::Cells`].
//! - [`mod@keyframe`]: two keyframes of an animated field in one hierarchy.
//! - [`mod@refresh`]: when a moving camera's batch is refined again.
//!
//! The forest rule, the deviation at each kind of point, the quantisation and
//! where nebel departs from the paper are in `docs/octree-lod.md` in the
//! repository.

mod build;
pub mod emit;
pub mod keyframe;
mod node;
pub mod refine;
pub mod refresh;
pub mod screen_error;

pub use emit::{CellScalars, lod_batch, lod_batch_with};
pub use node::Node;
pub use refine::{
    LodCriterion, NodeMorph, Refinement, RefinementError, RefinementSettings, RefinementStats,
    refine,
};

use std::sync::Arc;

use glam::DVec3;
use nebel_core::budget::{BudgetError, Dims, check_allocation};
use nebel_core::field::DensityGrid;
use thiserror::Error;

/// Why a [`VolumeHierarchy`] could not be built.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum HierarchyError {
    /// Some axis does not have `2^n + 1` points.
    #[error(
        "a volume hierarchy needs 2^n+1 points per axis (3, 5, 9, 17, 33, 65, ...), but the grid has {dims:?} points; pad or resample it first (DensityGrid::padded_to_power_of_two_plus_one)"
    )]
    NotPowerOfTwoPlusOne {
        /// Points per axis of the grid given.
        dims: [usize; 3],
    },
    /// A light field does not have the density grid's points per axis.
    #[error(
        "the light field has {light:?} points but the density grid {density:?}; sample both at the same points"
    )]
    LightDimsMismatch {
        /// Points per axis of the density grid.
        density: [usize; 3],
        /// Points per axis of the light field.
        light: [usize; 3],
    },
    /// The minimum accuracy `C` is not a finite number greater than √3.
    #[error(
        "the minimum accuracy C must be finite and greater than √3 ≈ 1.732 (Röttger and Ertl 2003 Eq. 4), got {value}"
    )]
    InvalidMinAccuracy {
        /// The value given.
        value: f64,
    },
    /// Two keyframes to blend differ in their grid, their minimum accuracy
    /// or whether they carry a light field.
    #[error(
        "keyframes to blend must share the grid (points, spacing, origin), the minimum accuracy and the light field's presence: {what} differ"
    )]
    KeyframeMismatch {
        /// What differs.
        what: &'static str,
    },
    /// The hierarchy would exceed the memory budget; nothing was allocated.
    #[error(transparent)]
    OverBudget(#[from] BudgetError),
}

/// The `[min, max]` bytes of a packed scalar range word.
fn unpack_range(word: u16) -> [u8; 2] {
    [(word & 0xff) as u8, (word >> 8) as u8]
}

/// Bytes a [`VolumeHierarchy`] keeps per grid point without a light field:
/// the quantised density (u8), the Δ or range word (u16) and e' (u8).
const BYTES_PER_POINT: u64 = (2 * size_of::<u8>() + size_of::<u16>()) as u64;

/// Bytes per grid point the light field adds (u8).
const LIGHT_BYTES_PER_POINT: u64 = size_of::<u8>() as u64;

/// The propagation factor `K_max = C / (2C − √3/2)` of Röttger and Ertl 2003 Eq. 4 for the
/// minimum accuracy `C` (`min_accuracy`): the largest ratio `d / (2 d_child)`
/// of eye distances between a node and a child when the node is at the
/// smallest distance `d = sC` at which Eq. 1 does not force refinement anyway.
/// It lies in `(1/2, 2/3)`. Errors unless `C` is finite and `C > √3`.
pub fn k_max(min_accuracy: f64) -> Result<f64, HierarchyError> {
    let sqrt_3 = 3f64.sqrt();
    if !(min_accuracy.is_finite() && min_accuracy > sqrt_3) {
        return Err(HierarchyError::InvalidMinAccuracy {
            value: min_accuracy,
        });
    }
    Ok(min_accuracy / (2.0 * min_accuracy - sqrt_3 / 2.0))
}

/// The view-independent volume octree of a density grid: quantised densities,
/// the propagated deviation Δ and the scalar range of every node, and the
/// per-frame morph factor e' (see the module docs, and `docs/octree-lod.md`
/// for the layout).
#[derive(Clone, Debug, PartialEq)]
pub struct VolumeHierarchy {
    /// Points per axis.
    dims: [usize; 3],
    /// World units between neighbouring points, per axis.
    spacing: DVec3,
    /// World position of point (0, 0, 0).
    origin: DVec3,
    /// Level of the roots, `min` of the axis exponents.
    root_level: u32,
    /// Roots per axis.
    root_counts: [usize; 3],
    /// The minimum accuracy `C` Δ was propagated with.
    min_accuracy: f64,
    /// `K_max` of `min_accuracy`.
    k_max: f64,
    /// Quantised density per grid point, `round(255 · s)`.
    density: Arc<Vec<u8>>,
    /// Quantised light γ per grid point, `round(255 · γ)`; empty without a
    /// light field.
    light: Arc<Vec<u8>>,
    /// The next keyframe's quantised density per grid point; empty unless
    /// the hierarchy blends two keyframes (see [`mod@keyframe`]).
    next_density: Arc<Vec<u8>>,
    /// The next keyframe's quantised light per grid point; empty unless the
    /// hierarchy blends two lit keyframes.
    next_light: Arc<Vec<u8>>,
    /// The next keyframe's Δ and scalar ranges (laid out as `words`); empty
    /// unless the hierarchy blends two keyframes.
    next_words: Arc<Vec<u16>>,
    /// Per grid point: Δ (units of 1/65535) at node centres, the packed scalar
    /// range at the centre of a node's +x face, 0 elsewhere.
    words: Arc<Vec<u16>>,
    /// Per grid point: e' (units of 1/255) at node centres.
    morph: Arc<Vec<u8>>,
}

impl VolumeHierarchy {
    /// The bytes the hierarchy of a grid of `dims` points keeps (4 per point,
    /// 5 `with_light`; see the module docs), checked against the memory
    /// budget: the check [`VolumeHierarchy::new`] and
    /// [`VolumeHierarchy::with_light`] make before they allocate, here
    /// without building one (e.g. for a padded size, to validate a
    /// description). Errors name a `volume octree of nx × ny × nz points`.
    pub fn check_budget(dims: [usize; 3], with_light: bool) -> Result<u64, BudgetError> {
        let (bytes_per_point, light) = if with_light {
            (
                BYTES_PER_POINT + LIGHT_BYTES_PER_POINT,
                " with a light field",
            )
        } else {
            (BYTES_PER_POINT, "")
        };
        check_allocation(
            || format!("volume octree of {} points{light}", Dims(&dims)),
            &dims,
            bytes_per_point,
        )
    }

    /// Points per axis.
    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// World units between neighbouring points, per axis (from the grid).
    pub fn spacing(&self) -> DVec3 {
        self.spacing
    }

    /// World position of point (0, 0, 0) (from the grid).
    pub fn origin(&self) -> DVec3 {
        self.origin
    }

    /// The roots' level: roots are cubes of `2^root_level` voxels.
    pub fn root_level(&self) -> u32 {
        self.root_level
    }

    /// Roots per axis.
    pub fn root_counts(&self) -> [usize; 3] {
        self.root_counts
    }

    /// The roots, x fastest.
    pub fn roots(&self) -> impl Iterator<Item = Node> + '_ {
        let [nx, ny, nz] = self.root_counts;
        let size = 1 << self.root_level;
        (0..nz).flat_map(move |z| {
            (0..ny).flat_map(move |y| {
                (0..nx).map(move |x| Node {
                    level: self.root_level,
                    origin: [x * size, y * size, z * size],
                })
            })
        })
    }

    /// The minimum accuracy `C` the hierarchy was built with; the per-frame
    /// refinement must use the same `C` in Eq. 1 for the propagation to hold.
    pub fn min_accuracy(&self) -> f64 {
        self.min_accuracy
    }

    /// `K_max` of [`VolumeHierarchy::min_accuracy`] ([`k_max`]).
    pub fn k_max(&self) -> f64 {
        self.k_max
    }

    /// The quantised density at grid point `p`, units of 1/255. Panics outside
    /// the grid.
    pub fn density_quantised(&self, p: [usize; 3]) -> u8 {
        self.density[self.index(p)]
    }

    /// The quantised density at grid point `p`, in [0, 1]. Panics outside the
    /// grid.
    pub fn density(&self, p: [usize; 3]) -> f32 {
        f32::from(self.density_quantised(p)) / 255.0
    }

    /// Whether the hierarchy was built with a light field
    /// ([`VolumeHierarchy::with_light`]).
    pub fn has_light(&self) -> bool {
        !self.light.is_empty()
    }

    /// The quantised light γ at grid point `p`, in [0, 1]; `None` without a
    /// light field. Panics outside the grid.
    pub fn light(&self, p: [usize; 3]) -> Option<f32> {
        let index = self.index(p);
        self.light.get(index).map(|&q| f32::from(q) / 255.0)
    }

    /// The quantised light field as a grid of the original geometry; `None`
    /// without one.
    pub fn quantised_light(&self) -> Option<DensityGrid> {
        self.has_light().then(|| {
            let values = self.light.iter().map(|&q| f32::from(q) / 255.0).collect();
            DensityGrid::new(self.dims, self.spacing, self.origin, values)
                .expect("dims, spacing and origin come from a valid grid and q/255 is in [0, 1]")
        })
    }

    /// The quantised densities as a grid of the original geometry: the exact
    /// full-resolution counterpart of what the LOD mesh draws.
    pub fn quantised_grid(&self) -> DensityGrid {
        let values = self.density.iter().map(|&q| f32::from(q) / 255.0).collect();
        DensityGrid::new(self.dims, self.spacing, self.origin, values)
            .expect("dims, spacing and origin come from a valid grid and q/255 is in [0, 1]")
    }

    /// The node's propagated Δ, units of 1/65535 (0 for a voxel). Panics when
    /// the node is not in this hierarchy.
    pub fn deviation_quantised(&self, node: Node) -> u16 {
        match self.centre_index(node) {
            Some(centre) => self.words[centre],
            None => 0,
        }
    }

    /// The node's propagated Δ in density units, in [0, 1] (0 for a voxel).
    /// Never below the true maximum deviation of the node and `K_max` times
    /// that of its descendants. Panics when the node is not in this hierarchy.
    pub fn deviation(&self, node: Node) -> f32 {
        f32::from(self.deviation_quantised(node)) / 65535.0
    }

    /// `[min, max]` of the quantised density (of both keyframes when the
    /// hierarchy blends two) over every grid point of the
    /// node's closed box, units of 1/255. Panics when the node is not in this
    /// hierarchy.
    pub fn scalar_range_quantised(&self, node: Node) -> [u8; 2] {
        match self.keyframe_ranges(node) {
            ([low, high], Some([next_low, next_high])) => [low.min(next_low), high.max(next_high)],
            (range, None) => range,
        }
    }

    /// The node's `[min, max]` density in the first keyframe and, when the
    /// hierarchy blends two, in the second, units of 1/255: a voxel's from
    /// its corners, a larger node's as stored. Panics when the node is not in
    /// this hierarchy.
    fn keyframe_ranges(&self, node: Node) -> ([u8; 2], Option<[u8; 2]>) {
        if node.level == 0 {
            self.check(node);
            let corners = |density: &[u8]| {
                let values = (0..8).map(|v| density[self.index(node.corner(v))]);
                [values.clone().min().unwrap_or(0), values.max().unwrap_or(0)]
            };
            let next = self
                .has_next_keyframe()
                .then(|| corners(&self.next_density));
            return (corners(&self.density), next);
        }
        let index = self.range_index(node);
        let next = self.next_words.get(index).map(|&word| unpack_range(word));
        (unpack_range(self.words[index]), next)
    }

    /// `[min, max]` of the node's densities in [0, 1], for
    /// `TransferFunction::is_transparent` (the zero-opacity test of Röttger and Ertl 2003
    /// §4.1). Panics when the node is not in this hierarchy.
    pub fn scalar_range(&self, node: Node) -> [f32; 2] {
        self.scalar_range_quantised(node)
            .map(|q| f32::from(q) / 255.0)
    }

    /// The node's morph factor e' in [0, 1] (Röttger and Ertl 2003 Eq. 6), as last set;
    /// 0 for a voxel. Panics when the node is not in this hierarchy.
    pub fn morph_factor(&self, node: Node) -> f32 {
        match self.centre_index(node) {
            Some(centre) => f32::from(self.morph[centre]) / 255.0,
            None => 0.0,
        }
    }

    /// Stores the node's morph factor, clamped to [0, 1] (NaN as 0) and rounded
    /// to 1/255. Panics for a voxel (it has no centre to store it at; a voxel
    /// is never refined) and when the node is not in this hierarchy.
    pub fn set_morph_factor(&mut self, node: Node, e: f32) {
        let centre = self
            .centre_index(node)
            .expect("a voxel (level 0) has no morph factor");
        let e = if e.is_nan() { 0.0 } else { e.clamp(0.0, 1.0) };
        Arc::make_mut(&mut self.morph)[centre] = (e * 255.0).round() as u8;
    }

    /// Bytes the hierarchy keeps per grid point (density, Δ and range words,
    /// e', and the light when there is one): 4, the paper's 1 + 2 + 1, or 5
    /// with a light field.
    pub fn bytes_per_point(&self) -> f64 {
        let bytes = self.density.len() * size_of::<u8>()
            + self.light.len() * size_of::<u8>()
            + (self.next_density.len() + self.next_light.len()) * size_of::<u8>()
            + self.next_words.len() * size_of::<u16>()
            + self.words.len() * size_of::<u16>()
            + self.morph.len() * size_of::<u8>();
        bytes as f64 / self.density.len() as f64
    }

    /// The flat index of grid point `p`.
    fn index(&self, [i, j, k]: [usize; 3]) -> usize {
        let [nx, ny, nz] = self.dims;
        assert!(
            i < nx && j < ny && k < nz,
            "grid point {:?} outside {:?}",
            [i, j, k],
            self.dims
        );
        i + nx * (j + ny * k)
    }

    /// Panics unless `node` is a node of this hierarchy: level at most the
    /// roots', origin a multiple of its size, box inside the grid.
    fn check(&self, node: Node) {
        let size = node.size();
        assert!(
            node.level <= self.root_level
                && (0..3)
                    .all(|a| node.origin[a].is_multiple_of(size)
                        && node.origin[a] + size < self.dims[a]),
            "{node:?} is not a node of a hierarchy of {:?} points with roots of level {}",
            self.dims,
            self.root_level
        );
    }

    /// The flat index of the node's centre; `None` for a voxel.
    fn centre_index(&self, node: Node) -> Option<usize> {
        self.check(node);
        node.centre().map(|c| self.index(c))
    }

    /// The flat index of the centre of the node's +x face, where its scalar
    /// range is stored. Level ≥ 1.
    fn range_index(&self, node: Node) -> usize {
        self.check(node);
        let (size, half) = (node.size(), node.size() / 2);
        let [x, y, z] = node.origin;
        self.index([x + size, y + half, z + half])
    }
}

#[cfg(test)]
mod tests;
