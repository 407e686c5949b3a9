//! Hosts beyond one: brokers federate over Zenoh.
//!
//! Each host runs its broker, systems and users as on one host; a broker started with
//! `--federate` also joins a Zenoh network (the `zenoh` crate), under the key space
//! `muster/<federation>/<host>/...`:
//!
//! | key | what |
//! |---|---|
//! | `<host>/alive` | liveliness token of the host's broker |
//! | `<host>/standby` | liveliness token the host's broker holds while a standby is in sync beside it |
//! | `<host>/system/<name>` | liveliness token of each system registered there |
//! | `<host>/list` | the host's services (JSON array of [`ServiceView`](muster_shared::snapshot::ServiceView)), put on every change; also a queryable |
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
//! arbitrates it (quota, queue) for the user `alice@a` as for any user. For the users of
//! each other host the system's host keeps one inbox in shared memory, that host's relay
//! (owned by its broker), so the system grants and streams to `alice@a` as to a local
//! user, its frames written into `a`'s relay in an envelope naming the user; the broker
//! relays those frames to the user's host, which delivers them to the user. One relay
//! per host, not an inbox per user: a system's update to 300 users of `a` costs it one
//! port and two bells, and the broker one inbox to read. The user's
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
//! **Liveness.** A host whose token goes (process killed, link cut past the lease) is
//! waited for [`HOST_GRACE`]; if it is not back by then, its services are removed, its
//! users' requests and sessions here end (the systems are told, as when a user is
//! revoked), and the sessions local users held there end with `peer gone`. A user or
//! system that dies is reported to the other side likewise.
//!
//! **Relays fail over.** A cross-host session runs through the two hosts' brokers, and
//! survives either one's failover to its standby: users and systems do not watch a
//! relay's process (they take its frames from whichever process is the broker now), the
//! standby serves the other hosts' users its core holds and opens their inboxes again
//! ([`FedCore::take_over`]), and whenever a host sees another (re)join it asks which
//! sessions of its users that one holds ([`FedMsg::Resync`], answered by
//! [`FedMsg::Held`]): those it relays go on, those its predecessor relayed are resumed,
//! and the rest end on both sides. Frames sent while a relay was down are lost and
//! counted as a gap. A broker that starts cold relays nothing of its predecessor's: its
//! users end their sessions on other hosts when they say hello to it, and its systems
//! end those of other hosts' users when they register with it.

mod core;
mod driver;

pub use self::core::{
    FedCore, FedInput, FedOutput, Inboxes, HOST_GRACE, LIST_REFRESH, MAX_FOREIGN_USER,
    MAX_FOREIGN_USERS, MAX_FOREIGN_USERS_PER_HOST, MAX_SERVICES_PER_HOST,
};
pub use driver::{Federation, FIRST_PROXY_TOKEN};

use muster_shared::protocol::{RemoteContact, ToSystem, ToUser};
use muster_shared::types::{ServiceId, ServiceKind, SessionId, UserId, MAX_HOST_NAME};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::time::Duration;

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
    /// How this broker joins the Zenoh network (`None`: the file's mode, else a peer).
    pub mode: Option<ZenohMode>,
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

/// How a broker joins the Zenoh network: the topology of a federation.
///
/// Peers (the default) connect to each other: every host keeps a link to every other
/// (Zenoh's gossip finds the rest from one `--connect`), so links, keep-alives and idle
/// CPU grow with the square of the number of hosts. For many hosts, a few brokers are
/// routers (meshed among themselves) and the rest clients, each with one link to a
/// router (`--connect` every router: a client whose router goes reconnects to another,
/// its host unseen by the others meanwhile).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ZenohMode {
    /// Links to every other peer.
    Peer,
    /// One link to a router; cannot be dialled.
    Client,
    /// Routes between its clients and the other routers; a host as any other too.
    Router,
}

impl std::str::FromStr for ZenohMode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "peer" => Ok(ZenohMode::Peer),
            "client" => Ok(ZenohMode::Client),
            "router" => Ok(ZenohMode::Router),
            _ => Err(format!("{s:?}: one of peer, client, router")),
        }
    }
}

impl ZenohMode {
    /// Its name in Zenoh's configuration (and on the command line).
    pub fn as_str(self) -> &'static str {
        match self {
            ZenohMode::Peer => "peer",
            ZenohMode::Client => "client",
            ZenohMode::Router => "router",
        }
    }
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
                "messages": ["liveliness_token"], "key_exprs": [format!("{prefix}{host}/alive"), format!("{prefix}{host}/standby")]}),
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
        if let Some(m) = self.mode {
            set(&mut c, "mode", &format!("\"{}\"", m.as_str()))?;
        }
        let client = self.mode == Some(ZenohMode::Client);
        if self.tls.is_some() && matches!(self.mode, Some(ZenohMode::Client | ZenohMode::Router)) {
            // A router's relayed messages reach the others on the router's link, with its
            // certificate: the access rules, which know a host by the certificate of the
            // link a message came on, could not tell the hosts behind it apart.
            return Err(FedError::Config(
                "--zenoh-mode client or router cannot be used with --tls yet: the access rules \
                 know a host by its own link's certificate, and behind a router every host \
                 would be the router (use peers, the default)"
                    .into(),
            ));
        }
        if client && !self.listen.is_empty() {
            return Err(FedError::Config(
                "--zenoh-mode client cannot --listen: a client is not dialled (it connects \
                 to a router)"
                    .into(),
            ));
        }
        if client && self.connect.is_empty() && !self.multicast && self.zenoh_config.is_none() {
            return Err(FedError::Config(
                "--zenoh-mode client needs --connect ROUTER (or --multicast to find one)".into(),
            ));
        }
        if client {
            // Zenoh's default for a client is to give up at once when no router answers:
            // a client started before its router (a whole federation restarting) would
            // exit. It waits for one instead.
            set(&mut c, "connect/timeout_ms", "-1")?;
        }
        if !self.listen.is_empty() {
            set(&mut c, "listen/endpoints", &json_list(&tls(&self.listen)))?;
        } else if self.zenoh_config.is_none() && !client {
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
        if self.zenoh_config.is_none() {
            set(
                &mut c,
                "transport/link/tx/queue/size/data",
                &ZENOH_DATA_QUEUE.to_string(),
            )?;
            // Each batch on a link LZ4-compressed when both ends say so (a client that
            // does not, such as Zenoh's Python one by default, gets them plain). The
            // lists are JSON and say the same keys a hundred times: when a hundred
            // hosts start together, every host fetches every other's.
            set(&mut c, "transport/unicast/compression/enabled", "true")?;
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
    /// The sending host saw the receiving host's broker (re)join, or (re)joined itself:
    /// which sessions of its users does the receiving host hold? Answered with
    /// [`FedMsg::Held`]; sent again until answered.
    Resync,
    /// The sessions the sending host holds for the receiving host's users (those with
    /// an inbox there), in parts: the receiving host resumes relaying those it knows
    /// (or, having just taken over, those of its users still here), ends the others,
    /// and, with the last part (`done`), ends its users' sessions there not listed.
    Held {
        /// The sessions.
        sessions: Vec<HeldSession>,
        /// Whether this is the last part.
        done: bool,
    },
}

/// A session one host holds for another host's user ([`FedMsg::Held`]).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct HeldSession {
    /// The user, as its own host knows it.
    pub user: UserId,
    /// The session.
    pub session: SessionId,
    /// The system serving it, as the sending host knows it.
    pub system: String,
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
    pub fn on_users_key(&self) -> bool {
        !matches!(
            self,
            FedMsg::ToUser { .. } | FedMsg::Granted(_) | FedMsg::Held { .. }
        )
    }

    /// Whether the frame may be dropped when the way to its host is congested: a data
    /// update, which its user counts as a gap (the next update or the session's end
    /// names the numbers missed). Everything else (requests, grants, ends, inputs) must
    /// arrive, and waits for room instead.
    pub fn droppable(&self) -> bool {
        matches!(
            self,
            FedMsg::ToUser {
                msg: ToUser::Update { .. },
                ..
            }
        )
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
    /// Other hosts' lists found missed (an announced version newer than the one held)
    /// and asked for.
    pub lists_missed: u64,
    /// Updates (and list announcements) not put because 1,024 puts already waited
    /// for room on the put thread.
    pub puts_dropped: u64,
}

/// Largest frame taken from another host (a session update is under 4 KiB); bigger ones
/// are dropped before they are copied.
pub const MAX_FED_FRAME: usize = 64 << 10;
/// Zenoh's own limit on a message it reassembles from fragments: bigger ones are
/// dropped by Zenoh before muster sees them.
const MAX_ZENOH_MESSAGE: usize = 8 << 20;
/// Most bytes of one batch of frames (one Zenoh put): within one of Zenoh's own 64 KiB
/// batches, so that it is never cut into fragments. A single frame goes alone however
/// large, up to [`MAX_FED_FRAME`].
pub const MAX_FED_BATCH: usize = 60 << 10;
/// Zenoh's transmission queue for data, in batches of 64 KiB (Zenoh's default is 2, its
/// most 16): a burst of frames to a host waits in it rather than being dropped or
/// holding the broker's loop.
const ZENOH_DATA_QUEUE: usize = 16;

/// Frames for one host on one key, gathered over a pass of the broker's loop and sent as
/// one Zenoh put: each frame is its length (`u32`, little-endian) and its bytes. Under
/// load a relay passes hundreds of frames a pass (a system's burst to another host's
/// users); one put and one wake-up at the other end each, rather than one per frame.
#[derive(Debug, Default)]
pub struct Batch {
    bytes: Vec<u8>,
    frames: usize,
}

impl Batch {
    /// Whether `frame` fits beside what the batch holds (an empty batch takes any frame
    /// up to [`MAX_FED_FRAME`]).
    pub fn fits(&self, frame: &[u8]) -> bool {
        frame.len() <= MAX_FED_FRAME
            && (self.frames == 0 || self.bytes.len() + 4 + frame.len() <= MAX_FED_BATCH)
    }

    /// Adds a frame (the caller checked [`Batch::fits`], or sends what it holds first).
    pub fn push(&mut self, frame: &[u8]) {
        // A frame is at most MAX_FED_FRAME (64 KiB), so its length fits a u32.
        self.bytes
            .extend_from_slice(&(frame.len() as u32).to_le_bytes());
        self.bytes.extend_from_slice(frame);
        self.frames += 1;
    }

    /// How many frames it holds.
    pub fn len(&self) -> usize {
        self.frames
    }

    /// Whether it holds none.
    pub fn is_empty(&self) -> bool {
        self.frames == 0
    }

    /// Its bytes, leaving it empty.
    pub fn take(&mut self) -> Vec<u8> {
        self.frames = 0;
        std::mem::take(&mut self.bytes)
    }
}

/// The frames of a batch as another host sent it, in order, and whether anything was
/// wrong with it: a length running past the end, or a frame over [`MAX_FED_FRAME`]. The
/// frames before the fault are kept; nothing after it is read.
pub fn split_batch(mut bytes: &[u8]) -> (Vec<&[u8]>, bool) {
    let mut frames = Vec::new();
    while !bytes.is_empty() {
        let Some((len, rest)) = bytes.split_first_chunk::<4>() else {
            return (frames, true);
        };
        let len = u32::from_le_bytes(*len) as usize;
        if len > MAX_FED_FRAME || len > rest.len() {
            return (frames, true);
        }
        let (frame, rest) = rest.split_at(len);
        frames.push(frame);
        bytes = rest;
    }
    (frames, false)
}

/// The specific IP of a Zenoh endpoint (`tcp/10.0.0.2:7447`), if it has one.
fn listen_ip(endpoint: &str) -> Option<IpAddr> {
    let (_, addr) = endpoint.split_once('/')?;
    let addr = addr.split(['#', '?']).next()?;
    let ip = addr.parse::<SocketAddr>().ok()?.ip();
    (!ip.is_unspecified()).then_some(ip)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::core::{local_part, merge_fairly, Retries};
    use super::*;
    use muster_shared::protocol::{decode, encode};
    use muster_shared::snapshot::ServiceView;
    use std::time::Duration;

    #[test]
    fn a_batch_splits_into_its_frames_in_order_and_a_bad_one_keeps_what_came_before() {
        let mut b = Batch::default();
        assert!(b.is_empty());
        for f in [&b"one"[..], b"", b"three"] {
            assert!(b.fits(f));
            b.push(f);
        }
        assert_eq!(b.len(), 3);
        let bytes = b.take();
        assert!(b.is_empty() && b.take().is_empty(), "taking empties it");
        assert_eq!(
            split_batch(&bytes),
            (vec![&b"one"[..], b"", b"three"], false)
        );
        assert_eq!(split_batch(&[]), (vec![], false));
        // A length past the end, a short length, a frame over the limit.
        assert_eq!(
            split_batch(&bytes[..bytes.len() - 1]),
            (vec![&b"one"[..], b""], true)
        );
        assert_eq!(split_batch(&bytes[..9]), (vec![&b"one"[..]], true));
        let mut big = ((MAX_FED_FRAME + 1) as u32).to_le_bytes().to_vec();
        big.resize(4 + MAX_FED_FRAME + 1, 0);
        assert_eq!(split_batch(&big), (vec![], true));
        // A frame at the frame limit goes alone, over the batch's size; nothing goes
        // beside it.
        let edge = vec![7u8; MAX_FED_FRAME];
        let mut b = Batch::default();
        assert!(b.fits(&edge));
        b.push(&edge);
        assert!(!b.fits(&[0u8; 1]), "nothing beside a frame at the limit");
        assert!(!Batch::default().fits(&vec![0u8; MAX_FED_FRAME + 1]));
        let (frames, bad) = split_batch(&b.bytes);
        assert_eq!(
            (frames.len(), frames[0].len(), bad),
            (1, MAX_FED_FRAME, false)
        );
        // Two frames filling a batch to its last byte fit; one byte more does not.
        let first = vec![1u8; MAX_FED_BATCH - 4 - 4 - 100];
        let mut b = Batch::default();
        b.push(&first);
        assert!(b.fits(&[0u8; 100]));
        assert!(!b.fits(&[0u8; 101]));
        b.push(&[0u8; 100]);
        assert_eq!(b.take().len(), MAX_FED_BATCH);
    }

    #[test]
    fn only_data_updates_may_be_dropped_on_a_congested_way() {
        use muster_shared::protocol::ToUser;
        use muster_shared::types::{EndReason, Payload};
        let user = UserId("u".into());
        let to_user = |msg| FedMsg::ToUser {
            user: user.clone(),
            msg,
        };
        let update = to_user(ToUser::Update {
            session: SessionId(1),
            seq: 1,
            sent_ns: 0,
            payload: Payload::Text("x".into()),
        });
        assert!(update.droppable());
        let ended = to_user(ToUser::Ended {
            session: SessionId(1),
            reason: EndReason::ByUser,
            last_seq: 1,
        });
        assert!(!ended.droppable());
        let cancel = FedMsg::Cancel { user, req: 1 };
        assert!(!cancel.droppable());
    }

    #[test]
    fn zenoh_modes_set_the_topology_and_refuse_what_cannot_work() {
        let base = FedConfig {
            host: "a".into(),
            federation: "f".into(),
            insecure: true,
            ..FedConfig::default()
        };
        let mode = |c: &FedConfig| -> Result<String, String> {
            let z = c.zenoh_config().map_err(|e| e.to_string())?;
            Ok(format!(
                "{} {}",
                z.get_json("mode").unwrap(),
                z.get_json("listen/endpoints").unwrap()
            ))
        };
        // A peer by default, listening on loopback.
        assert_eq!(mode(&base).unwrap(), "\"peer\" [\"tcp/127.0.0.1:0\"]");
        let router = FedConfig {
            mode: Some(ZenohMode::Router),
            listen: vec!["tcp/127.0.0.1:7447".into()],
            ..base.clone()
        };
        assert_eq!(
            mode(&router).unwrap(),
            "\"router\" [\"tcp/127.0.0.1:7447\"]"
        );
        // A client dials its routers and listens on nothing.
        let client = FedConfig {
            mode: Some(ZenohMode::Client),
            connect: vec!["tcp/127.0.0.1:7447".into()],
            ..base.clone()
        };
        // (Zenoh's own default names listen endpoints for routers and peers only.)
        let m = mode(&client).unwrap();
        assert!(
            m.starts_with("\"client\" ") && !m.contains("127.0.0.1"),
            "{m}"
        );
        // It waits for a router rather than giving up when none answers yet.
        let z = client.zenoh_config().unwrap();
        assert_eq!(z.get_json("connect/timeout_ms").unwrap(), "-1");
        let no_router = FedConfig {
            connect: vec![],
            ..client.clone()
        };
        assert!(mode(&no_router).unwrap_err().contains("--connect ROUTER"));
        let listening = FedConfig {
            listen: vec!["tcp/127.0.0.1:7448".into()],
            ..client.clone()
        };
        assert!(mode(&listening).unwrap_err().contains("cannot --listen"));
        // Not with TLS: the access rules would see every host behind a router as it.
        let tls = FedConfig {
            tls: Some("/nonexistent".into()),
            insecure: false,
            ..client
        };
        assert!(mode(&tls)
            .unwrap_err()
            .contains("cannot be used with --tls"));
        assert_eq!("router".parse::<ZenohMode>(), Ok(ZenohMode::Router));
        assert!("hub".parse::<ZenohMode>().is_err());
    }

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
    fn a_list_is_put_when_what_other_hosts_see_of_it_changed_and_not_otherwise() {
        use super::core::{FedCore, FedOutput};
        let t = Duration::from_secs(1);
        let mut core = FedCore::new("a", 1, None, None, t);
        let view = |name: &str, in_use: u16| ServiceView {
            id: format!("t1/{name}"),
            system: "t1".into(),
            name: name.into(),
            kind: "data".into(),
            quota: 2,
            in_use,
            payload: "pose2d".into(),
            ..ServiceView::default()
        };
        let puts = |core: &mut FedCore, views: &[ServiceView], wall: u64| {
            core.publish_list(t, wall, views, &["t1"]);
            std::iter::from_fn(|| core.poll_output())
                .filter_map(|o| match o {
                    FedOutput::PutList { version, body } => Some((version, body)),
                    _ => None,
                })
                .collect::<Vec<_>>()
        };
        // The first list is put even if empty.
        assert_eq!(puts(&mut core, &[], 10).len(), 1);
        let first = puts(&mut core, &[view("s0", 0)], 20);
        assert_eq!(first.len(), 1);
        assert_eq!(first[0].0, 20);
        // The same again: nothing put, the version kept (hosts that have it are not
        // sent it again, and do not read it again).
        assert!(puts(&mut core, &[view("s0", 0)], 30).is_empty());
        assert_eq!(core.my_list().0, 20);
        // A count other hosts see changed: put, with a newer version.
        let next = puts(&mut core, &[view("s0", 1)], 25);
        assert_eq!(next.len(), 1);
        assert_eq!(next[0].0, 25);
        assert_ne!(next[0].1, first[0].1);
    }

    #[test]
    fn unanswered_messages_are_sent_again_with_doubling_waits_until_answered() {
        let ms = Duration::from_millis;
        let t0 = Duration::from_secs(100);
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
