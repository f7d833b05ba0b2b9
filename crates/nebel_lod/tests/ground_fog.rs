//! Ground fog prisms on the terrain's level of detail: conforming, exactly the
//! fog's volume, back to front for every eye, continuous along a flight, left
//! out beyond a handoff distance, and bad input as errors.

#[path = "support/rays.rs"]
mod rays;
mod support;

use std::collections::HashSet;

use glam::{DAffine3, DMat4, DVec2, DVec3};
use nebel_core::cell::{Ray, Tetrahedron};
use nebel_core::field::{HeightField, ValueNoise};
use nebel_lod::quadtree::TerrainMap;
use nebel_lod::{
    CellOrder, FogProfile, Frustum, GpuCell, LodSettings, PrismError, PrismInput, PrismScalar,
    PrismStats, TerrainError, TerrainHierarchy, TerrainMesh, TriangleOrder, fog_prisms,
};
use rays::{OrderCost, composites};
use support::{
    SPACING, assert_conforming, assert_fills_the_prisms, check_ray_order, key, over_the_grid,
    random_eyes, uniform, valley,
};

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

#[test]
fn an_order_up_to_a_grid_spacing_old_costs_little_of_the_image() {
    // The prisms of a sorted fog are ordered for the eye the terrain was last
    // refined for, which waits until the eye has moved a part of a grid
    // spacing, and, built in the background, are drawn a frame or two later
    // still. Rays from the new eye meet cells out of order only where the eye
    // crossed the plane of a face between them.
    let (hierarchy, layer) = valley(33);
    let mut random = uniform(0x1a7e_u64);
    let profile = FogProfile::new(vec![[0.0, 1.0], [0.3, 0.8], [0.7, 0.3], [1.0, 0.0]]).unwrap();
    for step in [1.0, 0.25 * SPACING, 0.5 * SPACING, SPACING] {
        let mut cost = OrderCost::default();
        let more = random_eyes(&hierarchy, 4, 0x1a7e);
        for (_, eye) in eyes(&hierarchy, &layer).into_iter().chain(more) {
            let angle = random() * std::f64::consts::TAU;
            let moved = eye + step * DVec3::new(angle.cos(), 0.2 * (random() - 0.5), angle.sin());
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
                // Each cell emits its mean scalar `s` and has extinction
                // `0.02 s` per metre (fog about 100 m thick, optical depths
                // up to 2).
                cost.add(composites(&cells, &ray, 0.02));
            }
        }
        println!("{step} m: {cost}");
        // Half an 8-bit step in RMS over the rays into the fog.
        assert!(cost.rmse() <= 1.0 / 510.0, "{step} m: {cost}");
    }
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
