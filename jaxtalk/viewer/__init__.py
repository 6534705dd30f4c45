"""``jaxtalk view``: a page on localhost that plays the ``.glb`` files of a folder in sync with their audio, or
(``--live``, :func:`start_live_server`) streams the microphone or a file to ``jaxtalk serve`` and drives the
face with the frames that come back, showing the measured latency (``web/live.html``, ``web/live.js``,
``web/capture.js``).

The page (``web/index.html``, ``web/viewer.js``) runs three.js, which is not copied into jaxtalk: it is
installed from the npm registry by ``npm ci`` against ``web/package-lock.json`` into a cache folder
(once per lock file), and served from there. Without Node.js and npm, :func:`install_web_dependencies`
says so in one line.

The server answers only on 127.0.0.1, only to requests whose ``Host`` is this machine (``localhost``,
``127.0.0.1`` or ``[::1]``, with the server's port or none: a page on another site whose name was
rebound to 127.0.0.1 gets 403), and serves only: the page, the installed three.js, ``clips.json``
(the folder's ``.glb`` files and the ``.wav`` beside each) and those files themselves (with byte ranges,
so the audio element can seek); live, the live page, its audio worklet and ``live.json`` (the server's
address; the face comes from the server itself).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import json
import mimetypes
import os
import shutil
import subprocess
import threading
import uuid
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlparse

__all__ = ["ViewerError", "ViewerServer", "WEB_DIR", "clips", "install_web_dependencies", "start_live_server",
           "start_server", "write_stream_page"]

WEB_DIR = Path(__file__).with_name("web")
DEFAULT_CACHE = Path.home() / ".cache" / "jaxtalk" / "viewer"
_SHARED_FILES = {"/stage.js": "stage.js", "/viewer.css": "viewer.css"}
_PAGE_FILES = {"/": "index.html", "/index.html": "index.html", "/viewer.js": "viewer.js", **_SHARED_FILES}
_LIVE_FILES = {"/": "live.html", "/index.html": "live.html", "/live.js": "live.js", "/capture.js": "capture.js",
               "/sources.js": "sources.js", **_SHARED_FILES}
_TYPES = {".js": "text/javascript", ".css": "text/css", ".html": "text/html; charset=utf-8", ".glb": "model/gltf-binary",
          ".wav": "audio/wav", ".json": "application/json"}


class ViewerError(RuntimeError):
    """The viewer cannot run here (no Node.js/npm, or its install failed); the message says why."""


def install_web_dependencies(cache_dir: str | os.PathLike | None = None, *, npm: str | None = None) -> Path:
    """The page's ``node_modules``, installed by ``npm ci`` from the lock file if not cached yet.

    Args:
        cache_dir: where installs are kept (default ``~/.cache/jaxtalk/viewer``), one folder per lock file.
        npm: the npm executable (default: ``npm`` on ``PATH``).

    Returns:
        The ``node_modules`` folder holding ``three``.

    Raises:
        ViewerError: npm is not installed, or ``npm ci`` failed (its last output lines are quoted).
    """
    lock = (WEB_DIR / "package-lock.json").read_bytes()
    root = Path(cache_dir or DEFAULT_CACHE) / hashlib.sha256(lock).hexdigest()[:16]
    modules = root / "node_modules"
    if (modules / "three" / "package.json").is_file() and (modules / "onnxruntime-web" / "package.json").is_file():
        return modules
    npm = npm or shutil.which("npm")
    if npm is None or shutil.which("node") is None:
        raise ViewerError("jaxtalk view needs Node.js and npm to install three.js from its lock file; install "
                          "Node.js 18 or newer (https://nodejs.org, or your system's 'nodejs' and 'npm' packages) "
                          "and run the command again")
    # Install into a fresh folder, then rename it into place: a second process or an interrupted
    # install never leaves a half-filled cache behind.
    root.parent.mkdir(parents=True, exist_ok=True)
    work = root.parent / f".install-{uuid.uuid4().hex[:12]}"
    work.mkdir()
    try:
        for name in ("package.json", "package-lock.json"):
            shutil.copyfile(WEB_DIR / name, work / name)
        done = subprocess.run([npm, "ci", "--ignore-scripts", "--no-audit", "--no-fund"], cwd=work,
                              capture_output=True, text=True)
        if done.returncode != 0:
            tail = "\n".join((done.stderr or done.stdout).strip().splitlines()[-5:])
            raise ViewerError(f"npm ci could not install the viewer's three.js (exit {done.returncode}; is the npm "
                              f"registry reachable?):\n{tail}")
        with contextlib.suppress(OSError):  # another process finished first: keep its install
            work.rename(root)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return modules


# The stream page's files: its own (source -> name in the folder), and what it loads of the installed packages.
_STREAM_PAGE_FILES = {"stream.html": "index.html", "stream.js": "stream.js", "capture.js": "capture.js",
                      "sources.js": "sources.js", "stage.js": "stage.js", "viewer.css": "viewer.css"}
_STREAM_VENDOR_FILES = ("three/build/three.module.js", "three/build/three.core.js",
                        "three/examples/jsm/loaders/GLTFLoader.js", "three/examples/jsm/utils/BufferGeometryUtils.js",
                        "three/examples/jsm/utils/SkeletonUtils.js", "three/examples/jsm/controls/OrbitControls.js",
                        "onnxruntime-web/dist/ort.wasm.min.mjs", "onnxruntime-web/dist/ort-wasm-simd-threaded.mjs",
                        "onnxruntime-web/dist/ort-wasm-simd-threaded.wasm",
                        "three/LICENSE")


def write_stream_page(folder: str | os.PathLike, cache_dir: str | os.PathLike | None = None) -> Path:
    """Write the static page that runs an exported stream (``jaxtalk export-model``) into ``folder``: its HTML
    and scripts, and the three.js and onnxruntime-web files it loads (``vendor/``, from
    :func:`install_web_dependencies`). Any static file server serves the folder; nothing answers but files.

    Returns:
        The page, ``folder/index.html``.

    Raises:
        ViewerError: npm is not installed, or its install failed.
    """
    modules = install_web_dependencies(cache_dir)
    folder = Path(folder)
    for source, name in _STREAM_PAGE_FILES.items():
        shutil.copyfile(WEB_DIR / source, folder / name)
    for name in _STREAM_VENDOR_FILES:
        target = folder / "vendor" / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(modules / name, target)
    return folder / "index.html"


def clips(folder: str | os.PathLike) -> list[dict]:
    """The folder's exported clips: ``{"name", "glb", "audio"}`` per ``.glb`` (audio: ``NAME.glb.wav`` as
    ``jaxtalk export`` writes it, else the ``NAME.wav`` older exports wrote, else ``None``), as the page
    fetches them."""
    out = []
    for glb in sorted(Path(folder).glob("*.glb")):
        # The export's own name first (it never collides with the recording the clip was made from).
        wav = glb.with_name(glb.name + ".wav")
        if not wav.is_file():
            wav = glb.with_suffix(".wav")
        out.append({"name": glb.stem, "glb": f"/data/{glb.name}", "audio": f"/data/{wav.name}" if wav.is_file() else None})
    return out


@dataclasses.dataclass
class ViewerServer:
    """A running viewer: open :attr:`url`; :meth:`close` stops it."""

    httpd: ThreadingHTTPServer
    thread: threading.Thread

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{host}:{port}/"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join()


_LOCAL_NAMES = ("localhost", "127.0.0.1", "[::1]")


def _local_host(host: str | None, port: int) -> bool:
    """Whether a request's ``Host`` header names this machine (with ``port`` or no port). A request
    without one (HTTP/1.0) is not a browser's and passes; DNS rebinding always sends the attacker's name."""
    if host is None:
        return True
    host = host.strip().lower()
    end = host.rfind("]") + 1 if host.startswith("[") else 0
    rest, _, given = host[end:].partition(":")
    name = host[:end] + rest
    return name in _LOCAL_NAMES and given in ("", str(port))


def _handler(folder: Path | None, modules: Path, live: str | None = None) -> type[BaseHTTPRequestHandler]:
    """Folder mode (``folder``) or live mode (``live``: the ``jaxtalk serve`` address the page connects to)."""
    three = (modules / "three").resolve()
    pages = _PAGE_FILES if live is None else _LIVE_FILES

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, format: str, *args) -> None:  # noqa: A002  (the base class's name)
            pass  # quiet: the command prints its URL, not every request

        def _file(self, path: Path) -> None:
            size = path.stat().st_size
            start, end = 0, size - 1
            status = HTTPStatus.OK
            ranged = self.headers.get("Range", "")
            if ranged.startswith("bytes=") and "," not in ranged:
                first, _, last = ranged[6:].partition("-")
                start = int(first) if first else max(0, size - int(last or 0))
                end = min(int(last), size - 1) if first and last else end
                if start > end:
                    self.send_error(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
                    return
                status = HTTPStatus.PARTIAL_CONTENT
            self.send_response(status)
            self.send_header("Content-Type", _TYPES.get(path.suffix, mimetypes.guess_type(path.name)[0]
                                                        or "application/octet-stream"))
            self.send_header("Content-Length", str(end - start + 1))
            self.send_header("Accept-Ranges", "bytes")
            self.send_header("Cache-Control", "no-store")
            if status == HTTPStatus.PARTIAL_CONTENT:
                self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
            self.end_headers()
            with open(path, "rb") as f:
                f.seek(start)
                self.wfile.write(f.read(end - start + 1))

        def do_GET(self) -> None:  # noqa: N802  (http.server's name)
            if not _local_host(self.headers.get("Host"), self.server.server_address[1]):
                self.send_error(HTTPStatus.FORBIDDEN, "jaxtalk view answers only to localhost")
                return None
            route = unquote(urlparse(self.path).path)
            if route in pages:
                return self._file(WEB_DIR / pages[route])
            if route in ("/clips.json", "/live.json") and (route == "/live.json") == (live is not None):
                body = json.dumps(clips(folder) if live is None else {"server": live}).encode()
                self.send_response(HTTPStatus.OK)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)
                return None
            if route.startswith("/data/") and folder is not None:
                target = folder / route[len("/data/"):]
                if target.parent == folder and target.suffix in (".glb", ".wav") and target.is_file():
                    return self._file(target)
            elif route.startswith("/vendor/three/"):
                target = (three / route[len("/vendor/three/"):]).resolve()
                if target.is_relative_to(three) and target.is_file():
                    return self._file(target)
            self.send_error(HTTPStatus.NOT_FOUND)
            return None

    return Handler


def start_server(folder: str | os.PathLike, *, port: int = 8000, cache_dir: str | os.PathLike | None = None,
                 npm: str | None = None) -> ViewerServer:
    """Serve the viewer for ``folder`` on ``127.0.0.1:port`` (0: any free port) in a background thread.

    Raises:
        NotADirectoryError: ``folder`` is not a folder.
        ValueError: it holds no ``.glb`` file; ``port`` is not in 0..65535.
        ViewerError: see :func:`install_web_dependencies`; the port is taken (checked first).
    """
    folder = Path(folder).resolve()
    if not folder.is_dir():
        raise NotADirectoryError(f"not a folder: {str(folder)!r}")
    if not clips(folder):
        raise ValueError(f"{str(folder)!r} holds no .glb file: write one with `jaxtalk export INPUT --out "
                         f"{folder}/anim.glb`")
    return _serve(port, lambda modules: _handler(folder, modules), cache_dir, npm)


def _serve(port: int, handler: Callable[[Path], type[BaseHTTPRequestHandler]], cache_dir: str | os.PathLike | None,
           npm: str | None) -> ViewerServer:
    if not 0 <= port <= 65535:  # bind() would raise OverflowError, no OSError
        raise ValueError(f"--port must lie in 0..65535 (0: any free port), got {port}")
    try:  # bound before installing anything; the handler is set once three.js is there
        httpd = ThreadingHTTPServer(("127.0.0.1", port), BaseHTTPRequestHandler)
    except OSError as err:
        if err.errno != errno.EADDRINUSE:
            raise
        raise ViewerError(f"port {port} on 127.0.0.1 is in use: pass --port 0 for any free port, or another "
                          "--port") from None
    try:
        httpd.RequestHandlerClass = handler(install_web_dependencies(cache_dir, npm=npm))
    except BaseException:
        httpd.server_close()
        raise
    thread = threading.Thread(target=httpd.serve_forever, name="jaxtalk-view", daemon=True)
    thread.start()
    return ViewerServer(httpd, thread)


def start_live_server(server: str = "ws://127.0.0.1:8765", *, port: int = 8000,
                      cache_dir: str | os.PathLike | None = None, npm: str | None = None) -> ViewerServer:
    """Serve the live page (``jaxtalk view --live``) on ``127.0.0.1:port`` in a background thread; the page
    connects to the ``jaxtalk serve`` at ``server`` (which must let this page's origin in: a local one is).

    Raises:
        ValueError: ``server`` is not a ``ws://`` or ``wss://`` URL; ``port`` is not in 0..65535.
        ViewerError: see :func:`install_web_dependencies`; the port is taken (checked first).
    """
    parsed = urlparse(server)
    if parsed.scheme not in ("ws", "wss") or not parsed.hostname:
        raise ValueError(f"--server must be a WebSocket URL such as ws://127.0.0.1:8765, got {server!r}")
    return _serve(port, lambda modules: _handler(None, modules, live=server), cache_dir, npm)
