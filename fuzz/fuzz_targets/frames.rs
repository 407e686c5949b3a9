//! Shared-memory frames: the inbox decoders of broker, systems and users.
#![no_main]
use libfuzzer_sys::fuzz_target;
use muster_shared::protocol::{decode, encode, ToBroker, ToSystem, ToUser};

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = decode::<ToBroker>(data) {
        assert_eq!(decode::<ToBroker>(&encode(&m).expect("re-encodes")).ok(), Some(m));
    }
    let _ = decode::<ToSystem>(data);
    let _ = decode::<ToUser>(data);
});
