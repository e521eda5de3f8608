//! Certificates: a self-signed one made on first run and kept in the state directory (or
//! one given in files, [`load_files`]), its SHA-256 fingerprint (what viewers pin), and the
//! QUIC configurations of both ends.
//!
//! The state directory holds the server's identity: `key.der` (its private key, PKCS#8) and
//! `cert.der` (its certificate, whose SHA-256 viewers pin). Its rules, in the spirit of ssh:
//!
//! - **Modes.** The directory is made `0700` and `key.der` is written `0600` (`cert.der`
//!   `0644`: it is public, sent to every peer). An existing directory that others may only
//!   *read* (the `0755` that earlier versions made) is tightened to `0700` with a warning,
//!   and so is a `key.der` others may read (`0600`): the fix is unambiguous, and the warning
//!   says to rotate the identity if the key may have been read. A directory others may
//!   *write* is refused: anyone could have swapped the identity in it, and such a directory
//!   is most likely shared (`/tmp`), so changing its mode would lock its other users out;
//!   the operator decides (a directory of one's own, or `chmod 700` after a look).
//! - **Atomic writes.** Each file is written whole to a temporary name in the same
//!   directory (`.key.der.new`, `.cert.der.new`), created with its final mode (exact, not
//!   left to the umask), synced, and only then renamed over the real name, the key first: a
//!   crash never leaves a truncated file, nor a certificate without its key. A crash
//!   between the two renames leaves the new key beside the old certificate and
//!   `.cert.der.new`: the next start finishes the change (the certificate is complete and
//!   synced by then); a crash before the first rename leaves only temporary files, which
//!   the next start removes (the old identity, if any, stands). The directory is locked
//!   (`flock`) while the identity is read or written, so two starts at once cannot mix
//!   their keys and certificates.
//! - **Never a silent new identity.** A new identity breaks every viewer's pinned
//!   fingerprint, so one is made only where there is none at all: a certificate without its
//!   key (or the reverse), a file that does not parse, or a key that is not the
//!   certificate's is an error naming the files and what to do, and nothing is written.
//!   [`rotate`] replaces an identity on purpose.
//!
//! Only Linux is built and tested; the mode and lock code is `#[cfg(unix)]` and other
//! systems skip it.

use std::fs::File;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::CryptoProvider;
use rustls::pki_types::pem::{self, PemObject};
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
    /// One file of the identity without the other.
    #[error(
        "{present} exists but {missing} does not: restore the {what}, or remove {present} to \
         make a new identity ({pinned})"
    )]
    Incomplete {
        present: String,
        missing: String,
        what: &'static str,
        pinned: String,
    },
    /// A file of the identity that is not what its name says.
    #[error("{path}: {what}")]
    Invalid { path: String, what: String },
    /// A key and a certificate that are each fine but not a pair.
    #[error(
        "{key} is not the key of {cert}: restore the pair that belong together, or remove both \
         to make a new identity ({pinned})"
    )]
    Mismatch {
        cert: String,
        key: String,
        pinned: String,
    },
    /// A state directory other users may write to.
    #[error(
        "{path} can be written by other users (mode {mode:03o}), so anyone could have replaced \
         the server's identity in it: keep the state in a directory of your own, or check its \
         files and `chmod 700 {path}`"
    )]
    SharedDir { path: String, mode: u32 },
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

/// The SHA-256 of `bytes` (a certificate's DER, for its fingerprint).
pub fn sha256(bytes: &[u8]) -> [u8; 32] {
    let d = ring::digest::digest(&ring::digest::SHA256, bytes);
    let mut out = [0; 32];
    out.copy_from_slice(d.as_ref());
    out
}

/// `bytes` in lowercase hex, two digits each.
pub fn hex(bytes: &[u8]) -> String {
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

/// The identity in `dir` (`cert.der`, `key.der`), made and saved there on first use; see
/// the module's header for the modes, the atomic writes and the errors.
pub fn load_or_create(dir: &Path) -> Result<Identity, TlsError> {
    let state = StateDir::open(dir)?;
    if let Some(id) = state.load()? {
        return Ok(id);
    }
    let id = generate()?;
    state.save(&id)?;
    Ok(id)
}

/// The identity in two files an operator made or was given (`serve --cert F --key F`), so
/// that several servers can share one fingerprint. Each file is DER or PEM: the certificate
/// X.509 (the first `CERTIFICATE` of a PEM file; any others, such as a chain's, are not
/// used: viewers pin this one), the key PKCS#8 (`PRIVATE KEY`). Both are checked as the
/// state directory's are: the certificate parses, the key loads, and it is the
/// certificate's key. Nothing is written, and the files' modes are left as they are.
pub fn load_files(cert: &Path, key: &Path) -> Result<Identity, TlsError> {
    let read = |path: &Path| {
        File::open(path)
            .map_err(io(path))
            .and_then(|f| read_bounded(f, path))
    };
    let cert_der: CertificateDer<'static> = decode(
        cert,
        read(cert)?,
        "not a certificate (X.509, DER or PEM): no `-----BEGIN CERTIFICATE-----` in it",
    )?;
    let key_der: PrivatePkcs8KeyDer<'static> = decode(
        key,
        read(key)?,
        "no PKCS#8 private key (DER, or PEM `-----BEGIN PRIVATE KEY-----`) in it; another \
         PEM key converts with `openssl pkcs8 -topk8 -nocrypt`",
    )?;
    checked((cert_der, cert), (key_der, key), Source::Given)
}

/// The item in a file that is PEM (its first section of `T`'s kind) or else DER (the bytes
/// themselves); `missing` says what is wrong with a PEM file without such a section.
fn decode<T: PemObject + From<Vec<u8>>>(
    path: &Path,
    bytes: Vec<u8>,
    missing: &str,
) -> Result<T, TlsError> {
    let invalid = |what: String| TlsError::Invalid {
        path: path.display().to_string(),
        what,
    };
    match T::from_pem_slice(&bytes) {
        Ok(item) => Ok(item),
        Err(pem::Error::NoItemsFound) if !bytes.windows(11).any(|w| w == b"-----BEGIN ") => {
            Ok(T::from(bytes))
        }
        Err(pem::Error::NoItemsFound) => Err(invalid(missing.to_owned())),
        Err(e) => Err(invalid(format!("PEM that does not decode: {e}"))),
    }
}

/// What [`rotate`] did.
pub struct Rotated {
    /// The fingerprint of the certificate it replaced, if there was one.
    pub old: Option<String>,
    /// The identity now in the directory.
    pub new: Identity,
}

/// Replaces the identity in `dir` with a new one (made if there was none), atomically: a
/// crash leaves the old identity or the new one, never a mix. Whatever was there goes,
/// even a broken or incomplete identity; the old key is not kept (one rotates because it
/// may have leaked).
pub fn rotate(dir: &Path) -> Result<Rotated, TlsError> {
    let state = StateDir::open(dir)?;
    let old = state.read(CERT)?.map(|cert| hex(&sha256(&cert)));
    let new = generate()?;
    state.save(&new)?;
    Ok(Rotated { old, new })
}

const KEY: &str = "key.der";
const CERT: &str = "cert.der";
/// Where [`KEY`] and [`CERT`] are written before they are renamed into place.
const KEY_NEW: &str = ".key.der.new";
const CERT_NEW: &str = ".cert.der.new";
/// What a file of the identity may weigh: both are a few hundred bytes.
const MAX_FILE: u64 = 64 << 10;

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> TlsError {
    let path = path.display().to_string();
    move |error| TlsError::Io { path, error }
}

/// What a new identity costs the viewers, for the error messages.
fn pinned(cert: Option<&[u8]>) -> String {
    match cert {
        Some(cert) => format!(
            "viewers pinned to fingerprint {} will need the new one",
            hex(&sha256(cert))
        ),
        None => "viewers will need its new fingerprint".to_owned(),
    }
}

/// The state directory, made and checked, and locked for as long as this lives.
struct StateDir {
    path: PathBuf,
    /// The directory itself, open: holds the lock, and syncs renames to disk.
    #[cfg(unix)]
    handle: File,
}

impl StateDir {
    /// Makes `dir` (`0700`) or checks its mode, locks it, and finishes or undoes an identity
    /// change a crash interrupted.
    fn open(dir: &Path) -> Result<StateDir, TlsError> {
        let mut builder = std::fs::DirBuilder::new();
        builder.recursive(true);
        #[cfg(unix)]
        std::os::unix::fs::DirBuilderExt::mode(&mut builder, 0o700);
        builder.create(dir).map_err(io(dir))?;
        let state = StateDir {
            path: dir.to_path_buf(),
            #[cfg(unix)]
            handle: File::open(dir).map_err(io(dir))?,
        };
        #[cfg(unix)]
        state.secure()?;
        state.recover()?;
        Ok(state)
    }

    /// Locks the directory and keeps it to its owner (see the module's header).
    #[cfg(unix)]
    fn secure(&self) -> Result<(), TlsError> {
        use std::os::unix::fs::PermissionsExt;
        let dir = &self.path;
        self.handle.lock().map_err(io(dir))?;
        let mode = self
            .handle
            .metadata()
            .map_err(io(dir))?
            .permissions()
            .mode()
            & 0o777;
        if mode & 0o022 != 0 {
            return Err(TlsError::SharedDir {
                path: dir.display().to_string(),
                mode,
            });
        }
        if mode & 0o077 != 0 {
            self.handle
                .set_permissions(std::fs::Permissions::from_mode(0o700))
                .map_err(io(dir))?;
            tracing::warn!(
                "{} was open to other users (mode {mode:03o}): made it 700. If they could read \
                 {} in it, rotate the identity",
                dir.display(),
                self.file(KEY).display()
            );
        }
        Ok(())
    }

    fn file(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }

    /// Flushes the directory's entries (renames) to disk.
    fn sync(&self) -> Result<(), TlsError> {
        #[cfg(unix)]
        self.handle.sync_all().map_err(io(&self.path))?;
        Ok(())
    }

    fn exists(&self, name: &str) -> Result<bool, TlsError> {
        let path = self.file(name);
        match std::fs::symlink_metadata(&path) {
            Ok(_) => Ok(true),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
            Err(e) => Err(io(&path)(e)),
        }
    }

    fn remove(&self, name: &str) -> Result<(), TlsError> {
        let path = self.file(name);
        std::fs::remove_file(&path).map_err(io(&path))
    }

    /// Moves `from` over `to` and syncs the directory.
    fn rename(&self, from: &str, to: &str) -> Result<(), TlsError> {
        let from = self.file(from);
        std::fs::rename(&from, self.file(to)).map_err(io(&from))?;
        self.sync()
    }

    /// Finishes or undoes what [`StateDir::save`] left when it was interrupted.
    fn recover(&self) -> Result<(), TlsError> {
        match (self.exists(KEY_NEW)?, self.exists(CERT_NEW)?) {
            (false, false) => {}
            (false, true) => {
                // The key was renamed into place: its certificate is whole and synced.
                self.rename(CERT_NEW, CERT)?;
                tracing::warn!(
                    "{}: finished an identity change interrupted between its key and its \
                     certificate",
                    self.path.display()
                );
            }
            (true, cert_new) => {
                // Interrupted before the first rename: what was there stands. The
                // certificate goes first: a crash between the two removals must not leave
                // a lone certificate that looks like the key was already renamed.
                if cert_new {
                    self.remove(CERT_NEW)?;
                    self.sync()?;
                }
                self.remove(KEY_NEW)?;
                self.sync()?;
                tracing::warn!(
                    "{}: removed the files of an identity change interrupted before it took \
                     effect",
                    self.path.display()
                );
            }
        }
        Ok(())
    }

    /// The file `name`, if there is one. [`KEY`] is kept to its owner: one others may read
    /// is tightened to `0600`, with a warning.
    fn read(&self, name: &str) -> Result<Option<Vec<u8>>, TlsError> {
        let path = self.file(name);
        let file = match File::open(&path) {
            Ok(file) => file,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io(&path)(e)),
        };
        #[cfg(unix)]
        if name == KEY {
            use std::os::unix::fs::PermissionsExt;
            let mode = file.metadata().map_err(io(&path))?.permissions().mode() & 0o777;
            if mode & 0o077 != 0 {
                file.set_permissions(std::fs::Permissions::from_mode(0o600))
                    .map_err(io(&path))?;
                tracing::warn!(
                    "{} was readable by other users (mode {mode:03o}): made it 600. If someone \
                     may have read it, rotate the identity",
                    path.display()
                );
            }
        }
        read_bounded(file, &path).map(Some)
    }

    /// The identity in the directory: none if neither file is there, an error if only one
    /// is, if either does not parse, or if they are not a pair.
    fn load(&self) -> Result<Option<Identity>, TlsError> {
        let (cert_path, key_path) = (self.file(CERT), self.file(KEY));
        let name = |p: &Path| p.display().to_string();
        let (cert, key) = match (self.read(CERT)?, self.read(KEY)?) {
            (None, None) => return Ok(None),
            (Some(cert), Some(key)) => (CertificateDer::from(cert), PrivatePkcs8KeyDer::from(key)),
            (Some(cert), None) => {
                return Err(TlsError::Incomplete {
                    present: name(&cert_path),
                    missing: name(&key_path),
                    what: "key",
                    pinned: pinned(Some(&cert)),
                });
            }
            (None, Some(_)) => {
                return Err(TlsError::Incomplete {
                    present: name(&key_path),
                    missing: name(&cert_path),
                    what: "certificate",
                    pinned: pinned(None),
                });
            }
        };
        checked((cert, &cert_path), (key, &key_path), Source::StateDir).map(Some)
    }

    /// Writes `id` over the directory's identity: both files to temporary names (final
    /// modes, synced), then the key renamed into place, then the certificate.
    fn save(&self, id: &Identity) -> Result<(), TlsError> {
        let written = self
            .write_new(KEY_NEW, id.key.secret_pkcs8_der(), 0o600)
            .and_then(|()| self.write_new(CERT_NEW, &id.cert, 0o644))
            .and_then(|()| self.sync());
        if let Err(e) = written {
            // Nothing took effect; the next start would remove these anyway.
            // The certificate first (see `recover`).
            for name in [CERT_NEW, KEY_NEW] {
                let _best_effort = std::fs::remove_file(self.file(name));
            }
            return Err(e);
        }
        self.rename(KEY_NEW, KEY)?;
        self.rename(CERT_NEW, CERT)
    }

    /// Writes a new file `name` with `mode` from its creation on, and syncs it.
    fn write_new(&self, name: &str, bytes: &[u8], mode: u32) -> Result<(), TlsError> {
        let path = self.file(name);
        let mut options = std::fs::OpenOptions::new();
        options.write(true).create_new(true);
        #[cfg(unix)]
        std::os::unix::fs::OpenOptionsExt::mode(&mut options, mode);
        let mut file = options.open(&path).map_err(io(&path))?;
        // The mode given at creation is masked by the umask: make it exact.
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            file.set_permissions(std::fs::Permissions::from_mode(mode))
                .map_err(io(&path))?;
        }
        #[cfg(not(unix))]
        let _ = mode;
        file.write_all(bytes)
            .and_then(|()| file.sync_all())
            .map_err(io(&path))
    }
}

/// The whole of an identity's file, `path`, refused past [`MAX_FILE`].
fn read_bounded(file: File, path: &Path) -> Result<Vec<u8>, TlsError> {
    let mut bytes = Vec::new();
    file.take(MAX_FILE + 1)
        .read_to_end(&mut bytes)
        .map_err(io(path))?;
    if bytes.len() as u64 > MAX_FILE {
        return Err(TlsError::Invalid {
            path: path.display().to_string(),
            what: format!("over {MAX_FILE} bytes: too large for a certificate or key"),
        });
    }
    Ok(bytes)
}

/// Where an identity's files come from, for what its errors say.
#[derive(Clone, Copy)]
enum Source {
    /// `cert.der` and `key.der` in the state directory.
    StateDir,
    /// Files given (`--cert`, `--key`), DER or PEM.
    Given,
}

/// `cert` (read from `cert_path`) and `key` (from `key_path`) as an identity, if the
/// certificate parses, the key loads with the provider, and it is the certificate's key.
fn checked(
    (cert, cert_path): (CertificateDer<'static>, &Path),
    (key, key_path): (PrivatePkcs8KeyDer<'static>, &Path),
    source: Source,
) -> Result<Identity, TlsError> {
    let forms = match source {
        Source::StateDir => "DER",
        Source::Given => "DER or PEM",
    };
    let name = |p: &Path| p.display().to_string();
    rustls::server::ParsedCertificate::try_from(&cert).map_err(|e| TlsError::Invalid {
        path: name(cert_path),
        what: format!("not a certificate (X.509, {forms}): {e}"),
    })?;
    let signer = provider()
        .key_provider
        .load_private_key(PrivateKeyDer::Pkcs8(key.clone_key()))
        .map_err(|e| TlsError::Invalid {
            path: name(key_path),
            what: format!("not a private key (PKCS#8, {forms}): {e}"),
        })?;
    match rustls::sign::CertifiedKey::new(vec![cert.clone()], signer).keys_match() {
        Ok(()) => Ok(Identity { cert, key }),
        Err(rustls::Error::InconsistentKeys(rustls::InconsistentKeys::KeyMismatch)) => {
            Err(match source {
                Source::StateDir => TlsError::Mismatch {
                    cert: name(cert_path),
                    key: name(key_path),
                    pinned: pinned(Some(&cert)),
                },
                Source::Given => TlsError::Invalid {
                    path: name(key_path),
                    what: format!("the key does not match the certificate {}", name(cert_path)),
                },
            })
        }
        Err(e) => Err(TlsError::Invalid {
            path: name(cert_path),
            what: format!("cannot check it against {}: {e}", name(key_path)),
        }),
    }
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
/// frames nor the keys and acknowledgements starve on a path that loses packets at random;
/// and [`fewer_acks`].
fn floored_congestion(t: &mut quinn::TransportConfig) {
    t.congestion_controller_factory(Arc::new(crate::congestion::FlooredCubic {
        floor: crate::congestion::MIN_WINDOW,
    }));
    fewer_acks(t);
}

/// Both ends ask the other (QUIC's acknowledgement-frequency extension, which quinn speaks
/// at both ends) to acknowledge after more than [`ACK_ELICITING_THRESHOLD`] ack-eliciting
/// packets or [`ACK_DELAY`], not every second packet as QUIC does by default: a driver
/// sends 100 key datagrams a second and takes 60 frames, and each pair cost an
/// acknowledgement packet the other way. With 20 driving viewers on loopback
/// (`scripts/capacity.sh 20`, UDP datagrams counted in `/proc/net/snmp`), 4.9 datagrams a
/// frame became 3.9 (and 2.9 with the acknowledgements of frames in the key datagrams,
/// `KeyDatagram::acked`). Frames are datagrams or streams the server resets when
/// superseded, so a later acknowledgement delays little: on a link losing 5 % each way with
/// 40 ms of delay (`scripts/lossy.sh 40/0.05`) the viewer still took 57.3 frames a second,
/// input to frame 123 ms median, 140 ms p99.
fn fewer_acks(t: &mut quinn::TransportConfig) {
    let mut ack = quinn::AckFrequencyConfig::default();
    ack.ack_eliciting_threshold(quinn::VarInt::from_u32(ACK_ELICITING_THRESHOLD))
        .max_ack_delay(Some(ACK_DELAY));
    t.ack_frequency_config(Some(ack));
}

/// Ack-eliciting packets a peer may take without acknowledging them ([`fewer_acks`]).
pub const ACK_ELICITING_THRESHOLD: u32 = 9;
/// The longest a peer waits to acknowledge ([`fewer_acks`]).
pub const ACK_DELAY: std::time::Duration = std::time::Duration::from_millis(20);

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
    config.transport_config(Arc::new(server_transport()));
    Ok(config)
}

/// [`server_transport`]'s send window, bytes: what a connection may have sent and not yet had
/// acknowledged (also what it buffers at most for the viewer).
pub const SERVER_SEND_WINDOW: u64 = 2 << 20;
/// [`server_transport`]'s receive window for the whole connection, bytes (it bounds every
/// stream's together).
pub const SERVER_RECEIVE_WINDOW: u64 = 128 << 10;
/// [`server_transport`]'s receive window for one stream, bytes.
pub const SERVER_STREAM_RECEIVE_WINDOW: u64 = 64 << 10;
/// [`server_transport`]'s buffer for datagrams received and not yet read, bytes.
pub const SERVER_DATAGRAM_RECEIVE: u64 = 64 << 10;
/// [`server_transport`]'s buffer for datagrams queued to send, bytes.
pub const SERVER_DATAGRAM_SEND: u64 = 4 << 10;

/// The server's transport settings: one control stream from the viewer, no other stream
/// from it, small receive windows (what the server's WebTransport endpoint starts from,
/// adding the streams HTTP/3 needs).
pub fn server_transport() -> quinn::TransportConfig {
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
    let window = |bytes: u64| {
        quinn::VarInt::from_u64(bytes).expect("a window of a few hundred KiB is a valid varint")
    };
    t.stream_receive_window(window(SERVER_STREAM_RECEIVE_WINDOW));
    t.receive_window(window(SERVER_RECEIVE_WINDOW));
    t.datagram_receive_buffer_size(Some(SERVER_DATAGRAM_RECEIVE as usize));
    // Small frames go as datagrams, which quinn sends first in, first out and drops oldest
    // first when this buffer is full: room for a few frames only, so on a path that
    // cannot keep up the newest frame waits behind at most a few stale ones.
    t.datagram_send_buffer_size(SERVER_DATAGRAM_SEND as usize);
    // What a connection may have sent and not yet had acknowledged: it bounds what the
    // server buffers per viewer (the colour map at connect would otherwise sit whole in
    // the send buffer: tens of MB for a 4097² map), and is still 50 MB/s at a 40 ms RTT.
    t.send_window(SERVER_SEND_WINDOW);
    t
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

/// A TLS verifier that accepts only the certificate with this SHA-256 (and still checks
/// its signatures): what a browser's `serverCertificateHashes` does, for tests of the
/// server's HTTPS and WebTransport.
pub fn pinned_verifier(fingerprint: [u8; 32]) -> Arc<dyn ServerCertVerifier> {
    Arc::new(Pinned {
        fingerprint,
        provider: provider(),
    })
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
