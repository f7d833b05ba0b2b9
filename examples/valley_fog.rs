//! Valley fog: a terrain with fog lying in its valleys.
//!
//! `cargo run --release --example valley_fog` opens a window with a fly camera
//! (WASD, Q/E, Shift, right mouse button to look); with no display, or with
//! `-- --headless`, it renders `assets/scenes/valley_fog.ron` to
//! `target/nebel/valley_fog.png`.

fn main() -> std::process::ExitCode {
    nebel::example_runner::run_example("valley_fog")
}
