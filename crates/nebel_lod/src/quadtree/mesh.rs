//! The per-frame half: refinement, geomorphing and triangle-fan output in one
//! top-down pass ([`TerrainHierarchy::update`]; formulas in the
//! [module docs](super)).

use glam::DVec3;

use super::hierarchy::{TerrainHierarchy, level_offset};
use super::{DEFAULT_ACCURACY, TerrainError, TerrainMap};
use crate::frustum::Frustum;

/// In which order the triangles come out (see `docs/quadtree-lod.md`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum TriangleOrder {
    /// Farthest first, for the eye's ground projection: what sorted,
    /// emission–absorption ground fog over the triangles needs. The default.
    #[default]
    BackToFront,
    /// Nearest first (the best order for an opaque depth-tested terrain).
    FrontToBack,
    /// A fixed order, the cheapest (no per-node sorting).
    Unordered,
}

/// Per-frame settings of [`TerrainHierarchy::update`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LodSettings {
    /// Global accuracy `c` of the criterion `f = l² / (d² max(c·d2, C)²)`:
    /// larger gives more triangles; a left-out detail subtends at most about
    /// `1/(2c)` radian. Finite and > 0. Default [`DEFAULT_ACCURACY`] (100).
    pub accuracy: f32,
    /// Geomorphing: new vertices blend in with the weight `t` of their node.
    /// `false` forces every weight to 1 (vertices pop in at their true
    /// height). Default `true`.
    pub morph: bool,
    /// Write [`TerrainMesh::normals`] (morphed true-grid normals). Default
    /// `true`.
    pub normals: bool,
    /// Write [`TerrainMesh::grid_points`] (each vertex's grid index).
    /// Default `false`.
    pub grid_points: bool,
    /// Triangle order. Default [`TriangleOrder::BackToFront`].
    pub order: TriangleOrder,
}

impl Default for LodSettings {
    fn default() -> Self {
        Self {
            accuracy: DEFAULT_ACCURACY,
            morph: true,
            normals: true,
            grid_points: false,
            order: TriangleOrder::BackToFront,
        }
    }
}

/// The output of [`TerrainHierarchy::update`]: an indexed triangle list,
/// counter-clockwise seen from above (+y), in the order asked for. Reuse one
/// across frames: `update` clears it and keeps its capacity, so after the
/// first frames nothing is allocated.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TerrainMesh {
    /// Vertex positions relative to [`TerrainHierarchy::origin`]: grid point
    /// `(i, j)` at `(i·spacing.x, h, j·spacing.z)`, `h` the morphed height
    /// (absolute, world units). A vertex is written once per fan it belongs
    /// to.
    pub positions: Vec<[f32; 3]>,
    /// Unit normals per vertex when [`LodSettings::normals`], else empty.
    pub normals: Vec<[f32; 3]>,
    /// Grid index `(i, j)` per vertex when [`LodSettings::grid_points`], else
    /// empty.
    pub grid_points: Vec<[u32; 2]>,
    /// The morphed value of the [`TerrainMap`] per vertex when the update
    /// was given one (the fog's thickness above the ground, say), else empty.
    pub map: Vec<f32>,
    /// The morphed value of a second [`TerrainMap`] per vertex when the
    /// update was given one (a value over the ground, such as the scalar of
    /// a layer between two surfaces), else empty.
    pub values: Vec<f32>,
    /// Three vertex indices per triangle.
    pub indices: Vec<u32>,
}

impl TerrainMesh {
    /// An empty mesh.
    pub fn new() -> Self {
        Self::default()
    }

    /// Triangles in the mesh.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// Empties every array, keeping the capacity.
    pub fn clear(&mut self) {
        self.positions.clear();
        self.normals.clear();
        self.grid_points.clear();
        self.map.clear();
        self.values.clear();
        self.indices.clear();
    }
}

/// Counters of one update.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LodStats {
    /// Triangles written.
    pub triangles: usize,
    /// Vertices written.
    pub vertices: usize,
    /// Refined nodes drawn (each a fan or a parent of fans).
    pub nodes: usize,
    /// Refined nodes skipped with their subtree by frustum culling.
    pub culled: usize,
    /// Deepest level drawn (0 for the root).
    pub deepest_level: u32,
    /// Edge midpoints a refined child needed although the neighbour across
    /// was not refined, i.e. breaches of the one-level rule, repaired by
    /// placing the midpoint at its coarse value. Always 0 unless rounding
    /// defeated the propagation's margin; the tests check it.
    pub one_level_repairs: usize,
}

/// A vertex value: morphed height, morphed height gradient (∂h/∂x, ∂h/∂z)
/// and the morphed values of the update's `L` maps (none, the map, or
/// the map and the value map), so a terrain pays only for the maps it
/// has.
#[derive(Clone, Copy, Debug)]
struct Vtx<const L: usize> {
    h: f32,
    g: [f32; 2],
    maps: [f32; L],
}

impl<const L: usize> Vtx<L> {
    const ZERO: Self = Self {
        h: 0.0,
        g: [0.0; 2],
        maps: [0.0; L],
    };
}

/// `w · own + (1 − w) · (a + b)/2`, the same expression wherever a vertex is
/// computed, so a vertex shared by fans gets one value bit for bit.
#[inline(always)]
fn blend<const L: usize>(w: f32, own: &Vtx<L>, a: &Vtx<L>, b: &Vtx<L>) -> Vtx<L> {
    let v = 1.0 - w;
    Vtx {
        h: w * own.h + v * ((a.h + b.h) * 0.5),
        g: [
            w * own.g[0] + v * ((a.g[0] + b.g[0]) * 0.5),
            w * own.g[1] + v * ((a.g[1] + b.g[1]) * 0.5),
        ],
        maps: std::array::from_fn(|k| w * own.maps[k] + v * ((a.maps[k] + b.maps[k]) * 0.5)),
    }
}

/// Ring offsets in half sizes, counter-clockwise in (i, j) from +i: E, NE, N,
/// NW, W, SW, S, SE. Even slots are edge midpoints (edge `slot / 2`: E, N, W,
/// S), odd slots corners.
const RING_I: [i32; 8] = [1, 1, 0, -1, -1, -1, 0, 1];
const RING_J: [i32; 8] = [0, 1, 1, 1, 0, -1, -1, -1];
/// The vertex slot of a node's centre (slots 0 to 7 are the ring).
const CENTRE: usize = 8;

/// Per-level constants of one frame.
#[derive(Clone, Copy, Debug, Default)]
struct Level {
    /// Node size in cells.
    cells: u32,
    /// Half of it.
    half: u32,
    /// First node of the level in the d2 codes.
    offset: usize,
    /// `1 / d²`, `d` the node size in world units.
    inv_size2: f32,
    /// The level's height bound.
    bound: f32,
}

/// Everything one update reads and writes.
struct Frame<'a, const L: usize> {
    heights: &'a [f32],
    /// The maps' values per grid point: the map, then the value map.
    maps: [&'a [f32]; L],
    /// The map's largest value, added to the top of every culling box.
    layer_margin: f32,
    n: usize,
    levels: usize,
    d2: &'a [u8],
    /// `1 / max(c·d2, C)²` per code.
    weight: [f32; 256],
    level: [Level; 25],
    /// Eye x and z relative to the terrain origin.
    eye: [f32; 2],
    /// `v²`, the squared vertical distance of the eye from the height range.
    base2: f32,
    spacing: [f32; 2],
    /// `1/Δx` for one-sided (index 1) and central (index 2) differences.
    inv_dx: [f32; 3],
    inv_dz: [f32; 3],
    morph: bool,
    normals: bool,
    grid: bool,
    order: TriangleOrder,
    /// Frustum planes in the mesh frame, `(n, d)`, inside where `n·p + d ≥ 0`.
    planes: [[f32; 4]; 32],
    /// Slack of the culling test per plane, world units.
    slack: [f32; 32],
    mesh: &'a mut TerrainMesh,
    stats: LodStats,
}

/// A node being drawn: position, vertex values and the indices of the
/// vertices already written for its fan.
struct NodeVerts<const L: usize> {
    ci: u32,
    cj: u32,
    half: u32,
    ring: [Vtx<L>; 8],
    centre: Vtx<L>,
    index: [u32; 9],
}

impl TerrainHierarchy {
    /// Refines the quadtree for `eye` (world position) and writes the morphed
    /// triangle fans of every refined node into `mesh` (cleared first),
    /// skipping nodes whose box misses `frustum` (world space; `None` draws
    /// everything). See the [module docs](super) for the criterion, the
    /// morphing, the order and the culling.
    ///
    /// Errors for a non-finite eye and an accuracy that is not finite and
    /// positive; otherwise any eye works, including one on a vertex, below
    /// the terrain or far away, and nothing in the mesh is NaN.
    pub fn update(
        &self,
        eye: DVec3,
        frustum: Option<&Frustum>,
        settings: &LodSettings,
        mesh: &mut TerrainMesh,
    ) -> Result<LodStats, TerrainError> {
        self.update_with_map(eye, frustum, settings, None, mesh)
    }

    /// [`TerrainHierarchy::update`] that also morphs `map`, a value per grid
    /// point, with the terrain's weights (every vertex's value is blended from
    /// its coarse endpoints exactly like its height, so it never pops either)
    /// into [`TerrainMesh::map`], and culls each node on a box raised by the
    /// map's largest value (a map of thickness above the ground, like
    /// ground fog, stays inside it). Errors besides `update`'s: a map of
    /// another size than the terrain ([`TerrainError::DimsMismatch`]).
    pub fn update_with_map(
        &self,
        eye: DVec3,
        frustum: Option<&Frustum>,
        settings: &LodSettings,
        map: Option<&TerrainMap>,
        mesh: &mut TerrainMesh,
    ) -> Result<LodStats, TerrainError> {
        self.update_with_maps(eye, frustum, settings, map, None, mesh)
    }

    /// [`TerrainHierarchy::update_with_map`] that also morphs a second
    /// map, `values` (a value over the ground, such as the scalar of a
    /// layer between two surfaces), with the same weights into
    /// [`TerrainMesh::values`]; it does not raise the culling boxes. Each
    /// map costs only the updates that carry it. Errors besides
    /// `update_with_map`'s: `values` of another size, or without `map`
    /// ([`TerrainError::InvalidParameter`]).
    pub fn update_with_maps(
        &self,
        eye: DVec3,
        frustum: Option<&Frustum>,
        settings: &LodSettings,
        map: Option<&TerrainMap>,
        values: Option<&TerrainMap>,
        mesh: &mut TerrainMesh,
    ) -> Result<LodStats, TerrainError> {
        for extra in [map, values].into_iter().flatten() {
            if extra.side() != self.size {
                return Err(TerrainError::DimsMismatch {
                    terrain: self.field.dims(),
                    extra: [extra.side(); 2],
                });
            }
        }
        let requirement = "given with a map (the values ride on the map's cells)";
        TerrainError::check(
            values.is_none() || map.is_some(),
            "values",
            f64::NAN,
            requirement,
        )?;
        if !eye.is_finite() {
            return Err(TerrainError::NonFiniteEye { eye });
        }
        let c = settings.accuracy;
        TerrainError::check(
            c.is_finite() && c > 0.0,
            "accuracy c",
            c,
            "finite and positive",
        )?;
        mesh.clear();
        let origin = self.origin();
        let local_eye = eye - origin;
        let [low, high] = self.height_range.map(f64::from);
        let vertical = if local_eye.y > high {
            local_eye.y - high
        } else if local_eye.y < low {
            low - local_eye.y
        } else {
            0.0
        };
        let spacing = self.field.spacing();
        let min_resolution = f64::from(self.min_resolution);
        let weight = std::array::from_fn(|q| {
            let m = (f64::from(c) * f64::from(self.d2_table[q]))
                .max(min_resolution)
                .min(1e18);
            (1.0 / (m * m)) as f32
        });
        let mut level = [Level::default(); 25];
        for (l, slot) in level.iter_mut().enumerate().take(self.levels as usize) {
            let cells = ((self.size - 1) >> l) as u32;
            let size = f64::from(cells) * spacing.max_element();
            *slot = Level {
                cells,
                half: cells / 2,
                offset: level_offset(l as u32),
                inv_size2: (1.0 / (size * size)) as f32,
                bound: self.height_bound[l],
            };
        }
        let mut planes = [[0.0f32; 4]; 32];
        let mut slack = [0.0f32; 32];
        let mut mask = 0u32;
        if let Some(frustum) = frustum {
            // Pull the planes into the mesh frame (a translation by the
            // origin); planes beyond 32 are ignored, which only keeps more.
            for (p, plane) in frustum.planes().iter().take(32).enumerate() {
                let normal = plane.truncate();
                let d = plane.w + normal.dot(origin);
                planes[p] = [normal.x as f32, normal.y as f32, normal.z as f32, d as f32];
                slack[p] = 1e-5 * (1.0 + d.abs() as f32);
                mask |= 1 << p;
            }
        }
        let sx = spacing.x as f32;
        let sz = spacing.y as f32;
        // One frame type per number of maps, so a terrain without them
        // blends no map values.
        macro_rules! frame {
            ($maps:expr) => {
                Frame {
                    heights: self.field.heights(),
                    maps: $maps,
                    layer_margin: map.map_or(0.0, TerrainMap::max),
                    n: self.size,
                    levels: self.levels as usize,
                    d2: &self.d2,
                    weight,
                    level,
                    eye: [local_eye.x as f32, local_eye.z as f32],
                    base2: (vertical * vertical) as f32,
                    spacing: [sx, sz],
                    inv_dx: [0.0, (1.0 / spacing.x) as f32, (0.5 / spacing.x) as f32],
                    inv_dz: [0.0, (1.0 / spacing.y) as f32, (0.5 / spacing.y) as f32],
                    morph: settings.morph,
                    normals: settings.normals,
                    grid: settings.grid_points,
                    order: settings.order,
                    planes,
                    slack,
                    mesh,
                    stats: LodStats::default(),
                }
            };
        }
        Ok(match (map, values) {
            (Some(first), Some(second)) => frame!([first.values(), second.values()]).draw(mask),
            (Some(first), None) => frame!([first.values()]).draw(mask),
            _ => frame!([]).draw(mask),
        })
    }
}

impl<const L: usize> Frame<'_, L> {
    /// Draws the whole mesh and returns the statistics.
    fn draw(mut self, mask: u32) -> LodStats {
        self.root(mask);
        self.stats.vertices = self.mesh.positions.len();
        self.stats.triangles = self.mesh.triangle_count();
        self.stats
    }

    #[inline(always)]
    fn height(&self, i: u32, j: u32) -> f32 {
        self.heights[i as usize + self.n * j as usize]
    }

    /// The true height gradient at a grid point: central differences, one-sided
    /// on the boundary. Zero when normals are off.
    #[inline(always)]
    fn gradient(&self, i: u32, j: u32) -> [f32; 2] {
        if !self.normals {
            return [0.0; 2];
        }
        let last = (self.n - 1) as u32;
        let (i0, i1) = (i.saturating_sub(1), (i + 1).min(last));
        let (j0, j1) = (j.saturating_sub(1), (j + 1).min(last));
        [
            (self.height(i1, j) - self.height(i0, j)) * self.inv_dx[(i1 - i0) as usize],
            (self.height(i, j1) - self.height(i, j0)) * self.inv_dz[(j1 - j0) as usize],
        ]
    }

    /// The true value at a grid point.
    #[inline(always)]
    fn true_vertex(&self, i: u32, j: u32) -> Vtx<L> {
        let index = i as usize + self.n * j as usize;
        Vtx {
            h: self.height(i, j),
            g: self.gradient(i, j),
            maps: std::array::from_fn(|k| self.maps[k][index]),
        }
    }

    /// The criterion `f` of node `(a, b)` of `level`; the node is refined iff
    /// `f < 1`. The only place `f` is computed, so a node and its neighbours
    /// always agree on it.
    #[inline(always)]
    fn criterion(&self, level: usize, a: u32, b: u32) -> f32 {
        let lv = &self.level[level];
        let i = lv.half + a * lv.cells;
        let j = lv.half + b * lv.cells;
        let x = i as f32 * self.spacing[0] - self.eye[0];
        let z = j as f32 * self.spacing[1] - self.eye[1];
        let distance2 = x * x + z * z + self.base2;
        let code = self.d2[lv.offset + a as usize + ((b as usize) << level)];
        distance2 * lv.inv_size2 * self.weight[usize::from(code)]
    }

    /// The morph weight of a refined node with criterion `f < 1`.
    #[inline(always)]
    fn morph_weight(&self, f: f32) -> f32 {
        if self.morph {
            ((1.0 - f) * (4.0 / 3.0)).min(1.0)
        } else {
            1.0
        }
    }

    /// `None` when the box lies outside a plane of `mask`; otherwise `mask`
    /// without the planes the box lies entirely inside.
    fn cull(&self, mask: u32, lo: [f32; 3], hi: [f32; 3]) -> Option<u32> {
        let mut rest = mask;
        let mut out = mask;
        while rest != 0 {
            let p = rest.trailing_zeros() as usize;
            rest &= rest - 1;
            let [nx, ny, nz, d] = self.planes[p];
            let (px, qx) = if nx >= 0.0 {
                (hi[0], lo[0])
            } else {
                (lo[0], hi[0])
            };
            let (py, qy) = if ny >= 0.0 {
                (hi[1], lo[1])
            } else {
                (lo[1], hi[1])
            };
            let (pz, qz) = if nz >= 0.0 {
                (hi[2], lo[2])
            } else {
                (lo[2], hi[2])
            };
            if nx * px + ny * py + nz * pz + d < -self.slack[p] {
                return None;
            }
            if nx * qx + ny * qy + nz * qz + d >= self.slack[p] {
                out &= !(1 << p);
            }
        }
        Some(out)
    }

    /// Draws the root: its fan tree when refined, else its two triangles.
    fn root(&mut self, mask: u32) {
        let last = (self.n - 1) as u32;
        let corners = [
            self.true_vertex(last, last),
            self.true_vertex(0, last),
            self.true_vertex(0, 0),
            self.true_vertex(last, 0),
        ];
        let f = self.criterion(0, 0, 0);
        if f < 1.0 {
            let t = self.morph_weight(f);
            self.node(0, 0, 0, &corners, t, [f32::NAN; 4], mask);
            return;
        }
        if mask != 0 {
            let lo = corners.iter().fold(f32::INFINITY, |m, c| m.min(c.h));
            let hi = corners.iter().fold(f32::NEG_INFINITY, |m, c| m.max(c.h)) + self.layer_margin;
            let x1 = last as f32 * self.spacing[0];
            let z1 = last as f32 * self.spacing[1];
            if self.cull(mask, [0.0, lo, 0.0], [x1, hi, z1]).is_none() {
                self.stats.culled += 1;
                return;
            }
        }
        // Two triangles split along the SW–NE diagonal (the root's parity
        // diagonal, so its centre morphs out of this mesh).
        let mut verts = NodeVerts {
            ci: last / 2,
            cj: last / 2,
            half: last / 2,
            ring: [Vtx::ZERO; 8],
            centre: Vtx::ZERO,
            index: [u32::MAX; 9],
        };
        for (c, &slot) in [1, 3, 5, 7].iter().enumerate() {
            verts.ring[slot] = corners[c];
        }
        // SE side: SW, NE, SE; NW side: SW, NW, NE.
        let south_east = [5, 1, 7];
        let north_west = [5, 3, 1];
        // Eye left of SW→NE (in grid-scaled units) is the NW side.
        let ex = self.eye[0] / self.spacing[0];
        let ez = self.eye[1] / self.spacing[1];
        let eye_north_west = ez - ex > 0.0;
        let first_south_east = match self.order {
            TriangleOrder::BackToFront => eye_north_west,
            TriangleOrder::FrontToBack => !eye_north_west,
            TriangleOrder::Unordered => true,
        };
        let (first, second) = if first_south_east {
            (south_east, north_west)
        } else {
            (north_west, south_east)
        };
        self.triangle(&mut verts, first);
        self.triangle(&mut verts, second);
    }

    /// Writes the vertex in `slot` of the node (once per node) and returns its
    /// index.
    #[inline(always)]
    fn vertex(&mut self, verts: &mut NodeVerts<L>, slot: usize) -> u32 {
        let cached = verts.index[slot];
        if cached != u32::MAX {
            return cached;
        }
        let (i, j, v) = if slot == CENTRE {
            (verts.ci, verts.cj, verts.centre)
        } else {
            let half = verts.half as i32;
            (
                (verts.ci as i32 + RING_I[slot] * half) as u32,
                (verts.cj as i32 + RING_J[slot] * half) as u32,
                verts.ring[slot],
            )
        };
        let index = self.mesh.positions.len() as u32;
        self.mesh
            .positions
            .push([i as f32 * self.spacing[0], v.h, j as f32 * self.spacing[1]]);
        if self.normals {
            let [gx, gz] = v.g;
            let inv = 1.0 / (gx * gx + 1.0 + gz * gz).sqrt();
            self.mesh.normals.push([-gx * inv, inv, -gz * inv]);
        }
        if self.grid {
            self.mesh.grid_points.push([i, j]);
        }
        if let Some(map) = v.maps.first() {
            self.mesh.map.push(*map);
        }
        if let Some(value) = v.maps.get(1) {
            self.mesh.values.push(*value);
        }
        verts.index[slot] = index;
        index
    }

    /// Writes the triangle of three vertex slots.
    #[inline(always)]
    fn triangle(&mut self, verts: &mut NodeVerts<L>, slots: [usize; 3]) {
        let a = self.vertex(verts, slots[0]);
        let b = self.vertex(verts, slots[1]);
        let c = self.vertex(verts, slots[2]);
        self.mesh.indices.extend_from_slice(&[a, b, c]);
    }

    /// Draws refined node `(a, b)` of `level` with morphed `corners` (NE, NW,
    /// SW, SE) and morph weight `t`, culling against the planes in `mask`.
    ///
    /// `known[e]` is the criterion of the neighbour across edge `e` (E, N, W,
    /// S) when the caller has it (a sibling's, computed by the parent), else
    /// NaN.
    fn node(
        &mut self,
        level: usize,
        a: u32,
        b: u32,
        corners: &[Vtx<L>; 4],
        t: f32,
        known: [f32; 4],
        mut mask: u32,
    ) {
        let lv = self.level[level];
        let (ci, cj) = (lv.half + a * lv.cells, lv.half + b * lv.cells);
        let half = lv.half;
        let centre_height = self.height(ci, cj);
        if mask != 0 {
            let mut lo = centre_height - lv.bound;
            let mut hi = centre_height + lv.bound;
            for c in corners {
                lo = lo.min(c.h);
                hi = hi.max(c.h);
            }
            hi += self.layer_margin;
            let x0 = (ci - half) as f32 * self.spacing[0];
            let x1 = (ci + half) as f32 * self.spacing[0];
            let z0 = (cj - half) as f32 * self.spacing[1];
            let z1 = (cj + half) as f32 * self.spacing[1];
            match self.cull(mask, [x0, lo, z0], [x1, hi, z1]) {
                Some(m) => mask = m,
                None => {
                    self.stats.culled += 1;
                    return;
                }
            }
        }
        self.stats.nodes += 1;
        self.stats.deepest_level = self.stats.deepest_level.max(level as u32);

        // The centre, morphed from its parity diagonal.
        let (da, db) = if (a + b) & 1 == 0 {
            (&corners[2], &corners[0])
        } else {
            (&corners[1], &corners[3])
        };
        let centre = blend(t, &self.true_vertex(ci, cj), da, db);

        // The ring: corners as given, edge midpoints morphed with the minimum
        // weight of the two nodes sharing the edge, present only when the
        // neighbour is refined too (or the edge is on the terrain boundary).
        let mut ring = [Vtx::ZERO; 8];
        ring[1] = corners[0];
        ring[3] = corners[1];
        ring[5] = corners[2];
        ring[7] = corners[3];
        let side = 1u32 << level;
        let mut present = [true; 4];
        let mut edge_weight = [t; 4];
        let neighbours = [
            (a + 1 < side).then(|| (a + 1, b)),
            (b + 1 < side).then(|| (a, b + 1)),
            (a > 0).then(|| (a.wrapping_sub(1), b)),
            (b > 0).then(|| (a, b.wrapping_sub(1))),
        ];
        for (e, neighbour) in neighbours.into_iter().enumerate() {
            if let Some((na, nb)) = neighbour {
                let f = if known[e].is_nan() {
                    self.criterion(level, na, nb)
                } else {
                    known[e]
                };
                if f < 1.0 {
                    edge_weight[e] = t.min(self.morph_weight(f));
                } else {
                    present[e] = false;
                }
            }
        }

        // Children.
        let mut child_f = [f32::INFINITY; 4];
        let child_ab = [
            (2 * a + 1, 2 * b + 1),
            (2 * a, 2 * b + 1),
            (2 * a, 2 * b),
            (2 * a + 1, 2 * b),
        ];
        let mut refined = [false; 4];
        if level + 1 < self.levels {
            for q in 0..4 {
                let (qa, qb) = child_ab[q];
                child_f[q] = self.criterion(level + 1, qa, qb);
                refined[q] = child_f[q] < 1.0;
            }
            // A refined child needs both midpoints on its side; the
            // propagation guarantees them, this only keeps the mesh whole if
            // rounding ever disagreed (then the midpoint sits at its coarse
            // value, on the coarse edge).
            for e in 0..4 {
                let needed = refined[e] || refined[(e + 3) & 3];
                if needed && !present[e] {
                    self.stats.one_level_repairs += 1;
                    present[e] = true;
                    edge_weight[e] = 0.0;
                }
            }
        }
        for e in 0..4 {
            let slot = 2 * e;
            let (p, q) = (ring[(slot + 7) & 7], ring[slot + 1]);
            if present[e] {
                let i = (ci as i32 + RING_I[slot] * half as i32) as u32;
                let j = (cj as i32 + RING_J[slot] * half as i32) as u32;
                let own = self.true_vertex(i, j);
                ring[slot] = blend(edge_weight[e], &own, &p, &q);
            }
        }

        // Items: every sector (between ring vertices k and k+1) belongs to a
        // child (two sectors), a fan triangle (one sector) or a fan triangle
        // over a skipped midpoint (two sectors). An item is keyed by its first
        // sector counter-clockwise.
        let mut start = [0u8; 8];
        let mut span = [0u8; 8];
        for k in 0..8 {
            let q = k >> 1;
            if refined[q] {
                start[k] = (2 * q) as u8;
                span[2 * q] = 2;
            } else if k & 1 == 0 {
                if present[k >> 1] {
                    start[k] = k as u8;
                    span[k] = 1;
                } else {
                    let s = (k + 7) & 7;
                    start[k] = s as u8;
                    span[s] = 2;
                }
            } else {
                start[k] = k as u8;
                span[k] = if present[((k + 1) & 7) >> 1] { 1 } else { 2 };
            }
        }

        let mut verts = NodeVerts {
            ci,
            cj,
            half,
            ring,
            centre,
            index: [u32::MAX; 9],
        };
        let children = Children {
            level,
            f: child_f,
            ab: child_ab,
            mask,
        };
        match self.order {
            TriangleOrder::Unordered => {
                for k in 0..8 {
                    if usize::from(start[k]) == k {
                        self.item(&mut verts, k, span[k], &children);
                    }
                }
            }
            order => {
                let dx = self.eye[0] - ci as f32 * self.spacing[0];
                let dz = self.eye[1] - cj as f32 * self.spacing[1];
                // Compare |dx|/spacing.x with |dz|/spacing.z: sectors are 45°
                // in grid units.
                let ax = dx.abs() * self.spacing[1];
                let az = dz.abs() * self.spacing[0];
                let eye_sector = match (dx >= 0.0, dz >= 0.0) {
                    (true, true) => usize::from(az >= ax),
                    (false, true) => 2 + usize::from(ax >= az),
                    (false, false) => 4 + usize::from(az >= ax),
                    (true, false) => 6 + usize::from(ax >= az),
                };
                // Wedges around the centre: the one holding the direction
                // away from the eye is farthest, the one holding the eye's
                // direction nearest, and the wedges between them form two
                // chains (counter-clockwise and clockwise), each ordered from
                // the far one to the near one by the side of their shared ray
                // the eye is on. The chains are independent (no ray from the
                // eye crosses the line through the eye and the centre twice).
                let back = (eye_sector + 4) & 7;
                let front = usize::from(start[eye_sector]);
                let mut sequence = [usize::MAX; 8];
                let mut count = 0;
                let mut add = |item: usize, sequence: &mut [usize; 8]| {
                    if !sequence[..count].contains(&item) {
                        sequence[count] = item;
                        count += 1;
                    }
                };
                add(usize::from(start[back]), &mut sequence);
                for depth in 1..4 {
                    for k in [(back + depth) & 7, (back + 8 - depth) & 7] {
                        let item = usize::from(start[k]);
                        if item != front {
                            add(item, &mut sequence);
                        }
                    }
                }
                add(front, &mut sequence);
                let items = &sequence[..count];
                if order == TriangleOrder::BackToFront {
                    for &s in items {
                        self.item(&mut verts, s, span[s], &children);
                    }
                } else {
                    for &s in items.iter().rev() {
                        self.item(&mut verts, s, span[s], &children);
                    }
                }
            }
        }
    }

    /// Emits the item starting at sector `s`: a child subtree or a fan
    /// triangle.
    #[inline(always)]
    fn item(&mut self, verts: &mut NodeVerts<L>, s: usize, span: u8, children: &Children) {
        if span == 2 && s & 1 == 0 {
            let q = s >> 1;
            let r = &verts.ring;
            let c = verts.centre;
            let corners = match q {
                0 => [r[1], r[2], c, r[0]],
                1 => [r[2], r[3], r[4], c],
                2 => [c, r[4], r[5], r[6]],
                _ => [r[0], c, r[6], r[7]],
            };
            let (qa, qb) = children.ab[q];
            let f = &children.f;
            let t = self.morph_weight(f[q]);
            // Siblings: Q0 (NE) has Q1 to the W and Q3 to the S, and so on.
            let nan = f32::NAN;
            let known = match q {
                0 => [nan, nan, f[1], f[3]],
                1 => [f[0], nan, nan, f[2]],
                2 => [f[3], f[1], nan, nan],
                _ => [nan, f[0], f[2], nan],
            };
            self.node(
                children.level + 1,
                qa,
                qb,
                &corners,
                t,
                known,
                children.mask,
            );
        } else {
            let end = (s + usize::from(span)) & 7;
            self.triangle(verts, [CENTRE, end, s]);
        }
    }
}

/// The children of a node being drawn.
struct Children {
    level: usize,
    f: [f32; 4],
    ab: [(u32, u32); 4],
    mask: u32,
}
