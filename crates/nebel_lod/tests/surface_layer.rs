//! Prisms of a layer between two surfaces (`nebel_lod::SurfaceLayer`): a
//! scalar from a value map without popping, crossing surfaces with the
//! height above the bottom as the scalar, bad input as errors, aurora
//! curtains and a cloud layer lit through the cloud above.

mod support;

use std::collections::HashMap;

use glam::{DAffine3, DVec2, DVec3};
use nebel_core::cell::{Ray, Tetrahedron};
use nebel_core::field::{AuroraCurtains, FogNoise, HeightField, ValueNoise};
use nebel_lod::quadtree::TerrainMap;
use nebel_lod::{
    AuroraShape, CellOrder, CloudLayerShape, FogProfile, GpuCell, LayerTop, LayerView, LodSettings,
    PrismError, PrismInput, PrismScalar, SurfaceLayer, SurfaceLayerError, TerrainError,
    TerrainMesh, TriangleOrder, fog_prisms,
};
use support::{
    SPACING, assert_conforming, assert_fills_the_prisms, check_ray_order, key, over_the_grid,
    random_eyes, uniform, valley,
};

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
        edge_fade: 0.0,
    };
    let layer = shape.layer(side, &thickness, 2.0, 1.0).unwrap();
    let profile = CloudLayerShape::profile();
    let (extinction, sun_height, ambient, diffuse) = (0.004_f32, 0.7_f32, 0.3_f32, 0.7_f32);
    let origin = layer.hierarchy().origin();
    let mut random = uniform(0xc10d_u64);
    // Single scattering below; multiple scattering and the sky dimmed by
    // the cloud above inside and above.
    for (name, eye, octaves, sky_occlusion) in [
        ("below", DVec3::new(300.0, 200.0, -700.0), 1, false),
        ("inside", DVec3::new(-2100.0, 1550.0, 3300.0), 3, true),
        ("above", DVec3::new(4000.0, 5000.0, 1000.0), 8, true),
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
                octaves,
                sky_occlusion,
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
        // its column, Σ_k 2^−k e^{−2^−k τ} / Σ_k 2^−k over the octaves, and
        // the sky through it, e^{−1.66 σ d}.
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
                let tau = f64::from(extinction) * depth;
                let (sum, norm) = (0..octaves).fold((0.0, 0.0), |(sum, norm), k| {
                    let b = 0.5f64.powi(k as i32);
                    (sum + b * (-b * tau / f64::from(sun_height)).exp(), norm + b)
                });
                let sky = if sky_occlusion {
                    (-1.66 * tau).exp()
                } else {
                    1.0
                };
                let expected =
                    (f64::from(ambient) * sky + f64::from(diffuse) * sum / norm).clamp(0.0, 1.0);
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
            octaves: 1,
            sky_occlusion: false,
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
                edge_fade: 0.6,
                ..shape
            },
            "edge fade",
        ),
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

/// A cloud layer's edge fade thins its thickness to 0 at the square's edges
/// over its share of the side, and keeps it inside.
#[test]
fn a_cloud_layers_edges_fade_to_no_cloud() {
    let side = 33;
    let thickness = vec![500.0f32; side * side];
    let shape = CloudLayerShape {
        extent: 8e3,
        base: 1500.0,
        sag: 0.2,
        edge_fade: 0.25,
    };
    let faded = shape.layer(side, &thickness, 2.0, 1.0).unwrap();
    let map = faded.thickness();
    assert_eq!(map.side(), side);
    let inside = |i: usize| i.min(side - 1 - i) >= 8;
    for j in 0..side {
        for i in 0..side {
            let t = map.values()[i + side * j];
            if i == 0 || j == 0 || i == side - 1 || j == side - 1 {
                assert_eq!(t, 0.0, "({i}, {j}) on an edge");
            } else if inside(i) && inside(j) {
                assert!((t - 500.0).abs() < 1e-3, "({i}, {j}): {t}");
            } else {
                assert!(t > 0.0 && t < 500.0, "({i}, {j}): {t}");
            }
        }
    }
    // No fade: the thickness as given.
    let plain = CloudLayerShape {
        edge_fade: 0.0,
        ..shape
    }
    .layer(side, &thickness, 2.0, 1.0)
    .unwrap();
    assert!(
        plain
            .thickness()
            .values()
            .iter()
            .all(|t| (t - 500.0).abs() < 1e-3)
    );
}
