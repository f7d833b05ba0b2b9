//! Bringing a field to 2^n+1 points per axis, as the C-LOD quadtree and octree
//! need: other sizes are padded or resampled. Each axis is
//! handled on its own, so a 513×513×65 cloud stays as it is and becomes a
//! forest of octrees.
//!
//! Two rules, both provided:
//!
//! - **Padding** ([`DensityGrid::padded_to_power_of_two_plus_one`]) appends
//!   points at the high end of each axis with the same spacing. Every original
//!   sample keeps its value and position, so the data is reproduced exactly; the
//!   box grows (up to twice the points per axis). Pad density with
//!   `PadFill::Value(0.0)` (empty space stays empty) and height fields with
//!   [`PadFill::ReplicateEdge`] (the terrain continues flat). This is the
//!   default choice: it never alters the data.
//! - **Resampling** ([`DensityGrid::resampled_to_power_of_two_plus_one`]) keeps
//!   the box and places `2^n+1 ≥ n_old` points evenly over it, each taking the
//!   trilinear (bilinear) value of the old field there. No memory beyond the
//!   next size, but the field between old samples is smoothed; a field that is
//!   linear per axis is reproduced exactly, and a grid already of size 2^n+1 is
//!   returned unchanged.
//!
//! Both check the new field (up to twice the points per axis, so up to eight
//! times a 3D grid's memory) against the memory budget before allocating it
//! ([`FieldError::OverBudget`]).

use glam::{DVec2, DVec3};

use super::{
    DENSITY_GRID, DensityGrid, FieldError, HEIGHT_FIELD, HeightField, SAMPLE_BYTES, budgeted_points,
};
use crate::pacing::pace;

/// The smallest `2^k + 1 ≥ n` (2 for `n ≤ 2`): 3 → 3, 4 → 5, 65 → 65, 100 → 129.
/// Sizes beyond `2^(bits − 1) + 1`, larger than any allocatable grid, return `n`.
pub fn power_of_two_plus_one(n: usize) -> usize {
    if n <= 2 {
        return 2;
    }
    (n - 1)
        .checked_next_power_of_two()
        .and_then(|p| p.checked_add(1))
        .unwrap_or(n)
}

/// What padding puts into the new points.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PadFill {
    /// Copy the nearest original sample (the last one along each padded axis).
    ReplicateEdge,
    /// A constant; for density grids it must lie in [0, 1].
    Value(f32),
}

impl PadFill {
    fn check(self, name: &str, range: Option<(f32, f32)>) -> Result<(), FieldError> {
        if let Self::Value(value) = self {
            let valid =
                value.is_finite() && range.is_none_or(|(lo, hi)| (lo..=hi).contains(&value));
            if !valid {
                return Err(FieldError::InvalidParameter {
                    name: name.to_owned(),
                    parameter: "PadFill::Value",
                    value: value.to_string(),
                    requirement: "finite (and in [0, 1] for densities)",
                });
            }
        }
        Ok(())
    }

    /// The padded value at `index` along axes of old sizes `dims`, given the
    /// accessor of the original samples.
    fn value<const N: usize>(
        self,
        index: [usize; N],
        dims: [usize; N],
        original: impl Fn([usize; N]) -> f32,
    ) -> f32 {
        let inside = index.iter().zip(&dims).all(|(i, n)| i < n);
        match self {
            _ if inside => original(index),
            Self::ReplicateEdge => original(std::array::from_fn(|a| index[a].min(dims[a] - 1))),
            Self::Value(value) => value,
        }
    }
}

/// The points per axis of a field before and after bringing each axis to
/// 2^n+1.
struct Resize<const N: usize> {
    old: [usize; N],
    new: [usize; N],
}

impl<const N: usize> Resize<N> {
    /// The sizes of a field of `old` points brought to 2^n+1, checked against
    /// the memory budget for the new field (`kind`, 4 bytes per point) before
    /// it is allocated; `name` is for errors.
    fn of(name: &str, kind: &str, old: [usize; N]) -> Result<Self, FieldError> {
        let new = old.map(power_of_two_plus_one);
        budgeted_points(name, kind, &new, SAMPLE_BYTES)?;
        Ok(Self { old, new })
    }

    /// The samples at every new point, x fastest, from `value` at each new
    /// index.
    fn values(&self, mut value: impl FnMut([usize; N]) -> f32) -> Vec<f32> {
        let count = self.new.iter().product();
        let mut values = Vec::with_capacity(count);
        let mut index = [0; N];
        for _ in 0..count {
            values.push(value(index));
            for (i, n) in index.iter_mut().zip(self.new) {
                *i += 1;
                if *i < n {
                    break;
                }
                *i = 0;
            }
            if index[0] == 0 {
                // A row done: a yield point for a paced build.
                pace();
            }
        }
        values
    }

    /// Position in old grid units of the new point `index` when resampling over
    /// the same extent.
    fn resampled_position(&self, index: [usize; N]) -> [f64; N] {
        std::array::from_fn(|a| (index[a] * (self.old[a] - 1)) as f64 / (self.new[a] - 1) as f64)
    }

    /// New spacing over old spacing, per axis, when resampling over the same
    /// extent.
    fn resampled_spacing_ratio(&self) -> [f64; N] {
        std::array::from_fn(|a| (self.old[a] - 1) as f64 / (self.new[a] - 1) as f64)
    }
}

impl DensityGrid {
    /// Pads each axis at its high end to 2^n+1 points with `fill` (see the
    /// module docs), keeping spacing, origin and every original sample.
    pub fn padded_to_power_of_two_plus_one(&self, fill: PadFill) -> Result<Self, FieldError> {
        let name = "DensityGrid::padded_to_power_of_two_plus_one";
        fill.check(name, Some((0.0, 1.0)))?;
        let resize = Resize::of(name, DENSITY_GRID, self.dims())?;
        let values =
            resize.values(|index| fill.value(index, resize.old, |[i, j, k]| self.value(i, j, k)));
        Self::validated(name, resize.new, self.spacing(), self.origin(), values)
    }

    /// Resamples each axis to 2^n+1 points over the same box by trilinear
    /// interpolation (see the module docs).
    pub fn resampled_to_power_of_two_plus_one(&self) -> Result<Self, FieldError> {
        let name = "DensityGrid::resampled_to_power_of_two_plus_one";
        let resize = Resize::of(name, DENSITY_GRID, self.dims())?;
        let values = resize.values(|index| {
            let position = DVec3::from_array(resize.resampled_position(index));
            (self.sample_grid(position) as f32).clamp(0.0, 1.0)
        });
        let spacing = self.spacing() * DVec3::from_array(resize.resampled_spacing_ratio());
        Self::validated(name, resize.new, spacing, self.origin(), values)
    }
}

impl HeightField {
    /// Pads each axis at its high end to 2^n+1 points with `fill` (see the
    /// module docs), keeping spacing, origin and every original height.
    pub fn padded_to_power_of_two_plus_one(&self, fill: PadFill) -> Result<Self, FieldError> {
        let name = "HeightField::padded_to_power_of_two_plus_one";
        fill.check(name, None)?;
        let resize = Resize::of(name, HEIGHT_FIELD, self.dims())?;
        let heights =
            resize.values(|index| fill.value(index, resize.old, |[i, j]| self.height(i, j)));
        Self::validated(name, resize.new, self.spacing(), self.origin(), heights)
    }

    /// Resamples each axis to 2^n+1 points over the same extent by bilinear
    /// interpolation (see the module docs).
    pub fn resampled_to_power_of_two_plus_one(&self) -> Result<Self, FieldError> {
        let name = "HeightField::resampled_to_power_of_two_plus_one";
        let resize = Resize::of(name, HEIGHT_FIELD, self.dims())?;
        let heights = resize.values(|index| {
            self.sample_grid(DVec2::from_array(resize.resampled_position(index))) as f32
        });
        let spacing = self.spacing() * DVec2::from_array(resize.resampled_spacing_ratio());
        Self::validated(name, resize.new, spacing, self.origin(), heights)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn linear_density(dims: [usize; 3]) -> (DensityGrid, impl Fn(DVec3) -> f64) {
        let spacing = DVec3::new(0.5, 2.0, 1.0);
        let origin = DVec3::new(3.0, -1.0, 0.5);
        let extent = (DVec3::new(dims[0] as f64, dims[1] as f64, dims[2] as f64) - 1.0) * spacing;
        let field = move |p: DVec3| {
            let u = (p - origin) / extent;
            0.1 + 0.3 * u.x + 0.2 * u.y + 0.35 * u.z
        };
        let mut values = Vec::new();
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    values.push(
                        field(origin + DVec3::new(i as f64, j as f64, k as f64) * spacing) as f32,
                    );
                }
            }
        }
        (
            DensityGrid::new(dims, spacing, origin, values).unwrap(),
            field,
        )
    }

    #[test]
    fn sizes_round_up_to_two_to_the_n_plus_one() {
        let cases = [
            (0, 2),
            (2, 2),
            (3, 3),
            (4, 5),
            (5, 5),
            (6, 9),
            (65, 65),
            (100, 129),
            (513, 513),
        ];
        for (n, expected) in cases {
            assert_eq!(power_of_two_plus_one(n), expected, "n = {n}");
        }
        assert_eq!(power_of_two_plus_one(usize::MAX), usize::MAX);
    }

    #[test]
    fn trilinear_resampling_keeps_a_linear_field_exact() {
        let (grid, field) = linear_density([6, 4, 11]);
        let resampled = grid.resampled_to_power_of_two_plus_one().unwrap();
        assert_eq!(resampled.dims(), [9, 5, 17]);
        assert!(
            (resampled.max_corner() - grid.max_corner())
                .abs()
                .max_element()
                < 1e-12
        );
        for k in 0..17 {
            for j in 0..5 {
                for i in 0..9 {
                    let p = resampled.origin()
                        + DVec3::new(i as f64, j as f64, k as f64) * resampled.spacing();
                    assert!((f64::from(resampled.value(i, j, k)) - field(p)).abs() < 1e-6);
                }
            }
        }
        // Already 2^n+1: unchanged.
        assert_eq!(
            resampled.resampled_to_power_of_two_plus_one().unwrap(),
            resampled
        );
    }

    #[test]
    fn padding_keeps_every_sample() {
        let (grid, _) = linear_density([3, 4, 6]);
        for fill in [PadFill::ReplicateEdge, PadFill::Value(0.0)] {
            let padded = grid.padded_to_power_of_two_plus_one(fill).unwrap();
            assert_eq!(padded.dims(), [3, 5, 9]);
            assert_eq!(
                (padded.spacing(), padded.origin()),
                (grid.spacing(), grid.origin())
            );
            for k in 0..9 {
                for j in 0..5 {
                    for i in 0..3 {
                        let expected = if j < 4 && k < 6 {
                            grid.value(i, j, k)
                        } else if fill == PadFill::ReplicateEdge {
                            grid.value(i, j.min(3), k.min(5))
                        } else {
                            0.0
                        };
                        assert_eq!(padded.value(i, j, k), expected);
                    }
                }
            }
        }
        let message = grid
            .padded_to_power_of_two_plus_one(PadFill::Value(2.0))
            .unwrap_err()
            .to_string();
        assert!(message.contains("PadFill::Value"), "{message}");
    }

    #[test]
    fn height_fields_pad_and_resample() {
        let heights: Vec<f32> = (0..12).map(|v| v as f32).collect();
        let field = HeightField::new([4, 3], DVec2::ONE, DVec2::ZERO, heights).unwrap();
        let padded = field
            .padded_to_power_of_two_plus_one(PadFill::ReplicateEdge)
            .unwrap();
        assert_eq!(padded.dims(), [5, 3]);
        assert_eq!(padded.height(4, 2), field.height(3, 2));
        // Height = i + 4 j is linear, so resampling is exact.
        let resampled = field.resampled_to_power_of_two_plus_one().unwrap();
        assert_eq!(resampled.dims(), [5, 3]);
        assert!((resampled.height(2, 1) - (1.5 + 4.0)).abs() < 1e-6);
        assert!(
            field
                .padded_to_power_of_two_plus_one(PadFill::Value(f32::NAN))
                .is_err()
        );
    }

    /// A grid of zeros: calloc'd pages, so even a large one costs no memory
    /// until written.
    fn zeros(dims: [usize; 3]) -> DensityGrid {
        let count = dims.iter().product();
        DensityGrid::new(dims, DVec3::ONE, DVec3::ZERO, vec![0.0; count]).unwrap()
    }

    #[test]
    fn new_sizes_beyond_the_memory_budget_are_refused_before_allocating() {
        // 514³ points (543 MB) become 1025³ (4.3 GB) either way.
        let grid = zeros([514; 3]);
        let message = grid
            .padded_to_power_of_two_plus_one(PadFill::Value(0.0))
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with(
                "DensityGrid::padded_to_power_of_two_plus_one: density grid of 1025 × 1025 × 1025 points needs 4,307,562,500 bytes"
            ),
            "{message}"
        );
        let message = grid
            .resampled_to_power_of_two_plus_one()
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with(
                "DensityGrid::resampled_to_power_of_two_plus_one: density grid of 1025 × 1025 × 1025 points"
            ),
            "{message}"
        );
        // 16386² heights (1.1 GB) become 32769² (4.3 GB).
        let side = 16_386;
        let field =
            HeightField::new([side; 2], DVec2::ONE, DVec2::ZERO, vec![0.0; side * side]).unwrap();
        for message in [
            field
                .padded_to_power_of_two_plus_one(PadFill::ReplicateEdge)
                .unwrap_err()
                .to_string(),
            field
                .resampled_to_power_of_two_plus_one()
                .unwrap_err()
                .to_string(),
        ] {
            assert!(
                message.contains("height field of 32769 × 32769 points needs 4,295,229,444 bytes"),
                "{message}"
            );
        }
    }
}
