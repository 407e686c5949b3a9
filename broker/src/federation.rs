//! Hosts beyond one: brokers federate over Zenoh.
//!
//! Each host runs its broker, systems and users as on one host; a broker started with
//! `--federate` also joins a Zenoh network (the `zenoh` crate), under the key space
//! `muster/<federation>/<host>/...`:
//!
//! | key | what |
//! |---|---|
//! | `<host>/alive` | liveliness token of the host's broker |
//! | `<host>/system/<name>` | liveliness token of each system registered there |
//! | `<host>/list` | the host's services (JSON array of [`ServiceView`]), put on every change; also a queryable |
//! | `<host>/req/<from>` | a user's frames ([`FedMsg`]: request, cancel, input, end, gone) from host `from` to this host |
//! | `<host>/in/<from>` | frames for a user ([`FedMsg::ToUser`]) from host `from`'s arbitration and systems |
//!
//! **Security.** A federation runs on mutual TLS (`--tls DIR`, from `muster certs`);
//! without it a broker refuses to start unless told `--insecure-no-tls`, and with no
//! `--listen` it listens on loopback only. With TLS there are always access rules:
//! `--acl FILE`, else `DIR/acl.toml` (which `muster certs` writes). Each broker lets in
//! from a peer only what the peer's role allows (Zenoh's access control, the peer known
//! by its certificate's common name): hosts that offer publish their list, tokens and
//! systems' frames, under their own name only; hosts that request send requests under
//! their own name only; anything else, or any host not named, is denied. And each
//! broker sends a peer only the frames addressed to it (`<peer>/req/*`, `<peer>/in/*`)
//! and the lists: a member never sees other hosts' sessions.
//!
//! Every broker merges the others' lists into its shared-memory list, each service under
//! the id `system@host/name`, so a local user reads the global list as before.
//!
//! **Requests and sessions across hosts.** A user asks its own broker for
//! `tracking@b/red`; the broker passes the request to host `b`, where the broker
//! arbitrates it (quota, queue) for the user `alice@a` as for any user. For each such
//! foreign user the system's host keeps an inbox in shared memory (a proxy owned by its
//! broker), so the system grants and streams to it as to a local user; the broker
//! relays those frames to the user's host, which delivers them to the user. The user's
//! host keeps an inbox for the system (`tracking@b`), so the user's task input and end go
//! back the same way. A session's frames travel between the user's host and the
//! system's host only, in order (one Zenoh link, reliable), with the system's sequence
//! numbers untouched.
//!
//! **Remote users.** A remote (UDP) user of a host asks for another host's service
//! through its own broker too: the front issues the session key, the request carries
//! the user's address and key ([`FedMsg::Request`]'s `remote`), the system gets them
//! with its offer, and the grant comes back with the system's UDP endpoint
//! ([`FedMsg::Granted`]). The session then runs straight between the user and the
//! system, as on one host; the system's host keeps no inbox for such a user.
//!
//! **Liveness.** A host whose token goes (process killed, link cut past the lease) has
//! its services removed; its users' requests and sessions here end (the systems are
//! told, as when a user is revoked), and the sessions local users held there end with
//! `peer gone`. A user or system that dies is reported to the other side likewise. A
//! cross-host session runs through the two brokers: if either dies, the session ends
//! (its peer's pid, as the user or system sees it, is that broker's).

use crate::core::{Broker, Output};
use muster_shared::ipc::{create_node, Endpoint};
use muster_shared::names::{Address, Instance};
use muster_shared::protocol::{
    decode, encode, LinkInfo, RemoteContact, ToBroker, ToSystem, ToUser,
};
use muster_shared::reactor::Reactor;
use muster_shared::snapshot::{ServiceView, MAX_LISTED_SERVICES};
use muster_shared::types::{
    check_name, EndReason, Refusal, ServiceId, ServiceKind, SessionId, UserId, MAX_HOST_NAME,
    MAX_SERVICE_NAME, MAX_SYSTEM_NAME,
};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::io::{Read, Write};
use std::net::{IpAddr, SocketAddr};
use std::os::fd::AsRawFd;
use std::os::unix::net::UnixStream;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;

/// The first reactor token of proxy inboxes; the shell's own tokens stay below it.
pub const FIRST_PROXY_TOKEN: usize = 1 << 32;
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
pub const MAX_SERVICES_PER_HOST: usize = MAX_LISTED_SERVICES;
/// Most links of other hosts' users over this host's services counted at once.
const MAX_LINKS_IN: usize = 16 * 1024;
/// How long a proxy whose peer is gone keeps its ports: frames just sent through them
/// (an end, a revocation) must be read before the ports close.
const PROXY_LINGER: Duration = Duration::from_secs(2);
/// A host's list not come this long after asking is asked for again, the wait doubling
/// up to [`LIST_RETRY_MAX`].
const LIST_RETRY_FIRST: Duration = Duration::from_millis(250);
const LIST_RETRY_MAX: Duration = Duration::from_secs(4);
/// Each broker publishes its list again this often, unchanged (the same version): a
/// publication a peer missed (made before the peer's subscription was known here, so
/// Zenoh sent it nowhere) reaches it then.
const LIST_REFRESH: Duration = Duration::from_secs(2);
/// A request out on another host that has had no answer (queued, granted or refused)
/// this long is sent again, the wait doubling up to [`REQUEST_RETRY_MAX`]: a put made
/// before Zenoh knew the peer's subscription went nowhere, and so did its answer if the
/// way back was not known yet. The peer takes a repeat as the same request (its broker
/// answers a pending one once, its system a granted one with the same session).
const REQUEST_RETRY_FIRST: Duration = Duration::from_secs(1);
const REQUEST_RETRY_MAX: Duration = Duration::from_secs(4);

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
/// How long a starting broker looks for another broker already using its host name.
const HOST_CHECK: Duration = Duration::from_millis(400);

/// How a broker joins a federation (`muster broker --federate`).
#[derive(Clone, Debug, Default)]
pub struct FedConfig {
    /// This host's name in the federation: 1..=31 characters of `[A-Za-z0-9_-]`.
    pub host: String,
    /// The federation's name (the key space `muster/<name>/`), so federations can
    /// share a network.
    pub federation: String,
    /// A Zenoh configuration file (JSON5); the options below are applied over it.
    pub zenoh_config: Option<PathBuf>,
    /// Zenoh endpoints to connect to (`tcp/HOST:PORT`).
    pub connect: Vec<String>,
    /// Zenoh endpoints to listen on.
    pub listen: Vec<String>,
    /// The Zenoh lease: a peer silent this long is gone (Zenoh's default: 10 s).
    pub lease: Option<Duration>,
    /// Zenoh's multicast scouting (finding peers on the LAN without `--connect`).
    pub multicast: bool,
    /// Mutual TLS with the certificates in this folder (`muster certs`): `ca.pem`,
    /// `HOST.pem`, `HOST.key`. TCP endpoints are used as TLS ones.
    pub tls: Option<PathBuf>,
    /// Who may do what: which hosts offer services, which request them (needs `tls`;
    /// with `tls` and none given, `acl.toml` in the certificates' folder, which `muster
    /// certs` writes).
    pub acl: Option<Acl>,
    /// Federate without TLS: no authentication at all, anyone who reaches the endpoint
    /// acts as any host (`--insecure-no-tls`; refused otherwise).
    pub insecure: bool,
}

/// The access file `muster certs` writes beside the certificates.
pub const ACL_FILE: &str = "acl.toml";

/// A host's role in a federation's access control.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Publishes its services and serves other hosts' users.
    Offer,
    /// Its users request other hosts' services.
    Request,
}

/// The federation's access file (TOML), the same on every host:
///
/// ```toml
/// [hosts]
/// robot1 = ["offer"]
/// laptop = ["request"]
/// hub = ["offer", "request"]
/// ```
///
/// A host not named may connect (its certificate is good) but is let do nothing.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Acl {
    /// Each host's roles, by host name (its certificate's common name).
    pub hosts: BTreeMap<String, BTreeSet<Role>>,
}

impl Acl {
    /// Reads and checks an access file.
    pub fn load(path: &std::path::Path) -> Result<Self, FedError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| FedError::Config(format!("{}: {e}", path.display())))?;
        Self::parse(&text).map_err(|e| FedError::Config(format!("{}: {e}", path.display())))
    }

    /// Parses and checks an access file's text.
    pub fn parse(text: &str) -> Result<Self, String> {
        let acl: Acl = toml::from_str(text).map_err(|e| e.to_string())?;
        for h in acl.hosts.keys() {
            check_host_like("host name", h).map_err(|e| e.to_string())?;
        }
        Ok(acl)
    }

    /// Whether `host` has `role`.
    pub fn allows(&self, host: &str, role: Role) -> bool {
        self.hosts.get(host).is_some_and(|r| r.contains(&role))
    }

    /// Zenoh's `access_control` section for a federation under `prefix`
    /// (`muster/NAME/`): default deny; each named host, known by its certificate's
    /// common name, may subscribe, query and hold its host token; an offering host may
    /// publish its list, its systems' tokens and frames for users, and answer list
    /// queries; a requesting host may send its users' frames. Only under its own name.
    pub fn zenoh_json(&self, prefix: &str) -> serde_json::Value {
        use serde_json::json;
        let mut rules = Vec::new();
        let mut subjects = Vec::new();
        let mut policies = Vec::new();
        let all = format!("{prefix}**");
        for (i, (host, roles)) in self.hosts.iter().enumerate() {
            let subject = format!("h{i}");
            subjects.push(json!({"id": subject, "cert_common_names": [host]}));
            let mut mine = vec![format!("h{i}-member"), format!("h{i}-out")];
            rules.push(json!({"id": format!("h{i}-member"), "flows": ["ingress"], "permission": "allow",
                "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query", "query"],
                "key_exprs": [all]}));
            rules.push(
                json!({"id": format!("h{i}-token"), "flows": ["ingress"], "permission": "allow",
                "messages": ["liveliness_token"], "key_exprs": [format!("{prefix}{host}/alive")]}),
            );
            mine.push(format!("h{i}-token"));
            // What goes out to a member: the federation's declarations, queries, replies
            // and liveliness; of the frames, only those addressed to it (`HOST/req/*`,
            // `HOST/in/*`) and every host's list. Other hosts' session frames (updates,
            // remote users' keys and addresses) never reach it.
            rules.push(json!({"id": format!("h{i}-out"), "flows": ["egress"], "permission": "allow",
                "messages": ["declare_subscriber", "query", "reply", "declare_queryable",
                             "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                "key_exprs": [all]}));
            rules.push(
                json!({"id": format!("h{i}-out-frames"), "flows": ["egress"], "permission": "allow",
                "messages": ["put", "delete"],
                "key_exprs": [format!("{prefix}{host}/*/*"), format!("{prefix}*/list")]}),
            );
            mine.push(format!("h{i}-out-frames"));
            if roles.contains(&Role::Offer) {
                rules.push(
                    json!({"id": format!("h{i}-offer"), "flows": ["ingress"], "permission": "allow",
                    "messages": ["put", "declare_queryable", "reply"],
                    "key_exprs": [format!("{prefix}{host}/list"), format!("{prefix}*/in/{host}")]}),
                );
                rules.push(json!({"id": format!("h{i}-systems"), "flows": ["ingress"], "permission": "allow",
                    "messages": ["liveliness_token"], "key_exprs": [format!("{prefix}{host}/system/*")]}));
                mine.push(format!("h{i}-offer"));
                mine.push(format!("h{i}-systems"));
            }
            if roles.contains(&Role::Request) {
                rules.push(json!({"id": format!("h{i}-request"), "flows": ["ingress"], "permission": "allow",
                    "messages": ["put"], "key_exprs": [format!("{prefix}*/req/{host}")]}));
                mine.push(format!("h{i}-request"));
            }
            policies.push(json!({"rules": mine, "subjects": [subject]}));
        }
        json!({"enabled": true, "default_permission": "deny", "rules": rules,
               "subjects": subjects, "policies": policies})
    }
}

/// Why a broker could not join its federation.
#[derive(Debug, thiserror::Error)]
pub enum FedError {
    /// The host or federation name is not valid.
    #[error("invalid {what} {value:?}: use 1 to 31 characters of [A-Za-z0-9_-]")]
    BadName {
        /// Which name.
        what: &'static str,
        /// The value.
        value: String,
    },
    /// The Zenoh configuration could not be read or applied.
    #[error("zenoh configuration: {0}")]
    Config(String),
    /// Zenoh could not start (an endpoint could not be bound, say).
    #[error("cannot join the federation: {0}")]
    Open(String),
    /// Another broker of the federation already uses this host name.
    #[error("host name {0:?} is already in use in the federation: give each host its own --host")]
    HostTaken(String),
}

/// Whether `name` may name a host (or a federation): 1..=31 characters of
/// `[A-Za-z0-9_-]`.
pub fn valid_host_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= MAX_HOST_NAME
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

fn check_host_like(what: &'static str, value: &str) -> Result<(), FedError> {
    if valid_host_name(value) {
        Ok(())
    } else {
        Err(FedError::BadName {
            what,
            value: value.to_string(),
        })
    }
}

impl FedConfig {
    /// The Zenoh configuration: the file if given, then muster's settings over it.
    pub fn zenoh_config(&self) -> Result<zenoh::Config, FedError> {
        let mut c = match &self.zenoh_config {
            Some(p) => zenoh::Config::from_file(p).map_err(|e| FedError::Config(e.to_string()))?,
            None => {
                let mut c = zenoh::Config::default();
                set(&mut c, "mode", "\"peer\"")?;
                set(
                    &mut c,
                    "scouting/multicast/enabled",
                    if self.multicast { "true" } else { "false" },
                )?;
                c
            }
        };
        if self.tls.is_none() && !self.insecure {
            return Err(FedError::Config(
                "--federate needs --tls DIR: without it any program that reaches this host \
                 can act as any host of the federation (make DIR with `muster certs --out \
                 DIR --hosts a,b,...`; or say --insecure-no-tls, on a network you trust)"
                    .into(),
            ));
        }
        let tls = |eps: &[String]| -> Vec<String> {
            eps.iter()
                .map(|e| match (&self.tls, e.strip_prefix("tcp/")) {
                    (Some(_), Some(rest)) => format!("tls/{rest}"),
                    _ => e.clone(),
                })
                .collect()
        };
        if !self.listen.is_empty() {
            set(&mut c, "listen/endpoints", &json_list(&tls(&self.listen)))?;
        } else if self.zenoh_config.is_none() {
            // Zenoh's own default is every interface: here, only this machine's.
            set(
                &mut c,
                "listen/endpoints",
                &json_list(&tls(&["tcp/127.0.0.1:0".to_string()])),
            )?;
        }
        if !self.connect.is_empty() {
            set(&mut c, "connect/endpoints", &json_list(&tls(&self.connect)))?;
        }
        if self.acl.is_some() && self.tls.is_none() {
            return Err(FedError::Config(
                "--acl needs --tls: hosts are known by their certificates".into(),
            ));
        }
        if let Some(acl) = self.effective_acl()? {
            let prefix = format!("muster/{}/", self.federation);
            set(
                &mut c,
                "access_control",
                &acl.zenoh_json(&prefix).to_string(),
            )?;
        }
        if let Some(dir) = &self.tls {
            let file = |name: String| -> Result<String, FedError> {
                let p = dir.join(&name);
                if !p.is_file() {
                    return Err(FedError::Config(format!(
                        "--tls: {} is missing (make it with `muster certs --out {} --hosts {}`)",
                        p.display(),
                        dir.display(),
                        self.host
                    )));
                }
                serde_json::to_string(&p.display().to_string())
                    .map_err(|e| FedError::Config(e.to_string()))
            };
            let ca = file("ca.pem".into())?;
            let cert = file(format!("{}.pem", self.host))?;
            let key = file(format!("{}.key", self.host))?;
            set(&mut c, "transport/link/tls/root_ca_certificate", &ca)?;
            set(&mut c, "transport/link/tls/listen_certificate", &cert)?;
            set(&mut c, "transport/link/tls/listen_private_key", &key)?;
            set(&mut c, "transport/link/tls/connect_certificate", &cert)?;
            set(&mut c, "transport/link/tls/connect_private_key", &key)?;
            set(&mut c, "transport/link/tls/enable_mtls", "true")?;
            // The peer dialled must show a certificate for the name or address dialled
            // (`muster certs` puts the host's name, localhost, 127.0.0.1 and every
            // `--san` in it); who it is in the federation is its certificate's common
            // name, which the access rules check.
            set(&mut c, "transport/link/tls/verify_name_on_connect", "true")?;
        }
        set(
            &mut c,
            "transport/link/rx/max_message_size",
            &MAX_ZENOH_MESSAGE.to_string(),
        )?;
        if let Some(lease) = self.lease {
            let ms = lease.as_millis().max(100);
            set(&mut c, "transport/link/tx/lease", &ms.to_string())?;
            // Zenoh sends keep-alives lease / keep_alive apart: four per lease.
            set(&mut c, "transport/link/tx/keep_alive", "4")?;
        }
        Ok(c)
    }

    /// The access rules in force: `--acl`, else with TLS the certificates' folder's
    /// `acl.toml` (a TLS federation always has one: a host is its certificate's name,
    /// and may publish only under it); none without TLS.
    pub fn effective_acl(&self) -> Result<Option<Acl>, FedError> {
        match (&self.acl, &self.tls) {
            (Some(acl), _) => Ok(Some(acl.clone())),
            (None, None) => Ok(None),
            (None, Some(dir)) => {
                let path = dir.join(ACL_FILE);
                if !path.is_file() {
                    return Err(FedError::Config(format!(
                        "--tls {}: {} is missing: the access file says which host may offer \
                         and request (`muster certs --out {} --hosts {}` writes it; or give \
                         --acl FILE)",
                        dir.display(),
                        path.display(),
                        dir.display(),
                        self.host
                    )));
                }
                Acl::load(&path).map(Some)
            }
        }
    }
}

fn set(c: &mut zenoh::Config, key: &str, json5: &str) -> Result<(), FedError> {
    c.insert_json5(key, json5)
        .map_err(|e| FedError::Config(format!("{key} = {json5}: {e}")))
}

fn json_list(items: &[String]) -> String {
    serde_json::to_string(items).unwrap_or_else(|_| "[]".into())
}

/// A frame from one host's broker to another's, on `<to>/req/<from>` (a user's side)
/// or `<to>/in/<from>` ([`FedMsg::ToUser`], a system's side).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum FedMsg {
    /// A user of the sending host asks for a service of the receiving host.
    Request {
        /// The user, as its host knows it.
        user: UserId,
        /// Its request number.
        req: u64,
        /// The service, as the receiving host knows it (`system/name`).
        service: ServiceId,
        /// For a remote (UDP) user of the sending host: where it is and the session
        /// key its broker issued. The system then runs the session with the user over
        /// UDP, straight, as with its own host's remote users.
        remote: Option<RemoteContact>,
    },
    /// The user gives the request up.
    Cancel {
        /// The user.
        user: UserId,
        /// The request number.
        req: u64,
    },
    /// A user's task input or end, for a system of the receiving host.
    ToSystem {
        /// The system.
        system: String,
        /// [`ToSystem::Input`] or [`ToSystem::End`]; its user is the sending host's.
        msg: ToSystem,
    },
    /// A user of the sending host opened or closed a link over services of the
    /// receiving host: they count it in their lists.
    Link {
        /// The user.
        user: UserId,
        /// The link's number within the user.
        link: u64,
        /// The link's services on the receiving host (`system/name`; one or two).
        services: Vec<ServiceId>,
        /// Opened (or changed), or closed.
        open: bool,
    },
    /// The user died or left: its requests and sessions on the receiving host end.
    UserGone {
        /// The user.
        user: UserId,
    },
    /// A frame for a user of the receiving host, from its broker's arbitration or from
    /// the system serving it.
    ToUser {
        /// The user, as the receiving host knows it.
        user: UserId,
        /// The frame (`Granted` names the service as the sending host knows it).
        msg: ToUser,
    },
    /// A grant for a remote (UDP) user's request ([`FedMsg::Request`] with `remote`):
    /// the session runs between the user and the system's UDP endpoint.
    Granted(FarGrant),
}

/// A grant on another host for a remote (UDP) user: what its host's front tells it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FarGrant {
    /// The user, as its host knows it.
    pub user: UserId,
    /// Its request number.
    pub req: u64,
    /// The session.
    pub session: SessionId,
    /// The service: as the system's host knows it (`system/name`) on the wire, as the
    /// user's host lists it (`system@host/name`) once delivered.
    pub service: ServiceId,
    /// Data or command.
    pub kind: ServiceKind,
    /// Payload type.
    pub payload: String,
    /// The system's UDP endpoint, as the user reaches it.
    pub system_addr: String,
}

impl FarGrant {
    /// Grant `g` as its user reaches the system: at `system_addr`.
    pub fn new(g: crate::core::Grant, system_addr: String) -> Self {
        FarGrant {
            user: g.user,
            req: g.req,
            session: g.session,
            service: g.service,
            kind: g.kind,
            payload: g.payload,
            system_addr,
        }
    }
}

impl FedMsg {
    /// Whether the frame travels on the users' key (`req/`) rather than on the
    /// systems' (`in/`): access control tells the two apart.
    fn on_users_key(&self) -> bool {
        !matches!(self, FedMsg::ToUser { .. } | FedMsg::Granted(_))
    }
}

/// A frame the federation has for a local user; the shell delivers it through shared
/// memory or, to a remote user, through the UDP front.
#[derive(Clone, Debug, PartialEq)]
pub enum Delivery {
    /// A frame as it is.
    Msg(UserId, ToUser),
    /// A grant on another host for a remote user: the front gives it the system's
    /// UDP endpoint and the session key it issued for the request.
    Grant(FarGrant),
}

/// Counters of the federation, for status and benches.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct FedStats {
    /// Frames sent to other hosts.
    pub sent: u64,
    /// Frames received from other hosts.
    pub received: u64,
    /// Frames from other hosts dropped: malformed, or naming what they may not.
    pub dropped: u64,
    /// Requests passed to other hosts.
    pub requests_out: u64,
    /// Requests from other hosts' users.
    pub requests_in: u64,
    /// Hosts seen leaving.
    pub hosts_lost: u64,
    /// Local users' sessions on other hosts ended because the host left.
    pub sessions_lost: u64,
    /// Requests sent to other hosts again, having had no answer.
    pub requests_resent: u64,
}

/// Messages awaiting an answer, each sent again when its wait is over, the wait
/// doubling from `first` up to `max`.
struct Retries<K, M> {
    first: Duration,
    max: Duration,
    /// key → (message, when it is next sent, the wait after that).
    waiting: BTreeMap<K, (M, Instant, Duration)>,
}

impl<K: Ord + Clone, M: Clone> Retries<K, M> {
    fn new(first: Duration, max: Duration) -> Self {
        Retries {
            first,
            max,
            waiting: BTreeMap::new(),
        }
    }

    /// `msg` was sent for `key` at `now` (a new send starts the waits again).
    fn sent(&mut self, key: K, msg: M, now: Instant) {
        let next = (self.first * 2).min(self.max);
        self.waiting.insert(key, (msg, now + self.first, next));
    }

    /// `key` has its answer: no more sends.
    fn answered(&mut self, key: &K) {
        self.waiting.remove(key);
    }

    /// Keeps only the keys `keep` says still wait.
    fn retain(&mut self, mut keep: impl FnMut(&K) -> bool) {
        self.waiting.retain(|k, _| keep(k));
    }

    /// When the next send is due.
    fn next_due(&self) -> Option<Instant> {
        self.waiting.values().map(|(_, t, _)| *t).min()
    }

    /// The messages due at `now`, in key order; each is due again after its next wait.
    fn due(&mut self, now: Instant) -> Vec<(K, M)> {
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

/// What a Zenoh callback hands the broker's thread.
enum Event {
    Alive(String, bool),
    /// A host's list: its version and body.
    List(String, u64, Vec<u8>),
    /// From a host; `true` if on its users' key (`req`), `false` on its systems' (`in`).
    Msg(String, bool, Vec<u8>),
}

impl Event {
    fn bytes(&self) -> usize {
        match self {
            Event::Alive(..) => 0,
            Event::List(_, _, b) | Event::Msg(_, _, b) => b.len(),
        }
    }
}

/// Largest frame taken from another host (a session update is under 4 KiB); bigger ones
/// are dropped before they are copied.
pub const MAX_FED_FRAME: usize = 64 << 10;
/// Largest list taken from another host (a host lists at most 256 services).
const MAX_FED_LIST: usize = 1 << 20;
/// Zenoh's own limit on a message it reassembles from fragments: bigger ones are
/// dropped by Zenoh before muster sees them.
const MAX_ZENOH_MESSAGE: usize = 2 << 20;
/// Most bytes of frames and lists waiting for the broker's loop; beyond it, what comes
/// is dropped (and counted) rather than held: a flooding peer costs bounded memory.
const MAX_QUEUED_BYTES: usize = 32 << 20;

/// What Zenoh's threads hand the broker's loop: events on a channel, a wake-up on a
/// socket, within a byte budget.
struct Inflow {
    tx: Mutex<mpsc::Sender<Event>>,
    ring: Arc<UnixStream>,
    /// Bytes on the channel.
    queued: AtomicUsize,
    /// Frames and lists dropped at the door (too big, or over the budget) since the
    /// loop last looked.
    refused: AtomicU64,
}

impl Inflow {
    fn push(&self, ev: Event) {
        let n = ev.bytes();
        if self.queued.fetch_add(n, Ordering::Relaxed) + n > MAX_QUEUED_BYTES {
            self.queued.fetch_sub(n, Ordering::Relaxed);
            self.refused.fetch_add(1, Ordering::Relaxed);
            return;
        }
        if let Ok(tx) = self.tx.lock() {
            if tx.send(ev).is_ok() {
                // Full pipe: a wake-up is pending already.
                let _ = (&*self.ring).write(&[1]);
                return;
            }
        }
        self.queued.fetch_sub(n, Ordering::Relaxed);
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

/// A shared-memory inbox the broker keeps for a peer on another host.
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

struct Proxy {
    endpoint: Endpoint,
    token: usize,
    addr: Address,
}

/// A user of another host that this host serves.
struct Foreign {
    /// Its inbox here (`None` for a remote user of its host: its sessions run over
    /// UDP, and the broker's frames for it are relayed from the core's outputs).
    proxy: Option<Proxy>,
    host: String,
    /// Its sessions here: session → (system, the system's pid).
    sessions: BTreeMap<SessionId, (String, u32)>,
}

/// One broker's membership in a federation.
pub struct Federation {
    inst: Instance,
    host: String,
    prefix: String,
    pid: u32,
    session: zenoh::Session,
    _token: zenoh::liveliness::LivelinessToken,
    system_tokens: BTreeMap<String, zenoh::liveliness::LivelinessToken>,
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
    _queryable: zenoh::query::Queryable<()>,
    /// This host's list as last published: its version and body.
    my_list: Arc<Mutex<(u64, Vec<u8>)>>,
    /// When this host's list is published again unchanged ([`LIST_REFRESH`]).
    next_refresh: Instant,
    /// The version of each host's list taken.
    list_versions: HashMap<String, u64>,
    events: mpsc::Receiver<Event>,
    /// Hands an event to the broker's thread and wakes it (used on Zenoh's threads).
    notify: Arc<Inflow>,
    waker: UnixStream,
    alive: BTreeSet<String>,
    lists: BTreeMap<String, Vec<ServiceView>>,
    list_changed: bool,
    /// Requests of local users out on other hosts: (user, req) → host.
    outstanding: BTreeMap<(UserId, u64), Asked>,
    /// Those of them with no answer yet, and when each is sent again.
    unanswered: Retries<(UserId, u64), FedMsg>,
    /// Sessions of local users on other hosts: (user, session) → host.
    far: BTreeMap<(UserId, SessionId), String>,
    /// Inboxes of other hosts' systems (`system@host`), for local users' input and ends.
    systems: BTreeMap<String, Proxy>,
    /// Users of other hosts served here (`user@host`).
    foreign: BTreeMap<UserId, Foreign>,
    /// Contacts of other hosts' remote users for their requests here, given to the
    /// system with the offer: (`user@host`, req) → contact.
    contacts: HashMap<(UserId, u64), RemoteContact>,
    /// Frames for local users, for the shell to deliver.
    deliveries: VecDeque<Delivery>,
    /// Local users' links over other hosts' services: (user, link) → the link.
    links_out: BTreeMap<(UserId, u64), LinkInfo>,
    /// Other hosts' users' links over services here: (`user@host`, link) → services.
    links_in: BTreeMap<(UserId, u64), Vec<ServiceId>>,
    /// Whether `links_in` changed since the list was last written.
    links_changed: bool,
    /// The address other hosts' remote users reach this host's systems at, for a
    /// system listening on every address (from `--listen`).
    advertise: Option<IpAddr>,
    by_token: HashMap<usize, Address>,
    next_token: usize,
    lingering: Vec<(Instant, Proxy)>,
    /// Hosts whose list was asked for and has not come: when to ask again, and the
    /// wait after that. (A query made as a host's token arrives can reach it before
    /// its list's queryable is known here, and go unanswered.)
    list_asked: BTreeMap<String, (Instant, Duration)>,
    stats: FedStats,
    /// The federation's access file, if it has one.
    acl: Option<Acl>,
}

fn key_part<'a>(key: &'a str, prefix: &str) -> Option<(&'a str, &'a str)> {
    key.strip_prefix(prefix)?.split_once('/')
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
        check_host_like("host name", &cfg.host)?;
        check_host_like("federation name", &cfg.federation)?;
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
        let (tx, events) = mpsc::channel::<Event>();
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
        {
            let n = notify.clone();
            let p = prefix.clone();
            let me = host.clone();
            subscribers.push(
                session
                    .liveliness()
                    .declare_subscriber(format!("{prefix}*/alive"))
                    .history(true)
                    .callback(move |s| {
                        if let Some((h, _)) = key_part(s.key_expr().as_str(), &p) {
                            if h != me {
                                let up = s.kind() == zenoh::sample::SampleKind::Put;
                                n.push(Event::Alive(h.to_string(), up));
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
                                n.push(Event::List(h.to_string(), list_version(&s), body));
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
                            if let Some(frame) = n.payload(&s, MAX_FED_FRAME) {
                                n.push(Event::Msg(from.to_string(), users_side, frame));
                            }
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
        let fed = Federation {
            notify,
            inst: inst.clone(),
            host,
            prefix,
            pid,
            session,
            _token: token,
            system_tokens: BTreeMap::new(),
            _subscribers: subscribers,
            _queryable: queryable,
            my_list,
            next_refresh: Instant::now() + LIST_REFRESH,
            list_versions: HashMap::new(),
            events,
            waker,
            alive: BTreeSet::new(),
            lists: BTreeMap::new(),
            list_changed: false,
            outstanding: BTreeMap::new(),
            unanswered: Retries::new(REQUEST_RETRY_FIRST, REQUEST_RETRY_MAX),
            far: BTreeMap::new(),
            systems: BTreeMap::new(),
            foreign: BTreeMap::new(),
            contacts: HashMap::new(),
            deliveries: VecDeque::new(),
            links_out: BTreeMap::new(),
            links_in: BTreeMap::new(),
            links_changed: false,
            advertise: cfg.listen.iter().find_map(|e| listen_ip(e)),
            by_token: HashMap::new(),
            next_token: FIRST_PROXY_TOKEN,
            lingering: Vec::new(),
            list_asked: BTreeMap::new(),
            stats: FedStats::default(),
            acl: cfg.effective_acl()?,
        };
        if fed.acl.is_some() && !fed.may(&fed.host, Role::Offer) {
            tracing::info!("the access file does not let this host offer: its services stay local");
        }
        tracing::info!(host = %fed.host, federation = %cfg.federation, "joined the federation");
        Ok(fed)
    }

    /// Whether the access file (if any) gives `host` `role`.
    fn may(&self, host: &str, role: Role) -> bool {
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

    /// The descriptor that is readable when Zenoh has handed something over.
    pub fn wake_fd(&self) -> std::os::fd::RawFd {
        self.waker.as_raw_fd()
    }

    /// Whether `user` is another host's user served here (`user@host`).
    pub fn is_foreign(user: &UserId) -> bool {
        user.0.contains('@')
    }

    /// When [`Federation::sweep`] is next due.
    pub fn next_due(&self) -> Option<Duration> {
        let now = Instant::now();
        self.lingering
            .iter()
            .map(|(t, _)| *t)
            .chain(self.list_asked.values().map(|(t, _)| *t))
            .chain(self.unanswered.next_due())
            .chain(std::iter::once(self.next_refresh))
            .map(|t| t.saturating_duration_since(now))
            .min()
    }

    /// Closes proxies that have lingered long enough, asks again for lists that have
    /// not come, and publishes this host's list again when it is time.
    pub fn sweep(&mut self) {
        let now = Instant::now();
        if now >= self.next_refresh {
            let mine = self.my_list.lock().map(|l| l.clone()).ok();
            match mine {
                Some((version, body)) if version > 0 && self.may(&self.host, Role::Offer) => {
                    self.put_list(version, body)
                }
                _ => self.next_refresh = now + LIST_REFRESH,
            }
        }
        self.lingering.retain(|(t, _)| *t > now);
        let outstanding = &self.outstanding;
        self.unanswered.retain(|k| outstanding.contains_key(k));
        for (key, msg) in self.unanswered.due(now) {
            if let Some(host) = self.outstanding.get(&key).map(|a| a.host.clone()) {
                self.stats.requests_resent += 1;
                tracing::debug!(user = %key.0, req = key.1, host, "federation: a request with no answer, sent again");
                self.send(&host, &msg);
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
            self.query_list(&host);
            if let Some((t, wait)) = self.list_asked.get_mut(&host) {
                *wait = (*wait * 2).min(LIST_RETRY_MAX);
                *t = now + *wait;
            }
        }
    }

    /// Forgets the users of other hosts a previous broker run served: after a takeover
    /// their hosts see this host's token go and come back, and end their sessions here.
    pub fn forget_previous(&mut self, core: &mut Broker, now: Duration) {
        let old: Vec<UserId> = core
            .users()
            .filter(|u| Self::is_foreign(u))
            .cloned()
            .collect();
        for u in old {
            core.revoke(now, &u);
        }
    }

    /// Publishes this host's list (after every change of the core's) and keeps the
    /// systems' liveliness tokens in step with the registry.
    pub fn publish_list(&mut self, views: &[ServiceView], systems: &[&str]) {
        if !self.may(&self.host, Role::Offer) {
            return;
        }
        let mine: Vec<ServiceView> = views
            .iter()
            .map(|v| ServiceView {
                host: self.host.clone(),
                ..v.clone()
            })
            .collect();
        let body = serde_json::to_vec(&mine).unwrap_or_else(|_| b"[]".to_vec());
        let unix_ns = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
        let version = match self.my_list.lock() {
            Ok(mut l) => {
                let v = unix_ns.max(l.0 + 1);
                *l = (v, body.clone());
                v
            }
            Err(_) => unix_ns,
        };
        self.put_list(version, body);
        let want: BTreeSet<&str> = systems.iter().copied().collect();
        self.system_tokens.retain(|s, _| want.contains(s.as_str()));
        for s in want {
            if !self.system_tokens.contains_key(s) {
                let key = format!("{}{}/system/{s}", self.prefix, self.host);
                match self.session.liveliness().declare_token(&key).wait() {
                    Ok(t) => {
                        self.system_tokens.insert(s.to_string(), t);
                    }
                    Err(e) => tracing::warn!("federation: token for system {s}: {e}"),
                }
            }
        }
    }

    fn put_list(&mut self, version: u64, body: Vec<u8>) {
        self.next_refresh = Instant::now() + LIST_REFRESH;
        let key = format!("{}{}/list", self.prefix, self.host);
        let put = self
            .session
            .put(&key, body)
            .attachment(version.to_le_bytes().to_vec());
        if let Err(e) = put.wait() {
            tracing::warn!("federation: cannot publish the list: {e}");
        }
    }

    /// The other hosts' services, for the merged list.
    pub fn remote_views(&self) -> impl Iterator<Item = &ServiceView> {
        self.lists
            .iter()
            .filter(|(h, _)| self.alive.contains(*h))
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
        let hosts = self
            .lists
            .iter()
            .filter(|(h, _)| self.alive.contains(*h))
            .map(|(_, v)| v.as_slice());
        merge_fairly(local, hosts, cap)
    }

    /// Whether the other hosts' services changed since the last call.
    pub fn take_list_change(&mut self) -> bool {
        std::mem::take(&mut self.list_changed)
    }

    fn send(&mut self, to: &str, msg: &FedMsg) {
        let frame = match encode(msg) {
            Ok(f) => f,
            Err(e) => return tracing::warn!("federation: cannot encode a frame for {to}: {e}"),
        };
        let part = if msg.on_users_key() { "req" } else { "in" };
        let key = format!("{}{to}/{part}/{}", self.prefix, self.host);
        match self.session.put(&key, frame).wait() {
            Ok(()) => self.stats.sent += 1,
            Err(e) => tracing::warn!("federation: cannot send to {to}: {e}"),
        }
    }

    fn open_proxy(&mut self, addr: Address, reactor: &Reactor) -> Result<Proxy, String> {
        // One closed a moment ago (its peer's host left and came back): taken again.
        if let Some(i) = self.lingering.iter().position(|(_, p)| p.addr == addr) {
            let (_, p) = self.lingering.swap_remove(i);
            reactor
                .add(p.endpoint.bell_fd(), p.token)
                .map_err(|e| e.to_string())?;
            self.by_token.insert(p.token, addr);
            return Ok(p);
        }
        let name = match &addr {
            Address::System(s) => format!("muster-fed-system-{s}"),
            Address::User(u) => format!("muster-fed-user-{u}"),
            Address::Broker => "muster-fed".to_string(),
        };
        let node = create_node(&name, false).map_err(|e| e.to_string())?;
        let endpoint = Endpoint::open(&self.inst, addr.clone(), node).map_err(|e| e.to_string())?;
        let token = self.next_token;
        self.next_token += 1;
        reactor
            .add(endpoint.bell_fd(), token)
            .map_err(|e| e.to_string())?;
        self.by_token.insert(token, addr.clone());
        Ok(Proxy {
            endpoint,
            token,
            addr,
        })
    }

    fn close_proxy(&mut self, proxy: Proxy, reactor: &Reactor) {
        reactor.remove(proxy.endpoint.bell_fd());
        self.by_token.remove(&proxy.token);
        self.lingering.push((Instant::now() + PROXY_LINGER, proxy));
    }

    /// A local user's request or cancel for another host's service: passed on, and
    /// `true`. Anything else: `false` (the core handles it). `contact` gives a remote
    /// (UDP) user's address and a fresh session key for the request, `None` for a
    /// user on shared memory; it is asked only for a request passed on.
    pub fn intercept(
        &mut self,
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
                } else if !self.alive.contains(&host) {
                    Some(Refusal::Unknown)
                } else {
                    None
                };
                if let Some(reason) = refusal {
                    let m = ToUser::Refused { req: *req, reason };
                    self.deliveries.push_back(Delivery::Msg(user.clone(), m));
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
                self.send(&host, &m);
                self.unanswered
                    .sent((user.clone(), *req), m, Instant::now());
                true
            }
            ToBroker::Cancel { user, req } => {
                let Some(Asked { host, .. }) = self.outstanding.remove(&(user.clone(), *req))
                else {
                    return false;
                };
                self.send(
                    &host,
                    &FedMsg::Cancel {
                        user: user.clone(),
                        req: *req,
                    },
                );
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
                self.send(&h, &m);
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
            self.send(&h, &m);
        }
        self.links_out.insert(key, link);
    }

    /// Takes the core's outputs that concern other hosts' users: drops watching their
    /// process (the pid is this broker's own), gives a remote user's contact to the
    /// system with the offer, and relays the grant and the broker's frames for a
    /// remote user (who has no inbox here) to its host. Gives back the rest.
    pub fn route(&mut self, core: &Broker, out: Output) -> Option<Output> {
        match out {
            Output::WatchUser { ref user, .. } if Self::is_foreign(user) => None,
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
                self.send(&host, &msg);
                None
            }
            // A user of another host with an inbox here: its grant goes to its host
            // (whose broker passes it on), and the session's frames come from this
            // system's process.
            Output::Granted(g) if self.foreign.get(&g.user).is_some_and(|f| f.proxy.is_some()) => {
                let f = self.foreign.get_mut(&g.user)?;
                f.sessions.insert(g.session, (g.system()?, g.system_pid));
                let host = f.host.clone();
                let (user, msg) = (local_part(&g.user), g.message());
                self.send(&host, &FedMsg::ToUser { user, msg });
                None
            }
            Output::ToUser(user, msg)
                if self.foreign.get(&user).is_some_and(|f| f.proxy.is_none()) =>
            {
                if let ToUser::Refused { req, .. } = &msg {
                    self.contacts.remove(&(user.clone(), *req));
                }
                if matches!(msg, ToUser::Welcome { .. }) {
                    return None;
                }
                let host = self.foreign.get(&user)?.host.clone();
                let user = local_part(&user);
                self.send(&host, &FedMsg::ToUser { user, msg });
                None
            }
            o => Some(o),
        }
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

    /// The next frame for a local user.
    pub fn poll_delivery(&mut self) -> Option<Delivery> {
        self.deliveries.pop_front()
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
            self.send(&h, &FedMsg::UserGone { user: user.clone() });
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
            self.send(
                &host,
                &FedMsg::ToUser {
                    user,
                    msg: ToUser::Ended {
                        session,
                        reason: EndReason::PeerGone,
                        last_seq: 0,
                    },
                },
            );
        }
    }

    /// Handles what Zenoh handed over: hosts coming and going, lists, frames.
    pub fn on_wake(&mut self, core: &mut Broker, reactor: &Reactor, now: Duration) {
        let mut buf = [0u8; 256];
        while matches!((&self.waker).read(&mut buf), Ok(n) if n > 0) {}
        self.stats.dropped += self.notify.refused.swap(0, Ordering::Relaxed);
        while let Ok(ev) = self.events.try_recv() {
            self.notify.queued.fetch_sub(ev.bytes(), Ordering::Relaxed);
            match ev {
                Event::Alive(host, true) => {
                    if self.alive.insert(host.clone()) {
                        tracing::info!(host = %host, "federation: host joined");
                        self.list_changed = true;
                        self.query_list(&host);
                        self.list_asked.insert(
                            host.clone(),
                            (Instant::now() + LIST_RETRY_FIRST, LIST_RETRY_FIRST),
                        );
                        self.restate_links(&host);
                    }
                }
                Event::Alive(host, false) => {
                    if self.alive.remove(&host) {
                        self.host_lost(&host, core, reactor, now);
                    }
                }
                Event::List(host, version, body) => {
                    self.list_asked.remove(&host);
                    self.take_list(&host, version, &body)
                }
                Event::Msg(from, users_side, frame) => {
                    self.stats.received += 1;
                    match decode::<FedMsg>(&frame) {
                        // Each kind on its own key: access control is by key.
                        Ok(m) if m.on_users_key() != users_side => {
                            self.stats.dropped += 1;
                        }
                        Ok(m) => self.on_msg(&from, m, core, reactor, now),
                        Err(e) => {
                            self.stats.dropped += 1;
                            tracing::debug!(from = %from, "federation: bad frame: {e}");
                        }
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
            self.send(host, &m);
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

    fn query_list(&self, host: &str) {
        let key = format!("{}{host}/list", self.prefix);
        let h = host.to_string();
        let n = self.notify.clone();
        let r = self
            .session
            .get(&key)
            .target(zenoh::query::QueryTarget::All)
            .callback(move |reply| {
                if let Some(body) = reply.result().ok().and_then(|s| n.payload(s, MAX_FED_LIST)) {
                    let version = reply.result().map_or(0, list_version);
                    n.push(Event::List(h.clone(), version, body));
                }
            })
            .wait();
        if let Err(e) = r {
            tracing::warn!("federation: cannot ask {host} for its list: {e}");
        }
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
        if self.lists.get(host) != Some(&views) {
            self.lists.insert(host.to_string(), views);
            self.list_changed = true;
        }
    }

    fn host_lost(&mut self, host: &str, core: &mut Broker, reactor: &Reactor, now: Duration) {
        self.stats.hosts_lost += 1;
        tracing::info!(
            host,
            "federation: host left; its services, requests and sessions end"
        );
        self.list_versions.remove(host);
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
            self.deliveries.push_back(Delivery::Msg(user, m));
        }
        for (user, session) in take_on_host(&mut self.far, host, String::as_str) {
            self.stats.sessions_lost += 1;
            let m = ToUser::Ended {
                session,
                reason: EndReason::PeerGone,
                last_seq: 0,
            };
            self.deliveries.push_back(Delivery::Msg(user, m));
        }
        let gone: Vec<String> = self
            .systems
            .keys()
            .filter(|s| s.ends_with(&suffix))
            .cloned()
            .collect();
        for s in gone {
            if let Some(p) = self.systems.remove(&s) {
                self.close_proxy(p, reactor);
            }
        }
        // Its users here.
        let users: Vec<UserId> = self
            .foreign
            .iter()
            .filter(|(_, f)| f.host == host)
            .map(|(u, _)| u.clone())
            .collect();
        for u in users {
            self.foreign_gone(&u, core, reactor, now);
        }
    }

    fn foreign_gone(&mut self, user: &UserId, core: &mut Broker, reactor: &Reactor, now: Duration) {
        // The systems holding its sessions are told to end them; its requests go.
        core.revoke(now, user);
        self.contacts.retain(|(u, _), _| u != user);
        if let Some(p) = self.foreign.remove(user).and_then(|f| f.proxy) {
            self.close_proxy(p, reactor);
        }
    }

    fn on_msg(
        &mut self,
        from: &str,
        msg: FedMsg,
        core: &mut Broker,
        reactor: &Reactor,
        now: Duration,
    ) {
        if check_host_like("host", from).is_err() {
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
            FedMsg::Request { .. } | FedMsg::Link { .. } if !self.alive.contains(from) => {
                self.stats.dropped += 1;
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
                        .foreign_user(&user, from, udp, core, reactor, now)
                        .ok_or_else(|| "too many users of other hosts here".to_string()),
                };
                let foreign = match foreign {
                    Ok(f) => f,
                    Err(reason) => {
                        // Not served: tell its host.
                        self.stats.dropped += 1;
                        return self.send(
                            from,
                            &FedMsg::ToUser {
                                user,
                                msg: ToUser::Refused {
                                    req,
                                    reason: Refusal::BadRequest(reason),
                                },
                            },
                        );
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
                // Only to the system that holds that session of that user.
                let held = self
                    .foreign
                    .get_mut(&foreign)
                    .filter(|f| f.sessions.get(&session).is_some_and(|(s, _)| *s == system));
                let Some(proxy) = held.and_then(|f| f.proxy.as_mut()) else {
                    self.stats.dropped += 1;
                    return;
                };
                let msg = match payload {
                    Some(payload) => ToSystem::Input {
                        user: foreign,
                        session,
                        payload,
                    },
                    None => ToSystem::End {
                        user: foreign,
                        session,
                    },
                };
                proxy.endpoint.send_control(&Address::System(system), &msg);
            }
            FedMsg::UserGone { user } => {
                let foreign = UserId(format!("{user}@{from}"));
                self.drop_links_in(|u| *u == foreign);
                if self.foreign.contains_key(&foreign) {
                    self.foreign_gone(&foreign, core, reactor, now);
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
            FedMsg::ToUser { user, msg } => self.deliver(from, user, msg, core, reactor),
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
                    return self.send(from, &FedMsg::UserGone { user: g.user });
                }
                self.far
                    .insert((g.user.clone(), g.session), from.to_string());
                self.deliveries.push_back(Delivery::Grant(g));
            }
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
        reactor: &Reactor,
        now: Duration,
    ) -> Option<UserId> {
        if !valid_foreign_name(user) {
            return None;
        }
        let foreign = UserId(format!("{user}@{from}"));
        let has_inbox = self.foreign.get(&foreign).map(|f| f.proxy.is_some());
        if has_inbox == Some(false) && !udp {
            // Known as a remote user so far; now a user on shared memory there.
            let proxy = self.user_proxy(&foreign, reactor)?;
            if let Some(f) = self.foreign.get_mut(&foreign) {
                f.proxy = Some(proxy);
            }
        }
        if has_inbox.is_none() {
            let of_host = self.foreign.values().filter(|f| f.host == from).count();
            if self.foreign.len() >= MAX_FOREIGN_USERS || of_host >= MAX_FOREIGN_USERS_PER_HOST {
                return None;
            }
            let proxy = match udp {
                true => None,
                false => Some(self.user_proxy(&foreign, reactor)?),
            };
            self.foreign.insert(
                foreign.clone(),
                Foreign {
                    proxy,
                    host: from.to_string(),
                    sessions: BTreeMap::new(),
                },
            );
            // Its pid is ours: the systems take its frames from our proxy, and end its
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

    fn user_proxy(&mut self, foreign: &UserId, reactor: &Reactor) -> Option<Proxy> {
        self.open_proxy(Address::User(foreign.clone()), reactor)
            .map_err(|e| tracing::warn!(user = %foreign, "federation: cannot open an inbox: {e}"))
            .ok()
    }

    /// A frame from host `from` for local user `user`.
    fn deliver(
        &mut self,
        from: &str,
        user: UserId,
        msg: ToUser,
        core: &mut Broker,
        reactor: &Reactor,
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
                    && (self.systems.contains_key(&far_system)
                        || match self.open_proxy(Address::System(far_system.clone()), reactor) {
                            Ok(p) => {
                                self.systems.insert(far_system.clone(), p);
                                true
                            }
                            Err(e) => {
                                tracing::warn!(system = %far_system, "federation: cannot open an inbox: {e}");
                                false
                            }
                        });
                if !reachable {
                    self.send(
                        from,
                        &FedMsg::ToSystem {
                            system: system.to_string(),
                            msg: ToSystem::End {
                                user: user.clone(),
                                session,
                            },
                        },
                    );
                    // The user, if still here, waits for an answer: it is that the
                    // system cannot be reached.
                    if self.outstanding.remove(&(user.clone(), req)).is_some() && known {
                        let m = ToUser::Refused {
                            req,
                            reason: Refusal::SystemGone,
                        };
                        self.deliveries.push_back(Delivery::Msg(user, m));
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
            self.deliveries.push_back(Delivery::Msg(user, msg));
        }
    }

    /// Frames in a proxy inbox: a system's for a user of another host, or a local
    /// user's for a system of another host. Relayed to that host.
    pub fn on_proxy(&mut self, token: usize, core: &Broker) {
        let Some(addr) = self.by_token.get(&token).cloned() else {
            return;
        };
        match addr {
            Address::User(foreign) => self.drain_foreign(&foreign),
            Address::System(far) => self.drain_far_system(&far, core),
            Address::Broker => {}
        }
    }

    fn drain_foreign(&mut self, foreign: &UserId) {
        let mut out = Vec::new();
        let pid = self.pid;
        let Some(f) = self.foreign.get_mut(foreign) else {
            return;
        };
        let Some(proxy) = f.proxy.as_mut() else {
            return;
        };
        proxy.endpoint.drain_bell();
        while let Some((frame, sender)) = proxy.endpoint.recv_from() {
            let msg = match decode::<ToUser>(&frame) {
                Ok(m) => m,
                Err(e) => {
                    muster_shared::protocol::log_bad_frame(&e);
                    continue;
                }
            };
            let sender = sender.unwrap_or(0);
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
                    let owner = system
                        .as_ref()
                        .and_then(|s| proxy.endpoint.owner_pid(&Address::System(s.clone())));
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
                out.push(msg);
            }
        }
        let host = f.host.clone();
        let user = local_part(foreign);
        for msg in out {
            self.send(
                &host,
                &FedMsg::ToUser {
                    user: user.clone(),
                    msg,
                },
            );
        }
    }

    fn drain_far_system(&mut self, far: &str, core: &Broker) {
        let Some((system, host)) = far.split_once('@') else {
            return;
        };
        let (system, host) = (system.to_string(), host.to_string());
        let mut out = Vec::new();
        let Some(p) = self.systems.get_mut(far) else {
            return;
        };
        p.endpoint.drain_bell();
        while let Some((frame, sender)) = p.endpoint.recv_from() {
            let msg = match decode::<ToSystem>(&frame) {
                Ok(m) => m,
                Err(e) => {
                    muster_shared::protocol::log_bad_frame(&e);
                    continue;
                }
            };
            // Only a user's own input and ends, for its own sessions there.
            let (user, session) = match &msg {
                ToSystem::Input { user, session, .. } | ToSystem::End { user, session } => {
                    (user.clone(), *session)
                }
                _ => continue,
            };
            let own = sender.is_none_or(|pid| core.user_pid(&user) == Some(pid));
            let theirs = self
                .far
                .get(&(user.clone(), session))
                .is_some_and(|h| *h == host);
            if own && theirs {
                out.push(msg);
            }
        }
        for msg in out {
            self.send(
                &host,
                &FedMsg::ToSystem {
                    system: system.clone(),
                    msg,
                },
            );
        }
    }
}

/// [`Federation::merged_views`] of `local` and the other hosts' lists.
fn merge_fairly<'a>(
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

/// The specific IP of a Zenoh endpoint (`tcp/10.0.0.2:7447`), if it has one.
fn listen_ip(endpoint: &str) -> Option<IpAddr> {
    let (_, addr) = endpoint.split_once('/')?;
    let addr = addr.split(['#', '?']).next()?;
    let ip = addr.parse::<SocketAddr>().ok()?.ip();
    (!ip.is_unspecified()).then_some(ip)
}

/// `user@host` → `user`.
fn local_part(foreign: &UserId) -> UserId {
    UserId(
        foreign
            .0
            .rsplit_once('@')
            .map_or(foreign.0.as_str(), |(u, _)| u)
            .to_string(),
    )
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn access_files_parse_and_are_checked() {
        let acl =
            Acl::parse("[hosts]\nrobot1 = [\"offer\"]\nhub = [\"offer\", \"request\"]\n").unwrap();
        assert!(acl.allows("robot1", Role::Offer));
        assert!(!acl.allows("robot1", Role::Request));
        assert!(acl.allows("hub", Role::Request));
        assert!(!acl.allows("nobody", Role::Offer));
        assert!(
            Acl::parse("[hosts]\na = [\"admin\"]\n").is_err(),
            "unknown role"
        );
        assert!(
            Acl::parse("[hosts]\n\"a/b\" = [\"offer\"]\n").is_err(),
            "bad host name"
        );
        assert!(Acl::parse("[other]\n").is_err(), "unknown section");
    }

    #[test]
    fn the_zenoh_rules_give_each_host_its_own_keys_only() {
        let acl = Acl::parse("[hosts]\nr = [\"offer\"]\nl = [\"request\"]\n").unwrap();
        let z = acl.zenoh_json("muster/f/");
        assert_eq!(z["default_permission"], "deny");
        let rules = z["rules"].as_array().unwrap();
        let keys_of = |id: &str| -> Vec<String> {
            rules
                .iter()
                .find(|r| r["id"] == id)
                .map(|r| {
                    r["key_exprs"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .map(|k| k.as_str().unwrap().to_string())
                        .collect()
                })
                .unwrap_or_default()
        };
        // Hosts are numbered in name order: l = h0, r = h1.
        assert_eq!(keys_of("h0-request"), ["muster/f/*/req/l"]);
        assert!(keys_of("h0-offer").is_empty(), "l may not offer");
        assert_eq!(keys_of("h1-offer"), ["muster/f/r/list", "muster/f/*/in/r"]);
        assert!(keys_of("h1-request").is_empty(), "r may not request");
        assert_eq!(z["subjects"][1]["cert_common_names"][0], "r");
        // The JSON is a valid Zenoh access_control section.
        let mut c = zenoh::Config::default();
        c.insert_json5("access_control", &z.to_string()).unwrap();
    }

    #[test]
    fn a_host_listing_hundreds_cannot_push_the_others_out_of_the_merged_list() {
        let views = |host: &str, n: usize| -> Vec<ServiceView> {
            (0..n)
                .map(|k| ServiceView {
                    id: format!("s@{host}/{k:03}"),
                    host: host.into(),
                    remote: true,
                    ..ServiceView::default()
                })
                .collect()
        };
        let local = views("me", 10);
        let (a, flood, c) = (views("a", 30), views("aaa", 300), views("c", 100));
        let count = |all: &[&ServiceView], h: &str| all.iter().filter(|v| v.host == h).count();
        let all = merge_fairly(&local, [&a[..], &flood[..], &c[..]].into_iter(), 256);
        assert_eq!(all.len(), 256);
        // 10 local; 246 left: a lists 30 (under its share of 82), the rest shared
        // evenly between the flood and c (108 each; c lists only 100, the flood gets
        // its 8 more).
        assert_eq!(count(&all, "me"), 10);
        assert_eq!(count(&all, "a"), 30);
        assert_eq!(count(&all, "c"), 100);
        assert_eq!(count(&all, "aaa"), 116);
        assert!(all.windows(2).all(|w| w[0].id < w[1].id), "in id order");
        // Room for everyone: everyone whole.
        let all = merge_fairly(&local, [&a[..], &c[..]].into_iter(), 256);
        assert_eq!(all.len(), 140);
        // No room left: local first, then one each while places last.
        let all = merge_fairly(&flood, [&a[..], &c[..]].into_iter(), 256);
        assert_eq!(
            (count(&all, "aaa"), count(&all, "a"), count(&all, "c")),
            (256, 0, 0)
        );
        let all = merge_fairly(&flood[..254], [&a[..], &c[..]].into_iter(), 256);
        assert_eq!((count(&all, "a"), count(&all, "c")), (1, 1));
    }

    #[test]
    fn unanswered_messages_are_sent_again_with_doubling_waits_until_answered() {
        let ms = Duration::from_millis;
        let t0 = Instant::now();
        let mut r: Retries<u32, &str> = Retries::new(ms(1000), ms(4000));
        assert_eq!(r.next_due(), None);
        assert!(r.due(t0 + ms(10_000)).is_empty());
        r.sent(1, "one", t0);
        r.sent(2, "two", t0 + ms(500));
        assert_eq!(r.next_due(), Some(t0 + ms(1000)));
        assert!(r.due(t0 + ms(999)).is_empty(), "not before its wait");
        assert_eq!(r.due(t0 + ms(1000)), [(1, "one")]);
        // 1 waits 2 s now, 2 its first second.
        assert_eq!(r.next_due(), Some(t0 + ms(1500)));
        assert_eq!(r.due(t0 + ms(1500)), [(2, "two")]);
        assert!(r.due(t0 + ms(2999)).is_empty());
        assert_eq!(r.due(t0 + ms(3000)), [(1, "one")]);
        // Then 4 s, and 4 s again (the cap).
        assert_eq!(r.next_due(), Some(t0 + ms(3500)));
        r.answered(&2);
        assert_eq!(r.next_due(), Some(t0 + ms(7000)));
        assert_eq!(r.due(t0 + ms(7000)), [(1, "one")]);
        assert_eq!(r.next_due(), Some(t0 + ms(11_000)));
        // Sent anew: the waits start again.
        r.sent(1, "one again", t0 + ms(8000));
        assert_eq!(r.due(t0 + ms(9000)), [(1, "one again")]);
        r.retain(|k| *k != 1);
        assert_eq!(r.next_due(), None);
    }

    #[test]
    fn frames_round_trip_and_garbage_is_refused() {
        let m = FedMsg::Request {
            user: UserId("u1".into()),
            req: 3,
            service: ServiceId::new("t1", "s0"),
            remote: Some(RemoteContact {
                addr: "127.0.0.1:9".into(),
                key: [7; 32],
            }),
        };
        assert_eq!(decode::<FedMsg>(&encode(&m).unwrap()).unwrap(), m);
        assert!(m.on_users_key());
        let g = FedMsg::Granted(FarGrant {
            user: UserId("alice.1".into()),
            req: 3,
            session: SessionId(9),
            service: ServiceId::new("t1", "s0"),
            kind: ServiceKind::Data,
            payload: "pose2d".into(),
            system_addr: "127.0.0.1:7".into(),
        });
        assert_eq!(decode::<FedMsg>(&encode(&g).unwrap()).unwrap(), g);
        assert!(!g.on_users_key());
        assert_eq!(listen_ip("tcp/10.0.0.2:7447"), "10.0.0.2".parse().ok());
        assert_eq!(listen_ip("tcp/0.0.0.0:7447"), None);
        assert_eq!(listen_ip("tls/[::1]:7447#iface=lo"), "::1".parse().ok());
        assert!(decode::<FedMsg>(&[0xff; 12]).is_err());
        assert_eq!(
            local_part(&UserId("alice@a".into())),
            UserId("alice".into())
        );
        assert_eq!(
            ServiceId("t1@b/s0".into()).remote(),
            Some(("b", ServiceId::new("t1", "s0")))
        );
        assert_eq!(ServiceId("t1/s0".into()).remote(), None);
    }
}
