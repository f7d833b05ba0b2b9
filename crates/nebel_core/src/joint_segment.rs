//! The exact ray integral of several media that share one segment, in f64:
//! the reference for volumes that interpenetrate.
//!
//! Over a segment of length `l` (`x = t / l` in [0, 1]) medium `i` has a scalar
//! going linearly from `s_f,i` to `s_b,i`, its density scaled by `m_i` (a lit
//! cloud's modulator), and emits `e_i = m_i ρ_i (w_i κ_i + a_i)`: `w = 1, a = 0`
//! unlit, the sunlight and ambient weights of single scattering when lit.
//! Emission and absorption add (Röttger 2004 eq. 8.1 with both as sums):
//!
//! `C = l ∫_0^1 Σ_i e_i(x) exp(−l ∫_0^x Σ_j m_j ρ_j(u) du) dx`,
//! `α = 1 − exp(−l Σ_j m_j ρ̂_j)`,
//!
//! `j` over the absorbing media only: an emissive medium (Röttger 2004 §10.3)
//! emits and is attenuated but does not absorb.
//!
//! The segment is split at every medium's transfer-function control points, so
//! on each piece every κ and ρ is linear in `x`; each piece is integrated as
//! [`crate::segment`] integrates one medium (adaptive Gauss–Kronrod on
//! intervals of optical depth at most 1), so one absorbing medium alone gives
//! [`crate::segment::exact_segment`] to rounding.
//!
//! Bad input is clamped as in [`crate::segment`]; a NaN or negative density
//! scale counts as 0, one above [`MAX_DENSITY_SCALE`] is clamped to it.

use glam::{DVec3, DVec4};

use crate::optics::PremultipliedRgba;
use crate::segment::{
    DEPTH_CUTOFF, Piece, attenuated_emission, for_each_piece, sanitize_length, sanitize_scalar,
};
use crate::transfer::TransferFunction;

/// The largest density scale taken literally.
pub const MAX_DENSITY_SCALE: f64 = 1e6;

/// One medium's share of a segment (see the [module docs](self)).
#[derive(Clone, Copy, Debug)]
pub struct JointMedium<'a> {
    /// κ and ρ over the medium's scalar.
    pub transfer_function: &'a TransferFunction,
    /// The scalar at the segment's front.
    pub s_front: f64,
    /// The scalar at the segment's back.
    pub s_back: f64,
    /// `m`, the factor on the medium's density, ≥ 0. Default 1.
    pub density_scale: f64,
    /// Whether the medium absorbs (sorted) or only emits (emissive). Default
    /// `true`.
    pub absorbs: bool,
    /// `w`, the weight of the coloured emission `κρ`. Default 1.
    pub emission_weight: f64,
    /// `a`, the weight per channel of the emission `ρ` (the sky's light,
    /// not coloured by κ). Default 0.
    pub ambient: DVec3,
}

impl<'a> JointMedium<'a> {
    /// An unlit, unscaled, absorbing medium.
    pub fn new(transfer_function: &'a TransferFunction, s_front: f64, s_back: f64) -> Self {
        Self {
            transfer_function,
            s_front,
            s_back,
            density_scale: 1.0,
            absorbs: true,
            emission_weight: 1.0,
            ambient: DVec3::ZERO,
        }
    }
}

/// The exact premultiplied colour and opacity of `media` sharing one segment of
/// `length` world units (see the [module docs](self)).
pub fn exact_joint_segment(media: &[JointMedium<'_>], length: f64) -> PremultipliedRgba {
    let l = sanitize_length(length);
    if l == 0.0 || media.is_empty() {
        return DVec4::ZERO;
    }
    let pieces: Vec<Vec<Piece>> = media
        .iter()
        .map(|medium| {
            let mut pieces = Vec::new();
            for_each_piece(
                medium.transfer_function,
                sanitize_scalar(medium.s_front),
                sanitize_scalar(medium.s_back),
                |piece| pieces.push(piece),
            );
            pieces
        })
        .collect();
    let scales: Vec<f64> = media
        .iter()
        .map(|medium| sanitize_scale(medium.density_scale))
        .collect();
    let mut cuts: Vec<f64> = pieces
        .iter()
        .flatten()
        .flat_map(|piece| [piece.x0, piece.x1])
        .chain([0.0, 1.0])
        .collect();
    cuts.sort_by(f64::total_cmp);
    cuts.dedup();

    let mut cursors = vec![0; media.len()];
    let mut local = Vec::with_capacity(media.len());
    let (mut depth, mut colour) = (0.0, DVec3::ZERO);
    for window in cuts.windows(2) {
        let (xa, xb) = (window[0], window[1]);
        let mid = 0.5 * (xa + xb);
        // Every medium's linear piece over [xa, xb].
        local.clear();
        for (i, medium) in media.iter().enumerate() {
            let own = &pieces[i];
            while cursors[i] + 1 < own.len() && own[cursors[i]].x1 <= mid {
                cursors[i] += 1;
            }
            if let Some(piece) = own.get(cursors[i]) {
                local.push((restrict(piece, xa, xb), medium, scales[i]));
            }
        }
        let absorbing = |at: fn(&Piece) -> f64| {
            local
                .iter()
                .filter(|(_, medium, _)| medium.absorbs)
                .map(|(piece, _, scale)| scale * at(piece))
                .sum::<f64>()
        };
        let absorption = Piece {
            x0: xa,
            x1: xb,
            kappa0: DVec3::ZERO,
            kappa1: DVec3::ZERO,
            rho0: absorbing(|piece| piece.rho0),
            rho1: absorbing(|piece| piece.rho1),
        };
        if depth < DEPTH_CUTOFF {
            let emission = |u: f64| {
                local
                    .iter()
                    .map(|(piece, medium, scale)| {
                        let (kappa, rho) = piece.at(u);
                        scale * rho * (medium.emission_weight * kappa + medium.ambient)
                    })
                    .sum::<DVec3>()
            };
            colour += (-depth).exp() * attenuated_emission(&absorption, l, emission);
        }
        depth += l * absorption.depth();
    }
    colour.extend(-(-depth).exp_m1())
}

/// `piece` over `[x0, x1]` ⊆ its own range, still linear.
fn restrict(piece: &Piece, x0: f64, x1: f64) -> Piece {
    let (kappa0, rho0) = piece.at(x0 - piece.x0);
    let (kappa1, rho1) = piece.at(x1 - piece.x0);
    Piece {
        x0,
        x1,
        kappa0,
        kappa1,
        rho0,
        rho1,
    }
}

/// Replaces NaN and negative scales by 0 and clamps to [`MAX_DENSITY_SCALE`].
fn sanitize_scale(scale: f64) -> f64 {
    if scale.is_nan() || scale <= 0.0 {
        0.0
    } else {
        scale.min(MAX_DENSITY_SCALE)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::OpticalMode;
    use crate::segment::exact_segment;
    use crate::test_support::arbitrary_transfer_function;
    use crate::transfer::ControlPoint;
    use proptest::prelude::*;

    fn uniform(kappa: [f32; 3], rho: f32) -> TransferFunction {
        TransferFunction::new([ControlPoint { s: 0.5, kappa, rho }]).unwrap()
    }

    fn close(a: DVec4, b: DVec4, relative: f64) -> bool {
        (a - b).abs().max_element() <= relative * a.abs().max_element().max(1e-12)
    }

    #[test]
    fn two_uniform_media_mix_their_colours_by_density() {
        let (ka, ra) = (DVec3::new(1.0, 0.2, 0.1), 0.7);
        let (kb, rb) = (DVec3::new(0.1, 0.3, 0.9), 2.2);
        let a = uniform(ka.as_vec3().to_array(), ra as f32);
        let b = uniform(kb.as_vec3().to_array(), rb as f32);
        let (ra, rb) = (f64::from(ra as f32), f64::from(rb as f32));
        let (ka, kb) = (ka.as_vec3().as_dvec3(), kb.as_vec3().as_dvec3());
        for l in [1e-4, 0.3, 1.0, 7.0, 200.0] {
            let joint = exact_joint_segment(
                &[
                    JointMedium::new(&a, 0.5, 0.5),
                    JointMedium::new(&b, 0.5, 0.5),
                ],
                l,
            );
            let alpha = -(-(ra + rb) * l).exp_m1();
            let expected = ((ka * ra + kb * rb) / (ra + rb) * alpha).extend(alpha);
            assert!(close(joint, expected, 1e-12), "{l}: {joint} vs {expected}");
        }
    }

    #[test]
    fn an_emissive_medium_is_attenuated_by_the_absorbing_one() {
        let (ke, re) = (DVec3::new(1.0, 0.5, 0.1), 0.8);
        let (ka, ra) = (DVec3::new(0.2, 0.2, 0.2), 1.5);
        let fire = uniform(ke.as_vec3().to_array(), re as f32);
        let smoke = uniform(ka.as_vec3().to_array(), ra as f32);
        let (re, ra) = (f64::from(re as f32), f64::from(ra as f32));
        let (ke, ka) = (ke.as_vec3().as_dvec3(), ka.as_vec3().as_dvec3());
        let emissive = JointMedium {
            absorbs: false,
            ..JointMedium::new(&fire, 0.5, 0.5)
        };
        for l in [0.01, 1.0, 5.0] {
            let joint = exact_joint_segment(&[emissive, JointMedium::new(&smoke, 0.5, 0.5)], l);
            let alpha = -(-ra * l).exp_m1();
            let expected = (ke * re * alpha / ra + ka * alpha).extend(alpha);
            assert!(close(joint, expected, 1e-12), "{l}: {joint} vs {expected}");
            let alone = exact_joint_segment(&[emissive], l);
            let emitted = exact_segment(&fire, OpticalMode::Emissive, 0.5, 0.5, l);
            assert!(close(alone, emitted.truncate().extend(0.0), 1e-12));
        }
    }

    #[test]
    fn bad_input_never_gives_nan() {
        let tf = uniform([1.0, 1.0, 1.0], 2.0);
        for scale in [f64::NAN, -1.0, 0.0, 1e300, f64::INFINITY] {
            for l in [f64::NAN, -1.0, 0.0, 1e-300, 1.0, f64::INFINITY] {
                let medium = JointMedium {
                    density_scale: scale,
                    ..JointMedium::new(&tf, f64::NAN, 7.0)
                };
                let c = exact_joint_segment(&[medium, medium], l);
                assert!(
                    c.is_finite() && (0.0..=1.0).contains(&c.w),
                    "{scale} {l}: {c}"
                );
            }
        }
        assert_eq!(exact_joint_segment(&[], 1.0), DVec4::ZERO);
    }

    proptest! {
        #[test]
        fn one_medium_alone_is_the_exact_segment(
            tf in arbitrary_transfer_function(1..8, 2.0, 8.0),
            s_f in 0.0_f64..=1.0,
            s_b in 0.0_f64..=1.0,
            l in 0.0_f64..20.0,
            ambient in prop::array::uniform3(0.0_f64..1.0),
            weight in 0.0_f64..2.0,
        ) {
            let ambient = DVec3::from_array(ambient);
            let medium = JointMedium { ambient, emission_weight: weight, ..JointMedium::new(&tf, s_f, s_b) };
            let joint = exact_joint_segment(&[medium], l);
            let alone = exact_segment(&tf, OpticalMode::Sorted, s_f, s_b, l);
            let lit = (ambient * alone.w + weight * alone.truncate()).extend(alone.w);
            prop_assert!(close(joint, lit, 1e-10), "{joint} vs {lit}");
        }

        #[test]
        fn a_medium_split_in_two_halves_is_the_medium(
            tf in arbitrary_transfer_function(1..8, 2.0, 8.0),
            other in arbitrary_transfer_function(1..8, 2.0, 8.0),
            s_f in 0.0_f64..=1.0,
            s_b in 0.0_f64..=1.0,
            l in 0.0_f64..20.0,
        ) {
            // Half the density twice is the medium once, whatever else shares
            // the segment, and the order of the media does not matter.
            let half = JointMedium { density_scale: 0.5, ..JointMedium::new(&tf, s_f, s_b) };
            let third = JointMedium::new(&other, s_b, s_f);
            let split = exact_joint_segment(&[half, third, half], l);
            let whole = exact_joint_segment(&[third, JointMedium::new(&tf, s_f, s_b)], l);
            prop_assert!(close(split, whole, 1e-10), "{split} vs {whole}");
        }
    }
}
