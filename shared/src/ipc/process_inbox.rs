//! The inbox a process's users share: one inbox and one bell for every user a process
//! hosts (`muster user --count N`), read by a thread of its own that hands each frame
//! to its user's mailbox. The broker and the systems then hold one pair of ports for
//! the process (about ten descriptors at the broker), not one per user: at 5,000 local
//! users, 16 a process, the broker's descriptors were the limit.

use super::{create_node, open_envelope, Endpoint, InboxLimits, TransportError};
use crate::names::{Address, Instance};
use crate::reactor::{drain_eventfd, eventfd, ring_eventfd, Reactor};
use crate::types::UserId;
use std::collections::{HashMap, VecDeque};
use std::os::fd::{AsRawFd, OwnedFd, RawFd};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::thread::JoinHandle;

/// Most frames waiting in one user's mailbox; past it the oldest is dropped and
/// counted (a user whose thread stopped reading must not grow the process without
/// bound). A user's own inbox holds 128 per writer.
pub const MAILBOX_FRAMES: usize = 4096;

/// What a user's mailbox holds: frames with the pid of their writer, and bell ids.
struct Slot {
    frames: Mutex<VecDeque<(Vec<u8>, Option<u32>)>>,
    /// Bell ids other than "frames wait" rung since the user last looked (bit i = id i).
    rung: AtomicU64,
    wake: OwnedFd,
}

/// A user's mailbox in its process's shared inbox: its frames and bell ids, and a
/// descriptor that is readable when there are some. Dropping it leaves the inbox.
pub struct Mailbox {
    user: UserId,
    slot: Arc<Slot>,
    inbox: Weak<Shared>,
}

impl Mailbox {
    /// The descriptor readable when frames or bell ids wait.
    pub(super) fn fd(&self) -> RawFd {
        self.slot.wake.as_raw_fd()
    }

    /// Empties the wake-up; returns the bell ids rung since (bit i = id i).
    pub(super) fn drain(&self) -> u64 {
        drain_eventfd(&self.slot.wake);
        self.slot.rung.swap(0, Ordering::AcqRel)
    }

    /// The next frame, with its writer's pid.
    pub(super) fn take(&self) -> Option<(Vec<u8>, Option<u32>)> {
        lock(&self.slot.frames).pop_front()
    }
}

impl Drop for Mailbox {
    fn drop(&mut self) {
        if let Some(inbox) = self.inbox.upgrade() {
            lock(&inbox.mailboxes).remove(&self.user);
        }
    }
}

/// What the reading thread and the users share.
struct Shared {
    mailboxes: Mutex<HashMap<UserId, Arc<Slot>>>,
    stop: AtomicBool,
    wake: OwnedFd,
    counts: Counts,
}

/// Frames the reader could not hand to a user.
#[derive(Default)]
struct Counts {
    not_envelopes: AtomicU64,
    unknown_users: AtomicU64,
    overflowed: AtomicU64,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A user thread that panicked holding it left a queue that is still whole.
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// The inbox this process's users share, and the thread that reads it. Dropping it
/// stops the thread (after the users' endpoints are gone).
pub struct ProcessInbox {
    pid: u32,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

/// How big a [`ProcessInbox`] is: each possible writer costs its reader about 80 bytes
/// a frame it may have waiting (about 21 KiB at the default 256).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ProcessInboxSize {
    /// Most writers at once.
    pub writers: usize,
    /// Most frames one writer may have waiting.
    pub frames_per_writer: usize,
}

impl Default for ProcessInboxSize {
    fn default() -> Self {
        ProcessInboxSize {
            writers: super::MAX_PROCESS_INBOX_PEERS,
            frames_per_writer: super::PROCESS_INBOX_BUFFER,
        }
    }
}

impl ProcessInboxSize {
    /// Frames waiting per writer for each user of the process, past the default's: a
    /// system's tick to every session it serves there comes in one burst, and a user
    /// may hold two sessions of one system (a link: a data service and a command one).
    pub const FRAMES_PER_USER: usize = 2;

    /// The size for a process of `users` users: the default, with room for a burst of
    /// [`ProcessInboxSize::FRAMES_PER_USER`] frames to each of them from one writer
    /// (more than the default's 256 frames past 128 users).
    pub fn for_users(users: usize) -> Self {
        let d = Self::default();
        ProcessInboxSize {
            frames_per_writer: d
                .frames_per_writer
                .max(users.saturating_mul(Self::FRAMES_PER_USER)),
            ..d
        }
    }
}

/// Frames a [`ProcessInbox`] could not hand to a user, so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ProcessInboxStats {
    /// Frames that were not an envelope.
    pub not_envelopes: u64,
    /// Frames for a user not (or no longer) in this process.
    pub unknown_users: u64,
    /// Frames dropped from a full mailbox ([`MAILBOX_FRAMES`]).
    pub overflowed: u64,
}

const TOKEN_BELL: usize = 0;
const TOKEN_STOP: usize = 1;

impl ProcessInbox {
    /// Creates this process's shared inbox on `inst` and starts its reading thread.
    /// `size`: how many writers it takes (the broker and the systems its users hold
    /// sessions with) and how many frames each may have waiting (a system's update to
    /// every user of the process it serves comes in one burst; a frame past it is
    /// refused as to a full inbox, and a data update lost). [`ProcessInboxSize::default`]
    /// suits a harness's process of 16 users.
    pub fn start(inst: &Instance, size: ProcessInboxSize) -> Result<Self, TransportError> {
        let limits = InboxLimits {
            max_publishers: size.writers.max(2),
            buffer: size.frames_per_writer.max(1),
            ..InboxLimits::for_addr(&Address::Process(0))
        };
        let pid = std::process::id();
        let shared = Arc::new(Shared {
            mailboxes: Mutex::new(HashMap::new()),
            stop: AtomicBool::new(false),
            wake: eventfd().map_err(|e| TransportError::Node(format!("eventfd: {e}")))?,
            counts: Counts::default(),
        });
        let (opened, is_open) = std::sync::mpsc::sync_channel(1);
        let (inst, reader) = (inst.clone(), shared.clone());
        let thread = std::thread::Builder::new()
            .name("process-inbox".into())
            .spawn(move || {
                let endpoint =
                    create_node(&format!("process-inbox-{pid}"), false).and_then(|node| {
                        Endpoint::open_sized(&inst, Address::Process(pid), node, limits)
                    });
                let reactor = Reactor::new().map_err(|e| TransportError::Node(format!("{e}")));
                match (endpoint, reactor) {
                    (Ok(endpoint), Ok(reactor)) => {
                        let _ = opened.send(Ok(()));
                        read(endpoint, reactor, &reader);
                    }
                    (Err(e), _) | (_, Err(e)) => {
                        let _ = opened.send(Err(e));
                    }
                }
            })
            .map_err(|e| TransportError::Node(format!("the shared inbox's thread: {e}")))?;
        match is_open.recv() {
            Ok(Ok(())) => Ok(ProcessInbox {
                pid,
                shared,
                thread: Some(thread),
            }),
            Ok(Err(e)) => {
                let _ = thread.join();
                Err(e)
            }
            Err(_) => {
                let _ = thread.join();
                Err(TransportError::Node(
                    "the shared inbox's thread died".into(),
                ))
            }
        }
    }

    /// This process's shared inbox on `inst`: the one already open, or a new one of
    /// `size` ([`ProcessInbox::start`]). A process has one per instance (its name is
    /// the pid's), however many parts of it host users.
    pub fn of_this_process(
        inst: &Instance,
        size: ProcessInboxSize,
    ) -> Result<Arc<ProcessInbox>, TransportError> {
        static OPEN: Mutex<Vec<(Instance, Weak<ProcessInbox>)>> = Mutex::new(Vec::new());
        let mut open = lock(&OPEN);
        open.retain(|(_, w)| w.strong_count() > 0);
        if let Some(inbox) = open
            .iter()
            .find(|(i, _)| i == inst)
            .and_then(|(_, w)| w.upgrade())
        {
            return Ok(inbox);
        }
        let inbox = Arc::new(ProcessInbox::start(inst, size)?);
        open.push((inst.clone(), Arc::downgrade(&inbox)));
        Ok(inbox)
    }

    /// The address its writers write to.
    pub fn address(&self) -> Address {
        Address::Process(self.pid)
    }

    /// A new user id, `name` followed by this process's mark, for a user reached here.
    pub fn user_id(&self, name: &str) -> UserId {
        UserId::in_process_inbox(name, self.pid)
    }

    /// The users with a mailbox here.
    pub fn users(&self) -> usize {
        lock(&self.shared.mailboxes).len()
    }

    /// Frames it could not hand to a user, so far.
    pub fn stats(&self) -> ProcessInboxStats {
        let c = &self.shared.counts;
        ProcessInboxStats {
            not_envelopes: c.not_envelopes.load(Ordering::Relaxed),
            unknown_users: c.unknown_users.load(Ordering::Relaxed),
            overflowed: c.overflowed.load(Ordering::Relaxed),
        }
    }

    /// A mailbox for `user`, whose id must name this process's inbox.
    pub(super) fn join(&self, user: &UserId) -> Result<Mailbox, TransportError> {
        let me = Address::User(user.clone());
        if user.process_inbox() != Some(self.pid) || user.is_foreign() {
            return Err(TransportError::Send {
                peer: me,
                detail: format!("its id does not name process {}'s shared inbox", self.pid),
            });
        }
        let wake = eventfd().map_err(|e| TransportError::Node(format!("eventfd: {e}")))?;
        let slot = Arc::new(Slot {
            frames: Mutex::new(VecDeque::new()),
            rung: AtomicU64::new(0),
            wake,
        });
        let mut boxes = lock(&self.shared.mailboxes);
        if boxes.contains_key(user) {
            return Err(TransportError::InUse(me));
        }
        boxes.insert(user.clone(), slot.clone());
        Ok(Mailbox {
            user: user.clone(),
            slot,
            inbox: Arc::downgrade(&self.shared),
        })
    }
}

impl Drop for ProcessInbox {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
        ring_eventfd(&self.shared.wake);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The reading thread: each frame to its user's mailbox, each bell id but "frames
/// wait" to every user (a list change is news to each of them that watches).
fn read(mut endpoint: Endpoint, mut reactor: Reactor, shared: &Shared) {
    let added = reactor
        .add(endpoint.bell_fd(), TOKEN_BELL)
        .and_then(|()| reactor.add(shared.wake.as_raw_fd(), TOKEN_STOP));
    if let Err(e) = added {
        tracing::error!("the shared inbox's reader cannot wait: {e}");
        return;
    }
    let message = 1u64 << super::bell::MESSAGE;
    while !shared.stop.load(Ordering::Acquire) {
        let rung = endpoint.drain_bell() & !message;
        if rung != 0 {
            for slot in lock(&shared.mailboxes).values() {
                slot.rung.fetch_or(rung, Ordering::AcqRel);
                ring_eventfd(&slot.wake);
            }
        }
        while let Some((bytes, pid)) = endpoint.recv_from() {
            hand_over(shared, &bytes, pid);
        }
        if let Err(e) = reactor.wait(None) {
            tracing::error!("the shared inbox's reader cannot wait: {e}");
            return;
        }
        drain_eventfd(&shared.wake);
    }
}

/// Puts a frame read from the shared inbox into its user's mailbox.
fn hand_over(shared: &Shared, bytes: &[u8], pid: Option<u32>) {
    let c = &shared.counts;
    let Some((user, frame)) = open_envelope(bytes) else {
        if c.not_envelopes
            .fetch_add(1, Ordering::Relaxed)
            .is_power_of_two()
        {
            tracing::debug!(?pid, "a frame in the shared inbox that is not an envelope");
        }
        return;
    };
    let Some(slot) = lock(&shared.mailboxes).get(&user).cloned() else {
        if c.unknown_users
            .fetch_add(1, Ordering::Relaxed)
            .is_power_of_two()
        {
            tracing::debug!(%user, ?pid, "a frame in the shared inbox for a user not here");
        }
        return;
    };
    {
        let mut frames = lock(&slot.frames);
        if frames.len() >= MAILBOX_FRAMES {
            frames.pop_front();
            if c.overflowed
                .fetch_add(1, Ordering::Relaxed)
                .is_power_of_two()
            {
                tracing::warn!(%user, "a user's mailbox is full: dropped its oldest frame");
            }
        }
        frames.push_back((frame.to_vec(), pid));
    }
    ring_eventfd(&slot.wake);
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::ipc::bell;
    use std::time::{Duration, Instant};

    /// The next `n` frames `e` gets, waiting up to 5 s for them.
    fn frames(e: &mut Endpoint, n: usize) -> Vec<(Vec<u8>, Option<u32>)> {
        let deadline = Instant::now() + Duration::from_secs(5);
        let mut got = Vec::new();
        while got.len() < n && Instant::now() < deadline {
            match e.recv_from() {
                Some(f) => got.push(f),
                None => std::thread::sleep(Duration::from_millis(1)),
            }
        }
        got
    }

    #[test]
    fn a_processs_users_share_one_inbox_each_getting_its_own_frames_in_order() {
        let inst = Instance::new(&format!("pinbox-test-{}", std::process::id())).unwrap();
        let inbox = ProcessInbox::start(&inst, ProcessInboxSize::default()).unwrap();
        let pid = std::process::id();
        assert_eq!(inbox.address(), Address::Process(pid));
        let ids: Vec<UserId> = (0..3).map(|i| inbox.user_id(&format!("u{i}"))).collect();
        assert_eq!(ids[0].0, format!("u0~{pid}"));
        let mut users: Vec<Endpoint> = ids
            .iter()
            .map(|id| {
                let node = create_node("pinbox-test-u", false).unwrap();
                Endpoint::open_in_process_inbox(&inst, id.clone(), &inbox, node).unwrap()
            })
            .collect();
        assert_eq!(inbox.users(), 3);
        // A second mailbox for one user, and a user of another process's inbox: refused.
        let node = create_node("pinbox-test-x", false).unwrap();
        assert!(matches!(
            Endpoint::open_in_process_inbox(&inst, ids[0].clone(), &inbox, node),
            Err(TransportError::InUse(_))
        ));
        let node = create_node("pinbox-test-y", false).unwrap();
        let other = UserId::in_process_inbox("u9", pid + 1);
        assert!(Endpoint::open_in_process_inbox(&inst, other, &inbox, node).is_err());

        let s = Address::System("s".into());
        let mut system = Endpoint::open(
            &inst,
            s.clone(),
            create_node("pinbox-test-s", false).unwrap(),
        )
        .unwrap();
        // Interleaved frames to the three, and a control frame; then a list change for one.
        for k in 0..4 {
            for (i, u) in users.iter().enumerate() {
                let to = u.me().clone();
                system.send(&to, format!("{i}:{k}").as_bytes()).unwrap();
            }
        }
        system.send_control(users[1].me(), &7u32);
        system.ring(users[0].me(), bell::LIST_CHANGED).unwrap();
        assert_eq!(
            system.open_peers(),
            1,
            "one pair of ports for the process's users"
        );
        for (i, u) in users.iter_mut().enumerate() {
            let want = if i == 1 { 5 } else { 4 };
            let got = frames(u, want);
            assert_eq!(got.len(), want, "user {i}");
            for (k, (frame, from)) in got.iter().take(4).enumerate() {
                assert_eq!(frame, format!("{i}:{k}").as_bytes());
                assert_eq!(*from, Some(pid), "the writer's pid comes along");
            }
            if i == 1 {
                let control = crate::protocol::encode(&7u32).unwrap();
                assert_eq!(got[4].0, control, "the control frame after the updates");
            }
            assert_eq!(u.recv(), None, "nothing of another user's");
        }
        // A bell id reaches every user of the process (it names none); its readiness
        // shows on each user's descriptor, as its own bell's would.
        let deadline = Instant::now() + Duration::from_secs(5);
        let mut rung = [0u64; 3];
        while rung.iter().any(|r| r & (1 << bell::LIST_CHANGED) == 0) && Instant::now() < deadline {
            for (r, u) in rung.iter_mut().zip(&users) {
                *r |= u.drain_bell();
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        for r in rung {
            assert_ne!(r & (1 << bell::LIST_CHANGED), 0);
            assert_eq!(r & (1 << bell::MESSAGE), 0, "frames are not bell ids");
        }

        // A user writes to the system through its own ports, as itself.
        let u0 = users[0].me().clone();
        users[0].send(&s, b"hello").unwrap();
        let deadline = Instant::now() + Duration::from_secs(5);
        let got = loop {
            if let Some(f) = system.recv_from() {
                break Some(f);
            }
            if Instant::now() > deadline {
                break None;
            }
            std::thread::sleep(Duration::from_millis(1));
        };
        assert_eq!(got, Some((b"hello".to_vec(), Some(pid))));
        assert_eq!(
            system.owner_pid(&u0),
            Some(pid),
            "the process reads its users' inbox"
        );

        // A user that left: its frames are counted, not handed to another; and a frame
        // that is no envelope, written straight into the inbox, is counted too.
        let gone = users.pop().unwrap();
        let gone_addr = gone.me().clone();
        drop(gone);
        assert_eq!(inbox.users(), 2);
        system.send(&gone_addr, b"late").unwrap();
        system.send(&inbox.address(), b"").unwrap();
        system.send(users[0].me(), b"after").unwrap();
        assert_eq!(frames(&mut users[0], 1)[0].0, b"after");
        assert_eq!(
            inbox.stats(),
            ProcessInboxStats {
                not_envelopes: 1,
                unknown_users: 1,
                overflowed: 0
            }
        );
        assert_eq!(users[1].recv(), None);
        drop(users);
        drop(inbox);
    }

    #[test]
    fn a_writer_past_the_shared_inboxs_size_gets_an_error_not_a_silent_loss() {
        let inst = Instance::new(&format!("pinbox-cap-{}", std::process::id())).unwrap();
        let size = ProcessInboxSize {
            writers: 2,
            ..ProcessInboxSize::default()
        };
        let inbox = ProcessInbox::start(&inst, size).unwrap();
        let user = inbox.user_id("u0");
        let node = create_node("pinbox-cap-u", false).unwrap();
        let mut me = Endpoint::open_in_process_inbox(&inst, user.clone(), &inbox, node).unwrap();
        let to = Address::User(user);
        let mut systems: Vec<Endpoint> = (0..3)
            .map(|i| {
                let node = create_node("pinbox-cap-s", false).unwrap();
                Endpoint::open(&inst, Address::System(format!("s{i}")), node).unwrap()
            })
            .collect();
        assert!(systems[0].send(&to, b"0").is_ok());
        assert!(systems[1].send(&to, b"1").is_ok());
        let third = systems[2].send(&to, b"2");
        assert!(
            matches!(
                third,
                Err(TransportError::Send { .. } | TransportError::Service { .. })
            ),
            "{third:?}"
        );
        let got: Vec<Vec<u8>> = frames(&mut me, 2).into_iter().map(|(f, _)| f).collect();
        assert_eq!(got, [b"0".to_vec(), b"1".to_vec()]);
    }

    #[test]
    fn a_process_of_many_users_is_sized_for_a_burst_to_all_of_them_from_one_writer() {
        let d = ProcessInboxSize::default();
        assert_eq!(ProcessInboxSize::for_users(16), d);
        assert_eq!(ProcessInboxSize::for_users(128), d);
        let big = ProcessInboxSize::for_users(300);
        assert_eq!((big.writers, big.frames_per_writer), (d.writers, 600));
        // A burst of two frames to each of 300 users from one system, written while the
        // reading thread cannot hand any over (as when it waits for a core), reaches
        // every user whole and in order. At the default size 600 frames do not fit.
        let inst = Instance::new(&format!("pinbox-burst-{}", std::process::id())).unwrap();
        let inbox = ProcessInbox::start(&inst, big).unwrap();
        let mut users: Vec<Endpoint> = (0..300)
            .map(|i| {
                let node = create_node(&format!("pinbox-burst-u{i}"), false).unwrap();
                let id = inbox.user_id(&format!("u{i}"));
                Endpoint::open_in_process_inbox(&inst, id, &inbox, node).unwrap()
            })
            .collect();
        let node = create_node("pinbox-burst-s", false).unwrap();
        let mut system = Endpoint::open(&inst, Address::System("s".into()), node).unwrap();
        system.open_ports(users[0].me()).unwrap();
        let held = lock(&inbox.shared.mailboxes);
        let mut refused = 0;
        for round in 0..2u8 {
            for u in &users {
                refused += usize::from(system.send(u.me(), &[round]).is_err());
            }
        }
        drop(held);
        assert_eq!(refused, 0);
        for u in &mut users {
            let got: Vec<Vec<u8>> = frames(u, 2).into_iter().map(|(f, _)| f).collect();
            assert_eq!(got, [vec![0], vec![1]]);
        }
        assert_eq!(inbox.stats(), ProcessInboxStats::default());
    }
}
