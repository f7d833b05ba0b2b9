//! Point and spot lights scattered by a medium: the illuminance a light gives
//! a point and its single scattering toward the eye along a ray (the airlight
//! of Sun et al. 2005; the medium's attenuation toward the light is the
//! caller's).
//!
//! A [`LocalLight`] at `p` gives a point `x` at distance `r = |x − p|` the
//! illuminance `E(x) = c · W(r) · S(x) / (r² + r₀²)`: `c` its colour times its
//! luminous intensity over [`REFERENCE_ILLUMINANCE`] (so a transfer function's
//! colour is the medium's look under a light as bright as the reference sun,
//! [`LocalLight::from_lumens`]), `W(r) = clamp(1 − (r / range)⁴, 0, 1)²` Bevy's
//! smooth range window, `S` a spot light's cone `clamp(cos ψ · scale + offset,
//! 0, 1)²` with ψ the angle off its axis (Bevy's, [`SpotCone`]), and `r₀` =
//! [`CORE_RADIUS`], which keeps a ray through the light finite. A medium
//! scatters it toward the eye along the unit view ray `d` with the normalised
//! Henyey-Greenstein phase `4π p_HG(θ)`, `cos θ = d · (x − p) / r`:
//!
//! `L = ∫ f(t) E(x(t)) 4π p_HG(θ(t)) dt`
//!
//! with `f` the medium's weight (density times colour times the transmittance
//! to the eye). In the angle `γ = atan((t − t₀) / h)` at which the light sees
//! the ray's point (`t₀` the foot of the perpendicular from the light, `h² =
//! |p − x(t₀)|² + r₀²`), `dt / (r² + r₀²) = dγ / h`: the inverse square comes
//! out exactly, what is left is smooth and bounded, and Gauss-Legendre
//! quadrature in γ converges fast even where the ray passes by the light:
//! three nodes per interval no wider than [`interval_angle`] in γ (one for a
//! piece a tenth of its distance from the light long; the GPU's,
//! [`LocalLight::scattered`] with one interval) are within 2·10⁻³
//! (relative) of the converged integral (the reference's, with many) for
//! pieces of optical depth up to 2 as long as their distance from the light,
//! within 2·10⁻² for pieces reaching past its range.
//!
//! The medium's attenuation between the light and the point is the
//! caller's to put in `f` (fog layers do, in closed form; volumes leave it
//! out, so the light reaches them as through clear air). A light that casts
//! shadows is seen only from the stretches of a ray that opaque occluders
//! leave lit ([`LocalLight::scattered_past`], [`crate::occluder`]).

use glam::DVec3;

use crate::cell::Ray;
use crate::occluder::{Occluder, lit_spans};
use crate::optics::{checked_asymmetry, henyey_greenstein};

/// The illuminance, in lux, of a colour factor of 1: Bevy's default
/// `DirectionalLight` (the sun a volume's colours are authored under).
pub const REFERENCE_ILLUMINANCE: f64 = 10_000.0;

/// The core radius `r₀` of the inverse-square falloff `1 / (r² + r₀²)`, world
/// units (Bevy clamps the distance squared at `10⁻⁴` the same way).
pub const CORE_RADIUS: f64 = 0.01;

/// The most local lights one batch of cells is lit by.
pub const MAX_LOCAL_LIGHTS: usize = 8;

/// The widest interval of Gauss-Legendre quadrature in the angle γ, radians,
/// for isotropic scattering: a piece of a ray that passes close by a light
/// (and so spans a wide angle as the light sees it) takes several.
pub const MAX_INTERVAL_ANGLE: f64 = 0.5;

/// The widest interval in γ for the asymmetry `g`: [`MAX_INTERVAL_ANGLE`]
/// times `1 − |g|` (clamped to ±0.9), the width of the phase function's
/// peak, which lies in γ where the ray points away from the light.
pub fn interval_angle(asymmetry: f64) -> f64 {
    let g = if asymmetry.is_nan() {
        0.0
    } else {
        asymmetry.abs().min(0.9)
    };
    MAX_INTERVAL_ANGLE * (1.0 - g)
}

/// Gauss-Legendre nodes and weights on [−1, 1], three points (exact for
/// polynomials of degree 5): what the GPU takes per piece of a segment.
pub const GAUSS_LEGENDRE_3: [(f64, f64); 3] = [
    (-0.774_596_669_241_483_4, 5.0 / 9.0),
    (0.0, 8.0 / 9.0),
    (0.774_596_669_241_483_4, 5.0 / 9.0),
];

/// How a medium scatters local lights: the Henyey-Greenstein asymmetry of
/// its phase function and a factor on its colour κ. κ is the medium's look
/// under a light as bright as the reference sun, so a medium authored dark
/// for a night scene takes a `strength` above 1 to show a lamp's light.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(deny_unknown_fields, default))]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
pub struct LightResponse {
    /// The asymmetry `g`, in (−1, 1): > 0 scatters forward. Default 0
    /// (isotropic).
    pub asymmetry: f32,
    /// The factor on κ for the light it scatters, finite and ≥ 0. Default 1.
    pub strength: f32,
}

impl Default for LightResponse {
    fn default() -> Self {
        Self {
            asymmetry: 0.0,
            strength: 1.0,
        }
    }
}

impl LightResponse {
    /// What renderers use: the asymmetry clamped to ±0.99 (NaN as 0), the
    /// strength as 0 where it is negative or not finite.
    pub fn checked(&self) -> Self {
        Self {
            asymmetry: checked_asymmetry(self.asymmetry),
            strength: if self.strength.is_finite() {
                self.strength.max(0.0)
            } else {
                0.0
            },
        }
    }

    /// Why it is out of range, naming the field, if it is.
    pub fn invalid(&self) -> Option<(&'static str, String)> {
        if self.asymmetry.is_nan() || self.asymmetry.abs() >= 1.0 {
            return Some((
                "asymmetry",
                format!("must be in (−1, 1), got {}", self.asymmetry),
            ));
        }
        if !(self.strength.is_finite() && self.strength >= 0.0) {
            return Some((
                "strength",
                format!("must be finite and ≥ 0, got {}", self.strength),
            ));
        }
        None
    }
}

/// The factor on a firelight's intensity at `time` seconds for a flicker of
/// relative `amplitude` (clamped to [0, 1]): three incommensurate sines,
/// between `1 − amplitude` and `1 + amplitude`.
pub fn flicker(amplitude: f64, time: f64) -> f64 {
    use std::f64::consts::TAU;
    let wave = 0.5 * (TAU * 7.3 * time).sin()
        + 0.3 * (TAU * 13.1 * time + 1.3).sin()
        + 0.2 * (TAU * 2.9 * time + 0.7).sin();
    let amplitude = if amplitude.is_nan() {
        0.0
    } else {
        amplitude.clamp(0.0, 1.0)
    };
    1.0 + amplitude * wave
}

/// A spot light's cone: the factor `clamp(cos ψ · scale + offset, 0, 1)²` on
/// its light, ψ the angle between `direction` and the way to the point; 1
/// inside the inner angle, 0 outside the outer one (Bevy's `SpotLight`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpotCone {
    /// Unit direction the spot points in.
    pub direction: DVec3,
    /// `1 / max(cos inner − cos outer, 10⁻⁴)`.
    pub scale: f64,
    /// `−cos outer · scale`.
    pub offset: f64,
}

impl SpotCone {
    /// The cone along `direction` (normalised; zero points down −Y) between
    /// the inner and outer half-angles in radians, each clamped to [0, π/2],
    /// the inner to at most the outer, as Bevy clamps them.
    pub fn new(direction: DVec3, inner_angle: f64, outer_angle: f64) -> Self {
        let outer = if outer_angle.is_nan() {
            0.0
        } else {
            outer_angle.clamp(0.0, std::f64::consts::FRAC_PI_2)
        };
        let inner = if inner_angle.is_nan() {
            0.0
        } else {
            inner_angle.clamp(0.0, outer)
        };
        let scale = 1.0 / (inner.cos() - outer.cos()).max(1e-4);
        Self {
            direction: direction.normalize_or(DVec3::NEG_Y),
            scale,
            offset: -outer.cos() * scale,
        }
    }

    /// The factor for the unit direction `toward` from the light to a point.
    pub fn factor(&self, toward: DVec3) -> f64 {
        let f = (self.direction.dot(toward) * self.scale + self.offset).clamp(0.0, 1.0);
        f * f
    }

    /// The stretch `[t_0, t_1]` of the line `offset + t · direction` (`offset`
    /// from the apex, `direction` a unit vector) inside the outer cone, where
    /// the factor may be above 0; a convex cone meets a line in one stretch,
    /// possibly unbounded or empty (`t_0 > t_1`). The whole line where that
    /// cannot be told apart (the line parallel to the cone's side, an outer
    /// angle of 90°).
    pub fn chord(&self, offset: DVec3, direction: DVec3) -> (f64, f64) {
        self.chord_at(-self.offset / self.scale, offset, direction)
    }

    /// The same for the inner cone, where the factor is 1.
    pub fn inner_chord(&self, offset: DVec3, direction: DVec3) -> (f64, f64) {
        self.chord_at((1.0 - self.offset) / self.scale, offset, direction)
    }

    /// The stretch inside the cone of cosine `c` about the axis.
    fn chord_at(&self, c: f64, offset: DVec3, direction: DVec3) -> (f64, f64) {
        const WHOLE: (f64, f64) = (f64::NEG_INFINITY, f64::INFINITY);
        const EMPTY: (f64, f64) = (f64::INFINITY, f64::NEG_INFINITY);
        let (aw, ad) = (self.direction.dot(offset), self.direction.dot(direction));
        // Inside: a · v ≥ c |v| for v = offset + t direction, that is a · v ≥ 0
        // and q(t) = (a · v)² − c² |v|² = A t² + 2 B t + C ≥ 0.
        let a = ad * ad - c * c;
        let b = aw * ad - c * c * offset.dot(direction);
        let k = aw * aw - c * c * offset.length_squared();
        let discriminant = b * b - a * k;
        if c <= 1e-6 || a.abs() < 1e-9 || !discriminant.is_finite() {
            return WHOLE;
        }
        if discriminant < 0.0 {
            return if a < 0.0 { EMPTY } else { WHOLE };
        }
        let root = discriminant.sqrt();
        let (r0, r1) = ((-b - root) / a, (-b + root) / a);
        let (lo, hi) = (r0.min(r1), r0.max(r1));
        let forward = |t: f64| aw + t * ad >= 0.0;
        if a < 0.0 {
            // Between the roots, in one nappe.
            if forward(0.5 * (lo + hi)) {
                (lo, hi)
            } else {
                EMPTY
            }
        } else if ad > 0.0 {
            if forward(hi) {
                (hi, f64::INFINITY)
            } else {
                EMPTY
            }
        } else if forward(lo) {
            (f64::NEG_INFINITY, lo)
        } else {
            EMPTY
        }
    }
}

/// A point or spot light that scatters in a volume (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalLight {
    /// Where it is, world space.
    pub position: DVec3,
    /// Linear RGB illuminance at unit distance over [`REFERENCE_ILLUMINANCE`]
    /// (before the window and the cone), each ≥ 0.
    pub colour: DVec3,
    /// Distance beyond which it lights nothing, world units, > 0.
    pub range: f64,
    /// A spot light's cone; `None` lights every direction.
    pub cone: Option<SpotCone>,
    /// Whether opaque geometry casts its shadow into the medium.
    pub shadows: bool,
}

impl LocalLight {
    /// A point light of `lumens` (luminous power, Bevy's `intensity`) in the
    /// linear colour `colour`, whose luminous intensity `lumens / 4π` cd
    /// gives `colour · lumens / (4π r² REFERENCE_ILLUMINANCE)` at distance
    /// `r`. Bevy takes a spot light's intensity the same way.
    pub fn from_lumens(position: DVec3, colour: DVec3, lumens: f64, range: f64) -> Self {
        Self {
            position,
            colour: colour * lumens / (4.0 * std::f64::consts::PI * REFERENCE_ILLUMINANCE),
            range,
            cone: None,
            shadows: false,
        }
    }

    /// Why the light cannot be used, if it cannot: a non-finite position or
    /// colour, a negative colour, a range that is not finite and > 0, or a
    /// cone with a non-finite part.
    pub fn invalid(&self) -> Option<String> {
        if !self.position.is_finite() {
            return Some(format!("position {} is not finite", self.position));
        }
        if !(self.colour.is_finite() && self.colour.min_element() >= 0.0) {
            return Some(format!("colour {} must be finite and ≥ 0", self.colour));
        }
        if !(self.range.is_finite() && self.range > 0.0) {
            return Some(format!("range {} must be finite and > 0", self.range));
        }
        if let Some(cone) = self.cone
            && !(cone.direction.is_finite() && cone.scale.is_finite() && cone.offset.is_finite())
        {
            return Some(format!("cone {cone:?} is not finite"));
        }
        None
    }

    /// The illuminance at `x` over [`REFERENCE_ILLUMINANCE`], linear RGB.
    pub fn illuminance(&self, x: DVec3) -> DVec3 {
        let offset = x - self.position;
        let r2 = offset.length_squared();
        self.colour * self.falloff(offset, r2) / (r2 + CORE_RADIUS * CORE_RADIUS)
    }

    /// The range window times the cone at `offset` from the light, `r2` its
    /// length squared.
    fn falloff(&self, offset: DVec3, r2: f64) -> f64 {
        let u = r2 / (self.range * self.range);
        let window = (1.0 - u * u).clamp(0.0, 1.0);
        let cone = self.cone.map_or(1.0, |cone| {
            let r = r2.sqrt();
            cone.factor(if r > 0.0 { offset / r } else { DVec3::ZERO })
        });
        window * window * cone
    }

    /// Whether the light reaches any point of the box `[min, max]`.
    pub fn reaches_box(&self, min: DVec3, max: DVec3) -> bool {
        self.position
            .clamp(min, max)
            .distance_squared(self.position)
            < self.range * self.range
    }

    /// `∫ f(t) E(x(t)) 4π p_HG(θ(t)) dt` over `[t_a, t_b]` along the unit ray
    /// `origin + t · direction` (see the module docs), with `f` the medium's
    /// weight at `t`: over the part of the span inside the light's range and
    /// outer cone ([`SpotCone::chord`]), cut where the ray crosses the inner
    /// cone ([`SpotCone::inner_chord`]; the cone's factor has a kink there),
    /// each part in at least `intervals` equal intervals of
    /// [`GAUSS_LEGENDRE_3`] in the angle γ, none wider than
    /// [`interval_angle`]. One interval is what the GPU takes per piece of a
    /// segment; the reference takes many.
    pub fn scattered(
        &self,
        origin: DVec3,
        direction: DVec3,
        (t_a, t_b): (f64, f64),
        asymmetry: f64,
        intervals: u32,
        mut f: impl FnMut(f64) -> DVec3,
    ) -> DVec3 {
        if t_b.partial_cmp(&t_a) != Some(std::cmp::Ordering::Greater) {
            return DVec3::ZERO;
        }
        // The outer cone clips each part (`integrate`); the inner one cuts.
        let mut cuts = vec![t_a, t_b];
        if let Some(cone) = self.cone {
            let (t_0, t_1) = cone.inner_chord(origin - self.position, direction);
            cuts.extend([t_0, t_1]);
        }
        cuts.retain(|t| *t >= t_a && *t <= t_b);
        cuts.sort_by(f64::total_cmp);
        cuts.windows(2)
            .map(|pair| {
                self.integrate(
                    origin,
                    direction,
                    (pair[0], pair[1]),
                    asymmetry,
                    intervals,
                    &mut f,
                )
            })
            .fold(DVec3::ZERO, |sum, part| sum + part)
    }

    /// [`LocalLight::scattered`] along `ray` over the stretches of `[t_a,
    /// t_b]` inside the light's range that see it past `occluders`
    /// ([`lit_spans`]) when it casts shadows; over the whole span when it
    /// does not.
    pub fn scattered_past(
        &self,
        occluders: &[Occluder],
        ray: &Ray,
        (t_a, t_b): (f64, f64),
        asymmetry: f64,
        intervals: u32,
        mut f: impl FnMut(f64) -> DVec3,
    ) -> DVec3 {
        let (origin, direction) = (ray.origin, ray.direction);
        if !self.shadows || occluders.is_empty() {
            return self.scattered(origin, direction, (t_a, t_b), asymmetry, intervals, f);
        }
        // Only the chord inside the range is sampled for shadows.
        let foot = (self.position - origin).dot(direction);
        let miss2 = (self.position - origin - foot * direction).length_squared();
        let half_chord = (self.range * self.range - miss2).max(0.0).sqrt();
        let span = (t_a.max(foot - half_chord), t_b.min(foot + half_chord));
        lit_spans(occluders, self.position, ray, span)
            .into_iter()
            .map(|span| self.scattered(origin, direction, span, asymmetry, intervals, &mut f))
            .fold(DVec3::ZERO, |sum, part| sum + part)
    }

    /// Composite Gauss-Legendre in γ over the part of `[t_a, t_b]` inside the
    /// range and the outer cone, `intervals` equal intervals, or more where
    /// they would be wider than [`interval_angle`].
    fn integrate(
        &self,
        origin: DVec3,
        direction: DVec3,
        (t_a, t_b): (f64, f64),
        asymmetry: f64,
        intervals: u32,
        mut f: impl FnMut(f64) -> DVec3,
    ) -> DVec3 {
        if t_b.partial_cmp(&t_a) != Some(std::cmp::Ordering::Greater) {
            return DVec3::ZERO;
        }
        let to_light = self.position - origin;
        let foot = to_light.dot(direction);
        let miss2 = (to_light - foot * direction).length_squared();
        // Only the chord inside the light's range (the window is smooth there)
        // and inside a spot light's outer cone.
        let half_chord = (self.range * self.range - miss2).max(0.0).sqrt();
        let (mut t_a, mut t_b) = (t_a.max(foot - half_chord), t_b.min(foot + half_chord));
        if let Some(cone) = self.cone {
            let (t_0, t_1) = cone.chord(-to_light, direction);
            (t_a, t_b) = (t_a.max(t_0), t_b.min(t_1));
        }
        if t_b.partial_cmp(&t_a) != Some(std::cmp::Ordering::Greater) {
            return DVec3::ZERO;
        }
        let h = (miss2 + CORE_RADIUS * CORE_RADIUS).sqrt();
        let gamma_a = ((t_a - foot) / h).atan();
        let gamma_b = ((t_b - foot) / h).atan();
        // At least `intervals`, and none wider than the GPU's.
        let intervals = intervals
            .max(((gamma_b - gamma_a) / interval_angle(asymmetry)).ceil() as u32)
            .max(1);
        let width = (gamma_b - gamma_a) / f64::from(intervals);
        let mut sum = DVec3::ZERO;
        for interval in 0..intervals {
            let centre = gamma_a + width * (f64::from(interval) + 0.5);
            for (node, weight) in GAUSS_LEGENDRE_3 {
                let gamma = centre + 0.5 * width * node;
                let along = h * gamma.tan();
                let t = foot + along;
                let offset = origin + t * direction - self.position;
                let r2 = miss2 + along * along;
                let cos_theta = if r2 > 0.0 { along / r2.sqrt() } else { 0.0 };
                let light = self.falloff(offset, r2) * henyey_greenstein(asymmetry, cos_theta);
                sum += weight * light * f(t);
            }
        }
        self.colour * sum * (0.5 * width / h)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::SplitMix;

    /// A light too far-reaching for its window to matter.
    fn unwindowed(position: DVec3) -> LocalLight {
        LocalLight {
            position,
            colour: DVec3::new(1.0, 0.5, 0.25),
            range: 1e9,
            cone: None,
            shadows: false,
        }
    }

    /// `∫ g(t) dt` over `[a, b]` by the midpoint rule in `n` steps: an
    /// independent check, in `t` rather than in the angle.
    fn midpoint(a: f64, b: f64, n: u32, mut g: impl FnMut(f64) -> DVec3) -> DVec3 {
        let step = (b - a) / f64::from(n);
        (0..n)
            .map(|i| g(a + step * (f64::from(i) + 0.5)))
            .fold(DVec3::ZERO, |sum, v| sum + v)
            * step
    }

    #[test]
    fn a_clear_isotropic_ray_matches_the_arctangent() {
        // f = 1, g = 0, no window: ∫ dt / (h² + (t − t₀)²) = (atan((t_b − t₀)/h)
        // − atan((t_a − t₀)/h)) / h, which one interval integrates exactly
        // (its integrand in γ is constant).
        let light = unwindowed(DVec3::new(0.3, 0.4, -2.0));
        let origin = DVec3::new(0.0, 0.0, 0.0);
        let direction = DVec3::NEG_Z;
        let (t_a, t_b) = (0.5, 7.0);
        let h = (0.25 + CORE_RADIUS * CORE_RADIUS).sqrt();
        let exact = (((t_b - 2.0) / h).atan() - ((t_a - 2.0) / h).atan()) / h;
        let got = light.scattered(origin, direction, (t_a, t_b), 0.0, 1, |_| DVec3::ONE);
        let expected = light.colour * exact;
        assert!((got - expected).abs().max_element() < 1e-12 * expected.max_element());
    }

    #[test]
    fn quadrature_in_the_angle_matches_the_integral_in_distance() {
        // Random lights (point and spot, windowed, anisotropic) beside random
        // rays through an exponentially absorbing medium: the angle's
        // quadrature against a fine midpoint rule in t.
        let mut rng = SplitMix(7);
        for case in 0..40 {
            let mut light = LocalLight::from_lumens(
                DVec3::new(
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                ),
                DVec3::new(1.0, 0.8, 0.6),
                rng.random_range(1e4..1e6),
                rng.random_range(2.0..12.0),
            );
            if case % 2 == 1 {
                let direction = DVec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                );
                light.cone = Some(SpotCone::new(direction, 0.3, 0.6));
            }
            let origin = DVec3::new(rng.random_range(-1.0..1.0), 0.0, 4.0);
            let direction = DVec3::new(
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.5..0.5),
                -1.0,
            )
            .normalize();
            let asymmetry = rng.random_range(-0.7..0.7);
            let sigma = rng.random_range(0.0..1.5);
            let (t_a, t_b) = (rng.random_range(0.0..2.0), rng.random_range(3.0..9.0));
            let f = |t: f64| DVec3::splat(sigma * (-sigma * (t - t_a)).exp());
            let got = light.scattered(origin, direction, (t_a, t_b), asymmetry, 256, f);
            let expected = midpoint(t_a, t_b, 400_000, |t| {
                let x = origin + t * direction;
                let to = x - light.position;
                let cos_theta = direction.dot(to.normalize_or_zero());
                f(t) * light.illuminance(x) * henyey_greenstein(asymmetry, cos_theta)
            });
            let scale = expected.max_element().max(1e-12);
            assert!(
                (got - expected).abs().max_element() <= 1e-6 * scale,
                "case {case}: {got} against {expected}"
            );
        }
    }

    #[test]
    fn occluders_shade_a_light_that_casts_shadows() {
        // Random boxes and spheres between random lights and rays through an
        // absorbing medium: the integral over the lit stretches against a
        // fine midpoint rule in t of the integrand times the visibility.
        let mut rng = SplitMix(5);
        let mut shaded = 0;
        for case in 0..20 {
            let mut light = LocalLight::from_lumens(
                DVec3::new(
                    rng.random_range(-1.0..1.0),
                    0.0,
                    rng.random_range(-1.0..1.0),
                ),
                DVec3::new(1.0, 0.7, 0.4),
                rng.random_range(1e4..1e6),
                rng.random_range(6.0..12.0),
            );
            if case % 2 == 1 {
                light.cone = Some(SpotCone::new(DVec3::Y, 0.4, 0.9));
            }
            light.shadows = true;
            let sphere = Occluder::Sphere {
                centre: DVec3::new(rng.random_range(-2.0..2.0), 1.5, 0.0),
                radius: 0.4,
            };
            let occluders: Vec<Occluder> = (0..3)
                .map(|_| {
                    let centre = DVec3::new(
                        rng.random_range(-2.0..2.0),
                        rng.random_range(0.8..2.0),
                        rng.random_range(-2.0..2.0),
                    );
                    let half = DVec3::new(
                        rng.random_range(0.1..0.8),
                        rng.random_range(0.05..0.3),
                        rng.random_range(0.1..0.8),
                    );
                    Occluder::Box {
                        min: centre - half,
                        max: centre + half,
                    }
                })
                .chain([sphere])
                .collect();
            let ray = Ray::new(
                DVec3::new(
                    -6.0,
                    rng.random_range(2.5..4.0),
                    rng.random_range(-1.0..1.0),
                ),
                DVec3::new(
                    1.0,
                    rng.random_range(-0.1..0.1),
                    rng.random_range(-0.2..0.2),
                ),
            )
            .expect("a valid ray");
            let asymmetry = rng.random_range(-0.5..0.5);
            let sigma = rng.random_range(0.0..0.5);
            let (t_a, t_b) = (rng.random_range(0.0..2.0), rng.random_range(10.0..12.0));
            let f = |t: f64| DVec3::splat(sigma * (-sigma * (t - t_a)).exp());
            let got = light.scattered_past(&occluders, &ray, (t_a, t_b), asymmetry, 64, f);
            let integrand = |t: f64, visibility: bool| {
                let x = ray.origin + t * ray.direction;
                let seen = !visibility || !crate::occluder::hides(&occluders, x, light.position);
                let cos_theta = ray.direction.dot((x - light.position).normalize_or_zero());
                if seen {
                    f(t) * light.illuminance(x) * henyey_greenstein(asymmetry, cos_theta)
                } else {
                    DVec3::ZERO
                }
            };
            let expected = midpoint(t_a, t_b, 400_000, |t| integrand(t, true));
            let unshaded = midpoint(t_a, t_b, 4_000, |t| integrand(t, false));
            let scale = unshaded.max_element().max(1e-12);
            assert!(
                (got - expected).abs().max_element() <= 1e-5 * scale,
                "case {case}: {got} against {expected} (unshaded {unshaded})"
            );
            if (unshaded - expected).max_element() > 0.05 * scale {
                shaded += 1;
            }
            // Without shadows, the occluders change nothing.
            light.shadows = false;
            let clear = light.scattered_past(&occluders, &ray, (t_a, t_b), asymmetry, 64, f);
            assert_eq!(
                clear,
                light.scattered(ray.origin, ray.direction, (t_a, t_b), asymmetry, 64, f)
            );
        }
        // The cases are shaded, not merely lit.
        assert!(shaded >= 10, "{shaded} of 20 cases shaded");
    }

    #[test]
    fn the_gpu_quadrature_is_close_for_any_piece() {
        // The GPU's quadrature (intervals of three nodes no wider than
        // `interval_angle` per piece) against the converged one, for pieces of
        // optical depth up to 2, up to as long as their distance from the
        // light (1.7e-3 at most, where the depth is largest), and up to ten
        // times as long, reaching past the light's range, where its window
        // falls in a thin stretch of the angle (1.3e-2 at most).
        for (longest, bound) in [(1.0, 2e-3), (10.0, 2e-2)] {
            let mut rng = SplitMix(11);
            let mut worst: f64 = 0.0;
            for _ in 0..200 {
                let light = LocalLight::from_lumens(
                    DVec3::new(rng.random_range(-2.0..2.0), rng.random_range(0.5..2.0), 0.0),
                    DVec3::ONE,
                    1e5,
                    20.0,
                );
                let origin = DVec3::new(0.0, 0.0, 5.0);
                let direction = DVec3::new(rng.random_range(-0.3..0.3), 0.0, -1.0).normalize();
                let t_a = rng.random_range(0.0..9.0);
                let distance = light.position.distance(origin + t_a * direction);
                let length = rng.random_range(0.01..longest) * distance;
                let sigma = rng.random_range(0.0..1.0) * (2.0 / length).min(1.0);
                let asymmetry = rng.random_range(-0.8..0.8);
                let f = |t: f64| DVec3::splat(sigma * (-sigma * (t - t_a)).exp());
                let span = (t_a, t_a + length);
                let coarse = light.scattered(origin, direction, span, asymmetry, 1, f);
                let fine = light.scattered(origin, direction, span, asymmetry, 256, f);
                worst = worst.max((coarse - fine).abs().max_element() / fine.max_element());
            }
            assert!(
                worst < bound,
                "pieces up to {longest}: worst relative error {worst}"
            );
        }
    }

    #[test]
    fn the_cone_chord_holds_every_lit_point_of_a_line() {
        // Random cones and lines: every point with a factor above 0 lies in
        // the chord, and the chord's finite ends lie on the outer cone.
        let mut rng = SplitMix(3);
        let mut bounded = 0;
        for _ in 0..2000 {
            let mut random = || {
                DVec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                )
            };
            let (axis, offset, direction) = (random(), 3.0 * random(), random().normalize());
            let outer = 0.05 + 1.4 * (axis.x * 0.5 + 0.5);
            let cone = SpotCone::new(axis, 0.5 * outer, outer);
            let (t_0, t_1) = cone.chord(offset, direction);
            for i in 0..400 {
                let t = -10.0 + 0.05 * f64::from(i);
                let v = offset + t * direction;
                if cone.factor(v.normalize()) > 1e-9 {
                    assert!(
                        t >= t_0 - 1e-9 && t <= t_1 + 1e-9,
                        "{t} outside {t_0}..{t_1}"
                    );
                }
            }
            for end in [t_0, t_1] {
                if end.is_finite() {
                    bounded += 1;
                    let v = (offset + end * direction).normalize();
                    assert!((cone.direction.dot(v) - outer.cos()).abs() < 1e-9);
                }
            }
        }
        assert!(bounded > 1000, "only {bounded} finite ends");
    }

    #[test]
    fn the_cone_window_and_box_test() {
        let cone = SpotCone::new(DVec3::new(0.0, -2.0, 0.0), 0.2, 0.4);
        assert_eq!(cone.factor(DVec3::NEG_Y), 1.0);
        assert_eq!(cone.factor(DVec3::X), 0.0);
        let halfway = DVec3::new(0.3_f64.sin(), -0.3_f64.cos(), 0.0);
        let f = cone.factor(halfway);
        assert!(f > 0.0 && f < 1.0, "{f}");
        let mut light = LocalLight::from_lumens(DVec3::ZERO, DVec3::ONE, 1e5, 2.0);
        assert_eq!(light.illuminance(DVec3::new(2.0, 0.0, 0.0)), DVec3::ZERO);
        let near = light.illuminance(DVec3::new(1.0, 0.0, 0.0));
        let window = (1.0_f64 - 1.0 / 16.0).powi(2);
        let expected = 1e5 / (4.0 * std::f64::consts::PI * REFERENCE_ILLUMINANCE) * window
            / (1.0 + CORE_RADIUS * CORE_RADIUS);
        assert!((near.x - expected).abs() < 1e-12 * expected);
        light.cone = Some(cone);
        assert_eq!(light.illuminance(DVec3::new(1.0, 0.0, 0.0)), DVec3::ZERO);
        assert!(light.reaches_box(DVec3::new(1.0, -1.0, -1.0), DVec3::new(3.0, 1.0, 1.0)));
        assert!(!light.reaches_box(DVec3::new(1.5, 1.5, -1.0), DVec3::new(3.0, 3.0, 1.0)));
    }

    #[test]
    fn responses_are_checked_and_named() {
        let response = |asymmetry, strength| LightResponse {
            asymmetry,
            strength,
        };
        assert_eq!(response(f32::NAN, -1.0).checked(), response(0.0, 0.0));
        assert_eq!(response(2.0, f32::INFINITY).checked(), response(0.99, 0.0));
        assert_eq!(LightResponse::default().invalid(), None);
        assert_eq!(response(1.0, 1.0).invalid().unwrap().0, "asymmetry");
        assert_eq!(response(0.5, -1.0).invalid().unwrap().0, "strength");
    }

    #[test]
    fn bad_lights_are_named_and_odd_spans_give_nothing() {
        let light = LocalLight::from_lumens(DVec3::ZERO, DVec3::ONE, 1e5, 2.0);
        assert!(light.invalid().is_none());
        let bad = |change: fn(&mut LocalLight)| {
            let mut light = light;
            change(&mut light);
            light.invalid().expect("refused")
        };
        assert!(bad(|l| l.range = 0.0).contains("range"));
        assert!(bad(|l| l.position.x = f64::NAN).contains("position"));
        assert!(bad(|l| l.colour.y = -1.0).contains("colour"));
        let span = |a, b| light.scattered(DVec3::ZERO, DVec3::X, (a, b), 0.0, 1, |_| DVec3::ONE);
        assert_eq!(span(1.0, 1.0), DVec3::ZERO);
        assert_eq!(span(2.0, 1.0), DVec3::ZERO);
        assert_eq!(span(f64::NAN, 1.0), DVec3::ZERO);
        // A ray straight through the light stays finite.
        let through = span(-1.0, 1.0);
        assert!(through.is_finite() && through.x > 0.0);
        // NaN angles read as their defaults.
        let cone = SpotCone::new(DVec3::ZERO, f64::NAN, f64::NAN);
        assert!(cone.scale.is_finite() && cone.direction == DVec3::NEG_Y);
    }
}
