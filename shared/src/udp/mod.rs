//! The UDP path for remote users: datagram layout ([`wire`]), keys, handshake and
//! ciphers ([`crypto`]), the broker's access file ([`access`]) and the messages inside
//! the encrypted channels ([`msgs`]).

pub mod access;
pub mod crypto;
pub mod early;
pub mod msgs;
pub mod wire;

/// Most datagrams one wake-up reads from a socket, so a flood cannot starve the rest of
/// a process's work.
pub const RECV_BATCH: usize = 4096;

/// A datagram a sans-IO endpoint wants sent: the driver owns the socket and sends it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Transmit {
    /// Where to.
    pub to: std::net::SocketAddr,
    /// The whole datagram.
    pub bytes: Vec<u8>,
}

/// Sends `t` on `sock`; a failure (full buffer, unreachable) is counted as a drop, since
/// every datagram may be lost anyway and the endpoints retransmit what matters.
pub fn send_transmit(sock: &std::net::UdpSocket, t: &Transmit, drops: &mut DropCounters) {
    if sock.send_to(&t.bytes, t.to).is_err() {
        drops.drop("send_failed", &t.to);
    }
}

/// Receive buffer asked of the kernel for every muster UDP socket: a burst of a thousand
/// 1200-byte handshakes fits. The kernel caps it at `net.core.rmem_max` (the README says
/// how to raise that); the size obtained is returned.
pub const RECV_BUFFER: usize = 4 << 20;

/// Asks for [`RECV_BUFFER`] bytes of receive buffer on `sock`; returns what the kernel
/// granted (Linux reports twice the usable size).
pub fn size_recv_buffer(sock: &std::net::UdpSocket) -> std::io::Result<usize> {
    use std::os::fd::AsRawFd;
    let fd = sock.as_raw_fd();
    let want = RECV_BUFFER as libc::c_int;
    // SAFETY: fd is a valid socket for the lifetime of `sock`; the option value is a
    // c_int on the stack, of the size passed.
    let rc = unsafe {
        libc::setsockopt(
            fd,
            libc::SOL_SOCKET,
            libc::SO_RCVBUF,
            (&want as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    if rc != 0 {
        return Err(std::io::Error::last_os_error());
    }
    let mut got: libc::c_int = 0;
    let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
    // SAFETY: as above; `got` and `len` are valid for writes.
    let rc = unsafe {
        libc::getsockopt(
            fd,
            libc::SOL_SOCKET,
            libc::SO_RCVBUF,
            (&mut got as *mut libc::c_int).cast(),
            &mut len,
        )
    };
    if rc != 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(got.max(0) as usize)
}

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

/// Path validation for an authenticated peer whose datagrams come from a new address
/// (a NAT rebinding, or someone replaying them from elsewhere; RFC 9000 §9): a sealed
/// challenge goes to the new address, at most once per [`PathProbe::EVERY`], and the
/// peer's address moves only when the challenge is echoed from there.
#[derive(Clone, Copy, Debug, Default)]
pub struct PathProbe(Option<(std::net::SocketAddr, u64, std::time::Instant)>);

impl PathProbe {
    /// Least time between two challenges.
    pub const EVERY: std::time::Duration = std::time::Duration::from_millis(200);

    /// The challenge `token` echoed from `from`: whether that validates the path to
    /// `from` (the probe is then over).
    pub fn answered(&mut self, from: std::net::SocketAddr, token: u64) -> bool {
        let ok = self.0.is_some_and(|(a, t, _)| a == from && t == token);
        if ok {
            self.0 = None;
        }
        ok
    }

    /// A datagram came from `from`, not the peer's address: the token of a challenge to
    /// send there now (drawn from `token`), or `None` if one went there too recently.
    pub fn challenge(
        &mut self,
        from: std::net::SocketAddr,
        now: std::time::Instant,
        token: impl FnOnce() -> u64,
    ) -> Option<u64> {
        let due = self
            .0
            .is_none_or(|(a, _, at)| a != from || now.saturating_duration_since(at) >= Self::EVERY);
        if !due {
            return None;
        }
        let token = token();
        self.0 = Some((from, token, now));
        Some(token)
    }
}

#[cfg(test)]
mod path_probe_tests {
    use super::PathProbe;
    use std::time::{Duration, Instant};

    #[test]
    fn a_path_moves_only_on_its_own_echo_and_challenges_are_paced() {
        let (a, b) = ("10.0.0.1:1".parse().unwrap(), "10.0.0.2:1".parse().unwrap());
        let t = Instant::now();
        let mut p = PathProbe::default();
        assert!(!p.answered(a, 0), "nothing was sent");
        assert_eq!(p.challenge(a, t, || 7), Some(7));
        assert_eq!(p.challenge(a, t + Duration::from_millis(100), || 8), None);
        assert!(!p.answered(b, 7), "echoed from another address");
        assert!(!p.answered(a, 8), "another token");
        assert_eq!(p.challenge(a, t + PathProbe::EVERY, || 9), Some(9));
        assert!(!p.answered(a, 7), "only the newest challenge counts");
        // A challenge to another address replaces the first at once.
        assert_eq!(p.challenge(b, t + PathProbe::EVERY, || 10), Some(10));
        assert!(p.answered(b, 10));
        assert!(!p.answered(b, 10), "the probe is over");
    }
}
