//! NIfTI-1 (`.nii`, `.nii.gz`) through the nifti crate. NIfTI's world is RAS; like ITK we
//! present it as LPS (x and y negated), so a NIfTI volume and the same volume saved as
//! MetaImage or NRRD by ITK have equal origins and directions.

use std::path::Path;

use nalgebra::{Matrix3, Matrix4, Vector3};
use ndarray::{Array3, Ix3, ShapeBuilder};
use nifti::writer::WriterOptions;
use nifti::{IntoNdArray, NiftiHeader, NiftiObject, ReaderOptions};

use super::{malformed, IoError};
use crate::volume::Volume;

const LPS_FROM_RAS: [f64; 3] = [-1.0, -1.0, 1.0];

fn qform_affine(h: &NiftiHeader) -> Matrix4<f64> {
    let (b, c, d) = (h.quatern_b as f64, h.quatern_c as f64, h.quatern_d as f64);
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
    let s = Matrix3::from_diagonal(&Vector3::new(h.pixdim[1] as f64, h.pixdim[2] as f64, h.pixdim[3] as f64 * qfac));
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&(r * s));
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&Vector3::new(h.quatern_x as f64, h.quatern_y as f64, h.quatern_z as f64));
    m
}

fn affine(h: &NiftiHeader) -> Matrix4<f64> {
    if h.sform_code > 0 {
        let row = |r: [f32; 4]| r.map(|v| v as f64);
        let (x, y, z) = (row(h.srow_x), row(h.srow_y), row(h.srow_z));
        Matrix4::new(x[0], x[1], x[2], x[3], y[0], y[1], y[2], y[3], z[0], z[1], z[2], z[3], 0.0, 0.0, 0.0, 1.0)
    } else if h.qform_code > 0 {
        qform_affine(h)
    } else {
        Matrix4::from_diagonal(&nalgebra::Vector4::new(h.pixdim[1] as f64, h.pixdim[2] as f64, h.pixdim[3] as f64, 1.0))
    }
}

pub(super) fn read(path: &Path) -> Result<Volume, IoError> {
    if !path.exists() {
        return Err(IoError::Io {
            path: path.to_owned(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "file not found"),
        });
    }
    let obj = ReaderOptions::new()
        .read_file(path)
        .map_err(|e| malformed(path, format!("not a readable NIfTI-1 file: {e}")))?;
    let header = obj.header().clone();
    let rank = header.dim[0] as usize;
    if !(1..=7).contains(&rank) || header.dim[4..=rank.max(3)].iter().any(|d| *d > 1) {
        return Err(malformed(path, format!("dim {:?}: only single 3D volumes are supported", header.dim)));
    }
    let dims = [header.dim[1], header.dim[2].max(1), header.dim[3].max(1)].map(|d| d as usize);
    let array =
        obj.into_volume().into_ndarray::<f32>().map_err(|e| malformed(path, format!("cannot decode samples: {e}")))?;
    let array = array.into_dimensionality::<Ix3>().map_err(|e| malformed(path, format!("sample layout: {e}")))?;
    let data: Vec<f32> = array.permuted_axes([2, 1, 0]).iter().copied().collect();
    let m = affine(&header);
    let mut direction = Matrix3::zeros();
    let mut spacing = [0.0; 3];
    for a in 0..3 {
        let col = Vector3::new(m[(0, a)], m[(1, a)], m[(2, a)]);
        spacing[a] = col.norm();
        let unit = if spacing[a] > 0.0 { col / spacing[a] } else { Vector3::zeros() };
        for r in 0..3 {
            direction[(r, a)] = unit[r] * LPS_FROM_RAS[r];
        }
    }
    let origin = [m[(0, 3)] * LPS_FROM_RAS[0], m[(1, 3)] * LPS_FROM_RAS[1], m[(2, 3)] * LPS_FROM_RAS[2]];
    Ok(Volume::new(dims, spacing, origin, direction, data, &path.display().to_string())?)
}

pub(super) fn write(path: &Path, volume: &Volume) -> Result<(), IoError> {
    let [nx, ny, nz] = volume.dims();
    let sp = volume.spacing();
    let d = volume.direction();
    let o = volume.origin();
    let row = |r: usize| -> [f32; 4] {
        let f = LPS_FROM_RAS[r];
        [
            (f * d[(r, 0)] * sp[0]) as f32,
            (f * d[(r, 1)] * sp[1]) as f32,
            (f * d[(r, 2)] * sp[2]) as f32,
            (f * o[r]) as f32,
        ]
    };
    let header = NiftiHeader {
        dim: [3, nx as u16, ny as u16, nz as u16, 1, 1, 1, 1],
        pixdim: [1.0, sp[0] as f32, sp[1] as f32, sp[2] as f32, 0.0, 0.0, 0.0, 0.0],
        xyzt_units: 2, // millimetres
        sform_code: 1,
        qform_code: 0,
        srow_x: row(0),
        srow_y: row(1),
        srow_z: row(2),
        ..NiftiHeader::default()
    };
    let array = Array3::from_shape_vec((nx, ny, nz).f(), volume.data().to_vec())
        .map_err(|e| malformed(path, format!("sample layout: {e}")))?;
    WriterOptions::new(path)
        .reference_header(&header)
        .write_nifti(&array)
        .map_err(|e| malformed(path, format!("cannot write NIfTI: {e}")))
}
