//! Cloud shadows on the ground: lit clouds dim the sun's light on the meshes
//! below them (Nes 2008 §6.1).
//!
//! A lit grid [`Volume`] with [`CloudShadowCaster`] casts the transmittance
//! toward the sun of its light field's model, `e^{−σ ∫ f ds}` with `σ` its
//! [`VolumeLighting::shadow_extinction`], exact for the trilinear density
//! (`nebel_core::field::GroundShadow`): a map over the horizontal plane
//! under the casters' lowest corner, one for all casters, for the first
//! `DirectionalLight`. A mesh with [`CloudShadowReceiver`] and a
//! `StandardMaterial` is drawn with [`CloudShadowMaterial`] instead: the same
//! material, whose sun light (as Bevy's PBR adds it, with its shadow map) is
//! scaled by the map's transmittance where the line toward the sun crosses
//! the plane. The ambient and every other light stay as they are. The maps
//! are shared as `nebel_render`'s [`CloudShadowMaps`], so the sun in a
//! sunlit ground fog is dimmed by them too.
//!
//! Maps are made on the task pool when the sun turns by more than
//! [`CloudShadowSettings::sun_step`] or a caster changes (at most every
//! [`CloudShadowSettings::interval`]), and every keyframe interval while a
//! windy cloud moves. A new map fades in over the time since the one before
//! was started, so the shadow moves smoothly; each is made for the time it
//! is fully in (the sun extrapolated from its last frame's motion, a windy
//! cloud's grid at that time), so the shadow keeps up with the sun and the
//! wind to within a build's time. Under [`HeavyBuilds::Blocking`] each
//! frame's map is for that frame and shows at once. A volume of cells casts
//! no shadow.

use std::collections::HashMap;
use std::sync::Arc;

use bevy::asset::{AssetEvent, RenderAssetUsages, embedded_asset};
use bevy::diagnostic::{DiagnosticPath, Diagnostics};
use bevy::image::ImageSampler;
use bevy::math::DAffine3;
use bevy::pbr::{ExtendedMaterial, MaterialExtension, MaterialPlugin};
use bevy::prelude::*;
use bevy::render::render_resource::{
    AsBindGroup, Extent3d, ShaderType, TextureDimension, TextureFormat,
};
use bevy::render::storage::ShaderBuffer;
use bevy::shader::ShaderRef;
use bevy::transform::TransformSystems;
use nebel_core::field::{DensityGrid, GroundShadow, ShadowCaster};
use nebel_core::pacing::worker_threads;
use nebel_lod::AnimatedGrid;
use nebel_render::cloud_shadow_maps::load_cloud_shadow_maps_library;
use nebel_render::{
    CloudShadowMapUniform, CloudShadowMaps, HeavyBuild, HeavyBuilds, NebelSystems, cpu_timed,
    register_diagnostics,
};

use crate::cloud::{CloudGeneration, animates};
use crate::{CloudVolume, Volume, VolumeField, VolumeGrid, VolumeLighting};

/// Adds cloud shadows on the ground: [`CloudShadowCaster`],
/// [`CloudShadowReceiver`], [`CloudShadowMaterial`] and their systems (see
/// the module docs). A world without casters makes no map.
#[derive(Default)]
pub struct CloudShadowPlugin;

impl CloudShadowPlugin {
    /// Time of each map's build (on the task pool), ms.
    pub const BUILD_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/volume/cloud_shadow_ms");
}

impl Plugin for CloudShadowPlugin {
    fn build(&self, app: &mut App) {
        register_diagnostics(app, &[(Self::BUILD_MS, " ms")]);
        embedded_asset!(app, "cloud_shadow.wgsl");
        load_cloud_shadow_maps_library(app);
        app.add_plugins(MaterialPlugin::<CloudShadowMaterial>::default())
            .init_resource::<CloudShadowSettings>()
            .init_resource::<HeavyBuilds>()
            .init_resource::<CloudShadowMaps>()
            .register_type::<CloudShadowCaster>()
            .register_type::<CloudShadowReceiver>()
            .register_type::<CloudShadowSettings>()
            .add_systems(
                PostUpdate,
                (
                    cpu_timed(update_cloud_shadows),
                    cpu_timed(receive_cloud_shadows),
                )
                    .chain()
                    .in_set(NebelSystems)
                    .after(TransformSystems::Propagate),
            );
    }
}

/// Makes a lit grid [`Volume`] cast its shadow on the ground (see the module
/// docs); its [`VolumeLighting::shadow_extinction`] sets how dark.
#[derive(Component, Clone, Copy, Debug, Default, PartialEq, Eq, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(VolumeLighting)]
pub struct CloudShadowCaster;

/// Draws this mesh's `StandardMaterial` as a [`CloudShadowMaterial`], so
/// the clouds' shadow dims its sunlight (see the module docs). Changes to
/// the `StandardMaterial` asset carry over; removed, the mesh gets its
/// `StandardMaterial` back.
#[derive(Component, Clone, Copy, Debug, Default, PartialEq, Eq, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct CloudShadowReceiver;

/// How the cloud shadow map is made.
#[derive(Resource, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Resource, Default, Clone)]
pub struct CloudShadowSettings {
    /// Texels along the longer side of the map, 3 to
    /// [`GroundShadow::MAX_RESOLUTION`] (clamped). Default 256.
    pub resolution: u32,
    /// The angle the sun turns before a new map is made, radians (at least
    /// 10⁻⁴). Default 0.002 (about a ninth of a degree).
    pub sun_step: f32,
    /// The least time between the starts of two maps' builds, seconds
    /// (not under [`HeavyBuilds::Blocking`]); a windy cloud's keyframe
    /// interval if that is longer. Default 0.5.
    pub interval: f32,
}

impl Default for CloudShadowSettings {
    fn default() -> Self {
        Self {
            resolution: 256,
            sun_step: 0.002,
            interval: 0.5,
        }
    }
}

/// A `StandardMaterial` whose sunlight the clouds' shadow dims.
pub type CloudShadowMaterial = ExtendedMaterial<StandardMaterial, CloudShadowExtension>;

/// The cloud shadow maps a [`CloudShadowMaterial`] reads: two maps, the
/// newest fading in over the one before, and where they lie.
#[derive(Asset, AsBindGroup, Reflect, Debug, Clone)]
pub struct CloudShadowExtension {
    #[texture(100)]
    #[sampler(101)]
    first: Handle<Image>,
    #[texture(102)]
    second: Handle<Image>,
    #[storage(103, read_only)]
    maps: Handle<ShaderBuffer>,
}

impl MaterialExtension for CloudShadowExtension {
    fn fragment_shader() -> ShaderRef {
        "embedded://nebel_volume/cloud_shadow.wgsl".into()
    }
}

/// Both maps as the shader reads them, and the sun they dim.
#[derive(Clone, Copy, Debug, Default, PartialEq, ShaderType)]
struct MapsUniform {
    maps: [CloudShadowMapUniform; 2],
    /// Toward the sun now (xyz), to find its light among Bevy's: a map's own
    /// sun may lie ahead of it. Written again when it has turned by
    /// [`SUN_MATCH_STEP`].
    sun: Vec4,
}

/// The angle the sun turns before the shader is told where it is, radians
/// (the shader finds the light within about 8° of it).
const SUN_MATCH_STEP: f32 = 0.02;

/// `map`'s transmittance as the texels of a texture of `side` texels a side
/// (R8, lit beyond the map), made with the map off the frame.
fn texels(map: &GroundShadow, side: usize) -> Vec<u8> {
    let mut texels = vec![u8::MAX; side * side];
    for (row, values) in texels
        .chunks_mut(side)
        .zip(map.transmittance.chunks(map.size[0]))
    {
        for (texel, t) in row.iter_mut().zip(values) {
            *texel = (t.clamp(0.0, 1.0) * 255.0).round() as u8;
        }
    }
    texels
}

/// A caster's density as a map's build reads it.
#[derive(Clone, Debug)]
enum CasterGrid {
    Still(Arc<DensityGrid>),
    /// A windy cloud, sampled at the build's time.
    Windy(Arc<dyn AnimatedGrid>),
}

impl CasterGrid {
    fn same(&self, other: &Self) -> bool {
        match (self, other) {
            (Self::Still(a), Self::Still(b)) => Arc::ptr_eq(a, b),
            (Self::Windy(a), Self::Windy(b)) => std::ptr::addr_eq(Arc::as_ptr(a), Arc::as_ptr(b)),
            _ => false,
        }
    }
}

/// What a map is made of.
#[derive(Clone, Debug)]
struct Inputs {
    casters: Vec<(CasterGrid, DAffine3, f64)>,
    sun: Vec3,
    resolution: u32,
}

impl Inputs {
    /// Whether a map of `self` differs from one of `old` (the sun within
    /// `sun_step`).
    fn differs(&self, old: &Self, sun_step: f32) -> bool {
        self.resolution != old.resolution
            || self.sun.angle_between(old.sun) > sun_step.max(1e-4)
            || self.casters.len() != old.casters.len()
            || self
                .casters
                .iter()
                .zip(&old.casters)
                .any(|(a, b)| !a.0.same(&b.0) || a.1 != b.1 || a.2 != b.2)
    }

    fn build(self, time: f64) -> Option<GroundShadow> {
        let mut casters = Vec::with_capacity(self.casters.len());
        for (grid, world_from_local, extinction) in &self.casters {
            casters.push(ShadowCaster {
                grid: match grid {
                    CasterGrid::Still(grid) => grid.clone(),
                    CasterGrid::Windy(animation) => Arc::new(animation.grid_at(time).ok()?),
                },
                world_from_local: *world_from_local,
                extinction: *extinction,
            });
        }
        GroundShadow::compute(
            &casters,
            self.sun.as_dvec3(),
            self.resolution as usize,
            worker_threads(),
        )
    }
}

/// The maps, their textures and the build in flight (internal).
#[derive(Resource)]
struct CloudShadowState {
    textures: [Handle<Image>; 2],
    maps: Handle<ShaderBuffer>,
    side: u32,
    /// The texture the next map goes to.
    next: usize,
    /// Each texture's map and the time its build started.
    shown: [Option<(GroundShadow, f64)>; 2],
    /// When the newest map landed and how long it fades in.
    fade: (f64, f64),
    uniform: MapsUniform,
    /// The build in flight (its map and texels, and its time, ms) and its
    /// start.
    build: Option<(HeavyBuild<(Option<(GroundShadow, Vec<u8>)>, f64)>, f64)>,
    /// The inputs of the last build started, and its time.
    started: Option<(Inputs, f64)>,
    /// The sun in the frame before and its time, for the sun's motion.
    sun_seen: Option<(Vec3, f64)>,
    /// The shadow material made for each receiver's `StandardMaterial`.
    materials: HashMap<AssetId<StandardMaterial>, Handle<CloudShadowMaterial>>,
}

impl CloudShadowState {
    fn new(side: u32, images: &mut Assets<Image>, buffers: &mut Assets<ShaderBuffer>) -> Self {
        let mut maps = ShaderBuffer::default();
        maps.set_data(MapsUniform::default());
        Self {
            textures: [0, 1].map(|_| images.add(Self::texture(side))),
            maps: buffers.add(maps),
            side,
            next: 0,
            shown: [None, None],
            fade: (0.0, 0.0),
            uniform: MapsUniform::default(),
            build: None,
            started: None,
            sun_seen: None,
            materials: HashMap::new(),
        }
    }

    /// New textures of `side` texels a side for every shadow material; the
    /// maps are made again (a build in flight, of the old size, is dropped).
    fn resize(
        &mut self,
        side: u32,
        images: &mut Assets<Image>,
        materials: &mut Assets<CloudShadowMaterial>,
    ) {
        self.textures = [0, 1].map(|_| images.add(Self::texture(side)));
        self.side = side;
        self.shown = [None, None];
        self.build = None;
        self.started = None;
        for handle in self.materials.values() {
            if let Some(mut material) = materials.get_mut(handle) {
                material.extension.first = self.textures[0].clone();
                material.extension.second = self.textures[1].clone();
            }
        }
    }

    /// A texture of `side` texels a side, lit everywhere.
    fn texture(side: u32) -> Image {
        let mut image = Image::new_fill(
            Extent3d {
                width: side,
                height: side,
                depth_or_array_layers: 1,
            },
            TextureDimension::D2,
            &[u8::MAX],
            TextureFormat::R8Unorm,
            RenderAssetUsages::default(),
        );
        image.sampler = ImageSampler::linear();
        image
    }

    /// Puts `map` and its texels, started at `started`, into the next
    /// texture, landing at `now`; it fades in over the time since the one
    /// before was started if `fades`, at once otherwise.
    fn land(
        &mut self,
        map: Option<(GroundShadow, Vec<u8>)>,
        started: f64,
        now: f64,
        fades: bool,
        images: &mut Assets<Image>,
    ) {
        let slot = self.next;
        self.next = 1 - slot;
        let previous_start = self.shown[1 - slot].as_ref().map(|(_, t)| *t);
        let duration = previous_start
            .filter(|_| fades)
            .map_or(0.0, |t| (started - t).max(0.0));
        self.fade = (now, duration);
        self.shown[slot] = map.map(|(map, texels)| {
            if let Some(mut image) = images.get_mut(&self.textures[slot]) {
                image.data = Some(texels);
            }
            (map, started)
        });
    }

    /// The maps' weights at `now`, the newest fading in over the one before,
    /// and the sun `sun` (the one last told while within
    /// [`SUN_MATCH_STEP`]).
    fn uniform(&self, now: f64, sun: Vec3) -> MapsUniform {
        let newest = 1 - self.next;
        let (landed, duration) = self.fade;
        let w = if duration > 0.0 {
            ((now - landed) / duration).clamp(0.0, 1.0) as f32
        } else {
            1.0
        };
        let told = self.uniform.sun.truncate();
        let mut uniform = MapsUniform {
            sun: if told.angle_between(sun) <= SUN_MATCH_STEP {
                told
            } else {
                sun
            }
            .extend(0.0),
            ..default()
        };
        for (slot, weight) in [(newest, w), (1 - newest, 1.0 - w)] {
            if let Some((map, _)) = &self.shown[slot] {
                uniform.maps[slot] = CloudShadowMapUniform::new(map, self.side, weight);
            }
        }
        uniform
    }
}

/// What each caster shades with, this frame.
type Casters<'w, 's> = Query<
    'w,
    's,
    (
        &'static Volume,
        &'static GlobalTransform,
        &'static VolumeLighting,
        &'static InheritedVisibility,
        Option<(&'static CloudVolume, &'static CloudGeneration)>,
    ),
    With<CloudShadowCaster>,
>;

/// Starts a map when its inputs changed, lands finished ones and fades them
/// in (see the module docs).
#[allow(clippy::too_many_arguments)]
fn update_cloud_shadows(
    mut commands: Commands,
    casters: Casters,
    suns: Query<&GlobalTransform, With<DirectionalLight>>,
    grids: Res<Assets<VolumeGrid>>,
    settings: Res<CloudShadowSettings>,
    mode: Res<HeavyBuilds>,
    time: Res<Time>,
    state: Option<ResMut<CloudShadowState>>,
    mut images: ResMut<Assets<Image>>,
    mut buffers: ResMut<Assets<ShaderBuffer>>,
    mut materials: ResMut<Assets<CloudShadowMaterial>>,
    mut shared: ResMut<CloudShadowMaps>,
    mut diagnostics: Diagnostics,
) {
    let now = time.elapsed_secs_f64();
    let sun = suns
        .iter()
        .next()
        .map_or(Vec3::Y, |sun| sun.back().as_vec3());
    let mut windy_interval = f64::INFINITY;
    let mut inputs = Inputs {
        casters: Vec::new(),
        sun,
        resolution: settings
            .resolution
            .clamp(3, GroundShadow::MAX_RESOLUTION as u32),
    };
    for (volume, transform, lighting, visibility, cloud) in &casters {
        let animation = cloud
            .filter(|(cloud, _)| animates(cloud))
            .and_then(|(cloud, generation)| Some((cloud, generation.animation.clone()?)));
        let grid = match (&volume.field, animation) {
            (_, Some((cloud, animation))) => {
                windy_interval = windy_interval.min(f64::from(cloud.keyframe_interval.max(1e-3)));
                CasterGrid::Windy(animation)
            }
            (VolumeField::Grid(handle), None) => match grids.get(handle) {
                Some(grid) => CasterGrid::Still(grid.0.clone()),
                None => continue,
            },
            (VolumeField::Cells(_), None) => continue,
        };
        if visibility.get() {
            let world_from_local = transform.affine();
            inputs.casters.push((
                grid,
                DAffine3::from_mat4(Mat4::from(world_from_local).as_dmat4()),
                f64::from(lighting.shadow_extinction),
            ));
        }
    }
    let Some(mut state) = state else {
        if !inputs.casters.is_empty() {
            let side = inputs.resolution;
            commands.insert_resource(CloudShadowState::new(side, &mut images, &mut buffers));
        }
        return;
    };
    let state = &mut *state;
    if inputs.resolution != state.side {
        state.resize(inputs.resolution, &mut images, &mut materials);
    }
    if state.build.is_none() {
        let due = state.started.as_ref().is_none_or(|(old, at)| {
            let waited = now - at;
            let rested =
                *mode == HeavyBuilds::Blocking || waited >= f64::from(settings.interval).max(0.0);
            rested && inputs.differs(old, settings.sun_step)
                || (windy_interval.is_finite() && waited >= windy_interval)
        });
        if due {
            // The map fades in until the next one starts: made for then (the
            // sun turned on at its rate, a windy cloud's grid at that time),
            // it shows the scene as it is when fully in (module docs). The
            // next start: a windy cloud's next keyframe, or when the sun has
            // turned by a step (not before the interval); none where nothing
            // moves.
            let turn = state
                .sun_seen
                .filter(|(_, at)| now > *at)
                .and_then(|(seen, at)| {
                    let axis = seen.cross(sun).try_normalize()?;
                    Some((axis, f64::from(seen.angle_between(sun)) / (now - at)))
                });
            let sun_period = turn.map_or(f64::INFINITY, |(_, rate)| {
                (f64::from(settings.sun_step.max(1e-4)) / rate)
                    .max(f64::from(settings.interval).max(0.0))
            });
            let next = sun_period.min(windy_interval);
            let first = state.started.is_none();
            let ahead = if first || *mode == HeavyBuilds::Blocking || next.is_infinite() {
                0.0
            } else {
                next
            };
            let mut work = inputs.clone();
            if let Some((axis, rate)) = turn {
                work.sun = Quat::from_axis_angle(axis, (rate * ahead) as f32) * sun;
            }
            let side = state.side as usize;
            let build = HeavyBuild::spawn(move || {
                let started = std::time::Instant::now();
                let map = work.build(now + ahead).map(|map| {
                    let texels = texels(&map, side);
                    (map, texels)
                });
                (map, started.elapsed().as_secs_f64() * 1e3)
            });
            state.build = Some((build, now));
            state.started = Some((inputs, now));
        }
    }
    // Under `Blocking` the frame waits for the map it asked for and shows it
    // at once.
    if let Some((build, started)) = &mut state.build
        && let Some((map, ms)) = build.poll(*mode)
    {
        diagnostics.add_measurement(&CloudShadowPlugin::BUILD_MS, || ms);
        let started = *started;
        state.build = None;
        state.land(
            map,
            started,
            now,
            *mode != HeavyBuilds::Blocking,
            &mut images,
        );
    }
    state.sun_seen = Some((sun, now));
    let uniform = state.uniform(now, sun);
    if uniform != state.uniform
        && let Some(mut buffer) = buffers.get_mut(&state.maps)
    {
        buffer.set_data(uniform);
        state.uniform = uniform;
    }
    shared.set_if_neq(CloudShadowMaps {
        textures: state.textures.clone(),
        maps: uniform.maps,
    });
}

/// Draws each receiver's `StandardMaterial` as a [`CloudShadowMaterial`],
/// carries changes of the `StandardMaterial` over, and gives a former
/// receiver its `StandardMaterial` back.
fn receive_cloud_shadows(
    mut commands: Commands,
    receivers: Query<(Entity, &MeshMaterial3d<StandardMaterial>), With<CloudShadowReceiver>>,
    former: Query<(Entity, &ShadowedMaterial), Without<CloudShadowReceiver>>,
    state: Option<ResMut<CloudShadowState>>,
    standard: Res<Assets<StandardMaterial>>,
    mut events: MessageReader<AssetEvent<StandardMaterial>>,
    mut materials: ResMut<Assets<CloudShadowMaterial>>,
) {
    let Some(mut state) = state else {
        return;
    };
    let state = &mut *state;
    for event in events.read() {
        if let AssetEvent::Modified { id } = event
            && let Some(handle) = state.materials.get(id)
            && let (Some(base), Some(mut material)) = (standard.get(*id), materials.get_mut(handle))
        {
            material.base = base.clone();
        }
    }
    for (entity, material) in &receivers {
        let Some(base) = standard.get(&material.0) else {
            continue;
        };
        let handle = state
            .materials
            .entry(material.id())
            .or_insert_with(|| {
                materials.add(CloudShadowMaterial {
                    base: base.clone(),
                    extension: CloudShadowExtension {
                        first: state.textures[0].clone(),
                        second: state.textures[1].clone(),
                        maps: state.maps.clone(),
                    },
                })
            })
            .clone();
        commands
            .entity(entity)
            .remove::<MeshMaterial3d<StandardMaterial>>()
            .insert((MeshMaterial3d(handle), ShadowedMaterial(material.0.clone())));
    }
    // A receiver no more: its own material back.
    for (entity, ShadowedMaterial(base)) in &former {
        commands
            .entity(entity)
            .remove::<(MeshMaterial3d<CloudShadowMaterial>, ShadowedMaterial)>()
            .insert(MeshMaterial3d(base.clone()));
    }
}

/// The `StandardMaterial` a receiver is drawn with as a
/// [`CloudShadowMaterial`], given back when it stops receiving.
#[derive(Component)]
struct ShadowedMaterial(Handle<StandardMaterial>);

#[cfg(test)]
mod tests {
    use bevy::math::DVec3;
    use nebel_render::headless::headless_app;

    use super::*;

    /// A world with the plugin, a sun and a receiver, without a renderer.
    fn app() -> (App, Entity, Handle<StandardMaterial>) {
        let mut app = headless_app(None);
        app.init_asset::<Image>()
            .init_asset::<ShaderBuffer>()
            .init_asset::<StandardMaterial>()
            .add_plugins((crate::VolumePlugin, CloudShadowPlugin));
        app.world_mut().spawn((
            DirectionalLight::default(),
            Transform::default().looking_to(Vec3::new(-0.3, -1.0, -0.2), Vec3::Y),
        ));
        let material = app
            .world_mut()
            .resource_mut::<Assets<StandardMaterial>>()
            .add(StandardMaterial::default());
        let receiver = app
            .world_mut()
            .spawn((MeshMaterial3d(material.clone()), CloudShadowReceiver))
            .id();
        (app, receiver, material)
    }

    /// A uniform slab 10 units thick at height 50 casting with `σ = 0.05`.
    fn spawn_slab(app: &mut App) -> Entity {
        let grid = DensityGrid::new(
            [3, 3, 3],
            DVec3::new(10.0, 5.0, 10.0),
            DVec3::new(-10.0, 50.0, -10.0),
            vec![1.0; 27],
        )
        .unwrap();
        let handle = app
            .world_mut()
            .resource_mut::<Assets<VolumeGrid>>()
            .add(VolumeGrid::from(grid));
        app.world_mut()
            .spawn((
                Volume {
                    field: VolumeField::Grid(handle),
                    ..default()
                },
                VolumeLighting {
                    shadow_extinction: 0.05,
                    ..default()
                },
                CloudShadowCaster,
                InheritedVisibility::VISIBLE,
            ))
            .id()
    }

    #[test]
    fn without_a_caster_nothing_is_made_or_swapped() {
        let (mut app, receiver, _) = app();
        for _ in 0..3 {
            app.update();
        }
        assert!(app.world().get_resource::<CloudShadowState>().is_none());
        assert!(
            app.world()
                .get::<MeshMaterial3d<StandardMaterial>>(receiver)
                .is_some()
        );
        assert!(app.world().resource::<Assets<Image>>().is_empty());
    }

    /// The caster's map is the slab's closed form, the receiver draws the
    /// shadow material, and a change of its `StandardMaterial` carries over.
    #[test]
    fn a_caster_shades_its_receivers() {
        let (mut app, receiver, standard) = app();
        spawn_slab(&mut app);
        for _ in 0..3 {
            app.update();
        }
        let state = app.world().resource::<CloudShadowState>();
        let (map, _) = state.shown[1 - state.next].as_ref().expect("a map");
        let sun = DVec3::new(0.3, 1.0, 0.2).normalize();
        let below_centre = DVec3::new(0.0, 50.0, 0.0) - sun * (50.0 / sun.y);
        let closed = (-0.05 * 10.0 / sun.y).exp();
        assert!((map.transmittance(below_centre) - closed).abs() < 1e-4);
        assert_eq!(
            state.uniform.maps[1 - state.next].sun_and_weight.w,
            1.0,
            "no fade under Blocking"
        );
        assert!(
            app.world()
                .get::<MeshMaterial3d<StandardMaterial>>(receiver)
                .is_none()
        );
        let shaded = app
            .world()
            .get::<MeshMaterial3d<CloudShadowMaterial>>(receiver)
            .expect("the shadow material")
            .0
            .clone();
        let red = Color::srgb(1.0, 0.0, 0.0);
        app.world_mut()
            .resource_mut::<Assets<StandardMaterial>>()
            .get_mut(&standard)
            .unwrap()
            .base_color = red;
        app.update();
        let materials = app.world().resource::<Assets<CloudShadowMaterial>>();
        assert_eq!(materials.get(&shaded).unwrap().base.base_color, red);
        app.world_mut()
            .entity_mut(receiver)
            .remove::<CloudShadowReceiver>();
        app.update();
        let restored = app
            .world()
            .get::<MeshMaterial3d<StandardMaterial>>(receiver);
        assert_eq!(restored.map(|m| m.id()), Some(standard.id()));
        assert!(
            app.world()
                .get::<MeshMaterial3d<CloudShadowMaterial>>(receiver)
                .is_none()
        );
    }

    /// A new map fades in over the time since the one before was started;
    /// the weights always sum to one.
    #[test]
    fn a_new_map_fades_in_over_the_interval_between_builds() {
        let (mut images, mut buffers) = (Assets::default(), Assets::default());
        let mut state = CloudShadowState::new(16, &mut images, &mut buffers);
        let g = DensityGrid::new([2, 2, 2], DVec3::ONE, DVec3::Y * 5.0, vec![1.0; 8]).unwrap();
        let caster = ShadowCaster {
            grid: Arc::new(g),
            world_from_local: DAffine3::IDENTITY,
            extinction: 1.0,
        };
        let map = || {
            GroundShadow::compute(std::slice::from_ref(&caster), DVec3::Y, 16, 1).map(|map| {
                let texels = texels(&map, 16);
                (map, texels)
            })
        };
        state.land(map(), 0.0, 0.5, true, &mut images);
        let first = images.get(&state.textures[0]).unwrap().data.clone();
        assert_eq!(
            first,
            map().map(|(_, texels)| texels),
            "the texels land in the texture"
        );
        assert_eq!(
            state.uniform(0.5, Vec3::Y).maps[0].sun_and_weight.w,
            1.0,
            "the first map shows at once"
        );
        state.land(map(), 2.0, 2.5, true, &mut images);
        for (now, weight) in [(2.5, 0.0), (3.5, 0.5), (4.5, 1.0), (9.0, 1.0)] {
            let uniform = state.uniform(now, Vec3::Y);
            let [old, new] = [
                uniform.maps[0].sun_and_weight.w,
                uniform.maps[1].sun_and_weight.w,
            ];
            assert_eq!(new, weight, "at {now}");
            assert_eq!(old + new, 1.0);
        }
        // The sun set: the last map fades out to full light.
        state.land(None, 3.0, 4.5, true, &mut images);
        let uniform = state.uniform(5.0, Vec3::Y);
        assert_eq!(uniform.maps[0].sun_and_weight.w, 0.0);
        assert_eq!(uniform.maps[1].sun_and_weight.w, 0.5);
    }

    /// In the background, a map after the first is made for the time it is
    /// fully faded in: the sun turning at a steady rate is extrapolated to
    /// the end of the interval.
    #[test]
    fn a_map_is_made_for_the_sun_at_the_end_of_its_fade() {
        use bevy::time::TimeUpdateStrategy;
        use std::time::Duration;
        let (mut app, _, _) = app();
        app.insert_resource(HeavyBuilds::Background)
            .insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_millis(
                100,
            )))
            .insert_resource(CloudShadowSettings {
                interval: 1.0,
                ..default()
            });
        spawn_slab(&mut app);
        // The sun turns about x by 0.02 rad every frame of 0.1 s.
        let turn = |frame: u32| {
            let toward =
                Quat::from_rotation_x(0.02 * frame as f32) * Vec3::new(0.0, 1.0, 0.3).normalize();
            Transform::default().looking_to(-toward, Vec3::Y)
        };
        let mut suns = Vec::new();
        for frame in 0..60 {
            let mut lights = app
                .world_mut()
                .query_filtered::<&mut Transform, With<DirectionalLight>>();
            *lights.single_mut(app.world_mut()).unwrap() = turn(frame);
            app.update();
            std::thread::sleep(Duration::from_millis(5));
            // The shader finds the sun's light by where the sun is now, not
            // by the maps' suns ahead of it (from the frame after the one
            // that made the state).
            if let Some(state) = app.world().get_resource::<CloudShadowState>()
                && frame > 0
            {
                let (told, now) = (state.uniform.sun.truncate(), turn(frame).back().as_vec3());
                assert!(
                    told.angle_between(now) <= SUN_MATCH_STEP + 1e-4,
                    "frame {frame}: {told} against {now}"
                );
            }
            if let Some(state) = app.world().get_resource::<CloudShadowState>()
                && let Some((map, started)) = &state.shown[1 - state.next]
                && suns.last().is_none_or(|(_, s, _)| s != started)
            {
                suns.push((map.sun, *started, state.fade.1));
            }
        }
        assert!(suns.len() >= 3, "{} maps", suns.len());
        for (sun, started, fade) in &suns[1..] {
            // It fades in until the next start, the interval on.
            assert!(
                (fade - 1.0).abs() < 0.15,
                "map of {started} s fades over {fade} s"
            );
            // Started at `started`, the time of frame `10 started`, made for
            // 1 s later: ten frames on.
            let frame = (started * 10.0).round() as u32;
            let expected = turn(frame + 10).back().as_dvec3();
            assert!(
                sun.angle_between(expected) < 2e-3,
                "map of {started} s: {sun} against {expected}"
            );
        }
    }

    /// A new resolution drops the build in flight, gives every shadow
    /// material new textures, and the next map has the new size.
    #[test]
    fn a_new_resolution_makes_maps_of_its_size() {
        let (mut app, receiver, _) = app();
        app.insert_resource(HeavyBuilds::Background);
        spawn_slab(&mut app);
        app.update();
        app.update();
        assert!(app.world().resource::<CloudShadowState>().build.is_some());
        app.insert_resource(CloudShadowSettings {
            resolution: 16,
            ..default()
        });
        let mut landed = None;
        for _ in 0..200 {
            app.update();
            let state = app.world().resource::<CloudShadowState>();
            if let Some((map, _)) = &state.shown[1 - state.next] {
                landed = Some(map.size);
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        let size = landed.expect("a map");
        assert!(
            size.iter().all(|&n| n <= 16) && size.contains(&16),
            "{size:?}"
        );
        let state = app.world().resource::<CloudShadowState>();
        let handle = &app
            .world()
            .get::<MeshMaterial3d<CloudShadowMaterial>>(receiver)
            .unwrap()
            .0;
        let material = app
            .world()
            .resource::<Assets<CloudShadowMaterial>>()
            .get(handle)
            .unwrap();
        assert_eq!(material.extension.first, state.textures[0]);
        assert_eq!(material.extension.second, state.textures[1]);
    }
}
