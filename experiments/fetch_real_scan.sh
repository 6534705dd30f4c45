#!/usr/bin/env bash
# A real, independently made face scan for FreeTalk's tests and experiments: menpo3d's james.obj (a
# textured head scan in millimetres, 6,393 vertices, 28 components, with its 68 landmarks in
# james.ljson), which menpo3d ships in its source package (BSD-3-Clause). pip fetches the package by
# name; nothing of it is installed. Writes .cache/assets/james.obj and james.ljson.
# Usage: bash experiments/fetch_real_scan.sh   (inside the project's virtual environment)
set -euo pipefail
cd "$(dirname "$0")/.."
dest=.cache/assets
[ -f "$dest/james.obj" ] && [ -f "$dest/james.ljson" ] && exit 0
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# Its metadata is built by its own setup.py (needs setuptools and wheel, no compiler).
python -m pip install --quiet wheel setuptools
python -m pip download --quiet --no-deps --no-build-isolation --no-binary :all: "menpo3d==0.8.6" -d "$tmp"
mkdir -p "$dest"
tar -xzf "$tmp"/menpo3d-0.8.6.tar.gz -C "$tmp" menpo3d-0.8.6/menpo3d/data/james.obj menpo3d-0.8.6/menpo3d/data/james.ljson
cp "$tmp"/menpo3d-0.8.6/menpo3d/data/james.obj "$tmp"/menpo3d-0.8.6/menpo3d/data/james.ljson "$dest"/
echo "real face scan in $dest"
