//! The common currency of every volumetric effect: a batch of cells to draw
//! (DESIGN.md §3).
//!
//! An effect plugin (volumes, ground fog, ...) spawns an entity with a
//! [`CellBatch`] and rewrites it when the view or its data changes; the
//! cell-projection render system ([`crate::cell_projection`]) uploads it and
//! draws it. A batch is drawn only while it has cells and a transfer function
//! that is not transparent everywhere.

use std::sync::Arc;

use bevy::prelude::*;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::TransferFunction;
use nebel_lod::GpuCell;

/// Cells in world space with one transfer function and one optical mode.
#[derive(Component, Clone, Debug, Default)]
pub struct CellBatch {
    /// Tetrahedra in world space, scalar in `w`, in draw order: back to front
    /// for [`OpticalMode::Sorted`], any order for the other modes.
    pub cells: Arc<Vec<GpuCell>>,
    /// Increase it whenever `cells` changes: the GPU copy is replaced only
    /// when the generation differs from the uploaded one. Default: 0.
    pub generation: u64,
    /// κ and ρ over the scalar; `None` draws nothing. Default: `None`.
    pub transfer_function: Option<Arc<TransferFunction>>,
    /// How the cells' segments combine. Default: [`OpticalMode::Sorted`].
    pub mode: OpticalMode,
    /// Per cell, the segment-length modulator `m ∈ [0, 1]` at its four
    /// vertices: every ray segment is integrated over `l' = l · (m_f + m_b)/2`
    /// instead of `l` (paper 000 §5.1, Eq. 9; the lit clouds of
    /// `nebel_volume`, see `nebel_lod::CellBatch`). `None` draws unmodulated
    /// segments; a list whose length differs from `cells` is refused by the
    /// render system (the batch is not drawn and an error is logged).
    /// Default: `None`.
    pub modulators: Option<Arc<Vec<[f32; 4]>>>,
    /// The longest segment a ray can have in one cell, world units (the
    /// longest cell diameter); the pre-integration table covers 0 to this
    /// length. Default: 0 (computed by [`CellBatch::new`]).
    pub max_segment_length: f32,
    /// Minimum corner of the cells' world bounds.
    pub bounds_min: Vec3,
    /// Maximum corner of the cells' world bounds.
    pub bounds_max: Vec3,
}

impl CellBatch {
    /// A batch of `cells` with its bounds and longest segment computed.
    pub fn new(
        cells: Vec<GpuCell>,
        transfer_function: Arc<TransferFunction>,
        mode: OpticalMode,
        generation: u64,
    ) -> Self {
        let mut bounds_min = Vec3::splat(f32::INFINITY);
        let mut bounds_max = Vec3::splat(f32::NEG_INFINITY);
        let mut max_segment_length = 0.0_f32;
        for cell in &cells {
            let vertices = cell.vertices.map(|v| Vec3::new(v[0], v[1], v[2]));
            for (index, vertex) in vertices.iter().enumerate() {
                bounds_min = bounds_min.min(*vertex);
                bounds_max = bounds_max.max(*vertex);
                for other in &vertices[index + 1..] {
                    max_segment_length = max_segment_length.max(vertex.distance(*other));
                }
            }
        }
        Self {
            cells: Arc::new(cells),
            generation,
            transfer_function: Some(transfer_function),
            mode,
            modulators: None,
            max_segment_length,
            bounds_min,
            bounds_max,
        }
    }

    /// The batch with per-cell segment-length modulators (see
    /// [`CellBatch::modulators`]); an empty list leaves it unmodulated.
    pub fn with_modulators(mut self, modulators: Vec<[f32; 4]>) -> Self {
        self.modulators = (!modulators.is_empty()).then(|| Arc::new(modulators));
        self
    }

    /// Whether the render system has anything to draw for this batch.
    pub fn is_drawable(&self) -> bool {
        !self.cells.is_empty()
            && self.max_segment_length > 0.0
            && self
                .transfer_function
                .as_ref()
                .is_some_and(|tf| !tf.is_transparent(0.0, 1.0))
    }
}
