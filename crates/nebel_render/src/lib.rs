//! nebel's Bevy render plumbing.
//!
//! Every nebel effect plugin depends on this crate. It owns what the effects
//! share on the Bevy side:
//!
//! - [`diagnostics`]: the [`NebelSystems`] set that every per-frame nebel system
//!   joins, the CPU time that set takes each frame, and the per-effect counters
//!   that `nebel render --stats` reports.
//!
//! The cell-projection render system (DESIGN.md §3) joins this crate with the
//! volumes it draws.

pub mod diagnostics;

pub use diagnostics::{EffectCounters, NebelDiagnosticsPlugin, NebelFrameTimings, NebelSystems};
