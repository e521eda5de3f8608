//! What joining a server means, without the I/O: the welcome checked against the
//! protocol's grids, the colour messages that follow it taken up to the coarsest tile
//! ([`Joining`]), the next connection's hello ([`next_hello`]), and how the server's
//! refusals and messages read in words. Shared by the native viewer ([`crate::join`], over
//! QUIC) and the browser viewer (`roam-web`, over WebTransport), which differ only in how
//! the bytes travel.

use roam_protocol::messages::{Hello, Reason, Role, ServerMessage, Welcome};

use crate::color_cache::{ColorCache, Keep};

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
        ServerMessage::Refused(r) => format!("Refused({r:?})"),
        ServerMessage::Bye(r) => format!("Bye({r:?})"),
    }
}

/// The answer to a hello: a welcome, or a refusal (or anything else) in words.
pub fn welcome_of(msg: ServerMessage) -> Result<Welcome, String> {
    match msg {
        ServerMessage::Welcome(w) => Ok(w),
        ServerMessage::Refused(reason) => Err(format!("refused: {}", describe(&reason))),
        other => Err(format!("expected a welcome, got {}", name(&other))),
    }
}

/// A welcomed connection taking the colour messages that follow the welcome until the
/// coarsest level's tile is resident (the server sends it first; a few windows before it
/// are taken too).
pub struct Joining {
    cache: ColorCache,
    /// Messages still allowed before the coarsest tile.
    left: u32,
}

impl Joining {
    /// Checks the welcome's grid and colour layout against the window asked.
    pub fn new(welcome: &Welcome, asked: u8, keep: Keep) -> Result<Joining, String> {
        if roam_protocol::Grid::new(u32::from(welcome.levels)).is_none() {
            return Err(format!(
                "Welcome.levels: a grid of 2^{} + 1, expected 1 ..= {}",
                welcome.levels,
                roam_protocol::bintree::MAX_LEVELS
            ));
        }
        let cache = ColorCache::new(welcome.color, welcome.levels, asked, keep)
            .map_err(|e| format!("the server's welcome: {e}"))?;
        // Nothing the server may send before the coarsest tile can be more than a message
        // per slot and a window per level.
        let left = cache.capacity() + u32::from(welcome.color.levels) + 1;
        Ok(Joining { cache, left })
    }

    /// Takes the next message: the colour cache once the coarsest tile is in it.
    pub fn apply(&mut self, msg: &ServerMessage) -> Result<Option<ColorCache>, String> {
        if self.left == 0 {
            return Err("the server sent too many colour messages before the coarsest tile".into());
        }
        self.left -= 1;
        match self.cache.apply(msg) {
            Ok(true) if self.cache.has_coarsest() => {
                let fresh = self.cache.fresh();
                Ok(Some(std::mem::replace(&mut self.cache, fresh)))
            }
            Ok(true) => Ok(None),
            Ok(false) => Err(format!(
                "expected the coarsest colour tile, got {}",
                name(msg)
            )),
            Err(e) => Err(format!("the server's colour: {e}")),
        }
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
