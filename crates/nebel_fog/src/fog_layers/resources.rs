//! The render world of the fog layers, a row of small systems: extraction of
//! each camera's fog (with the sun's direction of this frame), a readable
//! depth texture, the terrain's shadow heights
//! ([`super::terrain_shadow`]), the per-view uniform and pipeline, and the
//! per-view bind group, made again only when a texture or the uniform
//! buffer is a new one.

use bevy::core_pipeline::FullscreenShader;
use bevy::core_pipeline::core_3d::prepare_core_3d_depth_textures;
use bevy::core_pipeline::schedule::{Core3d, Core3dSystems};
use bevy::pbr::{ViewLightsUniformOffset, ViewShadowBindings};
use bevy::prelude::*;
use bevy::render::render_resource::binding_types::{
    sampler, texture_2d, texture_2d_multisampled, uniform_buffer,
};
use bevy::render::render_resource::*;
use bevy::render::renderer::{RenderDevice, RenderQueue};
use bevy::render::sync_world::RenderEntity;
use bevy::render::view::{ExtractedView, Msaa, ViewDepthTexture};
use bevy::render::{
    Extract, ExtractSchedule, GpuResourceAppExt, Render, RenderApp, RenderStartup, RenderSystems,
};
use bevy::shader::ShaderDefVal;
use nebel_core::local_light::{LightResponse, MAX_LOCAL_LIGHTS};
use nebel_render::cell_projection::CellProjectionSystems;
use nebel_render::cloud_shadow_maps::CloudShadowTextures;
use nebel_render::fog_layers::{FogLayersUniform, ViewFogLayers};
use nebel_render::light_shadows::{LightShadows, light_shadow_layout};
use nebel_render::local_lights::{
    LocalLightsUniform, ReachingLights, SceneLight, VolumetricPointLights, VolumetricSpotLights,
    visible_volumetric_lights,
};
use nebel_render::{CloudShadowMapUniform, CloudShadowMaps, EffectiveQuality};

use super::terrain_shadow::{
    TERRAIN_SHADOW_BLOCK, TerrainShadowTexture, TerrainShadowUniform,
    prepare_terrain_shadow_texture,
};
use super::{FogLayers, FogLayersPasses, PreparedFogLayers};

/// The render side of [`super::FogLayersPlugin`].
pub struct FogLayersRenderPlugin {
    pub(super) passes: FogLayersPasses,
}

impl Plugin for FogLayersRenderPlugin {
    fn build(&self, app: &mut App) {
        bevy::asset::embedded_asset!(app, "fog_layers.wgsl");
        nebel_render::cloud_shadow_maps::load_cloud_shadow_maps_library(app);
        let Some(render_app) = app.get_sub_app_mut(RenderApp) else {
            return;
        };
        render_app
            .insert_resource(self.passes.clone())
            .init_gpu_resource::<FogPassUniforms>()
            .init_gpu_resource::<SpecializedRenderPipelines<FogLayersPipeline>>()
            .add_systems(RenderStartup, init_fog_layers_pipeline)
            .add_systems(ExtractSchedule, extract_fog_layers)
            .add_systems(
                Render,
                (
                    make_depth_readable
                        .in_set(RenderSystems::Prepare)
                        .before(prepare_core_3d_depth_textures),
                    prepare_terrain_shadow_texture.in_set(RenderSystems::PrepareResources),
                    prepare_fog_layer_views
                        .in_set(RenderSystems::PrepareResources)
                        .after(prepare_terrain_shadow_texture),
                    prepare_fog_layer_bind_groups.in_set(RenderSystems::PrepareBindGroups),
                ),
            )
            .add_systems(
                Core3d,
                super::node::draw_fog_layers
                    .after(Core3dSystems::MainPass)
                    .before(CellProjectionSystems::Draw)
                    .before(Core3dSystems::EarlyPostProcess),
            );
    }
}

/// The point and spot lights that reach a view's fog layers, scattered
/// with its response (render world, on the view entity).
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct FogLayerLights {
    /// The lights, the brightest at the eye first.
    pub lights: ReachingLights,
    /// How the fog scatters them.
    pub response: LightResponse,
}

impl FogLayerLights {
    /// The lights of `lights` that reach within `max_distance` of the eye,
    /// the brightest at the eye first, scattered with `response`; `None`
    /// where none does or the response's strength is 0 (the pass then runs
    /// without lights).
    pub fn reaching(
        lights: &[SceneLight],
        eye: Vec3,
        max_distance: f32,
        response: LightResponse,
    ) -> Option<Self> {
        let reach = Vec3::splat(max_distance);
        let lights = Self {
            lights: ReachingLights::reaching(lights, eye - reach, eye + reach),
            response,
        };
        (lights.lights.count > 0 && lights.uniform().response.w > 0.0).then_some(lights)
    }

    /// The lights as the shader's `LocalLights`.
    pub fn uniform(&self) -> LocalLightsUniform {
        LocalLightsUniform::new(&self.lights, self.response)
    }
}

/// On a view whose sunlit fog layers the sun shades through Bevy's shadow
/// map of it (the first `DirectionalLight` has `shadow_maps_enabled`;
/// render world).
#[derive(Component, Clone, Copy, Debug)]
pub struct FogLayersSunShadows;

/// Gives every camera with fog to draw its [`ViewFogLayers`], the sun's
/// direction taken from the first `DirectionalLight` (a light shines along
/// its forward axis, so the sun lies behind it), [`FogLayersSunShadows`]
/// where that light casts shadows on sunlit fog, and its
/// [`FogLayerLights`] where a volumetric light reaches within the fog's
/// largest distance (the brightest at the camera first); removes them, and
/// what was prepared from them, from the others.
pub fn extract_fog_layers(
    mut commands: Commands,
    cameras: Extract<
        Query<
            (
                RenderEntity,
                Option<&PreparedFogLayers>,
                Option<&FogLayers>,
                &GlobalTransform,
            ),
            With<Camera3d>,
        >,
    >,
    lights: Extract<Query<(&GlobalTransform, &DirectionalLight)>>,
    (points, spots): (
        Extract<VolumetricPointLights>,
        Extract<VolumetricSpotLights>,
    ),
    quality: Extract<Option<Res<EffectiveQuality>>>,
) {
    let local_lights = visible_volumetric_lights(&points, &spots);
    // A quality without ground fog prisms leaves the whole ray to the layers.
    let from_the_eye = quality
        .as_ref()
        .is_some_and(|quality| !quality.ground_fog_prisms());
    let (sun, sun_shadows) = lights
        .iter()
        .next()
        .map_or((Vec3::Y, false), |(at, light)| {
            (at.back().as_vec3(), light.shadow_maps_enabled)
        });
    for (entity, prepared, fog, camera) in &cameras {
        match prepared.and_then(|prepared| prepared.0) {
            Some(mut uniform) => {
                uniform.sun_direction = sun.extend(0.0);
                if from_the_eye {
                    uniform.ranges.x = 0.0;
                }
                let mut view = commands.entity(entity);
                view.insert(ViewFogLayers(uniform));
                if sun_shadows && uniform.has_sun() {
                    view.insert(FogLayersSunShadows);
                } else {
                    view.remove::<FogLayersSunShadows>();
                }
                match fog.and_then(|fog| {
                    FogLayerLights::reaching(
                        &local_lights,
                        camera.translation(),
                        uniform.ranges.y,
                        fog.light_response,
                    )
                }) {
                    Some(lights) => view.insert(lights),
                    None => view.remove::<FogLayerLights>(),
                };
            }
            None => {
                // What was prepared for it too: the view entity is kept
                // from frame to frame, and the draw runs for every view
                // that has a pipeline and bind group.
                commands.entity(entity).remove::<(
                    ViewFogLayers,
                    FogLayerLights,
                    FogLayersSunShadows,
                    FogLayersView,
                    FogLayersBindGroup,
                )>();
            }
        }
    }
}

/// The fog pass reads the view's depth.
pub fn make_depth_readable(mut cameras: Query<&mut Camera3d, With<ViewFogLayers>>) {
    for mut camera in &mut cameras {
        camera.depth_texture_usages.0 |= TextureUsages::TEXTURE_BINDING.bits();
    }
}

/// What the fog pass's shader reads, `FogPass` in `fog_layers.wgsl`.
#[derive(Clone, Copy, ShaderType)]
pub struct FogPassUniform {
    /// Clip to view space (the inverse projection).
    view_from_clip: Mat4,
    /// The camera's rotation, view to world directions.
    world_from_view: Mat4,
    camera_position: Vec4,
    /// x, y, width, height of the viewport in pixels.
    viewport: Vec4,
    fog: FogLayersUniform,
    /// Zeros where no light reaches the fog.
    lights: LocalLightsUniform,
    /// The clouds' shadow maps over sunlit fog (no weight otherwise).
    clouds: [CloudShadowMapUniform; 2],
    /// The terrain's shadow heights over sunlit fog (no weight otherwise).
    terrain: TerrainShadowUniform,
}

/// Every fogged view's [`FogPassUniform`] of this frame.
#[derive(Resource, Default)]
pub struct FogPassUniforms(pub(super) DynamicUniformBuffer<FogPassUniform>);

/// Per fogged view: its uniform's offset and its pipeline.
#[derive(Component)]
pub struct FogLayersView {
    pub(super) uniform_offset: u32,
    pub(super) multisampled: bool,
    pub(super) pipeline: CachedRenderPipelineId,
    /// A light, or the sun, reads its shadow map (bind group 1,
    /// `nebel_render::light_shadows`).
    pub(super) shadowed: bool,
}

/// The fog pass's bind group layouts (single-sampled and multisampled
/// depth) and shader.
#[derive(Resource)]
pub struct FogLayersPipeline {
    pub(super) layouts: [BindGroupLayoutDescriptor; 2],
    /// Bevy's lights and shadow maps, group 1 of the variant whose lights
    /// cast shadows.
    pub(super) shadow_layout: BindGroupLayoutDescriptor,
    shader: Handle<Shader>,
    fullscreen_vertex: VertexState,
}

/// What a fog pass pipeline depends on.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub struct FogLayersPipelineKey {
    multisampled: bool,
    local_lights: bool,
    /// A light reads its shadow map (`LIGHT_SHADOWS`).
    light_shadows: bool,
    /// The fog scatters sunlight (`FOG_SUN`).
    sun: bool,
    /// Bevy's shadow map of the sun shades it (`SUN_SHADOWS`).
    sun_shadows: bool,
    target_format: TextureFormat,
}

fn init_fog_layers_pipeline(
    mut commands: Commands,
    asset_server: Res<AssetServer>,
    fullscreen_shader: Res<FullscreenShader>,
    device: Res<RenderDevice>,
) {
    let layout = |multisampled: bool| {
        BindGroupLayoutDescriptor::new(
            "nebel_fog_layers_layout",
            &BindGroupLayoutEntries::sequential(
                ShaderStages::FRAGMENT,
                (
                    uniform_buffer::<FogPassUniform>(true),
                    // Depth as unfilterable float (see `fog_layers.wgsl`).
                    if multisampled {
                        texture_2d_multisampled(TextureSampleType::Float { filterable: false })
                    } else {
                        texture_2d(TextureSampleType::Float { filterable: false })
                    },
                    // The clouds' shadow maps and their sampler
                    // (`nebel_render::cloud_shadow_maps`).
                    texture_2d(TextureSampleType::Float { filterable: true }),
                    texture_2d(TextureSampleType::Float { filterable: true }),
                    sampler(SamplerBindingType::Filtering),
                    // The terrain's shadow heights and their blocks' bounds,
                    // loaded texel by texel.
                    texture_2d(TextureSampleType::Float { filterable: false }),
                    texture_2d(TextureSampleType::Float { filterable: false }),
                ),
            ),
        )
    };
    commands.insert_resource(FogLayersPipeline {
        layouts: [layout(false), layout(true)],
        shadow_layout: light_shadow_layout(&device),
        shader: bevy::asset::load_embedded_asset!(asset_server.as_ref(), "fog_layers.wgsl"),
        fullscreen_vertex: fullscreen_shader.to_vertex_state(),
    });
}

impl SpecializedRenderPipeline for FogLayersPipeline {
    type Key = FogLayersPipelineKey;

    fn specialize(&self, key: Self::Key) -> RenderPipelineDescriptor {
        let mut shader_defs: Vec<ShaderDefVal> = vec![
            ShaderDefVal::UInt("MAX_LOCAL_LIGHTS".into(), MAX_LOCAL_LIGHTS as u32),
            ShaderDefVal::UInt("TERRAIN_SHADOW_BLOCK".into(), TERRAIN_SHADOW_BLOCK as u32),
        ];
        if key.multisampled {
            shader_defs.push("MULTISAMPLED".into());
        }
        if key.local_lights {
            shader_defs.push("LOCAL_LIGHTS".into());
        }
        if key.sun {
            shader_defs.push("FOG_SUN".into());
        }
        let mut layout = vec![self.layouts[usize::from(key.multisampled)].clone()];
        if key.sun_shadows {
            shader_defs.push("SUN_SHADOWS".into());
        }
        if (key.local_lights && key.light_shadows) || key.sun_shadows {
            shader_defs.push("LIGHT_SHADOWS".into());
            shader_defs.push(ShaderDefVal::UInt("LIGHT_SHADOW_GROUP".into(), 1));
            layout.push(self.shadow_layout.clone());
        }
        RenderPipelineDescriptor {
            label: Some("nebel_fog_layers_pipeline".into()),
            layout,
            vertex: self.fullscreen_vertex.clone(),
            fragment: Some(FragmentState {
                shader: self.shader.clone(),
                shader_defs,
                targets: vec![Some(ColorTargetState {
                    format: key.target_format,
                    blend: Some(BlendState::PREMULTIPLIED_ALPHA_BLENDING),
                    write_mask: ColorWrites::ALL,
                })],
                ..default()
            }),
            ..default()
        }
    }
}

/// Writes each fogged view's uniform and specialises its pipeline.
pub fn prepare_fog_layer_views(
    mut commands: Commands,
    views: Query<(
        Entity,
        &ExtractedView,
        &Msaa,
        &ViewFogLayers,
        Option<&FogLayerLights>,
        (
            Has<ViewShadowBindings>,
            Has<ViewLightsUniformOffset>,
            Has<FogLayersSunShadows>,
        ),
    )>,
    light_shadows: LightShadows,
    clouds: Option<Res<CloudShadowMaps>>,
    terrain: Option<Res<TerrainShadowTexture>>,
    mut uniforms: ResMut<FogPassUniforms>,
    pipeline: Res<FogLayersPipeline>,
    mut pipelines: ResMut<SpecializedRenderPipelines<FogLayersPipeline>>,
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
) {
    if views.is_empty() {
        return;
    }
    uniforms.0.clear();
    for (entity, view, msaa, fog, lights, (shadow_maps, lights_offset, sun_shadows)) in &views {
        // Each light that casts shadows reads Bevy's map of this frame.
        let lights = lights.map(|lights| FogLayerLights {
            lights: lights
                .lights
                .with_shadow_indices(|entity| light_shadows.light_index(entity)),
            ..*lights
        });
        let light_shadows = shadow_maps
            && lights_offset
            && lights.is_some_and(|lights| lights.lights.is_shadowed());
        let sun_shadows = shadow_maps && lights_offset && sun_shadows && fog.0.has_sun();
        let rotation = Mat4::from_quat(view.world_from_view.rotation());
        let uniform_offset = uniforms.0.push(&FogPassUniform {
            view_from_clip: view.clip_from_view.inverse(),
            world_from_view: rotation,
            camera_position: view.world_from_view.translation().extend(1.0),
            viewport: view.viewport.as_vec4(),
            fog: fog.0,
            lights: lights.map_or_else(LocalLightsUniform::default, |lights| lights.uniform()),
            clouds: if fog.0.has_sun() {
                CloudShadowMaps::of(clouds.as_deref())
            } else {
                Default::default()
            },
            terrain: terrain
                .as_ref()
                .filter(|_| fog.0.has_sun())
                .map_or_else(TerrainShadowUniform::default, |terrain| terrain.uniform),
        });
        let multisampled = *msaa != Msaa::Off;
        let pipeline = pipelines.specialize(
            &pipeline_cache,
            &pipeline,
            FogLayersPipelineKey {
                multisampled,
                local_lights: lights.is_some(),
                light_shadows,
                sun: fog.0.has_sun(),
                sun_shadows,
                target_format: view.target_format,
            },
        );
        commands.entity(entity).insert(FogLayersView {
            uniform_offset,
            multisampled,
            pipeline,
            shadowed: light_shadows || sun_shadows,
        });
    }
    uniforms.0.write_buffer(&device, &queue);
}

/// A fogged view's bind group and what it was made from.
#[derive(Component)]
pub struct FogLayersBindGroup {
    pub(super) bind_group: BindGroup,
    /// The depth texture view, the uniform buffer, whether the depth is
    /// multisampled, the clouds' shadow maps and the terrain's.
    key: (
        TextureViewId,
        BufferId,
        bool,
        [TextureViewId; 2],
        TextureViewId,
    ),
}

/// Gives each fogged view its bind group, made again only when the depth
/// texture, the uniform buffer, the sample count or the clouds' shadow
/// maps changed.
pub fn prepare_fog_layer_bind_groups(
    mut commands: Commands,
    views: Query<(
        Entity,
        &ViewDepthTexture,
        &FogLayersView,
        Option<&FogLayersBindGroup>,
    )>,
    uniforms: Res<FogPassUniforms>,
    pipeline: Res<FogLayersPipeline>,
    pipeline_cache: Res<PipelineCache>,
    clouds: CloudShadowTextures,
    terrain: Option<Res<TerrainShadowTexture>>,
    device: Res<RenderDevice>,
) {
    let (Some(buffer), Some(binding), Some(terrain)) =
        (uniforms.0.buffer(), uniforms.0.binding(), terrain)
    else {
        return;
    };
    let (cloud_maps, cloud_sampler) = clouds.bindings();
    for (entity, depth, fog_view, made) in &views {
        let key = (
            depth.view().id(),
            buffer.id(),
            fog_view.multisampled,
            cloud_maps.map(TextureView::id),
            terrain.view.id(),
        );
        if made.is_some_and(|made| made.key == key) {
            continue;
        }
        let bind_group = device.create_bind_group(
            "nebel_fog_layers_bind_group",
            &pipeline_cache
                .get_bind_group_layout(&pipeline.layouts[usize::from(fog_view.multisampled)]),
            &BindGroupEntries::sequential((
                binding.clone(),
                depth.view(),
                cloud_maps[0],
                cloud_maps[1],
                cloud_sampler,
                &terrain.view,
                &terrain.blocks,
            )),
        );
        commands
            .entity(entity)
            .insert(FogLayersBindGroup { bind_group, key });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::math::DVec3;
    use nebel_core::local_light::LocalLight;

    #[test]
    fn the_fog_takes_the_lights_within_its_distance_or_none() {
        let at = |x: f64, lumens: f64| SceneLight {
            light: LocalLight::from_lumens(DVec3::new(x, 0.0, 0.0), DVec3::ONE, lumens, 10.0),
            shadow_source: None,
        };
        let lights = [at(50.0, 1e5), at(5.0, 1e4), at(200.0, 1e9)];
        let response = LightResponse {
            asymmetry: 0.3,
            strength: 2.0,
        };
        // The far light's range ends beyond the fog's 100 m.
        let near = FogLayerLights::reaching(&lights, Vec3::ZERO, 100.0, response)
            .expect("two lights reach");
        assert_eq!(near.uniform().response.x, 2.0);
        assert_eq!(
            (near.uniform().response.y, near.uniform().response.w),
            (0.3, 2.0)
        );
        // The brighter light at the eye first: 1e4 lm at 5 m over 1e5 at 50 m.
        assert_eq!(near.uniform().lights[0].position.x, 5.0);
        assert_eq!(
            FogLayerLights::reaching(&lights, Vec3::new(0.0, 500.0, 0.0), 100.0, response),
            None
        );
        assert_eq!(
            FogLayerLights::reaching(&[], Vec3::ZERO, 1e5, response),
            None
        );
        // A bad response is clamped, not passed on; one of no strength
        // takes no lights.
        let bad = LightResponse {
            asymmetry: f32::NAN,
            strength: 2.0,
        };
        let clamped = FogLayerLights::reaching(&lights, Vec3::ZERO, 100.0, bad).unwrap();
        assert_eq!(
            (clamped.uniform().response.y, clamped.uniform().response.w),
            (0.0, 2.0)
        );
        let dark = LightResponse {
            strength: f32::NAN,
            ..response
        };
        assert_eq!(
            FogLayerLights::reaching(&lights, Vec3::ZERO, 100.0, dark),
            None
        );
    }
}
