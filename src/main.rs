//! The `nebel` command line.
//!
//! ```text
//! nebel render SCENE --out IMAGE.png [--stats STATS.json] [--frames N] [--size WxH]
//! nebel reference SCENE --out IMAGE.png [--frames N] [--size WxH]
//! nebel compare A.png B.png [--diff DIFF.png]
//! ```
//!
//! `render` draws a scene file headless through whatever adapter wgpu finds
//! (lavapipe included) and writes the last frame; `--stats` writes the JSON of
//! [`nebel::stats::RenderStats`]; `--frames` and `--size` override the scene's
//! `output`.
//!
//! `reference` integrates the same view exactly on the CPU
//! ([`nebel_core::reference`], f64, adaptive, both cores): the scene's one
//! volume over its clear colour, from the camera of the last frame, cut at
//! the scene's meshes, which it draws black (the reference shades no surface;
//! accuracy scenes have black meshes and no lights).
//!
//! `compare` prints RMSE, maximum absolute error and PSNR over linear RGB of
//! two PNGs of the same size; `--diff` writes `|A − B| · 10` per channel.
//!
//! Errors are one line on stderr and a non-zero exit status.

use std::path::PathBuf;
use std::process::ExitCode;

use std::sync::Mutex;
use std::time::{Duration, Instant};

use nebel::headless::render_headless;
use nebel::scene_setup::SceneSetupPlugin;
use nebel_core::image_metrics::{difference_image, load_png_linear, save_png, srgb_to_linear};
use nebel_core::reference::{ReferenceScene, ReferenceVolume, RenderProgress};
use nebel_core::scene::{SceneDescription, VolumeField};

const USAGE: &str = "usage:
  nebel render SCENE --out IMAGE.png [--stats STATS.json] [--frames N] [--size WxH]
  nebel reference SCENE --out IMAGE.png [--frames N] [--size WxH]
  nebel compare A.png B.png [--diff DIFF.png]";

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
    let mut volumes = scene
        .build_volumes(&scene_path)
        .map_err(|e| e.to_string())?;
    if volumes.len() != 1 {
        return Err(format!(
            "{}: the reference renders exactly one volume, the scene has {}",
            scene_path.display(),
            volumes.len()
        ));
    }
    let volume = volumes.remove(0);
    let field = match volume.field {
        VolumeField::Grid(grid) => ReferenceVolume::Grid(grid),
        VolumeField::Cells(cells) => ReferenceVolume::Cells(cells),
        VolumeField::Campfire(campfire) => {
            let last_frame = scene.frame_time(scene.output.frames - 1);
            ReferenceVolume::Grid(campfire.grid_at(f64::from(last_frame)))
        }
    };
    let camera = scene.reference_camera();
    let mut reference_scene =
        ReferenceScene::new(camera.clone(), field, volume.transfer_function, volume.mode);
    reference_scene.opaque_depth = scene.opaque_depth(&camera);
    let started = Instant::now();
    let last_report = Mutex::new(Instant::now());
    let report = |progress: RenderProgress| {
        let mut last = last_report.lock().expect("progress clock");
        if last.elapsed() >= Duration::from_secs(2) {
            eprintln!(
                "nebel: reference row {}/{}",
                progress.rows_done, progress.rows_total
            );
            *last = Instant::now();
        }
    };
    let mut image = nebel_core::reference::render(&reference_scene, Some(&report))
        .map_err(|e| e.to_string())?;
    // Meshes are black (the reference shades no surface): pixels whose ray
    // ends on one composite over black, the others over the clear colour.
    if let Some(depth) = &reference_scene.opaque_depth {
        for (pixel, depth) in image.pixels.iter_mut().zip(depth) {
            if depth.is_finite() {
                pixel[3] = 1.0;
            }
        }
    }
    let background = scene
        .clear_color
        .map(|c| srgb_to_linear(f64::from(c)) as f32);
    save_png(&image, &out, background).map_err(|e| e.to_string())?;
    eprintln!(
        "nebel: wrote {} ({}x{}, exact CPU reference in {:.1} s)",
        out.display(),
        image.width,
        image.height,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

fn compare(args: &[String]) -> Result<(), String> {
    let arguments = Arguments::parse(args, &["diff"])?;
    let paths = arguments.positional(2, "two PNG files")?;
    let load = |path: &String| load_png_linear(path).map_err(|e| e.to_string());
    let (a, b) = (load(&paths[0])?, load(&paths[1])?);
    let metrics = nebel_core::image_metrics::compare(&a, &b)
        .map_err(|e| format!("{} vs {}: {e}", paths[0], paths[1]))?;
    println!("{metrics}");
    if let Some(diff_path) = arguments.option("diff") {
        let diff = difference_image(&a, &b, DIFF_SCALE).map_err(|e| e.to_string())?;
        save_png(&diff, diff_path, [0.0; 3]).map_err(|e| e.to_string())?;
    }
    Ok(())
}
