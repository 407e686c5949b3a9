//! A standby: follows the primary's replication stream and takes over when the
//! primary dies, is stopped, hangs or steps down.

#[allow(unused_imports)]
use super::*;

/// Runs a standby on `inst`: it follows the primary's state and takes over when the
/// primary dies (its pidfd), hangs (no record for `deadline`) or steps down; then it
/// serves as the primary until SIGINT or SIGTERM.
pub fn run_standby(
    inst: &Instance,
    cfg: BrokerConfig,
    udp: Option<UdpConfig>,
    fed: Option<FedConfig>,
    keep_log: bool,
    deadline: Duration,
) -> Result<BrokerReport, BrokerError> {
    raise_fds();
    let node = create_node(&inst.standby_node(), false)?;
    let fence = open_fence(inst)?;
    let Some(standby) = follow(inst, &node, &fence, deadline)? else {
        return Ok(BrokerReport {
            stats: crate::core::BrokerStats::default(),
            handling: Handling::new(false),
            udp: None,
            federation: None,
            descriptors: Default::default(),
        });
    };
    let Followed {
        noticed_ns,
        follower,
        presence,
        signals,
        me,
        old,
        why,
    } = standby;
    let pid = std::process::id();
    let t0 = Instant::now();
    let old_pid = old.as_ref().map(PidFd::pid);
    if why == Why::SteppedDown {
        // It is on its way out: let it go.
        if let Some(old) = &old {
            let until = Instant::now() + Duration::from_secs(2);
            while !old.exited() && Instant::now() < until {
                std::thread::sleep(Duration::from_micros(200));
            }
        }
    }
    if let Some(old) = old.filter(|o| !o.exited()) {
        // A hung primary still holds its share of the broker's inbox and would write
        // its list when it woke: having taken its term, end it. Were it to wake first, the fence stops it before it acts. Its
        // exit (slow for a process with hundreds of mappings) is not waited for: the
        // inbox takes more than one reader, and each run writes its own list.
        tracing::warn!(pid = old.pid(), "ending the hung primary");
        // SAFETY: kill(2) on a pid we hold a pidfd of (it cannot have been reused).
        unsafe { libc::kill(old.pid() as i32, libc::SIGKILL) };
        if udp.is_some() {
            // Its UDP socket is ours to bind only once it has exited.
            let until = Instant::now() + Duration::from_secs(5);
            while !old.exited() && Instant::now() < until {
                std::thread::sleep(Duration::from_micros(500));
            }
        }
    }
    let killed_us = t0.elapsed().as_micros() as u64;
    // The old primary's ports are cleaned up beside serving: the broker's inbox takes
    // more than one reader, and each run writes its own list.
    let cleanup = old_pid.map(|pid| cleaner(inst, Some(pid), CLEANUP_DELAY));
    let endpoint = Endpoint::open(inst, Address::Broker, node).map_err(|e| match e {
        TransportError::InUse(_) => BrokerError::AlreadyRunning(inst.to_string()),
        other => BrokerError::from(other),
    })?;
    let seq = follower.seq();
    let (core, how) = match follower.into_core() {
        Some(mut core) => {
            let epoch = new_epoch(core.epoch());
            core.take_over(host_now(), epoch, pid);
            (core, Start::Takeover)
        }
        None => (Broker::new(cfg, new_epoch(0), pid), Start::Cold),
    };
    tracing::warn!(
        ?why,
        term = me.term,
        state = if how == Start::Takeover {
            "replicated"
        } else {
            "none: starting cold"
        },
        killed_us,
        inbox_us = t0.elapsed().as_micros() as u64,
        "standby taking over"
    );
    event(serde_json::json!({
        "event": "took_over", "why": format!("{why:?}").to_lowercase(), "term": me.term,
        "replicated": how == Start::Takeover, "inbox_us": t0.elapsed().as_micros() as u64,
        "noticed_ns": noticed_ns,
    }));
    serve(
        inst,
        Primary {
            endpoint,
            fence,
            me,
            core,
            how,
            seq,
            standby_since: Some(t0),
            cleanup,
            presence: Some(presence),
            signals: Some(signals),
        },
        udp,
        fed,
        keep_log,
    )
}

/// Prints one standby event as a JSON line on stdout (for `muster up`, tests and the
/// failover bench).
pub(super) fn event(v: serde_json::Value) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{v}");
    let _ = out.flush();
}

/// Why a standby took over.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Why {
    /// The primary's process ended (its pidfd).
    Died,
    /// No record from the primary within the deadline, and its loop made no progress
    /// while it could have run ([`crate::takeover::judge`]).
    Hung,
    /// No record within the deadline, and the primary is stopped (SIGSTOP).
    Stopped,
    /// The primary stepped down (stopped on purpose with a standby running).
    SteppedDown,
    /// There was no primary.
    NoPrimary,
}

struct Followed {
    /// When the takeover was decided (host monotonic clock, ns).
    pub(super) noticed_ns: u64,
    pub(super) follower: Follower,
    pub(super) presence: Ringer,
    /// Its signal pipe, carried into serving.
    pub(super) signals: SignalPipe,
    pub(super) me: Holder,
    pub(super) old: Option<PidFd>,
    pub(super) why: Why,
}

/// Rings the presence event from a thread of its own: waking every process of the
/// instance takes long on a loaded host (each wakes up in turn), and the broker serves
/// meanwhile.
pub(super) struct Ringer {
    pub(super) tx: Option<std::sync::mpsc::Sender<usize>>,
    pub(super) thread: Option<std::thread::JoinHandle<()>>,
}

/// Asks the ringer to connect to every listener, without ringing.
const PREPARE: usize = usize::MAX;

impl Ringer {
    pub(super) fn spawn(inst: &Instance) -> Result<Self, BrokerError> {
        let (tx, rx) = std::sync::mpsc::channel::<usize>();
        let (ready_tx, ready_rx) = std::sync::mpsc::channel::<Result<(), TransportError>>();
        let inst = inst.clone();
        let thread = std::thread::spawn(move || {
            let made = create_node(&format!("muster-ringer-{inst}"), false)
                .and_then(|node| Presence::announce(&node, &inst).map(|p| (node, p)));
            let (_node, presence) = match made {
                Ok(v) => {
                    let _ = ready_tx.send(Ok(()));
                    v
                }
                Err(e) => {
                    let _ = ready_tx.send(Err(e));
                    return;
                }
            };
            while let Ok(id) = rx.recv() {
                if id == PREPARE {
                    presence.prepare();
                } else {
                    presence.ring(id);
                }
            }
        });
        match ready_rx.recv() {
            Ok(Ok(())) => Ok(Ringer {
                tx: Some(tx),
                thread: Some(thread),
            }),
            Ok(Err(e)) => Err(e.into()),
            Err(_) => Err(BrokerError::Os(std::io::Error::other(
                "the presence thread died",
            ))),
        }
    }

    pub(super) fn ring(&self, id: usize) {
        if let Some(tx) = &self.tx {
            let _ = tx.send(id);
        }
    }

    pub(super) fn prepare(&self) {
        self.ring(PREPARE);
    }

    /// Waits until every ring asked for has gone out.
    pub(super) fn finish(mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// How often a standby connects its presence notifier to listeners that came since.
const PREPARE_EVERY: Duration = Duration::from_secs(1);

/// How long a standby without a copy of the state waits on a silent primary.
const UNSYNCED_PATIENCE: Duration = Duration::from_secs(2);

/// How long a standby with no primary of record waits for a broker that reads the
/// broker's inbox (starting) to claim the fence.
const STARTING_PATIENCE: Duration = Duration::from_secs(10);

/// How often an unsynchronized standby asks the primary for its state.
const ASK_EVERY: Duration = Duration::from_millis(100);

const STANDBY_REPLICA: usize = 0;
const STANDBY_SIGNAL: usize = 1;
const STANDBY_PRIMARY: usize = 2;

/// What a standby that has no copy of its primary's state yet did to get one: told
/// once, when it has waited [`UNSYNCED_REPORT`] (an image takes milliseconds).
struct Unsynced {
    since: Instant,
    /// Asks rung on the primary's bell, and asks that found no bell to ring.
    asks: u64,
    unrung: u64,
    /// The primary's record parts read meanwhile (heartbeats, journal, images).
    records: u64,
    told: bool,
}

/// How long a standby goes without the primary's state before it says so.
const UNSYNCED_REPORT: Duration = Duration::from_secs(5);

impl Unsynced {
    fn new() -> Self {
        Unsynced {
            since: Instant::now(),
            asks: 0,
            unrung: 0,
            records: 0,
            told: false,
        }
    }

    fn report(&mut self, primary: u32, refused: u64) {
        if !self.told && self.since.elapsed() >= UNSYNCED_REPORT {
            self.told = true;
            tracing::warn!(
                primary,
                waited_ms = self.since.elapsed().as_millis() as u64,
                asks = self.asks,
                asks_with_no_bell = self.unrung,
                records = self.records,
                refused,
                "standby still without the primary's state"
            );
        }
    }
}

/// Follows the primary until this standby has taken its term (`Some`) or was told to
/// stop (`None`).
fn follow(
    inst: &Instance,
    node: &iceoryx2::prelude::Node<muster_shared::ipc::Ipc>,
    fence: &Fence,
    deadline: Duration,
) -> Result<Option<Followed>, BrokerError> {
    let mut reader = ReplicaReader::open(node, inst)?;
    // Made now, connected to every listener from time to time: the takeover rings at once.
    let presence = Ringer::spawn(inst)?;
    let mut prepared: Option<Instant> = None;
    let mut asker = BellRinger::open(node, inst, &Address::Broker)?;
    let mut signals = SignalPipe::install()?;
    let mut reactor = Reactor::new()?;
    reactor.add(reader.fd(), STANDBY_REPLICA)?;
    reactor.add(signals.raw(), STANDBY_SIGNAL)?;
    let mut follower = Follower::new();
    let mut watched: Option<(Holder, Option<PidFd>)> = None;
    let mut heard = Instant::now();
    let mut asked: Option<Instant> = None;
    let mut logged_sync = false;
    // What the takeover judgment needs beside the silence (see `takeover`).
    let mut own_lateness = Duration::ZERO;
    let mut queued_at_heard: Option<Duration> = None;
    let mut queued_read: Option<Instant> = None;
    let mut starved_logged = false;
    let mut starting_logged = false;
    let mut unsynced = Unsynced::new();
    tracing::info!(instance = %inst, deadline_ms = deadline.as_millis() as u64, "standby following");
    loop {
        // The primary of record: a new one (a cold start, or another standby's
        // takeover) starts a new copy.
        let holder = fence.holder();
        if watched.as_ref().is_none_or(|(h, _)| *h != holder) {
            if let Some((_, Some(p))) = watched.take() {
                reactor.remove(p.raw());
            }
            let pidfd = (holder.pid != 0)
                .then(|| PidFd::open(holder.pid).ok())
                .flatten();
            if let Some(p) = &pidfd {
                reactor.add(p.raw(), STANDBY_PRIMARY)?;
            }
            tracing::info!(pid = holder.pid, term = holder.term, "following primary");
            queued_at_heard = pidfd
                .as_ref()
                .and_then(|p| takeover::run_queue_wait(p.pid()));
            queued_read = Some(Instant::now());
            watched = Some((holder, pidfd));
            follower = Follower::new();
            heard = Instant::now();
            asked = None;
            logged_sync = false;
            unsynced = Unsynced::new();
        }
        let (holder, pidfd) = watched.as_ref().expect("set above");
        let holder = *holder;
        let mut why = None;
        // A primary this standby holds no copy of yet gets longer to answer before it is
        // taken for hung: on a loaded host its first image may take a while, and a
        // takeover without the state would be a cold start anyway.
        let patience = if follower.synced() {
            deadline
        } else {
            deadline.max(UNSYNCED_PATIENCE)
        };
        match pidfd {
            // No live primary of record. A standby started beside its primary (as `muster
            // up` starts them) may look before the primary has claimed the fence: one
            // that is starting already reads the broker's inbox, and is followed once it
            // claims. Only with no broker process, for as long as a standby without a
            // copy waits on a silent primary, does this one start cold; a broker that
            // has not claimed the fence within [`STARTING_PATIENCE`] is not waited for.
            None if heard.elapsed() >= patience => {
                let me = std::process::id();
                let starting = inbox_reader_pids(node, inst, &Address::Broker)
                    .into_iter()
                    .find(|p| *p != me && muster_shared::reactor::process_alive(*p))
                    .filter(|_| heard.elapsed() < STARTING_PATIENCE);
                match starting {
                    Some(pid) if !starting_logged => {
                        starting_logged = true;
                        tracing::info!(
                            pid,
                            "a broker is starting: waiting for it to claim the fence"
                        );
                    }
                    Some(_) => {}
                    None => why = Some(Why::NoPrimary),
                }
            }
            None => {}
            Some(p) if p.exited() => why = Some(Why::Died),
            Some(p)
                if heard.elapsed() >= patience
                    && !follower.synced()
                    && !muster_shared::reactor::process_stopped(p.pid()) =>
            {
                // Silence toward a standby that never had a record is no proof the
                // primary hangs (it may be this standby's stream that is not connected):
                // taking over a live primary would grant twice. Without the state, only
                // a primary seen stopped (or dead) is taken over; reconnect and ask again.
                tracing::warn!(
                    pid = p.pid(),
                    "no record from the running primary: reopening the replication stream"
                );
                reactor.remove(reader.fd());
                reader = ReplicaReader::open(node, inst)?;
                reactor.add(reader.fd(), STANDBY_REPLICA)?;
                heard = Instant::now();
                asked = None;
            }
            Some(p) if heard.elapsed() >= patience => {
                let beat = fence.last_beat();
                let now_ns = muster_shared::protocol::monotonic_ns();
                let seen = takeover::Seen {
                    silent: heard.elapsed(),
                    since_beat: (beat != 0)
                        .then(|| Duration::from_nanos(now_ns.saturating_sub(beat))),
                    state: takeover::proc_state(p.pid()),
                    waited_for_cpu: takeover::run_queue_wait(p.pid())
                        .zip(queued_at_heard)
                        .map(|(now, then)| now.saturating_sub(then)),
                    own_lateness,
                };
                match takeover::judge(&seen, patience) {
                    Verdict::Follow => {}
                    Verdict::Stopped => why = Some(Why::Stopped),
                    Verdict::Hung => why = Some(Why::Hung),
                    Verdict::Starved => {
                        if !starved_logged {
                            starved_logged = true;
                            tracing::warn!(
                                pid = p.pid(),
                                silent_ms = seen.silent.as_millis() as u64,
                                waited_for_cpu_ms =
                                    seen.waited_for_cpu.map(|w| w.as_millis() as u64),
                                own_lateness_ms = own_lateness.as_millis() as u64,
                                "the primary is silent but starved, not hung: not taking over"
                            );
                        }
                    }
                }
            }
            Some(_) => {}
        }
        if why.is_none() && !follower.synced() && asked.is_none_or(|t| t.elapsed() >= ASK_EVERY) {
            asker.reconnect(node);
            match asker.ring(bell::STANDBY) {
                Ok(()) => unsynced.asks += 1,
                Err(_) => unsynced.unrung += 1,
            }
            asked = Some(Instant::now());
        }
        let mut stepped_down = false;
        reader.drain_bell();
        let got = reader.drain(holder.pid, |bytes| match follower.apply(bytes) {
            Ok(Step::Gap) => {
                tracing::warn!("replication records lost: asking for the whole state again");
                asked = None;
            }
            Ok(Step::SteppingDown) => stepped_down = true,
            Ok(_) => {}
            Err(e) => tracing::warn!("{e}"),
        });
        unsynced.records += got as u64;
        if !follower.synced() {
            unsynced.report(holder.pid, reader.refused());
        }
        // Any record (a heartbeat at least) means the primary is not hung.
        if got > 0 {
            heard = Instant::now();
            starved_logged = false;
            // The run-queue figure at the start of a silence, read at most every
            // quarter deadline (every record would be a /proc read per heartbeat).
            if queued_read.is_none_or(|t| t.elapsed() >= deadline / 4) {
                queued_at_heard = pidfd
                    .as_ref()
                    .and_then(|p| takeover::run_queue_wait(p.pid()));
                queued_read = Some(Instant::now());
            }
        }
        if follower.synced() && prepared.is_none_or(|t| t.elapsed() >= PREPARE_EVERY) {
            presence.prepare();
            prepared = Some(Instant::now());
        }
        if follower.synced() && !logged_sync {
            logged_sync = true;
            tracing::info!(seq = follower.seq(), "standby in sync");
            event(
                serde_json::json!({"event": "in_sync", "primary": holder.pid, "seq": follower.seq()}),
            );
        }
        if stepped_down {
            why = Some(Why::SteppedDown);
        }
        if let Some(why) = why {
            // Told to stop at the same moment: stop, do not take over (the signal would
            // be lost to the primary this standby would become).
            if signals.drain() {
                tracing::info!("signal received: standby stopping");
                return Ok(None);
            }
            if let Some(me) = fence.claim(holder, std::process::id()) {
                let old = watched.and_then(|(_, p)| p);
                return Ok(Some(Followed {
                    noticed_ns: muster_shared::protocol::monotonic_ns(),
                    follower,
                    presence,
                    signals,
                    me,
                    old,
                    why,
                }));
            }
            // Another standby was quicker: follow it.
            continue;
        }
        let wait = patience
            .saturating_sub(heard.elapsed())
            .min(if follower.synced() {
                deadline
            } else {
                ASK_EVERY
            })
            .max(Duration::from_millis(1));
        let asked_at = Instant::now();
        let tokens = reactor.wait(Some(wait))?;
        // Woken by the timeout, later than asked: this standby was kept from running.
        own_lateness = match tokens.is_empty() {
            true => asked_at.elapsed().saturating_sub(wait),
            false => Duration::ZERO,
        };
        for token in tokens {
            match token {
                STANDBY_SIGNAL if signals.drain() => {
                    tracing::info!("signal received: standby stopping");
                    return Ok(None);
                }
                _ => {}
            }
        }
    }
}
