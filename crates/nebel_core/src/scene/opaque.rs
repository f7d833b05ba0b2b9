//! Opaque depth of a scene's plain meshes for the CPU reference renderer.
//!
//! The reference integrates the volume only up to the first opaque surface
//! on each pixel's ray, like the GPU pass that reads the depth buffer. This
//! module intersects every pixel's ray with the scene's planes, boxes and
//! spheres in f64 and returns the view-space depth of the nearest hit (`+∞`
//! where the ray hits nothing), the layout
//! [`ReferenceScene::opaque_depth`](crate::reference::ReferenceScene::opaque_depth)
//! takes.

use glam::DVec3;

use super::{MeshDescription, SceneDescription};
use crate::cell::Ray;
use crate::reference::ReferenceCamera;

impl SceneDescription {
    /// View-space depth of the nearest mesh per pixel of `camera`, row-major,
    /// top row first; `+∞` where no mesh is hit. `None` without meshes.
    pub fn opaque_depth(&self, camera: &ReferenceCamera) -> Option<Vec<f32>> {
        if self.meshes.is_empty() {
            return None;
        }
        let mut depth = Vec::with_capacity(camera.width as usize * camera.height as usize);
        for y in 0..camera.height {
            for x in 0..camera.width {
                let (ray, depth_to_distance) = camera.pixel_ray(x, y);
                let nearest = self
                    .meshes
                    .iter()
                    .filter_map(|mesh| mesh_hit(mesh, &ray))
                    .fold(f64::INFINITY, f64::min);
                depth.push((nearest * depth_to_distance) as f32);
            }
        }
        Some(depth)
    }
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
    use crate::scene::{BoxDescription, PlaneDescription, SphereDescription};

    fn ray(origin: [f64; 3], direction: [f64; 3]) -> Ray {
        Ray::new(DVec3::from(origin), DVec3::from(direction)).unwrap()
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
