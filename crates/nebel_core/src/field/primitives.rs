//! Implicit ellipsoids that shape a cloud, blended by Wyvill's field.
//!
//! Schpok et al. 2003 §3.1 model a cloud by implicit ellipsoids whose fields
//! blend smoothly, with noise subtracting detail at their surfaces. Each
//! [`CloudEllipsoid`] contributes `density · F(q)`, with `q` the squared
//! distance from its centre in its own radii (1 on its surface) and Wyvill's
//! soft-object function `F(q) = 1 − 4/9 q³ + 17/9 q² − 22/9 q` for `q < 1`, 0
//! beyond (Wyvill et al. 1986): 1 at the centre, 0 with zero slope on the
//! surface. The cloud's shape is `P = min(1, Σ density_i F_i)`, and it scales
//! the cloud's coverage (see `CloudNoise`), so the noise fills the cores and
//! only its strongest detail reaches the surfaces. Ellipsoids move
//! (`velocity`: a path, or a rise) and grow over time.

use std::sync::Arc;

use glam::{DQuat, DVec3};

use super::weather::WeatherMap;
use super::{FieldError, Settings};

/// One implicit ellipsoid of a cloud's shape, in the grid's frame (world
/// units) at time 0 of the cloud's clock (in Bevy, the app's elapsed time).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
pub struct CloudEllipsoid {
    /// Centre at time 0.
    pub centre: DVec3,
    /// Radii along the ellipsoid's own axes at time 0, each > 0.
    pub radii: DVec3,
    /// Orientation of the ellipsoid's axes.
    pub rotation: DQuat,
    /// Weight of its field, ≥ 0: 1 gives the cloud's full coverage at the
    /// centre; overlapping ellipsoids add up (to at most 1).
    pub density: f32,
    /// Drift, world units per second: its centre at time `t` is
    /// `centre + velocity · t` (a rise where `velocity.y > 0`).
    pub velocity: DVec3,
    /// Growth per second: its radii at time `t` are `radii · (1 + growth ·
    /// t)`; it vanishes once that factor reaches 0.
    pub growth: f64,
}

impl Default for CloudEllipsoid {
    fn default() -> Self {
        Self {
            centre: DVec3::ZERO,
            radii: DVec3::ONE,
            rotation: DQuat::IDENTITY,
            density: 1.0,
            velocity: DVec3::ZERO,
            growth: 0.0,
        }
    }
}

/// What shapes a cloud beyond its noise settings: a weather map over its
/// box, and implicit ellipsoids. The default shapes nothing.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CloudShape {
    /// A weather map instead of the procedural `CloudNoise::weather`.
    pub weather_map: Option<Arc<WeatherMap>>,
    /// Ellipsoids whose blended field scales the coverage; none leaves it
    /// as it is (`P = 1`).
    pub primitives: Vec<CloudEllipsoid>,
}

impl CloudEllipsoid {
    /// Whether it changes over time: it moves or grows.
    pub fn animates(&self) -> bool {
        self.velocity != DVec3::ZERO || self.growth != 0.0
    }
}

impl CloudShape {
    /// Whether the shape changes over time (an ellipsoid that moves or grows).
    pub fn animates(&self) -> bool {
        self.primitives.iter().any(CloudEllipsoid::animates)
    }
}

/// Wyvill's soft-object function of the squared normalised distance `q`.
pub fn wyvill(q: f64) -> f64 {
    if q >= 1.0 {
        0.0
    } else {
        1.0 + q * (-22.0 / 9.0 + q * (17.0 / 9.0 - q * 4.0 / 9.0))
    }
}

/// An ellipsoid at one time, ready to sample.
#[derive(Clone, Copy)]
struct Placed {
    centre: DVec3,
    /// Maps a world offset to the ellipsoid's unit frame.
    inverse: DQuat,
    inverse_radii: DVec3,
    /// Half extents of its axis-aligned bounding box.
    extent: DVec3,
    density: f64,
}

impl Placed {
    fn q(&self, p: DVec3) -> f64 {
        ((self.inverse * (p - self.centre)) * self.inverse_radii).length_squared()
    }
}

/// The ellipsoids of a shape at one time, sampled row by row.
pub(super) struct Primitives {
    placed: Vec<Placed>,
}

impl Primitives {
    /// The ellipsoids of `shape` at `time`, checked; `None` without any
    /// (the shape is 1 everywhere).
    ///
    /// # Errors
    ///
    /// [`FieldError::InvalidParameter`] naming `primitives[i]` and the
    /// setting (`radii`, …): a radius not finite and positive, a density not finite and
    /// at least 0, a centre, rotation, velocity or growth not finite.
    pub fn new(name: &str, shape: &CloudShape, time: f64) -> Result<Option<Self>, FieldError> {
        if shape.primitives.is_empty() {
            return Ok(None);
        }
        let mut placed = Vec::with_capacity(shape.primitives.len());
        for (i, e) in shape.primitives.iter().enumerate() {
            let name = format!("{name}, primitives[{i}]");
            let settings = Settings(&name);
            let radii_ok = e.radii.is_finite() && e.radii.min_element() > 0.0;
            settings.require(radii_ok, "radii", e.radii, "finite and positive")?;
            settings.non_negative(&[("density", e.density)])?;
            settings.require(e.centre.is_finite(), "centre", e.centre, "finite")?;
            settings.require(e.velocity.is_finite(), "velocity", e.velocity, "finite")?;
            settings.require(e.growth.is_finite(), "growth", e.growth, "finite")?;
            settings.require(e.rotation.is_finite(), "rotation", e.rotation, "finite")?;
            let turned = e.rotation.length_squared() != 0.0;
            settings.require(turned, "rotation", e.rotation, "not zero")?;
            let scale = 1.0 + e.growth * time;
            let centre = e.centre + e.velocity * time;
            settings.require(
                scale.is_finite() && centre.is_finite(),
                "velocity",
                e.velocity,
                "centre + velocity · time and 1 + growth · time finite",
            )?;
            if scale <= 0.0 || e.density == 0.0 {
                continue;
            }
            let rotation = e.rotation.normalize();
            let radii = e.radii * scale;
            let axes = [
                rotation * DVec3::X * radii.x,
                rotation * DVec3::Y * radii.y,
                rotation * DVec3::Z * radii.z,
            ];
            let extent = DVec3::new(
                axes.iter().map(|a| a.x * a.x).sum::<f64>().sqrt(),
                axes.iter().map(|a| a.y * a.y).sum::<f64>().sqrt(),
                axes.iter().map(|a| a.z * a.z).sum::<f64>().sqrt(),
            );
            settings.require(
                extent.is_finite(),
                "radii",
                e.radii,
                "small enough that radii · (1 + growth · time) squared stays finite",
            )?;
            placed.push(Placed {
                centre,
                inverse: rotation.inverse(),
                inverse_radii: radii.recip(),
                extent,
                density: f64::from(e.density),
            });
        }
        Ok(Some(Self { placed }))
    }

    /// The shape `P = min(1, Σ density_i F_i)` at the points `xs` of the
    /// row at height `y`, depth `z` into `row`; false when it is 0 at
    /// every point (nothing of the row can be cloud).
    pub fn fill_row(&self, xs: &[f64], y: f64, z: f64, row: &mut [f64]) -> bool {
        row.fill(0.0);
        let mut any = false;
        let (first, step) = (xs[0], xs.get(1).map_or(1.0, |x| x - xs[0]));
        for e in &self.placed {
            if (y - e.centre.y).abs() >= e.extent.y || (z - e.centre.z).abs() >= e.extent.z {
                continue;
            }
            // The row's points inside the box's x range (and a point either
            // side, whose F is 0).
            let len = xs.len() as f64;
            let index = |x: f64| x.clamp(0.0, len) as usize;
            let from = index(((e.centre.x - e.extent.x - first) / step).floor());
            let to = index(((e.centre.x + e.extent.x - first) / step).ceil() + 1.0);
            for (x, value) in xs[from.min(to)..to].iter().zip(&mut row[from.min(to)..to]) {
                let f = wyvill(e.q(DVec3::new(*x, y, z)));
                if f > 0.0 {
                    *value += e.density * f;
                    any = true;
                }
            }
        }
        for value in row.iter_mut() {
            *value = value.min(1.0);
        }
        any
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    #[test]
    fn wyvills_function_falls_from_one_to_zero_with_zero_slope() {
        assert_eq!(wyvill(0.0), 1.0);
        assert!(wyvill(1.0 - 1e-12).abs() < 1e-10);
        assert_eq!(wyvill(1.0), 0.0);
        assert_eq!(wyvill(4.0), 0.0);
        // Half the field at about r = 0.5 (q = 0.25): Wyvill's design.
        assert!((wyvill(0.25) - 0.5).abs() < 0.02, "{}", wyvill(0.25));
        // Monotone, and its slope in q vanishes at the surface.
        let mut last = 1.0;
        for i in 1..=1000 {
            let f = wyvill(i as f64 / 1000.0);
            assert!(f <= last);
            last = f;
        }
        let slope = (wyvill(1.0 - 1e-4) - wyvill(1.0 - 2e-4)) / 1e-4;
        assert!(slope.abs() < 1e-3, "{slope}");
    }

    /// The shape at `p` written out: the sum over every ellipsoid, with no
    /// bounding box; 1 without ellipsoids.
    pub(in crate::field) fn pointwise_shape(shape: &CloudShape, time: f64, p: DVec3) -> f64 {
        if shape.primitives.is_empty() {
            return 1.0;
        }
        let sum: f64 = shape
            .primitives
            .iter()
            .map(|e| {
                let scale = 1.0 + e.growth * time;
                if scale <= 0.0 {
                    return 0.0;
                }
                let local = e.rotation.normalize().inverse() * (p - e.centre - e.velocity * time);
                f64::from(e.density) * wyvill((local / (e.radii * scale)).length_squared())
            })
            .sum();
        sum.min(1.0)
    }

    #[test]
    fn rows_equal_the_sum_over_every_ellipsoid() {
        let shape = CloudShape {
            primitives: vec![
                CloudEllipsoid {
                    centre: DVec3::new(3.0, 2.0, 1.0),
                    radii: DVec3::new(4.0, 2.0, 3.0),
                    rotation: DQuat::from_euler(glam::EulerRot::YXZ, 0.7, 0.3, -0.2),
                    density: 0.8,
                    velocity: DVec3::new(0.5, 0.2, 0.0),
                    growth: 0.05,
                },
                CloudEllipsoid {
                    centre: DVec3::new(-2.0, 1.0, 0.0),
                    radii: DVec3::splat(2.5),
                    density: 0.7,
                    ..CloudEllipsoid::default()
                },
                // Gone by t = 2.
                CloudEllipsoid {
                    centre: DVec3::new(0.0, 0.0, 2.0),
                    growth: -0.5,
                    ..CloudEllipsoid::default()
                },
            ],
            ..CloudShape::default()
        };
        assert!(shape.animates());
        let xs: Vec<f64> = (0..41).map(|i| -8.0 + 0.4 * i as f64).collect();
        let mut row = vec![0.0; xs.len()];
        for time in [0.0, 1.0, 2.0, 3.0] {
            let primitives = Primitives::new("test", &shape, time).unwrap().unwrap();
            let mut inside = 0;
            for y in [-1.0, 0.0, 1.0, 2.2, 3.9, 6.0] {
                for z in [-3.0, 0.0, 0.5, 1.7, 4.0] {
                    let any = primitives.fill_row(&xs, y, z, &mut row);
                    for (x, value) in xs.iter().zip(&row) {
                        let expected = pointwise_shape(&shape, time, DVec3::new(*x, y, z));
                        assert!(
                            (value - expected).abs() < 1e-12,
                            "{x} {y} {z}: {value} {expected}"
                        );
                        inside += usize::from(*value > 0.0);
                    }
                    assert_eq!(any, row.iter().any(|&v| v > 0.0));
                }
            }
            assert!(inside > 20, "time {time}: {inside} points inside");
        }
    }

    #[test]
    fn a_shaped_cloud_lies_inside_its_moving_ellipsoids() {
        use crate::field::{CloudNoise, DensityGrid};
        let noise = CloudNoise {
            coverage: 1.0,
            wavelength: 6.0,
            base_fade: 0.0,
            top_fade: 0.0,
            side_fade: 0.0,
            ..CloudNoise::default()
        };
        let tower = CloudEllipsoid {
            centre: DVec3::new(10.0, 8.0, 12.0),
            radii: DVec3::new(5.0, 7.0, 4.0),
            rotation: DQuat::from_rotation_y(0.4),
            velocity: DVec3::new(1.0, 0.5, -0.5),
            ..CloudEllipsoid::default()
        };
        let shape = CloudShape {
            primitives: vec![tower],
            ..CloudShape::default()
        };
        let (dims, spacing) = ([33, 25, 33], DVec3::splat(0.75));
        for time in [0.0, 4.0] {
            let grid = DensityGrid::cloud_shaped(dims, spacing, DVec3::ZERO, &noise, &shape, time)
                .unwrap();
            let placed = Primitives::new("test", &shape, time)
                .unwrap()
                .unwrap()
                .placed[0];
            let (mut core, mut cloudy_core) = (0, 0);
            for k in 0..dims[2] {
                for j in 0..dims[1] {
                    for i in 0..dims[0] {
                        let p = DVec3::new(i as f64, j as f64, k as f64) * spacing;
                        let (q, v) = (placed.q(p), grid.value(i, j, k));
                        assert!(v == 0.0 || q < 1.0, "cloud outside at {p}, time {time}");
                        if q < 0.1 {
                            core += 1;
                            cloudy_core += usize::from(v > 0.0);
                        }
                    }
                }
            }
            assert!(core > 30, "{core}");
            assert!(
                2 * cloudy_core > core,
                "{cloudy_core} of {core} core points cloud"
            );
        }
    }

    #[test]
    fn bad_ellipsoids_are_refused_by_index_and_setting() {
        let check = |e: CloudEllipsoid, setting: &str| {
            let shape = CloudShape {
                primitives: vec![CloudEllipsoid::default(), e],
                ..CloudShape::default()
            };
            let message = Primitives::new("cloud", &shape, 0.0)
                .err()
                .expect("refused")
                .to_string();
            assert!(
                message.contains("cloud, primitives[1]") && message.contains(setting),
                "{message}"
            );
        };
        let ok = CloudEllipsoid::default();
        check(
            CloudEllipsoid {
                radii: DVec3::new(1.0, 0.0, 1.0),
                ..ok
            },
            "radii",
        );
        check(
            CloudEllipsoid {
                radii: DVec3::splat(f64::NAN),
                ..ok
            },
            "radii",
        );
        check(
            CloudEllipsoid {
                density: -1.0,
                ..ok
            },
            "density",
        );
        check(
            CloudEllipsoid {
                radii: DVec3::splat(1e200),
                ..ok
            },
            "radii",
        );
        check(
            CloudEllipsoid {
                centre: DVec3::splat(f64::INFINITY),
                ..ok
            },
            "centre",
        );
        check(
            CloudEllipsoid {
                rotation: DQuat::from_xyzw(0.0, 0.0, 0.0, 0.0),
                ..ok
            },
            "rotation",
        );
        check(
            CloudEllipsoid {
                growth: f64::NAN,
                ..ok
            },
            "growth",
        );
    }
}
