//! The viewer's side of its conversation with a server, without I/O: the hello it opens
//! with and the next connection's ([`hello`], [`next_hello`]), the welcome checked against
//! the protocol's grids and the colour messages that follow it taken up to the coarsest
//! tile ([`Joining`]), the terrain every reconnection must find again ([`TerrainId`]),
//! what a server message means during the session ([`take_control`]: colour into the
//! cache; an edge's news of its world, the vehicle followed and a watched recording's
//! state handed back), and how the server's refusals and messages read in words. Shared
//! by the native viewer (over QUIC, `quic.rs`) and the browser viewer (`roam-web`, over
//! WebTransport), which differ only in how the bytes travel.

use roam_protocol::messages::{
    Hello, Reason, ReplayStatus, Role, ServerMessage, Welcome, WorldNews,
};

use crate::color_cache::{ColorCache, ColorError, Keep};

/// What a server said (or failed to say) that ends a join or a session, naming the
/// message and what was expected; in the words the viewers show.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ConversationError {
    /// The server refused the hello.
    #[error("refused: {}", describe(.0))]
    Refused(Reason),
    /// The answer to the hello was another message (`got`: its name, as [`name`] says).
    #[error("expected a welcome, got {got}")]
    NotWelcome { got: String },
    /// The welcome's grid is not one of the protocol's.
    #[error(
        "Welcome.levels: a grid of 2^{levels} + 1, expected 1 ..= {}",
        roam_protocol::bintree::MAX_LEVELS
    )]
    Levels { levels: u8 },
    /// The welcome's colour layout does not fit the window asked.
    #[error("the server's welcome: {0}")]
    Welcome(ColorError),
    #[error("the server sent too much news before the coarsest tile")]
    TooMuchNews,
    #[error("the server sent too many colour messages before the coarsest tile")]
    TooManyColours,
    /// A message other than colour before the coarsest tile.
    #[error("expected the coarsest colour tile, got {got}")]
    NotCoarsest { got: String },
    /// Colour the cache refuses before the coarsest tile.
    #[error("the server's colour: {0}")]
    Colour(ColorError),
    /// The server's goodbye during the session.
    #[error("the server said goodbye: {}", describe(.0))]
    Goodbye(Reason),
    /// A message no server sends during a session.
    #[error("the server sent {got} during the session")]
    Unexpected { got: String },
    /// Colour the cache refuses during the session.
    #[error("the server broke the protocol: {0}")]
    Broke(ColorError),
}

/// Why a connection ended or was refused, in words.
pub fn describe(reason: &Reason) -> String {
    match reason {
        Reason::WrongToken => "wrong token".into(),
        Reason::Version { server } => format!("the server speaks protocol version {server}"),
        Reason::Shutdown => "the server is shutting down".into(),
        Reason::Quit => "quit".into(),
        Reason::Protocol(s) | Reason::Unavailable(s) => s.clone(),
        Reason::Full { viewers } => format!("the server is full ({viewers} viewers)"),
    }
}

/// A server message, named (a colour tile's bytes are not spelled out).
pub fn name(m: &ServerMessage) -> String {
    match m {
        ServerMessage::Welcome(_) => "a welcome".into(),
        ServerMessage::ColorWindow { level, x0, z0 } => {
            format!("a colour window (level {level} at ({x0}, {z0}))")
        }
        ServerMessage::ColorTile { level, x, z, data } => {
            format!(
                "a colour tile ({} bytes, level {level} at ({x}, {z}))",
                data.len()
            )
        }
        ServerMessage::NormalTile { level, x, z, data } => {
            format!(
                "a normal tile ({} bytes, level {level} at ({x}, {z}))",
                data.len()
            )
        }
        ServerMessage::Refused(r) => format!("Refused({r:?})"),
        ServerMessage::Bye(r) => format!("Bye({r:?})"),
        ServerMessage::World(WorldNews::Gone(why)) => format!("news of the world gone ({why})"),
        ServerMessage::World(WorldNews::Back) => "news of the world back".into(),
        ServerMessage::World(WorldNews::Edges(e)) => {
            format!("news of the world's edges ({} addresses)", e.len())
        }
        ServerMessage::Following(v) => format!("following vehicle {v}"),
        ServerMessage::Replay(s) => format!("a replay's status (tick {})", s.tick),
    }
}

/// What a server message during the session tells the session, beyond colour.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Told<'m> {
    /// An edge's news of its world.
    News(&'m WorldNews),
    /// The frames follow this vehicle from now on.
    Following(u16),
    /// A watched recording's state.
    Replay(&'m ReplayStatus),
}

/// The answer to a hello: a welcome, or a refusal (or anything else) in words.
pub fn welcome_of(msg: ServerMessage) -> Result<Welcome, ConversationError> {
    match msg {
        ServerMessage::Welcome(w) => Ok(w),
        ServerMessage::Refused(reason) => Err(ConversationError::Refused(reason)),
        other => Err(ConversationError::NotWelcome { got: name(&other) }),
    }
}

/// News of the world an edge may send before the coarsest tile, at most (kept for the
/// session, [`Joining::take_news`]).
const NEWS_BEFORE_TILE: usize = 16;

/// A welcomed connection taking the colour messages that follow the welcome until the
/// coarsest level's tile is resident (the server sends it first; a few windows before it
/// are taken too, and an edge's news of its world, kept).
pub struct Joining {
    cache: ColorCache,
    /// Messages still allowed before the coarsest tile.
    left: u32,
    /// News of the world that came before the coarsest tile.
    news: Vec<WorldNews>,
}

impl Joining {
    /// Checks the welcome's grid and colour layout against the window asked.
    pub fn new(welcome: &Welcome, asked: u8, keep: Keep) -> Result<Joining, ConversationError> {
        if roam_protocol::Grid::new(u32::from(welcome.levels)).is_none() {
            let levels = welcome.levels;
            return Err(ConversationError::Levels { levels });
        }
        let cache = ColorCache::new(welcome.color, welcome.levels, asked, keep)
            .map_err(ConversationError::Welcome)?;
        // Nothing the server may send before the coarsest tile can be more than a message
        // per slot and a window per level.
        let left = cache.capacity() + u32::from(welcome.color.levels) + 1;
        Ok(Joining {
            cache,
            left,
            news: Vec::new(),
        })
    }

    /// News of the world that came with the join, in order.
    pub fn take_news(&mut self) -> Vec<WorldNews> {
        std::mem::take(&mut self.news)
    }

    /// Takes the next message: the colour cache once the coarsest tile is in it.
    pub fn apply(&mut self, msg: &ServerMessage) -> Result<Option<ColorCache>, ConversationError> {
        if let ServerMessage::World(news) = msg {
            if self.news.len() >= NEWS_BEFORE_TILE {
                return Err(ConversationError::TooMuchNews);
            }
            self.news.push(news.clone());
            return Ok(None);
        }
        if self.left == 0 {
            return Err(ConversationError::TooManyColours);
        }
        self.left -= 1;
        match self.cache.apply(msg) {
            Ok(true) if self.cache.has_coarsest() => {
                let fresh = self.cache.fresh();
                Ok(Some(std::mem::replace(&mut self.cache, fresh)))
            }
            Ok(true) => Ok(None),
            Ok(false) => Err(ConversationError::NotCoarsest { got: name(msg) }),
            Err(e) => Err(ConversationError::Colour(e)),
        }
    }
}

/// The terrain a viewer draws, from its first welcome and coarsest colour tile: what every
/// reconnection must find again (the finer tiles are not compared: they come later).
#[derive(Clone, Debug, PartialEq)]
pub struct TerrainId {
    levels: u8,
    h_scale: f64,
    v_scale: f64,
    /// The colour pyramid's cells, tile, levels and window: the renderer's texture layers
    /// and resident masks are laid out for the first connection's window, so a server
    /// offering another one is another terrain for this session.
    color: (u32, u32, u8, u8),
    /// The decoded coarsest colour tile (one tile: at most 256² RGB texels), or its
    /// payload for a session that decodes no tile ([`crate::color_cache::Keep::Counted`]).
    colors: Vec<u8>,
}

impl TerrainId {
    /// The terrain of `welcome`, whose coarsest colour tile is `coarsest` (RGB, or its
    /// payload: [`crate::color_cache::ColorCache::coarsest`]).
    pub fn of(welcome: &Welcome, coarsest: &[u8]) -> TerrainId {
        let c = &welcome.color;
        TerrainId {
            levels: welcome.levels,
            h_scale: welcome.h_scale,
            v_scale: welcome.v_scale,
            color: (c.cells, c.tile, c.levels, c.window),
            colors: coarsest.to_vec(),
        }
    }

    /// What differs from `self` in `other`, in words; `None` when nothing does.
    pub fn differences(&self, other: &TerrainId) -> Option<String> {
        let mut out = Vec::new();
        if self.levels != other.levels {
            out.push(format!(
                "a grid of 2^{} + 1, was 2^{} + 1",
                other.levels, self.levels
            ));
        }
        if (self.h_scale, self.v_scale) != (other.h_scale, other.v_scale) {
            out.push(format!(
                "scales {} × {}, were {} × {}",
                other.h_scale, other.v_scale, self.h_scale, self.v_scale
            ));
        }
        if self.color != other.color || self.colors != other.colors {
            out.push("another colour map".into());
        }
        (!out.is_empty()).then(|| out.join("; "))
    }
}

/// Takes a server message that comes during the session: colour windows, colour tiles and
/// normal tiles into the colour cache, which `colors` lends (twice for a tile: it decodes
/// into `rgb` in between,
/// without the cache, which the display drains meanwhile); an edge's news of its world, the
/// vehicle followed and a watched recording's state are handed back (`Ok(Some(told))`)
/// for the session to take. `Err` with the reason when the
/// message ends the session: a goodbye, anything else not colour, or colour the cache
/// refuses.
pub fn take_control<'m, C: std::ops::DerefMut<Target = ColorCache>>(
    msg: &'m ServerMessage,
    rgb: &mut Vec<u8>,
    mut colors: impl FnMut() -> C,
) -> Result<Option<Told<'m>>, ConversationError> {
    let taken = match msg {
        ServerMessage::World(news) => return Ok(Some(Told::News(news))),
        ServerMessage::Following(v) => return Ok(Some(Told::Following(*v))),
        ServerMessage::Replay(s) => return Ok(Some(Told::Replay(s))),
        ServerMessage::Bye(reason) => return Err(ConversationError::Goodbye(reason.clone())),
        ServerMessage::ColorTile { level, x, z, data } => {
            let layout = *colors().layout();
            crate::color_cache::decode_tile(&layout, *level, *x, *z, data, rgb)
                .and_then(|()| colors().put_decoded(*level, *x, *z, rgb, data.len()))
        }
        ServerMessage::NormalTile { level, x, z, data } => {
            let layout = *colors().layout();
            crate::color_cache::decode_normal_tile(&layout, *level, *x, *z, data, rgb)
                .and_then(|()| colors().put_normals_decoded(*level, *x, *z, rgb, data.len()))
        }
        ServerMessage::ColorWindow { .. } => colors().apply(msg).map(|_| ()),
        other => return Err(ConversationError::Unexpected { got: name(other) }),
    };
    taken.map(|()| None).map_err(ConversationError::Broke)
}

/// A first hello, the one way every viewer (the window, the headless viewer, the
/// benchmarks, the page, the tests' viewers) makes one: `role` with `token`, a `viewport`
/// seen with a vertical field of view of `fov_y_deg` degrees, `budget` triangles,
/// `frame_rate` frames a second, and the colour window a device whose textures are at most
/// `max_texture` texels a side can hold ([`crate::render::native_max_texture`] natively).
pub fn hello(
    role: Role,
    token: String,
    viewport: [u32; 2],
    fov_y_deg: f32,
    budget: u32,
    frame_rate: u16,
    max_texture: u32,
) -> Hello {
    Hello {
        version: roam_protocol::messages::VERSION,
        role,
        token,
        viewport,
        fov_y_deg,
        budget,
        frame_rate,
        resume: None,
        color_window: crate::color_cache::window_for(max_texture),
    }
}

/// The hello of the connection after one welcomed with `welcome`: a driver presents its
/// ticket, a spectator asks for the vehicle it followed.
pub fn next_hello(mut hello: Hello, welcome: &Welcome) -> Hello {
    match hello.role {
        Role::Driver => hello.resume = welcome.ticket,
        Role::Spectator { .. } => {
            hello.role = Role::Spectator {
                follow: Some(welcome.vehicle),
            }
        }
    }
    hello
}

#[cfg(test)]
mod tests {
    use roam_protocol::messages::{Reason, ServerMessage};
    use roam_protocol::normals;
    use roam_protocol::tiles::ColorLayout;

    use super::{ConversationError, take_control, welcome_of};
    use crate::color_cache::{ColorCache, Keep};

    /// A normal tile of level `level` at `(x, z)` on the wire, its codes made from `seed`.
    fn tile(layout: &ColorLayout, level: u8, x: u32, z: u32, seed: u8) -> ServerMessage {
        let side = layout.tile_side(level);
        let codes: Vec<[u8; 2]> = (0..side * side)
            .map(|i| [seed.wrapping_add((i % 13) as u8), 128])
            .collect();
        let mut data = Vec::new();
        normals::encode_tile(side, &codes, &mut data).expect("a valid tile");
        ServerMessage::NormalTile { level, x, z, data }
    }

    /// The session's path: a normal tile during the session is decoded outside the
    /// cache's lock and put in ([`take_control`]); a tile the layout has no place for is
    /// refused.
    #[test]
    fn the_session_takes_normal_tiles() {
        // 64 cells in tiles of 8, a window of 2: levels of 8, 4, 2, 1 tiles a side.
        let layout = ColorLayout::new(64, 8, 2).expect("a valid layout");
        let cache = ColorCache::new(layout, 6, 8, Keep::Texels).expect("the layout fits");
        let c = std::cell::RefCell::new(cache);
        let mut scratch = Vec::new();
        let msg = tile(&layout, 2, 1, 0, 11);
        assert_eq!(
            take_control(&msg, &mut scratch, || c.borrow_mut()),
            Ok(None)
        );
        assert!(c.borrow().has_normals(2, 1, 0));
        let bad = ServerMessage::NormalTile {
            level: 9,
            x: 0,
            z: 0,
            data: vec![1, 2, 3],
        };
        let e = take_control(&bad, &mut scratch, || c.borrow_mut()).expect_err("no level 9");
        assert!(matches!(e, ConversationError::Broke(_)), "{e:?}");
        assert!(
            e.to_string().starts_with("the server broke the protocol: "),
            "{e}"
        );
    }

    /// What ends a join or a session, and how it reads: a refusal, a goodbye, a message
    /// in the wrong place.
    #[test]
    fn what_the_server_said_amiss_is_named() {
        let full = Reason::Full { viewers: 64 };
        for (msg, want, words) in [
            (
                ServerMessage::Refused(full.clone()),
                ConversationError::Refused(full),
                "refused: the server is full (64 viewers)",
            ),
            (
                ServerMessage::Following(3),
                ConversationError::NotWelcome {
                    got: "following vehicle 3".into(),
                },
                "expected a welcome, got following vehicle 3",
            ),
        ] {
            let e = welcome_of(msg).expect_err(words);
            assert_eq!((e.to_string().as_str(), e), (words, want));
        }
        let layout = ColorLayout::new(64, 8, 2).expect("a valid layout");
        let cache = ColorCache::new(layout, 6, 8, Keep::Masks).expect("the layout fits");
        let c = std::cell::RefCell::new(cache);
        for (msg, want, words) in [
            (
                ServerMessage::Bye(Reason::Shutdown),
                ConversationError::Goodbye(Reason::Shutdown),
                "the server said goodbye: the server is shutting down",
            ),
            (
                ServerMessage::Refused(Reason::WrongToken),
                ConversationError::Unexpected {
                    got: "Refused(WrongToken)".into(),
                },
                "the server sent Refused(WrongToken) during the session",
            ),
        ] {
            let colors = || c.borrow_mut();
            let e = take_control(&msg, &mut Vec::new(), colors).expect_err(words);
            assert_eq!((e.to_string().as_str(), e), (words, want));
        }
    }
}
