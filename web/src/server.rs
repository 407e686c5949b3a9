//! The HTTP and WebSocket server: routes, sign-in, security headers, the sockets.

use crate::auth::{random_token, Access, Limiter, WebSession, COOKIE, SESSION_IDLE};
use crate::hub::{Cmd, Hub, ListShare};
use crate::pool::Pool;
use crate::world::{map_frame, WorldFrame};
use anyhow::Context as _;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{ConnectInfo, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures_util::{SinkExt as _, StreamExt as _};
use muster_shared::protocol::Operation;
use muster_shared::types::{ServiceId, SessionId, UserId};
use muster_shared::udp::access::web_token_hash;
use muster_shared::Instance;
use muster_world_model::OccupancyMap;
use serde::Deserialize;
use serde_json::{json, Value};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::broadcast::{self, error::RecvError};
use tokio_rustls::rustls;

/// How `muster web` runs.
#[derive(Clone, Debug)]
pub struct WebOptions {
    /// The muster instance whose broker it acts on.
    pub instance: Instance,
    /// Where it listens.
    pub listen: SocketAddr,
    /// The access file: who may sign in (`web` lines) and what each may use.
    pub access: PathBuf,
    /// How long a signing-in user's connection waits for a broker.
    pub wait_for_broker: Duration,
    /// The floor's map (a ROS map_server YAML); `None`: the simulator's default office.
    pub map: Option<PathBuf>,
    /// Serve HTTPS with this certificate chain and private key (PEM files).
    pub tls: Option<(PathBuf, PathBuf)>,
}

/// Descriptors one signed-in user's broker connection holds (measured: 22 at 500
/// users, 26 at 20: its inbox and bell, their configurations and connections, the
/// presence bell, two pidfds, an epoll set; the node and the ports to the broker and
/// the systems are its worker's, shared).
const FDS_PER_USER: u64 = 26;
/// Threads driving the signed-in users' broker connections (each waits on all of its
/// users at once): as many as the machine has cores, up to four.
const HUB_THREADS_MAX: usize = 4;

/// Raises this process's descriptor limit as far as it may; returns the soft limit.
fn raise_descriptor_limit() -> u64 {
    match muster_shared::reactor::raise_fd_limit() {
        Ok(n) => n,
        Err(e) => {
            tracing::warn!("could not raise the descriptor limit: {e}");
            1024
        }
    }
}

/// The largest WebSocket message a browser may send (commands are tiny).
const MAX_MESSAGE: usize = 64 * 1024;
/// A socket's read buffer. tungstenite zeroes the whole buffer (128 KiB by default)
/// each time a read is tried, and a tab's read is tried at each frame sent to it: at
/// 500 tabs of 10 Hz that was 15 % of the process's CPU in memset. Commands are tiny.
const READ_BUFFER: usize = 4096;

/// The app's files, inside the binary.
const INDEX_HTML: &str = include_str!("../assets/index.html");
const APP_JS: &str = include_str!("../assets/app.js");
const APP_CSS: &str = include_str!("../assets/app.css");

/// No inline script or style, nothing from elsewhere, no framing.
const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; \
                   connect-src 'self'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'";

/// A user's hub, or nothing while it starts (its lock held) or after it stopped.
type HubSlot = Arc<Mutex<Option<Arc<Hub>>>>;

struct App {
    inst: Instance,
    access: Mutex<Access>,
    sessions: Mutex<HashMap<String, WebSession>>,
    hubs: Mutex<HashMap<String, HubSlot>>,
    limiter: Mutex<Limiter>,
    wait_for_broker: Duration,
    world: broadcast::Sender<Arc<WorldFrame>>,
    map_frame: Arc<str>,
    /// Served over TLS: cookies are `Secure`, origins `https://`.
    tls: bool,
    /// The service list, read once for all hubs.
    lists: Arc<ListShare>,
    /// The threads driving the hubs' broker connections.
    pool: Pool,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Serves until SIGINT or SIGTERM; prints `{"listen": ADDR, "url": URL}` on stdout
/// once listening.
pub fn serve(opts: WebOptions) -> anyhow::Result<()> {
    let fds = raise_descriptor_limit();
    tracing::info!(
        "descriptor limit {fds}: room for about {} signed-in users (each holds about {FDS_PER_USER} for its broker connection)",
        fds / FDS_PER_USER
    );
    let access = Access::load(opts.access.clone()).map_err(anyhow::Error::msg)?;
    if access.web_users() == 0 {
        tracing::warn!(
            "no user of {} may sign in on the web: add `web NAME HASH` lines (`muster keygen --user NAME --web`)",
            opts.access.display()
        );
    }
    let map = match &opts.map {
        Some(p) => {
            OccupancyMap::load(p).map_err(|e| anyhow::anyhow!("--map {}: {e}", p.display()))?
        }
        None => OccupancyMap::office(),
    };
    let (world, _) = broadcast::channel(4);
    let stop = Arc::new(AtomicBool::new(false));
    let reader = crate::world::start(opts.instance.clone(), world.clone(), stop.clone())
        .context("starting the map's reader")?;
    let app = Arc::new(App {
        inst: opts.instance.clone(),
        access: Mutex::new(access),
        sessions: Mutex::new(HashMap::new()),
        hubs: Mutex::new(HashMap::new()),
        limiter: Mutex::new(Limiter::default()),
        wait_for_broker: opts.wait_for_broker,
        world,
        map_frame: Arc::from(map_frame(&map)),
        tls: opts.tls.is_some(),
        lists: Arc::new(ListShare::default()),
        pool: Pool::new(
            &opts.instance,
            std::thread::available_parallelism().map_or(2, |n| n.get().min(HUB_THREADS_MAX)),
        )
        .map_err(anyhow::Error::msg)?,
    });
    let lister = {
        let app = app.clone();
        let stop = stop.clone();
        std::thread::Builder::new()
            .name("web-list".into())
            .spawn(move || read_list(&app, &stop))
            .context("starting the list's reader")?
    };
    let tls = opts
        .tls
        .as_ref()
        .map(|(c, k)| tls_config(c, k))
        .transpose()?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("web")
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let served = rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(opts.listen)
            .await
            .with_context(|| format!("listening on {}", opts.listen))?;
        let at = listener.local_addr()?;
        let scheme = if tls.is_some() { "https" } else { "http" };
        println!(
            "{}",
            json!({"listen": at.to_string(), "url": format!("{scheme}://{at}/")})
        );
        tracing::info!("muster web on {scheme}://{at}/");
        tokio::spawn(housekeeping(app.clone()));
        let router = router(app.clone());
        match tls {
            None => axum::serve(
                listener,
                router.into_make_service_with_connect_info::<SocketAddr>(),
            )
            .with_graceful_shutdown(stop_signal())
            .await
            .context("serving")?,
            Some(tls) => {
                tokio::select! {
                    r = serve_tls(listener, tls, router) => r?,
                    _ = stop_signal() => {}
                }
            }
        }
        close_all(&app).await;
        Ok(())
    });
    stop.store(true, Ordering::Release);
    let _ = reader.join();
    let _ = lister.join();
    served
}

/// How often the shared list is looked at (a look that finds it unchanged copies
/// nothing): changes reach the tabs within this and a hop.
const LIST_POLL: Duration = Duration::from_millis(25);

/// Reads the broker's list for every hub while some hub runs, and rings the hubs when
/// it changed (a new broker's list too).
fn read_list(app: &App, stop: &AtomicBool) {
    let node = match muster_shared::ipc::create_node(
        &format!("muster-web-list-{}", std::process::id()),
        false,
    ) {
        Ok(n) => n,
        Err(e) => {
            tracing::warn!("the list's reader: {e}");
            return;
        }
    };
    let mut reader: Option<muster_shared::ipc::ListReader> = None;
    let mut last: Option<(u64, u64)> = None;
    let mut next_open = Instant::now();
    while !stop.load(Ordering::Acquire) {
        std::thread::sleep(LIST_POLL);
        let hubs: Vec<Arc<Hub>> = lock(&app.hubs)
            .values()
            .filter_map(|slot| slot.try_lock().ok().and_then(|s| s.clone()))
            .collect();
        if hubs.is_empty() {
            continue;
        }
        if reader.is_none() && Instant::now() >= next_open {
            next_open = Instant::now() + Duration::from_secs(1);
            reader = muster_shared::ipc::ListReader::open(&node, &app.inst).ok();
        }
        let Some(snap) = reader.as_mut().and_then(|r| r.read_from(&node).ok()) else {
            continue;
        };
        if last == Some((snap.epoch, snap.generation)) {
            continue;
        }
        last = Some((snap.epoch, snap.generation));
        app.lists.set(snap);
        for h in &hubs {
            h.notify();
        }
    }
}

/// The server's TLS configuration from PEM files: a certificate chain and its key.
fn tls_config(cert: &Path, key: &Path) -> anyhow::Result<Arc<rustls::ServerConfig>> {
    let read = |p: &Path| {
        std::fs::read(p)
            .with_context(|| format!("--tls: reading {}", p.display()))
            .map(std::io::Cursor::new)
    };
    let certs = rustls_pemfile::certs(&mut read(cert)?)
        .collect::<Result<Vec<_>, _>>()
        .with_context(|| format!("--tls: certificates in {}", cert.display()))?;
    anyhow::ensure!(
        !certs.is_empty(),
        "--tls: no certificate in {}",
        cert.display()
    );
    let key = rustls_pemfile::private_key(&mut read(key)?)
        .with_context(|| format!("--tls: the key in {}", key.display()))?
        .with_context(|| format!("--tls: no private key in {}", key.display()))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .context("--tls: protocol versions")?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .context("--tls: the certificate and key")?;
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(Arc::new(config))
}

/// Serves HTTPS: each connection's TLS handshake (bounded), then HTTP/1.1 with upgrades
/// (the WebSocket), the peer's address given to the handlers as axum's own server does.
async fn serve_tls(
    listener: tokio::net::TcpListener,
    tls: Arc<rustls::ServerConfig>,
    router: Router,
) -> anyhow::Result<()> {
    use hyper_util::rt::{TokioExecutor, TokioIo};
    use tower::ServiceExt as _;
    let acceptor = tokio_rustls::TlsAcceptor::from(tls);
    loop {
        let (tcp, peer) = match listener.accept().await {
            Ok(c) => c,
            Err(e) => {
                // Out of descriptors and the like: wait, do not spin.
                tracing::warn!("accepting a connection: {e}");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let acceptor = acceptor.clone();
        let router = router.clone();
        tokio::spawn(async move {
            let stream =
                match tokio::time::timeout(Duration::from_secs(10), acceptor.accept(tcp)).await {
                    Ok(Ok(s)) => s,
                    Ok(Err(e)) => {
                        tracing::debug!(from = %peer, "TLS handshake failed: {e}");
                        return;
                    }
                    Err(_) => return,
                };
            let svc = hyper::service::service_fn(
                move |mut req: hyper::Request<hyper::body::Incoming>| {
                    req.extensions_mut().insert(ConnectInfo(peer));
                    router.clone().oneshot(req)
                },
            );
            let served = hyper_util::server::conn::auto::Builder::new(TokioExecutor::new())
                .serve_connection_with_upgrades(TokioIo::new(stream), svc)
                .await;
            if let Err(e) = served {
                tracing::debug!(from = %peer, "connection: {e}");
            }
        });
    }
}

async fn stop_signal() {
    use tokio::signal::unix::{signal, SignalKind};
    let mut term = match signal(SignalKind::terminate()) {
        Ok(s) => s,
        Err(_) => return std::future::pending().await,
    };
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = term.recv() => {}
    }
}

/// Ends every user's connection (their sessions end at the systems), waiting a little
/// for them to say goodbye.
async fn close_all(app: &App) {
    let hubs: Vec<Arc<Hub>> = lock(&app.hubs)
        .values()
        .filter_map(|slot| lock(slot).clone())
        .collect();
    for h in &hubs {
        h.send(Cmd::Close);
    }
    let deadline = Instant::now() + Duration::from_secs(2);
    while hubs.iter().any(|h| h.alive()) && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

fn router(app: Arc<App>) -> Router {
    Router::new()
        .route(
            "/",
            get(|| async { asset("text/html; charset=utf-8", INDEX_HTML) }),
        )
        .route(
            "/app.js",
            get(|| async { asset("text/javascript; charset=utf-8", APP_JS) }),
        )
        .route(
            "/app.css",
            get(|| async { asset("text/css; charset=utf-8", APP_CSS) }),
        )
        .route("/favicon.ico", get(|| async { StatusCode::NO_CONTENT }))
        .route("/api/login", post(login))
        .route("/api/logout", post(logout))
        .route("/api/me", get(me))
        .route("/ws", get(socket))
        .layer(axum::middleware::from_fn(security_headers))
        .with_state(app)
}

fn asset(kind: &'static str, body: &'static str) -> Response {
    ([(header::CONTENT_TYPE, kind)], body).into_response()
}

async fn security_headers(req: Request, next: Next) -> Response {
    let mut res = next.run(req).await;
    let h = res.headers_mut();
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    res
}

fn error(status: StatusCode, msg: impl Into<String>) -> Response {
    (status, Json(json!({"error": msg.into()}))).into_response()
}

/// The refusal of a request not from a page of this server: its Origin must be this
/// server's own (the Host it was asked for). Browsers send Origin on every POST and
/// WebSocket upgrade.
fn cross_origin(app: &App, headers: &HeaderMap) -> Option<Response> {
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
    let origin = headers.get(header::ORIGIN).and_then(|h| h.to_str().ok());
    let scheme = if app.tls { "https" } else { "http" };
    match (host, origin) {
        (Some(host), Some(origin)) if origin == format!("{scheme}://{host}") => None,
        (_, None) => Some(error(StatusCode::FORBIDDEN, "no Origin header")),
        _ => Some(error(StatusCode::FORBIDDEN, "cross-origin request refused")),
    }
}

fn cookie_value(headers: &HeaderMap) -> Option<String> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|h| h.to_str().ok())
        .flat_map(|h| h.split(';'))
        .filter_map(|kv| kv.trim().split_once('='))
        .find(|(k, _)| *k == COOKIE)
        .map(|(_, v)| v.to_string())
}

/// The signed-in browser session behind the request's cookie (touched).
fn session_of(app: &App, headers: &HeaderMap) -> Option<(String, WebSession)> {
    let cookie = cookie_value(headers)?;
    let mut sessions = lock(&app.sessions);
    let s = sessions.get_mut(&cookie)?;
    s.last_seen = Instant::now();
    Some((cookie, s.clone()))
}

#[derive(Deserialize)]
struct Login {
    user: String,
    token: String,
}

async fn login(
    State(app): State<Arc<App>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
    body: Result<Json<Login>, axum::extract::rejection::JsonRejection>,
) -> Response {
    if let Some(r) = cross_origin(&app, &headers) {
        return r;
    }
    let Ok(Json(l)) = body else {
        return error(
            StatusCode::BAD_REQUEST,
            "send JSON: {\"user\": NAME, \"token\": TOKEN}",
        );
    };
    let now = Instant::now();
    if let Some(wait) = lock(&app.limiter).blocked(peer.ip(), &l.user, now) {
        let secs = wait.as_secs().max(1);
        let mut r = error(
            StatusCode::TOO_MANY_REQUESTS,
            format!("too many failed sign-ins: try again in {secs} s"),
        );
        r.headers_mut()
            .insert(header::RETRY_AFTER, HeaderValue::from(secs));
        return r;
    }
    let policy = {
        let mut access = lock(&app.access);
        if let Err(e) = access.reload() {
            tracing::warn!("{e} (keeping the last good one)");
        }
        access
            .get(&l.user)
            .filter(|p| p.web_token_matches(&l.token))
            .cloned()
    };
    let Some(policy) = policy else {
        lock(&app.limiter).failed(peer.ip(), &l.user, now);
        tracing::info!(from = %peer.ip(), "a failed web sign-in");
        return error(StatusCode::UNAUTHORIZED, "wrong user name or token");
    };
    let cookie = random_token();
    let csrf = random_token();
    lock(&app.sessions).insert(
        cookie.clone(),
        WebSession {
            user: l.user.clone(),
            csrf: csrf.clone(),
            token_hash: web_token_hash(&l.token),
            last_seen: now,
        },
    );
    tracing::info!(user = %l.user, from = %peer.ip(), "signed in on the web");
    let secure = if app.tls { "; Secure" } else { "" };
    let set = format!(
        "{COOKIE}={cookie}; Path=/; HttpOnly; SameSite=Strict; Max-Age={}{secure}",
        SESSION_IDLE.as_secs()
    );
    let mut r =
        Json(json!({"user": l.user, "operator": policy.operator, "csrf": csrf})).into_response();
    if let Ok(v) = HeaderValue::from_str(&set) {
        r.headers_mut().insert(header::SET_COOKIE, v);
    }
    r
}

async fn me(State(app): State<Arc<App>>, headers: HeaderMap) -> Response {
    let Some((_, s)) = session_of(&app, &headers) else {
        return error(StatusCode::UNAUTHORIZED, "not signed in");
    };
    let operator = lock(&app.access).get(&s.user).is_some_and(|p| p.operator);
    Json(json!({"user": s.user, "operator": operator, "csrf": s.csrf})).into_response()
}

async fn logout(State(app): State<Arc<App>>, headers: HeaderMap) -> Response {
    if let Some(r) = cross_origin(&app, &headers) {
        return r;
    }
    let Some((cookie, s)) = session_of(&app, &headers) else {
        return error(StatusCode::UNAUTHORIZED, "not signed in");
    };
    let csrf = headers.get("x-csrf-token").and_then(|h| h.to_str().ok());
    if csrf != Some(s.csrf.as_str()) {
        return error(StatusCode::FORBIDDEN, "missing or wrong X-CSRF-Token");
    }
    let others = {
        let mut sessions = lock(&app.sessions);
        sessions.remove(&cookie);
        sessions.values().any(|o| o.user == s.user)
    };
    if !others {
        close_hub(&app, &s.user);
    }
    let secure = if app.tls { "; Secure" } else { "" };
    let clear = format!("{COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0{secure}");
    let mut r = Json(json!({"signed_out": true})).into_response();
    if let Ok(v) = HeaderValue::from_str(&clear) {
        r.headers_mut().insert(header::SET_COOKIE, v);
    }
    r
}

fn close_hub(app: &App, user: &str) {
    let slot = lock(&app.hubs).remove(user);
    if let Some(hub) = slot.and_then(|s| lock(&s).take()) {
        hub.send(Cmd::Close);
    }
}

/// The user's hub, started (connecting to the broker) if it is not running.
fn hub_for(app: &App, user: &str) -> Result<Arc<Hub>, String> {
    let (slot, others) = {
        let mut hubs = lock(&app.hubs);
        let others = hubs
            .len()
            .saturating_sub(usize::from(hubs.contains_key(user)));
        (hubs.entry(user.to_string()).or_default().clone(), others)
    };
    // Never `hubs` while holding a slot: `close_all` takes them the other way round.
    let mut slot = lock(&slot);
    if let Some(h) = slot.as_ref().filter(|h| h.alive()) {
        return Ok(h.clone());
    }
    let policy = lock(&app.access)
        .get(user)
        .cloned()
        .ok_or_else(|| format!("user {user:?} is no longer in the access file"))?;
    let hub = Hub::start(
        &app.pool,
        user,
        policy,
        app.wait_for_broker,
        app.lists.clone(),
    )
    .map_err(|e| {
        if others > 0 && e.starts_with("no broker") {
            // The broker ignores a process's users past its limit: it looks absent.
            format!(
                "{e} (with {others} other users signed in here: the broker lets one process \
                 hold --max-users-per-process users, 16 unless started with more)"
            )
        } else {
            e
        }
    })?;
    *slot = Some(hub.clone());
    Ok(hub)
}

async fn socket(State(app): State<Arc<App>>, headers: HeaderMap, ws: WebSocketUpgrade) -> Response {
    if let Some(r) = cross_origin(&app, &headers) {
        return r;
    }
    let Some((cookie, s)) = session_of(&app, &headers) else {
        return error(StatusCode::UNAUTHORIZED, "not signed in");
    };
    let a = app.clone();
    let user = s.user.clone();
    let hub = match tokio::task::spawn_blocking(move || hub_for(&a, &user)).await {
        Ok(Ok(h)) => h,
        Ok(Err(e)) => {
            tracing::warn!(user = %s.user, "connecting to the broker: {e}");
            return error(StatusCode::SERVICE_UNAVAILABLE, e);
        }
        Err(e) => return error(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()),
    };
    ws.max_message_size(MAX_MESSAGE)
        .read_buffer_size(READ_BUFFER)
        .on_upgrade(move |sock| tab(app, cookie, hub, sock))
}

/// What a tab sends.
#[derive(Deserialize)]
#[serde(tag = "op", rename_all = "snake_case")]
enum In {
    Request { service: String },
    Cancel { req: u64 },
    End { session: String },
    Goal { session: String, x: f64, y: f64 },
    Input { session: String, value: Value },
    Link { data: String, command: String },
    Unlink { link: u64 },
    Status,
    Withdraw { service: String },
    Restore { service: String },
    EndSession { session: String },
    DropUser { user: String },
    Map { on: bool },
}

/// A session as frames name it: 16 hex digits (a 64-bit number, more than a
/// JavaScript number holds).
fn session_id(s: &str) -> Result<u64, String> {
    u64::from_str_radix(s, 16)
        .map_err(|_| format!("bad session {s:?}: 16 hex digits, as the server sent it"))
}

fn parse(msg: &str) -> Result<In, String> {
    serde_json::from_str(msg).map_err(|e| format!("bad message: {e}"))
}

fn command(m: In) -> Result<Cmd, String> {
    Ok(match m {
        In::Request { service } => Cmd::Request(service),
        In::Cancel { req } => Cmd::Cancel(req),
        In::End { session } => Cmd::End(session_id(&session)?),
        In::Goal { session, x, y } => {
            if !x.is_finite() || !y.is_finite() {
                return Err("a goal's x and y are numbers".into());
            }
            Cmd::Input(
                session_id(&session)?,
                json!({"type": "goal2d", "x": x, "y": y}),
            )
        }
        In::Input { session, value } => Cmd::Input(session_id(&session)?, value),
        In::Link { data, command } => Cmd::Link(data, command),
        In::Unlink { link } => Cmd::Unlink(link),
        In::Status => Cmd::Operate(Operation::Status),
        In::Withdraw { service } => Cmd::Operate(Operation::Withdraw {
            service: ServiceId(service),
        }),
        In::Restore { service } => Cmd::Operate(Operation::Restore {
            service: ServiceId(service),
        }),
        In::EndSession { session } => Cmd::Operate(Operation::EndSession {
            session: SessionId(session_id(&session)?),
        }),
        In::DropUser { user } => Cmd::Operate(Operation::DropUser { user: UserId(user) }),
        In::Map { .. } => return Err("the map is the tab's own".into()),
    })
}

/// One browser tab's socket: the hub's frames out, the tab's commands in.
async fn tab(app: Arc<App>, cookie: String, hub: Arc<Hub>, sock: WebSocket) {
    // The socket is read by a task of its own: a read tried at every frame sent (as a
    // `select!` over both would) costs a system call per frame, for commands that are
    // rare.
    let (mut sock, mut incoming) = sock.split();
    let (texts, mut from_reader) = tokio::sync::mpsc::channel(16);
    let reader = tokio::spawn(async move {
        while let Some(msg) = incoming.next().await {
            match msg {
                Ok(Message::Text(t)) => {
                    if texts.send(t).await.is_err() {
                        return;
                    }
                }
                Ok(Message::Close(_)) | Err(_) => return,
                Ok(_) => {}
            }
        }
    });
    let _reader = AbortOnDrop(reader);
    let (_tab, first, mut frames) = hub.open_tab();
    if sock.send(Message::Text(first.into())).await.is_err() {
        return;
    }
    let mut check = tokio::time::interval(Duration::from_secs(1));
    let mut world: Option<broadcast::Receiver<Arc<WorldFrame>>> = None;
    let mut systems = hub.systems();
    loop {
        let next_world = async {
            match world.as_mut() {
                Some(r) => r.recv().await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            w = next_world => match w {
                Ok(f) => {
                    let text = f.json_for(|s| systems.contains(s));
                    if sock.send(Message::Text(text.into())).await.is_err() {
                        return;
                    }
                }
                // A slow tab skips frames of the floor: only the newest matters.
                Err(RecvError::Lagged(_)) => {}
                Err(RecvError::Closed) => world = None,
            },
            frame = frames.recv() => match frame {
                Ok(f) => {
                    if sock.send(Message::Text((*f).into())).await.is_err() {
                        return;
                    }
                }
                Err(RecvError::Lagged(n)) => {
                    tracing::debug!(user = %hub.user, "a tab fell {n} frames behind: sending the state again");
                    let (state, rx) = hub.resync();
                    frames = rx;
                    if sock.send(Message::Text(state.into())).await.is_err() {
                        return;
                    }
                }
                Err(RecvError::Closed) => return,
            },
            text = from_reader.recv() => match text {
                // Closed, or the connection failed.
                None => return,
                Some(t) => match parse(t.as_str()).and_then(|m| match m {
                    In::Map { on } => Ok(Err(on)),
                    other => command(other).map(Ok),
                }) {
                    Ok(Err(on)) => {
                        world = None;
                        if on {
                            world = Some(app.world.subscribe());
                            if sock.send(Message::Text((*app.map_frame).into())).await.is_err() {
                                return;
                            }
                        }
                    }
                    Ok(Ok(Cmd::Operate(_))) if !hub.operator => {
                        let e = json!({"t": "error", "error": "operators only"}).to_string();
                        if sock.send(Message::Text(e.into())).await.is_err() {
                            return;
                        }
                    }
                    Ok(Ok(cmd)) => hub.send(cmd),
                    Err(e) => {
                        let e = json!({"t": "error", "error": e}).to_string();
                        if sock.send(Message::Text(e.into())).await.is_err() {
                            return;
                        }
                    }
                },
            },
            _ = check.tick() => {
                systems = hub.systems();
                // Signed out, revoked, or the broker connection ended: close the tab.
                let signed_in = lock(&app.sessions).contains_key(&cookie);
                if !signed_in || !hub.alive() {
                    let why = if signed_in { "the broker connection ended" } else { "signed out" };
                    let e = json!({"t": "closed", "reason": why}).to_string();
                    let _ = sock.send(Message::Text(e.into())).await;
                    let _ = sock.send(Message::Close(None)).await;
                    return;
                }
            }
        }
    }
}

/// Aborts a task when dropped (a tab's reader, when its writer ends).
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Every two seconds: re-read the access file (a removed user or changed token signs
/// out; changed patterns take effect), forget idle sessions and stopped hubs.
async fn housekeeping(app: Arc<App>) {
    let mut every = tokio::time::interval(Duration::from_secs(2));
    loop {
        every.tick().await;
        let changed = match lock(&app.access).reload() {
            Ok(c) => c,
            Err(e) => {
                tracing::warn!("{e} (keeping the last good one)");
                false
            }
        };
        let now = Instant::now();
        let mut gone_users = Vec::new();
        {
            let access = lock(&app.access);
            let mut sessions = lock(&app.sessions);
            sessions.retain(|_, s| {
                let valid = access
                    .get(&s.user)
                    .and_then(|p| p.web)
                    .is_some_and(|h| h == s.token_hash);
                if !valid {
                    tracing::info!(user = %s.user, "signed out: the access file no longer lets this token in");
                }
                valid && now.duration_since(s.last_seen) < SESSION_IDLE
            });
            let hubs = lock(&app.hubs);
            for (user, slot) in hubs.iter() {
                let Some(hub) = slot.try_lock().ok().and_then(|s| s.clone()) else {
                    continue;
                };
                if !sessions.values().any(|s| &s.user == user) {
                    gone_users.push(user.clone());
                } else if changed {
                    if let Some(p) = access.get(user) {
                        hub.send(Cmd::Policy(Box::new(p.clone())));
                    }
                }
            }
        }
        for user in gone_users {
            close_hub(&app, &user);
        }
        // A slot being filled (its user's connection starting) is kept.
        lock(&app.hubs).retain(|_, slot| {
            slot.try_lock()
                .map(|s| s.as_ref().is_some_and(|h| h.alive()))
                .unwrap_or(true)
        });
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn cmd(text: &str) -> Result<Cmd, String> {
        parse(text).and_then(command)
    }

    #[test]
    fn a_tabs_messages_become_commands_and_bad_ones_say_why() {
        assert!(
            matches!(cmd(r#"{"op": "request", "service": "t1/s0"}"#), Ok(Cmd::Request(s)) if s == "t1/s0")
        );
        match cmd(r#"{"op": "goal", "session": "00000000000000ff", "x": 1.5, "y": -2}"#) {
            Ok(Cmd::Input(255, v)) => assert_eq!(v, json!({"type": "goal2d", "x": 1.5, "y": -2.0})),
            other => panic!("{other:?}"),
        }
        assert!(matches!(
            cmd(r#"{"op": "end", "session": "ffffffffffffffff"}"#),
            Ok(Cmd::End(u64::MAX))
        ));
        assert!(matches!(
            cmd(r#"{"op": "end_session", "session": "1"}"#),
            Ok(Cmd::Operate(Operation::EndSession {
                session: SessionId(1)
            }))
        ));
        // A session's number more than JavaScript holds, given as a decimal: refused.
        let e = cmd(r#"{"op": "end", "session": "18446744073709551615"}"#).unwrap_err();
        assert!(e.contains("16 hex digits"), "{e}");
        assert!(cmd(r#"{"op": "goal", "session": "1", "x": "far", "y": 0}"#)
            .unwrap_err()
            .starts_with("bad message"));
        assert!(cmd(r#"{"op": "launch", "service": "t1/s0"}"#)
            .unwrap_err()
            .starts_with("bad message"));
        assert!(cmd("not json").unwrap_err().starts_with("bad message"));
        assert!(
            cmd(r#"{"op": "map", "on": true}"#).is_err(),
            "the map is not a hub's command"
        );
        assert!(matches!(
            parse(r#"{"op": "map", "on": true}"#),
            Ok(In::Map { on: true })
        ));
    }

    #[test]
    fn the_session_cookie_is_found_among_others() {
        let mut h = HeaderMap::new();
        h.insert(
            header::COOKIE,
            HeaderValue::from_static("a=1; muster_session=abc; b=2"),
        );
        assert_eq!(cookie_value(&h).as_deref(), Some("abc"));
        let mut h = HeaderMap::new();
        h.insert(
            header::COOKIE,
            HeaderValue::from_static("muster_sessionx=abc"),
        );
        assert_eq!(cookie_value(&h), None);
    }
}
