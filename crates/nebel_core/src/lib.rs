//! nebel's optics, fields and exact CPU reference integrator, without Bevy.
//!
//! Everything here is plain Rust so it builds in a minute and is tested without a
//! GPU (DESIGN.md §2). The Bevy crates only move these results to the GPU.
//!
//! - [`optics`]: optical modes and compositing of premultiplied RGBA (DESIGN.md §4).
//! - [`transfer`]: transfer functions κ (chromaticity) and ρ (density) over a scalar.

pub mod optics;
pub mod transfer;
