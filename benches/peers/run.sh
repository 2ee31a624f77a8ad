#!/usr/bin/env bash
# The CPU warp against its peers, side by side in one run: `defvol bench warp` (spans,
# trilinear) and Taichi's CPU kernel (taichi_warp.py) on exactly the same work, on the same
# threads, with each one's error against defvol's f64 reference and the speed ratio.
# Outside the test command: Taichi comes from PyPI into its own virtual environment.
# Usage: benches/peers/run.sh [TETS] [CASES] [RUNS]   (default 700 rot45,upright,bend 9)
# DEFVOL_BIN names a built defvol; else the release binary is built.
set -euo pipefail
cd "$(dirname "$0")/../.."
tets="${1:-700}" cases="${2:-rot45,upright,bend}" runs="${3:-9}"
cache="${DEFVOL_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/defvol}"
requirements="taichi==1.7.4 numpy==1.26.4"
venv="$cache/peers-venv"
if [ "$(cat "$venv/.requirements" 2>/dev/null)" != "$requirements" ]; then
    rm -rf "$venv" && python3 -m venv "$venv"
    "$venv/bin/pip" install -q $requirements
    echo "$requirements" > "$venv/.requirements"
fi
bin="${DEFVOL_BIN:-}"
if [ -z "$bin" ]; then
    export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$cache/target}"
    cargo build --locked --release --bin defvol >&2
    bin="$CARGO_TARGET_DIR/release/defvol"
fi
threads=$(nproc)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$bin" bench warp --tets "$tets" --cases "$cases" --schemes spans --runs "$runs" --export "$work" --json \
    > "$work/defvol.jsonl"
printf '%-34s %12s %12s %8s %12s %12s\n' case "defvol ms" "taichi ms" ratio "defvol err" "taichi err"
while read -r row; do
    case_name=$(python3 -c 'import json,sys; r=json.loads(sys.argv[1]); print(r["case"]+"_"+r["params"]["sampling"])' "$row")
    # The last line: Taichi prints its banner on import.
    peer=$("$venv/bin/python" benches/peers/taichi_warp.py "$work/$case_name" "$threads" "$runs" | tail -n 1)
    python3 - "$row" "$peer" <<'PY'
import json, sys
ours, peer = json.loads(sys.argv[1]), json.loads(sys.argv[2])
a, b = ours["time_ms"]["median"], peer["time_ms"]["median"]
print(f'{ours["case"]:<34} {a:12.2f} {b:12.2f} {b / a:7.1f}x {ours["error"]["value"]:12.2e} {peer["error"]["value"]:12.2e}')
print(json.dumps({"stage": "warp", "case": ours["case"], "peer": "taichi", "threads": peer["threads"],
                  "defvol_median_ms": a, "peer_median_ms": b, "ratio": b / a, "peer": peer}), file=sys.stderr)
PY
done < <(grep '"backend":"cpu"' "$work/defvol.jsonl")
