"""``jaxtalk serve``'s server with Python WebSocket clients, on the session's two-step TokTalk run.

Several clients at once each get exactly their own stream (their frames equal the library's offline
``stream`` over the same audio and seed), a client that never reads holds up nobody and loses only its
oldest replies, a client that vanishes mid-stream leaves nothing behind, malformed messages are answered
and change nothing, the server binds 127.0.0.1 and turns away foreign web pages, serves the face its
``morph`` output drives, and with a registered ``arkit`` output sends Live Link Face packets a local
receiver decodes.
"""

from __future__ import annotations

import gc
import json
import logging
import queue
import signal
import socket
import threading
import time
import urllib.request
import weakref

import jax
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from jaxtalk.export import GlbAnimation
from jaxtalk.export.arkit import ARKIT_NAMES, LIVE_LINK_CURVES
from jaxtalk.export.livelink import decode_packet
from jaxtalk.face import builtin_face
from jaxtalk.serve import OUTPUTS, LiveServer, ServeOptions, start_server
from jaxtalk.serve.outputs import MorphOutput

pytestmark = pytest.mark.slow  # a server on the session's trained run


@pytest.fixture(scope="module")
def live(trained_toktalk):
    from jaxtalk.models.toktalk.live import LiveModel
    from jaxtalk.runs import load_run

    return LiveModel.from_run(load_run(trained_toktalk.dir))


@pytest.fixture(scope="module")
def server(live):
    running = start_server(live, ServeOptions(port=0, outbox=4, max_chunk_s=1.0))
    yield running
    running.close()


@pytest.fixture(scope="module")
def speech(synthtalk_tiny):
    """Three different 1.5-2.5 s utterances of the tiny corpus's test split."""
    clips = synthtalk_tiny.split("test")
    return [np.asarray(synthtalk_tiny.audio(clips[i]), np.float32)[: 16000 * (3 + i) // 2] for i in range(3)]


def client(url: str, **kw):
    return connect(url, proxy=None, compression=None, open_timeout=20, **kw)


def hello(ws, outputs=("params",), fmt="f32le", seed=0, **extra) -> dict:
    ws.send(json.dumps({"type": "hello", "sample_rate": 16000, "format": fmt, "outputs": list(outputs), "seed": seed,
                        **extra}))
    return json.loads(ws.recv(timeout=30))


def pcm(audio: np.ndarray, fmt: str = "f32le") -> bytes:
    if fmt == "f32le":
        return audio.astype("<f4").tobytes()
    return np.clip(np.round(audio * 32768), -32768, 32767).astype("<i2").tobytes()


def stream_through(url: str, audio: np.ndarray, *, piece: int, seed: int, outputs=("params",), fmt="f32le") -> dict:
    """One client's whole utterance: every frames reply's outputs concatenated, and the replies."""
    with client(url) as ws:
        ready = hello(ws, outputs, fmt, seed)
        assert ready["type"] == "ready", ready
        replies = []
        for start in range(0, audio.size, piece):
            ws.send(pcm(audio[start:start + piece], fmt))
            replies.append(json.loads(ws.recv(timeout=30)))
        ws.send(json.dumps({"type": "end"}))
        replies.append(json.loads(ws.recv(timeout=30)))
        end = json.loads(ws.recv(timeout=30))
    frames = [r for r in replies if r["type"] == "frames"]
    assert len(frames) == len(replies), [r for r in replies if r["type"] != "frames"]
    out = {name: np.concatenate([np.asarray(r["outputs"][name], np.float32).reshape(-1, len(ready["outputs"][name]["channels"]))
                                 for r in frames]) for name in outputs}
    return {"ready": ready, "replies": frames, "end": end, **out}


def offline(live, audio: np.ndarray, seed: int) -> np.ndarray:
    """The library's offline streaming engine over the tokenizer's tokens of the whole audio."""
    from jaxtalk.models import toktalk
    from jaxtalk.models.toktalk.live import frames_for_audio

    tokens = live.tokenizer.encode(audio).embeddings
    motion = toktalk.stream(live.params, live.config, tokens[None], live.style, jax.random.key(seed))
    return np.asarray(motion)[0][: frames_for_audio(live.config, tokens.shape[0], audio.size)]


def test_concurrent_clients_each_get_their_own_stream_equal_to_the_offline_engine(server, live, speech):
    # Different audio, seeds, message sizes and sample formats, all at once.
    plans = [(speech[0], 700, 0, "f32le"), (speech[1], 2560, 5, "pcm_s16le"), (speech[2], 16000, 9, "f32le")]
    results: list[dict | BaseException] = [None] * len(plans)

    def run(i: int) -> None:
        audio, piece, seed, fmt = plans[i]
        try:
            results[i] = stream_through(server.url, audio, piece=piece, seed=seed, outputs=("params", "morph"), fmt=fmt)
        except BaseException as err:  # noqa: BLE001  (re-raised below, in the test's thread)
            results[i] = err

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(plans))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    morph = MorphOutput(builtin_face(0))
    for (audio, piece, seed, fmt), got in zip(plans, results, strict=True):
        if isinstance(got, BaseException):
            raise got
        # What the server decoded: float32 as sent, 16-bit samples quantised.
        heard = audio if fmt == "f32le" else np.frombuffer(pcm(audio, fmt), "<i2").astype(np.float32) / 32768
        want = offline(live, heard, seed)
        assert got["params"].shape == want.shape and got["end"] == {"type": "end", "frames": want.shape[0],
                                                                     "audio_s": audio.size / 16000}
        np.testing.assert_allclose(got["params"], want, atol=2e-6, rtol=0)  # JSON carries 6 decimals
        _, want_morph = morph.convert(morph.start(), want)
        np.testing.assert_allclose(got["morph"], want_morph, atol=2e-6, rtol=0)
        frame0 = [r["frame0"] for r in got["replies"]]
        counts = [r["count"] for r in got["replies"]]
        assert frame0 == list(np.cumsum([0, *counts[:-1]])) and all(c % 4 == 0 for c in counts[:-1])
        assert [r["t0"] for r in got["replies"]] == [f / 25 for f in frame0]
        assert all(r["compute_ms"] > 0 and r["queue_ms"] >= 0 and r["dropped"] == 0 for r in got["replies"])
        assert got["replies"][-1]["final"] and [r["seq"] for r in got["replies"][:-1]] == list(
            range(1, len(got["replies"])))
    assert not np.allclose(results[0]["params"][:20], results[1]["params"][:20])  # not one shared stream


def test_a_streams_arkit_output_is_what_jaxtalk_retarget_gives_its_motion(server, live, speech):
    """The live solve is the offline one: a client's ARKit weights, chunk after chunk, are those of
    `jaxtalk retarget` (the same retargeter, penalties and solver) over the whole utterance's motion."""
    from jaxtalk.export import DEFAULT_PENALTIES, Retargeter, arkit_rig
    from jaxtalk.export.solver import DEFAULT_TOL

    got = stream_through(server.url, speech[1], piece=2560, seed=3, outputs=("params", "arkit"))
    want = offline(live, speech[1], 3)
    result = Retargeter.for_face(arkit_rig(), builtin_face(0), DEFAULT_PENALTIES)(want)
    assert got["arkit"].shape == (want.shape[0], 55)
    # JSON carries 6 decimals: 5e-7 of rounding on top of the solver's tolerance
    np.testing.assert_allclose(got["arkit"][:, :52], result.weights, atol=5e-7 + DEFAULT_TOL, rtol=0)
    np.testing.assert_allclose(got["arkit"][:, 52:], result.head_angles, atol=5e-7 + 1e-7, rtol=0)


class NeverReading:
    """A WebSocket client on a bare socket (websockets' sans-I/O protocol) that reads nothing until told to:
    a hung process, or one whose network stalls. Its receive buffer is small, so the server's replies
    back up at once."""

    def __init__(self, url: str, port: int):
        from websockets.client import ClientProtocol
        from websockets.uri import parse_uri

        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        self.sock.connect(("127.0.0.1", port))
        self.protocol = ClientProtocol(parse_uri(url))
        self.protocol.send_request(self.protocol.connect())
        self._flush()
        self.events: list = []
        while not self.events:  # the handshake's response
            self.protocol.receive_data(self.sock.recv(65536))
            self.events = self.protocol.events_received()

    def _flush(self) -> None:
        self.sock.sendall(b"".join(self.protocol.data_to_send()))

    def send(self, message: str | bytes) -> None:
        if isinstance(message, str):
            self.protocol.send_text(message.encode())
        else:
            self.protocol.send_binary(message)
        self._flush()

    def read_all(self, until_seq: int) -> list[dict]:
        """Read at last: every JSON message up to the frames reply of message ``until_seq``."""
        out: list[dict] = []
        self.sock.settimeout(30)
        while not out or out[-1].get("seq") != until_seq:
            self.protocol.receive_data(self.sock.recv(65536))
            out += [json.loads(e.data) for e in self.protocol.events_received() if e.opcode.name == "TEXT"]
        return out


def test_a_client_that_never_reads_holds_up_nobody_and_loses_only_its_oldest_replies(server, speech):
    before = set(server.server.clients)
    slow = NeverReading(server.url, server.server.port)
    try:
        slow.send(json.dumps({"type": "hello", "sample_rate": 16000, "format": "f32le", "outputs": ["params", "morph"]}))
        deadline = time.monotonic() + 10
        while len(server.server.clients) == len(before) and time.monotonic() < deadline:
            time.sleep(0.01)
        (slow_client,) = [c for n, c in server.server.clients.items() if n not in before]
        second = np.tile(speech[2], 2)[:16000]
        for _ in range(40):  # 40 s of audio whose replies (~35 KB each) it does not read
            slow.send(pcm(second))
        started = time.perf_counter()
        fast = stream_through(server.url, speech[0], piece=2560, seed=1)
        fast_s = time.perf_counter() - started
        # The fast client streamed its 1.5 s in well under real time while the slow one's replies piled up.
        assert fast_s < 5.0 and fast["replies"][-1]["final"]
        assert all(r["dropped"] == 0 for r in fast["replies"])
        deadline = time.monotonic() + 15
        while slow_client.seq < 40 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert slow_client.seq == 40  # every message computed while nothing was read
        assert 20 < slow_client.outbox.dropped and len(slow_client.outbox.items) <= 4  # bounded, oldest dropped
        # Reading at last, the slow client sees the gap: fewer frames replies than messages, and the count.
        seen = slow.read_all(until_seq=40)
        frames = [m for m in seen if m["type"] == "frames"]
        assert seen[0]["type"] == "ready" and len(frames) < 20 and frames[-1]["dropped"] == 40 - len(frames)
        assert frames[-1]["seq"] == 40 and [m["seq"] for m in frames] == sorted(m["seq"] for m in frames)
    finally:
        slow.sock.close()


def test_a_client_gone_mid_stream_leaves_no_state_and_the_server_keeps_serving(server, speech):
    with client(server.url) as ws:
        hello(ws, ("params",))
        ws.send(pcm(speech[1][:8000]))
        assert json.loads(ws.recv(timeout=30))["type"] == "frames"
        (gone,) = list(server.server.clients.values())
        stream = weakref.ref(gone.stream)
        del gone
        ws.send(pcm(speech[1][8000:16000]))
        ws.socket.shutdown(socket.SHUT_RDWR)  # no closing handshake: the network just went away
    deadline = time.monotonic() + 30
    while (server.server.clients or stream() is not None) and time.monotonic() < deadline:
        time.sleep(0.05)
        gc.collect()
    assert not server.server.clients and stream() is None
    again = stream_through(server.url, speech[1][:8000], piece=4000, seed=0)
    assert again["params"].shape[0] == 12  # 0.5 s at 25 fps


def test_malformed_messages_are_answered_and_leave_the_stream_as_it_was(server, live, speech):
    audio = speech[0][:9000]
    with client(server.url) as ws:

        def answer(message) -> dict:
            ws.send(message)
            return json.loads(ws.recv(timeout=30))

        assert answer(pcm(audio[:100]))["code"] == "no_hello"
        assert answer("not json")["code"] == "bad_json"
        assert answer(json.dumps({"type": "sing"}))["code"] == "unknown_type"
        assert hello(ws)["type"] == "ready"  # a hello may follow a refused one, and another may follow it
        for message, code in (
            ({"type": "hello", "sample_rate": 44100, "format": "f32le"}, "bad_rate"),
            ({"type": "hello", "format": "f32le"}, "bad_hello"),
            ({"type": "hello", "sample_rate": 16000, "format": "mp3"}, "bad_format"),
            ({"type": "hello", "sample_rate": 16000, "outputs": ["params", "mesh"]}, "unknown_output"),
            ({"type": "hello", "sample_rate": 16000, "outputs": "params"}, "bad_hello"),
        ):
            reply = answer(json.dumps(message))
            assert reply["type"] == "error" and reply["code"] == code, (message, reply)
        hello(ws, ("params",), seed=3)
        frames = []
        good = [audio[i:i + 3000] for i in range(0, audio.size, 3000)]
        garbage = [b"\x01\x02\x03", np.full(10, np.nan, "<f4").tobytes(), np.full(10, 1e30, "<f4").tobytes(),
                   np.zeros(16001, "<f4").tobytes(), b""]
        codes = []
        for piece, bad in zip(good, garbage[:len(good)], strict=True):
            reply = answer(bad)
            codes.append(reply["code"])
            assert reply["type"] == "error" and reply["seq"] == len(codes) + len(frames)
            reply = answer(pcm(piece))
            assert reply["type"] == "frames"
            frames.append(reply)
        for bad in garbage[len(good):]:
            codes.append(answer(bad)["code"])
        assert codes == ["odd_length", "not_finite", "out_of_range", "too_large", "empty"]
        ws.send(json.dumps({"type": "end"}))
        frames.append(json.loads(ws.recv(timeout=30)))
        assert json.loads(ws.recv(timeout=30))["type"] == "end"
    got = np.concatenate([np.asarray(r["outputs"]["params"], np.float32).reshape(-1, 56) for r in frames])
    np.testing.assert_allclose(got, offline(live, audio, 3), atol=2e-6, rtol=0)  # as if the garbage was never sent
    # A message far over the limit is refused by websockets itself (1009), and only that connection closes.
    with client(server.url) as ws:
        hello(ws)
        ws.send(np.zeros(200_000, "<f4").tobytes())
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=30)
        assert closed.value.rcvd.code == 1009
    assert stream_through(server.url, audio[:4000], piece=4000, seed=0)["params"].shape[0] == 6


def test_a_hello_with_a_number_out_of_range_is_answered_bad_hello_and_the_connection_goes_on(server, caplog):
    huge = "1" + "0" * 400
    with client(server.url) as ws:

        def answer(text: str) -> dict:
            ws.send(text)
            return json.loads(ws.recv(timeout=30))

        for field, value in (("sample_rate", huge), ("seed", huge), ("seed", "-" + huge), ("sample_rate", "1e400"),
                             ("seed", "NaN"), ("seed", "-Infinity"), ("sample_rate", "true"), ("sample_rate", "-16000"),
                             ("seed", str(2**64))):
            fields = {"sample_rate": "16000", "seed": "0", field: value}
            reply = answer('{"type": "hello", "format": "f32le", ' + ", ".join(f'"{k}": {v}' for k, v in fields.items())
                           + "}")
            assert reply["type"] == "error" and reply["code"] == "bad_hello", (field, value, reply)
            assert reply["message"].startswith(f"hello.{field} must be an integer in"), reply
        assert answer('{"type": "hello", "sample_rate": 16000, "format": ["f32le"]}')["code"] == "bad_format"
        assert answer('{"type": "hello", "sample_rate": 16000, "seed": ' + "9" * 5000 + "}")["code"] == "bad_json"
        assert hello(ws)["type"] == "ready"  # still connected, and a good hello is served
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_ctrl_c_closes_a_streaming_client_with_going_away_and_stops_the_server_cleanly(trained_toktalk, speech,
                                                                                     monkeypatch, caplog):
    """``jaxtalk serve`` interrupted (SIGINT, as Ctrl-C sends it) while it waits and a client streams."""
    from typer.testing import CliRunner

    from jaxtalk import serve
    from jaxtalk.cli import app

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("Python raises KeyboardInterrupt in the main thread only")
    servers: queue.Queue = queue.Queue()

    def recorded(*args, **kw):
        running = start_server(*args, **kw)
        servers.put(running)
        return running

    monkeypatch.setattr(serve, "start_server", recorded)
    got: dict = {}

    def stream() -> None:
        try:
            got["running"] = servers.get(timeout=300)
            with client(got["running"].url) as ws:
                hello(ws)
                deadline, replies = time.monotonic() + 60, 0
                while time.monotonic() < deadline:
                    for start in range(0, speech[0].size, 640):
                        ws.send(pcm(speech[0][start:start + 640]))
                        assert json.loads(ws.recv(timeout=30))["type"] == "frames"
                        replies += 1
                        if replies == 5:  # Ctrl-C, while the command waits for the server
                            signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
        except ConnectionClosed as closed:
            got["code"] = closed.rcvd.code if closed.rcvd is not None else None
        except BaseException as err:  # noqa: BLE001  (reported below, in the test's thread)
            got["error"] = err

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    streamer = threading.Thread(target=stream)
    streamer.start()
    try:
        result = CliRunner().invoke(app, ["serve", str(trained_toktalk.dir), "--port", "0"])
    finally:
        signal.signal(signal.SIGINT, previous)
        streamer.join(90)
    assert "error" not in got, got
    assert result.exit_code == 0 and "listening on" in result.output and "Traceback" not in result.output, result.output
    assert got.get("code") == 1001  # going away, not 1011 (internal error)
    assert got["running"].done.is_set() and not got["running"].server.clients
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_an_allowed_origin_lets_in_its_pages_on_the_port_it_names_or_on_any_with_star(live):
    running = start_server(live, ServeOptions(port=0, origins=("https://Studio.example:*", "http://tool.example:8080")),
                           warm_up=False)
    try:
        for origin in ("https://studio.example", "https://studio.example:4443", "http://tool.example:8080"):
            with client(running.url, origin=origin):
                pass
        for origin in ("http://studio.example:4443", "https://studio.example.evil.example", "http://tool.example:8081",
                       "http://tool.example"):
            with pytest.raises(InvalidStatus) as refused:
                client(running.url, origin=origin)
            assert refused.value.response.status_code == 403, origin
        request = urllib.request.Request(running.url.replace("ws://", "http://") + "/face.glb",
                                         headers={"Origin": "https://studio.example:4443"})
        with urllib.request.urlopen(request, timeout=60) as response:
            assert response.headers["Access-Control-Allow-Origin"] == "https://studio.example:4443"
    finally:
        running.close()
    with pytest.raises(ValueError, match="--allow-origin 'notaurl' is not a web page origin"):
        LiveServer(live, ServeOptions(origins=("notaurl",)))


def test_the_server_binds_localhost_refuses_foreign_pages_and_serves_the_face_the_morph_output_drives(server):
    from typer.testing import CliRunner

    from jaxtalk.cli import app

    assert ServeOptions().host == "127.0.0.1" and server.url.startswith("ws://127.0.0.1:")
    assert server.server.address[0] == "127.0.0.1"
    assert "[default: 127.0.0.1]" in CliRunner().invoke(app, ["serve", "--help"], terminal_width=200).output
    with pytest.raises(InvalidStatus) as refused:
        client(server.url, origin="http://evil.example")
    assert refused.value.response.status_code == 403
    with client(server.url, origin="http://localhost:8000") as ws:  # `jaxtalk view --live`'s page
        assert hello(ws)["type"] == "ready"
    request = urllib.request.Request(server.url.replace("ws://", "http://") + "/face.glb",
                                     headers={"Origin": "http://127.0.0.1:8000"})
    with urllib.request.urlopen(request, timeout=30) as response:
        body, cors = response.read(), response.headers["Access-Control-Allow-Origin"]
    assert cors == "http://127.0.0.1:8000"
    # The file's morph targets are the morph output's channels, in order.
    glb = glb_from_bytes(body)
    with client(server.url) as ws:
        channels = tuple(hello(ws, ("morph",))["outputs"]["morph"]["channels"])
    assert glb.target_names == list(channels[:100]) and channels[100:] == tuple(
        f"{j}.q{c}" for j in ("jaw", "neck") for c in "xyzw")
    assert np.allclose(np.abs(np.asarray(glb.gltf.meshes[0].extras["jaxtalk"]["targetScale"])), 1.0)


def glb_from_bytes(body: bytes) -> GlbAnimation:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "face.glb"
        path.write_bytes(body)
        return GlbAnimation(path)


def test_a_full_server_tells_the_next_client_it_is_busy(live):
    running = start_server(live, ServeOptions(port=0, max_clients=1), warm_up=False)
    try:
        with client(running.url) as first:
            hello(first)
            with client(running.url) as second:
                reply = json.loads(second.recv(timeout=30))
                assert reply["code"] == "busy"
                with pytest.raises(ConnectionClosed) as closed:
                    second.recv(timeout=30)
                assert closed.value.rcvd.code == 1013
        deadline = time.monotonic() + 10
        while running.server.clients and time.monotonic() < deadline:
            time.sleep(0.05)
        with client(running.url) as third:
            assert hello(third)["type"] == "ready"
    finally:
        running.close()


class LinearARKit:
    """A stand-in ARKit converter with fixed linear weights per channel, so that what reaches Live Link can
    be checked value by value (the real converter's values are tested in test_serve_protocol.py)."""

    name = "arkit"
    channels = (*ARKIT_NAMES, "HeadYaw", "HeadPitch", "HeadRoll")

    def __init__(self):
        self.matrix = np.random.default_rng(0).normal(scale=0.1, size=(56, len(self.channels))).astype(np.float32)

    def start(self):
        return 0

    def convert(self, state, params):
        return state + len(params), np.asarray(params, np.float32) @ self.matrix

    def describe(self):
        return {"channels": list(self.channels)}


def test_live_link_sends_each_frame_of_the_arkit_output_to_a_local_receiver(live, speech):
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.bind(("127.0.0.1", 0))
    receiver.settimeout(10.0)
    running = start_server(live, ServeOptions(port=0, live_link=("127.0.0.1", receiver.getsockname()[1])),
                           outputs={**OUTPUTS, "arkit": LinearARKit}, warm_up=False)
    try:
        audio = speech[0][:16000]
        started = time.monotonic()
        with client(running.url) as ws:
            ready = hello(ws, ("arkit",), subject="talker")
            assert ready["live_link"] == {"address": ["127.0.0.1", receiver.getsockname()[1]], "subject": "talker"}
            replies = []
            for i in range(0, audio.size, 1600):
                ws.send(pcm(audio[i:i + 1600]))
                replies.append(json.loads(ws.recv(timeout=30)))
            ws.send(json.dumps({"type": "end"}))
            replies.append(json.loads(ws.recv(timeout=30)))
            sent = np.concatenate([np.asarray(r["outputs"]["arkit"], np.float32).reshape(-1, 55) for r in replies])
            packets = [decode_packet(receiver.recvfrom(2048)[0]) for _ in range(sent.shape[0])]
        elapsed = time.monotonic() - started
    finally:
        running.close()
        receiver.close()
    assert sent.shape[0] == 25
    assert [p.frame for p in packets] == list(range(25)) and {p.subject for p in packets} == {"talker"}
    assert {p.fps for p in packets} == {(25, 1)}
    index = [LIVE_LINK_CURVES.index(c[:1].upper() + c[1:]) for c in LinearARKit.channels]
    values = np.stack([p.values for p in packets])
    np.testing.assert_allclose(values[:, index], sent, atol=2e-6)
    assert not np.delete(values, index, axis=1).any()  # the eyes' curves: 0
    assert elapsed >= 0.9  # paced at 25 fps, not sent in bursts
