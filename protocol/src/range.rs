//! A binary adaptive range coder (the LZMA design): each bit is coded with an 11-bit
//! probability that adapts after every use, so well-predicted bits cost a small fraction of
//! a bit.
//!
//! The decoder never panics and never reads past its input: past the end it reads zero
//! bytes and counts them, and [`Decoder::overrun`] says whether it needed more than the
//! encoder's flush can account for (a truncated or corrupt stream).

const PROB_BITS: u32 = 11;
const ONE: u32 = 1 << PROB_BITS;
const MOVE_BITS: u32 = 5;
const TOP: u32 = 1 << 24;

/// An adaptive probability that the next bit is 0.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Prob(u16);

impl Default for Prob {
    fn default() -> Self {
        Prob((ONE / 2) as u16)
    }
}

pub(crate) struct Encoder {
    low: u64,
    range: u32,
    cache: u8,
    cache_size: u64,
    out: Vec<u8>,
}

impl Encoder {
    /// An encoder appending to `out`.
    pub(crate) fn new(out: Vec<u8>) -> Encoder {
        Encoder {
            low: 0,
            range: u32::MAX,
            cache: 0,
            cache_size: 1,
            out,
        }
    }

    fn shift_low(&mut self) {
        if (self.low as u32) < 0xff00_0000 || (self.low >> 32) != 0 {
            let carry = (self.low >> 32) as u8;
            let mut byte = self.cache;
            loop {
                self.out.push(byte.wrapping_add(carry));
                byte = 0xff;
                self.cache_size -= 1;
                if self.cache_size == 0 {
                    break;
                }
            }
            self.cache = (self.low >> 24) as u8;
        }
        self.cache_size += 1;
        self.low = (self.low & 0x00ff_ffff) << 8;
    }

    #[inline]
    pub(crate) fn bit(&mut self, p: &mut Prob, bit: bool) {
        let bound = (self.range >> PROB_BITS) * u32::from(p.0);
        if bit {
            self.low += u64::from(bound);
            self.range -= bound;
            p.0 -= p.0 >> MOVE_BITS;
        } else {
            self.range = bound;
            p.0 += ((ONE - u32::from(p.0)) >> MOVE_BITS) as u16;
        }
        while self.range < TOP {
            self.range <<= 8;
            self.shift_low();
        }
    }

    /// `n` (≤ 32) low bits of `v`, most significant first, each with probability ½.
    pub(crate) fn direct(&mut self, v: u32, n: u32) {
        for i in (0..n).rev() {
            self.range >>= 1;
            if v >> i & 1 != 0 {
                self.low += u64::from(self.range);
            }
            while self.range < TOP {
                self.range <<= 8;
                self.shift_low();
            }
        }
    }

    /// `n` (≤ 8) low bits of `v` through a bit tree of `2^n` probabilities.
    pub(crate) fn tree(&mut self, probs: &mut [Prob], v: u32, n: u32) {
        let mut node = 1usize;
        for i in (0..n).rev() {
            let bit = v >> i & 1 != 0;
            self.bit(&mut probs[node], bit);
            node = node * 2 + usize::from(bit);
        }
    }

    /// Flushes and returns the output.
    pub(crate) fn finish(mut self) -> Vec<u8> {
        for _ in 0..5 {
            self.shift_low();
        }
        self.out
    }
}

pub(crate) struct Decoder<'a> {
    input: &'a [u8],
    pos: usize,
    range: u32,
    code: u32,
    /// Bytes read past the end of the input.
    past_end: usize,
    /// The stream's first byte was not 0, or the code left the range: not our encoding.
    bad: bool,
}

impl<'a> Decoder<'a> {
    pub(crate) fn new(input: &'a [u8]) -> Decoder<'a> {
        let mut d = Decoder {
            input,
            pos: 0,
            range: u32::MAX,
            code: 0,
            past_end: 0,
            bad: false,
        };
        d.bad = d.byte() != 0;
        for _ in 0..4 {
            d.code = (d.code << 8) | u32::from(d.byte());
        }
        d
    }

    #[inline]
    fn byte(&mut self) -> u8 {
        match self.input.get(self.pos) {
            Some(&b) => {
                self.pos += 1;
                b
            }
            None => {
                self.past_end += 1;
                0
            }
        }
    }

    #[inline]
    fn normalize(&mut self) {
        while self.range < TOP {
            self.range <<= 8;
            self.code = (self.code << 8) | u32::from(self.byte());
        }
    }

    #[inline]
    pub(crate) fn bit(&mut self, p: &mut Prob) -> bool {
        let bound = (self.range >> PROB_BITS) * u32::from(p.0);
        let bit = if self.code < bound {
            self.range = bound;
            p.0 += ((ONE - u32::from(p.0)) >> MOVE_BITS) as u16;
            false
        } else {
            self.code = self.code.wrapping_sub(bound);
            self.range -= bound;
            p.0 -= p.0 >> MOVE_BITS;
            true
        };
        if self.code >= self.range {
            self.bad = true;
        }
        self.normalize();
        bit
    }

    pub(crate) fn direct(&mut self, n: u32) -> u32 {
        let mut v = 0;
        for _ in 0..n {
            self.range >>= 1;
            let bit = self.code >= self.range;
            if bit {
                self.code -= self.range;
            }
            v = (v << 1) | u32::from(bit);
            self.normalize();
        }
        v
    }

    pub(crate) fn tree(&mut self, probs: &mut [Prob], n: u32) -> u32 {
        let mut node = 1usize;
        for _ in 0..n {
            let bit = self.bit(&mut probs[node]);
            node = node * 2 + usize::from(bit);
        }
        (node - (1 << n)) as u32
    }

    /// Whether the stream was not a valid encoding or ended early (the encoder's flush
    /// leaves 4 bytes of slack that a decoder may read).
    pub(crate) fn failed(&self) -> bool {
        self.bad || self.past_end > 4
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bits_round_trip_and_skewed_bits_are_cheap() {
        let pattern: Vec<bool> = (0..20_000u32).map(|i| i % 37 == 0).collect();
        let mut p = Prob::default();
        let mut e = Encoder::new(Vec::new());
        for &b in &pattern {
            e.bit(&mut p, b);
        }
        e.direct(0xdead_beef, 32);
        let mut tree = [Prob::default(); 64];
        e.tree(&mut tree, 45, 6);
        let bytes = e.finish();
        // About 0.2 bits per bit at p = 1/37.
        assert!(bytes.len() < 20_000 / 8 / 3, "{} bytes", bytes.len());
        let mut d = Decoder::new(&bytes);
        let mut p = Prob::default();
        for (i, &b) in pattern.iter().enumerate() {
            assert_eq!(d.bit(&mut p), b, "bit {i}");
        }
        assert_eq!(d.direct(32), 0xdead_beef);
        let mut tree = [Prob::default(); 64];
        assert_eq!(d.tree(&mut tree, 6), 45);
        assert!(!d.failed());
    }

    #[test]
    fn garbage_and_truncation_never_panic() {
        for input in [&[][..], &[1, 2, 3][..], &[0xff; 100][..], &[0; 3][..]] {
            let mut d = Decoder::new(input);
            let mut p = [Prob::default(); 256];
            for i in 0..1000 {
                d.bit(&mut p[i % 256]);
                d.direct(7);
                d.tree(&mut p, 8);
            }
            assert!(d.failed() || input.len() > 10, "{input:?}");
        }
    }
}
