//! Who may sign in, and who is signed in: the access file's `web` lines, browser
//! sessions behind an HttpOnly cookie, and a limit on failed sign-ins.

use muster_shared::udp::access::{AccessFile, Policy};
use std::collections::HashMap;
use std::net::IpAddr;
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime};

/// The session cookie's name.
pub const COOKIE: &str = "muster_session";
/// A browser session unused this long is forgotten.
pub const SESSION_IDLE: Duration = Duration::from_secs(12 * 3600);
/// Failed sign-ins allowed per client address, and per user name, in [`WINDOW`].
pub const FAILS_PER_ADDRESS: u32 = 5;
/// Failed sign-ins allowed per user name in [`WINDOW`] (from any address).
pub const FAILS_PER_USER: u32 = 20;
/// The window the failures are counted in.
pub const WINDOW: Duration = Duration::from_secs(60);
/// Addresses and names remembered at most (older ones go first).
const MAX_TRACKED: usize = 10_000;

/// 256 random bits as hex: a session cookie or a CSRF token.
pub fn random_token() -> String {
    let mut b = [0u8; 32];
    rand::fill(&mut b);
    hex::encode(b)
}

/// The access file, re-read when it changes on disk.
pub struct Access {
    path: PathBuf,
    file: AccessFile,
    mtime: Option<SystemTime>,
}

impl Access {
    /// Reads the file.
    pub fn load(path: PathBuf) -> Result<Self, String> {
        let file = AccessFile::load(&path)?;
        let mtime = std::fs::metadata(&path).and_then(|m| m.modified()).ok();
        Ok(Access { path, file, mtime })
    }

    /// Re-reads the file if it changed since; `Ok(true)` if it did. A file that no
    /// longer parses keeps the last good one (and says why).
    pub fn reload(&mut self) -> Result<bool, String> {
        let mtime = std::fs::metadata(&self.path)
            .and_then(|m| m.modified())
            .ok();
        if mtime == self.mtime {
            return Ok(false);
        }
        self.mtime = mtime;
        self.file = AccessFile::load(&self.path)?;
        Ok(true)
    }

    /// A user's policy.
    pub fn get(&self, user: &str) -> Option<&Policy> {
        self.file.get(user)
    }

    /// How many users may sign in on the web.
    pub fn web_users(&self) -> usize {
        self.file.users().filter(|(_, p)| p.web.is_some()).count()
    }
}

/// A signed-in browser.
#[derive(Clone, Debug)]
pub struct WebSession {
    /// The muster user.
    pub user: String,
    /// Sent back in the `X-CSRF-Token` header of state-changing HTTP requests.
    pub csrf: String,
    /// The token hash it signed in with: a changed or removed `web` line ends it.
    pub token_hash: [u8; 32],
    /// Last use.
    pub last_seen: Instant,
}

/// Failed sign-ins, counted per client address and per user name.
#[derive(Default)]
pub struct Limiter {
    by_address: HashMap<IpAddr, (Instant, u32)>,
    by_user: HashMap<String, (Instant, u32)>,
}

impl Limiter {
    /// How long `address` (or anyone trying `user`) must wait before trying again, if
    /// it has failed too often lately.
    pub fn blocked(&self, address: IpAddr, user: &str, now: Instant) -> Option<Duration> {
        let wait = |entry: Option<&(Instant, u32)>, limit: u32| {
            entry
                .filter(|(start, n)| *n >= limit && now < *start + WINDOW)
                .map(|(start, _)| *start + WINDOW - now)
        };
        wait(self.by_address.get(&address), FAILS_PER_ADDRESS)
            .into_iter()
            .chain(wait(self.by_user.get(user), FAILS_PER_USER))
            .max()
    }

    /// Counts a failed sign-in.
    pub fn failed(&mut self, address: IpAddr, user: &str, now: Instant) {
        fn bump<K: std::hash::Hash + Eq>(m: &mut HashMap<K, (Instant, u32)>, k: K, now: Instant) {
            if m.len() >= MAX_TRACKED {
                m.retain(|_, (start, _)| now < *start + WINDOW);
            }
            if m.len() >= MAX_TRACKED {
                return;
            }
            let e = m.entry(k).or_insert((now, 0));
            if now >= e.0 + WINDOW {
                *e = (now, 0);
            }
            e.1 += 1;
        }
        bump(&mut self.by_address, address, now);
        if !user.is_empty() && user.len() <= muster_shared::udp::access::MAX_USER_NAME {
            bump(&mut self.by_user, user.to_string(), now);
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn failures_block_an_address_for_the_rest_of_the_window_then_let_it_try_again() {
        let mut l = Limiter::default();
        let a: IpAddr = "127.0.0.1".parse().unwrap();
        let b: IpAddr = "127.0.0.2".parse().unwrap();
        let t0 = Instant::now();
        for i in 0..FAILS_PER_ADDRESS {
            assert!(l.blocked(a, "alice", t0).is_none(), "attempt {i}");
            l.failed(a, "alice", t0);
        }
        let wait = l.blocked(a, "alice", t0 + Duration::from_secs(10)).unwrap();
        assert_eq!(wait, Duration::from_secs(50));
        assert!(
            l.blocked(b, "alice", t0).is_none(),
            "another address still may"
        );
        assert!(
            l.blocked(a, "alice", t0 + WINDOW).is_none(),
            "the window passed"
        );
        // Names are limited too, across addresses.
        let mut l = Limiter::default();
        for i in 0..FAILS_PER_USER {
            l.failed(IpAddr::from([10, 0, (i / 256) as u8, i as u8]), "bob", t0);
        }
        assert!(l.blocked(b, "bob", t0).is_some());
        assert!(l.blocked(b, "carol", t0).is_none());
    }
}
