//! The browser viewer's certificate: one ECDSA P-256 certificate that both the page's HTTPS
//! server and the WebTransport endpoint present, made here and renewed before it expires,
//! or one given (`serve --web-cert/--web-key`), which is never renewed.
//!
//! Decisions:
//!
//! - **Short-lived, self-signed, pinned by hash.** A browser accepts a self-signed
//!   certificate for WebTransport only through `serverCertificateHashes`, and only an ECDSA
//!   one valid at most 14 days (Chromium refused 30). Ours is valid [`LIFETIME`] (13 days,
//!   back-dated [`BACKDATE`] for clocks a little behind, the whole span still 13 days),
//!   with BasicConstraints CA:false, KeyUsage digitalSignature and ExtKeyUsage serverAuth:
//!   the form checked to work. The page learns its hash from its own origin
//!   (`/webtransport.json`), so a new certificate needs no restart of anything.
//! - **Renewed well before it expires**: once [`RENEW_LEFT`] (7 days) or less remain, i.e.
//!   about every 6 days, or at once if the clock went back past its start. The old
//!   certificate stays valid a week after, for connections made with it.
//! - **Swapped in place.** [`CertStore`] is the `ResolvesServerCert` of both TLS servers:
//!   each handshake takes the certificate current at that moment, so renewal restarts no
//!   endpoint and drops no connection.
//! - **No clock here.** Every time is a parameter (`now`, Unix seconds); only the network
//!   shell reads the clock and calls [`CertStore::renew`] when [`CertStore::next_check`]
//!   says. The key is the one random thing: a fresh key pair from the system's source.

use std::net::IpAddr;
use std::sync::{Arc, Mutex};

use roam_protocol::sync::lock;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};
use rustls::sign::CertifiedKey;

/// Seconds in a day.
pub const DAY: u64 = 86_400;
/// A made certificate is valid this long, from its start to its end.
pub const LIFETIME: u64 = 13 * DAY;
/// A made certificate starts this long before it is made (a client's clock a little
/// behind still finds it valid).
pub const BACKDATE: u64 = 3_600;
/// A made certificate is renewed once this little of its validity is left.
pub const RENEW_LEFT: u64 = 7 * DAY;
/// The longest the shell waits between two looks at the certificate (a suspended machine
/// or a clock set forward is noticed within this).
pub const MAX_CHECK_EVERY: u64 = 3_600;

/// Why a certificate could not be made or used.
#[derive(Debug, thiserror::Error)]
pub enum CertError {
    #[error("making a certificate: {0}")]
    Generate(#[from] rcgen::Error),
    #[error("the time {0} (Unix seconds) is out of a certificate's range")]
    Time(u64),
    #[error("no certificate in the chain")]
    Empty,
    #[error("the private key is not the certificate's")]
    Mismatch,
    #[error("TLS: {0}")]
    Rustls(#[from] rustls::Error),
}

/// A certificate in use: what TLS presents, its SHA-256 and, for one made here, its span.
#[derive(Clone, Debug)]
pub struct Current {
    pub key: Arc<CertifiedKey>,
    /// The SHA-256 of the leaf certificate's DER.
    pub sha256: [u8; 32],
    /// `(not_before, not_after)` in Unix seconds, for a certificate made here.
    pub valid: Option<(u64, u64)>,
}

/// A made certificate and its key, as DER.
pub struct Made {
    pub cert: CertificateDer<'static>,
    pub key: PrivatePkcs8KeyDer<'static>,
    pub not_before: u64,
    pub not_after: u64,
}

/// The names a made certificate is for: `localhost`, `127.0.0.1`, `::1`, the listening
/// address when it is a specific one, the machine's LAN address and host name when known.
/// No duplicates; names that cannot be a DNS name (not ASCII, empty) are left out.
pub fn subject_names(listen: IpAddr, lan: Option<IpAddr>, hostname: Option<&str>) -> Vec<String> {
    let mut names = vec!["localhost".to_owned(), "127.0.0.1".into(), "::1".into()];
    let ips = [Some(listen).filter(|ip| !ip.is_unspecified()), lan];
    names.extend(ips.into_iter().flatten().map(|ip| ip.to_string()));
    if let Some(h) = hostname.map(str::trim)
        && !h.is_empty()
        && h.len() <= 253
        && h.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'.')
    {
        names.push(h.to_ascii_lowercase());
    }
    let mut out: Vec<String> = Vec::new();
    for n in names {
        if !out.contains(&n) {
            out.push(n);
        }
    }
    out
}

/// A fresh ECDSA P-256 certificate for `names`, valid from `now - BACKDATE` for
/// [`LIFETIME`] (`now` in Unix seconds).
pub fn generate(names: &[String], now: u64) -> Result<Made, CertError> {
    let not_before = now.saturating_sub(BACKDATE);
    let not_after = not_before + LIFETIME;
    let time = |t: u64| {
        i64::try_from(t)
            .ok()
            .and_then(|s| time::OffsetDateTime::from_unix_timestamp(s).ok())
            .ok_or(CertError::Time(t))
    };
    let mut params = rcgen::CertificateParams::default();
    params.not_before = time(not_before)?;
    params.not_after = time(not_after)?;
    params.subject_alt_names = names
        .iter()
        .map(|n| match n.parse::<IpAddr>() {
            Ok(ip) => Ok(rcgen::SanType::IpAddress(ip)),
            Err(_) => Ok(rcgen::SanType::DnsName(n.as_str().try_into()?)),
        })
        .collect::<Result<_, rcgen::Error>>()?;
    let mut dn = rcgen::DistinguishedName::new();
    dn.push(rcgen::DnType::CommonName, "roam browser viewer");
    params.distinguished_name = dn;
    params.is_ca = rcgen::IsCa::ExplicitNoCa;
    params.key_usages = vec![rcgen::KeyUsagePurpose::DigitalSignature];
    params.extended_key_usages = vec![rcgen::ExtendedKeyUsagePurpose::ServerAuth];
    let key = rcgen::KeyPair::generate_for(&rcgen::PKCS_ECDSA_P256_SHA256)?;
    let cert = params.self_signed(&key)?;
    Ok(Made {
        cert: cert.der().clone(),
        key: PrivatePkcs8KeyDer::from(key.serialize_der()),
        not_before,
        not_after,
    })
}

/// Whether a made certificate valid from `not_before` to `not_after` should be replaced at
/// `now`: [`RENEW_LEFT`] or less left, or not valid yet (the clock went back past its
/// start).
pub fn renewal_due(not_before: u64, not_after: u64, now: u64) -> bool {
    now.saturating_add(RENEW_LEFT) >= not_after || now < not_before
}

/// Seconds from `now` until the certificate valid until `not_after` is due for renewal,
/// at least one minute and at most [`MAX_CHECK_EVERY`].
pub fn next_check(not_after: u64, now: u64) -> u64 {
    not_after
        .saturating_sub(RENEW_LEFT)
        .saturating_sub(now)
        .clamp(60, MAX_CHECK_EVERY)
}

fn provider() -> rustls::crypto::CryptoProvider {
    rustls::crypto::ring::default_provider()
}

/// Where the certificate comes from.
#[derive(Debug)]
enum Source {
    /// Made here for these names, renewed before it expires.
    Made(Vec<String>),
    /// Given by the operator (a certificate a browser trusts): never renewed.
    Given,
}

/// A renewal: the SHA-256 of the certificate replaced and of its replacement.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Renewed {
    pub old: [u8; 32],
    pub new: [u8; 32],
}

/// The browser viewer's certificate, shared by its TLS servers (the page's HTTPS and the
/// WebTransport endpoint) and swapped in place when renewed.
#[derive(Debug)]
pub struct CertStore {
    source: Source,
    /// A mutex, not a read-write lock: it is held only to clone or replace a `Current`
    /// (an `Arc` and a few bytes), once per TLS handshake.
    current: Mutex<Current>,
}

impl CertStore {
    /// A certificate made now for `names`, renewed by [`CertStore::renew`].
    pub fn made(names: Vec<String>, now: u64) -> Result<CertStore, CertError> {
        let current = Self::make(&names, now)?;
        Ok(CertStore {
            source: Source::Made(names),
            current: Mutex::new(current),
        })
    }

    /// A given certificate chain (leaf first) and its private key, checked to match.
    pub fn given(
        chain: Vec<CertificateDer<'static>>,
        key: PrivateKeyDer<'static>,
    ) -> Result<CertStore, CertError> {
        let leaf = chain.first().ok_or(CertError::Empty)?;
        let sha256 = roam_link::tls::sha256(leaf);
        let certified = CertifiedKey::from_der(chain, key, &provider()).map_err(|e| match e {
            rustls::Error::InconsistentKeys(_) => CertError::Mismatch,
            e => CertError::Rustls(e),
        })?;
        Ok(CertStore {
            source: Source::Given,
            current: Mutex::new(Current {
                key: Arc::new(certified),
                sha256,
                valid: None,
            }),
        })
    }

    fn make(names: &[String], now: u64) -> Result<Current, CertError> {
        let made = generate(names, now)?;
        let sha256 = roam_link::tls::sha256(&made.cert);
        let key =
            CertifiedKey::from_der(vec![made.cert], PrivateKeyDer::Pkcs8(made.key), &provider())?;
        Ok(Current {
            key: Arc::new(key),
            sha256,
            valid: Some((made.not_before, made.not_after)),
        })
    }

    /// The certificate presented now.
    pub fn current(&self) -> Current {
        lock(&self.current).clone()
    }

    /// What a page passes as `serverCertificateHashes`: the made certificate's SHA-256, or
    /// nothing for a given certificate (the browser trusts it as it is).
    pub fn served_hashes(&self) -> Vec<[u8; 32]> {
        match self.source {
            Source::Made(_) => vec![self.current().sha256],
            Source::Given => Vec::new(),
        }
    }

    /// Replaces a made certificate with a new one if [`renewal_due`] at `now`; `None` if
    /// not due (or given).
    pub fn renew(&self, now: u64) -> Result<Option<Renewed>, CertError> {
        let Source::Made(names) = &self.source else {
            return Ok(None);
        };
        let old = self.current();
        match old.valid {
            Some((nb, na)) if renewal_due(nb, na, now) => {}
            _ => return Ok(None),
        }
        let new = Self::make(names, now)?;
        let renewed = Renewed {
            old: old.sha256,
            new: new.sha256,
        };
        *lock(&self.current) = new;
        Ok(Some(renewed))
    }

    /// Seconds from `now` until the certificate should be looked at again ([`next_check`]);
    /// `None` for a given certificate.
    pub fn next_check(&self, now: u64) -> Option<u64> {
        match self.source {
            Source::Made(_) => self.current().valid.map(|(_, na)| next_check(na, now)),
            Source::Given => None,
        }
    }
}

impl rustls::server::ResolvesServerCert for CertStore {
    fn resolve(&self, _hello: rustls::server::ClientHello<'_>) -> Option<Arc<CertifiedKey>> {
        Some(self.current().key)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use x509_parser::extensions::ParsedExtension;
    use x509_parser::prelude::{FromDer, GeneralName, X509Certificate};

    const NOW: u64 = 1_790_000_000;

    fn names() -> Vec<String> {
        subject_names(
            "192.168.1.20".parse().expect("an address"),
            None,
            Some("Roam-Host"),
        )
    }

    #[test]
    fn a_made_certificate_is_p256_valid_13_days_with_the_extensions_chromium_wants() {
        let made = generate(&names(), NOW).expect("made");
        let (rest, x509) = X509Certificate::from_der(&made.cert).expect("parses");
        assert!(rest.is_empty());
        let validity = x509.validity();
        let (nb, na) = (
            validity.not_before.timestamp() as u64,
            validity.not_after.timestamp() as u64,
        );
        assert_eq!((nb, na), (made.not_before, made.not_after));
        assert_eq!(nb, NOW - BACKDATE);
        assert_eq!(na - nb, 13 * DAY);
        assert!(na - nb <= 14 * DAY, "Chromium takes at most 14 days");
        // ECDSA with SHA-256 over a P-256 key.
        assert_eq!(
            x509.signature_algorithm.algorithm.to_id_string(),
            "1.2.840.10045.4.3.2"
        );
        let spki = &x509.public_key().algorithm;
        assert_eq!(spki.algorithm.to_id_string(), "1.2.840.10045.2.1");
        let curve = spki
            .parameters
            .as_ref()
            .and_then(|p| p.as_oid().ok())
            .expect("a named curve");
        assert_eq!(curve.to_id_string(), "1.2.840.10045.3.1.7", "P-256");
        let (mut basic, mut usage, mut ext_usage, mut sans) = (None, None, None, Vec::new());
        for ext in x509.extensions() {
            match ext.parsed_extension() {
                ParsedExtension::BasicConstraints(b) => basic = Some(b.ca),
                ParsedExtension::KeyUsage(k) => usage = Some(k.digital_signature()),
                ParsedExtension::ExtendedKeyUsage(e) => ext_usage = Some(e.server_auth),
                ParsedExtension::SubjectAlternativeName(s) => {
                    for n in &s.general_names {
                        sans.push(match n {
                            GeneralName::DNSName(d) => d.to_string(),
                            GeneralName::IPAddress(b) => match b.len() {
                                4 => std::net::Ipv4Addr::from(<[u8; 4]>::try_from(*b).expect("4"))
                                    .to_string(),
                                _ => std::net::Ipv6Addr::from(
                                    <[u8; 16]>::try_from(*b).expect("16 bytes"),
                                )
                                .to_string(),
                            },
                            other => format!("{other:?}"),
                        });
                    }
                }
                _ => {}
            }
        }
        assert_eq!(basic, Some(false), "BasicConstraints CA:false");
        assert_eq!(usage, Some(true), "KeyUsage digitalSignature");
        assert_eq!(ext_usage, Some(true), "ExtKeyUsage serverAuth");
        assert_eq!(
            sans,
            ["localhost", "127.0.0.1", "::1", "192.168.1.20", "roam-host"]
        );
    }

    #[test]
    fn subject_names_skip_the_unspecified_address_duplicates_and_odd_host_names() {
        let any = "0.0.0.0".parse().expect("an address");
        let lan = "10.0.0.5".parse().ok();
        assert_eq!(
            subject_names(any, lan, Some("box")),
            ["localhost", "127.0.0.1", "::1", "10.0.0.5", "box"]
        );
        let local = "127.0.0.1".parse().expect("an address");
        assert_eq!(
            subject_names(local, None, Some("  ")),
            ["localhost", "127.0.0.1", "::1"]
        );
        assert_eq!(subject_names(any, None, Some("bad name\u{e9}")).len(), 3);
    }

    #[test]
    fn renewal_is_due_with_a_week_left_or_before_the_start() {
        let (nb, na) = (NOW, NOW + LIFETIME);
        assert!(!renewal_due(nb, na, NOW));
        assert!(!renewal_due(nb, na, NOW + 6 * DAY - 1));
        assert!(renewal_due(nb, na, NOW + 6 * DAY), "7 days left");
        assert!(renewal_due(nb, na, na + 1), "expired");
        assert!(renewal_due(nb, na, NOW - 1), "the clock went back");
        // The next look: an hour at most, a minute at least, the due moment otherwise.
        assert_eq!(next_check(na, NOW), MAX_CHECK_EVERY);
        assert_eq!(next_check(na, NOW + 6 * DAY - 600), 600);
        assert_eq!(next_check(na, NOW + 6 * DAY + 5), 60);
    }

    #[test]
    fn a_store_renews_in_place_and_serves_the_new_hash() {
        let store = CertStore::made(names(), NOW).expect("made");
        let first = store.current();
        assert_eq!(store.served_hashes(), vec![first.sha256]);
        assert_eq!(
            first.sha256,
            roam_link::tls::sha256(&first.key.cert[0]),
            "the hash of what TLS presents"
        );
        assert_eq!(store.renew(NOW + DAY).expect("no error"), None);
        assert_eq!(store.next_check(NOW), Some(MAX_CHECK_EVERY));
        let later = NOW + 6 * DAY;
        let renewed = store.renew(later).expect("made").expect("due");
        assert_eq!(renewed.old, first.sha256);
        assert_ne!(renewed.new, first.sha256);
        let second = store.current();
        assert_eq!(second.sha256, renewed.new);
        assert_eq!(store.served_hashes(), vec![renewed.new]);
        assert_eq!(
            second.valid,
            Some((later - BACKDATE, later - BACKDATE + LIFETIME))
        );
        assert_eq!(store.renew(later).expect("no error"), None, "not due again");
    }

    #[test]
    fn a_given_certificate_is_checked_against_its_key_and_never_renewed() {
        let a = generate(&names(), NOW).expect("made");
        let b = generate(&names(), NOW).expect("made");
        let store = CertStore::given(
            vec![a.cert.clone()],
            PrivateKeyDer::Pkcs8(a.key.clone_key()),
        )
        .expect("a matching pair");
        assert!(store.served_hashes().is_empty());
        assert_eq!(store.current().sha256, roam_link::tls::sha256(&a.cert));
        assert_eq!(store.renew(NOW + 30 * DAY).expect("no error"), None);
        assert_eq!(store.next_check(NOW), None);
        let wrong = CertStore::given(vec![a.cert], PrivateKeyDer::Pkcs8(b.key));
        assert!(matches!(wrong, Err(CertError::Mismatch)), "{wrong:?}");
        let empty = CertStore::given(Vec::new(), PrivateKeyDer::Pkcs8(a.key));
        assert!(matches!(empty, Err(CertError::Empty)), "{empty:?}");
    }
}
