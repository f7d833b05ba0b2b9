//! The `nebel` command line: render scene files headless, integrate them
//! exactly on the CPU, compare images, and benchmark against Bevy's fog and
//! along the octree's accuracy. `nebel --help` and `nebel COMMAND --help`
//! describe every command and option; errors are one line on stderr and
//! exit status 1.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::{Args, Parser, Subcommand};
use nebel_core::optics::OpticalMode;
use nebel_reference::image_metrics::{
    difference_image, largest_difference_step, load_png_linear, save_png,
};
use nebel_scene::reference::{reference_image, save_reference};
use nebel_scene::{
    BuiltVolume, CellProjectionDescription, CellResolutionDescription, LightDescription,
    QualityDescription, SceneDescription, SceneError, SceneField,
};
use nebel_tools::error::CommandError;
use nebel_tools::fog_comparison::{self, BevyFog};
use nebel_tools::fog_layer_peers::run_fog_layer_peers;
use nebel_tools::headless::HeadlessOptions;
use nebel_tools::lod_sweep::{SweepSetting, run_lod_sweep};
use nebel_tools::progress::reference_bar;
use nebel_tools::reference::scene_reference;
use nebel_tools::scene_setup::{BevyPeer, SceneSetupPlugin};
use nebel_tools::soak::{soak, write_report};
use nebel_tools::stats::RenderStats;

/// Factor on the absolute error in `compare --diff` images.
const DIFF_SCALE: f32 = 10.0;

/// nebel's tools: headless rendering, the exact CPU reference, image
/// comparison and benchmarks of scene files.
#[derive(Parser)]
#[command(name = "nebel", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene headless (through whatever adapter wgpu finds, the CPU
    /// driver lavapipe included) and write its last frame.
    Render {
        #[command(flatten)]
        scene: SceneArgs,
        /// The PNG to write (sRGB).
        #[arg(long)]
        out: PathBuf,
        /// Also write the statistics as JSON: adapter, frame times, nebel's
        /// CPU time per frame, and the diagnostics of each effect present.
        #[arg(long)]
        stats: Option<PathBuf>,
        /// Run heavy builds (terrain quadtrees, cloud grids, light fields,
        /// octrees) in the background as a game does, instead of making each
        /// frame wait for them; the statistics then show a game's frame
        /// times.
        #[arg(long)]
        background_builds: bool,
        /// With `--background-builds`, give an animated volume's keyframes
        /// and refinement steps at most this many milliseconds of CPU time
        /// per frame, on nebel's worker threads (a game's fixed per-frame
        /// slice); the statistics then list their work per frame.
        #[arg(long, value_name = "MS", requires = "background_builds", value_parser = parse_budget)]
        build_budget_ms: Option<Duration>,
        /// Constrain the device to WebGL2-class limits (no storage buffers,
        /// no compute) and no optional features, and turn MSAA off (WebGL2
        /// cannot read multisampled depth); with `WGPU_BACKEND=gl`, a check
        /// of what runs on downlevel devices (fog layers do; the cell
        /// projection needs storage buffers).
        #[arg(long)]
        webgl2_limits: bool,
        /// Count the fragments the cell shader runs, for the statistics'
        /// `fragments_per_pixel` (a debug counter that costs GPU time: take
        /// timings without it).
        #[arg(long)]
        count_fragments: bool,
    },
    /// Integrate the scene's volumes exactly on the CPU (f64, adaptive, all
    /// cores) from the camera of the last frame, cut at its meshes and
    /// terrain, which are drawn black.
    Reference {
        #[command(flatten)]
        scene: SceneArgs,
        /// The PNG to write (sRGB).
        #[arg(long)]
        out: PathBuf,
    },
    /// Print RMSE, maximum absolute error and PSNR over linear RGB of two
    /// PNGs of the same size.
    Compare {
        /// The first image.
        a: PathBuf,
        /// The second image.
        b: PathBuf,
        /// Also write |A − B| · 10 per channel as a PNG.
        #[arg(long)]
        diff: Option<PathBuf>,
        /// Also print the largest change of A − B between adjacent pixels
        /// (the sharpest seam A has that B has not).
        #[arg(long)]
        steps: bool,
    },
    /// Render the scene's one grid volume with nebel (through the scene's
    /// `lod` when it has one) and with Bevy's `FogVolume` under the same
    /// optics, score both against the exact reference, write
    /// `DIR/fog_comparison.csv` and the images.
    BenchFog(PeerArgs),
    /// Render the scene's fog layers with nebel, with Bevy's `DistanceFog`
    /// (exponential and atmospheric falloff, fitted) and with Bevy's
    /// `FogVolume` covering them, score each against the exact reference,
    /// write `DIR/fog_layer_peers.csv`, a plot and the images.
    BenchFogLayers(PeerArgs),
    /// Fly the scene headless for many frames along a seeded random path
    /// through everything it draws as cells, check every frame's cell
    /// batches and its read-back HDR image for NaN and infinities, and write
    /// a JSON report (the counts, frame times, resident memory at frames 1,
    /// 1000, 10000 and the last); fails when anything was non-finite.
    Soak {
        /// The scene file (RON); its camera's start is the path's.
        scene: PathBuf,
        /// Frames to fly.
        #[arg(long, default_value_t = 10_000)]
        frames: u32,
        /// Seeds the path.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// The JSON report to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// Sweep the octree criteria of the scene's one grid volume (the
    /// distance criterion's accuracy c and the screen error's tolerance; in
    /// a scene without volumes, the accuracy c of its terrain with ground
    /// fog), score each image against full resolution and the exact
    /// reference, write `DIR/lod_sweep.csv` and a plot of frame time against
    /// error (`DIR/lod_sweep.svg`).
    BenchLod {
        #[command(flatten)]
        scene: SceneArgs,
        /// The folder to write into.
        #[arg(long)]
        out: PathBuf,
        /// The accuracies c to sweep, comma-separated.
        #[arg(long, value_delimiter = ',', default_values_t = [0.0, 4.0, 16.0, 64.0, 256.0])]
        accuracies: Vec<f64>,
        /// The screen error's tolerances to sweep, comma-separated: a
        /// volume's image error, or a terrain's pixel error.
        #[arg(long, value_delimiter = ',', default_values_t = [0.3, 0.1, 0.03, 0.01, 0.003])]
        image_errors: Vec<f64>,
        /// Score against the image at this c instead of full resolution, for
        /// a volume too large to draw at full resolution (the exact
        /// reference is skipped).
        #[arg(long)]
        comparison_accuracy: Option<f64>,
    },
}

/// What the comparisons with Bevy's fogs take.
#[derive(Args)]
struct PeerArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// The folder to write into.
    #[arg(long)]
    out: PathBuf,
    /// Samples per ray of Bevy's `FogVolume`.
    #[arg(long, default_value_t = 64)]
    steps: u32,
}

/// A scene file and the output settings a command may override.
#[derive(Args)]
struct SceneArgs {
    /// The scene file (RON).
    scene: PathBuf,
    /// Frames to run instead of the scene's `output.frames`.
    #[arg(long)]
    frames: Option<u32>,
    /// Simulated frames per second instead of the scene's
    /// `output.frame_rate` (60 follows a game's frames along a path).
    #[arg(long)]
    frame_rate: Option<f32>,
    /// Image size instead of the scene's, as `WIDTHxHEIGHT`.
    #[arg(long, value_parser = parse_size)]
    size: Option<(u32, u32)>,
    /// The quality preset instead of the scene's: low, medium or high.
    #[arg(long, value_parser = parse_quality)]
    quality: Option<QualityDescription>,
    /// Hold this frame time (ms) by lowering the detail (the automatic
    /// quality mode), instead of the scene's `auto_quality_ms`.
    #[arg(long)]
    auto_quality: Option<f32>,
    /// Draw cells at this resolution (full, half or quarter of the view's,
    /// mixed with full resolution where the lower one would be off) instead
    /// of the scene's.
    #[arg(long, value_parser = parse_resolution)]
    cell_resolution: Option<CellResolutionDescription>,
    /// Below full resolution, the largest interpolation error (linear RGB
    /// and transmittance) a pixel may take from the lower resolution,
    /// instead of the scene's.
    #[arg(long, value_parser = parse_tolerance)]
    upsample_tolerance: Option<f32>,
    /// Draw cells by the exact method of the papers: full resolution, grids
    /// as projected cells, every ray to its end (no early termination).
    #[arg(long, conflicts_with_all = ["cell_resolution", "upsample_tolerance"])]
    exact: bool,
    /// Draw grids at full resolution as their tetrahedra projected in
    /// visibility order instead of ray casting them.
    #[arg(long)]
    projected_cells: bool,
    /// Draw every grid volume at full resolution instead of through the
    /// octree (the scene's `lod` removed, `full_resolution` set): ray cast,
    /// lit or not.
    #[arg(long)]
    full_resolution: bool,
}

fn parse_tolerance(tolerance: &str) -> Result<f32, String> {
    tolerance
        .parse::<f32>()
        .ok()
        .filter(|t| t.is_finite() && *t >= 0.0)
        .ok_or_else(|| format!("takes a finite number ≥ 0, got `{tolerance}`"))
}

fn parse_resolution(resolution: &str) -> Result<CellResolutionDescription, String> {
    match resolution.to_ascii_lowercase().as_str() {
        "full" => Ok(CellResolutionDescription::Full),
        "half" => Ok(CellResolutionDescription::Half),
        "quarter" => Ok(CellResolutionDescription::Quarter),
        _ => Err(format!("takes full, half or quarter, got `{resolution}`")),
    }
}

fn parse_quality(quality: &str) -> Result<QualityDescription, String> {
    match quality.to_ascii_lowercase().as_str() {
        "low" => Ok(QualityDescription::Low),
        "medium" => Ok(QualityDescription::Medium),
        "high" => Ok(QualityDescription::High),
        _ => Err(format!("takes low, medium or high, got `{quality}`")),
    }
}

/// A per-frame budget in milliseconds: finite, ≥ 0 and at most a minute.
fn parse_budget(milliseconds: &str) -> Result<Duration, String> {
    milliseconds
        .parse::<f64>()
        .ok()
        .filter(|ms| (0.0..=60_000.0).contains(ms))
        .map(|ms| Duration::from_secs_f64(ms / 1e3))
        .ok_or_else(|| format!("takes milliseconds from 0 to 60000, got `{milliseconds}`"))
}

fn parse_size(size: &str) -> Result<(u32, u32), String> {
    size.split_once('x')
        .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)))
        .ok_or_else(|| format!("takes WIDTHxHEIGHT, got `{size}`"))
}

impl SceneArgs {
    /// Loads the scene and applies the options.
    fn load(&self) -> Result<SceneDescription, CommandError> {
        let mut scene = SceneDescription::load(&self.scene)?;
        if let Some(frames) = self.frames {
            scene.output.frames = frames;
        }
        if let Some(frame_rate) = self.frame_rate {
            scene.output.frame_rate = frame_rate;
        }
        if let Some((width, height)) = self.size {
            scene.output.width = width;
            scene.output.height = height;
        }
        if let Some(quality) = self.quality {
            scene.quality = quality;
        }
        if let Some(target) = self.auto_quality {
            scene.auto_quality_ms = Some(target);
        }
        if self.exact {
            scene.camera.cell_projection = Some(CellProjectionDescription::EXACT);
        }
        if self.exact || self.projected_cells {
            for volume in &mut scene.volumes {
                volume.projected_cells = true;
            }
        }
        if self.full_resolution {
            for volume in &mut scene.volumes {
                volume.lod = None;
                volume.full_resolution = true;
            }
        }
        if self.cell_resolution.is_some() || self.upsample_tolerance.is_some() {
            let mut cell_projection = scene.camera.cell_projection.unwrap_or_default();
            if let Some(resolution) = self.cell_resolution {
                cell_projection.resolution = resolution;
            }
            if let Some(tolerance) = self.upsample_tolerance {
                cell_projection.upsample_tolerance = tolerance;
            }
            scene.camera.cell_projection = Some(cell_projection);
        }
        scene.validate().map_err(|invalid| SceneError::Invalid {
            path: self.scene.clone(),
            field: format!("{} (with the command's options)", invalid.field),
            reason: invalid.reason,
        })?;
        Ok(scene)
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("nebel: {error}");
            ExitCode::FAILURE
        }
    }
}

fn run(command: Command) -> Result<(), CommandError> {
    match command {
        Command::Render {
            scene,
            out,
            stats,
            background_builds,
            build_budget_ms,
            webgl2_limits,
            count_fragments,
        } => render(
            &scene,
            &out,
            stats.as_deref(),
            HeadlessOptions {
                progress: true,
                background_builds,
                build_budget: build_budget_ms,
                webgl2_limits,
                count_fragments,
            },
        ),
        Command::Reference { scene, out } => reference(&scene, &out),
        Command::Compare { a, b, diff, steps } => compare(&a, &b, diff.as_deref(), steps),
        Command::BenchFog(PeerArgs { scene, out, steps }) => bench_fog(&scene, &out, steps),
        Command::BenchFogLayers(PeerArgs { scene, out, steps }) => {
            run_fog_layer_peers(&scene.scene, scene.load()?, &out, steps).map(drop)
        }
        Command::BenchLod {
            scene,
            out,
            accuracies,
            image_errors,
            comparison_accuracy,
        } => bench_lod(
            &scene,
            &out,
            &accuracies,
            &image_errors,
            comparison_accuracy,
        ),
        Command::Soak {
            scene,
            frames,
            seed,
            out,
        } => soak_flight(&scene, frames, seed, &out),
    }
}

fn soak_flight(scene_path: &Path, frames: u32, seed: u64, out: &Path) -> Result<(), CommandError> {
    let scene = SceneDescription::load(scene_path)?;
    let setup = SceneSetupPlugin::new(scene, scene_path)?;
    let report = soak(setup, frames, seed, true)?;
    write_report(&report, out).map_err(CommandError::write(out))?;
    eprintln!(
        "nebel: soak of {frames} frames: {} non-finite cells, {} non-finite channels in {} frames read back; report {}",
        report.non_finite_cells,
        report.non_finite_channels,
        report.frames_read_back,
        out.display()
    );
    if report.is_clean() {
        Ok(())
    } else {
        Err(CommandError::Unsuitable {
            path: scene_path.to_owned(),
            reason: String::from("the soak flight found non-finite values (see the report)"),
        })
    }
}

fn render(
    args: &SceneArgs,
    out: &Path,
    stats_path: Option<&Path>,
    options: HeadlessOptions,
) -> Result<(), CommandError> {
    let mut scene = args.load()?;
    if options.webgl2_limits {
        scene.camera.msaa = 1;
    }
    let setup = SceneSetupPlugin::new(scene, &args.scene)?;
    let stats = setup.render_headless(options, out)?;
    if let Some(stats_path) = stats_path {
        std::fs::write(stats_path, stats.to_json()).map_err(CommandError::write(stats_path))?;
    }
    eprintln!(
        "nebel: wrote {} ({}x{}, {} frames on {})",
        out.display(),
        stats.width,
        stats.height,
        stats.frames_rendered,
        stats.adapter.name
    );
    Ok(())
}

fn reference(args: &SceneArgs, out: &Path) -> Result<(), CommandError> {
    let scene = args.load()?;
    let started = Instant::now();
    let image = scene_reference(&args.scene, &scene, true)?;
    save_reference(&image, out)?;
    eprintln!(
        "nebel: wrote {} ({}x{}, exact CPU reference in {:.1} s)",
        out.display(),
        image.width,
        image.height,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

fn compare(a: &Path, b: &Path, diff: Option<&Path>, steps: bool) -> Result<(), CommandError> {
    let (first, second) = (load_png_linear(a)?, load_png_linear(b)?);
    let metrics = nebel_reference::image_metrics::compare(&first, &second)?;
    println!("{metrics}");
    if steps {
        let step = largest_difference_step(&first, &second)?;
        println!("largest step of A − B between adjacent pixels {step:e}");
    }
    if let Some(diff_path) = diff {
        let diff = difference_image(&first, &second, DIFF_SCALE)?;
        save_png(&diff, diff_path, [0.0; 3])?;
    }
    Ok(())
}

/// The scene's only volume, built.
fn single_volume(scene: &SceneDescription, scene_path: &Path) -> Result<BuiltVolume, CommandError> {
    let mut volumes = scene.build_volumes(scene_path)?;
    if volumes.len() != 1 {
        return Err(CommandError::Unsuitable {
            path: scene_path.to_owned(),
            reason: format!(
                "bench-fog compares exactly one volume, the scene has {}",
                volumes.len()
            ),
        });
    }
    Ok(volumes.remove(0))
}

/// `nebel bench-fog`: nebel against Bevy's `FogVolume` on the scene's grid
/// volume, both scored against the exact reference
/// ([`nebel_tools::fog_comparison`]).
fn bench_fog(args: &SceneArgs, out_dir: &Path, step_count: u32) -> Result<(), CommandError> {
    let scene_path = &args.scene;
    let mut scene = args.load()?;
    scene.camera.tonemapping = false;
    scene.camera.msaa = 1;
    let volume = single_volume(&scene, scene_path)?;
    let last_frame = f64::from(scene.frame_time(scene.output.frames - 1));
    let grid = match volume.field {
        SceneField::Grid(grid) => grid,
        SceneField::Campfire(campfire) => campfire.grid_at(last_frame),
        SceneField::Cloud(cloud) => cloud.grid_at(last_frame)?,
        SceneField::Cells(_) => {
            return Err(CommandError::Unsuitable {
                path: scene_path.clone(),
                reason: String::from("bench-fog needs a grid volume"),
            });
        }
    };
    let suns: Vec<_> = scene
        .lights
        .iter()
        .filter_map(|light| match light {
            LightDescription::Directional(sun) => Some(sun),
            _ => None,
        })
        .collect();
    let [sun] = suns[..] else {
        return Err(CommandError::Unsuitable {
            path: scene_path.clone(),
            reason: String::from("bench-fog needs exactly one directional light"),
        });
    };
    let light = bevy::color::Color::srgb(sun.color[0], sun.color[1], sun.color[2]).to_linear();
    let light = bevy::math::Vec3::new(light.red, light.green, light.blue) * sun.illuminance;
    let fog = BevyFog {
        scattering: 1.0,
        density_factor: volume.transfer_function.max_density(),
        step_count,
    };
    let fog_box = fog_comparison::fog_box(&grid);
    let transfer_function =
        fog.equivalent_transfer_function(light, fog_comparison::bounding_radius(&fog_box))?;
    let cells = grid.tetrahedra();
    let equivalent = BuiltVolume {
        field: SceneField::Grid(grid),
        transfer_function,
        mode: OpticalMode::Sorted,
        lod: None,
        lighting: None,
        projected_cells: false,
        ends_where_fog_layers_begin: false,
        fog_sunlight: None,
        light_response: Default::default(),
    };
    // Two references: through the trilinear grid (the total error) and
    // through nebel's six tetrahedra per voxel (the error of projection and
    // pre-integration alone).
    let tetrahedral = BuiltVolume {
        field: SceneField::Cells(cells),
        ..equivalent.clone()
    };
    std::fs::create_dir_all(out_dir).map_err(CommandError::write(out_dir))?;

    let (bar, report) = reference_bar(true);
    let reference = reference_image(&scene, vec![equivalent.clone()], Some(&report))?;
    save_reference(&reference, &out_dir.join("reference.png"))?;
    let tetrahedral_reference = reference_image(&scene, vec![tetrahedral], Some(&report))?;
    bar.finish_and_clear();
    save_reference(
        &tetrahedral_reference,
        &out_dir.join("reference_tetrahedral.png"),
    )?;
    let mut rows = vec![String::from(
        "renderer,frame_ms_median,frame_ms_max,cells_gpu_ms_mean,fragments_per_pixel,rmse,max_abs,psnr_db,rmse_vs_tetrahedral,max_abs_vs_tetrahedral",
    )];
    // nebel draws the volume as the scene says (its `lod`, if any), with the
    // scene's cell projection and with the exact method; the references and
    // Bevy's fog see the grid itself.
    let drawn_by_nebel = BuiltVolume {
        lod: volume.lod,
        ..equivalent.clone()
    };
    // A grid at full resolution is ray cast by default; the paper's
    // projected cells are measured beside it.
    let projected = BuiltVolume {
        projected_cells: true,
        ..drawn_by_nebel.clone()
    };
    let mut exact_scene = scene.clone();
    exact_scene.camera.cell_projection = Some(CellProjectionDescription::EXACT);
    let mut renderers = vec![
        ("nebel", &scene, &drawn_by_nebel, None),
        ("nebel_exact", &exact_scene, &drawn_by_nebel, None),
    ];
    if volume.lod.is_none() {
        renderers.push(("nebel_projected_cells", &exact_scene, &projected, None));
    }
    renderers.push(("bevy_fog_volume", &scene, &equivalent, Some(fog)));
    for (name, scene, drawn, bevy_fog) in renderers {
        let setup = SceneSetupPlugin {
            scene: scene.clone(),
            volumes: vec![drawn.clone()],
            terrain: scene.build_terrain(scene_path)?,
            ground_fog: scene.build_ground_fog(scene_path)?,
            aurora: scene.build_aurora(scene_path)?,
            cloud_layer: scene.build_cloud_layer(scene_path)?,
            peer: bevy_fog.map(BevyPeer::FogVolume),
        };
        let image_path = out_dir.join(format!("{name}.png"));
        let options = HeadlessOptions {
            progress: true,
            ..HeadlessOptions::default()
        };
        let stats = setup.clone().render_headless(options, &image_path)?;
        // The fragments are counted in a second run: the counter costs time.
        let fragments = match bevy_fog {
            None => {
                let counted = HeadlessOptions {
                    count_fragments: true,
                    ..options
                };
                let path = out_dir.join(format!("{name}_counted.png"));
                let counted = setup.render_headless(counted, &path)?;
                cell_figure(&counted, "fragments_per_pixel_mean")
            }
            Some(_) => String::new(),
        };
        let image = load_png_linear(&image_path)?;
        let metrics = nebel_reference::image_metrics::compare(&image, &reference)?;
        let tetrahedral = nebel_reference::image_metrics::compare(&image, &tetrahedral_reference)?;
        println!(
            "{name}: frame {:.1} ms (median); against the trilinear reference {metrics}; against the tetrahedral reference {tetrahedral}",
            stats.frame_wall_ms.median
        );
        rows.push(format!(
            "{name},{},{},{},{fragments},{},{},{},{},{}",
            stats.frame_wall_ms.median,
            stats.frame_wall_ms.max,
            cell_figure(&stats, "gpu_ms_mean"),
            metrics.rmse,
            metrics.max_abs,
            metrics.psnr,
            tetrahedral.rmse,
            tetrahedral.max_abs
        ));
    }
    let csv = out_dir.join("fog_comparison.csv");
    std::fs::write(&csv, rows.join("\n") + "\n").map_err(CommandError::write(&csv))?;
    eprintln!("nebel: wrote {}", csv.display());
    Ok(())
}

/// A figure of the cell projection's diagnostics in `stats` (`gpu_ms_mean`,
/// `fragments_per_pixel_mean`, ...), or empty where it was not measured.
fn cell_figure(stats: &RenderStats, figure: &str) -> String {
    stats
        .effects
        .get("cell_projection")
        .and_then(|figures| figures.get(figure))
        .map(f64::to_string)
        .unwrap_or_default()
}

fn bench_lod(
    args: &SceneArgs,
    out_dir: &Path,
    accuracies: &[f64],
    image_errors: &[f64],
    comparison_accuracy: Option<f64>,
) -> Result<(), CommandError> {
    let scene = args.load()?;
    let points = run_lod_sweep(
        &args.scene,
        scene,
        accuracies,
        image_errors,
        comparison_accuracy,
        out_dir,
    )?;
    for point in &points {
        let setting = match point.setting {
            Some(SweepSetting::Accuracy(c)) => format!("c = {c}"),
            Some(SweepSetting::ImageError(t)) => format!("screen error {t}"),
            None => String::from("full resolution"),
        };
        println!(
            "{setting}: {} cells, frame {:.1} ms, RMSE {:.3e} against full resolution, {:.3e} against the exact reference",
            point.cells_drawn, point.frame_ms, point.rmse_full, point.rmse
        );
    }
    eprintln!("nebel: wrote {}", out_dir.join("lod_sweep.csv").display());
    Ok(())
}
