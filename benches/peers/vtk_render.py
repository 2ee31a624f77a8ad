"""VTK's fixed-point CPU ray caster (vtkFixedPointVolumeRayCastMapper) on exactly the work
`defvol bench render` times (same volume, camera, transfer function, step, image size and
background, written by `defvol bench render --export DIR`), on the same threads, scored
against the same f64 reference with the same PSNR.

The mapper runs as a VTK user would set it up for a fair comparison: trilinear, unshaded,
the sample distance fixed (no automatic adjustment), one ray per pixel, the opacity given
per unit length (ScalarOpacityUnitDistance 1) exactly as defvol's transfer function is.

usage: vtk_render.py CASE_DIR THREADS RUNS   prints one JSON object per step
"""

import json
import os
import statistics
import sys
import time

import numpy as np
import vtk
from vtk.util import numpy_support


def load(case_dir):
    meta = json.load(open(os.path.join(case_dir, "case.json")))
    nx, ny, nz = meta["dims"]
    volume = np.fromfile(os.path.join(case_dir, "volume.f32"), dtype=np.float32)
    reference = np.fromfile(os.path.join(case_dir, "reference.f64"), dtype=np.float64)
    assert volume.size == nx * ny * nz, "volume.f32 does not match case.json's dims"
    return meta, volume, reference.reshape(meta["height"], meta["width"], 4)


def scene(meta, volume, threads):
    image = vtk.vtkImageData()
    image.SetDimensions(*meta["dims"])
    image.SetSpacing(*meta["spacing"])
    image.SetOrigin(*meta["origin"])
    image.GetPointData().SetScalars(numpy_support.numpy_to_vtk(volume, deep=1))
    mapper = vtk.vtkFixedPointVolumeRayCastMapper()
    mapper.SetInputData(image)
    mapper.AutoAdjustSampleDistancesOff()
    mapper.SetImageSampleDistance(1.0)
    mapper.SetNumberOfThreads(threads)
    prop = vtk.vtkVolumeProperty()
    opacity, color = vtk.vtkPiecewiseFunction(), vtk.vtkColorTransferFunction()
    for p in meta["tf"]:
        opacity.AddPoint(p["value"], p["opacity"])
        color.AddRGBPoint(p["value"], *p["color"])
    prop.SetScalarOpacity(opacity)
    prop.SetColor(color)
    prop.SetScalarOpacityUnitDistance(1.0)
    prop.SetInterpolationTypeToLinear()
    prop.ShadeOff()
    actor = vtk.vtkVolume()
    actor.SetMapper(mapper)
    actor.SetProperty(prop)
    renderer = vtk.vtkRenderer()
    renderer.AddVolume(actor)
    renderer.SetBackground(*meta["background"][:3])
    camera = renderer.GetActiveCamera()
    camera.SetPosition(*meta["camera"]["eye"])
    camera.SetFocalPoint(*meta["camera"]["focal_point"])
    camera.SetViewUp(*meta["camera"]["up"])
    camera.SetViewAngle(meta["camera"]["fov_y_deg"])
    renderer.ResetCameraClippingRange()
    window = vtk.vtkRenderWindow()
    window.SetOffScreenRendering(1)
    window.AddRenderer(renderer)
    window.SetSize(meta["width"], meta["height"])
    return window, mapper


def read_back(window, meta):
    grab = vtk.vtkWindowToImageFilter()
    grab.SetInput(window)
    grab.SetInputBufferTypeToRGB()
    grab.ReadFrontBufferOff()
    grab.Update()
    rgb = numpy_support.vtk_to_numpy(grab.GetOutput().GetPointData().GetScalars())
    # VTK's rows run bottom to top; defvol's top to bottom.
    return rgb.reshape(meta["height"], meta["width"], 3)[::-1]


def psnr(rgb, reference):
    """defvol's `Rendered::psnr`: RGB in 0..255 levels against the reference clamped to 0..1."""
    diff = rgb.astype(np.float64) - np.clip(reference[..., :3], 0.0, 1.0) * 255.0
    return 10.0 * np.log10(255.0 * 255.0 / max(np.mean(diff * diff), 1e-12))


def main():
    case_dir, threads, runs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    meta, volume, reference = load(case_dir)
    window, mapper = scene(meta, volume, threads)
    for step in meta["steps"]:
        mapper.SetSampleDistance(step)
        window.Render()  # settle: builds the mapper's tables and space-leaping grid
        samples, mapper_ms = [], []
        for _ in range(runs):
            start = time.perf_counter()
            window.Render()
            samples.append((time.perf_counter() - start) * 1e3)
            mapper_ms.append(mapper.GetTimeToDraw() * 1e3)
        print(json.dumps({
            "peer": f"vtk {vtk.vtkVersion.GetVTKVersion()} vtkFixedPointVolumeRayCastMapper",
            "case": meta["case"], "step_mm": step, "threads": threads,
            "time_ms": {"median": statistics.median(samples), "min": min(samples), "runs": runs},
            "mapper_ms": statistics.median(mapper_ms),
            "error": {"metric": "psnr_db", "value": psnr(read_back(window, meta), reference)},
        }))


if __name__ == "__main__":
    main()
