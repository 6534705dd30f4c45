#!/usr/bin/env bash
# A public face kit with separate inner parts for the alignment and retargeting experiments: the ICT
# Face Model's neutral head (USC ICT's ICT-FaceKit, MIT licence): 26,719 vertices in centimetres, 12
# materials (face, back of the head and neck, scleras, irises, eyelashes, lacrimal fluid, eye occlusion
# and blend, teeth, gums and tongue), with the 68 Multi-PIE landmarks listed in its README, and its 53
# expression shapes under ARKit's names (browDown_L, jawOpen, ...). Writes .cache/assets/ict_face_kit.obj
# and, with --rig, the expression shapes to .cache/assets/ict_face_kit/ (about 140 MB).
# Usage: bash experiments/fetch_ict_face_kit.sh [--rig]
set -euo pipefail
cd "$(dirname "$0")/.."
dest=.cache/assets
url=https://raw.githubusercontent.com/USC-ICT/ICT-FaceKit/master/FaceXModel
mkdir -p "$dest"
[ -f "$dest/ict_face_kit.obj" ] || curl -fsSL "$url/generic_neutral_mesh.obj" -o "$dest/ict_face_kit.obj"
if [ "${1:-}" = "--rig" ]; then
  mkdir -p "$dest/ict_face_kit"
  curl -fsSL "$url/vertex_indices.json" -o "$dest/ict_face_kit/vertex_indices.json"
  for name in $(python -c "import json; print(' '.join(json.load(open('$dest/ict_face_kit/vertex_indices.json'))['expressions']))"); do
    [ -f "$dest/ict_face_kit/$name.obj" ] || curl -fsSL "$url/$name.obj" -o "$dest/ict_face_kit/$name.obj"
  done
fi
echo "ICT face kit in $dest"
