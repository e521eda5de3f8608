//! What a viewer's task writes on its control stream after the welcome, beside the last
//! words ([`super::viewer`]): the colour tiles, each followed by its normals
//! ([`stream_color`], [`write_color`]: the viewer's [`ColorScheduler`] picks them for the
//! followed vehicle's position, paced by a
//! token bucket whose rate is the viewer's share of the server-wide colour budget,
//! [`super::color_budget`]; a tile is written whole and awaited before the next), and on
//! an edge the news of the world ([`tell_news`]: its edges, the world gone and back; a
//! driver whose world restarted is let go).

use std::sync::Arc;
use std::time::Duration;

use roam_link::wire;
use roam_protocol::messages::{ServerMessage, WorldNews};

use super::conn::SendStream;
use super::shared::Shared;
use crate::sim::world::VehicleId;
use crate::terrain::color_pyramid::TileError;
use crate::viewer::color::{ColorScheduler, ColorSend};

/// Writes one colour message (a tile's colour or normals from their pyramid), counting it.
pub(super) async fn write_color(
    send: &mut SendStream,
    shared: &Shared,
    m: ColorSend,
) -> Result<(), wire::WireError> {
    let stats = &shared.stats;
    let msg = match m {
        ColorSend::Window { level, x0, z0 } => ServerMessage::ColorWindow { level, x0, z0 },
        ColorSend::Tile { level, x, z } => {
            let Some(data) = served("colour", shared.pyramid.served_tile(level, x, z), m) else {
                return Ok(());
            };
            stats.add(&stats.color_tiles, 1);
            stats.add(&stats.color_bytes, data.len() as u64);
            ServerMessage::ColorTile {
                level,
                x,
                z,
                data: data.to_vec(),
            }
        }
        ColorSend::Normals { level, x, z } => {
            let Some(data) = served("normal", shared.normals.served_tile(level, x, z), m) else {
                return Ok(());
            };
            stats.add(&stats.normal_tiles, 1);
            stats.add(&stats.normal_bytes, data.len() as u64);
            ServerMessage::NormalTile {
                level,
                x,
                z,
                data: data.to_vec(),
            }
        }
    };
    send.write_msg(&msg).await
}

/// A tile's payload to send, or `None` (logged the first time when damaged). A tile not
/// sent is counted as held by the scheduler, so it is not asked for again: the viewer
/// draws a coarser level's colour there, or lights it per vertex.
fn served<'p>(what: &str, tile: Result<&'p [u8], TileError>, m: ColorSend) -> Option<&'p [u8]> {
    match tile {
        Ok(data) => Some(data),
        Err(e) => {
            if e == (TileError::Damaged { first: true }) {
                // True: the store removed the cache's stamp, so the next start checks the
                // file whole and rebuilds it (`terrain::tile_store`).
                tracing::error!(
                    "{what} tile not served ({m:?}): {e}; restart the server: the next start \
                     checks the cache file whole and rebuilds it"
                );
            }
            None
        }
    }
}

/// Why a driver on an edge is let go when its world restarts.
pub(super) const WORLD_RESTARTED: &str =
    "the world restarted and knows no vehicle from before: join again";

/// An edge's news of its world, told to the viewer as it changes (nothing on `serve`).
/// Completes only when a driver must go: the world restarted, and knows none of the
/// vehicles driven before.
pub(super) async fn tell_news(
    send: &tokio::sync::Mutex<SendStream>,
    remote: Option<Arc<super::bus::edge::Remote>>,
    driver: bool,
) -> String {
    let Some(remote) = remote else {
        return std::future::pending().await;
    };
    let mut news = remote.news();
    let mut told = super::bus::edge::News {
        restarts: news.borrow().restarts,
        ..Default::default()
    };
    loop {
        let now = news.borrow_and_update().clone();
        if driver && now.restarts != told.restarts {
            return WORLD_RESTARTED.into();
        }
        let mut say = Vec::new();
        if now.edges != told.edges {
            say.push(WorldNews::Edges(now.edges.clone()));
        }
        match (&told.gone, &now.gone) {
            (None, Some(why)) => {
                let mut why = why.clone();
                let mut end = why.len().min(roam_protocol::messages::MAX_REASON);
                while !why.is_char_boundary(end) {
                    end -= 1;
                }
                why.truncate(end);
                say.push(WorldNews::Gone(why));
            }
            (Some(_), None) => say.push(WorldNews::Back),
            _ => {}
        }
        for m in say {
            if send
                .lock()
                .await
                .write_msg(&ServerMessage::World(m))
                .await
                .is_err()
            {
                // The connection's end is seen by the other branches.
                return std::future::pending().await;
            }
        }
        told = now;
        if news.changed().await.is_err() {
            return std::future::pending().await;
        }
    }
}

/// How often the colour task looks at the camera and its budget.
const COLOR_TICK: Duration = Duration::from_millis(50);

/// Streams colour tiles (and their normals) to the viewer following `followed`, as its
/// scheduler picks them, within the byte rate, from the viewer's first frame on (`made`:
/// the frames made); ends when the control stream fails.
pub(super) async fn stream_color(
    send: Arc<tokio::sync::Mutex<SendStream>>,
    shared: Arc<Shared>,
    mut colors: ColorScheduler,
    (followed, mut made): (
        tokio::sync::watch::Receiver<VehicleId>,
        tokio::sync::watch::Receiver<u64>,
    ),
) {
    // Nothing before the first frame: the coarsest tile's normals, owed first, would
    // only share the path with it (a viewer lights per vertex until they come).
    if made.wait_for(|&n| n > 0).await.is_err() {
        return;
    }
    // A tile and its normals go out together.
    let largest = 2.0 * roam_protocol::colormap::max_len(colors.layout().tile) as f64;
    let h_scale = shared.terrain.map.h_scale;
    let mut tokens = 0.0f64;
    let mut last = tokio::time::Instant::now();
    let mut tick = tokio::time::interval(COLOR_TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let (pyramid, normals) = (shared.pyramid.clone(), shared.normals.clone());
    let cost = move |m: ColorSend| {
        let tile = match m {
            ColorSend::Tile { level, x, z } => pyramid.tile(level, x, z),
            ColorSend::Normals { level, x, z } => normals.tile(level, x, z),
            ColorSend::Window { .. } => None,
        };
        tile.map_or(0, |t| t.len() as u64)
    };
    // Counted among the viewers sharing the budget while its windows are not full.
    let mut want = Wanting {
        shared: shared.clone(),
        on: false,
    };
    want.set(true);
    let mut parked: Option<(f64, f64)> = None;
    loop {
        tick.tick().await;
        let now = tokio::time::Instant::now();
        let rate = shared.color.rate();
        let burst = (rate / 4.0).max(largest);
        tokens = (tokens + rate * now.duration_since(last).as_secs_f64()).min(burst);
        last = now;
        let camera = {
            let vehicle = *followed.borrow();
            let snap = shared.snapshots.borrow();
            snap.vehicles
                .iter()
                .find(|v| v.id == vehicle)
                .map(|v| (v.state.x / h_scale, v.state.z / h_scale))
        };
        // With no vehicle (a replay sought to before anyone joined), the camera stays
        // where it was, and so does the colour around it.
        if camera.is_some() {
            parked = camera;
        }
        let Some(camera) = parked else { continue };
        let mut msgs = Vec::new();
        let spent =
            shared
                .color
                .spend(now.into_std(), largest as u64, tokens as u64, |allowance| {
                    let (m, spent) = colors.step(camera, allowance, &cost);
                    msgs = m;
                    spent
                });
        tokens -= spent as f64;
        want.set(!colors.complete());
        for m in msgs {
            let mut s = send.lock().await;
            if write_color(&mut s, &shared, m).await.is_err() {
                return;
            }
        }
    }
}

/// A viewer's place among those sharing the colour budget, given up when dropped.
struct Wanting {
    shared: Arc<Shared>,
    on: bool,
}

impl Wanting {
    fn set(&mut self, on: bool) {
        self.shared.color.set_wanting(self.on, on);
        self.on = on;
    }
}

impl Drop for Wanting {
    fn drop(&mut self) {
        self.set(false);
    }
}
