#!/usr/bin/env bash
# Installs what crisp-gym needs on a fresh Debian/Ubuntu machine: system libraries for
# Open3D (libusb) and headless rendering (EGL/OSMesa), Chromium (the tests open the HTML reports
# in it), then the package itself (editable, so that edits to the checkout take effect; reconstruct/,
# train/ and assets/ install under crisp_gym) with its test and video extras,
# and MediaPipe for the video path in its private folder.
# PyTorch is pinned first: an unpinned torch would pull several GB of CUDA wheels.
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
for pkg in libusb-1.0-0 libgomp1 libegl1 libgl1 libgl1-mesa-dri libosmesa6 chromium; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
if ((${#need_apt[@]})); then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

PY="${PYTHON:-python3}"
if ! "$PY" -c "import torch" >/dev/null 2>&1; then
  "$PY" -m pip install -q "torch==2.13.0"
fi
"$PY" -m pip install -q -e ".[test,video]"
# MediaPipe for the plain-video path, into its own folder (it needs protobuf < 5; see reconstruct/person.py).
"$PY" -m crisp_gym.reconstruct.person --install
