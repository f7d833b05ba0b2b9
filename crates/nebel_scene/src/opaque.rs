//! Opaque depth of a scene's plain meshes and terrain for the CPU reference
//! renderer.
//!
//! The reference integrates the volume only up to the first opaque surface
//! on each pixel's ray, like the GPU pass that reads the depth buffer. This
//! module intersects every pixel's ray with the scene's planes, boxes and
//! spheres in f64 and returns the view-space depth of the nearest hit (`+∞`
//! where the ray hits nothing), the layout
//! [`ReferenceScene::opaque_depth`](crate::reference::ReferenceScene::opaque_depth)
//! takes.
//!
//! A terrain, given as its height field in world space
//! ([`TerrainDescription::world_heights`](super::TerrainDescription::world_heights)),
//! is the full-resolution bilinear surface over its grid: the ray is clipped
//! to the grid's box, marched in steps of half the smaller spacing and the
//! first crossing bisected to 1e-9 of the step. The GPU draws the quadtree's
//! level of detail instead (triangles, morphed), which lies within the
//! accuracy `c` implies; a feature thinner than half a spacing along the ray
//! may be stepped over.

use glam::{DVec2, DVec3};

use super::{MeshDescription, SceneDescription, check_opaque_depth_budget};
use nebel_core::budget::BudgetError;
use nebel_core::cell::Ray;
use nebel_core::field::HeightField;
use nebel_reference::ReferenceCamera;

impl SceneDescription {
    /// View-space depth of the nearest mesh per pixel of `camera`, row-major,
    /// top row first; `+∞` where no mesh is hit. `None` without meshes. A
    /// [`BudgetError`] when the depths (4 bytes per pixel) exceed the memory
    /// budget, before they are allocated.
    pub fn opaque_depth(&self, camera: &ReferenceCamera) -> Result<Option<Vec<f32>>, BudgetError> {
        self.opaque_depth_with_terrain(camera, None)
    }

    /// [`SceneDescription::opaque_depth`] of the meshes and the terrain
    /// `terrain` (heights in world space, see the module docs). `None`
    /// without meshes and terrain.
    pub fn opaque_depth_with_terrain(
        &self,
        camera: &ReferenceCamera,
        terrain: Option<&HeightField>,
    ) -> Result<Option<Vec<f32>>, BudgetError> {
        if self.meshes.is_empty() && terrain.is_none() {
            return Ok(None);
        }
        check_opaque_depth_budget(camera.width, camera.height)?;
        let terrain = terrain.map(TerrainSurface::new);
        let mut depth = Vec::with_capacity(camera.width as usize * camera.height as usize);
        for y in 0..camera.height {
            for x in 0..camera.width {
                let (ray, depth_to_distance) = camera.pixel_ray(x, y);
                let nearest = self
                    .meshes
                    .iter()
                    .filter_map(|mesh| mesh_hit(mesh, &ray))
                    .chain(terrain.as_ref().and_then(|surface| surface.hit(&ray)))
                    .fold(f64::INFINITY, f64::min);
                depth.push((nearest * depth_to_distance) as f32);
            }
        }
        Ok(Some(depth))
    }
}

/// A terrain's height field and the box around it.
struct TerrainSurface<'a> {
    field: &'a HeightField,
    min: DVec3,
    max: DVec3,
}

impl<'a> TerrainSurface<'a> {
    fn new(field: &'a HeightField) -> Self {
        let [nx, nz] = field.dims();
        let spacing = field.spacing();
        let origin = field.origin();
        let (low, high) = field
            .heights()
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &h| {
                (lo.min(f64::from(h)), hi.max(f64::from(h)))
            });
        Self {
            field,
            min: DVec3::new(origin.x, low, origin.y),
            max: DVec3::new(
                origin.x + (nx - 1) as f64 * spacing.x,
                high,
                origin.y + (nz - 1) as f64 * spacing.y,
            ),
        }
    }

    fn hit(&self, ray: &Ray) -> Option<f64> {
        terrain_hit(self.field, self.min, self.max, ray)
    }
}

/// Distance along `ray` (unit direction) to where it first passes from above
/// the bilinear surface of `field` (inside the box `min..max`) to below it,
/// within its grid (see the module docs).
fn terrain_hit(field: &HeightField, min: DVec3, max: DVec3, ray: &Ray) -> Option<f64> {
    // The ray's stretch inside the grid's box.
    let inverse = ray.direction.recip();
    let a = (min - ray.origin) * inverse;
    let b = (max - ray.origin) * inverse;
    let near = a.min(b).max_element().max(0.0);
    let far = a.max(b).min_element();
    // NaN (a ray parallel to a face, on it) counts as a miss.
    if near.partial_cmp(&far).is_none_or(std::cmp::Ordering::is_gt) {
        return None;
    }
    let above = |t: f64| {
        let p = ray.origin + t * ray.direction;
        p.y - field.sample(DVec2::new(p.x, p.z))
    };
    let step = 0.5 * field.spacing().min_element();
    // The surface is seen from above only (its back is culled on the GPU):
    // the hit is the first crossing from above to below.
    let mut t0 = near;
    let mut was_above = above(t0) > 0.0;
    while t0 < far {
        let t1 = (t0 + step).min(far);
        let f1 = above(t1);
        if f1 > 0.0 {
            was_above = true;
        } else if was_above {
            // Bisect the crossing in [t0, t1].
            let (mut lo, mut hi) = (t0, t1);
            while hi - lo > 1e-9 * step {
                let mid = 0.5 * (lo + hi);
                if above(mid) > 0.0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            return Some(hi);
        }
        t0 = t1;
    }
    None
}

fn vector(v: [f32; 3]) -> DVec3 {
    DVec3::from(v.map(f64::from))
}

/// Distance along `ray` to the first hit in front of its origin.
fn mesh_hit(mesh: &MeshDescription, ray: &Ray) -> Option<f64> {
    match mesh {
        MeshDescription::Plane(plane) => {
            let center = vector(plane.center);
            let half = DVec3::new(
                f64::from(plane.size[0]) / 2.0,
                0.0,
                f64::from(plane.size[1]) / 2.0,
            );
            let t = (center.y - ray.origin.y) / ray.direction.y;
            let point = ray.origin + t * ray.direction;
            let inside =
                (point.x - center.x).abs() <= half.x && (point.z - center.z).abs() <= half.z;
            (t.is_finite() && t > 0.0 && inside).then_some(t)
        }
        MeshDescription::Box(cuboid) => {
            let center = vector(cuboid.center);
            let half = vector(cuboid.size) / 2.0;
            let inverse = ray.direction.recip();
            let a = (center - half - ray.origin) * inverse;
            let b = (center + half - ray.origin) * inverse;
            let entry = a.min(b).max_element();
            let exit = a.max(b).min_element();
            let t = if entry > 0.0 { entry } else { exit };
            (entry <= exit && t > 0.0).then_some(t)
        }
        MeshDescription::Sphere(sphere) => {
            let offset = ray.origin - vector(sphere.center);
            let radius = f64::from(sphere.radius);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{BoxDescription, PlaneDescription, SphereDescription};

    fn ray(origin: [f64; 3], direction: [f64; 3]) -> Ray {
        Ray::new(DVec3::from(origin), DVec3::from(direction)).unwrap()
    }

    #[test]
    fn a_ray_meets_the_terrain_surface_or_misses_its_grid() {
        // A ramp h = 1 + 0.5 x over x, z in [0, 4], 5 × 5 points 1 apart.
        let heights = (0..25).map(|i| 1.0 + 0.5 * (i % 5) as f32).collect();
        let field = HeightField::new([5, 5], DVec2::ONE, DVec2::ZERO, heights).unwrap();
        let down = ray([2.0, 10.0, 2.0], [0.0, -1.0, 0.0]);
        let t = TerrainSurface::new(&field).hit(&down).unwrap();
        assert!((t - 8.0).abs() < 1e-7, "{t}");
        // Level from the left at y = 2.5: meets the ramp at x = 3.
        let level = ray([-5.0, 2.5, 1.5], [1.0, 0.0, 0.0]);
        let t = TerrainSurface::new(&field).hit(&level).unwrap();
        assert!((t - 8.0).abs() < 1e-7, "{t}");
        // Above the highest point, outside the grid, or pointing away: no hit.
        assert_eq!(
            TerrainSurface::new(&field).hit(&ray([-5.0, 3.5, 1.5], [1.0, 0.0, 0.0])),
            None
        );
        assert_eq!(
            TerrainSurface::new(&field).hit(&ray([9.0, 10.0, 2.0], [0.0, -1.0, 0.0])),
            None
        );
        assert_eq!(
            TerrainSurface::new(&field).hit(&ray([2.0, 10.0, 2.0], [0.0, 1.0, 0.0])),
            None
        );
        // Below the surface the ray sees its back (culled on the GPU too)
        // until it comes out above: then it meets the front.
        assert_eq!(
            TerrainSurface::new(&field).hit(&ray([2.0, 1.5, 2.0], [1.0, 0.0, 0.0])),
            None
        );
        assert_eq!(
            TerrainSurface::new(&field).hit(&ray([2.0, 0.5, 2.0], [1.0, 0.0, 0.0])),
            None
        );
        let up_and_over = ray([-1.0, 0.5, 2.0], [3.0, 1.0, 0.0]);
        assert_eq!(TerrainSurface::new(&field).hit(&up_and_over), None);
        let out_and_back =
            Ray::new(DVec3::new(1.0, 1.2, 2.0), DVec3::new(-1.0, 0.05, 0.0)).unwrap();
        assert_eq!(TerrainSurface::new(&field).hit(&out_and_back), None);
    }

    #[test]
    fn hits_are_the_nearest_surface_in_front() {
        let sphere = MeshDescription::Sphere(SphereDescription {
            center: [0.0, 0.0, -5.0],
            radius: 1.0,
            color: [1.0; 3],
        });
        assert_eq!(
            mesh_hit(&sphere, &ray([0.0; 3], [0.0, 0.0, -1.0])),
            Some(4.0)
        );
        assert_eq!(
            mesh_hit(&sphere, &ray([0.0, 0.0, -5.0], [0.0, 0.0, -1.0])),
            Some(1.0)
        );
        assert_eq!(mesh_hit(&sphere, &ray([0.0; 3], [0.0, 0.0, 1.0])), None);
        let cuboid = MeshDescription::Box(BoxDescription {
            center: [0.0, 0.0, -5.0],
            size: [2.0, 2.0, 2.0],
            color: [1.0; 3],
        });
        assert_eq!(
            mesh_hit(&cuboid, &ray([0.0; 3], [0.0, 0.0, -1.0])),
            Some(4.0)
        );
        assert_eq!(
            mesh_hit(&cuboid, &ray([0.0, 3.0, 0.0], [0.0, 0.0, -1.0])),
            None
        );
        let plane = MeshDescription::Plane(PlaneDescription {
            center: [0.0, -1.0, 0.0],
            size: [4.0, 4.0],
            color: [1.0; 3],
        });
        let down = ray([0.0, 1.0, 0.0], [0.0, -1.0, 0.0]);
        assert_eq!(mesh_hit(&plane, &down), Some(2.0));
        assert_eq!(
            mesh_hit(&plane, &ray([3.0, 1.0, 0.0], [0.0, -1.0, 0.0])),
            None
        );
        assert_eq!(
            mesh_hit(&plane, &ray([0.0, 1.0, 0.0], [1.0, 0.0, 0.0])),
            None
        );
    }
}
