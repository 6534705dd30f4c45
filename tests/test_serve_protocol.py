"""``jaxtalk serve``'s pieces without a model: audio decoding and its refusals, the hello, the reply outbox's
drop policy, and the ``morph`` output, which poses the built-in face's ``.glb`` exactly as an export of
the same frames animates it, chunk after chunk."""

from __future__ import annotations

import asyncio
import reprlib

import numpy as np
import pytest
from test_export_gltf import head_motion

from jaxtalk.export import GlbAnimation, export_face_model, face_model_rotations, face_model_targets, face_model_weights
from jaxtalk.face import builtin_face
from jaxtalk.serve import ProtocolError
from jaxtalk.serve.outputs import OUTPUTS, PARAM_CHANNELS, MorphOutput, OutputUnavailable, ParamsOutput, build_outputs
from jaxtalk.serve.protocol import decode_pcm, parse_hello, parse_message
from jaxtalk.serve.server import _Outbox


def test_pcm_decodes_at_full_scale_in_both_formats():
    s16 = np.array([0, 16384, -32768, 32767], "<i2").tobytes()
    np.testing.assert_array_equal(decode_pcm(s16, "pcm_s16le", 10), [0.0, 0.5, -1.0, 32767 / 32768])
    f32 = np.array([0.25, -1.5], "<f4")
    np.testing.assert_array_equal(decode_pcm(f32.tobytes(), "f32le", 10), f32)
    assert decode_pcm(s16, "pcm_s16le", 10).dtype == np.float32


@pytest.mark.parametrize("data, fmt, code", [
    (b"", "f32le", "empty"), (b"\x00" * 7, "f32le", "odd_length"), (b"\x00" * 3, "pcm_s16le", "odd_length"),
    (np.zeros(11, "<f4").tobytes(), "f32le", "too_large"), (np.array([0, np.inf], "<f4").tobytes(), "f32le", "not_finite"),
    (np.array([0, 7.0], "<f4").tobytes(), "f32le", "out_of_range"),
    (np.array([3e4, -3e4], "<f4").tobytes(), "f32le", "out_of_range"),  # 16-bit values sent as float
])
def test_malformed_audio_is_refused_with_its_code(data, fmt, code):
    with pytest.raises(ProtocolError) as err:
        decode_pcm(data, fmt, 10)
    assert err.value.code == code


def test_a_hello_takes_defaults_and_refuses_what_it_cannot_serve():
    known = ("params", "morph", "arkit")
    hello = parse_hello({"type": "hello", "sample_rate": 16000}, sample_rate=16000, outputs=known)
    assert (hello.format, hello.outputs, hello.seed, hello.subject) == ("pcm_s16le", ("params",), 0, "jaxtalk")
    hello = parse_hello({"type": "hello", "sample_rate": 16000.0, "format": "f32le", "outputs": ["morph", "params"],
                         "seed": -1, "subject": "Anna"}, sample_rate=16000, outputs=known)
    assert (hello.format, hello.outputs, hello.seed, hello.subject) == ("f32le", ("morph", "params"), 2**32 - 1, "Anna")
    for message, code in (({"sample_rate": 48000}, "bad_rate"), ({}, "bad_hello"), ({"sample_rate": "16k"}, "bad_hello"),
                          ({"sample_rate": 16000, "format": "opus"}, "bad_format"),
                          ({"sample_rate": 16000, "outputs": []}, "bad_hello"),
                          ({"sample_rate": 16000, "outputs": ["params", "params"]}, "bad_hello"),
                          ({"sample_rate": 16000, "outputs": ["blend"]}, "unknown_output"),
                          ({"sample_rate": 16000, "seed": 1.5}, "bad_hello"),
                          ({"sample_rate": 16000, "subject": ""}, "bad_hello")):
        with pytest.raises(ProtocolError) as err:
            parse_hello({"type": "hello", **message}, sample_rate=16000, outputs=known)
        assert err.value.code == code, message


@pytest.mark.parametrize("field, value", [
    ("sample_rate", 10**400), ("seed", 10**400), ("seed", -10**400), ("sample_rate", float("nan")),
    ("seed", float("inf")), ("seed", float("-inf")), ("sample_rate", True), ("seed", False), ("sample_rate", 0),
    ("sample_rate", -16000), ("sample_rate", 2**31), ("seed", 2**64), ("seed", -2**63 - 1), ("seed", 1e300),
    ("seed", "7"), ("seed", None), ("seed", [1]),
], ids=lambda v: v if isinstance(v, str) else reprlib.repr(v))
def test_a_hello_number_out_of_range_or_not_an_integer_is_bad_hello_naming_its_field(field, value):
    message = {"type": "hello", "sample_rate": 16000, field: value}
    with pytest.raises(ProtocolError, match=rf"^hello\.{field} must be an integer in -?\d+\.\.\d+, got ") as err:
        parse_hello(message, sample_rate=16000, outputs=("params",))
    assert err.value.code == "bad_hello" and len(str(err.value)) < 200  # a huge number is not echoed whole


def test_a_hello_takes_the_edges_of_its_ranges_and_refuses_what_is_no_json_or_no_format():
    for seed, reduced in ((2**64 - 1, 2**32 - 1), (-2**63, 0), (2.0**40, 0), (-1, 2**32 - 1)):
        assert parse_hello({"sample_rate": 16000, "seed": seed}, sample_rate=16000, outputs=("params",)).seed == reduced
    with pytest.raises(ProtocolError) as err:
        parse_hello({"sample_rate": 16000, "format": ["f32le"]}, sample_rate=16000, outputs=("params",))
    assert err.value.code == "bad_format"
    with pytest.raises(ProtocolError) as err:  # over Python's 4300 digits: json.loads itself refuses it
        parse_message('{"type": "hello", "seed": ' + "9" * 5000 + "}")
    assert err.value.code == "bad_json"


def test_a_full_outbox_drops_its_oldest_frames_reply_and_keeps_the_rest_in_order():
    async def scenario():
        box = _Outbox(3)
        box.put({"type": "ready"})
        for seq in range(1, 6):
            box.put({"type": "frames", "seq": seq})
        box.put({"type": "error", "code": "empty"})
        return [await box.get() for _ in range(3)], box.dropped

    got, dropped = asyncio.run(scenario())
    assert [m.get("seq", m["type"]) for m in got] == ["ready", 5, "error"] and dropped == 4


def test_outputs_are_built_once_per_server_and_an_unavailable_one_says_why():
    def unavailable():
        raise OutputUnavailable("this output is not available here")

    with pytest.raises(OutputUnavailable, match="not available here"):
        build_outputs(("gone",), {}, {**OUTPUTS, "gone": unavailable})
    cache = {}
    outputs = build_outputs(("params", "morph"), cache)
    assert isinstance(outputs["params"], ParamsOutput) and outputs["params"].channels == PARAM_CHANNELS
    assert build_outputs(("morph",), cache)["morph"] is outputs["morph"]  # built once per server
    assert set(OUTPUTS) == {"params", "morph", "arkit"}


def test_the_arkit_output_opens_jaw_open_with_the_jaw_and_turns_the_head_with_the_neck_across_chunks():
    from jaxtalk.export import arkit_rig, retarget
    from jaxtalk.export.arkit import ARKIT_NAMES
    from jaxtalk.export.solver import DEFAULT_TOL

    arkit = build_outputs(("arkit",), {})["arkit"]
    assert arkit.channels == (*ARKIT_NAMES, "HeadYaw", "HeadPitch", "HeadRoll")
    frames = 40
    params = np.zeros((frames, 56), np.float32)
    opening = 0.15 * (1 - np.cos(np.linspace(0, 4 * np.pi, frames))) / 2  # two jaw openings, 0..0.15 rad
    params[:, 50] = opening
    params[:, 54] = np.linspace(-0.2, 0.2, frames)  # the neck turns about its vertical axis
    state, chunks = arkit.start(), []
    for lo in range(0, frames, 10):  # a stream's chunks
        state, values = arkit.convert(state, params[lo:lo + 10])
        chunks.append(values)
    values = np.concatenate(chunks)
    assert values.shape == (frames, 55) and np.isfinite(values).all()
    # The chunks' weights are `jaxtalk retarget`'s of the whole motion (the solver looks back only).
    whole = retarget(params, arkit_rig())
    assert np.abs(values[:, :52] - whole.weights).max() <= DEFAULT_TOL
    np.testing.assert_allclose(values[:, 52:], whole.head_angles, atol=1e-7)  # float32 values
    weights = values[:, :52]
    assert weights.min() >= 0.0 and weights.max() <= 1.0
    jaw_open = weights[:, ARKIT_NAMES.index("jawOpen")]
    assert np.corrcoef(jaw_open, opening)[0, 1] > 0.95
    assert jaw_open.max() > 0.3  # 0.15 rad is half the rig's jawOpen (0.3 rad)
    yaw = values[:, 52]
    assert abs(np.corrcoef(yaw, params[:, 54])[0, 1]) > 0.99 and np.abs(yaw).max() > 0.1
    np.testing.assert_allclose(np.abs(values[:, 53:]), 0.0, atol=0.02)  # no pitch or roll asked for


@pytest.mark.slow
def test_morph_weights_and_rotations_pose_the_face_file_as_an_export_of_the_same_frames(tmp_path):
    face = builtin_face(0, resolution="low")
    params = head_motion(30, seed=2)
    params[:, 53:] *= 14.0  # the head turns past pi: raw quaternions flip sign 3 times in these frames
    output = MorphOutput(face)
    assert output.channels[:100] == tuple(face_model_targets(face))
    # Streamed in uneven chunks, the values equal one pass over all frames (signs continuous across chunks).
    state, chunks = output.start(), []
    for a, b in ((0, 4), (4, 5), (5, 17), (17, 30)):
        state, values = output.convert(state, params[a:b])
        chunks.append(values)
    streamed = np.concatenate(chunks)
    _, whole = output.convert(output.start(), params)
    np.testing.assert_allclose(streamed, whole, atol=1e-6)
    weights, quats = streamed[:, :100], streamed[:, 100:]
    # Unit-scale targets: each component's two one-sided weights give its coefficient back.
    np.testing.assert_allclose(weights[:, 0::2] - weights[:, 1::2], params[:, :50], atol=1e-6)
    assert weights.min() >= 0
    # A clip export of the same frames: its weights (its own scales) and its joint channels, read back.
    export_face_model(face, params, tmp_path / "clip.glb")
    clip = GlbAnimation(tmp_path / "clip.glb")
    scales = np.asarray(clip.gltf.meshes[0].extras["jaxtalk"]["targetScale"])
    np.testing.assert_allclose(face_model_weights(face, params, scales), clip.morph_weights(), atol=1e-6)
    nodes = {n.name: i for i, n in enumerate(clip.gltf.nodes)}
    for j, joint in enumerate(("jaw", "neck")):
        np.testing.assert_allclose(quats[:, 4 * j:4 * j + 4], clip._channels[(nodes[joint], "rotation")], atol=1e-6)
    signs = np.sum(quats[1:, 4:8] * quats[:-1, 4:8], axis=1)
    assert signs.min() > 0  # consecutive neck quaternions on one side
    rest = face_model_rotations(face, np.zeros((1, 56), np.float32))
    np.testing.assert_allclose(rest["jaw"], [[0, 0, 0, 1]], atol=1e-7)
    # The file the server hands out: the face at rest with unit target scales.
    (tmp_path / "face.glb").write_bytes(output.glb)
    served = GlbAnimation(tmp_path / "face.glb")
    assert served.target_names == list(output.channels[:100])
    assert np.array_equal(np.abs(served.gltf.meshes[0].extras["jaxtalk"]["targetScale"]), np.ones(100))
    with pytest.raises(ValueError, match="shape"):
        face_model_weights(face, np.zeros((3, 50)))
    with pytest.raises(ValueError, match="non-finite"):
        face_model_weights(face, np.full((2, 56), np.nan))
