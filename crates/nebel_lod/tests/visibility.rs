//! Properties of MPVO (`CellAdjacency`): exact back-to-front order along rays
//! from the eye for convex conforming meshes (regular grids, the search-light
//! cone), in any input order, eye inside or outside; adjacency against brute
//! force and face counts; permutations; bad input.

use glam::{DAffine3, DQuat, DVec3, UVec2, Vec3};
use nebel_core::cell::{Ray, Tetrahedron};
use nebel_core::field::{DensityGrid, search_light_cells};
use nebel_lod::{BatchError, CellAdjacency, Cells, View, sorted_batch};
use proptest::prelude::*;

/// Search-light cone length and half angle used throughout.
const CONE_LENGTH: f64 = 6.0;
const CONE_HALF_ANGLE: f64 = 0.35;

/// A grid whose tetrahedra share vertices bit for bit: `DensityGrid::tetrahedra`
/// computes a voxel's far corners as `min + spacing`, so the spacing and origin
/// must be dyadic for `origin + i·spacing + spacing == origin + (i + 1)·spacing`.
fn grid(dims: [usize; 3], spacing: DVec3, origin: DVec3) -> DensityGrid {
    let count: usize = dims.iter().product();
    let values = (0..count).map(|i| (i % 7) as f32 / 6.0).collect();
    DensityGrid::new(dims, spacing, origin, values).unwrap()
}

/// A point of the search-light cone from three fractions in [0, 1]: distance
/// along the axis, angle around it and radius (inside for `radius < 1`).
fn cone_point(fractions: DVec3, radius: f64) -> DVec3 {
    let distance = CONE_LENGTH * fractions.x;
    let angle = std::f64::consts::TAU * fractions.y;
    let r = distance * CONE_HALF_ANGLE.tan() * radius * fractions.z;
    DVec3::new(r * angle.cos(), r * angle.sin(), -distance)
}

/// Asserts that `order` is a permutation of `0..count`.
fn assert_permutation(order: &[usize], count: usize) {
    let mut seen = vec![false; count];
    assert_eq!(order.len(), count);
    for &cell in order {
        assert!(!seen[cell], "cell {cell} twice");
        seen[cell] = true;
    }
}

/// Checks that along every ray from `eye` towards `targets` the cells it
/// passes through (segments longer than `eps`, world units, behind the eye
/// clipped off) appear in `order` with the farther one first. Returns how many
/// ray-cell hits were checked.
fn assert_back_to_front(
    cells: &[Tetrahedron],
    order: &[usize],
    eye: DVec3,
    targets: &[DVec3],
    eps: f64,
) -> usize {
    assert_permutation(order, cells.len());
    let mut position = vec![0; cells.len()];
    for (index, &cell) in order.iter().enumerate() {
        position[cell] = index;
    }
    let prepared: Vec<_> = cells.iter().map(Tetrahedron::prepare).collect();
    let mut hits_checked = 0;
    for &target in targets {
        let Some(ray) = Ray::new(eye, target - eye) else {
            continue;
        };
        let mut hits: Vec<(f64, usize)> = prepared
            .iter()
            .enumerate()
            .filter_map(|(cell, prepared)| {
                let segment = prepared.as_ref()?.intersect(&ray)?;
                let entry = segment.t_entry.max(0.0);
                (segment.t_exit - entry > eps).then_some((entry, cell))
            })
            .collect();
        hits.sort_by(|a, b| a.0.total_cmp(&b.0));
        for pair in hits.windows(2) {
            let ((near_t, near), (far_t, far)) = (pair[0], pair[1]);
            assert!(
                position[far] < position[near],
                "eye {eye}, towards {target}: cell {far} entered at t = {far_t} is behind \
                 cell {near} entered at t = {near_t} but drawn after it"
            );
        }
        hits_checked += hits.len();
    }
    hits_checked
}

/// Every cell's faces matched against every other cell's, O(n²): the sorted
/// neighbour list per face, `None` on the boundary.
fn brute_force_neighbours(cells: &[Tetrahedron]) -> Vec<[Option<usize>; 4]> {
    let face = |t: &Tetrahedron, f: usize| {
        let mut corners = [1, 2, 3].map(|v| t.positions[(f + v) % 4].to_array());
        corners.sort_by(|a, b| a.partial_cmp(b).unwrap());
        corners
    };
    cells
        .iter()
        .enumerate()
        .map(|(cell, t)| {
            std::array::from_fn(|f| {
                let mine = face(t, f);
                let matches: Vec<usize> = (0..cells.len())
                    .filter(|&other| other != cell)
                    .filter(|&other| (0..4).any(|g| face(&cells[other], g) == mine))
                    .collect();
                (matches.len() == 1).then(|| matches[0])
            })
        })
        .collect()
}

fn neighbours(adjacency: &CellAdjacency) -> Vec<[Option<usize>; 4]> {
    (0..adjacency.len())
        .map(|cell| std::array::from_fn(|f| adjacency.neighbour(cell, f)))
        .collect()
}

/// Boundary triangles of a grid of `voxels` (two per boundary square).
fn grid_boundary_faces([x, y, z]: [usize; 3]) -> usize {
    2 * 2 * (x * y + y * z + z * x)
}

#[test]
fn grid_adjacency_finds_exactly_the_interior_faces() {
    for dims in [[2, 2, 2], [3, 4, 5], [17, 17, 17], [6, 2, 9]] {
        let grid = grid(
            dims,
            DVec3::new(0.5, 0.75, 1.25),
            DVec3::new(-1.0, 0.25, 2.0),
        );
        let cells = grid.tetrahedra();
        let adjacency = CellAdjacency::new(&cells);
        let voxels = dims.map(|n| n - 1);
        let v: usize = voxels.iter().product();
        assert_eq!(adjacency.len(), 6 * v);
        assert_eq!(
            adjacency.interior_face_count(),
            (4 * 6 * v - grid_boundary_faces(voxels)) / 2,
            "{dims:?}"
        );
        // Symmetric, and each face plane has its cell inside and the
        // neighbour's opposite vertex outside.
        for cell in 0..cells.len() {
            for f in 0..4 {
                let plane = adjacency.face_plane(cell, f).unwrap();
                let height = |p: DVec3| plane.normal.dot(p) - plane.offset;
                assert!(height(cells[cell].positions[f]) < 0.0);
                if let Some(other) = adjacency.neighbour(cell, f) {
                    assert!((0..4).any(|g| adjacency.neighbour(other, g) == Some(cell)));
                    let centroid = cells[other].positions.iter().sum::<DVec3>() / 4.0;
                    assert!(height(centroid) > 0.0);
                }
            }
        }
    }
}

#[test]
fn adjacency_matches_brute_force() {
    let grid = grid(
        [4, 3, 3],
        DVec3::new(1.0, 0.5, 2.0),
        DVec3::new(0.25, -3.0, 1.0),
    );
    let meshes = [
        grid.tetrahedra(),
        search_light_cells(CONE_LENGTH, CONE_HALF_ANGLE, [6, 3, 4]).unwrap(),
    ];
    for cells in meshes {
        let adjacency = CellAdjacency::new(&cells);
        let expected = brute_force_neighbours(&cells);
        assert_eq!(neighbours(&adjacency), expected);
        let interior = expected.iter().flatten().flatten().count();
        assert_eq!(2 * adjacency.interior_face_count(), interior);
    }
}

#[test]
fn faces_match_in_any_vertex_order_and_negative_zero() {
    let a = Tetrahedron {
        positions: [
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::X,
            DVec3::Y,
            DVec3::new(0.3, 0.3, 1.0),
        ],
        scalars: [0.5; 4],
    };
    // Shares the face (0, X, Y), listed in another order, one zero negative.
    let b = Tetrahedron {
        positions: [
            DVec3::Y,
            DVec3::new(0.2, 0.2, -1.0),
            DVec3::new(-0.0, 0.0, -0.0),
            DVec3::X,
        ],
        scalars: [0.5; 4],
    };
    let adjacency = CellAdjacency::new(&[a, b]);
    assert_eq!(adjacency.interior_face_count(), 1);
    assert_eq!(adjacency.neighbour(0, 3), Some(1));
    assert_eq!(adjacency.neighbour(1, 1), Some(0));
    assert_eq!(adjacency.neighbour(0, 0), None);
    // Eye above: b (below the shared plane z = 0) first.
    assert_eq!(adjacency.back_to_front(&[a, b], DVec3::Z), [1, 0]);
    assert_eq!(adjacency.back_to_front(&[a, b], -DVec3::Z), [0, 1]);
    // On the plane: no constraint, input order.
    assert_eq!(
        adjacency.back_to_front(&[a, b], DVec3::new(5.0, 7.0, 0.0)),
        [0, 1]
    );
}

#[test]
fn a_face_of_three_cells_and_degenerate_cells_constrain_nothing() {
    let base = [DVec3::ZERO, DVec3::X, DVec3::Y];
    let apex = |z: f64| Tetrahedron {
        positions: [base[0], base[1], base[2], DVec3::new(0.2, 0.2, z)],
        scalars: [0.5; 4],
    };
    // Three cells on one face (not a valid mesh): a boundary face for all.
    let cells = [apex(1.0), apex(-1.0), apex(2.0)];
    let adjacency = CellAdjacency::new(&cells);
    assert_eq!(adjacency.interior_face_count(), 0);
    assert_eq!(adjacency.back_to_front(&cells, DVec3::Z * 5.0), [0, 1, 2]);

    // A flat cell on the shared face: kept, matched with nothing, no plane.
    let flat = Tetrahedron {
        positions: [base[0], base[1], base[2], DVec3::new(0.2, 0.2, 0.0)],
        scalars: [0.5; 4],
    };
    let cells = [flat, apex(1.0), apex(-1.0)];
    let adjacency = CellAdjacency::new(&cells);
    assert_eq!(adjacency.len(), 3);
    assert_eq!(adjacency.interior_face_count(), 1);
    assert_eq!((0..4).find_map(|f| adjacency.neighbour(0, f)), None);
    assert_eq!(adjacency.face_plane(0, 2), None);
    assert_eq!(adjacency.back_to_front(&cells, DVec3::Z * 5.0), [0, 2, 1]);
    assert_eq!(adjacency.back_to_front(&cells, -DVec3::Z * 5.0), [0, 1, 2]);
}

/// A view of cells in world coordinates from `eye`, on a 640 × 480 viewport.
fn view(eye: DVec3) -> View {
    View::new(DAffine3::IDENTITY, eye, UVec2::new(640, 480))
}

#[test]
fn non_finite_eyes_keep_the_input_order_and_sorted_batch_refuses_them() {
    let cells = search_light_cells(CONE_LENGTH, CONE_HALF_ANGLE, [8, 2, 4]).unwrap();
    let adjacency = CellAdjacency::new(&cells);
    let identity: Vec<usize> = (0..cells.len()).collect();
    for eye in [
        DVec3::new(f64::NAN, 0.0, 1.0),
        DVec3::splat(f64::INFINITY),
        DVec3::new(0.0, f64::NEG_INFINITY, 0.0),
    ] {
        assert_eq!(adjacency.back_to_front(&cells, eye), identity);
        let err = sorted_batch(&cells, &adjacency, &view(eye)).unwrap_err();
        assert!(matches!(err, BatchError::NonFiniteEye { .. }), "{err}");
    }
    // A finite eye that a huge transform pulls back to infinity.
    let huge = View {
        world_from_local: DAffine3::from_scale(DVec3::new(1e-300, 1.0, 1.0)),
        ..view(DVec3::new(1e300, 0.0, 0.0))
    };
    let err = sorted_batch(&cells, &adjacency, &huge).unwrap_err();
    assert!(matches!(err, BatchError::NonFiniteEye { .. }), "{err}");
    for singular in [
        DAffine3::from_scale(DVec3::new(1.0, 1.0, 0.0)),
        DAffine3::from_translation(DVec3::new(0.0, f64::NAN, 0.0)),
    ] {
        let view = View {
            world_from_local: singular,
            ..view(DVec3::ONE)
        };
        let err = sorted_batch(&cells, &adjacency, &view).unwrap_err();
        assert!(matches!(err, BatchError::SingularTransform { .. }), "{err}");
    }
    let empty = CellAdjacency::new(&[]);
    assert!(empty.is_empty());
    assert_eq!(empty.back_to_front(&[], DVec3::ONE), Vec::<usize>::new());
    assert!(
        sorted_batch(&[], &empty, &view(DVec3::ONE))
            .unwrap()
            .is_empty()
    );
}

#[test]
#[should_panic(expected = "built for")]
fn back_to_front_refuses_another_mesh() {
    let cells = search_light_cells(CONE_LENGTH, CONE_HALF_ANGLE, [4, 1, 2]).unwrap();
    let adjacency = CellAdjacency::new(&cells);
    adjacency.back_to_front(&cells[1..], DVec3::ONE);
}

#[test]
fn sorted_batch_is_the_reordered_mesh() {
    let cells = search_light_cells(CONE_LENGTH, CONE_HALF_ANGLE, [8, 2, 4]).unwrap();
    let adjacency = CellAdjacency::new(&cells);
    let eye = DVec3::new(3.0, -1.0, 2.0);
    let order = adjacency.back_to_front(&cells, eye);
    let batch = sorted_batch(&cells, &adjacency, &view(eye)).unwrap();
    let reordered: Vec<Tetrahedron> = order.iter().map(|&c| cells[c]).collect();
    assert_eq!(batch, Cells::from_tetrahedra(&reordered));
    assert_eq!(batch.len(), cells.len());
    assert_eq!(batch.bounds_max.z, 0.0);
    assert!((batch.bounds_min.z - (-CONE_LENGTH as f32)).abs() < 1e-5);
    assert!(batch.bounds_min.cmplt(Vec3::ZERO).all());

    // A moved, mirrored and stretched mesh: ordered in its own frame, drawn
    // in the world, back to front along rays from the world eye.
    let world_from_local = DAffine3::from_scale_rotation_translation(
        DVec3::new(-2.0, 0.5, 1.5),
        DQuat::from_rotation_y(0.8),
        DVec3::new(10.0, -4.0, 3.0),
    );
    let moved = View {
        world_from_local,
        ..view(world_from_local.transform_point3(eye))
    };
    let batch = sorted_batch(&cells, &adjacency, &moved).unwrap();
    let in_world: Vec<Tetrahedron> = order
        .iter()
        .map(|&c| Tetrahedron {
            positions: cells[c]
                .positions
                .map(|p| world_from_local.transform_point3(p)),
            scalars: cells[c].scalars,
        })
        .collect();
    assert_eq!(batch, Cells::from_tetrahedra(&in_world));
    let drawn: Vec<Tetrahedron> = batch
        .tetrahedra
        .iter()
        .map(nebel_lod::GpuCell::to_tetrahedron)
        .collect();
    let targets: Vec<DVec3> = [0.2, 0.5, 0.9]
        .map(|f| world_from_local.transform_point3(cone_point(DVec3::new(f, f, 0.5), 0.8)))
        .to_vec();
    let identity: Vec<usize> = (0..drawn.len()).collect();
    assert!(assert_back_to_front(&drawn, &identity, moved.eye, &targets, 1e-6) > 0);

    // An empty viewport sees nothing.
    let hidden = View {
        viewport: UVec2::new(0, 480),
        ..moved
    };
    assert!(
        sorted_batch(&cells, &adjacency, &hidden)
            .unwrap()
            .is_empty()
    );
}

/// The bench meshes (search-light cone 16 × 4 × 32, 16³ grid), eyes outside
/// and inside, rays towards points spread over the mesh.
#[test]
fn full_size_meshes_are_ordered_along_rays() {
    let targets = |point: &dyn Fn(DVec3) -> DVec3| -> Vec<DVec3> {
        (0..24)
            .map(|i| {
                let f = |k: u32| ((i as f64 + 0.5) * [0.618, 0.414, 0.732][k as usize]).fract();
                point(DVec3::new(f(0), f(1), f(2)))
            })
            .collect()
    };
    let cone = search_light_cells(CONE_LENGTH, CONE_HALF_ANGLE, [16, 4, 32]).unwrap();
    let cone_targets = targets(&|f| cone_point(f, 0.99));
    let cone_eyes = [
        DVec3::new(3.0, 2.0, 1.5),
        DVec3::new(-0.3, 0.2, -8.0),
        cone_point(DVec3::new(0.37, 0.21, 0.55), 1.0),
        cone_point(DVec3::new(0.81, 0.66, 0.93), 1.0),
    ];
    let spacing = DVec3::new(0.25, 0.375, 0.125);
    let grid = grid([17; 3], spacing, DVec3::new(-2.0, 0.0, -1.5));
    let grid_cells = grid.tetrahedra();
    let extent = 16.0 * spacing;
    let grid_targets = targets(&|f| grid.origin() + f * extent);
    let grid_eyes = [
        grid.origin() + DVec3::new(1.4, -0.7, 1.9) * extent,
        grid.origin() + DVec3::new(0.33, 0.71, 0.48) * extent,
    ];
    for (cells, eyes, targets) in [
        (&cone, &cone_eyes[..], &cone_targets),
        (&grid_cells, &grid_eyes[..], &grid_targets),
    ] {
        let adjacency = CellAdjacency::new(cells);
        for &eye in eyes {
            let order = adjacency.back_to_front(cells, eye);
            let hits = assert_back_to_front(cells, &order, eye, targets, 1e-9);
            assert!(hits > 5 * targets.len(), "only {hits} hits");
        }
    }
}

fn fractions() -> impl Strategy<Value = DVec3> {
    (0.0..1.0f64, 0.0..1.0f64, 0.0..1.0f64).prop_map(|(x, y, z)| DVec3::new(x, y, z))
}

/// An eye: inside the mesh, or anywhere in a box around it three times its
/// size (mostly outside), as fractions.
fn eye() -> impl Strategy<Value = (bool, DVec3)> {
    (any::<bool>(), fractions())
}

/// Where the rays go: points of the mesh (fractions) or random directions.
fn targets() -> impl Strategy<Value = (Vec<DVec3>, Vec<DVec3>)> {
    (
        prop::collection::vec(fractions(), 12),
        prop::collection::vec(fractions().prop_map(|f| 2.0 * f - 1.0), 4),
    )
}

fn shuffled(cells: &[Tetrahedron], seed: u64) -> Vec<Tetrahedron> {
    let mut cells = cells.to_vec();
    let mut state = seed;
    for i in (1..cells.len()).rev() {
        // SplitMix64.
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        cells.swap(i, ((z ^ (z >> 31)) % (i as u64 + 1)) as usize);
    }
    cells
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    #[test]
    fn grid_order_is_back_to_front_along_rays(
        dims in (2..7usize, 2..6usize, 2..7usize),
        spacing in (1..16u8, 1..16u8, 1..16u8),
        (inside, eye_fraction) in eye(),
        (points, directions) in targets(),
        shuffle in any::<Option<u64>>(),
    ) {
        let spacing = DVec3::new(spacing.0.into(), spacing.1.into(), spacing.2.into()) / 8.0;
        let grid = grid([dims.0, dims.1, dims.2], spacing, DVec3::new(-1.0, 0.5, 0.25));
        let extent = grid.max_corner() - grid.origin();
        let eye = if inside {
            grid.origin() + eye_fraction * extent
        } else {
            grid.origin() + (3.0 * eye_fraction - 1.0) * extent
        };
        let cells = match shuffle {
            Some(seed) => shuffled(&grid.tetrahedra(), seed),
            None => grid.tetrahedra(),
        };
        let mut rays: Vec<DVec3> = points.iter().map(|&f| grid.origin() + f * extent).collect();
        rays.extend(directions.iter().map(|&d| eye + d));
        let order = CellAdjacency::new(&cells).back_to_front(&cells, eye);
        assert_back_to_front(&cells, &order, eye, &rays, 1e-9);
    }

    #[test]
    fn cone_order_is_back_to_front_along_rays(
        segments in (4..12usize, 1..4usize, 1..8usize),
        (inside, eye_fraction) in eye(),
        (points, directions) in targets(),
        shuffle in any::<Option<u64>>(),
    ) {
        let cells = search_light_cells(
            CONE_LENGTH,
            CONE_HALF_ANGLE,
            [segments.0, segments.1, segments.2],
        ).unwrap();
        let cells = match shuffle {
            Some(seed) => shuffled(&cells, seed),
            None => cells,
        };
        let eye = if inside {
            cone_point(eye_fraction, 1.0)
        } else {
            (3.0 * eye_fraction - 1.5) * CONE_LENGTH
        };
        let mut rays: Vec<DVec3> = points.iter().map(|&f| cone_point(f, 0.99)).collect();
        rays.extend(directions.iter().map(|&d| eye + d));
        let order = CellAdjacency::new(&cells).back_to_front(&cells, eye);
        assert_back_to_front(&cells, &order, eye, &rays, 1e-9);
    }
}
