//! Seeded procedural fields: fBm Perlin noise and ridged multifractal noise in
//! 2D (height fields) and 3D (density grids), through the `noise` crate.
//!
//! The noise is evaluated at each grid point's world position, so a field is a
//! pure function of its seed, settings and geometry: the same inputs give the
//! same field on every run and machine. Noise output (nominally in [−1, 1]) is
//! mapped to [0, 1] by `(v + 1) / 2` and clamped.
//!
//! Perlin noise is zero on its integer lattice, so a grid whose points land on
//! that lattice in every octave (spacing 1, frequency 1, lacunarity 2) would
//! come out flat. Every position is therefore shifted by the fixed offset
//! [`NOISE_OFFSET`] (in noise units, before the octaves scale it), which is
//! irrational in every component.

use glam::{DVec2, DVec3};
use noise::{Fbm, MultiFractal, NoiseFn, Perlin, RidgedMulti};

use super::{
    DENSITY_GRID, DensityGrid, FieldError, HEIGHT_FIELD, HeightField, SAMPLE_BYTES, Settings,
    budgeted_points,
};

/// Shift of every sample position in noise units (first-octave cycles): the
/// fractional parts of 1/π, the golden ratio and √2, so no grid point meets
/// Perlin's zero lattice in any octave.
pub const NOISE_OFFSET: [f64; 3] = [
    std::f64::consts::FRAC_1_PI,
    0.618_033_988_749_895,
    std::f64::consts::SQRT_2 - 1.0,
];

/// Which fractal sum of Perlin octaves to use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
pub enum NoiseKind {
    /// Fractal Brownian motion: a sum of octaves with geometrically falling
    /// amplitude. Soft, rolling shapes (cloud density, hills). The default.
    #[default]
    Fbm,
    /// Ridged multifractal: `(1 − |noise|)²` octaves weighted by the previous
    /// one. Sharp crests (mountain ridges, streaky aurora).
    Ridged,
}

/// Settings of a seeded noise generator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProceduralNoise {
    /// Fractal kind. Default [`NoiseKind::Fbm`].
    pub kind: NoiseKind,
    /// Seed; equal seeds give equal fields. Default 0.
    pub seed: u32,
    /// Number of octaves, 1 to 32. Default 6.
    pub octaves: usize,
    /// Frequency of the first octave, cycles per world unit, > 0. Default 1.
    pub frequency: f64,
    /// Frequency ratio between octaves, > 0. Default 2.
    pub lacunarity: f64,
    /// Amplitude ratio between octaves, > 0. Default 0.5.
    pub persistence: f64,
}

impl Default for ProceduralNoise {
    fn default() -> Self {
        Self {
            kind: NoiseKind::Fbm,
            seed: 0,
            octaves: 6,
            frequency: 1.0,
            lacunarity: 2.0,
            persistence: 0.5,
        }
    }
}

/// A configured generator from the `noise` crate.
enum Generator {
    Fbm(Fbm<Perlin>),
    Ridged(RidgedMulti<Perlin>),
}

impl ProceduralNoise {
    fn generator(&self, name: &str) -> Result<Generator, FieldError> {
        let settings = Settings(name);
        let ok = (1..=32).contains(&self.octaves);
        settings.require(ok, "octaves", self.octaves, "between 1 and 32")?;
        settings.positive(&[
            ("frequency", self.frequency),
            ("lacunarity", self.lacunarity),
            ("persistence", self.persistence),
        ])?;
        Ok(match self.kind {
            NoiseKind::Fbm => Generator::Fbm(self.fractal(Fbm::new(self.seed))),
            NoiseKind::Ridged => Generator::Ridged(self.fractal(RidgedMulti::new(self.seed))),
        })
    }

    /// `noise` with these octaves, frequency, lacunarity and persistence.
    fn fractal<T: MultiFractal>(&self, noise: T) -> T {
        noise
            .set_octaves(self.octaves)
            .set_frequency(self.frequency)
            .set_lacunarity(self.lacunarity)
            .set_persistence(self.persistence)
    }
}

impl Generator {
    /// Unit noise at `point` (world units); `frequency` is the first octave's.
    fn unit<const N: usize>(&self, point: [f64; N], frequency: f64) -> f32
    where
        Fbm<Perlin>: NoiseFn<f64, N>,
        RidgedMulti<Perlin>: NoiseFn<f64, N>,
    {
        let point: [f64; N] = std::array::from_fn(|a| point[a] + NOISE_OFFSET[a] / frequency);
        let value = match self {
            Self::Fbm(noise) => noise.get(point),
            Self::Ridged(noise) => noise.get(point),
        };
        let unit = ((value + 1.0) / 2.0).clamp(0.0, 1.0);
        if unit.is_nan() { 0.0 } else { unit as f32 }
    }
}

impl DensityGrid {
    /// A density grid of `dims` points (geometry as in [`DensityGrid::new`])
    /// filled with 3D `noise` at each point's world position, mapped to [0, 1].
    ///
    /// Errors: [`FieldError::InvalidParameter`] naming a noise setting,
    /// [`FieldError::TooSmall`], [`FieldError::OverBudget`] when the grid (4
    /// bytes per point) exceeds the memory budget, before anything is
    /// allocated, and the errors of [`DensityGrid::new`] for the geometry.
    pub fn procedural(
        dims: [usize; 3],
        spacing: DVec3,
        origin: DVec3,
        noise: &ProceduralNoise,
    ) -> Result<Self, FieldError> {
        let name = "DensityGrid::procedural";
        let generator = noise.generator(name)?;
        let points = budgeted_points(name, DENSITY_GRID, &dims, SAMPLE_BYTES)?;
        let [nx, ny, nz] = dims;
        let mut values = Vec::with_capacity(points);
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let p = origin + DVec3::new(i as f64, j as f64, k as f64) * spacing;
                    values.push(generator.unit(p.to_array(), noise.frequency));
                }
            }
        }
        Self::validated(name, dims, spacing, origin, values)
    }
}

impl HeightField {
    /// A height field of `dims` points (geometry as in [`HeightField::new`])
    /// with height `vertical_scale · unit noise` (world units), from 2D `noise`
    /// at each point's world (x, z).
    ///
    /// Errors: as [`DensityGrid::procedural`], and
    /// [`FieldError::InvalidParameter`] naming `vertical_scale`.
    pub fn procedural(
        dims: [usize; 2],
        spacing: DVec2,
        origin: DVec2,
        noise: &ProceduralNoise,
        vertical_scale: f64,
    ) -> Result<Self, FieldError> {
        let name = "HeightField::procedural";
        let generator = noise.generator(name)?;
        let points = budgeted_points(name, HEIGHT_FIELD, &dims, SAMPLE_BYTES)?;
        super::check_vertical_scale(name, vertical_scale)?;
        let [nx, nz] = dims;
        let mut heights = Vec::with_capacity(points);
        for j in 0..nz {
            for i in 0..nx {
                let p = origin + DVec2::new(i as f64, j as f64) * spacing;
                heights.push(
                    (f64::from(generator.unit(p.to_array(), noise.frequency)) * vertical_scale)
                        as f32,
                );
            }
        }
        Self::validated(name, dims, spacing, origin, heights)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{assert_mentions, error_message};

    fn settings(kind: NoiseKind, seed: u32) -> ProceduralNoise {
        ProceduralNoise {
            kind,
            seed,
            frequency: 0.37,
            ..Default::default()
        }
    }

    #[test]
    fn generators_are_deterministic_per_seed() {
        for kind in [NoiseKind::Fbm, NoiseKind::Ridged] {
            let grid = |seed| {
                DensityGrid::procedural(
                    [9, 5, 7],
                    DVec3::splat(0.7),
                    DVec3::new(0.1, 0.2, 0.3),
                    &settings(kind, seed),
                )
                .unwrap()
            };
            let (a, b, c) = (grid(42), grid(42), grid(43));
            assert_eq!(a, b, "{kind:?}");
            assert_ne!(a, c, "{kind:?}: another seed gives another field");
            let spread = a
                .values()
                .iter()
                .fold((1.0f32, 0.0f32), |(lo, hi), &v| (lo.min(v), hi.max(v)));
            assert!(
                spread.1 - spread.0 > 0.05,
                "{kind:?} field is not flat: {spread:?}"
            );

            let field = |seed| {
                HeightField::procedural(
                    [17, 9],
                    DVec2::splat(0.5),
                    DVec2::ZERO,
                    &settings(kind, seed),
                    10.0,
                )
                .unwrap()
            };
            assert_eq!(field(7), field(7));
            assert_ne!(field(7), field(8));
            assert!(field(7).heights().iter().all(|h| (0.0..=10.0).contains(h)));
        }
    }

    #[test]
    fn lattice_aligned_grids_are_not_flat() {
        let settings = ProceduralNoise::default();
        for kind in [NoiseKind::Fbm, NoiseKind::Ridged] {
            let noise = ProceduralNoise { kind, ..settings };
            let grid = DensityGrid::procedural([8, 8, 8], DVec3::ONE, DVec3::ZERO, &noise).unwrap();
            let first = grid.values()[0];
            assert!(
                grid.values().iter().any(|&v| (v - first).abs() > 0.01),
                "{kind:?}"
            );
            let field =
                HeightField::procedural([8, 8], DVec2::ONE, DVec2::ZERO, &noise, 1.0).unwrap();
            let first = field.heights()[0];
            assert!(
                field.heights().iter().any(|&h| (h - first).abs() > 0.01),
                "{kind:?}"
            );
        }
    }

    #[test]
    fn invalid_settings_are_refused() {
        let bad = ProceduralNoise {
            octaves: 0,
            ..Default::default()
        };
        let message = error_message(DensityGrid::procedural(
            [2, 2, 2],
            DVec3::ONE,
            DVec3::ZERO,
            &bad,
        ));
        assert_mentions(&message, &["DensityGrid::procedural", "octaves"]);
        let bad = ProceduralNoise {
            frequency: f64::NAN,
            ..Default::default()
        };
        let message = error_message(HeightField::procedural(
            [2, 2],
            DVec2::ONE,
            DVec2::ZERO,
            &bad,
            1.0,
        ));
        assert_mentions(&message, &["frequency"]);
    }

    #[test]
    fn grids_beyond_the_memory_budget_are_refused_before_allocating() {
        let noise = ProceduralNoise::default();
        let message = error_message(DensityGrid::procedural(
            [4097; 3],
            DVec3::ONE,
            DVec3::ZERO,
            &noise,
        ));
        assert_mentions(
            &message,
            &[
                "DensityGrid::procedural: density grid of 4097 × 4097 × 4097 points",
                "needs 275,079,282,692 bytes (256.2 GiB)",
                "memory budget of 4,294,967,296 bytes (4 GiB)",
            ],
        );
        // A product that overflows usize is refused, not wrapped.
        let message = error_message(DensityGrid::procedural(
            [usize::MAX, usize::MAX, 2],
            DVec3::ONE,
            DVec3::ZERO,
            &noise,
        ));
        assert_mentions(&message, &["DensityGrid::procedural", "memory budget"]);
        let message = error_message(HeightField::procedural(
            [100_000, 100_000],
            DVec2::ONE,
            DVec2::ZERO,
            &noise,
            1.0,
        ));
        assert_mentions(
            &message,
            &[
                "HeightField::procedural: height field of 100000 × 100000 points",
                "needs 40,000,000,000 bytes",
            ],
        );
        // Too few points stays its own error.
        let message = error_message(DensityGrid::procedural(
            [1, 4097, 4097],
            DVec3::ONE,
            DVec3::ZERO,
            &noise,
        ));
        assert_mentions(&message, &["at least 2 samples"]);
    }
}
