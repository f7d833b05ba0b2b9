//! The `nebel` command line.
//!
//! ```text
//! nebel render SCENE --out IMAGE.png [--stats STATS.json] [--frames N] [--size WxH]
//! ```
//!
//! `render` draws a scene file headless through whatever adapter wgpu finds
//! (lavapipe included) and writes the last frame; `--stats` writes the JSON of
//! [`nebel::stats::RenderStats`]; `--frames` and `--size` override the scene's
//! `output`. Errors are one line on stderr and a non-zero exit status.

use std::path::PathBuf;
use std::process::ExitCode;

use nebel::headless::render_headless;
use nebel_core::scene::SceneDescription;

const USAGE: &str = "usage:
  nebel render SCENE --out IMAGE.png [--stats STATS.json] [--frames N] [--size WxH]";

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

fn render(args: &[String]) -> Result<(), String> {
    let arguments = Arguments::parse(args, &["out", "stats", "frames", "size"])?;
    let scene_path = PathBuf::from(&arguments.positional(1, "one scene file")?[0]);
    let out = PathBuf::from(arguments.required("out")?);
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
    let stats = render_headless(&scene, &out, true).map_err(|e| e.to_string())?;
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
