//! Valley fog: a terrain with fog lying in its valleys. The terrain is a
//! procedural 513 × 513 height field drawn through the quadtree C-LOD with
//! geomorphing (`nebel_terrain`); the ground fog follows with its issue.
//!
//! `cargo run --release --example valley_fog` opens a window with a fly camera
//! (WASD, Q/E, Shift, right mouse button to look); with no display, or with
//! `-- --headless`, it renders `assets/scenes/valley_fog.ron` to
//! `target/nebel/valley_fog.png`.

fn main() -> std::process::ExitCode {
    nebel_tools::example_runner::run_example("valley_fog")
}
