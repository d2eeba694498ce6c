//! The first moments of a connection: TLS, the `Hello`, authentication; then the
//! peer is handed to its session ([`super::client_session`] or
//! [`super::worker_session`]).

use std::sync::Arc;
use std::time::Duration;

use anyhow::Result;
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use protocol::{CoordinatorChallenge, Hello, MessageCodec, Role, Welcome};
use tokio::net::TcpStream;
use tokio_util::codec::{Framed, LengthDelimitedCodec};
use tracing::info;
use transport::{Stream, TLS_HANDSHAKE_RECORD};

use super::keys::KeyHold;
use super::{client_session, worker_session, Shared};
use crate::keyring::Choice;

/// Sends a refusal the peer can read, then closes.
pub(super) async fn refuse(stream: Stream, reason: String) {
    let mut framed = Framed::new(stream, LengthDelimitedCodec::new());
    let refusal = protocol::wire::encode(&Welcome::Refused { reason });
    let _ = framed.send(Bytes::from(refusal)).await;
}

/// Mutual challenge-response with the secret of the peer's role: the coordinator proves
/// it knows the secret first (over the peer's nonce and a fresh one of its own), then the
/// peer answers with its proof. A wrong, unreadable or missing proof is refused.
async fn authenticate(
    framed: &mut Framed<Stream, LengthDelimitedCodec>,
    hello: &Hello,
    secret: &[u8],
    timeout: Duration,
) -> Result<()> {
    let mut nonce = [0u8; 32];
    getrandom::fill(&mut nonce).map_err(|e| anyhow::anyhow!("no randomness for a nonce: {e}"))?;
    let challenge = CoordinatorChallenge::new(hello, secret, nonce);
    framed
        .send(Bytes::from(protocol::wire::encode(&challenge.welcome())))
        .await?;
    let reason = match tokio::time::timeout(timeout, framed.next()).await {
        Ok(Some(Ok(frame))) => match challenge.check(&frame) {
            Ok(()) => return Ok(()),
            Err(failure) => failure.to_string(),
        },
        // The peer hung up rather than prove: it did not accept this coordinator's proof
        // (a token of another role or farm), or it has no token.
        Ok(None | Some(Err(_))) => anyhow::bail!(
            "the {} closed the connection instead of proving its token",
            hello.role.auth_role()
        ),
        Err(_) => format!(
            "authentication failed: no proof within {} ms",
            timeout.as_millis()
        ),
    };
    let refusal = Welcome::Refused {
        reason: reason.clone(),
    };
    let _ = framed
        .send(Bytes::from(protocol::wire::encode(&refusal)))
        .await;
    anyhow::bail!(reason)
}

/// Completes the TLS handshake when the coordinator serves TLS (by `deadline`); a peer
/// that speaks plain protocol to it is told, in plain protocol, what to do instead.
pub(super) async fn secure(
    shared: &Shared,
    stream: TcpStream,
    deadline: tokio::time::Instant,
) -> Result<Stream> {
    let Some(tls) = &shared.tls else {
        return Ok(Box::new(stream));
    };
    let mut first = [0u8; 1];
    match tokio::time::timeout_at(deadline, stream.peek(&mut first)).await {
        Ok(Ok(1)) if first[0] == TLS_HANDSHAKE_RECORD => {}
        Ok(Ok(1)) => {
            refuse(
                Box::new(stream),
                "this coordinator speaks TLS only: connect with --tls-fingerprint (or --tls-ca)"
                    .into(),
            )
            .await;
            anyhow::bail!("a plain connection to the TLS port");
        }
        _ => anyhow::bail!("no TLS handshake within the time limit"),
    }
    match tokio::time::timeout_at(deadline, tls.accept(stream)).await {
        Ok(Ok(stream)) => Ok(stream),
        Ok(Err(e)) => Err(anyhow::Error::from(e).context("TLS handshake failed")),
        Err(_) => anyhow::bail!("no TLS handshake within the time limit"),
    }
}

/// What a browser or `curl` sees when pointed at the protocol port.
const NOT_HTTP: &[u8] = b"HTTP/1.0 400 Bad Request\r\nContent-Type: text/plain\r\nConnection: close\r\n\r\nThis port speaks the Tessera protocol, not HTTP (see docs/protocol.md).\r\n";

pub(super) async fn handle_connection(
    shared: Arc<Shared>,
    mut stream: TcpStream,
    peer: std::net::IpAddr,
) -> Result<()> {
    stream.set_nodelay(true)?;
    // An HTTP request would read as a frame length of over a gigabyte: answer it in
    // its own language instead.
    let mut start = [0u8; 4];
    // One deadline for the whole handshake, however its reads are split.
    let deadline = tokio::time::Instant::now() + shared.handshake_timeout;
    if let Ok(Ok(4)) = tokio::time::timeout_at(deadline, stream.peek(&mut start)).await {
        if [
            &b"GET "[..],
            b"POST",
            b"HEAD",
            b"PUT ",
            b"OPTI",
            b"DELE",
            b"PATC",
            b"CONN",
        ]
        .contains(&&start[..])
        {
            use tokio::io::AsyncWriteExt;
            let _ = stream.write_all(NOT_HTTP).await;
            let _ = stream.shutdown().await;
            anyhow::bail!("an HTTP request on the protocol port");
        }
    }
    let stream = secure(&shared, stream, deadline).await?;
    let mut framed = Framed::new(stream, protocol::frame_codec(shared.max_frame));
    let first = match tokio::time::timeout_at(deadline, framed.next()).await {
        Err(_) => {
            let refusal = Welcome::Refused {
                reason: format!(
                    "no handshake within {} ms",
                    shared.handshake_timeout.as_millis()
                ),
            };
            let _ = framed
                .send(Bytes::from(protocol::wire::encode(&refusal)))
                .await;
            anyhow::bail!("no handshake within the time limit");
        }
        Ok(None) => anyhow::bail!("peer closed before its handshake"),
        Ok(Some(Err(e))) => {
            // Too long a frame (refused from its length prefix) or a broken stream.
            let refusal = Welcome::Refused {
                reason: format!("unreadable handshake: {e}"),
            };
            let _ = framed
                .send(Bytes::from(protocol::wire::encode(&refusal)))
                .await;
            return Err(anyhow::Error::from(e).context("unreadable handshake"));
        }
        Ok(Some(Ok(frame))) => frame,
    };
    let hello = match Hello::from_frame(&first) {
        Ok(hello) => hello,
        Err(e) => {
            let refusal = protocol::wire::encode(&Welcome::Refused {
                reason: e.to_string(),
            });
            let _ = framed.send(Bytes::from(refusal)).await;
            return Err(e.into());
        }
    };
    // The hello names the secret the peer holds by its key id: the coordinator proves
    // that one (the current secret, or the previous within an overlap window).
    let choice = shared
        .keys
        .borrow()
        .choose(hello.role.auth_role(), hello.key, shared.now());
    let hold = match choice {
        Choice::Open => None,
        Choice::Prove { secret, held } => {
            authenticate(&mut framed, &hello, &secret, shared.handshake_timeout).await?;
            Some(KeyHold::new(&shared, held))
        }
        Choice::Refuse(refusal) => {
            let reason = refusal.to_string();
            let refusal = protocol::wire::encode(&Welcome::Refused {
                reason: reason.clone(),
            });
            let _ = framed.send(Bytes::from(refusal)).await;
            anyhow::bail!(reason);
        }
    };
    // A worker's tags name pools in listings, metrics and autoscalers' queries: one
    // that breaks their grammar is refused before it joins, with the tag named.
    let mut hello = hello;
    if let Role::Worker { tags, .. } = &mut hello.role {
        match protocol::check_tags(tags) {
            Ok(sorted) => *tags = sorted,
            Err(why) => {
                let reason = format!("invalid worker tags: {why}");
                let refusal = protocol::wire::encode(&Welcome::Refused {
                    reason: reason.clone(),
                });
                let _ = framed.send(Bytes::from(refusal)).await;
                anyhow::bail!(reason);
            }
        }
    }
    let accepted = protocol::wire::encode(&Welcome::Accepted {
        version: protocol::PROTOCOL_VERSION,
    });
    framed.send(Bytes::from(accepted)).await?;
    let max_frame = shared.max_frame;
    match hello.role {
        Role::Client => {
            if let Some(hold) = &hold {
                info!(%peer, key = %hold.describe(), "client authenticated");
            }
            let framed = framed.map_codec(|_| MessageCodec::new(max_frame));
            client_session::serve(shared, framed, peer, hold).await
        }
        Role::Worker {
            name,
            threads,
            build,
            tags,
        } => {
            let framed = framed.map_codec(|_| MessageCodec::new(max_frame));
            let worker = worker_session::Joining {
                name,
                threads,
                build,
                tags,
            };
            worker_session::serve(shared, framed, peer, worker, hold).await
        }
    }
}
