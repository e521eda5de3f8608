//! The stats a headless run writes (`--stats OUT.json`).

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
    let made: Vec<f64> = viewers
        .iter()
        .map(|s| {
            let span = s
                .first_frame
                .map_or(0, |f| s.last_frame.saturating_sub(f) + 1);
            span as f64 / s.seconds.max(1e-9)
        })
        .collect();
    let latencies = all(&|s| s.latencies_ms.clone());
    serde_json::json!({
        "viewers": viewers.len(),
        "frames": frames,
        "frames_per_second": fps.iter().sum::<f64>() / fps.len().max(1) as f64,
        "frames_per_second_min": fps.iter().copied().fold(f64::INFINITY, f64::min),
        "frames_sent_per_second_min": made.iter().copied().fold(f64::INFINITY, f64::min),
        "first_frame_after_join_ms_max": viewers.iter().map(|s| s.first_frame_s * 1e3).fold(0.0, f64::max),
        "wire_bytes_per_triangle_first": quantile(&all(&|s| s.first.into_iter().collect()), 0.5),
        "wire_bytes_per_triangle_steady": quantile(&all(&|s| s.steady.clone()), 0.5),
        "input_to_frame_ms_median": quantile(&latencies, 0.5),
        "input_to_frame_ms_p99": quantile(&latencies, 0.99),
        "decode_errors": viewers.iter().map(|s| s.decode_errors).sum::<u64>(),
        "max_triangles": viewers.iter().map(|s| s.max_triangles).max().unwrap_or(0),
    })
}
