//! What the browser viewer's tests share: a server with `--web` on loopback and a small
//! page of its own ([`serve_web`], [`PAGE`]), HTTPS requests written by hand over
//! tokio-rustls, pinning the certificate by its SHA-256 ([`https`], [`get`]), and a
//! WebTransport session that speaks the protocol as the page does ([`connect`], [`join`],
//! [`next_frame`]): `web_transport_quinn` as the browser's WebTransport, pinning the hashes
//! that `/webtransport.json` gives, as `serverCertificateHashes` does.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use roam_link::{tls, wire};
use roam_protocol::messages::{ClientMessage, Hello, MAX_MESSAGE, Role, ServerMessage};
use roam_server::net::Options;
use roam_server::net::conn::{RecvStream, SendStream};
use roam_server::net::web::{WebCert, WebOptions};
use roam_server::web::Page;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use web_transport_quinn as wt;

use crate::fixtures::{self, Running};

/// A safety bound on each wait: a regression fails, never hangs.
pub const BOUND: Duration = Duration::from_secs(30);

/// The test page's files: a page, its script (and a "gzip" copy) and its "WebAssembly".
pub const PAGE: &[(&str, &[u8])] = &[
    (
        "index.html",
        b"<!doctype html><title>roam</title><script src=roam_web.js></script>",
    ),
    ("roam_web.js", b"console.log('roam');"),
    ("roam_web.js.gz", b"\x1f\x8b\x08\x00gzipped"),
    ("roam_web_bg.wasm", b"\0asm\x01\0\0\0"),
];

/// [`fixtures::serve`] with the browser viewer on `127.0.0.1:0` too, serving [`PAGE`]
/// with a certificate made for `localhost` and `127.0.0.1`.
pub fn serve_web(
    terrain: Arc<roam_server::Terrain>,
    tune: impl FnOnce(Options) -> Options,
) -> Running {
    let page = Page::from_files(
        PAGE.iter()
            .map(|&(name, bytes)| (name.to_owned(), Bytes::from_static(bytes))),
    );
    fixtures::serve(terrain, |o| {
        tune(Options {
            web: Some(WebOptions {
                listen: "127.0.0.1:0".parse().expect("an address"),
                page: Arc::new(page),
                cert: WebCert::Made {
                    names: vec!["localhost".into(), "127.0.0.1".into()],
                },
            }),
            ..o
        })
    })
}

/// The browser viewer's address and the SHA-256 of its certificate now.
pub fn web_of(r: &Running) -> (SocketAddr, [u8; 32]) {
    (
        r.server.web_addr().expect("serving --web"),
        r.server.web_certificate().expect("serving --web"),
    )
}

/// An HTTP response as read off the wire.
#[derive(Debug)]
pub struct Response {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl Response {
    /// The first header named `name` (any case).
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }
}

/// A TLS connection to `addr` that accepts only the certificate with SHA-256 `pin`.
pub async fn tls_connect(
    addr: SocketAddr,
    pin: [u8; 32],
) -> std::io::Result<tokio_rustls::client::TlsStream<tokio::net::TcpStream>> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(std::io::Error::other)?
        .dangerous()
        .with_custom_certificate_verifier(tls::pinned_verifier(pin))
        .with_no_client_auth();
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    let tcp = tokio::net::TcpStream::connect(addr).await?;
    let name = rustls::pki_types::ServerName::IpAddress(addr.ip().into());
    tokio_rustls::TlsConnector::from(Arc::new(config))
        .connect(name, tcp)
        .await
}

/// Sends `request` (whole, as bytes) over HTTPS to `addr` and reads the answer until the
/// server closes the connection (at most 1 MiB).
pub async fn https(addr: SocketAddr, pin: [u8; 32], request: &[u8]) -> std::io::Result<Response> {
    let mut tls = tls_connect(addr, pin).await?;
    tls.write_all(request).await?;
    tls.flush().await?;
    let mut raw = Vec::new();
    // A TLS stream the server drops without close_notify ends in an error, after the
    // bytes it sent: what was read counts.
    let _ = (&mut tls).take(1 << 20).read_to_end(&mut raw).await;
    parse(&raw).ok_or_else(|| {
        std::io::Error::other(format!(
            "not an HTTP response: {:?}",
            String::from_utf8_lossy(&raw[..raw.len().min(200)])
        ))
    })
}

/// `GET path` with `headers` (`Name: value` lines), the connection closed after.
pub async fn get(addr: SocketAddr, pin: [u8; 32], path: &str, headers: &[&str]) -> Response {
    let mut request = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for h in headers {
        request.push_str(h);
        request.push_str("\r\n");
    }
    request.push_str("\r\n");
    tokio::time::timeout(BOUND, https(addr, pin, request.as_bytes()))
        .await
        .expect("an answer in time")
        .expect("an HTTP answer")
}

fn parse(raw: &[u8]) -> Option<Response> {
    let end = raw.windows(4).position(|w| w == b"\r\n\r\n")?;
    let head = std::str::from_utf8(&raw[..end]).ok()?;
    let mut lines = head.split("\r\n");
    let status = lines.next()?.split(' ').nth(1)?.parse().ok()?;
    let headers = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_owned(), v.trim().to_owned()))
        .collect();
    Some(Response {
        status,
        headers,
        body: raw[end + 4..].to_vec(),
    })
}

/// What `/webtransport.json` says: the session's path, the UDP port, the certificate
/// hashes.
pub fn transport_of(body: &[u8]) -> (String, u16, Vec<[u8; 32]>) {
    let v: serde_json::Value = serde_json::from_slice(body).expect("JSON");
    let path = v["path"].as_str().expect("a path").to_owned();
    let port = v["port"].as_u64().expect("a port") as u16;
    let hashes = v["certificate_hashes"]
        .as_array()
        .expect("a list")
        .iter()
        .map(|h| tls::parse_fingerprint(h.as_str().expect("hex")).expect("a SHA-256"))
        .collect();
    (path, port, hashes)
}

/// A WebTransport session to `https://ADDR{path}`, accepting only certificates with one
/// of `hashes` (as a browser's `serverCertificateHashes`).
pub async fn connect(
    addr: SocketAddr,
    hashes: &[[u8; 32]],
    path: &str,
) -> Result<wt::Session, wt::ClientError> {
    // The client's own socket on the server's family (the library's default binds `[::]`,
    // which a machine without IPv6 lacks).
    let bind: SocketAddr = if addr.is_ipv4() {
        "0.0.0.0:0".parse().expect("an address")
    } else {
        "[::]:0".parse().expect("an address")
    };
    let endpoint = quinn::Endpoint::client(bind).expect("a UDP socket");
    let pin = *hashes.first().expect("a certificate hash");
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut tls = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])
        .expect("TLS 1.3")
        .dangerous()
        .with_custom_certificate_verifier(tls::pinned_verifier(pin))
        .with_no_client_auth();
    tls.alpn_protocols = vec![wt::ALPN.as_bytes().to_vec()];
    let quic = quinn::crypto::rustls::QuicClientConfig::try_from(tls).expect("TLS 1.3");
    let config = quinn::ClientConfig::new(Arc::new(quic));
    let url = url::Url::parse(&format!("https://{addr}{path}")).expect("a URL");
    wt::Client::new(endpoint, config).connect(url).await
}

/// A driver's (or spectator's) hello with `token`.
pub fn hello(token: &str, role: Role) -> Hello {
    fixtures::hello(role, token, [640, 360], 2_000, 30)
}

/// Opens the control stream as the page does, says `hello` and reads the answer (a
/// welcome or a refusal).
pub async fn join(session: &wt::Session, hello: Hello) -> (SendStream, RecvStream, ServerMessage) {
    let (send, recv) = session.open_bi().await.expect("a control stream");
    let (mut send, mut recv) = (SendStream::Web(send), RecvStream::Web(recv));
    send.write_msg(&ClientMessage::Hello(hello))
        .await
        .expect("the hello goes");
    let answer = read(&mut recv).await;
    (send, recv, answer)
}

/// The next control message.
pub async fn read(recv: &mut RecvStream) -> ServerMessage {
    tokio::time::timeout(BOUND, wire::read::<ServerMessage>(recv, MAX_MESSAGE))
        .await
        .expect("a control message in time")
        .expect("a control message")
}

/// The next frame's bytes, from a datagram or a stream of its own read to its end (a
/// stream the server abandoned for a newer frame is passed over).
pub async fn next_frame(session: &wt::Session) -> Vec<u8> {
    tokio::time::timeout(BOUND, async {
        loop {
            tokio::select! {
                d = session.read_datagram() => return d.expect("a frame datagram").to_vec(),
                s = session.accept_uni() => {
                    let mut s = s.expect("a frame stream");
                    if let Ok(bytes) = s.read_to_end(MAX_MESSAGE).await {
                        return bytes;
                    }
                }
            }
        }
    })
    .await
    .expect("a frame in time")
}
