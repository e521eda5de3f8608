//! The browser viewer in a real browser: headless Chromium opens the page a test server
//! serves with `--web` (the page `scripts/build-web` built), joins over WebTransport with
//! the token from the URL's fragment, drives a script, decodes every frame against the
//! frame's own check (a mesh differing from the server's by one height or split fails it,
//! and counts as a decode error), and posts its numbers and a screenshot read back from
//! the canvas. Both GPU paths run: WebGPU and WebGL2 (SwiftShader, no GPU needed). A wrong
//! token, a browser without either GPU API and a server shutting down are said on the
//! page.

use roam_server::net::web::{WebCert, WebOptions};
use roam_tests::browser::{Browser, GpuPath, Image, REPORTS, built_page, next, numbers, reports};
use roam_tests::fixtures::{self, Running};
use serde_json::Value;

use crate::alone;

/// Frames the page decodes before it reports.
const FRAMES: u64 = 90;

/// A drive: throttle, then a long left turn (it lasts the whole test).
const SCRIPT: &str = "150 U\n3000 UL\n";

fn serve() -> Running {
    fixtures::serve(fixtures::kossou(), |o| roam_server::net::Options {
        web: Some(WebOptions {
            listen: "127.0.0.1:0".parse().expect("an address"),
            page: built_page(),
            cert: WebCert::Made {
                names: vec!["localhost".into(), "127.0.0.1".into()],
            },
        }),
        ..o
    })
}

/// Opens the page on `running` with `token`, the GPU path and a script, and returns what
/// it reported (its numbers, or the error it showed), with the browser still open.
async fn open(running: &Running, token: &str, gpu: GpuPath) -> (Value, Browser) {
    let (report, mut reports) = reports().await;
    let web = running.server.web_addr().expect("serving --web");
    let url = format!(
        "https://127.0.0.1:{}/#token={token}&gpu={}&frames={FRAMES}&report=http://{report}/report&script={}",
        web.port(),
        gpu.option(),
        SCRIPT.replace('\n', "%0A").replace(' ', "%20"),
    );
    let browser = Browser::open(&url, gpu);
    (next(&mut reports).await, browser)
}

/// The page joined, drove, decoded every frame and drew sky above terrain.
fn check_drive(running: &Running, r: &Value, gpu: GpuPath, backend: &str) {
    assert!(r.get("error").is_none(), "the page failed ({gpu:?}): {r}");
    let numbers = {
        let mut n = r.clone();
        n["png"] = Value::from("…");
        n
    };
    println!("{gpu:?}: {numbers}");
    assert_eq!(r["backend"], backend, "{numbers}");
    assert!(r["frames"].as_u64() >= Some(FRAMES), "{numbers}");
    assert_eq!(
        r["decode_errors"], 0,
        "every frame decodes to the server's mesh: {numbers}"
    );
    assert!(r["triangles"].as_u64() > Some(1000), "{numbers}");
    // Every frame is decoded in the display loop, which then draws: the page drew at least
    // one picture for each frame it decoded.
    assert!(
        r["drawn"].as_u64() >= r["frames"].as_u64(),
        "a picture drawn for each frame decoded: {numbers}"
    );
    assert!(r["first_frame_ms"].as_f64() > Some(0.0), "{numbers}");
    // The script drove the page's vehicle (the world's own record of it).
    let vehicle = r["vehicle"].as_u64().expect("the vehicle") as u16;
    let snap = running.server.snapshot();
    let v = snap
        .vehicles
        .iter()
        .find(|v| v.id == vehicle)
        .expect("the page's vehicle is in the world");
    assert!(
        v.state.speed > 1.0,
        "the script drove the vehicle: {:?}",
        v.state
    );

    let image = Image::from_data_url(r["png"].as_str().expect("a screenshot"))
        .expect("the screenshot is a PNG");
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"));
    image.write_png(&dir.join(format!("browser-{}.png", gpu.option())));
    assert!(
        image.width >= 100 && image.height >= 100,
        "{}×{}",
        image.width,
        image.height
    );
    let h = image.height;
    let (sky, sky_spread) = image.band(0, h / 10);
    let (ground, _) = image.band(h * 3 / 4, h);
    // Sky: blue over red, smooth. Terrain (the start faces land): far from the sky's
    // colour, and green over blue.
    assert!(sky[2] > sky[0] + 25.0, "the top is sky-blue: {sky:?}");
    assert!(sky_spread < 25.0, "the sky is smooth: {sky_spread}");
    let apart = (0..3)
        .map(|c| (sky[c] - ground[c]).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(apart > 30.0, "the bottom is not sky: {sky:?} vs {ground:?}");
    assert!(
        ground[1] > ground[2] + 10.0,
        "the bottom is land: {ground:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_drives_over_webgpu() {
    let _turn = alone().await;
    let running = serve();
    let (r, _browser) = open(&running, &running.token.clone(), GpuPath::WebGpu).await;
    check_drive(&running, &r, GpuPath::WebGpu, "BrowserWebGpu");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_drives_over_webgl2() {
    let _turn = alone().await;
    let running = serve();
    let (r, _browser) = open(&running, &running.token.clone(), GpuPath::WebGl2).await;
    check_drive(&running, &r, GpuPath::WebGl2, "Gl");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_token_is_refused_with_a_message_on_the_page() {
    let running = serve();
    let (r, _browser) = open(&running, "not-the-token", GpuPath::WebGl2).await;
    let error = r["error"]
        .as_str()
        .unwrap_or_else(|| panic!("an error: {r}"));
    assert!(error.contains("wrong token"), "{error}");
    assert_eq!(running.server.counts().refused, 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_browser_without_a_gpu_api_is_told_so_on_the_page() {
    let running = serve();
    let (r, _browser) = open(&running, &running.token.clone(), GpuPath::Neither).await;
    let error = r["error"]
        .as_str()
        .unwrap_or_else(|| panic!("an error: {r}"));
    assert!(error.contains("neither WebGPU nor WebGL2"), "{error}");
    assert_eq!(running.server.counts().joins, 0, "it never joined");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_says_why_when_the_server_goes_away() {
    let running = serve();
    let (report, mut reports) = reports().await;
    let web = running.server.web_addr().expect("serving --web");
    let url = format!(
        "https://127.0.0.1:{}/#token={}&gpu=webgl&frames=10&report=http://{report}/report",
        web.port(),
        running.token,
    );
    let _browser = Browser::open(&url, GpuPath::WebGl2);
    numbers(&mut reports).await;
    running.server.shutdown().await.expect("the server stops");
    let said = next(&mut reports).await;
    assert_eq!(said["state"], "ended", "{said}");
    let message = said["message"].as_str().expect("a message");
    assert!(message.contains("shutting down"), "{message}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_reconnects_after_its_path_drops_and_gets_its_vehicle_back() {
    use roam_tests::relay::{Relay, RelayConfig};
    let running = serve();
    let web = running.server.web_addr().expect("serving --web");
    // The page's WebTransport goes through a relay the test can cut (`port=`); the page
    // itself still loads from the server.
    let relay = Relay::start(web, RelayConfig::default())
        .await
        .expect("the relay starts");
    let (report, mut reports) = reports().await;
    let url = format!(
        "https://127.0.0.1:{}/#token={}&gpu=webgl&frames=10&silence=3&port={}&report=http://{report}/report",
        web.port(),
        running.token,
        relay.addr().port(),
    );
    let _browser = Browser::open(&url, GpuPath::WebGl2);
    let first = numbers(&mut reports).await;
    let vehicle = first["vehicle"].clone();
    relay.cut();
    let lost = next(&mut reports).await;
    assert_eq!(lost["state"], "reconnecting", "{lost}");
    assert!(
        lost["message"]
            .as_str()
            .is_some_and(|m| m.contains("silent")),
        "{lost}"
    );
    relay.restore();
    // Each attempt may say so first (the reports are separate requests).
    let mut back = next(&mut reports).await;
    for _ in 0..REPORTS {
        if back["state"] != "reconnecting" {
            break;
        }
        back = next(&mut reports).await;
    }
    assert_eq!(back["state"], "connected", "{back}");
    assert_eq!(back["reconnects"], 1, "{back}");
    assert_eq!(
        back["resumed"], 1,
        "the driver got its vehicle back: {back}"
    );
    assert_eq!(back["vehicle"], vehicle, "{back}");
    assert_eq!(running.server.counts().joins, 2);
}

/// A recording served (`serve --replay`) is watched in the page: the page's hello (a
/// driver's) is served as a spectator's, every frame decodes, the server's replay state
/// reaches the page (the first viewer holds the controls) and its HUD line says it, and the
/// frames show the recording's vehicles.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_watches_a_recording() {
    let _turn = alone().await;
    use roam_server::sim::physics::Keys;
    use roam_server::sim::recorder::RecordedWorld;
    use roam_server::sim::world::{self, Inputs, World};
    let terrain = fixtures::kossou();
    let mut w = World::new(terrain.clone());
    for id in 0..2 {
        w.add(id, world::start_state(&terrain, u32::from(id)))
            .expect("on the map");
    }
    let mut rec = RecordedWorld::start(w, Vec::new(), terrain.content_hash(), 100)
        .expect("memory does not fail");
    let mut inputs = Inputs::new();
    inputs.set(0, Keys::UP);
    inputs.set(1, Keys::UP.union(Keys::LEFT));
    const TICKS: u64 = 6000;
    for _ in 0..TICKS {
        rec.step(&inputs).expect("memory does not fail");
    }
    let (_, bytes) = rec.finish().expect("memory does not fail");
    let watch =
        roam_server::sim::watch::open_bytes(&bytes, terrain.clone(), &terrain.content_hash())
            .expect("opens");
    let running = fixtures::serve(terrain, |o| roam_server::net::Options {
        web: Some(WebOptions {
            listen: "127.0.0.1:0".parse().expect("an address"),
            page: built_page(),
            cert: WebCert::Made {
                names: vec!["localhost".into(), "127.0.0.1".into()],
            },
        }),
        replay: Some(roam_server::net::replay::Replaying {
            watch,
            control_token: None,
            follow: None,
        }),
        ..o
    });
    let (r, _browser) = open(&running, &running.token.clone(), GpuPath::WebGl2).await;
    assert!(r.get("error").is_none(), "the page failed: {r}");
    assert!(r["frames"].as_u64() >= Some(FRAMES), "{r}");
    assert_eq!(r["decode_errors"], 0, "{r}");
    assert!(r["vehicle"].as_u64() < Some(2), "a recorded vehicle: {r}");
    let replay = &r["replay"];
    assert_eq!(replay["start"], 0, "{r}");
    assert_eq!(replay["end"], TICKS, "{r}");
    assert_eq!(
        replay["control"], true,
        "the only viewer holds the controls: {r}"
    );
    let line = replay["line"].as_str().expect("the HUD's line");
    assert!(
        line.starts_with("replay 0:") && line.contains("/ 1:00.0"),
        "{line}"
    );
    assert!(r["tick"].as_u64() > Some(0), "the clock runs: {r}");
}
