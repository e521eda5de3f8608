//! The heightfield: a square grid of `side = 2^N + 1` unsigned 16-bit samples, row-major.
//!
//! Row `i` (`z`) grows southwards, column `j` (`x`) eastwards; sample `(x, z)` is at index
//! `z * side + x`. World height is `v_scale * sample`, kept by the data set, not here.
//!
//! The samples are a [`Backing`]: owned (`new`) or a read-only map of the data set's cache
//! (`mapped`, see [`crate::terrain::cache`]); both read the same.

use crate::terrain::backing::Backing;

/// Largest supported exponent: side = 2^15 + 1 = 32769 keeps grid coordinates in `u16`.
pub const MAX_LEVELS: u32 = 15;

/// A validated square heightfield. Construction checks the shape, so every accessor can
/// index without further checks.
#[derive(Clone, Debug)]
pub struct Heightfield {
    levels: u32,
    side: u32,
    samples: Backing<u16>,
}

impl PartialEq for Heightfield {
    fn eq(&self, other: &Self) -> bool {
        self.side == other.side && self.samples() == other.samples()
    }
}

impl Eq for Heightfield {}

/// Why a grid of samples is not a heightfield.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ShapeError {
    #[error("side {side} is not 2^N + 1 with 1 <= N <= {MAX_LEVELS}")]
    Side { side: u64 },
    #[error("{got} samples for side {side}: expected {expected}")]
    Length {
        side: u32,
        got: usize,
        expected: u64,
    },
}

/// `Some(N)` when `side == 2^N + 1` with `1 <= N <= MAX_LEVELS`.
pub fn levels_of_side(side: u64) -> Option<u32> {
    let n = side.checked_sub(1)?;
    if n < 2 || !n.is_power_of_two() {
        return None;
    }
    let levels = n.trailing_zeros();
    (levels <= MAX_LEVELS).then_some(levels)
}

impl Heightfield {
    pub fn new(side: u32, samples: Vec<u16>) -> Result<Self, ShapeError> {
        Self::with_backing(side, Backing::Owned(samples))
    }

    /// A heightfield over samples owned or mapped; the shape is checked as in [`Self::new`].
    pub fn with_backing(side: u32, samples: Backing<u16>) -> Result<Self, ShapeError> {
        let levels = levels_of_side(u64::from(side)).ok_or(ShapeError::Side {
            side: u64::from(side),
        })?;
        let expected = u64::from(side) * u64::from(side);
        if samples.len() as u64 != expected {
            return Err(ShapeError::Length {
                side,
                got: samples.len(),
                expected,
            });
        }
        Ok(Heightfield {
            levels,
            side,
            samples,
        })
    }

    /// `N` in `side = 2^N + 1`.
    pub fn levels(&self) -> u32 {
        self.levels
    }

    /// Samples per row (and rows): `2^N + 1`.
    pub fn side(&self) -> u32 {
        self.side
    }

    /// Cells per row: `2^N`.
    pub fn size(&self) -> u32 {
        self.side - 1
    }

    #[inline]
    pub fn samples(&self) -> &[u16] {
        self.samples.as_slice()
    }

    /// Whether the samples are a file's map (shared with other processes) or owned.
    pub fn is_mapped(&self) -> bool {
        self.samples.is_mapped()
    }

    /// Sample at column `x`, row `z`. Panics when out of range (a caller bug, not input).
    #[inline]
    pub fn get(&self, x: u32, z: u32) -> u16 {
        self.samples()[(z * self.side + x) as usize]
    }

    /// Smallest and largest sample.
    pub fn range(&self) -> (u16, u16) {
        let mut lo = u16::MAX;
        let mut hi = 0;
        for &s in self.samples() {
            lo = lo.min(s);
            hi = hi.max(s);
        }
        (lo, hi)
    }

    /// Bytes of the samples on the heap (0 when mapped).
    pub fn heap_bytes(&self) -> usize {
        self.samples.heap_bytes()
    }

    /// Bytes of the samples, on the heap or mapped: what they take once all are resident.
    pub fn bytes(&self) -> usize {
        self.samples.bytes()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sides() {
        for (side, want) in [
            (0, None),
            (1, None),
            (2, None),
            (3, Some(1)),
            (5, Some(2)),
            (6, None),
            (1025, Some(10)),
            (32769, Some(15)),
            (65537, None),
            (u64::MAX, None),
        ] {
            assert_eq!(levels_of_side(side), want, "side {side}");
        }
    }

    #[test]
    fn shape_is_checked() {
        assert!(Heightfield::new(3, vec![0; 9]).is_ok());
        assert_eq!(
            Heightfield::new(3, vec![0; 8]),
            Err(ShapeError::Length {
                side: 3,
                got: 8,
                expected: 9
            })
        );
        assert_eq!(
            Heightfield::new(4, vec![0; 16]),
            Err(ShapeError::Side { side: 4 })
        );
    }
}
