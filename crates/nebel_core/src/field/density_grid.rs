//! [`DensityGrid`]: density samples on a regular 3D grid, trilinear in between.

use glam::DVec3;

use crate::budget::BudgetError;
use crate::cell::{Hexahedron, Tetrahedron};
use crate::pacing::pace;

use super::{
    DENSITY_GRID, FieldError, SAMPLE_BYTES, axis_weight, check_dims, check_finite, check_origin,
    check_points, check_spacing,
};

/// Density samples in [0, 1] at the points of a regular 3D grid, trilinear
/// between them.
///
/// Point `(i, j, k)` sits at `origin + (i, j, k) · spacing` and is stored at
/// index `i + nx · (j + ny · k)`. The grid covers the box from `origin` to
/// `origin + (dims − 1) · spacing`; it has `(nx − 1)(ny − 1)(nz − 1)` cells.
#[derive(Clone, Debug, PartialEq)]
pub struct DensityGrid {
    dims: [usize; 3],
    spacing: DVec3,
    origin: DVec3,
    values: Vec<f32>,
}

/// How many values the validation of a grid checks between two yield points
/// of a paced build (a fraction of a millisecond).
const VALIDATED_PER_PACE: usize = 1 << 18;

impl DensityGrid {
    /// A grid of `dims = [nx, ny, nz]` points (each ≥ 2) with `spacing` (world
    /// units between neighbouring points, > 0) and `origin` (world position of
    /// point (0, 0, 0)). `values` holds `nx · ny · nz` densities in [0, 1],
    /// x fastest.
    pub fn new(
        dims: [usize; 3],
        spacing: DVec3,
        origin: DVec3,
        values: Vec<f32>,
    ) -> Result<Self, FieldError> {
        Self::validated("DensityGrid::new", dims, spacing, origin, values)
    }

    /// The bytes of the samples of a grid of `dims` points (4 per point),
    /// checked against the memory budget: the check every constructor that
    /// builds a grid makes before it allocates, here without building one
    /// (e.g. to validate a description). Errors name a `density grid of
    /// nx × ny × nz points`.
    pub fn check_budget(dims: [usize; 3]) -> Result<u64, BudgetError> {
        check_points(DENSITY_GRID, &dims, SAMPLE_BYTES)
    }

    /// [`DensityGrid::new`] with `name` (a file path or source) in its errors.
    pub(super) fn validated(
        name: &str,
        dims: [usize; 3],
        spacing: DVec3,
        origin: DVec3,
        values: Vec<f32>,
    ) -> Result<Self, FieldError> {
        check_dims(name, &dims, values.len())?;
        check_spacing(name, &spacing.to_array())?;
        check_origin(name, &origin.to_array())?;
        // One branch-free (vectorised) pass over the values, with a yield
        // point for a paced build after every `VALIDATED_PER_PACE` values;
        // the passes that find the first offending value run only when there
        // is one.
        let in_unit_range = values.chunks(VALIDATED_PER_PACE).all(|run| {
            let in_range = run.chunks(4096).all(|chunk| {
                chunk
                    .iter()
                    .fold(true, |in_range, v| in_range & (0.0..=1.0).contains(v))
            });
            pace();
            in_range
        });
        if !in_unit_range {
            check_finite(name, &values)?;
            if let Some(index) = values.iter().position(|v| !(0.0..=1.0).contains(v)) {
                return Err(FieldError::OutOfRange {
                    name: name.to_owned(),
                    index,
                    value: values[index],
                });
            }
        }
        Ok(Self {
            dims,
            spacing,
            origin,
            values,
        })
    }

    /// Points per axis `[nx, ny, nz]`.
    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// World units between neighbouring points, per axis.
    pub fn spacing(&self) -> DVec3 {
        self.spacing
    }

    /// World position of point (0, 0, 0), the box's minimum corner.
    pub fn origin(&self) -> DVec3 {
        self.origin
    }

    /// The box's maximum corner, `origin + (dims − 1) · spacing`.
    pub fn max_corner(&self) -> DVec3 {
        let [nx, ny, nz] = self.dims;
        self.origin + DVec3::new((nx - 1) as f64, (ny - 1) as f64, (nz - 1) as f64) * self.spacing
    }

    /// All densities, x fastest.
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    /// Density at point `(i, j, k)`. Panics when an index is out of range, like
    /// slice indexing.
    pub fn value(&self, i: usize, j: usize, k: usize) -> f32 {
        let [nx, ny, _] = self.dims;
        self.values[i + nx * (j + ny * k)]
    }

    /// The full-resolution tetrahedral field: every grid
    /// cell `(i, j, k)` as a hexahedron split into Kuhn's six tetrahedra
    /// ([`Hexahedron::kuhn_tetrahedra`], the same in every cell), so the mesh
    /// conforms and the octree's coarser cells are nested in it. Returns
    /// `6 (nx − 1)(ny − 1)(nz − 1)` cells, cell by cell, x fastest. Inside each
    /// tetrahedron the scalar is linear: it equals the trilinear field at the
    /// grid points and everywhere when the field is linear.
    pub fn tetrahedra(&self) -> Vec<Tetrahedron> {
        let [nx, ny, nz] = self.dims;
        let mut cells = Vec::with_capacity(6 * (nx - 1) * (ny - 1) * (nz - 1));
        for k in 0..nz - 1 {
            for j in 0..ny - 1 {
                for i in 0..nx - 1 {
                    // Every corner from its own index, so cells that share a
                    // point share its coordinates bit for bit.
                    let corner = |v: usize| [i + (v & 1), j + ((v >> 1) & 1), k + ((v >> 2) & 1)];
                    let hexahedron = Hexahedron {
                        positions: std::array::from_fn(|v| {
                            self.origin + DVec3::from(corner(v).map(|n| n as f64)) * self.spacing
                        }),
                        scalars: std::array::from_fn(|v| {
                            let [ci, cj, ck] = corner(v);
                            f64::from(self.value(ci, cj, ck))
                        }),
                    };
                    cells.extend(hexahedron.kuhn_tetrahedra());
                }
            }
        }
        cells
    }

    /// The grid `(1 − t) · self + t · other`, point by point on `self`'s
    /// geometry (two keyframes of one field), `t` clamped to [0, 1] (NaN as
    /// 0) and every value to [0, 1] (the sum of two rounded products may
    /// pass 1 by a unit in the last place). An error
    /// ([`FieldError::SizeMismatch`]) when `other` has other dimensions.
    pub fn mixed(&self, other: &DensityGrid, t: f32) -> Result<Self, FieldError> {
        if other.dims != self.dims {
            return Err(FieldError::SizeMismatch {
                name: String::from("DensityGrid::mixed"),
                dims: self.dims.to_vec(),
                expected: self.values.len(),
                actual: other.values.len(),
            });
        }
        let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
        let values = self
            .values
            .iter()
            .zip(&other.values)
            .map(|(&a, &b)| ((1.0 - t) * a + t * b).clamp(0.0, 1.0))
            .collect();
        Ok(Self {
            dims: self.dims,
            spacing: self.spacing,
            origin: self.origin,
            values,
        })
    }

    /// Trilinear density at `world_position`. Positions outside the box are
    /// clamped onto it (the border values extend outwards); a NaN coordinate
    /// reads as the minimum corner's coordinate.
    pub fn sample(&self, world_position: DVec3) -> f64 {
        self.sample_grid((world_position - self.origin) / self.spacing)
    }

    /// Trilinear density at `grid_position`, in grid units (point `(i, j, k)` at
    /// `(i, j, k)`), clamped like [`DensityGrid::sample`].
    pub fn sample_grid(&self, grid_position: DVec3) -> f64 {
        let (i, fx) = axis_weight(grid_position.x, self.dims[0]);
        let (j, fy) = axis_weight(grid_position.y, self.dims[1]);
        let (k, fz) = axis_weight(grid_position.z, self.dims[2]);
        let corner =
            |di: usize, dj: usize, dk: usize| f64::from(self.value(i + di, j + dj, k + dk));
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let face = |dk: usize| {
            lerp(
                lerp(corner(0, 0, dk), corner(1, 0, dk), fx),
                lerp(corner(0, 1, dk), corner(1, 1, dk), fx),
                fy,
            )
        };
        lerp(face(0), face(1), fz)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mix_of_two_keyframes_stays_a_density_grid() {
        let full = DensityGrid::new([3, 2, 2], DVec3::ONE, DVec3::ZERO, vec![1.0; 12]).unwrap();
        let ramp = linear_grid();
        let other = DensityGrid::new(
            ramp.dims(),
            ramp.spacing(),
            ramp.origin(),
            ramp.values().iter().map(|v| 1.0 - v).collect(),
        )
        .unwrap();
        for step in 0..=1000 {
            let t = step as f32 / 1000.0;
            // Two full grids: no sum of rounded products passes 1.
            assert!(
                full.mixed(&full, t)
                    .unwrap()
                    .values()
                    .iter()
                    .all(|&v| v <= 1.0)
            );
            let mixed = ramp.mixed(&other, t).unwrap();
            assert_eq!(mixed.dims(), ramp.dims());
            for ((&m, &a), &b) in mixed.values().iter().zip(ramp.values()).zip(other.values()) {
                assert!(
                    (f64::from(m)
                        - ((1.0 - f64::from(t)) * f64::from(a) + f64::from(t) * f64::from(b)))
                    .abs()
                        < 1e-6
                );
            }
        }
        assert_eq!(ramp.mixed(&other, f32::NAN).unwrap(), ramp);
        assert_eq!(ramp.mixed(&other, 7.0).unwrap().values(), other.values());
        assert!(matches!(
            ramp.mixed(&full, 0.5),
            Err(FieldError::SizeMismatch { .. })
        ));
    }

    fn linear_grid() -> DensityGrid {
        let dims = [4, 3, 5];
        let mut values = Vec::new();
        for k in 0..5 {
            for j in 0..3 {
                for i in 0..4 {
                    values.push(0.05 * i as f32 + 0.1 * j as f32 + 0.08 * k as f32);
                }
            }
        }
        DensityGrid::new(
            dims,
            DVec3::new(0.5, 1.0, 2.0),
            DVec3::new(-1.0, 0.0, 3.0),
            values,
        )
        .unwrap()
    }

    #[test]
    fn trilinear_sampling_is_exact_on_a_linear_field() {
        let grid = linear_grid();
        for p in [
            DVec3::new(-1.0, 0.0, 3.0),
            DVec3::new(-0.3, 1.7, 9.1),
            DVec3::new(0.5, 2.0, 11.0),
        ] {
            let grid_position = (p - grid.origin()) / grid.spacing();
            let expected = 0.05 * grid_position.x + 0.1 * grid_position.y + 0.08 * grid_position.z;
            assert!((grid.sample(p) - expected).abs() < 1e-6);
        }
        assert_eq!(grid.max_corner(), DVec3::new(0.5, 2.0, 11.0));
        // Outside the box: clamped; NaN: no NaN out.
        assert_eq!(
            grid.sample(DVec3::splat(-100.0)),
            grid.sample(grid.origin())
        );
        assert!(grid.sample(DVec3::NAN).is_finite());
    }

    #[test]
    fn tetrahedra_share_grid_points_bit_for_bit() {
        // With this origin and spacing, origin + i·s + s differs from
        // origin + (i + 1)·s in the last bit for several i on x and y.
        let dims = [8, 8, 8];
        let grid = DensityGrid::new(
            dims,
            DVec3::new(0.3, 0.3, 0.2),
            DVec3::new(0.1, -7.3, 1.0 / 3.0),
            vec![0.5; 512],
        )
        .unwrap();
        let mut points: Vec<[u64; 3]> = grid
            .tetrahedra()
            .iter()
            .flat_map(|cell| cell.positions)
            .map(|p| p.to_array().map(f64::to_bits))
            .collect();
        points.sort_unstable();
        points.dedup();
        assert_eq!(points.len(), dims.iter().product::<usize>());
    }

    #[test]
    fn tetrahedra_fill_the_box_and_interpolate_the_linear_field() {
        let grid = linear_grid();
        let cells = grid.tetrahedra();
        assert_eq!(cells.len(), 6 * 3 * 2 * 4);
        let volume: f64 = cells.iter().map(Tetrahedron::volume).sum();
        let extent = grid.max_corner() - grid.origin();
        assert!((volume - extent.x * extent.y * extent.z).abs() < 1e-9);
        for cell in &cells {
            let centroid = cell.positions.iter().sum::<DVec3>() / 4.0;
            let linear = cell.scalars.iter().sum::<f64>() / 4.0;
            assert!((grid.sample(centroid) - linear).abs() < 1e-6);
        }
    }

    #[test]
    fn bad_input_is_refused_with_a_clear_message() {
        let ok = || vec![0.5f32; 8];
        let err = |r: Result<DensityGrid, FieldError>| r.unwrap_err().to_string();
        let message = err(DensityGrid::new([2, 2, 3], DVec3::ONE, DVec3::ZERO, ok()));
        assert!(message.contains("need 12 samples, found 8"), "{message}");
        let message = err(DensityGrid::new([1, 2, 4], DVec3::ONE, DVec3::ZERO, ok()));
        assert!(message.contains("at least 2 samples"), "{message}");
        let mut nan = ok();
        nan[3] = f32::NAN;
        let message = err(DensityGrid::new([2, 2, 2], DVec3::ONE, DVec3::ZERO, nan));
        assert!(message.contains("sample 3 is NaN"), "{message}");
        let mut big = ok();
        big[5] = 1.5;
        let message = err(DensityGrid::new([2, 2, 2], DVec3::ONE, DVec3::ZERO, big));
        assert!(
            message.contains("sample 5 is 1.5, outside [0, 1]"),
            "{message}"
        );
        // Past the first few thousand samples, after an infinite one.
        let mut late = vec![0.25f32; 16 * 16 * 17];
        late[4300] = -0.25;
        late[4301] = f32::INFINITY;
        let message = err(DensityGrid::new(
            [16, 16, 17],
            DVec3::ONE,
            DVec3::ZERO,
            late.clone(),
        ));
        assert!(message.contains("sample 4301 is inf"), "{message}");
        late[4301] = 0.5;
        let message = err(DensityGrid::new(
            [16, 16, 17],
            DVec3::ONE,
            DVec3::ZERO,
            late,
        ));
        assert!(
            message.contains("sample 4300 is -0.25, outside [0, 1]"),
            "{message}"
        );
        let message = err(DensityGrid::new(
            [2, 2, 2],
            DVec3::new(1.0, 0.0, 1.0),
            DVec3::ZERO,
            ok(),
        ));
        assert!(message.contains("spacing"), "{message}");
        let message = err(DensityGrid::new(
            [2, 2, 2],
            DVec3::ONE,
            DVec3::INFINITY,
            ok(),
        ));
        assert!(message.contains("origin"), "{message}");
        let message = err(DensityGrid::new(
            [usize::MAX, 2, 2],
            DVec3::ONE,
            DVec3::ZERO,
            ok(),
        ));
        assert!(message.contains("found 8"), "{message}");
    }
}
