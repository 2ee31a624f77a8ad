//! MetaImage (`.mha` with inline data, `.mhd` + a data file), ITK's own format.
//! `TransformMatrix` lists the direction matrix column by column, as ITK writes it.

use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

use nalgebra::Matrix3;

use super::{decompress, io_error, malformed, Compression, IoError, SampleType};
use crate::volume::Volume;

fn numbers(path: &Path, fields: &HashMap<String, String>, key: &str, n: usize) -> Result<Option<Vec<f64>>, IoError> {
    let Some(text) = fields.get(&key.to_lowercase()) else { return Ok(None) };
    let v: Vec<f64> = text
        .split_whitespace()
        .map(str::parse)
        .collect::<Result<_, _>>()
        .map_err(|_| malformed(path, format!("`{key}`: expected numbers, got `{text}`")))?;
    if v.len() != n {
        return Err(malformed(path, format!("`{key}`: expected {n} values, got {}", v.len())));
    }
    Ok(Some(v))
}

pub(super) fn read(path: &Path) -> Result<Volume, IoError> {
    let bytes = std::fs::read(path).map_err(io_error(path))?;
    let mut fields: HashMap<String, String> = HashMap::new();
    let mut pos = 0;
    let mut data_start = None;
    for line in bytes.split(|b| *b == b'\n') {
        pos += line.len() + 1;
        let text = String::from_utf8_lossy(line).trim().to_owned();
        let Some((k, v)) = text.split_once('=') else {
            if text.is_empty() {
                continue;
            }
            return Err(malformed(
                path,
                format!("header line `{}` is not `Key = Value`", text.chars().take(60).collect::<String>()),
            ));
        };
        let key = k.trim().to_lowercase();
        fields.insert(key.clone(), v.trim().to_owned());
        if key == "elementdatafile" {
            data_start = Some(pos.min(bytes.len()));
            break;
        }
    }
    let get = |k: &str| fields.get(k).map(String::as_str);
    if get("ndims") != Some("3") {
        return Err(malformed(
            path,
            format!("NDims = {}: only 3D volumes are supported", get("ndims").unwrap_or("missing")),
        ));
    }
    let Some(dims) = numbers(path, &fields, "DimSize", 3)? else {
        return Err(malformed(path, "header has no DimSize"));
    };
    let dims = [dims[0] as usize, dims[1] as usize, dims[2] as usize];
    let spacing = numbers(path, &fields, "ElementSpacing", 3)?.map_or([1.0; 3], |v| [v[0], v[1], v[2]]);
    let origin = match numbers(path, &fields, "Offset", 3)? {
        Some(v) => [v[0], v[1], v[2]],
        None => numbers(path, &fields, "Origin", 3)?.map_or([0.0; 3], |v| [v[0], v[1], v[2]]),
    };
    let direction = match numbers(path, &fields, "TransformMatrix", 9)?.or(numbers(path, &fields, "Rotation", 9)?) {
        Some(m) => Matrix3::from_column_slice(&m),
        None => Matrix3::identity(),
    };
    if get("elementnumberofchannels").is_some_and(|c| c != "1") {
        return Err(malformed(path, "only single-channel images are supported"));
    }
    let sample = match get("elementtype") {
        Some("MET_UCHAR") => SampleType::U8,
        Some("MET_CHAR") => SampleType::I8,
        Some("MET_USHORT") => SampleType::U16,
        Some("MET_SHORT") => SampleType::I16,
        Some("MET_UINT") => SampleType::U32,
        Some("MET_INT") => SampleType::I32,
        Some("MET_FLOAT") => SampleType::F32,
        Some("MET_DOUBLE") => SampleType::F64,
        other => return Err(malformed(path, format!("ElementType {}: not supported", other.unwrap_or("missing")))),
    };
    let big_endian =
        get("binarydatabyteordermsb").or(get("elementbyteordermsb")).is_some_and(|v| v.eq_ignore_ascii_case("true"));
    let compressed = get("compresseddata").is_some_and(|v| v.eq_ignore_ascii_case("true"));
    let Some(data_file) = get("elementdatafile") else { return Err(malformed(path, "header has no ElementDataFile")) };
    let payload = if data_file == "LOCAL" {
        bytes[data_start.unwrap_or(bytes.len())..].to_vec()
    } else {
        let data_path = path.parent().unwrap_or(Path::new(".")).join(data_file);
        std::fs::read(&data_path).map_err(io_error(&data_path))?
    };
    let count = dims[0] * dims[1] * dims[2];
    let raw = decompress(
        path,
        &payload,
        if compressed { Compression::Zlib } else { Compression::None },
        count * sample.size(),
    )?;
    Ok(Volume::new(dims, spacing, origin, direction, sample.decode(&raw, big_endian), &path.display().to_string())?)
}

pub(super) fn write(path: &Path, volume: &Volume) -> Result<(), IoError> {
    let [nx, ny, nz] = volume.dims();
    let sp = volume.spacing();
    let o = volume.origin();
    let m: Vec<String> = volume.direction().as_slice().iter().map(|v| v.to_string()).collect();
    let inline = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("mha"));
    let data_name = path.with_extension("zraw");
    let data_file = if inline {
        "LOCAL".to_owned()
    } else {
        data_name.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned())
    };
    let header = format!(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\nCompressedData = True\n\
         TransformMatrix = {}\nOffset = {} {} {}\nElementSpacing = {} {} {}\nDimSize = {nx} {ny} {nz}\n\
         ElementType = MET_FLOAT\nElementDataFile = {data_file}\n",
        m.join(" "),
        o[0],
        o[1],
        o[2],
        sp[0],
        sp[1],
        sp[2]
    );
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
    z.write_all(bytemuck::cast_slice(volume.data())).map_err(io_error(path))?;
    let compressed = z.finish().map_err(io_error(path))?;
    if inline {
        let mut bytes = header.into_bytes();
        bytes.extend_from_slice(&compressed);
        std::fs::write(path, bytes).map_err(io_error(path))
    } else {
        std::fs::write(path, header).map_err(io_error(path))?;
        std::fs::write(&data_name, compressed).map_err(io_error(&data_name))
    }
}
