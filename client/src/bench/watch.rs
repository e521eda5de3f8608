//! `roam-client --replay FILE --data DIR --headless --bench`: what watching a recording
//! costs the one watching, measured on a real stream from the in-process server:
//!
//! - `open_ms`: from the start (before the recording is read) to the first frame
//!   decoded, the data set's loading included;
//! - `frames_per_second_8x`, `ticks_per_frame_8x_mean`: frames taken a second at 8×,
//!   over [`FAST_FRAMES`] frames, and how far the clock moved between them (8× at 60
//!   frames a second is 13.3 ticks);
//! - `seek_ms_median`, `seek_ms_max`: from a seek asked (to [`SEEKS`] moments spread over
//!   the recording in a fixed shuffled order, paused) to the first frame decoded showing
//!   that tick: the server's seek, the cut rebuilt there, the frame's trip and decoding.

use std::net::SocketAddr;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use roam_protocol::messages::{ReplayControl, ReplayStatus, Role};
use roam_protocol::stats::quantile;

use crate::session::{KeySource, Session, Taken};

/// Frames counted at 8×.
pub const FAST_FRAMES: usize = 600;

/// Seeks timed.
pub const SEEKS: u64 = 30;

/// Frames at most a seek waits for its tick (10 s at 60 a second).
const SEEK_FRAMES: usize = 600;

/// The next frame, decoded.
async fn frame(s: &Session) -> Result<crate::session::Received> {
    loop {
        match s.next_frame(true).await? {
            Taken::Frame(r) => return Ok(r),
            Taken::Nothing => {}
            Taken::Dropped(why) => bail!("a frame failed to decode: {why}"),
        }
    }
}

/// Runs the benchmark against the in-process server at `addr` serving a recording;
/// `started` is when the process began opening it.
pub async fn run(
    addr: SocketAddr,
    fingerprint: [u8; 32],
    (token, budget, size): (String, u32, (u32, u32)),
    started: Instant,
) -> Result<serde_json::Value> {
    let hello = crate::conversation::hello(
        Role::Spectator { follow: None },
        token,
        [size.0, size.1],
        60.0,
        budget,
        60,
        crate::render::native_max_texture(),
    );
    let s = Session::join(addr, fingerprint, hello, KeySource::None).await?;
    frame(&s).await?;
    let open_ms = started.elapsed().as_secs_f64() * 1e3;
    let mut changes = s.status_changes();
    let status: ReplayStatus = changes
        .wait_for(|st| st.replay.is_some())
        .await
        .context("the server's replay status")?
        .replay
        .clone()
        .expect("waited for");
    if !status.control {
        bail!("this viewer does not hold the replay's controls");
    }
    // 8×, from the start.
    s.replay_control(ReplayControl::Seek(status.start));
    s.replay_control(ReplayControl::Speed(32));
    let at_speed = changes
        .wait_for(|st| st.replay.as_ref().is_some_and(|r| r.speed == 32))
        .await
        .context("the speed taken")?
        .replay
        .clone();
    drop(at_speed);
    let mut ticks = Vec::new();
    let t0 = Instant::now();
    let mut last = frame(&s).await?.tick;
    let mut fast = 0;
    while fast < FAST_FRAMES {
        let f = frame(&s).await?;
        ticks.push(f.tick.saturating_sub(last) as f64);
        last = f.tick;
        fast += 1;
        if f.tick >= status.end {
            break;
        }
    }
    let fps = fast as f64 / t0.elapsed().as_secs_f64();
    // Seeks, paused: a spread of moments in a shuffled order.
    s.replay_control(ReplayControl::Pause);
    let span = status.end - status.start;
    let mut seeks = Vec::new();
    for k in 0..SEEKS {
        // A fixed permutation of the 30 evenly spread moments (7 is prime to 30).
        let target = status.start + span * ((k * 7) % SEEKS) / SEEKS + 37;
        let target = target.min(status.end);
        let asked = Instant::now();
        s.replay_control(ReplayControl::Seek(target));
        let mut landed = false;
        for _ in 0..SEEK_FRAMES {
            if frame(&s).await?.tick == target {
                landed = true;
                break;
            }
        }
        if !landed {
            bail!("a seek to tick {target} never showed");
        }
        seeks.push(asked.elapsed().as_secs_f64() * 1e3);
    }
    s.quit().await;
    Ok(serde_json::json!({
        "recording_ticks": span,
        "open_ms": open_ms,
        "frames_per_second_8x": fps,
        "ticks_per_frame_8x_mean": ticks.iter().sum::<f64>() / ticks.len().max(1) as f64,
        "seeks": seeks.len(),
        "seek_ms_median": quantile(&seeks, 0.5),
        "seek_ms_max": seeks.iter().copied().fold(0.0, f64::max),
    }))
}
