//! The `nebel` command line.
//!
//! ```text
//! nebel render SCENE --out IMAGE.png [--stats STATS.json] [--frames N] [--size WxH]
//! nebel reference SCENE --out IMAGE.png [--frames N] [--size WxH]
//! nebel compare A.png B.png [--diff DIFF.png]
//! nebel bench-fog SCENE --out DIR [--frames N] [--size WxH] [--steps N]
//! nebel bench-lod SCENE --out DIR [--accuracies C1,C2,...] [--comparison-accuracy C] [--frames N] [--size WxH]
//! ```
//!
//! `render` draws a scene file headless through whatever adapter wgpu finds
//! (lavapipe included) and writes the last frame; `--stats` writes the JSON of
//! [`nebel_tools::stats::RenderStats`]; `--frames` and `--size` override the scene's
//! `output`.
//!
//! `reference` integrates the same view exactly on the CPU
//! ([`nebel_tools::reference_image`], f64, adaptive, both cores): the scene's
//! volumes over its clear colour, from the camera of the last frame, cut at
//! the scene's meshes, which it draws black (the reference shades no surface;
//! accuracy scenes have black meshes and no lights).
//!
//! `compare` prints RMSE, maximum absolute error and PSNR over linear RGB of
//! two PNGs of the same size; `--diff` writes `|A − B| · 10` per channel.
//!
//! `bench-fog` renders the scene's grid volume with nebel and with Bevy's own
//! `FogVolume` (`--steps` samples per ray, default 64) under the same optics
//! ([`nebel_tools::fog_comparison`]), scores both against the two exact references
//! (through the trilinear grid, and through nebel's tetrahedra) and writes
//! `DIR/fog_comparison.csv` (median and max frame time, RMSE, max error,
//! PSNR) with the images. Tonemapping and MSAA are off.
//!
//! `bench-lod` sweeps the octree accuracy `c` of the scene's grid volume
//! (default `0,4,16,64,256`) plus full resolution (or, with
//! `--comparison-accuracy C`, the image at `c = C` for a volume too large to
//! draw at full resolution, without the exact reference) and writes
//! `DIR/lod_sweep.csv` and a plot of frame time against error
//! ([`nebel_tools::lod_sweep`]).
//!
//! Errors are one line on stderr and a non-zero exit status.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use nebel_core::optics::OpticalMode;
use nebel_reference::image_metrics::{difference_image, load_png_linear, save_png};
use nebel_scene::reference::{reference_image, reference_image_with_terrain, save_reference};
use nebel_scene::{BuiltVolume, LightDescription, SceneDescription, VolumeField};
use nebel_tools::fog_comparison::{self, BevyFog};
use nebel_tools::headless::render_headless;
use nebel_tools::lod_sweep::run_lod_sweep;
use nebel_tools::scene_setup::SceneSetupPlugin;

const USAGE: &str = "usage:
  nebel render SCENE --out IMAGE.png [--stats STATS.json] [--frames N] [--size WxH]
  nebel reference SCENE --out IMAGE.png [--frames N] [--size WxH]
  nebel compare A.png B.png [--diff DIFF.png]
  nebel bench-fog SCENE --out DIR [--frames N] [--size WxH] [--steps N]
  nebel bench-lod SCENE --out DIR [--accuracies C1,C2,...] [--comparison-accuracy C] [--frames N] [--size WxH]";

/// Factor on the absolute error in `compare --diff` images.
const DIFF_SCALE: f32 = 10.0;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("nebel: {message}");
            ExitCode::FAILURE
        }
    }
}

fn run(args: &[String]) -> Result<(), String> {
    match args.first().map(String::as_str) {
        Some("render") => render(&args[1..]),
        Some("reference") => reference(&args[1..]),
        Some("compare") => compare(&args[1..]),
        Some("bench-fog") => bench_fog(&args[1..]),
        Some("bench-lod") => bench_lod(&args[1..]),
        Some("-h" | "--help") => {
            println!("{USAGE}");
            Ok(())
        }
        Some(other) => Err(format!("unknown command `{other}`\n{USAGE}")),
        None => Err(format!("no command given\n{USAGE}")),
    }
}

/// Positional arguments and `--name value` options of one command.
struct Arguments {
    positional: Vec<String>,
    options: Vec<(String, String)>,
}

impl Arguments {
    /// Splits `args`; every option takes a value and must be in `known`.
    fn parse(args: &[String], known: &[&str]) -> Result<Self, String> {
        let mut positional = Vec::new();
        let mut options = Vec::new();
        let mut iter = args.iter();
        while let Some(arg) = iter.next() {
            if let Some(name) = arg.strip_prefix("--") {
                if !known.contains(&name) {
                    return Err(format!("unknown option `{arg}`\n{USAGE}"));
                }
                let value = iter
                    .next()
                    .ok_or_else(|| format!("option `{arg}` needs a value"))?;
                options.push((name.to_owned(), value.clone()));
            } else {
                positional.push(arg.clone());
            }
        }
        Ok(Self {
            positional,
            options,
        })
    }

    fn option(&self, name: &str) -> Option<&str> {
        self.options
            .iter()
            .rev()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }

    fn required(&self, name: &str) -> Result<&str, String> {
        self.option(name)
            .ok_or_else(|| format!("missing `--{name}`\n{USAGE}"))
    }

    fn positional(&self, count: usize, what: &str) -> Result<&[String], String> {
        if self.positional.len() == count {
            Ok(&self.positional)
        } else {
            Err(format!(
                "expected {what}, got {} argument(s)\n{USAGE}",
                self.positional.len()
            ))
        }
    }
}

/// Loads the scene named by the one positional argument and applies
/// `--frames` and `--size`.
fn load_scene(arguments: &Arguments) -> Result<(PathBuf, SceneDescription), String> {
    let scene_path = PathBuf::from(&arguments.positional(1, "one scene file")?[0]);
    let mut scene = SceneDescription::load(&scene_path).map_err(|e| e.to_string())?;
    if let Some(frames) = arguments.option("frames") {
        scene.output.frames = frames
            .parse()
            .map_err(|_| format!("--frames takes a whole number, got `{frames}`"))?;
    }
    if let Some(size) = arguments.option("size") {
        let parsed = size
            .split_once('x')
            .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)));
        let (width, height) =
            parsed.ok_or_else(|| format!("--size takes WIDTHxHEIGHT, got `{size}`"))?;
        scene.output.width = width;
        scene.output.height = height;
    }
    scene.validate().map_err(|invalid| {
        format!(
            "{} with --frames/--size: field {}: {}",
            scene_path.display(),
            invalid.field,
            invalid.reason
        )
    })?;
    Ok((scene_path, scene))
}

fn render(args: &[String]) -> Result<(), String> {
    let arguments = Arguments::parse(args, &["out", "stats", "frames", "size"])?;
    let out = PathBuf::from(arguments.required("out")?);
    let (scene_path, scene) = load_scene(&arguments)?;
    let setup = SceneSetupPlugin::new(scene, &scene_path).map_err(|e| e.to_string())?;
    let stats = render_headless(setup, &out, true).map_err(|e| e.to_string())?;
    if let Some(stats_path) = arguments.option("stats") {
        std::fs::write(stats_path, stats.to_json())
            .map_err(|e| format!("{stats_path}: cannot write statistics: {e}"))?;
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

fn reference(args: &[String]) -> Result<(), String> {
    let arguments = Arguments::parse(args, &["out", "frames", "size"])?;
    let out = PathBuf::from(arguments.required("out")?);
    let (scene_path, scene) = load_scene(&arguments)?;
    let volumes = scene
        .build_volumes(&scene_path)
        .map_err(|e| e.to_string())?;
    let unit_heights = scene
        .build_terrain(&scene_path)
        .map_err(|e| e.to_string())?;
    let terrain = scene
        .terrain
        .as_ref()
        .zip(unit_heights.as_ref())
        .map(|(terrain, unit)| terrain.world_heights(unit));
    let started = Instant::now();
    let image = reference_image_with_terrain(&scene, volumes, terrain.as_ref(), true)
        .map_err(|e| e.to_string())?;
    save_reference(&image, &out).map_err(|e| e.to_string())?;
    eprintln!(
        "nebel: wrote {} ({}x{}, exact CPU reference in {:.1} s)",
        out.display(),
        image.width,
        image.height,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The scene's only volume, built.
fn single_volume(scene: &SceneDescription, scene_path: &Path) -> Result<BuiltVolume, String> {
    let mut volumes = scene.build_volumes(scene_path).map_err(|e| e.to_string())?;
    if volumes.len() != 1 {
        return Err(format!(
            "{}: bench-fog compares exactly one volume, the scene has {}",
            scene_path.display(),
            volumes.len()
        ));
    }
    Ok(volumes.remove(0))
}

/// `nebel bench-fog`: nebel against Bevy's `FogVolume` on the scene's grid
/// volume, both scored against the exact reference ([`nebel_tools::fog_comparison`]).
fn bench_fog(args: &[String]) -> Result<(), String> {
    let arguments = Arguments::parse(args, &["out", "frames", "size", "steps"])?;
    let out_dir = PathBuf::from(arguments.required("out")?);
    let step_count: u32 = match arguments.option("steps") {
        Some(steps) => steps
            .parse()
            .map_err(|_| format!("--steps takes a whole number, got `{steps}`"))?,
        None => 64,
    };
    let (scene_path, mut scene) = load_scene(&arguments)?;
    scene.camera.tonemapping = false;
    scene.camera.msaa = 1;
    let volume = single_volume(&scene, &scene_path)?;
    let grid = match volume.field {
        VolumeField::Grid(grid) => grid,
        VolumeField::Campfire(campfire) => {
            campfire.grid_at(f64::from(scene.frame_time(scene.output.frames - 1)))
        }
        VolumeField::Cloud(cloud) => cloud
            .grid_at(f64::from(scene.frame_time(scene.output.frames - 1)))
            .map_err(|e| e.to_string())?,
        VolumeField::Cells(_) => {
            return Err(format!(
                "{}: bench-fog needs a grid volume",
                scene_path.display()
            ));
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
        return Err(format!(
            "{}: bench-fog needs exactly one directional light",
            scene_path.display()
        ));
    };
    let light = bevy::color::Color::srgb(sun.color[0], sun.color[1], sun.color[2]).to_linear();
    let light = bevy::math::Vec3::new(light.red, light.green, light.blue) * sun.illuminance;
    let fog = BevyFog {
        scattering: 1.0,
        density_factor: volume.transfer_function.max_density(),
        step_count,
    };
    let fog_box = fog_comparison::fog_box(&grid);
    let transfer_function = fog
        .equivalent_transfer_function(light, fog_comparison::bounding_radius(&fog_box))
        .map_err(|e| e.to_string())?;
    let cells = grid.tetrahedra();
    let equivalent = BuiltVolume {
        field: VolumeField::Grid(grid),
        transfer_function,
        mode: OpticalMode::Sorted,
        lod: None,
        lighting: None,
    };
    // Two references (DESIGN.md §4): through the trilinear grid (the total
    // error) and through nebel's five tetrahedra per voxel (the error of
    // projection and pre-integration alone).
    let tetrahedral = BuiltVolume {
        field: VolumeField::Cells(cells),
        ..equivalent.clone()
    };
    std::fs::create_dir_all(&out_dir).map_err(|e| format!("{}: {e}", out_dir.display()))?;

    let reference =
        reference_image(&scene, vec![equivalent.clone()], true).map_err(|e| e.to_string())?;
    save_reference(&reference, &out_dir.join("reference.png")).map_err(|e| e.to_string())?;
    let tetrahedral_reference =
        reference_image(&scene, vec![tetrahedral], true).map_err(|e| e.to_string())?;
    save_reference(
        &tetrahedral_reference,
        &out_dir.join("reference_tetrahedral.png"),
    )
    .map_err(|e| e.to_string())?;
    let mut rows = vec![String::from(
        "renderer,frame_ms_median,frame_ms_max,rmse,max_abs,psnr_db,rmse_vs_tetrahedral,max_abs_vs_tetrahedral",
    )];
    for (name, bevy_fog) in [("nebel", None), ("bevy_fog_volume", Some(fog))] {
        let setup = SceneSetupPlugin {
            scene: scene.clone(),
            volumes: vec![equivalent.clone()],
            terrain: scene
                .build_terrain(&scene_path)
                .map_err(|e| e.to_string())?,
            target: None,
            bevy_fog,
        };
        let image_path = out_dir.join(format!("{name}.png"));
        let stats = render_headless(setup, &image_path, true).map_err(|e| e.to_string())?;
        let image = load_png_linear(&image_path).map_err(|e| e.to_string())?;
        let metrics = nebel_reference::image_metrics::compare(&image, &reference)
            .map_err(|e| e.to_string())?;
        let tetrahedral = nebel_reference::image_metrics::compare(&image, &tetrahedral_reference)
            .map_err(|e| e.to_string())?;
        println!(
            "{name}: frame {:.1} ms (median); against the trilinear reference {metrics}; against the tetrahedral reference {tetrahedral}",
            stats.frame_wall_ms.median
        );
        rows.push(format!(
            "{name},{},{},{},{},{},{},{}",
            stats.frame_wall_ms.median,
            stats.frame_wall_ms.max,
            metrics.rmse,
            metrics.max_abs,
            metrics.psnr,
            tetrahedral.rmse,
            tetrahedral.max_abs
        ));
    }
    let csv = out_dir.join("fog_comparison.csv");
    std::fs::write(&csv, rows.join("\n") + "\n").map_err(|e| format!("{}: {e}", csv.display()))?;
    eprintln!("nebel: wrote {}", csv.display());
    Ok(())
}

fn bench_lod(args: &[String]) -> Result<(), String> {
    let arguments = Arguments::parse(
        args,
        &["out", "frames", "size", "accuracies", "comparison-accuracy"],
    )?;
    let out_dir = PathBuf::from(arguments.required("out")?);
    let accuracies: Vec<f64> = match arguments.option("accuracies") {
        Some(list) => list
            .split(',')
            .map(|c| {
                c.trim()
                    .parse()
                    .map_err(|_| format!("--accuracies takes numbers, got `{c}`"))
            })
            .collect::<Result<_, _>>()?,
        None => vec![0.0, 4.0, 16.0, 64.0, 256.0],
    };
    let (scene_path, scene) = load_scene(&arguments)?;
    let comparison_accuracy = match arguments.option("comparison-accuracy") {
        Some(c) => Some(
            c.parse::<f64>()
                .map_err(|_| format!("--comparison-accuracy takes a number, got `{c}`"))?,
        ),
        None => None,
    };
    let points = run_lod_sweep(
        &scene_path,
        scene,
        &accuracies,
        comparison_accuracy,
        &out_dir,
    )?;
    for point in &points {
        let c = point
            .accuracy
            .map_or(String::from("full resolution"), |c| format!("c = {c}"));
        println!(
            "{c}: {} cells, frame {:.1} ms, RMSE {:.3e} against full resolution, {:.3e} against the exact reference",
            point.cells_drawn, point.frame_ms, point.rmse_full, point.rmse
        );
    }
    eprintln!("nebel: wrote {}", out_dir.join("lod_sweep.csv").display());
    Ok(())
}

fn compare(args: &[String]) -> Result<(), String> {
    let arguments = Arguments::parse(args, &["diff"])?;
    let paths = arguments.positional(2, "two PNG files")?;
    let load = |path: &String| load_png_linear(path).map_err(|e| e.to_string());
    let (a, b) = (load(&paths[0])?, load(&paths[1])?);
    let metrics = nebel_reference::image_metrics::compare(&a, &b)
        .map_err(|e| format!("{} vs {}: {e}", paths[0], paths[1]))?;
    println!("{metrics}");
    if let Some(diff_path) = arguments.option("diff") {
        let diff = difference_image(&a, &b, DIFF_SCALE).map_err(|e| e.to_string())?;
        save_png(&diff, diff_path, [0.0; 3]).map_err(|e| e.to_string())?;
    }
    Ok(())
}
