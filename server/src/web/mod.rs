//! The browser viewer, as `serve --web` offers it: the page's files and what the HTTPS
//! server answers for each request ([`Site::respond`]), and the certificate ([`cert`]).
//! Pure: no socket, no clock; the network shell (`net::web`) feeds it requests.
//!
//! Decisions:
//!
//! - **The page is built into the release binary.** `scripts/build-web` writes it to
//!   `web/dist/`; in release builds `build.rs` embeds every file there (`include_bytes!`)
//!   when `web/dist/index.html` exists, else none, and `serve --web` on a binary without it
//!   says to run `scripts/build-web` ([`NOT_BUILT`]). Other builds read `web/dist/` when
//!   the page is asked for ([`Page::embedded`]), so that the tests' build need not wait
//!   for the page, nor be redone after it. Tests hand [`Page::from_files`] or
//!   [`Page::read_dir`] a page of their own.
//! - **A closed set of answers.** `GET`/`HEAD` of `/` or `/index.html` gives the page,
//!   `/NAME` an embedded file by its name (gzip-coded when the client accepts it and
//!   `NAME.gz` is embedded), `/webtransport.json` where and how to open WebTransport
//!   (its path, UDP port and the certificate hashes to pin); anything else is 404, another
//!   method 405. No path ever reaches the file system.
//! - **Which build.** `scripts/build-web --quick` (the page the tests open, built in half
//!   the time) writes `quick` in the page's `BUILD` file; [`Page::is_quick`] tells, and
//!   `serve --web` says so in its log, so that nobody publishes it by mistake.
//! - **Caching**: the page's files are `no-cache` (revalidated: a new build is seen at
//!   once), `/webtransport.json` `no-store` (the certificate changes every few days).

pub mod cert;

use std::collections::BTreeMap;

use bytes::Bytes;
use http::{HeaderMap, HeaderValue, Method, Response, StatusCode, header};

/// What `serve --web` says when the binary has no page.
pub const NOT_BUILT: &str = "this roam-server was built without the browser viewer: run \
                             scripts/build-web, then build roam-server again";

/// The WebTransport session's path (its `CONNECT` request's).
pub const SESSION_PATH: &str = "/roam";

/// Where the page learns how to reach WebTransport.
pub const TRANSPORT_JSON: &str = "/webtransport.json";

mod embedded {
    //! The page's files as `build.rs` found them in `web/dist/` (none if it was not built).
    include!(concat!(env!("OUT_DIR"), "/page.rs"));
}

/// The page's files by name (`index.html`, `roam_web.js`, `roam_web_bg.wasm`, …, and
/// `NAME.gz` copies).
#[derive(Clone, Debug, Default)]
pub struct Page {
    files: BTreeMap<String, Bytes>,
}

impl Page {
    /// The page built into this binary (empty if it was built without one); in builds
    /// other than release, the page in the source tree's `web/dist/` as it is now (empty
    /// if it cannot be read).
    pub fn embedded() -> Page {
        if let Some(dist) = embedded::DIST {
            return Page::read_dir(std::path::Path::new(dist)).unwrap_or_default();
        }
        Page::from_files(
            embedded::FILES
                .iter()
                .map(|&(name, bytes)| (name.to_owned(), Bytes::from_static(bytes))),
        )
    }

    /// The files under `dir`, named as `build.rs` names the ones it embeds (relative to
    /// `dir`, `/` between folders, hidden ones left out), as `scripts/build-web` leaves
    /// them in `web/dist/`.
    pub fn read_dir(dir: &std::path::Path) -> std::io::Result<Page> {
        fn walk(
            dir: &std::path::Path,
            prefix: &str,
            out: &mut Vec<(String, Bytes)>,
        ) -> std::io::Result<()> {
            for entry in std::fs::read_dir(dir)? {
                let entry = entry?;
                let name = entry.file_name().to_string_lossy().into_owned();
                if name.starts_with('.') {
                    continue;
                }
                let kind = entry.file_type()?;
                if kind.is_dir() {
                    walk(&entry.path(), &format!("{prefix}{name}/"), out)?;
                } else if kind.is_file() {
                    out.push((
                        format!("{prefix}{name}"),
                        Bytes::from(std::fs::read(entry.path())?),
                    ));
                }
            }
            Ok(())
        }
        let mut files = Vec::new();
        walk(dir, "", &mut files)?;
        Ok(Page::from_files(files))
    }

    /// A page of these files, by name (`/` separates folders).
    pub fn from_files(files: impl IntoIterator<Item = (String, Bytes)>) -> Page {
        Page {
            files: files.into_iter().collect(),
        }
    }

    /// Whether there is a page to serve at all (an `index.html`).
    pub fn is_built(&self) -> bool {
        self.files.contains_key("index.html")
    }

    /// Whether this is the quick build of the page (`scripts/build-web --quick`: larger
    /// and slower to load than the one to publish).
    pub fn is_quick(&self) -> bool {
        self.get("BUILD")
            .is_some_and(|b| b.trim_ascii() == b"quick")
    }

    /// The file named `name`.
    pub fn get(&self, name: &str) -> Option<&Bytes> {
        self.files.get(name)
    }

    /// The files' names, in order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.files.keys().map(String::as_str)
    }
}

/// The `Content-Type` of a file, by its name's extension.
pub fn content_type(name: &str) -> &'static str {
    let ext = name.rsplit_once('.').map_or("", |(_, e)| e);
    match ext.to_ascii_lowercase().as_str() {
        "html" | "htm" => "text/html; charset=utf-8",
        "js" | "mjs" => "text/javascript",
        "wasm" => "application/wasm",
        "css" => "text/css",
        "png" => "image/png",
        "json" | "map" => "application/json",
        "svg" => "image/svg+xml",
        "ico" => "image/x-icon",
        "txt" => "text/plain; charset=utf-8",
        "gz" => "application/gzip",
        _ => "application/octet-stream",
    }
}

/// Whether an `Accept-Encoding` header accepts gzip (`gzip` or `*`, without `q=0`).
pub fn accepts_gzip(accept: Option<&HeaderValue>) -> bool {
    let Some(text) = accept.and_then(|v| v.to_str().ok()) else {
        return false;
    };
    text.split(',').any(|item| {
        let mut parts = item.split(';');
        let coding = parts.next().unwrap_or("").trim();
        let refused = parts.any(|p| {
            p.trim()
                .strip_prefix("q=")
                .and_then(|q| q.trim().parse::<f32>().ok())
                .is_some_and(|q| q <= 0.0)
        });
        (coding.eq_ignore_ascii_case("gzip") || coding == "*") && !refused
    })
}

/// `/webtransport.json`'s body: the session's path, the UDP port, and the certificate
/// hashes (lowercase hex SHA-256s of DER certificates) a page passes as
/// `serverCertificateHashes` (none for a certificate browsers trust).
pub fn transport_json(port: u16, hashes: &[[u8; 32]]) -> String {
    let hashes: Vec<String> = hashes.iter().map(|h| roam_link::tls::hex(h)).collect();
    serde_json::json!({
        "path": SESSION_PATH,
        "port": port,
        "certificate_hashes": hashes,
    })
    .to_string()
}

/// The page's address with the join token in its fragment (`https://HOST:PORT/#token=T`):
/// a browser never sends a fragment to the server, so the token stays out of request lines
/// and logs. The token is percent-encoded but for unreserved characters; an IPv6 host is
/// bracketed.
pub fn page_url(host: &str, port: u16, token: &str) -> String {
    let host = url_host(host);
    let mut encoded = String::with_capacity(token.len());
    for b in token.bytes() {
        if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
            encoded.push(char::from(b));
        } else {
            encoded.push_str(&format!("%{b:02X}"));
        }
    }
    format!("https://{host}:{port}/#token={encoded}")
}

/// An IPv6 address in brackets, as a URL writes it.
fn url_host(host: &str) -> String {
    match host.parse::<std::net::Ipv6Addr>() {
        Ok(_) => format!("[{host}]"),
        Err(_) => host.to_owned(),
    }
}

/// Where a page reaches this server's WebTransport directly, as an edge tells its world's
/// other pages (`roam_protocol::messages::WorldNews::Edges`):
/// `https://HOST:PORT/roam#hashes=HEX,…`, the certificate hashes to pin (none for a
/// certificate browsers trust).
pub fn transport_url(host: &str, port: u16, hashes: &[[u8; 32]]) -> String {
    let hashes: Vec<String> = hashes.iter().map(|h| roam_link::tls::hex(h)).collect();
    let url = format!("https://{}:{port}{SESSION_PATH}", url_host(host));
    if hashes.is_empty() {
        url
    } else {
        format!("{url}#hashes={}", hashes.join(","))
    }
}

/// What the HTTPS server serves: the page, and the WebTransport endpoint's port and
/// certificate.
#[derive(Debug)]
pub struct Site {
    pub page: std::sync::Arc<Page>,
    /// The WebTransport endpoint's UDP port (the HTTPS server's TCP port number too).
    pub port: u16,
    pub certs: std::sync::Arc<cert::CertStore>,
}

impl Site {
    /// The answer to a request (the body stays in `HEAD`'s answer: the HTTP server leaves
    /// it out and keeps its length).
    pub fn respond(&self, method: &Method, path: &str, headers: &HeaderMap) -> Response<Bytes> {
        if method != Method::GET && method != Method::HEAD {
            let mut r = plain(StatusCode::METHOD_NOT_ALLOWED, "only GET and HEAD\n");
            r.headers_mut()
                .insert(header::ALLOW, HeaderValue::from_static("GET, HEAD"));
            return r;
        }
        if path == TRANSPORT_JSON {
            let body = transport_json(self.port, &self.certs.served_hashes());
            return answer(
                Bytes::from(body),
                "application/json",
                "no-store",
                None,
                false,
            );
        }
        let name = match path {
            "/" => "index.html",
            p => p.strip_prefix('/').unwrap_or(p),
        };
        let Some(file) = self.page.get(name) else {
            return plain(StatusCode::NOT_FOUND, "not found\n");
        };
        let gz = self.page.get(&format!("{name}.gz"));
        let varies = gz.is_some();
        match gz {
            Some(gz) if accepts_gzip(headers.get(header::ACCEPT_ENCODING)) => answer(
                gz.clone(),
                content_type(name),
                "no-cache",
                Some("gzip"),
                varies,
            ),
            _ => answer(file.clone(), content_type(name), "no-cache", None, varies),
        }
    }
}

fn answer(
    body: Bytes,
    content_type: &'static str,
    cache: &'static str,
    encoding: Option<&'static str>,
    varies: bool,
) -> Response<Bytes> {
    let mut r = Response::new(body);
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static(cache));
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    if let Some(e) = encoding {
        h.insert(header::CONTENT_ENCODING, HeaderValue::from_static(e));
    }
    if varies {
        h.insert(header::VARY, HeaderValue::from_static("Accept-Encoding"));
    }
    r
}

/// A short plain-text answer with `status`.
pub fn plain(status: StatusCode, text: &'static str) -> Response<Bytes> {
    let mut r = answer(
        Bytes::from_static(text.as_bytes()),
        "text/plain; charset=utf-8",
        "no-store",
        None,
        false,
    );
    *r.status_mut() = status;
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    fn site() -> Site {
        let page = Page::from_files([
            ("index.html".to_owned(), Bytes::from_static(b"<p>roam</p>")),
            ("roam_web.js".to_owned(), Bytes::from_static(b"export {}")),
            (
                "roam_web.js.gz".to_owned(),
                Bytes::from_static(b"\x1f\x8bjs"),
            ),
            ("roam_web_bg.wasm".to_owned(), Bytes::from_static(b"\0asm")),
            ("style.css".to_owned(), Bytes::from_static(b"p{}")),
        ]);
        let names = vec!["localhost".to_owned()];
        Site {
            page: Arc::new(page),
            port: 4443,
            certs: Arc::new(cert::CertStore::made(names, 1_790_000_000).expect("made")),
        }
    }

    fn get(
        site: &Site,
        path: &str,
        headers: &[(header::HeaderName, &'static str)],
    ) -> Response<Bytes> {
        let mut map = HeaderMap::new();
        for (k, v) in headers {
            map.insert(k.clone(), HeaderValue::from_static(v));
        }
        site.respond(&Method::GET, path, &map)
    }

    #[test]
    fn a_page_read_from_a_folder_names_its_files_as_the_embedded_one() {
        let dir = std::env::temp_dir().join(format!("roam-page-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("assets")).expect("a temporary folder");
        for (name, bytes) in [
            ("index.html", "<p>"),
            ("assets/a.js", "x"),
            (".hidden", "h"),
        ] {
            std::fs::write(dir.join(name), bytes).expect("a temporary file");
        }
        let page = Page::read_dir(&dir).expect("the folder reads");
        let _ = std::fs::remove_dir_all(&dir);
        assert_eq!(
            page.names().collect::<Vec<_>>(),
            ["assets/a.js", "index.html"]
        );
        assert_eq!(page.get("assets/a.js").map(|b| &b[..]), Some(&b"x"[..]));
        assert!(
            Page::read_dir(&dir).is_err(),
            "a folder that is gone is an error"
        );
    }

    #[test]
    fn the_quick_build_is_told_by_its_build_file() {
        let page = |build: Option<&'static [u8]>| {
            let mut files = vec![("index.html".to_owned(), Bytes::from_static(b"<p>"))];
            files.extend(build.map(|b| ("BUILD".to_owned(), Bytes::from_static(b))));
            Page::from_files(files).is_quick()
        };
        for (build, quick) in [
            (Some(&b"quick\n"[..]), true),
            (Some(&b"quick"[..]), true),
            (Some(&b"publish\n"[..]), false),
            (Some(&b""[..]), false),
            (None, false),
        ] {
            assert_eq!(page(build), quick, "BUILD {build:?}");
        }
    }

    fn header_of(r: &Response<Bytes>, name: header::HeaderName) -> Option<&str> {
        r.headers().get(name).and_then(|v| v.to_str().ok())
    }

    #[test]
    fn the_page_and_its_files_are_served_with_their_types() {
        let site = site();
        for (path, body, ty) in [
            ("/", &b"<p>roam</p>"[..], "text/html; charset=utf-8"),
            ("/index.html", b"<p>roam</p>", "text/html; charset=utf-8"),
            ("/roam_web.js", b"export {}", "text/javascript"),
            ("/roam_web_bg.wasm", b"\0asm", "application/wasm"),
            ("/style.css", b"p{}", "text/css"),
        ] {
            let r = get(&site, path, &[]);
            assert_eq!(r.status(), StatusCode::OK, "{path}");
            assert_eq!(r.body().as_ref(), body, "{path}");
            assert_eq!(header_of(&r, header::CONTENT_TYPE), Some(ty), "{path}");
            assert_eq!(header_of(&r, header::CACHE_CONTROL), Some("no-cache"));
            assert_eq!(header_of(&r, header::CONTENT_ENCODING), None);
        }
        let head = site.respond(&Method::HEAD, "/", &HeaderMap::new());
        assert_eq!(head.status(), StatusCode::OK);
    }

    #[test]
    fn a_gzip_copy_goes_to_clients_that_accept_it() {
        let site = site();
        let r = get(
            &site,
            "/roam_web.js",
            &[(header::ACCEPT_ENCODING, "gzip, deflate, br")],
        );
        assert_eq!(r.body().as_ref(), b"\x1f\x8bjs");
        assert_eq!(header_of(&r, header::CONTENT_ENCODING), Some("gzip"));
        assert_eq!(header_of(&r, header::CONTENT_TYPE), Some("text/javascript"));
        assert_eq!(header_of(&r, header::VARY), Some("Accept-Encoding"));
        for refuses in ["br", "gzip;q=0", "identity"] {
            let r = get(&site, "/roam_web.js", &[(header::ACCEPT_ENCODING, refuses)]);
            assert_eq!(r.body().as_ref(), b"export {}", "{refuses}");
            assert_eq!(header_of(&r, header::CONTENT_ENCODING), None);
        }
        // No copy: the file as it is, whatever the client accepts.
        let r = get(
            &site,
            "/roam_web_bg.wasm",
            &[(header::ACCEPT_ENCODING, "gzip")],
        );
        assert_eq!(r.body().as_ref(), b"\0asm");
        assert_eq!(header_of(&r, header::CONTENT_ENCODING), None);
    }

    #[test]
    fn webtransport_json_names_the_path_port_and_certificate_hash() {
        let site = site();
        let r = get(&site, TRANSPORT_JSON, &[]);
        assert_eq!(r.status(), StatusCode::OK);
        assert_eq!(
            header_of(&r, header::CONTENT_TYPE),
            Some("application/json")
        );
        assert_eq!(header_of(&r, header::CACHE_CONTROL), Some("no-store"));
        let v: serde_json::Value = serde_json::from_slice(r.body()).expect("JSON");
        let hash = roam_link::tls::hex(&site.certs.current().sha256);
        assert_eq!(
            v,
            serde_json::json!({"path": "/roam", "port": 4443, "certificate_hashes": [hash]})
        );
        assert_eq!(hash.len(), 64);
        assert!(
            hash.bytes()
                .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
        );
    }

    #[test]
    fn anything_else_is_404_and_other_methods_405() {
        let site = site();
        for path in [
            "/nope",
            "/../Cargo.toml",
            "/index.html/",
            "//index.html",
            "/roam",
            "",
        ] {
            let r = get(&site, path, &[]);
            assert_eq!(r.status(), StatusCode::NOT_FOUND, "{path:?}");
        }
        for m in [
            Method::POST,
            Method::PUT,
            Method::DELETE,
            Method::OPTIONS,
            Method::CONNECT,
        ] {
            let r = site.respond(&m, "/", &HeaderMap::new());
            assert_eq!(r.status(), StatusCode::METHOD_NOT_ALLOWED, "{m}");
            assert_eq!(header_of(&r, header::ALLOW), Some("GET, HEAD"));
        }
    }

    #[test]
    fn the_page_url_carries_the_token_in_its_fragment() {
        assert_eq!(
            page_url("192.168.1.4", 4443, "abc-123_x.y~z"),
            "https://192.168.1.4:4443/#token=abc-123_x.y~z"
        );
        assert_eq!(
            page_url("::1", 8443, "a+b#c%d&e=f/g?"),
            "https://[::1]:8443/#token=a%2Bb%23c%25d%26e%3Df%2Fg%3F"
        );
        let url = page_url("box.lan", 1, "#");
        assert_eq!(url.matches('#').count(), 1, "{url}");
    }

    #[test]
    fn content_types_by_extension() {
        assert_eq!(content_type("a.JSON"), "application/json");
        assert_eq!(content_type("icon.png"), "image/png");
        assert_eq!(content_type("README"), "application/octet-stream");
    }
}
