# What the peer scripts share, sourced by run.sh and render.sh: `peer_venv NAME REQUIREMENTS`
# makes (or reuses) a virtual environment in defvol's cache and sets $venv; `peer_defvol`
# sets $bin to DEFVOL_BIN or the release binary, built.
cache="${DEFVOL_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/defvol}"

peer_venv() {
    venv="$cache/$1"
    if [ "$(cat "$venv/.requirements" 2>/dev/null)" != "$2" ]; then
        rm -rf "$venv" && python3 -m venv "$venv"
        "$venv/bin/pip" install -q $2
        echo "$2" > "$venv/.requirements"
    fi
}

peer_defvol() {
    bin="${DEFVOL_BIN:-}"
    if [ -z "$bin" ]; then
        export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$cache/target}"
        cargo build --locked --release --bin defvol >&2
        bin="$CARGO_TARGET_DIR/release/defvol"
    fi
}
