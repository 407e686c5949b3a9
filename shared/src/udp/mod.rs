//! The UDP path for remote users: datagram layout ([`wire`]), keys, handshake and
//! ciphers ([`crypto`]), the broker's access file ([`access`]) and the messages inside
//! the encrypted channels ([`msgs`]).

pub mod access;
pub mod crypto;
pub mod msgs;
pub mod wire;

/// Most datagrams one wake-up reads from a socket, so a flood cannot starve the rest of
/// a process's work.
pub const RECV_BATCH: usize = 4096;

/// Reads one datagram from a non-blocking socket into `buf`; `None` when none waits
/// (other errors are logged at debug level and also end the batch).
pub fn recv_one(
    sock: &std::net::UdpSocket,
    buf: &mut [u8],
) -> Option<(usize, std::net::SocketAddr)> {
    match sock.recv_from(buf) {
        Ok(x) => Some(x),
        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => None,
        Err(e) => {
            tracing::debug!("udp recv: {e}");
            None
        }
    }
}

/// Per-reason counters of dropped datagrams, and a rate-limited log line for them: the
/// 1st, 2nd, 4th, 8th, ... drop of each reason is logged.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub struct DropCounters {
    /// Drops by reason.
    pub by_reason: std::collections::BTreeMap<&'static str, u64>,
}

impl DropCounters {
    /// Counts one drop for `reason`, logging it if the count is a power of two.
    pub fn drop(&mut self, reason: &'static str, from: &std::net::SocketAddr) {
        let n = self.by_reason.entry(reason).or_insert(0);
        *n += 1;
        if n.is_power_of_two() {
            tracing::warn!(%from, dropped = *n, "dropped a datagram: {reason}");
        }
    }

    /// Counts one drop without logging (expected drops, e.g. updates in flight after a
    /// session ended).
    pub fn count(&mut self, reason: &'static str) {
        *self.by_reason.entry(reason).or_insert(0) += 1;
    }

    /// All drops.
    pub fn total(&self) -> u64 {
        self.by_reason.values().sum()
    }
}
