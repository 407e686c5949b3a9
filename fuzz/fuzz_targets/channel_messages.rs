//! The plaintexts inside the encrypted channels (after decryption, so only authenticated
//! peers reach these decoders, but they must still never panic).
#![no_main]
use libfuzzer_sys::fuzz_target;
use muster_shared::udp::msgs::{from_bytes, to_bytes, Down, Hs3, SessionDown, SessionUp, Up};

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = from_bytes::<Up>(data) {
        let _ = to_bytes(&m);
    }
    if let Ok(m) = from_bytes::<Down>(data) {
        let _ = to_bytes(&m);
    }
    let _ = from_bytes::<SessionUp>(data);
    let _ = from_bytes::<SessionDown>(data);
    let _ = from_bytes::<Hs3>(data);
});
