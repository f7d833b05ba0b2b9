//! Sunlight in ground fog: single scattering of the sun, dimmed by the fog
//! above each point and cut by the terrain's shadow.
//!
//! Ground fog (Röttger and Ertl 2003 §6) fills a layer over the terrain: over
//! the horizontal position `p` the ground `G(p)` and the thickness `H(p)`,
//! at relative height `u = (y − G)/H` the profile's scalar `s(u)` and the
//! density `ρ(s(u))`. A point sees the sun when it lies above the terrain's
//! shadow height ([`TerrainShadow`]), through
//! the fog between it and the sun, taken as the fog *above* it (the layer
//! locally level): the column `C = H F(u)`, `F(u) = ∫_u^1 ρ(s(u')) du'`
//! ([`FogColumn`], exact), along the slant `1/μ` (`μ` the sine of the sun's
//! elevation), so `T_sun = e^{−H F(u)/μ}`. That is exact for a level fog of
//! constant thickness; where the ground or the thickness changes along the
//! sun's path through the fog (at its shore, under a low sun) it is the fog
//! above the point instead of the fog along that path. Cloud volumes above
//! that cast shadows ([`FogSunlight::clouds`]) dim it further by their
//! transmittance toward the sun, exact for their trilinear density
//! ([`sun_transmittance`], Nes 2008 §6.1).
//!
//! Along a view ray the fog then adds
//!
//! `L = c ⊙ 4π p_HG(θ) ∫ ρ κ T V T_sun dt`
//!
//! (`c` the sunlight relative to the light the transfer function's colour κ
//! stands for, `T` the transmittance to the eye, `V` 1 where the terrain
//! lets the sun through, 0 below its shadow height or where an opaque shape
//! hides the sun ([`FogSunlight::occluders`]), θ between the view ray
//! and the sunlight, constant along the ray). [`FogSunMap`] holds `G`, `H`
//! and the shadow height at the points of one grid, bilinear in between
//! (what the GPU samples); [`FogSunlight::scattered`] integrates `L` over a
//! stretch of a ray, cut where the ray crosses the shadow.

use std::sync::Arc;

use glam::{DAffine3, DVec2, DVec3};

use crate::cell::Ray;
use crate::field::{HeightField, ShadowCaster, TerrainShadow, sun_transmittance};
use crate::local_light::GAUSS_LEGENDRE_3;
use crate::occluder::{Occluder, sun_lit_spans};
use crate::optics::henyey_greenstein;
use crate::pacing::worker_threads;
use crate::transfer::TransferFunction;

/// The fog above a relative height, `F(u) = ∫_u^1 ρ(s(u')) du'` (module
/// docs): `ρ(s(u))` is linear in `u` between the profile's points and the
/// heights where the scalar crosses a control point of the transfer
/// function, so `F` is exact, piecewise quadratic.
#[derive(Clone, Debug, PartialEq)]
pub struct FogColumn {
    /// `(u, ρ, F(u))` at the knots, `u` increasing from 0 to 1.
    knots: Vec<[f64; 3]>,
}

impl FogColumn {
    /// The column of a fog whose scalar over relative height runs through
    /// `profile` `(u, s)` (`u` increasing from 0 to 1, as
    /// `nebel_lod::FogProfile` checks), with the density of
    /// `transfer_function` (already scaled).
    pub fn new(profile: &[[f32; 2]], transfer_function: &TransferFunction) -> Self {
        let mut knots: Vec<[f64; 3]> = Vec::new();
        let mut push = |u: f64, s: f64| {
            if knots.last().is_none_or(|last| u > last[0]) {
                knots.push([u, transfer_function.evaluate(s).rho, 0.0]);
            }
        };
        for pair in profile.windows(2) {
            let ([u0, s0], [u1, s1]) = (pair[0].map(f64::from), pair[1].map(f64::from));
            push(u0, s0);
            let mut crossings: Vec<f64> = transfer_function
                .points()
                .iter()
                .map(|point| f64::from(point.s))
                .filter(|s| (s - s0) * (s - s1) < 0.0)
                .map(|s| u0 + (u1 - u0) * (s - s0) / (s1 - s0))
                .collect();
            crossings.sort_by(f64::total_cmp);
            for u in crossings {
                push(u, s0 + (s1 - s0) * (u - u0) / (u1 - u0));
            }
            push(u1, s1);
        }
        for k in (0..knots.len().saturating_sub(1)).rev() {
            let (a, b) = (knots[k], knots[k + 1]);
            knots[k][2] = b[2] + 0.5 * (b[0] - a[0]) * (a[1] + b[1]);
        }
        Self { knots }
    }

    /// `F(u)`, `u` clamped to [0, 1].
    pub fn above(&self, u: f64) -> f64 {
        let u = if u.is_nan() { 0.0 } else { u.clamp(0.0, 1.0) };
        let upper = self.knots.partition_point(|knot| knot[0] <= u);
        if upper == 0 || upper == self.knots.len() {
            return self
                .knots
                .get(upper.min(self.knots.len() - 1))
                .map_or(0.0, |k| k[2]);
        }
        let ([ua, ra, _], [ub, rb, fb]) = (self.knots[upper - 1], self.knots[upper]);
        let rho = ra + (rb - ra) * (u - ua) / (ub - ua);
        fb + 0.5 * (ub - u) * (rho + rb)
    }

    /// `F` at `n` equal steps from 0 to 1 (`n` ≥ 2): the GPU's table, read
    /// linearly in between.
    pub fn table(&self, n: usize) -> Vec<f32> {
        let n = n.max(2);
        (0..n)
            .map(|k| self.above(k as f64 / (n - 1) as f64) as f32)
            .collect()
    }
}

/// The ground, the fog's thickness and the terrain's shadow height at the
/// points of one grid, in the terrain's frame, with the fog's column
/// (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct FogSunMap {
    /// The shadow height and the sun, in the terrain's frame.
    pub shadow: TerrainShadow,
    /// `G` at the shadow's points.
    pub ground: HeightField,
    /// `H` at the shadow's points.
    pub thickness: HeightField,
    /// `F`.
    pub column: FogColumn,
}

impl FogSunMap {
    /// The most points along either side of a map a ground fog builds (a
    /// larger terrain is sampled bilinearly at fewer).
    pub const MAX_POINTS: usize = TerrainShadow::MAX_POINTS;

    /// The map of a fog of `thickness` over `ground` (each sampled
    /// bilinearly) for the sun in direction `sun` (toward it, the terrain's
    /// frame), at `points` grid points along x and z over the ground's
    /// extent ([`TerrainShadow::compute`]), on up to `threads` threads.
    /// `None` where the sun casts no shadow map (too low, or not finite):
    /// the fog is then unlit by it.
    pub fn compute(
        ground: &HeightField,
        thickness: &HeightField,
        column: FogColumn,
        sun: DVec3,
        points: [usize; 2],
        threads: usize,
    ) -> Option<Self> {
        let shadow = TerrainShadow::compute(ground, sun, points, threads)?;
        let resampled = |field: &HeightField| {
            let grid = &shadow.heights;
            let [nx, nz] = grid.dims();
            let values = (0..nx * nz)
                .map(|n| {
                    let at = DVec2::new((n % nx) as f64, (n / nx) as f64);
                    field.sample(grid.origin() + at * grid.spacing()) as f32
                })
                .collect();
            HeightField::new(grid.dims(), grid.spacing(), grid.origin(), values).ok()
        };
        Some(Self {
            ground: resampled(ground)?,
            thickness: resampled(thickness)?,
            column,
            shadow,
        })
    }

    /// The map a ground fog draws with: `thickness` one value per point of
    /// `ground`, the fog's `profile` `(u, s)` and its (scaled) transfer
    /// function, at the ground's points up to [`FogSunMap::MAX_POINTS`] a
    /// side, on every core a build may use
    /// ([`worker_threads`]). `None` as
    /// [`FogSunMap::compute`], or where `thickness` does not number the
    /// ground's points.
    pub fn of_fog(
        ground: &HeightField,
        thickness: &[f32],
        profile: &[[f32; 2]],
        transfer_function: &TransferFunction,
        sun: DVec3,
    ) -> Option<Self> {
        let thickness = HeightField::new(
            ground.dims(),
            ground.spacing(),
            ground.origin(),
            thickness.to_vec(),
        )
        .ok()?;
        let points = ground.dims().map(|n| n.min(Self::MAX_POINTS));
        let column = FogColumn::new(profile, transfer_function);
        Self::compute(ground, &thickness, column, sun, points, worker_threads())
    }

    /// The fog's optical depth toward the sun at `p` (the terrain's frame),
    /// `H F(u) / μ`; `None` below the terrain's shadow height.
    pub fn sun_depth(&self, p: DVec3) -> Option<f64> {
        let xz = DVec2::new(p.x, p.z);
        if p.y < self.shadow.heights.sample(xz) {
            return None;
        }
        let thickness = self.thickness.sample(xz);
        if thickness <= 0.0 {
            return Some(0.0);
        }
        let u = (p.y - self.ground.sample(xz)) / thickness;
        Some(thickness * self.column.above(u) / self.shadow.sun.y)
    }

    /// Per grid point, `(shadow height, G, H, t*)` (`t*` the distance of
    /// the shadow's caster, [`TerrainShadow::distances`]), x fastest: the
    /// GPU's texels.
    pub fn texels(&self) -> Vec<[f32; 4]> {
        let shadow = self.shadow.heights.heights();
        let (ground, thickness) = (self.ground.heights(), self.thickness.heights());
        let distances = self.shadow.distances.heights();
        (0..shadow.len())
            .map(|n| [shadow[n], ground[n], thickness[n], distances[n]])
            .collect()
    }
}

/// The sun that lights a ground fog (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct FogSunlight {
    /// The fog's map, in the terrain's frame.
    pub map: Arc<FogSunMap>,
    /// World space to the terrain's frame (a rigid motion).
    pub map_from_world: DAffine3,
    /// Unit direction toward the sun, world space.
    pub direction: DVec3,
    /// The sunlight relative to the light κ stands for, linear RGB.
    pub colour: DVec3,
    /// The Henyey-Greenstein asymmetry `g`, in (−1, 1).
    pub asymmetry: f64,
    /// The cloud volumes whose shadow dims the sun in the fog (none: no
    /// clouds).
    pub clouds: Vec<ShadowCaster>,
    /// Opaque shapes that hide the sun from the fog, a sun that casts
    /// shadows (Bevy's shadow map of it; none: only the terrain shades it).
    pub occluders: Vec<Occluder>,
}

/// Sub-intervals of a stretch in [`FogSunlight::scattered`]: each takes
/// [`GAUSS_LEGENDRE_3`] on either side of a crossing of the shadow.
const INTERVALS: usize = 32;

/// The world length of a unit of height in the frame `map_from_world`
/// maps into: a scaled terrain's fog column is that much longer, in the
/// density's world units.
pub fn vertical_scale(map_from_world: &DAffine3) -> f64 {
    map_from_world.matrix3.inverse().y_axis.length()
}

impl FogSunlight {
    /// `e^{−H F(u)/μ}` at the world point `p` (`H` in world units), times
    /// the clouds' transmittance toward the sun; 0 in the terrain's shadow.
    pub fn transmittance(&self, p: DVec3) -> f64 {
        let scale = vertical_scale(&self.map_from_world);
        let fog = self
            .map
            .sun_depth(self.map_from_world.transform_point3(p))
            .map_or(0.0, |depth| (-depth * scale).exp());
        if fog == 0.0 || self.clouds.is_empty() {
            return fog;
        }
        fog * sun_transmittance(&self.clouds, self.direction, p)
    }

    /// `c ⊙ 4π p_HG(θ) ∫ f(t) V T_sun dt` over `[t_a, t_b]` along the unit
    /// ray `direction` from `origin` (world space), `f` the medium's weight
    /// (density times colour times the transmittance to the eye): composite
    /// Gauss-Legendre over equal sub-intervals, each cut where the ray
    /// crosses the terrain's shadow (found by bisection), so the integral
    /// converges as `f` and `T_sun` are smooth; only over the stretches
    /// the [`FogSunlight::occluders`] leave lit ([`sun_lit_spans`]).
    pub fn scattered(
        &self,
        origin: DVec3,
        direction: DVec3,
        (t_a, t_b): (f64, f64),
        mut f: impl FnMut(f64) -> DVec3,
    ) -> DVec3 {
        if t_b.partial_cmp(&t_a) != Some(std::cmp::Ordering::Greater) {
            return DVec3::ZERO;
        }
        let Some(ray) = Ray::new(origin, direction) else {
            return DVec3::ZERO;
        };
        let sum = sun_lit_spans(&self.occluders, self.direction, &ray, (t_a, t_b))
            .into_iter()
            .map(|span| self.scattered_past_terrain(&ray, span, &mut f))
            .sum::<DVec3>();
        let phase = henyey_greenstein(self.asymmetry, direction.dot(self.direction));
        self.colour * phase * sum
    }

    /// `∫ f(t) V T_sun dt` over `[t_a, t_b]` (see [`FogSunlight::scattered`]).
    fn scattered_past_terrain(
        &self,
        ray: &Ray,
        (t_a, t_b): (f64, f64),
        mut f: impl FnMut(f64) -> DVec3,
    ) -> DVec3 {
        let (origin, direction) = (ray.origin, ray.direction);
        let lit = |t: f64| {
            self.map
                .sun_depth(self.map_from_world.transform_point3(origin + t * direction))
                .is_some()
        };
        let mut gauss = |a: f64, b: f64| {
            GAUSS_LEGENDRE_3
                .iter()
                .fold(DVec3::ZERO, |sum, (node, weight)| {
                    let t = 0.5 * (a + b) + 0.5 * (b - a) * node;
                    sum + f(t)
                        * (0.5 * (b - a) * weight * self.transmittance(origin + t * direction))
                })
        };
        let step = (t_b - t_a) / INTERVALS as f64;
        let mut sum = DVec3::ZERO;
        for k in 0..INTERVALS {
            let (a, b) = (t_a + step * k as f64, t_a + step * (k + 1) as f64);
            let (lit_a, lit_b) = (lit(a), lit(b));
            if lit_a == lit_b {
                sum += gauss(a, b);
                continue;
            }
            let (mut lo, mut hi) = (a, b);
            for _ in 0..48 {
                let mid = 0.5 * (lo + hi);
                if lit(mid) == lit_a {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            sum += gauss(a, lo) + gauss(hi, b);
        }
        sum
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::DensityGrid;
    use crate::transfer::{ControlPoint, TransferFunction};
    use proptest::prelude::*;

    fn ramp(rho: &[(f32, f32)]) -> TransferFunction {
        TransferFunction::new(
            rho.iter()
                .map(|&(s, rho)| ControlPoint {
                    s,
                    kappa: [1.0; 3],
                    rho,
                })
                .collect::<Vec<_>>(),
        )
        .unwrap()
    }

    fn flat(dims: [usize; 2], spacing: f64, value: f32) -> HeightField {
        HeightField::new(
            dims,
            DVec2::splat(spacing),
            DVec2::ZERO,
            vec![value; dims[0] * dims[1]],
        )
        .unwrap()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// `F` is the integral of the density over relative height: against
        /// a fine midpoint rule, on random profiles and transfer functions.
        #[test]
        fn the_column_is_the_integral_of_the_density_above(
            interior in prop::collection::vec((0.02f32..0.98, 0.0f32..=1.0), 0..4),
            ends in prop::array::uniform2(0.0f32..=1.0),
            points in prop::collection::vec((0.0f32..=1.0, 0.0f32..2.0), 1..5),
            u in 0.0f64..=1.0,
        ) {
            let mut profile = vec![[0.0, ends[0]]];
            let mut interior = interior;
            interior.sort_by(|a, b| a.0.total_cmp(&b.0));
            interior.dedup_by(|a, b| a.0 - b.0 < 0.01);
            profile.extend(interior.iter().map(|&(u, s)| [u, s]));
            profile.push([1.0, ends[1]]);
            let mut points = points;
            points.sort_by(|a, b| a.0.total_cmp(&b.0));
            points.dedup_by(|a, b| a.0 == b.0);
            let tf = ramp(&points);
            let column = FogColumn::new(&profile, &tf);
            let scalar = |u: f64| {
                let k = profile.partition_point(|p| f64::from(p[0]) <= u).clamp(1, profile.len() - 1);
                let ([u0, s0], [u1, s1]) = (profile[k - 1].map(f64::from), profile[k].map(f64::from));
                s0 + (s1 - s0) * (u - u0) / (u1 - u0)
            };
            let steps = 200_000;
            let h = (1.0 - u) / steps as f64;
            let sampled: f64 = (0..steps)
                .map(|k| tf.evaluate(scalar(u + (k as f64 + 0.5) * h)).rho * h)
                .sum();
            let exact = column.above(u);
            prop_assert!((exact - sampled).abs() <= 1e-6 * (1.0 + sampled), "{exact} against {sampled}");
        }
    }

    #[test]
    fn a_level_fog_dims_the_sun_by_the_closed_form_of_its_column() {
        // ρ = 2 (1 − u) over the default profile: F(u) = (1 − u)², 20 m of
        // fog on a ground at 5 m, the sun 30° up: depth 20 (1 − u)² / 0.5.
        let tf = ramp(&[(0.0, 0.0), (1.0, 2.0)]);
        let column = FogColumn::new(&[[0.0, 1.0], [1.0, 0.0]], &tf);
        let sun = DVec3::new(3f64.sqrt() / 2.0, 0.5, 0.0);
        let map = FogSunMap::compute(
            &flat([5, 5], 10.0, 5.0),
            &flat([5, 5], 10.0, 20.0),
            column,
            sun,
            [5, 5],
            1,
        )
        .unwrap();
        for u in [0.0, 0.25, 0.5, 0.9, 1.0] {
            let depth = map
                .sun_depth(DVec3::new(13.0, 5.0 + 20.0 * u, 27.0))
                .unwrap();
            let expected = 20.0 * (1.0 - u) * (1.0 - u) / 0.5;
            assert!(
                (depth - expected).abs() < 1e-9 * (1.0 + expected),
                "u {u}: {depth} against {expected}"
            );
        }
        // Above the fog, clear; below the ground, in the ground's shadow.
        assert_eq!(map.sun_depth(DVec3::new(13.0, 40.0, 27.0)), Some(0.0));
        assert_eq!(map.sun_depth(DVec3::new(13.0, 4.0, 27.0)), None);
        let texel = map.texels()[7];
        assert_eq!(texel, [5.0, 5.0, 20.0, 0.0]);
        assert_eq!(map.column.table(3), vec![1.0, 0.25, 0.0]);
    }

    #[test]
    fn a_level_ray_through_uniform_fog_scatters_the_closed_form_and_a_wall_or_a_cloud_shades_part()
    {
        // A uniform fog (F(u) = 1 − u times ρ = 0.1) of 10 m on flat ground,
        // a level ray at 4 m: T_sun = e^{−0.1 · 6 / μ}, constant along it.
        let tf = ramp(&[(0.0, 0.1), (1.0, 0.1)]);
        let column = FogColumn::new(&[[0.0, 1.0], [1.0, 0.0]], &tf);
        let sun = DVec3::new(0.6, 0.8, 0.0);
        let ground = flat([41, 3], 1.0, 0.0);
        let map = FogSunMap::compute(
            &ground,
            &flat([41, 3], 1.0, 10.0),
            column.clone(),
            sun,
            [41, 3],
            1,
        )
        .unwrap();
        let sunlight = FogSunlight {
            map: Arc::new(map),
            map_from_world: DAffine3::IDENTITY,
            direction: sun,
            colour: DVec3::new(1.0, 0.5, 0.25),
            asymmetry: 0.0,
            clouds: Vec::new(),
            occluders: Vec::new(),
        };
        let (origin, direction) = (DVec3::new(0.0, 4.0, 1.0), DVec3::X);
        let sigma = 0.1;
        let f = |t: f64| DVec3::splat(sigma * (-sigma * t).exp());
        let got = sunlight.scattered(origin, direction, (2.0, 30.0), f);
        let t_sun = (-0.1 * 6.0 / 0.8f64).exp();
        let expected = ((-sigma * 2.0f64).exp() - (-sigma * 30.0f64).exp()) * t_sun;
        let error = (got - DVec3::new(1.0, 0.5, 0.25) * expected)
            .abs()
            .max_element();
        // (The control point's ρ is an f32.)
        assert!(error < 1e-7 * expected, "{got} against {expected}");
        // The same terrain scaled by 2: the point at twice the height in
        // a column twice as tall (in world units) sees the sun through twice
        // the fog.
        let scaled = FogSunlight {
            map_from_world: DAffine3::from_scale(DVec3::splat(0.5)),
            ..sunlight.clone()
        };
        let depth: f64 = 0.1 * 6.0 / 0.8;
        assert!(
            (scaled.transmittance(DVec3::new(20.0, 8.0, 2.0)) - (-2.0 * depth).exp()).abs() < 1e-7
        );
        assert!((sunlight.transmittance(DVec3::new(10.0, 4.0, 1.0)) - (-depth).exp()).abs() < 1e-7);
        // A 12 m wall at x = 38..40 (toward the sun, which climbs 4/3 per
        // metre): it shades the ray at 4 m from x = 38 − 6 = 32 on.
        let mut heights = vec![0.0f32; 41 * 3];
        for j in 0..3 {
            heights[38 + 41 * j] = 12.0;
            heights[39 + 41 * j] = 12.0;
            heights[40 + 41 * j] = 12.0;
        }
        let walled = HeightField::new([41, 3], DVec2::ONE, DVec2::ZERO, heights).unwrap();
        let map = FogSunMap::compute(&walled, &flat([41, 3], 1.0, 10.0), column, sun, [41, 3], 1)
            .unwrap();
        let shaded = FogSunlight {
            map: Arc::new(map),
            ..sunlight.clone()
        };
        // The wall's foot rises from 0 at x = 37 to 12 at 38: the shadow
        // line from there, h = 12 − (38 − x) · 4/3, passes 4 m at x = 32.
        let got = shaded.scattered(origin, direction, (2.0, 36.0), f);
        let expected = ((-sigma * 2.0f64).exp() - (-sigma * 32.0f64).exp()) * t_sun;
        assert!(
            (got.x - expected).abs() < 1e-7 * expected,
            "{} against {expected}",
            got.x
        );
        // A box 12 to 14 m up over x in [20, 23]: the sun's line from (x,
        // 4 m) is 12 to 14 m up from x + 6 to x + 7.5, so the box hides
        // the sun from x = 20 − 7.5 = 12.5 to 23 − 6 = 17.
        let boxed = FogSunlight {
            occluders: vec![Occluder::Box {
                min: DVec3::new(20.0, 12.0, -5.0),
                max: DVec3::new(23.0, 14.0, 5.0),
            }],
            ..sunlight.clone()
        };
        let got = boxed.scattered(origin, direction, (2.0, 30.0), f);
        let lit = |a: f64, b: f64| ((-sigma * a).exp() - (-sigma * b).exp()) * t_sun;
        let expected = lit(2.0, 12.5) + lit(17.0, 30.0);
        assert!(
            (got.x - expected).abs() < 1e-7 * expected,
            "{} against {expected}",
            got.x
        );
        // A uniform cloud slab of density 1 from 20 to 25 m, σ = 0.2, over
        // the whole ray: the sun reaches the fog through 5/μ of it.
        let slab = |min_x: f64| ShadowCaster {
            grid: Arc::new(
                DensityGrid::new(
                    [2, 2, 2],
                    DVec3::new(200.0, 5.0, 200.0),
                    DVec3::new(min_x, 20.0, -100.0),
                    vec![1.0; 8],
                )
                .unwrap(),
            ),
            world_from_local: DAffine3::IDENTITY,
            extinction: 0.2,
        };
        let clouded = FogSunlight {
            clouds: vec![slab(-100.0)],
            ..sunlight.clone()
        };
        let cloud = (-0.2 * 5.0 / 0.8f64).exp();
        let got = clouded.scattered(origin, direction, (2.0, 30.0), f);
        let expected = ((-sigma * 2.0f64).exp() - (-sigma * 30.0f64).exp()) * t_sun * cloud;
        assert!(
            (got.x - expected).abs() < 1e-7 * expected,
            "{} against {expected}",
            got.x
        );
        // A slab from x = 20 on: the sun's line from (x, 4 m) runs through
        // it from x + 12 to x + 15.75, so it dims the fog from x = 4.25 on,
        // fully from x = 8.
        let edge = FogSunlight {
            clouds: vec![slab(20.0)],
            ..sunlight
        };
        for (x, inside) in [(3.0, 0.0), (6.0, 1.75 / 3.75), (9.0, 1.0)] {
            let p = DVec3::new(x, 4.0, 1.0);
            let expected = (-depth - 0.2 * 5.0 / 0.8 * inside).exp();
            assert!((edge.transmittance(p) - expected).abs() < 1e-7, "{x}");
        }
    }
}
