//! The user's UDP link: a socket driving the sans-IO [`RemoteConn`], with an optional
//! fault injector (seeded loss, duplication, reordering) around the transport.

use crate::conn::RemoteConn;
use crate::core::UserCore;
use muster_shared::protocol::{ToBroker, ToSystem};
use muster_shared::snapshot::ServiceListSnapshot;
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

/// Seeded loss, duplication and reordering applied to this client's datagrams in both
/// directions: the network-fault test and benchmark use it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Faults {
    /// Probability a datagram is dropped.
    pub loss: f64,
    /// Probability a datagram is delivered twice.
    pub dup: f64,
    /// Probability a datagram is held back and delivered after the next one.
    pub reorder: f64,
    /// Seed.
    pub seed: u64,
}

impl std::str::FromStr for Faults {
    type Err = String;
    /// `loss=0.05,dup=0.01,reorder=0.02,seed=7`
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
                "loss" => f.loss = p()?,
                "dup" => f.dup = p()?,
                "reorder" => f.reorder = p()?,
                "seed" => f.seed = v.parse().map_err(|e| format!("seed: {e}"))?,
                _ => return Err(format!("unknown fault {k:?} (loss, dup, reorder, seed)")),
            }
        }
        Ok(f)
    }
}

/// The fault injector: a wrapper around the transport, outside the protocol logic.
struct Lossy {
    f: Faults,
    rng: rand_pcg::Pcg64,
    held_out: Option<Transmit>,
    held_in: Option<(Vec<u8>, SocketAddr)>,
}

impl Lossy {
    /// What to do with one datagram: 0, 1 or 2 copies, and whether to hold it back.
    fn fate(&mut self) -> (usize, bool) {
        if self.rng.random::<f64>() < self.f.loss {
            return (0, false);
        }
        let copies = if self.rng.random::<f64>() < self.f.dup {
            2
        } else {
            1
        };
        (copies, self.rng.random::<f64>() < self.f.reorder)
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
        let lossy = opts.faults.map(|f| Lossy {
            f,
            rng: rand_pcg::Pcg64::seed_from_u64(f.seed),
            held_out: None,
            held_in: None,
        });
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

    /// Asks the broker for the list; [`RemoteLink::take_list`] returns it once complete.
    pub fn ask_list(&mut self) {
        self.conn.ask_list(Instant::now());
        self.transmit();
    }

    /// The list, once every chunk of one generation arrived.
    pub fn take_list(&mut self) -> Option<Box<ServiceListSnapshot>> {
        self.conn.take_list()
    }

    /// When [`RemoteLink::tick`] must run next.
    pub fn next_deadline(&self) -> Instant {
        let t = self.conn.poll_timeout();
        if self
            .lossy
            .as_ref()
            .is_some_and(|l| l.held_in.is_some() || l.held_out.is_some())
        {
            return t.min(Instant::now() + Duration::from_millis(5));
        }
        t
    }

    /// Retransmits what is due, sends keepalives, notices silent peers.
    pub fn tick(&mut self, core: &mut UserCore) {
        let now = Instant::now();
        if let Some(l) = self.lossy.as_mut() {
            let (inn, out) = (l.held_in.take(), l.held_out.take());
            if let Some((b, f)) = inn {
                self.conn.handle(now, f, &b, core);
            }
            if let Some(t) = out {
                send_transmit(&self.sock, &t, &mut self.conn.stats_mut().drops);
            }
        }
        self.conn.handle_timeout(now, core);
        self.transmit();
    }

    /// Reads waiting datagrams and hands their messages to the core.
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
                    let (copies, hold) = l.fate();
                    if copies == 0 {
                        continue;
                    }
                    if hold && l.held_in.is_none() {
                        l.held_in = Some((bytes.to_vec(), from));
                        if copies == 2 {
                            self.conn.handle(now, from, bytes, core);
                        }
                        continue;
                    }
                    let held = l.held_in.take();
                    for _ in 0..copies {
                        self.conn.handle(now, from, bytes, core);
                    }
                    if let Some((b, f)) = held {
                        self.conn.handle(now, f, &b, core);
                    }
                }
            }
        }
        self.transmit();
    }

    /// Sends what the connection has queued, through the fault injector if any.
    fn transmit(&mut self) {
        while let Some(t) = self.conn.poll_transmit() {
            let Some(l) = self.lossy.as_mut() else {
                send_transmit(&self.sock, &t, &mut self.conn.stats_mut().drops);
                continue;
            };
            let (copies, hold) = l.fate();
            if copies == 0 {
                continue;
            }
            let drops = &mut self.conn.stats_mut().drops;
            if hold && l.held_out.is_none() {
                if copies == 2 {
                    send_transmit(&self.sock, &t, drops);
                }
                l.held_out = Some(t);
                continue;
            }
            let held = l.held_out.take();
            for _ in 0..copies {
                send_transmit(&self.sock, &t, drops);
            }
            if let Some(h) = held {
                send_transmit(&self.sock, &h, drops);
            }
        }
    }

    /// Sends a held-back datagram at once (used when closing).
    pub fn flush_held(&mut self) {
        if let Some(t) = self.lossy.as_mut().and_then(|l| l.held_out.take()) {
            send_transmit(&self.sock, &t, &mut self.conn.stats_mut().drops);
        }
    }
}
