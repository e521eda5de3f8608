//! A raster of heights in metres, and the pipeline that turns any source raster into the
//! square `2^N + 1` grid of `u16` samples a data set holds. Pure: no I/O.
//!
//! - **Voids** are `NaN` samples. [`Raster::fill_voids`] fills them by *push–pull diffusion*:
//!   a pyramid is built by halving the raster, each coarse sample being the mean of the valid
//!   samples under it, until a level has no voids (there is one as soon as any sample is
//!   valid). Going back down, each void of a finer level starts from the bilinear
//!   interpolation of the level above and is then relaxed by [`RELAX_SWEEPS`] Gauss–Seidel
//!   sweeps of the Laplace equation (each void becomes the mean of its four neighbours), the
//!   valid samples held fixed. The coarse levels carry the large-scale shape across wide
//!   holes, the sweeps make the fill smooth and continuous with its rim; every filled value
//!   is a weighted mean of valid ones, so it never leaves their range (no spike to −32768 or
//!   to 0). The work is bounded: `O(samples)` for the pyramid plus
//!   `O(voids × RELAX_SWEEPS × 4/3)` for the sweeps.
//! - **Crop** ([`Raster::crop`]) takes a square window in source samples.
//! - **Padding and resampling** are one step, [`Raster::to_grid`]: the raster, whose samples
//!   are `dx` by `dy` metres apart (they differ for a geographic raster), is laid on a square
//!   grid of `side` samples `h_scale` apart that spans its longer extent; grid points beyond
//!   the shorter extent take the nearest edge sample (edge extension, never a cliff), and the
//!   others are bilinear interpolations. A square raster of the right side with square
//!   samples is copied unchanged.
//! - **Quantisation** ([`Raster::quantise`]) maps the lowest height to 0 (the map format has
//!   no vertical offset) and picks `vScale` as the range over 65535 steps, rounded up to three
//!   significant digits and at least [`MIN_V_SCALE`], so the heights keep all the precision
//!   16 bits allow.

use crate::terrain::heightfield::{Heightfield, MAX_LEVELS};

/// Largest side a raster may have on either axis: `2^15 + 1`.
pub const MAX_SIDE: u32 = (1 << MAX_LEVELS) + 1;
/// The smallest `vScale` chosen: a millimetre.
pub const MIN_V_SCALE: f64 = 0.001;
/// Gauss–Seidel sweeps per pyramid level when filling voids.
pub const RELAX_SWEEPS: usize = 16;

/// Why a raster cannot go through the pipeline.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RasterError {
    /// No valid sample to fill the voids from.
    #[error("every sample is a void (no data): nothing to fill the holes from")]
    AllVoid,
    /// A shape or an argument does not fit; the message says which and why.
    #[error("{0}")]
    Invalid(String),
}

/// A `width × height` raster of heights in metres, row-major; `NaN` marks a void.
#[derive(Clone, Debug, PartialEq)]
pub struct Raster {
    width: u32,
    height: u32,
    samples: Vec<f32>,
}

/// The result of [`Raster::quantise`].
#[derive(Clone, Debug)]
pub struct Quantised {
    /// The samples: `round((h − min) / v_scale)`.
    pub heights: Heightfield,
    /// Metres per sample step.
    pub v_scale: f64,
    /// The lowest height in metres, mapped to sample 0.
    pub min: f64,
    /// The highest height in metres.
    pub max: f64,
}

/// The smallest side `2^N + 1 ≥ longer` (`N ≥ 1`), capped at [`MAX_SIDE`].
pub fn default_side(longer: u32) -> u32 {
    let mut side = 3;
    while side < longer && side < MAX_SIDE {
        side = (side - 1) * 2 + 1;
    }
    side
}

impl Raster {
    /// A raster of `width × height` samples (both 1 ..= [`MAX_SIDE`]).
    pub fn new(width: u32, height: u32, samples: Vec<f32>) -> Result<Self, RasterError> {
        if !(1..=MAX_SIDE).contains(&width) || !(1..=MAX_SIDE).contains(&height) {
            return Err(RasterError::Invalid(format!(
                "{width} × {height} samples: expected 1 ..= {MAX_SIDE} on each side"
            )));
        }
        let want = width as usize * height as usize;
        if samples.len() != want {
            return Err(RasterError::Invalid(format!(
                "{} samples for {width} × {height}: expected {want}",
                samples.len()
            )));
        }
        Ok(Raster {
            width,
            height,
            samples,
        })
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    pub fn samples(&self) -> &[f32] {
        &self.samples
    }

    /// Height at column `x`, row `y` (`NaN` for a void). Panics out of range.
    pub fn get(&self, x: u32, y: u32) -> f32 {
        self.samples[y as usize * self.width as usize + x as usize]
    }

    /// Number of voids.
    pub fn voids(&self) -> usize {
        self.samples.iter().filter(|h| h.is_nan()).count()
    }

    /// Fill every void smoothly from the valid samples (see the module header). Returns how
    /// many were filled; an error when every sample is a void. `progress` gets
    /// `(samples of the pyramid's levels done, all of them)`.
    pub fn fill_voids(&mut self, progress: &mut dyn FnMut(u64, u64)) -> Result<usize, RasterError> {
        let voids = self.voids();
        if voids == 0 {
            return Ok(0);
        }
        if voids == self.samples.len() {
            return Err(RasterError::AllVoid);
        }
        let mut levels = vec![Level {
            w: self.width as usize,
            h: self.height as usize,
            v: std::mem::take(&mut self.samples),
        }];
        while let Some(top) = levels.last().filter(|l| l.v.iter().any(|h| h.is_nan())) {
            let next = top.halve();
            levels.push(next);
        }
        // Work is counted in samples of the levels filled, reported after every sweep.
        let total: u64 = levels[..levels.len() - 1]
            .iter()
            .map(|l| l.v.len() as u64)
            .sum();
        let mut done = 0;
        for k in (0..levels.len() - 1).rev() {
            let (fine, coarse) = levels.split_at_mut(k + 1);
            let size = fine[k].v.len() as u64;
            fine[k].fill_from(&coarse[0], &mut |sweeps| {
                progress(done + size * sweeps / RELAX_SWEEPS as u64, total);
            });
            done += size;
            // The coarse level is no longer needed.
            coarse[0].v = Vec::new();
        }
        self.samples = std::mem::take(&mut levels[0].v);
        Ok(voids)
    }

    /// The square window of `w × w` samples whose top-left sample is column `x`, row `y`.
    pub fn crop(&self, x: u32, y: u32, w: u32) -> Result<Raster, RasterError> {
        let fits = |start: u32, len: u32| u64::from(start) + u64::from(w) <= u64::from(len);
        if w < 2 || !fits(x, self.width) || !fits(y, self.height) {
            return Err(RasterError::Invalid(format!(
                "--crop {x},{y},{w}: expected a window of at least 2 × 2 samples inside the \
                 {} × {} raster (X + W ≤ {}, Y + W ≤ {})",
                self.width, self.height, self.width, self.height
            )));
        }
        let mut samples = Vec::with_capacity(w as usize * w as usize);
        for row in y..y + w {
            let start = row as usize * self.width as usize + x as usize;
            samples.extend_from_slice(&self.samples[start..start + w as usize]);
        }
        Raster::new(w, w, samples)
    }

    /// Lay the raster, samples `dx` (east) by `dy` (south) metres apart, on a square grid of
    /// `side` samples spanning its longer extent: padded with edge-extended heights on the
    /// shorter side and bilinearly resampled (see the module header). Returns the grid and
    /// its `h_scale` in metres. `progress` gets `(rows done, rows)`.
    pub fn to_grid(
        &self,
        dx: f64,
        dy: f64,
        side: u32,
        progress: &mut dyn FnMut(u64, u64),
    ) -> Result<(Raster, f64), RasterError> {
        if !(dx.is_finite() && dx > 0.0 && dy.is_finite() && dy > 0.0) {
            return Err(RasterError::Invalid(format!(
                "sample spacing {dx} × {dy} m: expected finite numbers > 0"
            )));
        }
        if !(3..=MAX_SIDE).contains(&side) {
            return Err(RasterError::Invalid(format!(
                "side {side}: expected 3 ..= {MAX_SIDE}"
            )));
        }
        let extent_x = f64::from(self.width - 1) * dx;
        let extent_y = f64::from(self.height - 1) * dy;
        let extent = extent_x.max(extent_y);
        if extent == 0.0 {
            let h = self.samples[0];
            let samples = vec![h; side as usize * side as usize];
            return Ok((Raster::new(side, side, samples)?, dx));
        }
        let h_scale = extent / f64::from(side - 1);
        if self.width == side && self.height == side && dx == dy {
            return Ok((self.clone(), dx));
        }
        let (w, h) = (self.width as usize, self.height as usize);
        // Source coordinate of each grid column / row, clamped to the raster: the clamp is
        // the edge extension.
        let axis = |n: usize, d: f64| -> Vec<(usize, usize, f32)> {
            (0..side)
                .map(|i| {
                    let s = (f64::from(i) * h_scale / d).min((n - 1) as f64);
                    let i0 = (s.floor() as usize).min(n - 1);
                    let i1 = (i0 + 1).min(n - 1);
                    (i0, i1, (s - i0 as f64) as f32)
                })
                .collect()
        };
        let xs = axis(w, dx);
        let ys = axis(h, dy);
        let mut out = Vec::new();
        let count = side as usize * side as usize;
        out.try_reserve_exact(count).map_err(|_| {
            RasterError::Invalid(format!("cannot allocate {count} samples for side {side}"))
        })?;
        for (row, &(y0, y1, fy)) in ys.iter().enumerate() {
            let (r0, r1) = (&self.samples[y0 * w..][..w], &self.samples[y1 * w..][..w]);
            out.extend(xs.iter().map(|&(x0, x1, fx)| {
                let top = r0[x0] + (r0[x1] - r0[x0]) * fx;
                let bottom = r1[x0] + (r1[x1] - r1[x0]) * fx;
                top + (bottom - top) * fy
            }));
            if row % 256 == 255 {
                progress(row as u64 + 1, u64::from(side));
            }
        }
        progress(u64::from(side), u64::from(side));
        Ok((Raster::new(side, side, out)?, h_scale))
    }

    /// The `u16` heightfield of a square `2^N + 1` raster without voids: the lowest height
    /// becomes 0, `v_scale` is `given` or chosen to keep the precision (module header).
    pub fn quantise(&self, given: Option<f64>) -> Result<Quantised, RasterError> {
        if self.width != self.height {
            return Err(RasterError::Invalid(format!(
                "{} × {} raster: expected a square",
                self.width, self.height
            )));
        }
        let (mut min, mut max) = (f64::INFINITY, f64::NEG_INFINITY);
        for &h in &self.samples {
            if !h.is_finite() {
                return Err(RasterError::Invalid(format!(
                    "expected finite heights (voids filled), got {h}"
                )));
            }
            min = min.min(f64::from(h));
            max = max.max(f64::from(h));
        }
        let range = max - min;
        let v_scale = match given {
            Some(v) if !(v.is_finite() && v > 0.0) => {
                return Err(RasterError::Invalid(format!(
                    "--v-scale: expected a finite number > 0, got {v}"
                )));
            }
            Some(v) => v,
            None => round_up_3(range / 65535.0).max(MIN_V_SCALE),
        };
        if range / v_scale > 65535.5 {
            return Err(RasterError::Invalid(format!(
                "--v-scale {v_scale}: heights span {range:.3} m, which needs at least {} m a \
                 step to fit 16 bits",
                round_up_3(range / 65535.0)
            )));
        }
        let samples = self
            .samples
            .iter()
            .map(|&h| ((f64::from(h) - min) / v_scale).round().min(65535.0) as u16)
            .collect();
        let heights = Heightfield::new(self.width, samples)
            .map_err(|e| RasterError::Invalid(e.to_string()))?;
        Ok(Quantised {
            heights,
            v_scale,
            min,
            max,
        })
    }
}

/// `x` rounded up to three significant digits (`x > 0`); 0 stays 0.
fn round_up_3(x: f64) -> f64 {
    if x <= 0.0 || !x.is_finite() {
        return 0.0;
    }
    // Dividing by a power of ten gives the correctly rounded decimal (154 / 1e4 = 0.0154).
    let exp = 2 - x.log10().floor() as i32;
    let up = if exp >= 0 {
        let scale = 10f64.powi(exp);
        (x * scale).ceil() / scale
    } else {
        let unit = 10f64.powi(-exp);
        (x / unit).ceil() * unit
    };
    // Guard against the scaling rounding below `x`.
    if up < x { up * (1.0 + 1e-12) } else { up }
}

/// One level of the void-filling pyramid.
struct Level {
    w: usize,
    h: usize,
    v: Vec<f32>,
}

impl Level {
    /// The next coarser level: each sample the mean of the valid ones in its 2 × 2 block.
    fn halve(&self) -> Level {
        let (w, h) = (self.w.div_ceil(2), self.h.div_ceil(2));
        let mut v = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let (mut sum, mut n) = (0.0f64, 0u32);
                for (sx, sy) in [(2 * x, 2 * y), (2 * x + 1, 2 * y), (2 * x, 2 * y + 1)]
                    .into_iter()
                    .chain([(2 * x + 1, 2 * y + 1)])
                {
                    if sx < self.w && sy < self.h {
                        let s = self.v[sy * self.w + sx];
                        if !s.is_nan() {
                            sum += f64::from(s);
                            n += 1;
                        }
                    }
                }
                v.push(if n == 0 {
                    f32::NAN
                } else {
                    (sum / f64::from(n)) as f32
                });
            }
        }
        Level { w, h, v }
    }

    /// Fill this level's voids from the (void-free) coarser level, then relax them;
    /// `progress` gets the sweeps done.
    fn fill_from(&mut self, coarse: &Level, progress: &mut dyn FnMut(u64)) {
        let holes: Vec<usize> = (0..self.v.len()).filter(|&i| self.v[i].is_nan()).collect();
        let at = |x: usize, y: usize| f64::from(coarse.v[y * coarse.w + x]);
        for &i in &holes {
            let (x, y) = (i % self.w, i / self.w);
            let cx = ((x as f64 + 0.5) / 2.0 - 0.5).clamp(0.0, (coarse.w - 1) as f64);
            let cy = ((y as f64 + 0.5) / 2.0 - 0.5).clamp(0.0, (coarse.h - 1) as f64);
            let (x0, y0) = (cx.floor() as usize, cy.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(coarse.w - 1), (y0 + 1).min(coarse.h - 1));
            let (fx, fy) = (cx - x0 as f64, cy - y0 as f64);
            let top = at(x0, y0) + (at(x1, y0) - at(x0, y0)) * fx;
            let bottom = at(x0, y1) + (at(x1, y1) - at(x0, y1)) * fx;
            self.v[i] = (top + (bottom - top) * fy) as f32;
        }
        for sweep in 0..RELAX_SWEEPS {
            for &i in &holes {
                let (x, y) = (i % self.w, i / self.w);
                let (mut sum, mut n) = (0.0f64, 0u32);
                if x > 0 {
                    sum += f64::from(self.v[i - 1]);
                    n += 1;
                }
                if x + 1 < self.w {
                    sum += f64::from(self.v[i + 1]);
                    n += 1;
                }
                if y > 0 {
                    sum += f64::from(self.v[i - self.w]);
                    n += 1;
                }
                if y + 1 < self.h {
                    sum += f64::from(self.v[i + self.w]);
                    n += 1;
                }
                if n > 0 {
                    self.v[i] = (sum / f64::from(n)) as f32;
                }
            }
            progress(sweep as u64 + 1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn none(_: u64, _: u64) {}

    fn plane(w: u32, h: u32) -> Raster {
        let samples = (0..h)
            .flat_map(|y| (0..w).map(move |x| 100.0 + x as f32 + 2.0 * y as f32))
            .collect();
        Raster::new(w, h, samples).unwrap()
    }

    #[test]
    fn default_sides() {
        for (longer, want) in [
            (1, 3),
            (3, 3),
            (4, 5),
            (65, 65),
            (1201, 2049),
            (3601, 4097),
            (40000, MAX_SIDE),
        ] {
            assert_eq!(default_side(longer), want, "{longer}");
        }
    }

    #[test]
    fn fill_is_smooth_and_in_range() {
        let mut r = plane(50, 40);
        let mut holes = 0;
        for y in 10..25 {
            for x in 5..30 {
                r.samples[y * 50 + x] = f32::NAN;
                holes += 1;
            }
        }
        // A void on the border too.
        r.samples[0] = f32::NAN;
        holes += 1;
        let mut reports = Vec::new();
        assert_eq!(
            r.fill_voids(&mut |d, t| reports.push((d, t))).unwrap(),
            holes
        );
        assert_eq!(r.voids(), 0);
        // Progress: one report a sweep a level, never backwards, ending at the total.
        let total = reports[0].1;
        assert!(
            reports
                .windows(2)
                .all(|w| w[0].0 <= w[1].0 && w[1].1 == total)
        );
        assert_eq!(reports.last(), Some(&(total, total)));
        assert_eq!(reports.len() % RELAX_SWEEPS, 0);
        let want = plane(50, 40);
        for (i, (&got, &exact)) in r.samples.iter().zip(&want.samples).enumerate() {
            // A plane is harmonic: the fill lands near it.
            assert!((got - exact).abs() < 3.0, "sample {i}: {got} vs {exact}");
            assert!(
                (100.0..=100.0 + 49.0 + 78.0).contains(&got),
                "sample {i}: {got}"
            );
        }
    }

    #[test]
    fn fill_errors_and_no_op() {
        let mut r = Raster::new(3, 2, vec![f32::NAN; 6]).unwrap();
        assert_eq!(r.fill_voids(&mut none), Err(RasterError::AllVoid));
        let mut r = plane(4, 4);
        assert_eq!(r.fill_voids(&mut none), Ok(0));
        assert_eq!(r, plane(4, 4));
        let mut r = Raster::new(3, 1, vec![f32::NAN, 7.0, f32::NAN]).unwrap();
        assert_eq!(r.fill_voids(&mut none), Ok(2));
        assert_eq!(r.samples, vec![7.0; 3]);
    }

    #[test]
    fn crop_windows() {
        let r = plane(10, 8);
        let c = r.crop(2, 3, 5).unwrap();
        assert_eq!((c.width, c.height), (5, 5));
        assert_eq!(c.get(0, 0), r.get(2, 3));
        assert_eq!(c.get(4, 4), r.get(6, 7));
        for (x, y, w) in [(6, 0, 5), (0, 4, 5), (0, 0, 1), (u32::MAX, 0, 2)] {
            let err = r.crop(x, y, w).unwrap_err().to_string();
            assert!(err.contains("--crop") && err.contains("10 × 8"), "{err}");
        }
    }

    #[test]
    fn grid_pads_with_edges_and_resamples() {
        let r = plane(40, 20);
        let (g, h_scale) = r.to_grid(1.0, 1.0, 65, &mut none).unwrap();
        assert_eq!((g.width, g.height), (65, 65));
        assert!((h_scale - 39.0 / 64.0).abs() < 1e-12);
        for x in 0..65 {
            let sx = (f64::from(x) * h_scale).min(39.0) as f32;
            // The last row repeats the raster's bottom edge (row 19): no cliff.
            let want = 100.0 + sx + 38.0;
            assert!((g.get(x, 64) - want).abs() < 1e-3, "{x}: {}", g.get(x, 64));
            assert!((g.get(x, 0) - (100.0 + sx)).abs() < 1e-3);
        }
        assert!(g.samples.iter().all(|&h| (100.0..=177.0).contains(&h)));
        // Already a grid: unchanged.
        let sq = plane(9, 9);
        assert_eq!(
            sq.to_grid(2.0, 2.0, 9, &mut none).unwrap(),
            (sq.clone(), 2.0)
        );
        // Non-square samples: the grid spans the longer extent (9 × 3 m rows).
        let (g, h_scale) = sq.to_grid(1.0, 3.0, 9, &mut none).unwrap();
        assert_eq!(h_scale, 3.0);
        assert_eq!(g.get(2, 1), sq.get(6, 1));
        assert_eq!(g.get(8, 8), sq.get(8, 8));
    }

    #[test]
    fn quantise_keeps_precision() {
        let r = Raster::new(
            3,
            3,
            vec![-5.0, 0.0, 1000.0, 10.5, 2.25, 3.0, 4.0, 5.0, 6.0],
        )
        .unwrap();
        let q = r.quantise(None).unwrap();
        assert_eq!((q.min, q.max), (-5.0, 1000.0));
        assert_eq!(q.v_scale, 0.0154);
        for (&s, &h) in q.heights.samples().iter().zip(&r.samples) {
            let back = q.min + f64::from(s) * q.v_scale;
            assert!((back - f64::from(h)).abs() <= q.v_scale / 2.0 + 1e-9);
        }
        let flat = Raster::new(3, 3, vec![7.0; 9])
            .unwrap()
            .quantise(None)
            .unwrap();
        assert_eq!(flat.v_scale, MIN_V_SCALE);
        assert!(flat.heights.samples().iter().all(|&s| s == 0));
        let err = r.quantise(Some(0.01)).unwrap_err().to_string();
        assert!(err.contains("--v-scale 0.01"), "{err}");
        assert_eq!(round_up_3(0.0457763), 0.0458);
    }
}
