//! nebel's optics, transfer functions, pre-integration, cells and fields,
//! without Bevy.
//!
//! Everything here is plain Rust so it builds in a minute and is tested without a
//! GPU (DESIGN.md §2). The Bevy crates only move these results to the GPU.
//!
//! - [`optics`]: optical modes and compositing of premultiplied RGBA (DESIGN.md §4).
//! - [`transfer`]: transfer functions κ (chromaticity) and ρ (density) over a scalar.
//! - [`cell`]: tetrahedra, prisms, hexahedra, their decompositions and exact ray-cell intersection.
//! - [`segment`]: the exact f64 ray integral of one linear segment, the reference for the tables.
//! - [`preintegration`]: pre-integration tables (3D colour, ρ̂, emission, MIP) and the zero-opacity test.
//! - [`field`]: density grids and height fields, PNG/raw loaders, noise generators, 2^n+1 resampling.
//! - [`budget`]: the memory budget every allocation sized by input is checked against first.

pub mod budget;
pub mod cell;
pub mod field;
pub mod optics;
pub mod preintegration;
pub mod segment;
#[cfg(test)]
mod test_support;
pub mod transfer;
