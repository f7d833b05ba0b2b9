//! nebel's exact CPU reference renderer and image error metrics, without Bevy.
//!
//! Accuracy is measured, not assumed: the GPU images of nebel are scored
//! against an exact integral of the same optical model.
//!
//! - [`render`] and [`ReferenceScene`] (module `integrator`): the f64 CPU
//!   reference renderer through a tetrahedral mesh or a trilinear grid, with
//!   an optional segment-length modulator, single scattering, opaque depth
//!   and fog layers ([`ReferenceFog`], module `fog`: height fog exact along
//!   every ray, and volumes seen through it); [`render_together`] integrates
//!   several volumes along each ray as one medium.
//! - [`image_metrics`]: linear images, sRGB PNG input and output, RMSE,
//!   maximum absolute error and PSNR, difference images.
//!
//! Papers are cited by author and year; `docs/references.md` in the repository lists them.

mod fog;
pub mod image_metrics;
mod integrator;

pub use fog::{FogSunlight, ReferenceFog};
pub use integrator::{
    DEFAULT_SCALAR_TOLERANCE, Modulation, ReferenceCamera, ReferenceError, ReferenceScene,
    ReferenceVolume, RenderProgress, SegmentScattering, render, render_together,
};
