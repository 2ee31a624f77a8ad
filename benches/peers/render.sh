#!/usr/bin/env bash
# The CPU volume raycaster against VTK's fixed-point CPU ray caster, side by side in one
# run: `defvol bench render` (the phantom, point-sampled and pre-integrated, unshaded) and
# vtkFixedPointVolumeRayCastMapper (vtk_render.py) on exactly the same work (volume,
# camera, transfer function, step, image size, threads), both scored against defvol's f64
# reference with the same PSNR (compare_render.py). A table on stdout, one JSON object a
# case and step on stderr.
# Outside the test command: VTK comes from PyPI into its own virtual environment.
# Usage: benches/peers/render.sh [SIZES] [STEPS] [RUNS]   (default 512 1,1.25 7)
# DEFVOL_BIN names a built defvol; else the release binary is built.
set -euo pipefail
cd "$(dirname "$0")/../.."
sizes="${1:-512}" steps="${2:-1,1.25}" runs="${3:-7}"
requirements="vtk==9.7.2 numpy==1.26.4"
. benches/peers/common.sh
peer_venv peers-vtk-venv "$requirements"
peer_defvol
threads=$(nproc)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$bin" bench render --sizes "$sizes" --steps "$steps" --runs "$runs" --no-warped --meshes --source-meshes \
    --export "$work" --json > "$work/defvol.jsonl"
python3 benches/peers/compare_render.py "$work" "$venv/bin/python" "$threads" "$runs"
