//! `roam-client --headless --bench`: the viewer's own costs per frame, measured on a real
//! stream: decoding (with mesh emission), building the vertices, uploading them, and
//! drawing a frame offscreen (waiting for the GPU to finish), at the window's size. The
//! upload includes the colour tiles that arrived (at most the window's per-frame number).

use std::net::SocketAddr;
use std::time::Instant;

use anyhow::Result;
use roam_protocol::messages::{DEFAULT_PITCH_DEG, Hello, Role, VERSION};
use roam_protocol::script::Script;
use roam_protocol::stats::quantile;

use crate::render::{Gpu, Renderer, TerrainVertices, Toggles, View};
use crate::session::{KeySource, Session, Taken};

/// Colour tiles uploaded a frame at most (as the window does).
const MAX_UPLOADS: usize = crate::window::MAX_UPLOADS;

/// What to measure.
#[derive(Clone, Debug)]
pub struct Options {
    pub token: String,
    pub budget: u32,
    pub frames: u64,
    pub size: (u32, u32),
    pub fov_y_deg: f32,
    pub toggles: Toggles,
    /// Keys to drive with (the server's benchmark drive by default).
    pub inputs: Script,
}

/// Runs the benchmark and returns its JSON report.
pub async fn run(
    addr: SocketAddr,
    fingerprint: [u8; 32],
    opts: Options,
) -> Result<serde_json::Value> {
    let hello = Hello {
        version: VERSION,
        role: Role::Driver,
        token: opts.token.clone(),
        viewport: [opts.size.0, opts.size.1],
        fov_y_deg: opts.fov_y_deg,
        budget: opts.budget,
        frame_rate: 60,
        resume: None,
        // The device opened below has wgpu's default limits (it asks for them).
        color_window: crate::color_cache::window_for(
            wgpu::Limits::default().max_texture_dimension_2d,
        ),
    };
    let session = Session::join(
        addr,
        fingerprint,
        hello,
        KeySource::Script(opts.inputs.clone()),
    )
    .await?;
    let gpu = Gpu::headless()?;
    let format = wgpu::TextureFormat::Rgba8UnormSrgb;
    let mut renderer = Renderer::new(&gpu, format, session.scene.clone());
    let target = gpu.device.create_texture(&wgpu::TextureDescriptor {
        label: Some("bench target"),
        size: wgpu::Extent3d {
            width: opts.size.0,
            height: opts.size.1,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
        view_formats: &[],
    });
    let target = target.create_view(&Default::default());
    let wait = |gpu: &Gpu| {
        gpu.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
    };
    let (mut decode, mut build, mut upload, mut draw, mut tris) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut vertices = TerrainVertices::default();
    let mut frames = 0u64;
    while frames < opts.frames {
        let r = match session.next_frame(true).await? {
            Taken::Nothing | Taken::Dropped(_) => continue,
            Taken::Frame(r) => r,
        };
        frames += 1;
        let t0 = Instant::now();
        session
            .core()
            .update_vertices(&session.scene, &mut vertices);
        let t1 = Instant::now();
        renderer.upload_dirty(&gpu, &mut vertices);
        let colors = session.colors().drain(MAX_UPLOADS);
        renderer.update_colors(&gpu, &colors);
        gpu.queue.submit([]);
        wait(&gpu)?;
        let t2 = Instant::now();
        let me = session.vehicle();
        let Some(v) = r.vehicles.iter().find(|v| v.id == me) else {
            continue;
        };
        let view = View {
            eye: [v.x as f32, v.y as f32 + 1.5, v.z as f32],
            yaw_deg: v.heading as f32,
            pitch_deg: DEFAULT_PITCH_DEG as f32,
            fov_y_deg: opts.fov_y_deg,
            time_s: frames as f32 / 60.0,
        };
        renderer.render(&gpu, &target, opts.size, &view, opts.toggles);
        wait(&gpu)?;
        let t3 = Instant::now();
        // The first frames warm caches and compile pipelines: measured, not reported.
        if frames > 5 {
            decode.push(r.decode_s * 1e3);
            build.push((t1 - t0).as_secs_f64() * 1e3);
            upload.push((t2 - t1).as_secs_f64() * 1e3);
            draw.push((t3 - t2).as_secs_f64() * 1e3);
            tris.push(r.triangles as f64);
        }
    }
    session.quit().await;
    let per_frame: Vec<f64> = (0..decode.len())
        .map(|i| decode[i] + build[i] + upload[i])
        .collect();
    let median = |v: &[f64]| quantile(v, 0.5);
    Ok(serde_json::json!({
        "adapter": format!("{} ({:?})", gpu.adapter.name, gpu.adapter.backend),
        "width": opts.size.0,
        "height": opts.size.1,
        "frames_measured": draw.len(),
        "triangles_median": median(&tris),
        "frame_ms_median": median(&draw),
        "frame_ms_p99": quantile(&draw, 0.99),
        "decode_ms_median": median(&decode),
        "build_vertices_ms_median": median(&build),
        "upload_ms_median": median(&upload),
        "decode_and_upload_ms_median": median(&per_frame),
        "decode_and_upload_ms_p99": quantile(&per_frame, 0.99),
    }))
}
