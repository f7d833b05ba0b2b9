//! Tests of the terrain quadtree: conformity (no cracks, no T-vertices) for
//! random eyes and frusta, the full grid at large c, morph continuity, the
//! error bound of c, visibility order, propagation, and the stress cases.

use std::collections::{HashMap, HashSet};

use glam::{DMat4, DVec2, DVec3};
use nebel_core::field::{HeightField, ValueNoise};
use proptest::prelude::*;

use super::*;
use crate::frustum::Frustum;

/// Deterministic pseudo-random numbers in [0, 1).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let mut x = self.0;
        x ^= x >> 33;
        x = x.wrapping_mul(0xff51_afd7_ed55_8ccd);
        x ^= x >> 33;
        (x >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// An fBm height field of `n × n` points, `spacing` apart, `octaves` of value
/// noise from wavelength `wavelength` halving, gain 0.5, rescaled to
/// 0..`relief`, origin at `origin`.
fn fbm_field(
    n: usize,
    spacing: f64,
    wavelength: f64,
    octaves: u32,
    relief: f64,
    origin: DVec2,
) -> HeightField {
    let noise = ValueNoise {
        seed: 7,
        octaves,
        wavelength,
        gain: 0.5,
    };
    HeightField::value_noise([n, n], DVec2::splat(spacing), origin, &noise, relief).unwrap()
}

/// Random heights: a smooth bump plus noise of amplitude `noise`.
fn random_field(n: usize, seed: u64, noise: f64) -> HeightField {
    let mut rng = Rng(seed);
    let heights = (0..n * n)
        .map(|p| {
            let (i, j) = ((p % n) as f64, (p / n) as f64);
            let smooth = 20.0 * ((i * 0.37).sin() + (j * 0.23).cos());
            (smooth + noise * (rng.next() - 0.5)) as f32
        })
        .collect();
    HeightField::new([n, n], DVec2::new(2.0, 3.0), DVec2::new(-5.0, 7.0), heights).unwrap()
}

fn settings(accuracy: f32) -> LodSettings {
    LodSettings {
        accuracy,
        grid_points: true,
        ..LodSettings::default()
    }
}

/// The triangles of `mesh` as grid points.
fn grid_triangles(mesh: &TerrainMesh) -> Vec<[[u32; 2]; 3]> {
    mesh.indices
        .chunks_exact(3)
        .map(|t| [t[0], t[1], t[2]].map(|v| mesh.grid_points[v as usize]))
        .collect()
}

/// Twice the signed area in (i, j); negative for the counter-clockwise-from-
/// above winding (+i to the right, +j towards the viewer).
fn cross(t: &[[u32; 2]; 3]) -> i64 {
    let p = t.map(|[i, j]| (i64::from(i), i64::from(j)));
    (p[1].0 - p[0].0) * (p[2].1 - p[0].1) - (p[1].1 - p[0].1) * (p[2].0 - p[0].0)
}

fn gcd(a: i64, b: i64) -> i64 {
    if b == 0 { a.abs() } else { gcd(b, a % b) }
}

/// Checks that the mesh is a conforming triangulation: every vertex has one
/// height and normal in every fan, every triangle is counter-clockwise from
/// above, no vertex lies inside another triangle's edge, and every edge is
/// shared by at most two triangles. With `whole`, the triangles tile the
/// whole square: area (n−1)², interior edges exactly twice, boundary edges
/// once. Returns the vertex heights by grid point.
fn check_conforming(
    hierarchy: &TerrainHierarchy,
    mesh: &TerrainMesh,
    whole: bool,
) -> HashMap<[u32; 2], f32> {
    let n = hierarchy.size() as u32;
    let spacing = hierarchy.field().spacing();
    assert_eq!(mesh.grid_points.len(), mesh.positions.len());
    let mut heights: HashMap<[u32; 2], (u32, Option<[u32; 3]>)> = HashMap::new();
    for (v, p) in mesh.grid_points.iter().enumerate() {
        let pos = mesh.positions[v];
        assert!(pos.iter().all(|c| c.is_finite()), "{pos:?}");
        assert!((f64::from(pos[0]) - f64::from(p[0]) * spacing.x).abs() < 1e-3);
        assert!((f64::from(pos[2]) - f64::from(p[1]) * spacing.y).abs() < 1e-3);
        let normal = mesh.normals.get(v).map(|n| n.map(f32::to_bits));
        if let Some(nrm) = mesh.normals.get(v) {
            let len = (nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]).sqrt();
            assert!((len - 1.0).abs() < 1e-4 && nrm[1] > 0.0, "{nrm:?}");
        }
        let entry = heights.entry(*p).or_insert((pos[1].to_bits(), normal));
        assert_eq!(
            *entry,
            (pos[1].to_bits(), normal),
            "vertex {p:?} has two values"
        );
    }
    let vertices: HashSet<[u32; 2]> = heights.keys().copied().collect();
    let mut edges: HashMap<([u32; 2], [u32; 2]), u32> = HashMap::new();
    let mut area = 0i64;
    for t in grid_triangles(mesh) {
        let c = cross(&t);
        assert!(c < 0, "triangle {t:?} is not counter-clockwise from above");
        area -= c;
        for e in 0..3 {
            let (p, q) = (t[e], t[(e + 1) % 3]);
            let key = if p < q { (p, q) } else { (q, p) };
            *edges.entry(key).or_insert(0) += 1;
            let (di, dj) = (
                i64::from(q[0]) - i64::from(p[0]),
                i64::from(q[1]) - i64::from(p[1]),
            );
            let g = gcd(di, dj);
            for k in 1..g {
                let inner = [
                    (i64::from(p[0]) + di / g * k) as u32,
                    (i64::from(p[1]) + dj / g * k) as u32,
                ];
                assert!(
                    !vertices.contains(&inner),
                    "T-vertex {inner:?} on edge {p:?}-{q:?}"
                );
            }
        }
    }
    let last = n - 1;
    for ((p, q), count) in &edges {
        let boundary = (p[0] == q[0] && (p[0] == 0 || p[0] == last))
            || (p[1] == q[1] && (p[1] == 0 || p[1] == last));
        if whole {
            let expected = if boundary { 1 } else { 2 };
            assert_eq!(*count, expected, "edge {p:?}-{q:?}");
        } else {
            assert!(*count <= 2, "edge {p:?}-{q:?} in {count} triangles");
        }
    }
    if whole {
        assert_eq!(area, 2 * i64::from(last) * i64::from(last), "area");
    }
    heights
        .into_iter()
        .map(|(p, (h, _))| (p, f32::from_bits(h)))
        .collect()
}

/// The mesh's height at every grid point (linear in each triangle; NaN where
/// no triangle covers the point), index `i + n·j`.
fn surface(hierarchy: &TerrainHierarchy, mesh: &TerrainMesh) -> Vec<f64> {
    let n = hierarchy.size();
    let mut out = vec![f64::NAN; n * n];
    for (t, idx) in grid_triangles(mesh)
        .iter()
        .zip(mesh.indices.chunks_exact(3))
    {
        let h = [0, 1, 2].map(|k| f64::from(mesh.positions[idx[k] as usize][1]));
        let p = t.map(|[i, j]| (i64::from(i), i64::from(j)));
        let total = cross(t);
        let (i0, i1) = (
            p.iter().map(|p| p.0).min().unwrap(),
            p.iter().map(|p| p.0).max().unwrap(),
        );
        let (j0, j1) = (
            p.iter().map(|p| p.1).min().unwrap(),
            p.iter().map(|p| p.1).max().unwrap(),
        );
        for j in j0..=j1 {
            for i in i0..=i1 {
                let w = [0, 1, 2].map(|k| {
                    let (a, b) = (p[(k + 1) % 3], p[(k + 2) % 3]);
                    (b.0 - a.0) * (j - a.1) - (b.1 - a.1) * (i - a.0)
                });
                if w.iter().all(|&w| w * total.signum() >= 0) {
                    out[i as usize + n * j as usize] = (0..3)
                        .map(|k| w[k] as f64 / total as f64 * h[k])
                        .sum::<f64>();
                }
            }
        }
    }
    out
}

fn update(
    hierarchy: &TerrainHierarchy,
    eye: DVec3,
    frustum: Option<&Frustum>,
    settings: &LodSettings,
) -> (TerrainMesh, LodStats) {
    let mut mesh = TerrainMesh::new();
    let stats = hierarchy
        .update(eye, frustum, settings, &mut mesh)
        .expect("valid eye and settings");
    assert_eq!(stats.one_level_repairs, 0, "one-level rule broken");
    assert_eq!(stats.triangles, mesh.triangle_count());
    (mesh, stats)
}

fn world_eye(hierarchy: &TerrainHierarchy, u: f64, v: f64, height: f64) -> DVec3 {
    let extent = (hierarchy.size() - 1) as f64;
    let s = hierarchy.field().spacing();
    hierarchy.origin() + DVec3::new(u * extent * s.x, height, v * extent * s.y)
}

fn order_strategy() -> impl Strategy<Value = TriangleOrder> {
    prop_oneof![
        Just(TriangleOrder::BackToFront),
        Just(TriangleOrder::FrontToBack),
        Just(TriangleOrder::Unordered),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    /// Random terrain, eye, c, C, order and morphing: every interior edge in
    /// exactly two triangles, boundary edges in one, no T-vertices, one value
    /// per vertex, the square tiled.
    #[test]
    fn crack_free_for_random_eyes(
        levels in 2u32..6,
        seed in any::<u64>(),
        noise in 0.0f64..60.0,
        min_resolution in 1.6f32..12.0,
        accuracy_log in -1.0f32..3.5,
        (u, v, height) in (-0.6f64..1.6, -0.6f64..1.6, -200.0f64..400.0),
        order in order_strategy(),
        morph in any::<bool>(),
    ) {
        let n = (1usize << levels) + 1;
        let hierarchy = TerrainHierarchy::new(random_field(n, seed, noise), min_resolution).unwrap();
        let eye = world_eye(&hierarchy, u, v, height);
        let settings = LodSettings { order, morph, ..settings(10f32.powf(accuracy_log)) };
        let (mesh, _) = update(&hierarchy, eye, None, &settings);
        check_conforming(&hierarchy, &mesh, true);
    }

    /// With a frustum: still no T-vertex and one value per vertex, and every
    /// triangle of the unculled mesh with a corner inside the frustum is kept.
    #[test]
    fn culling_is_conservative_and_conforming(
        seed in any::<u64>(),
        (u, v, height) in (-0.3f64..1.3, -0.3f64..1.3, 5.0f64..300.0),
        (yaw, pitch) in (0.0f64..std::f64::consts::TAU, -1.2f64..0.3),
        accuracy_log in 0.0f32..3.0,
    ) {
        let hierarchy = TerrainHierarchy::new(random_field(33, seed, 30.0), 2.0).unwrap();
        let eye = world_eye(&hierarchy, u, v, height);
        let forward = DVec3::new(yaw.cos() * pitch.cos(), pitch.sin(), yaw.sin() * pitch.cos());
        let view = DMat4::look_to_rh(eye, forward, DVec3::Y);
        let projection = DMat4::perspective_infinite_reverse_rh(0.9, 1.5, 0.5);
        let frustum = Frustum::from_view_projection(projection * view).unwrap();
        let settings = settings(10f32.powf(accuracy_log));
        let (culled, _) = update(&hierarchy, eye, Some(&frustum), &settings);
        let (full, _) = update(&hierarchy, eye, None, &settings);
        check_conforming(&hierarchy, &culled, false);
        let kept: HashSet<[[u32; 2]; 3]> = grid_triangles(&culled).into_iter().collect();
        let origin = hierarchy.origin();
        for (t, idx) in grid_triangles(&full).iter().zip(full.indices.chunks_exact(3)) {
            let visible = idx.iter().any(|&v| {
                let p = full.positions[v as usize];
                frustum.contains_point(origin + DVec3::new(p[0].into(), p[1].into(), p[2].into()))
            });
            if visible {
                prop_assert!(kept.contains(t), "visible triangle {:?} culled", t);
            }
        }
    }
}

#[test]
fn large_accuracy_gives_the_full_grid() {
    for levels in [1u32, 3, 5] {
        let n = (1usize << levels) + 1;
        let hierarchy = TerrainHierarchy::new(random_field(n, 3, 10.0), 1.6).unwrap();
        let eye = world_eye(&hierarchy, 0.3, 0.8, 500.0);
        for order in [
            TriangleOrder::BackToFront,
            TriangleOrder::FrontToBack,
            TriangleOrder::Unordered,
        ] {
            let s = LodSettings {
                order,
                ..settings(1e7)
            };
            let (mesh, stats) = update(&hierarchy, eye, None, &s);
            // Every node of two cells is a full fan of 8 triangles.
            assert_eq!(mesh.triangle_count(), 2 * (n - 1) * (n - 1));
            assert_eq!(stats.deepest_level, levels - 1);
            let heights = check_conforming(&hierarchy, &mesh, true);
            assert_eq!(heights.len(), n * n, "every grid point is a vertex");
            for ([i, j], h) in heights {
                assert_eq!(h, hierarchy.field().height(i as usize, j as usize));
            }
            // Fully refined normals are the true-grid ones.
            let f = hierarchy.field();
            for (v, [i, j]) in mesh.grid_points.iter().enumerate() {
                let (i, j) = (*i as usize, *j as usize);
                if i == 0 || j == 0 || i == n - 1 || j == n - 1 {
                    continue;
                }
                let s = f.spacing();
                let gx = (f.height(i + 1, j) - f.height(i - 1, j)) as f64 / (2.0 * s.x);
                let gz = (f.height(i, j + 1) - f.height(i, j - 1)) as f64 / (2.0 * s.y);
                let expected = DVec3::new(-gx, 1.0, -gz).normalize();
                let got = mesh.normals[v];
                assert!(
                    (DVec3::new(got[0].into(), got[1].into(), got[2].into()) - expected).length()
                        < 1e-5
                );
            }
        }
    }
}

/// Morph continuity: along a smooth flight the mesh surface at every grid
/// point changes by a bounded amount per frame with morphing, and by much
/// more (pops) without.
#[test]
fn morphing_keeps_heights_continuous_along_a_path() {
    let field = fbm_field(129, 10.0, 640.0, 6, 300.0, DVec2::ZERO);
    let hierarchy = TerrainHierarchy::new(field, 2.0).unwrap();
    // Largest jump of the surface at any grid point between frames, for a
    // flight of `frames` steps of `step` m.
    let largest_jump = |morph: bool, step: f64, frames: usize| {
        let settings = LodSettings {
            morph,
            ..settings(60.0)
        };
        let mut previous: Option<Vec<f64>> = None;
        let mut largest = 0.0f64;
        for frame in 0..frames {
            let s = frame as f64 * step;
            let eye = DVec3::new(100.0 + s, 350.0 - 0.1 * s, 200.0 + 0.5 * s);
            let (mesh, _) = update(&hierarchy, eye, None, &settings);
            let now = surface(&hierarchy, &mesh);
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
    let morph = largest_jump(true, 2.0, 300);
    let morph_fine = largest_jump(true, 0.5, 1200);
    let pop = largest_jump(false, 2.0, 300);
    let pop_fine = largest_jump(false, 0.5, 1200);
    println!(
        "largest surface jump per frame: morphing {morph:.3} m (2 m steps), {morph_fine:.3} m (0.5 m steps); without morphing {pop:.3} m, {pop_fine:.3} m"
    );
    // Continuity: the morphed jump shrinks with the step (linear: ~1/4)…
    assert!(morph_fine < 0.5 * morph, "{morph_fine} vs {morph}");
    // …and stays below a tenth of the eye's step on this 300 m relief…
    assert!(morph < 0.1 * 2.0, "{morph}");
    // …while without morphing vertices pop by a step-independent amount.
    assert!(pop > 3.0 * morph, "{pop} vs {morph}");
    assert!(pop_fine > 0.5 * pop, "{pop_fine} vs {pop}");
}

/// The details the mesh leaves out: for every node that is not refined, each
/// of its five new points (centre and edge midpoints) at its true height,
/// with the coarse mesh's height there (the mean of the two ends of the edge
/// or diagonal it splits). Positions in the height field's frame.
fn left_out_details(hierarchy: &TerrainHierarchy, mesh: &TerrainMesh) -> Vec<(DVec3, f64)> {
    let field = hierarchy.field();
    let n = hierarchy.size();
    let h = |i: usize, j: usize| f64::from(field.height(i, j));
    let vertices: HashSet<[u32; 2]> = mesh.grid_points.iter().copied().collect();
    let mut details = Vec::new();
    for level in 0..hierarchy.levels() {
        let s = (n - 1) >> level;
        let half = s / 2;
        for b in 0..1usize << level {
            for a in 0..1usize << level {
                let (ci, cj) = (a * s + half, b * s + half);
                if vertices.contains(&[ci as u32, cj as u32]) {
                    continue; // refined
                }
                let (i0, j0, i1, j1) = (a * s, b * s, a * s + s, b * s + s);
                let diagonal = if (a + b) % 2 == 0 {
                    ((i0, j0), (i1, j1))
                } else {
                    ((i0, j1), (i1, j0))
                };
                let points = [
                    ((ci, cj), diagonal.0, diagonal.1),
                    ((ci, j0), (i0, j0), (i1, j0)),
                    ((ci, j1), (i0, j1), (i1, j1)),
                    ((i0, cj), (i0, j0), (i0, j1)),
                    ((i1, cj), (i1, j0), (i1, j1)),
                ];
                for (m, p, q) in points {
                    let position =
                        field.origin() + DVec2::new(m.0 as f64, m.1 as f64) * field.spacing();
                    details.push((
                        DVec3::new(position.x, h(m.0, m.1), position.y),
                        (h(p.0, p.1) + h(q.0, q.1)) / 2.0,
                    ));
                }
            }
        }
    }
    details
}

/// Every node that is not refined leaves out details (the deviation of its
/// five new points from the coarse mesh) that subtend at most
/// `1 / (2c (1 − 1/(2C)))` radian vertically from the eye.
#[test]
fn left_out_detail_stays_under_the_bound_of_c() {
    let field = fbm_field(129, 10.0, 640.0, 7, 400.0, DVec2::new(-640.0, -640.0));
    for min_resolution in [1.6f32, 4.0, 9.0] {
        let hierarchy = TerrainHierarchy::new(field.clone(), min_resolution).unwrap();
        for (eye, accuracy) in [
            (DVec3::new(0.0, 500.0, 0.0), 20.0f32),
            (DVec3::new(-600.0, 120.0, 300.0), 100.0),
            (DVec3::new(900.0, 800.0, -900.0), 300.0),
        ] {
            let (mesh, _) = update(&hierarchy, eye, None, &settings(accuracy));
            let bound = 1.0 / (2.0 * f64::from(accuracy) * (1.0 - 0.5 / f64::from(min_resolution)));
            let largest = left_out_details(&hierarchy, &mesh)
                .into_iter()
                .map(|(point, coarse)| (point.y - coarse).abs() / (point - eye).length())
                .fold(0.0, f64::max);
            println!(
                "C = {min_resolution}, c = {accuracy}: largest left-out detail {largest:.2e} rad, bound {bound:.2e} rad, {} triangles",
                mesh.triangle_count()
            );
            assert!(largest <= bound * 1.0001, "{largest} > {bound}");
        }
    }
}

/// With the accuracy of a pixel tolerance, no detail the mesh leaves out
/// inside the view moves by more than that many pixels between its true and
/// its coarse height, for views from the ground to high above, through
/// narrow and wide lenses; the tolerance is approached (the bound is not
/// vacuous), and a finer tolerance draws more triangles.
#[test]
fn left_out_detail_stays_within_the_pixel_tolerance() {
    let field = fbm_field(257, 10.0, 640.0, 8, 400.0, DVec2::new(-1280.0, -1280.0));
    let hierarchy = TerrainHierarchy::new(field, 2.0).unwrap();
    for (eye, target, fov_degrees, viewport) in [
        (
            DVec3::new(-1500.0, 700.0, -1500.0),
            DVec3::ZERO,
            60.0f64,
            [320u32, 180u32],
        ),
        (
            DVec3::new(0.0, 420.0, 900.0),
            DVec3::new(0.0, 150.0, 0.0),
            90.0,
            [200, 200],
        ),
        (
            DVec3::new(900.0, 3000.0, 0.0),
            DVec3::new(0.0, 0.0, 100.0),
            25.0,
            [640, 360],
        ),
    ] {
        let world_from_view = DMat4::look_at_rh(eye, target, DVec3::Y).inverse();
        let aspect = f64::from(viewport[0]) / f64::from(viewport[1]);
        let clip_from_view =
            DMat4::perspective_infinite_reverse_rh(fov_degrees.to_radians(), aspect, 0.1);
        let clip_from_world = clip_from_view * world_from_view.inverse();
        let pixel = |point: DVec3| {
            let clip = clip_from_world * point.extend(1.0);
            let ndc = DVec2::new(clip.x, clip.y) / clip.w;
            let inside = clip.w > 0.0 && ndc.abs().max_element() <= 1.0;
            inside.then(|| ndc * DVec2::new(f64::from(viewport[0]), f64::from(viewport[1])) / 2.0)
        };
        let mut triangles = Vec::new();
        for pixel_error in [4.0, 1.0] {
            let accuracy = accuracy_for_pixel_error(
                pixel_error,
                clip_from_view,
                viewport,
                hierarchy.min_resolution(),
            )
            .unwrap();
            let (mesh, _) = update(&hierarchy, eye, None, &settings(accuracy as f32));
            let largest = left_out_details(&hierarchy, &mesh)
                .into_iter()
                .filter_map(|(point, coarse)| {
                    let coarse = DVec3::new(point.x, coarse, point.z);
                    Some((pixel(point)? - pixel(coarse)?).length())
                })
                .fold(0.0, f64::max);
            println!(
                "eye {eye}, {fov_degrees}°, {viewport:?}, {pixel_error} px: c = {accuracy:.0}, largest left-out detail {largest:.3} px, {} triangles",
                mesh.triangle_count()
            );
            // To first order in the detail's angle (see pixel_error's docs).
            assert!(
                largest <= pixel_error * 1.01,
                "{largest} px > {pixel_error} px"
            );
            assert!(
                largest >= pixel_error * 0.1,
                "{largest} px: the bound is vacuous"
            );
            triangles.push(mesh.triangle_count());
        }
        assert!(triangles[1] > triangles[0], "{triangles:?}");
    }
}

/// Back to front: along every ray from the eye's ground projection, the
/// triangles it crosses come out farthest first (and nearest first for
/// front to back).
#[test]
fn order_is_a_visibility_order_of_the_ground_projection() {
    let hierarchy = TerrainHierarchy::new(random_field(17, 11, 40.0), 2.0).unwrap();
    let spacing = hierarchy.field().spacing();
    for (u, v) in [
        (0.37, 0.61),
        (-0.4, 0.2),
        (1.3, 1.7),
        (0.5, 0.5),
        (0.25, 0.75),
    ] {
        let eye = world_eye(&hierarchy, u, v, 30.0);
        for order in [TriangleOrder::BackToFront, TriangleOrder::FrontToBack] {
            let s = LodSettings {
                order,
                ..settings(40.0)
            };
            let (mesh, _) = update(&hierarchy, eye, None, &s);
            let local = eye - hierarchy.origin();
            let e = (local.x / spacing.x, local.z / spacing.y);
            let triangles: Vec<[(f64, f64); 3]> = grid_triangles(&mesh)
                .iter()
                .map(|t| t.map(|[i, j]| (f64::from(i), f64::from(j))))
                .collect();
            for ray in 0..1440 {
                let angle = (ray as f64 + 0.123) * std::f64::consts::TAU / 1440.0;
                let d = (angle.cos(), angle.sin());
                // Entry distance of the ray into each triangle it crosses.
                let mut hits: Vec<(f64, usize)> = Vec::new();
                for (index, t) in triangles.iter().enumerate() {
                    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
                    for k in 0..3 {
                        let (a, b) = (t[k], t[(k + 1) % 3]);
                        // The triangles are clockwise in (i, j): inside is
                        // where nrm·(p − a) ≥ 0, p = e + s·d.
                        let nrm = (b.1 - a.1, -(b.0 - a.0));
                        let num = nrm.0 * (a.0 - e.0) + nrm.1 * (a.1 - e.1);
                        let den = nrm.0 * d.0 + nrm.1 * d.1;
                        if den.abs() < 1e-12 {
                            if num > 0.0 {
                                t1 = -1.0;
                            }
                        } else if den > 0.0 {
                            t0 = t0.max(num / den);
                        } else {
                            t1 = t1.min(num / den);
                        }
                    }
                    if t1 - t0 > 1e-6 {
                        hits.push((t0, index));
                    }
                }
                hits.sort_by(|a, b| a.0.total_cmp(&b.0));
                for pair in hits.windows(2) {
                    let (near, far) = (pair[0].1, pair[1].1);
                    match order {
                        TriangleOrder::BackToFront => assert!(
                            far < near,
                            "eye {e:?}: triangle {far} behind {near} drawn after it"
                        ),
                        _ => assert!(near < far, "eye {e:?}: front-to-back broken"),
                    }
                }
            }
        }
    }
}

#[test]
fn stored_roughness_satisfies_the_propagation() {
    let hierarchy = TerrainHierarchy::new(random_field(65, 5, 25.0), 3.0).unwrap();
    let k_parent = propagation_factor(3.0, PARENT_FACTOR_DISTANCE);
    let k_neighbour = propagation_factor(3.0, NEIGHBOUR_FACTOR_DISTANCE);
    let f = hierarchy.field();
    let n = hierarchy.size();
    for level in 0..hierarchy.levels() {
        let side = 1usize << level;
        let s = (n - 1) >> level;
        let size = hierarchy.node_size(level);
        for b in 0..side {
            for a in 0..side {
                let d2 = hierarchy.roughness(level, a, b).unwrap();
                // Local: every second difference over the size.
                let (i0, j0, half) = (a * s, b * s, s / 2);
                let at = |i: usize, j: usize| f.height(i, j);
                let second = |p: f32, q: f32, m: f32| (p + q - 2.0 * m).abs();
                let (ci, cj) = (i0 + half, j0 + half);
                let local = second(at(i0, j0), at(i0 + s, j0), at(ci, j0))
                    .max(second(at(i0, j0 + s), at(i0 + s, j0 + s), at(ci, j0 + s)))
                    .max(second(at(i0, j0), at(i0, j0 + s), at(i0, cj)))
                    .max(second(at(i0 + s, j0), at(i0 + s, j0 + s), at(i0 + s, cj)));
                assert!(d2 >= local / size * 0.99999, "local at {level} ({a}, {b})");
                if level + 1 == hierarchy.levels() {
                    continue;
                }
                for (ca, cb) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (qa, qb) = (2 * a + ca, 2 * b + cb);
                    let child = hierarchy.roughness(level + 1, qa, qb).unwrap();
                    assert!(d2 >= k_parent * child * 0.99999);
                    // The child's outer edges face the neighbours at
                    // (a ± 1, b) and (a, b ± 1) on its side.
                    let da: isize = if ca == 0 { -1 } else { 1 };
                    let db: isize = if cb == 0 { -1 } else { 1 };
                    for (na, nb) in [(a as isize + da, b as isize), (a as isize, b as isize + db)] {
                        if let Some(other) = (na >= 0 && nb >= 0)
                            .then(|| hierarchy.roughness(level, na as usize, nb as usize))
                            .flatten()
                        {
                            assert!(other >= k_neighbour * child * 0.99999);
                        }
                    }
                }
            }
        }
    }
    assert!(hierarchy.roughness(hierarchy.levels(), 0, 0).is_none());
    assert!(hierarchy.roughness(1, 2, 0).is_none());
    // One byte per node, (n − 1)²/3 of them, besides the 4-byte heights and
    // a fixed table.
    let nodes = ((n - 1) * (n - 1) - 1) / 3;
    assert_eq!(
        hierarchy.memory_bytes(),
        4 * n * n + nodes + 4 * hierarchy.levels() as usize + 1024 + size_of::<TerrainHierarchy>()
    );
}

#[test]
fn flat_map_gives_minimal_triangles_and_an_exact_mesh() {
    let n = 65;
    let flat =
        TerrainHierarchy::from_heights(n, DVec2::ONE, DVec2::ZERO, vec![12.5; n * n], 2.0).unwrap();
    for level in 0..flat.levels() {
        assert_eq!(flat.roughness(level, 0, 0), Some(0.0));
        assert_eq!(flat.height_bound(level), 0.0);
    }
    // High above: the root alone, two triangles.
    let (mesh, _) = update(
        &flat,
        DVec3::new(32.0, 12.5 + 200.0, 32.0),
        None,
        &settings(1e6),
    );
    assert_eq!(mesh.triangle_count(), 2);
    check_conforming(&flat, &mesh, true);
    // Close: refinement by distance alone (C), whatever c, and no more than
    // on a rough terrain; every vertex exactly at the flat height.
    let eye = DVec3::new(20.0, 14.0, 40.0);
    let (near, _) = update(&flat, eye, None, &settings(1e6));
    let (near_small_c, _) = update(&flat, eye, None, &settings(0.01));
    assert_eq!(near.triangle_count(), near_small_c.triangle_count());
    let mut rng = Rng(9);
    let bumpy = (0..n * n)
        .map(|_| 12.5 + (rng.next() - 0.5) as f32)
        .collect();
    let rough = TerrainHierarchy::from_heights(n, DVec2::ONE, DVec2::ZERO, bumpy, 2.0).unwrap();
    let (rough_mesh, _) = update(&rough, eye, None, &settings(1e6));
    assert!(near.triangle_count() < rough_mesh.triangle_count());
    assert!(near.positions.iter().all(|p| p[1] == 12.5));
    check_conforming(&flat, &near, true);
}

#[test]
fn single_spike() {
    let n = 65;
    let mut heights = vec![0.0f32; n * n];
    heights[37 + n * 29] = 1000.0;
    let spike =
        TerrainHierarchy::from_heights(n, DVec2::splat(10.0), DVec2::ZERO, heights, 2.0).unwrap();
    for (eye, accuracy) in [
        (DVec3::new(370.0, 50.0, 290.0), 1e4f32),
        (DVec3::new(-3000.0, 500.0, 100.0), 10.0),
        (DVec3::new(100.0, -20.0, 600.0), 50.0),
        (DVec3::new(370.0, 1000.0, 290.0), 1.0),
    ] {
        for order in [TriangleOrder::BackToFront, TriangleOrder::Unordered] {
            let s = LodSettings {
                order,
                ..settings(accuracy)
            };
            let (mesh, _) = update(&spike, eye, None, &s);
            let heights = check_conforming(&spike, &mesh, true);
            if accuracy == 1e4 {
                assert_eq!(heights.get(&[37, 29]), Some(&1000.0), "spike drawn in full");
            }
        }
    }
    // Far away with a small c the spike is left out: few triangles.
    let (far, _) = update(
        &spike,
        DVec3::new(-50_000.0, 500.0, 0.0),
        None,
        &settings(0.5),
    );
    assert!(far.triangle_count() <= 8, "{}", far.triangle_count());
}

#[test]
fn nan_heights_are_an_error_naming_the_point() {
    let n = 9;
    let mut heights = vec![1.0f32; n * n];
    heights[3 + n * 5] = f32::NAN;
    let err = TerrainHierarchy::from_heights(n, DVec2::ONE, DVec2::ZERO, heights, 2.0).unwrap_err();
    assert!(
        matches!(
            err,
            TerrainError::NonFiniteHeight {
                i: 3,
                j: 5,
                index: 48,
                ..
            }
        ),
        "{err:?}"
    );
    let message = err.to_string();
    assert!(
        message.contains("(3, 5)") && message.contains("NaN"),
        "{message}"
    );
    let mut heights = vec![1.0f32; n * n];
    heights[80] = f32::NEG_INFINITY;
    let err = TerrainHierarchy::from_heights(n, DVec2::ONE, DVec2::ZERO, heights, 2.0).unwrap_err();
    assert!(err.to_string().contains("(8, 8)"), "{err}");
    // A HeightField refuses NaN itself.
    assert!(
        HeightField::new(
            [2, 2],
            DVec2::ONE,
            DVec2::ZERO,
            vec![0.0, f32::NAN, 0.0, 0.0]
        )
        .is_err()
    );
}

#[test]
fn sizes_other_than_two_to_the_k_plus_one_are_refused_and_padded() {
    let field = random_field(100, 1, 10.0);
    let small = HeightField::new(
        [100, 60],
        DVec2::ONE,
        DVec2::ZERO,
        field.heights()[..6000].to_vec(),
    )
    .unwrap();
    for f in [&field, &small] {
        let err = TerrainHierarchy::new(f.clone(), 2.0).unwrap_err();
        assert!(
            matches!(err, TerrainError::NotPowerOfTwoPlusOne { padded: 129, .. }),
            "{err:?}"
        );
        assert!(
            err.to_string().contains("pad_to_power_of_two_plus_one"),
            "{err}"
        );
        let padded = pad_to_power_of_two_plus_one(f).unwrap();
        assert_eq!(padded.dims(), [129, 129]);
        assert_eq!(
            (padded.spacing(), padded.origin()),
            (f.spacing(), f.origin())
        );
        let [nx, nz] = f.dims();
        for j in 0..129 {
            for i in 0..129 {
                assert_eq!(padded.height(i, j), f.height(i.min(nx - 1), j.min(nz - 1)));
            }
        }
        let hierarchy = TerrainHierarchy::new(padded, 2.0).unwrap();
        let (mesh, _) = update(
            &hierarchy,
            world_eye(&hierarchy, 0.4, 0.4, 50.0),
            None,
            &settings(50.0),
        );
        check_conforming(&hierarchy, &mesh, true);
    }
    let fits = random_field(33, 1, 1.0);
    assert_eq!(pad_to_power_of_two_plus_one(&fits).unwrap(), fits);
    let tiny = HeightField::new([2, 2], DVec2::ONE, DVec2::ZERO, vec![0.0; 4]).unwrap();
    assert!(matches!(
        TerrainHierarchy::new(tiny.clone(), 2.0),
        Err(TerrainError::NotPowerOfTwoPlusOne { padded: 3, .. })
    ));
    assert_eq!(pad_to_power_of_two_plus_one(&tiny).unwrap().dims(), [3, 3]);
}

#[test]
fn eye_on_a_vertex_below_the_terrain_and_far_away() {
    let hierarchy = TerrainHierarchy::new(random_field(33, 21, 30.0), 2.0).unwrap();
    let f = hierarchy.field();
    let [low, _] = hierarchy.height_range();
    let on_vertex = |i: usize, j: usize| {
        let p = f.origin() + DVec2::new(i as f64, j as f64) * f.spacing();
        DVec3::new(p.x, f64::from(f.height(i, j)), p.y)
    };
    let eyes = [
        on_vertex(16, 16),
        on_vertex(8, 24),
        on_vertex(0, 0),
        on_vertex(32, 17),
        world_eye(&hierarchy, 0.5, 0.5, f64::from(low) - 100.0),
        world_eye(&hierarchy, 0.2, 0.9, f64::from(low) - 1e-3),
        world_eye(&hierarchy, 1e9, -1e9, 1e9),
    ];
    for eye in eyes {
        for order in [TriangleOrder::BackToFront, TriangleOrder::FrontToBack] {
            for accuracy in [1.0f32, 100.0, 1e6] {
                let s = LodSettings {
                    order,
                    ..settings(accuracy)
                };
                let (mesh, _) = update(&hierarchy, eye, None, &s);
                assert!(mesh.normals.iter().flatten().all(|c| c.is_finite()));
                check_conforming(&hierarchy, &mesh, true);
            }
        }
    }
}

#[test]
fn coordinates_far_from_the_origin_lose_nothing() {
    let near = random_field(65, 4, 20.0);
    let far_origin = DVec2::new(100_000.0, -100_000.0);
    let far = HeightField::new(
        near.dims(),
        near.spacing(),
        far_origin,
        near.heights().to_vec(),
    )
    .unwrap();
    let near = TerrainHierarchy::new(near, 2.0).unwrap();
    let far = TerrainHierarchy::new(far, 2.0).unwrap();
    assert_eq!(far.origin(), DVec3::new(100_000.0, 0.0, -100_000.0));
    let offset = far.origin() - near.origin();
    for local_eye in [DVec3::new(30.0, 40.0, 70.0), DVec3::new(-10.0, 5.0, 100.0)] {
        let eye = near.origin() + local_eye;
        let (a, _) = update(&near, eye, None, &settings(100.0));
        let (b, _) = update(&far, eye + offset, None, &settings(100.0));
        assert_eq!(
            a, b,
            "the mesh relative to the origin does not depend on it"
        );
        let extent = 64.0 * 3.0 + 1.0;
        assert!(
            b.positions
                .iter()
                .all(|p| p[0].abs() <= extent && p[2].abs() <= extent)
        );
        check_conforming(&far, &b, true);
    }
}

#[test]
fn extra_roughness_plugs_into_d2() {
    let terrain = random_field(33, 8, 3.0);
    let fog = random_field(33, 99, 80.0);
    let base = TerrainHierarchy::new(terrain.clone(), 2.0).unwrap();
    let with_fog = base.clone().with_extra_roughness(&fog, 0.5).unwrap();
    let fog_only = TerrainHierarchy::new(
        HeightField::new(
            fog.dims(),
            terrain.spacing(),
            terrain.origin(),
            fog.heights().iter().map(|h| h * 0.5).collect(),
        )
        .unwrap(),
        2.0,
    )
    .unwrap();
    for level in 0..base.levels() {
        for b in 0..1usize << level {
            for a in 0..1usize << level {
                let d = with_fog.roughness(level, a, b).unwrap();
                // The maximum of the two sources propagated alone (up to
                // one code: the fog's second differences are rounded
                // differently when scaled before or after).
                let (t, f) = (
                    base.roughness(level, a, b).unwrap(),
                    fog_only.roughness(level, a, b).unwrap(),
                );
                assert!(d >= t);
                assert!(d >= f / 1.075 && d <= t.max(f) * 1.075, "{d} {t} {f}");
            }
        }
    }
    let eye = world_eye(&base, 0.3, 0.4, 20.0);
    let (plain, _) = update(&base, eye, None, &settings(30.0));
    let (fogged, _) = update(&with_fog, eye, None, &settings(30.0));
    assert!(fogged.triangle_count() > plain.triangle_count());
    check_conforming(&with_fog, &fogged, true);
    // Weight 0 changes nothing.
    let unchanged = base.clone().with_extra_roughness(&fog, 0.0).unwrap();
    assert_eq!(update(&unchanged, eye, None, &settings(30.0)).0, plain);
    // Wrong size, bad weight.
    let other = random_field(17, 1, 1.0);
    assert!(matches!(
        base.clone().with_extra_roughness(&other, 1.0),
        Err(TerrainError::DimsMismatch { .. })
    ));
    for weight in [-1.0, f32::NAN, f32::INFINITY] {
        assert!(base.clone().with_extra_roughness(&fog, weight).is_err());
    }
    // A map's values are the same source as a field of them.
    let map = TerrainMap::new(33, fog.heights().iter().map(|h| h.max(0.0)).collect()).unwrap();
    let as_field = HeightField::new(
        [33, 33],
        terrain.spacing(),
        terrain.origin(),
        map.values().to_vec(),
    )
    .unwrap();
    let by_map = base.clone().with_map_roughness(&map, 0.5).unwrap();
    let by_field = base.clone().with_extra_roughness(&as_field, 0.5).unwrap();
    assert_eq!(by_map.d2, by_field.d2);
    let small = TerrainMap::new(17, vec![1.0; 17 * 17]).unwrap();
    assert!(matches!(
        base.clone().with_map_roughness(&small, 1.0),
        Err(TerrainError::DimsMismatch { .. })
    ));
}

#[test]
fn invalid_input_is_an_error_not_a_panic() {
    let hierarchy = TerrainHierarchy::new(random_field(9, 1, 1.0), 2.0).unwrap();
    let mut mesh = TerrainMesh::new();
    for eye in [DVec3::NAN, DVec3::new(0.0, f64::INFINITY, 0.0)] {
        let err = hierarchy
            .update(eye, None, &LodSettings::default(), &mut mesh)
            .unwrap_err();
        assert!(matches!(err, TerrainError::NonFiniteEye { .. }), "{err}");
    }
    for accuracy in [0.0, -1.0, f32::NAN, f32::INFINITY] {
        let s = LodSettings {
            accuracy,
            ..LodSettings::default()
        };
        let err = hierarchy
            .update(DVec3::ZERO, None, &s, &mut mesh)
            .unwrap_err();
        assert!(err.to_string().contains("accuracy c"), "{err}");
    }
    for c in [1.5f32, 0.0, f32::NAN, f32::INFINITY] {
        let err = TerrainHierarchy::new(random_field(9, 1, 1.0), c).unwrap_err();
        assert!(err.to_string().contains("min_resolution C"), "{err}");
    }
    assert!(
        TerrainHierarchy::from_heights(9, DVec2::ZERO, DVec2::ZERO, vec![0.0; 81], 2.0).is_err()
    );
    assert!(
        TerrainHierarchy::from_heights(9, DVec2::ONE, DVec2::ZERO, vec![0.0; 80], 2.0).is_err()
    );
}

#[test]
fn the_mesh_is_reused_without_allocating() {
    let hierarchy = TerrainHierarchy::new(random_field(65, 2, 20.0), 2.0).unwrap();
    let mut mesh = TerrainMesh::new();
    let s = LodSettings::default();
    let eye = world_eye(&hierarchy, 0.5, 0.5, 40.0);
    let first = hierarchy.update(eye, None, &s, &mut mesh).unwrap();
    let capacity = (mesh.positions.capacity(), mesh.indices.capacity());
    let pointer = mesh.positions.as_ptr();
    for far in [false, true, false] {
        let eye = if far {
            world_eye(&hierarchy, 3.0, 3.0, 400.0)
        } else {
            eye
        };
        let stats = hierarchy.update(eye, None, &s, &mut mesh).unwrap();
        assert!(stats.triangles <= first.triangles);
    }
    assert_eq!(
        (mesh.positions.capacity(), mesh.indices.capacity()),
        capacity
    );
    assert_eq!(mesh.positions.as_ptr(), pointer);
    assert_eq!(mesh.normals.len(), mesh.positions.len());
    assert!(mesh.grid_points.is_empty());
}

#[test]
fn terrains_beyond_the_memory_budget_are_refused_before_allocating() {
    // A 2 × 40000 strip pads to a 65537² square: 17 GB of heights.
    let strip = HeightField::new([2, 40_000], DVec2::ONE, DVec2::ZERO, vec![0.0; 80_000]).unwrap();
    let error = pad_to_power_of_two_plus_one(&strip).unwrap_err();
    assert!(matches!(error, TerrainError::OverBudget(_)), "{error}");
    assert!(
        error
            .to_string()
            .starts_with("height field of 65537 × 65537 points needs 17,180,393,476 bytes"),
        "{error}"
    );
    let message = TerrainHierarchy::check_budget(65_537)
        .unwrap_err()
        .to_string();
    assert!(
        message.starts_with("terrain quadtree of 65537 × 65537 points needs 12,169,074,005 bytes"),
        "{message}"
    );
    // The figure: the codes a hierarchy keeps and the ranges of its two
    // finest levels (256 and 64 nodes for 33², 8 bytes each).
    let hierarchy =
        TerrainHierarchy::new(random_field(33, 3, 1.0), DEFAULT_MIN_RESOLUTION).unwrap();
    assert_eq!(hierarchy.d2.len(), 341);
    assert_eq!(TerrainHierarchy::check_budget(33), Ok(341 + 8 * (256 + 64)));
    // Another side counts as the next 2^k + 1.
    assert_eq!(
        TerrainHierarchy::check_budget(20),
        TerrainHierarchy::check_budget(33)
    );
    assert!(TerrainHierarchy::check_budget(usize::MAX).is_err());
}
