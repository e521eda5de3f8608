//! The terrain's normals at the data's full resolution, as both ends see them: one normal
//! per map cell (the colour map's texel), its two-byte code, and a tile of codes coded
//! for the wire. The server builds a pyramid of them with the colour pyramid's layout
//! ([`crate::tiles::ColorLayout`]: level 0 is the cells, each next level the 2×2 parent)
//! and streams each tile right after its colour tile
//! ([`crate::messages::ServerMessage::NormalTile`]); the viewer lights every pixel with
//! them, whatever the cut drawn over them.
//!
//! Definitions (exact):
//!
//! - **A cell's normal** ([`cell_normal`]): the normal at the cell's centre of the
//!   bilinear patch through its four corner samples, from central differences —
//!   `gx = ((h10 + h11) − (h00 + h01)) · v / (2h)`, `gz = ((h01 + h11) − (h00 + h10)) ·
//!   v / (2h)` (heights in samples, `v` the map's vScale, `h` its hScale; `h10` is east of
//!   `h00`, `h01` south), normal `normalize(−gx, 1, −gz)`. Computed in `f64`.
//! - **A coarser level's normal**: the sum of its four children's unit normals (`f32`,
//!   before quantisation), renormalised — the average normal direction, so a rough patch
//!   seen from afar is lit as the mean of its facets, as filtering a normal map does.
//! - **The code** ([`encode`], [`decode`]): hemi-octahedral, a byte per axis. The upper
//!   hemisphere (every terrain normal has `ny > 0`) is projected onto the octahedron
//!   `|x| + |y| + |z| = 1` and its `(x, z)` turned 45° into the square `(a, b) = (x + z,
//!   x − z) ∈ [−1, 1]²`; each of `a`, `b` is stored as `round(127·v) + 128` (1 ..= 255),
//!   so a level cell is exactly `(128, 128)`. The square has no seam inside, so a GPU's
//!   bilinear filter of the two bytes (an `Rg8Unorm` texel) is a valid code too. Worst
//!   error over the hemisphere 0.54° (a test sweeps it), at 2 bytes a texel where
//!   `(nx, ny, nz)` in bytes would take 3 (or 4 in a GPU texel).
//! - **A tile on the wire** ([`encode_tile`], [`decode_tile`]): the codes through the
//!   colour map codec ([`crate::colormap`], lossless), `a` as its green channel (coded
//!   first, predicted from its neighbours), `b` as red (also fitted to green's error) and
//!   a constant 128 as blue, which costs nothing after the fit. Its limits and checks are
//!   the colour map's: a tile's payload is at most [`crate::colormap::max_len`] of its
//!   side, and a payload that is not a normal tile (blue not 128) is refused. Measured
//!   in `server/src/terrain/normal_pyramid.rs`'s header.

use crate::colormap;
use crate::format::DecodeError;

/// The blue channel of a normal tile on the wire (a constant: costs nothing).
const FILL: u8 = 128;

/// The normal of the cell whose corners hold `h00` (north-west), `h10` (north-east),
/// `h01` (south-west) and `h11` (south-east) samples, on a map of `h_scale` world units
/// between samples and `v_scale` per sample step (see the module's header).
pub fn cell_normal(h00: u16, h10: u16, h01: u16, h11: u16, h_scale: f64, v_scale: f64) -> [f32; 3] {
    let (h00, h10, h01, h11) = (
        f64::from(h00),
        f64::from(h10),
        f64::from(h01),
        f64::from(h11),
    );
    let k = v_scale / (2.0 * h_scale);
    let gx = ((h10 + h11) - (h00 + h01)) * k;
    let gz = ((h01 + h11) - (h00 + h10)) * k;
    let len = (gx * gx + 1.0 + gz * gz).sqrt();
    [(-gx / len) as f32, (1.0 / len) as f32, (-gz / len) as f32]
}

/// `v` scaled to unit length (`(0, 1, 0)` for a zero vector).
pub fn normalize(v: [f32; 3]) -> [f32; 3] {
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if len > 0.0 && len.is_finite() {
        [v[0] / len, v[1] / len, v[2] / len]
    } else {
        [0.0, 1.0, 0.0]
    }
}

/// The two-byte code of a unit normal of the upper hemisphere (a lower one is taken as on
/// the horizon).
pub fn encode(n: [f32; 3]) -> [u8; 2] {
    let (x, y, z) = (n[0], n[1].max(0.0), n[2]);
    let s = x.abs() + y + z.abs();
    if !(s > 0.0 && s.is_finite()) {
        return [128, 128];
    }
    let (px, pz) = (x / s, z / s);
    let q = |v: f32| ((v.clamp(-1.0, 1.0) * 127.0).round() as i32 + 128) as u8;
    [q(px + pz), q(px - pz)]
}

/// The unit normal a code stands for (any two bytes are one).
pub fn decode(c: [u8; 2]) -> [f32; 3] {
    let v = |b: u8| ((f32::from(b) - 128.0) / 127.0).clamp(-1.0, 1.0);
    let (a, b) = (v(c[0]), v(c[1]));
    let (px, pz) = ((a + b) / 2.0, (a - b) / 2.0);
    let y = (1.0 - px.abs() - pz.abs()).max(0.0);
    normalize([px, y, pz])
}

/// Appends to `out` the tile of `side × side` codes, row-major (see the module's header);
/// an error (nothing appended) when `codes` is not `side²` of them or `side` is not one
/// the colour map codec takes.
pub fn encode_tile(
    side: u32,
    codes: &[[u8; 2]],
    out: &mut Vec<u8>,
) -> Result<(), colormap::SizeError> {
    let rgb: Vec<u8> = codes.iter().flat_map(|&[a, b]| [b, a, FILL]).collect();
    if codes.len() as u64 != u64::from(side) * u64::from(side) {
        return Err(colormap::SizeError {
            cells: side,
            expected: side as usize * side as usize * 3,
            got: rgb.len(),
        });
    }
    colormap::encode(side, &rgb, out)
}

/// Decodes a tile of `side × side` codes into `out` (cleared first): `side² · 2` bytes,
/// `a` then `b` per texel, row-major. `out` is used as scratch for the colour map
/// decoder's `side² · 3` bytes on the way; on error it holds nothing usable.
pub fn decode_tile(side: u32, bytes: &[u8], out: &mut Vec<u8>) -> Result<(), DecodeError> {
    colormap::decode(side, bytes, out)?;
    let n = out.len() / 3;
    for i in 0..n {
        let (r, g, b) = (out[3 * i], out[3 * i + 1], out[3 * i + 2]);
        if b != FILL {
            out.clear();
            return Err(DecodeError::Corrupt(
                "not a normal tile (its third channel)",
            ));
        }
        out[2 * i] = g;
        out[2 * i + 1] = r;
    }
    out.truncate(2 * n);
    Ok(())
}

/// The angle between two unit vectors, degrees.
pub fn angle_deg(a: [f32; 3], b: [f32; 3]) -> f64 {
    let d: f64 = (0..3).map(|k| f64::from(a[k]) * f64::from(b[k])).sum();
    d.clamp(-1.0, 1.0).acos().to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_level_cell_is_straight_up_and_codes_exactly() {
        let n = cell_normal(700, 700, 700, 700, 30.0, 0.1);
        assert_eq!(n, [0.0, 1.0, 0.0]);
        assert_eq!(encode(n), [128, 128]);
        assert_eq!(decode([128, 128]), [0.0, 1.0, 0.0]);
    }

    #[test]
    fn a_slope_leans_away_from_its_rise() {
        // Rising east by 2 samples a cell at v/h = 0.5: gx = 1, the normal leans west.
        let n = cell_normal(0, 2, 0, 2, 1.0, 0.5);
        let r = std::f32::consts::FRAC_1_SQRT_2;
        assert!((n[0] + r).abs() < 1e-6 && (n[1] - r).abs() < 1e-6 && n[2] == 0.0);
        // Rising south: leans north (−z).
        let s = cell_normal(0, 0, 4, 4, 2.0, 0.5);
        assert!(s[2] < 0.0 && s[0] == 0.0);
    }

    #[test]
    fn codes_are_within_0_6_degrees_over_the_hemisphere() {
        let mut worst = 0.0f64;
        for i in 0..=200 {
            for j in 0..400 {
                let theta = f64::from(i) / 200.0 * 89.9f64.to_radians();
                let phi = f64::from(j) / 400.0 * std::f64::consts::TAU;
                let n = [
                    (theta.sin() * phi.cos()) as f32,
                    theta.cos() as f32,
                    (theta.sin() * phi.sin()) as f32,
                ];
                worst = worst.max(angle_deg(n, decode(encode(n))));
            }
        }
        assert!(worst < 0.6, "worst error {worst}°");
        // Every code decodes to a unit normal of the upper hemisphere.
        for a in 0..=255u8 {
            for b in 0..=255u8 {
                let n = decode([a, b]);
                let len = n.iter().map(|v| v * v).sum::<f32>();
                assert!((len - 1.0).abs() < 1e-5 && n[1] >= 0.0, "{a} {b}: {n:?}");
            }
        }
    }

    #[test]
    fn tiles_round_trip_and_other_payloads_are_refused() {
        let side = 16u32;
        let codes: Vec<[u8; 2]> = (0..side * side)
            .map(|i| [(100 + i % 17) as u8, (120 + (i / 16) % 9) as u8])
            .collect();
        let mut coded = Vec::new();
        encode_tile(side, &codes, &mut coded).expect("a tile");
        let mut out = Vec::new();
        decode_tile(side, &coded, &mut out).expect("decodes");
        assert_eq!(out, codes.iter().flatten().copied().collect::<Vec<u8>>());
        // A colour tile is not a normal tile.
        let rgb: Vec<u8> = (0..side * side * 3).map(|i| (i % 7) as u8).collect();
        let mut colour = Vec::new();
        colormap::encode(side, &rgb, &mut colour).expect("a colour tile");
        assert!(decode_tile(side, &colour, &mut out).is_err());
        assert!(decode_tile(8, &coded, &mut out).is_err());
        assert!(encode_tile(side, &codes[1..], &mut coded).is_err());
    }
}
