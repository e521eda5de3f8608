//! The blocking frame makers' permits ([`super::Shared::makers`]): at most one fewer than
//! the cores at once, handed out **streaming viewers first, joining ones after**.
//!
//! A viewer's first frame is a key frame from scratch (several milliseconds at 32,768
//! triangles), and when this was written its second frame was not cheap either (made on
//! a blocking thread too; it is made in line now). With one FIFO queue, 20 viewers joining at once queued 20 first key
//! frames, and each viewer's second frame waited behind the key frames of all those
//! that joined after it: seen in the server (one core, `data/kossou`, 32,768 triangles,
//! every second frame timed), 16 to 151 ms, growing by one key frame (7.5 ms there) per
//! viewer, which is the longest gap after the first frame a join storm showed (110–130 ms
//! with 20, 1.1–2.2 s with 40 on that loaded machine, where acknowledgements then fell
//! behind and more key frames followed). A driving viewer's rebuild waited the same way.
//! Now a waiting frame of a viewer that has a frame out goes before every first frame;
//! first frames go in the order they asked. Each second frame then waited 1–14 ms; with
//! the colour spread too ([`super::color_budget`]), 20 joining at once had their longest
//! gap after the first frame at 35–43 ms.

//!
//! **Below the async workers.** A blocking maker thread runs at a lower scheduling
//! priority ([`lower_this_thread`], nice [`MAKER_NICE`]) than the async workers that make
//! and send the streaming viewers' frames: on the one core a server is given, the kernel
//! otherwise shared it evenly between them, and 40 viewers joining at once (40 first key
//! frames, 7–10 ms each, back to back on the maker) left the workers half a core, so the
//! frames of the viewers already served started up to 330 ms late, their acknowledgements
//! fell more than [`crate::viewer::LOGS`] frames behind and ~100 more key frames followed
//! (the server's summary: 53, then 75, then 11 key frames a second for 40 joins). Frames
//! first; key frames in what is left.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use roam_protocol::sync::lock;
use tokio::sync::oneshot;

/// The nice value of a blocking frame maker thread (the async workers run at 0): about a
/// tenth of the core against a busy worker, all of it against an idle one.
pub const MAKER_NICE: i32 = 10;

/// Lowers the calling thread's scheduling priority to [`MAKER_NICE`], once per thread (a
/// thread of tokio's blocking pool keeps it: the pool also runs only the shutdown's join
/// of the world thread). Where the system refuses, or is not Linux, it stays as it was.
pub fn lower_this_thread() {
    thread_local!(static LOWERED: std::cell::Cell<bool> = const { std::cell::Cell::new(false) });
    LOWERED.with(|lowered| {
        if lowered.replace(true) {
            return;
        }
        #[cfg(target_os = "linux")]
        {
            // SAFETY: setpriority reads its three integer arguments and touches no memory;
            // `who` 0 with PRIO_PROCESS is the calling thread on Linux.
            let r = unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, MAKER_NICE) };
            if r != 0 {
                tracing::debug!(
                    "frame maker priority unchanged: {}",
                    std::io::Error::last_os_error()
                );
            }
        }
    });
}

/// The permits, and who waits for one.
#[derive(Debug)]
pub struct Makers {
    state: Mutex<State>,
}

#[derive(Debug)]
struct State {
    free: usize,
    /// Frames of viewers already streaming, in the order they asked.
    streaming: VecDeque<oneshot::Sender<()>>,
    /// Joining viewers' first frames, in the order they asked.
    joining: VecDeque<oneshot::Sender<()>>,
}

/// Never returned: the pool is never closed (kept for the caller's shutdown path).
#[derive(Debug)]
pub struct Closed;

/// A maker's permit, handed to the next waiter when dropped.
#[derive(Debug)]
pub struct Permit {
    makers: Arc<Makers>,
}

impl Drop for Permit {
    fn drop(&mut self) {
        self.makers.release();
    }
}

impl Makers {
    pub fn new(permits: usize) -> Makers {
        Makers {
            state: Mutex::new(State {
                free: permits,
                streaming: VecDeque::new(),
                joining: VecDeque::new(),
            }),
        }
    }

    /// A permit: at once if one is free, else when one is released, a viewer already
    /// streaming before any `first` frame.
    pub async fn acquire(self: &Arc<Self>, first: bool) -> Result<Permit, Closed> {
        let rx = {
            let mut s = lock(&self.state);
            if s.free > 0 {
                s.free -= 1;
                return Ok(Permit {
                    makers: self.clone(),
                });
            }
            let (tx, rx) = oneshot::channel();
            if first {
                s.joining.push_back(tx);
            } else {
                s.streaming.push_back(tx);
            }
            rx
        };
        // A waiter dropped after it was handed the permit gives it on (its guard).
        let mut waiting = Waiting {
            makers: self.clone(),
            rx: Some(rx),
        };
        let rx = waiting.rx.as_mut().expect("set above, taken only below");
        let handed = rx.await.is_ok();
        waiting.rx = None;
        if handed {
            Ok(Permit {
                makers: self.clone(),
            })
        } else {
            // Its sender is only dropped unsent when the pool is dropped: not while a
            // viewer task holds `Shared`.
            Err(Closed)
        }
    }

    /// A permit comes back: to the first live waiter (streaming ones first), else free.
    fn release(&self) {
        let mut s = lock(&self.state);
        loop {
            let next = match s.streaming.pop_front() {
                Some(tx) => tx,
                None => match s.joining.pop_front() {
                    Some(tx) => tx,
                    None => {
                        s.free += 1;
                        return;
                    }
                },
            };
            if next.send(()).is_ok() {
                return;
            }
            // That waiter is gone: the next one.
        }
    }

    /// Permits free now.
    pub fn free(&self) -> usize {
        lock(&self.state).free
    }
}

/// A waiter's receiver: dropped while still waiting, a permit already sent to it is
/// released.
struct Waiting {
    makers: Arc<Makers>,
    rx: Option<oneshot::Receiver<()>>,
}

impl Drop for Waiting {
    fn drop(&mut self) {
        if let Some(mut rx) = self.rx.take()
            && rx.try_recv().is_ok()
        {
            self.makers.release();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn streaming_viewers_go_before_joining_ones_and_permits_are_never_lost() {
        let m = Arc::new(Makers::new(1));
        let held = m.acquire(true).await.expect("free");
        assert_eq!(m.free(), 0);
        let order = Arc::new(Mutex::new(Vec::new()));
        let mut tasks = Vec::new();
        // Two joiners ask first, then a streaming viewer, then one that gives up.
        for (name, first) in [("join a", true), ("join b", true), ("stream", false)] {
            let (m, order) = (m.clone(), order.clone());
            let (asked, asked_rx) = oneshot::channel();
            tasks.push(tokio::spawn(async move {
                let fut = m.acquire(first);
                let _ = asked.send(());
                let p = fut.await.expect("open");
                lock(&order).push(name);
                drop(p);
            }));
            // Each is queued before the next asks (they run on this runtime's thread).
            let _ = asked_rx.await;
            tokio::task::yield_now().await;
        }
        let m2 = m.clone();
        let gone = tokio::spawn(async move { m2.acquire(false).await.map(drop) });
        tokio::task::yield_now().await;
        gone.abort();
        let _ = gone.await;
        drop(held);
        for t in tasks {
            t.await.expect("a waiter");
        }
        assert_eq!(*lock(&order), ["stream", "join a", "join b"]);
        assert_eq!(
            m.free(),
            1,
            "the permit is back, the aborted waiter skipped"
        );
    }
}
