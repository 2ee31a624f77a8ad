//! The seed's UDP marker frames on arbitrary datagrams.
#![no_main]

use defvol::dpcm::markers::FrameParser;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    FrameParser::default().parse(data);
});
