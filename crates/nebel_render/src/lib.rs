//! nebel's Bevy render plumbing.
//!
//! Every nebel effect plugin depends on this crate. It owns what the effects
//! share on the Bevy side:
//!
//! - [`cell_batch`]: the [`CellBatch`] component, the cells an effect wants drawn.
//! - [`cell_projection`]: the render system that draws them, exact per pixel.
//! - [`diagnostics`]: the [`NebelSystems`] set that every per-frame nebel system
//!   joins, the CPU time that set takes each frame, and the per-effect counters
//!   that `nebel render --stats` reports.

pub mod cell_batch;
pub mod cell_projection;
pub mod diagnostics;

pub use cell_batch::{CellBatch, CellScattering};
pub use cell_projection::{CellProjectionPlugin, CellProjectionStats};
pub use diagnostics::{EffectCounters, NebelDiagnosticsPlugin, NebelFrameTimings, NebelSystems};
