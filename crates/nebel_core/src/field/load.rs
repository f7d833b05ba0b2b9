//! Loaders for [`DensityGrid`] and [`HeightField`]: 8- and 16-bit grayscale PNG
//! and raw little-endian samples.
//!
//! Conventions:
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
//!
//! Sizes are checked against the memory budget before anything sized by the
//! file is allocated ([`FieldError::OverBudget`]): a raw file's dimensions
//! and length before it is read, a PNG's width and height from its header
//! before it is decoded (the decoder itself stays within the `image` crate's
//! default limit of 512 MiB of decoded pixels), a stack of slices as the
//! whole grid before the first slice is decoded.

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

use glam::{DVec2, DVec3};
use image::{DynamicImage, ImageFormat, ImageReader};

use super::{
    DENSITY_GRID, DensityGrid, FieldError, HEIGHT_FIELD, HeightField, SAMPLE_BYTES, budgeted_points,
};
use crate::budget::{Dims, check_allocation};

/// The sample type of a raw little-endian file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
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
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
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

/// Reads the PNG at `path`: its header first, whose width and height go to
/// `check_size` (a memory-budget check; nothing is decoded when it fails),
/// then the whole file, decoded as it is read. `read_error` and
/// `decode_error` turn the file's path and the cause into the caller's error.
pub fn read_png<E>(
    path: &Path,
    read_error: impl Fn(PathBuf, std::io::Error) -> E,
    decode_error: impl Fn(PathBuf, image::ImageError) -> E,
    check_size: impl FnOnce(u32, u32) -> Result<(), E>,
) -> Result<DynamicImage, E> {
    let reader = || {
        let file = File::open(path).map_err(|source| read_error(path.to_owned(), source))?;
        Ok(ImageReader::with_format(
            BufReader::new(file),
            ImageFormat::Png,
        ))
    };
    let (width, height) = reader()?
        .into_dimensions()
        .map_err(|source| decode_error(path.to_owned(), source))?;
    check_size(width, height)?;
    reader()?
        .decode()
        .map_err(|source| decode_error(path.to_owned(), source))
}

/// A decoded grayscale PNG with values in [0, 1], row-major, top row first.
struct GrayImage {
    width: u32,
    height: u32,
    values: Vec<f32>,
}

impl GrayImage {
    /// The values of image row `y`.
    fn row(&self, y: usize) -> &[f32] {
        let width = self.width as usize;
        &self.values[y * width..(y + 1) * width]
    }
}

/// Reads a grayscale PNG; `check_size` sees its width and height before it
/// is decoded and must cover the budget of its f32 values (4 bytes per
/// pixel).
fn read_grayscale_png(
    path: &Path,
    check_size: impl FnOnce(u32, u32) -> Result<(), FieldError>,
) -> Result<GrayImage, FieldError> {
    let image = read_png(
        path,
        |path, source| FieldError::Io { path, source },
        |path, source| FieldError::Decode { path, source },
        check_size,
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

/// Reads a raw file of `dims` samples for a `kind` (e.g. `density grid`):
/// checks the f32 values against the memory budget, then the file's length,
/// before reading it.
fn read_raw(
    path: &Path,
    kind: &str,
    dims: &[usize],
    sample_type: RawSampleType,
) -> Result<Vec<f32>, FieldError> {
    let name = path.display().to_string();
    budgeted_points(&name, kind, dims, SAMPLE_BYTES)?;
    let io = |source| FieldError::Io {
        path: path.to_owned(),
        source,
    };
    let file = File::open(path).map_err(io)?;
    let length = file.metadata().map_err(io)?.len();
    check_raw_length(path, dims, sample_type, length)?;
    // The length is at most 4 bytes per sample, within the budget checked.
    let mut bytes = Vec::with_capacity(length as usize);
    file.take(length).read_to_end(&mut bytes).map_err(io)?;
    // The file may have shrunk while it was read.
    check_raw_length(path, dims, sample_type, bytes.len() as u64)?;
    Ok(sample_type.decode(&bytes))
}

/// Refuses `actual` bytes unless they are exactly `dims` samples of
/// `sample_type`; `path` names them in the error.
fn check_raw_length(
    path: &Path,
    dims: &[usize],
    sample_type: RawSampleType,
    actual: u64,
) -> Result<(), FieldError> {
    let expected = dims
        .iter()
        .fold(sample_type.bytes() as u128, |acc, &n| acc * n as u128);
    if expected == u128::from(actual) {
        Ok(())
    } else {
        Err(FieldError::RawSizeMismatch {
            path: path.to_owned(),
            dims: dims.to_vec(),
            sample_type,
            expected,
            actual,
        })
    }
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
        let image = read_grayscale_png(path, |width, height| {
            budgeted_points(
                &path.display().to_string(),
                HEIGHT_FIELD,
                &[width as usize, height as usize],
                SAMPLE_BYTES,
            )
            .map(drop)
        })?;
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
        let values = read_raw(path, HEIGHT_FIELD, &dims, sample_type)?;
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
        let name = first_path.display().to_string();
        let count = paths.len();
        // The whole grid is checked from the first slice's header.
        let first = read_grayscale_png(first_path, |width, height| {
            let dims = [width as usize, count, height as usize];
            budgeted_points(&name, DENSITY_GRID, &dims, SAMPLE_BYTES).map(drop)
        })?;
        let (width, height) = (first.width, first.height);
        let dims = [width as usize, count, height as usize];
        let mut values = vec![0.0; dims.iter().product()];
        place_slice(&mut values, dims, 0, |z| first.row(z));
        for (index, path) in paths.iter().enumerate().skip(1) {
            let path = path.as_ref();
            let slice = read_grayscale_png(path, |found_width, found_height| {
                if (found_width, found_height) == (width, height) {
                    Ok(())
                } else {
                    Err(FieldError::SliceSizeMismatch {
                        path: path.to_owned(),
                        found: (found_width, found_height),
                        first: first_path.to_owned(),
                        expected: (width, height),
                    })
                }
            })?;
            place_slice(&mut values, dims, index, |z| slice.row(z));
        }
        Self::validated(&name, dims, spacing, origin, values)
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
        let name = path.display().to_string();
        // The grid holds at most the image's pixels, so this covers it too.
        let image = read_grayscale_png(path, |width, height| {
            let dims = [width as usize, height as usize];
            check_allocation(
                || format!("image of {} pixels as f32 samples", Dims(&dims)),
                &dims,
                SAMPLE_BYTES,
            )
            .map(drop)
            .map_err(FieldError::over_budget(&name))
        })?;
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
        let dims = [tile_width, slices as usize, tile_height];
        let mut values = vec![0.0; dims.iter().product()];
        for slice in 0..slices {
            let (column, row) = ((slice % columns) as usize, (slice / columns) as usize);
            place_slice(&mut values, dims, slice as usize, |z| {
                let start = (row * tile_height + z) * image_width + column * tile_width;
                &image.values[start..start + tile_width]
            });
        }
        Self::validated(&name, dims, spacing, origin, values)
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
        let mut values = read_raw(path, DENSITY_GRID, &dims, sample_type)?;
        normalization.apply(&name, &mut values)?;
        Self::validated(&name, dims, spacing, origin, values)
    }

    /// [`DensityGrid::load_raw`] of bytes already read (an asset loader's):
    /// `name` names them in errors. The grid is checked against the memory
    /// budget and the byte count against `dims` before anything is decoded.
    pub fn from_raw_bytes(
        name: &str,
        bytes: &[u8],
        dims: [usize; 3],
        sample_type: RawSampleType,
        normalization: Normalization,
        spacing: DVec3,
        origin: DVec3,
    ) -> Result<Self, FieldError> {
        budgeted_points(name, DENSITY_GRID, &dims, SAMPLE_BYTES)?;
        check_raw_length(Path::new(name), &dims, sample_type, bytes.len() as u64)?;
        let mut values = sample_type.decode(bytes);
        normalization.apply(name, &mut values)?;
        Self::validated(name, dims, spacing, origin, values)
    }
}

/// Writes horizontal slice `slice` (grid index y) into the `values` of a
/// grid of `dims = [width, slices, depth]` points in the grid order (x
/// fastest, then y, then z): `row(z)` gives the slice's `width` values of
/// row z.
fn place_slice<'a>(
    values: &mut [f32],
    dims: [usize; 3],
    slice: usize,
    row: impl Fn(usize) -> &'a [f32],
) {
    let [width, slices, _] = dims;
    for (z, layer) in values.chunks_exact_mut(width * slices).enumerate() {
        layer[slice * width..(slice + 1) * width].copy_from_slice(row(z));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{assert_mentions, error_message, write_png_header};
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
    fn raw_bytes_decode_like_raw_files_and_are_checked_before_decoding() {
        let bytes = [0u8, 36, 73, 109, 146, 182, 219, 255];
        let grid = DensityGrid::from_raw_bytes(
            "cloud.raw",
            &bytes,
            [2, 2, 2],
            RawSampleType::U8,
            Normalization::None,
            DVec3::ONE,
            DVec3::ZERO,
        )
        .unwrap();
        assert_eq!(grid.values()[7], 1.0);
        assert!((grid.values()[1] - 36.0 / 255.0).abs() < 1e-7);
        let short = DensityGrid::from_raw_bytes(
            "cloud.raw",
            &bytes[..7],
            [2, 2, 2],
            RawSampleType::U8,
            Normalization::None,
            DVec3::ONE,
            DVec3::ZERO,
        );
        assert_mentions(&error_message(short), &["cloud.raw", "8", "7"]);
        let huge = DensityGrid::from_raw_bytes(
            "huge.raw",
            &bytes,
            [4097, 4097, 4097],
            RawSampleType::U8,
            Normalization::None,
            DVec3::ONE,
            DVec3::ZERO,
        );
        assert_mentions(&error_message(huge), &["huge.raw", "memory budget"]);
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

    #[test]
    fn sizes_beyond_the_budget_are_refused_before_anything_is_read() {
        let dir = temp_dir("budget");
        // A raw file of 8 bytes declared as 4097³ samples: refused from the
        // dimensions, before its length or contents are looked at.
        let tiny = dir.join("tiny.u8");
        std::fs::write(&tiny, [0u8; 8]).unwrap();
        let message = error_message(DensityGrid::load_raw(
            &tiny,
            [4097; 3],
            RawSampleType::U8,
            Normalization::None,
            DVec3::ONE,
            DVec3::ZERO,
        ));
        assert_mentions(
            &message,
            &[
                "tiny.u8",
                "density grid of 4097 × 4097 × 4097 points needs 275,079,282,692 bytes",
                "memory budget of 4,294,967,296 bytes",
            ],
        );
        let message = error_message(HeightField::load_raw(
            &tiny,
            [100_000, 100_000],
            RawSampleType::F32,
            1.0,
            DVec2::ONE,
            DVec2::ZERO,
        ));
        assert_mentions(
            &message,
            &[
                "tiny.u8",
                "height field of 100000 × 100000 points needs 40,000,000,000 bytes",
            ],
        );

        // PNG headers declaring huge images: refused before decoding.
        let huge = dir.join("huge.png");
        write_png_header(&huge, 70_000, 70_000);
        let message = error_message(HeightField::load_png(&huge, DVec2::ONE, DVec2::ZERO, 1.0));
        assert_mentions(
            &message,
            &[
                "huge.png",
                "height field of 70000 × 70000 points needs 19,600,000,000 bytes",
            ],
        );
        let layout = TileLayout {
            columns: 2,
            rows: 2,
            slices: 4,
        };
        let message = error_message(DensityGrid::load_png_tiled(
            &huge,
            layout,
            DVec3::ONE,
            DVec3::ZERO,
        ));
        assert_mentions(
            &message,
            &[
                "huge.png",
                "image of 70000 × 70000 pixels as f32 samples needs",
            ],
        );
        // Slices of 40000² pixels: each within the budget, three of them not.
        let slice = dir.join("slice.png");
        write_png_header(&slice, 40_000, 40_000);
        let message = error_message(DensityGrid::load_png_slices(
            &[&slice, &slice, &slice],
            DVec3::ONE,
            DVec3::ZERO,
        ));
        assert_mentions(
            &message,
            &[
                "slice.png",
                "density grid of 40000 × 3 × 40000 points needs 19,200,000,000 bytes",
            ],
        );
        // A later slice of another size is refused from its header too.
        let small = dir.join("small.png");
        save_gray8(&small, 2, 2, &[0; 4]);
        let message = error_message(DensityGrid::load_png_slices(
            &[&small, &slice],
            DVec3::ONE,
            DVec3::ZERO,
        ));
        assert_mentions(&message, &["slice.png", "(40000, 40000)", "small.png"]);
    }
}
