//! A terrain's ground fog in a scene file (Röttger and Ertl 2003 §6): its
//! thickness above the ground, density, transfer function, mode and vertical
//! profile, and the exact cells the reference integrates.
//!
//! ```ron
//! terrain: (
//!     source: Procedural((dims: 257)),
//!     fog: (
//!         thickness: Valley((altitude: 60.0, edge: 8.0)), // fill the valleys to 60 m ± 8 m
//!         // or Noise((thickness: 40.0, coverage: 0.5)): noise patches, up to 40 m thick
//!         // or Png((path: "fog.png", scale: 50.0)): a grayscale map, white = 50 m
//!         density: 0.03,            // extinction at the ground, 1/m; default 0.03
//!         transfer: Preset(GroundFog), // default GroundFog
//!         mode: Sorted,             // or Emissive, Mip; default Sorted
//!         saturate: false,          // Emissive: saturating emission (Eq. 10); default false
//!         profile: [(0.0, 1.0), (1.0, 0.0)], // scalar over relative height; default this
//!         roughness_weight: 1.0,    // the thickness's weight in the quadtree's d2; default 1
//!         debug_wireframe: false,   // draw the cells' edges; default false
//!     ),
//! )
//! ```
//!
//! Heights and altitudes are in the terrain's frame (its `center` at 0), as
//! the plugin's `GroundFog` reads them. The reference draws the fog as the
//! cells the plugin draws for the reference camera, on the ground the GPU
//! draws ([`TerrainDescription::fog_reference`]): the same quadtree,
//! refinement and prisms (`nebel_lod::fog_prisms`), without culling.

use std::path::Path;
use std::sync::Arc;

use glam::{DAffine3, DVec2, DVec3};
use serde::{Deserialize, Serialize};

use nebel_core::field::{FogNoise, HeightField, ValleyFog};
use nebel_core::fog_sunlight::{FogSunMap, FogSunlight};
use nebel_core::local_light::LightResponse;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_lod::quadtree::{TerrainMap, pad_to_power_of_two_plus_one};
use nebel_lod::{
    CellOrder, FogProfile, GpuCell, LodSettings, PrismInput, PrismScalar, TerrainHierarchy,
    TerrainMesh, TriangleOrder, fog_prisms,
};
use nebel_reference::ReferenceCamera;

use super::{
    BuiltVolume, InvalidField, SceneField, TerrainDescription, TerrainTriangles,
    TransferDescription, colour,
};

/// A terrain's ground fog.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GroundFogDescription {
    /// The thickness above the ground.
    pub thickness: FogThicknessDescription,
    /// Multiplies the transfer function's ρ, finite and ≥ 0 (the extinction
    /// at the ground, 1/m, with the default transfer function). Default 0.03.
    #[serde(default = "default_density")]
    pub density: f32,
    /// κ and ρ over the scalar. Default `Preset(GroundFog)`.
    #[serde(default)]
    pub transfer: Option<TransferDescription>,
    /// How segments combine. Default `Sorted`.
    #[serde(default)]
    pub mode: OpticalMode,
    /// With `Emissive`, saturate each segment's emission (Röttger and Ertl
    /// 2003 §6 Eq. 10; `nebel_fog::GroundFog::saturate`); the reference
    /// integrates the sorted model it equals for a constant colour. Only
    /// with `Emissive`. Default false.
    #[serde(default)]
    pub saturate: bool,
    /// `(relative height, scalar)` points from 0 to 1, strictly increasing,
    /// scalars in [0, 1]. Default `[(0, 1), (1, 0)]`.
    #[serde(default = "default_profile")]
    pub profile: Vec<[f32; 2]>,
    /// The thickness's roughness weight in the quadtree's d2, finite and
    /// ≥ 0. Default 1.
    #[serde(default = "default_roughness_weight")]
    pub roughness_weight: f32,
    /// How a sorted fog scatters the scene's volumetric point and spot
    /// lights. Default `(asymmetry: 0.0, strength: 1.0)`.
    #[serde(default)]
    pub light_response: LightResponse,
    /// Sunlight a sorted fog scatters from the scene's directional light,
    /// linear RGB, relative to the light its colour stands for (its glow in
    /// the shade), dimmed by the fog above and cut by the terrain's shadow
    /// (`nebel_fog::GroundFog::sun_color`). Default `(0, 0, 0)`: none.
    #[serde(default)]
    pub sun_color: [f32; 3],
    /// Henyey-Greenstein asymmetry of the sunlight, in (−1, 1). Default 0.6.
    #[serde(default = "default_sun_asymmetry")]
    pub sun_asymmetry: f32,
    /// Debug view: draw every cell's edges. Default false.
    #[serde(default)]
    pub debug_wireframe: bool,
}

fn default_sun_asymmetry() -> f32 {
    0.6
}

fn default_density() -> f32 {
    0.03
}

fn default_profile() -> Vec<[f32; 2]> {
    FogProfile::default().points().to_vec()
}

fn default_roughness_weight() -> f32 {
    1.0
}

/// Where a ground fog's thickness comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum FogThicknessDescription {
    /// The valleys filled up to an altitude with a noisy edge.
    Valley(ValleyFog),
    /// Seeded noise patches.
    Noise(FogNoise),
    /// A grayscale PNG (black 0, white 1) times `scale` metres, covering the
    /// terrain's grid from corner to corner.
    Png(FogMapSource),
}

/// A fog map file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FogMapSource {
    /// The PNG, relative to the scene file.
    pub path: String,
    /// Metres of a white pixel, finite and ≥ 0.
    pub scale: f32,
}

impl GroundFogDescription {
    /// Checks every setting against its documented range (the noise's own
    /// settings are checked when the thickness is built).
    pub(super) fn validate(&self) -> Result<(), InvalidField> {
        let checks: [(&str, f32, bool, &str); 2] = [
            ("density", self.density, self.density >= 0.0, ">= 0"),
            (
                "roughness_weight",
                self.roughness_weight,
                self.roughness_weight >= 0.0,
                ">= 0",
            ),
        ];
        InvalidField::check_finite(checks)?;
        InvalidField::check_light_response(&self.light_response)?;
        colour("sun_color", self.sun_color)?;
        if !(self.sun_asymmetry > -1.0 && self.sun_asymmetry < 1.0) {
            return Err(InvalidField::new(
                "sun_asymmetry",
                format!("must be in (−1, 1), got {}", self.sun_asymmetry),
            ));
        }
        if self.saturate && self.mode != OpticalMode::Emissive {
            return Err(InvalidField::new(
                "saturate",
                format!(
                    "saturates unsorted emissive fog: needs mode Emissive, got {:?}",
                    self.mode
                ),
            ));
        }
        FogProfile::new(self.profile.clone())
            .map_err(|error| InvalidField::new("profile", error.to_string()))?;
        match &self.thickness {
            FogThicknessDescription::Png(map) => {
                if map.path.trim().is_empty() {
                    return Err(InvalidField::new(
                        "thickness.Png.path",
                        "must name a PNG file (relative to the scene file)",
                    ));
                }
                if !(map.scale.is_finite() && map.scale >= 0.0) {
                    return Err(InvalidField::new(
                        "thickness.Png.scale",
                        format!("must be finite and >= 0, got {}", map.scale),
                    ));
                }
            }
            FogThicknessDescription::Valley(valley) => {
                if !(valley.altitude.is_finite() && valley.edge.is_finite() && valley.edge >= 0.0) {
                    return Err(InvalidField::new(
                        "thickness.Valley",
                        format!(
                            "altitude must be finite and edge finite and >= 0, got {} and {}",
                            valley.altitude, valley.edge
                        ),
                    ));
                }
            }
            FogThicknessDescription::Noise(noise) => {
                if !(noise.thickness.is_finite()
                    && noise.thickness >= 0.0
                    && noise.coverage > 0.0
                    && noise.coverage <= 1.0)
                {
                    return Err(InvalidField::new(
                        "thickness.Noise",
                        format!(
                            "thickness must be finite and >= 0 and coverage in (0, 1], got {} and {}",
                            noise.thickness, noise.coverage
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Loads the fog map (for a `Png` thickness) and builds the transfer
    /// function with ρ times `density`; `scene_dir` resolves their paths.
    /// Errors name the field (relative to the fog).
    pub fn build(&self, scene_dir: &Path) -> Result<BuiltGroundFog, InvalidField> {
        let map = match &self.thickness {
            FogThicknessDescription::Png(map) => Some(InvalidField::load_map(
                scene_dir,
                &map.path,
                "thickness.Png.path",
            )?),
            _ => None,
        };
        let transfer = self.transfer.as_ref();
        let preset = TransferPreset::GroundFog;
        Ok(BuiltGroundFog {
            transfer_function: TransferDescription::scaled(
                transfer,
                preset,
                scene_dir,
                self.density,
            )?,
            map,
        })
    }

    /// The thickness at every point of `local` (the terrain's padded heights
    /// in its own frame), from the built fog map for a `Png` thickness.
    pub fn thickness(
        &self,
        local: &HeightField,
        built: &BuiltGroundFog,
    ) -> Result<TerrainMap, InvalidField> {
        let side = local.dims()[0];
        match (&self.thickness, &built.map) {
            (FogThicknessDescription::Valley(valley), _) => valley
                .thickness(local)
                .map_err(|error| InvalidField::new("thickness.Valley", error.to_string()))
                .and_then(|values| layer(side, values, "thickness.Valley")),
            (FogThicknessDescription::Noise(noise), _) => noise
                .thickness(side, local.spacing().x)
                .map_err(|error| InvalidField::new("thickness.Noise", error.to_string()))
                .and_then(|values| layer(side, values, "thickness.Noise")),
            (FogThicknessDescription::Png(map), Some(unit)) => {
                let metres: Vec<f32> = unit.heights().iter().map(|u| u * map.scale).collect();
                TerrainMap::resample(&metres, unit.dims(), side)
                    .map_err(|error| InvalidField::new("thickness.Png.path", error.to_string()))
            }
            (FogThicknessDescription::Png(_), None) => Err(InvalidField::new(
                "thickness.Png.path",
                "the fog map was not loaded",
            )),
        }
    }
}

/// A scene's ground fog with its files read: the fog map (unit values, for
/// a `Png` thickness) and the density-scaled transfer function.
#[derive(Clone, Debug, PartialEq)]
pub struct BuiltGroundFog {
    /// The fog map's unit values (black 0, white 1), `None` unless the
    /// thickness is a `Png`.
    pub map: Option<HeightField>,
    /// κ and ρ, `density` applied.
    pub transfer_function: TransferFunction,
}

fn layer(side: usize, values: Vec<f32>, field: &str) -> Result<TerrainMap, InvalidField> {
    TerrainMap::new(side, values).map_err(|error| InvalidField::new(field, error.to_string()))
}

impl TerrainDescription {
    /// The terrain's heights as the terrain plugin builds them: in its own
    /// frame (`center` at the origin), `vertical_scale · unit`, centred, and
    /// padded to `2^k + 1` points per side.
    pub fn local_heights(&self, unit: &HeightField) -> Result<HeightField, InvalidField> {
        let [nx, nz] = unit.dims();
        let spacing = unit.spacing();
        let half = DVec2::new((nx - 1) as f64, (nz - 1) as f64) * spacing / 2.0;
        let heights = unit
            .heights()
            .iter()
            .map(|u| u * self.vertical_scale)
            .collect();
        HeightField::new(unit.dims(), spacing, -half, heights)
            .map_err(|error| InvalidField::new("source", error.to_string()))
            .and_then(|field| {
                pad_to_power_of_two_plus_one(&field)
                    .map_err(|error| InvalidField::new("source", error.to_string()))
            })
    }

    /// The ground fog's cells for `camera` (world space), as the plugin
    /// draws them with the same quadtree, layer and refinement (its accuracy
    /// [`TerrainDescription::accuracy_for`] the camera; without culling), and the ground they lie on (the refinement's
    /// triangles, which the GPU draws), ready for the reference; `None`
    /// without a fog. `unit` are the terrain's unit heights, `built` the
    /// fog's files ([`GroundFogDescription::build`]), `sun` the unit
    /// direction toward the scene's sun, if it has one (a sorted fog with a
    /// sun colour is lit by it, on the map the plugin builds). Errors name
    /// the field (relative to `terrain`).
    pub fn fog_reference(
        &self,
        unit: &HeightField,
        built: &BuiltGroundFog,
        camera: &ReferenceCamera,
        sun: Option<DVec3>,
    ) -> Result<Option<FogReference>, InvalidField> {
        let Some(fog) = &self.fog else {
            return Ok(None);
        };
        let within = |invalid: InvalidField| invalid.within("fog");
        let local = self.local_heights(unit)?;
        let layer = fog.thickness(&local, built).map_err(within)?;
        let side = local.dims()[0];
        let spacing = local.spacing();
        let quadtree =
            |error: nebel_lod::TerrainError| InvalidField::new("source", error.to_string());
        let mut hierarchy = TerrainHierarchy::new(local, self.min_accuracy).map_err(quadtree)?;
        // As the plugin: a fog that draws nothing (no thickness, no density,
        // a transparent transfer function) leaves the terrain alone.
        let fogged = !layer.is_zero()
            && fog.density > 0.0
            && !built.transfer_function.is_transparent(0.0, 1.0);
        if fogged {
            hierarchy
                .add_map_roughness(&layer, fog.roughness_weight)
                .map_err(quadtree)?;
        }
        let center = DVec3::from(self.center.map(f64::from));
        let settings = LodSettings {
            accuracy: self.accuracy_for(camera)?,
            morph: self.morph,
            normals: false,
            grid_points: true,
            order: TriangleOrder::BackToFront,
        };
        let mut mesh = TerrainMesh::new();
        hierarchy
            .update_with_map(
                camera.position - center,
                None,
                &settings,
                fogged.then_some(&layer),
                &mut mesh,
            )
            .map_err(quadtree)?;
        let offset = center + hierarchy.origin();
        let ground = TerrainTriangles::new(&mesh, offset, side, spacing);
        if !fogged {
            return Ok(Some(FogReference {
                volume: None,
                ground,
            }));
        }
        let profile = FogProfile::new(fog.profile.clone())
            .map_err(|error| InvalidField::new("fog.profile", error.to_string()))?;
        let input = PrismInput {
            world_from_mesh: DAffine3::from_translation(offset),
            eye: camera.position - offset,
            mesh_order: TriangleOrder::BackToFront,
            order: CellOrder::BackToFront,
            profile: &profile,
            scalar: PrismScalar::Profile,
            beyond: None,
        };
        let mut cells = Vec::new();
        fog_prisms(&mesh, &input, &mut cells)
            .map_err(|error| InvalidField::new("fog", error.to_string()))?;
        let fog_sunlight = sun
            .filter(|_| fog.mode == OpticalMode::Sorted && fog.sun_color.iter().any(|c| *c > 0.0))
            .and_then(|sun| {
                let map = FogSunMap::of_fog(
                    hierarchy.field(),
                    layer.values(),
                    &fog.profile,
                    &built.transfer_function,
                    sun,
                )?;
                Some(FogSunlight {
                    map: Arc::new(map),
                    map_from_world: DAffine3::from_translation(-center),
                    direction: sun,
                    colour: DVec3::from(fog.sun_color.map(f64::from)),
                    asymmetry: f64::from(fog.sun_asymmetry),
                    clouds: Vec::new(),
                    occluders: Vec::new(),
                })
            });
        let volume = (!cells.is_empty()).then(|| BuiltVolume {
            field: SceneField::Cells(cells.iter().map(GpuCell::to_tetrahedron).collect()),
            transfer_function: built.transfer_function.clone(),
            // A saturated emissive fog is the sorted model, unsorted.
            mode: if fog.saturate {
                OpticalMode::Sorted
            } else {
                fog.mode
            },
            lod: None,
            lighting: None,
            projected_cells: false,
            ends_where_fog_layers_begin: true,
            light_response: fog.light_response,
            fog_sunlight,
        });
        Ok(Some(FogReference { volume, ground }))
    }
}

/// What the reference draws of a terrain's ground fog: its cells (`None`
/// when it has none) and the ground they lie on.
#[derive(Clone, Debug)]
pub struct FogReference {
    /// The fog's cells as a volume.
    pub volume: Option<BuiltVolume>,
    /// The terrain as the GPU draws it for the same eye.
    pub ground: TerrainTriangles,
}
