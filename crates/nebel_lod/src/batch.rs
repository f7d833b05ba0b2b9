//! Cell batches: tetrahedra in world space in GPU layout, in draw order.
//!
//! A [`Cells`] is what every effect hands to the render system: its cells
//! in the order they are drawn (back to front for the sorted
//! emission-absorption model, any order for the emissive and MIP modes) and
//! their world bounds, by which whole batches are ordered against each other.

use std::sync::Arc;

use glam::{DVec3, Vec3};
use nebel_core::cell::Tetrahedron;

use crate::cell_grid::CellGrid;

/// One tetrahedron as the GPU reads it: four vertices, each
/// `[x, y, z, s]` with the world position in world units (f32, relative to the
/// world origin) and the scalar `s` in [0, 1]. 64 bytes, no padding.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GpuCell {
    /// The four vertices `[x, y, z, s]`, any orientation.
    pub vertices: [[f32; 4]; 4],
}

impl GpuCell {
    /// The tetrahedron rounded to f32. Positions are not checked; see
    /// [`Cells::from_tetrahedra`] for a checked conversion.
    pub fn from_tetrahedron(tetrahedron: &Tetrahedron) -> Self {
        Self {
            vertices: std::array::from_fn(|v| {
                let p = tetrahedron.positions[v].as_vec3();
                [p.x, p.y, p.z, tetrahedron.scalars[v] as f32]
            }),
        }
    }

    /// The cell back in f64, exactly the f32 values the GPU sees (for the CPU
    /// reference and for tests).
    pub fn to_tetrahedron(&self) -> Tetrahedron {
        Tetrahedron {
            positions: self
                .vertices
                .map(|[x, y, z, _]| DVec3::new(f64::from(x), f64::from(y), f64::from(z))),
            scalars: self.vertices.map(|v| f64::from(v[3])),
        }
    }

    /// World position of vertex `index` (0 to 3).
    pub fn position(&self, index: usize) -> Vec3 {
        let [x, y, z, _] = self.vertices[index % 4];
        Vec3::new(x, y, z)
    }
}

/// Tetrahedra in world space, in draw order, with their world bounds.
///
/// An empty batch has both bounds at the origin.
///
/// # Segment-length modulation (Röttger and Ertl 2003 §5.1, Eq. 9)
///
/// A lit cloud carries two scalars per vertex: the one in
/// [`GpuCell::vertices`] indexes the transfer function (its pre-integration
/// tables), and the **modulator** `m ∈ [0, 1]` scales the length of every ray
/// segment before the lookup: `l' = l · (m_f + m_b) / 2`, the mean of the
/// linear modulator, over each of `nebel_core::optics::MODULATOR_PIECES`
/// equal pieces of the segment, composited front to back (the optical depth
/// is exact for a linear `m`; the colour's weighting approaches the
/// continuous model's with more pieces). With the light
/// γ as scalar and the density `f / f_max` as modulator this is the paper's
/// `l' = l · f / f_max`; the non-physical variant (§5.2) swaps the two.
/// `modulators` is empty for an unmodulated batch, otherwise it has one entry
/// per cell, the modulator at the cell's four vertices in vertex order.
///
/// # Keyframe blending
///
/// A batch drawn from two keyframes of an animated field (a cloud in the
/// wind, a light field under a moving sun) serves a span of keyframe blends
/// ([`Cells::blends`]): its scalars and modulators are the field at the
/// span's first blend, and it carries those at its last blend too
/// ([`Cells::next_scalars`], [`Cells::next_modulators`]), for the
/// same cells. The renderer draws each vertex at `(1 − t) · current + t ·
/// next` for a mix factor `t` in [0, 1] ([`Cells::mix_factor`] of the
/// blend) that it may change every frame without a new batch, so every
/// vertex moves continuously from one end of the span to the other. Where a
/// batch for the next span takes over at that end, it starts from the same
/// field ([`crate::octree::emit`]).
///
/// # A grid drawn whole
///
/// A batch may instead be a whole density grid ([`Cells::grid`]): its Kuhn
/// tetrahedra, ray cast by the renderer front to back without being
/// emitted ([`crate::cell_grid`]). It has no tetrahedra, modulators or next
/// keyframe then; a lit grid carries its modulators at its points
/// ([`CellGrid::modulators`]), a blended one its next keyframe
/// ([`CellGrid::next_keyframe`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Cells {
    /// The cells in draw order.
    pub tetrahedra: Vec<GpuCell>,
    /// Per cell, the segment-length modulator at its four vertices, in
    /// [0, 1]; empty when the batch is not modulated (see the type docs).
    pub modulators: Vec<[f32; 4]>,
    /// Per cell, the scalar at its four vertices at the last blend of
    /// [`Cells::blends`]; empty when the batch is not blended (see the
    /// type docs).
    pub next_scalars: Vec<[f32; 4]>,
    /// Per cell, the modulator at its four vertices at the last blend of
    /// [`Cells::blends`]; empty when the batch is not blended or not
    /// modulated.
    pub next_modulators: Vec<[f32; 4]>,
    /// For a blended batch, the first and last keyframe blend `β` (in [0,
    /// 1]) of the span it serves: the cells' own scalars and modulators are
    /// the field at the first, [`Cells::next_scalars`] and
    /// [`Cells::next_modulators`] at the last. `[0, 0]` when not
    /// blended. Default `[0, 0]`.
    pub blends: [f32; 2],
    /// Minimum corner of the axis-aligned box around every vertex, world units.
    pub bounds_min: Vec3,
    /// Maximum corner of the axis-aligned box around every vertex, world units.
    pub bounds_max: Vec3,
    /// A grid drawn whole by ray casting instead of `tetrahedra` (see the
    /// type docs). Default `None`.
    pub grid: Option<Arc<CellGrid>>,
}

impl Cells {
    /// A batch of scene-given tetrahedra, kept in their order (the caller's
    /// draw order).
    ///
    /// Cells with a non-finite position or scalar, or a position beyond the f32
    /// range, are dropped (the rest keep their order); scalars are clamped into
    /// [0, 1], the range every pre-integration table covers.
    pub fn from_tetrahedra(tetrahedra: &[Tetrahedron]) -> Self {
        let cells = tetrahedra
            .iter()
            .filter(|t| t.scalars.iter().all(|s| s.is_finite()))
            .map(|t| {
                let mut cell = GpuCell::from_tetrahedron(t);
                for vertex in &mut cell.vertices {
                    vertex[3] = vertex[3].clamp(0.0, 1.0);
                }
                cell
            })
            .filter(|cell| cell.vertices.iter().flatten().all(|c| c.is_finite()))
            .collect();
        Self::with_bounds(cells)
    }

    /// The batch of `cells` with bounds computed from every vertex.
    pub fn with_bounds(cells: Vec<GpuCell>) -> Self {
        let mut vertices = cells.iter().flat_map(|c| (0..4).map(|v| c.position(v)));
        let Some(first) = vertices.next() else {
            return Self::default();
        };
        let (bounds_min, bounds_max) =
            vertices.fold((first, first), |(lo, hi), p| (lo.min(p), hi.max(p)));
        Self {
            tetrahedra: cells,
            bounds_min,
            bounds_max,
            ..Self::default()
        }
    }

    /// Whether the cells carry segment-length modulators (per cell, or at a
    /// ray-cast grid's points).
    pub fn is_modulated(&self) -> bool {
        !self.modulators.is_empty()
            || self
                .grid
                .as_ref()
                .is_some_and(|grid| grid.modulators().is_some())
    }

    /// Whether the cells carry a next keyframe to blend toward (see the type
    /// docs).
    pub fn is_blended(&self) -> bool {
        !self.next_scalars.is_empty() || self.grid.as_ref().is_some_and(|grid| grid.is_blended())
    }

    /// The mix factor `t` in [0, 1] at which the renderer draws the
    /// keyframe blend `blend` (see the type docs): `(β − β₀) / (β₁ − β₀)`
    /// for the span `[β₀, β₁]` of [`Cells::blends`], clamped to [0, 1]
    /// (a batch drawn past its span holds the field at its end); 0 for NaN,
    /// an empty span or a batch that is not blended.
    pub fn mix_factor(&self, blend: f32) -> f32 {
        let [first, last] = self.blends;
        let t = (blend - first) / (last - first);
        if self.is_blended() && last > first && !t.is_nan() {
            t.clamp(0.0, 1.0)
        } else {
            0.0
        }
    }

    /// The batch as the renderer draws it at keyframe blend `blend`: every
    /// vertex's scalar and modulator at `(1 − t) · current + t · next` for
    /// `t` = [`Cells::mix_factor`], no next values. A batch that is not
    /// blended is returned as it is.
    pub fn blended(&self, blend: f32) -> Self {
        if !self.is_blended() {
            return self.clone();
        }
        let t = self.mix_factor(blend);
        if let Some(grid) = &self.grid {
            return Self {
                grid: Some(Arc::new(grid.blended(t))),
                blends: [0.0; 2],
                ..self.clone()
            };
        }
        let mix = |current: f32, next: f32| (1.0 - t) * current + t * next;
        let cells = self
            .tetrahedra
            .iter()
            .zip(&self.next_scalars)
            .map(|(cell, next)| GpuCell {
                vertices: std::array::from_fn(|v| {
                    let [x, y, z, s] = cell.vertices[v];
                    [x, y, z, mix(s, next[v])]
                }),
            })
            .collect();
        let modulators = self
            .modulators
            .iter()
            .zip(&self.next_modulators)
            .map(|(current, next)| std::array::from_fn(|v| mix(current[v], next[v])))
            .collect();
        Self {
            tetrahedra: cells,
            modulators,
            next_scalars: Vec::new(),
            next_modulators: Vec::new(),
            blends: [0.0; 2],
            grid: self.grid.clone(),
            ..*self
        }
    }

    /// The batch of a whole grid, drawn by ray casting (see the type
    /// docs); a blended grid serves the whole span of its two keyframes,
    /// blends `[0, 1]`.
    pub fn from_grid(grid: CellGrid) -> Self {
        let (bounds_min, bounds_max) = grid.bounds();
        Self {
            blends: if grid.is_blended() {
                [0.0, 1.0]
            } else {
                [0.0; 2]
            },
            bounds_min,
            bounds_max,
            grid: Some(Arc::new(grid)),
            ..Self::default()
        }
    }

    /// Number of cells: the tetrahedra, or the grid's.
    pub fn len(&self) -> usize {
        self.tetrahedra.len() + self.grid.as_ref().map_or(0, |grid| grid.cell_count())
    }

    /// Whether the batch has no cells.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tetrahedron(offset: f64, scalar: f64) -> Tetrahedron {
        Tetrahedron {
            positions: [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z].map(|p| p + offset),
            scalars: [scalar, 0.25, 0.5, 0.75],
        }
    }

    #[test]
    fn gpu_cell_is_64_bytes_and_round_trips() {
        assert_eq!(size_of::<GpuCell>(), 64);
        let t = tetrahedron(0.5, 0.125);
        assert_eq!(GpuCell::from_tetrahedron(&t).to_tetrahedron(), t);
        let cell = GpuCell::from_tetrahedron(&t);
        assert_eq!(bytemuck::bytes_of(&cell).len(), 64);
    }

    #[test]
    fn a_blended_batch_mixes_scalars_and_modulators_and_drops_the_next_keyframe() {
        let mut batch = Cells::from_tetrahedra(&[tetrahedron(0.0, 0.0)]);
        assert_eq!(batch.blended(0.5), batch, "not blended: unchanged");
        batch.modulators = vec![[1.0, 0.0, 0.5, 0.25]];
        batch.next_scalars = vec![[1.0; 4]];
        batch.next_modulators = vec![[0.0; 4]];
        batch.blends = [0.25, 0.75];
        assert_eq!(batch.mix_factor(0.5), 0.5);
        assert_eq!(batch.mix_factor(0.375), 0.25);
        assert_eq!(batch.mix_factor(0.0), 0.0, "before the span: its start");
        assert_eq!(batch.mix_factor(0.9), 1.0, "past the span: its end");
        let half = batch.blended(0.5);
        assert!(!half.is_blended());
        assert_eq!(
            half.tetrahedra[0].vertices.map(|v| v[3]),
            [0.5, 0.625, 0.75, 0.875]
        );
        assert_eq!(half.modulators, vec![[0.5, 0.0, 0.25, 0.125]]);
        assert_eq!(
            half.tetrahedra[0].position(2),
            batch.tetrahedra[0].position(2)
        );
        assert_eq!(batch.blended(f32::NAN).tetrahedra, batch.tetrahedra);
        assert_eq!(batch.blended(7.0).tetrahedra[0].vertices[0][3], 1.0);
        batch.blends = [0.5, 0.5];
        assert_eq!(batch.mix_factor(0.75), 0.0, "an empty span");
    }

    #[test]
    fn from_tetrahedra_keeps_order_drops_non_finite_and_clamps() {
        let mut bad = tetrahedron(0.0, 0.5);
        bad.positions[2].y = f64::NAN;
        let input = [
            tetrahedron(2.0, 0.1),
            bad,
            tetrahedron(0.0, f64::NAN),
            tetrahedron(-1.0, 3.0),
            tetrahedron(1e300, 0.5),
        ];
        let batch = Cells::from_tetrahedra(&input);
        assert_eq!(batch.len(), 2);
        assert_eq!(batch.tetrahedra[0].vertices[0], [2.0, 2.0, 2.0, 0.1]);
        assert_eq!(batch.tetrahedra[1].vertices[0], [-1.0, -1.0, -1.0, 1.0]);
        assert_eq!(batch.bounds_min, Vec3::splat(-1.0));
        assert_eq!(batch.bounds_max, Vec3::splat(3.0));
        let empty = Cells::from_tetrahedra(&[]);
        assert!(empty.is_empty());
        assert_eq!(
            (empty.bounds_min, empty.bounds_max),
            (Vec3::ZERO, Vec3::ZERO)
        );
    }
}
