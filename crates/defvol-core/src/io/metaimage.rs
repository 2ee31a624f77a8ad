//! MetaImage (`.mha` with inline data, `.mhd` + data files), ITK's own format, 2D and 3D:
//! `TransformMatrix` lists the direction column by column, as ITK writes it; compressed data
//! are one zlib stream of `CompressedDataSize` bytes; `HeaderSize` bytes are skipped (-1: the
//! data end the file); `ElementDataFile` is `LOCAL`, a file, a `LIST` of slice files or a
//! `%d` pattern. Written with `CompressedDataSize`, as ITK needs to read compressed data.

use std::io::Write;
use std::path::Path;

use nalgebra::Matrix3;

use super::error::{malformed, IoError};
use super::raw::{decompress, pattern_files, sample_bytes, Compression, Fields, SampleType};
use crate::volume::Volume;

fn numbers(path: &Path, fields: &Fields, key: &str, n: usize) -> Result<Option<Vec<f64>>, IoError> {
    let Some(text) = fields.get(key) else { return Ok(None) };
    let v: Vec<f64> = text
        .split_whitespace()
        .map(str::parse)
        .collect::<Result<_, _>>()
        .map_err(|_| malformed(path, format!("`{key}`: expected {n} numbers")))?;
    if v.len() != n {
        return Err(malformed(path, format!("`{key}`: expected {n} values, got {}", v.len())));
    }
    Ok(Some(v))
}

/// The header fields, where the header ends, and the `LIST` file names after it.
fn header(path: &Path, bytes: &[u8]) -> Result<(Fields, usize, Vec<String>), IoError> {
    let mut fields = Fields::new();
    let mut position = 0;
    let mut lines = bytes.split(|b| *b == b'\n');
    for line in lines.by_ref() {
        position += line.len() + 1;
        let text = String::from_utf8_lossy(line).trim().to_owned();
        if text.is_empty() {
            continue;
        }
        let Some((key, value)) = text.split_once('=') else {
            return Err(malformed(
                path,
                format!("header line `{}` is not `Key = Value`", text.chars().take(60).collect::<String>()),
            ));
        };
        fields.insert(key, value);
        if key.trim().eq_ignore_ascii_case("ElementDataFile") {
            let mut list = Vec::new();
            if value.trim().starts_with("LIST") {
                for line in lines.by_ref() {
                    let name = String::from_utf8_lossy(line).trim().to_owned();
                    if !name.is_empty() {
                        list.push(name);
                    }
                }
            }
            return Ok((fields, position.min(bytes.len()), list));
        }
    }
    Err(malformed(path, "header has no ElementDataFile"))
}

pub(super) fn parse(path: &Path, bytes: &[u8], sidecar: &dyn Fn(&str) -> Option<Vec<u8>>) -> Result<Volume, IoError> {
    let (fields, data_start, list) = header(path, bytes)?;
    let ndims = fields.get("ndims").unwrap_or("missing");
    let rank = match ndims {
        "2" => 2,
        "3" => 3,
        _ => {
            return Err(IoError::Unrepresentable {
                path: path.to_owned(),
                message: format!("NDims = {ndims}: only 2D and 3D volumes, not a 4D volume"),
            })
        }
    };
    let pad = |v: Vec<f64>, fill: f64| -> [f64; 3] { [v[0], v[1], if rank == 3 { v[2] } else { fill }] };
    let Some(dims) = numbers(path, &fields, "DimSize", rank)? else {
        return Err(malformed(path, "header has no DimSize"));
    };
    if dims.iter().any(|d| !(d.fract() == 0.0 && *d >= 1.0 && *d < 1e12)) {
        return Err(malformed(path, format!("DimSize {dims:?}: not positive integers")));
    }
    let dims = pad(dims, 1.0).map(|d| d as usize);
    let spacing = match numbers(path, &fields, "ElementSpacing", rank)? {
        Some(v) => pad(v, 1.0),
        None => numbers(path, &fields, "ElementSize", rank)?.map_or([1.0; 3], |v| pad(v, 1.0)),
    };
    let origin = match numbers(path, &fields, "Offset", rank)?
        .or(numbers(path, &fields, "Origin", rank)?)
        .or(numbers(path, &fields, "Position", rank)?)
    {
        Some(v) => pad(v, 0.0),
        None => [0.0; 3],
    };
    let matrix = numbers(path, &fields, "TransformMatrix", rank * rank)?
        .or(numbers(path, &fields, "Rotation", rank * rank)?)
        .or(numbers(path, &fields, "Orientation", rank * rank)?);
    let direction = match matrix {
        Some(m) if rank == 3 => Matrix3::from_column_slice(&m),
        Some(m) => Matrix3::new(m[0], m[2], 0.0, m[1], m[3], 0.0, 0.0, 0.0, 1.0),
        None => Matrix3::identity(),
    };
    if fields.get("elementnumberofchannels").is_some_and(|c| c != "1") {
        return Err(IoError::Unrepresentable {
            path: path.to_owned(),
            message: "more than one channel per voxel (a vector image)".into(),
        });
    }
    let sample = match fields.get("elementtype") {
        Some("MET_UCHAR") => SampleType::U8,
        Some("MET_CHAR") => SampleType::I8,
        Some("MET_USHORT") => SampleType::U16,
        Some("MET_SHORT") => SampleType::I16,
        Some("MET_UINT") => SampleType::U32,
        Some("MET_INT") => SampleType::I32,
        Some("MET_ULONG_LONG") => SampleType::U64,
        Some("MET_LONG_LONG") => SampleType::I64,
        Some("MET_FLOAT") => SampleType::F32,
        Some("MET_DOUBLE") => SampleType::F64,
        other => return Err(malformed(path, format!("ElementType {}: not supported", other.unwrap_or("missing")))),
    };
    let yes = |key: &str| fields.get(key).is_some_and(|v| v.eq_ignore_ascii_case("true"));
    let big_endian = yes("BinaryDataByteOrderMSB") || yes("ElementByteOrderMSB");
    let compressed = yes("CompressedData");
    let expected = sample_bytes(path, dims, sample)?;
    let data_file = fields.get("elementdatafile").unwrap_or("LOCAL");
    let mut payload = if data_file == "LOCAL" {
        bytes[data_start..].to_vec()
    } else {
        let names = if data_file.starts_with("LIST") {
            list
        } else if data_file.contains('%') {
            pattern_files(path, data_file, dims[2])?
        } else {
            vec![data_file.to_owned()]
        };
        let mut joined = Vec::new();
        for name in &names {
            let data = sidecar(name).ok_or_else(|| malformed(path, format!("data file `{name}` cannot be read")))?;
            if joined.len().saturating_add(data.len()) > super::error::MAX_DECODED_BYTES {
                return Err(malformed(path, "the data files hold more than a volume here can"));
            }
            joined.extend_from_slice(&data);
        }
        joined
    };
    if let Some(skip) = fields.get("headersize") {
        let skip: i64 = skip.parse().map_err(|_| malformed(path, format!("HeaderSize = {skip} is not an integer")))?;
        let at = match skip {
            -1 if !compressed => payload.len().checked_sub(expected).ok_or_else(|| {
                malformed(path, format!("HeaderSize = -1 but the data hold {} bytes of {expected}", payload.len()))
            })?,
            -1 => return Err(malformed(path, "HeaderSize = -1 is for uncompressed data only")),
            n => usize::try_from(n).ok().filter(|n| *n <= payload.len()).ok_or_else(|| {
                malformed(path, format!("HeaderSize = {n} is outside the {} bytes of data", payload.len()))
            })?,
        };
        payload.drain(..at);
    }
    if compressed {
        if let Some(size) = fields.get("compresseddatasize") {
            let size: usize =
                size.parse().map_err(|_| malformed(path, format!("CompressedDataSize = {size} is not a count")))?;
            if size > payload.len() {
                return Err(malformed(
                    path,
                    format!("CompressedDataSize = {size}, but {} bytes follow", payload.len()),
                ));
            }
            payload.truncate(size);
        }
    }
    let raw = decompress(path, &payload, if compressed { Compression::Zlib } else { Compression::None }, expected)?;
    Ok(Volume::new(dims, spacing, origin, direction, sample.decode(&raw, big_endian), &path.display().to_string())?)
}

/// The header for `volume`, its data `CompressedDataSize` bytes in `data_file`.
fn header_text(volume: &Volume, data_file: &str, compressed_size: usize) -> String {
    let [nx, ny, nz] = volume.dims();
    let sp = volume.spacing();
    let o = volume.origin();
    let m: Vec<String> = volume.direction().as_slice().iter().map(|v| v.to_string()).collect();
    format!(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\nCompressedData = True\nCompressedDataSize = {compressed_size}\n\
         TransformMatrix = {}\nOffset = {} {} {}\nCenterOfRotation = 0 0 0\nElementSpacing = {} {} {}\n\
         DimSize = {nx} {ny} {nz}\nElementType = MET_FLOAT\nElementDataFile = {data_file}\n",
        m.join(" "),
        o[0],
        o[1],
        o[2],
        sp[0],
        sp[1],
        sp[2]
    )
}

pub(super) fn write(path: &Path, volume: &Volume) -> Result<(), IoError> {
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
    z.write_all(bytemuck::cast_slice(volume.data())).map_err(super::error::io_error(path))?;
    let compressed = z.finish().map_err(super::error::io_error(path))?;
    if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("mha")) {
        let mut bytes = header_text(volume, "LOCAL", compressed.len()).into_bytes();
        bytes.extend_from_slice(&compressed);
        return super::files::write_atomically(path, &bytes);
    }
    // `.mhd`: the data file beside it, named after it, written first.
    let data_path = path.with_extension("zraw");
    let data_name = data_path.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    super::files::write_atomically(&data_path, &compressed)?;
    super::files::write_atomically(path, header_text(volume, &data_name, compressed.len()).as_bytes())
}
