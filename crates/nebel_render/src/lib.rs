//! nebel's Bevy render plumbing.
//!
//! Every nebel effect plugin depends on this crate. It owns what the effects
//! share on the Bevy side:
//!
//! - [`cell_batch`]: the [`CellBatch`] component, the cells an effect wants drawn.
//! - [`cell_projection`]: the render feature that draws them, exact per pixel.
//! - [`builds`]: heavy builds on the task pool ([`HeavyBuilds`]).
//! - [`camera`]: the camera that drives the level of detail ([`LodCamera`]).
//! - [`diagnostics`]: the [`NebelSystems`] set that every per-frame nebel system
//!   joins and the CPU time that set takes each frame.

pub mod builds;
pub mod camera;
pub mod cell_batch;
pub mod cell_projection;
pub mod diagnostics;

pub use builds::{HeavyBuild, HeavyBuilds};
pub use camera::{LodCamera, LodCameras, LodView};
pub use cell_batch::{CellBatch, CellScattering};
pub use cell_projection::{CellProjectionPlugin, CellProjectionStats};
pub use diagnostics::{NebelDiagnosticsPlugin, NebelSystems};
