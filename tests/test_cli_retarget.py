"""``jaxtalk retarget`` end to end: a parameters npz with audio onto the built-in rig and onto a rig file, a
vertex sequence, and the one-line refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import bad_numpy_files, cli_error, cli_ok

from jaxtalk.export import (
    GlbAnimation,
    arkit_rig,
    export_rig_animation,
    read_live_link_csv,
)
from jaxtalk.export.arkit import ARKIT_NAMES, LIVE_LINK_CURVES
from jaxtalk.export.solver import DEFAULT_TOL


@pytest.fixture(scope="module")
def talk(tmp_path_factory):
    """A speech-driven SynthTalk clip with its audio, as ``jaxtalk sample`` writes one."""
    from jaxtalk.data.formats import MotionClip, save_npz
    from jaxtalk.data.synthtalk import SizeSpec, generate

    folder = tmp_path_factory.mktemp("talk")
    corpus = generate(SizeSpec((1, 0, 0, 0), 1, 4.0, (0, 0, 0, 0), 4.0, 8, 1e9, identities=(0,), lazy=True), seed=0)
    save_npz(folder / "talk.npz", MotionClip(name="talk", fps=25, params=corpus.motion(0), audio=corpus.audio(0)))
    return folder


def test_parameters_onto_the_builtin_rig_write_glb_csv_json_and_audio(talk):
    out = talk / "talk_rig.glb"
    printed = cli_ok(["retarget", talk / "talk.npz", "--out", out])
    assert "52 shapes (52 ARKit-named, 20 left/right pairs)" in printed and "same mesh" in printed
    for suffix in (".glb", ".csv", ".json", ".glb.wav"):
        assert (talk / f"talk_rig{suffix}").is_file(), suffix
    params = np.load(talk / "talk.npz")["params"]
    glb = GlbAnimation(out)
    assert glb.target_names == list(ARKIT_NAMES) and glb.num_frames == params.shape[0]
    weights = glb.morph_weights()
    assert weights.min() >= 0.0 and weights.max() <= 1.0 + 1e-6
    assert np.corrcoef(weights[:, ARKIT_NAMES.index("jawOpen")], params[:, 50])[0, 1] > 0.8
    stamps, values = read_live_link_csv(talk / "talk_rig.csv")
    assert len(stamps) == params.shape[0] and stamps[1] == "00:00:00:01.000"
    np.testing.assert_allclose(values[:, :52], weights, atol=1e-5)
    data = json.loads((talk / "talk_rig.json").read_text())
    assert data["fps"] == 25 and len(data["weights"]) == params.shape[0] and data["names"] == list(ARKIT_NAMES)
    np.testing.assert_allclose(values[:, LIVE_LINK_CURVES.index("HeadYaw")], data["head"]["yaw"], atol=1e-5)


def test_a_rig_file_and_a_vertex_sequence(talk, tmp_path):
    from jaxtalk.face import builtin_face

    rig = arkit_rig("low")
    export_rig_animation(rig, np.zeros((1, 52)), tmp_path / "rig.glb")
    face = builtin_face(0, resolution="low")
    verts = np.asarray(face.vertices_seq(np.load(talk / "talk.npz")["params"][:40]))
    np.save(tmp_path / "talk_vertices.npy", verts)
    printed = cli_ok(["retarget", tmp_path / "talk_vertices.npy", "--rig", tmp_path / "rig.glb", "--out",
                      tmp_path / "out.glb"])
    assert "rig 'rig'" in printed and "no audio" in printed
    assert GlbAnimation(tmp_path / "out.glb").num_frames == 40


def test_a_rig_file_registered_by_its_landmarks(talk, tmp_path):
    """--landmarks: the rig file's 68 landmarks (positions in its units, as sample's --landmarks take them)
    register it; the built-in rig needs none."""
    from jaxtalk.face import builtin_face
    from jaxtalk.models.freetalk.data import neutral_landmarks

    rig = arkit_rig("low")  # the built-in face at low resolution; the parameters are posed on the default one
    export_rig_animation(rig, np.zeros((1, 52)), tmp_path / "rig.glb")
    np.save(tmp_path / "rig_landmarks.npy", neutral_landmarks(builtin_face(0, resolution="low")).astype(np.float64))
    printed = cli_ok(["retarget", talk / "talk.npz", "--rig", tmp_path / "rig.glb", "--landmarks",
                      tmp_path / "rig_landmarks.npy", "--out", tmp_path / "out.glb"])
    assert "registered (landmarks, units m)" in printed
    data = json.loads((tmp_path / "out.json").read_text())
    assert data["registration"]["method"] == "landmarks"
    cli_error(["retarget", talk / "talk.npz", "--landmarks", tmp_path / "rig_landmarks.npy", "--out",
               tmp_path / "b.glb"], "--landmarks", "built-in rig")


def test_bad_inputs_are_refused_in_one_line(talk, tmp_path):
    np.save(tmp_path / "bad.npy", np.zeros((4, 10, 3)))
    cli_error(["retarget", tmp_path / "bad.npy", "--out", tmp_path / "a.glb"], "10 vertices", "--mesh")
    nan = np.load(talk / "talk.npz")["params"].copy()
    nan[3, 5] = np.nan
    np.savez(tmp_path / "nan.npz", params=nan, fps=25)
    cli_error(["retarget", tmp_path / "nan.npz", "--out", tmp_path / "b.glb"], "NaN")
    (tmp_path / "flat.glb").write_bytes(b"")
    cli_error(["retarget", talk / "talk.npz", "--rig", tmp_path / "flat.glb", "--out", tmp_path / "c.glb"], "glTF")
    cli_error(["retarget", talk / "talk.npz", "--out", tmp_path / "x.csv"], ".glb")
    cli_error(["retarget", talk / "talk.npz", "--out", talk / "talk.npz"], ".glb")
    cli_error(["retarget", talk / "talk.npz", "--smoothness", "-1", "--out", tmp_path / "d.glb"], "smoothness")


def _hashes(folder) -> dict[str, str]:
    import hashlib

    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("side", ["talk.csv", "talk.json"])
def test_the_side_files_of_a_named_glb_replace_a_user_file_only_with_overwrite(talk, tmp_path, side):
    # --out names the .glb; the CSV and JSON beside it are names the command derives, as the audio's is.
    folder = tmp_path / "c"
    folder.mkdir()
    (folder / side).write_bytes(b"the user's own file")
    before = _hashes(folder)
    cli_error(["retarget", talk / "talk.npz", "--out", folder / "talk.glb"], side, "--overwrite")
    assert _hashes(folder) == before  # nothing replaced, nothing written (not even the .glb)
    cli_ok(["retarget", talk / "talk.npz", "--out", folder / "talk.glb", "--overwrite"])
    after = _hashes(folder)
    assert after[side] != before[side]
    assert set(after) == {"talk.glb", "talk.csv", "talk.json", "talk.glb.wav"}


def _write_obj(path, vertices, faces):
    lines = [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def test_an_obj_folder_with_two_shapes_on_one_arkit_name_is_refused_naming_both_files(talk, tmp_path):
    rig = arkit_rig("low")
    folder = tmp_path / "shapes"
    folder.mkdir()
    _write_obj(folder / "neutral.obj", rig.neutral, rig.faces)
    jaw = rig.neutral + rig.deltas[ARKIT_NAMES.index("jawOpen")]
    for name in ("jawOpen", "JAWOPEN"):  # the solver would give each about half of the jaw's weight
        _write_obj(folder / f"{name}.obj", jaw, rig.faces)
    _write_obj(folder / "eyeBlink_L.obj", rig.neutral + rig.deltas[ARKIT_NAMES.index("eyeBlinkLeft")], rig.faces)
    line = cli_error(["retarget", talk / "talk.npz", "--rig", folder, "--out", tmp_path / "out.glb"],
                     "jawOpen.obj", "JAWOPEN.obj", "'jawOpen'")
    assert str(folder) in line
    assert not (tmp_path / "out.glb").exists()


def test_a_gltf_rig_with_two_morph_targets_on_one_arkit_name_is_refused_naming_both(talk, tmp_path):
    import pygltflib

    export_rig_animation(arkit_rig("low"), np.zeros((1, 52)), tmp_path / "rig.glb")
    gltf = pygltflib.GLTF2().load(str(tmp_path / "rig.glb"))
    names = gltf.meshes[0].extras["targetNames"]
    names[ARKIT_NAMES.index("eyeBlinkRight")] = "EyeBlinkLeft"  # eyeBlinkLeft under a second spelling
    gltf.save(str(tmp_path / "rig.glb"))
    cli_error(["retarget", talk / "talk.npz", "--rig", tmp_path / "rig.glb", "--out", tmp_path / "out.glb"],
              "rig.glb", "'eyeBlinkLeft' and 'EyeBlinkLeft'")
    assert not (tmp_path / "out.glb").exists()


def test_a_bad_motion_file_is_one_line_naming_it_never_advice_to_unpickle(tmp_path):
    for name, words in bad_numpy_files(tmp_path).items():
        for command in (["retarget", tmp_path / name, "--out", tmp_path / "out.glb"],
                        ["render", tmp_path / name, "--out", tmp_path / "out.mp4"]):
            line = cli_error(command, str(tmp_path / name), *words)
            assert "pickle" not in line.lower() and "unsafe" not in line.lower(), line
    assert not (tmp_path / "out.glb").exists() and not (tmp_path / "out.mp4").exists()


def test_motion_in_the_wrong_units_is_refused_naming_the_mistake_and_writes_nothing(talk, tmp_path):
    from jaxtalk.data.formats import MotionClip, save_npz
    from jaxtalk.face import builtin_face

    params = np.load(talk / "talk.npz")["params"]
    save_npz(tmp_path / "scaled.npz", MotionClip(name="scaled", fps=25, params=params * 1000.0))
    line = cli_error(["retarget", tmp_path / "scaled.npz", "--out", tmp_path / "a.glb"],
                     "fit error", "mm RMS is larger than the face itself", "scaled")
    assert float(line.split("fit error ")[1].split(" mm")[0]) > 1000.0
    face = builtin_face(0, resolution="low")
    metres = np.asarray(face.vertices_seq(params[:20]))
    np.save(tmp_path / "mm.npy", 1000.0 * metres)  # millimetres on a mesh in metres
    cli_error(["retarget", tmp_path / "mm.npy", "--out", tmp_path / "b.glb"],
              "larger than the face itself", "1000 times the size", "are they in mm and the mesh in m?")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mm.npy", "scaled.npz"]
    # The same vertices in the mesh's units fit to millimetres.
    np.save(tmp_path / "m.npy", metres)
    printed = cli_ok(["retarget", tmp_path / "m.npy", "--out", tmp_path / "c.glb"])
    assert float(printed.split("fit error ")[1].split(" mm")[0]) < 10.0


# Runs the command line given after it as a child and prints the child's peak resident set size last:
# a fresh process, so that no earlier child of the test session's counts.
_PEAK_RSS = """
import resource, subprocess, sys
done = subprocess.run(sys.argv[1:])
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
sys.exit(done.returncode)
"""


def _peak_rss(args: list) -> tuple[int, str]:
    """``(peak RSS in bytes, output)`` of ``jaxtalk ARGS`` in a subprocess; it must succeed."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", _PEAK_RSS, sys.executable, "-m", "jaxtalk", *map(str, args)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    *printed, peak = done.stdout.splitlines()
    return int(peak) * (1 if sys.platform == "darwin" else 1024), "\n".join(printed)  # ru_maxrss: KiB on Linux


@pytest.mark.slow
@pytest.mark.optimized
def test_half_an_hour_retargets_in_bounded_memory_and_its_windows_join_as_one_solve(tmp_path):
    import jax

    from jaxtalk.data.formats import MotionClip, save_npz
    from jaxtalk.export import DEFAULT_WINDOW, Retargeter
    from jaxtalk.face import builtin_face

    frames = 45_000  # 30 minutes at 25 fps
    t = np.arange(frames)
    params = np.zeros((frames, 56), np.float32)
    params[:, 50] = 0.1 * (1.0 + np.sin(t / 7.0))  # the jaw, talking
    params[:, 54] = 0.1 * np.sin(t / 50.0)  # the head turning
    short_frames = 3 * DEFAULT_WINDOW  # windowed too: the same programs, the same windows' memory
    save_npz(tmp_path / "long.npz", MotionClip(name="long", fps=25, params=params))
    save_npz(tmp_path / "short.npz", MotionClip(name="short", fps=25, params=params[:short_frames]))
    short, _ = _peak_rss(["retarget", tmp_path / "short.npz", "--out", tmp_path / "short.glb"])
    peak, printed = _peak_rss(["retarget", tmp_path / "long.npz", "--out", tmp_path / "long.glb"])
    print(f"peak RSS: {short / 2**20:.0f} MiB for {short_frames} frames, {peak / 2**20:.0f} MiB for {frames}")
    # Solved whole, the clip held 0.5 MB a frame (22 GB here). A window at a time, more frames add only
    # what is kept for the whole clip: the motion, the weights and head rotations and angles (0.8 KB a
    # frame), and copies of them where they are written; 2 KB a frame bounds that. A per-frame array of
    # anything more (a vertex's worth is 12 bytes times 3705 vertices) breaks the bound many times over.
    assert peak - short < 2048 * (frames - short_frames), (short, peak)
    assert f"{frames} frames x 52 shapes in {frames // DEFAULT_WINDOW} windows" in printed, printed

    # Where two windows join, the weights are those of the frames around the seam solved in one piece from the
    # weights written before them (each frame depends only on the frames up to it): to the solver's tolerance,
    # through the .glb's float32 storage.
    weights = GlbAnimation(tmp_path / "long.glb").morph_weights()
    assert weights.shape == (frames, 52)
    # Compiled afresh, with the optimisations the command ran with: a program an earlier test compiled
    # without them would round differently.
    jax.clear_caches()
    retargeter = Retargeter.for_face(arkit_rig(), builtin_face(0))
    middle = frames // 2 // DEFAULT_WINDOW * DEFAULT_WINDOW
    for seam in (DEFAULT_WINDOW, middle, frames - DEFAULT_WINDOW):
        around = slice(seam - 50, seam + 50)
        solved = retargeter(params[around], previous=weights[seam - 51], window=None).weights
        error = np.abs(solved - weights[around]).max()
        print(f"seam at frame {seam}: the frames around it solved in one piece are within {error:.1e}")
        assert error <= DEFAULT_TOL, seam
