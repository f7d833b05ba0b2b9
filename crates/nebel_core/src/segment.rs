//! The exact ray integral of one linear segment, in f64: the reference that the
//! pre-integration tables ([`crate::preintegration`]) and the GPU are tested
//! against (Röttger 2004 eq. 8.1 and §9.1).
//!
//! A ray crosses a cell over a length `l`; the scalar varies linearly from
//! `s_f` (front, entry) to `s_b` (back, exit). With `x = t / l` in [0, 1] and
//! `s(x) = s_f + x (s_b − s_f)`:
//!
//! - [`OpticalMode::Sorted`] (emission-absorption, Röttger 2004 eq. 8.1):
//!   `C = l ∫_0^1 κ(s(x)) ρ(s(x)) exp(−l ∫_0^x ρ(s(u)) du) dx`,
//!   `α = 1 − exp(−l ρ̂)` with `ρ̂ = ∫_0^1 ρ(s(x)) dx` (Röttger 2004 eq. 9.1).
//! - [`OpticalMode::Emissive`] (PCP, Röttger 2004 §10.3): `C = l ∫_0^1 E(s(x)) dx` with
//!   `E = κρ`, no absorption. α is defined as `1 − exp(−l ρ̂)` as well: it does
//!   not attenuate anything in this mode, it only records coverage for the
//!   "sum" compositing of [`OpticalMode::composite`].
//! - [`OpticalMode::Mip`]: `C` is the per-channel maximum of `E(s) = κ(s)ρ(s)`
//!   over `s` between `s_f` and `s_b` (independent of `l`), and
//!   `α = 1 − exp(−l ρ_max)` with `ρ_max` the largest density there: in [0, 1],
//!   growing with `l`, zero exactly when the range is transparent.
//!
//! # Method
//!
//! The segment is split at the transfer function's control points, so on each
//! piece κ and ρ are linear in `x` and everything is smooth. ρ̂, the emissive
//! colour and the MIP maximum then have closed forms. The sorted colour is a
//! sum over pieces, front to back, of `exp(−depth so far) · C_piece`; each
//! `C_piece` is integrated by adaptive Gauss–Kronrod (7/15 points, relative
//! tolerance 1e-13) on sub-intervals of optical depth ≤ 1, found by inverting
//! the piece's quadratic optical depth. That split keeps the exponential
//! resolved however large `l ρ` is, and stops where the optical depth exceeds
//! 48 (what lies behind contributes less than e^−48 ≈ 1e-21 of κ). Every term
//! is non-negative, so the result is accurate to about 1e-13 relative.
//!
//! # Bad input
//!
//! Nothing here panics or returns NaN. A NaN scalar reads as 0 and scalars are
//! clamped to [0, 1] (as in [`TransferFunction::evaluate`]). A NaN or negative
//! `l` counts as 0 and gives a fully transparent zero in every mode (also MIP:
//! a segment of zero length is no segment); `l` above [`MAX_SEGMENT_LENGTH`]
//! (including +∞) is clamped to it.

use glam::{DVec3, DVec4};

use crate::optics::{OpticalMode, PremultipliedRgba};
use crate::transfer::TransferFunction;

/// The longest segment length taken literally, in world units; longer ones
/// (and +∞) are clamped to it. Far beyond any scene, small enough that
/// `l · ρ` stays finite for every finite f32 density.
pub const MAX_SEGMENT_LENGTH: f64 = 1e30;

/// Optical depth behind which the sorted colour integral stops (e^−48 ≈ 1.4e-21).
pub(crate) const DEPTH_CUTOFF: f64 = 48.0;

/// Optical depth of one Gauss–Kronrod starting interval.
const DEPTH_STEP: f64 = 1.0;

/// Relative tolerance of the adaptive quadrature.
const RELATIVE_TOLERANCE: f64 = 1e-13;

/// Deepest bisection of one starting interval.
const MAX_BISECTIONS: u32 = 16;

/// A piece of the segment on which κ and ρ are linear in the parameter `x`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Piece {
    /// Start of the piece in `x` ∈ [0, 1] (nearer the front).
    pub x0: f64,
    /// End of the piece in `x`, `x1 > x0`.
    pub x1: f64,
    /// κ at `x0`.
    pub kappa0: DVec3,
    /// κ at `x1`.
    pub kappa1: DVec3,
    /// ρ at `x0`, 1/world unit.
    pub rho0: f64,
    /// ρ at `x1`, 1/world unit.
    pub rho1: f64,
}

impl Piece {
    /// Width of the piece in `x`.
    pub fn width(&self) -> f64 {
        self.x1 - self.x0
    }

    /// `∫ ρ dx` over the piece (unit segment length).
    pub fn depth(&self) -> f64 {
        0.5 * self.width() * (self.rho0 + self.rho1)
    }

    /// `∫ κρ dx` over the piece (unit segment length), exact:
    /// `∫_0^1 (κ0 + (κ1 − κ0) t)(ρ0 + (ρ1 − ρ0) t) dt` times the width.
    pub fn emission(&self) -> DVec3 {
        let mean = (self.kappa0 * (2.0 * self.rho0 + self.rho1)
            + self.kappa1 * (self.rho0 + 2.0 * self.rho1))
            / 6.0;
        self.width() * mean
    }

    /// `∫_0^u ρ` from the piece's front (unit segment length).
    pub fn depth_at(&self, u: f64) -> f64 {
        self.rho0 * u + 0.5 * (self.rho1 - self.rho0) * u * u / self.width()
    }

    /// κ and ρ at local coordinate `u` ∈ [0, width].
    pub fn at(&self, u: f64) -> (DVec3, f64) {
        let t = if self.width() > 0.0 {
            u / self.width()
        } else {
            0.0
        };
        (
            self.kappa0.lerp(self.kappa1, t),
            self.rho0 + (self.rho1 - self.rho0) * t,
        )
    }

    /// The local coordinate `u` ∈ [0, width] where `∫_0^u ρ = depth`, for
    /// `0 ≤ depth ≤ self.depth()` (the inverse of a monotone quadratic).
    pub fn u_at_depth(&self, depth: f64) -> f64 {
        // ∫_0^u ρ = p u + q u²
        let w = self.width();
        let p = self.rho0;
        let q = 0.5 * (self.rho1 - self.rho0) / w;
        let denominator = p + (p * p + 4.0 * q * depth).max(0.0).sqrt();
        if depth <= 0.0 || denominator <= 0.0 {
            return 0.0;
        }
        (2.0 * depth / denominator).clamp(0.0, w)
    }
}

/// Replaces NaN by 0 and clamps to [0, 1].
pub(crate) fn sanitize_scalar(s: f64) -> f64 {
    if s.is_nan() { 0.0 } else { s.clamp(0.0, 1.0) }
}

/// Replaces NaN and negative lengths by 0 and clamps to [`MAX_SEGMENT_LENGTH`].
pub(crate) fn sanitize_length(l: f64) -> f64 {
    if l.is_nan() || l <= 0.0 {
        0.0
    } else {
        l.min(MAX_SEGMENT_LENGTH)
    }
}

/// Calls `visit` with the pieces of the segment from `s_front` to `s_back` in
/// front-to-back order, split at the transfer function's control points.
/// Scalars must be sanitized. Pieces have positive width and cover [0, 1].
pub(crate) fn for_each_piece(
    tf: &TransferFunction,
    s_front: f64,
    s_back: f64,
    mut visit: impl FnMut(Piece),
) {
    if s_front == s_back {
        let sample = tf.evaluate(s_front);
        visit(Piece {
            x0: 0.0,
            x1: 1.0,
            kappa0: sample.kappa,
            kappa1: sample.kappa,
            rho0: sample.rho,
            rho1: sample.rho,
        });
        return;
    }
    let points = tf.points();
    let (lo, hi) = (s_front.min(s_back), s_front.max(s_back));
    let first = points.partition_point(|p| f64::from(p.s) <= lo);
    let last = points.partition_point(|p| f64::from(p.s) < hi).max(first);
    let inner = points[first..last].iter().map(|p| f64::from(p.s));
    let span = s_back - s_front;
    let to_x = |s: f64| {
        if s == s_front {
            0.0
        } else if s == s_back {
            1.0
        } else {
            ((s - s_front) / span).clamp(0.0, 1.0)
        }
    };
    // A piece in s between two consecutive breakpoints, read from the transfer
    // function segment that contains its midpoint (right of a step, the step's
    // second point; left of it, the first).
    let piece = |a: f64, b: f64| {
        let mid = 0.5 * (a + b);
        let upper = points.partition_point(|p| f64::from(p.s) <= mid);
        let (ka, ra, kb, rb) = if upper == 0 || upper == points.len() {
            let p = &points[upper.min(points.len() - 1)];
            let k = DVec3::from(p.kappa.map(f64::from));
            (k, f64::from(p.rho), k, f64::from(p.rho))
        } else {
            let (p, n) = (&points[upper - 1], &points[upper]);
            let (ps, ns) = (f64::from(p.s), f64::from(n.s));
            let kp = DVec3::from(p.kappa.map(f64::from));
            let kn = DVec3::from(n.kappa.map(f64::from));
            let (rp, rn) = (f64::from(p.rho), f64::from(n.rho));
            let ta = (a - ps) / (ns - ps);
            let tb = (b - ps) / (ns - ps);
            (
                kp.lerp(kn, ta),
                rp + (rn - rp) * ta,
                kp.lerp(kn, tb),
                rp + (rn - rp) * tb,
            )
        };
        // Orient front to back.
        if span > 0.0 {
            Piece {
                x0: to_x(a),
                x1: to_x(b),
                kappa0: ka,
                kappa1: kb,
                rho0: ra,
                rho1: rb,
            }
        } else {
            Piece {
                x0: to_x(b),
                x1: to_x(a),
                kappa0: kb,
                kappa1: ka,
                rho0: rb,
                rho1: ra,
            }
        }
    };
    let mut emit = |a: f64, b: f64| {
        if b > a {
            let p = piece(a, b);
            if p.x1 > p.x0 {
                visit(p);
            }
        }
    };
    if span > 0.0 {
        let mut previous = lo;
        for s in inner {
            emit(previous, s);
            previous = s;
        }
        emit(previous, hi);
    } else {
        let mut next = hi;
        for s in inner.rev() {
            emit(s, next);
            next = s;
        }
        emit(lo, next);
    }
}

/// The exact mean density `ρ̂ = ∫_0^1 ρ(s_f + x (s_b − s_f)) dx` in 1/world
/// unit (Röttger 2004 eq. 9.1), in closed form: `α = 1 − exp(−l ρ̂)`.
///
/// Scalars are sanitized as in [`exact_segment`]; ρ̂ is symmetric in its two
/// arguments.
pub fn rho_hat(tf: &TransferFunction, s_front: f64, s_back: f64) -> f64 {
    let (s_front, s_back) = (sanitize_scalar(s_front), sanitize_scalar(s_back));
    let mut sum = 0.0;
    for_each_piece(tf, s_front, s_back, |p| sum += p.depth());
    sum
}

/// The exact premultiplied colour (`xyz`) and opacity (`w`) of one ray segment
/// of length `length` (world units) along which the scalar goes linearly from
/// `s_front` to `s_back`, in the given optical mode (see the [module docs](self)
/// for the integrals, the accuracy and how bad input is clamped).
pub fn exact_segment(
    tf: &TransferFunction,
    mode: OpticalMode,
    s_front: f64,
    s_back: f64,
    length: f64,
) -> PremultipliedRgba {
    let (s_front, s_back) = (sanitize_scalar(s_front), sanitize_scalar(s_back));
    let l = sanitize_length(length);
    if l == 0.0 {
        return DVec4::ZERO;
    }
    match mode {
        OpticalMode::Sorted => {
            let mut depth = 0.0;
            let mut colour = DVec3::ZERO;
            for_each_piece(tf, s_front, s_back, |piece| {
                let piece_depth = l * piece.depth();
                if depth < DEPTH_CUTOFF && piece_depth > 0.0 {
                    colour += (-depth).exp() * sorted_piece_colour(&piece, l);
                }
                depth += piece_depth;
            });
            colour.extend(-(-depth).exp_m1())
        }
        OpticalMode::Emissive => {
            let mut emission = DVec3::ZERO;
            let mut depth = 0.0;
            for_each_piece(tf, s_front, s_back, |p| {
                emission += p.emission();
                depth += p.depth();
            });
            (l * emission).extend(-(-l * depth).exp_m1())
        }
        OpticalMode::Mip => {
            let mut maximum = DVec3::ZERO;
            let mut rho_max: f64 = 0.0;
            for_each_piece(tf, s_front, s_back, |p| {
                maximum = maximum.max(piece_max_emission(&p));
                rho_max = rho_max.max(p.rho0).max(p.rho1);
            });
            maximum.extend(-(-l * rho_max).exp_m1())
        }
    }
}

/// Per-channel maximum of `E = κρ` on a piece: each channel is a quadratic in
/// the piece parameter, so the maximum is at an end or at a concave vertex.
pub(crate) fn piece_max_emission(p: &Piece) -> DVec3 {
    let dk = p.kappa1 - p.kappa0;
    let dr = p.rho1 - p.rho0;
    let ends = (p.kappa0 * p.rho0).max(p.kappa1 * p.rho1);
    let vertex = |k0: f64, dk: f64| {
        // e(t) = k0 r0 + (k0 dr + dk r0) t + dk dr t²
        let (b, a) = (k0 * dr + dk * p.rho0, dk * dr);
        if a < 0.0 {
            let t = -b / (2.0 * a);
            if t > 0.0 && t < 1.0 {
                return (k0 + dk * t) * (p.rho0 + dr * t);
            }
        }
        0.0
    };
    ends.max(DVec3::new(
        vertex(p.kappa0.x, dk.x),
        vertex(p.kappa0.y, dk.y),
        vertex(p.kappa0.z, dk.z),
    ))
}

/// `l ∫ κ ρ exp(−l ∫_0^u ρ) du` over one piece, from the piece's own front.
fn sorted_piece_colour(piece: &Piece, l: f64) -> DVec3 {
    attenuated_emission(piece, l, |u| {
        let (kappa, rho) = piece.at(u);
        kappa * rho
    })
}

/// `l ∫ e(u) exp(−l ∫_0^u ρ) du` over the local coordinate `u` ∈ [0, width]
/// of `absorption` (whose ρ is the density that attenuates; its κ is unused),
/// for an emission `e` smooth on the piece: adaptive Gauss–Kronrod on
/// intervals of optical depth at most [`DEPTH_STEP`], up to [`DEPTH_CUTOFF`].
pub(crate) fn attenuated_emission(
    absorption: &Piece,
    l: f64,
    emission: impl Fn(f64) -> DVec3,
) -> DVec3 {
    let piece = absorption;
    let total = l * piece.depth();
    let reach = total.min(DEPTH_CUTOFF);
    let intervals = (reach / DEPTH_STEP).ceil().max(1.0) as u32;
    let integrand = |u: f64| emission(u) * (l * (-l * piece.depth_at(u)).exp());
    let mut colour = DVec3::ZERO;
    let mut a = 0.0;
    for i in 1..=intervals {
        let b = if i == intervals && total <= DEPTH_CUTOFF {
            piece.width()
        } else {
            piece.u_at_depth(reach * f64::from(i) / f64::from(intervals) / l)
        };
        if b > a {
            colour += adaptive_kronrod(&integrand, a, b, MAX_BISECTIONS);
        }
        a = b;
    }
    colour
}

/// Abscissae of the 15-point Kronrod rule on [−1, 1] (QUADPACK qk15), from the
/// outside in; the odd ones are the 7-point Gauss nodes.
const KRONROD_NODES: [f64; 8] = [
    0.991_455_371_120_812_6,
    0.949_107_912_342_758_5,
    0.864_864_423_359_769_1,
    0.741_531_185_599_394_4,
    0.586_087_235_467_691_1,
    0.405_845_151_377_397_2,
    0.207_784_955_007_898_5,
    0.0,
];

/// Weights of the 15-point Kronrod rule, matching [`KRONROD_NODES`].
const KRONROD_WEIGHTS: [f64; 8] = [
    0.022_935_322_010_529_22,
    0.063_092_092_629_978_55,
    0.104_790_010_322_250_2,
    0.140_653_259_715_525_9,
    0.169_004_726_639_267_9,
    0.190_350_578_064_785_4,
    0.204_432_940_075_298_9,
    0.209_482_141_084_727_8,
];

/// Weights of the 7-point Gauss rule at `KRONROD_NODES[1], [3], [5], [7]`.
const GAUSS_WEIGHTS: [f64; 4] = [
    0.129_484_966_168_869_7,
    0.279_705_391_489_276_7,
    0.381_830_050_505_118_9,
    0.417_959_183_673_469_4,
];

/// Adaptive Gauss–Kronrod 7/15 of a vector integrand over [a, b].
fn adaptive_kronrod(f: &impl Fn(f64) -> DVec3, a: f64, b: f64, depth: u32) -> DVec3 {
    let centre = 0.5 * (a + b);
    let half = 0.5 * (b - a);
    let mut kronrod = f(centre) * KRONROD_WEIGHTS[7];
    let mut gauss = f(centre) * GAUSS_WEIGHTS[3];
    for i in 0..7 {
        let dx = half * KRONROD_NODES[i];
        let pair = f(centre - dx) + f(centre + dx);
        kronrod += pair * KRONROD_WEIGHTS[i];
        if i % 2 == 1 {
            gauss += pair * GAUSS_WEIGHTS[i / 2];
        }
    }
    kronrod *= half;
    gauss *= half;
    let error = (kronrod - gauss).abs().max_element();
    if error <= RELATIVE_TOLERANCE * kronrod.abs().max_element() || error < 1e-300 || depth == 0 {
        return kronrod;
    }
    adaptive_kronrod(f, a, centre, depth - 1) + adaptive_kronrod(f, centre, b, depth - 1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::arbitrary_transfer_function;
    use crate::transfer::ControlPoint;
    use proptest::prelude::*;

    fn point(s: f32, kappa: [f32; 3], rho: f32) -> ControlPoint {
        ControlPoint { s, kappa, rho }
    }

    fn ramp() -> TransferFunction {
        TransferFunction::new([
            point(0.0, [1.0, 0.2, 0.0], 0.0),
            point(0.3, [0.5, 0.8, 0.1], 2.0),
            point(0.3, [0.5, 0.8, 0.1], 0.5),
            point(0.7, [0.1, 0.3, 1.0], 3.0),
            point(1.0, [0.9, 0.9, 0.9], 1.0),
        ])
        .unwrap()
    }

    /// Brute-force composite Simpson of the sorted integral in t, independent
    /// of the piece machinery.
    fn brute_sorted(tf: &TransferFunction, s_f: f64, s_b: f64, l: f64) -> DVec4 {
        let n = 200_000;
        let h = l / f64::from(n);
        let s_at = |t: f64| s_f + (s_b - s_f) * t / l;
        // Optical depth by trapezoids on a grid twice as fine, then Simpson on C.
        let mut depth = 0.0;
        let mut previous_rho = tf.evaluate(s_f).rho;
        let mut colour = DVec3::ZERO;
        let mut previous = tf.evaluate(s_f).emission();
        for i in 0..n {
            let t0 = f64::from(i) * h;
            let mid = tf.evaluate(s_at(t0 + 0.5 * h));
            let end = tf.evaluate(s_at(t0 + h));
            let depth_mid = depth + 0.25 * h * (previous_rho + mid.rho);
            let depth_end = depth_mid + 0.25 * h * (mid.rho + end.rho);
            colour += h / 6.0
                * ((-depth).exp() * previous
                    + 4.0 * (-depth_mid).exp() * mid.emission()
                    + (-depth_end).exp() * end.emission());
            depth = depth_end;
            previous_rho = end.rho;
            previous = end.emission();
        }
        colour.extend(1.0 - (-depth).exp())
    }

    #[test]
    fn zero_length_is_transparent_in_every_mode() {
        let tf = ramp();
        for mode in [OpticalMode::Sorted, OpticalMode::Emissive, OpticalMode::Mip] {
            for l in [0.0, -1.0, f64::NAN, f64::NEG_INFINITY] {
                assert_eq!(exact_segment(&tf, mode, 0.2, 0.9, l), DVec4::ZERO);
            }
        }
    }

    #[test]
    fn bad_input_never_gives_nan() {
        let tf = ramp();
        for mode in [OpticalMode::Sorted, OpticalMode::Emissive, OpticalMode::Mip] {
            for (s_f, s_b) in [
                (f64::NAN, 0.5),
                (-3.0, 7.0),
                (f64::INFINITY, f64::NEG_INFINITY),
            ] {
                for l in [1e-300, 1.0, 1e12, f64::INFINITY] {
                    let c = exact_segment(&tf, mode, s_f, s_b, l);
                    assert!(c.is_finite(), "{mode:?} {s_f} {s_b} {l}: {c}");
                    assert!((0.0..=1.0).contains(&c.w));
                }
            }
        }
        let opaque = exact_segment(&tf, OpticalMode::Sorted, 0.5, 0.5, f64::INFINITY);
        assert_eq!(opaque.w, 1.0);
    }

    #[test]
    fn diagonal_is_closed_form() {
        let tf = ramp();
        for s in [0.0, 0.15, 0.3, 0.5, 0.99] {
            for l in [1e-6, 0.1, 1.0, 10.0, 1000.0] {
                let sample = tf.evaluate(s);
                let alpha = -(-l * sample.rho).exp_m1();
                let c = exact_segment(&tf, OpticalMode::Sorted, s, s, l);
                assert!((c.w - alpha).abs() <= 1e-15, "{s} {l}");
                let expected = sample.kappa * alpha;
                assert!(
                    (c.truncate() - expected).abs().max_element()
                        <= 1e-13 * expected.max_element().max(1e-300),
                    "{s} {l}: {c} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn constant_density_is_closed_form() {
        // κ linear in s, ρ constant: C = ρ ∫_0^l κ(t) e^{−ρt} dt, done by hand.
        let tf = TransferFunction::new([
            point(0.0, [0.0, 1.0, 0.5], 2.0),
            point(1.0, [1.0, 0.0, 0.5], 2.0),
        ])
        .unwrap();
        let (rho, l) = (2.0_f64, 1.5_f64);
        // κ(t) = κ0 + (κ1 − κ0) t / l along s from 0 to 1.
        let k0 = DVec3::new(0.0, 1.0, 0.5);
        let dk = DVec3::new(1.0, -1.0, 0.0) / l;
        let e = (-rho * l).exp();
        // ∫_0^l ρ e^{−ρt} dt = 1 − e ; ∫_0^l ρ t e^{−ρt} dt = (1 − e − ρ l e) / ρ
        let expected = k0 * (1.0 - e) + dk * ((1.0 - e - rho * l * e) / rho);
        let c = exact_segment(&tf, OpticalMode::Sorted, 0.0, 1.0, l);
        assert!(
            (c.truncate() - expected).abs().max_element() < 1e-14,
            "{c} {expected}"
        );
        assert!((c.w - (1.0 - e)).abs() < 1e-15);
        let emissive = exact_segment(&tf, OpticalMode::Emissive, 0.0, 1.0, l);
        assert!(
            (emissive.truncate() - DVec3::new(0.5, 0.5, 0.5) * rho * l)
                .abs()
                .max_element()
                < 1e-14
        );
    }

    #[test]
    fn matches_brute_force_integration() {
        // Kinks but no step: Simpson's rule converges as h² there.
        let tf = TransferFunction::new([
            point(0.0, [1.0, 0.2, 0.0], 0.0),
            point(0.3, [0.5, 0.8, 0.1], 2.0),
            point(0.7, [0.1, 0.3, 1.0], 3.0),
            point(1.0, [0.9, 0.9, 0.9], 1.0),
        ])
        .unwrap();
        for (s_f, s_b, l) in [
            (0.0, 1.0, 1.0),
            (0.9, 0.1, 3.0),
            (0.3, 0.3001, 0.5),
            (0.25, 0.75, 0.05),
        ] {
            let exact = exact_segment(&tf, OpticalMode::Sorted, s_f, s_b, l);
            let brute = brute_sorted(&tf, s_f, s_b, l);
            assert!(
                (exact - brute).abs().max_element() < 1e-9,
                "{exact} {brute}"
            );
        }
    }

    #[test]
    fn huge_optical_depth_still_resolves_the_front() {
        // l ρ = 1e8: the colour is κ at the very front.
        let tf = ramp();
        let c = exact_segment(&tf, OpticalMode::Sorted, 0.5, 0.9, 1e8);
        let front = tf.evaluate(0.5).kappa;
        assert!(
            (c.truncate() - front).abs().max_element() < 1e-6,
            "{c} {front}"
        );
        assert_eq!(c.w, 1.0);
    }

    #[test]
    fn narrow_peak_is_a_heaviside_isosurface() {
        // Röttger 2004 §8.13: ρ = C δ(s − 0.5) with a large C; κ is red at the peak.
        let (eps, peak) = (1e-5_f32, 1e7_f32);
        let tf = TransferFunction::new([
            point(0.0, [0.0, 0.0, 1.0], 0.0),
            point(0.5 - eps, [1.0, 0.0, 0.0], 0.0),
            point(0.5, [1.0, 0.0, 0.0], peak),
            point(0.5 + eps, [1.0, 0.0, 0.0], 0.0),
            point(1.0, [0.0, 0.0, 1.0], 0.0),
        ])
        .unwrap();
        for (s_f, s_b) in [(0.2, 0.8), (0.9, 0.3), (0.45, 0.55)] {
            for l in [0.5, 1.0, 20.0] {
                let c = exact_segment(&tf, OpticalMode::Sorted, s_f, s_b, l);
                assert!(c.w > 1.0 - 1e-12, "crossing {s_f} {s_b} {l}: {c}");
                assert!((c.truncate() - DVec3::X).abs().max_element() < 1e-9, "{c}");
            }
        }
        for (s_f, s_b) in [(0.1, 0.4), (0.6, 0.99), (0.2, 0.2)] {
            let c = exact_segment(&tf, OpticalMode::Sorted, s_f, s_b, 10.0);
            assert_eq!(c, DVec4::ZERO, "missing {s_f} {s_b}");
        }
    }

    #[test]
    fn mip_takes_the_maximum_emission() {
        // E_red = κ ρ with κ falling and ρ rising: an interior maximum.
        let tf = TransferFunction::new([
            point(0.0, [1.0, 0.0, 0.0], 0.0),
            point(1.0, [0.0, 0.0, 0.0], 1.0),
        ])
        .unwrap();
        // E(s) = (1 − s) s, maximum 1/4 at s = 1/2.
        let c = exact_segment(&tf, OpticalMode::Mip, 0.1, 0.9, 2.0);
        assert!((c.x - 0.25).abs() < 1e-15);
        assert!((c.w - (1.0 - (-2.0 * 0.9_f64).exp())).abs() < 1e-15);
        let c = exact_segment(&tf, OpticalMode::Mip, 0.7, 0.6, 2.0);
        assert!((c.x - 0.6 * 0.4).abs() < 1e-15);
    }

    #[test]
    fn rho_hat_is_exact_and_symmetric() {
        let tf = ramp();
        // ∫_0^1 ρ ds by hand: 0.3·(0+2)/2 + 0.4·(0.5+3)/2 + 0.3·(3+1)/2
        let expected = 0.3 + 0.7 + 0.6;
        // (0.3 and 0.7 are f32 control points, hence the tolerance).
        assert!((rho_hat(&tf, 0.0, 1.0) - expected).abs() < 1e-7);
        assert_eq!(rho_hat(&tf, 0.0, 1.0), rho_hat(&tf, 1.0, 0.0));
        assert_eq!(rho_hat(&tf, 0.5, 0.5), tf.evaluate(0.5).rho);
    }

    proptest! {
        #[test]
        fn sorted_segments_are_bounded_and_monotone(
            tf in arbitrary_transfer_function(1..8, 2.0, 8.0),
            s_f in 0.0_f64..=1.0,
            s_b in 0.0_f64..=1.0,
            l in 0.0_f64..50.0,
            extra in 0.0_f64..50.0,
        ) {
            let c = exact_segment(&tf, OpticalMode::Sorted, s_f, s_b, l);
            prop_assert!(c.is_finite());
            prop_assert!((0.0..=1.0).contains(&c.w));
            let bound = c.w * f64::from(tf.max_chromaticity());
            prop_assert!(c.truncate().max_element() <= bound * (1.0 + 1e-12) + 1e-15);
            prop_assert!(c.truncate().min_element() >= 0.0);
            let longer = exact_segment(&tf, OpticalMode::Sorted, s_f, s_b, l + extra);
            prop_assert!(longer.w >= c.w);
            for mode in [OpticalMode::Emissive, OpticalMode::Mip] {
                let other = exact_segment(&tf, mode, s_f, s_b, l);
                prop_assert!(other.is_finite() && (0.0..=1.0).contains(&other.w));
                prop_assert!((other.w - c.w).abs() < 1e-12 || mode == OpticalMode::Mip);
            }
        }
    }
}
