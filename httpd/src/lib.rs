//! The HTTP side both daemons serve with `--http ADDR`: the listener (plain TCP, or TLS
//! with the daemon's own certificate, each connection knowing its peer), the task that
//! serves a router on it in the background, and the health endpoints every daemon
//! answers. The coordinator adds its metrics, status page, studio and controls
//! (`coordinator::http`); a worker serves its health alone. Kept below both, so that
//! neither daemon takes this from the other.

mod listener;

use std::sync::Arc;

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use tokio::net::TcpListener;
use transport::ServerTls;

pub use listener::{HttpListener, Peer, HANDSHAKE_TIMEOUT, MAX_HANDSHAKES};

/// Serves `routes` on `listener` in the background, with TLS when `tls` is given, until
/// the returned guard is dropped.
pub fn spawn(listener: TcpListener, tls: Option<ServerTls>, routes: Router) -> Serving {
    Serving(tokio::spawn(async move {
        use axum::serve::ListenerExt;
        // The peer's address decides who may use the coordinator's controls without a
        // secret; the (empty) tap gives the listener axum's connection info of its
        // address type.
        let service = routes.into_make_service_with_connect_info::<Peer>();
        let listener = HttpListener::new(listener, tls).tap_io(|_| {});
        if let Err(e) = axum::serve(listener, service).await {
            tracing::error!(error = %e, "the HTTP listener failed");
        }
    }))
}

/// An HTTP listener serving in the background; dropping it stops the listener.
pub struct Serving(tokio::task::JoinHandle<()>);

impl Drop for Serving {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// A readiness answer: 200 `ready: {yes}` or 503 `not ready: {no}`, one line each.
fn readiness(ready: bool, yes: &'static str, no: &'static str) -> Response {
    if ready {
        (StatusCode::OK, format!("ready: {yes}\n")).into_response()
    } else {
        (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("not ready: {no}\n"),
        )
            .into_response()
    }
}

/// A worker's endpoints: alive, and ready while `ready` says it is connected.
pub fn worker_routes(ready: Arc<dyn Fn() -> bool + Send + Sync>) -> Router {
    Router::new()
        .route("/healthz", get(|| async { "ok\n" }))
        .route(
            "/readyz",
            get(move || async move {
                readiness(
                    ready(),
                    "connected to a coordinator",
                    "not connected to a coordinator",
                )
            }),
        )
}
