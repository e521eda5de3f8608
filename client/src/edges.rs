//! A world served by several edge servers, as a viewer sees it, without I/O or a clock
//! (instants come in): the addresses it tries in turn ([`Addresses`]: the ones given,
//! then those the edges told of, [`native_edges`] for QUIC and [`web_edges`] for the
//! page's WebTransport) and what the edge said of its world ([`World`]: gone, why, for how
//! long in all). Shared by the native viewer's session and the browser viewer
//! (`roam-web`); the silence rule counted per address is the reconnection supervisor's.
//!
//! **The order.** The first connection tries the addresses in the order given; after
//! losing address `i`, the next attempt goes to `i + 1`, then `i + 2`, … wrapping around
//! ([`next_address`]): a viewer moves on from an edge that went away rather than waiting
//! on it. Addresses learned from [`WorldNews::Edges`] join the rotation after the given
//! ones, each once, and stay for the session (a dead one costs one short attempt a round),
//! at most [`MAX_ADDRESSES`] in all.

use std::net::SocketAddr;
use std::time::Duration;

use roam_protocol::messages::WorldNews;
use web_time::Instant;

/// The most addresses a viewer keeps in its rotation.
pub const MAX_ADDRESSES: usize = 64;

/// The address tried after address `i` of `n` (wrapping); 0 when there are none.
pub fn next_address(i: usize, n: usize) -> usize {
    if n == 0 { 0 } else { (i + 1) % n }
}

/// The addresses a session tries, in turn, and the one it is on.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Addresses<T> {
    list: Vec<T>,
    /// How many of `list` were given (the rest were learned).
    given: usize,
    current: usize,
}

impl<T: Clone + PartialEq> Addresses<T> {
    /// The addresses given, in order (duplicates dropped, at most [`MAX_ADDRESSES`]);
    /// `None` when there are none.
    pub fn new(given: impl IntoIterator<Item = T>) -> Option<Addresses<T>> {
        let mut a = Addresses {
            list: Vec::new(),
            given: 0,
            current: 0,
        };
        a.learn(given);
        a.given = a.list.len();
        (!a.list.is_empty()).then_some(a)
    }

    /// The address in use (or being tried).
    pub fn current(&self) -> &T {
        &self.list[self.current]
    }

    /// Its place in the rotation.
    pub fn index(&self) -> usize {
        self.current
    }

    /// Makes address `i` the current one (the first connection found it); out of range
    /// changes nothing.
    pub fn set_current(&mut self, i: usize) {
        if i < self.list.len() {
            self.current = i;
        }
    }

    /// The current address was lost (or an attempt on it failed): the next one in turn,
    /// now current.
    pub fn after_loss(&mut self) -> &T {
        self.current = next_address(self.current, self.list.len());
        self.current()
    }

    /// Adds the addresses not yet known, after the others, while there is room: how many
    /// were added.
    pub fn learn(&mut self, found: impl IntoIterator<Item = T>) -> usize {
        let mut added = 0;
        for a in found {
            if self.list.len() >= MAX_ADDRESSES {
                break;
            }
            if !self.list.contains(&a) {
                self.list.push(a);
                added += 1;
            }
        }
        added
    }

    /// Every address, in the order tried.
    pub fn all(&self) -> &[T] {
        &self.list
    }

    pub fn len(&self) -> usize {
        self.list.len()
    }

    /// Always false: there is at least one address.
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// Whether there is another address to move on to.
    pub fn many(&self) -> bool {
        self.list.len() > 1
    }

    /// The addresses learned from the edges (not given).
    pub fn learned(&self) -> usize {
        self.list.len() - self.given
    }
}

/// What the edge says of the world behind it ([`WorldNews`]): gone (why) or not, and the
/// time it was said gone, in all.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct World {
    /// The world does not answer: why, in the edge's words.
    pub gone: Option<String>,
    since: Option<Instant>,
    before: Duration,
}

/// How news changed the world's state.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Change {
    Gone(String),
    /// Back after this long gone.
    Back(Duration),
}

impl World {
    /// Takes `news`: the change it makes (none for the edges, or news already known).
    pub fn apply(&mut self, news: &WorldNews, now: Instant) -> Option<Change> {
        match news {
            WorldNews::Gone(why) => {
                if self.gone.as_deref() == Some(why.as_str()) {
                    return None;
                }
                self.since.get_or_insert(now);
                self.gone = Some(why.clone());
                Some(Change::Gone(why.clone()))
            }
            WorldNews::Back => self.back(now).map(Change::Back),
            WorldNews::Edges(_) => None,
        }
    }

    /// No longer gone (news from a new connection will say if it still is): how long it
    /// was, if it was.
    pub fn back(&mut self, now: Instant) -> Option<Duration> {
        self.gone.take()?;
        let was = self
            .since
            .take()
            .map_or(Duration::ZERO, |t| now.saturating_duration_since(t));
        self.before += was;
        Some(was)
    }

    /// The time the world was said gone, in all, until `now`.
    pub fn gone_total(&self, now: Instant) -> Duration {
        self.before
            + self
                .since
                .map_or(Duration::ZERO, |t| now.saturating_duration_since(t))
    }
}

/// The native viewer's addresses among an edge list: the plain `host:port` ones that are
/// socket addresses (a name is not looked up; an unspecified address, `0.0.0.0`, is no
/// place to connect to).
pub fn native_edges(edges: &[String]) -> Vec<SocketAddr> {
    edges
        .iter()
        .filter_map(|e| e.parse::<SocketAddr>().ok())
        .filter(|a| !a.ip().is_unspecified() && a.port() != 0)
        .collect()
}

/// Where a page reaches an edge's WebTransport: the session's URL and the SHA-256 hashes
/// (lowercase hex) of the certificates to pin (empty: one browsers trust).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WebEdge {
    pub url: String,
    pub hashes: Vec<String>,
}

/// The page's addresses among an edge list: `https://HOST:PORT/PATH#hashes=HEX,…` (the
/// fragment optional), each hash 64 hex digits; an entry not of that form is skipped.
pub fn web_edges(edges: &[String]) -> Vec<WebEdge> {
    edges.iter().filter_map(|e| web_edge(e)).collect()
}

fn web_edge(edge: &str) -> Option<WebEdge> {
    let rest = edge.strip_prefix("https://")?;
    let (url, fragment) = match edge.split_once('#') {
        Some((url, fragment)) => (url, Some(fragment)),
        None => (edge, None),
    };
    // A host, and nothing a URL would not hold.
    if rest.is_empty() || rest.starts_with(['/', '#', ':']) || url.chars().any(char::is_whitespace)
    {
        return None;
    }
    let hashes = match fragment {
        None | Some("") => Vec::new(),
        Some(f) => {
            let list = f.strip_prefix("hashes=")?;
            let hashes: Vec<String> = list
                .split(',')
                .filter(|h| !h.is_empty())
                .map(str::to_ascii_lowercase)
                .collect();
            let hex = |h: &String| h.len() == 64 && h.bytes().all(|b| b.is_ascii_hexdigit());
            if !hashes.iter().all(hex) {
                return None;
            }
            hashes
        }
    };
    Some(WebEdge {
        url: url.to_owned(),
        hashes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn after_a_loss_the_next_address_is_tried_wrapping_around() {
        assert_eq!(next_address(0, 3), 1);
        assert_eq!(next_address(2, 3), 0);
        assert_eq!(next_address(0, 1), 0);
        assert_eq!(next_address(5, 0), 0);
        let mut a = Addresses::new(["a", "b", "c"]).expect("three");
        assert_eq!(*a.current(), "a");
        let tried: Vec<&str> = (0..5).map(|_| *a.after_loss()).collect();
        assert_eq!(tried, ["b", "c", "a", "b", "c"]);
        // The first connection found "b": losing it tries "c" first, not "b" again.
        a.set_current(1);
        assert_eq!(*a.after_loss(), "c");
        // One address: always itself.
        let mut one = Addresses::new(["only"]).expect("one");
        assert!(!one.many());
        assert_eq!(*one.after_loss(), "only");
        assert!(Addresses::<&str>::new([]).is_none());
    }

    #[test]
    fn learned_addresses_follow_the_given_ones_once_and_bounded() {
        let mut a = Addresses::new(["a", "b", "a"]).expect("two");
        assert_eq!(a.all(), ["a", "b"]);
        assert_eq!(a.learn(["b", "c", "d", "c"]), 2);
        assert_eq!(a.all(), ["a", "b", "c", "d"]);
        assert_eq!(a.learned(), 2);
        // Learning keeps the one in use, and the rotation goes on through the new ones.
        a.set_current(1);
        a.learn(["e"]);
        assert_eq!(*a.current(), "b");
        assert_eq!(*a.after_loss(), "c");
        let many: Vec<String> = (0..200).map(|i| format!("10.0.0.{i}:1")).collect();
        let mut big = Addresses::new(["x".to_owned()]).expect("one");
        assert_eq!(big.learn(many), MAX_ADDRESSES - 1);
        assert_eq!(big.len(), MAX_ADDRESSES);
        assert_eq!(big.learn(["y".to_owned()]), 0);
    }

    #[test]
    fn edge_lists_are_split_between_quic_and_webtransport() {
        let h1 = "ab".repeat(32);
        let h2 = "CD".repeat(32);
        let edges: Vec<String> = vec![
            "127.0.0.1:4433".into(),
            "[::1]:4434".into(),
            "0.0.0.0:4433".into(),
            "edge.example:4433".into(),
            format!("https://edge.example:4433/roam#hashes={h1},{h2}"),
            "https://[::1]:443/roam".into(),
            "https://x:1/roam#hashes=".into(),
            "https://x:1/roam#hashes=zz".into(),
            "https://x:1/roam#other=1".into(),
            "https://".into(),
        ];
        assert_eq!(
            native_edges(&edges),
            vec![
                "127.0.0.1:4433".parse::<SocketAddr>().expect("valid"),
                "[::1]:4434".parse().expect("valid"),
            ]
        );
        assert_eq!(
            web_edges(&edges),
            vec![
                WebEdge {
                    url: "https://edge.example:4433/roam".into(),
                    hashes: vec![h1.clone(), h2.to_ascii_lowercase()],
                },
                WebEdge {
                    url: "https://[::1]:443/roam".into(),
                    hashes: vec![],
                },
                WebEdge {
                    url: "https://x:1/roam".into(),
                    hashes: vec![],
                },
            ]
        );
    }
}
