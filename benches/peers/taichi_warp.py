"""Taichi's warp kernel, on the CPU or on CUDA, on exactly the work `defvol bench warp` times
(same phantom, mesh, deformation and output grid, written by `defvol bench warp --export
DIR`), timed on the same threads, with its agreement to defvol's f64 reference.

The kernel is the seed paper's algorithm as a Taichi user writes it: the grid filled with the
background, then for each tet (the parallel loop) every voxel of its bounding box tested by
its barycentric coordinates and, inside, the source sampled trilinearly at the same
coordinates in the rest tet.

usage: taichi_warp.py CASE_DIR THREADS RUNS [ARCH]   prints one JSON object (ARCH: cpu, the
default, or cuda: then the inputs live on the GPU and the read-back is timed apart)
"""

import json
import os
import statistics
import sys
import time

import numpy as np
import taichi as ti


def load(case_dir):
    meta = json.load(open(os.path.join(case_dir, "case.json")))
    raw = lambda name, dtype: np.fromfile(os.path.join(case_dir, name), dtype=dtype)
    sx, sy, sz = meta["source_dims"]
    ox, oy, oz = meta["out_dims"]
    return {
        "meta": meta,
        "source": raw("source.f32", np.float32).reshape(sz, sy, sx),
        "tets": raw("tets.u32", np.uint32).astype(np.int32).reshape(-1, 4),
        "rest": raw("rest_index.f64", np.float64).astype(np.float32).reshape(-1, 3),
        "deformed": raw("deformed_index.f64", np.float64).astype(np.float32).reshape(-1, 3),
        "reference": raw("reference.f32", np.float32).reshape(oz, oy, ox),
    }


@ti.kernel
def fill(out: ti.types.ndarray(dtype=ti.f32, ndim=3), background: ti.f32):
    for k, j, i in out:
        out[k, j, i] = background


@ti.func
def trilinear(src: ti.types.ndarray(dtype=ti.f32, ndim=3), x: ti.f32, y: ti.f32, z: ti.f32) -> ti.f32:
    nz, ny, nx = src.shape
    i = ti.min(ti.max(ti.cast(ti.floor(x), ti.i32), 0), nx - 2)
    j = ti.min(ti.max(ti.cast(ti.floor(y), ti.i32), 0), ny - 2)
    k = ti.min(ti.max(ti.cast(ti.floor(z), ti.i32), 0), nz - 2)
    fx, fy, fz = x - i, y - j, z - k
    c00 = src[k, j, i] * (1 - fx) + src[k, j, i + 1] * fx
    c10 = src[k, j + 1, i] * (1 - fx) + src[k, j + 1, i + 1] * fx
    c01 = src[k + 1, j, i] * (1 - fx) + src[k + 1, j, i + 1] * fx
    c11 = src[k + 1, j + 1, i] * (1 - fx) + src[k + 1, j + 1, i + 1] * fx
    return (c00 * (1 - fy) + c10 * fy) * (1 - fz) + (c01 * (1 - fy) + c11 * fy) * fz


@ti.kernel
def rasterize(out: ti.types.ndarray(dtype=ti.f32, ndim=3), src: ti.types.ndarray(dtype=ti.f32, ndim=3),
              tets: ti.types.ndarray(dtype=ti.i32, ndim=2), rest: ti.types.ndarray(dtype=ti.f32, ndim=2),
              deformed: ti.types.ndarray(dtype=ti.f32, ndim=2)):
    nz, ny, nx = out.shape
    for t in range(tets.shape[0]):
        p = [ti.Vector([deformed[tets[t, v], 0], deformed[tets[t, v], 1], deformed[tets[t, v], 2]]) for v in range(4)]
        q = [ti.Vector([rest[tets[t, v], 0], rest[tets[t, v], 1], rest[tets[t, v], 2]]) for v in range(4)]
        d = ti.Matrix.cols([p[1] - p[0], p[2] - p[0], p[3] - p[0]])
        r = ti.Matrix.cols([q[1] - q[0], q[2] - q[0], q[3] - q[0]])
        if ti.abs(d.determinant()) > 1e-9:
            inv = d.inverse()
            lo = ti.max(ti.ceil(ti.min(p[0], p[1], p[2], p[3]) - 1e-6), 0)
            hi = ti.min(ti.floor(ti.max(p[0], p[1], p[2], p[3]) + 1e-6), ti.Vector([nx - 1, ny - 1, nz - 1]))
            for k in range(ti.cast(lo[2], ti.i32), ti.cast(hi[2], ti.i32) + 1):
                for j in range(ti.cast(lo[1], ti.i32), ti.cast(hi[1], ti.i32) + 1):
                    for i in range(ti.cast(lo[0], ti.i32), ti.cast(hi[0], ti.i32) + 1):
                        b = inv @ (ti.Vector([i, j, k], ti.f32) - p[0])
                        if b.min() >= -1e-6 and b.sum() <= 1 + 1e-6:
                            s = q[0] + r @ b
                            out[k, j, i] = trilinear(src, s[0], s[1], s[2])


def main():
    case_dir, threads, runs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    arch = sys.argv[4] if len(sys.argv) > 4 else "cpu"
    ti.init(arch=getattr(ti, arch), cpu_max_num_threads=threads, log_level=ti.ERROR)
    work = load(case_dir)
    background = float(work["meta"]["background"])
    if arch == "cpu":
        out, args = np.empty_like(work["reference"]), [work[k] for k in ("source", "tets", "rest", "deformed")]
        read_back = lambda: out
    else:
        # On a GPU the inputs stay on the device, as defvol's do; the deformed positions go up
        # each step and the picture comes back only in the runs timed with read-back.
        out = ti.ndarray(ti.f32, work["reference"].shape)
        args = []
        for name, dtype in (("source", ti.f32), ("tets", ti.i32), ("rest", ti.f32), ("deformed", ti.f32)):
            array = ti.ndarray(dtype, work[name].shape)
            array.from_numpy(work[name])
            args.append(array)
        read_back = out.to_numpy

    def once(with_read_back):
        if arch != "cpu":
            args[3].from_numpy(work["deformed"])
        fill(out, background)
        rasterize(out, *args)
        ti.sync()
        return read_back() if with_read_back else None

    once(True)  # compiles the kernels
    timed = {}
    for with_read_back in (False, True):
        times = []
        for _ in range(runs):
            start = time.perf_counter()
            picture = once(with_read_back)
            times.append((time.perf_counter() - start) * 1e3)
        timed[with_read_back] = {"min": min(times), "median": statistics.median(times), "max": max(times)}
    low, high = work["meta"]["source_range"]
    error = float(np.abs(picture.astype(np.float64) - work["reference"]).max()) / (high - low)
    differ = int(np.count_nonzero(np.abs(picture - work["reference"]) > 1e-3 * (high - low)))
    print(json.dumps({"peer": "taichi", "version": ".".join(map(str, ti.__version__)), "arch": arch,
                      "threads": threads, "runs": runs, "time_ms": timed[False], "with_read_back_ms": timed[True],
                      "error": {"metric": "max_abs_over_range", "value": error, "reference": "f64"},
                      "voxels_differing": differ, "voxels": int(picture.size)}))


if __name__ == "__main__":
    main()
