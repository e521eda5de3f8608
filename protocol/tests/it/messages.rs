//! Every message round-trips; limits hold; any bytes decode to a value or an error.

use proptest::prelude::*;
use roam_protocol::messages::{
    self, ClientMessage, ColorLayout, DecodeError, Frame, Hello, KeyDatagram, KeyState,
    MAX_TILE_BYTES, Reason, Role, ServerMessage, VehicleView, Welcome, WorldNews,
};

fn round_trip<T>(msg: &T)
where
    T: serde::Serialize
        + serde::de::DeserializeOwned
        + messages::Checked
        + PartialEq
        + std::fmt::Debug,
{
    let mut bytes = Vec::new();
    messages::encode(msg, &mut bytes).expect("encodes");
    let back: T = messages::decode(&bytes).expect("decodes");
    assert_eq!(&back, msg);
    // Every strict prefix is an error, and so are trailing bytes.
    for cut in 0..bytes.len() {
        assert!(
            messages::decode::<T>(&bytes[..cut]).is_err(),
            "{msg:?} cut at {cut}"
        );
    }
    bytes.push(0);
    assert!(matches!(
        messages::decode::<T>(&bytes),
        Err(DecodeError::Trailing { extra: 1 })
    ));
}

fn hello() -> Hello {
    Hello {
        version: messages::VERSION,
        role: Role::Spectator { follow: Some(3) },
        token: "c0ffee-42".into(),
        viewport: [1920, 1080],
        fov_y_deg: 60.0,
        budget: 65_536,
        frame_rate: 60,
        resume: None,
        color_window: 8,
    }
}

#[test]
fn every_message_round_trips() {
    for m in [
        ClientMessage::Hello(hello()),
        ClientMessage::Hello(Hello {
            role: Role::Driver,
            ..hello()
        }),
        ClientMessage::Budget(46_341),
        ClientMessage::Ack { frame: u64::MAX },
        ClientMessage::KeyFrame,
        ClientMessage::View(messages::ViewChange {
            pitch_deg: -12.5,
            eye_above: 1.5,
            viewport: [800, 600],
            fog: true,
        }),
        ClientMessage::View(messages::ViewChange {
            pitch_deg: 3.0,
            eye_above: -0.5,
            viewport: [1920, 1080],
            fog: false,
        }),
        ClientMessage::Bye(Reason::Quit),
        ClientMessage::Bye(Reason::Protocol("bad".into())),
    ] {
        round_trip(&m);
    }
    let welcome = Welcome {
        version: messages::VERSION,
        levels: 10,
        h_scale: 92.0,
        v_scale: 0.01,
        sun_dir: [-0.757, 0.574, 0.313],
        sun_color: [255, 244, 225],
        fog_density: 5e-5,
        fog_color: [200, 210, 218],
        water_level: Some(28.5),
        vehicle: 0,
        color: ColorLayout::new(1024, 256, 8).expect("a valid layout"),
        tick: 9_000,
        ticket: None,
        resumed: false,
        max_budget: messages::MAX_BUDGET,
        max_fps: 240,
    };
    for m in [
        ServerMessage::Welcome(welcome.clone()),
        ServerMessage::Welcome(Welcome {
            water_level: None,
            ..welcome
        }),
        ServerMessage::ColorWindow {
            level: 1,
            x0: 300,
            z0: 7,
        },
        ServerMessage::ColorTile {
            level: 2,
            x: 127,
            z: 128,
            data: vec![7; 1000],
        },
        ServerMessage::NormalTile {
            level: 3,
            x: 5,
            z: 0,
            data: vec![9; 700],
        },
        ServerMessage::Refused(Reason::WrongToken),
        ServerMessage::Refused(Reason::Version { server: 1 }),
        ServerMessage::Bye(Reason::Shutdown),
        ServerMessage::Bye(Reason::Unavailable("no vehicle 9".into())),
        ServerMessage::World(WorldNews::Gone("no snapshot for 2 s".into())),
        ServerMessage::World(WorldNews::Back),
        ServerMessage::World(WorldNews::Edges(vec![
            "10.0.0.2:4433".into(),
            "https://10.0.0.2:4434".into(),
        ])),
    ] {
        round_trip(&m);
    }
    round_trip(&Frame {
        frame: 17,
        base: Some(15),
        tick: 1_234,
        vehicles: vec![VehicleView {
            id: 0,
            x: 37_628.5,
            z: 82_984.25,
            y: 41.0,
            speed: 9.5,
            heading: 53.0,
        }],
        input_seq: Some(41),
        mesh: (0..=255).collect(),
    });
    round_trip(&Frame {
        frame: 0,
        base: None,
        tick: 0,
        vehicles: vec![],
        input_seq: None,
        mesh: vec![],
    });
    round_trip(&KeyDatagram {
        states: (0..8)
            .map(|i| KeyState {
                seq: 100 - i,
                held: 1,
                pressed: (i % 2) as u8,
            })
            .collect(),
        acked: Some(u64::MAX),
    });
    round_trip(&KeyDatagram {
        states: vec![],
        acked: None,
    });
}

/// What a decode should give.
#[derive(Debug, PartialEq)]
enum Want {
    Value,
    /// `DecodeError::TooLong` naming the field, the length and the limit.
    TooLong(&'static str, usize, usize),
    /// Any other error.
    Error,
}

/// Which message type the bytes are decoded as.
#[derive(Clone, Copy, Debug)]
enum As {
    Client,
    Server,
    Frame,
    Keys,
}

fn outcome<T: serde::de::DeserializeOwned + messages::Checked>(bytes: &[u8]) -> Want {
    match messages::decode::<T>(bytes) {
        Ok(_) => Want::Value,
        Err(DecodeError::TooLong { what, got, limit }) => Want::TooLong(what, got, limit),
        Err(_) => Want::Error,
    }
}

/// Decoding `input` as `kind` gives `want`.
fn check(name: &str, kind: As, input: &[u8], want: Want) {
    let got = match kind {
        As::Client => outcome::<ClientMessage>(input),
        As::Server => outcome::<ServerMessage>(input),
        As::Frame => outcome::<Frame>(input),
        As::Keys => outcome::<KeyDatagram>(input),
    };
    assert_eq!(got, want, "{name}");
}

fn encoded<T: serde::Serialize>(msg: &T) -> Vec<u8> {
    let mut bytes = Vec::new();
    messages::encode(msg, &mut bytes).expect("encodes");
    bytes
}

/// `prefix`, then a bincode varint claiming `len` (its `u32` form), then `rest`.
fn claiming(prefix: &[u8], len: u32, rest: &[u8]) -> Vec<u8> {
    let mut v = prefix.to_vec();
    v.push(252);
    v.extend_from_slice(&len.to_le_bytes());
    v.extend_from_slice(rest);
    v
}

#[test]
fn limits() {
    use Want::{Error, TooLong, Value};
    let token = |n: usize| {
        encoded(&ClientMessage::Hello(Hello {
            token: "x".repeat(n),
            role: Role::Driver,
            ..hello()
        }))
    };
    let reason = |n: usize| Reason::Protocol("r".repeat(n));
    let tile = |n: usize| {
        encoded(&ServerMessage::ColorTile {
            level: 0,
            x: 0,
            z: 0,
            data: vec![3; n],
        })
    };
    let normals = |n: usize| {
        encoded(&ServerMessage::NormalTile {
            level: 0,
            x: 0,
            z: 0,
            data: vec![3; n],
        })
    };
    let keys = |n: usize| {
        encoded(&KeyDatagram {
            states: vec![
                KeyState {
                    seq: 1,
                    held: 0,
                    pressed: 0
                };
                n
            ],
            acked: None,
        })
    };
    let mb16 = 16 << 20;
    // A hello: variant, version, role (a driver), then the token's length.
    let hello_head = [0, messages::VERSION as u8, 0];
    // A frame: frame 3, no base, tick 77, then its vehicles' count.
    let frame_head = [3, 0, 77];
    let mut bad_utf8 = token(2);
    // The token's first byte, after the hello's head and the token's length.
    bad_utf8[hello_head.len() + 1] = 0xff;
    // A view change ends with its fog flag: one byte, 0 or 1.
    let view = |fog: u8| {
        let mut v = encoded(&ClientMessage::View(messages::ViewChange {
            pitch_deg: -5.0,
            eye_above: 0.0,
            viewport: [640, 480],
            fog: true,
        }));
        *v.last_mut().expect("a message has bytes") = fog;
        v
    };
    for (name, kind, input, want) in [
        ("a view change without fog", As::Client, view(0), Value),
        ("a view change with fog", As::Client, view(1), Value),
        ("a view change whose fog is 2", As::Client, view(2), Error),
        ("a 128-byte token", As::Client, token(128), Value),
        (
            "a 129-byte token",
            As::Client,
            token(129),
            TooLong("join token bytes", 129, 128),
        ),
        (
            "a token claiming 16 MiB",
            As::Client,
            claiming(&hello_head, mb16, b"abc"),
            TooLong("join token bytes", 16 << 20, 128),
        ),
        ("a token that is not UTF-8", As::Client, bad_utf8, Error),
        (
            "a 1024-byte reason",
            As::Client,
            encoded(&ClientMessage::Bye(reason(1024))),
            Value,
        ),
        (
            "a 1025-byte reason from a viewer",
            As::Client,
            encoded(&ClientMessage::Bye(reason(1025))),
            TooLong("reason bytes", 1025, 1024),
        ),
        (
            "a 1025-byte reason from a server",
            As::Server,
            encoded(&ServerMessage::Refused(reason(1025))),
            TooLong("reason bytes", 1025, 1024),
        ),
        (
            "a colour tile of the largest payload",
            As::Server,
            tile(MAX_TILE_BYTES),
            Value,
        ),
        (
            "a colour tile a byte longer",
            As::Server,
            tile(MAX_TILE_BYTES + 1),
            TooLong("colour tile bytes", MAX_TILE_BYTES + 1, MAX_TILE_BYTES),
        ),
        (
            "a colour tile claiming 16 MiB",
            As::Server,
            // Variant 2 (a tile), level 0, x 0, z 0, then the payload's length.
            claiming(&[2, 0, 0, 0], mb16, &[]),
            TooLong("colour tile bytes", 16 << 20, MAX_TILE_BYTES),
        ),
        (
            "a normal tile of the largest payload",
            As::Server,
            normals(MAX_TILE_BYTES),
            Value,
        ),
        (
            "a normal tile a byte longer",
            As::Server,
            normals(MAX_TILE_BYTES + 1),
            TooLong("normal tile bytes", MAX_TILE_BYTES + 1, MAX_TILE_BYTES),
        ),
        (
            "a normal tile claiming 16 MiB",
            As::Server,
            // Variant 6 (a tile's normals), level 0, x 0, z 0, then the payload's length.
            claiming(&[6, 0, 0, 0], mb16, &[]),
            TooLong("normal tile bytes", 16 << 20, MAX_TILE_BYTES),
        ),
        (
            "a frame claiming 65,537 vehicles",
            As::Frame,
            claiming(&frame_head, 65_537, &[]),
            TooLong("vehicles", 65_537, 65_536),
        ),
        (
            "a frame claiming 65,536 vehicles it does not hold",
            As::Frame,
            claiming(&frame_head, 65_536, &[0; 60]),
            Error,
        ),
        (
            "a frame claiming a mesh it does not hold",
            As::Frame,
            claiming(&[3, 0, 77, 0, 0], mb16, &[0; 60]),
            Error,
        ),
        ("eight key states", As::Keys, keys(8), Value),
        (
            "nine key states",
            As::Keys,
            keys(9),
            TooLong("key states", 9, 8),
        ),
        (
            "a key datagram claiming 2^20 states",
            As::Keys,
            claiming(&[], 1 << 20, &[]),
            TooLong("key states", 1 << 20, 8),
        ),
        (
            "a key datagram longer than a datagram",
            As::Keys,
            vec![0; 300],
            TooLong("message bytes", 300, 256),
        ),
    ] {
        check(name, kind, &input, want);
    }
    let mut bad_utf8 = token(2);
    bad_utf8[hello_head.len() + 1] = 0xff;
    let err = messages::decode::<ClientMessage>(&bad_utf8).expect_err("not UTF-8");
    assert!(
        err.to_string()
            .contains("join token bytes: not UTF-8 at byte 0"),
        "{err}"
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn any_bytes_decode_to_a_value_or_an_error(bytes in prop::collection::vec(any::<u8>(), 0..300)) {
        let _ = messages::decode::<ClientMessage>(&bytes);
        let _ = messages::decode::<ServerMessage>(&bytes);
        let _ = messages::decode::<Frame>(&bytes);
        let _ = messages::decode::<KeyDatagram>(&bytes);
    }
}
