"""``jaxtalk export-model RUN --format onnx --out DIR``: a run's live stream as ONNX graphs, a manifest, the
reference host (``host.py``) and a static page that runs it in the browser on the microphone.

The run's live model comes through the registry's ``live`` entry with the style, guidance, steps and
temperature given (as ``jaxtalk serve`` makes it), and its ``export_stream`` writes the graphs; models without
one are refused with the reason. ``DIR`` must be new, empty, or an earlier export (replaced with
``--overwrite``): nothing else a user keeps there is written over. A new export is made in a folder beside
``DIR`` and renamed into place when whole, so a failed one leaves nothing behind; an earlier export is
replaced file by file (each written atomically; files a user added beside it stay).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["ExportModelOptions", "export_model_run", "FORMATS"]

FORMATS = ("onnx",)


@dataclasses.dataclass(frozen=True)
class ExportModelOptions:
    """Settings of :func:`export_model_run`.

    Attributes:
        run_dir: a folder written by ``jaxtalk train``.
        out: the folder to write.
        format: ``onnx``.
        style: TokTalk reference motion (``.npz`` with ``params``); default: the run's training clip.
        cfg_scale: guidance weight (default: the config's).
        sample_steps: sampler steps (default: the config's).
        temperature: scale of the starting noise (default: the config's).
        best: the run's best-validated checkpoint instead of its newest.
        page: write the browser page (needs Node.js and npm for three.js and onnxruntime-web).
        overwrite: replace an earlier export in ``out``.
        cache_dir: where the page's npm packages are installed (default: the viewer's cache).
    """

    run_dir: Path
    out: Path
    format: str = "onnx"
    style: Path | None = None
    cfg_scale: float | None = None
    sample_steps: int | None = None
    temperature: float | None = None
    best: bool = False
    page: bool = True
    overwrite: bool = False
    cache_dir: Path | None = None


def _check_out(out: Path, overwrite: bool) -> bool:
    """Refuse a folder that holds anything but an earlier export (that one only with ``overwrite``); True when
    ``out`` is an earlier export."""
    from jaxtalk.export.onnx import MANIFEST_FORMAT

    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"--out {out} is a file: name a folder for the export")
    if not out.is_dir() or not any(out.iterdir()):
        return False
    manifest = out / "manifest.json"
    try:
        earlier = json.loads(manifest.read_text()).get("format") == MANIFEST_FORMAT[0]
    except (OSError, ValueError, AttributeError):
        earlier = False
    if not earlier:
        raise FileExistsError(f"--out {out} is not empty and holds no earlier export: name a new or empty folder")
    if not overwrite:
        raise FileExistsError(f"--out {out} holds an earlier export: pass --overwrite to replace it")
    return True


def export_model_run(opts: ExportModelOptions, echo: Callable[[str], Any] = print) -> dict[str, Any]:
    """Export the run's stream into ``opts.out`` (see the module).

    Returns:
        The manifest written.

    Raises:
        ValueError: an unknown format; a model without an export (the reason); bad settings.
        FileNotFoundError: not a run, no checkpoint, a missing style file.
        FileExistsError: ``out`` holds other files, or an earlier export without ``overwrite``.
        ImportError: jax2onnx is not installed.
        ViewerError: the page's packages cannot be installed (no npm); pass ``page=False``.
    """
    from jaxtalk.commands.serving import live_model_of_run
    from jaxtalk.runs import RunRecord, model_spec

    if opts.format not in FORMATS:
        raise ValueError(f"--format must be one of {', '.join(FORMATS)}, got {opts.format!r}")
    record = RunRecord.load(opts.run_dir)
    spec = model_spec(record.model)
    if spec.export_stream is None:
        raise ValueError(f"{opts.run_dir} is a {record.model} run: {spec.title} has no ONNX export ({spec.export_refusal})")
    earlier = _check_out(opts.out, opts.overwrite)
    from jaxtalk.export.onnx import require_converter

    try:
        require_converter()  # said before the model loads
    except ImportError as error:
        raise ValueError(str(error)) from None
    model = live_model_of_run(opts)
    echo(f"exporting {opts.run_dir} ({spec.title}, {model.describe()['sample_steps']} steps) to {opts.out} ...")
    out = Path(opts.out)
    folder = out if earlier else out.parent / f".{out.name}.partial-{uuid.uuid4().hex[:12]}"
    try:
        manifest = spec.export_stream(model, folder, run_name=Path(opts.run_dir).name)
        if opts.page:
            from jaxtalk.viewer import write_stream_page

            write_stream_page(folder, opts.cache_dir)
        if folder != out:
            if out.is_dir():
                out.rmdir()  # empty (checked above)
            folder.rename(out)
    finally:
        if folder != out:
            shutil.rmtree(folder, ignore_errors=True)
    graphs = [manifest[name]["file"] for name in ("frontend", "step", "morph") if manifest.get(name)]
    echo(f"written {', '.join(graphs)}, manifest.json and host.py in {out}")
    if opts.page:
        echo(f"written {out / 'index.html'}: serve the folder with any static file server (python -m http.server -d "
             f"{out}) and open it; the model runs in the browser")
    return manifest
