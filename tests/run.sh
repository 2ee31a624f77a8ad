#!/usr/bin/env bash
# The whole test suite on a fresh Debian machine: installs what the tests need, then runs them.
# Usage: tests/run.sh   (from anywhere; extra arguments go to `cargo test`)
set -euo pipefail
cd "$(dirname "$0")/.."

as_root() { if [ "$(id -u)" -eq 0 ]; then "$@"; else sudo "$@"; fi; }

# Software Vulkan (lavapipe) so the GPU kernels run and are checked against their CPU twins.
if ! ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1; then
    echo "tests/run.sh: installing mesa-vulkan-drivers (software Vulkan adapter)"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mesa-vulkan-drivers >/dev/null
fi
if ! command -v cargo >/dev/null 2>&1; then
    echo "tests/run.sh: cargo is required (https://rustup.rs)" >&2
    exit 1
fi

export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
# GPU tests must run, not skip, once the adapter is installed.
export DEFVOL_REQUIRE_GPU=1
cargo test --locked "$@"
