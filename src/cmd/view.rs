//! `muster view`: the live world and infrastructure over the Foxglove WebSocket protocol
//! (the `foxglove` crate's server), for Foxglove or Lichtblick; `muster replay`: a
//! recording served the same way, at its pace or faster.

use super::record::{scenario_and_map, Scene};
use crate::cli::{ReplayArgs, ViewArgs};
use anyhow::Context as _;
use foxglove::websocket::{ChannelView, Client, ServerListener};
use foxglove::{ChannelBuilder, Context, PartialMetadata, RawChannel, Schema, WebSocketServer};
use muster_shared::reactor::SignalPipe;
use muster_shared::Instance;
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Notes that a client just subscribed to the map (sent once, so sent again then).
#[derive(Default)]
struct Latch {
    map_wanted: AtomicBool,
}

impl Latch {
    /// Whether the map is to be sent again (once per subscription).
    fn take(&self) -> bool {
        self.map_wanted.swap(false, Ordering::AcqRel)
    }
}

impl ServerListener for Latch {
    fn on_subscribe(&self, _client: Client, channel: ChannelView) {
        if channel.topic() == "/map" {
            self.map_wanted.store(true, Ordering::Release);
        }
    }
}

/// Messages a Foxglove server queues for one client before it drops the client (the
/// crate's default is 1,024: with the world's larger messages, a few hundred clients
/// that never read held a gigabyte).
const BACKLOG: usize = 64;

/// Starts a Foxglove WebSocket server for `ctx` on `listen` (never with the broker's
/// event feed when `public`).
fn start_server(
    ctx: &Arc<Context>,
    listen: SocketAddr,
    latch: &Arc<Latch>,
    public: bool,
) -> anyhow::Result<foxglove::WebSocketServerHandle> {
    let mut server = WebSocketServer::new()
        .name("muster")
        .context(ctx)
        .listener(latch.clone())
        .message_backlog_size(BACKLOG)
        .bind(listen.ip().to_string(), listen.port());
    if public {
        server = server.channel_filter_fn(|c| c.topic() != EVENTS_TOPIC);
    }
    server
        .start_blocking()
        .with_context(|| format!("serving the Foxglove WebSocket protocol on {listen}"))
}

/// The event feed's topic: operators only.
const EVENTS_TOPIC: &str = "/muster/events";

/// Prints where a server listens (one JSON line, then the URL for people).
fn announce(at: SocketAddr, events: Option<&str>) {
    println!(
        "{}",
        serde_json::json!({"listen": at.to_string(), "events": events})
    );
    eprintln!("muster: Foxglove WebSocket server on ws://{at} (open it in Foxglove or Lichtblick: Open connection, Foxglove WebSocket)");
}

/// A replay's server, on `listen` itself.
fn serve(
    ctx: &Arc<Context>,
    listen: SocketAddr,
    latch: &Arc<Latch>,
) -> anyhow::Result<foxglove::WebSocketServerHandle> {
    let server = start_server(ctx, listen, latch, false)?;
    announce(SocketAddr::new(listen.ip(), server.port()), None);
    Ok(server)
}

/// The operators' token: the file's first line, or a new random one.
fn operator_token(file: Option<&std::path::Path>) -> anyhow::Result<String> {
    match file {
        Some(p) => {
            let t = std::fs::read_to_string(p)
                .with_context(|| format!("--token-file {}", p.display()))?;
            let t = t.lines().next().unwrap_or_default().trim().to_string();
            anyhow::ensure!(
                t.len() >= 16
                    && t.bytes()
                        .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_'),
                "--token-file {}: a token is 16 or more characters of [A-Za-z0-9_-]",
                p.display()
            );
            Ok(t)
        }
        None => {
            use rand::RngExt;
            let bytes: [u8; 24] = rand::rng().random();
            Ok(hex::encode(bytes))
        }
    }
}

/// `muster view`.
pub fn run(inst: &Instance, a: ViewArgs) -> anyhow::Result<ExitCode> {
    let mut signals = SignalPipe::install().context("signal handlers")?;
    let (scenario, map) = scenario_and_map(a.scene.scenario.as_deref(), a.scene.map.as_deref())?;
    let ctx = Context::new();
    let latch = Arc::new(Latch::default());
    let mut scene = Scene::new(&ctx, inst, scenario, map)?;
    // The Foxglove server on a loopback port of its own, the world and infrastructure
    // only; the gate on --listen in front of it, with the event feed for operators.
    let server = start_server(&ctx, SocketAddr::from(([127, 0, 0, 1], 0)), &latch, true)?;
    let token = operator_token(a.token_file.as_deref())?;
    let feed = super::view_gate::Feed::default();
    let gate = super::view_gate::Gate::start(
        a.listen,
        super::view_gate::Backends {
            foxglove: SocketAddr::from(([127, 0, 0, 1], server.port())),
            token: token.clone(),
        },
        feed.clone(),
        usize::from(a.max_clients),
    )
    .with_context(|| format!("listening on {}", a.listen))?;
    let events_url = format!("ws://{}/events?token={token}", gate.addr());
    announce(gate.addr(), Some(&events_url));
    eprintln!("muster: the broker's event feed, for operators: {events_url}");
    scene.on_event(move |json| feed.send(json));
    let mut taps = super::taps::Taps::new(inst, &ctx, &a.scene.services);
    let end = a.duration.map(|d| Instant::now() + d);
    loop {
        if latch.take() {
            scene.log_map();
        }
        let any = scene.poll()? | taps.poll();
        if signals.drain() || end.is_some_and(|e| Instant::now() >= e) {
            break;
        }
        if !any {
            std::thread::sleep(Duration::from_millis(10));
        }
    }
    drop(gate);
    server.stop().wait_blocking();
    Ok(ExitCode::SUCCESS)
}

/// `muster replay`.
pub fn replay(a: ReplayArgs) -> anyhow::Result<ExitCode> {
    if !(a.speed > 0.0 && a.speed.is_finite()) {
        anyhow::bail!("--speed must be a positive number");
    }
    let mut signals = SignalPipe::install().context("signal handlers")?;
    let bytes = std::fs::read(&a.file).with_context(|| format!("reading {}", a.file.display()))?;
    // Check the whole file first: a bad one is refused before anything is served.
    let total = mcap::MessageStream::new(&bytes)
        .with_context(|| format!("{} is not an MCAP file", a.file.display()))?
        .try_fold(0u64, |n, m| m.map(|_| n + 1))
        .with_context(|| format!("reading {}", a.file.display()))?;
    let ctx = Context::new();
    let latch = Arc::new(Latch::default());
    let mut channels: BTreeMap<u16, Arc<RawChannel>> = BTreeMap::new();
    // The map as last sent, and its channel.
    let mut map: Option<(Arc<RawChannel>, Vec<u8>)> = None;
    let server = serve(&ctx, a.listen, &latch)?;
    let mut sent = 0u64;
    let mut round = 0u64;
    'rounds: loop {
        round += 1;
        let mut first: Option<(u64, Instant)> = None;
        for m in mcap::MessageStream::new(&bytes)? {
            let m = m?;
            let ch = match channels.get(&m.channel.id) {
                Some(c) => c.clone(),
                None => {
                    let mut b = ChannelBuilder::new(m.channel.topic.clone())
                        .context(&ctx)
                        .message_encoding(m.channel.message_encoding.clone());
                    if let Some(s) = &m.channel.schema {
                        b = b.schema(Schema::new(
                            s.name.clone(),
                            s.encoding.clone(),
                            s.data.to_vec(),
                        ));
                    }
                    let c = b.build_raw()?;
                    channels.insert(m.channel.id, c.clone());
                    c
                }
            };
            // At the recording's pace (divided by --speed), from its first message.
            let (t0, w0) = *first.get_or_insert((m.log_time, Instant::now()));
            let due =
                w0 + Duration::from_secs_f64(m.log_time.saturating_sub(t0) as f64 / 1e9 / a.speed);
            loop {
                let wanted = latch.take();
                if let Some((c, data)) = map.as_ref().filter(|_| wanted) {
                    c.log(data);
                }
                if signals.drain() {
                    break 'rounds;
                }
                let now = Instant::now();
                if now >= due {
                    break;
                }
                std::thread::sleep((due - now).min(Duration::from_millis(20)));
            }
            if m.channel.topic == "/map" {
                map = Some((ch.clone(), m.data.to_vec()));
            }
            ch.log_with_meta(&m.data, PartialMetadata::with_log_time(now_ns()));
            sent += 1;
        }
        if !a.loop_ {
            break;
        }
    }
    println!(
        "{}",
        serde_json::json!({"file": a.file, "messages": total, "sent": sent, "rounds": round})
    );
    server.stop().wait_blocking();
    Ok(ExitCode::SUCCESS)
}

fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}
