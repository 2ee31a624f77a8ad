"""Writes an oblique volume with SimpleITK: a rotation for its direction, anisotropic
spacing, an origin off the axes, and values that tell every voxel apart.

usage: oblique_volume.py OUT (.nrrd, .mha, .nii, ...)
"""

import math
import sys

import SimpleITK as sitk


def main():
    size = (24, 18, 12)
    image = sitk.Image(size, sitk.sitkFloat32)
    image.SetSpacing((1.5, 2.0, 2.5))
    image.SetOrigin((-17.0, 31.5, 8.25))
    a, b = math.radians(30.0), math.radians(20.0)
    rz = [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]]
    rx = [[1.0, 0.0, 0.0], [0.0, math.cos(b), -math.sin(b)], [0.0, math.sin(b), math.cos(b)]]
    d = [[sum(rz[r][k] * rx[k][c] for k in range(3)) for c in range(3)] for r in range(3)]
    image.SetDirection([d[r][c] for r in range(3) for c in range(3)])
    for k in range(size[2]):
        for j in range(size[1]):
            for i in range(size[0]):
                image.SetPixel(i, j, k, float(i + 100 * j + 10000 * k))
    sitk.WriteImage(image, sys.argv[1])


if __name__ == "__main__":
    main()
