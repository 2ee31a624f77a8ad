#!/usr/bin/env bash
# The CPU warp against its peers, side by side in one run: `defvol bench warp` (spans,
# trilinear) and Taichi's CPU kernel
# (taichi_warp.py) on exactly the same work, on the same threads, with each one's error
# against defvol's f64 reference and the speed ratio (compare.py). A table on stdout, one
# JSON object a case on stderr.
# Outside the test command: Taichi comes from PyPI into its own virtual environment.
# Usage: benches/peers/run.sh [TETS] [CASES] [RUNS]   (default 700 rot45,upright,bend 9)
# DEFVOL_BIN names a built defvol; else the release binary is built.
set -euo pipefail
cd "$(dirname "$0")/../.."
tets="${1:-700}" cases="${2:-rot45,upright,bend}" runs="${3:-9}"
requirements="taichi==1.7.4 numpy==1.26.4"
. benches/peers/common.sh
peer_venv peers-venv "$requirements"
peer_defvol
threads=$(nproc)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$bin" bench warp --tets "$tets" --cases "$cases" --schemes spans --runs "$runs" --export "$work" \
    --json > "$work/defvol.jsonl"
python3 benches/peers/compare.py "$work" "$venv/bin/python" "$threads" "$runs"
