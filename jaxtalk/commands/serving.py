"""``jaxtalk serve``: a trained run -> the live WebSocket server (:mod:`jaxtalk.serve`), on 127.0.0.1 by default.

The run's model comes through the run registry's ``live`` entry (TokTalk: audio -> the run's tokenizer ->
the streaming engine); models without one (TIMAR, FreeTalk, DualTalk) are refused with a reason.
"""

from __future__ import annotations

import dataclasses
import errno
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["ServeCommandOptions", "live_model_of_run", "serve_run"]


@dataclasses.dataclass(frozen=True)
class ServeCommandOptions:
    """Settings of :func:`serve_run`.

    Attributes:
        run_dir: a folder written by ``jaxtalk train``.
        host, port: where to listen (port 0: any free one).
        style: TokTalk reference motion (``.npz`` with ``params``); default: the run's training clip.
        cfg_scale: guidance weight (default: the config's).
        sample_steps: sampler steps (default: the config's).
        temperature: scale of the starting noise (default: the config's).
        best: the run's best-validated checkpoint instead of its newest.
        max_clients: clients served at once.
        max_chunk_s: the longest audio message, seconds.
        live_link: ``HOST:PORT`` (or ``PORT``, ``HOST``) to send ARKit curves to as Live Link Face packets.
        origins: web page origins allowed besides this machine's own.
    """

    run_dir: Path
    host: str = "127.0.0.1"
    port: int = 8765
    style: Path | None = None
    cfg_scale: float | None = None
    sample_steps: int | None = None
    temperature: float | None = None
    best: bool = False
    max_clients: int = 8
    max_chunk_s: float = 1.0
    live_link: str | None = None
    origins: tuple[str, ...] = ()


def live_model_of_run(opts: Any) -> Any:
    """The run's live model (the registry's ``live`` factory with the style, guidance, steps and
    temperature given): ``opts`` is a :class:`ServeCommandOptions` or any settings with its ``run_dir``,
    ``best``, ``style``, ``cfg_scale``, ``sample_steps`` and ``temperature`` (``jaxtalk export-model``'s).

    Raises:
        FileNotFoundError: not a run, no checkpoint, a missing style file.
        ValueError: a model that does not animate live speech; bad settings.
    """
    from jaxtalk.runs import RunRecord, load_run, model_spec

    record = RunRecord.load(opts.run_dir)
    factory = model_spec(record.model).live
    if factory is None:
        raise ValueError(f"{opts.run_dir} is a {record.model} run; jaxtalk serve animates live speech with a toktalk "
                         "run (TIMAR answers whole turns of a conversation: use jaxtalk stream)")
    style = None
    if opts.style is not None:
        from jaxtalk.commands.rendering import read_params

        style = read_params(opts.style)
    return factory(load_run(opts.run_dir, best=opts.best), style=style, cfg_scale=opts.cfg_scale,
                   sample_steps=opts.sample_steps, temperature=opts.temperature)


def _listen(opts: ServeCommandOptions) -> Any:
    """The server's listening socket, bound before the model loads (a port in use is said at once)."""
    from jaxtalk.serve.server import listen_socket

    try:
        return listen_socket(opts.host, opts.port)
    except OSError as err:
        if err.errno == errno.EADDRINUSE:
            raise ValueError(f"port {opts.port} on {opts.host} is in use: pass --port 0 for any free port, or another "
                             "--port") from None
        raise ValueError(f"cannot listen on {opts.host}:{opts.port}: {err.strerror or err}") from None


def serve_run(opts: ServeCommandOptions, *, echo: Callable[[str], None] = print) -> Any:
    """Check every option and take the port, then load the run, warm its model up, and start the server on
    a background thread.

    Returns:
        The :class:`~jaxtalk.serve.server.RunningServer` (``close()`` stops it).

    Raises:
        See :func:`live_model_of_run`; ValueError: an option out of range, a port in use, a bad
        ``--live-link`` address or ``--allow-origin``, or ``--live-link`` while the ``arkit`` output is not
        available.
    """
    from jaxtalk.commands.inference import check_sampling_options
    from jaxtalk.export.livelink import parse_address
    from jaxtalk.serve import OutputUnavailable, ServeOptions, start_server
    from jaxtalk.serve.server import origin_pattern

    # Every option first: loading and warming the model up takes seconds to minutes.
    if not 0 <= opts.port <= 65535:
        raise ValueError(f"--port must lie in 0..65535 (0: any free port), got {opts.port}")
    if not 1 <= opts.max_clients <= 1024:
        raise ValueError(f"--max-clients must lie in 1..1024, got {opts.max_clients}")
    if not 0.01 <= opts.max_chunk_s <= 60:
        raise ValueError(f"--max-chunk-s must lie in 0.01..60, got {opts.max_chunk_s}")
    check_sampling_options(opts.cfg_scale, opts.sample_steps, opts.temperature)
    for origin in opts.origins:
        origin_pattern(origin)
    link = parse_address(opts.live_link) if opts.live_link is not None else None
    sock = _listen(opts)
    try:
        model = live_model_of_run(opts)
    except BaseException:
        sock.close()
        raise
    info = model.describe()
    echo(f"jaxtalk serve: {info['model']} run {opts.run_dir}: {info['fps']} fps in chunks of {info['chunk_frames']} frames "
         f"({1e3 * info['chunk_samples'] / info['sample_rate']:.0f} ms of audio, plus "
         f"{1e3 * info['lookahead_samples'] / info['sample_rate']:.1f} ms look-ahead), {info['sample_steps']} sampler steps")
    options = ServeOptions(host=opts.host, port=opts.port, max_clients=opts.max_clients, max_chunk_s=opts.max_chunk_s,
                           live_link=link, origins=tuple(opts.origins))
    try:
        running = start_server(model, options, sock=sock)  # which closes the socket if it fails
    except OutputUnavailable as err:  # the server builds the arkit output once, for --live-link, and refuses here
        raise ValueError(f"--live-link sends ARKit curves, and {err}") from None
    server = running.server
    outputs = ", ".join(name if reason is None else f"{name} (not available)"
                        for name, reason in server.output_status().items())
    echo(f"warmed up in {server.warmed_s:.1f} s; outputs: {outputs}")
    if link is not None:
        echo(f"sending each client's ARKit curves to Live Link at {link[0]}:{link[1]} (UDP, Live Link Face packets)")
    if opts.host not in ("127.0.0.1", "localhost", "::1"):
        echo(f"warning: listening on {opts.host}: other machines can connect and use this model")
    http = running.url.replace("ws://", "http://", 1)
    echo(f"listening on {running.url} (Ctrl-C stops); the morph output's face: {http}/face.glb; protocol: docs/serve.md")
    return running
