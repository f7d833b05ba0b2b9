//! A density grid drawn whole by ray casting through its voxels' tetrahedra.
//!
//! A [`CellGrid`] is a grid's Kuhn tetrahedra (six per voxel,
//! [`nebel_core::cell::KUHN_TETRAHEDRA`]) without emitting them: a renderer
//! walks each pixel's ray through the voxels (Amanatides and Woo, "A Fast
//! Voxel Traversal Algorithm for Ray Tracing", 1987) and splits each voxel's
//! stretch where the ray crosses the planes `u_a = u_b` between Kuhn's
//! tetrahedra. The pieces are exactly the ray's segments through the cells,
//! front to back for any eye, with the field linear along each: the
//! pre-integrated segments of sorted cell projection (Röttger 2004 ch. 9), with
//! no visibility order to build and no cell to rasterise. The renderer stops a
//! ray once it is opaque (Krüger and Westermann 2003).
//!
//! Bricks of voxels whose scalar range has zero opacity under the transfer
//! function ([`CellGrid::with_occupancy`], the zero-opacity test of Röttger
//! and Ertl 2003 §4.1) are marked empty, and the renderer shades none of
//! their pieces: exact, since their segments have no opacity and emit
//! nothing.
//!
//! A lit cloud's grid carries a second field at the same points, the
//! segment-length modulator ([`CellGrid::with_modulators`]; the light and the
//! density of Röttger and Ertl 2003 §5, as [`crate::Cells`] describes): it is
//! linear over the same tetrahedra, so each piece has its value at both
//! ends too. Where the modulator is the density (§5.1, `l' = l · f`), the
//! opacity is zero exactly where the density is, and the bricks are tested
//! on it ([`CellGrid::with_modulator_occupancy`]).
//!
//! A grid of two keyframes ([`CellGrid::with_next_keyframe`], a cloud in the
//! wind or a light field under a moving sun) carries both fields at its
//! points; the renderer draws each point at `(1 − t) current + t next` for
//! the batch's mix factor `t` ([`crate::Cells::mix_factor`]), still linear
//! over the same tetrahedra. Its bricks are tested on the range spanning
//! both keyframes ([`BrickTable::spanning`]), which holds every mix.
//!
//! [`CellGrid::segments`] is that traversal on the CPU: the model the shader
//! follows, tested against the tetrahedra's own intersections.

use std::sync::Arc;

use glam::{DAffine3, DVec3, Vec3};
use nebel_core::cell::{CellSegment, Ray, kuhn_value};
use nebel_core::field::DensityGrid;
use nebel_core::transfer::TransferFunction;

use crate::full_resolution::{BatchError, BrickTable, index_maps};

/// A density grid placed in the world, drawn whole (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct CellGrid {
    grid: Arc<DensityGrid>,
    world_from_index: DAffine3,
    index_from_world: DAffine3,
    /// Voxels per brick edge of the occupancy.
    brick_size: usize,
    /// Bricks per axis.
    bricks: [usize; 3],
    /// Per brick (x fastest), 1 where it may have opacity, 0 where empty.
    occupied: Vec<u32>,
    /// The transfer function has no opacity on `[0, clear_below]`
    /// (negative where it has some at 0).
    clear_below: f32,
    /// The segment-length modulator at the same points, if any.
    modulators: Option<Arc<DensityGrid>>,
    /// The occupancy and `clear_below` are over the modulators (their
    /// opacity) instead of the scalars.
    clears_modulators: bool,
    /// The next keyframe's scalars and modulators, for a blended grid.
    next: Option<NextKeyframe>,
}

/// A blended grid's fields at its next keyframe.
#[derive(Clone, Debug, PartialEq)]
struct NextKeyframe {
    scalars: Arc<DensityGrid>,
    modulators: Option<Arc<DensityGrid>>,
}

impl CellGrid {
    /// The grid placed by `world_from_local`; an error when the placement is
    /// not finite and invertible.
    pub fn new(grid: Arc<DensityGrid>, world_from_local: DAffine3) -> Result<Self, BatchError> {
        let (world_from_index, index_from_world) =
            index_maps(grid.origin(), grid.spacing(), world_from_local).ok_or(
                BatchError::SingularTransform {
                    determinant: world_from_local.matrix3.determinant(),
                },
            )?;
        let voxels = grid.dims().map(|n| n - 1);
        Ok(Self {
            grid,
            world_from_index,
            index_from_world,
            brick_size: voxels.into_iter().max().unwrap_or(1),
            bricks: [1; 3],
            occupied: vec![1],
            clear_below: -1.0,
            modulators: None,
            clears_modulators: false,
            next: None,
        })
    }

    /// The grid blending toward `next`, the same grid's fields at the next
    /// keyframe (module docs; its placement and occupancy are not read); an
    /// error when its points differ or only one of the two has modulators.
    /// Give the occupancy a table spanning both keyframes.
    pub fn with_next_keyframe(self, next: &CellGrid) -> Result<Self, BatchError> {
        if next.grid.dims() != self.grid.dims()
            || next.modulators.is_some() != self.modulators.is_some()
        {
            return Err(BatchError::KeyframeMismatch {
                current: self.grid.dims(),
                current_modulated: self.modulators.is_some(),
                next: next.grid.dims(),
                next_modulated: next.modulators.is_some(),
            });
        }
        Ok(Self {
            next: Some(NextKeyframe {
                scalars: next.grid.clone(),
                modulators: next.modulators.clone(),
            }),
            ..self
        })
    }

    /// Whether the grid blends toward a next keyframe.
    pub fn is_blended(&self) -> bool {
        self.next.is_some()
    }

    /// The next keyframe's scalars and modulators, for a blended grid.
    pub fn next_keyframe(&self) -> Option<(&DensityGrid, Option<&DensityGrid>)> {
        self.next
            .as_ref()
            .map(|next| (next.scalars.as_ref(), next.modulators.as_deref()))
    }

    /// The grid as drawn at mix factor `t` (clamped to [0, 1], NaN as 0):
    /// every field at `(1 − t) current + t next`, not blended; a grid that
    /// is not blended as it is.
    pub fn blended(&self, t: f32) -> Self {
        let Some(next) = &self.next else {
            return self.clone();
        };
        let mix = |current: &DensityGrid, next: &DensityGrid| {
            Arc::new(
                current
                    .mixed(next, t)
                    .expect("with_next_keyframe checked that the keyframes share their points"),
            )
        };
        Self {
            grid: mix(&self.grid, &next.scalars),
            modulators: self
                .modulators
                .as_ref()
                .zip(next.modulators.as_ref())
                .map(|(current, next)| mix(current, next)),
            next: None,
            ..self.clone()
        }
    }

    /// The grid with `modulators`, the segment-length modulator at its points
    /// (module docs); an error when they are not on a grid of the same
    /// points.
    pub fn with_modulators(self, modulators: Arc<DensityGrid>) -> Result<Self, BatchError> {
        if modulators.dims() != self.grid.dims() {
            return Err(BatchError::ModulatorMismatch {
                scalars: self.grid.dims(),
                modulators: modulators.dims(),
            });
        }
        Ok(Self {
            modulators: Some(modulators),
            ..self
        })
    }

    /// The grid with its bricks of `bricks` (a table of this grid) marked
    /// empty where `transfer` has zero opacity over their scalar range, and
    /// the scalar below which `transfer` has none
    /// ([`CellGrid::clear_below`]); an error when the table is another
    /// grid's.
    pub fn with_occupancy(
        self,
        bricks: &BrickTable,
        transfer: &TransferFunction,
    ) -> Result<Self, BatchError> {
        let clear = clear_below(transfer);
        self.with_bricks(bricks, clear, false, |[low, high]| {
            transfer.is_transparent(f64::from(low), f64::from(high))
        })
    }

    /// The grid with its bricks of `bricks` (a table of the modulators)
    /// marked empty where the modulator is at most 0 throughout, for a
    /// modulator that carries the opacity (the density of §5.1: a piece's
    /// optical depth is its length times the mean modulator, so none where
    /// the modulator is 0 at both ends); [`CellGrid::clear_below`] is then 0,
    /// over the modulators. An error without modulators
    /// ([`BatchError::ModulatorMismatch`]) or when the table is another
    /// grid's.
    pub fn with_modulator_occupancy(self, bricks: &BrickTable) -> Result<Self, BatchError> {
        if self.modulators.is_none() {
            return Err(BatchError::ModulatorMismatch {
                scalars: self.grid.dims(),
                modulators: [0; 3],
            });
        }
        self.with_bricks(bricks, 0.0, true, |[_, high]| high <= 0.0)
    }

    /// The grid with the bricks of `bricks` whose `[low, high]` range is
    /// `empty` marked so, nothing at or below `clear_below` (over the
    /// modulators where `clears_modulators`); an error when the table is
    /// another grid's.
    fn with_bricks(
        self,
        bricks: &BrickTable,
        clear_below: f32,
        clears_modulators: bool,
        empty: impl Fn([f32; 2]) -> bool,
    ) -> Result<Self, BatchError> {
        let voxels = self.voxels();
        if bricks.voxels() != voxels {
            return Err(BatchError::BrickTableMismatch {
                table: bricks.voxels(),
                grid: voxels,
            });
        }
        let counts = bricks.brick_counts();
        let mut occupied = Vec::with_capacity(counts.iter().product());
        for bz in 0..counts[2] {
            for by in 0..counts[1] {
                for bx in 0..counts[0] {
                    let range = bricks.scalar_range([bx, by, bz]).unwrap_or([0.0, 1.0]);
                    occupied.push(u32::from(!empty(range)));
                }
            }
        }
        Ok(Self {
            brick_size: bricks.brick_size(),
            bricks: counts,
            occupied,
            clear_below,
            clears_modulators,
            ..self
        })
    }

    /// The segment-length modulator at the grid's points, if any.
    pub fn modulators(&self) -> Option<&DensityGrid> {
        self.modulators.as_deref()
    }

    /// Whether the occupancy and [`CellGrid::clear_below`] are over the
    /// modulators ([`CellGrid::with_modulator_occupancy`]) instead of the
    /// scalars.
    pub fn clears_modulators(&self) -> bool {
        self.clears_modulators
    }

    /// A scalar below which the transfer function of
    /// [`CellGrid::with_occupancy`] has no opacity: a voxel whose corners
    /// are all at most this adds nothing (negative without a transfer
    /// function or with opacity at 0). Over the modulators where
    /// [`CellGrid::clears_modulators`].
    pub fn clear_below(&self) -> f32 {
        self.clear_below
    }

    /// Voxels per brick edge of the occupancy.
    pub fn brick_size(&self) -> usize {
        self.brick_size
    }

    /// Bricks per axis of the occupancy.
    pub fn brick_counts(&self) -> [usize; 3] {
        self.bricks
    }

    /// Per brick (x fastest), 1 where it may have opacity, 0 where it has
    /// none; one brick over the whole grid without
    /// [`CellGrid::with_occupancy`].
    pub fn occupied(&self) -> &[u32] {
        &self.occupied
    }

    /// The grid.
    pub fn grid(&self) -> &DensityGrid {
        &self.grid
    }

    /// World position of grid point `(i, j, k)` at `(i, j, k)`.
    pub fn world_from_index(&self) -> DAffine3 {
        self.world_from_index
    }

    /// Grid index coordinates of a world position.
    pub fn index_from_world(&self) -> DAffine3 {
        self.index_from_world
    }

    /// Voxels per axis.
    pub fn voxels(&self) -> [usize; 3] {
        self.grid.dims().map(|n| n - 1)
    }

    /// The grid's tetrahedra: six per voxel.
    pub fn cell_count(&self) -> usize {
        6 * self.voxels().iter().product::<usize>()
    }

    /// The world-space box around the grid.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let n = self.voxels().map(|v| v as f64);
        (0..8)
            .map(|corner| {
                let pick = |axis: usize| {
                    if corner >> axis & 1 == 0 {
                        0.0
                    } else {
                        n[axis]
                    }
                };
                self.world_from_index
                    .transform_point3(DVec3::new(pick(0), pick(1), pick(2)))
                    .as_vec3()
            })
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), p| {
                (lo.min(p), hi.max(p))
            })
    }

    /// The segments of `ray` (world space; `t` in units of its direction)
    /// through the grid's tetrahedra between `t_min` and `t_max`, front to
    /// back: per voxel the ray crosses, its stretch split where it crosses
    /// the planes between Kuhn's tetrahedra, with the linear field's value
    /// at both ends. Zero-length pieces are left out.
    pub fn segments(&self, ray: &Ray, t_min: f64, t_max: f64) -> Vec<CellSegment> {
        self.field_segments(&self.grid, ray, t_min, t_max)
    }

    /// [`CellGrid::segments`] with the modulator's values at their ends
    /// instead of the scalar's; none without modulators.
    pub fn modulator_segments(&self, ray: &Ray, t_min: f64, t_max: f64) -> Vec<CellSegment> {
        self.modulators.as_ref().map_or_else(Vec::new, |field| {
            self.field_segments(field, ray, t_min, t_max)
        })
    }

    /// The pieces of `ray` with the values of `field`, a grid of the same
    /// points.
    fn field_segments(
        &self,
        field: &DensityGrid,
        ray: &Ray,
        t_min: f64,
        t_max: f64,
    ) -> Vec<CellSegment> {
        let origin = self.index_from_world.transform_point3(ray.origin);
        let step = self.index_from_world.transform_vector3(ray.direction);
        let voxels = self.voxels();
        let mut segments = Vec::new();
        let (mut t_entry, mut t_exit) = (t_min, t_max);
        for axis in 0..3 {
            let n = voxels[axis] as f64;
            if step[axis] == 0.0 {
                if !(0.0..=n).contains(&origin[axis]) {
                    return segments;
                }
                continue;
            }
            let (a, b) = (-origin[axis] / step[axis], (n - origin[axis]) / step[axis]);
            t_entry = t_entry.max(a.min(b));
            t_exit = t_exit.min(a.max(b));
        }
        if t_entry.partial_cmp(&t_exit) != Some(std::cmp::Ordering::Less) {
            return segments;
        }
        // The voxel the ray enters: on a grid plane, the one it moves into.
        let entry = origin + t_entry * step;
        let mut voxel = [0i64; 3];
        let mut next = [f64::INFINITY; 3];
        for axis in 0..3 {
            let p = entry[axis];
            let cell = if step[axis] < 0.0 && p == p.floor() {
                p - 1.0
            } else {
                p.floor()
            };
            voxel[axis] = (cell as i64).clamp(0, voxels[axis] as i64 - 1);
            if step[axis] != 0.0 {
                let boundary = (voxel[axis] + i64::from(step[axis] > 0.0)) as f64;
                next[axis] = (boundary - origin[axis]) / step[axis];
            }
        }
        let mut t = t_entry;
        while t < t_exit {
            let axis = (0..3)
                .min_by(|&a, &b| next[a].total_cmp(&next[b]))
                .unwrap_or(0);
            let end = next[axis].min(t_exit);
            if end > t {
                voxel_segments(field, voxel, origin, step, [t, end], &mut segments);
            }
            t = t.max(end);
            voxel[axis] += if step[axis] > 0.0 { 1 } else { -1 };
            if !(0..voxels[axis] as i64).contains(&voxel[axis]) {
                break;
            }
            next[axis] += 1.0 / step[axis].abs();
        }
        segments
    }
}

/// The pieces of the stretch `[t0, t1]` of the ray through `voxel`, with
/// the values of `field`.
fn voxel_segments(
    field: &DensityGrid,
    voxel: [i64; 3],
    origin: DVec3,
    step: DVec3,
    [t0, t1]: [f64; 2],
    segments: &mut Vec<CellSegment>,
) {
    let corner = DVec3::new(voxel[0] as f64, voxel[1] as f64, voxel[2] as f64);
    let local = origin - corner;
    let values: [f64; 8] = std::array::from_fn(|c| {
        let [i, j, k] = [0, 1, 2].map(|axis| voxel[axis] as usize + (c >> axis & 1));
        f64::from(field.value(i, j, k))
    });
    let mut breaks = [t1; 3];
    for (slot, (a, b)) in [(0, 1), (1, 2), (0, 2)].into_iter().enumerate() {
        let rate = step[a] - step[b];
        if rate != 0.0 {
            let t = -(local[a] - local[b]) / rate;
            if t > t0 && t < t1 {
                breaks[slot] = t;
            }
        }
    }
    breaks.sort_by(f64::total_cmp);
    let at = |t: f64| kuhn_value(&values, (local + t * step).clamp(DVec3::ZERO, DVec3::ONE));
    let mut start = t0;
    for end in breaks.into_iter().chain([t1]) {
        if end > start {
            segments.push(CellSegment {
                t_entry: start,
                t_exit: end,
                s_entry: at(start),
                s_exit: at(end),
            });
            start = end;
        }
    }
}

/// The largest f32 `s` with no opacity of `transfer` on `[0, s]` (to 2⁻⁴⁰,
/// rounded down), or −1 when it has opacity at 0.
fn clear_below(transfer: &TransferFunction) -> f32 {
    if !transfer.is_transparent(0.0, 0.0) {
        return -1.0;
    }
    let (mut clear, mut opaque) = (0.0f64, 2.0f64);
    for _ in 0..40 {
        let middle = 0.5 * (clear + opaque);
        if transfer.is_transparent(0.0, middle) && middle <= 1.0 {
            clear = middle;
        } else {
            opaque = middle;
        }
    }
    let rounded = clear as f32;
    if f64::from(rounded) > clear {
        rounded.next_down()
    } else {
        rounded
    }
}

#[cfg(test)]
mod tests {
    use glam::DMat3;
    use nebel_core::cell::Tetrahedron;
    use proptest::prelude::*;

    use super::*;

    /// The segments of `ray` through `cells` (world space) clipped to
    /// `[t_min, t_max]`, by the tetrahedra's own intersection, in order.
    fn tetrahedra_segments(
        cells: &[Tetrahedron],
        ray: &Ray,
        t_min: f64,
        t_max: f64,
    ) -> Vec<CellSegment> {
        let mut segments: Vec<CellSegment> = cells
            .iter()
            .filter_map(|cell| cell.intersect(ray))
            .filter_map(|s| {
                let (a, b) = (s.t_entry.max(t_min), s.t_exit.min(t_max));
                let at = |t: f64| {
                    s.s_entry + (s.s_exit - s.s_entry) * (t - s.t_entry) / (s.t_exit - s.t_entry)
                };
                (b - a > 1e-9).then(|| CellSegment {
                    t_entry: a,
                    t_exit: b,
                    s_entry: at(a),
                    s_exit: at(b),
                })
            })
            .collect();
        segments.sort_by(|a, b| a.t_entry.total_cmp(&b.t_entry));
        segments
    }

    fn placed(tetrahedron: &Tetrahedron, world_from_local: DAffine3) -> Tetrahedron {
        Tetrahedron {
            positions: tetrahedron
                .positions
                .map(|p| world_from_local.transform_point3(p)),
            ..*tetrahedron
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]

        /// For any grid, placement (rotated, sheared, mirrored) and ray, from
        /// inside or outside, the traversal gives the tetrahedra's segments
        /// in front-to-back order, with their scalars.
        #[test]
        fn the_traversal_gives_every_tetrahedron_segment_in_order(
            dims in prop::array::uniform3(2usize..6),
            spacing in prop::array::uniform3(0.2f64..3.0),
            origin in prop::array::uniform3(-5.0f64..5.0),
            values in prop::collection::vec(0.0f32..=1.0, 216),
            modulator_values in prop::collection::vec(0.0f32..=1.0, 216),
            linear in prop::array::uniform9(-2.0f64..2.0),
            eye in prop::array::uniform3(-12.0f64..12.0),
            target in prop::array::uniform3(0.0f64..1.0),
            clip in (0.0f64..6.0, 4.0f64..60.0),
        ) {
            let count = dims.iter().product::<usize>();
            let grid = DensityGrid::new(dims, DVec3::from(spacing), DVec3::from(origin), values[..count].to_vec())
                .expect("valid grid");
            let matrix = DMat3::from_cols_array(&linear);
            prop_assume!(matrix.determinant().abs() > 0.05);
            let world_from_local = DAffine3::from_mat3_translation(matrix, DVec3::new(1.0, -2.0, 0.5));
            // Toward a point of the grid, so every ray meets it.
            let inside = grid.origin() + DVec3::from(target) * (grid.max_corner() - grid.origin());
            let ray = Ray::new(DVec3::from(eye), world_from_local.transform_point3(inside) - DVec3::from(eye))
                .expect("a direction");
            let (t_min, t_max) = (clip.0, clip.0 + clip.1);

            let modulators = DensityGrid::new(dims, DVec3::from(spacing), DVec3::from(origin), modulator_values[..count].to_vec())
                .expect("valid grid");
            let placed_cells = |grid: &DensityGrid| -> Vec<Tetrahedron> {
                grid.tetrahedra().iter().map(|t| placed(t, world_from_local)).collect()
            };
            let expected = tetrahedra_segments(&placed_cells(&grid), &ray, t_min, t_max);
            let expected_modulators = tetrahedra_segments(&placed_cells(&modulators), &ray, t_min, t_max);
            let grid = CellGrid::new(Arc::new(grid), world_from_local)
                .expect("invertible")
                .with_modulators(Arc::new(modulators))
                .expect("the same points");
            let pieces = |segments: Vec<CellSegment>| -> Vec<CellSegment> {
                segments.into_iter().filter(|s| s.t_exit - s.t_entry > 1e-9).collect()
            };
            for (traversed, expected) in [
                (pieces(grid.segments(&ray, t_min, t_max)), expected),
                (pieces(grid.modulator_segments(&ray, t_min, t_max)), expected_modulators),
            ] {
                prop_assert_eq!(traversed.len(), expected.len());
                for (got, want) in traversed.iter().zip(&expected) {
                    for (g, w) in [
                        (got.t_entry, want.t_entry),
                        (got.t_exit, want.t_exit),
                        (got.s_entry, want.s_entry),
                        (got.s_exit, want.s_exit),
                    ] {
                        prop_assert!((g - w).abs() < 1e-7, "{got:?} against {want:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn a_ray_along_a_grid_plane_and_a_missing_ray_are_handled() {
        let grid = DensityGrid::new(
            [3, 3, 3],
            DVec3::ONE,
            DVec3::ZERO,
            (0..27).map(|i| i as f32 / 26.0).collect(),
        )
        .expect("valid grid");
        let grid = CellGrid::new(Arc::new(grid), DAffine3::IDENTITY).expect("invertible");
        // Along the plane y = 1, z = 1 (an edge of four voxels): one voxel
        // row, pieces covering [1, 3] once.
        let ray = Ray::new(DVec3::new(-1.0, 1.0, 1.0), DVec3::X).expect("a direction");
        let segments = grid.segments(&ray, 0.0, 10.0);
        let covered: f64 = segments.iter().map(|s| s.t_exit - s.t_entry).sum();
        assert!((covered - 2.0).abs() < 1e-12, "{segments:?}");
        assert!(segments.windows(2).all(|w| w[0].t_exit == w[1].t_entry));
        // The field along it is linear in x: value at (x, 1, 1).
        let linear = |x: f64| (x + 3.0 + 9.0) / 26.0;
        for s in &segments {
            assert!((s.s_entry - linear(s.t_entry - 1.0)).abs() < 1e-6);
        }
        let away = Ray::new(DVec3::new(-1.0, 5.0, 1.0), DVec3::X).expect("a direction");
        assert!(grid.segments(&away, 0.0, 10.0).is_empty());
        assert_eq!(grid.cell_count(), 48);
        assert_eq!(grid.bounds(), (Vec3::ZERO, Vec3::splat(2.0)));
    }

    /// `count` rays from in front of the 13 × 9 × 11 test grids toward
    /// points spread through them.
    fn rays_through_the_test_grid(count: usize) -> impl Iterator<Item = Ray> {
        (0..count).map(|n| {
            let f = n as f64;
            let eye = DVec3::new(-3.0 + (f * 0.37) % 18.0, -2.0 + (f * 0.71) % 13.0, -4.0);
            let target = DVec3::new((f * 0.53) % 12.0, (f * 0.29) % 8.0, (f * 0.61) % 10.0);
            Ray::new(eye, target - eye).expect("a direction")
        })
    }

    /// A transfer function with no opacity below s = 0.4.
    fn opaque_above_0_4() -> TransferFunction {
        let point = |s: f32, rho: f32| nebel_core::transfer::ControlPoint {
            s,
            kappa: [1.0; 3],
            rho,
        };
        TransferFunction::new([point(0.0, 0.0), point(0.4, 0.0), point(1.0, 3.0)])
            .expect("valid points")
    }

    #[test]
    fn every_piece_in_an_empty_brick_has_no_opacity() {
        // 13 × 9 × 11 points, dense only where x > 6.
        let dims = [13, 9, 11];
        let values = (0..dims.iter().product::<usize>())
            .map(|n| {
                let x = n % dims[0];
                if x > 6 {
                    0.3 + 0.05 * (n % 13) as f32
                } else {
                    0.1 + 0.02 * (n % 7) as f32
                }
            })
            .collect();
        let grid =
            Arc::new(DensityGrid::new(dims, DVec3::ONE, DVec3::ZERO, values).expect("valid"));
        let transfer = opaque_above_0_4();
        let table = BrickTable::new(&grid, 4);
        let cells = CellGrid::new(grid.clone(), DAffine3::IDENTITY)
            .expect("invertible")
            .with_occupancy(&table, &transfer)
            .expect("the grid's table");
        assert_eq!(cells.brick_counts(), [3, 2, 3]);
        let clear = f64::from(cells.clear_below());
        assert!((clear - f64::from(0.4f32)).abs() < 1e-9, "{clear}");
        assert!(transfer.is_transparent(0.0, clear) && !transfer.is_transparent(0.0, clear + 1e-6));
        let point = |s: f32, rho: f32| nebel_core::transfer::ControlPoint {
            s,
            kappa: [1.0; 3],
            rho,
        };
        let dense =
            TransferFunction::new([point(0.0, 1.0), point(1.0, 2.0)]).expect("valid points");
        let unclear = CellGrid::new(grid.clone(), DAffine3::IDENTITY).unwrap();
        assert!(unclear.clear_below() < 0.0);
        assert!(
            unclear
                .with_occupancy(&table, &dense)
                .unwrap()
                .clear_below()
                < 0.0
        );
        let brick_of = |p: DVec3| {
            let [x, y, z] = [p.x, p.y, p.z].map(|c| (c.max(0.0) as usize / 4).min(2));
            x + 3 * (y.min(1) + 2 * z)
        };
        // Bricks x = 0 and 1 cover points 0..=8 in x, which reach the dense
        // side only in brick 1 (points 4..=8).
        for (index, &occupied) in cells.occupied().iter().enumerate() {
            assert_eq!(occupied, u32::from(index % 3 != 0), "brick {index}");
        }
        let mut checked = 0;
        for ray in rays_through_the_test_grid(200) {
            for segment in cells.segments(&ray, 0.0, 100.0) {
                let middle = ray.at(0.5 * (segment.t_entry + segment.t_exit));
                if cells.occupied()[brick_of(middle)] == 0 {
                    checked += 1;
                    assert!(
                        transfer.is_transparent(segment.s_entry, segment.s_exit),
                        "{segment:?}"
                    );
                }
            }
        }
        assert!(checked > 100, "{checked}");
        let other = BrickTable::new(
            &DensityGrid::new([5; 3], DVec3::ONE, DVec3::ZERO, vec![0.5; 125]).unwrap(),
            4,
        );
        assert!(matches!(
            CellGrid::new(grid, DAffine3::IDENTITY)
                .unwrap()
                .with_occupancy(&other, &transfer),
            Err(BatchError::BrickTableMismatch { .. })
        ));
    }

    #[test]
    fn every_piece_in_a_brick_without_density_has_no_opacity() {
        // A lit cloud (§5.1): the light is the scalar, the density the
        // modulator, 0 where x ≤ 6.
        let dims = [13, 9, 11];
        let field = |f: fn(usize, usize) -> f32| {
            let values = (0..dims.iter().product::<usize>())
                .map(|n| f(n % dims[0], n))
                .collect();
            Arc::new(DensityGrid::new(dims, DVec3::ONE, DVec3::ZERO, values).expect("valid"))
        };
        let density = field(|x, n| {
            if x > 6 {
                0.1 + 0.07 * (n % 11) as f32
            } else {
                0.0
            }
        });
        let light = field(|_, n| 0.2 + 0.05 * (n % 9) as f32);
        let table = BrickTable::new(&density, 4);
        let cells = CellGrid::new(light.clone(), DAffine3::IDENTITY)
            .expect("invertible")
            .with_modulators(density.clone())
            .expect("the same points")
            .with_modulator_occupancy(&table)
            .expect("the modulators' table");
        assert!(cells.clears_modulators());
        assert_eq!(cells.clear_below(), 0.0);
        // Bricks x = 0 cover points 0..=4, all without density; x = 1
        // reaches x = 7.
        for (index, &occupied) in cells.occupied().iter().enumerate() {
            assert_eq!(occupied, u32::from(index % 3 != 0), "brick {index}");
        }
        let brick_of = |p: DVec3| {
            let [x, y, z] = [p.x, p.y, p.z].map(|c| (c.max(0.0) as usize / 4).min(2));
            x + 3 * (y.min(1) + 2 * z)
        };
        let mut checked = 0;
        for ray in rays_through_the_test_grid(200) {
            let scalars = cells.segments(&ray, 0.0, 100.0);
            let modulators = cells.modulator_segments(&ray, 0.0, 100.0);
            assert_eq!(scalars.len(), modulators.len());
            for (scalar, modulator) in scalars.iter().zip(&modulators) {
                assert_eq!(
                    (scalar.t_entry, scalar.t_exit),
                    (modulator.t_entry, modulator.t_exit)
                );
                let middle = ray.at(0.5 * (modulator.t_entry + modulator.t_exit));
                if cells.occupied()[brick_of(middle)] == 0 {
                    checked += 1;
                    assert!(
                        modulator.s_entry <= 0.0 && modulator.s_exit <= 0.0,
                        "{modulator:?}"
                    );
                }
            }
        }
        assert!(checked > 100, "{checked}");
        // Modulators on other points, and modulator occupancy without
        // modulators, are refused.
        let other =
            Arc::new(DensityGrid::new([5; 3], DVec3::ONE, DVec3::ZERO, vec![0.5; 125]).unwrap());
        let unmodulated = CellGrid::new(light, DAffine3::IDENTITY).unwrap();
        assert!(matches!(
            unmodulated.clone().with_modulators(other),
            Err(BatchError::ModulatorMismatch { .. })
        ));
        assert!(
            unmodulated
                .modulator_segments(&Ray::new(DVec3::ZERO, DVec3::X).unwrap(), 0.0, 9.0)
                .is_empty()
        );
        assert!(matches!(
            unmodulated.with_modulator_occupancy(&table),
            Err(BatchError::ModulatorMismatch { .. })
        ));
    }

    #[test]
    fn a_blended_grid_draws_every_mix_of_its_keyframes() {
        // Two keyframes of a lit cloud (§5.1): the density moves from x > 8
        // to x > 6 and the light changes; neither has density where x ≤ 4.
        let dims = [13, 9, 11];
        let field = |f: &dyn Fn(usize, usize) -> f32| {
            let values = (0..dims.iter().product::<usize>())
                .map(|n| f(n % dims[0], n))
                .collect();
            Arc::new(DensityGrid::new(dims, DVec3::ONE, DVec3::ZERO, values).expect("valid"))
        };
        let density = |edge: usize| {
            field(&move |x, n| {
                if x > edge {
                    0.1 + 0.07 * (n % 11) as f32
                } else {
                    0.0
                }
            })
        };
        let (first, second) = (density(8), density(6));
        let (first_light, second_light) = (
            field(&|_, n| 0.2 + 0.05 * (n % 9) as f32),
            field(&|_, n| 0.9 - 0.04 * (n % 7) as f32),
        );
        let keyframe = |light: &Arc<DensityGrid>, density: &Arc<DensityGrid>| {
            CellGrid::new(light.clone(), DAffine3::IDENTITY)
                .expect("invertible")
                .with_modulators(density.clone())
                .expect("the same points")
        };
        let bricks = BrickTable::new(&first, 4)
            .spanning(&BrickTable::new(&second, 4))
            .expect("the same grid");
        let pair = keyframe(&first_light, &first)
            .with_next_keyframe(&keyframe(&second_light, &second))
            .expect("the same points")
            .with_modulator_occupancy(&bricks)
            .expect("the modulators' table");
        assert!(pair.is_blended());
        // The second keyframe's density reaches brick x = 1 (x = 7, 8),
        // the first's does not: the pair's occupancy holds both.
        for (index, &occupied) in pair.occupied().iter().enumerate() {
            assert_eq!(occupied, u32::from(index % 3 != 0), "brick {index}");
        }
        let brick_of = |p: DVec3| {
            let [x, y, z] = [p.x, p.y, p.z].map(|c| (c.max(0.0) as usize / 4).min(2));
            x + 3 * (y.min(1) + 2 * z)
        };
        for t in [0.0f32, 0.25, 0.6, 1.0] {
            let drawn = pair.blended(t);
            assert!(!drawn.is_blended());
            let mix = |a: &DensityGrid, b: &DensityGrid| -> Vec<f32> {
                a.values()
                    .iter()
                    .zip(b.values())
                    .map(|(&a, &b)| (1.0 - t) * a + t * b)
                    .collect()
            };
            assert_eq!(drawn.grid().values(), mix(&first_light, &second_light));
            assert_eq!(
                drawn.modulators().map(DensityGrid::values),
                Some(&mix(&first, &second)[..])
            );
            assert_eq!(drawn.occupied(), pair.occupied());
            let mut checked = 0;
            for ray in rays_through_the_test_grid(100) {
                for modulator in drawn.modulator_segments(&ray, 0.0, 100.0) {
                    let middle = ray.at(0.5 * (modulator.t_entry + modulator.t_exit));
                    if pair.occupied()[brick_of(middle)] == 0 {
                        checked += 1;
                        assert!(modulator.s_entry <= 0.0 && modulator.s_exit <= 0.0);
                    }
                }
            }
            assert!(checked > 50, "{checked}");
        }
        assert_eq!(pair.blended(f32::NAN).grid(), first_light.as_ref());
        // A next keyframe on other points, or without modulators, is refused.
        let other =
            Arc::new(DensityGrid::new([5; 3], DVec3::ONE, DVec3::ZERO, vec![0.5; 125]).unwrap());
        for next in [
            keyframe(&other, &other),
            CellGrid::new(second_light, DAffine3::IDENTITY).unwrap(),
        ] {
            assert!(matches!(
                keyframe(&first_light, &first).with_next_keyframe(&next),
                Err(BatchError::KeyframeMismatch { .. })
            ));
        }
    }

    #[test]
    fn a_singular_placement_is_refused() {
        let grid =
            DensityGrid::new([2, 2, 2], DVec3::ONE, DVec3::ZERO, vec![0.5; 8]).expect("valid grid");
        let flat = DAffine3::from_scale(DVec3::new(1.0, 0.0, 1.0));
        assert!(matches!(
            CellGrid::new(Arc::new(grid), flat),
            Err(BatchError::SingularTransform { .. })
        ));
    }
}
