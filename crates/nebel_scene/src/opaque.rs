//! Opaque depth of a scene's plain meshes and terrain for the CPU reference
//! renderer.
//!
//! The reference integrates the volume only up to the first opaque surface
//! on each pixel's ray, like the GPU pass that reads the depth buffer. This
//! module intersects every pixel's ray with the scene's planes, boxes and
//! spheres in f64 and returns the view-space depth of the nearest hit (`+∞`
//! where the ray hits nothing), the layout
//! [`ReferenceScene::opaque_depth`](nebel_reference::ReferenceScene::opaque_depth)
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
//!
//! A terrain with ground fog is given as the triangles of the level of detail
//! the GPU draws ([`TerrainTriangles`], the same refinement as the fog's
//! cells), so the fog's bottom and the opaque ground are the same surface in
//! both renderers; it is marched the same way, its height at a point found
//! through a grid of the triangles over the terrain's cells.

use glam::{DVec2, DVec3};
use nebel_lod::TerrainMesh;

use super::{MeshDescription, SceneDescription, check_opaque_depth_budget};
use nebel_core::budget::BudgetError;
use nebel_core::cell::Ray;
use nebel_core::field::HeightField;
use nebel_core::occluder::Occluder;
use nebel_reference::ReferenceCamera;

impl SceneDescription {
    /// The scene's meshes as opaque shapes in f64 (what its rays end on and
    /// what shades the lights that cast shadows).
    pub fn occluders(&self) -> Vec<Occluder> {
        self.meshes.iter().map(MeshDescription::occluder).collect()
    }

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
        terrain: Option<&ReferenceTerrain>,
    ) -> Result<Option<Vec<f32>>, BudgetError> {
        if self.meshes.is_empty() && terrain.is_none() {
            return Ok(None);
        }
        check_opaque_depth_budget(camera.width, camera.height)?;
        let terrain = terrain.map(TerrainSurface::new);
        let occluders = self.occluders();
        let mut depth = Vec::with_capacity(camera.width as usize * camera.height as usize);
        for y in 0..camera.height {
            for x in 0..camera.width {
                let (ray, depth_to_distance) = camera.pixel_ray(x, y);
                let nearest = occluders
                    .iter()
                    .filter_map(|occluder| occluder.hit(&ray))
                    .chain(terrain.as_ref().and_then(|surface| surface.hit(&ray)))
                    .fold(f64::INFINITY, f64::min);
                depth.push((nearest * depth_to_distance) as f32);
            }
        }
        Ok(Some(depth))
    }
}

/// A terrain surface for the reference: the bilinear height field, or the
/// triangles of a level of detail (see the module docs).
#[derive(Clone, Debug)]
pub enum ReferenceTerrain {
    /// The full-resolution bilinear surface of heights in world space.
    Bilinear(HeightField),
    /// The triangles the GPU draws.
    Triangles(TerrainTriangles),
}

/// A terrain mesh's triangles in world space with a grid over its cells to
/// find the triangle under a point.
#[derive(Clone, Debug)]
pub struct TerrainTriangles {
    /// Corners of every triangle, world space.
    triangles: Vec<[DVec3; 3]>,
    /// World (x, z) of the grid's first corner.
    origin: DVec2,
    /// Grid cell size (the terrain's spacing) and cells per side.
    cell: DVec2,
    cells: [usize; 2],
    /// Per grid cell, the triangles overlapping it (`offsets` into `items`).
    offsets: Vec<u32>,
    items: Vec<u32>,
    /// The box around every triangle.
    min: DVec3,
    max: DVec3,
}

impl TerrainTriangles {
    /// The triangles of `mesh` placed by the translation `offset` (mesh
    /// frame to world), over a terrain of `side × side` grid points `spacing`
    /// apart.
    pub fn new(mesh: &TerrainMesh, offset: DVec3, side: usize, spacing: DVec2) -> Self {
        let corner = |v: u32| DVec3::from(mesh.positions[v as usize].map(f64::from)) + offset;
        let triangles: Vec<[DVec3; 3]> = mesh
            .indices
            .chunks_exact(3)
            .map(|t| [corner(t[0]), corner(t[1]), corner(t[2])])
            .collect();
        let cells = [side.saturating_sub(1).max(1); 2];
        let origin = DVec2::new(offset.x, offset.z);
        let (mut min, mut max) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
        let range = |t: &[DVec3; 3]| {
            let lo = t.iter().fold(DVec3::INFINITY, |m, p| m.min(*p));
            let hi = t.iter().fold(DVec3::NEG_INFINITY, |m, p| m.max(*p));
            let cell_of = |v: f64, o: f64, s: f64, n: usize| {
                (((v - o) / s).floor().max(0.0) as usize).min(n - 1)
            };
            (
                [
                    cell_of(lo.x, origin.x, spacing.x, cells[0]),
                    cell_of(hi.x - 1e-9 * spacing.x, origin.x, spacing.x, cells[0]),
                ],
                [
                    cell_of(lo.z, origin.y, spacing.y, cells[1]),
                    cell_of(hi.z - 1e-9 * spacing.y, origin.y, spacing.y, cells[1]),
                ],
                lo,
                hi,
            )
        };
        let mut counts = vec![0u32; cells[0] * cells[1] + 1];
        for t in &triangles {
            let ([i0, i1], [j0, j1], lo, hi) = range(t);
            min = min.min(lo);
            max = max.max(hi);
            for j in j0..=j1 {
                for i in i0..=i1 {
                    counts[i + cells[0] * j + 1] += 1;
                }
            }
        }
        for k in 1..counts.len() {
            counts[k] += counts[k - 1];
        }
        let mut fill = counts.clone();
        let mut items = vec![0u32; *counts.last().unwrap_or(&0) as usize];
        for (index, t) in triangles.iter().enumerate() {
            let ([i0, i1], [j0, j1], _, _) = range(t);
            for j in j0..=j1 {
                for i in i0..=i1 {
                    let slot = &mut fill[i + cells[0] * j];
                    items[*slot as usize] = index as u32;
                    *slot += 1;
                }
            }
        }
        Self {
            triangles,
            origin,
            cell: spacing,
            cells,
            offsets: counts,
            items,
            min,
            max,
        }
    }

    /// The mesh's height above world `(x, z)`, `None` outside it.
    fn height(&self, xz: DVec2) -> Option<f64> {
        let local = (xz - self.origin) / self.cell;
        let (i, j) = (local.x.floor(), local.y.floor());
        if !(i >= 0.0 && j >= 0.0) {
            return None;
        }
        let (i, j) = (
            (i as usize).min(self.cells[0] - 1),
            (j as usize).min(self.cells[1] - 1),
        );
        let cell = i + self.cells[0] * j;
        let range = self.offsets[cell] as usize..self.offsets[cell + 1] as usize;
        self.items[range].iter().find_map(|&index| {
            let [a, b, c] = self.triangles[index as usize];
            let (a2, b2, c2) = (
                DVec2::new(a.x, a.z),
                DVec2::new(b.x, b.z),
                DVec2::new(c.x, c.z),
            );
            let area = (b2 - a2).perp_dot(c2 - a2);
            let wa = (c2 - b2).perp_dot(xz - b2) / area;
            let wb = (a2 - c2).perp_dot(xz - c2) / area;
            let wc = 1.0 - wa - wb;
            let tolerance = -1e-9;
            (wa >= tolerance && wb >= tolerance && wc >= tolerance)
                .then_some(wa * a.y + wb * b.y + wc * c.y)
        })
    }
}

/// A terrain surface and the box around it.
struct TerrainSurface<'a> {
    terrain: &'a ReferenceTerrain,
    min: DVec3,
    max: DVec3,
    step: f64,
}

impl<'a> TerrainSurface<'a> {
    fn new(terrain: &'a ReferenceTerrain) -> Self {
        let (min, max, spacing) = match terrain {
            ReferenceTerrain::Bilinear(field) => {
                let [nx, nz] = field.dims();
                let spacing = field.spacing();
                let origin = field.origin();
                let (low, high) = field
                    .heights()
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &h| {
                        (lo.min(f64::from(h)), hi.max(f64::from(h)))
                    });
                (
                    DVec3::new(origin.x, low, origin.y),
                    DVec3::new(
                        origin.x + (nx - 1) as f64 * spacing.x,
                        high,
                        origin.y + (nz - 1) as f64 * spacing.y,
                    ),
                    spacing,
                )
            }
            ReferenceTerrain::Triangles(triangles) => {
                (triangles.min, triangles.max, triangles.cell)
            }
        };
        // A margin above and below, so a flat terrain's box is not a plane
        // a ray crosses in a single point.
        let margin = DVec3::new(0.0, 0.01 * spacing.min_element(), 0.0);
        Self {
            terrain,
            min: min - margin,
            max: max + margin,
            step: 0.5 * spacing.min_element(),
        }
    }

    /// How far `p` lies above the surface (negative below; outside the
    /// terrain, far above).
    fn above(&self, p: DVec3) -> f64 {
        let xz = DVec2::new(p.x, p.z);
        let ground = match self.terrain {
            ReferenceTerrain::Bilinear(field) => Some(field.sample(xz)),
            ReferenceTerrain::Triangles(triangles) => triangles.height(xz),
        };
        ground.map_or(f64::INFINITY, |h| p.y - h)
    }

    /// Distance along `ray` (unit direction) to where it first passes from
    /// above the surface (inside its box) to below it (see the module docs).
    fn hit(&self, ray: &Ray) -> Option<f64> {
        // The ray's stretch inside the box (a ray parallel to a pair of
        // faces is inside between them, on them included).
        let (mut near, mut far) = (0.0_f64, f64::INFINITY);
        for axis in 0..3 {
            let (origin, direction) = (ray.origin[axis], ray.direction[axis]);
            let (low, high) = (self.min[axis], self.max[axis]);
            if direction == 0.0 {
                if origin < low || origin > high {
                    return None;
                }
                continue;
            }
            let (a, b) = ((low - origin) / direction, (high - origin) / direction);
            near = near.max(a.min(b));
            far = far.min(a.max(b));
        }
        if near.partial_cmp(&far).is_none_or(std::cmp::Ordering::is_gt) {
            return None;
        }
        let above = |t: f64| self.above(ray.origin + t * ray.direction);
        let step = self.step;
        // The surface is seen from above only (its back is culled on the
        // GPU): the hit is the first crossing from above to below.
        let mut t0 = near;
        let mut was_above = above(t0) >= 0.0;
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
}

fn vector(v: [f32; 3]) -> DVec3 {
    DVec3::from(v.map(f64::from))
}

impl MeshDescription {
    /// The mesh as an opaque shape in f64.
    pub fn occluder(&self) -> Occluder {
        match self {
            MeshDescription::Plane(plane) => Occluder::Rectangle {
                centre: vector(plane.center),
                half_size: DVec2::new(f64::from(plane.size[0]), f64::from(plane.size[1])) / 2.0,
            },
            MeshDescription::Box(cuboid) => {
                let (centre, half) = (vector(cuboid.center), vector(cuboid.size) / 2.0);
                Occluder::Box {
                    min: centre - half,
                    max: centre + half,
                }
            }
            MeshDescription::Sphere(sphere) => Occluder::Sphere {
                centre: vector(sphere.center),
                radius: f64::from(sphere.radius),
            },
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
        let t = TerrainSurface::new(&ReferenceTerrain::Bilinear(field.clone()))
            .hit(&down)
            .unwrap();
        assert!((t - 8.0).abs() < 1e-7, "{t}");
        // Level from the left at y = 2.5: meets the ramp at x = 3.
        let level = ray([-5.0, 2.5, 1.5], [1.0, 0.0, 0.0]);
        let t = TerrainSurface::new(&ReferenceTerrain::Bilinear(field.clone()))
            .hit(&level)
            .unwrap();
        assert!((t - 8.0).abs() < 1e-7, "{t}");
        // Above the highest point, outside the grid, or pointing away: no hit.
        assert_eq!(
            TerrainSurface::new(&ReferenceTerrain::Bilinear(field.clone()))
                .hit(&ray([-5.0, 3.5, 1.5], [1.0, 0.0, 0.0])),
            None
        );
        assert_eq!(
            TerrainSurface::new(&ReferenceTerrain::Bilinear(field.clone()))
                .hit(&ray([9.0, 10.0, 2.0], [0.0, -1.0, 0.0])),
            None
        );
        assert_eq!(
            TerrainSurface::new(&ReferenceTerrain::Bilinear(field.clone()))
                .hit(&ray([2.0, 10.0, 2.0], [0.0, 1.0, 0.0])),
            None
        );
        // Below the surface the ray sees its back (culled on the GPU too)
        // until it comes out above: then it meets the front.
        assert_eq!(
            TerrainSurface::new(&ReferenceTerrain::Bilinear(field.clone()))
                .hit(&ray([2.0, 1.5, 2.0], [1.0, 0.0, 0.0])),
            None
        );
        assert_eq!(
            TerrainSurface::new(&ReferenceTerrain::Bilinear(field.clone()))
                .hit(&ray([2.0, 0.5, 2.0], [1.0, 0.0, 0.0])),
            None
        );
        let up_and_over = ray([-1.0, 0.5, 2.0], [3.0, 1.0, 0.0]);
        assert_eq!(
            TerrainSurface::new(&ReferenceTerrain::Bilinear(field.clone())).hit(&up_and_over),
            None
        );
        let out_and_back =
            Ray::new(DVec3::new(1.0, 1.2, 2.0), DVec3::new(-1.0, 0.05, 0.0)).unwrap();
        assert_eq!(
            TerrainSurface::new(&ReferenceTerrain::Bilinear(field.clone())).hit(&out_and_back),
            None
        );
        // A flat terrain (a box of no height) is met too, at any angle.
        let flat = HeightField::new([5, 5], DVec2::ONE, DVec2::ZERO, vec![2.0; 25]).unwrap();
        for direction in [[0.0, -1.0, 0.0], [1.0, -1.0, 0.5], [1.0, -0.35, 0.2]] {
            let oblique = ray([0.5, 3.0, 0.5], direction);
            let t = TerrainSurface::new(&ReferenceTerrain::Bilinear(flat.clone()))
                .hit(&oblique)
                .unwrap();
            assert!((oblique.at(t).y - 2.0).abs() < 1e-7, "{t}");
        }
    }

    #[test]
    fn a_ray_meets_the_level_of_detail_triangles() {
        use nebel_lod::{LodSettings, TerrainHierarchy};
        // A bumpy 17 × 17 terrain, coarsely refined: the triangles, not the
        // bilinear surface, are the ground.
        let heights = (0..289)
            .map(|p| 3.0 * ((p % 17) as f32 * 0.9).sin() * ((p / 17) as f32 * 0.7).cos())
            .collect();
        let field = HeightField::new(
            [17, 17],
            DVec2::splat(2.0),
            DVec2::new(-16.0, -16.0),
            heights,
        )
        .unwrap();
        let hierarchy = TerrainHierarchy::new(field, 2.0).unwrap();
        let mut mesh = TerrainMesh::new();
        let settings = LodSettings {
            accuracy: 3.0,
            ..LodSettings::default()
        };
        hierarchy
            .update(DVec3::new(0.0, 30.0, 0.0), None, &settings, &mut mesh)
            .unwrap();
        let offset = hierarchy.origin() + DVec3::new(5.0, 1.0, -2.0);
        let triangles = TerrainTriangles::new(&mesh, offset, 17, DVec2::splat(2.0));
        let terrain = ReferenceTerrain::Triangles(triangles.clone());
        let surface = TerrainSurface::new(&terrain);
        // Every vertex of the mesh, straight down and obliquely.
        for p in mesh.positions.iter().step_by(7) {
            let vertex = DVec3::from(p.map(f64::from)) + offset;
            for from in [DVec3::new(0.0, 50.0, 0.0), DVec3::new(-20.0, 40.0, 13.0)] {
                let down = Ray::new(vertex + from, -from).unwrap();
                let t = surface.hit(&down).unwrap();
                assert!((down.at(t) - vertex).length() < 1e-6, "{vertex} {from}");
            }
        }
        // Off the grid: no ground.
        assert_eq!(triangles.height(DVec2::new(offset.x - 1.0, offset.z)), None);
    }

    #[test]
    fn hits_are_the_nearest_surface_in_front() {
        let sphere = MeshDescription::Sphere(SphereDescription {
            center: [0.0, 0.0, -5.0],
            radius: 1.0,
            color: [1.0; 3],
        });
        assert_eq!(
            sphere.occluder().hit(&ray([0.0; 3], [0.0, 0.0, -1.0])),
            Some(4.0)
        );
        assert_eq!(
            sphere
                .occluder()
                .hit(&ray([0.0, 0.0, -5.0], [0.0, 0.0, -1.0])),
            Some(1.0)
        );
        assert_eq!(sphere.occluder().hit(&ray([0.0; 3], [0.0, 0.0, 1.0])), None);
        let cuboid = MeshDescription::Box(BoxDescription {
            center: [0.0, 0.0, -5.0],
            size: [2.0, 2.0, 2.0],
            color: [1.0; 3],
        });
        assert_eq!(
            cuboid.occluder().hit(&ray([0.0; 3], [0.0, 0.0, -1.0])),
            Some(4.0)
        );
        assert_eq!(
            cuboid
                .occluder()
                .hit(&ray([0.0, 3.0, 0.0], [0.0, 0.0, -1.0])),
            None
        );
        let plane = MeshDescription::Plane(PlaneDescription {
            center: [0.0, -1.0, 0.0],
            size: [4.0, 4.0],
            color: [1.0; 3],
        });
        let down = ray([0.0, 1.0, 0.0], [0.0, -1.0, 0.0]);
        assert_eq!(plane.occluder().hit(&down), Some(2.0));
        assert_eq!(
            plane
                .occluder()
                .hit(&ray([3.0, 1.0, 0.0], [0.0, -1.0, 0.0])),
            None
        );
        assert_eq!(
            plane.occluder().hit(&ray([0.0, 1.0, 0.0], [1.0, 0.0, 0.0])),
            None
        );
    }
}
