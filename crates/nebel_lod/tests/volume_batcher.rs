//! Properties of `VolumeBatcher`: every source kind builds exactly what the
//! crate's builders build for the same view, the batch is rebuilt exactly when
//! the view or the inputs change it (and kept otherwise), an empty viewport
//! sees nothing, lit clouds carry modulators, and bad input gives typed errors.

#[path = "support/rays.rs"]
mod rays;

use std::sync::Arc;

use glam::{DAffine3, DMat4, DQuat, DVec3, UVec2};
use nebel_core::cell::{Ray, Tetrahedron};
use nebel_core::field::{CloudLighting, DensityGrid, PadFill, light_field, search_light_cells};
use nebel_core::transfer::{ControlPoint, TransferFunction, TransferPreset};
use nebel_lod::octree::{
    CellScalars, LodCriterion, RefinementError, RefinementSettings, lod_batch_with, refine, refresh,
};
use nebel_lod::{
    BatchError, BatchLighting, BatchSettings, BrickTable, CellAdjacency, CellGrid, CellOrder,
    Cells, FrameInputs, Frustum, GridDrawing, HierarchyError, OctreeSettings, View,
    VolumeBatchError, VolumeBatcher, VolumeHierarchy, VolumeSource, full_resolution_batch,
    order_key, sorted_batch,
};

/// The render target of every view here, pixels.
const VIEWPORT: UVec2 = UVec2::new(640, 480);

/// The accuracy `c` of every frame here unless a test changes it.
const ACCURACY: f64 = 16.0;

/// A rough field in [0.05, 0.95] with an empty (density 0) column at low x
/// and y, spacing (0.5, 0.25, 0.5), origin off zero.
fn field(dims: [usize; 3], seed: u64) -> DensityGrid {
    let [nx, ny, nz] = dims;
    let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    let mut values = Vec::with_capacity(nx * ny * nz);
    for _ in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let noise = (state >> 40) as f32 / (1u64 << 24) as f32;
                let empty = i < nx / 3 && j < ny / 3;
                values.push(if empty { 0.0 } else { 0.05 + 0.9 * noise });
            }
        }
    }
    DensityGrid::new(
        dims,
        DVec3::new(0.5, 0.25, 0.5),
        DVec3::new(-2.0, 1.0, 0.5),
        values,
    )
    .expect("valid grid")
}

/// The test grid: 9 × 7 × 6 points, padded to 9 × 9 × 9 for the octree.
fn grid() -> DensityGrid {
    field([9, 7, 6], 3)
}

/// The volume's placement: stretched, turned and moved.
fn world_from_local() -> DAffine3 {
    DAffine3::from_scale_rotation_translation(
        DVec3::new(1.5, 1.0, 2.0),
        DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.7, 0.2),
        DVec3::new(1.0, 2.0, -3.0),
    )
}

/// The world position of the point `u` in the test grid's index coordinates.
fn eye_at(u: DVec3) -> DVec3 {
    let g = grid();
    world_from_local().transform_point3(g.origin() + u * g.spacing())
}

/// The view from `eye` (world units) of the volume placed by
/// [`world_from_local`], without culling.
fn view(eye: DVec3) -> View {
    View::new(world_from_local(), eye, VIEWPORT)
}

/// A narrow frustum from `eye` towards the point `target` (index
/// coordinates of the test grid), which sees part of the grid.
fn frustum(eye: DVec3, target: DVec3) -> Frustum {
    let camera = DMat4::look_at_rh(eye, eye_at(target), DVec3::Y);
    Frustum::from_view_projection(DMat4::perspective_infinite_reverse_rh(0.4, 1.0, 0.1) * camera)
        .expect("a valid projection")
}

/// A rough 33 × 17 × 33 field of `seed`, its source and octree settings.
fn rough_octree(seed: u64) -> (DensityGrid, VolumeSource, BatchSettings) {
    let grid = field([33, 17, 33], seed);
    let settings = BatchSettings {
        octree: Some(OctreeSettings::default()),
        ..BatchSettings::default()
    };
    (grid.clone(), VolumeSource::Grid(Arc::new(grid)), settings)
}

/// An eye inside the rough octree's grid or just outside it (index
/// coordinates) and a direction to move it in.
fn eye_and_direction(random: &mut impl FnMut() -> f64) -> (DVec3, DVec3) {
    let u = DVec3::new(
        random() * 40.0 - 4.0,
        random() * 20.0 - 2.0,
        random() * 40.0 - 4.0,
    );
    let direction = DVec3::new(random() - 0.5, random() - 0.5, random() - 0.5).normalize();
    (u, direction)
}

/// Uniform numbers in [0, 1) from `seed` (xorshift).
fn uniform(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn cloud() -> TransferFunction {
    TransferFunction::preset(TransferPreset::Cloud)
}

/// ρ = 0 everywhere.
fn clear() -> TransferFunction {
    TransferFunction::new([ControlPoint {
        s: 0.5,
        kappa: [1.0; 3],
        rho: 0.0,
    }])
    .expect("one control point")
}

/// The zero-opacity test of a lit cloud whose density is its opacity.
fn density_as_opacity() -> TransferFunction {
    let point = |s: f32| ControlPoint {
        s,
        kappa: [0.0; 3],
        rho: s,
    };
    TransferFunction::new([point(0.0), point(1.0)]).expect("two control points")
}

fn inputs(transfer: &TransferFunction) -> FrameInputs<'_> {
    FrameInputs {
        transfer,
        criterion: LodCriterion::distance(ACCURACY),
        blend: 0.0,
        blend_span: 0.0,
    }
}

/// A conforming cell mesh with scalars, in its own frame.
fn cells() -> Arc<Vec<Tetrahedron>> {
    let mut cells = search_light_cells(6.0, 0.35, [8, 2, 4]).unwrap();
    for (index, cell) in cells.iter_mut().enumerate() {
        cell.scalars = [0.2, 0.4, 0.6, 0.8].map(|s| (s + index as f64 * 0.01).fract());
    }
    Arc::new(cells)
}

fn grid_source() -> VolumeSource {
    VolumeSource::Grid(Arc::new(grid()))
}

fn settings(order: CellOrder, octree: bool) -> BatchSettings {
    BatchSettings {
        order,
        octree: octree.then(OctreeSettings::default),
        lighting: None,
        drawing: GridDrawing::ProjectedCells,
    }
}

fn lit(scalars: CellScalars) -> BatchSettings {
    BatchSettings {
        lighting: Some(BatchLighting {
            light: CloudLighting {
                shadow_extinction: 0.5,
                ..CloudLighting::default()
            },
            scalars,
        }),
        ..settings(CellOrder::BackToFront, true)
    }
}

/// A lit grid at full resolution, ray cast.
fn lit_ray_cast(scalars: CellScalars) -> BatchSettings {
    BatchSettings {
        octree: None,
        drawing: GridDrawing::RayCast,
        ..lit(scalars)
    }
}

/// Every kind of batcher, named: grids at full resolution and through the
/// octree, cell meshes, back to front and unordered.
fn every_kind() -> Vec<(&'static str, VolumeBatcher)> {
    let new = |source, settings| VolumeBatcher::new(source, &settings).expect("valid settings");
    vec![
        (
            "ray-cast grid",
            new(
                grid_source(),
                BatchSettings {
                    drawing: GridDrawing::RayCast,
                    ..settings(CellOrder::BackToFront, false)
                },
            ),
        ),
        (
            "sorted grid",
            new(grid_source(), settings(CellOrder::BackToFront, false)),
        ),
        (
            "unordered grid",
            new(grid_source(), settings(CellOrder::Unordered, false)),
        ),
        (
            "octree",
            new(grid_source(), settings(CellOrder::BackToFront, true)),
        ),
        (
            "lit octree",
            new(grid_source(), lit(CellScalars::LightModulatedByDensity)),
        ),
        (
            "lit ray-cast grid",
            new(
                grid_source(),
                lit_ray_cast(CellScalars::LightModulatedByDensity),
            ),
        ),
        (
            "sorted cells",
            new(
                VolumeSource::Cells(cells()),
                settings(CellOrder::BackToFront, false),
            ),
        ),
        (
            "unordered cells",
            new(
                VolumeSource::Cells(cells()),
                settings(CellOrder::Unordered, false),
            ),
        ),
    ]
}

/// The octree batch of the padded test grid for `view`, built by hand.
fn octree_batch(
    lighting: Option<&BatchLighting>,
    view: &View,
    transfer: &TransferFunction,
) -> Cells {
    let padded = grid()
        .padded_to_power_of_two_plus_one(PadFill::Value(0.0))
        .unwrap();
    let c = OctreeSettings::DEFAULT_MIN_ACCURACY;
    let (hierarchy, scalars) = match lighting {
        Some(lighting) => {
            let light = light_field(&padded, &lighting.light).unwrap();
            let hierarchy = VolumeHierarchy::with_light(&padded, &light, c).unwrap();
            (hierarchy, lighting.scalars)
        }
        None => (
            VolumeHierarchy::new(&padded, c).unwrap(),
            CellScalars::Density,
        ),
    };
    let opacity = match scalars {
        CellScalars::LightModulatedByDensity => density_as_opacity(),
        _ => transfer.clone(),
    };
    let settings = RefinementSettings::new(LodCriterion::distance(ACCURACY));
    // Culled, as the batcher culls, for the views the batch serves.
    let view = &View {
        frustum: refresh::culling(&hierarchy, view, refresh::Latency::default()),
        ..view.clone()
    };
    let refinement = refine(&hierarchy, view, &opacity, &settings).unwrap();
    lod_batch_with(&hierarchy, &refinement, view, scalars).unwrap()
}

#[test]
fn every_source_builds_what_its_builder_builds() {
    let grid = grid();
    let bricks = BrickTable::new(&grid, BrickTable::DEFAULT_BRICK_SIZE);
    let transfer = cloud();
    let eye = eye_at(DVec3::new(-6.0, 3.3, 2.6));
    let culled = view(eye).with_frustum(frustum(eye, DVec3::new(1.0, 1.0, 1.0)));
    let unculled = view(eye);

    // Full resolution, back to front: culled by the frustum.
    let mut sorted =
        VolumeBatcher::new(grid_source(), &settings(CellOrder::BackToFront, false)).unwrap();
    assert!(sorted.update(&culled, &inputs(&transfer)).unwrap());
    let expected =
        full_resolution_batch(&grid, &bricks, &culled, &transfer, CellOrder::BackToFront);
    assert_eq!(sorted.batch().as_ref(), &expected.unwrap());
    let all = full_resolution_batch(&grid, &bricks, &unculled, &transfer, CellOrder::BackToFront);
    let all = all.unwrap();
    assert!(!sorted.batch().is_empty() && sorted.batch().len() < all.len());
    assert_eq!(sorted.full_resolution_cells(), 6 * 8 * 6 * 5);
    assert!(sorted.is_view_dependent());
    assert_eq!(sorted.scalars(), CellScalars::Density);

    // Full resolution, unordered: not culled.
    let mut unordered =
        VolumeBatcher::new(grid_source(), &settings(CellOrder::Unordered, false)).unwrap();
    assert!(unordered.update(&culled, &inputs(&transfer)).unwrap());
    let expected =
        full_resolution_batch(&grid, &bricks, &unculled, &transfer, CellOrder::Unordered);
    assert_eq!(unordered.batch().as_ref(), &expected.unwrap());
    assert_eq!(unordered.batch().len(), all.len());

    // The octree, on the grid padded with zero density.
    let mut octree =
        VolumeBatcher::new(grid_source(), &settings(CellOrder::BackToFront, true)).unwrap();
    assert!(octree.update(&culled, &inputs(&transfer)).unwrap());
    assert_eq!(
        octree.batch().as_ref(),
        &octree_batch(None, &culled, &transfer)
    );
    assert!(!octree.batch().is_empty() && !octree.batch().is_modulated());
    assert_eq!(octree.full_resolution_cells(), 6 * 8 * 6 * 5);
    // Its Unordered setting changes nothing: the octree is back to front.
    let mut octree_unordered =
        VolumeBatcher::new(grid_source(), &settings(CellOrder::Unordered, true)).unwrap();
    octree_unordered
        .update(&culled, &inputs(&transfer))
        .unwrap();
    assert_eq!(octree_unordered.batch(), octree.batch());
    assert!(octree_unordered.is_view_dependent());

    // Cell meshes, in their own frame placed by world_from_local.
    let cells = cells();
    let mut sorted_cells = VolumeBatcher::new(
        VolumeSource::Cells(cells.clone()),
        &settings(CellOrder::BackToFront, false),
    )
    .unwrap();
    assert!(sorted_cells.update(&culled, &inputs(&transfer)).unwrap());
    let expected = sorted_batch(&cells, &CellAdjacency::new(&cells), &culled).unwrap();
    assert_eq!(sorted_cells.batch().as_ref(), &expected);
    assert_eq!(sorted_cells.batch().len(), cells.len());
    assert_eq!(sorted_cells.full_resolution_cells(), cells.len());
    let mut unordered_cells = VolumeBatcher::new(
        VolumeSource::Cells(cells.clone()),
        &settings(CellOrder::Unordered, false),
    )
    .unwrap();
    assert!(unordered_cells.update(&culled, &inputs(&transfer)).unwrap());
    let in_world: Vec<Tetrahedron> = cells
        .iter()
        .map(|t| Tetrahedron {
            positions: t.positions.map(|p| world_from_local().transform_point3(p)),
            scalars: t.scalars,
        })
        .collect();
    assert_eq!(
        unordered_cells.batch().as_ref(),
        &Cells::from_tetrahedra(&in_world)
    );
    assert_ne!(unordered_cells.batch(), sorted_cells.batch());
}

#[test]
fn lit_clouds_carry_modulators_and_pick_the_opacity_field() {
    let eye = eye_at(DVec3::new(4.2, 11.0, 3.1));
    let v = view(eye).with_frustum(frustum(eye, DVec3::new(4.0, 3.0, 2.5)));
    let transfer = cloud();
    for scalars in [
        CellScalars::LightModulatedByDensity,
        CellScalars::DensityModulatedByLight,
    ] {
        let settings = lit(scalars);
        let mut batcher = VolumeBatcher::new(grid_source(), &settings).unwrap();
        assert_eq!(batcher.scalars(), scalars);
        assert_eq!(batcher.settings(), &settings);
        assert!(batcher.update(&v, &inputs(&transfer)).unwrap());
        let batch = batcher.batch();
        assert!(!batch.is_empty());
        assert_eq!(batch.modulators.len(), batch.len());
        assert!(
            batch
                .modulators
                .iter()
                .flatten()
                .all(|m| (0.0..=1.0).contains(m))
        );
        let lighting = settings.lighting.as_ref();
        assert_eq!(batch.as_ref(), &octree_batch(lighting, &v, &transfer));

        // The volume's transfer function is over the light for §5.1, so it
        // does not cull: a transparent one still draws the cloud there.
        let mut batcher = VolumeBatcher::new(grid_source(), &settings).unwrap();
        batcher.update(&v, &inputs(&clear())).unwrap();
        let light_over_density = scalars == CellScalars::LightModulatedByDensity;
        assert_eq!(
            !batcher.batch().is_empty(),
            light_over_density,
            "{scalars:?}"
        );
    }
}

#[test]
fn a_lit_ray_cast_grid_carries_the_light_field_at_its_points() {
    let v = view(eye_at(DVec3::new(4.2, 11.0, 3.1)));
    // The test grid without density in its first brick along x (points
    // x ≤ 4).
    let density = {
        let grid = grid();
        let values = grid
            .values()
            .iter()
            .enumerate()
            .map(|(n, &value)| if n % 9 <= 4 { 0.0 } else { value })
            .collect();
        Arc::new(DensityGrid::new(grid.dims(), grid.spacing(), grid.origin(), values).unwrap())
    };
    for scalars in [
        CellScalars::LightModulatedByDensity,
        CellScalars::DensityModulatedByLight,
    ] {
        let settings = lit_ray_cast(scalars);
        let mut batcher =
            VolumeBatcher::new(VolumeSource::Grid(density.clone()), &settings).unwrap();
        assert_eq!(batcher.scalars(), scalars);
        assert!(!batcher.is_view_dependent());
        assert!(batcher.update(&v, &inputs(&cloud())).unwrap());
        let batch = batcher.batch();
        assert!(batch.is_modulated() && batch.modulators.is_empty());
        assert_eq!(batch.len(), batcher.full_resolution_cells());
        let cell_grid = batch.grid.as_ref().expect("a ray-cast grid");
        // The light field of the grid as given, unpadded.
        let light = light_field(&density, &settings.lighting.unwrap().light).unwrap();
        let (scalar, modulator) = match scalars {
            CellScalars::LightModulatedByDensity => (&light, density.as_ref()),
            _ => (density.as_ref(), &light),
        };
        assert_eq!(cell_grid.grid(), scalar);
        assert_eq!(cell_grid.modulators(), Some(modulator));
        // The bricks are tested on the density: over the modulator for
        // §5.1, the transfer function's scalar for §5.2.
        let light_over_density = scalars == CellScalars::LightModulatedByDensity;
        assert_eq!(cell_grid.clears_modulators(), light_over_density);
        let bricks = BrickTable::new(&density, BrickTable::DEFAULT_BRICK_SIZE);
        let placed = CellGrid::new(Arc::new(scalar.clone()), world_from_local())
            .unwrap()
            .with_modulators(Arc::new(modulator.clone()))
            .unwrap();
        let expected = if light_over_density {
            placed.with_modulator_occupancy(&bricks)
        } else {
            placed.with_occupancy(&bricks, &cloud())
        }
        .unwrap();
        assert_eq!(cell_grid.as_ref(), &expected);
        // Its first bricks along x are empty.
        assert!(cell_grid.occupied().contains(&0) && cell_grid.occupied().contains(&1));
        // The eye moving keeps the batch.
        assert!(
            !batcher
                .update(&view(eye_at(DVec3::new(-7.0, 2.0, 1.0))), &inputs(&cloud()))
                .unwrap()
        );
        // A transparent transfer function empties only the batch whose
        // opacity it gives (§5.2).
        let mut batcher =
            VolumeBatcher::new(VolumeSource::Grid(density.clone()), &settings).unwrap();
        batcher.update(&v, &inputs(&clear())).unwrap();
        assert_eq!(!batcher.batch().is_empty(), light_over_density);
    }
}

#[test]
fn a_transparent_volume_gives_an_empty_batch() {
    let zeros = DensityGrid::new([5, 6, 7], DVec3::ONE, DVec3::ZERO, vec![0.0; 5 * 6 * 7]).unwrap();
    let v = view(eye_at(DVec3::splat(-3.0)));
    for settings in [
        settings(CellOrder::BackToFront, false),
        settings(CellOrder::Unordered, false),
        settings(CellOrder::BackToFront, true),
        lit(CellScalars::LightModulatedByDensity),
        lit_ray_cast(CellScalars::LightModulatedByDensity),
    ] {
        let mut batcher =
            VolumeBatcher::new(VolumeSource::Grid(Arc::new(zeros.clone())), &settings).unwrap();
        assert!(batcher.update(&v, &inputs(&cloud())).unwrap());
        assert!(batcher.batch().is_empty(), "{settings:?}");
        // A transparent transfer function empties any grid but the lit one
        // whose opacity is the density.
        let mut batcher = VolumeBatcher::new(grid_source(), &settings).unwrap();
        assert!(batcher.update(&v, &inputs(&clear())).unwrap());
        assert_eq!(
            batcher.batch().is_empty(),
            settings.lighting.is_none(),
            "{settings:?}"
        );
    }
}

#[test]
fn a_sorted_grid_is_rebuilt_when_its_order_key_or_frustum_changes() {
    let grid = grid();
    let bricks = BrickTable::new(&grid, BrickTable::DEFAULT_BRICK_SIZE);
    let transfer = cloud();
    let fresh = |v: &View| {
        full_resolution_batch(&grid, &bricks, v, &transfer, CellOrder::BackToFront).unwrap()
    };
    let mut batcher =
        VolumeBatcher::new(grid_source(), &settings(CellOrder::BackToFront, false)).unwrap();
    let u = DVec3::new(3.3, 2.45, 1.7);
    let v0 = view(eye_at(u));
    assert!(batcher.update(&v0, &inputs(&transfer)).unwrap());
    assert!(!batcher.update(&v0, &inputs(&transfer)).unwrap());

    // A move that stays on the same side of every plane: the same batch.
    let v1 = view(eye_at(u + DVec3::new(0.01, -0.01, 0.005)));
    assert_ne!(v0.eye, v1.eye);
    assert_eq!(order_key(&grid, &v0), order_key(&grid, &v1));
    assert!(!batcher.update(&v1, &inputs(&transfer)).unwrap());
    assert_eq!(batcher.batch().as_ref(), &fresh(&v1));

    // Across a voxel's corner face (x + y + z = 8 in index units).
    let v2 = view(eye_at(u + DVec3::new(0.3, 0.3, 0.3)));
    assert_ne!(order_key(&grid, &v1), order_key(&grid, &v2));
    assert!(batcher.update(&v2, &inputs(&transfer)).unwrap());
    assert_eq!(batcher.batch().as_ref(), &fresh(&v2));
    assert_ne!(batcher.batch().as_ref(), &fresh(&v1));

    // Far away every plane is on one side: moving farther keeps the batch.
    let far = view(eye_at(DVec3::new(-1e4, 3.0, 2.0)));
    assert!(batcher.update(&far, &inputs(&transfer)).unwrap());
    let farther = view(eye_at(DVec3::new(-1e6, 3.5, 2.5)));
    assert!(!batcher.update(&farther, &inputs(&transfer)).unwrap());

    // The frustum culls bricks: a new one rebuilds, the same one does not.
    let culled = v2
        .clone()
        .with_frustum(frustum(v2.eye, DVec3::new(8.0, 6.0, 5.0)));
    assert!(batcher.update(&culled, &inputs(&transfer)).unwrap());
    assert_eq!(batcher.batch().as_ref(), &fresh(&culled));
    assert!(!batcher.update(&culled, &inputs(&transfer)).unwrap());
    assert!(batcher.update(&v2, &inputs(&transfer)).unwrap());
    assert_eq!(batcher.batch().as_ref(), &fresh(&v2));
}

#[test]
fn the_octree_is_refined_again_after_half_a_voxel_or_a_turn_of_3_degrees() {
    let transfer = cloud();
    let mut batcher =
        VolumeBatcher::new(grid_source(), &settings(CellOrder::BackToFront, true)).unwrap();
    let g = grid();
    // A step of `voxels` along the grid's index axes from index point `u`.
    let at = |u: DVec3, voxels: DVec3| eye_at(u + voxels);
    let u = DVec3::new(3.3, 2.45, 1.7);
    let v0 = view(at(u, DVec3::ZERO));
    assert!(batcher.update(&v0, &inputs(&transfer)).unwrap());
    assert!(!batcher.update(&v0, &inputs(&transfer)).unwrap());
    // Within half a voxel (index units: the spacing is not cubic) the batch
    // serves; beyond it the octree refines again.
    for (step, rebuilds) in [
        (DVec3::new(1e-9, 0.0, 0.0), false),
        (DVec3::new(0.0, 0.49, 0.0), false),
        (DVec3::new(0.3, 0.0, -0.39), false),
        (DVec3::new(0.0, 0.0, 0.51), true),
    ] {
        let moved = view(at(u, step));
        assert_eq!(
            batcher.update(&moved, &inputs(&transfer)).unwrap(),
            rebuilds,
            "{step}"
        );
        if rebuilds {
            assert_eq!(
                batcher.batch().as_ref(),
                &octree_batch(None, &moved, &transfer)
            );
        }
    }
    assert!(batcher.update(&v0, &inputs(&transfer)).unwrap());
    assert!(g.spacing().x != g.spacing().y);

    // Culled by a camera: a new frustum refines, and so does a turn of more
    // than 3° or a zoom; a turn of less does not.
    let camera = |eye: DVec3, yaw: f64, fov: f64| {
        let forward = (eye_at(DVec3::new(8.0, 6.0, 5.0)) - eye).normalize();
        let turned = DQuat::from_rotation_y(yaw.to_radians()) * forward;
        let clip_from_world = DMat4::perspective_infinite_reverse_rh(fov, 1.0, 0.1)
            * DMat4::look_to_rh(eye, turned, DVec3::Y);
        view(eye).with_frustum(Frustum::from_view_projection(clip_from_world).unwrap())
    };
    let culled = camera(v0.eye, 0.0, 0.4);
    assert!(batcher.update(&culled, &inputs(&transfer)).unwrap());
    assert!(!batcher.update(&culled, &inputs(&transfer)).unwrap());
    assert_eq!(
        batcher.batch().as_ref(),
        &octree_batch(None, &culled, &transfer)
    );
    for (yaw, fov, rebuilds) in [
        (2.9, 0.4, false),
        (-2.9, 0.4, false),
        (3.2, 0.4, true),
        (0.0, 0.38, true),
    ] {
        let turned = camera(v0.eye, yaw, fov);
        let rebuilt = batcher.update(&turned, &inputs(&transfer)).unwrap();
        assert_eq!(rebuilt, rebuilds, "{yaw}° {fov}");
        // Back to the first camera for the next case.
        if rebuilt {
            assert!(batcher.update(&culled, &inputs(&transfer)).unwrap());
        }
    }
    assert!(batcher.update(&v0, &inputs(&transfer)).unwrap());

    // The accuracy c sets the level of detail.
    let finer = FrameInputs {
        criterion: LodCriterion::distance(64.0),
        ..inputs(&transfer)
    };
    assert!(batcher.update(&culled, &finer).unwrap());
    assert!(!batcher.update(&culled, &finer).unwrap());
    assert!(batcher.update(&culled, &inputs(&transfer)).unwrap());
    assert!(batcher.is_view_dependent());
}

#[test]
fn unordered_batches_ignore_the_eye_and_the_frustum() {
    let transfer = cloud();
    for source in [grid_source(), VolumeSource::Cells(cells())] {
        let mut batcher =
            VolumeBatcher::new(source, &settings(CellOrder::Unordered, false)).unwrap();
        assert!(!batcher.is_view_dependent());
        let v0 = view(eye_at(DVec3::new(-5.0, 2.0, 1.0)));
        assert!(batcher.update(&v0, &inputs(&transfer)).unwrap());
        let first = batcher.batch().clone();
        for eye in [DVec3::new(40.0, -3.0, 7.0), DVec3::ZERO, DVec3::NAN] {
            let moved = View { eye, ..v0.clone() }.with_frustum(frustum(
                DVec3::new(40.0, -3.0, 7.0),
                DVec3::new(8.0, 6.0, 5.0),
            ));
            assert!(!batcher.update(&moved, &inputs(&transfer)).unwrap());
        }
        // Without the octree the accuracy is not read.
        let other_accuracy = FrameInputs {
            criterion: LodCriterion::distance(f64::NAN),
            ..inputs(&transfer)
        };
        assert!(!batcher.update(&v0, &other_accuracy).unwrap());
        assert_eq!(batcher.batch(), &first);
    }
}

#[test]
fn a_ray_cast_grid_is_the_whole_grid_built_once_for_its_placement() {
    let transfer = cloud();
    for mode in [CellOrder::BackToFront, CellOrder::Unordered] {
        let mut batcher = VolumeBatcher::new(
            grid_source(),
            &BatchSettings {
                order: mode,
                ..BatchSettings::default()
            },
        )
        .unwrap();
        assert!(!batcher.is_view_dependent());
        let v0 = view(eye_at(DVec3::new(-5.0, 2.0, 1.0)));
        assert!(batcher.update(&v0, &inputs(&transfer)).unwrap());
        let batch = batcher.batch().clone();
        let drawn = batch.grid.as_ref().expect("a whole grid");
        assert!(batch.tetrahedra.is_empty());
        assert_eq!(batch.len(), 6 * 8 * 6 * 5);
        assert_eq!(drawn.grid(), &grid());
        let corner = world_from_local().transform_point3(grid().max_corner());
        let mapped = drawn
            .world_from_index()
            .transform_point3(DVec3::new(8.0, 6.0, 5.0));
        assert!((mapped - corner).length() < 1e-9);
        assert!(batch.bounds_min.cmple(corner.as_vec3()).all());
        assert!(batch.bounds_max.cmpge(corner.as_vec3()).all());
        // No eye, frustum or accuracy builds it again.
        for eye in [
            DVec3::new(40.0, -3.0, 7.0),
            eye_at(DVec3::splat(2.5)),
            DVec3::NAN,
        ] {
            let moved = View { eye, ..v0.clone() }.with_frustum(frustum(
                DVec3::new(40.0, -3.0, 7.0),
                DVec3::new(8.0, 6.0, 5.0),
            ));
            assert!(!batcher.update(&moved, &inputs(&transfer)).unwrap());
        }
        assert_eq!(batcher.batch(), &batch);
        // A transfer function transparent over the grid's values draws nothing.
        assert!(batcher.update(&v0, &inputs(&clear())).unwrap());
        assert!(batcher.batch().is_empty());
    }
}

#[test]
fn sorted_cells_are_rebuilt_when_the_eye_moves() {
    let cells = cells();
    let adjacency = CellAdjacency::new(&cells);
    let transfer = cloud();
    let mut batcher = VolumeBatcher::new(
        VolumeSource::Cells(cells.clone()),
        &settings(CellOrder::BackToFront, false),
    )
    .unwrap();
    assert!(batcher.is_view_dependent());
    let v0 = view(DVec3::new(3.0, -1.0, 2.0));
    assert!(batcher.update(&v0, &inputs(&transfer)).unwrap());
    // Cells are not culled: a frustum changes nothing.
    let culled = v0.clone().with_frustum(frustum(v0.eye, DVec3::ZERO));
    assert!(!batcher.update(&culled, &inputs(&transfer)).unwrap());
    let moved = view(DVec3::new(-4.0, 2.0, -1.0));
    assert!(batcher.update(&moved, &inputs(&transfer)).unwrap());
    assert_eq!(
        batcher.batch().as_ref(),
        &sorted_batch(&cells, &adjacency, &moved).unwrap()
    );
    assert!(!batcher.update(&moved, &inputs(&transfer)).unwrap());
}

#[test]
fn every_kind_is_rebuilt_for_a_new_placement_or_transfer_function() {
    let transfer = cloud();
    let v0 = view(eye_at(DVec3::new(-5.0, 2.0, 1.0)));
    for (name, mut batcher) in every_kind() {
        assert!(batcher.update(&v0, &inputs(&transfer)).unwrap(), "{name}");
        // Another instance with the same content is the same function.
        let same = cloud();
        assert!(!batcher.update(&v0, &inputs(&same)).unwrap(), "{name}");
        let fog = TransferFunction::preset(TransferPreset::GroundFog);
        assert!(batcher.update(&v0, &inputs(&fog)).unwrap(), "{name}");
        assert!(!batcher.update(&v0, &inputs(&fog)).unwrap(), "{name}");

        // The volume moved, the eye stayed.
        let before = batcher.batch().clone();
        let moved = View {
            world_from_local: DAffine3::from_translation(DVec3::new(0.5, 0.0, -0.25))
                * world_from_local(),
            ..v0.clone()
        };
        assert!(batcher.update(&moved, &inputs(&fog)).unwrap(), "{name}");
        assert_ne!(batcher.batch(), &before, "{name}");
        assert!(!batcher.update(&moved, &inputs(&fog)).unwrap(), "{name}");

        // Only the octree reads the accuracy.
        let finer = FrameInputs {
            criterion: LodCriterion::distance(64.0),
            ..inputs(&fog)
        };
        let octree = batcher.settings().octree.is_some();
        assert_eq!(batcher.update(&moved, &finer).unwrap(), octree, "{name}");
    }
}

#[test]
fn an_empty_viewport_gives_an_empty_batch() {
    let transfer = cloud();
    let v0 = view(eye_at(DVec3::new(-5.0, 2.0, 1.0)));
    let hidden = View {
        viewport: UVec2::new(640, 0),
        ..v0.clone()
    };
    for (name, mut batcher) in every_kind() {
        assert!(
            batcher.update(&hidden, &inputs(&transfer)).unwrap(),
            "{name}"
        );
        assert_eq!(batcher.batch().as_ref(), &Cells::default(), "{name}");
        // Hidden it stays empty, whatever moves.
        let elsewhere = View {
            eye: DVec3::new(9.0, 9.0, 9.0),
            viewport: UVec2::new(0, 480),
            world_from_local: DAffine3::from_translation(DVec3::X) * world_from_local(),
            ..hidden.clone()
        };
        assert!(
            !batcher.update(&elsewhere, &inputs(&transfer)).unwrap(),
            "{name}"
        );
        assert!(batcher.batch().is_empty(), "{name}");
        // Shown again it draws, hidden again it empties.
        assert!(batcher.update(&v0, &inputs(&transfer)).unwrap(), "{name}");
        assert!(!batcher.batch().is_empty(), "{name}");
        assert!(
            batcher.update(&hidden, &inputs(&transfer)).unwrap(),
            "{name}"
        );
        assert!(batcher.batch().is_empty(), "{name}");
    }
}

#[test]
fn bad_views_and_inputs_give_typed_errors_and_keep_the_last_batch() {
    let transfer = cloud();
    let v0 = view(eye_at(DVec3::new(-5.0, 2.0, 1.0)));
    let nan_eye = View {
        eye: DVec3::new(0.0, f64::NAN, 0.0),
        ..v0.clone()
    };
    let singular = View {
        world_from_local: DAffine3::from_scale(DVec3::new(1.0, 0.0, 1.0)),
        ..v0.clone()
    };
    for (name, mut batcher) in every_kind() {
        assert!(batcher.update(&v0, &inputs(&transfer)).unwrap(), "{name}");
        let good = batcher.batch().clone();
        let octree = batcher.settings().octree.is_some();
        let ordered = batcher.is_view_dependent();

        let result = batcher.update(&nan_eye, &inputs(&transfer));
        match result {
            Err(VolumeBatchError::Batch(BatchError::NonFiniteEye { .. })) => {
                assert!(ordered && !octree, "{name}");
            }
            Err(VolumeBatchError::Refinement(RefinementError::NonFiniteEye { .. })) => {
                assert!(octree, "{name}");
            }
            Ok(changed) => assert!(!ordered && !changed, "{name}"),
            Err(other) => panic!("{name}: {other}"),
        }

        let error = batcher.update(&singular, &inputs(&transfer)).unwrap_err();
        let expected_kind = match &error {
            VolumeBatchError::Batch(BatchError::SingularTransform { .. }) => !octree,
            VolumeBatchError::Refinement(RefinementError::SingularTransform { .. }) => octree,
            _ => false,
        };
        assert!(expected_kind, "{name}: {error}");
        assert!(error.to_string().contains("world_from_local"), "{error}");

        // The errors left the batch and what it was built for alone.
        assert_eq!(batcher.batch(), &good, "{name}");
        assert!(!batcher.update(&v0, &inputs(&transfer)).unwrap(), "{name}");

        if octree {
            for accuracy in [f64::NAN, -1.0] {
                let bad = FrameInputs {
                    criterion: LodCriterion::distance(accuracy),
                    ..inputs(&transfer)
                };
                let error = batcher.update(&v0, &bad).unwrap_err();
                assert!(
                    matches!(
                        error,
                        VolumeBatchError::Refinement(RefinementError::InvalidAccuracy { .. })
                    ),
                    "{name}: {error}"
                );
            }
        }
    }
}

#[test]
fn bad_settings_give_typed_errors() {
    let new = |source, settings: BatchSettings| VolumeBatcher::new(source, &settings).err();
    for min_accuracy in [3f64.sqrt(), 1.0, f64::NAN, f64::INFINITY] {
        let settings = BatchSettings {
            octree: Some(OctreeSettings { min_accuracy }),
            ..BatchSettings::default()
        };
        let error = new(grid_source(), settings).unwrap();
        assert!(
            matches!(
                error,
                VolumeBatchError::Hierarchy(HierarchyError::InvalidMinAccuracy { .. })
            ),
            "{error}"
        );
    }
    let lit_without_octree = BatchSettings {
        octree: None,
        drawing: GridDrawing::ProjectedCells,
        ..lit(CellScalars::LightModulatedByDensity)
    };
    assert_eq!(
        new(grid_source(), lit_without_octree),
        Some(VolumeBatchError::LightingWithoutOctree)
    );
    assert_eq!(
        new(grid_source(), lit(CellScalars::Density)),
        Some(VolumeBatchError::UnlitScalars)
    );
    assert_eq!(
        new(
            VolumeSource::Cells(cells()),
            settings(CellOrder::BackToFront, true)
        ),
        Some(VolumeBatchError::OctreeWithoutGrid)
    );

    // Invalid light-field settings: a shared FieldError, equal by message.
    let mut bright = lit(CellScalars::DensityModulatedByLight);
    if let Some(lighting) = &mut bright.lighting {
        lighting.light.ambient = 2.0;
    }
    let error = new(grid_source(), bright).unwrap();
    assert!(matches!(error, VolumeBatchError::Field(_)), "{error}");
    assert!(error.to_string().contains("ambient"), "{error}");
    let again = new(grid_source(), bright).unwrap();
    assert_eq!(error.clone(), again);
    assert_ne!(error, VolumeBatchError::UnlitScalars);
}

#[test]
fn grids_of_any_size_go_through_the_octree() {
    let transfer = cloud();
    for dims in [[2, 2, 2], [6, 5, 7], [17, 3, 4]] {
        let grid = field(dims, 9);
        let voxels: usize = dims.iter().map(|n| n - 1).product();
        let mut batcher = VolumeBatcher::new(
            VolumeSource::Grid(Arc::new(grid)),
            &settings(CellOrder::BackToFront, true),
        )
        .unwrap();
        assert_eq!(batcher.full_resolution_cells(), 6 * voxels);
        assert!(
            batcher
                .update(&view(DVec3::new(-9.0, 4.0, 3.0)), &inputs(&transfer))
                .unwrap()
        );
        assert!(!batcher.batch().is_empty(), "{dims:?}");
    }
}

#[test]
fn a_batcher_built_on_a_worker_thread_is_handed_over() {
    fn send_and_sync<T: Send + Sync>() {}
    send_and_sync::<VolumeBatcher>();
    send_and_sync::<VolumeBatchError>();
    let worker = std::thread::spawn(|| {
        VolumeBatcher::new(grid_source(), &lit(CellScalars::LightModulatedByDensity))
    });
    let mut batcher = worker.join().expect("the worker ran").unwrap();
    let transfer = cloud();
    assert!(
        batcher
            .update(&view(eye_at(DVec3::splat(-4.0))), &inputs(&transfer))
            .unwrap()
    );
    assert!(batcher.batch().is_modulated());
}

#[test]
fn a_full_resolution_batch_beyond_the_memory_budget_is_refused_before_it_is_built() {
    // 1025 × 1025 × 513 points: the grid is a zero page mapping, its batch
    // would be 1024 · 1024 · 512 · 5 cells of 64 bytes = 172 GB.
    let dims = [1025, 1025, 513];
    let grid = DensityGrid::new(
        dims,
        DVec3::ONE,
        DVec3::ZERO,
        vec![0.0; dims.iter().product()],
    )
    .unwrap();
    let error = VolumeBatcher::new(
        VolumeSource::Grid(Arc::new(grid)),
        &settings(CellOrder::BackToFront, false),
    )
    .unwrap_err();
    assert!(matches!(error, VolumeBatchError::OverBudget(_)), "{error}");
    let message = error.to_string();
    assert!(
        message.contains("full-resolution batch of 1024 × 1024 × 512 voxels")
            && message.contains("memory budget")
            && message.contains("octree"),
        "{message}"
    );
}

/// Two keyframes of the lit grid under a moving sun: the first one's
/// settings, and a batcher for each sun.
fn sun_keyframes() -> (BatchSettings, VolumeBatcher, VolumeBatcher) {
    let first_sun = lit(CellScalars::LightModulatedByDensity);
    let mut later = first_sun;
    if let Some(lighting) = &mut later.lighting {
        lighting.light.sun_direction = DVec3::new(-0.8, 0.3, 0.1);
    }
    let first = VolumeBatcher::new(grid_source(), &first_sun).unwrap();
    let second = VolumeBatcher::new(grid_source(), &later).unwrap();
    (first_sun, first, second)
}

/// Keyframes of a moving sun: the pair's batch carries the second sun's light
/// beside the first's, over cells refined for both; kinds without the octree
/// and different scalars are refused.
#[test]
fn a_batcher_blends_toward_the_next_keyframe() {
    let eye = eye_at(DVec3::new(4.2, 11.0, 3.1));
    let v = view(eye).with_frustum(frustum(eye, DVec3::new(4.0, 3.0, 2.5)));
    let transfer = cloud();
    let (first_sun, first, second) = sun_keyframes();
    let mut pair = first.with_next_keyframe(&second).unwrap();
    assert_eq!(pair.settings(), &first_sun);
    // Refined for the whole interval: the batch ends at the second sun.
    let whole = FrameInputs {
        blend_span: 1.0,
        ..inputs(&transfer)
    };
    assert!(pair.update(&v, &whole).unwrap());
    let batch = pair.batch();
    assert!(batch.is_blended() && !batch.is_empty());
    assert_eq!(batch.blends, [0.0, 1.0]);
    assert_eq!(batch.next_scalars.len(), batch.len());
    // Same density in both: the modulators agree, the light differs.
    assert_eq!(batch.next_modulators, batch.modulators);
    let scalars: Vec<[f32; 4]> = batch
        .tetrahedra
        .iter()
        .map(|c| c.vertices.map(|v| v[3]))
        .collect();
    assert_ne!(batch.next_scalars, scalars, "the sun moved");
    assert!(!pair.update(&v, &whole).unwrap(), "nothing changed");

    let sorted = VolumeBatcher::new(grid_source(), &settings(CellOrder::BackToFront, false));
    let unlit = VolumeBatcher::new(grid_source(), &settings(CellOrder::BackToFront, true));
    let non_physical =
        VolumeBatcher::new(grid_source(), &lit(CellScalars::DensityModulatedByLight));
    for other in [sorted, unlit, non_physical] {
        let other = other.unwrap();
        assert_eq!(
            first.with_next_keyframe(&other).unwrap_err(),
            VolumeBatchError::MismatchedKeyframes
        );
    }
}

/// Keyframes of a moving sun, ray cast: the pair's grid carries both
/// keyframes' fields and serves the whole interval, and is not rebuilt
/// for a new blend or eye; a ray-cast keyframe and an octree one are
/// refused.
#[test]
fn a_ray_cast_pair_carries_both_keyframes() {
    let transfer = cloud();
    let (first_sun, octree_first, _) = sun_keyframes();
    let mut later = lit_ray_cast(CellScalars::LightModulatedByDensity);
    if let Some(lighting) = &mut later.lighting {
        lighting.light.sun_direction = DVec3::new(-0.8, 0.3, 0.1);
    }
    let settings = BatchSettings {
        octree: None,
        drawing: GridDrawing::RayCast,
        ..first_sun
    };
    let first = VolumeBatcher::new(grid_source(), &settings).unwrap();
    let second = VolumeBatcher::new(grid_source(), &later).unwrap();
    let mut pair = first.with_next_keyframe(&second).unwrap();
    assert!(!pair.is_view_dependent());
    let v = view(eye_at(DVec3::new(4.2, 11.0, 3.1)));
    assert!(pair.update(&v, &inputs(&transfer)).unwrap());
    let batch = pair.batch().clone();
    assert!(batch.is_blended() && batch.is_modulated() && !batch.is_empty());
    assert_eq!(batch.blends, [0.0, 1.0]);
    assert_eq!(batch.mix_factor(0.3), 0.3);
    let cell_grid = batch.grid.as_ref().expect("a ray-cast grid");
    let light =
        |settings: &BatchSettings| light_field(&grid(), &settings.lighting.unwrap().light).unwrap();
    let (next_light, next_density) = cell_grid.next_keyframe().expect("blended");
    assert_eq!(cell_grid.grid(), &light(&settings));
    assert_eq!(next_light, &light(&later));
    assert_eq!(next_density, cell_grid.modulators());
    assert_ne!(next_light, cell_grid.grid(), "the sun moved");
    let moved = FrameInputs {
        blend: 0.6,
        blend_span: 0.1,
        ..inputs(&transfer)
    };
    assert!(
        !pair
            .update(&view(eye_at(DVec3::new(-6.0, 2.0, 1.0))), &moved)
            .unwrap()
    );
    for (a, b) in [(&first, &octree_first), (&octree_first, &first)] {
        assert_eq!(
            a.with_next_keyframe(b).unwrap_err(),
            VolumeBatchError::MismatchedKeyframes
        );
    }
    // A pair is not a keyframe of another pair.
    assert_eq!(
        pair.with_next_keyframe(&second).unwrap_err(),
        VolumeBatchError::MismatchedKeyframes
    );
}

/// A refinement step can be built detached and adopted: the same batch
/// `update` builds, for a new blend, a new span and a moved camera; a batch
/// already current, a single keyframe's new blend and other batchers' steps
/// give none or are ignored.
#[test]
fn a_refinement_step_builds_detached_what_update_builds() {
    let eye = eye_at(DVec3::new(4.2, 11.0, 3.1));
    let v = view(eye).with_frustum(frustum(eye, DVec3::new(4.0, 3.0, 2.5)));
    let transfer = cloud();
    let (first_sun, first, second) = sun_keyframes();
    let mut detached = first.with_next_keyframe(&second).unwrap();
    let mut inline = first.with_next_keyframe(&second).unwrap();
    let at = |blend: f32| FrameInputs {
        blend,
        ..inputs(&transfer)
    };
    // The first build, made ahead, is the first update's.
    assert!(
        detached.refinement_step(&v, &at(0.0)).is_some(),
        "not built yet"
    );
    let first = detached.first_build(&v, &at(0.0)).expect("not built yet");
    assert!(detached.adopt(first.build()).unwrap());
    assert!(detached.first_build(&v, &at(0.0)).is_none(), "built");
    assert!(!detached.update(&v, &at(0.0)).unwrap(), "adopted as built");
    inline.update(&v, &at(0.0)).unwrap();
    assert!(
        detached.refinement_step(&v, &at(0.0)).is_none(),
        "nothing changed"
    );
    let step = detached.refinement_step(&v, &at(0.5)).expect("a new blend");
    assert!(detached.adopt(step.build()).unwrap());
    assert!(inline.update(&v, &at(0.5)).unwrap());
    assert_eq!(detached.batch(), inline.batch());
    assert!(!detached.update(&v, &at(0.5)).unwrap(), "adopted as built");
    // A new span of blends is a step too.
    let spanned = FrameInputs {
        blend_span: 0.25,
        ..at(0.5)
    };
    let step = detached.refinement_step(&v, &spanned).expect("a new span");
    assert!(detached.adopt(step.build()).unwrap());
    assert!(!detached.update(&v, &spanned).unwrap(), "adopted as built");
    // So is a moved camera: made for the old inputs from the new eye.
    let moved_eye = eye_at(DVec3::new(5.0, 10.0, 2.0));
    let moved = view(moved_eye).with_frustum(frustum(moved_eye, DVec3::new(4.0, 3.0, 2.5)));
    let step = detached
        .refinement_step(&moved, &spanned)
        .expect("the camera moved");
    let built = step.build();
    assert!(built.is_for_inputs(&spanned) && !built.is_for(&v, &spanned));
    assert!(!built.is_for_inputs(&at(0.75)));
    assert!(detached.adopt(built).unwrap());
    assert!(inline.update(&moved, &spanned).unwrap());
    assert_eq!(detached.batch(), inline.batch());
    assert!(
        !detached.update(&moved, &spanned).unwrap(),
        "adopted as built"
    );
    // A step of another batcher is not taken; a single keyframe's batch
    // does not depend on the blend.
    let other = inline.refinement_step(&v, &at(0.75)).unwrap();
    assert!(!detached.adopt(other.build()).unwrap());
    let mut single = VolumeBatcher::new(grid_source(), &first_sun).unwrap();
    assert!(single.first_build(&v, &at(0.0)).is_none());
    single.update(&v, &at(0.0)).unwrap();
    assert!(single.refinement_step(&v, &at(0.5)).is_none());
    assert!(single.refinement_step(&moved, &at(0.0)).is_some());
}

/// A batch serves the camera until the eye moved half a voxel
/// (`refresh::REFRESH_DISTANCE`): seen from there, against a batch refined
/// for that eye, it composites some rays out of order and carries the morph
/// of another distance. Both together change what the camera sees by less
/// than half an 8-bit step, for the distance and the screen-error criterion.
#[test]
fn an_octree_batch_kept_for_half_a_voxel_costs_little_of_the_image() {
    let (grid, source, settings) = rough_octree(11);
    let transfer = cloud();
    let at = |u: DVec3| world_from_local().transform_point3(grid.origin() + u * grid.spacing());
    let mut random = uniform(0x0c7e_u64);
    let centre = at(DVec3::new(16.0, 8.0, 16.0));
    for criterion in [LodCriterion::distance(ACCURACY), LodCriterion::default()] {
        for step in [0.5 * refresh::REFRESH_DISTANCE, refresh::REFRESH_DISTANCE] {
            let mut cost = rays::OrderCost::default();
            for _ in 0..4 {
                let (u, direction) = eye_and_direction(&mut random);
                let moved = u + direction * step;
                // A camera looking at the grid's centre, for the screen error.
                let seen_from = |u: DVec3| {
                    let eye = at(u);
                    let clip_from_world = DMat4::perspective_infinite_reverse_rh(1.0, 1.0, 0.1)
                        * DMat4::look_at_rh(eye, centre, DVec3::Y);
                    View {
                        clip_from_world: Some(clip_from_world),
                        ..view(eye)
                    }
                };
                let batch = |u: DVec3| -> Vec<Tetrahedron> {
                    let mut batcher = VolumeBatcher::new(source.clone(), &settings).unwrap();
                    let inputs = FrameInputs {
                        criterion,
                        ..inputs(&transfer)
                    };
                    batcher.update(&seen_from(u), &inputs).unwrap();
                    let cells = batcher.batch().tetrahedra.iter();
                    cells.map(nebel_lod::GpuCell::to_tetrahedron).collect()
                };
                let (kept, fresh) = (batch(u), batch(moved));
                assert!(!kept.is_empty() && !fresh.is_empty());
                let clip_from_world = seen_from(moved).clip_from_world.unwrap();
                let mut traced = 0;
                while traced < 250 {
                    let target = at(DVec3::new(
                        random() * 32.0,
                        random() * 16.0,
                        random() * 32.0,
                    ));
                    // Rays the camera sees.
                    let clip = clip_from_world * target.extend(1.0);
                    if !(clip.w > 0.0 && clip.x.abs() <= clip.w && clip.y.abs() <= clip.w) {
                        continue;
                    }
                    traced += 1;
                    let ray = Ray::new(at(moved), target - at(moved)).unwrap();
                    let (drawn, _) = rays::composites(&kept, &ray, 0.15);
                    let (_, exact) = rays::composites(&fresh, &ray, 0.15);
                    cost.add((drawn, exact));
                }
            }
            println!("{criterion:?}, {step} voxels: {cost}");
            // Half an 8-bit step in RMS over the rays into the volume.
            assert!(cost.rmse() <= 1.0 / 510.0, "{criterion:?}, {step}: {cost}");
        }
    }
}

/// Refined on a worker, an octree batch is drawn a frame or two after the eye
/// it was refined and ordered for. Rays from the new eye meet cells out of
/// order only where the eye crossed the plane of a face between them, near
/// the eye, where the cells are small and thin: the image changes by far
/// less than an 8-bit step.
#[test]
fn an_octree_order_a_frame_or_two_old_costs_little_of_the_image() {
    let (grid, source, settings) = rough_octree(7);
    let transfer = cloud();
    let at = |u: DVec3| world_from_local().transform_point3(grid.origin() + u * grid.spacing());
    let mut random = uniform(0x5eed_u64);
    let mut cost = rays::OrderCost::default();
    for _ in 0..4 {
        // An eye inside the grid or just outside it, moved one or two
        // voxels (a fly-through's frame or two at 60 frames a second).
        let (u, direction) = eye_and_direction(&mut random);
        let moved = u + direction * (1.0 + random());
        let mut batcher = VolumeBatcher::new(source.clone(), &settings).unwrap();
        batcher.update(&view(at(u)), &inputs(&transfer)).unwrap();
        let cells: Vec<Tetrahedron> = batcher
            .batch()
            .tetrahedra
            .iter()
            .map(nebel_lod::GpuCell::to_tetrahedron)
            .collect();
        assert!(!cells.is_empty());
        // A ray from `eye` (index coordinates) to a random point in the
        // grid, composited both ways; optical depths up to about 3.
        let mut composites = |eye: DVec3| {
            let target = at(DVec3::new(
                random() * 32.0,
                random() * 16.0,
                random() * 32.0,
            ));
            let ray = Ray::new(at(eye), target - at(eye)).unwrap();
            rays::composites(&cells, &ray, 0.15)
        };
        // From the eye it was ordered for, the order is exact.
        for _ in 0..50 {
            let (drawn, exact) = composites(u);
            assert!((drawn - exact).abs() <= 1e-9, "{drawn} against {exact}");
        }
        for _ in 0..250 {
            cost.add(composites(moved));
        }
    }
    println!("{cost}");
    // Half an 8-bit step in RMS over the rays into the volume.
    assert!(cost.rmse() <= 1.0 / 510.0, "{cost}");
}
