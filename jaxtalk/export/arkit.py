"""ARKit's 52 blendshape names and the curves of a Live Link Face recording, in its CSV order.

Apple's ARKit names its face shapes in camelCase (``jawOpen``, ``mouthSmileLeft``); Epic's Live Link
Face app records the same 52 shapes, capitalised (``JawOpen``), in one fixed order, followed by the
head's yaw, pitch and roll and each eye's yaw, pitch and roll: 61 curves in all. That order is the one
a Live Link Face CSV's header uses, so the names here keep it (note ``JawRight`` before ``JawLeft`` and
``MouthRight`` before ``MouthLeft``, as the app writes them). Its UDP packets carry the same 61 curves
in Unreal's ``EARFaceBlendShape`` order instead, where those two pairs are the other way round;
:mod:`jaxtalk.export.livelink` permutes them on the wire.

"Left" and "Right" are the subject's own sides, as in ARKit.
"""

from __future__ import annotations

__all__ = ["ARKIT_NAMES", "LIVE_LINK_CURVES", "LIVE_LINK_HEAD_CURVES", "LIVE_LINK_EYE_CURVES", "live_link_name",
           "arkit_name"]

# The 52 shapes, in Live Link Face's order, with ARKit's own (camelCase) spelling.
ARKIT_NAMES: tuple[str, ...] = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight", "jawForward", "jawRight", "jawLeft", "jawOpen", "mouthClose",
    "mouthFunnel", "mouthPucker", "mouthRight", "mouthLeft", "mouthSmileLeft", "mouthSmileRight",
    "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft",
    "mouthStretchRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft",
    "mouthUpperUpRight", "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
)

LIVE_LINK_HEAD_CURVES: tuple[str, ...] = ("HeadYaw", "HeadPitch", "HeadRoll")
LIVE_LINK_EYE_CURVES: tuple[str, ...] = ("LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
                                         "RightEyeYaw", "RightEyePitch", "RightEyeRoll")


def live_link_name(name: str) -> str:
    """Live Link Face's spelling of an ARKit shape name: ``jawOpen`` -> ``JawOpen``."""
    return name[:1].upper() + name[1:]


def arkit_name(name: str) -> str:
    """ARKit's spelling of a Live Link Face shape name: ``JawOpen`` -> ``jawOpen``."""
    return name[:1].lower() + name[1:]


# All 61 curves of a Live Link Face CSV row (after Timecode and BlendShapeCount); a UDP packet holds them
# in Unreal's order (jaxtalk.export.livelink.PACKET_CURVES).
LIVE_LINK_CURVES: tuple[str, ...] = (tuple(live_link_name(n) for n in ARKIT_NAMES) + LIVE_LINK_HEAD_CURVES
                                     + LIVE_LINK_EYE_CURVES)
