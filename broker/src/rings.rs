//! Which list watchers to ring: those watching all of the list, and those watching a
//! part of it that changed.
//!
//! The broker notes each entry of the list that changes between two rings (as it was
//! and as it is); a watcher of part of the list (a [`ListFilter`]) is rung only if one
//! of them is in its part. When services come or go, rows move, and when too much
//! changes to keep, every watcher is rung: a ring too many costs a reader one read of
//! its part, a ring missed would leave it showing an old list.

use crate::core::Broker;
use muster_shared::snapshot::{ListFilter, ListMatcher, ServiceEntry};
use muster_shared::types::UserId;
use std::collections::{HashMap, HashSet};

/// Most changed entries (before and after) kept between two rings; past it, every
/// watcher is rung.
pub const CHANGED_MAX: usize = 4096;

/// What changed since the last ring, and the watchers' filters ready to match.
pub struct Rings {
    /// Each changed entry as it was and as it is; `None`: ring everyone.
    changed: Option<Vec<ServiceEntry>>,
    matchers: HashMap<UserId, ListMatcher>,
}

impl Default for Rings {
    /// Nothing changed yet.
    fn default() -> Self {
        Rings {
            changed: Some(Vec::new()),
            matchers: HashMap::new(),
        }
    }
}

impl Rings {
    /// Nothing changed yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// An entry changed from `old` to `new`.
    pub fn changed(&mut self, old: &ServiceEntry, new: &ServiceEntry) {
        if let Some(c) = self.changed.as_mut() {
            c.push(*old);
            c.push(*new);
            if c.len() > CHANGED_MAX {
                self.changed = None;
            }
        }
    }

    /// Services came or went (or something else every watcher must hear of).
    pub fn everything_changed(&mut self) {
        self.changed = None;
    }

    /// The watchers to ring now, and forgets what changed.
    pub fn take<'a>(
        &mut self,
        watchers: impl Iterator<Item = (&'a UserId, Option<&'a ListFilter>)>,
    ) -> Vec<UserId> {
        let changed = self.changed.replace(Vec::new());
        let mut filtered = HashSet::new();
        let matchers = &mut self.matchers;
        let rung = watchers
            .filter(|(u, f)| {
                let (Some(f), Some(changed)) = (f, changed.as_ref()) else {
                    return true;
                };
                filtered.insert((*u).clone());
                let m = matchers.entry((*u).clone()).or_insert_with(|| f.matcher());
                if m.filter() != *f {
                    *m = f.matcher();
                }
                changed.iter().any(|e| m.matches(e))
            })
            .map(|(u, _)| u.clone())
            .collect();
        // Users gone or no longer filtering are forgotten.
        if changed.is_some() {
            self.matchers.retain(|u, _| filtered.contains(u));
        }
        rung
    }

    /// [`Rings::take`] of the core's watchers.
    pub fn take_from(&mut self, core: &Broker) -> Vec<UserId> {
        self.take(core.list_watchers_with_filters())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use muster_shared::snapshot::{FixedStr, ServiceListSnapshot};
    use muster_shared::types::ServiceKind;

    fn entry(system: &str, name: &str, in_use: u16) -> ServiceEntry {
        let mut e = ServiceListSnapshot::EMPTY_ENTRY;
        e.system = FixedStr::new(system);
        e.name = FixedStr::new(name);
        e.in_use = in_use;
        e
    }

    #[test]
    fn watchers_of_a_part_are_rung_only_when_that_part_changes() {
        let (all, t1, t2, cmd) = (
            UserId("all".into()),
            UserId("t1".into()),
            UserId("t2".into()),
            UserId("cmd".into()),
        );
        let on = |s: &str| ListFilter {
            system: Some(s.into()),
            ..ListFilter::default()
        };
        let (f1, f2) = (on("t1"), on("t2"));
        let fc = ListFilter {
            kind: Some(ServiceKind::Command),
            ..ListFilter::default()
        };
        let watchers = || {
            vec![
                (&all, None),
                (&t1, Some(&f1)),
                (&t2, Some(&f2)),
                (&cmd, Some(&fc)),
            ]
            .into_iter()
        };
        let mut r = Rings::new();
        // t1/s0's sessions in use change: its watchers, not t2's or command's.
        r.changed(&entry("t1", "s0", 0), &entry("t1", "s0", 1));
        assert_eq!(r.take(watchers()), vec![all.clone(), t1.clone()]);
        // Nothing changed since: only those watching everything.
        assert_eq!(r.take(watchers()), vec![all.clone()]);
        // A service turning into a command service: the old entry matches t2, the
        // new one command.
        let mut c = entry("t2", "s3", 0);
        c.kind = 1;
        r.changed(&entry("t2", "s3", 0), &c);
        assert_eq!(
            r.take(watchers()),
            vec![all.clone(), t2.clone(), cmd.clone()]
        );
        // Services came or went: everyone.
        r.everything_changed();
        assert_eq!(r.take(watchers()).len(), 4);
        // Too many changes to keep: everyone.
        for i in 0..=CHANGED_MAX / 2 {
            r.changed(
                &entry("t9", &format!("s{i}"), 0),
                &entry("t9", &format!("s{i}"), 1),
            );
        }
        assert_eq!(r.take(watchers()).len(), 4);
        // A watcher whose filter changes is matched with the new one.
        let f3 = on("t3");
        r.changed(&entry("t3", "s0", 0), &entry("t3", "s0", 1));
        let rung = r.take(vec![(&t1, Some(&f3))].into_iter());
        assert_eq!(rung, vec![t1.clone()]);
    }
}
