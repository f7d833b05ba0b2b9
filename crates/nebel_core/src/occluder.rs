//! Opaque boxes, spheres, horizontal rectangles and terrains: where a ray
//! first meets them, and which stretches of a ray they hide from a light
//! (the shadow a point or spot light, or the sun, casts into a medium, for
//! the CPU reference).
//!
//! A point `x` sees a light at `p` when no occluder meets the segment from
//! `x` to `p`, and the sun when none meets the ray from `x` toward it; a
//! point inside a box or sphere, or below a terrain, sees nothing, as a
//! shadow map has it. A terrain is its bilinear heights, met exactly
//! ([`PlacedHeights::below`]). Along a ray the visibility is piecewise constant:
//! [`lit_spans`] finds where it changes by sampling [`SHADOW_SAMPLES`]
//! equal steps and bisecting each change to the precision of f64, so a
//! shadow (or a gap in one) shorter than a step may be missed.

use glam::{DVec2, DVec3};

use crate::cell::Ray;
use crate::field::PlacedHeights;

/// The equal steps in which [`lit_spans`] samples a stretch of a ray.
pub const SHADOW_SAMPLES: u32 = 256;

/// The farthest a terrain is walked along a ray: finite, so that a
/// vertical ray's one cell ends.
const TERRAIN_REACH: f64 = f64::MAX / 4.0;

/// Bisections of a change of visibility between two samples: the crossing
/// to 2⁻⁶⁰ of the step.
const BISECTIONS: u32 = 60;

/// An opaque shape.
#[derive(Clone, Debug, PartialEq)]
pub enum Occluder {
    /// A horizontal rectangle at `centre.y`, `half_size` its half extents
    /// along x and z.
    Rectangle {
        /// Its centre, world units.
        centre: DVec3,
        /// Half its extent along x and z.
        half_size: DVec2,
    },
    /// An axis-aligned box.
    Box {
        /// Its lowest corner.
        min: DVec3,
        /// Its highest corner.
        max: DVec3,
    },
    /// A sphere.
    Sphere {
        /// Its centre.
        centre: DVec3,
        /// Its radius, > 0.
        radius: f64,
    },
    /// A terrain's surface, seen from above: a ray below it is inside.
    Terrain(PlacedHeights),
}

impl Occluder {
    /// Whether it meets `ray` nearer than `distance` (at once for an origin
    /// inside a box or sphere, or below a terrain).
    pub fn meets(&self, ray: &Ray, distance: f64) -> bool {
        match self {
            Occluder::Terrain(terrain) => !terrain
                .below(
                    ray.origin,
                    ray.direction,
                    (0.0, distance.min(TERRAIN_REACH)),
                )
                .is_empty(),
            _ => self.hit(ray).is_some_and(|t| t < distance),
        }
    }

    /// Distance along `ray` to its first surface in front of the origin
    /// (the exit for an origin inside a box or sphere).
    pub fn hit(&self, ray: &Ray) -> Option<f64> {
        match *self {
            Occluder::Terrain(ref terrain) => {
                // Where the first stretch below begins, or ends for an
                // origin below the surface.
                let (from, to) = *terrain
                    .below(ray.origin, ray.direction, (0.0, TERRAIN_REACH))
                    .first()?;
                Some(if from > 0.0 { from } else { to })
            }
            Occluder::Rectangle { centre, half_size } => {
                let t = (centre.y - ray.origin.y) / ray.direction.y;
                let point = ray.origin + t * ray.direction;
                let inside = (point.x - centre.x).abs() <= half_size.x
                    && (point.z - centre.z).abs() <= half_size.y;
                (t.is_finite() && t > 0.0 && inside).then_some(t)
            }
            Occluder::Box { min, max } => {
                let inverse = ray.direction.recip();
                let a = (min - ray.origin) * inverse;
                let b = (max - ray.origin) * inverse;
                let entry = a.min(b).max_element();
                let exit = a.max(b).min_element();
                let t = if entry > 0.0 { entry } else { exit };
                (entry <= exit && t > 0.0).then_some(t)
            }
            Occluder::Sphere { centre, radius } => {
                let offset = ray.origin - centre;
                let b = offset.dot(ray.direction);
                let discriminant = b * b - (offset.length_squared() - radius * radius);
                if discriminant < 0.0 {
                    return None;
                }
                let root = discriminant.sqrt();
                [-b - root, -b + root].into_iter().find(|t| *t > 0.0)
            }
        }
    }
}

/// Whether one of `occluders` hides `light` from `point` (meets the segment
/// between them).
pub fn hides(occluders: &[Occluder], point: DVec3, light: DVec3) -> bool {
    let distance = point.distance(light);
    let Some(ray) = Ray::new(point, light - point) else {
        return false;
    };
    occluders
        .iter()
        .any(|occluder| occluder.meets(&ray, distance))
}

/// The stretches of `[t_a, t_b]` along `ray` from which `light` is seen past
/// `occluders` (see the module docs), in order; the whole stretch without
/// occluders.
pub fn lit_spans(
    occluders: &[Occluder],
    light: DVec3,
    ray: &Ray,
    range: (f64, f64),
) -> Vec<(f64, f64)> {
    seen_spans(occluders, ray, range, |x| hides(occluders, x, light))
}

/// Whether one of `occluders` hides the sun, in the unit direction `sun`
/// (toward it), from `point`.
pub fn hides_sun(occluders: &[Occluder], point: DVec3, sun: DVec3) -> bool {
    Ray::new(point, sun).is_some_and(|ray| occluders.iter().any(|o| o.meets(&ray, f64::MAX)))
}

/// The stretches of `[t_a, t_b]` along `ray` from which the sun, in the
/// direction `sun`, is seen past `occluders` (as [`lit_spans`]).
pub fn sun_lit_spans(
    occluders: &[Occluder],
    sun: DVec3,
    ray: &Ray,
    range: (f64, f64),
) -> Vec<(f64, f64)> {
    seen_spans(occluders, ray, range, |x| hides_sun(occluders, x, sun))
}

/// The stretches of `range` along `ray` whose points `hidden` does not
/// hold for: the whole range without occluders, else [`spans_where`].
fn seen_spans(
    occluders: &[Occluder],
    ray: &Ray,
    range: (f64, f64),
    hidden: impl Fn(DVec3) -> bool,
) -> Vec<(f64, f64)> {
    if occluders.is_empty() {
        return whole(range);
    }
    spans_where(range, |t| !hidden(ray.origin + t * ray.direction))
}

/// `[t_a, t_b]` as the one span, or none where it is empty.
fn whole((t_a, t_b): (f64, f64)) -> Vec<(f64, f64)> {
    if t_b.partial_cmp(&t_a) == Some(std::cmp::Ordering::Greater) {
        vec![(t_a, t_b)]
    } else {
        Vec::new()
    }
}

/// The stretches of `[t_a, t_b]` where `lit` holds: [`SHADOW_SAMPLES`]
/// equal steps, each change bisected (module docs).
fn spans_where((t_a, t_b): (f64, f64), lit: impl Fn(f64) -> bool) -> Vec<(f64, f64)> {
    if t_b.partial_cmp(&t_a) != Some(std::cmp::Ordering::Greater) {
        return Vec::new();
    }
    let step = (t_b - t_a) / f64::from(SHADOW_SAMPLES);
    let mut spans = Vec::new();
    let mut start = lit(t_a).then_some(t_a);
    let mut previous = (t_a, start.is_some());
    for i in 1..=SHADOW_SAMPLES {
        let t = if i == SHADOW_SAMPLES {
            t_b
        } else {
            t_a + step * f64::from(i)
        };
        let now = lit(t);
        if now != previous.1 {
            let (mut lo, mut hi) = (previous.0, t);
            for _ in 0..BISECTIONS {
                let mid = 0.5 * (lo + hi);
                if lit(mid) == previous.1 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let crossing = 0.5 * (lo + hi);
            match start.take() {
                Some(begin) => spans.push((begin, crossing)),
                None => start = Some(crossing),
            }
        }
        previous = (t, now);
    }
    if let Some(begin) = start {
        spans.push((begin, t_b));
    }
    spans
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use glam::DAffine3;

    use super::*;
    use crate::field::HeightField;
    use crate::test_support::SplitMix;

    fn ray(origin: [f64; 3], direction: [f64; 3]) -> Ray {
        Ray::new(DVec3::from(origin), DVec3::from(direction)).expect("a valid ray")
    }

    #[test]
    fn hits_are_the_nearest_surface_in_front() {
        let sphere = Occluder::Sphere {
            centre: DVec3::new(0.0, 0.0, -5.0),
            radius: 1.0,
        };
        assert_eq!(sphere.hit(&ray([0.0; 3], [0.0, 0.0, -1.0])), Some(4.0));
        // From inside, the exit.
        assert_eq!(
            sphere.hit(&ray([0.0, 0.0, -5.0], [0.0, 0.0, -1.0])),
            Some(1.0)
        );
        assert_eq!(sphere.hit(&ray([0.0; 3], [0.0, 0.0, 1.0])), None);
        let cuboid = Occluder::Box {
            min: DVec3::new(-1.0, -1.0, -4.0),
            max: DVec3::new(1.0, 1.0, -2.0),
        };
        assert_eq!(cuboid.hit(&ray([0.0; 3], [0.0, 0.0, -1.0])), Some(2.0));
        assert_eq!(cuboid.hit(&ray([0.0, 3.0, 0.0], [0.0, 0.0, -1.0])), None);
        let plane = Occluder::Rectangle {
            centre: DVec3::new(0.0, -2.0, 0.0),
            half_size: DVec2::new(1.0, 1.0),
        };
        assert_eq!(plane.hit(&ray([0.0; 3], [0.0, -1.0, 0.0])), Some(2.0));
        assert_eq!(plane.hit(&ray([3.0, 1.0, 0.0], [0.0, -1.0, 0.0])), None);
        assert_eq!(plane.hit(&ray([0.0, 1.0, 0.0], [1.0, 0.0, 0.0])), None);
    }

    #[test]
    fn a_point_sees_a_light_unless_an_occluder_lies_between() {
        let wall = [Occluder::Box {
            min: DVec3::new(-1.0, -1.0, 1.0),
            max: DVec3::new(1.0, 1.0, 1.5),
        }];
        let light = DVec3::ZERO;
        assert!(hides(&wall, DVec3::new(0.0, 0.0, 3.0), light));
        assert!(!hides(&wall, DVec3::new(0.0, 0.0, 0.5), light));
        assert!(!hides(&wall, DVec3::new(0.0, 0.0, -3.0), light));
        // Inside the wall: hidden.
        assert!(hides(&wall, DVec3::new(0.0, 0.0, 1.2), light));
        // The light itself.
        assert!(!hides(&wall, light, light));
    }

    #[test]
    fn a_slab_above_a_light_shades_a_level_ray_over_it_in_closed_form() {
        // A light at the origin, a slab y ∈ [1, 1.5], |x| ≤ 1, wide in z;
        // a ray along x at y = 3. The segment from the light to (x, 3)
        // crosses y ∈ [1, 1.5] at x·y/3, inside |·| ≤ 1 for |x| ≤ 3: lit
        // outside [−3, 3] only.
        let slab = [Occluder::Box {
            min: DVec3::new(-1.0, 1.0, -50.0),
            max: DVec3::new(1.0, 1.5, 50.0),
        }];
        let level = ray([-10.0, 3.0, 0.0], [1.0, 0.0, 0.0]);
        let spans = lit_spans(&slab, DVec3::ZERO, &level, (0.0, 20.0));
        assert_eq!(spans.len(), 2);
        assert_eq!(spans[0].0, 0.0);
        assert!((spans[0].1 - 7.0).abs() < 1e-12, "{spans:?}");
        assert!((spans[1].0 - 13.0).abs() < 1e-12, "{spans:?}");
        assert_eq!(spans[1].1, 20.0);
        // Starting in the shadow.
        let spans = lit_spans(&slab, DVec3::ZERO, &level, (10.0, 15.0));
        assert_eq!(spans.len(), 1);
        assert!((spans[0].0 - 13.0).abs() < 1e-12 && spans[0].1 == 15.0);
        // No occluders: the whole stretch.
        assert_eq!(
            lit_spans(&[], DVec3::ZERO, &level, (1.0, 2.0)),
            vec![(1.0, 2.0)]
        );
    }

    /// A strip 10 m above a level ray hides the sun (53° up along +x) from
    /// the stretch whose sun line crosses it: x + 7.5 in [−5, 5].
    #[test]
    fn a_strip_above_shades_the_sun_from_a_level_ray_in_closed_form() {
        let strip = [Occluder::Rectangle {
            centre: DVec3::new(0.0, 10.0, 0.0),
            half_size: DVec2::new(5.0, 100.0),
        }];
        let sun = DVec3::new(0.6, 0.8, 0.0);
        let level = ray([-50.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
        let spans = sun_lit_spans(&strip, sun, &level, (0.0, 100.0));
        assert_eq!(spans.len(), 2, "{spans:?}");
        assert_eq!(spans[0].0, 0.0);
        assert!((spans[0].1 - 37.5).abs() < 1e-9, "{spans:?}");
        assert!((spans[1].0 - 47.5).abs() < 1e-9 && spans[1].1 == 100.0);
        assert!(hides_sun(&strip, DVec3::new(-10.0, 0.0, 0.0), sun));
        assert!(!hides_sun(&strip, DVec3::new(-10.0, 11.0, 0.0), sun));
        assert_eq!(
            sun_lit_spans(&[], sun, &level, (3.0, 4.0)),
            vec![(3.0, 4.0)]
        );
        assert!(sun_lit_spans(&strip, sun, &level, (4.0, 3.0)).is_empty());
    }

    /// A wall 12 m high over x in [38, 40] (its face rising from x = 37),
    /// a light at (45, 20): the segment from (x, 4) clears the wall's
    /// corner (38, 12) for x ≤ 31; a point inside the wall sees nothing,
    /// and the terrain moved by its placement moves the shadow with it.
    #[test]
    fn a_terrain_wall_hides_a_light_from_the_ray_behind_it_in_closed_form() {
        let mut heights = vec![0.0f32; 41 * 3];
        for row in heights.chunks_mut(41) {
            row[38..].fill(12.0);
        }
        let field = HeightField::new([41, 3], DVec2::ONE, DVec2::ZERO, heights).unwrap();
        let placed = |offset: DVec3| {
            Occluder::Terrain(PlacedHeights::new(
                Arc::new(field.clone()),
                DAffine3::from_translation(-offset),
            ))
        };
        let wall = [placed(DVec3::ZERO)];
        let light = DVec3::new(45.0, 20.0, 1.0);
        let level = ray([0.0, 4.0, 1.0], [1.0, 0.0, 0.0]);
        let spans = lit_spans(&wall, light, &level, (2.0, 36.0));
        assert_eq!(spans.len(), 1, "{spans:?}");
        assert!(
            spans[0].0 == 2.0 && (spans[0].1 - 31.0).abs() < 1e-9,
            "{spans:?}"
        );
        assert!(hides(&wall, DVec3::new(39.0, 5.0, 1.0), light));
        assert!(!hides(&wall, DVec3::new(39.0, 13.0, 1.0), light));
        // Straight down onto the wall's top, and from inside it.
        let down = ray([39.0, 30.0, 1.0], [0.0, -1.0, 0.0]);
        assert!((wall[0].hit(&down).unwrap() - 18.0).abs() < 1e-9);
        let inside = ray([39.0, 5.0, 1.0], [1.0, 1.0, 0.0]);
        assert!(wall[0].hit(&inside).is_some_and(|t| t > 0.0));
        // Moved 10 m up, the same points lie 10 m lower relative to it.
        let raised = [placed(DVec3::new(0.0, 10.0, 0.0))];
        assert!(hides(&raised, DVec3::new(39.0, 13.0, 1.0), light));
        assert!(!hides(&raised, DVec3::new(39.0, 23.0, 1.0), light));
    }

    #[test]
    fn lit_spans_agree_with_the_visibility_at_random_points() {
        let mut rng = SplitMix(11);
        let mut wrong_cases = 0;
        for _ in 0..30 {
            let occluders: Vec<Occluder> = (0..3)
                .map(|k| {
                    let centre = DVec3::new(
                        rng.random_range(-3.0..3.0),
                        rng.random_range(0.5..2.5),
                        rng.random_range(-3.0..3.0),
                    );
                    if k == 2 {
                        Occluder::Sphere {
                            centre,
                            radius: rng.random_range(0.2..1.0),
                        }
                    } else {
                        let half = DVec3::new(
                            rng.random_range(0.1..1.0),
                            rng.random_range(0.1..1.0),
                            rng.random_range(0.1..1.0),
                        );
                        Occluder::Box {
                            min: centre - half,
                            max: centre + half,
                        }
                    }
                })
                .collect();
            let light = DVec3::new(
                rng.random_range(-1.0..1.0),
                0.0,
                rng.random_range(-1.0..1.0),
            );
            let r = ray(
                [
                    rng.random_range(-8.0..-6.0),
                    rng.random_range(2.0..4.0),
                    rng.random_range(-2.0..2.0),
                ],
                [
                    1.0,
                    rng.random_range(-0.2..0.2),
                    rng.random_range(-0.3..0.3),
                ],
            );
            let spans = lit_spans(&occluders, light, &r, (0.0, 14.0));
            for (a, b) in &spans {
                assert!(a < b);
            }
            for w in spans.windows(2) {
                assert!(w[0].1 < w[1].0);
            }
            // Each point is lit exactly when it lies in a span, but for
            // shadows (or gaps) missed between two samples: less than a step
            // in all.
            let step = 14.0 / f64::from(SHADOW_SAMPLES);
            let points = 20_000;
            let wrong = (0..points)
                .filter(|i| {
                    let t = 14.0 * (f64::from(*i) + 0.5) / f64::from(points);
                    let inside = spans.iter().any(|(a, b)| t > *a && t < *b);
                    let seen = !hides(&occluders, r.origin + t * r.direction, light);
                    inside != seen
                })
                .count();
            assert!(
                wrong as f64 * 14.0 / f64::from(points) <= step,
                "{wrong} of {points} points wrong, spans {spans:?}"
            );
            wrong_cases += usize::from(wrong > 0);
        }
        // A crossing found is found to f64: most cases have no point wrong.
        assert!(wrong_cases <= 3, "{wrong_cases} of 30 cases");
    }
}
