//! Ground fog thickness maps without painting one: seeded noise patches, and
//! valleys filled up to an altitude with a noisy edge (the ground fog of
//! Röttger and Ertl 2003 §6 takes its thickness above the ground from such a
//! map).
//!
//! Both give one thickness in metres per terrain grid point (index `i + n·j`,
//! the terrain's own layout), finite and never negative.
//!
//! - [`FogNoise`]: `thickness · max(0, (u − (1 − coverage)) / coverage)` with
//!   `u` the unit [`TerrainNoise`] field ([`HeightField::terrain`]): patches
//!   of fog covering about `coverage` of the ground, thickest at the noise's
//!   peaks.
//! - [`ValleyFog`]: `max(0, altitude + edge · (2u − 1) − h)` with `h` the
//!   terrain's height: every point below the fog's top altitude is filled up
//!   to it, so the fog lies in the valleys with a flat top, and the unit noise
//!   `u` moves that top by up to `±edge` metres so the shore line is ragged.

use super::{FieldError, HeightField, TerrainNoise};

/// Patches of ground fog from noise: the thickness at a point is
/// `thickness · max(0, (u − (1 − coverage)) / coverage)` with `u` the unit
/// [`TerrainNoise`] field there ([`HeightField::terrain`]), so the fog
/// covers about `coverage` of the ground, thickest at the noise's peaks.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
pub struct FogNoise {
    /// The noise; its wavelength is the size of the patches. Default: 4
    /// octaves from 800 m.
    pub noise: TerrainNoise,
    /// Thickness at the noise's peaks, metres, finite and ≥ 0. Default 40.
    pub thickness: f32,
    /// Part of the ground the fog covers, in (0, 1]. Default 0.5.
    pub coverage: f32,
}

impl Default for FogNoise {
    fn default() -> Self {
        Self {
            noise: TerrainNoise {
                octaves: 4,
                wavelength: 800.0,
                ..TerrainNoise::default()
            },
            thickness: 40.0,
            coverage: 0.5,
        }
    }
}

/// Valleys filled with fog up to an altitude: the thickness over a ground
/// height `h` is `max(0, altitude + edge · (2u − 1) − h)`, `u` the unit
/// [`TerrainNoise`] field of `edge_noise` there, so the fog lies in the
/// valleys with a flat top that the noise moves by up to `±edge` metres (a
/// ragged shore).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
pub struct ValleyFog {
    /// Altitude of the fog's top, metres in the terrain's frame (heights
    /// included), finite. Default 60.
    pub altitude: f32,
    /// How far the noise moves the top up and down, metres, finite and ≥ 0.
    /// Default 8.
    pub edge: f32,
    /// The noise of the edge; its wavelength is the size of the shore's
    /// bays. Default: 3 octaves from 300 m, seed 7.
    pub edge_noise: TerrainNoise,
}

impl Default for ValleyFog {
    fn default() -> Self {
        Self {
            altitude: 60.0,
            edge: 8.0,
            edge_noise: TerrainNoise {
                seed: 7,
                octaves: 3,
                wavelength: 300.0,
                ..TerrainNoise::default()
            },
        }
    }
}

fn check(
    name: &str,
    parameter: &'static str,
    value: f32,
    valid: bool,
    requirement: &'static str,
) -> Result<(), FieldError> {
    if valid {
        Ok(())
    } else {
        Err(FieldError::InvalidParameter {
            name: name.to_owned(),
            parameter,
            value: value.to_string(),
            requirement,
        })
    }
}

impl FogNoise {
    /// The thickness at each point of a `side × side` terrain `spacing`
    /// metres apart. Errors name a setting out of range or the noise's own
    /// ([`HeightField::terrain`]).
    pub fn thickness(&self, side: usize, spacing: f64) -> Result<Vec<f32>, FieldError> {
        let name = "FogNoise";
        check(
            name,
            "thickness",
            self.thickness,
            self.thickness.is_finite() && self.thickness >= 0.0,
            "finite and ≥ 0",
        )?;
        check(
            name,
            "coverage",
            self.coverage,
            self.coverage > 0.0 && self.coverage <= 1.0,
            "in (0, 1]",
        )?;
        let unit = HeightField::terrain([side, side], spacing, &self.noise)?;
        let floor = 1.0 - self.coverage;
        Ok(unit
            .heights()
            .iter()
            .map(|u| self.thickness * ((u - floor).max(0.0) / self.coverage))
            .collect())
    }
}

impl ValleyFog {
    /// The thickness at each point of `heights` (absolute heights, metres;
    /// a square terrain field). Errors name a setting out of range or the
    /// noise's own ([`HeightField::terrain`]).
    pub fn thickness(&self, heights: &HeightField) -> Result<Vec<f32>, FieldError> {
        let name = "ValleyFog";
        check(
            name,
            "altitude",
            self.altitude,
            self.altitude.is_finite(),
            "finite",
        )?;
        check(
            name,
            "edge",
            self.edge,
            self.edge.is_finite() && self.edge >= 0.0,
            "finite and ≥ 0",
        )?;
        let spacing = heights.spacing().x;
        let edge = HeightField::terrain(heights.dims(), spacing, &self.edge_noise)?;
        Ok(heights
            .heights()
            .iter()
            .zip(edge.heights())
            .map(|(h, u)| (self.altitude + self.edge * (2.0 * u - 1.0) - h).max(0.0))
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec2;

    #[test]
    fn valleys_fill_to_the_altitude_within_the_edge() {
        let unit = HeightField::terrain([65, 65], 10.0, &TerrainNoise::default()).unwrap();
        let heights: Vec<f32> = unit.heights().iter().map(|u| 200.0 * u).collect();
        let field = HeightField::new([65, 65], DVec2::splat(10.0), DVec2::ZERO, heights).unwrap();
        let valley = ValleyFog {
            altitude: 80.0,
            edge: 5.0,
            ..ValleyFog::default()
        };
        let thickness = valley.thickness(&field).unwrap();
        let mut fogged = 0;
        for (t, h) in thickness.iter().zip(field.heights()) {
            assert!(t.is_finite() && *t >= 0.0);
            if *h < 75.0 {
                assert!(
                    *t > 0.0 && (t + h - 80.0).abs() <= 5.0 + 1e-3,
                    "{t} over {h}"
                );
            }
            if *h > 85.0 {
                assert_eq!(*t, 0.0);
            }
            fogged += usize::from(*t > 0.0);
        }
        assert!(fogged > 100 && fogged < 65 * 65 - 100, "{fogged}");
        // No edge: a flat top at the altitude exactly.
        let flat = ValleyFog {
            edge: 0.0,
            ..valley
        }
        .thickness(&field)
        .unwrap();
        for (t, h) in flat.iter().zip(field.heights()) {
            assert_eq!(*t, (80.0 - h).max(0.0));
        }
    }

    #[test]
    fn noise_patches_cover_about_the_coverage_and_peak_at_the_thickness() {
        let fog = FogNoise {
            coverage: 0.3,
            ..FogNoise::default()
        };
        let thickness = fog.thickness(129, 10.0).unwrap();
        let covered =
            thickness.iter().filter(|t| **t > 0.0).count() as f64 / thickness.len() as f64;
        let peak = thickness.iter().copied().fold(0.0, f32::max);
        assert!(covered > 0.02 && covered < 0.5, "{covered}");
        assert!((peak - 40.0).abs() < 1e-3, "{peak}");
        assert!(thickness.iter().all(|t| t.is_finite() && *t >= 0.0));
    }

    #[test]
    fn bad_settings_are_named() {
        for (fog, parameter) in [
            (
                FogNoise {
                    thickness: -1.0,
                    ..FogNoise::default()
                },
                "thickness",
            ),
            (
                FogNoise {
                    coverage: 0.0,
                    ..FogNoise::default()
                },
                "coverage",
            ),
            (
                FogNoise {
                    thickness: f32::NAN,
                    ..FogNoise::default()
                },
                "thickness",
            ),
        ] {
            let error = fog.thickness(9, 10.0).unwrap_err().to_string();
            assert!(error.contains(parameter), "{error}");
        }
        let field = HeightField::new([3, 3], DVec2::ONE, DVec2::ZERO, vec![0.0; 9]).unwrap();
        for (valley, parameter) in [
            (
                ValleyFog {
                    altitude: f32::INFINITY,
                    ..ValleyFog::default()
                },
                "altitude",
            ),
            (
                ValleyFog {
                    edge: -2.0,
                    ..ValleyFog::default()
                },
                "edge",
            ),
        ] {
            let error = valley.thickness(&field).unwrap_err().to_string();
            assert!(error.contains(parameter), "{error}");
        }
    }
}
