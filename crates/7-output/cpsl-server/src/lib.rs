//! The `cpsl serve` HTTP server: packages as static files and the browser player.
//!
//! ```text
//! GET /                      the player (embedded, no Node at run time)
//! GET /player/<file>         the player's scripts
//! GET /api/packages          JSON list of the packages under the root (and variant sets)
//! GET /files/<path>          any file under the root: byte ranges, ETag / 304,
//!                            immutable caching of segment files, CORS, gzip/brotli for JSON
//! ```
//!
//! Packages are plain files (see `cpsl-package`), so any static server or CDN can serve
//! them; this one adds what a player wants and refuses what a hostile client tries. It is
//! read-only; every path component is decoded on its own and must be an ordinary name
//! (no `..`, `.`, empty or hidden components, no encoded separators), and the canonical path
//! must stay under the canonical root, so symbolic links cannot lead out of it. Requests are
//! bounded: header read timeout, response timeout, concurrency limit, URI length, no bodies;
//! only GET and HEAD are answered. Shutdown is graceful: open connections finish their
//! requests.

mod assets;
mod files;
mod listing;
mod load;

pub use listing::{list_packages, package_urls, Listing, PackageSummary};
pub use load::{run_load, LoadConfig, LoadReport};

use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::{header, HeaderValue, Method, StatusCode, Uri};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;
use thiserror::Error;
use tokio::net::TcpListener;
use tower::ServiceExt;
use tower_http::compression::predicate::{Predicate, SizeAbove};
use tower_http::compression::CompressionLayer;
use tower_http::cors::{Any, CorsLayer};
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::{DefaultMakeSpan, DefaultOnResponse, TraceLayer};

/// Errors of starting the server.
#[derive(Debug, Error)]
pub enum ServerError {
    /// The root is missing or not a directory.
    #[error("cannot serve {path}: {reason}")]
    Root {
        /// The root given.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// Accepting connections failed.
    #[error("server: {0}")]
    Io(#[from] std::io::Error),
}

/// Server limits.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Most requests handled at once (further ones wait).
    pub max_concurrent: usize,
    /// Most open connections; further ones wait in the listen backlog.
    pub max_connections: usize,
    /// Time a client has to send its request headers.
    pub header_timeout: Duration,
    /// Time to produce a response's headers.
    pub response_timeout: Duration,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            max_concurrent: 1024,
            max_connections: 4096,
            header_timeout: Duration::from_secs(10),
            response_timeout: Duration::from_secs(30),
        }
    }
}

#[derive(Debug)]
struct Shared {
    root: PathBuf,
    cache: Arc<files::FileCache>,
}

/// The application: routes and middleware over the canonical `root`.
pub fn router(root: &Path, cfg: &ServerConfig) -> Result<Router, ServerError> {
    let bad = |reason: String| ServerError::Root {
        path: root.to_path_buf(),
        reason,
    };
    let root = std::fs::canonicalize(root).map_err(|e| bad(e.to_string()))?;
    if !root.is_dir() {
        return Err(bad("not a directory".into()));
    }
    let shared = Arc::new(Shared {
        root,
        cache: Arc::default(),
    });
    // Compress text (manifests, listings, the player) but never video, ranges or tiny bodies.
    let compress = SizeAbove::new(256).and(|_: StatusCode, _, h: &axum::http::HeaderMap, _: &_| {
        h.get(header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .is_some_and(files::compressible)
            && !h.contains_key(header::CONTENT_RANGE)
    });
    let cors = CorsLayer::new()
        .allow_origin(Any)
        .allow_methods([Method::GET, Method::HEAD])
        .allow_headers([
            header::RANGE,
            header::IF_NONE_MATCH,
            header::IF_RANGE,
            header::IF_MODIFIED_SINCE,
        ])
        .expose_headers([
            header::CONTENT_RANGE,
            header::ACCEPT_RANGES,
            header::CONTENT_LENGTH,
            header::ETAG,
        ])
        .max_age(Duration::from_secs(86400));
    Ok(Router::new()
        .route("/", get(assets::index))
        .route("/player/{file}", get(assets::asset))
        .route("/api/packages", get(packages))
        .route("/files/{*path}", get(file))
        .fallback(|| async { files::status(StatusCode::NOT_FOUND) })
        .with_state(shared)
        .layer(axum::middleware::from_fn(guard))
        .layer(
            CompressionLayer::new()
                .gzip(true)
                .br(true)
                .compress_when(compress),
        )
        .layer(cors)
        .layer(tower::limit::ConcurrencyLimitLayer::new(cfg.max_concurrent))
        .layer(TimeoutLayer::with_status_code(
            StatusCode::SERVICE_UNAVAILABLE,
            cfg.response_timeout,
        ))
        // One span and one line per request at INFO (`RUST_LOG=tower_http=info`).
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(DefaultMakeSpan::new().level(tracing::Level::INFO))
                .on_response(DefaultOnResponse::new().level(tracing::Level::INFO)),
        ))
}

/// Refuses what no route should see: long URIs (414) and request bodies (413).
async fn guard(req: Request, next: axum::middleware::Next) -> Response {
    if req.uri().to_string().len() > files::MAX_PATH + 512 {
        return files::status(StatusCode::URI_TOO_LONG);
    }
    let has_body = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .is_some_and(|v| v.as_bytes() != b"0")
        || req.headers().contains_key(header::TRANSFER_ENCODING);
    if has_body {
        return files::status(StatusCode::PAYLOAD_TOO_LARGE);
    }
    next.run(req).await
}

async fn file(State(s): State<Arc<Shared>>, method: Method, uri: Uri, req: Request) -> Response {
    // The raw (still percent-encoded) path, so that encoded separators stay inside components.
    let rel = uri.path().strip_prefix("/files/").unwrap_or("");
    files::serve(&s.root, &s.cache, rel, &method, req.headers()).await
}

async fn packages(State(s): State<Arc<Shared>>) -> Response {
    let root = s.root.clone();
    match tokio::task::spawn_blocking(move || list_packages(&root)).await {
        Ok(list) => {
            let mut r = axum::Json(list).into_response();
            r.headers_mut()
                .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
            r
        }
        Err(_) => files::status(StatusCode::INTERNAL_SERVER_ERROR),
    }
}

/// Serves `app` on `listener` until `shutdown` resolves, then stops accepting and waits for
/// open connections to finish their requests (at most `drain`).
pub async fn serve(
    listener: TcpListener,
    app: Router,
    cfg: &ServerConfig,
    shutdown: impl Future<Output = ()>,
    drain: Duration,
) -> Result<(), ServerError> {
    let mut builder = auto::Builder::new(TokioExecutor::new());
    builder
        .http1()
        .timer(TokioTimer::new())
        .header_read_timeout(cfg.header_timeout)
        .max_buf_size(64 * 1024);
    let builder = Arc::new(builder);
    let graceful = hyper_util::server::graceful::GracefulShutdown::new();
    let slots = Arc::new(tokio::sync::Semaphore::new(cfg.max_connections.max(1)));
    tokio::pin!(shutdown);
    loop {
        let permit = tokio::select! {
            p = slots.clone().acquire_owned() => p.expect("semaphore open"),
            _ = &mut shutdown => break,
        };
        let (stream, peer) = tokio::select! {
            r = listener.accept() => match r {
                Ok(c) => c,
                Err(e) => {
                    // Out of descriptors and the like: back off instead of spinning.
                    tracing::warn!("accept: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            _ = &mut shutdown => break,
        };
        let _ = stream.set_nodelay(true);
        let app = app.clone();
        let service =
            hyper::service::service_fn(move |req: hyper::Request<hyper::body::Incoming>| {
                app.clone().oneshot(req.map(Body::new))
            });
        let conn = builder
            .serve_connection_with_upgrades(TokioIo::new(stream), service)
            .into_owned();
        let conn = graceful.watch(conn);
        tokio::spawn(async move {
            if let Err(e) = conn.await {
                tracing::debug!(%peer, "connection: {e}");
            }
            drop(permit);
        });
    }
    drop(listener);
    tokio::select! {
        _ = graceful.shutdown() => {}
        _ = tokio::time::sleep(drain) => tracing::warn!("connections still open after {drain:?}"),
    }
    Ok(())
}
