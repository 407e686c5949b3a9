//! A system's UDP endpoint for remote users' sessions.
//!
//! The broker authenticates a remote user, issues a random key for each session it
//! offers us, and tells us (in the offer) where the user is; the user gets the same key
//! with its grant. Session traffic then goes straight between this endpoint and the
//! user, sealed with ChaCha20-Poly1305 under that key, so it never touches the broker
//! and survives a broker crash like a local session.
//!
//! Liveness: the user sends a keepalive on each session every second; a session silent
//! for [`LEASE`] ends as `PeerGone`. An ended session's key lingers for [`LINGER`] to
//! answer a repeated `End` with `Ended` again.
//!
//! [`RemoteSessions`] is sans IO (datagrams and the time are handed in, datagrams to
//! send are taken out); [`UdpSessions`] drives it over a socket.

use crate::core::{SystemCore, SystemOutput};
use muster_shared::protocol::{RemoteContact, ToSystem, ToUser};
use muster_shared::types::{EndReason, SessionId, UserId};
use muster_shared::udp::crypto::{SessionCipher, Side};
use muster_shared::udp::early::Early;
use muster_shared::udp::msgs::{from_bytes, seal_session, SessionDown, SessionUp};
use muster_shared::udp::wire::{Datagram, MAX_DATAGRAM};
use muster_shared::udp::{
    recv_one, send_transmit, size_recv_buffer, DropCounters, PathProbe, Transmit, RECV_BATCH,
};
use std::collections::{HashMap, VecDeque};
use std::net::{SocketAddr, UdpSocket};
use std::os::fd::{AsRawFd, RawFd};
use std::time::{Duration, Instant};

/// A remote session silent this long ends (the user is gone).
pub const LEASE: Duration = Duration::from_secs(5);
/// An ended session's key is kept this long to answer repeated `End`s.
pub const LINGER: Duration = Duration::from_secs(10);

/// How often silent sessions are looked for.
const HOUSEKEEPING: Duration = Duration::from_millis(500);

struct Remote {
    user: UserId,
    addr: SocketAddr,
    key: [u8; 32],
    /// A new address the user's datagrams came from, the challenge sent there, and when.
    probe: PathProbe,
    cipher: SessionCipher,
    last_heard: Instant,
    ended: Option<(Instant, EndReason, u64)>,
}

/// Counters of the endpoint.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct RemoteStats {
    /// Datagrams received.
    pub datagrams_in: u64,
    /// Datagrams sent.
    pub datagrams_out: u64,
    /// Sessions ended because the user went silent.
    pub leases_expired: u64,
    /// Path challenges sent to new addresses of a session's user.
    pub path_challenges: u64,
    /// Sessions moved to a validated new address.
    pub migrations: u64,
    /// Dropped datagrams by reason.
    pub drops: DropCounters,
}

/// The endpoint's logic: keys of offers in flight, sessions, datagrams to send.
#[derive(Default)]
pub struct RemoteSessions {
    out: VecDeque<Transmit>,
    next_housekeeping: Option<Instant>,
    offers: HashMap<(UserId, u64), RemoteContact>,
    sessions: HashMap<u64, Remote>,
    /// Datagrams of sessions not offered yet: the broker sends a remote user its grant
    /// before it writes us the offer (the grant is on the user's path, the offer is not),
    /// so a user's first keepalive or input may come first. Replayed, in order, when the
    /// session opens.
    early: Early,
    stats: RemoteStats,
}

impl RemoteSessions {
    /// The next datagram to send.
    pub fn poll_transmit(&mut self) -> Option<Transmit> {
        self.out.pop_front()
    }

    /// Counters.
    pub fn stats(&self) -> &RemoteStats {
        &self.stats
    }

    /// Open remote sessions (not counting ended ones that linger).
    pub fn open_sessions(&self) -> usize {
        self.sessions.values().filter(|r| r.ended.is_none()).count()
    }

    /// Remembers the contact of a remote offer before the core handles it.
    pub fn note(&mut self, msg: &ToSystem) {
        if let ToSystem::Offer {
            user,
            req,
            remote: Some(contact),
            ..
        } = msg
        {
            if self.offers.len() > 4096 {
                self.offers.clear(); // offers are answered at once; this never grows
            }
            self.offers.insert((user.clone(), *req), contact.clone());
        }
    }

    /// Takes the core's outputs for remote users; gives back the rest.
    pub fn route(&mut self, now: Instant, out: SystemOutput) -> Option<SystemOutput> {
        match out {
            SystemOutput::ToUser(user, ToUser::Granted { req, session, .. })
                if self.offers.contains_key(&(user.clone(), req)) =>
            {
                let contact = self.offers.remove(&(user.clone(), req))?;
                match contact.addr.parse::<SocketAddr>() {
                    Ok(addr) => {
                        self.next_housekeeping.get_or_insert(now + HOUSEKEEPING);
                        // A repeated offer for a session we hold (the user asked again
                        // through a new broker or connection, so it never got the first
                        // grant) carries the key the user now gets: take it. The same key
                        // keeps its cipher (a fresh one would reuse nonces).
                        let fresh = || Remote {
                            user: user.clone(),
                            addr,
                            key: contact.key,
                            cipher: SessionCipher::new(&contact.key, Side::System),
                            last_heard: now,
                            ended: None,
                            probe: PathProbe::default(),
                        };
                        match self.sessions.get_mut(&session.0) {
                            Some(r) if r.key == contact.key => {}
                            Some(r) if r.ended.is_none() => {
                                tracing::info!(
                                    session = format!("{:x}", session.0),
                                    "a repeated offer brings a new session key: taken"
                                );
                                *r = fresh();
                            }
                            Some(_) => {}
                            None => {
                                self.sessions.insert(session.0, fresh());
                                // Its early datagrams, at the next turn of the loop.
                                if self.early.holds(session.0) {
                                    self.next_housekeeping = Some(now);
                                }
                            }
                        }
                    }
                    Err(e) => tracing::warn!("bad remote address {:?}: {e}", contact.addr),
                }
                // The broker delivers the grant (with the key) to the remote user.
                None
            }
            SystemOutput::ToUser(user, msg) => {
                let session = match &msg {
                    ToUser::Update { session, .. }
                    | ToUser::Status { session, .. }
                    | ToUser::Ended { session, .. } => *session,
                    _ => return Some(SystemOutput::ToUser(user, msg)),
                };
                if !self.sessions.contains_key(&session.0) {
                    return Some(SystemOutput::ToUser(user, msg));
                }
                if let ToUser::Ended {
                    reason, last_seq, ..
                } = &msg
                {
                    if let Some(r) = self.sessions.get_mut(&session.0) {
                        r.ended = Some((now, reason.clone(), *last_seq));
                    }
                }
                self.send(session.0, &SessionDown::Msg(msg));
                None
            }
            SystemOutput::WatchUser(user, _) | SystemOutput::ForgetUser(user)
                if self.is_remote(&user) =>
            {
                None
            }
            other => Some(other),
        }
    }

    fn is_remote(&self, user: &UserId) -> bool {
        self.sessions.values().any(|r| r.user == *user)
    }

    /// One datagram from `from` at `now`: its messages go to `core`.
    pub fn handle(&mut self, now: Instant, from: SocketAddr, bytes: &[u8], core: &mut SystemCore) {
        self.stats.datagrams_in += 1;
        self.on_datagram(now, from, bytes, core);
    }

    /// Hands the core the early datagrams of sessions now open, in the order they came.
    fn replay_early(&mut self, now: Instant, session: Option<u64>, core: &mut SystemCore) {
        if self.early.is_empty() {
            return;
        }
        let open: Vec<u64> = match session {
            Some(s) => vec![s],
            None => self.sessions.keys().copied().collect(),
        };
        for s in open {
            for (bytes, from) in self.early.take(now, s) {
                self.on_datagram(now, from, &bytes, core);
            }
        }
    }

    fn on_datagram(&mut self, now: Instant, from: SocketAddr, bytes: &[u8], core: &mut SystemCore) {
        let (session, nonce, sealed) = match Datagram::decode(bytes) {
            Ok(Datagram::Session {
                session,
                nonce,
                sealed,
            }) => (session, nonce, sealed),
            Ok(_) => return self.stats.drops.drop("unexpected_kind", &from),
            Err(_) => return self.stats.drops.drop("malformed", &from),
        };
        if !self.sessions.contains_key(&session) {
            if self.early.keep(now, bytes.to_vec(), from) {
                self.stats.drops.drop("unknown_session", &from);
            }
            return;
        }
        // What came before it, first.
        if self.early.holds(session) {
            self.replay_early(now, Some(session), core);
        }
        let Some(r) = self.sessions.get_mut(&session) else {
            return;
        };
        let Ok(plain) = r.cipher.open(session, nonce, sealed) else {
            return self.stats.drops.drop("forged_or_replayed", &from);
        };
        r.last_heard = now;
        let user = r.user.clone();
        let ended = r.ended.clone();
        let msg = match from_bytes::<SessionUp>(&plain) {
            Ok(m) => m,
            Err(_) => return self.stats.drops.drop("bad_message", &from),
        };
        // From a new address: validate the path before streaming there (RFC 9000 §9);
        // the stream stays on the old address until the challenge is echoed from it.
        if from != r.addr {
            if let SessionUp::PathResponse { token } = msg {
                if r.probe.answered(from, token) {
                    r.addr = from;
                    self.stats.migrations += 1;
                }
                return;
            }
            // The challenge is sealed: only the key's holder can echo it, so the token
            // needs to be unique, not secret.
            if let Some(token) = r.probe.challenge(from, now, || nonce) {
                self.stats.path_challenges += 1;
                self.send_to(session, from, &SessionDown::PathChallenge { token });
            }
        }
        let id = SessionId(session);
        match (msg, ended) {
            (SessionUp::Keepalive, None) => self.send(session, &SessionDown::Alive),
            (SessionUp::Keepalive, Some((_, reason, last_seq))) => self.send(
                session,
                &SessionDown::Msg(ToUser::Ended {
                    session: id,
                    reason,
                    last_seq,
                }),
            ),
            (SessionUp::Msg(ToSystem::Input { payload, .. }), None) => {
                core.handle(ToSystem::Input {
                    user,
                    session: id,
                    payload,
                })
            }
            // The core confirms with `Ended` (routed back here, which marks the session
            // ended so its key lingers for repeats that cross the answer).
            (SessionUp::Msg(ToSystem::End { .. }), None) => {
                core.handle(ToSystem::End { user, session: id })
            }
            // Already ended: say so again (the user retries `End` until it hears).
            (SessionUp::Msg(ToSystem::End { .. }), Some((_, reason, last_seq))) => self.send(
                session,
                &SessionDown::Msg(ToUser::Ended {
                    session: id,
                    reason,
                    last_seq,
                }),
            ),
            (SessionUp::Msg(ToSystem::Input { .. }), Some(_)) => {}
            (SessionUp::Msg(_), _) => self.stats.drops.drop("not_a_session_message", &from),
            (SessionUp::PathResponse { .. }, _) => {}
        }
    }

    /// When [`RemoteSessions::handle_timeout`] is next due.
    pub fn poll_timeout(&self) -> Option<Instant> {
        if self.sessions.is_empty() {
            None
        } else {
            self.next_housekeeping
        }
    }

    /// Ends silent sessions and forgets old ended ones, if due.
    pub fn handle_timeout(&mut self, now: Instant, core: &mut SystemCore) {
        if self.poll_timeout().is_none_or(|t| now < t) {
            return;
        }
        self.replay_early(now, None, core);
        self.next_housekeeping = Some(now + HOUSEKEEPING);
        let silent: Vec<u64> = self
            .sessions
            .iter()
            .filter(|(_, r)| r.ended.is_none() && now.duration_since(r.last_heard) >= LEASE)
            .map(|(id, _)| *id)
            .collect();
        for id in silent {
            tracing::info!(
                session = format!("{id:x}"),
                "remote user silent: session ended"
            );
            self.stats.leases_expired += 1;
            core.end_session(SessionId(id), EndReason::PeerGone);
            // A session the core no longer knows still needs its linger mark.
            if let Some(r) = self.sessions.get_mut(&id) {
                r.ended.get_or_insert((now, EndReason::PeerGone, 0));
            }
        }
        self.sessions.retain(|_, r| {
            r.ended
                .as_ref()
                .is_none_or(|(t, ..)| now.duration_since(*t) < LINGER)
        });
    }

    fn send(&mut self, session: u64, m: &SessionDown) {
        let Some(addr) = self.sessions.get(&session).map(|r| r.addr) else {
            return;
        };
        self.send_to(session, addr, m);
    }

    fn send_to(&mut self, session: u64, addr: SocketAddr, m: &SessionDown) {
        let Some(r) = self.sessions.get_mut(&session) else {
            return;
        };
        let Ok(dg) = seal_session(&mut r.cipher, session, m) else {
            return self.stats.drops.drop("too_large_for_a_datagram", &addr);
        };
        self.stats.datagrams_out += 1;
        self.out.push_back(Transmit {
            to: addr,
            bytes: dg,
        });
    }
}

/// A socket driving [`RemoteSessions`].
pub struct UdpSessions {
    sock: UdpSocket,
    local: SocketAddr,
    /// The sessions' logic.
    pub logic: RemoteSessions,
}

impl UdpSessions {
    /// Binds the endpoint.
    pub fn bind(addr: SocketAddr) -> std::io::Result<Self> {
        let sock = UdpSocket::bind(addr)?;
        sock.set_nonblocking(true)?;
        if let Err(e) = size_recv_buffer(&sock) {
            tracing::debug!("cannot size the receive buffer: {e}");
        }
        let local = sock.local_addr()?;
        Ok(UdpSessions {
            sock,
            local,
            logic: RemoteSessions::default(),
        })
    }

    /// The bound address (announced in the registration).
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// The socket, for the reactor.
    pub fn fd(&self) -> RawFd {
        self.sock.as_raw_fd()
    }

    /// Reads waiting datagrams and feeds their messages to the core.
    pub fn on_readable(&mut self, core: &mut SystemCore) {
        let mut buf = [0u8; MAX_DATAGRAM + 1];
        for _ in 0..RECV_BATCH {
            let Some((n, from)) = recv_one(&self.sock, &mut buf) else {
                break;
            };
            self.logic.handle(Instant::now(), from, &buf[..n], core);
        }
        self.transmit();
    }

    /// Sends what the logic queued.
    pub fn transmit(&mut self) {
        while let Some(t) = self.logic.poll_transmit() {
            send_transmit(&self.sock, &t, &mut self.logic.stats.drops);
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use muster_shared::types::{ServiceId, ServiceKind, ServiceSpec};

    fn offer(core: &mut SystemCore, r: &mut RemoteSessions, now: Instant, ticket: u64, key: u8) {
        let msg = ToSystem::Offer {
            ticket,
            session: SessionId::for_request(
                &ServiceId::new("t1", "s0"),
                &UserId("alice.x".into()),
                1,
            ),
            user: UserId("alice.x".into()),
            user_pid: 0,
            req: 1,
            service: "s0".into(),
            remote: Some(RemoteContact {
                addr: "10.0.2.1:5000".into(),
                key: [key; 32],
            }),
        };
        r.note(&msg);
        core.handle(msg);
        while let Some(o) = core.poll_output() {
            let _ = r.route(now, o);
        }
    }

    /// System t1 with one service, s0, and its remote endpoint.
    fn system(kind: ServiceKind, payload: &str) -> (SystemCore, RemoteSessions) {
        let spec = ServiceSpec {
            name: "s0".into(),
            description: String::new(),
            kind,
            queue: false,
            quota: 5,
            payload: payload.into(),
            schema: None,
        };
        (
            SystemCore::new("t1", 1, vec![spec]),
            RemoteSessions::default(),
        )
    }

    /// A keepalive from the user under cipher `c`: whether the endpoint answers it.
    fn alive(
        core: &mut SystemCore,
        r: &mut RemoteSessions,
        now: Instant,
        c: &mut SessionCipher,
    ) -> bool {
        let id = core.sessions().next().unwrap().0 .0;
        let d = seal_session(c, id, &SessionUp::Keepalive).unwrap();
        let from: SocketAddr = "10.0.2.1:5000".parse().unwrap();
        r.handle(now, from, &d, core);
        std::iter::from_fn(|| r.poll_transmit()).count() == 1
    }

    #[test]
    fn a_repeated_offer_with_a_new_key_moves_the_session_to_it() {
        let (mut core, mut r) = system(ServiceKind::Data, "pose2d");
        let now = Instant::now();
        let mut k1 = SessionCipher::new(&[1; 32], Side::User);
        let mut k2 = SessionCipher::new(&[2; 32], Side::User);
        offer(&mut core, &mut r, now, 1, 1);
        assert!(alive(&mut core, &mut r, now, &mut k1));
        // The same request through a new broker: the same session, the user's new key.
        offer(&mut core, &mut r, now, 2, 2);
        assert_eq!(core.sessions().count(), 1);
        assert!(
            alive(&mut core, &mut r, now, &mut k2),
            "the user's key works"
        );
        assert!(
            !alive(&mut core, &mut r, now, &mut k1),
            "the old one no longer"
        );
        // The same key again keeps the cipher: its replay window still holds.
        offer(&mut core, &mut r, now, 3, 2);
        assert!(alive(&mut core, &mut r, now, &mut k2));
        let mut replay = SessionCipher::new(&[2; 32], Side::User);
        assert!(
            !alive(&mut core, &mut r, now, &mut replay),
            "nonce 0 again is a replay"
        );
    }

    #[test]
    fn a_users_datagrams_that_come_before_the_offer_are_kept_and_taken_in_order() {
        let (mut core, mut r) = system(ServiceKind::Command, "scalar");
        let now = Instant::now();
        let user = UserId("alice.x".into());
        let id = SessionId::for_request(&ServiceId::new("t1", "s0"), &user, 1);
        let from: SocketAddr = "10.0.2.1:5000".parse().unwrap();
        // The user heard of its grant first: a keepalive and two inputs, before the
        // broker wrote us the offer.
        let mut c = SessionCipher::new(&[1; 32], Side::User);
        let input = |x: f64| {
            SessionUp::Msg(ToSystem::Input {
                user: user.clone(),
                session: id,
                payload: muster_shared::types::Payload::Scalar(x),
            })
        };
        for m in [SessionUp::Keepalive, input(1.0), input(2.0)] {
            let d = seal_session(&mut c, id.0, &m).unwrap();
            r.handle(now, from, &d, &mut core);
        }
        assert_eq!(r.poll_transmit(), None, "nothing to answer yet");
        assert_eq!(r.stats().drops.total(), 0, "kept, not dropped");
        // A third input after the offer: the early ones go first.
        offer(&mut core, &mut r, now, 1, 1);
        assert_eq!(
            r.poll_timeout(),
            Some(now),
            "the early ones are due at once"
        );
        let d = seal_session(&mut c, id.0, &input(3.0)).unwrap();
        r.handle(now, from, &d, &mut core);
        let inputs: Vec<f64> = std::iter::from_fn(|| core.poll_event())
            .filter_map(|e| match e {
                crate::core::SystemEvent::Input {
                    payload: muster_shared::types::Payload::Scalar(x),
                    ..
                } => Some(x),
                _ => None,
            })
            .collect();
        assert_eq!(inputs, [1.0, 2.0, 3.0]);
        // The keepalive was answered.
        assert_eq!(std::iter::from_fn(|| r.poll_transmit()).count(), 1);
        assert_eq!(r.stats().drops.total(), 0);
        // Nothing left to replay: a later housekeeping hands the core nothing again.
        r.handle_timeout(now, &mut core);
        assert!(std::iter::from_fn(|| core.poll_event())
            .all(|e| !matches!(e, crate::core::SystemEvent::Input { .. })));
    }

    #[test]
    fn early_datagrams_with_no_more_coming_are_taken_at_the_next_turn() {
        let (mut core, mut r) = system(ServiceKind::Data, "pose2d");
        let now = Instant::now();
        let id = SessionId::for_request(&ServiceId::new("t1", "s0"), &UserId("alice.x".into()), 1);
        let from: SocketAddr = "10.0.2.1:5000".parse().unwrap();
        let mut c = SessionCipher::new(&[1; 32], Side::User);
        let d = seal_session(&mut c, id.0, &SessionUp::Keepalive).unwrap();
        r.handle(now, from, &d, &mut core);
        // A session of someone else's, never offered: it only expires.
        let mut other = SessionCipher::new(&[9; 32], Side::User);
        let junk = seal_session(&mut other, 77, &SessionUp::Keepalive).unwrap();
        r.handle(now, from, &junk, &mut core);
        offer(&mut core, &mut r, now, 1, 1);
        r.handle_timeout(now, &mut core);
        assert_eq!(
            std::iter::from_fn(|| r.poll_transmit()).count(),
            1,
            "the keepalive is answered"
        );
        assert_eq!(
            r.early.len(),
            1,
            "the other session's stays until it expires"
        );
        assert!(r.stats().drops.total() == 0);
    }
}
