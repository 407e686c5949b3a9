//! What /proc and /dev/shm say about processes and shared memory.

use std::fs;

/// Resident set size, KiB.
pub fn rss_kib(pid: u32) -> Option<u64> {
    let status = fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    field_kib(&status, "VmRSS:")
}

/// Proportional set size (shared pages divided among their users), KiB.
pub fn pss_kib(pid: u32) -> Option<u64> {
    let rollup = fs::read_to_string(format!("/proc/{pid}/smaps_rollup")).ok()?;
    field_kib(&rollup, "Pss:")
}

fn field_kib(text: &str, name: &str) -> Option<u64> {
    text.lines()
        .find(|l| l.starts_with(name))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// User + system CPU time of a process, in clock ticks.
pub fn cpu_ticks(pid: u32) -> Option<u64> {
    // utime and stime are fields 14 and 15.
    let f = stat_fields(pid)?;
    Some(f.get(11)?.parse::<u64>().ok()? + f.get(12)?.parse::<u64>().ok()?)
}

/// A process's scheduling niceness (`/proc/PID/stat` field 19).
pub fn nice(pid: u32) -> Option<i32> {
    stat_fields(pid)?.get(16)?.parse().ok()
}

/// The fields of `/proc/PID/stat` after the parenthesised command name (field 3 on).
fn stat_fields(pid: u32) -> Option<Vec<String>> {
    let stat = fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let rest = &stat[stat.rfind(')')? + 2..];
    Some(rest.split_whitespace().map(String::from).collect())
}

/// Clock ticks per second.
pub fn ticks_per_second() -> u64 {
    // SAFETY: sysconf has no preconditions.
    let t = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    u64::try_from(t).unwrap_or(100).max(1)
}

/// Bytes of iceoryx2 shared memory actually allocated in /dev/shm (not just reserved).
pub fn shm_allocated_bytes() -> u64 {
    use std::os::unix::fs::MetadataExt;
    let Ok(dir) = fs::read_dir("/dev/shm") else {
        return 0;
    };
    dir.flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with("iox2_"))
        .filter_map(|e| e.metadata().ok())
        .map(|m| m.blocks() * 512)
        .sum()
}

/// Bytes of iceoryx2 shared memory reserved (file sizes) in /dev/shm.
pub fn shm_reserved_bytes() -> u64 {
    let Ok(dir) = fs::read_dir("/dev/shm") else {
        return 0;
    };
    dir.flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with("iox2_"))
        .filter_map(|e| e.metadata().ok())
        .map(|m| m.len())
        .sum()
}
