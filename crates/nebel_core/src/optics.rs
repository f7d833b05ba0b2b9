//! Optical models and compositing (Röttger 2004 ch. 6-9, Röttger and Ertl 2003 §4).
//!
//! A ray segment through one cell contributes a premultiplied colour `C` and an
//! opacity `α`. How segments combine depends on the [`OpticalMode`]:
//!
//! - [`OpticalMode::Sorted`]: emission-absorption, composited back to front with
//!   the premultiplied "over" operator `I' = C + (1 − α) I` (Röttger 2004 eq. 6.x).
//! - [`OpticalMode::Emissive`]: emission only (PCP, Röttger 2004 §10.3): `I' = C + I`,
//!   commutative, so cells need no sorting.
//! - [`OpticalMode::Mip`]: maximum intensity projection: `I' = max(C, I)` per
//!   channel, commutative.

use glam::DVec4;

/// In how many equal pieces a ray segment through a cell with a
/// segment-length modulator is integrated, each with the mean of the linear
/// modulator over it (Röttger and Ertl 2003 §5.1 Eq. 9, `l' = l · m̄`),
/// composited front to back: by the GPU (`cell_projection.wgsl`) and by the
/// exact reference for cells alike. The mean over a whole segment puts a
/// cell's densest end's opacity into its thinnest end too, and differently for
/// every split of the segments, so a refinement that splits them differently
/// changed the image; in four pieces that error is a sixteenth.
pub const MODULATOR_PIECES: u32 = 4;

/// How the segments of a ray combine into a pixel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
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

/// The asymmetry renderers use: `g` clamped to ±0.99, NaN as 0 (isotropic).
pub fn checked_asymmetry(asymmetry: f32) -> f32 {
    if asymmetry.is_nan() {
        0.0
    } else {
        asymmetry.clamp(-0.99, 0.99)
    }
}

/// The Henyey-Greenstein phase function times 4π (Nes 2008): `(1 − g²) /
/// (1 + g² − 2g cos θ)^{3/2}` for the asymmetry `g` (clamped to ±0.99) and
/// the cosine `cos θ` between the light's travel direction and the scattered
/// direction. 1 for `g = 0`; its mean over the sphere is 1 for every `g`, so
/// it scales a light's colour without changing its total. NaN input gives 1
/// (isotropic).
pub fn henyey_greenstein(asymmetry: f64, cos_theta: f64) -> f64 {
    if asymmetry.is_nan() || cos_theta.is_nan() {
        return 1.0;
    }
    let g = asymmetry.clamp(-0.99, 0.99);
    let cos_theta = cos_theta.clamp(-1.0, 1.0);
    (1.0 - g * g) / (1.0 + g * g - 2.0 * g * cos_theta).powf(1.5)
}

/// `e^{−x}` for `x ≥ 0` (larger arguments are clamped to 700, NaN reads as
/// 0), to about 1e-15 relative: `2^{−n} e^{−r}` with `|r| ≤ ln 2 / 2` and a
/// degree-12 Taylor polynomial. Branch-free, so loops over it vectorize
/// (`f64::exp` is a library call per value): the pre-integration's
/// quadrature sums and the light field's transmittance toward the sun.
/// Always inlined, so that it is compiled for the instructions of the loop
/// it is in.
#[inline(always)]
pub(crate) fn exp_neg(x: f64) -> f64 {
    // 1.5 · 2^52: adding it rounds to an integer kept in the low mantissa bits.
    const ROUND: f64 = 6_755_399_441_055_744.0;
    const LN2_HI: f64 = 0.693_147_180_369_123_8;
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
    let x = if x > 0.0 { x.min(700.0) } else { 0.0 };
    let shifted = x * std::f64::consts::LOG2_E + ROUND;
    let n = shifted - ROUND;
    let exponent = (shifted.to_bits() as i64).wrapping_sub(ROUND.to_bits() as i64);
    let r = (x - n * LN2_HI) - n * LN2_LO;
    // e^{−r} = Σ (−r)^i / i!, Horner.
    const COEFFICIENTS: [f64; 13] = [
        1.0 / 479_001_600.0,
        1.0 / 39_916_800.0,
        1.0 / 3_628_800.0,
        1.0 / 362_880.0,
        1.0 / 40_320.0,
        1.0 / 5_040.0,
        1.0 / 720.0,
        1.0 / 120.0,
        1.0 / 24.0,
        1.0 / 6.0,
        0.5,
        1.0,
        1.0,
    ];
    let t = -r;
    let mut p = COEFFICIENTS[0];
    for c in &COEFFICIENTS[1..] {
        p = p * t + c;
    }
    let scale = f64::from_bits(((1023 - exponent) as u64) << 52);
    p * scale
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

    #[test]
    fn henyey_greenstein_is_normalised_and_forward_peaked() {
        for g in [-0.8, 0.0, 0.3, 0.85] {
            // The mean over the sphere: a midpoint rule in cos θ.
            let n = 100_000;
            let mean = (0..n)
                .map(|i| henyey_greenstein(g, -1.0 + (2.0 * i as f64 + 1.0) / n as f64))
                .sum::<f64>()
                / n as f64;
            assert!((mean - 1.0).abs() < 1e-4, "g = {g}: {mean}");
        }
        assert_eq!(henyey_greenstein(0.0, 0.3), 1.0);
        assert!(henyey_greenstein(0.7, 1.0) > 20.0 * henyey_greenstein(0.7, -1.0));
        assert_eq!(henyey_greenstein(f64::NAN, 0.5), 1.0);
        assert!(henyey_greenstein(1.0, 1.0).is_finite());
    }

    #[test]
    fn the_fast_exponential_matches_the_library() {
        let mut worst: f64 = 0.0;
        for step in 0..=175_000 {
            let x = f64::from(step) * 0.004;
            worst = worst.max((exp_neg(x) / (-x).exp() - 1.0).abs());
        }
        assert!(worst < 1e-14, "{worst}");
        assert_eq!(exp_neg(0.0), 1.0);
        assert!(exp_neg(1e9) < 1e-300 && exp_neg(1e9) >= 0.0);
        assert_eq!(exp_neg(f64::NAN), 1.0);
    }
}
