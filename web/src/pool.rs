//! The threads that drive the hubs. Each owns the broker connections of the hubs it
//! was given: one iceoryx2 node and one set of ports to the broker and to each system,
//! shared by its users (each keeps its own inbox and bell: the broker and the systems
//! tell users apart by the user ids in the frames and hold a process to its pid), and one
//! epoll over every user's descriptor. A few hundred people signed in are then a few
//! threads and about 22–26 descriptors each, where a thread and a node per user took one
//! thread and about 48 descriptors each: 500 people did not fit the descriptor limit,
//! and their 500 threads queued for the cores behind everything else.

use crate::hub::{eventfd, Run, Start};
use muster_shared::ipc::{create_node, PortShare};
use muster_shared::reactor::Reactor;
use muster_shared::Instance;
use muster_users::{ConnectOptions, UserClient, UserError, Wake};
use serde_json::json;
use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};
use std::os::fd::{AsRawFd, OwnedFd};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

/// How often a worker looks at every hub (connections that did not come, tabs all
/// closed, hubs dropped).
const HOUSEKEEPING: Duration = Duration::from_secs(1);
/// The longest a worker spends starting new users before it looks at the others.
const START_BUDGET: Duration = Duration::from_millis(2);
/// The worker's own token in its reactor (new hubs, stop); hubs' tokens follow.
const TOKEN_WORKER: usize = 0;

/// The hubs' threads.
pub struct Pool {
    workers: Vec<Worker>,
}

struct Worker {
    tx: Mutex<mpsc::Sender<Start>>,
    wake: Arc<OwnedFd>,
    /// Hubs it drives now.
    hubs: Arc<AtomicUsize>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Pool {
    /// `threads` workers for the hubs of instance `inst`.
    pub fn new(inst: &Instance, threads: usize) -> Result<Pool, String> {
        let mut workers = Vec::new();
        for i in 0..threads.max(1) {
            let (tx, rx) = mpsc::channel();
            let wake = Arc::new(eventfd().map_err(|e| format!("eventfd: {e}"))?);
            let hubs = Arc::new(AtomicUsize::new(0));
            let stop = Arc::new(AtomicBool::new(false));
            let mut w = Work {
                inst: inst.clone(),
                index: i,
                rx,
                wake: wake.clone(),
                hubs: hubs.clone(),
                stop: stop.clone(),
            };
            let thread = std::thread::Builder::new()
                .name(format!("web-users-{i}"))
                .spawn(move || w.run())
                .map_err(|e| format!("thread: {e}"))?;
            workers.push(Worker {
                tx: Mutex::new(tx),
                wake,
                hubs,
                stop,
                thread: Some(thread),
            });
        }
        Ok(Pool { workers })
    }

    /// Hands a new hub to the worker with the fewest.
    pub(crate) fn start(&self, start: Start) -> Result<(), String> {
        let w = self
            .workers
            .iter()
            .min_by_key(|w| w.hubs.load(Ordering::Acquire))
            .ok_or("no worker threads")?;
        w.hubs.fetch_add(1, Ordering::AcqRel);
        w.tx.lock()
            .map_err(|_| "a worker's queue is poisoned".to_string())?
            .send(start)
            .map_err(|_| "the web console's worker thread died".to_string())?;
        crate::hub::ring(&w.wake);
        Ok(())
    }

    /// Hubs driven now, all workers together.
    pub fn hubs(&self) -> usize {
        self.workers
            .iter()
            .map(|w| w.hubs.load(Ordering::Acquire))
            .sum()
    }
}

impl Drop for Pool {
    /// Ends every hub (their sessions end, their users say goodbye) and the threads.
    fn drop(&mut self) {
        for w in &self.workers {
            w.stop.store(true, Ordering::Release);
            crate::hub::ring(&w.wake);
        }
        for w in &mut self.workers {
            if let Some(t) = w.thread.take() {
                let _ = t.join();
            }
        }
    }
}

/// A hub on a worker: connecting (its start waits for the broker's welcome) or running.
struct Slot {
    run: Run,
    /// Until the welcome: when to give up, and whom to tell.
    connecting: Option<(Instant, mpsc::Sender<Result<(), String>>)>,
    /// When its client's own timers need it next.
    due: Option<Instant>,
}

/// A worker thread's state.
struct Work {
    inst: Instance,
    index: usize,
    rx: mpsc::Receiver<Start>,
    wake: Arc<OwnedFd>,
    hubs: Arc<AtomicUsize>,
    stop: Arc<AtomicBool>,
}

impl Work {
    fn run(&mut self) {
        let name = format!("muster-web-{}-{}", std::process::id(), self.index);
        let setup = create_node(&name, false)
            .map_err(|e| e.to_string())
            .and_then(|node| {
                let reactor = Reactor::new().map_err(|e| format!("epoll: {e}"))?;
                reactor
                    .add(self.wake.as_raw_fd(), TOKEN_WORKER)
                    .map_err(|e| format!("epoll: {e}"))?;
                Ok((PortShare::new(&self.inst, node), reactor))
            });
        let (share, mut reactor) = match setup {
            Ok(s) => s,
            Err(e) => return self.refuse_all(&e),
        };
        let mut slots: HashMap<usize, Slot> = HashMap::new();
        let mut timers: BinaryHeap<Reverse<(Instant, usize)>> = BinaryHeap::new();
        let mut next_token = TOKEN_WORKER + 1;
        let mut housekeeping = Instant::now() + HOUSEKEEPING;
        // New hubs wait in the queue.
        let mut starting = false;
        loop {
            let now = Instant::now();
            let next = timers
                .peek()
                .map_or(housekeeping, |Reverse((at, _))| (*at).min(housekeeping));
            let wait = if starting {
                Duration::ZERO
            } else {
                next.saturating_duration_since(now)
            };
            let tokens = match reactor.wait(Some(wait)) {
                Ok(t) => t,
                Err(e) => {
                    tracing::error!("web worker's epoll failed: {e}");
                    std::thread::sleep(Duration::from_millis(10));
                    Vec::new()
                }
            };
            let mut ready = Vec::with_capacity(tokens.len());
            for t in tokens {
                if t != TOKEN_WORKER {
                    ready.push(t);
                    continue;
                }
                crate::hub::drain(&self.wake);
                if self.stop.load(Ordering::Acquire) {
                    for (_, slot) in slots.drain() {
                        self.end(&reactor, slot, None);
                    }
                    return;
                }
                starting = true;
            }
            if starting {
                // New users, for at most START_BUDGET a pass: a storm of sign-ins (each
                // a few iceoryx2 services) must not hold up the updates of those
                // already in; the rest wait for the next pass, which comes at once.
                let began = Instant::now();
                starting = false;
                while let Ok(start) = self.rx.try_recv() {
                    let token = next_token;
                    next_token += 1;
                    if let Some(slot) = self.begin(&share, &reactor, token, start) {
                        slots.insert(token, slot);
                        // Its hello is out: the welcome may already be here.
                        ready.push(token);
                    }
                    if began.elapsed() >= START_BUDGET {
                        starting = true;
                        break;
                    }
                }
            }
            let now = Instant::now();
            while let Some(Reverse((at, t))) = timers.peek().copied() {
                if at > now {
                    break;
                }
                timers.pop();
                if let Some(slot) = slots.get_mut(&t).filter(|s| s.due == Some(at)) {
                    // Spent: the step below sets the next one.
                    slot.due = None;
                    ready.push(t);
                }
            }
            for t in ready {
                let Some(slot) = slots.get_mut(&t) else {
                    continue;
                };
                match step(slot) {
                    Ok(true) => {
                        // One timer a hub: a new one only when the time changed (the
                        // one in the heap still stands otherwise).
                        let due = slot.run.client.next_turn();
                        if due != slot.due {
                            slot.due = due;
                            if let Some(at) = due {
                                timers.push(Reverse((at, t)));
                            }
                        }
                    }
                    Ok(false) => {
                        if let Some(slot) = slots.remove(&t) {
                            self.end(&reactor, slot, None);
                        }
                    }
                    Err(e) => {
                        if let Some(slot) = slots.remove(&t) {
                            self.end(&reactor, slot, Some(e));
                        }
                    }
                }
            }
            if now >= housekeeping {
                housekeeping = now + HOUSEKEEPING;
                let done: Vec<usize> = slots
                    .iter_mut()
                    .filter(|(_, s)| match &s.connecting {
                        Some((deadline, _)) => now >= *deadline,
                        None => false,
                    })
                    .map(|(t, _)| *t)
                    .collect();
                for t in done {
                    if let Some(mut slot) = slots.remove(&t) {
                        if let Some((_, ready)) = slot.connecting.take() {
                            let _ = ready
                                .send(Err(UserError::NoBroker(self.inst.to_string()).to_string()));
                        }
                        self.end(&reactor, slot, None);
                    }
                }
                let idle: Vec<usize> = slots
                    .iter_mut()
                    .filter_map(|(t, s)| (s.connecting.is_none() && !s.run.keep(now)).then_some(*t))
                    .collect();
                for t in idle {
                    if let Some(slot) = slots.remove(&t) {
                        self.end(&reactor, slot, None);
                    }
                }
            }
        }
    }

    /// A new hub's user, its hello sent; `None` (its start told why) if it could not be
    /// made.
    fn begin(
        &self,
        share: &PortShare,
        reactor: &Reactor,
        token: usize,
        start: Start,
    ) -> Option<Slot> {
        let opts = ConnectOptions {
            wait_for_broker: start.wait,
            handle_signals: false,
            // The list comes from the shared reader.
            watch_list: false,
        };
        let prefix = format!("web-{}-", start.user);
        let made = UserClient::start_shared(&self.inst, &opts, &prefix, share)
            .map_err(|e| e.to_string())
            .and_then(|client| {
                reactor
                    .add(client.fd(), token)
                    .map_err(|e| format!("epoll: {e}"))?;
                Ok(client)
            });
        match made {
            Ok(client) => {
                let deadline = Instant::now() + start.wait;
                let (run, ready) = Run::new(start, client);
                Some(Slot {
                    run,
                    connecting: Some((deadline, ready)),
                    due: None,
                })
            }
            Err(e) => {
                start.alive.store(false, Ordering::Release);
                let _ = start.ready.send(Err(e));
                self.hubs.fetch_sub(1, Ordering::AcqRel);
                None
            }
        }
    }

    /// A hub is done: its tabs are told why (if it failed), its user closed.
    fn end(&self, reactor: &Reactor, slot: Slot, error: Option<UserError>) {
        let Slot {
            run, connecting, ..
        } = slot;
        if let Some((_, ready)) = connecting {
            let why = error
                .as_ref()
                .map_or_else(|| "stopped".to_string(), ToString::to_string);
            let _ = ready.send(Err(why));
        } else if let Some(e) = &error {
            tracing::warn!(user = %run.name, "web user's broker connection ended: {e}");
            run.send(json!({"t": "error", "error": format!("the broker connection ended: {e}")}));
        }
        run.alive.store(false, Ordering::Release);
        reactor.remove(run.client.fd());
        run.close();
        self.hubs.fetch_sub(1, Ordering::AcqRel);
    }

    /// The worker could not start: every hub sent to it is refused, with why.
    fn refuse_all(&mut self, why: &str) {
        tracing::error!("a web console worker could not start: {why}");
        while !self.stop.load(Ordering::Acquire) {
            while let Ok(start) = self.rx.try_recv() {
                start.alive.store(false, Ordering::Release);
                let _ = start.ready.send(Err(why.to_string()));
                self.hubs.fetch_sub(1, Ordering::AcqRel);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// Handles what is here for a slot's hub; while connecting, the welcome finishes the
/// start. `Ok(false)`: the hub is done.
fn step(slot: &mut Slot) -> Result<bool, UserError> {
    if slot.connecting.is_some() {
        // Not welcomed yet: take in what came (the welcome turns `connected` on).
        while slot.run.client.core().connected().is_none() {
            match slot.run.client.poll()? {
                Wake::Event(e) => slot.run.on_event(e)?,
                Wake::Extra => {}
                Wake::Timeout => return Ok(true),
            }
        }
        let (_, ready) = slot.connecting.take().expect("checked above");
        if let Err(e) = slot.run.init() {
            let _ = ready.send(Err(e.to_string()));
            return Ok(false);
        }
        tracing::info!(user = %slot.run.name, id = %slot.run.client.id().0, "web user connected to the broker");
        let _ = ready.send(Ok(()));
    }
    slot.run.step()
}
