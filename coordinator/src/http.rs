//! The HTTP side of the daemons (`--http ADDR`): health for supervisors, Prometheus
//! metrics, and the coordinator's status page with live previews.
//!
//! It only reads: nothing here can submit, cancel or change a job, so it needs no
//! authentication beyond where it listens (loopback unless told otherwise).

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::{header, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use protocol::JobId;
use tokio::net::TcpListener;

use crate::server::{Observer, Picture};

/// The status page: one self-contained file, polling `/api/status`.
const STATUS_PAGE: &str = include_str!("status.html");

/// The coordinator's endpoints.
pub fn coordinator_routes(observer: Observer) -> Router {
    Router::new()
        .route("/", get(|| async { Html(STATUS_PAGE) }))
        .route("/api/status", get(status))
        .route("/jobs/{id}/image.png", get(picture))
        .route("/metrics", get(metrics))
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(coordinator_ready))
        .with_state(observer)
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

/// Serves `routes` on `listener` in the background until the returned guard is
/// dropped.
pub fn spawn(listener: TcpListener, routes: Router) -> Serving {
    Serving(tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, routes).await {
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

async fn coordinator_ready(State(observer): State<Observer>) -> Response {
    match observer.not_ready() {
        None => (StatusCode::OK, "ready: accepting jobs\n").into_response(),
        Some(reason) => (StatusCode::SERVICE_UNAVAILABLE, format!("{reason}\n")).into_response(),
    }
}

async fn status(State(observer): State<Observer>) -> Response {
    let farm = tokio::task::spawn_blocking(move || observer.farm()).await;
    match farm {
        Ok(farm) => ([(header::CACHE_CONTROL, "no-store")], Json(farm)).into_response(),
        Err(_) => StatusCode::INTERNAL_SERVER_ERROR.into_response(),
    }
}

async fn picture(State(observer): State<Observer>, Path(id): Path<JobId>) -> Response {
    let picture = tokio::task::spawn_blocking(move || observer.picture(id)).await;
    let png = match picture {
        Ok(Some(Picture::Final(png))) => png,
        Ok(Some(Picture::Preview(png))) => png,
        Ok(None) => {
            return (StatusCode::NOT_FOUND, format!("no image for job {id}\n")).into_response()
        }
        Err(_) => return StatusCode::INTERNAL_SERVER_ERROR.into_response(),
    };
    (
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        png,
    )
        .into_response()
}

async fn metrics(State(observer): State<Observer>) -> Response {
    let text = tokio::task::spawn_blocking(move || observer.metrics()).await;
    match text {
        Ok(text) => (
            [(
                header::CONTENT_TYPE,
                "application/openmetrics-text; version=1.0.0; charset=utf-8",
            )],
            text,
        )
            .into_response(),
        Err(_) => StatusCode::INTERNAL_SERVER_ERROR.into_response(),
    }
}
