//! What the tests of prisms on a terrain and of layers between two surfaces
//! share: a valley with fog, random eyes and numbers, and the checks that
//! prisms conform, fill their columns and are in visibility order.

use std::collections::{HashMap, HashSet};

use glam::{DVec2, DVec3};
use nebel_core::cell::{Ray, Tetrahedron};
use nebel_core::field::{HeightField, ValueNoise};
use nebel_lod::quadtree::TerrainMap;
use nebel_lod::{GpuCell, TerrainHierarchy, TerrainMesh};

pub const SPACING: f64 = 10.0;

/// An fBm terrain of `n²` points, 0..300 m, and valley fog filling it up to
/// 120 m (zero thickness on the ridges), plus a noisy top.
pub fn valley(n: usize) -> (TerrainHierarchy, TerrainMap) {
    let noise = ValueNoise {
        seed: 3,
        octaves: 5,
        wavelength: 320.0,
        gain: 0.5,
    };
    let field = HeightField::value_noise(
        [n, n],
        DVec2::splat(SPACING),
        DVec2::new(-50.0, 20.0),
        &noise,
        300.0,
    )
    .unwrap();
    let thickness: Vec<f32> = field
        .heights()
        .iter()
        .enumerate()
        .map(|(p, h)| {
            let wobble = 6.0 * ((p % n) as f32 * 0.7).sin() * ((p / n) as f32 * 0.45).cos();
            120.0 + wobble - h
        })
        .collect();
    let layer = TerrainMap::new(n, thickness).unwrap();
    let hierarchy = TerrainHierarchy::new(field, 2.0)
        .unwrap()
        .with_map_roughness(&layer, 1.0)
        .unwrap();
    (hierarchy, layer)
}

/// `count` seeded random eyes over and around the terrain (200 m beyond
/// its edges), from 20 m below its lowest point to far above the fog.
pub fn random_eyes(
    hierarchy: &TerrainHierarchy,
    count: usize,
    seed: u64,
) -> Vec<(&'static str, DVec3)> {
    let extent = (hierarchy.size() - 1) as f64 * SPACING;
    let mut random = uniform(seed);
    (0..count)
        .map(|_| {
            let offset = DVec3::new(
                -200.0 + random() * (extent + 400.0),
                -20.0 + random() * 420.0,
                -200.0 + random() * (extent + 400.0),
            );
            ("a random eye", hierarchy.origin() + offset)
        })
        .collect()
}

pub fn key(p: [f32; 4]) -> [u32; 3] {
    [p[0].to_bits(), p[1].to_bits(), p[2].to_bits()]
}

/// Checks that every face is shared by two cells, or lies on the ground, on
/// the layer's top or on the grid's outer boundary (`extent` from `origin`).
pub fn assert_conforming(
    cells: &[GpuCell],
    mesh: &TerrainMesh,
    origin: DVec3,
    extent: f64,
    name: &str,
) {
    // Ground and top positions of every mesh vertex.
    let mut ground = HashSet::new();
    let mut top = HashSet::new();
    for (p, t) in mesh.positions.iter().zip(&mesh.map) {
        let world = |dy: f32| {
            let w = (origin
                + DVec3::new(
                    f64::from(p[0]),
                    f64::from(p[1]) + f64::from(dy),
                    f64::from(p[2]),
                ))
            .as_vec3();
            key([w.x, w.y, w.z, 0.0])
        };
        ground.insert(world(0.0));
        top.insert(world(*t));
    }
    let mut faces: HashMap<[[u32; 3]; 3], usize> = HashMap::new();
    for cell in cells {
        for skip in 0..4 {
            let mut face: Vec<[u32; 3]> = (0..4)
                .filter(|&v| v != skip)
                .map(|v| key(cell.vertices[v]))
                .collect();
            face.sort();
            face.dedup();
            if face.len() == 3 {
                *faces.entry([face[0], face[1], face[2]]).or_default() += 1;
            }
        }
    }
    let on_boundary = |face: &[[u32; 3]; 3]| {
        let xs = face.map(|p| f64::from(f32::from_bits(p[0])) - origin.x);
        let zs = face.map(|p| f64::from(f32::from_bits(p[2])) - origin.z);
        let all = |v: [f64; 3], target: f64| v.iter().all(|x| (x - target).abs() < 1e-3);
        all(xs, 0.0) || all(xs, extent) || all(zs, 0.0) || all(zs, extent)
    };
    for (face, count) in &faces {
        assert!(*count <= 2, "{name}: a face shared by {count} cells");
        if *count == 1 {
            let lies_on = |set: &HashSet<[u32; 3]>| face.iter().all(|p| set.contains(p));
            assert!(
                lies_on(&ground) || lies_on(&top) || on_boundary(face),
                "{name}: a crack at {face:?}"
            );
        }
    }
}

/// Checks that the cells fill each prism exactly: Σ volume = Σ area · mean
/// thickness.
pub fn assert_fills_the_prisms(cells: &[GpuCell], mesh: &TerrainMesh, name: &str) {
    let volume: f64 = cells.iter().map(|c| c.to_tetrahedron().volume()).sum();
    let expected: f64 = mesh
        .indices
        .chunks_exact(3)
        .map(|t| {
            let p = |k: usize| {
                let [x, _, z] = mesh.positions[t[k] as usize];
                DVec2::new(f64::from(x), f64::from(z))
            };
            let area = 0.5 * (p(1) - p(0)).perp_dot(p(2) - p(0)).abs();
            let mean = t
                .iter()
                .map(|&v| f64::from(mesh.map[v as usize]))
                .sum::<f64>()
                / 3.0;
            area * mean
        })
        .sum();
    assert!(
        (volume - expected).abs() <= 1e-4 * expected,
        "{name}: {volume} m³ against {expected} m³"
    );
}

/// Uniform numbers in [0, 1) from `seed` (a 64-bit LCG).
pub fn uniform(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Sorts the cells hit by `ray` by entry and checks that a nearer cell is
/// always drawn after a farther one; returns the cells hit.
pub fn check_ray_order(cells: &[Tetrahedron], ray: &Ray, what: &str) -> usize {
    let mut hits: Vec<(f64, f64, usize)> = cells
        .iter()
        .enumerate()
        .filter_map(|(index, cell)| {
            // The line's part in front of the eye.
            let segment = cell.intersect(ray)?;
            let entry = segment.t_entry.max(0.0);
            (segment.t_exit - entry > 1e-4).then_some((entry, segment.t_exit, index))
        })
        .collect();
    hits.sort_by(|a, b| a.0.total_cmp(&b.0));
    for pair in hits.windows(2) {
        let (near, far) = (pair[0], pair[1]);
        // Segments of one ray through a conforming mesh do not overlap.
        assert!(
            near.1 <= far.0 + 1e-3,
            "{what}: overlapping cells {near:?} {far:?}"
        );
        assert!(
            near.2 > far.2,
            "{what}: cell {} at {:.3} m is drawn before cell {} at {:.3} m behind it",
            near.2,
            near.0,
            far.2,
            far.0
        );
    }
    hits.len()
}

/// The linear interpolation over the mesh's triangles of `per_vertex` at
/// every grid point.
pub fn over_the_grid(n: usize, mesh: &TerrainMesh, per_vertex: impl Fn(usize) -> f64) -> Vec<f64> {
    let mut out = vec![f64::NAN; n * n];
    for t in mesh.indices.chunks_exact(3) {
        let g = [0, 1, 2].map(|k| mesh.grid_points[t[k] as usize].map(i64::from));
        let h = [0, 1, 2].map(|k| per_vertex(t[k] as usize));
        let total =
            (g[1][0] - g[0][0]) * (g[2][1] - g[0][1]) - (g[1][1] - g[0][1]) * (g[2][0] - g[0][0]);
        let lo = |a: usize| g.iter().map(|p| p[a]).min().unwrap();
        let hi = |a: usize| g.iter().map(|p| p[a]).max().unwrap();
        for j in lo(1)..=hi(1) {
            for i in lo(0)..=hi(0) {
                let w = [0, 1, 2].map(|k| {
                    let (a, b) = (g[(k + 1) % 3], g[(k + 2) % 3]);
                    (b[0] - a[0]) * (j - a[1]) - (b[1] - a[1]) * (i - a[0])
                });
                if w.iter().all(|&w| w * total.signum() >= 0) {
                    out[i as usize + n * j as usize] =
                        (0..3).map(|k| w[k] as f64 / total as f64 * h[k]).sum();
                }
            }
        }
    }
    out
}
