//! An edge of a test world as a process of its own, so that a test can kill it (`kill -9`)
//! as an operator's machine dies: the test terrain ([`roam_tests::fixtures::flat`]) served
//! on `127.0.0.1:0` with the identity kept in `STATE_DIR` (edges given one directory share
//! one fingerprint), its world on NATS. With `--web`, it serves the page too (`web/dist`,
//! a certificate made for `127.0.0.1`) and names its WebTransport URL among its addresses.
//!
//! ```text
//! roam-test-edge NATS_URL WORLD STATE_DIR [--web]
//! ```
//!
//! Prints `listening on ADDR`, `fingerprint HEX` and with `--web` `web on ADDR` once it
//! serves, then serves until killed.
// A tool whose output is its figures or its addresses, on stdout.
#![allow(clippy::print_stdout)]

use std::path::Path;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use roam_server::net::Options;
use roam_server::net::bus::BusOptions;
use roam_server::net::bus::edge::Remote;
use roam_server::net::web::{WebCert, WebOptions};
use roam_tests::fixtures;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (url, world, state, web) = match args.as_slice() {
        [url, world, state] => (url, world, state, false),
        [url, world, state, flag] if flag == "--web" => (url, world, state, true),
        _ => bail!("usage: roam-test-edge NATS_URL WORLD STATE_DIR [--web]"),
    };
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
        let terrain = fixtures::flat();
        let bus = BusOptions {
            url: url.clone(),
            world: world.clone(),
            creds: None,
            ca: None,
            name: "roam-test-edge".into(),
            secret: Some(roam_tests::nats::test_secret(world)),
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
                web: web.then(|| WebOptions {
                    listen: "127.0.0.1:0".parse().expect("a literal address"),
                    page: roam_tests::browser::built_page(),
                    cert: WebCert::Made {
                        names: vec!["127.0.0.1".into()],
                    },
                }),
                ..o
            },
        );
        let mut addresses = vec![running.server.addr.to_string()];
        if let Some(web) = running.server.web_addr() {
            let hashes = running.server.web_hashes();
            addresses.push(roam_server::web::transport_url(
                "127.0.0.1",
                web.port(),
                &hashes,
            ));
        }
        remote.set_addresses(addresses);
        println!("listening on {}", running.server.addr);
        println!("fingerprint {}", identity.fingerprint());
        if let Some(web) = running.server.web_addr() {
            println!("web on {web}");
        }
        std::future::pending::<()>().await;
        Ok(())
    })
}
