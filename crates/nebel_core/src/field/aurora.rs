//! Aurora curtains as a footprint over the ground: a few long arcs with
//! folds and rays, drifting, folding and pulsing over time. Röttger 2004
//! §10.4 draws the aurora as prisms between two height fields over such a
//! footprint, emissive, coloured by relative height.
//!
//! The footprint is a strength in [0, 1] over the unit square `(u, v)`, at
//! a time `t` in seconds. Arc `k`, with seeded parameters, runs along `u`:
//! its centre line is
//!
//! `v_k(u, t) = c_k + 0.1 sin(2π drift t + φ_k) + 0.12 sin(2π λ_k u + ψ_k)
//!             + fold · sin(2π f_k u + χ_k + 2π · 0.2 t)`
//!
//! (a slow sway across the footprint, a large bend, and folds that travel
//! along the arc), and its strength at `(u, v)` is
//!
//! `b_k · e^{−(d/width)²} · (1 − rays · r(u, t)) · p_k(t) · e(u)`
//!
//! with `d = |v − v_k(u, t)|`, `r ∈ [0, 1]` streaks along the arc (the
//! curtains' rays), `p_k(t) = 0.75 + 0.25 sin(2π pulse t + ω_k)` the
//! brightness pulses, `e(u)` a smooth taper to 0 over the last 10 % of the
//! square so the arcs end inside it, and `b_k ∈ [0.6, 1]` the arc's
//! brightness; an arc's share is left out beyond `d = 3` (below `e^{−9}`).
//! The arcs add; the sum `S` gives the strength `(S − 0.01)/0.99` clamped
//! to [0, 1], so the curtains end where their faint tails would be
//! (continuously: the strength reaches 0 there). [`AuroraCurtains::map`]
//! evaluates each arc only on the points within its reach, so a map costs
//! about its lit points, not its size times the arcs. Every term is smooth in `t`, so
//! the footprint never jumps between frames: its change over `Δt` is bounded
//! by `Δt` times a constant of the settings (the tests measure it).

use super::{FieldError, Settings, smoothstep};
use crate::budget::check_allocation;

/// Procedural aurora curtains (see the module docs). Lengths are fractions
/// of the footprint's side, times in seconds.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(default, deny_unknown_fields))]
pub struct AuroraCurtains {
    /// Seeds the arcs' positions, bends, folds and brightness. Default 1.
    pub seed: u64,
    /// Arcs, 1 to 16. Default 3.
    pub count: u32,
    /// Half width of a curtain across its arc (where it falls to 1/e), in
    /// (0, 0.25]. Default 0.015.
    pub width: f32,
    /// Amplitude of the folds along an arc, in [0, 0.25]. Default 0.03.
    pub fold: f32,
    /// Sways of the arcs across the footprint per second, finite and ≥ 0.
    /// Default 0.01.
    pub drift: f32,
    /// Brightness pulses per second, finite and ≥ 0. Default 0.2.
    pub pulse: f32,
    /// How much the rays darken the curtain between them, in [0, 1].
    /// Default 0.4.
    pub rays: f32,
}

impl Default for AuroraCurtains {
    fn default() -> Self {
        Self {
            seed: 1,
            count: 3,
            width: 0.015,
            fold: 0.03,
            drift: 0.01,
            pulse: 0.2,
            rays: 0.4,
        }
    }
}

/// One arc's seeded parameters.
#[derive(Clone, Copy, Debug)]
struct Arc {
    centre: f64,
    sway_phase: f64,
    bend_cycles: f64,
    bend_phase: f64,
    fold_cycles: f64,
    fold_phase: f64,
    brightness: f64,
    pulse_phase: f64,
}

/// What errors name this generator.
const NAME: &str = "aurora curtains";

impl AuroraCurtains {
    /// Checks every setting.
    pub fn validate(&self) -> Result<(), FieldError> {
        let settings = Settings(NAME);
        let count_ok = (1..=16).contains(&self.count);
        settings.require(count_ok, "count", self.count, "from 1 to 16")?;
        let width_ok = self.width > 0.0 && self.width <= 0.25;
        settings.require(width_ok, "width", self.width, "in (0, 0.25]")?;
        let fold_ok = (0.0..=0.25).contains(&self.fold);
        settings.require(fold_ok, "fold", self.fold, "in [0, 0.25]")?;
        settings.non_negative(&[("drift", self.drift), ("pulse", self.pulse)])?;
        let rays_ok = (0.0..=1.0).contains(&self.rays);
        settings.require(rays_ok, "rays", self.rays, "in [0, 1]")?;
        Ok(())
    }

    /// The arcs' seeded parameters.
    fn arcs(&self) -> Vec<Arc> {
        let mut state = self.seed ^ 0xa070_2a00_c0ff_ee00;
        let mut next = || {
            // splitmix64
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            (z ^ (z >> 31)) as f64 / u64::MAX as f64
        };
        let tau = std::f64::consts::TAU;
        let count = self.count.clamp(1, 16);
        (0..count)
            .map(|k| Arc {
                // Spread over [0.2, 0.8], each in its own band, jittered.
                centre: 0.2 + 0.6 * (f64::from(k) + 0.25 + 0.5 * next()) / f64::from(count),
                sway_phase: tau * next(),
                bend_cycles: 0.6 + 0.8 * next(),
                bend_phase: tau * next(),
                fold_cycles: 3.0 + 3.0 * next(),
                fold_phase: tau * next(),
                brightness: 0.6 + 0.4 * next(),
                pulse_phase: tau * next(),
            })
            .collect()
    }

    /// What the strength along the column `u` at time `t` shares: the taper
    /// times the rays, and each arc's centre line `v_k(u, t)` and its
    /// brightness `b_k p_k(t)`.
    fn column(&self, arcs: &[Arc], u: f64, t: f64, centres: &mut Vec<(f64, f64)>) -> f64 {
        let tau = std::f64::consts::TAU;
        centres.clear();
        let taper = smoothstep(0.0, 0.1, u) * smoothstep(0.0, 0.1, 1.0 - u);
        if taper <= 0.0 {
            return 0.0;
        }
        let streaks = 0.5 + 0.5 * (tau * 40.0 * u + 3.0 * (tau * 7.0 * u).sin() + t).sin();
        let rays = 1.0 - f64::from(self.rays) * streaks;
        centres.extend(arcs.iter().map(|arc| {
            let centre = arc.centre
                + 0.1 * (tau * f64::from(self.drift) * t + arc.sway_phase).sin()
                + 0.12 * (tau * arc.bend_cycles * u + arc.bend_phase).sin()
                + f64::from(self.fold)
                    * (tau * arc.fold_cycles * u + arc.fold_phase + tau * 0.2 * t).sin();
            let pulse = 0.75 + 0.25 * (tau * f64::from(self.pulse) * t + arc.pulse_phase).sin();
            (centre, arc.brightness * pulse)
        }));
        rays * taper
    }

    /// Arc `(centre, brightness)`'s share at `v`: zero beyond
    /// [`CUT_OFF`] half widths, where it is below `e^{−9}`.
    fn share(&self, (centre, brightness): (f64, f64), v: f64) -> f64 {
        let d = (v - centre) / f64::from(self.width);
        if d.abs() > CUT_OFF {
            0.0
        } else {
            brightness * (-d * d).exp()
        }
    }

    /// The strength from the arcs' summed shares `total` at a point of a
    /// column whose taper and rays are `column`: cut at [`FLOOR`] (the arcs'
    /// faint tails give no curtain) and clamped to 1.
    fn floored(total: f64, column: f64) -> f64 {
        ((total * column - FLOOR) / (1.0 - FLOOR)).clamp(0.0, 1.0)
    }

    /// The strength at `(u, v)` of the unit square at time `t` from `arcs`.
    fn strength_of(&self, arcs: &[Arc], u: f64, v: f64, t: f64) -> f64 {
        let mut centres = Vec::with_capacity(arcs.len());
        let column = self.column(arcs, u, t, &mut centres);
        let total: f64 = centres.iter().map(|&arc| self.share(arc, v)).sum();
        Self::floored(total, column)
    }

    /// The strength in [0, 1] at `(u, v)` of the unit square at time `t`
    /// seconds (see the module docs); 0 outside the square and for
    /// non-finite input. Errors for invalid settings.
    pub fn strength(&self, u: f64, v: f64, t: f64) -> Result<f32, FieldError> {
        self.validate()?;
        // NaN is in no range; the time must be finite itself.
        let inside = (0.0..=1.0).contains(&u) && (0.0..=1.0).contains(&v) && t.is_finite();
        if !inside {
            return Ok(0.0);
        }
        Ok(self.strength_of(&self.arcs(), u, v, t) as f32)
    }

    /// The footprint on `side × side` points covering the unit square corner
    /// to corner (index `i + side · j`, `u = i / (side − 1)`, `v = j /
    /// (side − 1)`), at time `t` seconds (a non-finite time counts as 0).
    /// Errors for invalid settings, a side below 2, or a map beyond the
    /// memory budget.
    pub fn map(&self, side: usize, t: f64) -> Result<Vec<f32>, FieldError> {
        self.validate()?;
        Settings(NAME).require(side >= 2, "side", side, "at least 2 points")?;
        check_allocation(
            || format!("aurora footprint of {side} × {side} points"),
            &[side, side],
            size_of::<f32>() as u64,
        )
        .map_err(FieldError::over_budget(NAME))?;
        let t = if t.is_finite() { t } else { 0.0 };
        let arcs = self.arcs();
        let last = (side - 1) as f64;
        let mut map = vec![0.0_f32; side * side];
        let mut totals = vec![0.0_f64; side];
        let mut centres = Vec::with_capacity(arcs.len());
        let reach = CUT_OFF * f64::from(self.width);
        for i in 0..side {
            let u = i as f64 / last;
            let column = self.column(&arcs, u, t, &mut centres);
            if column <= 0.0 {
                continue;
            }
            totals.fill(0.0);
            // Only the rows within an arc's reach get a share from it.
            for &arc in &centres {
                let rows = |v: f64| (v * last).clamp(0.0, last);
                // One row more on each side: the share itself decides.
                let first = (rows(arc.0 - reach).floor() as usize).saturating_sub(1);
                let end = rows(arc.0 + reach).ceil() as usize + 1;
                for (j, total) in totals.iter_mut().enumerate().take(end + 1).skip(first) {
                    *total += self.share(arc, j as f64 / last);
                }
            }
            for (j, total) in totals.iter().enumerate() {
                if *total > 0.0 {
                    map[i + side * j] = Self::floored(*total, column) as f32;
                }
            }
        }
        Ok(map)
    }
}

/// Half widths beyond which an arc's share is left out (`e^{−9} ≈ 1.2e-4`;
/// sixteen arcs there sum to less than [`FLOOR`]).
const CUT_OFF: f64 = 3.0;

/// The strength below which the curtains end.
const FLOOR: f64 = 0.01;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arcs_are_narrow_bright_bands_inside_the_footprint() {
        let curtains = AuroraCurtains::default();
        let side = 257;
        let map = curtains.map(side, 0.0).unwrap();
        assert!(map.iter().all(|s| s.is_finite() && (0.0..=1.0).contains(s)));
        // Narrow: most of the sky is dark, some of it bright.
        let lit = map.iter().filter(|s| **s > 0.05).count() as f64 / map.len() as f64;
        let bright = map.iter().copied().fold(0.0, f32::max);
        eprintln!("lit above 0.05: {lit:.3} of the footprint; brightest {bright:.3}");
        assert!((0.01..0.3).contains(&lit), "{lit} of the footprint lit");
        assert!(bright > 0.5, "{bright}");
        // The arcs end inside the square: its left and right columns are dark.
        for j in 0..side {
            assert_eq!(map[j * side], 0.0);
            assert_eq!(map[j * side + side - 1], 0.0);
        }
        // Each column crosses every arc: more arcs, more lit points per column.
        let lit_in = |map: &[f32]| map.iter().filter(|s| **s > 0.05).count();
        let more = AuroraCurtains {
            count: 8,
            ..curtains
        };
        assert!(lit_in(&more.map(side, 0.0).unwrap()) > lit_in(&map));
        // Wider curtains light more.
        let wide = AuroraCurtains {
            width: 0.05,
            ..curtains
        };
        assert!(lit_in(&wide.map(side, 0.0).unwrap()) > lit_in(&map));
    }

    #[test]
    fn a_seed_gives_one_footprint_and_another_seed_another() {
        let a = AuroraCurtains::default();
        let b = AuroraCurtains { seed: 2, ..a };
        assert_eq!(a.map(65, 3.0).unwrap(), a.map(65, 3.0).unwrap());
        assert_ne!(a.map(65, 3.0).unwrap(), b.map(65, 3.0).unwrap());
        // The map, which evaluates each arc near it only, samples the same
        // function as `strength` at every point, wide curtains and many arcs
        // included.
        for curtains in [
            a,
            AuroraCurtains {
                count: 16,
                width: 0.25,
                ..a
            },
        ] {
            let map = curtains.map(65, 3.0).unwrap();
            for (p, value) in map.iter().enumerate() {
                let (u, v) = ((p % 65) as f64 / 64.0, (p / 65) as f64 / 64.0);
                assert_eq!(*value, curtains.strength(u, v, 3.0).unwrap(), "at {p}");
            }
        }
    }

    #[test]
    fn the_footprint_changes_smoothly_over_time() {
        // The largest change of any point between frames 1/60 s apart, over
        // ten seconds, against the change over a whole second: smooth in t,
        // so a frame's change is about a sixtieth of it and never a jump.
        let curtains = AuroraCurtains {
            drift: 0.05,
            pulse: 0.5,
            ..AuroraCurtains::default()
        };
        let side = 129;
        let mut previous = curtains.map(side, 0.0).unwrap();
        let mut largest: f32 = 0.0;
        for frame in 1..=600 {
            let map = curtains.map(side, f64::from(frame) / 60.0).unwrap();
            for (a, b) in map.iter().zip(&previous) {
                largest = largest.max((a - b).abs());
            }
            previous = map;
        }
        assert!(largest < 0.1, "a frame changed a point by {largest}");
        let second = curtains.map(side, 1.0).unwrap();
        let first = curtains.map(side, 0.0).unwrap();
        let over_a_second = second
            .iter()
            .zip(&first)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        eprintln!(
            "largest change of a point: {largest:.4} per frame at 60 Hz, {over_a_second:.4} over a second"
        );
        assert!(over_a_second > largest, "{over_a_second} vs {largest}");
    }

    #[test]
    fn bad_settings_are_named_and_bad_positions_are_dark() {
        for (curtains, needle) in [
            (
                AuroraCurtains {
                    count: 0,
                    ..Default::default()
                },
                "count",
            ),
            (
                AuroraCurtains {
                    count: 17,
                    ..Default::default()
                },
                "count",
            ),
            (
                AuroraCurtains {
                    width: 0.0,
                    ..Default::default()
                },
                "width",
            ),
            (
                AuroraCurtains {
                    width: f32::NAN,
                    ..Default::default()
                },
                "width",
            ),
            (
                AuroraCurtains {
                    fold: -0.1,
                    ..Default::default()
                },
                "fold",
            ),
            (
                AuroraCurtains {
                    drift: f32::INFINITY,
                    ..Default::default()
                },
                "drift",
            ),
            (
                AuroraCurtains {
                    pulse: -1.0,
                    ..Default::default()
                },
                "pulse",
            ),
            (
                AuroraCurtains {
                    rays: 1.5,
                    ..Default::default()
                },
                "rays",
            ),
        ] {
            let error = curtains.map(9, 0.0).unwrap_err().to_string();
            assert!(error.contains(needle), "{error}");
            assert!(curtains.strength(0.5, 0.5, 0.0).is_err());
        }
        let curtains = AuroraCurtains::default();
        assert!(
            curtains
                .map(1, 0.0)
                .unwrap_err()
                .to_string()
                .contains("side")
        );
        assert!(
            curtains
                .map(1 << 20, 0.0)
                .unwrap_err()
                .to_string()
                .contains("budget")
        );
        for (u, v, t) in [
            (f64::NAN, 0.5, 0.0),
            (0.5, 2.0, 0.0),
            (0.5, 0.5, f64::INFINITY),
        ] {
            assert_eq!(curtains.strength(u, v, t).unwrap(), 0.0);
        }
        // A non-finite time counts as 0.
        assert_eq!(
            curtains.map(9, f64::NAN).unwrap(),
            curtains.map(9, 0.0).unwrap()
        );
    }
}
