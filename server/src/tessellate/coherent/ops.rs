//! The cut's operations: split and merge with the frontiers' upkeep, the bintree's
//! neighbours, forced splits, and the queues' and schedules' upkeep (each evaluation kept
//! in its member, which is queued and scheduled by it; due ones evaluated again).

use super::eval::{Lanes, lane_flags};
use super::{Coherent, pack, unpack};
use crate::tessellate::Frame;
use crate::tessellate::queue::TOP;
use roam_protocol::bintree;

impl Coherent {
    pub(super) fn root(&self) -> u32 {
        let r = self.size / 2;
        pack(r, r)
    }

    /// Children on the map (none for the finest rotated diamonds), packed.
    pub(super) fn children(&self, x: u32, z: u32) -> [Option<u32>; 4] {
        bintree::children(self.size, x, z).map(|c| c.map(|(x, z)| pack(x, z)))
    }

    /// Parents on the map (none for the root, one for a rotated diamond on the edge).
    pub(super) fn parents(&self, x: u32, z: u32) -> [Option<u32>; 2] {
        bintree::parents(self.size, x, z).map(|p| p.map(|(x, z)| pack(x, z)))
    }

    /// Triangles a split of `(x, z)` adds: a square 2, a rotated diamond one per parent
    /// on the map (1 on the map's edge).
    pub(super) fn added(&self, x: u32, z: u32) -> u32 {
        bintree::added(self.size, x, z)
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

    /// Keeps lane `i` of an evaluation in member `at` (a place) of the merge or split
    /// frontier, and queues and schedules it by it.
    fn keep(&mut self, l: &Lanes, i: usize, at: u32, merges: bool) {
        let (m, t) = l.slack[i];
        let keys = [self.odometers[0].key(m), self.odometers[1].key(t)];
        let fr = if merges {
            &mut self.merges
        } else {
            &mut self.splits
        };
        fr.keep(at, l.prio[i], lane_flags(l, i), keys);
    }

    /// Evaluates again the frontier diamonds whose evaluations are due (four at a time),
    /// and queues them by the new ones.
    pub(super) fn evaluate_due(&mut self, f: &Frame) {
        let now = [self.odometers[0].now(), self.odometers[1].now()];
        let mut due = std::mem::take(&mut self.due);
        for merges in [false, true] {
            let frontier = if merges {
                &mut self.merges
            } else {
                &mut self.splits
            };
            due.clear();
            // One due on both odometers is taken once (out of both schedules).
            for k in 0..2 {
                frontier.take_due(k, now, &mut due);
            }
            self.stats.popped += due.len() as u32;
            self.evaluate_list(f, &due, merges);
        }
        self.due = due;
    }

    /// Evaluates the members `list` (places) of a frontier, four at a time, and keeps and
    /// queues each evaluation.
    fn evaluate_list(&mut self, f: &Frame, list: &[u32], merges: bool) {
        for chunk in list.chunks(4) {
            let fr = if merges { &self.merges } else { &self.splits };
            let mut pos = [0u32; 4];
            for (p, &i) in pos.iter_mut().zip(chunk) {
                *p = fr.pos(i);
            }
            let lanes = self.evaluate_at(f, &pos[..chunk.len()]);
            for (i, &at) in chunk.iter().enumerate() {
                self.keep(&lanes, i, at, merges);
            }
            self.stats.evaluated += chunk.len() as u32;
        }
    }

    /// Before an odometer's keys could run out (see [`super::Odometer`]), shifts them
    /// down: its base moves to the reading now, every schedule's keys with it.
    pub(super) fn rebase(&mut self) {
        for k in 0..2 {
            if let Some(shift) = self.odometers[k].rebase() {
                self.splits.rebase(k, shift);
                self.merges.rebase(k, shift);
            }
        }
    }

    /// The frontiers' members for the cut `new` (sorted; `split` says what it splits), made
    /// afresh, not yet evaluated ([`Self::evaluate_frontiers`]).
    pub(super) fn rebuild_frontiers(&mut self, new: &[u32], split: impl Fn(u32) -> bool) {
        self.splits.clear();
        self.merges.clear();
        // About as many split candidates as split diamonds, and a quarter as many merge
        // candidates (on `kossou` at 65,536 triangles: 30,781 and 8,496 of 32,913).
        self.splits.reserve(new.len());
        self.merges.reserve(new.len() / 4);
        let root = self.root();
        if new.is_empty() {
            self.splits.insert(root);
        }
        for &p in new {
            let (x, z) = unpack(p);
            let mut any = false;
            for c in self.children(x, z).into_iter().flatten() {
                if split(c) {
                    any = true;
                    continue;
                }
                // Listed once, by its first split parent in `new`'s order (the other
                // parent: `bintree::other_parent`).
                let other = bintree::other_parent(self.size, (x, z), unpack(c));
                if other.is_some_and(|(ox, oz)| pack(ox, oz) < p && split(pack(ox, oz))) {
                    continue;
                }
                self.splits.insert(c);
            }
            if !any {
                self.merges.insert(p);
            }
        }
    }

    /// Evaluates every member of both frontiers (after [`Self::rebuild_frontiers`]).
    pub(super) fn evaluate_frontiers(&mut self, f: &Frame) {
        for merges in [false, true] {
            let cands = if merges { &self.merges } else { &self.splits };
            let list: Vec<u32> = cands.places().collect();
            self.evaluate_list(f, &list, merges);
        }
    }

    /// The next split candidate queued, with its bucket and priority (taken out of the
    /// queue; [`super::frontier::Frontier::requeue`] puts it back).
    pub(super) fn pop_split(&mut self) -> Option<(usize, u32, f32)> {
        self.splits.pop()
    }

    /// The bucket and priority of the next merge candidate.
    pub(super) fn peek_merge(&self) -> Option<(usize, f32)> {
        let (b, m) = self.merges.peek()?;
        // Unwanted splits cost nothing to merge.
        Some((b, if b == TOP { 0.0 } else { m.prio }))
    }

    /// The next merge candidate's position.
    pub(super) fn pop_merge(&mut self) -> Option<u32> {
        self.merges.pop().map(|(_, pos, _)| pos)
    }

    /// Asks for the index slots a split or merge of `pos` looks up: its own in the split
    /// set and both frontiers, its children's in the split candidates, its parents' in the
    /// merge candidates. With many viewers' cuts nothing of one is in the cache, and a
    /// change's half-dozen look-ups otherwise wait for their misses one after another:
    /// `Frontier::find` was a tenth of a server's time serving 100 viewers in step, and
    /// over a third of their cuts' updates (`perf`, `data/kossou`, 2026-12-08). With this
    /// and [`Self::prefetch_members`], 120 viewers in step (`scripts/capacity.sh --in-step
    /// 120`, `FRAMES=1800`, in turn with the build before) took 112–117 µs a frame instead
    /// of 120–121; the frames are the same bit for bit.
    fn prefetch(&self, pos: u32, children: &[Option<u32>; 4], parents: &[Option<u32>; 2]) {
        self.split.prefetch(pos);
        self.splits.prefetch(pos);
        self.merges.prefetch(pos);
        for &c in children.iter().flatten() {
            self.splits.prefetch(c);
        }
        for &p in parents.iter().flatten() {
            self.merges.prefetch(p);
        }
    }

    /// And for a merge, the split set's slots of what it asks besides: whether each child
    /// keeps a split parent (its other parent, [`bintree::other_parent`]) and each parent
    /// a split child.
    fn prefetch_merge(&self, pos: u32, children: &[Option<u32>; 4], parents: &[Option<u32>; 2]) {
        let at = unpack(pos);
        for &c in children.iter().flatten() {
            if let Some((ox, oz)) = bintree::other_parent(self.size, at, unpack(c)) {
                self.split.prefetch(pack(ox, oz));
            }
        }
        for &p in parents.iter().flatten() {
            let (px, pz) = unpack(p);
            for q in self.children(px, pz).into_iter().flatten() {
                self.split.prefetch(q);
            }
        }
    }

    /// Then asks for the records of the members a split or merge of `pos` reads: its own,
    /// its children's and its parents', in whichever frontier each is likely in.
    fn prefetch_members(&self, pos: u32, children: &[Option<u32>; 4], parents: &[Option<u32>; 2]) {
        self.splits.prefetch_member(pos);
        self.merges.prefetch_member(pos);
        for &c in children.iter().flatten() {
            self.splits.prefetch_member(c);
        }
        for &p in parents.iter().flatten() {
            self.merges.prefetch_member(p);
        }
    }

    /// Splits `pos`, whose parents are split: the frontiers follow and the children it
    /// uncovers are queued.
    pub(super) fn split(&mut self, f: &Frame, pos: u32) {
        let (x, z) = unpack(pos);
        let (children, parents) = (self.children(x, z), self.parents(x, z));
        self.prefetch(pos, &children, &parents);
        self.split.insert(pos);
        self.prefetch_members(pos, &children, &parents);
        self.triangles += self.added(x, z);
        self.split_count += 1;
        self.stats.splits += 1;
        self.log.push(pos);
        self.splits.remove(pos);
        for p in parents.into_iter().flatten() {
            self.merges.remove(p);
        }
        let at = self
            .merges
            .insert(pos)
            .expect("an unsplit diamond is no merge candidate");
        // Places, valid to the end: nothing leaves a frontier below.
        let (mut fresh, mut places) = ([0u32; 4], [0u32; 4]);
        let mut n = 0;
        for c in children.into_iter().flatten() {
            if let Some(i) = self.splits.insert(c) {
                (fresh[n], places[n]) = (c, i);
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
        for (i, &c) in places.iter().enumerate().take(n) {
            self.keep(&lanes, i, c, false);
        }
        if n < 4 {
            self.keep(&lanes, n, at, true);
        } else {
            let lanes = self.evaluate_at(f, &[pos]);
            self.keep(&lanes, 0, at, true);
        }
    }

    /// Merges `pos`, split with no split child: the frontiers follow, and it and the
    /// parents it leaves mergeable are queued.
    pub(super) fn merge(&mut self, f: &Frame, pos: u32) {
        let (x, z) = unpack(pos);
        let (children, parents) = (self.children(x, z), self.parents(x, z));
        self.prefetch(pos, &children, &parents);
        self.prefetch_merge(pos, &children, &parents);
        self.split.remove(pos);
        self.prefetch_members(pos, &children, &parents);
        self.triangles -= self.added(x, z);
        self.split_count -= 1;
        self.stats.merges += 1;
        self.log.push(pos);
        self.merges.remove(pos);
        self.splits.insert(pos);
        for c in children.into_iter().flatten() {
            let (cx, cz) = unpack(c);
            if !self.any_split(&self.parents(cx, cz)) {
                self.splits.remove(c);
            }
        }
        // Places, valid to the end: nothing leaves a frontier below.
        let at = self.splits.place(pos).expect("inserted above");
        let (mut fresh, mut places) = ([0u32; 4], [0u32; 4]);
        let mut n = 0;
        for p in parents.into_iter().flatten() {
            let (px, pz) = unpack(p);
            if !self.any_split(&self.children(px, pz))
                && let Some(i) = self.merges.insert(p)
            {
                (fresh[n], places[n]) = (p, i);
                n += 1;
            }
        }
        let mut pos4 = [pos; 4];
        pos4[1..=n].copy_from_slice(&fresh[..n]);
        let lanes = self.evaluate_at(f, &pos4[..=n]);
        self.keep(&lanes, 0, at, false);
        for (i, &p) in places.iter().enumerate().take(n) {
            self.keep(&lanes, i + 1, p, true);
        }
    }
}
