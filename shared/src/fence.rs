//! The instance's fence: which broker may act on it.
//!
//! One 64-bit word in a small shared-memory file beside iceoryx2's metadata holds the
//! current *term* and the primary's pid. A broker becomes primary by swapping the word
//! it saw for the next term and its own pid (compare-and-swap: of two standbys racing
//! for a dead primary, one wins). The primary checks the word before it acts each time
//! it wakes: once another broker holds a newer term, it has been taken over (it was
//! stopped or hung past its deadline) and stops without writing anything. A third word
//! is the primary loop's heartbeat ([`Fence::beat`]): the progress a standby reads
//! before it takes a silent primary for hung.

use std::os::fd::AsRawFd;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};

/// A term and the pid of the broker holding it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Holder {
    /// Incremented at every takeover.
    pub term: u32,
    /// The primary's pid (0: none yet).
    pub pid: u32,
}

impl Holder {
    fn word(self) -> u64 {
        (u64::from(self.term) << 32) | u64::from(self.pid)
    }

    fn of(word: u64) -> Self {
        Holder {
            term: (word >> 32) as u32,
            pid: word as u32,
        }
    }
}

/// The mapped fence file.
pub struct Fence {
    word: *const AtomicU64,
    path: PathBuf,
}

// SAFETY: the mapping lives as long as the Fence and is only touched through atomics.
unsafe impl Send for Fence {}

const SIZE: usize = 4096;

impl Fence {
    /// Opens (creating if needed) the fence of `inst`.
    pub fn open(inst: &crate::Instance) -> std::io::Result<Self> {
        let path = Self::path(inst);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)?;
        if file.metadata()?.len() < SIZE as u64 {
            file.set_len(SIZE as u64)?;
        }
        // SAFETY: a fresh shared mapping of a file we hold open, SIZE bytes long; the
        // kernel keeps it valid after the descriptor closes.
        let ptr = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                SIZE,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_SHARED,
                file.as_raw_fd(),
                0,
            )
        };
        if ptr == libc::MAP_FAILED {
            return Err(std::io::Error::last_os_error());
        }
        Ok(Fence {
            word: ptr.cast::<AtomicU64>(),
            path,
        })
    }

    fn atomic(&self) -> &AtomicU64 {
        // SAFETY: page-aligned, mapped for the Fence's lifetime; u64 atomics on shared
        // memory are sound across processes on Linux.
        unsafe { &*self.word }
    }

    fn list_word(&self) -> &AtomicU64 {
        // SAFETY: the second word of the same page-sized mapping.
        unsafe { &*self.word.add(1) }
    }

    fn beat_word(&self) -> &AtomicU64 {
        // SAFETY: the third word of the same page-sized mapping.
        unsafe { &*self.word.add(2) }
    }

    /// The primary's loop passed now (`CLOCK_MONOTONIC` nanoseconds, the same clock in
    /// every process): the progress a standby reads before taking a silent primary for
    /// hung. One relaxed store per pass.
    pub fn beat(&self) {
        self.beat_word()
            .store(crate::protocol::monotonic_ns(), Ordering::Release);
    }

    /// When the primary's loop last passed (`CLOCK_MONOTONIC` ns; 0: never).
    pub fn last_beat(&self) -> u64 {
        self.beat_word().load(Ordering::Acquire)
    }

    /// The epoch of the broker run whose service list readers should read (0: none).
    pub fn list(&self) -> u64 {
        self.list_word().load(Ordering::Acquire)
    }

    /// Names the service list of broker run `epoch` as the one to read.
    pub fn set_list(&self, epoch: u64) {
        self.list_word().store(epoch, Ordering::Release);
    }

    /// Who holds the instance now.
    pub fn holder(&self) -> Holder {
        Holder::of(self.atomic().load(Ordering::Acquire))
    }

    /// Takes the next term from `seen` for `pid`; false if someone else moved it first.
    pub fn claim(&self, seen: Holder, pid: u32) -> Option<Holder> {
        let next = Holder {
            term: seen.term.wrapping_add(1),
            pid,
        };
        self.atomic()
            .compare_exchange(
                seen.word(),
                next.word(),
                Ordering::AcqRel,
                Ordering::Acquire,
            )
            .ok()
            .map(|_| next)
    }

    /// Whether `me` still holds the instance.
    pub fn holds(&self, me: Holder) -> bool {
        self.holder() == me
    }

    /// Opens the fence of `inst` if a broker ever made one (for peers, which only read it).
    pub fn open_existing(inst: &crate::Instance) -> std::io::Result<Self> {
        let path = Self::path(inst);
        if !path.exists() {
            return Err(std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "no broker has run on this instance",
            ));
        }
        Self::open(inst)
    }

    fn path(inst: &crate::Instance) -> PathBuf {
        PathBuf::from(format!(
            "{}{}.broker-fence",
            crate::names::iox2_root(),
            inst
        ))
    }

    /// Removes the file (the last broker of the instance stopping on purpose). Those
    /// who still map it see no primary and no list, and look for a new file.
    pub fn remove(&self) {
        let h = self.holder();
        self.atomic().store(
            Holder {
                term: h.term,
                pid: 0,
            }
            .word(),
            Ordering::Release,
        );
        self.set_list(0);
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Removes the fence of `inst` if no live broker holds it (every broker of a run was
/// stopped, and the last one, stopped in the middle of taking over, could not remove
/// it); returns whether it did.
pub fn remove_if_orphaned(inst: &crate::Instance) -> bool {
    let Ok(f) = Fence::open_existing(inst) else {
        return false;
    };
    let h = f.holder();
    if h.pid != 0 && crate::reactor::process_alive(h.pid) {
        return false;
    }
    f.remove();
    true
}

impl Drop for Fence {
    fn drop(&mut self) {
        // SAFETY: the mapping made in `open`, unmapped once.
        unsafe { libc::munmap(self.word as *mut libc::c_void, SIZE) };
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn one_of_two_claims_wins_and_the_loser_sees_it() {
        let inst = crate::Instance::new(&format!("fence-{}", std::process::id())).unwrap();
        let a = Fence::open(&inst).unwrap();
        let b = Fence::open(&inst).unwrap();
        let seen = a.holder();
        let won = a.claim(seen, 11).unwrap();
        assert_eq!(
            won,
            Holder {
                term: seen.term + 1,
                pid: 11
            }
        );
        // b saw the same old holder: its claim fails, and it reads a's.
        assert_eq!(b.claim(seen, 12), None);
        assert_eq!(b.holder(), won);
        assert!(a.holds(won));
        // b takes over from a; a is fenced.
        let next = b.claim(won, 12).unwrap();
        assert!(!a.holds(won));
        assert_eq!(a.holder(), next);
        a.remove();
        assert!(!a.path.exists());
    }

    #[test]
    fn only_a_fence_no_live_broker_holds_is_removed_as_orphaned() {
        let inst = crate::Instance::new(&format!("orphan-{}", std::process::id())).unwrap();
        assert!(!remove_if_orphaned(&inst), "no fence: nothing to do");
        let f = Fence::open(&inst).unwrap();
        // Held by this (live) process: kept.
        let mine = f.claim(f.holder(), std::process::id()).unwrap();
        assert!(!remove_if_orphaned(&inst));
        assert!(f.path.exists());
        // Held by a process that is gone: removed.
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let gone = child.id();
        child.wait().unwrap();
        f.claim(mine, gone).unwrap();
        assert!(remove_if_orphaned(&inst));
        assert!(!f.path.exists());
    }
}
