//! `cargo bench -p roam-protocol --bench fuzz`: a million inputs at every decoder (random
//! bytes, and valid encodings with bytes flipped, cut or extended), which must each give a
//! value or an error: no panic, no allocation beyond the limits. Prints one JSON object.

use std::time::Instant;

use roam_protocol::messages::{
    self, ClientMessage, Frame, Hello, KeyDatagram, KeyState, Role, ServerMessage, VehicleView,
};
use roam_protocol::{
    BitSet, CHANGES_FORMAT, ChangeEncoder, Cut, Grid, MeshDecoder, MeshEncoder, colormap,
};

/// SplitMix64: a seeded, portable generator.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// The side of the fuzzed colour maps: small, so that the many inputs that get past the
/// header (and decode every texel) stay quick.
const COLOR_CELLS: u32 = 32;

/// The base the change frames are coded against (as a viewer holds it), its heights,
/// and the split sets the fuzzed change frames lead to.
fn change_base(grid: Grid, heights: &[u16]) -> (Cut, Vec<BitSet>) {
    let mut rng = Rng(11);
    let mut base = BitSet::new(grid.vertices());
    for _ in 0..30 {
        let (x, z) = (
            rng.below(grid.side() as usize) as u32,
            rng.below(grid.side() as usize) as u32,
        );
        grid.split_closed(&mut base, x, z);
    }
    let mut nows = Vec::new();
    for n in [2u32, 10, 40] {
        let mut now = base.clone();
        for _ in 0..n {
            let (x, z) = (
                rng.below(grid.side() as usize) as u32,
                rng.below(grid.side() as usize) as u32,
            );
            grid.split_closed(&mut now, x, z);
        }
        nows.push(now);
    }
    (Cut::of(&grid, base, heights), nows)
}

fn heights(grid: Grid) -> Vec<u16> {
    (0..grid.vertices() as u32)
        .map(|i| (i * 7919 % 60_000) as u16)
        .collect()
}

/// Valid encodings to mutate: messages of every kind, a few meshes (key frames and change
/// frames) and colour maps.
fn seeds(grid: Grid) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let mut push = |f: &dyn Fn(&mut Vec<u8>)| {
        let mut b = Vec::new();
        f(&mut b);
        out.push(b);
    };
    let hello = ClientMessage::Hello(Hello {
        version: 1,
        role: Role::Driver,
        token: "token".into(),
        viewport: [1280, 720],
        fov_y_deg: 60.0,
        budget: 65_536,
        frame_rate: 60,
        resume: None,
    });
    push(&|b| messages::encode(&hello, b).expect("encodes"));
    push(&|b| messages::encode(&ClientMessage::Ack { frame: 99 }, b).expect("encodes"));
    push(&|b| {
        let m = ServerMessage::ColorMap {
            offset: 0,
            data: vec![1; 64],
        };
        messages::encode(&m, b).expect("encodes")
    });
    push(&|b| {
        let f = Frame {
            frame: 3,
            base: Some(2),
            tick: 77,
            vehicles: vec![VehicleView {
                id: 1,
                x: 1.0,
                z: 2.0,
                y: 3.0,
                speed: 4.0,
                heading: 5.0,
            }],
            input_seq: None,
            mesh: vec![9; 40],
        };
        messages::encode(&f, b).expect("encodes")
    });
    push(&|b| {
        let k = KeyDatagram {
            states: vec![
                KeyState {
                    seq: 5,
                    held: 3,
                    pressed: 1
                };
                4
            ],
        };
        messages::encode(&k, b).expect("encodes")
    });
    let heights = heights(grid);
    let (base, nows) = change_base(grid, &heights);
    let mut enc = ChangeEncoder::new(grid, 1);
    for now in &nows {
        for (from, to) in [(&base.split, now), (now, &base.split)] {
            let changes: Vec<u32> = (0..grid.vertices() as u32)
                .filter(|&i| from.contains(i) != to.contains(i))
                .collect();
            let cut = Cut::of(&grid, to.clone(), &heights);
            let mut b = Vec::new();
            enc.encode(
                &changes,
                |i| to.contains(i),
                &heights,
                cut.triangles,
                to.len() as u32,
                cut.hash,
                &mut b,
            )
            .expect("encodes");
            // Those back to the base are coded against `now`: wrong-base frames here.
            out.push(b);
        }
    }
    for n in [3u32, 40, 400] {
        let mut set = BitSet::new(grid.vertices());
        let mut rng = Rng(u64::from(n));
        for _ in 0..n {
            let (x, z) = (
                rng.below(grid.side() as usize) as u32,
                rng.below(grid.side() as usize) as u32,
            );
            grid.split_closed(&mut set, x, z);
        }
        let mut b = Vec::new();
        MeshEncoder::new(grid)
            .encode(&set, &heights, None, &mut b)
            .expect("encodes");
        out.push(b);
    }
    let mut rng = Rng(7);
    let n = COLOR_CELLS * COLOR_CELLS;
    for amp in [0u64, 8, 256] {
        // Smooth colour under noise of growing strength (256: pure noise).
        let rgb: Vec<u8> = (0..n * 3)
            .map(|i| (i / 3 % COLOR_CELLS * 5 + i / 3 / COLOR_CELLS * 3) as u64)
            .map(|smooth| (smooth + rng.next() % amp.max(1)) as u8)
            .collect();
        let mut b = Vec::new();
        colormap::encode(COLOR_CELLS, &rgb, &mut b).expect("texels of the right size");
        out.push(b);
    }
    out
}

fn main() {
    const INPUTS: usize = 1_000_000;
    let grid = Grid::new(6).expect("valid");
    let seeds = seeds(grid);
    let mut rng = Rng(1);
    let mut dec = MeshDecoder::new(grid);
    let base = BitSet::new(grid.vertices());
    let mut got = BitSet::default();
    // The change frames' base, as a viewer would hold it: decoded from a key frame.
    let (cut_base, _) = change_base(grid, &heights(grid));
    let mut key = Vec::new();
    MeshEncoder::new(grid)
        .encode(&cut_base.split, &heights(grid), None, &mut key)
        .expect("encodes");
    let mut change_dec = MeshDecoder::new(grid);
    let mut cut = Cut::default();
    change_dec
        .decode_cut(&key, None, u32::MAX, &mut cut)
        .expect("decodes");
    assert_eq!(cut, cut_base);
    let mut texels = Vec::new();
    let (mut ok, mut err, mut panics) = (0u64, 0u64, 0u64);
    let mut first_panic: Option<Vec<u8>> = None;
    let mut input = Vec::new();
    let mut forced = Vec::new();
    let started = Instant::now();
    for n in 0..INPUTS {
        input.clear();
        if n % 2 == 0 {
            let len = rng.below(300);
            input.extend((0..len).map(|_| rng.next() as u8));
        } else {
            input.extend_from_slice(&seeds[rng.below(seeds.len())]);
            for _ in 0..1 + rng.below(4) {
                match rng.below(3) {
                    0 if !input.is_empty() => {
                        let i = rng.below(input.len());
                        input[i] ^= 1 << rng.below(8);
                    }
                    1 => input.truncate(rng.below(input.len() + 1)),
                    _ => input.push(rng.next() as u8),
                }
            }
        }
        // Random bytes reach the change frame decoder behind a change frame's header.
        let change_input: &[u8] = if n % 2 == 0 && input.len() >= 4 {
            forced.clear();
            forced.extend_from_slice(&input);
            forced[..4].copy_from_slice(&[CHANGES_FORMAT, 6, 0, 0]);
            &forced
        } else {
            &input
        };
        // Each decode runs under catch_unwind: a panic is counted (and the input kept),
        // not fatal, so the report's "panics" is what happened, not what was hoped.
        let mut run = |f: &mut dyn FnMut() -> bool| match std::panic::catch_unwind(
            std::panic::AssertUnwindSafe(&mut *f),
        ) {
            Ok(true) => ok += 1,
            Ok(false) => err += 1,
            Err(_) => {
                panics += 1;
                first_panic.get_or_insert_with(|| input.clone());
            }
        };
        run(&mut || messages::decode::<ClientMessage>(&input).is_ok());
        run(&mut || messages::decode::<ServerMessage>(&input).is_ok());
        run(&mut || messages::decode::<Frame>(&input).is_ok());
        run(&mut || messages::decode::<KeyDatagram>(&input).is_ok());
        run(&mut || dec.decode(&input, None, 100_000, &mut got).is_ok());
        run(&mut || dec.decode(&input, Some(&base), 100_000, &mut got).is_ok());
        run(&mut || {
            change_dec
                .decode_cut(change_input, Some(&cut_base), 100_000, &mut cut)
                .is_ok()
        });
        run(&mut || colormap::decode(COLOR_CELLS, &input, &mut texels).is_ok());
    }
    let secs = started.elapsed().as_secs_f64();
    println!(
        "{{\"inputs\":{INPUTS},\"decodes\":{},\"values\":{ok},\"errors\":{err},\"seconds\":{secs:.2},\"panics\":{panics}}}",
        ok + err + panics
    );
    if let Some(input) = first_panic {
        eprintln!("a decoder panicked, first on input {input:02x?}");
        std::process::exit(1);
    }
}
