//! The federation's logic, with no Zenoh, thread or clock inside: a sans-IO core.
//!
//! [`FedCore`] takes what comes from the other hosts ([`FedCore::handle`]: a host's
//! token up or down, its list, a frame), what this host's users and systems do
//! ([`FedCore::intercept`], [`FedCore::route`], [`FedCore::inbox_frame`], the `gone`
//! calls) and the time ([`FedCore::handle_timeout`]), and gives back what to do
//! ([`FedCore::poll_output`]: frames for other hosts, this host's list to publish, lists
//! to ask for, systems' tokens, frames for local users). The shared-memory inboxes it
//! keeps for peers on other hosts are behind [`Inboxes`]. Time is a [`Duration`] on the
//! caller's clock, so the same core runs under Zenoh (`driver.rs`) and on the virtual
//! clock of `tests/harness.rs`.

use super::{valid_host_name, Acl, Delivery, FarGrant, FedMsg, FedStats, HeldSession, Role};
use crate::core::{Broker, Output};
use muster_shared::names::Address;
use muster_shared::protocol::{decode, LinkInfo, RemoteContact, ToBroker, ToSystem, ToUser};
use muster_shared::snapshot::{ServiceView, DEFAULT_MAX_SERVICES};
use muster_shared::types::{
    check_name, EndReason, Refusal, ServiceId, SessionId, UserId, MAX_SERVICE_NAME, MAX_SYSTEM_NAME,
};
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

/// Longest user id accepted from another host (before `@host` is added).
pub const MAX_FOREIGN_USER: usize = 64;
/// Most users of other hosts this broker serves at once.
pub const MAX_FOREIGN_USERS: usize = 1024;
/// Most users of any one other host this broker serves at once: one host cannot take
/// every place.
pub const MAX_FOREIGN_USERS_PER_HOST: usize = MAX_FOREIGN_USERS / 2;
/// Most requests of other hosts' remote users waiting here for their offer at once.
const MAX_CONTACTS: usize = 16 * 1024;
/// The same, from any one host.
const MAX_CONTACTS_PER_HOST: usize = MAX_CONTACTS / 2;
/// Most services taken from one host's list (a broker lists at most this many of its
/// own).
pub const MAX_SERVICES_PER_HOST: usize = DEFAULT_MAX_SERVICES;
/// Most links of other hosts' users over this host's services counted at once.
const MAX_LINKS_IN: usize = 16 * 1024;
/// A query for a host's list that ended unanswered ([`FedInput::ListQueryEnded`]) is
/// made again this long after, the wait doubling up to [`LIST_RETRY_MAX`]. A query is
/// never made again while one is out: under load a reply takes long, and asking again
/// on a timer (every 250 ms, as it once did) piled up copies of every list, until a
/// hundred hosts starting together never got theirs.
const LIST_RETRY_FIRST: Duration = Duration::from_millis(250);
const LIST_RETRY_MAX: Duration = Duration::from_secs(4);
/// How long a query for a list waits for its reply. Longer than Zenoh's default
/// (10 s): when a hundred hosts start together, replies take seconds, and one that
/// came after its query ended was thrown away and asked for again (26,000 such ends
/// in one start of 100 hosts), which loaded every host more.
pub const LIST_QUERY_TIMEOUT: Duration = Duration::from_secs(30);
/// A query out this long with no end heard (its driver lost it) is taken to have ended
/// unanswered.
const LIST_QUERY_OUT: Duration = LIST_QUERY_TIMEOUT.saturating_add(Duration::from_secs(2));
/// Each broker says which version its list is at ([`FedOutput::AnnounceList`], a few
/// bytes), at least this often: a peer that missed a publication (made before the
/// peer's subscription was known there, so it went nowhere) sees it is behind and asks
/// for the list. Such misses come when hosts join, so a host that sees another join
/// announces [`LIST_ANNOUNCE_FIRST`] later, then ever more rarely, back to this. The
/// list itself goes out only when it changes: publishing it whole every 2 s cost a
/// federation of N hosts N² lists every 2 s (30 hosts of 100 services: 10.8 MB/s on
/// loopback while idle), and announcing every 2 s N² messages.
pub const LIST_REFRESH: Duration = Duration::from_secs(30);
/// The first announcement after a host joined; each next one twice as late, up to
/// [`LIST_REFRESH`].
pub const LIST_ANNOUNCE_FIRST: Duration = Duration::from_millis(500);
/// A host announces soon after another joined only if its own list was put within this
/// long of the join (before or after): only such a put can have gone nowhere for the
/// newcomer, whose query at its start got the list as it was. (When a hundred hosts
/// start together, announcing after every join would keep every host announcing twice
/// a second the whole time.)
const LIST_ANNOUNCE_WINDOW: Duration = Duration::from_secs(5);
/// A request out on another host that has had no answer (queued, granted or refused)
/// this long is sent again, the wait doubling up to [`REQUEST_RETRY_MAX`]: a put made
/// before the network knew the peer's subscription went nowhere, and so did its answer
/// if the way back was not known yet. The peer takes a repeat as the same request (its
/// broker answers a pending one once, its system a granted one with the same session).
const REQUEST_RETRY_FIRST: Duration = Duration::from_secs(1);
const REQUEST_RETRY_MAX: Duration = Duration::from_secs(4);
/// How long a host with a standby whose token went is waited for before its services,
/// requests and sessions end here: a broker that dies and is taken over by its standby
/// comes back within it (its token goes and comes), and the sessions it relayed go on.
/// A host without a standby is gone at once.
pub const HOST_GRACE: Duration = Duration::from_secs(5);
/// How long after taking over a broker resumes, from other hosts' [`FedMsg::Held`], the
/// sessions of its users there that it does not know yet (its predecessor relayed them).
const RESUME_WINDOW: Duration = Duration::from_secs(10);
/// A host whose standby token went this long before its broker's token is still taken
/// to have had a standby (a killed broker's tokens go together, in any order).
const STANDBY_SLACK: Duration = Duration::from_secs(1);
/// Most sessions in one [`FedMsg::Held`] part.
const HELD_PART: usize = 256;

/// What comes from the other hosts.
#[derive(Clone, Debug, PartialEq)]
pub enum FedInput {
    /// A host's broker token came (`true`) or went (`false`).
    Alive(String, bool),
    /// A host's standby token came or went: its broker has a standby in sync beside it.
    Standby(String, bool),
    /// A host's list: its version (0: none given, always taken) and its JSON body; or,
    /// with an empty body, only the version it is at ([`FedOutput::AnnounceList`]).
    List {
        /// The host.
        host: String,
        /// Its version: rising with each change.
        version: u64,
        /// A JSON array of [`ServiceView`], or nothing.
        body: Vec<u8>,
    },
    /// A query for a host's list ([`FedOutput::QueryList`]) ended, with the list
    /// (`answered`) or without it (the host's queryable not known yet, or it timed out).
    ListQueryEnded {
        /// The host asked.
        host: String,
        /// Whether a list came.
        answered: bool,
    },
    /// A frame from a host, as it came: on its users' key (`req`, `users_side`) or on
    /// its systems' (`in`).
    Frame {
        /// The host.
        from: String,
        /// Whether it came on the users' key.
        users_side: bool,
        /// The encoded [`FedMsg`].
        bytes: Vec<u8>,
    },
}

/// What the core asks of its driver.
#[derive(Clone, Debug, PartialEq)]
pub enum FedOutput {
    /// A frame for host `to` (on its `req/` key if [`FedMsg::on_users_key`], else `in/`).
    Send {
        /// The host.
        to: String,
        /// The frame.
        msg: FedMsg,
    },
    /// This host's list, to publish (and to answer queries with from now on).
    PutList {
        /// Its version.
        version: u64,
        /// A JSON array of [`ServiceView`].
        body: Vec<u8>,
    },
    /// Say which version this host's list is at (on the list's key, with no body):
    /// hosts that have an older one ask for it.
    AnnounceList {
        /// The version of the list last put.
        version: u64,
    },
    /// Ask host `0` for its list (it comes as [`FedInput::List`]).
    QueryList(String),
    /// A system registered here: declare its token.
    SystemUp(String),
    /// A system gone from here: withdraw its token.
    SystemDown(String),
    /// A frame for a local user.
    Deliver(Delivery),
}

/// The shared-memory inboxes the core keeps for peers on other hosts: for each user of
/// another host served here (`Address::User("alice@a")`), and for each system of
/// another host that local users hold sessions with (`Address::System("t1@b")`). What
/// local processes write into one comes back through [`FedCore::inbox_frame`]. (The
/// driver keeps one inbox for all the users of a host, that host's relay
/// ([`Address::Relay`]), and hands back each frame with the user it names; the core
/// opens and closes per user all the same.)
pub trait Inboxes {
    /// Opens the inbox of `peer`.
    fn open(&mut self, peer: &Address) -> Result<(), String>;
    /// Closes it (frames just written through it may still be read for a while).
    fn close(&mut self, peer: &Address);
    /// Writes `msg` for local process `to` through `peer`'s inbox (as sent by `peer`).
    fn send(&mut self, peer: &Address, to: &Address, msg: &ToSystem);
    /// The pid of the process owning `of`'s port, as `peer`'s inbox sees it.
    fn owner_pid(&mut self, peer: &Address, of: &Address) -> Option<u32>;
}

/// Messages awaiting an answer, each sent again when its wait is over, the wait
/// doubling from `first` up to `max`.
pub(super) struct Retries<K, M> {
    first: Duration,
    max: Duration,
    /// key → (message, when it is next sent, the wait after that).
    waiting: BTreeMap<K, (M, Duration, Duration)>,
}

impl<K: Ord + Clone, M: Clone> Retries<K, M> {
    pub(super) fn new(first: Duration, max: Duration) -> Self {
        Retries {
            first,
            max,
            waiting: BTreeMap::new(),
        }
    }

    /// `msg` was sent for `key` at `now` (a new send starts the waits again).
    pub(super) fn sent(&mut self, key: K, msg: M, now: Duration) {
        let next = (self.first * 2).min(self.max);
        self.waiting.insert(key, (msg, now + self.first, next));
    }

    /// `key` has its answer: no more sends.
    pub(super) fn answered(&mut self, key: &K) {
        self.waiting.remove(key);
    }

    /// Keeps only the keys `keep` says still wait.
    pub(super) fn retain(&mut self, mut keep: impl FnMut(&K) -> bool) {
        self.waiting.retain(|k, _| keep(k));
    }

    /// When the next send is due.
    pub(super) fn next_due(&self) -> Option<Duration> {
        self.waiting.values().map(|(_, t, _)| *t).min()
    }

    /// The messages due at `now`, in key order; each is due again after its next wait.
    pub(super) fn due(&mut self, now: Duration) -> Vec<(K, M)> {
        let max = self.max;
        self.waiting
            .iter_mut()
            .filter(|(_, (_, t, _))| *t <= now)
            .map(|(k, (m, t, wait))| {
                *t = now + *wait;
                *wait = (*wait * 2).min(max);
                (k.clone(), m.clone())
            })
            .collect()
    }
}

/// A local user's request out on another host: which host, for which service (as that
/// host knows it). Only that host's answers, for that service, are taken.
#[derive(Clone, Debug, PartialEq)]
struct Asked {
    host: String,
    service: ServiceId,
}

impl Asked {
    fn on(&self, host: &str) -> bool {
        self.host == host
    }
}

/// A user of another host that this host serves.
struct Foreign {
    /// Whether it has an inbox here (not a remote user of its host: its sessions run
    /// over UDP, and the broker's frames for it are relayed from the core's outputs).
    inbox: bool,
    host: String,
    /// Its sessions here: session → (system, the system's pid).
    sessions: BTreeMap<SessionId, (String, u32)>,
}

/// One broker's part of a federation: what it knows of the other hosts, and of the
/// requests, sessions and links between them and this host.
pub struct FedCore {
    host: String,
    pid: u32,
    /// This host's list as last published: its version and body.
    my_list: (u64, Vec<u8>),
    /// When this host next announces its list's version, and the wait after that
    /// ([`LIST_ANNOUNCE_FIRST`] doubling to [`LIST_REFRESH`]).
    next_refresh: Duration,
    announce_wait: Duration,
    /// When this host last put its list, and last saw another host join.
    last_put: Option<Duration>,
    last_join: Option<Duration>,
    /// The version of each host's list taken.
    list_versions: HashMap<String, u64>,
    alive: BTreeSet<String>,
    lists: BTreeMap<String, Vec<ServiceView>>,
    list_changed: bool,
    /// Requests of local users out on other hosts: (user, req) → host.
    outstanding: BTreeMap<(UserId, u64), Asked>,
    /// Those of them with no answer yet, and when each is sent again.
    unanswered: Retries<(UserId, u64), FedMsg>,
    /// Sessions of local users on other hosts: (user, session) → host.
    far: BTreeMap<(UserId, SessionId), String>,
    /// Other hosts' systems (`system@host`) with an inbox here, for local users' input
    /// and ends.
    systems: BTreeSet<String>,
    /// Users of other hosts served here (`user@host`).
    foreign: BTreeMap<UserId, Foreign>,
    /// Contacts of other hosts' remote users for their requests here, given to the
    /// system with the offer: (`user@host`, req) → contact.
    contacts: HashMap<(UserId, u64), RemoteContact>,
    /// Local users' links over other hosts' services: (user, link) → the link.
    links_out: BTreeMap<(UserId, u64), LinkInfo>,
    /// Other hosts' users' links over services here: (`user@host`, link) → services.
    links_in: BTreeMap<(UserId, u64), Vec<ServiceId>>,
    /// Whether `links_in` changed since the list was last written.
    links_changed: bool,
    /// The address other hosts' remote users reach this host's systems at, for a
    /// system listening on every address (from `--listen`).
    advertise: Option<IpAddr>,
    /// Hosts whose list was asked for and has not come: when to ask again (while a
    /// query is out, when to give it up: [`LIST_QUERY_OUT`]), and the wait after an
    /// unanswered one. (A query made as a host's token arrives can reach it before its
    /// list's queryable is known here, and go unanswered.)
    list_asked: BTreeMap<String, (Duration, Duration)>,
    /// Systems whose token is declared.
    system_tokens: BTreeSet<String>,
    /// Hosts whose token went, and until when they are waited for ([`HOST_GRACE`]).
    away: BTreeMap<String, Duration>,
    /// Hosts with a standby: `None` while its token is up, else when it went.
    standbys: BTreeMap<String, Option<Duration>>,
    /// Hosts asked which sessions of this host's users they hold ([`FedMsg::Resync`]),
    /// until their last [`FedMsg::Held`] part comes.
    resync: Retries<String, FedMsg>,
    /// The sessions a host has said it holds so far in its answer.
    held_seen: BTreeMap<String, BTreeSet<(UserId, SessionId)>>,
    /// Until when sessions others hold for this host's users are resumed though not
    /// known here (this broker took over: [`FedCore::take_over`]).
    resume_until: Option<Duration>,
    stats: FedStats,
    /// The federation's access file, if it has one.
    acl: Option<Acl>,
    out: VecDeque<FedOutput>,
}

impl FedCore {
    /// The core of host `host`, whose broker runs as `pid` (the pid other hosts' users
    /// have here), at `now`. `advertise`: the address this host's systems are reached
    /// at by other hosts' remote users when they listen on every address.
    pub fn new(
        host: &str,
        pid: u32,
        acl: Option<Acl>,
        advertise: Option<IpAddr>,
        now: Duration,
    ) -> Self {
        FedCore {
            host: host.to_string(),
            pid,
            my_list: (0, b"[]".to_vec()),
            next_refresh: now + LIST_ANNOUNCE_FIRST,
            announce_wait: LIST_ANNOUNCE_FIRST,
            last_put: None,
            last_join: None,
            list_versions: HashMap::new(),
            alive: BTreeSet::new(),
            lists: BTreeMap::new(),
            list_changed: false,
            outstanding: BTreeMap::new(),
            unanswered: Retries::new(REQUEST_RETRY_FIRST, REQUEST_RETRY_MAX),
            far: BTreeMap::new(),
            systems: BTreeSet::new(),
            foreign: BTreeMap::new(),
            contacts: HashMap::new(),
            links_out: BTreeMap::new(),
            links_in: BTreeMap::new(),
            links_changed: false,
            advertise,
            list_asked: BTreeMap::new(),
            system_tokens: BTreeSet::new(),
            away: BTreeMap::new(),
            standbys: BTreeMap::new(),
            resync: Retries::new(REQUEST_RETRY_FIRST, REQUEST_RETRY_MAX),
            held_seen: BTreeMap::new(),
            resume_until: None,
            stats: FedStats::default(),
            acl,
            out: VecDeque::new(),
        }
    }

    /// Whether the access file (if any) gives `host` `role`.
    pub fn may(&self, host: &str, role: Role) -> bool {
        self.acl.as_ref().is_none_or(|a| a.allows(host, role))
    }

    /// This host's name.
    pub fn host(&self) -> &str {
        &self.host
    }

    /// The counters.
    pub fn stats(&self) -> &FedStats {
        &self.stats
    }

    /// Counts `n` frames or lists dropped before they reached the core (too big, or
    /// over the driver's budget).
    pub fn count_dropped(&mut self, n: u64) {
        self.stats.dropped += n;
    }

    /// This host's list as last published (version 0: none yet), for queries.
    pub fn my_list(&self) -> (u64, &[u8]) {
        (self.my_list.0, &self.my_list.1)
    }

    /// The hosts whose broker is up, as far as this one knows.
    pub fn hosts(&self) -> impl Iterator<Item = &str> {
        self.alive.iter().map(String::as_str)
    }

    /// The next output.
    pub fn poll_output(&mut self) -> Option<FedOutput> {
        self.out.pop_front()
    }

    /// When [`FedCore::handle_timeout`] is next due.
    pub fn poll_timeout(&self) -> Option<Duration> {
        self.list_asked
            .values()
            .map(|(t, _)| *t)
            .chain(self.away.values().copied())
            .chain(self.resync.next_due())
            .chain(self.unanswered.next_due())
            .chain(std::iter::once(self.next_refresh))
            .min()
    }

    /// Asks again for lists that have not come, sends again requests with no answer,
    /// publishes this host's list again when it is time, and gives up on hosts gone
    /// longer than [`HOST_GRACE`].
    pub fn handle_timeout(&mut self, now: Duration, core: &mut Broker, inboxes: &mut dyn Inboxes) {
        let gone: Vec<String> = self
            .away
            .iter()
            .filter(|(_, t)| **t <= now)
            .map(|(h, _)| h.clone())
            .collect();
        for host in gone {
            self.away.remove(&host);
            self.host_lost(&host, core, inboxes, now);
        }
        let alive = &self.alive;
        self.resync.retain(|h| alive.contains(h));
        for (host, msg) in self.resync.due(now) {
            self.send(&host, msg);
        }
        if now >= self.next_refresh {
            self.announce_wait = (self.announce_wait * 2).min(LIST_REFRESH);
            self.next_refresh = now + self.announce_wait;
            if self.my_list.0 > 0 && self.may(&self.host, Role::Offer) {
                self.out.push_back(FedOutput::AnnounceList {
                    version: self.my_list.0,
                });
            }
        }
        let outstanding = &self.outstanding;
        self.unanswered.retain(|k| outstanding.contains_key(k));
        for (key, msg) in self.unanswered.due(now) {
            if let Some(host) = self.outstanding.get(&key).map(|a| a.host.clone()) {
                self.stats.requests_resent += 1;
                tracing::debug!(user = %key.0, req = key.1, host, "federation: a request with no answer, sent again");
                self.send(&host, msg);
            }
        }
        let due: Vec<String> = self
            .list_asked
            .iter()
            .filter(|(h, (t, _))| *t <= now && self.alive.contains(*h))
            .map(|(h, _)| h.clone())
            .collect();
        self.list_asked.retain(|h, _| self.alive.contains(h));
        for host in due {
            self.out.push_back(FedOutput::QueryList(host.clone()));
            if let Some((t, _)) = self.list_asked.get_mut(&host) {
                *t = now + LIST_QUERY_OUT;
            }
        }
    }

    /// This broker took over its host from a broker that died (a standby, with the
    /// core's state): the users of other hosts that one served are served on, their
    /// sessions relayed again (their inboxes opened anew), and their hosts waited for
    /// ([`HOST_GRACE`]); sessions of this host's users on other hosts are resumed as
    /// those hosts say they hold them ([`FedMsg::Held`]).
    pub fn take_over(&mut self, now: Duration, core: &mut Broker, inboxes: &mut dyn Inboxes) {
        self.resume_until = Some(now + RESUME_WINDOW);
        let theirs: Vec<UserId> = core.users().filter(|u| u.is_foreign()).cloned().collect();
        for u in theirs {
            let host = host_of_foreign(&u)
                .filter(|h| valid_host_name(h) && *h != self.host)
                .map(str::to_string);
            let inbox = core.user_pid(&u).is_some_and(|p| p != 0);
            let opened = !inbox || open_inbox(inboxes, &Address::User(u.clone())).is_some();
            let (Some(host), true) = (host, opened) else {
                core.revoke(now, &u);
                continue;
            };
            let sessions = core
                .user_sessions(&u)
                .into_iter()
                .map(|(s, system, pid)| (s, (system, pid)))
                .collect();
            self.away.entry(host.clone()).or_insert(now + HOST_GRACE);
            self.foreign.insert(
                u,
                Foreign {
                    inbox,
                    host,
                    sessions,
                },
            );
        }
    }

    /// This host's services for its list and the other hosts': the core's `views` with
    /// the other hosts' users' links over them counted. Published (with `systems`'
    /// tokens kept in step) when the host may offer; `wall_ns` (Unix ns) gives the
    /// list's version, kept rising.
    pub fn publish_list(
        &mut self,
        now: Duration,
        wall_ns: u64,
        views: &[ServiceView],
        systems: &[&str],
    ) -> Vec<ServiceView> {
        let n = self.links_in();
        let mine: Vec<ServiceView> = views
            .iter()
            .map(|v| ServiceView {
                links: v
                    .links
                    .saturating_add(n.get(v.id.as_str()).copied().unwrap_or(0)),
                ..v.clone()
            })
            .collect();
        if !self.may(&self.host, Role::Offer) {
            return mine;
        }
        let published: Vec<ServiceView> = mine
            .iter()
            .map(|v| ServiceView {
                host: self.host.clone(),
                ..v.clone()
            })
            .collect();
        let body = serde_json::to_vec(&published).unwrap_or_else(|_| b"[]".to_vec());
        // The same list again (a change of what other hosts are not shown) is not put:
        // every host would take and read it anew.
        if self.my_list.0 == 0 || body != self.my_list.1 {
            let version = wall_ns.max(self.my_list.0 + 1);
            self.my_list = (version, body.clone());
            self.out.push_back(FedOutput::PutList { version, body });
            // A host that joined just before may not have been subscribed yet.
            self.last_put = Some(now);
            if self
                .last_join
                .is_some_and(|t| now <= t + LIST_ANNOUNCE_WINDOW)
            {
                self.announce_soon(now);
            }
        }
        let want: BTreeSet<&str> = systems.iter().copied().collect();
        let gone: Vec<String> = self
            .system_tokens
            .iter()
            .filter(|s| !want.contains(s.as_str()))
            .cloned()
            .collect();
        for s in gone {
            self.system_tokens.remove(&s);
            self.out.push_back(FedOutput::SystemDown(s));
        }
        for s in want {
            if self.system_tokens.insert(s.to_string()) {
                self.out.push_back(FedOutput::SystemUp(s.to_string()));
            }
        }
        mine
    }

    /// The other hosts' services, for the merged list.
    pub fn remote_views(&self) -> impl Iterator<Item = &ServiceView> {
        self.lists
            .iter()
            .filter(|(h, _)| self.listed(h))
            .flat_map(|(_, v)| v.iter())
    }

    /// This host's services (`local`) and the other hosts', in id order, at most `cap`:
    /// this host's first, then the places left shared fairly among the other hosts
    /// (each host gets as many as it lists, up to an even share of what is left, the
    /// share of hosts listing fewer going to those listing more), each host's first
    /// services by id. A host listing hundreds cannot push the others out.
    pub fn merged_views<'a>(
        &'a self,
        local: &'a [ServiceView],
        cap: usize,
    ) -> Vec<&'a ServiceView> {
        let total = local.len() + self.remote_views().count();
        if total > cap {
            tracing::warn!(
                total,
                "the global list holds more services than the {cap} the shared list can: each host gets a fair share"
            );
        }
        let hosts = self
            .lists
            .iter()
            .filter(|(h, _)| self.listed(h))
            .map(|(_, v)| v.as_slice());
        merge_fairly(local, hosts, cap)
    }

    /// Whether `host`'s services are listed: its broker is up, or was until less than
    /// [`HOST_GRACE`] ago.
    fn listed(&self, host: &str) -> bool {
        self.alive.contains(host) || self.away.contains_key(host)
    }

    /// Whether the other hosts' services changed since the last call.
    pub fn take_list_change(&mut self) -> bool {
        std::mem::take(&mut self.list_changed)
    }

    fn send(&mut self, to: &str, msg: FedMsg) {
        self.stats.sent += 1;
        self.out.push_back(FedOutput::Send {
            to: to.to_string(),
            msg,
        });
    }

    /// A local user's session on another host is gone with it (that host left, or no
    /// longer holds it): counted, and the user told.
    fn far_session_lost(&mut self, user: UserId, session: SessionId) {
        self.stats.sessions_lost += 1;
        let m = ToUser::Ended {
            session,
            reason: EndReason::PeerGone,
            last_seq: 0,
        };
        self.deliver_msg(user, m);
    }

    fn deliver_msg(&mut self, user: UserId, msg: ToUser) {
        self.out
            .push_back(FedOutput::Deliver(Delivery::Msg(user, msg)));
    }

    /// A local user's request or cancel for another host's service: passed on, and
    /// `true`. Anything else: `false` (the core handles it). `contact` gives a remote
    /// (UDP) user's address and a fresh session key for the request, `None` for a
    /// user on shared memory; it is asked only for a request passed on.
    pub fn intercept(
        &mut self,
        now: Duration,
        msg: &ToBroker,
        contact: impl FnOnce(&UserId, u64) -> Option<RemoteContact>,
    ) -> bool {
        match msg {
            ToBroker::Request { user, req, service } => {
                let Some((host, there)) = service.remote() else {
                    return false;
                };
                let host = host.to_string();
                let refusal = if !self.may(&self.host, Role::Request) {
                    Some(Refusal::BadRequest(format!(
                        "host {} may not request other hosts' services (the federation's access file)",
                        self.host
                    )))
                } else if !self.listed(&host) {
                    Some(Refusal::Unknown)
                } else {
                    None
                };
                if let Some(reason) = refusal {
                    self.deliver_msg(user.clone(), ToUser::Refused { req: *req, reason });
                    return true;
                }
                self.outstanding.insert(
                    (user.clone(), *req),
                    Asked {
                        host: host.clone(),
                        service: there.clone(),
                    },
                );
                self.stats.requests_out += 1;
                let remote = contact(user, *req);
                let m = FedMsg::Request {
                    user: user.clone(),
                    req: *req,
                    service: there,
                    remote,
                };
                self.send(&host, m.clone());
                self.unanswered.sent((user.clone(), *req), m, now);
                true
            }
            ToBroker::Cancel { user, req } => {
                let Some(Asked { host, .. }) = self.outstanding.remove(&(user.clone(), *req))
                else {
                    return false;
                };
                let m = FedMsg::Cancel {
                    user: user.clone(),
                    req: *req,
                };
                self.send(&host, m);
                true
            }
            ToBroker::Goodbye { user } => {
                self.local_user_gone(user);
                false
            }
            // Links: the core counts this host's services; the other hosts theirs.
            ToBroker::LinkOpened { user, link } => {
                self.link_out(user, Some(link.clone()), link.link);
                false
            }
            ToBroker::LinkClosed { user, link } => {
                self.link_out(user, None, *link);
                false
            }
            ToBroker::Hello { user, links, .. } => {
                // A user saying hello again states its links anew.
                let old: Vec<u64> = self
                    .links_out
                    .range((user.clone(), 0)..=(user.clone(), u64::MAX))
                    .map(|((_, l), _)| *l)
                    .filter(|l| !links.iter().any(|n| n.link == *l))
                    .collect();
                for l in old {
                    self.link_out(user, None, l);
                }
                for l in links {
                    self.link_out(user, Some(l.clone()), l.link);
                }
                false
            }
            _ => false,
        }
    }

    /// A local user's link `number` opened as `link` (or changed), or closed (`None`):
    /// the hosts of its services hear of it.
    fn link_out(&mut self, user: &UserId, link: Option<LinkInfo>, number: u64) {
        let hosts_of = |l: &LinkInfo| -> BTreeMap<String, Vec<ServiceId>> {
            let mut by = BTreeMap::<String, Vec<ServiceId>>::new();
            for id in [&l.data, &l.command] {
                if let Some((h, there)) = id.remote() {
                    by.entry(h.to_string()).or_default().push(there);
                }
            }
            by
        };
        let key = (user.clone(), number);
        let now = link.as_ref().map(hosts_of).unwrap_or_default();
        if let Some(old) = self.links_out.remove(&key) {
            for h in hosts_of(&old).into_keys().filter(|h| !now.contains_key(h)) {
                let m = FedMsg::Link {
                    user: user.clone(),
                    link: number,
                    services: Vec::new(),
                    open: false,
                };
                self.send(&h, m);
            }
        }
        let Some(link) = link.filter(|_| !now.is_empty()) else {
            return;
        };
        for (h, services) in now {
            let m = FedMsg::Link {
                user: user.clone(),
                link: number,
                services,
                open: true,
            };
            self.send(&h, m);
        }
        self.links_out.insert(key, link);
    }

    /// Takes the core's outputs that concern other hosts' users: drops watching their
    /// process (the pid is this broker's own), gives a remote user's contact to the
    /// system with the offer, and relays the grant and the broker's frames for a
    /// remote user (who has no inbox here) to its host. Gives back the rest.
    pub fn route(&mut self, core: &Broker, out: Output) -> Option<Output> {
        match out {
            Output::WatchUser { ref user, .. } if user.is_foreign() => None,
            Output::ToSystem(system, mut offer @ ToSystem::Offer { remote: None, .. }) => {
                if let ToSystem::Offer {
                    user, req, remote, ..
                } = &mut offer
                {
                    *remote = self.contacts.get(&(user.clone(), *req)).cloned();
                }
                Some(Output::ToSystem(system, offer))
            }
            Output::Granted(g) if self.contacts.contains_key(&(g.user.clone(), g.req)) => {
                self.contacts.remove(&(g.user.clone(), g.req));
                let system = g.system()?;
                let addr = core.system_udp(&system).map(|a| self.reachable(a));
                let f = self.foreign.get_mut(&g.user)?;
                let host = f.host.clone();
                let home = local_part(&g.user);
                let msg = match addr {
                    Some(system_addr) => {
                        f.sessions.insert(g.session, (system, 0));
                        FedMsg::Granted(FarGrant {
                            user: home,
                            ..FarGrant::new(g, system_addr)
                        })
                    }
                    // The system dropped its UDP endpoint (re-registered without one)
                    // after the request came: the session it opened lapses unheard.
                    None => FedMsg::ToUser {
                        user: home,
                        msg: ToUser::Refused {
                            req: g.req,
                            reason: Refusal::BadRequest(format!(
                                "{} is on a system without a UDP endpoint: local users only",
                                g.service
                            )),
                        },
                    },
                };
                self.send(&host, msg);
                None
            }
            // A user of another host with an inbox here: its grant goes to its host
            // (whose broker passes it on), and the session's frames come from this
            // system's process.
            Output::Granted(g) if self.foreign.get(&g.user).is_some_and(|f| f.inbox) => {
                let f = self.foreign.get_mut(&g.user)?;
                f.sessions.insert(g.session, (g.system()?, g.system_pid));
                let host = f.host.clone();
                let (user, msg) = (local_part(&g.user), g.message());
                self.send(&host, FedMsg::ToUser { user, msg });
                None
            }
            Output::ToUser(user, msg) if self.foreign.get(&user).is_some_and(|f| !f.inbox) => {
                if let ToUser::Refused { req, .. } = &msg {
                    self.contacts.remove(&(user.clone(), *req));
                }
                if matches!(msg, ToUser::Welcome { .. }) {
                    return None;
                }
                let host = self.foreign.get(&user)?.host.clone();
                let user = local_part(&user);
                self.send(&host, FedMsg::ToUser { user, msg });
                None
            }
            o => Some(o),
        }
    }

    /// A frame that goes right behind grant `session` to `user`, a user of another
    /// host (a latched service's update 0): on the same way as the grant, so it comes
    /// after it. Nothing if no grant of that session went to that host.
    pub fn follow_grant(&mut self, user: &UserId, session: SessionId, msg: ToUser) {
        let Some(f) = self.foreign.get(user) else {
            return;
        };
        if !f.sessions.contains_key(&session) {
            return;
        }
        let host = f.host.clone();
        let user = local_part(user);
        self.send(&host, FedMsg::ToUser { user, msg });
    }

    /// A system's UDP address as other hosts' users reach it: a system listening on
    /// every address is reached at the address this broker listens on, if it names one.
    fn reachable(&self, addr: &str) -> String {
        match (addr.parse::<SocketAddr>(), self.advertise) {
            (Ok(a), Some(ip)) if a.ip().is_unspecified() => {
                SocketAddr::new(ip, a.port()).to_string()
            }
            _ => addr.to_string(),
        }
    }

    /// A local user died or left: the hosts holding its requests or sessions hear of it.
    pub fn local_user_gone(&mut self, user: &UserId) {
        let mut hosts = BTreeSet::new();
        self.outstanding.retain(|(u, _), a| {
            if u == user {
                hosts.insert(a.host.clone());
            }
            u != user
        });
        self.far.retain(|(u, _), h| {
            if u == user {
                hosts.insert(h.clone());
            }
            u != user
        });
        self.links_out.retain(|(u, _), l| {
            if u == user {
                for id in [&l.data, &l.command] {
                    if let Some((h, _)) = id.remote() {
                        hosts.insert(h.to_string());
                    }
                }
            }
            u != user
        });
        for h in hosts {
            self.send(&h, FedMsg::UserGone { user: user.clone() });
        }
    }

    /// A local system died: the other hosts' users of its sessions are told.
    pub fn local_system_gone(&mut self, system: &str) {
        let mut ends = Vec::new();
        for (u, f) in self.foreign.iter_mut() {
            f.sessions.retain(|s, (sys, _)| {
                if sys == system {
                    ends.push((f.host.clone(), u.clone(), *s));
                }
                sys != system
            });
        }
        for (host, user, session) in ends {
            let user = local_part(&user);
            let msg = ToUser::Ended {
                session,
                reason: EndReason::PeerGone,
                last_seq: 0,
            };
            self.send(&host, FedMsg::ToUser { user, msg });
        }
    }

    /// Handles what came from the other hosts: hosts coming and going, lists, frames.
    pub fn handle(
        &mut self,
        now: Duration,
        input: FedInput,
        core: &mut Broker,
        inboxes: &mut dyn Inboxes,
    ) {
        match input {
            FedInput::Alive(host, _) | FedInput::Standby(host, _)
                if host == self.host || !valid_host_name(&host) => {}
            FedInput::Standby(host, up) => {
                self.standbys.insert(host, (!up).then_some(now));
            }
            FedInput::Alive(host, true) => {
                if self.alive.insert(host.clone()) {
                    if self.away.remove(&host).is_some() {
                        tracing::info!(host = %host, "federation: host back");
                    } else {
                        tracing::info!(host = %host, "federation: host joined");
                        self.list_changed = true;
                    }
                    // What this host put before the newcomer's subscription was known
                    // here went nowhere for it: say the version soon, and again.
                    self.last_join = Some(now);
                    if self
                        .last_put
                        .is_some_and(|t| now <= t + LIST_ANNOUNCE_WINDOW)
                    {
                        self.announce_soon(now);
                    }
                    self.ask_list(&host, now);
                    self.restate_links(&host);
                    // Which sessions of this host's users does it hold (its broker may
                    // be new, or this one)?
                    self.held_seen.remove(&host);
                    self.send(&host, FedMsg::Resync);
                    self.resync.sent(host, FedMsg::Resync, now);
                }
            }
            FedInput::Alive(host, false) => {
                let standby = match self.standbys.get(&host) {
                    Some(None) => true,
                    Some(Some(went)) => now <= *went + STANDBY_SLACK,
                    None => false,
                };
                if !self.alive.remove(&host) {
                } else if standby {
                    tracing::info!(host = %host, "federation: host's token went; waiting for its standby");
                    self.away.insert(host, now + HOST_GRACE);
                } else {
                    self.host_lost(&host, core, inboxes, now);
                }
            }
            FedInput::List {
                host,
                version,
                body,
            } => {
                if host == self.host || !valid_host_name(&host) {
                    return;
                }
                if body.is_empty() {
                    return self.list_announced(&host, version, now);
                }
                self.list_asked.remove(&host);
                self.take_list(&host, version, &body)
            }
            FedInput::ListQueryEnded { host, answered } => {
                // Unanswered while still wanted: asked again after a wait, doubling.
                if let Some((t, wait)) = self.list_asked.get_mut(&host).filter(|_| !answered) {
                    *t = now + *wait;
                    *wait = (*wait * 2).min(LIST_RETRY_MAX);
                }
            }
            FedInput::Frame {
                from,
                users_side,
                bytes,
            } => {
                self.stats.received += 1;
                match decode::<FedMsg>(&bytes) {
                    // Each kind on its own key: access control is by key.
                    Ok(m) if m.on_users_key() != users_side => {
                        self.stats.dropped += 1;
                    }
                    Ok(m) => self.on_msg(&from, m, core, inboxes, now),
                    Err(e) => {
                        self.stats.dropped += 1;
                        tracing::debug!(from = %from, "federation: bad frame: {e}");
                    }
                }
            }
        }
    }

    /// Tells a host that (re)joined of local users' links over its services.
    fn restate_links(&mut self, host: &str) {
        let mut msgs = Vec::new();
        for ((user, number), l) in &self.links_out {
            let services: Vec<ServiceId> = [&l.data, &l.command]
                .into_iter()
                .filter_map(|id| id.remote().filter(|(h, _)| *h == host).map(|(_, s)| s))
                .collect();
            if !services.is_empty() {
                msgs.push(FedMsg::Link {
                    user: user.clone(),
                    link: *number,
                    services,
                    open: true,
                });
            }
        }
        for m in msgs {
            self.send(host, m);
        }
    }

    /// How many links of other hosts' users each of this host's services is in.
    pub fn links_in(&self) -> HashMap<&str, u16> {
        let mut n = HashMap::<&str, u16>::new();
        for services in self.links_in.values() {
            for s in services {
                let c = n.entry(s.0.as_str()).or_default();
                *c = c.saturating_add(1);
            }
        }
        n
    }

    /// Whether other hosts' links here changed since the last call.
    pub fn take_links_change(&mut self) -> bool {
        std::mem::take(&mut self.links_changed)
    }

    /// Forgets the links of other hosts' users matching `gone`.
    fn drop_links_in(&mut self, gone: impl Fn(&UserId) -> bool) {
        let before = self.links_in.len();
        self.links_in.retain(|(u, _), _| !gone(u));
        if self.links_in.len() != before {
            self.links_changed = true;
            self.list_changed = true;
        }
    }

    /// Announces this host's list's version [`LIST_ANNOUNCE_FIRST`] from now, then ever
    /// more rarely.
    fn announce_soon(&mut self, now: Duration) {
        self.announce_wait = LIST_ANNOUNCE_FIRST;
        self.next_refresh = self.next_refresh.min(now + LIST_ANNOUNCE_FIRST);
    }

    /// Host `host` says its list is at `version`: asked for if this one has an older one
    /// (and is not asking already). Hosts not (yet) seen alive are asked when they are.
    fn list_announced(&mut self, host: &str, version: u64, now: Duration) {
        let behind = self.list_versions.get(host).is_none_or(|v| *v < version);
        if behind
            && self.alive.contains(host)
            && self.may(host, Role::Offer)
            && !self.list_asked.contains_key(host)
        {
            self.stats.lists_missed += 1;
            tracing::debug!(
                host,
                version,
                "federation: behind a host's list; asking for it"
            );
            self.ask_list(host, now);
        }
    }

    /// Asks `host` for its list, as anew: given up on after [`LIST_QUERY_OUT`], asked
    /// again [`LIST_RETRY_FIRST`] after it ends unanswered.
    fn ask_list(&mut self, host: &str, now: Duration) {
        self.out.push_back(FedOutput::QueryList(host.to_string()));
        self.list_asked
            .insert(host.to_string(), (now + LIST_QUERY_OUT, LIST_RETRY_FIRST));
    }

    fn take_list(&mut self, host: &str, version: u64, body: &[u8]) {
        if !self.may(host, Role::Offer) {
            self.stats.dropped += 1;
            return;
        }
        // The same list again (a refresh), or an older one (a late reply).
        if version != 0 && self.list_versions.get(host).is_some_and(|v| version <= *v) {
            return;
        }
        let views: Vec<ServiceView> = match serde_json::from_slice(body) {
            Ok(v) => v,
            Err(e) => {
                self.stats.dropped += 1;
                return tracing::debug!(host, "federation: bad list: {e}");
            }
        };
        if views.len() > MAX_SERVICES_PER_HOST {
            self.stats.dropped += 1;
            tracing::warn!(
                host,
                services = views.len(),
                "federation: a host lists more services than a broker can hold: the first \
                 {MAX_SERVICES_PER_HOST} are taken"
            );
        }
        let views: Vec<ServiceView> = views
            .into_iter()
            .take(MAX_SERVICES_PER_HOST)
            .filter(|v| {
                check_name("system", &v.system, MAX_SYSTEM_NAME).is_ok()
                    && check_name("service", &v.name, MAX_SERVICE_NAME).is_ok()
            })
            .map(|v| ServiceView {
                id: ServiceId::on_host(&v.system, host, &v.name).0,
                host: host.to_string(),
                remote: true,
                ..v
            })
            .collect();
        self.list_versions.insert(host.to_string(), version);
        tracing::debug!(
            host,
            version,
            services = views.len(),
            "federation: a host's list taken"
        );
        if self.lists.get(host) != Some(&views) {
            self.lists.insert(host.to_string(), views);
            self.list_changed = true;
        }
    }

    fn host_lost(
        &mut self,
        host: &str,
        core: &mut Broker,
        inboxes: &mut dyn Inboxes,
        now: Duration,
    ) {
        self.stats.hosts_lost += 1;
        tracing::warn!(
            host,
            "federation: host left; its services, requests and sessions end"
        );
        self.list_versions.remove(host);
        self.list_asked.remove(host);
        self.away.remove(host);
        self.standbys.remove(host);
        self.held_seen.remove(host);
        self.resync.answered(&host.to_string());
        if self.lists.remove(host).is_some() {
            self.list_changed = true;
        }
        // Its users' links here (they are stated again if it comes back).
        let suffix = format!("@{host}");
        self.drop_links_in(|u| u.0.ends_with(&suffix));
        // Local users' requests and sessions there.
        for (user, req) in take_on_host(&mut self.outstanding, host, |a| &a.host) {
            let m = ToUser::Refused {
                req,
                reason: Refusal::SystemGone,
            };
            self.deliver_msg(user, m);
        }
        for (user, session) in take_on_host(&mut self.far, host, String::as_str) {
            self.far_session_lost(user, session);
        }
        let gone: Vec<String> = self
            .systems
            .iter()
            .filter(|s| s.ends_with(&suffix))
            .cloned()
            .collect();
        for s in gone {
            self.systems.remove(&s);
            inboxes.close(&Address::System(s));
        }
        // Its users here.
        let users: Vec<UserId> = self
            .foreign
            .iter()
            .filter(|(_, f)| f.host == host)
            .map(|(u, _)| u.clone())
            .collect();
        for u in users {
            self.foreign_gone(&u, core, inboxes, now);
        }
    }

    fn foreign_gone(
        &mut self,
        user: &UserId,
        core: &mut Broker,
        inboxes: &mut dyn Inboxes,
        now: Duration,
    ) {
        // The systems holding its sessions are told to end them; its requests go.
        core.revoke(now, user);
        self.contacts.retain(|(u, _), _| u != user);
        if self.foreign.remove(user).is_some_and(|f| f.inbox) {
            inboxes.close(&Address::User(user.clone()));
        }
    }

    fn on_msg(
        &mut self,
        from: &str,
        msg: FedMsg,
        core: &mut Broker,
        inboxes: &mut dyn Inboxes,
        now: Duration,
    ) {
        if !valid_host_name(from) || from == self.host {
            self.stats.dropped += 1;
            return;
        }
        match msg {
            FedMsg::Request { .. } if !self.may(from, Role::Request) => {
                self.stats.dropped += 1;
            }
            // Users only of hosts that joined (their broker's token is up): no ghost
            // users of a host that never did. A host's request that beat its token here
            // is asked again (the requesting broker resends unanswered requests).
            FedMsg::Request { .. } | FedMsg::Link { .. } | FedMsg::Resync
                if !self.alive.contains(from) =>
            {
                self.stats.dropped += 1;
            }
            FedMsg::Held { .. } if !self.may(from, Role::Offer) || !self.alive.contains(from) => {
                self.stats.dropped += 1;
            }
            FedMsg::Resync => self.send_held(from),
            FedMsg::Held { sessions, done } => {
                self.on_held(from, sessions, done, core, inboxes, now)
            }
            FedMsg::Request {
                user,
                req,
                service,
                remote,
            } => {
                self.stats.requests_in += 1;
                let udp = remote.is_some();
                // A remote user's session runs over the system's UDP endpoint.
                let no_udp = udp
                    && core.kind_of(&service).is_some()
                    && service
                        .split()
                        .is_some_and(|(sys, _)| core.system_udp(sys).is_none());
                let refusal = if no_udp {
                    Some(format!(
                        "{service} is on a system without a UDP endpoint: local users only"
                    ))
                } else if udp
                    && (self.contacts.len() >= MAX_CONTACTS
                        || self
                            .contacts
                            .keys()
                            .filter(|(u, _)| host_of_foreign(u) == Some(from))
                            .count()
                            >= MAX_CONTACTS_PER_HOST)
                {
                    Some("too many remote users' requests from other hosts here".into())
                } else {
                    None
                };
                let foreign = match refusal {
                    Some(r) => Err(r),
                    None => self
                        .foreign_user(&user, from, udp, core, inboxes, now)
                        .ok_or_else(|| "too many users of other hosts here".to_string()),
                };
                let foreign = match foreign {
                    Ok(f) => f,
                    Err(reason) => {
                        // Not served: tell its host.
                        self.stats.dropped += 1;
                        let msg = ToUser::Refused {
                            req,
                            reason: Refusal::BadRequest(reason),
                        };
                        return self.send(from, FedMsg::ToUser { user, msg });
                    }
                };
                if let Some(c) = remote {
                    self.contacts.insert((foreign.clone(), req), c);
                }
                core.handle(
                    now,
                    ToBroker::Request {
                        user: foreign,
                        req,
                        service,
                    },
                );
            }
            FedMsg::Cancel { user, req } => {
                let foreign = UserId(format!("{user}@{from}"));
                if self.foreign.contains_key(&foreign) {
                    self.contacts.remove(&(foreign.clone(), req));
                    core.handle(now, ToBroker::Cancel { user: foreign, req });
                }
            }
            FedMsg::ToSystem { system, msg } => {
                // Only a user's input and ends; the user becomes `user@from`.
                let (user, session, payload) = match msg {
                    ToSystem::Input {
                        user,
                        session,
                        payload,
                    } => (user, session, Some(payload)),
                    ToSystem::End { user, session } => (user, session, None),
                    _ => {
                        self.stats.dropped += 1;
                        return;
                    }
                };
                let foreign = UserId(format!("{user}@{from}"));
                // Only to the system that holds that session of that user, through the
                // user's inbox.
                let held = self.foreign.get(&foreign).is_some_and(|f| {
                    f.inbox && f.sessions.get(&session).is_some_and(|(s, _)| *s == system)
                });
                if !held {
                    self.stats.dropped += 1;
                    return;
                }
                let msg = match payload {
                    Some(payload) => ToSystem::Input {
                        user: foreign.clone(),
                        session,
                        payload,
                    },
                    None => ToSystem::End {
                        user: foreign.clone(),
                        session,
                    },
                };
                inboxes.send(&Address::User(foreign), &Address::System(system), &msg);
            }
            FedMsg::UserGone { user } => {
                let foreign = UserId(format!("{user}@{from}"));
                self.drop_links_in(|u| *u == foreign);
                if self.foreign.contains_key(&foreign) {
                    self.foreign_gone(&foreign, core, inboxes, now);
                }
            }
            FedMsg::Link { .. } if !self.may(from, Role::Request) => {
                self.stats.dropped += 1;
            }
            FedMsg::Link {
                user,
                link,
                services,
                open,
            } => {
                let key = (UserId(format!("{user}@{from}")), link);
                let fits = valid_foreign_name(&user)
                    && services.len() <= 2
                    && (self.links_in.contains_key(&key) || self.links_in.len() < MAX_LINKS_IN);
                if !fits {
                    self.stats.dropped += 1;
                    return;
                }
                let changed = if open && !services.is_empty() {
                    self.links_in.insert(key, services.clone()) != Some(services)
                } else {
                    self.links_in.remove(&key).is_some()
                };
                if changed {
                    self.links_changed = true;
                    self.list_changed = true;
                }
            }
            FedMsg::ToUser { user, msg } => self.deliver(from, user, msg, core, inboxes),
            FedMsg::Granted(mut g) => {
                // Only for a request out on `from`, of a user still here.
                let key = (g.user.clone(), g.req);
                let ours = self
                    .outstanding
                    .get(&key)
                    .is_some_and(|a| a.on(from) && a.service == g.service);
                let Some((system, name)) = g.service.split().filter(|_| ours) else {
                    self.stats.dropped += 1;
                    return;
                };
                g.service = ServiceId::on_host(system, from, name);
                self.outstanding.remove(&key);
                if core.user_pid(&g.user).is_none() {
                    // Gone: its host ends its sessions there.
                    return self.send(from, FedMsg::UserGone { user: g.user });
                }
                self.far
                    .insert((g.user.clone(), g.session), from.to_string());
                self.out.push_back(FedOutput::Deliver(Delivery::Grant(g)));
            }
        }
    }

    /// Tells host `to` which sessions of its users (those with an inbox here) this host
    /// holds, in parts.
    fn send_held(&mut self, to: &str) {
        let held: Vec<HeldSession> = self
            .foreign
            .iter()
            .filter(|(_, f)| f.inbox && f.host == to)
            .flat_map(|(u, f)| {
                f.sessions.iter().map(move |(s, (system, _))| HeldSession {
                    user: local_part(u),
                    session: *s,
                    system: system.clone(),
                })
            })
            .collect();
        let mut parts: Vec<Vec<HeldSession>> = held.chunks(HELD_PART).map(<[_]>::to_vec).collect();
        if parts.is_empty() {
            parts.push(Vec::new());
        }
        let n = parts.len();
        for (i, sessions) in parts.into_iter().enumerate() {
            let done = i + 1 == n;
            self.send(to, FedMsg::Held { sessions, done });
        }
    }

    /// Host `from` holds `sessions` of this host's users: those relayed here go on;
    /// those this broker does not know are resumed if it just took over (and their
    /// user is still here), else ended there (and here, for a user that has one);
    /// with the last part, this host's users' sessions there that it did not list end.
    fn on_held(
        &mut self,
        from: &str,
        sessions: Vec<HeldSession>,
        done: bool,
        core: &Broker,
        inboxes: &mut dyn Inboxes,
        now: Duration,
    ) {
        let resuming = self.resume_until.is_some_and(|t| now <= t);
        let mut seen = self.held_seen.remove(from).unwrap_or_default();
        for h in sessions {
            if !valid_foreign_name(&h.user)
                || check_name("system", &h.system, MAX_SYSTEM_NAME).is_err()
            {
                self.stats.dropped += 1;
                continue;
            }
            let key = (h.user.clone(), h.session);
            let local = core.user_pid(&h.user).is_some_and(|p| p != 0);
            if self.far.get(&key).map(String::as_str) == Some(from) {
                seen.insert(key);
                continue;
            }
            let far_system = format!("{}@{from}", h.system);
            let resumed = resuming
                && local
                && !self.far.contains_key(&key)
                && (self.systems.contains(&far_system)
                    || open_inbox(inboxes, &Address::System(far_system.clone())).is_some_and(
                        |()| {
                            self.systems.insert(far_system.clone());
                            true
                        },
                    ));
            if resumed {
                tracing::info!(user = %h.user, host = from, "federation: a session on another host resumed");
                self.far.insert(key.clone(), from.to_string());
                seen.insert(key);
                continue;
            }
            let end = FedMsg::ToSystem {
                system: h.system,
                msg: ToSystem::End {
                    user: h.user.clone(),
                    session: h.session,
                },
            };
            self.send(from, end);
        }
        if !done {
            self.held_seen.insert(from.to_string(), seen);
            return;
        }
        self.resync.answered(&from.to_string());
        let stale: Vec<(UserId, SessionId)> = self
            .far
            .iter()
            .filter(|(k, h)| h.as_str() == from && !seen.contains(*k))
            .filter(|((u, _), _)| core.user_pid(u).is_some_and(|p| p != 0))
            .map(|(k, _)| k.clone())
            .collect();
        for (user, session) in stale {
            tracing::warn!(host = from, %user, %session, "federation: a host no longer holds a session of a user here: ended");
            self.far.remove(&(user.clone(), session));
            self.far_session_lost(user, session);
        }
    }

    /// The foreign user `user@from`, opened (hello; an inbox unless `udp`, a remote
    /// user of its host) if new.
    fn foreign_user(
        &mut self,
        user: &UserId,
        from: &str,
        udp: bool,
        core: &mut Broker,
        inboxes: &mut dyn Inboxes,
        now: Duration,
    ) -> Option<UserId> {
        if !valid_foreign_name(user) {
            return None;
        }
        let foreign = UserId(format!("{user}@{from}"));
        let has_inbox = self.foreign.get(&foreign).map(|f| f.inbox);
        if has_inbox == Some(false) && !udp {
            // Known as a remote user so far; now a user on shared memory there.
            open_inbox(inboxes, &Address::User(foreign.clone()))?;
            if let Some(f) = self.foreign.get_mut(&foreign) {
                f.inbox = true;
            }
        }
        if has_inbox.is_none() {
            let of_host = self.foreign.values().filter(|f| f.host == from).count();
            if self.foreign.len() >= MAX_FOREIGN_USERS || of_host >= MAX_FOREIGN_USERS_PER_HOST {
                return None;
            }
            if !udp {
                open_inbox(inboxes, &Address::User(foreign.clone()))?;
            }
            self.foreign.insert(
                foreign.clone(),
                Foreign {
                    inbox: !udp,
                    host: from.to_string(),
                    sessions: BTreeMap::new(),
                },
            );
            // Its pid is ours: the systems take its frames from our inbox, and end its
            // sessions if this broker (the relay) dies. A remote user's sessions run
            // past the brokers, kept alive by the user itself: no pid, as on one host.
            core.handle(
                now,
                ToBroker::Hello {
                    user: foreign.clone(),
                    pid: if udp { 0 } else { self.pid },
                    links: Vec::new(),
                    watch_list: false,
                },
            );
        }
        Some(foreign)
    }

    /// A frame from host `from` for local user `user`.
    fn deliver(
        &mut self,
        from: &str,
        user: UserId,
        msg: ToUser,
        core: &mut Broker,
        inboxes: &mut dyn Inboxes,
    ) {
        // A user on shared memory (a remote user's grants come as `FedMsg::Granted`).
        let on_shm = core.user_pid(&user).is_some_and(|p| p != 0);
        let known = core.user_pid(&user).is_some();
        let msg = match msg {
            ToUser::Welcome { .. } | ToUser::Operated { .. } => return,
            // Answers to a request out on `from` only.
            ToUser::Queued { req, .. } | ToUser::Refused { req, .. }
                if !self
                    .outstanding
                    .get(&(user.clone(), req))
                    .is_some_and(|a| a.on(from)) =>
            {
                return;
            }
            // A grant from the host the request went to, for the service requested.
            ToUser::Granted {
                req, ref service, ..
            } if !self
                .outstanding
                .get(&(user.clone(), req))
                .is_some_and(|a| a.on(from) && a.service == *service) =>
            {
                self.stats.dropped += 1;
                return;
            }
            ToUser::Queued { req, position } => {
                self.unanswered.answered(&(user.clone(), req));
                ToUser::Queued { req, position }
            }
            ToUser::Refused { req, reason } => {
                self.outstanding.remove(&(user.clone(), req));
                ToUser::Refused { req, reason }
            }
            ToUser::Granted {
                req,
                session,
                service,
                kind,
                payload,
                ..
            } => {
                let Some((system, name)) = service.split() else {
                    self.stats.dropped += 1;
                    return;
                };
                let far_system = format!("{system}@{from}");
                let service = ServiceId::on_host(system, from, name);
                // The user needs an inbox here for the system's input and ends; with
                // the user gone, or no inbox, the session ends at once.
                let reachable = on_shm
                    && (self.systems.contains(&far_system)
                        || open_inbox(inboxes, &Address::System(far_system.clone())).is_some_and(
                            |()| {
                                self.systems.insert(far_system.clone());
                                true
                            },
                        ));
                if !reachable {
                    let end = FedMsg::ToSystem {
                        system: system.to_string(),
                        msg: ToSystem::End {
                            user: user.clone(),
                            session,
                        },
                    };
                    self.send(from, end);
                    // The user, if still here, waits for an answer: it is that the
                    // system cannot be reached.
                    if self.outstanding.remove(&(user.clone(), req)).is_some() && known {
                        let m = ToUser::Refused {
                            req,
                            reason: Refusal::SystemGone,
                        };
                        self.deliver_msg(user, m);
                    }
                    return;
                }
                self.outstanding.remove(&(user.clone(), req));
                self.far.insert((user.clone(), session), from.to_string());
                ToUser::Granted {
                    req,
                    session,
                    service,
                    kind,
                    payload,
                    // Schemas do not cross hosts yet: another host's open-type samples
                    // reach this host's users as bytes.
                    schema: None,
                    system_pid: self.pid,
                    relayed: false,
                }
            }
            // A session's frames from the host it runs on only.
            ToUser::Update { session, .. }
            | ToUser::Status { session, .. }
            | ToUser::Ended { session, .. }
                if self.far.get(&(user.clone(), session)).map(String::as_str) != Some(from) =>
            {
                return;
            }
            m @ (ToUser::Update { .. } | ToUser::Status { .. }) => m,
            m @ ToUser::Ended { session, .. } => {
                self.far.remove(&(user.clone(), session));
                m
            }
        };
        if known {
            self.deliver_msg(user, msg);
        }
    }

    /// A frame local process `sender` wrote into `peer`'s inbox: a system's for a user
    /// of another host (`Address::User`), or a local user's for a system of another
    /// host (`Address::System`). Relayed to that host, if it is what that peer may get.
    pub fn inbox_frame(
        &mut self,
        peer: &Address,
        frame: &[u8],
        sender: Option<u32>,
        core: &Broker,
        inboxes: &mut dyn Inboxes,
    ) {
        match peer {
            Address::User(foreign) => match decode::<ToUser>(frame) {
                Ok(m) => self.system_frame(foreign, m, sender.unwrap_or(0), inboxes),
                Err(e) => muster_shared::protocol::log_bad_frame(&e),
            },
            Address::System(far) => match decode::<ToSystem>(frame) {
                Ok(m) => self.user_frame(far, m, sender, core),
                Err(e) => muster_shared::protocol::log_bad_frame(&e),
            },
            Address::Broker | Address::Relay(_) | Address::Process(_) => {}
        }
    }

    /// A local system's frame for the foreign user `foreign`.
    fn system_frame(
        &mut self,
        foreign: &UserId,
        msg: ToUser,
        sender: u32,
        inboxes: &mut dyn Inboxes,
    ) {
        let pid = self.pid;
        let Some(f) = self.foreign.get_mut(foreign).filter(|f| f.inbox) else {
            return;
        };
        let ok = match &msg {
            ToUser::Welcome { .. } | ToUser::Operated { .. } => false,
            ToUser::Queued { .. } | ToUser::Refused { .. } => sender == pid,
            ToUser::Granted {
                session,
                service,
                system_pid,
                ..
            } => {
                let system = service.split().map(|(s, _)| s.to_string());
                let owner = system.as_ref().and_then(|s| {
                    inboxes.owner_pid(&Address::User(foreign.clone()), &Address::System(s.clone()))
                });
                let ok = *system_pid == sender && owner == Some(sender);
                if ok {
                    if let Some(s) = system {
                        f.sessions.insert(*session, (s, sender));
                    }
                }
                ok
            }
            ToUser::Update { session, .. } | ToUser::Status { session, .. } => {
                f.sessions.get(session).is_some_and(|(_, p)| *p == sender)
            }
            // Its system's, or ours (a grant its system did not take).
            ToUser::Ended { session, .. } => {
                let ok = f
                    .sessions
                    .get(session)
                    .is_some_and(|(_, p)| *p == sender || sender == pid);
                if ok {
                    f.sessions.remove(session);
                }
                ok
            }
        };
        if ok {
            let host = f.host.clone();
            let user = local_part(foreign);
            self.send(&host, FedMsg::ToUser { user, msg });
        }
    }

    /// A local user's frame for the far system `far` (`system@host`).
    fn user_frame(&mut self, far: &str, msg: ToSystem, sender: Option<u32>, core: &Broker) {
        let Some((system, host)) = far.split_once('@') else {
            return;
        };
        if !self.systems.contains(far) {
            return;
        }
        // Only a user's own input and ends, for its own sessions there.
        let (user, session) = match &msg {
            ToSystem::Input { user, session, .. } | ToSystem::End { user, session } => {
                (user.clone(), *session)
            }
            _ => return,
        };
        let own = sender.is_none_or(|pid| core.user_pid(&user) == Some(pid));
        let theirs = self.far.get(&(user, session)).is_some_and(|h| *h == host);
        if own && theirs {
            let (system, host) = (system.to_string(), host.to_string());
            self.send(&host, FedMsg::ToSystem { system, msg });
        }
    }
}

/// Opens `peer`'s inbox; `None` (logged) if it cannot be.
fn open_inbox(inboxes: &mut dyn Inboxes, peer: &Address) -> Option<()> {
    inboxes
        .open(peer)
        .map_err(|e| tracing::warn!(peer = ?peer, "federation: cannot open an inbox: {e}"))
        .ok()
}

/// [`FedCore::merged_views`] of `local` and the other hosts' lists.
pub(super) fn merge_fairly<'a>(
    local: &'a [ServiceView],
    hosts: impl Iterator<Item = &'a [ServiceView]>,
    cap: usize,
) -> Vec<&'a ServiceView> {
    let mut hosts: Vec<&[ServiceView]> = hosts.collect();
    let mut all: Vec<&ServiceView> = local.iter().take(cap).collect();
    let mut left = cap - all.len();
    // Fewest first: what a small host leaves of its share goes to the larger ones.
    hosts.sort_by_key(|v| v.len());
    let mut n = hosts.len();
    for v in hosts {
        let share = (left / n.max(1)).max(usize::from(left > 0));
        let take = v.len().min(share);
        all.extend(v.iter().take(take));
        left -= take;
        n -= 1;
    }
    all.sort_by(|a, b| a.id.cmp(&b.id));
    all
}

/// The host of a foreign user `user@host`.
fn host_of_foreign(user: &UserId) -> Option<&str> {
    user.0.rsplit_once('@').map(|(_, h)| h)
}

/// Removes the entries of `map` held on `host` (`host_of` a value); returns their keys.
fn take_on_host<K: Ord + Clone, V>(
    map: &mut BTreeMap<K, V>,
    host: &str,
    host_of: impl Fn(&V) -> &str,
) -> Vec<K> {
    let mut taken = Vec::new();
    map.retain(|k, v| {
        let on = host_of(v) == host;
        if on {
            taken.push(k.clone());
        }
        !on
    });
    taken
}

/// Whether another host's user id may be taken as one here (`user@host` then).
fn valid_foreign_name(user: &UserId) -> bool {
    !user.0.is_empty()
        && user.0.len() <= MAX_FOREIGN_USER
        && !user.0.contains(['@', '/'])
        && user.0.bytes().all(|b| b.is_ascii_graphic())
}

/// `user@host` → `user`.
pub(super) fn local_part(foreign: &UserId) -> UserId {
    UserId(
        foreign
            .0
            .rsplit_once('@')
            .map_or(foreign.0.as_str(), |(u, _)| u)
            .to_string(),
    )
}
