//! `roam-client --headless --bench`: the viewer's own costs per frame, measured on a real
//! stream (decoding with mesh emission, building the vertices (geomorphs included),
//! uploading them, and drawing a frame offscreen, waiting for the GPU, at the window's
//! size; the upload includes the colour tiles that arrived, at most the window's
//! per-frame number), and what the level of detail's changes show ([`lod`]).
//!
//! **Every frame, however slow the drawing** (issue 24): the frames are taken and decoded
//! as they come, 60 a second, and the drawn meshes' changes, colour uploads and cameras
//! kept; they are drawn afterwards. So each pair of consecutive frames t → t+1 is
//! measured as the server sent it, the morphs advancing by the frames' ticks: the
//! figures do not depend on how fast this machine renders. A pair with a frame missing
//! between (taken late and superseded) is not measured, and counted
//! (`frames_skipped`).
//!
//! Each pair is drawn twice from t+1's camera, with t's drawn mesh and with t+1's (same
//! colour tiles), and once with no terrain (the sky, to tell the terrain's pixels):
//! `lod_luma_diff_p99`. `pop_px_p99`/`pop_px_max` are computed from the two drawn cuts
//! ([`lod::pop_px`]). `frame_ms_*` time the drawing of t+1's mesh alone, as before.

mod fogged;
mod lod;
pub mod watch;

pub use fogged::Truth;

use std::net::SocketAddr;
use std::time::Instant;

use anyhow::Result;
use roam_protocol::messages::{DEFAULT_PITCH_DEG, Role, VehicleView};
use roam_protocol::script::Script;
use roam_protocol::stats::quantile;

use crate::color_cache::ColorUpdate;
use crate::render::{
    self, Gpu, Morph, MorphView, Renderer, TerrainUpdate, TerrainVertices, Toggles, View,
};
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
    /// Geomorphs' length, ticks (0: none, today's viewer before issue 24).
    pub morph_ticks: u16,
    /// The data set served (a `--local` server's), for `fogged_error_px_*`.
    pub truth: Option<Truth>,
}

/// A frame taken, as the drawing pass needs it.
struct Recorded {
    frame: u64,
    view: View,
    /// The viewer's vehicle, and the diamonds the frame toggled (with their heights).
    vehicle: VehicleView,
    toggled: Vec<(u32, u16)>,
    terrain: TerrainUpdate,
    colors: ColorUpdate,
}

/// Runs the benchmark and returns its JSON report.
pub async fn run(
    addr: SocketAddr,
    fingerprint: [u8; 32],
    opts: Options,
) -> Result<serde_json::Value> {
    // The device opened below has wgpu's default limits (it asks for them).
    let hello = crate::conversation::hello(
        Role::Driver,
        opts.token.clone(),
        [opts.size.0, opts.size.1],
        opts.fov_y_deg,
        opts.budget,
        60,
        crate::render::native_max_texture(),
    );
    let mut fogged = opts
        .truth
        .clone()
        .map(|t| fogged::FoggedError::new(t, &hello));
    let session = Session::join(
        addr,
        fingerprint,
        hello,
        KeySource::Script(opts.inputs.clone()),
    )
    .await?;
    session.set_morph(opts.morph_ticks);
    // Taking: every frame decoded and followed, nothing drawn.
    let (mut decode, mut build, mut tris, mut pops) = (vec![], vec![], vec![], vec![]);
    let mut recorded: Vec<Recorded> = Vec::new();
    let mut vertices = TerrainVertices::default();
    let mut before: Option<(u64, Morph)> = None;
    let mut skipped = 0u64;
    let mut carry: Vec<(u32, u16)> = Vec::new();
    let mut bytes = 0usize;
    while (recorded.len() as u64) < opts.frames {
        let r = match session.next_frame(true).await? {
            Taken::Nothing | Taken::Dropped(_) => continue,
            Taken::Frame(r) => r,
        };
        let me = session.vehicle();
        let vehicle = r.vehicles.iter().find(|v| v.id == me).copied();
        let view = vehicle.map(|v| View {
            eye: [
                v.x as f32,
                (v.y + crate::camera::EYE_ABOVE_VEHICLE) as f32,
                v.z as f32,
            ],
            yaw_deg: v.heading as f32,
            pitch_deg: DEFAULT_PITCH_DEG as f32,
            fov_y_deg: opts.fov_y_deg,
            time_s: recorded.len() as f32 / 60.0,
        });
        let seen = view.map(|v| MorphView::new(&session.scene, v.eye, v.fov_y_deg, opts.size.1));
        let t0 = Instant::now();
        {
            let mut core = session.core();
            core.set_morph_view(seen);
            core.update_vertices(&session.scene, &mut vertices);
        }
        let t1 = Instant::now();
        // The cut's changes, carried to the next frame recorded when this one is not.
        carry.extend_from_slice(session.core().cut().toggled_heights());
        let (Some(view), Some(vehicle)) = (view, vehicle) else {
            continue; // not seated yet: nothing to look from
        };
        let core = session.core();
        let drawn = core
            .morph()
            .expect("set above: the cut is drawn through a morph");
        if let Some((frame, ref old)) = before {
            if frame + 1 == r.frame {
                let cut = core.cut();
                let vp = lod::view_proj(&view, opts.size);
                pops.push(f64::from(lod::pop_px(
                    &session.scene,
                    old,
                    drawn,
                    |i| cut.height(i),
                    &vp,
                    opts.size,
                )));
            } else {
                skipped += r.frame.saturating_sub(frame + 1);
            }
        }
        bytes = bytes.max(drawn.bytes());
        before = Some((r.frame, drawn.clone()));
        drop(core);
        // The first frames warm caches: measured, not reported.
        if recorded.len() > 5 {
            decode.push(r.decode_s * 1e3);
            build.push((t1 - t0).as_secs_f64() * 1e3);
            tris.push(r.triangles as f64);
        }
        let toggled = std::mem::take(&mut carry);
        recorded.push(Recorded {
            frame: r.frame,
            view,
            vehicle,
            toggled,
            terrain: vertices.take_update(),
            colors: session.colors().drain(MAX_UPLOADS),
        });
    }
    session.quit().await;
    // The fogged error of each frame's cut (slow: a walk of the cut a frame).
    let mut fog = Vec::new();
    if let Some(f) = fogged.as_mut() {
        for (k, r) in recorded.iter().enumerate() {
            let e = f.frame(&r.toggled, &r.vehicle);
            if k > 5 {
                fog.push(f64::from(e));
            }
        }
    }
    // Drawing: `now` has each frame's mesh, `then` the one before.
    let gpu = Gpu::headless()?;
    let format = wgpu::TextureFormat::Rgba8UnormSrgb;
    let mut now = Renderer::new(&gpu, format, session.scene.clone());
    let mut then = Renderer::new(&gpu, format, session.scene.clone());
    let mut sky = Renderer::new(&gpu, format, session.scene.clone());
    let target = render::target_texture(
        &gpu,
        "bench target",
        opts.size,
        format,
        wgpu::TextureUsages::empty(),
    );
    let target = target.create_view(&Default::default());
    let wait = |gpu: &Gpu| {
        gpu.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
    };
    let (mut upload, mut draw, mut luma) = (vec![], vec![], vec![]);
    let toggles = Toggles {
        vehicles: false,
        ..opts.toggles
    };
    for (k, f) in recorded.iter().enumerate() {
        // The three renderers keep one clock, so a tile's normals fade alike in each.
        for r in [&mut now, &mut then, &mut sky] {
            r.set_time(&gpu, f.view.time_s);
        }
        let t0 = Instant::now();
        now.apply(&gpu, &f.terrain);
        now.update_colors(&gpu, &f.colors);
        gpu.queue.submit([]);
        wait(&gpu)?;
        let t1 = Instant::now();
        now.render(&gpu, &target, opts.size, &f.view, toggles);
        wait(&gpu)?;
        let t2 = Instant::now();
        then.update_colors(&gpu, &f.colors);
        sky.update_colors(&gpu, &f.colors);
        if k > 0 && recorded[k - 1].frame + 1 == f.frame {
            let b = render::render_offscreen(&gpu, &mut now, opts.size, &f.view, toggles)?;
            let a = render::render_offscreen(&gpu, &mut then, opts.size, &f.view, toggles)?;
            let s = render::render_offscreen(&gpu, &mut sky, opts.size, &f.view, toggles)?;
            luma.push(lod::luma_diff(&a, &b, &s));
        }
        then.apply(&gpu, &f.terrain);
        if k > 5 {
            upload.push((t1 - t0).as_secs_f64() * 1e3);
            draw.push((t2 - t1).as_secs_f64() * 1e3);
        }
    }
    let per_frame: Vec<f64> = (0..decode.len().min(upload.len()))
        .map(|i| decode[i] + build[i] + upload[i])
        .collect();
    let median = |v: &[f64]| quantile(v, 0.5);
    Ok(serde_json::json!({
        "adapter": format!("{} ({:?})", gpu.adapter.name, gpu.adapter.backend),
        "width": opts.size.0,
        "height": opts.size.1,
        "morph_ticks": opts.morph_ticks,
        "frames_measured": draw.len(),
        "frames_skipped": skipped,
        "pairs_measured": pops.len(),
        "triangles_median": median(&tris),
        "frame_ms_median": median(&draw),
        "frame_ms_p99": quantile(&draw, 0.99),
        "decode_ms_median": median(&decode),
        "build_vertices_ms_median": median(&build),
        "upload_ms_median": median(&upload),
        "decode_and_upload_ms_median": median(&per_frame),
        "decode_and_upload_ms_p99": quantile(&per_frame, 0.99),
        "pop_px_p99": quantile(&pops, 0.99),
        "pop_px_max": pops.iter().copied().fold(0.0, f64::max),
        "lod_luma_diff_p99": quantile(&luma, 0.99),
        "lod_luma_diff_median": median(&luma),
        "lod_luma_diff_mean": luma.iter().sum::<f64>() / luma.len().max(1) as f64,
        "drawn_cut_bytes_max": bytes,
        "fogged_error_px_p99": (!fog.is_empty()).then(|| quantile(&fog, 0.99)),
        "fogged_error_px_median": (!fog.is_empty()).then(|| median(&fog)),
    }))
}
