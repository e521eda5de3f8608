//! The lossy relay on its own: an echo server behind it, datagrams through it with delay,
//! seeded loss, a socket of its own per client, and nothing left running once dropped.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use roam_tests::relay::{Direction, Relay, RelayConfig};
use tokio::net::UdpSocket;

/// An echo server: each datagram goes back to its sender, prefixed with the sender's port
/// (so a client can tell which upstream socket the relay used for it).
async fn echo() -> Result<(SocketAddr, tokio::task::JoinHandle<()>)> {
    let socket = UdpSocket::bind("127.0.0.1:0").await.context("binding")?;
    let addr = socket.local_addr().context("its address")?;
    let task = tokio::spawn(async move {
        let mut buf = vec![0u8; 2048];
        while let Ok((len, from)) = socket.recv_from(&mut buf).await {
            let mut reply = from.port().to_le_bytes().to_vec();
            reply.extend_from_slice(&buf[..len]);
            let _ = socket.send_to(&reply, from).await;
        }
    });
    Ok((addr, task))
}

async fn client(relay: SocketAddr) -> Result<UdpSocket> {
    let socket = UdpSocket::bind("127.0.0.1:0").await.context("binding")?;
    socket.connect(relay).await.context("connecting")?;
    Ok(socket)
}

#[tokio::test]
async fn delays_each_way_and_keeps_clients_apart() -> Result<()> {
    let (server, _echo) = echo().await?;
    let delay = Direction {
        delay: Duration::from_millis(30),
        ..Direction::NONE
    };
    let relay = Relay::start(server, RelayConfig::symmetric(delay, 1)).await?;
    let (a, b) = (client(relay.addr()).await?, client(relay.addr()).await?);
    let mut ports = Vec::new();
    for (socket, text) in [(&a, b"a"), (&b, b"b")] {
        let sent = Instant::now();
        socket.send(text).await?;
        let mut buf = [0u8; 64];
        let len = tokio::time::timeout(Duration::from_secs(2), socket.recv(&mut buf))
            .await
            .context("no echo within 2 s")??;
        let took = sent.elapsed();
        assert!(took >= Duration::from_millis(60), "round trip {took:?}");
        assert_eq!(&buf[2..len], text);
        ports.push(u16::from_le_bytes([buf[0], buf[1]]));
    }
    assert_ne!(
        ports[0], ports[1],
        "each client has an upstream socket of its own"
    );
    let stats = relay.stats();
    assert_eq!(
        (stats.to_server.forwarded, stats.to_client.forwarded),
        (2, 2)
    );
    assert_eq!(stats.to_server.dropped() + stats.to_client.dropped(), 0);
    Ok(())
}

/// Sends `n` numbered datagrams through a relay losing `loss` towards the server and
/// returns which came back.
async fn survivors(loss: f64, seed: u64, n: u32) -> Result<Vec<u32>> {
    let (server, _echo) = echo().await?;
    let config = RelayConfig {
        to_server: Direction {
            loss,
            ..Direction::NONE
        },
        to_client: Direction::NONE,
        seed,
    };
    let relay = Relay::start(server, config).await?;
    let socket = std::sync::Arc::new(client(relay.addr()).await?);
    // Read as the echoes come: a socket's receive buffer holds only a few hundred.
    let reader = {
        let socket = socket.clone();
        tokio::spawn(async move {
            let mut got = Vec::new();
            let mut buf = [0u8; 64];
            while let Ok(Ok(len)) =
                tokio::time::timeout(Duration::from_millis(300), socket.recv(&mut buf)).await
            {
                if len == 6 {
                    got.push(u32::from_le_bytes([buf[2], buf[3], buf[4], buf[5]]));
                }
            }
            got
        })
    };
    for i in 0..n {
        socket.send(&i.to_le_bytes()).await?;
        // Paced, so that no socket buffer on the way drops anything.
        if i % 20 == 19 {
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    }
    let mut got = reader.await.context("the reader")?;
    got.sort_unstable();
    let stats = relay.stats();
    assert_eq!(stats.to_server.forwarded as usize, got.len());
    assert_eq!(stats.to_server.lost as usize, n as usize - got.len());
    Ok(got)
}

#[tokio::test]
async fn loses_about_the_loss_the_same_for_a_seed() -> Result<()> {
    let n = 2000;
    let first = survivors(0.1, 7, n).await?;
    let lost = n as usize - first.len();
    assert!((140..260).contains(&lost), "{lost} of {n} lost at 10%");
    assert_eq!(
        first,
        survivors(0.1, 7, n).await?,
        "the same seed, the same drops"
    );
    assert_ne!(
        first,
        survivors(0.1, 8, n).await?,
        "another seed, other drops"
    );
    Ok(())
}

#[tokio::test]
async fn stops_when_stopped() -> Result<()> {
    let (server, _echo) = echo().await?;
    let relay = Relay::start(server, RelayConfig::default()).await?;
    let addr = relay.addr();
    let socket = client(addr).await?;
    socket.send(b"x").await?;
    let mut buf = [0u8; 64];
    tokio::time::timeout(Duration::from_secs(2), socket.recv(&mut buf))
        .await
        .context("no echo within 2 s")??;
    relay.stop().await;
    UdpSocket::bind(addr)
        .await
        .context("the relay's port is free once it is dropped")?;
    Ok(())
}
