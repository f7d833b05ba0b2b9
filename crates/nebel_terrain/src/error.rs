//! Why a terrain could not be built: [`TerrainBuildError`].

use std::sync::Arc;

use bevy::asset::AssetLoadError;
use bevy::prelude::*;
use nebel_core::field::FieldError;
use nebel_lod::TerrainError;
use nebel_lod::quadtree::MAX_TERRAIN_SIDE;
use nebel_render::InvalidSetting;
use thiserror::Error;

/// Why a [`Terrain`](crate::Terrain) has no mesh. Every message names the
/// setting, file or grid point at fault.
#[derive(Clone, Debug, Error, Reflect)]
#[reflect(opaque, Clone, Debug, PartialEq)]
pub enum TerrainBuildError {
    /// The height map asset failed to load.
    #[error("cannot load the height map {path}: {error}")]
    HeightsNotLoaded {
        /// The asset path, or `(no path)` for an asset added in memory.
        path: String,
        /// The asset server's error.
        error: Arc<AssetLoadError>,
    },
    /// A procedural source with too few or too many points per side.
    #[error("a procedural terrain of {size} points per side: it must have 2 to {MAX_TERRAIN_SIDE}")]
    ProceduralSize {
        /// The points per side asked for.
        size: u32,
    },
    /// `spacing` is not finite and positive, or `vertical_scale` not
    /// finite.
    #[error(transparent)]
    InvalidSetting(#[from] InvalidSetting),
    /// The height map has fewer than 2 points along a side.
    #[error("the height map has {nx} × {nz} points; a terrain needs at least 2 × 2")]
    TooSmall {
        /// Points along x.
        nx: usize,
        /// Points along z.
        nz: usize,
    },
    /// The height map has more points along a side than the quadtree takes.
    #[error(
        "the height map has {nx} × {nz} points; the largest terrain side is {MAX_TERRAIN_SIDE}"
    )]
    TooLarge {
        /// Points along x.
        nx: usize,
        /// Points along z.
        nz: usize,
    },
    /// The height map's values do not fill its grid.
    #[error("the height map is {nx} × {nz} points but holds {count} values")]
    ValueCount {
        /// Points along x.
        nx: usize,
        /// Points along z.
        nz: usize,
        /// Values present.
        count: usize,
    },
    /// A height is NaN or infinite after scaling.
    #[error(
        "height at grid point ({i}, {j}) is {height} ({unit} × vertical_scale {scale}); every height must be finite"
    )]
    NonFiniteHeight {
        /// Column of the grid point.
        i: usize,
        /// Row of the grid point.
        j: usize,
        /// The scaled height.
        height: f32,
        /// The unit height.
        unit: f32,
        /// The vertical scale.
        scale: f32,
    },
    /// The procedural generator or the height field refused its input.
    #[error(transparent)]
    Field(Arc<FieldError>),
    /// The quadtree refused its input or the view.
    #[error(transparent)]
    Quadtree(Arc<TerrainError>),
}

impl From<FieldError> for TerrainBuildError {
    fn from(error: FieldError) -> Self {
        Self::Field(Arc::new(error))
    }
}

impl From<TerrainError> for TerrainBuildError {
    fn from(error: TerrainError) -> Self {
        Self::Quadtree(Arc::new(error))
    }
}

nebel_render::eq_by_message!(TerrainBuildError);
