//! Terrain C-LOD: Röttger's quadtree with geomorphing.
//!
//! Röttger 2004 §3.5.3 (Eq. 3.2 and Fig. 3.9), with the semantics of the
//! author's libMini, in pure Rust: [`TerrainHierarchy`] is built once per
//! height field, [`TerrainHierarchy::update`] turns it into a morphed,
//! crack-free triangle mesh for an eye every frame.
//!
//! The [`HeightField`] has `2^k + 1` points per side
//! ([`pad_to_power_of_two_plus_one`] pads other sizes). Every node stores its
//! roughness `d2`, the largest second difference over its edges and one
//! diagonal over its size, in one byte (about 1/3 byte per grid point besides
//! the f32 heights; [`TerrainHierarchy::check_budget`] checks the memory budget
//! first). Extra sources such as a fog's thickness add their own roughness
//! ([`TerrainHierarchy::with_extra_roughness`]). `d2` is propagated bottom-up
//! to the parent and to the parent's neighbours with libMini's factor
//! `K = C / (2C − x)` ([`propagation_factor`]), which needs the minimum
//! resolution `C > √10/2` ([`MIN_RESOLUTION_LOWER_BOUND`]): then a node refines
//! whenever one of its children or a child of a neighbour would, so
//! neighbouring leaves differ by at most one level and skipping the T-vertices
//! makes the mesh crack-free.
//!
//! A node refines when `f = l² / (d² · max(c · d2, C)²) < 1` (Eq. 3.2 squared,
//! libMini's form), with `d` its size, `c` = [`LodSettings::accuracy`] and `l`
//! the distance from the eye to its centre, measured vertically to the
//! terrain's height range. A left-out detail then subtends at most
//! `1 / (2c · (1 − 1/(2C)))` radians; [`accuracy_for_pixel_error`] turns a
//! tolerance in pixels into `c`. New vertices geomorph from the coarse mesh
//! with the weight `t = min(1, (1 − f) / (3/4))`, the same in every fan, so
//! nothing pops.
//!
//! The output is a [`TerrainMesh`] of triangle fans, positions relative to
//! [`TerrainHierarchy::origin`], with morphed normals of the true grid
//! ([`LodSettings::normals`]), frustum culling, and triangles back to front,
//! front to back or unordered ([`TriangleOrder`]): the order vertical fog
//! prisms over the triangles need.
//!
//! The derivations (why the propagation factor keeps the refinement consistent,
//! the error bound, the morph rule, the order of the fans, the culling boxes
//! and the memory layout) are in `docs/quadtree-lod.md` in the repository.

mod hierarchy;
mod map;
mod mesh;
mod pixel_error;
mod refiner;

pub use hierarchy::{TerrainHierarchy, pad_to_power_of_two_plus_one};
pub use map::TerrainMap;
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
    /// A [`TerrainMap`]'s values are not one per grid point.
    #[error("a terrain map of {side}×{side} points needs {} values, but it has {len}", side * side)]
    MapLength {
        /// Points per side of the terrain.
        side: usize,
        /// The number of values given.
        len: usize,
    },
    /// A map to resample into a [`TerrainMap`] is empty or its values do
    /// not fill its size.
    #[error("a map of {dims:?} points needs that many values (at least one), but it has {len}")]
    MapSize {
        /// Points per axis `[width, height]` of the map.
        dims: [usize; 2],
        /// The number of values given.
        len: usize,
    },
    /// A map value is NaN or infinite.
    #[error("map value {index} is {value}; every value must be finite")]
    NonFiniteMapValue {
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

impl TerrainError {
    /// `Err` of [`TerrainError::MapLength`] unless `len` is `side²` and
    /// `side` at least 2.
    pub(crate) fn check_map_length(side: usize, len: usize) -> Result<(), Self> {
        if side >= 2 && side.checked_mul(side) == Some(len) {
            return Ok(());
        }
        Err(Self::MapLength { side, len })
    }

    /// `Err` of [`TerrainError::InvalidParameter`] unless `ok`.
    pub(crate) fn check(
        ok: bool,
        parameter: &'static str,
        value: impl Into<f64>,
        requirement: &'static str,
    ) -> Result<(), Self> {
        if ok {
            return Ok(());
        }
        Err(Self::InvalidParameter {
            parameter,
            value: value.into(),
            requirement,
        })
    }
}

#[cfg(test)]
mod tests;
