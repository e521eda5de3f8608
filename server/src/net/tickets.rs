//! Drivers' tickets: what one names ([`Claim`]), fresh random tickets and join tokens
//! from the system's random source, and how a secret a peer sends is compared with ours
//! ([`secret_eq`]).
//!
//! **Secrets are compared in constant time whatever their lengths.** A byte-wise compare
//! that returns early when the lengths differ tells, in principle, a peer timing its
//! guesses how long the secret is. [`secret_eq`] hashes both sides with blake3 (the work
//! depends on each side's own length only: the peer's, which it knows, and the secret's,
//! the same for every guess) and compares the two 32-byte digests with `blake3::Hash`'s
//! equality, which is constant time (its documentation says so). Equal digests mean equal
//! secrets (a collision of blake3 is not a risk this server guards against). Every token
//! the server checks goes through it: the join token and the control token of a replay
//! (`handshake.rs`). Tickets are looked up in a map keyed by the whole ticket (SipHash
//! with a random key), not compared byte by byte.

use roam_protocol::messages::Ticket;
use tokio::sync::oneshot;

use crate::sim::world::VehicleId;

/// What a ticket names: the vehicle, and how to end the connection driving it now.
pub(super) struct Claim {
    pub(super) vehicle: VehicleId,
    pub(super) replace: Option<oneshot::Sender<oneshot::Sender<()>>>,
}

/// Whether the secret `got` (from a peer) is `want` (ours), in constant time whatever
/// either's length (see the module docs): the comparison is of their blake3 digests,
/// never of the bytes, so no length is compared and nothing returns early.
pub(crate) fn secret_eq(got: &[u8], want: &[u8]) -> bool {
    blake3::hash(got) == blake3::hash(want)
}

/// A fresh random ticket (128 bits), for a driver's new vehicle.
pub(crate) fn random_ticket() -> Ticket {
    use ring::rand::SecureRandom;
    let mut t = [0u8; 16];
    ring::rand::SystemRandom::new()
        .fill(&mut t)
        .expect("the system's random source works");
    t
}

/// A fresh random join token (32 hex digits: 128 bits), for a server started in process.
pub fn random_token() -> String {
    use ring::rand::SecureRandom;
    let mut bytes = [0u8; 16];
    ring::rand::SystemRandom::new()
        .fill(&mut bytes)
        .expect("the system's random source works");
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::secret_eq;

    fn check(got: &str, want: &str, expected: bool) {
        assert_eq!(
            secret_eq(got.as_bytes(), want.as_bytes()),
            expected,
            "{got:?} against {want:?}"
        );
    }

    #[test]
    fn secrets_are_equal_only_when_every_byte_is() {
        let token = "0123456789abcdef0123456789abcdef";
        check(token, token, true);
        check("", "", true);
        // Different, the same length: the first byte, the last, a middle one.
        check("1123456789abcdef0123456789abcdef", token, false);
        check("0123456789abcdef0123456789abcdee", token, false);
        check("0123456789abcdeF0123456789abcdef", token, false);
        // Different lengths: a prefix, a longer one, empty against a secret and the reverse.
        check("0123456789abcdef", token, false);
        check(&format!("{token}0"), token, false);
        check("", token, false);
        check(token, "", false);
        check("\0", "", false);
    }

    /// Structural: every token the handshake checks is compared through [`secret_eq`],
    /// and `secret_eq` compares fixed-size digests, never the bytes or their lengths (a
    /// compare that answers "different" at once for a different length leaks the length).
    #[test]
    fn tokens_are_compared_through_digests_only() {
        let handshake = include_str!("handshake.rs");
        let code: Vec<&str> = handshake
            .lines()
            .map(str::trim_start)
            .filter(|l| !l.starts_with("//"))
            .collect();
        for line in code.iter().filter(|l| l.contains("token.as_bytes()")) {
            assert!(
                line.contains("secret_eq("),
                "handshake.rs compares a token otherwise: {line}"
            );
        }
        assert!(
            code.iter().any(|l| l.contains("secret_eq(hello.token")),
            "the hello's token is compared with secret_eq"
        );
        assert!(
            !code.iter().any(|l| l.contains("fn constant_time_eq")),
            "handshake.rs has a comparison of its own"
        );
        let this = include_str!("tickets.rs");
        let body = this
            .split("fn secret_eq(")
            .nth(1)
            .and_then(|rest| rest.split("\n}").next())
            .expect("tickets.rs defines secret_eq");
        assert!(
            body.contains("blake3::hash(got) == blake3::hash(want)") && !body.contains("len()"),
            "secret_eq must compare the digests only: {body}"
        );
    }
}
