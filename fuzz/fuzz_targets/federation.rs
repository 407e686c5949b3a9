//! Federation frames from another host (`muster/<f>/<host>/req|in/<from>`) and the lists
//! hosts publish: what a broker decodes from the network. A frame decodes or is refused;
//! one that decodes encodes again to the same bytes.
#![no_main]
use libfuzzer_sys::fuzz_target;
use muster_broker::federation::FedMsg;
use muster_shared::protocol::{decode, encode};
use muster_shared::snapshot::ServiceView;

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = decode::<FedMsg>(data) {
        // Re-encoding is stable (compared as bytes: a NaN in a payload is not equal to
        // itself).
        let once = encode(&m).expect("re-encodes");
        let back = decode::<FedMsg>(&once).expect("decodes what it encoded");
        assert_eq!(encode(&back).expect("re-encodes"), once);
    }
    let _ = serde_json::from_slice::<Vec<ServiceView>>(data);
});
