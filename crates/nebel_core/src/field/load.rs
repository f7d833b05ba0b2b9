//! Loaders for [`DensityGrid`] and [`HeightField`]: 8- and 16-bit grayscale PNG
//! and raw little-endian samples.
//!
//! Conventions (DESIGN.md §5, §6; Bevy is y-up):
//!
//! - A grayscale PNG maps its pixel values to [0, 1] (`v / 255` or `v / 65535`);
//!   image columns run along world x, rows (top row first) along world z.
//! - A height field or fog map multiplies that unit value by a vertical scale.
//! - A density volume is a stack of horizontal slices along world y, slice 0
//!   lowest: either one PNG per slice or one PNG holding all slices as tiles in
//!   reading order (left to right, then top to bottom). Each slice is then a
//!   top view, like a height field.
//! - Raw files hold samples without header, x fastest, little-endian
//!   ([`RawSampleType`]).

use std::path::{Path, PathBuf};

use glam::{DVec2, DVec3};
use image::DynamicImage;

use super::{DensityGrid, FieldError, HeightField};

/// The sample type of a raw little-endian file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum RawSampleType {
    /// One unsigned byte per sample; `v / 255` gives [0, 1]. The default.
    #[default]
    U8,
    /// Two bytes per sample, unsigned little-endian; `v / 65535` gives [0, 1].
    U16,
    /// Four bytes per sample, IEEE 754 little-endian, taken as they are.
    F32,
}

impl RawSampleType {
    /// Bytes per sample.
    pub fn bytes(self) -> usize {
        match self {
            Self::U8 => 1,
            Self::U16 => 2,
            Self::F32 => 4,
        }
    }

    /// Decodes `bytes` (a whole number of samples) into values: integers scaled
    /// to [0, 1], floats as stored.
    fn decode(self, bytes: &[u8]) -> Vec<f32> {
        match self {
            Self::U8 => bytes.iter().map(|&v| f32::from(v) / 255.0).collect(),
            Self::U16 => bytes
                .chunks_exact(2)
                .map(|b| f32::from(u16::from_le_bytes([b[0], b[1]])) / 65535.0)
                .collect(),
            Self::F32 => bytes
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
        }
    }
}

/// How raw density samples become densities in [0, 1].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Normalization {
    /// Keep the decoded values; they must lie in [0, 1]. The default.
    #[default]
    None,
    /// Divide by the largest value, so it becomes 1 and 0 stays 0 (empty space
    /// stays empty). Values must be ≥ 0; an all-zero volume stays zero.
    DivideByMax,
}

impl Normalization {
    /// Turns decoded `values` into densities as described above; `name` (the
    /// file) is for errors.
    fn apply(self, name: &str, values: &mut [f32]) -> Result<(), FieldError> {
        match self {
            Self::None => Ok(()),
            Self::DivideByMax => {
                super::check_finite(name, values)?;
                let max = values.iter().copied().fold(0.0f32, f32::max);
                if max > 0.0 {
                    values.iter_mut().for_each(|v| *v /= max);
                }
                Ok(())
            }
        }
    }
}

/// How a tiled PNG holds the slices of a density volume.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TileLayout {
    /// Tiles per image row; the image width must be a multiple of it.
    pub columns: u32,
    /// Tiles per image column; the image height must be a multiple of it.
    pub rows: u32,
    /// Slices used, in reading order, ≥ 2 and ≤ `columns · rows`.
    pub slices: u32,
}

/// A decoded grayscale PNG with values in [0, 1], row-major, top row first.
/// Reads the file at `path` and decodes it as PNG; `read_error` and
/// `decode_error` turn the file's path and the cause into the caller's error.
pub fn read_png<E>(
    path: &Path,
    read_error: impl FnOnce(PathBuf, std::io::Error) -> E,
    decode_error: impl FnOnce(PathBuf, image::ImageError) -> E,
) -> Result<DynamicImage, E> {
    let bytes = std::fs::read(path).map_err(|source| read_error(path.to_owned(), source))?;
    image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
        .map_err(|source| decode_error(path.to_owned(), source))
}

struct GrayImage {
    width: u32,
    height: u32,
    values: Vec<f32>,
}

fn read_file(path: &Path) -> Result<Vec<u8>, FieldError> {
    std::fs::read(path).map_err(|source| FieldError::Io {
        path: path.to_owned(),
        source,
    })
}

fn read_grayscale_png(path: &Path) -> Result<GrayImage, FieldError> {
    let image = read_png(
        path,
        |path, source| FieldError::Io { path, source },
        |path, source| FieldError::Decode { path, source },
    )?;
    let (width, height) = (image.width(), image.height());
    let values = match image {
        DynamicImage::ImageLuma8(buffer) => buffer
            .into_raw()
            .into_iter()
            .map(|v| f32::from(v) / 255.0)
            .collect(),
        DynamicImage::ImageLuma16(buffer) => buffer
            .into_raw()
            .into_iter()
            .map(|v| f32::from(v) / 65535.0)
            .collect(),
        other => {
            return Err(FieldError::NotGrayscale {
                path: path.to_owned(),
                found: format!("{:?}", other.color()),
            });
        }
    };
    Ok(GrayImage {
        width,
        height,
        values,
    })
}

/// Reads a raw file of `dims` samples, checking its length first.
fn read_raw(
    path: &Path,
    dims: &[usize],
    sample_type: RawSampleType,
) -> Result<Vec<f32>, FieldError> {
    let bytes = read_file(path)?;
    let expected = dims
        .iter()
        .fold(sample_type.bytes() as u128, |acc, &n| acc * n as u128);
    if expected != bytes.len() as u128 {
        return Err(FieldError::RawSizeMismatch {
            path: path.to_owned(),
            dims: dims.to_vec(),
            sample_type,
            expected,
            actual: bytes.len() as u64,
        });
    }
    Ok(sample_type.decode(&bytes))
}

impl HeightField {
    /// Loads an 8- or 16-bit grayscale PNG as a height field (terrain or fog
    /// thickness): height = unit pixel value · `vertical_scale` (world units).
    /// Columns run along x, rows along z (see the module docs); `spacing` and
    /// `origin` as in [`HeightField::new`].
    pub fn load_png(
        path: impl AsRef<Path>,
        spacing: DVec2,
        origin: DVec2,
        vertical_scale: f64,
    ) -> Result<Self, FieldError> {
        let path = path.as_ref();
        let image = read_grayscale_png(path)?;
        let dims = [image.width as usize, image.height as usize];
        Self::from_file_values(path, dims, image.values, vertical_scale, spacing, origin)
    }

    /// Loads a raw little-endian file of `dims = [nx, nz]` samples (x fastest):
    /// height = decoded value · `vertical_scale`, where integers decode to [0, 1]
    /// and f32 as stored.
    pub fn load_raw(
        path: impl AsRef<Path>,
        dims: [usize; 2],
        sample_type: RawSampleType,
        vertical_scale: f64,
        spacing: DVec2,
        origin: DVec2,
    ) -> Result<Self, FieldError> {
        let path = path.as_ref();
        let values = read_raw(path, &dims, sample_type)?;
        Self::from_file_values(path, dims, values, vertical_scale, spacing, origin)
    }

    /// The height field of `values` read from `path`: height = value ·
    /// `vertical_scale`, which must be finite. Errors name the file.
    fn from_file_values(
        path: &Path,
        dims: [usize; 2],
        values: Vec<f32>,
        vertical_scale: f64,
        spacing: DVec2,
        origin: DVec2,
    ) -> Result<Self, FieldError> {
        let name = path.display().to_string();
        super::check_vertical_scale(&name, vertical_scale)?;
        let heights = values
            .into_iter()
            .map(|v| (f64::from(v) * vertical_scale) as f32)
            .collect();
        Self::validated(&name, dims, spacing, origin, heights)
    }
}

impl DensityGrid {
    /// Loads a density volume from one 8- or 16-bit grayscale PNG per horizontal
    /// slice, lowest first. All slices must have the same size; the grid has
    /// `[width, slices, height]` points (see the module docs).
    pub fn load_png_slices(
        paths: &[impl AsRef<Path>],
        spacing: DVec3,
        origin: DVec3,
    ) -> Result<Self, FieldError> {
        let [first_path, ..] = paths else {
            return Err(FieldError::TooFewSlices { count: 0 });
        };
        if paths.len() < 2 {
            return Err(FieldError::TooFewSlices { count: paths.len() });
        }
        let first_path = first_path.as_ref();
        let first = read_grayscale_png(first_path)?;
        let (width, height) = (first.width, first.height);
        let mut slices = vec![first.values];
        for path in &paths[1..] {
            let path = path.as_ref();
            let slice = read_grayscale_png(path)?;
            if (slice.width, slice.height) != (width, height) {
                return Err(FieldError::SliceSizeMismatch {
                    path: path.to_owned(),
                    found: (slice.width, slice.height),
                    first: first_path.to_owned(),
                    expected: (width, height),
                });
            }
            slices.push(slice.values);
        }
        let tiles = slices.iter().map(|s| s.as_slice());
        let values = stack_slices(width as usize, height as usize, tiles);
        let dims = [width as usize, paths.len(), height as usize];
        Self::validated(
            &first_path.display().to_string(),
            dims,
            spacing,
            origin,
            values,
        )
    }

    /// Loads a density volume from one 8- or 16-bit grayscale PNG holding its
    /// horizontal slices as equal tiles in reading order ([`TileLayout`]).
    pub fn load_png_tiled(
        path: impl AsRef<Path>,
        layout: TileLayout,
        spacing: DVec3,
        origin: DVec3,
    ) -> Result<Self, FieldError> {
        let path = path.as_ref();
        let image = read_grayscale_png(path)?;
        let TileLayout {
            columns,
            rows,
            slices,
        } = layout;
        let fits = columns > 0
            && rows > 0
            && image.width % columns == 0
            && image.height % rows == 0
            && slices >= 2
            && u64::from(slices) <= u64::from(columns) * u64::from(rows);
        if !fits {
            return Err(FieldError::TileLayout {
                path: path.to_owned(),
                width: image.width,
                height: image.height,
                columns,
                rows,
                slices,
            });
        }
        let (tile_width, tile_height) = (
            (image.width / columns) as usize,
            (image.height / rows) as usize,
        );
        let image_width = image.width as usize;
        let mut tiles = Vec::with_capacity(slices as usize);
        for slice in 0..slices {
            let (column, row) = ((slice % columns) as usize, (slice / columns) as usize);
            let mut tile = Vec::with_capacity(tile_width * tile_height);
            for y in 0..tile_height {
                let start = (row * tile_height + y) * image_width + column * tile_width;
                tile.extend_from_slice(&image.values[start..start + tile_width]);
            }
            tiles.push(tile);
        }
        let values = stack_slices(tile_width, tile_height, tiles.iter().map(|t| t.as_slice()));
        let dims = [tile_width, slices as usize, tile_height];
        Self::validated(&path.display().to_string(), dims, spacing, origin, values)
    }

    /// Loads a raw little-endian density volume of `dims = [nx, ny, nz]` samples,
    /// x fastest, then y, then z (the [`DensityGrid`] order). Integers decode to
    /// [0, 1]; `normalization` says how values become densities in [0, 1].
    pub fn load_raw(
        path: impl AsRef<Path>,
        dims: [usize; 3],
        sample_type: RawSampleType,
        normalization: Normalization,
        spacing: DVec3,
        origin: DVec3,
    ) -> Result<Self, FieldError> {
        let path = path.as_ref();
        let name = path.display().to_string();
        let mut values = read_raw(path, &dims, sample_type)?;
        normalization.apply(&name, &mut values)?;
        Self::validated(&name, dims, spacing, origin, values)
    }
}

/// Interleaves horizontal slices (each `width × depth`, row = z) into the grid
/// order x fastest, then y (slice), then z (row).
fn stack_slices<'a>(
    width: usize,
    depth: usize,
    slices: impl ExactSizeIterator<Item = &'a [f32]> + Clone,
) -> Vec<f32> {
    let count = slices.len();
    let mut values = Vec::with_capacity(width * depth * count);
    for row in 0..depth {
        for slice in slices.clone() {
            values.extend_from_slice(&slice[row * width..(row + 1) * width]);
        }
    }
    values
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{assert_mentions, error_message};
    use std::path::PathBuf;

    /// A fresh directory for one test's files.
    fn temp_dir(test: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nebel-field-{}-{test}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// Whether `actual` and `expected` agree within `tolerance`, pair by pair.
    fn all_close(actual: &[f32], expected: &[f32], tolerance: f32) -> bool {
        actual
            .iter()
            .zip(expected)
            .all(|(a, e)| (a - e).abs() < tolerance)
    }

    fn save_gray8(path: &Path, width: u32, height: u32, values: &[u8]) {
        image::GrayImage::from_raw(width, height, values.to_vec())
            .unwrap()
            .save(path)
            .unwrap();
    }

    #[test]
    fn height_field_png_round_trips_in_8_and_16_bit() {
        let dir = temp_dir("height");
        let path8 = dir.join("height8.png");
        save_gray8(&path8, 3, 2, &[0, 51, 102, 153, 204, 255]);
        let field = HeightField::load_png(&path8, DVec2::ONE, DVec2::ZERO, 100.0).unwrap();
        assert_eq!(field.dims(), [3, 2]);
        let expected = [0.0, 20.0, 40.0, 60.0, 80.0, 100.0];
        assert!(all_close(field.heights(), &expected, 1e-4));
        assert_eq!(field.height(2, 1), 100.0);

        let path16 = dir.join("height16.png");
        let values: Vec<u16> = vec![0, 1, 65535, 32768];
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(2, 2, values)
            .unwrap()
            .save(&path16)
            .unwrap();
        let field = HeightField::load_png(&path16, DVec2::ONE, DVec2::ZERO, 65535.0).unwrap();
        assert_eq!(field.heights(), &[0.0, 1.0, 65535.0, 32768.0]);
    }

    #[test]
    fn density_slices_and_tiles_agree() {
        let dir = temp_dir("slices");
        // Three 2×2 slices; value = 10 · slice + 2 · row + column.
        let slice_values = |s: u8| [10 * s, 10 * s + 1, 10 * s + 2, 10 * s + 3];
        let paths: Vec<PathBuf> = (0..3)
            .map(|s| {
                let path = dir.join(format!("slice{s}.png"));
                save_gray8(&path, 2, 2, &slice_values(s));
                path
            })
            .collect();
        let stacked = DensityGrid::load_png_slices(&paths, DVec3::ONE, DVec3::ZERO).unwrap();
        assert_eq!(stacked.dims(), [2, 3, 2]);
        // Point (column 1, slice 2, row 1).
        assert_eq!(stacked.value(1, 2, 1), 23.0 / 255.0);
        assert_eq!(stacked.value(0, 1, 0), 10.0 / 255.0);

        // The same slices as a 2×2 tile layout (4 × 4 pixels, last tile unused).
        let mut tiled = vec![0u8; 16];
        for s in 0..3u8 {
            let (column, row) = (usize::from(s % 2), usize::from(s / 2));
            for y in 0..2 {
                for x in 0..2 {
                    tiled[(row * 2 + y) * 4 + column * 2 + x] = slice_values(s)[y * 2 + x];
                }
            }
        }
        let tiled_path = dir.join("tiled.png");
        save_gray8(&tiled_path, 4, 4, &tiled);
        let layout = TileLayout {
            columns: 2,
            rows: 2,
            slices: 3,
        };
        let from_tiles =
            DensityGrid::load_png_tiled(&tiled_path, layout, DVec3::ONE, DVec3::ZERO).unwrap();
        assert_eq!(from_tiles, stacked);

        let bad = TileLayout {
            columns: 3,
            ..layout
        };
        let message = error_message(DensityGrid::load_png_tiled(
            &tiled_path,
            bad,
            DVec3::ONE,
            DVec3::ZERO,
        ));
        assert_mentions(&message, &["tiled.png", "3×2 equal tiles"]);
        let too_many = TileLayout {
            slices: 5,
            ..layout
        };
        assert!(
            DensityGrid::load_png_tiled(&tiled_path, too_many, DVec3::ONE, DVec3::ZERO).is_err()
        );
    }

    #[test]
    fn png_errors_name_the_file() {
        let dir = temp_dir("png-errors");
        let load_height_png = |path: &Path, vertical_scale| {
            HeightField::load_png(path, DVec2::ONE, DVec2::ZERO, vertical_scale)
        };
        let missing = dir.join("missing.png");
        let message = error_message(load_height_png(&missing, 1.0));
        assert!(
            message.starts_with("cannot read") && message.contains("missing.png"),
            "{message}"
        );

        let not_png = dir.join("text.png");
        std::fs::write(&not_png, b"not an image").unwrap();
        let message = error_message(load_height_png(&not_png, 1.0));
        assert_mentions(&message, &["cannot decode", "text.png"]);

        let rgb = dir.join("rgb.png");
        image::RgbImage::new(2, 2).save(&rgb).unwrap();
        let message = error_message(load_height_png(&rgb, 1.0));
        assert_mentions(&message, &["rgb.png", "grayscale", "Rgb8"]);

        let small = dir.join("small.png");
        save_gray8(&small, 2, 2, &[0; 4]);
        let large = dir.join("large.png");
        save_gray8(&large, 3, 2, &[0; 6]);
        let load_slices =
            |paths: &[&PathBuf]| DensityGrid::load_png_slices(paths, DVec3::ONE, DVec3::ZERO);
        let message = error_message(load_slices(&[&small, &large]));
        assert_mentions(&message, &["large.png", "(3, 2)", "small.png"]);
        let message = error_message(load_slices(&[&small]));
        assert_mentions(&message, &["1 given"]);
        let message = error_message(load_height_png(&small, f64::NAN));
        assert_mentions(&message, &["small.png", "vertical_scale"]);
        let line = dir.join("line.png");
        save_gray8(&line, 5, 1, &[0; 5]);
        let message = error_message(load_height_png(&line, 1.0));
        assert_mentions(&message, &["line.png", "at least 2"]);
    }

    #[test]
    fn raw_volumes_round_trip_in_every_sample_type() {
        let dir = temp_dir("raw");
        let dims = [2, 2, 2];
        let expected: Vec<f32> = (0..8).map(|v| v as f32 / 7.0).collect();
        let load_volume = |path: &Path, dims, sample_type, normalization| {
            DensityGrid::load_raw(
                path,
                dims,
                sample_type,
                normalization,
                DVec3::ONE,
                DVec3::ZERO,
            )
        };

        let u8_path = dir.join("volume.u8");
        std::fs::write(&u8_path, [0u8, 36, 73, 109, 146, 182, 219, 255]).unwrap();
        let grid = load_volume(&u8_path, dims, RawSampleType::U8, Normalization::None).unwrap();
        assert!(all_close(grid.values(), &expected, 1.0 / 255.0));

        let u16_path = dir.join("volume.u16");
        let bytes: Vec<u8> = expected
            .iter()
            .flat_map(|v| ((v * 65535.0).round() as u16).to_le_bytes())
            .collect();
        std::fs::write(&u16_path, bytes).unwrap();
        let grid = load_volume(&u16_path, dims, RawSampleType::U16, Normalization::None).unwrap();
        assert!(all_close(grid.values(), &expected, 1e-4));

        let f32_path = dir.join("volume.f32");
        let write_f32 = |values: &[f32]| {
            let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            std::fs::write(&f32_path, bytes).unwrap();
        };
        write_f32(&expected);
        let load = |normalization| load_volume(&f32_path, dims, RawSampleType::F32, normalization);
        let grid = load(Normalization::None).unwrap();
        assert_eq!(grid.values(), expected.as_slice());

        // Physical densities: rescaled by their maximum.
        let physical: Vec<f32> = expected.iter().map(|v| v * 40.0).collect();
        write_f32(&physical);
        let message = error_message(load(Normalization::None));
        assert_mentions(&message, &["volume.f32", "outside [0, 1]"]);
        let grid = load(Normalization::DivideByMax).unwrap();
        assert!(all_close(grid.values(), &expected, 1e-6));

        let mut with_nan = expected.clone();
        with_nan[6] = f32::NAN;
        write_f32(&with_nan);
        for normalization in [Normalization::None, Normalization::DivideByMax] {
            let message = error_message(load(normalization));
            assert_mentions(&message, &["volume.f32", "sample 6 is NaN"]);
        }

        let message = error_message(load_volume(
            &u8_path,
            [2, 2, 3],
            RawSampleType::U8,
            Normalization::None,
        ));
        assert_mentions(&message, &["volume.u8", "need 12 bytes, the file has 8"]);

        let height = HeightField::load_raw(
            &u16_path,
            [4, 2],
            RawSampleType::U16,
            7.0,
            DVec2::ONE,
            DVec2::ZERO,
        )
        .unwrap();
        assert!((height.height(3, 1) - 7.0).abs() < 1e-5);
    }
}
