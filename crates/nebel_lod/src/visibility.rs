//! Back-to-front visibility order for any conforming tetrahedral mesh (MPVO).
//!
//! MPVO is the Meshed Polyhedra Visibility Ordering of Williams 1992, the
//! visibility sorting of Röttger 2004 §8.1.
//!
//! The GPU draws a batch's cells in buffer order with premultiplied "over"
//! blending, so a sorted (emission-absorption) batch must list every cell
//! before the cells that occlude it. Regular grids get that order by traversal
//! ([`full_resolution_batch`](crate::full_resolution_batch)); any other
//! tetrahedral mesh (the search-light cone of
//! [`search_light_cells`](nebel_core::field::search_light_cells), cells from a
//! scene file) gets it here.
//!
//! [`CellAdjacency::new`] runs once per mesh: it pairs the tetrahedra that
//! share a face (the same three vertex positions, bit for bit) and keeps each
//! face's plane. Degenerate cells ([`Tetrahedron::is_degenerate`]) match no
//! face. [`CellAdjacency::back_to_front`] runs per eye: across each interior
//! face the cell on the far side from the eye goes first, and the constraint
//! graph is sorted topologically (Kahn's algorithm), in time linear in the
//! cells.
//!
//! The order is exact for a convex mesh whose constraint graph is acyclic:
//! Delaunay meshes and regular grids of Kuhn's six tetrahedra per voxel for
//! every eye. A cycle (possible in other meshes) is broken by drawing the
//! remaining cell farthest from the eye next; non-convex meshes are ordered
//! only through shared faces (MPVONC is not implemented); a non-finite eye
//! leaves the input order.
//!
//! Sidedness is invariant under affine maps, so build the adjacency once in the
//! mesh's own frame and pass the eye in that frame; [`sorted_batch`] does this
//! for a [`View`] and emits the cells in world space. Shared vertices must be
//! computed identically for their faces to match.
//!
//! The exactness argument and the limits in full are in
//! `docs/visibility-order.md` in the repository.

use std::collections::HashMap;

use glam::DVec3;
use nebel_core::cell::{Plane, Tetrahedron};

use crate::batch::Cells;
use crate::full_resolution::BatchError;
use crate::view::View;

/// Marks a face slot without a neighbour (a boundary face, or a face of a
/// degenerate cell).
const NO_NEIGHBOUR: usize = usize::MAX;

/// The stored plane of every face of a degenerate cell.
const DEGENERATE_PLANE: Plane = Plane {
    normal: DVec3::ZERO,
    offset: 0.0,
};

/// Marks, in [`CellAdjacency::back_to_front`], a cell placed to break a cycle
/// while it still waited for others.
const PLACED: u8 = u8::MAX;

/// Which tetrahedra of a mesh share a face, and the plane of every face: the
/// per-mesh part of MPVO (module docs). Build it once per mesh with
/// [`CellAdjacency::new`] and keep it while the cells do not move; every eye
/// then costs one [`CellAdjacency::back_to_front`].
///
/// Faces are numbered per cell: face `f` is the face opposite vertex `f`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CellAdjacency {
    /// Per face slot `4 · cell + face`: the neighbour's face slot sharing that
    /// face, or [`NO_NEIGHBOUR`].
    neighbours: Vec<usize>,
    /// Per face slot: its plane with the normal pointing out of its cell (not
    /// normalised); a zero normal for the faces of degenerate cells.
    planes: Vec<Plane>,
    /// Faces shared by two cells, each counted once.
    interior_faces: usize,
}

impl CellAdjacency {
    /// Matches the faces of `cells` (module docs). Costs a sort of the
    /// `4 · cells.len()` faces.
    pub fn new(cells: &[Tetrahedron]) -> Self {
        let mut planes = Vec::with_capacity(4 * cells.len());
        let mut faces = Vec::with_capacity(4 * cells.len());
        // Positions numbered by bit pattern, so faces compare as three ids.
        let mut vertex_ids: HashMap<[u64; 3], u32> = HashMap::with_capacity(cells.len());
        for (cell, tetrahedron) in cells.iter().enumerate() {
            if tetrahedron.is_degenerate() {
                planes.extend([DEGENERATE_PLANE; 4]);
                continue;
            }
            let ids = tetrahedron.positions.map(|p| {
                let next = vertex_ids.len() as u32;
                *vertex_ids.entry(position_key(p)).or_insert(next)
            });
            for face in 0..4 {
                let [a, b, c] = [1, 2, 3].map(|v| tetrahedron.positions[(face + v) % 4]);
                let mut normal = (b - a).cross(c - a);
                if normal.dot(tetrahedron.positions[face] - a) > 0.0 {
                    normal = -normal;
                }
                planes.push(Plane::from_point_normal(a, normal));
                let mut key = [1, 2, 3].map(|v| ids[(face + v) % 4]);
                key.sort_unstable();
                faces.push((key, 4 * cell + face));
            }
        }
        faces.sort_unstable();
        let mut neighbours = vec![NO_NEIGHBOUR; 4 * cells.len()];
        let mut interior_faces = 0;
        for run in faces.chunk_by(|x, y| x.0 == y.0) {
            if let &[(_, first), (_, second)] = run {
                neighbours[first] = second;
                neighbours[second] = first;
                interior_faces += 1;
            }
        }
        Self {
            neighbours,
            planes,
            interior_faces,
        }
    }

    /// Number of cells of the mesh.
    pub fn len(&self) -> usize {
        self.neighbours.len() / 4
    }

    /// Whether the mesh has no cells.
    pub fn is_empty(&self) -> bool {
        self.neighbours.is_empty()
    }

    /// Number of faces shared by two cells, each counted once.
    pub fn interior_face_count(&self) -> usize {
        self.interior_faces
    }

    /// The cell sharing face `face` (0 to 3, opposite vertex `face`) of cell
    /// `cell`; `None` for a boundary face or a degenerate cell. Panics when
    /// `cell` or `face` is out of range.
    pub fn neighbour(&self, cell: usize, face: usize) -> Option<usize> {
        assert!(face < 4, "a tetrahedron has faces 0 to 3, not {face}");
        let other = self.neighbours[4 * cell + face];
        (other != NO_NEIGHBOUR).then_some(other / 4)
    }

    /// The plane of face `face` (0 to 3, opposite vertex `face`) of cell
    /// `cell`, its normal (not normalised) pointing out of the cell: the cell
    /// lies where `normal · p ≤ offset`. `None` for a degenerate cell. Panics
    /// when `cell` or `face` is out of range.
    pub fn face_plane(&self, cell: usize, face: usize) -> Option<Plane> {
        assert!(face < 4, "a tetrahedron has faces 0 to 3, not {face}");
        let plane = self.planes[4 * cell + face];
        (plane.normal != DVec3::ZERO).then_some(plane)
    }

    /// The indices of `cells` in back-to-front order for an eye at `eye`
    /// (world units): a permutation of `0..cells.len()` in which, for every
    /// interior face, the cell on the far side of its plane comes before the
    /// cell on the eye's side. Cycles are broken by the farthest remaining
    /// centroid, and a non-finite eye gives the input order (module docs).
    ///
    /// # Panics
    ///
    /// When `cells` has another length than the mesh this adjacency was built
    /// from (it must be that mesh).
    pub fn back_to_front(&self, cells: &[Tetrahedron], eye: DVec3) -> Vec<usize> {
        assert_eq!(
            cells.len(),
            self.len(),
            "the adjacency was built for {} cells but {} were given",
            self.len(),
            cells.len()
        );
        let count = cells.len();
        if !eye.is_finite() {
            return (0..count).collect();
        }

        // `ahead[slot]`: the slot's cell is drawn before its neighbour.
        // `waiting[cell]`: how many neighbours must be drawn before it.
        let mut ahead = vec![false; self.neighbours.len()];
        let mut waiting = vec![0u8; count];
        for (slot, &other) in self.neighbours.iter().enumerate() {
            // Each interior face once, with its lower slot's plane.
            if other == NO_NEIGHBOUR || other < slot {
                continue;
            }
            let plane = &self.planes[slot];
            let height = plane.normal.dot(eye) - plane.offset;
            if height > 0.0 {
                // The eye is outside the slot's cell, on its neighbour's side.
                ahead[slot] = true;
                waiting[other / 4] += 1;
            } else if height < 0.0 {
                ahead[other] = true;
                waiting[slot / 4] += 1;
            }
        }

        // Kahn's algorithm with `order` as the queue: `order[..head]` done.
        let mut order: Vec<usize> = Vec::with_capacity(count);
        order.extend((0..count).filter(|&cell| waiting[cell] == 0));
        let mut head = 0;
        // Built at the first cycle: cells by centroid distance, farthest
        // first, and how far the search for a waiting one has come.
        let mut by_distance: Option<(Vec<usize>, usize)> = None;
        while order.len() < count {
            if head == order.len() {
                let (cells_by_distance, next) =
                    by_distance.get_or_insert_with(|| (farthest_first(cells, eye), 0));
                while matches!(waiting[cells_by_distance[*next]], 0 | PLACED) {
                    *next += 1;
                }
                let cell = cells_by_distance[*next];
                waiting[cell] = PLACED;
                order.push(cell);
            }
            let cell = order[head];
            head += 1;
            let faces = 4 * cell..4 * cell + 4;
            for (_, &other) in ahead[faces.clone()]
                .iter()
                .zip(&self.neighbours[faces])
                .filter(|(ahead, _)| **ahead)
            {
                let next = other / 4;
                match waiting[next] {
                    PLACED => {}
                    1 => {
                        waiting[next] = 0;
                        order.push(next);
                    }
                    _ => waiting[next] -= 1,
                }
            }
        }
        order
    }
}

/// `cells` (in the mesh's own frame, `adjacency` built from them) reordered
/// back to front for the view's eye with [`CellAdjacency::back_to_front`] in
/// that frame, moved to world space by the view's `world_from_local`, as a
/// batch ([`Cells::from_tetrahedra`], which drops non-finite cells and
/// clamps scalars). The frustum is not read; an empty viewport gives an empty
/// batch (after the checks below).
///
/// Errors: [`BatchError::SingularTransform`] unless `world_from_local` is
/// finite and invertible, [`BatchError::NonFiniteEye`] when the eye (or its
/// image in the mesh's frame) is not finite.
///
/// # Panics
///
/// When `adjacency` was built for a different number of cells.
pub fn sorted_batch(
    cells: &[Tetrahedron],
    adjacency: &CellAdjacency,
    view: &View,
) -> Result<Cells, BatchError> {
    let local_from_world = view
        .local_from_world()
        .ok_or(BatchError::SingularTransform {
            determinant: view.world_from_local.matrix3.determinant(),
        })?;
    let eye = local_from_world.transform_point3(view.eye);
    if !(view.eye.is_finite() && eye.is_finite()) {
        return Err(BatchError::NonFiniteEye { eye: view.eye });
    }
    if view.viewport_is_empty() {
        return Ok(Cells::default());
    }
    let sorted: Vec<Tetrahedron> = adjacency
        .back_to_front(cells, eye)
        .into_iter()
        .map(|cell| view.to_world(&cells[cell]))
        .collect();
    Ok(Cells::from_tetrahedra(&sorted))
}

/// The bit pattern of a position, `-0.0` read as `0.0`.
fn position_key(position: DVec3) -> [u64; 3] {
    position
        .to_array()
        .map(|c| if c == 0.0 { 0 } else { c.to_bits() })
}

/// The indices of `cells` by the distance of their centroid from `eye`,
/// farthest first, ties in index order.
fn farthest_first(cells: &[Tetrahedron], eye: DVec3) -> Vec<usize> {
    let distances: Vec<f64> = cells
        .iter()
        .map(|t| (t.positions.iter().sum::<DVec3>() / 4.0).distance_squared(eye))
        .collect();
    let mut order: Vec<usize> = (0..cells.len()).collect();
    order.sort_by(|&a, &b| distances[b].total_cmp(&distances[a]));
    order
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tetrahedron(offset: DVec3) -> Tetrahedron {
        Tetrahedron {
            positions: [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z].map(|p| p + offset),
            scalars: [0.5; 4],
        }
    }

    /// A plane with the eye (at the origin) `height` outside it.
    fn plane(height: f64) -> Plane {
        Plane {
            normal: DVec3::X,
            offset: -height,
        }
    }

    #[test]
    fn a_cycle_is_broken_at_the_farthest_cell() {
        // Cells 0 → 1 → 2 → 0 ("→": drawn before), through faces given by hand:
        // slots 0 ↔ 4, 5 ↔ 8, 9 ↔ 1; the lower slot's plane decides.
        let mut neighbours = vec![NO_NEIGHBOUR; 12];
        for (a, b) in [(0, 4), (5, 8), (9, 1)] {
            neighbours[a] = b;
            neighbours[b] = a;
        }
        let mut planes = vec![plane(0.0); 12];
        planes[0] = plane(1.0); // eye outside cell 0: 0 before 1
        planes[5] = plane(1.0); // eye outside cell 1: 1 before 2
        planes[1] = plane(-1.0); // eye inside cell 0: 2 before 0
        let adjacency = CellAdjacency {
            neighbours,
            planes,
            interior_faces: 3,
        };
        let at = |x: f64| tetrahedron(DVec3::new(x, 0.0, 0.0));
        let eye = DVec3::ZERO;
        // Cell 2 farthest: it breaks the cycle, then 0 and 1 follow the edges.
        assert_eq!(
            adjacency.back_to_front(&[at(1.0), at(2.0), at(3.0)], eye),
            [2, 0, 1]
        );
        assert_eq!(
            adjacency.back_to_front(&[at(3.0), at(2.0), at(1.0)], eye),
            [0, 1, 2]
        );
        // Equal distances: the lowest index breaks it.
        assert_eq!(
            adjacency.back_to_front(&[at(1.0), at(1.0), at(1.0)], eye),
            [0, 1, 2]
        );
    }

    #[test]
    fn position_keys_ignore_the_sign_of_zero() {
        assert_eq!(
            position_key(DVec3::new(-0.0, 1.0, 0.0)),
            position_key(DVec3::new(0.0, 1.0, -0.0))
        );
        assert_ne!(position_key(DVec3::X), position_key(-DVec3::X));
    }
}
