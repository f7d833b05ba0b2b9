//! Weather over a cloud: coverage and cloud type per column.
//!
//! A 2D map over the box's footprint, after the weather maps of Schneider's
//! Nubis (2015) and Unreal's volumetric clouds: at each column it gives a
//! coverage `w` in [0, 1], which scales [`CloudNoise::coverage`], and a cloud
//! type `t` in [0, 1] from stratus (0) to cumulus (1), which sets the column's
//! top `H = stratus_top + (1 − stratus_top) · t` as a fraction of the box's
//! height. The cloud's vertical profile is evaluated at `h / H`, so a stratus
//! column is a low flat deck and a cumulus column reaches the top.
//!
//! The map is either procedural ([`CloudWeather`], two octaves of Perlin noise
//! over the world's x and z drifting with the cloud's wind) or given as data
//! ([`WeatherMap`] in a [`CloudShape`](super::CloudShape), for example grayscale PNGs). It only lowers coverage and
//! tops, so the octave skipping of the cloud's rows stays exact.

use glam::{DVec2, DVec3};
use noise::{NoiseFn, Perlin};

use super::cloud::{CloudNoise, LOGISTIC_SLOPE, PERLIN_STD, equalised};
use super::{FieldError, HeightField, NOISE_OFFSET, Settings, smoothstep};

/// Half the width of the band of the type noise over which stratus turns
/// into cumulus.
const TYPE_BLEND: f64 = 0.1;

/// Procedural weather over a cloud ([`CloudNoise::weather`]): regions of
/// clear sky, scattered cloud and overcast, and of stratus and cumulus.
///
/// Two equalised noises `u_c`, `u_t` (two Perlin octaves each, seeds `seed`
/// and `seed + 2`, frequency `1 / wavelength`, nearly uniform on (0, 1)) are
/// sampled at the column's world `(x, z)`, drifting with the cloud's
/// [`CloudNoise::wind`]:
///
/// - coverage `w = clamp((u_c − clear) / (1 − clear − overcast), 0, 1)`
///   (a step at `clear` where `clear + overcast = 1`): about a fraction
///   `clear` of the sky has no cloud and a fraction `overcast` the full
///   coverage;
/// - type `t = smoothstep(stratus − 0.1, stratus + 0.1, u_t)`: about a
///   fraction `stratus` of the columns are stratus.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
pub struct CloudWeather {
    /// Size of the weather's regions, world units, ≥ 0; 0 (the default)
    /// turns the weather off: coverage and type are 1 everywhere.
    pub wavelength: f64,
    /// Seed of the weather's noise. Default 0.
    pub seed: u32,
    /// Fraction of the sky without cloud, in [0, 1]. Default 0.3.
    pub clear: f32,
    /// Fraction of the sky at the full coverage, in [0, 1], with `clear +
    /// overcast ≤ 1`. Default 0.2.
    pub overcast: f32,
    /// Fraction of the columns of stratus, in [0, 1]. Default 0.3.
    pub stratus: f32,
    /// Top of a stratus column, a fraction of the box's height in (0, 1].
    /// Default 0.35.
    pub stratus_top: f32,
}

impl Default for CloudWeather {
    fn default() -> Self {
        Self {
            wavelength: 0.0,
            seed: 0,
            clear: 0.3,
            overcast: 0.2,
            stratus: 0.3,
            stratus_top: 0.35,
        }
    }
}

impl CloudWeather {
    /// Whether the weather changes anything (a positive wavelength).
    pub fn is_on(&self) -> bool {
        self.wavelength > 0.0
    }

    /// Checks every setting, naming the offending one in errors of `name`.
    pub(super) fn check(&self, name: &str) -> Result<(), FieldError> {
        let settings = Settings(name);
        let wavelength = self.wavelength;
        let ok = wavelength.is_finite() && wavelength >= 0.0;
        settings.require(
            ok,
            "weather.wavelength",
            wavelength,
            "finite and at least 0",
        )?;
        settings.fractions(&[
            ("weather.clear", self.clear),
            ("weather.overcast", self.overcast),
            ("weather.stratus", self.stratus),
        ])?;
        let ok = self.clear + self.overcast <= 1.0;
        settings.require(ok, "weather.overcast", self.overcast, "at most 1 − clear")?;
        check_stratus_top(name, "weather.stratus_top", self.stratus_top)
    }
}

fn check_stratus_top(name: &str, parameter: &'static str, value: f32) -> Result<(), FieldError> {
    let ok = value > 0.0 && value <= 1.0;
    Settings(name).require(ok, parameter, value, "above 0 and at most 1")
}

/// A weather map given as data: coverage and, optionally, cloud type over
/// the cloud box's footprint, each a [`HeightField`] of values in [0, 1]
/// stretched over the box (its first point at the box's minimum x and z,
/// its last at the maximum; its spacing and origin are not read), bilinear
/// in between. Without a type map every column is cumulus (`t = 1`).
#[derive(Clone, PartialEq)]
pub struct WeatherMap {
    coverage: HeightField,
    kind: Option<HeightField>,
    stratus_top: f32,
    /// A hash of every value, so that `Debug` tells maps apart without
    /// printing them.
    fingerprint: u64,
}

/// The maps' sizes and a hash of their values, not the values.
impl std::fmt::Debug for WeatherMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WeatherMap")
            .field("coverage", &self.coverage.dims())
            .field("kind", &self.kind.as_ref().map(HeightField::dims))
            .field("stratus_top", &self.stratus_top)
            .field("fingerprint", &format_args!("{:016x}", self.fingerprint))
            .finish()
    }
}

impl WeatherMap {
    /// A weather map of `coverage` and `kind` (cloud type, black stratus,
    /// white cumulus) with stratus columns reaching `stratus_top` of the
    /// box's height.
    ///
    /// # Errors
    ///
    /// [`FieldError::InvalidParameter`] for a value outside [0, 1] in either
    /// map or a `stratus_top` outside (0, 1].
    pub fn new(
        coverage: HeightField,
        kind: Option<HeightField>,
        stratus_top: f32,
    ) -> Result<Self, FieldError> {
        let name = "WeatherMap::new";
        for (parameter, map) in [("coverage", Some(&coverage)), ("kind", kind.as_ref())] {
            let heights = map.map_or(&[][..], HeightField::heights);
            if let Some(&bad) = heights.iter().find(|v| !(0.0..=1.0).contains(*v)) {
                let requirement = "every value between 0 and 1";
                Settings(name).require(false, parameter, bad, requirement)?;
            }
        }
        check_stratus_top(name, "stratus_top", stratus_top)?;
        let mut hasher = std::hash::DefaultHasher::new();
        for map in [Some(&coverage), kind.as_ref()].into_iter().flatten() {
            std::hash::Hash::hash(&map.dims(), &mut hasher);
            for value in map.heights() {
                std::hash::Hash::hash(&value.to_bits(), &mut hasher);
            }
        }
        Ok(Self {
            coverage,
            kind,
            stratus_top,
            fingerprint: std::hash::Hasher::finish(&hasher),
        })
    }

    /// Coverage and type at the footprint fractions `fraction` (0 at the
    /// box's minimum x and z, 1 at its maximum).
    fn sample(&self, fraction: DVec2) -> (f64, f64) {
        let at = |map: &HeightField| {
            let [nx, nz] = map.dims();
            map.sample_grid(fraction * DVec2::new((nx - 1) as f64, (nz - 1) as f64))
        };
        (at(&self.coverage), self.kind.as_ref().map_or(1.0, at))
    }
}

/// One column's weather: the factor on the coverage and the top of its
/// vertical profile, as a fraction of the box's height.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Column {
    pub coverage: f64,
    pub top: f64,
}

impl Column {
    const CLEAR_SKY: Self = Self {
        coverage: 1.0,
        top: 1.0,
    };
}

/// Where a cloud's columns take their weather from.
pub(super) enum Weather<'a> {
    /// No weather: every column [`Column::CLEAR_SKY`]'s factors of 1.
    None,
    Procedural(Box<Procedural<'a>>),
    Map(&'a WeatherMap),
}

/// The procedural weather's noises at a time.
pub(super) struct Procedural<'a> {
    weather: &'a CloudWeather,
    coverage: [Perlin; 2],
    kind: [Perlin; 2],
    /// The first octave's drift at the time, subtracted from positions.
    drift: DVec3,
}

impl<'a> Weather<'a> {
    /// The weather of a cloud of `noise` at `time`, from `map` where given.
    ///
    /// # Errors
    ///
    /// [`FieldError::InvalidParameter`] for bad settings of
    /// [`CloudNoise::weather`], or for a map given to a cloud whose
    /// procedural weather is on (a cloud has one weather).
    pub fn new(
        name: &str,
        noise: &'a CloudNoise,
        map: Option<&'a WeatherMap>,
        time: f64,
    ) -> Result<Self, FieldError> {
        noise.weather.check(name)?;
        match map {
            Some(_) if noise.weather.is_on() => Err(FieldError::invalid_parameter(
                name,
                "weather.wavelength",
                noise.weather.wavelength.to_string(),
                "0 when a weather map is given (a cloud has one weather)",
            )),
            Some(map) => Ok(Self::Map(map)),
            None if noise.weather.is_on() => {
                let seed = noise.weather.seed;
                let perlins = |first: u32| {
                    [
                        Perlin::new(seed.wrapping_add(first)),
                        Perlin::new(seed.wrapping_add(first + 1)),
                    ]
                };
                Ok(Self::Procedural(Box::new(Procedural {
                    weather: &noise.weather,
                    coverage: perlins(0),
                    kind: perlins(2),
                    drift: noise.wind * time,
                })))
            }
            None => Ok(Self::None),
        }
    }

    /// The column at world `(x, z)` = `world`, at footprint fractions
    /// `fraction` of the box.
    pub fn column(&self, world: DVec2, fraction: DVec2) -> Column {
        match self {
            Self::None => Column::CLEAR_SKY,
            Self::Procedural(procedural) => {
                let Procedural {
                    weather,
                    coverage,
                    kind,
                    drift,
                } = procedural.as_ref();
                let p = (world - DVec2::new(drift.x, drift.z)) / weather.wavelength;
                let (u_c, u_t) = (unit_noise(coverage, p), unit_noise(kind, p));
                let (clear, overcast) = (f64::from(weather.clear), f64::from(weather.overcast));
                let span = 1.0 - clear - overcast;
                let w = if span > 0.0 {
                    ((u_c - clear) / span).clamp(0.0, 1.0)
                } else if u_c > clear {
                    1.0
                } else {
                    0.0
                };
                let stratus = f64::from(weather.stratus);
                let t = smoothstep(stratus - TYPE_BLEND, stratus + TYPE_BLEND, u_t);
                Column {
                    coverage: w,
                    top: column_top(weather.stratus_top, t),
                }
            }
            Self::Map(map) => {
                let (w, t) = map.sample(fraction);
                Column {
                    coverage: w,
                    top: column_top(map.stratus_top, t),
                }
            }
        }
    }
}

/// `H = stratus_top + (1 − stratus_top) · t`.
fn column_top(stratus_top: f32, t: f64) -> f64 {
    let s = f64::from(stratus_top);
    s + (1.0 - s) * t
}

/// Two octaves (frequencies 1 and 2, amplitudes 1 and 1/2) of `perlins` on
/// the plane at `p`, equalised as the cloud's octaves are: nearly uniform on
/// (0, 1).
fn unit_noise(perlins: &[Perlin; 2], p: DVec2) -> f64 {
    let [ox, oy, oz] = NOISE_OFFSET;
    let norm = (1.0f64 + 0.25).sqrt();
    let v: f64 = perlins
        .iter()
        .zip([1.0, 2.0])
        .map(|(perlin, f)| {
            perlin.get([p.x * f + ox, oy, p.y * f + oz]) * (1.0 / f) / (PERLIN_STD * norm)
        })
        .sum();
    equalised(LOGISTIC_SLOPE * v)
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::field::{CloudShape, DensityGrid};
    use crate::test_support::{assert_mentions, error_message};

    /// The procedural column `(w, H)` at world `(x, z)` and `time`, the
    /// formulas of [`CloudWeather`] written out with `noise::Perlin`.
    pub(in crate::field) fn pointwise_column(
        noise: &CloudNoise,
        time: f64,
        x: f64,
        z: f64,
    ) -> (f64, f64) {
        let weather = &noise.weather;
        let (px, pz) = (
            (x - noise.wind.x * time) / weather.wavelength,
            (z - noise.wind.z * time) / weather.wavelength,
        );
        let unit = |first: u32| {
            let v: f64 = [(0, 1.0), (1, 2.0)]
                .into_iter()
                .map(|(octave, f)| {
                    let perlin = Perlin::new(weather.seed.wrapping_add(first + octave));
                    let [ox, oy, oz] = NOISE_OFFSET;
                    perlin.get([px * f + ox, oy, pz * f + oz]) / f
                })
                .sum();
            1.0 / (1.0 + (-1.702 * v / (0.312 * 1.25f64.sqrt())).exp())
        };
        let (clear, overcast) = (f64::from(weather.clear), f64::from(weather.overcast));
        let w = ((unit(0) - clear) / (1.0 - clear - overcast)).clamp(0.0, 1.0);
        let stratus = f64::from(weather.stratus);
        let t = smoothstep(stratus - 0.1, stratus + 0.1, unit(2));
        let s = f64::from(weather.stratus_top);
        (w, s + (1.0 - s) * t)
    }

    fn weather(wavelength: f64) -> CloudNoise {
        CloudNoise {
            wavelength: 24.0,
            weather: CloudWeather {
                wavelength,
                seed: 5,
                ..CloudWeather::default()
            },
            ..CloudNoise::default()
        }
    }

    fn shape(map: WeatherMap) -> CloudShape {
        CloudShape {
            weather_map: Some(std::sync::Arc::new(map)),
            ..CloudShape::default()
        }
    }

    fn map(dims: [usize; 2], values: impl Fn(usize, usize) -> f32) -> HeightField {
        let heights = (0..dims[1])
            .flat_map(|j| (0..dims[0]).map(move |i| (i, j)))
            .map(|(i, j)| values(i, j))
            .collect();
        HeightField::new(dims, DVec2::ONE, DVec2::ZERO, heights).unwrap()
    }

    #[test]
    fn the_weather_clears_covers_and_types_the_stated_fractions() {
        for (clear, overcast, stratus) in [(0.3, 0.2, 0.3), (0.6, 0.1, 0.7), (0.1, 0.5, 0.5)] {
            let mut noise = weather(100.0);
            noise.weather.clear = clear;
            noise.weather.overcast = overcast;
            noise.weather.stratus = stratus;
            let columns = Weather::new("test", &noise, None, 0.0).unwrap();
            // 60 × 60 wavelengths of columns.
            let n = 600;
            let (mut clear_count, mut overcast_count, mut stratus_count) = (0, 0, 0);
            for i in 0..n {
                for k in 0..n {
                    let world = DVec2::new(i as f64, k as f64) * 10.0;
                    let column = columns.column(world, DVec2::ZERO);
                    clear_count += usize::from(column.coverage == 0.0);
                    overcast_count += usize::from(column.coverage == 1.0);
                    // Below the middle of the type band: mostly stratus.
                    let middle = column_top(noise.weather.stratus_top, 0.5);
                    stratus_count += usize::from(column.top < middle);
                }
            }
            let fraction = |count: usize| count as f64 / (n * n) as f64;
            for (what, measured, stated) in [
                ("clear", fraction(clear_count), clear),
                ("overcast", fraction(overcast_count), overcast),
                ("stratus", fraction(stratus_count), stratus),
            ] {
                assert!(
                    (measured - f64::from(stated)).abs() < 0.06,
                    "{what}: {measured} of the columns against {stated}"
                );
            }
        }
    }

    #[test]
    fn the_weather_drifts_with_the_wind() {
        let noise = CloudNoise {
            wind: DVec3::new(7.0, 2.0, -3.0),
            ..weather(80.0)
        };
        let (now, later) = (
            Weather::new("test", &noise, None, 0.0).unwrap(),
            Weather::new("test", &noise, None, 11.0).unwrap(),
        );
        for (x, z) in [(0.0, 0.0), (13.5, -40.0), (200.0, 77.0)] {
            let moved = DVec2::new(x + 77.0, z - 33.0);
            let (a, b) = (
                now.column(DVec2::new(x, z), DVec2::ZERO),
                later.column(moved, DVec2::ZERO),
            );
            assert!((a.coverage - b.coverage).abs() < 1e-9 && (a.top - b.top).abs() < 1e-9);
            let expected = pointwise_column(&noise, 11.0, moved.x, moved.y);
            assert!((b.coverage - expected.0).abs() < 1e-12 && (b.top - expected.1).abs() < 1e-12);
        }
    }

    #[test]
    fn a_maps_debug_tells_maps_apart_without_printing_them() {
        let ones = WeatherMap::new(map([64, 64], |_, _| 1.0), None, 0.35).unwrap();
        let one_less = WeatherMap::new(
            map([64, 64], |i, j| if (i, j) == (5, 7) { 0.5 } else { 1.0 }),
            None,
            0.35,
        )
        .unwrap();
        let (a, b) = (format!("{ones:?}"), format!("{one_less:?}"));
        assert_ne!(a, b);
        assert_eq!(a, format!("{:?}", ones.clone()));
        assert!(a.len() < 200, "{a}");
    }

    #[test]
    fn a_map_of_ones_is_no_weather() {
        let noise = weather(0.0);
        let (dims, spacing, origin) = ([17, 9, 13], DVec3::splat(2.0), DVec3::ZERO);
        let ones = WeatherMap::new(map([5, 4], |_, _| 1.0), None, 0.35).unwrap();
        let plain = DensityGrid::cloud(dims, spacing, origin, &noise, 0.0).unwrap();
        let under =
            DensityGrid::cloud_shaped(dims, spacing, origin, &noise, &shape(ones), 0.0).unwrap();
        assert_eq!(plain.values(), under.values());
        assert!(plain.values().iter().any(|&v| v > 0.0));
    }

    #[test]
    fn clear_columns_are_empty_and_stratus_columns_stay_low() {
        let noise = CloudNoise {
            coverage: 1.0,
            side_fade: 0.0,
            ..weather(0.0)
        };
        let (dims, spacing, origin) = ([21, 11, 9], DVec3::splat(2.0), DVec3::ZERO);
        let [nx, ny, nz] = dims;
        // Coverage 0 in the left half of the box, 1 in the right; stratus
        // (type 0) at the front, cumulus (1) at the back.
        let coverage = map([3, 2], |i, _| if i == 2 { 1.0 } else { 0.0 });
        let kind = map([2, 2], |_, j| j as f32);
        let under = WeatherMap::new(coverage, Some(kind), 0.4).unwrap();
        let grid =
            DensityGrid::cloud_shaped(dims, spacing, origin, &noise, &shape(under), 0.0).unwrap();
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let v = grid.value(i, j, k);
                    if i <= nx / 2 {
                        assert_eq!(v, 0.0, "clear column ({i}, {k}) at height {j}");
                    }
                    let h = j as f64 / (ny - 1) as f64;
                    let top = 0.4 + 0.6 * k as f64 / (nz - 1) as f64;
                    if h > top {
                        assert_eq!(v, 0.0, "above the column's top {top} at ({i}, {j}, {k})");
                    }
                }
            }
        }
        // The right half has cloud, and higher at the back than at the front.
        let highest = |k: usize| {
            (0..ny)
                .rev()
                .find(|&j| (nx / 2 + 1..nx).any(|i| grid.value(i, j, k) > 0.0))
        };
        assert!(highest(0).is_some_and(|front| highest(nz - 1).is_some_and(|back| back > front)));
    }

    #[test]
    fn bad_weather_is_refused_by_name() {
        let dims = [3, 3, 3];
        let cloud = |noise: &CloudNoise| {
            error_message(DensityGrid::cloud(
                dims,
                DVec3::ONE,
                DVec3::ZERO,
                noise,
                0.0,
            ))
        };
        let with = |change: fn(&mut CloudWeather)| {
            let mut noise = weather(10.0);
            change(&mut noise.weather);
            noise
        };
        for (noise, parameter) in [
            (with(|w| w.wavelength = -1.0), "weather.wavelength"),
            (with(|w| w.wavelength = f64::NAN), "weather.wavelength"),
            (with(|w| w.clear = 1.5), "weather.clear"),
            (with(|w| w.overcast = 0.8), "weather.overcast"),
            (with(|w| w.stratus = f32::NAN), "weather.stratus"),
            (with(|w| w.stratus_top = 0.0), "weather.stratus_top"),
        ] {
            assert_mentions(&cloud(&noise), &["DensityGrid::cloud", parameter]);
        }
        let half = map([2, 2], |_, _| 0.5);
        let message = error_message(WeatherMap::new(map([2, 2], |_, _| 1.2), None, 0.3));
        assert_mentions(&message, &["WeatherMap::new", "coverage", "1.2"]);
        let message = error_message(WeatherMap::new(
            half.clone(),
            Some(map([2, 2], |_, _| -0.1)),
            0.3,
        ));
        assert_mentions(&message, &["kind"]);
        let message = error_message(WeatherMap::new(half.clone(), None, 1.5));
        assert_mentions(&message, &["stratus_top"]);
        let both = WeatherMap::new(half, None, 0.3).unwrap();
        let message = error_message(DensityGrid::cloud_shaped(
            dims,
            DVec3::ONE,
            DVec3::ZERO,
            &weather(10.0),
            &shape(both),
            0.0,
        ));
        assert_mentions(&message, &["weather.wavelength", "one weather"]);
    }
}
