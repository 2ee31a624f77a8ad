"""A newcomer's files, written by the tools they come from: a CT by SimpleITK (an organ of
40 HU in air, 1 mm voxels, centred on the origin) and an organ mesh by meshio, both in
millimetres.

usage: newcomer.py DIR MESH.json   (MESH.json: {"points": [[x, y, z], ...], "tets": [[a, b, c, d], ...]} in mm)
writes DIR/ct.nii.gz and DIR/organ.vtu
"""

import json
import sys

import meshio
import numpy as np
import SimpleITK as sitk


def main():
    out, mesh_json = sys.argv[1], sys.argv[2]
    mesh = json.load(open(mesh_json))
    points, tets = np.array(mesh["points"], dtype=float), np.array(mesh["tets"], dtype=np.int64)
    meshio.write(f"{out}/organ.vtu", meshio.Mesh(points, [("tetra", tets)]))
    size = 140
    z, y, x = np.mgrid[0:size, 0:size, 0:size].astype(float) - (size - 1) / 2
    inside = (x / 50.0) ** 2 + (y / 40.0) ** 2 + (z / 60.0) ** 2 <= 1.0
    ct = sitk.GetImageFromArray(np.where(inside, 40, -1000).astype(np.int16))
    ct.SetSpacing((1.0, 1.0, 1.0))
    ct.SetOrigin((-(size - 1) / 2,) * 3)
    sitk.WriteImage(ct, f"{out}/ct.nii.gz")


if __name__ == "__main__":
    main()
