//! The user's UDP link: a socket driving the sans-IO [`RemoteConn`], with an optional
//! fault injector (seeded loss, duplication, reordering) around the transport.

use crate::conn::RemoteConn;
use crate::core::UserCore;
use muster_shared::protocol::{ToBroker, ToSystem};
use muster_shared::snapshot::{ListFilter, ServiceListSnapshot};
use muster_shared::types::UserId;
use muster_shared::udp::crypto::KeyPair;
use muster_shared::udp::wire::MAX_DATAGRAM;
use muster_shared::udp::{recv_one, send_transmit, size_recv_buffer, Transmit, RECV_BATCH};
use rand::{RngExt, SeedableRng};
use std::net::{SocketAddr, UdpSocket};
use std::os::fd::{AsRawFd, RawFd};
use std::time::{Duration, Instant};

pub use crate::conn::{
    LinkStats, BROKER_SILENCE, BROKER_SILENCE_BUSY, KEEPALIVE, MAX_RTO, MIN_RTO, RTO,
    SESSION_KEEPALIVE, SYSTEM_SILENCE,
};

/// Seeded delay, loss, duplication and reordering applied to this client's datagrams in
/// both directions (a wrapper around its socket, outside the protocol logic): the
/// slow-network tests and `bench remote` use it, since this kernel has no netem.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Faults {
    /// Round trip added: half on the way out, half on the way in.
    pub rtt: Duration,
    /// Probability a datagram is dropped.
    pub loss: f64,
    /// Probability a datagram is delivered twice.
    pub dup: f64,
    /// Probability a datagram is held back a little longer than the others (reordered).
    pub reorder: f64,
    /// Seed.
    pub seed: u64,
}

impl std::str::FromStr for Faults {
    type Err = String;
    /// `rtt=300ms,loss=0.05,dup=0.01,reorder=0.02,seed=7`
    fn from_str(s: &str) -> Result<Self, String> {
        let mut f = Faults::default();
        for kv in s.split(',').filter(|x| !x.is_empty()) {
            let (k, v) = kv
                .split_once('=')
                .ok_or(format!("expected key=value, got {kv:?}"))?;
            let p = || -> Result<f64, String> {
                let x: f64 = v.parse().map_err(|e| format!("{k}: {e}"))?;
                if (0.0..=1.0).contains(&x) {
                    Ok(x)
                } else {
                    Err(format!("{k} must be in [0, 1]"))
                }
            };
            match k {
                "rtt" => f.rtt = parse_duration(v).map_err(|e| format!("rtt: {e}"))?,
                "loss" => f.loss = p()?,
                "dup" => f.dup = p()?,
                "reorder" => f.reorder = p()?,
                "seed" => f.seed = v.parse().map_err(|e| format!("seed: {e}"))?,
                _ => {
                    return Err(format!(
                        "unknown fault {k:?} (rtt, loss, dup, reorder, seed)"
                    ))
                }
            }
        }
        Ok(f)
    }
}

/// `250ms`, `1s`, `1.5s`: at most a minute.
fn parse_duration(v: &str) -> Result<Duration, String> {
    let (num, unit) = match v.strip_suffix("ms") {
        Some(n) => (n, 1e-3),
        None => (v.strip_suffix('s').ok_or("expected e.g. 300ms or 1s")?, 1.0),
    };
    let x: f64 = num.parse().map_err(|e| format!("{e}"))?;
    if !(0.0..=60.0).contains(&(x * unit)) {
        return Err("must be between 0 and 60 s".into());
    }
    Ok(Duration::from_secs_f64(x * unit))
}

/// The fault injector: datagrams wait in time-ordered queues until their (delayed)
/// delivery, lost ones never enter, duplicated ones enter twice.
struct Lossy {
    f: Faults,
    rng: rand_pcg::Pcg64,
    seq: u64,
    inq: std::collections::BTreeMap<(Instant, u64), (Vec<u8>, SocketAddr)>,
    outq: std::collections::BTreeMap<(Instant, u64), Transmit>,
}

impl Lossy {
    fn new(f: Faults) -> Self {
        Lossy {
            f,
            rng: rand_pcg::Pcg64::seed_from_u64(f.seed),
            seq: 0,
            inq: Default::default(),
            outq: Default::default(),
        }
    }

    /// When each copy of one datagram sent at `now` arrives (none if it is lost).
    fn fate(&mut self, now: Instant) -> Vec<(Instant, u64)> {
        if self.rng.random::<f64>() < self.f.loss {
            return Vec::new();
        }
        let copies = if self.rng.random::<f64>() < self.f.dup {
            2
        } else {
            1
        };
        (0..copies)
            .map(|_| {
                let mut at = now + self.f.rtt / 2;
                if self.rng.random::<f64>() < self.f.reorder {
                    at += Duration::from_millis(1)
                        + (Duration::from_millis(5) + self.f.rtt / 4)
                            .mul_f64(self.rng.random::<f64>());
                }
                self.seq += 1;
                (at, self.seq)
            })
            .collect()
    }

    /// When the next held datagram is due.
    fn next(&self) -> Option<Instant> {
        let a = self.inq.keys().next().map(|k| k.0);
        let b = self.outq.keys().next().map(|k| k.0);
        a.into_iter().chain(b).min()
    }
}

/// How to reach the broker over UDP.
#[derive(Clone, Debug)]
pub struct RemoteOptions {
    /// The broker's UDP address.
    pub broker: SocketAddr,
    /// The user's name in the broker's access file.
    pub name: String,
    /// The user's key.
    pub key: KeyPair,
    /// Refuse a broker whose static key is not this one.
    pub broker_key: Option<[u8; 32]>,
    /// Injected faults (tests and benchmarks).
    pub faults: Option<Faults>,
}

/// The user's UDP link to the broker and to systems: the socket and the clock around a
/// [`RemoteConn`].
pub struct RemoteLink {
    sock: UdpSocket,
    conn: RemoteConn,
    lossy: Option<Lossy>,
}

impl RemoteLink {
    /// A link for `opts`; binds an ephemeral UDP port on the broker's address family and
    /// starts the handshake.
    pub fn new(opts: RemoteOptions) -> std::io::Result<Self> {
        let bind: SocketAddr = if opts.broker.is_ipv4() {
            "0.0.0.0:0".parse().expect("literal")
        } else {
            "[::]:0".parse().expect("literal")
        };
        let sock = UdpSocket::bind(bind)?;
        sock.set_nonblocking(true)?;
        if let Err(e) = size_recv_buffer(&sock) {
            tracing::debug!("cannot size the receive buffer: {e}");
        }
        let lossy = opts.faults.map(Lossy::new);
        let seed: [u8; 32] = rand::rng().random();
        let conn = RemoteConn::new(opts, Instant::now(), seed);
        let mut link = RemoteLink { sock, conn, lossy };
        link.transmit();
        Ok(link)
    }

    /// The user id the broker will give this link (`name.suffix`).
    pub fn user_id(&self) -> UserId {
        self.conn.user_id()
    }

    /// The socket, for the reactor.
    pub fn fd(&self) -> RawFd {
        self.sock.as_raw_fd()
    }

    /// Counters.
    pub fn stats(&self) -> &LinkStats {
        self.conn.stats()
    }

    /// Whether the broker welcomed us on the current connection.
    pub fn welcomed(&self) -> bool {
        self.conn.welcomed()
    }

    /// Whether the connection ever got a welcome (for the first connect's error).
    pub fn ever_connected(&self) -> bool {
        self.conn.ever_connected()
    }

    /// Sessions whose `End` is not yet confirmed.
    pub fn ending(&self) -> usize {
        self.conn.ending()
    }

    /// The current retransmission timeout.
    pub fn rto(&self) -> Duration {
        self.conn.rto()
    }

    /// Sends a message the core wants at the broker.
    pub fn send_broker(&mut self, msg: ToBroker) {
        self.conn.send_broker(Instant::now(), msg);
        self.transmit();
    }

    /// Sends a message the core wants at a system (task input, end of a session).
    pub fn send_system(&mut self, msg: ToSystem) {
        self.conn.send_system(Instant::now(), msg);
        self.transmit();
    }

    /// Asks the broker for the services `filter` lets through, from the `offset`th, at
    /// most `limit`; [`RemoteLink::take_list`] returns them once complete.
    pub fn ask_list(&mut self, filter: &ListFilter, offset: usize, limit: usize) {
        self.conn
            .ask_list_page(Instant::now(), filter, offset, limit);
        self.transmit();
    }

    /// The list (or page) asked for, once every chunk of one generation arrived, with
    /// how many services the filter let through.
    pub fn take_list(&mut self) -> Option<(u32, Box<ServiceListSnapshot>)> {
        self.conn.take_list()
    }

    /// When [`RemoteLink::tick`] must run next.
    pub fn next_deadline(&self) -> Instant {
        let t = self.conn.poll_timeout();
        match self.lossy.as_ref().and_then(Lossy::next) {
            Some(held) => t.min(held),
            None => t,
        }
    }

    /// Retransmits what is due, sends keepalives, notices silent peers.
    pub fn tick(&mut self, core: &mut UserCore) {
        let now = Instant::now();
        self.deliver_held(now, core);
        self.conn.handle_timeout(now, core);
        self.transmit();
    }

    /// Reads waiting datagrams and hands their messages to the core. What the
    /// connection owes in return (acknowledgements, a new session's first keepalive)
    /// goes out with the next [`RemoteLink::tick`] or send: the caller hands the core's
    /// news to the application first, since a datagram to the broker or a system wakes
    /// a process that runs before this one.
    pub fn on_readable(&mut self, core: &mut UserCore) {
        let mut buf = [0u8; MAX_DATAGRAM + 1];
        for _ in 0..RECV_BATCH {
            let Some((n, from)) = recv_one(&self.sock, &mut buf) else {
                break;
            };
            let now = Instant::now();
            let bytes = &buf[..n];
            match self.lossy.as_mut() {
                None => self.conn.handle(now, from, bytes, core),
                Some(l) => {
                    for k in l.fate(now) {
                        l.inq.insert(k, (bytes.to_vec(), from));
                    }
                }
            }
        }
        self.deliver_held(Instant::now(), core);
    }

    /// Hands the connection the delayed datagrams that are due, and sends the due ones.
    fn deliver_held(&mut self, now: Instant, core: &mut UserCore) {
        let Some(l) = self.lossy.as_mut() else { return };
        let later_in = l.inq.split_off(&(now, u64::MAX));
        let due_in = std::mem::replace(&mut l.inq, later_in);
        let later_out = l.outq.split_off(&(now, u64::MAX));
        let due_out = std::mem::replace(&mut l.outq, later_out);
        for t in due_out.into_values() {
            send_transmit(&self.sock, &t, &mut self.conn.stats_mut().drops);
        }
        for ((at, _), (b, f)) in due_in {
            self.conn.handle(at.max(now), f, &b, core);
        }
    }

    /// Sends what the connection has queued, through the fault injector if any.
    fn transmit(&mut self) {
        let now = Instant::now();
        while let Some(t) = self.conn.poll_transmit() {
            match self.lossy.as_mut() {
                None => send_transmit(&self.sock, &t, &mut self.conn.stats_mut().drops),
                Some(l) => {
                    for k in l.fate(now) {
                        l.outq.insert(k, t.clone());
                    }
                }
            }
        }
        // Undelayed datagrams leave at once.
        if let Some(l) = self.lossy.as_mut() {
            let later = l.outq.split_off(&(now, u64::MAX));
            for t in std::mem::replace(&mut l.outq, later).into_values() {
                send_transmit(&self.sock, &t, &mut self.conn.stats_mut().drops);
            }
        }
    }

    /// Sends every held-back datagram at once (used when closing).
    pub fn flush_held(&mut self) {
        if let Some(l) = self.lossy.as_mut() {
            for t in std::mem::take(&mut l.outq).into_values() {
                send_transmit(&self.sock, &t, &mut self.conn.stats_mut().drops);
            }
        }
    }
}
