//! The service's HTTP server (shell layer, async): the status API, Prometheus
//! `/metrics`, and the live preview page with mask painting.
//!
//! Security model:
//! - Off unless `[http] listen` or `clearview run --http ADDR` says where; the loopback is
//!   the expected place. Binding anywhere else needs a configured token (checked with the
//!   configuration: exit 64 without one).
//! - Without a configured token one is generated at each start and the page's URL is
//!   printed with it (`http://127.0.0.1:PORT/?token=...`), as Jupyter does.
//! - Every request that changes something (any method but GET/HEAD) needs the token; on a
//!   non-loopback bind every request does except `/healthz`. The token is taken from
//!   `Authorization: Bearer ...` or a `token` query parameter (for `<img>` and
//!   `EventSource`, which cannot set headers), compared in constant time. Missing: 401;
//!   wrong: 403.
//! - On a loopback bind, requests whose `Host` is not a loopback name are refused (403):
//!   a web page elsewhere cannot reach the service through DNS rebinding.
//! - Request bodies are limited (`max_body_bytes`, 413 beyond). Session ids and file
//!   names in paths are looked up among the sessions and views the workers published,
//!   never joined to a folder as given; inbox files are opened through
//!   [`crate::daemon::paths::Inbox`] (no symbolic link followed unless configured).
//! - A request head must arrive within [`HEADER_TIMEOUT`], a request with a body be done
//!   within [`BODY_TIMEOUT`]; at most [`MAX_CONNECTIONS`] connections are served at once.
//! - `clearview collect --http` serves the same page read-only ([`Shared::read_only`]): the
//!   same rules, and the two changes answered 405 with the reason (the sessions' files are
//!   in the folder ingest watches, on another machine).
//! - Memory and connections are bounded whatever the requests ([`limits`]): event streams
//!   are capped (503 beyond), images are decoded one at a time (thumbnails cached), a few
//!   bodies at a time are held, files are streamed from disk.

mod api;
pub mod limits;
mod metrics;
mod page;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::{HeaderValue, Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use crossbeam_channel::Sender;
use tokio_util::sync::CancellationToken;

use super::emit::Emitter;
use super::job::Job;
use super::registry::Registry;
use super::{Backlog, Stats};
use crate::config::{Config, HttpConfig};

/// What the handlers share.
pub struct Shared {
    pub config: Arc<Config>,
    pub registry: Arc<Registry>,
    pub stats: Arc<Stats>,
    pub backlog: Arc<Backlog>,
    pub emitter: Arc<Emitter>,
    /// The workers' queues (for their depth only).
    pub queues: Vec<Sender<Job>>,
    pub token: String,
    /// Bound to the loopback: reads need no token.
    pub loopback: bool,
    pub started: Instant,
    pub cancel: CancellationToken,
    /// Event streams, decodes, bodies and thumbnails, bounded ([`limits`]).
    pub limits: limits::Limits,
    /// `Some(why)`: the server only shows results (`clearview collect --http`); the two
    /// changes (paint the mask, choose the keyframe) are answered 405 with `why`.
    pub read_only: Option<&'static str>,
}

type AppState = State<Arc<Shared>>;

/// A fresh random token (128 bits, hex).
pub fn generate_token() -> String {
    let bytes: [u8; 16] = rand::random();
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Equality that takes the same time wherever the first difference is.
pub fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    let diff = a.iter().zip(b).fold(0u8, |acc, (x, y)| std::hint::black_box(acc | (x ^ y)));
    diff == 0
}

/// A bound server, ready to serve.
pub struct Server {
    listener: tokio::net::TcpListener,
    pub addr: SocketAddr,
    /// The page's URL (with the token when it was generated).
    pub url: String,
}

/// Binds `http.listen`. The token is the configured one or `generated`.
pub async fn bind(http: &HttpConfig, token: &str) -> std::io::Result<Server> {
    let listener = tokio::net::TcpListener::bind(http.listen).await?;
    let addr = listener.local_addr()?;
    let url = if http.token.is_some() {
        format!("http://{addr}/")
    } else {
        format!("http://{addr}/?token={token}")
    };
    Ok(Server { listener, addr, url })
}

/// Says where the page is on standard output (with the generated token: the operator's
/// way in), and flushes it.
pub fn announce(server: &Server) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "clearview: preview page at {}", server.url);
    let _ = out.flush();
}

/// Connections served at once; more wait in the kernel's backlog until one closes.
pub const MAX_CONNECTIONS: usize = 256;

/// A connection must send a whole request head within this time (idle keep-alive
/// connections included), or it is closed: a client sending its headers a byte at a
/// time cannot hold a connection (slow-loris).
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(10);

/// A request that sends a body must have sent it, and been answered, within this time.
pub const BODY_TIMEOUT: Duration = Duration::from_secs(60);

/// Serves until `shared.cancel` is cancelled: at most [`MAX_CONNECTIONS`] connections,
/// each closed when its request head takes longer than [`HEADER_TIMEOUT`].
pub async fn serve(server: Server, shared: Arc<Shared>, max_body: usize) {
    let cancel = shared.cancel.clone();
    let app = router(shared, max_body);
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CONNECTIONS));
    let connections = tokio_util::task::TaskTracker::new();
    loop {
        let slot = tokio::select! {
            () = cancel.cancelled() => break,
            s = slots.clone().acquire_owned() => s.expect("never closed"),
        };
        let stream = tokio::select! {
            () = cancel.cancelled() => break,
            r = server.listener.accept() => match r {
                Ok((stream, _)) => stream,
                Err(e) => {
                    // Out of descriptors and the like: wait rather than spin.
                    tracing::warn!(error = %e, "cannot accept an HTTP connection");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        let service = hyper_util::service::TowerToHyperService::new(app.clone());
        let cancel = cancel.clone();
        connections.spawn(async move {
            let _slot = slot;
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder.timer(hyper_util::rt::TokioTimer::new()).header_read_timeout(HEADER_TIMEOUT);
            let conn = builder.serve_connection(hyper_util::rt::TokioIo::new(stream), service);
            tokio::pin!(conn);
            tokio::select! {
                r = conn.as_mut() => {
                    if let Err(e) = r {
                        tracing::debug!(error = %e, "HTTP connection ended");
                    }
                }
                () = cancel.cancelled() => {
                    conn.as_mut().graceful_shutdown();
                    let _ = conn.await;
                }
            }
        });
    }
    connections.close();
    connections.wait().await;
}

fn router(shared: Arc<Shared>, max_body: usize) -> Router {
    Router::new()
        .route("/", get(page::index))
        .route("/app.js", get(page::script))
        .route("/app.css", get(page::style))
        .route("/healthz", get(healthz))
        .route("/metrics", get(metrics::handler))
        .route("/api/events", get(api::events))
        .route("/api/sessions", get(api::list))
        .route("/api/sessions/{id}", get(api::one))
        .route("/api/sessions/{id}/result", get(api::result))
        .route("/api/sessions/{id}/keyframe", get(api::keyframe).put(api::choose_keyframe))
        .route("/api/sessions/{id}/mask", get(api::mask).put(api::put_mask))
        .route("/api/sessions/{id}/provenance", get(api::provenance))
        .route("/api/sessions/{id}/provenance.json", get(api::legend))
        .route("/api/sessions/{id}/surfaces", get(api::surfaces))
        .route("/api/sessions/{id}/views/{file}/thumb", get(api::thumb))
        .layer(axum::middleware::from_fn_with_state(shared.clone(), body_slots))
        .layer(axum::middleware::from_fn_with_state(shared.clone(), guard))
        .layer(axum::middleware::from_fn(move |req: Request, next: Next| {
            declared_length_limit(max_body, req, next)
        }))
        .layer(DefaultBodyLimit::max(max_body))
        .layer(axum::middleware::from_fn(body_timeout))
        .with_state(shared)
}

/// Bounds a request that sends a body (anything but GET and HEAD: the server-sent events
/// stream is a GET and may last) by [`BODY_TIMEOUT`]: 408 beyond.
async fn body_timeout(req: Request, next: Next) -> Response {
    if matches!(*req.method(), Method::GET | Method::HEAD) {
        return next.run(req).await;
    }
    match tokio::time::timeout(BODY_TIMEOUT, next.run(req)).await {
        Ok(r) => r,
        Err(_) => (StatusCode::REQUEST_TIMEOUT, "the request took too long to arrive\n").into_response(),
    }
}

/// At most [`limits::MAX_BODIES`] requests with a body are served at once (each may
/// hold up to `max_body_bytes` in memory); more are answered 503 at once.
async fn body_slots(State(s): AppState, req: Request, next: Next) -> Response {
    if matches!(*req.method(), Method::GET | Method::HEAD) {
        return next.run(req).await;
    }
    let Some(_slot) = s.limits.body() else {
        return busy("too many uploads at once: try again shortly\n");
    };
    next.run(req).await
}

/// 503 with a hint to come back, and the connection closed (a refused client does not
/// keep holding one).
pub(crate) fn busy(message: &'static str) -> Response {
    let mut r = (StatusCode::SERVICE_UNAVAILABLE, message).into_response();
    let h = r.headers_mut();
    h.insert(header::RETRY_AFTER, HeaderValue::from_static("5"));
    h.insert(header::CONNECTION, HeaderValue::from_static("close"));
    r
}

/// Refuses a body whose declared length is over the limit at once, without reading it
/// (`DefaultBodyLimit` still stops a body that declares nothing, or lies, at the limit).
async fn declared_length_limit(max_body: usize, req: Request, next: Next) -> Response {
    let declared = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok());
    if declared.is_some_and(|n| n > max_body as u64) {
        return (StatusCode::PAYLOAD_TOO_LARGE, format!("request bodies are limited to {max_body} bytes\n"))
            .into_response();
    }
    next.run(req).await
}

async fn healthz(State(s): AppState) -> Response {
    let body = serde_json::json!({
        "status": "ok",
        "uptime_s": s.started.elapsed().as_secs(),
        "sessions": s.registry.all().len(),
    });
    axum::Json(body).into_response()
}

/// The token the request presents, if any: bearer header, else `token=` in the query.
fn presented(req: &Request) -> Option<String> {
    if let Some(v) = req.headers().get(header::AUTHORIZATION).and_then(|v| v.to_str().ok())
        && let Some(t) = v.strip_prefix("Bearer ")
    {
        return Some(t.trim().to_owned());
    }
    req.uri().query()?.split('&').find_map(|kv| kv.strip_prefix("token=")).map(percent_decode)
}

fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'%' if i + 2 < b.len() => {
                match u8::from_str_radix(std::str::from_utf8(&b[i + 1..i + 3]).unwrap_or("zz"), 16) {
                    Ok(v) => {
                        out.push(v);
                        i += 3;
                        continue;
                    }
                    Err(_) => out.push(b'%'),
                }
            }
            b'+' => out.push(b' '),
            c => out.push(c),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

fn is_loopback_host(host: &str) -> bool {
    let name = if let Some(rest) = host.strip_prefix('[') {
        rest.split(']').next().unwrap_or("")
    } else {
        host.rsplit_once(':').map_or(host, |(n, _)| n)
    };
    name.eq_ignore_ascii_case("localhost")
        || name.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

/// Host check, then the token where one is needed (see the module's security model).
async fn guard(State(s): AppState, req: Request, next: Next) -> Response {
    if s.loopback {
        let host = req.headers().get(header::HOST).and_then(|h| h.to_str().ok()).unwrap_or("");
        if !is_loopback_host(host) {
            return (StatusCode::FORBIDDEN, "this service answers to loopback host names only\n")
                .into_response();
        }
    }
    let changes = !matches!(*req.method(), Method::GET | Method::HEAD);
    let needed = changes || (!s.loopback && req.uri().path() != "/healthz");
    if needed {
        match presented(&req) {
            None => {
                let mut r = (StatusCode::UNAUTHORIZED, "a token is required (Authorization: Bearer TOKEN)\n")
                    .into_response();
                r.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
                return r;
            }
            Some(t) if constant_time_eq(t.as_bytes(), s.token.as_bytes()) => {}
            Some(_) => return (StatusCode::FORBIDDEN, "wrong token\n").into_response(),
        }
    }
    let mut r = next.run(req).await;
    let h = r.headers_mut();
    h.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    h.insert(header::REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_compare_whole() {
        assert!(constant_time_eq(b"abcdef", b"abcdef"));
        assert!(!constant_time_eq(b"abcdef", b"abcdeg"));
        assert!(!constant_time_eq(b"abcdef", b"abcde"));
        let t = generate_token();
        assert_eq!(t.len(), 32);
        assert_ne!(t, generate_token());
    }

    #[test]
    fn loopback_hosts() {
        for h in ["127.0.0.1:8080", "localhost:1", "[::1]:80", "LOCALHOST", "127.1.2.3"] {
            assert!(is_loopback_host(h), "{h}");
        }
        for h in ["evil.example:8080", "10.0.0.1:80", "", "[2001:db8::1]:80", "localhost.evil.example"] {
            assert!(!is_loopback_host(h), "{h}");
        }
    }

    #[test]
    fn query_tokens_are_decoded() {
        assert_eq!(percent_decode("a%2Bb+c"), "a+b c");
        assert_eq!(percent_decode("abc%"), "abc%");
        assert_eq!(percent_decode("abc%4"), "abc%4");
    }
}
