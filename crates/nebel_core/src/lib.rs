//! nebel's optics, pre-integration, cells and fields, without Bevy.
//!
//! Everything here is plain Rust, so it builds without Bevy and is tested
//! without a GPU. The Bevy crates only move these results to the GPU.
//!
//! - [`optics`]: optical modes and compositing of premultiplied RGBA.
//! - [`transfer`]: transfer functions κ (chromaticity) and ρ (density) over a scalar.
//! - [`cell`]: tetrahedra, prisms, hexahedra, their decompositions and exact ray-cell intersection.
//! - [`segment`]: the exact f64 ray integral of one linear segment, the reference for the tables.
//! - [`joint_segment`]: the same for several media sharing a segment (volumes that interpenetrate).
//! - [`local_light`]: point and spot lights scattered along a ray (single scattering, shadows of occluders).
//! - [`occluder`]: opaque boxes, spheres and rectangles, and the stretches of a ray they hide from a light.
//! - [`overlap`]: the joint composite of overlapping volumes known per ray by colour, transmittance and span.
//! - [`preintegration`]: pre-integration tables (3D colour, ρ̂, emission, MIP) and the zero-opacity test.
//! - [`height_fog`]: density over altitude as layers and its exact optical depth along any ray.
//! - [`field`]: density grids and height fields, PNG/raw loaders, noise generators, 2^n+1 resampling.
//! - [`budget`]: the memory budget every allocation sized by input is checked against first.
//! - [`pacing`]: yield points that let a long build share a per-frame time budget.
//!
//! Papers are cited by author and year; `docs/references.md` in the repository lists them.

pub mod budget;
pub mod cell;
pub mod field;
pub mod fog_sunlight;
pub mod height_fog;
pub mod joint_segment;
pub mod local_light;
pub mod occluder;
pub mod optics;
pub mod overlap;
pub mod pacing;
pub mod preintegration;
pub mod segment;
#[cfg(test)]
mod test_support;
pub mod transfer;
