"""Blender's own glTF importer plays a jaxtalk export as the face model does: the skinned mesh with its
one-sided shape keys and the jaw/neck armature, posed at four times to 1e-5 of ``LinearFaceModel``.
Skips where Blender is not installed (Debian: ``apt-get install blender python3-numpy``)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from test_export_gltf import head_motion

from jaxtalk.export import export_face_model
from jaxtalk.face import builtin_face

pytestmark = pytest.mark.external  # Blender

SCRIPT = Path(__file__).with_name("blender_playback.py")


def test_blender_imports_the_export_and_poses_it_as_the_face_model(tmp_path):
    blender = shutil.which("blender")
    if blender is None:
        pytest.skip("Blender is not installed (Debian: apt-get install blender python3-numpy)")
    face = builtin_face(0)
    params = head_motion(100)
    export_face_model(face, params, tmp_path / "clip.glb")
    times = (0.0, 1.0, 2.0, 3.0)  # keyframes 0, 25, 50, 75
    done = subprocess.run([blender, "-b", "--factory-startup", "--python", str(SCRIPT), "--", str(tmp_path / "clip.glb"),
                           ",".join(map(str, times)), str(tmp_path / "seen.json")], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0 and (tmp_path / "seen.json").is_file(), done.stdout[-2000:] + done.stderr[-2000:]
    seen = json.loads((tmp_path / "seen.json").read_text())
    assert seen["objects"] == ["ARMATURE", "EMPTY", "MESH"]  # the EMPTY: the skinned mesh node's own place
    assert seen["shape_keys"][:3] == ["exp_00+", "exp_00-", "exp_01+"] and len(seen["shape_keys"]) == 100
    assert seen["bones"] == ["neck", "jaw"]
    assert seen["actions"] == [8, 100]  # neck + jaw rotations (4 curves each), 100 shape-key curves
    want = np.asarray(face.vertices_seq(params), np.float64)
    for t in times:
        v = np.asarray(seen["vertices"][str(t)])
        gltf_frame = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)  # Blender is z-up: (x, -z, y) of glTF's y-up
        frame = round(t * 25)
        assert np.abs(gltf_frame - want[frame]).max() / np.abs(want[frame]).max() < 1e-5, t
