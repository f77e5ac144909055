#!/usr/bin/env bash
# Debian packages the project needs at run time: Mesa's software EGL/GL for the ground-truth mesh
# renderer (moderngl), redis-server for the
# queue's Redis mode tests, Chromium with its WebDriver for the web page's browser test (a
# browser downloaded at test time does not work offline), Node.js for the page scripts' quick
# tests (tests/test_page_scripts.py), and g++ with ninja, which build the
# C++ kernels of the rasterizer and the skinning (eva_engine/native.py; without them the slower torch kernels
# run). Installs only what is missing.
set -euo pipefail
pkgs=(libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri redis-server chromium chromium-driver nodejs g++ ninja-build)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
echo "installing Debian packages: ${missing[*]}"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null || { echo "need root (or sudo) to apt-get install: ${missing[*]}" >&2; exit 1; }
  SUDO=sudo
fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
