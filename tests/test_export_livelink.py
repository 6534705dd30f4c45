"""Live Link Face packets: the bytes laid out field by field as Unreal reads them (checked against a packet
built here by hand from the published layout, with Unreal's curve order typed out independently), the
decoder's refusals, and frames sent over UDP to a local receiver that decodes them."""

from __future__ import annotations

import socket
import struct

import numpy as np
import pytest

from jaxtalk.export.arkit import ARKIT_NAMES, LIVE_LINK_CURVES
from jaxtalk.export.livelink import PACKET_CURVES, LiveLinkSender, decode_packet, encode_packet, parse_address
from jaxtalk.export.recording import live_link_curves

# Unreal's EARFaceBlendShape, in enum order (AugmentedReality/Public/ARTypes.h): what packet index i means.
UNREAL_ORDER = """EyeBlinkLeft EyeLookDownLeft EyeLookInLeft EyeLookOutLeft EyeLookUpLeft EyeSquintLeft EyeWideLeft
EyeBlinkRight EyeLookDownRight EyeLookInRight EyeLookOutRight EyeLookUpRight EyeSquintRight EyeWideRight JawForward
JawLeft JawRight JawOpen MouthClose MouthFunnel MouthPucker MouthLeft MouthRight MouthSmileLeft MouthSmileRight
MouthFrownLeft MouthFrownRight MouthDimpleLeft MouthDimpleRight MouthStretchLeft MouthStretchRight MouthRollLower
MouthRollUpper MouthShrugLower MouthShrugUpper MouthPressLeft MouthPressRight MouthLowerDownLeft MouthLowerDownRight
MouthUpperUpLeft MouthUpperUpRight BrowDownLeft BrowDownRight BrowInnerUp BrowOuterUpLeft BrowOuterUpRight CheekPuff
CheekSquintLeft CheekSquintRight NoseSneerLeft NoseSneerRight TongueOut HeadYaw HeadPitch HeadRoll LeftEyeYaw
LeftEyePitch LeftEyeRoll RightEyeYaw RightEyePitch RightEyeRoll""".split()


def curves(seed: int = 0, frames: int | None = None) -> np.ndarray:
    rng = np.random.default_rng(seed)
    shape = (61,) if frames is None else (frames, 61)
    return rng.uniform(-1, 1, size=shape).astype(np.float32)


def test_packet_bytes_follow_the_layout_unreal_reads_with_each_value_under_its_own_curve_name():
    values = curves()
    named = dict(zip(LIVE_LINK_CURVES, values.tolist(), strict=True))
    device, subject = "3A0F2C1E-0000-4000-8000-00000000BEEF", "Jäxtalk"
    want = (bytes([6]) + struct.pack(">i", len(device)) + device.encode() + struct.pack(">i", len(subject.encode()))
            + subject.encode() + struct.pack(">ifii", 1234, 0.25, 30, 1) + bytes([61])
            + struct.pack(">61f", *[named[name] for name in UNREAL_ORDER]))
    packet = encode_packet(values, frame=1234, subject=subject, device_id=device, fps=(30, 1), subframe=0.25)
    assert packet == want
    assert PACKET_CURVES == tuple(UNREAL_ORDER)
    assert sorted(PACKET_CURVES) == sorted(LIVE_LINK_CURVES)  # a permutation: JawLeft/Right, MouthLeft/Right swapped
    frame = decode_packet(packet)
    assert (frame.frame, frame.subframe, frame.fps, frame.subject, frame.device_id, frame.version) == (
        1234, 0.25, (30, 1), subject, device, 6)
    np.testing.assert_array_equal(frame.values, values)  # float32 values round-trip exactly
    assert frame.named()["JawLeft"] == named["JawLeft"] and frame.named()["MouthRight"] == named["MouthRight"]


def test_decoder_reads_a_packet_laid_out_like_the_apps_and_refuses_malformed_ones():
    good = encode_packet(curves(1), frame=5, device_id="d" * 36)
    assert decode_packet(good).frame == 5
    bad_version = bytes([5]) + good[1:]
    bad_count = bytearray(good)
    bad_count[-61 * 4 - 1] = 52
    overrun = bytearray(good)
    overrun[1:5] = struct.pack(">i", 10_000)
    for data, words in ((good[:-4], "bytes"), (good[:100], "bytes"), (bad_version, "version"),
                        (bytes(bad_count), "52 curves"), (bytes(overrun), "overruns"), (good + b"\0" * 600, "bytes")):
        with pytest.raises(ValueError, match=words):
            decode_packet(data)


def test_encoder_refuses_what_unreal_could_not_read():
    with pytest.raises(ValueError, match="61 finite"):
        encode_packet(np.zeros(52), frame=0)
    with pytest.raises(ValueError, match="61 finite"):
        encode_packet(np.full(61, np.nan), frame=0)
    with pytest.raises(ValueError, match="int32"):
        encode_packet(np.zeros(61), frame=2**31)
    with pytest.raises(ValueError, match="too long"):
        encode_packet(np.zeros(61), frame=0, subject="s" * 300, device_id="d" * 300)
    with pytest.raises(ValueError, match="empty"):
        encode_packet(np.zeros(61), frame=0, subject="")


def test_a_local_receiver_decodes_every_frame_the_sender_sends():
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.bind(("127.0.0.1", 0))
    receiver.settimeout(5.0)
    frames = curves(2, frames=40)
    try:
        with LiveLinkSender(("localhost", receiver.getsockname()[1]), subject="face", fps=(25, 1)) as sender:
            sender.send(frames[:25], first_frame=100)
            sender.send(frames[25:], first_frame=125)
            assert (sender.sent, sender.errors) == (40, 0)
            got = [decode_packet(receiver.recvfrom(2048)[0]) for _ in range(40)]
    finally:
        receiver.close()
    assert [f.frame for f in got] == list(range(100, 140))  # UDP on loopback: every packet, in order
    assert {(f.subject, f.device_id, f.fps) for f in got} == {("face", sender.device_id, (25, 1))}
    np.testing.assert_array_equal(np.stack([f.values for f in got]), frames)


def test_a_rigs_weights_and_head_angles_become_the_61_curves_a_packet_carries():
    # One assembly of the 61 curves for a Live Link Face recording's rows and its UDP packets.
    names = ["jawOpen", "MouthLeft", "eyeBlink_R", "smile"]  # any spelling a rig uses; an unknown shape is left out
    weights = np.array([[0.5, 0.25, 1.0, 0.9], [0.0, 0.0, 0.0, 0.0]], np.float32)
    head = np.array([[-0.1, 0.2, 0.05], [0.0, 0.0, 0.0]], np.float32)
    out = live_link_curves(names, weights, head)
    index = {name: i for i, name in enumerate(LIVE_LINK_CURVES)}
    assert out.shape == (2, 61) and out[0, index["JawOpen"]] == 0.5 and out[0, index["MouthLeft"]] == 0.25
    assert out[0, index["EyeBlinkRight"]] == 1.0 and np.count_nonzero(out[0]) == 6
    np.testing.assert_allclose(out[0, [index["HeadYaw"], index["HeadPitch"], index["HeadRoll"]]], head[0])
    frame = decode_packet(encode_packet(out[0], frame=0))
    assert frame.named()["JawOpen"] == 0.5 and frame.named()["HeadPitch"] == np.float32(0.2)
    every = live_link_curves(list(ARKIT_NAMES), np.ones((1, 52), np.float32))
    assert every[0, :52].min() == 1.0 and not every[0, 52:].any()


def test_a_shape_of_both_sides_split_into_halves_is_the_curve_of_their_mean():
    # ICT-FaceKit splits ARKit's browInnerUp and cheekPuff into _L / _R halves; a whole shape wins over halves.
    names = ["browInnerUp_L", "browInnerUp_R", "cheekPuff_L", "cheekPuff_R", "cheekPuff", "mouthClose_L"]
    weights = np.array([[0.2, 0.6, 0.9, 0.1, 0.3, 0.8]])
    out = live_link_curves(names, weights)
    index = {name: i for i, name in enumerate(LIVE_LINK_CURVES)}
    assert out[0, index["BrowInnerUp"]] == pytest.approx(0.4)
    assert out[0, index["CheekPuff"]] == pytest.approx(0.3)
    assert out[0, index["MouthClose"]] == 0.0 and np.count_nonzero(out[0]) == 2  # one half alone is no curve


@pytest.mark.parametrize("text, want", [
    ("10.0.0.5:9000", ("10.0.0.5", 9000)), (":9000", ("127.0.0.1", 9000)), ("9000", ("127.0.0.1", 9000)),
    ("studio-pc", ("studio-pc", 11111)), ("[::1]:7000", ("::1", 7000)), ("localhost", ("localhost", 11111)),
])
def test_addresses_take_a_host_a_port_or_both(text, want):
    assert parse_address(text) == want


@pytest.mark.parametrize("text", ["host:0", "host:70000", "host:port"])
def test_bad_ports_are_refused(text):
    with pytest.raises(ValueError, match="port"):
        parse_address(text)
