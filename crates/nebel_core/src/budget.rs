//! The memory budget: the most bytes nebel allocates for one structure it
//! builds from input, checked before the allocation is made.
//!
//! Every allocation in nebel whose size comes from input (a scene file, a
//! loaded file's header, a caller's dimensions or settings) goes through
//! [`check_allocation`] or [`check_bytes`] first: density grids and height
//! fields (generated, loaded, padded, resampled), light fields, the volume
//! octree and the terrain quadtree, pre-integration tables, transfer-function
//! strips, search-light cones, reference images and their depth buffers, and
//! scene files. A request above [`MEMORY_BUDGET_BYTES`] is refused with a
//! [`BudgetError`] that names what was to be built, the bytes it needs and
//! the limit, instead of the process aborting on a failed allocation (or
//! swapping for minutes first). Structures that infallible functions derive
//! from a grid ([`DensityGrid::tetrahedra`], the full-resolution cell batch
//! of `nebel_lod`) are not checked there; scene validation checks the
//! full-resolution batch of every volume a scene draws at full resolution.
//!
//! A check counts the bytes one builder holds at once for what it builds: the
//! arrays of the structure it returns and the temporary arrays of a similar
//! size it fills on the way (the f64 sums of value noise, the rows of a
//! pre-integration table), not the input it reads from and not scratch
//! buffers of one slice or row. Products and sums are taken in `u128`, so no
//! request overflows into a small number; a request beyond `u128` is refused
//! too.
//!
//! [`DensityGrid::tetrahedra`]: crate::field::DensityGrid::tetrahedra

use std::fmt;

/// The most bytes one structure built from input may take: 4 GiB.
///
/// Larger than anything the shipped scenes need (the 513 × 65 × 513 cloud
/// grid is 68 MB, an 8193² terrain with its quadtree about 290 MB), small
/// enough that a typo in a size (`dims: (4097, 4097, 4097)` is 256 GiB of
/// density alone) is refused at once instead of swapping or aborting.
pub const MEMORY_BUDGET_BYTES: u64 = 4 * 1024 * 1024 * 1024;

/// A structure that would need more than the memory budget.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error(
    "{what} needs {}, more than the memory budget of {}",
    amount(*.bytes),
    amount(u128::from(*.limit))
)]
pub struct BudgetError {
    /// What was to be built, e.g. `density grid of 4097 × 4097 × 4097 points`.
    pub what: String,
    /// Bytes it needs; `u128::MAX` when the count overflows `u128`.
    pub bytes: u128,
    /// The budget, bytes ([`MEMORY_BUDGET_BYTES`]).
    pub limit: u64,
}

/// Checks `bytes` against [`MEMORY_BUDGET_BYTES`] and returns them, or a
/// [`BudgetError`] naming `what()` (called only then). Pass `u128::MAX` for a
/// count that overflowed.
pub fn check_bytes(what: impl FnOnce() -> String, bytes: u128) -> Result<u64, BudgetError> {
    match u64::try_from(bytes) {
        Ok(bytes) if bytes <= MEMORY_BUDGET_BYTES => Ok(bytes),
        _ => Err(BudgetError {
            what: what(),
            bytes,
            limit: MEMORY_BUDGET_BYTES,
        }),
    }
}

/// Checks an array of `counts[0] · counts[1] · …` elements of
/// `bytes_per_element` bytes each (e.g. the points per axis of a grid and 4
/// bytes per f32 sample) against [`MEMORY_BUDGET_BYTES`]; returns its bytes.
/// The product is exact in `u128`; one that overflows is refused.
pub fn check_allocation(
    what: impl FnOnce() -> String,
    counts: &[usize],
    bytes_per_element: u64,
) -> Result<u64, BudgetError> {
    let bytes = counts
        .iter()
        .try_fold(u128::from(bytes_per_element), |acc, &n| {
            acc.checked_mul(n as u128)
        })
        .unwrap_or(u128::MAX);
    check_bytes(what, bytes)
}

/// Sizes per axis written as `4097 × 4097 × 4097`, for the `what` of a
/// [`BudgetError`].
#[derive(Clone, Copy, Debug)]
pub struct Dims<'a>(pub &'a [usize]);

impl fmt::Display for Dims<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (axis, n) in self.0.iter().enumerate() {
            if axis > 0 {
                f.write_str(" × ")?;
            }
            write!(f, "{n}")?;
        }
        Ok(())
    }
}

/// `275,079,282,692 bytes (256.2 GiB)`: the exact count with thousands
/// separators and, from 1 KiB on, the size in binary units to one decimal.
fn amount(bytes: u128) -> String {
    if bytes == u128::MAX {
        return String::from("more than 2^128 bytes");
    }
    let digits = bytes.to_string();
    let mut exact = String::with_capacity(digits.len() + digits.len() / 3);
    for (index, digit) in digits.chars().enumerate() {
        if index > 0 && (digits.len() - index).is_multiple_of(3) {
            exact.push(',');
        }
        exact.push(digit);
    }
    const UNITS: [&str; 8] = ["KiB", "MiB", "GiB", "TiB", "PiB", "EiB", "ZiB", "YiB"];
    let mut scaled = bytes as f64;
    let mut unit = None;
    for name in UNITS {
        if scaled < 1024.0 {
            break;
        }
        scaled /= 1024.0;
        unit = Some(name);
    }
    match unit {
        None => format!("{exact} bytes"),
        Some(unit) => {
            let rounded = format!("{scaled:.1}");
            let rounded = rounded.strip_suffix(".0").unwrap_or(&rounded);
            format!("{exact} bytes ({rounded} {unit})")
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_huge_volume_is_refused_with_what_bytes_and_limit() {
        let dims = [4097usize; 3];
        let error = check_allocation(
            || format!("density grid of {} points", Dims(&dims)),
            &dims,
            4,
        )
        .unwrap_err();
        assert_eq!(error.bytes, 275_079_282_692);
        assert_eq!(error.limit, MEMORY_BUDGET_BYTES);
        assert_eq!(
            error.to_string(),
            "density grid of 4097 × 4097 × 4097 points needs 275,079,282,692 bytes (256.2 GiB), \
             more than the memory budget of 4,294,967,296 bytes (4 GiB)"
        );
    }

    #[test]
    fn the_budget_itself_is_allowed_and_one_byte_more_is_not() {
        let what = || String::from("test");
        assert_eq!(check_bytes(what, 0), Ok(0));
        assert_eq!(
            check_bytes(what, u128::from(MEMORY_BUDGET_BYTES)),
            Ok(MEMORY_BUDGET_BYTES)
        );
        assert!(check_bytes(what, u128::from(MEMORY_BUDGET_BYTES) + 1).is_err());
        assert_eq!(check_allocation(what, &[1 << 30], 4), Ok(1 << 32));
        assert_eq!(check_allocation(what, &[], 7), Ok(7));
        assert_eq!(check_allocation(what, &[3, 0, usize::MAX], 8), Ok(0));
    }

    #[test]
    fn what_is_only_formatted_for_an_error() {
        let result = check_allocation(|| unreachable!("formatted on success"), &[2, 2], 4);
        assert_eq!(result, Ok(16));
    }

    #[test]
    fn overflowing_products_are_refused_not_wrapped() {
        let dims = [usize::MAX; 3];
        let error = check_allocation(|| format!("grid of {}", Dims(&dims)), &dims, 4).unwrap_err();
        assert_eq!(error.bytes, u128::MAX);
        let message = error.to_string();
        assert!(
            message.starts_with(&format!(
                "grid of {0} × {0} × {0} needs more than 2^128 bytes,",
                usize::MAX
            )),
            "{message}"
        );
        // Within u128 but beyond u64: the exact count.
        let error = check_allocation(|| String::from("wide"), &[usize::MAX], 16).unwrap_err();
        assert_eq!(error.bytes, u128::from(u64::MAX) * 16);
    }

    #[test]
    fn amounts_read_in_binary_units() {
        assert_eq!(amount(0), "0 bytes");
        assert_eq!(amount(999), "999 bytes");
        assert_eq!(amount(1024), "1,024 bytes (1 KiB)");
        assert_eq!(amount(1536), "1,536 bytes (1.5 KiB)");
        assert_eq!(amount(68_423_940), "68,423,940 bytes (65.3 MiB)");
        assert_eq!(amount(1 << 40), "1,099,511,627,776 bytes (1 TiB)");
    }
}
