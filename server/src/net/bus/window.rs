//! Replay windows ([`Window`], [`Replays`]): which counters each sender of sealed bus
//! messages ([`super::seal`]) has used, so that a message played again is refused. No
//! clock: a counter is new or it is not. Pure.

use std::collections::{HashMap, HashSet};

use super::seal::Header;

/// How far behind the newest counter from a sender a message may come and still be taken
/// (NATS keeps one publisher's order, but a process's tasks seal before they publish, so a
/// few may swap).
pub const WINDOW: u64 = 1024;

/// Senders whose replay windows one receiver keeps (each is some 150 bytes): past it, the
/// one heard from longest ago is retired, and every message from it refused from then on.
pub const MAX_SENDERS: usize = 65_536;

/// A sender's counters seen: the newest and, behind it, a bit for each of [`WINDOW`].
#[derive(Clone, Debug, Default)]
pub struct Window {
    newest: u64,
    seen: [u64; (WINDOW / 64) as usize],
}

impl Window {
    /// Whether `counter` is new (never seen, not too old); it is seen from now on.
    pub fn accept(&mut self, counter: u64) -> bool {
        if counter == 0 {
            return false;
        }
        if counter > self.newest {
            let shift = counter - self.newest;
            self.shift(shift);
            self.newest = counter;
            self.set(0);
            return true;
        }
        let behind = self.newest - counter;
        if behind >= WINDOW || self.get(behind) {
            return false;
        }
        self.set(behind);
        true
    }

    /// Moves every bit `by` places further behind.
    fn shift(&mut self, by: u64) {
        if by >= WINDOW {
            self.seen = Default::default();
            return;
        }
        let (words, bits) = ((by / 64) as usize, (by % 64) as u32);
        let n = self.seen.len();
        for i in (0..n).rev() {
            let from = i.checked_sub(words);
            let hi = from.map_or(0, |f| self.seen[f]);
            let lo = from
                .and_then(|f| f.checked_sub(1))
                .map_or(0, |f| self.seen[f]);
            self.seen[i] = if bits == 0 {
                hi
            } else {
                (hi << bits) | (lo >> (64 - bits))
            };
        }
    }

    fn get(&self, behind: u64) -> bool {
        self.seen[(behind / 64) as usize] & (1 << (behind % 64)) != 0
    }

    fn set(&mut self, behind: u64) {
        self.seen[(behind / 64) as usize] |= 1 << (behind % 64);
    }
}

/// Every sender's [`Window`], at most [`MAX_SENDERS`]: past it the one heard from longest
/// ago is retired (its messages refused from then on: a sender silent that long is a
/// process long gone, and only a replay would name it).
#[derive(Default)]
pub struct Replays {
    windows: HashMap<u64, (u64, Window)>,
    retired: HashSet<u64>,
    /// Messages taken, for the windows' age.
    taken: u64,
}

impl Replays {
    /// Whether `header`'s counter is new from its sender.
    pub fn accept(&mut self, header: &Header) -> bool {
        self.accept_with_limit(header, MAX_SENDERS)
    }

    fn accept_with_limit(&mut self, header: &Header, limit: usize) -> bool {
        if self.retired.contains(&header.sender) {
            return false;
        }
        self.taken += 1;
        if !self.windows.contains_key(&header.sender) && self.windows.len() >= limit {
            let oldest = self
                .windows
                .iter()
                .min_by_key(|(_, (at, _))| *at)
                .map(|(s, _)| *s);
            if let Some(s) = oldest {
                self.windows.remove(&s);
                self.retired.insert(s);
            }
        }
        let taken = self.taken;
        let (at, window) = self.windows.entry(header.sender).or_default();
        *at = taken;
        window.accept(header.counter)
    }
}

#[cfg(test)]
mod tests {
    use std::collections::HashSet;

    use super::*;
    use crate::net::bus::seal::Kind;

    #[test]
    fn a_window_takes_each_counter_once_and_none_too_old() {
        let mut w = Window::default();
        let mut check = |counter: u64, expected: bool| {
            assert_eq!(w.accept(counter), expected, "counter {counter}");
        };
        check(0, false);
        check(1, true);
        check(1, false);
        check(3, true);
        check(2, true);
        check(2, false);
        check(3, false);
        check(100, true);
        check(50, true);
        check(50, false);
        check(99, true);
        check(100 + WINDOW - 1, true);
        check(100, false);
        check(101, true);
        check(100 + WINDOW, true);
        check(100, false); // now WINDOW behind: too old
        check(101, false);
        check(5_000, true);
        check(5_000 - WINDOW + 1, true);
        check(5_000 - WINDOW, false);
        check(u64::MAX, true);
        check(u64::MAX, false);
        // A model: every counter taken once, in any order within the window.
        let mut w = Window::default();
        let mut seen = HashSet::new();
        let mut x = 7u64;
        for _ in 0..20_000 {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let c = 1 + (x >> 33) % 3_000;
            let newest = seen.iter().copied().max().unwrap_or(0);
            let want = !seen.contains(&c) && c + WINDOW > newest;
            assert_eq!(w.accept(c), want, "counter {c}, newest {newest}");
            if want {
                seen.insert(c);
            }
        }
    }

    #[test]
    fn past_the_senders_limit_the_stalest_is_retired() {
        let h = |sender, counter| Header {
            kind: Kind::Ask,
            sender,
            to: 0,
            counter,
            re: 0,
        };
        let mut r = Replays::default();
        assert!(r.accept(&h(9, 1)));
        assert!(!r.accept(&h(9, 1)), "a replay");
        let mut r = Replays::default();
        assert!(r.accept_with_limit(&h(1, 1), 2));
        assert!(r.accept_with_limit(&h(2, 1), 2));
        assert!(r.accept_with_limit(&h(1, 2), 2));
        // Sender 3 takes the place of 2, heard from longest ago: 2 is refused for good.
        assert!(r.accept_with_limit(&h(3, 1), 2));
        assert!(!r.accept_with_limit(&h(2, 2), 2));
        assert!(r.accept_with_limit(&h(1, 3), 2));
    }
}
