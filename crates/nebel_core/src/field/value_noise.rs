//! Height fields of hashed value noise in fractal sums: the terrain of the
//! libMini peer scenario (`nebel_lod`'s quadtree benchmark), shared by the terrain
//! benchmark and the quadtree's tests so both measure the same surface.
//!
//! Octave `o` (from 0) has wavelength `wavelength / 2^o`, amplitude `gain^o`
//! and its own lattice seed `seed + o`. Each octave is value noise: a hash of
//! the integer lattice point in [0, 1), interpolated with the cubic
//! smoothstep. Noise is sampled at each point's world position, so a field
//! is a pure function of its settings and geometry; the sum is rescaled to
//! exactly `0..relief` (a flat sum gives zeros).

use glam::DVec2;

use super::{
    FieldError, HeightField, SAMPLE_BYTES, Settings, budgeted_points, check_vertical_scale,
};

/// Settings of [`HeightField::value_noise`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ValueNoise {
    /// Seed of the first octave; octave `o` uses `seed + o`. Default 1.
    pub seed: u64,
    /// Number of octaves, 1 to 32. Default 8.
    pub octaves: u32,
    /// Wavelength of the first octave, world units, finite and > 0. Default
    /// 5120.
    pub wavelength: f64,
    /// Amplitude ratio between octaves, finite and > 0. Default 0.5.
    pub gain: f64,
}

impl Default for ValueNoise {
    fn default() -> Self {
        Self {
            seed: 1,
            octaves: 8,
            wavelength: 5120.0,
            gain: 0.5,
        }
    }
}

/// Hash of a lattice point and seed to [0, 1).
fn lattice(x: i64, z: i64, seed: u64) -> f64 {
    let mut h = (x as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)
        ^ (z as u64).wrapping_mul(0xc2b2_ae3d_27d4_eb4f)
        ^ seed.wrapping_mul(0x1656_67b1_9e37_79f9);
    h ^= h >> 29;
    h = h.wrapping_mul(0xbf58_476d_1ce4_e5b9);
    h ^= h >> 32;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Value noise at `(x, z)` lattice units with smoothstep interpolation, in
/// [0, 1).
fn value_noise(x: f64, z: f64, seed: u64) -> f64 {
    let (x0, z0) = (x.floor(), z.floor());
    let (fx, fz) = (x - x0, z - z0);
    let (sx, sz) = (fx * fx * (3.0 - 2.0 * fx), fz * fz * (3.0 - 2.0 * fz));
    let (i, j) = (x0 as i64, z0 as i64);
    let a = lattice(i, j, seed) + (lattice(i + 1, j, seed) - lattice(i, j, seed)) * sx;
    let b = lattice(i, j + 1, seed) + (lattice(i + 1, j + 1, seed) - lattice(i, j + 1, seed)) * sx;
    a + (b - a) * sz
}

impl HeightField {
    /// A height field of `dims` points (geometry as in [`HeightField::new`])
    /// of value-noise fBm (module docs), rescaled to `0..relief` world units.
    ///
    /// Errors: [`FieldError::InvalidParameter`] naming `octaves`,
    /// `wavelength`, `gain` or `vertical_scale` (the relief, finite),
    /// [`FieldError::OverBudget`] when the f64 sums and f32 heights (12 bytes
    /// per point) exceed the memory budget, before anything is allocated,
    /// and the errors of [`HeightField::new`] for the geometry.
    pub fn value_noise(
        dims: [usize; 2],
        spacing: DVec2,
        origin: DVec2,
        noise: &ValueNoise,
        relief: f64,
    ) -> Result<Self, FieldError> {
        let name = "HeightField::value_noise";
        let settings = Settings(name);
        let ok = (1..=32).contains(&noise.octaves);
        settings.require(ok, "octaves", noise.octaves, "between 1 and 32")?;
        settings.positive(&[("wavelength", noise.wavelength), ("gain", noise.gain)])?;
        check_vertical_scale(name, relief)?;
        // The f64 sums and the f32 heights are held together.
        let len = budgeted_points(
            name,
            "value-noise height field",
            &dims,
            size_of::<f64>() as u64 + SAMPLE_BYTES,
        )?;
        let [nx, nz] = dims;
        let mut sums = Vec::with_capacity(len);
        for j in 0..nz {
            for i in 0..nx {
                let p = origin + DVec2::new(i as f64, j as f64) * spacing;
                let mut sum = 0.0;
                for octave in 0..noise.octaves {
                    let wavelength = noise.wavelength / f64::from(octave).exp2();
                    sum += noise.gain.powi(octave as i32)
                        * value_noise(
                            p.x / wavelength,
                            p.y / wavelength,
                            noise.seed.wrapping_add(u64::from(octave)),
                        );
                }
                sums.push(sum);
            }
        }
        let low = sums.iter().copied().fold(f64::INFINITY, f64::min);
        let high = sums.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let span = high - low;
        let heights = sums
            .iter()
            .map(|v| {
                if span > 0.0 {
                    ((v - low) / span * relief) as f32
                } else {
                    0.0
                }
            })
            .collect();
        Self::validated(name, dims, spacing, origin, heights)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{assert_mentions, error_message};

    #[test]
    fn spans_the_relief_is_deterministic_and_follows_the_world_position() {
        let noise = ValueNoise {
            octaves: 4,
            wavelength: 160.0,
            ..ValueNoise::default()
        };
        let field =
            HeightField::value_noise([33, 17], DVec2::splat(10.0), DVec2::ZERO, &noise, 1000.0)
                .unwrap();
        let (low, high) = field
            .heights()
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        assert_eq!((low, high), (0.0, 1000.0));
        let again =
            HeightField::value_noise([33, 17], DVec2::splat(10.0), DVec2::ZERO, &noise, 1000.0)
                .unwrap();
        assert_eq!(field, again);
        // One octave, no rescaling difference: a shifted origin samples the
        // same noise at the same world points.
        let single = ValueNoise {
            octaves: 1,
            ..noise
        };
        let whole = HeightField::value_noise([9, 9], DVec2::splat(10.0), DVec2::ZERO, &single, 1.0)
            .unwrap();
        let raw = |i: usize, j: usize| value_noise(i as f64 / 16.0, j as f64 / 16.0, 1);
        let (lo, hi) = (0..81)
            .map(|p| raw(p % 9, p / 9))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
                (l.min(v), h.max(v))
            });
        for (p, &h) in whole.heights().iter().enumerate() {
            let expected = (raw(p % 9, p / 9) - lo) / (hi - lo);
            assert!((f64::from(h) - expected).abs() < 1e-6);
        }
    }

    #[test]
    fn bad_settings_are_refused_by_name() {
        let geometry = ([5, 5], DVec2::ONE, DVec2::ZERO);
        for (noise, relief, parameter) in [
            (
                ValueNoise {
                    octaves: 0,
                    ..ValueNoise::default()
                },
                1.0,
                "octaves",
            ),
            (
                ValueNoise {
                    wavelength: f64::NAN,
                    ..ValueNoise::default()
                },
                1.0,
                "wavelength",
            ),
            (
                ValueNoise {
                    gain: 0.0,
                    ..ValueNoise::default()
                },
                1.0,
                "gain",
            ),
            (ValueNoise::default(), f64::INFINITY, "vertical_scale"),
        ] {
            let message = error_message(HeightField::value_noise(
                geometry.0, geometry.1, geometry.2, &noise, relief,
            ));
            assert_mentions(&message, &["HeightField::value_noise", parameter]);
        }
    }

    #[test]
    fn the_budget_counts_the_sums_with_the_heights() {
        // 4 · 10⁸ points: 1.6 GB of heights alone, 4.8 GB with the f64 sums.
        let message = error_message(HeightField::value_noise(
            [20_000, 20_000],
            DVec2::ONE,
            DVec2::ZERO,
            &ValueNoise::default(),
            1.0,
        ));
        assert_mentions(
            &message,
            &[
                "HeightField::value_noise",
                "value-noise height field of 20000 × 20000 points needs 4,800,000,000 bytes",
            ],
        );
    }
}
