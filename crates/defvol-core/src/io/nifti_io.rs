//! NIfTI-1 (`.nii`, `.nii.gz`). The nifti crate parses and writes the header; the samples are
//! decoded here from the file's bytes (every size checked against them first). NIfTI's world
//! is RAS; like ITK we present it as LPS (x and y negated), and choose between the sform and
//! the qform as ITK does: the sform when it is a rotation with scales and either the qform
//! is unknown, the sform's code is scanner-anatomical, or the two agree; else the qform; with
//! both unknown, the identity. Written with both, code 1 (scanner-anatomical), as ITK writes.

use std::io::Read;
use std::path::Path;

use nalgebra::{Matrix3, Vector3};
use ndarray::{Array3, ShapeBuilder};
use nifti::writer::WriterOptions;
use nifti::NiftiHeader;

use super::error::{malformed, IoError, MAX_DECODED_BYTES};
use super::raw::{sample_bytes, SampleType};
use crate::volume::Volume;

const LPS_FROM_RAS: [f64; 3] = [-1.0, -1.0, 1.0];
/// NIfTI-1 stores dims as signed 16-bit integers.
const MAX_DIM: usize = 32_767;

/// The rotation-and-scale part and the offset of a voxel-to-RAS map.
struct Affine {
    linear: Matrix3<f64>,
    offset: Vector3<f64>,
}

fn qform(h: &NiftiHeader) -> Affine {
    let (b, c, d) = (f64::from(h.quatern_b), f64::from(h.quatern_c), f64::from(h.quatern_d));
    let a = (1.0 - b * b - c * c - d * d).max(0.0).sqrt();
    let r = Matrix3::new(
        a * a + b * b - c * c - d * d,
        2.0 * (b * c - a * d),
        2.0 * (b * d + a * c),
        2.0 * (b * c + a * d),
        a * a + c * c - b * b - d * d,
        2.0 * (c * d - a * b),
        2.0 * (b * d - a * c),
        2.0 * (c * d + a * b),
        a * a + d * d - b * b - c * c,
    );
    let qfac = if h.pixdim[0] < 0.0 { -1.0 } else { 1.0 };
    let s =
        Matrix3::from_diagonal(&Vector3::new(spacing(h.pixdim[1]), spacing(h.pixdim[2]), spacing(h.pixdim[3]) * qfac));
    Affine {
        linear: r * s,
        offset: Vector3::new(f64::from(h.quatern_x), f64::from(h.quatern_y), f64::from(h.quatern_z)),
    }
}

fn sform(h: &NiftiHeader) -> Affine {
    let rows = [h.srow_x, h.srow_y, h.srow_z].map(|r| r.map(f64::from));
    Affine {
        linear: Matrix3::new(
            rows[0][0], rows[0][1], rows[0][2], rows[1][0], rows[1][1], rows[1][2], rows[2][0], rows[2][1], rows[2][2],
        ),
        offset: Vector3::new(rows[0][3], rows[1][3], rows[2][3]),
    }
}

fn spacing(pixdim: f32) -> f64 {
    let s = f64::from(pixdim).abs();
    if s > 0.0 && s.is_finite() {
        s
    } else {
        1.0
    }
}

/// How far the normalised columns of `m` are from orthonormal (`None`: a zero or infinite column).
fn shear(m: &Matrix3<f64>) -> Option<f64> {
    let mut unit = *m;
    for mut column in unit.column_iter_mut() {
        let norm = column.norm();
        if !(norm > 0.0 && norm.is_finite()) {
            return None;
        }
        column /= norm;
    }
    Some((unit.transpose() * unit - Matrix3::identity()).norm())
}

/// The map ITK would use, or why none can be.
fn choose(h: &NiftiHeader) -> Result<Option<Affine>, String> {
    if h.qform_code <= 0 && h.sform_code <= 0 {
        return Ok(None);
    }
    let s = sform(h);
    let s_usable =
        h.sform_code > 0 && shear(&s.linear).is_some_and(|d| d < 1e-4) && s.offset.iter().all(|v| v.is_finite());
    if s_usable {
        let q = qform(h);
        let agree = (s.linear - q.linear).norm() <= 1e-4 * s.linear.norm()
            && (s.offset - q.offset).norm() <= 1e-4 * (1.0 + s.offset.norm());
        if h.qform_code <= 0 || h.sform_code == 1 || agree {
            return Ok(Some(s));
        }
    }
    if h.qform_code > 0 {
        return Ok(Some(qform(h)));
    }
    Err(format!("the sform is sheared (|UᵀU - I| = {:.2e}) and there is no qform: not a rotation and scales, as a voxel grid needs", shear(&s.linear).unwrap_or(f64::INFINITY)))
}

fn sample_type(datatype: i16) -> Option<SampleType> {
    Some(match datatype {
        2 => SampleType::U8,
        4 => SampleType::I16,
        8 => SampleType::I32,
        16 => SampleType::F32,
        64 => SampleType::F64,
        256 => SampleType::I8,
        512 => SampleType::U16,
        768 => SampleType::U32,
        1024 => SampleType::I64,
        1280 => SampleType::U64,
        _ => return None,
    })
}

pub(super) fn parse(path: &Path, bytes: &[u8]) -> Result<Volume, IoError> {
    let unzipped;
    let bytes = if bytes.starts_with(&[0x1f, 0x8b]) {
        let mut out = Vec::new();
        flate2::read::MultiGzDecoder::new(bytes)
            .take(MAX_DECODED_BYTES as u64)
            .read_to_end(&mut out)
            .map_err(|e| malformed(path, format!("cannot decompress: {e}")))?;
        unzipped = out;
        &unzipped[..]
    } else {
        bytes
    };
    let header =
        NiftiHeader::from_reader(bytes).map_err(|e| malformed(path, format!("not a readable NIfTI-1 header: {e}")))?;
    if &header.magic != b"n+1\0" {
        return Err(malformed(path, "not a single-file NIfTI-1 image (magic n+1): a .hdr/.img pair is not read"));
    }
    let rank = usize::from(header.dim[0]);
    if !(1..=7).contains(&rank) {
        return Err(malformed(path, format!("dim[0] = {rank}: not 1 to 7")));
    }
    if header.dim[4..=rank.max(3)].iter().any(|d| *d > 1) {
        return Err(IoError::Unrepresentable {
            path: path.to_owned(),
            message: format!(
                "dim {:?}: a 4D (or higher) volume; only single 3D volumes are read",
                &header.dim[..=rank]
            ),
        });
    }
    let dims = [header.dim[1], header.dim[2].max(1), header.dim[3].max(1)].map(usize::from);
    if dims.contains(&0) {
        return Err(malformed(path, format!("dim {:?}: a zero size", &header.dim[..=rank])));
    }
    let Some(sample) = sample_type(header.datatype) else {
        return Err(IoError::Unrepresentable {
            path: path.to_owned(),
            message: format!("datatype {}: not a real scalar type", header.datatype),
        });
    };
    let needed = sample_bytes(path, dims, sample)?;
    let offset = header.vox_offset;
    if !(offset.is_finite() && offset >= 348.0) {
        return Err(malformed(path, format!("vox_offset {offset} is before the end of the header")));
    }
    let data = bytes.get(offset as usize..).filter(|d| d.len() >= needed).ok_or_else(|| {
        malformed(
            path,
            format!(
                "{} bytes of samples after vox_offset {offset}, {needed} needed",
                bytes.len().saturating_sub(offset as usize)
            ),
        )
    })?;
    let big_endian = matches!(header.endianness, nifti::Endianness::Big);
    let mut values = sample.decode(&data[..needed], big_endian);
    let (slope, intercept) = (header.scl_slope, header.scl_inter);
    if slope != 0.0 && slope.is_finite() && intercept.is_finite() && (slope != 1.0 || intercept != 0.0) {
        values.iter_mut().for_each(|v| *v = *v * slope + intercept);
    }
    let affine = choose(&header).map_err(|message| IoError::Unrepresentable { path: path.to_owned(), message })?;
    let (mut direction, mut spacing_out, mut origin) = (
        Matrix3::identity(),
        [spacing(header.pixdim[1]), spacing(header.pixdim[2]), spacing(header.pixdim[3])],
        [0.0; 3],
    );
    if let Some(m) = affine {
        for a in 0..3 {
            let column = m.linear.column(a).into_owned();
            spacing_out[a] = column.norm();
            let unit = column / spacing_out[a];
            for r in 0..3 {
                direction[(r, a)] = unit[r] * LPS_FROM_RAS[r];
            }
        }
        origin = [0, 1, 2].map(|r| m.offset[r] * LPS_FROM_RAS[r]);
    }
    Ok(Volume::new(dims, spacing_out, origin, direction, values, &path.display().to_string())?)
}

/// The quaternion (b, c, d) and qfac of a rotation (or a reflection), as nifti1_io's
/// `nifti_mat44_to_quatern` computes them.
fn quaternion(rotation: &Matrix3<f64>) -> ([f64; 3], f64) {
    let mut r = *rotation;
    let qfac = if r.determinant() > 0.0 { 1.0 } else { -1.0 };
    if qfac < 0.0 {
        let flipped = -r.column(2);
        r.set_column(2, &flipped);
    }
    let a = r[(0, 0)] + r[(1, 1)] + r[(2, 2)] + 1.0;
    let (a, b, c, d) = if a > 0.5 {
        let a = 0.5 * a.sqrt();
        (a, 0.25 * (r[(2, 1)] - r[(1, 2)]) / a, 0.25 * (r[(0, 2)] - r[(2, 0)]) / a, 0.25 * (r[(1, 0)] - r[(0, 1)]) / a)
    } else {
        let xd = 1.0 + r[(0, 0)] - (r[(1, 1)] + r[(2, 2)]);
        let yd = 1.0 + r[(1, 1)] - (r[(0, 0)] + r[(2, 2)]);
        let zd = 1.0 + r[(2, 2)] - (r[(0, 0)] + r[(1, 1)]);
        if xd > 1.0 {
            let b = 0.5 * xd.sqrt();
            (
                0.25 * (r[(2, 1)] - r[(1, 2)]) / b,
                b,
                0.25 * (r[(0, 1)] + r[(1, 0)]) / b,
                0.25 * (r[(0, 2)] + r[(2, 0)]) / b,
            )
        } else if yd > 1.0 {
            let c = 0.5 * yd.sqrt();
            (
                0.25 * (r[(0, 2)] - r[(2, 0)]) / c,
                0.25 * (r[(0, 1)] + r[(1, 0)]) / c,
                c,
                0.25 * (r[(1, 2)] + r[(2, 1)]) / c,
            )
        } else {
            let d = 0.5 * zd.sqrt();
            (
                0.25 * (r[(1, 0)] - r[(0, 1)]) / d,
                0.25 * (r[(0, 2)] + r[(2, 0)]) / d,
                0.25 * (r[(1, 2)] + r[(2, 1)]) / d,
                d,
            )
        }
    };
    let sign = if a < 0.0 { -1.0 } else { 1.0 };
    ([b * sign, c * sign, d * sign], qfac)
}

pub(super) fn write(path: &Path, volume: &Volume) -> Result<(), IoError> {
    let [nx, ny, nz] = volume.dims();
    if [nx, ny, nz].iter().any(|d| *d > MAX_DIM) {
        return Err(IoError::Unrepresentable {
            path: path.to_owned(),
            message: format!("dims {:?}: NIfTI-1 holds at most {MAX_DIM} voxels along an axis", volume.dims()),
        });
    }
    let sp = volume.spacing();
    let o = volume.origin();
    // The direction in RAS.
    let ras = Matrix3::from_fn(|r, c| LPS_FROM_RAS[r] * volume.direction()[(r, c)]);
    let row = |r: usize| -> [f32; 4] {
        [
            (ras[(r, 0)] * sp[0]) as f32,
            (ras[(r, 1)] * sp[1]) as f32,
            (ras[(r, 2)] * sp[2]) as f32,
            (LPS_FROM_RAS[r] * o[r]) as f32,
        ]
    };
    let ([b, c, d], qfac) = quaternion(&ras);
    let header = NiftiHeader {
        dim: [3, nx as u16, ny as u16, nz as u16, 1, 1, 1, 1],
        pixdim: [qfac as f32, sp[0] as f32, sp[1] as f32, sp[2] as f32, 0.0, 0.0, 0.0, 0.0],
        xyzt_units: 2, // millimetres
        sform_code: 1,
        qform_code: 1,
        quatern_b: b as f32,
        quatern_c: c as f32,
        quatern_d: d as f32,
        quatern_x: (LPS_FROM_RAS[0] * o[0]) as f32,
        quatern_y: (LPS_FROM_RAS[1] * o[1]) as f32,
        quatern_z: (LPS_FROM_RAS[2] * o[2]) as f32,
        srow_x: row(0),
        srow_y: row(1),
        srow_z: row(2),
        ..NiftiHeader::default()
    };
    let array = Array3::from_shape_vec((nx, ny, nz).f(), volume.data().to_vec())
        .map_err(|e| malformed(path, format!("sample layout: {e}")))?;
    // The nifti crate renames what it writes by extension ("scan.v2.nii" would become
    // "scan.nii"): write a dot-free temporary name beside the target, then rename it.
    let temporary = super::files::temporary_beside(path);
    if let Err(e) = WriterOptions::new(&temporary).reference_header(&header).write_nifti(&array) {
        let _ = std::fs::remove_file(&temporary);
        return Err(malformed(path, format!("cannot write NIfTI: {e}")));
    }
    super::files::commit(&temporary, path)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// nifti1_io's quaternion of a rotation (and a reflection) gives the rotation back
    /// through the qform's formula.
    #[test]
    fn quaternions_give_their_rotation_back() {
        let rotations = [
            nalgebra::Rotation3::from_euler_angles(0.3, -1.1, 2.0).into_inner(),
            nalgebra::Rotation3::from_euler_angles(std::f64::consts::PI, 0.0, 0.0).into_inner(),
            Matrix3::from_diagonal(&Vector3::new(-1.0, -1.0, 1.0)),
            Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0)),
        ];
        for r in rotations {
            let ([b, c, d], qfac) = quaternion(&r);
            let h = NiftiHeader {
                quatern_b: b as f32,
                quatern_c: c as f32,
                quatern_d: d as f32,
                pixdim: [qfac as f32, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0],
                ..NiftiHeader::default()
            };
            let back = qform(&h).linear;
            assert!((back - r).norm() < 1e-6, "{r} came back as {back}");
        }
    }
}
