//! The listener: plain TCP, or TLS with the daemon's own certificate.
//!
//! The handshakes run in tasks of their own (at most [`MAX_HANDSHAKES`] at once, each
//! within [`HANDSHAKE_TIMEOUT`]), so that a peer that connects and says nothing holds
//! up no one. A peer that speaks plain HTTP to the TLS port is served too, marked as
//! such ([`Peer::tls`]): health and readiness answer it, for supervisors that cannot
//! speak TLS, and everything else tells it to use `https://`, instead of a connection
//! closed without a word.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, Semaphore};
use transport::{ServerTls, Stream};

/// Time a peer has to complete its TLS handshake.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// Handshakes in progress at once; more connections wait to be accepted.
pub const MAX_HANDSHAKES: usize = 64;

/// Who is connected: the peer's address, and whether it came over TLS.
#[derive(Clone, Copy, Debug)]
pub struct Peer {
    pub addr: SocketAddr,
    /// Over TLS (always, when the listener has none: then nothing is).
    pub tls: bool,
}

/// Connections ready to be served: accepted, and with TLS past their handshake.
pub struct HttpListener {
    ready: mpsc::Receiver<(Stream, Peer)>,
    local: SocketAddr,
    accepting: tokio::task::JoinHandle<()>,
}

impl HttpListener {
    /// Starts accepting on `listener`, with TLS when `tls` is given.
    pub fn new(listener: TcpListener, tls: Option<ServerTls>) -> HttpListener {
        let local = listener
            .local_addr()
            .unwrap_or_else(|_| SocketAddr::from(([0, 0, 0, 0], 0)));
        let (sender, ready) = mpsc::channel(MAX_HANDSHAKES);
        let accepting = tokio::spawn(accept_loop(listener, tls.map(Arc::new), sender));
        HttpListener {
            ready,
            local,
            accepting,
        }
    }
}

impl Drop for HttpListener {
    fn drop(&mut self) {
        self.accepting.abort();
    }
}

impl axum::serve::Listener for HttpListener {
    type Io = Stream;
    type Addr = Peer;

    async fn accept(&mut self) -> (Stream, Peer) {
        match self.ready.recv().await {
            Some(connection) => connection,
            // The accepting task ended (it does not, short of a panic): serve no more.
            None => std::future::pending().await,
        }
    }

    fn local_addr(&self) -> std::io::Result<Peer> {
        Ok(Peer {
            addr: self.local,
            tls: false,
        })
    }
}

async fn accept_loop(
    listener: TcpListener,
    tls: Option<Arc<ServerTls>>,
    ready: mpsc::Sender<(Stream, Peer)>,
) {
    let handshakes = Arc::new(Semaphore::new(MAX_HANDSHAKES));
    loop {
        let (tcp, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(e) => {
                // Out of descriptors, mostly: wait for some to close.
                tracing::warn!(error = %e, "HTTP accept failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Some(tls) = &tls else {
            let peer = Peer {
                addr: peer,
                tls: false,
            };
            if ready.send((Box::new(tcp), peer)).await.is_err() {
                return;
            }
            continue;
        };
        let Ok(permit) = Arc::clone(&handshakes).acquire_owned().await else {
            return;
        };
        let (tls, ready) = (Arc::clone(tls), ready.clone());
        tokio::spawn(async move {
            let _permit = permit;
            match tokio::time::timeout(HANDSHAKE_TIMEOUT, handshake(&tls, tcp)).await {
                Ok(Ok((stream, tls))) => {
                    let _ = ready.send((stream, Peer { addr: peer, tls })).await;
                }
                Ok(Err(e)) => tracing::debug!(%peer, error = %e, "HTTPS handshake failed"),
                Err(_) => tracing::debug!(%peer, "HTTPS handshake timed out"),
            }
        });
    }
}

/// The connection past its TLS handshake, or as it is for a peer that speaks plain
/// text: the stream, and whether it is over TLS.
async fn handshake(tls: &ServerTls, tcp: TcpStream) -> std::io::Result<(Stream, bool)> {
    let mut first = [0u8; 1];
    if tcp.peek(&mut first).await? == 1 && first[0].is_ascii_uppercase() {
        // An HTTP method: `GET /readyz`, or a browser told http://.
        return Ok((Box::new(tcp), false));
    }
    tls.accept(tcp).await.map(|stream| (stream, true))
}
