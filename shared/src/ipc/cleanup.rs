//! Cleaning up after dead processes: their iceoryx2 nodes and ports, half-removed
//! node files, and segments nobody finished making.

#[allow(unused_imports)]
use super::*;

/// Removes what the dead process `pid` left in shared memory (its nodes' ports), and
/// nothing else: unlike a full dead-node cleanup it does not pay for other dead nodes.
/// Returns how many nodes were removed.
pub fn cleanup_dead_nodes_of(pid: u32) -> usize {
    cleanup_dead_nodes(Some(pid))
}

/// Removes what dead processes left in shared memory: first what `pid` left, once it
/// has exited (a process SIGKILLed while stopped takes a moment to go, and its nodes
/// are not dead until then), then what any other dead process left (a cleanup skipped
/// because another was under way, or never run because its broker was killed first).
/// Returns how many nodes were removed.
pub fn cleanup_after(pid: Option<u32>) -> usize {
    // A segment whose creator was killed between creating and sizing it stays empty,
    // and iceoryx2 0.10 waits forever to open an empty one (its cleanup of a dead
    // node's connections among others): such segments go first, and again while the
    // cleanup runs.
    let mut scan = StillbornScan::default();
    scan.run();
    let running = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let watch = {
        let running = running.clone();
        std::thread::spawn(move || {
            // Soon at first (a takeover's cleanup of the old primary is waited for),
            // then ever more rarely: each look reads the whole of /dev/shm. Woken
            // (unparked) when the cleanup ends.
            let mut wait = STILLBORN_LOOK_FIRST;
            loop {
                std::thread::park_timeout(wait);
                if !running.load(std::sync::atomic::Ordering::Relaxed) {
                    return;
                }
                scan.run();
                wait = (wait * 2).min(STILLBORN_LOOK_MAX);
            }
        })
    };
    let n = cleanup_after_inner(pid);
    running.store(false, std::sync::atomic::Ordering::Relaxed);
    watch.thread().unpark();
    let _ = watch.join();
    n
}

/// While a cleanup runs, stillborn segments are looked for again this long after it
/// began, then twice as late each time, up to [`STILLBORN_LOOK_MAX`].
const STILLBORN_LOOK_FIRST: Duration = Duration::from_millis(250);
const STILLBORN_LOOK_MAX: Duration = Duration::from_secs(4);

/// How long an empty segment must have stayed empty to be taken for stillborn (its
/// creator sizes it microseconds after creating it).
const STILLBORN_AFTER: Duration = Duration::from_secs(1);

/// Removes iceoryx2 segments in /dev/shm that are empty and were made more than
/// [`STILLBORN_AFTER`] ago: their creator died before sizing them. Returns how many.
pub fn remove_stillborn_segments() -> usize {
    StillbornScan::default().run()
}

/// Looks for stillborn segments again and again, and asks the size of each file only
/// until it is seen sized: a segment never shrinks back to nothing, so one seen sized
/// is skipped after (known by its inode and name, so a new file under an old name is
/// looked at anew). On a machine with many instances /dev/shm holds thousands of
/// segments, and a cleanup that asked each one's size four times a second for as long
/// as it ran (beside a hundred brokers starting, a cleanup each) took more of the
/// machine than the brokers did.
#[derive(Default)]
struct StillbornScan {
    /// The segments seen sized, by inode: their name, and the look they were last
    /// seen in.
    sized: std::collections::HashMap<u64, (std::ffi::OsString, u64)>,
    looks: u64,
}

impl StillbornScan {
    /// One look: returns how many stillborn segments it removed.
    fn run(&mut self) -> usize {
        use std::os::unix::ffi::OsStrExt;
        use std::os::unix::fs::DirEntryExt;
        let Ok(dir) = std::fs::read_dir("/dev/shm") else {
            return 0;
        };
        self.looks += 1;
        let mut n = 0;
        for entry in dir.flatten() {
            let name = entry.file_name();
            if !name.as_bytes().starts_with(b"iox2_") {
                continue;
            }
            let ino = entry.ino();
            if let Some((known, seen)) = self.sized.get_mut(&ino) {
                if *known == name {
                    *seen = self.looks;
                    continue;
                }
            }
            let Ok(meta) = entry.metadata() else { continue };
            if !meta.is_file() {
                continue;
            }
            if meta.len() > 0 {
                self.sized.insert(ino, (name, self.looks));
            } else if old(&meta) && std::fs::remove_file(entry.path()).is_ok() {
                tracing::info!(segment = %name.to_string_lossy(), "removed an empty segment its dead creator never sized");
                n += 1;
            }
        }
        // Forget the files that are gone, so the map holds only what is there.
        let look = self.looks;
        self.sized.retain(|_, (_, seen)| *seen == look);
        n
    }
}

/// Whether a file was last written at least [`STILLBORN_AFTER`] ago: what a live
/// process makes and fills within microseconds is not taken for a dead one's leftover
/// before then.
fn old(meta: &std::fs::Metadata) -> bool {
    meta.modified()
        .ok()
        .and_then(|m| m.elapsed().ok())
        .is_some_and(|age| age >= STILLBORN_AFTER)
}

fn cleanup_after_inner(pid: Option<u32>) -> usize {
    let mut n = 0;
    if let Some(pid) = pid {
        let until = std::time::Instant::now() + Duration::from_secs(10);
        while crate::reactor::process_alive(pid) && std::time::Instant::now() < until {
            std::thread::sleep(Duration::from_millis(5));
        }
        // The old primary's first, at full speed: it holds one of the reader slots of
        // the broker's inbox and bell, which the next takeover or restart needs. (At
        // niceness 19 it also holds /dev/shm's directory lock while it waits for a core,
        // and everyone opening a file there waits behind it.)
        n += cleanup_dead_nodes(Some(pid));
    }
    // The rest beside whatever the host is doing, never ahead of it; dead brokers
    // first, the slots they hold being the scarcest.
    let _ = crate::reactor::set_nice(19);
    n += cleanup_dead_nodes_where(is_broker_node);
    n + cleanup_dead_nodes(None)
}

/// Whether an iceoryx2 node of this name is a broker's (primary or standby), of any
/// instance.
fn is_broker_node(name: &str) -> bool {
    use crate::names::{BROKER_NODE, STANDBY_NODE};
    name.starts_with(BROKER_NODE) || name.starts_with(STANDBY_NODE)
}

/// The nodes of dead processes that `take` takes.
fn dead_views(
    take: impl Fn(&iceoryx2::node::DeadNodeView<Ipc>) -> bool,
) -> Vec<iceoryx2::node::DeadNodeView<Ipc>> {
    let mut dead = Vec::new();
    let _ = Node::<Ipc>::list(&config(true), |state| {
        if let NodeState::Dead(view) = state {
            if take(&view) {
                dead.push(view);
            }
        }
        CallbackProgression::Continue
    });
    dead
}

/// Removes what the dead process `pid` left, waiting up to `patience` for a cleanup
/// another process has under way (a broker's inbox cannot be opened before its dead
/// readers are gone). Returns how many of its nodes are gone.
pub fn cleanup_dead_nodes_of_waiting(pid: u32, patience: Duration) -> usize {
    use iceoryx2::node::NodeView;
    dead_views(|view| node_pid(view.id()) == Some(pid))
        .into_iter()
        .filter(
            |view| match view.clone().blocking_remove_stale_resources(patience) {
                Ok(()) => true,
                Err(e) => {
                    tracing::warn!(pid, "cannot remove the resources of a dead process: {e:?}");
                    false
                }
            },
        )
        .count()
}

/// How many live processes run a broker (primary or standby) of `inst`, by their
/// iceoryx2 nodes.
pub fn live_brokers(inst: &Instance) -> usize {
    use iceoryx2::node::NodeView;
    let names = [inst.broker_node(), inst.standby_node()];
    let mut n = 0;
    let _ = Node::<Ipc>::list(&config(true), |state| {
        if let NodeState::Alive(view) = state {
            if view
                .details()
                .as_ref()
                .is_some_and(|d| names.iter().any(|m| d.name().as_str() == m))
            {
                n += 1;
            }
        }
        CallbackProgression::Continue
    });
    n
}

/// How many iceoryx2 nodes of dead processes are still waiting for their cleanup.
pub fn dead_nodes() -> usize {
    dead_views(|_| true).len()
}

/// Removes what dead processes left in shared memory: those of process `only`, or all.
/// Returns how many nodes were removed.
pub fn cleanup_dead_nodes(only: Option<u32>) -> usize {
    use iceoryx2::node::NodeView;
    let dead = dead_views(|view| only.is_none_or(|pid| node_pid(view.id()) == Some(pid)));
    if only.is_none() {
        remove_half_removed_monitors(&std::path::Path::new(&iox2_root()).join("nodes"));
    }
    remove_dead(dead)
}

/// Removes what dead processes whose node name `pred` takes left in shared memory.
/// Returns how many nodes were removed.
fn cleanup_dead_nodes_where(pred: impl Fn(&str) -> bool) -> usize {
    use iceoryx2::node::NodeView;
    remove_dead(dead_views(|view| {
        view.details()
            .as_ref()
            .is_some_and(|d| pred(d.name().as_str()))
    }))
}

/// Removes what the dead nodes `dead` left; returns how many there were.
fn remove_dead(dead: Vec<iceoryx2::node::DeadNodeView<Ipc>>) -> usize {
    use iceoryx2::node::{NodeCleanupFailure, NodeView};
    let n = dead.len();
    for view in dead {
        if view.details().is_none() {
            // Killed while its node was being made: no details, so iceoryx2 would look
            // for the node under its default root, not ours, and never remove it.
            remove_detail_less_node(&view.id().value().to_string());
            continue;
        }
        match view.try_remove_stale_resources() {
            Ok(_) => {}
            // Someone else (another process's cleanup) got there first: nothing is lost.
            Err(
                e @ (NodeCleanupFailure::ResourcesAlreadyCleanedUp
                | NodeCleanupFailure::AnotherInstanceIsCleaningUpTheNode),
            ) => tracing::debug!("a dead process's resources: {e:?}"),
            Err(e) => tracing::warn!("cannot remove the resources of a dead process: {e:?}"),
        }
    }
    n
}

/// Removes the files of a dead node that has no details (its folder under our root's
/// `nodes/`, and its monitor's three files beside it). One made just now, whose maker
/// may not hold its monitor yet, is left alone.
fn remove_detail_less_node(id: &str) {
    let nodes = std::path::Path::new(&iox2_root()).join("nodes");
    let monitor = nodes.join(format!("iox2_{id}{MONITOR}"));
    if !std::fs::metadata(&monitor).as_ref().is_ok_and(old) {
        return;
    }
    remove_node_files(&nodes, id);
    tracing::info!(node = id, "removed a dead node that was never finished");
}

/// A node's monitor state file is `iox2_<id>` and this, in our root's `nodes/`; its
/// owner lock and context add [`MONITOR_TAILS`].
const MONITOR: &str = ".node_monitor";
const MONITOR_TAILS: [&str; 2] = ["_context", "_owner_lock"];

/// Removes whatever is left of node `id` in `nodes`: its folder and its monitor's files.
fn remove_node_files(nodes: &std::path::Path, id: &str) {
    let _ = std::fs::remove_dir_all(nodes.join(id));
    for tail in std::iter::once("").chain(MONITOR_TAILS) {
        let _ = std::fs::remove_file(nodes.join(format!("iox2_{id}{MONITOR}{tail}")));
    }
}

/// Removes the monitor files of nodes whose state file is gone, in `nodes` (our root's
/// `nodes/`). iceoryx2 lists nodes by their state file (`iox2_<id>.node_monitor`) and
/// removes it first when a node is dropped, then its owner lock and its context: a
/// process killed in between (a SIGKILL after a slow shutdown) leaves those two behind,
/// where no node listing ever finds them. A live node always has its state file but for
/// microseconds while it is made or dropped, so only files older than [`STILLBORN_AFTER`]
/// are taken. Returns how many nodes' leftovers were removed.
pub(super) fn remove_half_removed_monitors(nodes: &std::path::Path) -> usize {
    let Ok(dir) = std::fs::read_dir(nodes) else {
        return 0;
    };
    let mut orphans = std::collections::BTreeSet::new();
    for entry in dir.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(id) = MONITOR_TAILS
            .iter()
            .find_map(|tail| name.strip_suffix(&format!("{MONITOR}{tail}")))
            .and_then(|stem| stem.strip_prefix("iox2_"))
        else {
            continue;
        };
        if entry.metadata().as_ref().is_ok_and(old)
            && !nodes.join(format!("iox2_{id}{MONITOR}")).exists()
        {
            orphans.insert(id.to_string());
        }
    }
    for id in &orphans {
        remove_node_files(nodes, id);
        tracing::info!(node = %id, "removed what a node killed while it was dropped left");
    }
    orphans.len()
}

/// The pid of the process that created an iceoryx2 node, if it can be told.
pub(super) fn node_pid(node: &iceoryx2::identifiers::UniqueNodeId) -> Option<u32> {
    node.pid::<Ipc>()
        .ok()
        .and_then(|p| u32::try_from(p.value()).ok())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_repeated_scan_skips_what_it_saw_sized_and_still_finds_new_stillborn_segments() {
        let name = |what: &str| format!("/dev/shm/iox2_muster_scan_{}_{what}", std::process::id());
        let long_ago = std::time::SystemTime::now() - Duration::from_secs(5);
        let make = |path: &str, bytes: &[u8]| {
            let f = std::fs::File::create(path).unwrap();
            std::io::Write::write_all(&mut &f, bytes).unwrap();
            f.set_modified(long_ago).unwrap();
            f
        };
        let exists = |p: &str| std::path::Path::new(p).exists();
        let (sized, later) = (name("sized"), name("later"));
        let f = make(&sized, b"data");
        let mut scan = StillbornScan::default();
        scan.run();
        assert!(exists(&sized), "a sized segment stays");
        // The same file emptied (which a segment never is): the scan does not ask its
        // size again, so it stays.
        f.set_len(0).unwrap();
        f.set_modified(long_ago).unwrap();
        make(&later, b"");
        assert!(scan.run() >= 1, "the new stillborn one is found");
        assert!(!exists(&later));
        assert!(exists(&sized), "what was seen sized is not looked at again");
        // A new file under the old name is looked at anew.
        std::fs::remove_file(&sized).unwrap();
        drop(f);
        make(&sized, b"");
        assert!(scan.run() >= 1);
        assert!(
            !exists(&sized),
            "a new empty file under a known name is taken"
        );
    }
}
