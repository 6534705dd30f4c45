"""Live Link Face UDP packets: what Epic's Live Link Face app sends Unreal Engine, encoded, decoded and sent.

One packet carries one frame of the 61 curves (:data:`~jaxtalk.export.arkit.LIVE_LINK_CURVES`: the 52
ARKit shapes, the head's yaw, pitch and roll, each eye's yaw, pitch and roll). Every field is big-endian:

=============  ===============================================================================
version        uint8, 6 (what the app and Unreal's ``AppleARKitFaceSupport`` plugin speak)
device id      int32 byte length, then UTF-8 bytes (no terminator): the sending device
subject name   int32 byte length, then UTF-8 bytes: the Live Link subject Unreal lists
frame time     int32 frame number, float32 sub-frame, int32 rate numerator, int32 denominator
curve count    uint8, 61
curves         61 float32, in Unreal's ``EARFaceBlendShape`` order (:data:`PACKET_CURVES`)
=============  ===============================================================================

Unreal reads curve ``i`` as ``EARFaceBlendShape(i)``, whose order differs from the app's CSV header
(:data:`~jaxtalk.export.arkit.LIVE_LINK_CURVES`) in two pairs: the enum has ``JawLeft`` before
``JawRight`` and ``MouthLeft`` before ``MouthRight``. The functions here take and return values in
``LIVE_LINK_CURVES`` order and permute them on the wire, so a value reaches Unreal under its own name.
(The layout agrees with the public implementations that talk to Unreal: Unreal's own enum,
PyLiveLinkFace's and LLV's encoders.) Unreal accepts packets of 264 to 774 bytes, which bounds the two
names to 512 bytes together.

:class:`LiveLinkSender` sends frames to a receiver (Unreal's Live Link, default UDP port 11111);
:func:`jaxtalk.export.recording.live_link_curves` makes the 61 curves from a rig's weights and head angles.
"""

from __future__ import annotations

import dataclasses
import socket
import struct
import uuid
from collections.abc import Sequence

import numpy as np

from jaxtalk.export.arkit import LIVE_LINK_CURVES
from jaxtalk.types import Float

__all__ = [
    "DEFAULT_PORT",
    "PACKET_CURVES",
    "PACKET_VERSION",
    "LiveLinkFrame",
    "LiveLinkSender",
    "decode_packet",
    "encode_packet",
    "parse_address",
]

PACKET_VERSION = 6
DEFAULT_PORT = 11111
NUM_CURVES = len(LIVE_LINK_CURVES)
# Unreal's EARFaceBlendShape order: LIVE_LINK_CURVES with JawLeft/JawRight and MouthLeft/MouthRight swapped.
_SWAPS = {"JawRight": "JawLeft", "JawLeft": "JawRight", "MouthRight": "MouthLeft", "MouthLeft": "MouthRight"}
PACKET_CURVES: tuple[str, ...] = tuple(_SWAPS.get(name, name) for name in LIVE_LINK_CURVES)
# packet[i] = values[_TO_PACKET[i]]
_TO_PACKET = np.array([LIVE_LINK_CURVES.index(name) for name in PACKET_CURVES])
_MIN_PACKET, _MAX_PACKET = 264, 774
_HEAD = struct.Struct(">B")
_TIME = struct.Struct(">ifiiB")
_CURVES = struct.Struct(f">{NUM_CURVES}f")


@dataclasses.dataclass(frozen=True)
class LiveLinkFrame:
    """One decoded packet.

    Attributes:
        values: ``(61,)`` curves in :data:`~jaxtalk.export.arkit.LIVE_LINK_CURVES` order.
        frame: the frame number.
        subframe: the fraction of a frame, in ``[0, 1)``.
        fps: the frame rate as ``(numerator, denominator)``.
        subject: the Live Link subject name.
        device_id: the sender's device id.
        version: the packet version.
    """

    values: np.ndarray
    frame: int
    subframe: float
    fps: tuple[int, int]
    subject: str
    device_id: str
    version: int = PACKET_VERSION

    def named(self) -> dict[str, float]:
        """``{curve name: value}`` in :data:`~jaxtalk.export.arkit.LIVE_LINK_CURVES` order."""
        return dict(zip(LIVE_LINK_CURVES, self.values.tolist(), strict=True))


def _text(value: str, what: str) -> bytes:
    data = str(value).encode("utf-8")
    if not data:
        raise ValueError(f"the {what} must not be empty")
    return struct.pack(">i", len(data)) + data


def encode_packet(
    values: Float[np.ndarray, "..."] | Sequence[float], *, frame: int, subject: str = "jaxtalk",
    device_id: str = "jaxtalk", fps: tuple[int, int] = (25, 1), subframe: float = 0.0,
) -> bytes:
    """One Live Link Face packet (module docstring).

    Args:
        values: the 61 curves in :data:`~jaxtalk.export.arkit.LIVE_LINK_CURVES` order.
        frame: the frame number (int32).
        subject: the Live Link subject name Unreal lists.
        device_id: the sender's id.
        fps: the frame rate as ``(numerator, denominator)``.
        subframe: the fraction of a frame, in ``[0, 1)``.

    Returns:
        The packet's bytes.

    Raises:
        ValueError: not 61 finite values; a frame number outside int32; a bad rate or sub-frame; an empty
            name, or names too long for Unreal's packet bound.
    """
    values = np.asarray(values, np.float64)
    if values.shape != (NUM_CURVES,) or not np.all(np.isfinite(values)):
        raise ValueError(f"a Live Link Face frame is {NUM_CURVES} finite curve values, got shape {values.shape}")
    if not -(2**31) <= int(frame) < 2**31:
        raise ValueError(f"frame number {frame} does not fit Live Link's int32")
    numerator, denominator = (int(x) for x in fps)
    if numerator < 1 or denominator < 1:
        raise ValueError(f"fps must be a positive (numerator, denominator), got {fps}")
    if not 0.0 <= subframe < 1.0:
        raise ValueError(f"subframe must lie in [0, 1), got {subframe}")
    packet = b"".join([
        _HEAD.pack(PACKET_VERSION), _text(device_id, "device id"), _text(subject, "subject name"),
        _TIME.pack(int(frame), float(subframe), numerator, denominator, NUM_CURVES),
        _CURVES.pack(*values[_TO_PACKET].astype(np.float32).tolist()),
    ])
    if len(packet) > _MAX_PACKET:
        raise ValueError(f"the subject name and device id are too long: the packet is {len(packet)} bytes, Unreal "
                         f"reads at most {_MAX_PACKET}")
    return packet


def decode_packet(data: bytes) -> LiveLinkFrame:
    """Read a Live Link Face packet (the app's, or :func:`encode_packet`'s).

    Raises:
        ValueError: a packet of the wrong size, version or curve count, or with names that overrun it.
    """
    data = bytes(data)
    if not _MIN_PACKET <= len(data) <= _MAX_PACKET:
        raise ValueError(f"a Live Link Face packet has {_MIN_PACKET} to {_MAX_PACKET} bytes, got {len(data)}")
    (version,) = _HEAD.unpack_from(data, 0)
    if version != PACKET_VERSION:
        raise ValueError(f"unsupported Live Link Face packet version {version} (expected {PACKET_VERSION})")
    pos, names = 1, []
    for what in ("device id", "subject name"):
        (length,) = struct.unpack_from(">i", data, pos)
        if not 0 <= length <= len(data) - pos - 4:
            raise ValueError(f"the packet's {what} length {length} overruns the packet")
        names.append(data[pos + 4:pos + 4 + length].decode("utf-8", errors="replace"))
        pos += 4 + length
    if len(data) != pos + _TIME.size + _CURVES.size:
        raise ValueError(f"a packet with these names has {pos + _TIME.size + _CURVES.size} bytes, got {len(data)}")
    frame, subframe, numerator, denominator, count = _TIME.unpack_from(data, pos)
    if count != NUM_CURVES:
        raise ValueError(f"the packet has {count} curves, expected {NUM_CURVES}")
    packet = np.asarray(_CURVES.unpack_from(data, pos + _TIME.size), np.float32)
    values = np.empty(NUM_CURVES, np.float32)
    values[_TO_PACKET] = packet
    return LiveLinkFrame(values=values, frame=frame, subframe=subframe, fps=(numerator, denominator),
                         subject=names[1], device_id=names[0], version=version)


def parse_address(text: str, *, default_host: str = "127.0.0.1", default_port: int = DEFAULT_PORT) -> tuple[str, int]:
    """``"HOST:PORT"``, ``":PORT"``, ``"PORT"`` or ``"HOST"`` (``[v6]:PORT`` for IPv6) -> ``(host, port)``.

    Raises:
        ValueError: an empty host or a port outside 1..65535.
    """
    text = text.strip()
    if text.startswith("["):
        host, _, rest = text[1:].partition("]")
        port = rest.removeprefix(":")
    elif text.isdigit():
        host, port = "", text
    elif text.count(":") == 1:
        host, port = text.split(":")
    else:
        host, port = text, ""
    try:
        number = int(port) if port else default_port
    except ValueError:
        raise ValueError(f"{text!r}: the port must be a number") from None
    if not 1 <= number <= 65535:
        raise ValueError(f"{text!r}: the port must lie in 1..65535")
    return host or default_host, number


class LiveLinkSender:
    """Sends frames of the 61 curves to a Live Link receiver as Live Link Face packets over UDP.

    A send that fails (no route; an ICMP "port unreachable" reported on a later send) is counted in
    :attr:`errors` and does not raise: a live stream keeps going while the receiver is away.

    Args:
        address: ``(host, port)`` of the receiver (Unreal's Live Link: port 11111).
        subject: the Live Link subject name.
        device_id: the device id in every packet (default: a new UUID).
        fps: the frame rate as ``(numerator, denominator)``.

    Attributes:
        sent: packets sent.
        errors: packets that could not be sent.
    """

    def __init__(self, address: tuple[str, int], *, subject: str = "jaxtalk", device_id: str | None = None,
                 fps: tuple[int, int] = (25, 1)):
        try:
            family, _, _, _, self.address = socket.getaddrinfo(address[0], int(address[1]), type=socket.SOCK_DGRAM)[0]
        except socket.gaierror as err:
            raise ValueError(f"cannot resolve the Live Link host {address[0]!r} ({err})") from None
        self.subject = subject
        self.device_id = device_id or str(uuid.uuid4())
        self.fps = fps
        self.sent = 0
        self.errors = 0
        encode_packet(np.zeros(NUM_CURVES), frame=0, subject=subject, device_id=self.device_id, fps=fps)  # checks
        self._socket = socket.socket(family, socket.SOCK_DGRAM)

    def send(self, curves: Float[np.ndarray, "..."], first_frame: int) -> None:
        """Send frames ``first_frame, first_frame + 1, ...``, one packet each.

        Raises:
            ValueError: curves of the wrong shape or NaN (nothing is sent).
        """
        curves = np.asarray(curves, np.float32)
        if curves.ndim != 2 or curves.shape[1] != NUM_CURVES:
            raise ValueError(f"curves must have shape (frames, {NUM_CURVES}), got {curves.shape}")
        packets = [encode_packet(row, frame=first_frame + i, subject=self.subject, device_id=self.device_id,
                                 fps=self.fps) for i, row in enumerate(curves)]
        for packet in packets:
            try:
                self._socket.sendto(packet, self.address)
                self.sent += 1
            except OSError:
                self.errors += 1

    def close(self) -> None:
        """Close the socket."""
        self._socket.close()

    def __enter__(self) -> LiveLinkSender:  # noqa: PYI034  (beartype refuses typing.Self on methods)
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
