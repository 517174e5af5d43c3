#!/usr/bin/env bash
# Installs everything plvo needs on a fresh Debian machine: system packages, a virtualenv in .venv, the package.
#   scripts/setup.sh          runtime (libusb for open3d, libgl/libgomp)
#   scripts/setup.sh --test   also the test extras and headless Chromium for the viewer test
# Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."

want_test=0
[ "${1:-}" = "--test" ] && want_test=1

pkgs=(libusb-1.0-0 libgl1 libgomp1)
[ $want_test = 1 ] && pkgs+=(chromium)
missing=()
for p in "${pkgs[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""
  [ "$(id -u)" != 0 ] && SUDO="sudo"
  echo "setup: installing system packages: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
extras="compare"
[ $want_test = 1 ] && extras="test,compare"
stamp=".venv/.plvo-installed-$extras"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ constraints.txt -nt "$stamp" ]; then
  echo "setup: installing plvo[$extras] into .venv"
  # pip fails half-way with a bare OSError on a full disk; say why first (the venv takes ~3 GB, pip unpacks in TMPDIR)
  for d in . "${TMPDIR:-/tmp}"; do
    free_mb=$(df -Pm "$d" | awk 'NR==2 {print $4}')
    if [ "${free_mb:-0}" -lt 4000 ]; then
      echo "setup: warning: only ${free_mb} MB free on $(cd "$d" && pwd); installing plvo needs about 4000 MB" >&2
    fi
  done
  # constraints.txt: the exact versions the suite passes with; pyproject.toml only states ranges
  .venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt -e ".[$extras]"
  # map-closures (lidar place recognition) and kiss-slam (the lidar-only SLAM compared with) pin numpy < 2.3,
  # pydantic < 2.14 and typer < 0.26 although they run on the versions above (tests/plvo/loop/test_lidar_place.py,
  # tests/plvo_eval/test_kiss_slam.py); installed without their dependency pins so that pip keeps ours
  .venv/bin/python -m pip install -q --disable-pip-version-check --no-deps -c constraints.txt map-closures kiss-slam
  touch "$stamp"
fi
