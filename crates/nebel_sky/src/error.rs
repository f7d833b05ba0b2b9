//! Why an aurora or a cloud layer draws nothing: one error for both sky
//! layers, each message naming the layer and the setting or file at fault.

use std::sync::Arc;

use bevy::asset::AssetLoadError;
use bevy::prelude::*;
use nebel_core::field::FieldError;
use nebel_core::transfer::TransferError;
use nebel_lod::SurfaceLayerError;
use nebel_render::InvalidSetting;
use thiserror::Error;

/// Why an [`Aurora`](crate::Aurora) or a [`CloudLayer`](crate::CloudLayer)
/// draws nothing.
#[derive(Clone, Debug, Error, Reflect)]
#[reflect(opaque, Clone, Debug, PartialEq)]
pub enum SkyLayerError {
    /// A map asset failed to load.
    #[error("cannot load the {layer}'s map {path}: {error}")]
    MapNotLoaded {
        /// The layer: `aurora` or `cloud layer`.
        layer: &'static str,
        /// The asset path, or `(no path)` for an asset added in memory.
        path: String,
        /// The asset server's error.
        error: Arc<AssetLoadError>,
    },
    /// A setting is out of its range.
    #[error("{layer} {setting}")]
    InvalidSetting {
        /// The layer: `aurora` or `cloud layer`.
        layer: &'static str,
        /// The setting.
        setting: InvalidSetting,
    },
    /// The aurora's curtains or the cloud layer's noise refused its
    /// settings.
    #[error(transparent)]
    Field(Arc<FieldError>),
    /// The layer was refused (NaN in a map, a bad size or shape).
    #[error(transparent)]
    Layer(Arc<SurfaceLayerError>),
    /// The transfer function could not be scaled by the brightness or
    /// density.
    #[error(transparent)]
    Transfer(Arc<TransferError>),
}

impl SkyLayerError {
    /// `Err` of [`SkyLayerError::InvalidSetting`] of the `layer` unless
    /// `ok` ([`InvalidSetting::check`]).
    pub(crate) fn check(
        ok: bool,
        layer: &'static str,
        setting: &'static str,
        value: f32,
        requirement: &'static str,
    ) -> Result<(), Self> {
        InvalidSetting::check(ok, setting, value, requirement)
            .map_err(|setting| Self::InvalidSetting { layer, setting })
    }
}

impl From<FieldError> for SkyLayerError {
    fn from(error: FieldError) -> Self {
        Self::Field(Arc::new(error))
    }
}

impl From<SurfaceLayerError> for SkyLayerError {
    fn from(error: SurfaceLayerError) -> Self {
        Self::Layer(Arc::new(error))
    }
}

impl From<TransferError> for SkyLayerError {
    fn from(error: TransferError) -> Self {
        Self::Transfer(Arc::new(error))
    }
}

nebel_render::eq_by_message!(SkyLayerError);
