//! Spawns a scene file's contents into a Bevy world.
//!
//! [`SceneSetupPlugin`] takes a validated [`SceneDescription`] and, at startup,
//! spawns its camera, lights, meshes, volumes and terrain (a
//! `nebel_terrain::Terrain` whose heights, generated or loaded from the PNG
//! relative to the scene file when the plugin is made, become a
//! `GrayscaleMap` asset; the entity sits at the terrain's `center`), its
//! aurora (a `nebel_sky::Aurora` at its `center`, a map footprint read when
//! the plugin is made), its cloud layer (a `nebel_sky::CloudLayer`, likewise)
//! and its stars ([`crate::stars`], centred on the
//! camera's first position). A camera with a keyframe path follows
//! it by [`Time::elapsed_secs`] (headless runs step time by exactly
//! `1 / output.frame_rate` per frame, so frame `i` shows the path at
//! `i / frame_rate`). Colours in scene files are sRGB.
//!
//! The camera renders in HDR (nebel's volumes accumulate in float targets)
//! to the window, or headless to an image ([`crate::headless`]).

use bevy::camera::{Hdr, ShadowLodOrigin};
use bevy::core_pipeline::tonemapping::{DebandDither, Tonemapping};
use bevy::light::VolumetricLight;
use bevy::prelude::*;
use std::path::Path;
use std::sync::Arc;

use nebel_core::field::HeightField;
use nebel_render::{
    AutoQuality, CellProjection, CellResolution, NebelQuality, NebelSystems, QualityPreset,
    cpu_timed,
};

use crate::headless::{HeadlessError, HeadlessOptions, render_headless};
use crate::stats::RenderStats;
use nebel_scene::{
    BuiltAurora, BuiltCloudLayer, BuiltGroundFog, BuiltVolume, CameraView,
    CellResolutionDescription, DirectionalLightDescription, FogThicknessDescription,
    GroundFogDescription, LightDescription, MeshDescription, QualityDescription, SceneDescription,
    SceneError,
};
use nebel_volume::VolumeGrid;

use crate::fog_comparison::{BevyFog, BevyFogSettings, enable_bevy_fog, spawn_bevy_fog};
use nebel_volume::FlickeringLight;

/// Spawns a scene description at startup.
#[derive(Clone)]
pub struct SceneSetupPlugin {
    /// The scene to spawn.
    pub scene: SceneDescription,
    /// The scene's volumes, built ([`SceneSetupPlugin::new`] builds them),
    /// spawned as [`nebel_volume::Volume`]s.
    pub volumes: Vec<BuiltVolume>,
    /// The scene terrain's unit heights ([`SceneSetupPlugin::new`] builds
    /// them), spawned as a `nebel_terrain::Terrain`.
    pub terrain: Option<HeightField>,
    /// The terrain fog's files ([`SceneSetupPlugin::new`] reads them),
    /// spawned as a `nebel_fog::GroundFog` on the terrain.
    pub ground_fog: Option<BuiltGroundFog>,
    /// The aurora's files ([`SceneSetupPlugin::new`] reads them), spawned
    /// as a `nebel_sky::Aurora`.
    pub aurora: Option<BuiltAurora>,
    /// The cloud layer's files ([`SceneSetupPlugin::new`] reads them),
    /// spawned as a `nebel_sky::CloudLayer`.
    pub cloud_layer: Option<BuiltCloudLayer>,
    /// One of Bevy's own fogs, for comparisons: grid volumes drawn by its
    /// `FogVolume` ray marcher instead of nebel ([`crate::fog_comparison`]),
    /// or its `DistanceFog` on the camera. Default: `None`.
    pub peer: Option<BevyPeer>,
}

/// Bevy's own fogs a scene can be drawn with, for comparisons.
#[derive(Clone, Debug)]
pub enum BevyPeer {
    /// The grid volumes as `FogVolume`s.
    FogVolume(BevyFog),
    /// A `DistanceFog` on the camera.
    DistanceFog(DistanceFog),
}

/// The `DistanceFog` a scene's camera gets.
#[derive(Resource, Clone, Debug)]
struct BevyDistanceFog(DistanceFog);

impl SceneSetupPlugin {
    /// Renders this scene headless (see [`render_headless`]) with the
    /// scene's output settings.
    pub fn render_headless(
        self,
        options: HeadlessOptions,
        out: &Path,
    ) -> Result<RenderStats, HeadlessError> {
        let output = self.scene.output.clone();
        render_headless(&output, options, out, |app| {
            app.add_plugins(self);
        })
    }

    /// Builds the scene's volumes (`scene_path` resolves their relative
    /// paths and names the file in errors); renders to the primary window.
    pub fn new(scene: SceneDescription, scene_path: &Path) -> Result<Self, SceneError> {
        let volumes = scene.build_volumes(scene_path)?;
        let terrain = scene.build_terrain(scene_path)?;
        let ground_fog = scene.build_ground_fog(scene_path)?;
        let aurora = scene.build_aurora(scene_path)?;
        let cloud_layer = scene.build_cloud_layer(scene_path)?;
        Ok(Self {
            scene,
            volumes,
            terrain,
            ground_fog,
            aurora,
            cloud_layer,
            peer: None,
        })
    }
}

/// The scene's built volumes, taken by the startup system.
#[derive(Resource, Clone, Debug)]
struct SceneVolumes(Vec<BuiltVolume>);

/// The scene's aurora and cloud layer files, taken by the startup system.
#[derive(Resource, Clone, Debug)]
struct SceneSky(Option<BuiltAurora>, Option<BuiltCloudLayer>);

/// The scene's terrain heights and fog files, taken by the startup system.
#[derive(Resource, Clone, Debug)]
struct SceneTerrain(Option<HeightField>, Option<BuiltGroundFog>);

/// The scene file the world was set up from.
#[derive(Resource, Clone, Debug, Deref, Reflect)]
#[reflect(opaque, Resource, Debug, Clone)]
pub struct LoadedScene(pub SceneDescription);

/// Marks the camera spawned from the scene file.
#[derive(Component, Clone, Copy, Debug, Default, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct SceneCamera {
    /// Whether the camera follows the scene's keyframe path. Default: false
    /// (set when the scene has a path; a fly camera clears it).
    pub follows_path: bool,
}

impl Plugin for SceneSetupPlugin {
    fn build(&self, app: &mut App) {
        app.insert_resource(LoadedScene(self.scene.clone()))
            .register_type::<LoadedScene>()
            .register_type::<SceneCamera>()
            .insert_resource(SceneVolumes(self.volumes.clone()))
            .insert_resource(SceneTerrain(self.terrain.clone(), self.ground_fog.clone()))
            .insert_resource(SceneSky(self.aurora.clone(), self.cloud_layer.clone()))
            .add_systems(
                Startup,
                (spawn_scene, spawn_terrain, spawn_aurora, spawn_cloud_layer),
            )
            .add_systems(PostStartup, enable_bevy_fog)
            .add_systems(
                Update,
                (cpu_timed(follow_camera_path), cpu_timed(turn_lights)).in_set(NebelSystems),
            );
        match self.peer.clone() {
            Some(BevyPeer::FogVolume(fog)) => {
                app.insert_resource(BevyFogSettings(fog));
            }
            Some(BevyPeer::DistanceFog(fog)) => {
                app.insert_resource(BevyDistanceFog(fog));
            }
            None => {}
        }
    }
}

/// The scene's fog layers as the camera's component.
fn fog_layers(fog: &nebel_scene::FogLayersDescription) -> nebel_fog::FogLayers {
    let linear = |c: [f32; 3]| Color::linear_rgb(c[0], c[1], c[2]);
    nebel_fog::FogLayers {
        layers: fog.layers.clone(),
        color: linear(fog.color),
        sun_color: linear(fog.sun_color),
        sun_asymmetry: fog.sun_asymmetry,
        start_distance: fog.start_distance,
        max_distance: fog.max_distance,
        light_response: fog.light_response,
    }
}

fn srgb(color: [f32; 3]) -> Color {
    Color::srgb(color[0], color[1], color[2])
}

fn pose_transform(position: [f32; 3], look_at: [f32; 3]) -> Transform {
    Transform::from_translation(Vec3::from(position)).looking_at(Vec3::from(look_at), Vec3::Y)
}

fn spawn_scene(
    mut commands: Commands,
    scene: Res<LoadedScene>,
    volumes: Res<SceneVolumes>,
    bevy_fog: Option<Res<BevyFogSettings>>,
    distance_fog: Option<Res<BevyDistanceFog>>,
    mut images: ResMut<Assets<Image>>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
    mut grids: ResMut<Assets<VolumeGrid>>,
) {
    let camera = &scene.camera;
    let pose = scene.camera_pose_at(0.0);
    let mut camera_entity = commands.spawn((
        Camera3d::default(),
        Camera {
            clear_color: ClearColorConfig::Custom(srgb(scene.clear_color)),
            ..default()
        },
        Hdr,
        // The camera renders to an image: point and spot lights' shadow
        // maps take their detail from it.
        ShadowLodOrigin,
        Projection::Perspective(PerspectiveProjection {
            fov: camera.fov_degrees.to_radians(),
            near: camera.near,
            ..default()
        }),
        pose_transform(pose.position, pose.look_at),
        SceneCamera {
            follows_path: matches!(camera.view, CameraView::Path(_)),
        },
    ));
    camera_entity.insert(match camera.msaa {
        1 => Msaa::Off,
        2 => Msaa::Sample2,
        8 => Msaa::Sample8,
        _ => Msaa::Sample4,
    });
    if !camera.tonemapping {
        camera_entity.insert((Tonemapping::None, DebandDither::Disabled));
    }
    if let Some(cell_projection) = camera.cell_projection {
        camera_entity.insert(CellProjection {
            resolution: match cell_projection.resolution {
                CellResolutionDescription::Full => CellResolution::Full,
                CellResolutionDescription::Half => CellResolution::Half,
                CellResolutionDescription::Quarter => CellResolution::Quarter,
            },
            upsample_tolerance: cell_projection.upsample_tolerance,
            early_termination: cell_projection.early_termination,
        });
    }
    if let Some(fog) = &scene.fog_layers {
        camera_entity.insert(fog_layers(fog));
    }
    if let Some(fog) = distance_fog {
        camera_entity.insert(fog.0.clone());
    }
    commands.insert_resource(NebelQuality {
        preset: match scene.quality {
            QualityDescription::Low => QualityPreset::Low,
            QualityDescription::Medium => QualityPreset::Medium,
            QualityDescription::High => QualityPreset::High,
        },
        auto: scene.auto_quality_ms.map(|target_frame_ms| AutoQuality {
            target_frame_ms,
            ..default()
        }),
    });

    let mut ambient = GlobalAmbientLight {
        brightness: 0.0,
        ..default()
    };
    for light in &scene.lights {
        match light {
            LightDescription::Directional(sun) => {
                let mut light = commands.spawn((
                    DirectionalLight {
                        color: srgb(sun.color),
                        illuminance: sun.illuminance,
                        shadow_maps_enabled: sun.shadows,
                        ..default()
                    },
                    Transform::default().looking_to(Vec3::from(sun.direction), Vec3::Y),
                ));
                if sun.turn.is_some() {
                    light.insert(TurningLight(sun.clone()));
                }
            }
            LightDescription::Point(point) => {
                let mut light = commands.spawn((
                    PointLight {
                        color: srgb(point.color),
                        intensity: point.intensity,
                        range: point.range,
                        shadow_maps_enabled: point.shadows,
                        ..default()
                    },
                    Transform::from_translation(Vec3::from(point.position)),
                ));
                if point.flicker > 0.0 {
                    light.insert(FlickeringLight {
                        base_intensity: point.intensity,
                        amplitude: point.flicker,
                    });
                }
                if point.volumetric {
                    light.insert(VolumetricLight);
                }
            }
            LightDescription::Spot(spot) => {
                let mut light = commands.spawn((
                    SpotLight {
                        color: srgb(spot.color),
                        intensity: spot.intensity,
                        range: spot.range,
                        inner_angle: spot.inner_angle_degrees.to_radians(),
                        outer_angle: spot.outer_angle_degrees.to_radians(),
                        shadow_maps_enabled: spot.shadows,
                        ..default()
                    },
                    Transform::from_translation(Vec3::from(spot.position))
                        .looking_at(Vec3::from(spot.look_at), Vec3::Y),
                ));
                if spot.volumetric {
                    light.insert(VolumetricLight);
                }
            }
            LightDescription::Ambient(light) => {
                ambient.color = srgb(light.color);
                ambient.brightness = light.brightness;
            }
        }
    }
    commands.insert_resource(ambient);
    if let Some(stars) = &scene.stars {
        // About 1.5 pixels across at the scene's resolution.
        let angular_size = 1.5 * camera.fov_degrees.to_radians() / scene.output.height as f32;
        crate::stars::spawn_stars(
            &mut commands,
            &mut meshes,
            &mut materials,
            stars,
            angular_size,
            Vec3::from(pose.position),
        );
    }

    for mesh in &scene.meshes {
        let (shape, center, color): (Mesh, _, _) = match mesh {
            MeshDescription::Plane(plane) => (
                Plane3d::new(Vec3::Y, Vec2::from(plane.size) / 2.0).into(),
                plane.center,
                plane.color,
            ),
            MeshDescription::Box(cuboid) => (
                Cuboid::from_size(Vec3::from(cuboid.size)).into(),
                cuboid.center,
                cuboid.color,
            ),
            MeshDescription::Sphere(sphere) => (
                Sphere::new(sphere.radius).mesh().uv(48, 24),
                sphere.center,
                sphere.color,
            ),
        };
        let mut mesh = commands.spawn((
            Mesh3d(meshes.add(shape)),
            MeshMaterial3d(materials.add(StandardMaterial {
                base_color: srgb(color),
                perceptual_roughness: 0.9,
                ..default()
            })),
            Transform::from_translation(Vec3::from(center)),
        ));
        if scene.casts_ground_shadow() {
            mesh.insert(nebel_volume::CloudShadowReceiver);
        }
    }
    match bevy_fog {
        Some(fog) => {
            for volume in &volumes.0 {
                if let nebel_scene::SceneField::Grid(grid) = &volume.field {
                    spawn_bevy_fog(&mut commands, &mut images, &Arc::new(grid.clone()), &fog.0);
                }
            }
        }
        None => spawn_volumes(&mut commands, &mut grids, &volumes.0),
    }
}

/// Spawns the scene's volumes; their fields are in world space.
fn spawn_volumes(commands: &mut Commands, grids: &mut Assets<VolumeGrid>, volumes: &[BuiltVolume]) {
    use nebel_scene::LightModel;
    use nebel_scene::SceneField;
    use nebel_volume::{
        Campfire, CloudLightModel, CloudVolume, ProjectedCells, Volume, VolumeField,
        VolumeLighting, VolumeLod,
    };
    use std::sync::Arc;
    for volume in volumes {
        let transfer_function = Arc::new(volume.transfer_function.clone());
        let field = match &volume.field {
            SceneField::Grid(grid) => VolumeField::Grid(grids.add(VolumeGrid::from(grid.clone()))),
            // The cloud's generator fills its field.
            SceneField::Cloud(_) => VolumeField::default(),
            SceneField::Cells(cells) => VolumeField::Cells(Arc::new(cells.clone())),
            SceneField::Campfire(campfire) => {
                let (scale, offset) = campfire.placement();
                commands.spawn((
                    Campfire {
                        seed: campfire.seed,
                        dims: campfire.dims,
                    },
                    // The campfire's animation fills the field (in the flame
                    // box, placed by the transform) before the first batch.
                    Volume {
                        transfer_function,
                        mode: volume.mode,
                        light_response: volume.light_response,
                        ..default()
                    },
                    Transform::from_translation(offset.as_vec3()).with_scale(scale.as_vec3()),
                ));
                continue;
            }
        };
        let mut entity = match &volume.field {
            SceneField::Cloud(cloud) => {
                // The cloud's generator fills the field, or in the wind its
                // keyframes.
                let mut entity = commands.spawn((
                    CloudVolume {
                        dims: UVec3::from_array(cloud.dims.map(|n| n as u32)),
                        min: cloud.min.as_vec3(),
                        max: cloud.max.as_vec3(),
                        noise: cloud.noise,
                        keyframe_interval: cloud.keyframe_interval,
                        weather_map: cloud.shape.weather_map.clone(),
                        primitives: cloud.shape.primitives.clone(),
                    },
                    Volume {
                        transfer_function,
                        mode: volume.mode,
                        light_response: volume.light_response,
                        ..default()
                    },
                ));
                if volume.lighting.is_none() {
                    entity.remove::<VolumeLighting>();
                }
                entity
            }
            _ => commands.spawn(Volume {
                field,
                transfer_function,
                mode: volume.mode,
                light_response: volume.light_response,
            }),
        };
        if volume.projected_cells {
            entity.insert(ProjectedCells);
        }
        match volume.lod {
            Some(lod) => {
                entity.insert(VolumeLod {
                    criterion: lod.criterion(),
                    min_accuracy: lod.min_accuracy,
                });
            }
            // A cloud, too, is drawn at full resolution without it.
            None => {
                entity.remove::<VolumeLod>();
            }
        }
        if let Some(lighting) = volume.lighting {
            entity.insert(VolumeLighting {
                ambient: lighting.ambient,
                diffuse: lighting.diffuse,
                shadow_extinction: lighting.shadow_extinction,
                model: match lighting.model {
                    LightModel::Isotropic => CloudLightModel::Isotropic,
                    LightModel::NonPhysical => CloudLightModel::NonPhysical,
                    LightModel::Scattering { asymmetry } => {
                        CloudLightModel::Scattering { asymmetry }
                    }
                },
                keyframe_interval: lighting.keyframe_interval,
                scattering_octaves: lighting.scattering_octaves,
                sky_occlusion: lighting.sky_occlusion,
            });
            if lighting.ground_shadow {
                entity.insert(nebel_volume::CloudShadowCaster);
            }
        }
    }
}

/// Spawns the scene's terrain: its heights as an asset, the entity at its
/// centre.
fn spawn_terrain(
    mut commands: Commands,
    scene: Res<LoadedScene>,
    terrain: Res<SceneTerrain>,
    heights: Option<ResMut<Assets<nebel_render::GrayscaleMap>>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
) {
    use nebel_render::GrayscaleMap;
    use nebel_terrain::{Terrain, TerrainDebug, TerrainMaterial, TerrainSource};
    let (Some(description), Some(unit)) = (&scene.terrain, &terrain.0) else {
        return;
    };
    let Some(mut heights) = heights else {
        warn!("nebel: the scene has a terrain but the app has no TerrainPlugin");
        return;
    };
    let mut entity = commands.spawn((
        Terrain {
            source: TerrainSource::Heights(heights.add(GrayscaleMap::from_field(unit))),
            spacing: description.spacing,
            vertical_scale: description.vertical_scale,
            accuracy: description.accuracy(),
            pixel_error: description.pixel_error,
            min_accuracy: description.min_accuracy,
            morph: description.morph,
            debug: TerrainDebug {
                lod_colours: description.debug_lod_colours,
                edges: description.debug_edges,
            },
            material: description
                .color
                .map_or(TerrainMaterial::HeightAndSlope, |color| {
                    TerrainMaterial::Standard(materials.add(StandardMaterial {
                        base_color: srgb(color),
                        unlit: true,
                        ..default()
                    }))
                }),
            ..default()
        },
        Transform::from_translation(Vec3::from(description.center)),
    ));
    if scene.casts_ground_shadow() {
        entity.insert(nebel_volume::CloudShadowReceiver);
    }
    if let (Some(fog), Some(built)) = (&description.fog, &terrain.1)
        && let Some(fog) = ground_fog(fog, built, &mut heights)
    {
        entity.insert(fog);
    }
}

/// The scene terrain's fog as a `nebel_fog::GroundFog`, its map (if any) as
/// an asset; `None` for a `Png` fog whose map was not read.
fn ground_fog(
    fog: &GroundFogDescription,
    built: &BuiltGroundFog,
    heights: &mut Assets<nebel_render::GrayscaleMap>,
) -> Option<nebel_fog::GroundFog> {
    use nebel_fog::{FogThickness, GroundFog, GroundFogDebug};
    let thickness = match (&fog.thickness, &built.map) {
        (FogThicknessDescription::Valley(valley), _) => FogThickness::Valley(*valley),
        (FogThicknessDescription::Noise(noise), _) => FogThickness::Noise(*noise),
        (FogThicknessDescription::Png(map), Some(unit)) => FogThickness::Map {
            map: heights.add(nebel_render::GrayscaleMap::from_field(unit)),
            scale: map.scale,
        },
        (FogThicknessDescription::Png(_), None) => {
            error!("nebel: the scene's fog map was not read; no ground fog");
            return None;
        }
    };
    Some(GroundFog {
        thickness,
        // The built transfer function has the density in it.
        density: 1.0,
        transfer_function: Arc::new(built.transfer_function.clone()),
        mode: fog.mode,
        saturate: fog.saturate,
        profile: fog.profile.clone(),
        roughness_weight: fog.roughness_weight,
        light_response: fog.light_response,
        sun_color: Color::linear_rgb(fog.sun_color[0], fog.sun_color[1], fog.sun_color[2]),
        sun_asymmetry: fog.sun_asymmetry,
        debug: GroundFogDebug {
            wireframe: fog.debug_wireframe,
        },
    })
}

/// Spawns the scene's aurora at its centre, its map (if any) as an asset.
fn spawn_aurora(
    mut commands: Commands,
    scene: Res<LoadedScene>,
    built: Res<SceneSky>,
    heights: Option<ResMut<Assets<nebel_render::GrayscaleMap>>>,
) {
    use nebel_sky::{Aurora, AuroraFootprint};
    let (Some(description), Some(built)) = (&scene.aurora, &built.0) else {
        return;
    };
    let footprint = match (&built.map, heights) {
        (None, _) => AuroraFootprint::Curtains(description.curtains),
        (Some(map), Some(mut heights)) => {
            AuroraFootprint::Map(heights.add(nebel_render::GrayscaleMap::from_field(map)))
        }
        (Some(_), None) => {
            warn!("nebel: the scene's aurora has a map but the app has no TerrainPlugin");
            return;
        }
    };
    commands.spawn((
        Aurora {
            footprint,
            extent: description.extent,
            bottom: description.bottom,
            top: description.top,
            resolution: description.resolution,
            // The built transfer function has the brightness in it.
            brightness: 1.0,
            transfer_function: Arc::new(built.transfer_function.clone()),
            speed: description.speed,
            accuracy: description.accuracy,
        },
        Transform::from_translation(Vec3::from(description.center)),
    ));
}

/// Spawns the scene's cloud layer at its centre, its maps (if any) as
/// assets.
fn spawn_cloud_layer(
    mut commands: Commands,
    scene: Res<LoadedScene>,
    built: Res<SceneSky>,
    heights: Option<ResMut<Assets<nebel_render::GrayscaleMap>>>,
) {
    use nebel_render::GrayscaleMap;
    use nebel_sky::{CloudLayer, CloudLayerSource};
    let (Some(description), Some(built)) = (&scene.cloud_layer, &built.1) else {
        return;
    };
    let source = match (&built.maps, &description.maps, heights) {
        (Some((bottom, top)), Some(maps), Some(mut heights)) => CloudLayerSource::Maps {
            bottom: heights.add(GrayscaleMap::from_field(bottom)),
            top: heights.add(GrayscaleMap::from_field(top)),
            scale: maps.scale,
        },
        (Some(_), _, _) => {
            warn!("nebel: the scene's cloud layer has maps but the app has no TerrainPlugin");
            return;
        }
        (None, _, _) => CloudLayerSource::Noise(description.noise),
    };
    commands.spawn((
        CloudLayer {
            source,
            extent: description.extent,
            base: description.base,
            sag: description.sag,
            edge_fade: description.edge_fade,
            resolution: description.resolution,
            // The built transfer function has the density in it.
            density: 1.0,
            ambient: description.ambient,
            diffuse: description.diffuse,
            shadow_extinction: description.shadow_extinction,
            scattering_octaves: description.scattering_octaves,
            sky_occlusion: description.sky_occlusion,
            light_response: description.light_response,
            transfer_function: Arc::new(built.transfer_function.clone()),
            accuracy: description.accuracy,
        },
        Transform::from_translation(Vec3::from(description.center)),
    ));
}

/// A directional light of the scene that turns with the time.
#[derive(Component)]
struct TurningLight(DirectionalLightDescription);

/// Points every turning light where the scene says it is at this frame's
/// time.
fn turn_lights(time: Res<Time>, mut lights: Query<(&TurningLight, &mut Transform)>) {
    for (light, mut transform) in &mut lights {
        let direction = light.0.direction_at(time.elapsed_secs_f64()).as_vec3();
        *transform = Transform::default().looking_to(direction, Vec3::Y);
    }
}

fn follow_camera_path(
    scene: Res<LoadedScene>,
    time: Res<Time>,
    mut cameras: Query<(&SceneCamera, &mut Transform)>,
) {
    for (camera, mut transform) in &mut cameras {
        if camera.follows_path {
            let pose = scene.camera_pose_at(time.elapsed_secs());
            *transform = pose_transform(pose.position, pose.look_at);
        }
    }
}
