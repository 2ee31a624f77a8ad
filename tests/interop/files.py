"""Files written and read by the field's own tools, for tests/file_interop.rs.

usage:
  files.py write DIR   writes meshes (meshio, VTK, Gmsh) and volumes (SimpleITK, nibabel,
                       pynrrd) in every encoding they offer into DIR, and prints a JSON
                       manifest: per file, what it holds (meshes: the points, tets and point
                       array written; volumes: what SimpleITK, ITK being the reference for
                       geometry, reads back: size, origin, spacing, direction, a checksum and
                       some voxels).
  files.py read DIR    reads every file defvol wrote into DIR with every tool that reads its
                       format, and prints a JSON object of what each tool found.
"""

import json
import math
import os
import sys

import numpy as np

# Two cubes side by side, six tets each around the main diagonal (so that the cubes' shared
# face is split alike), plus boundary triangles and a line, as Gmsh and meshio write them
# beside the volume cells.
CUBE = [(0, 1, 3, 7), (0, 3, 2, 7), (0, 2, 6, 7), (0, 6, 4, 7), (0, 4, 5, 7), (0, 5, 1, 7)]


def mesh_data():
    points = []
    for i in range(3):
        for j in range(2):
            for k in range(2):
                points.append((0.5 * i + 0.01 * j * k, 0.7 * j, 0.9 * k + 0.003 * i))
    index = lambda i, j, k: 4 * i + 2 * j + k
    tets = []
    for cube in range(2):
        corners = [index(cube + (c >> 2 & 1), c >> 1 & 1, c & 1) for c in range(8)]
        for t in CUBE:
            tet = [corners[v] for v in t]
            p = np.array([points[v] for v in tet])
            if np.linalg.det(np.array([p[1] - p[0], p[2] - p[0], p[3] - p[0]])) < 0:
                tet[2], tet[3] = tet[3], tet[2]
            tets.append(tet)
    points = np.array(points, dtype=np.float64)
    triangles = np.array([[0, 4, 2], [4, 6, 2]], dtype=np.int64)
    lines = np.array([[0, 4]], dtype=np.int64)
    dose = np.arange(len(points), dtype=np.float64) * 1.5 + 0.25
    return points, np.array(tets, dtype=np.int64), triangles, lines, dose


def write_meshes(out, manifest):
    import meshio

    points, tets, triangles, lines, dose = mesh_data()
    expected = {"points": points.tolist(), "tets": tets.tolist(), "array": "dose", "values": dose.tolist()}
    mixed = meshio.Mesh(points, [("tetra", tets), ("triangle", triangles), ("line", lines)], point_data={"dose": dose})
    only_tets = meshio.Mesh(points, [("tetra", tets)], point_data={"dose": dose})
    variants = [
        ("meshio_vtu_zlib.vtu", "vtu", dict(binary=True, compression="zlib"), mixed, 3),
        ("meshio_vtu_lzma.vtu", "vtu", dict(binary=True, compression="lzma"), mixed, 3),
        ("meshio_vtu_raw.vtu", "vtu", dict(binary=True, compression=None), mixed, 3),
        ("meshio_vtu_ascii.vtu", "vtu", dict(binary=False), mixed, 3),
        ("meshio_vtk_binary.vtk", "vtk", dict(binary=True), mixed, 3),
        ("meshio_vtk_ascii.vtk", "vtk", dict(binary=False), mixed, 3),
        ("meshio_gmsh22_binary.msh", "gmsh22", dict(binary=True), mixed, 3),
        ("meshio_gmsh22_ascii.msh", "gmsh22", dict(binary=False), mixed, 3),
        ("meshio_gmsh41_binary.msh", "gmsh", dict(binary=True), only_tets, 0),
        ("meshio_gmsh41_ascii.msh", "gmsh", dict(binary=False), only_tets, 0),
        ("meshio_tetgen.node", "tetgen", {}, only_tets, 0),
    ]
    # A file whose extension lies: VTK XML saved as `.vtk`, as some tools and users do.
    variants.append(("meshio_vtu_named.vtk", "vtu", dict(binary=True, compression="zlib"), mixed, 3))
    for name, fmt, kw, mesh, skipped in variants:
        meshio.write(os.path.join(out, name), mesh, file_format=fmt, **kw)
        arrays = fmt in ("vtu", "vtk")
        manifest[name] = dict(expected, kind="mesh", tool="meshio", skipped=skipped, has_array=arrays)
    # A node no cell uses (a mesher's leftover), last: read without it.
    stray = np.vstack([points, [[5.0, 5.0, 5.0]]])
    strays = meshio.Mesh(stray, [("tetra", tets)], point_data={"dose": np.append(dose, 99.0)})
    meshio.write(os.path.join(out, "meshio_stray_node.vtu"), strays, file_format="vtu", binary=False)
    manifest["meshio_stray_node.vtu"] = dict(expected, kind="mesh", tool="meshio", skipped=0, has_array=True)
    write_vtk_meshes(out, manifest, points, tets, triangles, dose, expected)
    write_gmsh_meshes(out, manifest, points, tets, triangles, expected)


def write_vtk_meshes(out, manifest, points, tets, triangles, dose, expected):
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    grid = vtk.vtkUnstructuredGrid()
    vtk_points = vtk.vtkPoints()
    vtk_points.SetData(numpy_to_vtk(points, deep=True))
    grid.SetPoints(vtk_points)
    for t in tets:
        grid.InsertNextCell(vtk.VTK_TETRA, 4, [int(v) for v in t])
    for tri in triangles:
        grid.InsertNextCell(vtk.VTK_TRIANGLE, 3, [int(v) for v in tri])
    array = numpy_to_vtk(dose, deep=True)
    array.SetName("dose")
    grid.GetPointData().SetScalars(array)
    xml = vtk.vtkXMLUnstructuredGridWriter
    for mode in ("ascii", "binary", "appended_raw", "appended_base64"):
        for compressor in ("none", "zlib", "lz4", "lzma"):
            for header in (32, 64):
                if mode == "ascii" and (compressor != "none" or header == 64):
                    continue
                name = f"vtk_xml_{mode}_{compressor}_uint{header}.vtu"
                writer = xml()
                writer.SetFileName(os.path.join(out, name))
                writer.SetInputData(grid)
                {"ascii": writer.SetDataModeToAscii, "binary": writer.SetDataModeToBinary}.get(mode, writer.SetDataModeToAppended)()
                writer.SetEncodeAppendedData(1 if mode == "appended_base64" else 0)
                {"none": writer.SetCompressorTypeToNone, "zlib": writer.SetCompressorTypeToZLib, "lz4": writer.SetCompressorTypeToLZ4, "lzma": writer.SetCompressorTypeToLZMA}[compressor]()
                (writer.SetHeaderTypeToUInt32 if header == 32 else writer.SetHeaderTypeToUInt64)()
                if not writer.Write():
                    raise RuntimeError(f"VTK could not write {name}")
                manifest[name] = dict(expected, kind="mesh", tool="vtk", skipped=2, has_array=True)
    for file_type in ("ascii", "binary"):
        for version in (42, 51):
            name = f"vtk_legacy_{file_type}_{version}.vtk"
            writer = vtk.vtkUnstructuredGridWriter()
            writer.SetFileName(os.path.join(out, name))
            writer.SetInputData(grid)
            (writer.SetFileTypeToASCII if file_type == "ascii" else writer.SetFileTypeToBinary)()
            writer.SetFileVersion(version)
            if not writer.Write():
                raise RuntimeError(f"VTK could not write {name}")
            manifest[name] = dict(expected, kind="mesh", tool="vtk", skipped=2, has_array=True)


def write_gmsh_meshes(out, manifest, points, tets, triangles, expected):
    import gmsh

    gmsh.initialize(["-noenv"])
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add("two cubes")
    volume = gmsh.model.addDiscreteEntity(3)
    surface = gmsh.model.addDiscreteEntity(2)
    tags = list(range(1, len(points) + 1))
    gmsh.model.mesh.addNodes(3, volume, tags, points.flatten().tolist())
    gmsh.model.mesh.addElementsByType(volume, 4, [], (tets + 1).flatten().tolist())
    gmsh.model.mesh.addElementsByType(surface, 2, [], (triangles + 1).flatten().tolist())
    gmsh.model.addPhysicalGroup(3, [volume], name="organ")
    gmsh.model.addPhysicalGroup(2, [surface], name="wall")
    # Gmsh's first format: ASCII only, no $MeshFormat.
    gmsh.option.setNumber("Mesh.MshFileVersion", 1)
    gmsh.option.setNumber("Mesh.Binary", 0)
    gmsh.option.setNumber("Mesh.SaveAll", 1)
    gmsh.write(os.path.join(out, "gmsh_1_ascii.msh"))
    manifest["gmsh_1_ascii.msh"] = dict(expected, kind="mesh", tool="gmsh", skipped=2, has_array=False)
    for version in (2.2, 4.1):
        for binary in (0, 1):
            name = f"gmsh_{str(version).replace('.', '')}_{'binary' if binary else 'ascii'}.msh"
            gmsh.option.setNumber("Mesh.MshFileVersion", version)
            gmsh.option.setNumber("Mesh.Binary", binary)
            gmsh.option.setNumber("Mesh.SaveAll", 1)
            gmsh.write(os.path.join(out, name))
            manifest[name] = dict(expected, kind="mesh", tool="gmsh", skipped=2, has_array=False)
    gmsh.finalize()


def itk_geometry(path):
    """What SimpleITK reads: ITK is the reference for where voxels are."""
    import SimpleITK as sitk

    image = sitk.ReadImage(path)
    array = sitk.GetArrayFromImage(image).astype(np.float64)  # z, y, x
    size = list(image.GetSize()) + [1] * (3 - image.GetDimension())
    flat = array.reshape(-1)
    picks = [0, len(flat) // 3, len(flat) // 2, len(flat) - 1]
    direction = list(image.GetDirection())
    if image.GetDimension() == 2:
        direction = [direction[0], direction[1], 0.0, direction[2], direction[3], 0.0, 0.0, 0.0, 1.0]
    origin = list(image.GetOrigin()) + [0.0] * (3 - image.GetDimension())
    spacing = list(image.GetSpacing()) + [1.0] * (3 - image.GetDimension())
    return {
        "dims": size,
        "origin": origin,
        "spacing": spacing,
        "direction": direction,
        "sum": float(flat.sum()),
        "picks": {str(i): float(flat[i]) for i in picks},
    }


def oblique_direction():
    a, b = math.radians(25.0), math.radians(-15.0)
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    return rz @ ry


def write_volumes(out, manifest):
    import SimpleITK as sitk

    values = (np.arange(7 * 6 * 5, dtype=np.float64).reshape(5, 6, 7) * 3.0 - 100.0)  # z, y, x
    direction = oblique_direction()
    for pixel in ("float32", "int16", "uint8"):
        data = values.astype(pixel) if pixel == "float32" else np.clip(values, 0 if pixel == "uint8" else -1000, 250).astype(pixel)
        image = sitk.GetImageFromArray(data)
        image.SetSpacing((0.8, 1.25, 2.5))
        image.SetOrigin((-12.5, 40.0, 7.75))
        image.SetDirection(direction.flatten().tolist())
        for ext in ("mha", "mhd", "nrrd", "nhdr", "nii", "nii.gz"):
            for compressed in (False, True):
                if ext in ("nii",) and compressed:
                    continue
                name = f"sitk_{pixel}_{'z' if compressed else 'raw'}.{ext}"
                sitk.WriteImage(image, os.path.join(out, name), useCompression=compressed)
                manifest[name] = dict(itk_geometry(os.path.join(out, name)), kind="volume", tool="SimpleITK")
    write_nibabel(out, manifest, values)
    write_pynrrd(out, manifest, values)


def write_nibabel(out, manifest, values):
    import nibabel as nib

    data = np.ascontiguousarray(values.transpose(2, 1, 0)).astype(np.float32)  # x, y, z
    affine = np.eye(4)
    affine[:3, :3] = oblique_direction() @ np.diag([0.8, 1.25, 2.5])
    affine[:3, 3] = [12.5, -40.0, 7.75]
    cases = {
        "nibabel_default.nii.gz": {},
        "nibabel_sform_only.nii": {"sform": 1, "qform": 0},
        "nibabel_qform_only.nii": {"sform": 0, "qform": 1},
        # The sform aligned (code 2) and a different qform (code 1): ITK takes the qform.
        "nibabel_sform_aligned_qform_scanner.nii": {"sform": 2, "qform": 1, "shift": 30.0},
    }
    for name, case in cases.items():
        image = nib.Nifti1Image(data, affine)
        if case:
            sform = affine.copy()
            sform[0, 3] += case.get("shift", 0.0)
            image.set_sform(sform, code=case["sform"])
            image.set_qform(affine, code=case["qform"])
        nib.save(image, os.path.join(out, name))
        manifest[name] = dict(itk_geometry(os.path.join(out, name)), kind="volume", tool="nibabel")


def write_pynrrd(out, manifest, values):
    import nrrd

    data = np.ascontiguousarray(values.transpose(2, 1, 0)).astype(np.float32)  # x, y, z (Fortran)
    directions = (oblique_direction() @ np.diag([0.8, 1.25, 2.5])).T
    for space in ("left-posterior-superior", "right-anterior-superior", "left-anterior-superior"):
        for encoding in ("raw", "gzip", "ascii"):
            name = f"pynrrd_{''.join(w[0] for w in space.split('-'))}_{encoding}.nrrd"
            header = {"space": space, "space directions": directions, "space origin": np.array([5.0, -6.0, 7.5]), "encoding": encoding, "kinds": ["domain"] * 3}
            nrrd.write(os.path.join(out, name), data, header, index_order="F")
            manifest[name] = dict(itk_geometry(os.path.join(out, name)), kind="volume", tool="pynrrd")
    name = "pynrrd_detached.nhdr"
    nrrd.write(os.path.join(out, name), data, {"space": "left-posterior-superior", "space directions": directions, "space origin": np.array([1.0, 2.0, 3.0]), "encoding": "gzip"}, detached_header=True, index_order="F")
    manifest[name] = dict(itk_geometry(os.path.join(out, name)), kind="volume", tool="pynrrd")


def read_defvol_files(folder):
    """What each tool finds in the files defvol wrote."""
    import SimpleITK as sitk

    found = {}
    for name in sorted(os.listdir(folder)):
        path = os.path.join(folder, name)
        entry = {}
        try:
            if name.endswith((".mha", ".mhd", ".nrrd", ".nii", ".nii.gz")):
                entry["SimpleITK"] = itk_geometry(path)
                if name.endswith((".nii", ".nii.gz")):
                    import nibabel as nib

                    image = nib.load(path)
                    data = np.asarray(image.dataobj, dtype=np.float64)
                    entry["nibabel"] = {"shape": list(data.shape), "sum": float(data.sum()), "affine": image.affine.tolist(), "first": float(data[0, 0, 0])}
                if name.endswith(".nrrd"):
                    import nrrd

                    data, header = nrrd.read(path, index_order="F")
                    entry["pynrrd"] = {"shape": list(data.shape), "sum": float(np.asarray(data, dtype=np.float64).sum()), "space": header.get("space"), "space origin": np.asarray(header["space origin"]).tolist(), "space directions": np.asarray(header["space directions"]).tolist()}
            elif name.endswith((".vtu", ".vtk", ".msh")):
                import meshio

                mesh = meshio.read(path)
                tets = mesh.cells_dict.get("tetra")
                entry["meshio"] = {"points": mesh.points.tolist(), "tets": tets.tolist() if tets is not None else [], "arrays": sorted(mesh.point_data), "field_data": {k: np.asarray(v).ravel().tolist() for k, v in mesh.field_data.items()}}
                if name.endswith((".vtu", ".vtk")):
                    import vtk

                    reader = vtk.vtkXMLUnstructuredGridReader() if name.endswith(".vtu") else vtk.vtkUnstructuredGridReader()
                    reader.SetFileName(path)
                    reader.Update()
                    grid = reader.GetOutput()
                    fields = grid.GetFieldData()
                    field_data = {fields.GetArrayName(i): [fields.GetArray(i).GetValue(j) for j in range(fields.GetArray(i).GetNumberOfValues())] for i in range(fields.GetNumberOfArrays())}
                    entry["vtk"] = {"points": grid.GetNumberOfPoints(), "cells": grid.GetNumberOfCells(), "first": list(grid.GetPoint(0)), "last": list(grid.GetPoint(grid.GetNumberOfPoints() - 1)), "field_data": field_data}
                if name.endswith(".msh"):
                    import gmsh

                    gmsh.initialize(["-noenv"])
                    gmsh.option.setNumber("General.Terminal", 0)
                    gmsh.open(path)
                    types, _, nodes = gmsh.model.mesh.getElements(3)
                    tets = [len(n) // 4 for t, n in zip(types, nodes) if t == 4]
                    entry["gmsh"] = {"tets": sum(tets), "nodes": len(gmsh.model.mesh.getNodes()[0])}
                    gmsh.finalize()
        except Exception as e:  # a tool that cannot read a file says why
            entry["error"] = f"{type(e).__name__}: {e}"
        if entry:
            found[name] = entry
    return found


def main():
    command, folder = sys.argv[1], sys.argv[2]
    if command == "write":
        manifest = {}
        write_meshes(folder, manifest)
        write_volumes(folder, manifest)
        print(json.dumps(manifest))
    elif command == "read":
        print(json.dumps(read_defvol_files(folder)))
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main()
