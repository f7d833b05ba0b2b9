//! Height fog: density over altitude only, integrated exactly along any ray
//! (Röttger 2004 §5.3, layered fog).
//!
//! When the density ρ depends on the altitude `h` alone, a straight ray
//! segment of length `L` from altitude `h₀` to `h₁` has the optical depth
//!
//! `τ = L · (T(h₁) − T(h₀)) / (h₁ − h₀)`
//!
//! with `T` the prefix integral of ρ over altitude: the segment's length
//! times the mean density over `[h₀, h₁]`. [`HeightFog::optical_depth`]
//! evaluates the mean per layer in a form that keeps its precision for
//! horizontal rays (`h₁ → h₀`, where the quotient above divides two rounding
//! errors): the exponential layer through `expm1`, the constant one by the
//! overlap of the ranges, the piecewise-linear one by its exact integral, each
//! falling back to the density at the midpoint when the range is below 1e-9
//! of the altitudes. The eye may be inside, above or below the layers; a sky
//! pixel is a segment to the largest distance the caller integrates (the
//! bounded layers end by themselves).
//!
//! **Sunlight** ([`HeightFog::sunlit`]) is closed form too. With `C(h) =
//! ∫_h^∞ ρ` the fog above `h` ([`HeightFog::column_above`]) and `μ` the sine
//! of the sun's elevation, a point at altitude `h` sees the sun through
//! `C(h)/μ`, and along the segment `ρ dt = −dC / d_y`, so the single
//! scattering `∫ ρ e^{−τ(0, t) − C(h(t))/μ} dt` is the integral of an
//! exponential in `C`:
//!
//! `I = τ e^{−τ − s₁} (e^{x} − 1) / x`, `x = τ − (s₀ − s₁)`,
//!
//! with `τ` the segment's optical depth and `s₀`, `s₁` the sun's optical
//! depths at its ends: `(e^{−s₀} − e^{−τ − s₁}) / (1 − d_y/μ)`, for any
//! profile. (`x = 0` where the segment climbs at the sun's elevation: `I = τ
//! e^{−s₀}`; a level segment: `I = e^{−s₀} (1 − e^{−τ})`.)
//!
//! Layers ([`HeightFogLayer`]) add up:
//!
//! - `Exponential`: `ρ(h) = density · e^{−falloff (h − base)}` at every
//!   altitude (it grows below `base`; the exponent is capped at 700, so ρ
//!   stays finite);
//! - `Constant`: `density` between `bottom` and `top`, 0 elsewhere;
//! - `Linear`: piecewise linear through `(altitude, density)` points, 0
//!   below the first and above the last.

use thiserror::Error;

/// One layer of a [`HeightFog`] (see the module docs). Altitudes in
/// metres, densities in 1/m.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
pub enum HeightFogLayer {
    /// `density · e^{−falloff (h − base)}`.
    Exponential {
        /// The altitude where the density is `density`, finite.
        base: f64,
        /// The density at `base`, finite and ≥ 0.
        density: f64,
        /// The rate the density falls with altitude, 1/m, finite and > 0.
        falloff: f64,
    },
    /// `density` between `bottom` and `top`.
    Constant {
        /// Lower altitude, finite.
        bottom: f64,
        /// Upper altitude, finite and above `bottom`.
        top: f64,
        /// The density, finite and ≥ 0.
        density: f64,
    },
    /// Piecewise linear through `(altitude, density)` points: at least two,
    /// altitudes strictly increasing, densities ≥ 0, all finite.
    Linear(Vec<[f64; 2]>),
}

/// Why a [`HeightFog`] could not be made.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum HeightFogError {
    /// A layer's settings are out of range.
    #[error("height fog layer {index} is invalid: {reason}")]
    InvalidLayer {
        /// The layer's index.
        index: usize,
        /// What is wrong.
        reason: &'static str,
    },
}

/// Density over altitude as a sum of layers, with its exact optical depth
/// along rays (see the module docs).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct HeightFog {
    layers: Vec<HeightFogLayer>,
}

/// The largest exponent an exponential layer is evaluated at.
const MAX_EXPONENT: f64 = 700.0;

/// Below this altitude range, relative to the altitudes, a layer's mean is
/// its density at the midpoint.
const FLAT_RANGE: f64 = 1e-9;

impl HeightFog {
    /// Checks and keeps `layers`.
    pub fn new(layers: Vec<HeightFogLayer>) -> Result<Self, HeightFogError> {
        for (index, layer) in layers.iter().enumerate() {
            let invalid = |reason| Err(HeightFogError::InvalidLayer { index, reason });
            match layer {
                HeightFogLayer::Exponential {
                    base,
                    density,
                    falloff,
                } => {
                    if !(base.is_finite() && density.is_finite() && *density >= 0.0) {
                        return invalid("base and density must be finite, density ≥ 0");
                    }
                    if !(falloff.is_finite() && *falloff > 0.0) {
                        return invalid("falloff must be finite and > 0");
                    }
                }
                HeightFogLayer::Constant {
                    bottom,
                    top,
                    density,
                } => {
                    if !(bottom.is_finite() && top.is_finite() && bottom < top) {
                        return invalid("bottom and top must be finite, bottom below top");
                    }
                    if !(density.is_finite() && *density >= 0.0) {
                        return invalid("density must be finite and ≥ 0");
                    }
                }
                HeightFogLayer::Linear(points) => {
                    let valid = points.len() >= 2
                        && points
                            .iter()
                            .all(|[h, d]| h.is_finite() && d.is_finite() && *d >= 0.0)
                        && points.windows(2).all(|w| w[0][0] < w[1][0]);
                    if !valid {
                        return invalid(
                            "needs two or more finite (altitude, density) points, altitudes increasing, densities ≥ 0",
                        );
                    }
                }
            }
        }
        Ok(Self { layers })
    }

    /// The layers.
    pub fn layers(&self) -> &[HeightFogLayer] {
        &self.layers
    }

    /// Whether some layer has a density above zero somewhere.
    pub fn has_density(&self) -> bool {
        self.layers.iter().any(|layer| match layer {
            HeightFogLayer::Exponential { density, .. }
            | HeightFogLayer::Constant { density, .. } => *density > 0.0,
            HeightFogLayer::Linear(points) => points.iter().any(|[_, d]| *d > 0.0),
        })
    }

    /// The altitudes where the density is not smooth, ascending: a constant
    /// layer's bottom and top, a linear layer's points. Between two of them
    /// the density is smooth (exponential or linear), so a quadrature along
    /// a ray converges fast only when it cuts the ray there.
    pub fn kinks(&self) -> Vec<f64> {
        let mut kinks: Vec<f64> = self
            .layers
            .iter()
            .flat_map(|layer| match layer {
                HeightFogLayer::Exponential { .. } => Vec::new(),
                HeightFogLayer::Constant { bottom, top, .. } => vec![*bottom, *top],
                HeightFogLayer::Linear(points) => points.iter().map(|[h, _]| *h).collect(),
            })
            .collect();
        kinks.sort_by(f64::total_cmp);
        kinks.dedup();
        kinks
    }

    /// The density at altitude `h`, 1/m (0 for a non-finite `h`).
    pub fn density(&self, h: f64) -> f64 {
        if !h.is_finite() {
            return 0.0;
        }
        self.layers.iter().map(|layer| layer.density(h)).sum()
    }

    /// The optical depth of a straight segment of `length` metres from
    /// altitude `h0` to `h1` (see the module docs). Non-finite or negative
    /// input gives 0 (no fog); the result is finite or +∞ for unbounded
    /// lengths, never NaN.
    pub fn optical_depth(&self, h0: f64, h1: f64, length: f64) -> f64 {
        if !(h0.is_finite() && h1.is_finite() && length > 0.0) || length.is_nan() {
            return 0.0;
        }
        let mean: f64 = self.layers.iter().map(|layer| layer.mean(h0, h1)).sum();
        if mean == 0.0 { 0.0 } else { length * mean }
    }

    /// The fog above altitude `h`, `C(h) = ∫_h^∞ ρ`: the optical depth
    /// straight up to the sky (0 for a non-finite `h`).
    pub fn column_above(&self, h: f64) -> f64 {
        if !h.is_finite() {
            return 0.0;
        }
        self.layers.iter().map(|layer| layer.column_above(h)).sum()
    }

    /// The sunlight scattered once toward the start of a straight segment of
    /// `length` metres from altitude `h0` to `h1`, per unit of sunlight and
    /// of phase: `∫ ρ(h(t)) e^{−τ(0, t) − C(h(t))/μ} dt`, with `μ` the sine
    /// of the sun's elevation (see the module docs: closed form). 0 for the
    /// sun at or below the horizon (`μ ≤ 0`, the ground in its way) and for
    /// non-finite or negative input.
    pub fn sunlit(&self, h0: f64, h1: f64, length: f64, mu: f64) -> f64 {
        let view = self.optical_depth(h0, h1, length);
        if view == 0.0 || mu.is_nan() || mu <= 0.0 {
            return 0.0;
        }
        let (sun_start, sun_end) = (self.column_above(h0) / mu, self.column_above(h1) / mu);
        if view.is_infinite() {
            return (-sun_start).exp();
        }
        let x = view - (sun_start - sun_end);
        if x > 1.0 {
            view * ((-sun_start).exp() - (-view - sun_end).exp()) / x
        } else {
            let growth = if x == 0.0 { 1.0 } else { x.exp_m1() / x };
            view * (-view - sun_end).exp() * growth
        }
    }
}

impl HeightFogLayer {
    /// `∫_h^∞` of the layer's density (its exponent capped as
    /// [`HeightFogLayer::density`]'s).
    fn column_above(&self, h: f64) -> f64 {
        match self {
            Self::Exponential {
                base,
                density,
                falloff,
            } => density / falloff * (-falloff * (h - base)).min(MAX_EXPONENT).exp(),
            Self::Constant {
                bottom,
                top,
                density,
            } => density * (top - h.max(*bottom)).max(0.0),
            Self::Linear(points) => {
                let last = points[points.len() - 1][0];
                if h < last {
                    linear_integral(points, h, last)
                } else {
                    0.0
                }
            }
        }
    }

    fn density(&self, h: f64) -> f64 {
        match self {
            Self::Exponential {
                base,
                density,
                falloff,
            } => density * (-falloff * (h - base)).min(MAX_EXPONENT).exp(),
            Self::Constant {
                bottom,
                top,
                density,
            } => {
                if (*bottom..=*top).contains(&h) {
                    *density
                } else {
                    0.0
                }
            }
            Self::Linear(points) => linear_at(points, h),
        }
    }

    /// The mean density over altitudes `[h0, h1]` (either order).
    fn mean(&self, h0: f64, h1: f64) -> f64 {
        let (low, high) = (h0.min(h1), h0.max(h1));
        let range = high - low;
        let flat = range <= FLAT_RANGE * (1.0 + low.abs().max(high.abs()));
        if flat {
            return self.density(0.5 * (low + high));
        }
        match self {
            Self::Exponential {
                base,
                density,
                falloff,
            } => {
                // ρ(low) · (1 − e^{−k·range}) / (k·range), exact and stable.
                let x = falloff * range;
                let at_low = (-falloff * (low - base)).min(MAX_EXPONENT);
                density * at_low.exp() * (-(-x).exp_m1() / x)
            }
            Self::Constant {
                bottom,
                top,
                density,
            } => {
                let overlap = (high.min(*top) - low.max(*bottom)).max(0.0);
                density * overlap / range
            }
            Self::Linear(points) => linear_integral(points, low, high) / range,
        }
    }
}

/// The piecewise-linear function through `points` at `h`, 0 outside.
fn linear_at(points: &[[f64; 2]], h: f64) -> f64 {
    let (first, last) = (points[0][0], points[points.len() - 1][0]);
    if !(first..=last).contains(&h) {
        return 0.0;
    }
    points.windows(2).find(|w| h <= w[1][0]).map_or(0.0, |w| {
        let t = (h - w[0][0]) / (w[1][0] - w[0][0]);
        w[0][1] + t * (w[1][1] - w[0][1])
    })
}

/// `∫_low^high` of the piecewise-linear function through `points`.
fn linear_integral(points: &[[f64; 2]], low: f64, high: f64) -> f64 {
    points
        .windows(2)
        .map(|w| {
            let (a, b) = (w[0][0].max(low), w[1][0].min(high));
            if b <= a {
                return 0.0;
            }
            // Trapezoid of the linear piece over [a, b]: exact.
            (b - a) * 0.5 * (linear_at(w, a) + linear_at(w, b))
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The optical depth by composite Gauss–Legendre quadrature along the
    /// segment, split where it crosses the fog's kinks.
    fn quadrature(fog: &HeightFog, h0: f64, h1: f64, length: f64) -> f64 {
        let nodes = [
            (0.069_431_844_202_973_71, 0.173_927_422_568_726_93),
            (0.330_009_478_207_571_87, 0.326_072_577_431_273_07),
            (0.669_990_521_792_428_1, 0.326_072_577_431_273_07),
            (0.930_568_155_797_026_3, 0.173_927_422_568_726_93),
        ];
        let mut cuts = vec![0.0, 1.0];
        if h1 != h0 {
            cuts.extend(
                fog.kinks()
                    .iter()
                    .map(|b| (b - h0) / (h1 - h0))
                    .filter(|s| *s > 0.0 && *s < 1.0),
            );
        }
        cuts.sort_by(f64::total_cmp);
        let pieces = 400;
        cuts.windows(2)
            .map(|cut| {
                (0..pieces)
                    .map(|p| {
                        let span = (cut[1] - cut[0]) / pieces as f64;
                        let a = cut[0] + p as f64 * span;
                        nodes
                            .iter()
                            .map(|(x, w)| w * span * fog.density(h0 + (a + x * span) * (h1 - h0)))
                            .sum::<f64>()
                    })
                    .sum::<f64>()
            })
            .sum::<f64>()
            * length
    }

    fn fog() -> HeightFog {
        HeightFog::new(vec![
            HeightFogLayer::Exponential {
                base: 20.0,
                density: 0.02,
                falloff: 0.01,
            },
            HeightFogLayer::Constant {
                bottom: 50.0,
                top: 120.0,
                density: 0.004,
            },
            HeightFogLayer::Linear(vec![[0.0, 0.0], [30.0, 0.05], [90.0, 0.01], [140.0, 0.0]]),
        ])
        .unwrap()
    }

    #[test]
    fn closed_forms_of_a_constant_layer() {
        let slab = HeightFog::new(vec![HeightFogLayer::Constant {
            bottom: 0.0,
            top: 10.0,
            density: 0.3,
        }])
        .unwrap();
        // Horizontal inside: ρ L; vertical through: ρ · thickness; oblique
        // from above to below: ρ · thickness · L / Δh; outside: 0.
        assert_eq!(slab.optical_depth(5.0, 5.0, 40.0), 0.3 * 40.0);
        assert!((slab.optical_depth(20.0, -5.0, 25.0) - 3.0).abs() < 1e-12);
        assert!((slab.optical_depth(30.0, -10.0, 80.0) - 0.3 * 10.0 * 2.0).abs() < 1e-12);
        assert_eq!(slab.optical_depth(11.0, 11.0, 1e6), 0.0);
        assert_eq!(slab.optical_depth(50.0, 20.0, 1e3), 0.0);
    }

    #[test]
    fn random_rays_match_quadrature_from_inside_above_and_below() {
        let fog = fog();
        let mut rng = 0x6865_6967_6874_u64;
        let mut random = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (rng >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..300 {
            let h0 = -50.0 + 250.0 * random();
            let h1 = -50.0 + 250.0 * random();
            let length = (h1 - h0).abs() + 2000.0 * random();
            let exact = fog.optical_depth(h0, h1, length);
            let numeric = quadrature(&fog, h0, h1, length);
            assert!(
                (exact - numeric).abs() <= 1e-9 * (1.0 + numeric),
                "{h0} → {h1} over {length}: {exact} vs {numeric}"
            );
        }
    }

    #[test]
    fn horizontal_rays_lose_no_precision() {
        let fog = fog();
        for h in [-30.0, 0.0, 20.0, 45.5, 77.7, 130.0, 1e4] {
            let level = fog.optical_depth(h, h, 1000.0);
            assert!((level - 1000.0 * fog.density(h)).abs() <= 1e-12 * (1.0 + level));
            // Nearly horizontal: continuous with the level ray, no
            // cancellation.
            for dh in [1e-13, 1e-10, 1e-7, 1e-4] {
                let tilted = fog.optical_depth(h, h + dh, 1000.0);
                let numeric = quadrature(&fog, h, h + dh, 1000.0);
                assert!(
                    (tilted - numeric).abs() <= 1e-7 * (1.0 + numeric),
                    "{h} + {dh}: {tilted} vs {numeric}"
                );
            }
        }
    }

    #[test]
    fn layers_add_and_bad_input_is_an_error_or_zero() {
        let fog = fog();
        // The jumps of the constant layer and the linear layer's kinks, once
        // each, ascending; the exponential layer has none.
        assert_eq!(fog.kinks(), [0.0, 30.0, 50.0, 90.0, 120.0, 140.0]);
        assert!(
            HeightFog::new(vec![fog.layers()[0].clone()])
                .unwrap()
                .kinks()
                .is_empty()
        );
        let parts: f64 = fog
            .layers()
            .iter()
            .map(|layer| {
                HeightFog::new(vec![layer.clone()])
                    .unwrap()
                    .optical_depth(10.0, 95.0, 300.0)
            })
            .sum();
        assert!((fog.optical_depth(10.0, 95.0, 300.0) - parts).abs() < 1e-12);
        for (h0, h1, length) in [
            (f64::NAN, 1.0, 10.0),
            (1.0, f64::INFINITY, 10.0),
            (1.0, 2.0, -3.0),
            (1.0, 2.0, f64::NAN),
            (1.0, 2.0, 0.0),
        ] {
            assert_eq!(fog.optical_depth(h0, h1, length), 0.0);
        }
        // Far below an exponential layer the density is capped, not infinite.
        let deep = fog.optical_depth(-1e6, -1e6 + 1.0, 10.0);
        assert!(deep.is_finite() && deep > 0.0);
        assert!(fog.optical_depth(-1e6, -1e6, f64::INFINITY).is_infinite());
        for (layer, needle) in [
            (
                HeightFogLayer::Exponential {
                    base: 0.0,
                    density: -1.0,
                    falloff: 0.1,
                },
                "density",
            ),
            (
                HeightFogLayer::Exponential {
                    base: 0.0,
                    density: 1.0,
                    falloff: 0.0,
                },
                "falloff",
            ),
            (
                HeightFogLayer::Constant {
                    bottom: 5.0,
                    top: 5.0,
                    density: 1.0,
                },
                "bottom below top",
            ),
            (HeightFogLayer::Linear(vec![[0.0, 1.0]]), "two or more"),
            (
                HeightFogLayer::Linear(vec![[0.0, 1.0], [0.0, 2.0]]),
                "increasing",
            ),
        ] {
            let error = HeightFog::new(vec![layer]).unwrap_err().to_string();
            assert!(error.contains(needle), "{error}");
        }
    }

    /// The fog above an altitude is the integral of the density up to where
    /// every layer has ended or fallen off.
    #[test]
    fn the_column_above_integrates_the_density_to_the_sky() {
        let fog = fog();
        for h in [-40.0, 0.0, 25.0, 50.0, 77.7, 120.0, 139.0, 400.0] {
            let top = 6000.0;
            let expected = quadrature(&fog, h, top, top - h);
            let column = fog.column_above(h);
            assert!(
                (column - expected).abs() <= 1e-9 * (1.0 + expected),
                "{h}: {column} against {expected}"
            );
        }
        assert_eq!(fog.column_above(f64::NAN), 0.0);
    }

    /// The closed form of the sunlight scattered once along a segment agrees
    /// with a midpoint integral of its definition (the transmittances to the
    /// eye and to the sun from the exact optical depths) on level, climbing,
    /// falling and steep segments, one climbing at the sun's elevation.
    #[test]
    fn sunlight_scattered_once_is_the_integral_of_its_definition() {
        let fog = fog();
        let steps = 200_000;
        for (h0, d_y, length, mu) in [
            (50.0, 0.0, 300.0, 0.5),
            (10.0, 0.3, 500.0, 0.6),
            (200.0, -0.5, 380.0, 0.4),
            (5.0, 0.6, 300.0, 0.6),
            (150.0, -0.9, 160.0, 0.2),
            (300.0, -0.2, 1400.0, 0.7),
            (-30.0, 0.05, 4000.0, 0.1),
        ] {
            let altitude = |t: f64| h0 + d_y * t;
            let dt = length / steps as f64;
            let sampled: f64 = (0..steps)
                .map(|k| {
                    let t = (k as f64 + 0.5) * dt;
                    let to_eye = fog.optical_depth(h0, altitude(t), t);
                    let to_sun = fog.column_above(altitude(t)) / mu;
                    fog.density(altitude(t)) * (-to_eye - to_sun).exp() * dt
                })
                .sum();
            let exact = fog.sunlit(h0, altitude(length), length, mu);
            assert!(
                (exact - sampled).abs() <= 2e-6 * sampled + 1e-12,
                "({h0}, {d_y}, {length}, {mu}): {exact} against {sampled}"
            );
        }
    }

    /// Sunlit pieces compose as emission and absorption do, `I(0, t₂) = I(0,
    /// t₁) + e^{−τ(0, t₁)} I(t₁, t₂)`; no sun at or below the horizon.
    #[test]
    fn sunlit_pieces_compose_and_a_set_sun_lights_nothing() {
        let fog = fog();
        let (h0, d_y, mu) = (130.0, -0.4, 0.35);
        let altitude = |t: f64| h0 + d_y * t;
        for (t1, t2) in [(10.0, 90.0), (120.0, 300.0), (200.0, 201.0)] {
            let whole = fog.sunlit(h0, altitude(t2), t2, mu);
            let near = fog.sunlit(h0, altitude(t1), t1, mu);
            let far = fog.sunlit(altitude(t1), altitude(t2), t2 - t1, mu);
            let through = (-fog.optical_depth(h0, altitude(t1), t1)).exp();
            assert!((whole - (near + through * far)).abs() <= 1e-12 * (1.0 + whole));
        }
        for mu in [0.0, -0.3, f64::NAN] {
            assert_eq!(fog.sunlit(h0, altitude(100.0), 100.0, mu), 0.0);
        }
        assert_eq!(fog.sunlit(h0, h0, 0.0, 0.5), 0.0);
    }
}
