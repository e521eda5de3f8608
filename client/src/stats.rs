//! The stats a headless run writes (`--stats OUT.json`). Every key scripts read stays as it
//! is; the reconnection keys are `reconnects` (connections made again after a loss, every
//! viewer's), `resumed` (of those, the drivers' that got their vehicle back: equal to
//! `reconnects` when every one did), `gap_ms_max` (the longest time between two frames,
//! a reconnection's included), `budget_served_min` (the smallest budget served: asked, or
//! the server's most if less) and `errors` (viewers whose session ended early). The colour
//! keys: `color_bytes` (colour tile bytes received, every viewer's), `color_tiles` (the
//! fewest tiles resident at the end, of any viewer) and `color_capacity` (the most a
//! viewer holds). The keys of a world served by edges: `edges_learned` (the most
//! addresses one viewer learned from the edges' lists) and `world_gone_s` (the longest
//! time one viewer's edge said its world was gone, in all).
//!
//! The load generator's keys (`scripts/capacity.sh` reads them): `frames_per_second_min`
//! (the slowest viewer's frames taken a second, from its first frame to its last),
//! `frames_sent_per_second_min` (the slowest viewer's frames the server made a second over
//! the same span: the frame numbers say how many were made), `frames_sent` and
//! `frames_lost` (made and not taken: lost on the way, or superseded by a newer frame
//! before the viewer took it; every viewer's), `gap_ms_max` (after each viewer's first
//! frame: joining is `first_frame_after_join_ms_max`), `streaming_s_max` (the longest
//! first-to-last-frame span).

use crate::headless::ViewerStats;

use roam_protocol::stats::quantile;

/// The JSON report over every viewer of a run.
pub fn report(viewers: &[ViewerStats]) -> serde_json::Value {
    let all =
        |f: &dyn Fn(&ViewerStats) -> Vec<f64>| -> Vec<f64> { viewers.iter().flat_map(f).collect() };
    let frames: u64 = viewers.iter().map(|s| s.frames).sum();
    // Frames after the first, over the time from the first to the last: the rate frames
    // arrive at once streaming (joining is reported apart).
    let fps: Vec<f64> = viewers
        .iter()
        .map(|s| s.frames.saturating_sub(1) as f64 / s.streaming_s.max(1e-9))
        .collect();
    // Over the same span as `fps` (before: over the whole session, joining included).
    let made: Vec<f64> = viewers
        .iter()
        .map(|s| s.made().saturating_sub(1) as f64 / s.streaming_s.max(1e-9))
        .collect();
    let sent: u64 = viewers.iter().map(|s| s.made()).sum();
    let latencies = all(&|s| s.latencies_ms.clone());
    serde_json::json!({
        "viewers": viewers.len(),
        "frames": frames,
        "frames_per_second": fps.iter().sum::<f64>() / fps.len().max(1) as f64,
        "frames_per_second_min": fps.iter().copied().fold(f64::INFINITY, f64::min),
        "frames_sent_per_second_min": made.iter().copied().fold(f64::INFINITY, f64::min),
        "frames_sent": sent,
        "frames_lost": sent.saturating_sub(frames),
        "streaming_s_max": viewers.iter().map(|s| s.streaming_s).fold(0.0, f64::max),
        "first_frame_after_join_ms_max": viewers.iter().map(|s| s.first_frame_s * 1e3).fold(0.0, f64::max),
        "wire_bytes_per_triangle_first": quantile(&all(&|s| s.first.into_iter().collect()), 0.5),
        "wire_bytes_per_triangle_steady": quantile(&all(&|s| s.steady.clone()), 0.5),
        "input_to_frame_ms_median": quantile(&latencies, 0.5),
        "input_to_frame_ms_p99": quantile(&latencies, 0.99),
        "decode_errors": viewers.iter().map(|s| s.decode_errors).sum::<u64>(),
        "max_triangles": viewers.iter().map(|s| s.max_triangles).max().unwrap_or(0),
        "vehicles_max": viewers.iter().map(|s| s.vehicles_max).max().unwrap_or(0),
        "budget_served_min": viewers.iter().map(|s| s.budget_served).min().unwrap_or(0),
        "reconnects": viewers.iter().map(|s| s.reconnects).sum::<u32>(),
        "resumed": viewers.iter().map(|s| s.resumed).sum::<u32>(),
        "gap_ms_max": viewers.iter().map(|s| s.gap_max_s * 1e3).fold(0.0, f64::max),
        "errors": viewers.iter().filter(|s| s.error.is_some()).count(),
        "color_bytes": viewers.iter().map(|s| s.color_bytes).sum::<u64>(),
        "color_tiles": viewers.iter().map(|s| s.color_tiles).min().unwrap_or(0),
        "color_capacity": viewers.iter().map(|s| s.color_capacity).max().unwrap_or(0),
        "edges_learned": viewers.iter().map(|s| s.edges_learned).max().unwrap_or(0),
        "world_gone_s": viewers.iter().map(|s| s.world_gone_s).fold(0.0, f64::max),
    })
}
