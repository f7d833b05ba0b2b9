//! Procedural terrain heights: fractal Perlin noise rescaled to exactly
//! [0, 1] and shaped by an exponent, the unit height field a terrain
//! multiplies by its vertical scale (Röttger 2004 §3.5).
//!
//! The noise is [`ProceduralNoise`] (fBm or ridged multifractal, first-octave
//! frequency `1 / wavelength`, lacunarity 2) sampled at each grid point's
//! position `(i · spacing, j · spacing)`. Its output never spans its nominal
//! range, so the field is rescaled to its own minimum and maximum (the
//! lowest point becomes 0, the highest 1, like the libMini peer scenario of
//! the quadtree benchmark, "rescaled to 0..1000 m"): a terrain's vertical scale is then exactly its
//! relief. Last, every unit height `u` becomes `u^exponent`: an exponent above
//! 1 widens and flattens the valleys and sharpens the peaks (valleys for
//! ground fog to lie in), 1 keeps the noise as it is.

use glam::DVec2;

use super::{
    FieldError, HEIGHT_FIELD, HeightField, NoiseKind, ProceduralNoise, SAMPLE_BYTES, Settings,
    budgeted_points,
};

/// The default distance between neighbouring terrain grid points, metres.
pub const DEFAULT_TERRAIN_SPACING: f32 = 10.0;

/// The default height of a unit height (a white pixel), metres.
pub const DEFAULT_TERRAIN_VERTICAL_SCALE: f32 = 400.0;

/// Settings of [`HeightField::terrain`]: seeded fractal noise for terrain
/// heights.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct TerrainNoise {
    /// Fractal kind: [`NoiseKind::Fbm`] for rolling hills,
    /// [`NoiseKind::Ridged`] for mountain crests. Default `Fbm`.
    pub kind: NoiseKind,
    /// Seed; equal seeds give equal terrains. Default 0.
    pub seed: u32,
    /// Octaves, 1 to 32; each halves the wavelength. Default 6.
    pub octaves: usize,
    /// Wavelength of the first octave, world units (metres), finite and > 0:
    /// the size of the largest hills. Default 2000.
    pub wavelength: f64,
    /// Amplitude ratio between octaves, finite and > 0: larger is rougher.
    /// Default 0.5.
    pub persistence: f64,
    /// Exponent on the unit height, finite and > 0: above 1 flattens the
    /// valleys and sharpens the peaks. Default 1.
    pub exponent: f64,
}

impl Default for TerrainNoise {
    fn default() -> Self {
        Self {
            kind: NoiseKind::Fbm,
            seed: 0,
            octaves: 6,
            wavelength: 2000.0,
            persistence: 0.5,
            exponent: 1.0,
        }
    }
}

impl HeightField {
    /// A unit height field of `dims = [nx, nz]` points (each ≥ 2), `spacing`
    /// world units apart (finite, > 0), origin (0, 0): [`TerrainNoise`] at
    /// each point, rescaled to [0, 1] and raised to the exponent (see the
    /// module docs). A field whose noise is constant comes out all 0.
    ///
    /// Errors: [`FieldError::InvalidParameter`] naming a setting,
    /// [`FieldError::TooSmall`], and [`FieldError::OverBudget`] when the
    /// field (4 bytes per point) exceeds the memory budget, before anything
    /// is allocated.
    pub fn terrain(
        dims: [usize; 2],
        spacing: f64,
        noise: &TerrainNoise,
    ) -> Result<Self, FieldError> {
        let name = "HeightField::terrain";
        Settings(name).positive(&[
            ("wavelength", noise.wavelength),
            ("exponent", noise.exponent),
        ])?;
        let settings = ProceduralNoise {
            kind: noise.kind,
            seed: noise.seed,
            octaves: noise.octaves,
            frequency: 1.0 / noise.wavelength,
            lacunarity: 2.0,
            persistence: noise.persistence,
        };
        budgeted_points(name, HEIGHT_FIELD, &dims, SAMPLE_BYTES)?;
        let raw = Self::procedural(dims, DVec2::splat(spacing), DVec2::ZERO, &settings, 1.0)?;
        let (low, high) = raw
            .heights()
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &h| {
                (lo.min(h), hi.max(h))
            });
        let range = high - low;
        let spacing = raw.spacing();
        // Rescaled in place: the noise's heights become the terrain's.
        let mut heights = raw.into_heights();
        for h in &mut heights {
            *h = if range > 0.0 {
                let unit = f64::from(((*h - low) / range).clamp(0.0, 1.0));
                unit.powf(noise.exponent) as f32
            } else {
                0.0
            };
        }
        Self::validated(name, dims, spacing, DVec2::ZERO, heights)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn terrain_spans_the_unit_range_and_the_exponent_deepens_valleys() {
        let noise = TerrainNoise {
            wavelength: 80.0,
            ..TerrainNoise::default()
        };
        let field = HeightField::terrain([33, 33], 10.0, &noise).unwrap();
        let heights = field.heights();
        let min = heights.iter().copied().fold(f32::INFINITY, f32::min);
        let max = heights.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        assert_eq!((min, max), (0.0, 1.0));
        assert_eq!(field.spacing(), DVec2::splat(10.0));

        let shaped = HeightField::terrain(
            [33, 33],
            10.0,
            &TerrainNoise {
                exponent: 2.0,
                ..noise
            },
        )
        .unwrap();
        for (a, b) in heights.iter().zip(shaped.heights()) {
            assert!((a * a - b).abs() < 1e-6, "{a}² != {b}");
        }
        let mean = |h: &[f32]| h.iter().sum::<f32>() / h.len() as f32;
        assert!(mean(shaped.heights()) < mean(heights));

        // Deterministic for a seed, different for another.
        assert_eq!(HeightField::terrain([33, 33], 10.0, &noise).unwrap(), field);
        let other = HeightField::terrain([33, 33], 10.0, &TerrainNoise { seed: 1, ..noise });
        assert_ne!(other.unwrap(), field);
    }

    #[test]
    fn bad_settings_are_named() {
        let error = |noise: TerrainNoise| {
            HeightField::terrain([9, 9], 1.0, &noise)
                .unwrap_err()
                .to_string()
        };
        let message = error(TerrainNoise {
            wavelength: 0.0,
            ..TerrainNoise::default()
        });
        assert!(message.contains("wavelength = 0"), "{message}");
        let message = error(TerrainNoise {
            exponent: f64::NAN,
            ..TerrainNoise::default()
        });
        assert!(message.contains("exponent = NaN"), "{message}");
        let message = error(TerrainNoise {
            octaves: 0,
            ..TerrainNoise::default()
        });
        assert!(message.contains("octaves"), "{message}");
        assert!(HeightField::terrain([1, 9], 1.0, &TerrainNoise::default()).is_err());
    }

    #[test]
    fn terrains_beyond_the_memory_budget_are_refused_before_allocating() {
        let message = HeightField::terrain([65_537; 2], 1.0, &TerrainNoise::default())
            .unwrap_err()
            .to_string();
        assert!(
            message.contains(
                "HeightField::terrain: height field of 65537 × 65537 points needs 17,180,393,476 bytes"
            ),
            "{message}"
        );
    }
}
