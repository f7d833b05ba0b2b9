//! Fog layers in the reference: height fog along every ray, exact, and the
//! volume seen through it (Röttger 2004 §5.3, layered fog).
//!
//! The fog's density depends on the altitude only ([`HeightFog`]), so the
//! optical depth of any piece of a ray is exact in closed form. It glows
//! with an ambient colour `c`, so the fog over `[t₀, t₁]` is the
//! premultiplied layer `(c · α, α)`, `α = 1 − e^{−τ}`, plus, optionally,
//! sunlight scattered once toward the eye with the Henyey-Greenstein phase
//! function (the same at every point of a straight ray), dimmed by the fog
//! on its way from the sun and to the eye: closed form too
//! ([`HeightFog::sunlit`], [`ReferenceFog::sunlit`]). Cloud volumes that
//! cast shadows ([`ReferenceFog::clouds`]) hold back
//! `c 4π p_HG ∫ ρ e^{−τ(t₀, t) − C(h)/μ} (1 − T_c) dt` of it, `T_c` their
//! exact transmittance toward the sun
//! (`nebel_core::field::sun_transmittance`), by composite Gauss-Legendre
//! over [`CLOUD_INTERVALS`] equal intervals of the stretch they can shade
//! (`nebel_core::field::shaded_stretch`). The terrain's shadow heights
//! ([`ReferenceFog::terrain`]) take the sunlight of every stretch of the ray
//! below them (`nebel_core::field::PlacedTerrainShadow::shaded`, exact for
//! the map's bilinear heights): each stretch's closed form, seen through the
//! fog before it; the clouds then hold back light only where the terrain
//! lets the sun through. A sun that casts shadows ([`FogSunlight::shadows`])
//! is hidden by [`ReferenceFog::occluders`] too: the stretches from which
//! they hide it (`nebel_core::occluder::sun_lit_spans`, sampled and
//! bisected) join the terrain's. Such layers compose with "over".
//!
//! Point and spot lights ([`ReferenceFog::lights`]) add
//! `s c ∫ ρ(h(t)) e^{−τ(t₀, t) − τ(x(t), p)} E(t) 4π p_HG dt` over the piece
//! ([`nebel_core::local_light`]; the fog's colour `c` is its look under a
//! light as bright as the reference sun, as a ground fog's κ; `τ(x, p)` the
//! fog's optical depth from the point to the light at `p`, in closed form
//! like any straight segment's), converged by [`LocalLight::scattered`] on
//! the stretches between the altitudes where the density has a jump or a
//! kink ([`HeightFog::kinks`]). The piece is still an emission-absorption
//! layer, so pieces still compose with "over".
//!
//! # Volumes inside the fog
//!
//! A volume and the fog share the ray. Written as maps of the radiance
//! behind, a piece of volume `x ↦ C + (1 − α) x` between fog segments
//! `x ↦ F + T x` is the same as the piece *conjugated* by the fog in front
//! of it, `(T C + α F, α)` with `T`, `F` the fog from the eye to the piece,
//! followed by the fog from the eye to the end of the ray (the map algebra:
//! `Fog₀ₛ ∘ Cell ∘ Fogₛ_D = (Fog₀ₛ ∘ Cell ∘ Fog₀ₛ⁻¹) ∘ Fog₀_D`). So a volume
//! composited from conjugated pieces, put over the fogged background
//! ([`ReferenceFog::over`]), is the exact image of both media, as long as the
//! fog is applied at the right point of each piece. Inside a piece the two
//! media overlap; conjugating at the piece's middle is Strang splitting,
//! whose error is third order in the pieces' optical depths: the reference
//! cuts every piece until that error bound is below 1e-6
//! ([`conjugation_pieces`]), so its image is exact to far below the 8-bit
//! floor. Emissive and MIP pieces have no opacity: their colour is scaled by
//! the fog's transmittance.

use glam::DVec3;
use nebel_core::cell::Ray;
use nebel_core::field::{PlacedTerrainShadow, ShadowCaster, shaded_stretch, sun_transmittance};
use nebel_core::height_fog::{HeightFog, HeightFogLayer};
use nebel_core::local_light::{GAUSS_LEGENDRE_3, LightResponse, LocalLight};
use nebel_core::occluder::{Occluder, sun_lit_spans};
use nebel_core::optics::{PremultipliedRgba, henyey_greenstein};

use crate::integrator::LIGHT_INTERVALS;

/// Sunlight the fog scatters toward the eye.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FogSunlight {
    /// Unit direction toward the sun.
    pub direction: DVec3,
    /// The colour added to the fog's colour on average over all directions,
    /// linear RGB: it is scaled by `4π p_HG(g, cos θ)`, θ between the ray and
    /// the direction toward the sun.
    pub colour: DVec3,
    /// The Henyey-Greenstein asymmetry `g` (0 isotropic, toward 1 forward).
    pub asymmetry: f64,
    /// Whether [`ReferenceFog::occluders`] shade the sun (its light casts
    /// shadows; module docs).
    pub shadows: bool,
}

/// Fog layers seen along every ray (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct ReferenceFog {
    /// Density over altitude (y).
    pub fog: HeightFog,
    /// The colour dense fog converges to without sunlight, linear RGB.
    pub colour: DVec3,
    /// Optional sunlight scattered toward the eye.
    pub sun: Option<FogSunlight>,
    /// The fog begins at this distance along each ray, world units (≥ 0):
    /// nearer, another method (ground fog's prisms) draws it.
    pub start_distance: f64,
    /// Where the fog ends along each ray, world units (> 0): a ray that
    /// meets nothing opaque integrates to here.
    pub max_distance: f64,
    /// Point and spot lights the fog scatters toward the eye (see the module
    /// docs).
    pub lights: Vec<LocalLight>,
    /// How the fog scatters them: the phase's asymmetry and the factor `s`
    /// on its colour ([`LightResponse::checked`]).
    pub light_response: LightResponse,
    /// Opaque shapes that shade the lights that cast shadows
    /// ([`LocalLight::scattered_past`]), and the sun where it does (but for
    /// a terrain, whose shadow of the sun is [`ReferenceFog::terrain`]).
    pub occluders: Vec<Occluder>,
    /// Cloud volumes whose shadow dims the sunlight in the fog (module
    /// docs).
    pub clouds: Vec<ShadowCaster>,
    /// The terrain's shadow heights: the fog below them is not sunlit
    /// (module docs).
    pub terrain: Option<PlacedTerrainShadow>,
}

/// Intervals of the clouds' held-back sunlight over a stretch
/// ([`ReferenceFog::sunlit`]), three Gauss-Legendre nodes each (shared out
/// among the parts the terrain leaves sunlit).
pub const CLOUD_INTERVALS: usize = 512;

/// `spans` sorted and joined where they meet or overlap, empty ones
/// dropped.
fn union(mut spans: Vec<(f64, f64)>) -> Vec<(f64, f64)> {
    spans.retain(|(a, b)| b > a);
    spans.sort_by(|x, y| x.0.total_cmp(&y.0));
    let mut joined: Vec<(f64, f64)> = Vec::with_capacity(spans.len());
    for (a, b) in spans {
        match joined.last_mut() {
            Some(last) if a <= last.1 => last.1 = last.1.max(b),
            _ => joined.push((a, b)),
        }
    }
    joined
}

/// The most optical depth, plus exponential falloff times the altitude
/// crossed, in one part of a lit stretch ([`ReferenceFog::lit`]).
const MAX_PART_CHANGE: f64 = 0.05;

/// The most parts a lit stretch between two kinks is cut into.
const MAX_PARTS: f64 = 4096.0;

/// Largest number of pieces a volume piece is cut into for the fog.
const MAX_CONJUGATION_PIECES: f64 = 20_000.0;

impl ReferenceFog {
    /// Why the fog is invalid, if it is.
    pub(crate) fn invalid(&self) -> Option<String> {
        let colours_valid = |c: DVec3| c.is_finite() && c.min_element() >= 0.0;
        if !colours_valid(self.colour) {
            return Some(format!("colour {} must be finite and ≥ 0", self.colour));
        }
        if let Some(sun) = &self.sun
            && !(colours_valid(sun.colour)
                && sun.direction.is_finite()
                && sun.direction.length() > 0.0
                && sun.asymmetry.is_finite())
        {
            return Some(format!("sunlight {sun:?} must be finite, with a direction"));
        }
        if let Some(reason) = self.lights.iter().find_map(LocalLight::invalid) {
            return Some(reason);
        }
        if let Some((field, reason)) = self.light_response.invalid() {
            return Some(format!("light_response.{field} {reason}"));
        }
        if !(self.start_distance.is_finite() && self.start_distance >= 0.0) {
            return Some(format!(
                "start_distance {} must be finite and ≥ 0",
                self.start_distance
            ));
        }
        if !(self.max_distance.is_finite() && self.max_distance > 0.0) {
            return Some(format!(
                "max_distance {} must be finite and > 0",
                self.max_distance
            ));
        }
        None
    }

    /// `[t0, t1]` clipped to `[start_distance, max_distance]`; `None` where
    /// nothing is left (or an end is NaN).
    fn within(&self, t0: f64, t1: f64) -> Option<(f64, f64)> {
        let (a, b) = (t0.max(self.start_distance), t1.min(self.max_distance));
        (b.partial_cmp(&a) == Some(std::cmp::Ordering::Greater)).then_some((a, b))
    }

    /// The sunlight the fog over `[t0, t1]` along `ray` (clipped to
    /// `[start_distance, max_distance]`) scatters once toward `t0`,
    /// attenuated on its way from the sun and to `t0` (closed form,
    /// [`HeightFog::sunlit`]); none for the sun at or below the horizon.
    pub fn sunlit(&self, ray: &Ray, t0: f64, t1: f64) -> DVec3 {
        let Some(sun) = self.sun else {
            return DVec3::ZERO;
        };
        let Some((a, b)) = self.within(t0, t1) else {
            return DVec3::ZERO;
        };
        let direction = sun.direction.normalize();
        let altitude = |t: f64| ray.origin.y + t * ray.direction.y;
        let mut scattered = self
            .fog
            .sunlit(altitude(a), altitude(b), b - a, direction.y);
        // The terrain's shadow and the occluders' (where the sun casts
        // shadows): each shaded stretch's sunlight, closed form seen from its
        // start, then dimmed to `a`.
        let mut shaded = self.terrain.as_ref().map_or_else(Vec::new, |terrain| {
            terrain.shaded(ray.origin, ray.direction, (a, b))
        });
        let meshes: Vec<Occluder> = if sun.shadows {
            self.occluders
                .iter()
                .filter(|occluder| !matches!(occluder, Occluder::Terrain(_)))
                .cloned()
                .collect()
        } else {
            Vec::new()
        };
        if !meshes.is_empty() {
            let mut from = a;
            for (lit_from, lit_to) in sun_lit_spans(&meshes, direction, ray, (a, b)) {
                shaded.push((from, lit_from));
                from = lit_to;
            }
            shaded.push((from, b));
            shaded = union(shaded);
        }
        for &(c, d) in &shaded {
            scattered -= (-self.optical_depth(ray, a, c)).exp()
                * self
                    .fog
                    .sunlit(altitude(c), altitude(d), d - c, direction.y);
        }
        // The clouds' shadow over the sunlit rest of the stretch they can
        // shade, in intervals proportional to each lit part's length.
        if let Some((c, d)) =
            shaded_stretch(&self.clouds, direction, ray.origin, ray.direction, (a, b))
        {
            let mut lit = Vec::new();
            let mut from = c;
            for &(e, f) in shaded.iter().filter(|&&(e, f)| f > c && e < d) {
                lit.push((from, e.max(c)));
                from = f.min(d);
            }
            lit.push((from, d));
            for (u, v) in lit.into_iter().filter(|(u, v)| v > u) {
                let intervals = (CLOUD_INTERVALS as f64 * (v - u) / (d - c)).ceil().max(1.0);
                let step = (v - u) / intervals;
                for k in 0..intervals as usize {
                    let middle = u + step * (k as f64 + 0.5);
                    for (node, weight) in GAUSS_LEGENDRE_3 {
                        let t = middle + 0.5 * step * node;
                        let h = altitude(t);
                        let x = ray.origin + t * ray.direction;
                        let held = 1.0 - sun_transmittance(&self.clouds, direction, x);
                        if held > 0.0 {
                            let depth = self.optical_depth(ray, a, t)
                                + self.fog.column_above(h) / direction.y;
                            scattered -=
                                0.5 * step * weight * self.fog.density(h) * (-depth).exp() * held;
                        }
                    }
                }
            }
        }
        sun.colour
            * henyey_greenstein(sun.asymmetry, ray.direction.dot(direction))
            * scattered.max(0.0)
    }

    /// The optical depth of the fog over `[t0, t1]` along `ray` (clipped to
    /// `[start_distance, max_distance]`).
    pub fn optical_depth(&self, ray: &Ray, t0: f64, t1: f64) -> f64 {
        let Some((t0, t1)) = self.within(t0, t1) else {
            return 0.0;
        };
        let altitude = |t: f64| ray.origin.y + t * ray.direction.y;
        self.fog.optical_depth(altitude(t0), altitude(t1), t1 - t0)
    }

    /// The fog over `[t0, t1]` along `ray` as a premultiplied layer, its
    /// lights' part included.
    pub fn segment(&self, ray: &Ray, t0: f64, t1: f64) -> PremultipliedRgba {
        let alpha = -(-self.optical_depth(ray, t0, t1)).exp_m1();
        (self.colour * alpha + self.sunlit(ray, t0, t1) + self.lit(ray, t0, t1)).extend(alpha)
    }

    /// The lights scattered toward the eye over `[t0, t1]` along `ray`, seen
    /// from `t0` (see the module docs).
    pub fn lit(&self, ray: &Ray, t0: f64, t1: f64) -> DVec3 {
        let Some((a, b)) = self.within(t0, t1).filter(|_| !self.lights.is_empty()) else {
            return DVec3::ZERO;
        };
        let altitude = |t: f64| ray.origin.y + t * ray.direction.y;
        let mut cuts = vec![a, b];
        if ray.direction.y != 0.0 {
            cuts.extend(
                self.fog
                    .kinks()
                    .iter()
                    .map(|h| (h - ray.origin.y) / ray.direction.y)
                    .filter(|t| *t > a && *t < b),
            );
        }
        cuts.sort_by(f64::total_cmp);
        let response = self.light_response.checked();
        // The density, and the transmittance to the eye and to the light.
        let weight = |light: &LocalLight, t: f64| {
            let x = ray.origin + t * ray.direction;
            let to_light =
                self.fog
                    .optical_depth(x.y, light.position.y, x.distance(light.position));
            let depth = self.optical_depth(ray, t0, t) + to_light;
            DVec3::splat(self.fog.density(altitude(t)) * (-depth).exp())
        };
        // Each stretch in parts short enough that the density and the
        // transmittance change little in each (the quadrature's intervals
        // are set by the angle the light sees, which says nothing of them).
        let falloff: f64 = self
            .fog
            .layers()
            .iter()
            .map(|layer| match layer {
                HeightFogLayer::Exponential { falloff, .. } => *falloff,
                _ => 0.0,
            })
            .sum();
        let mut parts = Vec::new();
        for stretch in cuts.windows(2) {
            let (a, b) = (stretch[0], stretch[1]);
            let change = self.optical_depth(ray, a, b) + falloff * (b - a) * ray.direction.y.abs();
            let count = (change / MAX_PART_CHANGE).ceil().clamp(1.0, MAX_PARTS);
            parts.extend((0..count as usize).map(|k| {
                let part = |k: f64| a + (b - a) * k / count;
                (part(k as f64), part(k as f64 + 1.0))
            }));
        }
        let mut sum = DVec3::ZERO;
        for light in &self.lights {
            for &part in &parts {
                sum += light.scattered_past(
                    &self.occluders,
                    ray,
                    part,
                    f64::from(response.asymmetry),
                    LIGHT_INTERVALS,
                    |t| weight(light, t),
                );
            }
        }
        self.colour * f64::from(response.strength) * sum
    }

    /// `background` seen through the fog from the eye to `t_far` (+∞: a ray
    /// that meets nothing opaque, to `max_distance`).
    pub fn over(&self, ray: &Ray, t_far: f64, background: PremultipliedRgba) -> PremultipliedRgba {
        let fog = self.segment(ray, 0.0, t_far);
        fog + (1.0 - fog.w) * background
    }

    /// A volume piece over `[t0, t1]` seen through the fog in front of it
    /// (see the module docs), cut into the pieces
    /// [`conjugation_pieces`] asks for: `piece(k, n)` returns the k-th of n
    /// equal parts of the volume piece, already lit; the parts go to `emit`
    /// conjugated, front to back, until it returns `true`. `absorbs`: whether
    /// the pieces' alpha is an opacity (Sorted), not only a record of their
    /// density (Emissive, MIP).
    pub(crate) fn conjugated_pieces(
        &self,
        ray: &Ray,
        t0: f64,
        t1: f64,
        whole: PremultipliedRgba,
        absorbs: bool,
        mut piece: impl FnMut(usize, usize) -> PremultipliedRgba,
        mut emit: impl FnMut(PremultipliedRgba) -> bool,
    ) {
        let fog_depth = self.optical_depth(ray, t0, t1);
        let volume_depth = if absorbs {
            -(1.0 - whole.w).max(1e-300).ln()
        } else {
            0.0
        };
        let coverage = |part: PremultipliedRgba| if absorbs { part.w } else { 0.0 };
        let count = conjugation_pieces(fog_depth, volume_depth);
        // The lights' part of the fog in front, carried from middle to
        // middle: `lit(0, m) = lit(0, m′) + T(0, m′) lit(m′, m)`.
        let (mut lit, mut lit_to) = (DVec3::ZERO, 0.0);
        for k in 0..count {
            let middle = t0 + (k as f64 + 0.5) / count as f64 * (t1 - t0);
            let part = if count == 1 { whole } else { piece(k, count) };
            if !self.lights.is_empty() {
                lit +=
                    (-self.optical_depth(ray, 0.0, lit_to)).exp() * self.lit(ray, lit_to, middle);
                lit_to = middle;
            }
            let transmittance = (-self.optical_depth(ray, 0.0, middle)).exp();
            // The fog in front, `F` of the map `x ↦ F + T x`.
            let front = (1.0 - transmittance) * self.colour + self.sunlit(ray, 0.0, middle) + lit;
            let fogged = transmittance * part.truncate() + coverage(part) * front;
            if emit(fogged.extend(part.w)) {
                return;
            }
        }
    }
}

/// How many equal parts a volume piece of optical depth `volume_depth` over a
/// stretch of fog of optical depth `fog_depth` is cut into so that conjugating
/// each at its middle errs by at most about 1e-6: the splitting error of one
/// part is about `τ_f τ_v (τ_f + τ_v) / 24` relative (Strang splitting of the
/// two media's affine maps, whose commutator is `τ_f τ_v (c_f − c_v)`), and
/// emission-only pieces (`τ_v = 0`) err by `τ_f² / 24`.
fn conjugation_pieces(fog_depth: f64, volume_depth: f64) -> usize {
    if fog_depth <= 0.0 {
        return 1;
    }
    let error = fog_depth * (fog_depth + volume_depth) * (1.0 + volume_depth) / 24.0;
    (error / 1e-6)
        .sqrt()
        .ceil()
        .clamp(1.0, MAX_CONJUGATION_PIECES) as usize
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec4;

    fn fog(layers: Vec<HeightFogLayer>) -> ReferenceFog {
        ReferenceFog {
            fog: HeightFog::new(layers).unwrap(),
            colour: DVec3::new(0.6, 0.7, 0.8),
            sun: None,
            start_distance: 0.0,
            max_distance: 1e5,
            lights: Vec::new(),
            light_response: LightResponse::default(),
            occluders: Vec::new(),
            clouds: Vec::new(),
            terrain: None,
        }
    }

    fn slab() -> ReferenceFog {
        fog(vec![HeightFogLayer::Constant {
            bottom: 0.0,
            top: 10.0,
            density: 0.05,
        }])
    }

    /// The slab lit by a sun 53° up along +x, which casts no shadows.
    fn sunlit_slab() -> ReferenceFog {
        ReferenceFog {
            sun: Some(FogSunlight {
                direction: DVec3::new(0.6, 0.8, 0.0),
                colour: DVec3::ONE,
                asymmetry: 0.3,
                shadows: false,
            }),
            ..slab()
        }
    }

    /// A ray from `origin` at `elevation` degrees above the horizontal.
    fn ray(origin: DVec3, elevation: f64) -> Ray {
        let e = elevation.to_radians();
        Ray::new(origin, DVec3::new(e.cos(), e.sin(), 0.0)).unwrap()
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-12 * (1.0 + b.abs())
    }

    #[test]
    fn a_constant_layer_at_every_angle_inside_above_and_below() {
        let slab = slab();
        let eye = DVec3::new(0.0, 4.0, 0.0);
        for elevation in [
            -90.0, -60.0, -30.0, -5.0, -0.01, 0.0, 0.01, 5.0, 30.0, 60.0, 90.0,
        ] {
            let ray = ray(eye, elevation);
            let sin = f64::sin(f64::to_radians(elevation));
            // To an opaque point 3 m along the ray (still inside the slab at
            // every angle): ρ t.
            assert!(close(slab.optical_depth(&ray, 0.0, 3.0), 0.05 * 3.0));
            // Sky pixels: to where the ray leaves the slab, or to the
            // largest distance for a level ray.
            let inside = if elevation > 0.0 {
                (6.0 / sin).min(1e5)
            } else if elevation < 0.0 {
                (4.0 / -sin).min(1e5)
            } else {
                1e5
            };
            let sky = slab.optical_depth(&ray, 0.0, f64::INFINITY);
            assert!(close(sky, 0.05 * inside), "{elevation}°: {sky}");
        }
        // From above and below, through the whole slab: ρ · 10 / |sin|.
        for (y, elevation) in [(25.0, -40.0), (-7.0, 20.0), (100.0, -89.0)] {
            let ray = ray(DVec3::new(0.0, y, 0.0), elevation);
            let through = 0.05 * 10.0 / f64::sin(f64::to_radians(elevation)).abs();
            let sky = slab.optical_depth(&ray, 0.0, f64::INFINITY);
            assert!(
                close(sky, through),
                "{y} at {elevation}°: {sky} vs {through}"
            );
        }
        // Level rays above and below see nothing.
        assert_eq!(
            slab.optical_depth(&ray(DVec3::Y * 11.0, 0.0), 0.0, 1e9),
            0.0
        );
        assert_eq!(
            slab.optical_depth(&ray(DVec3::Y * -1.0, 0.0), 0.0, 1e9),
            0.0
        );
    }

    #[test]
    fn the_eye_on_a_layer_boundary() {
        let slab = slab();
        let top = DVec3::Y * 10.0;
        // Down at 30° from the top: the whole slab along 20 m; up: nothing.
        assert!(close(
            slab.optical_depth(&ray(top, -30.0), 0.0, 1e3),
            0.05 * 20.0
        ));
        assert!(close(
            slab.optical_depth(&ray(top, -30.0), 0.0, 8.0),
            0.05 * 8.0
        ));
        assert_eq!(slab.optical_depth(&ray(top, 30.0), 0.0, 1e3), 0.0);
        // A level ray on the boundary counts as inside (the layers are closed
        // intervals), so it is the limit of rays from just below.
        let level = slab.optical_depth(&ray(top, 0.0), 0.0, 50.0);
        let below = slab.optical_depth(&ray(top - DVec3::Y * 1e-9, 0.0), 0.0, 50.0);
        assert!(close(level, below) && close(level, 0.05 * 50.0));
    }

    #[test]
    fn an_exponential_layer_for_level_and_vertical_rays_to_100_km() {
        let (density, falloff, base) = (2e-4, 1.0 / 1200.0, 0.0);
        let fog = fog(vec![HeightFogLayer::Exponential {
            base,
            density,
            falloff,
        }]);
        for altitude in [0.0, 350.0, 4000.0] {
            let at = density * (-falloff * (altitude - base)).exp();
            // Level, to 100 km and to 1 m: ρ(h) L.
            let level = ray(DVec3::new(1e5, altitude, -1e5), 0.0);
            for length in [1.0, 1e3, 1e5] {
                assert!(close(fog.optical_depth(&level, 0.0, length), at * length));
            }
            // Straight up to the largest distance: ρ(h) (1 − e^{−k L}) / k.
            let up = ray(DVec3::new(0.0, altitude, 0.0), 90.0);
            let closed = at * -(-falloff * 1e5f64).exp_m1() / falloff;
            assert!(close(fog.optical_depth(&up, 0.0, f64::INFINITY), closed));
            // Straight down 100 m.
            let down = ray(DVec3::new(0.0, altitude, 0.0), -90.0);
            let closed = at * (falloff * 100.0f64).exp_m1() / falloff;
            assert!(close(fog.optical_depth(&down, 0.0, 100.0), closed));
        }
    }

    #[test]
    fn the_fog_begins_at_its_start_distance_and_colours_by_the_sun() {
        let mut slab = slab();
        slab.start_distance = 40.0;
        let level = ray(DVec3::Y * 5.0, 0.0);
        assert_eq!(slab.optical_depth(&level, 0.0, 30.0), 0.0);
        assert!(close(slab.optical_depth(&level, 0.0, 100.0), 0.05 * 60.0));
        assert!(close(slab.optical_depth(&level, 50.0, 100.0), 0.05 * 50.0));
        // The layer over a background: F + T · background, F = c (1 − T).
        let background = DVec4::new(0.1, 0.2, 0.3, 1.0);
        let t = (-0.05f64 * 60.0).exp();
        let over = slab.over(&level, 100.0, background);
        let expected = slab.colour * (1.0 - t) + t * background.truncate();
        assert!((over.truncate() - expected).abs().max_element() < 1e-12);
        assert!(close(over.w, 1.0));
        // Sunlight: 4π p_HG, 1 on average; (1 + g) / (1 − g)² toward the sun,
        // which sees the ray through the 5 m of the slab above it.
        let sun = DVec3::new(1.0, 1.0, 0.0).normalize();
        slab.sun = Some(FogSunlight {
            direction: sun,
            colour: DVec3::splat(0.5),
            asymmetry: 0.5,
            shadows: false,
        });
        assert!(slab.invalid().is_none());
        slab.start_distance = 0.0;
        let toward = ray(DVec3::Y * 5.0, 45.0);
        let (tau, to_sun) = (0.05 * 5.0 * 2f64.sqrt(), 0.05 * 5.0 / sun.y);
        // Climbing at the sun's elevation: I = τ e^{−s₀}.
        let expected = 0.5 * 1.5 / 0.25 * tau * (-to_sun).exp();
        let sunlit = slab.sunlit(&toward, 0.0, 100.0);
        assert!(
            (sunlit - DVec3::splat(expected)).abs().max_element() < 1e-12,
            "{sunlit}"
        );
        let level = slab.sunlit(&level, 0.0, 100.0);
        let expected =
            (-to_sun).exp() * -(-0.05f64 * 100.0).exp_m1() * henyey_greenstein(0.5, sun.x) * 0.5;
        assert!(
            (level - DVec3::splat(expected)).abs().max_element() < 1e-12,
            "{level}"
        );
        slab.sun = Some(FogSunlight {
            direction: DVec3::new(1.0, -0.2, 0.0),
            ..slab.sun.unwrap()
        });
        assert_eq!(
            slab.sunlit(&toward, 0.0, 100.0),
            DVec3::ZERO,
            "a set sun lights nothing"
        );
    }

    /// A uniform cloud slab over the whole fog dims its sunlight by its
    /// transmittance `e^{−σ d/μ}` (the closed form), one over half of it
    /// (from x = 0 on, whose shadow the sun's slant moves by the slab's
    /// height over its tangent) dims the stretch it shades only.
    #[test]
    fn a_cloud_slab_holds_back_the_sunlight_it_shades() {
        use nebel_core::field::DensityGrid;
        use std::sync::Arc;
        let slab = sunlit_slab();
        let cloud = |min_x: f64| ShadowCaster {
            grid: Arc::new(
                DensityGrid::new(
                    [2, 2, 2],
                    DVec3::new(1e4, 5.0, 1e4),
                    DVec3::new(min_x, 50.0, -5e3),
                    vec![1.0; 8],
                )
                .unwrap(),
            ),
            world_from_local: glam::DAffine3::IDENTITY,
            extinction: 0.1,
        };
        let level = ray(DVec3::new(-100.0, 4.0, 0.0), 0.0);
        let clear = slab.sunlit(&level, 0.0, 200.0);
        let transmittance = (-0.1 * 5.0 / 0.8f64).exp();
        let covered = ReferenceFog {
            clouds: vec![cloud(-5e3)],
            ..slab.clone()
        };
        let dimmed = covered.sunlit(&level, 0.0, 200.0);
        assert!(
            (dimmed - clear * transmittance).abs().max_element() < 1e-9 * clear.x,
            "{dimmed} against {}",
            clear * transmittance
        );
        // The slab from x = 0 on: the sun's line from (x, 4 m) meets its
        // side at the height 4 − 4x/3, so it runs through (55 − 4 + 4x/3)/μ
        // of it for x from −38.25 to −34.5 and through all of it, 5/μ, on.
        // The held-back light by a fine midpoint rule of the closed forms.
        let half = ReferenceFog {
            clouds: vec![cloud(0.0)],
            ..slab.clone()
        };
        let got = half.sunlit(&level, 0.0, 200.0);
        let chord = |x: f64| ((55.0 - 4.0 + 4.0 * x / 3.0) / 0.8).clamp(0.0, 5.0 / 0.8);
        let steps = 400_000;
        let dt = 200.0 / steps as f64;
        let held: f64 = (0..steps)
            .map(|n| {
                let t = (n as f64 + 0.5) * dt;
                let x = t - 100.0;
                let shaded = if x < -38.25 {
                    0.0
                } else {
                    1.0 - (-0.1 * chord(x)).exp()
                };
                0.05 * (-0.05 * t - 0.05 * 6.0 / 0.8).exp() * shaded * dt
            })
            .sum();
        let expected = clear.x - henyey_greenstein(0.3, 0.6) * held;
        assert!(
            (got.x - expected).abs() < 1e-6 * clear.x,
            "{} against {expected}",
            got.x
        );
        assert!(
            got.x > dimmed.x && got.x < 0.99 * clear.x,
            "{got} {dimmed} {clear}"
        );
    }

    /// Shadow heights level at 6 m over a map that ends at x = −100 shade
    /// the slab below 6 m on that part of a falling ray: what is left is the
    /// closed-form sunlight of the rest, seen through the fog before it;
    /// under a cloud slab over everything, that rest is dimmed by its
    /// transmittance and the shaded part is not held back twice (to the
    /// quadrature's 1e-8, which does not cut at the slab's floor).
    #[test]
    fn the_terrain_shadow_leaves_the_sunlight_of_the_stretches_above_it() {
        use nebel_core::field::{DensityGrid, HeightField, TerrainShadow};
        use std::sync::Arc;
        let (slab, sun) = (sunlit_slab(), DVec3::new(0.6, 0.8, 0.0));
        let heights = HeightField::new(
            [2, 2],
            glam::DVec2::new(200.0, 400.0),
            glam::DVec2::new(-200.0, -200.0),
            vec![6.0, 6.0, 6.0, 6.0],
        )
        .unwrap();
        // The map's frame: x from −200 to 0 is world x from −300 to −100.
        let terrain = PlacedTerrainShadow::new(
            Arc::new(TerrainShadow {
                distances: heights.clone(),
                heights,
                sun,
            }),
            glam::DAffine3::from_translation(DVec3::new(100.0, 0.0, 0.0)),
        );
        let shaded = ReferenceFog {
            terrain: Some(terrain),
            ..slab.clone()
        };
        // Falling from (−190, 6.5) at 1.5° down: it crosses 6 m at
        // x = −190 + 0.5/tan 1.5° ≈ −171, then leaves the map at x = −100.
        let falling = ray(DVec3::new(-190.0, 6.5, 0.0), -1.5);
        let dy = falling.direction.y;
        let (cross, leave) = (-0.5 / dy, 90.0 / falling.direction.x);
        let got = shaded.sunlit(&falling, 0.0, 300.0);
        let before = slab.sunlit(&falling, 0.0, cross);
        let after =
            (-slab.optical_depth(&falling, 0.0, leave)).exp() * slab.sunlit(&falling, leave, 300.0);
        let expected = before + after;
        assert!(
            (got - expected).abs().max_element() < 1e-12 * expected.x,
            "{got} against {expected}"
        );
        assert!(got.x < 0.8 * slab.sunlit(&falling, 0.0, 300.0).x);
        let cloud = ShadowCaster {
            grid: Arc::new(
                DensityGrid::new(
                    [2, 2, 2],
                    DVec3::new(1e4, 5.0, 1e4),
                    DVec3::new(-5e3, 50.0, -5e3),
                    vec![1.0; 8],
                )
                .unwrap(),
            ),
            world_from_local: glam::DAffine3::IDENTITY,
            extinction: 0.1,
        };
        let both = ReferenceFog {
            clouds: vec![cloud],
            ..shaded
        };
        let dimmed = both.sunlit(&falling, 0.0, 300.0);
        let transmittance = (-0.1 * 5.0 / 0.8f64).exp();
        assert!(
            (dimmed - expected * transmittance).abs().max_element() < 1e-7 * expected.x,
            "{dimmed} against {}",
            expected * transmittance
        );
    }

    /// A strip 20 m up hides the sun (53° up along +x) from the stretch of a
    /// level ray at 4 m whose sun line crosses it, x + 12 in [−5, 5]: that
    /// stretch's closed form is held back where the sun casts shadows, and
    /// nothing where it does not.
    #[test]
    fn an_occluder_hides_the_sun_from_the_stretch_in_its_shadow() {
        let mut slab = sunlit_slab();
        let sunlight = FogSunlight {
            shadows: true,
            ..slab.sun.unwrap()
        };
        slab.sun = Some(sunlight);
        slab.occluders = vec![Occluder::Rectangle {
            centre: DVec3::new(0.0, 20.0, 0.0),
            half_size: glam::DVec2::new(5.0, 100.0),
        }];
        let level = ray(DVec3::new(-30.0, 4.0, 0.0), 0.0);
        let clear = ReferenceFog {
            occluders: Vec::new(),
            ..slab.clone()
        };
        let expected = clear.sunlit(&level, 0.0, 200.0)
            - (-clear.optical_depth(&level, 0.0, 13.0)).exp() * clear.sunlit(&level, 13.0, 23.0);
        let got = slab.sunlit(&level, 0.0, 200.0);
        assert!(
            (got - expected).abs().max_element() < 1e-9 * expected.x,
            "{got} against {expected}"
        );
        assert!(got.x < 0.95 * clear.sunlit(&level, 0.0, 200.0).x);
        let unshadowed = ReferenceFog {
            sun: Some(FogSunlight {
                shadows: false,
                ..sunlight
            }),
            ..slab
        };
        assert_eq!(
            unshadowed.sunlit(&level, 0.0, 200.0),
            clear.sunlit(&level, 0.0, 200.0)
        );
    }

    /// A fog with a jump (a constant layer) and a smooth falloff, lit by a
    /// point light inside it and a spot light slanting down through it.
    fn lit_fog() -> ReferenceFog {
        let mut fog = fog(vec![
            HeightFogLayer::Constant {
                bottom: 0.0,
                top: 6.0,
                density: 0.08,
            },
            HeightFogLayer::Exponential {
                base: 0.0,
                density: 0.05,
                falloff: 0.2,
            },
        ]);
        let mut spot = LocalLight::from_lumens(
            DVec3::new(8.0, 12.0, -3.0),
            DVec3::new(1.0, 0.8, 0.5),
            4e5,
            30.0,
        );
        spot.cone = Some(nebel_core::local_light::SpotCone::new(
            DVec3::new(0.2, -1.0, 0.3).normalize(),
            0.15,
            0.35,
        ));
        fog.lights = vec![
            LocalLight::from_lumens(DVec3::new(5.0, 3.0, 1.0), DVec3::ONE, 2e5, 12.0),
            spot,
        ];
        fog.light_response = LightResponse {
            asymmetry: 0.5,
            strength: 3.0,
        };
        fog
    }

    /// A ray slanting down through both layers and the spot light's beam.
    fn down_through_the_beam() -> Ray {
        Ray::new(
            DVec3::new(-6.0, 7.0, 0.0),
            DVec3::new(1.0, -0.3, 0.1).normalize(),
        )
        .unwrap()
    }

    #[test]
    fn lights_in_the_fog_match_a_fine_midpoint_integral() {
        let fog = lit_fog();
        for (origin, direction) in [
            (DVec3::new(-5.0, 2.0, 0.5), DVec3::new(1.0, 0.05, 0.0)),
            (DVec3::new(-4.0, 9.0, -2.0), DVec3::new(1.0, -0.6, 0.2)),
            (DVec3::new(5.0, 14.0, 1.2), DVec3::new(0.02, -1.0, 0.0)),
        ] {
            let ray = Ray::new(origin, direction.normalize()).unwrap();
            let (t0, t1) = (0.5, 40.0);
            // ∫ s c ρ e^{−τ(t₀, t)} E 4π p_HG dt by the midpoint rule, straight
            // from the definitions.
            let steps = 400_000;
            let dt = (t1 - t0) / f64::from(steps);
            let mut expected = DVec3::ZERO;
            for i in 0..steps {
                let t = t0 + (f64::from(i) + 0.5) * dt;
                let x = ray.origin + t * ray.direction;
                let rho = fog.fog.density(x.y);
                let transmittance = (-fog.optical_depth(&ray, t0, t)).exp();
                for light in &fog.lights {
                    let cos_theta = (x - light.position).normalize().dot(ray.direction);
                    let toward = Ray::new(x, (light.position - x).normalize()).unwrap();
                    let attenuation =
                        (-fog.optical_depth(&toward, 0.0, x.distance(light.position))).exp();
                    expected += light.illuminance(x)
                        * henyey_greenstein(0.5, cos_theta)
                        * (rho * transmittance * attenuation * dt);
                }
            }
            expected *= fog.colour * 3.0;
            let lit = fog.lit(&ray, t0, t1);
            assert!(expected.max_element() > 1e-3, "{expected}");
            assert!(
                (lit - expected).abs().max_element() <= 1e-5 * expected.max_element(),
                "{lit} against {expected}"
            );
        }
    }

    #[test]
    fn lit_fog_pieces_compose_with_over() {
        let (fog, ray) = (lit_fog(), down_through_the_beam());
        let whole = fog.segment(&ray, 0.0, 50.0);
        let mut composed = DVec4::ZERO;
        for [a, b] in [[0.0, 3.7], [3.7, 11.0], [11.0, 19.5], [19.5, 50.0]] {
            composed += (1.0 - composed.w) * fog.segment(&ray, a, b);
        }
        assert!(whole.truncate().max_element() > 1e-2);
        assert!(
            (whole - composed).abs().max_element() < 1e-9,
            "{whole} {composed}"
        );
        // Without lights the fog is its colour alone.
        let mut unlit = fog.clone();
        unlit.lights.clear();
        let plain = unlit.segment(&ray, 0.0, 50.0);
        assert!(
            (plain.truncate() - fog.colour * plain.w)
                .abs()
                .max_element()
                < 1e-12
        );
    }

    #[test]
    fn a_piece_in_lit_fog_is_conjugated_by_the_fog_in_front_sun_and_lights_included() {
        let (mut fog, ray) = (lit_fog(), down_through_the_beam());
        fog.sun = Some(FogSunlight {
            direction: DVec3::new(0.3, 0.8, -0.2),
            colour: DVec3::new(0.9, 0.8, 0.6),
            asymmetry: 0.6,
            shadows: false,
        });
        assert!(fog.sunlit(&ray, 0.0, 12.0).min_element() > 0.01);
        let (t0, t1) = (2.0, 12.0);
        let whole = DVec4::new(0.2, 0.1, 0.05, 0.5);
        // Equal parts of a uniform piece.
        let part = |n: usize| {
            let alpha = 1.0 - (1.0 - whole.w).powf(1.0 / n as f64);
            (whole.truncate() / whole.w * alpha).extend(alpha)
        };
        let mut emitted = Vec::new();
        fog.conjugated_pieces(
            &ray,
            t0,
            t1,
            whole,
            true,
            |_, n| part(n),
            |fogged| {
                emitted.push(fogged);
                false
            },
        );
        let n = emitted.len();
        assert!(n > 10, "{n} parts");
        for (k, fogged) in emitted.iter().enumerate() {
            let middle = t0 + (k as f64 + 0.5) / n as f64 * (t1 - t0);
            let front = fog.segment(&ray, 0.0, middle);
            let expected = (1.0 - front.w) * part(n).truncate() + part(n).w * front.truncate();
            assert!(
                (fogged.truncate() - expected).abs().max_element() <= 1e-9,
                "part {k}: {fogged} against {expected}"
            );
        }
    }

    #[test]
    fn bad_fog_settings_are_named() {
        let mut bad = slab();
        bad.colour = DVec3::new(f64::NAN, 0.0, 0.0);
        assert!(bad.invalid().unwrap().contains("colour"));
        let mut bad = slab();
        bad.start_distance = -1.0;
        assert!(bad.invalid().unwrap().contains("start_distance"));
        let mut bad = slab();
        bad.max_distance = f64::INFINITY;
        assert!(bad.invalid().unwrap().contains("max_distance"));
        let mut bad = slab();
        bad.sun = Some(FogSunlight {
            direction: DVec3::ZERO,
            colour: DVec3::ONE,
            asymmetry: 0.0,
            shadows: false,
        });
        assert!(bad.invalid().unwrap().contains("sunlight"));
        let mut bad = lit_fog();
        bad.lights[1].range = f64::NAN;
        assert!(bad.invalid().unwrap().contains("range"));
        let mut bad = lit_fog();
        bad.light_response.strength = -1.0;
        assert!(bad.invalid().unwrap().contains("light_response.strength"));
    }
}
