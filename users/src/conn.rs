//! The user's side of the UDP path, sans IO: handshake with the broker, the encrypted
//! channel, retries, keepalives, reconnection, and sessions straight with systems.
//!
//! Reliability is pull-based: the user repeats what it needs until it hears the answer
//! (hello until welcome, a request until it is granted or refused, an `End` until the
//! system says `Ended`, the list until every chunk of one generation arrived), with
//! exponential backoff. The broker and systems answer repeats idempotently, so a
//! duplicated or retried request never yields two grants.
//!
//! [`crate::remote::RemoteLink`] drives it over a socket; the in-memory harness drives
//! it over a simulated network on a virtual clock.

use crate::core::UserCore;
use crate::remote::RemoteOptions;
use muster_shared::protocol::{EventRecord, ToBroker, ToSystem, ToUser};
use muster_shared::snapshot::{ListFilter, ServiceListSnapshot, ServiceView};
use muster_shared::types::{SessionId, UserId};
use muster_shared::udp::crypto::{self, Channel, HandshakeState, SessionCipher, Side};
use muster_shared::udp::early::Early;
use muster_shared::udp::msgs::{
    from_bytes, seal_channel, seal_session, to_bytes, Down, Hs3, OperatedAssembly, SessionDown,
    SessionUp, Up,
};
use muster_shared::udp::wire::{Datagram, RESET_TOKEN};
use muster_shared::udp::{DropCounters, Transmit};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// Retransmission timeout before any round trip was measured; doubles up to
/// [`MAX_RTO`] on each retry. Once keepalives have measured the round trip, the timeout
/// is RFC 6298's `SRTT + 4·RTTVAR`, at least [`MIN_RTO`].
pub const RTO: Duration = Duration::from_millis(200);
/// Shortest retransmission timeout.
pub const MIN_RTO: Duration = Duration::from_millis(20);
/// Longest retransmission timeout.
pub const MAX_RTO: Duration = Duration::from_secs(2);
/// A handshake that has not finished after this long starts over (the broker may have
/// restarted and forgotten it). Three round trips of a satellite link fit many times.
pub const HANDSHAKE_GIVE_UP: Duration = Duration::from_secs(15);
/// Keepalive period towards the broker (an idle user costs the broker one small
/// datagram per period).
pub const KEEPALIVE: Duration = Duration::from_secs(5);
/// Keepalive period on each session (the system's lease is 5 s).
pub const SESSION_KEEPALIVE: Duration = Duration::from_secs(1);
/// The broker is taken as lost after this long without a datagram from it...
pub const BROKER_SILENCE: Duration = Duration::from_secs(12);
/// ...or after this long while something we asked for (a request, the list) is unanswered.
pub const BROKER_SILENCE_BUSY: Duration = Duration::from_secs(6);
/// A system is taken as dead after this long without a datagram on a session.
pub const SYSTEM_SILENCE: Duration = Duration::from_secs(5);

enum Hs {
    /// Sent an `INITIAL` without a token; waiting for the `RETRY`.
    Token { client: u64 },
    /// Sent the `INITIAL` with token and Noise message 1.
    Reply {
        client: u64,
        initial: Vec<u8>,
        hs: Box<HandshakeState>,
    },
    /// Handshake done on our side; the broker confirms with any channel datagram.
    Up {
        conn: u64,
        chan: Box<Channel>,
        fin: Vec<u8>,
        confirmed: bool,
        /// The broker's stateless reset token for this connection.
        reset_token: Option<[u8; RESET_TOKEN]>,
    },
}

struct Retry {
    next: Instant,
    rto: Duration,
}

impl Retry {
    fn new(now: Instant, rto: Duration) -> Self {
        Retry {
            next: now + rto,
            rto,
        }
    }
    fn due(&mut self, now: Instant) -> bool {
        if now < self.next {
            return false;
        }
        self.rto = (self.rto * 2).min(MAX_RTO);
        self.next = now + self.rto;
        true
    }
}

struct Session {
    system: String,
    addr: SocketAddr,
    cipher: SessionCipher,
    last_heard: Instant,
    next_keepalive: Instant,
    ending: Option<(Retry, u32)>,
}

/// What asks for the whole list.
fn whole_list() -> Up {
    Up::List {
        ask: 0,
        filter: ListFilter::default(),
        offset: 0,
        limit: u32::MAX,
    }
}

struct ListAssembly {
    generation: u64,
    epoch: u64,
    total: u16,
    matching: u32,
    chunks: BTreeMap<u16, Vec<ServiceView>>,
}

/// Counters of the remote link.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct LinkStats {
    /// Datagrams sent (before injected faults).
    pub datagrams_out: u64,
    /// Datagrams received (after injected faults).
    pub datagrams_in: u64,
    /// Retransmissions (hello, requests, ends, list, handshake).
    pub retransmissions: u64,
    /// Handshakes completed (1 + reconnections).
    pub handshakes: u64,
    /// Stateless resets taken (a broker that did not know the connection).
    pub resets: u64,
    /// Grants heard more than once (the same session again): not given to the core.
    pub duplicate_grants: u64,
    /// Dropped datagrams by reason.
    pub drops: DropCounters,
}

/// The user's side of the UDP path, sans IO: it never touches a socket or a clock.
/// Feed it datagrams with [`RemoteConn::handle`] and the time with
/// [`RemoteConn::handle_timeout`] (when [`RemoteConn::poll_timeout`] says), and send what
/// [`RemoteConn::poll_transmit`] gives. Randomness comes from a seed given to
/// [`RemoteConn::new`] (the driver draws it from the OS; tests fix it).
pub struct RemoteConn {
    opts: RemoteOptions,
    rng: StdRng,
    out: VecDeque<Transmit>,
    suffix: String,
    hs: Option<Hs>,
    hs_retry: Retry,
    hs_started: Instant,
    /// When the current handshake message was first sent, while it was not repeated:
    /// its answer is a round-trip sample (Karn's rule).
    hs_sent: Option<Instant>,
    welcomed: bool,
    last_from_broker: Instant,
    next_ping: Instant,
    hello: Option<(ToBroker, Retry)>,
    requests: BTreeMap<u64, (ToBroker, Retry)>,
    /// Operator actions waiting for their answer: sent again until it is whole, given
    /// up after [`OPERATE_PATIENCE`].
    operations: BTreeMap<u64, Operation>,
    sessions: HashMap<u64, Session>,
    list_want: Option<Retry>,
    /// What was asked for the list (sent again until it comes).
    list_ask: Up,
    list_part: Option<ListAssembly>,
    /// The list (or page) that came, with how many services the filter let through.
    list_done: Option<(u32, Box<ServiceListSnapshot>)>,
    generation: u64,
    stats: LinkStats,
    ever_connected: bool,
    /// Smoothed round trip and its variation (RFC 6298), from keepalive pongs.
    srtt: Option<Duration>,
    rttvar: Duration,
    born: Instant,
    /// Session datagrams that arrived before their grant (the system streams as soon as
    /// it grants; the grant comes through the broker): replayed when the grant arrives.
    early: Early,
    /// Sessions ended lately, oldest first.
    retired: HashSet<u64>,
    retired_order: VecDeque<u64>,
}

/// An operator action on its way.
struct Operation {
    msg: ToBroker,
    retry: Retry,
    sent: Instant,
    answer: OperatedAssembly,
}

/// How long an operator action waits for its answer before the user is told there is
/// none.
const OPERATE_PATIENCE: Duration = Duration::from_secs(20);

/// Most ended session ids remembered (a duplicate grant can lag by a few round trips).
const RETIRED_MAX: usize = 4096;

impl RemoteConn {
    /// A connection for `opts` (its `faults` are the driver's business) that starts its
    /// handshake at `now`.
    pub fn new(opts: RemoteOptions, now: Instant, seed: [u8; 32]) -> Self {
        let mut rng = StdRng::from_seed(seed);
        let suffix = format!("{:08x}", rng.random::<u32>());
        let mut conn = RemoteConn {
            opts,
            rng,
            out: VecDeque::new(),
            suffix,
            hs: None,
            hs_retry: Retry::new(now, RTO),
            hs_started: now,
            hs_sent: None,
            welcomed: false,
            last_from_broker: now,
            next_ping: now + KEEPALIVE,
            hello: None,
            requests: BTreeMap::new(),
            operations: BTreeMap::new(),
            sessions: HashMap::new(),
            list_want: None,
            list_ask: whole_list(),
            list_part: None,
            list_done: None,
            generation: 0,
            stats: LinkStats::default(),
            ever_connected: false,
            early: Early::default(),
            retired: HashSet::new(),
            retired_order: VecDeque::new(),
            srtt: None,
            rttvar: Duration::ZERO,
            born: now,
        };
        conn.start_handshake(now);
        conn
    }

    /// The next datagram to send.
    pub fn poll_transmit(&mut self) -> Option<Transmit> {
        self.out.pop_front()
    }

    /// The user id the broker will give this link (`name.suffix`).
    pub fn user_id(&self) -> UserId {
        UserId(format!("{}.{}", self.opts.name, self.suffix))
    }

    /// Counters.
    pub fn stats(&self) -> &LinkStats {
        &self.stats
    }

    /// Counters, for the driver's own drops (a failed send).
    pub fn stats_mut(&mut self) -> &mut LinkStats {
        &mut self.stats
    }

    /// Whether the broker welcomed us on the current connection.
    pub fn welcomed(&self) -> bool {
        self.welcomed
    }

    fn start_handshake(&mut self, now: Instant) {
        let client: u64 = self.rng.random();
        self.hs = Some(Hs::Token { client });
        self.hs_retry = Retry::new(now, self.rto());
        self.hs_started = now;
        self.hs_sent = Some(now);
        self.welcomed = false;
        self.send_initial(client, &[], &[]);
    }

    fn send_initial(&mut self, client: u64, token: &[u8], noise: &[u8]) -> Vec<u8> {
        let bytes = Datagram::Initial {
            client,
            token,
            noise,
        }
        .encode()
        .unwrap_or_default();
        let to = self.opts.broker;
        self.send_raw(&bytes, to);
        bytes
    }

    /// Sends a message the core wants at the broker.
    pub fn send_broker(&mut self, now: Instant, msg: ToBroker) {
        match &msg {
            ToBroker::Hello { .. } => self.hello = Some((msg.clone(), Retry::new(now, self.rto()))),
            ToBroker::Request { req, .. } => {
                let rto = self.rto();
                self.requests
                    .insert(*req, (msg.clone(), Retry::new(now, rto)));
            }
            ToBroker::Cancel { req, .. } => {
                self.requests.remove(req);
            }
            ToBroker::Operate { id, .. } => {
                let retry = Retry::new(now, self.rto());
                self.operations.insert(
                    *id,
                    Operation {
                        msg: msg.clone(),
                        retry,
                        sent: now,
                        answer: OperatedAssembly::default(),
                    },
                );
            }
            ToBroker::Goodbye { .. } => {
                // Unanswered: said twice against loss (the broker also times us out).
                self.send_up(&Up::Msg(msg.clone()));
            }
            _ => {}
        }
        self.send_up(&Up::Msg(msg));
    }

    /// Sends a message the core wants at a system (task input, end of a session).
    pub fn send_system(&mut self, now: Instant, msg: ToSystem) {
        let session = match &msg {
            ToSystem::Input { session, .. } | ToSystem::End { session, .. } => *session,
            _ => return,
        };
        if let ToSystem::End { .. } = &msg {
            let rto = self.rto();
            if let Some(s) = self.sessions.get_mut(&session.0) {
                s.ending = Some((Retry::new(now, rto), 0));
            }
        }
        self.send_session(session.0, &SessionUp::Msg(msg));
    }

    /// Asks the broker for the list; [`RemoteLink::take_list`] returns it once complete.
    pub fn ask_list(&mut self, now: Instant) {
        self.ask_list_page(now, &ListFilter::default(), 0, usize::MAX);
    }

    /// Asks for the services `filter` lets through, from the `offset`th, at most
    /// `limit` (sent again until every chunk of one generation came).
    pub fn ask_list_page(
        &mut self,
        now: Instant,
        filter: &ListFilter,
        offset: usize,
        limit: usize,
    ) {
        self.list_want = Some(Retry::new(now, self.rto()));
        self.list_part = None;
        self.list_done = None;
        let ask = match &self.list_ask {
            Up::List { ask, .. } => ask.wrapping_add(1),
            _ => 1,
        };
        self.list_ask = Up::List {
            ask,
            filter: filter.clone(),
            offset: u32::try_from(offset).unwrap_or(u32::MAX),
            limit: u32::try_from(limit).unwrap_or(u32::MAX),
        };
        self.send_up(&self.list_ask.clone());
    }

    /// The list (or the page asked for), once every chunk of one generation arrived,
    /// with how many services the filter let through.
    pub fn take_list(&mut self) -> Option<(u32, Box<ServiceListSnapshot>)> {
        self.list_done.take()
    }

    /// When [`RemoteConn::handle_timeout`] must run next.
    pub fn poll_timeout(&self) -> Instant {
        let mut t = self.next_ping;
        if !matches!(
            self.hs,
            Some(Hs::Up {
                confirmed: true,
                ..
            })
        ) {
            t = t.min(self.hs_retry.next);
        }
        if let Some((_, r)) = &self.hello {
            t = t.min(r.next);
        }
        for (_, r) in self.requests.values() {
            t = t.min(r.next);
        }
        for o in self.operations.values() {
            t = t.min(o.retry.next).min(o.sent + OPERATE_PATIENCE);
        }
        if let Some(r) = &self.list_want {
            t = t.min(r.next);
        }
        for s in self.sessions.values() {
            // An ending session sends no keepalives, only its repeated End.
            match &s.ending {
                Some((r, _)) => t = t.min(r.next),
                None => t = t.min(s.next_keepalive),
            }
        }
        t
    }

    /// Retransmits what is due, sends keepalives, notices silent peers.
    pub fn handle_timeout(&mut self, now: Instant, core: &mut UserCore) {
        // Handshake.
        match &self.hs {
            Some(Hs::Up {
                confirmed: true, ..
            }) => {}
            _ if self.hs_retry.due(now) => {
                self.stats.retransmissions += 1;
                self.hs_sent = None;
                match self.hs.take() {
                    Some(Hs::Token { client }) => {
                        self.hs = Some(Hs::Token { client });
                        self.send_initial(client, &[], &[]);
                    }
                    Some(Hs::Reply {
                        client,
                        initial,
                        hs,
                    }) => {
                        let to = self.opts.broker;
                        self.send_raw(&initial, to);
                        self.hs = Some(Hs::Reply {
                            client,
                            initial,
                            hs,
                        });
                    }
                    Some(Hs::Up {
                        conn,
                        chan,
                        fin,
                        confirmed,
                        reset_token,
                    }) => {
                        let to = self.opts.broker;
                        self.send_raw(&fin, to);
                        self.hs = Some(Hs::Up {
                            conn,
                            chan,
                            fin,
                            confirmed,
                            reset_token,
                        });
                    }
                    None => self.start_handshake(now),
                }
                // A handshake that gets nowhere starts over (the broker restarted).
                if now.duration_since(self.hs_started) > HANDSHAKE_GIVE_UP {
                    self.start_handshake(now);
                }
            }
            _ => {}
        }
        if let Some((msg, r)) = self.hello.as_mut() {
            if r.due(now) {
                let m = msg.clone();
                self.stats.retransmissions += 1;
                self.send_up(&Up::Msg(m));
            }
        }
        let due: Vec<u64> = self
            .requests
            .iter_mut()
            .filter_map(|(req, (_, r))| r.due(now).then_some(*req))
            .collect();
        for req in due {
            if !core.is_pending(req) {
                self.requests.remove(&req);
                continue;
            }
            if let Some((m, _)) = self.requests.get(&req) {
                let m = m.clone();
                self.stats.retransmissions += 1;
                self.send_up(&Up::Msg(m));
            }
        }
        let mut resend = Vec::new();
        let mut expired = Vec::new();
        for (id, o) in &mut self.operations {
            if now >= o.sent + OPERATE_PATIENCE {
                expired.push(*id);
            } else if o.retry.due(now) {
                resend.push(o.msg.clone());
            }
        }
        for m in resend {
            self.stats.retransmissions += 1;
            self.send_up(&Up::Msg(m));
        }
        for id in expired {
            self.operations.remove(&id);
            core.handle(ToUser::Operated {
                id,
                result: Err("no answer from the broker".into()),
            });
        }
        if self.list_want.as_mut().is_some_and(|r| r.due(now)) {
            // The chunks that came are kept: the answer to this ask again is the same
            // list while its generation holds, and fills in the chunks lost.
            self.stats.retransmissions += 1;
            self.send_up(&self.list_ask.clone());
        }
        // Keepalives and silence.
        if now >= self.next_ping {
            self.next_ping = now + KEEPALIVE;
            if self.welcomed {
                self.ping(now);
            }
        }
        let waiting = !self.requests.is_empty() || self.list_want.is_some();
        let silence = if waiting {
            BROKER_SILENCE_BUSY
        } else {
            BROKER_SILENCE
        };
        if self.welcomed && now.duration_since(self.last_from_broker) > silence {
            tracing::warn!("broker silent: lost; sessions go on, reconnecting");
            core.broker_lost();
            self.hello = None;
            self.start_handshake(now);
        }
        let mut keepalive = Vec::new();
        let mut ends = Vec::new();
        let mut dead_systems = Vec::new();
        let mut gone = Vec::new();
        for (id, s) in self.sessions.iter_mut() {
            if let Some((r, tries)) = s.ending.as_mut() {
                if *tries >= 10 {
                    gone.push(*id);
                } else if r.due(now) {
                    *tries += 1;
                    ends.push(*id);
                }
                continue;
            }
            if now >= s.next_keepalive {
                s.next_keepalive = now + SESSION_KEEPALIVE;
                keepalive.push(*id);
            }
            if now.duration_since(s.last_heard) > SYSTEM_SILENCE {
                dead_systems.push(s.system.clone());
            }
        }
        for id in gone {
            self.retire(id);
        }
        for id in keepalive {
            self.send_session(id, &SessionUp::Keepalive);
        }
        let me = self.user_id();
        for id in ends {
            self.stats.retransmissions += 1;
            let m = ToSystem::End {
                user: me.clone(),
                session: SessionId(id),
            };
            self.send_session(id, &SessionUp::Msg(m));
        }
        dead_systems.sort();
        dead_systems.dedup();
        for system in dead_systems {
            tracing::warn!(%system, "system silent: its sessions are over");
            let ids: Vec<u64> = self
                .sessions
                .iter()
                .filter(|(_, s)| s.system == system)
                .map(|(id, _)| *id)
                .collect();
            for id in ids {
                self.retire(id);
            }
            core.system_died(&system);
        }
    }

    /// One datagram from `from` at `now`: its messages go to `core`.
    pub fn handle(&mut self, now: Instant, from: SocketAddr, bytes: &[u8], core: &mut UserCore) {
        self.stats.datagrams_in += 1;
        let d = match Datagram::decode(bytes) {
            Ok(d) => d,
            Err(_) => return self.stats.drops.drop("malformed", &from),
        };
        match d {
            Datagram::Retry { client, token } => self.on_retry(now, client, token, from),
            Datagram::HsReply {
                client,
                conn,
                noise,
            } => self.on_reply(now, core, client, conn, noise, from),
            Datagram::Channel {
                conn,
                nonce,
                sealed,
            } => self.on_channel(now, core, conn, nonce, sealed, from),
            Datagram::Session {
                session,
                nonce,
                sealed,
            } => self.on_session(now, core, session, nonce, sealed, from),
            Datagram::Reset { conn, token } => self.on_reset(now, core, conn, token, from),
            _ => self.stats.drops.drop("unexpected_kind", &from),
        }
    }

    fn on_retry(&mut self, now: Instant, client: u64, token: &[u8], from: SocketAddr) {
        let ok = matches!(&self.hs, Some(Hs::Token { client: c }) if *c == client);
        if !ok || from != self.opts.broker {
            // A repeat (our INITIAL went out more than once) or a forgery: it changes
            // nothing.
            return self.stats.drops.count("stale_handshake");
        }
        self.hs_rtt_sample(now);
        let mut hs = match crypto::initiator(&self.opts.key) {
            Ok(h) => h,
            Err(e) => return tracing::error!("cannot start a handshake: {e}"),
        };
        let mut msg1 = [0u8; 256];
        let Ok(n) = hs.write_message(&[], &mut msg1) else {
            return;
        };
        let initial = self.send_initial(client, token, &msg1[..n]);
        self.hs = Some(Hs::Reply {
            client,
            initial,
            hs: Box::new(hs),
        });
        self.hs_retry = Retry::new(now, self.rto());
        self.hs_sent = Some(now);
    }

    /// The answer to a handshake message sent once is a round-trip sample.
    fn hs_rtt_sample(&mut self, now: Instant) {
        if let Some(sent) = self.hs_sent.take() {
            let rtt = now.saturating_duration_since(sent);
            if rtt < Duration::from_secs(10) {
                self.sample_rtt(rtt);
            }
        }
    }

    fn on_reply(
        &mut self,
        now: Instant,
        core: &mut UserCore,
        client: u64,
        conn: u64,
        noise: &[u8],
        from: SocketAddr,
    ) {
        // Only the reply we wait for, from the broker's address, may move the handshake:
        // a repeat (the broker answered our repeated INITIAL again) or a forgery leaves
        // the state, and above all a working channel, as it is.
        let waiting = matches!(&self.hs, Some(Hs::Reply { client: c, .. }) if *c == client);
        if !waiting || from != self.opts.broker {
            return self.stats.drops.count("stale_handshake");
        }
        let Some(Hs::Reply {
            client: c,
            initial,
            mut hs,
        }) = self.hs.take()
        else {
            return;
        };
        let restore = |hs, initial| Hs::Reply {
            client: c,
            initial,
            hs,
        };
        let mut scratch = [0u8; 512];
        let Ok(got) = hs.read_message(noise, &mut scratch) else {
            self.stats
                .drops
                .drop("bad_handshake", &self.opts.broker.clone());
            self.hs = Some(restore(hs, initial));
            return;
        };
        // Noise message 2 carries (encrypted, authenticated) the connection's stateless
        // reset token: a broker that later does not know the connection proves with it
        // that it holds the broker's key.
        let reset_token = <[u8; RESET_TOKEN]>::try_from(&scratch[..got]).ok();
        if let Some(pin) = self.opts.broker_key {
            if hs.get_remote_static() != Some(pin.as_slice()) {
                tracing::error!(
                    "the broker's key is not the one given with --broker-key: refusing it"
                );
                self.hs = None;
                return;
            }
        }
        let payload = to_bytes(&Hs3 {
            name: self.opts.name.clone(),
            suffix: self.suffix.clone(),
        })
        .unwrap_or_default();
        let mut msg3 = [0u8; 512];
        let Ok(n) = hs.write_message(&payload, &mut msg3) else {
            return;
        };
        let fin = Datagram::HsFinal {
            conn,
            noise: &msg3[..n],
        }
        .encode()
        .unwrap_or_default();
        let Ok(chan) = Channel::new(*hs) else { return };
        let to = self.opts.broker;
        self.send_raw(&fin, to);
        self.hs = Some(Hs::Up {
            conn,
            chan: Box::new(chan),
            fin,
            confirmed: false,
            reset_token,
        });
        self.hs_rtt_sample(now);
        self.hs_retry = Retry::new(now, self.rto());
        self.stats.handshakes += 1;
        // Say hello at once (repeated until the welcome): the first connection's hello
        // waits in `hello`; after a reconnection the core says it again.
        match self.hello.as_ref().map(|(m, _)| m.clone()) {
            Some(m) => self.send_up(&Up::Msg(m)),
            None => core.hello(),
        }
    }

    /// A broker that does not know our connection (a standby took over, or the broker
    /// restarted with its key): if the token is the one the handshake gave us, shake
    /// hands again now instead of waiting to notice the silence.
    fn on_reset(
        &mut self,
        now: Instant,
        core: &mut UserCore,
        conn: u64,
        token: [u8; RESET_TOKEN],
        from: SocketAddr,
    ) {
        let ours = matches!(
            &self.hs,
            Some(Hs::Up { conn: c, reset_token: Some(t), .. })
                if *c == conn && constant_time_eq(t, &token)
        );
        if !ours || from != self.opts.broker {
            return self.stats.drops.drop("stale_reset", &from);
        }
        tracing::warn!("the broker does not know this connection (a new broker): reconnecting");
        self.stats.resets += 1;
        core.broker_lost();
        self.hello = None;
        self.start_handshake(now);
    }

    fn on_channel(
        &mut self,
        now: Instant,
        core: &mut UserCore,
        conn: u64,
        nonce: u64,
        sealed: &[u8],
        from: SocketAddr,
    ) {
        let Some(Hs::Up {
            conn: c,
            chan,
            confirmed,
            ..
        }) = self.hs.as_mut()
        else {
            return self.stats.drops.drop("no_channel", &from);
        };
        if *c != conn {
            return self.stats.drops.drop("unknown_conn", &from);
        }
        let Ok(plain) = chan.open(nonce, sealed) else {
            return self.stats.drops.drop("forged_or_replayed", &from);
        };
        *confirmed = true;
        self.last_from_broker = now;
        let Ok(msg) = from_bytes::<Down>(&plain) else {
            return self.stats.drops.drop("bad_message", &from);
        };
        match msg {
            Down::Welcome { user, epoch } => {
                if user != self.user_id() {
                    tracing::warn!(%user, "broker named us differently");
                }
                if !self.welcomed {
                    self.welcomed = true;
                    self.ever_connected = true;
                    // Measure the round trip at once, for the retransmission timeout.
                    self.ping(now);
                    self.hello = None;
                    core.handle(ToUser::Welcome {
                        epoch,
                        broker_pid: 0,
                    });
                }
            }
            Down::Msg(m) => {
                if let ToUser::Queued { req, .. } = &m {
                    // Still waiting: keep asking, slowly.
                    if let Some((_, r)) = self.requests.get_mut(req) {
                        r.rto = MAX_RTO;
                        r.next = now + MAX_RTO;
                    }
                }
                if let ToUser::Refused { req, .. } = &m {
                    self.requests.remove(req);
                }
                if let ToUser::Operated { id, .. } = &m {
                    self.operations.remove(id);
                }
                core.handle(m);
            }
            Down::OperatedChunk {
                id,
                index,
                total,
                bytes,
            } => {
                // Pieces of an answer already taken (a repeat crossed it) are dropped.
                let Some(o) = self.operations.get_mut(&id) else {
                    return;
                };
                if let Some(result) = o.answer.add(index, total, bytes) {
                    self.operations.remove(&id);
                    core.handle(ToUser::Operated { id, result });
                }
            }
            Down::Event(json) => match serde_json::from_str::<EventRecord>(&json) {
                Ok(r) => core.feed(r),
                Err(_) => self.stats.drops.drop("bad_event", &from),
            },
            Down::Granted {
                req,
                session,
                service,
                kind,
                payload,
                system_addr,
                key,
            } => {
                self.requests.remove(&req);
                if self.sessions.contains_key(&session.0) || self.retired.contains(&session.0) {
                    self.stats.duplicate_grants += 1;
                    return;
                }
                let Ok(addr) = system_addr.parse::<SocketAddr>() else {
                    return self.stats.drops.drop("bad_system_addr", &from);
                };
                let system = service
                    .split()
                    .map(|(s, _)| s.to_string())
                    .unwrap_or_default();
                // A grant the core no longer waits for (cancelled) still gets a cipher:
                // the core ends it on sight, and the End must reach the system.
                self.sessions.insert(
                    session.0,
                    Session {
                        system,
                        addr,
                        cipher: SessionCipher::new(&key, Side::User),
                        last_heard: now,
                        next_keepalive: now,
                        ending: None,
                    },
                );
                core.handle(ToUser::Granted {
                    req,
                    session,
                    service,
                    kind,
                    payload,
                    // Open types' schemas do not travel over UDP yet: a remote user
                    // gets their samples as bytes.
                    schema: None,
                    system_pid: 0,
                    relayed: true,
                });
                for (b, f) in self.early.take(now, session.0) {
                    self.handle(now, f, &b, core);
                }
            }
            Down::ListChunk {
                epoch,
                generation,
                index,
                total,
                ask,
                matching,
                entries,
            } => {
                if matches!(self.list_ask, Up::List { ask: a, .. } if a == ask) {
                    self.on_chunk(epoch, generation, (index, total), matching, entries);
                }
            }
            Down::Pong { nonce, generation } => {
                let sent = self.born + Duration::from_nanos(nonce);
                if let Some(rtt) = now.checked_duration_since(sent) {
                    if rtt < Duration::from_secs(10) {
                        self.sample_rtt(rtt);
                    }
                }
                if generation != self.generation {
                    self.generation = generation;
                    core.list_changed();
                }
            }
            Down::ListChanged { generation } => {
                if generation != self.generation {
                    self.generation = generation;
                    core.list_changed();
                }
            }
            Down::PathChallenge { token } => self.send_up(&Up::PathResponse { token }),
        }
    }

    fn on_chunk(
        &mut self,
        epoch: u64,
        generation: u64,
        (index, total): (u16, u16),
        matching: u32,
        entries: Vec<ServiceView>,
    ) {
        if self.list_want.is_none() || total == 0 || index >= total {
            return;
        }
        let part = self.list_part.get_or_insert_with(|| ListAssembly {
            generation,
            epoch,
            total,
            matching,
            chunks: BTreeMap::new(),
        });
        if part.generation != generation
            || part.epoch != epoch
            || part.total != total
            || part.matching != matching
        {
            // A newer list began: start over with it.
            *part = ListAssembly {
                generation,
                epoch,
                total,
                matching,
                chunks: BTreeMap::new(),
            };
        }
        part.chunks.insert(index, entries);
        if part.chunks.len() == usize::from(part.total) {
            let entries = part.chunks.values().flatten().map(ServiceView::to_entry);
            let snap = Box::new(ServiceListSnapshot::from_entries(
                part.generation,
                part.epoch,
                entries.collect(),
            ));
            self.generation = part.generation;
            self.list_done = Some((part.matching, snap));
            self.list_want = None;
            self.list_part = None;
        }
    }

    fn on_session(
        &mut self,
        now: Instant,
        core: &mut UserCore,
        session: u64,
        nonce: u64,
        sealed: &[u8],
        from: SocketAddr,
    ) {
        let Some(s) = self.sessions.get_mut(&session) else {
            if self.retired.contains(&session) {
                return self.stats.drops.count("after_end");
            }
            let bytes = Datagram::Session {
                session,
                nonce,
                sealed,
            }
            .encode()
            .unwrap_or_default();
            return self.keep_early(now, bytes, from);
        };
        let Ok(plain) = s.cipher.open(session, nonce, sealed) else {
            return self.stats.drops.drop("forged_or_replayed", &from);
        };
        s.last_heard = now;
        let Ok(msg) = from_bytes::<SessionDown>(&plain) else {
            return self.stats.drops.drop("bad_message", &from);
        };
        match msg {
            SessionDown::Alive => {}
            SessionDown::PathChallenge { token } => {
                self.send_session(session, &SessionUp::PathResponse { token })
            }
            SessionDown::Msg(m) => {
                if let ToUser::Ended { .. } = &m {
                    self.retire(session);
                }
                core.handle(m);
            }
        }
    }

    /// Keeps a session datagram that came before its grant ([`Early::keep`]).
    fn keep_early(&mut self, now: Instant, bytes: Vec<u8>, from: SocketAddr) {
        if self.early.keep(now, bytes, from) {
            self.stats.drops.count("unknown_session");
        }
    }

    /// Forgets a session; its id stays retired, so a late duplicate grant of it never
    /// builds a second cipher under the same key (nonce reuse).
    fn retire(&mut self, id: u64) {
        if self.sessions.remove(&id).is_some() && self.retired.insert(id) {
            self.retired_order.push_back(id);
            while self.retired_order.len() > RETIRED_MAX {
                if let Some(old) = self.retired_order.pop_front() {
                    self.retired.remove(&old);
                }
            }
        }
    }

    fn send_up(&mut self, m: &Up) {
        let Some(Hs::Up { conn, chan, .. }) = self.hs.as_mut() else {
            return; // not connected: retries go out once the handshake is done
        };
        match seal_channel(chan, *conn, m) {
            Ok(dg) => {
                let to = self.opts.broker;
                self.send_raw(&dg, to);
            }
            Err(e) => tracing::warn!("not sent to the broker: {e}"),
        }
    }

    fn send_session(&mut self, session: u64, m: &SessionUp) {
        let Some(s) = self.sessions.get_mut(&session) else {
            return;
        };
        match seal_session(&mut s.cipher, session, m) {
            Ok(dg) => {
                let to = s.addr;
                self.send_raw(&dg, to);
            }
            Err(e) => tracing::warn!("task input not sent: {e}"),
        }
    }

    fn send_raw(&mut self, bytes: &[u8], to: SocketAddr) {
        self.stats.datagrams_out += 1;
        self.out.push_back(Transmit {
            to,
            bytes: bytes.to_vec(),
        });
    }

    /// The current retransmission timeout.
    pub fn rto(&self) -> Duration {
        match self.srtt {
            None => RTO,
            Some(s) => (s + 4 * self.rttvar).clamp(MIN_RTO, MAX_RTO),
        }
    }

    fn sample_rtt(&mut self, r: Duration) {
        match self.srtt {
            None => {
                self.srtt = Some(r);
                self.rttvar = r / 2;
            }
            Some(s) => {
                let diff = s.abs_diff(r);
                self.rttvar = (self.rttvar * 3 + diff) / 4;
                self.srtt = Some((s * 7 + r) / 8);
            }
        }
    }

    /// A keepalive stamped with its send time, so its pong is a round-trip sample.
    fn ping(&mut self, now: Instant) {
        let nonce = now.saturating_duration_since(self.born).as_nanos() as u64;
        self.send_up(&Up::Ping { nonce });
    }

    /// Sessions held (with a cipher), ending ones included.
    pub fn sessions(&self) -> usize {
        self.sessions.len()
    }

    /// Sessions whose `End` is not yet confirmed.
    pub fn ending(&self) -> usize {
        self.sessions
            .values()
            .filter(|s| s.ending.is_some())
            .count()
    }

    /// Whether the connection ever got a welcome (for the first connect's error).
    pub fn ever_connected(&self) -> bool {
        self.ever_connected
    }
}

/// Compares two tokens in time independent of where they differ.
fn constant_time_eq(a: &[u8; RESET_TOKEN], b: &[u8; RESET_TOKEN]) -> bool {
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}
