//! The global service list as one fixed-size `#[repr(C)]` value that the broker writes
//! into an iceoryx2 blackboard and every local user reads from shared memory.
//!
//! The broker writes it once per change, never once per user, in chunks (see
//! [`ListHeader`]); the header's write counter tells a reader whether the copy it holds
//! is stale.

use crate::types::{
    ServiceId, ServiceKind, MAX_DESCRIPTION, MAX_HOST_NAME, MAX_PAYLOAD_TYPE, MAX_SERVICE_NAME,
    MAX_SYSTEM_NAME,
};
use iceoryx2::prelude::ZeroCopySend;
use serde::Serialize;

/// Most services a broker lists unless told otherwise (`muster broker --max-services`;
/// the paper ran 80). Neither the list in shared memory nor the remote users' list has a
/// fixed size: this is an admission limit, kept so that a runaway system cannot fill
/// memory, and a federation's merged list is held to it too.
pub const DEFAULT_MAX_SERVICES: usize = 65_536;

/// A fixed-capacity UTF-8 string that lives in shared memory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
pub struct FixedStr<const N: usize> {
    len: u8,
    bytes: [u8; N],
}

impl<const N: usize> FixedStr<N> {
    /// The empty string.
    pub const EMPTY: Self = FixedStr {
        len: 0,
        bytes: [0; N],
    };

    /// Copies `s`, cut at a character boundary to fit `N` bytes (at most 255).
    pub fn new(s: &str) -> Self {
        let cap = N.min(255);
        let mut end = s.len().min(cap);
        while !s.is_char_boundary(end) {
            end -= 1;
        }
        let mut bytes = [0u8; N];
        bytes[..end].copy_from_slice(&s.as_bytes()[..end]);
        FixedStr {
            len: end as u8,
            bytes,
        }
    }

    /// The bytes, as stored (a reader that only compares need not check them).
    pub fn as_bytes(&self) -> &[u8] {
        &self.bytes[..(self.len as usize).min(N)]
    }

    /// The text; empty if the bytes in shared memory are not valid UTF-8.
    pub fn as_str(&self) -> &str {
        let len = (self.len as usize).min(N);
        std::str::from_utf8(&self.bytes[..len]).unwrap_or("")
    }
}

/// One service as the list shows it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
pub struct ServiceEntry {
    /// Offering system.
    pub system: FixedStr<{ MAX_SYSTEM_NAME + 1 }>,
    /// Service name.
    pub name: FixedStr<{ MAX_SERVICE_NAME + 1 }>,
    /// Description.
    pub description: FixedStr<{ MAX_DESCRIPTION + 1 }>,
    /// Payload type name.
    pub payload: FixedStr<{ MAX_PAYLOAD_TYPE + 1 }>,
    /// How an open payload type's samples are encoded (`cdr`, `json`); empty for the
    /// built-in types.
    pub encoding: FixedStr<15>,
    /// Quota.
    pub quota: u16,
    /// Sessions in use (granted and being granted).
    pub in_use: u16,
    /// Requests waiting in the task queue.
    pub queued: u16,
    /// Links through this service.
    pub links: u16,
    /// 0 = data, 1 = command.
    pub kind: u8,
    /// 1 if a task queue is kept.
    pub queue: u8,
    /// 1 if withdrawn for now.
    pub withdrawn: u8,
    /// 1 if offered on another host of a federation (its id is `system@host/name`).
    pub remote: u8,
    /// The host that offers it, in a federation; empty otherwise.
    pub host: FixedStr<{ MAX_HOST_NAME + 1 }>,
}

impl ServiceEntry {
    /// Data or command.
    pub fn kind(&self) -> ServiceKind {
        if self.kind == 1 {
            ServiceKind::Command
        } else {
            ServiceKind::Data
        }
    }

    /// The stable id: `system/name`, or `system@host/name` for another host's service.
    pub fn id(&self) -> ServiceId {
        if self.remote == 1 {
            ServiceId::on_host(self.system.as_str(), self.host.as_str(), self.name.as_str())
        } else {
            ServiceId::new(self.system.as_str(), self.name.as_str())
        }
    }

    /// An owned view for printing and JSON.
    pub fn view(&self) -> ServiceView {
        ServiceView {
            id: self.id().0,
            system: self.system.as_str().to_string(),
            name: self.name.as_str().to_string(),
            description: self.description.as_str().to_string(),
            kind: self.kind().as_str().to_string(),
            queue: self.queue == 1,
            quota: self.quota,
            in_use: self.in_use,
            queued: self.queued,
            links: self.links,
            withdrawn: self.withdrawn == 1,
            payload: self.payload.as_str().to_string(),
            encoding: self.encoding.as_str().to_string(),
            host: self.host.as_str().to_string(),
            remote: self.remote == 1,
        }
    }
}

/// The whole list, as a reader copies it out of shared memory (or a remote user gets it).
#[derive(Clone, Debug, Default)]
pub struct ServiceListSnapshot {
    /// Bumped by the broker on every change; with the epoch it orders snapshots.
    pub generation: u64,
    /// The broker run that wrote it (0 = no broker has written yet).
    pub epoch: u64,
    /// The entries, in id order.
    entries: Vec<ServiceEntry>,
}

impl ServiceListSnapshot {
    /// An entry with nothing in it.
    pub const EMPTY_ENTRY: ServiceEntry = ServiceEntry {
        system: FixedStr::EMPTY,
        name: FixedStr::EMPTY,
        description: FixedStr::EMPTY,
        payload: FixedStr::EMPTY,
        encoding: FixedStr::EMPTY,
        quota: 0,
        in_use: 0,
        queued: 0,
        links: 0,
        kind: 0,
        queue: 0,
        withdrawn: 0,
        remote: 0,
        host: FixedStr::EMPTY,
    };

    /// An empty list.
    pub fn empty() -> Self {
        Self::default()
    }

    /// A list of these entries.
    pub fn from_entries(generation: u64, epoch: u64, entries: Vec<ServiceEntry>) -> Self {
        ServiceListSnapshot {
            generation,
            epoch,
            entries,
        }
    }

    /// Makes the list `count` entries long (new ones empty) and gives them to be written.
    pub fn resize(&mut self, count: usize) -> &mut [ServiceEntry] {
        self.entries.resize(count, Self::EMPTY_ENTRY);
        &mut self.entries
    }

    /// How many entries it has.
    pub fn count(&self) -> usize {
        self.entries.len()
    }

    /// The entries.
    pub fn entries(&self) -> &[ServiceEntry] {
        &self.entries
    }

    /// Finds a service by id.
    pub fn find(&self, id: &ServiceId) -> Option<&ServiceEntry> {
        self.entries().iter().find(|e| &e.id() == id)
    }

    /// Owned views of every entry.
    pub fn views(&self) -> Vec<ServiceView> {
        self.entries().iter().map(ServiceEntry::view).collect()
    }

    /// The entries `filter` lets through, from the `offset`th of them, at most `limit`.
    pub fn page(&self, filter: &ListFilter, offset: usize, limit: usize) -> ListPage {
        let m = filter.matcher();
        let (matching, page) = page_of(self.entries.iter().filter(|e| m.matches(e)), offset, limit);
        ListPage {
            generation: self.generation,
            epoch: self.epoch,
            matching,
            entries: page.into_iter().copied().collect(),
        }
    }
}

/// Of `items`, how many there are, and the ones from the `offset`th, at most `limit`
/// (references stay references: nothing is cloned here).
pub fn page_of<T>(items: impl Iterator<Item = T>, offset: usize, limit: usize) -> (usize, Vec<T>) {
    let mut page = Vec::new();
    let mut n = 0;
    for item in items {
        if n >= offset && page.len() < limit {
            page.push(item);
        }
        n += 1;
    }
    (n, page)
}

/// Which services a user wants to see: every condition given must hold.
#[derive(
    Clone,
    Debug,
    Default,
    PartialEq,
    Eq,
    Serialize,
    serde::Deserialize,
    rkyv::Archive,
    rkyv::Serialize,
    rkyv::Deserialize,
)]
pub struct ListFilter {
    /// The host offering it (in a federation, this host's services carry its name).
    pub host: Option<String>,
    /// The offering system.
    pub system: Option<String>,
    /// Data or command.
    pub kind: Option<ServiceKind>,
    /// The payload type's name.
    pub payload: Option<String>,
    /// A glob over the service's name (`*`, `?`, `[...]`, `{a,b}`).
    pub name: Option<String>,
}

/// The most bytes of a [`ListFilter`]'s texts taken: longer can match nothing listed.
const MAX_FILTER_TEXT: usize = 256;

impl ListFilter {
    /// Whether it lets every service through.
    pub fn is_everything(&self) -> bool {
        *self == ListFilter::default()
    }

    /// Checks the name glob and the lengths; an error says what is wrong.
    pub fn check(&self) -> Result<(), String> {
        for (what, t) in [
            ("host", &self.host),
            ("system", &self.system),
            ("payload", &self.payload),
            ("name", &self.name),
        ] {
            if t.as_ref().is_some_and(|t| t.len() > MAX_FILTER_TEXT) {
                return Err(format!(
                    "the {what} filter is longer than {MAX_FILTER_TEXT} bytes"
                ));
            }
        }
        if let Some(g) = &self.name {
            globset::Glob::new(g).map_err(|e| format!("the name filter {g:?}: {e}"))?;
        }
        Ok(())
    }

    /// The filter ready to match; a bad name glob matches nothing (see [`Self::check`]).
    pub fn matcher(&self) -> ListMatcher {
        ListMatcher {
            filter: self.clone(),
            name: self.name.as_ref().map(|g| {
                // The glob's own regex, matched on the name's bytes: globset's path
                // matcher first makes every name a path, which costs more than the match.
                let g = globset::Glob::new(g).ok()?;
                regex::bytes::Regex::new(g.regex()).ok()
            }),
            prefix: self.name.as_deref().map_or(Vec::new(), |g| {
                let end = g.find(['*', '?', '[', '{', '\\']).unwrap_or(g.len());
                g.as_bytes()[..end].to_vec()
            }),
        }
    }
}

/// The part of the list a view shows: the services a filter lets through, from an
/// offset, at most a limit.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ListPart {
    /// Which services.
    pub filter: ListFilter,
    /// How many of them to skip.
    pub offset: usize,
    /// Most to show.
    pub limit: usize,
}

impl Default for ListPart {
    fn default() -> Self {
        ListPart {
            filter: ListFilter::default(),
            offset: 0,
            limit: usize::MAX,
        }
    }
}

/// A [`ListFilter`] with its glob compiled.
pub struct ListMatcher {
    filter: ListFilter,
    name: Option<Option<regex::bytes::Regex>>,
    /// What every name the glob matches starts with (its text before the first
    /// wildcard): most names fail on it, before the regex.
    prefix: Vec<u8>,
}

impl ListMatcher {
    /// The filter it matches.
    pub fn filter(&self) -> &ListFilter {
        &self.filter
    }

    /// Whether `e` passes.
    pub fn matches(&self, e: &ServiceEntry) -> bool {
        self.passes(e)
    }

    /// Whether `v` passes.
    pub fn matches_view(&self, v: &ServiceView) -> bool {
        self.passes(v)
    }

    /// Whether `row` passes; only the fields the filter names are looked at, and
    /// bytes are compared as they are (nothing is checked as UTF-8).
    fn passes(&self, row: &impl ListRow) -> bool {
        let f = &self.filter;
        let same = |want: &Option<String>, have: &[u8]| {
            want.as_deref().is_none_or(|w| w.as_bytes() == have)
        };
        same(&f.system, row.system())
            && same(&f.host, row.host())
            && same(&f.payload, row.payload())
            && f.kind.is_none_or(|k| k == row.kind())
            && match &self.name {
                None => true,
                Some(None) => false,
                Some(Some(g)) => {
                    let name = row.name();
                    name.starts_with(&self.prefix) && g.is_match(name)
                }
            }
    }
}

/// What a [`ListMatcher`] looks at in a row of the list, shared memory's or owned.
trait ListRow {
    fn system(&self) -> &[u8];
    fn host(&self) -> &[u8];
    fn payload(&self) -> &[u8];
    fn kind(&self) -> ServiceKind;
    fn name(&self) -> &[u8];
}

impl ListRow for ServiceEntry {
    fn system(&self) -> &[u8] {
        self.system.as_bytes()
    }
    fn host(&self) -> &[u8] {
        self.host.as_bytes()
    }
    fn payload(&self) -> &[u8] {
        self.payload.as_bytes()
    }
    fn kind(&self) -> ServiceKind {
        ServiceEntry::kind(self)
    }
    fn name(&self) -> &[u8] {
        self.name.as_bytes()
    }
}

impl ListRow for ServiceView {
    fn system(&self) -> &[u8] {
        self.system.as_bytes()
    }
    fn host(&self) -> &[u8] {
        self.host.as_bytes()
    }
    fn payload(&self) -> &[u8] {
        self.payload.as_bytes()
    }
    fn kind(&self) -> ServiceKind {
        if self.kind == ServiceKind::Command.as_str() {
            ServiceKind::Command
        } else {
            ServiceKind::Data
        }
    }
    fn name(&self) -> &[u8] {
        self.name.as_bytes()
    }
}

/// One page of the list: the entries a filter lets through, from an offset.
#[derive(Clone, Debug, Default)]
pub struct ListPage {
    /// The list's generation.
    pub generation: u64,
    /// The broker run that wrote it.
    pub epoch: u64,
    /// How many entries in the whole list the filter lets through.
    pub matching: usize,
    /// The page's entries, in id order.
    pub entries: Vec<ServiceEntry>,
}

impl ListPage {
    /// Owned views of the page's entries.
    pub fn views(&self) -> Vec<ServiceView> {
        self.entries.iter().map(ServiceEntry::view).collect()
    }
}

/// Entries per chunk of the list in shared memory.
pub const CHUNK_ENTRIES: usize = 16;
/// Chunks of the first list in shared memory a broker run makes; a longer list is
/// written into a new one with room for twice as many, and so on.
pub const FIRST_LIST_CHUNKS: usize = 16;

/// The list's header in shared memory: which write it is, and how many entries.
///
/// The list is a header and `chunks` chunks of [`CHUNK_ENTRIES`] entries, each a
/// blackboard entry of its own, so a reader copies only the chunks that hold
/// entries and the broker writes only the chunks that changed. The broker writes the
/// changed chunks, each stamped with the write's `seq`, then the header; a reader takes
/// the header, the chunks, and the header again, and keeps what it read only if the
/// header did not change and no chunk is newer than it (else it reads again).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
pub struct ListHeader {
    /// The write, counted from 1 by the writer; 0: nothing written yet.
    pub seq: u64,
    /// The list's generation (the broker's).
    pub generation: u64,
    /// The broker run that wrote it.
    pub epoch: u64,
    /// Valid entries.
    pub count: u32,
    /// The chunks this blackboard holds (fixed when it is made).
    pub chunks: u32,
}

/// One chunk of the list in shared memory (see [`ListHeader`]).
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[repr(C)]
pub struct ListChunk {
    /// The write that last changed it.
    pub seq: u64,
    /// Entries `k * CHUNK_ENTRIES ..` of the list.
    pub entries: [ServiceEntry; CHUNK_ENTRIES],
}

/// Chunks whose last write one [`ListSeqs`] page holds.
pub const SEQS_PER_PAGE: usize = 512;

/// Which write last changed each of [`SEQS_PER_PAGE`] chunks (page `p` holds chunks
/// `p * SEQS_PER_PAGE ..`): a reader holding a copy takes only the chunks that changed
/// since, and a whole-list read after a change copies one chunk, not the whole list.
#[derive(Clone, Copy, Debug, ZeroCopySend)]
#[repr(C)]
pub struct ListSeqs {
    /// The chunks' `seq`s.
    pub seqs: [u64; SEQS_PER_PAGE],
}

impl ListChunk {
    /// A chunk of empty entries.
    pub fn empty() -> Self {
        ListChunk {
            seq: 0,
            entries: [ServiceListSnapshot::EMPTY_ENTRY; CHUNK_ENTRIES],
        }
    }
}

/// An owned, printable row of the list; its JSON form is what `muster user list --json` prints.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct ServiceView {
    /// `system/name`.
    pub id: String,
    /// Offering system.
    pub system: String,
    /// Service name.
    pub name: String,
    /// Description.
    pub description: String,
    /// `data` or `command`.
    pub kind: String,
    /// Task queue kept.
    pub queue: bool,
    /// Quota.
    pub quota: u16,
    /// Sessions in use.
    pub in_use: u16,
    /// Requests waiting.
    pub queued: u16,
    /// Links through the service.
    pub links: u16,
    /// Withdrawn for now.
    pub withdrawn: bool,
    /// Payload type.
    pub payload: String,
    /// How an open payload type's samples are encoded (`cdr` for ROS 2 messages, `json`);
    /// empty for the built-in types.
    #[serde(default)]
    pub encoding: String,
    /// The host offering it, in a federation (`muster broker --federate`); empty otherwise.
    pub host: String,
    /// Offered on another host: the id is `system@host/name`, and a request for it goes
    /// to that host's broker.
    pub remote: bool,
}

impl ServiceView {
    /// Packs the view into a shared-memory entry.
    pub fn to_entry(&self) -> ServiceEntry {
        ServiceEntry {
            system: FixedStr::new(&self.system),
            name: FixedStr::new(&self.name),
            description: FixedStr::new(&self.description),
            payload: FixedStr::new(&self.payload),
            encoding: FixedStr::new(&self.encoding),
            quota: self.quota,
            in_use: self.in_use,
            queued: self.queued,
            links: self.links,
            kind: u8::from(self.kind == "command"),
            queue: u8::from(self.queue),
            withdrawn: u8::from(self.withdrawn),
            remote: u8::from(self.remote),
            host: FixedStr::new(&self.host),
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn fixed_str_cuts_at_char_boundary() {
        let s = FixedStr::<4>::new("aéé");
        assert_eq!(s.as_str(), "aé");
        assert_eq!(FixedStr::<8>::new("tracker").as_str(), "tracker");
    }

    #[test]
    fn view_round_trips_through_entry() {
        let v = ServiceView {
            id: "t1/track".into(),
            system: "t1".into(),
            name: "track".into(),
            description: "follows a beacon".into(),
            kind: "command".into(),
            queue: true,
            quota: 10,
            in_use: 3,
            queued: 2,
            links: 1,
            withdrawn: false,
            payload: "geometry_msgs/msg/PoseWithCovarianceStamped".into(),
            encoding: "cdr".into(),
            host: String::new(),
            remote: false,
        };
        assert_eq!(v.to_entry().view(), v);
        let far = ServiceView {
            id: "t1@lab-2/track".into(),
            host: "lab-2".into(),
            remote: true,
            ..v
        };
        assert_eq!(far.to_entry().view(), far);
        assert_eq!(far.to_entry().id().0, "t1@lab-2/track");
    }
}
