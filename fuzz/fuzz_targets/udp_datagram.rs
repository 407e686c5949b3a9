//! Every datagram a socket can receive: decode never panics, and whatever decodes
//! re-encodes to bytes that decode to the same datagram.
#![no_main]
use libfuzzer_sys::fuzz_target;
use muster_shared::udp::wire::Datagram;

fuzz_target!(|data: &[u8]| {
    if let Ok(d) = Datagram::decode(data) {
        let again = d.encode().expect("a decoded datagram re-encodes");
        assert_eq!(Datagram::decode(&again).expect("re-decodes"), d);
    }
});
