//! Records on the standby stream: a standby's follower takes any bytes (a record, a
//! torn one, garbage) and applies, ignores or refuses them; never a panic. A follower
//! that holds a state keeps applying the real records that follow.
#![no_main]
use libfuzzer_sys::fuzz_target;
use muster_broker::replica::{Follower, Leader};
use muster_broker::{Broker, BrokerConfig};

fuzz_target!(|data: &[u8]| {
    // Bytes as they come: a fresh follower.
    let mut f = Follower::new();
    let _ = f.apply(data);
    // The same after a real image: the follower is in sync, then gets the bytes.
    let core = Broker::new(BrokerConfig::default(), 1, 1);
    let leader = Leader::after(0);
    let mut f = Follower::new();
    f.apply(&leader.image(&core)).expect("a real image applies");
    let _ = f.apply(data);
    let _ = f.apply(&leader.heartbeat());
});
