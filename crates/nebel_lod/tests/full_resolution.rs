//! Properties of `full_resolution_batch`: exact visibility order along rays from
//! the eye, complete and conforming tiling, the zero-opacity test and frustum
//! culling against brute force, and refusal of bad input.

use std::collections::HashMap;

use glam::{DAffine3, DMat3, DMat4, DQuat, DVec3, UVec2, Vec3};
use nebel_core::cell::{Ray, Tetrahedron};
use nebel_core::field::DensityGrid;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_lod::{
    BatchError, BrickTable, CellOrder, Cells, Frustum, GpuCell, View, full_resolution_batch,
};
use proptest::prelude::*;

/// ρ > 0 for every s > 0.
fn linear_transfer() -> TransferFunction {
    TransferFunction::preset(TransferPreset::GroundFog)
}

fn grid(dims: [usize; 3], spacing: DVec3, origin: DVec3, values: &[f32]) -> DensityGrid {
    let count: usize = dims.iter().product();
    let values = (0..count).map(|i| values[i % values.len()]).collect();
    DensityGrid::new(dims, spacing, origin, values).unwrap()
}

/// The view of a grid placed by `world_from_grid` from `eye`, culled by
/// `frustum`, on a 640 × 480 viewport.
fn view(world_from_grid: DAffine3, eye: DVec3, frustum: Option<&Frustum>) -> View {
    View {
        frustum: frustum.cloned(),
        ..View::new(world_from_grid, eye, UVec2::new(640, 480))
    }
}

fn batch(
    grid: &DensityGrid,
    brick_size: usize,
    world_from_grid: DAffine3,
    eye: DVec3,
    frustum: Option<&Frustum>,
    transfer: &TransferFunction,
    order: CellOrder,
) -> Cells {
    let bricks = BrickTable::new(grid, brick_size);
    let view = view(world_from_grid, eye, frustum);
    full_resolution_batch(grid, &bricks, &view, transfer, order).unwrap()
}

fn voxel_count(grid: &DensityGrid) -> usize {
    grid.dims().iter().map(|n| n - 1).product()
}

/// Checks that along every ray from `eye` the cells it passes through appear in
/// `cells` with the farther one first, ignoring segments shorter than `eps`
/// (world units). Returns how many ray-cell pairs were seen.
fn assert_back_to_front(cells: &[GpuCell], eye: DVec3, directions: &[DVec3], eps: f64) -> usize {
    let cells: Vec<Tetrahedron> = cells.iter().map(GpuCell::to_tetrahedron).collect();
    assert_back_to_front_f64(&cells, eye, directions, eps)
}

/// [`assert_back_to_front`] for cells in f64.
fn assert_back_to_front_f64(
    cells: &[Tetrahedron],
    eye: DVec3,
    directions: &[DVec3],
    eps: f64,
) -> usize {
    let prepared: Vec<_> = cells
        .iter()
        .map(|c| c.prepare().expect("non-degenerate cell"))
        .collect();
    let mut pairs = 0;
    for &direction in directions {
        let Some(ray) = Ray::new(eye, direction) else {
            continue;
        };
        let mut hits: Vec<(f64, f64, usize)> = prepared
            .iter()
            .enumerate()
            .filter_map(|(index, cell)| {
                let segment = cell.intersect(&ray)?;
                let entry = segment.t_entry.max(0.0);
                (segment.t_exit - entry > eps).then_some((entry, segment.t_exit, index))
            })
            .collect();
        hits.sort_by(|a, b| (a.0 + a.1).total_cmp(&(b.0 + b.1)));
        for pair in hits.windows(2) {
            let (near, far) = (pair[0], pair[1]);
            assert!(
                near.1 <= far.0 + eps,
                "cells {} and {} overlap along the ray: {near:?} {far:?}",
                near.2,
                far.2
            );
            assert!(
                far.2 < near.2,
                "eye {eye}, direction {direction}: cell {} at t = {:.6}..{:.6} is behind cell {} at t = {:.6}..{:.6} but drawn after it",
                far.2,
                far.0,
                far.1,
                near.2,
                near.0,
                near.1
            );
        }
        pairs += hits.len();
    }
    pairs
}

fn unit_vector() -> impl Strategy<Value = DVec3> {
    (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64)
        .prop_filter("non-zero", |(x, y, z)| x * x + y * y + z * z > 1e-4)
        .prop_map(|(x, y, z)| DVec3::new(x, y, z).normalize())
}

/// Where the eye goes, in voxel index coordinates relative to the grid.
#[derive(Clone, Debug)]
enum EyePlacement {
    /// Anywhere in a box three times the grid's size (mostly outside).
    Anywhere(DVec3),
    /// Inside the grid.
    Inside(DVec3),
    /// At a voxel centre.
    VoxelCentre([u8; 3]),
    /// On grid planes: each axis either on a plane (integer) or free.
    OnPlanes([u8; 3], [bool; 3], DVec3),
}

fn eye_placement() -> impl Strategy<Value = EyePlacement> {
    let fraction = || (0.0..1.0f64, 0.0..1.0f64, 0.0..1.0f64);
    prop_oneof![
        fraction().prop_map(|(x, y, z)| EyePlacement::Anywhere(DVec3::new(x, y, z))),
        fraction().prop_map(|(x, y, z)| EyePlacement::Inside(DVec3::new(x, y, z))),
        any::<[u8; 3]>().prop_map(EyePlacement::VoxelCentre),
        (any::<[u8; 3]>(), any::<[bool; 3]>(), fraction())
            .prop_map(|(i, on, (x, y, z))| EyePlacement::OnPlanes(i, on, DVec3::new(x, y, z))),
    ]
}

impl EyePlacement {
    /// The eye in voxel index coordinates of a grid with `voxels` per axis.
    fn index_position(&self, voxels: [usize; 3]) -> DVec3 {
        let n = DVec3::from(voxels.map(|v| v as f64));
        match self {
            Self::Anywhere(f) => (*f * 3.0 - 1.0) * n,
            Self::Inside(f) => *f * n,
            Self::VoxelCentre(i) => DVec3::from(std::array::from_fn::<f64, 3, _>(|a| {
                (i[a] as usize % voxels[a]) as f64 + 0.5
            })),
            Self::OnPlanes(i, on, f) => DVec3::from(std::array::from_fn::<f64, 3, _>(|a| {
                if on[a] {
                    (i[a] as usize % (voxels[a] + 1)) as f64
                } else {
                    f[a] * voxels[a] as f64
                }
            })),
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]

    /// Exact order with the eye exactly where it was placed: axis-aligned grids
    /// with dyadic spacing, so every position is exact in f32 and f64.
    #[test]
    fn order_is_back_to_front_for_exact_eyes(
        dims in prop::array::uniform3(2usize..6),
        spacing_exponents in prop::array::uniform3(-1i32..2),
        origin in prop::array::uniform3(-3i32..3),
        mirror in any::<bool>(),
        placement in eye_placement(),
        brick_size in 1usize..4,
        directions in prop::collection::vec(unit_vector(), 40),
    ) {
        let spacing = DVec3::from(spacing_exponents.map(|e| 2f64.powi(e)));
        let origin = DVec3::from(origin.map(f64::from));
        let g = grid(dims, spacing, origin, &[0.3, 0.7, 0.1, 0.9, 0.5]);
        // A mirror in x is exact too and flips the handedness.
        let world_from_grid = if mirror {
            DAffine3::from_scale(DVec3::new(-1.0, 1.0, 1.0))
        } else {
            DAffine3::IDENTITY
        };
        let u = placement.index_position(g.dims().map(|n| n - 1));
        let eye = world_from_grid.transform_point3(origin + u * spacing);
        let b = batch(&g, brick_size, world_from_grid, eye, None, &linear_transfer(), CellOrder::BackToFront);
        prop_assert_eq!(b.len(), 6 * voxel_count(&g));
        assert_back_to_front(&b.tetrahedra, eye, &directions, 1e-9);
        // Rays towards the voxel centres and grid points reach every cell.
        let targets: Vec<DVec3> = b.tetrahedra.iter().map(|c| {
            let t = c.to_tetrahedron();
            t.positions.iter().sum::<DVec3>() / 4.0 - eye
        }).collect();
        assert_back_to_front(&b.tetrahedra, eye, &targets, 1e-9);
    }

    /// Exact order under general affine maps (rotation, non-uniform scale,
    /// shear, mirror), eye anywhere.
    #[test]
    fn order_is_back_to_front_under_affine_maps(
        dims in prop::array::uniform3(2usize..5),
        rotation in unit_vector(),
        angle in 0.0..6.3f64,
        scale in prop::array::uniform3(0.3..3.0f64),
        shear in prop::array::uniform3(-0.5..0.5f64),
        mirror in any::<bool>(),
        placement in eye_placement(),
        directions in prop::collection::vec(unit_vector(), 40),
    ) {
        let g = grid(dims, DVec3::new(0.7, 1.1, 0.9), DVec3::new(-1.0, 0.5, 2.0), &[0.2, 0.6, 0.9]);
        let shear = DMat3::from_cols(
            DVec3::X,
            DVec3::new(shear[0], 1.0, 0.0),
            DVec3::new(shear[1], shear[2], 1.0),
        );
        let mirror = DMat3::from_diagonal(DVec3::new(if mirror { -1.0 } else { 1.0 }, 1.0, 1.0));
        let linear = DMat3::from_quat(DQuat::from_axis_angle(rotation, angle))
            * DMat3::from_diagonal(DVec3::from(scale))
            * shear
            * mirror;
        let world_from_grid = DAffine3::from_mat3_translation(linear, DVec3::new(5.0, -2.0, 1.0));
        let u = placement.index_position(g.dims().map(|n| n - 1));
        let eye = world_from_grid.transform_point3(g.origin() + u * g.spacing());
        let b = batch(&g, 2, world_from_grid, eye, None, &linear_transfer(), CellOrder::BackToFront);
        prop_assert_eq!(b.len(), 6 * voxel_count(&g));
        // The order is exact for the f64 geometry: check it on the cells
        // rebuilt in f64 from their grid points. (In f32, an eye within
        // rounding of a plane may see slivers of about 1e-7 × coordinates in
        // the other order, which no image can show.)
        let exact = exact_cells(&b.tetrahedra, &g, world_from_grid);
        let pairs = assert_back_to_front_f64(&exact, eye, &directions, 1e-9);
        // An eye strictly inside sees cells in every direction.
        let inside = matches!(placement, EyePlacement::Inside(_) | EyePlacement::VoxelCentre(_));
        prop_assert!(pairs > 0 || !inside);
    }

    /// Frustum culling keeps every cell with a point inside the frustum, drops
    /// (with one-voxel bricks) every voxel entirely outside one plane, and keeps
    /// the order of the full batch.
    #[test]
    fn frustum_culling_matches_brute_force(
        dims in prop::array::uniform3(2usize..7),
        eye in prop::array::uniform3(-4.0..4.0f64),
        look in unit_vector(),
        fov in 0.3..2.0f64,
        brick_size in 1usize..4,
    ) {
        let g = grid(dims, DVec3::splat(0.5), DVec3::splat(-1.0), &[0.4, 0.8, 0.2]);
        let world_from_grid = DAffine3::from_rotation_y(0.4);
        let eye = DVec3::from(eye);
        let view = DMat4::look_to_rh(eye, look, if look.y.abs() > 0.9 { DVec3::X } else { DVec3::Y });
        let frustum = Frustum::from_view_projection(
            DMat4::perspective_infinite_reverse_rh(fov, 1.3, 0.05) * view,
        ).unwrap();
        let transfer = linear_transfer();
        let full = batch(&g, brick_size, world_from_grid, eye, None, &transfer, CellOrder::BackToFront);
        let culled = batch(&g, brick_size, world_from_grid, eye, Some(&frustum), &transfer, CellOrder::BackToFront);
        let key = |c: &GpuCell| c.vertices.map(|v| v.map(f32::to_bits));
        let kept: HashMap<_, usize> = culled.tetrahedra.iter().enumerate().map(|(i, c)| (key(c), i)).collect();
        // Order: the culled batch is a subsequence of the full one.
        let mut last = None;
        for cell in &full.tetrahedra {
            if let Some(&index) = kept.get(&key(cell)) {
                prop_assert!(last.is_none_or(|l| index > l));
                last = Some(index);
            }
        }
        for cell in &full.tetrahedra {
            let t = cell.to_tetrahedron();
            let inside = sample_points(&t).any(|p| strictly_inside(&frustum, p));
            if inside {
                prop_assert!(kept.contains_key(&key(cell)), "a cell inside the frustum was culled");
            }
        }
        if brick_size == 1 {
            for cell in &culled.tetrahedra {
                let t = cell.to_tetrahedron();
                let centroid = t.positions.iter().sum::<DVec3>() / 4.0;
                let voxel = (world_from_grid.inverse().transform_point3(centroid) - g.origin()) / g.spacing();
                let min = g.origin() + voxel.floor() * g.spacing();
                let corners: Vec<DVec3> = (0..8).map(|v| {
                    let bits = DVec3::new((v & 1) as f64, ((v >> 1) & 1) as f64, ((v >> 2) & 1) as f64);
                    world_from_grid.transform_point3(min + bits * g.spacing())
                }).collect();
                let outside_one_plane = frustum.planes().iter().any(|plane| {
                    corners.iter().all(|c| plane.truncate().dot(*c) + plane.w < -1e-9)
                });
                prop_assert!(!outside_one_plane, "a voxel entirely outside a plane was kept");
            }
        }
    }

    /// The zero-opacity test drops exactly the bricks whose scalar range has no
    /// ρ > 0: compared with a brute-force scan of each brick's points.
    #[test]
    fn zero_opacity_test_matches_brute_force(
        dims in prop::array::uniform3(2usize..9),
        values in prop::collection::vec(prop_oneof![3 => Just(0.0f32), 1 => 0.0..0.1f32, 1 => 0.0..1.0f32], 1..40),
        brick_size in 1usize..5,
    ) {
        let g = grid(dims, DVec3::ONE, DVec3::ZERO, &values);
        // The cloud preset: ρ = 0 up to s = 0.05, then a step to ρ > 0.
        let transfer = TransferFunction::preset(TransferPreset::Cloud);
        let b = batch(&g, brick_size, DAffine3::IDENTITY, DVec3::splat(-5.0), None, &transfer, CellOrder::BackToFront);
        let mut voxels_seen: HashMap<[usize; 3], usize> = HashMap::new();
        for cell in &b.tetrahedra {
            let centroid = cell.to_tetrahedron().positions.iter().sum::<DVec3>() / 4.0;
            *voxels_seen.entry(centroid.floor().to_array().map(|c| c as usize)).or_default() += 1;
        }
        let voxels = g.dims().map(|n| n - 1);
        for k in 0..voxels[2] {
            for j in 0..voxels[1] {
                for i in 0..voxels[0] {
                    let brick = [i, j, k].map(|v| v / brick_size);
                    let points = |axis: usize| {
                        brick[axis] * brick_size..=((brick[axis] + 1) * brick_size).min(voxels[axis])
                    };
                    let mut any_opaque = false;
                    for z in points(2) {
                        for y in points(1) {
                            for x in points(0) {
                                any_opaque |= transfer.evaluate(f64::from(g.value(x, y, z))).rho > 0.0;
                            }
                        }
                    }
                    let emitted = voxels_seen.get(&[i, j, k]).copied().unwrap_or(0);
                    prop_assert_eq!(emitted, if any_opaque { 6 } else { 0 }, "voxel {:?}", [i, j, k]);
                }
            }
        }
    }
}

/// The cells of a batch of `grid` in f64: each f32 vertex snapped to its grid
/// point and transformed again in f64.
fn exact_cells(
    cells: &[GpuCell],
    grid: &DensityGrid,
    world_from_grid: DAffine3,
) -> Vec<Tetrahedron> {
    let grid_from_world = world_from_grid.inverse();
    cells
        .iter()
        .map(|cell| {
            let mut t = cell.to_tetrahedron();
            for p in &mut t.positions {
                let index = ((grid_from_world.transform_point3(*p) - grid.origin())
                    / grid.spacing())
                .round();
                *p = world_from_grid.transform_point3(grid.origin() + index * grid.spacing());
            }
            t
        })
        .collect()
}

/// Vertices, edge midpoints, face centres, the centroid and a few interior
/// points of a tetrahedron.
fn sample_points(t: &Tetrahedron) -> impl Iterator<Item = DVec3> + '_ {
    const WEIGHTS: [[f64; 4]; 9] = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
        [0.25, 0.25, 0.25, 0.25],
        [0.7, 0.1, 0.1, 0.1],
        [0.1, 0.7, 0.1, 0.1],
        [0.1, 0.1, 0.7, 0.1],
        [0.1, 0.1, 0.1, 0.7],
    ];
    let edges = (0..4).flat_map(|a| (a + 1..4).map(move |b| (a, b)));
    WEIGHTS
        .iter()
        .map(|w| (0..4).map(|v| w[v] * t.positions[v]).sum())
        .chain(edges.map(|(a, b)| (t.positions[a] + t.positions[b]) / 2.0))
        .chain((0..4).map(|skip| {
            (0..4)
                .filter(|&v| v != skip)
                .map(|v| t.positions[v])
                .sum::<DVec3>()
                / 3.0
        }))
}

fn strictly_inside(frustum: &Frustum, p: DVec3) -> bool {
    frustum
        .planes()
        .iter()
        .all(|plane| plane.truncate().dot(p) + plane.w > 1e-9)
}

#[test]
fn full_batch_tiles_the_box_conformingly_and_unordered_has_the_same_cells() {
    let g = grid(
        [5, 4, 6],
        DVec3::new(0.3, 0.5, 0.2),
        DVec3::new(1.0, -2.0, 0.5),
        &[0.1, 0.5, 0.9, 0.3],
    );
    let world_from_grid = DAffine3::from_scale_rotation_translation(
        DVec3::new(2.0, -1.0, 0.5),
        DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -1.2, 2.0),
        DVec3::new(100.0, 20.0, -7.0),
    );
    let transfer = linear_transfer();
    let eye = DVec3::new(101.0, 19.0, -6.5);
    let b = batch(
        &g,
        2,
        world_from_grid,
        eye,
        None,
        &transfer,
        CellOrder::BackToFront,
    );
    assert_eq!(b.len(), 6 * 4 * 3 * 5);
    let volume: f64 = b
        .tetrahedra
        .iter()
        .map(|c| c.to_tetrahedron().volume())
        .sum();
    let extent = g.max_corner() - g.origin();
    let expected = extent.x * extent.y * extent.z * world_from_grid.matrix3.determinant().abs();
    assert!(
        (volume - expected).abs() < 1e-5 * expected,
        "{volume} vs {expected}"
    );

    // Conforming in f32: every triangle is shared by at most two cells and the
    // triangles used once make up exactly the box's surface.
    let mut faces: HashMap<[[u32; 3]; 3], (usize, f64)> = HashMap::new();
    for cell in &b.tetrahedra {
        let t = cell.to_tetrahedron();
        for skip in 0..4 {
            let mut corners: Vec<(DVec3, [u32; 3])> = (0..4)
                .filter(|&v| v != skip)
                .map(|v| {
                    (
                        t.positions[v],
                        cell.position(v).to_array().map(f32::to_bits),
                    )
                })
                .collect();
            corners.sort_by_key(|c| c.1);
            let area = (corners[1].0 - corners[0].0)
                .cross(corners[2].0 - corners[0].0)
                .length()
                / 2.0;
            faces
                .entry([corners[0].1, corners[1].1, corners[2].1])
                .or_insert((0, area))
                .0 += 1;
        }
    }
    assert!(faces.values().all(|&(count, _)| count <= 2));
    let boundary: f64 = faces.values().filter(|f| f.0 == 1).map(|f| f.1).sum();
    let m = world_from_grid.matrix3;
    let side = |a: DVec3, b: DVec3| 2.0 * (m * a).cross(m * b).length();
    let surface = side(DVec3::X * extent.x, DVec3::Y * extent.y)
        + side(DVec3::Y * extent.y, DVec3::Z * extent.z)
        + side(DVec3::Z * extent.z, DVec3::X * extent.x);
    assert!(
        (boundary - surface).abs() < 1e-4 * surface,
        "{boundary} vs {surface}"
    );

    // Bounds are those of the vertices.
    let recomputed = Cells::with_bounds(b.tetrahedra.clone());
    assert_eq!(
        (b.bounds_min, b.bounds_max),
        (recomputed.bounds_min, recomputed.bounds_max)
    );

    // Unordered: the same cells, another order, independent of the eye.
    let unordered = batch(
        &g,
        2,
        world_from_grid,
        eye,
        None,
        &transfer,
        CellOrder::Unordered,
    );
    let sorted = |cells: &[GpuCell]| {
        let mut keys: Vec<_> = cells
            .iter()
            .map(|c| c.vertices.map(|v| v.map(f32::to_bits)))
            .collect();
        keys.sort();
        keys
    };
    assert_eq!(sorted(&unordered.tetrahedra), sorted(&b.tetrahedra));
    let elsewhere = batch(
        &g,
        2,
        world_from_grid,
        -eye,
        None,
        &transfer,
        CellOrder::Unordered,
    );
    assert_eq!(elsewhere, unordered);
}

#[test]
fn transparent_grids_give_empty_batches() {
    // Below the cloud preset's cut-off everywhere: nothing to draw.
    let g = grid([6, 6, 6], DVec3::ONE, DVec3::ZERO, &[0.0, 0.04, 0.02]);
    let transfer = TransferFunction::preset(TransferPreset::Cloud);
    let b = batch(
        &g,
        2,
        DAffine3::IDENTITY,
        DVec3::splat(3.0),
        None,
        &transfer,
        CellOrder::BackToFront,
    );
    assert!(b.is_empty());
    assert_eq!((b.bounds_min, b.bounds_max), (Vec3::ZERO, Vec3::ZERO));
    // One point just above the cut-off keeps the bricks around it.
    let mut values = vec![0.0f32; 216];
    values[3 + 6 * (3 + 6 * 3)] = 0.06;
    let g = DensityGrid::new([6, 6, 6], DVec3::ONE, DVec3::ZERO, values).unwrap();
    let b = batch(
        &g,
        2,
        DAffine3::IDENTITY,
        DVec3::splat(3.0),
        None,
        &transfer,
        CellOrder::BackToFront,
    );
    // Point 3 lies inside brick 1 (voxels 2..4) on each axis: one brick, 8 voxels.
    assert_eq!(b.len(), 6 * 8);
    assert_eq!(
        (b.bounds_min, b.bounds_max),
        (Vec3::splat(2.0), Vec3::splat(4.0))
    );
}

#[test]
fn bad_input_gives_clear_errors_and_never_panics() {
    let g = grid([4, 4, 4], DVec3::ONE, DVec3::ZERO, &[0.5]);
    let transfer = linear_transfer();
    let bricks = BrickTable::new(&g, 0);
    assert_eq!(bricks.brick_size(), 1);
    assert_eq!(bricks.brick_counts(), [3, 3, 3]);
    assert_eq!(bricks.scalar_range([2, 2, 2]), Some([0.5, 0.5]));
    assert_eq!(bricks.scalar_range([3, 0, 0]), None);
    let build = |eye: DVec3, world: DAffine3, order| {
        full_resolution_batch(&g, &bricks, &view(world, eye, None), &transfer, order)
    };

    let err = build(DVec3::NAN, DAffine3::IDENTITY, CellOrder::BackToFront).unwrap_err();
    assert!(matches!(err, BatchError::NonFiniteEye { .. }));
    assert!(err.to_string().contains("Unordered"), "{err}");
    let b = build(DVec3::NAN, DAffine3::IDENTITY, CellOrder::Unordered).unwrap();
    assert_eq!(b.len(), 6 * 27);
    let b = build(DVec3::INFINITY, DAffine3::IDENTITY, CellOrder::Unordered).unwrap();
    assert_eq!(b.len(), 6 * 27);

    for world in [
        DAffine3::from_scale(DVec3::new(1.0, 0.0, 1.0)),
        DAffine3::from_translation(DVec3::NAN),
        DAffine3::from_scale(DVec3::splat(f64::INFINITY)),
    ] {
        let err = build(DVec3::ONE, world, CellOrder::BackToFront).unwrap_err();
        assert!(matches!(err, BatchError::SingularTransform { .. }), "{err}");
    }

    let other = grid([5, 4, 4], DVec3::ONE, DVec3::ZERO, &[0.5]);
    let err = full_resolution_batch(
        &other,
        &bricks,
        &view(DAffine3::IDENTITY, DVec3::ONE, None),
        &transfer,
        CellOrder::BackToFront,
    )
    .unwrap_err();
    assert_eq!(
        err,
        BatchError::BrickTableMismatch {
            table: [3, 3, 3],
            grid: [4, 3, 3]
        }
    );
    assert!(err.to_string().contains("BrickTable::new"));

    // An empty viewport sees nothing, but the view is still checked.
    for viewport in [UVec2::new(0, 480), UVec2::new(640, 0), UVec2::ZERO] {
        let hidden = View {
            viewport,
            ..view(DAffine3::IDENTITY, DVec3::ONE, None)
        };
        for order in [CellOrder::BackToFront, CellOrder::Unordered] {
            let b = full_resolution_batch(&g, &bricks, &hidden, &transfer, order).unwrap();
            assert_eq!(b, Cells::default());
        }
        let nan_eye = View {
            eye: DVec3::NAN,
            ..hidden.clone()
        };
        let err = full_resolution_batch(&g, &bricks, &nan_eye, &transfer, CellOrder::BackToFront);
        assert!(matches!(err, Err(BatchError::NonFiniteEye { .. })));
        let singular = View {
            world_from_local: DAffine3::ZERO,
            ..hidden
        };
        let err = full_resolution_batch(&g, &bricks, &singular, &transfer, CellOrder::Unordered);
        assert!(matches!(err, Err(BatchError::SingularTransform { .. })));
    }

    // Far eyes and 100 km coordinates: finite output in the right order.
    for eye in [
        DVec3::splat(1e300),
        DVec3::new(-1e300, 2.0, 1e-300),
        DVec3::new(1e5, 1.5, 1.5),
    ] {
        let b = build(eye, DAffine3::IDENTITY, CellOrder::BackToFront).unwrap();
        assert_eq!(b.len(), 6 * 27);
        assert!(
            b.tetrahedra
                .iter()
                .flat_map(|c| c.vertices)
                .flatten()
                .all(f32::is_finite)
        );
    }
    let far = DAffine3::from_translation(DVec3::new(1e5, 0.0, -1e5));
    let eye = DVec3::new(1e5 + 1.5, 1.5, -1e5 + 1.5);
    let b = build(eye, far, CellOrder::BackToFront).unwrap();
    let pairs = assert_back_to_front(
        &b.tetrahedra,
        eye,
        // Not along a plane u_a = u_b through the voxel's centre, which holds
        // the eye and faces between tetrahedra.
        &[
            DVec3::new(1.0, 0.1, -0.2),
            DVec3::new(0.3, -0.2, 0.9),
            DVec3::new(0.15, -1.0, 0.05),
        ],
        1e-9,
    );
    assert!(pairs >= 6);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    /// Equal order keys give identical batches; the key is finite input only.
    #[test]
    fn equal_order_keys_give_equal_batches(
        a in prop::array::uniform3(-2.0..5.0f64),
        step in prop::array::uniform3(-0.3..0.3f64),
        snap in any::<[bool; 3]>(),
    ) {
        let g = grid([4, 3, 5], DVec3::new(0.5, 1.0, 0.25), DVec3::new(-1.0, 0.0, 1.0), &[0.2, 0.7]);
        let world_from_grid = DAffine3::from_rotation_x(0.5) * DAffine3::from_scale(DVec3::new(1.0, 2.0, 1.0));
        // Eyes in voxel index coordinates, some snapped onto grid planes.
        let a = DVec3::from(std::array::from_fn::<f64, 3, _>(|i| if snap[i] { a[i].round() } else { a[i] }));
        let b = a + DVec3::from(step);
        let to_world = |u: DVec3| world_from_grid.transform_point3(g.origin() + u * g.spacing());
        let (eye_a, eye_b) = (to_world(a), to_world(b));
        let key_a = nebel_lod::order_key(&g, &view(world_from_grid, eye_a, None)).unwrap();
        let key_b = nebel_lod::order_key(&g, &view(world_from_grid, eye_b, None)).unwrap();
        let transfer = linear_transfer();
        let batch_a = batch(&g, 2, world_from_grid, eye_a, None, &transfer, CellOrder::BackToFront);
        let batch_b = batch(&g, 2, world_from_grid, eye_b, None, &transfer, CellOrder::BackToFront);
        if key_a == key_b {
            prop_assert_eq!(batch_a, batch_b);
        }
    }
}

#[test]
fn order_key_changes_across_the_planes_between_tetrahedra_and_refuses_bad_input() {
    use nebel_lod::order_key;
    let g = grid([4, 4, 4], DVec3::ONE, DVec3::ZERO, &[0.5]);
    let key = |u: DVec3| order_key(&g, &view(DAffine3::IDENTITY, u, None)).unwrap();
    // Same voxel, opposite sides of the plane x = y between its tetrahedra.
    assert_ne!(
        key(DVec3::new(0.3, 0.4, 0.2)),
        key(DVec3::new(0.4, 0.3, 0.2))
    );
    assert_eq!(
        key(DVec3::new(0.4, 0.3, 0.2)),
        key(DVec3::new(0.45, 0.3, 0.2))
    );
    // On the plane is its own class; so is the plane x − y = 1 of the next
    // voxel along x.
    assert_ne!(
        key(DVec3::new(0.3, 0.3, 0.1)),
        key(DVec3::new(0.3, 0.29, 0.1))
    );
    assert_ne!(
        key(DVec3::new(1.3, 0.3, 0.1)),
        key(DVec3::new(1.3, 0.29, 0.1))
    );
    assert_ne!(
        key(DVec3::new(1.3, 0.3, 0.1)),
        key(DVec3::new(1.3, 0.31, 0.1))
    );
    // Far away everything is on one side: the key stops changing.
    assert_eq!(key(DVec3::splat(1e6)), key(DVec3::splat(1e300)));
    assert!(order_key(&g, &view(DAffine3::IDENTITY, DVec3::NAN, None)).is_none());
    let singular = view(DAffine3::from_scale(DVec3::ZERO), DVec3::ONE, None);
    assert!(order_key(&g, &singular).is_none());
}
