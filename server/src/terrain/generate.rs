//! Synthetic terrain and colour maps.
//!
//! [`heights`] is a seeded, deterministic fBm generator (gradient noise, domain-warped, with
//! ridged mountains and flattened lowlands) for any `2^N + 1` side; [`colorize`] derives a
//! colour per cell from height and slope; [`synthetic`] makes a complete data set. Only
//! integer hashing and `+ − × ÷` touch the samples, so the output depends on the seed alone.

use crate::terrain::dataset::{ColorMap, Terrain};
use crate::terrain::heightfield::{Heightfield, ShapeError};
use crate::terrain::map::{MapParams, Start};

/// Largest sample the generator produces (of 65535): leaves head-room for edits.
pub const MAX_SAMPLE: u16 = 40_000;

/// splitmix64: a tiny, well-mixed 64-bit PRNG / hash step.
#[derive(Clone, Debug)]
pub struct SplitMix64(pub u64);

impl SplitMix64 {
    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix(self.0)
    }
}

/// The splitmix64 finaliser.
fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Hash of a lattice point for one noise layer.
fn hash(layer: u64, x: i64, z: i64) -> u64 {
    mix(layer ^ mix((x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (z as u64)))
}

const R2: f64 = std::f64::consts::FRAC_1_SQRT_2;
/// cos 22.5°.
const C8: f64 = 0.923_879_532_511_286_7;
/// sin 22.5°.
const S8: f64 = 0.382_683_432_365_089_8;

/// 16 unit gradients, spaced evenly around the circle.
const GRADS: [(f64, f64); 16] = [
    (1.0, 0.0),
    (C8, S8),
    (R2, R2),
    (S8, C8),
    (0.0, 1.0),
    (-S8, C8),
    (-R2, R2),
    (-C8, S8),
    (-1.0, 0.0),
    (-C8, -S8),
    (-R2, -R2),
    (-S8, -C8),
    (0.0, -1.0),
    (S8, -C8),
    (R2, -R2),
    (C8, -S8),
];

fn fade(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a + (b - a) * t
}

fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// 2D gradient noise, roughly in −0.7 ..= 0.7, zero at lattice points.
fn noise(layer: u64, x: f64, z: f64) -> f64 {
    let (x0, z0) = (x.floor(), z.floor());
    let (fx, fz) = (x - x0, z - z0);
    let (ix, iz) = (x0 as i64, z0 as i64);
    let dot = |cx: i64, cz: i64, dx: f64, dz: f64| {
        let (gx, gz) = GRADS[(hash(layer, cx, cz) >> 60) as usize];
        gx * dx + gz * dz
    };
    let (u, v) = (fade(fx), fade(fz));
    let a = lerp(dot(ix, iz, fx, fz), dot(ix + 1, iz, fx - 1.0, fz), u);
    let b = lerp(
        dot(ix, iz + 1, fx, fz - 1.0),
        dot(ix + 1, iz + 1, fx - 1.0, fz - 1.0),
        u,
    );
    lerp(a, b, v)
}

/// Fractal sum of `octaves` noise layers, normalised to roughly −1 ..= 1.
fn fbm(layer: u64, x: f64, z: f64, octaves: u32, gain: f64) -> f64 {
    let (mut sum, mut amp, mut freq, mut norm) = (0.0, 1.0, 1.0, 0.0);
    for o in 0..octaves {
        sum += amp
            * noise(
                layer.wrapping_add(u64::from(o) * 0x51_7CC1),
                x * freq,
                z * freq,
            );
        norm += amp;
        amp *= gain;
        freq *= 2.0;
    }
    sum / norm * 1.6
}

/// Ridged fractal: sharp crests where the noise crosses zero, in 0 ..= ~1.
fn ridged(layer: u64, x: f64, z: f64, octaves: u32) -> f64 {
    let (mut sum, mut amp, mut freq, mut norm, mut weight) = (0.0, 1.0, 1.0, 0.0, 1.0);
    for o in 0..octaves {
        let n = noise(
            layer.wrapping_add(u64::from(o) * 0x2F_0A31),
            x * freq,
            z * freq,
        );
        let r = (1.0 - 1.5 * n.abs()).max(0.0);
        let r = r * r * weight;
        weight = (r * 1.5).clamp(0.0, 1.0);
        sum += amp * r;
        norm += amp;
        amp *= 0.5;
        freq *= 2.0;
    }
    sum / norm
}

/// Deterministic fBm terrain of `side = 2^N + 1` samples in `0 ..= MAX_SAMPLE`: rolling hills,
/// ridged mountain ranges, valleys and flat lowland basins. Same `(side, seed)`, same samples.
pub fn heights(side: u32, seed: u64) -> Result<Heightfield, ShapeError> {
    heights_with(side, seed, 1, &mut |_, _| {})
}

/// [`heights`] on `threads` threads (the bytes do not depend on how many), reporting
/// `progress(rows done, rows in all)` as it goes: each sample's noise is computed once and
/// kept (8 bytes a sample while generating) for the shaping pass that needs the whole
/// map's range.
pub fn heights_with(
    side: u32,
    seed: u64,
    threads: usize,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<Heightfield, ShapeError> {
    if crate::terrain::heightfield::levels_of_side(u64::from(side)).is_none() {
        return Err(ShapeError::Side {
            side: u64::from(side),
        });
    }
    let mut rng = SplitMix64(seed);
    let layers: [u64; 5] = std::array::from_fn(|_| rng.next_u64());
    let cells = f64::from(side - 1);
    // Detail down to about two samples per noise period.
    let octaves = (side - 1).ilog2().saturating_sub(1).max(1);
    let base = 3.0; // noise periods across the map for the largest features
    let raw = |x: u32, z: u32| {
        let (u, v) = (f64::from(x) / cells * base, f64::from(z) / cells * base);
        // Domain warp: bends valleys and ridges so they do not follow the lattice.
        let wu = u + 0.35 * fbm(layers[0], u * 0.7, v * 0.7, 4, 0.5);
        let wv = v + 0.35 * fbm(layers[1], u * 0.7 + 5.2, v * 0.7 + 1.3, 4, 0.5);
        let t = 0.5 + 0.5 * fbm(layers[2], wu, wv, octaves, 0.47);
        let mountains = smoothstep(0.5, 0.8, t);
        let r = ridged(layers[3], wu * 1.3, wv * 1.3, octaves);
        let hills_octaves = octaves.saturating_sub(2).max(1);
        let hills = 0.05 * fbm(layers[4], u * 4.0, v * 4.0, hills_octaves, 0.55);
        t + 0.6 * mountains * r + hills
    };
    // Pass 1: every sample's noise, the range, and the 25th percentile from at most 1025²
    // evenly spread samples (all of them up to side 1025). Rows go in slabs, each split
    // among the threads; minimum, maximum and a sorted subset do not depend on the split.
    let n = side as usize;
    let stride = ((side - 1) / 1024).max(1);
    let (mut lo, mut hi) = (f64::MAX, f64::MIN);
    let mut subset = Vec::new();
    let mut noise = vec![0f64; n * n];
    let threads = threads.max(1);
    let slab = 64usize;
    let rows_total = 2 * u64::from(side);
    for z0 in (0..n).step_by(slab) {
        let rows = slab.min(n - z0);
        let per = rows.div_ceil(threads);
        let parts: Vec<(f64, f64, Vec<f64>)> = std::thread::scope(|scope| {
            let raw = &raw;
            let handles: Vec<_> = noise[z0 * n..(z0 + rows) * n]
                .chunks_mut(per * n)
                .enumerate()
                .map(|(k, part)| {
                    let first = (z0 + k * per) as u32;
                    scope.spawn(move || {
                        let (mut lo, mut hi, mut picked) = (f64::MAX, f64::MIN, Vec::new());
                        for (r, row) in part.chunks_mut(n).enumerate() {
                            let z = first + r as u32;
                            for (x, h) in row.iter_mut().enumerate() {
                                let x = x as u32;
                                *h = raw(x, z);
                                lo = lo.min(*h);
                                hi = hi.max(*h);
                                if x.is_multiple_of(stride) && z.is_multiple_of(stride) {
                                    picked.push(*h);
                                }
                            }
                        }
                        (lo, hi, picked)
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| {
                    h.join()
                        .expect("noise is plain arithmetic: it does not panic")
                })
                .collect()
        });
        for (l, h, picked) in parts {
            lo = lo.min(l);
            hi = hi.max(h);
            subset.extend(picked);
        }
        progress((z0 + rows) as u64, rows_total);
    }
    subset.sort_by(f64::total_cmp);
    // Flatten everything below the 25th percentile into near-level basins and plains, and
    // steepen the highest ground a little.
    let floor = subset[subset.len() / 4];
    let shape = |h: f64| {
        if h < floor {
            -(floor - h) * 0.1
        } else {
            let n = (h - floor) / (hi - floor).max(1e-9);
            (hi - floor) * n * (0.7 + 0.3 * n)
        }
    };
    let (s_lo, s_hi) = (shape(lo), shape(hi));
    let span = (s_hi - s_lo).max(1e-9);
    // Pass 2: the same values, shaped and quantised.
    let mut samples = Vec::with_capacity(n * n);
    for (z, row) in noise.chunks(n).enumerate() {
        samples.extend(
            row.iter()
                .map(|&h| ((shape(h) - s_lo) / span * f64::from(MAX_SAMPLE)).round() as u16),
        );
        if z % slab == slab - 1 || z == n - 1 {
            progress(u64::from(side) + z as u64 + 1, rows_total);
        }
    }
    drop(noise);
    Heightfield::new(side, samples)
}

/// Linear blend of two colours.
fn mix_rgb(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    [
        lerp(a[0], b[0], t),
        lerp(a[1], b[1], t),
        lerp(a[2], b[2], t),
    ]
}

/// Land colours by relative altitude (0 = shore or lowest point, 1 = highest).
const LAND: [(f64, [f64; 3]); 6] = [
    (0.00, [74.0, 118.0, 50.0]),   // lush lowland
    (0.30, [90.0, 126.0, 56.0]),   // grass
    (0.55, [108.0, 118.0, 64.0]),  // scrub
    (0.75, [126.0, 110.0, 82.0]),  // brown uplands
    (0.90, [150.0, 142.0, 130.0]), // bare rock
    (1.00, [212.0, 208.0, 200.0]), // pale summits
];
const DRY: [f64; 3] = [150.0, 142.0, 84.0]; // savanna patches
const FOREST: [f64; 3] = [46.0, 84.0, 38.0]; // dense forest patches
const ROCK: [f64; 3] = [138.0, 126.0, 110.0]; // steep slopes
const SAND: [f64; 3] = [184.0, 166.0, 120.0];
const SHALLOW: [f64; 3] = [58.0, 112.0, 138.0];
const DEEP: [f64; 3] = [22.0, 52.0, 92.0];

fn land(a: f64) -> [f64; 3] {
    let a = a.clamp(0.0, 1.0);
    for w in LAND.windows(2) {
        let ((a0, c0), (a1, c1)) = (w[0], w[1]);
        if a <= a1 {
            return mix_rgb(c0, c1, (a - a0) / (a1 - a0));
        }
    }
    LAND[LAND.len() - 1].1
}

/// Topographic position of every cell, row by row: the mean sample height (in samples) in a
/// window of `2r × 2r` samples centred on the cell, minus the cell's own mean. Positive in
/// valleys and hollows, negative on ridges. Sliding sums: O(side) memory, O(side²) time.
struct Hollows<'h> {
    heights: &'h Heightfield,
    r: u32,
    z: u32,
    /// Column sums of samples over the rows `rows.0 ..= rows.1`.
    colsum: Vec<u64>,
    rows: (u32, u32),
    /// No row made yet: the column sums start from nothing.
    fresh: bool,
    prefix: Vec<u64>,
    row: Vec<f64>,
}

impl<'h> Hollows<'h> {
    /// Rows from cell row `z` on. The sums are integers, so a band started anywhere gives
    /// the same rows as one started at 0.
    fn starting_at(heights: &'h Heightfield, r: u32, z: u32) -> Self {
        let side = heights.side() as usize;
        Hollows {
            heights,
            r,
            z,
            fresh: true,
            colsum: vec![0; side],
            rows: (0, 0),
            prefix: vec![0; side + 1],
            row: vec![0.0; side - 1],
        }
    }

    /// The window of samples around cell index `i` (samples `i` and `i + 1`), clamped.
    fn window(&self, i: u32) -> (u32, u32) {
        let last = self.heights.side() - 1;
        (i.saturating_sub(self.r - 1), (i + self.r).min(last))
    }

    /// Hollowness of the next row of cells (in samples).
    fn next_row(&mut self) -> &[f64] {
        let hf = self.heights;
        let side = hf.side();
        let (z0, z1) = self.window(self.z);
        if self.fresh {
            self.fresh = false;
            for z in z0..=z1 {
                for x in 0..side {
                    self.colsum[x as usize] += u64::from(hf.get(x, z));
                }
            }
        } else {
            for z in self.rows.0..z0 {
                for x in 0..side {
                    self.colsum[x as usize] -= u64::from(hf.get(x, z));
                }
            }
            for z in self.rows.1 + 1..=z1 {
                for x in 0..side {
                    self.colsum[x as usize] += u64::from(hf.get(x, z));
                }
            }
        }
        self.rows = (z0, z1);
        for (i, &c) in self.colsum.iter().enumerate() {
            self.prefix[i + 1] = self.prefix[i] + c;
        }
        let rows = f64::from(z1 - z0 + 1);
        let z = self.z;
        for x in 0..side - 1 {
            let (x0, x1) = self.window(x);
            let sum = self.prefix[x1 as usize + 1] - self.prefix[x0 as usize];
            let mean = sum as f64 / (rows * f64::from(x1 - x0 + 1));
            let cell = f64::from(
                u32::from(hf.get(x, z))
                    + u32::from(hf.get(x + 1, z))
                    + u32::from(hf.get(x, z + 1))
                    + u32::from(hf.get(x + 1, z + 1)),
            ) / 4.0;
            self.row[x as usize] = mean - cell;
        }
        self.z += 1;
        &self.row
    }
}

/// One colour per cell from the mean height of its four corners, its slope and its
/// position in the landscape: water below `map.water_level` (darker with depth), sand just
/// above it, greens in the lowlands with forest along valleys and drier grass on ridges,
/// browns and rock higher up and on steep slopes (rise over run ≳ 0.4), pale rock on the
/// highest ground. Deterministic.
pub fn colorize(heights: &Heightfield, map: &MapParams) -> ColorMap {
    colorize_with(heights, map, 1, &mut |_, _| {})
}

/// [`colorize`] on `threads` threads in bands of rows, reporting `progress(rows done, rows
/// in all)`. The bytes do not depend on the thread count: the hollows' RMS adds per-row sums
/// in row order, and every texel depends only on its own neighbourhood. Measured on 4097²
/// (2 cores): 2.6 s on one thread, about half that on two.
pub fn colorize_with(
    heights: &Heightfield,
    map: &MapParams,
    threads: usize,
    progress: &mut dyn FnMut(u64, u64),
) -> ColorMap {
    let cells = heights.size();
    let (lo, hi) = heights.range();
    let (lo, hi) = (f64::from(lo) * map.v_scale, f64::from(hi) * map.v_scale);
    let range = (hi - lo).max(1e-9);
    let water = map.water_level;
    let land_lo = water.map_or(lo, |w| w.clamp(lo, hi));
    let land_range = (hi - land_lo).max(1e-9);
    let sand_band = range * 0.0025;
    let depth_scale = range * 0.06;
    let h = |x: u32, z: u32| f64::from(heights.get(x, z)) * map.v_scale;
    let patch_freq = 24.0 / f64::from(cells.max(1));
    // Valleys versus ridges, normalised by their RMS over the map.
    let radius = (cells / 256).clamp(2, 8);
    let total = 2 * u64::from(cells);
    let row_sums = in_sub_bands(0, cells, threads, |z0, z1| {
        let mut hollows = Hollows::starting_at(heights, radius, z0);
        (z0..z1)
            .map(|_| hollows.next_row().iter().map(|t| t * t).sum::<f64>())
            .collect::<Vec<f64>>()
    });
    progress(u64::from(cells), total);
    let mut sq = 0.0;
    for s in row_sums.iter().flatten() {
        sq += s;
    }
    let rms = (sq / f64::from(cells).powi(2)).sqrt().max(1e-9);
    let texel = |x: u32, z: u32, hollowness: f64| -> [u8; 3] {
        let (h00, h10, h01, h11) = (h(x, z), h(x + 1, z), h(x, z + 1), h(x + 1, z + 1));
        let mean = (h00 + h10 + h01 + h11) / 4.0;
        let dx = ((h10 + h11) - (h00 + h01)) / (2.0 * map.h_scale);
        let dz = ((h01 + h11) - (h00 + h10)) / (2.0 * map.h_scale);
        let slope = (dx * dx + dz * dz).sqrt();
        let grain = (hash(0x5EED, i64::from(x), i64::from(z)) >> 56) as f64 / 255.0 - 0.5;
        let c = match water {
            Some(w) if mean < w => mix_rgb(
                SHALLOW,
                DEEP,
                0.3 + 0.7 * smoothstep(0.0, depth_scale, w - mean),
            ),
            _ => {
                let a = (mean - land_lo) / land_range;
                let (u, v) = (f64::from(x) * patch_freq, f64::from(z) * patch_freq);
                let patches = fbm(0xC0FFEE, u, v, 5, 0.55);
                let hollow = hollowness / rms + 0.8 * patches;
                let mut c = land(a);
                // Forest in valleys, dry grass on ridges, fading out on high ground.
                let veg = 1.0 - smoothstep(0.6, 0.85, a);
                c = mix_rgb(c, FOREST, veg * smoothstep(0.0, 1.2, hollow) * 0.85);
                c = mix_rgb(c, DRY, veg * smoothstep(0.2, 1.4, -hollow) * 0.6);
                c = mix_rgb(c, ROCK, smoothstep(0.35, 0.9, slope));
                if let Some(w) = water {
                    c = mix_rgb(SAND, c, smoothstep(0.0, sand_band, mean - w));
                }
                c
            }
        };
        let j = 1.0 + 0.06 * grain;
        c.map(|v| (v * j).round().clamp(0.0, 255.0) as u8)
    };
    // Bands of at most 256 rows, so progress moves and each band's buffer stays small.
    let mut rgb = Vec::with_capacity(cells as usize * cells as usize);
    let band = 256u32.max(threads as u32);
    for b0 in (0..cells).step_by(band as usize) {
        let b1 = (b0 + band).min(cells);
        let parts = in_sub_bands(b0, b1, threads, |z0, z1| {
            let mut hollows = Hollows::starting_at(heights, radius, z0);
            let mut out = Vec::with_capacity(((z1 - z0) * cells) as usize);
            for z in z0..z1 {
                let row = hollows.next_row();
                out.extend((0..cells).map(|x| texel(x, z, row[x as usize])));
            }
            out
        });
        for p in parts {
            rgb.extend(p);
        }
        progress(u64::from(cells + b1), total);
    }
    ColorMap::new(cells, rgb).unwrap_or_else(|| unreachable!("cells² pixels were pushed"))
}

/// `f(z0, z1)` over rows `first .. end` split into `threads` contiguous bands (scoped
/// threads), results in row order.
fn in_sub_bands<T: Send>(
    first: u32,
    end: u32,
    threads: usize,
    f: impl Fn(u32, u32) -> T + Sync,
) -> Vec<T> {
    let per = (end - first).div_ceil(threads.max(1) as u32).max(1);
    let bands: Vec<(u32, u32)> = (first..end)
        .step_by(per as usize)
        .map(|z0| (z0, (z0 + per).min(end)))
        .collect();
    if bands.len() <= 1 {
        return bands.into_iter().map(|(a, b)| f(a, b)).collect();
    }
    std::thread::scope(|scope| {
        let f = &f;
        let handles: Vec<_> = bands
            .into_iter()
            .map(|(a, b)| scope.spawn(move || f(a, b)))
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .expect("colouring is plain arithmetic: it does not panic")
            })
            .collect()
    })
}

/// A complete synthetic data set: [`heights`] with `hScale` 10, `vScale = (side − 1)/32000`
/// (relief up to an eighth of the map's width), a lake level that floods the lowest basins,
/// fog that leaves 5 % contrast across the whole map, and a start on dry, gentle ground near
/// the centre facing the highest summit. Panics only for a `side` that is not `2^N + 1`
/// (a caller bug: check with [`crate::terrain::heightfield::levels_of_side`]).
pub fn synthetic(side: u32, seed: u64) -> Terrain {
    synthetic_with(side, seed, 1, &mut |_, _| {})
}

/// [`synthetic`] with its heights made on `threads` threads, reporting progress (the same
/// bytes).
pub fn synthetic_with(
    side: u32,
    seed: u64,
    threads: usize,
    progress: &mut dyn FnMut(u64, u64),
) -> Terrain {
    // One scale for both steps: heights report `2 · side` rows, colours `2 · (side − 1)`.
    let all = 4 * u64::from(side);
    let heights = match heights_with(side, seed, threads, &mut |d, _| progress(d, all)) {
        Ok(h) => h,
        Err(e) => panic!("synthetic: {e}"),
    };
    let h_scale = 10.0;
    let v_scale = f64::from(side - 1) / 32000.0;
    let mut map = MapParams::default_for_side(side);
    map.h_scale = h_scale;
    map.v_scale = v_scale;
    let world = map.world_size(side);
    map.fog_density = 3.0 / world;
    // Lakes: about the lowest 8 % of the samples, on the flattened basin floors.
    let mut histogram = vec![0u64; 65536];
    for &s in heights.samples() {
        histogram[usize::from(s)] += 1;
    }
    let rank = heights.samples().len() as u64 * 2 / 25;
    let mut seen = 0;
    let eighth = histogram
        .iter()
        .position(|&n| {
            seen += n;
            seen > rank
        })
        .unwrap_or(0);
    let water_sample = eighth as f64 + 0.5;
    map.water_level = Some((water_sample * v_scale * 1000.0).round() / 1000.0);
    map.start = pick_start(&heights, &map, water_sample);
    let first = 2 * u64::from(side);
    let color = colorize_with(&heights, &map, threads, &mut |d, _| {
        progress(first + d, all)
    });
    Terrain {
        map,
        heights,
        color: Some(color),
    }
}

/// The dry, gentle sample nearest the centre, facing the highest sample.
fn pick_start(heights: &Heightfield, map: &MapParams, water_sample: f64) -> Start {
    let side = heights.side();
    let c = i64::from(side / 2);
    let dry = f64::from(MAX_SAMPLE) * 0.05;
    let mut best: Option<(i64, u32, u32)> = None;
    let mut peak = (0u16, side / 2, side / 2);
    for z in 1..side - 1 {
        for x in 1..side - 1 {
            let s = heights.get(x, z);
            if s > peak.0 {
                peak = (s, x, z);
            }
            let around = [
                heights.get(x - 1, z),
                heights.get(x + 1, z),
                heights.get(x, z - 1),
                heights.get(x, z + 1),
            ];
            let rise = around
                .iter()
                .map(|&a| (f64::from(a) - f64::from(s)).abs() * map.v_scale)
                .fold(0.0, f64::max);
            let ok = f64::from(s) > water_sample + dry && rise < 0.25 * map.h_scale;
            let d = (i64::from(x) - c).pow(2) + (i64::from(z) - c).pow(2);
            if ok && best.is_none_or(|(bd, _, _)| d < bd) {
                best = Some((d, x, z));
            }
        }
    }
    let (_, x, z) = best.unwrap_or((0, side / 2, side / 2));
    let (dx, dz) = (
        f64::from(peak.1) - f64::from(x),
        f64::from(peak.2) - f64::from(z),
    );
    let heading = if dx == 0.0 && dz == 0.0 {
        0.0
    } else {
        (dx.atan2(dz).to_degrees() * 10.0).round() / 10.0
    };
    Start {
        x: f64::from(x) * map.h_scale,
        z: f64::from(z) * map.h_scale,
        heading_deg: heading.rem_euclid(360.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn range_and_shape() {
        let h = heights(65, 7).unwrap();
        let (lo, hi) = h.range();
        assert_eq!((lo, hi), (0, MAX_SAMPLE));
        assert!(heights(64, 7).is_err());
        let t = synthetic(33, 1);
        assert!(t.validate().is_ok());
    }

    /// Colours do not depend on the thread count either (bands of 256 rows, split further).
    #[test]
    fn colorize_threads_do_not_change_the_bytes() {
        let t = synthetic(513, 5);
        for threads in [2, 3] {
            let mut last = (0, 0);
            let c = colorize_with(&t.heights, &t.map, threads, &mut |d, n| last = (d, n));
            assert_eq!(Some(c), t.color, "{threads} threads");
            assert_eq!(last, (1024, 1024), "{threads} threads");
        }
    }

    /// The bytes do not depend on the thread count, across several 64-row slabs, and the
    /// progress reaches its total.
    #[test]
    fn threads_do_not_change_the_bytes() {
        let one = heights(257, 3).unwrap();
        for threads in [2, 3, 7] {
            let mut last = (0, 0);
            let many = heights_with(257, 3, threads, &mut |d, t| last = (d, t)).unwrap();
            assert_eq!(many, one, "{threads} threads");
            assert_eq!(last, (514, 514), "{threads} threads");
        }
    }
}
