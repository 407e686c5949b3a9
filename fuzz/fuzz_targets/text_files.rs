//! The text files muster reads: the access file and key files.
#![no_main]
use libfuzzer_sys::fuzz_target;
use muster_shared::udp::access::AccessFile;
use muster_shared::udp::crypto::KeyPair;

fuzz_target!(|data: &[u8]| {
    if let Ok(s) = std::str::from_utf8(data) {
        if let Ok(a) = AccessFile::parse(s) {
            if let Some(p) = a.get("alice") {
                let _ = p.allows("T1/camera");
            }
        }
        let _ = KeyPair::parse(s);
    }
});
