//! The mesh codec on random conforming meshes: exact round trips, key and delta frames,
//! wrong bases, damage and truncation.

use proptest::prelude::*;
use roam_protocol::mesh::{self, Mesh};
use roam_protocol::{BitSet, DecodeError, Grid, MeshDecoder, MeshEncoder};

/// A conforming split set: the ancestors of `picks` (grid vertices, corners skipped).
fn split_set(grid: &Grid, picks: &[(u32, u32)]) -> BitSet {
    let mut set = BitSet::new(grid.vertices());
    for &(x, z) in picks {
        grid.split_closed(&mut set, x % grid.side(), z % grid.side());
    }
    set
}

fn heights(grid: &Grid, seed: u32) -> Vec<u16> {
    (0..grid.vertices() as u32)
        .map(|i| {
            let (x, z) = grid.coords(i);
            // Smooth terrain plus some noise, over most of the range.
            let smooth = 30_000.0 + 20_000.0 * ((x as f64 * 0.05).sin() * (z as f64 * 0.07).cos());
            let noise = (i.wrapping_mul(2_654_435_761).wrapping_add(seed) >> 24) as f64;
            (smooth + noise) as u16
        })
        .collect()
}

/// Encodes `set` (against `base`), decodes it, and checks the split set, the heights of
/// its vertices and the emitted mesh.
fn round_trip(
    grid: &Grid,
    heights: &[u16],
    set: &BitSet,
    base: Option<&BitSet>,
    dec: &mut MeshDecoder,
) -> Vec<u8> {
    let mut enc = MeshEncoder::new(*grid);
    let mut bytes = Vec::new();
    enc.encode(set, heights, base, &mut bytes)
        .expect("a conforming set");
    let mut got = BitSet::default();
    let info = dec
        .decode(&bytes, base, u32::MAX, &mut got)
        .expect("decodes");
    assert_eq!(&got, set);
    assert_eq!(info.splits as usize, set.len());
    let (mut want, mut have) = (Mesh::default(), Mesh::default());
    mesh::emit(grid, set, heights, &mut want);
    mesh::emit(grid, &got, dec.heights(), &mut have);
    assert_eq!(have, want, "the viewer's mesh is the server's");
    assert_eq!(info.triangles as usize, want.triangle_count());
    bytes
}

#[test]
fn empty_and_full_meshes() {
    for levels in 1..=6 {
        let grid = Grid::new(levels).expect("valid");
        let h = heights(&grid, 1);
        let mut dec = MeshDecoder::new(grid);
        round_trip(&grid, &h, &BitSet::new(grid.vertices()), None, &mut dec);
        let mut all = BitSet::new(grid.vertices());
        for i in 0..grid.vertices() as u32 {
            let (x, z) = grid.coords(i);
            if !(x.is_multiple_of(grid.size()) && z.is_multiple_of(grid.size())) {
                all.insert(i);
            }
        }
        round_trip(&grid, &h, &all, None, &mut dec);
        let mut m = Mesh::default();
        mesh::emit(&grid, &all, &h, &mut m);
        assert_eq!(m.triangle_count(), 2 * (grid.size() * grid.size()) as usize);
    }
}

#[test]
fn a_set_not_closed_under_parent_is_refused() {
    let grid = Grid::new(4).expect("valid");
    let mut set = BitSet::new(grid.vertices());
    set.insert(grid.index(1, 1));
    let err = MeshEncoder::new(grid)
        .encode(&set, &heights(&grid, 0), None, &mut Vec::new())
        .expect_err("not a mesh");
    assert!(err.to_string().contains("not closed under parent"));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    /// Key frames, then a delta against the first: exact, and a delta is smaller.
    #[test]
    fn key_and_delta_frames_round_trip(
        levels in 1u32..=7,
        a in prop::collection::vec((0u32..200, 0u32..200), 0..60),
        b in prop::collection::vec((0u32..200, 0u32..200), 0..20),
        seed in any::<u32>(),
    ) {
        let grid = Grid::new(levels).expect("valid");
        let h = heights(&grid, seed);
        let first = split_set(&grid, &a);
        let mut more = a.clone();
        more.extend(&b);
        let second = split_set(&grid, &more);
        let mut dec = MeshDecoder::new(grid);
        let key = round_trip(&grid, &h, &first, None, &mut dec);
        let delta = round_trip(&grid, &h, &second, Some(&first), &mut dec);
        if b.is_empty() {
            prop_assert!(delta.len() <= key.len());
        }
        // The other way round too: a delta may also unsplit.
        round_trip(&grid, &h, &first, Some(&second), &mut dec);
    }

    /// Damage anywhere is an error (or, in the encoder's slack bytes, the same mesh),
    /// never a panic and never a wrong mesh.
    #[test]
    fn damaged_frames_are_errors(
        picks in prop::collection::vec((0u32..200, 0u32..200), 1..60),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..4),
        cut in any::<prop::sample::Index>(),
    ) {
        let grid = Grid::new(7).expect("valid");
        let h = heights(&grid, 9);
        let set = split_set(&grid, &picks);
        let mut bytes = Vec::new();
        MeshEncoder::new(grid).encode(&set, &h, None, &mut bytes).expect("encodes");
        let mut bad = bytes.clone();
        for (at, x) in &flips {
            let i = at.index(bad.len());
            bad[i] ^= x;
        }
        let mut dec = MeshDecoder::new(grid);
        let mut got = BitSet::default();
        if dec.decode(&bad, None, u32::MAX, &mut got).is_ok() {
            prop_assert_eq!(&got, &set);
        }
        let short = &bytes[..cut.index(bytes.len())];
        if dec.decode(short, None, u32::MAX, &mut got).is_ok() {
            prop_assert_eq!(&got, &set);
        }
    }

    /// Any bytes at all: a value or an error.
    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..400), delta in any::<bool>()) {
        let grid = Grid::new(6).expect("valid");
        let mut dec = MeshDecoder::new(grid);
        let base = BitSet::new(grid.vertices());
        let mut got = BitSet::default();
        let _ = dec.decode(&bytes, delta.then_some(&base), 10_000, &mut got);
    }
}

#[test]
fn a_delta_against_the_wrong_base_is_detected() {
    let grid = Grid::new(6).expect("valid");
    let h = heights(&grid, 4);
    let base = split_set(&grid, &[(10, 10), (40, 3)]);
    let other = split_set(&grid, &[(50, 50)]);
    let next = split_set(&grid, &[(10, 10), (40, 3), (20, 60)]);
    let mut bytes = Vec::new();
    MeshEncoder::new(grid)
        .encode(&next, &h, Some(&base), &mut bytes)
        .expect("encodes");
    let mut dec = MeshDecoder::new(grid);
    round_trip(&grid, &h, &other, None, &mut dec);
    let mut got = BitSet::default();
    let err = dec
        .decode(&bytes, Some(&other), u32::MAX, &mut got)
        .expect_err("wrong base");
    assert!(
        matches!(err, DecodeError::Check | DecodeError::Corrupt(_)),
        "{err}"
    );
    assert_eq!(
        dec.decode(&bytes, None, u32::MAX, &mut got),
        Err(DecodeError::Base)
    );
}

#[test]
fn limits_and_header_errors() {
    let grid = Grid::new(5).expect("valid");
    let h = heights(&grid, 2);
    let set = split_set(&grid, &[(3, 7), (20, 30)]);
    let mut bytes = Vec::new();
    MeshEncoder::new(grid)
        .encode(&set, &h, None, &mut bytes)
        .expect("encodes");
    let mut dec = MeshDecoder::new(grid);
    let mut got = BitSet::default();
    assert!(matches!(
        dec.decode(&bytes, None, 10, &mut got),
        Err(DecodeError::TooBig { limit: 10, .. })
    ));
    assert_eq!(
        dec.decode(&bytes[..7], None, u32::MAX, &mut got),
        Err(DecodeError::Short(7))
    );
    let mut other = MeshDecoder::new(Grid::new(6).expect("valid"));
    assert!(matches!(
        other.decode(&bytes, None, u32::MAX, &mut got),
        Err(DecodeError::Grid {
            got: 5,
            expected: 6
        })
    ));
    let mut v2 = bytes.clone();
    v2[0] = 2;
    assert_eq!(
        dec.decode(&v2, None, u32::MAX, &mut got),
        Err(DecodeError::Format(2))
    );
}

#[test]
fn heights_on_a_step_are_coded_in_steps() {
    let grid = Grid::new(6).expect("valid");
    let h: Vec<u16> = heights(&grid, 3).iter().map(|&v| v / 100 * 100).collect();
    assert_eq!(roam_protocol::height_step(&h), 100);
    assert_eq!(roam_protocol::height_step(&[0, 0]), 1, "no step: 1");
    assert_eq!(roam_protocol::height_step(&[6, 9, 15]), 3);
    assert_eq!(
        roam_protocol::height_step(&[4, 6, 5, 10]),
        1,
        "1 once reached"
    );
    assert_eq!(roam_protocol::height_step(&[0, 8, 0, 12]), 4);
    let set = split_set(&grid, &[(5, 9), (40, 33), (60, 2), (17, 50)]);
    let (mut plain, mut stepped) = (Vec::new(), Vec::new());
    MeshEncoder::new(grid)
        .encode(&set, &h, None, &mut plain)
        .expect("encodes");
    MeshEncoder::with_step(grid, 100)
        .encode(&set, &h, None, &mut stepped)
        .expect("encodes");
    assert!(
        stepped.len() < plain.len(),
        "{} vs {}",
        stepped.len(),
        plain.len()
    );
    for bytes in [&plain, &stepped] {
        let mut dec = MeshDecoder::new(grid);
        let mut got = BitSet::default();
        dec.decode(bytes, None, u32::MAX, &mut got)
            .expect("decodes");
        assert_eq!(got, set);
        for i in set.iter() {
            assert_eq!(dec.heights()[i as usize], h[i as usize]);
        }
    }
    let err = MeshEncoder::with_step(grid, 7)
        .encode(&set, &h, None, &mut Vec::new())
        .expect_err("heights off the step");
    assert!(
        err.to_string().contains("not a multiple of the step 7"),
        "{err}"
    );
}

#[test]
fn a_hostile_step_is_an_error_not_an_overflow() {
    let grid = Grid::new(6).expect("valid");
    let h = heights(&grid, 5);
    let set = split_set(&grid, &[(9, 9), (50, 21)]);
    let mut bytes = Vec::new();
    MeshEncoder::new(grid)
        .encode(&set, &h, None, &mut bytes)
        .expect("encodes");
    for step in [0u16, 2, 0xffff] {
        let mut bad = bytes.clone();
        bad[20..22].copy_from_slice(&step.to_le_bytes());
        let mut got = BitSet::default();
        assert!(
            MeshDecoder::new(grid)
                .decode(&bad, None, u32::MAX, &mut got)
                .is_err(),
            "step {step}"
        );
    }
}
