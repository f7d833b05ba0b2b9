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
    .prop_map(|points| {
        TransferFunction::new(
            points
                .into_iter()
                .map(|(s, kappa, rho)| ControlPoint { s, kappa, rho })
                .collect::<Vec<_>>(),
        )
        .unwrap()
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
    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = !0u32;
        for &byte in bytes {
            crc ^= u32::from(byte);
            for _ in 0..8 {
                crc = (crc >> 1) ^ (0xedb8_8320 & (crc & 1).wrapping_neg());
            }
        }
        !crc
    }
    let mut png = vec![0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a];
    let mut chunk = |kind: &[u8; 4], data: &[u8]| {
        png.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let start = png.len();
        png.extend_from_slice(kind);
        png.extend_from_slice(data);
        let crc = crc32(&png[start..]);
        png.extend_from_slice(&crc.to_be_bytes());
    };
    let mut header = Vec::new();
    header.extend_from_slice(&width.to_be_bytes());
    header.extend_from_slice(&height.to_be_bytes());
    // Bit depth 8, grayscale, deflate, adaptive filtering, no interlace.
    header.extend_from_slice(&[8, 0, 0, 0, 0]);
    chunk(b"IHDR", &header);
    chunk(b"IDAT", &[]);
    chunk(b"IEND", &[]);
    std::fs::write(path, png).unwrap();
}
