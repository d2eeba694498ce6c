//! The whole coordinator daemon: the farm's server and, with `--http`, its status page,
//! metrics and health beside it. The two are put together here rather than one
//! starting the other, so that neither module depends on the other: the HTTP side
//! reads the server only through its [`Observer`](crate::server::Observer).

use std::future::Future;

use anyhow::Result;

use crate::http;
use crate::server::{Config, Server};

/// Serves `server`, and its HTTP side if it has one, until `shutdown` completes. The
/// HTTP side stays up through the graceful shutdown (readiness says so), and stops
/// once the server has.
pub async fn run(mut server: Server, shutdown: impl Future<Output = ()>) -> Result<()> {
    let _stop_http = server.take_http().map(|(listener, tls)| {
        httpd::spawn(listener, tls, http::coordinator_routes(server.observer()))
    });
    server.run(shutdown).await
}

/// Binds and serves: the whole daemon.
pub async fn serve(config: Config, shutdown: impl Future<Output = ()>) -> Result<()> {
    run(Server::bind(config).await?, shutdown).await
}
