//! The terrain's tolerance in pixels: the accuracy `c` of Röttger's
//! criterion (Röttger 2004 §3.5.3, Eq. 3.2) that keeps every detail the mesh
//! leaves out within a given number of pixels of the real projection and
//! viewport.
//!
//! # From radians to pixels
//!
//! A node that is not refined leaves out details (the deviation of its new
//! points from the coarse mesh) that subtend at most `θ = 1 / (2c (1 −
//! 1/(2C)))` radian from the eye (the module docs of [`crate::quadtree`]; the
//! same holds for the part `1 − t` of a detail that a morphing node has not
//! yet blended in, since `(1 − t)·d·d2/2 ≤ l/(2c)` on the morph zone).
//!
//! A perspective projection maps a view-space point `(x, y, z)` to the
//! pixel `A · (x, y)/|z| + o` (`A`: the 2×2 block of the projection times half
//! the viewport, divided by the projection's depth factor). Moving the point
//! by `v` moves its pixel by `A (v_xy |z| − p_xy v_z)/z²`, whose length is at
//! most `‖A‖ · |v| · r / z²` (Cauchy–Schwarz; `r` the distance to the eye),
//! that is `‖A‖ · (|v|/r) · (1 + tan²φ)`, with `φ` the angle between the
//! point's direction and the view axis. So over the viewport a detail of
//! angular size `θ` moves at most
//!
//! `‖A‖ · θ · (1 + tan²φ_max)` pixels,
//!
//! `φ_max` the angle of the viewport's farthest corner (both to first order in
//! `θ`, which is at most a few thousandths of a radian at any useful `c`). So
//! the accuracy
//!
//! `c = ‖A‖ (1 + tan²φ_max) / (2 p (1 − 1/(2C)))`
//!
//! keeps every left-out detail within `p` pixels; at the view's centre the
//! bound is `1 + tan²φ_max` times smaller (2.4 for a 60°, 16:9 view). For a
//! 1080-line, 60°, 16:9 view at `p` = 2 and `C` = 2 that is `c` ≈ 740 (the
//! default `c` = 300 keeps two pixels at the view's centre only).
//!
//! # Where it applies, and what it leaves out
//!
//! The bound holds for a terrain placed by a rigid motion with a uniform scale
//! (angles do not change); a non-uniform scale distorts them. An orthographic
//! projection shows far details as large as near ones, which no
//! distance-based criterion can bound: it is an error
//! ([`TerrainError::PixelErrorNeedsPerspective`]). Fog prisms ride on the
//! terrain's mesh (their tops are its layer, refined by the same criterion
//! with the layer's roughness in d2), so the same `c` bounds the fog's top.
//!
//! Occlusion (terrain hidden behind terrain or dense fog needing less
//! detail) is not used: the propagation's guarantee (a node refines whenever
//! a child or a neighbour's child would, which makes the mesh crack-free and
//! the geomorphing continuous) needs the refinement test to depend on the eye
//! only through the 1-Lipschitz distance `l`; a per-node occlusion factor
//! breaks it, and the cracks and pops it causes at the edge of the occluded
//! region would be visible.

use glam::DMat4;

use super::TerrainError;

/// The accuracy `c` (see the module docs) at which no detail the mesh leaves
/// out moves by more than `pixel_error` pixels in a `viewport` (pixels) seen
/// through the perspective projection `clip_from_view`, for a hierarchy of
/// minimum resolution `min_resolution` (`C`).
///
/// Errors: `pixel_error` not finite and > 0, an empty viewport or a
/// `min_resolution` below 1 ([`TerrainError::InvalidParameter`]), and a
/// projection that is not a finite perspective one
/// ([`TerrainError::PixelErrorNeedsPerspective`]).
pub fn accuracy_for_pixel_error(
    pixel_error: f64,
    clip_from_view: DMat4,
    viewport: [u32; 2],
    min_resolution: f32,
) -> Result<f64, TerrainError> {
    let check = TerrainError::check;
    let pixel_error_ok = pixel_error.is_finite() && pixel_error > 0.0;
    check(pixel_error_ok, "pixel_error", pixel_error, "finite and > 0")?;
    let smaller_side = f64::from(viewport[0].min(viewport[1]));
    check(
        smaller_side > 0.0,
        "viewport",
        smaller_side,
        "at least one pixel each way",
    )?;
    let min_resolution = f64::from(min_resolution);
    let resolution_ok = min_resolution.is_finite() && min_resolution >= 1.0;
    check(
        resolution_ok,
        "min_resolution",
        min_resolution,
        "finite and >= 1",
    )?;
    let spread = pixels_per_tangent(clip_from_view, viewport)?
        * (1.0 + largest_tangent_squared(clip_from_view)?);
    Ok(spread / (2.0 * pixel_error * (1.0 - 0.5 / min_resolution)))
}

/// `‖A‖` of the module docs: the largest number of pixels a unit change of
/// the view tangent `(x, y)/|z|` moves a point, or an error for a projection
/// that is not perspective (its `w` must be a multiple of the view depth).
fn pixels_per_tangent(clip_from_view: DMat4, viewport: [u32; 2]) -> Result<f64, TerrainError> {
    let [x, y, z, w] = [
        clip_from_view.x_axis,
        clip_from_view.y_axis,
        clip_from_view.z_axis,
        clip_from_view.w_axis,
    ];
    let depth_factor = z.w.abs();
    let perspective = clip_from_view.is_finite()
        && x.w == 0.0
        && y.w == 0.0
        && w.w == 0.0
        && w.x == 0.0
        && w.y == 0.0
        && depth_factor > 0.0;
    if !perspective {
        return Err(TerrainError::PixelErrorNeedsPerspective);
    }
    let (half_width, half_height) = (0.5 * f64::from(viewport[0]), 0.5 * f64::from(viewport[1]));
    // Rows: pixel x and y; columns: view x and y.
    let a = [
        [half_width * x.x, half_width * y.x],
        [half_height * x.y, half_height * y.y],
    ]
    .map(|row| row.map(|value| value / depth_factor));
    // The spectral norm of a 2×2 matrix in closed form.
    let frobenius = a.iter().flatten().map(|value| value * value).sum::<f64>();
    let determinant = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    let gap = (frobenius * frobenius - 4.0 * determinant * determinant).max(0.0);
    Ok((0.5 * (frobenius + gap.sqrt())).sqrt())
}

/// `tan²φ_max`: the largest squared tangent of the angle between the view
/// axis and the ray through a corner of the viewport.
fn largest_tangent_squared(clip_from_view: DMat4) -> Result<f64, TerrainError> {
    let view_from_clip = clip_from_view.inverse();
    let corners = [[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]];
    let mut largest = 0.0f64;
    for [x, y] in corners {
        // Any depth between the planes gives the corner's ray.
        let point = view_from_clip * glam::DVec4::new(x, y, 0.5, 1.0);
        let tangent_squared = (point.x * point.x + point.y * point.y) / (point.z * point.z);
        if !tangent_squared.is_finite() {
            return Err(TerrainError::PixelErrorNeedsPerspective);
        }
        largest = largest.max(tangent_squared);
    }
    Ok(largest)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DVec2, DVec3, DVec4};

    /// Bevy's perspective: right-handed, infinite, reversed depth.
    fn projection(fov_y: f64, aspect: f64) -> DMat4 {
        DMat4::perspective_infinite_reverse_rh(fov_y, aspect, 0.1)
    }

    fn pixel(clip_from_view: DMat4, viewport: [u32; 2], point: DVec3) -> DVec2 {
        let clip = clip_from_view * point.extend(1.0);
        let ndc = DVec2::new(clip.x, clip.y) / clip.w;
        ndc * DVec2::new(f64::from(viewport[0]), f64::from(viewport[1])) * 0.5
    }

    /// Deterministic pseudo-random numbers in [-1, 1).
    fn next(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((*state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    /// A detail of the angular size the accuracy allows, anywhere in the
    /// view, in any direction, moves at most the tolerance; at a corner,
    /// moved across the ray, it moves almost exactly that much.
    #[test]
    fn details_of_the_bound_stay_within_the_pixel_tolerance_and_reach_it_at_a_corner() {
        let mut state = 3u64;
        for (fov_y, aspect, viewport, min_resolution) in [
            (60f64.to_radians(), 16.0 / 9.0, [1920, 1080], 2.0f32),
            (90f64.to_radians(), 1.0, [64, 64], 1.6),
            (20f64.to_radians(), 2.4, [2400, 1000], 9.0),
            // Non-square pixels: the viewport's aspect differs from the projection's.
            (45f64.to_radians(), 1.0, [800, 400], 4.0),
        ] {
            let clip_from_view = projection(fov_y, aspect);
            let pixel_error = 1.5;
            let c = accuracy_for_pixel_error(pixel_error, clip_from_view, viewport, min_resolution)
                .unwrap();
            let theta = 1.0 / (2.0 * c * (1.0 - 0.5 / f64::from(min_resolution)));
            let (tan_x, tan_y) = ((fov_y / 2.0).tan() * aspect, (fov_y / 2.0).tan());
            let mut largest = 0.0f64;
            for _ in 0..20_000 {
                let depth = 1.0 + 1000.0 * (next(&mut state) + 1.0);
                let point = DVec3::new(
                    next(&mut state) * tan_x * depth,
                    next(&mut state) * tan_y * depth,
                    -depth,
                );
                let direction = DVec3::new(next(&mut state), next(&mut state), next(&mut state))
                    .normalize_or(DVec3::Y);
                let moved = point + direction * theta * point.length();
                let shift = (pixel(clip_from_view, viewport, moved)
                    - pixel(clip_from_view, viewport, point))
                .length();
                largest = largest.max(shift);
            }
            assert!(largest <= pixel_error * 1.002, "{largest} px");
            // The worst case: a corner, moved in the image plane across the ray.
            let corner = DVec3::new(tan_x * 100.0, tan_y * 100.0, -100.0);
            let across = DVec3::new(corner.x, corner.y, 0.0).normalize();
            let along_depth = corner.normalize();
            let worst = (across - across.dot(along_depth) * along_depth).normalize();
            let shift = (pixel(
                clip_from_view,
                viewport,
                corner + worst * theta * corner.length(),
            ) - pixel(clip_from_view, viewport, corner))
            .length();
            // Square pixels reach the bound; the stretched ones reach the
            // larger of the two scales only along that axis.
            let square = viewport[0] as f64 / viewport[1] as f64 == aspect;
            println!(
                "fov {:.0}°, {viewport:?}: c = {c:.1}, random {largest:.3} px, corner {shift:.3} px",
                fov_y.to_degrees()
            );
            if square {
                assert!(shift >= pixel_error * 0.99, "{shift} px at the corner");
            }
        }
    }

    #[test]
    fn a_narrower_view_or_a_smaller_tolerance_raises_the_accuracy() {
        let c = |fov: f64, pixels: f64| {
            accuracy_for_pixel_error(pixels, projection(fov.to_radians(), 1.5), [900, 600], 2.0)
                .unwrap()
        };
        // A telephoto magnifies; a very wide lens stretches its corners.
        assert!(c(20.0, 1.0) > c(60.0, 1.0));
        assert!(c(120.0, 1.0) > c(60.0, 1.0));
        assert!((c(60.0, 2.0) - c(60.0, 1.0) / 2.0).abs() < 1e-9 * c(60.0, 1.0));
        // 1080 lines, 60°, 16:9, 2 px, C = 2: about 740 (see the module docs).
        let bevy = accuracy_for_pixel_error(
            2.0,
            projection(60f64.to_radians(), 16.0 / 9.0),
            [1920, 1080],
            2.0,
        )
        .unwrap();
        assert!((735.0..750.0).contains(&bevy), "{bevy}");
    }

    #[test]
    fn bad_input_is_an_error() {
        let perspective = projection(1.0, 1.0);
        for (pixels, viewport, min_resolution) in [
            (0.0, [10, 10], 2.0),
            (f64::NAN, [10, 10], 2.0),
            (f64::INFINITY, [10, 10], 2.0),
            (1.0, [0, 10], 2.0),
            (1.0, [10, 10], 0.5),
            (1.0, [10, 10], f32::NAN),
        ] {
            assert!(matches!(
                accuracy_for_pixel_error(pixels, perspective, viewport, min_resolution),
                Err(TerrainError::InvalidParameter { .. })
            ));
        }
        let orthographic = DMat4::orthographic_rh(-1.0, 1.0, -1.0, 1.0, 0.1, 100.0);
        let mut nan = perspective;
        nan.x_axis = DVec4::splat(f64::NAN);
        for clip_from_view in [orthographic, nan, DMat4::ZERO] {
            assert!(matches!(
                accuracy_for_pixel_error(1.0, clip_from_view, [10, 10], 2.0),
                Err(TerrainError::PixelErrorNeedsPerspective)
            ));
        }
    }
}
