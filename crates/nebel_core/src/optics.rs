//! Optical models and compositing (paper 001 ch. 6-9, 000 §4; DESIGN.md §4).
//!
//! A ray segment through one cell contributes a premultiplied colour `C` and an
//! opacity `α`. How segments combine depends on the [`OpticalMode`]:
//!
//! - [`OpticalMode::Sorted`]: emission-absorption, composited back to front with
//!   the premultiplied "over" operator `I' = C + (1 − α) I` (001 eq. 6.x).
//! - [`OpticalMode::Emissive`]: emission only (PCP, 001 §10.3): `I' = C + I`,
//!   commutative, so cells need no sorting.
//! - [`OpticalMode::Mip`]: maximum intensity projection: `I' = max(C, I)` per
//!   channel, commutative.

use glam::DVec4;
use serde::{Deserialize, Serialize};

/// How the segments of a ray combine into a pixel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum OpticalMode {
    /// Emission-absorption, back to front, premultiplied "over". Clouds, fog, smoke.
    #[default]
    Sorted,
    /// Emission only, additive and order independent. Fire, search lights, aurora.
    Emissive,
    /// Maximum intensity projection, order independent. The cheapest preview.
    Mip,
}

/// Premultiplied linear RGBA of one segment or of a whole ray: `xyz` is the
/// colour already weighted by opacity, `w` is the opacity α in [0, 1].
pub type PremultipliedRgba = DVec4;

impl OpticalMode {
    /// Combines `front` (nearer the eye) with `back` (farther away).
    ///
    /// For [`OpticalMode::Sorted`] this is `front + (1 − α_front) · back`; the two
    /// other modes are commutative (sum and per-channel maximum; α of a sum is
    /// `1 − (1 − α_f)(1 − α_b)` so it stays in [0, 1]).
    pub fn composite(self, front: PremultipliedRgba, back: PremultipliedRgba) -> PremultipliedRgba {
        match self {
            OpticalMode::Sorted => front + (1.0 - front.w) * back,
            OpticalMode::Emissive => {
                let alpha = 1.0 - (1.0 - front.w) * (1.0 - back.w);
                (front + back).truncate().extend(alpha)
            }
            OpticalMode::Mip => front.max(back),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sorted_over_is_associative() {
        let a = DVec4::new(0.2, 0.1, 0.0, 0.3);
        let b = DVec4::new(0.05, 0.4, 0.1, 0.5);
        let c = DVec4::new(0.3, 0.3, 0.3, 0.9);
        let m = OpticalMode::Sorted;
        let left = m.composite(m.composite(a, b), c);
        let right = m.composite(a, m.composite(b, c));
        assert!((left - right).abs().max_element() < 1e-15);
    }

    #[test]
    fn commutative_modes_ignore_order() {
        let a = DVec4::new(0.2, 0.1, 0.0, 0.3);
        let b = DVec4::new(0.05, 0.4, 0.1, 0.5);
        for m in [OpticalMode::Emissive, OpticalMode::Mip] {
            assert_eq!(m.composite(a, b), m.composite(b, a));
        }
        assert_ne!(
            OpticalMode::Sorted.composite(a, b),
            OpticalMode::Sorted.composite(b, a)
        );
    }
}
