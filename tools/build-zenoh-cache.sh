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
# Cold build on 2 shared cores: see docs/hil.md, "A real router and DDS bridge".
set -euo pipefail
version=1.10.2
root="${XDG_CACHE_HOME:-$HOME/.cache}/platoon-cosim/zenoh-$version"
jobs="${CARGO_BUILD_JOBS:-2}"
mkdir -p "$root/lib" "$root/build"
if [ ! -x "$root/bin/zenohd" ]; then
  echo "+ cargo install zenohd --version $version --locked --root $root"
  nice -n 19 cargo install zenohd --version "$version" --locked --root "$root" -j "$jobs"
fi
if [ ! -e "$root/lib/libzenoh_plugin_ros2dds.so" ]; then
  # A library crate: cargo install builds only binaries, so the published source is built in place, with
  # the Cargo.lock it ships (--locked), its checksum checked against the one crates.io's index records.
  crate="$root/build/zenoh-plugin-ros2dds-$version.crate"
  curl -fsSL -o "$crate" "https://static.crates.io/crates/zenoh-plugin-ros2dds/zenoh-plugin-ros2dds-$version.crate"
  echo "1e7d42cc7ed61b792194e3f1862241721fa6577b4d171412a64486c1ac53c7e9  $crate" | sha256sum -c --quiet -
  tar -xzf "$crate" -C "$root/build"
  echo "+ cargo build --release --locked (zenoh-plugin-ros2dds $version)"
  (cd "$root/build/zenoh-plugin-ros2dds-$version" &&
     CARGO_TARGET_DIR="$root/build/target" nice -n 19 cargo build --release --locked -j "$jobs")
  cp "$root/build/target/release/libzenoh_plugin_ros2dds.so" "$root/lib/"
fi
echo "$root/bin/zenohd"
echo "$root/lib/libzenoh_plugin_ros2dds.so"
