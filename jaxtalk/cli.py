"""The ``jaxtalk`` command line.

Every command has ``--help`` and sensible defaults. User mistakes (a missing file, a bad option value,
a malformed input) end with one clear line on stderr and exit code 2, never a traceback; pass
``--debug`` before the command to see the traceback anyway.
"""

from __future__ import annotations

import functools
import json
import sys
import time
from pathlib import Path
from collections.abc import Callable
from typing import Annotated, Any

import typer

app = typer.Typer(
    name="jaxtalk",
    help="Speech-driven 3D face animation in JAX (TokTalk, FreeTalk, TIMAR).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

_STATE = {"debug": False}

# Errors that mean "the user asked for something wrong", reported as one line.
USER_ERRORS = (ValueError, FileNotFoundError, NotADirectoryError, FileExistsError, KeyError)


def _user_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except USER_ERRORS as err:
            if _STATE["debug"]:
                raise
            message = err.args[0] if isinstance(err, KeyError) and err.args else err
            typer.echo(f"error: {message}", err=True)
            raise typer.Exit(code=2) from None

    return wrapper


@app.callback()
def _main(
    debug: Annotated[bool, typer.Option("--debug", help="Show full tracebacks.")] = False,
) -> None:
    _STATE["debug"] = debug


@app.command()
@_user_errors
def data(
    size: Annotated[str, typer.Option(help="Corpus size: tiny, small or full.")] = "tiny",
    seed: Annotated[int, typer.Option(help="Random seed (same seed, byte-identical corpus).")] = 0,
    cache_dir: Annotated[
        Path, typer.Option(help="Where the corpus and its fitted tokenizers are cached.")
    ] = Path(".cache/synthtalk"),
    tokens: Annotated[bool, typer.Option(help="Also fit the token streams A and B.")] = True,
    metadata: Annotated[
        Path | None, typer.Option(help="Write the corpus metadata (clips, speakers) as JSON here.")
    ] = None,
) -> None:
    """Generate (or load from cache) the built-in SynthTalk corpus and print a summary."""
    from jaxtalk.data import synthtalk

    start = time.perf_counter()
    corpus = synthtalk.generate(size=size, seed=seed, cache_dir=cache_dir)
    if tokens:
        for stream in synthtalk.TOKEN_STREAMS:
            corpus.tokenizer(stream)
    elapsed = time.perf_counter() - start
    rows = []
    for split in synthtalk.SPLITS:
        idx = corpus.split(split)
        rows.append(
            {
                "split": split,
                "clips": len(idx),
                "speakers": len({corpus.clips[i].speaker for i in idx}),
                "minutes": round(sum(corpus.clips[i].seconds for i in idx) / 60.0, 2),
                "conversational": sum(corpus.clips[i].is_conversation for i in idx),
            }
        )
    from jaxtalk.benchmarking import format_table

    typer.echo(format_table(rows, title=f"SynthTalk {size} (seed {seed}) in {cache_dir}"))
    typer.echo(f"ready in {elapsed:.1f} s")
    if metadata is not None:
        metadata.parent.mkdir(parents=True, exist_ok=True)
        metadata.write_text(json.dumps(corpus.metadata(), indent=1, default=str))
        typer.echo(f"metadata written to {metadata}")


@app.command()
@_user_errors
def demo(
    out: Annotated[Path, typer.Option(help="Output folder (checkpoint, video, plots, report).")] = Path("jaxtalk-demo"),
    audio: Annotated[
        Path | None, typer.Option(help="Also animate your own speech file (WAV/FLAC, any rate, mono or stereo).")
    ] = None,
    size: Annotated[str, typer.Option(help="SynthTalk size: tiny (quick look) or small.")] = "small",
    steps: Annotated[int, typer.Option(help="Training steps of the small TokTalk model.")] = 1500,
    seed: Annotated[int, typer.Option(help="Corpus and training seed.")] = 0,
    retrain: Annotated[bool, typer.Option(help="Ignore an existing checkpoint and retrain.")] = False,
    sweep: Annotated[bool, typer.Option(help="Run the chunk size x Euler steps sweep.")] = True,
    render: Annotated[bool, typer.Option(help="Write the mp4 and GIF.")] = True,
    progress: Annotated[bool, typer.Option(help="Show the training progress bar.")] = True,
) -> None:
    """Train TokTalk on SynthTalk, stream a held-out clip, and write video, plots and a report."""
    from jaxtalk.demo import DemoOptions, run_demo

    options = DemoOptions(out_dir=out, size=size, seed=seed, train_steps=steps, retrain=retrain,
                          audio=audio, sweep=sweep, render=render, progress=progress)
    result = run_demo(options, echo=typer.echo)
    from jaxtalk.benchmarking import format_table

    typer.echo(format_table(result.quality, title="quality on the held-out clip"))
    typer.echo(f"done in {result.wall_s:.1f} s; outputs in {result.out_dir.resolve()}")
    for name, path in result.files.items():
        typer.echo(f"  {name:15s} {path}")


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
