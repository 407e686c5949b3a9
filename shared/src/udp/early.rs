//! Session datagrams that came before their session was known.
//!
//! A session's two ends hear of it through the broker, each on its own path: the user
//! with its grant, the system with the offer. Either may hear the other's first
//! datagram before that (a system streams as soon as it grants; a remote user sends a
//! keepalive and its first input as soon as it is granted). Such a datagram cannot be
//! authenticated yet (its key comes with the grant or the offer), so it is kept a
//! moment, bounded, and replayed when the session opens: a lost first input would be a
//! silent loss.

use super::wire::Datagram;
use std::collections::HashMap;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// Most early datagrams kept.
pub const EARLY_MAX: usize = 64;
/// How long an early datagram is kept.
pub const EARLY_AGE: Duration = Duration::from_secs(2);

/// The early datagrams of an endpoint, oldest first.
#[derive(Debug, Default)]
pub struct Early {
    held: Vec<Held>,
}

/// One early datagram: when it came, its bytes, its sender, and its session (read from
/// its header once, as it is kept: [`Early::holds`] is asked for every datagram of an
/// open session while any is held).
#[derive(Debug)]
struct Held {
    at: Instant,
    bytes: Vec<u8>,
    from: SocketAddr,
    session: Option<u64>,
}

impl Early {
    /// Keeps a session datagram from `from` whose session is not known yet. Junk may
    /// fill the buffer: old entries expire, and when it is full the source holding the
    /// most entries loses its oldest (if it holds more than `from` would), so junk from
    /// a few addresses cannot push out a real peer's datagrams. Whether a datagram was
    /// dropped for room (this one or another).
    pub fn keep(&mut self, now: Instant, bytes: Vec<u8>, from: SocketAddr) -> bool {
        self.held
            .retain(|h| now.saturating_duration_since(h.at) < EARLY_AGE);
        let mut dropped = false;
        if self.held.len() >= EARLY_MAX {
            let mut by_source: HashMap<SocketAddr, usize> = HashMap::new();
            for h in &self.held {
                *by_source.entry(h.from).or_default() += 1;
            }
            let mine = by_source.get(&from).copied().unwrap_or(0);
            let top = by_source
                .into_iter()
                .filter(|(_, n)| *n > mine + 1)
                .max_by_key(|(a, n)| (*n, *a));
            let Some((victim, _)) = top else {
                return true;
            };
            if let Some(i) = self.held.iter().position(|h| h.from == victim) {
                self.held.remove(i);
            }
            dropped = true;
        }
        let session = session_of(&bytes);
        self.held.push(Held {
            at: now,
            bytes,
            from,
            session,
        });
        dropped
    }

    /// Takes session `session`'s datagrams still young at `now`, in arrival order, with
    /// their senders.
    pub fn take(&mut self, now: Instant, session: u64) -> Vec<(Vec<u8>, SocketAddr)> {
        let (mine, rest): (Vec<_>, Vec<_>) = std::mem::take(&mut self.held)
            .into_iter()
            .filter(|h| now.saturating_duration_since(h.at) < EARLY_AGE)
            .partition(|h| h.session == Some(session));
        self.held = rest;
        mine.into_iter().map(|h| (h.bytes, h.from)).collect()
    }

    /// Whether a datagram of session `session` is held.
    pub fn holds(&self, session: u64) -> bool {
        self.held.iter().any(|h| h.session == Some(session))
    }

    /// How many are held.
    pub fn len(&self) -> usize {
        self.held.len()
    }

    /// Whether none is held.
    pub fn is_empty(&self) -> bool {
        self.held.is_empty()
    }
}

fn session_of(bytes: &[u8]) -> Option<u64> {
    match Datagram::decode(bytes) {
        Ok(Datagram::Session { session, .. }) => Some(session),
        _ => None,
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn dg(session: u64, nonce: u64) -> Vec<u8> {
        Datagram::Session {
            session,
            nonce,
            sealed: &[7u8; 20],
        }
        .encode()
        .unwrap()
    }

    fn addr(port: u16) -> SocketAddr {
        SocketAddr::from(([10, 0, 0, 1], port))
    }

    #[test]
    fn a_sessions_datagrams_come_back_in_order_and_others_stay() {
        let t = Instant::now();
        let mut e = Early::default();
        assert!(!e.keep(t, dg(1, 10), addr(1)));
        assert!(!e.keep(t, dg(2, 20), addr(2)));
        assert!(!e.keep(t, dg(1, 11), addr(1)));
        assert!(e.holds(1) && e.holds(2) && !e.holds(3));
        let back = e.take(t, 1);
        assert_eq!(back, vec![(dg(1, 10), addr(1)), (dg(1, 11), addr(1))]);
        assert!(!e.holds(1));
        assert_eq!(e.len(), 1);
        assert_eq!(e.take(t, 2), vec![(dg(2, 20), addr(2))]);
        assert!(e.is_empty());
    }

    #[test]
    fn old_datagrams_expire() {
        let t = Instant::now();
        let mut e = Early::default();
        e.keep(t, dg(1, 1), addr(1));
        assert!(e.take(t + EARLY_AGE, 1).is_empty(), "expired");
        e.keep(t, dg(2, 1), addr(1));
        e.keep(t + EARLY_AGE, dg(3, 1), addr(1));
        assert_eq!(e.len(), 1, "the old one went when a new one came");
    }

    #[test]
    fn a_flood_from_one_source_cannot_push_out_another_sources_datagrams() {
        let t = Instant::now();
        let mut e = Early::default();
        e.keep(t, dg(9, 0), addr(9));
        let mut dropped = 0;
        for i in 0..(3 * EARLY_MAX as u64) {
            dropped += usize::from(e.keep(t, dg(100 + i, i), addr(1)));
        }
        assert_eq!(e.len(), EARLY_MAX);
        // Full, the flooder (holding the most) loses its own new ones.
        assert_eq!(dropped, 2 * EARLY_MAX + 1);
        assert!(e.holds(9), "the other source's datagram stays");
        let last_kept = 100 + EARLY_MAX as u64 - 2;
        assert!(e.holds(100) && e.holds(last_kept) && !e.holds(last_kept + 1));
        // A second real source still gets in, at the flooder's expense.
        assert!(e.keep(t, dg(8, 0), addr(8)));
        assert!(e.holds(8) && e.holds(9) && !e.holds(100));
    }

    #[test]
    fn junk_is_never_taken_for_a_session() {
        let t = Instant::now();
        let mut e = Early::default();
        e.keep(t, vec![0xff; 5], addr(1));
        assert!(!e.holds(0));
        assert!(e.take(t, 0).is_empty());
        assert_eq!(e.len(), 1, "it only expires");
    }
}
