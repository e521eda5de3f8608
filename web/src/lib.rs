//! roam-web: the browser viewer. The native viewer's clock-free core, colour cache,
//! cockpit and renderer (`roam-client`), compiled to WebAssembly with wasm-bindgen, over
//! WebTransport ([`net`]) into a canvas ([`app`]); only the I/O and the canvas differ from
//! the window. `roam-server serve --web ADDR` serves the page (`web/static/index.html` and
//! what `scripts/build-web` makes) and takes its sessions.
//!
//! The page learns everything from its own address: the token from the URL's fragment
//! (never sent to the server in a request), the WebTransport port and the certificate
//! hashes from `/webtransport.json` on its own origin ([`page`]); an edge server names the
//! world's other edges, where the page goes when its connection is lost ([`net`]). It
//! says clearly what is wrong when the browser lacks WebTransport or both GPU APIs, when
//! the token is refused, when the connection drops (and reconnects as the native viewer
//! does, by the same supervisor, `roam_client::supervisor`), and when an edge says its
//! world is gone.
//!
//! Natively this crate is empty: `cargo test --workspace` builds none of it.
#![cfg(target_arch = "wasm32")]

mod app;
mod net;
mod page;
mod wire;

use roam_client::supervisor;
use roam_protocol::messages::Role;
use wasm_bindgen::prelude::*;

/// What the page says when the browser has no WebTransport.
const NO_WEBTRANSPORT: &str = "This browser has no WebTransport, which the viewer talks to \
    the server with. Use a current Chrome, Edge or Firefox (Safari has none yet).";

#[wasm_bindgen(start)]
pub fn main() {
    // A panic aborts the page's one thread: say so on the page rather than freeze.
    std::panic::set_hook(Box::new(|info| {
        let text = format!("The viewer stopped on an internal error: {info}. Reload the page.");
        web_sys::console::error_1(&text.clone().into());
        page::say(&text, true);
    }));
    wasm_bindgen_futures::spawn_local(async {
        let options = page::Options::parse(&page::window().location().hash().unwrap_or_default());
        if let Err(why) = run(options.clone()).await {
            let why = why.to_string();
            page::say(&why, true);
            if let Some(url) = options.report {
                let body = serde_json::json!({ "error": why }).to_string();
                page::post(&url, &body).await;
            }
        }
    });
}

/// Why the viewer did not start, in the words the page shows (and reports to a test).
#[derive(Debug, thiserror::Error)]
enum StartError {
    #[error("{NO_WEBTRANSPORT}")]
    NoWebTransport,
    #[error(
        "No token in this page's address: open the URL roam-server printed (it ends in \
         #token=…)."
    )]
    NoToken,
    #[error(transparent)]
    Page(#[from] page::PageError),
    #[error(transparent)]
    Gfx(#[from] app::GfxError),
    /// The server refused the token (`why`: the join's words).
    #[error(
        "The server refused this viewer: wrong token. Open the URL roam-server printed, with \
         its #token=…, again ({why})"
    )]
    WrongToken { why: String },
    #[error("Could not join the server: {why}")]
    Join { why: String },
    #[error("script: {0}")]
    Script(roam_protocol::script::ScriptError),
    #[error(transparent)]
    Welcome(#[from] roam_client::conversation::ConversationError),
}

async fn run(options: page::Options) -> Result<(), StartError> {
    if !net::has_webtransport() {
        return Err(StartError::NoWebTransport);
    }
    if options.token.is_empty() {
        return Err(StartError::NoToken);
    }
    page::say("opening the GPU…", false);
    let canvas = page::canvas()?;
    let gfx = app::Gfx::open(canvas.clone(), &options.gpu).await?;
    page::say("connecting…", false);
    let mut endpoint = page::endpoint().await?;
    if let Some(port) = options.port {
        endpoint.port = port;
    }
    let size = app::pixel_size(&canvas);
    let budget = options.budget.unwrap_or(65_536);
    let hello = roam_client::conversation::hello(
        if options.spectator {
            Role::Spectator { follow: None }
        } else {
            Role::Driver
        },
        options.token.clone(),
        [size.0, size.1],
        60.0,
        budget,
        60,
        gfx.gpu.device.limits().max_texture_dimension_2d,
    );
    let edge = endpoint.edge()?;
    let mut joined = net::join(&edge, hello.clone(), supervisor::HANDSHAKE)
        .await
        .map_err(|e| {
            let why = e.message;
            if why.contains("wrong token") {
                StartError::WrongToken { why }
            } else {
                StartError::Join { why }
            }
        })?;
    let script = match &options.script {
        Some(text) => {
            let script = roam_protocol::script::parse(text).map_err(StartError::Script)?;
            let mut steps: Vec<_> = script.steps().collect();
            steps.reverse();
            Some(steps)
        }
        None => None,
    };
    let silence = options
        .silence_s
        .map_or(supervisor::SILENCE, web_time::Duration::from_secs_f64);
    let live = net::live(&mut joined, edge, budget, script, silence)?;
    let scene = roam_client::render::Scene::of(&joined.welcome);
    wasm_bindgen_futures::spawn_local(net::supervise(live.clone(), hello, joined));
    app::start(gfx, scene, live.clone(), options)
        .inspect_err(|e| live.borrow_mut().end(e))
        .map_err(StartError::Gfx)
}
