#!/usr/bin/env bash
# Install Cut-and-Splat into the active Python environment (make and activate a virtual environment first:
# `python3 -m venv .venv && . .venv/bin/activate`). The README's first command and CI (.ci/run) run this.
#   ./install.sh            the project, its tests' tools and the Debian libraries Open3D and torch need
#   TORCH_INDEX=https://download.pytorch.org/whl/cpu ./install.sh
#                           first take torch's CPU-only build from that index (about 4 GB less than PyPI's CUDA
#                           build; only where that index can be reached)
set -euo pipefail
cd "$(dirname "$0")"
sudo=""
[ "$(id -u)" -eq 0 ] || sudo="sudo"
export DEBIAN_FRONTEND=noninteractive
$sudo apt-get update -qq
$sudo apt-get install -y -qq libusb-1.0-0 libgomp1 > /dev/null
if [ -n "${TORCH_INDEX:-}" ]; then
    python -m pip install -q "torch==2.14.1" "torchvision==0.29.1" --index-url "$TORCH_INDEX"
fi
python -m pip install -q -e ".[dev]"
