//! [`ServeError`]: why a server could not start or stop cleanly.

use std::net::SocketAddr;

use roam_link::tls;

/// Why the server could not start or stop cleanly.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("listening on {addr}: {error}")]
    Listen {
        addr: SocketAddr,
        error: std::io::Error,
    },
    #[error(transparent)]
    Tls(#[from] tls::TlsError),
    #[error("starting the world: {0}")]
    World(std::io::Error),
    #[error("the world thread panicked")]
    WorldPanicked,
    #[error("the colour pyramid: {0}")]
    ColorLayout(#[from] roam_protocol::tiles::LayoutError),
    #[error("the colour pyramid is of a {got}² map, the terrain's colour map is {expected}²")]
    ColorPyramid { got: u32, expected: u32 },
    #[error("the normal tiles: {0}")]
    Normals(#[from] crate::terrain::normal_pyramid::NormalError),
    #[error("the normal tiles are laid out as {got:?}, the colour as {expected:?}")]
    NormalLayout {
        got: roam_protocol::ColorLayout,
        expected: roam_protocol::ColorLayout,
    },
    #[error(
        "a grid of {side}² samples: this server serves at most {max}² (2^{levels} + 1), \
         the protocol's largest colour map; import it again with a smaller side"
    )]
    TooLarge { side: u32, max: u32, levels: u32 },
    #[error("{}", crate::web::NOT_BUILT)]
    NoPage,
    #[error("the browser viewer's certificate: {0}")]
    WebCert(#[from] crate::web::cert::CertError),
    #[error("the browser viewer's TLS: {0}")]
    WebTls(String),
}
