//! The cell-projection render feature: draws every [`CellBatch`] into the HDR
//! view target after the opaque pass, exact per pixel (Röttger, "Volumetric
//! Methods for the Real-Time Display of Natural Gaseous Phenomena", 2004,
//! ch. 8-10; Röttger and Ertl, "Fast Volumetric Display of Natural Gaseous
//! Phenomena", 2003, §4), front to back with early ray termination (Krüger
//! and Westermann, "Acceleration Techniques for GPU-based Volume Rendering",
//! 2003, §4), at the resolution a camera's [`CellProjection`] asks for.
//!
//! Bevy 0.19 has no render-graph nodes: the passes are a system in the
//! [`Core3d`] schedule between the main pass and the early post process,
//! reading the scene depth. The render world is a row of small systems, as
//! in Bevy's volumetric fog, split by concern:
//!
//! - `resources`: extraction of the drawable batches, their GPU buffers
//!   (uploaded again only when the batch component changed), per-view
//!   uniforms and targets;
//! - `tables`: the pre-integration tables (64×64×128 colour, 64×64 pair
//!   table), cached by transfer function hash and built off the frame;
//! - `pipeline`: bind group layouts, shaders and the pipeline variants;
//! - `settings`: [`CellProjection`] and its extraction;
//! - `low_resolution`: the downsampled depth and the upsample;
//! - `merge`: overlapping batches, composited jointly per pixel; `queries`:
//!   the GPU time and the fragment counter;
//! - `node`: the draw system. Batches go front to back by the distance of
//!   their bounds' centre (batches that overlap merged per pixel), inside a batch in reverse buffer order (the
//!   batch's exact order is back to front), "under" the accumulation: a
//!   float target of colour `C` and transmittance `T`, cleared to (0, 1),
//!   takes each segment `(c, α)` as `C += T c`, `T *= 1 − α`. Between
//!   groups of cells a full-screen pass marks the pixels with
//!   `T < 1/512` in a stencil, which the later cells' fragments are tested
//!   against before they run. At a lower resolution the cells go into a
//!   smaller target first, the upsample fills and marks the pixels it can
//!   interpolate, and the full-resolution cells draw only the others. One
//!   full-screen pass (`cell_composite.wgsl`) then puts the result over the
//!   scene: `I = C + T scene`.
//!
//! The accumulation target is `Rgba32Float` where the device can blend it
//! (`FLOAT32_BLENDABLE`; lavapipe can), `Rgba16Float` otherwise: a ray may
//! cross hundreds of cells and every blend rounds. Emissive cells add
//! `T c` and leave `T`; MIP cells take the maximum over the cells,
//! unattenuated, and it is added to the scene.
//!
//! A view with fog layers ([`crate::fog_layers::ViewFogLayers`]) has the
//! fog over its scene already (`nebel_fog`'s pass runs before this one);
//! every segment is then conjugated by the fog in front of it, which makes
//! the composite exact for volumes inside and behind the fog up to the
//! splitting of the fog inside each segment (see `cell_projection.wgsl`).
//!
//! A whole grid (`nebel_lod::Cells::grid`) draws its box's back faces, each
//! fragment walking its ray through the voxels' Kuhn tetrahedra front to
//! back, the segments the grid's cells would give (Amanatides and Woo 1987).
//!
//! Each pixel of a cell is computed exactly under perspective: the fragment
//! shader intersects the view ray with the cell's planes, clips the segment to
//! the near plane and to the opaque depth and looks up the tables (see
//! `cell_projection.wgsl`). With no drawable batch, none of these systems does
//! any work: no table is built, no buffer written, no pass begun; the
//! [`CellProjectionStats`] counters and the `nebel/cell_projection/*`
//! diagnostics prove it.

mod low_resolution;
mod merge;
mod node;
mod pipeline;
mod queries;
mod resources;
mod settings;
mod tables;

pub use node::draw_over_view;
pub use queries::CountCellFragments;
pub use settings::{CellProjection, CellResolution};

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use bevy::asset::embedded_asset;
use bevy::core_pipeline::core_3d::prepare_core_3d_depth_textures;
use bevy::core_pipeline::schedule::{Core3d, Core3dSystems};
use bevy::diagnostic::{
    Diagnostic, DiagnosticMeasurement, DiagnosticPath, Diagnostics, DiagnosticsStore,
    RegisterDiagnostic,
};
use bevy::platform::time::Instant;
use bevy::prelude::*;
use bevy::render::extract_resource::ExtractResourcePlugin;
use bevy::render::render_resource::SpecializedRenderPipelines;
use bevy::render::renderer::{RenderGraph, RenderGraphSystems};
use bevy::render::{
    ExtractSchedule, GpuResourceAppExt, Render, RenderApp, RenderStartup, RenderSystems,
};

use crate::builds::HeavyBuilds;
use crate::cell_batch::CellBatch;
use low_resolution::{UpsampleUniforms, init_resample_pipelines};
use merge::init_merge_pipelines;
use pipeline::{CellCompositePipelines, CellProjectionPipeline, init_cell_projection_pipeline};
use queries::{CellQueries, collect_cell_queries, map_cell_queries, resolve_cell_queries};
use resources::{
    CellViewUniforms, ExtractedCellBatches, GpuCellBuffers, extract_cell_batches,
    make_depth_readable, prepare_cell_buffers, prepare_cell_views, resolve_light_shadows,
};
use tables::{GpuCellTables, extract_heavy_builds, prepare_cell_tables};

/// Draws [`CellBatch`]es (see the module docs).
#[derive(Default)]
pub struct CellProjectionPlugin;

/// The cell projection's systems in the `Core3d` schedule; passes that must
/// draw over the scene before the cells (the fog layers) run before
/// [`CellProjectionSystems::Draw`].
#[derive(SystemSet, Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum CellProjectionSystems {
    /// The cells into the accumulation target and over the scene.
    Draw,
}

impl CellProjectionPlugin {
    /// Render passes begun so far (one per view with batches, per frame).
    pub const PASSES: DiagnosticPath = DiagnosticPath::const_new("nebel/cell_projection/passes");
    /// Pre-integration tables built so far.
    pub const TABLES_BUILT: DiagnosticPath =
        DiagnosticPath::const_new("nebel/cell_projection/tables_built");
    /// Cell buffers uploaded so far.
    pub const UPLOADS: DiagnosticPath = DiagnosticPath::const_new("nebel/cell_projection/uploads");
    /// Cells drawn so far, summed over passes.
    pub const CELLS_DRAWN: DiagnosticPath =
        DiagnosticPath::const_new("nebel/cell_projection/cells_drawn");
    /// Batches drawn merged with others whose bounds they intersect, summed
    /// over passes.
    pub const MERGED_BATCHES: DiagnosticPath =
        DiagnosticPath::const_new("nebel/cell_projection/merged_batches");
    /// Per frame, the fragments the cell shader ran over the views' pixels
    /// at full resolution, while [`CountCellFragments`] is on.
    pub const FRAGMENTS_PER_PIXEL: DiagnosticPath =
        DiagnosticPath::const_new("nebel/cell_projection/fragments_per_pixel");
    /// Per frame, the GPU time from the first cell pass to the composite,
    /// milliseconds (where the device has timestamps).
    pub const GPU_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/cell_projection/gpu_ms");
}

/// Work counters of the cell-projection render system, shared by the main and
/// the render world (an `Arc`): the render world counts, the main world
/// publishes the totals as the [`CellProjectionPlugin`] diagnostics once any
/// work was done.
#[derive(Resource, Clone, Default, Debug, Reflect)]
#[reflect(opaque, Resource, Default, Debug, Clone)]
pub struct CellProjectionStats(Arc<CellProjectionCounters>);

/// The counters behind [`CellProjectionStats`]; each only grows.
#[derive(Default, Debug)]
pub struct CellProjectionCounters {
    /// Render passes begun (one per view that had batches, per frame).
    pub passes: AtomicU64,
    /// Pre-integration tables built.
    pub tables_built: AtomicU64,
    /// Cell buffers uploaded.
    pub uploads: AtomicU64,
    /// Cells drawn, summed over passes.
    pub cells_drawn: AtomicU64,
    /// Batches drawn merged, summed over passes.
    pub merged_batches: AtomicU64,
    /// Frames measured on the GPU whose figures the main world has not
    /// published yet.
    measured: Mutex<Vec<FrameMeasurement>>,
}

/// What the GPU counted of one frame's cell projection.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameMeasurement {
    /// Fragments the cell shader ran per pixel of the views; `None` unless
    /// [`CountCellFragments`] is on.
    pub fragments_per_pixel: Option<f64>,
    /// GPU time of the cell projection, milliseconds; `None` where the
    /// device has no timestamps.
    pub gpu_ms: Option<f64>,
}

impl CellProjectionStats {
    /// The counters.
    pub fn counters(&self) -> &CellProjectionCounters {
        &self.0
    }

    /// Queues a frame's GPU figures for the main world.
    fn record(&self, measurement: FrameMeasurement) {
        self.0
            .measured
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push(measurement);
    }

    /// The frames measured since the last call, oldest first.
    fn take_measured(&self) -> Vec<FrameMeasurement> {
        std::mem::take(
            &mut *self
                .0
                .measured
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
        )
    }
}

impl CellProjectionCounters {
    /// Current values: passes, tables built, uploads, cells drawn, batches
    /// drawn merged.
    pub fn snapshot(&self) -> [u64; 5] {
        [
            &self.passes,
            &self.tables_built,
            &self.uploads,
            &self.cells_drawn,
            &self.merged_batches,
        ]
        .map(|c| c.load(Ordering::Relaxed))
    }
}

impl Plugin for CellProjectionPlugin {
    fn build(&self, app: &mut App) {
        crate::fog_layers::load_fog_layers_library(app);
        crate::local_lights::load_local_lights_library(app);
        crate::light_shadows::load_light_shadows_library(app);
        crate::cloud_shadow_maps::load_cloud_shadow_maps_library(app);
        embedded_asset!(app, "cell_projection.wgsl");
        embedded_asset!(app, "cell_composite.wgsl");
        embedded_asset!(app, "cell_termination.wgsl");
        embedded_asset!(app, "low_resolution.wgsl");
        embedded_asset!(app, "cell_merge.wgsl");
        let stats = CellProjectionStats::default();
        app.insert_resource(stats.clone())
            .register_type::<CellBatch>()
            .register_type::<CellProjection>()
            .register_type::<CountCellFragments>()
            .init_resource::<CountCellFragments>()
            .add_plugins(ExtractResourcePlugin::<CountCellFragments>::default())
            .add_plugins(ExtractResourcePlugin::<crate::CloudShadowMaps>::default())
            .register_type::<CellResolution>()
            .register_type::<crate::CellBlend>()
            .register_type::<crate::CellSunlight>()
            .register_type::<CellProjectionStats>()
            .register_type::<crate::LodCamera>()
            .register_type::<HeavyBuilds>()
            .init_resource::<HeavyBuilds>()
            .register_type::<crate::CellScattering>()
            .add_systems(Last, (publish_counters, publish_gpu_measurements));
        for path in [
            Self::PASSES,
            Self::TABLES_BUILT,
            Self::UPLOADS,
            Self::CELLS_DRAWN,
            Self::MERGED_BATCHES,
            Self::FRAGMENTS_PER_PIXEL,
            Self::GPU_MS,
        ] {
            app.register_diagnostic(Diagnostic::new(path));
        }
        let Some(render_app) = app.get_sub_app_mut(RenderApp) else {
            return;
        };
        render_app
            .insert_resource(stats)
            .init_resource::<ExtractedCellBatches>()
            .init_gpu_resource::<GpuCellBuffers>()
            .init_gpu_resource::<GpuCellTables>()
            .init_gpu_resource::<SpecializedRenderPipelines<CellProjectionPipeline>>()
            .init_gpu_resource::<CellViewUniforms>()
            .init_gpu_resource::<CellCompositePipelines>()
            .init_gpu_resource::<CellQueries>()
            .init_resource::<UpsampleUniforms>()
            .init_resource::<HeavyBuilds>()
            .add_systems(
                RenderStartup,
                (
                    init_cell_projection_pipeline,
                    init_resample_pipelines,
                    init_merge_pipelines,
                ),
            )
            .add_systems(
                ExtractSchedule,
                (
                    extract_cell_batches,
                    settings::extract_cell_projection,
                    extract_heavy_builds,
                ),
            )
            .add_systems(
                Render,
                (
                    make_depth_readable
                        .in_set(RenderSystems::Prepare)
                        .before(prepare_core_3d_depth_textures),
                    (
                        resolve_light_shadows,
                        (
                            prepare_cell_buffers,
                            prepare_cell_tables,
                            prepare_cell_views,
                        ),
                    )
                        .chain()
                        .in_set(RenderSystems::PrepareResources),
                ),
            )
            .add_systems(
                RenderGraph,
                (
                    collect_cell_queries.in_set(RenderGraphSystems::Begin),
                    resolve_cell_queries
                        .after(RenderGraphSystems::Render)
                        .before(RenderGraphSystems::Submit),
                    map_cell_queries.in_set(RenderGraphSystems::Finish),
                ),
            )
            .add_systems(
                Core3d,
                node::draw_cell_batches
                    .in_set(CellProjectionSystems::Draw)
                    .after(Core3dSystems::MainPass)
                    .before(Core3dSystems::EarlyPostProcess),
            );
    }
}

/// Publishes each frame the GPU measured, straight into the store: two
/// frames may come back in one.
fn publish_gpu_measurements(stats: Res<CellProjectionStats>, mut store: ResMut<DiagnosticsStore>) {
    for frame in stats.take_measured() {
        for (path, value) in [
            (
                CellProjectionPlugin::FRAGMENTS_PER_PIXEL,
                frame.fragments_per_pixel,
            ),
            (CellProjectionPlugin::GPU_MS, frame.gpu_ms),
        ] {
            if let (Some(value), Some(diagnostic)) = (value, store.get_mut(&path)) {
                diagnostic.add_measurement(DiagnosticMeasurement {
                    time: Instant::now(),
                    value,
                });
            }
        }
    }
}

/// Publishes the render world's totals as diagnostics, from the first frame
/// that did any cell-projection work on.
fn publish_counters(stats: Res<CellProjectionStats>, mut diagnostics: Diagnostics) {
    let [passes, tables_built, uploads, cells_drawn, merged] = stats.counters().snapshot();
    if passes + tables_built + uploads == 0 {
        return;
    }
    for (path, value) in [
        (CellProjectionPlugin::PASSES, passes),
        (CellProjectionPlugin::TABLES_BUILT, tables_built),
        (CellProjectionPlugin::UPLOADS, uploads),
        (CellProjectionPlugin::CELLS_DRAWN, cells_drawn),
        (CellProjectionPlugin::MERGED_BATCHES, merged),
    ] {
        diagnostics.add_measurement(&path, || value as f64);
    }
}
