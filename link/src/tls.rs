//! Certificates: a self-signed one made on first run and kept in the state directory, its
//! SHA-256 fingerprint (what viewers pin), and the QUIC configurations of both ends.

use std::path::Path;
use std::sync::Arc;

use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::CryptoProvider;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer, ServerName, UnixTime};
use rustls::{DigitallySignedStruct, SignatureScheme};

/// The ALPN protocol name both ends insist on.
pub const ALPN: &[u8] = b"roam/1";

/// Why the certificate or a QUIC configuration could not be made.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    #[error("{path}: {error}")]
    Io { path: String, error: std::io::Error },
    #[error("making a certificate: {0}")]
    Generate(#[from] rcgen::Error),
    #[error("TLS: {0}")]
    Rustls(#[from] rustls::Error),
    #[error("QUIC: {0}")]
    Quic(String),
    #[error("fingerprint {0:?}: expected 64 hex digits (a SHA-256)")]
    Fingerprint(String),
}

/// A certificate and its key.
pub struct Identity {
    pub cert: CertificateDer<'static>,
    key: PrivatePkcs8KeyDer<'static>,
}

impl Identity {
    /// The SHA-256 of the certificate, in hex: what viewers pass as `--fingerprint`.
    pub fn fingerprint(&self) -> String {
        hex(&sha256(&self.cert))
    }
}

fn sha256(bytes: &[u8]) -> [u8; 32] {
    let d = ring::digest::digest(&ring::digest::SHA256, bytes);
    let mut out = [0; 32];
    out.copy_from_slice(d.as_ref());
    out
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Parses a fingerprint: 64 hex digits (colons and case are ignored).
pub fn parse_fingerprint(text: &str) -> Result<[u8; 32], TlsError> {
    let digits: String = text.chars().filter(|&c| c != ':').collect();
    let bad = || TlsError::Fingerprint(text.to_owned());
    if digits.len() != 64 {
        return Err(bad());
    }
    let mut out = [0u8; 32];
    for (i, b) in out.iter_mut().enumerate() {
        *b = u8::from_str_radix(&digits[2 * i..2 * i + 2], 16).map_err(|_| bad())?;
    }
    Ok(out)
}

/// The identity in `dir` (`cert.der`, `key.der`), made and saved there on first use.
pub fn load_or_create(dir: &Path) -> Result<Identity, TlsError> {
    let io = |path: &Path| {
        let path = path.display().to_string();
        move |error| TlsError::Io { path, error }
    };
    let (cert_path, key_path) = (dir.join("cert.der"), dir.join("key.der"));
    if cert_path.exists() && key_path.exists() {
        let cert = std::fs::read(&cert_path).map_err(io(&cert_path))?;
        let key = std::fs::read(&key_path).map_err(io(&key_path))?;
        return Ok(Identity {
            cert: CertificateDer::from(cert),
            key: PrivatePkcs8KeyDer::from(key),
        });
    }
    let id = generate()?;
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    std::fs::write(&cert_path, id.cert.as_ref()).map_err(io(&cert_path))?;
    std::fs::write(&key_path, id.key.secret_pkcs8_der()).map_err(io(&key_path))?;
    Ok(id)
}

/// A fresh self-signed identity (for tests and in-process servers).
pub fn generate() -> Result<Identity, TlsError> {
    let ck = rcgen::generate_simple_self_signed(vec!["roam".into(), "localhost".into()])?;
    Ok(Identity {
        cert: ck.cert.der().clone(),
        key: PrivatePkcs8KeyDer::from(ck.signing_key.serialize_der()),
    })
}

fn provider() -> Arc<CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// Cubic with a floor under its window ([`crate::congestion`]): both ends, so neither the
/// frames nor the keys and acknowledgements starve on a link that loses packets at random.
fn floored_congestion(t: &mut quinn::TransportConfig) {
    t.congestion_controller_factory(Arc::new(crate::congestion::FlooredCubic {
        floor: crate::congestion::MIN_WINDOW,
    }));
}

fn transport(keep_alive: bool) -> Arc<quinn::TransportConfig> {
    let mut t = quinn::TransportConfig::default();
    floored_congestion(&mut t);
    t.max_idle_timeout(Some(
        std::time::Duration::from_secs(10)
            .try_into()
            .expect("10 s is a valid idle timeout"),
    ));
    if keep_alive {
        t.keep_alive_interval(Some(std::time::Duration::from_secs(2)));
    }
    // A viewer reads frames on uni streams the server opens, a few at a time (a newer frame
    // resets the older). At most 16 at once; with the viewer's frame size limit, that bounds
    // what a server can make it hold.
    t.max_concurrent_uni_streams(16u32.into());
    t.max_concurrent_bidi_streams(0u32.into());
    t.stream_receive_window((16u32 << 20).into());
    t.receive_window((48u32 << 20).into());
    // Small frames come as datagrams; a viewer reads them as they arrive.
    t.datagram_receive_buffer_size(Some(1 << 20));
    Arc::new(t)
}

/// The server's QUIC configuration.
pub fn server_config(id: &Identity) -> Result<quinn::ServerConfig, TlsError> {
    let mut tls = rustls::ServerConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .with_no_client_auth()
        .with_single_cert(
            vec![id.cert.clone()],
            PrivateKeyDer::Pkcs8(id.key.clone_key()),
        )?;
    tls.alpn_protocols = vec![ALPN.to_vec()];
    let quic = quinn::crypto::rustls::QuicServerConfig::try_from(tls)
        .map_err(|e| TlsError::Quic(e.to_string()))?;
    let mut config = quinn::ServerConfig::with_crypto(Arc::new(quic));
    // A viewer opens one control stream and sends small messages and key datagrams: a
    // peer cannot make the server buffer more than that.
    let mut t = quinn::TransportConfig::default();
    floored_congestion(&mut t);
    t.max_idle_timeout(Some(
        std::time::Duration::from_secs(10)
            .try_into()
            .expect("10 s is a valid idle timeout"),
    ));
    t.max_concurrent_uni_streams(0u32.into());
    t.max_concurrent_bidi_streams(1u32.into());
    t.stream_receive_window((64u32 << 10).into());
    t.receive_window((128u32 << 10).into());
    t.datagram_receive_buffer_size(Some(64 << 10));
    // Small frames go as datagrams, which quinn sends first in, first out and drops oldest
    // first when this buffer is full: room for a few frames only, so on a link that
    // cannot keep up the newest frame waits behind at most a few stale ones.
    t.datagram_send_buffer_size(4 << 10);
    // What a connection may have sent and not yet had acknowledged: it bounds what the
    // server buffers per viewer (the colour map at connect would otherwise sit whole in
    // the send buffer: tens of MB for a 4097² map), and is still 50 MB/s at a 40 ms RTT.
    t.send_window(2 << 20);
    config.transport_config(Arc::new(t));
    Ok(config)
}

/// A viewer's QUIC configuration: it accepts only the certificate with this SHA-256.
pub fn client_config(fingerprint: [u8; 32]) -> Result<quinn::ClientConfig, TlsError> {
    let provider = provider();
    let mut tls = rustls::ClientConfig::builder_with_provider(provider.clone())
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .dangerous()
        .with_custom_certificate_verifier(Arc::new(Pinned {
            fingerprint,
            provider,
        }))
        .with_no_client_auth();
    tls.alpn_protocols = vec![ALPN.to_vec()];
    let quic = quinn::crypto::rustls::QuicClientConfig::try_from(tls)
        .map_err(|e| TlsError::Quic(e.to_string()))?;
    let mut config = quinn::ClientConfig::new(Arc::new(quic));
    config.transport_config(transport(true));
    Ok(config)
}

/// Accepts the one certificate whose SHA-256 is pinned, and still checks its signatures.
#[derive(Debug)]
struct Pinned {
    fingerprint: [u8; 32],
    provider: Arc<CryptoProvider>,
}

impl ServerCertVerifier for Pinned {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp_response: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        if sha256(end_entity) == self.fingerprint {
            Ok(ServerCertVerified::assertion())
        } else {
            Err(rustls::Error::General(format!(
                "the server's certificate has fingerprint {}, not the one given",
                hex(&sha256(end_entity))
            )))
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls12_signature(
            message,
            cert,
            dss,
            &self.provider.signature_verification_algorithms,
        )
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls13_signature(
            message,
            cert,
            dss,
            &self.provider.signature_verification_algorithms,
        )
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.provider
            .signature_verification_algorithms
            .supported_schemes()
    }
}
