//! Tests of the queues and schedules ([`super`]).

use super::*;

#[derive(Clone, Copy)]
struct N {
    links: [Link; 3],
    keys: [u32; 2],
    at: [usize; 2],
}

impl Nodes for Vec<N> {
    fn len(&self) -> usize {
        self.as_slice().len()
    }
    fn link(&self, i: u32, w: usize) -> Link {
        self[i as usize].links[w]
    }
    fn set_link(&mut self, i: u32, w: usize, l: Link) {
        self[i as usize].links[w] = l;
    }
    fn key(&self, i: u32, k: usize) -> u32 {
        self[i as usize].keys[k]
    }
    fn set_key(&mut self, i: u32, k: usize, key: u32) {
        self[i as usize].keys[k] = key;
    }
    fn entry_bucket(&self, i: u32, k: usize) -> usize {
        self[i as usize].at[k]
    }
    fn set_entry_bucket(&mut self, i: u32, k: usize, b: usize) {
        self[i as usize].at[k] = b;
    }
    fn prio(&self, i: u32) -> f32 {
        self[i as usize].keys[0] as f32
    }
}

fn nodes(n: usize) -> Vec<N> {
    vec![
        N {
            links: [Link::OUT; 3],
            keys: [0; 2],
            at: [0; 2],
        };
        n
    ]
}

#[test]
fn pops_highest_bucket_first_oldest_within() {
    let mut nodes = nodes(8);
    let mut q = Queue::new(false);
    for (b, i) in [(5, 1), (700, 2), (5, 3), (BUCKETS - 1, 4), (700, 5), (0, 6)] {
        q.push(&mut nodes, b, i);
    }
    assert_eq!(q.len(), 6);
    assert_eq!(q.peek(), Some((BUCKETS - 1, 4)));
    assert_eq!(q.members(&nodes, 700).collect::<Vec<_>>(), [2, 5]);
    // A member taken out of the middle, and one moved in the list.
    q.remove(&mut nodes, 5, 1);
    nodes[7] = nodes[3];
    q.relocate(&mut nodes, 5, 3, 7);
    q.push(&mut nodes, 5, 1);
    let order: Vec<u32> = std::iter::from_fn(|| q.pop(&mut nodes))
        .map(|(_, i)| i)
        .collect();
    assert_eq!(order, [4, 2, 5, 7, 1, 6]);
    assert_eq!((q.top_bucket(), q.len()), (None, 0));
    assert!(q.lists(&nodes).is_ok_and(|l| l.is_empty()));
    q.push(&mut nodes, 9, 0);
    q.clear();
    assert_eq!(q.pop(&mut nodes), None);
}

/// Each bucket's highest priority, kept through pushes and removals, and the buckets
/// below one.
#[test]
fn keeps_each_buckets_highest() {
    let mut nodes = nodes(8);
    for (i, n) in nodes.iter_mut().enumerate() {
        n.keys[0] = 10 * i as u32;
    }
    let mut q = Queue::new(true);
    for i in [2, 5, 3] {
        q.push(&mut nodes, 40, i);
    }
    q.push(&mut nodes, 100, 1);
    q.push(&mut nodes, 900, 7);
    assert_eq!(q.most(&nodes, 40), 50.0);
    q.remove(&mut nodes, 40, 2);
    assert_eq!(q.most(&nodes, 40), 50.0, "a lower one left");
    q.remove(&mut nodes, 40, 5);
    assert_eq!(q.most(&nodes, 40), 30.0, "the highest left: walked again");
    q.push(&mut nodes, 40, 6);
    assert_eq!(q.most(&nodes, 40), 60.0);
    assert!(q.lists(&nodes).is_ok());
    assert_eq!(
        (
            q.below(900),
            q.below(100),
            q.below(40),
            q.below(BUCKETS - 1)
        ),
        (Some(100), Some(40), None, Some(900))
    );
}

/// The members due at `now`, taken out, in place order.
fn due(d: &mut Schedule, nodes: &mut Vec<N>, now: u32) -> Vec<u32> {
    let mut out = Vec::new();
    d.take_due(nodes, now, &mut out);
    out.sort_unstable();
    out
}

#[test]
fn schedule_takes_what_is_due() {
    let mut nodes = nodes(8);
    let mut d = Schedule::new(1);
    d.push(&mut nodes, 3, 3000);
    d.push(&mut nodes, 1, 1000);
    d.push(&mut nodes, 2, 2000);
    assert_eq!(due(&mut d, &mut nodes, 500), Vec::<u32>::new());
    assert_eq!(due(&mut d, &mut nodes, 2000), [1, 2]);
    // Pushed after keys were taken: at least the last one.
    d.push(&mut nodes, 4, 2500);
    d.push(&mut nodes, 5, 0);
    assert_eq!(nodes[5].keys[1], 2000);
    assert_eq!(due(&mut d, &mut nodes, 2000), [5]);
    // One moved in the list, one taken out before it was due.
    nodes[6] = nodes[4];
    d.relocate(&mut nodes, 4, 6);
    d.push(&mut nodes, 7, 2600);
    d.remove(&mut nodes, 7);
    let mut listed = d.lists(&nodes).expect("well formed");
    listed.sort_unstable();
    assert_eq!(listed, [3, 6]);
    assert_eq!(due(&mut d, &mut nodes, 2900), [6]);
    // A key that grew keeps its entry, and is due at the new key only.
    d.reschedule(&mut nodes, 3, Some(5000));
    assert_eq!(due(&mut d, &mut nodes, 4000), Vec::<u32>::new());
    assert!(d.lists(&nodes).is_ok_and(|l| l == [3]));
    assert_eq!(due(&mut d, &mut nodes, 10_000), [3]);
    assert_eq!((due(&mut d, &mut nodes, u32::MAX), d.len()), (vec![], 0));
}

/// Many keys, pushed as an odometer grows, some taken out again, popped as it passes
/// them, come out exactly when due, against a sorted reference.
#[test]
fn schedule_matches_a_reference() {
    let mut nodes = nodes(8000);
    let mut d = Schedule::new(0);
    let mut reference: Vec<(u32, u32)> = Vec::new();
    let mut seed = 99u64;
    let mut rand = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut now = 0u32;
    for step in 0..2000u32 {
        now += (rand() * 3000.0) as u32;
        for k in 0..3 {
            let key = now + (rand().powi(3) * 500_000.0) as u32;
            d.push(&mut nodes, step * 4 + k, key);
            reference.push((key, step * 4 + k));
        }
        if step % 7 == 0
            && let Some(&(_, i)) = reference.get(reference.len() / 2)
        {
            d.remove(&mut nodes, i);
            reference.retain(|&(_, j)| j != i);
        }
        // Scheduled again: later (the entry stays, only its key grows), earlier (moved),
        // or never.
        if step % 3 == 0
            && let Some(&(old, i)) = reference.get(reference.len() / 3)
        {
            let key = match step % 4 {
                0 => Some(old + 40_000),
                1 => Some(now.max(old / 2)),
                2 => Some(old),
                _ => None,
            };
            d.reschedule(&mut nodes, i, key);
            reference.retain(|&(_, j)| j != i);
            if let Some(key) = key {
                reference.push((key, i));
            }
        }
        let popped = due(&mut d, &mut nodes, now);
        let mut got: Vec<(u32, u32)> = popped
            .into_iter()
            .map(|i| (nodes[i as usize].keys[0], i))
            .collect();
        let (mut want, rest): (Vec<_>, Vec<_>) =
            reference.iter().partition(|&&(key, _)| key <= now);
        reference = rest;
        got.sort_unstable();
        want.sort_unstable();
        assert_eq!(got, want, "step {step}");
        assert_eq!(d.len(), reference.len());
        assert!(d.lists(&nodes).is_ok_and(|l| l.len() == reference.len()));
    }
}
