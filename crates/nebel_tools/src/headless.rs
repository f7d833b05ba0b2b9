//! Headless rendering: a scene to a PNG, with no window.
//!
//! [`render_headless`] builds a Bevy app without winit, lets the caller add
//! the scene (a [`SceneSetupPlugin`](crate::scene_setup::SceneSetupPlugin) of
//! a scene file, or an example's own systems), points every camera at one
//! sRGB image (a scene renders with one camera; several would overwrite each
//! other) through whatever adapter wgpu finds (lavapipe, the CPU Vulkan
//! driver, included), steps `output.frames` frames with time advancing by
//! exactly `1 / output.frame_rate` each, captures the last frame and writes
//! it. Before Bevy starts, [`probe_adapter`] asks wgpu for an adapter, so a
//! machine with none gets a one-line error ([`HeadlessError::NoAdapter`])
//! rather than Bevy's panic.
//!
//! Before the scene's first frame, frames with time standing still run until
//! every pipeline has compiled (shaders load asynchronously; pipelines compile
//! synchronously), so even a one-frame render shows the whole scene. The app
//! waits for the GPU after every frame, so frame times include the GPU's work.
//! Heavy builds (terrain quadtrees, cloud grids, light fields, octrees) make
//! their frame wait (`HeavyBuilds::Blocking`), so every frame shows the scene
//! at its own time, as the exact reference does; with
//! [`HeadlessOptions::background_builds`] they run in the background as in a
//! game, and the statistics show what a game's frames cost.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bevy::asset::RenderAssetUsages;
use bevy::camera::RenderTarget;
use bevy::diagnostic::{DiagnosticPath, DiagnosticsStore};
use bevy::log::{Level, LogPlugin};
use bevy::prelude::*;
use bevy::render::pipelined_rendering::PipelinedRenderingPlugin;
use bevy::render::render_resource::PipelineCache;
use bevy::render::render_resource::{
    Extent3d, PollType, TextureDimension, TextureFormat, TextureUsages,
};
use bevy::render::renderer::{RenderAdapterInfo, RenderDevice};
use bevy::render::settings::WgpuSettings;
use bevy::render::view::screenshot::{Screenshot, ScreenshotCaptured};
use bevy::render::{RenderApp, RenderPlugin};
use bevy::time::TimeUpdateStrategy;
use bevy::window::ExitCondition;
use bevy::winit::WinitPlugin;
use nebel_render::{CellProjectionPlugin, CountCellFragments, HeavyBuilds, NebelDiagnosticsPlugin};
use nebel_volume::VolumePlugin;
use thiserror::Error;

use crate::stats::{AdapterSummary, FrameTimes, RenderStats, TimeSummary};
use nebel::NebelPlugins;
use nebel_scene::OutputSettings;

/// Frames to keep running after the last scene frame while the read-back of
/// the captured image completes (it takes one or two on every driver seen).
/// Bevy finishes the read-back on the `AsyncComputeTaskPool`, where
/// background builds may be queued ahead of it, so the read-back frames wait
/// for their builds (`HeavyBuilds::Blocking`): the pool is free for it
/// within a frame, whatever the builds cost.
const READBACK_FRAMES: u32 = 8;

/// Most frames to wait, before the scene's first, for shaders to load and
/// pipelines to compile.
const WARM_UP_FRAMES: u32 = 30;

/// Whether a render of this process has set the global logger.
static LOGGER_SET: AtomicBool = AtomicBool::new(false);

/// How a headless render runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HeadlessOptions {
    /// A progress bar of the frames on stderr (drawn only on a terminal).
    /// Default false.
    pub progress: bool,
    /// Heavy builds in the background, as in a game (`HeavyBuilds::Background`):
    /// no frame waits for them, so a frame may show an older build. Default
    /// false: every frame waits for its builds.
    pub background_builds: bool,
    /// With `background_builds`, give an animated volume's keyframes and
    /// refinement steps at most this much CPU time per frame
    /// (`HeavyBuilds::Budgeted`). Default `None`: no budget.
    pub build_budget: Option<Duration>,
    /// Constrain the device to WebGL2-class limits
    /// (`wgpu::Limits::downlevel_webgl2_defaults`: no storage buffers or
    /// textures, no compute) and no optional features, to check what runs
    /// where Bevy's volumetric fog cannot. Default false.
    pub webgl2_limits: bool,
    /// Count the fragments the cell shader runs
    /// ([`CountCellFragments`]), which
    /// costs GPU time. Default false.
    pub count_fragments: bool,
}

/// The image every camera renders into.
#[derive(Resource, Clone)]
struct HeadlessTarget(Handle<Image>);

/// Why a headless render failed.
#[derive(Debug, Error)]
pub enum HeadlessError {
    /// wgpu found no adapter at all.
    #[error(
        "no graphics adapter found: install a Vulkan driver; without a GPU, the CPU driver lavapipe \
         comes in the Debian/Ubuntu package mesa-vulkan-drivers"
    )]
    NoAdapter,
    /// The frame was rendered but never came back from the GPU.
    #[error("the rendered image did not come back from the GPU within {READBACK_FRAMES} frames")]
    Readback,
    /// The captured image could not be converted or written.
    #[error("{}: cannot write image: {reason}", path.display())]
    Write {
        /// The output file.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
}

/// An adapter wgpu found, and the backends to ask Bevy for so it picks it.
#[derive(Clone, Debug)]
pub struct ProbedAdapter {
    /// The adapter.
    pub adapter: AdapterSummary,
    /// The backends it was found with.
    pub backends: wgpu::Backends,
}

/// Asks wgpu for an adapter: the backends in `WGPU_BACKEND` if set, otherwise
/// the primary ones (Vulkan, Metal, DX12) and, only when they have none, GL.
/// Trying GL last keeps its EGL probing (and its warnings) off machines with
/// a Vulkan driver.
pub fn probe_adapter() -> Result<ProbedAdapter, HeadlessError> {
    let candidates = match wgpu::Backends::from_env() {
        Some(backends) => vec![backends],
        None => vec![wgpu::Backends::PRIMARY, wgpu::Backends::SECONDARY],
    };
    for backends in candidates {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends,
            ..wgpu::InstanceDescriptor::new_without_display_handle_from_env()
        });
        let request = instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..default()
        });
        if let Ok(adapter) = bevy::tasks::block_on(request) {
            return Ok(ProbedAdapter {
                adapter: summary(&adapter.get_info()),
                backends,
            });
        }
    }
    Err(HeadlessError::NoAdapter)
}

fn summary(info: &wgpu::AdapterInfo) -> AdapterSummary {
    AdapterSummary {
        name: info.name.clone(),
        backend: format!("{:?}", info.backend),
        device_type: format!("{:?}", info.device_type),
    }
}

/// A headless app whose pipelines have compiled, at the scene's time 0,
/// its camera rendering into `target`.
pub(crate) struct HeadlessApp {
    /// The app.
    pub(crate) app: App,
    /// The image every camera renders into.
    pub(crate) target: Handle<Image>,
    /// Wall time of each frame before the scene's first.
    pub(crate) warm_up_times: Vec<Duration>,
}

impl HeadlessApp {
    /// Builds the app for `output` (see the module docs), its cameras
    /// rendering into an image of `format`, adds the scene and runs frames
    /// with time standing still until every pipeline has compiled; then time
    /// steps by `1 / output.frame_rate` from the second scene frame on
    /// ([`HeadlessApp::start_time`]).
    pub(crate) fn new(
        output: &OutputSettings,
        options: HeadlessOptions,
        format: TextureFormat,
        add_scene: impl FnOnce(&mut App),
    ) -> Result<Self, HeadlessError> {
        let probed = probe_adapter()?;
        let mut app = App::new();
        let plugins = DefaultPlugins
            .set(WindowPlugin {
                primary_window: None,
                exit_condition: ExitCondition::DontExit,
                ..default()
            })
            .set(RenderPlugin {
                render_creation: WgpuSettings {
                    backends: Some(probed.backends),
                    constrained_limits: options
                        .webgl2_limits
                        .then(wgpu::Limits::downlevel_webgl2_defaults),
                    disabled_features: options.webgl2_limits.then(wgpu::Features::all),
                    ..default()
                }
                .into(),
                synchronous_pipeline_compilation: true,
                ..default()
            })
            .set(LogPlugin {
                level: Level::WARN,
                filter: String::from("wgpu=error,naga=error"),
                ..default()
            })
            .disable::<WinitPlugin>()
            // Render each frame in the update that simulates it, so the
            // captured image is exactly the last scene frame.
            .disable::<PipelinedRenderingPlugin>();
        // The global logger can be set once per process: a second render in
        // the same process (`nebel bench-fog` runs two) keeps the first one's.
        if LOGGER_SET.swap(true, Ordering::Relaxed) {
            app.add_plugins(plugins.disable::<LogPlugin>());
        } else {
            app.add_plugins(plugins);
        }
        let target = render_target(&mut app, output.width, output.height, format);
        app.add_plugins(NebelPlugins)
            .insert_resource(HeadlessTarget(target.clone()))
            .insert_resource(TimeUpdateStrategy::ManualDuration(Duration::ZERO))
            .insert_resource(match (options.background_builds, options.build_budget) {
                (false, _) => HeavyBuilds::Blocking,
                (true, None) => HeavyBuilds::Background,
                (true, Some(budget)) => HeavyBuilds::Budgeted(budget),
            })
            .insert_resource(CountCellFragments(options.count_fragments))
            .add_systems(First, render_to_image);
        add_scene(&mut app);
        app.finish();
        app.cleanup();

        // Shaders load asynchronously: run frames with time standing still
        // until no pipeline waits any more, so the scene's first frame is
        // complete.
        let mut warm_up_times = Vec::new();
        for warm_up in 0..WARM_UP_FRAMES {
            let start = Instant::now();
            update_and_wait(&mut app);
            warm_up_times.push(start.elapsed());
            let cache = app.sub_app(RenderApp).world().resource::<PipelineCache>();
            if warm_up > 0 && cache.waiting_pipelines().next().is_none() {
                break;
            }
        }
        // The GPU's per-frame figures describe the scene's frames only.
        let mut store = app.world_mut().resource_mut::<DiagnosticsStore>();
        for path in [
            CellProjectionPlugin::FRAGMENTS_PER_PIXEL,
            CellProjectionPlugin::GPU_MS,
        ] {
            if let Some(diagnostic) = store.get_mut(&path) {
                diagnostic.clear_history();
            }
        }
        let frame_duration = Duration::from_secs_f64(1.0 / f64::from(output.frame_rate));
        // Virtual time clamps each step to `max_delta` (250 ms by default): a
        // scene at fewer than 4 frames per second would fall behind its path.
        let mut virtual_time = app.world_mut().resource_mut::<Time<Virtual>>();
        let max_delta = virtual_time.max_delta().max(frame_duration);
        virtual_time.set_max_delta(max_delta);
        Ok(Self {
            app,
            target,
            warm_up_times,
        })
    }

    /// Makes time step by `1 / output.frame_rate` per frame from now on
    /// (frame 0 is at time 0, like the reference).
    pub(crate) fn start_time(&mut self, output: &OutputSettings) {
        let frame_duration = Duration::from_secs_f64(1.0 / f64::from(output.frame_rate));
        self.app
            .insert_resource(TimeUpdateStrategy::ManualDuration(frame_duration));
    }

    /// Runs one frame and waits for the GPU.
    pub(crate) fn update(&mut self) {
        update_and_wait(&mut self.app);
    }

    /// What the app rendered with.
    pub(crate) fn adapter(&self) -> AdapterSummary {
        summary(&self.app.world().resource::<RenderAdapterInfo>().0)
    }
}

/// Renders the scene that `add_scene` adds to the app headless with the
/// size, frame count and frame rate of `output`, writes the last frame to
/// `out` (PNG, sRGB) and returns the statistics (see the module docs).
pub fn render_headless(
    output: &OutputSettings,
    options: HeadlessOptions,
    out: &Path,
    add_scene: impl FnOnce(&mut App),
) -> Result<RenderStats, HeadlessError> {
    let mut headless = HeadlessApp::new(output, options, TextureFormat::Rgba8UnormSrgb, add_scene)?;
    let captured: Arc<Mutex<Option<Image>>> = Arc::default();
    let mut frame_times = Vec::with_capacity(output.frames as usize);
    let mut nebel_times = Vec::with_capacity(output.frames as usize);
    let mut nebel_wall_times = Vec::with_capacity(output.frames as usize);
    let mut build_times = Vec::with_capacity(output.frames as usize);
    let mut budgeted_times = Vec::new();
    let bar = crate::progress::bar(options.progress, "frame", u64::from(output.frames));
    for frame in 0..output.frames {
        // Frame 0 is at time 0, like the reference; time steps from frame 1 on.
        if frame == 1 {
            headless.start_time(output);
        }
        if frame + 1 == output.frames {
            let slot = captured.clone();
            headless
                .app
                .world_mut()
                .spawn(Screenshot::image(headless.target.clone()))
                .observe(move |capture: On<ScreenshotCaptured>| {
                    *slot.lock().expect("capture slot") = Some(capture.image.clone());
                });
        }
        let start = Instant::now();
        headless.update();
        frame_times.push(start.elapsed());
        let diagnostics = headless.app.world().resource::<DiagnosticsStore>();
        let latest = |path: &DiagnosticPath| {
            diagnostics
                .get_measurement(path)
                .map(|ms| Duration::from_secs_f64(ms.value / 1e3))
        };
        nebel_times.extend(latest(&NebelDiagnosticsPlugin::SYSTEMS_CPU_MS));
        nebel_wall_times.extend(latest(&NebelDiagnosticsPlugin::SYSTEMS_MS));
        build_times.extend(latest(&NebelDiagnosticsPlugin::BUILDS_CPU_MS));
        // Measured every frame under a build budget only.
        budgeted_times.extend(latest(&VolumePlugin::BUDGETED_BUILD_MS));
        bar.inc(1);
    }
    bar.finish_and_clear();
    // The image is taken: drain the builds so the read-back gets the pool.
    headless.app.insert_resource(HeavyBuilds::Blocking);
    for _ in 0..READBACK_FRAMES {
        if captured.lock().expect("capture slot").is_some() {
            break;
        }
        headless.update();
    }
    let image = captured
        .lock()
        .expect("capture slot")
        .take()
        .ok_or(HeadlessError::Readback)?;
    write_png(image, out)?;

    let world = headless.app.world();
    Ok(RenderStats {
        adapter: headless.adapter(),
        frames_rendered: output.frames,
        width: output.width,
        height: output.height,
        frame_wall_ms: TimeSummary::of(&frame_times),
        warm_up_frames: headless.warm_up_times.len() as u32,
        warm_up_frame_wall_ms: TimeSummary::of(&headless.warm_up_times),
        nebel_systems_cpu_ms: TimeSummary::of(&nebel_times),
        nebel_systems_wall_ms: TimeSummary::of(&nebel_wall_times),
        nebel_builds_cpu_ms: TimeSummary::of(&build_times),
        budgeted_builds_ms: (!budgeted_times.is_empty()).then(|| TimeSummary::of(&budgeted_times)),
        per_frame_ms: FrameTimes::of(
            &frame_times,
            &nebel_times,
            &nebel_wall_times,
            &budgeted_times,
        ),
        effects: effect_counters(world.resource::<DiagnosticsStore>()),
    })
}

/// The effects' diagnostics (`nebel/<effect>/<counter>`) that measured
/// anything, by effect: the latest value of each, and for timings (`_ms`)
/// and per-pixel figures (`_per_pixel`) also the mean and maximum over the
/// diagnostic's history (`_ms_mean`, `_ms_max`, `_per_pixel_mean`, ...).
pub(crate) fn effect_counters(store: &DiagnosticsStore) -> BTreeMap<String, BTreeMap<String, f64>> {
    let mut effects: BTreeMap<String, BTreeMap<String, f64>> = BTreeMap::new();
    for diagnostic in store.iter() {
        let mut components = diagnostic.path().components();
        let (Some("nebel"), Some(effect), Some(counter), None) = (
            components.next(),
            components.next(),
            components.next(),
            components.next(),
        ) else {
            continue;
        };
        let Some(value) = diagnostic.value() else {
            continue;
        };
        let group = effects.entry(effect.to_owned()).or_default();
        group.insert(counter.to_owned(), value);
        if counter.ends_with("_ms") || counter.ends_with("_per_pixel") {
            let values = || diagnostic.values().copied();
            let max = values().fold(f64::NEG_INFINITY, f64::max);
            group.insert(
                format!("{counter}_mean"),
                diagnostic.average().unwrap_or(value),
            );
            group.insert(format!("{counter}_max"), max);
        }
    }
    effects
}

/// Points every new camera at the headless image.
fn render_to_image(
    mut commands: Commands,
    target: Res<HeadlessTarget>,
    cameras: Query<Entity, Added<Camera>>,
) {
    for camera in &cameras {
        commands
            .entity(camera)
            .insert(RenderTarget::Image(target.0.clone().into()));
    }
}

fn render_target(app: &mut App, width: u32, height: u32, format: TextureFormat) -> Handle<Image> {
    let mut image = Image::new_uninit(
        Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        },
        TextureDimension::D2,
        format,
        RenderAssetUsages::RENDER_WORLD,
    );
    image.texture_descriptor.usage |= TextureUsages::RENDER_ATTACHMENT;
    app.world_mut().resource_mut::<Assets<Image>>().add(image)
}

fn update_and_wait(app: &mut App) {
    app.update();
    // A lost device shows in the next frame's errors; a poll error here only
    // means there was nothing to wait for.
    let _ = app
        .world()
        .resource::<RenderDevice>()
        .wgpu_device()
        .poll(PollType::Wait {
            submission_index: None,
            timeout: None,
        });
}

fn write_png(image: Image, out: &Path) -> Result<(), HeadlessError> {
    let write_error = |reason: String| HeadlessError::Write {
        path: out.to_owned(),
        reason,
    };
    let pixels = image
        .try_into_dynamic()
        .map_err(|error| write_error(error.to_string()))?;
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|error| write_error(error.to_string()))?;
    }
    pixels
        .to_rgb8()
        .save_with_format(out, image::ImageFormat::Png)
        .map_err(|error| write_error(error.to_string()))
}
