//! The conversation's decisions, one boundary each: when a frame is due, how it goes
//! (datagram, stream, a copy on a lossy path), what is reset when a newer frame comes, the
//! budget's clamp, a spectator's switch, and the end when the vehicle leaves.

use std::sync::Arc;
use std::time::{Duration, Instant};

use roam_protocol::messages::{ClientMessage, Hello, KeyDatagram, KeyState, Role as HelloRole};

use super::*;
use crate::sim::world_core::WorldCore;
use crate::terrain::variance::VarianceTree;
use crate::tessellate::Scratch;
use crate::viewer::{Scene, ViewerLimits};

struct Fixture {
    terrain: Arc<Terrain>,
    variance: VarianceTree,
    scratch: Scratch,
    world: WorldCore,
    t0: Instant,
}

fn fixture() -> Fixture {
    let terrain = Arc::new(crate::terrain::generate::synthetic(129, 7));
    let variance = VarianceTree::build(&terrain.heights, 1, &mut |_, _| {});
    let scratch = Scratch::new(terrain.heights.side(), 1);
    let world = WorldCore::new(terrain.clone(), None).expect("no recording to fail");
    Fixture {
        terrain,
        variance,
        scratch,
        world,
        t0: Instant::now(),
    }
}

fn hello(budget: u32, role: HelloRole) -> Hello {
    Hello {
        version: roam_protocol::messages::VERSION,
        role,
        token: "t".into(),
        viewport: [640, 480],
        fov_y_deg: 60.0,
        budget,
        frame_rate: 50,
        resume: None,
        color_window: 4,
    }
}

impl Fixture {
    fn scene(&self) -> Scene<'_> {
        Scene {
            terrain: &self.terrain,
            variance: &self.variance,
            scratch: &self.scratch,
        }
    }

    /// A driver's conversation, its vehicle in the world, and the snapshot showing it.
    fn driver(&mut self, budget: u32) -> (Conversation, Arc<Snapshot>) {
        let vehicle = self.world.handle(world_core::Event::Join).expect("room");
        let snap = Arc::new(self.world.tick());
        let role = Role {
            vehicle,
            driver: true,
            replay: false,
        };
        let h = hello(budget, HelloRole::Driver);
        let c = Conversation::new(
            &self.terrain,
            1,
            &h,
            ViewerLimits::default(),
            role,
            (self.t0, self.t0),
        );
        (c, snap)
    }

    /// The frame due at `at`, its heavy part run in place.
    fn frame(&self, c: &mut Conversation, at: Instant, snap: &Arc<Snapshot>) -> Step {
        match c.frame(at, &self.scene(), snap, &mut |b| b) {
            Step::Heavy(job) => {
                let done = job.run(&self.scene(), || snap.clone());
                c.finish(at, &self.terrain, done)
            }
            other => other,
        }
    }
}

fn drain(c: &mut Conversation, now: Instant) -> Vec<String> {
    std::iter::from_fn(|| c.poll_transmit(now))
        .map(|t| match t {
            Transmit::Datagram { frame, .. } => format!("datagram {frame}"),
            Transmit::Stream {
                frame, priority, ..
            } => format!("stream {frame} at {priority}"),
            Transmit::Reset { frame } => format!("reset {frame}"),
        })
        .collect()
}

const MS: Duration = Duration::from_millis(1);

#[test]
fn frames_are_due_on_the_grid_of_their_period_missed_ones_skipped() {
    let mut f = fixture();
    let (mut c, snap) = f.driver(2048);
    let t0 = f.t0;
    assert!(c.frame_due(t0), "the first frame is due at once");
    assert!(matches!(f.frame(&mut c, t0 + 3 * MS, &snap), Step::Sent(_)));
    // 50 Hz from the origin: 20 ms, then 40 ms.
    assert_eq!(c.poll_timeout(), Some(t0 + 20 * MS));
    assert!(matches!(f.frame(&mut c, t0 + 19 * MS, &snap), Step::Idle));
    assert!(matches!(
        f.frame(&mut c, t0 + 20 * MS, &snap),
        Step::Sent(_)
    ));
    assert_eq!(c.poll_timeout(), Some(t0 + 40 * MS));
    // Late by more than two periods: one frame, then the next grid point after it.
    assert!(matches!(
        f.frame(&mut c, t0 + 95 * MS, &snap),
        Step::Sent(_)
    ));
    assert_eq!(c.poll_timeout(), Some(t0 + 100 * MS));
    assert_eq!(c.frames(), 3);
}

/// While viewers join, a served viewer's due frame may be passed over: never its first,
/// never two in a row, and the next is due on its grid.
#[test]
fn frames_passed_over_while_viewers_join_alternate_and_keep_the_grid() {
    let mut f = fixture();
    let (mut c, snap) = f.driver(2048);
    let t0 = f.t0;
    assert!(!c.pass_over(t0), "a first frame is never passed over");
    assert!(matches!(f.frame(&mut c, t0, &snap), Step::Sent(_)));
    assert!(!c.pass_over(t0 + 10 * MS), "nothing due yet");
    // Due at 20 ms (50 Hz): passed over, the next due at 40 ms.
    assert!(c.pass_over(t0 + 21 * MS));
    assert_eq!(c.poll_timeout(), Some(t0 + 40 * MS));
    assert!(!c.frame_due(t0 + 30 * MS));
    // Not twice in a row, however often asked between.
    assert!(!c.pass_over(t0 + 30 * MS));
    assert!(!c.pass_over(t0 + 40 * MS));
    assert!(matches!(
        f.frame(&mut c, t0 + 40 * MS, &snap),
        Step::Sent(_)
    ));
    // Made: the next may be passed over again.
    assert!(c.pass_over(t0 + 60 * MS));
    assert_eq!(c.frames(), 2);
}

#[test]
fn a_key_frame_goes_on_a_stream_and_change_frames_as_datagrams() {
    let mut f = fixture();
    let (mut c, snap) = f.driver(2048);
    let t0 = f.t0;
    let path = |max| Event::Path {
        max_datagram: max,
        lost: 0,
        sent: 0,
    };
    c.handle(t0, path(Some(1200)));
    let Step::Sent(first) = f.frame(&mut c, t0, &snap) else {
        panic!("the first frame is made")
    };
    assert_eq!(first.key, Some(KeyCause::First));
    assert_eq!(drain(&mut c, t0), ["stream 0 at 2147483647"]);
    // Not acknowledged: the next is coded against the pending key frame, a datagram; the
    // key frame's stream is kept.
    let t1 = t0 + 20 * MS;
    f.frame(&mut c, t1, &snap);
    assert_eq!(drain(&mut c, t1), ["datagram 1"]);
    // A path that takes no datagram: on a stream, at its frame's priority.
    c.handle(t1, path(None));
    let t2 = t0 + 40 * MS;
    f.frame(&mut c, t2, &snap);
    assert_eq!(drain(&mut c, t2), ["stream 2 at 2"]);
    // The viewer asks for a key frame: the old key frame (no longer pending, unacknowledged)
    // and the change frame's stream are reset.
    assert_eq!(c.handle(t2, Event::Control(ClientMessage::KeyFrame)), None);
    let t3 = t0 + 60 * MS;
    f.frame(&mut c, t3, &snap);
    assert_eq!(
        drain(&mut c, t3),
        ["reset 0", "reset 2", "stream 3 at 2147483647"]
    );
    // Acknowledged, nothing is reset.
    c.handle(t3, Event::Control(ClientMessage::Ack { frame: 3 }));
    let t4 = t0 + 80 * MS;
    f.frame(&mut c, t4, &snap);
    assert_eq!(drain(&mut c, t4), ["stream 4 at 4"]);
}

#[test]
fn small_frames_go_twice_on_a_lossy_path_and_a_refused_datagram_takes_a_stream() {
    let mut f = fixture();
    let (mut c, snap) = f.driver(2048);
    let t0 = f.t0;
    f.frame(&mut c, t0, &snap);
    drain(&mut c, t0);
    c.handle(t0, Event::Control(ClientMessage::Ack { frame: 0 }));
    // 5 % lost over a window.
    for (lost, sent) in [(0, 0), (10, 200)] {
        let path = Event::Path {
            max_datagram: Some(1200),
            lost,
            sent,
        };
        c.handle(t0, path);
    }
    let t1 = t0 + 20 * MS;
    f.frame(&mut c, t1, &snap);
    assert_eq!(drain(&mut c, t1), ["datagram 1"]);
    assert_eq!(
        c.poll_timeout(),
        Some(t1 + REPEAT_AFTER),
        "the copy is due first"
    );
    assert_eq!(drain(&mut c, t1 + REPEAT_AFTER), ["datagram 1"]);
    // The shell could not send it after all: a stream; a copy refused, or an older
    // frame, is let go.
    let refused = |frame| Event::Refused {
        frame,
        bytes: vec![1, 2, 3],
    };
    c.handle(t1, refused(1));
    c.handle(t1, refused(1));
    c.handle(t1, refused(0));
    assert_eq!(drain(&mut c, t1), ["stream 1 at 1"]);
}

#[test]
fn a_budget_is_clamped_by_the_limits_then_granted() {
    let mut f = fixture();
    let (mut c, snap) = f.driver(2048);
    let t0 = f.t0;
    let mut asked = Vec::new();
    c.handle(t0, Event::Control(ClientMessage::Budget(u32::MAX)));
    let step = c.frame(t0, &f.scene(), &snap, &mut |b| {
        asked.push(b);
        b / 2
    });
    let max = ViewerLimits::default().max_budget;
    assert_eq!(
        asked,
        [max],
        "clamped to the server's limit before the grant"
    );
    let Step::Heavy(job) = step else {
        panic!("a first frame is heavy")
    };
    c.finish(t0, &f.terrain, job.run(&f.scene(), || snap.clone()));
    assert_eq!(c.core().map(|k| k.budget()), Some(max / 2));
}

#[test]
fn key_datagrams_become_world_events_for_a_driver_only() {
    let mut f = fixture();
    let (mut c, _) = f.driver(2048);
    let t0 = f.t0;
    let state = KeyState {
        seq: 1,
        held: 1,
        pressed: 0,
    };
    let d = KeyDatagram {
        states: vec![state],
        acked: None,
    };
    let mut bytes = Vec::new();
    roam_protocol::messages::encode(&d, &mut bytes).expect("a small datagram");
    let got = c.handle(t0 + 5 * MS, Event::Datagram(&bytes));
    assert_eq!(
        got,
        Some(Handled::World(world_core::Event::Keys {
            vehicle: c.vehicle(),
            states: vec![state],
        }))
    );
    assert_eq!(c.handle(t0 + 10 * MS, Event::Datagram(b"not one")), None);
    assert_eq!(
        c.silent(t0 + 25 * MS, t0),
        15 * MS,
        "since the last datagram, any"
    );
    assert_eq!(
        c.handle(
            t0,
            Event::Control(ClientMessage::Bye(roam_protocol::messages::Reason::Quit))
        ),
        Some(Handled::Goodbye)
    );
}

/// The frame a driver's key datagram acknowledges, as the conversation takes it: the core's
/// acknowledged frame after the next frame, and whether that frame is a key frame.
fn acked_by_datagram(
    f: &Fixture,
    c: &mut Conversation,
    acked: Option<u64>,
    at: Instant,
    snap: &Arc<Snapshot>,
) -> (Option<u64>, Option<KeyCause>) {
    let d = KeyDatagram {
        states: vec![],
        acked,
    };
    let mut bytes = Vec::new();
    roam_protocol::messages::encode(&d, &mut bytes).expect("a small datagram");
    c.handle(at, Event::Datagram(&bytes));
    let Step::Sent(sent) = f.frame(c, at, snap) else {
        panic!("a frame is due every 20 ms")
    };
    (c.core().and_then(ViewerCore::acked), sent.key)
}

#[test]
fn a_key_datagram_acknowledges_frames_but_none_made_before_a_key_frame_request() {
    let mut f = fixture();
    let (mut c, snap) = f.driver(2048);
    let t0 = f.t0;
    assert!(matches!(f.frame(&mut c, t0, &snap), Step::Sent(_)));
    let mut check = |acked, k: u32, control: Option<ClientMessage>, want| {
        if let Some(m) = control {
            c.handle(t0, Event::Control(m));
        }
        let at = t0 + k * 20 * MS;
        assert_eq!(
            acked_by_datagram(&f, &mut c, acked, at, &snap),
            want,
            "frame {k}"
        );
    };
    // Frame 0 acknowledged: frame 1 is coded against it.
    check(Some(0), 1, None, (Some(0), None));
    // An acknowledgement of a frame not made yet is not taken.
    check(Some(9), 2, None, (Some(0), None));
    // A key frame asked for, then frame 2 (made before the request) acknowledged by a
    // datagram that arrived late: not taken, the key frame made.
    check(
        Some(2),
        3,
        Some(ClientMessage::KeyFrame),
        (None, Some(KeyCause::Asked)),
    );
    // The key frame acknowledged: taken.
    check(Some(3), 4, None, (Some(3), None));
}

#[test]
fn a_spectator_switches_to_a_vehicle_there_and_ends_when_its_vehicle_leaves() {
    let mut f = fixture();
    let a = f.world.handle(world_core::Event::Join).expect("room");
    let b = f.world.handle(world_core::Event::Join).expect("room");
    let snap = Arc::new(f.world.tick());
    let role = Role {
        vehicle: a,
        driver: false,
        replay: false,
    };
    let h = hello(2048, HelloRole::Spectator { follow: Some(a) });
    let t0 = f.t0;
    let mut c = Conversation::new(&f.terrain, 1, &h, ViewerLimits::default(), role, (t0, t0));
    f.frame(&mut c, t0, &snap);
    c.handle(t0, Event::Control(ClientMessage::Follow(99)));
    f.frame(&mut c, t0 + 20 * MS, &snap);
    assert_eq!(c.poll_event(), None, "no vehicle 99: it stays");
    c.handle(t0, Event::Control(ClientMessage::Follow(b)));
    f.frame(&mut c, t0 + 40 * MS, &snap);
    assert_eq!(c.poll_event(), Some(Out::Following(b)));
    f.world.handle(world_core::Event::Leave(b));
    let gone = Arc::new(f.world.tick());
    assert!(matches!(
        f.frame(&mut c, t0 + 60 * MS, &gone),
        Step::End(End::VehicleLeft)
    ));
}

#[test]
fn a_frame_shows_the_followed_vehicle_and_those_nearest_it() {
    let mut f = fixture();
    let (c, _) = f.driver(2048);
    let me = c.vehicle();
    let dist = |snap: &Snapshot, id| {
        let (a, b) = (
            snap.vehicles.iter().find(|v| v.id == me),
            snap.vehicles.iter().find(|v| v.id == id),
        );
        let (a, b) = (a.expect("followed").state, b.expect("shown").state);
        (a.x - b.x).hypot(a.z - b.z)
    };
    let check = |snap: &Snapshot, want: usize| {
        let made = crate::viewer::Made {
            frame: 0,
            base: None,
            payload: Vec::new(),
            mode: crate::tessellate::Mode::Update,
            changes: 0,
            triangles: 0,
            key: None,
        };
        let shown: Vec<VehicleId> = frame_message(&f.terrain, snap, made, me, true)
            .vehicles
            .iter()
            .map(|v| v.id)
            .collect();
        assert_eq!(shown.len(), want);
        assert!(shown.contains(&me), "the followed vehicle is always shown");
        let order: Vec<VehicleId> = snap
            .vehicles
            .iter()
            .map(|v| v.id)
            .filter(|id| shown.contains(id))
            .collect();
        assert_eq!(shown, order, "in the snapshot's order");
        let far = shown.iter().map(|&id| dist(snap, id)).fold(0.0, f64::max);
        for v in snap.vehicles.iter().filter(|v| !shown.contains(&v.id)) {
            assert!(dist(snap, v.id) >= far, "a nearer vehicle left out");
        }
    };
    for _ in 0..9 {
        f.world.handle(world_core::Event::Join);
    }
    check(&f.world.tick(), 10);
    for _ in 0..20 {
        f.world.handle(world_core::Event::Join);
    }
    check(&f.world.tick(), MAX_SHOWN);
}

/// The clock's allowance reaches the cut: the same view change (the eye pitched 25° down)
/// stops short with an allowance of 4 changes, after fewer changes than without one,
/// and the frame says so; without one, the frame is whole.
#[test]
fn an_allowance_holds_a_frames_cut_back_and_the_frame_says_so() {
    let run = |allowance: u32| {
        let mut f = fixture();
        let (mut c, snap) = f.driver(2048);
        let t0 = f.t0;
        f.frame(&mut c, t0, &snap);
        c.handle(t0, Event::Control(ClientMessage::Ack { frame: 0 }));
        c.set_allowance(allowance);
        let view = roam_protocol::messages::ViewChange {
            pitch_deg: -30.0,
            eye_above: 0.0,
            viewport: [640, 480],
            fog: true,
        };
        c.handle(t0, Event::Control(ClientMessage::View(view)));
        let Step::Sent(sent) = f.frame(&mut c, t0 + 20 * MS, &snap) else {
            panic!("the second frame is made");
        };
        let core = c.core().expect("the frame is made in line");
        (sent.short, core.cut().changes().len())
    };
    let (held, free) = (run(4), run(u32::MAX));
    assert!(held.0 && !free.0, "held {held:?}, free {free:?}");
    assert!(
        4 <= held.1 && held.1 < free.1,
        "held {held:?}, free {free:?}"
    );
}

/// What the clock's allowance hears of a frame's lateness is the wait for the core only:
/// nothing for a first frame (its wait for its turn is the clock's own), and for a frame
/// whose core came back from a job after the frame was due, from when it came back.
#[test]
fn a_frames_lateness_counts_only_the_wait_for_the_core() {
    let mut f = fixture();
    let (mut c, snap) = f.driver(2048);
    let t0 = f.t0;
    assert_eq!(c.late(t0 + 30 * MS), None, "a first frame");
    let Step::Heavy(job) = c.frame(t0, &f.scene(), &snap, &mut |b| b) else {
        panic!("a first frame is made off the pass");
    };
    let done = job.run(&f.scene(), || snap.clone());
    // Due again 20 ms after t0 (50 Hz); the core comes back 50 ms after it.
    let back = t0 + 50 * MS;
    assert!(matches!(c.finish(back, &f.terrain, done), Step::Sent(_)));
    assert!(c.due_at() < back);
    assert_eq!(c.late(back + 2 * MS), Some(2 * MS));
    f.frame(&mut c, back + 2 * MS, &snap);
    let due = c.due_at();
    assert_eq!(c.late(due + 3 * MS), Some(3 * MS), "on the grid again");
}
