//! Volumes in scene files: where the scalar field comes from, its box, its
//! transfer function and its optical mode (DESIGN.md §3-4).
//!
//! ```ron
//! volumes: [
//!     (
//!         source: Procedural((dims: (33, 17, 33), kind: Fbm, seed: 7, octaves: 4, frequency: 0.5, coverage: 0.6)),
//!         // or Uniform((value: 1.0)), Ramp((axis: Y, from: 1.0, to: 0.0)),
//!         // or Cells([(positions: ((0,0,0), (1,0,0), (0,1,0), (0,0,1)), scalars: (1, 1, 1, 1)), ...]),
//!         min: (-4.0, 0.0, -4.0),          // the grid's box, metres; default (-1, -1, -1)
//!         max: (4.0, 2.0, 4.0),            // default (1, 1, 1)
//!         transfer: Preset(Cloud),         // or Points([(s: 0.0, kappa: (1, 1, 1), rho: 0.0), ...])
//!                                          // or Strip((path: "ramps/fire.png", max_density: 2.0))
//!         density_scale: 1.0,              // multiplies ρ; default 1
//!         mode: Sorted,                    // Sorted, Emissive or Mip; default Sorted
//!     ),
//! ]
//! ```
//!
//! Grid sources sample the box `min..max` at `dims` points per axis (corners
//! included), trilinear in between. `Cells` gives tetrahedra in world space
//! and ignores the box. A transfer-function strip path is relative to the scene
//! file. Building a volume ([`VolumeDescription::build`]) generates or loads its
//! data; a scene file's validation checks only what is cheap.

use std::path::Path;

use glam::DVec3;
use serde::{Deserialize, Serialize};

use super::InvalidField;
use crate::cell::Tetrahedron;
use crate::field::{DensityGrid, FieldError, NoiseKind, ProceduralNoise};
use crate::optics::OpticalMode;
use crate::transfer::{ControlPoint, TransferFunction, TransferPreset};

/// One volume of a scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeDescription {
    /// Where the scalar field comes from.
    pub source: VolumeSource,
    /// Minimum corner of the grid's box, metres. Default `(-1, -1, -1)`.
    #[serde(default = "default_min")]
    pub min: [f32; 3],
    /// Maximum corner of the grid's box, metres, above `min` on every axis.
    /// Default `(1, 1, 1)`.
    #[serde(default = "default_max")]
    pub max: [f32; 3],
    /// κ and ρ over the scalar. Default `Preset(Cloud)`.
    #[serde(default)]
    pub transfer: TransferDescription,
    /// Factor on ρ, finite and ≥ 0. Default 1.
    #[serde(default = "default_density_scale")]
    pub density_scale: f32,
    /// How segments combine. Default `Sorted`.
    #[serde(default)]
    pub mode: OpticalMode,
}

fn default_min() -> [f32; 3] {
    [-1.0; 3]
}

fn default_max() -> [f32; 3] {
    [1.0; 3]
}

fn default_density_scale() -> f32 {
    1.0
}

/// Where a volume's scalar field comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum VolumeSource {
    /// The same scalar everywhere in the box.
    Uniform(UniformSource),
    /// A scalar linear along one axis of the box.
    Ramp(RampSource),
    /// Seeded Perlin noise.
    Procedural(ProceduralSource),
    /// Tetrahedra in world space with a scalar per vertex.
    Cells(Vec<TetrahedronDescription>),
}

/// The same scalar everywhere.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UniformSource {
    /// The scalar, in [0, 1].
    pub value: f32,
    /// Grid points per axis, each ≥ 2. Default `(2, 2, 2)`.
    #[serde(default = "default_small_dims")]
    pub dims: [usize; 3],
}

/// A coordinate axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Axis {
    /// World X.
    X,
    /// World Y (up).
    Y,
    /// World Z.
    Z,
}

/// A scalar linear along one axis: `from` at the box's minimum, `to` at its maximum.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RampSource {
    /// The axis the scalar changes along.
    pub axis: Axis,
    /// Scalar at `min` along the axis, in [0, 1].
    pub from: f32,
    /// Scalar at `max` along the axis, in [0, 1].
    pub to: f32,
    /// Grid points per axis, each ≥ 2. Default `(2, 2, 2)`: the ramp is exact
    /// with two points.
    #[serde(default = "default_small_dims")]
    pub dims: [usize; 3],
}

fn default_small_dims() -> [usize; 3] {
    [2; 3]
}

/// Seeded fractal Perlin noise over the box.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProceduralSource {
    /// Grid points per axis, each ≥ 2.
    pub dims: [usize; 3],
    /// Fractal kind. Default `Fbm`.
    #[serde(default)]
    pub kind: NoiseKind,
    /// Seed. Default 0.
    #[serde(default)]
    pub seed: u32,
    /// Octaves, 1 to 32. Default 4.
    #[serde(default = "default_octaves")]
    pub octaves: usize,
    /// First-octave frequency, cycles per metre, > 0. Default 1.
    #[serde(default = "default_frequency")]
    pub frequency: f32,
    /// Share of the noise range kept, in (0, 1]: a noise value `n` in [0, 1]
    /// becomes `clamp((n − (1 − coverage)) / coverage, 0, 1)`, so a smaller
    /// coverage leaves more empty space. Default 1 (the noise as it is).
    #[serde(default = "default_coverage")]
    pub coverage: f32,
}

fn default_octaves() -> usize {
    4
}

fn default_frequency() -> f32 {
    1.0
}

fn default_coverage() -> f32 {
    1.0
}

/// A tetrahedron in world space.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TetrahedronDescription {
    /// The four vertices, metres.
    pub positions: [[f32; 3]; 4],
    /// The scalar at each vertex, in [0, 1].
    pub scalars: [f32; 4],
}

/// A transfer function in a scene file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum TransferDescription {
    /// A named preset.
    Preset(TransferPreset),
    /// Control points, piecewise linear.
    Points(Vec<ControlPoint>),
    /// A 1-pixel-high PNG strip, see [`TransferFunction::from_png_strip`].
    Strip(TransferStrip),
}

impl Default for TransferDescription {
    fn default() -> Self {
        Self::Preset(TransferPreset::Cloud)
    }
}

/// A transfer function from a PNG strip.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransferStrip {
    /// The PNG, relative to the scene file.
    pub path: String,
    /// ρ where the strip's alpha is 1, 1/metre.
    pub max_density: f32,
}

/// A volume ready to render: its field and its transfer function.
#[derive(Clone, Debug, PartialEq)]
pub struct BuiltVolume {
    /// The scalar field.
    pub field: VolumeField,
    /// κ and ρ, `density_scale` applied.
    pub transfer_function: TransferFunction,
    /// How segments combine.
    pub mode: OpticalMode,
}

/// A volume's scalar field.
#[derive(Clone, Debug, PartialEq)]
pub enum VolumeField {
    /// A trilinear grid over a box.
    Grid(DensityGrid),
    /// Tetrahedra with a scalar per vertex.
    Cells(Vec<Tetrahedron>),
}

fn source_error(error: FieldError) -> InvalidField {
    InvalidField::new("source", error.to_string())
}

impl VolumeDescription {
    /// Generates or loads the field and builds the transfer function.
    /// `scene_dir` resolves a strip's relative path. Errors name the field
    /// (relative to this volume) and the reason.
    pub fn build(&self, scene_dir: &Path) -> Result<BuiltVolume, InvalidField> {
        let field = match &self.source {
            VolumeSource::Cells(cells) => VolumeField::Cells(
                cells
                    .iter()
                    .map(|cell| Tetrahedron {
                        positions: cell.positions.map(|p| DVec3::from(p.map(f64::from))),
                        scalars: cell.scalars.map(f64::from),
                    })
                    .collect(),
            ),
            VolumeSource::Uniform(uniform) => VolumeField::Grid(self.uniform_grid(uniform)?),
            VolumeSource::Ramp(ramp) => VolumeField::Grid(self.ramp_grid(ramp)?),
            VolumeSource::Procedural(procedural) => {
                VolumeField::Grid(self.procedural_grid(procedural)?)
            }
        };
        let transfer = match &self.transfer {
            TransferDescription::Preset(preset) => Ok(TransferFunction::preset(*preset)),
            TransferDescription::Points(points) => TransferFunction::new(points.clone()),
            TransferDescription::Strip(strip) => {
                TransferFunction::from_png_strip(scene_dir.join(&strip.path), strip.max_density)
            }
        }
        .and_then(|tf| tf.scale_density(self.density_scale))
        .map_err(|error| InvalidField::new("transfer", error.to_string()))?;
        Ok(BuiltVolume {
            field,
            transfer_function: transfer,
            mode: self.mode,
        })
    }

    fn spacing(&self, dims: [usize; 3]) -> DVec3 {
        let steps = DVec3::from(dims.map(|n| (n.max(2) - 1) as f64));
        (self.max_corner() - self.min_corner()) / steps
    }

    fn min_corner(&self) -> DVec3 {
        DVec3::from(self.min.map(f64::from))
    }

    fn max_corner(&self) -> DVec3 {
        DVec3::from(self.max.map(f64::from))
    }

    fn uniform_grid(&self, uniform: &UniformSource) -> Result<DensityGrid, InvalidField> {
        let count = uniform.dims.iter().product();
        DensityGrid::new(
            uniform.dims,
            self.spacing(uniform.dims),
            self.min_corner(),
            vec![uniform.value; count],
        )
        .map_err(source_error)
    }

    fn ramp_grid(&self, ramp: &RampSource) -> Result<DensityGrid, InvalidField> {
        let [nx, ny, nz] = ramp.dims;
        let axis = ramp.axis as usize;
        let mut values = Vec::with_capacity(nx * ny * nz);
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let t = [i, j, k][axis] as f32 / (ramp.dims[axis] - 1) as f32;
                    values.push(ramp.from + (ramp.to - ramp.from) * t);
                }
            }
        }
        DensityGrid::new(
            ramp.dims,
            self.spacing(ramp.dims),
            self.min_corner(),
            values,
        )
        .map_err(source_error)
    }

    fn procedural_grid(&self, procedural: &ProceduralSource) -> Result<DensityGrid, InvalidField> {
        let noise = ProceduralNoise {
            kind: procedural.kind,
            seed: procedural.seed,
            octaves: procedural.octaves,
            frequency: f64::from(procedural.frequency),
            ..ProceduralNoise::default()
        };
        let spacing = self.spacing(procedural.dims);
        let grid = DensityGrid::procedural(procedural.dims, spacing, self.min_corner(), &noise)
            .map_err(source_error)?;
        let coverage = procedural.coverage;
        let values = grid
            .values()
            .iter()
            .map(|n| ((n - (1.0 - coverage)) / coverage).clamp(0.0, 1.0))
            .collect();
        DensityGrid::new(procedural.dims, spacing, self.min_corner(), values).map_err(source_error)
    }

    /// Checks what is cheap to check; [`VolumeDescription::build`] checks the rest.
    pub(super) fn validate(&self) -> Result<(), InvalidField> {
        for (name, corner) in [("min", self.min), ("max", self.max)] {
            if let Some(value) = corner.iter().find(|c| !c.is_finite()) {
                return Err(InvalidField::new(
                    name,
                    format!("must be finite, got {value}"),
                ));
            }
        }
        if (0..3).any(|a| self.max[a] <= self.min[a]) {
            return Err(InvalidField::new(
                "max",
                format!(
                    "must exceed min on every axis, got min {:?} max {:?}",
                    self.min, self.max
                ),
            ));
        }
        if !(self.density_scale.is_finite() && self.density_scale >= 0.0) {
            return Err(InvalidField::new(
                "density_scale",
                format!("must be finite and >= 0, got {}", self.density_scale),
            ));
        }
        let unit = |field: &str, value: f32| {
            if (0.0..=1.0).contains(&value) {
                Ok(())
            } else {
                Err(InvalidField::new(
                    field,
                    format!("must be in [0, 1], got {value}"),
                ))
            }
        };
        let dims = |field: &str, dims: [usize; 3]| {
            if dims.iter().all(|n| (2..=4097).contains(n)) {
                Ok(())
            } else {
                Err(InvalidField::new(
                    field,
                    format!("each must be in [2, 4097], got {dims:?}"),
                ))
            }
        };
        match &self.source {
            VolumeSource::Uniform(uniform) => {
                unit("source.Uniform.value", uniform.value)?;
                dims("source.Uniform.dims", uniform.dims)
            }
            VolumeSource::Ramp(ramp) => {
                unit("source.Ramp.from", ramp.from)?;
                unit("source.Ramp.to", ramp.to)?;
                dims("source.Ramp.dims", ramp.dims)
            }
            VolumeSource::Procedural(procedural) => {
                dims("source.Procedural.dims", procedural.dims)?;
                if !(procedural.coverage > 0.0 && procedural.coverage <= 1.0) {
                    return Err(InvalidField::new(
                        "source.Procedural.coverage",
                        format!("must be in (0, 1], got {}", procedural.coverage),
                    ));
                }
                Ok(())
            }
            VolumeSource::Cells(cells) => {
                if cells.is_empty() {
                    return Err(InvalidField::new("source.Cells", "needs at least one cell"));
                }
                for (index, cell) in cells.iter().enumerate() {
                    if cell.positions.iter().flatten().any(|c| !c.is_finite()) {
                        return Err(InvalidField::new(
                            format!("source.Cells[{index}].positions"),
                            "must be finite",
                        ));
                    }
                    for scalar in cell.scalars {
                        unit(&format!("source.Cells[{index}].scalars"), scalar)?;
                    }
                }
                Ok(())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn volume(source: VolumeSource) -> VolumeDescription {
        VolumeDescription {
            source,
            min: [0.0; 3],
            max: [2.0, 4.0, 8.0],
            transfer: TransferDescription::default(),
            density_scale: 2.0,
            mode: OpticalMode::Emissive,
        }
    }

    fn grid(built: BuiltVolume) -> DensityGrid {
        match built.field {
            VolumeField::Grid(grid) => grid,
            VolumeField::Cells(_) => panic!("expected a grid"),
        }
    }

    #[test]
    fn ramp_is_linear_along_its_axis_and_spans_the_box() {
        let ramp = volume(VolumeSource::Ramp(RampSource {
            axis: Axis::Y,
            from: 0.2,
            to: 0.8,
            dims: [3, 5, 2],
        }));
        let built = ramp.build(Path::new(".")).unwrap();
        assert_eq!(built.mode, OpticalMode::Emissive);
        let grid = grid(built);
        assert_eq!(grid.max_corner(), DVec3::new(2.0, 4.0, 8.0));
        for y in [0.0, 1.0, 2.5, 4.0] {
            let expected = 0.2 + 0.6 * y / 4.0;
            assert!((grid.sample(DVec3::new(1.3, y, 5.0)) - expected).abs() < 1e-6);
        }
    }

    #[test]
    fn density_scale_multiplies_rho() {
        let built = volume(VolumeSource::Uniform(UniformSource {
            value: 1.0,
            dims: [2; 3],
        }))
        .build(Path::new("."))
        .unwrap();
        let cloud = TransferFunction::preset(TransferPreset::Cloud);
        assert_eq!(
            built.transfer_function.evaluate(1.0).rho,
            2.0 * cloud.evaluate(1.0).rho
        );
    }

    #[test]
    fn coverage_empties_low_noise() {
        let source = |coverage| {
            VolumeSource::Procedural(ProceduralSource {
                dims: [9; 3],
                kind: NoiseKind::Fbm,
                seed: 3,
                octaves: 3,
                frequency: 0.4,
                coverage,
            })
        };
        let full = grid(volume(source(1.0)).build(Path::new(".")).unwrap());
        let half = grid(volume(source(0.5)).build(Path::new(".")).unwrap());
        for (n, h) in full.values().iter().zip(half.values()) {
            assert!((h - ((n - 0.5) / 0.5).clamp(0.0, 1.0)).abs() < 1e-6);
        }
        assert!(
            half.values().iter().filter(|v| **v == 0.0).count()
                > full.values().iter().filter(|v| **v == 0.0).count()
        );
    }

    #[test]
    fn cells_keep_world_positions() {
        let cell = TetrahedronDescription {
            positions: [[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            scalars: [0.0, 0.5, 1.0, 0.25],
        };
        let built = volume(VolumeSource::Cells(vec![cell]))
            .build(Path::new("."))
            .unwrap();
        let VolumeField::Cells(cells) = built.field else {
            panic!("expected cells");
        };
        assert_eq!(cells[0].positions[1], DVec3::X);
        assert_eq!(cells[0].scalars[2], 1.0);
    }

    #[test]
    fn missing_strip_names_the_file() {
        let mut strip = volume(VolumeSource::Uniform(UniformSource {
            value: 1.0,
            dims: [2; 3],
        }));
        strip.transfer = TransferDescription::Strip(TransferStrip {
            path: String::from("ramps/none.png"),
            max_density: 1.0,
        });
        let error = strip.build(Path::new("scenes")).unwrap_err();
        assert_eq!(error.field, "transfer");
        assert!(
            error.reason.contains("scenes/ramps/none.png"),
            "{}",
            error.reason
        );
    }
}
