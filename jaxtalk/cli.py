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
from typing import Annotated, Any, Callable

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


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
