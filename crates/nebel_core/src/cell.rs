//! Convex cells with a scalar per vertex, their decomposition into tetrahedra and
//! exact ray-cell intersection (Röttger and Ertl 2003 §2-3 and §6, Röttger
//! 2004 ch. 7 and 11).
//!
//! Every volumetric effect ends as cells: [`Tetrahedron`]s for the sorted
//! emission-absorption model, [`Prism`]s (cells between two height fields) and
//! [`Hexahedron`]s (voxels, octree leaves) for the emissive model. Inside a
//! tetrahedron the scalar is the barycentric (linear) interpolation of its four
//! vertex scalars, which is what pre-integration assumes: along any ray the
//! scalar is linear from the entry `s_f` to the exit `s_b`.
//!
//! # Decompositions
//!
//! - A hexahedron splits into five tetrahedra: one central tetrahedron on four
//!   alternate corners and four corner tetrahedra ([`Hexahedron::tetrahedra`]).
//!   There are two such decompositions, mirror images of each other; which one
//!   a grid cell uses follows the parity `(i + j + k) mod 2` of its integer
//!   position ([`HexahedronParity::of_cell`]). Every face diagonal of one
//!   decomposition then coincides with the face diagonal its neighbour uses on the
//!   shared face, so the tetrahedral mesh conforms (Röttger and Ertl 2003 §3, Figure 1).
//!   The search-light cone uses it.
//! - A hexahedron also splits into six tetrahedra around its diagonal from
//!   corner 0 to corner 7, one per ordering of the axes
//!   ([`Hexahedron::kuhn_tetrahedra`], [`KUHN_TETRAHEDRA`], their field
//!   [`kuhn_value`]; Kuhn 1960; Freudenthal 1942). Every cell
//!   uses the same one, whose face diagonals all run from a face's lowest
//!   corner to its highest, so a grid conforms without alternating. Unlike
//!   the five-tetrahedron one it is **nested**: halving a box's edges and
//!   splitting the eight halves the same way splits each of the box's six
//!   tetrahedra into eight of the halves' (Bey, "Simplicial grid refinement",
//!   2000). So the piecewise-linear field of a box equals, everywhere, the
//!   field its halves interpolate from its own values at their corners. The
//!   density grids and their octrees use it: that is what lets a refining
//!   octree change its field continuously.
//! - A prism splits into three tetrahedra ([`Prism::tetrahedra`]). Each
//!   quadrilateral side face is cut by the diagonal that runs from the bottom
//!   vertex with the smaller global id to the top vertex with the larger one.
//!   Two prisms sharing a side face share its two ids and therefore its
//!   diagonal, for any numbering (Dompierre et al., "How to subdivide pyramids,
//!   prisms and hexahedra into tetrahedra", 1999). Over a terrain grid the id is
//!   the grid point index, which gives the alternating pattern of Röttger and Ertl 2003 §6.
//!
//! # Ray-cell intersection
//!
//! [`Tetrahedron::intersect`] clips the ray against the four face planes
//! (Cyrus–Beck) and evaluates the barycentric coordinates of the entry and exit
//! points from the same plane equations, so `s_f` and `s_b` are exact up to
//! rounding. Prisms and hexahedra intersect through their tetrahedra: entry and
//! exit are the first entry and last exit over the pieces, each with the scalar
//! of the tetrahedron it lies in. Inside a prism or hexahedron the scalar along
//! the ray is only piecewise linear; consumers that need the exact integral (the
//! reference renderer) decompose into tetrahedra first.
//!
//! # Degenerate input
//!
//! A tetrahedron whose volume is below [`DEGENERATE_VOLUME_RATIO`] times the
//! cube of its longest edge (zero volume, slivers, repeated vertices), or that
//! has a non-finite position or scalar, is never hit: intersection returns
//! `None`. A ray grazing an edge or a vertex returns a zero-length segment. No
//! function here returns NaN.

use glam::DVec3;

/// A tetrahedron is treated as degenerate (never hit by a ray) when
/// `6 · |volume| ≤ DEGENERATE_VOLUME_RATIO · (longest edge)³`.
///
/// A regular tetrahedron has a ratio of about 0.7, so this only rejects cells
/// flat to twelve digits, where barycentric coordinates lose all precision.
pub const DEGENERATE_VOLUME_RATIO: f64 = 1e-12;

/// A ray `origin + t · direction`, `t` a distance along the ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Start of the ray, world units.
    pub origin: DVec3,
    /// Direction, unit length, so `t` is measured in world units.
    pub direction: DVec3,
}

impl Ray {
    /// A ray from `origin` towards `direction` (normalised here). `None` when the
    /// direction has zero length or either vector is not finite.
    pub fn new(origin: DVec3, direction: DVec3) -> Option<Self> {
        let direction = direction.try_normalize()?;
        origin.is_finite().then_some(Self { origin, direction })
    }

    /// The point at distance `t` along the ray.
    pub fn at(&self, t: f64) -> DVec3 {
        self.origin + t * self.direction
    }
}

/// An oriented plane `normal · p = offset`. Its "front" side is `normal · p ≥ offset`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plane {
    /// Normal, pointing to the side that clipping keeps; any non-zero length.
    pub normal: DVec3,
    /// `normal · p` of any point `p` on the plane.
    pub offset: f64,
}

impl Plane {
    /// The plane through `point` with `normal` pointing to the kept side.
    pub fn from_point_normal(point: DVec3, normal: DVec3) -> Self {
        Self {
            normal,
            offset: normal.dot(point),
        }
    }
}

/// The part of a ray inside a cell: entry and exit distance along the ray and
/// the interpolated scalar at each. Always `t_entry ≤ t_exit`; equal for a ray
/// that grazes an edge or a vertex.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CellSegment {
    /// Distance along the ray where it enters the cell, world units.
    pub t_entry: f64,
    /// Distance along the ray where it leaves the cell, world units.
    pub t_exit: f64,
    /// Scalar `s_f` at the entry point.
    pub s_entry: f64,
    /// Scalar `s_b` at the exit point.
    pub s_exit: f64,
}

impl CellSegment {
    /// Length of the segment, `t_exit − t_entry` (≥ 0), world units.
    pub fn length(&self) -> f64 {
        self.t_exit - self.t_entry
    }

    /// The scalar at distance `t` (linear between entry and exit; a
    /// zero-length segment returns its entry scalar).
    pub fn scalar_at(&self, t: f64) -> f64 {
        let length = self.length();
        if length <= 0.0 {
            return self.s_entry;
        }
        let x = ((t - self.t_entry) / length).clamp(0.0, 1.0);
        self.s_entry + (self.s_exit - self.s_entry) * x
    }

    /// The part of the segment with `t_min ≤ t ≤ t_max`, scalars interpolated
    /// linearly at the new ends. `None` when nothing is left; a single point
    /// left gives a zero-length segment.
    pub fn clip_to_range(&self, t_min: f64, t_max: f64) -> Option<CellSegment> {
        let t_entry = self.t_entry.max(t_min);
        let t_exit = self.t_exit.min(t_max);
        (t_entry <= t_exit).then(|| CellSegment {
            t_entry,
            t_exit,
            s_entry: self.scalar_at(t_entry),
            s_exit: self.scalar_at(t_exit),
        })
    }

    /// The part of the segment of `ray` on the front side of `plane`
    /// (`normal · p ≥ offset`). A near plane keeps what lies beyond it
    /// (normal along the view direction); an opaque depth keeps what lies before
    /// it (normal against the view direction). A ray parallel to the plane keeps
    /// all or nothing. `None` when nothing is left or the plane is not finite.
    pub fn clip_to_plane(&self, ray: &Ray, plane: &Plane) -> Option<CellSegment> {
        let (t_min, t_max) = half_space_range(ray, plane.normal, plane.offset)?;
        self.clip_to_range(t_min, t_max)
    }
}

/// The range of `t` where `normal · ray.at(t) ≥ offset`, or `None` if empty.
fn half_space_range(ray: &Ray, normal: DVec3, offset: f64) -> Option<(f64, f64)> {
    if !normal.is_finite() || !offset.is_finite() {
        return None;
    }
    let along = normal.dot(ray.direction);
    let distance = normal.dot(ray.origin) - offset;
    if along.abs() <= f64::EPSILON * normal.length() {
        return (distance >= 0.0).then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let t = -distance / along;
    if !t.is_finite() {
        return None;
    }
    Some(if along > 0.0 {
        (t, f64::INFINITY)
    } else {
        (f64::NEG_INFINITY, t)
    })
}

/// A tetrahedron with a scalar per vertex, linear inside.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tetrahedron {
    /// Vertex positions, world units, any orientation.
    pub positions: [DVec3; 4],
    /// Scalar per vertex (density `s`, normally in [0, 1]).
    pub scalars: [f64; 4],
}

impl Tetrahedron {
    /// Signed volume `(b − a) · ((c − a) × (d − a)) / 6` of the vertices
    /// `a, b, c, d`, world units cubed; positive for a right-handed order.
    pub fn signed_volume(&self) -> f64 {
        let [a, b, c, d] = self.positions;
        (b - a).dot((c - a).cross(d - a)) / 6.0
    }

    /// Volume, world units cubed (≥ 0).
    pub fn volume(&self) -> f64 {
        self.signed_volume().abs()
    }

    /// Whether the tetrahedron is degenerate (see [`DEGENERATE_VOLUME_RATIO`])
    /// or has a non-finite position or scalar. Degenerate cells are never hit.
    pub fn is_degenerate(&self) -> bool {
        if !self.positions.iter().all(|p| p.is_finite())
            || !self.scalars.iter().all(|s| s.is_finite())
        {
            return true;
        }
        let [a, b, c, d] = self.positions;
        let longest_squared = [b - a, c - a, d - a, c - b, d - b, d - c]
            .iter()
            .map(|e| e.length_squared())
            .fold(0.0, f64::max);
        let scale = longest_squared * longest_squared.sqrt();
        let well_shaped = 6.0 * self.volume() > DEGENERATE_VOLUME_RATIO * scale;
        !well_shaped
    }

    /// The tetrahedron with its face planes precomputed, for many ray queries;
    /// `None` when it is degenerate ([`Tetrahedron::is_degenerate`]).
    pub fn prepare(&self) -> Option<PreparedTetrahedron> {
        if self.is_degenerate() {
            return None;
        }
        let p = self.positions;
        let faces = std::array::from_fn(|i| {
            let a = p[(i + 1) % 4];
            let b = p[(i + 2) % 4];
            let c = p[(i + 3) % 4];
            // Unit outward normal: the vertex opposite lies on the inner side.
            let mut normal = (b - a).cross(c - a).normalize();
            if normal.dot(p[i] - a) > 0.0 {
                normal = -normal;
            }
            let offset = normal.dot(a);
            FacePlane {
                normal,
                offset,
                vertex_height: normal.dot(p[i]) - offset,
            }
        });
        Some(PreparedTetrahedron {
            faces,
            scalars: self.scalars,
        })
    }

    /// Where `ray` passes through the tetrahedron, over the whole line
    /// (negative `t` included; clip with [`CellSegment::clip_to_range`]).
    ///
    /// Exact: the entry and exit come from the face planes and the scalars from
    /// the barycentric coordinates at those points (clamped into [0, 1] against
    /// rounding, so `s` stays within the vertex scalars). `None` for a miss or a
    /// degenerate tetrahedron; a zero-length segment when the ray only touches an
    /// edge or a vertex. For many rays, [`Tetrahedron::prepare`] once instead.
    pub fn intersect(&self, ray: &Ray) -> Option<CellSegment> {
        self.prepare()?.intersect(ray)
    }
}

/// One face plane of a prepared tetrahedron: unit `normal` pointing out,
/// `normal · p ≤ offset` inside, and `vertex_height = normal · v − offset` (< 0)
/// of the vertex opposite.
#[derive(Clone, Copy, Debug, PartialEq)]
struct FacePlane {
    normal: DVec3,
    offset: f64,
    vertex_height: f64,
}

/// A non-degenerate [`Tetrahedron`] with its four face planes precomputed, so
/// that each ray query costs a few dot products. Build it with
/// [`Tetrahedron::prepare`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PreparedTetrahedron {
    faces: [FacePlane; 4],
    scalars: [f64; 4],
}

impl PreparedTetrahedron {
    /// Where `ray` passes through the tetrahedron; see [`Tetrahedron::intersect`].
    pub fn intersect(&self, ray: &Ray) -> Option<CellSegment> {
        if !ray.origin.is_finite() || !ray.direction.is_finite() {
            return None;
        }
        let (mut t_entry, mut t_exit) = (f64::NEG_INFINITY, f64::INFINITY);
        for face in &self.faces {
            let along = face.normal.dot(ray.direction);
            let height = face.normal.dot(ray.origin) - face.offset;
            if along.abs() <= f64::EPSILON {
                // Parallel to the face: inside or outside along the whole line.
                if height > 0.0 {
                    return None;
                }
                continue;
            }
            let t = -height / along;
            if along > 0.0 {
                t_exit = t_exit.min(t);
            } else {
                t_entry = t_entry.max(t);
            }
        }
        if !t_entry.is_finite() || !t_exit.is_finite() || t_entry > t_exit {
            return None;
        }
        Some(CellSegment {
            t_entry,
            t_exit,
            s_entry: self.scalar_at(ray.at(t_entry)),
            s_exit: self.scalar_at(ray.at(t_exit)),
        })
    }

    /// Barycentric scalar at a point on or in the tetrahedron, the weights
    /// clamped into [0, 1] and renormalised against rounding.
    fn scalar_at(&self, point: DVec3) -> f64 {
        let weights = self.faces.map(|face| {
            ((face.normal.dot(point) - face.offset) / face.vertex_height).clamp(0.0, 1.0)
        });
        let total: f64 = weights.iter().sum();
        if total <= 0.0 {
            return self.scalars.iter().sum::<f64>() / 4.0;
        }
        weights
            .iter()
            .zip(self.scalars)
            .map(|(w, s)| w * s)
            .sum::<f64>()
            / total
    }
}

/// Entry and exit over a set of tetrahedra tiling a convex cell.
fn intersect_pieces(pieces: &[Tetrahedron], ray: &Ray) -> Option<CellSegment> {
    pieces
        .iter()
        .filter_map(|piece| piece.intersect(ray))
        .reduce(|a, b| {
            let (t_entry, s_entry) = if b.t_entry < a.t_entry {
                (b.t_entry, b.s_entry)
            } else {
                (a.t_entry, a.s_entry)
            };
            let (t_exit, s_exit) = if b.t_exit > a.t_exit {
                (b.t_exit, b.s_exit)
            } else {
                (a.t_exit, a.s_exit)
            };
            CellSegment {
                t_entry,
                t_exit,
                s_entry,
                s_exit,
            }
        })
}

/// A triangular prism: a bottom triangle `0, 1, 2` and a top triangle `3, 4, 5`,
/// vertex `i + 3` above vertex `i` (ground fog over a terrain triangle, Röttger and Ertl 2003 §6).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prism {
    /// Vertex positions, world units: bottom `0..3`, top `3..6`.
    pub positions: [DVec3; 6],
    /// Scalar per vertex.
    pub scalars: [f64; 6],
}

impl Prism {
    /// Splits the prism into three tetrahedra.
    ///
    /// `vertex_ids` are global ids of the three vertical edges (e.g. terrain grid
    /// point indices); they must be distinct. Each side face is cut from the
    /// bottom vertex with the smaller id to the top vertex with the larger id, so
    /// neighbouring prisms conform (see the module docs). With the edges sorted
    /// by id as `a < b < c` (tops `a', b', c'`) the pieces are
    /// `(a, b, c, c')`, `(a, b, b', c')` and `(a, a', b', c')`.
    pub fn tetrahedra(&self, vertex_ids: [u64; 3]) -> [Tetrahedron; 3] {
        let mut order = [0usize, 1, 2];
        order.sort_by_key(|&i| vertex_ids[i]);
        let [a, b, c] = order;
        let piece = |indices: [usize; 4]| Tetrahedron {
            positions: indices.map(|i| self.positions[i]),
            scalars: indices.map(|i| self.scalars[i]),
        };
        [
            piece([a, b, c, c + 3]),
            piece([a, b, b + 3, c + 3]),
            piece([a, a + 3, b + 3, c + 3]),
        ]
    }

    /// Volume of the prism as the solid swept by linear interpolation between
    /// the bottom and top triangles (the wedge element), world units cubed.
    ///
    /// Exact: the Jacobian is linear over the triangle and quadratic in height,
    /// so the centroid rule times two-point Gauss–Legendre integrates it exactly.
    /// Equals the polyhedral volume when the side faces are planar (vertical
    /// prisms over terrain); then it also equals the sum over
    /// [`Prism::tetrahedra`] for either diagonal choice.
    pub fn volume(&self) -> f64 {
        let p = self.positions;
        let gauss = 0.5 / 3f64.sqrt();
        let mut volume = 0.0;
        for height in [0.5 - gauss, 0.5 + gauss] {
            let edge = |i: usize| (1.0 - height) * (p[i] - p[0]) + height * (p[i + 3] - p[3]);
            let rise = (p[3] + p[4] + p[5] - p[0] - p[1] - p[2]) / 3.0;
            // Reference triangle area 1/2, Gauss weights 1/2 each.
            volume += 0.25 * edge(1).cross(edge(2)).dot(rise);
        }
        volume.abs()
    }

    /// Where `ray` passes through the prism, via [`Prism::tetrahedra`]: the first
    /// entry and last exit over the three pieces, each with the scalar of the
    /// piece it lies in. Inside, the scalar is piecewise linear. `None` for a miss.
    pub fn intersect(&self, ray: &Ray, vertex_ids: [u64; 3]) -> Option<CellSegment> {
        intersect_pieces(&self.tetrahedra(vertex_ids), ray)
    }
}

/// Which of the two five-tetrahedron decompositions a hexahedron uses.
///
/// Vertices are numbered `x + 2y + 4z` for local corner bits `x, y, z ∈ {0, 1}`.
/// [`HexahedronParity::Even`] puts the central tetrahedron on corners
/// `1, 2, 4, 7`; [`HexahedronParity::Odd`] (its mirror in x) on `0, 3, 5, 6`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum HexahedronParity {
    /// Central tetrahedron on corners 1, 2, 4, 7. The default.
    #[default]
    Even,
    /// Central tetrahedron on corners 0, 3, 5, 6.
    Odd,
}

impl HexahedronParity {
    /// The parity of grid cell `(i, j, k)`: `Even` when `i + j + k` is even. Face
    /// neighbours then alternate and share their face diagonals.
    pub fn of_cell(i: i64, j: i64, k: i64) -> Self {
        if (i + j + k).rem_euclid(2) == 0 {
            Self::Even
        } else {
            Self::Odd
        }
    }
}

/// Kuhn's six tetrahedra of a hexahedron ([`Hexahedron::kuhn_tetrahedra`]),
/// as corner indices `x + 2y + 4z`: for the axis ordering `(a, b, c)` (from
/// `[x, y, z]`), the tetrahedron of the unit cube's points with
/// `u_a ≥ u_b ≥ u_c`, on corners `0`, `a`, `a + b` and `7` (for an odd
/// ordering the middle two swapped, so that all six have positive volume like
/// the five-tetrahedron pieces). Listed with `a` slowest and `b` next. Two listed tetrahedra share a face exactly when their
/// orderings differ by swapping two neighbours (`a, b` or `b, c`); the face
/// lies in the plane `u_a = u_b` (or `u_b = u_c`) through the diagonal.
pub const KUHN_TETRAHEDRA: [[usize; 4]; 6] = kuhn_tetrahedra();

/// The axis orderings of [`KUHN_TETRAHEDRA`], in its order.
pub const KUHN_AXIS_ORDERS: [[usize; 3]; 6] = [
    [0, 1, 2],
    [0, 2, 1],
    [1, 0, 2],
    [1, 2, 0],
    [2, 0, 1],
    [2, 1, 0],
];

const fn kuhn_tetrahedra() -> [[usize; 4]; 6] {
    let mut tetrahedra = [[0; 4]; 6];
    let mut t = 0;
    while t < 6 {
        let [a, b, c] = KUHN_AXIS_ORDERS[t];
        let (side, diagonal) = (1 << a, (1 << a) | (1 << b));
        // (a, b, c) is an even permutation of (x, y, z) iff it is a rotation.
        let even = (a + 1) % 3 == b && (b + 1) % 3 == c;
        tetrahedra[t] = if even {
            [0, side, diagonal, 7]
        } else {
            [0, diagonal, side, 7]
        };
        t += 1;
    }
    tetrahedra
}

/// The piecewise-linear field of Kuhn's tetrahedra ([`KUHN_TETRAHEDRA`]) in
/// a box with corner values `values` (corner `x + 2y + 4z`) at local
/// coordinates `u` in [0, 1]³, in closed form: with the axes ordered `u_a ≥
/// u_b ≥ u_c`, the barycentric weights of corners 0, `e_a`, `e_a + e_b` and 7
/// are `1 − u_a`, `u_a − u_b`, `u_b − u_c` and `u_c`.
pub fn kuhn_value(values: &[f64; 8], u: DVec3) -> f64 {
    let mut axes = [0, 1, 2];
    axes.sort_by(|&a, &b| u[b].total_cmp(&u[a]));
    let [a, b, c] = axes;
    let (side, diagonal) = (1 << a, (1 << a) | (1 << b));
    values[0] * (1.0 - u[a])
        + values[side] * (u[a] - u[b])
        + values[diagonal] * (u[b] - u[c])
        + values[7] * u[c]
}

/// A hexahedron (voxel or general convex cell with 8 corners), corner
/// `x + 2y + 4z` at local corner bits `x, y, z ∈ {0, 1}`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hexahedron {
    /// Corner positions, world units, indexed `x + 2y + 4z`.
    pub positions: [DVec3; 8],
    /// Scalar per corner, same indexing.
    pub scalars: [f64; 8],
}

impl Hexahedron {
    /// The axis-aligned box with minimum corner `min` and edge lengths `size`
    /// (a voxel), corner `x + 2y + 4z` at `min + (x, y, z) · size`.
    pub fn axis_aligned(min: DVec3, size: DVec3, scalars: [f64; 8]) -> Self {
        let positions = std::array::from_fn(|v| {
            let bits = DVec3::new((v & 1) as f64, ((v >> 1) & 1) as f64, ((v >> 2) & 1) as f64);
            min + bits * size
        });
        Self { positions, scalars }
    }

    /// Splits the hexahedron into five tetrahedra: four corner tetrahedra and a
    /// central one, arranged by `parity` (see [`HexahedronParity`]). The central
    /// tetrahedron comes last.
    pub fn tetrahedra(&self, parity: HexahedronParity) -> [Tetrahedron; 5] {
        // Even parity; Odd mirrors every corner in x (v ^ 1).
        const EVEN: [[usize; 4]; 5] = [
            [0, 1, 2, 4],
            [3, 2, 1, 7],
            [5, 4, 7, 1],
            [6, 7, 4, 2],
            [1, 2, 4, 7],
        ];
        let flip = match parity {
            HexahedronParity::Even => 0,
            HexahedronParity::Odd => 1,
        };
        EVEN.map(|corners| {
            let corners = corners.map(|v| v ^ flip);
            Tetrahedron {
                positions: corners.map(|v| self.positions[v]),
                scalars: corners.map(|v| self.scalars[v]),
            }
        })
    }

    /// Splits the hexahedron into Kuhn's six tetrahedra around its diagonal
    /// from corner 0 to corner 7, in the order of [`KUHN_TETRAHEDRA`] (see the
    /// module docs: the same in every cell, conforming and nested).
    pub fn kuhn_tetrahedra(&self) -> [Tetrahedron; 6] {
        KUHN_TETRAHEDRA.map(|corners| Tetrahedron {
            positions: corners.map(|v| self.positions[v]),
            scalars: corners.map(|v| self.scalars[v]),
        })
    }

    /// Volume of the trilinear hexahedron (the solid swept by trilinear
    /// interpolation of the corners), world units cubed.
    ///
    /// Exact: the Jacobian determinant has degree ≤ 2 in each local coordinate,
    /// so 2×2×2 Gauss–Legendre integrates it exactly. Equals the polyhedral volume
    /// when the faces are planar (boxes, frusta), and then also the sum over
    /// [`Hexahedron::tetrahedra`] in either parity.
    pub fn volume(&self) -> f64 {
        let p = self.positions;
        let gauss = 0.5 / 3f64.sqrt();
        let nodes = [0.5 - gauss, 0.5 + gauss];
        let mut volume = 0.0;
        for &z in &nodes {
            for &y in &nodes {
                for &x in &nodes {
                    // Partial derivatives of the trilinear map at (x, y, z).
                    let lerp = |a: DVec3, b: DVec3, w: f64| a + (b - a) * w;
                    let dx = lerp(
                        lerp(p[1] - p[0], p[3] - p[2], y),
                        lerp(p[5] - p[4], p[7] - p[6], y),
                        z,
                    );
                    let dy = lerp(
                        lerp(p[2] - p[0], p[3] - p[1], x),
                        lerp(p[6] - p[4], p[7] - p[5], x),
                        z,
                    );
                    let dz = lerp(
                        lerp(p[4] - p[0], p[5] - p[1], x),
                        lerp(p[6] - p[2], p[7] - p[3], x),
                        y,
                    );
                    volume += dx.cross(dy).dot(dz) / 8.0;
                }
            }
        }
        volume.abs()
    }

    /// Where `ray` passes through the hexahedron, via its five tetrahedra in
    /// `parity`: first entry and last exit, each with the scalar of the piece it
    /// lies in. Inside, the scalar is piecewise linear. `None` for a miss.
    pub fn intersect(&self, ray: &Ray, parity: HexahedronParity) -> Option<CellSegment> {
        intersect_pieces(&self.tetrahedra(parity), ray)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn unit_tetrahedron() -> Tetrahedron {
        Tetrahedron {
            positions: [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z],
            scalars: [0.1, 0.9, 0.4, 0.6],
        }
    }

    /// Barycentric scalar at a point, computed independently by solving the
    /// 3×3 system, and whether the point is inside.
    fn brute_force_scalar(tet: &Tetrahedron, point: DVec3) -> Option<f64> {
        let [a, b, c, d] = tet.positions;
        let m = glam::DMat3::from_cols(b - a, c - a, d - a);
        let l = m.inverse() * (point - a);
        let weights = [1.0 - l.x - l.y - l.z, l.x, l.y, l.z];
        weights.iter().all(|&w| w >= -1e-12).then(|| {
            weights
                .iter()
                .zip(tet.scalars)
                .map(|(w, s)| w * s)
                .sum::<f64>()
        })
    }

    fn coordinate() -> impl Strategy<Value = f64> {
        -10.0..10.0f64
    }

    fn point() -> impl Strategy<Value = DVec3> {
        (coordinate(), coordinate(), coordinate()).prop_map(|(x, y, z)| DVec3::new(x, y, z))
    }

    /// A convex hexahedron with planar faces: the unit cube under a random
    /// projective map whose denominator stays positive over the cube.
    fn convex_hexahedron() -> impl Strategy<Value = Hexahedron> {
        (
            prop::array::uniform9(-1.0..1.0f64),
            point(),
            prop::array::uniform3(-0.3..0.3f64),
        )
            .prop_filter_map("singular map", |(m, shift, perspective)| {
                let linear = glam::DMat3::from_cols_array(&m) + glam::DMat3::IDENTITY * 1.5;
                // The homogeneous map [[linear, shift], [perspective, 1]] must be
                // regular: its Schur complement is linear − shift ⊗ perspective.
                let schur = linear
                    - glam::DMat3::from_cols(
                        shift * perspective[0],
                        shift * perspective[1],
                        shift * perspective[2],
                    );
                (linear.determinant().abs() > 0.1 && schur.determinant().abs() > 0.1).then(|| {
                    let cube = Hexahedron::axis_aligned(DVec3::ZERO, DVec3::ONE, [0.0; 8]);
                    let positions = cube.positions.map(|p| {
                        let w = 1.0 + DVec3::from(perspective).dot(p);
                        (linear * p + shift) / w
                    });
                    Hexahedron {
                        positions,
                        scalars: [0.0; 8],
                    }
                })
            })
    }

    proptest! {
        #[test]
        fn box_decompositions_sum_to_box_volume(
            min in point(),
            size in (0.01..5.0f64, 0.01..5.0f64, 0.01..5.0f64),
        ) {
            let size = DVec3::new(size.0, size.1, size.2);
            let hex = Hexahedron::axis_aligned(min, size, [0.0; 8]);
            let expected = size.x * size.y * size.z;
            prop_assert!((hex.volume() - expected).abs() <= 1e-12 * expected.max(1.0));
            for parity in [HexahedronParity::Even, HexahedronParity::Odd] {
                let sum: f64 = hex.tetrahedra(parity).iter().map(Tetrahedron::volume).sum();
                prop_assert!((sum - expected).abs() <= 1e-9 * expected.max(1.0));
            }
            let sum: f64 = hex.kuhn_tetrahedra().iter().map(Tetrahedron::volume).sum();
            prop_assert!((sum - expected).abs() <= 1e-9 * expected.max(1.0));
        }

        #[test]
        fn convex_hexahedron_decompositions_sum_to_volume(hex in convex_hexahedron()) {
            let volume = hex.volume();
            let decompositions = [
                hex.tetrahedra(HexahedronParity::Even).to_vec(),
                hex.tetrahedra(HexahedronParity::Odd).to_vec(),
                hex.kuhn_tetrahedra().to_vec(),
            ];
            for pieces in decompositions {
                let sum: f64 = pieces.iter().map(Tetrahedron::volume).sum();
                let signed: f64 = pieces.iter().map(Tetrahedron::signed_volume).sum();
                prop_assert!((sum - volume).abs() <= 1e-9 * volume.max(1.0), "{sum} vs {volume}");
                // All pieces have the same orientation: no overlap, no inversion.
                prop_assert!((signed.abs() - sum).abs() <= 1e-9 * volume.max(1.0));
            }
        }

        #[test]
        fn vertical_prism_decomposition_sums_to_volume(
            base in prop::array::uniform3((coordinate(), coordinate(), coordinate())),
            heights in prop::array::uniform3(0.0..5.0f64),
            ids in prop::array::uniform3(0u64..1000),
        ) {
            prop_assume!(ids[0] != ids[1] && ids[1] != ids[2] && ids[0] != ids[2]);
            let bottom = base.map(|(x, y, z)| DVec3::new(x, y, z));
            let positions = [
                bottom[0], bottom[1], bottom[2],
                bottom[0] + DVec3::Y * heights[0],
                bottom[1] + DVec3::Y * heights[1],
                bottom[2] + DVec3::Y * heights[2],
            ];
            let prism = Prism { positions, scalars: [0.0; 6] };
            let volume = prism.volume();
            let sum: f64 = prism.tetrahedra(ids).iter().map(Tetrahedron::volume).sum();
            prop_assert!((sum - volume).abs() <= 1e-9 * volume.max(1.0), "{sum} vs {volume}");
            // Independent closed form: projected base area times mean height.
            let area = 0.5 * (bottom[1] - bottom[0]).cross(bottom[2] - bottom[0]).y.abs();
            let mean_height = heights.iter().sum::<f64>() / 3.0;
            prop_assert!((volume - area * mean_height).abs() <= 1e-9 * volume.max(1.0));
        }

        #[test]
        fn ray_tetrahedron_matches_brute_force_sampling(
            origin in point(),
            target in (0.0..1.0f64, 0.0..1.0f64, 0.0..1.0f64),
            scalars in prop::array::uniform4(0.0..1.0f64),
        ) {
            let tet = Tetrahedron { scalars, ..unit_tetrahedron() };
            let target = DVec3::new(target.0, target.1, target.2) * 0.5;
            let Some(ray) = Ray::new(origin, target - origin) else { return Ok(()) };
            let segment = tet.intersect(&ray);
            // Sample the line densely; every inside sample must lie in the
            // segment with the segment's scalar.
            let steps = 4000;
            let mut inside_samples = 0;
            for step in 0..=steps {
                let t = -30.0 + 60.0 * step as f64 / steps as f64;
                if let Some(s) = brute_force_scalar(&tet, ray.at(t)) {
                    inside_samples += 1;
                    let seg = segment.expect("a sample inside but no segment");
                    prop_assert!(t >= seg.t_entry - 1e-9 && t <= seg.t_exit + 1e-9);
                    prop_assert!((seg.scalar_at(t) - s).abs() < 1e-9);
                }
            }
            if let Some(seg) = segment {
                for t in [seg.t_entry, seg.t_exit] {
                    let s = brute_force_scalar(&tet, ray.at(t)).expect("end point outside");
                    prop_assert!((seg.scalar_at(t) - s).abs() < 1e-9);
                }
                // Long segments must have been seen by the sampling.
                prop_assert!(seg.length() < 0.03 || inside_samples > 0);
            }
        }

        #[test]
        fn random_cells_and_rays_never_give_nan(
            positions in prop::array::uniform4(point()),
            origin in point(),
            direction in point(),
        ) {
            let tet = Tetrahedron { positions, scalars: [0.0, 1.0, 0.5, 0.25] };
            if let Some(ray) = Ray::new(origin, direction)
                && let Some(seg) = tet.intersect(&ray)
            {
                for value in [seg.t_entry, seg.t_exit, seg.s_entry, seg.s_exit] {
                    prop_assert!(value.is_finite());
                }
                prop_assert!(seg.t_entry <= seg.t_exit);
                prop_assert!((0.0..=1.0).contains(&seg.s_entry) && (0.0..=1.0).contains(&seg.s_exit));
            }
        }
    }

    #[test]
    fn neighbouring_hexahedra_share_face_diagonals() {
        // Diagonals of a face are the edges of the pieces that join opposite
        // corners of that face; compare them as world-space point pairs.
        fn face_diagonals(pieces: &[Tetrahedron], axis: usize, side: f64) -> Vec<[[i64; 3]; 2]> {
            let mut diagonals = Vec::new();
            for tet in pieces {
                for i in 0..4 {
                    for j in i + 1..4 {
                        let (a, b) = (tet.positions[i], tet.positions[j]);
                        let on_face = a[axis] == side && b[axis] == side;
                        let differing = (0..3).filter(|&k| a[k] != b[k]).count();
                        if on_face && differing == 2 {
                            let key = |p: DVec3| p.to_array().map(|c| c.round() as i64);
                            let mut pair = [key(a), key(b)];
                            pair.sort();
                            diagonals.push(pair);
                        }
                    }
                }
            }
            diagonals.sort();
            diagonals.dedup();
            diagonals
        }
        for (i, j, k) in [(0, 0, 0), (1, 0, 0), (3, 2, 5), (-1, 4, 2)] {
            let cell = |c: [i64; 3]| {
                Hexahedron::axis_aligned(
                    DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64),
                    DVec3::ONE,
                    [0.0; 8],
                )
            };
            let here = [i, j, k];
            let parity = HexahedronParity::of_cell(i, j, k);
            for axis in 0..3 {
                let mut next = here;
                next[axis] += 1;
                let neighbour_parity = HexahedronParity::of_cell(next[0], next[1], next[2]);
                assert_ne!(parity, neighbour_parity);
                let side = (here[axis] + 1) as f64;
                let ours = face_diagonals(&cell(here).tetrahedra(parity), axis, side);
                let theirs = face_diagonals(&cell(next).tetrahedra(neighbour_parity), axis, side);
                assert_eq!(ours.len(), 1, "one diagonal per face");
                assert_eq!(ours, theirs, "cell {here:?} axis {axis}");
                // Kuhn's decomposition is the same in every cell and conforms too.
                let ours = face_diagonals(&cell(here).kuhn_tetrahedra(), axis, side);
                let theirs = face_diagonals(&cell(next).kuhn_tetrahedra(), axis, side);
                assert_eq!(ours.len(), 1, "one Kuhn diagonal per face");
                assert_eq!(ours, theirs, "Kuhn cell {here:?} axis {axis}");
            }
        }
    }

    /// [`kuhn_value`] of the box `min + [0, size]³` at `p`.
    fn kuhn_field(min: DVec3, size: f64, scalars: &[f64; 8], p: DVec3) -> f64 {
        kuhn_value(scalars, (p - min) / size)
    }

    proptest! {
        /// `kuhn_tetrahedra` interpolates the closed form, and the field of a
        /// box equals, at every point, that of its eight halves given the
        /// box's own field at their corners: the decomposition is nested, so
        /// refining a box by its own field changes nothing.
        #[test]
        fn kuhn_decomposition_is_the_closed_form_and_nested(
            min in point(),
            size in 0.01..5.0f64,
            scalars in prop::array::uniform8(0.0..1.0f64),
            local in prop::array::uniform3(0.0..1.0f64),
        ) {
            let p = min + DVec3::from(local) * size;
            let expected = kuhn_field(min, size, &scalars, p);
            let hex = Hexahedron::axis_aligned(min, DVec3::splat(size), scalars);
            let through_pieces: Vec<f64> = hex
                .kuhn_tetrahedra()
                .iter()
                .filter_map(|tet| brute_force_scalar(tet, p))
                .collect();
            prop_assert!(!through_pieces.is_empty());
            for s in through_pieces {
                prop_assert!((s - expected).abs() <= 1e-9, "{s} vs {expected}");
            }
            // The half holding p, and its corners' values from the box's field.
            let half = 0.5 * size;
            let half_min = min + DVec3::from(local.map(|u| if u < 0.5 { 0.0 } else { 1.0 })) * half;
            let half_scalars: [f64; 8] = std::array::from_fn(|v| {
                let corner = DVec3::new((v & 1) as f64, ((v >> 1) & 1) as f64, (v >> 2) as f64);
                kuhn_field(min, size, &scalars, half_min + corner * half)
            });
            let refined = kuhn_field(half_min, half, &half_scalars, p);
            prop_assert!((refined - expected).abs() <= 1e-9, "{refined} vs {expected}");
        }
    }

    #[test]
    fn kuhn_tables_list_one_tetrahedron_per_axis_ordering() {
        for (corners, [a, b, _]) in KUHN_TETRAHEDRA.iter().zip(KUHN_AXIS_ORDERS) {
            let mut sorted = *corners;
            sorted[1..3].sort_by_key(|v| v.count_ones());
            assert_eq!(sorted, [0, 1 << a, (1 << a) | (1 << b), 7]);
        }
        let unit = Hexahedron::axis_aligned(DVec3::ZERO, DVec3::ONE, [0.0; 8]);
        for tet in unit.kuhn_tetrahedra() {
            assert!((tet.signed_volume() - 1.0 / 6.0).abs() < 1e-15);
        }
        let mut orders = KUHN_AXIS_ORDERS.to_vec();
        orders.sort();
        orders.dedup();
        assert_eq!(orders.len(), 6);
        assert!(orders.iter().all(|o| {
            let mut sorted = *o;
            sorted.sort();
            sorted == [0, 1, 2]
        }));
    }

    #[test]
    fn neighbouring_prisms_share_side_diagonals() {
        // Two prisms over triangles (0, 1, 2) and (1, 3, 2) share the edge 1-2.
        let grid = [DVec3::ZERO, DVec3::X, DVec3::Z, DVec3::new(1.0, 0.0, 1.0)];
        let prism = |ids: [u64; 3]| {
            let bottom = ids.map(|i| grid[i as usize]);
            let top = bottom.map(|p| p + DVec3::Y);
            Prism {
                positions: [bottom[0], bottom[1], bottom[2], top[0], top[1], top[2]],
                scalars: [0.0; 6],
            }
        };
        let shared_face_diagonal = |ids: [u64; 3]| {
            let mut found = Vec::new();
            for tet in prism(ids).tetrahedra(ids) {
                for a in tet.positions {
                    for b in tet.positions {
                        let on_shared = |p: DVec3| p.x + p.z == 1.0;
                        if on_shared(a) && on_shared(b) && a.y == 0.0 && b.y == 1.0 && a.x != b.x {
                            found.push((a.to_array(), b.to_array()));
                        }
                    }
                }
            }
            found.sort_by(|x, y| x.partial_cmp(y).unwrap());
            found.dedup();
            found
        };
        let left = shared_face_diagonal([0, 1, 2]);
        let right = shared_face_diagonal([1, 3, 2]);
        assert_eq!(left.len(), 1);
        assert_eq!(left, right);
    }

    #[test]
    fn cells_100_km_from_the_origin_stay_accurate() {
        let tet = Tetrahedron {
            positions: [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z].map(|p| p * 3.0),
            scalars: [0.1, 0.9, 0.4, 0.6],
        };
        let ray = Ray::new(DVec3::new(0.5, 0.7, -4.0), DVec3::new(0.1, 0.05, 1.0)).unwrap();
        let near = tet.intersect(&ray).unwrap();
        let offset = DVec3::new(1e5, -2e5, 1e5);
        let far_tet = Tetrahedron {
            positions: tet.positions.map(|p| p + offset),
            ..tet
        };
        let far_ray = Ray {
            origin: ray.origin + offset,
            ..ray
        };
        let far = far_tet.intersect(&far_ray).unwrap();
        assert!(
            (far.t_entry - near.t_entry).abs() < 1e-9 && (far.t_exit - near.t_exit).abs() < 1e-9
        );
        assert!(
            (far.s_entry - near.s_entry).abs() < 1e-9 && (far.s_exit - near.s_exit).abs() < 1e-9
        );
    }

    #[test]
    fn grazing_rays_give_zero_length_segments() {
        let tet = unit_tetrahedron();
        // Through vertex X only.
        let ray = Ray::new(DVec3::new(1.0, -1.0, 0.0), DVec3::Y).unwrap();
        let seg = tet.intersect(&ray).expect("touches the vertex");
        assert!(seg.length().abs() < 1e-12);
        assert!((seg.s_entry - 0.9).abs() < 1e-12);
        // Along the edge X–Y inside the face z = 0.
        let ray = Ray::new(DVec3::new(1.0, 0.0, 0.0), DVec3::new(-1.0, 1.0, 0.0)).unwrap();
        let seg = tet.intersect(&ray).expect("runs along the edge");
        assert!((seg.length() - 2f64.sqrt()).abs() < 1e-12);
        assert!((seg.s_entry - 0.9).abs() < 1e-12 && (seg.s_exit - 0.4).abs() < 1e-12);
        // Just outside the vertex: a miss.
        let ray = Ray::new(DVec3::new(1.0 + 1e-9, -1.0, 0.0), DVec3::Y).unwrap();
        assert!(tet.intersect(&ray).is_none());
    }

    #[test]
    fn degenerate_cells_are_never_hit() {
        let ray = Ray::new(DVec3::new(0.1, 0.1, -5.0), DVec3::Z).unwrap();
        let flat = Tetrahedron {
            positions: [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::new(0.3, 0.3, 0.0)],
            scalars: [0.0; 4],
        };
        let repeated = Tetrahedron {
            positions: [DVec3::ZERO, DVec3::ZERO, DVec3::Y, DVec3::Z],
            scalars: [0.0; 4],
        };
        let sliver = Tetrahedron {
            positions: [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::new(0.5, 0.5, 1e-14)],
            scalars: [0.0; 4],
        };
        let point = Tetrahedron {
            positions: [DVec3::ZERO; 4],
            scalars: [0.0; 4],
        };
        let nan = Tetrahedron {
            scalars: [f64::NAN, 0.0, 0.0, 0.0],
            ..unit_tetrahedron()
        };
        for tet in [flat, repeated, sliver, point, nan] {
            assert!(tet.is_degenerate());
            assert!(tet.intersect(&ray).is_none());
            assert!(tet.volume().is_finite() || tet.positions.iter().any(|p| !p.is_finite()));
        }
        assert!(Ray::new(DVec3::ZERO, DVec3::ZERO).is_none());
        assert!(Ray::new(DVec3::NAN, DVec3::X).is_none());
    }

    #[test]
    fn clipping_interpolates_scalars() {
        let tet = unit_tetrahedron();
        let ray = Ray::new(DVec3::new(0.2, 0.2, -1.0), DVec3::Z).unwrap();
        let seg = tet.intersect(&ray).unwrap();
        assert!((seg.t_entry - 1.0).abs() < 1e-12 && (seg.t_exit - 1.6).abs() < 1e-12);
        // Near plane at z = 0.3, keeping z ≥ 0.3.
        let near = Plane::from_point_normal(DVec3::new(0.0, 0.0, 0.3), DVec3::Z);
        let clipped = seg.clip_to_plane(&ray, &near).unwrap();
        assert!((clipped.t_entry - 1.3).abs() < 1e-12);
        let expected = brute_force_scalar(&tet, DVec3::new(0.2, 0.2, 0.3)).unwrap();
        assert!((clipped.s_entry - expected).abs() < 1e-12);
        assert_eq!(clipped.s_exit, seg.s_exit);
        // Opaque depth at z = 0.5, keeping z ≤ 0.5.
        let depth = Plane::from_point_normal(DVec3::new(0.0, 0.0, 0.5), -DVec3::Z);
        let both = clipped.clip_to_plane(&ray, &depth).unwrap();
        assert!((both.length() - 0.2).abs() < 1e-12);
        // Everything behind a plane: nothing left; parallel plane keeps all or nothing.
        let behind = Plane::from_point_normal(DVec3::new(0.0, 0.0, 2.0), DVec3::Z);
        assert!(seg.clip_to_plane(&ray, &behind).is_none());
        let parallel = Plane::from_point_normal(DVec3::ZERO, DVec3::X);
        assert_eq!(seg.clip_to_plane(&ray, &parallel), Some(seg));
        let parallel_away = Plane::from_point_normal(DVec3::X, DVec3::X);
        assert!(seg.clip_to_plane(&ray, &parallel_away).is_none());
        let nan_plane = Plane::from_point_normal(DVec3::ZERO, DVec3::NAN);
        assert!(seg.clip_to_plane(&ray, &nan_plane).is_none());
    }

    #[test]
    fn hexahedron_and_prism_intersections_span_the_cell() {
        let hex = Hexahedron::axis_aligned(
            DVec3::ZERO,
            DVec3::ONE,
            [0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0],
        );
        let ray = Ray::new(DVec3::new(-1.0, 0.3, 0.6), DVec3::X).unwrap();
        for parity in [HexahedronParity::Even, HexahedronParity::Odd] {
            let seg = hex.intersect(&ray, parity).unwrap();
            assert!((seg.t_entry - 1.0).abs() < 1e-12 && (seg.t_exit - 2.0).abs() < 1e-12);
            // The field is s = x, linear, so every decomposition is exact.
            assert!(seg.s_entry.abs() < 1e-12 && (seg.s_exit - 1.0).abs() < 1e-12);
        }
        let prism = Prism {
            positions: [
                DVec3::ZERO,
                DVec3::X,
                DVec3::Z,
                DVec3::Y,
                DVec3::X + DVec3::Y,
                DVec3::Z + DVec3::Y,
            ],
            scalars: [0.0, 0.0, 0.0, 1.0, 1.0, 1.0],
        };
        let ray = Ray::new(DVec3::new(0.2, -1.0, 0.2), DVec3::Y).unwrap();
        let seg = prism.intersect(&ray, [7, 3, 5]).unwrap();
        assert!((seg.length() - 1.0).abs() < 1e-12);
        assert!(seg.s_entry.abs() < 1e-12 && (seg.s_exit - 1.0).abs() < 1e-12);
        assert!((prism.volume() - 0.5).abs() < 1e-12);
    }
}
