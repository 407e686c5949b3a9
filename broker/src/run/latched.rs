//! Latched data services: the newest update of each, kept for the next session's grant.
//!
//! A system that latches a data service ([`muster_systems`'s `SystemCore::latch`])
//! writes each update it streams into the broker's inbox too ([`ToBroker::Latest`]),
//! ringing the broker's bell for one at most every 250 ms (the broker reads the rest
//! as it reads its inbox for anything else). The broker keeps the newest per service and,
//! granting a session of it to a user of this host (over shared memory, or remote through
//! the UDP front) or of another host (through the federation), sends the user that value
//! right behind the grant as the session's
//! update 0: the user has the service's value with its grant, instead of at
//! the system's next turn (its offer is read a moment later, and its first contact
//! with a new user's inbox costs a few tenths of a millisecond). The value is the
//! shell's, not the core's: it is neither journaled nor replicated (the system sends
//! its newest value of each again every time it registers, so a standby that takes
//! over has it as soon as the system registers with it).

use muster_shared::protocol::{decode, ToBroker, ToUser};
use muster_shared::types::{Payload, ServiceId, ServiceKind};
use std::collections::HashMap;

use crate::core::{Broker, Grant};

/// One service's newest update.
struct Kept {
    /// The system process that sent it: only a session that process granted gets it.
    pid: u32,
    sent_ns: u64,
    /// Its [`Payload`] as a frame: decoded at a grant, not at each update (a service
    /// updates far more often than it is granted).
    payload: Vec<u8>,
}

/// The newest update of each latched service.
#[derive(Default)]
pub(super) struct Latched {
    kept: HashMap<ServiceId, Kept>,
}

impl Latched {
    /// Keeps `msg` (a [`ToBroker::Latest`] the core let through from process `pid`)
    /// if it is the value of a data service its system offers.
    pub(super) fn keep(&mut self, core: &Broker, pid: Option<u32>, msg: ToBroker) {
        let ToBroker::Latest {
            system,
            service,
            sent_ns,
            payload,
        } = msg
        else {
            return;
        };
        let id = ServiceId::new(&system, &service);
        // From a process that cannot be told (no check possible), or for no listed data
        // service: nothing to keep.
        let (Some(pid), Some(ServiceKind::Data)) = (pid, core.kind_of(&id)) else {
            return;
        };
        // At most one per listed service: those no longer listed go first.
        if !self.kept.contains_key(&id) && self.kept.len() >= core.config().max_services {
            self.kept.retain(|id, _| core.kind_of(id).is_some());
        }
        self.kept.insert(
            id,
            Kept {
                pid,
                sent_ns,
                payload,
            },
        );
    }

    /// The update 0 that goes with grant `g`, if its service is a latched data service
    /// whose value came from the process that granted it.
    pub(super) fn update_zero(&self, g: &Grant) -> Option<ToUser> {
        if g.kind != ServiceKind::Data {
            return None;
        }
        let kept = self
            .kept
            .get(&g.service)
            .filter(|k| k.pid == g.system_pid)?;
        let payload = decode::<Payload>(&kept.payload)
            .map_err(|e| tracing::debug!(service = %g.service, "a latched value that does not decode: {e}"))
            .ok()?;
        Some(ToUser::Update {
            session: g.session,
            seq: 0,
            sent_ns: kept.sent_ns,
            payload,
        })
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::core::BrokerConfig;
    use muster_shared::protocol::encode;
    use muster_shared::types::{ServiceSpec, SessionId, UserId};
    use std::time::Duration;

    fn spec(name: &str, kind: ServiceKind) -> ServiceSpec {
        ServiceSpec {
            name: name.into(),
            description: format!("{name} service"),
            kind,
            queue: false,
            quota: 5,
            payload: if kind == ServiceKind::Data {
                "pose2d"
            } else {
                "goal2d"
            }
            .into(),
            schema: None,
        }
    }

    /// A broker with system `t` (pid 50) offering data service `d` and command `c`.
    fn broker() -> Broker {
        let mut b = Broker::new(BrokerConfig::default(), 42, 1000);
        b.handle(
            Duration::ZERO,
            ToBroker::Register {
                system: "t".into(),
                pid: 50,
                services: vec![
                    spec("d", ServiceKind::Data),
                    spec("c", ServiceKind::Command),
                ],
                sessions: vec![],
                udp: None,
            },
        );
        b
    }

    fn latest(service: &str, x: f64) -> ToBroker {
        ToBroker::Latest {
            system: "t".into(),
            service: service.into(),
            sent_ns: 7,
            payload: encode(&Payload::Pose2d {
                x,
                y: 0.0,
                theta: 0.0,
            })
            .unwrap(),
        }
    }

    fn grant(service: &str, kind: ServiceKind, system_pid: u32) -> Grant {
        Grant {
            user: UserId("u1".into()),
            req: 1,
            session: SessionId(9),
            service: ServiceId::new("t", service),
            kind,
            payload: "pose2d".into(),
            schema: None,
            system_pid,
        }
    }

    #[test]
    fn the_newest_value_of_a_data_service_goes_with_a_grant_by_its_sender() {
        let core = broker();
        let mut l = Latched::default();
        l.keep(&core, Some(50), latest("d", 1.0));
        l.keep(&core, Some(50), latest("d", 2.0));
        let zero = l.update_zero(&grant("d", ServiceKind::Data, 50)).unwrap();
        assert_eq!(
            zero,
            ToUser::Update {
                session: SessionId(9),
                seq: 0,
                sent_ns: 7,
                payload: Payload::Pose2d {
                    x: 2.0,
                    y: 0.0,
                    theta: 0.0
                },
            },
            "the newest, as update 0 of the granted session"
        );
        // Granted by another process (the system restarted since): not its value.
        assert_eq!(l.update_zero(&grant("d", ServiceKind::Data, 51)), None);
    }

    #[test]
    fn values_for_no_listed_data_service_or_from_an_unknown_process_are_not_kept() {
        let core = broker();
        let mut l = Latched::default();
        l.keep(&core, Some(50), latest("c", 1.0));
        l.keep(&core, Some(50), latest("nosuch", 1.0));
        l.keep(&core, None, latest("d", 1.0));
        assert_eq!(l.kept.len(), 0);
        assert_eq!(l.update_zero(&grant("c", ServiceKind::Command, 50)), None);
        assert_eq!(l.update_zero(&grant("d", ServiceKind::Data, 50)), None);
        // A value whose payload does not decode gives no update 0.
        let mut bad = latest("d", 1.0);
        if let ToBroker::Latest { payload, .. } = &mut bad {
            payload.truncate(3);
        }
        l.keep(&core, Some(50), bad);
        assert_eq!(l.update_zero(&grant("d", ServiceKind::Data, 50)), None);
    }
}
