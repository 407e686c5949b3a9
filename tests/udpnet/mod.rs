//! A seeded, simulated UDP network on a virtual clock: per-endpoint delay, jitter, loss,
//! duplication and reordering, a tap of everything sent (for an attacker to replay),
//! and injection of forged datagrams. The in-memory harness carries remote users, the
//! broker's UDP front and systems' session endpoints over it.

use rand::{RngExt, SeedableRng};
use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};
use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

/// The conditions on the path to and from one endpoint (both directions).
#[derive(Clone, Copy, Debug, Default)]
pub struct PathFaults {
    /// Round trip this endpoint adds (half each way).
    pub rtt: Duration,
    /// Extra delay, uniform in [0, jitter), each way.
    pub jitter: Duration,
    /// Probability a datagram is lost.
    pub loss: f64,
    /// Probability a datagram arrives twice.
    pub dup: f64,
    /// Probability a datagram is held back by up to half the round trip more.
    pub reorder: f64,
}

/// A datagram in flight.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct InFlight {
    /// When it arrives.
    pub at: Duration,
    seq: u64,
    /// Sender.
    pub from: SocketAddr,
    /// Receiver.
    pub to: SocketAddr,
    /// Bytes.
    pub bytes: Vec<u8>,
}

/// The network.
pub struct Network {
    rng: rand_pcg::Pcg64,
    queue: BinaryHeap<Reverse<InFlight>>,
    seq: u64,
    faults: HashMap<IpAddr, PathFaults>,
    /// Every datagram sent by an endpoint (not injected ones), when tapping.
    pub tap: Vec<InFlight>,
    /// Whether to record [`Network::tap`].
    pub tapping: bool,
    /// Datagrams sent, lost to faults.
    pub sent: u64,
    /// Datagrams lost to faults.
    pub lost: u64,
    /// Everything `from` sends is lost until the given time (a cut in one direction).
    pub blackhole: Option<(SocketAddr, Duration)>,
}

impl Network {
    /// An empty network with fault decisions drawn from `seed`.
    pub fn new(seed: u64) -> Self {
        Network {
            rng: rand_pcg::Pcg64::seed_from_u64(seed),
            queue: BinaryHeap::new(),
            seq: 0,
            faults: HashMap::new(),
            tap: Vec::new(),
            tapping: false,
            sent: 0,
            lost: 0,
            blackhole: None,
        }
    }

    /// Sets the path conditions of the endpoint at `ip` (both directions).
    pub fn set_faults(&mut self, ip: IpAddr, f: PathFaults) {
        self.faults.insert(ip, f);
    }

    fn path(&self, a: &SocketAddr, b: &SocketAddr) -> PathFaults {
        let fa = self.faults.get(&a.ip()).copied().unwrap_or_default();
        let fb = self.faults.get(&b.ip()).copied().unwrap_or_default();
        PathFaults {
            rtt: fa.rtt + fb.rtt,
            jitter: fa.jitter + fb.jitter,
            loss: 1.0 - (1.0 - fa.loss) * (1.0 - fb.loss),
            dup: fa.dup.max(fb.dup),
            reorder: fa.reorder.max(fb.reorder),
        }
    }

    /// An endpoint sends `bytes` at `now`: the path's faults apply.
    pub fn send(&mut self, now: Duration, from: SocketAddr, to: SocketAddr, bytes: Vec<u8>) {
        self.sent += 1;
        let p = self.path(&from, &to);
        if self.tapping {
            self.tap.push(InFlight {
                at: now,
                seq: 0,
                from,
                to,
                bytes: bytes.clone(),
            });
        }
        let cut = self
            .blackhole
            .is_some_and(|(who, until)| who == from && now < until);
        if cut || self.rng.random::<f64>() < p.loss {
            self.lost += 1;
            return;
        }
        let copies = if self.rng.random::<f64>() < p.dup {
            2
        } else {
            1
        };
        for _ in 0..copies {
            let mut delay = p.rtt / 2;
            if !p.jitter.is_zero() {
                delay += p.jitter.mul_f64(self.rng.random::<f64>());
            }
            if self.rng.random::<f64>() < p.reorder {
                delay += (p.rtt / 2).mul_f64(self.rng.random::<f64>()) + Duration::from_millis(1);
            }
            self.push(now + delay, from, to, bytes.clone());
        }
    }

    /// A datagram that arrives at `at` as it is, whoever claims to send it (an attacker
    /// forging a source address, or replaying a tapped datagram).
    pub fn inject(&mut self, at: Duration, from: SocketAddr, to: SocketAddr, bytes: Vec<u8>) {
        self.push(at, from, to, bytes);
    }

    fn push(&mut self, at: Duration, from: SocketAddr, to: SocketAddr, bytes: Vec<u8>) {
        self.seq += 1;
        self.queue.push(Reverse(InFlight {
            at,
            seq: self.seq,
            from,
            to,
            bytes,
        }));
    }

    /// When the next datagram arrives.
    pub fn next_at(&self) -> Option<Duration> {
        self.queue.peek().map(|Reverse(d)| d.at)
    }

    /// The next datagram due by `now`.
    pub fn pop_due(&mut self, now: Duration) -> Option<InFlight> {
        if self.next_at()? > now {
            return None;
        }
        self.queue.pop().map(|Reverse(d)| d)
    }
}
