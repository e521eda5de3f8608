//! What the browser tests need besides the server: the built page (`web/dist`, made by
//! `scripts/build-web`), headless Chromium (Debian's `chromium`) with the flags that give
//! it WebGPU or WebGL2 without a GPU (SwiftShader; `GpuPath::flags`), killed with its
//! whole process group when dropped, and a local HTTP endpoint the page posts its results
//! to (`--dump-dom` does not wait for GPU work). A missing browser or page fails the test
//! with the command that provides it.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;

use roam_server::web::Page;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::mpsc;

/// The page's files as `scripts/build-web` left them in `web/dist`.
pub fn built_page() -> Arc<Page> {
    let dist = Path::new(env!("CARGO_MANIFEST_DIR")).join("../web/dist");
    let page = Page::read_dir(&dist).unwrap_or_else(|e| {
        panic!(
            "{}: {e}: build the browser viewer first with scripts/build-web --quick",
            dist.display()
        )
    });
    assert!(
        page.get("index.html").is_some() && page.get("roam_web_bg.wasm").is_some(),
        "{} is incomplete: run scripts/build-web --quick",
        dist.display()
    );
    Arc::new(page)
}

/// Which GPU path the page takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GpuPath {
    WebGpu,
    WebGl2,
    /// A browser with both GPU APIs off (`--disable-3d-apis`): the page must say so.
    Neither,
}

impl GpuPath {
    /// The page's `gpu=` option.
    pub fn option(self) -> &'static str {
        match self {
            GpuPath::WebGpu => "webgpu",
            GpuPath::WebGl2 => "webgl",
            GpuPath::Neither => "",
        }
    }

    /// Chromium's flags for it on a machine without a GPU (SwiftShader).
    fn flags(self) -> &'static [&'static str] {
        match self {
            GpuPath::WebGpu => &[
                "--enable-unsafe-webgpu",
                "--enable-features=Vulkan",
                "--use-vulkan=swiftshader",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
            ],
            GpuPath::WebGl2 => &["--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
            GpuPath::Neither => &["--disable-3d-apis"],
        }
    }
}

/// Headless Chromium on a page, killed (with every process it started) when dropped.
pub struct Browser {
    child: Child,
    _profile: TempDir,
}

impl Browser {
    /// Opens `url` in a fresh profile.
    pub fn open(url: &str, gpu: GpuPath) -> Browser {
        let exe = std::env::var_os("ROAM_CHROMIUM")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("/usr/bin/chromium"));
        assert!(
            exe.exists(),
            "{} is missing: the browser tests need Debian's chromium (apt-get install -y \
             chromium), or ROAM_CHROMIUM naming another Chromium",
            exe.display()
        );
        let profile = TempDir::new("roam-chromium");
        let mut cmd = Command::new(&exe);
        cmd.args([
            "--headless=new",
            "--no-sandbox",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-default-apps",
            // The page's certificate is the server's own, made for this run; WebTransport
            // still checks its hash (serverCertificateHashes).
            "--ignore-certificate-errors",
            "--window-size=640,400",
        ])
        .arg(format!("--user-data-dir={}", profile.0.display()))
        .args(gpu.flags())
        .arg(url)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null());
        // ROAM_BROWSER_LOG=1: the browser's log, the page's console included, on stderr.
        if std::env::var_os("ROAM_BROWSER_LOG").is_some() {
            cmd.arg("--enable-logging=stderr").stderr(Stdio::inherit());
        }
        std::os::unix::process::CommandExt::process_group(&mut cmd, 0);
        let child = cmd.spawn().expect("starting chromium");
        Browser {
            child,
            _profile: profile,
        }
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        // The whole group: the browser's GPU, renderer and network processes too.
        let _ = Command::new("kill")
            .args(["-KILL", "--", &format!("-{}", self.child.id())])
            .status();
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A directory removed when dropped.
struct TempDir(PathBuf);

impl TempDir {
    fn new(prefix: &str) -> TempDir {
        use std::sync::atomic::{AtomicU32, Ordering};
        static N: AtomicU32 = AtomicU32::new(0);
        let dir = std::env::temp_dir().join(format!(
            "{prefix}-{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).expect("making a temporary directory");
        TempDir(dir)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The most a report may be (a screenshot as a data URL included).
const MAX_REPORT: usize = 32 << 20;

/// A bound on the wait for the page's report: a regression fails, never hangs (a page on
/// SwiftShader takes seconds).
pub const REPORT_WITHIN: std::time::Duration = std::time::Duration::from_secs(150);

/// The page's next report.
pub async fn next(reports: &mut mpsc::UnboundedReceiver<String>) -> serde_json::Value {
    let body = tokio::time::timeout(REPORT_WITHIN, reports.recv())
        .await
        .unwrap_or_else(|_| panic!("no report from the page within {REPORT_WITHIN:?}"))
        .expect("the report endpoint runs");
    serde_json::from_str(&body).expect("the page reports JSON")
}

/// Reports a wait may pass over before it fails (the page posts one for each change of its
/// state, a few in a run).
pub const REPORTS: usize = 50;

/// The page's numbers, after any state report before them (an error fails, and so do
/// [`REPORTS`] reports without the numbers).
pub async fn numbers(reports: &mut mpsc::UnboundedReceiver<String>) -> serde_json::Value {
    for _ in 0..REPORTS {
        let r = next(reports).await;
        if r.get("frames").is_some() {
            return r;
        }
        assert!(r.get("error").is_none(), "{r}");
    }
    panic!("no numbers from the page in {REPORTS} reports");
}

/// A local HTTP endpoint taking POSTed bodies (as text/plain, so without a CORS
/// preflight); each body comes out of the receiver.
pub async fn reports() -> (SocketAddr, mpsc::UnboundedReceiver<String>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("binding the report endpoint");
    let addr = listener.local_addr().expect("a bound address");
    let (tx, rx) = mpsc::unbounded_channel();
    tokio::spawn(async move {
        while let Ok((mut tcp, _)) = listener.accept().await {
            let tx = tx.clone();
            tokio::spawn(async move {
                if let Some(body) = read_post(&mut tcp).await {
                    let _ = tx.send(body);
                }
                let _ = tcp
                    .write_all(
                        b"HTTP/1.1 204 No Content\r\nAccess-Control-Allow-Origin: *\r\n\
                          Connection: close\r\n\r\n",
                    )
                    .await;
            });
        }
    });
    (addr, rx)
}

/// A POST's body, if the request is one within [`MAX_REPORT`].
async fn read_post(tcp: &mut tokio::net::TcpStream) -> Option<String> {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 64 << 10];
    let head_end = loop {
        let n = tcp.read(&mut chunk).await.ok()?;
        if n == 0 || buf.len() + n > MAX_REPORT {
            return None;
        }
        buf.extend_from_slice(&chunk[..n]);
        if let Some(i) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break i + 4;
        }
    };
    let head = String::from_utf8_lossy(&buf[..head_end]).to_ascii_lowercase();
    if !head.starts_with("post ") {
        return None;
    }
    let len: usize = head
        .lines()
        .find_map(|l| l.strip_prefix("content-length:"))
        .and_then(|v| v.trim().parse().ok())?;
    if len > MAX_REPORT {
        return None;
    }
    while buf.len() < head_end + len {
        let n = tcp.read(&mut chunk).await.ok()?;
        if n == 0 {
            return None;
        }
        buf.extend_from_slice(&chunk[..n]);
    }
    String::from_utf8(buf[head_end..head_end + len].to_vec()).ok()
}

/// Why a screenshot's data URL is no RGBA image.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// Not `data:image/png;base64,…` (`start`: its first 40 characters).
    #[error("not a PNG data URL: {start}")]
    NotDataUrl { start: String },
    #[error("the PNG's base64: {0}")]
    Base64(base64::DecodeError),
    #[error(transparent)]
    Png(#[from] png::DecodingError),
    #[error("an image too large")]
    TooLarge,
    /// Decoded as another colour type than RGBA.
    #[error("a PNG of {0:?}")]
    ColorType(png::ColorType),
}

/// An RGBA image.
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub rgba: Vec<u8>,
}

impl Image {
    /// A `data:image/png;base64,…` URL's picture.
    pub fn from_data_url(url: &str) -> Result<Image, ImageError> {
        let b64 =
            url.strip_prefix("data:image/png;base64,")
                .ok_or_else(|| ImageError::NotDataUrl {
                    start: url.chars().take(40).collect(),
                })?;
        use base64::Engine;
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(b64)
            .map_err(ImageError::Base64)?;
        let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::ALPHA);
        let mut reader = decoder.read_info()?;
        let mut rgba = vec![0; reader.output_buffer_size().ok_or(ImageError::TooLarge)?];
        let info = reader.next_frame(&mut rgba)?;
        if info.color_type != png::ColorType::Rgba {
            return Err(ImageError::ColorType(info.color_type));
        }
        rgba.truncate(info.buffer_size());
        Ok(Image {
            width: info.width as usize,
            height: info.height as usize,
            rgba,
        })
    }

    /// The mean colour (RGB) of rows `from..to`, and its spread (the mean distance of the
    /// pixels from it).
    pub fn band(&self, from: usize, to: usize) -> ([f64; 3], f64) {
        let px = |i: usize| {
            let p = &self.rgba[i * 4..i * 4 + 3];
            [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])]
        };
        let range = from * self.width..to * self.width;
        let n = range.len().max(1) as f64;
        let mut mean = [0.0; 3];
        for i in range.clone() {
            let p = px(i);
            (0..3).for_each(|c| mean[c] += p[c] / n);
        }
        let spread = range
            .map(|i| {
                let p = px(i);
                (0..3).map(|c| (p[c] - mean[c]).powi(2)).sum::<f64>().sqrt()
            })
            .sum::<f64>()
            / n;
        (mean, spread)
    }

    pub fn write_png(&self, path: &Path) {
        let file = std::fs::File::create(path).expect("creating the screenshot");
        let mut enc = png::Encoder::new(file, self.width as u32, self.height as u32);
        enc.set_color(png::ColorType::Rgba);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().expect("a PNG header");
        w.write_image_data(&self.rgba).expect("the PNG's pixels");
    }
}

#[cfg(test)]
mod tests {
    use base64::Engine;

    use super::{Image, ImageError};

    /// A `width × height` PNG of `color` pixels, `data`, as a data URL.
    fn data_url(width: u32, height: u32, color: png::ColorType, data: &[u8]) -> String {
        let mut png = Vec::new();
        let mut enc = png::Encoder::new(&mut png, width, height);
        enc.set_color(color);
        let mut w = enc.write_header().expect("a header in memory");
        w.write_image_data(data).expect("the pixels in memory");
        w.finish().expect("the end in memory");
        let b64 = base64::engine::general_purpose::STANDARD.encode(png);
        format!("data:image/png;base64,{b64}")
    }

    /// A screenshot's URL is read as RGBA, or refused naming what it is instead.
    #[test]
    fn a_data_url_is_an_rgba_image_or_says_what_it_is() {
        let rgba = data_url(2, 1, png::ColorType::Rgba, &[1, 2, 3, 255, 4, 5, 6, 255]);
        let image = Image::from_data_url(&rgba).expect("an RGBA PNG");
        assert_eq!((image.width, image.height), (2, 1));
        assert_eq!(image.rgba, [1, 2, 3, 255, 4, 5, 6, 255]);
        let long = format!("data:text/plain,{}", "x".repeat(100));
        let grey = data_url(1, 1, png::ColorType::Grayscale, &[9]);
        let not_png = "data:image/png;base64,aGVsbG8=";
        let kind = |e: &ImageError| match e {
            ImageError::NotDataUrl { .. } => "not a data URL",
            ImageError::Base64(_) => "base64",
            ImageError::Png(_) => "PNG",
            ImageError::TooLarge => "too large",
            ImageError::ColorType(_) => "colour type",
        };
        let cases = [
            (
                &*long,
                "not a data URL",
                "not a PNG data URL: data:text/plain,xxxxxxxxxxxxxxxxxxxxxxxx",
            ),
            ("data:image/png;base64,!!", "base64", "the PNG's base64: "),
            (not_png, "PNG", ""),
            (&*grey, "colour type", "a PNG of GrayscaleAlpha"),
        ];
        for (url, want, words) in cases {
            let Err(e) = Image::from_data_url(url) else {
                panic!("{url:.60}: an image")
            };
            assert_eq!(kind(&e), want, "{url:.60}: {e:?}");
            assert!(e.to_string().starts_with(words), "{url:.60}: {e}");
        }
    }
}
