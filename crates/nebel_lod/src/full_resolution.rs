//! A density grid at full resolution as tetrahedra in exact visibility order.
//!
//! Visibility sorting after Röttger 2004 §8.1, with the zero-opacity test of
//! Röttger and Ertl 2003 §4.1. Every voxel becomes Kuhn's six tetrahedra around
//! its diagonal from its lowest to its highest corner
//! ([`nebel_core::cell::Hexahedron::kuhn_tetrahedra`], the same in every
//! voxel), so neighbouring voxels share their face diagonals and the mesh
//! conforms. It is [`DensityGrid::tetrahedra`] and the octree's finest level,
//! whose coarser cells it refines without changing their field (the
//! decomposition is nested; the five alternating tetrahedra of Röttger and Ertl
//! 2003 §2.1 are not). It draws every grid volume without the octree and is the
//! exact reference the octree is measured against.
//!
//! The grid is cut into bricks of `brick_size³` voxels with their scalar ranges
//! ([`BrickTable`], once per grid). A brick is skipped when its range has zero
//! opacity ([`TransferFunction::is_transparent`], the zero-opacity test of
//! §4.1, exact for any transfer function) or its box misses the view frustum
//! ([`Frustum::intersects_aabb`](crate::Frustum::intersects_aabb)); an empty
//! viewport ([`View::viewport_is_empty`]) keeps none.
//!
//! [`CellOrder::BackToFront`] emits no cell before one that occludes it, for
//! any eye (inside the grid, inside a voxel or on a grid plane included):
//! bricks and voxels in a nested BSP order of slabs (along each axis from both
//! far ends towards the eye's slab), and the six tetrahedra of a voxel by the
//! MPVO rule (Williams 1992), by how many axis pairs each orders against the
//! eye. The order depends on the eye only through the side of the planes
//! `u_a = m` and `u_a − u_b = m` it is on, which [`order_key`] records, so a
//! caller rebuilds only when the key (or the grid, transform, transfer
//! function, frustum or viewport) changes
//! ([`VolumeBatcher`](crate::VolumeBatcher) does). [`CellOrder::Unordered`]
//! emits storage order, for the emissive and MIP modes. The order is exact for
//! the f64 geometry; the cost is linear in the kept voxels, with no sorting.
//!
//! Why the traversal and the in-voxel rule give an exact order is in
//! `docs/visibility-order.md` in the repository.

use glam::{DAffine3, DVec3, Vec3};
use nebel_core::cell::{KUHN_AXIS_ORDERS, KUHN_TETRAHEDRA};
use nebel_core::field::DensityGrid;
use nebel_core::transfer::TransferFunction;
use thiserror::Error;

use crate::batch::{Cells, GpuCell};
use crate::view::View;

/// The order in which a batch's cells are emitted.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum CellOrder {
    /// Exact back-to-front visibility order for the eye (the sorted
    /// emission-absorption model, "over" blending). The default.
    #[default]
    BackToFront,
    /// Storage order, independent of the eye (the emissive and MIP modes,
    /// whose blending is commutative).
    Unordered,
}

/// Why a batch could not be built.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum BatchError {
    /// The brick table belongs to a grid of another size.
    #[error(
        "the brick table was built for a grid of {table:?} voxels but this grid has {grid:?}; rebuild it with BrickTable::new"
    )]
    BrickTableMismatch {
        /// Voxels per axis of the grid the table was built for.
        table: [usize; 3],
        /// Voxels per axis of the grid given.
        grid: [usize; 3],
    },
    /// A ray-cast grid's modulators lie on another grid than its scalars.
    #[error(
        "the modulators have {modulators:?} points but the scalars {scalars:?}; both fields must share the grid"
    )]
    ModulatorMismatch {
        /// Points per axis of the scalars.
        scalars: [usize; 3],
        /// Points per axis of the modulators.
        modulators: [usize; 3],
    },
    /// A ray-cast grid's next keyframe lies on other points, or only one of
    /// the two keyframes has modulators.
    #[error(
        "the next keyframe has {next:?} points (modulated: {next_modulated}) but the grid {current:?} (modulated: {current_modulated}); both keyframes must share the grid and its fields"
    )]
    KeyframeMismatch {
        /// Points per axis of the current keyframe.
        current: [usize; 3],
        /// Whether it has modulators.
        current_modulated: bool,
        /// Points per axis of the next keyframe.
        next: [usize; 3],
        /// Whether it has modulators.
        next_modulated: bool,
    },
    /// The view's `world_from_local` is not finite or not invertible.
    #[error("world_from_local must be finite and invertible (determinant {determinant})")]
    SingularTransform {
        /// Determinant of its linear part.
        determinant: f64,
    },
    /// Back-to-front order was asked for with a NaN or infinite eye.
    #[error(
        "the eye position {eye} is not finite, so no back-to-front order exists (use CellOrder::Unordered)"
    )]
    NonFiniteEye {
        /// The eye position given, world units.
        eye: DVec3,
    },
}

/// The scalar range of every brick of a density grid, for the zero-opacity
/// test. Build it once per grid and keep it while the grid's values do not
/// change (a stale table may drop bricks that became visible).
#[derive(Clone, Debug, PartialEq)]
pub struct BrickTable {
    /// Voxels per axis of the grid the table belongs to.
    voxels: [usize; 3],
    /// Voxels per brick edge, ≥ 1.
    brick_size: usize,
    /// Bricks per axis, `ceil(voxels / brick_size)`.
    bricks: [usize; 3],
    /// `[min, max]` of the scalars on each brick's points (its boundary
    /// included), brick x fastest.
    ranges: Vec<[f32; 2]>,
}

impl BrickTable {
    /// The default brick edge, voxels: 4³ voxels (5³ points) per brick.
    pub const DEFAULT_BRICK_SIZE: usize = 4;

    /// The table of two fields on the same points, each brick's range
    /// spanning both (the ranges of any mix `(1 − t) a + t b`, `t` in [0,
    /// 1], lie within it); an error when the tables are of other grids or
    /// brick sizes.
    pub fn spanning(&self, other: &BrickTable) -> Result<Self, BatchError> {
        if (other.voxels, other.brick_size) != (self.voxels, self.brick_size) {
            return Err(BatchError::BrickTableMismatch {
                table: other.voxels,
                grid: self.voxels,
            });
        }
        let ranges = self
            .ranges
            .iter()
            .zip(&other.ranges)
            .map(|(a, b)| [a[0].min(b[0]), a[1].max(b[1])])
            .collect();
        Ok(Self {
            voxels: self.voxels,
            brick_size: self.brick_size,
            bricks: self.bricks,
            ranges,
        })
    }

    /// Scans `grid` once (cost about one read per grid point). `brick_size` is
    /// the brick edge in voxels; 0 is treated as 1.
    pub fn new(grid: &DensityGrid, brick_size: usize) -> Self {
        let brick_size = brick_size.max(1);
        let voxels = grid.dims().map(|n| n - 1);
        let bricks = voxels.map(|n| n.div_ceil(brick_size));
        let mut ranges = Vec::with_capacity(bricks.iter().product());
        for bz in 0..bricks[2] {
            for by in 0..bricks[1] {
                for bx in 0..bricks[0] {
                    let points = |b: usize, axis: usize| {
                        b * brick_size..=((b + 1) * brick_size).min(voxels[axis])
                    };
                    let mut range = [f32::INFINITY, f32::NEG_INFINITY];
                    for k in points(bz, 2) {
                        for j in points(by, 1) {
                            for i in points(bx, 0) {
                                let value = grid.value(i, j, k);
                                range = [range[0].min(value), range[1].max(value)];
                            }
                        }
                    }
                    ranges.push(range);
                }
            }
        }
        Self {
            voxels,
            brick_size,
            bricks,
            ranges,
        }
    }

    /// Voxels per axis of the grid the table belongs to.
    pub fn voxels(&self) -> [usize; 3] {
        self.voxels
    }

    /// Voxels per brick edge.
    pub fn brick_size(&self) -> usize {
        self.brick_size
    }

    /// Bricks per axis.
    pub fn brick_counts(&self) -> [usize; 3] {
        self.bricks
    }

    /// `[min, max]` of the scalar over brick `[bx, by, bz]` (its boundary points
    /// included); `None` outside the table.
    pub fn scalar_range(&self, brick: [usize; 3]) -> Option<[f32; 2]> {
        let [bx, by, bz] = brick;
        let [nx, ny, nz] = self.bricks;
        (bx < nx && by < ny && bz < nz).then(|| self.ranges[bx + nx * (by + ny * bz)])
    }

    /// The voxel range `[start, end)` of brick `b` along `axis`.
    fn voxel_range(&self, b: usize, axis: usize) -> (usize, usize) {
        (
            b * self.brick_size,
            ((b + 1) * self.brick_size).min(self.voxels[axis]),
        )
    }
}

/// The axis pairs `[a, b]` of the planes `u_a − u_b = m` between the Kuhn
/// tetrahedra of every voxel and octree node ([`EyeSides::differences`]).
pub(crate) const AXIS_PAIRS: [[usize; 2]; 3] = [[0, 1], [1, 2], [0, 2]];

/// The indices into [`KUHN_TETRAHEDRA`] of the six tetrahedra of a cube whose
/// lowest corner is `origin` (index coordinates, integers), back to front for
/// an eye with `differences` ([`EyeSides::differences`]): by how many axis
/// pairs each orders against the eye, most first (module docs). The cube's
/// size does not matter: its planes between tetrahedra all pass through its
/// lowest corner and its diagonal.
pub(crate) fn kuhn_back_to_front(differences: &[f64; 3], origin: [f64; 3]) -> [usize; 6] {
    // Per axis pair [a, b]: −1 when the eye has u_a < u_b in the cube's own
    // coordinates, +1 when u_a > u_b, 0 on the plane.
    let sides: [i8; 3] = std::array::from_fn(|p| {
        let [a, b] = AXIS_PAIRS[p];
        let plane = origin[a] - origin[b];
        i8::from(differences[p] > plane) - i8::from(differences[p] < plane)
    });
    let against: [u8; 6] = std::array::from_fn(|t| {
        let order = KUHN_AXIS_ORDERS[t];
        let rank = |axis: usize| order.iter().position(|&o| o == axis).unwrap_or(0);
        AXIS_PAIRS
            .iter()
            .zip(sides)
            .map(|(&[a, b], side)| {
                // The tetrahedron has u_a ≥ u_b when a comes first.
                let tetrahedron_side = if rank(a) < rank(b) { 1 } else { -1 };
                u8::from(side == -tetrahedron_side)
            })
            .sum()
    });
    let mut order = [0; 6];
    let mut next = 0;
    for count in (0..=3).rev() {
        for t in (0..6).filter(|&t| against[t] == count) {
            order[next] = t;
            next += 1;
        }
    }
    order
}

/// Builds the full-resolution batch of `grid` (six tetrahedra per voxel), in
/// world space, pruned and ordered as described in the module docs.
///
/// - `bricks`: the grid's [`BrickTable`] (any brick size).
/// - `view`: its `world_from_local` maps the grid's own coordinates (point
///   `(i, j, k)` at `origin + (i, j, k) · spacing`) to world space; the eye is
///   only read for [`CellOrder::BackToFront`]; the frustum culls bricks; an
///   empty viewport gives an empty batch (after the checks below).
/// - `transfer`: the transfer function of the zero-opacity test.
/// - `order`: see [`CellOrder`].
///
/// Vertex positions are rounded to f32 after the transform, each grid point the
/// same way in every cell that shares it, so the batch conforms in f32 too.
/// The bounds are those of the kept bricks' corners, which are exactly those of
/// the emitted vertices. Errors: [`BatchError`].
pub fn full_resolution_batch(
    grid: &DensityGrid,
    bricks: &BrickTable,
    view: &View,
    transfer: &TransferFunction,
    order: CellOrder,
) -> Result<Cells, BatchError> {
    let voxels = grid.dims().map(|n| n - 1);
    if bricks.voxels != voxels {
        return Err(BatchError::BrickTableMismatch {
            table: bricks.voxels,
            grid: voxels,
        });
    }
    let Some((world_from_index, index_from_world)) =
        index_maps(grid.origin(), grid.spacing(), view.world_from_local)
    else {
        return Err(BatchError::SingularTransform {
            determinant: view.world_from_local.matrix3.determinant(),
        });
    };
    let eye = match order {
        CellOrder::BackToFront => Some(
            EyeSides::new(index_from_world.transform_point3(view.eye))
                .ok_or(BatchError::NonFiniteEye { eye: view.eye })?,
        ),
        CellOrder::Unordered => None,
    };
    if view.viewport_is_empty() {
        return Ok(Cells::default());
    }
    let local_frustum = view
        .frustum
        .as_ref()
        .map(|f| f.in_local_frame(&world_from_index));
    let point = |i: usize, j: usize, k: usize| {
        world_from_index
            .transform_point3(DVec3::new(i as f64, j as f64, k as f64))
            .as_vec3()
    };

    // Pass 1: which bricks stay, how many voxels they hold, their bounds.
    let [nbx, nby, nbz] = bricks.bricks;
    let mut kept = Vec::with_capacity(nbx * nby * nbz);
    let mut kept_voxels = 0;
    let (mut bounds_min, mut bounds_max) = (Vec3::INFINITY, Vec3::NEG_INFINITY);
    for bz in 0..nbz {
        for by in 0..nby {
            for bx in 0..nbx {
                let [s_min, s_max] = bricks.ranges[bx + nbx * (by + nby * bz)];
                let (x, y, z) = (
                    bricks.voxel_range(bx, 0),
                    bricks.voxel_range(by, 1),
                    bricks.voxel_range(bz, 2),
                );
                let visible = !transfer.is_transparent(f64::from(s_min), f64::from(s_max))
                    && local_frustum.as_ref().is_none_or(|f| {
                        f.intersects_aabb(
                            DVec3::new(x.0 as f64, y.0 as f64, z.0 as f64),
                            DVec3::new(x.1 as f64, y.1 as f64, z.1 as f64),
                        )
                    });
                kept.push(visible);
                if visible {
                    kept_voxels += (x.1 - x.0) * (y.1 - y.0) * (z.1 - z.0);
                    for corner in 0..8 {
                        let p = point(
                            if corner & 1 == 0 { x.0 } else { x.1 },
                            if corner & 2 == 0 { y.0 } else { y.1 },
                            if corner & 4 == 0 { z.0 } else { z.1 },
                        );
                        bounds_min = bounds_min.min(p);
                        bounds_max = bounds_max.max(p);
                    }
                }
            }
        }
    }
    if kept_voxels == 0 {
        return Ok(Cells::default());
    }

    // Pass 2: emit, bricks and voxels in BSP order.
    let mut cells = Vec::with_capacity(6 * kept_voxels);
    let brick_order: [Vec<usize>; 3] = std::array::from_fn(|axis| {
        let mut order = Vec::with_capacity(bricks.bricks[axis]);
        let slab = eye
            .as_ref()
            .map(|e| e.slab[axis].div_euclid(bricks.brick_size as i64));
        axis_order(0, bricks.bricks[axis], slab, &mut order);
        order
    });
    let mut voxel_order: [Vec<usize>; 3] = Default::default();
    for &bz in &brick_order[2] {
        for &by in &brick_order[1] {
            for &bx in &brick_order[0] {
                if !kept[bx + nbx * (by + nby * bz)] {
                    continue;
                }
                for (axis, b) in [bx, by, bz].into_iter().enumerate() {
                    let (start, end) = bricks.voxel_range(b, axis);
                    let slab = eye.as_ref().map(|e| e.slab[axis]);
                    axis_order(start, end, slab, &mut voxel_order[axis]);
                }
                for &k in &voxel_order[2] {
                    for &j in &voxel_order[1] {
                        for &i in &voxel_order[0] {
                            emit_voxel(grid, &point, [i, j, k], eye.as_ref(), &mut cells);
                        }
                    }
                }
            }
        }
    }
    Ok(Cells {
        tetrahedra: cells,
        bounds_min,
        bounds_max,
        ..Cells::default()
    })
}

/// A cheap fingerprint of the back-to-front order for the view's eye: two
/// views with the same `world_from_local` (the grid's coordinates to world,
/// as for [`full_resolution_batch`]) and the same key get the same
/// [`CellOrder::BackToFront`] batch of `grid` (with the same bricks, frustum,
/// viewport and transfer function). The frustum and viewport are not read.
///
/// With the eye at `u` in voxel index coordinates, the key holds `⌊u_a⌋` per
/// axis and, for each axis pair `(a, b)`, which integer or open interval
/// between integers `u_a − u_b` lies on (`2⌊v⌋` for an integer `v`,
/// `2⌊v⌋ + 1` otherwise), each clamped to where the order stops changing.
/// `None` when the eye is not finite or `world_from_local` is not invertible
/// (then [`full_resolution_batch`] fails for that order too).
pub fn order_key(grid: &DensityGrid, view: &View) -> Option<[i64; 6]> {
    let (_, index_from_world) = index_maps(grid.origin(), grid.spacing(), view.world_from_local)?;
    let eye = EyeSides::new(index_from_world.transform_point3(view.eye))?;
    // Beyond ±limit every plane of the grid is on the same side.
    let limit = 4 * grid.dims().iter().sum::<usize>() as i64 + 8;
    let mut key = [0; 6];
    for (axis, slab) in eye.slab.into_iter().enumerate() {
        key[axis] = slab.clamp(-limit, limit);
    }
    for (pair, v) in eye.differences.into_iter().enumerate() {
        let floor = v.floor();
        let interval = 2.0 * floor + if v == floor { 0.0 } else { 1.0 };
        key[3 + pair] = interval.clamp(-2.0 * limit as f64, 2.0 * limit as f64) as i64;
    }
    Some(key)
}

/// The maps between world space and the index space of a grid with `origin`
/// and `spacing` (point `(i, j, k)` at `(i, j, k)`) placed by
/// `world_from_grid` (the view's `world_from_local`):
/// `(world_from_index, index_from_world)`, or `None` when not finite or not
/// invertible. The octree's refinement and emission use the same maps.
pub(crate) fn index_maps(
    origin: DVec3,
    spacing: DVec3,
    world_from_grid: DAffine3,
) -> Option<(DAffine3, DAffine3)> {
    let world_from_index =
        world_from_grid * DAffine3::from_translation(origin) * DAffine3::from_scale(spacing);
    let determinant = world_from_index.matrix3.determinant();
    let index_from_world = world_from_index.inverse();
    let invertible = world_from_index.is_finite()
        && determinant != 0.0
        && determinant.is_finite()
        && index_from_world.is_finite();
    invertible.then_some((world_from_index, index_from_world))
}

/// What the order depends on: the eye's slab per axis and, per axis pair
/// `[a, b]` of [`AXIS_PAIRS`], `u_a − u_b`. Computed once per batch, so every
/// voxel compares the same rounded values (and [`order_key`] sees exactly
/// what the batch sees).
pub(crate) struct EyeSides {
    /// `⌊u_a⌋` per axis, clamped to the i64 range.
    pub(crate) slab: [i64; 3],
    /// `u_a − u_b` per axis pair of [`AXIS_PAIRS`].
    pub(crate) differences: [f64; 3],
}

impl EyeSides {
    /// The sides of `u` (voxel index coordinates); `None` if not finite.
    pub(crate) fn new(u: DVec3) -> Option<Self> {
        if !u.is_finite() {
            return None;
        }
        // ±2⁶² keeps the i64 arithmetic of the traversal far from overflow.
        let bound = 2f64.powi(62);
        let slab = u.to_array().map(|v| v.floor().clamp(-bound, bound) as i64);
        let differences = AXIS_PAIRS.map(|[a, b]| u[a] - u[b]);
        Some(Self { slab, differences })
    }
}

/// Writes into `order` the slabs `start..end` of one axis: with the eye's slab
/// index (slab `s` spans `[s, s + 1)`), from both far ends towards the eye's
/// slab, the eye's slab last; without one, ascending.
pub(crate) fn axis_order(start: usize, end: usize, eye_slab: Option<i64>, order: &mut Vec<usize>) {
    order.clear();
    let Some(slab) = eye_slab else {
        order.extend(start..end);
        return;
    };
    // Slabs below the eye's ascending, those above descending, the eye's last.
    let below = slab.clamp(start as i64, end as i64) as usize;
    let above = slab.saturating_add(1).clamp(start as i64, end as i64) as usize;
    order.extend(start..below);
    order.extend((above..end).rev());
    if below < above {
        order.push(below);
    }
}

/// Appends the six tetrahedra of voxel `[i, j, k]`; with an eye back to
/// front ([`kuhn_back_to_front`]), else in the order of [`KUHN_TETRAHEDRA`].
fn emit_voxel(
    grid: &DensityGrid,
    point: &impl Fn(usize, usize, usize) -> Vec3,
    [i, j, k]: [usize; 3],
    eye: Option<&EyeSides>,
    cells: &mut Vec<GpuCell>,
) {
    let corner = |v: usize| {
        let (ci, cj, ck) = (i + (v & 1), j + ((v >> 1) & 1), k + ((v >> 2) & 1));
        let p = point(ci, cj, ck);
        [p.x, p.y, p.z, grid.value(ci, cj, ck)]
    };
    let vertices: [[f32; 4]; 8] = std::array::from_fn(corner);
    let cell = |t: usize| GpuCell {
        vertices: KUHN_TETRAHEDRA[t].map(|v| vertices[v]),
    };
    match eye {
        Some(eye) => {
            let origin = [i, j, k].map(|n| n as f64);
            cells.extend(kuhn_back_to_front(&eye.differences, origin).map(cell));
        }
        None => cells.extend((0..6).map(cell)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn order(start: usize, end: usize, eye: Option<f64>) -> Vec<usize> {
        let mut out = vec![];
        let slab = eye.map(|e| EyeSides::new(DVec3::splat(e)).unwrap().slab[0]);
        axis_order(start, end, slab, &mut out);
        out
    }

    #[test]
    fn axis_order_visits_far_ends_first_and_the_eye_slab_last() {
        assert_eq!(order(0, 5, None), [0, 1, 2, 3, 4]);
        assert_eq!(order(0, 5, Some(2.5)), [0, 1, 4, 3, 2]);
        assert_eq!(order(0, 5, Some(2.0)), [0, 1, 4, 3, 2]);
        assert_eq!(order(0, 5, Some(-0.5)), [4, 3, 2, 1, 0]);
        assert_eq!(order(0, 5, Some(0.0)), [4, 3, 2, 1, 0]);
        assert_eq!(order(0, 5, Some(5.0)), [0, 1, 2, 3, 4]);
        assert_eq!(order(0, 5, Some(1e300)), [0, 1, 2, 3, 4]);
        assert_eq!(order(0, 5, Some(-1e300)), [4, 3, 2, 1, 0]);
        assert_eq!(order(4, 8, Some(6.3)), [4, 5, 7, 6]);
        assert_eq!(order(4, 8, Some(1.0)), [7, 6, 5, 4]);
        assert_eq!(order(4, 8, Some(9.0)), [4, 5, 6, 7]);
        assert!(EyeSides::new(DVec3::new(0.0, f64::NAN, 0.0)).is_none());
    }

    /// For eyes on every side of the planes between a cube's tetrahedra
    /// (and on them), the order is a permutation in which every pair of
    /// face neighbours comes far one first: the one whose axis ordering the
    /// eye's local coordinates break on their shared pair.
    #[test]
    fn kuhn_order_crosses_every_shared_face_from_back_to_front() {
        let origin = [3.0, -2.0, 5.0];
        let values = [-1.5, -0.5, 0.0, 0.25, 0.5, 1.0, 2.0];
        for &x in &values {
            for &y in &values {
                for &z in &values {
                    let local = [x, y, z];
                    let u: [f64; 3] = std::array::from_fn(|a| origin[a] + local[a]);
                    let eye = EyeSides::new(DVec3::from(u)).unwrap();
                    let order = kuhn_back_to_front(&eye.differences, origin);
                    let mut sorted = order;
                    sorted.sort();
                    assert_eq!(sorted, [0, 1, 2, 3, 4, 5], "{local:?}");
                    let position = |t: usize| order.iter().position(|&o| o == t).unwrap();
                    for (s, os) in KUHN_AXIS_ORDERS.into_iter().enumerate() {
                        for (t, ot) in KUHN_AXIS_ORDERS.into_iter().enumerate() {
                            // Neighbours: the orderings swap one neighbouring pair.
                            let swapped = |i: usize| {
                                os[i] == ot[i + 1]
                                    && os[i + 1] == ot[i]
                                    && os[2 - 2 * i] == ot[2 - 2 * i]
                            };
                            let Some(i) = (0..2).find(|&i| swapped(i)) else {
                                continue;
                            };
                            // s has u_a ≥ u_b; the eye behind it has u_a < u_b.
                            let (a, b) = (os[i], os[i + 1]);
                            if local[a] < local[b] {
                                assert!(position(s) < position(t), "{local:?}: {s} before {t}");
                            }
                        }
                    }
                }
            }
        }
    }
}
