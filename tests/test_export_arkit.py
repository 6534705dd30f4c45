"""ARKit's shape names and Live Link Face's curve order."""

from jaxtalk.export.arkit import ARKIT_NAMES, LIVE_LINK_CURVES, arkit_name, live_link_name


def test_52_distinct_camel_case_names_with_every_side_paired():
    assert len(ARKIT_NAMES) == 52 and len(set(ARKIT_NAMES)) == 52
    assert all(n[0].islower() and n.isalpha() for n in ARKIT_NAMES)
    for name in ARKIT_NAMES:
        if name.endswith("Left"):
            assert name[:-4] + "Right" in ARKIT_NAMES
        if name.endswith("Right"):
            assert name[:-5] + "Left" in ARKIT_NAMES


def test_live_link_curves_are_the_52_shapes_then_head_then_eyes_in_the_apps_order():
    assert len(LIVE_LINK_CURVES) == 61
    assert LIVE_LINK_CURVES[:3] == ("EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft")
    assert LIVE_LINK_CURVES[14:18] == ("JawForward", "JawRight", "JawLeft", "JawOpen")
    assert LIVE_LINK_CURVES[51:55] == ("TongueOut", "HeadYaw", "HeadPitch", "HeadRoll")
    assert LIVE_LINK_CURVES[-1] == "RightEyeRoll"
    assert [arkit_name(n) for n in LIVE_LINK_CURVES[:52]] == list(ARKIT_NAMES)
    assert live_link_name("mouthSmileLeft") == "MouthSmileLeft"
