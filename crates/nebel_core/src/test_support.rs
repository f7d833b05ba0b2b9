//! Helpers shared by the unit tests of several modules.

use std::fmt::{Debug, Display};
use std::ops::Range;
use std::path::Path;

use proptest::prelude::*;

use crate::transfer::{ControlPoint, TransferFunction};

/// Random valid transfer functions: `point_counts` control points at random
/// `s` in [0, 1], each κ channel in [0, `kappa_below`), ρ in [0, `rho_below`).
pub(crate) fn arbitrary_transfer_function(
    point_counts: Range<usize>,
    kappa_below: f32,
    rho_below: f32,
) -> impl Strategy<Value = TransferFunction> {
    prop::collection::vec(
        (
            0.0_f32..=1.0,
            prop::array::uniform3(0.0_f32..kappa_below),
            0.0_f32..rho_below,
        ),
        point_counts,
    )
    .prop_map(|points| transfer_function(points.into_iter()))
}

/// The transfer function through `(s, κ, ρ)` points.
fn transfer_function(points: impl Iterator<Item = (f32, [f32; 3], f32)>) -> TransferFunction {
    TransferFunction::new(
        points
            .map(|(s, kappa, rho)| ControlPoint { s, kappa, rho })
            .collect::<Vec<_>>(),
    )
    .unwrap()
}

/// Random valid transfer functions whose control points sit on distinct
/// multiples of 1/15 (so no feature is narrower than about four nodes of a
/// 64-node table), each κ channel in [0, `kappa_below`), ρ in [0,
/// `rho_below`).
pub(crate) fn resolved_transfer_function(
    point_counts: Range<usize>,
    kappa_below: f32,
    rho_below: f32,
) -> impl Strategy<Value = TransferFunction> {
    prop::collection::btree_map(
        0_u8..=15,
        (
            prop::array::uniform3(0.0_f32..kappa_below),
            0.0_f32..rho_below,
        ),
        point_counts,
    )
    .prop_map(|points| {
        transfer_function(
            points
                .into_iter()
                .map(|(k, (kappa, rho))| (f32::from(k) / 15.0, kappa, rho)),
        )
    })
}

/// The message of the error that `result` must hold.
pub(crate) fn error_message<T: Debug, E: Display>(result: Result<T, E>) -> String {
    result.unwrap_err().to_string()
}

/// Asserts that `message` contains every one of `parts`.
pub(crate) fn assert_mentions(message: &str, parts: &[&str]) {
    for part in parts {
        assert!(message.contains(part), "{message}");
    }
}

/// Writes a PNG whose header declares `width × height` 8-bit grayscale
/// pixels, followed by an empty image-data chunk: its size can be read, its
/// pixels cannot be decoded. For inputs too large to build.
pub(crate) fn write_png_header(path: &Path, width: u32, height: u32) {
    let file = std::fs::File::create(path).unwrap();
    let mut encoder = png::Encoder::new(file, width, height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Eight);
    // The header and an empty data chunk: the size reads, the pixels do not.
    let mut writer = encoder.write_header().unwrap();
    writer.write_chunk(png::chunk::IDAT, &[]).unwrap();
}

/// A deterministic generator of uniform numbers (`SplitMix64`) for tests that
/// draw many random cases without proptest's shrinking.
pub(crate) struct SplitMix(pub(crate) u64);

impl SplitMix {
    /// A uniform number in `[range.start, range.end)`.
    pub(crate) fn random_range(&mut self, range: Range<f64>) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        let unit = (z >> 11) as f64 / (1_u64 << 53) as f64;
        range.start + (range.end - range.start) * unit
    }
}
