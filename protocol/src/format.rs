//! What the decoders share: the payload format numbers (a mesh frame, a change frame, a
//! colour map) and `DecodeError`, the one error type all three report.

/// The mesh codec's payload format ([`crate::codec`]).
pub const MESH: u8 = 1;
/// A change frame's payload format ([`crate::changes`]).
pub const CHANGES: u8 = 2;
/// The colour map codec's payload format ([`crate::colormap`]).
pub const COLORMAP: u8 = 1;

/// Why a payload could not be decoded. A mesh frame is to be dropped (and a key frame
/// asked for); nothing of it is shown. The colour map codec ([`crate::colormap`]) reports
/// its errors with the same type.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    #[error("payload of {0} bytes: shorter than its header")]
    Short(usize),
    #[error(
        "payload format {0}; this build reads mesh formats {MESH} and {CHANGES} and colour \
         map format {COLORMAP}"
    )]
    Format(u8),
    #[error("mesh for a grid of 2^{got} + 1, expected 2^{expected} + 1")]
    Grid { got: u8, expected: u32 },
    #[error("a delta frame without its base, or a key frame given one")]
    Base,
    #[error("{declared} triangles declared, more than the {limit} allowed")]
    TooBig { declared: u32, limit: u32 },
    #[error("the coded payload is corrupt: {0}")]
    Corrupt(&'static str),
    #[error("the decoded payload does not match its check (a mesh coded against another base?)")]
    Check,
    /// A colour map payload for another size than the one asked for.
    #[error("colour map of {got} cells a side, expected {expected}")]
    Cells { got: u32, expected: u32 },
}
