//! The browser viewer's server side, end to end against a real server with `--web` on
//! `127.0.0.1:0` (a small page of the test's own): the page and `/webtransport.json` over
//! real HTTPS, pinning the certificate by its hash; a WebTransport session at the path and
//! port the JSON gives, pinned by the hashes it gives, that says hello on its control
//! stream as the page does and gets the welcome, the coarsest colour tile and frames the
//! viewer's own core ([`ClientCore`]) decodes; a wrong token refused with its reason and
//! close code; another path refused with 404; a native and a web viewer in the same world;
//! hostile HTTP (a head too large, other methods, too many connections) answered within
//! bounds.

use std::time::Instant;

use roam_client::core::{ClientCore, Taken};
use roam_protocol::messages::{self, ClientMessage, Frame, Reason, Role, ServerMessage, close};
use roam_tests::fixtures::{Running, flat};
use roam_tests::web::{self, BOUND, PAGE};
use tokio::io::AsyncReadExt;
use web_transport_quinn as wt;

use crate::turn;

fn page_file(name: &str) -> &'static [u8] {
    PAGE.iter()
        .find(|(n, _)| *n == name)
        .map(|(_, b)| *b)
        .expect("a test page file")
}

/// The page's WebTransport: where `/webtransport.json` says, pinned as it says.
async fn session(r: &Running) -> wt::Session {
    let (addr, pin) = web::web_of(r);
    let json = web::get(addr, pin, "/webtransport.json", &[]).await;
    let (path, port, hashes) = web::transport_of(&json.body);
    let at = std::net::SocketAddr::new(addr.ip(), port);
    tokio::time::timeout(BOUND, web::connect(at, &hashes, &path))
        .await
        .expect("a session in time")
        .expect("a session")
}

/// Waits until the world holds `n` vehicles.
async fn vehicles(r: &Running, n: usize) {
    let mut watch = r.server.watch();
    tokio::time::timeout(BOUND, watch.wait_for(|s| s.vehicles.len() == n))
        .await
        .expect("the world in time")
        .expect("the server runs");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_and_its_transport_come_over_https_and_a_web_viewer_decodes_frames() {
    let _turn = turn().await;
    let r = web::serve_web(flat(), |o| o);
    let (addr, pin) = web::web_of(&r);
    // The page, by `/` and by name, with its types.
    for (path, name, ty) in [
        ("/", "index.html", "text/html; charset=utf-8"),
        ("/index.html", "index.html", "text/html; charset=utf-8"),
        ("/roam_web_bg.wasm", "roam_web_bg.wasm", "application/wasm"),
        ("/roam_web.js", "roam_web.js", "text/javascript"),
    ] {
        let got = web::get(addr, pin, path, &[]).await;
        assert_eq!(got.status, 200, "{path}");
        assert_eq!(got.body, page_file(name), "{path}");
        assert_eq!(got.header("content-type"), Some(ty), "{path}");
        assert_eq!(got.header("cache-control"), Some("no-cache"), "{path}");
    }
    let gz = web::get(addr, pin, "/roam_web.js", &["Accept-Encoding: gzip, br"]).await;
    assert_eq!(gz.body, page_file("roam_web.js.gz"));
    assert_eq!(gz.header("content-encoding"), Some("gzip"));
    // Where WebTransport is: this port, the path, and the certificate pinned above.
    let json = web::get(addr, pin, "/webtransport.json", &[]).await;
    assert_eq!(json.status, 200);
    assert_eq!(json.header("cache-control"), Some("no-store"));
    assert_eq!(json.header("content-type"), Some("application/json"));
    let (path, port, hashes) = web::transport_of(&json.body);
    assert_eq!((path.as_str(), port), ("/roam", addr.port()));
    assert_eq!(hashes, vec![pin]);

    // A driver over WebTransport: the welcome, the coarsest tile, then frames.
    let session = session(&r).await;
    let (mut send, mut recv, answer) =
        web::join(&session, web::hello(&r.token, Role::Driver)).await;
    let ServerMessage::Welcome(welcome) = answer else {
        panic!("expected the welcome, got {answer:?}");
    };
    assert!(welcome.ticket.is_some(), "a driver's ticket");
    let ServerMessage::ColorTile { level, .. } = web::read(&mut recv).await else {
        panic!("expected the coarsest colour tile");
    };
    assert_eq!(level, welcome.color.levels - 1);
    let mut core = ClientCore::new(&welcome, 2_000).expect("the welcome's grid");
    let mut decoded = 0;
    let mut triangles = 0;
    for _ in 0..200 {
        let bytes = web::next_frame(&session).await;
        core.offer(&bytes, Instant::now());
        match core.take(true).expect("frame numbers a server sends") {
            Taken::Frame(f) => {
                decoded += 1;
                triangles = triangles.max(f.triangles);
                assert_eq!(f.vehicles.len(), 1, "this driver's vehicle");
            }
            Taken::Nothing => {}
            Taken::Dropped(why) => panic!("a frame that does not decode: {why}"),
        }
        // Acknowledgements back on the control stream, as the page sends them.
        while let Some(msg) = core.poll_control() {
            send.write_msg(&msg).await.expect("the control stream");
        }
        if decoded >= 5 {
            break;
        }
    }
    assert!(decoded >= 5, "{decoded} frames decoded");
    assert!(triangles > 2, "a mesh ({triangles} triangles)");
    vehicles(&r, 1).await;
    // A goodbye frees the vehicle at once (no hold).
    send.write_msg(&ClientMessage::Bye(Reason::Quit))
        .await
        .expect("the goodbye goes");
    vehicles(&r, 0).await;
    session.close(close::BYE, b"bye");
    let counts = r.server.counts();
    assert_eq!(counts.joins, 1);
    r.server.shutdown().await.expect("stops");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_token_and_a_wrong_path_are_refused() {
    let _turn = turn().await;
    let r = web::serve_web(flat(), |o| o);
    let session = session(&r).await;
    let (_send, _recv, answer) =
        web::join(&session, web::hello("not-the-token-at-all", Role::Driver)).await;
    assert_eq!(answer, ServerMessage::Refused(Reason::WrongToken));
    // The session ends with the refusal's close code, as the page sees it.
    let ended = tokio::time::timeout(BOUND, session.closed())
        .await
        .expect("closed in time");
    match ended {
        wt::SessionError::WebTransportError(wt::WebTransportError::Closed(code, _)) => {
            assert_eq!(code, close::REFUSED);
        }
        other => panic!("expected a close with a code, got {other}"),
    }
    // Another path than /roam: 404, and no session.
    let (addr, _) = web::web_of(&r);
    let hashes = vec![r.server.web_certificate().expect("--web")];
    let refused = tokio::time::timeout(BOUND, web::connect(addr, &hashes, "/other"))
        .await
        .expect("an answer in time");
    match refused {
        Err(wt::ClientError::HttpError(wt::ConnectError::ProtoError(
            wt::proto::ConnectError::WrongStatus(Some(s)),
        ))) => assert_eq!(s.as_u16(), 404),
        Err(other) => panic!("expected 404, got {other}"),
        Ok(_) => panic!("expected 404, got a session"),
    }
    // A certificate other than the one served is refused by the client (the pinning is
    // real), and nothing joined.
    let wrong = tokio::time::timeout(BOUND, web::connect(addr, &[[7; 32]], "/roam"))
        .await
        .expect("an answer in time");
    assert!(wrong.is_err(), "a session with the wrong certificate hash");
    assert_eq!(r.server.counts().joins, 0);
    r.server.shutdown().await.expect("stops");
}

/// A frame's vehicles, from a native connection.
async fn native_frame(conn: &quinn::Connection) -> Frame {
    let bytes = tokio::time::timeout(BOUND, async {
        loop {
            tokio::select! {
                d = conn.read_datagram() => return d.expect("a frame datagram").to_vec(),
                s = conn.accept_uni() => {
                    let mut s = s.expect("a frame stream");
                    if let Ok(bytes) = s.read_to_end(messages::MAX_MESSAGE).await {
                        return bytes;
                    }
                }
            }
        }
    })
    .await
    .expect("a frame in time");
    messages::decode::<Frame>(&bytes).expect("a frame")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_native_and_a_web_viewer_drive_in_the_same_world() {
    let _turn = turn().await;
    let r = web::serve_web(flat(), |o| o);
    let (_endpoint, conn) = roam_client::quic::connect(r.server.addr, r.fingerprint)
        .await
        .expect("connects natively");
    let native = roam_client::quic::hello(
        conn.clone(),
        web::hello(&r.token, Role::Driver),
        roam_client::color_cache::Keep::Masks,
    )
    .await
    .expect("joins natively");
    let session = session(&r).await;
    let (_send, _recv, answer) = web::join(&session, web::hello(&r.token, Role::Driver)).await;
    let ServerMessage::Welcome(welcome) = answer else {
        panic!("expected the welcome, got {answer:?}");
    };
    assert_ne!(welcome.vehicle, native.welcome.vehicle, "a vehicle each");
    vehicles(&r, 2).await;
    // Each sees both vehicles in its frames.
    let mut seen = (false, false);
    for _ in 0..300 {
        if !seen.0 {
            seen.0 = native_frame(&conn).await.vehicles.len() == 2;
        }
        if !seen.1 {
            let bytes = web::next_frame(&session).await;
            seen.1 = messages::decode::<Frame>(&bytes)
                .expect("a frame")
                .vehicles
                .len()
                == 2;
        }
        if seen == (true, true) {
            break;
        }
    }
    assert_eq!(seen, (true, true), "(native, web) saw both vehicles");
    assert_eq!(r.server.counts().joins, 2);
    assert_eq!(r.server.load().1, 2, "two viewers seated, one gate");
    r.server.shutdown().await.expect("stops");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_http_gets_clear_answers_within_bounds() {
    let _turn = turn().await;
    let r = web::serve_web(flat(), |o| o);
    let (addr, pin) = web::web_of(&r);
    let get = |path: &'static str| web::get(addr, pin, path, &[]);
    assert_eq!(get("/nothing-here").await.status, 404);
    assert_eq!(get("/../../etc/passwd").await.status, 404);
    let post = b"POST / HTTP/1.1\r\nHost: x\r\nContent-Length: 3\r\nConnection: close\r\n\r\nabc";
    let answer = web::https(addr, pin, post).await.expect("an answer");
    assert_eq!(answer.status, 405);
    assert_eq!(answer.header("allow"), Some("GET, HEAD"));
    // A request head past the limit: 431, whatever it is made of.
    let huge = format!(
        "GET / HTTP/1.1\r\nHost: x\r\nX-Junk: {}\r\n\r\n",
        "a".repeat(roam_server::net::web::MAX_HEAD)
    );
    let answer = tokio::time::timeout(BOUND, web::https(addr, pin, huge.as_bytes()))
        .await
        .expect("an answer in time")
        .expect("an answer");
    assert_eq!(answer.status, 431);
    let many: String = (0..roam_server::net::web::MAX_HEADERS + 1)
        .map(|i| format!("X-{i}: 1\r\n"))
        .collect();
    let answer = web::https(
        addr,
        pin,
        format!("GET / HTTP/1.1\r\nHost: x\r\n{many}\r\n").as_bytes(),
    )
    .await
    .expect("an answer");
    assert_eq!(answer.status, 431);
    // Not HTTP at all: an error answer, and the page still serves.
    let answer = web::https(addr, pin, b"\x00\x01garbage\r\n\r\n")
        .await
        .expect("an answer");
    assert_eq!(answer.status, 400);
    // At most MAX_HTTP_CONNECTIONS at once: the next is closed at once, unanswered.
    let mut held = Vec::new();
    for _ in 0..roam_server::net::web::MAX_HTTP_CONNECTIONS {
        held.push(
            tokio::net::TcpStream::connect(addr)
                .await
                .expect("connects"),
        );
    }
    // The server takes connections in the order they came: these hold every slot.
    let mut extra = tokio::net::TcpStream::connect(addr)
        .await
        .expect("connects");
    let mut buf = [0u8; 16];
    let read = tokio::time::timeout(BOUND, extra.read(&mut buf))
        .await
        .expect("closed in time");
    assert!(matches!(read, Ok(0) | Err(_)), "{read:?}");
    drop(held);
    // Served again once the server has seen them go (it may take a few tries).
    let again = tokio::time::timeout(BOUND, async {
        loop {
            let request = format!("GET / HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
            if let Ok(answer) = web::https(addr, pin, request.as_bytes()).await {
                return answer;
            }
            tokio::task::yield_now().await;
        }
    })
    .await
    .expect("served again in time");
    assert_eq!(again.status, 200);
    r.server.shutdown().await.expect("stops");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_web_driver_closing_without_a_goodbye_is_held_and_with_one_freed() {
    let _turn = turn().await;
    let r = web::serve_web(flat(), |o| o);
    let mut watch = r.server.watch();
    for (code, held) in [(0, true), (close::BYE, false)] {
        let session = session(&r).await;
        let (_send, _recv, answer) = web::join(&session, web::hello(&r.token, Role::Driver)).await;
        let ServerMessage::Welcome(welcome) = answer else {
            panic!("expected the welcome, got {answer:?}");
        };
        tokio::time::timeout(
            BOUND,
            watch.wait_for(|s| s.vehicles.iter().any(|v| v.id == welcome.vehicle)),
        )
        .await
        .expect("the vehicle in time")
        .expect("the server runs");
        // A tab closed (any code but the goodbye's) holds the vehicle for its driver to
        // come back to; the goodbye's code frees it.
        session.close(code, b"closing");
        let v = welcome.vehicle;
        let snap = tokio::time::timeout(
            BOUND,
            watch.wait_for(|s| s.held.contains(&v) || !s.vehicles.iter().any(|x| x.id == v)),
        )
        .await
        .expect("the end seen in time")
        .expect("the server runs")
        .clone();
        assert_eq!(snap.held.contains(&v), held, "closed with code {code}");
    }
    r.server.shutdown().await.expect("stops");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_without_the_page_refuses_web_naming_the_command_that_builds_it() {
    use roam_server::net::web::{WebCert, WebOptions};
    use roam_server::net::{Options, Server};
    let terrain = flat();
    let pyramid = roam_tests::fixtures::pyramid(&terrain, roam_protocol::tiles::DEFAULT_TILE);
    let vt =
        roam_server::terrain::variance::VarianceTree::build(&terrain.heights, 1, &mut |_, _| {});
    let identity = roam_link::tls::generate().expect("a certificate");
    let mut options = Options::new("127.0.0.1:0".parse().expect("valid"), "t".repeat(16));
    options.web = Some(WebOptions {
        listen: "127.0.0.1:0".parse().expect("valid"),
        page: std::sync::Arc::new(roam_server::web::Page::from_files([])),
        cert: WebCert::Made {
            names: vec!["localhost".into()],
        },
    });
    let Err(e) = Server::start(
        terrain,
        std::sync::Arc::new(vt),
        pyramid,
        &identity,
        options,
    ) else {
        panic!("a server without a page started with --web");
    };
    assert!(e.to_string().contains("scripts/build-web"), "{e}");
}
