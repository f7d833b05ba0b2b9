//! Transfer functions: chromaticity κ (linear RGB) and density ρ over a scalar
//! `s` in [0, 1] (Röttger 2004 §7.1 and §8.4, the volume density optical model of
//! Williams and Max).
//!
//! A transfer function is piecewise linear between control points sorted by `s`
//! and constant beyond the first and last point. ρ is an extinction coefficient
//! in 1/world unit; κ·ρ is the emission per unit length.
//!
//! # Steps
//!
//! Two control points may share the same `s`: that is a step. Left of the step
//! the function interpolates towards the first of the two, at and right of the
//! step it starts from the second (the function is right-continuous). If more
//! than two points share one `s`, only the first and the last of them matter.
//!
//! # Sources
//!
//! - [`TransferFunction::new`]: control points, validated.
//! - [`TransferFunction::from_png_strip`]: a 1-pixel-high PNG, one control point
//!   per pixel (RGB = κ in sRGB, alpha = ρ / `max_density`).
//! - [`TransferFunction::preset`]: named looks for the effects of nebel
//!   ([`TransferPreset`]).
//!
//! [`TransferFunction::content_hash`] is stable across runs and platforms, so
//! renderers rebuild their pre-integration tables only when it changes.

use std::path::{Path, PathBuf};

use glam::DVec3;
use thiserror::Error;

use crate::budget::{BudgetError, check_allocation};

/// One control point of a piecewise-linear transfer function.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
pub struct ControlPoint {
    /// Scalar position in [0, 1].
    pub s: f32,
    /// Chromaticity κ, linear RGB, each channel ≥ 0.
    pub kappa: [f32; 3],
    /// Density ρ (extinction coefficient), 1/world unit, ≥ 0.
    pub rho: f32,
}

/// κ and ρ at one scalar value, in f64 for the reference integrator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransferSample {
    /// Chromaticity κ, linear RGB.
    pub kappa: DVec3,
    /// Density ρ, 1/world unit.
    pub rho: f64,
}

impl TransferSample {
    /// Emission per unit length κ·ρ.
    pub fn emission(&self) -> DVec3 {
        self.kappa * self.rho
    }
}

/// Why a transfer function could not be built.
#[derive(Debug, Error)]
pub enum TransferError {
    /// No control points were given.
    #[error("a transfer function needs at least one control point")]
    Empty,
    /// A control point holds a NaN or infinite value.
    #[error("control point {index} has a non-finite value (NaN or infinity)")]
    NonFinite {
        /// Index of the point in the input, before sorting.
        index: usize,
    },
    /// A control point's `s` lies outside [0, 1].
    #[error("control point {index} has s = {s}, outside [0, 1]")]
    ScalarOutOfRange {
        /// Index of the point in the input, before sorting.
        index: usize,
        /// The offending scalar position.
        s: f32,
    },
    /// A control point has a negative chromaticity channel.
    #[error("control point {index} has a negative chromaticity κ = {kappa:?}")]
    NegativeChromaticity {
        /// Index of the point in the input, before sorting.
        index: usize,
        /// The offending chromaticity.
        kappa: [f32; 3],
    },
    /// A control point has a negative density.
    #[error("control point {index} has a negative density ρ = {rho}")]
    NegativeDensity {
        /// Index of the point in the input, before sorting.
        index: usize,
        /// The offending density.
        rho: f32,
    },
    /// A density scale (the `max_density` of a PNG strip or a
    /// [`TransferFunction::scale_density`] factor) is negative or not finite.
    #[error("density scale {value} must be finite and ≥ 0")]
    InvalidDensityScale {
        /// The offending scale.
        value: f32,
    },
    /// A PNG strip could not be opened or decoded.
    #[error("cannot read transfer-function strip {}: {source}", path.display())]
    Image {
        /// The file that failed.
        path: PathBuf,
        /// What `image` reported.
        source: image::ImageError,
    },
    /// A PNG strip's control points would exceed the memory budget; its
    /// pixels were not decoded.
    #[error("transfer-function strip {}: {source}", path.display())]
    OverBudget {
        /// The file that failed.
        path: PathBuf,
        /// What was to be built, its bytes and the budget.
        source: BudgetError,
    },
    /// A PNG strip is not exactly one pixel high.
    #[error(
        "transfer-function strip {} is {width}×{height} pixels; it must be 1 pixel high",
        path.display()
    )]
    StripHeight {
        /// The file that failed.
        path: PathBuf,
        /// Its width in pixels.
        width: u32,
        /// Its height in pixels.
        height: u32,
    },
}

/// A piecewise-linear transfer function (κ, ρ) over the scalar `s` in [0, 1].
///
/// Build it with [`TransferFunction::new`], which validates the control points.
/// It (de)serializes as `(points: [...])`; deserializing validates as `new` does.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(try_from = "RawTransferFunction")
)]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
pub struct TransferFunction {
    points: Vec<ControlPoint>,
}

/// The unvalidated serialized form of a [`TransferFunction`].
#[cfg(feature = "serde")]
#[derive(serde::Deserialize)]
struct RawTransferFunction {
    points: Vec<ControlPoint>,
}

#[cfg(feature = "serde")]
impl TryFrom<RawTransferFunction> for TransferFunction {
    type Error = TransferError;

    fn try_from(raw: RawTransferFunction) -> Result<Self, Self::Error> {
        TransferFunction::new(raw.points)
    }
}

/// Named transfer functions for the effects nebel ships.
///
/// Every preset peaks at ρ = 1 per world unit; scale it to the scene with
/// [`TransferFunction::scale_density`]. κ is linear RGB in [0, 1].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
pub enum TransferPreset {
    /// The paper's non-photorealistic cloud (Röttger and Ertl 2003 §5, Röttger 2004 §11.6.2): κ is an
    /// inverse colour ramp, white where the cloud is thin, darker bluish grey
    /// where it is dense; ρ is zero below the cut-off s = 0.05 and rises
    /// linearly from 0 there to 1 at s = 1 (continuous, so the tables
    /// interpolate it as well as any linear function).
    #[default]
    Cloud,
    /// Ground fog: light grey-blue, ρ linear in `s` from 0 (the fog top, where
    /// the density vanishes) to 1.
    GroundFog,
    /// Fire (emissive): dark red through orange to yellow-white as `s` rises;
    /// nothing below s = 0.1.
    Fire,
    /// Aurora curtains (emissive) over the relative altitude `s` in the
    /// curtains' layer (0 at its bottom, 1 at its top; 100 to 300 km for
    /// the defaults of nebel's aurora): a thin pink-violet lower fringe
    /// (molecular nitrogen, near 100 km), the bright green of atomic
    /// oxygen's 557.7 nm line peaking just above the bottom (ρ = 1 at
    /// `s = 0.03`) and fading by `s = 0.45` (190 km), then the faint red of
    /// its 630.0 nm line from `s = 0.6` (220 km), fading to nothing at the
    /// top: the emission altitudes of the two lines.
    Aurora,
    /// Search-light cone (emissive): warm white, ρ linear in `s` (the
    /// attenuated intensity).
    SearchLight,
    /// Smoke: dark grey, slightly lighter where thin; zero below s = 0.02.
    Smoke,
    /// A lit cloud's colour over its light intensity γ (Röttger and Ertl 2003 §5.1): κ
    /// rises from a dark blue-grey in the shade (γ = 0) through light grey to
    /// a warm white of 1.7 in full sun (γ = 1; above 1 so that sunlit cloud
    /// stays white through the camera's tonemapping); ρ is the constant 1 (`ρ_max`, scaled by the
    /// volume's density scale), since the density enters as the segment
    /// length `l' = l · f` (Eq. 9), not through this function.
    CloudLight,
    /// Sunlight scattered by a cloud, over its transmittance toward the sun
    /// (the single-scattering model, Nes 2008): κ rises linearly from black
    /// (in full shadow) to white (in full sun), ρ is the constant 1.
    Transmittance,
    /// A lit cloud at sunset (Röttger 2004 §11.7, Fig. 11.4), over its light
    /// intensity γ as [`TransferPreset::CloudLight`]: κ rises from a dusky
    /// violet-grey in the shade through pink to a warm orange of 1.6 in full
    /// sun (above 1 for the same reason); ρ is the constant 1.
    SunsetCloudLight,
    /// Bad weather (Röttger 2004 §11.7, Fig. 11.4): overcast storm cloud over
    /// the density, as [`TransferPreset::Cloud`] but dark slate grey, lighter
    /// where thin; ρ is zero below s = 0.02 and reaches 0.6 by s = 0.2, so
    /// thin cloud is already dense.
    BadWeather,
}

impl TransferPreset {
    /// Every preset, in declaration order.
    pub const ALL: [TransferPreset; 10] = [
        TransferPreset::Cloud,
        TransferPreset::GroundFog,
        TransferPreset::Fire,
        TransferPreset::Aurora,
        TransferPreset::SearchLight,
        TransferPreset::Smoke,
        TransferPreset::CloudLight,
        TransferPreset::Transmittance,
        TransferPreset::SunsetCloudLight,
        TransferPreset::BadWeather,
    ];

    /// The preset's control points (`s`, κ, ρ).
    fn points(self) -> Vec<ControlPoint> {
        let p = |s, kappa, rho| ControlPoint { s, kappa, rho };
        match self {
            TransferPreset::Cloud => vec![
                p(0.0, [1.0, 1.0, 1.0], 0.0),
                p(0.05, [1.0, 1.0, 1.0], 0.0),
                p(0.4, [0.82, 0.84, 0.88], 0.35 / 0.95),
                p(1.0, [0.38, 0.41, 0.50], 1.0),
            ],
            TransferPreset::GroundFog => vec![
                p(0.0, [0.86, 0.88, 0.92], 0.0),
                p(1.0, [0.74, 0.78, 0.85], 1.0),
            ],
            TransferPreset::Fire => vec![
                p(0.0, [0.5, 0.04, 0.0], 0.0),
                p(0.1, [0.5, 0.04, 0.0], 0.0),
                p(0.45, [1.0, 0.35, 0.05], 0.45),
                p(0.8, [1.0, 0.7, 0.25], 0.8),
                p(1.0, [1.0, 0.9, 0.6], 1.0),
            ],
            TransferPreset::Aurora => vec![
                p(0.0, [0.55, 0.25, 0.6], 0.5),
                p(0.03, [0.15, 1.0, 0.35], 1.0),
                p(0.25, [0.15, 1.0, 0.35], 0.45),
                p(0.45, [0.55, 0.6, 0.2], 0.12),
                p(0.6, [1.0, 0.12, 0.15], 0.1),
                p(1.0, [1.0, 0.12, 0.15], 0.0),
            ],
            TransferPreset::SearchLight => vec![
                p(0.0, [1.0, 0.95, 0.85], 0.0),
                p(1.0, [1.0, 0.97, 0.9], 1.0),
            ],
            TransferPreset::Smoke => vec![
                p(0.0, [0.3, 0.3, 0.31], 0.0),
                p(0.02, [0.3, 0.3, 0.31], 0.0),
                p(1.0, [0.1, 0.1, 0.11], 1.0),
            ],
            TransferPreset::CloudLight => vec![
                p(0.0, [0.3, 0.33, 0.42], 1.0),
                p(0.5, [0.85, 0.87, 0.92], 1.0),
                p(1.0, [1.7, 1.66, 1.6], 1.0),
            ],
            TransferPreset::Transmittance => {
                vec![p(0.0, [0.0, 0.0, 0.0], 1.0), p(1.0, [1.0, 1.0, 1.0], 1.0)]
            }
            TransferPreset::SunsetCloudLight => vec![
                p(0.0, [0.2, 0.16, 0.28], 1.0),
                p(0.5, [0.85, 0.5, 0.52], 1.0),
                p(1.0, [1.6, 0.9, 0.5], 1.0),
            ],
            TransferPreset::BadWeather => vec![
                p(0.0, [0.52, 0.54, 0.58], 0.0),
                p(0.02, [0.52, 0.54, 0.58], 0.0),
                p(0.2, [0.34, 0.36, 0.4], 0.6),
                p(1.0, [0.14, 0.15, 0.18], 1.0),
            ],
        }
    }
}

impl TransferFunction {
    /// Builds a transfer function from control points in any order.
    ///
    /// The points are sorted by `s` (stably, so two points with the same `s`
    /// form a step in the given order, see the [module docs](self)).
    ///
    /// # Errors
    ///
    /// [`TransferError`] when `points` is empty or a point has a non-finite
    /// value, `s` outside [0, 1], or a negative κ channel or ρ.
    pub fn new(points: impl Into<Vec<ControlPoint>>) -> Result<Self, TransferError> {
        let mut points = points.into();
        if points.is_empty() {
            return Err(TransferError::Empty);
        }
        for (index, p) in points.iter_mut().enumerate() {
            if !(p.s.is_finite() && p.rho.is_finite() && p.kappa.iter().all(|k| k.is_finite())) {
                return Err(TransferError::NonFinite { index });
            }
            if !(0.0..=1.0).contains(&p.s) {
                return Err(TransferError::ScalarOutOfRange { index, s: p.s });
            }
            if p.kappa.iter().any(|&k| k < 0.0) {
                return Err(TransferError::NegativeChromaticity {
                    index,
                    kappa: p.kappa,
                });
            }
            if p.rho < 0.0 {
                return Err(TransferError::NegativeDensity { index, rho: p.rho });
            }
            // −0.0 becomes +0.0 so equal functions hash equally.
            p.s += 0.0;
            p.rho += 0.0;
            p.kappa = p.kappa.map(|k| k + 0.0);
        }
        points.sort_by(|a, b| a.s.total_cmp(&b.s));
        Ok(Self { points })
    }

    /// A named preset, see [`TransferPreset`].
    pub fn preset(preset: TransferPreset) -> Self {
        Self::new(preset.points()).expect("presets are valid")
    }

    /// Loads a transfer function from a 1-pixel-high PNG strip (8 or 16 bit,
    /// grey or RGB, with or without alpha).
    ///
    /// Pixel `i` of a strip `w` pixels wide becomes a control point at
    /// `s = i / (w − 1)` (`s = 0` when `w = 1`, a constant function). Its RGB
    /// is κ, decoded from sRGB to linear; its alpha (1 without an alpha channel)
    /// times `max_density` is ρ in 1/world unit.
    ///
    /// # Errors
    ///
    /// [`TransferError::Image`] when the file cannot be read or decoded,
    /// [`TransferError::StripHeight`] when it is not 1 pixel high,
    /// [`TransferError::OverBudget`] when its control points exceed the
    /// memory budget (36 bytes per pixel), checked from the header, and
    /// [`TransferError::InvalidDensityScale`] for a negative or non-finite
    /// `max_density`. The file errors name the file.
    pub fn from_png_strip(path: impl AsRef<Path>, max_density: f32) -> Result<Self, TransferError> {
        let path = path.as_ref();
        if !(max_density.is_finite() && max_density >= 0.0) {
            return Err(TransferError::InvalidDensityScale { value: max_density });
        }
        let image_error = |source| TransferError::Image {
            path: path.to_path_buf(),
            source,
        };
        let reader = || {
            image::ImageReader::open(path)
                .map_err(|e| image_error(image::ImageError::IoError(e)))?
                .with_guessed_format()
                .map_err(|e| image_error(image::ImageError::IoError(e)))
        };
        // The header first: the height and the memory budget before decoding.
        let (width, height) = reader()?.into_dimensions().map_err(image_error)?;
        if height != 1 {
            return Err(TransferError::StripHeight {
                path: path.to_path_buf(),
                width,
                height,
            });
        }
        // The pixels as RGBA f32, then a control point per pixel.
        check_allocation(
            || format!("a transfer function of {width} control points"),
            &[width as usize],
            (size_of::<[f32; 4]>() + size_of::<ControlPoint>()) as u64,
        )
        .map_err(|source| TransferError::OverBudget {
            path: path.to_path_buf(),
            source,
        })?;
        let image = reader()?.decode().map_err(image_error)?;
        let rgba = image.to_rgba32f();
        let last = (width.max(2) - 1) as f32;
        let points: Vec<ControlPoint> = rgba
            .pixels()
            .enumerate()
            .map(|(i, pixel)| {
                let [r, g, b, a] = pixel.0;
                ControlPoint {
                    s: (i as f32 / last).min(1.0),
                    kappa: [r, g, b].map(srgb_to_linear),
                    rho: a.clamp(0.0, 1.0) * max_density,
                }
            })
            .collect();
        Self::new(points)
    }

    /// The same function with every ρ multiplied by `factor` (κ unchanged).
    ///
    /// # Errors
    ///
    /// [`TransferError::InvalidDensityScale`] for a negative or non-finite
    /// factor, [`TransferError::NonFinite`] if a product overflows.
    pub fn scale_density(&self, factor: f32) -> Result<Self, TransferError> {
        if !(factor.is_finite() && factor >= 0.0) {
            return Err(TransferError::InvalidDensityScale { value: factor });
        }
        let points: Vec<ControlPoint> = self
            .points
            .iter()
            .map(|p| ControlPoint {
                rho: p.rho * factor,
                ..*p
            })
            .collect();
        Self::new(points)
    }

    /// The control points, sorted by `s`.
    pub fn points(&self) -> &[ControlPoint] {
        &self.points
    }

    /// The largest density ρ anywhere, 1/world unit (a piecewise-linear function
    /// peaks at a control point).
    pub fn max_density(&self) -> f32 {
        self.points.iter().map(|p| p.rho).fold(0.0, f32::max)
    }

    /// The largest chromaticity channel anywhere (for bounds such as
    /// `C ≤ α · max κ`).
    pub fn max_chromaticity(&self) -> f32 {
        self.points.iter().flat_map(|p| p.kappa).fold(0.0, f32::max)
    }

    /// Whether ρ is exactly zero for every `s` in `[s_min, s_max]` (the
    /// zero-opacity test, Röttger and Ertl 2003 §4.1), exact for any transfer function.
    ///
    /// The bounds may come in either order and are clamped to [0, 1]; a NaN
    /// bound stands for the whole range, so the answer stays conservative:
    /// `true` only if no ρ > 0 exists in the range.
    pub fn is_transparent(&self, s_min: f64, s_max: f64) -> bool {
        let (lo, hi) = if s_min.is_nan() || s_max.is_nan() {
            (0.0, 1.0)
        } else {
            (
                s_min.min(s_max).clamp(0.0, 1.0),
                s_min.max(s_max).clamp(0.0, 1.0),
            )
        };
        let points = &self.points;
        // ρ ≥ 0 is piecewise linear and right-continuous, so it vanishes on
        // [lo, hi] iff it vanishes at `lo`, at every control point strictly
        // inside, at `hi` and just left of `hi` (a step down exactly at `hi`).
        let first = points.partition_point(|p| f64::from(p.s) <= lo);
        let last = points.partition_point(|p| f64::from(p.s) < hi).max(first);
        self.evaluate(lo).rho == 0.0
            && self.evaluate(hi).rho == 0.0
            && (lo == hi || self.left_limit_rho(hi) == 0.0)
            && points[first..last].iter().all(|p| p.rho == 0.0)
    }

    /// ρ approaching `s` from below (differs from `evaluate(s).rho` only at a step).
    fn left_limit_rho(&self, s: f64) -> f64 {
        let points = &self.points;
        let upper = points.partition_point(|p| f64::from(p.s) < s);
        if upper == 0 {
            return f64::from(points[0].rho);
        }
        if upper == points.len() {
            return f64::from(points[upper - 1].rho);
        }
        let (a, b) = (&points[upper - 1], &points[upper]);
        let t = (s - f64::from(a.s)) / (f64::from(b.s) - f64::from(a.s));
        f64::from(a.rho) + (f64::from(b.rho) - f64::from(a.rho)) * t
    }

    /// A 64-bit FNV-1a hash of the control points' bit patterns: equal for equal
    /// functions, stable across runs, builds and platforms (unlike std's
    /// `RandomState`). Renderers keep it next to a table and rebuild when it
    /// changes.
    pub fn content_hash(&self) -> u64 {
        const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
        const PRIME: u64 = 0x0000_0100_0000_01b3;
        let mut hash = OFFSET;
        let mut feed = |bytes: &[u8]| {
            for &byte in bytes {
                hash ^= u64::from(byte);
                hash = hash.wrapping_mul(PRIME);
            }
        };
        feed(&(self.points.len() as u64).to_le_bytes());
        for p in &self.points {
            feed(&p.s.to_bits().to_le_bytes());
            for k in p.kappa {
                feed(&k.to_bits().to_le_bytes());
            }
            feed(&p.rho.to_bits().to_le_bytes());
        }
        hash
    }

    /// κ and ρ at `s` (clamped to [0, 1]; a NaN `s` reads as 0).
    pub fn evaluate(&self, s: f64) -> TransferSample {
        let s = if s.is_nan() { 0.0 } else { s.clamp(0.0, 1.0) };
        let points = &self.points;
        let upper = points.partition_point(|p| f64::from(p.s) <= s);
        let sample = |p: &ControlPoint| TransferSample {
            kappa: DVec3::from(p.kappa.map(f64::from)),
            rho: f64::from(p.rho),
        };
        if upper == 0 {
            return sample(&points[0]);
        }
        if upper == points.len() {
            return sample(&points[points.len() - 1]);
        }
        let (a, b) = (&points[upper - 1], &points[upper]);
        let t = (s - f64::from(a.s)) / (f64::from(b.s) - f64::from(a.s));
        let (sa, sb) = (sample(a), sample(b));
        TransferSample {
            kappa: sa.kappa.lerp(sb.kappa, t),
            rho: sa.rho + (sb.rho - sa.rho) * t,
        }
    }
}

/// sRGB transfer curve to linear (IEC 61966-2-1), for values in [0, 1].
fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.040_45 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(s: f32, kappa: [f32; 3], rho: f32) -> ControlPoint {
        ControlPoint { s, kappa, rho }
    }

    fn temp_png(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("nebel-transfer-{}-{name}.png", std::process::id()))
    }

    #[test]
    fn points_are_sorted_and_steps_are_right_continuous() {
        let tf = TransferFunction::new([
            point(1.0, [0.0; 3], 1.0),
            point(0.5, [0.0; 3], 0.0),
            point(0.5, [0.0; 3], 4.0),
            point(0.0, [1.0; 3], 0.0),
        ])
        .unwrap();
        let s: Vec<f32> = tf.points().iter().map(|p| p.s).collect();
        assert_eq!(s, [0.0, 0.5, 0.5, 1.0]);
        assert_eq!(tf.evaluate(0.5).rho, 4.0);
        assert_eq!(tf.evaluate(0.25).rho, 0.0);
        assert_eq!(tf.evaluate(0.75).rho, 2.5);
        assert_eq!(tf.max_density(), 4.0);
        assert!(tf.is_transparent(0.1, 0.4999));
        assert!(!tf.is_transparent(0.1, 0.5));
    }

    #[test]
    fn every_error_has_a_clear_message() {
        let cases: [(Vec<ControlPoint>, &str); 5] = [
            (
                vec![],
                "a transfer function needs at least one control point",
            ),
            (
                vec![
                    point(0.0, [0.0; 3], 0.0),
                    point(0.5, [f32::NAN, 0.0, 0.0], 1.0),
                ],
                "control point 1 has a non-finite value (NaN or infinity)",
            ),
            (
                vec![point(1.5, [0.0; 3], 0.0)],
                "control point 0 has s = 1.5, outside [0, 1]",
            ),
            (
                vec![point(0.5, [0.0, -1.0, 0.0], 0.0)],
                "control point 0 has a negative chromaticity κ = [0.0, -1.0, 0.0]",
            ),
            (
                vec![point(0.5, [0.0; 3], -2.0)],
                "control point 0 has a negative density ρ = -2",
            ),
        ];
        for (points, message) in cases {
            assert_eq!(
                TransferFunction::new(points).unwrap_err().to_string(),
                message
            );
        }
        let tf = TransferFunction::preset(TransferPreset::Smoke);
        assert_eq!(
            tf.scale_density(-1.0).unwrap_err().to_string(),
            "density scale -1 must be finite and ≥ 0"
        );
        assert!(matches!(
            tf.scale_density(2.0).unwrap().scale_density(f32::MAX),
            Err(TransferError::NonFinite { .. })
        ));
    }

    #[test]
    fn hash_is_stable_and_tracks_content() {
        let a = TransferFunction::preset(TransferPreset::Cloud);
        let b = TransferFunction::new(a.points().to_vec()).unwrap();
        assert_eq!(a.content_hash(), b.content_hash());
        let mut points = a.points().to_vec();
        points[3].kappa[1] += 1e-6;
        let c = TransferFunction::new(points).unwrap();
        assert_ne!(a.content_hash(), c.content_hash());
        assert_ne!(
            a.content_hash(),
            a.scale_density(2.0).unwrap().content_hash()
        );
        // −0.0 and +0.0 are the same function.
        let zero = TransferFunction::new([point(0.0, [0.0; 3], 0.0)]).unwrap();
        let negative = TransferFunction::new([point(-0.0, [-0.0; 3], -0.0)]).unwrap();
        assert_eq!(zero.content_hash(), negative.content_hash());
        // Fixed value: FNV-1a of the bit patterns, the same on every platform.
        assert_eq!(zero.content_hash(), 0xc118_bcb0_0c9e_84e4);
    }

    #[test]
    fn presets_are_valid_and_distinct() {
        let hashes: std::collections::HashSet<u64> = TransferPreset::ALL
            .iter()
            .map(|&p| {
                let tf = TransferFunction::preset(p);
                assert_eq!(tf.max_density(), 1.0, "{p:?}");
                tf.content_hash()
            })
            .collect();
        assert_eq!(hashes.len(), TransferPreset::ALL.len());
        // The cloud's inverse ramp: bright where thin, darker and bluer where dense.
        let cloud = TransferFunction::preset(TransferPreset::Cloud);
        let (thin, dense) = (cloud.evaluate(0.1).kappa, cloud.evaluate(1.0).kappa);
        assert!(thin.min_element() > dense.max_element());
        assert!(dense.z > dense.x);
        assert!(cloud.is_transparent(0.0, 0.04));
        // The sunset is warm where the sun reaches and dusky in the shade;
        // bad weather is darker than the cloud and denser where thin.
        let (day, sunset) = (
            TransferFunction::preset(TransferPreset::CloudLight),
            TransferFunction::preset(TransferPreset::SunsetCloudLight),
        );
        let (lit, shade) = (sunset.evaluate(1.0).kappa, sunset.evaluate(0.0).kappa);
        assert!(lit.x > 1.5 * lit.z && shade.max_element() < day.evaluate(0.0).kappa.min_element());
        let storm = TransferFunction::preset(TransferPreset::BadWeather);
        for s in [0.05, 0.2, 0.5, 1.0] {
            let (grey, white) = (storm.evaluate(s), cloud.evaluate(s));
            assert!(grey.kappa.max_element() < white.kappa.min_element(), "{s}");
            assert!(grey.rho >= white.rho, "{s}");
        }
    }

    #[test]
    fn png_strip_loads_srgb_and_alpha() {
        let path = temp_png("ok");
        let strip = image::RgbaImage::from_fn(3, 1, |x, _| match x {
            0 => image::Rgba([0, 0, 0, 0]),
            1 => image::Rgba([188, 255, 10, 128]),
            _ => image::Rgba([255, 255, 255, 255]),
        });
        strip.save(&path).unwrap();
        let tf = TransferFunction::from_png_strip(&path, 2.0).unwrap();
        std::fs::remove_file(&path).unwrap();
        let points = tf.points();
        assert_eq!(points.len(), 3);
        assert_eq!(points[1].s, 0.5);
        assert_eq!(points[2].kappa, [1.0; 3]);
        assert_eq!(points[2].rho, 2.0);
        // sRGB 188 → linear ≈ 0.5.
        assert!(
            (points[1].kappa[0] - 0.5029).abs() < 1e-3,
            "{:?}",
            points[1]
        );
        assert!((points[1].kappa[2] - srgb_to_linear(10.0 / 255.0)).abs() < 1e-7);
        assert!((points[1].rho - 2.0 * 128.0 / 255.0).abs() < 1e-6);
    }

    #[test]
    fn a_png_strip_beyond_the_memory_budget_is_refused_from_its_header() {
        let path = temp_png("wide");
        crate::test_support::write_png_header(&path, 200_000_000, 1);
        let error = TransferFunction::from_png_strip(&path, 1.0).unwrap_err();
        std::fs::remove_file(&path).unwrap();
        assert!(matches!(error, TransferError::OverBudget { .. }));
        let message = error.to_string();
        assert!(
            message.contains("wide.png: a transfer function of 200000000 control points needs 7,200,000,000 bytes"),
            "{message}"
        );
    }

    #[test]
    fn png_strip_errors_name_the_file() {
        let path = temp_png("tall");
        image::RgbImage::new(4, 2).save(&path).unwrap();
        let error = TransferFunction::from_png_strip(&path, 1.0).unwrap_err();
        std::fs::remove_file(&path).unwrap();
        assert_eq!(
            error.to_string(),
            format!(
                "transfer-function strip {} is 4×2 pixels; it must be 1 pixel high",
                path.display()
            )
        );
        let missing = temp_png("missing");
        let error = TransferFunction::from_png_strip(&missing, 1.0).unwrap_err();
        assert!(matches!(error, TransferError::Image { .. }));
        assert!(
            error.to_string().starts_with(&format!(
                "cannot read transfer-function strip {}: ",
                missing.display()
            )),
            "{error}"
        );
        let garbage = temp_png("garbage");
        std::fs::write(&garbage, b"not a png").unwrap();
        let error = TransferFunction::from_png_strip(&garbage, 1.0).unwrap_err();
        std::fs::remove_file(&garbage).unwrap();
        assert!(matches!(error, TransferError::Image { .. }), "{error}");
        assert!(matches!(
            TransferFunction::from_png_strip(&garbage, f32::NAN),
            Err(TransferError::InvalidDensityScale { .. })
        ));
    }
}
