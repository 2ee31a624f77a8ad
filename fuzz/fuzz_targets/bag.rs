//! The bag reader and the message decoder on arbitrary bytes.
#![no_main]

use std::path::Path;

use defvol::msgs::{self, PoseStamped};
use defvol::record::bag;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(messages) = bag::parse_messages(Path::new("fuzz.mcap"), data, &[]) {
        for m in messages {
            let _ = msgs::decode::<PoseStamped>(&m.data, &m.topic);
        }
    }
});
