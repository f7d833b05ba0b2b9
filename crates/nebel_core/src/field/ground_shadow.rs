//! Cloud shadows on the ground: the transmittance toward the sun below cloud
//! volumes, on a map over a horizontal plane.
//!
//! A volume's shadow is the light field's (Nes 2008 §2.2.6, Eq. 2.13; §6.1
//! draws it on the ground): `T = e^{−σ ∫ f ds}` toward the sun, `f` the
//! trilinear density, `σ` the volume's shadow extinction per unit of the
//! volume's local frame, the path measured in that frame. Along a straight
//! line `f` is a cubic inside each grid cell, so
//! [`optical_depth_toward`] cuts the ray where it crosses a grid plane and
//! takes Simpson's rule on each piece, which is exact for cubics.
//!
//! [`GroundShadow`] stores `T` at texel centres on the world plane `y = h`,
//! `h` the lowest corner of the casting volumes, over the rectangle their
//! boxes cast along the sun (one texel of margin, where `T = 1`); volumes'
//! depths add. Between the plane and a point below it the air is clear, so a
//! point `p` below `h` takes the map's value where the line from `p` toward
//! the sun crosses the plane ([`GroundShadow::transmittance`], bilinear
//! between texel centres, clamped to the border: what the GPU samples). A
//! point above `h` takes the value at its own projection back onto the plane,
//! which includes cloud between the plane and it, up to the casters' highest
//! corner, above which nothing shades it; [`sun_transmittance`] is
//! the exact value at any point (what the reference takes). The sun lower than
//! [`GroundShadow::MIN_SUN_SINE`] above the horizon casts no map (its shadow
//! would stretch without bound; the ground is nearly unlit then).

use std::sync::Arc;

use glam::{DAffine3, DVec2, DVec3};

use super::DensityGrid;
use crate::pacing::fill_slices;

/// One cloud volume that shades the ground.
#[derive(Clone, Debug, PartialEq)]
pub struct ShadowCaster {
    /// The density, in the volume's local frame.
    pub grid: Arc<DensityGrid>,
    /// The volume's local frame in the world.
    pub world_from_local: DAffine3,
    /// Optical depth per unit length of the local frame at density 1; a
    /// caster with none (≤ 0 or not finite) casts no shadow.
    pub extinction: f64,
}

/// The transmittance toward the sun on a horizontal plane below clouds
/// (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct GroundShadow {
    /// World height `h` of the plane.
    pub height: f64,
    /// World height of the casting volumes' highest corner: above it the
    /// sun is not shaded.
    pub top: f64,
    /// World `(x, z)` of the map's lower corner (not a texel centre).
    pub min: DVec2,
    /// World length of a texel's side.
    pub texel: f64,
    /// Texels along x and z.
    pub size: [usize; 2],
    /// Unit direction toward the sun, world space.
    pub sun: DVec3,
    /// `T` at texel centres, x fastest.
    pub transmittance: Vec<f32>,
}

impl GroundShadow {
    /// The lowest sine of the sun's elevation that casts a map (about 2.9°).
    pub const MIN_SUN_SINE: f64 = 0.05;
    /// Texels along a map's longer side at most.
    pub const MAX_RESOLUTION: usize = 4096;

    /// The shadow of `casters` for the sun in world direction `sun` (toward
    /// the sun), `resolution` texels along the longer side of the map (at
    /// most `resolution` along either side)
    /// (clamped to 3 ..= [`GroundShadow::MAX_RESOLUTION`]), filled on up to
    /// `threads` threads. `None` where nothing casts: no caster with a
    /// shadow and an invertible frame, or the sun lower than
    /// [`GroundShadow::MIN_SUN_SINE`] or not finite.
    pub fn compute(
        casters: &[ShadowCaster],
        sun: DVec3,
        resolution: usize,
        threads: usize,
    ) -> Option<Self> {
        let sun = sun.try_normalize()?;
        if sun.y < Self::MIN_SUN_SINE {
            return None;
        }
        let casting: Vec<Local> = casters.iter().filter_map(|c| Local::new(c, sun)).collect();
        let corners = || casting.iter().flat_map(|c| c.corners);
        let height = corners().map(|p| p.y).reduce(f64::min)?;
        let top = corners().map(|p| p.y).reduce(f64::max)?;
        let along = |p: DVec3| {
            let q = p - sun * ((p.y - height) / sun.y);
            DVec2::new(q.x, q.z)
        };
        let lo = corners().map(along).reduce(DVec2::min)?;
        let hi = corners().map(along).reduce(DVec2::max)?;
        let resolution = resolution.clamp(3, Self::MAX_RESOLUTION);
        let texel = (hi - lo).max_element() / (resolution - 2) as f64;
        if !(texel.is_finite() && texel > 0.0) {
            return None;
        }
        // One texel of margin on each side, where no ray meets a box.
        let inner = ((hi - lo) / texel)
            .ceil()
            .min(DVec2::splat((resolution - 2) as f64));
        let size = inner.as_uvec2() + 2;
        let size = [size.x as usize, size.y as usize];
        let min = lo - texel;
        let mut transmittance = vec![1.0f32; size[0] * size[1]];
        fill_slices(&mut transmittance, size[0], threads, |first_row, rows| {
            for (n, t) in rows.iter_mut().enumerate() {
                let (u, v) = (n % size[0], first_row + n / size[0]);
                let centre = min + (DVec2::new(u as f64, v as f64) + 0.5) * texel;
                let point = DVec3::new(centre.x, height, centre.y);
                let depth: f64 = casting.iter().map(|c| c.optical_depth(point)).sum();
                *t = (-depth).exp() as f32;
            }
        });
        Some(Self {
            height,
            top,
            min,
            texel,
            size,
            sun,
            transmittance,
        })
    }

    /// The transmittance toward the sun at world point `p`, as the GPU
    /// samples it (module docs); 1 outside the map and above [`Self::top`].
    pub fn transmittance(&self, p: DVec3) -> f64 {
        if p.y > self.top {
            return 1.0;
        }
        let q = p + self.sun * ((self.height - p.y) / self.sun.y);
        let uv = (DVec2::new(q.x, q.z) - self.min) / self.texel - 0.5;
        let last = |n: usize| (n - 1) as f64;
        let (x, z) = (
            uv.x.clamp(0.0, last(self.size[0])),
            uv.y.clamp(0.0, last(self.size[1])),
        );
        let (i, j) = (
            (x as usize).min(self.size[0] - 2),
            (z as usize).min(self.size[1] - 2),
        );
        let (fx, fz) = (x - i as f64, z - j as f64);
        let at =
            |di: usize, dj: usize| f64::from(self.transmittance[i + di + (j + dj) * self.size[0]]);
        let row = |dj: usize| at(0, dj) + (at(1, dj) - at(0, dj)) * fx;
        row(0) + (row(1) - row(0)) * fz
    }
}

/// The transmittance toward the sun (unit `sun`, world space) at the world
/// point `p` through `casters`, exact at any height: `e^{−Σ σ ∫ f ds}` from
/// `p` to each box's far side. 1 for a sun too low to cast a map
/// ([`GroundShadow::MIN_SUN_SINE`]), as there is none then.
pub fn sun_transmittance(casters: &[ShadowCaster], sun: DVec3, p: DVec3) -> f64 {
    if sun.y.is_nan() || sun.y < GroundShadow::MIN_SUN_SINE {
        return 1.0;
    }
    let depth: f64 = casters
        .iter()
        .filter_map(|caster| Local::new(caster, sun))
        .map(|caster| caster.optical_depth(p))
        .sum();
    (-depth).exp()
}

/// The part of `[t_a, t_b]` of the ray from `origin` along `direction`
/// (world space) where a point can lie in the shadow of `casters` toward the
/// unit `sun`, or `None`: a superset, the points below the casters' highest
/// corner whose line toward the sun, followed back to the plane of a caster's
/// lowest corner, lands within the bounds of what its box casts on that
/// plane. A point whose line meets the box passes both tests.
pub fn shaded_stretch(
    casters: &[ShadowCaster],
    sun: DVec3,
    origin: DVec3,
    direction: DVec3,
    (t_a, t_b): (f64, f64),
) -> Option<(f64, f64)> {
    if sun.y.is_nan() || sun.y < GroundShadow::MIN_SUN_SINE {
        return None;
    }
    let mut hull: Option<(f64, f64)> = None;
    for caster in casters.iter().filter_map(|caster| Local::new(caster, sun)) {
        let bottom = caster
            .corners
            .iter()
            .map(|c| c.y)
            .fold(f64::INFINITY, f64::min);
        let top = caster
            .corners
            .iter()
            .map(|c| c.y)
            .fold(f64::NEG_INFINITY, f64::max);
        // Followed back along the sun to the plane y = bottom.
        let onto_plane =
            |p: DVec3| DVec2::new(p.x, p.z) - DVec2::new(sun.x, sun.z) * ((p.y - bottom) / sun.y);
        let (low, high) = caster
            .corners
            .iter()
            .fold((DVec2::INFINITY, DVec2::NEG_INFINITY), |(low, high), &c| {
                (low.min(onto_plane(c)), high.max(onto_plane(c)))
            });
        let (mut a, mut b) = (t_a, t_b);
        // Below the top.
        if direction.y > 0.0 {
            b = b.min((top - origin.y) / direction.y);
        } else if direction.y < 0.0 {
            a = a.max((top - origin.y) / direction.y);
        } else if origin.y > top {
            continue;
        }
        // The crossing moves linearly with t.
        let start = onto_plane(origin);
        let rate = onto_plane(origin + direction) - start;
        let mut misses = false;
        for axis in 0..2 {
            if rate[axis] == 0.0 {
                misses |= start[axis] < low[axis] || start[axis] > high[axis];
                continue;
            }
            let (u, v) = (
                (low[axis] - start[axis]) / rate[axis],
                (high[axis] - start[axis]) / rate[axis],
            );
            a = a.max(u.min(v));
            b = b.min(u.max(v));
        }
        if !misses && a < b {
            hull = Some(hull.map_or((a, b), |(lo, hi)| (lo.min(a), hi.max(b))));
        }
    }
    hull
}

/// A caster in its local frame: the sun there, its box's world corners.
struct Local<'a> {
    grid: &'a DensityGrid,
    local_from_world: DAffine3,
    sun: DVec3,
    /// Optical depth per local unit length at density 1.
    extinction: f64,
    corners: [DVec3; 8],
}

impl<'a> Local<'a> {
    fn new(caster: &'a ShadowCaster, sun_world: DVec3) -> Option<Self> {
        let frame = caster.world_from_local;
        if !caster.extinction.is_finite()
            || caster.extinction <= 0.0
            || !frame.is_finite()
            || frame.matrix3.determinant().abs() <= f64::EPSILON
        {
            return None;
        }
        let local_from_world = frame.inverse();
        let sun = local_from_world
            .transform_vector3(sun_world)
            .try_normalize()?;
        let (a, b) = (caster.grid.origin(), caster.grid.max_corner());
        let corners = std::array::from_fn(|n| {
            let pick = |bit: usize, lo: f64, hi: f64| if n >> bit & 1 == 0 { lo } else { hi };
            frame.transform_point3(DVec3::new(
                pick(0, a.x, b.x),
                pick(1, a.y, b.y),
                pick(2, a.z, b.z),
            ))
        });
        Some(Self {
            grid: &caster.grid,
            local_from_world,
            sun,
            extinction: caster.extinction,
            corners,
        })
    }

    fn optical_depth(&self, world: DVec3) -> f64 {
        let from = self.local_from_world.transform_point3(world);
        self.extinction * optical_depth_toward(self.grid, from, self.sun)
    }
}

/// `∫ f ds` from `from` along the unit `direction` to the grid box's far
/// side (both in the grid's frame; 0 for a ray that misses the box): exact
/// for the trilinear density, by Simpson's rule on each piece between grid
/// planes (module docs).
pub fn optical_depth_toward(grid: &DensityGrid, from: DVec3, direction: DVec3) -> f64 {
    let (origin, spacing) = (grid.origin(), grid.spacing());
    // The ray in grid units: point (i, j, k) at (i, j, k).
    let start = (from - origin) / spacing;
    let step = direction / spacing;
    let last = (DVec3::from_array(grid.dims().map(|n| n as f64))) - 1.0;
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for axis in 0..3 {
        let (s, d) = (start[axis], step[axis]);
        if d == 0.0 {
            if !(0.0..=last[axis]).contains(&s) {
                return 0.0;
            }
            continue;
        }
        let (a, b) = ((0.0 - s) / d, (last[axis] - s) / d);
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    if t0.is_nan() || t1.is_nan() || t0 >= t1 {
        return 0.0;
    }
    // The ray from where it enters the box, so the grid planes are found
    // to the precision of the box's own coordinates however far `from` is.
    let start = start + step * t0;
    let length = t1 - t0;
    // The next grid plane each axis crosses after t.
    let next_plane = |axis: usize, t: f64| -> f64 {
        let d = step[axis];
        if d == 0.0 {
            return f64::INFINITY;
        }
        let u = start[axis] + d * t;
        let plane = if d > 0.0 {
            u.floor() + 1.0
        } else {
            u.ceil() - 1.0
        };
        (plane - start[axis]) / d
    };
    let density = |t: f64| grid.sample_grid(start + step * t);
    let mut depth = 0.0;
    let mut t = 0.0;
    // Pieces share their ends: two samples per piece.
    let mut at_t = density(0.0);
    // A ray crosses each plane once: at most that many pieces, the last
    // one to the far side.
    let pieces = grid.dims().iter().sum::<usize>() + 3;
    for piece in 0..pieces {
        let mut end = (0..3)
            .map(|axis| next_plane(axis, t))
            .fold(length, f64::min);
        // A plane met again by rounding: step past it.
        if end <= t {
            end = length.min(t + length * 1e-12);
        }
        if piece + 1 == pieces {
            end = length;
        }
        let at_end = density(end);
        depth += (end - t) / 6.0 * (at_t + 4.0 * density(0.5 * (t + end)) + at_end);
        (t, at_t) = (end, at_end);
        if t >= length {
            break;
        }
    }
    depth
}

#[cfg(test)]
mod tests {
    use glam::DQuat;
    use proptest::prelude::*;

    use super::*;

    /// A grid of `dims` points with densities from `values`, cycled.
    fn grid(dims: [usize; 3], spacing: DVec3, origin: DVec3, values: &[f32]) -> DensityGrid {
        let n = dims.iter().product::<usize>();
        DensityGrid::new(
            dims,
            spacing,
            origin,
            values.iter().copied().cycle().take(n).collect(),
        )
        .unwrap()
    }

    /// `∫ f ds` by the midpoint rule, `steps` steps over the ray's chord.
    fn midpoint(grid: &DensityGrid, from: DVec3, direction: DVec3, steps: usize) -> f64 {
        let (a, b) = (grid.origin(), grid.max_corner());
        let inside = |p: DVec3| p.cmpge(a - 1e-12).all() && p.cmple(b + 1e-12).all();
        let length = 4.0 * (b - a).length() + (from - a).length();
        let dt = length / steps as f64;
        (0..steps)
            .map(|n| from + direction * ((n as f64 + 0.5) * dt))
            .filter(|&p| inside(p))
            .map(|p| grid.sample(p) * dt)
            .sum()
    }

    fn unit(v: [f64; 3]) -> DVec3 {
        DVec3::from_array(v).try_normalize().unwrap_or(DVec3::Y)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// Simpson's rule on the pieces between grid planes is exact for the
        /// trilinear density: it agrees with a fine midpoint rule, whose own
        /// error is below the bound, on random grids, rays and spacings.
        #[test]
        fn the_optical_depth_is_the_integral_of_the_trilinear_density(
            values in prop::collection::vec(0.0f32..=1.0, 60),
            spacing in prop::array::uniform3(0.3f64..2.0),
            from in prop::array::uniform3(-3.0f64..6.0),
            direction in prop::array::uniform3(-1.0f64..1.0),
        ) {
            let g = grid([3, 4, 5], DVec3::from_array(spacing), DVec3::new(0.5, -0.25, 0.0), &values);
            let (from, direction) = (DVec3::from_array(from), unit(direction));
            let exact = optical_depth_toward(&g, from, direction);
            let sampled = midpoint(&g, from, direction, 400_000);
            prop_assert!((exact - sampled).abs() <= 2e-4 * (1.0 + sampled), "{exact} against {sampled}");
        }
    }

    /// A uniform density `c` gives `c` times the chord to the box's side,
    /// along the axes (where the ray runs in grid planes) and obliquely.
    #[test]
    fn a_uniform_grid_gives_the_chord() {
        let g = grid([5, 3, 4], DVec3::new(1.0, 2.0, 0.5), DVec3::ZERO, &[0.4]);
        let cases = [
            (DVec3::new(1.0, 0.0, 1.0), DVec3::Y, 4.0),
            (DVec3::new(2.0, 2.0, 0.5), DVec3::X, 2.0),
            (DVec3::new(4.0, 1.0, 1.5), DVec3::NEG_X, 4.0),
            (DVec3::new(1.0, -1.0, 1.0), DVec3::Y, 4.0),
            (
                DVec3::new(0.0, 0.0, 0.0),
                DVec3::new(1.0, 1.0, 0.0).normalize(),
                4.0 * 2f64.sqrt(),
            ),
            (DVec3::new(1.0, 5.0, 1.0), DVec3::Y, 0.0),
            (DVec3::new(9.0, 1.0, 1.0), DVec3::Y, 0.0),
        ];
        for (from, direction, chord) in cases {
            let depth = optical_depth_toward(&g, from, direction);
            assert!(
                (depth - 0.4 * chord).abs() < 1e-6,
                "{from} {direction}: {depth}, chord {chord}"
            );
        }
    }

    /// From far away a ray still meets every grid plane once: the depth
    /// through a uniform box is its chord to the precision of the box's
    /// coordinates, and from absurdly far it ends, finite.
    #[test]
    fn a_ray_from_far_away_gives_the_chord() {
        let g = grid(
            [5, 3, 5],
            DVec3::new(50.0, 10.0, 50.0),
            DVec3::new(212.0, 600.0, -389.0),
            &[1.0],
        );
        let direction = DVec3::new(0.5, 0.8, -0.33).normalize();
        // The box's centre, on a level through its middle: the chord is the
        // height 20 over the direction's y.
        let centre = DVec3::new(312.0, 610.0, -289.0);
        let chord = 20.0 / direction.y;
        for distance in [1e3, 1e6, 1e9] {
            let depth = optical_depth_toward(&g, centre - direction * distance, direction);
            assert!(
                (depth - chord).abs() < 1e-9 * distance.max(chord),
                "{distance}: {depth}"
            );
        }
        for distance in [1e17, 1e300] {
            let depth = optical_depth_toward(&g, centre - direction * distance, direction);
            assert!(depth.is_finite() && depth >= 0.0, "{distance}: {depth}");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// Every point of a ray that a turned, scaled cloud shades lies in
        /// the shaded stretch, and the stretch is not the whole ray when the
        /// ray passes far from the cloud's shadow.
        #[test]
        fn the_shaded_stretch_holds_every_shaded_point(
            turn in -3.0f64..3.0,
            scale in prop::array::uniform3(0.5f64..3.0),
            centre in prop::array::uniform3(-20.0f64..20.0),
            origin in prop::array::uniform3(-40.0f64..40.0),
            direction in prop::array::uniform3(-1.0f64..1.0),
            sun in prop::array::uniform3(-1.0f64..1.0),
        ) {
            let g = grid([3, 3, 3], DVec3::splat(2.0), DVec3::ZERO, &[1.0, 0.0, 0.5]);
            let casters = [ShadowCaster {
                grid: Arc::new(g),
                world_from_local: DAffine3::from_scale_rotation_translation(
                    DVec3::from_array(scale),
                    DQuat::from_rotation_y(turn) * DQuat::from_rotation_x(0.3 * turn),
                    DVec3::from_array(centre) + DVec3::Y * 30.0,
                ),
                extinction: 1.0,
            }];
            let sun = DVec3::new(sun[0], sun[1].abs() + 0.1, sun[2]).normalize();
            let (origin, direction) = (DVec3::from_array(origin), unit(direction));
            let stretch = shaded_stretch(&casters, sun, origin, direction, (0.0, 200.0));
            for n in 0..4000 {
                let t = 200.0 * (n as f64 + 0.5) / 4000.0;
                if sun_transmittance(&casters, sun, origin + t * direction) < 1.0 {
                    let (a, b) = stretch.unwrap_or((f64::NAN, f64::NAN));
                    prop_assert!(t >= a - 1e-9 && t <= b + 1e-9, "{t} outside {stretch:?}");
                }
            }
        }
    }

    #[test]
    fn a_ray_beside_the_shadow_has_no_shaded_stretch() {
        let g = grid(
            [2, 2, 2],
            DVec3::splat(10.0),
            DVec3::new(0.0, 50.0, 0.0),
            &[1.0],
        );
        let casters = [ShadowCaster {
            grid: Arc::new(g),
            world_from_local: DAffine3::IDENTITY,
            extinction: 1.0,
        }];
        // Straight up: a level ray at 4 m sees the box's shadow over x in
        // [0, 10] only, and a ray along z at x = 100 never.
        let level = shaded_stretch(
            &casters,
            DVec3::Y,
            DVec3::new(-50.0, 4.0, 5.0),
            DVec3::X,
            (0.0, 100.0),
        );
        assert_eq!(level, Some((50.0, 60.0)));
        let beside = shaded_stretch(
            &casters,
            DVec3::Y,
            DVec3::new(100.0, 4.0, -50.0),
            DVec3::Z,
            (0.0, 100.0),
        );
        assert_eq!(beside, None);
        // Above the box's top nothing is shaded.
        let above = shaded_stretch(
            &casters,
            DVec3::Y,
            DVec3::new(-50.0, 70.0, 5.0),
            DVec3::X,
            (0.0, 100.0),
        );
        assert_eq!(above, None);
    }

    /// Under a uniform slab, turned and scaled in the world, the map is the
    /// closed form `e^{−σ c h / cos θ}` (local units) inside the shadow, 1
    /// outside it, and sampled between texel centres from any height below.
    #[test]
    fn a_slab_casts_the_closed_form() {
        let g = grid([9, 3, 9], DVec3::new(1.0, 0.5, 1.0), DVec3::ZERO, &[0.5]);
        let world_from_local = DAffine3::from_scale_rotation_translation(
            DVec3::new(3.0, 2.0, 3.0),
            DQuat::from_rotation_y(0.4),
            DVec3::new(-5.0, 40.0, 2.0),
        );
        let caster = ShadowCaster {
            grid: Arc::new(g),
            world_from_local,
            extinction: 0.8,
        };
        let sun = DVec3::new(0.3, 1.0, -0.2).normalize();
        let map = GroundShadow::compute(std::slice::from_ref(&caster), sun, 128, 2).unwrap();
        assert_eq!(map.height, 40.0);
        assert!((map.top - 42.0).abs() < 1e-12);
        assert!(
            map.size.iter().all(|&n| n <= 128) && map.size.contains(&128),
            "{:?}",
            map.size
        );
        let sun_local = world_from_local
            .inverse()
            .transform_vector3(sun)
            .normalize();
        let closed = (-0.8 * 0.5 * 1.0 / sun_local.y).exp();
        let centre = world_from_local.transform_point3(DVec3::new(4.0, 0.0, 4.0));
        for drop in [0.0, 7.5, 30.0] {
            let below = centre - sun * (drop / sun.y);
            for offset in [
                DVec3::ZERO,
                DVec3::new(1.3, 0.0, -0.7),
                DVec3::new(-2.1, 0.0, 0.9),
            ] {
                let t = map.transmittance(below + offset);
                assert!((t - closed).abs() < 1e-6, "{t} against {closed}");
            }
        }
        let beside = centre + DVec3::new(60.0, -10.0, 0.0);
        assert_eq!(map.transmittance(beside), 1.0);
        for edge in [0, map.size[0] - 1] {
            assert_eq!(map.transmittance[edge], 1.0, "the margin is lit");
        }
    }

    /// At any height the exact transmittance is the slab's closed form over
    /// the part of it above the point: all of it below (where it is the
    /// map's value too), part of it inside, none above; a sun lower than
    /// the maps' lowest casts nothing.
    #[test]
    fn the_transmittance_at_any_height_is_the_cloud_above() {
        let g = grid([9, 3, 9], DVec3::new(1.0, 0.5, 1.0), DVec3::ZERO, &[0.5]);
        let world_from_local = DAffine3::from_scale_rotation_translation(
            DVec3::new(3.0, 2.0, 3.0),
            DQuat::from_rotation_y(0.4),
            DVec3::new(-5.0, 40.0, 2.0),
        );
        let casters = [ShadowCaster {
            grid: Arc::new(g),
            world_from_local,
            extinction: 0.8,
        }];
        let sun = DVec3::new(0.3, 1.0, -0.2).normalize();
        let map = GroundShadow::compute(&casters, sun, 128, 2).unwrap();
        let sun_local = world_from_local
            .inverse()
            .transform_vector3(sun)
            .normalize();
        for (height, above) in [
            (-3.0, 1.0),
            (0.0, 1.0),
            (0.25, 0.75),
            (0.7, 0.3),
            (1.5, 0.0),
        ] {
            let p = world_from_local.transform_point3(DVec3::new(4.0, height, 4.0));
            let closed = (-0.8 * 0.5 * above / sun_local.y).exp();
            let t = sun_transmittance(&casters, sun, p);
            assert!(
                (t - closed).abs() < 1e-9,
                "height {height}: {t} against {closed}"
            );
            if height <= 0.0 || height > 1.0 {
                assert!((map.transmittance(p) - t).abs() < 1e-6);
            }
        }
        let centre = world_from_local.transform_point3(DVec3::new(4.0, -1.0, 4.0));
        assert_eq!(
            sun_transmittance(&casters, DVec3::new(1.0, 0.04, 0.0).normalize(), centre),
            1.0
        );
        assert_eq!(sun_transmittance(&[], sun, centre), 1.0);
    }

    /// Two volumes' depths add: each texel of the map of both is
    /// `e^{−σ₁τ₁ − σ₂τ₂}`, each `τ` taken in its volume's own frame.
    #[test]
    fn two_casters_multiply() {
        let values: Vec<f32> = (0..27).map(|n| (n * 7 % 11) as f32 / 10.0).collect();
        let g = grid([3, 3, 3], DVec3::splat(2.0), DVec3::ZERO, &values);
        let g = Arc::new(g);
        let first = ShadowCaster {
            grid: g.clone(),
            world_from_local: DAffine3::from_translation(DVec3::new(0.0, 10.0, 0.0)),
            extinction: 0.3,
        };
        let second = ShadowCaster {
            world_from_local: DAffine3::from_scale_rotation_translation(
                DVec3::new(1.5, 0.5, 1.0),
                DQuat::from_rotation_x(0.3),
                DVec3::new(1.0, 14.0, 0.5),
            ),
            extinction: 0.7,
            ..first.clone()
        };
        let sun = DVec3::new(-0.2, 1.0, 0.1).normalize();
        let both = GroundShadow::compute(&[first.clone(), second.clone()], sun, 64, 2).unwrap();
        let depth = |c: &ShadowCaster, p: DVec3| {
            let local = c.world_from_local.inverse();
            let direction = local.transform_vector3(sun).normalize();
            c.extinction * optical_depth_toward(&g, local.transform_point3(p), direction)
        };
        let (mut shaded, mut overlapped) = (0, 0);
        for v in 0..both.size[1] {
            for u in 0..both.size[0] {
                let centre = both.min + (DVec2::new(u as f64, v as f64) + 0.5) * both.texel;
                let p = DVec3::new(centre.x, both.height, centre.y);
                let (a, b) = (depth(&first, p), depth(&second, p));
                let t = f64::from(both.transmittance[u + v * both.size[0]]);
                assert!((t - (-a - b).exp()).abs() < 1e-6, "{t} against {a} + {b}");
                shaded += usize::from(a + b > 0.0);
                overlapped += usize::from(a > 0.0 && b > 0.0);
            }
        }
        assert!(
            shaded > 500 && overlapped > 100,
            "{shaded} shaded, {overlapped} by both"
        );
    }

    /// No map where nothing casts: a sun at or below the horizon, a NaN sun,
    /// no extinction, a singular frame.
    #[test]
    fn nothing_casts_no_map() {
        let g = grid([2, 2, 2], DVec3::ONE, DVec3::ZERO, &[1.0]);
        let caster = ShadowCaster {
            grid: Arc::new(g),
            world_from_local: DAffine3::IDENTITY,
            extinction: 1.0,
        };
        assert!(GroundShadow::compute(std::slice::from_ref(&caster), DVec3::Y, 16, 1).is_some());
        for sun in [
            DVec3::X,
            DVec3::new(1.0, 0.01, 0.0),
            DVec3::NEG_Y,
            DVec3::NAN,
            DVec3::ZERO,
        ] {
            assert!(
                GroundShadow::compute(std::slice::from_ref(&caster), sun, 16, 1).is_none(),
                "{sun}"
            );
        }
        for extinction in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let c = ShadowCaster {
                extinction,
                ..caster.clone()
            };
            assert!(
                GroundShadow::compute(&[c], DVec3::Y, 16, 1).is_none(),
                "{extinction}"
            );
        }
        let flat = ShadowCaster {
            world_from_local: DAffine3::from_scale(DVec3::new(1.0, 0.0, 1.0)),
            ..caster.clone()
        };
        assert!(GroundShadow::compute(&[flat], DVec3::Y, 16, 1).is_none());
        assert!(GroundShadow::compute(&[], DVec3::Y, 16, 1).is_none());
    }
}
