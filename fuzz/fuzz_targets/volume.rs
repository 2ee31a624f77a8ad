//! Every volume format's parser on arbitrary bytes: the first byte picks the format (DICOM
//! among them); a detached header's data file is the same bytes again.
#![no_main]

use std::path::Path;

use defvol::io;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((kind, bytes)) = data.split_first() else { return };
    let name = ["v.nii", "v.nii.gz", "v.nrrd", "v.nhdr", "v.mha", "v.mhd", "v.dcm"][usize::from(*kind) % 7];
    let _ = match name {
        "v.dcm" => io::parse_dicom(Path::new(name), bytes),
        _ => io::parse_volume(Path::new(name), bytes, &|_| Some(bytes.to_vec())),
    };
});
