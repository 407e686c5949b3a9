//! muster and VDA 5050, the interface between AGVs and a master control (JSON over
//! MQTT): a fleet's vehicles become muster services many users can ask for
//! ([`fleet::Fleet`], `muster system vda5050`).
//!
//! Version 2 is spoken (header `2.x.y`, topics `interface/v2/manufacturer/serial/topic`):
//! messages to a vehicle carry the version the vehicle itself sends (2.0.0 or 2.1.0),
//! or the configured one before it said any. Every message read or written is checked
//! ([`msg::decode`], [`msg::encode`]); one that breaks the rules is logged and dropped.

pub mod agv;
pub mod fleet;
pub mod graph;
pub mod mqtt;
pub mod msg;
pub mod schemas;

/// Why the bridge could not start.
#[derive(Debug, thiserror::Error)]
pub enum VdaFail {
    /// A bad option (address, name, graph file); the text says which.
    #[error("VDA 5050: {0}")]
    Config(String),
}

/// The MQTT topic layout: `interfaceName/majorVersion/manufacturer/serialNumber/topic`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Topics {
    /// `interfaceName` (`uagv` by default).
    pub interface: String,
    /// `majorVersion` (`v2`).
    pub major: String,
}

impl Topics {
    /// Topics of interface `interface`, major version 2.
    pub fn v2(interface: &str) -> Self {
        Topics {
            interface: interface.to_string(),
            major: "v2".to_string(),
        }
    }

    /// One vehicle's topic.
    pub fn topic(&self, manufacturer: &str, serial: &str, topic: &str) -> String {
        format!(
            "{}/{}/{manufacturer}/{serial}/{topic}",
            self.interface, self.major
        )
    }

    /// The filter for `topic` of every vehicle (of `manufacturer`, if given).
    pub fn filter(&self, manufacturer: Option<&str>, topic: &str) -> String {
        self.topic(manufacturer.unwrap_or("+"), "+", topic)
    }

    /// `(manufacturer, serial, topic)` of one of our topics, `None` for any other.
    pub fn parse<'a>(&self, topic: &'a str) -> Option<(&'a str, &'a str, &'a str)> {
        let mut it = topic.split('/');
        let (i, v, m, s, t) = (it.next()?, it.next()?, it.next()?, it.next()?, it.next()?);
        if it.next().is_some() || i != self.interface || v != self.major {
            return None;
        }
        if m.is_empty() || s.is_empty() || t.is_empty() {
            return None;
        }
        Some((m, s, t))
    }
}

/// A name from a vehicle (serial, manufacturer) as a muster name: `[A-Za-z0-9_.-]`,
/// at most `max` bytes (a long one keeps its start and a hash of the whole).
pub fn muster_name(s: &str, max: usize) -> String {
    let clean: String = s
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "_-.".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect();
    let clean = if clean.is_empty() { "_".into() } else { clean };
    if clean.len() <= max {
        return clean;
    }
    // FNV-1a of the original, so two long names that share a start stay apart.
    let h = s.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
    });
    let tail = format!("-{:06x}", h & 0xff_ffff);
    format!("{}{tail}", &clean[..max - tail.len()])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topics_are_made_and_read_back() {
        let t = Topics::v2("uagv");
        assert_eq!(t.topic("acme", "agv1", "order"), "uagv/v2/acme/agv1/order");
        assert_eq!(t.filter(None, "state"), "uagv/v2/+/+/state");
        assert_eq!(t.filter(Some("acme"), "state"), "uagv/v2/acme/+/state");
        assert_eq!(
            t.parse("uagv/v2/acme/agv1/state"),
            Some(("acme", "agv1", "state"))
        );
        for bad in [
            "uagv/v1/acme/agv1/state",
            "x/v2/a/b/c",
            "uagv/v2/a/b",
            "uagv/v2/a/b/c/d",
            "uagv/v2//b/c",
        ] {
            assert_eq!(t.parse(bad), None, "{bad}");
        }
    }

    #[test]
    fn vehicle_names_become_muster_names() {
        assert_eq!(muster_name("agv-1.x", 25), "agv-1.x");
        assert_eq!(muster_name("AGV #7/ü", 25), "AGV__7__");
        let a = muster_name(&"a".repeat(40), 25);
        let b = muster_name(&format!("{}b", "a".repeat(39)), 25);
        assert_eq!(a.len(), 25);
        assert_ne!(a, b);
        assert_eq!(muster_name("", 25), "_");
    }
}
