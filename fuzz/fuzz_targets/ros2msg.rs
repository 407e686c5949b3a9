//! ROS 2 message definitions and CDR samples (open payloads): any definition text and
//! any sample bytes give a value or a clear error, never a panic or a runaway allocation.
#![no_main]
use libfuzzer_sys::fuzz_target;
use muster_shared::ros2msg::Definitions;

/// A definition that parses, for the samples-only half of the input.
const CLOUD: &str = "string name\ngeometry_msgs/Point[] points\nuint8[2] flags\nfloat32 scale\nbool[] bits\nint64 big\n================================================================================\nMSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n";

fuzz_target!(|data: &[u8]| {
    // The first byte picks the half: a fuzzed definition (text, then a NUL, then a
    // sample) or a fixed one with a fuzzed sample.
    let Some((&pick, rest)) = data.split_first() else { return };
    let (defs, sample) = if pick & 1 == 0 {
        let cut = rest.iter().position(|&b| b == 0).unwrap_or(rest.len());
        let Ok(text) = std::str::from_utf8(&rest[..cut]) else { return };
        match Definitions::parse("fuzz_pkg/msg/Root", text) {
            Ok(d) => (d, rest.get(cut + 1..).unwrap_or(&[])),
            Err(_) => return,
        }
    } else {
        match Definitions::parse("fuzz_pkg/Cloud", CLOUD) {
            Ok(d) => (d, rest),
            Err(_) => return,
        }
    };
    if let Ok(v) = defs.decode(sample) {
        // What decodes re-serializes, and its walk transcodes back to CDR that decodes.
        let walked = defs
            .reserialize(sample, serde_json::value::Serializer)
            .expect("a sample that decodes re-serializes");
        // Non-finite floats become null in JSON: only finite samples come back whole.
        let text = v.to_string();
        if !text.contains("inf") && !text.contains("nan") {
            let bytes = defs.transcode(walked).expect("a finite sample transcodes");
            let again = defs.decode(&bytes).expect("transcoded CDR decodes");
            assert_eq!(again, v);
        }
    }
});
