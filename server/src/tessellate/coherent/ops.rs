//! The cut's operations: split and merge with the frontiers' upkeep, the bintree's
//! neighbours, forced splits, and the queues' and schedules' upkeep (evaluations queued
//! with a stamp, due ones evaluated again, stale entries compacted away).

use super::buckets::{Buckets, Stamped};
use super::eval::{Entry, Fixed, Lanes, fixed};
use super::{Coherent, Frontier, pack, unpack};
use crate::tessellate::diamond::Shape;
use crate::tessellate::queue::{TOP, bucket_of};
use crate::tessellate::{Frame, classify};

/// Stale entries a queue or schedule may hold beyond its frontier's size before it is
/// compacted (re-filled from the live evaluations alone).
const SLACK: usize = 4096;

/// Stamps past this renumber every live evaluation at the next frame's start: a frame
/// (a rebuild at the largest budget evaluates a few million diamonds) never takes the
/// rest.
const RENUMBER_AT: u32 = u32::MAX - (1 << 28);

impl Coherent {
    pub(super) fn root(&self) -> u32 {
        let r = self.size / 2;
        pack(r, r)
    }

    /// Children on the map (none for the finest rotated diamonds), packed.
    pub(super) fn children(&self, x: u32, z: u32) -> [Option<u32>; 4] {
        let (m, shape) = classify(x, z);
        let h = 1 << m;
        let s = self.size;
        match shape {
            Shape::Square => [
                Some(pack(x + h, z)),
                Some(pack(x - h, z)),
                Some(pack(x, z + h)),
                Some(pack(x, z - h)),
            ],
            Shape::Rotated { .. } if m == 0 => [None; 4],
            Shape::Rotated { .. } => {
                let k = h / 2;
                let ok = |dx: i64, dz: i64| {
                    let (cx, cz) = (i64::from(x) + dx, i64::from(z) + dz);
                    (cx >= 0 && cz >= 0 && cx <= i64::from(s) && cz <= i64::from(s))
                        .then(|| pack(cx as u32, cz as u32))
                };
                let k = i64::from(k);
                [ok(k, -k), ok(-k, -k), ok(-k, k), ok(k, k)]
            }
        }
    }

    /// Parents on the map (none for the root, one for a rotated diamond on the edge).
    pub(super) fn parents(&self, x: u32, z: u32) -> [Option<u32>; 2] {
        let (m, shape) = classify(x, z);
        let h = 1 << m;
        let s = self.size;
        match shape {
            Shape::Square if 2 * h == s => [None, None],
            Shape::Square => {
                if (((x + h) >> (m + 1)) + ((z + h) >> (m + 1))) & 1 == 1 {
                    [Some(pack(x + h, z + h)), Some(pack(x - h, z - h))]
                } else {
                    [Some(pack(x + h, z - h)), Some(pack(x - h, z + h))]
                }
            }
            Shape::Rotated { horizontal: true } => [
                (z >= h).then(|| pack(x, z - h)),
                (z + h <= s).then(|| pack(x, z + h)),
            ],
            Shape::Rotated { horizontal: false } => [
                (x >= h).then(|| pack(x - h, z)),
                (x + h <= s).then(|| pack(x + h, z)),
            ],
        }
    }

    /// Triangles a split of `(x, z)` adds: a square 2, a rotated diamond one per parent
    /// on the map (1 on the map's edge).
    pub(super) fn added(&self, x: u32, z: u32) -> u32 {
        match classify(x, z).1 {
            Shape::Square => 2,
            Shape::Rotated { .. } => self.parents(x, z).iter().flatten().count() as u32,
        }
    }

    fn any_split(&self, list: &[Option<u32>]) -> bool {
        list.iter().flatten().any(|&p| self.split.contains(p))
    }

    /// Collects into `chain`, parents first, the unsplit diamonds that splitting `(x, z)`
    /// needs (ROAM's forced splits, as from scratch), and returns the triangles their
    /// splits add. Recursion depth is bounded by the tree's depth.
    pub(super) fn collect(&mut self, x: u32, z: u32) -> u32 {
        let mut tris = 0;
        for p in self.parents(x, z).into_iter().flatten() {
            if !self.split.contains(p) && !self.chain.contains(&p) {
                let (px, pz) = unpack(p);
                tris += self.collect(px, pz);
            }
        }
        self.chain.push(pack(x, z));
        tris + self.added(x, z)
    }

    fn next_stamp(&mut self) -> u32 {
        self.stamp = self.stamp.wrapping_add(1);
        self.stamp
    }

    /// Keeps lane `i` of an evaluation beside split candidate `pos`, and queues it.
    pub(super) fn keep_split(&mut self, l: &Lanes, i: usize, pos: u32) {
        self.keep(l, i, pos, false);
    }

    /// Keeps lane `i` of an evaluation beside merge candidate `pos`, and queues it.
    pub(super) fn keep_merge(&mut self, l: &Lanes, i: usize, pos: u32) {
        self.keep(l, i, pos, true);
    }

    /// Keeps lane `i` of an evaluation beside `pos` in the merge or split frontier, under a
    /// new stamp, and queues and schedules it.
    fn keep(&mut self, l: &Lanes, i: usize, pos: u32, merges: bool) {
        let stamp = self.next_stamp();
        let (moved, turned) = (self.moved, self.turned);
        let fr = if merges {
            &mut self.merges
        } else {
            &mut self.splits
        };
        let Some(e) = fr.cands.get_mut(pos) else {
            return;
        };
        e.keep(l, i, moved, turned);
        e.stamp = stamp;
        let e = *e;
        if merges {
            push_merge(&mut fr.queue, &e, pos);
        } else {
            push_split(&mut fr.queue, &e, pos);
        }
        schedule(fr, &e, pos);
    }

    /// Evaluates again the frontier diamonds whose evaluations are due (four at a time),
    /// and queues them by the new ones.
    pub(super) fn evaluate_due(&mut self, f: &Frame) {
        for merges in [false, true] {
            let (moved, turned) = (self.moved, self.turned);
            let frontier = if merges {
                &mut self.merges
            } else {
                &mut self.splits
            };
            let mut due = std::mem::take(&mut self.new);
            due.clear();
            // An entry due on both odometers is taken once (its `DUE` flag set).
            let mut popped = 0;
            while let Some((at, s)) = frontier.due_moved.pop_due(moved) {
                take_due(frontier, s, |e| e.due_moved == at, &mut due);
                popped += 1;
            }
            while let Some((at, s)) = frontier.due_turned.pop_due(turned) {
                take_due(frontier, s, |e| e.due_turned == at, &mut due);
                popped += 1;
            }
            self.stats.popped += popped;
            self.evaluate_list(f, &due, merges);
            self.new = due;
        }
    }

    /// Evaluates the members `list` of a frontier, four at a time, and keeps and queues
    /// each evaluation.
    fn evaluate_list(&mut self, f: &Frame, list: &[u32], merges: bool) {
        for chunk in list.chunks(4) {
            let cands = if merges {
                &self.merges.cands
            } else {
                &self.splits.cands
            };
            let d: [&Fixed; 4] = std::array::from_fn(|i| {
                let p = chunk[i.min(chunk.len() - 1)];
                &cands.get(p).expect("listed members are members").fixed
            });
            let lanes = self.evaluate(f, d, chunk.len());
            for (i, &p) in chunk.iter().enumerate() {
                self.keep(&lanes, i, p, merges);
            }
            self.stats.evaluated += chunk.len() as u32;
        }
    }

    /// Re-fills a frontier's queue and schedules from its live evaluations alone once
    /// stale entries outnumber them (each member has at most one live entry in each);
    /// and before the stamps could wrap, renumbers every live evaluation and re-fills all
    /// (so an entry's stamp names one evaluation, always).
    pub(super) fn compact(&mut self) {
        let renumber = self.stamp > RENUMBER_AT;
        if renumber {
            self.stamp = 0;
        }
        for merges in [false, true] {
            if renumber {
                let fr = if merges {
                    &mut self.merges
                } else {
                    &mut self.splits
                };
                for e in fr.cands.values_mut() {
                    self.stamp += 1;
                    e.stamp = self.stamp;
                }
                fr.queue.clear();
                fr.due_moved.clear();
                fr.due_turned.clear();
            }
            let fr = if merges {
                &mut self.merges
            } else {
                &mut self.splits
            };
            let most = 2 * fr.cands.len() + SLACK;
            if renumber || fr.queue.len() > most {
                fr.queue.clear();
                for (&pos, e) in fr.cands.as_slice().iter().zip(fr.cands.values()) {
                    let e = *e;
                    if merges {
                        push_merge(&mut fr.queue, &e, pos);
                    } else {
                        push_split(&mut fr.queue, &e, pos);
                    }
                }
                fr.queue.shrink();
            }
            if renumber || fr.due_moved.len() + fr.due_turned.len() > 2 * most {
                fr.due_moved.clear();
                fr.due_turned.clear();
                for (&pos, e) in fr.cands.as_slice().iter().zip(fr.cands.values()) {
                    let s = Stamped {
                        pos,
                        stamp: e.stamp,
                    };
                    fr.due_moved.push(e.due_moved, s);
                    fr.due_turned.push(e.due_turned, s);
                }
                fr.due_moved.shrink();
                fr.due_turned.shrink();
            }
        }
    }

    /// The frontiers of the cut `new` (sorted), made afresh and every member evaluated.
    pub(super) fn rebuild_frontiers(&mut self, f: &Frame, new: &[u32]) {
        self.splits.clear();
        self.merges.clear();
        let root = self.root();
        if new.is_empty() {
            self.splits
                .cands
                .insert_with(root, || Entry::fresh(fixed(f, root)));
        }
        for &p in new {
            let (x, z) = unpack(p);
            let mut any = false;
            for c in self.children(x, z).into_iter().flatten() {
                if self.split.contains(c) {
                    any = true;
                } else {
                    self.splits
                        .cands
                        .insert_with(c, || Entry::fresh(fixed(f, c)));
                }
            }
            if !any {
                self.merges
                    .cands
                    .insert_with(p, || Entry::fresh(fixed(f, p)));
            }
        }
        for merges in [false, true] {
            let mut list = std::mem::take(&mut self.old);
            list.clear();
            let cands = if merges {
                &self.merges.cands
            } else {
                &self.splits.cands
            };
            list.extend_from_slice(cands.as_slice());
            self.evaluate_list(f, &list, merges);
            self.old = list;
        }
    }

    /// The next split candidate still valid (its newest evaluation), with its bucket and
    /// priority.
    pub(super) fn pop_split(&mut self) -> Option<(usize, Stamped, f32)> {
        loop {
            let (b, s) = self.splits.queue.pop()?;
            if let Some(e) = self.splits.live(s) {
                return Some((b, s, e.prio));
            }
        }
    }

    /// The bucket and priority of the next valid merge candidate (stale entries are dropped
    /// on the way).
    pub(super) fn peek_merge(&mut self) -> Option<(usize, f32)> {
        loop {
            let (b, s) = self.merges.queue.peek()?;
            if let Some(e) = self.merges.live(s) {
                // Unwanted splits cost nothing to merge.
                return Some((b, if b == TOP { 0.0 } else { e.prio }));
            }
            self.merges.queue.pop();
        }
    }

    /// The next valid merge candidate's position.
    pub(super) fn pop_merge(&mut self) -> Option<u32> {
        loop {
            let (_, s) = self.merges.queue.pop()?;
            if self.merges.live(s).is_some() {
                return Some(s.pos);
            }
        }
    }

    /// Splits `pos`, whose parents are split: the frontiers follow and the children it
    /// uncovers are queued.
    pub(super) fn split(&mut self, f: &Frame, pos: u32) {
        let (x, z) = unpack(pos);
        self.split.insert_with(pos, || ());
        self.triangles += self.added(x, z);
        self.split_count += 1;
        self.stats.splits += 1;
        self.log.push(pos);
        self.splits.cands.remove(pos);
        for p in self.parents(x, z).into_iter().flatten() {
            self.merges.cands.remove(p);
        }
        self.merges
            .cands
            .insert_with(pos, || Entry::fresh(fixed(f, pos)));
        let mut fresh = [0u32; 4];
        let mut n = 0;
        for c in self.children(x, z).into_iter().flatten() {
            if self
                .splits
                .cands
                .insert_with(c, || Entry::fresh(fixed(f, c)))
            {
                fresh[n] = c;
                n += 1;
            }
        }
        // The diamond itself rides in the children's batch when there is a lane for it.
        let mut pos4 = fresh;
        let lanes = if n < 4 {
            pos4[n] = pos;
            self.evaluate_at(f, &pos4[..=n])
        } else {
            self.evaluate_at(f, &pos4)
        };
        for (i, &c) in fresh.iter().enumerate().take(n) {
            self.keep_split(&lanes, i, c);
        }
        if n < 4 {
            self.keep_merge(&lanes, n, pos);
        } else {
            let lanes = self.evaluate_at(f, &[pos]);
            self.keep_merge(&lanes, 0, pos);
        }
    }

    /// Merges `pos`, split with no split child: the frontiers follow, and it and the
    /// parents it leaves mergeable are queued.
    pub(super) fn merge(&mut self, f: &Frame, pos: u32) {
        let (x, z) = unpack(pos);
        self.split.remove(pos);
        self.triangles -= self.added(x, z);
        self.split_count -= 1;
        self.stats.merges += 1;
        self.log.push(pos);
        self.merges.cands.remove(pos);
        self.splits
            .cands
            .insert_with(pos, || Entry::fresh(fixed(f, pos)));
        for c in self.children(x, z).into_iter().flatten() {
            let (cx, cz) = unpack(c);
            if !self.any_split(&self.parents(cx, cz)) {
                self.splits.cands.remove(c);
            }
        }
        let mut fresh = [0u32; 4];
        let mut n = 0;
        for p in self.parents(x, z).into_iter().flatten() {
            let (px, pz) = unpack(p);
            if !self.any_split(&self.children(px, pz))
                && self
                    .merges
                    .cands
                    .insert_with(p, || Entry::fresh(fixed(f, p)))
            {
                fresh[n] = p;
                n += 1;
            }
        }
        let mut pos4 = [pos; 4];
        pos4[1..=n].copy_from_slice(&fresh[..n]);
        let lanes = self.evaluate_at(f, &pos4[..=n]);
        self.keep_split(&lanes, 0, pos);
        for (i, &p) in fresh.iter().enumerate().take(n) {
            self.keep_merge(&lanes, i + 1, p);
        }
    }
}

/// Takes a due schedule entry into `due` if it is a member's newest evaluation (its stamp,
/// and its reading, `newest`), not taken yet.
fn take_due(
    frontier: &mut Frontier,
    s: Stamped,
    newest: impl Fn(&Entry) -> bool,
    due: &mut Vec<u32>,
) {
    if let Some(e) = frontier.cands.get_mut(s.pos)
        && e.stamp == s.stamp
        && newest(e)
        && e.flags & DUE == 0
    {
        e.flags |= DUE;
        due.push(s.pos);
    }
}

/// An [`Entry`] flag: taken for evaluation this frame (cleared when it is kept).
const DUE: u8 = 8;

fn schedule(fr: &mut Frontier, e: &Entry, pos: u32) {
    let s = Stamped {
        pos,
        stamp: e.stamp,
    };
    fr.due_moved.push(e.due_moved, s);
    fr.due_turned.push(e.due_turned, s);
}

/// A split candidate goes in its priority's bucket (under the eye: the top one) when it
/// is worth splitting; otherwise in none.
fn push_split(q: &mut Buckets, e: &Entry, pos: u32) {
    let (wanted, under) = (e.flags & 1 != 0, e.flags & 2 != 0);
    if !wanted {
        return;
    }
    let bucket = if under { TOP } else { bucket_of(e.prio) };
    q.push(
        bucket,
        Stamped {
            pos,
            stamp: e.stamp,
        },
        e.prio,
    );
}

/// A merge candidate goes first (the top bucket) when unwanted, else lowest priority
/// first; one under the eye in none (the ground under the eye stays refined).
fn push_merge(q: &mut Buckets, e: &Entry, pos: u32) {
    if e.flags & 2 != 0 {
        return;
    }
    let bucket = if e.flags & 1 == 0 {
        TOP
    } else {
        TOP - 1 - bucket_of(e.prio)
    };
    q.push(
        bucket,
        Stamped {
            pos,
            stamp: e.stamp,
        },
        e.prio,
    );
}
