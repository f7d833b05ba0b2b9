//! An aurora in a scene file (Röttger 2004 §10.4): curtains between a plane
//! and tops raised by their strength, emissive, coloured by altitude, and
//! the exact cells the reference integrates; and the stars behind it.
//!
//! ```ron
//! aurora: (
//!     curtains: (seed: 1, count: 3, width: 0.015, fold: 0.03, drift: 0.01, pulse: 0.2, rays: 0.4),
//!     // or map: Some("aurora.png"): a grayscale footprint (black none, white
//!     // the strongest) instead of the curtains, still
//!     center: (0.0, 0.0, 0.0),  // the footprint's centre at the bottom's altitude 0
//!     extent: 600000.0,         // side of the square footprint, m; default 600 km
//!     bottom: 100000.0,         // the curtains' bottom, m above center; default 100 km
//!     top: 300000.0,            // where the strongest reach; default 300 km
//!     resolution: 257,          // footprint points per side, 2^k + 1 from 9 to 2049
//!     brightness: 6e-6,         // emission per metre, times the transfer function's ρ
//!     transfer: Preset(Aurora), // κ and ρ over the altitude in the curtains; default this
//!     speed: 1.0,               // animation seconds per second; default 1
//!     accuracy: 12.0,           // the quadtree's c; default 12
//! ),
//! stars: (count: 3000, seed: 7, brightness: 1.0), // simple stars on the sky
//! ```
//!
//! Every field has the default shown. The reference draws the aurora as the
//! cells the plugin draws for the reference camera at the last frame's time
//! (the same footprint, quadtree, refinement and prisms, without culling),
//! integrated exactly; it draws no stars (it shades no surface).

use std::path::Path;

use glam::DVec3;
use serde::{Deserialize, Serialize};

use nebel_core::field::{AuroraCurtains, HeightField};
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_lod::quadtree::DEFAULT_MIN_RESOLUTION;
use nebel_lod::{AuroraShape, CellOrder, TerrainMap};

use super::sky_layer::{LayerDrawing, layer_reference};
use super::{
    BuiltVolume, InvalidField, TransferDescription, finite, layer_side, non_negative, positive,
    shape_error,
};

/// An aurora over the scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AuroraDescription {
    /// The procedural curtains (ignored with a `map`).
    pub curtains: AuroraCurtains,
    /// A grayscale PNG footprint, relative to the scene file, instead of the
    /// curtains. Default none.
    pub map: Option<String>,
    /// The footprint's centre, world space; the bottom and top are above it.
    pub center: [f32; 3],
    /// Side of the square footprint, m, finite and > 0.
    pub extent: f32,
    /// Altitude of the curtains' bottom above `center`, m, finite.
    pub bottom: f32,
    /// Altitude the strongest curtains reach, m, finite and above `bottom`.
    pub top: f32,
    /// Footprint points per side, `2^k + 1` from 9 to 2049.
    pub resolution: u32,
    /// Multiplies the transfer function's ρ, 1/m, finite and ≥ 0.
    pub brightness: f32,
    /// κ and ρ over the altitude in the curtains. Default `Preset(Aurora)`.
    pub transfer: Option<TransferDescription>,
    /// Animation seconds per second, finite and ≥ 0.
    pub speed: f32,
    /// Accuracy `c` of the quadtree's criterion, finite and > 0.
    pub accuracy: f32,
}

impl Default for AuroraDescription {
    fn default() -> Self {
        Self {
            curtains: AuroraCurtains::default(),
            map: None,
            center: [0.0; 3],
            extent: 600e3,
            bottom: 100e3,
            top: 300e3,
            resolution: 257,
            brightness: 6e-6,
            transfer: None,
            speed: 1.0,
            accuracy: 12.0,
        }
    }
}

/// Stars on the night sky: small white points far beyond everything else,
/// seeded, with a spread of brightness.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StarsDescription {
    /// Stars over the whole sphere, up to 100,000. Default 3000.
    pub count: u32,
    /// Seeds their places and brightness. Default 7.
    pub seed: u64,
    /// The brightest star's colour value (linear), finite and ≥ 0. Default 1.
    pub brightness: f32,
}

impl Default for StarsDescription {
    fn default() -> Self {
        Self {
            count: 3000,
            seed: 7,
            brightness: 1.0,
        }
    }
}

impl StarsDescription {
    /// Checks the ranges.
    pub(super) fn validate(&self) -> Result<(), InvalidField> {
        if self.count > 100_000 {
            return Err(InvalidField::new(
                "count",
                format!("must be at most 100000, got {}", self.count),
            ));
        }
        non_negative("brightness", self.brightness)
    }

    /// The stars as unit directions with a brightness in (0, 1] each
    /// (uniform over the sphere; the brightness falls off like a power law,
    /// many faint and few bright).
    pub fn stars(&self) -> Vec<([f32; 3], f32)> {
        let mut state = self.seed ^ 0x57a2_5eed;
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..self.count)
            .map(|_| {
                let y = 2.0 * next() - 1.0;
                let angle = std::f64::consts::TAU * next();
                let r = (1.0 - y * y).max(0.0).sqrt();
                let direction = [(r * angle.cos()) as f32, y as f32, (r * angle.sin()) as f32];
                (direction, next().powi(4).max(0.02) as f32)
            })
            .collect()
    }
}

/// A scene's aurora with its files read: the map's unit values (for a
/// `map`) and the brightness-scaled transfer function.
#[derive(Clone, Debug, PartialEq)]
pub struct BuiltAurora {
    /// The footprint map (black 0, white 1), `None` for the curtains.
    pub map: Option<HeightField>,
    /// κ and ρ, `brightness` applied.
    pub transfer_function: TransferFunction,
}

impl AuroraDescription {
    /// The curtains' shape.
    pub fn shape(&self) -> AuroraShape {
        AuroraShape {
            extent: f64::from(self.extent),
            bottom: f64::from(self.bottom),
            top: f64::from(self.top),
        }
    }

    /// Checks every setting against its documented range.
    pub(super) fn validate(&self) -> Result<(), InvalidField> {
        self.shape()
            .validate()
            .map_err(|error| shape_error(error, "aurora "))?;
        finite("center", &self.center)?;
        layer_side("resolution", self.resolution)?;
        non_negative("brightness", self.brightness)?;
        non_negative("speed", self.speed)?;
        positive("accuracy", self.accuracy)?;
        if self.map.as_ref().is_some_and(|path| path.trim().is_empty()) {
            return Err(InvalidField::new(
                "map",
                "must name a PNG file (relative to the scene file)",
            ));
        }
        if self.map.is_none() {
            self.curtains
                .validate()
                .map_err(|error| InvalidField::new("curtains", error.to_string()))?;
        }
        Ok(())
    }

    /// Loads the map (if any) and builds the transfer function with ρ times
    /// `brightness`; `scene_dir` resolves their paths. Errors name the field.
    pub fn build(&self, scene_dir: &Path) -> Result<BuiltAurora, InvalidField> {
        let load = |path: &String| InvalidField::load_map(scene_dir, path, "map");
        let transfer = self.transfer.as_ref();
        Ok(BuiltAurora {
            map: self.map.as_ref().map(load).transpose()?,
            transfer_function: TransferDescription::scaled(
                transfer,
                TransferPreset::Aurora,
                scene_dir,
                self.brightness,
            )?,
        })
    }

    /// The footprint's strengths on the grid at animation time `seconds`.
    pub fn strength(&self, built: &BuiltAurora, seconds: f64) -> Result<Vec<f32>, InvalidField> {
        let side = self.resolution as usize;
        match &built.map {
            Some(map) => TerrainMap::resample(map.heights(), map.dims(), side)
                .map(|layer| layer.values().to_vec())
                .map_err(|error| InvalidField::new("map", error.to_string())),
            None => self
                .curtains
                .map(side, seconds)
                .map_err(|error| InvalidField::new("curtains", error.to_string())),
        }
    }

    /// The aurora's cells for an eye at `eye` (world space) at the scene
    /// time `time` s, as the plugin draws them (without culling), as an
    /// emissive volume for the reference; `None` when it has none.
    pub fn reference(
        &self,
        built: &BuiltAurora,
        eye: DVec3,
        time: f64,
    ) -> Result<Option<BuiltVolume>, InvalidField> {
        let side = self.resolution as usize;
        let strength = self.strength(built, time * f64::from(self.speed))?;
        let shape = self.shape();
        let layer = shape
            .layer(side, &strength, DEFAULT_MIN_RESOLUTION, 1.0)
            .map_err(|error| InvalidField::new("map", error.to_string()))?;
        let drawing = LayerDrawing {
            center: self.center,
            accuracy: self.accuracy,
            profile: &AuroraShape::profile(),
            scalar: shape.scalar(),
            order: CellOrder::Unordered,
            light_response: Default::default(),
            transfer_function: &built.transfer_function,
            mode: OpticalMode::Emissive,
        };
        layer_reference(&layer, &drawing, eye)
    }
}
