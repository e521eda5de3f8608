//! The page around the viewer: its options (from the URL's fragment, which a browser
//! never sends to the server), its elements (the canvas, the message line, the HUD), the
//! server's WebTransport address and certificate hashes (`/webtransport.json`, from the
//! page's own origin: [`Endpoint::edge`], the first place the page connects to; an edge
//! server names the world's others, `roam_client::edges::web_edges`), timers as futures,
//! and the results a test asks to be posted.

use std::collections::HashMap;

use roam_client::edges::WebEdge;
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use wasm_bindgen_futures::JsFuture;
use web_sys::{HtmlCanvasElement, HtmlElement};

/// What the page was asked to do: `#token=…&role=spectator&gpu=webgl&budget=…`, `port=N`
/// (the WebTransport port, when a forwarded one differs from the server's own), and for
/// tests `script=…` (a key script, URL-encoded), `report=URL` (where to post the results),
/// `frames=N` (after how many decoded frames) and `silence=S` (seconds without a word from
/// the server before the connection counts as lost; 10 unless told).
#[derive(Clone, Debug, Default)]
pub(crate) struct Options {
    pub token: String,
    pub spectator: bool,
    /// `webgpu`, `webgl` or empty (WebGPU where the browser has it, else WebGL2).
    pub gpu: String,
    pub budget: Option<u32>,
    pub script: Option<String>,
    pub report: Option<String>,
    pub frames: u64,
    pub port: Option<u16>,
    pub silence_s: Option<f64>,
}

impl Options {
    /// The options in a URL fragment (with or without its `#`).
    pub(crate) fn parse(fragment: &str) -> Options {
        let fields: HashMap<String, String> = fragment
            .trim_start_matches('#')
            .split('&')
            .filter_map(|kv| {
                let (k, v) = kv.split_once('=')?;
                let v = js_sys::decode_uri_component(&v.replace('+', " ")).ok()?;
                Some((k.to_owned(), String::from(v)))
            })
            .collect();
        let get = |k: &str| fields.get(k).cloned().filter(|v| !v.is_empty());
        Options {
            token: get("token").unwrap_or_default(),
            spectator: get("role").is_some_and(|r| r == "spectator"),
            gpu: get("gpu").unwrap_or_default(),
            budget: get("budget").and_then(|b| b.parse().ok()),
            script: get("script"),
            report: get("report"),
            frames: get("frames").and_then(|f| f.parse().ok()).unwrap_or(300),
            port: get("port").and_then(|p| p.parse().ok()),
            silence_s: get("silence")
                .and_then(|s| s.parse().ok())
                .filter(|s: &f64| s.is_finite() && *s > 0.0),
        }
    }
}

pub(crate) fn window() -> web_sys::Window {
    web_sys::window().expect("a page runs in a window")
}

fn document() -> web_sys::Document {
    window().document().expect("a window has a document")
}

/// What the page lacks that the viewer needs: an element, its own address, the server's
/// WebTransport endpoint; in the words the page shows.
#[derive(Debug, thiserror::Error)]
pub(crate) enum PageError {
    #[error("the page has no #{id}")]
    NoElement { id: String },
    #[error("#{id} is not the element expected")]
    WrongElement { id: String },
    #[error("the page's address has no host")]
    NoHost,
    /// A certificate hash in `/webtransport.json` or an edge's news.
    #[error("certificate hash {hash:?} is not a SHA-256 in hex")]
    Hash { hash: String },
    /// The browser could not fetch `/webtransport.json` (its error, as the browser gives
    /// it).
    #[error("fetching /webtransport.json: {error}")]
    Fetch { error: String },
    #[error("fetching /webtransport.json: HTTP {status}")]
    Http { status: u16 },
    #[error("/webtransport.json: {0}")]
    Json(serde_json::Error),
}

/// The page's element `id`, of type `T`.
pub(crate) fn element<T: JsCast>(id: &str) -> Result<T, PageError> {
    let id = id.to_owned();
    document()
        .get_element_by_id(&id)
        .ok_or_else(|| PageError::NoElement { id: id.clone() })?
        .dyn_into::<T>()
        .map_err(|_| PageError::WrongElement { id })
}

pub(crate) fn canvas() -> Result<HtmlCanvasElement, PageError> {
    element("view")
}

/// Shows `text` on the message line (`error` in red), or hides the line when empty.
pub(crate) fn say(text: &str, error: bool) {
    // The console keeps each line said (the browser's log shows how a session went).
    if !text.is_empty() {
        web_sys::console::log_1(&text.into());
    }
    if let Ok(m) = element::<HtmlElement>("message") {
        m.set_text_content(Some(text));
        let style = m.style();
        let _ = style.set_property("display", if text.is_empty() { "none" } else { "block" });
        m.set_class_name(if error { "error" } else { "" });
    }
}

/// Writes the HUD's lines (or hides it).
pub(crate) fn hud(lines: Option<&[String]>) {
    if let Ok(h) = element::<HtmlElement>("hud") {
        match lines {
            Some(l) => {
                h.set_text_content(Some(&l.join("\n")));
                let _ = h.style().set_property("display", "block");
            }
            None => {
                let _ = h.style().set_property("display", "none");
            }
        }
    }
}

/// Milliseconds since the page began to load.
pub(crate) fn since_load_ms() -> f64 {
    window().performance().map_or(0.0, |p| p.now())
}

/// Resolves after `ms` milliseconds.
pub(crate) async fn sleep(ms: i32) {
    let promise = js_sys::Promise::new(&mut |resolve, _| {
        let _ = window().set_timeout_with_callback_and_timeout_and_arguments_0(&resolve, ms);
    });
    let _ = JsFuture::from(promise).await;
}

/// Where the server takes WebTransport sessions, and the certificate hashes to accept.
#[derive(Clone, Debug, serde::Deserialize)]
pub(crate) struct Endpoint {
    pub path: String,
    pub port: u16,
    /// SHA-256 of each certificate, lowercase hex (empty: a certificate the browser trusts).
    pub certificate_hashes: Vec<String>,
}

impl Endpoint {
    /// The session's URL on the page's own host.
    pub(crate) fn url(&self) -> Result<String, PageError> {
        let host = window()
            .location()
            .hostname()
            .map_err(|_| PageError::NoHost)?;
        let host = if host.contains(':') && !host.starts_with('[') {
            format!("[{host}]")
        } else {
            host
        };
        Ok(format!("https://{host}:{}{}", self.port, self.path))
    }

    /// The session's URL and the certificate hashes, as an edge names a place to
    /// connect to.
    pub(crate) fn edge(&self) -> Result<WebEdge, PageError> {
        Ok(WebEdge {
            url: self.url()?,
            hashes: self
                .certificate_hashes
                .iter()
                .map(|h| h.to_ascii_lowercase())
                .collect(),
        })
    }
}

/// Certificate hashes in hex as bytes (each a SHA-256).
pub(crate) fn hash_bytes(hashes: &[String]) -> Result<Vec<Vec<u8>>, PageError> {
    hashes
        .iter()
        .map(|h| {
            let bytes: Option<Vec<u8>> = (0..h.len())
                .step_by(2)
                .map(|i| u8::from_str_radix(h.get(i..i + 2)?, 16).ok())
                .collect();
            bytes
                .filter(|b| b.len() == 32)
                .ok_or_else(|| PageError::Hash { hash: h.clone() })
        })
        .collect()
}

/// Fetches `/webtransport.json` from the page's origin.
pub(crate) async fn endpoint() -> Result<Endpoint, PageError> {
    let fail = |e: JsValue| PageError::Fetch {
        error: format!("{e:?}"),
    };
    let response: web_sys::Response = JsFuture::from(window().fetch_with_str("/webtransport.json"))
        .await
        .map_err(fail)?
        .dyn_into()
        .map_err(fail)?;
    if !response.ok() {
        let status = response.status();
        return Err(PageError::Http { status });
    }
    let text = JsFuture::from(response.text().map_err(fail)?)
        .await
        .map_err(fail)?
        .as_string()
        .unwrap_or_default();
    serde_json::from_str(&text).map_err(PageError::Json)
}

/// Posts `body` (JSON) to `url`, for a test (as text/plain: no CORS preflight).
pub(crate) async fn post(url: &str, body: &str) {
    let init = web_sys::RequestInit::new();
    init.set_method("POST");
    init.set_body(&JsValue::from_str(body));
    let _ = JsFuture::from(window().fetch_with_str_and_init(url, &init)).await;
}
