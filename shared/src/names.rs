//! Instance names and the iceoryx2 service names derived from them.
//!
//! Everything a process creates in shared memory is named `muster/<instance>/...`, so
//! instances (tests, demos) run side by side without seeing each other.

use crate::types::UserId;
use std::fmt;

/// Where a frame goes: the broker, a system, or a user. Each owns one inbox and one bell.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Address {
    /// The broker.
    Broker,
    /// A system, by name.
    System(String),
    /// A user, by id.
    User(UserId),
    /// The inbox at which a federated broker takes the frames for every user of another
    /// host (by that host's name): a frame for the user `alice@a` is written there, in an
    /// envelope naming its user ([`Address::relay`]). One inbox and one bell per host,
    /// not per user: a system's burst to 300 users of `a` is one inbox for the broker to
    /// read, its bell rung for the burst's first frame and at its end.
    Relay(String),
    /// The inbox shared by the users of one local process (by its pid), for a process
    /// that hosts many users (`muster user --count N`): a frame for the user
    /// `u1f2e3d~4242` ([`UserId::process_inbox`]) is written into process 4242's inbox, in
    /// an envelope naming its user, as for a relay. The broker and the systems then hold
    /// one pair of ports (about ten descriptors) for the process, not one per user.
    Process(u32),
}

impl Address {
    /// The relay through which frames for this address go, if any: a user of another
    /// host (`user@host`, [`UserId::is_foreign`]) is reached through its host's relay.
    pub fn relay(&self) -> Option<Address> {
        match self {
            Address::User(u) => u.0.rsplit_once('@').map(|(_, h)| Address::Relay(h.into())),
            _ => None,
        }
    }

    /// The inbox shared with others that frames for this address are written into, in
    /// envelopes naming their user: its host's relay for a user of another host
    /// ([`Address::relay`]), or its process's inbox for a local user that shares it
    /// ([`UserId::process_inbox`]); `None` for an address with an inbox of its own.
    pub fn shared_inbox(&self) -> Option<Address> {
        if let Some(r) = self.relay() {
            return Some(r);
        }
        match self {
            Address::User(u) => u.process_inbox().map(Address::Process),
            _ => None,
        }
    }

    /// The address whose inbox frames for this one are written into: its own, or a
    /// shared one ([`Address::shared_inbox`]).
    pub fn inbox_owner(&self) -> std::borrow::Cow<'_, Address> {
        match self.shared_inbox() {
            Some(r) => std::borrow::Cow::Owned(r),
            None => std::borrow::Cow::Borrowed(self),
        }
    }
}

impl fmt::Display for Address {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Address::Broker => f.write_str("broker"),
            Address::System(s) => write!(f, "system {s}"),
            Address::User(u) => write!(f, "user {u}"),
            Address::Relay(h) => write!(f, "relay for host {h}"),
            Address::Process(p) => write!(f, "users' inbox of process {p}"),
        }
    }
}

/// A validated instance name.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Instance(String);

/// The instance name is not 1..=32 characters of `[A-Za-z0-9_-]`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid instance name {0:?}: use 1 to 32 characters of [A-Za-z0-9_-]")]
pub struct BadInstance(pub String);

impl Instance {
    /// Checks and wraps an instance name.
    pub fn new(name: &str) -> Result<Self, BadInstance> {
        let ok = !name.is_empty()
            && name.len() <= 32
            && name
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
        if ok {
            Ok(Instance(name.to_string()))
        } else {
            Err(BadInstance(name.to_string()))
        }
    }

    /// The name.
    pub fn as_str(&self) -> &str {
        &self.0
    }

    fn owner(&self, addr: &Address) -> String {
        match addr {
            Address::Broker => format!("muster/{}/broker", self.0),
            Address::System(s) => format!("muster/{}/system/{s}", self.0),
            Address::User(u) => format!("muster/{}/user/{u}", self.0),
            Address::Relay(h) => format!("muster/{}/relay/{h}", self.0),
            Address::Process(p) => format!("muster/{}/process/{p}", self.0),
        }
    }

    /// The inbox (publish-subscribe) of `addr`.
    pub fn inbox(&self, addr: &Address) -> String {
        format!("{}/inbox", self.owner(addr))
    }

    /// The bell (event) of `addr`.
    pub fn bell(&self, addr: &Address) -> String {
        format!("{}/bell", self.owner(addr))
    }

    /// The event on which a starting broker announces itself to everyone.
    pub fn presence(&self) -> String {
        format!("muster/{}/presence", self.0)
    }

    /// The blackboard holding the service list snapshot of broker run `epoch`.
    pub fn service_list(&self, epoch: u64) -> String {
        format!("muster/{}/service-list/{epoch:016x}", self.0)
    }

    /// The stream a primary broker replicates its state on, to its standbys.
    pub fn replica(&self) -> String {
        format!("muster/{}/broker/replica", self.0)
    }

    /// The event rung when replication records wait.
    pub fn replica_bell(&self) -> String {
        format!("muster/{}/broker/replica-bell", self.0)
    }

    /// The broker's event feed (what it did, for consoles and recorders).
    pub fn events(&self) -> String {
        format!("muster/{}/broker/events", self.0)
    }

    /// The event rung when the feed has new events (the readers listen).
    pub fn events_bell(&self) -> String {
        format!("muster/{}/broker/events-bell", self.0)
    }

    /// The event a reader rings when it opens the feed (the broker listens): a bell of
    /// its own, so that the broker's news does not wake the broker.
    pub fn events_hello(&self) -> String {
        format!("muster/{}/broker/events-hello", self.0)
    }

    /// What system `system` shows of its own state (its estimates, tracks and plans),
    /// for recorders and viewers.
    pub fn viz(&self, system: &str) -> String {
        format!("muster/{}/system/{system}/viz", self.0)
    }

    /// The iceoryx2 node name of this instance's primary broker.
    pub fn broker_node(&self) -> String {
        format!("{BROKER_NODE}{}", self.0)
    }

    /// The iceoryx2 node name of this instance's standby brokers.
    pub fn standby_node(&self) -> String {
        format!("{STANDBY_NODE}{}", self.0)
    }

    /// The prefix of every service of this instance.
    pub fn prefix(&self) -> String {
        format!("muster/{}/", self.0)
    }
}

impl fmt::Display for Instance {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

/// Where iceoryx2 keeps node and service metadata, unless `MUSTER_IOX2_ROOT` says
/// otherwise. On tmpfs: iceoryx2 fsyncs these files, and on a disk-backed /tmp (its
/// default) that cost 4 fsyncs and ~5 ms of broker time per connecting user.
pub const DEFAULT_IOX2_ROOT: &str = "/dev/shm/muster/";

/// How the iceoryx2 node of a primary broker is named, before its instance.
pub const BROKER_NODE: &str = "muster-broker-";
/// How the iceoryx2 node of a standby broker is named, before its instance.
pub const STANDBY_NODE: &str = "muster-standby-";

/// The iceoryx2 metadata directory in use.
pub fn iox2_root() -> String {
    let mut root =
        std::env::var("MUSTER_IOX2_ROOT").unwrap_or_else(|_| DEFAULT_IOX2_ROOT.to_string());
    if !root.ends_with('/') {
        root.push('/');
    }
    root
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn instance_names() {
        assert!(Instance::new("t-1_x").is_ok());
        assert!(Instance::new("").is_err());
        assert!(Instance::new("a/b").is_err());
        assert!(Instance::new(&"x".repeat(33)).is_err());
        let i = Instance::new("t1").unwrap();
        assert_eq!(i.inbox(&Address::Broker), "muster/t1/broker/inbox");
        assert_eq!(
            i.bell(&Address::System("d1".into())),
            "muster/t1/system/d1/bell"
        );
        assert_eq!(
            i.inbox(&Address::User(UserId("u9".into()))),
            "muster/t1/user/u9/inbox"
        );
        assert_eq!(
            i.inbox(&Address::Relay("a".into())),
            "muster/t1/relay/a/inbox"
        );
        assert_eq!(
            Address::User(UserId("alice@a".into())).relay(),
            Some(Address::Relay("a".into()))
        );
        assert_eq!(Address::User(UserId("alice".into())).relay(), None);
        assert_eq!(Address::System("t1@b".into()).relay(), None);
        assert_eq!(
            *Address::User(UserId("alice@a".into())).inbox_owner(),
            Address::Relay("a".into())
        );
        assert_eq!(*Address::Broker.inbox_owner(), Address::Broker);
        // A user sharing its process's inbox, here and as another host sees it.
        let shared = Address::User(UserId("u1f2e3d~4242".into()));
        assert_eq!(*shared.inbox_owner(), Address::Process(4242));
        assert_eq!(shared.relay(), None);
        assert_eq!(
            i.inbox(&Address::Process(4242)),
            "muster/t1/process/4242/inbox"
        );
        assert_eq!(
            *Address::User(UserId("u1f2e3d~4242@a".into())).inbox_owner(),
            Address::Relay("a".into())
        );
        // Not a pid: an inbox of its own.
        for own in ["u~", "u~42x", "u~-1", "~", "u~99999999999"] {
            let a = Address::User(UserId(own.into()));
            assert_eq!(*a.inbox_owner(), a, "{own}");
        }
    }
}
