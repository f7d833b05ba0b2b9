//! Terrain C-LOD: Röttger's quadtree with geomorphing (Röttger 2004 §3.5.3,
//! Eq. 3.2 and Fig. 3.9; the author's libMini is the reference
//! implementation). Pure Rust, no Bevy: [`TerrainHierarchy`] is built once per
//! height field, [`TerrainHierarchy::update`] turns it into a morphed,
//! crack-free triangle mesh for an eye every frame.
//!
//! # Grid, nodes and levels
//!
//! The height field has `n × n` points with `n = 2^k + 1`, `k ≥ 1` (other sizes
//! are a [`TerrainError::NotPowerOfTwoPlusOne`]; [`pad_to_power_of_two_plus_one`]
//! replicates the last row and column up to the next such square). Level `L`
//! (`0` = the root, `k − 1` = the finest) has `2^L × 2^L` nodes of `s = 2^(k−L)`
//! grid cells; node `(a, b)` covers points `a·s ..= (a+1)·s` along x (index `i`)
//! and `b·s ..= (b+1)·s` along z (index `j`), its centre is `(a·s + s/2,
//! b·s + s/2)`. Its size in world units is `d = s · max(spacing.x, spacing.z)`.
//!
//! # Roughness d2
//!
//! For a node with corners `NE, NW, SW, SE`, edge midpoints and centre `m`,
//! the local roughness is the largest second difference over its four edges
//! and one diagonal, over the node size:
//!
//! `d2_local = max(|a + b − 2m|) / d`
//!
//! with `(a, b)` the two ends of each edge for the edge's midpoint `m`, and for
//! the centre the diagonal **SW–NE when `a + b` is even, NW–SE when it is odd**
//! (checkerboard parity, as libMini): that diagonal joins the node's corner at
//! its parent's centre to the opposite corner, so it is an edge of the
//! parent's triangle fan and `(a + b)/2` is what the coarser mesh shows at the
//! centre. Extra sources ([`TerrainHierarchy::with_extra_roughness`], a fog
//! thickness map, say) enter as `weight · d2_local(source)`; the
//! node keeps the maximum over all sources, then propagation runs unchanged.
//!
//! # Propagation (the one-level rule)
//!
//! Bottom-up, level by level, every node takes
//!
//! `d2 = max(d2_local, K_p · d2(children), K_n · d2(children of its four
//! neighbours that touch it))`
//!
//! that is, every child pushes its d2 to its parent and to its parent's two
//! same-level neighbours across the child's outer edges (libMini's
//! `propagate`), with libMini's factor `K = C / (2C − x)`, `x` the horizontal
//! distance between the child's centre and the target's centre in child
//! sizes: `x = √2/2` for the parent ([`PARENT_FACTOR_DISTANCE`]) and
//! `x = √10/2` for the parent's neighbours ([`NEIGHBOUR_FACTOR_DISTANCE`]),
//! both enlarged by 0.1 % so rounding never breaks the inequality below.
//! `C` is the minimum resolution ([`TerrainHierarchy::min_resolution`], at
//! least [`MIN_RESOLUTION_LOWER_BOUND`]).
//!
//! Why this factor: with `M = max(c·d2, C)`, a child (size `d_c`) refines when
//! `l_c < d_c·M_c`; the target (size `2 d_c`) is at most `x·d_c` farther from
//! the eye, so it refines too if `M_t ≥ (M_c + x)/2`. For `M_c ≤ 2C − x` the
//! floor `C` of `M_t` is enough (this needs `C ≥ x`, hence the lower bound
//! `C > √10/2`); above it `c·d2_t ≥ K·c·d2_c` is, since `M_c·(2K − 1) ≥ x`.
//! So for every eye and every `c`: **a node refines whenever one of its
//! children would, and whenever a child of one of its neighbours would**.
//! The first makes "refined" the same as "`f < 1`" (no node below an
//! unrefined one passes the test), the second makes neighbouring leaves differ
//! by at most one level, so skipping the T-vertices is all it takes to be
//! crack-free.
//!
//! # Refinement criterion (Eq. 3.2, squared, libMini's form)
//!
//! A node refines when
//!
//! `f = l² / (d² · max(c · d2, C)²) < 1`
//!
//! (libMini's `max(c·d2, C)`; the 1998 paper's `C·max(c·d2, 1)` is the same
//! criterion with `c` scaled by `C`). `c` is [`LodSettings::accuracy`], per
//! frame; `C` is fixed when the hierarchy is built, because the propagation
//! depends on it.
//!
//! `l² = h² + v²`: `h` is the horizontal distance from the eye to the node's
//! centre; `v` is the vertical distance from the eye to the terrain's height
//! range `[min, max]` (0 when the eye's height lies inside it, so also for an
//! eye below the terrain's top). `v` is the same for every node, so `l` is a
//! 1-Lipschitz function of the node's horizontal position, which is what the
//! propagation needs (libMini does the same with the eye's height above the
//! ground below it). Using each node's own height instead would let one steep
//! spike break the one-level rule. Since every terrain point lies in the
//! height range, `l` never exceeds the 3D distance from the eye to the node's
//! centre: the mesh is never coarser than the 3D distance would make it. The
//! eye on a vertex (`l = 0`) just gives `f = 0`.
//!
//! Error bound implied by `c`: a node that is not refined has
//! `|a + b − 2m|/2 ≤ d2·d/2 ≤ l/(2c)`, so every detail the mesh leaves out
//! (the deviation of a point from the coarse mesh one level up) subtends at
//! most `1 / (2c · (1 − 1/(2C)))` radians vertically from the eye (the
//! `1 − 1/(2C)` accounts for the point being up to `d/2` nearer than the
//! node's centre). This holds for d2 up to the largest stored code (about
//! 676, a slope change of 676:1 across a node); beyond it a node refines
//! a little late.
//!
//! [`accuracy_for_pixel_error`] turns a tolerance in pixels into the `c` that
//! keeps this angle within that many pixels of a perspective projection and
//! viewport.
//!
//! # Geomorphing
//!
//! A refined node gets the weight `t = min(1, (1 − f) / (3/4))`: 1 for
//! `f ≤ 1/4`, falling linearly to 0 at `f = 1`, where it refines (libMini's
//! `340 − 340 f` in 1/255 units). Its new vertices take
//!
//! `h = t · h_true + (1 − t) · (h_a + h_b) / 2`
//!
//! with `(h_a, h_b)` the *morphed* values of the two coarse endpoints (the
//! diagonal above for the centre, the edge's ends for an edge midpoint). An
//! edge midpoint uses the minimum weight of the two nodes sharing the edge
//! (only the node's own on the terrain boundary), children's corners take the
//! parent's morphed values, so every vertex gets the same value in every fan
//! it belongs to (bit for bit) and a node appears exactly where the coarse
//! mesh was: nothing pops. [`LodSettings::morph`] = `false` forces every
//! weight to 1.
//!
//! # Output
//!
//! A triangle fan per leaf around its centre (up to eight triangles), in a
//! [`TerrainMesh`]: an indexed triangle list, counter-clockwise seen from
//! above (+y), the same vertex written once per fan. Edge midpoints next to a
//! coarser neighbour are skipped. Positions are f32 **relative to the terrain
//! origin** [`TerrainHierarchy::origin`] = (height field origin x, 0, height
//! field origin z): point `(i, j)` at `(i·spacing.x, h, j·spacing.z)`, the
//! height absolute. A Bevy `Transform` at the origin places the mesh, so a
//! terrain 100 km from the world origin keeps millimetre precision.
//!
//! Normals ([`LodSettings::normals`]) come from the true grid, not from the
//! mesh: the height gradient by central differences at each grid point
//! (one-sided on the boundary), morphed with the same weight as the height
//! (`g = t·g_true + (1 − t)·(g_a + g_b)/2`) and turned into `normalize(−g_x, 1,
//! −g_z)`. Like the heights they are the same in every fan and never pop, and
//! a fully refined region shows the true normals of the height field.
//!
//! Order ([`TriangleOrder`]): back to front, front to back or unordered. In a
//! node, the children and fan triangles are wedges around the centre (a
//! child or a triangle over a skipped midpoint spans two of the eight 45°
//! sectors). Back to front, the wedge holding the direction from the eye
//! through the centre (projected on the ground) comes first, the wedge
//! holding the eye's direction last, and the wedges between them in two
//! chains, counter-clockwise and clockwise, each from the far end to the near
//! one: two wedges sharing a ray are ordered by the side of that ray's line
//! the eye is on, which is the order "by the side of each split line the eye
//! is on" for the children, and no ray from the eye crosses from one chain to
//! the other. Front to back is the reverse. Nested, this orders the whole
//! mesh for the eye's ground projection, the order vertical fog prisms over
//! the triangles need.
//!
//! Frustum culling: a node is skipped with its subtree when its box misses the
//! frustum. The box is exact horizontally; vertically it spans the node's true
//! centre height ± the level's height bound (the largest `|h − h_centre|` over
//! the points of any node of that level) and the node's morphed corner
//! heights, which bounds every morphed vertex inside (all are convex
//! combinations of those). Planes a node lies entirely inside are not tested
//! again for its descendants.
//!
//! # Memory
//!
//! Besides the f32 heights (the [`HeightField`], 4 bytes per point) one byte
//! per node: `d2` quantised on a logarithmic scale rounded up
//! ([`TerrainHierarchy::roughness`]), about `(n − 1)² / 3` bytes, i.e. 1/3 byte
//! per grid point, plus one f32 per level. Nothing is stored per frame: the
//! refinement state of a neighbour is recomputed from its `d2` when a midpoint
//! needs it, so there is nothing to clear and nothing stale.
//!
//! Building needs, for a while, the height ranges of the two finest levels
//! (8 bytes per node, about 2.5 bytes per grid point) besides the codes;
//! [`TerrainHierarchy::check_budget`] checks both against the memory budget
//! of `nebel_core::budget` before anything is allocated, and
//! [`pad_to_power_of_two_plus_one`] checks the padded heights.
//!
//! # Cost
//!
//! Building: one pass per level (nine height reads per node for the local
//! d2, twelve code reads for the propagation) and one for the height bounds:
//! 16 ms for 1025², 65 ms for 2049², 240 ms for 4097². Per frame, `cargo bench
//! -p nebel_lod --bench quadtree` runs the libMini peer scenario (fBm terrain
//! 0..1000 m at 10 m spacing, eye 2000 m up looking along +x through a 60° ×
//! 4/3 frustum, moving 11 m per frame; see the bench's docs). At libMini
//! 8.8.6's triangle counts (c found by bisection, `C` = 2, morphing on,
//! unordered, no normals, like libMini's fans), the median update on the
//! shared two-core development machine took 0.73 ms for 51,792 triangles on
//! 2049² (libMini: 51,794 in 2.09 ms) and 1.82 ms for 114,996 triangles on
//! 4097² (libMini: 9.8 ms); back to front with normals 1.12 ms and 2.57 ms.
//! At libMini's default (1,109 triangles on 2049², 0.07 ms) 0.017 ms. 4.33
//! bytes per grid point (libMini: 5.0 with f32 heights).

mod hierarchy;
mod layer;
mod mesh;
mod pixel_error;
mod refiner;

pub use hierarchy::{TerrainHierarchy, pad_to_power_of_two_plus_one};
pub use layer::TerrainLayer;
pub use mesh::{LodSettings, LodStats, TerrainMesh, TriangleOrder};
pub use pixel_error::accuracy_for_pixel_error;
pub use refiner::{RefinerSettings, TerrainRefiner, TerrainView};

use glam::DVec3;
use nebel_core::budget::BudgetError;
use nebel_core::field::FieldError;
use thiserror::Error;

#[cfg(doc)]
use nebel_core::field::HeightField;

/// Default global accuracy `c`: with the default `C` a left-out detail
/// subtends at most `1/(2c (1 − 1/(2C)))` = 2.2 mrad (about two pixels on a
/// 1080-pixel, 60° view); geomorphing hides the changes.
pub const DEFAULT_ACCURACY: f32 = 300.0;

/// The largest terrain side in grid points (after padding): 8193² points
/// take about 290 MB with the quadtree.
pub const MAX_TERRAIN_SIDE: usize = 8193;

/// Default minimum resolution `C`: a node of size `d` is refined within
/// `C·d` of the eye whatever its roughness.
pub const DEFAULT_MIN_RESOLUTION: f32 = 2.0;

/// The smallest minimum resolution `C` accepted: the one-level rule needs
/// `C > √10/2 ≈ 1.581` (see the module docs); 1.6 leaves room for rounding.
pub const MIN_RESOLUTION_LOWER_BOUND: f32 = 1.6;

/// Distance between a child's centre and its parent's centre in child sizes,
/// `√2/2`, enlarged by 0.1 % (used in `K_p`).
pub const PARENT_FACTOR_DISTANCE: f32 = std::f32::consts::FRAC_1_SQRT_2 * 1.001;

/// Distance between a child's centre and the centre of its parent's
/// neighbour across one of the child's outer edges in child sizes, `√10/2`,
/// enlarged by 0.1 % (used in `K_n`).
pub const NEIGHBOUR_FACTOR_DISTANCE: f32 = 1.581_138_8 * 1.001;

/// libMini's propagation factor `K = C / (2C − x)` for the minimum resolution
/// `C` and a distance `x` in child sizes (see the module docs).
pub fn propagation_factor(min_resolution: f32, distance: f32) -> f32 {
    min_resolution / (2.0 * min_resolution - distance)
}

/// Why a terrain hierarchy could not be built or updated.
#[derive(Debug, Error)]
pub enum TerrainError {
    /// The height field is not a square of `2^k + 1` points per side.
    #[error(
        "the terrain quadtree needs a square height field of 2^k+1 points per side (3, 5, 9, ..., 1025, 2049, 4097), but it has {dims:?} points; pad it to {padded}×{padded} with quadtree::pad_to_power_of_two_plus_one (edge replicated)"
    )]
    NotPowerOfTwoPlusOne {
        /// Points per axis `[nx, nz]` of the field given.
        dims: [usize; 2],
        /// The side the padding helper would produce.
        padded: usize,
    },
    /// A height is NaN or infinite.
    #[error(
        "height at grid point ({i}, {j}) (index {index}) is {value}; every height must be finite"
    )]
    NonFiniteHeight {
        /// Grid index along x.
        i: usize,
        /// Grid index along z.
        j: usize,
        /// Flat index `i + n·j` in the input.
        index: usize,
        /// The value found.
        value: f32,
    },
    /// A parameter is out of range.
    #[error("{parameter} = {value} is invalid: it must be {requirement}")]
    InvalidParameter {
        /// The parameter's name.
        parameter: &'static str,
        /// The value given.
        value: f64,
        /// What it must be.
        requirement: &'static str,
    },
    /// An extra roughness source does not have the terrain's points.
    #[error(
        "the extra roughness field has {extra:?} points but the terrain {terrain:?}; sample it at the terrain's grid points"
    )]
    DimsMismatch {
        /// Points per axis of the terrain.
        terrain: [usize; 2],
        /// Points per axis of the extra field.
        extra: [usize; 2],
    },
    /// A [`TerrainLayer`]'s values are not one per grid point.
    #[error("a terrain layer of {side}×{side} points needs {} values, but it has {len}", side * side)]
    LayerLength {
        /// Points per side of the terrain.
        side: usize,
        /// The number of values given.
        len: usize,
    },
    /// A map to resample into a [`TerrainLayer`] is empty or its values do
    /// not fill its size.
    #[error(
        "a layer map of {dims:?} points needs that many values (at least one), but it has {len}"
    )]
    LayerMapSize {
        /// Points per axis `[width, height]` of the map.
        dims: [usize; 2],
        /// The number of values given.
        len: usize,
    },
    /// A layer value is NaN or infinite.
    #[error("layer value {index} is {value}; every value must be finite")]
    NonFiniteLayer {
        /// Flat index of the value.
        index: usize,
        /// The value found.
        value: f32,
    },
    /// A pixel tolerance was asked for through a projection that is not a
    /// finite perspective one (an orthographic view shows far details as
    /// large as near ones, which the distance-based criterion cannot bound).
    #[error(
        "a terrain pixel error needs a finite perspective projection; give an orthographic camera an accuracy instead"
    )]
    PixelErrorNeedsPerspective,
    /// The eye position is NaN or infinite.
    #[error("the eye position {eye} is not finite")]
    NonFiniteEye {
        /// The eye given.
        eye: DVec3,
    },
    /// The height field could not be built (spacing, origin or size invalid).
    #[error(transparent)]
    Field(#[from] FieldError),
    /// The hierarchy or the padded height field would exceed the memory
    /// budget; nothing was allocated.
    #[error(transparent)]
    OverBudget(#[from] BudgetError),
}

#[cfg(test)]
mod tests;
