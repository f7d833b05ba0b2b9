//! The stretches of a ray below a terrain or below its shadow: where the ray
//! runs below a bilinear height field (the terrain's heights, or the shadow
//! heights of a [`TerrainShadow`]), exact for the bilinear heights.
//!
//! Inside one cell of the field the bilinear height along a straight line
//! is a quadratic in the ray's parameter, and the ray's own height is
//! linear, so the difference `d(t) = y(t) − h(x(t), z(t))` is a quadratic
//! whose roots are the crossings in that cell. [`PlacedTerrainShadow::shaded`]
//! and [`PlacedHeights::below`] walk the cells the ray's horizontal
//! projection crosses (Amanatides and Woo 1987) between the field's edges
//! and below its highest height, solve each cell's quadratic and join the
//! pieces of neighbouring cells. Outside the field's extent nothing is
//! below it (a terrain's shadow beyond its edge, under a low sun, is not in
//! the map). The fog layers' pass walks the same cells on the GPU; the
//! reference takes a terrain ([`PlacedHeights`]) as an opaque shape that
//! hides the lights (`crate::occluder::Occluder::Terrain`).

use std::sync::Arc;

use glam::{DAffine3, DVec2, DVec3};

use super::{HeightField, TerrainShadow};

/// A terrain's shadow heights placed in the world.
#[derive(Clone, Debug, PartialEq)]
pub struct PlacedTerrainShadow {
    /// The shadow heights, in the terrain's frame.
    pub shadow: Arc<TerrainShadow>,
    /// World space to the terrain's frame, affine (a rigid motion keeps the
    /// heights' meaning).
    pub map_from_world: DAffine3,
    /// The highest shadow height: above it nothing is shaded.
    top: f64,
}

impl PlacedTerrainShadow {
    /// `shadow` placed by `map_from_world`.
    pub fn new(shadow: Arc<TerrainShadow>, map_from_world: DAffine3) -> Self {
        let top = shadow
            .heights
            .heights()
            .iter()
            .copied()
            .fold(f32::MIN, f32::max);
        Self {
            shadow,
            map_from_world,
            top: f64::from(top),
        }
    }

    /// The highest shadow height, in the terrain's frame.
    pub fn top(&self) -> f64 {
        self.top
    }

    /// The stretches of `[t0, t1]` along the ray `origin + t direction`
    /// (world space) whose points lie below the shadow heights, in order,
    /// disjoint and each of positive length (module docs). An affine map
    /// keeps the ray's parameter, so the stretches are in the world ray's
    /// `t`. Empty where the range is empty or not finite.
    pub fn shaded(&self, origin: DVec3, direction: DVec3, (t0, t1): (f64, f64)) -> Vec<(f64, f64)> {
        below(
            &self.shadow.heights,
            self.top,
            &self.map_from_world,
            (origin, direction),
            (t0, t1),
        )
    }
}

/// A terrain's heights placed in the world: an opaque surface seen from
/// above (a ray below it is inside the ground).
#[derive(Clone, Debug, PartialEq)]
pub struct PlacedHeights {
    /// The heights, in the terrain's frame.
    pub heights: Arc<HeightField>,
    /// World space to the terrain's frame, affine.
    pub map_from_world: DAffine3,
    /// The highest height.
    top: f64,
}

impl PlacedHeights {
    /// `heights` placed by `map_from_world`.
    pub fn new(heights: Arc<HeightField>, map_from_world: DAffine3) -> Self {
        let top = heights.heights().iter().copied().fold(f32::MIN, f32::max);
        Self {
            heights,
            map_from_world,
            top: f64::from(top),
        }
    }

    /// The stretches of `[t0, t1]` along the ray `origin + t direction`
    /// (world space) below the heights, as [`PlacedTerrainShadow::shaded`].
    pub fn below(&self, origin: DVec3, direction: DVec3, range: (f64, f64)) -> Vec<(f64, f64)> {
        below(
            &self.heights,
            self.top,
            &self.map_from_world,
            (origin, direction),
            range,
        )
    }
}

/// The stretches of `[t0, t1]` along the world ray `(origin, direction)`
/// below `grid`'s bilinear heights (highest `top`), placed by
/// `map_from_world` (module docs).
fn below(
    grid: &HeightField,
    top: f64,
    map_from_world: &DAffine3,
    (origin, direction): (DVec3, DVec3),
    (t0, t1): (f64, f64),
) -> Vec<(f64, f64)> {
    let origin = map_from_world.transform_point3(origin);
    let direction = map_from_world.transform_vector3(direction);
    let [nx, nz] = grid.dims();
    let last = DVec2::new((nx - 1) as f64, (nz - 1) as f64);
    // The ray in grid units: g(t) = start + t e.
    let start = (DVec2::new(origin.x, origin.z) - grid.origin()) / grid.spacing();
    let e = DVec2::new(direction.x, direction.z) / grid.spacing();
    let Some((t0, t1)) = within_map(start, e, last, origin.y, direction.y, top, (t0, t1)) else {
        return Vec::new();
    };
    let mut shaded = Vec::new();
    let mut open: Option<f64> = None;
    let mut edge = |t: f64, dark: bool, shaded: &mut Vec<(f64, f64)>| match (open, dark) {
        (None, true) => open = Some(t),
        (Some(from), false) => {
            if t > from {
                shaded.push((from, t));
            }
            open = None;
        }
        _ => {}
    };
    let g0 = start + t0 * e;
    // Where the ray leaves the cell across each axis.
    let exit = |cell: DVec2, axis: usize| {
        if e[axis] > 0.0 {
            (cell[axis] + 1.0 - start[axis]) / e[axis]
        } else if e[axis] < 0.0 {
            (cell[axis] - start[axis]) / e[axis]
        } else {
            f64::INFINITY
        }
    };
    let mut cell = DVec2::ZERO;
    for axis in 0..2 {
        let mut c = g0[axis].floor();
        if e[axis] < 0.0 && c == g0[axis] {
            c -= 1.0;
        }
        cell[axis] = c.clamp(0.0, last[axis] - 1.0);
    }
    let mut t = t0;
    loop {
        let next = DVec2::new(exit(cell, 0), exit(cell, 1));
        let end = next.x.min(next.y).min(t1).max(t);
        for (a, dark) in cell_pieces(grid, cell, start, e, origin.y, direction.y, t, end) {
            edge(a, dark, &mut shaded);
        }
        if end >= t1 {
            break;
        }
        let axis = usize::from(next.y < next.x);
        cell[axis] += e[axis].signum();
        if cell[axis] < 0.0 || cell[axis] > last[axis] - 1.0 {
            break;
        }
        t = end;
    }
    edge(t1, false, &mut shaded);
    shaded
}

/// `[t0, t1]` clipped to the map's extent (`g(t)` in `[0, last]` on both
/// axes) and to heights at or below `top`; `None` where nothing is left.
fn within_map(
    start: DVec2,
    e: DVec2,
    last: DVec2,
    y: f64,
    d_y: f64,
    top: f64,
    (mut t0, mut t1): (f64, f64),
) -> Option<(f64, f64)> {
    if d_y > 0.0 {
        t1 = t1.min((top - y) / d_y);
    } else if d_y < 0.0 {
        t0 = t0.max((top - y) / d_y);
    } else if y > top {
        return None;
    }
    for axis in 0..2 {
        if e[axis] == 0.0 {
            if start[axis] < 0.0 || start[axis] > last[axis] {
                return None;
            }
            continue;
        }
        let (a, b) = (-start[axis] / e[axis], (last[axis] - start[axis]) / e[axis]);
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    (t0.is_finite() && t1.is_finite() && t1 > t0).then_some((t0, t1))
}

/// Where each piece of `[ta, tb]` inside `cell` begins, with whether it
/// lies below the bilinear shadow height: the pieces cut at the roots of
/// the cell's quadratic `d(s)`, `s = t − ta` (module docs).
#[allow(clippy::too_many_arguments)]
fn cell_pieces(
    grid: &HeightField,
    cell: DVec2,
    start: DVec2,
    e: DVec2,
    y: f64,
    d_y: f64,
    ta: f64,
    tb: f64,
) -> impl Iterator<Item = (f64, bool)> {
    let (i, j) = (cell.x as usize, cell.y as usize);
    let h = |di: usize, dj: usize| f64::from(grid.height(i + di, j + dj));
    let (a, b, c, k) = (
        h(0, 0),
        h(1, 0) - h(0, 0),
        h(0, 1) - h(0, 0),
        h(1, 1) - h(1, 0) - h(0, 1) + h(0, 0),
    );
    let (p, q) = (start.x + ta * e.x - cell.x, start.y + ta * e.y - cell.y);
    // d(s) = constant + linear s + quadratic s².
    let constant = y + ta * d_y - (a + b * p + c * q + k * p * q);
    let linear = d_y - (b * e.x + c * e.y + k * (p * e.y + q * e.x));
    let quadratic = -k * e.x * e.y;
    let length = tb - ta;
    let mut cuts = [0.0, length, length, length];
    for (n, root) in roots(quadratic, linear, constant)
        .into_iter()
        .flatten()
        .enumerate()
    {
        if root > 0.0 && root < length {
            cuts[n + 1] = root;
        }
    }
    cuts[1..3].sort_by(f64::total_cmp);
    let d = move |s: f64| constant + s * (linear + s * quadratic);
    (0..3).filter_map(move |n| {
        let (s0, s1) = (cuts[n], cuts[n + 1]);
        (s1 > s0).then(|| (ta + s0, d(0.5 * (s0 + s1)) < 0.0))
    })
}

/// The real roots of `a s² + b s + c`, without cancellation (a tiny `a`
/// puts one root far away); a linear or constant one has fewer.
fn roots(a: f64, b: f64, c: f64) -> [Option<f64>; 2] {
    if a == 0.0 {
        return [(b != 0.0).then(|| -c / b), None];
    }
    let discriminant = b * b - 4.0 * a * c;
    if discriminant < 0.0 {
        return [None, None];
    }
    let root = discriminant.sqrt();
    let big = -0.5 * (b + b.signum() * root);
    if big == 0.0 {
        return [Some(0.0), None];
    }
    [Some(big / a), Some(c / big)]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::HeightField;
    use proptest::prelude::*;

    fn placed(dims: [usize; 2], spacing: f64, heights: Vec<f32>, at: DVec3) -> PlacedTerrainShadow {
        let heights = HeightField::new(
            dims,
            DVec2::splat(spacing),
            DVec2::new(-40.0, 15.0),
            heights,
        )
        .unwrap();
        PlacedTerrainShadow::new(
            Arc::new(TerrainShadow {
                distances: heights.clone(),
                heights,
                sun: DVec3::Y,
            }),
            DAffine3::from_translation(-at),
        )
    }

    /// Whether the point `p` (world space) lies below the shadow heights,
    /// inside the map's extent: the point test the stretches must agree
    /// with.
    fn in_shadow(map: &PlacedTerrainShadow, p: DVec3) -> bool {
        let p = map.map_from_world.transform_point3(p);
        let grid = &map.shadow.heights;
        let [nx, nz] = grid.dims();
        let g = (DVec2::new(p.x, p.z) - grid.origin()) / grid.spacing();
        let inside = g.x >= 0.0 && g.y >= 0.0 && g.x <= (nx - 1) as f64 && g.y <= (nz - 1) as f64;
        inside && p.y < grid.sample_grid(g)
    }

    #[test]
    fn level_shadow_heights_shade_the_ray_below_them() {
        // h_s = 12 everywhere over x ∈ [−40, 40], z ∈ [15, 95] (the world
        // shifted by (100, 5, −20)): a ray falling from 40 m crosses 12 m at
        // t = 28 · √2 and leaves the map at x = 40.
        let map = placed([9, 9], 10.0, vec![12.0; 81], DVec3::new(100.0, 5.0, -20.0));
        let origin = DVec3::new(60.0, 45.0, 30.0);
        let direction = DVec3::new(1.0, -1.0, 0.0).normalize();
        let shaded = map.shaded(origin, direction, (0.0, 1e3));
        assert_eq!(shaded.len(), 1);
        let (a, b) = shaded[0];
        assert!((a - 28.0 * 2f64.sqrt()).abs() < 1e-9, "{a}");
        assert!((b - 80.0 * 2f64.sqrt()).abs() < 1e-9, "{b}");
        // Beside the map, above its top and rising: nothing.
        assert!(
            map.shaded(origin + DVec3::Z * 200.0, direction, (0.0, 1e3))
                .is_empty()
        );
        assert!(map.shaded(origin, DVec3::X, (0.0, 1e3)).is_empty());
        assert!(
            map.shaded(origin, DVec3::new(1.0, 0.5, 0.0), (0.0, 1e3))
                .is_empty()
        );
        // A level ray below the top, from outside across the whole map.
        let across = map.shaded(DVec3::new(0.0, 10.0, 60.0), DVec3::X, (0.0, 1e3));
        assert_eq!(across, vec![(60.0, 140.0)]);
        assert!(map.shaded(origin, direction, (f64::NAN, 1.0)).is_empty());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        /// On random maps and rays through a random point near the map,
        /// every point of the ray is shaded exactly when a point test says
        /// so (away from the stretches' ends), and the stretches are
        /// ordered, disjoint and within the range.
        #[test]
        fn the_stretches_are_exactly_where_points_are_shaded(
            dims in prop::array::uniform2(2usize..12),
            values in prop::collection::vec(0.0f32..30.0, 144),
            through in prop::array::uniform3(-0.2f64..1.2),
            direction in prop::array::uniform3(-1.0f64..1.0),
            axis_aligned in 0usize..4,
            (before, after) in (0.0f64..120.0, 1.0f64..120.0),
        ) {
            let heights = values[..dims[0] * dims[1]].to_vec();
            let at = DVec3::new(3.0, -2.0, 60.0);
            let map = placed(dims, 7.0, heights, at);
            let mut direction = DVec3::from_array(direction);
            if axis_aligned < 2 {
                direction[2 * axis_aligned] = 0.0;
            }
            prop_assume!(direction.length() > 1e-3);
            let direction = direction.normalize();
            let extent = 7.0 * DVec3::new((dims[0] - 1) as f64, 0.0, (dims[1] - 1) as f64);
            let through = at + DVec3::new(-40.0, -5.0, 15.0) + DVec3::from_array(through) * (extent + 40.0 * DVec3::Y);
            let origin = through - before * direction;
            let (t0, t1) = (0.5 * before, before + after);
            let shaded = map.shaded(origin, direction, (t0, t1));
            let mut previous = t0;
            for &(a, b) in &shaded {
                prop_assert!(a >= previous && b > a && b <= t1, "{shaded:?}");
                previous = b;
            }
            for n in 0..2000 {
                let t = t0 + (t1 - t0) * (n as f64 + 0.5) / 2000.0;
                let near_an_end = shaded.iter().any(|&(a, b)| (t - a).abs() < 1e-6 || (t - b).abs() < 1e-6);
                if near_an_end {
                    continue;
                }
                let inside = shaded.iter().any(|&(a, b)| t > a && t < b);
                prop_assert_eq!(inside, in_shadow(&map, origin + t * direction), "t = {}", t);
            }
        }
    }
}
