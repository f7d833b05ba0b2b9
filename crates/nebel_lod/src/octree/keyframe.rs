//! Two keyframes of an animated field in one hierarchy, for a batch that
//! blends between them on the GPU (`CellBatch`'s keyframe blending).
//!
//! A cloud in the wind or under a moving sun changes everywhere, every
//! frame; rebuilding its grid, light field and hierarchy takes seconds for
//! the 513 × 65 × 513 layer. Instead the field is drawn as
//! `f_β = (1 − β) f_a + β f_b` between two keyframes `a` and `b` computed
//! ahead, with `β` moving from 0 to 1 over the time between them. The batch
//! of such a pair carries both keyframes' morphed values at every vertex, and
//! only `β` changes from frame to frame.
//!
//! [`VolumeHierarchy::with_next_keyframe`] makes the pair's hierarchy: the
//! first keyframe's quantised density and light, the second's beside them,
//! and per node
//!
//! - Δ = `max(Δ_a, Δ_b)`: the deviation of a blend at any grid point is
//!   `|(1 − β)(v_a − c_a) + β (v_b − c_b)| ≤ max(|v_a − c_a|, |v_b − c_b|)`
//!   (the coarse value `c` is linear in the corners), so the refinement of
//!   Röttger and Ertl 2003 Eq. 1 is conservative for every `β`; the maximum of
//!   two values that satisfy Eq. 5 (`Δ ≥ K_max Δ_child`) satisfies it too;
//! - the scalar range is the union of both: every blend lies between them,
//!   so the zero-opacity test never culls a node either keyframe draws.
//!
//! The morph of Röttger and Ertl 2003 §3 is linear in the grid values with
//! weights that depend only on the refinement, so the emitted next values are
//! exactly the morph of the second keyframe over the same cells, and the GPU's
//! per-vertex blend draws exactly the morph of the blended field.
//!
//! Keyframes `T` apart sit at the times `k·T` for integer `k`
//! ([`keyframe_index`], [`keyframe_time`]), so every user of a keyframe
//! sequence (the renderer, a reference image) agrees on them.

use nebel_core::budget::{Dims, check_allocation};

use super::{HierarchyError, Node, VolumeHierarchy};

impl VolumeHierarchy {
    /// The hierarchy that blends from this keyframe to `next` (see the
    /// module docs): this one's densities, light and morph slots, `next`'s
    /// densities and light beside them, Δ the larger of the two per node and
    /// the scalar range the union. Of a hierarchy that already blends, the
    /// first keyframe stays and `next`'s first becomes the second; its Δ and
    /// ranges then cover the old second too (still conservative).
    ///
    /// Errors: [`HierarchyError::KeyframeMismatch`] when the two differ in
    /// points, spacing, origin, minimum accuracy or in having a light field,
    /// [`HierarchyError::OverBudget`] when the second keyframe's bytes (one
    /// per point, two with light) exceed the memory budget.
    pub fn with_next_keyframe(&self, next: &VolumeHierarchy) -> Result<Self, HierarchyError> {
        let mismatch = |what| Err(HierarchyError::KeyframeMismatch { what });
        if self.dims != next.dims {
            return mismatch("the points per axis");
        }
        if self.spacing != next.spacing || self.origin != next.origin {
            return mismatch("the spacing or origin");
        }
        if self.min_accuracy.to_bits() != next.min_accuracy.to_bits() {
            return mismatch("the minimum accuracies");
        }
        if self.has_light() != next.has_light() {
            return mismatch("the light fields");
        }
        let bytes_per_point = if self.has_light() { 2 } else { 1 };
        check_allocation(
            || {
                format!(
                    "second keyframe of a volume octree of {} points",
                    Dims(&self.dims)
                )
            },
            &self.dims,
            bytes_per_point,
        )?;
        let mut pair = Self {
            next_density: next.density.clone(),
            next_light: next.light.clone(),
            ..self.clone()
        };
        for level in 1..=self.root_level {
            let size = 1usize << level;
            let counts = self.dims.map(|n| (n - 1) / size);
            for z in 0..counts[2] {
                for y in 0..counts[1] {
                    for x in 0..counts[0] {
                        let node = Node {
                            level,
                            origin: [x * size, y * size, z * size],
                        };
                        let centre = self.centre_index(node).expect("level ≥ 1");
                        pair.words[centre] = self.words[centre].max(next.words[centre]);
                        let range = self.range_index(node);
                        let ([low, high], [next_low, next_high]) =
                            (self.packed_range(range), next.packed_range(range));
                        pair.words[range] =
                            u16::from(low.min(next_low)) | (u16::from(high.max(next_high)) << 8);
                    }
                }
            }
        }
        Ok(pair)
    }

    /// Whether the hierarchy blends two keyframes
    /// ([`VolumeHierarchy::with_next_keyframe`]).
    pub fn has_next_keyframe(&self) -> bool {
        !self.next_density.is_empty()
    }

    /// The next keyframe's quantised density at grid point `p` in [0, 1];
    /// `None` unless the hierarchy blends two keyframes. Panics outside the
    /// grid.
    pub fn next_density(&self, p: [usize; 3]) -> Option<f32> {
        let index = self.index(p);
        self.next_density.get(index).map(|&q| f32::from(q) / 255.0)
    }

    /// The next keyframe's quantised light at grid point `p` in [0, 1];
    /// `None` unless the hierarchy blends two lit keyframes. Panics outside
    /// the grid.
    pub fn next_light(&self, p: [usize; 3]) -> Option<f32> {
        let index = self.index(p);
        self.next_light.get(index).map(|&q| f32::from(q) / 255.0)
    }

    /// The `[min, max]` bytes of the range word at flat index `index`.
    fn packed_range(&self, index: usize) -> [u8; 2] {
        let word = self.words[index];
        [(word & 0xff) as u8, (word >> 8) as u8]
    }
}

/// The index of the keyframe at or before `time` for keyframes `interval`
/// apart (saturating for times beyond ±2⁶³ intervals; NaN gives 0).
pub fn keyframe_index(time: f64, interval: f64) -> i64 {
    (time / interval).floor() as i64
}

/// The time of keyframe `index` for keyframes `interval` apart.
pub fn keyframe_time(index: i64, interval: f64) -> f64 {
    index as f64 * interval
}
