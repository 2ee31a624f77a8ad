//! A walk over a DICOM file's element headers before dicom-rs parses it: every declared
//! length must fit in the bytes that follow it, and sequences nest at most `MAX_DEPTH`
//! deep. dicom-rs allocates (and zeroes) what a length declares before it reads, so a
//! damaged length would cost gigabytes before the error.

/// Undefined length: a sequence or item read up to its delimiter.
const UNDEFINED: u32 = 0xFFFF_FFFF;
const MAX_DEPTH: usize = 32;
/// Explicit VRs with a 2-byte length (PS3.5 7.1.2); every other, an unknown one too (read
/// as UN, as dicom-rs reads it), has two reserved bytes and a 4-byte length.
const SHORT_VRS: [&[u8; 2]; 21] = [
    b"AE", b"AS", b"AT", b"CS", b"DA", b"DS", b"DT", b"FL", b"FD", b"IS", b"LO", b"LT", b"PN", b"SH", b"SL", b"SS",
    b"ST", b"TM", b"UI", b"UL", b"US",
];
const DEFLATED: &str = "1.2.840.10008.1.2.1.99";
const IMPLICIT_LE: &str = "1.2.840.10008.1.2";
const EXPLICIT_BE: &str = "1.2.840.10008.1.2.2";

/// How a data set's element headers are encoded.
#[derive(Clone, Copy)]
struct Encoding {
    explicit: bool,
    big_endian: bool,
}

/// Checks every element length of a DICOM file (its preamble optional); why not, else.
/// A deflated data set is checked up to its meta group (the rest is compressed).
pub(super) fn check_lengths(bytes: &[u8]) -> Result<(), String> {
    let start = if bytes.len() >= 132 && &bytes[128..132] == b"DICM" {
        132
    } else if bytes.starts_with(b"DICM") {
        4
    } else {
        0
    };
    let meta = Encoding { explicit: true, big_endian: false };
    let mut walk = Walk { bytes, syntax: None };
    let after_meta = walk.elements(start, bytes.len(), meta, 0, true)?;
    let data = match walk.syntax.as_deref() {
        Some(DEFLATED) => return Ok(()),
        Some(IMPLICIT_LE) => Encoding { explicit: false, big_endian: false },
        Some(EXPLICIT_BE) => Encoding { explicit: true, big_endian: true },
        _ => meta,
    };
    walk.elements(after_meta, bytes.len(), data, 0, false).map(|_| ())
}

struct Walk<'a> {
    bytes: &'a [u8],
    /// The transfer syntax the meta group names.
    syntax: Option<String>,
}

/// What the items of a container hold: data elements (a sequence) or raw bytes
/// (encapsulated pixel data's fragments).
#[derive(Clone, Copy, PartialEq)]
enum Items {
    Elements,
    Fragments,
}

const PIXEL_DATA: (u16, u16) = (0x7FE0, 0x0010);

impl Walk<'_> {
    fn u16_at(&self, at: usize, e: Encoding) -> Result<u16, String> {
        let b: [u8; 2] = self.bytes.get(at..at + 2).and_then(|s| s.try_into().ok()).ok_or("cut inside a header")?;
        Ok(if e.big_endian { u16::from_be_bytes(b) } else { u16::from_le_bytes(b) })
    }

    fn u32_at(&self, at: usize, e: Encoding) -> Result<u32, String> {
        let b: [u8; 4] = self.bytes.get(at..at + 4).and_then(|s| s.try_into().ok()).ok_or("cut inside a header")?;
        Ok(if e.big_endian { u32::from_be_bytes(b) } else { u32::from_le_bytes(b) })
    }

    /// The elements (or items holding `items`) from `at` to `end`, or to a delimiter;
    /// where they end. `meta`: only group 2, the file meta group, noting its syntax.
    fn elements(&mut self, mut at: usize, end: usize, e: Encoding, depth: usize, meta: bool) -> Result<usize, String> {
        self.walk(&mut at, end, e, depth, meta, Items::Elements)?;
        Ok(at)
    }

    fn walk(
        &mut self,
        at: &mut usize,
        end: usize,
        e: Encoding,
        depth: usize,
        meta: bool,
        items: Items,
    ) -> Result<(), String> {
        if depth > MAX_DEPTH {
            return Err(format!("sequences nested over {MAX_DEPTH} deep"));
        }
        while *at + 8 <= end {
            let tag = (self.u16_at(*at, e)?, self.u16_at(*at + 2, e)?);
            if meta && tag.0 != 2 {
                return Ok(());
            }
            if tag.0 == 0xFFFE {
                let length = self.u32_at(*at + 4, e)?;
                *at += 8;
                match tag.1 {
                    0xE00D | 0xE0DD => return Ok(()),
                    _ => {
                        *at =
                            self.contents(*at, end, length, tag, e, depth, items == Items::Elements, Items::Elements)?
                    }
                }
                continue;
            }
            let vr = self.bytes.get(*at + 4..*at + 6).unwrap_or_default();
            let (length, header) = match e.explicit {
                true if SHORT_VRS.iter().any(|short| short.as_slice() == vr) => {
                    (u32::from(self.u16_at(*at + 6, e)?), 8)
                }
                true => (self.u32_at(*at + 8, e)?, 12),
                false => (self.u32_at(*at + 4, e)?, 8),
            };
            *at += header;
            if meta && tag.1 == 0x0010 && length != UNDEFINED {
                let value = self.bytes.get(*at..*at + length as usize).ok_or("cut inside the meta group")?;
                self.syntax = Some(String::from_utf8_lossy(value).trim_end_matches(['\0', ' ']).to_owned());
            }
            let inner = if tag == PIXEL_DATA { Items::Fragments } else { Items::Elements };
            *at = self.contents(*at, end, length, tag, e, depth, e.explicit && vr == b"SQ", inner)?;
        }
        Ok(())
    }

    /// Past one value of `length` at `at`: a container (undefined length, or `nested`)
    /// walked for its items, a defined length checked against the bytes left.
    #[allow(clippy::too_many_arguments)]
    fn contents(
        &mut self,
        at: usize,
        end: usize,
        length: u32,
        tag: (u16, u16),
        e: Encoding,
        depth: usize,
        nested: bool,
        items: Items,
    ) -> Result<usize, String> {
        let mut inside = at;
        if length == UNDEFINED {
            self.walk(&mut inside, end, e, depth + 1, false, items)?;
            return Ok(inside);
        }
        let length = length as usize;
        let remain = end.saturating_sub(at);
        if length > remain {
            return Err(format!("element ({:04X},{:04X}) declares {length} bytes where {remain} remain", tag.0, tag.1));
        }
        if nested {
            self.walk(&mut inside, at + length, e, depth + 1, false, items)?;
        }
        Ok(at + length)
    }
}
