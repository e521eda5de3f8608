//! An edge of a test world as a process of its own, so that a test can kill it (`kill -9`)
//! as an operator's machine dies: the test terrain ([`roam_tests::fixtures::flat`]) served
//! on `127.0.0.1:0` with the identity kept in `STATE_DIR` (edges given one directory share
//! one fingerprint), its world on NATS.
//!
//! ```text
//! roam-test-edge NATS_URL WORLD STATE_DIR
//! ```
//!
//! Prints `listening on ADDR` and `fingerprint HEX` once it serves, then serves until
//! killed.

use std::path::Path;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use roam_server::net::Options;
use roam_server::net::bus::BusOptions;
use roam_server::net::bus::edge::Remote;
use roam_tests::fixtures;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [url, world, state] = args.as_slice() else {
        bail!("usage: roam-test-edge NATS_URL WORLD STATE_DIR");
    };
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
        let terrain = fixtures::flat();
        let bus = BusOptions {
            url: url.clone(),
            world: world.clone(),
            creds: None,
            name: "roam-test-edge".into(),
        };
        let remote = Remote::connect(
            &bus,
            terrain.content_hash(),
            "the test terrain",
            Vec::new(),
            Duration::from_secs(10),
        )
        .await?;
        let identity = roam_link::tls::load_or_create(Path::new(state))
            .with_context(|| format!("the identity in {state}"))?;
        let running = fixtures::serve_as(
            terrain,
            roam_protocol::tiles::DEFAULT_TILE,
            &identity,
            |o| Options {
                remote: Some(remote.clone()),
                ..o
            },
        );
        remote.set_addresses(vec![running.server.addr.to_string()]);
        println!("listening on {}", running.server.addr);
        println!("fingerprint {}", identity.fingerprint());
        std::future::pending::<()>().await;
        Ok(())
    })
}
