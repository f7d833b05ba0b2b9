use glam::{DMat3, DVec3};
use nebel_core::cell::Hexahedron;
use proptest::prelude::*;

use super::*;

/// The minimum accuracy used by the tests: `K_max` = 2 / (4 − √3/2) ≈ 0.638.
const C: f64 = 2.0;

fn grid(dims: [usize; 3], value: impl Fn([usize; 3]) -> f32) -> DensityGrid {
    let [nx, ny, nz] = dims;
    let mut values = Vec::with_capacity(nx * ny * nz);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                values.push(value([i, j, k]));
            }
        }
    }
    DensityGrid::new(dims, DVec3::splat(0.5), DVec3::new(1.0, -2.0, 3.0), values)
        .expect("valid grid")
}

/// Every node of the hierarchy, voxels included, parents before children.
fn all_nodes(hierarchy: &VolumeHierarchy) -> Vec<Node> {
    let mut nodes: Vec<Node> = hierarchy.roots().collect();
    let mut next = 0;
    while next < nodes.len() {
        if let Some(children) = nodes[next].children() {
            nodes.extend(children);
        }
        next += 1;
    }
    nodes
}

/// Grid points of the node's closed box.
fn box_points(node: Node) -> impl Iterator<Item = [usize; 3]> {
    let (o, s) = (node.origin, node.size());
    (o[2]..=o[2] + s).flat_map(move |k| {
        (o[1]..=o[1] + s).flat_map(move |j| (o[0]..=o[0] + s).map(move |i| [i, j, k]))
    })
}

/// The quantised density at `p` in f64, without the f32 rounding.
fn exact_density(hierarchy: &VolumeHierarchy, p: [usize; 3]) -> f64 {
    f64::from(hierarchy.density_quantised(p)) / 255.0
}

/// The piecewise-linear interpolation of the node's corners over its six
/// Kuhn tetrahedra (`nebel_core`'s decomposition), at grid point `p` in its
/// box: an independent reference for the coarse values.
fn coarse_value(hierarchy: &VolumeHierarchy, node: Node, p: [usize; 3]) -> f64 {
    coarse_value_of(|q| exact_density(hierarchy, q), node, p)
}

/// [`coarse_value`] of the field `value` (quantised values, f64).
fn coarse_value_of(value: impl Fn([usize; 3]) -> f64, node: Node, p: [usize; 3]) -> f64 {
    let to_f = |q: [usize; 3]| DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64);
    let corners = std::array::from_fn(|v| value(node.corner(v)));
    let hex =
        Hexahedron::axis_aligned(to_f(node.origin), DVec3::splat(node.size() as f64), corners);
    let x = to_f(p);
    for tet in hex.kuhn_tetrahedra() {
        let [p0, p1, p2, p3] = tet.positions;
        let lambda = DMat3::from_cols(p1 - p0, p2 - p0, p3 - p0).inverse() * (x - p0);
        let weights = [
            1.0 - lambda.x - lambda.y - lambda.z,
            lambda.x,
            lambda.y,
            lambda.z,
        ];
        if weights.iter().all(|&w| w >= -1e-12) {
            return weights.iter().zip(tet.scalars).map(|(w, s)| w * s).sum();
        }
    }
    unreachable!("{p:?} is in no tetrahedron of {node:?}")
}

/// The node's local deviation by the reference: max over its non-corner points.
fn local_deviation(hierarchy: &VolumeHierarchy, node: Node) -> f64 {
    local_deviation_of(|p| exact_density(hierarchy, p), node)
}

/// [`local_deviation`] of the field `value` (quantised values, f64).
fn local_deviation_of(value: impl Fn([usize; 3]) -> f64 + Copy, node: Node) -> f64 {
    let half = node.size() / 2;
    box_points(node)
        .filter(|p| {
            let rel: [usize; 3] = std::array::from_fn(|a| p[a] - node.origin[a]);
            rel.iter().all(|r| r % half == 0) && !rel.iter().all(|&r| r % node.size() == 0)
        })
        .map(|p| (value(p) - coarse_value_of(value, node, p)).abs())
        .fold(0.0, f64::max)
}

#[test]
fn the_budget_figure_is_what_a_hierarchy_keeps() {
    let density = grid([9, 5, 17], |[i, j, k]| ((i + j + k) % 3) as f32 / 2.0);
    let points = (9 * 5 * 17) as f64;
    let plain = VolumeHierarchy::new(&density, C).unwrap();
    let lit = VolumeHierarchy::with_light(&density, &density, C).unwrap();
    for (hierarchy, with_light) in [(plain, false), (lit, true)] {
        let bytes = VolumeHierarchy::check_budget(hierarchy.dims(), with_light).unwrap();
        assert_eq!(bytes as f64, hierarchy.bytes_per_point() * points);
    }
    let message = VolumeHierarchy::check_budget([4097; 3], true)
        .unwrap_err()
        .to_string();
    assert!(
        message.starts_with(
            "volume octree of 4097 × 4097 × 4097 points with a light field needs 343,849,103,365 bytes (320.2 GiB), more than the memory budget"
        ),
        "{message}"
    );
}

#[test]
fn a_hierarchy_beyond_the_memory_budget_is_refused_before_allocating() {
    // 1025³ points: 4.3 GB of zeros that were never written (calloc'd pages
    // cost no memory), more than the budget at 4 bytes per point.
    let dims = [1025; 3];
    let zeros = DensityGrid::new(
        dims,
        DVec3::ONE,
        DVec3::ZERO,
        vec![0.0; dims.iter().product()],
    )
    .unwrap();
    let error = VolumeHierarchy::new(&zeros, C).unwrap_err();
    assert!(matches!(error, HierarchyError::OverBudget(_)), "{error}");
    assert!(
        error
            .to_string()
            .starts_with("volume octree of 1025 × 1025 × 1025 points needs 4,307,562,500 bytes"),
        "{error}"
    );
}

#[test]
fn k_max_matches_equation_4_and_rejects_small_or_invalid_c() {
    let k = k_max(C).unwrap();
    assert!((k - 2.0 / (4.0 - 3f64.sqrt() / 2.0)).abs() < 1e-15);
    assert!(k_max(1e9).unwrap() > 0.5 && k_max(1.7321).unwrap() < 2.0 / 3.0);
    for c in [3f64.sqrt(), 1.0, 0.0, -3.0, f64::NAN, f64::INFINITY] {
        assert!(
            matches!(k_max(c), Err(HierarchyError::InvalidMinAccuracy { value }) if value.to_bits() == c.to_bits()),
            "{c}"
        );
        assert!(VolumeHierarchy::new(&grid([3; 3], |_| 0.0), c).is_err());
    }
}

#[test]
fn sizes_other_than_power_of_two_plus_one_are_errors_naming_the_dims() {
    for dims in [[10, 9, 9], [9, 9, 4], [2, 7, 3], [513, 513, 64]] {
        let error = VolumeHierarchy::new(&grid(dims, |_| 0.5), C).unwrap_err();
        assert_eq!(error, HierarchyError::NotPowerOfTwoPlusOne { dims });
        assert!(error.to_string().contains(&format!("{dims:?}")), "{error}");
    }
}

#[test]
fn nan_densities_never_reach_the_hierarchy() {
    // The grid itself refuses NaN, so `VolumeHierarchy::new` only sees finite
    // values in [0, 1].
    let mut values = vec![0.5; 27];
    values[13] = f32::NAN;
    assert!(DensityGrid::new([3; 3], DVec3::ONE, DVec3::ZERO, values).is_err());
}

#[test]
fn forest_of_9_9_5_has_2_by_2_by_1_roots_of_5_cubed() {
    let hierarchy = VolumeHierarchy::new(&grid([9, 9, 5], |_| 0.25), C).unwrap();
    assert_eq!(hierarchy.root_level(), 2);
    assert_eq!(hierarchy.root_counts(), [2, 2, 1]);
    let origins: Vec<_> = hierarchy.roots().map(|n| (n.level, n.origin)).collect();
    assert_eq!(
        origins,
        [
            (2, [0, 0, 0]),
            (2, [4, 0, 0]),
            (2, [0, 4, 0]),
            (2, [4, 4, 0])
        ]
    );
    // 2 · 2 roots, each 1 + 8 + 64 nodes.
    assert_eq!(all_nodes(&hierarchy).len(), 4 * 73);
    assert_eq!(hierarchy.bytes_per_point(), 4.0);
}

#[test]
fn forest_of_the_paper_cloud_field_has_8_by_8_by_1_roots_of_65_cubed() {
    let dims = [513, 513, 65];
    let grid = DensityGrid::new(dims, DVec3::ONE, DVec3::ZERO, vec![0.0; 513 * 513 * 65])
        .expect("valid grid");
    let hierarchy = VolumeHierarchy::new(&grid, C).unwrap();
    assert_eq!(hierarchy.root_level(), 6);
    assert_eq!(hierarchy.root_counts(), [8, 8, 1]);
    assert_eq!(hierarchy.roots().count(), 64);
    assert!(
        hierarchy
            .roots()
            .all(|n| n.size() == 64 && n.origin[2] == 0)
    );
    assert_eq!(hierarchy.bytes_per_point(), 4.0);
}

#[test]
fn an_axis_of_two_points_makes_every_root_a_voxel() {
    let hierarchy =
        VolumeHierarchy::new(&grid([3, 5, 2], |[i, j, k]| (i + j + k) as f32 / 8.0), C).unwrap();
    assert_eq!(hierarchy.root_level(), 0);
    assert_eq!(hierarchy.root_counts(), [2, 4, 1]);
    for root in hierarchy.roots() {
        assert!(root.children().is_none() && root.centre().is_none());
        assert_eq!(hierarchy.deviation(root), 0.0);
        assert_eq!(hierarchy.morph_factor(root), 0.0);
    }
}

#[test]
fn linear_fields_have_zero_deviation_at_every_node() {
    // Values on multiples of 1/255, so the u8 quantisation keeps them linear.
    type Field = fn([usize; 3]) -> f32;
    let fields: [([usize; 3], Field); 2] = [
        ([17, 9, 33], |[i, j, k]| (i + 2 * j + 3 * k) as f32 / 255.0),
        ([17, 17, 17], |[i, j, k]| {
            (100 + 3 * i + k - 2 * j) as f32 / 255.0
        }),
    ];
    for (dims, field) in fields {
        let hierarchy = VolumeHierarchy::new(&grid(dims, field), C).unwrap();
        for node in all_nodes(&hierarchy) {
            assert_eq!(hierarchy.deviation_quantised(node), 0, "{node:?}");
            // A linear field is extreme at corners.
            let corners: Vec<f32> = (0..8).map(|v| hierarchy.density(node.corner(v))).collect();
            let min = corners.iter().copied().fold(1.0, f32::min);
            let max = corners.iter().copied().fold(0.0, f32::max);
            assert_eq!(hierarchy.scalar_range(node), [min, max], "{node:?}");
        }
    }
}

/// Where grid point `p` lies in `node`: 2 for a non-corner point of its
/// 3³ sample points (edge midpoint, face centre, centre), 1 for a corner, 0
/// otherwise.
fn spike_role(node: Node, p: [usize; 3]) -> u16 {
    let half = (node.size() / 2).max(1);
    let inside = (0..3).all(|a| p[a] >= node.origin[a] && p[a] <= node.origin[a] + node.size());
    if !inside || node.level == 0 {
        return 0;
    }
    let rel: [usize; 3] = std::array::from_fn(|a| p[a] - node.origin[a]);
    if !rel.iter().all(|r| r % half == 0) {
        0
    } else if rel.iter().all(|&r| r % node.size() == 0) {
        1
    } else {
        2
    }
}

#[test]
fn a_spike_gives_its_height_at_its_finest_nodes_and_k_max_powers_above() {
    // A spike of height h on zero: a node that has it as an edge midpoint,
    // face centre or centre deviates by h there (its coarse value is 0); one
    // that has it as a corner by h/2 (at the edge midpoints next to it); any
    // other by 0. Propagation then multiplies by K_max per level.
    let height = 200u16;
    let k = k_max(C).unwrap();
    // (spike point, level of its finest non-corner owners, their origins): a
    // level-1 centre, a level-2 face centre shared by two nodes, a level-2
    // edge midpoint shared by four.
    let cases: [([usize; 3], u32, Vec<[usize; 3]>); 3] = [
        ([5, 7, 3], 1, vec![[4, 6, 2]]),
        ([4, 2, 2], 2, vec![[0, 0, 0], [4, 0, 0]]),
        (
            [4, 4, 2],
            2,
            vec![[0, 0, 0], [4, 0, 0], [0, 4, 0], [4, 4, 0]],
        ),
    ];
    for (spike, owner_level, owners) in cases {
        let field = grid([17; 3], |p| {
            if p == spike {
                f32::from(height) / 255.0
            } else {
                0.0
            }
        });
        let hierarchy = VolumeHierarchy::new(&field, C).unwrap();
        assert_eq!(hierarchy.root_level(), 4);
        // Children come after their parents: fill the expectation bottom-up.
        let nodes = all_nodes(&hierarchy);
        let mut expected = std::collections::HashMap::new();
        for &node in nodes.iter().rev() {
            // h / 255 is 257 h / 65535 exactly.
            let mut raw = (u32::from(spike_role(node, spike)) * 257 * u32::from(height) / 2) as u16;
            for child in node.children().into_iter().flatten() {
                raw = raw.max((k * f64::from(expected[&child])).ceil() as u16);
            }
            expected.insert(node, raw);
            assert_eq!(
                hierarchy.deviation_quantised(node),
                raw,
                "spike {spike:?}, {node:?}"
            );
        }
        // The owners and their ancestors: Δ = K_max^n · h, n levels above the
        // owners, up to the 1/65535 rounding per level.
        for level in owner_level..=4 {
            for owner in &owners {
                let node = Node {
                    level,
                    origin: owner.map(|c| (c >> level) << level),
                };
                let closed_form = k.powi((level - owner_level) as i32) * f64::from(height) / 255.0;
                let error = f64::from(hierarchy.deviation(node)) - closed_form;
                assert!(
                    (-1e-6..=4.0 / 65535.0).contains(&error),
                    "spike {spike:?}, {node:?}: {error}"
                );
            }
        }
        // The face and edge spikes are corners of level-1 nodes (Δ = h/2 there).
        let corner_of_level_1 = nodes
            .iter()
            .any(|n| n.level == 1 && spike_role(*n, spike) == 1);
        assert_eq!(corner_of_level_1, owner_level == 2);
    }
}

#[test]
fn face_centres_have_one_coarse_value_from_either_neighbour() {
    let field = grid([9; 3], |[i, j, k]| {
        ((i * 7 + j * 13 + k * 29) % 17) as f32 / 16.0
    });
    let hierarchy = VolumeHierarchy::new(&field, C).unwrap();
    for node in all_nodes(&hierarchy).into_iter().filter(|n| n.level >= 1) {
        let (s, h) = (node.size(), node.size() / 2);
        for axis in 0..3 {
            let mut neighbour = node;
            neighbour.origin[axis] += s;
            if neighbour.origin[axis] + s >= 9 {
                continue;
            }
            let mut face_centre = node.centre().unwrap();
            face_centre[axis] += h;
            let ours = coarse_value(&hierarchy, node, face_centre);
            let theirs = coarse_value(&hierarchy, neighbour, face_centre);
            assert!((ours - theirs).abs() < 1e-12, "{node:?} axis {axis}");
        }
    }
}

#[test]
fn morph_factor_is_stored_at_the_centre_clamped_and_rounded() {
    let mut hierarchy = VolumeHierarchy::new(&grid([5; 3], |_| 0.5), C).unwrap();
    let root = hierarchy.roots().next().unwrap();
    let child = root.children().unwrap()[5];
    assert_eq!(hierarchy.morph_factor(root), 0.0);
    hierarchy.set_morph_factor(root, 0.5);
    hierarchy.set_morph_factor(child, 7.0);
    assert_eq!(hierarchy.morph_factor(root), 128.0 / 255.0);
    assert_eq!(hierarchy.morph_factor(child), 1.0);
    hierarchy.set_morph_factor(child, f32::NAN);
    assert_eq!(hierarchy.morph_factor(child), 0.0);
    hierarchy.set_morph_factor(child, -1.0);
    assert_eq!(hierarchy.morph_factor(child), 0.0);
    // Δ and the ranges are untouched.
    assert_eq!(hierarchy.deviation(root), 0.0);
    assert_eq!(hierarchy.scalar_range(root), [128.0 / 255.0; 2]);
}

#[test]
#[should_panic(expected = "no morph factor")]
fn a_voxel_has_no_morph_factor_to_set() {
    let mut hierarchy = VolumeHierarchy::new(&grid([3; 3], |_| 0.5), C).unwrap();
    let voxel = hierarchy.roots().next().unwrap().children().unwrap()[0];
    hierarchy.set_morph_factor(voxel, 0.5);
}

#[test]
#[should_panic(expected = "is not a node")]
fn nodes_outside_the_hierarchy_panic() {
    let hierarchy = VolumeHierarchy::new(&grid([5; 3], |_| 0.5), C).unwrap();
    hierarchy.deviation(Node {
        level: 1,
        origin: [1, 0, 0],
    });
}

#[test]
fn quantised_grid_holds_what_the_hierarchy_draws() {
    let field = grid([5, 9, 3], |[i, j, k]| {
        ((i + 3 * j + 5 * k) as f32 * 0.037) % 1.0
    });
    let hierarchy = VolumeHierarchy::new(&field, C).unwrap();
    let quantised = hierarchy.quantised_grid();
    assert_eq!(quantised.dims(), field.dims());
    assert_eq!(quantised.spacing(), field.spacing());
    assert_eq!(quantised.origin(), field.origin());
    for (&q, &v) in quantised.values().iter().zip(field.values()) {
        assert!((q - v).abs() <= 0.5 / 255.0 + 1e-7);
    }
    for (index, &q) in quantised.values().iter().enumerate() {
        let p = [index % 5, (index / 5) % 9, index / 45];
        assert_eq!(q, hierarchy.density(p));
    }
}

/// Grids of 2^a + 1 × 2^b + 1 × 2^c + 1 points (a, b, c ≤ 3) with random
/// densities.
fn random_grid() -> impl Strategy<Value = DensityGrid> {
    [0u32..=3, 0u32..=3, 0u32..=3].prop_flat_map(|exponents| {
        let dims = exponents.map(|e| (1usize << e) + 1);
        let points = dims.iter().product::<usize>();
        // Mostly smooth-ish small values with occasional spikes.
        proptest::collection::vec(prop_oneof![3 => 0u8..=40, 1 => any::<u8>()], points).prop_map(
            move |values| {
                DensityGrid::new(
                    dims,
                    DVec3::ONE,
                    DVec3::ZERO,
                    values.into_iter().map(|v| f32::from(v) / 255.0).collect(),
                )
                .expect("valid grid")
            },
        )
    })
}

/// Every node's Δ above the voxels is the largest of its local deviation
/// (`local`, by the reference) and `K_max` times its children's Δ, rounded
/// up to 1/65535; Eq. 5 holds exactly on the stored values.
fn check_deviations(
    hierarchy: &VolumeHierarchy,
    local: impl Fn(Node) -> f64,
) -> Result<(), TestCaseError> {
    let k = hierarchy.k_max();
    for node in all_nodes(hierarchy).into_iter().filter(|n| n.level >= 1) {
        let parent = f64::from(hierarchy.deviation_quantised(node));
        let mut bound = local(node);
        for child in node.children().unwrap() {
            let child = f64::from(hierarchy.deviation_quantised(child));
            prop_assert!(parent >= k * child, "{node:?}: {parent} < {k} · {child}");
            bound = bound.max(k * child / 65535.0);
        }
        let excess = parent / 65535.0 - bound;
        prop_assert!(
            (-1e-9..=1.0 / 65535.0 + 1e-9).contains(&excess),
            "{node:?}: Δ {} against {bound}",
            parent / 65535.0
        );
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn deviation_is_the_local_maximum_propagated_by_k_max(
        field in random_grid(),
        min_accuracy in 1.75f64..20.0,
    ) {
        let hierarchy = VolumeHierarchy::new(&field, min_accuracy).unwrap();
        check_deviations(&hierarchy, |node| local_deviation(&hierarchy, node))?;
    }

    #[test]
    fn a_lit_hierarchy_takes_the_larger_deviation_of_density_and_light(
        field in random_grid(),
        min_accuracy in 1.75f64..20.0,
        stride in 1usize..64,
    ) {
        // A light field as rough as the density and unlike it: the density
        // values read in another order.
        let values = field.values();
        let light_values = (0..values.len())
            .map(|i| values[(i * (2 * stride + 1) + stride) % values.len()])
            .collect();
        let light =
            DensityGrid::new(field.dims(), field.spacing(), field.origin(), light_values).unwrap();
        let hierarchy = VolumeHierarchy::with_light(&field, &light, min_accuracy).unwrap();
        // The light's quantised value, exactly (`light` is q / 255 in f32).
        let exact_light = |p| {
            let light = f64::from(hierarchy.light(p).expect("a lit hierarchy"));
            (light * 255.0).round() / 255.0
        };
        check_deviations(&hierarchy, |node| {
            local_deviation(&hierarchy, node).max(local_deviation_of(exact_light, node))
        })?;
        // The ranges stay those of the density.
        for node in all_nodes(&hierarchy) {
            let values: Vec<u8> = box_points(node).map(|p| hierarchy.density_quantised(p)).collect();
            let expected = [*values.iter().min().unwrap(), *values.iter().max().unwrap()];
            prop_assert_eq!(hierarchy.scalar_range_quantised(node), expected, "{:?}", node);
        }
    }

    #[test]
    fn scalar_ranges_are_the_extremes_of_the_covered_points(field in random_grid()) {
        let hierarchy = VolumeHierarchy::new(&field, C).unwrap();
        for node in all_nodes(&hierarchy) {
            let values: Vec<u8> = box_points(node).map(|p| hierarchy.density_quantised(p)).collect();
            let expected = [*values.iter().min().unwrap(), *values.iter().max().unwrap()];
            prop_assert_eq!(hierarchy.scalar_range_quantised(node), expected, "{:?}", node);
        }
    }
}

/// A pair of keyframes keeps each one's Δ and range; the blend of the two at
/// any β deviates from its coarse values by no more than the blended Δ and
/// lies in the blended range, by which the refinement refines and culls; at
/// β = 0 and 1 they are the keyframes' own.
#[test]
fn a_keyframe_pair_bounds_every_blend_of_its_keyframes() {
    let dims = [17, 9, 17];
    let wave = |phase: f32| {
        move |[i, j, k]: [usize; 3]| {
            let x = i as f32 * 0.7 + phase;
            (0.5 + 0.5 * (x.sin() * (k as f32 * 0.45 - phase).cos()) - 0.05 * j as f32)
                .clamp(0.0, 1.0)
        }
    };
    let first = VolumeHierarchy::new(&grid(dims, wave(0.0)), C).unwrap();
    let second = VolumeHierarchy::new(&grid(dims, wave(1.3)), C).unwrap();
    let pair = first.with_next_keyframe(&second).unwrap();
    assert!(pair.has_next_keyframe() && !first.has_next_keyframe());
    assert!((pair.bytes_per_point() - 7.0).abs() < 1e-12);
    let mut largest_blend = 0.0f64;
    for node in all_nodes(&pair) {
        let ranges = [first.scalar_range(node), second.scalar_range(node)];
        assert_eq!(
            pair.scalar_range(node),
            [
                ranges[0][0].min(ranges[1][0]),
                ranges[0][1].max(ranges[1][1])
            ],
            "{node:?}"
        );
        // At either end the refinement sees that keyframe alone, voxels too.
        assert_eq!(
            pair.scalar_range_at(node, 0.0),
            first.scalar_range_quantised(node)
        );
        assert_eq!(
            pair.scalar_range_at(node, 1.0),
            second.scalar_range_quantised(node)
        );
        if node.level == 0 {
            continue;
        }
        assert_eq!(pair.deviation(node), first.deviation(node));
        assert_eq!(pair.next_deviation(node), Some(second.deviation(node)));
        assert_eq!(pair.deviation_at(node, 0.0), first.deviation(node));
        assert_eq!(pair.deviation_at(node, 1.0), second.deviation(node));
        // Over a span of blends: the largest Δ and a range holding each
        // blend's, the span's ends in either order.
        for (start, end) in [(0.0f32, 0.25f32), (0.75, 0.25), (0.5, 1.0)] {
            let deviation = pair.deviation_over(node, [start, end]);
            let [low, high] = pair.scalar_range_over(node, [start, end]);
            for beta in [0.0, 0.25, 0.375, 0.5, 0.625, 0.75, 1.0] {
                if beta < start.min(end) || beta > start.max(end) {
                    continue;
                }
                assert!(
                    deviation >= pair.deviation_at(node, beta),
                    "{node:?}, β = {beta}"
                );
                let [at_low, at_high] = pair.scalar_range_at(node, beta);
                assert!(low <= at_low && at_high <= high, "{node:?}, β = {beta}");
            }
            assert_eq!(
                deviation,
                pair.deviation_at(node, start)
                    .max(pair.deviation_at(node, end))
            );
        }

        let half = node.size() / 2;
        for p in box_points(node) {
            let rel: [usize; 3] = std::array::from_fn(|a| p[a] - node.origin[a]);
            if !rel.iter().all(|r| r % half == 0) || rel.iter().all(|&r| r % node.size() == 0) {
                continue;
            }
            let offsets = [&first, &second].map(|h| exact_density(h, p) - coarse_value(h, node, p));
            let values = [&first, &second].map(|h| exact_density(h, p));
            for beta in [0.0f32, 0.25, 0.5, 0.75, 1.0] {
                let b = f64::from(beta);
                let blend = ((1.0 - b) * offsets[0] + b * offsets[1]).abs();
                largest_blend = largest_blend.max(blend);
                assert!(
                    blend <= f64::from(pair.deviation_at(node, beta)) + 1e-6,
                    "{node:?} at {p:?}, β = {beta}"
                );
                let value = (1.0 - b) * values[0] + b * values[1];
                let [low, high] = pair
                    .scalar_range_at(node, beta)
                    .map(|q| f64::from(q) / 255.0);
                assert!(
                    (low - 1e-9..=high + 1e-9).contains(&value),
                    "{node:?} at {p:?}"
                );
            }
        }
    }
    assert!(
        largest_blend > 0.05,
        "{largest_blend}: the fields are too flat"
    );
    for p in box_points(pair.roots().next().unwrap()).step_by(7) {
        assert_eq!(pair.density(p), first.density(p));
        assert_eq!(pair.next_density(p), Some(second.density(p)));
    }

    // Keyframes of different grids or settings are refused.
    let mismatch = |other: &VolumeHierarchy| {
        matches!(
            first.with_next_keyframe(other),
            Err(HierarchyError::KeyframeMismatch { .. })
        )
    };
    assert!(mismatch(
        &VolumeHierarchy::new(&grid([9, 9, 17], wave(0.0)), C).unwrap()
    ));
    assert!(mismatch(
        &VolumeHierarchy::new(&grid(dims, wave(0.0)), 3.0).unwrap()
    ));
    let lit = VolumeHierarchy::with_light(&grid(dims, wave(0.0)), &grid(dims, wave(2.0)), C);
    assert!(mismatch(&lit.unwrap()));
    let moved = grid(dims, wave(0.0));
    let moved = DensityGrid::new(
        dims,
        moved.spacing(),
        moved.origin() + DVec3::X,
        moved.values().to_vec(),
    )
    .unwrap();
    assert!(mismatch(&VolumeHierarchy::new(&moved, C).unwrap()));
}

#[test]
fn a_paced_keyframe_and_refinement_step_equal_the_unpaced_ones() {
    use std::cell::Cell;
    use std::rc::Rc;

    use glam::{DAffine3, DMat4, UVec2};
    use nebel_core::field::{CloudLighting, CloudNoise, light_field};
    use nebel_core::pacing::with_pacer;
    use nebel_core::transfer::{TransferFunction, TransferPreset};

    use crate::View;

    let dims = [33, 17, 33];
    let noise = CloudNoise {
        seed: 3,
        coverage: 0.5,
        octaves: 3,
        wavelength: 120.0,
        wind: DVec3::new(4.0, 0.0, 2.0),
        ..CloudNoise::default()
    };
    let lighting = CloudLighting {
        sun_direction: DVec3::new(0.4, 0.7, 0.2),
        shadow_extinction: 0.05,
        ..CloudLighting::default()
    };
    let transfer = TransferFunction::preset(TransferPreset::CloudLight)
        .scale_density(0.2)
        .expect("a finite scale");
    let eye = DVec3::new(-60.0, 90.0, -70.0);
    let clip_from_world = DMat4::perspective_infinite_reverse_rh(1.0, 1.6, 1.0)
        * DMat4::look_at_rh(eye, DVec3::new(80.0, 40.0, 80.0), DVec3::Y);
    let view =
        View::new(DAffine3::IDENTITY, eye, UVec2::new(160, 100)).with_projection(clip_from_world);
    let settings = RefinementSettings {
        scalars: CellScalars::LightModulatedByDensity,
        ..RefinementSettings::default()
    };
    // The yield points `work` passes, under a pacer of its own (paced), or
    // none as the work runs unpaced, on every core.
    let counted = |paced: bool, work: &mut dyn FnMut()| {
        if !paced {
            work();
            return 0;
        }
        let calls = Rc::new(Cell::new(0usize));
        let counter = calls.clone();
        with_pacer(Rc::new(move || counter.set(counter.get() + 1)), work);
        calls.get()
    };
    // A keyframe pair and its batch, the work of budgeted builds, as bits,
    // and the yield points of each part.
    let build = |paced: bool| {
        let mut yield_points = Vec::new();
        let mut keyframe = |time: f64| {
            let mut grid = None;
            yield_points.push(counted(paced, &mut || {
                grid = Some(
                    DensityGrid::cloud(dims, DVec3::splat(5.0), DVec3::ZERO, &noise, time)
                        .expect("valid cloud"),
                );
            }));
            let grid = grid.expect("built");
            let mut light = None;
            yield_points.push(counted(paced, &mut || {
                light = Some(light_field(&grid, &lighting).expect("valid light"));
            }));
            let light = light.expect("built");
            let mut hierarchy = None;
            yield_points.push(counted(paced, &mut || {
                hierarchy = Some(VolumeHierarchy::with_light(&grid, &light, C).expect("2^n+1"));
            }));
            let bits = |grid: &DensityGrid| -> Vec<u32> {
                grid.values().iter().map(|v| v.to_bits()).collect()
            };
            (hierarchy.expect("built"), [bits(&grid), bits(&light)])
        };
        let (first, first_bits) = keyframe(0.0);
        let (second, _) = keyframe(4.0);
        let pair = first
            .with_next_keyframe(&second)
            .expect("matching keyframes");
        let mut refinement = None;
        yield_points.push(counted(paced, &mut || {
            refinement = Some(refine(&pair, &view, &transfer, &settings).expect("valid settings"));
        }));
        let refinement = refinement.expect("refined");
        let mut batch = None;
        yield_points.push(counted(paced, &mut || {
            batch =
                Some(lod_batch_with(&pair, &refinement, &view, settings.scalars).expect("a batch"));
        }));
        let batch = batch.expect("emitted");
        assert!(!batch.is_empty(), "the view sees the cloud");
        let sizes = (refinement.stats.nodes_visited, refinement.leaves.len());
        (first_bits, format!("{batch:?}"), sizes, yield_points)
    };
    let (unpaced, paced) = (build(false), build(true));
    assert_eq!(paced.0, unpaced.0, "pacing changes no grid or light field");
    assert_eq!(paced.1, unpaced.1, "pacing changes no cell");
    assert_eq!(paced.2, unpaced.2, "pacing changes no refinement");
    // A yield point at least per z-slice of a grid, per slice of each of
    // the light field's passes, per layer of nodes of each octree level, per
    // node visited by the refinement and per leaf emitted.
    let ((visited, leaves), points) = (paced.2, &paced.3);
    let layers: usize = (1..=4).map(|level| (dims[2] - 1) >> level).sum();
    for keyframe in [&points[0..3], &points[3..6]] {
        assert!(keyframe[0] >= dims[2], "{points:?}");
        assert!(keyframe[1] >= 2 * dims[1].min(dims[2]), "{points:?}");
        assert!(keyframe[2] >= layers, "{points:?}");
    }
    assert!(
        points[6] >= visited && points[7] >= leaves,
        "{points:?} {visited} {leaves}"
    );
}
