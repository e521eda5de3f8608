//! `identity`: the server's identity in its state directory, shown or replaced, so that an
//! operator can read the fingerprint to give viewers without starting `serve`, and rotate
//! it when the key may have leaked. The rules (modes, atomic writes, refusing half or
//! broken identities) are `roam_link::tls`'s, the same as `serve` uses.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use roam_link::tls;

#[derive(Args)]
pub(crate) struct IdentityArgs {
    /// Where the certificate is kept (made here if there is none).
    #[arg(long, default_value = "roam-state")]
    pub state_dir: PathBuf,
    /// Replace the identity with a new one: every viewer will need the new fingerprint. A
    /// running server keeps the old one until it restarts.
    #[arg(long)]
    pub rotate: bool,
}

/// Prints `fingerprint HEX` (the line `serve` prints too); with `--rotate`, first
/// `old fingerprint HEX` (or `no identity before`).
pub(crate) fn identity(args: IdentityArgs) -> Result<()> {
    let dir = &args.state_dir;
    let context = || format!("the identity in {}", dir.display());
    let id = if args.rotate {
        let rotated = tls::rotate(dir).with_context(context)?;
        match &rotated.old {
            Some(old) => say!("old fingerprint {old}"),
            None => say!("no identity before"),
        }
        rotated.new
    } else {
        tls::load_or_create(dir).with_context(context)?
    };
    say!("fingerprint {}", id.fingerprint());
    Ok(())
}
