//! The per-viewer core driven without sockets: frames made for a vehicle's drive go to a
//! simulated viewer that loses (all but key frames, which the shell sends reliably),
//! reorders and acknowledges them late; every frame it decodes must equal the server's cut
//! for that frame, index for index. And when the core makes key frames: the first, when
//! asked, and when the pending key frame is superseded (its logs gone), never merely
//! because no frame has been acknowledged yet. And that a driving viewer's state stays
//! within what admission reserves for its budget.

use std::collections::VecDeque;
use std::sync::Arc;

use roam_protocol::{BitSet, DecodeError, Follower, Grid, mesh};
use roam_server::Terrain;
use roam_server::sim::physics::{Keys, VehicleState};
use roam_server::sim::world::{self, Inputs, World};
use roam_server::terrain::generate;
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::{Mesh, Mode, Scratch};
use roam_server::viewer::{Event, LOGS, Made, Scene, ViewerCore};

struct Fixture {
    terrain: Arc<Terrain>,
    variance: VarianceTree,
    scratch: Scratch,
}

impl Fixture {
    fn new(side: u32, seed: u64) -> Fixture {
        let terrain = Arc::new(generate::synthetic(side, seed));
        let variance = VarianceTree::build(&terrain.heights, 1, &mut |_, _| {});
        let scratch = Scratch::new(terrain.heights.side(), 1);
        Fixture {
            terrain,
            variance,
            scratch,
        }
    }

    fn scene(&self) -> Scene<'_> {
        Scene {
            terrain: &self.terrain,
            variance: &self.variance,
            scratch: &self.scratch,
        }
    }

    fn core(&self, budget: u32) -> ViewerCore {
        let step = roam_protocol::height_step(self.terrain.heights.samples());
        ViewerCore::new(
            self.terrain.heights.levels(),
            step,
            60.0,
            [640, 480],
            budget,
        )
    }

    fn grid(&self) -> Grid {
        Grid::new(self.terrain.heights.levels()).expect("a valid size")
    }

    /// Vehicle states of a drive: throttle and turns both ways, `frames` of them two ticks
    /// apart (50 frames a second).
    fn drive(&self, frames: usize) -> Vec<VehicleState> {
        let mut w = World::new(self.terrain.clone());
        w.add(0, world::start_state(&self.terrain, 0))
            .expect("the start is on the map");
        let mut inputs = Inputs::new();
        let mut out = Vec::new();
        for k in 0..frames * 2 {
            let keys = match (k / 150) % 4 {
                0 => Keys::UP,
                1 => Keys::UP.union(Keys::LEFT),
                2 => Keys::UP,
                _ => Keys::UP.union(Keys::RIGHT),
            };
            inputs.set(0, keys);
            world::step(&mut w, &inputs);
            if k % 2 == 1 {
                out.push(w.vehicles()[0].state);
            }
        }
        out
    }
}

/// A viewer as the client keeps one: the viewer's decoder, which keeps 32 decoded frames
/// as bases (like the client, it decodes only frames newer than the newest decoded), and
/// its cut mirrored over the grid for `mesh::emit`.
struct Viewer {
    grid: Grid,
    decoder: Follower,
    split: BitSet,
    heights: Vec<u16>,
}

/// What the viewer did with a frame.
enum Received {
    Decoded(mesh::Mesh),
    /// Not newer than the newest decoded: skipped.
    Stale,
    /// Coded against a frame newer than the newest decoded (a key frame on its way).
    Awaiting,
}

impl Viewer {
    fn new(grid: Grid) -> Viewer {
        Viewer {
            grid,
            decoder: Follower::new(grid, 32),
            split: BitSet::new(grid.vertices()),
            heights: vec![0; grid.vertices()],
        }
    }

    /// Decodes a frame newer than the newest decoded against the base it names; keeps it
    /// as a base.
    fn receive(&mut self, made: &Made) -> Result<Received, DecodeError> {
        let newest = self.decoder.frame();
        if newest.is_some_and(|n| made.frame <= n) {
            return Ok(Received::Stale);
        }
        if made.base.is_some_and(|b| newest.is_none_or(|n| b > n)) {
            return Ok(Received::Awaiting);
        }
        self.decoder
            .decode(made.frame, &made.payload, made.base, u32::MAX)?;
        self.decoder.mirror(&mut self.split, &mut self.heights);
        let mut out = mesh::Mesh::default();
        mesh::emit(&self.grid, &self.split, &self.heights, &mut out);
        Ok(Received::Decoded(out))
    }

    /// Decodes a frame that must decode.
    fn decode(&mut self, made: &Made) -> mesh::Mesh {
        match self.receive(made) {
            Ok(Received::Decoded(m)) => m,
            Ok(Received::Stale) => panic!("frame {}: stale", made.frame),
            Ok(Received::Awaiting) => panic!("frame {}: its base has not come", made.frame),
            Err(e) => panic!("frame {}: {e}", made.frame),
        }
    }
}

/// The server's mesh for the core's cut now.
fn server_mesh(core: &ViewerCore, scene: &Scene) -> Mesh {
    let mut m = Mesh::default();
    core.mesh(scene.scratch, &mut m);
    m
}

/// A small deterministic generator for the network's whims.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 33
    }

    fn chance(&mut self, percent: u64) -> bool {
        self.next() % 100 < percent
    }
}

#[test]
fn a_lossy_drive_decodes_exactly_frame_for_frame() {
    let fx = Fixture::new(257, 7);
    let scene = fx.scene();
    for (seed, loss, budget) in [(1, 0, 3000), (2, 20, 3000), (3, 50, 1500), (4, 10, 40_000)] {
        let mut rng = Rng(seed);
        let mut core = fx.core(budget);
        let mut viewer = Viewer::new(fx.grid());
        // Frames in flight (delivered in a random order), acknowledgements in flight.
        let mut wire: Vec<(Made, Mesh)> = Vec::new();
        let mut acks: VecDeque<(usize, u64)> = VecDeque::new();
        let (mut decoded, mut keys, mut changes) = (0, 0, 0);
        let (mut waiting, mut missing) = (0, 0);
        for (k, state) in fx.drive(300).iter().enumerate() {
            while acks.front().is_some_and(|&(due, _)| due <= k) {
                let (_, f) = acks.pop_front().expect("checked above");
                core.handle(Event::Acked(f));
            }
            let unacked = core.acked().is_none();
            let made = core.make_frame(&scene, state);
            waiting += usize::from(unacked);
            assert!(made.triangles <= budget, "over budget at frame {k}");
            keys += usize::from(made.base.is_none());
            changes += made.changes;
            let expected = server_mesh(&core, &scene);
            // Key frames are never lost (the shell sends them reliably), only late.
            if made.base.is_none() || !rng.chance(loss) {
                wire.push((made, expected));
            }
            // Deliver some of what is in flight, in any order.
            while !wire.is_empty() && rng.chance(60) {
                let i = rng.next() as usize % wire.len();
                let (made, expected) = wire.swap_remove(i);
                match viewer.receive(&made) {
                    Ok(Received::Decoded(got)) => {
                        assert_eq!(
                            got.indices, expected.indices,
                            "frame {} differs",
                            made.frame
                        );
                        assert_eq!(got.vertices.len(), expected.vertices.len());
                        decoded += 1;
                        if !rng.chance(loss) {
                            acks.push_back((k + 1 + rng.next() as usize % 3, made.frame));
                        }
                    }
                    Ok(Received::Stale) => {}
                    // Came before its key frame: the viewer passes it over.
                    Ok(Received::Awaiting) => {}
                    // Only acknowledged frames and the pending key frame are bases, and the
                    // viewer keeps 32 of them while the server codes against the last
                    // `LOGS` (<= 32) frames: never missing.
                    Err(DecodeError::Base) => missing += 1,
                    Err(e) => panic!("frame {}: {e}", made.frame),
                }
            }
        }
        assert!(
            decoded > 100 * (100 - loss as usize) / 100,
            "{decoded} decoded at {loss}% loss"
        );
        assert!(changes > 0, "the cut changed along the drive");
        assert_eq!(missing, 0, "frames coded against a base the viewer lacks");
        assert!(waiting >= 1, "frames made before the first ack");
        if loss == 0 {
            // The first frame is a key frame; the frames after it are coded against it
            // before it is acknowledged, and against the acknowledged frames after.
            assert_eq!(keys, 1, "a lossless drive needs one key frame");
        } else {
            assert!(keys < 300 / 4, "{keys} key frames at {loss}% loss");
        }
    }
}

#[test]
fn a_delta_against_a_base_the_viewer_lacks_is_refused_and_a_key_frame_follows() {
    let fx = Fixture::new(129, 3);
    let scene = fx.scene();
    let drive = fx.drive(40);
    let mut core = fx.core(2000);
    let mut viewer = Viewer::new(fx.grid());
    let first = core.make_frame(&scene, &drive[0]);
    viewer.receive(&first).expect("a key frame decodes alone");
    core.handle(Event::Acked(first.frame));
    let mut last = first.clone();
    for state in &drive[1..10] {
        last = core.make_frame(&scene, state);
    }
    assert_eq!(last.base, Some(first.frame));
    // Decoded against another cut than its base, the frame is refused, never shown: a
    // viewer holding as that frame another core's key frame (a smaller budget's cut).
    let mut misled = Viewer::new(fx.grid());
    misled.decode(&fx.core(1000).make_frame(&scene, &drive[0]));
    let before = (misled.decoder.frame(), misled.decoder.hash());
    assert_eq!(before.0, Some(first.frame));
    let err = misled
        .decoder
        .decode(last.frame, &last.payload, last.base, u32::MAX)
        .expect_err("a frame against the wrong base");
    assert!(
        matches!(err, DecodeError::Check | DecodeError::Corrupt(_)),
        "{err}"
    );
    assert_eq!(
        (misled.decoder.frame(), misled.decoder.hash()),
        before,
        "nothing taken"
    );
    core.handle(Event::KeyFrame);
    let key = core.make_frame(&scene, &drive[30]);
    assert_eq!(key.base, None, "a key frame follows the request");
    assert_eq!(core.pending_key(), Some(key.frame));
    let next = core.make_frame(&scene, &drive[31]);
    assert_eq!(
        next.base,
        Some(key.frame),
        "coded against the key frame on its way, before it is acknowledged"
    );
    core.handle(Event::KeyFrame);
    assert_eq!(
        core.pending_key(),
        None,
        "a request drops the pending key frame"
    );
    let again = core.make_frame(&scene, &drive[32]);
    assert_eq!(again.base, None, "and a new key frame follows");
    core.handle(Event::Acked(next.frame));
    assert_eq!(
        core.pending_key(),
        Some(again.frame),
        "an older ack leaves it pending"
    );
    core.handle(Event::Acked(again.frame));
    assert_eq!(core.pending_key(), None, "acknowledged: no longer pending");
    let after = core.make_frame(&scene, &drive[33]);
    assert_eq!(after.base, Some(again.frame));
}

#[test]
fn acks_beyond_the_logs_or_from_the_future_give_key_frames() {
    let fx = Fixture::new(129, 5);
    let scene = fx.scene();
    let drive = fx.drive(LOGS + 10);
    let mut core = fx.core(2000);
    core.handle(Event::Acked(5)); // not made yet: ignored
    let first = core.make_frame(&scene, &drive[0]);
    assert_eq!((first.frame, first.base), (0, None));
    core.handle(Event::Acked(0));
    let second = core.make_frame(&scene, &drive[1]);
    assert_eq!(second.base, Some(0));
    for state in &drive[2..LOGS + 3] {
        let made = core.make_frame(&scene, state);
        assert_ne!(made.base, Some(0).filter(|_| made.frame > LOGS as u64));
    }
    assert_eq!(
        core.pending_key(),
        Some(LOGS as u64 + 1),
        "frame 0's changes since are no longer logged: a key frame"
    );
    let late = core.make_frame(&scene, &drive[LOGS + 3]);
    assert_eq!(
        late.base,
        Some(LOGS as u64 + 1),
        "the frames after it are coded against it"
    );
}

/// The frames after a key frame are coded against it before the viewer has it (it comes
/// late, on a stream, after them): a viewer passes over those that come first, decodes the
/// key frame when it comes, and then every one of them that is newer, each exactly the
/// server's cut; once the key frame (or a frame after it) is acknowledged, the newest
/// acknowledged frame is the base.
#[test]
fn frames_coded_against_the_pending_key_frame_decode_once_it_arrives() {
    let fx = Fixture::new(257, 7);
    let scene = fx.scene();
    let drive = fx.drive(20);
    let mut core = fx.core(3000);
    let mut made = Vec::new();
    for state in &drive[..10] {
        let m = core.make_frame(&scene, state);
        made.push((m, server_mesh(&core, &scene)));
    }
    let (key, key_mesh) = &made[0];
    assert_eq!(key.base, None);
    assert_eq!(core.pending_key(), Some(key.frame));
    assert!(
        made[1..].iter().all(|(m, _)| m.base == Some(key.frame)),
        "no ack yet: every frame after the key frame is coded against it"
    );
    assert!(made.iter().any(|(m, _)| m.changes > 0), "the cut changed");
    let same = |got: &mesh::Mesh, want: &Mesh, frame: u64| {
        assert_eq!(got.indices, want.indices, "frame {frame} differs");
        assert_eq!(got.vertices.len(), want.vertices.len(), "frame {frame}");
    };
    // Frames 3 and 4 come before the key frame: passed over, not an error.
    let mut viewer = Viewer::new(fx.grid());
    for (m, _) in &made[3..5] {
        assert!(matches!(viewer.receive(m), Ok(Received::Awaiting)));
    }
    same(&viewer.decode(key), key_mesh, key.frame);
    let (m, want) = &made[6];
    same(&viewer.decode(m), want, m.frame);
    assert!(
        matches!(viewer.receive(&made[5].0), Ok(Received::Stale)),
        "older than the newest decoded"
    );
    // Another viewer takes them all, in order: each decodes against the key frame.
    let mut all = Viewer::new(fx.grid());
    for (m, want) in &made {
        same(&all.decode(m), want, m.frame);
    }
    // An ack of a frame after the key frame ends its wait: that frame is the base now.
    core.handle(Event::Acked(6));
    assert_eq!(core.pending_key(), None);
    let next = core.make_frame(&scene, &drive[10]);
    assert_eq!(next.base, Some(6));
    let want = server_mesh(&core, &scene);
    same(&viewer.decode(&next), &want, next.frame);
}

/// While no frame is acknowledged, the core makes no key frame but the first, until the
/// viewer asks for one or the key frame pending is superseded (its changes since no longer
/// logged, [`LOGS`] frames on); a late ack of a frame before the pending key frame does not
/// end its wait.
#[test]
fn a_new_key_frame_only_when_asked_or_superseded() {
    let fx = Fixture::new(129, 5);
    let scene = fx.scene();
    let drive = fx.drive(LOGS + 12);
    let mut core = fx.core(2000);
    let mut states = drive.iter();
    let mut next = |core: &mut ViewerCore| {
        let made = core.make_frame(&scene, states.next().expect("enough states"));
        (made.frame, made.base, core.pending_key())
    };
    assert_eq!(next(&mut core), (0, None, Some(0)));
    for f in 1..=LOGS as u64 {
        assert_eq!(
            next(&mut core),
            (f, Some(0), Some(0)),
            "coded against the pending key frame"
        );
    }
    // Frame 0's changes since are no longer all logged: a new key frame supersedes it.
    let k = LOGS as u64 + 1;
    assert_eq!(next(&mut core), (k, None, Some(k)));
    assert_eq!(next(&mut core), (k + 1, Some(k), Some(k)));
    // A late ack of a frame before the pending key frame: it stays the base.
    core.handle(Event::Acked(3));
    assert_eq!((core.acked(), core.pending_key()), (Some(3), Some(k)));
    assert_eq!(next(&mut core), (k + 2, Some(k), Some(k)));
    // Asked for: a new key frame at once, and the frames after it coded against it.
    core.handle(Event::KeyFrame);
    assert_eq!((core.acked(), core.pending_key()), (None, None));
    let asked = k + 3;
    assert_eq!(next(&mut core), (asked, None, Some(asked)));
    for f in asked + 1..asked + 8 {
        assert_eq!(next(&mut core), (f, Some(asked), Some(asked)));
    }
}

#[test]
fn budget_view_and_jumps_steer_the_cut() {
    let fx = Fixture::new(257, 9);
    let scene = fx.scene();
    let drive = fx.drive(20);
    let mut core = fx.core(4000);
    assert_eq!(core.make_frame(&scene, &drive[0]).mode, Mode::Rebuild);
    let step = core.make_frame(&scene, &drive[1]);
    assert_eq!(step.mode, Mode::Update, "a frame's step is an update");
    assert!(step.triangles > 3000);
    core.handle(Event::Budget(500));
    let small = core.make_frame(&scene, &drive[2]);
    assert!(small.triangles <= 500, "{}", small.triangles);
    core.handle(Event::Budget(1));
    assert!(core.make_frame(&scene, &drive[3]).triangles <= 2);
    core.handle(Event::Budget(4000));
    core.make_frame(&scene, &drive[4]);
    // A spectator switching to a vehicle far away, and the bounce at the map's edge (the
    // heading turned around), rebuild.
    let mut far = drive[5];
    far.x = fx.terrain.map.h_scale * 10.0;
    far.z = fx.terrain.map.h_scale * 240.0;
    assert_eq!(core.make_frame(&scene, &far).mode, Mode::Rebuild);
    let mut bounced = far;
    bounced.heading = (far.heading + 180.0) % 360.0;
    assert_eq!(core.make_frame(&scene, &bounced).mode, Mode::Rebuild);
    assert_eq!(core.make_frame(&scene, &bounced).mode, Mode::Update);
    // Looking straight down sees little: the budget is spent under the eye.
    let before = core.make_frame(&scene, &bounced).triangles;
    core.handle(Event::View(roam_protocol::messages::ViewChange {
        pitch_deg: -89.0,
        eye_above: 0.0,
        viewport: [640, 480],
        fog: true,
    }));
    let down = core.make_frame(&scene, &bounced);
    assert!(down.triangles < before, "{} !< {before}", down.triangles);
}

/// The priority weighs errors by the map's fog while the viewer draws it: its view change
/// turning the fog off rebuilds the cut as the fog-unaware priority makes it (from
/// scratch at density 0, split for split), turning it on again as the fog-aware one, and a
/// server serving with `fog_priority` off never weighs by the fog.
#[test]
fn the_viewers_fog_steers_the_priority() {
    use roam_protocol::messages::{DEFAULT_PITCH_DEG, ViewChange};
    use roam_server::tessellate::{Limits, Scales, Tessellator};
    use roam_server::viewer::ViewerLimits;
    let fx = Fixture::new(257, 9);
    let scene = fx.scene();
    let density = fx.terrain.map.fog_density as f32;
    assert!(density > 0.0, "synthetic maps have fog");
    let drive = fx.drive(12);
    let mut core = fx.core(3000);
    assert_eq!(
        core.fog_density(&scene),
        density,
        "fog until told otherwise"
    );
    let scales = Scales {
        h: fx.terrain.map.h_scale,
        v: fx.terrain.map.v_scale,
    };
    let mut t = Tessellator::new(fx.terrain.heights.side());
    let mut scratch = |core: &ViewerCore, v: &VehicleState, fog_density: f32| {
        let limits = Limits {
            budget: 3000,
            threshold_px: 0.0,
            fog_density,
            // The guard band the core serves by default.
            guard_deg: f32::from(ViewerLimits::default().guard_deg),
        };
        let cam = core.camera_at(&scene, v);
        t.tessellate(
            &fx.terrain.heights,
            &fx.variance,
            scales,
            &cam,
            limits,
            &mut Mesh::default(),
        );
        let mut split: Vec<(u32, u32)> = t.split_diamonds().collect();
        split.sort_unstable();
        split
    };
    let cut = |core: &ViewerCore| {
        let mut split: Vec<(u32, u32)> = core.cut().split_diamonds().collect();
        split.sort_unstable();
        split
    };
    // The default camera, the fog as given.
    let view = |fog: bool| {
        Event::View(ViewChange {
            pitch_deg: DEFAULT_PITCH_DEG as f32,
            eye_above: 0.0,
            viewport: [640, 480],
            fog,
        })
    };
    for v in &drive[..4] {
        core.make_frame(&scene, v);
    }
    core.handle(view(false));
    assert_eq!(core.fog_density(&scene), 0.0);
    assert_eq!(core.make_frame(&scene, &drive[4]).mode, Mode::Rebuild);
    let plain = scratch(&core, &drive[4], 0.0);
    assert_eq!(cut(&core), plain, "fog off: the fog-unaware cut");
    assert_eq!(core.make_frame(&scene, &drive[5]).mode, Mode::Update);
    core.handle(view(true));
    assert_eq!(core.make_frame(&scene, &drive[6]).mode, Mode::Rebuild);
    let fogged = scratch(&core, &drive[6], density);
    assert_eq!(cut(&core), fogged, "fog on: the fog-aware cut");
    assert_ne!(
        fogged,
        scratch(&core, &drive[6], 0.0),
        "the fog changes the cut"
    );
    // A server serving without fog priority: density 0 whatever the viewer draws.
    let caps = ViewerLimits {
        fog_priority: false,
        ..ViewerLimits::default()
    };
    let mut off = fx.core(3000).with_caps(caps);
    assert_eq!(off.fog_density(&scene), 0.0);
    off.handle(view(true));
    assert_eq!(off.fog_density(&scene), 0.0);
    off.make_frame(&scene, &drive[6]);
    assert_eq!(cut(&off), scratch(&off, &drive[6], 0.0));
}

/// A frame begun in line (on the server's async workers) is made there only when it is
/// cheap: an update of at most `INLINE_CHANGES` changes coded as a change frame. A
/// rebuild (the first frame, a jump), a larger update and a key frame (asked for, or a
/// base the logs no longer reach) are left unfinished for a blocking thread. Either way
/// the frames are the very ones `make_frame` makes, byte for byte.
#[test]
fn frames_begun_in_line_leave_rebuilds_and_key_frames_unfinished() {
    let fx = Fixture::new(257, 5);
    let scene = fx.scene();
    let drive = fx.drive(40);
    let (mut twostep, mut oneshot) = (fx.core(16_000), fx.core(16_000));
    let mut inline = 0;
    // `cheap`: whether the frame must be made in line (`None`: either).
    let mut check = |k: usize, state: &VehicleState, events: &[Event], cheap: Option<bool>| {
        for &e in events {
            twostep.handle(e);
            oneshot.handle(e);
        }
        let begun = twostep.begin_frame(&scene, state);
        let inline_made = begun.is_some();
        if let Some(cheap) = cheap {
            assert_eq!(inline_made, cheap, "frame {k}: made in line");
        }
        assert_eq!(
            twostep.unfinished(),
            !inline_made,
            "frame {k}: left unfinished"
        );
        let made = begun.unwrap_or_else(|| twostep.finish_frame(&scene));
        assert!(!twostep.unfinished());
        let want = oneshot.make_frame(&scene, state);
        assert_eq!(made, want, "frame {k}: the same frame either way");
        if inline_made {
            assert!(made.base.is_some(), "frame {k}: a key frame made in line");
            assert!(made.changes <= roam_server::viewer::INLINE_CHANGES);
            inline += 1;
        }
        made
    };
    // The first frame rebuilds and is a key frame.
    let first = check(0, &drive[0], &[], Some(false));
    assert_eq!((first.mode, first.base), (Mode::Rebuild, None));
    assert!(first.triangles > 12_000, "{} triangles", first.triangles);
    // Acknowledged: the frames of a drive are cheap updates, but for a sharp turn's.
    let mut last = first.frame;
    for (k, state) in drive.iter().enumerate().take(20).skip(1) {
        last = check(k, state, &[Event::Acked(last)], None).frame;
    }
    // A key frame asked for: the update is cheap, its coding is not.
    let key = check(20, &drive[20], &[Event::KeyFrame], Some(false));
    assert_eq!((key.mode, key.base), (Mode::Update, None));
    last = check(21, &drive[21], &[Event::Acked(key.frame)], None).frame;
    // A budget cut by a quarter (within the jump's ×2) is an update of thousands of merges, within
    // its bound but past INLINE_CHANGES: left for the blocking thread, which goes on from
    // where the first step stopped.
    let halved = check(
        22,
        &drive[22],
        &[Event::Acked(last), Event::Budget(12_000)],
        Some(false),
    );
    assert_eq!(halved.mode, Mode::Update);
    assert!(halved.changes > roam_server::viewer::INLINE_CHANGES);
    assert!(halved.triangles <= 12_000);
    // A jump across the map rebuilds.
    let mut far = drive[23];
    far.x = fx.terrain.map.h_scale * 20.0;
    far.z = fx.terrain.map.h_scale * 230.0;
    let jumped = check(23, &far, &[Event::Acked(halved.frame)], Some(false));
    assert_eq!(jumped.mode, Mode::Rebuild);
    assert!(inline >= 15, "{inline} of 20 driving frames made in line");
}

/// Admission reserves a viewer's state from its budget before it costs anything
/// (`viewer::admission::viewer_bytes`): a driving viewer's core, whatever its budget and
/// however its budget changes, must stay within the cut's share of it and the core's own.
#[test]
fn a_driving_viewers_state_stays_within_its_admission_estimate() {
    use roam_server::viewer::admission::{CORE_BYTES, CUT_BYTES_PER_TRIANGLE};
    let fx = Fixture::new(257, 11);
    let scene = fx.scene();
    let drive = fx.drive(150);
    for budget in [500u32, 4_000, 40_000] {
        let mut core = fx.core(budget);
        let most = u64::from(budget) * CUT_BYTES_PER_TRIANGLE + CORE_BYTES;
        let mut largest = 0;
        for (k, state) in drive.iter().enumerate() {
            // Halfway, the viewer halves its budget and then asks for it back.
            match k {
                50 => core.handle(Event::Budget(budget / 2)),
                60 => core.handle(Event::Budget(budget)),
                _ => {}
            }
            let made = core.make_frame(&scene, state);
            core.handle(Event::Acked(made.frame));
            largest = largest.max(core.heap_bytes() as u64);
        }
        assert!(
            largest <= most,
            "{budget} triangles: {largest} bytes, more than the {most} reserved"
        );
        // Not a bound so loose that the cut's share would reserve four times what a
        // viewer holds (the core's fixed share aside: it weighs most at small budgets).
        if budget >= 4_000 {
            let share = u64::from(budget) * CUT_BYTES_PER_TRIANGLE;
            assert!(
                largest * 4 > share,
                "{budget} triangles: {largest} bytes held, {share} reserved for the cut"
            );
        }
    }
}

/// A swap margin: along a drive (throttle, turns both ways), a cut at its budget trades
/// fewer diamonds of nearly equal priority, so fewer change, and its error stays within
/// the margin of what the budget allows.
#[test]
fn a_swap_margin_trades_less_along_a_drive() {
    use roam_server::viewer::ViewerLimits;
    let fx = Fixture::new(513, 3);
    let scene = fx.scene();
    let drive = fx.drive(600);
    let run = |pct: u16| {
        let caps = ViewerLimits {
            swap_margin_pct: pct,
            ..ViewerLimits::default()
        };
        let mut core = fx.core(8000).with_caps(caps);
        let (mut changes, mut error) = (0u64, 0f64);
        for (k, v) in drive.iter().enumerate() {
            let made = core.make_frame(&scene, v);
            if k > 0 {
                assert_eq!(made.mode, Mode::Update, "frame {k}");
                changes += u64::from(made.changes);
                error += f64::from(core.cut().error_bound_px());
            }
        }
        (changes, error / (drive.len() - 1) as f64)
    };
    let ((plain, plain_error), (fewer, error)) = (run(0), run(30));
    let wild = ViewerLimits {
        swap_margin_pct: u16::MAX,
        ..ViewerLimits::default()
    };
    assert_eq!(
        wild.clamped().swap_margin_pct,
        roam_server::viewer::MAX_SWAP_MARGIN_PCT,
        "a margin past the most a server takes is served as the most"
    );
    assert!(
        (fewer as f64) < 0.9 * plain as f64,
        "{fewer} changes with the margin, {plain} without"
    );
    assert!(
        error <= 1.3 * plain_error,
        "error left {error} px with the margin, {plain_error} px without"
    );
}
