//! Ground fog as vertical prisms on the terrain's level of detail.
//!
//! After Röttger and Ertl 2003 §6 and Röttger 2004 §10.4, every triangle the
//! quadtree draws carries a prism from the morphed ground up to the morphed fog
//! top, split into tetrahedra for the cell projection.
//!
//! [`fog_prisms`] reads a [`TerrainMesh`] refined with the fog's thickness as
//! its [`TerrainMap`](crate::quadtree::TerrainMap)
//! ([`TerrainHierarchy::update_with_map`](crate::quadtree::TerrainHierarchy::update_with_map),
//! with [`TerrainMesh::grid_points`]): ground and top are morphed with the
//! terrain's own weights, so the fog top never pops, and the thickness's
//! roughness refines the quadtree too
//! ([`TerrainHierarchy::add_map_roughness`](crate::quadtree::TerrainHierarchy::add_map_roughness)).
//!
//! A [`FogProfile`] cuts every prism into stacked prisms at relative heights,
//! with its scalar at each level (the default is the paper's fog, dense at the
//! ground and clear at its top). Each splits into three tetrahedra by
//! `nebel_core::cell::Prism::tetrahedra`'s rule on grid ids, so neighbouring
//! prisms share their face diagonals and the mesh conforms for any refinement;
//! pieces of zero thickness are dropped. Any layer between two surfaces over
//! one grid is the bottom as the terrain and their difference as the map
//! (aurora curtains, a cloud layer), its scalar from the profile
//! ([`PrismScalar::Profile`]) or from a second morphed map
//! ([`PrismScalar::Values`]). With [`PrismInput::beyond`] the columns wholly
//! beyond a distance are left out, for fog layers to take over there.
//!
//! [`CellOrder::BackToFront`] is exact for any eye: the columns in the
//! quadtree's back-to-front triangle order (every ray's ground projection
//! crosses them in that order), the cells of a column as a chain ordered across
//! each shared face (Williams 1992's rule on a path). [`CellOrder::Unordered`]
//! keeps mesh order for the emissive and MIP modes. The [`GpuCell`]s are in
//! world space, each shared vertex rounded once.
//!
//! The split, the handling of zero thickness and the proof of the order are in
//! `docs/ground-fog-prisms.md` in the repository.

use glam::{DAffine3, DVec3};
use thiserror::Error;

use nebel_core::field::{SKY_DIFFUSIVITY, ScatteringOctaves};

use crate::batch::GpuCell;
use crate::full_resolution::CellOrder;
use crate::quadtree::{TerrainMesh, TriangleOrder};

/// The fog's scalar over relative height inside its layer: piecewise linear
/// through `points` `(r, s)`, `r` from 0 (the ground) to 1 (the fog top)
/// strictly increasing, `s` in [0, 1] (the transfer function's input).
#[derive(Clone, Debug, PartialEq)]
pub struct FogProfile {
    points: Vec<[f32; 2]>,
}

impl Default for FogProfile {
    /// The paper's fog: the full density at the ground, zero at the top.
    fn default() -> Self {
        Self {
            points: vec![[0.0, 1.0], [1.0, 0.0]],
        }
    }
}

impl FogProfile {
    /// The profile through `points` `(relative height, scalar)`: at least two,
    /// the first at 0 and the last at 1, strictly increasing, scalars in
    /// [0, 1], all finite.
    pub fn new(points: Vec<[f32; 2]>) -> Result<Self, PrismError> {
        let valid = points.len() >= 2
            && points.first().is_some_and(|p| p[0] == 0.0)
            && points.last().is_some_and(|p| p[0] == 1.0)
            && points.windows(2).all(|w| w[0][0] < w[1][0])
            && points
                .iter()
                .all(|p| p[0].is_finite() && (0.0..=1.0).contains(&p[1]));
        if valid {
            Ok(Self { points })
        } else {
            Err(PrismError::InvalidProfile { points })
        }
    }

    /// A fog of the same density from the ground to its top (`s = 1`).
    pub fn uniform() -> Self {
        Self {
            points: vec![[0.0, 1.0], [1.0, 1.0]],
        }
    }

    /// The points `(relative height, scalar)`.
    pub fn points(&self) -> &[[f32; 2]] {
        &self.points
    }

    /// Stacked prisms per terrain triangle.
    pub fn layers(&self) -> usize {
        self.points.len() - 1
    }
}

/// Why no prisms could be built.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum PrismError {
    /// The mesh was refined without the fog's thickness or grid points.
    #[error(
        "the terrain mesh has no fog thickness or no grid points per vertex: refine it with update_with_map and grid_points"
    )]
    MissingMap,
    /// A scalar from the mesh's values was asked of a mesh refined without
    /// them.
    #[error(
        "the prisms' scalar comes from the mesh's values, but the mesh has none: refine it with update_with_maps and a value map"
    )]
    MissingValues,
    /// The span of [`PrismScalar::Height`] is not finite and positive.
    #[error("the prisms' height span is {span}; it must be finite and > 0")]
    InvalidSpan {
        /// The span given.
        span: f32,
    },
    /// The lighting of [`PrismScalar::Sunlit`] is not finite, or its
    /// extinction negative.
    #[error(
        "the prisms' lighting (extinction, sun height, ambient, diffuse) = {lighting:?} is invalid: all must be finite and the extinction >= 0"
    )]
    InvalidLighting {
        /// The lighting given.
        lighting: [f32; 4],
    },
    /// A sorted batch was asked of an unordered mesh.
    #[error("sorted fog needs a back-to-front or front-to-back terrain mesh, not an unordered one")]
    UnorderedMesh,
    /// The profile is not a valid piecewise-linear function on [0, 1].
    #[error(
        "fog profile {points:?} is invalid: it needs at least two (height, scalar) points from height 0 to height 1, strictly increasing, scalars in [0, 1]"
    )]
    InvalidProfile {
        /// The points given.
        points: Vec<[f32; 2]>,
    },
}

/// Counters of one [`fog_prisms`] call.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PrismStats {
    /// Terrain triangles with fog above at least one vertex (each a column of
    /// [`FogProfile::layers`] prisms).
    pub prisms: usize,
    /// Tetrahedra written.
    pub tetrahedra: usize,
}

/// Where the scalar of the prisms' vertices comes from.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum PrismScalar {
    /// The [`FogProfile`]'s scalar at each level's relative height (0 at the
    /// bottom, 1 at the top with the profile `[(0, 0), (1, 1)]`).
    #[default]
    Profile,
    /// Each column vertex's morphed value from [`TerrainMesh::values`] (a
    /// map over the ground, clamped to [0, 1]), the same on every level: a
    /// layer whose scalar varies over the ground only.
    Values,
    /// The height above the bottom divided by `span` (world units of the
    /// mesh frame, finite and > 0), clamped to [0, 1]: the same scalar at
    /// the same height above the bottom in thin and thick columns (aurora
    /// curtains coloured by altitude). It is linear in every tetrahedron
    /// (the bottom of a column is planar), so the cells carry it exactly.
    Height {
        /// The height above the bottom where the scalar reaches 1.
        span: f32,
    },
    /// The sunlight that reaches each level through the layer above it, as
    /// a light intensity for a transfer function over light (the
    /// `CloudLight` preset): `ambient · T_sky + diffuse · T_sun(τ)` clamped
    /// to [0, 1], with `τ = extinction · d / sun_height`, `d` the thickness
    /// above the level in its column (`(1 − r) · t`), `sun_height` the sine
    /// of the sun's elevation (clamped to at least 0.05): Beer-Lambert along
    /// the slant path to the top of a plane-parallel layer of the column's
    /// local thickness. `T_sun` is `e^{−τ}`, or with several `octaves` the
    /// multiple-scattering sum of `nebel_core::field::ScatteringOctaves`;
    /// `T_sky` is 1, or with `sky_occlusion` the layer's diffuse
    /// transmittance `e^{−1.66 · extinction · d}` of the sky's light. The
    /// profile's levels sample it; it is linear between them. All four
    /// floats finite, `extinction ≥ 0`.
    Sunlit {
        /// Extinction inside the layer, 1 / world unit.
        extinction: f32,
        /// Sine of the sun's elevation above the horizon.
        sun_height: f32,
        /// Light without the sun.
        ambient: f32,
        /// Light of the unshadowed sun.
        diffuse: f32,
        /// Octaves of multiple scattering, 1 to 8 (others clamped); 1 is
        /// single scattering.
        octaves: u32,
        /// Whether the layer above a level dims its sky light.
        sky_occlusion: bool,
    },
}

/// What [`fog_prisms`] needs besides the mesh.
#[derive(Clone, Copy, Debug)]
pub struct PrismInput<'a> {
    /// The mesh frame (the hierarchy's, relative to its origin) to world
    /// space.
    pub world_from_mesh: DAffine3,
    /// The eye in the mesh frame (read by the sorted order only).
    pub eye: DVec3,
    /// The order in which the mesh's triangles come.
    pub mesh_order: TriangleOrder,
    /// The order of the cells written.
    pub order: CellOrder,
    /// The scalar over relative height.
    pub profile: &'a FogProfile,
    /// Where the cells' scalar comes from.
    pub scalar: PrismScalar,
    /// Leave out every column whose box lies wholly farther from `eye` (in
    /// world space) than this many world units: where another method (fog
    /// layers) takes the fog over. `None` keeps every column.
    pub beyond: Option<(DVec3, f64)>,
}

/// The vertices of one column: level `k` of corner `v` at `3k + v`, corners
/// sorted by grid id.
struct Column {
    positions: Vec<DVec3>,
    /// `positions` in world space, rounded once.
    world: Vec<[f32; 3]>,
    /// Per vertex, the first vertex at its position (a corner of zero
    /// thickness has one position on every level).
    canonical: Vec<usize>,
    scalars: Vec<f32>,
    /// Kept cells, as indices into `positions`, in chain order.
    cells: Vec<[usize; 4]>,
    /// The chain order of the kept cells, back to front.
    order: Vec<usize>,
    stack: Vec<usize>,
}

/// Writes the fog prisms of `mesh` into `out` (cleared first) in the order
/// asked for (see the [module docs](self)).
pub fn fog_prisms(
    mesh: &TerrainMesh,
    input: &PrismInput,
    out: &mut Vec<GpuCell>,
) -> Result<PrismStats, PrismError> {
    out.clear();
    let vertices = mesh.positions.len();
    if mesh.map.len() != vertices || mesh.grid_points.len() != vertices {
        return Err(PrismError::MissingMap);
    }
    match input.scalar {
        PrismScalar::Values if mesh.values.len() != vertices => {
            return Err(PrismError::MissingValues);
        }
        PrismScalar::Height { span } if !(span.is_finite() && span > 0.0) => {
            return Err(PrismError::InvalidSpan { span });
        }
        PrismScalar::Sunlit {
            extinction,
            sun_height,
            ambient,
            diffuse,
            ..
        } if !([extinction, sun_height, ambient, diffuse]
            .iter()
            .all(|v| v.is_finite())
            && extinction >= 0.0) =>
        {
            return Err(PrismError::InvalidLighting {
                lighting: [extinction, sun_height, ambient, diffuse],
            });
        }
        _ => {}
    }
    let sorted = input.order == CellOrder::BackToFront;
    if sorted && input.mesh_order == TriangleOrder::Unordered {
        return Err(PrismError::UnorderedMesh);
    }
    let levels = input.profile.points();
    let mut column = Column {
        positions: Vec::with_capacity(3 * levels.len()),
        world: Vec::with_capacity(3 * levels.len()),
        canonical: Vec::with_capacity(3 * levels.len()),
        scalars: Vec::with_capacity(3 * levels.len()),
        cells: Vec::with_capacity(3 * levels.len()),
        order: Vec::with_capacity(3 * levels.len()),
        stack: Vec::with_capacity(3 * levels.len()),
    };
    let mut stats = PrismStats::default();
    let triangles = mesh.indices.chunks_exact(3);
    let reversed = sorted && input.mesh_order == TriangleOrder::FrontToBack;
    let mut emit = |triangle: &[u32]| {
        let mut corners = [triangle[0], triangle[1], triangle[2]].map(|v| v as usize);
        let id = |v: usize| {
            let [i, j] = mesh.grid_points[v];
            u64::from(i) | (u64::from(j) << 32)
        };
        corners.sort_by_key(|&v| id(v));
        let thickness = corners.map(|v| f64::from(mesh.map[v]));
        if thickness.iter().all(|t| *t <= 0.0) {
            return;
        }
        column.build(
            mesh,
            corners,
            thickness,
            levels,
            input.scalar,
            &input.world_from_mesh,
        );
        if column.cells.is_empty()
            || input
                .beyond
                .is_some_and(|(eye, distance)| column.distance_from(eye) > distance)
        {
            return;
        }
        if sorted {
            column.sort(input.eye);
        } else {
            column.order.clear();
            column.order.extend(0..column.cells.len());
        }
        stats.prisms += 1;
        stats.tetrahedra += column.cells.len();
        for &cell in &column.order {
            let indices = column.cells[cell];
            out.push(GpuCell {
                vertices: indices.map(|p| {
                    let [x, y, z] = column.world[p];
                    [x, y, z, column.scalars[p]]
                }),
            });
        }
    };
    if reversed {
        triangles.rev().for_each(&mut emit);
    } else {
        triangles.for_each(&mut emit);
    }
    Ok(stats)
}

impl Column {
    /// The distance from `eye` (world space) to the nearest point of the
    /// column's world box.
    fn distance_from(&self, eye: DVec3) -> f64 {
        let (min, max) =
            self.world
                .iter()
                .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(min, max), p| {
                    let p = DVec3::from(p.map(f64::from));
                    (min.min(p), max.max(p))
                });
        (eye.clamp(min, max) - eye).length()
    }

    /// The column's vertices and kept cells, in chain order.
    fn build(
        &mut self,
        mesh: &TerrainMesh,
        corners: [usize; 3],
        thickness: [f64; 3],
        levels: &[[f32; 2]],
        scalar: PrismScalar,
        world_from_mesh: &DAffine3,
    ) {
        self.positions.clear();
        self.world.clear();
        self.canonical.clear();
        self.scalars.clear();
        self.cells.clear();
        // A corner is flat where its top is its ground: no thickness, or one
        // below the height's rounding.
        let flat: [bool; 3] = std::array::from_fn(|corner| {
            let y = f64::from(mesh.positions[corners[corner]][1]);
            y + thickness[corner].max(0.0) == y
        });
        for (level, &[r, s]) in levels.iter().enumerate() {
            for (corner, (v, t)) in corners.iter().zip(thickness).enumerate() {
                self.canonical.push(if flat[corner] {
                    corner
                } else {
                    3 * level + corner
                });
                let [x, y, z] = mesh.positions[*v].map(f64::from);
                let above = f64::from(r) * t.max(0.0);
                let position = DVec3::new(x, y + above, z);
                self.positions.push(position);
                self.world.push(
                    world_from_mesh
                        .transform_point3(position)
                        .as_vec3()
                        .to_array(),
                );
                self.scalars.push(match scalar {
                    PrismScalar::Profile => s,
                    PrismScalar::Values => mesh.values[*v].clamp(0.0, 1.0),
                    PrismScalar::Height { span } => {
                        (above / f64::from(span)).clamp(0.0, 1.0) as f32
                    }
                    PrismScalar::Sunlit {
                        extinction,
                        sun_height,
                        ambient,
                        diffuse,
                        octaves,
                        sky_occlusion,
                    } => {
                        let tau = f64::from(extinction) * (t.max(0.0) - above);
                        let slant = f64::from(sun_height.max(0.05));
                        let sun = ScatteringOctaves::new(octaves).transmittance(tau / slant);
                        let sky = if sky_occlusion {
                            (-SKY_DIFFUSIVITY * tau).exp()
                        } else {
                            1.0
                        };
                        (f64::from(ambient) * sky + f64::from(diffuse) * sun).clamp(0.0, 1.0) as f32
                    }
                });
            }
        }
        let [a, b, c] = [0, 1, 2];
        for layer in 0..levels.len() - 1 {
            let (bottom, top) = (3 * layer, 3 * layer + 3);
            // Prism::tetrahedra's pieces, each dropped when its collapsing
            // vertical edge has zero thickness.
            let pieces = [
                (c, [bottom + a, bottom + b, bottom + c, top + c]),
                (b, [bottom + a, bottom + b, top + b, top + c]),
                (a, [bottom + a, top + a, top + b, top + c]),
            ];
            for (edge, cell) in pieces {
                if !flat[edge] {
                    self.cells.push(cell);
                }
            }
        }
    }

    /// Orders the kept cells back to front for `eye` by the shared faces of
    /// consecutive cells (see `docs/ground-fog-prisms.md`).
    fn sort(&mut self, eye: DVec3) {
        self.order.clear();
        self.stack.clear();
        let count = self.cells.len();
        for k in 0..count {
            self.stack.push(k);
            if k + 1 == count || !self.in_front_of_next(k, eye) {
                // Cell k is drawn before k + 1: the run waiting on it goes
                // first, nearest to k last.
                while let Some(cell) = self.stack.pop() {
                    self.order.push(cell);
                }
            }
        }
    }

    /// Whether cell `k` lies between the eye and cell `k + 1` (the eye is on
    /// `k`'s side of their shared face), so `k` is drawn after it.
    fn in_front_of_next(&self, k: usize, eye: DVec3) -> bool {
        let (own, next) = (self.cells[k], self.cells[k + 1]);
        let at = |p: usize| self.positions[p];
        let id = |p: usize| self.canonical[p];
        let shared = |p: usize| next.iter().any(|&q| id(q) == id(p));
        let Some(apex) = own.iter().copied().find(|&p| !shared(p)) else {
            return false;
        };
        let mut face = [DVec3::ZERO; 3];
        for (slot, p) in face.iter_mut().zip(own.iter().filter(|&&p| p != apex)) {
            *slot = at(*p);
        }
        let normal = (face[1] - face[0]).cross(face[2] - face[0]);
        let apex_side = normal.dot(at(apex) - face[0]);
        let eye_side = normal.dot(eye - face[0]);
        apex_side * eye_side > 0.0
    }
}
