//! DICOM series as ITK's `ImageSeriesReader` reads them (GDCM's sorting): the slices of a
//! folder grouped by SeriesInstanceUID, sorted along the normal of ImageOrientationPatient
//! by ImagePositionPatient, values through RescaleSlope/Intercept, in ITK's LPS frame.
//!
//! Origin: the first sorted slice's position. Direction: the orientation's row and column
//! directions, then the unit step from the first slice to the second (ITK's rule). Spacing:
//! PixelSpacing, then the measured distance between positions (not SliceThickness). What
//! is not one regular volume (mixed orientations or sizes, a slice missing, uneven steps,
//! gantry tilt) is refused naming the files and the reason. Pixel data is decoded by
//! dicom-pixeldata's pure-Rust decoders: native little endian (explicit and implicit VR),
//! deflate, RLE, JPEG baseline and lossless; other transfer syntaxes are refused by name.
//!
//! A multi-frame file is a series in one file, each frame a slice: an enhanced one
//! (Enhanced CT/MR) places its frames by the per-frame functional groups' positions and
//! takes orientation, PixelSpacing and rescale from the shared ones (GDCM's rule); a
//! classic one steps its frames along the normal by SpacingBetweenSlices.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use dicom_dictionary_std::tags;
use dicom_object::mem::InMemElement;
use dicom_object::{DefaultDicomObject, InMemDicomObject, OpenFileOptions, Tag};
use dicom_pixeldata::{ConvertOptions, PixelDecoder};
use nalgebra::{Matrix3, Vector3};

use super::dicom_scan::check_lengths;
use super::error::{io_error, malformed, IoError, MAX_DECODED_BYTES};
use crate::volume::Volume;

/// Steps between slices may differ from the first by this fraction before a series is
/// refused as uneven (positions are printed to a few decimals).
const STEP_TOLERANCE: f64 = 1e-3;
/// The largest angle (as 1 - cos) between the slice step and the orientation's normal
/// before a series counts as tilted.
const TILT_TOLERANCE: f64 = 1e-4;
/// More frames than any one volume holds: a file declaring more is refused before its
/// frames are listed.
const MAX_FRAMES: usize = 1 << 16;

/// One series of a folder: its UID, description, files and slices (a multi-frame file
/// holds many).
#[derive(Debug, Clone, PartialEq)]
pub struct SeriesInfo {
    pub uid: String,
    pub description: String,
    pub files: usize,
    pub slices: usize,
}

/// A volume read from DICOM: the series read, the others the folder holds, and the files
/// skipped as not DICOM (with why).
#[derive(Debug)]
pub struct DicomRead {
    pub volume: Volume,
    /// The values' unit: RescaleType, or HU for a CT without one.
    pub units: Option<String>,
    pub series: SeriesInfo,
    pub others: Vec<SeriesInfo>,
    pub skipped: Vec<(PathBuf, String)>,
}

/// What a slice's header says, read before its pixel data: one a file, or one a frame of a
/// multi-frame file.
#[derive(Debug, Clone)]
struct Slice {
    path: PathBuf,
    /// Which frame of its file.
    frame: usize,
    uid: String,
    description: String,
    size: [usize; 2],
    frames: usize,
    row_dir: Vector3<f64>,
    col_dir: Vector3<f64>,
    position: Vector3<f64>,
    /// Between columns (x), then between rows (y): PixelSpacing reversed.
    pixel_spacing: [f64; 2],
    units: Option<String>,
    /// The pixel data's bytes as Columns x Rows x frames x BitsAllocated give them.
    pixel_bytes: u64,
    /// Whether the transfer syntax stores them uncompressed (the file must hold them all).
    native: bool,
    /// SpacingBetweenSlices, else SliceThickness: a lone slice's depth, as ITK takes it.
    thickness: Option<f64>,
}

impl Slice {
    fn normal(&self) -> Vector3<f64> {
        self.row_dir.cross(&self.col_dir)
    }

    /// The file, and the frame where the file holds several.
    fn name(&self) -> String {
        match self.frames {
            1 => self.path.display().to_string(),
            _ => format!("{} (frame {})", self.path.display(), self.frame + 1),
        }
    }
}

/// Reads the DICOM volume at `path` (a folder of slices, or one file): series `series` when
/// given, else the one with the most files.
pub fn read_dicom(path: &Path, series: Option<&str>) -> Result<DicomRead, IoError> {
    let files = if path.is_dir() { folder_files(path)? } else { vec![path.to_owned()] };
    let mut skipped = Vec::new();
    let mut by_series: BTreeMap<String, Vec<Slice>> = BTreeMap::new();
    for file in files {
        match read_header(&file) {
            Ok(frames) => by_series.entry(frames[0].uid.clone()).or_default().extend(frames),
            // A file that says it is DICOM and cannot be read is damaged, not a stray.
            Err(why) if has_dicom_mark(&file) => return Err(damaged(&file, why)),
            Err(why) => skipped.push((file, why)),
        }
    }
    let infos: Vec<SeriesInfo> = by_series
        .values()
        .map(|s| SeriesInfo {
            uid: s[0].uid.clone(),
            description: s[0].description.clone(),
            files: s.iter().filter(|slice| slice.frame == 0).count(),
            slices: s.len(),
        })
        .collect();
    let chosen = match series {
        Some(uid) => infos
            .iter()
            .find(|i| i.uid == uid)
            .cloned()
            .ok_or_else(|| malformed(path, format!("no series {uid}; it holds {}", list(&infos))))?,
        // The largest; of equal ones, the first by UID.
        None => {
            infos.iter().max_by(|a, b| a.slices.cmp(&b.slices).then(b.uid.cmp(&a.uid))).cloned().ok_or_else(|| {
                malformed(path, format!("no DICOM image among {} files ({})", skipped.len(), first_reason(&skipped)))
            })?
        }
    };
    let slices = by_series.remove(&chosen.uid).unwrap_or_default();
    let units = slices.first().and_then(|s| s.units.clone());
    if !skipped.is_empty() {
        tracing::warn!(
            "{}: {} files skipped, not DICOM images ({})",
            path.display(),
            skipped.len(),
            first_reason(&skipped)
        );
    }
    let others: Vec<SeriesInfo> = infos.into_iter().filter(|i| i.uid != chosen.uid).collect();
    if !others.is_empty() && series.is_none() {
        tracing::info!(
            "{}: read series {} ({} slices); also there: {}",
            path.display(),
            chosen.uid,
            chosen.slices,
            list(&others)
        );
    }
    let volume = assemble(path, slices, decode_file)?;
    Ok(DicomRead { volume, units, series: chosen, others, skipped })
}

fn list(infos: &[SeriesInfo]) -> String {
    let each: Vec<String> =
        infos.iter().map(|i| format!("{} \"{}\" ({} slices)", i.uid, i.description, i.slices)).collect();
    each.join(", ")
}

fn first_reason(skipped: &[(PathBuf, String)]) -> String {
    skipped.first().map_or_else(String::new, |(file, why)| format!("{}: {why}", file.display()))
}

/// The folder's files (not its subfolders), by name.
fn folder_files(folder: &Path) -> Result<Vec<PathBuf>, IoError> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(folder).map_err(io_error(folder))? {
        let path = entry.map_err(io_error(folder))?.path();
        if path.is_file() {
            files.push(path);
        }
    }
    files.sort();
    Ok(files)
}

/// A file's slices from its header up to its pixel data, or why it is not a DICOM image.
fn read_header(path: &Path) -> Result<Vec<Slice>, String> {
    let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
    check_lengths(&bytes)?;
    let object =
        OpenFileOptions::new().read_until(tags::PIXEL_DATA).from_reader(&bytes[..]).map_err(|e| e.to_string())?;
    header(path, &object, bytes.len() as u64)
}

/// Whether a file carries the DICOM preamble's `DICM` mark.
pub(super) fn has_dicom_mark(path: &Path) -> bool {
    let mut mark = [0u8; 132];
    std::fs::File::open(path).and_then(|mut f| std::io::Read::read_exact(&mut f, &mut mark)).is_ok()
        && &mark[128..] == b"DICM"
}

/// Transfer syntaxes whose pixel data is stored as is: implicit and explicit VR little
/// endian, explicit big endian.
const NATIVE_SYNTAXES: [&str; 3] = ["1.2.840.10008.1.2", "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.2"];

/// An attribute as an enhanced file keeps it: in the first item of `group` in the shared
/// functional groups, else in the first frame's, else at the top level (a classic file).
fn functional(object: &DefaultDicomObject, group: Tag, attribute: Tag) -> Option<&InMemElement> {
    let in_group = |groups: Tag| object.get(groups)?.items()?.first()?.get(group)?.items()?.first()?.get(attribute);
    in_group(tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE)
        .or_else(|| in_group(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE))
        .or_else(|| object.get(attribute))
}

/// `count` finite numbers from `element`, named `name` in errors.
fn numbers(element: Option<&InMemElement>, name: &str, count: usize) -> Result<Vec<f64>, String> {
    let values = element.ok_or_else(|| format!("no {name}"))?.to_multi_float64().map_err(|e| format!("{name}: {e}"))?;
    if values.len() != count || !values.iter().all(|v| v.is_finite()) {
        return Err(format!("{name} is {values:?}; {count} finite numbers expected"));
    }
    Ok(values)
}

/// A file's slices, one a frame, from its header; `available` is the file's size, so pixel
/// data that cannot be in it is refused before a frame is listed.
fn header(path: &Path, object: &DefaultDicomObject, available: u64) -> Result<Vec<Slice>, String> {
    let text = |tag, name: &str| -> Result<String, String> {
        let element = object.element(tag).map_err(|_| format!("no {name}"))?;
        Ok(element.to_str().map_err(|e| format!("{name}: {e}"))?.trim().to_owned())
    };
    let count = |tag, name: &str| -> Result<usize, String> {
        let element = object.element(tag).map_err(|_| format!("no {name}"))?;
        element.to_int::<u32>().map(|v| v as usize).map_err(|e| format!("{name}: {e}"))
    };
    let frames = match object.element_opt(tags::NUMBER_OF_FRAMES).map_err(|e| e.to_string())? {
        Some(element) => element.to_int::<u32>().map_err(|e| format!("NumberOfFrames: {e}"))? as usize,
        None => 1,
    };
    let size = [count(tags::COLUMNS, "Columns")?, count(tags::ROWS, "Rows")?];
    let bits = count(tags::BITS_ALLOCATED, "BitsAllocated")?;
    let stored = count(tags::BITS_STORED, "BitsStored")?;
    // CT and MR store 8 or 16 bits; dicom-pixeldata's tables assume what is checked here.
    if !(bits == 8 || bits == 16) || stored == 0 || stored > bits {
        return Err(format!(
            "BitsAllocated {bits}, BitsStored {stored}: 8 or 16 bits, stored in 1 to all of them, are read"
        ));
    }
    let samples = object.element_opt(tags::SAMPLES_PER_PIXEL).ok().flatten().and_then(|e| e.to_int::<u32>().ok());
    if samples.unwrap_or(1) != 1 {
        return Err(format!("{} samples a pixel (colour); a volume has one", samples.unwrap_or(1)));
    }
    let bytes = (size[0] as u128) * (size[1] as u128) * (frames as u128) * (bits.div_ceil(8) as u128).max(1);
    if size.contains(&0) || frames == 0 || bytes > MAX_DECODED_BYTES as u128 {
        return Err(format!(
            "{}x{} pixels x {frames} frames x {bits} bits: empty, or beyond {MAX_DECODED_BYTES} bytes",
            size[0], size[1]
        ));
    }
    let orientation = numbers(
        functional(object, tags::PLANE_ORIENTATION_SEQUENCE, tags::IMAGE_ORIENTATION_PATIENT),
        "ImageOrientationPatient",
        6,
    )?;
    let (row_dir, col_dir) = (
        Vector3::new(orientation[0], orientation[1], orientation[2]),
        Vector3::new(orientation[3], orientation[4], orientation[5]),
    );
    if (row_dir.norm() - 1.0).abs() > 1e-3 || (col_dir.norm() - 1.0).abs() > 1e-3 || row_dir.dot(&col_dir).abs() > 1e-3
    {
        return Err(format!("ImageOrientationPatient {orientation:?} is not two orthonormal directions"));
    }
    let spacing = numbers(functional(object, tags::PIXEL_MEASURES_SEQUENCE, tags::PIXEL_SPACING), "PixelSpacing", 2)?;
    if !spacing.iter().all(|s| *s > 0.0) {
        return Err(format!("PixelSpacing {spacing:?} must be positive"));
    }
    let depth = |tag| {
        functional(object, tags::PIXEL_MEASURES_SEQUENCE, tag)?.to_float64().ok().filter(|t| t.is_finite() && *t > 0.0)
    };
    let first = Slice {
        path: path.to_owned(),
        frame: 0,
        uid: text(tags::SERIES_INSTANCE_UID, "SeriesInstanceUID")?,
        description: text(tags::SERIES_DESCRIPTION, "SeriesDescription").unwrap_or_default(),
        size,
        frames,
        row_dir: row_dir.normalize(),
        col_dir: col_dir.normalize(),
        position: Vector3::zeros(),
        pixel_spacing: [spacing[1], spacing[0]],
        pixel_bytes: u64::try_from(bytes).unwrap_or(u64::MAX),
        native: NATIVE_SYNTAXES.contains(&object.meta().transfer_syntax().trim_end_matches('\0')),
        thickness: depth(tags::SPACING_BETWEEN_SLICES).or_else(|| depth(tags::SLICE_THICKNESS)),
        units: functional(object, tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE, tags::RESCALE_TYPE)
            .and_then(|e| Some(e.to_str().ok()?.trim().to_owned()))
            .filter(|t| !t.is_empty())
            .or_else(|| (text(tags::MODALITY, "Modality").ok()? == "CT").then(|| "HU".to_owned())),
    };
    check_pixel_bytes(&first, available)?;
    let positions = frame_positions(object, &first)?;
    Ok(positions.into_iter().enumerate().map(|(frame, position)| Slice { frame, position, ..first.clone() }).collect())
}

/// Where each frame of a file lies: the per-frame functional groups' positions where an
/// enhanced file gives them, else ImagePositionPatient stepped along the normal by
/// SpacingBetweenSlices (a classic multi-frame file).
fn frame_positions(object: &DefaultDicomObject, first: &Slice) -> Result<Vec<Vector3<f64>>, String> {
    if first.frames > MAX_FRAMES {
        return Err(format!("{} frames: more than the {MAX_FRAMES} a volume is read with", first.frames));
    }
    let per_frame = object.get(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE).and_then(|e| e.items());
    let placed = |item: &InMemDicomObject| {
        let position = item.get(tags::PLANE_POSITION_SEQUENCE)?.items()?.first()?.get(tags::IMAGE_POSITION_PATIENT);
        Some(numbers(position, "ImagePositionPatient (per frame)", 3).map(|p| Vector3::new(p[0], p[1], p[2])))
    };
    if let Some(items) = per_frame.filter(|items| items.first().and_then(placed).is_some()) {
        if items.len() != first.frames {
            return Err(format!("{} per-frame functional groups for {} frames", items.len(), first.frames));
        }
        return items
            .iter()
            .enumerate()
            .map(|(k, item)| {
                placed(item).unwrap_or_else(|| Err(format!("frame {} has no PlanePositionSequence", k + 1)))
            })
            .collect();
    }
    let position = numbers(object.get(tags::IMAGE_POSITION_PATIENT), "ImagePositionPatient", 3)?;
    let origin = Vector3::new(position[0], position[1], position[2]);
    if first.frames == 1 {
        return Ok(vec![origin]);
    }
    let step = object
        .get(tags::SPACING_BETWEEN_SLICES)
        .and_then(|e| e.to_float64().ok())
        .filter(|s| s.is_finite() && *s > 0.0)
        .ok_or("a multi-frame file with neither per-frame positions nor a positive SpacingBetweenSlices")?;
    Ok((0..first.frames).map(|k| origin + first.normal() * (step * k as f64)).collect())
}

/// Slices as a volume: checked to be one regular grid, sorted, and filled by `decode` (all
/// the frames of a slice's file, called once a file).
fn assemble(
    path: &Path,
    mut slices: Vec<Slice>,
    mut decode: impl FnMut(&Slice) -> Result<Vec<Vec<f32>>, IoError>,
) -> Result<Volume, IoError> {
    let first = slices[0].clone();
    for s in &slices[1..] {
        let reason = if s.size != first.size {
            Some(format!("{}x{} pixels, not {}x{}", s.size[0], s.size[1], first.size[0], first.size[1]))
        } else if (s.row_dir - first.row_dir).norm() > 1e-4 || (s.col_dir - first.col_dir).norm() > 1e-4 {
            Some("mixed orientations (ImageOrientationPatient differs)".to_owned())
        } else if (0..2).any(|a| (s.pixel_spacing[a] - first.pixel_spacing[a]).abs() > 1e-4 * first.pixel_spacing[a]) {
            Some(format!("PixelSpacing differs ({:?} and {:?})", s.pixel_spacing, first.pixel_spacing))
        } else {
            None
        };
        if let Some(reason) = reason {
            return Err(malformed(path, format!("not one volume: {} and {}: {reason}", first.name(), s.name())));
        }
    }
    let normal = first.normal();
    slices.sort_by(|a, b| a.position.dot(&normal).total_cmp(&b.position.dot(&normal)));
    let (slice_dir, step) = slice_step(path, &slices)?;
    let direction = Matrix3::from_columns(&[first.row_dir, first.col_dir, slice_dir]);
    let [nx, ny] = first.size;
    let mut data = Vec::with_capacity(nx * ny * slices.len());
    let mut decoded: HashMap<PathBuf, Vec<Vec<f32>>> = HashMap::new();
    for s in &slices {
        if !decoded.contains_key(&s.path) {
            decoded.insert(s.path.clone(), decode(s)?);
        }
        let frame = decoded.get_mut(&s.path).and_then(|frames| frames.get_mut(s.frame));
        data.extend(frame.map(std::mem::take).unwrap_or_default());
    }
    let spacing = [first.pixel_spacing[0], first.pixel_spacing[1], step];
    let origin = slices[0].position.into();
    Ok(Volume::new([nx, ny, slices.len()], spacing, origin, direction, data, &path.display().to_string())?)
}

/// The unit step between slices and its length, as ITK takes them from the first two
/// positions, after checking every step against the median step: no two slices at one
/// place, none missing, no uneven step, no tilt from the orientation's normal.
fn slice_step(path: &Path, slices: &[Slice]) -> Result<(Vector3<f64>, f64), IoError> {
    let normal = slices[0].normal();
    if slices.len() == 1 {
        return Ok((normal, slices[0].thickness.unwrap_or(1.0)));
    }
    let steps: Vec<Vector3<f64>> = slices.windows(2).map(|w| w[1].position - w[0].position).collect();
    let mut lengths: Vec<f64> = steps.iter().map(|d| d.norm()).collect();
    lengths.sort_by(f64::total_cmp);
    let median = lengths[lengths.len() / 2];
    for (k, d) in steps.iter().enumerate() {
        let (length, along) = (d.norm(), d.dot(&normal));
        let reason = if length < 1e-6 {
            Some("two slices at one position".to_owned())
        } else if 1.0 - along / length > TILT_TOLERANCE {
            let degrees = (along / length).clamp(-1.0, 1.0).acos().to_degrees();
            Some(format!("the slices step {degrees:.2}° off their normal (gantry tilt); resample the series first"))
        } else if length > 1.5 * median {
            Some(format!("a slice is missing: {length:.4} mm between them, {median:.4} mm between the others"))
        } else if (length - median).abs() > STEP_TOLERANCE * median {
            Some(format!("uneven slice spacing: {length:.4} mm between them, {median:.4} mm between the others"))
        } else {
            None
        };
        if let Some(reason) = reason {
            let pair = format!("{} and {}", slices[k].name(), slices[k + 1].name());
            return Err(malformed(path, format!("{pair}: {reason}")));
        }
    }
    Ok((steps[0] / steps[0].norm(), steps[0].norm()))
}

/// No codec packs more than this many decoded bytes into one (deflate's limit is 1032,
/// RLE's 128): a compressed file declaring more lies about its size.
const MAX_COMPRESSION: u64 = 2048;

/// Refuses a file whose pixel data cannot be in `available` bytes, before anything is
/// allocated for it (a cut file, or a header that lies): uncompressed, every byte must be
/// there; compressed, no more than [`MAX_COMPRESSION`] to one, and a byte a frame.
fn check_pixel_bytes(slice: &Slice, available: u64) -> Result<(), String> {
    let (needed, frames) = (slice.pixel_bytes, slice.frames as u64);
    let lie = if slice.native && needed > available {
        format!("declares {needed} bytes of pixel data (Columns x Rows x frames x BitsAllocated)")
    } else if needed > available.saturating_mul(MAX_COMPRESSION) || frames > available {
        format!("declares {needed} bytes of pixel data in {frames} frames, compressed beyond any codec's ratio")
    } else {
        return Ok(());
    };
    Err(format!("{lie} but holds {available} bytes in all: truncated, or its header is wrong"))
}

fn damaged(path: &Path, e: impl std::fmt::Display) -> IoError {
    malformed(path, format!("a DICOM file that cannot be read (truncated or damaged): {e}"))
}

/// Every frame's values of a slice's file, through its RescaleSlope and RescaleIntercept.
fn decode_file(slice: &Slice) -> Result<Vec<Vec<f32>>, IoError> {
    let path = &slice.path;
    let bytes = std::fs::read(path).map_err(io_error(path))?;
    check_lengths(&bytes).map_err(|e| damaged(path, e))?;
    decode_checked(path, &bytes, slice)
}

/// Every frame's values of a file whose element lengths were checked, once its pixel data
/// is known to fit in its bytes; a frame's own rescale where the per-frame functional
/// groups give one (dicom-pixeldata reads them).
fn decode_checked(path: &Path, bytes: &[u8], slice: &Slice) -> Result<Vec<Vec<f32>>, IoError> {
    check_pixel_bytes(slice, bytes.len() as u64).map_err(|why| malformed(path, why))?;
    let object = OpenFileOptions::new().from_reader(bytes).map_err(|e| damaged(path, e))?;
    let pixels = slice.size[0] * slice.size[1];
    let decoded = object.decode_pixel_data().map_err(|e| malformed(path, format!("pixel data: {e}")))?;
    let mut frames = Vec::with_capacity(slice.frames);
    for frame in 0..slice.frames {
        let values: Vec<f32> = decoded
            .to_vec_frame_with_options(frame as u32, &ConvertOptions::new())
            .map_err(|e| malformed(path, format!("pixel data, frame {}: {e}", frame + 1)))?;
        if values.len() != pixels {
            return Err(malformed(path, format!("{} pixel values, Rows x Columns is {pixels}", values.len())));
        }
        frames.push(values);
    }
    Ok(frames)
}

/// Parses one DICOM file from its bytes: a multi-frame file as its volume, a single-frame
/// one as a volume one slice deep (its depth SpacingBetweenSlices, else SliceThickness, else
/// 1, as ITK takes it); `path` names it in errors. The fuzz tests drive the DICOM path
/// through it.
pub fn parse_dicom(path: &Path, bytes: &[u8]) -> Result<Volume, IoError> {
    check_lengths(bytes).map_err(|e| damaged(path, e))?;
    let object =
        OpenFileOptions::new().read_until(tags::PIXEL_DATA).from_reader(bytes).map_err(|e| damaged(path, e))?;
    let slices = header(path, &object, bytes.len() as u64).map_err(|why| malformed(path, why))?;
    assemble(path, slices, |slice| decode_checked(path, bytes, slice))
}
