//! Emissive effects of Röttger 2004 §10.4 (Figure 10.3): a campfire from animated
//! 3D Perlin noise and a search light cone with quadratic attenuation; both
//! are drawn with the emissive model by default.
//!
//! # Campfire
//!
//! [`campfire_density`] samples, on a grid over the box
//! [`CAMPFIRE_MIN`]..[`CAMPFIRE_MAX`] = `[−0.5, 0.5] × [0, 1.5] × [−0.5, 0.5]`
//! (world units, y up, the fire's base centred on the origin), the density
//!
//! ```text
//! h = y / 1.5,  r = √(x² + z²),  n = fBm(x, y − 1.2 t, z, 0.9 t) ∈ [0, 1]
//! R = 0.34 (1 − h)^0.75 (0.6 + 0.8 n)                      flame radius
//! ρ = clamp(smoothstep(0, 0.08, h) · (1 − h)^1.5 · max(0, 1 − (r/R)²) · (0.4 + 1.2 n), 0, 1)
//! ```
//!
//! `fBm` is four octaves of seeded Perlin noise in 4D (3 cycles per world unit
//! in space, lacunarity 2, persistence 0.5, mapped from [−1, 1] to [0, 1]), the
//! space part scrolling upward at 1.2 units/s so the flames rise, the fourth
//! coordinate advancing 0.9 cycles/s so their shapes flicker. The envelope is
//! dense and wide at the base, narrows and fades to zero at the top, and is
//! exactly zero on the whole box boundary (R < 0.48 keeps the sides clear, the
//! smoothstep the ground, `(1 − h)` the top), so the volume has no hard edge.
//!
//! # Search light
//!
//! [`search_light_cells`] builds a cone of tetrahedra, apex at the origin,
//! opening along −Z (Bevy's forward), from a structured grid around × radial ×
//! along of hexahedra split with the alternating five-tetrahedron
//! decomposition. The cells next to the axis are hexahedra with one edge
//! collapsed (prisms) and those at the apex have a collapsed face (pyramids,
//! tetrahedra); their zero-volume pieces are dropped. Shared faces use the same
//! diagonal because the decomposition alternates with `(around + radial +
//! along) mod 2`, which closes around the axis because the number of sectors is
//! even. The intensity (the scalar) at distance `d = −z` from the apex and
//! ring fraction `q` (0 on the axis, 1 on the cone surface) is
//!
//! ```text
//! s = 1 / (1 + (d / d0)²) · (1 − q²)²,  d0 = length / 3,  s = 1 at the apex
//! ```
//!
//! quadratic attenuation along the beam (1 at the apex, 0.1 at the far end)
//! times a smooth radial falloff (1 on the axis, 0 with zero slope at the
//! surface).

use glam::DVec3;
use noise::{Fbm, MultiFractal, NoiseFn, Perlin};

use super::{DensityGrid, NOISE_OFFSET, SAMPLE_BYTES};
use crate::budget::{BudgetError, Dims, MEMORY_BUDGET_BYTES, check_allocation};
use crate::cell::{Hexahedron, HexahedronParity, Tetrahedron};

/// Minimum corner of the campfire's box, world units.
pub const CAMPFIRE_MIN: DVec3 = DVec3::new(-0.5, 0.0, -0.5);
/// Maximum corner of the campfire's box, world units.
pub const CAMPFIRE_MAX: DVec3 = DVec3::new(0.5, 1.5, 0.5);
/// Default campfire grid: 17³ points, 16³ cells (Röttger 2004, Table 10.4).
pub const CAMPFIRE_DIMS: [usize; 3] = [17, 17, 17];
/// Largest campfire grid edge, points; larger requests are clamped.
pub const CAMPFIRE_MAX_DIM: usize = 257;

// The largest campfire grid (68 MB) lies far within the memory budget, so
// [`campfire_density`] needs no budget check.
const _: () = assert!((CAMPFIRE_MAX_DIM as u64).pow(3) * SAMPLE_BYTES <= MEMORY_BUDGET_BYTES);

/// Default search-light segments `[around, radial, along]` (Röttger 2004,
/// Table 10.4).
pub const SEARCH_LIGHT_SEGMENTS: [usize; 3] = [16, 4, 32];
/// Largest segment count on any search-light axis; larger requests are clamped.
pub const SEARCH_LIGHT_MAX_SEGMENTS: usize = 256;
/// Largest search-light half angle, radians (85°); wider cones are clamped.
pub const SEARCH_LIGHT_MAX_HALF_ANGLE: f64 = 85.0 * std::f64::consts::PI / 180.0;

/// Noise cycles per world unit of the campfire.
const FLAME_FREQUENCY: f64 = 3.0;
/// Upward scroll speed of the campfire noise, world units per second.
const FLAME_RISE: f64 = 1.2;
/// Flicker rate of the campfire noise, cycles per second.
const FLAME_FLICKER: f64 = 0.9;
/// Fourth noise coordinate's offset (fractional part of the Euler–Mascheroni
/// constant), off Perlin's zero lattice like [`NOISE_OFFSET`].
const FLICKER_OFFSET: f64 = 0.577_215_664_901_532_9;

/// The campfire density over [`CAMPFIRE_MIN`]..[`CAMPFIRE_MAX`] at
/// `time_seconds` (see the module docs for the formula), values in [0, 1],
/// zero on the box boundary, the same for equal `(dims, time_seconds, seed)`.
///
/// `dims` are points per axis (default [`CAMPFIRE_DIMS`]), each clamped to
/// 2..=[`CAMPFIRE_MAX_DIM`]; a non-finite time reads as 0. Precision of the
/// animation degrades slowly beyond about 10⁶ s.
pub fn campfire_density(dims: [usize; 3], time_seconds: f64, seed: u32) -> DensityGrid {
    let dims = dims.map(|n| n.clamp(2, CAMPFIRE_MAX_DIM));
    let time = if time_seconds.is_finite() {
        time_seconds
    } else {
        0.0
    };
    let noise = flame_fbm(seed);
    let values = campfire_points(dims)
        .map(|(f, p)| {
            let r = p.x.hypot(p.z);
            // Outside the widest flame any noise gives (n = 1) the density
            // is 0 whatever the noise: most of the box.
            let n = if r < flame_radius(f.y, 1.0) {
                flame_noise(&noise, p, time)
            } else {
                0.0
            };
            flame(f.y, r, n)
        })
        .collect();
    let [nx, ny, nz] = dims;
    let extent = CAMPFIRE_MAX - CAMPFIRE_MIN;
    let spacing = extent / DVec3::new((nx - 1) as f64, (ny - 1) as f64, (nz - 1) as f64);
    DensityGrid::new(dims, spacing, CAMPFIRE_MIN, values)
        .expect("campfire densities are finite, in [0, 1], on a valid grid")
}

/// The fractions (0 to 1 along each axis) and positions of the points of a
/// campfire grid of `dims` points (at least 2 per axis), x fastest.
fn campfire_points(dims: [usize; 3]) -> impl Iterator<Item = (DVec3, DVec3)> {
    let [nx, ny, nz] = dims;
    let extent = CAMPFIRE_MAX - CAMPFIRE_MIN;
    (0..nz).flat_map(move |k| {
        (0..ny).flat_map(move |j| {
            (0..nx).map(move |i| {
                // Fractions from the indices, so the boundary is exactly 0 or 1.
                let f = DVec3::new(
                    i as f64 / (nx - 1) as f64,
                    j as f64 / (ny - 1) as f64,
                    k as f64 / (nz - 1) as f64,
                );
                (f, CAMPFIRE_MIN + f * extent)
            })
        })
    })
}

/// The flame's fBm (module docs) for `seed`.
fn flame_fbm(seed: u32) -> Fbm<Perlin> {
    Fbm::<Perlin>::new(seed)
        .set_octaves(4)
        .set_frequency(1.0)
        .set_lacunarity(2.0)
        .set_persistence(0.5)
}

/// The unit noise `n` of the flame at `p` (world units) and `time` seconds
/// (module docs), 0 where the noise is NaN.
fn flame_noise(noise: &Fbm<Perlin>, p: DVec3, time: f64) -> f64 {
    let n = noise.get([
        p.x * FLAME_FREQUENCY + NOISE_OFFSET[0],
        (p.y - FLAME_RISE * time) * FLAME_FREQUENCY + NOISE_OFFSET[1],
        p.z * FLAME_FREQUENCY + NOISE_OFFSET[2],
        FLAME_FLICKER * time + FLICKER_OFFSET,
    ]);
    let n = ((n + 1.0) / 2.0).clamp(0.0, 1.0);
    if n.is_nan() { 0.0 } else { n }
}

/// The flame radius `R` at height fraction `h` and unit noise `n`; rounding
/// keeps it non-decreasing in `n`, so `n = 1` bounds it.
fn flame_radius(h: f64, n: f64) -> f64 {
    0.34 * (1.0 - h).max(0.0).powf(0.75) * (0.6 + 0.8 * n)
}

/// The flame envelope times the noise at height fraction `h`, radius `r`
/// (world units) and unit noise `n` (module docs).
fn flame(h: f64, r: f64, n: f64) -> f32 {
    let radius = flame_radius(h, n);
    if radius <= 0.0 {
        return 0.0;
    }
    let radial = (1.0 - (r / radius).powi(2)).max(0.0);
    let ground = {
        let x = (h / 0.08).clamp(0.0, 1.0);
        x * x * (3.0 - 2.0 * x)
    };
    let top = (1.0 - h).max(0.0).powf(1.5);
    (ground * top * radial * (0.4 + 1.2 * n)).clamp(0.0, 1.0) as f32
}

/// A search light cone as conforming tetrahedra (see the module docs): apex at
/// the origin, axis along −Z, `length` world units long, `half_angle_radians`
/// between axis and surface, scalar = intensity in [0, 1].
///
/// `segments = [around, radial, along]` (default [`SEARCH_LIGHT_SEGMENTS`]):
/// `around` is rounded up to an even number ≥ 4, `radial` and `along` are at
/// least 1, all at most [`SEARCH_LIGHT_MAX_SEGMENTS`]. The half angle is
/// clamped to at most [`SEARCH_LIGHT_MAX_HALF_ANGLE`]. A non-finite or
/// non-positive length or half angle gives no cells. The cells tile the
/// polygonal cone (an `around`-gon pyramid) exactly; they come in no
/// particular visibility order (the emissive and MIP modes need none).
///
/// # Errors
///
/// A [`BudgetError`] when the cells of these segments exceed the memory
/// budget ([`check_search_light_budget`]), before they are allocated.
pub fn search_light_cells(
    length: f64,
    half_angle_radians: f64,
    segments: [usize; 3],
) -> Result<Vec<Tetrahedron>, BudgetError> {
    check_search_light_budget(segments)?;
    if !(length.is_finite() && length > 0.0 && half_angle_radians > 0.0) {
        return Ok(Vec::new());
    }
    let radius = length * half_angle_radians.min(SEARCH_LIGHT_MAX_HALF_ANGLE).tan();
    let [around, radial, along] = search_light_segments(segments);
    let attenuation_distance = length / 3.0;

    // Vertex (a, r, t): slice a along the beam, ring r, sector boundary t.
    let vertex = |a: usize, r: usize, t: usize| -> (DVec3, f64) {
        if a == 0 {
            return (DVec3::ZERO, 1.0);
        }
        let along_fraction = a as f64 / along as f64;
        let q = r as f64 / radial as f64;
        let distance = length * along_fraction;
        let intensity = (1.0 - q * q).powi(2) / (1.0 + (distance / attenuation_distance).powi(2));
        let position = if r == 0 {
            DVec3::new(0.0, 0.0, -distance)
        } else {
            let angle = std::f64::consts::TAU * (t % around) as f64 / around as f64;
            let ring = radius * along_fraction * q;
            DVec3::new(ring * angle.cos(), ring * angle.sin(), -distance)
        };
        (position, intensity)
    };

    let mut cells = Vec::with_capacity(5 * around * radial * along);
    for a in 0..along {
        for r in 0..radial {
            for t in 0..around {
                // Corner x + 2y + 4z: x around, y radial, z along.
                let corners: [(DVec3, f64); 8] =
                    std::array::from_fn(|v| vertex(a + (v >> 2), r + ((v >> 1) & 1), t + (v & 1)));
                let hexahedron = Hexahedron {
                    positions: corners.map(|c| c.0),
                    scalars: corners.map(|c| c.1),
                };
                let parity = HexahedronParity::of_cell(t as i64, r as i64, a as i64);
                cells.extend(
                    hexahedron
                        .tetrahedra(parity)
                        .into_iter()
                        .filter(|t| !t.is_degenerate()),
                );
            }
        }
    }
    Ok(cells)
}

/// The bytes of the cells [`search_light_cells`] builds for `segments` (five
/// tetrahedra per segment of the clamped `[around, radial, along]`, 128 bytes
/// each), checked against the memory budget without building them. Errors
/// name a `search-light cone of around × radial × along segments`.
pub fn check_search_light_budget(segments: [usize; 3]) -> Result<u64, BudgetError> {
    let segments = search_light_segments(segments);
    check_allocation(
        || {
            format!(
                "search-light cone of {} segments (5 tetrahedra each)",
                Dims(&segments)
            )
        },
        &[5, segments[0], segments[1], segments[2]],
        size_of::<Tetrahedron>() as u64,
    )
}

/// `[around, radial, along]` as [`search_light_cells`] uses them: clamped to
/// 1..=[`SEARCH_LIGHT_MAX_SEGMENTS`], `around` rounded up to an even number
/// ≥ 4.
fn search_light_segments(segments: [usize; 3]) -> [usize; 3] {
    let [around, radial, along] = segments.map(|n| n.clamp(1, SEARCH_LIGHT_MAX_SEGMENTS));
    [around.max(4).next_multiple_of(2), radial, along]
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use super::*;

    #[test]
    fn campfire_is_bounded_zero_on_the_boundary_deterministic_and_animated() {
        let a = campfire_density(CAMPFIRE_DIMS, 1.25, 7);
        assert_eq!(a.dims(), [17, 17, 17]);
        assert_eq!(a.origin(), CAMPFIRE_MIN);
        assert!((a.max_corner() - CAMPFIRE_MAX).abs().max_element() < 1e-12);
        assert!(a.values().iter().all(|v| (0.0..=1.0).contains(v)));
        let [nx, ny, nz] = a.dims();
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    if i == 0 || j == 0 || k == 0 || i == nx - 1 || j == ny - 1 || k == nz - 1 {
                        assert_eq!(a.value(i, j, k), 0.0, "({i}, {j}, {k})");
                    }
                }
            }
        }
        // Dense near the base centre, fading with height.
        let low = a.value(8, 2, 8);
        let high = a.value(8, 14, 8);
        assert!(low > 0.2 && low > high, "{low} {high}");
        assert_eq!(a, campfire_density(CAMPFIRE_DIMS, 1.25, 7));
        assert_ne!(
            a,
            campfire_density(CAMPFIRE_DIMS, 1.3, 7),
            "changes with time"
        );
        assert_ne!(
            a,
            campfire_density(CAMPFIRE_DIMS, 1.25, 8),
            "changes with seed"
        );
    }

    proptest::proptest! {
        /// The grid equals the one with the noise evaluated at every point,
        /// bit for bit.
        #[test]
        fn skipping_the_noise_outside_the_widest_flame_changes_no_value(
            dims in proptest::array::uniform3(2_usize..40),
            time in -100.0_f64..1e4,
            seed: u32,
        ) {
            let grid = campfire_density(dims, time, seed);
            let noise = flame_fbm(seed);
            let full = campfire_points(dims)
                .map(|(f, p)| flame(f.y, p.x.hypot(p.z), flame_noise(&noise, p, time)).to_bits());
            proptest::prop_assert!(grid.values().iter().map(|v| v.to_bits()).eq(full));
        }
    }

    #[test]
    fn campfire_clamps_bad_input() {
        let grid = campfire_density([0, 1, 1000], f64::NAN, 0);
        assert_eq!(grid.dims(), [2, 2, CAMPFIRE_MAX_DIM]);
        assert_eq!(
            campfire_density([5, 5, 5], f64::INFINITY, 3),
            campfire_density([5, 5, 5], 0.0, 3)
        );
        assert!(
            campfire_density([9, 9, 9], 1e9, 1)
                .values()
                .iter()
                .all(|v| (0.0..=1.0).contains(v))
        );
    }

    /// Exact volume of the polygonal cone the cells tile.
    fn polygonal_cone_volume(length: f64, half_angle: f64, around: usize) -> f64 {
        let r = length * half_angle.tan();
        let base = around as f64 / 2.0 * r * r * (std::f64::consts::TAU / around as f64).sin();
        base * length / 3.0
    }

    #[test]
    fn search_light_fills_the_polygonal_cone_with_bounded_intensity() {
        for (segments, around) in [(SEARCH_LIGHT_SEGMENTS, 16), ([3, 1, 1], 4), ([7, 2, 5], 8)] {
            let (length, half_angle) = (10.0, 0.3);
            let cells = search_light_cells(length, half_angle, segments).unwrap();
            let volume: f64 = cells.iter().map(Tetrahedron::volume).sum();
            let exact = polygonal_cone_volume(length, half_angle, around);
            assert!(
                (volume - exact).abs() < 1e-9 * exact,
                "{segments:?}: {volume} vs {exact}"
            );
            // The polygonal cone approaches the round one.
            let round = std::f64::consts::PI * (length * half_angle.tan()).powi(2) * length / 3.0;
            assert!(volume < round);
            for cell in &cells {
                assert!(!cell.is_degenerate());
                assert!(cell.scalars.iter().all(|s| (0.0..=1.0).contains(s)));
                assert!(cell.positions.iter().all(|p| p.z <= 0.0 && p.z >= -length));
            }
        }
        let cells = search_light_cells(10.0, 0.3, SEARCH_LIGHT_SEGMENTS).unwrap();
        // Apex 1, axis at the far end 0.1, surface 0.
        let scalar_at = |target: DVec3| {
            cells
                .iter()
                .flat_map(|c| c.positions.into_iter().zip(c.scalars))
                .find(|(p, _)| p.distance(target) < 1e-12)
                .map(|(_, s)| s)
        };
        assert_eq!(scalar_at(DVec3::ZERO), Some(1.0));
        assert!((scalar_at(DVec3::new(0.0, 0.0, -10.0)).unwrap() - 0.1).abs() < 1e-12);
        let rim = DVec3::new(10.0 * 0.3f64.tan(), 0.0, -10.0);
        assert_eq!(scalar_at(rim), Some(0.0));
    }

    #[test]
    fn search_light_cells_conform() {
        let (length, half_angle) = (4.0, 0.4);
        let cells = search_light_cells(length, half_angle, [6, 3, 5]).unwrap();
        // Every triangle shared by at most two cells; the triangles used once
        // make up exactly the cone's surface, so no face is split differently
        // by its two cells (a mismatch would add inner boundary area).
        let key = |p: DVec3| (p + DVec3::ZERO).to_array().map(f64::to_bits);
        let mut faces: HashMap<[[u64; 3]; 3], (usize, f64)> = HashMap::new();
        for cell in &cells {
            for skip in 0..4 {
                let mut corners: Vec<DVec3> = (0..4)
                    .filter(|&v| v != skip)
                    .map(|v| cell.positions[v])
                    .collect();
                corners.sort_by_key(|&p| key(p));
                let area = (corners[1] - corners[0])
                    .cross(corners[2] - corners[0])
                    .length()
                    / 2.0;
                let entry = faces
                    .entry([key(corners[0]), key(corners[1]), key(corners[2])])
                    .or_insert((0, area));
                entry.0 += 1;
            }
        }
        assert!(faces.values().all(|&(count, _)| count <= 2));
        let boundary: f64 = faces
            .values()
            .filter(|&&(c, _)| c == 1)
            .map(|&(_, a)| a)
            .sum();
        let r = length * half_angle.tan();
        let rim = |t: usize| {
            let angle = std::f64::consts::TAU * t as f64 / 6.0;
            DVec3::new(r * angle.cos(), r * angle.sin(), -length)
        };
        let lateral: f64 = (0..6)
            .map(|t| rim(t).cross(rim(t + 1)).length() / 2.0)
            .sum();
        let cap = 3.0 * r * r * (std::f64::consts::TAU / 6.0).sin();
        assert!(
            (boundary - lateral - cap).abs() < 1e-9,
            "{boundary} vs {}",
            lateral + cap
        );
    }

    #[test]
    fn search_light_refuses_bad_geometry_without_panicking() {
        for (length, angle) in [
            (f64::NAN, 0.3),
            (-1.0, 0.3),
            (1.0, 0.0),
            (1.0, f64::NAN),
            (f64::INFINITY, 0.2),
        ] {
            assert!(
                search_light_cells(length, angle, SEARCH_LIGHT_SEGMENTS)
                    .unwrap()
                    .is_empty()
            );
        }
        let wide = search_light_cells(1.0, 10.0, [0, 0, 0]).unwrap();
        let volume: f64 = wide.iter().map(Tetrahedron::volume).sum();
        let exact = polygonal_cone_volume(1.0, SEARCH_LIGHT_MAX_HALF_ANGLE, 4);
        assert!((volume - exact).abs() < 1e-9 * exact);
    }

    #[test]
    fn search_light_cells_are_checked_against_the_memory_budget() {
        let message = search_light_cells(10.0, 0.3, [256; 3])
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with(
                "search-light cone of 256 × 256 × 256 segments (5 tetrahedra each) needs 10,737,418,240 bytes (10 GiB)"
            ),
            "{message}"
        );
        // The figure is what the cells take, for the clamped segments.
        let cells = search_light_cells(10.0, 0.3, [7, 2, 5]).unwrap();
        let bytes = check_search_light_budget([7, 2, 5]).unwrap();
        assert_eq!(bytes, 5 * 8 * 2 * 5 * size_of::<Tetrahedron>() as u64);
        assert!(cells.len() * size_of::<Tetrahedron>() <= bytes as usize);
        assert_eq!(
            check_search_light_budget([usize::MAX; 3]),
            check_search_light_budget([SEARCH_LIGHT_MAX_SEGMENTS; 3])
        );
    }
}
