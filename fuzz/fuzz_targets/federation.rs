//! Federation frames from another host (`muster/<f>/<host>/req|in/<from>`, a batch of
//! frames each) and the lists hosts publish: what a broker decodes from the network. A
//! batch splits into frames within its bytes; a frame decodes or is refused; one that
//! decodes encodes again to the same bytes.
#![no_main]
use libfuzzer_sys::fuzz_target;
use muster_broker::federation::{split_batch, Batch, FedMsg, MAX_FED_FRAME};
use muster_shared::protocol::{decode, encode};
use muster_shared::snapshot::ServiceView;

fuzz_target!(|data: &[u8]| {
    let (frames, bad) = split_batch(data);
    let mut again = Batch::default();
    for f in &frames {
        assert!(f.len() <= MAX_FED_FRAME);
        frame(f);
        again.push(f);
    }
    // The frames taken make up the batch's bytes up to any fault, and all of them
    // without one.
    let bytes = again.take();
    assert_eq!(&data[..bytes.len()], &bytes[..]);
    assert!(bad || bytes.len() == data.len());
    frame(data);
    let _ = serde_json::from_slice::<Vec<ServiceView>>(data);
});

fn frame(data: &[u8]) {
    if let Ok(m) = decode::<FedMsg>(data) {
        // Re-encoding is stable (compared as bytes: a NaN in a payload is not equal to
        // itself).
        let once = encode(&m).expect("re-encodes");
        let back = decode::<FedMsg>(&once).expect("decodes what it encoded");
        assert_eq!(encode(&back).expect("re-encodes"), once);
    }
}
