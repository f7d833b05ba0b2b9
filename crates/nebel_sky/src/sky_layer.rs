//! What the aurora and the cloud layer share: one skeleton of systems over
//! the [`SkyLayer`] trait that each implements. For each visible layer whose
//! cells are out of date (the layer's key, the projection, the placement,
//! the sun for a sunlit layer or a setting changed, the eye moved more than
//! a quarter of the layer's grid spacing or the camera turned more than 3°,
//! as for the terrain: `nebel_lod::quadtree::TerrainRefiner`, whose docs
//! bound the morph's step this allows), one build at a time
//! runs on Bevy's `AsyncComputeTaskPool`: the layer between two surfaces
//! when its key changed ([`SkyLayer::layer_key`]; a map's values are read
//! on the frame's thread first), then its cells for the eye
//! ([`nebel_lod::SurfaceLayer::cells`]). The layer draws its last
//! `CellBatch` until the build is done and takes the new one in the first
//! frame after (the same frame under `HeavyBuilds::Blocking`). A sorted
//! layer's cells are then ordered for the eye of an earlier frame: prisms on
//! a triangulation, as the ground fog's, whose order stays a visibility
//! order while the eye keeps to the same side of every face's plane (the
//! ground-fog tests of `nebel_lod` hold orders up to a grid spacing old to
//! half an 8-bit step). The cells are culled by the camera's side planes
//! widened by what the view may change until the next cells land (the
//! thresholds, and twice what it changed during the last build). A
//! hidden or dark layer (no density or brightness, a transparent transfer
//! function) has no batch and costs a few comparisons per frame; removing
//! the component removes its batch and state.

use std::sync::Arc;
use std::time::Instant;

use bevy::camera::CameraUpdateSystems;
use bevy::camera::visibility::VisibilitySystems;
use bevy::diagnostic::{DiagnosticPath, Diagnostics};
use bevy::math::DVec3;
use bevy::prelude::*;
use nebel_core::local_light::LightResponse;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferError, TransferFunction};
use nebel_lod::quadtree::TerrainView;
use nebel_lod::{
    CellOrder, Cells, FogProfile, GpuCell, LayerStats, LayerView, LodSettings, PrismScalar,
    SurfaceLayer, SurfaceLayerError, TerrainMap, TerrainMesh,
};
use nebel_render::camera::to_double_affine;
use nebel_render::{
    CellBatch, EffectStatus, EffectiveQuality, GrayscaleMap, GrayscaleMapPlugin, HeavyBuild,
    HeavyBuilds, LodCameras, NebelSystems, cpu_timed, register_diagnostics,
};

use crate::error::SkyLayerError;

/// A transfer function with ρ times a factor, kept while neither changes.
#[derive(Default)]
pub(crate) struct ScaledTransfer(Option<(u64, u32, Arc<TransferFunction>)>);

impl ScaledTransfer {
    /// `transfer` with ρ times `factor`, from the cache when both are the
    /// same as last time.
    pub(crate) fn get(
        &mut self,
        transfer: &TransferFunction,
        factor: f32,
    ) -> Result<Arc<TransferFunction>, TransferError> {
        let key = (transfer.content_hash(), factor.to_bits());
        if let Some((hash, bits, scaled)) = &self.0
            && (*hash, *bits) == key
        {
            return Ok(scaled.clone());
        }
        let scaled = Arc::new(transfer.scale_density(factor)?);
        self.0 = Some((key.0, key.1, scaled.clone()));
        Ok(scaled)
    }
}

/// A map of the sky layer `layer` (its name) resampled onto `side²` points
/// (bilinear, corner to corner), `None` while it loads.
pub(crate) fn map_values(
    layer: &'static str,
    handle: &Handle<GrayscaleMap>,
    side: usize,
    maps: &Assets<GrayscaleMap>,
    asset_server: &AssetServer,
) -> Result<Option<Vec<f32>>, SkyLayerError> {
    if let Some((path, error)) = GrayscaleMap::load_failure(handle, asset_server) {
        return Err(SkyLayerError::MapNotLoaded { layer, path, error });
    }
    let Some(map) = maps.get(handle) else {
        return Ok(None);
    };
    let dims = [map.dims.x as usize, map.dims.y as usize];
    let values = TerrainMap::resample(&map.values, dims, side)
        .map_err(|error| SkyLayerError::from(SurfaceLayerError::from(error)))?;
    Ok(Some(values.values().to_vec()))
}

/// An effect drawn as a layer between two surfaces: what the aurora and the
/// cloud layer tell the systems they share (see the module docs).
pub trait SkyLayer: Component + Sized {
    /// What its layer is built from; a new key builds the layer again.
    type LayerKey: Clone + PartialEq + Send + Sync + 'static;
    /// What a build of its layer reads besides the key: the values of its
    /// maps, taken from the assets on the frame's thread.
    type LayerInput: Send + 'static;
    /// Its name in the log.
    const NAME: &'static str;
    /// Its diagnostics: layers drawn, their tetrahedra, and the time of a
    /// frame's work.
    const DRAWN: DiagnosticPath;
    /// See [`SkyLayer::DRAWN`].
    const TETRAHEDRA: DiagnosticPath;
    /// See [`SkyLayer::DRAWN`].
    const UPDATE_MS: DiagnosticPath;
    /// How its segments combine.
    const MODE: OpticalMode;
    /// Whether the sun's direction changes its cells.
    const SUNLIT: bool;

    /// Checks the settings its builders do not check themselves.
    fn validate(&self) -> Result<(), SkyLayerError>;
    /// Whether it draws nothing whatever the view: no density or brightness,
    /// a transparent transfer function.
    fn is_dark(&self) -> bool;
    /// What its layer is built from at `seconds` of virtual time.
    fn layer_key(&self, seconds: f64, maps: &Assets<GrayscaleMap>) -> Self::LayerKey;
    /// What a build of the layer for `key` reads, `None` while a map loads.
    fn layer_input(
        key: &Self::LayerKey,
        maps: &Assets<GrayscaleMap>,
        asset_server: &AssetServer,
    ) -> Result<Option<Self::LayerInput>, SkyLayerError>;
    /// Its layer for `key` (on a worker).
    fn build_layer(
        key: &Self::LayerKey,
        input: Self::LayerInput,
    ) -> Result<SurfaceLayer, SkyLayerError>;
    /// Its transfer function and the factor of its ρ.
    fn transfer(&self) -> (&TransferFunction, f32);
    /// The quadtree's accuracy `c` before the quality's scale.
    fn accuracy(&self) -> f32;
    /// How a sorted layer scatters the point and spot lights that reach it.
    fn light_response(&self) -> LightResponse {
        LightResponse::default()
    }
    /// Its prisms' levels, scalar and order, with `sun` the direction toward
    /// the sun in the layer's frame.
    fn drawing(&self, key: &Self::LayerKey, sun: DVec3) -> (FogProfile, PrismScalar, CellOrder);
}

/// Statistics of a sky layer ([`Aurora`](crate::Aurora) or
/// [`CloudLayer`](crate::CloudLayer)), updated by its plugin. An entity holds
/// one sky layer, as it holds one status.
#[derive(Component, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct SkyLayerStats {
    /// Triangles of the layer's refined quadtree in the last update.
    pub triangles: u32,
    /// Of them, those under the medium (curtains or clouds), each a column
    /// of prisms.
    pub prisms: u32,
    /// Tetrahedra drawn.
    pub tetrahedra: u32,
    /// Updates of the cells so far.
    pub updates: u64,
    /// Time of the last layer and quadtree build, ms (an animated aurora's
    /// footprint builds them again every time).
    pub build_ms: f32,
    /// Time of the last build on a worker (layer and quadtree when built,
    /// refinement and prisms), ms.
    pub update_ms: f32,
}

impl SkyLayerStats {
    /// Records an update: its counts, the layer's build time if it was
    /// built, and the whole build's time.
    fn record(&mut self, counts: LayerStats, build_ms: Option<f32>, update_ms: f32) {
        *self = Self {
            triangles: counts.triangles as u32,
            prisms: counts.prisms as u32,
            tetrahedra: counts.tetrahedra as u32,
            updates: self.updates + 1,
            build_ms: build_ms.unwrap_or(self.build_ms),
            update_ms,
        };
    }
}

/// Adds the systems of the layer `T` (in [`PostUpdate`], after the camera's
/// transform) and its diagnostics, and the grayscale maps it reads.
pub(crate) fn add_sky_layer<T: SkyLayer>(app: &mut App) {
    GrayscaleMapPlugin::add_once(app);
    app.init_resource::<HeavyBuilds>().add_systems(
        PostUpdate,
        (
            cpu_timed(remove_sky_layers::<T>),
            cpu_timed(update_sky_layers::<T>),
            cpu_timed(measure_sky_layers::<T>),
        )
            .chain()
            .in_set(NebelSystems)
            .after(TransformSystems::Propagate)
            .after(CameraUpdateSystems)
            .after(VisibilitySystems::VisibilityPropagate),
    );
    register_diagnostics(
        app,
        &[(T::DRAWN, ""), (T::TETRAHEDRA, ""), (T::UPDATE_MS, " ms")],
    );
}

/// How far the eye may move, in grid spacings of the layer, before its
/// cells are refined again (module docs).
const UPDATE_DISTANCE: f64 = 0.25;
/// How far the camera may turn, radians (3°), before the cells are refined
/// again.
const VIEW_MARGIN: f64 = std::f64::consts::PI / 60.0;

/// What a layer's cells were built from.
struct CellsKey<T: SkyLayer> {
    /// The layer they were refined from.
    layer: T::LayerKey,
    /// The camera they were refined for, seen from the layer.
    view: TerrainView,
    /// The layer's placement.
    transform: GlobalTransform,
    /// Toward the sun, world space, for a sunlit layer.
    sun: Option<[u32; 3]>,
    /// The refinement's accuracy (bits).
    accuracy: u32,
}

impl<T: SkyLayer> CellsKey<T> {
    /// Whether cells built for `self` serve `other`: the same inputs and
    /// projection, the eye moved by at most `distance` (the layer's units)
    /// and the camera turned by at most `angle` (radians).
    fn serves(&self, other: &Self, distance: f64, angle: f64) -> bool {
        let (moved, turned) = other.view.change_since(&self.view);
        self.layer == other.layer
            && self.transform == other.transform
            && self.sun == other.sun
            && self.accuracy == other.accuracy
            && self.view.clip_from_view == other.view.clip_from_view
            && moved <= distance
            && turned <= angle
    }
}

/// What a build on a worker hands back.
struct Built {
    /// The layer, when the build made a new one.
    layer: Option<Arc<SurfaceLayer>>,
    cells: Vec<GpuCell>,
    counts: LayerStats,
    /// The refinement's mesh, lent to the build.
    mesh: TerrainMesh,
    transfer: Arc<TransferFunction>,
    build_ms: Option<f32>,
    update_ms: f32,
}

/// A build in flight and what it is built from.
type Building<T> = (CellsKey<T>, HeavyBuild<Result<Built, SkyLayerError>>);

/// A layer's quadtree, buffers and caches.
#[derive(Component)]
pub struct SkyLayerState<T: SkyLayer> {
    /// The layer and what it was built from.
    layer: Option<(T::LayerKey, Arc<SurfaceLayer>)>,
    /// What the cells drawn (or the last failure) came from.
    cells: Option<CellsKey<T>>,
    /// The component changed since the last build started.
    dirty: bool,
    building: Option<Building<T>>,
    transfer: ScaledTransfer,
    /// The refinement's mesh, reused; `None` while a build holds it.
    mesh: Option<TerrainMesh>,
    /// Twice how far the eye moved (the layer's units) and the camera
    /// turned (radians) while the last build ran: how much more the next
    /// one's culling keeps.
    latency: (f64, f64),
}

impl<T: SkyLayer> Default for SkyLayerState<T> {
    fn default() -> Self {
        Self {
            layer: None,
            cells: None,
            dirty: true,
            building: None,
            transfer: ScaledTransfer::default(),
            mesh: Some(TerrainMesh::default()),
            latency: (0.0, 0.0),
        }
    }
}

/// A layer component removed from an entity that lives on: its batch and
/// state go with it.
fn remove_sky_layers<T: SkyLayer>(mut commands: Commands, mut removed: RemovedComponents<T>) {
    for entity in removed.read() {
        if let Ok(mut entity) = commands.get_entity(entity) {
            entity.remove::<(
                CellBatch,
                SkyLayerState<T>,
                EffectStatus<SkyLayerError>,
                SkyLayerStats,
            )>();
        }
    }
}

/// Starts the builds of every visible layer whose cells are out of date and
/// takes the finished ones (see the module docs).
#[expect(clippy::too_many_arguments, reason = "a Bevy system's parameters")]
fn update_sky_layers<T: SkyLayer>(
    mut commands: Commands,
    cameras: LodCameras,
    time: Res<Time<Virtual>>,
    mode: Res<HeavyBuilds>,
    suns: Query<&GlobalTransform, With<DirectionalLight>>,
    mut layers: Query<(
        Entity,
        Ref<T>,
        Ref<GlobalTransform>,
        &InheritedVisibility,
        Has<CellBatch>,
        &mut SkyLayerState<T>,
        &mut EffectStatus<SkyLayerError>,
        &mut SkyLayerStats,
    )>,
    maps: Res<Assets<GrayscaleMap>>,
    asset_server: Res<AssetServer>,
    quality: Option<Res<EffectiveQuality>>,
    mut diagnostics: Diagnostics,
) {
    if layers.is_empty() {
        return;
    }
    let Some(camera) = cameras.view() else {
        return;
    };
    let accuracy_scale = quality
        .as_ref()
        .map_or(1.0, |quality| quality.terrain_accuracy_scale());
    // Toward the sun, world space: straight up without a directional light.
    let toward_sun = suns
        .iter()
        .next()
        .map_or(Vec3::Y, |sun| -sun.forward().as_vec3());
    let mut frame_ms = None;
    for (entity, layer, transform, visibility, has_batch, mut state, mut status, mut stats) in
        &mut layers
    {
        let state = &mut *state;
        state.dirty |= layer.is_changed();
        let clear = |commands: &mut Commands, state: &mut SkyLayerState<T>| {
            if has_batch {
                commands.entity(entity).remove::<CellBatch>();
            }
            state.cells = None;
            state.building = None;
        };
        if let Err(error) = layer.validate() {
            clear(&mut commands, state);
            EffectStatus::fail(status.reborrow(), T::NAME, entity, error);
            continue;
        }
        if !visibility.get() || layer.is_dark() {
            clear(&mut commands, state);
            status.set_if_neq(EffectStatus::Ready);
            continue;
        }
        let world_from_field = to_double_affine(&transform);
        let view = camera.seen_from(world_from_field);
        // A quarter of the layer's grid spacing, in its units.
        let distance = state.layer.as_ref().map_or(0.0, |(_, built)| {
            UPDATE_DISTANCE * built.hierarchy().field().spacing().max_element()
        });
        if state.building.is_none() {
            let layer_key = layer.layer_key(time.elapsed_secs_f64(), &maps);
            let accuracy = (f64::from(layer.accuracy()) * accuracy_scale) as f32;
            let key = CellsKey {
                layer: layer_key,
                view,
                transform: *transform,
                sun: T::SUNLIT.then(|| toward_sun.to_array().map(f32::to_bits)),
                accuracy: accuracy.to_bits(),
            };
            // Drawn already, or failed for this layer: not again until
            // something changes.
            let failed = matches!(*status, EffectStatus::Failed(_))
                && state.layer.is_none()
                && state
                    .cells
                    .as_ref()
                    .is_some_and(|cells| cells.layer == key.layer);
            let drawn = state
                .cells
                .as_ref()
                .is_some_and(|cells| cells.serves(&key, distance, VIEW_MARGIN));
            if !state.dirty && (failed || drawn) {
                continue;
            }
            // The layer, when its key changed: its maps' values now, the
            // build on the worker.
            let new_layer = if state.layer.as_ref().map(|(built, _)| built) == Some(&key.layer) {
                None
            } else {
                match T::layer_input(&key.layer, &maps, &asset_server) {
                    Ok(Some(input)) => Some(input),
                    Ok(None) => {
                        status.set_if_neq(EffectStatus::Pending);
                        continue;
                    }
                    Err(error) => {
                        state.layer = None;
                        clear(&mut commands, state);
                        // Not again until something changes.
                        state.cells = Some(key);
                        state.dirty = false;
                        EffectStatus::fail(status.reborrow(), T::NAME, entity, error);
                        continue;
                    }
                }
            };
            let (transfer_function, factor) = layer.transfer();
            let transfer = match state.transfer.get(transfer_function, factor) {
                Ok(transfer) => transfer,
                Err(error) => {
                    EffectStatus::fail(status.reborrow(), T::NAME, entity, error.into());
                    continue;
                }
            };
            let sun = world_from_field
                .inverse()
                .transform_vector3(toward_sun.as_dvec3())
                .normalize_or(DVec3::Y);
            let (profile, scalar, order) = layer.drawing(&key.layer, sun);
            // Widened by what the view may change until the next cells land
            // (module docs); a degenerate projection culls nothing.
            let frustum =
                view.culling_frustum(distance + state.latency.0, VIEW_MARGIN + state.latency.1);
            let eye = camera.eye;
            let layer_key = key.layer.clone();
            let current = state.layer.as_ref().map(|(_, built)| built.clone());
            let mut mesh = state.mesh.take().unwrap_or_default();
            let build = HeavyBuild::spawn(move || {
                let started = Instant::now();
                let (layer, build_ms) = match new_layer {
                    Some(input) => {
                        let built = Arc::new(T::build_layer(&layer_key, input)?);
                        (Some(built), Some(started.elapsed().as_secs_f32() * 1e3))
                    }
                    None => (None, None),
                };
                let surface = layer
                    .as_ref()
                    .or(current.as_ref())
                    .expect("a layer built now or before");
                let view = LayerView {
                    world_from_field,
                    eye,
                    frustum: frustum.as_ref(),
                    lod: LodSettings {
                        accuracy,
                        ..LodSettings::default()
                    },
                    order,
                    profile: &profile,
                    scalar,
                };
                let mut cells = Vec::new();
                let counts = surface.cells(&view, &mut mesh, &mut cells)?;
                Ok(Built {
                    layer,
                    cells,
                    counts,
                    mesh,
                    transfer,
                    build_ms,
                    update_ms: started.elapsed().as_secs_f32() * 1e3,
                })
            });
            state.building = Some((key, build));
            state.dirty = false;
        }
        let Some(built) = state
            .building
            .as_mut()
            .and_then(|(_, build)| build.poll(*mode))
        else {
            continue;
        };
        let (key, _) = state.building.take().expect("a build was polled");
        let (moved, turned) = view.change_since(&key.view);
        state.latency = (2.0 * moved, 2.0 * turned);
        let built = match built {
            Ok(built) => built,
            Err(error) => {
                state.layer = None;
                clear(&mut commands, state);
                // Not again until something changes.
                state.cells = Some(key);
                EffectStatus::fail(status.reborrow(), T::NAME, entity, error);
                continue;
            }
        };
        if let Some(layer) = built.layer {
            state.layer = Some((key.layer.clone(), layer));
        }
        state.mesh = Some(built.mesh);
        state.cells = Some(key);
        status.set_if_neq(EffectStatus::Ready);
        if built.cells.is_empty() {
            if has_batch {
                commands.entity(entity).remove::<CellBatch>();
            }
        } else {
            commands.entity(entity).insert(CellBatch {
                light_response: layer.light_response(),
                ..CellBatch::new(
                    Arc::new(Cells::with_bounds(built.cells)),
                    built.transfer,
                    T::MODE,
                )
            });
        }
        stats.record(built.counts, built.build_ms, built.update_ms);
        *frame_ms.get_or_insert(0.0) += f64::from(built.update_ms);
    }
    if let Some(ms) = frame_ms {
        diagnostics.add_measurement(&T::UPDATE_MS, || ms);
    }
}

/// Measures the layers' totals; nothing in a world without one.
fn measure_sky_layers<T: SkyLayer>(
    layers: Query<(&SkyLayerStats, Has<CellBatch>), With<T>>,
    mut diagnostics: Diagnostics,
) {
    if layers.is_empty() {
        return;
    }
    let (drawn, tetrahedra) = layers
        .iter()
        .filter(|(_, has_batch)| *has_batch)
        .fold((0.0, 0.0), |(drawn, tetrahedra), (stats, _)| {
            (drawn + 1.0, tetrahedra + f64::from(stats.tetrahedra))
        });
    diagnostics.add_measurement(&T::DRAWN, || drawn);
    diagnostics.add_measurement(&T::TETRAHEDRA, || tetrahedra);
}
