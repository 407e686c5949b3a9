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
        TeardownTurn {
            dir: take_place(vec![iox2_root()], 0, patience),
        }
    }

    /// Whether the turn is held (not gone on without it).
    pub fn held(&self) -> bool {
        self.dir.is_some()
    }
}

/// One of this machine's two turns to create the shared memory of a new user, held
/// until dropped: an exclusive `flock` on the iceoryx2 root's `nodes/` or `services/`
/// directory (not the teardown's, so an arrival does not wait for a departure). Users
/// arriving by the hundred otherwise queue on the directories' locks as leaving ones
/// do, and the broker's creations (its port into a new inbox) wait behind them. Two at
/// a time, not one: a setup is about 2 ms of CPU, and one at a time leaves a core idle
/// (measured, 900 users a process each starting together: one place, 9 ms a setup
/// under load, and the turn's patience ran out for the last hundreds).
pub struct SetupTurn {
    dir: Option<std::fs::File>,
}

impl SetupTurn {
    /// Takes a free place if there is one, or else waits for place `prefer` (modulo the
    /// places), sleeping, for at most `patience`. Where no place can be opened, goes
    /// on at once.
    pub fn wait(prefer: usize, patience: Duration) -> SetupTurn {
        let root = iox2_root();
        Self::wait_in(
            vec![format!("{root}nodes"), format!("{root}services")],
            prefer,
            patience,
        )
    }

    fn wait_in(places: Vec<String>, prefer: usize, patience: Duration) -> SetupTurn {
        SetupTurn {
            dir: take_place(places, prefer, patience),
        }
    }

    /// Whether a place is held (not gone on without one).
    pub fn held(&self) -> bool {
        self.dir.is_some()
    }
}

/// An exclusive `flock` on one of `paths` (directories): the first free one, or else
/// `paths[prefer % len]` when it comes free, within `patience`. `None` when none could
/// be opened or the patience ran out.
fn take_place(paths: Vec<String>, prefer: usize, patience: Duration) -> Option<std::fs::File> {
    let (tx, rx) = std::sync::mpsc::sync_channel(1);
    let spawned = std::thread::Builder::new()
        .name("shm-turn".into())
        .spawn(move || {
            let mut dirs: Vec<_> = paths
                .iter()
                .filter_map(|p| std::fs::File::open(p).ok())
                .collect();
            if dirs.is_empty() {
                let _ = tx.send(None);
                return;
            }
            // SAFETY: flock(2) on descriptors this thread owns.
            let free = dirs.iter().position(|d| unsafe {
                libc::flock(d.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) == 0
            });
            if let Some(i) = free {
                let _ = tx.send(Some(dirs.swap_remove(i)));
                return;
            }
            let dir = dirs.swap_remove(prefer % dirs.len());
            loop {
                // SAFETY: as above.
                if unsafe { libc::flock(dir.as_raw_fd(), libc::LOCK_EX) } == 0 {
                    // Given up on meanwhile: the place goes to the next at once.
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
        return None;
    }
    rx.recv_timeout(patience).ok().flatten()
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

    #[test]
    fn two_set_up_at_once_a_third_waits_for_a_place_and_past_its_patience_goes_on() {
        let root = std::env::temp_dir().join(format!("setup-turn-{}", std::process::id()));
        let places: Vec<String> = ["a", "b"]
            .iter()
            .map(|p| {
                let d = root.join(p);
                std::fs::create_dir_all(&d).unwrap();
                d.to_string_lossy().into_owned()
            })
            .collect();
        let wait = |prefer, patience| SetupTurn::wait_in(places.clone(), prefer, patience);
        // Two places, both free: the first two take one each, whichever they prefer.
        let first = wait(0, Duration::from_secs(5));
        let second = wait(0, Duration::from_secs(5));
        assert!(first.held() && second.held());
        // A third waits its patience, then goes on without one.
        let t = Instant::now();
        assert!(!wait(1, Duration::from_millis(100)).held());
        assert!(t.elapsed() >= Duration::from_millis(100));
        // A waiter for the second's place has it once the second lets go.
        let p = places.clone();
        let waiter =
            std::thread::spawn(move || SetupTurn::wait_in(p, 1, Duration::from_secs(5)).held());
        std::thread::sleep(Duration::from_millis(50));
        drop(second);
        assert!(waiter.join().unwrap());
        // A place that cannot be opened is skipped; none at all: on at once, without.
        let missing = root.join("missing").to_string_lossy().into_owned();
        drop(first);
        assert!(SetupTurn::wait_in(
            vec![missing.clone(), places[0].clone()],
            0,
            Duration::from_secs(5)
        )
        .held());
        let t = Instant::now();
        assert!(!SetupTurn::wait_in(vec![missing], 0, Duration::from_secs(5)).held());
        assert!(t.elapsed() < Duration::from_secs(5));
        std::fs::remove_dir_all(&root).unwrap();
    }
}
