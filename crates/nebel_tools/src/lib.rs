//! nebel's tools: what the `nebel` command line, the examples and the
//! integration tests share, and nothing a game needs.
//!
//! - [`scene_setup`]: a scene file's contents spawned into a Bevy world.
//! - [`headless`]: a scene rendered to a PNG with no window, through whatever
//!   adapter wgpu finds (the CPU driver lavapipe included), and its
//!   statistics ([`stats`]).
//! - [`example_runner`]: what every example does: a window with a fly camera
//!   ([`fly_camera`]), or a headless render when there is no display;
//!   [`stars`]: stars on the night sky.
//! - [`fog_comparison`], [`fog_layer_peers`] and [`lod_sweep`]: the
//!   `bench-fog`, `bench-fog-layers` and `bench-lod` commands, and their
//!   chart ([`time_error_chart`]); [`reference`](mod@reference): the exact CPU reference of a whole scene;
//!   [`error`]: why a command failed; [`progress`]: progress bars;
//!   [`soak`]: the soak flight of `nebel soak`.

pub mod error;
pub mod example_runner;
pub mod fly_camera;
pub mod fog_comparison;
pub mod fog_layer_peers;
pub mod headless;
pub mod lod_sweep;
pub mod progress;
pub mod reference;
pub mod scene_setup;
pub mod soak;
pub mod stars;
pub mod stats;
pub mod time_error_chart;

pub use nebel_scene;
