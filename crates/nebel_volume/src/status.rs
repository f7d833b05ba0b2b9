//! What became of a volume: [`VolumeStatus`] and [`VolumeError`].

use std::sync::Arc;

use bevy::asset::AssetLoadError;
use bevy::prelude::*;
use nebel_core::field::FieldError;
use nebel_lod::VolumeBatchError;
use nebel_render::EffectStatus;
use thiserror::Error;

/// What became of a [`Volume`](crate::Volume): pending, ready, or failed and why.
pub type VolumeStatus = EffectStatus<VolumeError>;

/// Why a volume is not drawn (or not updated). Every message names what is
/// at fault.
#[derive(Clone, Debug, Error, Reflect)]
#[reflect(opaque, Clone, Debug, PartialEq)]
pub enum VolumeError {
    /// The grid asset failed to load.
    #[error("cannot load the density grid {path}: {error}")]
    GridNotLoaded {
        /// The asset path, or `(no path)` for an asset added in memory.
        path: String,
        /// The asset server's error.
        error: Arc<AssetLoadError>,
    },
    /// A cloud's weather map failed to load.
    #[error("cannot load the weather map {path}: {error}")]
    WeatherMapNotLoaded {
        /// The asset path, or `(no path)` for an asset added in memory.
        path: String,
        /// The asset server's error.
        error: Arc<AssetLoadError>,
    },
    /// A generator (a cloud's noise) refused its settings.
    #[error("cannot generate the grid: {0}")]
    Generation(Arc<FieldError>),
    /// The batch could not be built (padding, light field, hierarchy) or
    /// updated for the view.
    #[error(transparent)]
    Batch(#[from] VolumeBatchError),
}

impl From<FieldError> for VolumeError {
    fn from(error: FieldError) -> Self {
        Self::Generation(Arc::new(error))
    }
}

nebel_render::eq_by_message!(VolumeError);
