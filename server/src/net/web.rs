//! The browser viewer's shell (`serve --web ADDR`): the page over HTTPS on TCP `ADDR`, and
//! WebTransport (HTTP/3) on UDP `ADDR` (the same port number), both presenting the one
//! certificate in [`CertStore`], which a task renews when due. The page's answers are
//! [`crate::web::Site`]'s; a WebTransport connection goes through the same admission and
//! handshake as a native one ([`super::handshake::arrive`] with [`Via::Web`]).
//!
//! Decisions:
//!
//! - **Bounded HTTP.** HTTP/1.1 only (hyper), GET and HEAD only; at most
//!   [`MAX_HTTP_CONNECTIONS`] connections at once (past it a new one is closed at once), a
//!   TLS handshake within [`TLS_TIMEOUT`], each request head within [`HEAD_TIMEOUT`] and at
//!   most [`MAX_HEAD`] bytes and [`MAX_HEADERS`] headers (431 past it), a connection at most
//!   [`CONNECTION_LIFETIME`] in all (a client that reads slowly or not at all is cut).
//!   Requests are logged at debug level only: a page load is a handful of them.
//! - **One port number.** The page finds WebTransport on its own origin's port. With port
//!   0 the UDP port is taken first and the TCP port of the same number after, a few tries
//!   before giving up.
//! - **Renewal by the clock.** The task sleeps until [`CertStore::next_check`] (an hour at
//!   most) and calls [`CertStore::renew`] with the wall clock; TLS takes the new
//!   certificate at the next handshake.

use std::convert::Infallible;
use std::net::{SocketAddr, TcpListener, UdpSocket};
use std::sync::Arc;
use std::time::Duration;

use http_body_util::Full;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use tokio::task::JoinHandle;

use super::conn::Via;
use super::serve_error::ServeError;
use super::shared::Shared;
use crate::web::cert::CertStore;
use crate::web::{Page, Site};

/// HTTPS connections served at once.
pub const MAX_HTTP_CONNECTIONS: usize = 64;
/// A TLS handshake on the HTTPS port must be over within this.
pub const TLS_TIMEOUT: Duration = Duration::from_secs(10);
/// Each request head must arrive within this (an idle kept-alive connection too).
pub const HEAD_TIMEOUT: Duration = Duration::from_secs(10);
/// A request head's bytes at most (its line and headers).
pub const MAX_HEAD: usize = 16 << 10;
/// A request's headers at most.
pub const MAX_HEADERS: usize = 64;
/// An HTTPS connection lasts at most this long, whatever it does.
pub const CONNECTION_LIFETIME: Duration = Duration::from_secs(120);
/// WebTransport: HTTP/3's control and QPACK streams and a few more from the browser.
const WEB_UNI_STREAMS: u32 = 8;
/// WebTransport: the `CONNECT` stream and the viewer's control stream.
const WEB_BIDI_STREAMS: u32 = 2;

/// How to serve the browser viewer.
pub struct WebOptions {
    /// TCP (HTTPS) and UDP (WebTransport) address; port 0 takes a free one for both.
    pub listen: SocketAddr,
    /// The page's files ([`Page::embedded`] in the binary).
    pub page: Arc<Page>,
    pub cert: WebCert,
}

/// The browser viewer's certificate.
pub enum WebCert {
    /// Made here for these names ([`crate::web::cert::subject_names`]), renewed when due.
    Made { names: Vec<String> },
    /// A certificate chain (leaf first) that browsers trust, and its key.
    Given {
        chain: Vec<CertificateDer<'static>>,
        key: PrivateKeyDer<'static>,
    },
}

/// The browser viewer being served.
pub(super) struct Running {
    /// The HTTPS address (TCP); WebTransport listens on the same one over UDP.
    pub addr: SocketAddr,
    pub endpoint: quinn::Endpoint,
    pub certs: Arc<CertStore>,
    tasks: Vec<JoinHandle<()>>,
}

impl Running {
    /// Stops taking HTTPS connections and renewing (open HTTPS connections are dropped);
    /// the endpoint is closed with the native one.
    pub(super) fn stop(&mut self) {
        for t in self.tasks.drain(..) {
            t.abort();
        }
    }
}

/// The browser viewer's sockets and configurations, ready to serve: everything that can
/// fail, before the server starts anything.
pub(super) struct Bound {
    addr: SocketAddr,
    endpoint: quinn::Endpoint,
    tcp: tokio::net::TcpListener,
    acceptor: tokio_rustls::TlsAcceptor,
    site: Arc<Site>,
}

/// Checks the page, makes or checks the certificate, and binds both sockets.
pub(super) fn bind(options: WebOptions) -> Result<Bound, ServeError> {
    if !options.page.is_built() {
        return Err(ServeError::NoPage);
    }
    let certs = Arc::new(match options.cert {
        WebCert::Made { names } => CertStore::made(names, super::world_loop::unix_seconds())?,
        WebCert::Given { chain, key } => CertStore::given(chain, key)?,
    });
    let (udp, tcp) = bind_pair(options.listen)?;
    let addr = tcp.local_addr().map_err(|error| ServeError::Listen {
        addr: options.listen,
        error,
    })?;
    let endpoint = quinn::Endpoint::new(
        quinn::EndpointConfig::default(),
        Some(quic_config(certs.clone())?),
        udp,
        Arc::new(quinn::TokioRuntime),
    )
    .map_err(|error| ServeError::Listen { addr, error })?;
    tcp.set_nonblocking(true)
        .map_err(|error| ServeError::Listen { addr, error })?;
    let tcp = tokio::net::TcpListener::from_std(tcp)
        .map_err(|error| ServeError::Listen { addr, error })?;
    let acceptor = tokio_rustls::TlsAcceptor::from(Arc::new(https_config(certs.clone())?));
    let site = Arc::new(Site {
        page: options.page,
        port: addr.port(),
        certs,
    });
    Ok(Bound {
        addr,
        endpoint,
        tcp,
        acceptor,
        site,
    })
}

impl Bound {
    /// Serves: the HTTPS server, the WebTransport endpoint and the renewal task.
    pub(super) fn start(self, shared: Arc<Shared>) -> Running {
        let certs = self.site.certs.clone();
        let tasks = vec![
            tokio::spawn(accept_web(self.endpoint.clone(), shared)),
            tokio::spawn(serve_https(self.tcp, self.acceptor, self.site)),
            tokio::spawn(renew(certs.clone())),
        ];
        Running {
            addr: self.addr,
            endpoint: self.endpoint,
            certs,
            tasks,
        }
    }
}

/// A UDP socket and a TCP listener on the same port of `listen`'s address.
fn bind_pair(listen: SocketAddr) -> Result<(UdpSocket, TcpListener), ServeError> {
    let failed = |error| ServeError::Listen {
        addr: listen,
        error,
    };
    if listen.port() != 0 {
        let udp = UdpSocket::bind(listen).map_err(failed)?;
        let tcp = TcpListener::bind(listen).map_err(failed)?;
        return Ok((udp, tcp));
    }
    let mut last = None;
    for _ in 0..16 {
        let udp = UdpSocket::bind(listen).map_err(failed)?;
        let port = udp.local_addr().map_err(failed)?.port();
        match TcpListener::bind(SocketAddr::new(listen.ip(), port)) {
            Ok(tcp) => return Ok((udp, tcp)),
            Err(e) => last = Some(e),
        }
    }
    Err(failed(last.unwrap_or_else(|| {
        std::io::Error::new(std::io::ErrorKind::AddrInUse, "no free port pair")
    })))
}

fn tls_builder()
-> Result<rustls::ConfigBuilder<rustls::ServerConfig, rustls::WantsVerifier>, ServeError> {
    rustls::ServerConfig::builder_with_provider(Arc::new(rustls::crypto::ring::default_provider()))
        .with_safe_default_protocol_versions()
        .map_err(|e| ServeError::WebTls(e.to_string()))
}

/// WebTransport's QUIC configuration: ALPN `h3`, the native transport settings with the
/// streams HTTP/3 needs.
fn quic_config(certs: Arc<CertStore>) -> Result<quinn::ServerConfig, ServeError> {
    let mut tls = tls_builder()?
        .with_no_client_auth()
        .with_cert_resolver(certs);
    tls.alpn_protocols = vec![web_transport_quinn::ALPN.as_bytes().to_vec()];
    let quic = quinn::crypto::rustls::QuicServerConfig::try_from(tls)
        .map_err(|e| ServeError::WebTls(e.to_string()))?;
    let mut config = quinn::ServerConfig::with_crypto(Arc::new(quic));
    let mut t = roam_link::tls::server_transport();
    t.max_concurrent_uni_streams(WEB_UNI_STREAMS.into());
    t.max_concurrent_bidi_streams(WEB_BIDI_STREAMS.into());
    config.transport_config(Arc::new(t));
    Ok(config)
}

/// The page's TLS configuration: HTTP/1.1.
fn https_config(certs: Arc<CertStore>) -> Result<rustls::ServerConfig, ServeError> {
    let mut tls = tls_builder()?
        .with_no_client_auth()
        .with_cert_resolver(certs);
    tls.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(tls)
}

async fn accept_web(endpoint: quinn::Endpoint, shared: Arc<Shared>) {
    while let Some(incoming) = endpoint.accept().await {
        super::handshake::arrive(incoming, &shared, Via::Web);
    }
}

/// Renews the certificate when due, for as long as the server runs.
async fn renew(certs: Arc<CertStore>) {
    loop {
        let Some(wait) = certs.next_check(super::world_loop::unix_seconds()) else {
            return; // a given certificate
        };
        tokio::time::sleep(Duration::from_secs(wait)).await;
        match certs.renew(super::world_loop::unix_seconds()) {
            Ok(Some(r)) => tracing::info!(
                old = roam_link::tls::hex(&r.old),
                new = roam_link::tls::hex(&r.new),
                "the browser viewer's certificate renewed"
            ),
            Ok(None) => {}
            Err(e) => tracing::error!("renewing the browser viewer's certificate: {e}"),
        }
    }
}

/// Takes HTTPS connections, each on a task of its own, at most
/// [`MAX_HTTP_CONNECTIONS`] at once; their tasks end with this one.
async fn serve_https(
    listener: tokio::net::TcpListener,
    acceptor: tokio_rustls::TlsAcceptor,
    site: Arc<Site>,
) {
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_HTTP_CONNECTIONS));
    let mut connections = tokio::task::JoinSet::new();
    loop {
        let accepted = tokio::select! {
            a = listener.accept() => a,
            Some(_) = connections.join_next() => continue,
        };
        let (tcp, peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                // Out of file descriptors, say: wait a little rather than spin.
                tracing::debug!("accepting an HTTPS connection: {e}");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Ok(slot) = slots.clone().try_acquire_owned() else {
            tracing::debug!(%peer, "HTTPS connection closed: {MAX_HTTP_CONNECTIONS} open already");
            continue;
        };
        let _ = tcp.set_nodelay(true);
        let (acceptor, site) = (acceptor.clone(), site.clone());
        connections.spawn(async move {
            let _slot = slot;
            let served = serve_connection(tcp, peer, acceptor, site);
            if tokio::time::timeout(CONNECTION_LIFETIME, served)
                .await
                .is_err()
            {
                tracing::debug!(%peer, "HTTPS connection cut after {CONNECTION_LIFETIME:?}");
            }
        });
    }
}

/// One HTTPS connection: TLS, then HTTP/1.1 requests answered by `site`.
async fn serve_connection(
    tcp: tokio::net::TcpStream,
    peer: SocketAddr,
    acceptor: tokio_rustls::TlsAcceptor,
    site: Arc<Site>,
) {
    let tls = match tokio::time::timeout(TLS_TIMEOUT, acceptor.accept(tcp)).await {
        Ok(Ok(tls)) => tls,
        Ok(Err(e)) => return tracing::debug!(%peer, "HTTPS handshake failed: {e}"),
        Err(_) => return tracing::debug!(%peer, "HTTPS handshake timed out"),
    };
    let service = hyper::service::service_fn(move |req: http::Request<hyper::body::Incoming>| {
        let r = site.respond(req.method(), req.uri().path(), req.headers());
        tracing::debug!(%peer, method = %req.method(), path = req.uri().path(), status = r.status().as_u16(), "HTTPS");
        std::future::ready(Ok::<_, Infallible>(r.map(Full::new)))
    });
    let served = hyper::server::conn::http1::Builder::new()
        .timer(hyper_util::rt::TokioTimer::new())
        .header_read_timeout(HEAD_TIMEOUT)
        .max_header_size(MAX_HEAD)
        .max_headers(MAX_HEADERS)
        .max_buf_size(4 * MAX_HEAD)
        .serve_connection(hyper_util::rt::TokioIo::new(tls), service)
        .await;
    if let Err(e) = served {
        tracing::debug!(%peer, "HTTPS connection ended: {e}");
    }
}
