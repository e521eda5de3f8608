//! [`lock`]: a `std::sync::Mutex` locked whether or not a thread panicked holding it, the
//! one way roam's code locks one; [`wait`], a `Condvar` waited on the same way.
//!
//! **Why poison is ignored.** Every mutex in roam guards state that is whole between
//! statements (a queue, a pool, counters, a cache, the newest of something): no invariant
//! is broken for a while under a lock and mended later, so a panic while holding one
//! leaves nothing half done that the next holder could trip on. Propagating the poison
//! would instead turn one task's panic (one viewer's, one worker thread's) into a panic in
//! every task that shares the lock: the server would stop serving everyone for one
//! viewer's bug, and the viewer would stop drawing for one reader's.
//!
//! **Why here.** The server, the viewer and the test helpers all lock mutexes, and
//! `roam-protocol` is the one crate all of them depend on. It is `std` only: no thread,
//! clock or I/O, so the protocol crate stays pure.

use std::sync::{Condvar, Mutex, MutexGuard, PoisonError};

/// Locks `m`, taking the guard of a poisoned mutex as it is (see the module's header).
pub fn lock<T: ?Sized>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Waits on `c` with `guard`, taking the guard back from a poisoned mutex as it is (as
/// [`lock`]).
pub fn wait<'a, T>(c: &Condvar, guard: MutexGuard<'a, T>) -> MutexGuard<'a, T> {
    c.wait(guard).unwrap_or_else(PoisonError::into_inner)
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use super::lock;

    /// A mutex whose holder panicked is locked anyway, its value as the holder left it.
    #[test]
    fn a_poisoned_mutex_locks_with_its_value() {
        let m = Mutex::new(vec![1]);
        let panicked = std::panic::catch_unwind(|| {
            let mut held = m.lock().expect("not poisoned yet");
            held.push(2);
            panic!("a holder panics");
        });
        assert!(panicked.is_err() && m.is_poisoned());
        lock(&m).push(3);
        assert_eq!(*lock(&m), [1, 2, 3]);
    }
}
