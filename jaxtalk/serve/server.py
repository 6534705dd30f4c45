"""The live server behind ``jaxtalk serve``: WebSocket clients stream audio in and get frames back.

Each client gets its own stream (the live model's ``open(key)``: the model's carried stream state) and
its own output converters' states; every client shares one model and its compiled step. All model work
runs on one worker thread (the device), so device calls never overlap, while the event loop keeps every
socket moving: a client's messages are handled one at a time, in order, and its next message is read
only once the previous one is computed, so a client that sends faster than the model runs is slowed
by TCP (websockets buffers at most ``max_queue`` messages), not by growing memory. Replies go through a
bounded outbox per client, behind a fixed kernel send buffer: a client that does not read its replies
has the oldest ``frames`` message dropped when the outbox is full (each later reply's ``dropped`` counts
them), and never holds up another client.

The server binds 127.0.0.1 unless told otherwise, and refuses WebSocket handshakes whose ``Origin`` is a
web page on another host (a browser page on any site could otherwise open ``ws://127.0.0.1``).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import dataclasses
import functools
import json
import os
import re
import socket
import sys
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from typing import Any

import numpy as np

from jaxtalk.serve.outputs import OUTPUTS, Output, OutputUnavailable, build_outputs
from jaxtalk.serve.protocol import (
    PROTOCOL,
    Hello,
    ProtocolError,
    decode_pcm,
    error_message,
    parse_hello,
    parse_message,
)

__all__ = ["LiveServer", "RunningServer", "ServeOptions", "listen_socket", "origin_pattern", "rss_bytes",
           "start_server"]

_LOCAL_ORIGIN = re.compile(r"https?://(localhost|127\.0\.0\.1|\[::1\])(:\d+)?")
# An origin as browsers send it: scheme, host (a name, an IPv4 address or a bracketed IPv6 one) and port.
_ORIGIN = re.compile(r"(https?)://(\[[0-9a-f:.]+\]|[a-z0-9]([a-z0-9.-]*[a-z0-9])?)(:(\d{1,5}|\*))?", re.IGNORECASE)


@dataclasses.dataclass(frozen=True)
class ServeOptions:
    """Settings of the live server.

    Attributes:
        host: the interface to bind (127.0.0.1: this machine only).
        port: the TCP port (0: any free one, see :attr:`LiveServer.port`).
        max_clients: clients served at once; one more is refused with ``busy``.
        max_chunk_s: the longest audio message, in seconds (longer ones get ``too_large``).
        outbox: replies queued per client before the oldest ``frames`` reply is dropped.
        max_queue: incoming messages websockets buffers per client before it stops reading the socket.
        send_buffer: the kernel's send buffer per client, bytes (fixed, not auto-tuned: a client that
            reads slowly then sees at most this much of stale frames before its outbox starts dropping,
            instead of the megabytes Linux would otherwise let queue up).
        live_link: ``(host, port)`` to send every client's ARKit curves to as Live Link Face packets
            (needs the ``arkit`` output), or None.
        origins: web page origins allowed besides this machine's own (``http://localhost:*``...), each
            as :func:`origin_pattern` takes it.
    """

    host: str = "127.0.0.1"
    port: int = 8765
    max_clients: int = 8
    max_chunk_s: float = 1.0
    outbox: int = 8
    max_queue: int = 4
    send_buffer: int = 64 * 1024
    live_link: tuple[str, int] | None = None
    origins: tuple[str, ...] = ()


def origin_pattern(origin: str) -> re.Pattern[str]:
    """The ``Origin`` headers an allowed origin lets in.

    Args:
        origin: ``http(s)://HOST`` or ``http(s)://HOST:PORT``, PORT ``*`` for any port (or none), as
            ``http://localhost:*`` stands for this machine's own pages.

    Raises:
        ValueError: anything else (another scheme, no host, a path, a port beyond 65535), in one line.
    """
    found = _ORIGIN.fullmatch(origin)
    port = found.group(5) if found else None
    if found is None or (port not in (None, "*") and not 0 < int(port) <= 65535):
        raise ValueError(f"--allow-origin {origin!r} is not a web page origin: expected http(s)://HOST or "
                         "http(s)://HOST:PORT (PORT * for any), e.g. https://example.com or http://localhost:*")
    # Browsers send the scheme and host in lower case, and no port for the scheme's default one.
    scheme = found.group(1).lower()
    base = re.escape(f"{scheme}://{found.group(2)}".lower())
    if port == "*":
        return re.compile(base + r"(:\d+)?")
    if port is None or int(port) == {"http": 80, "https": 443}[scheme]:
        return re.compile(base + (f"(:{int(port)})?" if port else ""))
    return re.compile(base + re.escape(f":{int(port)}"))


def listen_socket(host: str, port: int) -> socket.socket:
    """A TCP socket listening on ``host:port`` (0: any free port; the first address ``host`` resolves to),
    for :func:`start_server`'s ``sock``: bound before the model loads, so that a port in use is said at
    once, and held until the server takes it over, so that nothing else takes the port in between.
    Clients that connect before the server serves wait in the kernel's backlog.

    Raises:
        OSError: the address is in use (errno EADDRINUSE) or cannot be bound (an unknown host, ...).
    """
    family, _, _, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
    # socket.create_server sets SO_REUSEADDR as asyncio's server does (a restarted server rebinds a port
    # whose old connections linger in TIME_WAIT) and IPV6_V6ONLY for an IPv6 address.
    return socket.create_server(address, family=family)


def rss_bytes() -> int:
    """This process's resident memory in bytes (Linux: /proc; elsewhere the peak, from getrusage)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        import resource

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return int(peak if sys.platform == "darwin" else peak * 1024)


class _Outbox:
    """A client's bounded reply queue: when full, the oldest ``frames`` reply (else the oldest reply) goes."""

    def __init__(self, limit: int):
        self.limit = limit
        self.items: collections.deque[dict[str, Any]] = collections.deque()
        self.ready = asyncio.Event()
        self.dropped = 0

    def put(self, message: dict[str, Any]) -> None:
        if len(self.items) >= self.limit:
            victim = next((m for m in self.items if m["type"] == "frames"), self.items[0])
            self.items.remove(victim)
            self.dropped += 1
        self.items.append(message)
        self.ready.set()

    async def get(self) -> dict[str, Any]:
        while not self.items:
            self.ready.clear()
            await self.ready.wait()
        return self.items.popleft()


class _Client:
    """One connection's state: its hello, stream, output states, outbox and Live Link sender."""

    def __init__(self, number: int, outbox: int):
        self.number = number
        self.hello: Hello | None = None
        self.stream: Any = None
        self.outputs: dict[str, Output] = {}
        self.states: dict[str, Any] = {}
        self.outbox = _Outbox(outbox)
        self.seq = 0
        self.frames = 0  # frames sent in this utterance
        self.samples = 0  # samples received in this utterance
        self.live_link: Any = None
        self.link_anchor: float | None = None  # loop time of frame 0 for the Live Link pacing


class LiveServer:
    """The server (module docstring); run it with :func:`start_server` or ``await server.run(stop)``.

    Args:
        model: the live model (``fps``, ``sample_rate``, ``chunk_frames``, ``lookahead_samples``,
            ``describe()``, ``open(key) -> stream`` whose ``push(samples)`` and ``finish()`` return
            ``(n, 56)`` frames), e.g. :class:`jaxtalk.models.toktalk.live.LiveModel`.
        options: :class:`ServeOptions`.
        outputs: output name -> converter factory (default :data:`~jaxtalk.serve.outputs.OUTPUTS`).
        key_fn: seed -> the stream's PRNG key (default ``jax.random.key``).
    """

    def __init__(self, model: Any, options: ServeOptions = ServeOptions(), *,
                 outputs: dict[str, Callable[[], Output]] | None = None, key_fn: Callable[[int], Any] | None = None):
        self.model = model
        self.options = options
        self.registry = dict(OUTPUTS if outputs is None else outputs)
        self._converters: dict[str, Output] = {}
        self._key_fn = key_fn
        self.clients: dict[int, _Client] = {}
        self._count = 0
        self._device = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="jaxtalk-serve-device")
        self.port: int | None = None
        self.address: tuple[str, int] | None = None  # the bound socket's (host, port)
        self.warmed_s: float | None = None  # what warm_up took, when it ran
        self.started = time.monotonic()
        self.max_chunk_samples = max(1, round(options.max_chunk_s * model.sample_rate))
        self.origins = tuple(origin_pattern(o) for o in options.origins)  # refused here, before serving
        if options.live_link is not None:
            build_outputs(("arkit",), self._converters, self.registry)  # refused here, before serving

    def warm_up(self) -> float:
        """Compile what a client's first chunk and last frames run (the model's step, the tokenizer, every
        output that can be built), so that no client waits for XLA; returns the seconds it took."""
        started = time.perf_counter()
        stream = self.model.open(self._key(0))
        frames = [stream.push(np.zeros(self.model.chunk_samples + self.model.lookahead_samples, np.float32)),
                  stream.finish()]
        for name, reason in self.output_status().items():
            if reason is not None:
                continue
            out = self._converters[name]
            state = out.start()
            for chunk in frames:
                state, _ = out.convert(state, chunk)
        return time.perf_counter() - started

    def output_status(self) -> dict[str, str | None]:
        """Each output's name -> None when this server can produce it, else why not."""
        status = {}
        for name in self.registry:
            try:
                build_outputs((name,), self._converters, self.registry)
                status[name] = None
            except OutputUnavailable as err:
                status[name] = str(err)
        return status

    # ------------------------------------------------------------------ running

    async def run(self, stop: asyncio.Future | asyncio.Event, ready: Callable[[LiveServer], None] | None = None, *,
                  sock: socket.socket | None = None) -> None:
        """Serve until ``stop`` is set (an Event) or done (a Future), on ``sock`` (a listening socket, e.g.
        :func:`listen_socket`'s; closed when the server stops) or else on the options' host and port;
        then close every client with 1001 (going away)."""
        from websockets.asyncio.server import serve

        origins = [None, _LOCAL_ORIGIN, *self.origins]
        # Audio messages are bounded by max_chunk_samples (too_large, answered); websockets itself closes a
        # connection whose message is over 4x that (1009), so nothing unbounded is ever buffered.
        max_size = 4 * 4 * self.max_chunk_samples + 4096
        where = {"sock": sock} if sock is not None else {"host": self.options.host, "port": self.options.port}
        async with serve(self._connection, **where, origins=origins,
                         process_request=self._http, compression=None, max_size=max_size,
                         max_queue=self.options.max_queue, ping_interval=20, ping_timeout=20) as server:
            self.address = next(iter(server.sockets)).getsockname()[:2]
            self.port = self.address[1]
            if ready is not None:
                ready(self)
            await (stop.wait() if isinstance(stop, asyncio.Event) else stop)
        self._device.shutdown(wait=True)

    def _http(self, connection: Any, request: Any) -> Any:
        """Plain HTTP GET ``/face.glb``: the file the ``morph`` output drives (CORS open to local pages)."""
        if request.path.split("?")[0] != "/face.glb" or request.headers.get("Upgrade"):
            return None
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        try:
            body = build_outputs(("morph",), self._converters, self.registry)["morph"].glb
        except (KeyError, OutputUnavailable, AttributeError) as err:
            return connection.respond(HTTPStatus.NOT_FOUND, f"no face file: {err}\n")
        headers = Headers([("Content-Type", "model/gltf-binary"), ("Content-Length", str(len(body))),
                           ("Cache-Control", "no-store")])
        origin = request.headers.get("Origin")
        if origin and any(p.fullmatch(origin) for p in (_LOCAL_ORIGIN, *self.origins)):
            headers["Access-Control-Allow-Origin"] = origin
        return Response(200, "OK", headers, body)

    # ------------------------------------------------------------------ connections

    async def _connection(self, ws: Any) -> None:
        from websockets.exceptions import ConnectionClosed

        if len(self.clients) >= self.options.max_clients:
            await ws.send(json.dumps(error_message("busy", f"this server serves {self.options.max_clients} clients at "
                                                           "once; try again later")))
            await ws.close(1013, "busy")
            return
        raw = ws.transport.get_extra_info("socket")
        if raw is not None:
            raw.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.options.send_buffer)
        self._count += 1
        client = _Client(self._count, self.options.outbox)
        self.clients[client.number] = client
        writer = asyncio.create_task(self._write(ws, client))
        try:
            async for message in ws:
                await self._message(client, message)
        except ConnectionClosed:
            pass
        finally:
            writer.cancel()
            del self.clients[client.number]
            if client.live_link is not None:
                client.live_link.close()
            client.stream = None  # the stream state goes with the connection

    async def _write(self, ws: Any, client: _Client) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            while True:
                message = await client.outbox.get()
                if message["type"] == "frames":
                    message["dropped"] = client.outbox.dropped
                await ws.send(json.dumps(message, separators=(",", ":")))
        except ConnectionClosed:
            pass

    async def _message(self, client: _Client, message: str | bytes) -> None:
        try:
            if isinstance(message, str):
                await self._control(client, parse_message(message))
            elif client.hello is None:
                raise ProtocolError("no_hello", 'send a hello first: {"type": "hello", "sample_rate": '
                                                f'{self.model.sample_rate}, "format": "pcm_s16le", "outputs": ["params"]}}')
            else:
                samples = decode_pcm(message, client.hello.format, self.max_chunk_samples)
                await self._compute(client, samples)
        except (ProtocolError, ValueError) as err:
            # A ValueError past the protocol's checks is the library refusing what it was given: said, and
            # the connection goes on (the stream state is unchanged: the push raised before any step).
            client.seq += isinstance(message, bytes)
            code = err.code if isinstance(err, ProtocolError) else "internal"
            client.outbox.put(error_message(code, str(err), **({"seq": client.seq} if isinstance(message, bytes)
                                                                else {})))

    async def _control(self, client: _Client, message: dict[str, Any]) -> None:
        kind = message["type"]
        if kind == "hello":
            hello = parse_hello(message, sample_rate=self.model.sample_rate, outputs=tuple(self.registry))
            try:
                outputs = build_outputs(hello.outputs, self._converters, self.registry)
            except OutputUnavailable as err:
                raise ProtocolError("output_unavailable", str(err)) from None
            client.hello, client.outputs = hello, outputs
            client.states = {name: out.start() for name, out in outputs.items()}
            client.stream = self.model.open(self._key(hello.seed))
            client.seq = client.frames = client.samples = 0
            await self._link(client)
            client.outbox.put({"type": "ready", "protocol": PROTOCOL, "session": client.number, **self.model.describe(),
                               "format": hello.format, "max_chunk_samples": self.max_chunk_samples,
                               "outputs": {name: out.describe() for name, out in outputs.items()},
                               "live_link": None if client.live_link is None else
                               {"address": list(self.options.live_link), "subject": hello.subject}})
        elif kind == "end":
            if client.hello is None:
                raise ProtocolError("no_hello", "nothing to end: send a hello and audio first")
            await self._compute(client, None)
            client.outbox.put({"type": "end", "frames": client.frames, "audio_s": client.samples / self.model.sample_rate})
            client.frames = client.samples = 0
            client.link_anchor = None
        elif kind == "stats":
            client.outbox.put(self.stats(client))
        else:
            raise ProtocolError("unknown_type", f"unknown message type {kind!r}: expected hello, end or stats")

    def _key(self, seed: int) -> Any:
        if self._key_fn is not None:
            return self._key_fn(seed)
        import jax

        return jax.random.key(seed)

    async def _link(self, client: _Client) -> None:
        if client.live_link is not None:
            client.live_link.close()
            client.live_link = None
        if self.options.live_link is not None:
            from jaxtalk.export.livelink import LiveLinkSender

            client.live_link = LiveLinkSender(self.options.live_link, subject=client.hello.subject,
                                              fps=(int(self.model.fps), 1))

    async def _compute(self, client: _Client, samples: np.ndarray | None) -> None:
        """One audio message (or the utterance's end) through the model on the device thread, then the
        reply into the outbox and the frames to Live Link."""
        received = time.perf_counter()
        loop = asyncio.get_running_loop()
        frame0 = client.frames
        values, compute_s, started = await loop.run_in_executor(
            self._device, functools.partial(self._work, client, samples))
        if samples is not None:
            client.seq += 1
            client.samples += samples.size
        count = next(iter(values.values())).shape[0]
        client.frames += count
        fps = self.model.fps
        client.outbox.put({
            "type": "frames", "seq": client.seq, "final": samples is None, "frame0": frame0, "count": count,
            "t0": frame0 / fps, "fps": fps, "audio_s": client.samples / self.model.sample_rate,
            "compute_ms": round(1e3 * compute_s, 3), "queue_ms": round(1e3 * (started - received), 3),
            "outputs": {name: np.round(v.astype(np.float64), 6).tolist() for name, v in values.items()
                        if name in client.hello.outputs},
        })
        if client.live_link is not None and count:
            self._pace(client, values["arkit"], frame0)

    def _work(self, client: _Client, samples: np.ndarray | None) -> tuple[dict[str, np.ndarray], float, float]:
        """On the device thread: the model's frames and every output's values."""
        started = time.perf_counter()
        stream = client.stream
        frames = stream.push(samples) if samples is not None else stream.finish()
        wanted = client.hello.outputs + (("arkit",) if client.live_link is not None else ())
        outputs = build_outputs(tuple(dict.fromkeys(wanted)), self._converters, self.registry)
        values = {}
        for name, out in outputs.items():
            state = client.states[name] if name in client.states else out.start()
            client.states[name], values[name] = out.convert(state, frames)
        return values, time.perf_counter() - started, started

    def _pace(self, client: _Client, arkit: np.ndarray, frame0: int) -> None:
        """Send the frames to Live Link at the frame rate: frame ``f`` at ``anchor + f / fps``, the anchor
        set by the first frames and moved when frames come later than due or over a second early (a
        client sending faster than real time)."""
        from jaxtalk.export.arkit import LIVE_LINK_HEAD_CURVES
        from jaxtalk.export.recording import live_link_curves

        loop = asyncio.get_running_loop()
        now, fps = loop.time(), self.model.fps
        due = None if client.link_anchor is None else client.link_anchor + frame0 / fps
        if due is None or due < now or due > now + 1.0:
            client.link_anchor = now - frame0 / fps
        channels = self._converters["arkit"].channels
        head = [channels.index(c) for c in LIVE_LINK_HEAD_CURVES] if set(LIVE_LINK_HEAD_CURVES) <= set(channels) else []
        shapes = [i for i in range(len(channels)) if i not in head]
        curves = live_link_curves([channels[i] for i in shapes], arkit[:, shapes], arkit[:, head] if head else None)
        sender = client.live_link
        for i in range(curves.shape[0]):
            loop.call_at(client.link_anchor + (frame0 + i) / fps, sender.send, curves[i:i + 1], frame0 + i)

    # ------------------------------------------------------------------ introspection

    def stats(self, client: _Client | None = None) -> dict[str, Any]:
        """The ``stats`` reply: clients, resident memory, Python's allocated blocks, and this client's counts."""
        out = {"type": "stats", "clients": len(self.clients), "rss_bytes": rss_bytes(),
               "python_blocks": sys.getallocatedblocks(), "uptime_s": round(time.monotonic() - self.started, 3)}
        if client is not None:
            out.update({"session": client.number, "frames": client.frames, "audio_s":
                        client.samples / self.model.sample_rate, "dropped": client.outbox.dropped})
        return out


@dataclasses.dataclass
class RunningServer:
    """A server running on its own thread and event loop: :attr:`url`; :meth:`close` stops it."""

    server: LiveServer
    thread: threading.Thread
    loop: asyncio.AbstractEventLoop
    stop: asyncio.Event
    done: threading.Event  # set once the thread has served its last client and stopped

    @property
    def url(self) -> str:
        host = self.server.options.host
        return f"ws://{f'[{host}]' if ':' in host else host}:{self.server.port}"

    def close(self) -> None:
        """Stop serving: every client is closed with 1001 (going away), and this returns once the server
        has stopped (its clients' work done, its device thread ended).

        It waits on :attr:`done`, not on the thread's state: a Ctrl-C that interrupts ``thread.join()``
        (``jaxtalk serve``'s wait) can leave CPython (3.11, for one) calling the thread finished while it
        still serves, and then neither ``is_alive()`` nor ``join()`` tells.
        """
        if not self.done.is_set():
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile: the server has stopped
                self.loop.call_soon_threadsafe(self.stop.set)
        self.done.wait()
        self.thread.join()


def start_server(model: Any, options: ServeOptions = ServeOptions(), *, warm_up: bool = True,
                 sock: socket.socket | None = None, **kw: Any) -> RunningServer:
    """Start a :class:`LiveServer` on a background thread (after :meth:`LiveServer.warm_up`); returns once it
    listens.

    Args:
        model, options, kw: as :class:`LiveServer` takes them.
        warm_up: compile the model's step before serving.
        sock: a listening socket to serve on (:func:`listen_socket`) instead of binding the options' host
            and port; the server owns it from here on (closed when it stops, or fails to start).

    Raises:
        OSError: the address is in use or cannot be bound (errno EADDRINUSE, ...).
        OutputUnavailable: ``live_link`` without an ``arkit`` output.
        ValueError: an origin :func:`origin_pattern` refuses.
    """
    try:
        server = LiveServer(model, options, **kw)
        server.warmed_s = server.warm_up() if warm_up else None
    except BaseException:
        if sock is not None:
            sock.close()
        raise
    started, done = threading.Event(), threading.Event()
    box: dict[str, Any] = {}

    def main() -> None:
        async def serve() -> None:
            box["loop"], box["stop"] = asyncio.get_running_loop(), asyncio.Event()
            await server.run(box["stop"], ready=lambda _: started.set(), sock=sock)

        try:
            asyncio.run(serve())
        except BaseException as err:  # noqa: BLE001  (handed to the caller, which re-raises it)
            box["error"] = err
        finally:
            started.set()
            done.set()

    thread = threading.Thread(target=main, name="jaxtalk-serve", daemon=True)
    thread.start()
    started.wait()
    if "error" in box:
        thread.join()
        if sock is not None:
            sock.close()
        raise box["error"]
    return RunningServer(server, thread, box["loop"], box["stop"], done)
