//! Grayscale maps as Bevy assets: [`GrayscaleMap`] and its PNG loader.
//!
//! A [`GrayscaleMap`] holds *unit* values on a grid, which each effect
//! scales: a terrain's heights (its `vertical_scale`), a ground fog's
//! thickness, a sky layer's surfaces or an aurora's footprint. Load an 8- or
//! 16-bit grayscale PNG with `asset_server.load::<GrayscaleMap>("map.png")`
//! (black = 0, white = 1; image columns run along +x, rows, top row first,
//! along +z, like `nebel_core::field::HeightField::load_png`), or build one
//! in memory with [`GrayscaleMap::from_field`] and add it to
//! `Assets<GrayscaleMap>`. [`GrayscaleMapPlugin`] registers both; every
//! plugin that reads maps adds it.
//!
//! [`GrayscaleMapLoader`] registers no file extension, so it never takes a
//! PNG that is loaded as an `Image`: Bevy picks it by the asset type asked
//! for. Use 16-bit maps for terrain; 8 bits give 256 height steps, visible
//! as terraces on gentle slopes.

use std::sync::Arc;

use bevy::asset::io::Reader;
use bevy::asset::{AssetLoadError, AssetLoader, LoadContext, LoadState};
use bevy::prelude::*;
use bevy::tasks::futures_lite::AsyncReadExt;
use nebel_core::budget::{BudgetError, MEMORY_BUDGET_BYTES};
use nebel_core::field::HeightField;
use thiserror::Error;

/// Unit heights on a regular grid, x fastest (see the module docs).
#[derive(Asset, TypePath, Clone, Debug, PartialEq)]
pub struct GrayscaleMap {
    /// Grid points along x (image columns) and z (image rows).
    pub dims: UVec2,
    /// `dims.x · dims.y` unit heights, point `(i, j)` at `i + dims.x · j`;
    /// usually in [0, 1], any finite value works (the terrain plugin refuses
    /// NaN and infinities, naming the point). Shared, so the background
    /// build of the quadtree reads them without a copy; change them with
    /// `Arc::make_mut`.
    pub values: Arc<Vec<f32>>,
}

impl GrayscaleMap {
    /// The height assets added, loaded or modified since `events` last read
    /// (what a build keyed on an asset rebuilds for).
    pub fn changed(events: &mut MessageReader<AssetEvent<GrayscaleMap>>) -> Vec<AssetId<Self>> {
        events
            .read()
            .filter_map(|event| match event {
                AssetEvent::Added { id }
                | AssetEvent::Modified { id }
                | AssetEvent::LoadedWithDependencies { id } => Some(*id),
                AssetEvent::Removed { .. } | AssetEvent::Unused { .. } => None,
            })
            .collect()
    }

    /// Why `handle` failed to load: its path (`(no path)` for an asset
    /// added in memory) and the asset server's error; `None` while it loads
    /// or once it is loaded.
    pub fn load_failure(
        handle: &Handle<Self>,
        asset_server: &AssetServer,
    ) -> Option<(String, Arc<AssetLoadError>)> {
        match asset_server.get_load_state(handle.id()) {
            Some(LoadState::Failed(error)) => Some((
                handle
                    .path()
                    .map_or_else(|| String::from("(no path)"), ToString::to_string),
                error,
            )),
            _ => None,
        }
    }

    /// The heights of `field` (its spacing and origin are not kept).
    pub fn from_field(field: &HeightField) -> Self {
        let [nx, nz] = field.dims();
        Self {
            dims: UVec2::new(nx as u32, nz as u32),
            values: Arc::new(field.heights().to_vec()),
        }
    }

    /// Decodes an 8- or 16-bit grayscale PNG: value / 255 or / 65535. The
    /// heights are checked against the memory budget from the PNG's header,
    /// before the image is decoded.
    pub fn from_png_bytes(bytes: &[u8]) -> Result<Self, GrayscaleMapError> {
        let reader = || {
            image::ImageReader::with_format(std::io::Cursor::new(bytes), image::ImageFormat::Png)
        };
        let (width, height) = reader().into_dimensions()?;
        HeightField::check_budget([width as usize, height as usize])?;
        let image = reader().decode()?;
        let dims = UVec2::new(image.width(), image.height());
        let values = match image {
            image::DynamicImage::ImageLuma8(buffer) => buffer
                .into_raw()
                .into_iter()
                .map(|v| f32::from(v) / 255.0)
                .collect(),
            image::DynamicImage::ImageLuma16(buffer) => buffer
                .into_raw()
                .into_iter()
                .map(|v| f32::from(v) / 65535.0)
                .collect(),
            other => {
                return Err(GrayscaleMapError::NotGrayscale {
                    found: format!("{:?}", other.color()),
                });
            }
        };
        Ok(Self {
            dims,
            values: Arc::new(values),
        })
    }
}

/// Why a height map could not be loaded.
#[derive(Debug, Error)]
pub enum GrayscaleMapError {
    /// The file could not be read.
    #[error("cannot read the height map: {0}")]
    Io(#[from] std::io::Error),
    /// The bytes are not a PNG.
    #[error("cannot decode the height map as PNG: {0}")]
    Decode(#[from] image::ImageError),
    /// The heights would exceed the memory budget.
    #[error(transparent)]
    OverBudget(#[from] BudgetError),
    /// The PNG has colour channels or alpha.
    #[error("expected an 8- or 16-bit grayscale PNG, found {found}; convert it to grayscale")]
    NotGrayscale {
        /// The colour type found, e.g. `Rgb8`.
        found: String,
    },
}

/// Registers the [`GrayscaleMap`] asset and its loader, once however many
/// plugins add it.
#[derive(Default)]
pub struct GrayscaleMapPlugin;

impl GrayscaleMapPlugin {
    /// Adds the plugin to `app` unless it is there already: for the plugins
    /// of the effects that read maps.
    pub fn add_once(app: &mut App) {
        if !app.is_plugin_added::<Self>() {
            app.add_plugins(Self);
        }
    }
}

impl Plugin for GrayscaleMapPlugin {
    fn build(&self, app: &mut App) {
        app.init_asset::<GrayscaleMap>()
            .register_asset_loader(GrayscaleMapLoader);
    }
}

/// Loads [`GrayscaleMap`] from grayscale PNGs (see the module docs).
#[derive(Clone, Copy, Debug, Default, TypePath)]
pub struct GrayscaleMapLoader;

impl AssetLoader for GrayscaleMapLoader {
    type Asset = GrayscaleMap;
    type Settings = ();
    type Error = GrayscaleMapError;

    async fn load(
        &self,
        reader: &mut dyn Reader,
        _settings: &(),
        _load_context: &mut LoadContext<'_>,
    ) -> Result<GrayscaleMap, GrayscaleMapError> {
        // A compressed PNG larger than the budget cannot decode within it.
        let mut bytes = Vec::new();
        reader
            .take(MEMORY_BUDGET_BYTES + 1)
            .read_to_end(&mut bytes)
            .await?;
        if bytes.len() as u64 > MEMORY_BUDGET_BYTES {
            return Err(GrayscaleMapError::OverBudget(BudgetError {
                what: String::from("height map file"),
                bytes: bytes.len() as u128,
                limit: MEMORY_BUDGET_BYTES,
            }));
        }
        GrayscaleMap::from_png_bytes(&bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png(image: image::DynamicImage) -> Vec<u8> {
        let mut bytes = std::io::Cursor::new(Vec::new());
        image.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
        bytes.into_inner()
    }

    #[test]
    fn decodes_8_and_16_bit_grayscale_and_refuses_colour() {
        let sixteen = image::ImageBuffer::<image::Luma<u16>, _>::from_raw(
            3,
            2,
            vec![0, 65535, 32768, 1, 2, 3],
        )
        .unwrap();
        let heights = GrayscaleMap::from_png_bytes(&png(sixteen.into())).unwrap();
        assert_eq!(heights.dims, UVec2::new(3, 2));
        assert_eq!(heights.values[1], 1.0);
        assert!((heights.values[2] - 32768.0 / 65535.0).abs() < 1e-7);

        let eight = image::GrayImage::from_raw(2, 2, vec![0, 255, 51, 0]).unwrap();
        let heights = GrayscaleMap::from_png_bytes(&png(eight.into())).unwrap();
        assert_eq!(*heights.values, vec![0.0, 1.0, 0.2, 0.0]);

        let colour = image::RgbImage::from_raw(1, 1, vec![1, 2, 3]).unwrap();
        let error = GrayscaleMap::from_png_bytes(&png(colour.into())).unwrap_err();
        assert!(error.to_string().contains("found Rgb8"), "{error}");
        let error = GrayscaleMap::from_png_bytes(b"not a png").unwrap_err();
        assert!(error.to_string().contains("cannot decode"), "{error}");

        // A header of 100 000 × 100 000 pixels: refused before decoding.
        let mut huge = Vec::new();
        let mut encoder = png::Encoder::new(&mut huge, 100_000, 100_000);
        encoder.set_color(png::ColorType::Grayscale);
        let mut writer = encoder.write_header().unwrap();
        writer.write_chunk(png::chunk::IDAT, &[]).unwrap();
        drop(writer);
        let error = GrayscaleMap::from_png_bytes(&huge).unwrap_err();
        assert!(matches!(error, GrayscaleMapError::OverBudget(_)), "{error}");
        assert!(error.to_string().contains("memory budget"), "{error}");
    }
}
