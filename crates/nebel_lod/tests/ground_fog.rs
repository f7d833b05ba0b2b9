//! Ground fog prisms on the terrain's level of detail: conforming, exactly the
//! fog's volume, back to front for every eye, continuous along a flight, left
//! out beyond a handoff distance, with a scalar from a value map, and bad
//! input as errors; and the same prisms for a layer between two crossing
//! surfaces, with the height above the bottom as their scalar, for aurora
//! curtains and for a cloud layer lit through the cloud above.

use std::collections::{HashMap, HashSet};

use glam::{DAffine3, DMat4, DVec2, DVec3};
use nebel_core::cell::{Ray, Tetrahedron};
use nebel_core::field::{AuroraCurtains, FogNoise, HeightField, ValueNoise};
use nebel_lod::quadtree::TerrainMap;
use nebel_lod::{
    AuroraShape, CellOrder, CloudLayerShape, FogProfile, Frustum, GpuCell, LayerTop, LayerView,
    LodSettings, PrismError, PrismInput, PrismScalar, PrismStats, SurfaceLayer, SurfaceLayerError,
    TerrainError, TerrainHierarchy, TerrainMesh, TriangleOrder, fog_prisms,
};

const SPACING: f64 = 10.0;

/// An fBm terrain of `n²` points, 0..300 m, and valley fog filling it up to
/// 120 m (zero thickness on the ridges), plus a noisy top.
fn valley(n: usize) -> (TerrainHierarchy, TerrainMap) {
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

fn refine(
    hierarchy: &TerrainHierarchy,
    layer: &TerrainMap,
    eye: DVec3,
    order: TriangleOrder,
    morph: bool,
) -> TerrainMesh {
    let settings = LodSettings {
        accuracy: 40.0,
        morph,
        normals: false,
        grid_points: true,
        order,
    };
    let mut mesh = TerrainMesh::new();
    hierarchy
        .update_with_map(eye, None, &settings, Some(layer), &mut mesh)
        .unwrap();
    mesh
}

fn prisms(
    hierarchy: &TerrainHierarchy,
    mesh: &TerrainMesh,
    eye: DVec3,
    mesh_order: TriangleOrder,
    order: CellOrder,
    profile: &FogProfile,
) -> (Vec<GpuCell>, PrismStats) {
    let mut cells = Vec::new();
    let input = PrismInput {
        world_from_mesh: DAffine3::from_translation(hierarchy.origin()),
        eye: eye - hierarchy.origin(),
        mesh_order,
        order,
        profile,
        scalar: PrismScalar::Profile,
        beyond: None,
    };
    let stats = fog_prisms(mesh, &input, &mut cells).unwrap();
    (cells, stats)
}

/// Eyes above the fog, inside it, exactly on its top, below the ground and
/// under the top on a steep slope, in world space.
fn eyes(hierarchy: &TerrainHierarchy, layer: &TerrainMap) -> Vec<(&'static str, DVec3)> {
    let n = hierarchy.size();
    let origin = hierarchy.origin();
    let at = |i: usize, j: usize, above_ground: f64| {
        let h = f64::from(hierarchy.field().height(i, j));
        origin + DVec3::new(i as f64 * SPACING, h + above_ground, j as f64 * SPACING)
    };
    // The deepest fog and the steepest fogged point.
    let deepest = (0..n * n)
        .max_by(|a, b| layer.values()[*a].total_cmp(&layer.values()[*b]))
        .unwrap();
    let (di, dj) = (deepest % n, deepest / n);
    let thickness = f64::from(layer.values()[deepest]);
    let steep = (1..n - 1)
        .flat_map(|j| (1..n - 1).map(move |i| (i, j)))
        .filter(|&(i, j)| layer.values()[i + n * j] > 5.0)
        .max_by(|&(a, b), &(c, d)| {
            let slope = |i: usize, j: usize| {
                let h = |i, j| hierarchy.field().height(i, j);
                (h(i + 1, j) - h(i - 1, j)).abs() + (h(i, j + 1) - h(i, j - 1)).abs()
            };
            slope(a, b).total_cmp(&slope(c, d))
        })
        .unwrap();
    vec![
        ("above the fog", origin + DVec3::new(-120.0, 600.0, 90.0)),
        (
            "inside the fog",
            at(di, dj, 0.5 * thickness) + DVec3::new(3.3, 0.0, 1.7),
        ),
        ("on the fog top", at(di, dj, thickness)),
        ("below the ground", at(di, dj, -15.0)),
        ("under the top on a steep slope", at(steep.0, steep.1, 2.0)),
        ("far and low", origin + DVec3::new(1500.0, 60.0, -700.0)),
    ]
}

/// `count` seeded random eyes over and around the terrain (200 m beyond
/// its edges), from 20 m below its lowest point to far above the fog.
fn random_eyes(
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

fn key(p: [f32; 4]) -> [u32; 3] {
    [p[0].to_bits(), p[1].to_bits(), p[2].to_bits()]
}

#[test]
fn prisms_conform_and_hold_exactly_the_fogs_volume() {
    let (hierarchy, layer) = valley(65);
    let extent = 64.0 * SPACING;
    let origin = hierarchy.origin();
    let random = random_eyes(&hierarchy, 8, 0x0f09);
    for (name, eye) in eyes(&hierarchy, &layer).into_iter().chain(random) {
        let mesh = refine(&hierarchy, &layer, eye, TriangleOrder::BackToFront, true);
        let profile = FogProfile::default();
        let (cells, stats) = prisms(
            &hierarchy,
            &mesh,
            eye,
            TriangleOrder::BackToFront,
            CellOrder::BackToFront,
            &profile,
        );
        assert_eq!(stats.tetrahedra, cells.len());
        assert!(
            stats.prisms > 100 && stats.prisms < mesh.triangle_count(),
            "{name}: {stats:?}"
        );
        assert_conforming(&cells, &mesh, origin, extent, name);
        assert_fills_the_prisms(&cells, &mesh, name);
    }
}

/// Checks that every face is shared by two cells, or lies on the ground, on
/// the layer's top or on the grid's outer boundary (`extent` from `origin`).
fn assert_conforming(
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
fn assert_fills_the_prisms(cells: &[GpuCell], mesh: &TerrainMesh, name: &str) {
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
fn uniform(seed: u64) -> impl FnMut() -> f64 {
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
fn check_ray_order(cells: &[Tetrahedron], ray: &Ray, what: &str) -> usize {
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

#[test]
fn back_to_front_is_a_visibility_order_for_every_eye_by_ray_tests() {
    let (hierarchy, layer) = valley(33);
    let mut random = uniform(0x5eed_u64);
    // A profile of three layers: chains of nine cells per column.
    let profile = FogProfile::new(vec![[0.0, 1.0], [0.3, 0.8], [0.7, 0.3], [1.0, 0.0]]).unwrap();
    for mesh_order in [TriangleOrder::BackToFront, TriangleOrder::FrontToBack] {
        let more = random_eyes(&hierarchy, 4, 0x5eed);
        for (name, eye) in eyes(&hierarchy, &layer).into_iter().chain(more) {
            let mesh = refine(&hierarchy, &layer, eye, mesh_order, true);
            let (cells, stats) = prisms(
                &hierarchy,
                &mesh,
                eye,
                mesh_order,
                CellOrder::BackToFront,
                &profile,
            );
            assert!(stats.tetrahedra > 0);
            let cells: Vec<Tetrahedron> = cells.iter().map(GpuCell::to_tetrahedron).collect();
            let mut hit = 0;
            for _ in 0..150 {
                // Toward a random point of the fogged region.
                let target = hierarchy.origin()
                    + DVec3::new(random() * 320.0, 40.0 + random() * 100.0, random() * 320.0);
                let ray = Ray::new(eye, target - eye).unwrap();
                hit += check_ray_order(&cells, &ray, &format!("{name} at {eye}, {mesh_order:?}"));
            }
            assert!(hit > 150, "{name}: the rays hit only {hit} cells");
        }
    }
}

/// The colour `ray` gets from `cells` composited back to front in their
/// drawn order, and in the order of their distance along the ray: each cell
/// emits its mean scalar `s` and has extinction `0.02 s` per metre (fog
/// about 100 m thick, optical depths up to 2).
fn composites(cells: &[Tetrahedron], ray: &Ray) -> (f64, f64) {
    let mut hits: Vec<(f64, usize, f64, f64)> = cells
        .iter()
        .enumerate()
        .filter_map(|(index, cell)| {
            let segment = cell.intersect(ray)?;
            let entry = segment.t_entry.max(0.0);
            let length = segment.t_exit - entry;
            let scalar = cell.scalars.iter().sum::<f64>() / 4.0;
            let alpha = 1.0 - (-0.02 * scalar * length.max(0.0)).exp();
            (length > 1e-4).then_some((entry, index, scalar, alpha))
        })
        .collect();
    let over = |hits: &[(f64, usize, f64, f64)]| {
        hits.iter().fold(0.0, |colour, (_, _, scalar, alpha)| {
            scalar * alpha + (1.0 - alpha) * colour
        })
    };
    hits.sort_by_key(|hit| hit.1);
    let drawn = over(&hits);
    hits.sort_by(|a, b| b.0.total_cmp(&a.0));
    (drawn, over(&hits))
}

#[test]
fn an_order_a_frame_old_costs_little_of_the_image() {
    // Built in the background, the prisms of a sorted fog are drawn a frame
    // or two after the eye they were refined and ordered for: 1 m away at
    // 60 m/s. Rays from the new eye meet cells out of order only where the
    // eye crossed the plane of a face between them.
    let (hierarchy, layer) = valley(33);
    let mut random = uniform(0x1a7e_u64);
    let profile = FogProfile::new(vec![[0.0, 1.0], [0.3, 0.8], [0.7, 0.3], [1.0, 0.0]]).unwrap();
    let (mut rays, mut wrong, mut squares, mut worst) = (0, 0, 0.0, 0.0_f64);
    let more = random_eyes(&hierarchy, 4, 0x1a7e);
    for (_, eye) in eyes(&hierarchy, &layer).into_iter().chain(more) {
        let angle = random() * std::f64::consts::TAU;
        let moved = eye + DVec3::new(angle.cos(), 0.2 * (random() - 0.5), angle.sin());
        let order = TriangleOrder::FrontToBack;
        let mesh = refine(&hierarchy, &layer, eye, order, true);
        let (cells, _) = prisms(
            &hierarchy,
            &mesh,
            eye,
            order,
            CellOrder::BackToFront,
            &profile,
        );
        let cells: Vec<Tetrahedron> = cells.iter().map(GpuCell::to_tetrahedron).collect();
        for _ in 0..300 {
            let target = hierarchy.origin()
                + DVec3::new(random() * 320.0, 40.0 + random() * 100.0, random() * 320.0);
            let ray = Ray::new(moved, target - moved).unwrap();
            let (drawn, exact) = composites(&cells, &ray);
            let error = (drawn - exact).abs();
            rays += 1;
            wrong += usize::from(error > 1e-9);
            squares += error * error;
            worst = worst.max(error);
        }
    }
    let rmse = (squares / f64::from(rays)).sqrt();
    println!("{wrong} of {rays} rays differ; RMSE {rmse:.2e}, max {worst:.2e}");
    // Half an 8-bit step in RMS over the rays into the fog.
    assert!(rmse <= 1.0 / 510.0, "RMSE {rmse:.2e}, max {worst:.2e}");
}

#[test]
fn culling_keeps_every_cell_the_frustum_sees_above_the_ground() {
    // A flat view skimming the fog's top from inside a valley: much of the
    // ground under the fog is below the frustum, the fog above it is not.
    let (hierarchy, layer) = valley(65);
    let n = hierarchy.size();
    let deepest = (0..n * n)
        .max_by(|a, b| layer.values()[*a].total_cmp(&layer.values()[*b]))
        .unwrap();
    let (i, j) = (deepest % n, deepest / n);
    let ground = f64::from(hierarchy.field().height(i, j));
    let top = ground + f64::from(layer.values()[deepest]);
    let eye = hierarchy.origin() + DVec3::new(i as f64 * SPACING, top - 1.0, j as f64 * SPACING);
    let profile = FogProfile::default();
    for yaw in [0.3_f64, 1.9, 3.5, 5.1] {
        let forward = DVec3::new(yaw.cos(), -0.02, yaw.sin());
        let clip_from_world = DMat4::perspective_infinite_reverse_rh(8f64.to_radians(), 3.0, 1.0)
            * DMat4::look_to_rh(eye, forward, DVec3::Y);
        let frustum = Frustum::from_view_projection(clip_from_world).unwrap();
        let settings = LodSettings {
            accuracy: 40.0,
            normals: false,
            grid_points: true,
            ..LodSettings::default()
        };
        let cells = |frustum: Option<&Frustum>| {
            let mut mesh = TerrainMesh::new();
            hierarchy
                .update_with_map(eye, frustum, &settings, Some(&layer), &mut mesh)
                .unwrap();
            prisms(
                &hierarchy,
                &mesh,
                eye,
                TriangleOrder::BackToFront,
                CellOrder::BackToFront,
                &profile,
            )
            .0
        };
        let (all, culled) = (cells(None), cells(Some(&frustum)));
        let kept: HashSet<[[u32; 3]; 4]> =
            culled.iter().map(|cell| cell.vertices.map(key)).collect();
        let seen: Vec<&GpuCell> = all
            .iter()
            .filter(|cell| (0..4).any(|v| frustum.contains_point(cell.position(v).as_dvec3())))
            .collect();
        assert!(
            seen.len() > 20,
            "yaw {yaw}: the view sees {} cells",
            seen.len()
        );
        for cell in seen {
            assert!(
                kept.contains(&cell.vertices.map(key)),
                "yaw {yaw}: a cell in view was culled: {cell:?}"
            );
        }
        assert!(culled.len() < all.len(), "yaw {yaw}: nothing culled");
    }
}

#[test]
fn zero_thickness_gives_no_cells_and_partly_zero_prisms_stay_exact() {
    let (hierarchy, _) = valley(33);
    let n = hierarchy.size();
    let eye = hierarchy.origin() + DVec3::new(100.0, 500.0, 100.0);
    let zero = TerrainMap::new(n, vec![0.0; n * n]).unwrap();
    assert!(zero.is_zero());
    let mesh = refine(&hierarchy, &zero, eye, TriangleOrder::BackToFront, true);
    for order in [CellOrder::BackToFront, CellOrder::Unordered] {
        let (cells, stats) = prisms(
            &hierarchy,
            &mesh,
            eye,
            TriangleOrder::BackToFront,
            order,
            &FogProfile::default(),
        );
        assert!(cells.is_empty());
        assert_eq!(stats, PrismStats::default());
    }
    // One fogged grid point: only the triangles around it have prisms, each
    // one piece per layer (the two pieces whose top vertex has no
    // thickness are dropped), and their volume is area · t/3.
    let mut values = vec![0.0; n * n];
    let centre = n / 2 + n * (n / 2);
    values[centre] = 9.0;
    let spike = TerrainMap::new(n, values).unwrap();
    let settings = LodSettings {
        accuracy: 1e6,
        grid_points: true,
        normals: false,
        ..LodSettings::default()
    };
    let mut mesh = TerrainMesh::new();
    hierarchy
        .update_with_map(eye, None, &settings, Some(&spike), &mut mesh)
        .unwrap();
    let (cells, stats) = prisms(
        &hierarchy,
        &mesh,
        eye,
        TriangleOrder::BackToFront,
        CellOrder::BackToFront,
        &FogProfile::default(),
    );
    assert_eq!(
        stats.prisms, 8,
        "the full grid has eight triangles around a point"
    );
    assert_eq!(cells.len(), 8);
    let volume: f64 = cells.iter().map(|c| c.to_tetrahedron().volume()).sum();
    let expected = 8.0 * 0.5 * SPACING * SPACING * 9.0 / 3.0;
    assert!(
        (volume - expected).abs() < 1e-3 * expected,
        "{volume} vs {expected}"
    );
}

#[test]
fn the_scalar_follows_the_profile_exactly_where_the_thickness_is_constant() {
    let noise = ValueNoise {
        seed: 9,
        octaves: 3,
        wavelength: 80.0,
        gain: 0.5,
    };
    let n = 17;
    let field =
        HeightField::value_noise([n, n], DVec2::splat(SPACING), DVec2::ZERO, &noise, 40.0).unwrap();
    let hierarchy = TerrainHierarchy::new(field, 2.0).unwrap();
    let layer = TerrainMap::new(n, vec![12.0; n * n]).unwrap();
    let profile = FogProfile::new(vec![[0.0, 0.2], [0.25, 1.0], [1.0, 0.0]]).unwrap();
    let eye = DVec3::new(30.0, 200.0, 40.0);
    let mesh = refine(&hierarchy, &layer, eye, TriangleOrder::BackToFront, false);
    let (cells, _) = prisms(
        &hierarchy,
        &mesh,
        eye,
        TriangleOrder::BackToFront,
        CellOrder::BackToFront,
        &profile,
    );
    let cells: Vec<Tetrahedron> = cells.iter().map(GpuCell::to_tetrahedron).collect();
    let expected = |r: f64| {
        if r <= 0.25 {
            0.2 + 0.8 * r / 0.25
        } else {
            1.0 - (r - 0.25) / 0.75
        }
    };
    for (x, z) in [(33.3, 71.7), (101.2, 12.9), (140.1, 150.6)] {
        let ray = Ray::new(DVec3::new(x, 500.0, z), DVec3::NEG_Y).unwrap();
        let mut segments: Vec<_> = cells
            .iter()
            .filter_map(|c| c.intersect(&ray))
            .filter(|s| s.length() > 1e-6)
            .collect();
        segments.sort_by(|a, b| a.t_entry.total_cmp(&b.t_entry));
        let top = 500.0 - segments[0].t_entry;
        let bottom = 500.0 - segments.last().unwrap().t_exit;
        assert!(((top - bottom) - 12.0).abs() < 1e-3, "{top} {bottom}");
        for segment in &segments {
            for (t, s) in [
                (segment.t_entry, segment.s_entry),
                (segment.t_exit, segment.s_exit),
            ] {
                let r = (500.0 - t - bottom) / 12.0;
                assert!(
                    (s - expected(r)).abs() < 1e-4,
                    "at r = {r}: {s} vs {}",
                    expected(r)
                );
            }
        }
    }
}

/// The fog top at every grid point: the mesh's top surface interpolated over
/// its triangles.
fn fog_top(n: usize, mesh: &TerrainMesh) -> Vec<f64> {
    over_the_grid(n, mesh, |v| {
        f64::from(mesh.positions[v][1]) + f64::from(mesh.map[v])
    })
}

/// The linear interpolation over the mesh's triangles of `per_vertex` at
/// every grid point.
fn over_the_grid(n: usize, mesh: &TerrainMesh, per_vertex: impl Fn(usize) -> f64) -> Vec<f64> {
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

#[test]
fn the_fog_top_morphs_continuously_along_a_flight() {
    let (hierarchy, layer) = valley(129);
    let n = hierarchy.size();
    let largest_jump = |morph: bool| {
        let mut previous: Option<Vec<f64>> = None;
        let mut largest = 0.0_f64;
        for frame in 0..300 {
            let s = frame as f64 * 2.0;
            let eye = hierarchy.origin() + DVec3::new(100.0 + s, 250.0 - 0.2 * s, 200.0 + 0.5 * s);
            let mesh = refine(&hierarchy, &layer, eye, TriangleOrder::BackToFront, morph);
            let now = fog_top(n, &mesh);
            assert!(
                now.iter().all(|h| h.is_finite()),
                "the mesh covers the grid"
            );
            if let Some(before) = &previous {
                for (h, b) in now.iter().zip(before) {
                    largest = largest.max((h - b).abs());
                }
            }
            previous = Some(now);
        }
        largest
    };
    let (morph, pop) = (largest_jump(true), largest_jump(false));
    println!("largest fog-top jump per 2 m frame: {morph:.3} m with morphing, {pop:.3} m without");
    assert!(morph < 0.2, "{morph}");
    assert!(pop > 5.0 * morph, "{pop} vs {morph}");
}

#[test]
fn bad_input_is_an_error() {
    let (hierarchy, layer) = valley(33);
    let eye = DVec3::new(0.0, 400.0, 0.0);
    let mut mesh = TerrainMesh::new();
    let settings = LodSettings {
        grid_points: true,
        ..LodSettings::default()
    };
    // A layer of another size.
    let other = TerrainMap::new(17, vec![1.0; 17 * 17]).unwrap();
    let error = hierarchy
        .update_with_map(eye, None, &settings, Some(&other), &mut mesh)
        .unwrap_err();
    assert!(
        matches!(error, TerrainError::DimsMismatch { .. }),
        "{error}"
    );
    // A mesh without the layer or without grid points.
    hierarchy.update(eye, None, &settings, &mut mesh).unwrap();
    let profile = FogProfile::default();
    let input = PrismInput {
        world_from_mesh: DAffine3::IDENTITY,
        eye,
        mesh_order: TriangleOrder::BackToFront,
        order: CellOrder::BackToFront,
        profile: &profile,
        scalar: PrismScalar::Profile,
        beyond: None,
    };
    let mut cells = Vec::new();
    assert_eq!(
        fog_prisms(&mesh, &input, &mut cells),
        Err(PrismError::MissingMap)
    );
    // Sorted fog from an unordered mesh.
    let unordered = LodSettings {
        order: TriangleOrder::Unordered,
        ..settings
    };
    hierarchy
        .update_with_map(eye, None, &unordered, Some(&layer), &mut mesh)
        .unwrap();
    let input = PrismInput {
        mesh_order: TriangleOrder::Unordered,
        ..input
    };
    assert_eq!(
        fog_prisms(&mesh, &input, &mut cells),
        Err(PrismError::UnorderedMesh)
    );
    let unsorted = PrismInput {
        order: CellOrder::Unordered,
        ..input
    };
    assert!(fog_prisms(&mesh, &unsorted, &mut cells).unwrap().tetrahedra > 0);
    // Profiles that are not functions on [0, 1].
    for points in [
        vec![[0.0, 1.0]],
        vec![[0.1, 1.0], [1.0, 0.0]],
        vec![[0.0, 1.0], [0.5, 0.5], [0.5, 0.2], [1.0, 0.0]],
        vec![[0.0, 1.5], [1.0, 0.0]],
        vec![[0.0, f32::NAN], [1.0, 0.0]],
    ] {
        let error = FogProfile::new(points).unwrap_err();
        assert!(error.to_string().contains("fog profile"), "{error}");
    }
}

#[test]
fn columns_beyond_the_handoff_distance_are_left_out_and_no_nearer_one() {
    let (hierarchy, layer) = valley(65);
    let profile = FogProfile::default();
    let random = random_eyes(&hierarchy, 4, 0xbe70);
    for (name, eye) in eyes(&hierarchy, &layer).into_iter().chain(random) {
        let mesh = refine(&hierarchy, &layer, eye, TriangleOrder::BackToFront, true);
        let input = |beyond| PrismInput {
            world_from_mesh: DAffine3::from_translation(hierarchy.origin()),
            eye: eye - hierarchy.origin(),
            mesh_order: TriangleOrder::BackToFront,
            order: CellOrder::BackToFront,
            profile: &profile,
            scalar: PrismScalar::Profile,
            beyond,
        };
        let mut all = Vec::new();
        fog_prisms(&mesh, &input(None), &mut all).unwrap();
        let distance = 0.25 * 64.0 * SPACING;
        let mut near = Vec::new();
        let stats = fog_prisms(&mesh, &input(Some((eye, distance))), &mut near).unwrap();
        assert_eq!(stats.tetrahedra, near.len());
        // The kept cells are cells of the whole set, in the same order...
        let mut rest = all.iter();
        for cell in &near {
            assert!(
                rest.any(|c| c == cell),
                "{name}: a kept cell is not in the whole set"
            );
        }
        // ...and every cell with a point nearer than the distance is kept.
        let nearest = |cell: &GpuCell| {
            cell.vertices
                .iter()
                .map(|v| {
                    DVec3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2])).distance(eye)
                })
                .fold(f64::INFINITY, f64::min)
        };
        let needed = all.iter().filter(|cell| nearest(cell) <= distance).count();
        let kept = near.iter().filter(|cell| nearest(cell) <= distance).count();
        assert_eq!(kept, needed, "{name}");
        assert!(
            near.len() < all.len(),
            "{name}: {} of {} cells kept",
            near.len(),
            all.len()
        );
    }
}

/// A value map over the grid of `n²` points, in [0.1, 0.9].
fn value_map(n: usize) -> TerrainMap {
    let values = (0..n * n)
        .map(|p| {
            let (i, j) = ((p % n) as f32, (p / n) as f32);
            0.5 + 0.4 * (0.31 * i).sin() * (0.17 * j + 0.5).cos()
        })
        .collect();
    TerrainMap::new(n, values).unwrap()
}

#[test]
fn a_value_map_gives_the_scalar_of_a_layer_between_two_surfaces_without_popping() {
    let (hierarchy, layer) = valley(129);
    let n = hierarchy.size();
    let values = value_map(n);
    let refine_with = |eye: DVec3, accuracy: f32, morph: bool| {
        let settings = LodSettings {
            accuracy,
            morph,
            normals: false,
            grid_points: true,
            order: TriangleOrder::BackToFront,
        };
        let mut mesh = TerrainMesh::new();
        hierarchy
            .update_with_maps(eye, None, &settings, Some(&layer), Some(&values), &mut mesh)
            .unwrap();
        mesh
    };
    let eye = hierarchy.origin() + DVec3::new(300.0, 400.0, 500.0);
    // Fully refined, every vertex carries its grid point's value, and every
    // cell vertex the value of its column vertex, on every level.
    let fine = refine_with(eye, 1e7, true);
    assert_eq!(fine.values.len(), fine.positions.len());
    for (v, [i, j]) in fine.grid_points.iter().enumerate() {
        assert_eq!(
            fine.values[v],
            values.values()[*i as usize + n * *j as usize]
        );
    }
    let profile = FogProfile::new(vec![[0.0, 0.0], [0.5, 0.5], [1.0, 1.0]]).unwrap();
    let input = PrismInput {
        world_from_mesh: DAffine3::from_translation(hierarchy.origin()),
        eye: eye - hierarchy.origin(),
        mesh_order: TriangleOrder::BackToFront,
        order: CellOrder::BackToFront,
        profile: &profile,
        scalar: PrismScalar::Values,
        beyond: None,
    };
    let mut cells = Vec::new();
    fog_prisms(&fine, &input, &mut cells).unwrap();
    assert!(!cells.is_empty());
    let column_value: HashMap<[u32; 2], f32> = fine
        .positions
        .iter()
        .zip(&fine.values)
        .map(|(p, value)| {
            let world = hierarchy.origin() + DVec3::new(f64::from(p[0]), 0.0, f64::from(p[2]));
            (
                [(world.x as f32).to_bits(), (world.z as f32).to_bits()],
                *value,
            )
        })
        .collect();
    for cell in &cells {
        for [x, _, z, scalar] in cell.vertices {
            assert_eq!(Some(&scalar), column_value.get(&[x.to_bits(), z.to_bits()]));
        }
    }
    // Along a flight the values morph with the terrain's weights: the value
    // surface over the grid moves by a little per frame, where without
    // morphing it jumps as points become vertices.
    let largest_jump = |morph: bool| {
        let mut previous: Option<Vec<f64>> = None;
        let mut largest = 0.0_f64;
        for frame in 0..200 {
            let s = frame as f64 * 2.0;
            let eye = hierarchy.origin() + DVec3::new(100.0 + s, 250.0 - 0.2 * s, 200.0 + 0.5 * s);
            let mesh = refine_with(eye, 40.0, morph);
            let now = over_the_grid(n, &mesh, |v| f64::from(mesh.values[v]));
            if let Some(before) = &previous {
                for (value, b) in now.iter().zip(before) {
                    largest = largest.max((value - b).abs());
                }
            }
            previous = Some(now);
        }
        largest
    };
    let (morph, pop) = (largest_jump(true), largest_jump(false));
    println!("largest value jump per 2 m frame: {morph:.4} with morphing, {pop:.4} without");
    assert!(morph < 0.01, "{morph}");
    assert!(pop > 5.0 * morph, "{pop} vs {morph}");

    // Bad input: values of another size, values without a layer, the
    // values' scalar from a mesh without values.
    let settings = LodSettings {
        grid_points: true,
        ..LodSettings::default()
    };
    let mut mesh = TerrainMesh::new();
    let small = value_map(17);
    assert!(matches!(
        hierarchy.update_with_maps(eye, None, &settings, Some(&layer), Some(&small), &mut mesh),
        Err(TerrainError::DimsMismatch { .. })
    ));
    assert!(matches!(
        hierarchy.update_with_maps(eye, None, &settings, None, Some(&values), &mut mesh),
        Err(TerrainError::InvalidParameter { .. })
    ));
    hierarchy
        .update_with_map(eye, None, &settings, Some(&layer), &mut mesh)
        .unwrap();
    assert!(mesh.values.is_empty());
    assert_eq!(
        fog_prisms(&mesh, &input, &mut cells),
        Err(PrismError::MissingValues)
    );
}

/// A layer between the valley's ground and a second noise surface that
/// crosses it (the top dips below the bottom over the ridges).
fn crossing_layer(n: usize) -> (HeightField, Vec<f32>) {
    let (hierarchy, _) = valley(n);
    let bottom = hierarchy.field().clone();
    let noise = ValueNoise {
        seed: 11,
        octaves: 4,
        wavelength: 200.0,
        gain: 0.5,
    };
    let upper = HeightField::value_noise(
        [n, n],
        DVec2::splat(SPACING),
        DVec2::new(-50.0, 20.0),
        &noise,
        160.0,
    )
    .unwrap();
    let top = upper.heights().iter().map(|h| 80.0 + h).collect();
    (bottom, top)
}

#[test]
fn a_layer_between_two_crossing_surfaces_conforms_is_ordered_and_carries_its_height() {
    let n = 65;
    let (bottom, top) = crossing_layer(n);
    let layer = SurfaceLayer::new(bottom.clone(), LayerTop::Surface(&top), None, 2.0, 1.0).unwrap();
    // The thickness is top − bottom, clamped to 0 where they cross; both
    // signs occur.
    let mut crossed = 0;
    for (p, t) in layer.thickness().values().iter().enumerate() {
        let difference = top[p] - bottom.heights()[p];
        assert_eq!(*t, difference.max(0.0));
        crossed += usize::from(difference < 0.0);
    }
    assert!(
        crossed > n && crossed < n * n / 2,
        "{crossed} points crossed"
    );
    let hierarchy = layer.hierarchy();
    let origin = hierarchy.origin();
    let extent = (n - 1) as f64 * SPACING;
    let span = 250.0;
    let profile = FogProfile::new(vec![[0.0, 0.0], [0.4, 0.4], [1.0, 1.0]]).unwrap();
    let mut random = uniform(0x1a7e_u64);
    let named = [
        ("below both", origin + DVec3::new(300.0, -80.0, 250.0)),
        ("between them", origin + DVec3::new(333.0, 230.0, 311.0)),
        ("above both", origin + DVec3::new(-100.0, 900.0, 500.0)),
    ];
    let random_eyes = random_eyes(hierarchy, 3, 0x2f);
    for (name, eye) in named.into_iter().chain(random_eyes) {
        let view = |order| LayerView {
            world_from_field: DAffine3::IDENTITY,
            eye,
            frustum: None,
            lod: LodSettings {
                accuracy: 40.0,
                ..LodSettings::default()
            },
            order,
            profile: &profile,
            scalar: PrismScalar::Height { span },
        };
        let mut mesh = TerrainMesh::new();
        let mut cells = Vec::new();
        let stats = layer
            .cells(&view(CellOrder::BackToFront), &mut mesh, &mut cells)
            .unwrap();
        assert_eq!(stats.tetrahedra, cells.len());
        assert_eq!(stats.triangles, mesh.triangle_count());
        // Only the triangles with a layer above a corner carry prisms.
        let layered = mesh
            .indices
            .chunks_exact(3)
            .filter(|t| t.iter().any(|&v| mesh.map[v as usize] > 0.0))
            .count();
        assert_eq!(stats.prisms, layered, "{name}");
        assert!(
            stats.prisms > 50 && stats.prisms < stats.triangles,
            "{name}: {stats:?}"
        );
        assert_conforming(&cells, &mesh, origin, extent, name);
        assert_fills_the_prisms(&cells, &mesh, name);
        // The scalar is the height above the bottom over the span at every
        // vertex (the bottom of each column is its mesh vertex).
        let ground: HashMap<[u32; 2], f64> = mesh
            .positions
            .iter()
            .map(|p| {
                let w = origin + DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                ([(w.x as f32).to_bits(), (w.z as f32).to_bits()], w.y)
            })
            .collect();
        for cell in &cells {
            for [x, y, z, s] in cell.vertices {
                let below = ground[&[x.to_bits(), z.to_bits()]];
                let expected = ((f64::from(y) - below) / f64::from(span)).clamp(0.0, 1.0);
                assert!(
                    (f64::from(s) - expected).abs() < 1e-5,
                    "{name}: {s} vs {expected}"
                );
            }
        }
        // Back to front for the eye by ray tests.
        let tetrahedra: Vec<Tetrahedron> = cells.iter().map(GpuCell::to_tetrahedron).collect();
        let mut hit = 0;
        for _ in 0..60 {
            let target =
                origin + DVec3::new(random() * extent, random() * 300.0, random() * extent);
            let ray = Ray::new(eye, target - eye).unwrap();
            hit += check_ray_order(&tetrahedra, &ray, name);
        }
        assert!(hit > 60, "{name}: the rays hit only {hit} cells");
        // Unordered: the same cells.
        let mut unordered = Vec::new();
        layer
            .cells(&view(CellOrder::Unordered), &mut mesh, &mut unordered)
            .unwrap();
        let set = |cells: &[GpuCell]| {
            let mut keys: Vec<[[u32; 3]; 4]> =
                cells.iter().map(|cell| cell.vertices.map(key)).collect();
            keys.sort();
            keys
        };
        assert_eq!(set(&unordered), set(&cells), "{name}");
    }
    // Surfaces that meet everywhere give no cells.
    let flat = SurfaceLayer::new(
        bottom.clone(),
        LayerTop::Surface(bottom.heights()),
        None,
        2.0,
        1.0,
    )
    .unwrap();
    assert!(flat.is_empty());
    let mut cells = Vec::new();
    let view = LayerView {
        world_from_field: DAffine3::IDENTITY,
        eye: origin + DVec3::new(10.0, 500.0, 10.0),
        frustum: None,
        lod: LodSettings::default(),
        order: CellOrder::Unordered,
        profile: &profile,
        scalar: PrismScalar::Height { span },
    };
    let stats = flat
        .cells(&view, &mut TerrainMesh::new(), &mut cells)
        .unwrap();
    assert!(cells.is_empty() && stats.prisms == 0 && stats.triangles > 0);
}

#[test]
fn a_layer_between_two_surfaces_refuses_bad_input() {
    let n = 33;
    let (bottom, top) = crossing_layer(n);
    let build = |top: &[f32], values: Option<&[f32]>, weight: f32| {
        SurfaceLayer::new(bottom.clone(), LayerTop::Surface(top), values, 2.0, weight)
    };
    let mut nan = top.clone();
    nan[7] = f32::NAN;
    let messages = [
        build(&nan, None, 1.0),
        build(&top[1..], None, 1.0),
        build(&top, Some(&[0.5; 10]), 1.0),
        build(&top, None, f32::NAN),
        SurfaceLayer::new(
            bottom.clone(),
            LayerTop::Thickness(&[f32::INFINITY; 33 * 33]),
            None,
            2.0,
            1.0,
        ),
    ]
    .map(|built| built.unwrap_err().to_string());
    for (message, needle) in messages
        .iter()
        .zip(["NaN", "values", "values", "weight", "inf"])
    {
        assert!(message.contains(needle), "{message}");
    }
    // A bottom that is not 2^k + 1 points per side.
    let odd = HeightField::new([20, 20], DVec2::ONE, DVec2::ZERO, vec![0.0; 400]).unwrap();
    assert!(matches!(
        SurfaceLayer::new(odd, LayerTop::Thickness(&[1.0; 400]), None, 2.0, 1.0),
        Err(SurfaceLayerError::Terrain(
            TerrainError::NotPowerOfTwoPlusOne { .. }
        ))
    ));
    // A height span that is not positive.
    let layer = build(&top, None, 1.0).unwrap();
    let profile = FogProfile::default();
    for span in [0.0, -1.0, f32::NAN] {
        let view = LayerView {
            world_from_field: DAffine3::IDENTITY,
            eye: DVec3::new(0.0, 500.0, 0.0),
            frustum: None,
            lod: LodSettings::default(),
            order: CellOrder::Unordered,
            profile: &profile,
            scalar: PrismScalar::Height { span },
        };
        let error = layer
            .cells(&view, &mut TerrainMesh::new(), &mut Vec::new())
            .unwrap_err();
        assert!(
            matches!(
                error,
                SurfaceLayerError::Prisms(PrismError::InvalidSpan { .. })
            ),
            "{error}"
        );
    }
}

#[test]
fn aurora_curtains_rise_as_high_as_they_are_strong_and_are_coloured_by_altitude() {
    let side = 129;
    let strength = AuroraCurtains::default().map(side, 2.0).unwrap();
    let shape = AuroraShape {
        extent: 600e3,
        bottom: 100e3,
        top: 300e3,
    };
    let layer = shape.layer(side, &strength, 2.0, 1.0).unwrap();
    let profile = AuroraShape::profile();
    let view = LayerView {
        world_from_field: DAffine3::from_translation(DVec3::new(5e3, 0.0, -7e3)),
        eye: DVec3::new(0.0, 2.0, 0.0),
        frustum: None,
        lod: LodSettings {
            accuracy: 20.0,
            ..LodSettings::default()
        },
        order: CellOrder::Unordered,
        profile: &profile,
        scalar: shape.scalar(),
    };
    let mut mesh = TerrainMesh::new();
    let mut cells = Vec::new();
    let stats = layer.cells(&view, &mut mesh, &mut cells).unwrap();
    assert!(stats.tetrahedra > 100, "{stats:?}");
    // The quadtree refines along the curtains, coarse over the dark sky
    // between them, which has no prisms.
    assert!(stats.prisms < stats.triangles, "{stats:?}");
    assert!(stats.triangles < 2 * 128 * 128 / 3, "{stats:?}");
    let origin = layer.hierarchy().origin() + DVec3::new(5e3, 0.0, -7e3);
    assert_fills_the_prisms(&cells, &mesh, "aurora");
    let spacing = 600e3 / (side - 1) as f64;
    for cell in &cells {
        for [_, y, _, s] in cell.vertices {
            let altitude = f64::from(y);
            assert!(
                (100e3 - 1.0..=300e3 + 1.0).contains(&altitude),
                "{altitude}"
            );
            // Coloured by altitude: the scalar is the height over the span.
            let expected = (altitude - 100e3) / 200e3;
            assert!((f64::from(s) - expected).abs() < 1e-4, "{s} vs {expected}");
        }
    }
    // Without morphing every column stands on a grid point and rises to
    // exactly its strength times the span.
    let unmorphed = LayerView {
        lod: LodSettings {
            morph: false,
            ..view.lod
        },
        ..view
    };
    layer.cells(&unmorphed, &mut mesh, &mut cells).unwrap();
    for cell in &cells {
        for [x, y, z, _] in cell.vertices {
            let (i, j) = (
                ((f64::from(x) - origin.x) / spacing).round() as usize,
                ((f64::from(z) - origin.z) / spacing).round() as usize,
            );
            let height = f64::from(y) - 100e3;
            let top = f64::from(strength[i + side * j]) * 200e3;
            assert!(
                height.abs() < 0.02 || (height - top).abs() < 0.02,
                "{height} m above the bottom at ({i}, {j}), where the curtain rises {top} m"
            );
        }
    }
    // No strength anywhere, no cells; bad shapes and strengths are errors.
    let dark = shape
        .layer(side, &vec![0.0; side * side], 2.0, 1.0)
        .unwrap();
    assert!(dark.is_empty());
    let mut nan = strength.clone();
    nan[side * 60 + 60] = f32::NAN;
    for (built, needle) in [
        (shape.layer(side, &nan, 2.0, 1.0), "NaN"),
        (shape.layer(side, &strength[1..], 2.0, 1.0), "values"),
        (
            AuroraShape { top: 50e3, ..shape }.layer(side, &strength, 2.0, 1.0),
            "top",
        ),
        (
            AuroraShape {
                extent: f64::INFINITY,
                ..shape
            }
            .layer(side, &strength, 2.0, 1.0),
            "extent",
        ),
        (
            AuroraShape {
                bottom: f64::NAN,
                ..shape
            }
            .layer(side, &strength, 2.0, 1.0),
            "bottom",
        ),
    ] {
        let message = built.unwrap_err().to_string();
        assert!(message.contains(needle), "{message}");
    }
}

#[test]
fn a_cloud_layer_is_conforming_sorted_and_lit_through_the_cloud_above() {
    let side = 65;
    let extent = 20e3;
    let noise = FogNoise {
        thickness: 600.0,
        coverage: 0.5,
        ..FogNoise::default()
    };
    let thickness = noise.thickness(side, extent / 64.0).unwrap();
    let shape = CloudLayerShape {
        extent,
        base: 1500.0,
        sag: 0.2,
    };
    let layer = shape.layer(side, &thickness, 2.0, 1.0).unwrap();
    let profile = CloudLayerShape::profile();
    let (extinction, sun_height, ambient, diffuse) = (0.004_f32, 0.7_f32, 0.3_f32, 0.7_f32);
    let origin = layer.hierarchy().origin();
    let mut random = uniform(0xc10d_u64);
    for (name, eye) in [
        ("below", DVec3::new(300.0, 200.0, -700.0)),
        ("inside", DVec3::new(-2100.0, 1550.0, 3300.0)),
        ("above", DVec3::new(4000.0, 5000.0, 1000.0)),
    ] {
        let view = LayerView {
            world_from_field: DAffine3::IDENTITY,
            eye,
            frustum: None,
            lod: LodSettings {
                accuracy: 30.0,
                ..LodSettings::default()
            },
            order: CellOrder::BackToFront,
            profile: &profile,
            scalar: PrismScalar::Sunlit {
                extinction,
                sun_height,
                ambient,
                diffuse,
            },
        };
        let mut mesh = TerrainMesh::new();
        let mut cells = Vec::new();
        let stats = layer.cells(&view, &mut mesh, &mut cells).unwrap();
        assert!(
            stats.prisms > 50 && stats.prisms < stats.triangles,
            "{name}: {stats:?}"
        );
        assert_conforming(&cells, &mesh, origin, extent, name);
        assert_fills_the_prisms(&cells, &mesh, name);
        // The light at every vertex: the sun through the cloud above it in
        // its column.
        let columns: HashMap<[u32; 2], (f64, f64)> = mesh
            .positions
            .iter()
            .zip(&mesh.map)
            .map(|(p, t)| {
                let w = origin + DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                (
                    [(w.x as f32).to_bits(), (w.z as f32).to_bits()],
                    (w.y, w.y + f64::from(*t)),
                )
            })
            .collect();
        for cell in &cells {
            for [x, y, z, s] in cell.vertices {
                let (_, top) = columns[&[x.to_bits(), z.to_bits()]];
                let depth = (top - f64::from(y)).max(0.0);
                let transmittance = (-f64::from(extinction) * depth / f64::from(sun_height)).exp();
                let expected =
                    (f64::from(ambient) + f64::from(diffuse) * transmittance).clamp(0.0, 1.0);
                assert!(
                    (f64::from(s) - expected).abs() < 1e-4,
                    "{name}: {s} vs {expected}"
                );
            }
        }
        let tetrahedra: Vec<Tetrahedron> = cells.iter().map(GpuCell::to_tetrahedron).collect();
        let mut hit = 0;
        for _ in 0..60 {
            let target = DVec3::new(
                (random() - 0.5) * extent,
                1300.0 + random() * 700.0,
                (random() - 0.5) * extent,
            );
            let ray = Ray::new(eye, target - eye).unwrap();
            hit += check_ray_order(&tetrahedra, &ray, name);
        }
        assert!(hit > 30, "{name}: the rays hit only {hit} cells");
    }
    // Bad lighting and shapes are errors.
    let view = LayerView {
        world_from_field: DAffine3::IDENTITY,
        eye: DVec3::new(0.0, 100.0, 0.0),
        frustum: None,
        lod: LodSettings::default(),
        order: CellOrder::Unordered,
        profile: &profile,
        scalar: PrismScalar::Sunlit {
            extinction: -1.0,
            sun_height,
            ambient,
            diffuse,
        },
    };
    let error = layer
        .cells(&view, &mut TerrainMesh::new(), &mut Vec::new())
        .unwrap_err();
    assert!(
        matches!(
            error,
            SurfaceLayerError::Prisms(PrismError::InvalidLighting { .. })
        ),
        "{error}"
    );
    for (bad, needle) in [
        (CloudLayerShape { sag: 1.5, ..shape }, "sag"),
        (
            CloudLayerShape {
                extent: 0.0,
                ..shape
            },
            "extent",
        ),
        (
            CloudLayerShape {
                base: f64::NAN,
                ..shape
            },
            "base",
        ),
    ] {
        let message = bad
            .layer(side, &thickness, 2.0, 1.0)
            .unwrap_err()
            .to_string();
        assert!(message.contains(needle), "{message}");
    }
    let mut nan = thickness.clone();
    nan[100] = f32::NAN;
    let message = shape.layer(side, &nan, 2.0, 1.0).unwrap_err().to_string();
    assert!(message.contains("NaN"), "{message}");
}
