//! Whether a session's frame fits the path it takes: a 4 KiB shared-memory frame
//! between local processes, or one sealed UDP datagram to or from a remote user. A frame
//! that does not fit is refused where it is made and the caller told, never handed to a
//! transport that would drop it unseen.

use crate::protocol::{ToSystem, ToUser};
use crate::types::Payload;

/// More than the bytes a frame adds around its variable-length text or data: header,
/// tags, ids, sequence number, stamp and length prefixes.
const FRAME_SLACK: usize = 128;

/// A frame too large for its path.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TooLarge {
    /// The frame's size on that path.
    pub bytes: usize,
    /// The path's limit.
    pub limit: usize,
    /// The path: `shared memory` or `UDP datagram`.
    pub path: &'static str,
}

impl std::fmt::Display for TooLarge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "a frame of {} bytes is larger than the {} bytes a {} takes",
            self.bytes, self.limit, self.path
        )
    }
}

/// The path a session's frames take.
fn limit_of(remote: bool) -> (usize, &'static str) {
    if remote {
        (crate::udp::wire::MAX_PLAINTEXT, "UDP datagram")
    } else {
        (crate::ipc::SMALL_FRAME, "shared memory")
    }
}

/// The bytes of text or data in `payload` (0 for a fixed-size built-in type).
fn variable(payload: &Payload) -> usize {
    match payload {
        Payload::Text(t) => t.len(),
        Payload::Encoded { type_name, data } => type_name.len() + data.len(),
        _ => 0,
    }
}

/// Measures `msg` only when its variable part comes near the limit: the usual frame
/// costs a length, not an encoding.
fn check<T: serde::Serialize>(
    variable: usize,
    remote: bool,
    encode_remote: impl FnOnce() -> Result<Vec<u8>, crate::udp::msgs::MsgError>,
    msg: &T,
) -> Result<(), TooLarge> {
    let (limit, path) = limit_of(remote);
    if variable + FRAME_SLACK <= limit {
        return Ok(());
    }
    let bytes = if remote {
        encode_remote().map_or(limit + 1, |b| b.len())
    } else {
        crate::protocol::encode(msg).map_or(crate::protocol::MAX_FRAME + 1, |b| b.len())
    };
    if bytes <= limit {
        Ok(())
    } else {
        Err(TooLarge { bytes, limit, path })
    }
}

/// Whether a system's frame `msg` fits its user's path (a remote user's datagram, else
/// shared memory).
pub fn to_user(msg: &ToUser, remote: bool) -> Result<(), TooLarge> {
    let v = match msg {
        ToUser::Update { payload, .. } => variable(payload),
        ToUser::Status { status, .. } => status.to_string().len(),
        _ => return Ok(()),
    };
    let down = || crate::udp::msgs::to_bytes(&crate::udp::msgs::SessionDown::Msg(msg.clone()));
    check(v, remote, down, msg)
}

/// Whether a user's frame `msg` fits the path to its system (the user's datagram if the
/// user is remote, else shared memory).
pub fn to_system(msg: &ToSystem, remote: bool) -> Result<(), TooLarge> {
    let v = match msg {
        ToSystem::Input { payload, .. } => variable(payload),
        _ => return Ok(()),
    };
    let up = || crate::udp::msgs::to_bytes(&crate::udp::msgs::SessionUp::Msg(msg.clone()));
    check(v, remote, up, msg)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::types::{SessionId, UserId};

    fn input(n: usize) -> ToSystem {
        ToSystem::Input {
            user: UserId("u".into()),
            session: SessionId(1),
            payload: Payload::Text("x".repeat(n)),
        }
    }

    #[test]
    fn an_input_fits_shared_memory_or_a_datagram_up_to_the_byte() {
        let (dgram, _) = limit_of(true);
        // Find the largest text that fits each path: one byte more does not.
        for remote in [false, true] {
            let (limit, path) = limit_of(remote);
            let fits = (0..limit)
                .rev()
                .find(|n| to_system(&input(*n), remote).is_ok());
            let n = fits.unwrap();
            assert!(n + 64 > limit - FRAME_SLACK, "{path}: {n} of {limit}");
            let e = to_system(&input(n + 1), remote).unwrap_err();
            assert_eq!((e.limit, e.path), (limit, path));
            assert!(e.bytes > limit, "{e}");
        }
        // A small input is never measured; a goal always fits.
        assert!(to_system(&input(10), true).is_ok());
        assert!(dgram < crate::ipc::SMALL_FRAME);
        let goal = ToSystem::Input {
            user: UserId("u".into()),
            session: SessionId(1),
            payload: Payload::Goal2d { x: 1.0, y: 2.0 },
        };
        assert!(to_system(&goal, true).is_ok());
    }
}
