//! NRRD (`.nrrd` attached, `.nhdr` detached), as ITK, 3D Slicer and pynrrd write 2D and 3D
//! scalar volumes: raw, gzip or ascii encodings; `byte skip` (-1: the data end the file)
//! and `line skip`; one data file, a `LIST` of slice files or a `%d` pattern; every `space`
//! ITK reads, placed where ITK places it (RAS and LAS turned as ITK's reader turns them;
//! other spaces taken as they are).
//! Written as NRRD0004, f32, gzip, in LPS space.

use std::io::Write;
use std::path::Path;

use nalgebra::{Matrix3, Vector3};

use super::error::{malformed, IoError};
use super::raw::{decompress, pattern_files, sample_bytes, Compression, Fields, SampleType};
use crate::volume::Volume;

fn parse_vector(path: &Path, field: &str, text: &str) -> Result<Vector3<f64>, IoError> {
    let v: Vec<f64> = text
        .trim()
        .trim_start_matches('(')
        .trim_end_matches(')')
        .split(',')
        .map(|c| c.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| malformed(path, format!("`{field}`: expected (x,y,z) numbers")))?;
    match v[..] {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok(Vector3::new(x, y, z)),
        _ => Err(malformed(path, format!("`{field}`: expected 3 finite components, got {}", v.len()))),
    }
}

fn sample_type(path: &Path, name: &str) -> Result<SampleType, IoError> {
    Ok(match name {
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => SampleType::U8,
        "signed char" | "int8" | "int8_t" => SampleType::I8,
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => SampleType::U16,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => SampleType::I16,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => SampleType::U32,
        "int" | "signed int" | "int32" | "int32_t" => SampleType::I32,
        "ulonglong" | "unsigned long long" | "unsigned long long int" | "uint64" | "uint64_t" => SampleType::U64,
        "longlong"
        | "long long"
        | "long long int"
        | "signed long long"
        | "signed long long int"
        | "int64"
        | "int64_t" => SampleType::I64,
        "float" => SampleType::F32,
        "double" => SampleType::F64,
        _ => {
            return Err(malformed(
                path,
                "this `type` is not supported (signed and unsigned 8 to 64-bit integers, float, double)",
            ))
        }
    })
}

/// The header fields and where the attached data start (`None` for a detached header);
/// `LIST` data files follow the header lines.
fn header(path: &Path, bytes: &[u8]) -> Result<(Fields, Option<usize>, Vec<String>), IoError> {
    if !bytes.starts_with(b"NRRD000") {
        return Err(malformed(path, "missing the NRRD000x magic line"));
    }
    let mut fields = Fields::new();
    let mut list = Vec::new();
    let mut in_list = false;
    let mut position = 0;
    for line in bytes.split(|b| *b == b'\n') {
        position += line.len() + 1;
        let text = String::from_utf8_lossy(line).trim_end_matches('\r').to_owned();
        if text.is_empty() {
            return Ok((fields, Some(position.min(bytes.len())), list));
        }
        if in_list {
            list.push(text.trim().to_owned());
            continue;
        }
        if text.starts_with('#') || text.starts_with("NRRD") || text.contains(":=") {
            continue;
        }
        let Some((key, value)) = text.split_once(": ") else {
            return Err(malformed(
                path,
                format!("header line `{}` is not `field: value`", text.chars().take(60).collect::<String>()),
            ));
        };
        fields.insert(key, value);
        if (key.eq_ignore_ascii_case("data file") || key.eq_ignore_ascii_case("datafile"))
            && value.trim().starts_with("LIST")
        {
            in_list = true;
        }
    }
    Ok((fields, None, list))
}

pub(super) fn parse(path: &Path, bytes: &[u8], sidecar: &dyn Fn(&str) -> Option<Vec<u8>>) -> Result<Volume, IoError> {
    let (fields, attached_at, list) = header(path, bytes)?;
    let need = |k: &str| fields.get(k).ok_or_else(|| malformed(path, format!("header has no `{k}` field")));
    let dimension: usize = need("dimension")?.parse().map_err(|_| malformed(path, "`dimension` is not an integer"))?;
    let sizes: Vec<usize> = need("sizes")?
        .split_whitespace()
        .map(str::parse)
        .collect::<Result<_, _>>()
        .map_err(|_| malformed(path, "`sizes`: expected integers"))?;
    if sizes.len() != dimension {
        return Err(malformed(path, format!("`sizes` has {} values for dimension {dimension}", sizes.len())));
    }
    let dims = match sizes[..] {
        [nx, ny] => [nx, ny, 1],
        [nx, ny, nz] => [nx, ny, nz],
        _ => return Err(IoError::Unrepresentable { path: path.to_owned(), message: format!("dimension {dimension} (sizes {sizes:?}): only 2D and 3D scalar volumes, not a 4D volume or a vector image") }),
    };
    let sample = sample_type(path, need("type")?)?;
    let big_endian = fields.get("endian") == Some("big");
    let spatial = dimension.min(3);
    let (mut direction, mut spacing) = (Matrix3::identity(), [1.0; 3]);
    if let Some(dirs) = fields.get("space directions") {
        let cols: Vec<&str> = dirs.split_whitespace().collect();
        if cols.len() != spatial {
            return Err(malformed(path, format!("`space directions`: expected {spatial} vectors, got `{dirs}`")));
        }
        for (a, c) in cols.iter().enumerate() {
            if *c == "none" {
                return Err(IoError::Unrepresentable {
                    path: path.to_owned(),
                    message: format!("axis {a} is not spatial (`none` in `space directions`)"),
                });
            }
            let v = parse_vector(path, "space directions", c)?;
            spacing[a] = v.norm();
            direction.set_column(a, &(v / spacing[a].max(f64::MIN_POSITIVE)));
        }
    } else if let Some(sp) = fields.get("spacings") {
        for (a, s) in sp.split_whitespace().take(3).enumerate() {
            spacing[a] = s.parse().map_err(|_| malformed(path, format!("`spacings`: bad value `{s}`")))?;
        }
    }
    let mut origin = match fields.get("space origin") {
        Some(o) => parse_vector(path, "space origin", o)?,
        None => Vector3::zeros(),
    };
    // As ITK reads them (its reference for where voxels are): RAS negating x and y, LAS
    // negating x (so ITK's NRRD reader does), other spaces as they are.
    let flips: [f64; 3] = match fields.get("space").map(str::to_ascii_lowercase).as_deref() {
        Some("right-anterior-superior" | "ras") => [-1.0, -1.0, 1.0],
        Some("left-anterior-superior" | "las") => [-1.0, 1.0, 1.0],
        Some(
            "left-posterior-superior"
            | "lps"
            | "scanner-xyz"
            | "3d-right-handed"
            | "3d-left-handed"
            | "right-anterior-superior-time"
            | "left-anterior-superior-time"
            | "left-posterior-superior-time",
        )
        | None => [1.0; 3],
        Some(_) => return Err(malformed(path, "this `space` is not one ITK reads (a 3D RAS/LAS/LPS name, or none)")),
    };
    for r in 0..3 {
        origin[r] *= flips[r];
        for c in 0..3 {
            direction[(r, c)] *= flips[r];
        }
    }
    let expected = sample_bytes(path, dims, sample)?;
    let encoding = need("encoding")?;
    let compression = match encoding {
        "raw" => Some(Compression::None),
        "gzip" | "gz" => Some(Compression::Gzip),
        "ascii" | "text" | "txt" => None,
        _ => return Err(malformed(path, "this `encoding` is not supported (raw, gzip, ascii)")),
    };
    let data_file = fields.get("data file").or(fields.get("datafile"));
    let files: Vec<String> = match data_file {
        None => Vec::new(),
        Some(spec) if spec.starts_with("LIST") => list,
        Some(spec) if spec.contains('%') => pattern_files(path, spec, dims[2].max(1))?,
        Some(name) => vec![name.to_owned()],
    };
    let payload = if files.is_empty() {
        let start =
            attached_at.ok_or_else(|| malformed(path, "a detached header (no blank line) names no data file"))?;
        bytes[start..].to_vec()
    } else {
        let mut joined = Vec::new();
        for name in &files {
            let data = sidecar(name).ok_or_else(|| malformed(path, format!("data file `{name}` cannot be read")))?;
            if joined.len().saturating_add(data.len()) > super::error::MAX_DECODED_BYTES {
                return Err(malformed(path, "the data files hold more than a volume here can"));
            }
            joined.extend_from_slice(&data);
        }
        joined
    };
    let payload = skip(path, &fields, payload, expected, compression == Some(Compression::None))?;
    let data = match compression {
        Some(compression) => sample.decode(&decompress(path, &payload, compression, expected)?, big_endian),
        None => {
            let count = expected / sample.size();
            let text = String::from_utf8_lossy(&payload);
            let values: Vec<f32> = text
                .split_ascii_whitespace()
                .take(count)
                .map(|w| {
                    w.parse::<f32>().map_err(|_| {
                        malformed(path, format!("`{}` is not a number", w.chars().take(20).collect::<String>()))
                    })
                })
                .collect::<Result<_, _>>()?;
            if values.len() != count {
                return Err(malformed(path, format!("{} values for {count} samples", values.len())));
            }
            values
        }
    };
    Ok(Volume::new(dims, spacing, origin.into(), direction, data, &path.display().to_string())?)
}

/// `line skip` lines, then `byte skip` bytes (-1: the data are the payload's last bytes).
fn skip(path: &Path, fields: &Fields, mut payload: Vec<u8>, expected: usize, raw: bool) -> Result<Vec<u8>, IoError> {
    if let Some(lines) = fields.get("line skip").or(fields.get("lineskip")) {
        let lines: usize = lines.parse().map_err(|_| malformed(path, "`line skip` is not a count"))?;
        let mut at = 0;
        for _ in 0..lines {
            let next = payload[at..]
                .iter()
                .position(|b| *b == b'\n')
                .ok_or_else(|| malformed(path, format!("`line skip` {lines} skips past the data")))?;
            at += next + 1;
        }
        payload.drain(..at);
    }
    if let Some(bytes) = fields.get("byte skip").or(fields.get("byteskip")) {
        let skip: i64 =
            bytes.parse().map_err(|_| malformed(path, format!("`byte skip: {bytes}` is not an integer")))?;
        let at = match skip {
            -1 if raw => payload.len().checked_sub(expected).ok_or_else(|| {
                malformed(path, format!("`byte skip: -1` but the data hold {} bytes of {expected}", payload.len()))
            })?,
            -1 => return Err(malformed(path, "`byte skip: -1` is for raw data only")),
            n if n >= 0 => usize::try_from(n).map_err(|_| malformed(path, "`byte skip` is too large"))?,
            n => return Err(malformed(path, format!("`byte skip: {n}` is negative"))),
        };
        if at > payload.len() {
            return Err(malformed(path, format!("`byte skip: {at}` skips past the {} bytes of data", payload.len())));
        }
        payload.drain(..at);
    }
    Ok(payload)
}

/// The volume as attached NRRD0004 bytes (f32, gzip, LPS).
pub(super) fn encode(volume: &Volume) -> Result<Vec<u8>, IoError> {
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
    let mut gz = flate2::write::GzEncoder::new(header.into_bytes(), flate2::Compression::fast());
    gz.write_all(bytemuck::cast_slice(volume.data())).map_err(|e| malformed(Path::new("nrrd"), e.to_string()))?;
    gz.finish().map_err(|e| malformed(Path::new("nrrd"), e.to_string()))
}
