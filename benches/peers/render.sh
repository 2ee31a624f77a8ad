#!/usr/bin/env bash
# The CPU volume raycaster against VTK's fixed-point CPU ray caster, side by side in one
# run: `defvol bench render` (the phantom, point-sampled and pre-integrated, unshaded) and
# vtkFixedPointVolumeRayCastMapper (vtk_render.py) on exactly the same work (volume,
# camera, transfer function, step, image size, threads), both scored against defvol's f64
# reference with the same PSNR (compare_render.py). The two take turns, ROUNDS times, so
# that both see the host in the same state (on a shared 2-core VM, VTK's median alone moved
# 120-181 ms between three runs of the script); each round's ratio comes from its own two
# medians. A second table compares at equal accuracy (defvol's fastest run at VTK's PSNR
# or above). Tables on stdout, one JSON object a comparison on stderr.
# Outside the test command: VTK comes from PyPI into its own virtual environment.
# Usage: benches/peers/render.sh [SIZES] [STEPS] [RUNS] [ROUNDS]   (default 512 1,1.25 7 3)
# DEFVOL_BIN names a built defvol; else the release binary is built.
set -euo pipefail
cd "$(dirname "$0")/../.."
sizes="${1:-512}" steps="${2:-1,1.25}" runs="${3:-7}" rounds="${4:-3}"
if ! [[ "$rounds" =~ ^[1-9][0-9]*$ ]]; then
    echo "render.sh: ROUNDS must be a whole number of at least 1, not '$rounds'" >&2
    exit 2
fi
requirements="vtk==9.7.2 numpy==1.26.4"
. benches/peers/common.sh
peer_venv peers-vtk-venv "$requirements"
peer_defvol
threads=$(nproc)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
for round in $(seq "$rounds"); do
    # The first round writes the work (volume, camera, table, reference) VTK then reads.
    export_to=()
    [ "$round" -eq 1 ] && export_to=(--export "$work/cases")
    "$bin" bench render --sizes "$sizes" --steps "$steps" --runs "$runs" --no-warped --meshes --source-meshes \
        "${export_to[@]}" --json > "$work/defvol-$round.jsonl"
    for case in "$work"/cases/*/; do
        # VTK logs to stderr on a machine without a display: kept aside, shown if it fails.
        if ! "$venv/bin/python" benches/peers/vtk_render.py "$case" "$threads" "$runs" \
            > "$work/vtk.out" 2> "$work/vtk.err"; then
            cat "$work/vtk.err" >&2
            exit 1
        fi
        grep '^{' "$work/vtk.out" >> "$work/vtk-$round.jsonl"
    done
done
python3 benches/peers/compare_render.py "$work" "$rounds" "$threads"
