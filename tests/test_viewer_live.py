"""``jaxtalk view --live``'s server without Node: it serves the live page, its audio worklet and the address of
the ``jaxtalk serve`` to stream to (nothing of a clip folder), and the command says what a user got wrong.
A cached three.js install is faked as in test_viewer_server."""

from __future__ import annotations

import json

import pytest
from test_viewer_server import cached_three, get  # noqa: F401  (cached_three: a fixture)
from typer.testing import CliRunner

from jaxtalk.cli import app
from jaxtalk.viewer import WEB_DIR, start_live_server


def test_the_live_page_its_worklet_and_the_servers_address_are_served_and_nothing_else(cached_three):  # noqa: F811
    viewer = start_live_server("ws://127.0.0.1:9999", port=0, cache_dir=cached_three)
    try:
        status, _, body = get(viewer.url)
        assert status == 200 and body == (WEB_DIR / "live.html").read_bytes() and b'src="/live.js"' in body
        for name in ("live.js", "capture.js", "stage.js"):
            status, headers, body = get(viewer.url + name)
            assert status == 200 and headers["Content-Type"] == "text/javascript" and body == (WEB_DIR / name).read_bytes()
        assert json.loads(get(viewer.url + "live.json")[2]) == {"server": "ws://127.0.0.1:9999"}
        assert get(viewer.url + "vendor/three/build/three.module.js")[0] == 200
        for path in ("clips.json", "viewer.js", "data/a.glb", "../live.js"):
            assert get(viewer.url + path)[0] == 404, path
        assert get(viewer.url + "live.json", {"Host": "evil.example"})[0] == 403
    finally:
        viewer.close()


def test_the_live_pages_module_and_worklet_are_packaged():
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    for name in ("live.html", "live.js", "capture.js", "stage.js", "viewer.css"):
        assert f'"web/{name}"' in text


@pytest.mark.parametrize("args, words", [
    (["view"], "pass --live"),
    (["view", ".", "--live"], "drop FOLDER"),
    (["view", "--live", "--server", "http://127.0.0.1:8765"], "WebSocket URL"),
])
def test_view_says_what_is_wrong_with_its_arguments(args, words, cached_three, monkeypatch):  # noqa: F811
    monkeypatch.setattr("jaxtalk.viewer.DEFAULT_CACHE", cached_three)
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2 and words in result.output and "Traceback" not in result.output


@pytest.mark.parametrize("args", [["--live", "--port", "99999"], ["--live", "--port", "-1"], ["FOLDER", "--port", "70000"],
                                  ["--live", "--port", "TAKEN"], ["FOLDER", "--port", "TAKEN"]])
def test_view_refuses_a_bad_or_taken_port_in_one_line_before_installing_anything(args, tmp_path, monkeypatch):
    import socket

    from helpers import cli_error

    def install(*args, **kw):
        pytest.fail("three.js was installed before the port was checked")

    monkeypatch.setattr("jaxtalk.viewer.install_web_dependencies", install)
    (tmp_path / "a.glb").write_bytes(b"")  # a clip to play: the folder is checked before the port
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        given = [str(tmp_path) if a == "FOLDER" else str(port) if a == "TAKEN" else a for a in args]
        words = (f"port {port} on 127.0.0.1 is in use",) if "TAKEN" in args else ("--port", "0..65535", args[-1])
        cli_error(["view", *given], *words)
