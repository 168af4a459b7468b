#!/usr/bin/env bash
# Build, once per machine, the real parts a lab puts between a run and its robots, for the slow tests that
# drive a robot through them (tests/test_zenoh_router.py): the Zenoh router zenohd and the ROS 2 / DDS plugin
# zenohd loads (zenoh-plugin-ros2dds, the plugin of zenoh-bridge-ros2dds), both at the version of the zenoh
# Python package, into a cache outside the repository:
#   ${XDG_CACHE_HOME:-~/.cache}/platoon-cosim/zenoh-1.10.2/bin/zenohd
#   ${XDG_CACHE_HOME:-~/.cache}/platoon-cosim/zenoh-1.10.2/lib/libzenoh_plugin_ros2dds.so
# Needs: cargo (rustup), a C compiler, cmake and libclang (the plugin builds CycloneDDS through cyclors,
# whose bindings are made by bindgen; on Debian: apt-get install cmake libclang-dev).
# The plugin must come from the same rustc and the same zenoh features as zenohd (zenohd refuses a plugin
# built otherwise), so both are built here with the toolchain on PATH; rerun after a toolchain change.
# Everything is fetched by cargo's own client from the registry cargo is configured with (its index checks
# each crate's checksum); the build runs at nice 19 and each part says how long it took.
# Cold build on 2 shared cores: see docs/hil.md, "A real router and DDS bridge".
set -euo pipefail
version=1.10.2
root="${XDG_CACHE_HOME:-$HOME/.cache}/platoon-cosim/zenoh-$version"
jobs="${CARGO_BUILD_JOBS:-2}"
mkdir -p "$root/lib" "$root/build"
if [ ! -x "$root/bin/zenohd" ]; then
  echo "+ cargo install zenohd --version $version --locked --root $root"
  time nice -n 19 cargo install zenohd --version "$version" --locked --root "$root" -j "$jobs"
fi
if [ ! -e "$root/lib/libzenoh_plugin_ros2dds.so" ]; then
  # A library crate: cargo install builds only binaries. So a manifest that depends on the plugin has cargo
  # fetch and unpack its published source (cargo metadata says where), which is then built in place with the
  # Cargo.lock it ships (--locked).
  fetcher="$root/build/fetch-plugin"
  mkdir -p "$fetcher/src"
  : >"$fetcher/src/lib.rs"
  cat >"$fetcher/Cargo.toml" <<EOF
[package]
name = "fetch-zenoh-plugin-ros2dds"
version = "0.0.0"
edition = "2021"
publish = false

[dependencies]
zenoh-plugin-ros2dds = "=$version"
EOF
  echo "+ cargo fetch (zenoh-plugin-ros2dds $version)"
  nice -n 19 cargo fetch --manifest-path "$fetcher/Cargo.toml"
  manifest=$(cargo metadata --format-version 1 --manifest-path "$fetcher/Cargo.toml" |
    python3 -c 'import json, sys; print(next(p["manifest_path"] for p in json.load(sys.stdin)["packages"]
                if p["name"] == "zenoh-plugin-ros2dds"))')
  echo "+ cargo build --release --locked --manifest-path $manifest"
  time CARGO_TARGET_DIR="$root/build/target" nice -n 19 cargo build --release --locked -j "$jobs" \
    --manifest-path "$manifest"
  cp "$root/build/target/release/libzenoh_plugin_ros2dds.so" "$root/lib/"
fi
echo "$root/bin/zenohd"
echo "$root/lib/libzenoh_plugin_ros2dds.so"
