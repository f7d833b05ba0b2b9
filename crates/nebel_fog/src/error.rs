//! Why a ground fog is not drawn: [`GroundFogError`].

use std::sync::Arc;

use bevy::asset::AssetLoadError;
use bevy::prelude::*;
use nebel_core::field::FieldError;
use nebel_core::transfer::TransferError;
use nebel_lod::{PrismError, TerrainError};
use nebel_render::InvalidSetting;
use thiserror::Error;

/// Why a [`GroundFog`](crate::GroundFog) draws nothing. Every message names
/// the setting or file at fault.
#[derive(Clone, Debug, Error, Reflect)]
#[reflect(opaque, Clone, Debug, PartialEq)]
pub enum GroundFogError {
    /// The entity has a `GroundFog` but no `Terrain` to lie on.
    #[error("a ground fog needs a Terrain on the same entity; this one has none")]
    NoTerrain,
    /// The fog map asset failed to load.
    #[error("cannot load the fog map {path}: {error}")]
    MapNotLoaded {
        /// The asset path, or `(no path)` for an asset added in memory.
        path: String,
        /// The asset server's error.
        error: Arc<AssetLoadError>,
    },
    /// A setting is out of its range.
    #[error(transparent)]
    InvalidSetting(#[from] InvalidSetting),
    /// The noise or valley generator refused its settings.
    #[error(transparent)]
    Field(Arc<FieldError>),
    /// The fog map or its terrain map was refused (NaN values, a bad size).
    #[error(transparent)]
    Layer(Arc<TerrainError>),
    /// The vertical profile is not a function on [0, 1].
    #[error(transparent)]
    Prisms(#[from] PrismError),
    /// The transfer function could not be scaled by the density.
    #[error(transparent)]
    Transfer(Arc<TransferError>),
}

impl From<FieldError> for GroundFogError {
    fn from(error: FieldError) -> Self {
        Self::Field(Arc::new(error))
    }
}

impl From<TerrainError> for GroundFogError {
    fn from(error: TerrainError) -> Self {
        Self::Layer(Arc::new(error))
    }
}

impl From<TransferError> for GroundFogError {
    fn from(error: TransferError) -> Self {
        Self::Transfer(Arc::new(error))
    }
}

nebel_render::eq_by_message!(GroundFogError);
