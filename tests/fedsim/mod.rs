//! Several hosts on one virtual clock: on each, the broker core and its federation
//! core ([`FedCore`]), system cores running the synthetic system's logic, and user
//! cores; between them, a seeded model of Zenoh: per-link latency, liveliness tokens
//! that go when a broker dies or a link stays cut past the lease, frames held while a
//! link is cut for less than the lease (TCP keeps them) and lost when it is cut for
//! longer, and, when asked, duplicated and reordered frames. A process's death reaches
//! whoever watches its pid, as the kernel's pidfds do. Frames go through the wire codec.
//!
//! The shell's glue is the broker shell's (`broker/src/run/`): a local user's frame for
//! the broker goes through [`FedCore::intercept`] first, the core's outputs through
//! [`FedCore::route`], and a frame written to a peer's inbox reaches
//! [`FedCore::inbox_frame`].

use muster_broker::core::{Broker, BrokerConfig, Output};
use muster_broker::federation::{Delivery, FedCore, FedInput, FedOutput, Inboxes};
use muster_broker::replica::{Follower, Leader};
use muster_shared::names::Address;
use muster_shared::protocol::{decode, encode, ToBroker, ToSystem, ToUser};
use muster_shared::snapshot::{ServiceView, DEFAULT_MAX_SERVICES};
use muster_shared::types::{ServiceId, UserId};
use muster_systems::core::{SystemCore, SystemOutput};
use muster_systems::runtime::SystemApp;
use muster_systems::synthetic::{Synthetic, SyntheticOptions};
use muster_users::core::{UserCore, UserEvent, UserOutput};
use rand::{RngExt, SeedableRng};
use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::Duration;

/// A frame on one host's shared memory, with its sender's pid.
enum Frame {
    Broker(Vec<u8>),
    System(String, Vec<u8>, u32),
    User(UserId, Vec<u8>, u32),
}

struct Sys {
    core: SystemCore,
    app: Synthetic,
    pid: u32,
    /// Users it watches: pid → users.
    watches: BTreeMap<u32, BTreeSet<UserId>>,
}

struct User {
    core: UserCore,
    pid: u32,
    /// Systems it watches: pid → systems.
    watches: BTreeMap<u32, BTreeSet<String>>,
}

/// One host: a broker (with its federation core) while it runs, its systems and users.
pub struct Host {
    /// Its name in the federation.
    pub name: String,
    broker: Option<Broker>,
    fed: Option<FedCore>,
    broker_pid: u32,
    epoch: u64,
    runs: u32,
    systems: BTreeMap<String, Sys>,
    users: BTreeMap<UserId, User>,
    events: BTreeMap<UserId, Vec<UserEvent>>,
    wire: VecDeque<Frame>,
    /// The inboxes the federation core keeps open here.
    inboxes: BTreeSet<Address>,
    /// What the broker watches: pid → addresses.
    broker_watches: BTreeMap<u32, BTreeSet<Address>>,
    /// Whether a standby runs beside its broker (its token is up while the broker is).
    pub standby: bool,
    /// The core's rows, and this host's own with other hosts' links counted.
    core_views: Vec<ServiceView>,
    local_views: Vec<ServiceView>,
}

/// The federation core's inboxes on a host: frames written through one go to the host's
/// wire as sent by the broker.
struct HostInboxes<'a> {
    open: &'a mut BTreeSet<Address>,
    wire: &'a mut VecDeque<Frame>,
    systems: &'a BTreeMap<String, Sys>,
    pid: u32,
}

impl Inboxes for HostInboxes<'_> {
    fn open(&mut self, peer: &Address) -> Result<(), String> {
        self.open.insert(peer.clone());
        Ok(())
    }

    fn close(&mut self, peer: &Address) {
        self.open.remove(peer);
    }

    fn send(&mut self, peer: &Address, to: &Address, msg: &ToSystem) {
        if let (true, Address::System(s)) = (self.open.contains(peer), to) {
            self.wire
                .push_back(Frame::System(s.clone(), encode(msg).unwrap(), self.pid));
        }
    }

    fn owner_pid(&mut self, _peer: &Address, of: &Address) -> Option<u32> {
        match of {
            Address::System(s) => self.systems.get(s).map(|s| s.pid),
            _ => None,
        }
    }
}

/// What travels between hosts.
#[derive(Clone, Debug)]
enum Wire {
    Input(FedInput),
    /// Host `0` asks for the receiver's list.
    Query(usize),
}

/// A cut link: since when, and whether it is down (cut past the lease).
#[derive(Clone, Copy, Debug)]
struct Cut {
    since: Duration,
    down: bool,
}

/// Faults on every link between hosts.
#[derive(Clone, Copy, Debug, Default)]
pub struct LinkFaults {
    /// Probability a frame arrives twice.
    pub dup: f64,
    /// Extra delay, uniform in [0, jitter): frames overtake each other.
    pub jitter: Duration,
}

/// The hosts and the network between them.
pub struct World {
    /// The virtual clock.
    pub now: Duration,
    /// The hosts, by index.
    pub hosts: Vec<Host>,
    /// One way, on every link.
    pub latency: Duration,
    /// A peer silent this long is gone.
    pub lease: Duration,
    /// Faults on every link.
    pub faults: LinkFaults,
    rng: rand_pcg::Pcg64,
    inflight: BTreeMap<(Duration, u64), (usize, usize, Wire)>,
    seq: u64,
    cuts: BTreeMap<(usize, usize), Cut>,
    /// Frames sent over a cut link that is not down yet: from, to, what.
    held: Vec<(usize, usize, Wire)>,
    /// Whether host `0` sees host `1`'s token.
    seen: BTreeSet<(usize, usize)>,
    /// Whether host `0` sees host `1`'s standby token.
    seen_standby: BTreeSet<(usize, usize)>,
    /// Frames between hosts delivered, duplicated, lost to a cut.
    pub carried: u64,
    /// Frames delivered twice.
    pub duplicated: u64,
    /// Frames lost with a link that went down.
    pub lost: u64,
    /// Hosts that miss every list published whole (as a host does whose subscription
    /// the publisher's network did not know yet); queries still reach them.
    pub deaf_to_lists: BTreeSet<usize>,
    next_pid: u32,
}

fn pair(a: usize, b: usize) -> (usize, usize) {
    (a.min(b), a.max(b))
}

/// Unix ns at virtual time `now` (lists' versions).
fn wall(now: Duration) -> u64 {
    1_700_000_000_000_000_000 + now.as_nanos() as u64
}

impl World {
    /// Hosts named `names`, each with a broker, on links of 1 ms, lease 10 s.
    pub fn new(names: &[&str], seed: u64) -> Self {
        let mut w = World {
            now: Duration::ZERO,
            hosts: Vec::new(),
            latency: Duration::from_millis(1),
            lease: Duration::from_secs(10),
            faults: LinkFaults::default(),
            rng: rand_pcg::Pcg64::seed_from_u64(seed),
            inflight: BTreeMap::new(),
            seq: 0,
            cuts: BTreeMap::new(),
            held: Vec::new(),
            seen: BTreeSet::new(),
            seen_standby: BTreeSet::new(),
            carried: 0,
            duplicated: 0,
            lost: 0,
            deaf_to_lists: BTreeSet::new(),
            next_pid: 1000,
        };
        for (idx, name) in names.iter().enumerate() {
            w.hosts.push(Host {
                name: name.to_string(),
                broker: None,
                fed: None,
                broker_pid: 0,
                epoch: 0,
                runs: 0,
                systems: BTreeMap::new(),
                users: BTreeMap::new(),
                events: BTreeMap::new(),
                wire: VecDeque::new(),
                inboxes: BTreeSet::new(),
                broker_watches: BTreeMap::new(),
                standby: false,
                core_views: Vec::new(),
                local_views: Vec::new(),
            });
            w.start_broker(idx, None);
        }
        w.settle();
        w
    }

    /// The index of host `name`.
    pub fn h(&self, name: &str) -> usize {
        self.hosts
            .iter()
            .position(|h| h.name == name)
            .expect("a host of the world")
    }

    fn pid(&mut self) -> u32 {
        self.next_pid += 1;
        self.next_pid
    }

    /// Starts host `h`'s broker: cold (`None`), or a standby taking over `state`.
    fn start_broker(&mut self, h: usize, state: Option<Broker>) {
        let pid = self.pid();
        let now = self.now;
        let host = &mut self.hosts[h];
        host.epoch += 1;
        host.runs += 1;
        host.broker_pid = pid;
        let mut fed = FedCore::new(&host.name, pid, None, None, now);
        let takeover = state.is_some();
        let mut broker = match state {
            Some(mut b) => {
                b.take_over(now, host.epoch, pid);
                b
            }
            None => Broker::new(BrokerConfig::default(), host.epoch, pid),
        };
        host.core_views.clear();
        host.local_views.clear();
        host.broker_watches.clear();
        if takeover {
            let mut io = HostInboxes {
                open: &mut host.inboxes,
                wire: &mut host.wire,
                systems: &host.systems,
                pid,
            };
            fed.take_over(now, &mut broker, &mut io);
        }
        host.broker = Some(broker);
        host.fed = Some(fed);
        // Nobody's token is seen by a new session yet; its subscription's history
        // brings every live one.
        self.seen.retain(|(x, _)| *x != h);
        self.seen_standby.retain(|(x, _)| *x != h);
        // The presence event: systems register again; users say hello to a new broker,
        // or adopt a standby that took over with their state.
        let host = &mut self.hosts[h];
        let epoch = host.epoch;
        for s in host.systems.values_mut() {
            s.core.broker_lost();
            s.core.register();
        }
        for u in host.users.values_mut() {
            u.core.broker_lost();
            if takeover {
                u.core.adopt(epoch, pid);
            } else {
                u.core.hello();
            }
        }
        self.reconcile_tokens();
    }

    /// Host `h`'s broker process dies (SIGKILL): its inboxes go, whoever watched it
    /// hears, and the other hosts see its token go.
    pub fn kill_broker(&mut self, h: usize) -> Option<Broker> {
        let host = &mut self.hosts[h];
        let broker = host.broker.take();
        host.fed = None;
        host.inboxes.clear();
        let pid = host.broker_pid;
        for s in host.systems.values_mut() {
            s.core.broker_lost();
        }
        for u in host.users.values_mut() {
            u.core.broker_lost();
        }
        self.process_died(h, pid);
        self.reconcile_tokens();
        self.settle();
        broker
    }

    /// A standby starts (or stops) beside host `h`'s broker.
    pub fn set_standby(&mut self, h: usize, on: bool) {
        self.hosts[h].standby = on;
        self.reconcile_tokens();
        self.settle();
    }

    /// Host `h`'s broker dies and its standby, in sync with it, takes over (another
    /// standby starts beside it).
    pub fn fail_over(&mut self, h: usize) {
        assert!(self.hosts[h].standby, "host {h} has no standby");
        let Some(old) = self.kill_broker(h) else {
            return;
        };
        // What the standby holds: the state as replicated, record by record.
        let mut f = Follower::new();
        f.apply(&Leader::after(0).image(&old)).unwrap();
        self.start_broker(h, f.into_core());
        self.settle();
    }

    /// Host `h`'s broker dies and starts again with nothing (a cold restart).
    pub fn restart_broker(&mut self, h: usize) {
        self.kill_broker(h);
        self.start_broker(h, None);
        self.settle();
    }

    /// The whole host `h` goes: broker, systems, users.
    pub fn lose_host(&mut self, h: usize) {
        self.kill_broker(h);
        let host = &mut self.hosts[h];
        host.systems.clear();
        host.users.clear();
        host.wire.clear();
    }

    /// Cuts the link between `a` and `b` (both ways).
    pub fn cut(&mut self, a: usize, b: usize) {
        self.cuts.entry(pair(a, b)).or_insert(Cut {
            since: self.now,
            down: false,
        });
    }

    /// Heals the link between `a` and `b`: frames it held go on, tokens come back.
    pub fn heal(&mut self, a: usize, b: usize) {
        let Some(cut) = self.cuts.remove(&pair(a, b)) else {
            return;
        };
        if !cut.down {
            let held = std::mem::take(&mut self.held);
            for (from, to, w) in held {
                if pair(from, to) == pair(a, b) {
                    self.queue(from, to, w);
                } else {
                    self.held.push((from, to, w));
                }
            }
        }
        self.reconcile_tokens();
    }

    fn link_up(&self, a: usize, b: usize) -> bool {
        !self.cuts.get(&pair(a, b)).is_some_and(|c| c.down)
    }

    /// Sends the token changes each host's session would see (a standby token before
    /// the broker's, when both go: either order can happen).
    fn reconcile_tokens(&mut self) {
        let n = self.hosts.len();
        for x in 0..n {
            for y in 0..n {
                if x == y || self.hosts[x].fed.is_none() {
                    continue;
                }
                let up = self.hosts[y].fed.is_some() && self.link_up(x, y);
                let standby = up && self.hosts[y].standby;
                let name = self.hosts[y].name.clone();
                for (seen, should, input) in [
                    (true, standby, FedInput::Standby(name.clone(), standby)),
                    (false, up, FedInput::Alive(name, up)),
                ] {
                    let set = if seen {
                        &mut self.seen_standby
                    } else {
                        &mut self.seen
                    };
                    if set.contains(&(x, y)) == should {
                        continue;
                    }
                    if should {
                        set.insert((x, y));
                    } else {
                        set.remove(&(x, y));
                    }
                    let at = self.now + self.latency;
                    self.seq += 1;
                    self.inflight
                        .insert((at, self.seq), (y, x, Wire::Input(input)));
                }
            }
        }
    }

    /// Sends `w` from host `from` to host `to`, as the network does.
    fn send(&mut self, from: usize, to: usize, w: Wire) {
        match self.cuts.get(&pair(from, to)) {
            Some(c) if c.down => self.lost += 1,
            Some(_) => self.held.push((from, to, w)),
            None => self.queue(from, to, w),
        }
    }

    fn queue(&mut self, from: usize, to: usize, w: Wire) {
        let mut delay = self.latency;
        if !self.faults.jitter.is_zero() {
            delay += self.faults.jitter.mul_f64(self.rng.random::<f64>());
        }
        if self.faults.dup > 0.0 && self.rng.random::<f64>() < self.faults.dup {
            self.duplicated += 1;
            self.seq += 1;
            let again = delay + self.faults.jitter.mul_f64(self.rng.random::<f64>());
            self.inflight
                .insert((self.now + again, self.seq), (from, to, w.clone()));
        }
        self.seq += 1;
        self.inflight
            .insert((self.now + delay, self.seq), (from, to, w));
    }

    /// A system `opts` on host `h`.
    pub fn add_system(&mut self, h: usize, opts: &SyntheticOptions) {
        let pid = self.pid();
        let mut core = SystemCore::new(&opts.name, pid, opts.specs());
        core.register();
        self.hosts[h].systems.insert(
            opts.name.clone(),
            Sys {
                core,
                app: Synthetic::new(opts),
                pid,
                watches: BTreeMap::new(),
            },
        );
        self.settle();
    }

    /// A user `name` on host `h`.
    pub fn add_user(&mut self, h: usize, name: &str) -> UserId {
        let pid = self.pid();
        let id = UserId(name.into());
        let mut core = UserCore::new(id.clone(), pid, false);
        core.hello();
        self.hosts[h].users.insert(
            id.clone(),
            User {
                core,
                pid,
                watches: BTreeMap::new(),
            },
        );
        self.settle();
        id
    }

    /// User `u` of host `h`.
    pub fn user(&mut self, h: usize, u: &UserId) -> &mut UserCore {
        &mut self.hosts[h]
            .users
            .get_mut(u)
            .expect("a user of the host")
            .core
    }

    /// System `s` of host `h`.
    pub fn system(&self, h: usize, s: &str) -> &SystemCore {
        &self.hosts[h]
            .systems
            .get(s)
            .expect("a system of the host")
            .core
    }

    /// User `u` of host `h` asks for `service`.
    pub fn request(&mut self, h: usize, u: &UserId, service: &str) -> u64 {
        let req = self.user(h, u).request(ServiceId(service.into()));
        self.settle();
        req
    }

    /// User `u` of host `h` ends `session`.
    pub fn end(&mut self, h: usize, u: &UserId, session: muster_shared::types::SessionId) {
        self.user(h, u).end(session);
        self.settle();
    }

    /// What user `u` of host `h` heard since the last call.
    pub fn take_events(&mut self, h: usize, u: &UserId) -> Vec<UserEvent> {
        std::mem::take(self.hosts[h].events.entry(u.clone()).or_default())
    }

    /// User `u`'s process on host `h` dies.
    pub fn kill_user(&mut self, h: usize, u: &UserId) {
        if let Some(user) = self.hosts[h].users.remove(u) {
            self.process_died(h, user.pid);
            self.settle();
        }
    }

    /// The list host `h`'s users read: its services and the other hosts'.
    pub fn list(&self, h: usize) -> Vec<ServiceView> {
        let host = &self.hosts[h];
        match host.fed.as_ref() {
            Some(f) => f
                .merged_views(&host.local_views, DEFAULT_MAX_SERVICES)
                .into_iter()
                .cloned()
                .collect(),
            None => Vec::new(),
        }
    }

    /// The ids in host `h`'s list.
    pub fn list_ids(&self, h: usize) -> Vec<String> {
        self.list(h).into_iter().map(|v| v.id).collect()
    }

    /// Host `h`'s broker core, while it runs.
    pub fn broker(&self, h: usize) -> Option<&Broker> {
        self.hosts[h].broker.as_ref()
    }

    /// Host `h`'s federation core, while its broker runs.
    pub fn fed(&self, h: usize) -> Option<&FedCore> {
        self.hosts[h].fed.as_ref()
    }

    /// Process `pid` on host `h` died: whoever watched it hears.
    fn process_died(&mut self, h: usize, pid: u32) {
        let host = &mut self.hosts[h];
        for s in host.systems.values_mut() {
            for u in s.watches.remove(&pid).unwrap_or_default() {
                s.core.user_died(&u);
            }
        }
        for u in host.users.values_mut() {
            for s in u.watches.remove(&pid).unwrap_or_default() {
                u.core.system_died(&s);
            }
        }
        let who = host.broker_watches.remove(&pid).unwrap_or_default();
        if let (Some(b), Some(f)) = (host.broker.as_mut(), host.fed.as_mut()) {
            for a in who {
                match a {
                    Address::System(s) => {
                        f.local_system_gone(&s);
                        b.system_died(self.now, &s);
                    }
                    Address::User(u) => {
                        f.local_user_gone(&u);
                        b.user_died(self.now, &u);
                    }
                    Address::Broker | Address::Relay(_) | Address::Process(_) => {}
                }
            }
        }
    }

    /// Moves frames and outputs until nothing is left to deliver now.
    pub fn settle(&mut self) {
        for _ in 0..1_000_000 {
            let mut moved = false;
            for h in 0..self.hosts.len() {
                moved |= self.collect(h);
                moved |= self.deliver_one(h);
            }
            moved |= self.deliver_due();
            if !moved {
                return;
            }
        }
        panic!("the hosts did not settle");
    }

    /// Delivers what is due on the network now; whether anything was.
    fn deliver_due(&mut self) -> bool {
        let mut any = false;
        while let Some((&(at, seq), _)) = self.inflight.first_key_value() {
            if at > self.now {
                break;
            }
            let Some((from, to, w)) = self.inflight.remove(&(at, seq)) else {
                break;
            };
            any = true;
            self.carried += 1;
            let now = self.now;
            match w {
                Wire::Query(asker) => {
                    let reply = self.hosts[to].fed.as_ref().map(|f| {
                        let (version, body) = f.my_list();
                        FedInput::List {
                            host: self.hosts[to].name.clone(),
                            version,
                            body: body.to_vec(),
                        }
                    });
                    let answered = reply.is_some();
                    if let Some(r) = reply {
                        self.send(to, asker, Wire::Input(r));
                    }
                    // The query ends as Zenoh's does: after its replies.
                    let ended = FedInput::ListQueryEnded {
                        host: self.hosts[to].name.clone(),
                        answered,
                    };
                    self.send(to, asker, Wire::Input(ended));
                }
                Wire::Input(input) => {
                    let _ = from;
                    let host = &mut self.hosts[to];
                    let Host {
                        broker,
                        fed,
                        inboxes,
                        wire,
                        systems,
                        broker_pid,
                        ..
                    } = host;
                    if let (Some(b), Some(f)) = (broker.as_mut(), fed.as_mut()) {
                        let mut io = HostInboxes {
                            open: inboxes,
                            wire,
                            systems,
                            pid: *broker_pid,
                        };
                        f.handle(now, input, b, &mut io);
                    }
                }
            }
        }
        any
    }

    /// Delivers one frame on host `h`'s shared memory; whether there was one.
    fn deliver_one(&mut self, h: usize) -> bool {
        let now = self.now;
        let host = &mut self.hosts[h];
        let Some(frame) = host.wire.pop_front() else {
            return false;
        };
        let Host {
            broker,
            fed,
            inboxes,
            wire,
            systems,
            users,
            broker_pid,
            ..
        } = host;
        match frame {
            Frame::Broker(f) => {
                let msg: ToBroker = decode(&f).unwrap();
                if let (Some(b), Some(fc)) = (broker.as_mut(), fed.as_mut()) {
                    if !fc.intercept(now, &msg, |_, _| None) {
                        b.handle(now, msg);
                    }
                }
            }
            Frame::System(name, f, sender) => {
                if let Some(s) = systems.get_mut(&name) {
                    let msg: ToSystem = decode(&f).unwrap();
                    s.core.handle(msg);
                } else if inboxes.contains(&Address::System(name.clone())) {
                    if let (Some(b), Some(fc)) = (broker.as_ref(), fed.as_mut()) {
                        let mut io = HostInboxes {
                            open: inboxes,
                            wire,
                            systems,
                            pid: *broker_pid,
                        };
                        fc.inbox_frame(&Address::System(name), &f, Some(sender), b, &mut io);
                    }
                }
            }
            Frame::User(id, f, sender) => {
                if let Some(u) = users.get_mut(&id) {
                    let msg: ToUser = decode(&f).unwrap();
                    u.core.handle(msg);
                } else if inboxes.contains(&Address::User(id.clone())) {
                    if let (Some(b), Some(fc)) = (broker.as_ref(), fed.as_mut()) {
                        let mut io = HostInboxes {
                            open: inboxes,
                            wire,
                            systems,
                            pid: *broker_pid,
                        };
                        fc.inbox_frame(&Address::User(id), &f, Some(sender), b, &mut io);
                    }
                }
            }
        }
        true
    }

    /// Takes the outputs of host `h`'s cores; whether there were any.
    fn collect(&mut self, h: usize) -> bool {
        let now = self.now;
        let mut any = false;
        let mut sends: Vec<(String, Wire)> = Vec::new();
        let host = &mut self.hosts[h];
        let bpid = host.broker_pid;
        let up = host.broker.is_some();
        if let (Some(b), Some(f)) = (host.broker.as_mut(), host.fed.as_mut()) {
            while let Some(o) = b.poll_output() {
                any = true;
                let Some(o) = f.route(b, o) else { continue };
                match o {
                    Output::Granted(g) => {
                        if !g.user.is_foreign() {
                            let m = encode(&g.message()).unwrap();
                            host.wire.push_back(Frame::User(g.user.clone(), m, bpid));
                        }
                    }
                    Output::ToSystem(s, m) => {
                        host.wire
                            .push_back(Frame::System(s, encode(&m).unwrap(), bpid))
                    }
                    Output::ToUser(u, m) => {
                        host.wire
                            .push_back(Frame::User(u, encode(&m).unwrap(), bpid))
                    }
                    Output::WatchSystem { system, pid } => {
                        host.broker_watches
                            .entry(pid)
                            .or_default()
                            .insert(Address::System(system));
                    }
                    Output::WatchUser { user, pid } => {
                        host.broker_watches
                            .entry(pid)
                            .or_default()
                            .insert(Address::User(user));
                    }
                    Output::ForgetSystem(s) => {
                        let a = Address::System(s);
                        host.broker_watches.values_mut().for_each(|w| {
                            w.remove(&a);
                        });
                    }
                    Output::ForgetUser(u) => {
                        let a = Address::User(u);
                        host.broker_watches.values_mut().for_each(|w| {
                            w.remove(&a);
                        });
                    }
                }
            }
            let local = b.take_list_change_into(&mut host.core_views).is_some();
            if local || f.take_links_change() {
                let systems: Vec<&str> = b.systems().collect();
                host.local_views = f.publish_list(now, wall(now), &host.core_views, &systems);
            }
            f.take_list_change();
            while let Some(o) = f.poll_output() {
                any = true;
                match o {
                    FedOutput::Send { to, msg } => {
                        let users_side = msg.on_users_key();
                        let input = FedInput::Frame {
                            from: host.name.clone(),
                            users_side,
                            bytes: encode(&msg).unwrap(),
                        };
                        sends.push((to, Wire::Input(input)));
                    }
                    FedOutput::PutList { version, body } => {
                        let input = FedInput::List {
                            host: host.name.clone(),
                            version,
                            body,
                        };
                        sends.push((String::new(), Wire::Input(input)));
                    }
                    FedOutput::AnnounceList { version } => {
                        let input = FedInput::List {
                            host: host.name.clone(),
                            version,
                            body: Vec::new(),
                        };
                        sends.push((String::new(), Wire::Input(input)));
                    }
                    FedOutput::QueryList(to) => sends.push((to, Wire::Query(h))),
                    FedOutput::SystemUp(_) | FedOutput::SystemDown(_) => {}
                    FedOutput::Deliver(Delivery::Msg(u, m)) => {
                        host.wire
                            .push_back(Frame::User(u, encode(&m).unwrap(), bpid))
                    }
                    FedOutput::Deliver(Delivery::Grant(_)) => {}
                }
            }
        }
        for s in host.systems.values_mut() {
            loop {
                while let Some(o) = s.core.poll_output() {
                    any = true;
                    match o {
                        SystemOutput::ToBroker(m) if up => {
                            host.wire.push_back(Frame::Broker(encode(&m).unwrap()))
                        }
                        SystemOutput::ToUser(u, m) => {
                            host.wire
                                .push_back(Frame::User(u, encode(&m).unwrap(), s.pid))
                        }
                        SystemOutput::WatchUser(u, pid) => {
                            s.watches.entry(pid).or_default().insert(u);
                        }
                        SystemOutput::ForgetUser(u) => s.watches.values_mut().for_each(|w| {
                            w.remove(&u);
                        }),
                        _ => {}
                    }
                }
                let Some(ev) = s.core.poll_event() else { break };
                any = true;
                s.app.on_event(&mut s.core, now, ev);
            }
        }
        for (id, u) in host.users.iter_mut() {
            while let Some(o) = u.core.poll_output() {
                any = true;
                match o {
                    UserOutput::ToBroker(m) if up => {
                        host.wire.push_back(Frame::Broker(encode(&m).unwrap()))
                    }
                    UserOutput::ToSystem(s, m) => {
                        host.wire
                            .push_back(Frame::System(s, encode(&m).unwrap(), u.pid))
                    }
                    UserOutput::WatchSystem(s, pid) => {
                        u.watches.entry(pid).or_default().insert(s);
                    }
                    UserOutput::ForgetSystem(s) => u.watches.values_mut().for_each(|w| {
                        w.remove(&s);
                    }),
                    _ => {}
                }
            }
            while let Some(e) = u.core.poll_event() {
                any = true;
                host.events.entry(id.clone()).or_default().push(e);
            }
        }
        for (to, w) in sends {
            if to.is_empty() {
                // A publication: to every host whose session sees this one.
                let whole_list =
                    matches!(&w, Wire::Input(FedInput::List { body, .. }) if !body.is_empty());
                let peers: Vec<usize> = (0..self.hosts.len())
                    .filter(|x| *x != h && self.seen.contains(&(*x, h)))
                    .filter(|x| !(whole_list && self.deaf_to_lists.contains(x)))
                    .collect();
                for x in peers {
                    self.send(h, x, w.clone());
                }
            } else if let Some(x) = self.hosts.iter().position(|o| o.name == to) {
                self.send(h, x, w);
            }
        }
        any
    }

    /// The next deadline of anything in the world.
    fn next_deadline(&self) -> Option<Duration> {
        let mut t: Vec<Duration> = Vec::new();
        for host in &self.hosts {
            t.extend(host.broker.as_ref().and_then(Broker::poll_timeout));
            t.extend(host.fed.as_ref().and_then(FedCore::poll_timeout));
            t.extend(
                host.systems
                    .values()
                    .filter_map(|s| s.app.next_tick(&s.core)),
            );
        }
        t.extend(self.inflight.keys().next().map(|(at, _)| *at));
        t.extend(
            self.cuts
                .values()
                .filter(|c| !c.down)
                .map(|c| c.since + self.lease),
        );
        t.into_iter().min()
    }

    /// Advances the clock to `until`, running every deadline on the way.
    pub fn run_until(&mut self, until: Duration) {
        let mut spins = 0u32;
        loop {
            match self.next_deadline() {
                Some(t) if t <= until => {
                    if t <= self.now {
                        spins += 1;
                        assert!(spins < 10_000, "a deadline at {t:?} is never handled");
                    } else {
                        spins = 0;
                    }
                    self.now = self.now.max(t);
                    let now = self.now;
                    // Links cut past the lease go down: what they held is lost.
                    let lease = self.lease;
                    let mut went_down = Vec::new();
                    for (k, c) in self.cuts.iter_mut() {
                        if !c.down && c.since + lease <= now {
                            c.down = true;
                            went_down.push(*k);
                        }
                    }
                    if !went_down.is_empty() {
                        let before = self.held.len();
                        self.held
                            .retain(|(f, t, _)| !went_down.contains(&pair(*f, *t)));
                        self.lost += (before - self.held.len()) as u64;
                        self.reconcile_tokens();
                    }
                    for host in self.hosts.iter_mut() {
                        if let Some(b) = host.broker.as_mut() {
                            if b.poll_timeout().is_some_and(|bt| bt <= now) {
                                b.handle_timeout(now);
                            }
                        }
                        let Host {
                            broker,
                            fed,
                            inboxes,
                            wire,
                            systems,
                            broker_pid,
                            ..
                        } = host;
                        if let (Some(b), Some(f)) = (broker.as_mut(), fed.as_mut()) {
                            if f.poll_timeout().is_some_and(|ft| ft <= now) {
                                let mut io = HostInboxes {
                                    open: inboxes,
                                    wire,
                                    systems,
                                    pid: *broker_pid,
                                };
                                f.handle_timeout(now, b, &mut io);
                            }
                        }
                        for s in host.systems.values_mut() {
                            if s.app.next_tick(&s.core).is_some_and(|st| st <= now) {
                                s.app.on_tick(&mut s.core, now);
                            }
                        }
                    }
                    self.settle();
                }
                _ => {
                    self.now = until;
                    return;
                }
            }
        }
    }

    /// Runs for `d` more.
    pub fn run_for(&mut self, d: Duration) {
        let until = self.now + d;
        self.run_until(until);
    }
}

mod scenarios;
