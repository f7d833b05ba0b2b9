//! Two keyframes of an animated field in one hierarchy, blended on the GPU.
//!
//! A cloud in the wind or under a moving sun changes everywhere, every frame.
//! Instead of rebuilding it, the field is drawn as `f_β = (1 − β) f_a + β f_b`
//! between two keyframes `a` and `b` computed ahead, `β` moving from 0 to 1
//! over the time between them. [`VolumeHierarchy::with_next_keyframe`] makes
//! the pair's hierarchy, which shares both keyframes' arrays.
//!
//! The refinement ([`super::refine()`]) for a blend `β`
//! ([`super::RefinementSettings::blend`]) uses per node
//! `Δ_β = (1 − β) Δ_a + β Δ_b` ([`VolumeHierarchy::deviation_at`]), which
//! bounds the blend's deviation and satisfies Eq. 5 (Röttger and Ertl 2003),
//! and the blended scalar range rounded outward
//! ([`VolumeHierarchy::scalar_range_at`]), so the zero-opacity test culls
//! nothing the blend draws. Both are continuous in `β` and at `β = 1` equal the
//! second keyframe's, where the next pair starts.
//!
//! A batch serves a span of blends ([`super::RefinementSettings::blend_span`],
//! [`REFINEMENT_SPAN`], [`REFINEMENT_STEPS`] per interval): it is refined for
//! the largest Δ and the hull of the ranges over the span
//! ([`VolumeHierarchy::deviation_over`],
//! [`VolumeHierarchy::scalar_range_over`]) and carries the morphed field at
//! both of its ends, which the renderer mixes. The next span's batch starts
//! from the same field: a node refined by one batch and not the other has
//! `e' = 0` there and, Kuhn's tetrahedra being nested, draws its unrefined
//! field ([`super::emit`]).
//!
//! Keyframes `T` apart sit at the times `k·T` for integer `k`
//! ([`keyframe_index`], [`keyframe_time`]), so every user of a keyframe
//! sequence agrees on them. Why no span, hand-over or transparent node makes a
//! step is in `docs/wind-keyframes.md` in the repository.

use super::{HierarchyError, Node, VolumeHierarchy};

/// How many times per keyframe interval a blended octree is refined again
/// for the advancing blend (besides when the camera moved enough): the blend a
/// refinement is made for is the drawn blend rounded down to a step of
/// `1 / REFINEMENT_STEPS`. Consecutive steps draw the same field where they
/// meet (module docs), so fewer steps cost less without a pop; a longer
/// step refines for more blends at once, so draws a few more cells (`cargo
/// bench -p nebel_lod --bench wind_keyframes`, one run each, the 513 layer's
/// pair: 78,642 cells at 32 steps, 81,912 at 8, 86,508 at 4; every change
/// between frames of the 129 layer under 1.25e-2 at 8 and 4, one at a
/// hand-over 1.4e-2 at 32). Four: a step of that pair costs about 17 ms of
/// one core, so an interval's steps take about 67 ms against 128 ms with
/// eight, beside a keyframe of about 290 ms, for about 6 % more cells.
pub const REFINEMENT_STEPS: u32 = 4;

/// The blends a stepped refinement is made for
/// ([`super::RefinementSettings::blend_span`]): its step, from the step's
/// start to the next step's. The next step's refinement is made ahead,
/// while these cells are drawn, and takes over at the step's end (a caller
/// whose next refinement is late holds the blend there, or draws these
/// cells' end field until it lands: [`crate::Cells::mix_factor`]).
pub const REFINEMENT_SPAN: f32 = 1.0 / REFINEMENT_STEPS as f32;

impl VolumeHierarchy {
    /// The hierarchy that blends from this keyframe to `next` (see the
    /// module docs): this one's densities, light, Δ, ranges and morph slots,
    /// `next`'s densities, light, Δ and ranges beside them. Of a hierarchy
    /// that already blends, the first keyframe stays and `next`'s first
    /// becomes the second.
    ///
    /// Nothing is copied: the pair shares both keyframes' arrays (module
    /// docs of [`super`]), so it costs no time and no memory beyond theirs.
    ///
    /// Errors: [`HierarchyError::KeyframeMismatch`] when the two differ in
    /// points, spacing, origin, minimum accuracy or in having a light field.
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
        Ok(Self {
            next_density: next.density.clone(),
            next_light: next.light.clone(),
            next_words: next.words.clone(),
            ..self.clone()
        })
    }

    /// The propagated Δ of `node` for the blend `blend` toward the next
    /// keyframe (clamped to [0, 1], NaN as 0): `(1 − β) Δ_a + β Δ_b` (module
    /// docs); [`VolumeHierarchy::deviation`] for a single keyframe. Panics
    /// when the node is not in this hierarchy.
    pub fn deviation_at(&self, node: Node, blend: f32) -> f32 {
        self.deviation_over(node, [blend, blend])
    }

    /// The largest propagated Δ of `node` over the blends between
    /// `blends[0]` and `blends[1]` (each clamped to [0, 1], NaN as 0):
    /// `Δ_β` is linear in `β`, so the larger of its values at the two ends
    /// (module docs). Panics when the node is not in this hierarchy.
    pub fn deviation_over(&self, node: Node, blends: [f32; 2]) -> f32 {
        let first = self.deviation(node);
        match self.next_deviation(node) {
            // Equal ends blend to themselves exactly: the f32 blend of equal
            // values may round an ulp above them inside the span.
            Some(next) if next != first => {
                let [start, end] = blends.map(|blend| {
                    let beta = clamped_blend(blend);
                    (1.0 - beta) * first + beta * next
                });
                start.max(end)
            }
            _ => first,
        }
    }

    /// The node's scalar range for the blend `blend` toward the next
    /// keyframe (clamped to [0, 1], NaN as 0), units of 1/255: the blend of
    /// both keyframes' ranges rounded outward (module docs);
    /// [`VolumeHierarchy::scalar_range_quantised`] for a single keyframe.
    /// Panics when the node is not in this hierarchy.
    pub fn scalar_range_at(&self, node: Node, blend: f32) -> [u8; 2] {
        self.scalar_range_over(node, [blend, blend])
    }

    /// The node's scalar range over the blends between `blends[0]` and
    /// `blends[1]` (each clamped to [0, 1], NaN as 0), units of 1/255: the
    /// hull of [`VolumeHierarchy::scalar_range_at`] at the two ends, which
    /// holds every blend in between (the blended extremes are linear in
    /// `β`). Panics when the node is not in this hierarchy.
    pub fn scalar_range_over(&self, node: Node, blends: [f32; 2]) -> [u8; 2] {
        let ([low, high], Some([next_low, next_high])) = self.keyframe_ranges(node) else {
            return self.scalar_range_quantised(node);
        };
        let [first, second] = blends.map(|blend| {
            let beta = clamped_blend(blend);
            let mix = |a: u8, b: u8| (1.0 - beta) * f32::from(a) + beta * f32::from(b);
            // Rounded outward, and never outside the two keyframes' own.
            let low = (mix(low, next_low).floor() as u8).max(low.min(next_low));
            let high = (mix(high, next_high).ceil() as u8).min(high.max(next_high));
            [low, high]
        });
        [first[0].min(second[0]), first[1].max(second[1])]
    }

    /// The next keyframe's propagated Δ of `node` in density units (0 for a
    /// voxel); `None` unless the hierarchy blends two keyframes. Panics when
    /// the node is not in this hierarchy.
    pub fn next_deviation(&self, node: Node) -> Option<f32> {
        if !self.has_next_keyframe() {
            return None;
        }
        let word = self
            .centre_index(node)
            .map_or(0, |centre| self.next_words[centre]);
        Some(f32::from(word) / 65535.0)
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
}

/// A blend factor clamped to [0, 1], NaN as 0.
pub(super) fn clamped_blend(blend: f32) -> f32 {
    if blend.is_nan() {
        0.0
    } else {
        blend.clamp(0.0, 1.0)
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
