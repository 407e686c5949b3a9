//! The broker's UDP front for remote users.
//!
//! It turns authenticated datagrams into the same [`ToBroker`] messages local users put
//! in the broker's inbox (with the user id and pid it authenticated, not the ones the
//! datagram claims), and the core's outputs for remote users into datagrams. Session data
//! never passes here: systems send it to remote users from their own UDP endpoints under
//! a per-session key this front issues.
//!
//! Defences, in the order a datagram meets them: size and header checks; a stateless
//! `RETRY` with an HMAC token for any `INITIAL` without a valid one (no state is kept
//! for unvalidated sources, and a `RETRY` is ~36 bytes against a 1200-byte padded
//! `INITIAL`, far under RFC 9000's 3× rule); a token bucket per validated source address;
//! a cap on pending handshakes, which expire; the Noise XX handshake against the access
//! file; a token bucket per connection; a replay window on every channel.
//!
//! The front is sans IO, in the manner of quinn-proto's `Endpoint`: it is handed
//! datagrams ([`UdpFront::handle`]) and the time ([`UdpFront::handle_timeout`]) and
//! gives back datagrams to send ([`UdpFront::poll_transmit`]) and messages for the core
//! ([`UdpFront::poll_event`]); randomness comes from a seed. It never calls the core:
//! `run/udp_driver.rs` owns the socket and is the only caller of the core, and the in-memory
//! harness drives the same front over a simulated network on a virtual clock.

use crate::core::{Broker, Output};
use crate::federation::FarGrant;
use muster_shared::protocol::{LinkInfo, RemoteContact, ToBroker, ToSystem, ToUser};
use muster_shared::snapshot::{page_of, ListFilter, ServiceView};
use muster_shared::types::{Refusal, ServiceId, UserId};
use muster_shared::udp::access::{valid_user_name, AccessFile};
use muster_shared::udp::crypto::{self, Channel, Cookies, HandshakeState, KeyPair};
use muster_shared::udp::msgs::{
    chunk_list, chunk_operated, from_bytes, seal_channel, Down, Hs3, Up,
};
use muster_shared::udp::wire::RESET_TOKEN;
use muster_shared::udp::wire::{Datagram, WireError};
use muster_shared::udp::{DropCounters, PathProbe, Transmit};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// Most remote users connected at once unless told (`--udp-max-users`).
pub const DEFAULT_MAX_REMOTE_USERS: usize = 16_384;

/// Limits of the UDP front.
#[derive(Clone, Debug)]
pub struct UdpLimits {
    /// Most handshakes in progress at once.
    pub max_pending: usize,
    /// A handshake not finished in this time is dropped.
    pub handshake_timeout: Duration,
    /// Most connections.
    pub max_conns: usize,
    /// A connection silent this long is a dead user.
    pub idle_timeout: Duration,
    /// Datagrams per second (and burst) one connection may send.
    pub conn_rate: (f64, f64),
    /// Handshake datagrams per second (and burst) from one validated address.
    pub source_rate: (f64, f64),
    /// `RETRY`s per second (and burst) for all unvalidated sources together.
    pub retry_rate: (f64, f64),
    /// Requests remembered per connection for idempotent answers.
    pub remembered_requests: usize,
}

impl Default for UdpLimits {
    fn default() -> Self {
        UdpLimits {
            max_pending: 1024,
            handshake_timeout: Duration::from_secs(5),
            max_conns: DEFAULT_MAX_REMOTE_USERS,
            idle_timeout: Duration::from_secs(30),
            conn_rate: (2000.0, 4000.0),
            source_rate: (1000.0, 2000.0),
            retry_rate: (50_000.0, 50_000.0),
            remembered_requests: 256,
        }
    }
}

/// How the front is set up.
#[derive(Clone, Debug)]
pub struct UdpConfig {
    /// Where to listen.
    pub bind: SocketAddr,
    /// The broker's static key.
    pub key: KeyPair,
    /// The access file (reloaded on SIGHUP); `None` denies every user.
    pub access_path: Option<PathBuf>,
    /// Limits.
    pub limits: UdpLimits,
}

/// Counters of the UDP front, for `--stats-json` and tests.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct UdpStats {
    /// Datagrams received.
    pub datagrams_in: u64,
    /// Datagrams sent.
    pub datagrams_out: u64,
    /// Bytes received from sources not (yet) validated.
    pub unvalidated_bytes_in: u64,
    /// Bytes sent to sources not (yet) validated (only `RETRY`s).
    pub unvalidated_bytes_out: u64,
    /// `RETRY`s sent.
    pub retries: u64,
    /// Handshakes finished and authenticated.
    pub handshakes: u64,
    /// Handshakes whose user or key the access file refused.
    pub auth_failed: u64,
    /// Pending handshakes dropped to make room for another source's (fair sharing).
    pub evicted: u64,
    /// Connections dropped for silence.
    pub expired: u64,
    /// Path challenges sent to new addresses of authenticated users.
    pub path_challenges: u64,
    /// Users that moved to a validated new address.
    pub migrations: u64,
    /// Requests that arrived again and were answered from memory.
    pub duplicate_requests: u64,
    /// Requests refused here (not allowed, or no UDP endpoint on the system).
    pub refused_here: u64,
    /// Access file reloads.
    pub reloads: u64,
    /// Stateless resets sent (channel datagrams of connections this broker never had).
    pub resets_sent: u64,
    /// Dropped datagrams by reason.
    pub drops: DropCounters,
}

/// Why a remote user's operator action is refused.
pub const REMOTE_OPERATORS: &str =
    "operators only: this user is not an operator in the broker's access file (an `operator` line, `muster keygen --operator`)";

/// Operator actions whose answers a connection keeps for repeats.
const KEPT_OPS: usize = 16;

/// Most stateless resets a front sends a second (and its burst).
const RESETS_PER_SEC: f64 = 500.0;

struct Bucket {
    tokens: f64,
    last: Instant,
}

impl Bucket {
    fn new(now: Instant, burst: f64) -> Self {
        Bucket {
            tokens: burst,
            last: now,
        }
    }

    fn take(&mut self, now: Instant, (rate, burst): (f64, f64)) -> bool {
        let dt = now.saturating_duration_since(self.last).as_secs_f64();
        self.last = now;
        self.tokens = (self.tokens + dt * rate).min(burst);
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

struct Pending {
    addr: SocketAddr,
    client: u64,
    hs: HandshakeState,
    reply: Vec<u8>,
    deadline: Instant,
}

enum ReqState {
    Pending,
    Queued(u16),
    Done(Box<Down>),
}

struct Conn {
    addr: SocketAddr,
    name: String,
    suffix: String,
    user: Option<UserId>,
    chan: Channel,
    last_heard: Instant,
    bucket: Bucket,
    reqs: BTreeMap<u64, ReqState>,
    /// Requests at or below this number were forgotten; repeats of them are dropped.
    floor: u64,
    keys: HashMap<u64, [u8; 32]>,
    /// A new address the user's datagrams came from, the challenge sent there, and when.
    probe: PathProbe,
    /// An operator's latest actions: `None` while the core works on one, then its
    /// answer in pieces, sent again whole if the action comes again.
    ops: BTreeMap<u64, Option<Vec<Down>>>,
}

/// What the front hands the core (through the broker shell, `run/`).
#[derive(Clone, Debug, PartialEq)]
pub enum FrontEvent {
    /// A message from an authenticated remote user, with the id the front gave it.
    ToCore(ToBroker),
    /// A remote user is gone (silence).
    UserGone(UserId),
    /// A remote user's access was revoked: its sessions must end at the systems.
    Revoked(UserId),
}

/// What the front asks of the broker's state (read only): [`Broker`] answers it, and
/// tests may answer it themselves.
pub trait Directory {
    /// Whether `service` is registered.
    fn knows(&self, service: &ServiceId) -> bool;
    /// The UDP endpoint `system` registered, if any.
    fn system_udp(&self, system: &str) -> Option<&str>;
}

impl Directory for Broker {
    fn knows(&self, service: &ServiceId) -> bool {
        self.kind_of(service).is_some()
    }
    fn system_udp(&self, system: &str) -> Option<&str> {
        Broker::system_udp(self, system)
    }
}

/// The UDP front: handshakes and connections, sans IO.
pub struct UdpFront {
    local: SocketAddr,
    key: KeyPair,
    access: AccessFile,
    cookies: Cookies,
    /// The clock's origin, for the address-validation tokens' time stamps.
    born: Instant,
    rng: StdRng,
    out: VecDeque<Transmit>,
    events: VecDeque<FrontEvent>,
    next_housekeeping: Option<Instant>,
    limits: UdpLimits,
    pending: HashMap<u64, Pending>,
    pending_by: HashMap<(SocketAddr, u64), u64>,
    /// Pending handshakes by source, oldest first (for fair sharing of the table).
    pending_of: HashMap<Source, VecDeque<u64>>,
    /// Handshakes finished lately, by source and handshake id: a late repeat of their
    /// INITIAL (a slow link) is dropped instead of starting another one.
    finished: HashMap<(SocketAddr, u64), Instant>,
    conns: HashMap<u64, Conn>,
    /// Connections closed lately (goodbye, expiry, revocation): their stragglers (a
    /// repeated goodbye, a keepalive in flight) are counted quietly, not as attacks.
    closed: HashMap<u64, Instant>,
    by_user: HashMap<UserId, u64>,
    sources: HashMap<IpAddr, Bucket>,
    retry_bucket: Bucket,
    reset_budget: Bucket,
    views: Vec<ServiceView>,
    /// Connections of operators that have acted: the event feed's records go to them
    /// (a set, so that a record does not look through every connection: it is made
    /// for every grant and end, hundreds a second at 900 users).
    following: BTreeSet<u64>,
    epoch: u64,
    generation: u64,
    stats: UdpStats,
}

/// Why the UDP front could not start.
#[derive(Debug, thiserror::Error)]
pub enum UdpError {
    /// The socket could not be bound.
    #[error("cannot listen on udp {0}: {1}")]
    Bind(SocketAddr, std::io::Error),
    /// The access file is unreadable or wrong.
    #[error("{0}")]
    Access(String),
}

/// Housekeeping period (expiring handshakes and silent connections).
const HOUSEKEEPING: Duration = Duration::from_millis(500);

impl UdpFront {
    /// A front that says it listens at `local` (for the systems' addresses it gives
    /// out), with the broker's static key, the access file's contents and a seed for
    /// its randomness (connection ids, session keys, the token secret).
    pub fn new(
        key: KeyPair,
        access: AccessFile,
        limits: UdpLimits,
        local: SocketAddr,
        epoch: u64,
        now: Instant,
        seed: [u8; 32],
    ) -> Self {
        let mut rng = StdRng::from_seed(seed);
        let retry_bucket = Bucket::new(now, limits.retry_rate.1);
        UdpFront {
            local,
            key,
            access,
            cookies: Cookies::with_secret(rng.random()),
            born: now,
            rng,
            out: VecDeque::new(),
            events: VecDeque::new(),
            next_housekeeping: None,
            limits,
            pending: HashMap::new(),
            pending_by: HashMap::new(),
            pending_of: HashMap::new(),
            finished: HashMap::new(),
            conns: HashMap::new(),
            closed: HashMap::new(),
            by_user: HashMap::new(),
            sources: HashMap::new(),
            retry_bucket,
            reset_budget: Bucket::new(now, RESETS_PER_SEC),
            views: Vec::new(),
            following: BTreeSet::new(),
            epoch,
            generation: 0,
            stats: UdpStats::default(),
        }
    }

    /// The next datagram to send.
    pub fn poll_transmit(&mut self) -> Option<Transmit> {
        self.out.pop_front()
    }

    /// The next message for the core.
    pub fn poll_event(&mut self) -> Option<FrontEvent> {
        self.events.pop_front()
    }

    /// The address the front says it listens at.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// Counters.
    pub fn stats(&self) -> &UdpStats {
        &self.stats
    }

    /// Counters, for the driver's own drops (a failed send).
    pub fn stats_mut(&mut self) -> &mut UdpStats {
        &mut self.stats
    }

    /// Number of authenticated connections.
    pub fn connections(&self) -> usize {
        self.conns.len()
    }

    /// Whether `user` is one of ours.
    pub fn is_remote(&self, user: &UserId) -> bool {
        self.by_user.contains_key(user)
    }

    /// A new access file (SIGHUP). Connections whose user left the file or whose key
    /// changed are closed (their users die to the core).
    pub fn reload(&mut self, now: Instant, access: AccessFile) {
        tracing::info!(users = access.len(), "access file reloaded");
        self.access = access;
        self.stats.reloads += 1;
        let revoked: Vec<u64> = self
            .conns
            .iter()
            .filter(|(_, c)| {
                self.access
                    .get(&c.name)
                    .is_none_or(|p| Some(p.key.as_slice()) != c.chan_key())
            })
            .map(|(id, _)| *id)
            .collect();
        for id in revoked {
            tracing::warn!(conn = format!("{id:016x}"), "access revoked: closed");
            self.close(now, id, true);
        }
    }

    /// The list changed: remember it for list requests.
    pub fn list_changed(&mut self, epoch: u64, generation: u64, views: &[ServiceView]) {
        self.epoch = epoch;
        self.generation = generation;
        self.views = views.to_vec();
    }

    /// [`UdpFront::list_changed`] where only `rows` of `views` changed since the last
    /// call (`None`: any may have).
    pub fn list_changed_rows(
        &mut self,
        epoch: u64,
        generation: u64,
        views: &[ServiceView],
        rows: Option<&[usize]>,
    ) {
        match rows.filter(|_| self.views.len() == views.len() && self.epoch == epoch) {
            Some(rows) => {
                self.generation = generation;
                for &i in rows {
                    self.views[i].clone_from(&views[i]);
                }
            }
            None => self.list_changed(epoch, generation, views),
        }
    }

    /// Tells remote list watchers that the list changed.
    pub fn ring(&mut self, watchers: &[UserId]) {
        let generation = self.generation;
        for u in watchers {
            if let Some(&id) = self.by_user.get(u) {
                self.send(id, &Down::ListChanged { generation });
            }
        }
    }

    /// When [`UdpFront::handle_timeout`] is next due.
    pub fn poll_timeout(&self) -> Option<Instant> {
        if self.pending.is_empty() && self.conns.is_empty() {
            None
        } else {
            Some(self.next_housekeeping.unwrap_or(self.born))
        }
    }

    /// Expires handshakes and silent connections, if due.
    pub fn handle_timeout(&mut self, now: Instant) {
        if self.poll_timeout().is_none_or(|t| now < t) {
            return;
        }
        self.next_housekeeping = Some(now + HOUSEKEEPING);
        let t = now;
        let expired: Vec<u64> = self
            .pending
            .iter()
            .filter(|(_, p)| t >= p.deadline)
            .map(|(id, _)| *id)
            .collect();
        for id in expired {
            self.drop_pending(id);
        }
        let idle = self.limits.idle_timeout;
        let silent: Vec<u64> = self
            .conns
            .iter()
            .filter(|(_, c)| t.saturating_duration_since(c.last_heard) >= idle)
            .map(|(id, _)| *id)
            .collect();
        for id in silent {
            tracing::info!(conn = format!("{id:016x}"), "remote user silent: gone");
            self.stats.expired += 1;
            self.close(now, id, false);
        }
        self.closed
            .retain(|_, at| t.saturating_duration_since(*at) < Duration::from_secs(10));
        let keep = self.limits.handshake_timeout * 2;
        self.finished
            .retain(|_, at| t.saturating_duration_since(*at) < keep);
        if self.sources.len() > 4 * self.limits.max_pending {
            let (rate, burst) = self.limits.source_rate;
            self.sources
                .retain(|_, b| t.saturating_duration_since(b.last).as_secs_f64() * rate < burst);
        }
    }

    fn drop_pending(&mut self, id: u64) {
        let _ = self.take_pending(id);
    }

    fn take_pending(&mut self, id: u64) -> Option<Pending> {
        let p = self.pending.remove(&id)?;
        self.pending_by.remove(&(p.addr, p.client));
        let src = source_of(&p.addr);
        if let Some(q) = self.pending_of.get_mut(&src) {
            q.retain(|c| *c != id);
            if q.is_empty() {
                self.pending_of.remove(&src);
            }
        }
        Some(p)
    }

    /// Makes room for a handshake from `src` when the table is full: the source holding
    /// the most pending handshakes loses its oldest, if it holds more than `src` would
    /// after this one. So a flood from one or a few addresses only ever competes with
    /// itself, and every other source still gets its handshake in.
    fn make_room(&mut self, src: &Source) -> bool {
        if self.pending.len() < self.limits.max_pending {
            return true;
        }
        let mine = self.pending_of.get(src).map_or(0, VecDeque::len);
        let Some(victim) = self
            .pending_of
            .iter()
            .filter(|(_, q)| q.len() > mine + 1)
            .max_by_key(|(s, q)| (q.len(), **s))
            .and_then(|(_, q)| q.front().copied())
        else {
            return false;
        };
        self.stats.evicted += 1;
        self.drop_pending(victim);
        true
    }

    fn close(&mut self, now: Instant, id: u64, revoked: bool) {
        self.closed.insert(id, now);
        if let Some(c) = self.conns.remove(&id) {
            if let Some(u) = c.user {
                if self.by_user.get(&u) == Some(&id) {
                    self.by_user.remove(&u);
                    self.events.push_back(if revoked {
                        FrontEvent::Revoked(u)
                    } else {
                        FrontEvent::UserGone(u)
                    });
                }
            }
        }
    }

    /// One datagram from `from` at `now`. What it means for the core comes out of
    /// [`UdpFront::poll_event`]; `dir` answers questions about the registry.
    pub fn handle(&mut self, now: Instant, from: SocketAddr, bytes: &[u8], dir: &impl Directory) {
        self.stats.datagrams_in += 1;
        let d = match Datagram::decode(bytes) {
            Ok(d) => d,
            Err(e) => {
                self.stats.unvalidated_bytes_in += bytes.len() as u64;
                return self.stats.drops.drop(wire_reason(&e), &from);
            }
        };
        match d {
            Datagram::Initial {
                client,
                token,
                noise,
            } => self.on_initial(now, bytes.len(), from, client, token, noise),
            Datagram::HsFinal { conn, noise } => self.on_final(now, from, conn, noise),
            Datagram::Channel {
                conn,
                nonce,
                sealed,
            } => self.on_channel(dir, now, from, conn, nonce, sealed),
            _ => {
                self.stats.unvalidated_bytes_in += bytes.len() as u64;
                self.stats.drops.drop("unexpected_kind", &from)
            }
        }
    }

    fn on_initial(
        &mut self,
        t: Instant,
        len: usize,
        from: SocketAddr,
        client: u64,
        token: &[u8],
        noise: &[u8],
    ) {
        let now_s = t.saturating_duration_since(self.born).as_secs();
        if !self.cookies.check(now_s, token, &from, client) {
            self.stats.unvalidated_bytes_in += len as u64;
            if !token.is_empty() {
                return self.stats.drops.drop("bad_token", &from);
            }
            if !self.retry_bucket.take(t, self.limits.retry_rate) {
                return self.stats.drops.drop("retry_budget", &from);
            }
            let token = self.cookies.mint(now_s, &from, client);
            let Ok(bytes) = (Datagram::Retry {
                client,
                token: &token,
            })
            .encode() else {
                return;
            };
            debug_assert!(bytes.len() * 3 <= len, "a retry never amplifies");
            self.stats.retries += 1;
            self.stats.unvalidated_bytes_out += bytes.len() as u64;
            return self.send_raw(bytes, from);
        }
        // The address is validated: it received our token.
        let (rate, burst) = self.limits.source_rate;
        let bucket = self
            .sources
            .entry(from.ip())
            .or_insert_with(|| Bucket::new(t, burst));
        if !bucket.take(t, (rate, burst)) {
            return self.stats.drops.drop("source_rate", &from);
        }
        if self.finished.contains_key(&(from, client)) {
            return self.stats.drops.count("handshake_done");
        }
        if let Some(id) = self.pending_by.get(&(from, client)) {
            // A retransmitted INITIAL: answer with the same reply.
            if let Some(p) = self.pending.get(id) {
                let reply = p.reply.clone();
                return self.send_raw(reply, from);
            }
        }
        let src = source_of(&from);
        if !self.make_room(&src) {
            return self.stats.drops.drop("pending_full", &from);
        }
        let mut hs = match crypto::responder(&self.key) {
            Ok(h) => h,
            Err(e) => {
                tracing::error!("cannot start a handshake: {e}");
                return;
            }
        };
        let mut scratch = [0u8; 1024];
        if hs.read_message(noise, &mut scratch).is_err() {
            return self.stats.drops.drop("bad_handshake", &from);
        }
        let conn: u64 = self.rng.random();
        // The connection's stateless reset token rides in Noise message 2 (encrypted
        // to the user, authenticated): any broker with this key can later prove it
        // does not know the connection.
        let mut msg2 = [0u8; 1024];
        let Ok(n) = hs.write_message(&self.key.reset_token(conn), &mut msg2) else {
            return self.stats.drops.drop("bad_handshake", &from);
        };
        let Ok(reply) = (Datagram::HsReply {
            client,
            conn,
            noise: &msg2[..n],
        })
        .encode() else {
            return;
        };
        self.send_raw(reply.clone(), from);
        self.pending_by.insert((from, client), conn);
        self.pending_of.entry(src).or_default().push_back(conn);
        self.pending.insert(
            conn,
            Pending {
                addr: from,
                client,
                hs,
                reply,
                deadline: t + self.limits.handshake_timeout,
            },
        );
    }

    fn on_final(&mut self, now: Instant, from: SocketAddr, conn: u64, noise: &[u8]) {
        if self.conns.contains_key(&conn) {
            return; // a retransmission of a handshake already done
        }
        if self.pending.get(&conn).is_none_or(|p| p.addr != from) {
            return self.stats.drops.drop("unknown_handshake", &from);
        }
        let Some(mut p) = self.take_pending(conn) else {
            return;
        };
        let mut payload = [0u8; 1024];
        let n = match p.hs.read_message(noise, &mut payload) {
            Ok(n) => n,
            Err(_) => return self.stats.drops.drop("bad_handshake", &from),
        };
        let Ok(hs3) = from_bytes::<Hs3>(&payload[..n]) else {
            return self.stats.drops.drop("bad_handshake", &from);
        };
        let proven = p.hs.get_remote_static().map(<[u8]>::to_vec);
        let allowed = valid_user_name(&hs3.name)
            && valid_suffix(&hs3.suffix)
            && self
                .access
                .get(&hs3.name)
                .is_some_and(|pol| Some(pol.key.as_slice()) == proven.as_deref());
        if !allowed {
            self.stats.auth_failed += 1;
            return self.stats.drops.drop("auth_failed", &from);
        }
        if self.conns.len() >= self.limits.max_conns {
            return self.stats.drops.drop("conns_full", &from);
        }
        let chan = match Channel::new(p.hs) {
            Ok(c) => c,
            Err(_) => return self.stats.drops.drop("bad_handshake", &from),
        };
        let (_, burst) = self.limits.conn_rate;
        self.stats.handshakes += 1;
        self.finished.insert((from, p.client), now);
        tracing::debug!(user = %hs3.name, %from, "remote user authenticated");
        self.conns.insert(
            conn,
            Conn {
                addr: from,
                name: hs3.name,
                suffix: hs3.suffix,
                user: None,
                chan,
                last_heard: now,
                bucket: Bucket::new(now, burst),
                reqs: BTreeMap::new(),
                floor: 0,
                keys: HashMap::new(),
                probe: PathProbe::default(),
                ops: BTreeMap::new(),
            },
        );
    }

    fn on_channel(
        &mut self,
        dir: &impl Directory,
        t: Instant,
        from: SocketAddr,
        id: u64,
        nonce: u64,
        sealed: &[u8],
    ) {
        let rate = self.limits.conn_rate;
        let Some(c) = self.conns.get_mut(&id) else {
            if self.closed.contains_key(&id) {
                return self.stats.drops.count("after_close");
            }
            if self.pending.contains_key(&id) {
                // The user's first sealed datagrams overtook (or outlived) its FINAL:
                // the connection is ours, just not up yet. It retransmits both.
                return self.stats.drops.drop("before_final", &from);
            }
            self.stats.drops.drop("unknown_conn", &from);
            // A connection of a broker before us (a standby took over, or we restarted
            // with the same key): tell the user at once, with the token only the key's
            // holder can compute (RFC 9000 §10.3). Smaller than what came, and rate
            // limited, so it amplifies nothing.
            if sealed.len() >= RESET_TOKEN
                && self.reset_budget.take(t, (RESETS_PER_SEC, RESETS_PER_SEC))
            {
                let reset = Datagram::Reset {
                    conn: id,
                    token: self.key.reset_token(id),
                };
                if let Ok(bytes) = reset.encode() {
                    self.stats.resets_sent += 1;
                    self.send_raw(bytes, from);
                }
            }
            return;
        };
        // Authenticate first: forged datagrams carrying a live connection id (it is on
        // the wire) must not spend the real user's rate.
        let plain = match c.chan.open(nonce, sealed) {
            Ok(p) => p,
            Err(_) => return self.stats.drops.drop("forged_or_replayed", &from),
        };
        if !c.bucket.take(t, rate) {
            return self.stats.drops.drop("conn_rate", &from);
        }
        c.last_heard = t;
        let msg = match from_bytes::<Up>(&plain) {
            Ok(m) => m,
            Err(_) => return self.stats.drops.drop("bad_message", &from),
        };
        // Authenticated, but maybe from a new address: the user moved (NAT rebinding),
        // or someone replays its datagrams from elsewhere. The path is validated first
        // (RFC 9000 §9): a challenge goes there, smaller than what came; answers keep
        // going to the old address until the new one echoes the challenge.
        if from != c.addr {
            if let Up::PathResponse { token } = msg {
                if c.probe.answered(from, token) {
                    tracing::debug!(conn = format!("{id:016x}"), %from, "remote user moved");
                    c.addr = from;
                    self.stats.migrations += 1;
                }
                return;
            }
            if let Some(token) = c.probe.challenge(from, t, || self.rng.random()) {
                self.stats.path_challenges += 1;
                self.send_to(id, from, &Down::PathChallenge { token });
            }
        }
        match msg {
            Up::Ping { nonce } => {
                let generation = self.generation;
                self.send(id, &Down::Pong { nonce, generation });
            }
            Up::List {
                ask,
                filter,
                offset,
                limit,
            } => self.send_list(id, ask, &filter, (offset as usize, limit as usize)),
            Up::PathResponse { .. } => {}
            Up::Msg(m) => self.on_user_msg(dir, t, id, m, from),
        }
    }

    /// Sends the services `filter` lets through that the user may see, from the
    /// `offset`th, at most `limit` (a bad name glob lets nothing through; the client
    /// checks it before asking).
    fn send_list(
        &mut self,
        id: u64,
        ask: u32,
        filter: &ListFilter,
        (offset, limit): (usize, usize),
    ) {
        let Some(c) = self.conns.get(&id) else { return };
        let policy = self.access.get(&c.name);
        let m = filter.matcher();
        let visible = self
            .views
            .iter()
            .filter(|v| policy.is_some_and(|p| p.allows(&v.id)) && m.matches_view(v));
        let (matching, views) = page_of(visible, offset, limit);
        let matching = u32::try_from(matching).unwrap_or(u32::MAX);
        // The chunks borrow the views: sealed here, field by field, not through
        // `send` (which borrows the whole front).
        let Some(c) = self.conns.get_mut(&id) else {
            return;
        };
        for chunk in chunk_list(self.epoch, self.generation, (ask, matching), views) {
            match seal_channel(&mut c.chan, id, &chunk) {
                Ok(bytes) => queue(&mut self.out, &mut self.stats, c.addr, bytes),
                Err(e) => tracing::error!("cannot send a list to a remote user: {e}"),
            }
        }
    }

    fn on_user_msg(
        &mut self,
        dir: &impl Directory,
        now: Instant,
        id: u64,
        m: ToBroker,
        from: SocketAddr,
    ) {
        let Some(c) = self.conns.get_mut(&id) else {
            return;
        };
        let policy = self.access.get(&c.name);
        let allowed =
            |l: &LinkInfo| policy.is_some_and(|p| p.allows(&l.data.0) && p.allows(&l.command.0));
        if let ToBroker::Hello {
            links, watch_list, ..
        } = m
        {
            // Links over services the user may not use do not show in anyone's list.
            let links: Vec<LinkInfo> = links.into_iter().filter(|l| allowed(l)).collect();
            let user = UserId(format!("{}.{}", c.name, c.suffix));
            c.user = Some(user.clone());
            if let Some(old) = self.by_user.insert(user.clone(), id) {
                if old != id {
                    // The same user reconnected (new handshake): the old connection goes,
                    // its requests' memory and keys move over (an offer in flight must
                    // reach the user with the key the system got).
                    if let Some(o) = self.conns.remove(&old) {
                        if let Some(c) = self.conns.get_mut(&id) {
                            c.reqs = o.reqs;
                            c.keys = o.keys;
                            c.floor = o.floor;
                        }
                    }
                    self.closed.insert(old, now);
                }
            }
            self.events.push_back(FrontEvent::ToCore(ToBroker::Hello {
                user,
                pid: 0,
                links,
                watch_list,
            }));
            return;
        }
        let Some(user) = c.user.clone() else {
            return self.stats.drops.drop("no_hello", &from);
        };
        match m {
            ToBroker::Request { req, service, .. } => {
                self.on_request(dir, id, user, req, service, from)
            }
            ToBroker::Cancel { req, .. } => self
                .events
                .push_back(FrontEvent::ToCore(ToBroker::Cancel { user, req })),
            ToBroker::LinkOpened { link, .. } if !allowed(&link) => {
                self.stats.drops.drop("link_not_allowed", &from)
            }
            ToBroker::LinkOpened { link, .. } => self
                .events
                .push_back(FrontEvent::ToCore(ToBroker::LinkOpened { user, link })),
            ToBroker::LinkClosed { link, .. } => self
                .events
                .push_back(FrontEvent::ToCore(ToBroker::LinkClosed { user, link })),
            ToBroker::WatchList { filter, .. } => self
                .events
                .push_back(FrontEvent::ToCore(ToBroker::WatchList { user, filter })),
            ToBroker::Goodbye { .. } => {
                self.by_user.remove(&user);
                self.conns.remove(&id);
                self.closed.insert(id, now);
                self.events
                    .push_back(FrontEvent::ToCore(ToBroker::Goodbye { user }));
            }
            // Operators are the users the access file calls so.
            ToBroker::Operate { id: op, .. } if !policy.is_some_and(|p| p.operator) => {
                let m = ToUser::Operated {
                    id: op,
                    result: Err(REMOTE_OPERATORS.into()),
                };
                self.send(id, &Down::Msg(m));
            }
            ToBroker::Operate {
                id: op, op: action, ..
            } => match c.ops.get(&op) {
                // The core has it; its answer will come.
                Some(None) => self.stats.duplicate_requests += 1,
                Some(Some(pieces)) => {
                    self.stats.duplicate_requests += 1;
                    for d in pieces.clone() {
                        self.send(id, &d);
                    }
                }
                None => {
                    c.ops.insert(op, None);
                    while c.ops.len() > KEPT_OPS {
                        c.ops.pop_first();
                    }
                    self.following.insert(id);
                    self.events.push_back(FrontEvent::ToCore(ToBroker::Operate {
                        user,
                        id: op,
                        op: action,
                    }));
                }
            },
            _ => self.stats.drops.drop("not_a_user_message", &from),
        }
    }

    fn on_request(
        &mut self,
        dir: &impl Directory,
        id: u64,
        user: UserId,
        req: u64,
        service: ServiceId,
        from: SocketAddr,
    ) {
        let Some(c) = self.conns.get_mut(&id) else {
            return;
        };
        if req <= c.floor {
            return self.stats.drops.drop("stale_request", &from);
        }
        match c.reqs.get(&req) {
            Some(ReqState::Pending) => {
                self.stats.duplicate_requests += 1;
                return;
            }
            Some(ReqState::Queued(position)) => {
                self.stats.duplicate_requests += 1;
                let m = Down::Msg(ToUser::Queued {
                    req,
                    position: *position,
                });
                return self.send(id, &m);
            }
            Some(ReqState::Done(d)) => {
                self.stats.duplicate_requests += 1;
                let d = (**d).clone();
                return self.send(id, &d);
            }
            None => {}
        }
        let allowed = self
            .access
            .get(&c.name)
            .is_some_and(|p| p.allows(&service.0));
        let no_udp = service
            .split()
            .is_some_and(|(sys, _)| dir.knows(&service) && dir.system_udp(sys).is_none());
        let refusal = if !allowed {
            // Not allowed looks like not there: the list never showed it either.
            Some(Refusal::Unknown)
        } else if no_udp {
            Some(Refusal::BadRequest(format!(
                "{service} is on a system without a UDP endpoint: local users only"
            )))
        } else {
            None
        };
        c.reqs.insert(req, ReqState::Pending);
        while c.reqs.len() > self.limits.remembered_requests {
            let Some((&oldest, _)) = c.reqs.iter().next() else {
                break;
            };
            c.reqs.remove(&oldest);
            c.keys.remove(&oldest);
            c.floor = c.floor.max(oldest);
        }
        match refusal {
            Some(reason) => {
                self.stats.refused_here += 1;
                self.answer(id, req, Down::Msg(ToUser::Refused { req, reason }), true);
            }
            None => {
                muster_shared::trace::stamp(muster_shared::trace::Stage::BrokerRecv, &user, req);
                self.events
                    .push_back(FrontEvent::ToCore(ToBroker::Request { user, req, service }))
            }
        }
    }

    /// Records a final or queued answer and sends it.
    fn answer(&mut self, id: u64, req: u64, d: Down, fin: bool) {
        if let Some(c) = self.conns.get_mut(&id) {
            if let Some(slot) = c.reqs.get_mut(&req) {
                *slot = if fin {
                    ReqState::Done(Box::new(d.clone()))
                } else {
                    match &d {
                        Down::Msg(ToUser::Queued { position, .. }) => ReqState::Queued(*position),
                        _ => ReqState::Pending,
                    }
                };
            }
        }
        self.send(id, &d);
    }

    /// Takes the core's outputs meant for remote users (and fills in remote offers);
    /// gives back the rest for the shared-memory side.
    pub fn route(&mut self, dir: &impl Directory, out: Output) -> Option<Output> {
        match out {
            Output::ToUser(user, msg) => {
                let Some(&id) = self.by_user.get(&user) else {
                    return Some(Output::ToUser(user, msg));
                };
                match msg {
                    ToUser::Welcome { epoch, .. } => self.send(id, &Down::Welcome { user, epoch }),
                    ToUser::Refused { req, reason } => {
                        self.answer(id, req, Down::Msg(ToUser::Refused { req, reason }), true)
                    }
                    ToUser::Queued { req, position } => {
                        self.answer(id, req, Down::Msg(ToUser::Queued { req, position }), false)
                    }
                    ToUser::Operated { id: op, result } => self.operated(id, op, &result),
                    other => self.send(id, &Down::Msg(other)),
                }
                None
            }
            Output::Granted(g) if self.by_user.contains_key(&g.user) => {
                let system_addr = dir.system_udp(&g.system()?)?.to_string();
                let _ = self.granted(FarGrant::new(g, system_addr));
                None
            }
            Output::ToSystem(system, mut offer @ ToSystem::Offer { .. }) => {
                if let ToSystem::Offer {
                    user, req, remote, ..
                } = &mut offer
                {
                    *remote = self.remote_contact(user, *req);
                }
                Some(Output::ToSystem(system, offer))
            }
            Output::WatchUser { user, .. } | Output::ForgetUser(user)
                if self.by_user.contains_key(&user) =>
            {
                None
            }
            other => Some(other),
        }
    }

    /// The core's answer to operator action `op` of connection `id`: sent in pieces and
    /// kept for a repeat of the action.
    fn operated(&mut self, id: u64, op: u64, result: &muster_shared::udp::msgs::OperatedResult) {
        let pieces = chunk_operated(op, result).unwrap_or_else(|| {
            let why: muster_shared::udp::msgs::OperatedResult =
                Err("the answer is too large to send".into());
            chunk_operated(op, &why).unwrap_or_default()
        });
        for d in &pieces {
            self.send(id, d);
        }
        if let Some(c) = self.conns.get_mut(&id) {
            if let Some(slot) = c.ops.get_mut(&op) {
                *slot = Some(pieces);
            }
        }
    }

    /// A record of the broker's event feed (its JSON): sent to every operator that has
    /// acted, if it fits a datagram.
    pub fn feed(&mut self, json: &str) {
        if self.following.is_empty() {
            return;
        }
        // Operators now: one the access file no longer calls so (SIGHUP) gets no more.
        let conns = &self.conns;
        self.following.retain(|id| conns.contains_key(id));
        let access = &self.access;
        let ids: Vec<u64> = self
            .following
            .iter()
            .copied()
            .filter(|id| {
                conns.get(id).is_some_and(|c| {
                    c.user.is_some() && access.get(&c.name).is_some_and(|p| p.operator)
                })
            })
            .collect();
        // Room for the variant's tag and the length prefix.
        if ids.is_empty() || json.len() > muster_shared::udp::wire::MAX_PLAINTEXT - 8 {
            return;
        }
        let d = Down::Event(json.to_string());
        for id in ids {
            self.send(id, &d);
        }
    }

    /// A remote user's address and a fresh session key for its request `req` (kept for
    /// the grant), given to the system that will serve it; `None` for a user not here.
    pub fn remote_contact(&mut self, user: &UserId, req: u64) -> Option<RemoteContact> {
        let &id = self.by_user.get(user)?;
        let key: [u8; 32] = self.rng.random();
        let c = self.conns.get_mut(&id)?;
        c.keys.insert(req, key);
        Some(RemoteContact {
            addr: c.addr.to_string(),
            key,
        })
    }

    /// Tells remote user `g.user` of its grant: the session runs with the system at
    /// `g.system_addr` under the key issued for the request. Gives the grant back if the
    /// user or the key is gone.
    pub fn granted(&mut self, g: FarGrant) -> Result<(), FarGrant> {
        let id = self.by_user.get(&g.user).copied();
        let key = id.and_then(|id| self.conns.get(&id)?.keys.get(&g.req).copied());
        let (Some(id), Some(key)) = (id, key) else {
            return Err(g);
        };
        let (user, req) = (g.user, g.req);
        let d = Down::Granted {
            req,
            session: g.session,
            service: g.service,
            kind: g.kind,
            payload: g.payload,
            system_addr: self.reachable(&g.system_addr),
            key,
        };
        muster_shared::trace::stamp(muster_shared::trace::Stage::BrokerRelay, &user, req);
        self.answer(id, req, d, true);
        Ok(())
    }

    /// A system's UDP address as a remote user can reach it: an unspecified IP (the
    /// system listens everywhere) becomes the address users reach this broker at.
    fn reachable(&self, addr: &str) -> String {
        match addr.parse::<SocketAddr>() {
            Ok(a) if a.ip().is_unspecified() => {
                let ip = if self.local.ip().is_unspecified() {
                    IpAddr::V4(Ipv4Addr::LOCALHOST)
                } else {
                    self.local.ip()
                };
                SocketAddr::new(ip, a.port()).to_string()
            }
            _ => addr.to_string(),
        }
    }

    fn send(&mut self, id: u64, d: &Down) {
        let Some(addr) = self.conns.get(&id).map(|c| c.addr) else {
            return;
        };
        self.send_to(id, addr, d);
    }

    fn send_to(&mut self, id: u64, addr: SocketAddr, d: &Down) {
        let Some(c) = self.conns.get_mut(&id) else {
            return;
        };
        match seal_channel(&mut c.chan, id, d) {
            Ok(dg) => self.send_raw(dg, addr),
            Err(e) => tracing::error!("cannot send to a remote user: {e}"),
        }
    }

    fn send_raw(&mut self, bytes: Vec<u8>, to: SocketAddr) {
        queue(&mut self.out, &mut self.stats, to, bytes);
    }
}

/// Queues a datagram for [`UdpFront::poll_transmit`], counted (a function of the two
/// fields, for callers that hold a borrow of another).
fn queue(out: &mut VecDeque<Transmit>, stats: &mut UdpStats, to: SocketAddr, bytes: Vec<u8>) {
    stats.datagrams_out += 1;
    out.push_back(Transmit { to, bytes });
}

impl Conn {
    fn chan_key(&self) -> Option<&[u8]> {
        self.chan.remote_static()
    }
}

/// A source for fair sharing: an IPv4 address, or an IPv6 /64 (one host's share).
type Source = u128;

fn source_of(addr: &SocketAddr) -> Source {
    match addr.ip() {
        IpAddr::V4(a) => u128::from(u32::from(a)),
        IpAddr::V6(a) => (u128::from(a) >> 64 << 64) | (1 << 32),
    }
}

fn valid_suffix(s: &str) -> bool {
    !s.is_empty() && s.len() <= 16 && s.bytes().all(|b| b.is_ascii_alphanumeric())
}

fn wire_reason(e: &WireError) -> &'static str {
    match e {
        WireError::Truncated(_) => "truncated",
        WireError::BadMagic(_) => "bad_magic",
        WireError::WrongVersion(_) => "wrong_version",
        WireError::UnknownKind(_) => "unknown_kind",
        WireError::Oversized(_) => "oversized",
        WireError::Unpadded(_) => "unpadded_initial",
        WireError::Trailing(_) => "trailing_bytes",
    }
}

#[cfg(test)]
#[path = "udp_tests.rs"]
mod tests;
