"""The command line: help texts, one-line errors for user mistakes, the data command end to end."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from jaxtalk.cli import app

runner = CliRunner()


def test_help_lists_commands():
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    assert "data" in result.output


def test_user_error_is_one_line_without_traceback():
    result = runner.invoke(app, ["data", "--size", "huge"])
    assert result.exit_code == 2
    assert "unknown SynthTalk size 'huge'" in result.output
    assert "Traceback" not in result.output


def test_data_command_loads_the_cache_and_writes_metadata(tmp_path, synthtalk_tiny):
    # The session fixture already rendered the tiny corpus into its cache: the command must load it.
    cache = str(synthtalk_tiny._cache_dir)
    meta = tmp_path / "meta.json"
    result = runner.invoke(app, ["data", "--size", "tiny", "--no-tokens", "--cache-dir", cache, "--metadata", str(meta)])
    assert result.exit_code == 0, result.output
    for split in ("train", "val", "test", "ood"):
        assert split in result.output
    payload = json.loads(meta.read_text())
    assert payload["fps"] == 25 and payload["sample_rate"] == 16000
    assert len(payload["clips"]) == len(synthtalk_tiny.clips)
