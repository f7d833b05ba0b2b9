//! A density grid at full resolution as a batch of tetrahedra in exact
//! visibility order (paper 001 §8.1 visibility sorting, paper 000 §3 and §4.1;
//! DESIGN.md §3, §5).
//!
//! Every voxel becomes five tetrahedra with the alternating decomposition of
//! [`Hexahedron::tetrahedra`] (parity `(i + j + k) mod 2`), so neighbouring
//! voxels share their face diagonals and the mesh conforms. Before the octree
//! C-LOD replaces it, this is the source of every grid volume, and the exact
//! reference the octree is measured against.
//!
//! # Pruning
//!
//! The grid is cut into bricks of `brick_size³` voxels (the last brick on an
//! axis may be thinner). A [`BrickTable`] holds each brick's scalar range,
//! computed once per grid. A brick is skipped when
//! - its scalar range has zero opacity, [`TransferFunction::is_transparent`]
//!   (the zero-opacity test of paper 000 §4.1, exact for any transfer
//!   function: a brick with any ρ > 0 in its range stays), or
//! - its box misses the view frustum ([`Frustum::intersects_aabb`] in the grid's
//!   own frame, conservative).
//!
//! # Visibility order
//!
//! [`CellOrder::BackToFront`] emits the cells so that a cell never occludes one
//! emitted before it, for the given eye, also when the eye is inside the grid,
//! inside a voxel or exactly on a grid plane:
//! - Across bricks and voxels: a BSP-style nested traversal of the axis-aligned
//!   grid in its own frame (the eye is pulled back through `world_from_grid`;
//!   sidedness is invariant under affine maps, mirrors included). Along each
//!   axis the slabs are visited from both far ends towards the eye's slab, the
//!   eye's slab last; z outermost, x innermost. Each slab boundary is a plane
//!   that separates everything visited earlier on the eye's far side from what
//!   follows, so the nesting is a valid BSP order. Bricks are visited this way,
//!   then the voxels inside each brick, which is again a BSP order.
//! - Inside a voxel, the MPVO rule (Williams, "Visibility ordering meshed
//!   polyhedra", 1992) on its five tetrahedra: each corner tetrahedron shares
//!   one face with the central tetrahedron and touches the other corner
//!   tetrahedra only along edges, so the corner tetrahedra on the far side of
//!   their shared face (seen from the eye) come first, then the central one,
//!   then those on the eye's side. An eye exactly on a face plane may see
//!   either order; both are correct.
//!
//! [`CellOrder::Unordered`] emits bricks, voxels and tetrahedra in storage order
//! (x fastest), for the emissive and MIP modes, which need no sorting.
//!
//! # Cost
//!
//! Linear in the number of voxels of kept bricks, plus one visit per brick; no
//! sorting. Measured with `cargo bench -p nebel_lod --bench full_resolution`
//! (64³ grid, every brick kept, 1.31 million cells, one core): about 40 000
//! cells per ms in back-to-front order, with the eye outside or inside the grid,
//! and about 44 000 unordered, so a full 64³ batch takes about 30 ms and a
//! 32³ one about 4 ms. Rebuilding when the eye moves is affordable for the
//! small grids of the emissive effects; large grids are the octree's job.

use std::sync::LazyLock;

use glam::{DAffine3, DVec3, Vec3};
use nebel_core::cell::{Hexahedron, HexahedronParity};
use nebel_core::field::DensityGrid;
use nebel_core::transfer::TransferFunction;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::batch::{CellBatch, GpuCell};
use crate::frustum::Frustum;

/// The order in which a batch's cells are emitted.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
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
    /// `world_from_grid` is not finite or not invertible.
    #[error("world_from_grid must be finite and invertible (determinant {determinant})")]
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

/// The five-tetrahedron pattern of one parity, as corner indices `x + 2y + 4z`.
struct Decomposition {
    /// Corner indices of the central tetrahedron.
    central: [usize; 4],
    /// Corner tetrahedra: their corner indices and their apex (the cube corner
    /// whose three neighbours form the face shared with the central one).
    corners: [([usize; 4], usize); 4],
}

/// nebel_core's decomposition for each parity, read off once from
/// [`Hexahedron::tetrahedra`] of a hexahedron whose scalars are its corner
/// indices, so the batch conforms exactly as nebel_core's meshes do.
static DECOMPOSITIONS: LazyLock<[Decomposition; 2]> = LazyLock::new(|| {
    let indices =
        Hexahedron::axis_aligned(DVec3::ZERO, DVec3::ONE, std::array::from_fn(|v| v as f64));
    [HexahedronParity::Even, HexahedronParity::Odd].map(|parity| {
        let tetrahedra = indices
            .tetrahedra(parity)
            .map(|t| t.scalars.map(|s| s as usize));
        // A corner tetrahedron has an apex whose three cube neighbours are
        // its other vertices; the central one has none.
        let apex = |t: &[usize; 4]| {
            t.iter().copied().find(|&a| {
                t.iter()
                    .filter(|&&v| v != a)
                    .all(|&v| (v ^ a).count_ones() == 1)
            })
        };
        let mut central = [0; 4];
        let mut corners = Vec::with_capacity(4);
        for t in tetrahedra {
            match apex(&t) {
                Some(a) => corners.push((t, a)),
                None => central = t,
            }
        }
        Decomposition {
            central,
            corners: std::array::from_fn(|c| corners[c]),
        }
    })
});

/// Builds the full-resolution batch of `grid` (five tetrahedra per voxel), in
/// world space, pruned and ordered as described in the module docs.
///
/// - `bricks`: the grid's [`BrickTable`] (any brick size).
/// - `world_from_grid`: maps the grid's own coordinates (point `(i, j, k)` at
///   `origin + (i, j, k) · spacing`) to world space; any finite invertible
///   affine map (rotation, non-uniform scale, shear, mirror).
/// - `eye_world`: the eye, world units; only read for
///   [`CellOrder::BackToFront`].
/// - `frustum`: world-space view frustum; `None` culls nothing.
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
    world_from_grid: DAffine3,
    eye_world: DVec3,
    frustum: Option<&Frustum>,
    transfer: &TransferFunction,
    order: CellOrder,
) -> Result<CellBatch, BatchError> {
    let voxels = grid.dims().map(|n| n - 1);
    if bricks.voxels != voxels {
        return Err(BatchError::BrickTableMismatch {
            table: bricks.voxels,
            grid: voxels,
        });
    }
    // Voxel index space: point (i, j, k) at (i, j, k).
    let world_from_index = world_from_grid
        * DAffine3::from_translation(grid.origin())
        * DAffine3::from_scale(grid.spacing());
    let determinant = world_from_index.matrix3.determinant();
    let index_from_world = world_from_index.inverse();
    let invertible = world_from_index.is_finite()
        && determinant != 0.0
        && determinant.is_finite()
        && index_from_world.is_finite();
    if !invertible {
        return Err(BatchError::SingularTransform {
            determinant: world_from_grid.matrix3.determinant(),
        });
    }
    let eye = match order {
        CellOrder::BackToFront if !eye_world.is_finite() => {
            return Err(BatchError::NonFiniteEye { eye: eye_world });
        }
        CellOrder::BackToFront => Some(index_from_world.transform_point3(eye_world)),
        CellOrder::Unordered => None,
    };
    let local_frustum = frustum.map(|f| f.in_local_frame(&world_from_index));
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
        return Ok(CellBatch::default());
    }

    // Pass 2: emit, bricks and voxels in BSP order.
    let mut cells = Vec::with_capacity(5 * kept_voxels);
    let brick_size = bricks.brick_size as f64;
    let (mut brick_order, mut voxel_order) = ([vec![], vec![], vec![]], [vec![], vec![], vec![]]);
    for axis in 0..3 {
        axis_order(
            0,
            bricks.bricks[axis],
            eye.map(|e| e[axis] / brick_size),
            &mut brick_order[axis],
        );
    }
    for &bz in &brick_order[2] {
        for &by in &brick_order[1] {
            for &bx in &brick_order[0] {
                if !kept[bx + nbx * (by + nby * bz)] {
                    continue;
                }
                for (axis, b) in [bx, by, bz].into_iter().enumerate() {
                    let (start, end) = bricks.voxel_range(b, axis);
                    axis_order(start, end, eye.map(|e| e[axis]), &mut voxel_order[axis]);
                }
                for &k in &voxel_order[2] {
                    for &j in &voxel_order[1] {
                        for &i in &voxel_order[0] {
                            emit_voxel(grid, &point, [i, j, k], eye, &mut cells);
                        }
                    }
                }
            }
        }
    }
    Ok(CellBatch {
        cells,
        bounds_min,
        bounds_max,
    })
}

/// Writes into `order` the slabs `start..end` of one axis: with an eye
/// coordinate (in slab units, slab `s` spanning `[s, s + 1)`), from both far
/// ends towards the eye's slab, the eye's slab last; without one, ascending.
fn axis_order(start: usize, end: usize, eye: Option<f64>, order: &mut Vec<usize>) {
    order.clear();
    let Some(eye) = eye else {
        order.extend(start..end);
        return;
    };
    // The eye's slab, clamped to one slab beyond either end (finite eye).
    let slab = eye.floor().clamp(start as f64 - 1.0, end as f64);
    let below = (slab.max(start as f64) as usize).min(end);
    order.extend(start..below);
    let above = if slab < start as f64 {
        start
    } else {
        (slab as usize + 1).min(end)
    };
    order.extend((above..end).rev());
    if slab >= start as f64 && slab < end as f64 {
        order.push(slab as usize);
    }
}

/// Appends the five tetrahedra of voxel `[i, j, k]`; with an eye (voxel index
/// space) in MPVO order, else in decomposition order.
fn emit_voxel(
    grid: &DensityGrid,
    point: &impl Fn(usize, usize, usize) -> Vec3,
    [i, j, k]: [usize; 3],
    eye: Option<DVec3>,
    cells: &mut Vec<GpuCell>,
) {
    let corner = |v: usize| {
        let (ci, cj, ck) = (i + (v & 1), j + ((v >> 1) & 1), k + ((v >> 2) & 1));
        let p = point(ci, cj, ck);
        [p.x, p.y, p.z, grid.value(ci, cj, ck)]
    };
    let vertices: [[f32; 4]; 8] = std::array::from_fn(corner);
    let cell = |t: &[usize; 4]| GpuCell {
        vertices: t.map(|v| vertices[v]),
    };
    let decomposition = &DECOMPOSITIONS[(i + j + k) % 2];
    let Some(eye) = eye else {
        cells.extend(decomposition.corners.iter().map(|(t, _)| cell(t)));
        cells.push(cell(&decomposition.central));
        return;
    };
    // The eye in the voxel's unit cube; corner tetrahedron with apex `a` lies on
    // the eye's side of its shared face iff Σ |eye − a| < 1 along the axes.
    let local = eye - DVec3::new(i as f64, j as f64, k as f64);
    let in_front = |apex: usize| {
        let distance = |axis: usize, bit: usize| {
            if apex & bit == 0 {
                local[axis]
            } else {
                1.0 - local[axis]
            }
        };
        distance(0, 1) + distance(1, 2) + distance(2, 4) < 1.0
    };
    let mut front = [false; 4];
    for (c, (t, apex)) in decomposition.corners.iter().enumerate() {
        front[c] = in_front(*apex);
        if !front[c] {
            cells.push(cell(t));
        }
    }
    cells.push(cell(&decomposition.central));
    for (c, (t, _)) in decomposition.corners.iter().enumerate() {
        if front[c] {
            cells.push(cell(t));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn order(start: usize, end: usize, eye: Option<f64>) -> Vec<usize> {
        let mut out = vec![];
        axis_order(start, end, eye, &mut out);
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
    }

    #[test]
    fn decompositions_have_one_central_and_four_corner_tetrahedra() {
        for (d, corners) in DECOMPOSITIONS.iter().zip([[0, 3, 5, 6], [1, 2, 4, 7]]) {
            let mut apexes = d.corners.map(|(_, a)| a);
            apexes.sort();
            assert_eq!(apexes, corners);
            for (t, a) in d.corners {
                // The face opposite the apex is a face of the central tetrahedron.
                assert!(t.iter().filter(|&&v| v != a).all(|v| d.central.contains(v)));
            }
        }
    }
}
