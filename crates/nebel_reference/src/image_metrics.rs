//! Linear-light images, PNG input and output, and the error between two images.
//!
//! - [`LinearImage`]: premultiplied linear RGBA in f32, what the reference
//!   renderer ([`crate::render`]) produces.
//! - [`load_png_linear`]: an 8- or 16-bit PNG (gray, gray-alpha, RGB, RGBA),
//!   decoded from sRGB with the exact IEC 61966-2-1 curve, alpha premultiplied.
//! - [`save_png`]: composite over an opaque background colour, encode to sRGB,
//!   write an 8-bit RGB PNG.
//! - [`compare`]: RMSE, maximum absolute error and PSNR over the linear RGB
//!   channels (alpha ignored), PSNR with peak 1.0:
//!   `PSNR = 10 log10(1 / MSE)` dB; identical images give `f64::INFINITY`.
//! - [`difference_image`]: `|a − b| · scale` per channel, for `--diff` output.

use std::fmt;
use std::path::{Path, PathBuf};

use image::{ImageFormat, RgbImage};
use nebel_core::budget::{BudgetError, Dims, check_allocation};

/// A linear-light image: `width × height` premultiplied RGBA pixels in f32,
/// row-major, top row first. Colour channels are linear (not sRGB) and already
/// multiplied by alpha; alpha is opacity in [0, 1].
#[derive(Clone, Debug, PartialEq)]
pub struct LinearImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width · height` pixels, row-major, top row first.
    pub pixels: Vec<[f32; 4]>,
}

/// Bytes per pixel of a [`LinearImage`] (RGBA f32).
const PIXEL_BYTES: u64 = size_of::<[f32; 4]>() as u64;

impl LinearImage {
    /// The bytes of the pixels of a `width × height` image (16 per pixel),
    /// checked against the memory budget without allocating them: what the
    /// reference renderer checks before it allocates its image. Errors name
    /// a `linear image of width × height pixels`.
    pub fn check_budget(width: u32, height: u32) -> Result<u64, BudgetError> {
        let dims = [width as usize, height as usize];
        check_allocation(
            || format!("linear image of {} pixels", Dims(&dims)),
            &dims,
            PIXEL_BYTES,
        )
    }

    /// A fully transparent black image; for a size from input, check
    /// [`LinearImage::check_budget`] first.
    pub fn transparent(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            pixels: vec![[0.0; 4]; width as usize * height as usize],
        }
    }

    /// Checks that `pixels` has `width · height` entries, all finite.
    fn validate(&self) -> Result<(), ImageMetricsError> {
        let expected = self.width as usize * self.height as usize;
        if self.pixels.len() != expected {
            return Err(ImageMetricsError::PixelCount {
                width: self.width,
                height: self.height,
                actual: self.pixels.len(),
            });
        }
        match self
            .pixels
            .iter()
            .position(|p| !p.iter().all(|c| c.is_finite()))
        {
            Some(index) => Err(ImageMetricsError::NonFinite {
                x: index as u32 % self.width,
                y: index as u32 / self.width,
            }),
            None => Ok(()),
        }
    }
}

/// The error between two images over linear RGB (alpha ignored).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageErrorMetrics {
    /// Root mean square error over all RGB channel values.
    pub rmse: f64,
    /// Largest absolute difference of any RGB channel value.
    pub max_abs: f64,
    /// Peak signal-to-noise ratio in dB with peak 1.0, `10 log10(1 / MSE)`;
    /// `f64::INFINITY` when the images are identical.
    pub psnr: f64,
}

impl fmt::Display for ImageErrorMetrics {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "RMSE {:.6e}  max abs {:.6e}  PSNR {:.2} dB",
            self.rmse, self.max_abs, self.psnr
        )
    }
}

/// Why an image could not be read, written or compared.
#[derive(Debug, thiserror::Error)]
pub enum ImageMetricsError {
    /// The file could not be read.
    #[error("cannot read {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying I/O error.
        source: std::io::Error,
    },
    /// The file is not a readable PNG.
    #[error("cannot decode {} as PNG: {source}", path.display())]
    Decode {
        /// The file.
        path: PathBuf,
        /// The decoder's error.
        source: image::ImageError,
    },
    /// The decoded image would exceed the memory budget; its pixels were not
    /// decoded.
    #[error("{}: {source}", path.display())]
    OverBudget {
        /// The file.
        path: PathBuf,
        /// What was to be built, its bytes and the budget.
        source: BudgetError,
    },
    /// The PNG could not be written.
    #[error("cannot write {}: {source}", path.display())]
    Encode {
        /// The file.
        path: PathBuf,
        /// The encoder's error.
        source: image::ImageError,
    },
    /// The two images differ in size.
    #[error(
        "images differ in size: the first is {}×{}, the second {}×{}",
        first.0, first.1, second.0, second.1
    )]
    SizeMismatch {
        /// Width and height of the first image.
        first: (u32, u32),
        /// Width and height of the second image.
        second: (u32, u32),
    },
    /// A [`LinearImage`] whose pixel count does not match its size.
    #[error("a {width}×{height} image needs {} pixels, found {actual}", *width as usize * *height as usize)]
    PixelCount {
        /// Declared width.
        width: u32,
        /// Declared height.
        height: u32,
        /// Pixels present.
        actual: usize,
    },
    /// A pixel holds NaN or infinity.
    #[error("pixel ({x}, {y}) is not finite")]
    NonFinite {
        /// Column.
        x: u32,
        /// Row, from the top.
        y: u32,
    },
    /// A colour or scale parameter is not finite or negative.
    #[error("{parameter} = {value} is invalid: it must be finite and ≥ 0")]
    InvalidParameter {
        /// The parameter's name.
        parameter: &'static str,
        /// Its value, formatted.
        value: String,
    },
}

/// sRGB transfer curve, encoded value in [0, 1] to linear (IEC 61966-2-1).
pub fn srgb_to_linear(encoded: f64) -> f64 {
    if encoded <= 0.04045 {
        encoded / 12.92
    } else {
        ((encoded + 0.055) / 1.055).powf(2.4)
    }
}

/// Inverse of [`srgb_to_linear`]: linear in [0, 1] to encoded sRGB.
pub fn linear_to_srgb(linear: f64) -> f64 {
    if linear <= 0.0031308 {
        linear * 12.92
    } else {
        1.055 * linear.powf(1.0 / 2.4) - 0.055
    }
}

/// Loads an 8- or 16-bit PNG of any channel layout as linear RGB with
/// premultiplied alpha (opaque when the file has no alpha). The image and its
/// 16-bit RGBA copy (24 bytes per pixel together) are checked against the
/// memory budget from the file's header, before it is decoded
/// ([`ImageMetricsError::OverBudget`]).
pub fn load_png_linear(path: impl AsRef<Path>) -> Result<LinearImage, ImageMetricsError> {
    let path = path.as_ref();
    let image = nebel_core::field::read_png(
        path,
        |path, source| ImageMetricsError::Io { path, source },
        |path, source| ImageMetricsError::Decode { path, source },
        |width, height| {
            let dims = [width as usize, height as usize];
            check_allocation(
                || {
                    format!(
                        "linear image of {} pixels with its 16-bit copy",
                        Dims(&dims)
                    )
                },
                &dims,
                PIXEL_BYTES + size_of::<[u16; 4]>() as u64,
            )
            .map(drop)
            .map_err(|source| ImageMetricsError::OverBudget {
                path: path.to_owned(),
                source,
            })
        },
    )?;
    let (width, height) = (image.width(), image.height());
    // 8-bit values widen exactly (v · 257), so one path serves both depths.
    let pixels = image
        .to_rgba16()
        .pixels()
        .map(|p| {
            let alpha = f64::from(p.0[3]) / 65535.0;
            let channel = |c: u16| (srgb_to_linear(f64::from(c) / 65535.0) * alpha) as f32;
            [
                channel(p.0[0]),
                channel(p.0[1]),
                channel(p.0[2]),
                alpha as f32,
            ]
        })
        .collect();
    Ok(LinearImage {
        width,
        height,
        pixels,
    })
}

/// Writes `image` as an 8-bit sRGB RGB PNG after compositing it over the
/// opaque linear RGB `background` (`colour + (1 − α) · background`, each
/// channel clamped to [0, 1]). Pass `[0.0; 3]` for black.
pub fn save_png(
    image: &LinearImage,
    path: impl AsRef<Path>,
    background: [f32; 3],
) -> Result<(), ImageMetricsError> {
    let path = path.as_ref();
    image.validate()?;
    if !background.iter().all(|c| c.is_finite() && *c >= 0.0) {
        return Err(ImageMetricsError::InvalidParameter {
            parameter: "background",
            value: format!("{background:?}"),
        });
    }
    let mut bytes = Vec::with_capacity(image.pixels.len() * 3);
    for pixel in &image.pixels {
        let alpha = pixel[3].clamp(0.0, 1.0);
        for (channel, back) in pixel[..3].iter().zip(background) {
            let linear = f64::from(channel + (1.0 - alpha) * back).clamp(0.0, 1.0);
            bytes.push((linear_to_srgb(linear) * 255.0).round() as u8);
        }
    }
    let encode_error = |source| ImageMetricsError::Encode {
        path: path.to_owned(),
        source,
    };
    let buffer = RgbImage::from_raw(image.width, image.height, bytes).ok_or_else(|| {
        encode_error(image::ImageError::Parameter(
            image::error::ParameterError::from_kind(
                image::error::ParameterErrorKind::DimensionMismatch,
            ),
        ))
    })?;
    buffer
        .save_with_format(path, ImageFormat::Png)
        .map_err(encode_error)
}

/// Checks that both images are valid and of the same size.
fn check_pair(a: &LinearImage, b: &LinearImage) -> Result<(), ImageMetricsError> {
    if (a.width, a.height) != (b.width, b.height) {
        return Err(ImageMetricsError::SizeMismatch {
            first: (a.width, a.height),
            second: (b.width, b.height),
        });
    }
    a.validate()?;
    b.validate()
}

/// RMSE, maximum absolute error and PSNR between `a` and `b` over linear RGB
/// (alpha ignored). Refuses images of different sizes. Empty images compare as
/// identical.
pub fn compare(a: &LinearImage, b: &LinearImage) -> Result<ImageErrorMetrics, ImageMetricsError> {
    check_pair(a, b)?;
    let mut sum_squared = 0.0;
    let mut max_abs: f64 = 0.0;
    for (pa, pb) in a.pixels.iter().zip(&b.pixels) {
        for c in 0..3 {
            let difference = f64::from(pa[c]) - f64::from(pb[c]);
            sum_squared += difference * difference;
            max_abs = max_abs.max(difference.abs());
        }
    }
    let samples = 3 * a.pixels.len();
    let mse = if samples == 0 {
        0.0
    } else {
        sum_squared / samples as f64
    };
    let psnr = if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    };
    Ok(ImageErrorMetrics {
        rmse: mse.sqrt(),
        max_abs,
        psnr,
    })
}

/// The largest change of the difference `a − b` between two horizontally or
/// vertically adjacent pixels, over linear RGB channels: how much sharper an
/// edge (a seam) `a` has than `b` anywhere. Two images that differ by a
/// smooth function of the pixel give a small value even where they differ
/// much. Refuses images of different sizes; 0 for images under 2 pixels.
pub fn largest_difference_step(a: &LinearImage, b: &LinearImage) -> Result<f64, ImageMetricsError> {
    check_pair(a, b)?;
    let (width, height) = (a.width as usize, a.height as usize);
    let difference =
        |index: usize, c: usize| f64::from(a.pixels[index][c]) - f64::from(b.pixels[index][c]);
    let mut largest: f64 = 0.0;
    for y in 0..height {
        for x in 0..width {
            let here = y * width + x;
            let neighbours = [
                (x + 1 < width).then_some(here + 1),
                (y + 1 < height).then_some(here + width),
            ];
            for there in neighbours.into_iter().flatten() {
                for c in 0..3 {
                    largest = largest.max((difference(here, c) - difference(there, c)).abs());
                }
            }
        }
    }
    Ok(largest)
}

/// The difference image `|a − b| · scale` per linear RGB channel, opaque. A
/// `scale` of 10 makes errors of 0.01 show as 0.1. Refuses images of different
/// sizes and a negative or non-finite `scale`.
pub fn difference_image(
    a: &LinearImage,
    b: &LinearImage,
    scale: f32,
) -> Result<LinearImage, ImageMetricsError> {
    check_pair(a, b)?;
    if !(scale.is_finite() && scale >= 0.0) {
        return Err(ImageMetricsError::InvalidParameter {
            parameter: "scale",
            value: scale.to_string(),
        });
    }
    let pixels = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .map(|(pa, pb)| {
            let channel = |c: usize| ((pa[c] - pb[c]).abs() * scale).min(f32::MAX);
            [channel(0), channel(1), channel(2), 1.0]
        })
        .collect();
    Ok(LinearImage {
        width: a.width,
        height: a.height,
        pixels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_difference_step_sees_seams_not_smooth_offsets() {
        let image = |value: &dyn Fn(u32, u32) -> f32| LinearImage {
            width: 8,
            height: 4,
            pixels: (0..32)
                .map(|i| {
                    let v = value(i % 8, i / 8);
                    [v, v, v, 1.0]
                })
                .collect(),
        };
        let base = image(&|x, _| 0.1 * x as f32 / 8.0);
        // A smooth ramp of difference: steps of 0.01 between neighbours.
        let ramp = image(&|x, _| 0.1 * x as f32 / 8.0 + 0.01 * x as f32);
        let step = largest_difference_step(&ramp, &base).unwrap();
        assert!((step - 0.01).abs() < 1e-6, "{step}");
        // A seam of 0.2 between columns 3 and 4.
        let seam = image(&|x, _| 0.1 * x as f32 / 8.0 + if x >= 4 { 0.2 } else { 0.0 });
        let step = largest_difference_step(&seam, &base).unwrap();
        assert!((step - 0.2).abs() < 1e-6, "{step}");
        assert_eq!(largest_difference_step(&base, &base).unwrap(), 0.0);
        assert!(largest_difference_step(&base, &LinearImage::transparent(2, 2)).is_err());
    }

    fn temp_path(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nebel-image-metrics-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    fn gradient(width: u32, height: u32) -> LinearImage {
        let pixels = (0..width * height)
            .map(|i| {
                let v = i as f32 / (width * height) as f32;
                [v, 0.5 * v, 1.0 - v, 1.0]
            })
            .collect();
        LinearImage {
            width,
            height,
            pixels,
        }
    }

    #[test]
    fn srgb_curve_round_trips() {
        for i in 0..=100 {
            let v = f64::from(i) / 100.0;
            assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 1e-12);
        }
        assert!((srgb_to_linear(0.5) - 0.214041).abs() < 1e-6);
    }

    #[test]
    fn png_round_trip_stays_within_8_bit_quantisation() {
        let image = gradient(16, 8);
        let path = temp_path("gradient.png");
        save_png(&image, &path, [0.0; 3]).unwrap();
        let loaded = load_png_linear(&path).unwrap();
        let metrics = compare(&image, &loaded).unwrap();
        // Half an 8-bit sRGB step is at most (1/510) · 2.4/1.055 ≈ 0.0045 in
        // linear (the curve is steepest at 1).
        assert!(metrics.max_abs < 0.0046, "{metrics}");

        // 16-bit input with alpha is decoded and premultiplied.
        let path16 = temp_path("rgba16.png");
        let pixel = image::Rgba([65535u16, 32768, 0, 32768]);
        image::ImageBuffer::from_pixel(2, 2, pixel)
            .save(&path16)
            .unwrap();
        let loaded = load_png_linear(&path16).unwrap();
        let p = loaded.pixels[0];
        assert!((p[3] - 0.5).abs() < 1e-4 && (p[0] - 0.5).abs() < 1e-4 && p[2] == 0.0);
        assert!((p[1] - 0.5 * srgb_to_linear(32768.0 / 65535.0) as f32).abs() < 1e-5);
    }

    #[test]
    fn transparent_pixels_take_the_background() {
        let image = LinearImage::transparent(2, 1);
        let path = temp_path("background.png");
        save_png(
            &image,
            &path,
            [1.0, 0.0, srgb_to_linear(128.0 / 255.0) as f32],
        )
        .unwrap();
        let loaded = image::open(&path).unwrap().to_rgb8();
        assert_eq!(loaded.get_pixel(1, 0).0, [255, 0, 128]);
    }

    #[test]
    fn compare_identical_different_and_mismatched() {
        let a = gradient(8, 4);
        let identical = compare(&a, &a.clone()).unwrap();
        assert_eq!((identical.rmse, identical.max_abs), (0.0, 0.0));
        assert_eq!(identical.psnr, f64::INFINITY);

        let mut b = a.clone();
        b.pixels[5][1] += 0.3;
        let metrics = compare(&a, &b).unwrap();
        let samples = 3.0 * 32.0;
        let expected_rmse = (0.09f64 / samples).sqrt();
        assert!((metrics.rmse - expected_rmse).abs() < 1e-6);
        assert!((metrics.max_abs - 0.3).abs() < 1e-6);
        assert!((metrics.psnr - 20.0 * (1.0 / expected_rmse).log10()).abs() < 1e-4);
        // Alpha is ignored.
        let mut c = a.clone();
        c.pixels[0][3] = 0.0;
        assert_eq!(compare(&a, &c).unwrap().psnr, f64::INFINITY);

        let message = compare(&a, &gradient(4, 8)).unwrap_err().to_string();
        assert_eq!(
            message,
            "images differ in size: the first is 8×4, the second 4×8"
        );
        let broken = LinearImage {
            width: 8,
            height: 4,
            pixels: vec![[0.0; 4]; 3],
        };
        let message = compare(&a, &broken).unwrap_err().to_string();
        assert!(message.contains("needs 32 pixels, found 3"), "{message}");
        let mut nan = a.clone();
        nan.pixels[9][0] = f32::NAN;
        let message = compare(&a, &nan).unwrap_err().to_string();
        assert!(message.contains("pixel (1, 1)"), "{message}");
    }

    #[test]
    fn difference_image_scales_absolute_errors() {
        let a = gradient(4, 4);
        let mut b = a.clone();
        b.pixels[3][2] -= 0.01;
        let diff = difference_image(&a, &b, 10.0).unwrap();
        assert!((diff.pixels[3][2] - 0.1).abs() < 1e-5);
        assert_eq!(diff.pixels[0], [0.0, 0.0, 0.0, 1.0]);
        let path = temp_path("diff.png");
        save_png(&diff, &path, [0.0; 3]).unwrap();
        assert_eq!(load_png_linear(&path).unwrap().width, 4);
        assert!(difference_image(&a, &b, -1.0).is_err());
        assert!(difference_image(&a, &gradient(2, 2), 1.0).is_err());
    }

    #[test]
    fn file_errors_name_the_file() {
        let message = load_png_linear(temp_path("absent.png"))
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with("cannot read") && message.contains("absent.png"),
            "{message}"
        );
        let junk = temp_path("junk.png");
        std::fs::write(&junk, b"junk").unwrap();
        let message = load_png_linear(&junk).unwrap_err().to_string();
        assert!(
            message.contains("cannot decode") && message.contains("junk.png"),
            "{message}"
        );
        let unwritable = temp_path("no-such-dir").join("out.png");
        let message = save_png(&gradient(2, 2), &unwritable, [0.0; 3])
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("cannot write") && message.contains("out.png"),
            "{message}"
        );
    }

    /// A PNG whose header declares `width × height` 8-bit grayscale pixels
    /// and no pixel data: its size can be read, its pixels not decoded.
    fn png_header(path: &Path, width: u32, height: u32) {
        let file = std::fs::File::create(path).unwrap();
        let mut encoder = png::Encoder::new(file, width, height);
        encoder.set_color(png::ColorType::Grayscale);
        let mut writer = encoder.write_header().unwrap();
        writer.write_chunk(png::chunk::IDAT, &[]).unwrap();
    }

    #[test]
    fn a_png_beyond_the_memory_budget_is_refused_from_its_header() {
        let path = temp_path("huge.png");
        png_header(&path, 20_000, 10_000);
        let error = load_png_linear(&path).unwrap_err();
        assert!(
            matches!(error, ImageMetricsError::OverBudget { .. }),
            "{error}"
        );
        let message = error.to_string();
        assert!(
            message.contains(
                "huge.png: linear image of 20000 × 10000 pixels with its 16-bit copy needs 4,800,000,000 bytes"
            ),
            "{message}"
        );
        assert_eq!(
            LinearImage::check_budget(16_384, 16_384),
            Ok(16_384 * 16_384 * 16)
        );
    }
}
