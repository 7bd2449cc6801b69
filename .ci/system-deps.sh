#!/usr/bin/env bash
# System libraries simgen needs beyond its Python wheels, on Debian/Ubuntu.
#
# Offscreen rendering (simgen.io.render): the VTK wheel (9.4+) loads OpenGL at run time and, with no
# X display, renders through EGL. Mesa's software EGL needs
#   libegl1          the EGL loader (libglvnd, libEGL.so.1) that VTK dlopens
#   libegl-mesa0     Mesa's EGL vendor library (surfaceless platform, no display needed)
#   libgl1-mesa-dri  Mesa's DRI drivers, including swrast/llvmpipe, the CPU rasteriser EGL loads
# Video encoding needs nothing here: imageio-ffmpeg ships its own ffmpeg binary.
# The viewer's browser test (tests/test_view.py) needs
#   chromium         headless Chromium (/usr/bin/chromium), WebGL through its bundled SwiftShader
#
# Idempotent: installs only what is missing, prints nothing when everything is present.
set -euo pipefail

packages=(libegl1 libegl-mesa0 libgl1-mesa-dri chromium)

if ! command -v dpkg-query >/dev/null 2>&1; then
    echo "system-deps: not a Debian-based system; install EGL (Mesa) and Chromium yourself" >&2
    exit 0
fi

missing=()
for pkg in "${packages[@]}"; do
    status=$(dpkg-query -W -f='${db:Status-Status}' "$pkg" 2>/dev/null || true)
    [[ "$status" == "installed" ]] || missing+=("$pkg")
done
[[ ${#missing[@]} -eq 0 ]] && exit 0

if [[ $(id -u) -eq 0 ]]; then
    sudo=()
elif command -v sudo >/dev/null 2>&1; then
    sudo=(sudo)
else
    echo "system-deps: missing ${missing[*]}; run this script as root to install them" >&2
    exit 1
fi

echo "system-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
"${sudo[@]}" apt-get update -qq
"${sudo[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
