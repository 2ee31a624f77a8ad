//! Every mesh format's parser on arbitrary bytes: the first byte picks the format.
#![no_main]

use std::path::Path;

use defvol::io::{self, MeshFormat};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((kind, bytes)) = data.split_first() else { return };
    let path = Path::new("fuzz");
    let _ = match kind % 4 {
        0 => io::parse_mesh(path, bytes, MeshFormat::VtkXml),
        1 => io::parse_mesh(path, bytes, MeshFormat::VtkLegacy),
        2 => io::parse_mesh(path, bytes, MeshFormat::Gmsh),
        _ => {
            // TetGen: the .node and .ele files split where the first NUL byte is.
            let split = bytes.iter().position(|b| *b == 0).unwrap_or(bytes.len());
            io::parse_tetgen(path, &bytes[..split], bytes.get(split + 1..).unwrap_or(&[]))
        }
    };
});
