"""GP fits of training: each GP of the classifier (stage d, eq. 13–14) and of the pose regressors
(stage e, eq. 15–17) is fitted in float64 (:func:`gtsjax.gp.fit`: hyperparameters by maximum
marginal likelihood, paper section 3b) and stored as the float32, bounded-cost predictor the step
runs (:meth:`~gtsjax.gp.GP.sparse`), with a line of the training report per fit.

:class:`GPFits` draws each fit's random key from one stream seeded by ``TrainConfig.seed``, in the
order training fits them, so that a seed fixes the model.
"""

import contextlib
import threading
import time
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..gp import GPArgumentError, SharedSparseGP, SparseGP, fit, fit_shared
from .config import TrainConfig


def sample(rng: np.random.Generator, idx: np.ndarray, cap: int) -> np.ndarray:
    """``idx`` if at most ``cap`` long, else ``cap`` of them drawn without replacement, in order."""
    return idx if idx.size <= cap else np.sort(rng.choice(idx, cap, replace=False))


# JAX's monitoring events for the work of making a program (tracing, lowering, XLA's compilation), as
# :mod:`jax.monitoring` names them: what a fit spends before its optimiser's first step.
_COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                   "/jax/core/compile/backend_compile_duration")


@contextlib.contextmanager
def compile_seconds() -> Iterator[list[float]]:
    """Seconds this thread spends tracing and compiling JAX programs inside the block (a one-element
    list, final once the block ends). A fit of a new size compiles its optimiser first, seconds that do
    not grow with the fit's rows: training's estimate of the time left counts them apart
    (``compile_seconds`` in each fit's summary)."""
    box = [0.0]
    me = threading.get_ident()

    def heard(event: str, duration: float, **_) -> None:
        if event in _COMPILE_EVENTS and threading.get_ident() == me:
            box[0] += duration

    jax.monitoring.register_event_duration_secs_listener(heard)
    try:
        yield box
    finally:
        jax.monitoring.unregister_event_duration_listener(heard)


def fit_gp(x, y, key, cfg: TrainConfig, progress: Callable[[dict], None] | None, label: str, n_inducing: int,
           max_fit: int | None = None) -> tuple[SparseGP, dict]:
    """One GP on inputs ``x`` [n, d] and targets ``y`` [n], with ``cfg``'s restarts and noise floor;
    returns its float32 predictor on ``n_inducing`` inducing points (``cfg.n_inducing_var`` for the
    variance) and the fit's summary (also passed to ``progress``). With ``max_fit`` the
    hyperparameters are fitted on a subsample of that many and the posterior takes every example
    given (the caller capped them); without, the GP library's own cap applies to both. A bad setting
    is the user's :class:`~gtsjax.errors.InputError`, not the GP library's error."""
    t0 = time.perf_counter()
    cap = {} if max_fit is None else {"max_points": x.shape[0], "max_fit_points": max_fit}
    try:
        with compile_seconds() as compiling:
            gp = fit(x, y, key=key, restarts=cfg.restarts, jitter=cfg.noise_floor, **cap)
            sparse = gp.sparse(n_inducing, cfg.n_inducing_var).astype(jnp.float32)
    except GPArgumentError as err:  # the GP library is core code; to the user it is a bad setting
        raise InputError(err.where, err.problem) from None
    info = _summary(label, gp, x.shape[0], max_fit, round(time.perf_counter() - t0, 2), compiling[0])
    if progress is not None:
        progress(info)
    return sparse, info


def fit_shared_gp(x, ys: dict[str, np.ndarray], key, cfg: TrainConfig, progress: Callable[[dict], None] | None,
                  label: str, n_inducing: int, max_fit: int | None = None) -> tuple[SharedSparseGP, list[dict]]:
    """The GPs of the targets ``ys`` (name → [n]) on inputs ``x`` with one shared kernel
    (:func:`gtsjax.gp.fit_shared`: the same length scales, each its own signal and noise), as one
    float32 :class:`~gtsjax.gp.SharedSparseGP` on ``n_inducing`` inducing points; and a summary per
    output, labelled ``label.name``, the joint fit's time on the first (the others say which they
    were fitted with). Otherwise as :func:`fit_gp`."""
    t0 = time.perf_counter()
    cap = {} if max_fit is None else {"max_points": x.shape[0], "max_fit_points": max_fit}
    try:
        with compile_seconds() as compiling:
            gps = fit_shared(x, np.stack(list(ys.values()), 1), key=key, restarts=cfg.restarts,
                             jitter=cfg.noise_floor, **cap)
            shared = SharedSparseGP.build(gps, n_inducing, cfg.n_inducing_var).astype(jnp.float32)
    except GPArgumentError as err:
        raise InputError(err.where, err.problem) from None
    seconds = round(time.perf_counter() - t0, 2)
    infos = []
    for j, (name, gp) in enumerate(zip(ys, gps, strict=True)):
        info = _summary(f"{label}.{name}", gp, x.shape[0], max_fit, seconds if j == 0 else 0.0,
                        compiling[0] if j == 0 else 0.0)
        if j:
            info["kernel_shared_with"] = f"{label}.{next(iter(ys))}"
        infos.append(info)
        if progress is not None:
            progress(info)
    return shared, infos


def _summary(label: str, gp, n: int, max_fit: int | None, seconds: float, compiling: float = 0.0) -> dict:
    """A fit's line of the training report (``compile_seconds``: of its ``seconds``, those spent
    tracing and compiling, :func:`compile_seconds`)."""
    p = gp.params
    return {"gp": label, "n": int(n), "n_fit": int(min(n, max_fit or n)), "seconds": seconds,
            "compile_seconds": round(min(float(compiling), seconds), 2),
            "lml": float(gp.log_marginal_likelihood()), "signal_var": float(p.signal_var),
            "noise_var": float(p.noise_var), "lengthscale_median": float(np.median(np.asarray(p.lengthscale)))}


class GPFits:
    """The GP fits of one training run: each call fits one GP (:func:`fit_gp`) with the next key of
    the run's stream, and ``fits`` lists their summaries in order."""

    def __init__(self, cfg: TrainConfig, progress: Callable[[dict], None] | None = None):
        self.cfg = cfg
        self.progress = progress
        self.key = jax.random.PRNGKey(cfg.seed)
        self.fits: list[dict] = []

    def __call__(self, x, y, label: str, n_inducing: int, max_fit: int | None = None) -> SparseGP:
        self.key, sub = jax.random.split(self.key)
        gp, info = fit_gp(x, y, sub, self.cfg, self.progress, label, n_inducing, max_fit)
        self.fits.append(info)
        return gp

    def shared(self, x, ys: dict[str, np.ndarray], label: str, n_inducing: int,
               max_fit: int | None = None) -> SharedSparseGP:
        """The GPs of ``ys`` with one shared kernel (:func:`fit_shared_gp`), with the next key."""
        self.key, sub = jax.random.split(self.key)
        gp, infos = fit_shared_gp(x, ys, sub, self.cfg, self.progress, label, n_inducing, max_fit)
        self.fits.extend(infos)
        return gp
