//! The joint composite of volumes that overlap along a ray, each known only by
//! what it gives alone and where along the ray it lies: how the GPU merges
//! batches whose bounds intersect, per pixel.
//!
//! Each volume `k` is summarised by its premultiplied colour `C_k`, its
//! transmittance `T_k` and its span `[a_k, b_k]` along the ray (its first
//! entry and last exit). Over its span it is taken as uniform: extinction
//! `σ_k = τ_k / (b_k − a_k)` with `τ_k = −ln T_k`, and emission
//! `j_k = C_k σ_k / (1 − T_k)` per unit length, which gives `(C_k, T_k)`
//! back for the volume alone (Röttger 2004 eq. 8.1 with constant κ and ρ).
//! The ray is split at every span's ends; on each piece the volumes present
//! absorb and emit together, `α = 1 − e^{−Σσ l}`, `C = (Σ j) l (1 − e^{−Σσ l})
//! / (Σσ l)`, and the pieces go front to back.
//!
//! This is exact where the volumes are uniform over their spans (the closed
//! forms of overlapping boxes of constant fog, an emissive box inside a
//! sorted one) and wherever the spans do not overlap, whatever the media:
//! then it is each volume whole, in its order along this ray. Elsewhere each
//! volume's medium is spread evenly over its span. An emissive volume has
//! `T = 1`: it emits without absorbing.
//!
//! Bad input is clamped: a NaN colour counts as 0, a transmittance outside
//! [0, 1] (or NaN) is clamped to it (NaN to 1), a span that is empty or not
//! finite contributes nothing, and a span shorter than [`MIN_SPAN`] relative
//! to its distance is widened to it.

use glam::DVec3;

use crate::optics::PremultipliedRgba;

/// The shortest span, relative to `1 + |a|`: a volume crossed at a grazing
/// angle keeps a finite extinction.
pub const MIN_SPAN: f64 = 1e-6;

/// The smallest transmittance taken literally: an opaque volume keeps a
/// finite optical depth (`−ln` of it, 69).
pub const MIN_TRANSMITTANCE: f64 = 1e-30;

/// One volume along one ray (see the [module docs](self)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RaySpan {
    /// The volume's premultiplied colour alone.
    pub colour: DVec3,
    /// The volume's transmittance alone, in [0, 1].
    pub transmittance: f64,
    /// Where along the ray the volume begins.
    pub entry: f64,
    /// Where along the ray the volume ends.
    pub exit: f64,
}

/// `τ / (1 − e^{−τ})`, 1 at τ = 0.
fn depth_per_opacity(tau: f64) -> f64 {
    if tau < 1e-4 {
        1.0 + 0.5 * tau
    } else {
        tau / -(-tau).exp_m1()
    }
}

/// A span's uniform medium: its extinction and emission per unit length and
/// its ends, or `None` where it contributes nothing.
fn medium(span: &RaySpan) -> Option<(f64, DVec3, f64, f64)> {
    if !(span.entry.is_finite() && span.exit.is_finite()) || span.exit < span.entry {
        return None;
    }
    let colour = DVec3::from_array(
        span.colour
            .to_array()
            .map(|c| if c.is_nan() { 0.0 } else { c }),
    );
    let transmittance = if span.transmittance.is_nan() {
        1.0
    } else {
        span.transmittance.clamp(MIN_TRANSMITTANCE, 1.0)
    };
    let exit = span
        .exit
        .max(span.entry + MIN_SPAN * (1.0 + span.entry.abs()));
    let length = exit - span.entry;
    let tau = -transmittance.ln();
    Some((
        tau / length,
        colour * depth_per_opacity(tau) / length,
        span.entry,
        exit,
    ))
}

/// The premultiplied colour and opacity of `spans` together (see the
/// [module docs](self)); the order of `spans` does not matter.
pub fn merge_spans(spans: &[RaySpan]) -> PremultipliedRgba {
    let media: Vec<_> = spans.iter().filter_map(medium).collect();
    let mut ends: Vec<f64> = media.iter().flat_map(|m| [m.2, m.3]).collect();
    ends.sort_by(f64::total_cmp);
    let mut colour = DVec3::ZERO;
    let mut transmittance = 1.0;
    for pair in ends.windows(2) {
        let (near, far) = (pair[0], pair[1]);
        let length = far - near;
        if length <= 0.0 {
            continue;
        }
        let (extinction, emission) = media
            .iter()
            .filter(|m| m.2 <= near && far <= m.3)
            .fold((0.0, DVec3::ZERO), |(s, j), m| (s + m.0, j + m.1));
        let tau = extinction * length;
        colour += transmittance * emission * length / depth_per_opacity(tau);
        transmittance *= (-tau).exp();
    }
    colour.extend(1.0 - transmittance)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::joint_segment::{JointMedium, exact_joint_segment};
    use crate::optics::OpticalMode;
    use crate::transfer::{ControlPoint, TransferFunction};
    use proptest::prelude::*;

    /// A uniform medium over `[entry, exit]` of chromaticity `kappa` and
    /// density `rho`, absorbing or only emitting.
    #[derive(Clone, Debug)]
    struct Box1d {
        transfer_function: TransferFunction,
        absorbs: bool,
        entry: f64,
        exit: f64,
    }

    fn box1d(kappa: [f32; 3], rho: f32, absorbs: bool, entry: f64, exit: f64) -> Box1d {
        Box1d {
            transfer_function: TransferFunction::new([ControlPoint { s: 0.5, kappa, rho }])
                .unwrap(),
            absorbs,
            entry,
            exit,
        }
    }

    fn joint(media: &[&Box1d], length: f64) -> PremultipliedRgba {
        let media: Vec<_> = media
            .iter()
            .map(|b| JointMedium {
                absorbs: b.absorbs,
                ..JointMedium::new(&b.transfer_function, 0.5, 0.5)
            })
            .collect();
        exact_joint_segment(&media, length)
    }

    /// The exact integral of the boxes together along the ray: split at
    /// every end, each piece the exact joint segment of the boxes there.
    fn exact(boxes: &[Box1d]) -> PremultipliedRgba {
        let mut ends: Vec<f64> = boxes.iter().flat_map(|b| [b.entry, b.exit]).collect();
        ends.sort_by(f64::total_cmp);
        let mut total = PremultipliedRgba::ZERO;
        for pair in ends.windows(2) {
            let present: Vec<&Box1d> = boxes
                .iter()
                .filter(|b| b.entry <= pair[0] && pair[1] <= b.exit)
                .collect();
            total = OpticalMode::Sorted.composite(total, joint(&present, pair[1] - pair[0]));
        }
        total
    }

    /// What one box gives alone, as its span.
    fn span(b: &Box1d) -> RaySpan {
        let alone = joint(&[b], b.exit - b.entry);
        RaySpan {
            colour: alone.truncate(),
            transmittance: 1.0 - alone.w,
            entry: b.entry,
            exit: b.exit,
        }
    }

    fn close(a: PremultipliedRgba, b: PremultipliedRgba) -> bool {
        (a - b).abs().max_element() <= 1e-9 * b.abs().max_element().max(1.0)
    }

    #[test]
    fn a_sorted_box_around_an_emissive_one() {
        let fog = box1d([0.3, 0.3, 0.35], 0.6, true, 1.0, 6.0);
        let fire = box1d([2.0, 0.8, 0.1], 1.5, false, 3.0, 4.0);
        let boxes = [fog, fire];
        let merged = merge_spans(&boxes.each_ref().map(span));
        let truth = exact(&boxes);
        assert!(close(merged, truth), "{merged} vs {truth}");
        // The fire is attenuated by the fog in front of it and in itself:
        // more than in front of the fog, less than behind it.
        let front = OpticalMode::Sorted.composite(span_rgba(&boxes[1]), span_rgba(&boxes[0]));
        let behind = OpticalMode::Sorted.composite(span_rgba(&boxes[0]), span_rgba(&boxes[1]));
        assert!(behind.x < merged.x && merged.x < front.x);
    }

    fn span_rgba(b: &Box1d) -> PremultipliedRgba {
        let s = span(b);
        s.colour.extend(1.0 - s.transmittance)
    }

    #[test]
    fn bad_input_never_gives_nan() {
        let good = RaySpan {
            colour: DVec3::splat(0.4),
            transmittance: 0.5,
            entry: 1.0,
            exit: 2.0,
        };
        for bad in [
            RaySpan {
                colour: DVec3::NAN,
                transmittance: f64::NAN,
                ..good
            },
            RaySpan {
                transmittance: 0.0,
                exit: 1.0,
                ..good
            },
            RaySpan {
                transmittance: -3.0,
                entry: f64::NEG_INFINITY,
                ..good
            },
            RaySpan {
                entry: 5.0,
                exit: f64::NAN,
                ..good
            },
            RaySpan {
                transmittance: 7.0,
                entry: 3.0,
                exit: 2.0,
                ..good
            },
        ] {
            let merged = merge_spans(&[good, bad]);
            assert!(
                merged.is_finite() && (0.0..=1.0).contains(&merged.w),
                "{bad:?}: {merged}"
            );
        }
        assert_eq!(merge_spans(&[]), PremultipliedRgba::ZERO);
    }

    /// An opaque span shorter than the shortest span stays opaque and keeps
    /// its colour.
    #[test]
    fn an_opaque_point_is_itself() {
        let point = RaySpan {
            colour: DVec3::new(0.2, 0.5, 0.1),
            transmittance: 0.0,
            entry: 4.0,
            exit: 4.0,
        };
        let merged = merge_spans(&[point]);
        assert!((merged - point.colour.extend(1.0)).abs().max_element() < 1e-12);
    }

    fn arbitrary_box() -> impl Strategy<Value = Box1d> {
        (
            prop::array::uniform3(0.0_f32..2.0),
            0.0_f32..3.0,
            prop::bool::weighted(0.7),
            0.0_f64..10.0,
            0.01_f64..6.0,
        )
            .prop_map(|(kappa, rho, absorbs, entry, length)| {
                box1d(kappa, rho, absorbs, entry, entry + length)
            })
    }

    proptest! {
        /// Uniform boxes, however they overlap: the merge is the exact joint
        /// integral.
        #[test]
        fn uniform_boxes_merge_exactly(boxes in prop::collection::vec(arbitrary_box(), 1..6)) {
            let spans: Vec<RaySpan> = boxes.iter().map(span).collect();
            let merged = merge_spans(&spans);
            let truth = exact(&boxes);
            prop_assert!(close(merged, truth), "{merged} vs {truth}");
        }

        /// Spans that do not overlap, whatever they hold, are each whole in
        /// their order along the ray, given in any order.
        #[test]
        fn disjoint_spans_composite_in_ray_order(
            pieces in prop::collection::vec(
                (prop::array::uniform3(0.0_f64..1.0), 0.0_f64..=1.0, 0.01_f64..3.0, 0.0_f64..1.0),
                1..6,
            ),
            rotate in 0_usize..6,
        ) {
            let mut at = 0.5;
            let mut spans = Vec::new();
            let mut expected = PremultipliedRgba::ZERO;
            for (colour, transmittance, length, gap) in pieces {
                // A premultiplied colour is at most its opacity per channel.
                let alpha = 1.0 - transmittance;
                let colour = DVec3::from_array(colour) * alpha;
                spans.push(RaySpan { colour, transmittance, entry: at, exit: at + length });
                expected = OpticalMode::Sorted.composite(expected, colour.extend(alpha));
                at += length + gap;
            }
            let turn = rotate % spans.len();
            spans.rotate_left(turn);
            let merged = merge_spans(&spans);
            prop_assert!(close(merged, expected), "{merged} vs {expected}");
        }
    }
}
