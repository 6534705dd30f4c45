"""Suite-wide JAX settings and fixtures.

* Rank promotion raises, so an accidental (n,) + (n, 1) broadcast is an error, not a silent (n, n).
* ``float64`` fixture: enables x64 inside one test only (finite-difference gradient checks,
  analytic-target checks) and restores the previous setting afterwards.
* XLA's optimisations (and XLA:CPU's fusion emitters) are off by default, here and in every subprocess
  a test starts: most tests compile tiny programs and run them a few times, so compile time dominates.
  A test whose run time dominates (a training that must learn) is marked ``optimized`` and runs with
  them on.
* ``synthtalk_tiny``, ``prepared_tiny`` and ``trained_toktalk`` / ``trained_timar`` / ``trained_ats``: the
  tiny corpus, its prepared folder and one two-step run per model, each made once per test session and
  shared by the xdist workers (built under a file lock by the first worker that needs it).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import shutil
from pathlib import Path

FUSION_EMITTERS_OFF = "--xla_cpu_use_fusion_emitters=false"
# Keep CPU tests deterministic and avoid oversubscribing the 2 CI cores. XLA:CPU's fusion emitters
# off: with optimisations off (the suite's default, below) they double the compile time of a small
# train step (TokTalk tiny's grad step: 4.6 s -> 2.2 s, and it runs 10% faster); three compile-bound
# modules (2 workers): 138 s -> 102 s. With optimisations on they are the faster choice (the learning
# tests ran 162 s -> 185 s without them), so a test marked ``optimized`` turns them back on.
os.environ.setdefault("XLA_FLAGS", f"--xla_cpu_multi_thread_eigen=true {FUSION_EMITTERS_OFF}")
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
# XLA's optimisations off for every test but those marked ``optimized`` (see _optimized_if_marked): the
# suite compiles thousands of small programs and runs each a few times. Set before jax is imported so
# it is the flag's default here and in every subprocess the tests start (the CLI, the notebook, the
# distributed workers). Measured on six compile-bound modules (2 workers): 196 s -> 170 s.
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
# One persistent XLA compilation cache for the session: modules (whose in-memory caches are dropped
# after each, see _release_compiled_programs), xdist workers and the CLI subprocesses compile many of
# the same programs (the tiny models' train steps, samplers and initialisers). Made fresh by the
# controller, which the workers and subprocesses inherit it from, and removed at its end, so every
# session compiles from scratch. Measured on the four CLI modules (2 workers): 381 s -> 333 s.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    import tempfile

    os.environ["JAX_COMPILATION_CACHE_DIR"] = _XLA_CACHE = tempfile.mkdtemp(prefix="jaxtalk-tests-xla-")
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
else:
    _XLA_CACHE = None

# These imports come after the environment set above: jax reads the flags when imported.
import jax  # noqa: E402
import pytest  # noqa: E402

from helpers import jax_flag, xla_options  # noqa: E402  # after the environment above: helpers imports jax

jax.config.update("jax_numpy_rank_promotion", "raise")


@pytest.hookimpl(tryfirst=True)  # before -m selects: the measured-slow marks must be there by then
def pytest_collection_modifyitems(config, items):
    """Marks every test measured at 3 s or more ``slow`` and starts the longest modules first (see
    ``tests/durations.py``, which records both in ``durations.json``)."""
    recorded = json.loads((Path(__file__).parent / "durations.json").read_text())
    for item in items:
        if item.nodeid in recorded["slow_tests"] and item.get_closest_marker("slow") is None:
            item.add_marker(pytest.mark.slow)
    modules = recorded["modules"]
    items.sort(key=lambda item: -modules.get(item.path.name, 0.0))  # stable: a module keeps its order


def _stray_caches() -> set[str]:
    """What the commands' default cache folders (``.cache/prepared``, ``.cache/synthtalk``) hold in the
    folder the suite runs from: a test must give every command a folder of its own."""
    root = Path.cwd() / ".cache"
    return {str(p.relative_to(root)) for p in root.glob("*/*")} if root.is_dir() else set()


def pytest_sessionstart(session):
    session.config._stray_caches_before = _stray_caches()


def pytest_sessionfinish(session, exitstatus):
    """Fails the session if a test wrote into the default cache folders of the folder it ran from (a
    command called without ``--cache-dir``): the suite writes only under its temporary folders."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return  # the controller checks, once
    new = sorted(_stray_caches() - session.config._stray_caches_before)
    if new:
        print(f"\nerror: tests wrote into {Path.cwd() / '.cache'}: {', '.join(new)} (pass --cache-dir)")
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_unconfigure(config):
    if _XLA_CACHE is not None:  # the process that made the session's compilation cache
        shutil.rmtree(_XLA_CACHE, ignore_errors=True)


@pytest.fixture
def float64():
    """Enable 64-bit JAX arrays for the duration of one test."""
    with jax_flag("jax_enable_x64", True):
        yield


@pytest.fixture(autouse=True)
def _optimized_if_marked(request, monkeypatch):
    """XLA's optimisations back on for a test marked ``optimized`` (run time dominates: a training that
    must learn in hundreds of steps, ten minutes of audio through a server, runs slower, not faster,
    without them), in this process and in the subprocesses the test starts."""
    if request.node.get_closest_marker("optimized") is None:
        yield
        return
    monkeypatch.setenv("JAX_DISABLE_MOST_OPTIMIZATIONS", "0")
    monkeypatch.setenv("XLA_FLAGS", os.environ["XLA_FLAGS"].replace(FUSION_EMITTERS_OFF, ""))
    with jax_flag("jax_disable_most_optimizations", False), xla_options(xla_cpu_use_fusion_emitters=True):
        yield


@pytest.fixture
def no_typecheck():
    """Turn the jaxtyping checker off so the library's own ValueErrors are what is tested (the checker
    refuses a wrong shape first under pytest; users get the ValueError)."""
    import jaxtyping

    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", False)


@pytest.fixture
def key():
    return jax.random.key(0)


def _session_shared(tmp_path_factory, name: str) -> Path:
    """A folder every xdist worker of this test session shares (one session's worker folders share a
    parent); without xdist, this session's own temporary folder."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    folder = root / name
    folder.mkdir(parents=True, exist_ok=True)
    return folder


@contextlib.contextmanager
def _exclusive(folder: Path):
    """Holds an exclusive lock on ``folder`` across processes: one worker builds, the others wait and
    then find it built."""
    with open(folder / ".lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def synthtalk_tiny(tmp_path_factory):
    """The tiny SynthTalk corpus (seed 0), generated once per test session into a cache all workers
    share (byte-identical from its seed; its files are written atomically)."""
    from jaxtalk.data import synthtalk

    return synthtalk.generate("tiny", seed=0, cache_dir=_session_shared(tmp_path_factory, "synthtalk_tiny"))


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drops JAX's in-memory caches of compiled programs after every test module.

    A full run compiles thousands of programs and keeps every one alive for the whole session unless
    told otherwise; a CI rehearsal once segfaulted inside XLA's compiler late in the run (the same test
    passes alone), so the suite no longer accumulates them. Modules rarely share programs, so this
    costs little compile time.
    """
    yield
    jax.clear_caches()


@pytest.fixture(scope="session")
def prepared_tiny(tmp_path_factory, synthtalk_tiny):
    """The tiny SynthTalk corpus prepared (``jaxtalk prepare``) once per test session.

    It lies where ``--data synthtalk:tiny --cache-dir <prepared_tiny.root.parent>`` finds it, so CLI
    tests train on it without preparing again. The xdist workers share it: the first prepares it under
    a file lock, the others read it (tests only read a prepared folder).
    """
    from jaxtalk.data.loader import PreparedData
    from jaxtalk.data.prepare import prepare
    from jaxtalk.data.sources import Source, synthtalk_entries

    cache = _session_shared(tmp_path_factory, "prepared")
    with _exclusive(cache):  # prepared once per session, by the first worker that needs it
        if not (cache / "synthtalk-tiny-seed0" / "manifest.json").is_file():
            source = Source("synthtalk:tiny:0", "synthtalk", tuple(synthtalk_entries(synthtalk_tiny)),
                            tokenizer=lambda: synthtalk_tiny.tokenizer("A"))
            prepare(source, cache / "synthtalk-tiny-seed0", progress=False, echo=lambda line: None)
    return PreparedData(cache / "synthtalk-tiny-seed0")


@pytest.fixture(scope="module")
def stm_run(tmp_path_factory, prepared_tiny):
    """An STM run at its initial parameters (a step-0 checkpoint) on one small mesh.

    Training STM renders several meshes (minutes); tests of the wiring around it need only a run.
    """
    import dataclasses

    import optax

    from jaxtalk.runs import RunRecord, checkpoint_dir, save_run_assets
    from jaxtalk.models.freetalk import stm
    from jaxtalk.models.freetalk.config import STMConfig
    from jaxtalk.models.freetalk.data import face_mesh
    from jaxtalk.train import create_train_state, save_checkpoint

    out = tmp_path_factory.mktemp("stm_run")
    config = STMConfig.small(encoder_blocks=1, decoder_blocks=1, num_eigenpairs=16)
    fm = face_mesh(1, "decimated")
    params = stm.init_params(config, jax.random.key(0), stm.prepare_mesh(fm.vertices, fm.faces, config))
    save_checkpoint(checkpoint_dir(out), create_train_state(params, optax.identity(), jax.random.key(0)))
    data = prepared_tiny
    RunRecord(model="stm", preset="small", items=[], config=dataclasses.asdict(config), train={}, optim={},
              data={"spec": "synthtalk:tiny", "path": str(data.root), "key": data.key}, seed=0,
              extra={"meshes": [[1, "decimated"]], "resolution": "low", "window": 16}).save(out)
    save_run_assets(out, "stm", data, config)
    return out


# --------------------------------------------------------------------------- shared trained runs


@dataclasses.dataclass(frozen=True)
class TrainedRun:
    """A run ``jaxtalk train`` made once per test session: its folder (read it, never write into it; a
    test that resumes or overwrites works on :meth:`copy`) and what the command printed."""

    dir: Path
    output: str

    def copy(self, dest: Path) -> Path:
        shutil.copytree(self.dir, dest)
        return dest


def _trained_run(tmp_path_factory, prepared_tiny, model: str) -> TrainedRun:
    """``jaxtalk train MODEL`` on SynthTalk tiny: two steps, batch 2, the smallest graph, the suite's
    default compilation (a session fixture is made before any test's ``optimized`` switch). The xdist
    workers share it: the first trains it under a file lock, the others wait for it and read it."""
    from helpers import TINY_TRAIN_ARGS, cli_ok

    folder = _session_shared(tmp_path_factory, f"trained_{model}")
    run, printed = folder / "run", folder / "output.txt"
    with _exclusive(folder):
        if not printed.is_file():  # written last: a run a killed worker left half-made is trained again
            shutil.rmtree(run, ignore_errors=True)
            output = cli_ok(["train", model, "--data", "synthtalk:tiny", "--cache-dir", prepared_tiny.root.parent,
                             "--steps", "2", "--set", "batch_size=2", *TINY_TRAIN_ARGS[model], "--no-progress",
                             "--out", run])
            printed.write_text(output)
    return TrainedRun(run, printed.read_text())


@pytest.fixture(scope="session")
def trained_toktalk(tmp_path_factory, prepared_tiny) -> TrainedRun:
    """TokTalk's tiny preset without middle stages, two steps through ``jaxtalk train``."""
    return _trained_run(tmp_path_factory, prepared_tiny, "toktalk")


@pytest.fixture(scope="session")
def trained_timar(tmp_path_factory, prepared_tiny) -> TrainedRun:
    """A one-layer, 32-wide TIMAR on two-turn windows, two steps through ``jaxtalk train``."""
    return _trained_run(tmp_path_factory, prepared_tiny, "timar")


@pytest.fixture(scope="session")
def trained_ats(tmp_path_factory, prepared_tiny) -> TrainedRun:
    """A one-layer, 32-wide ATS (four sampling steps), two steps through ``jaxtalk train``."""
    return _trained_run(tmp_path_factory, prepared_tiny, "ats")


@pytest.fixture(scope="session")
def learned_toktalk_small(tmp_path_factory, prepared_tiny):
    """``(config, params)``: TokTalk ``small`` trained 200 steps on SynthTalk tiny (batch 16, the recipe's
    learning rate, 50 warm-up steps, its EMA, key 0), with XLA's optimisations on (run time dominates). The
    learning test and the exported page's test read it; the xdist workers share it: the first trains it
    under a file lock, the others wait for it and read it."""
    import pickle

    from jaxtalk.files import atomic_write_bytes
    from jaxtalk.models import toktalk as tt
    from jaxtalk.models.toktalk import recipe
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings, OptimConfig

    config = tt.TokTalkConfig.small()
    folder = _session_shared(tmp_path_factory, "learned_toktalk_small")
    path = folder / "params.pkl"
    with _exclusive(folder):
        if not path.is_file():
            with jax_flag("jax_disable_most_optimizations", False), xla_options(xla_cpu_use_fusion_emitters=True):
                result = recipe.train(config, prepared_tiny,
                                      OptimConfig(lr=recipe.DEFAULTS.lr, warmup_steps=50, total_steps=200,
                                                  ema_decay=recipe.DEFAULTS.ema_decay),
                                      key=jax.random.key(0),
                                      run=RunSettings(batch_size=16, loop=LoopSettings(progress=False)), val_clips=0)
            atomic_write_bytes(path, pickle.dumps(jax.device_get(result.state.eval_params)))
    return config, pickle.loads(path.read_bytes())
