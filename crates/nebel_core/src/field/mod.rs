//! Scalar fields: 3D density grids and 2D height fields, their loaders, seeded
//! procedural generators and the 2^n+1 padding and resampling rules
//! (Röttger and Ertl 2003 §2 and §6, Röttger 2004 ch. 3 and 11).
//!
//! - [`DensityGrid`]: density samples in [0, 1] on a regular 3D grid of points,
//!   trilinear in between (clouds, smoke, any volume).
//! - [`HeightField`]: heights on a regular 2D grid of points over the horizontal
//!   x–z plane (Bevy is y-up), bilinear in between (terrain, fog thickness maps).
//! - Loaders: 8- and 16-bit grayscale PNG (height fields, fog maps, density
//!   volumes as a stack of slice files or one tiled image) and raw little-endian
//!   u8 / u16 / f32 with the dimensions given ([`RawSampleType`]).
//! - Generators: fBm Perlin noise in 2D and 3D and ridged multifractal noise,
//!   deterministic for a seed ([`ProceduralNoise`]); terrain heights rescaled
//!   to [0, 1] and shaped by an exponent ([`TerrainNoise`],
//!   [`HeightField::terrain`]).
//! - Ground fog thickness maps from noise patches ([`FogNoise`]) or valleys
//!   filled up to an altitude with a noisy edge ([`ValleyFog`]).
//! - Aurora curtain footprints: arcs with folds and rays that drift, fold and
//!   pulse smoothly over time ([`AuroraCurtains`]).
//! - Cloud shadows on the ground: the transmittance toward the sun below
//!   cloud volumes on a map over a plane ([`GroundShadow`]).
//! - [`effects`]: the emissive effects of Röttger 2004 §10.4, an animated campfire
//!   density and a search-light cone of tetrahedra.
//! - The C-LOD hierarchies need (2^n+1) points per axis; other sizes are padded
//!   or resampled ([`PadFill`], [`power_of_two_plus_one`]).
//!
//! Grid points are stored x fastest: index `i + nx · (j + ny · k)`. Every
//! constructor validates its input and returns a [`FieldError`] naming the file
//! (or the in-memory source) on wrong sizes, non-finite values, out-of-range
//! densities and unreadable files. Every constructor that allocates samples
//! checks their size against the memory budget first
//! ([`crate::budget`], [`FieldError::OverBudget`]; [`DensityGrid::check_budget`]
//! and [`HeightField::check_budget`] give the same check without building).

mod aurora;
mod cloud;
mod density_grid;
pub mod effects;
mod fog;
mod ground_shadow;
mod height_field;
mod light;
mod load;
mod perlin_row;
mod primitives;
mod procedural;
mod resample;
mod terrain;
mod terrain_shade;
mod terrain_shadow;
mod value_noise;
mod weather;

pub use aurora::AuroraCurtains;
pub use cloud::{CloudKind, CloudNoise, side_fade_factors};
pub use density_grid::DensityGrid;
pub use effects::{campfire_density, search_light_cells};
pub use fog::{FogNoise, ValleyFog};
pub use ground_shadow::{
    GroundShadow, ShadowCaster, optical_depth_toward, shaded_stretch, sun_transmittance,
};
pub use height_field::HeightField;
pub use light::{
    CloudLighting, SKY_DIFFUSIVITY, ScatteringOctaves, light_field, light_field_with_threads,
};
pub use load::{Normalization, RawSampleType, TileLayout, read_png};
pub use primitives::{CloudEllipsoid, CloudShape, wyvill};
pub use procedural::{NOISE_OFFSET, NoiseKind, ProceduralNoise};
pub use resample::{PadFill, power_of_two_plus_one};
pub use terrain::{DEFAULT_TERRAIN_SPACING, DEFAULT_TERRAIN_VERTICAL_SCALE, TerrainNoise};
pub use terrain_shade::{PlacedHeights, PlacedTerrainShadow};
pub use terrain_shadow::{TerrainShadow, shadow_height};
pub use value_noise::ValueNoise;
pub use weather::{CloudWeather, WeatherMap};

/// `0` below `edge0`, `1` above `edge1`, the cubic `3s² − 2s³` of `s = (x −
/// edge0) / (edge1 − edge0)` between.
pub(crate) fn smoothstep(edge0: f64, edge1: f64, x: f64) -> f64 {
    let s = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0);
    s * s * (3.0 - 2.0 * s)
}

use std::path::PathBuf;

use crate::budget::{BudgetError, Dims, check_allocation};

/// Why a field could not be built or loaded. `name` is the file path or, for
/// in-memory data, the constructor that received it.
#[derive(Debug, thiserror::Error)]
pub enum FieldError {
    /// The file could not be read (missing, no permission, ...).
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
    /// The PNG is not 8- or 16-bit grayscale.
    #[error(
        "{}: expected an 8- or 16-bit grayscale PNG, found {found}; convert it to grayscale",
        path.display()
    )]
    NotGrayscale {
        /// The file.
        path: PathBuf,
        /// The colour type found, e.g. `Rgb8`.
        found: String,
    },
    /// The number of samples does not match the dimensions.
    #[error("{name}: dimensions {dims:?} need {expected} samples, found {actual}")]
    SizeMismatch {
        /// File or source.
        name: String,
        /// Samples per axis.
        dims: Vec<usize>,
        /// Product of `dims`.
        expected: usize,
        /// Samples present.
        actual: usize,
    },
    /// A raw file's length does not match its dimensions and sample type.
    #[error(
        "{}: dimensions {dims:?} of {sample_type:?} need {expected} bytes, the file has {actual}",
        path.display()
    )]
    RawSizeMismatch {
        /// The file.
        path: PathBuf,
        /// Samples per axis.
        dims: Vec<usize>,
        /// The sample type the caller declared.
        sample_type: RawSampleType,
        /// Bytes the dimensions need.
        expected: u128,
        /// Bytes in the file.
        actual: u64,
    },
    /// Two density slices differ in size.
    #[error(
        "{}: slice is {found:?} pixels but {} is {expected:?}; all slices must have the same size",
        path.display(),
        first.display()
    )]
    SliceSizeMismatch {
        /// The offending slice.
        path: PathBuf,
        /// Its width and height.
        found: (u32, u32),
        /// The first slice, which sets the size.
        first: PathBuf,
        /// The first slice's width and height.
        expected: (u32, u32),
    },
    /// A tiled image does not split into the requested tiles.
    #[error(
        "{}: a {width}×{height} image cannot hold {slices} slices as {columns}×{rows} equal tiles",
        path.display()
    )]
    TileLayout {
        /// The file.
        path: PathBuf,
        /// Image width, pixels.
        width: u32,
        /// Image height, pixels.
        height: u32,
        /// Tiles per row.
        columns: u32,
        /// Tiles per column.
        rows: u32,
        /// Slices requested.
        slices: u32,
    },
    /// No slice files were given.
    #[error("a density volume needs at least two slice files, {count} given")]
    TooFewSlices {
        /// Slices given.
        count: usize,
    },
    /// A sample is NaN or infinite.
    #[error("{name}: sample {index} is {value}, not a finite number")]
    NonFinite {
        /// File or source.
        name: String,
        /// Index of the sample (x fastest).
        index: usize,
        /// The value found.
        value: f32,
    },
    /// A density sample lies outside [0, 1].
    #[error(
        "{name}: density sample {index} is {value}, outside [0, 1] (load with Normalization::DivideByMax to rescale)"
    )]
    OutOfRange {
        /// File or source.
        name: String,
        /// Index of the sample (x fastest).
        index: usize,
        /// The value found.
        value: f32,
    },
    /// Fewer than two samples along an axis.
    #[error("{name}: dimensions {dims:?}: every axis needs at least 2 samples")]
    TooSmall {
        /// File or source.
        name: String,
        /// Samples per axis.
        dims: Vec<usize>,
    },
    /// The samples to be built would exceed the memory budget; nothing was
    /// allocated.
    #[error("{name}: {source}")]
    OverBudget {
        /// File or source.
        name: String,
        /// What was to be built, its bytes and the budget.
        source: BudgetError,
    },
    /// A geometric parameter (spacing, origin, vertical scale, noise setting) is
    /// not finite or out of its range.
    #[error("{name}: {parameter} = {value} is invalid: {requirement}")]
    InvalidParameter {
        /// File or source.
        name: String,
        /// The parameter, e.g. `spacing`.
        parameter: &'static str,
        /// Its value, formatted.
        value: String,
        /// What it must satisfy.
        requirement: &'static str,
    },
}

impl FieldError {
    /// A [`FieldError::InvalidParameter`] of the source or generator `name`.
    pub(crate) fn invalid_parameter(
        name: &str,
        parameter: &'static str,
        value: String,
        requirement: &'static str,
    ) -> Self {
        Self::InvalidParameter {
            name: name.to_owned(),
            parameter,
            value,
            requirement,
        }
    }

    /// Turns a [`BudgetError`] into a [`FieldError::OverBudget`] of the
    /// source or generator `name`.
    fn over_budget(name: &str) -> impl FnOnce(BudgetError) -> Self + '_ {
        move |source| Self::OverBudget {
            name: name.to_owned(),
            source,
        }
    }
}

/// The settings of the source or generator it names, each checked against
/// its range: the first out of it is a [`FieldError::InvalidParameter`].
#[derive(Clone, Copy)]
pub(crate) struct Settings<'a>(pub(crate) &'a str);

impl Settings<'_> {
    /// `Err` naming `parameter` and its `value` unless `ok`.
    pub(crate) fn require(
        self,
        ok: bool,
        parameter: &'static str,
        value: impl std::fmt::Display,
        requirement: &'static str,
    ) -> Result<(), FieldError> {
        if ok {
            return Ok(());
        }
        Err(FieldError::invalid_parameter(
            self.0,
            parameter,
            value.to_string(),
            requirement,
        ))
    }

    /// Each value finite and above 0.
    pub(crate) fn positive<T>(self, values: &[(&'static str, T)]) -> Result<(), FieldError>
    where
        T: Copy + Into<f64> + std::fmt::Display,
    {
        self.each(values, |v| v.is_finite() && v > 0.0, "finite and positive")
    }

    /// Each value finite and at least 0.
    pub(crate) fn non_negative<T>(self, values: &[(&'static str, T)]) -> Result<(), FieldError>
    where
        T: Copy + Into<f64> + std::fmt::Display,
    {
        self.each(values, |v| v.is_finite() && v >= 0.0, "finite and ≥ 0")
    }

    /// Each value between 0 and 1.
    pub(crate) fn fractions<T>(self, values: &[(&'static str, T)]) -> Result<(), FieldError>
    where
        T: Copy + Into<f64> + std::fmt::Display,
    {
        self.each(values, |v| (0.0..=1.0).contains(&v), "between 0 and 1")
    }

    /// Each value `ok`, or an error that it must be `requirement`.
    fn each<T>(
        self,
        values: &[(&'static str, T)],
        ok: impl Fn(f64) -> bool,
        requirement: &'static str,
    ) -> Result<(), FieldError>
    where
        T: Copy + Into<f64> + std::fmt::Display,
    {
        for &(parameter, value) in values {
            self.require(ok(value.into()), parameter, value, requirement)?;
        }
        Ok(())
    }
}

/// Bytes per f32 sample of a grid or field.
const SAMPLE_BYTES: u64 = size_of::<f32>() as u64;

/// What a budget error calls a [`DensityGrid`].
const DENSITY_GRID: &str = "density grid";

/// What a budget error calls a [`HeightField`].
const HEIGHT_FIELD: &str = "height field";

/// The bytes of a field of `dims` points at `bytes_per_point`, checked
/// against the memory budget; `kind` (e.g. `density grid`) names it.
fn check_points(kind: &str, dims: &[usize], bytes_per_point: u64) -> Result<u64, BudgetError> {
    check_allocation(
        || format!("{kind} of {} points", Dims(dims)),
        dims,
        bytes_per_point,
    )
}

/// The points of a field of `dims` (each ≥ 2) that `name` builds as `kind`
/// at `bytes_per_point`, checked against the memory budget before anything
/// is allocated.
fn budgeted_points(
    name: &str,
    kind: &str,
    dims: &[usize],
    bytes_per_point: u64,
) -> Result<usize, FieldError> {
    if dims.iter().any(|&n| n < 2) {
        return Err(FieldError::TooSmall {
            name: name.to_owned(),
            dims: dims.to_vec(),
        });
    }
    check_points(kind, dims, bytes_per_point).map_err(FieldError::over_budget(name))?;
    // Within the budget, so the product fits in usize.
    Ok(dims.iter().product())
}

/// Checks that every sample is finite, naming the first offender.
fn check_finite(name: &str, values: &[f32]) -> Result<(), FieldError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(FieldError::NonFinite {
            name: name.to_owned(),
            index,
            value: values[index],
        }),
        None => Ok(()),
    }
}

/// Checks `dims` (each ≥ 2) against `len` samples.
fn check_dims(name: &str, dims: &[usize], len: usize) -> Result<(), FieldError> {
    if dims.iter().any(|&n| n < 2) {
        return Err(FieldError::TooSmall {
            name: name.to_owned(),
            dims: dims.to_vec(),
        });
    }
    let expected = dims.iter().try_fold(1usize, |acc, &n| acc.checked_mul(n));
    if expected != Some(len) {
        return Err(FieldError::SizeMismatch {
            name: name.to_owned(),
            dims: dims.to_vec(),
            expected: expected.unwrap_or(usize::MAX),
            actual: len,
        });
    }
    Ok(())
}

/// Checks that a spacing is finite and positive on every axis.
fn check_spacing(name: &str, spacing: &[f64]) -> Result<(), FieldError> {
    let ok = spacing.iter().all(|s| s.is_finite() && *s > 0.0);
    let requirement = "finite and positive on every axis";
    Settings(name).require(ok, "spacing", format!("{spacing:?}"), requirement)
}

/// Checks that an origin is finite.
fn check_origin(name: &str, origin: &[f64]) -> Result<(), FieldError> {
    let ok = origin.iter().all(|o| o.is_finite());
    Settings(name).require(ok, "origin", format!("{origin:?}"), "finite")
}

/// Checks that a height field's vertical scale is finite.
fn check_vertical_scale(name: &str, vertical_scale: f64) -> Result<(), FieldError> {
    let ok = vertical_scale.is_finite();
    Settings(name).require(ok, "vertical_scale", vertical_scale, "finite")
}

/// Linear interpolation weights of a coordinate `u` (grid units) along an axis
/// of `n` points: the lower index (≤ n − 2) and the fraction in [0, 1]. `u` is
/// clamped to the axis; NaN reads as 0.
fn axis_weight(u: f64, n: usize) -> (usize, f64) {
    let last = (n - 1) as f64;
    let u = if u.is_nan() { 0.0 } else { u.clamp(0.0, last) };
    let lower = (u.floor() as usize).min(n - 2);
    (lower, u - lower as f64)
}
