//! What `tests/tests/it/docs.rs` needs to check the documents against the repository:
//! reading Markdown into tokens ([`markdown`]), and the workspace's packages, sources and
//! names ([`code`]); running the binaries for their `--help` ([`binaries`]).

pub mod binaries;
pub mod code;
pub mod markdown;
