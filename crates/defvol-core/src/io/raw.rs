//! What NRRD and MetaImage share: raw sample types, their sizes checked against the bytes
//! there, compression, `key: value` header fields and numbered data-file patterns.

use std::collections::BTreeMap;
use std::path::Path;

use super::error::{malformed, IoError, MAX_DECODED_BYTES};

/// Sample element types found in volume files; all become f32.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum SampleType {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F32,
    F64,
}

impl SampleType {
    pub(crate) fn size(self) -> usize {
        match self {
            SampleType::U8 | SampleType::I8 => 1,
            SampleType::U16 | SampleType::I16 => 2,
            SampleType::U32 | SampleType::I32 | SampleType::F32 => 4,
            SampleType::U64 | SampleType::I64 | SampleType::F64 => 8,
        }
    }

    /// Decodes raw bytes (little- or big-endian) into f32 samples.
    pub(crate) fn decode(self, bytes: &[u8], big_endian: bool) -> Vec<f32> {
        let n = self.size();
        bytes
            .chunks_exact(n)
            .map(|c| {
                let mut b = [0u8; 8];
                b[..n].copy_from_slice(c);
                if big_endian {
                    b[..n].reverse();
                }
                match self {
                    SampleType::U8 => f32::from(b[0]),
                    SampleType::I8 => f32::from(b[0] as i8),
                    SampleType::U16 => f32::from(u16::from_le_bytes([b[0], b[1]])),
                    SampleType::I16 => f32::from(i16::from_le_bytes([b[0], b[1]])),
                    SampleType::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
                    SampleType::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
                    SampleType::U64 => u64::from_le_bytes(b) as f32,
                    SampleType::I64 => i64::from_le_bytes(b) as f32,
                    SampleType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                    SampleType::F64 => f64::from_le_bytes(b) as f32,
                }
            })
            .collect()
    }
}

/// The bytes `dims` samples of `sample` take, checked (overflow, and the decoding limit).
pub(crate) fn sample_bytes(path: &Path, dims: [usize; 3], sample: SampleType) -> Result<usize, IoError> {
    let bytes = dims.iter().try_fold(sample.size(), |acc, d| acc.checked_mul(*d));
    match bytes {
        Some(b) if b <= MAX_DECODED_BYTES => Ok(b),
        _ => Err(malformed(
            path,
            format!("dims {dims:?} of {} bytes each: more data than a volume file can hold here", sample.size()),
        )),
    }
}

/// The samples from a payload: compressed streams are read up to `expected` bytes, never
/// grown into beyond; too few bytes is an error naming how many there were.
pub(crate) fn decompress(
    path: &Path,
    payload: &[u8],
    compression: Compression,
    expected: usize,
) -> Result<Vec<u8>, IoError> {
    use std::io::Read;
    let limit = expected as u64;
    let mut out = Vec::new();
    let result = match compression {
        Compression::None => {
            out.extend_from_slice(&payload[..payload.len().min(expected)]);
            Ok(())
        }
        Compression::Gzip => flate2::read::MultiGzDecoder::new(payload).take(limit).read_to_end(&mut out).map(|_| ()),
        Compression::Zlib => flate2::read::ZlibDecoder::new(payload).take(limit).read_to_end(&mut out).map(|_| ()),
    };
    result.map_err(|e| malformed(path, format!("cannot decompress the sample data: {e}")))?;
    if out.len() < expected {
        return Err(malformed(path, format!("sample data holds {} bytes, {} needed", out.len(), expected)));
    }
    Ok(out)
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Compression {
    None,
    Gzip,
    Zlib,
}

/// Header text as `Key = Value` or `key: value` lines: the value of a key, any case.
pub(crate) struct Fields(BTreeMap<String, String>);

impl Fields {
    pub(crate) fn get(&self, key: &str) -> Option<&str> {
        self.0.get(&key.to_ascii_lowercase()).map(String::as_str)
    }

    pub(crate) fn insert(&mut self, key: &str, value: &str) {
        self.0.insert(key.trim().to_ascii_lowercase(), value.trim().to_owned());
    }

    pub(crate) fn new() -> Self {
        Self(BTreeMap::new())
    }
}

/// Samples named by pattern (`name%03d.raw 1 10 1`, as MetaImage and NRRD detached headers
/// give per-slice files): the file names, checked for count.
pub(crate) fn pattern_files(path: &Path, spec: &str, max_files: usize) -> Result<Vec<String>, IoError> {
    let words: Vec<&str> = spec.split_whitespace().collect();
    let [format, min, max, step, ..] = words[..] else {
        return Err(malformed(path, format!("data file pattern `{spec}`: expected `format min max step`")));
    };
    let parse = |w: &str| {
        w.parse::<i32>()
            .map(i128::from)
            .map_err(|_| malformed(path, format!("data file pattern `{spec}`: `{w}` is not an integer")))
    };
    let (min, max, step) = (parse(min)?, parse(max)?, parse(step)?);
    if step == 0 || (max - min).signum() * step.signum() < 0 {
        return Err(malformed(path, format!("data file pattern `{spec}`: step {step} never reaches {max} from {min}")));
    }
    let count = ((max - min) / step + 1).unsigned_abs() as usize;
    if count > max_files {
        return Err(malformed(path, format!("data file pattern `{spec}`: {count} files for {max_files} slices")));
    }
    let Some(percent) = format.find('%') else {
        return Err(malformed(path, format!("data file pattern `{spec}`: no %d in `{format}`")));
    };
    let Some(d) = format[percent..].find('d') else {
        return Err(malformed(path, format!("data file pattern `{spec}`: no %d in `{format}`")));
    };
    let width: usize = format[percent + 1..percent + d].trim_start_matches('0').parse().unwrap_or(0);
    let zero = format[percent + 1..percent + d].starts_with('0');
    Ok((0..count as i128)
        .map(|k| {
            let n = min + k * step;
            let number = if zero { format!("{n:0width$}") } else { format!("{n:width$}") };
            format!("{}{number}{}", &format[..percent], &format[percent + d + 1..])
        })
        .collect())
}
