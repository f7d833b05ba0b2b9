//! Campfire: a night scene with an animated emissive fire, a point light and
//! smoke rising above it.
//!
//! `cargo run --release --example campfire` opens a window with a fly camera
//! (WASD, Q/E, Shift, right mouse button to look); with no display, or with
//! `-- --headless`, it renders `assets/scenes/campfire.ron` to
//! `target/nebel/campfire.png`.

fn main() -> std::process::ExitCode {
    nebel_tools::example_runner::run_example("campfire")
}
