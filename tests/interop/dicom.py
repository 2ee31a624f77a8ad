"""DICOM series written by SimpleITK (GDCM) and multi-frame files written by pydicom, and what
SimpleITK reads of them (ImageSeriesReader for a series, GDCM's ImageIO for one file), for
tests/it/dicom.rs.

usage:
  dicom.py write DIR   writes each case's series into DIR/<case>/ (slices as a scanner writes
                       them: one file a slice, CT values stored through RescaleSlope and
                       RescaleIntercept), and for each case ITK reads as one volume, what
                       ImageSeriesReader reads (GDCM's sorting) as DIR/<case>.<uid>.mha; a
                       multi-frame case is one file, DIR/<case>/volume.dcm; prints a JSON
                       object: case -> {"series": [uids], "readable": bool}.
"""

import json
import math
import os
import random
import sys

import numpy as np


def oblique():
    a, b = math.radians(20.0), math.radians(-12.0)
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    return rz @ ry


def ct_values(shape):
    """A CT in Hounsfield units: air around a soft-tissue body with a bone in it."""
    z, y, x = np.indices(shape, dtype=np.float64)
    c = [(s - 1) / 2.0 for s in shape]
    r = np.sqrt(((x - c[2]) / shape[2]) ** 2 + ((y - c[1]) / shape[1]) ** 2)
    values = np.where(r < 0.35, 40.0 + 2.0 * z + 0.5 * x, -1000.0)
    values = np.where(r < 0.1, 700.0 + 3.0 * y, values)
    return values


def write_series(folder, values, spacing, origin, direction, uid, description, steps, names, compressor=None):
    """One file a slice, positions along the direction's third column every spacing[2] (or
    at the cumulative `steps`), values stored as int16 through slope 0.5, intercept -1024."""
    import SimpleITK as sitk

    os.makedirs(folder, exist_ok=True)
    direction = np.asarray(direction)
    depth = values.shape[0]
    offsets = np.concatenate([[0.0], np.cumsum(steps)]) if steps is not None else np.arange(depth) * spacing[2]
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    if compressor:
        # GDCM's "JPEG": JPEG lossless, first-order prediction (1.2.840.10008.1.2.4.70).
        writer.SetUseCompression(True)
        writer.SetCompressor(compressor)
    orientation = "\\".join(f"{v:.10f}" for v in list(direction[:, 0]) + list(direction[:, 1]))
    for k in range(depth):
        image = sitk.GetImageFromArray(values[k : k + 1].astype(np.float32))
        image.SetSpacing(spacing)
        position = np.asarray(origin) + direction[:, 2] * offsets[k]
        image.SetOrigin(position.tolist())
        image.SetDirection(direction.flatten().tolist())
        tags = {
            "0008|0060": "CT",
            "0008|0008": "ORIGINAL\\PRIMARY\\AXIAL",
            "0020|000d": "1.2.826.0.1.3680043.2.1125.1",
            "0020|000e": uid,
            "0008|103e": description,
            "0020|0037": orientation,
            "0020|0032": "\\".join(f"{v:.10f}" for v in position),
            "0020|0013": str(k + 1),
            "0008|0018": f"{uid}.{k + 1}",
            "0028|1052": "-1024",
            "0028|1053": "0.5",
            "0028|1054": "HU",
            # Stored as signed 16-bit integers: GDCM applies the inverse rescale.
            "0028|0100": "16",
            "0028|0101": "16",
            "0028|0102": "15",
            "0028|0103": "1",
        }
        for tag, value in tags.items():
            image.SetMetaData(tag, value)
        writer.SetFileName(os.path.join(folder, names[k]))
        writer.Execute(image)


def write_multiframe(path, values, spacing, origin, direction, uid, enhanced, syntax):
    """One file holding every slice as a frame, by pydicom. Enhanced (Enhanced CT Image
    Storage): per-frame positions, orientation, PixelSpacing and rescale (slope 0.5,
    intercept -1024) in the shared functional groups. Classic (MR Image Storage, which GDCM
    steps by SpacingBetweenSlices): one ImagePositionPatient, values stored as they are."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sequence import Sequence
    from pydicom.uid import ExplicitVRLittleEndian

    def item(**attributes):
        ds = Dataset()
        for name, value in attributes.items():
            setattr(ds, name, Sequence([value]) if isinstance(value, Dataset) else value)
        return ds

    os.makedirs(os.path.dirname(path), exist_ok=True)
    direction = np.asarray(direction)
    depth, rows, cols = values.shape
    sop_class = "1.2.840.10008.5.1.4.1.1.2.1" if enhanced else "1.2.840.10008.5.1.4.1.1.4"
    ds = item(SOPClassUID=sop_class, SOPInstanceUID=f"{uid}.1", StudyInstanceUID="1.2.826.0.1.3680043.2.1125.1",
              SeriesInstanceUID=uid, SeriesDescription="multi-frame", Modality="CT" if enhanced else "MR",
              Rows=rows, Columns=cols, NumberOfFrames=depth, SamplesPerPixel=1,
              PhotometricInterpretation="MONOCHROME2", BitsAllocated=16, BitsStored=16, HighBit=15,
              PixelRepresentation=1)
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta.MediaStorageSOPClassUID = sop_class
    ds.file_meta.MediaStorageSOPInstanceUID = f"{uid}.1"
    orientation = [float(v) for v in list(direction[:, 0]) + list(direction[:, 1])]
    pixel_spacing = [spacing[1], spacing[0]]
    if enhanced:
        stored = np.round((values + 1024.0) / 0.5).astype(np.int16)
        ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL", "NONE"]
        ds.SharedFunctionalGroupsSequence = Sequence([item(
            PixelMeasuresSequence=item(PixelSpacing=pixel_spacing, SliceThickness=spacing[2]),
            PlaneOrientationSequence=item(ImageOrientationPatient=orientation),
            PixelValueTransformationSequence=item(RescaleIntercept=-1024, RescaleSlope=0.5, RescaleType="HU"),
        )])
        positions = [np.asarray(origin) + direction[:, 2] * spacing[2] * k for k in range(depth)]
        ds.PerFrameFunctionalGroupsSequence = Sequence([
            item(PlanePositionSequence=item(ImagePositionPatient=[float(v) for v in p])) for p in positions
        ])
    else:
        stored = np.round(values).astype(np.int16)
        ds.ImageOrientationPatient = orientation
        ds.ImagePositionPatient = list(origin)
        ds.PixelSpacing = pixel_spacing
        ds.SpacingBetweenSlices = spacing[2]
    ds.PixelData = stored.tobytes()
    if syntax.is_compressed:
        ds.compress(syntax, stored)
    else:
        # Deflate compresses the whole data set, not the pixel data: pydicom deflates on save.
        ds.file_meta.TransferSyntaxUID = syntax
    ds.save_as(path, enforce_file_format=True)


def itk_read(folder, uid, out):
    import SimpleITK as sitk

    reader = sitk.ImageSeriesReader()
    files = reader.GetGDCMSeriesFileNames(folder, uid)
    image = sitk.ReadImage(files[0]) if len(files) == 1 else sitk.ReadImage(files)
    sitk.WriteImage(sitk.Cast(image, sitk.sitkFloat32), out)


def main():
    out = sys.argv[2]
    random.seed(7)
    shape = (9, 12, 10)  # z, y, x
    values = ct_values(shape)
    axial = np.eye(3)
    spacing = (0.7, 0.8, 1.25)
    origin = (-3.5, 12.0, -40.0)
    cases = {}

    def case(name, readable, series, **kwargs):
        folder = os.path.join(out, name)
        for n, (uid, description, vals) in enumerate(series):
            names = kwargs.get("names") or [f"{'s%d_' % n if n else ''}slice{k:03d}.dcm" for k in range(len(vals))]
            write_series(folder, vals, spacing, origin, kwargs.get("direction", axial), uid, description,
                         kwargs.get("steps"), names, kwargs.get("compressor"))
        cases[name] = {"series": [s[0] for s in series], "readable": readable}
        return folder

    one = [("1.2.3.4.1", "CT abdomen", values)]
    case("axial", True, one)
    case("oblique", True, one, direction=oblique())
    case("jpeg_lossless", True, one, compressor="JPEG")
    shuffled = [f"{random.getrandbits(48):012x}.dcm" for _ in range(shape[0])]
    case("shuffled", True, one, names=shuffled)
    # A second, smaller series in the folder: the larger is read, `--series` picks either.
    case("two_series", True, one + [("1.2.3.4.2", "CT scout", values[:4])])
    folder = case("missing_slice", False, one)
    os.remove(os.path.join(folder, "slice004.dcm"))
    case("uneven", False, one, steps=[1.25] * 4 + [1.6] + [1.25] * 3)
    # Gantry tilt: slices stepping 15 degrees off the orientation's normal.
    tilt = math.radians(15.0)
    tilted = np.eye(3)
    tilted[:, 2] = [0.0, math.sin(tilt), math.cos(tilt)]
    folder = case("tilted", False, one)
    for name in os.listdir(folder):
        os.remove(os.path.join(folder, name))
    write_tilted(folder, values, spacing, origin, tilted)
    # Multi-frame files: an enhanced CT (oblique; native, then deflated) and a classic MR in RLE.
    from pydicom.uid import DeflatedExplicitVRLittleEndian, ExplicitVRLittleEndian, RLELossless

    for name, enhanced, syntax in [("enhanced_ct", True, ExplicitVRLittleEndian),
                                   ("enhanced_ct_deflated", True, DeflatedExplicitVRLittleEndian),
                                   ("multiframe_mr_rle", False, RLELossless)]:
        path = os.path.join(out, name, "volume.dcm")
        write_multiframe(path, values, spacing, origin, oblique(), "1.2.3.4.7", enhanced, syntax)
        cases[name] = {"series": ["1.2.3.4.7"], "readable": True}
    folder = case("with_a_stray_file", True, one)
    with open(os.path.join(folder, "README.txt"), "w") as f:
        f.write("not a DICOM file\n")
    for name, entry in cases.items():
        if entry["readable"]:
            for uid in entry["series"]:
                itk_read(os.path.join(out, name), uid, os.path.join(out, f"{name}.{uid}.mha"))
    json.dump(cases, sys.stdout)


def write_tilted(folder, values, spacing, origin, tilted):
    """Axial slices whose positions step along `tilted`'s third column."""
    import SimpleITK as sitk

    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(values.shape[0]):
        image = sitk.GetImageFromArray(values[k : k + 1].astype(np.int16))
        image.SetSpacing(spacing)
        position = np.asarray(origin) + tilted[:, 2] * spacing[2] * k
        for tag, value in {
            "0008|0060": "CT",
            "0020|000e": "1.2.3.4.1",
            "0020|0037": "1\\0\\0\\0\\1\\0",
            "0020|0032": "\\".join(f"{v:.10f}" for v in position),
            "0020|0013": str(k + 1),
            "0008|0018": f"1.2.3.4.1.{k + 1}",
        }.items():
            image.SetMetaData(tag, value)
        writer.SetFileName(os.path.join(folder, f"slice{k:03d}.dcm"))
        writer.Execute(image)


if __name__ == "__main__":
    main()
