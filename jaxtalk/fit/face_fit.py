"""Fit the 56-d head vector ``[exp 50 | jaw 3 | neck 3]`` of a ``LinearFaceModel`` to observed geometry.

Three kinds of observation share one solver:

* ``fit_landmarks``: the 68 landmarks per frame (FreeTalk's ATS output -> params for the parametric
  pipeline and renders), optionally a subset (mask; NaN allowed where masked out);
* ``fit_vertices``: the full vertex sequence of the model's own mesh;
* ``fit_vertices(..., variant=v)``: vertices of a remeshed face (``jaxtalk.geometry.topology``),
  compared with the model's vertices carried onto the variant through its barycentric map.

Objective, per sequence (``y`` the fitted parameters, ``o(y)`` the predicted observations)::

    sum_t mean_c (o_tc(y_t) - target_tc)_mm^2  +  sum_t sum_k prior_k y_tk^2
                                               +  smoothness * sum_t |y_{t+1} - y_t|^2

(``c`` runs over the observed coordinates of frame ``t``.) The data term is a per-frame *mean*
squared coordinate error in **millimetres squared**, so one set of weights means the same for 68
landmarks and for 4k vertices, and a prior weight of 0.01 says "one unit of a parameter costs as much
as a 0.1 mm RMS misfit". It is solved with optimistix (Levenberg-Marquardt by default, or
Gauss-Newton) in one of three modes:

* ``"independent"``: one small problem per frame, ``vmap``ped (no temporal term);
* ``"sequential"``: frames in order (``lax.scan``), each warm-started from the previous frame's fit,
  with the temporal term pulling towards that previous fit (a causal smoother, as in streaming);
* ``"joint"``: one problem over the whole sequence with the temporal term, solved with a
  block-tridiagonal linear solver (:class:`jaxtalk.fit.banded.FrameBandedSolver`) so its cost grows
  linearly with the number of frames.

What the data determine: the built-in face's 50 expression components are linearly independent on
the vertices, but 68 landmarks see some of them only weakly (cheek puffs, nose wrinkles, residual
modes move few landmark triangles), and a user's own model may be rank-deficient. Starting from zero,
Levenberg-Marquardt only ever steps in the row space of the Jacobian, so the fit is the minimum-norm
solution along the invisible directions; to recover
*parameters* exactly, fit an identifiable subset (``FitConfig.active``, see
:func:`identifiable_params`) or add a prior. Gauss-Newton has no damping: on a rank-deficient problem
it stops with ``RESULTS.singular``, which is reported, not hidden.

A fit never fails silently: a solver result other than ``successful`` or a per-frame residual RMS
above ``max_rms`` raises :class:`FitFailedError` naming the result and the residual (or, with
``on_failure="return"``, comes back with ``converged`` False).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxtalk.face.model import LinearFaceModel
from jaxtalk.fit.banded import FrameBandedSolver
from jaxtalk.geometry.topology import TopologyVariant
from jaxtalk.types import NUM_LANDMARKS, PARAM_DIM, Array, Bool, Float, Int, Shaped

__all__ = [
    "FitConfig",
    "FitResult",
    "FitFailedError",
    "fit_landmarks",
    "fit_vertices",
    "identifiable_params",
    "result_name",
]

ArrayLike = Array | np.ndarray
MODES = ("independent", "sequential", "joint")
SOLVERS = ("levenberg_marquardt", "gauss_newton")


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Static settings of a fit (part of the compiled program: changing them recompiles).

    Attributes:
        mode: ``"independent"`` (per-frame problems, vmapped), ``"sequential"`` (per-frame
            problems in order, each warm-started from and smoothed towards the previous fit) or
            ``"joint"`` (one problem over the sequence).
        solver: ``"levenberg_marquardt"`` (default, robust to rank deficiency) or
            ``"gauss_newton"``.
        rtol: relative tolerance of optimistix's Cauchy termination: stop when every param step
            is below ``atol + rtol |param|`` and every (weighted) residual change below
            ``atol + rtol |residual|``. ``None``: 1e-4 in float32, 1e-8 in float64 (the model's
            dtype); float32 iterates of ill-conditioned landmark fits wander at ~1e-5, so a
            tighter float32 tolerance only burns steps up to ``max_steps``.
        atol: absolute tolerance of the same test. ``None``: 1e-5 in float32, 1e-10 in float64.
        max_steps: most solver steps per problem.
        active: indices into the 56-d vector that are fitted, sorted and unique; the others are
            held at their initial values. ``None``: all 56.
    """

    # Plain str (not Literal) so a wrong value reaches the ValueError below that lists the options.
    mode: str = "independent"
    solver: str = "levenberg_marquardt"
    rtol: float | None = None
    atol: float | None = None
    max_steps: int = 100
    active: tuple[int | np.integer, ...] | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if value is None:
                continue
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if isinstance(self.max_steps, bool) or not isinstance(self.max_steps, int) or self.max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {self.max_steps!r}")
        if self.active is not None:
            active = tuple(int(i) for i in self.active)
            if not active or list(active) != sorted(set(active)) or active[0] < 0 or active[-1] >= PARAM_DIM:
                raise ValueError(
                    f"active must be a non-empty sorted tuple of unique indices in [0, {PARAM_DIM}), "
                    f"got {self.active!r}"
                )
            object.__setattr__(self, "active", active)

    @property
    def active_indices(self) -> np.ndarray:
        """The fitted indices into the 56-d vector, ``(n,)`` int."""
        return np.arange(PARAM_DIM) if self.active is None else np.asarray(self.active)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FitResult:
    """Outcome of a fit (a pytree of arrays).

    A "problem" is one frame in the ``"independent"`` and ``"sequential"`` modes and the whole
    sequence in ``"joint"`` mode.

    Attributes:
        params: fitted head vectors, ``(T, 56)``.
        rms: per-frame residual RMS over the observed coordinates (metres), ``(T,)``.
        result_code: optimistix ``RESULTS`` index per problem (see :func:`result_name`),
            ``(problems,)``.
        steps: solver steps taken per problem, ``(problems,)``.
        converged: per problem, solver successful and every frame's RMS within ``max_rms``,
            ``(problems,)``.
    """

    params: Float[Array, "frames 56"]
    rms: Float[Array, " frames"]
    result_code: Int[Array, " problems"]
    steps: Int[Array, " problems"]
    converged: Bool[Array, " problems"]

    @property
    def all_converged(self) -> bool:
        """True when every problem converged."""
        return bool(np.all(np.asarray(self.converged)))


class FitFailedError(RuntimeError):
    """A fit did not converge or left a residual above the threshold.

    Attributes:
        result: the :class:`FitResult` (with ``converged`` False where it failed).
    """

    def __init__(self, message: str, result: FitResult):
        super().__init__(message)
        self.result = result


def result_name(code: int) -> str:
    """Name of an optimistix ``RESULTS`` index, e.g. ``"nonlinear_max_steps_reached"``.

    Args:
        code: an entry of ``FitResult.result_code``.

    Returns:
        The ``optimistix.RESULTS`` member name, or ``"unknown result <code>"``.
    """
    # optimistix exposes item -> message but no public code -> name table; read it off the enum.
    table = getattr(optx.RESULTS, "_name_to_item", {})
    names = {int(np.asarray(item._value)): name for name, item in table.items()}
    return names.get(int(code), f"unknown result {int(code)}")


# ---- observation models ----------------------------------------------------------------------------


def _observe(
    model: LinearFaceModel, surface: tuple[Array, Array] | None, params: Array, kind: str
) -> Array:
    """Predicted observations ``(T, P, 3)`` for params ``(T, 56)``."""
    if kind == "landmarks":
        return model.landmarks_seq(params)
    verts = model.vertices_seq(params)
    if kind == "vertices":
        return verts
    # The variant's barycentric map (TopologyVariant.transfer) with its arrays as traced inputs, so
    # one compiled fit serves every variant with the same vertex count.
    corners, bary = surface
    return sum(bary[None, :, k, None] * jnp.take(verts, corners[:, k], axis=1) for k in range(3))


# ---- the jitted solve ------------------------------------------------------------------------------


def _make_solver(config: FitConfig, dtype: Any):
    # Default tolerances per dtype (see FitConfig.rtol).
    rtol_default, atol_default = (1e-8, 1e-10) if np.dtype(dtype).itemsize >= 8 else (1e-4, 1e-5)
    rtol = rtol_default if config.rtol is None else config.rtol
    atol = atol_default if config.atol is None else config.atol
    cls = optx.GaussNewton if config.solver == "gauss_newton" else optx.LevenbergMarquardt
    return cls(rtol=rtol, atol=atol, linear_solver=FrameBandedSolver())


def _least_squares(fn, y0, args, config: FitConfig):
    sol = optx.least_squares(
        fn, _make_solver(config, y0.dtype), y0, args, max_steps=config.max_steps, throw=False
    )
    # The enum item's integer is the only array form of the result code optimistix gives.
    return sol.value, jnp.asarray(sol.result._value, jnp.int32), jnp.asarray(sol.stats["num_steps"], jnp.int32)


_MM = 1000.0


@functools.partial(jax.jit, static_argnames=("config", "kind"))
def _fit_core(model, surface, target, weights, init, prior, smoothness, *, config: FitConfig, kind: str):
    """Solve; returns (params (T, 56), rms (T,), codes (P,), steps (P,))."""
    active = config.active_indices
    num_frames = target.shape[0]

    def data_residual(y, base, tgt, w):
        params = base.at[:, active].set(y)
        pred = _observe(model, surface, params, kind)
        # In millimetres: Levenberg-Marquardt's damping starts at 1 and is not scale invariant, so
        # metre-scale residuals (J^T J ~ 1e-8) would spend a dozen steps shrinking it.
        return (_MM * (pred - tgt) * w[..., None]).reshape(y.shape[0], -1)

    prior_scale = jnp.sqrt(prior[active])
    smooth_scale = jnp.sqrt(smoothness)
    y_init = init[:, active]

    if config.mode == "joint":

        def residuals(y, args):
            base, tgt, w = args
            return {
                "data": data_residual(y, base, tgt, w),
                "prior": prior_scale[None] * y,
                "smooth": smooth_scale * (y[1:] - y[:-1]),
            }

        y, code, steps = _least_squares(residuals, y_init, (init, target, weights), config)
        codes, steps = code.reshape(1), steps.reshape(1)
    elif config.mode == "independent":

        def residuals(y, args):
            base, tgt, w = args
            return {"data": data_residual(y, base, tgt, w), "prior": prior_scale[None] * y}

        def one(y0, base, tgt, w):
            y, code, steps = _least_squares(residuals, y0[None], (base[None], tgt[None], w[None]), config)
            return y[0], code, steps

        y, codes, steps = jax.vmap(one)(y_init, init, target, weights)
    else:  # sequential

        def residuals(y, args):
            base, tgt, w, previous, pull = args
            return {
                "data": data_residual(y, base, tgt, w),
                "prior": prior_scale[None] * y,
                "smooth": pull * (y - previous),
            }

        def step(carry, inputs):
            previous, first = carry
            base, tgt, w = inputs
            # The first frame starts from its init and has no previous fit to be pulled towards.
            y0 = jnp.where(first, base[active], previous)
            pull = jnp.where(first, 0.0, smooth_scale)
            args = (base[None], tgt[None], w[None], y0[None], pull)
            y, code, steps = _least_squares(residuals, y0[None], args, config)
            return (y[0], jnp.asarray(False)), (y[0], code, steps)

        carry0 = (y_init[0], jnp.asarray(True))
        _, (y, codes, steps) = jax.lax.scan(step, carry0, (init, target, weights))

    params = init.at[:, active].set(y)
    # weights hold mask / sqrt(observed coordinates), so the weighted sum of squares is the MSE.
    residual = (_observe(model, surface, params, kind) - target) * weights[..., None]
    rms = jnp.sqrt(jnp.sum(residual.reshape(num_frames, -1) ** 2, axis=1))
    return params, rms, codes, steps


# ---- input checks ----------------------------------------------------------------------------------


def _float_array(x: Any, name: str, dtype: Any) -> np.ndarray:
    try:
        arr = np.asarray(x)
    except Exception as err:  # noqa: BLE001 - ragged lists etc.
        raise ValueError(f"{name} must be an array, got {type(x).__name__}: {err}") from None
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    return arr.astype(dtype, copy=False)


def _first_bad(mask: np.ndarray) -> list[int]:
    return [int(i) for i in np.argwhere(mask)[0]]


def _check_finite(arr: np.ndarray, name: str) -> None:
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} holds NaN or inf (first at index {_first_bad(~np.isfinite(arr))})")


def _weights_and_init(
    init: Any, prior: Any, smoothness: Any, num_frames: int, config: FitConfig, dtype: Any
) -> tuple[np.ndarray, Array, Array]:
    if init is None:
        init_arr = np.zeros((num_frames, PARAM_DIM), dtype)
    else:
        init_arr = _float_array(init, "init", dtype)
        if init_arr.shape == (PARAM_DIM,):
            init_arr = np.broadcast_to(init_arr, (num_frames, PARAM_DIM))
        elif init_arr.shape != (num_frames, PARAM_DIM):
            raise ValueError(f"init must have shape (56,) or ({num_frames}, 56), got {init_arr.shape}")
        _check_finite(init_arr, "init")
    prior_arr = _float_array(prior, "prior", dtype)
    if prior_arr.shape not in ((), (PARAM_DIM,)):
        raise ValueError(f"prior must be a scalar or have shape (56,), got {prior_arr.shape}")
    _check_finite(prior_arr, "prior")
    if np.any(prior_arr < 0):
        raise ValueError(f"prior weights must be >= 0, got minimum {float(prior_arr.min())}")
    smooth_arr = _float_array(smoothness, "smoothness", dtype)
    if smooth_arr.shape != () or not np.isfinite(smooth_arr) or smooth_arr < 0:
        raise ValueError(f"smoothness must be a finite scalar >= 0, got {smoothness!r}")
    if config.mode == "independent" and smooth_arr > 0:
        raise ValueError(
            f"smoothness={float(smooth_arr)} has no effect in mode 'independent' (frames are separate "
            "problems); use mode 'joint' or 'sequential'"
        )
    prior_vec = np.broadcast_to(prior_arr, (PARAM_DIM,))
    return np.ascontiguousarray(init_arr), jnp.asarray(prior_vec), jnp.asarray(smooth_arr)


def _finish(
    params: Array,
    rms: Array,
    codes: Array,
    steps: Array,
    config: FitConfig,
    max_rms: float | None,
    on_failure: str,
) -> FitResult:
    rms_np = np.asarray(rms)
    codes_np = np.asarray(codes)
    ok_solver = codes_np == 0
    frame_ok = np.ones_like(rms_np, bool) if max_rms is None else rms_np <= max_rms
    frame_ok &= np.isfinite(rms_np)
    ok_frames = frame_ok[None, :] if config.mode == "joint" else frame_ok
    converged = ok_solver & (np.all(ok_frames, axis=-1) if config.mode == "joint" else ok_frames)
    result = FitResult(
        params=params,
        rms=rms,
        result_code=jnp.asarray(codes_np),
        steps=jnp.asarray(steps),
        converged=jnp.asarray(converged),
    )
    if on_failure == "raise" and not np.all(converged):
        raise FitFailedError(_failure_message(result, config, max_rms), result)
    return result


def _failure_message(result: FitResult, config: FitConfig, max_rms: float | None) -> str:
    codes = np.asarray(result.result_code)
    rms = np.asarray(result.rms)
    bad = np.flatnonzero(~np.asarray(result.converged))
    unit = "sequence" if config.mode == "joint" else "frame"
    first = int(bad[0])
    frames = np.arange(len(rms)) if config.mode == "joint" else np.asarray([first])
    worst = float(np.max(rms[frames]))
    name = result_name(int(codes[first]))
    threshold = "" if max_rms is None else f" (max_rms={max_rms:.3g} m)"
    return (
        f"face fit failed on {len(bad)} of {len(codes)} {unit} problem(s); first: {unit} {first}: "
        f"optimistix result {name!r} after {int(np.asarray(result.steps)[first])} steps "
        f"(max_steps={config.max_steps}), residual RMS {worst:.3g} m{threshold}"
    )


def _check_on_failure(on_failure: str, max_rms: float | None) -> None:
    if on_failure not in ("raise", "return"):
        raise ValueError(f"on_failure must be 'raise' or 'return', got {on_failure!r}")
    if max_rms is not None and (not isinstance(max_rms, (int, float)) or not max_rms > 0):
        raise ValueError(f"max_rms must be a positive number or None, got {max_rms!r}")


def _dtype(model: LinearFaceModel) -> Any:
    return np.dtype(jnp.asarray(model.template).dtype)


# ---- public entry points ---------------------------------------------------------------------------


def fit_landmarks(
    model: LinearFaceModel,
    landmarks: Float[ArrayLike, "..."],
    *,
    mask: Shaped[ArrayLike, "..."] | None = None,
    config: FitConfig = FitConfig(),
    smoothness: float | Float[ArrayLike, ""] = 0.0,
    prior: float | Float[ArrayLike, "..."] = 0.0,
    init: Float[ArrayLike, "..."] | None = None,
    max_rms: float | None = None,
    on_failure: str = "raise",
) -> FitResult:
    """Fit head vectors to 68 landmarks per frame (e.g. FreeTalk ATS output).

    Inputs are annotated loosely so malformed arrays reach the explicit checks below.

    Args:
        model: the face model whose ``landmarks`` are compared with the targets.
        landmarks: target landmarks in metres, ``(T, 68, 3)``.
        mask: which landmarks are observed, ``(68,)`` or ``(T, 68)`` bool; unobserved entries may
            hold anything, NaN included. ``None``: all.
        config: static settings (mode, solver, tolerances, max_steps, active subset).
        smoothness: weight of the first-difference term (traced; ``"joint"``/``"sequential"``).
        prior: L2 weight on the fitted params, scalar or ``(56,)`` per component (traced).
        init: initial params ``(56,)`` or ``(T, 56)`` (``"sequential"`` uses frame 0's and then
            warm-starts from each previous fit); inactive components stay at these values.
        max_rms: fail when a frame's landmark RMS (metres) exceeds this. ``None``: no threshold.
        on_failure: ``"raise"`` (default) or ``"return"`` a result with ``converged`` False.

    Returns:
        :class:`FitResult` with ``params`` ``(T, 56)`` and per-frame landmark RMS.

    Raises:
        ValueError: wrong shapes, NaN/inf in observed landmarks or in init/weights, fewer observed
            landmarks in a frame than needed (``3 * points >= fitted params``), negative weights,
            smoothness in ``"independent"`` mode, bad ``on_failure``/``max_rms``.
        FitFailedError: the solver did not succeed or ``max_rms`` was exceeded (``on_failure="raise"``).
    """
    _check_on_failure(on_failure, max_rms)
    dtype = _dtype(model)
    target = _float_array(landmarks, "landmarks", dtype)
    if target.ndim != 3 or target.shape[1:] != (NUM_LANDMARKS, 3) or target.shape[0] == 0:
        raise ValueError(f"landmarks must have shape (T >= 1, {NUM_LANDMARKS}, 3), got {target.shape}")
    num_frames = target.shape[0]
    if mask is None:
        observed = np.ones((num_frames, NUM_LANDMARKS), bool)
    else:
        m = np.asarray(mask)
        if m.dtype != bool:
            raise ValueError(f"mask must be boolean, got dtype {m.dtype}")
        if m.shape == (NUM_LANDMARKS,):
            m = np.broadcast_to(m, (num_frames, NUM_LANDMARKS))
        elif m.shape != (num_frames, NUM_LANDMARKS):
            raise ValueError(f"mask must have shape (68,) or ({num_frames}, 68), got {m.shape}")
        observed = np.array(m)
    bad = observed[..., None] & ~np.isfinite(target)
    if np.any(bad):
        t, i, _ = _first_bad(bad)
        raise ValueError(
            f"landmarks hold NaN or inf at observed points (first: frame {t}, landmark {i}); "
            "mask them out to fit without them"
        )
    needed = math.ceil(len(config.active_indices) / 3)
    counts = observed.sum(axis=1)
    if np.any(counts < needed):
        t = int(np.argmin(counts))
        raise ValueError(
            f"too few observed landmarks: frame {t} has {int(counts[t])}, need at least {needed} "
            f"to fit {len(config.active_indices)} parameters (restrict FitConfig.active to fit fewer)"
        )
    weights = observed / np.sqrt(3.0 * np.maximum(counts, 1))[:, None]
    target = np.where(observed[..., None], target, 0.0).astype(dtype)
    init_arr, prior_vec, smooth = _weights_and_init(init, prior, smoothness, num_frames, config, dtype)
    out = _fit_core(
        model, None, jnp.asarray(target), jnp.asarray(weights, dtype), jnp.asarray(init_arr),
        prior_vec, smooth, config=config, kind="landmarks",
    )
    return _finish(*out, config, max_rms, on_failure)


def fit_vertices(
    model: LinearFaceModel,
    vertices: Float[ArrayLike, "..."],
    *,
    variant: TopologyVariant | None = None,
    config: FitConfig = FitConfig(),
    smoothness: float | Float[ArrayLike, ""] = 0.0,
    prior: float | Float[ArrayLike, "..."] = 0.0,
    init: Float[ArrayLike, "..."] | None = None,
    max_rms: float | None = None,
    on_failure: str = "raise",
) -> FitResult:
    """Fit head vectors to a vertex sequence of the model's mesh or of a topology variant of it.

    Inputs are annotated loosely so malformed arrays reach the explicit checks below.

    Args:
        model: the face model.
        vertices: target vertices in metres, ``(T, V, 3)`` with ``V`` the model's vertex count, or
            ``(T, V', 3)`` on ``variant``.
        variant: a remeshed face (``jaxtalk.geometry.topology.make_variant`` of this model's mesh);
            the residual is ``vertices - variant.transfer(model vertices)``.
        config, smoothness, prior, init, max_rms, on_failure: as :func:`fit_landmarks`.

    Returns:
        :class:`FitResult` with ``params`` ``(T, 56)`` and per-frame vertex RMS.

    Raises:
        ValueError: wrong shapes (including a variant of another mesh), NaN/inf, negative weights,
            smoothness in ``"independent"`` mode, bad ``on_failure``/``max_rms``.
        FitFailedError: the solver did not succeed or ``max_rms`` was exceeded (``on_failure="raise"``).
    """
    _check_on_failure(on_failure, max_rms)
    dtype = _dtype(model)
    target = _float_array(vertices, "vertices", dtype)
    surface = None
    if variant is None:
        count, kind = model.num_vertices, "vertices"
    else:
        base_vertices = int(np.max(variant.base_faces)) + 1
        if base_vertices != model.num_vertices or variant.base_faces.shape != np.shape(model.faces):
            raise ValueError(
                f"variant was made from a mesh with {base_vertices} vertices and "
                f"{len(variant.base_faces)} faces, the model has {model.num_vertices} and "
                f"{np.shape(model.faces)[0]}"
            )
        count, kind = len(variant.vertices), "surface"
        corners = variant.base_faces[variant.face_index]
        surface = (jnp.asarray(corners, jnp.int32), jnp.asarray(variant.barycentric, dtype))
    if target.ndim != 3 or target.shape[1:] != (count, 3) or target.shape[0] == 0:
        raise ValueError(f"vertices must have shape (T >= 1, {count}, 3), got {target.shape}")
    _check_finite(target, "vertices")
    num_frames = target.shape[0]
    weights = np.full((num_frames, count), 1.0 / np.sqrt(3.0 * count), dtype)
    init_arr, prior_vec, smooth = _weights_and_init(init, prior, smoothness, num_frames, config, dtype)
    out = _fit_core(
        model, surface, jnp.asarray(target), jnp.asarray(weights), jnp.asarray(init_arr),
        prior_vec, smooth, config=config, kind=kind,
    )
    return _finish(*out, config, max_rms, on_failure)


def identifiable_params(
    model: LinearFaceModel,
    *,
    target: str = "landmarks",
    params: Float[ArrayLike, "..."] | None = None,
    rtol: float = 1e-3,
) -> np.ndarray:
    """A subset of the 56 parameters that the observations determine (pivoted QR of the Jacobian).

    Column-pivoted QR of the observation Jacobian at ``params`` picks, greedily, the parameter that
    adds the most new motion; the subset is the pivots whose ``|R_kk|`` exceeds ``rtol`` times the
    largest. Fitting only these (``FitConfig(active=...)``) is a well-posed problem. The Jacobian's
    columns are normalised first, so rotations (radians) do not outrank expressions (unit
    coefficients) merely by scale.

    Args:
        model: the face model.
        target: ``"landmarks"`` (the 68 points) or ``"vertices"`` (the whole mesh).
        params: the pose to linearise at, ``(56,)``; ``None``: the rest pose.
        rtol: relative threshold on the pivots, in (0, 1).

    Returns:
        Sorted indices into the 56-d vector, ``(k,)`` int.

    Raises:
        ValueError: unknown target, bad ``params`` shape or values, ``rtol`` outside (0, 1).
    """
    import scipy.linalg

    if target not in ("landmarks", "vertices"):
        raise ValueError(f"target must be 'landmarks' or 'vertices', got {target!r}")
    if not 0 < rtol < 1:
        raise ValueError(f"rtol must lie in (0, 1), got {rtol!r}")
    dtype = _dtype(model)
    p = np.zeros(PARAM_DIM, dtype) if params is None else _float_array(params, "params", dtype)
    if p.shape != (PARAM_DIM,):
        raise ValueError(f"params must have shape (56,), got {p.shape}")
    _check_finite(p, "params")
    observe = model.landmarks if target == "landmarks" else model.vertices
    jac = np.asarray(jax.jacfwd(lambda q: observe(q).reshape(-1))(jnp.asarray(p)), np.float64)
    norms = np.linalg.norm(jac, axis=0)
    jac = jac / np.where(norms > 0, norms, 1.0)
    _, r, pivots = scipy.linalg.qr(jac, mode="economic", pivoting=True)
    diag = np.abs(np.diag(r))
    keep = diag > rtol * diag[0]
    return np.sort(pivots[: len(diag)][keep])
