//! The congestion controller both ends use: quinn's Cubic with a floor under its window.
//!
//! A roam connection is application-limited (a few hundred bytes a frame) and
//! latency-bound, with bursts: a key frame (tens of kilobytes at the usual budgets) must
//! leave within a frame or two. Cubic (quinn's default) cuts its window by 30% at each
//! loss, and on a path that loses packets at random (Wi-Fi, mobile) it sits at its
//! minimum, two packets; it does not grow back while the sender is application-limited.
//! A key frame then takes many round trips to leave. The floor keeps a window that
//! carries a key frame in one round trip; above it, Cubic reacts to congestion as usual.

use std::any::Any;
use std::sync::Arc;
use std::time::Instant;

use quinn::congestion::{Controller, ControllerFactory, ControllerMetrics, CubicConfig};
use quinn_proto::RttEstimator;

/// The least congestion window, bytes: a key frame at 65,536 triangles (about 24 kB) and
/// the frames around it in one round trip. At an 80 ms round trip it allows 800 kB/s.
pub const MIN_WINDOW: u64 = 64 << 10;

/// Builds [`Floored`] Cubic controllers.
#[derive(Debug)]
pub struct FlooredCubic {
    pub floor: u64,
}

impl ControllerFactory for FlooredCubic {
    fn build(self: Arc<Self>, now: Instant, current_mtu: u16) -> Box<dyn Controller> {
        let mut cubic = CubicConfig::default();
        cubic.initial_window(self.floor);
        Box::new(Floored {
            inner: Arc::new(cubic).build(now, current_mtu),
            floor: self.floor,
        })
    }
}

/// A controller whose window never falls below `floor`.
pub struct Floored {
    inner: Box<dyn Controller>,
    floor: u64,
}

impl Controller for Floored {
    fn on_sent(&mut self, now: Instant, bytes: u64, last_packet_number: u64) {
        self.inner.on_sent(now, bytes, last_packet_number);
    }

    fn on_ack(
        &mut self,
        now: Instant,
        sent: Instant,
        bytes: u64,
        app_limited: bool,
        rtt: &RttEstimator,
    ) {
        self.inner.on_ack(now, sent, bytes, app_limited, rtt);
    }

    fn on_end_acks(
        &mut self,
        now: Instant,
        in_flight: u64,
        app_limited: bool,
        largest_packet_num_acked: Option<u64>,
    ) {
        self.inner
            .on_end_acks(now, in_flight, app_limited, largest_packet_num_acked);
    }

    fn on_congestion_event(
        &mut self,
        now: Instant,
        sent: Instant,
        is_persistent_congestion: bool,
        lost_bytes: u64,
    ) {
        self.inner
            .on_congestion_event(now, sent, is_persistent_congestion, lost_bytes);
    }

    fn on_mtu_update(&mut self, new_mtu: u16) {
        self.inner.on_mtu_update(new_mtu);
    }

    fn window(&self) -> u64 {
        self.inner.window().max(self.floor)
    }

    fn metrics(&self) -> ControllerMetrics {
        let mut m = self.inner.metrics();
        m.congestion_window = self.window();
        m
    }

    fn clone_box(&self) -> Box<dyn Controller> {
        Box::new(Floored {
            inner: self.inner.clone_box(),
            floor: self.floor,
        })
    }

    fn initial_window(&self) -> u64 {
        self.inner.initial_window().max(self.floor)
    }

    fn into_any(self: Box<Self>) -> Box<dyn Any> {
        self
    }
}
