"""``jaxtalk serve`` checks every option, and takes its port, before it loads the run: a bad value or a port in
use is one ``error:`` line at once, not a traceback (or a message blaming the model) after the model's
loading and warm-up. The model loader fails the test if it is reached."""

from __future__ import annotations

import socket

import pytest

from helpers import cli_error


@pytest.fixture
def never_loaded(monkeypatch):
    def load(opts):
        pytest.fail("the model was loaded before the options were checked")

    monkeypatch.setattr("jaxtalk.commands.serving.live_model_of_run", load)


@pytest.mark.parametrize("options, words", [
    (["--port", "99999"], ("--port", "0..65535", "99999")),
    (["--port", "-1"], ("--port", "0..65535", "-1")),
    (["--cfg-scale", "nan"], ("--cfg-scale", "finite")),
    (["--cfg-scale", "inf"], ("--cfg-scale", "finite")),
    (["--sample-steps", "0"], ("--sample-steps", ">= 1")),
    (["--temperature", "-1"], ("--temperature", ">= 0")),
    (["--temperature", "nan"], ("--temperature", "finite")),
    (["--max-clients", "0"], ("--max-clients", "1..1024")),
    (["--max-chunk-s", "nan"], ("--max-chunk-s", "0.01..60")),
    (["--allow-origin", "notaurl"], ("--allow-origin", "'notaurl'", "http(s)://HOST")),
    (["--allow-origin", "ftp://example.com"], ("--allow-origin", "ftp://example.com")),
    (["--allow-origin", "https://example.com/page"], ("--allow-origin", "https://example.com/page")),
    (["--allow-origin", "http://example.com:99999"], ("--allow-origin", "99999")),
    (["--allow-origin", "http://:8000"], ("--allow-origin", "http://:8000")),
    (["--allow-origin", "http://localhost:*", "--allow-origin", "http://evil.example:x"], ("evil.example:x",)),
])
def test_a_bad_option_is_one_error_line_before_the_model_loads(tmp_path, never_loaded, options, words):
    cli_error(["serve", tmp_path, *options], *words)


def test_a_port_in_use_is_said_before_the_model_loads(tmp_path, never_loaded):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        cli_error(["serve", tmp_path, "--port", port], f"port {port} on 127.0.0.1 is in use", "--port 0")


def test_the_port_is_held_while_the_model_loads(tmp_path, monkeypatch):
    """Bound before loading, not merely checked: nothing else can take the port meanwhile, and a failed
    load gives it back."""
    held = {}

    def load(opts):
        with socket.socket() as other, pytest.raises(OSError):
            other.bind(("127.0.0.1", opts.port))
            other.listen()
        held["port"] = opts.port
        raise FileNotFoundError(f"no run in {opts.run_dir}")

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    monkeypatch.setattr("jaxtalk.commands.serving.live_model_of_run", load)
    cli_error(["serve", tmp_path, "--port", port], "no run in")
    assert held == {"port": port}
    with socket.socket() as again:  # released after the failed load
        again.bind(("127.0.0.1", port))
