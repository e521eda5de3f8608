//! The colour map codec: lossless, for `cells × cells` RGB8 texels.
//!
//! Texels are coded in raster order, each as G, then R, then B. Every sample is predicted
//! from samples already coded and only the residual is entropy-coded:
//!
//! - each channel's **spatial prediction** is the mean of its left and up neighbours. The
//!   colour maps this is for are smooth colour under per-texel noise (grain, height
//!   noise), where averaging two noisy neighbours beats the edge-following predictors of
//!   LOCO-I (MED) or PNG (Paeth): on `kossou`, 2.5 % smaller than MED;
//! - then R and B are corrected by the spatial errors of the channels coded before them at
//!   this texel (G's; G's and R's), weighted by a least-squares fit over the texels just
//!   before it, left and above (see `Sums`). Both ends compute the fit from the same
//!   decoded samples, so nothing is sent for it. Noise that scales a texel's brightness
//!   moves all three channels together, and a change of ground cover moves them in fixed
//!   proportions. With the fit, R costs 0.9 and B under half of what G costs.
//!
//! A residual (mod 256) is zigzagged and split into a token (small values whole; larger
//! ones as bit length and two more bits) and raw low bits. Tokens are coded by static rANS
//! (`rans`), one stream per channel, in one of 192 contexts: the channel and a
//! bucket of the expected error (for G the local gradient; for R this texel's G error
//! and R's activity; for B this texel's G and R errors). The encoder counts every
//! context's tokens and sends the tables up front (about 4 KB).
//!
//! # Payload
//!
//! ```text
//! format    u8        1
//! reserved  3 × u8    0
//! cells     u32       texels a side
//! check     u64       a 64-bit hash of the texels (see `check`)
//! tables    per context: a symbol count n (u8), then n LEB128 frequencies
//! symbols   3 ×, for R, G, B: a u32 byte length, then that many bytes of rANS words
//! raw       the raw bits, least significant first, to the end
//! ```
//!
//! Decoding never panics and allocates the `cells² · 3` output, two rows of state and
//! the decoding tables (26 KiB, and 2 KiB for each context the payload uses: at most
//! 412 KiB), whatever the payload. A payload that is short, for another size, truncated, extended
//! or damaged is an error: every stream must end exactly where the texels do, and the
//! texels must match the check.

use crate::format::{self, DecodeError};
use crate::rans;

/// The payload format this code writes and reads.
pub const FORMAT: u8 = format::COLORMAP;
/// The largest colour map side either end accepts: bounds what a decoder allocates.
pub const MAX_CELLS: u32 = 8192;
const HEADER: usize = 16;
/// Contexts per channel.
const CTX: usize = 64;
const CONTEXTS: usize = 3 * CTX;

/// The bucket of an expected error `e` (a sum of absolute differences): about two buckets
/// per doubling, so contexts are as fine where errors are small as where they are large.
#[inline(always)]
fn bucket(e: u32, max: usize) -> usize {
    usize::from(BUCKETS[(e as usize).min(BUCKETS.len() - 1)]).min(max - 1)
}

/// [`bucket`] by table (a few instructions less on the decoder's critical path): 0, 1, 2,
/// 3–4, 5–6, 7–10, 11–14, 15–22, …
const BUCKETS: [u8; 1024] = {
    let mut t = [0u8; 1024];
    let mut e = 0;
    while e < t.len() {
        let v = e as u32 + 1;
        let bits = 32 - v.leading_zeros();
        let half = if bits >= 2 { (v >> (bits - 2)) & 1 } else { 1 };
        t[e] = (2 * (bits - 1) + half - 1) as u8;
        e += 1;
    }
    t
};

/// The texel check: a 64-bit multiply-rotate hash of the texels, eight bytes at a time.
/// It catches damage the entropy coder let through and a payload decoded as the wrong map;
/// QUIC already authenticates the bytes, so it need not resist forgery.
fn check(rgb: &[u8]) -> u64 {
    let mut h = 0x243f_6a88_85a3_08d3u64 ^ rgb.len() as u64;
    let mut add = |v: u64| h = (h.rotate_left(23) ^ v).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    let mut words = rgb.chunks_exact(8);
    for w in &mut words {
        let mut b = [0u8; 8];
        b.copy_from_slice(w);
        add(u64::from_le_bytes(b));
    }
    let mut b = [0u8; 8];
    b[..words.remainder().len()].copy_from_slice(words.remainder());
    add(u64::from_le_bytes(b));
    h ^= h >> 33;
    h = h.wrapping_mul(0xff51_afd7_ed55_8ccd);
    h ^ (h >> 33)
}

/// Residuals (mod 256, zigzagged to 0 ..= 255) below this are a token each; above, the
/// token holds the bit length and the next bits below the leading one, the rest go raw.
const DIRECT: u32 = 16;
/// Bits below the leading one held in the token.
const TOKEN_BITS: u32 = 2;

/// The token of zigzagged residual `u`, and its raw bits and their count.
#[inline]
fn tokenize(u: u32) -> (u32, u32, u32) {
    if u < DIRECT {
        return (u, 0, 0);
    }
    let e = 31 - u.leading_zeros(); // 4 ..= 7
    let raw = e - TOKEN_BITS;
    let top = (u >> raw) & ((1 << TOKEN_BITS) - 1);
    (
        DIRECT + ((e - DIRECT.trailing_zeros()) << TOKEN_BITS) + top,
        u & ((1 << raw) - 1),
        raw,
    )
}

/// The bit length − 1 of the residuals of token `t` ≥ [`DIRECT`].
#[inline]
fn token_exponent(t: u32) -> u32 {
    ((t - DIRECT) >> TOKEN_BITS) + DIRECT.trailing_zeros()
}

/// One end of the coder: the encoder reads samples from its input, the decoder writes them.
trait Coder {
    /// Codes sample `i`, predicted as `pred` (0 ..= 255), in context `ctx`; returns it.
    fn code(&mut self, ch: usize, ctx: usize, pred: i32, i: usize) -> u8;
}

struct Enc<'a> {
    rgb: &'a [u8],
    /// One symbol stream per channel: three independent decoder state chains that a CPU
    /// can overlap (measured 2 % faster decoding than one stream).
    syms: [rans::Encoder; 3],
    bits: rans::BitWriter,
}

impl Coder for Enc<'_> {
    #[inline(always)]
    fn code(&mut self, ch: usize, ctx: usize, pred: i32, i: usize) -> u8 {
        let v = self.rgb[i];
        // Residuals wrap mod 256 into −128 ..= 127: every sample stays reachable and the
        // magnitude never needs more than 8 bits.
        let r = i32::from((i32::from(v) - pred) as i8);
        let u = ((r << 1) ^ (r >> 31)) as u32;
        let (t, raw, n) = tokenize(u);
        self.syms[ch].put(ctx, t);
        self.bits.put(raw, n);
        v
    }
}

struct Dec<'a> {
    out: &'a mut [u8],
    tables: &'a rans::DecTables,
    syms: [rans::Decoder<'a>; 3],
    bits: rans::BitReader<'a>,
}

impl Coder for Dec<'_> {
    #[inline(always)]
    fn code(&mut self, ch: usize, ctx: usize, pred: i32, i: usize) -> u8 {
        let t = self.syms[ch].get(self.tables, ctx);
        let u = if t < DIRECT {
            t
        } else {
            let e = token_exponent(t);
            let raw = e - TOKEN_BITS;
            let top = (1 << TOKEN_BITS) | (t & ((1 << TOKEN_BITS) - 1));
            top << raw | self.bits.get(raw)
        };
        let r = (u >> 1) as i32 ^ -((u & 1) as i32);
        // A damaged stream may give any residual; mod 256 keeps it a sample (the check
        // catches it).
        let v = (pred + r) as u8;
        if let Some(s) = self.out.get_mut(i) {
            *s = v;
        }
        v
    }
}

/// Local least-squares sums for the cross-channel fits, over the spatial errors of the
/// texels coded before this one: `[g², g·r, r², g·b, r·b]`. Each texel's sums are its own
/// products plus 3/8 of its left neighbour's sums and 2/8 of its upper neighbour's, so
/// the weight of earlier texels falls off within a few texels in both directions: how the
/// channels move together changes from texel to texel (water, forest, rock, their
/// mixes), and on `kossou` a fit this local is 5 % smaller overall than one over the last
/// hundred texels of the row. Errors are within ±255, so a sum stays within
/// 65025 / (1 − 5/8) < 2^18.
type Sums = [i32; 5];

#[inline(always)]
fn blend(left: &Sums, up: &Sums) -> Sums {
    std::array::from_fn(|k| (3 * left[k] + 2 * up[k]) >> 3)
}

/// The fits' weights, in 1/256ths: R's on G's error, and B's on G's and R's. Ridge-
/// regularised, so that where there has been little error they stay near 0; in integers,
/// so both ends agree bit for bit on every platform.
#[inline(always)]
fn weights(s: &Sums) -> (i64, [i64; 2]) {
    const RIDGE: i64 = 2;
    let [gg, gr, rr, gb, rb] = s.map(i64::from);
    let (gg, rr) = (gg + RIDGE, rr + RIDGE);
    let w_r = gr * 256 / gg;
    // Positive (Cauchy–Schwarz plus the ridge) for exact sums; the guard covers the
    // blend's rounding. |numerators| < 2^36 · 2^8, no overflow.
    let det = gg * rr - gr * gr;
    let w_b = if det > 0 {
        [
            (gb * rr - rb * gr) * 256 / det,
            (gg * rb - gr * gb) * 256 / det,
        ]
    } else {
        [0, 0]
    };
    let clamp = |w: i64| w.clamp(-512, 512);
    (clamp(w_r), w_b.map(clamp))
}

/// What the model keeps of a coded texel for the texels after it.
#[derive(Clone, Copy, Default)]
struct Cell {
    rgb: [i32; 3],
    /// R's absolute residual, for R's contexts.
    r_err: u32,
    /// The fit sums including this texel.
    sums: Sums,
}

/// A row of cells with one more on each side, so that the neighbours of every texel are
/// plain reads: index `x + 1` is column `x`. Past the right edge "up-right" is "up"; past
/// the left edge "left" and "up-left" are "up".
type Row = Vec<Cell>;

/// Contexts of each channel: G by gradient; R by G's error and R's activity; B by G's
/// and R's errors.
const G_CTX: usize = 0;
const R_CTX: usize = CTX;
const R_BY_G: usize = 6;
const R_BY_ACTIVITY: usize = 10;
const B_CTX: usize = 2 * CTX;
const B_BY_R: usize = 8;
const B_BY_G: usize = 8;
const _: () = assert!(R_BY_G * R_BY_ACTIVITY <= CTX && B_BY_R * B_BY_G <= CTX);

/// The model, shared by both ends: predicts and picks the context of every sample in
/// order, and `c` codes it.
fn run<C: Coder>(cells: u32, c: &mut C) {
    let n = cells as usize;
    let mut up: Row = vec![Cell::default(); n + 2];
    let mut cur: Row = vec![Cell::default(); n + 2];
    for z in 0..n {
        cur[0] = up[1];
        for x in 0..n {
            if z == 0 {
                // Above the first row is the left neighbour, so the row is predicted
                // from the left (and the first texel from zeros).
                up[x..x + 3].fill(cur[x]);
            }
            let i = (z * n + x) * 3;
            let (left, ul, above, ur) = (&cur[x], &up[x], &up[x + 1], &up[x + 2]);
            let (l, u) = (left.rgb, above.rgb);
            let spatial = |k: usize| (l[k] + u[k] + 1) >> 1;
            let sums = blend(&left.sums, &above.sums);
            let (w_r, w_b) = weights(&sums);

            // G: its spatial prediction, in a context of its gradient.
            let pg = spatial(1);
            let grad_g =
                (l[1] - ul.rgb[1]).abs() + (u[1] - ul.rgb[1]).abs() + (ur.rgb[1] - u[1]).abs();
            let g = i32::from(c.code(1, G_CTX + bucket(grad_g as u32, CTX), pg, i + 1));
            let eg = g - pg;

            // R: spatial plus the fit on G's error, in a context of G's error and R's
            // activity (the R − G gradient and the neighbours' R residuals).
            let sr = spatial(0);
            let pr = (sr + ((w_r * i64::from(eg) + 128) >> 8) as i32).clamp(0, 255);
            let d = |p: &Cell| p.rgb[0] - p.rgb[1];
            let grad_d =
                (d(left) - d(ul)).abs() + (d(above) - d(ul)).abs() + (d(ur) - d(above)).abs();
            let activity = grad_d as u32 + left.r_err + above.r_err;
            let ctx = R_CTX
                + bucket(eg.unsigned_abs(), R_BY_G) * R_BY_ACTIVITY
                + bucket(activity, R_BY_ACTIVITY);
            let r = i32::from(c.code(0, ctx, pr, i));
            let er = r - sr;

            // B: spatial plus the fit on G's and R's errors, in a context of those errors.
            let sb = spatial(2);
            let fit = w_b[0] * i64::from(eg) + w_b[1] * i64::from(er);
            let pb = (sb + ((fit + 128) >> 8) as i32).clamp(0, 255);
            let ctx = B_CTX
                + bucket(eg.unsigned_abs(), B_BY_G) * B_BY_R
                + bucket(er.unsigned_abs(), B_BY_R);
            let b = i32::from(c.code(2, ctx, pb, i + 2));
            let eb = b - sb;

            let add = [eg * eg, eg * er, er * er, eg * eb, er * eb];
            cur[x + 1] = Cell {
                rgb: [r, g, b],
                r_err: (r - pr).unsigned_abs(),
                sums: std::array::from_fn(|k| sums[k] + add[k]),
            };
        }
        cur[n + 1] = cur[n];
        std::mem::swap(&mut up, &mut cur);
        up[0] = up[1];
    }
}

/// The most bytes a coded map of `cells` a side may take: the raw texels and 64 KiB for
/// headers and tables. A viewer refuses more; a server never sends more.
pub fn max_len(cells: u32) -> usize {
    let c = cells as usize;
    c * c * 3 + (64 << 10)
}

/// Texels that do not make a colour map of the size given.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error(
    "a colour map of {cells} cells a side (1 ..= {MAX_CELLS} allowed) takes {expected} bytes of texels, got {got}"
)]
pub struct SizeError {
    pub cells: u32,
    pub expected: usize,
    pub got: usize,
}

/// Appends to `out` the colour map of `cells × cells` texels, `rgb` row-major, 3 bytes a
/// texel; an error (and nothing appended) if `cells` is not in 1 ..= 8192 or `rgb` is not
/// `cells² · 3` bytes.
pub fn encode(cells: u32, rgb: &[u8], out: &mut Vec<u8>) -> Result<(), SizeError> {
    let n = cells as usize * cells as usize * 3;
    if !(1..=MAX_CELLS).contains(&cells) || rgb.len() != n {
        return Err(SizeError {
            cells,
            expected: n,
            got: rgb.len(),
        });
    }
    out.push(FORMAT);
    out.extend_from_slice(&[0; 3]);
    out.extend_from_slice(&cells.to_le_bytes());
    out.extend_from_slice(&check(rgb).to_le_bytes());
    let mut enc = Enc {
        rgb,
        syms: std::array::from_fn(|_| rans::Encoder::with_capacity(n / 3)),
        bits: rans::BitWriter::default(),
    };
    run(cells, &mut enc);
    let mut counts = vec![[0; rans::ALPHABET]; CONTEXTS];
    for s in &enc.syms {
        s.count(&mut counts);
    }
    let tables = rans::EncTables::new(&counts, out);
    for s in enc.syms {
        s.finish(&tables, out);
    }
    out.extend_from_slice(&enc.bits.finish());
    Ok(())
}

/// Decodes a colour map of `cells × cells` texels into `out` (cleared first): `cells² · 3`
/// bytes, row-major RGB. On error `out` holds nothing usable.
pub fn decode(cells: u32, bytes: &[u8], out: &mut Vec<u8>) -> Result<(), DecodeError> {
    out.clear();
    let Some((head, body)) = bytes.split_at_checked(HEADER) else {
        return Err(DecodeError::Short(bytes.len()));
    };
    if head[0] != FORMAT {
        return Err(DecodeError::Format(head[0]));
    }
    if head[1..4] != [0; 3] {
        return Err(DecodeError::Corrupt("unknown colour map flags"));
    }
    let got = u32::from_le_bytes([head[4], head[5], head[6], head[7]]);
    if got != cells || !(1..=MAX_CELLS).contains(&cells) {
        return Err(DecodeError::Cells {
            got,
            expected: cells,
        });
    }
    let mut declared = [0u8; 8];
    declared.copy_from_slice(&head[8..16]);
    let Some((tables, body)) = rans::DecTables::read(CONTEXTS, body) else {
        return Err(DecodeError::Corrupt("invalid colour map tables"));
    };
    let stream =
        |body| rans::Decoder::new(body).ok_or(DecodeError::Corrupt("colour map symbols cut short"));
    let (r, body) = stream(body)?;
    let (g, body) = stream(body)?;
    let (b, raw) = stream(body)?;
    let n = cells as usize * cells as usize * 3;
    out.resize(n, 0);
    let mut dec = Dec {
        out: out.as_mut_slice(),
        tables: &tables,
        syms: [r, g, b],
        bits: rans::BitReader::new(raw),
    };
    run(cells, &mut dec);
    if dec.syms.iter().any(|s| s.failed()) || dec.bits.failed() {
        out.clear();
        return Err(DecodeError::Corrupt(
            "the colour map's coded texels are cut short or damaged",
        ));
    }
    if check(out) != u64::from_le_bytes(declared) {
        out.clear();
        return Err(DecodeError::Check);
    }
    Ok(())
}
