//! nebel's scene files: a whole scene as data, in RON, without Bevy.
//!
//! The integration tests and the `nebel` command line load the same files
//! (`assets/scenes/*.ron`, `tests/scenes/*.ron`). This crate is the schema, its
//! loader and its validation, builds the fields a scene describes
//! ([`SceneDescription::build_volumes`], [`SceneDescription::build_terrain`]),
//! and renders a scene's exact reference image ([`mod@reference`]); it knows
//! nothing of Bevy, so the CPU reference renderer reads the same files.
//!
//! The schema (version 1), every field with its default, is written out in
//! the repository's `docs/scene-format.md`; volumes are described in
//! [`VolumeDescription`], the terrain in [`TerrainDescription`]. Right-handed,
//! +Y up, metres; unknown fields are errors, so a typo never goes unnoticed,
//! and every error names the file, the position, the field and the reason,
//! e.g. `scenes/a.ron:4:9: field camera.fov_degrees: must be in (0, 180), got 190`.
//!
//! The papers cited by author and year are listed in `docs/references.md`.

mod aurora;
mod cloud_layer;
mod fog_layers;
mod ground_fog;
pub mod opaque;
pub mod reference;
mod sky_layer;
mod terrain;
mod volume;

pub use aurora::{AuroraDescription, BuiltAurora, StarsDescription};
pub use cloud_layer::{BuiltCloudLayer, CloudLayerDescription, CloudLayerMaps};
pub use fog_layers::FogLayersDescription;
pub use ground_fog::{
    BuiltGroundFog, FogMapSource, FogReference, FogThicknessDescription, GroundFogDescription,
};
pub use opaque::{ReferenceTerrain, TerrainTriangles};
pub use terrain::{
    PngTerrainSource, ProceduralTerrainSource, TerrainDescription, TerrainHeightSource,
};

pub use volume::{
    AnimatedCampfire, AnimatedCloud, Axis, BuiltVolume, CampfireSource, CloudSource, LightModel,
    LightingDescription, LodDescription, ProceduralSource, RampSource, SceneField,
    SearchLightSource, SourceDescription, TetrahedronDescription, TransferDescription,
    TransferStrip, UniformSource, VolumeDescription,
};

use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::{DAffine3, DVec2, DVec3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use nebel_core::budget::{BudgetError, Dims, check_allocation, check_bytes};
use nebel_core::field::{HeightField, PlacedHeights, PlacedTerrainShadow, TerrainShadow};
use nebel_core::local_light::{LightResponse, LocalLight, SpotCone, flicker};
use nebel_reference::ReferenceCamera;
use nebel_reference::image_metrics::{LinearImage, srgb_to_linear};

/// The schema version this build reads and writes.
pub const SCENE_VERSION: u32 = 1;

/// A scene file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneDescription {
    /// Schema version; must be [`SCENE_VERSION`].
    pub version: u32,
    /// Image size and frame count. Default: [`OutputSettings::default`].
    #[serde(default)]
    pub output: OutputSettings,
    /// The camera.
    pub camera: CameraSettings,
    /// Background colour where nothing is drawn, sRGB. Default: `(0.0, 0.0, 0.0)`.
    #[serde(default)]
    pub clear_color: [f32; 3],
    /// Lights. Default: none.
    #[serde(default)]
    pub lights: Vec<LightDescription>,
    /// Plain meshes with one colour each. Default: none.
    #[serde(default)]
    pub meshes: Vec<MeshDescription>,
    /// Volumes (clouds, smoke, fire, search lights), see [`VolumeDescription`].
    /// Default: none.
    #[serde(default)]
    pub volumes: Vec<VolumeDescription>,
    /// A terrain drawn through the quadtree C-LOD, see
    /// [`TerrainDescription`]. Default: none.
    #[serde(default)]
    pub terrain: Option<TerrainDescription>,
    /// Height fog over the whole scene, seen by the camera, see
    /// [`FogLayersDescription`]. Default: none.
    #[serde(default)]
    pub fog_layers: Option<FogLayersDescription>,
    /// An aurora over the scene, see [`AuroraDescription`]. Default: none.
    #[serde(default)]
    pub aurora: Option<AuroraDescription>,
    /// Stars on the sky, see [`StarsDescription`]. Default: none.
    #[serde(default)]
    pub stars: Option<StarsDescription>,
    /// A cloud layer between two surfaces, see [`CloudLayerDescription`].
    /// Default: none.
    #[serde(default)]
    pub cloud_layer: Option<CloudLayerDescription>,
    /// The quality preset every effect draws at (`nebel_render`'s
    /// `NebelQuality`): `Low`, `Medium` or `High`. Default `High`. The
    /// reference ignores it.
    #[serde(default)]
    pub quality: QualityDescription,
    /// The frame time in ms that `NebelQuality`'s automatic mode holds by
    /// lowering the detail below the preset's, finite and > 0. Default none
    /// (the preset's detail).
    #[serde(default)]
    pub auto_quality_ms: Option<f32>,
}

/// The quality preset of a scene, see [`SceneDescription::quality`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum QualityDescription {
    /// Fog layers only (no ground fog prisms); clouds at a quarter, terrain
    /// at half their accuracy.
    Low,
    /// Clouds at half, terrain at three quarters of their accuracy.
    Medium,
    /// Every effect at its own accuracy.
    #[default]
    High,
}

/// Image size and the frames to run before the image is taken.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OutputSettings {
    /// Image width in pixels, 1 to 8192. Default: 640.
    pub width: u32,
    /// Image height in pixels, 1 to 8192. Default: 360.
    pub height: u32,
    /// Frames to run; the image shows the last. Default: 1.
    pub frames: u32,
    /// Simulated frames per second: frame `i` is at time `i / frame_rate`
    /// seconds, whatever the real frame time. Default: 60.
    pub frame_rate: f32,
}

impl Default for OutputSettings {
    fn default() -> Self {
        Self {
            width: 640,
            height: 360,
            frames: 1,
            frame_rate: 60.0,
        }
    }
}

/// The camera: a perspective projection and where it looks from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSettings {
    /// Vertical field of view in degrees, in (0, 180). Default: 60.
    #[serde(default = "default_fov_degrees")]
    pub fov_degrees: f32,
    /// Near plane distance in metres, > 0. Default: 0.1.
    #[serde(default = "default_near")]
    pub near: f32,
    /// A fixed pose or a path of keyframes.
    pub view: CameraView,
    /// Whether the HDR image is tonemapped (Bevy's `TonyMcMapface` with
    /// debanding) before it is written. `false` writes linear HDR values,
    /// clamped, sRGB encoded: what `nebel reference` computes, so accuracy
    /// tests compare like with like. Default: true.
    #[serde(default = "default_tonemapping")]
    pub tonemapping: bool,
    /// Multisample anti-aliasing samples per pixel: 1 (off), 2, 4 or 8.
    /// The reference samples each pixel's centre once, so accuracy scenes with
    /// mesh edges use 1. Default: 4 (Bevy's).
    #[serde(default = "default_msaa")]
    pub msaa: u32,
    /// How the cells are drawn (`nebel_render`'s `CellProjection`), e.g.
    /// `cell_projection: (resolution: Full, early_termination: false)`, the
    /// exact method of the papers. Default: as the quality preset says.
    #[serde(default)]
    pub cell_projection: Option<CellProjectionDescription>,
}

/// How a camera draws cells, see [`CameraSettings::cell_projection`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellProjectionDescription {
    /// `Full`, `Half` or `Quarter` of the view's resolution, mixed with full
    /// resolution where the lower one would be off. Default `Half`.
    #[serde(default)]
    pub resolution: CellResolutionDescription,
    /// Below full resolution, the largest interpolation error (linear RGB
    /// and transmittance) a pixel may take from the lower resolution before
    /// it is drawn at full resolution; finite and ≥ 0. Default 0.004.
    #[serde(default = "default_upsample_tolerance")]
    pub upsample_tolerance: f32,
    /// Stop shading pixels whose transmittance fell below 1/512. Default
    /// true.
    #[serde(default = "default_early_termination")]
    pub early_termination: bool,
}

impl Default for CellProjectionDescription {
    fn default() -> Self {
        Self {
            resolution: CellResolutionDescription::default(),
            upsample_tolerance: default_upsample_tolerance(),
            early_termination: default_early_termination(),
        }
    }
}

impl CellProjectionDescription {
    /// Every cell at full resolution, every ray to its end.
    pub const EXACT: Self = Self {
        resolution: CellResolutionDescription::Full,
        upsample_tolerance: 0.0,
        early_termination: false,
    };
}

fn default_early_termination() -> bool {
    true
}

fn default_upsample_tolerance() -> f32 {
    0.004
}

/// The resolution of [`CellProjectionDescription`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum CellResolutionDescription {
    /// Every pixel.
    Full,
    /// Half the width and height.
    #[default]
    Half,
    /// A quarter of the width and height.
    Quarter,
}

fn default_msaa() -> u32 {
    4
}

fn default_tonemapping() -> bool {
    true
}

fn default_fov_degrees() -> f32 {
    60.0
}

fn default_near() -> f32 {
    0.1
}

/// Where the camera is.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum CameraView {
    /// One pose for every frame.
    Pose(CameraPose),
    /// Keyframes with strictly increasing times; between two keyframes position
    /// and target are interpolated linearly, before the first and after the
    /// last they hold.
    Path(Vec<CameraKeyframe>),
}

/// A camera position and the point it looks at (+Y is up).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraPose {
    /// Eye position, metres.
    pub position: [f32; 3],
    /// Point the camera looks at, metres; must differ from `position`.
    pub look_at: [f32; 3],
}

/// One keyframe of a camera path.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraKeyframe {
    /// Time in seconds.
    pub time: f32,
    /// Eye position, metres.
    pub position: [f32; 3],
    /// Point the camera looks at, metres; must differ from `position`.
    pub look_at: [f32; 3],
}

/// A light source.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum LightDescription {
    /// Sunlight: parallel rays.
    Directional(DirectionalLightDescription),
    /// A point light with a range.
    Point(PointLightDescription),
    /// A spot light: a point light in a cone.
    Spot(SpotLightDescription),
    /// Light from everywhere, applied to every surface.
    Ambient(AmbientLightDescription),
}

/// Sunlight.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DirectionalLightDescription {
    /// The direction the light travels in (from the sun to the ground); non-zero.
    pub direction: [f32; 3],
    /// sRGB colour. Default: white.
    #[serde(default = "white")]
    pub color: [f32; 3],
    /// Illuminance in lux. Default: 10 000 (overcast day).
    #[serde(default = "default_illuminance")]
    pub illuminance: f32,
    /// Whether it casts shadows. Default: false.
    #[serde(default)]
    pub shadows: bool,
    /// The light turns with the time (a day cycle): its direction at time
    /// `t` is `direction` turned about `axis` by `degrees_per_second · t`.
    /// Default: none (still).
    #[serde(default)]
    pub turn: Option<LightTurn>,
}

/// A light turning at a constant rate about an axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightTurn {
    /// The axis it turns about, world space, non-zero (normalised).
    pub axis: [f32; 3],
    /// How fast it turns, degrees per second, finite (positive turns
    /// counter-clockwise seen from the axis' tip).
    pub degrees_per_second: f32,
}

impl DirectionalLightDescription {
    /// The direction the light travels in at `time` seconds (normalised),
    /// turned by [`Self::turn`].
    pub fn direction_at(&self, time: f64) -> DVec3 {
        let direction = DVec3::from(self.direction.map(f64::from)).normalize_or(DVec3::NEG_Y);
        let Some(turn) = self.turn else {
            return direction;
        };
        let axis = DVec3::from(turn.axis.map(f64::from)).normalize_or(DVec3::X);
        let angle = f64::from(turn.degrees_per_second).to_radians() * time;
        glam::DQuat::from_axis_angle(axis, angle) * direction
    }
}

fn default_illuminance() -> f32 {
    10_000.0
}

/// A point light.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PointLightDescription {
    /// Position, metres.
    pub position: [f32; 3],
    /// sRGB colour. Default: white.
    #[serde(default = "white")]
    pub color: [f32; 3],
    /// Luminous power in lumens. Default: 100 000.
    #[serde(default = "default_point_intensity")]
    pub intensity: f32,
    /// Distance beyond which it lights nothing, metres, > 0. Default: 20.
    #[serde(default = "default_point_range")]
    pub range: f32,
    /// Relative amplitude of a firelight flicker of the intensity, in [0, 1];
    /// 0 is steady. Default: 0.
    #[serde(default)]
    pub flicker: f32,
    /// Whether it casts shadows. Default: false.
    #[serde(default)]
    pub shadows: bool,
    /// Whether sorted volumes scatter its light (Bevy's `VolumetricLight`).
    /// Default: false.
    #[serde(default)]
    pub volumetric: bool,
}

/// A spot light.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpotLightDescription {
    /// Position, metres.
    pub position: [f32; 3],
    /// Point it shines at, metres; must differ from `position`.
    pub look_at: [f32; 3],
    /// sRGB colour. Default: white.
    #[serde(default = "white")]
    pub color: [f32; 3],
    /// Luminous power in lumens, as Bevy's `SpotLight::intensity`. Default:
    /// 100 000.
    #[serde(default = "default_point_intensity")]
    pub intensity: f32,
    /// Distance beyond which it lights nothing, metres, > 0. Default: 20.
    #[serde(default = "default_point_range")]
    pub range: f32,
    /// Half-angle of the fully lit cone, degrees, in [0, outer]. Default: 0.
    #[serde(default)]
    pub inner_angle_degrees: f32,
    /// Half-angle beyond which it lights nothing, degrees, in (0, 90).
    /// Default: 45.
    #[serde(default = "default_outer_angle")]
    pub outer_angle_degrees: f32,
    /// Whether it casts shadows. Default: false.
    #[serde(default)]
    pub shadows: bool,
    /// Whether sorted volumes scatter its light (Bevy's `VolumetricLight`).
    /// Default: false.
    #[serde(default)]
    pub volumetric: bool,
}

fn default_outer_angle() -> f32 {
    45.0
}

fn default_point_intensity() -> f32 {
    100_000.0
}

fn default_point_range() -> f32 {
    20.0
}

/// Ambient light.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AmbientLightDescription {
    /// sRGB colour. Default: white.
    #[serde(default = "white")]
    pub color: [f32; 3],
    /// Luminance in cd/m², as Bevy's `AmbientLight::brightness`. Default: 80.
    #[serde(default = "default_ambient_brightness")]
    pub brightness: f32,
}

fn default_ambient_brightness() -> f32 {
    80.0
}

/// A plain mesh with one colour.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum MeshDescription {
    /// A horizontal rectangle facing +Y.
    Plane(PlaneDescription),
    /// An axis-aligned box.
    Box(BoxDescription),
    /// A sphere.
    Sphere(SphereDescription),
}

/// A horizontal rectangle facing +Y.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaneDescription {
    /// Centre, metres.
    pub center: [f32; 3],
    /// Extent along X and Z, metres, each > 0.
    pub size: [f32; 2],
    /// sRGB colour. Default: white.
    #[serde(default = "white")]
    pub color: [f32; 3],
}

/// An axis-aligned box.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxDescription {
    /// Centre, metres.
    pub center: [f32; 3],
    /// Extent along X, Y and Z, metres, each > 0.
    pub size: [f32; 3],
    /// sRGB colour. Default: white.
    #[serde(default = "white")]
    pub color: [f32; 3],
}

/// A sphere.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SphereDescription {
    /// Centre, metres.
    pub center: [f32; 3],
    /// Radius, metres, > 0.
    pub radius: f32,
    /// sRGB colour. Default: white.
    #[serde(default = "white")]
    pub color: [f32; 3],
}

fn white() -> [f32; 3] {
    [1.0; 3]
}

/// Why a scene file could not be used. Every variant names the file.
#[derive(Debug, Error)]
pub enum SceneError {
    /// The file could not be read.
    #[error("{}: cannot read scene file: {source}", path.display())]
    Read {
        /// The scene file.
        path: PathBuf,
        /// What the operating system said.
        source: std::io::Error,
    },
    /// The file is not valid RON for the schema (syntax, unknown or missing
    /// field, wrong type).
    #[error("{}:{line}:{column}: field {field}: {reason}", path.display())]
    Parse {
        /// The scene file.
        path: PathBuf,
        /// 1-based line of the error.
        line: usize,
        /// 1-based column of the error.
        column: usize,
        /// Dotted path of the field, `(top level)` outside any field.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// The file is larger than the memory budget; it was not read.
    #[error("{}: {source}", path.display())]
    OverBudget {
        /// The scene file.
        path: PathBuf,
        /// The file's size and the budget.
        source: BudgetError,
    },
    /// The file parsed but a value is out of range, or what it describes
    /// would exceed the memory budget.
    #[error("{}: field {field}: {reason}", path.display())]
    Invalid {
        /// The scene file.
        path: PathBuf,
        /// Dotted path of the field.
        field: String,
        /// What is wrong.
        reason: String,
    },
}

impl SceneDescription {
    /// Reads, parses and validates a scene file. A file larger than the
    /// memory budget is refused before it is read.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, SceneError> {
        let path = path.as_ref();
        let read_error = |source| SceneError::Read {
            path: path.to_owned(),
            source,
        };
        let length = std::fs::metadata(path).map_err(read_error)?.len();
        check_bytes(|| String::from("the scene file"), u128::from(length)).map_err(|source| {
            SceneError::OverBudget {
                path: path.to_owned(),
                source,
            }
        })?;
        let text = std::fs::read_to_string(path).map_err(read_error)?;
        Self::from_ron(&text, path)
    }

    /// Parses and validates scene text; `origin` names the file in errors.
    pub fn from_ron(text: &str, origin: &Path) -> Result<Self, SceneError> {
        let parse_error = |field: String, error: ron::error::SpannedError| SceneError::Parse {
            path: origin.to_owned(),
            line: error.span.start.line,
            column: error.span.start.col,
            field,
            reason: error.code.to_string(),
        };
        let mut deserializer = ron::Deserializer::from_str_with_options(
            text,
            &ron::Options::default()
                .with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME),
        )
        .map_err(|error| parse_error(String::from("(top level)"), error))?;
        let scene: Self = serde_path_to_error::deserialize(&mut deserializer).map_err(|error| {
            let field = match error.path().to_string() {
                path if path == "." => String::from("(top level)"),
                path => path,
            };
            let spanned = deserializer.span_error(error.into_inner());
            parse_error(field, spanned)
        })?;
        deserializer.end().map_err(|code| {
            parse_error(String::from("(top level)"), deserializer.span_error(code))
        })?;
        scene.validate().map_err(|invalid| SceneError::Invalid {
            path: origin.to_owned(),
            field: invalid.field,
            reason: invalid.reason,
        })?;
        Ok(scene)
    }

    /// Writes the scene as pretty RON that [`SceneDescription::from_ron`] reads back.
    pub fn to_ron(&self) -> String {
        ron::ser::to_string_pretty(self, ron::ser::PrettyConfig::default())
            .expect("a scene description always serialises")
    }

    /// The camera pose at `time` seconds (see [`CameraView::Path`]).
    pub fn camera_pose_at(&self, time: f32) -> CameraPose {
        match &self.camera.view {
            CameraView::Pose(pose) => *pose,
            CameraView::Path(keyframes) => {
                let pose = |k: &CameraKeyframe| CameraPose {
                    position: k.position,
                    look_at: k.look_at,
                };
                let next = keyframes.partition_point(|k| k.time <= time);
                if next == 0 {
                    return pose(&keyframes[0]);
                }
                if next == keyframes.len() {
                    return pose(&keyframes[keyframes.len() - 1]);
                }
                let (a, b) = (&keyframes[next - 1], &keyframes[next]);
                let t = (time - a.time) / (b.time - a.time);
                let lerp =
                    |x: [f32; 3], y: [f32; 3]| std::array::from_fn(|i| x[i] + (y[i] - x[i]) * t);
                CameraPose {
                    position: lerp(a.position, b.position),
                    look_at: lerp(a.look_at, b.look_at),
                }
            }
        }
    }

    /// The camera of the last frame as the CPU reference renderer takes it.
    pub fn reference_camera(&self) -> ReferenceCamera {
        let pose = self.camera_pose_at(self.frame_time(self.output.frames.saturating_sub(1)));
        let position = DVec3::from(pose.position.map(f64::from));
        ReferenceCamera {
            position,
            vertical_fov: f64::from(self.camera.fov_degrees).to_radians(),
            width: self.output.width,
            height: self.output.height,
            near: f64::from(self.camera.near),
            ..ReferenceCamera::default()
        }
        .looking_at(DVec3::from(pose.look_at.map(f64::from)), DVec3::Y)
    }

    /// The direction toward the sun at the last frame: against the travel
    /// direction of the first directional light, normalised; `None` without
    /// one. Lit volumes use it (straight up when `None`), as the Bevy side
    /// does.
    pub fn sun_direction(&self) -> Option<DVec3> {
        let last_frame = f64::from(self.frame_time(self.output.frames.saturating_sub(1)));
        self.lights.iter().find_map(|light| match light {
            LightDescription::Directional(sun) => (-sun.direction_at(last_frame)).try_normalize(),
            _ => None,
        })
    }

    /// Whether the scene's directional light casts shadows (none: false).
    pub fn sun_casts_shadows(&self) -> bool {
        self.lights
            .iter()
            .find_map(|light| match light {
                LightDescription::Directional(sun) => Some(sun.shadows),
                _ => None,
            })
            .unwrap_or(false)
    }

    /// The sky's colour, linear: the colour of the scene's ambient light
    /// (Bevy's `GlobalAmbientLight`), white without one. It tints the
    /// ambient light of clouds lit by single scattering.
    pub fn sky_colour(&self) -> DVec3 {
        self.lights
            .iter()
            .rev()
            .find_map(|light| match light {
                LightDescription::Ambient(ambient) => Some(DVec3::from(
                    ambient.color.map(|c| srgb_to_linear(f64::from(c))),
                )),
                _ => None,
            })
            .unwrap_or(DVec3::ONE)
    }

    /// Whether a volume's cloud shadow falls on the meshes and terrain
    /// (`lighting: (ground_shadow: true)`): then they all receive it.
    pub fn casts_ground_shadow(&self) -> bool {
        self.volumes.iter().any(|volume| {
            volume
                .lighting
                .as_ref()
                .is_some_and(|lighting| lighting.ground_shadow)
        })
    }

    /// The point and spot lights marked `volumetric`, as the volumes scatter
    /// them at `time` seconds (a flickering light's intensity then), in
    /// linear colour.
    pub fn volumetric_lights(&self, time: f64) -> Vec<LocalLight> {
        let linear = |color: [f32; 3]| DVec3::from(color.map(|c| srgb_to_linear(f64::from(c))));
        self.lights
            .iter()
            .filter_map(|light| match light {
                LightDescription::Point(point) if point.volumetric => Some(LocalLight {
                    shadows: point.shadows,
                    ..LocalLight::from_lumens(
                        DVec3::from(point.position.map(f64::from)),
                        linear(point.color),
                        f64::from(point.intensity) * flicker(f64::from(point.flicker), time),
                        f64::from(point.range),
                    )
                }),
                LightDescription::Spot(spot) if spot.volumetric => {
                    let position = DVec3::from(spot.position.map(f64::from));
                    let target = DVec3::from(spot.look_at.map(f64::from));
                    Some(LocalLight {
                        cone: Some(SpotCone::new(
                            target - position,
                            f64::from(spot.inner_angle_degrees).to_radians(),
                            f64::from(spot.outer_angle_degrees).to_radians(),
                        )),
                        shadows: spot.shadows,
                        ..LocalLight::from_lumens(
                            position,
                            linear(spot.color),
                            f64::from(spot.intensity),
                            f64::from(spot.range),
                        )
                    })
                }
                _ => None,
            })
            .collect()
    }

    /// The simulated time of frame `index` in seconds.
    pub fn frame_time(&self, index: u32) -> f32 {
        index as f32 / self.output.frame_rate
    }

    /// Checks every value against its documented range, and that what the
    /// scene describes fits the memory budget (`nebel_core::budget`): every
    /// volume's structures, the terrain's, the reference image and its
    /// opaque depth.
    pub fn validate(&self) -> Result<(), InvalidField> {
        if self.version != SCENE_VERSION {
            return Err(InvalidField::new(
                "version",
                format!(
                    "this build reads version {SCENE_VERSION}, got {}",
                    self.version
                ),
            ));
        }
        let output = &self.output;
        in_range("output.width", output.width as f32, 1.0, 8192.0)?;
        in_range("output.height", output.height as f32, 1.0, 8192.0)?;
        in_range("output.frames", output.frames as f32, 1.0, 1.0e6)?;
        positive("output.frame_rate", output.frame_rate)?;
        check_output_budget(output.width, output.height)
            .map_err(|error| InvalidField::new("output", error.to_string()))?;
        let camera = &self.camera;
        if !(camera.fov_degrees > 0.0 && camera.fov_degrees < 180.0) {
            return Err(InvalidField::new(
                "camera.fov_degrees",
                format!("must be in (0, 180), got {}", camera.fov_degrees),
            ));
        }
        positive("camera.near", camera.near)?;
        if let Some(cell_projection) = camera.cell_projection
            && !(cell_projection.upsample_tolerance.is_finite()
                && cell_projection.upsample_tolerance >= 0.0)
        {
            return Err(InvalidField::new(
                "camera.cell_projection.upsample_tolerance",
                format!(
                    "must be finite and ≥ 0, got {}",
                    cell_projection.upsample_tolerance
                ),
            ));
        }
        if ![1, 2, 4, 8].contains(&camera.msaa) {
            return Err(InvalidField::new(
                "camera.msaa",
                format!("must be 1, 2, 4 or 8, got {}", camera.msaa),
            ));
        }
        match &camera.view {
            CameraView::Pose(pose) => pose_valid("camera.view.Pose", pose.position, pose.look_at)?,
            CameraView::Path(keyframes) => {
                if keyframes.is_empty() {
                    return Err(InvalidField::new(
                        "camera.view.Path",
                        "needs at least one keyframe",
                    ));
                }
                for (index, keyframe) in keyframes.iter().enumerate() {
                    let field = format!("camera.view.Path[{index}]");
                    finite(&format!("{field}.time"), &[keyframe.time])?;
                    pose_valid(&field, keyframe.position, keyframe.look_at)?;
                    if index > 0 && keyframe.time <= keyframes[index - 1].time {
                        return Err(InvalidField::new(
                            format!("{field}.time"),
                            format!(
                                "times must increase strictly, got {} after {}",
                                keyframe.time,
                                keyframes[index - 1].time
                            ),
                        ));
                    }
                }
            }
        }
        colour("clear_color", self.clear_color)?;
        for (index, light) in self.lights.iter().enumerate() {
            match light {
                LightDescription::Directional(sun) => {
                    let field = format!("lights[{index}].Directional");
                    finite(&format!("{field}.direction"), &sun.direction)?;
                    if sun.direction.iter().all(|c| *c == 0.0) {
                        return Err(InvalidField::new(
                            format!("{field}.direction"),
                            "must not be zero",
                        ));
                    }
                    colour(&format!("{field}.color"), sun.color)?;
                    non_negative(&format!("{field}.illuminance"), sun.illuminance)?;
                    if let Some(turn) = &sun.turn {
                        finite(&format!("{field}.turn.axis"), &turn.axis)?;
                        if turn.axis.iter().all(|c| *c == 0.0) {
                            return Err(InvalidField::new(
                                format!("{field}.turn.axis"),
                                "must not be zero",
                            ));
                        }
                        if !turn.degrees_per_second.is_finite() {
                            return Err(InvalidField::new(
                                format!("{field}.turn.degrees_per_second"),
                                format!("must be finite, got {}", turn.degrees_per_second),
                            ));
                        }
                    }
                }
                LightDescription::Point(point) => {
                    let field = format!("lights[{index}].Point");
                    finite(&format!("{field}.position"), &point.position)?;
                    colour(&format!("{field}.color"), point.color)?;
                    non_negative(&format!("{field}.intensity"), point.intensity)?;
                    positive(&format!("{field}.range"), point.range)?;
                    if !(0.0..=1.0).contains(&point.flicker) {
                        return Err(InvalidField::new(
                            format!("{field}.flicker"),
                            format!("must be in [0, 1], got {}", point.flicker),
                        ));
                    }
                }
                LightDescription::Spot(spot) => {
                    let field = format!("lights[{index}].Spot");
                    finite(&format!("{field}.position"), &spot.position)?;
                    finite(&format!("{field}.look_at"), &spot.look_at)?;
                    if spot.look_at == spot.position {
                        return Err(InvalidField::new(
                            format!("{field}.look_at"),
                            "must differ from position",
                        ));
                    }
                    colour(&format!("{field}.color"), spot.color)?;
                    non_negative(&format!("{field}.intensity"), spot.intensity)?;
                    positive(&format!("{field}.range"), spot.range)?;
                    if !(spot.outer_angle_degrees > 0.0 && spot.outer_angle_degrees < 90.0) {
                        return Err(InvalidField::new(
                            format!("{field}.outer_angle_degrees"),
                            format!("must be in (0, 90), got {}", spot.outer_angle_degrees),
                        ));
                    }
                    if !(0.0..=spot.outer_angle_degrees).contains(&spot.inner_angle_degrees) {
                        return Err(InvalidField::new(
                            format!("{field}.inner_angle_degrees"),
                            format!(
                                "must be in [0, outer_angle_degrees], got {}",
                                spot.inner_angle_degrees
                            ),
                        ));
                    }
                }
                LightDescription::Ambient(ambient) => {
                    let field = format!("lights[{index}].Ambient");
                    colour(&format!("{field}.color"), ambient.color)?;
                    non_negative(&format!("{field}.brightness"), ambient.brightness)?;
                }
            }
        }
        for (index, mesh) in self.meshes.iter().enumerate() {
            let (field, center, extents, color): (_, _, &[f32], _) = match mesh {
                MeshDescription::Plane(plane) => ("Plane", plane.center, &plane.size, plane.color),
                MeshDescription::Box(cuboid) => ("Box", cuboid.center, &cuboid.size, cuboid.color),
                MeshDescription::Sphere(sphere) => (
                    "Sphere",
                    sphere.center,
                    std::slice::from_ref(&sphere.radius),
                    sphere.color,
                ),
            };
            let field = format!("meshes[{index}].{field}");
            finite(&format!("{field}.center"), &center)?;
            let extent_name = if matches!(mesh, MeshDescription::Sphere(_)) {
                "radius"
            } else {
                "size"
            };
            for extent in extents {
                positive(&format!("{field}.{extent_name}"), *extent)?;
            }
            colour(&format!("{field}.color"), color)?;
        }
        for (index, volume) in self.volumes.iter().enumerate() {
            volume
                .validate()
                .map_err(|invalid| invalid.within(&format!("volumes[{index}]")))?;
        }
        if let Some(terrain) = &self.terrain {
            terrain
                .validate()
                .map_err(|invalid| invalid.within("terrain"))?;
        }
        if let Some(target) = self.auto_quality_ms {
            positive("auto_quality_ms", target)?;
        }
        if let Some(fog_layers) = &self.fog_layers {
            fog_layers
                .validate()
                .map_err(|invalid| invalid.within("fog_layers"))?;
        }
        if let Some(aurora) = &self.aurora {
            aurora
                .validate()
                .map_err(|invalid| invalid.within("aurora"))?;
        }
        if let Some(stars) = &self.stars {
            stars
                .validate()
                .map_err(|invalid| invalid.within("stars"))?;
        }
        if let Some(layer) = &self.cloud_layer {
            layer
                .validate()
                .map_err(|invalid| invalid.within("cloud_layer"))?;
        }
        Ok(())
    }

    /// Reads the cloud layer's files ([`CloudLayerDescription::build`]);
    /// `None` without a cloud layer.
    pub fn build_cloud_layer(
        &self,
        scene_path: &Path,
    ) -> Result<Option<BuiltCloudLayer>, SceneError> {
        let Some(layer) = &self.cloud_layer else {
            return Ok(None);
        };
        let scene_dir = scene_path.parent().unwrap_or(Path::new("."));
        layer
            .build(scene_dir)
            .map(Some)
            .map_err(|invalid| invalid.in_scene(scene_path, "cloud_layer"))
    }

    /// The cloud layer's cells for the reference camera and the scene's sun
    /// ([`CloudLayerDescription::reference`]); `None` without a cloud layer
    /// or cells.
    pub fn build_cloud_layer_reference(
        &self,
        scene_path: &Path,
        built: &BuiltCloudLayer,
    ) -> Result<Option<BuiltVolume>, SceneError> {
        let Some(layer) = &self.cloud_layer else {
            return Ok(None);
        };
        let toward_sun = self.sun_direction().unwrap_or(DVec3::Y);
        layer
            .reference(built, self.reference_camera().position, toward_sun)
            .map_err(|invalid| invalid.in_scene(scene_path, "cloud_layer"))
    }

    /// Reads the aurora's files ([`AuroraDescription::build`]); `None`
    /// without an aurora. `scene_path` names the file in errors and resolves
    /// the map's path.
    pub fn build_aurora(&self, scene_path: &Path) -> Result<Option<BuiltAurora>, SceneError> {
        let Some(aurora) = &self.aurora else {
            return Ok(None);
        };
        let scene_dir = scene_path.parent().unwrap_or(Path::new("."));
        aurora
            .build(scene_dir)
            .map(Some)
            .map_err(|invalid| invalid.in_scene(scene_path, "aurora"))
    }

    /// The aurora's cells for the reference camera at the last frame's time
    /// ([`AuroraDescription::reference`]); `None` without an aurora or cells.
    pub fn build_aurora_reference(
        &self,
        scene_path: &Path,
        built: &BuiltAurora,
    ) -> Result<Option<BuiltVolume>, SceneError> {
        let Some(aurora) = &self.aurora else {
            return Ok(None);
        };
        let last_frame = self.frame_time(self.output.frames.saturating_sub(1));
        aurora
            .reference(
                built,
                self.reference_camera().position,
                f64::from(last_frame),
            )
            .map_err(|invalid| invalid.in_scene(scene_path, "aurora"))
    }

    /// Generates or loads the terrain's unit heights
    /// ([`TerrainDescription::unit_heights`]); `None` without a terrain.
    /// `scene_path` is the scene file: it names the file in errors and
    /// resolves the PNG's relative path.
    pub fn build_terrain(&self, scene_path: &Path) -> Result<Option<HeightField>, SceneError> {
        let Some(terrain) = &self.terrain else {
            return Ok(None);
        };
        let scene_dir = scene_path.parent().unwrap_or(Path::new("."));
        terrain
            .unit_heights(scene_dir)
            .map(Some)
            .map_err(|invalid| invalid.in_scene(scene_path, "terrain"))
    }

    /// Reads the terrain fog's files ([`GroundFogDescription::build`]);
    /// `None` without a terrain fog. `scene_path` is the scene file: it names
    /// the file in errors and resolves the fog map's relative path.
    pub fn build_ground_fog(
        &self,
        scene_path: &Path,
    ) -> Result<Option<BuiltGroundFog>, SceneError> {
        let Some(fog) = self
            .terrain
            .as_ref()
            .and_then(|terrain| terrain.fog.as_ref())
        else {
            return Ok(None);
        };
        let scene_dir = scene_path.parent().unwrap_or(Path::new("."));
        fog.build(scene_dir)
            .map(Some)
            .map_err(|invalid| invalid.in_scene(scene_path, "terrain.fog"))
    }

    /// The terrain fog's cells and ground for the reference camera
    /// ([`TerrainDescription::fog_reference`]); `None` without a terrain
    /// fog.
    pub fn build_fog_reference(
        &self,
        scene_path: &Path,
        unit: &HeightField,
        built: &BuiltGroundFog,
    ) -> Result<Option<FogReference>, SceneError> {
        let Some(terrain) = &self.terrain else {
            return Ok(None);
        };
        terrain
            .fog_reference(unit, built, &self.reference_camera(), self.sun_direction())
            .map_err(|invalid| invalid.in_scene(scene_path, "terrain"))
    }

    /// The terrain's shadow heights over sunlit fog layers, as the fog
    /// layers' plugin builds them (`TerrainShadow::of_field` of the
    /// terrain's heights in its own frame); `None` without a terrain, fog
    /// layers with a sun colour, or a sun that casts a map.
    pub fn build_terrain_shadow(
        &self,
        scene_path: &Path,
        unit: &HeightField,
    ) -> Result<Option<PlacedTerrainShadow>, SceneError> {
        let (Some(terrain), Some(fog), Some(sun)) =
            (&self.terrain, &self.fog_layers, self.sun_direction())
        else {
            return Ok(None);
        };
        if fog.sun_color.iter().all(|c| *c <= 0.0) {
            return Ok(None);
        }
        let local = terrain
            .local_heights(unit)
            .map_err(|invalid| invalid.in_scene(scene_path, "terrain"))?;
        let map_from_world =
            DAffine3::from_translation(-DVec3::from(terrain.center.map(f64::from)));
        Ok(TerrainShadow::of_field(&local, sun)
            .map(|shadow| PlacedTerrainShadow::new(Arc::new(shadow), map_from_world)))
    }

    /// The terrain's bilinear heights in world space as an opaque shape
    /// (`unit` its heights from [`SceneDescription::build_terrain`]): the
    /// reference's occluder of the point and spot lights that cast shadows,
    /// as Bevy's shadow maps hold the terrain. `None` without a terrain.
    pub fn terrain_occluder(&self, unit: &HeightField) -> Option<PlacedHeights> {
        let terrain = self.terrain.as_ref()?;
        Some(PlacedHeights::new(
            Arc::new(terrain.world_heights(unit)),
            DAffine3::IDENTITY,
        ))
    }

    /// Generates or loads every volume's field and transfer function.
    /// `scene_path` is the scene file: it names the file in errors and
    /// resolves paths relative to it.
    pub fn build_volumes(&self, scene_path: &Path) -> Result<Vec<BuiltVolume>, SceneError> {
        let scene_dir = scene_path.parent().unwrap_or(Path::new("."));
        self.volumes
            .iter()
            .enumerate()
            .map(|(index, volume)| {
                volume
                    .build(scene_dir)
                    .map_err(|invalid| invalid.in_scene(scene_path, &format!("volumes[{index}]")))
            })
            .collect()
    }
}

/// A value outside its documented range: which field, and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct InvalidField {
    /// Dotted path of the field.
    pub field: String,
    /// What is wrong.
    pub reason: String,
}

impl InvalidField {
    /// The same error with `prefix.` before the field's path.
    fn within(self, prefix: &str) -> Self {
        Self {
            field: format!("{prefix}.{}", self.field),
            reason: self.reason,
        }
    }

    /// The scene error of this field of `scene_path`, below `prefix`.
    fn in_scene(self, scene_path: &Path, prefix: &str) -> SceneError {
        let invalid = self.within(prefix);
        SceneError::Invalid {
            path: scene_path.to_owned(),
            field: invalid.field,
            reason: invalid.reason,
        }
    }

    /// The first `(field, value, ok, requirement)` whose value is not finite
    /// or not `ok`, as an error that it must be finite and `requirement`.
    fn check_finite<const N: usize>(checks: [(&str, f32, bool, &str); N]) -> Result<(), Self> {
        for (field, value, ok, requirement) in checks {
            if !(value.is_finite() && ok) {
                return Err(Self::new(
                    field,
                    format!("must be finite and {requirement}, got {value}"),
                ));
            }
        }
        Ok(())
    }

    /// The grayscale map at `path`, relative to `scene_dir`, as a unit
    /// height field; errors name the scene file's `field`.
    /// Checks a `light_response` setting (`LightResponse::invalid`).
    fn check_light_response(response: &LightResponse) -> Result<(), Self> {
        response.invalid().map_or(Ok(()), |(field, reason)| {
            Err(Self::new(format!("light_response.{field}"), reason))
        })
    }

    fn load_map(scene_dir: &Path, path: &str, field: &str) -> Result<HeightField, Self> {
        HeightField::load_png(scene_dir.join(path), DVec2::ONE, DVec2::ZERO, 1.0)
            .map_err(|error| Self::new(field, error.to_string()))
    }

    fn new(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self {
            field: field.into(),
            reason: reason.into(),
        }
    }
}

/// Checks the reference image of `width × height` pixels and its opaque
/// depth against the memory budget.
fn check_output_budget(width: u32, height: u32) -> Result<(), BudgetError> {
    LinearImage::check_budget(width, height)?;
    check_opaque_depth_budget(width, height)
}

/// Checks the opaque depth of a `width × height` reference camera (one f32
/// per pixel) against the memory budget.
fn check_opaque_depth_budget(width: u32, height: u32) -> Result<(), BudgetError> {
    let dims = [width as usize, height as usize];
    check_allocation(
        || format!("opaque depth of {} pixels", Dims(&dims)),
        &dims,
        size_of::<f32>() as u64,
    )
    .map(drop)
}

fn finite(field: &str, values: &[f32]) -> Result<(), InvalidField> {
    match values.iter().find(|v| !v.is_finite()) {
        Some(value) => Err(InvalidField::new(
            field,
            format!("must be finite, got {value}"),
        )),
        None => Ok(()),
    }
}

fn positive(field: &str, value: f32) -> Result<(), InvalidField> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(InvalidField::new(
            field,
            format!("must be finite and > 0, got {value}"),
        ))
    }
}

fn non_negative(field: &str, value: f32) -> Result<(), InvalidField> {
    if value.is_finite() && value >= 0.0 {
        Ok(())
    } else {
        Err(InvalidField::new(
            field,
            format!("must be finite and >= 0, got {value}"),
        ))
    }
}

/// A layer's grid side ([`nebel_lod::is_layer_side`]).
fn layer_side(field: &str, side: u32) -> Result<(), InvalidField> {
    if nebel_lod::is_layer_side(side) {
        Ok(())
    } else {
        Err(InvalidField::new(
            field,
            format!("must be {}, got {side}", nebel_lod::LAYER_SIDES),
        ))
    }
}

/// A layer shape's refusal (`AuroraShape::validate`,
/// `CloudLayerShape::validate`), named by its parameter without the
/// shape's `prefix`.
fn shape_error(error: nebel_lod::TerrainError, prefix: &str) -> InvalidField {
    let field = match &error {
        nebel_lod::TerrainError::InvalidParameter { parameter, .. } => {
            parameter.trim_start_matches(prefix).to_owned()
        }
        _ => String::from("extent"),
    };
    InvalidField::new(field, error.to_string())
}

fn in_range(field: &str, value: f32, min: f32, max: f32) -> Result<(), InvalidField> {
    if (min..=max).contains(&value) {
        Ok(())
    } else {
        Err(InvalidField::new(
            field,
            format!("must be in [{min}, {max}], got {value}"),
        ))
    }
}

fn colour(field: &str, color: [f32; 3]) -> Result<(), InvalidField> {
    match color.iter().find(|c| !(c.is_finite() && **c >= 0.0)) {
        Some(value) => Err(InvalidField::new(
            field,
            format!("colour components must be finite and >= 0, got {value}"),
        )),
        None => Ok(()),
    }
}

fn pose_valid(field: &str, position: [f32; 3], look_at: [f32; 3]) -> Result<(), InvalidField> {
    finite(&format!("{field}.position"), &position)?;
    finite(&format!("{field}.look_at"), &look_at)?;
    if position == look_at {
        return Err(InvalidField::new(
            format!("{field}.look_at"),
            "must differ from position (the view direction would be undefined)",
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nebel_core::height_fog::HeightFogLayer;
    use nebel_core::transfer::TransferPreset;

    const MINIMAL: &str =
        "(version: 1, camera: (view: Pose((position: (0.0, 1.0, 5.0), look_at: (0.0, 0.0, 0.0)))))";

    fn full() -> SceneDescription {
        SceneDescription {
            version: 1,
            output: OutputSettings {
                width: 64,
                height: 48,
                frames: 3,
                frame_rate: 30.0,
            },
            camera: CameraSettings {
                fov_degrees: 45.0,
                near: 0.05,
                tonemapping: false,
                msaa: 1,
                cell_projection: Some(CellProjectionDescription::EXACT),
                view: CameraView::Path(vec![
                    CameraKeyframe {
                        time: 0.0,
                        position: [0.0, 1.0, 5.0],
                        look_at: [0.0; 3],
                    },
                    CameraKeyframe {
                        time: 2.0,
                        position: [4.0, 3.0, 5.0],
                        look_at: [0.0, 2.0, 0.0],
                    },
                ]),
            },
            clear_color: [0.1, 0.2, 0.3],
            lights: vec![
                LightDescription::Directional(DirectionalLightDescription {
                    direction: [-1.0, -1.0, 0.0],
                    color: [1.0, 0.9, 0.8],
                    illuminance: 5000.0,
                    shadows: true,
                    turn: Some(LightTurn {
                        axis: [1.0, 0.0, 0.0],
                        degrees_per_second: 2.0,
                    }),
                }),
                LightDescription::Point(PointLightDescription {
                    position: [0.0, 1.0, 0.0],
                    color: [1.0, 0.5, 0.2],
                    intensity: 2000.0,
                    range: 10.0,
                    flicker: 0.25,
                    shadows: false,
                    volumetric: true,
                }),
                LightDescription::Spot(SpotLightDescription {
                    position: [0.0, 3.0, 0.0],
                    look_at: [1.0, 0.0, 0.0],
                    color: [0.9, 0.9, 1.0],
                    intensity: 5000.0,
                    range: 12.0,
                    inner_angle_degrees: 10.0,
                    outer_angle_degrees: 20.0,
                    shadows: true,
                    volumetric: true,
                }),
                LightDescription::Ambient(AmbientLightDescription {
                    color: [0.5, 0.5, 1.0],
                    brightness: 100.0,
                }),
            ],
            meshes: vec![
                MeshDescription::Plane(PlaneDescription {
                    center: [0.0; 3],
                    size: [10.0, 10.0],
                    color: [0.2, 0.6, 0.2],
                }),
                MeshDescription::Box(BoxDescription {
                    center: [0.0, 0.5, 0.0],
                    size: [1.0, 1.0, 1.0],
                    color: [1.0; 3],
                }),
                MeshDescription::Sphere(SphereDescription {
                    center: [2.0, 1.0, 0.0],
                    radius: 0.5,
                    color: [0.9, 0.1, 0.1],
                }),
            ],
            volumes: vec![VolumeDescription {
                source: SourceDescription::Procedural(ProceduralSource {
                    dims: [9, 5, 9],
                    kind: nebel_core::field::NoiseKind::Ridged,
                    seed: 4,
                    octaves: 3,
                    frequency: 0.5,
                    coverage: 0.7,
                    ellipsoid: true,
                }),
                min: [-2.0, 0.0, -2.0],
                max: [2.0, 1.0, 2.0],
                transfer: Some(TransferDescription::Points(vec![
                    nebel_core::transfer::ControlPoint {
                        s: 0.5,
                        kappa: [1.0, 0.5, 0.2],
                        rho: 2.0,
                    },
                ])),
                density_scale: 0.5,
                mode: Some(nebel_core::optics::OpticalMode::Mip),
                lod: Some(LodDescription {
                    accuracy: Some(8.0),
                    min_accuracy: 3.0,
                    ..LodDescription::default()
                }),
                lighting: Some(LightingDescription {
                    ambient: 0.2,
                    diffuse: 0.6,
                    shadow_extinction: 0.5,
                    model: LightModel::NonPhysical,
                    keyframe_interval: 2.0,
                    scattering_octaves: 1,
                    sky_occlusion: false,
                    ground_shadow: false,
                }),
                projected_cells: false,
                full_resolution: false,
                light_response: LightResponse {
                    asymmetry: 0.3,
                    strength: 2.0,
                },
            }],
            terrain: Some(TerrainDescription {
                source: TerrainHeightSource::Procedural(ProceduralTerrainSource {
                    dims: 65,
                    kind: nebel_core::field::NoiseKind::Ridged,
                    seed: 3,
                    octaves: 5,
                    wavelength: 300.0,
                    persistence: 0.45,
                    exponent: 1.5,
                }),
                center: [10.0, -2.0, 5.0],
                spacing: 4.0,
                vertical_scale: 50.0,
                accuracy: Some(100.0),
                pixel_error: None,
                min_accuracy: 3.0,
                morph: false,
                debug_lod_colours: true,
                debug_edges: true,
                color: Some([0.2, 0.3, 0.1]),
                fog: None,
            }),
            fog_layers: Some(FogLayersDescription {
                layers: vec![
                    HeightFogLayer::Exponential {
                        base: 10.0,
                        density: 0.01,
                        falloff: 0.02,
                    },
                    HeightFogLayer::Constant {
                        bottom: 0.0,
                        top: 40.0,
                        density: 0.002,
                    },
                    HeightFogLayer::Linear(vec![[0.0, 0.0], [20.0, 0.004], [60.0, 0.0]]),
                ],
                color: [0.4, 0.5, 0.6],
                sun_color: [1.0, 0.9, 0.7],
                sun_asymmetry: 0.3,
                start_distance: 25.0,
                max_distance: 5000.0,
                light_response: LightResponse {
                    asymmetry: 0.2,
                    strength: 2.0,
                },
            }),
            aurora: Some(AuroraDescription {
                curtains: nebel_core::field::AuroraCurtains {
                    seed: 4,
                    count: 5,
                    ..Default::default()
                },
                map: Some("aurora.png".into()),
                center: [1.0, 2.0, 3.0],
                extent: 4e5,
                bottom: 9e4,
                top: 2e5,
                resolution: 129,
                brightness: 2e-5,
                transfer: Some(TransferDescription::Preset(TransferPreset::Fire)),
                speed: 0.5,
                accuracy: 8.0,
            }),
            stars: Some(StarsDescription {
                count: 10,
                seed: 3,
                brightness: 0.5,
            }),
            cloud_layer: Some(CloudLayerDescription {
                maps: Some(CloudLayerMaps {
                    bottom: "base.png".into(),
                    top: "tops.png".into(),
                    scale: 600.0,
                }),
                center: [0.0, 10.0, 0.0],
                extent: 2e4,
                base: 900.0,
                sag: 0.1,
                resolution: 65,
                density: 0.02,
                ambient: 0.2,
                diffuse: 0.8,
                shadow_extinction: 0.001,
                transfer: Some(TransferDescription::Preset(TransferPreset::Cloud)),
                accuracy: 20.0,
                ..Default::default()
            }),
            quality: QualityDescription::Medium,
            auto_quality_ms: Some(33.3),
        }
    }

    #[test]
    fn the_sky_colour_is_the_ambient_light_s_linear_colour_or_white() {
        assert_eq!(parse(MINIMAL).unwrap().sky_colour(), DVec3::ONE);
        let blue = MINIMAL.replace(
            "version: 1,",
            "version: 1, lights: [Ambient((color: (0.5, 0.6, 1.0), brightness: 300.0))],",
        );
        let sky = parse(&blue).unwrap().sky_colour();
        let expected = DVec3::new(srgb_to_linear(0.5), srgb_to_linear(0.6), 1.0);
        assert!((sky - expected).abs().max_element() < 1e-6, "{sky}");
    }

    fn parse(text: &str) -> Result<SceneDescription, SceneError> {
        SceneDescription::from_ron(text, Path::new("scenes/test.ron"))
    }

    fn message(text: &str) -> String {
        parse(text)
            .expect_err("scene should be refused")
            .to_string()
    }

    #[test]
    fn round_trip_keeps_every_field() {
        let scene = full();
        assert_eq!(parse(&scene.to_ron()).unwrap(), scene);
    }

    #[test]
    fn minimal_scene_takes_documented_defaults() {
        let scene = parse(MINIMAL).unwrap();
        assert_eq!(scene.output, OutputSettings::default());
        assert_eq!(scene.camera.fov_degrees, 60.0);
        assert_eq!(scene.camera.near, 0.1);
        assert_eq!(scene.camera.cell_projection, None);
        assert_eq!(scene.clear_color, [0.0; 3]);
        assert!(scene.lights.is_empty() && scene.meshes.is_empty());
    }

    #[test]
    fn cell_projection_takes_documented_defaults() {
        let text = MINIMAL.replace(
            "camera: (",
            "camera: (cell_projection: (resolution: Quarter), ",
        );
        let cell_projection = parse(&text).unwrap().camera.cell_projection.unwrap();
        assert_eq!(
            cell_projection,
            CellProjectionDescription {
                resolution: CellResolutionDescription::Quarter,
                ..CellProjectionDescription::default()
            }
        );
        assert_eq!(cell_projection.upsample_tolerance, 0.004);
        assert!(cell_projection.early_termination);
    }

    #[test]
    fn unknown_field_is_named_with_file_and_position() {
        let text = MINIMAL.replace("version: 1,", "version: 1, fog_colour: (1.0, 1.0, 1.0),");
        let message = message(&text);
        assert!(message.starts_with("scenes/test.ron:1:"), "{message}");
        assert!(message.contains("fog_colour"), "{message}");
    }

    #[test]
    fn wrong_type_names_the_nested_field() {
        let text = MINIMAL.replace("camera: (", "camera: (fov_degrees: \"wide\", ");
        let message = message(&text);
        assert!(message.contains("field camera.fov_degrees"), "{message}");
        assert!(message.contains("scenes/test.ron:1:"), "{message}");
    }

    #[test]
    fn missing_required_field_is_named() {
        let message = message("(version: 1)");
        assert!(message.contains("camera"), "{message}");
    }

    #[test]
    fn syntax_error_gives_line_and_column() {
        let message = message(
            "(version: 1,\n camera: (view: Pose((position: (0.0, 1.0, 5.0) look_at: (0.0, 0.0, 0.0)))))",
        );
        assert!(message.starts_with("scenes/test.ron:2:"), "{message}");
    }

    #[test]
    fn trailing_text_is_refused() {
        let message = message(&format!("{MINIMAL} extra"));
        assert!(message.contains("scenes/test.ron:1:"), "{message}");
    }

    #[test]
    fn each_range_check_names_field_and_reason() {
        let cases: &[(&str, &str, &str)] = &[
            (
                "version: 1",
                "version: 2",
                "field version: this build reads version 1, got 2",
            ),
            (
                "camera: (",
                "camera: (fov_degrees: 190.0, ",
                "field camera.fov_degrees: must be in (0, 180), got 190",
            ),
            (
                "camera: (",
                "camera: (near: 0.0, ",
                "field camera.near: must be finite and > 0, got 0",
            ),
            (
                "camera: (",
                "camera: (cell_projection: (upsample_tolerance: -0.1), ",
                "field camera.cell_projection.upsample_tolerance: must be finite and ≥ 0, got -0.1",
            ),
            (
                "look_at: (0.0, 0.0, 0.0)",
                "look_at: (0.0, 1.0, 5.0)",
                "field camera.view.Pose.look_at: must differ from position",
            ),
            (
                "version: 1,",
                "version: 1, output: (width: 0),",
                "field output.width: must be in [1, 8192], got 0",
            ),
            (
                "version: 1,",
                "version: 1, output: (frame_rate: -1.0),",
                "field output.frame_rate: must be finite and > 0, got -1",
            ),
            (
                "version: 1,",
                "version: 1, clear_color: (0.0, -1.0, 0.0),",
                "field clear_color: colour components must be finite and >= 0, got -1",
            ),
            (
                "version: 1,",
                "version: 1, lights: [Directional((direction: (0.0, 0.0, 0.0)))],",
                "field lights[0].Directional.direction: must not be zero",
            ),
            (
                "version: 1,",
                "version: 1, lights: [Point((position: (0.0, 0.0, 0.0), range: 0.0))],",
                "field lights[0].Point.range: must be finite and > 0, got 0",
            ),
            (
                "version: 1,",
                "version: 1, lights: [Spot((position: (0.0, 1.0, 0.0), look_at: (0.0, 0.0, 0.0), outer_angle_degrees: 90.0))],",
                "field lights[0].Spot.outer_angle_degrees: must be in (0, 90), got 90",
            ),
            (
                "version: 1,",
                "version: 1, lights: [Spot((position: (0.0, 1.0, 0.0), look_at: (0.0, 0.0, 0.0), inner_angle_degrees: 50.0))],",
                "field lights[0].Spot.inner_angle_degrees: must be in [0, outer_angle_degrees], got 50",
            ),
            (
                "version: 1,",
                "version: 1, lights: [Spot((position: (0.0, 1.0, 0.0), look_at: (0.0, 1.0, 0.0)))],",
                "field lights[0].Spot.look_at: must differ from position",
            ),
            (
                "version: 1,",
                "version: 1, lights: [Ambient((brightness: -2.0))],",
                "field lights[0].Ambient.brightness: must be finite and >= 0, got -2",
            ),
            (
                "version: 1,",
                "version: 1, meshes: [Sphere((center: (0.0, 0.0, 0.0), radius: 0.0))],",
                "field meshes[0].Sphere.radius: must be finite and > 0, got 0",
            ),
            (
                "version: 1,",
                "version: 1, meshes: [Box((center: (0.0, 0.0, 0.0), size: (1.0, inf, 1.0)))],",
                "field meshes[0].Box.size: must be finite and > 0, got inf",
            ),
            (
                "version: 1,",
                "version: 1, meshes: [Plane((center: (NaN, 0.0, 0.0), size: (1.0, 1.0)))],",
                "field meshes[0].Plane.center: must be finite, got NaN",
            ),
            (
                "version: 1,",
                "version: 1, volumes: [(source: Uniform((value: 2.0)))],",
                "field volumes[0].source.Uniform.value: must be in [0, 1], got 2",
            ),
            (
                "version: 1,",
                "version: 1, volumes: [(source: Ramp((axis: X, from: 0.0, to: 1.0)), min: (0.0, 0.0, 0.0), max: (1.0, 0.0, 1.0))],",
                "field volumes[0].max: must exceed min on every axis",
            ),
            (
                "version: 1,",
                "version: 1, volumes: [(source: Procedural((dims: (1, 4, 4))))],",
                "field volumes[0].source.Procedural.dims: each must be in [2, 4097], got [1, 4, 4]",
            ),
            (
                "version: 1,",
                "version: 1, volumes: [(source: Cells([]))],",
                "field volumes[0].source.Cells: needs at least one cell",
            ),
            (
                "version: 1,",
                "version: 1, volumes: [(source: Uniform((value: 1.0)), lod: (min_accuracy: 1.5))],",
                "field volumes[0].lod.min_accuracy: must be finite and > √3, got 1.5",
            ),
            (
                "version: 1,",
                "version: 1, volumes: [(source: Uniform((value: 1.0)), lod: (image_error: 0.0))],",
                "field volumes[0].lod.image_error: must be finite and > 0, got 0",
            ),
            (
                "version: 1,",
                "version: 1, volumes: [(source: Uniform((value: 1.0)), lod: (image_error: 0.1, accuracy: 4.0))],",
                "field volumes[0].lod: give either image_error (the screen error) or accuracy (the distance criterion), not both",
            ),
            (
                "version: 1,",
                "version: 1, volumes: [(source: Uniform((value: 1.0)), density_scale: -1.0)],",
                "field volumes[0].density_scale: must be finite and >= 0, got -1",
            ),
            (
                "version: 1,",
                "version: 1, fog_layers: (layers: [Exponential(base: 0.0, density: -0.1, falloff: 0.01)]),",
                "field fog_layers.layers: height fog layer 0 is invalid: base and density must be finite, density ≥ 0",
            ),
            (
                "version: 1,",
                "version: 1, fog_layers: (layers: [Exponential(base: 0.0, density: 0.1, falloff: 0.0)]),",
                "field fog_layers.layers: height fog layer 0 is invalid: falloff must be finite and > 0",
            ),
            (
                "version: 1,",
                "version: 1, fog_layers: (layers: [Constant(bottom: 5.0, top: 5.0, density: 0.1)]),",
                "field fog_layers.layers: height fog layer 0 is invalid: bottom and top must be finite, bottom below top",
            ),
            (
                "version: 1,",
                "version: 1, fog_layers: (layers: [Linear([(0.0, 0.1), (NaN, 0.0)])]),",
                "field fog_layers.layers: height fog layer 0 is invalid: needs two or more",
            ),
            (
                "version: 1,",
                "version: 1, fog_layers: (layers: [], start_distance: 10.0, max_distance: 5.0),",
                "field fog_layers.max_distance: must be greater than start_distance (10), got 5",
            ),
            (
                "version: 1,",
                "version: 1, auto_quality_ms: 0.0,",
                "field auto_quality_ms: must be finite and > 0, got 0",
            ),
            (
                "version: 1,",
                "version: 1, aurora: (bottom: 5e5),",
                "field aurora.top: aurora top = 300000 is invalid: it must be finite and above the bottom",
            ),
            (
                "version: 1,",
                "version: 1, aurora: (resolution: 100),",
                "field aurora.resolution: must be 2^k + 1 from 9 to 2049, got 100",
            ),
            (
                "version: 1,",
                "version: 1, aurora: (curtains: (count: 0)),",
                "field aurora.curtains: aurora curtains",
            ),
            (
                "version: 1,",
                "version: 1, stars: (count: 1000000),",
                "field stars.count: must be at most 100000, got 1000000",
            ),
            (
                "version: 1,",
                "version: 1, cloud_layer: (sag: 2.0),",
                "field cloud_layer.sag: cloud layer sag = 2 is invalid: it must be in [0, 1]",
            ),
            (
                "version: 1,",
                "version: 1, cloud_layer: (ambient: -1.0),",
                "field cloud_layer.ambient: must be in [0, 1], got -1",
            ),
            (
                "version: 1,",
                "version: 1, fog_layers: (layers: [], color: (0.0, -1.0, 0.0)),",
                "field fog_layers.color: colour components must be finite and >= 0, got -1",
            ),
        ];
        for (from, to, expected) in cases {
            let text = MINIMAL.replace(from, to);
            assert_ne!(text, MINIMAL, "case {expected} did not change the scene");
            let message = message(&text);
            let prefix = format!("scenes/test.ron: {expected}");
            assert!(message.starts_with(&prefix), "{message}");
        }
    }

    #[test]
    fn path_must_increase_strictly() {
        let text = "(version: 1, camera: (view: Path([(time: 1.0, position: (0.0, 0.0, 1.0), look_at: (0.0, 0.0, 0.0)), (time: 1.0, position: (0.0, 0.0, 2.0), look_at: (0.0, 0.0, 0.0))])))";
        let refused = message(text);
        assert!(
            refused.contains("field camera.view.Path[1].time: times must increase strictly"),
            "{refused}"
        );
        let empty = "(version: 1, camera: (view: Path([])))";
        assert!(message(empty).contains("needs at least one keyframe"));
    }

    #[test]
    fn camera_path_interpolates_and_holds() {
        let scene = full();
        assert_eq!(scene.camera_pose_at(-1.0).position, [0.0, 1.0, 5.0]);
        assert_eq!(scene.camera_pose_at(1.0).position, [2.0, 2.0, 5.0]);
        assert_eq!(scene.camera_pose_at(1.0).look_at, [0.0, 1.0, 0.0]);
        assert_eq!(scene.camera_pose_at(9.0).position, [4.0, 3.0, 5.0]);
        assert_eq!(scene.frame_time(3), 0.1);
    }

    #[test]
    fn building_a_volume_names_file_and_field() {
        let text = MINIMAL.replace(
            "version: 1,",
            "version: 1, volumes: [(source: Uniform((value: 1.0)), transfer: Points([]))],",
        );
        let scene = parse(&text).unwrap();
        let error = scene
            .build_volumes(Path::new("scenes/test.ron"))
            .unwrap_err()
            .to_string();
        assert!(
            error.starts_with("scenes/test.ron: field volumes[0].transfer: "),
            "{error}"
        );
    }

    #[test]
    fn volumetric_lights_are_the_marked_ones_in_linear_colour() {
        let scene = parse(&MINIMAL.replace(
            "version: 1,",
            "version: 1, lights: [
                Point((position: (1.0, 2.0, 3.0), color: (1.0, 0.5, 0.0), intensity: 4000.0, range: 5.0, volumetric: true, flicker: 0.5)),
                Point((position: (0.0, 0.0, 0.0), volumetric: false)),
                Spot((position: (0.0, 4.0, 0.0), look_at: (0.0, 0.0, 0.0), inner_angle_degrees: 10.0, outer_angle_degrees: 30.0, volumetric: true, shadows: true)),
            ], volumes: [(source: Uniform((value: 1.0)), light_response: (asymmetry: 0.5, strength: 3.0))],",
        ))
        .unwrap();
        let lights = scene.volumetric_lights(0.3);
        assert_eq!(lights.len(), 2);
        let point = lights[0];
        assert_eq!(point.position, DVec3::new(1.0, 2.0, 3.0));
        let factor = 4000.0 * flicker(0.5, 0.3) / (4.0 * std::f64::consts::PI * 10_000.0);
        let linear_half = srgb_to_linear(0.5);
        assert!((point.colour - DVec3::new(1.0, linear_half, 0.0) * factor).length() < 1e-12);
        assert!(point.cone.is_none() && point.range == 5.0 && !point.shadows);
        assert!(lights[1].shadows);
        let cone = lights[1].cone.expect("a spot light's cone");
        assert!((cone.direction - DVec3::NEG_Y).length() < 1e-12);
        assert!((cone.factor(DVec3::NEG_Y) - 1.0).abs() < 1e-12);
        assert_eq!(cone.factor(DVec3::X), 0.0);
        let response = scene.volumes[0].light_response;
        assert_eq!((response.asymmetry, response.strength), (0.5, 3.0));
        let error = parse(&MINIMAL.replace(
            "version: 1,",
            "version: 1, volumes: [(source: Uniform((value: 1.0)), light_response: (asymmetry: 1.0))],",
        ))
        .unwrap_err()
        .to_string();
        assert!(
            error.contains("light_response.asymmetry: must be in (−1, 1), got 1"),
            "{error}"
        );
    }

    #[test]
    fn reference_camera_uses_the_last_frame_pose() {
        let camera = full().reference_camera();
        // Frame 2 of 3 at 30 fps is t = 1/15 s on the path from (0, 1, 5) to (4, 3, 5) over 2 s.
        let t = (2.0_f32 / 30.0) / 2.0;
        let expected = DVec3::new(f64::from(4.0 * t), f64::from(1.0 + 2.0 * t), 5.0);
        assert!((camera.position - expected).length() < 1e-6);
        assert_eq!((camera.width, camera.height), (64, 48));
        assert!((camera.vertical_fov - 45f64.to_radians()).abs() < 1e-7);
        let look = DVec3::new(0.0, f64::from(2.0 * t), 0.0) - camera.position;
        assert!((camera.forward() - look.normalize()).length() < 1e-6);
    }

    #[test]
    fn missing_file_is_named() {
        let error = SceneDescription::load("does/not/exist.ron").unwrap_err();
        assert!(
            error
                .to_string()
                .starts_with("does/not/exist.ron: cannot read scene file")
        );
    }

    #[test]
    fn a_volume_beyond_the_memory_budget_is_refused_when_loaded() {
        let text = MINIMAL.replace(
            "version: 1,",
            "version: 1, volumes: [(source: Procedural((dims: (4097, 4097, 4097))))],",
        );
        let error = parse(&text).expect_err("a 256 GiB volume must be refused");
        let SceneError::Invalid { field, reason, .. } = &error else {
            panic!("expected an invalid field, got {error}");
        };
        assert_eq!(field, "volumes[0].source.Procedural.dims");
        assert_eq!(
            reason,
            "density grid of 4097 × 4097 × 4097 points needs 275,079,282,692 bytes (256.2 GiB), \
             more than the memory budget of 4,294,967,296 bytes (4 GiB)"
        );
        assert!(
            error
                .to_string()
                .starts_with("scenes/test.ron: field volumes[0].source.Procedural.dims: "),
            "{error}"
        );
    }

    #[test]
    fn every_sized_volume_source_is_checked_against_the_memory_budget() {
        let cases: &[(&str, &str, &str)] = &[
            (
                "(source: Uniform((value: 1.0, dims: (2049, 2049, 2049))))",
                "volumes[0].source.Uniform.dims",
                "density grid of 2049 × 2049 × 2049 points needs 34,410,094,596 bytes",
            ),
            // The grid fits; its batch of projected cells does not.
            (
                "(source: Ramp((axis: X, from: 0.0, to: 1.0, dims: (300, 300, 300))), projected_cells: true)",
                "volumes[0].source.Ramp.dims",
                "full-resolution batch of 299 × 299 × 299 voxels (6 tetrahedra each) needs 10,264,665,216 bytes",
            ),
            // Drawn through the octree instead, the grid padded to 1025³ does not.
            (
                "(source: Cloud((dims: (600, 600, 600))), lod: (accuracy: 16.0))",
                "volumes[0].source.Cloud.dims",
                "padded to 2^n+1 points per axis for the octree, the density grid of 1025 × 1025 × 1025 points needs 4,307,562,500 bytes",
            ),
            (
                "(source: Procedural((dims: (600, 600, 600))), lighting: (ambient: 0.3))",
                "volumes[0].source.Procedural.dims",
                "padded to 2^n+1 points per axis for the octree, the density grid of 1025 × 1025 × 1025 points",
            ),
            (
                "(source: Campfire((dims: (257, 257, 257))), projected_cells: true)",
                "volumes[0].source.Campfire.dims",
                "full-resolution batch of 256 × 256 × 256 voxels (6 tetrahedra each) needs 6,442,450,944 bytes",
            ),
            (
                "(source: SearchLight((position: (0.0, 0.0, 0.0), direction: (0.0, -1.0, 0.0), length: 5.0, half_angle_degrees: 20.0, segments: (256, 256, 256))))",
                "volumes[0].source.SearchLight.segments",
                "search-light cone of 256 × 256 × 256 segments (5 tetrahedra each) needs 10,737,418,240 bytes",
            ),
        ];
        for (volume, expected_field, expected_reason) in cases {
            let text = MINIMAL.replace("version: 1,", &format!("version: 1, volumes: [{volume}],"));
            match parse(&text) {
                Err(SceneError::Invalid { field, reason, .. }) => {
                    assert_eq!(&field, expected_field, "{volume}");
                    assert!(reason.starts_with(expected_reason), "{reason}");
                    assert!(
                        reason.contains("memory budget of 4,294,967,296 bytes"),
                        "{reason}"
                    );
                }
                other => panic!("{volume}: expected a budget error, got {other:?}"),
            }
        }
        // Within the budget: the same sources at sizes that fit, and ray
        // cast (the default), which needs no cells.
        for volume in [
            "(source: Ramp((axis: X, from: 0.0, to: 1.0, dims: (200, 200, 200))), projected_cells: true)",
            "(source: Ramp((axis: X, from: 0.0, to: 1.0, dims: (300, 300, 300))))",
            "(source: Cloud((dims: (513, 65, 513))), lod: (accuracy: 16.0), lighting: (ambient: 0.3))",
            "(source: Campfire((dims: (129, 129, 129))))",
        ] {
            let text = MINIMAL.replace("version: 1,", &format!("version: 1, volumes: [{volume}],"));
            parse(&text).unwrap_or_else(|error| panic!("{volume}: {error}"));
        }
    }

    #[test]
    fn a_scene_file_beyond_the_memory_budget_is_not_read() {
        let path =
            std::env::temp_dir().join(format!("nebel-scene-huge-{}.ron", std::process::id()));
        // Sparse: 5 GiB long, no data written.
        std::fs::File::create(&path)
            .unwrap()
            .set_len(5 << 30)
            .unwrap();
        let error = SceneDescription::load(&path).unwrap_err();
        std::fs::remove_file(&path).unwrap();
        assert!(matches!(error, SceneError::OverBudget { .. }), "{error}");
        assert!(
            error.to_string().contains(
                "the scene file needs 5,368,709,120 bytes (5 GiB), more than the memory budget"
            ),
            "{error}"
        );
    }
}
