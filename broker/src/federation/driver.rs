//! The federation's driver: [`FedCore`] on Zenoh and shared memory.
//!
//! Zenoh's threads hand what comes (tokens, lists, frames) to the broker's loop through
//! a channel and a wake-up socket, within a byte budget; the loop feeds it to the core
//! and carries out the core's outputs (puts, queries, tokens) and inboxes (shared-memory
//! endpoints the broker owns for peers on other hosts). Nothing here decides anything.

use super::core::{FedCore, FedInput, FedOutput, Inboxes, LIST_QUERY_TIMEOUT};
use super::{
    split_batch, Batch, Delivery, FedConfig, FedError, FedMsg, FedStats, Role, MAX_FED_BATCH,
    MAX_FED_FRAME,
};
use crate::core::{Broker, Output};
use muster_shared::ipc::{create_node, open_envelope, Endpoint};
use muster_shared::names::{Address, Instance};
use muster_shared::protocol::{encode, monotonic_ns, RemoteContact, ToBroker, ToSystem, ToUser};
use muster_shared::reactor::Reactor;
use muster_shared::snapshot::ServiceView;
use muster_shared::types::{SessionId, UserId};
use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::io::{Read, Write};
use std::os::fd::AsRawFd;
use std::os::unix::net::UnixStream;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;

/// What a batch to a host holds: frames on its users' key or on its systems' (access
/// control is by key), and updates only, which Zenoh may drop when the way is congested,
/// or frames that must arrive, which wait for room.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct BatchKind {
    users_key: bool,
    droppable: bool,
}

/// Puts a batch of frames from `me` on host `to`'s key for its kind.
fn put_batch(puts: &Putter, prefix: &str, me: &str, to: &str, kind: BatchKind, bytes: Vec<u8>) {
    let part = if kind.users_key { "req" } else { "in" };
    puts.put(Put {
        key: format!("{prefix}{to}/{part}/{me}"),
        body: bytes,
        droppable: kind.droppable,
        attachment: None,
    });
}

/// One Zenoh put, made on the [`Putter`]'s thread.
struct Put {
    key: String,
    body: Vec<u8>,
    /// Updates only: Zenoh may drop it when the way is congested, and so may the
    /// putter when its queue is full. Otherwise it waits for room (and so, when
    /// [`PUT_QUEUE`] puts already wait, does the loop).
    droppable: bool,
    /// A list's version.
    attachment: Option<Vec<u8>>,
}

/// Puts waiting for the putter's thread before the loop waits too (or, for updates,
/// drops them).
const PUT_QUEUE: usize = 1024;
/// How long a stopping broker waits for its last puts to go out.
const PUT_DRAIN: Duration = Duration::from_secs(2);

/// Zenoh puts made in order on a thread of their own: a put that waits for room
/// (congestion control `Block`, when a peer's link is full) holds that thread, not the
/// broker's loop. Under a start of 100 hosts one broker's loop was seen blocked 10 s in
/// such a put.
struct Putter {
    tx: Option<mpsc::SyncSender<Put>>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// Droppable puts dropped because the queue was full.
    dropped: AtomicU64,
}

impl Putter {
    fn new(session: zenoh::Session) -> Result<Self, FedError> {
        let (tx, rx) = mpsc::sync_channel::<Put>(PUT_QUEUE);
        let thread = std::thread::Builder::new()
            .name("fed-put".into())
            .spawn(move || {
                for p in rx {
                    let congestion = if p.droppable {
                        zenoh::qos::CongestionControl::Drop
                    } else {
                        zenoh::qos::CongestionControl::Block
                    };
                    let mut put = session.put(&p.key, p.body).congestion_control(congestion);
                    if let Some(a) = p.attachment {
                        put = put.attachment(a);
                    }
                    if let Err(e) = put.wait() {
                        tracing::warn!("federation: cannot put {}: {e}", p.key);
                    }
                }
            })
            .map_err(|e| FedError::Open(format!("starting the put thread: {e}")))?;
        Ok(Putter {
            tx: Some(tx),
            thread: Some(thread),
            dropped: AtomicU64::new(0),
        })
    }

    fn put(&self, p: Put) {
        let Some(tx) = &self.tx else { return };
        let sent = if p.droppable {
            match tx.try_send(p) {
                Err(mpsc::TrySendError::Full(_)) => {
                    self.dropped.fetch_add(1, Ordering::Relaxed);
                    return;
                }
                r => r.map_err(|_| ()),
            }
        } else {
            tx.send(p).map_err(|_| ())
        };
        if sent.is_err() {
            tracing::warn!("federation: the put thread is gone");
        }
    }
}

impl Drop for Putter {
    /// Lets the queued puts go out, for up to [`PUT_DRAIN`].
    fn drop(&mut self) {
        drop(self.tx.take());
        let Some(t) = self.thread.take() else { return };
        let deadline = Instant::now() + PUT_DRAIN;
        while !t.is_finished() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(5));
        }
        if t.is_finished() {
            let _ = t.join();
        } else {
            tracing::warn!("federation: puts still waiting after {PUT_DRAIN:?}: left");
        }
    }
}

/// The first reactor token of proxy inboxes; the shell's own tokens stay below it.
pub const FIRST_PROXY_TOKEN: usize = 1 << 32;
/// How long a proxy whose peer is gone keeps its ports: frames just sent through them
/// (an end, a revocation) must be read before the ports close.
const PROXY_LINGER: Duration = Duration::from_secs(2);
/// How long a starting broker looks for another broker already using its host name.
const HOST_CHECK: Duration = Duration::from_millis(400);
/// Largest list taken from another host: its JSON, about 300 bytes a service, so some
/// 28,000 services.
const MAX_FED_LIST: usize = 8 << 20;
/// Most bytes of frames and lists waiting for the broker's loop; beyond it, what comes
/// is dropped (and counted) rather than held: a flooding peer costs bounded memory.
const MAX_QUEUED_BYTES: usize = 32 << 20;

/// The broker's clock (the core's `now`).
fn now() -> Duration {
    Duration::from_nanos(monotonic_ns())
}

/// A list's version, sent as the Zenoh attachment of its publication and of the
/// queryable's reply: Unix ns of the change, kept rising. A peer takes a list only if
/// it is newer than the one it has, so a late reply to an old query does not undo a
/// newer publication. (A list without one, version 0, is always taken.)
fn list_version(sample: &zenoh::sample::Sample) -> u64 {
    sample
        .attachment()
        .and_then(|a| <[u8; 8]>::try_from(a.to_bytes().as_ref()).ok())
        .map_or(0, u64::from_le_bytes)
}

fn input_bytes(ev: &FedInput) -> usize {
    match ev {
        FedInput::Alive(..) | FedInput::Standby(..) | FedInput::ListQueryEnded { .. } => 0,
        FedInput::List { body, .. } => body.len(),
        FedInput::Frame { bytes, .. } => bytes.len(),
    }
}

/// Held by a list query's callback: when Zenoh drops it (the query ended), the core
/// hears whether a list came ([`FedInput::ListQueryEnded`]).
struct QueryEnded {
    notify: Arc<Inflow>,
    host: String,
    answered: AtomicBool,
}

impl Drop for QueryEnded {
    fn drop(&mut self) {
        self.notify.push(FedInput::ListQueryEnded {
            host: std::mem::take(&mut self.host),
            answered: self.answered.load(Ordering::Relaxed),
        });
    }
}

/// What Zenoh's threads hand the broker's loop: inputs on a channel, a wake-up on a
/// socket, within a byte budget.
struct Inflow {
    tx: Mutex<mpsc::Sender<FedInput>>,
    ring: Arc<UnixStream>,
    /// Bytes on the channel.
    queued: AtomicUsize,
    /// Frames and lists dropped at the door (too big, or over the budget) since the
    /// loop last looked.
    refused: AtomicU64,
}

impl Inflow {
    fn push(&self, ev: FedInput) {
        self.push_all(vec![ev]);
    }

    /// Hands inputs over together, with one wake-up, if they fit the byte budget (all
    /// of them are counted as refused otherwise).
    fn push_all(&self, evs: Vec<FedInput>) {
        if evs.is_empty() {
            return;
        }
        let n: usize = evs.iter().map(input_bytes).sum();
        if self.queued.fetch_add(n, Ordering::Relaxed) + n > MAX_QUEUED_BYTES {
            self.queued.fetch_sub(n, Ordering::Relaxed);
            self.refused.fetch_add(evs.len() as u64, Ordering::Relaxed);
            return;
        }
        let (mut unsent, mut sent) = (n, 0);
        if let Ok(tx) = self.tx.lock() {
            for ev in evs {
                let size = input_bytes(&ev);
                if tx.send(ev).is_err() {
                    break;
                }
                unsent -= size;
                sent += 1;
            }
        }
        if sent > 0 {
            // Full pipe: a wake-up is pending already.
            let _ = (&*self.ring).write(&[1]);
        }
        self.queued.fetch_sub(unsent, Ordering::Relaxed);
    }

    /// The frames of a batch another host sent, handed over together.
    fn push_batch(&self, s: &zenoh::sample::Sample, from: &str, users_side: bool) {
        if s.payload().len() > MAX_FED_BATCH {
            self.refused.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let payload = s.payload().to_bytes();
        let (frames, bad) = split_batch(&payload);
        if bad {
            self.refused.fetch_add(1, Ordering::Relaxed);
        }
        self.push_all(
            frames
                .into_iter()
                .map(|f| FedInput::Frame {
                    from: from.to_string(),
                    users_side,
                    bytes: f.to_vec(),
                })
                .collect(),
        );
    }

    /// A sample's bytes, if at most `max` (counted as refused otherwise, not copied).
    fn payload(&self, s: &zenoh::sample::Sample, max: usize) -> Option<Vec<u8>> {
        if s.payload().len() > max {
            self.refused.fetch_add(1, Ordering::Relaxed);
            return None;
        }
        Some(s.payload().to_bytes().to_vec())
    }
}

/// A shared-memory inbox the broker keeps for peers on other hosts: a far system's
/// (`system@host`, written to by local users), or a host's relay (written to by local
/// systems for every user of that host, each frame in an envelope naming its user).
struct Proxy {
    endpoint: Endpoint,
    token: usize,
    /// The peers it is open for: the far system, or the host's users.
    peers: HashSet<Address>,
}

/// The inboxes of peers on other hosts, each an endpoint in the reactor, by the address
/// they are opened as ([`Address::inbox_owner`]: a user's host's relay, or the far
/// system's own).
struct ShmInboxes {
    inst: Instance,
    open: HashMap<Address, Proxy>,
    by_token: HashMap<usize, Address>,
    next_token: usize,
    /// Closed ones, kept until their frames are read.
    lingering: Vec<(Instant, Address, Proxy)>,
}

/// [`ShmInboxes`] with the reactor they are watched in, as the core uses them.
struct ShmIo<'a> {
    shm: &'a mut ShmInboxes,
    reactor: &'a Reactor,
}

impl Inboxes for ShmIo<'_> {
    fn open(&mut self, peer: &Address) -> Result<(), String> {
        let shm = &mut *self.shm;
        let key = peer.inbox_owner().into_owned();
        if let Some(p) = shm.open.get_mut(&key) {
            p.peers.insert(peer.clone());
            return Ok(());
        }
        // One closed a moment ago (its peer's host left and came back): taken again.
        let mut proxy = match shm.lingering.iter().position(|(_, a, _)| *a == key) {
            Some(i) => shm.lingering.swap_remove(i).2,
            None => {
                let name = match &key {
                    Address::System(s) => format!("muster-fed-system-{s}"),
                    Address::Relay(h) => format!("muster-fed-relay-{h}"),
                    Address::User(u) => format!("muster-fed-user-{u}"),
                    Address::Process(p) => format!("muster-fed-process-{p}"),
                    Address::Broker => "muster-fed".to_string(),
                };
                let node = create_node(&name, false).map_err(|e| e.to_string())?;
                let endpoint =
                    Endpoint::open(&shm.inst, key.clone(), node).map_err(|e| e.to_string())?;
                let token = shm.next_token;
                shm.next_token += 1;
                Proxy {
                    endpoint,
                    token,
                    peers: HashSet::new(),
                }
            }
        };
        self.reactor
            .add(proxy.endpoint.bell_fd(), proxy.token)
            .map_err(|e| e.to_string())?;
        proxy.peers.insert(peer.clone());
        shm.by_token.insert(proxy.token, key.clone());
        shm.open.insert(key, proxy);
        Ok(())
    }

    fn close(&mut self, peer: &Address) {
        let key = peer.inbox_owner().into_owned();
        let Some(p) = self.shm.open.get_mut(&key) else {
            return;
        };
        p.peers.remove(peer);
        if !p.peers.is_empty() {
            return;
        }
        if let Some(p) = self.shm.open.remove(&key) {
            self.reactor.remove(p.endpoint.bell_fd());
            self.shm.by_token.remove(&p.token);
            self.shm
                .lingering
                .push((Instant::now() + PROXY_LINGER, key, p));
        }
    }

    fn send(&mut self, peer: &Address, to: &Address, msg: &ToSystem) {
        if let Some(p) = self.shm.open.get_mut(&*peer.inbox_owner()) {
            p.endpoint.send_control(to, msg);
        }
    }

    fn owner_pid(&mut self, peer: &Address, of: &Address) -> Option<u32> {
        self.shm
            .open
            .get_mut(&*peer.inbox_owner())?
            .endpoint
            .owner_pid(of)
    }
}

/// What a liveliness token's coming (`true`) or going is for the core.
type TokenInput = fn(String, bool) -> FedInput;

fn key_part<'a>(key: &'a str, prefix: &str) -> Option<(&'a str, &'a str)> {
    key.strip_prefix(prefix)?.split_once('/')
}

/// One broker's membership in a federation: its [`FedCore`] on a Zenoh session.
pub struct Federation {
    core: FedCore,
    prefix: String,
    session: zenoh::Session,
    _token: zenoh::liveliness::LivelinessToken,
    system_tokens: BTreeMap<String, zenoh::liveliness::LivelinessToken>,
    /// Held while a standby is in sync beside this broker.
    standby_token: Option<zenoh::liveliness::LivelinessToken>,
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
    _queryable: zenoh::query::Queryable<()>,
    /// This host's list as last published, for the queryable (on Zenoh's threads).
    my_list: Arc<Mutex<(u64, Vec<u8>)>>,
    events: mpsc::Receiver<FedInput>,
    /// Hands an input to the broker's thread and wakes it (used on Zenoh's threads).
    notify: Arc<Inflow>,
    waker: UnixStream,
    shm: ShmInboxes,
    /// Frames for local users, for the shell to deliver.
    deliveries: VecDeque<Delivery>,
    /// Frames for other hosts not yet put, by host: the batch's kind and the batch
    /// ([`Federation::send_pending`]).
    outgoing: BTreeMap<String, (BatchKind, Batch)>,
    /// Where puts are made (dropped last: it lets the last of them out).
    puts: Putter,
}

impl Drop for Federation {
    fn drop(&mut self) {
        self.send_pending();
    }
}

impl Federation {
    /// Joins the federation as `cfg.host`: opens the Zenoh session, declares the host's
    /// token, and subscribes to the others' tokens, lists and frames.
    /// `check_host`: look for another broker under this host name first (a cold start;
    /// a standby taking over its host's name does not).
    pub fn join(
        inst: &Instance,
        cfg: &FedConfig,
        pid: u32,
        check_host: bool,
    ) -> Result<Self, FedError> {
        super::check_host_like("host name", &cfg.host)?;
        super::check_host_like("federation name", &cfg.federation)?;
        let zcfg = cfg.zenoh_config()?;
        if cfg.insecure {
            tracing::warn!(
                host = %cfg.host,
                "federating WITHOUT TLS (--insecure-no-tls): anyone who reaches this \
                 host's endpoints can read every cross-host frame and act as any host"
            );
        }
        let session = zenoh::open(zcfg)
            .wait()
            .map_err(|e| FedError::Open(e.to_string()))?;
        let prefix = format!("muster/{}/", cfg.federation);
        let host = cfg.host.clone();
        let alive_key = format!("{prefix}{host}/alive");
        // Another broker under this name? (Best effort: peers not yet found are missed.)
        // Asked a few times: peers found by gossip after the first connection answer
        // only once connected.
        if check_host {
            let until = Instant::now() + HOST_CHECK;
            while Instant::now() < until {
                let taken = session
                    .liveliness()
                    .get(&alive_key)
                    .timeout(HOST_CHECK / 8)
                    .wait()
                    .is_ok_and(|replies| replies.recv().is_ok_and(|r| r.result().is_ok()));
                if taken {
                    return Err(FedError::HostTaken(host));
                }
            }
        }
        let (tx, events) = mpsc::channel::<FedInput>();
        let (waker, ring) = UnixStream::pair().map_err(|e| FedError::Open(e.to_string()))?;
        waker
            .set_nonblocking(true)
            .map_err(|e| FedError::Open(e.to_string()))?;
        ring.set_nonblocking(true)
            .map_err(|e| FedError::Open(e.to_string()))?;
        let ring = Arc::new(ring);
        let notify = Arc::new(Inflow {
            tx: Mutex::new(tx),
            ring,
            queued: AtomicUsize::new(0),
            refused: AtomicU64::new(0),
        });
        let zerr = |e: zenoh::Error| FedError::Open(e.to_string());
        let mut subscribers = Vec::new();
        // Brokers' tokens, and their standbys'.
        let tokens: [(&str, TokenInput); 2] =
            [("alive", FedInput::Alive), ("standby", FedInput::Standby)];
        for (what, input) in tokens {
            let n = notify.clone();
            let p = prefix.clone();
            let me = host.clone();
            subscribers.push(
                session
                    .liveliness()
                    .declare_subscriber(format!("{prefix}*/{what}"))
                    .history(true)
                    .callback(move |s| {
                        if let Some((h, _)) = key_part(s.key_expr().as_str(), &p) {
                            if h != me {
                                let up = s.kind() == zenoh::sample::SampleKind::Put;
                                n.push(input(h.to_string(), up));
                            }
                        }
                    })
                    .wait()
                    .map_err(zerr)?,
            );
        }
        {
            let n = notify.clone();
            let p = prefix.clone();
            let me = host.clone();
            subscribers.push(
                session
                    .declare_subscriber(format!("{prefix}*/list"))
                    .callback(move |s| {
                        if let Some((h, _)) = key_part(s.key_expr().as_str(), &p) {
                            if let Some(body) = n.payload(&s, MAX_FED_LIST).filter(|_| h != me) {
                                let (host, version) = (h.to_string(), list_version(&s));
                                n.push(FedInput::List {
                                    host,
                                    version,
                                    body,
                                });
                            }
                        }
                    })
                    .wait()
                    .map_err(zerr)?,
            );
        }
        for (part, users_side) in [("req", true), ("in", false)] {
            let n = notify.clone();
            let inbox = format!("{prefix}{host}/{part}/");
            subscribers.push(
                session
                    .declare_subscriber(format!("{inbox}*"))
                    .callback(move |s| {
                        if let Some(from) = s.key_expr().as_str().strip_prefix(&inbox) {
                            n.push_batch(&s, from, users_side);
                        }
                    })
                    .wait()
                    .map_err(zerr)?,
            );
        }
        let my_list = Arc::new(Mutex::new((0u64, b"[]".to_vec())));
        let queryable = {
            let list = my_list.clone();
            let key = format!("{prefix}{host}/list");
            session
                .declare_queryable(key.clone())
                .callback(move |q| {
                    let (version, body) = list.lock().map(|l| l.clone()).unwrap_or_default();
                    // Under its own key (the query's may be a wildcard over hosts).
                    let _ = q
                        .reply(&key, body)
                        .attachment(version.to_le_bytes().to_vec())
                        .wait();
                })
                .wait()
                .map_err(zerr)?
        };
        let token = session
            .liveliness()
            .declare_token(&alive_key)
            .wait()
            .map_err(zerr)?;
        let advertise = cfg.listen.iter().find_map(|e| super::listen_ip(e));
        let core = FedCore::new(&host, pid, cfg.effective_acl()?, advertise, now());
        if !core.may(&host, Role::Offer) {
            tracing::info!("the access file does not let this host offer: its services stay local");
        }
        tracing::info!(host = %host, federation = %cfg.federation, "joined the federation");
        let puts = Putter::new(session.clone())?;
        Ok(Federation {
            core,
            notify,
            prefix,
            session,
            _token: token,
            system_tokens: BTreeMap::new(),
            standby_token: None,
            _subscribers: subscribers,
            _queryable: queryable,
            my_list,
            events,
            waker,
            shm: ShmInboxes {
                inst: inst.clone(),
                open: HashMap::new(),
                by_token: HashMap::new(),
                next_token: FIRST_PROXY_TOKEN,
                lingering: Vec::new(),
            },
            deliveries: VecDeque::new(),
            outgoing: BTreeMap::new(),
            puts,
        })
    }

    /// Whether a standby is in sync beside this broker: the other hosts then wait for
    /// this host a while when its token goes ([`super::HOST_GRACE`]).
    pub fn set_standby(&mut self, has: bool) {
        if has == self.standby_token.is_some() {
            return;
        }
        self.standby_token = None;
        if has {
            let key = format!("{}{}/standby", self.prefix, self.core.host());
            match self.session.liveliness().declare_token(&key).wait() {
                Ok(t) => self.standby_token = Some(t),
                Err(e) => tracing::warn!("federation: standby token: {e}"),
            }
        }
    }

    /// This host's name.
    pub fn host(&self) -> &str {
        self.core.host()
    }

    /// The counters.
    pub fn stats(&self) -> FedStats {
        FedStats {
            puts_dropped: self.puts.dropped.load(Ordering::Relaxed),
            ..self.core.stats().clone()
        }
    }

    /// The descriptor that is readable when Zenoh has handed something over.
    pub fn wake_fd(&self) -> std::os::fd::RawFd {
        self.waker.as_raw_fd()
    }

    /// When [`Federation::sweep`] is next due.
    pub fn next_due(&self) -> Option<Duration> {
        let (t, i) = (now(), Instant::now());
        self.shm
            .lingering
            .iter()
            .map(|(at, _, _)| at.saturating_duration_since(i))
            .chain(self.core.poll_timeout().map(|at| at.saturating_sub(t)))
            .min()
    }

    /// Closes proxies that have lingered long enough, and runs the core's timers.
    pub fn sweep(&mut self, core: &mut Broker, reactor: &Reactor, now: Duration) {
        let i = Instant::now();
        self.shm.lingering.retain(|(at, _, _)| *at > i);
        if self.core.poll_timeout().is_some_and(|at| at <= now) {
            let mut io = ShmIo {
                shm: &mut self.shm,
                reactor,
            };
            self.core.handle_timeout(now, core, &mut io);
        }
        self.carry_out();
    }

    /// This broker took over its host (see [`FedCore::take_over`]).
    pub fn take_over(&mut self, core: &mut Broker, reactor: &Reactor, now: Duration) {
        let mut io = ShmIo {
            shm: &mut self.shm,
            reactor,
        };
        self.core.take_over(now, core, &mut io);
        self.carry_out();
    }

    /// This host's services with other hosts' links counted, published (see
    /// [`FedCore::publish_list`]).
    pub fn publish_list(&mut self, views: &[ServiceView], systems: &[&str]) -> Vec<ServiceView> {
        let unix_ns = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
        let mine = self.core.publish_list(now(), unix_ns, views, systems);
        self.carry_out();
        mine
    }

    /// This host's services and the other hosts' (see [`FedCore::merged_views`]).
    pub fn merged_views<'a>(
        &'a self,
        local: &'a [ServiceView],
        cap: usize,
    ) -> Vec<&'a ServiceView> {
        self.core.merged_views(local, cap)
    }

    /// Whether the other hosts' services changed since the last call.
    pub fn take_list_change(&mut self) -> bool {
        self.core.take_list_change()
    }

    /// Whether other hosts' links here changed since the last call.
    pub fn take_links_change(&mut self) -> bool {
        self.core.take_links_change()
    }

    /// See [`FedCore::intercept`].
    pub fn intercept(
        &mut self,
        msg: &ToBroker,
        contact: impl FnOnce(&UserId, u64) -> Option<RemoteContact>,
    ) -> bool {
        let passed = self.core.intercept(now(), msg, contact);
        self.carry_out();
        passed
    }

    /// See [`FedCore::route`].
    pub fn route(&mut self, core: &Broker, out: Output) -> Option<Output> {
        let out = self.core.route(core, out);
        self.carry_out();
        out
    }

    /// See [`FedCore::follow_grant`].
    pub fn follow_grant(&mut self, user: &UserId, session: SessionId, msg: ToUser) {
        self.core.follow_grant(user, session, msg);
        self.carry_out();
    }

    /// The next frame for a local user.
    pub fn poll_delivery(&mut self) -> Option<Delivery> {
        self.deliveries.pop_front()
    }

    /// A local user died or left: the hosts holding its requests or sessions hear of it.
    pub fn local_user_gone(&mut self, user: &UserId) {
        self.core.local_user_gone(user);
        self.carry_out();
    }

    /// A local system died: the other hosts' users of its sessions are told.
    pub fn local_system_gone(&mut self, system: &str) {
        self.core.local_system_gone(system);
        self.carry_out();
    }

    /// Hands what Zenoh handed over to the core: hosts coming and going, lists, frames.
    pub fn on_wake(&mut self, core: &mut Broker, reactor: &Reactor, now: Duration) {
        let mut buf = [0u8; 256];
        while matches!((&self.waker).read(&mut buf), Ok(n) if n > 0) {}
        self.core
            .count_dropped(self.notify.refused.swap(0, Ordering::Relaxed));
        while let Ok(ev) = self.events.try_recv() {
            self.notify
                .queued
                .fetch_sub(input_bytes(&ev), Ordering::Relaxed);
            let mut io = ShmIo {
                shm: &mut self.shm,
                reactor,
            };
            self.core.handle(now, ev, core, &mut io);
            self.carry_out();
        }
    }

    /// Frames in a proxy inbox: a system's for a user of another host, or a local
    /// user's for a system of another host. Handed to the core, which relays them.
    pub fn on_proxy(&mut self, token: usize, core: &Broker, reactor: &Reactor) {
        let Some(key) = self.shm.by_token.get(&token).cloned() else {
            return;
        };
        let mut frames = Vec::new();
        if let Some(p) = self.shm.open.get_mut(&key) {
            p.endpoint.drain_bell();
            while let Some(f) = p.endpoint.recv_from() {
                frames.push(f);
            }
        }
        let mut io = ShmIo {
            shm: &mut self.shm,
            reactor,
        };
        for (frame, sender) in frames {
            match &key {
                // A relay's frame names its user, who must be of the relay's host.
                Address::Relay(host) => {
                    let Some((user, frame)) = open_envelope(&frame) else {
                        tracing::debug!(%host, "a frame in a relay that is not an envelope");
                        continue;
                    };
                    let peer = Address::User(user);
                    if peer.relay().as_ref() != Some(&key) {
                        tracing::debug!(%peer, %host, "a frame in a relay for another host's user");
                        continue;
                    }
                    self.core.inbox_frame(&peer, frame, sender, core, &mut io);
                }
                _ => self.core.inbox_frame(&key, &frame, sender, core, &mut io),
            }
        }
        self.carry_out();
    }

    /// Carries out the core's outputs.
    fn carry_out(&mut self) {
        while let Some(o) = self.core.poll_output() {
            match o {
                FedOutput::Send { to, msg } => self.put_frame(&to, &msg),
                FedOutput::PutList { version, body } => {
                    if let Ok(mut l) = self.my_list.lock() {
                        *l = (version, body.clone());
                    }
                    // Waits for room rather than being dropped: the others would see
                    // the change only at their next refresh.
                    self.puts.put(Put {
                        key: format!("{}{}/list", self.prefix, self.core.host()),
                        body,
                        droppable: false,
                        attachment: Some(version.to_le_bytes().to_vec()),
                    });
                }
                FedOutput::AnnounceList { version } => {
                    // No body: only the version, which peers compare with theirs; the
                    // next announcement repeats it, so it may be dropped.
                    self.puts.put(Put {
                        key: format!("{}{}/list", self.prefix, self.core.host()),
                        body: Vec::new(),
                        droppable: true,
                        attachment: Some(version.to_le_bytes().to_vec()),
                    });
                }
                FedOutput::QueryList(host) => self.query_list(&host),
                FedOutput::SystemUp(s) => {
                    let key = format!("{}{}/system/{s}", self.prefix, self.core.host());
                    match self.session.liveliness().declare_token(&key).wait() {
                        Ok(t) => {
                            self.system_tokens.insert(s, t);
                        }
                        Err(e) => tracing::warn!("federation: token for system {s}: {e}"),
                    }
                }
                FedOutput::SystemDown(s) => {
                    self.system_tokens.remove(&s);
                }
                FedOutput::Deliver(d) => self.deliveries.push_back(d),
            }
        }
    }

    /// Adds a frame to `to`'s batch; a batch of another kind, or one it does not fit
    /// beside, is put first (a host's frames keep their order).
    fn put_frame(&mut self, to: &str, msg: &FedMsg) {
        let frame = match encode(msg) {
            Ok(f) => f,
            Err(e) => return tracing::warn!("federation: cannot encode a frame for {to}: {e}"),
        };
        if frame.len() > MAX_FED_FRAME {
            // The other host would drop it unread.
            return tracing::warn!(
                bytes = frame.len(),
                limit = MAX_FED_FRAME,
                "federation: a frame for {to} is too large: not sent"
            );
        }
        let kind = BatchKind {
            users_key: msg.on_users_key(),
            droppable: msg.droppable(),
        };
        let flush = self
            .outgoing
            .get(to)
            .is_some_and(|(k, b)| !b.is_empty() && (*k != kind || !b.fits(&frame)));
        let (k, batch) = self.outgoing.entry(to.to_string()).or_default();
        if flush {
            put_batch(
                &self.puts,
                &self.prefix,
                self.core.host(),
                to,
                *k,
                batch.take(),
            );
        }
        *k = kind;
        batch.push(&frame);
    }

    /// Puts every batch gathered since the last call. The shell calls it at the end of
    /// each flush of its outputs, so a frame waits at most for the rest of the pass of
    /// the loop that made it.
    pub fn send_pending(&mut self) {
        let host = self.core.host();
        for (to, (kind, batch)) in self.outgoing.iter_mut().filter(|(_, (_, b))| !b.is_empty()) {
            put_batch(&self.puts, &self.prefix, host, to, *kind, batch.take());
        }
    }

    fn query_list(&self, host: &str) {
        let key = format!("{}{host}/list", self.prefix);
        let h = host.to_string();
        let n = self.notify.clone();
        // Zenoh drops the callback when the query ends (its last reply, or its
        // timeout): the core hears then whether a list came.
        let ended = QueryEnded {
            notify: n.clone(),
            host: host.to_string(),
            answered: AtomicBool::new(false),
        };
        let r = self
            .session
            .get(&key)
            .target(zenoh::query::QueryTarget::All)
            .timeout(LIST_QUERY_TIMEOUT)
            .callback(move |reply| {
                if let Some(body) = reply.result().ok().and_then(|s| n.payload(s, MAX_FED_LIST)) {
                    let version = reply.result().map_or(0, list_version);
                    ended.answered.store(true, Ordering::Relaxed);
                    n.push(FedInput::List {
                        host: h.clone(),
                        version,
                        body,
                    });
                }
            })
            .wait();
        if let Err(e) = r {
            tracing::warn!("federation: cannot ask {host} for its list: {e}");
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn inflow() -> (Inflow, mpsc::Receiver<FedInput>, UnixStream) {
        let (tx, rx) = mpsc::channel();
        let (ring, woken) = UnixStream::pair().unwrap();
        woken.set_nonblocking(true).unwrap();
        let inflow = Inflow {
            tx: Mutex::new(tx),
            ring: Arc::new(ring),
            queued: AtomicUsize::new(0),
            refused: AtomicU64::new(0),
        };
        (inflow, rx, woken)
    }

    fn rang(woken: &UnixStream) -> bool {
        let mut buf = [0u8; 16];
        matches!((&*woken).read(&mut buf), Ok(n) if n > 0)
    }

    #[test]
    fn puts_go_out_in_order_from_their_own_thread_and_the_last_ones_before_it_stops() {
        // A session of its own: no scouting, no listening, no peers.
        let mut c = zenoh::Config::default();
        for (k, v) in [
            ("mode", "\"peer\""),
            ("scouting/multicast/enabled", "false"),
            ("scouting/gossip/enabled", "false"),
            ("listen/endpoints", "[]"),
            ("connect/endpoints", "[]"),
        ] {
            c.insert_json5(k, v).unwrap();
        }
        let session = zenoh::open(c).wait().unwrap();
        let (tx, rx) = mpsc::channel();
        let _sub = session
            .declare_subscriber("putter-test/**")
            .callback(move |s| {
                let a = s.attachment().map(|a| a.to_bytes().to_vec());
                let _ = tx.send((s.key_expr().to_string(), s.payload().to_bytes().to_vec(), a));
            })
            .wait()
            .unwrap();
        let puts = Putter::new(session.clone()).unwrap();
        for i in 0..200u32 {
            puts.put(Put {
                key: format!("putter-test/{}", i % 3),
                body: i.to_le_bytes().to_vec(),
                droppable: i % 2 == 0,
                attachment: (i % 5 == 0).then(|| vec![i as u8]),
            });
        }
        // Dropped: the queued ones go out first.
        drop(puts);
        let got: Vec<_> = rx.try_iter().collect();
        assert_eq!(got.len(), 200, "nothing dropped below the queue's bound");
        for (i, (key, body, a)) in got.into_iter().enumerate() {
            let i = i as u32;
            assert_eq!(key, format!("putter-test/{}", i % 3));
            assert_eq!(body, i.to_le_bytes(), "in the order put");
            assert_eq!(a, i.is_multiple_of(5).then(|| vec![i as u8]));
        }
    }

    #[test]
    fn every_input_wakes_the_loop_even_one_of_no_bytes_and_the_budget_is_kept() {
        let (inflow, rx, woken) = inflow();
        // A host's token going carries no bytes: it must wake the loop all the same.
        inflow.push(FedInput::Alive("b".into(), false));
        assert!(rang(&woken), "a token wakes the loop");
        assert_eq!(rx.try_recv().unwrap(), FedInput::Alive("b".into(), false));
        let frame = |n: usize| FedInput::Frame {
            from: "b".into(),
            users_side: true,
            bytes: vec![0; n],
        };
        inflow.push_all(vec![frame(3), frame(4)]);
        assert!(rang(&woken));
        assert_eq!(inflow.queued.load(Ordering::Relaxed), 7);
        assert_eq!(
            (rx.try_recv().unwrap(), rx.try_recv().unwrap()),
            (frame(3), frame(4))
        );
        // Over the budget: refused whole, counted, nothing queued, no wake-up.
        inflow.push_all(vec![frame(MAX_QUEUED_BYTES), frame(1)]);
        assert!(!rang(&woken));
        assert_eq!(inflow.refused.load(Ordering::Relaxed), 2);
        assert_eq!(inflow.queued.load(Ordering::Relaxed), 7);
        assert!(rx.try_recv().is_err());
    }
}
