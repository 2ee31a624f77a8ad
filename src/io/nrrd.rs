//! NRRD (`.nrrd` attached, `.nhdr` detached): the header fields a 3D scalar volume uses.
//! Written as NRRD0004, f32, gzip, in LPS space.

use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

use nalgebra::{Matrix3, Vector3};

use super::{decompress, io_error, malformed, Compression, IoError, SampleType};
use crate::volume::Volume;

fn parse_vector(path: &Path, field: &str, text: &str) -> Result<Vector3<f64>, IoError> {
    let v: Vec<f64> = text
        .trim()
        .trim_start_matches('(')
        .trim_end_matches(')')
        .split(',')
        .map(|c| c.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| malformed(path, format!("`{field}`: expected (x,y,z), got `{text}`")))?;
    match v[..] {
        [x, y, z] => Ok(Vector3::new(x, y, z)),
        _ => Err(malformed(path, format!("`{field}`: expected 3 components, got `{text}`"))),
    }
}

pub(super) fn read(path: &Path) -> Result<Volume, IoError> {
    let bytes = std::fs::read(path).map_err(io_error(path))?;
    if !bytes.starts_with(b"NRRD000") {
        return Err(malformed(path, "missing the NRRD000x magic line"));
    }
    let mut fields: HashMap<String, String> = HashMap::new();
    let mut pos = 0;
    let mut header_end = None;
    for line in bytes.split(|b| *b == b'\n') {
        pos += line.len() + 1;
        let text = String::from_utf8_lossy(line).trim_end_matches('\r').to_owned();
        if text.is_empty() {
            header_end = Some(pos);
            break;
        }
        if text.starts_with('#') || text.starts_with("NRRD") {
            continue;
        }
        if let Some((k, v)) = text.split_once(": ") {
            fields.insert(k.trim().to_lowercase(), v.trim().to_owned());
        }
    }
    let get = |k: &str| fields.get(k).map(String::as_str);
    let need = |k: &str| get(k).ok_or_else(|| malformed(path, format!("header has no `{k}` field")));
    if need("dimension")? != "3" {
        return Err(malformed(path, format!("dimension {}: only 3D scalar volumes are supported", need("dimension")?)));
    }
    let sizes: Vec<usize> = need("sizes")?
        .split_whitespace()
        .map(str::parse)
        .collect::<Result<_, _>>()
        .map_err(|_| malformed(path, "`sizes`: expected 3 integers"))?;
    let [nx, ny, nz] = sizes[..] else { return Err(malformed(path, "`sizes`: expected 3 integers")) };
    let sample = match need("type")? {
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => SampleType::U8,
        "signed char" | "int8" | "int8_t" => SampleType::I8,
        "ushort" | "unsigned short" | "uint16" | "uint16_t" => SampleType::U16,
        "short" | "signed short" | "int16" | "int16_t" => SampleType::I16,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => SampleType::U32,
        "int" | "signed int" | "int32" | "int32_t" => SampleType::I32,
        "float" => SampleType::F32,
        "double" => SampleType::F64,
        other => return Err(malformed(path, format!("`type: {other}` is not supported"))),
    };
    let compression = match need("encoding")? {
        "raw" => Compression::None,
        "gzip" | "gz" => Compression::Gzip,
        other => return Err(malformed(path, format!("`encoding: {other}` is not supported (raw, gzip)"))),
    };
    let big_endian = get("endian") == Some("big");
    let (mut direction, mut spacing) = (Matrix3::identity(), [1.0; 3]);
    if let Some(dirs) = get("space directions") {
        let cols: Vec<&str> = dirs.split_whitespace().collect();
        if cols.len() != 3 {
            return Err(malformed(path, format!("`space directions`: expected 3 vectors, got `{dirs}`")));
        }
        for (a, c) in cols.iter().enumerate() {
            let v = parse_vector(path, "space directions", c)?;
            spacing[a] = v.norm();
            direction.set_column(a, &(v / spacing[a].max(f64::MIN_POSITIVE)));
        }
    } else if let Some(sp) = get("spacings") {
        for (a, s) in sp.split_whitespace().take(3).enumerate() {
            spacing[a] = s.parse().map_err(|_| malformed(path, format!("`spacings`: bad value `{s}`")))?;
        }
    }
    let mut origin = match get("space origin") {
        Some(o) => parse_vector(path, "space origin", o)?,
        None => Vector3::zeros(),
    };
    if let Some(space) = get("space") {
        let flip = match space {
            "left-posterior-superior" | "LPS" => false,
            "right-anterior-superior" | "RAS" => true,
            other => return Err(malformed(path, format!("`space: {other}` is not supported (LPS, RAS)"))),
        };
        if flip {
            for r in 0..2 {
                origin[r] = -origin[r];
                for c in 0..3 {
                    direction[(r, c)] = -direction[(r, c)];
                }
            }
        }
    }
    let payload = match get("data file").or(get("datafile")) {
        Some(file) => {
            let data_path = path.parent().unwrap_or(Path::new(".")).join(file);
            std::fs::read(&data_path).map_err(io_error(&data_path))?
        }
        None => bytes
            [header_end.ok_or_else(|| malformed(path, "header never ends (no blank line)"))?.min(bytes.len())..]
            .to_vec(),
    };
    let count = nx * ny * nz;
    let raw = decompress(path, &payload, compression, count * sample.size())?;
    let data = sample.decode(&raw, big_endian);
    Ok(Volume::new([nx, ny, nz], spacing, origin.into(), direction, data, &path.display().to_string())?)
}

pub(super) fn write(path: &Path, volume: &Volume) -> Result<(), IoError> {
    let [nx, ny, nz] = volume.dims();
    let d = volume.direction();
    let sp = volume.spacing();
    let o = volume.origin();
    let dir = |a: usize| format!("({},{},{})", d[(0, a)] * sp[a], d[(1, a)] * sp[a], d[(2, a)] * sp[a]);
    let header = format!(
        "NRRD0004\n# written by defvol\ntype: float\ndimension: 3\nspace: left-posterior-superior\nsizes: {nx} {ny} {nz}\n\
         space directions: {} {} {}\nkinds: domain domain domain\nendian: little\nencoding: gzip\nspace origin: ({},{},{})\n\n",
        dir(0),
        dir(1),
        dir(2),
        o[0],
        o[1],
        o[2]
    );
    let file = std::fs::File::create(path).map_err(io_error(path))?;
    let mut w = std::io::BufWriter::new(file);
    w.write_all(header.as_bytes()).map_err(io_error(path))?;
    let mut gz = flate2::write::GzEncoder::new(w, flate2::Compression::fast());
    gz.write_all(bytemuck::cast_slice(volume.data())).map_err(io_error(path))?;
    gz.finish().and_then(|mut w| w.flush()).map_err(io_error(path))
}
