//! An edge's requests to its world, and their answers ([`Asker`]): each request sealed for
//! the world process the edge knows, published with a reply subject of the edge's own
//! (`<inbox>.<counter>`), and its answer taken only if it opens, names this edge and that
//! request. Not `async_nats::Client::request`: that takes the first message on the reply
//! subject, so anyone who can publish there would answer first; here a forged or replayed
//! answer is counted and the request goes on waiting for the world's.
//!
//! NATS's "no responders" status (no world subscribed) ends a request at once when the bus
//! is plain; sealed, it is ignored (anyone can publish a message that looks like one) and
//! the request waits out its time.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures_util::StreamExt;
use roam_protocol::bus::{Answer, Ask, Subjects};
use roam_protocol::sync::lock;
use tokio::sync::oneshot;

use super::BusError;
use super::seal::{BusKey, Header, Kind, Refusal, RefusedCounts};
use super::voice::{Ear, Voice};

/// How long one request waits for the world's answer.
pub const ASK_TIMEOUT: Duration = Duration::from_secs(2);

/// Requests waiting for their answers at most (each its own task's; past it a request is
/// refused at once).
const MAX_PENDING: usize = 8192;

type Waiting = Mutex<HashMap<u64, oneshot::Sender<Result<Answer, BusError>>>>;

/// An edge's way to ask its world.
pub struct Asker {
    client: async_nats::Client,
    subject: String,
    inbox: String,
    voice: Voice,
    pending: Arc<Waiting>,
    /// The world process requests are sealed for (0 until one has answered).
    world: AtomicU64,
    answers: tokio::task::JoinHandle<()>,
}

impl Drop for Asker {
    fn drop(&mut self) {
        self.answers.abort();
    }
}

impl Asker {
    /// Asks on `subjects` as `sender` (sealed under `key`, or plain), counting answers
    /// refused in `counts`.
    pub async fn start(
        client: async_nats::Client,
        subjects: &Subjects,
        key: Option<&BusKey>,
        sender: u64,
        counts: Arc<RefusedCounts>,
    ) -> Result<Asker, BusError> {
        let inbox = client.new_inbox();
        let sub = client
            .subscribe(format!("{inbox}.*"))
            .await
            .map_err(|e| BusError::Nats {
                what: "subscribing to the world's answers",
                error: e.to_string(),
            })?;
        let pending: Arc<Waiting> = Arc::default();
        let ear = Ear::new(Kind::Answer, key, counts, "answer");
        let answers = tokio::spawn(take_answers(sub, ear, pending.clone(), sender));
        Ok(Asker {
            client,
            subject: subjects.ask.clone(),
            inbox,
            voice: Voice::new(key, sender),
            pending,
            world: AtomicU64::new(0),
            answers,
        })
    }

    /// The world process this edge's requests are for.
    pub fn world(&self) -> u64 {
        self.world.load(Ordering::Acquire)
    }

    /// From now on, requests are for world process `world` (its answer confirmed it).
    pub fn set_world(&self, world: u64) {
        self.world.store(world, Ordering::Release);
    }

    pub fn voice(&self) -> &Voice {
        &self.voice
    }

    /// `ask`, and the world's answer (within [`ASK_TIMEOUT`]).
    pub async fn ask(&self, ask: &Ask) -> Result<Answer, BusError> {
        let nats = |e: String| BusError::Nats {
            what: "asking the world",
            error: e,
        };
        // The reply subject names the counter; it is known only once the counter is. The
        // seal is bound to it: played again with another reply subject, it does not open.
        let counter = self.voice.next(Kind::Ask);
        let reply = format!("{}.{counter}", self.inbox);
        let bytes =
            self.voice
                .say_numbered(Kind::Ask, counter, (self.world(), 0), reply.as_bytes(), ask);
        let (tx, rx) = oneshot::channel();
        {
            let mut pending = lock(&self.pending);
            if pending.len() >= MAX_PENDING {
                return Err(nats("too many requests waiting for the world".into()));
            }
            pending.insert(counter, tx);
        }
        let sent = self
            .client
            .publish_with_reply(self.subject.clone(), reply, bytes)
            .await;
        let answer = match sent {
            Err(e) => Err(nats(e.to_string())),
            Ok(()) => match tokio::time::timeout(ASK_TIMEOUT, rx).await {
                Ok(Ok(answer)) => answer,
                Ok(Err(_)) => Err(nats("the answers' subscription ended".into())),
                Err(_) => Err(nats("no answer in 2 s".into())),
            },
        };
        lock(&self.pending).remove(&counter);
        answer
    }
}

/// Hands each answer that opens, names this edge (`me`) and a request waiting, to it.
async fn take_answers(
    mut sub: async_nats::Subscriber,
    mut ear: Ear,
    pending: Arc<Waiting>,
    me: u64,
) {
    while let Some(msg) = sub.next().await {
        let Some(counter) = msg
            .subject
            .rsplit('.')
            .next()
            .and_then(|c| c.parse::<u64>().ok())
        else {
            continue;
        };
        let sealed = ear.sealed();
        // Sealed, what is not for this edge and a request waiting is dropped before any
        // cryptography (copies of other edges' answers, played into this inbox).
        if sealed
            && let Some(h) = Header::peek(&msg.payload)
            && (h.to != me || h.re != counter || !lock(&pending).contains_key(&counter))
        {
            ear.refuse(Refusal::Replayed, Some(h.sender));
            continue;
        }
        if msg.status.is_some() {
            // "No responders" (or any status): said by NATS when plain; anyone can say it
            // when sealed, so then the request waits for its answer.
            if !sealed {
                let error = BusError::Nats {
                    what: "asking the world",
                    error: format!("NATS: {:?}", msg.status),
                };
                if let Some(tx) = lock(&pending).remove(&counter) {
                    let _ = tx.send(Err(error));
                }
            }
            continue;
        }
        // Bound to its request (`to`, `re`, checked when opened): an answer played again
        // finds no request waiting, so no replay window is needed.
        let Some((header, answer)) = ear.open::<Answer>(&msg.payload, b"") else {
            continue;
        };
        if let Some(h) = header {
            // A hello's world is the process that sealed it.
            if matches!(&answer, Answer::Hello { world, .. } if *world != h.sender) {
                ear.refuse(Refusal::Forged, Some(h.sender));
                continue;
            }
        }
        if let Some(tx) = lock(&pending).remove(&counter) {
            let _ = tx.send(Ok(answer));
        }
    }
}
