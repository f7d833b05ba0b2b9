//! The volume C-LOD at the algorithm level, measured in images: the octree
//! (`VolumeHierarchy`, `refine`, `lod_batch`; Röttger and Ertl 2003 §2-3)
//! rendered by the exact CPU cell reference (`nebel_reference::render`) and
//! compared with the full-resolution batch of the same quantised grid.
//!
//! - Error against full resolution falls as the accuracy `c` grows, and is
//!   zero at `c = ∞`.
//! - No popping: along a smooth camera path into a cloud the largest
//!   per-pixel change between consecutive frames stays below a bound that
//!   the same path without morphing exceeds, while the full-resolution render
//!   itself (the floor) changes by less than half the bound; the same cloud
//!   in the wind, drawn from keyframes (a still camera, the octree refined
//!   again every step of the blend), stays below the same bound.
//! - Stress: the eye at node centres and on node faces, edges and corners;
//!   flat-zero and all-one fields; NaN input; sizes that are not `2^n + 1`; a
//!   non-cubic forest.
//! - Random eyes (proptest) with zero-opacity and frustum culling: finite
//!   cells, morphed scalars in [0, 1], leaves that tile what is visible, and a
//!   crack check at T-vertices.
//!
//! Every test prints what it measured (`cargo test --release -p nebel_lod
//! --test lod_images -- --nocapture`).

use std::collections::HashMap;

use glam::{DAffine3, DMat4, DVec3, UVec2};
use nebel_core::cell::Tetrahedron;
use nebel_core::field::{DensityGrid, FieldError, PadFill, ProceduralNoise};
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{ControlPoint, TransferFunction, TransferPreset};
use nebel_lod::octree::{
    LodCriterion, NodeMorph, Refinement, RefinementSettings, lod_batch, refine,
};
use nebel_lod::{
    BrickTable, CellOrder, Cells, Frustum, HierarchyError, Node, View, VolumeHierarchy,
    full_resolution_batch,
};
use nebel_reference::image_metrics::{LinearImage, compare};
use nebel_reference::{ReferenceCamera, ReferenceScene, ReferenceVolume, render};
use proptest::prelude::*;

/// Minimum accuracy C of every hierarchy here (`K_max` ≈ 0.64).
const C_MIN: f64 = 2.0;

/// The accuracies of the error sweep.
const SWEEP: [f64; 5] = [0.0, 4.0, 16.0, 64.0, f64::INFINITY];

// ---------------------------------------------------------------------------
// Fields, transfer functions, batches and images
// ---------------------------------------------------------------------------

/// How a cloud field ends at its edge.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Edge {
    /// As the noise gives it: densities in (0, 0.05] (transparent under the
    /// cloud preset, but not zero) around the cloud.
    Soft,
    /// Every density below 0.06 set to 0: no point is transparent without
    /// being zero.
    Hard,
}

/// A cumulus-like blob of `dims` points, `spacing` world units apart and
/// centred on the world origin: inside an ellipsoid that ends one voxel
/// inside the box, `clamp(1.6 e + 2.5 (n − 1/2) − 0.1, 0, 1)` with `e` the
/// envelope (1 at the centre, 0 on the ellipsoid) and `n` fBm noise
/// (`octaves`, first octave 1/16 cycles per world unit, seed 7); outside it
/// 0, so every boundary point is exactly 0.
fn cloud_grid(dims: [usize; 3], spacing: f64, octaves: usize, edge: Edge) -> DensityGrid {
    drifting_cloud_grid(dims, spacing, octaves, edge, DVec3::ZERO)
}

/// [`cloud_grid`] with its noise moved by `drift` (world units) through the
/// envelope, which stays: the cloud a wind blows through its shape.
fn drifting_cloud_grid(
    dims: [usize; 3],
    spacing: f64,
    octaves: usize,
    edge: Edge,
    drift: DVec3,
) -> DensityGrid {
    let half = DVec3::from(dims.map(|n| (n - 1) as f64 / 2.0));
    let origin = -half * spacing;
    let noise = ProceduralNoise {
        seed: 7,
        octaves,
        frequency: 1.0 / 16.0,
        ..ProceduralNoise::default()
    };
    let raw = DensityGrid::procedural(dims, DVec3::splat(spacing), origin - drift, &noise)
        .expect("valid noise settings");
    let semi_axes = (half - 1.0).max(DVec3::splat(0.5));
    let [nx, ny, _] = dims;
    let values = raw
        .values()
        .iter()
        .enumerate()
        .map(|(index, &v)| {
            let p = DVec3::new(
                (index % nx) as f64,
                ((index / nx) % ny) as f64,
                (index / (nx * ny)) as f64,
            );
            let envelope = 1.0 - ((p - half) / semi_axes).length();
            if envelope <= 0.0 {
                return 0.0;
            }
            let s = (1.6 * envelope + 2.5 * (f64::from(v) - 0.5) - 0.1).clamp(0.0, 1.0) as f32;
            if edge == Edge::Hard && s < 0.06 {
                0.0
            } else {
                s
            }
        })
        .collect();
    DensityGrid::new(dims, DVec3::splat(spacing), origin, values).expect("valid grid")
}

/// A grid of `dims` points, spacing 1, origin 0 (index space = world space),
/// with `value` per point.
fn grid_of(dims: [usize; 3], value: impl Fn([usize; 3]) -> f32) -> DensityGrid {
    let [nx, ny, nz] = dims;
    let mut values = Vec::with_capacity(nx * ny * nz);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                values.push(value([i, j, k]));
            }
        }
    }
    DensityGrid::new(dims, DVec3::ONE, DVec3::ZERO, values).expect("valid grid")
}

/// The paper's cloud (Röttger and Ertl 2003 §5.2), ρ scaled to `rho` per world unit at s = 1.
fn cloud_transfer(rho: f32) -> TransferFunction {
    TransferFunction::preset(TransferPreset::Cloud)
        .scale_density(rho)
        .expect("valid scale")
}

/// ρ > 0 for every s, so the zero-opacity test never prunes anything.
fn never_transparent() -> TransferFunction {
    TransferFunction::new([
        ControlPoint {
            s: 0.0,
            kappa: [0.9, 0.9, 1.0],
            rho: 0.02,
        },
        ControlPoint {
            s: 1.0,
            kappa: [0.4, 0.45, 0.5],
            rho: 0.2,
        },
    ])
    .expect("valid transfer function")
}

/// A `width × height` pinhole camera at `position` looking at `target`.
fn camera(
    position: DVec3,
    target: DVec3,
    fov_degrees: f64,
    [width, height]: [u32; 2],
) -> ReferenceCamera {
    ReferenceCamera {
        position,
        vertical_fov: fov_degrees.to_radians(),
        width,
        height,
        ..ReferenceCamera::default()
    }
    .looking_at(target, DVec3::Y)
}

/// The view of a grid in world coordinates (identity `world_from_local`) from
/// `eye`, culled by `frustum`, on a 640 × 480 viewport.
fn view(eye: DVec3, frustum: Option<&Frustum>) -> View {
    View {
        frustum: frustum.cloned(),
        ..View::new(DAffine3::IDENTITY, eye, UVec2::new(640, 480))
    }
}

/// Refines `h` for `eye` (identity `world_from_local`, no frustum) at accuracy
/// `c` and emits the batch. With `morph == false` every refined node gets
/// e' = 1 before emission: morphing off, each node shows its own values the
/// moment it is refined.
fn lod(
    h: &VolumeHierarchy,
    transfer: &TransferFunction,
    eye: DVec3,
    c: f64,
    morph: bool,
) -> (Refinement, Cells) {
    lod_in(
        h,
        transfer,
        &view(eye, None),
        &RefinementSettings::new(LodCriterion::distance(c)),
        morph,
    )
}

/// [`lod`] for any view and refinement settings (criterion, keyframe blend).
fn lod_in(
    h: &VolumeHierarchy,
    transfer: &TransferFunction,
    view: &View,
    settings: &RefinementSettings,
    morph: bool,
) -> (Refinement, Cells) {
    let mut r = refine(h, view, transfer, settings).expect("refinement");
    if !morph {
        for node in &mut r.refined {
            node.morph = 1.0;
            node.end_morph = 1.0;
        }
    }
    let batch = lod_batch(h, &r, view).expect("LOD batch");
    (r, batch)
}

/// The view of [`camera`]`(eye, target, fov_degrees, size)` with its
/// projection (and frustum), for the screen-error criterion.
fn projected_view(eye: DVec3, target: DVec3, fov_degrees: f64, [width, height]: [u32; 2]) -> View {
    let clip_from_world = DMat4::perspective_infinite_reverse_rh(
        fov_degrees.to_radians(),
        f64::from(width) / f64::from(height),
        0.01,
    ) * DMat4::look_at_rh(eye, target, DVec3::Y);
    View::new(DAffine3::IDENTITY, eye, UVec2::new(width, height)).with_projection(clip_from_world)
}

/// The full-resolution batch of `grid` (one-voxel bricks, the same zero-opacity
/// test per voxel as the octree's), back to front for `eye`.
fn full(grid: &DensityGrid, transfer: &TransferFunction, eye: DVec3) -> Cells {
    full_resolution_batch(
        grid,
        &BrickTable::new(grid, 1),
        &view(eye, None),
        transfer,
        CellOrder::BackToFront,
    )
    .expect("full-resolution batch")
}

/// The exact reference image of `batch` (sorted emission-absorption).
fn image(batch: &Cells, transfer: &TransferFunction, camera: ReferenceCamera) -> LinearImage {
    let cells = batch
        .tetrahedra
        .iter()
        .map(nebel_lod::GpuCell::to_tetrahedron)
        .collect();
    let scene = ReferenceScene::new(
        camera,
        ReferenceVolume::Cells(cells),
        transfer.clone(),
        OpticalMode::Sorted,
    );
    render(&scene, None).expect("reference render")
}

fn rmse(a: &LinearImage, b: &LinearImage) -> f64 {
    compare(a, b).expect("comparable images").rmse
}

/// The largest absolute change of any linear RGB channel of any pixel.
fn max_change(a: &LinearImage, b: &LinearImage) -> f64 {
    compare(a, b).expect("comparable images").max_abs
}

fn mean_alpha(image: &LinearImage) -> f64 {
    image.pixels.iter().map(|p| f64::from(p[3])).sum::<f64>() / image.pixels.len() as f64
}

fn node_box(node: Node) -> (DVec3, DVec3) {
    let lo = DVec3::from(node.origin.map(|o| o as f64));
    (lo, lo + node.size() as f64)
}

// ---------------------------------------------------------------------------
// Checks shared by the stress tests and the proptest
// ---------------------------------------------------------------------------

/// Panics unless every e' of `r` is in [0, 1], leaves above level 0 have
/// e' = 0 and refined nodes e' > 0.
fn assert_morph_factors(r: &Refinement) {
    for n in &r.leaves {
        assert!((0.0..=1.0).contains(&n.morph), "leaf {n:?}");
        assert!(n.node.level == 0 || n.morph == 0.0, "leaf {n:?}");
    }
    for n in &r.refined {
        assert!(n.morph > 0.0 && n.morph <= 1.0, "refined {n:?}");
    }
}

/// Panics unless every vertex of `batch` is finite with a scalar in [0, 1],
/// inside `[lo, hi]` (world units), and every position carries one scalar in
/// every cell that uses it. Returns the scalar per position (f32 bits).
fn assert_finite_and_conforming(batch: &Cells, lo: DVec3, hi: DVec3) -> HashMap<[u32; 3], f32> {
    let mut values = HashMap::new();
    for vertex in batch.tetrahedra.iter().flat_map(|c| c.vertices) {
        let [x, y, z, s] = vertex;
        assert!(
            vertex.iter().all(|c| c.is_finite()),
            "non-finite vertex {vertex:?}"
        );
        assert!((0.0..=1.0).contains(&s), "scalar {s} outside [0, 1]");
        let p = DVec3::new(f64::from(x), f64::from(y), f64::from(z));
        assert!(
            p.cmpge(lo - 1e-4).all() && p.cmple(hi + 1e-4).all(),
            "{p} outside the grid box {lo} .. {hi}"
        );
        let first = *values.entry([x, y, z].map(f32::to_bits)).or_insert(s);
        assert_eq!(first.to_bits(), s.to_bits(), "two scalars at {p}");
    }
    values
}

/// Barycentric coordinates of `p` in `t`.
fn barycentric(t: &Tetrahedron, p: DVec3) -> [f64; 4] {
    let [a, b, c, d] = t.positions;
    let volume =
        |p0: DVec3, p1: DVec3, p2: DVec3, p3: DVec3| (p1 - p0).dot((p2 - p0).cross(p3 - p0));
    let total = volume(a, b, c, d);
    [
        volume(p, b, c, d) / total,
        volume(a, p, c, d) / total,
        volume(a, b, p, d) / total,
        volume(a, b, c, p) / total,
    ]
}

/// The crack check for a batch in grid index space (identity transform,
/// spacing 1, origin 0, so every vertex is an integer grid point): every grid
/// point that lies in a cell (on a face or edge, not a vertex of it) and is a
/// vertex of some other cell must carry the value that cell interpolates
/// there. T-vertices between leaves of different levels are exactly these
/// points; a point strictly inside a cell that is another cell's vertex would
/// be an overlap and fails too. Returns how many such points were checked.
fn assert_no_t_vertex_cracks(batch: &Cells, values: &HashMap<[u32; 3], f32>) -> usize {
    let mut checked = 0;
    for cell in &batch.tetrahedra {
        let t = cell.to_tetrahedron();
        let lo = t.positions.iter().fold(DVec3::INFINITY, |a, &p| a.min(p));
        let hi = t
            .positions
            .iter()
            .fold(DVec3::NEG_INFINITY, |a, &p| a.max(p));
        for k in lo.z as i64..=hi.z as i64 {
            for j in lo.y as i64..=hi.y as i64 {
                for i in lo.x as i64..=hi.x as i64 {
                    let p = DVec3::new(i as f64, j as f64, k as f64);
                    if t.positions.contains(&p) {
                        continue;
                    }
                    let key = [i as f32, j as f32, k as f32].map(f32::to_bits);
                    let Some(&value) = values.get(&key) else {
                        continue;
                    };
                    let w = barycentric(&t, p);
                    if w.iter().any(|&w| w < -1e-9) {
                        continue;
                    }
                    let interpolated: f64 = (0..4).map(|v| w[v] * t.scalars[v]).sum();
                    assert!(
                        (interpolated - f64::from(value)).abs() < 1e-5,
                        "crack at {p}: vertex value {value}, the cell {:?} interpolates {interpolated}",
                        t.positions
                    );
                    checked += 1;
                }
            }
        }
    }
    checked
}

/// How often each voxel is covered by a leaf of `r`.
fn coverage(h: &VolumeHierarchy, r: &Refinement) -> Vec<u8> {
    let v = h.dims().map(|n| n - 1);
    let mut cover = vec![0u8; v[0] * v[1] * v[2]];
    for leaf in &r.leaves {
        let (o, s) = (leaf.node.origin, leaf.node.size());
        for k in o[2]..o[2] + s {
            for j in o[1]..o[1] + s {
                for i in o[0]..o[0] + s {
                    cover[i + v[0] * (j + v[1] * k)] += 1;
                }
            }
        }
    }
    cover
}

/// Panics unless the leaves of `r` cover every voxel exactly once.
fn assert_leaves_tile(h: &VolumeHierarchy, r: &Refinement) {
    let cover = coverage(h, r);
    assert!(
        cover.iter().all(|&c| c == 1),
        "leaves do not tile the volume"
    );
}

// ---------------------------------------------------------------------------
// 1. Error against full resolution falls as c grows
// ---------------------------------------------------------------------------

/// The image error of the LOD batch against the full-resolution batch of the
/// same quantised 33³ cloud, for c in {0, 4, 16, 64, ∞}, two cameras (one
/// outside, one inside the cloud), 40×30 px, sorted mode, cloud preset.
/// Returns `(morphed, unmorphed)` RMSE per c.
fn error_sweep(grid: &DensityGrid, name: &str, eye: DVec3, target: DVec3) -> Sweep {
    let transfer = cloud_transfer(0.25);
    let h = VolumeHierarchy::new(grid, C_MIN).expect("33³ grid");
    let size = [40, 30];
    let cam = camera(eye, target, 45.0, size);
    let full_batch = full(&h.quantised_grid(), &transfer, eye);
    let reference = image(&full_batch, &transfer, cam);
    eprintln!(
        "{name}: full resolution {} cells, mean alpha {:.3}",
        full_batch.len(),
        mean_alpha(&reference)
    );
    let mut sweep = Sweep::default();
    for c in SWEEP {
        let (r, batch) = lod(&h, &transfer, eye, c, true);
        let (_, batch_off) = lod(&h, &transfer, eye, c, false);
        sweep
            .morphed
            .push(rmse(&image(&batch, &transfer, cam), &reference));
        sweep
            .unmorphed
            .push(rmse(&image(&batch_off, &transfer, cam), &reference));
        // The refinement's size: six cells per leaf. The batch drops the
        // cells of transparent leaves whose field stays transparent, so a
        // finer refinement that finds empty space may draw a few fewer.
        sweep.cells.push(6 * r.leaves.len());
        eprintln!(
            "{name}: c = {c:>3}: {:>6} cells ({} voxel leaves), RMSE morphed {:.3e}, morphing off {:.3e}",
            batch.len(),
            r.stats.full_resolution_leaves,
            sweep.morphed.last().unwrap(),
            sweep.unmorphed.last().unwrap(),
        );
    }
    let view = projected_view(eye, target, 45.0, size);
    for tolerance in SCREEN_SWEEP {
        let (r, batch) = lod_in(
            &h,
            &transfer,
            &view,
            &RefinementSettings::new(LodCriterion::screen_error(tolerance)),
            true,
        );
        let error = rmse(&image(&batch, &transfer, cam), &reference);
        eprintln!(
            "{name}: screen error {tolerance:>5}: {:>6} cells ({} drawn), RMSE {error:.3e}",
            6 * r.leaves.len(),
            batch.len()
        );
        sweep.screen.push((6 * r.leaves.len(), error));
    }
    sweep
}

/// What [`error_sweep`] measured: per c of [`SWEEP`] the RMSE (morphed and
/// not) and cells, per tolerance of [`SCREEN_SWEEP`] the cells and RMSE.
#[derive(Default)]
struct Sweep {
    morphed: Vec<f64>,
    unmorphed: Vec<f64>,
    cells: Vec<usize>,
    screen: Vec<(usize, f64)>,
}

/// The screen error's RMSE at `cells` cells, interpolated log-log between
/// the neighbouring points of its sweep; beyond its finest point that
/// point's (more cells would not raise it: the sweep is monotone); `None`
/// below its coarsest.
fn screen_error_at(screen: &[(usize, f64)], cells: usize) -> Option<f64> {
    let &(most_cells, finest) = screen.last()?;
    if cells >= most_cells {
        return Some(finest);
    }
    screen.windows(2).find_map(|pair| {
        let [(c0, e0), (c1, e1)] = [pair[0], pair[1]];
        (c0 <= cells && cells <= c1 && c0 < c1).then(|| {
            let t = (cells as f64 / c0 as f64).ln() / (c1 as f64 / c0 as f64).ln();
            (e0.ln() + t * (e1.ln() - e0.ln())).exp()
        })
    })
}

/// The screen-error tolerances of the error sweep, coarse to fine.
const SCREEN_SWEEP: [f64; 8] = [3.0, 1.0, 0.3, 0.1, 0.03, 0.01, 0.003, 0.001];

/// Absolute slack on "non-increasing": 1e-4 in linear RGB (1/40 of an 8-bit
/// step), a fifth of the smallest step measured between neighbouring c
/// (5e-4).
const MONOTONE_SLACK: f64 = 1e-4;

#[test]
fn error_against_full_resolution_falls_as_c_grows() {
    let cameras = [
        ("outside", DVec3::new(-12.0, 14.0, 40.0), DVec3::ZERO),
        (
            "inside",
            DVec3::new(3.0, -2.0, 5.0),
            DVec3::new(-8.0, 4.0, -10.0),
        ),
    ];
    for edge in [Edge::Soft, Edge::Hard] {
        let grid = cloud_grid([33; 3], 1.0, 3, edge);
        for (camera_name, eye, target) in cameras {
            let name = format!("{edge:?} edge, {camera_name}");
            let sweep = error_sweep(&grid, &name, eye, target);
            let (morphed, unmorphed) = (&sweep.morphed, &sweep.unmorphed);
            // The refinement alone (morphing off): more accuracy, a finer
            // mesh of exact vertex values, never a larger error.
            for i in 1..SWEEP.len() {
                assert!(
                    unmorphed[i] <= unmorphed[i - 1] + MONOTONE_SLACK,
                    "{name}, morphing off: RMSE rises from c = {} ({:.3e}) to c = {} ({:.3e})",
                    SWEEP[i - 1],
                    unmorphed[i - 1],
                    SWEEP[i],
                    unmorphed[i]
                );
            }
            // Morphed: non-increasing from c = 4 on. Between c = 0 and 4 it
            // may rise: at c = 0 the few refined coarse nodes are only partly
            // morphed (e' < 1), and that blend toward the smooth coarse field
            // can happen to be closer in RMSE than their fully morphed
            // children (measured: outside camera, RMSE 0.109 at c = 0 and
            // 0.143 at c = 4).
            for i in 2..SWEEP.len() {
                assert!(
                    morphed[i] <= morphed[i - 1] + MONOTONE_SLACK,
                    "{name}, morphed: RMSE rises from c = {} ({:.3e}) to c = {} ({:.3e})",
                    SWEEP[i - 1],
                    morphed[i - 1],
                    SWEEP[i],
                    morphed[i]
                );
            }
            // The screen error: finer with every smaller tolerance, and at
            // the cells the distance criterion draws at c = 16 and c = 64 no
            // larger an RMSE (measured: outside 5 % and 33 % below, inside
            // the screen error reaches a third of the error with a fifth of
            // the cells).
            for pair in sweep.screen.windows(2) {
                assert!(
                    pair[1].0 >= pair[0].0 && pair[1].1 <= pair[0].1 + MONOTONE_SLACK,
                    "{name}: the screen error's sweep is not monotone: {:?}",
                    sweep.screen
                );
            }
            for i in [2, 3] {
                let at = screen_error_at(&sweep.screen, sweep.cells[i]).unwrap_or_else(|| {
                    panic!(
                        "{name}: {} cells outside the screen sweep {:?}",
                        sweep.cells[i], sweep.screen
                    )
                });
                assert!(
                    at <= morphed[i],
                    "{name}: at {} cells the screen error's RMSE {at:.3e} exceeds the distance criterion's {:.3e} (c = {})",
                    sweep.cells[i],
                    morphed[i],
                    SWEEP[i]
                );
            }
            assert!(
                morphed[3] < 0.25 * morphed[0],
                "{name}: c = 64 should cut the c = 0 error at least fourfold"
            );
            if edge == Edge::Hard {
                assert!(
                    morphed[4] <= 1e-6 && unmorphed[4] <= 1e-6,
                    "{name}: c = ∞ must reproduce the full-resolution image, RMSE {:.3e}",
                    morphed[4]
                );
            }
        }
    }
}

/// Known bug, ignored until fixed: at `c = ∞` a grid point shared by a
/// refined node and a node pruned by the zero-opacity test takes its coarse
/// value instead of its own, because `lod_batch` reads a pruned node's e' as
/// 0 (emit.rs: "e' = 0 for a node that is not in that list (a leaf, a node
/// below a leaf, or a pruned one)"). With densities in (0, 0.05] around the
/// cloud (transparent under the cloud preset, not zero) the LOD image then
/// differs from full resolution: RMSE 3.7e-4 from outside, 1.3e-5 from
/// inside. Skipping pruned sharers in the minimum (only a sharer under a
/// drawn leaf forces w = 0) makes both 0 and keeps the crack checks here
/// passing.
#[test]
fn infinite_accuracy_with_soft_cloud_edges_matches_full_resolution() {
    let grid = cloud_grid([33; 3], 1.0, 3, Edge::Soft);
    let transfer = cloud_transfer(0.25);
    let h = VolumeHierarchy::new(&grid, C_MIN).unwrap();
    for (eye, target) in [
        (DVec3::new(-12.0, 14.0, 40.0), DVec3::ZERO),
        (DVec3::new(3.0, -2.0, 5.0), DVec3::new(-8.0, 4.0, -10.0)),
    ] {
        let cam = camera(eye, target, 45.0, [40, 30]);
        let reference = image(&full(&h.quantised_grid(), &transfer, eye), &transfer, cam);
        let (_, batch) = lod(&h, &transfer, eye, f64::INFINITY, true);
        let error = rmse(&image(&batch, &transfer, cam), &reference);
        eprintln!("soft edge, eye {eye}: c = ∞ RMSE {error:.3e}");
        assert!(error <= 1e-6, "c = ∞ RMSE {error:.3e}");
    }
}

// ---------------------------------------------------------------------------
// 2. No popping along a smooth camera path
// ---------------------------------------------------------------------------

/// Largest per-pixel change between consecutive frames along one path.
#[derive(Clone, Copy, Debug, Default)]
struct Popping {
    /// The largest change and the frame it ends at.
    max: f64,
    frame: usize,
}

impl Popping {
    fn add(&mut self, change: f64, frame: usize) {
        if change > self.max {
            *self = Self { max: change, frame };
        }
    }
}

/// Frames of the path.
const PATH_FRAMES: usize = 100;

/// The path: from the direction `(−20, 15, 50)`, the eye's distance from the
/// cloud centre falls geometrically from 24 to 9 world units (1 % per frame,
/// so the image scales by about as much per frame everywhere), looking at the
/// centre. The cloud (17³ points, spacing 2: a 32-unit box whose envelope
/// ends 14 units from the centre) fills the 20° view; the eye enters it
/// about 55 frames in.
fn path_eye(frame: usize) -> DVec3 {
    let direction = DVec3::new(-20.0, 15.0, 50.0).normalize();
    let t = frame as f64 / (PATH_FRAMES - 1) as f64;
    direction * 24.0 * (9.0f64 / 24.0).powf(t)
}

#[test]
fn morphing_keeps_frame_to_frame_change_below_a_bound_that_popping_exceeds() {
    // One fBm octave: a smooth cloud, so the full-resolution render changes
    // little per frame (the floor) and LOD transitions stand out.
    let grid = cloud_grid([17; 3], 2.0, 1, Edge::Soft);
    let transfer = cloud_transfer(0.15);
    let h = VolumeHierarchy::new(&grid, C_MIN).unwrap();
    let quantised = h.quantised_grid();
    let size = [40, 30];
    // (criterion, bound). Each bound of the distance criterion is the
    // geometric mean of the morphed and the unmorphed maximum measured when
    // this test was written (c = 16: 0.0081 and 0.0187; c = 4: 0.0198 and
    // 0.0640), rounded, so either side is about 1.5× (c = 16) or 1.8× (c = 4)
    // away from it. The screen error (tolerance 0.03, about as many cells as
    // c = 16) is held to c = 16's bound; measured when it was added: 0.0045
    // morphed (the floor's 0.0040 is the camera's own motion), 0.0118 with
    // morphing off.
    let cases = [
        (
            LodCriterion::distance(LodCriterion::DEFAULT_ACCURACY),
            0.0125,
        ),
        (LodCriterion::distance(4.0), 0.035),
        (LodCriterion::screen_error(0.03), 0.0125),
    ];

    let mut floor = Popping::default();
    let mut morphed = [Popping::default(); 3];
    let mut unmorphed = [Popping::default(); 3];
    let mut cells = [0usize; 3];
    let mut previous: Option<(LinearImage, Vec<[LinearImage; 2]>)> = None;
    for frame in 0..PATH_FRAMES {
        let eye = path_eye(frame);
        let cam = camera(eye, DVec3::ZERO, 20.0, size);
        let full_image = image(&full(&quantised, &transfer, eye), &transfer, cam);
        let lod_images: Vec<[LinearImage; 2]> = cases
            .iter()
            .enumerate()
            .map(|(i, &(criterion, _))| {
                let view = match criterion {
                    LodCriterion::Distance { .. } => view(eye, None),
                    LodCriterion::ScreenError { .. } => {
                        projected_view(eye, DVec3::ZERO, 20.0, size)
                    }
                };
                let settings = RefinementSettings::new(criterion);
                let (_, on) = lod_in(&h, &transfer, &view, &settings, true);
                let (_, off) = lod_in(&h, &transfer, &view, &settings, false);
                cells[i] = cells[i].max(on.len());
                [image(&on, &transfer, cam), image(&off, &transfer, cam)]
            })
            .collect();
        if let Some((last_full, last_lod)) = &previous {
            floor.add(max_change(&full_image, last_full), frame);
            for i in 0..cases.len() {
                morphed[i].add(max_change(&lod_images[i][0], &last_lod[i][0]), frame);
                unmorphed[i].add(max_change(&lod_images[i][1], &last_lod[i][1]), frame);
            }
        }
        previous = Some((full_image, lod_images));
    }

    eprintln!(
        "path of {PATH_FRAMES} frames, {}×{} px: largest change of the full-resolution render (floor) {:.4} (frame {})",
        size[0], size[1], floor.max, floor.frame
    );
    for (i, (c, bound)) in cases.iter().enumerate() {
        eprintln!(
            "{c:?}: up to {} cells; largest change morphed {:.4} (frame {}), morphing off {:.4} (frame {}), ratio {:.2}, bound {bound}",
            cells[i],
            morphed[i].max,
            morphed[i].frame,
            unmorphed[i].max,
            unmorphed[i].frame,
            unmorphed[i].max / morphed[i].max
        );
    }
    for (i, &(c, bound)) in cases.iter().enumerate() {
        let (on, off) = (morphed[i].max, unmorphed[i].max);
        assert!(on < bound, "{c:?}: morphed change {on:.4} ≥ bound {bound}");
        // The distance criterion pops past the bound without morphing (the
        // test can fail); for both, morphing takes out most of the change.
        if matches!(c, LodCriterion::Distance { .. }) {
            assert!(
                off > bound,
                "{c:?}: change without morphing {off:.4} ≤ bound {bound}"
            );
        }
        assert!(
            off >= 1.5 * on,
            "{c:?}: without morphing {off:.4} is not 1.5× the morphed {on:.4}"
        );
        // The path is smooth: camera motion alone changes the exact image by
        // well under the bound, so what exceeds it is LOD popping.
        assert!(
            floor.max < 0.5 * bound,
            "floor {:.4} is not below half the bound {bound}",
            floor.max
        );
    }
}

// ---------------------------------------------------------------------------
// 3. Stress
// ---------------------------------------------------------------------------

/// The eye exactly at node centres (d = 0 for that node), on node faces, on
/// node edges, at node corners and at grid corners, for c in {0, 16}: no
/// panic, no NaN, e' in [0, 1], leaves that tile the volume (a transfer
/// function that never prunes), a conforming batch without T-vertex cracks,
/// and a finite image from that eye. With the cloud preset (pruning) and a
/// hard-edged cloud, c = ∞ still reproduces the full-resolution image from
/// those eyes.
#[test]
fn eye_at_node_centres_faces_edges_and_corners() {
    // Index space = world space: the eye's coordinates are grid coordinates.
    let soft = cloud_grid([33; 3], 1.0, 3, Edge::Soft);
    let hard = cloud_grid([33; 3], 1.0, 3, Edge::Hard);
    let in_index_space = |g: &DensityGrid| {
        DensityGrid::new(g.dims(), DVec3::ONE, DVec3::ZERO, g.values().to_vec()).unwrap()
    };
    let h = VolumeHierarchy::new(&in_index_space(&soft), C_MIN).unwrap();
    let h_hard = VolumeHierarchy::new(&in_index_space(&hard), C_MIN).unwrap();
    let opaque = never_transparent();
    let cloud = cloud_transfer(0.25);
    let eyes: [(&str, [f64; 3]); 11] = [
        ("root centre", [16.0, 16.0, 16.0]),
        ("level-4 centre", [8.0, 8.0, 8.0]),
        ("level-3 centre", [12.0, 4.0, 20.0]),
        ("level-1 centre", [1.0, 1.0, 1.0]),
        ("voxel centre", [0.5, 0.5, 0.5]),
        ("root split plane (face)", [16.0, 5.3, 7.7]),
        ("root split line (edge)", [16.0, 16.0, 7.7]),
        ("level-3 corner, not a centre", [8.0, 16.0, 24.0]),
        ("box face", [0.0, 13.3, 21.1]),
        ("box corner", [0.0, 0.0, 0.0]),
        ("far box corner", [32.0, 32.0, 32.0]),
    ];
    let (lo, hi) = (DVec3::ZERO, DVec3::splat(32.0));
    let mut t_vertices = 0;
    for (name, eye) in eyes {
        let eye = DVec3::from(eye);
        let target = if eye == DVec3::splat(16.0) {
            DVec3::new(30.0, 20.0, 0.0)
        } else {
            DVec3::splat(16.0)
        };
        let cam = camera(eye, target, 60.0, [24, 18]);
        for c in [0.0, 16.0] {
            let (r, batch) = lod(&h, &opaque, eye, c, true);
            assert_morph_factors(&r);
            assert_leaves_tile(&h, &r);
            assert_eq!(batch.len(), 6 * r.leaves.len());
            let values = assert_finite_and_conforming(&batch, lo, hi);
            t_vertices += assert_no_t_vertex_cracks(&batch, &values);
            let volume: f64 = batch
                .tetrahedra
                .iter()
                .map(|c| c.to_tetrahedron().volume())
                .sum();
            assert!(
                (volume - 32f64.powi(3)).abs() < 1e-6 * 32f64.powi(3),
                "{name}, c = {c}: cells fill {volume}, not the box"
            );
            // The node whose centre is the eye is refined with e = ∞, e' = 1,
            // and the voxel around the eye is drawn at full resolution.
            for n in &r.refined {
                if n.node.centre().map(|p| DVec3::from(p.map(|v| v as f64))) == Some(eye) {
                    assert_eq!(n.morph, 1.0, "{name}: {n:?}");
                }
            }
            let around = r.leaves.iter().find(|l| {
                let (a, b) = node_box(l.node);
                eye.cmpge(a).all() && eye.cmple(b).all()
            });
            assert_eq!(around.map(|l| l.node.level), Some(0), "{name}, c = {c}");
            if c == 16.0 {
                let picture = image(&batch, &opaque, cam);
                assert!(picture.pixels.iter().flatten().all(|v| v.is_finite()));
                assert!(mean_alpha(&picture) > 0.1, "{name}: the eye sees nothing");
            }
        }
        // Pruning by the cloud preset, c = ∞: the full-resolution image.
        let (r, batch) = lod(&h_hard, &cloud, eye, f64::INFINITY, true);
        assert_morph_factors(&r);
        assert_finite_and_conforming(&batch, lo, hi);
        let reference = image(&full(&h_hard.quantised_grid(), &cloud, eye), &cloud, cam);
        let error = rmse(&image(&batch, &cloud, cam), &reference);
        eprintln!(
            "eye at {name} {eye}: c = ∞ with pruning: {} cells, RMSE {error:.1e} against full resolution",
            batch.len()
        );
        assert!(error <= 1e-6, "{name}: RMSE {error:.3e}");
    }
    eprintln!("{t_vertices} T-vertices checked");
    assert!(t_vertices > 0);
}

/// A field that is zero everywhere: Δ = 0, every node is transparent under
/// the cloud preset and ground fog (nothing to draw, no NaN), and under a
/// transfer function that is never transparent only the distance term
/// refines: roots from far away, at any c.
#[test]
fn flat_zero_field() {
    let h = VolumeHierarchy::new(&grid_of([17; 3], |_| 0.0), C_MIN).unwrap();
    let root = h.roots().next().unwrap();
    assert_eq!((h.deviation(root), h.scalar_range(root)), (0.0, [0.0, 0.0]));
    let eyes = [
        DVec3::new(8.0, 8.0, 8.0),
        DVec3::new(3.3, 0.0, 12.0),
        DVec3::new(-40.0, 25.0, 70.0),
        DVec3::splat(1e5),
    ];
    let transfers = [
        TransferFunction::preset(TransferPreset::Cloud),
        TransferFunction::preset(TransferPreset::GroundFog),
    ];
    for eye in eyes {
        for c in [0.0, 16.0, f64::INFINITY] {
            for transfer in &transfers {
                let (r, batch) = lod(&h, transfer, eye, c, true);
                assert!(r.leaves.is_empty() && r.refined.is_empty() && batch.is_empty());
                assert_eq!(r.stats.culled_transparent, 1);
                let picture = image(&batch, transfer, camera(eye, DVec3::ZERO, 45.0, [8, 6]));
                assert!(picture.pixels.iter().all(|p| *p == [0.0; 4]));
            }
            let (r, batch) = lod(&h, &never_transparent(), eye, c, true);
            assert_morph_factors(&r);
            assert_leaves_tile(&h, &r);
            let values = assert_finite_and_conforming(&batch, DVec3::ZERO, DVec3::splat(16.0));
            assert!(values.values().all(|&s| s == 0.0));
            if eye == DVec3::splat(1e5) {
                assert_eq!(r.leaves.len(), 1, "far away only the root, c = {c}");
            }
        }
    }
}

/// A field that is one everywhere: Δ = 0 at every node, so c changes
/// nothing: only the distance term `s·C/d > 1` refines (the same leaves at
/// c = 0 and c = ∞), far away only the roots are drawn (c = ∞ with Δ = 0 does
/// not give NaN), every scalar is 1, and the image equals full resolution.
#[test]
fn all_one_field() {
    let h = VolumeHierarchy::new(&grid_of([33, 33, 17], |_| 1.0), C_MIN).unwrap();
    assert_eq!(h.root_counts(), [2, 2, 1]);
    let transfer = cloud_transfer(0.05);
    for eye in [
        DVec3::new(1e4, -3e3, 2e3),
        DVec3::new(-30.0, 50.0, 90.0),
        DVec3::new(16.0, 16.0, 8.0),
        DVec3::new(7.2, 21.9, 3.3),
    ] {
        let (r0, _) = lod(&h, &transfer, eye, 0.0, true);
        let (r, batch) = lod(&h, &transfer, eye, f64::INFINITY, true);
        assert_eq!(r.leaves, r0.leaves, "c must not matter when Δ = 0");
        assert_morph_factors(&r);
        assert_leaves_tile(&h, &r);
        for n in &r.refined {
            // Refined by distance alone: e = s·C/d > 1.
            let centre = DVec3::from(n.node.centre().unwrap().map(|v| v as f64));
            let s = n.node.size() as f64;
            assert!(s * C_MIN > centre.distance(eye), "{n:?} refined at Δ = 0");
        }
        let values =
            assert_finite_and_conforming(&batch, DVec3::ZERO, DVec3::new(32.0, 32.0, 16.0));
        assert!(values.values().all(|&s| s == 1.0));
        let far = eye.length() > 1e3;
        if far {
            assert_eq!(r.leaves.len(), 4, "far away only the four roots");
        }
        let cam = camera(eye, DVec3::new(16.0, 16.0, 8.0), 45.0, [24, 18]);
        let cam = if eye == DVec3::new(16.0, 16.0, 8.0) {
            camera(eye, DVec3::new(30.0, 2.0, 0.0), 60.0, [24, 18])
        } else {
            cam
        };
        let reference = image(&full(&h.quantised_grid(), &transfer, eye), &transfer, cam);
        let error = compare(&image(&batch, &transfer, cam), &reference).unwrap();
        eprintln!(
            "all-one field, eye {eye}: {} leaves ({} refined), {error}",
            r.leaves.len(),
            r.refined.len()
        );
        assert!(error.max_abs <= 1e-6);
    }
}

/// NaN never reaches the octree: `VolumeHierarchy::new` takes a
/// `DensityGrid`, and building one with NaN (or ±∞, or a value outside
/// [0, 1]) is an error that names the sample; the padding helper refuses a
/// NaN fill.
#[test]
fn nan_in_the_input_is_an_error() {
    for (index, bad) in [(13, f32::NAN), (0, f32::INFINITY), (26, f32::NEG_INFINITY)] {
        let mut values = vec![0.5; 27];
        values[index] = bad;
        let error = DensityGrid::new([3; 3], DVec3::ONE, DVec3::ZERO, values).unwrap_err();
        eprintln!("{error}");
        assert!(
            matches!(error, FieldError::NonFinite { index: i, .. } if i == index),
            "{error:?}"
        );
        assert!(error.to_string().contains(&format!("sample {index}")));
    }
    let mut values = vec![0.5; 27];
    values[5] = 1.5;
    let error = DensityGrid::new([3; 3], DVec3::ONE, DVec3::ZERO, values).unwrap_err();
    assert!(
        matches!(error, FieldError::OutOfRange { index: 5, .. }),
        "{error:?}"
    );
    let grid = grid_of([3, 4, 3], |_| 0.5);
    let error = grid
        .padded_to_power_of_two_plus_one(PadFill::Value(f32::NAN))
        .unwrap_err();
    assert!(
        matches!(error, FieldError::InvalidParameter { .. }),
        "{error:?}"
    );
}

/// A 20 × 20 × 12 cloud is refused with an error naming its dims; padded with
/// zeros (`DensityGrid::padded_to_power_of_two_plus_one`) to 33 × 33 × 17 it
/// builds a forest of 2 × 2 × 1 roots, and at c = ∞ the LOD image of the
/// padded grid equals the full-resolution image of the original grid (the
/// padding is empty space and is pruned).
#[test]
fn sizes_other_than_power_of_two_plus_one() {
    let original = cloud_grid([20, 20, 12], 1.0, 3, Edge::Hard);
    let error = VolumeHierarchy::new(&original, C_MIN).unwrap_err();
    eprintln!("{error}");
    assert_eq!(
        error,
        HierarchyError::NotPowerOfTwoPlusOne { dims: [20, 20, 12] }
    );
    let message = error.to_string();
    assert!(
        message.contains("[20, 20, 12]") && message.contains("padded_to_power_of_two_plus_one")
    );

    let padded = original
        .padded_to_power_of_two_plus_one(PadFill::Value(0.0))
        .unwrap();
    assert_eq!(padded.dims(), [33, 33, 17]);
    assert_eq!(
        (padded.origin(), padded.spacing()),
        (original.origin(), original.spacing())
    );
    for (k, j, i) in [(0, 0, 0), (5, 9, 13), (11, 19, 19)] {
        assert_eq!(padded.value(i, j, k), original.value(i, j, k));
    }
    let h = VolumeHierarchy::new(&padded, C_MIN).unwrap();
    assert_eq!((h.root_level(), h.root_counts()), (4, [2, 2, 1]));

    // The original's quantised values: the padded hierarchy's, cropped.
    let quantised = h.quantised_grid();
    let mut cropped = Vec::with_capacity(20 * 20 * 12);
    for k in 0..12 {
        for j in 0..20 {
            for i in 0..20 {
                cropped.push(quantised.value(i, j, k));
            }
        }
    }
    let cropped =
        DensityGrid::new([20, 20, 12], original.spacing(), original.origin(), cropped).unwrap();
    let transfer = cloud_transfer(0.25);
    for (eye, target) in [
        (DVec3::new(-10.0, 12.0, 15.0), DVec3::ZERO),
        (DVec3::new(1.0, 0.5, 0.0), DVec3::new(-6.0, 2.0, -3.0)),
    ] {
        let cam = camera(eye, target, 45.0, [40, 30]);
        let reference = image(&full(&cropped, &transfer, eye), &transfer, cam);
        let mut errors = Vec::new();
        for c in SWEEP {
            let (r, batch) = lod(&h, &transfer, eye, c, true);
            assert_morph_factors(&r);
            errors.push(rmse(&image(&batch, &transfer, cam), &reference));
        }
        let shown: Vec<String> = errors.iter().map(|e| format!("{e:.3e}")).collect();
        let alpha = mean_alpha(&reference);
        eprintln!(
            "padded 20×20×12, eye {eye}: mean alpha {alpha:.3}, RMSE at c = {SWEEP:?}: {shown:?}"
        );
        assert!(alpha > 0.05, "the camera sees too little cloud: {alpha}");
        assert!(errors[4] <= 1e-6, "c = ∞: RMSE {:.3e}", errors[4]);
        assert!(errors[3] < errors[1]);
    }
}

/// A cloud layer of 33 × 33 × 9 points is a forest of 4 × 4 × 1 roots of 9³
/// points: leaves tile it from outside, from inside the layer and from the
/// line where four roots meet, the batch conforms across root boundaries, and
/// c = ∞ gives the full-resolution image.
#[test]
fn non_cubic_forest() {
    let layer = cloud_grid([33, 33, 9], 1.0, 3, Edge::Hard);
    let layer = DensityGrid::new(
        layer.dims(),
        DVec3::ONE,
        DVec3::ZERO,
        layer.values().to_vec(),
    )
    .unwrap();
    let h = VolumeHierarchy::new(&layer, C_MIN).unwrap();
    assert_eq!((h.root_level(), h.root_counts()), (3, [4, 4, 1]));
    let cloud = cloud_transfer(0.25);
    let opaque = never_transparent();
    let (lo, hi) = (DVec3::ZERO, DVec3::new(32.0, 32.0, 8.0));
    for (eye, target) in [
        (DVec3::new(-10.0, 40.0, 30.0), DVec3::new(16.0, 16.0, 4.0)),
        (DVec3::new(13.7, 20.2, 4.4), DVec3::new(30.0, 2.0, 4.0)),
        (DVec3::new(8.0, 8.0, 4.0), DVec3::new(30.0, 30.0, 0.0)),
        (DVec3::new(16.0, 16.0, 20.0), DVec3::new(16.0, 16.0, 0.0)),
    ] {
        let cam = camera(eye, target, 50.0, [32, 24]);
        for c in [0.0, 16.0] {
            let (r, batch) = lod(&h, &opaque, eye, c, true);
            assert_morph_factors(&r);
            assert_leaves_tile(&h, &r);
            let values = assert_finite_and_conforming(&batch, lo, hi);
            assert_no_t_vertex_cracks(&batch, &values);
        }
        let reference = image(&full(&h.quantised_grid(), &cloud, eye), &cloud, cam);
        let (r, batch) = lod(&h, &cloud, eye, f64::INFINITY, true);
        let error = rmse(&image(&batch, &cloud, cam), &reference);
        eprintln!(
            "33×33×9 forest, eye {eye}: c = ∞ {} leaves, RMSE {error:.1e}",
            r.leaves.len()
        );
        assert!(error <= 1e-6);
    }
}

// ---------------------------------------------------------------------------
// 4. Random eyes
// ---------------------------------------------------------------------------

/// The error metric of Röttger and Ertl 2003 Eq. 1 recomputed in f64 for a node of `h`
/// (index space = world space, so the voxel edge is 1).
fn error_metric(h: &VolumeHierarchy, node: Node, eye: DVec3, c: f64) -> f64 {
    let (lo, hi) = node_box(node);
    let d = (0.5 * (lo + hi)).distance(eye);
    let delta = f64::from(h.deviation(node));
    // f64::max ignores the NaN of ∞ · 0.
    let e = node.size() as f64 * h.min_accuracy() * (c * delta).max(1.0);
    if d > 0.0 { e / d } else { f64::INFINITY }
}

/// An eye coordinate: anywhere in `range`, or on a node plane (a multiple of
/// 4 voxels) in it.
fn coordinate(range: std::ops::Range<f64>) -> impl Strategy<Value = f64> {
    let planes = (range.start / 4.0).ceil() as i32..=(range.end / 4.0).floor() as i32;
    prop_oneof![
        3 => range,
        1 => planes.prop_map(|k| f64::from(4 * k)),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    /// Random eyes, accuracies and view directions over a 33 × 17 × 9 cloud
    /// (a forest of 4 × 2 × 1 roots), half the time with the cloud preset's
    /// zero-opacity test (else a transfer function that prunes nothing) and
    /// half the time with frustum culling: e' follows Eq. 1 and Eq. 6 and is
    /// in [0, 1], every vertex is finite with its morphed scalar in [0, 1],
    /// every visible voxel is covered by exactly one leaf and no voxel twice,
    /// and there are no cracks (one value per point, T-vertices on the
    /// coarser cell's field).
    #[test]
    fn random_eyes_with_culling_give_finite_crack_free_batches(
        eye in (coordinate(-12.0..44.0), coordinate(-12.0..28.0), coordinate(-8.0..16.0)),
        look in prop::array::uniform3(-1.0..1.0f64),
        c in prop::sample::select(vec![0.0, 1.0, 4.0, 16.0, 64.0, 1e3, f64::INFINITY]),
        use_frustum in any::<bool>(),
        prune in any::<bool>(),
    ) {
        let layer = cloud_grid([33, 17, 9], 1.0, 3, Edge::Soft);
        let layer = DensityGrid::new(layer.dims(), DVec3::ONE, DVec3::ZERO, layer.values().to_vec())
            .unwrap();
        let h = VolumeHierarchy::new(&layer, C_MIN).unwrap();
        let transfer = if prune { cloud_transfer(0.25) } else { never_transparent() };
        let eye = DVec3::new(eye.0, eye.1, eye.2);
        let direction = DVec3::from(look).try_normalize().unwrap_or(DVec3::NEG_Z);
        let up = if direction.cross(DVec3::Y).length() > 1e-3 { DVec3::Y } else { DVec3::Z };
        let frustum = Frustum::from_view_projection(
            DMat4::perspective_infinite_reverse_rh(1.0, 4.0 / 3.0, 0.1)
                * DMat4::look_to_rh(eye, direction, up),
        )
        .unwrap();
        let frustum = use_frustum.then_some(&frustum);
        let r = refine(
            &h,
            &view(eye, frustum),
            &transfer,
            &RefinementSettings::new(LodCriterion::distance(c)),
        )
        .unwrap();
        let batch = lod_batch(&h, &r, &view(eye, frustum)).unwrap();
        // Six cells per leaf, but none for a transparent leaf whose field
        // stays transparent.
        let (transparent, shown): (Vec<&NodeMorph>, Vec<&NodeMorph>) =
            r.leaves.iter().partition(|n| n.transparent[0]);
        prop_assert_eq!(batch.len() % 6, 0);
        prop_assert!(batch.len() >= 6 * shown.len() && batch.len() <= 6 * r.leaves.len());
        prop_assert_eq!(transparent.len(), r.stats.transparent_leaves);
        prop_assert!(prune || transparent.is_empty());
        assert_morph_factors(&r);
        // A transparent leaf: e' = 0, its range transparent, its parent
        // drawn refined.
        for n in &transparent {
            let [s_lo, s_hi] = h.scalar_range(n.node);
            prop_assert!(transfer.is_transparent(f64::from(s_lo), f64::from(s_hi)));
            prop_assert!(n.morph == 0.0 && n.node.level < h.root_level());
            prop_assert!(r.refined.iter().any(|p| p.node == n.node.parent()));
        }

        // Eq. 1 and Eq. 6: refined iff e > 1, e' = clamp(e − 1, 0, 1).
        for n in r.refined.iter().chain(shown.iter().copied()) {
            let e = error_metric(&h, n.node, eye, c);
            let expected = (e - 1.0).clamp(0.0, 1.0);
            prop_assert!((f64::from(n.morph) - expected).abs() < 1e-5, "{:?}: e = {}", n, e);
        }
        for n in &r.refined {
            prop_assert!(error_metric(&h, n.node, eye, c) > 1.0 - 1e-12, "{:?}", n);
        }
        for n in shown.iter().filter(|n| n.node.level > 0) {
            prop_assert!(error_metric(&h, n.node, eye, c) <= 1.0 + 1e-12, "{:?}", n);
        }

        // Tiling of what is visible.
        let cover = coverage(&h, &r);
        let v = h.dims().map(|n| n - 1);
        for k in 0..v[2] {
            for j in 0..v[1] {
                for i in 0..v[0] {
                    let voxel = Node { level: 0, origin: [i, j, k] };
                    let [s_lo, s_hi] = h.scalar_range(voxel);
                    let (lo, hi) = node_box(voxel);
                    let visible = !transfer.is_transparent(f64::from(s_lo), f64::from(s_hi))
                        && frustum.is_none_or(|f| f.intersects_aabb(lo, hi));
                    let count = cover[i + v[0] * (j + v[1] * k)];
                    prop_assert!(count <= 1, "voxel {:?} covered {} times", [i, j, k], count);
                    prop_assert!(!visible || count == 1, "visible voxel {:?} not drawn", [i, j, k]);
                }
            }
        }

        let values = assert_finite_and_conforming(&batch, DVec3::ZERO, DVec3::new(32.0, 16.0, 8.0));
        assert_no_t_vertex_cracks(&batch, &values);
    }
}

/// The wind's keyframes, drawn as the volume plugin draws them: the cloud
/// of the popping test, its noise drifting through its envelope at one voxel
/// per second (2 world units per second), keyframes at `k·T`; a still camera;
/// each pair refined again every `1/REFINEMENT_STEPS` of the interval for the
/// blends from the step's start (`REFINEMENT_SPAN`), at the popping test's
/// screen error, and drawn at
/// every frame's blend (60 frames per second, a quarter interval past a
/// hand-over). The largest per-pixel change between consecutive frames stays
/// under the popping test's bound, inside a refinement step, across one and
/// at the hand-over; with morphing off it is at least 1.5 times larger (the
/// test can fail); the exact blend at full resolution (the floor) changes by
/// less than half the bound.
#[test]
fn wind_keyframes_change_consecutive_frames_less_than_the_popping_bound() {
    use nebel_lod::octree::keyframe::{REFINEMENT_SPAN, REFINEMENT_STEPS};
    const BOUND: f64 = 0.0125;
    const FRAME_RATE: f64 = 60.0;
    let dims = [17; 3];
    let wind = DVec3::new(2.0, 0.0, 0.8);
    let transfer = cloud_transfer(0.15);
    let size = [40, 30];
    let eye = path_eye(40);
    let cam = camera(eye, DVec3::ZERO, 20.0, size);
    let view = projected_view(eye, DVec3::ZERO, 20.0, size);
    let criterion = LodCriterion::screen_error(0.03);
    for (interval, check_unmorphed) in [(2.0f64, true), (4.0, false)] {
        let grids: Vec<DensityGrid> = (0..3)
            .map(|k| drifting_cloud_grid(dims, 2.0, 1, Edge::Soft, wind * (k as f64 * interval)))
            .collect();
        let keyframes: Vec<VolumeHierarchy> = grids
            .iter()
            .map(|g| VolumeHierarchy::new(g, C_MIN).unwrap())
            .collect();
        let pairs = [
            keyframes[0].with_next_keyframe(&keyframes[1]).unwrap(),
            keyframes[1].with_next_keyframe(&keyframes[2]).unwrap(),
        ];
        let quantised: Vec<DensityGrid> = keyframes
            .iter()
            .map(VolumeHierarchy::quantised_grid)
            .collect();
        // (pair, refinement step) → batch with morphing on and off.
        let mut batches: HashMap<(usize, u32), [Cells; 2]> = HashMap::new();
        let mut floor = 0.0f64;
        // [morphed, unmorphed] × [inside a step, across one, at the hand-over].
        let mut largest = [[0.0f64; 3]; 2];
        let mut previous: Option<((usize, u32), LinearImage, [LinearImage; 2])> = None;
        for frame in 0..(1.25 * interval * FRAME_RATE) as usize {
            let time = frame as f64 / FRAME_RATE;
            let pair = (time / interval).floor() as usize;
            let blend = (time / interval - pair as f64) as f32;
            let step = (blend * REFINEMENT_STEPS as f32).floor() as u32;
            let batch = batches.entry((pair, step)).or_insert_with(|| {
                let settings = RefinementSettings {
                    blend: step as f32 / REFINEMENT_STEPS as f32,
                    blend_span: REFINEMENT_SPAN,
                    ..RefinementSettings::new(criterion)
                };
                [true, false]
                    .map(|morph| lod_in(&pairs[pair], &transfer, &view, &settings, morph).1)
            });
            let images = [0, 1].map(|i| image(&batch[i].blended(blend), &transfer, cam));
            let (current, next) = (&quantised[pair], &quantised[pair + 1]);
            let exact_blend = DensityGrid::new(
                dims,
                current.spacing(),
                current.origin(),
                current
                    .values()
                    .iter()
                    .zip(next.values())
                    .map(|(a, b)| (1.0 - blend) * a + blend * b)
                    .collect(),
            )
            .unwrap();
            let exact = image(&full(&exact_blend, &transfer, eye), &transfer, cam);
            if let Some((last_key, last_exact, last_images)) = &previous {
                floor = floor.max(max_change(&exact, last_exact));
                let kind = if *last_key == (pair, step) {
                    0
                } else if last_key.0 == pair {
                    1
                } else {
                    2
                };
                for i in 0..2 {
                    largest[i][kind] =
                        largest[i][kind].max(max_change(&images[i], &last_images[i]));
                }
            }
            previous = Some(((pair, step), exact, images));
        }
        eprintln!(
            "wind keyframes T = {interval} s, {} batches: largest change between frames inside a refinement step / across one / at the hand-over {:.4} / {:.4} / {:.4} (morphing off {:.4} / {:.4} / {:.4}), exact blend (floor) {floor:.4}, bound {BOUND}",
            batches.len(),
            largest[0][0],
            largest[0][1],
            largest[0][2],
            largest[1][0],
            largest[1][1],
            largest[1][2],
        );
        let [morphed, unmorphed] = largest.map(|l| l.into_iter().fold(0.0, f64::max));
        assert!(
            morphed < BOUND,
            "T = {interval} s: largest change {morphed:.4} ≥ bound {BOUND}"
        );
        assert!(
            largest[0][2] > 0.0,
            "T = {interval} s: the hand-over was reached"
        );
        if check_unmorphed {
            assert!(
                unmorphed >= 1.5 * morphed,
                "T = {interval} s: without morphing {unmorphed:.4} is not 1.5× the morphed {morphed:.4}"
            );
        }
        assert!(
            floor < 0.5 * BOUND,
            "T = {interval} s: floor {floor:.4} is not below half the bound"
        );
    }
}
