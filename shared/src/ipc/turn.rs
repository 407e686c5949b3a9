//! One teardown at a time: a process leaving removes its shared-memory files, and every
//! removal (and creation) in `/dev/shm` takes that directory's lock. Hundreds of users
//! leaving in the same second queue on it, each holding it in turn; a broker removing a
//! departed user's ports, or reading its inbox (iceoryx2's subscriber drops a departed
//! writer's connection there), waits behind them all, and more so when they run at a
//! low priority (measured: the broker asleep in `unlink` for up to 107 ms). A
//! [`TeardownTurn`] makes processes take turns: one removes its files while the others
//! sleep, so the broker waits for one removal at most.

#[allow(unused_imports)]
use super::*;
use std::os::fd::AsRawFd;

/// This machine's one turn to remove shared memory, held until dropped: an exclusive
/// `flock` on the iceoryx2 root directory (no file of its own to leave behind).
pub struct TeardownTurn {
    dir: Option<std::fs::File>,
}

impl TeardownTurn {
    /// Waits for the turn, sleeping, for at most `patience`: a process that holds it
    /// and was stopped, or is stuck, does not keep the others from leaving (they go on
    /// without it). Where the root cannot be opened (another user's), goes on at once.
    pub fn wait(patience: Duration) -> TeardownTurn {
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        let root = iox2_root();
        let spawned = std::thread::Builder::new()
            .name("teardown-turn".into())
            .spawn(move || {
                let Ok(dir) = std::fs::File::open(&root) else {
                    let _ = tx.send(None);
                    return;
                };
                loop {
                    // SAFETY: flock(2) on a descriptor this thread owns.
                    if unsafe { libc::flock(dir.as_raw_fd(), libc::LOCK_EX) } == 0 {
                        // Given up on meanwhile: the turn goes to the next at once.
                        let _ = tx.send(Some(dir));
                        return;
                    }
                    if std::io::Error::last_os_error().kind() != std::io::ErrorKind::Interrupted {
                        let _ = tx.send(None);
                        return;
                    }
                }
            });
        if spawned.is_err() {
            return TeardownTurn { dir: None };
        }
        TeardownTurn {
            dir: rx.recv_timeout(patience).ok().flatten(),
        }
    }

    /// Whether the turn is held (not gone on without it).
    pub fn held(&self) -> bool {
        self.dir.is_some()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn the_turn_goes_to_one_at_a_time_and_past_its_patience_on_without_it() {
        std::fs::create_dir_all(iox2_root()).unwrap();
        let first = TeardownTurn::wait(Duration::from_secs(5));
        assert!(first.held());
        // Another, while the first holds it: waits its patience, then goes on without.
        let t = Instant::now();
        let second = TeardownTurn::wait(Duration::from_millis(100));
        assert!(!second.held());
        assert!(t.elapsed() >= Duration::from_millis(100));
        // Held by a waiter once the first lets go.
        let waiter = std::thread::spawn(|| TeardownTurn::wait(Duration::from_secs(5)).held());
        std::thread::sleep(Duration::from_millis(50));
        drop(first);
        assert!(waiter.join().unwrap());
        // And free again after that.
        assert!(TeardownTurn::wait(Duration::from_secs(5)).held());
    }
}
