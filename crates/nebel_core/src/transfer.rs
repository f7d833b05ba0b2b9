//! Transfer functions: chromaticity κ (linear RGB) and density ρ over a scalar
//! `s` in [0, 1] (paper 001 §7.1, DESIGN.md §4).
//!
//! A transfer function is piecewise linear between control points sorted by `s`
//! and constant beyond the first and last point. ρ is an extinction coefficient
//! in 1/world unit; κ·ρ is the emission per unit length.

use glam::DVec3;
use serde::{Deserialize, Serialize};

/// One control point of a piecewise-linear transfer function.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControlPoint {
    /// Scalar position in [0, 1].
    pub s: f32,
    /// Chromaticity κ, linear RGB, each channel ≥ 0.
    pub kappa: [f32; 3],
    /// Density ρ (extinction coefficient), 1/world unit, ≥ 0.
    pub rho: f32,
}

/// κ and ρ at one scalar value, in f64 for the reference integrator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransferSample {
    /// Chromaticity κ, linear RGB.
    pub kappa: DVec3,
    /// Density ρ, 1/world unit.
    pub rho: f64,
}

impl TransferSample {
    /// Emission per unit length κ·ρ.
    pub fn emission(&self) -> DVec3 {
        self.kappa * self.rho
    }
}

/// A piecewise-linear transfer function (κ, ρ) over the scalar `s` in [0, 1].
///
/// Build it with [`TransferFunction::new`], which validates the control points.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TransferFunction {
    points: Vec<ControlPoint>,
}

impl TransferFunction {
    /// The control points, sorted by `s`.
    pub fn points(&self) -> &[ControlPoint] {
        &self.points
    }

    /// κ and ρ at `s` (clamped to [0, 1]; a NaN `s` reads as 0).
    pub fn evaluate(&self, s: f64) -> TransferSample {
        let s = if s.is_nan() { 0.0 } else { s.clamp(0.0, 1.0) };
        let points = &self.points;
        let upper = points.partition_point(|p| f64::from(p.s) <= s);
        let sample = |p: &ControlPoint| TransferSample {
            kappa: DVec3::from(p.kappa.map(f64::from)),
            rho: f64::from(p.rho),
        };
        if upper == 0 {
            return sample(&points[0]);
        }
        if upper == points.len() {
            return sample(&points[points.len() - 1]);
        }
        let (a, b) = (&points[upper - 1], &points[upper]);
        let t = (s - f64::from(a.s)) / (f64::from(b.s) - f64::from(a.s));
        let (sa, sb) = (sample(a), sample(b));
        TransferSample {
            kappa: sa.kappa.lerp(sb.kappa, t),
            rho: sa.rho + (sb.rho - sa.rho) * t,
        }
    }
}
