"""``jaxtalk view``'s server without Node: what it serves (and refuses), and the message a user without
Node.js gets. A cached install is faked by a ``node_modules/three`` folder under the lock file's hash."""

from __future__ import annotations

import hashlib
import json
import urllib.error
import urllib.request

import numpy as np
import pytest
import soundfile
from typer.testing import CliRunner

from jaxtalk.cli import app
from jaxtalk.export import export_face_model
from jaxtalk.face import builtin_face
from jaxtalk.viewer import WEB_DIR, ViewerError, clips, install_web_dependencies, start_server

runner = CliRunner()


@pytest.fixture
def cached_three(tmp_path):
    """A cache folder in which the viewer's three.js counts as installed."""
    digest = hashlib.sha256((WEB_DIR / "package-lock.json").read_bytes()).hexdigest()[:16]
    three = tmp_path / "cache" / digest / "node_modules" / "three"
    (three / "build").mkdir(parents=True)
    (three / "package.json").write_text("{}")
    (three / "build" / "three.module.js").write_text("export const REVISION = 'test';")
    return tmp_path / "cache"


@pytest.fixture
def folder(tmp_path):
    out = tmp_path / "clips"
    out.mkdir()
    export_face_model(builtin_face(0, resolution="low"), np.zeros((4, 56), np.float32), out / "a.glb")
    export_face_model(builtin_face(0, resolution="low"), np.zeros((4, 56), np.float32), out / "b.glb")
    soundfile.write(out / "a.wav", np.zeros(1600, np.float32), 16000)
    (out / "secret.txt").write_text("not served")
    return out


def get(url: str, headers: dict | None = None) -> tuple[int, dict, bytes]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=10) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as err:
        return err.code, dict(err.headers), b""


def test_clips_pair_each_glb_with_its_glb_wav_else_the_wav_of_its_stem(folder):
    # c.glb.wav is the export's own audio; c.wav, the recording it was made from, is not taken instead.
    export_face_model(builtin_face(0, resolution="low"), np.zeros((4, 56), np.float32), folder / "c.glb")
    soundfile.write(folder / "c.glb.wav", np.zeros(1600, np.float32), 16000)
    soundfile.write(folder / "c.wav", np.zeros(800, np.float32), 16000)
    assert clips(folder) == [{"name": "a", "glb": "/data/a.glb", "audio": "/data/a.wav"},
                             {"name": "b", "glb": "/data/b.glb", "audio": None},
                             {"name": "c", "glb": "/data/c.glb", "audio": "/data/c.glb.wav"}]


def test_server_serves_the_page_three_the_clips_and_byte_ranges_and_nothing_else(folder, cached_three):
    server = start_server(folder, port=0, cache_dir=cached_three)
    try:
        status, headers, body = get(server.url)
        assert status == 200 and b'"three": "/vendor/three/build/three.module.js"' in body
        status, headers, _ = get(server.url + "viewer.js")
        assert status == 200 and headers["Content-Type"] == "text/javascript"  # ES modules need it
        status, _, body = get(server.url + "vendor/three/build/three.module.js")
        assert status == 200 and b"REVISION" in body
        assert json.loads(get(server.url + "clips.json")[2]) == clips(folder)
        status, headers, body = get(server.url + "data/a.glb")
        assert status == 200 and body == (folder / "a.glb").read_bytes() and headers["Content-Type"] == "model/gltf-binary"
        status, headers, body = get(server.url + "data/a.wav", {"Range": "bytes=10-19"})
        wav = (folder / "a.wav").read_bytes()
        assert status == 206 and body == wav[10:20] and headers["Content-Range"] == f"bytes 10-19/{len(wav)}"
        for path in ("data/secret.txt", "data/../clips/a.glb", "vendor/three/../../../package-lock.json", "nope"):
            assert get(server.url + path)[0] == 404, path
        assert server.url.startswith("http://127.0.0.1:")
    finally:
        server.close()


def test_without_node_the_user_is_told_to_install_it(tmp_path, folder, monkeypatch):
    monkeypatch.setattr("shutil.which", lambda name: None)
    with pytest.raises(ViewerError, match="needs Node.js and npm"):
        install_web_dependencies(tmp_path / "empty-cache")
    monkeypatch.setattr("jaxtalk.viewer.DEFAULT_CACHE", tmp_path / "empty-cache")  # the default cache: empty here
    result = runner.invoke(app, ["view", str(folder)])
    assert result.exit_code == 2 and "needs Node.js and npm" in result.output and "Traceback" not in result.output


def test_a_folder_without_exports_is_refused(tmp_path, cached_three):
    with pytest.raises(ValueError, match="holds no .glb file"):
        start_server(tmp_path, cache_dir=cached_three)
    with pytest.raises(NotADirectoryError):
        start_server(tmp_path / "missing", cache_dir=cached_three)


def test_server_refuses_a_host_other_than_this_machine_and_serves_local_names(folder, cached_three):
    # DNS rebinding: a page on evil.example whose name now resolves to 127.0.0.1 sends its own Host.
    server = start_server(folder, port=0, cache_dir=cached_three)
    try:
        port = server.httpd.server_address[1]
        for host in ("evil.example", f"evil.example:{port}", f"127.0.0.1.evil.example:{port}", "127.0.0.1:1"):
            assert get(f"{server.url}clips.json", {"Host": host})[0] == 403, host
        for host in (f"127.0.0.1:{port}", f"localhost:{port}", "localhost", f"[::1]:{port}"):
            status, _, body = get(f"{server.url}clips.json", {"Host": host})
            assert status == 200 and json.loads(body)[0]["name"] == "a", host
    finally:
        server.close()
