//! [`HeightField`]: heights on a regular 2D grid, bilinear in between.

use glam::DVec2;

use crate::budget::BudgetError;

use super::{
    FieldError, HEIGHT_FIELD, SAMPLE_BYTES, axis_weight, check_dims, check_finite, check_origin,
    check_points, check_spacing,
};

/// Heights (world units, any finite value) at the points of a regular grid over
/// the horizontal x–z plane, bilinear between them. Terrain and fog thickness
/// maps (Röttger and Ertl 2003 §6).
///
/// Point `(i, j)` sits at horizontal position `origin + (i, j) · spacing`, that
/// is world `x = origin.x + i · spacing.x` and `z = origin.y + j · spacing.y`,
/// and is stored at index `i + nx · j`. Loaded images map their columns to `i`
/// and their rows (top row first) to `j`.
#[derive(Clone, Debug, PartialEq)]
pub struct HeightField {
    dims: [usize; 2],
    spacing: DVec2,
    origin: DVec2,
    heights: Vec<f32>,
}

impl HeightField {
    /// A height field of `dims = [nx, nz]` points (each ≥ 2), `spacing` (world
    /// units between neighbouring points along x and z, > 0), `origin` (world
    /// x and z of point (0, 0)) and `nx · nz` finite `heights`, x fastest.
    pub fn new(
        dims: [usize; 2],
        spacing: DVec2,
        origin: DVec2,
        heights: Vec<f32>,
    ) -> Result<Self, FieldError> {
        Self::validated("HeightField::new", dims, spacing, origin, heights)
    }

    /// The bytes of the heights of a field of `dims` points (4 per point),
    /// checked against the memory budget: the check the generators, loaders
    /// and resamplers of height fields make before they allocate
    /// ([`HeightField::value_noise`] adds its f64 sums), here without
    /// building one. Errors name a `height field of nx × nz points`.
    pub fn check_budget(dims: [usize; 2]) -> Result<u64, BudgetError> {
        check_points(HEIGHT_FIELD, &dims, SAMPLE_BYTES)
    }

    /// [`HeightField::new`] with `name` (a file path or source) in its errors.
    pub(super) fn validated(
        name: &str,
        dims: [usize; 2],
        spacing: DVec2,
        origin: DVec2,
        heights: Vec<f32>,
    ) -> Result<Self, FieldError> {
        check_dims(name, &dims, heights.len())?;
        check_spacing(name, &spacing.to_array())?;
        check_origin(name, &origin.to_array())?;
        check_finite(name, &heights)?;
        Ok(Self {
            dims,
            spacing,
            origin,
            heights,
        })
    }

    /// Points per axis `[nx, nz]`.
    pub fn dims(&self) -> [usize; 2] {
        self.dims
    }

    /// World units between neighbouring points along x and z.
    pub fn spacing(&self) -> DVec2 {
        self.spacing
    }

    /// World x and z of point (0, 0).
    pub fn origin(&self) -> DVec2 {
        self.origin
    }

    /// All heights, x fastest.
    pub fn heights(&self) -> &[f32] {
        &self.heights
    }

    /// The heights, x fastest, without copying them.
    pub(super) fn into_heights(self) -> Vec<f32> {
        self.heights
    }

    /// Height at point `(i, j)`. Panics when an index is out of range, like
    /// slice indexing.
    pub fn height(&self, i: usize, j: usize) -> f32 {
        self.heights[i + self.dims[0] * j]
    }

    /// Bilinear height at the horizontal world position `xz` (world x, world z).
    /// Positions outside the grid are clamped onto it; a NaN coordinate reads as
    /// the origin's coordinate.
    pub fn sample(&self, xz: DVec2) -> f64 {
        self.sample_grid((xz - self.origin) / self.spacing)
    }

    /// Bilinear height at `grid_position` in grid units (point `(i, j)` at
    /// `(i, j)`), clamped like [`HeightField::sample`].
    pub fn sample_grid(&self, grid_position: DVec2) -> f64 {
        let (i, fx) = axis_weight(grid_position.x, self.dims[0]);
        let (j, fz) = axis_weight(grid_position.y, self.dims[1]);
        let corner = |di: usize, dj: usize| f64::from(self.height(i + di, j + dj));
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        lerp(
            lerp(corner(0, 0), corner(1, 0), fx),
            lerp(corner(0, 1), corner(1, 1), fx),
            fz,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_sampling_reproduces_a_bilinear_field() {
        let height = |x: f64, z: f64| 2.0 + 0.5 * x - 0.25 * z + 0.125 * x * z;
        let mut heights = Vec::new();
        for j in 0..4 {
            for i in 0..3 {
                heights.push(height(10.0 + 2.0 * i as f64, -4.0 + j as f64) as f32);
            }
        }
        let field = HeightField::new(
            [3, 4],
            DVec2::new(2.0, 1.0),
            DVec2::new(10.0, -4.0),
            heights,
        )
        .unwrap();
        // Bilinear interpolation is exact for x·z inside a cell.
        for p in [DVec2::new(11.0, -3.5), DVec2::new(13.9, -1.1)] {
            assert!((field.sample(p) - height(p.x, p.y)).abs() < 1e-5);
        }
        assert!(field.sample(DVec2::NAN).is_finite());
        let message = HeightField::new([3, 3], DVec2::ONE, DVec2::ZERO, vec![0.0; 8])
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("HeightField::new") && message.contains("need 9 samples"),
            "{message}"
        );
        let message = HeightField::new(
            [2, 2],
            DVec2::ONE,
            DVec2::ZERO,
            vec![0.0, f32::INFINITY, 0.0, 0.0],
        )
        .unwrap_err()
        .to_string();
        assert!(message.contains("sample 1 is inf"), "{message}");
    }
}
