//! Procedural cumulus cloud density with artist controls.
//!
//! The cumulus density `f` of Röttger and Ertl 2003 §5 and §7, generated after
//! Schpok et al. 2003. [`DensityGrid::cloud`] evaluates, at each grid point's
//! world position `p` and time `t`, with the settings of [`CloudNoise`]:
//!
//! 1. **Octaves** (Schpok et al. 2003 §3.2, §4.1 Eq. 3, §5.2): `octaves`
//!    [`noise::Perlin`] fields of frequency `lacunarity^i / (wavelength ·
//!    stretch)` per axis and amplitude `persistence^i`, each drifting with
//!    its own wind (§5.3): sampled at `φ_i · (p − wind · t · detail_wind^i)`
//!    plus [`NOISE_OFFSET`](super::NOISE_OFFSET), and under `torque` turned
//!    at its own speed about the box's centre drifting with it; with `wisps`
//!    each adds the ridged `E|P| − |P|` instead (the wispy filter;
//!    [`CloudKind`]).
//! 2. **Equalised fBm**: `v = Σ a_i P_i / (σ_P √(Σ a_i²))` (`σ_P` the standard
//!    deviation of 3D Perlin noise) has about unit variance, and the logistic
//!    approximation of the normal distribution, `u = 1 / (1 + exp(−1.702 v))`,
//!    makes `u` nearly uniform on (0, 1).
//! 3. **Coverage remap** (Schpok et al. 2003 Table 2, noise as a density
//!    cut-off): `d = clamp((u − (1 − c)) / (c · (1 − sharpness)), 0, 1)`, so
//!    about a fraction `c` of space is cloud, its density rising from 0 at
//!    the edge (faster for a higher `sharpness`, the alpha cut-off).
//! 4. **Vertical profile** (altitude tiers):
//!    `b(h) = smoothstep(0, base_fade, h)` fades every column in at one
//!    altitude (flat bases) and the coverage shrinks toward the top
//!    (`top_fade`: rounded tops).
//! 5. **Side fade**: the coverage shrinks to 0 toward the box's four vertical
//!    sides over `side_fade` of its width and depth, so no cloud is cut flat
//!    by the box: clouds thin out and end inside it.
//! 6. **Weather** ([`super::weather`]): a column's coverage `w` scales the
//!    coverage and its cloud type sets its top `H`, so the profile is
//!    evaluated at `h / H` (none above the top).
//! 7. **Shape** ([`super::primitives`], Schpok et al. 2003 §3.1): implicit
//!    ellipsoids blended by Wyvill's field `P` scale the coverage, so the
//!    noise subtracts detail at their surfaces.
//!
//! So `f = b(h) · clamp((u − (1 − c)) / (c · (1 − sharpness)), 0, 1)` with
//! `c = c(h / H) · s(x) · s(z) · w · P`, in [0, 1], a pure function of the settings, time and
//! geometry: the same on every run, machine and thread count.
//!
//! Rows of grid points are evaluated octave by octave by `PerlinRow`, in the
//! CPU's vector instructions, and finer octaves skip the points that can no
//! longer reach the coverage threshold; the result equals the pointwise
//! `noise::Perlin` sum to a unit in the last place of the f32 density (a test);
//! a turned octave's rows are lines in any direction, evaluated point by point.
//!
//! Every formula, the skipping bound and the evaluation in full are in
//! `docs/cloud-field.md` in the repository.

use glam::{DMat3, DVec2, DVec3};

use super::perlin_row::{PerlinRow, RowLattice};
use super::primitives::{CloudShape, Primitives};
use super::weather::{CloudWeather, Column, Weather};
use super::{
    DENSITY_GRID, DensityGrid, FieldError, NOISE_OFFSET, SAMPLE_BYTES, Settings, budgeted_points,
    check_origin, check_spacing, smoothstep,
};
use crate::pacing::{fill_slices, pace, worker_threads};

/// Standard deviation of 3D `noise::Perlin` output (measured over 2·10⁶
/// random points for three seeds: 0.311–0.313).
pub(super) const PERLIN_STD: f64 = 0.312;

/// Mean and standard deviation of `|P|` for 3D `noise::Perlin` (measured over
/// 2·10⁶ random points for three seeds: 0.254–0.257 and 0.180–0.181), which
/// equalise the octaves of [`CloudNoise::wisps`].
const PERLIN_ABS_MEAN: f64 = 0.255;
const PERLIN_ABS_STD: f64 = 0.180;

/// Slope of the logistic approximation `1 / (1 + e^{−1.702 v})` of the normal
/// distribution function.
pub(super) const LOGISTIC_SLOPE: f64 = 1.702;

/// Most octaves [`CloudNoise::octaves`] accepts.
const MAX_OCTAVES: usize = 16;

/// Settings of the procedural cumulus density of [`DensityGrid::cloud`]
/// (Schpok et al. 2003's artist controls).
///
/// At world position `p`, time `t` and height fraction `h = j / (ny − 1)` of
/// the grid box (grid axis y is up):
///
/// - octave `i` (from 0): Perlin noise `P_i` with seed `seed + i`, frequency
///   `φ_i = lacunarity^i / (wavelength · stretch)` (per axis), amplitude
///   `a_i = persistence^i`, sampled at `φ_i · (c_i + R_i^{−1} (p − c_i) −
///   d_i)` with the drift `d_i = wind · t · detail_wind^i` (per-octave wind),
///   `c_i = c + d_i` the box's centre `c` drifted with it and `R_i` the turn
///   about the axis of `torque` by `|torque| · t · detail_wind^i`
///   (right-handed; per-octave torque, the identity without): the octave's
///   pattern drifts with its wind and turns about its drifting centre;
/// - `v = Σ a_i P_i / (0.312 √(Σ a_i²))` (unit variance) and
///   `u = 1 / (1 + e^{−1.702 v})` (nearly uniform on (0, 1));
/// - `c(h) = coverage · (1 − smoothstep(1 − top_fade, 1, h))`,
///   `b(h) = smoothstep(0, base_fade, h)` (a fade of 0 disables it);
/// - `s(x) = smoothstep(0, side_fade, min(x, 1 − x))` of the width fraction
///   `x = i / (nx − 1)`, and `s(z)` of the depth fraction alike (a fade of 0
///   disables it);
/// - the column's weather coverage `w` and top `H` ([`CloudWeather`], or a
///   [`WeatherMap`](super::WeatherMap) in a [`CloudShape`] through
///   [`DensityGrid::cloud_shaped`]; 1 and 1 without);
/// - the shape `P` of the [`CloudShape`]'s ellipsoids (1 without);
/// - density `f = b(h) · clamp((u − (1 − c)) / (c · (1 − sharpness)), 0, 1)`
///   with `c = c(h / H) · s(x) · s(z) · w · P` (`c(h / H) = 0` above the
///   top), 0 where `c = 0`.
///
/// About a fraction `coverage` of the points away from the base, the top and
/// the sides is cloud.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
pub struct CloudNoise {
    /// Seed; octave `i` uses `seed + i` (wrapping). Equal seeds give equal
    /// fields. Default 0.
    pub seed: u32,
    /// Fraction of space (and so of the sky) covered by cloud, in [0, 1]:
    /// 0 is empty, 1 fills the box. Default 0.5.
    pub coverage: f32,
    /// Number of detail octaves, 1 to 16. Default 5.
    pub octaves: usize,
    /// Wavelength of the first octave, world units, > 0: the size of the
    /// clouds (Schpok et al. 2003 §5.2 "cloud size"). Default 2000.
    pub wavelength: f64,
    /// Frequency ratio between successive octaves, > 0 (Schpok et al. 2003 §5.2
    /// "detail"). Default 2.
    pub lacunarity: f64,
    /// Amplitude ratio between successive octaves, > 0. Default 0.5.
    pub persistence: f64,
    /// Drift of the first octave, world units per second (in the grid's
    /// frame), finite. Default zero.
    pub wind: DVec3,
    /// Factor by which each octave drifts faster than the previous one, > 0:
    /// octave `i` moves with `wind · detail_wind^i` (Schpok et al. 2003 §4.1 eq. 3,
    /// §5.3). Above 1 the fine detail streams past the cloud; below 1 it lags
    /// behind. Default 1.5.
    pub detail_wind: f64,
    /// Fractal rotation of the noise (Schpok et al. 2003 §5.3 "torque"):
    /// axis times the angular speed of the first octave, radians per second
    /// (in the grid's frame), finite. Octave `i` turns `detail_wind^i` times
    /// as fast about the axis through the box's centre, so the detail swirls
    /// against the cloud's large shapes. Default zero (no turn; a turned
    /// octave is sampled point by point, several times slower than along
    /// the noise's rows).
    pub torque: DVec3,
    /// Height fraction of the box, in [0, 1], over which the density fades in
    /// from the bottom (flat cloud bases). Default 0.15.
    pub base_fade: f32,
    /// Height fraction of the box, in [0, 1], over which the coverage
    /// threshold rises to 1 at the top (rounded tops). Default 0.5.
    pub top_fade: f32,
    /// Fraction of the box's width and depth, in [0, 0.5], over which the
    /// coverage falls to 0 toward each of its vertical sides (no cloud cut
    /// flat by the box). Default 0.1.
    pub side_fade: f32,
    /// Wisps (Schpok et al. 2003's wispy filter): each octave adds `E|P| −
    /// |P|` (ridged turbulence, equalised by `|P|`'s mean and deviation)
    /// instead of `P`, so the cloud gathers along the noise's zero sheets in
    /// thin, torn filaments. Default false.
    pub wisps: bool,
    /// Elongation of the clouds' features along the box's x, y and z axes,
    /// each finite and > 0 (the wavelength is multiplied by it per axis): 1
    /// keeps them round (cumulus); wider than tall flattens them (stratus);
    /// long along one axis draws streaks (cirrus; turn the volume to aim
    /// them). Default 1 on every axis. See [`CloudKind`].
    pub stretch: DVec3,
    /// Procedural weather over the box: regions of clear sky and overcast,
    /// of stratus and cumulus ([`CloudWeather`]). Default off.
    pub weather: CloudWeather,
    /// How sharply a cloud's density rises from its edge (Schpok et al.
    /// 2003's alpha cut-off), in [0, 1): the remap divides by `c · (1 −
    /// sharpness)`, so at 0 the density rises over the whole noise range
    /// above the threshold and toward 1 it jumps to full at the edge. The
    /// clouds' extent does not change. Default 0.
    pub sharpness: f32,
}

impl Default for CloudNoise {
    fn default() -> Self {
        Self {
            seed: 0,
            coverage: 0.5,
            octaves: 5,
            wavelength: 2000.0,
            lacunarity: 2.0,
            persistence: 0.5,
            wind: DVec3::ZERO,
            detail_wind: 1.5,
            torque: DVec3::ZERO,
            base_fade: 0.15,
            top_fade: 0.5,
            side_fade: 0.1,
            weather: CloudWeather::default(),
            sharpness: 0.0,
            stretch: DVec3::ONE,
            wisps: false,
        }
    }
}

/// A kind of cloud: the filter of Schpok et al. 2003's noise (Table 2) as
/// starting settings for [`CloudNoise::of_kind`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum CloudKind {
    /// Heaped clouds with flat bases and rounded tops: round features, the
    /// noise cut off at the coverage ([`CloudNoise::default`]).
    #[default]
    Cumulus,
    /// A layer: features four times wider than tall, a dense, sharper deck
    /// over most of the sky, a short fade at the base and top.
    Stratus,
    /// High streaks: features ten times longer along x than tall (6.7 times
    /// longer than wide), thin and soft, little coverage, more fine detail.
    Cirrus,
    /// Thin, torn filaments along the noise's zero sheets
    /// ([`CloudNoise::wisps`]), wider than tall.
    Wispy,
}

impl CloudNoise {
    /// Whether the noise changes with time: a wind or a torque.
    pub fn animates(&self) -> bool {
        self.wind != DVec3::ZERO || self.torque != DVec3::ZERO
    }

    /// The starting settings of a kind of cloud (every other setting as
    /// [`CloudNoise::default`]):
    ///
    /// | kind | `stretch` | `coverage` | `sharpness` | `base_fade`, `top_fade` | `persistence` |
    /// |---|---|---|---|---|---|
    /// | cumulus | (1, 1, 1) | 0.5 | 0 | 0.15, 0.5 | 0.5 |
    /// | stratus | (4, 1, 4) | 0.8 | 0.4 | 0.3, 0.3 | 0.5 |
    /// | cirrus | (10, 0.5, 1.5) | 0.3 | 0 | 0.3, 0.3 | 0.65 |
    /// | wispy (with `wisps`) | (2, 1, 2) | 0.35 | 0 | 0.3, 0.3 | 0.55 |
    pub fn of_kind(kind: CloudKind) -> Self {
        let cumulus = Self::default();
        match kind {
            CloudKind::Cumulus => cumulus,
            CloudKind::Stratus => Self {
                stretch: DVec3::new(4.0, 1.0, 4.0),
                coverage: 0.8,
                sharpness: 0.4,
                base_fade: 0.3,
                top_fade: 0.3,
                ..cumulus
            },
            CloudKind::Cirrus => Self {
                stretch: DVec3::new(10.0, 0.5, 1.5),
                coverage: 0.3,
                base_fade: 0.3,
                top_fade: 0.3,
                persistence: 0.65,
                ..cumulus
            },
            CloudKind::Wispy => Self {
                wisps: true,
                stretch: DVec3::new(2.0, 1.0, 2.0),
                coverage: 0.35,
                base_fade: 0.3,
                top_fade: 0.3,
                persistence: 0.55,
                ..cumulus
            },
        }
    }
}

/// One Perlin octave, ready to sample: `amplitude · P(position · frequency + offset)`.
struct Octave {
    perlin: PerlinRow,
    /// Cycles per world unit along each axis.
    frequency: DVec3,
    /// Noise-space shift: wind drift and [`NOISE_OFFSET`].
    offset: DVec3,
    /// `LOGISTIC_SLOPE · a_i / (σ √(Σ a²))`, `σ` the standard deviation of
    /// `P` (or of `|P|` for wisps).
    amplitude: f64,
    /// Wisps: the octave adds `shift − |amplitude · P|`, `shift` the mean of
    /// `|amplitude · P|`; `None` adds `amplitude · P`.
    ridge: Option<f64>,
    /// Under torque, the inverse turn `R⁻¹` and the centre `c` it turns
    /// about (drifted with the octave): the octave samples `frequency · (c +
    /// R⁻¹ (p − c)) + offset`.
    turn: Option<(DMat3, DVec3)>,
}

impl Octave {
    /// The noise-space line of the row at height `y` and depth `z` of a
    /// turned octave: the point at `x` along the row is `base + x ·
    /// direction`.
    fn line(&self, (rotation, centre): (DMat3, DVec3), y: f64, z: f64) -> (DVec3, DVec3) {
        let start = centre + rotation * (DVec3::new(0.0, y, z) - centre);
        (
            self.frequency * start + self.offset,
            self.frequency * rotation.x_axis,
        )
    }

    /// The most the octave can add to a point's sum.
    fn most(&self) -> f64 {
        self.ridge.unwrap_or(self.amplitude)
    }
}

/// The vertical profile of [`CloudNoise`]: the base factor `b(h)` and the
/// coverage `c(h)` at a height fraction of the column.
#[derive(Clone, Copy)]
struct Profile {
    coverage: f64,
    base_fade: f64,
    top_fade: f64,
}

impl Profile {
    fn new(noise: &CloudNoise) -> Self {
        Self {
            coverage: f64::from(noise.coverage),
            base_fade: f64::from(noise.base_fade),
            top_fade: f64::from(noise.top_fade),
        }
    }

    /// `b(h)` at the height fraction `h` of the box.
    fn base(self, h: f64) -> f64 {
        if self.base_fade > 0.0 {
            smoothstep(0.0, self.base_fade, h)
        } else {
            1.0
        }
    }

    /// `c(h')` at the height fraction `h'` of the column's top: 0 above it.
    fn coverage(self, h: f64) -> f64 {
        let top = if h > 1.0 {
            0.0
        } else if self.top_fade > 0.0 {
            1.0 - smoothstep(1.0 - self.top_fade, 1.0, h)
        } else {
            1.0
        };
        self.coverage * top
    }
}

/// A bound below which the equalised noise `v` gives density 0 at every
/// coverage up to `coverage`: `u = 1 / (1 + e^{−v})` stays below the
/// threshold `1 − c` for every `v` under `ln((1 − c) / c)`, here less a
/// margin far above the rounding of `u` (`du/dv ≤ 1/4`). −∞ when `c ≥ 1`
/// (every point may be cloud).
fn zero_below(coverage: f64) -> f64 {
    if coverage >= 1.0 {
        f64::NEG_INFINITY
    } else {
        ((1.0 - coverage) / coverage).ln() - 1e-9
    }
}

/// Density from the equalised unit noise `u` at base factor `base`,
/// coverage `coverage` and softness `1 − sharpness`.
fn density(base: f64, coverage: f64, softness: f64, u: f64) -> f32 {
    if base <= 0.0 || coverage <= 0.0 {
        return 0.0;
    }
    let d = base * ((u - (1.0 - coverage)) / (coverage * softness)).clamp(0.0, 1.0);
    if d.is_nan() { 0.0 } else { d as f32 }
}

/// The side fade `s` at each of `n` points across a box, corner to corner:
/// `smoothstep(0, side_fade, min(x, 1 − x))` of the fraction `x = i / (n −
/// 1)`, 1 everywhere for a fade of 0 (the cloud's [`CloudNoise::side_fade`],
/// and a cloud layer's edges).
pub fn side_fade_factors(side_fade: f32, n: usize) -> Vec<f64> {
    let fade = f64::from(side_fade);
    (0..n)
        .map(|i| {
            if fade <= 0.0 {
                return 1.0;
            }
            let x = i as f64 / (n - 1) as f64;
            smoothstep(0.0, fade, x.min(1.0 - x))
        })
        .collect()
}

impl CloudNoise {
    /// Validates every setting and `time`, and builds the octaves.
    /// `centre` is the box's, the pivot of the torque.
    fn octaves(&self, name: &str, time: f64, centre: DVec3) -> Result<Vec<Octave>, FieldError> {
        let settings = Settings(name);
        settings.fractions(&[
            ("coverage", self.coverage),
            ("base_fade", self.base_fade),
            ("top_fade", self.top_fade),
        ])?;
        let sharpness = self.sharpness;
        let below_one = (0.0..1.0).contains(&sharpness);
        settings.require(below_one, "sharpness", sharpness, "at least 0 and below 1")?;
        let side_fade = self.side_fade;
        let ok = (0.0..=0.5).contains(&side_fade);
        settings.require(ok, "side_fade", side_fade, "between 0 and 0.5")?;
        let ok = (1..=MAX_OCTAVES).contains(&self.octaves);
        settings.require(ok, "octaves", self.octaves, "between 1 and 16")?;
        settings.positive(&[
            ("wavelength", self.wavelength),
            ("lacunarity", self.lacunarity),
            ("persistence", self.persistence),
            ("detail_wind", self.detail_wind),
        ])?;
        let stretch = self.stretch;
        let ok = stretch.is_finite() && stretch.min_element() > 0.0;
        settings.require(ok, "stretch", stretch, "finite and positive on every axis")?;
        let wind = self.wind;
        settings.require(wind.is_finite(), "wind", wind, "finite on every axis")?;
        let torque = self.torque;
        settings.require(torque.is_finite(), "torque", torque, "finite on every axis")?;
        settings.require(time.is_finite(), "time", time, "finite")?;
        let amplitudes: Vec<f64> = (0..self.octaves)
            .map(|i| self.persistence.powi(i as i32))
            .collect();
        let norm = amplitudes.iter().map(|a| a * a).sum::<f64>().sqrt();
        settings.require(
            norm.is_finite() && amplitudes.iter().all(|a| a.is_finite()),
            "persistence",
            self.persistence,
            "persistence^(octaves − 1) squared must stay finite",
        )?;
        let mut octaves = Vec::with_capacity(self.octaves);
        for (i, amplitude) in amplitudes.into_iter().enumerate() {
            let frequency = self.lacunarity.powi(i as i32) / self.wavelength / self.stretch;
            settings.require(
                frequency.is_finite() && frequency.min_element() > 0.0,
                "lacunarity",
                self.lacunarity,
                "lacunarity^(octaves − 1) / (wavelength · stretch) must stay finite and positive",
            )?;
            let drift = self.wind * (time * self.detail_wind.powi(i as i32));
            let offset = DVec3::from(NOISE_OFFSET) - drift * frequency;
            settings.require(
                offset.is_finite(),
                "time",
                time,
                "wind · time · detail_wind^(octaves − 1) / wavelength must stay finite",
            )?;
            let angle = torque.length() * time * self.detail_wind.powi(i as i32);
            settings.require(
                angle.is_finite(),
                "torque",
                torque,
                "|torque| · time · detail_wind^(octaves − 1) must stay finite",
            )?;
            // The pattern turns by the angle, so its points are sampled
            // turned back, about the centre drifted with the octave.
            let turn = torque
                .try_normalize()
                .filter(|_| angle != 0.0)
                .map(|axis| (DMat3::from_axis_angle(axis, -angle), centre + drift));
            let (std, ridge) = if self.wisps {
                (PERLIN_ABS_STD, Some(PERLIN_ABS_MEAN))
            } else {
                (PERLIN_STD, None)
            };
            let amplitude = LOGISTIC_SLOPE * amplitude / (std * norm);
            octaves.push(Octave {
                perlin: PerlinRow::new(self.seed.wrapping_add(i as u32)),
                frequency,
                offset,
                amplitude,
                ridge: ridge.map(|mean| amplitude * mean),
                turn,
            });
        }
        Ok(octaves)
    }
}

/// Equalised unit noise `u` in (0, 1) from the sum `v` of the octaves
/// (each already times [`LOGISTIC_SLOPE`]).
pub(super) fn equalised(v: f64) -> f64 {
    1.0 / (1.0 + (-v).exp())
}

/// The densities of one grid row at height `y`, depth `z` (world units)
/// into `row`, octave after octave along the row ([`PerlinRow`]).
///
/// A point whose partial sum plus the largest the remaining octaves can add
/// (`Σ a_j` as `|P| ≤ 1`, the sum of the shifts for wisps) stays below [`zero_below`] of the row's largest coverage is density 0
/// whatever they add: the remaining octaves skip the lattice cells of the
/// row where every point is so (exact: the density is the same as with
/// every octave).
struct RowFiller<'a> {
    octaves: &'a [Octave],
    /// The row's x, world units.
    xs: &'a [f64],
    /// Per octave, how its rows are sampled.
    rows: Vec<OctaveRows>,
    /// Per octave, the most the octaves after it can add.
    remaining: Vec<f64>,
    sums: Vec<f64>,
    live: Vec<bool>,
    /// `1 − sharpness`.
    softness: f64,
}

impl<'a> RowFiller<'a> {
    fn new(octaves: &'a [Octave], xs: &'a [f64], softness: f64) -> Self {
        let rows = octaves
            .iter()
            .map(|o| match o.turn {
                None => OctaveRows::Lattice(RowLattice::new(
                    xs.iter().map(|&x| x * o.frequency.x + o.offset.x).collect(),
                )),
                Some(turn) => OctaveRows::Turned(turn),
            })
            .collect();
        let remaining = (0..octaves.len())
            .map(|i| octaves[i + 1..].iter().map(Octave::most).sum())
            .collect();
        Self {
            octaves,
            xs,
            rows,
            remaining,
            sums: vec![0.0; xs.len()],
            live: vec![true; xs.len()],
            softness,
        }
    }

    /// The densities of the row `at` into `row`, through [`FillRow`].
    fn fill(&mut self, at: RowAt, row: &mut [f32]) {
        pulp::Arch::new().dispatch(FillRow {
            filler: self,
            at,
            row,
        });
    }

    #[inline(always)]
    fn fill_row(&mut self, at: RowAt, row: &mut [f32]) {
        let RowAt {
            base,
            coverage,
            largest,
            y,
            z,
        } = at;
        // The row's largest coverage: a point of less needs more noise.
        let zero_below = zero_below(largest);
        self.sums.fill(0.0);
        self.live.fill(true);
        for ((octave, rows), remaining) in
            self.octaves.iter().zip(&mut self.rows).zip(&self.remaining)
        {
            let live = &self.live;
            let (sums, amplitude) = (&mut self.sums, octave.amplitude);
            let perlin = &octave.perlin;
            match (rows, octave.ridge) {
                (OctaveRows::Lattice(lattice), ridge) => {
                    let (y, z) = (
                        y * octave.frequency.y + octave.offset.y,
                        z * octave.frequency.z + octave.offset.z,
                    );
                    match ridge {
                        None => perlin.add_row(lattice, y, z, amplitude, sums, |i| live[i], |n| n),
                        Some(shift) => perlin.add_row(
                            lattice,
                            y,
                            z,
                            amplitude,
                            sums,
                            |i| live[i],
                            move |n: f64| shift - n.abs(),
                        ),
                    }
                }
                (OctaveRows::Turned(turn), ridge) => {
                    let line = octave.line(*turn, y, z);
                    let xs = self.xs;
                    match ridge {
                        None => perlin.add_line(line, xs, amplitude, sums, |i| live[i], |n| n),
                        Some(shift) => perlin.add_line(
                            line,
                            xs,
                            amplitude,
                            sums,
                            |i| live[i],
                            move |n: f64| shift - n.abs(),
                        ),
                    }
                }
            }
            for (live, sum) in self.live.iter_mut().zip(&self.sums) {
                *live &= sum + remaining >= zero_below;
            }
        }
        for (i, ((value, &sum), &live)) in
            row.iter_mut().zip(&self.sums).zip(&self.live).enumerate()
        {
            *value = if live {
                density(base, coverage.at(i), self.softness, equalised(sum))
            } else {
                0.0
            };
        }
    }
}

/// How a [`RowFiller`] samples an octave's rows.
enum OctaveRows {
    /// Along the noise's x axis: the row's x in noise space, `x · φ_i +
    /// offset_i.x`, in its lattice cells, with the cells' corner hashes.
    Lattice(RowLattice),
    /// Along a turned line ([`Octave::turn`]).
    Turned((DMat3, DVec3)),
}

/// [`RowFiller::fill`] of one row, compiled for the vector instructions the
/// CPU has (`pulp`'s runtime dispatch: AVX2 and FMA where there are, SSE2
/// otherwise). The loops are the same IEEE operations in the same order on
/// every instruction set (Rust never fuses a multiply and an add), so the
/// density is too.
struct FillRow<'f, 'a, 'r> {
    filler: &'f mut RowFiller<'a>,
    at: RowAt<'r>,
    row: &'r mut [f32],
}

/// Where a row lies and what scales its noise: its height `y` and depth `z`
/// (world units), the base factor and each point's coverage, the largest of
/// which is at most `largest`.
#[derive(Clone, Copy)]
struct RowAt<'r> {
    base: f64,
    coverage: Coverage<'r>,
    largest: f64,
    y: f64,
    z: f64,
}

/// The coverage of each point of a row.
#[derive(Clone, Copy)]
enum Coverage<'r> {
    /// The row's coverage times each point's side factor.
    Sides { scalar: f64, sides: &'r [f64] },
    /// Each point's own.
    Points(&'r [f64]),
}

impl Coverage<'_> {
    fn at(self, i: usize) -> f64 {
        match self {
            Self::Sides { scalar, sides } => scalar * sides[i],
            Self::Points(coverages) => coverages[i],
        }
    }
}

impl pulp::WithSimd for FillRow<'_, '_, '_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        self.filler.fill_row(self.at, self.row);
    }
}

impl DensityGrid {
    /// A procedural cumulus density grid of `dims` points (geometry as in
    /// [`DensityGrid::new`]; grid axis y is up) at `time` seconds, from the
    /// artist controls `noise` (formulas at [`CloudNoise`]). Uses every
    /// available core, or only the calling thread when it is paced
    /// ([`crate::pacing`], a yield point after every z-slice); the result
    /// does not depend on the number of threads.
    ///
    /// # Errors
    ///
    /// [`FieldError::InvalidParameter`] naming the offending setting (or
    /// `spacing`, `origin`, `time`), [`FieldError::TooSmall`] for an axis with
    /// fewer than 2 points, [`FieldError::OverBudget`] when the grid (4 bytes
    /// per point) exceeds the memory budget, before anything is allocated.
    pub fn cloud(
        dims: [usize; 3],
        spacing: DVec3,
        origin: DVec3,
        noise: &CloudNoise,
        time: f64,
    ) -> Result<Self, FieldError> {
        Self::cloud_shaped(dims, spacing, origin, noise, &CloudShape::default(), time)
    }

    /// [`DensityGrid::cloud`] shaped by `shape`: a weather map over the box
    /// instead of the procedural [`CloudNoise::weather`] (which must then be
    /// off), and implicit ellipsoids whose blended field scales the coverage
    /// ([`CloudShape`]).
    ///
    /// # Errors
    ///
    /// As [`DensityGrid::cloud`]; [`FieldError::InvalidParameter`] naming
    /// `weather.wavelength` when a weather map is given with the procedural
    /// weather on, or an ellipsoid's bad setting.
    pub fn cloud_shaped(
        dims: [usize; 3],
        spacing: DVec3,
        origin: DVec3,
        noise: &CloudNoise,
        shape: &CloudShape,
        time: f64,
    ) -> Result<Self, FieldError> {
        Self::cloud_with_threads(dims, spacing, origin, noise, shape, time, worker_threads())
    }

    /// [`DensityGrid::cloud_shaped`] on `threads` threads (0 or 1: on the
    /// calling thread), each taking a contiguous run of z-slices.
    ///
    /// # Errors
    ///
    /// As [`DensityGrid::cloud_shaped`].
    pub fn cloud_with_threads(
        dims: [usize; 3],
        spacing: DVec3,
        origin: DVec3,
        noise: &CloudNoise,
        shape: &CloudShape,
        time: f64,
        threads: usize,
    ) -> Result<Self, FieldError> {
        let name = "DensityGrid::cloud";
        let points = budgeted_points(name, DENSITY_GRID, &dims, SAMPLE_BYTES)?;
        check_spacing(name, &spacing.to_array())?;
        check_origin(name, &origin.to_array())?;
        let centre = origin + spacing * (DVec3::from(dims.map(|n| n as f64)) - 1.0) / 2.0;
        let octaves = noise.octaves(name, time, centre)?;
        let weather = Weather::new(name, noise, shape.weather_map.as_deref(), time)?;
        let primitives = Primitives::new(name, shape, time)?;
        let profile = Profile::new(noise);
        let [nx, ny, nz] = dims;
        let fraction = |n: usize, i: usize| i as f64 / (n - 1) as f64;
        let xs: Vec<f64> = (0..nx).map(|i| origin.x + i as f64 * spacing.x).collect();
        let (sides_x, sides_z) = (
            side_fade_factors(noise.side_fade, nx),
            side_fade_factors(noise.side_fade, nz),
        );
        let widest = sides_x.iter().copied().fold(0.0, f64::max);
        // Without weather or shape every point's coverage is its row's times
        // its side factors.
        let plain = matches!(weather, Weather::None) && primitives.is_none();
        let mut values = vec![0.0f32; points];
        let fill = |first_slice: usize, chunk: &mut [f32]| {
            let softness = 1.0 - f64::from(noise.sharpness);
            let mut filler = RowFiller::new(&octaves, &xs, softness);
            let mut coverages = vec![0.0; nx];
            let mut shaped = vec![1.0; nx];
            for (dk, slice) in chunk.chunks_mut(nx * ny).enumerate() {
                let k = first_slice + dk;
                let z = origin.z + k as f64 * spacing.z;
                let columns: Vec<Column> = if plain {
                    Vec::new()
                } else {
                    xs.iter()
                        .enumerate()
                        .map(|(i, &x)| {
                            let at = DVec2::new(fraction(nx, i), fraction(nz, k));
                            weather.column(DVec2::new(x, z), at)
                        })
                        .collect()
                };
                // Without cloud types every column has the row's profile.
                let full_tops = columns.iter().all(|column| column.top == 1.0);
                for (j, row) in slice.chunks_mut(nx).enumerate() {
                    let h = fraction(ny, j);
                    let base = profile.base(h);
                    let row_coverage = profile.coverage(h);
                    if base <= 0.0 || (full_tops && row_coverage <= 0.0) {
                        continue;
                    }
                    let y = origin.y + j as f64 * spacing.y;
                    if let Some(primitives) = &primitives
                        && !primitives.fill_row(&xs, y, z, &mut shaped)
                    {
                        continue;
                    }
                    // Without weather or shape a point's coverage is the
                    // row's times its side factor, found for live points only.
                    let (coverage, largest) = if plain {
                        let scalar = row_coverage * sides_z[k];
                        (
                            Coverage::Sides {
                                scalar,
                                sides: &sides_x,
                            },
                            scalar * widest,
                        )
                    } else {
                        let mut largest = 0.0f64;
                        for (((coverage, column), side), shaped) in coverages
                            .iter_mut()
                            .zip(&columns)
                            .zip(&sides_x)
                            .zip(&shaped)
                        {
                            let profiled = if full_tops {
                                row_coverage
                            } else {
                                profile.coverage(h / column.top)
                            };
                            *coverage = profiled * sides_z[k] * side * column.coverage * shaped;
                            largest = largest.max(*coverage);
                        }
                        (Coverage::Points(&coverages), largest)
                    };
                    if largest > 0.0 {
                        let at = RowAt {
                            base,
                            coverage,
                            largest,
                            y,
                            z,
                        };
                        filler.fill(at, row);
                    }
                }
                pace();
            }
        };
        fill_slices(&mut values, nx * ny, threads, fill);
        Self::validated(name, dims, spacing, origin, values)
    }
}

#[cfg(test)]
mod tests {
    use noise::{NoiseFn, Perlin};

    use super::*;
    use crate::field::CloudEllipsoid;
    use crate::field::primitives::tests::pointwise_shape;
    use crate::field::weather::tests::pointwise_column;
    use crate::test_support::{assert_mentions, error_message};

    /// Small clouds on a small grid: wavelength 24 world units over a 40-unit box.
    fn small() -> CloudNoise {
        CloudNoise {
            seed: 11,
            wavelength: 24.0,
            ..Default::default()
        }
    }

    const DIMS: [usize; 3] = [21, 11, 17];
    const SPACING: DVec3 = DVec3::new(2.0, 1.5, 2.5);
    const ORIGIN: DVec3 = DVec3::new(-10.0, 300.0, 7.0);

    fn grid(noise: &CloudNoise, time: f64) -> DensityGrid {
        DensityGrid::cloud(DIMS, SPACING, ORIGIN, noise, time).unwrap()
    }

    fn non_zero_fraction(values: &[f32]) -> f64 {
        values.iter().filter(|&&v| v > 0.0).count() as f64 / values.len() as f64
    }

    #[test]
    fn clouds_are_deterministic_and_independent_of_threads() {
        let noise = CloudNoise {
            wind: DVec3::new(3.0, 0.5, -2.0),
            ..small()
        };
        let a = grid(&noise, 4.0);
        assert_eq!(a, grid(&noise, 4.0));
        for threads in [0, 1, 3, 40] {
            let b = DensityGrid::cloud_with_threads(
                DIMS,
                SPACING,
                ORIGIN,
                &noise,
                &CloudShape::default(),
                4.0,
                threads,
            )
            .unwrap();
            assert_eq!(a, b, "{threads} threads");
        }
        assert_ne!(a, grid(&CloudNoise { seed: 12, ..noise }, 4.0));
        assert_ne!(a, grid(&noise, 5.0), "the wind moves the clouds");
        assert!(a.values().iter().all(|v| (0.0..=1.0).contains(v)));
        let max = a.values().iter().copied().fold(0.0f32, f32::max);
        assert!(max > 0.3, "some dense cloud: {max}");
    }

    /// The density at one point as the formulas at [`CloudNoise`] state it,
    /// each octave by `noise::Perlin`'s pointwise `get`: at `p`, height
    /// fraction `h`, side factor `side` (the product of the two axes') and in
    /// a column of weather coverage `w` and top `H` (`column = (w, H)`).
    fn pointwise_in_weather(
        noise: &CloudNoise,
        time: f64,
        p: DVec3,
        h: f64,
        side: f64,
        (w, top): (f64, f64),
    ) -> f32 {
        let centre = ORIGIN + SPACING * (DVec3::from(DIMS.map(|n| n as f64)) - 1.0) / 2.0;
        let octaves = noise.octaves("test", time, centre).unwrap();
        let v: f64 = octaves
            .iter()
            .enumerate()
            .map(|(i, o)| {
                let perlin = Perlin::new(noise.seed.wrapping_add(i as u32));
                // The turn written out from the settings: the pattern turns
                // by |torque| t detail_wind^i about the axis of `torque`
                // through the box's centre drifted with the octave, so the
                // point is sampled turned back.
                let speed = time * noise.detail_wind.powi(i as i32);
                let angle = noise.torque.length() * speed;
                let turned = if noise.torque == DVec3::ZERO {
                    p
                } else {
                    let back = glam::DQuat::from_axis_angle(noise.torque.normalize(), -angle);
                    let pivot = centre + noise.wind * speed;
                    pivot + back * (p - pivot)
                };
                let n = o.amplitude * perlin.get((turned * o.frequency + o.offset).to_array());
                if noise.wisps {
                    o.amplitude * 0.255 - n.abs()
                } else {
                    n
                }
            })
            .sum();
        let profile = Profile::new(noise);
        density(
            profile.base(h),
            profile.coverage(h / top) * side * w,
            1.0 - f64::from(noise.sharpness),
            equalised(v),
        )
    }

    /// The side factor at index `i` of `n` points, written out.
    fn side(side_fade: f32, i: usize, n: usize) -> f64 {
        let x = i as f64 / (n - 1) as f64;
        let distance = x.min(1.0 - x) / f64::from(side_fade);
        if side_fade == 0.0 || distance >= 1.0 {
            1.0
        } else {
            distance * distance * (3.0 - 2.0 * distance)
        }
    }

    #[test]
    fn rows_and_skipped_octaves_equal_the_pointwise_formula() {
        // Coverages from sparse (most points skip the fine octaves) to full
        // (none may), several octave counts, lacunarities, winds and side
        // fades, without and with procedural weather (region size 30) and
        // ellipsoids.
        let ellipsoids = CloudShape {
            primitives: vec![
                CloudEllipsoid {
                    centre: DVec3::new(2.0, 307.0, 25.0),
                    radii: DVec3::new(14.0, 6.0, 9.0),
                    rotation: glam::DQuat::from_rotation_y(0.6),
                    velocity: DVec3::new(1.0, 0.5, 0.0),
                    growth: 0.05,
                    ..CloudEllipsoid::default()
                },
                CloudEllipsoid {
                    centre: DVec3::new(20.0, 310.0, 40.0),
                    radii: DVec3::splat(8.0),
                    density: 0.6,
                    ..CloudEllipsoid::default()
                },
            ],
            ..CloudShape::default()
        };
        let no_turn = DVec3::ZERO;
        let turn = DVec3::new(0.05, 0.4, -0.2);
        for (coverage, octaves, lacunarity, time, side_fade, weather, shaped, wisps, torque) in [
            (0.1, 5, 2.0, 0.0, 0.1, 0.0, false, false, no_turn),
            (0.42, 5, 2.0, 3.5, 0.3, 0.0, false, false, no_turn),
            (0.5, 8, 2.3, -7.0, 0.0, 0.0, false, false, no_turn),
            (0.9, 3, 1.7, 1.0, 0.5, 0.0, false, false, no_turn),
            (1.0, 5, 2.0, 2.0, 0.2, 0.0, false, false, no_turn),
            (0.6, 5, 2.0, 2.0, 0.1, 30.0, false, false, no_turn),
            (1.0, 4, 2.0, -3.0, 0.0, 30.0, false, false, no_turn),
            (1.0, 5, 2.0, 2.0, 0.0, 0.0, true, false, no_turn),
            (0.7, 4, 2.0, 1.0, 0.1, 0.0, true, false, no_turn),
            (0.3, 5, 2.0, 1.0, 0.1, 0.0, false, true, no_turn),
            (0.8, 3, 2.0, -2.0, 0.0, 0.0, true, true, no_turn),
            (0.42, 5, 2.0, 0.0, 0.1, 0.0, false, false, turn),
            (0.5, 6, 2.0, 2.5, 0.1, 0.0, false, false, turn),
            (0.3, 5, 2.0, -4.0, 0.1, 0.0, false, true, turn),
            (1.0, 4, 2.0, 1.0, 0.1, 0.0, true, false, turn),
            (0.6, 5, 2.0, 2.0, 0.1, 30.0, false, false, turn),
        ] {
            let noise = CloudNoise {
                coverage,
                octaves,
                lacunarity,
                wind: DVec3::new(3.0, 0.5, -2.0),
                side_fade,
                weather: CloudWeather {
                    wavelength: weather,
                    clear: 0.2,
                    ..CloudWeather::default()
                },
                wisps,
                torque,
                ..small()
            };
            let shape = if shaped {
                ellipsoids.clone()
            } else {
                CloudShape::default()
            };
            let grid =
                DensityGrid::cloud_shaped(DIMS, SPACING, ORIGIN, &noise, &shape, time).unwrap();
            let [nx, ny, nz] = DIMS;
            let mut zeros = 0;
            for k in 0..nz {
                for j in 0..ny {
                    for i in 0..nx {
                        let p = ORIGIN + DVec3::new(i as f64, j as f64, k as f64) * SPACING;
                        let h = j as f64 / (ny - 1) as f64;
                        let sides = side(side_fade, k, nz)
                            * side(side_fade, i, nx)
                            * pointwise_shape(&shape, time, p);
                        let column = if weather > 0.0 {
                            pointwise_column(&noise, time, p.x, p.z)
                        } else {
                            (1.0, 1.0)
                        };
                        let expected = pointwise_in_weather(&noise, time, p, h, sides, column);
                        // The rows agree with `noise` to rounding: at most
                        // a unit in the last place of the f32 density.
                        assert!(
                            (grid.value(i, j, k) - expected).abs() <= 1e-6,
                            "coverage {coverage}, point ({i}, {j}, {k}): {} against {expected}",
                            grid.value(i, j, k)
                        );
                        zeros += usize::from(expected == 0.0);
                    }
                }
            }
            assert!(zeros < nx * ny * nz, "coverage {coverage}: some cloud");
        }
    }

    #[test]
    fn a_torque_turns_the_cloud_about_its_centre() {
        // Every octave turns as fast (detail_wind 1): at 2 s a quarter turn
        // about +y, right-handed, so the point of index (i, k) at time 0 lies
        // at (c + (k − c), c − (i − c)) = (k, 2c − i) (x̂ turns to −ẑ) on a
        // square grid.
        let noise = CloudNoise {
            octaves: 3,
            detail_wind: 1.0,
            torque: DVec3::new(0.0, std::f64::consts::FRAC_PI_4, 0.0),
            coverage: 0.6,
            ..small()
        };
        let (dims, spacing) = ([17, 5, 17], DVec3::new(2.0, 1.5, 2.0));
        let at = |time| DensityGrid::cloud(dims, spacing, ORIGIN, &noise, time).unwrap();
        let (before, after) = (at(0.0), at(2.0));
        let c = 8;
        let mut cloud = 0;
        for k in 0..17 {
            for j in 0..5 {
                for i in 0..17 {
                    let (turned_i, turned_k) = (k, 2 * c - i);
                    let (was, is) = (before.value(i, j, k), after.value(turned_i, j, turned_k));
                    assert!((was - is).abs() <= 1e-5, "({i}, {j}, {k}): {was} {is}");
                    cloud += usize::from(was > 0.0);
                }
            }
        }
        assert!(cloud > 100, "{cloud} points of cloud");
        assert_ne!(before, after, "the cloud turned");
    }

    #[test]
    fn sharper_clouds_keep_their_extent_and_rise_to_full_density_sooner() {
        let soft = CloudNoise {
            coverage: 0.6,
            ..small()
        };
        let sharp = CloudNoise {
            sharpness: 0.75,
            ..soft
        };
        let (soft_grid, sharp_grid) = (grid(&soft, 1.0), grid(&sharp, 1.0));
        let mut cloud = 0;
        for (&d, &d_sharp) in soft_grid.values().iter().zip(sharp_grid.values()) {
            // The same points are cloud; where the soft density is d, the
            // sharp one is min(4 d, b(h)) up to rounding.
            assert_eq!(d > 0.0, d_sharp > 0.0);
            assert!(
                d_sharp >= d && d_sharp <= (4.0 * d).min(1.0) + 1e-6,
                "{d} {d_sharp}"
            );
            cloud += usize::from(d > 0.0);
        }
        assert!(cloud > 100);
        let message = error_message(DensityGrid::cloud(
            DIMS,
            SPACING,
            ORIGIN,
            &CloudNoise {
                sharpness: 1.0,
                ..soft
            },
            0.0,
        ));
        assert_mentions(&message, &["DensityGrid::cloud", "sharpness"]);
    }

    #[test]
    fn a_stretched_cloud_is_the_round_one_scaled() {
        // Stretched by (4, 1, 0.5), the field at p is the round field at
        // p / stretch: a grid 4 times wider along x and half as deep along z
        // holds the same values.
        let stretch = DVec3::new(4.0, 1.0, 0.5);
        let round = CloudNoise {
            wind: DVec3::new(2.0, 0.0, 1.0),
            ..small()
        };
        let stretched = CloudNoise { stretch, ..round };
        let time = 1.5;
        let a = DensityGrid::cloud(DIMS, SPACING * stretch, ORIGIN * stretch, &stretched, time)
            .unwrap();
        // The wind drifts the round field by wind · t; the stretched one by
        // the same distance in stretched space, so it is the round field of
        // the wind / stretch.
        let round = CloudNoise {
            wind: round.wind / stretch,
            ..round
        };
        let b = DensityGrid::cloud(DIMS, SPACING, ORIGIN, &round, time).unwrap();
        let cloud = a.values().iter().filter(|&&v| v > 0.0).count();
        assert!(cloud > 100, "{cloud}");
        for (x, y) in a.values().iter().zip(b.values()) {
            assert!((x - y).abs() <= 1e-6, "{x} against {y}");
        }
    }

    #[test]
    fn cloud_kinds_start_from_their_filters() {
        assert_eq!(
            CloudNoise::of_kind(CloudKind::Cumulus),
            CloudNoise::default()
        );
        let dims = [33, 9, 33];
        let spacing = DVec3::new(4.0, 2.0, 4.0);
        for kind in [CloudKind::Stratus, CloudKind::Cirrus, CloudKind::Wispy] {
            let noise = CloudNoise {
                wavelength: 40.0,
                ..CloudNoise::of_kind(kind)
            };
            let grid = DensityGrid::cloud(dims, spacing, DVec3::ZERO, &noise, 0.0).unwrap();
            let covered = non_zero_fraction(grid.values());
            assert!(covered > 0.02, "{kind:?}: {covered}");
        }
        let stratus = CloudNoise::of_kind(CloudKind::Stratus);
        let cirrus = CloudNoise::of_kind(CloudKind::Cirrus);
        assert!(stratus.stretch.x > stratus.stretch.y && cirrus.stretch.x > cirrus.stretch.z);
        assert!(stratus.coverage > cirrus.coverage);
        let message = error_message(DensityGrid::cloud(
            DIMS,
            SPACING,
            ORIGIN,
            &CloudNoise {
                stretch: DVec3::new(1.0, 0.0, 1.0),
                ..small()
            },
            0.0,
        ));
        assert_mentions(&message, &["DensityGrid::cloud", "stretch"]);
    }

    #[test]
    fn the_sides_fade_to_no_cloud() {
        // Full coverage: without a side fade every point is cloud.
        let dims = [33, 9, 25];
        let noise = |side_fade| CloudNoise {
            coverage: 1.0,
            base_fade: 0.0,
            top_fade: 0.0,
            side_fade,
            ..small()
        };
        let field = |side_fade| {
            DensityGrid::cloud(dims, DVec3::ONE, DVec3::ZERO, &noise(side_fade), 0.0).unwrap()
        };
        let (plain, faded) = (field(0.0), field(0.25));
        let [nx, ny, nz] = dims;
        let margin = |i: usize, n: usize| i.min(n - 1 - i) as f64 / (n - 1) as f64 >= 0.25;
        let mut thinned = 0;
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let (p, f) = (plain.value(i, j, k), faded.value(i, j, k));
                    // Less coverage never adds density.
                    assert!(f <= p, "({i}, {j}, {k}): {f} above {p}");
                    if i == 0 || i == nx - 1 || k == 0 || k == nz - 1 {
                        assert_eq!(f, 0.0, "({i}, {j}, {k}) on a side");
                    } else if margin(i, nx) && margin(k, nz) {
                        assert_eq!(f, p, "({i}, {j}, {k}) inside the margin");
                    } else {
                        thinned += usize::from(f < p);
                    }
                }
            }
        }
        assert!(thinned > 0);
        assert!(plain.values().iter().all(|&v| v > 0.0));
        // Outside [0, 0.5] it is refused.
        for side_fade in [-0.1, 0.6, f32::NAN] {
            let error = DensityGrid::cloud(dims, DVec3::ONE, DVec3::ZERO, &noise(side_fade), 0.0);
            assert_mentions(&error_message(error), &["side_fade"]);
        }
    }

    #[test]
    fn coverage_sets_the_covered_fraction() {
        // No vertical profile or side fade, so every layer has the full
        // coverage.
        let flat = CloudNoise {
            base_fade: 0.0,
            top_fade: 0.0,
            side_fade: 0.0,
            wavelength: 12.0,
            ..small()
        };
        let dims = [41, 17, 41];
        for wisps in [false, true] {
            let fraction = |coverage: f32| {
                let noise = CloudNoise {
                    coverage,
                    wisps,
                    ..flat
                };
                let grid = DensityGrid::cloud(dims, DVec3::ONE, DVec3::ZERO, &noise, 0.0).unwrap();
                non_zero_fraction(grid.values())
            };
            assert_eq!(fraction(0.0), 0.0);
            assert!(fraction(1.0) > 0.999, "{}", fraction(1.0));
            for coverage in [0.25, 0.5, 0.75] {
                let covered = fraction(coverage);
                assert!(
                    (covered - f64::from(coverage)).abs() < 0.12,
                    "wisps {wisps}, coverage {coverage}: {covered} of the points are cloud"
                );
            }
        }
        // Empty with the default profile too.
        let empty = grid(
            &CloudNoise {
                coverage: 0.0,
                ..small()
            },
            0.0,
        );
        assert!(empty.values().iter().all(|&v| v == 0.0));
    }

    #[test]
    fn one_octave_drifts_with_the_wind() {
        let wind = DVec3::new(7.5, -1.25, 3.0);
        let time = 2.6;
        for (base_fade, top_fade, wind) in [
            // No profile: the wind may have a vertical component.
            (0.0, 0.0, wind),
            // The profile is tied to the box, so only horizontal wind.
            (0.15, 0.5, wind * DVec3::new(1.0, 0.0, 1.0)),
        ] {
            let noise = CloudNoise {
                octaves: 1,
                coverage: 0.8,
                wind,
                base_fade,
                top_fade,
                ..small()
            };
            let moved = grid(&noise, time);
            let shifted =
                DensityGrid::cloud(DIMS, SPACING, ORIGIN - wind * time, &noise, 0.0).unwrap();
            let largest = moved
                .values()
                .iter()
                .zip(shifted.values())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(largest < 1e-5, "{largest}");
            assert!(non_zero_fraction(moved.values()) > 0.2);
            assert_ne!(moved, grid(&noise, 0.0));
        }
    }

    #[test]
    fn finer_octaves_drift_faster() {
        // With several octaves a pure shift of the grid no longer reproduces the
        // moved field: the detail has moved further than the base.
        let noise = CloudNoise {
            wind: DVec3::new(5.0, 0.0, 0.0),
            coverage: 0.8,
            ..small()
        };
        let moved = grid(&noise, 2.0);
        let shifted =
            DensityGrid::cloud(DIMS, SPACING, ORIGIN - noise.wind * 2.0, &noise, 0.0).unwrap();
        let largest = moved
            .values()
            .iter()
            .zip(shifted.values())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(largest > 0.01, "{largest}");
        // detail_wind = 1: everything moves together again.
        let rigid = CloudNoise {
            detail_wind: 1.0,
            ..noise
        };
        let moved = grid(&rigid, 2.0);
        let shifted =
            DensityGrid::cloud(DIMS, SPACING, ORIGIN - rigid.wind * 2.0, &rigid, 0.0).unwrap();
        let largest = moved
            .values()
            .iter()
            .zip(shifted.values())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(largest < 1e-5, "{largest}");
    }

    #[test]
    fn vertical_profile_fades_the_base_and_rounds_the_top() {
        // The vertical profile alone: no side fade.
        let noise = CloudNoise {
            coverage: 1.0,
            side_fade: 0.0,
            ..small()
        };
        let grid = grid(&noise, 0.0);
        let [nx, ny, nz] = DIMS;
        let layer_mean = |j: usize| {
            let mut sum = 0.0;
            for k in 0..nz {
                for i in 0..nx {
                    sum += f64::from(grid.value(i, j, k));
                }
            }
            sum / (nx * nz) as f64
        };
        let cover = |j: usize| {
            let mut count = 0;
            for k in 0..nz {
                for i in 0..nx {
                    count += usize::from(grid.value(i, j, k) > 0.0);
                }
            }
            count as f64 / (nx * nz) as f64
        };
        assert_eq!(layer_mean(0), 0.0, "bottom layer");
        assert_eq!(layer_mean(ny - 1), 0.0, "top layer");
        // Fades in over the lowest 15 % (h = 0.1 lies inside the fade) ...
        assert!(layer_mean(1) < layer_mean(3));
        // ... and the covered fraction shrinks toward the top.
        assert!(cover(3) > 0.99);
        assert!(
            cover(9) < cover(7) && cover(7) < cover(5),
            "{:?}",
            [cover(5), cover(7), cover(9)]
        );
    }

    #[test]
    fn bad_settings_are_refused_by_name() {
        let check = |noise: CloudNoise, time: f64, parameter: &str| {
            let message = error_message(DensityGrid::cloud(
                [3, 3, 3],
                DVec3::ONE,
                DVec3::ZERO,
                &noise,
                time,
            ));
            assert_mentions(&message, &["DensityGrid::cloud", parameter]);
        };
        let ok = CloudNoise::default();
        check(
            CloudNoise {
                coverage: 1.5,
                ..ok
            },
            0.0,
            "coverage",
        );
        check(
            CloudNoise {
                coverage: f32::NAN,
                ..ok
            },
            0.0,
            "coverage",
        );
        check(CloudNoise { octaves: 0, ..ok }, 0.0, "octaves");
        let torque = |torque| CloudNoise { torque, ..ok };
        check(torque(DVec3::new(0.0, f64::NAN, 0.0)), 0.0, "torque");
        check(torque(DVec3::new(0.0, 1e300, 0.0)), 1e300, "torque");
        check(CloudNoise { octaves: 17, ..ok }, 0.0, "octaves");
        check(
            CloudNoise {
                wavelength: 0.0,
                ..ok
            },
            0.0,
            "wavelength",
        );
        check(
            CloudNoise {
                lacunarity: f64::INFINITY,
                ..ok
            },
            0.0,
            "lacunarity",
        );
        check(
            CloudNoise {
                lacunarity: 1e300,
                ..ok
            },
            0.0,
            "lacunarity",
        );
        check(
            CloudNoise {
                persistence: -0.5,
                ..ok
            },
            0.0,
            "persistence",
        );
        check(
            CloudNoise {
                persistence: 1e200,
                ..ok
            },
            0.0,
            "persistence",
        );
        check(
            CloudNoise {
                wind: DVec3::new(1.0, f64::NAN, 0.0),
                ..ok
            },
            0.0,
            "wind",
        );
        check(
            CloudNoise {
                detail_wind: f64::NAN,
                ..ok
            },
            0.0,
            "detail_wind",
        );
        check(
            CloudNoise {
                base_fade: -0.1,
                ..ok
            },
            0.0,
            "base_fade",
        );
        check(
            CloudNoise {
                top_fade: 2.0,
                ..ok
            },
            0.0,
            "top_fade",
        );
        check(ok, f64::NAN, "time");
        check(
            CloudNoise {
                wind: DVec3::X,
                detail_wind: 1e300,
                ..ok
            },
            1.0,
            "time",
        );
        let message = error_message(DensityGrid::cloud(
            [3, 3, 3],
            DVec3::new(1.0, 0.0, 1.0),
            DVec3::ZERO,
            &ok,
            0.0,
        ));
        assert_mentions(&message, &["spacing"]);
        let message = error_message(DensityGrid::cloud(
            [3, 3, 3],
            DVec3::ONE,
            DVec3::splat(f64::NAN),
            &ok,
            0.0,
        ));
        assert_mentions(&message, &["origin"]);
        let message = error_message(DensityGrid::cloud(
            [3, 1, 3],
            DVec3::ONE,
            DVec3::ZERO,
            &ok,
            0.0,
        ));
        assert_mentions(&message, &["at least 2 samples"]);
    }

    #[test]
    fn clouds_beyond_the_memory_budget_are_refused_before_allocating() {
        let message = error_message(DensityGrid::cloud(
            [4097, 4097, 4097],
            DVec3::ONE,
            DVec3::ZERO,
            &small(),
            0.0,
        ));
        assert_mentions(
            &message,
            &[
                "DensityGrid::cloud: density grid of 4097 × 4097 × 4097 points",
                "needs 275,079,282,692 bytes",
            ],
        );
    }
}
