//! The variance tree: for every bintree triangle, a bound on the vertical distance between
//! the heightfield and the triangle's plane, stored per diamond in one byte.
//!
//! - **Exact, then max over the subtree.** A diamond's value is the largest deviation of any
//!   sample inside either of its triangles from that triangle's plane, raised to the values
//!   of its children, so a bump deep down keeps every ancestor splittable and values never
//!   grow with depth.
//! - **Compact.** Values are kept per diamond (one per grid vertex, not two per triangle),
//!   except for the finest level, the rotated diamonds of half-size 1 (half of all
//!   vertices), whose error is exactly `|H(centre) - mean(H(ends))|` and is computed on the
//!   fly from three samples. That stores about `side² / 2` bytes: **0.5 byte per sample**.
//! - **Quantized up.** A byte is a code into a fixed logarithmic table (about 5 % steps from
//!   a quarter of a sample unit up to the full 16-bit range); a code's value is never below
//!   the exact error, so the stored error is still a true bound. Parents are built from
//!   their children's codes, so the build keeps no exact values: it needs the heights and
//!   the codes, nothing more.
//! - **Implicit.** No pointers: a diamond's slot is computed from its centre and level, with
//!   each level's diamonds packed together so coarse levels stay dense in cache.
//!
//! - **Built once, kept beside the data set.** The codes are owned after a build, or a
//!   read-only map of the data set's cache (`.cache/variance.bin`, see
//!   [`crate::terrain::cache`]), validated against the heights' hash and this table.
//!
//! Errors are in sample units; multiply by the map's `vScale` for world units.

use crate::terrain::backing::Backing;
use crate::terrain::heightfield::Heightfield;
use roam_protocol::bintree::{Diamond, Shape, Triangle, Vertex};

/// Why codes kept in a cache file cannot be a tree ([`VarianceTree::from_codes`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum CodesError {
    /// The grid's size (side − 1) is no power of two ≥ 2.
    #[error("size: expected a power of two ≥ 2, got {0}")]
    Size(u32),
    /// Not [`VarianceTree::codes_len`] codes for the side.
    #[error("expected {expected} codes for a side of {side}, got {got}")]
    Count {
        expected: usize,
        side: u64,
        got: usize,
    },
}

/// Value of code 1: the smallest non-zero error the table can express, in sample units.
const SMALLEST: f64 = 0.25;

/// Per-diamond error bounds of a heightfield.
#[derive(Clone, Debug)]
pub struct VarianceTree {
    size: u32,
    codes: Backing<u8>,
    /// Offsets of each level's block in `codes`, indexed by `m` (`h = 2^m`); entry 0 unused.
    square_offset: Vec<usize>,
    rotated_offset: Vec<usize>,
    table: [f32; 256],
}

impl VarianceTree {
    /// Builds the tree, reporting `(done, total)` work units to `progress` now and then.
    /// Uses up to `threads` scoped worker threads; the result does not depend on it.
    pub fn build(
        hf: &Heightfield,
        threads: usize,
        progress: &mut dyn FnMut(u64, u64),
    ) -> VarianceTree {
        let size = hf.size();
        let n_levels = hf.levels();
        let (square_offset, rotated_offset, total) = layout(size);
        // Codes are written level by level, fine to coarse; a parent reads its children's
        // codes (whose values bound their errors from above), so no exact values are kept.
        let table = log_table();
        let mut codes = vec![0u8; total];
        let work_total = u64::from(n_levels) * 2;
        let mut work_done = 0;
        // Fine to coarse: rotated level m (children: squares of level m - 1), then square
        // level m (children: rotated level m). Level 0 has squares only (its rotated
        // diamonds are computed on the fly).
        for m in 0..n_levels {
            let h = 1u32 << m;
            let n = (size >> (m + 1)) as usize;
            let shapes: &[Shape] = if m == 0 {
                &[Shape::Square]
            } else {
                &[
                    Shape::Rotated { horizontal: true },
                    Shape::Rotated { horizontal: false },
                    Shape::Square,
                ]
            };
            for &shape in shapes {
                let (offset, count, row) = match shape {
                    Shape::Square => (square_offset[m as usize], n * n, n),
                    Shape::Rotated { horizontal: true } => {
                        (rotated_offset[m as usize], n * (n + 1), n)
                    }
                    Shape::Rotated { horizontal: false } => {
                        (rotated_offset[m as usize] + n * (n + 1), n * (n + 1), n + 1)
                    }
                };
                let (done, todo) = codes.split_at_mut(offset);
                let todo = &mut todo[..count];
                let done = &*done;
                let centre = |i: usize| -> Vertex {
                    let (a, b) = ((i % row) as u32, (i / row) as u32);
                    match shape {
                        Shape::Square => (h + 2 * h * a, h + 2 * h * b),
                        Shape::Rotated { horizontal: true } => (h + 2 * h * a, 2 * h * b),
                        Shape::Rotated { horizontal: false } => (2 * h * a, h + 2 * h * b),
                    }
                };
                let partial = Partial {
                    hf,
                    size,
                    done,
                    table: &table,
                    square_offset: &square_offset,
                    rotated_offset: &rotated_offset,
                };
                parallel_fill(todo, threads, |i| {
                    let (x, z) = centre(i);
                    let d = Diamond { x, z, m, shape };
                    let e = if m == 0 {
                        f64::from(finest(hf, &d))
                    } else {
                        partial.diamond_value(&d)
                    };
                    quantize_up(&table, e)
                });
                if shape != (Shape::Rotated { horizontal: true }) {
                    work_done += 1;
                    progress(work_done.min(work_total), work_total);
                }
            }
        }
        VarianceTree {
            size,
            codes: Backing::Owned(codes),
            square_offset,
            rotated_offset,
            table,
        }
    }

    /// A tree over codes built earlier for a heightfield of `size + 1` samples a side (kept
    /// in a cache file), or why they cannot be: `size` not a power of two, or a count of
    /// codes that is not [`Self::codes_len`].
    pub fn from_codes(size: u32, codes: Backing<u8>) -> Result<VarianceTree, CodesError> {
        if size < 2 || !size.is_power_of_two() {
            return Err(CodesError::Size(size));
        }
        let (square_offset, rotated_offset, total) = layout(size);
        if codes.len() != total {
            return Err(CodesError::Count {
                expected: total,
                side: u64::from(size) + 1,
                got: codes.len(),
            });
        }
        Ok(VarianceTree {
            size,
            codes,
            square_offset,
            rotated_offset,
            table: log_table(),
        })
    }

    /// How many codes a tree over `size + 1` samples a side stores.
    pub fn codes_len(size: u32) -> usize {
        layout(size).2
    }

    /// Whether the codes are a file's map (shared with other processes) or owned.
    pub fn is_mapped(&self) -> bool {
        self.codes.is_mapped()
    }

    /// Error bound of the diamond centred at `(x, z)`, in sample units. Panics on a corner
    /// or a point off the map (a caller bug).
    pub fn error(&self, hf: &Heightfield, x: u32, z: u32) -> f32 {
        let d = Diamond::at(x, z, self.size).expect("error() wants a diamond centre");
        if d.m == 0 && d.shape != Shape::Square {
            finest(hf, &d)
        } else {
            self.table[self.codes()[self.slot(&d)] as usize]
        }
    }

    /// Slot of a stored diamond (all but the finest rotated ones).
    #[inline]
    pub(crate) fn slot(&self, d: &Diamond) -> usize {
        slot(
            &self.square_offset,
            &self.rotated_offset,
            self.size,
            d.x,
            d.z,
            d.m,
            d.shape,
        )
    }

    /// Bytes of the codes on the heap (0 when mapped) and the table.
    pub fn heap_bytes(&self) -> usize {
        self.codes.heap_bytes() + std::mem::size_of_val(&self.table)
    }

    /// Bytes of the codes, on the heap or mapped, and the table: what the tree takes once
    /// all of it is resident.
    pub fn bytes(&self) -> usize {
        self.codes.bytes() + std::mem::size_of_val(&self.table)
    }

    /// Stored bytes per heightfield sample (owned or mapped).
    pub fn bytes_per_sample(&self) -> f64 {
        let side = f64::from(self.size + 1);
        self.bytes() as f64 / (side * side)
    }

    /// The value of each code, in sample units (code 0 is exactly zero).
    pub fn table(&self) -> &[f32; 256] {
        &self.table
    }

    /// `side - 1` of the heightfield the tree was built for.
    pub fn size(&self) -> u32 {
        self.size
    }

    /// The stored codes, in slot order (what `.cache/variance.bin` holds after its header).
    #[inline]
    pub fn codes(&self) -> &[u8] {
        self.codes.as_slice()
    }

    pub(crate) fn square_offsets(&self) -> &[usize] {
        &self.square_offset
    }

    pub(crate) fn rotated_offsets(&self) -> &[usize] {
        &self.rotated_offset
    }
}

/// Slot of the stored diamond at `(x, z)` of level `m` and the given shape (not a rotated
/// diamond of level 0).
#[inline(always)]
pub(crate) fn slot(
    square_offset: &[usize],
    rotated_offset: &[usize],
    size: u32,
    x: u32,
    z: u32,
    m: u32,
    shape: Shape,
) -> usize {
    let n = (size >> (m + 1)) as usize;
    let (a, b) = ((x >> (m + 1)) as usize, (z >> (m + 1)) as usize);
    match shape {
        Shape::Square => square_offset[m as usize] + b * n + a,
        Shape::Rotated { horizontal: true } => rotated_offset[m as usize] + b * n + a,
        Shape::Rotated { horizontal: false } => {
            rotated_offset[m as usize] + n * (n + 1) + b * (n + 1) + a
        }
    }
}

/// Level blocks: for each `m` in `0..N`, `2·n·(n+1)` rotated diamonds (none for `m = 0`)
/// then `n²` squares, `n = size / 2^(m+1)`. Returns the offsets and the total count.
fn layout(size: u32) -> (Vec<usize>, Vec<usize>, usize) {
    let n_levels = size.trailing_zeros();
    let mut square = vec![0; n_levels as usize];
    let mut rotated = vec![0; n_levels as usize];
    let mut total = 0;
    for m in 0..n_levels {
        let n = (size >> (m + 1)) as usize;
        rotated[m as usize] = total;
        if m > 0 {
            total += 2 * n * (n + 1);
        }
        square[m as usize] = total;
        total += n * n;
    }
    (square, rotated, total)
}

/// What a level's builder can read: the heightfield and the finished finer levels.
struct Partial<'a> {
    hf: &'a Heightfield,
    size: u32,
    done: &'a [u8],
    table: &'a [f32; 256],
    square_offset: &'a [usize],
    rotated_offset: &'a [usize],
}

impl Partial<'_> {
    /// The exact error of the diamond's triangles, raised to its children's bounds.
    fn diamond_value(&self, d: &Diamond) -> f64 {
        let mut e = 0f64;
        for t in d.triangles(self.size).into_iter().flatten() {
            e = e.max(triangle_error(self.hf, &t));
        }
        for (cx, cz) in d.children(self.size).into_iter().flatten() {
            let c = Diamond::at(cx, cz, self.size).expect("children are diamonds");
            let v = if c.m == 0 && c.shape != Shape::Square {
                finest(self.hf, &c)
            } else {
                let s = slot(
                    self.square_offset,
                    self.rotated_offset,
                    self.size,
                    c.x,
                    c.z,
                    c.m,
                    c.shape,
                );
                self.table[self.done[s] as usize]
            };
            e = e.max(f64::from(v));
        }
        e
    }
}

/// Exact error of a diamond with `h = 1` (the two finest levels), in sample units.
/// Rotated ones are never stored; squares are stored, and built from this.
#[inline]
pub(crate) fn finest(hf: &Heightfield, d: &Diamond) -> f32 {
    let (x, z) = (d.x, d.z);
    let hs = |x: u32, z: u32| f32::from(hf.get(x, z));
    let dev = |c: Vertex, p: Vertex, q: Vertex| {
        (hs(c.0, c.1) - 0.5 * (hs(p.0, p.1) + hs(q.0, q.1))).abs()
    };
    match d.shape {
        Shape::Rotated { horizontal: true } => dev((x, z), (x - 1, z), (x + 1, z)),
        Shape::Rotated { horizontal: false } => dev((x, z), (x, z - 1), (x, z + 1)),
        Shape::Square => {
            let [p, q] = d.hypotenuse();
            dev((x, z), p, q)
                .max(dev((x - 1, z), (x - 1, z - 1), (x - 1, z + 1)))
                .max(dev((x + 1, z), (x + 1, z - 1), (x + 1, z + 1)))
                .max(dev((x, z - 1), (x - 1, z - 1), (x + 1, z - 1)))
                .max(dev((x, z + 1), (x - 1, z + 1), (x + 1, z + 1)))
        }
    }
}

/// Largest `|H - plane|` over the samples inside (or on the boundary of) triangle `t`, in
/// sample units.
pub fn triangle_error(hf: &Heightfield, t: &Triangle) -> f64 {
    let plane = plane_of(hf, t);
    let mut worst = 0f64;
    let (z0, z1) = (
        t.apex.1.min(t.left.1).min(t.right.1),
        t.apex.1.max(t.left.1).max(t.right.1),
    );
    for z in z0..=z1 {
        let Some((x0, x1)) = row_span(t, z) else {
            continue;
        };
        let row = &hf.samples()[(z * hf.side()) as usize..][x0 as usize..=x1 as usize];
        let mut p = plane.at(x0, z);
        for &s in row {
            worst = worst.max((f64::from(s) - p).abs());
            p += plane.gx;
        }
    }
    worst
}

/// A triangle's plane over the grid, in sample units.
#[derive(Clone, Copy, Debug)]
pub struct Plane {
    pub h0: f64,
    pub gx: f64,
    pub gz: f64,
    pub x0: f64,
    pub z0: f64,
}

impl Plane {
    pub fn at(&self, x: u32, z: u32) -> f64 {
        self.h0 + self.gx * (f64::from(x) - self.x0) + self.gz * (f64::from(z) - self.z0)
    }
}

/// The plane through the heights at a triangle's corners.
pub fn plane_of(hf: &Heightfield, t: &Triangle) -> Plane {
    let h = |v: Vertex| f64::from(hf.get(v.0, v.1));
    let (a, l, r) = (t.apex, t.left, t.right);
    let u = (l.0 as f64 - a.0 as f64, l.1 as f64 - a.1 as f64);
    let w = (r.0 as f64 - a.0 as f64, r.1 as f64 - a.1 as f64);
    let len2 = u.0 * u.0 + u.1 * u.1;
    let (dl, dr) = ((h(l) - h(a)) / len2, (h(r) - h(a)) / len2);
    Plane {
        h0: h(a),
        gx: dl * u.0 + dr * w.0,
        gz: dl * u.1 + dr * w.1,
        x0: a.0 as f64,
        z0: a.1 as f64,
    }
}

/// Inclusive column range of the grid points in row `z` inside triangle `t` or on its edges.
pub fn row_span(t: &Triangle, z: u32) -> Option<(u32, u32)> {
    let (mut lo, mut hi) = (i64::MIN, i64::MAX);
    let z = z as i64;
    for (p, q) in [(t.apex, t.left), (t.left, t.right), (t.right, t.apex)] {
        // ccw(p, q, (x, z)) = a·x + b >= 0 for points inside a counter-clockwise triangle.
        let (px, pz, qx, qz) = (p.0 as i64, p.1 as i64, q.0 as i64, q.1 as i64);
        let a = qz - pz;
        let b = -(qx - px) * (z - pz) - a * px;
        match a.cmp(&0) {
            std::cmp::Ordering::Greater => {
                lo = lo.max((-b).div_euclid(a) + i64::from((-b).rem_euclid(a) != 0))
            }
            std::cmp::Ordering::Less => hi = hi.min(b.div_euclid(-a)),
            std::cmp::Ordering::Equal if b < 0 => return None,
            std::cmp::Ordering::Equal => {}
        }
    }
    (lo <= hi).then_some((lo as u32, hi as u32))
}

/// The code table: 0, then `SMALLEST · r^(q-1)`, with `r` (about 1.05) chosen so that code
/// 255 reaches the largest possible error, a full 16-bit sample range. Fixed, so a code
/// can be written as soon as its diamond is computed.
pub(crate) fn log_table() -> [f32; 256] {
    const LARGEST: f64 = 65535.0;
    let r = (LARGEST / SMALLEST).powf(1.0 / 254.0);
    let mut table = [0f32; 256];
    for (q, v) in table.iter_mut().enumerate().skip(1) {
        *v = (SMALLEST * r.powi(q as i32 - 1)) as f32;
    }
    // Make sure the top code covers the largest error despite rounding.
    table[255] = table[255].max(next_up(LARGEST));
    table
}

fn next_up(v: f64) -> f32 {
    let f = v as f32;
    if f64::from(f) >= v {
        f
    } else {
        f32::from_bits(f.to_bits() + 1)
    }
}

/// The smallest code whose value is at least `e`.
fn quantize_up(table: &[f32; 256], e: f64) -> u8 {
    // `table` is increasing: binary search for the first value >= e.
    let q = table.partition_point(|&v| f64::from(v) < e);
    debug_assert!(q < 256, "the table covers the largest error");
    q.min(255) as u8
}

/// Fills `out[i] = f(i)` using up to `threads` scoped threads.
fn parallel_fill<T: Send, F: Fn(usize) -> T + Sync>(out: &mut [T], threads: usize, f: F) {
    let threads = threads.max(1);
    if threads == 1 || out.len() < 1024 {
        for (i, v) in out.iter_mut().enumerate() {
            *v = f(i);
        }
        return;
    }
    let chunk = out.len().div_ceil(threads);
    std::thread::scope(|scope| {
        for (c, part) in out.chunks_mut(chunk).enumerate() {
            let f = &f;
            scope.spawn(move || {
                for (i, v) in part.iter_mut().enumerate() {
                    *v = f(c * chunk + i);
                }
            });
        }
    });
}
