//! Protocol messages, grouped by the inbox they arrive at, and the one codec that
//! encodes and decodes all of them.
//!
//! Every frame is `MAGIC`, `VERSION`, then a postcard body. [`decode`] checks the
//! header, the size limit and that no bytes trail the message.

use crate::types::{
    EndReason, Payload, Refusal, ServiceId, ServiceKind, ServiceSpec, SessionId, TaskStatus, UserId,
};
use serde::{de::DeserializeOwned, Deserialize, Serialize};

/// First byte of every frame.
pub const MAGIC: u8 = 0x4d; // 'M'
/// Protocol version; a frame of another version is refused.
pub const VERSION: u8 = 5;
/// Largest frame, in bytes, on any transport.
pub const MAX_FRAME: usize = 64 * 1024;

/// Why a frame could not be decoded. The frame is dropped; nothing else changes.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// The frame is shorter than its 2-byte header.
    #[error("frame truncated: {0} bytes")]
    Truncated(usize),
    /// The first byte is not [`MAGIC`]: not a muster frame.
    #[error("not a muster frame (magic {0:#04x})")]
    BadMagic(u8),
    /// The peer speaks another protocol version; upgrade one side.
    #[error("protocol version {got}, this build speaks {VERSION}")]
    WrongVersion {
        /// The version in the frame.
        got: u8,
    },
    /// The frame is larger than [`MAX_FRAME`].
    #[error("frame of {0} bytes exceeds the {MAX_FRAME}-byte limit")]
    Oversized(usize),
    /// The body does not decode as the expected message.
    #[error("malformed body: {0}")]
    Malformed(String),
    /// The message decoded but bytes were left over.
    #[error("{0} trailing bytes after the message")]
    Trailing(usize),
}

/// Why a message could not be encoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    /// The message would be larger than [`MAX_FRAME`]; send less (e.g. fewer services).
    #[error("message of {0} bytes exceeds the {MAX_FRAME}-byte frame limit")]
    Oversized(usize),
    /// Serialization failed.
    #[error("cannot serialize: {0}")]
    Serialize(String),
}

/// Encodes a message into a frame.
pub fn encode<T: Serialize>(msg: &T) -> Result<Vec<u8>, EncodeError> {
    let out = postcard::to_extend(msg, vec![MAGIC, VERSION])
        .map_err(|e| EncodeError::Serialize(e.to_string()))?;
    if out.len() > MAX_FRAME {
        return Err(EncodeError::Oversized(out.len()));
    }
    Ok(out)
}

/// Decodes one frame into a message: header, size, body and no trailing bytes.
pub fn decode<T: DeserializeOwned>(frame: &[u8]) -> Result<T, DecodeError> {
    if frame.len() > MAX_FRAME {
        return Err(DecodeError::Oversized(frame.len()));
    }
    if frame.len() < 2 {
        return Err(DecodeError::Truncated(frame.len()));
    }
    if frame[0] != MAGIC {
        return Err(DecodeError::BadMagic(frame[0]));
    }
    if frame[1] != VERSION {
        return Err(DecodeError::WrongVersion { got: frame[1] });
    }
    let (msg, rest) = postcard::take_from_bytes(&frame[2..])
        .map_err(|e| DecodeError::Malformed(e.to_string()))?;
    if !rest.is_empty() {
        return Err(DecodeError::Trailing(rest.len()));
    }
    Ok(msg)
}

/// CLOCK_MONOTONIC in nanoseconds: the same clock in every process of a host, so a
/// stamp taken in one process can be compared in another.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: valid out-pointer; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    (ts.tv_sec as u64)
        .saturating_mul(1_000_000_000)
        .saturating_add(ts.tv_nsec as u64)
}

static BAD_FRAMES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// Counts a dropped frame and logs it, rate-limited: the 1st, 2nd, 4th, 8th, ... get a line.
pub fn log_bad_frame(e: &DecodeError) {
    let n = BAD_FRAMES.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
    if n.is_power_of_two() {
        tracing::warn!(dropped = n, "dropped a malformed frame: {e}");
    }
}

/// Counts a local frame refused because its writer was not who it claimed to be (see
/// `sender_allowed` in each core) and logs it, rate-limited like [`log_bad_frame`], with
/// `about` (whom it spoke for, or the frame's kind); returns `ok` so a check can end
/// with it.
pub fn note_impersonation(ok: bool, count: &mut u64, pid: u32, about: &str) -> bool {
    if !ok {
        *count += 1;
        if count.is_power_of_two() {
            tracing::warn!(
                pid,
                refused = *count,
                about,
                "a local process spoke for another: frame refused"
            );
        }
    }
    ok
}

/// Frames dropped as malformed by this process so far.
pub fn bad_frames() -> u64 {
    BAD_FRAMES.load(std::sync::atomic::Ordering::Relaxed)
}

/// A digest of a set of sessions: how many, and the xor of a mix of their ids (order
/// does not matter; a difference in either means the sets differ).
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
)]
pub struct SessionDigest {
    /// Number of sessions.
    pub count: u32,
    /// Xor of each id's splitmix64 mix.
    pub mix: u64,
}

impl SessionDigest {
    /// The digest of `ids`.
    pub fn of(ids: impl IntoIterator<Item = SessionId>) -> Self {
        let mut d = SessionDigest::default();
        for id in ids {
            let mut z = id.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            d.mix ^= z ^ (z >> 31);
            d.count += 1;
        }
        d
    }
}

/// A session a system holds, reported when it (re-)registers so a new broker counts it.
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Debug,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
)]
pub struct ActiveSession {
    /// The session.
    pub session: SessionId,
    /// The service it uses.
    pub service: String,
    /// The user holding it.
    pub user: UserId,
    /// Whether the user is another host's, relayed by this host's broker (not a remote
    /// user over UDP): a broker that did not take over its predecessor's state cannot
    /// relay such a session, and has the system end it.
    #[serde(default)]
    pub relayed: bool,
}

/// How a system reaches a remote user: the address the broker authenticated it at and
/// the key the broker issued for this session (also given to the user).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RemoteContact {
    /// The user's UDP address (`ip:port`).
    pub addr: String,
    /// The session key.
    pub key: [u8; 32],
}

/// A system's limit on its sessions over all its services ([`ToBroker::Limit`]).
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Debug,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
)]
pub struct SessionLimit {
    /// Sessions it takes at once (0: none for now).
    pub sessions: u32,
    /// Why no more, as users are told (e.g. "overloaded").
    pub reason: String,
}

/// A link a user runs, reported to the broker so that it is visible.
#[derive(
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
    Clone,
    Debug,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
)]
pub struct LinkInfo {
    /// Number of the link within the user.
    pub link: u64,
    /// The data service feeding the link.
    pub data: ServiceId,
    /// The command service taking the data as task input.
    pub command: ServiceId,
}

pub use to_broker::ToBroker;

// rkyv's derive leaves the variant fields of its generated resolver undocumented.
#[allow(missing_docs)]
mod to_broker {
    use super::*;

    /// Messages arriving at the broker's inbox.
    #[derive(
        rkyv::Archive,
        rkyv::Serialize,
        rkyv::Deserialize,
        Clone,
        Debug,
        PartialEq,
        Serialize,
        Deserialize,
    )]
    pub enum ToBroker {
        /// A system joins (or re-joins) with its services and the sessions it already holds.
        Register {
            /// System name.
            system: String,
            /// Its process id, watched for death.
            pid: u32,
            /// Its services.
            services: Vec<ServiceSpec>,
            /// Sessions it holds (after a broker restart or delinquency).
            sessions: Vec<ActiveSession>,
            /// Where its UDP endpoint for remote users listens (`ip:port`), if it has one.
            udp: Option<String>,
        },
        /// Answer to [`ToSystem::Ping`].
        Pong {
            /// System name.
            system: String,
            /// The ping's nonce.
            nonce: u64,
            /// A digest of the sessions the system holds: if the broker's differs (a
            /// control frame was lost), it asks for the whole set ([`ToSystem::ReportSessions`]).
            held: Option<SessionDigest>,
        },
        /// Every session the system holds, asked for by [`ToSystem::ReportSessions`]: the
        /// system's set is the truth, and the broker's counts follow it.
        Sessions {
            /// System name.
            system: String,
            /// The sessions.
            sessions: Vec<ActiveSession>,
        },
        /// The system's answer to a forwarded request.
        OfferAnswer {
            /// System name.
            system: String,
            /// The offer's ticket.
            ticket: u64,
            /// `Ok(session)` if granted (the system told the user directly), `Err(reason)` if not.
            answer: Result<SessionId, String>,
        },
        /// A session ended (either side); the quota is free again.
        SessionEnded {
            /// System name.
            system: String,
            /// The session.
            session: SessionId,
        },
        /// The system can no longer offer the service, for now.
        Withdraw {
            /// System name.
            system: String,
            /// Service name.
            service: String,
        },
        /// The system offers a withdrawn service again.
        Restore {
            /// System name.
            system: String,
            /// Service name.
            service: String,
        },
        /// How many sessions the system takes at once over all its services, and why no
        /// more (`None`: no limit of its own, only its services' quotas). Sent after each
        /// registration and whenever it changes: the broker refuses requests beyond it
        /// itself, with this reason, as the system would.
        Limit {
            /// System name.
            system: String,
            /// The limit.
            limit: Option<SessionLimit>,
        },
        /// The system leaves on purpose.
        Unregister {
            /// System name.
            system: String,
        },
        /// A user connects (or reconnects after a broker restart).
        Hello {
            /// User id.
            user: UserId,
            /// Its process id.
            pid: u32,
            /// Links it already runs.
            links: Vec<LinkInfo>,
            /// Ring this user's bell when the service list changes.
            watch_list: bool,
        },
        /// A user asks for a service.
        Request {
            /// User id.
            user: UserId,
            /// The user's request number, echoed in the answer.
            req: u64,
            /// The service.
            service: ServiceId,
        },
        /// A user gives up a pending or queued request.
        Cancel {
            /// User id.
            user: UserId,
            /// The request number.
            req: u64,
        },
        /// A user started a link.
        LinkOpened {
            /// User id.
            user: UserId,
            /// The link.
            link: LinkInfo,
        },
        /// A user's link ended.
        LinkClosed {
            /// User id.
            user: UserId,
            /// The link number.
            link: u64,
        },
        /// A user that watches the list (its hello said so) is rung only when a service
        /// `filter` lets through changes, comes or goes; `None`: on every change. A new
        /// hello forgets it (a user sends it again after each).
        WatchList {
            /// User id.
            user: UserId,
            /// The part of the list it watches.
            filter: Option<crate::snapshot::ListFilter>,
        },
        /// A user leaves.
        Goodbye {
            /// User id.
            user: UserId,
        },
        /// An operator's action, answered with [`ToUser::Operated`]. Only operators may:
        /// on shared memory, processes of the instance's owner (the broker's user).
        Operate {
            /// The operator (a user).
            user: UserId,
            /// Its number for the action, echoed in the answer.
            id: u64,
            /// The action.
            op: Operation,
        },
        /// A latched data service's newest update, sent by its system as it publishes
        /// it: the broker keeps the last one and hands it to each new session of the
        /// service with its grant, as its update 0 (ROS 2's transient-local durability).
        /// Kept by the broker's shell, never by its core (not replicated: a standby
        /// that takes over has it again at the service's next update).
        Latest {
            /// System name.
            system: String,
            /// Service name.
            service: String,
            /// When the system published it (CLOCK_MONOTONIC ns).
            sent_ns: u64,
            /// The update's [`Payload`], encoded as in a frame.
            payload: Vec<u8>,
        },
    }

    /// What an operator can do.
    #[derive(
        rkyv::Archive,
        rkyv::Serialize,
        rkyv::Deserialize,
        Clone,
        Debug,
        PartialEq,
        Serialize,
        Deserialize,
    )]
    pub enum Operation {
        /// The broker's state: systems and their liveness, users, sessions, queues.
        Status,
        /// Withdraw a service (its queue is refused), as its system could.
        Withdraw {
            /// The service.
            service: ServiceId,
        },
        /// Offer a withdrawn service again.
        Restore {
            /// The service.
            service: ServiceId,
        },
        /// End a session (its system ends it and tells its user).
        EndSession {
            /// The session.
            session: SessionId,
        },
        /// Drop a user: its sessions end, its requests and links go.
        DropUser {
            /// The user.
            user: UserId,
        },
        /// Move a request waiting in a service's task queue to `position` (1 = next).
        MoveRequest {
            /// The service.
            service: ServiceId,
            /// The request's user.
            user: UserId,
            /// Its request number.
            req: u64,
            /// Its new place (past the end: last).
            position: u16,
        },
        /// Drop a request from a service's task queue (its user is told).
        DropRequest {
            /// The service.
            service: ServiceId,
            /// The request's user.
            user: UserId,
            /// Its request number.
            req: u64,
        },
    }
}

pub use to_broker::Operation;

impl std::fmt::Display for Operation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Operation::Status => f.write_str("status"),
            Operation::Withdraw { service } => write!(f, "withdraw {service}"),
            Operation::Restore { service } => write!(f, "restore {service}"),
            Operation::EndSession { session } => write!(f, "end session {:016x}", session.0),
            Operation::DropUser { user } => write!(f, "drop user {user}"),
            Operation::MoveRequest {
                service,
                user,
                req,
                position,
            } => write!(
                f,
                "move request {req} of {user} to place {position} in {service}"
            ),
            Operation::DropRequest { service, user, req } => {
                write!(f, "drop request {req} of {user} from {service}")
            }
        }
    }
}

/// The broker's state as an operator sees it ([`Operation::Status`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BrokerStatus {
    /// The broker run.
    pub epoch: u64,
    /// Registered systems.
    pub systems: Vec<SystemStatus>,
    /// Users (at most [`MAX_STATUS_ROWS`]; `users_total` counts all).
    pub users: Vec<UserStatus>,
    /// How many users there are.
    pub users_total: usize,
    /// Open sessions (at most [`MAX_STATUS_ROWS`]; `sessions_total` counts all).
    pub sessions: Vec<SessionStatus>,
    /// How many sessions are open.
    pub sessions_total: usize,
    /// Non-empty task queues, each in order.
    pub queues: Vec<QueueStatus>,
    /// How long the broker took to handle each kind of message in this run (filled
    /// in by the broker's shell, which times the core; empty from the core alone).
    #[serde(default)]
    pub handling: Vec<HandlingFigures>,
}

/// The broker's handling of one kind of message (a [`ToBroker::kind`], or
/// `list_write`) since it began serving: how many, and how long each took.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HandlingFigures {
    /// The message kind.
    pub kind: String,
    /// Messages handled.
    pub count: u64,
    /// Median handling time, µs.
    pub p50_us: u64,
    /// 99th percentile, µs.
    pub p99_us: u64,
    /// Longest, µs.
    pub max_us: u64,
}

/// Most users or sessions listed in a [`BrokerStatus`] (it must fit in one frame).
pub const MAX_STATUS_ROWS: usize = 200;

/// A system, as [`BrokerStatus`] lists it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SystemStatus {
    /// Its name.
    pub name: String,
    /// Its process.
    pub pid: u32,
    /// Its services' names.
    pub services: Vec<String>,
    /// Sessions it holds.
    pub sessions: usize,
    /// Milliseconds since it last answered a ping (`None`: not yet).
    pub last_answer_ms: Option<u64>,
    /// Whether a ping waits for its answer.
    pub ping_outstanding: bool,
    /// Times the broker found it delinquent (no answer to a ping) in this broker run.
    pub delinquencies: u32,
    /// Its UDP endpoint for remote users, if any.
    pub udp: Option<String>,
}

/// A user, as [`BrokerStatus`] lists it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct UserStatus {
    /// Its id.
    pub user: UserId,
    /// Its process (0: a remote user).
    pub pid: u32,
    /// Its links.
    pub links: Vec<LinkInfo>,
}

/// A session, as [`BrokerStatus`] lists it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SessionStatus {
    /// The session (16 hex digits in JSON).
    #[serde(with = "session_hex")]
    pub session: SessionId,
    /// Its service.
    pub service: ServiceId,
    /// Its user.
    pub user: UserId,
}

/// A task queue, as [`BrokerStatus`] lists it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QueueStatus {
    /// The service.
    pub service: ServiceId,
    /// Waiting requests, next first: (user, request number).
    pub waiting: Vec<(UserId, u64)>,
}

impl ToBroker {
    /// The message type's name, for statistics.
    pub fn kind(&self) -> &'static str {
        match self {
            ToBroker::Register { .. } => "register",
            ToBroker::Pong { .. } => "pong",
            ToBroker::Sessions { .. } => "sessions",
            ToBroker::OfferAnswer { .. } => "offer_answer",
            ToBroker::SessionEnded { .. } => "session_ended",
            ToBroker::Withdraw { .. } => "withdraw",
            ToBroker::Restore { .. } => "restore",
            ToBroker::Limit { .. } => "limit",
            ToBroker::Unregister { .. } => "unregister",
            ToBroker::Latest { .. } => "latest",
            ToBroker::Hello { .. } => "hello",
            ToBroker::Request { .. } => "request",
            ToBroker::Cancel { .. } => "cancel",
            ToBroker::LinkOpened { .. } => "link_opened",
            ToBroker::LinkClosed { .. } => "link_closed",
            ToBroker::Goodbye { .. } => "goodbye",
            ToBroker::WatchList { .. } => "watch_list",
            ToBroker::Operate { .. } => "operate",
        }
    }
}

/// Messages arriving at a system's inbox.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ToSystem {
    /// The broker accepted the registration.
    Registered {
        /// The broker's run (changes on restart).
        epoch: u64,
        /// The broker's process id, watched for death.
        broker_pid: u32,
    },
    /// The broker refused the registration (bad spec, name held by a live process, list full).
    RegistrationRefused {
        /// Why.
        reason: String,
    },
    /// Liveness check; answer with [`ToBroker::Pong`].
    Ping {
        /// Echo this.
        nonce: u64,
    },
    /// The broker removed the system as delinquent (or does not know it); re-register.
    Delinquent,
    /// The broker's sessions of this system differ from the system's digest: send them
    /// all ([`ToBroker::Sessions`]).
    ReportSessions,
    /// A user's request the broker granted: open session `session` for it. The broker
    /// told the user right after sending this, so the user's first input or end comes
    /// after it. Answer with [`ToBroker::OfferAnswer`]: `Ok(session)` confirms;
    /// `Err(reason)` (the system cannot take it after all) makes the broker end the
    /// user's session with that reason.
    Offer {
        /// Echo this.
        ticket: u64,
        /// The session the broker granted ([`SessionId::for_request`]).
        session: SessionId,
        /// The requesting user.
        user: UserId,
        /// The user's process id (0 if unknown), watched for death.
        user_pid: u32,
        /// The user's request number.
        req: u64,
        /// Service name.
        service: String,
        /// Set when the user is remote: where it is and the session key to seal with.
        remote: Option<RemoteContact>,
    },
    /// Task input on a command session.
    Input {
        /// The user.
        user: UserId,
        /// The session.
        session: SessionId,
        /// The input.
        payload: Payload,
    },
    /// The user ends a session.
    End {
        /// The user.
        user: UserId,
        /// The session.
        session: SessionId,
    },
    /// The user's access was revoked: end every session it holds here.
    Revoked {
        /// The user.
        user: UserId,
    },
    /// An operator ended the session: end it (its user is told why).
    Terminate {
        /// The session.
        session: SessionId,
        /// Why, in words.
        reason: String,
    },
}

/// Messages arriving at a user's inbox.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ToUser {
    /// The broker accepted the user's hello.
    Welcome {
        /// The broker's run (changes on restart).
        epoch: u64,
        /// The broker's process id.
        broker_pid: u32,
    },
    /// The request waits in the service's task queue at this position (1 = next).
    Queued {
        /// Request number.
        req: u64,
        /// Position, 1-based.
        position: u16,
    },
    /// The request was refused.
    Refused {
        /// Request number.
        req: u64,
        /// Why.
        reason: Refusal,
    },
    /// The session is granted; updates follow on this inbox. The broker sends it as
    /// it grants (`relayed`), over its port open since the hello; the system's own
    /// copy (not `relayed`) comes only where the system must set the session up with
    /// the user itself (a remote user's UDP path).
    Granted {
        /// Request number.
        req: u64,
        /// The session.
        session: SessionId,
        /// The service.
        service: ServiceId,
        /// Data or command.
        kind: ServiceKind,
        /// Payload type name.
        payload: String,
        /// The schema of an open payload type (its updates are
        /// [`crate::types::Payload::Encoded`]).
        schema: Option<crate::types::Schema>,
        /// The system's process id, watched for death.
        system_pid: u32,
        /// Sent by the broker, which decides ([`ToSystem::Offer`]).
        #[serde(default)]
        relayed: bool,
    },
    /// Sent by the system: one data update.
    Update {
        /// The session.
        session: SessionId,
        /// Sequence number, from 1, no gaps unless data was dropped.
        seq: u64,
        /// When the system sent it: CLOCK_MONOTONIC ns (one clock for all processes on
        /// a host), for update latency; 0 if unknown.
        sent_ns: u64,
        /// The data.
        payload: Payload,
    },
    /// Sent by the system: task status on a command session.
    Status {
        /// The session.
        session: SessionId,
        /// Sequence number shared with updates.
        seq: u64,
        /// The status.
        status: TaskStatus,
    },
    /// The session ended. Sent by the system; or by the broker, for a session it
    /// granted that the system could not take or did not answer for.
    Ended {
        /// The session.
        session: SessionId,
        /// Why.
        reason: EndReason,
        /// The sequence number of the last update or status the system sent on the
        /// session (0: none; the broker, which sends none, says 0). A user that saw less
        /// counts the rest as lost: a refused or dropped last frame is a gap, not silence.
        last_seq: u64,
    },
    /// The broker's answer to an operator's action ([`ToBroker::Operate`]): done (with
    /// the status, for [`Operation::Status`]), or why not.
    Operated {
        /// The action's number.
        id: u64,
        /// The outcome.
        result: Result<Option<Box<BrokerStatus>>, String>,
    },
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn sample() -> ToBroker {
        ToBroker::Request {
            user: UserId("u1".into()),
            req: 7,
            service: ServiceId::new("s", "a"),
        }
    }

    #[test]
    fn round_trip() {
        let frame = encode(&sample()).unwrap();
        assert_eq!(frame[0], MAGIC);
        assert_eq!(frame[1], VERSION);
        assert_eq!(decode::<ToBroker>(&frame).unwrap(), sample());
    }

    #[test]
    fn rejects_bad_frames() {
        let frame = encode(&sample()).unwrap();
        assert_eq!(decode::<ToBroker>(&[]), Err(DecodeError::Truncated(0)));
        assert_eq!(
            decode::<ToBroker>(&[0, 1, 2]),
            Err(DecodeError::BadMagic(0))
        );
        let mut v2 = frame.clone();
        v2[1] = VERSION + 1;
        assert_eq!(
            decode::<ToBroker>(&v2),
            Err(DecodeError::WrongVersion { got: VERSION + 1 })
        );
        let mut trailing = frame.clone();
        trailing.push(0);
        assert_eq!(decode::<ToBroker>(&trailing), Err(DecodeError::Trailing(1)));
        assert!(matches!(
            decode::<ToBroker>(&frame[..frame.len() - 1]),
            Err(DecodeError::Malformed(_))
        ));
        let big = vec![MAGIC; MAX_FRAME + 1];
        assert_eq!(
            decode::<ToBroker>(&big),
            Err(DecodeError::Oversized(MAX_FRAME + 1))
        );
    }

    #[test]
    fn refuses_oversized_encode() {
        let msg = ToUser::Update {
            sent_ns: 0,
            session: SessionId(1),
            seq: 1,
            payload: Payload::Text("x".repeat(MAX_FRAME)),
        };
        assert!(matches!(encode(&msg), Err(EncodeError::Oversized(_))));
    }

    proptest! {
        #[test]
        fn decoders_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = decode::<ToBroker>(&bytes);
            let _ = decode::<ToSystem>(&bytes);
            let _ = decode::<ToUser>(&bytes);
        }

        #[test]
        fn decoders_never_panic_with_valid_header(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let mut f = vec![MAGIC, VERSION];
            f.extend(bytes);
            let _ = decode::<ToBroker>(&f);
            let _ = decode::<ToSystem>(&f);
            let _ = decode::<ToUser>(&f);
        }

        #[test]
        fn text_updates_round_trip(s in ".{0,200}", seq in any::<u64>()) {
            let m = ToUser::Update { session: SessionId(seq ^ 1), seq, sent_ns: seq / 3, payload: Payload::Text(s) };
            prop_assert_eq!(decode::<ToUser>(&encode(&m).unwrap()).unwrap(), m);
        }
    }
}

/// What the broker did, as operators and recorders see it: the broker publishes each on
/// its instance's event feed ([`crate::ipc::EventWriter`]), in order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum BrokerEvent {
    /// A system registered (or registered again) its services.
    Registered {
        /// The system.
        system: String,
        /// Its services' names.
        services: Vec<String>,
    },
    /// A registration was refused.
    RegistrationRefused {
        /// The system.
        system: String,
        /// Why.
        reason: String,
    },
    /// A system left the registry.
    SystemRemoved {
        /// The system.
        system: String,
        /// `delinquent` (no answer to a ping), `died` or `unregistered`.
        why: String,
    },
    /// A user said hello.
    UserJoined {
        /// The user.
        user: UserId,
    },
    /// A user left, died or was revoked.
    UserLeft {
        /// The user.
        user: UserId,
    },
    /// A user asked for a service.
    Requested {
        /// The user.
        user: UserId,
        /// Its request number.
        req: u64,
        /// The service.
        service: ServiceId,
    },
    /// A request waits in a service's task queue.
    Queued {
        /// The user.
        user: UserId,
        /// Its request number.
        req: u64,
        /// The service.
        service: ServiceId,
        /// Its place (1 = next).
        position: u16,
    },
    /// A system granted a request: a session opened.
    Granted {
        /// The user.
        user: UserId,
        /// Its request number.
        req: u64,
        /// The service.
        service: ServiceId,
        /// The session (16 hex digits, as users print it).
        #[serde(with = "session_hex")]
        session: SessionId,
    },
    /// A request was refused.
    Refused {
        /// The user.
        user: UserId,
        /// Its request number.
        req: u64,
        /// Why, as a code (`quota_full`, `unknown`, ...).
        code: String,
        /// Why, in words.
        reason: String,
    },
    /// A session ended (its quota is free again).
    SessionEnded {
        /// The service.
        service: ServiceId,
        /// The session.
        #[serde(with = "session_hex")]
        session: SessionId,
    },
    /// A service was withdrawn (or restored, `false`).
    Withdrawn {
        /// The service.
        service: ServiceId,
        /// Withdrawn, or restored.
        withdrawn: bool,
    },
    /// A user's link was opened.
    LinkOpened {
        /// The user.
        user: UserId,
        /// The link.
        link: LinkInfo,
    },
    /// A user's link was closed.
    LinkClosed {
        /// The user.
        user: UserId,
        /// The link number.
        link: u64,
    },
    /// An operator acted (a status read is not told).
    Operated {
        /// The operator.
        user: UserId,
        /// What it did.
        op: String,
        /// Why it could not, if it could not.
        error: Option<String>,
    },
}

/// One event on the feed: its number (from 1 per broker run), when the broker
/// published it (Unix time, ns), and the event.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EventRecord {
    /// The broker run (its epoch, 16 hex digits): a new run (a restart, a standby taking
    /// over) numbers its events from 1 again.
    pub epoch: String,
    /// Number on this broker's feed, from 1.
    pub seq: u64,
    /// Unix time of publishing, ns.
    pub t_ns: u64,
    /// The event.
    #[serde(flatten)]
    pub event: BrokerEvent,
}

/// A session id as 16 hex digits (JSON numbers lose u64 precision in many readers).
mod session_hex {
    use crate::types::SessionId;
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(s: &SessionId, ser: S) -> Result<S::Ok, S::Error> {
        ser.serialize_str(&format!("{:016x}", s.0))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(de: D) -> Result<SessionId, D::Error> {
        let text = String::deserialize(de)?;
        u64::from_str_radix(&text, 16)
            .map(SessionId)
            .map_err(serde::de::Error::custom)
    }
}
