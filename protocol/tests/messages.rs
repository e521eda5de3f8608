//! Every message round-trips; limits hold; any bytes decode to a value or an error.

use proptest::prelude::*;
use roam_protocol::messages::{
    self, ClientMessage, DecodeError, Frame, Hello, KeyDatagram, KeyState, Reason, Role,
    ServerMessage, VehicleView, Welcome,
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
        color_cells: 1024,
        color_bytes: 123_456,
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
        ServerMessage::ColorMap {
            offset: 4096,
            data: vec![7; 1000],
        },
        ServerMessage::Refused(Reason::WrongToken),
        ServerMessage::Refused(Reason::Version { server: 1 }),
        ServerMessage::Bye(Reason::Shutdown),
        ServerMessage::Bye(Reason::Unavailable("no vehicle 9".into())),
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
    });
}

#[test]
fn limits() {
    let long = ClientMessage::Hello(Hello {
        token: "x".repeat(129),
        ..hello()
    });
    let mut bytes = Vec::new();
    messages::encode(&long, &mut bytes).expect("encodes");
    assert!(matches!(
        messages::decode::<ClientMessage>(&bytes),
        Err(DecodeError::TooLong {
            what: "join token bytes",
            got: 129,
            limit: 128
        })
    ));
    let many = KeyDatagram {
        states: vec![
            KeyState {
                seq: 1,
                held: 0,
                pressed: 0
            };
            9
        ],
    };
    let mut bytes = Vec::new();
    messages::encode(&many, &mut bytes).expect("encodes");
    assert!(messages::decode::<KeyDatagram>(&bytes).is_err());
    // A count claiming far more than the bytes hold fails without allocating it.
    let mut huge = vec![0u8; 4];
    huge.extend_from_slice(&[0xfc, 0xff, 0xff, 0xff, 0x7f]);
    assert!(messages::decode::<Frame>(&huge).is_err());
    assert!(
        messages::decode::<KeyDatagram>(&[0u8; 300]).is_err(),
        "over the datagram limit"
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
