//! A value per terrain grid point that the level of detail morphs with the
//! heights: the ground fog's thickness (Röttger and Ertl 2003 §6), or any
//! other quantity carried by the terrain's vertices.

use super::TerrainError;

/// A map over a terrain: one finite, non-negative value per grid point of an
/// `n × n` terrain, index `i + n·j`, and its largest value.
///
/// [`TerrainHierarchy::update_with_map`](super::TerrainHierarchy::update_with_map)
/// morphs it with the terrain's weights into
/// [`TerrainMesh::map`](super::TerrainMesh::map).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TerrainMap {
    side: usize,
    values: Vec<f32>,
    max: f32,
}

impl TerrainMap {
    /// A map of `values` on a terrain of `side × side` points (index
    /// `i + side·j`). Negative values are clamped to 0 (no map there); a
    /// NaN or infinite value, or a length other than `side²`, is an error.
    pub fn new(side: usize, mut values: Vec<f32>) -> Result<Self, TerrainError> {
        if values.len() != side * side {
            return Err(TerrainError::MapLength {
                side,
                len: values.len(),
            });
        }
        check_finite(&values)?;
        let mut max = 0.0_f32;
        for value in &mut values {
            *value = value.max(0.0);
            max = max.max(*value);
        }
        Ok(Self { side, values, max })
    }

    /// Resamples a map of `dims = [width, height]` values (row-major, x
    /// fastest; at least 1 × 1) onto a terrain of `side × side` points: the
    /// map covers the terrain from corner to corner (its first and last
    /// samples sit on the terrain's first and last grid points), and grid
    /// point `(i, j)` takes the map's bilinear interpolation at `(i/(side−1)
    /// · (width−1), j/(side−1) · (height−1))`. So a map of any size fits, and
    /// one of the terrain's size is taken as it is. Negative values clamp to
    /// 0; NaN, infinite values or a length other than `width · height` are
    /// errors.
    pub fn resample(map: &[f32], dims: [usize; 2], side: usize) -> Result<Self, TerrainError> {
        let [width, height] = dims;
        if width == 0 || height == 0 || map.len() != width * height {
            return Err(TerrainError::MapSize {
                dims,
                len: map.len(),
            });
        }
        check_finite(map)?;
        let last = side.saturating_sub(1).max(1) as f64;
        let axis = |k: usize, count: usize| {
            let x = k as f64 / last * (count - 1) as f64;
            let lower = (x.floor() as usize).min(count.saturating_sub(2));
            (lower, (x - lower as f64).clamp(0.0, 1.0) as f32)
        };
        let at = |x: usize, y: usize| map[x.min(width - 1) + width * y.min(height - 1)];
        let mut values = Vec::with_capacity(side * side);
        for j in 0..side {
            let (y, ty) = axis(j, height);
            for i in 0..side {
                let (x, tx) = axis(i, width);
                let near = at(x, y) + tx * (at(x + 1, y) - at(x, y));
                let far = at(x, y + 1) + tx * (at(x + 1, y + 1) - at(x, y + 1));
                values.push(near + ty * (far - near));
            }
        }
        Self::new(side, values)
    }

    /// Points per side of the terrain the map belongs to.
    pub fn side(&self) -> usize {
        self.side
    }

    /// The values, index `i + side·j`.
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    /// The largest value (0 for a map that is zero everywhere).
    pub fn max(&self) -> f32 {
        self.max
    }

    /// Whether the map is zero everywhere (a fog of no thickness: nothing
    /// to draw).
    pub fn is_zero(&self) -> bool {
        self.max == 0.0
    }
}

fn check_finite(values: &[f32]) -> Result<(), TerrainError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(TerrainError::NonFiniteMapValue {
            index,
            value: values[index],
        }),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resampling_is_bilinear_from_corner_to_corner() {
        // A 2 × 2 map of a plane v = 1 + 2x + 3y (x, y in [0, 1]) onto 5 × 5.
        let corners = [1.0, 3.0, 4.0, 6.0];
        let map = TerrainMap::resample(&corners, [2, 2], 5).unwrap();
        for j in 0..5 {
            for i in 0..5 {
                let expected = 1.0 + 2.0 * i as f32 / 4.0 + 3.0 * j as f32 / 4.0;
                assert!((map.values()[i + 5 * j] - expected).abs() < 1e-6);
            }
        }
        assert_eq!(map.max(), 6.0);
        // A map of the terrain's size is taken as it is.
        let values: Vec<f32> = (0..9).map(|v| v as f32 * 0.37).collect();
        let same = TerrainMap::resample(&values, [3, 3], 3).unwrap();
        assert_eq!(same.values(), &values[..]);
        // One value covers everything; other sizes of any aspect work.
        let one = TerrainMap::resample(&[2.5], [1, 1], 9).unwrap();
        assert!(one.values().iter().all(|v| *v == 2.5));
        let wide = TerrainMap::resample(&[0.0, 1.0, 2.0, 3.0, 4.0], [5, 1], 3).unwrap();
        assert_eq!(
            wide.values(),
            &[0.0, 2.0, 4.0, 0.0, 2.0, 4.0, 0.0, 2.0, 4.0]
        );
    }

    #[test]
    fn bad_maps_are_errors_and_negative_values_clamp() {
        let clamped = TerrainMap::new(2, vec![-1.0, 0.5, -0.0, 2.0]).unwrap();
        assert_eq!(clamped.values(), &[0.0, 0.5, 0.0, 2.0]);
        assert!(TerrainMap::new(2, vec![0.0; 4]).unwrap().is_zero());
        let nan = TerrainMap::new(2, vec![0.0, f32::NAN, 0.0, 0.0]).unwrap_err();
        assert_eq!(
            nan.to_string(),
            "map value 1 is NaN; every value must be finite"
        );
        let short = TerrainMap::new(3, vec![0.0; 4]).unwrap_err();
        assert!(short.to_string().contains("9"), "{short}");
        let size = TerrainMap::resample(&[1.0; 5], [2, 2], 3).unwrap_err();
        assert!(size.to_string().contains("[2, 2]"), "{size}");
        let inf = TerrainMap::resample(&[1.0, f32::INFINITY], [2, 1], 3).unwrap_err();
        assert!(matches!(
            inf,
            TerrainError::NonFiniteMapValue { index: 1, .. }
        ));
    }
}
