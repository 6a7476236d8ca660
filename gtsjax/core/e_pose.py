"""Stage e, pose regression (eq. 15–17): per class, GPs for the object's position ``(x̃, ỹ)`` in the
candidate's object reference system and, for mobile classes, its heading as ``(sin θ̃, cos θ̃)``.

The paper regresses θ̃ directly, which breaks at ±π; regressing the sine and cosine and taking
``atan2`` does not (READING-NOTES). Landmark classes get position regressors too: the centre of a
post lies behind the surface the laser sees, and the map transformation is better fed with centres.

The GPs' predictive variances (noise included) become the measurement noise of the tracker:
position variances rotated from ORS into S, heading variance propagated through ``atan2``.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..gp import GP, SharedSparseGP, SparseGP
from ..gp.sparse import CommonInputsGP, predict_many
from .buckets import bucketed, slots_of
from .geometry import compose

# Heading variance is capped where the sine and cosine predictions carry no information.
MAX_THETA_VAR = float(jnp.pi**2 / 3)


class PoseRegressor(eqx.Module):
    """GPs of one class: ``x``, ``y`` (ORS-relative position) and, if the class has a heading, ``sin``,
    ``cos``; each on its own (``x``, ``y``, ``sin``, ``cos``), or in groups that share one kernel
    (``shared``: :class:`~gtsjax.gp.SharedSparseGP` groups whose outputs, in order, are ``x``, ``y``
    (, ``sin``, ``cos``); one kernel row per candidate and group). Training makes two
    groups, the position and the heading (:attr:`gtsjax.train.TrainConfig.pose_kernels`); models
    trained before hold the separate GPs and still load.

    ``var_scale`` multiplies the predictive variances of ``(x̃, ỹ, θ̃)``, set at training
    (:func:`gtsjax.train.calibrate.calibrate`). ``heading_var_max``: the largest (calibrated) heading
    variance of a read the tracker trusts for the heading; a candidate above it is *vague* and updates
    a track's position only (set by the same calibration; ``None``: every heading is used).

    ``turns``: the heading GPs regress ``(sin nθ̃, cos nθ̃)`` for a class whose outline looks the same
    turned by ``2π/n`` (set at training, ``n`` = 2; ``None``: 1), the heading read modulo ``2π/n``.

    ``common``: the separate GPs again, as one :class:`~gtsjax.gp.sparse.CommonInputsGP` whose
    inducing inputs are stored and read once (:meth:`with_common_inputs`; a model file's loader makes
    it, its writer leaves it out). Where it is set, :meth:`predict` uses it and the separate GPs
    are not read."""

    x: SparseGP | GP | None = None
    y: SparseGP | GP | None = None
    sin: SparseGP | GP | None = None
    cos: SparseGP | GP | None = None
    var_scale: Float[Array, "3"] | None = None
    heading_var_max: Float[Array, ""] | None = None
    shared: tuple[SharedSparseGP, ...] | None = None
    common: CommonInputsGP | None = None
    # The outline's half-turn symmetry: 2 where the class looks the same turned by 180° (a rectangular
    # base), its heading then regressed as ``(sin 2θ̃, cos 2θ̃)`` and known up to a half-turn (the other
    # side is a hypothesis of its own, as likely: stage e′, the tracker's mixture); ``None``: 1.
    turns: Int[Array, ""] | None = None

    @property
    def has_heading(self) -> bool:
        """Whether the class has heading GPs (``sin``, ``cos``)."""
        if self.shared is not None:
            return sum(g.n_outputs for g in self.shared) == 4
        return self.sin is not None and self.cos is not None

    @property
    def n_kernel_rows(self) -> int:
        """Kernel rows the step computes per candidate: one per group or separate GP."""
        return len(self.shared) if self.shared is not None else (4 if self.has_heading else 2)

    def outputs(self) -> tuple[SparseGP | GP, ...]:
        """The GPs of ``x``, ``y`` (and ``sin``, ``cos``) one by one (a shared group's outputs as
        :class:`~gtsjax.gp.SparseGP` with the same predictions)."""
        if self.shared is not None:
            return tuple(g.output(j) for g in self.shared for j in range(g.n_outputs))
        return (self.x, self.y, self.sin, self.cos) if self.has_heading else (self.x, self.y)

    def predict(self, vectors: Float[Array, "cands features"], *, include_noise: bool = False,
                mean_only: bool = False):
        """Means ``[outputs, cands]`` of ``x``, ``y`` (, ``sin``, ``cos``) and, unless ``mean_only``,
        their variances: one kernel row per shared group (groups of one shape batched), or the
        separate GPs batched (:func:`~gtsjax.gp.sparse.predict_many`)."""
        if self.common is not None:
            return (self.common.predict_mean(vectors),) if mean_only else self.common.predict(
                vectors, include_noise=include_noise)
        gps = self.shared if self.shared is not None else self.outputs()
        return predict_many(gps, vectors, include_noise=include_noise, mean_only=mean_only)

    def with_common_inputs(self) -> "PoseRegressor":
        """This regressor with :attr:`common` made from its separate GPs where they share their inducing
        inputs (a class's pose GPs each over all its training examples); else unchanged. Host-side:
        call it on a loaded model, outside any jit."""
        if self.shared is not None or self.common is not None:
            return self
        common = CommonInputsGP.of(self.outputs())
        return self if common is None else eqx.tree_at(lambda r: r.common, self, common, is_leaf=lambda x: x is None)


def regress_one_class(
    reg: PoseRegressor, vectors: Float[Array, "cands features"]
) -> tuple[Float[Array, "cands 3"], Float[Array, "cands 3"]]:
    """ORS-relative pose ``(x̃, ỹ, θ̃)`` and its variances for every candidate under one class's GPs
    (eq. 15), all outputs at once (:meth:`PoseRegressor.predict`). A class without heading GPs
    reports θ̃ = 0 with zero variance."""
    dt = vectors.dtype
    m, v = reg.predict(vectors, include_noise=True)
    if not reg.has_heading:
        zero = jnp.zeros_like(m[0], dt)
        return jnp.stack([m[0].astype(dt), m[1].astype(dt), zero], -1), jnp.stack([v[0].astype(dt), v[1].astype(dt), zero], -1)
    (mx, my, ms, mc), (vx, vy, vs, vc) = m.astype(dt), v.astype(dt)
    theta = jnp.arctan2(ms, mc)
    # dθ = (c ds − s dc) / (s² + c²): first-order propagation of the two predictive variances.
    r2 = ms**2 + mc**2
    r2_safe = jnp.where(r2 > 1e-6, r2, 1.0)
    vt = jnp.where(r2 > 1e-6, (mc**2 * vs + ms**2 * vc) / r2_safe**2, MAX_THETA_VAR)
    if reg.turns is not None:  # the GPs read n·θ̃: θ̃ modulo 2π/n, its variance 1/n² of theirs
        n = reg.turns.astype(dt)
        theta, vt = theta / n, vt / (n * n)
    var = jnp.stack([vx, vy, vt], -1)
    if reg.var_scale is not None:
        var = var * reg.var_scale.astype(var.dtype)[None, :]
    cap = jnp.asarray([jnp.inf, jnp.inf, MAX_THETA_VAR], var.dtype)
    return jnp.stack([mx, my, theta], -1), jnp.minimum(var, cap[None, :])


def vague_headings(regressors: "tuple[PoseRegressor | None, ...]", cls: Int[Array, " cands"],
                   var: Float[Array, "cands 3"]) -> Bool[Array, " cands"]:
    """Candidates whose heading variance exceeds their class's ``heading_var_max`` (never, for a class
    without one)."""
    vmax = jnp.stack([jnp.asarray(jnp.inf if r is None or r.heading_var_max is None else r.heading_var_max,
                                  var.dtype) for r in regressors])
    return var[:, 2] > vmax[cls]


def _top(sel: Bool[Array, " cands"], score: Float[Array, " cands"], k: int) -> tuple[Int[Array, " k"], Bool[Array, " k"]]:
    """Indices of the ``k`` selected candidates with the highest scores, and which of them are selected."""
    _, idx = jax.lax.top_k(jnp.where(sel, score, -jnp.inf), k)
    return idx, sel[idx]


def regress(
    regressors: tuple[PoseRegressor | None, ...],
    vectors: Float[Array, "cands features"],
    cls: Int[Array, " cands"],
    ok: Bool[Array, " cands"],
    scores: Float[Array, "cands classes"],
    max_objects: int,
    max_landmarks: int,
    bucket: bool = True,
    axis_name=None,
) -> tuple[Float[Array, "cands 3"], Float[Array, "cands 3"], Bool[Array, " cands"]]:
    """Each kept candidate's ORS-relative pose and variances under the regressors of its own class,
    and which candidates got one.

    Fixed shapes, and no GP runs on a candidate that cannot use it: per class, the candidates of the
    class with the highest class scores are gathered (``top_k``), regressed and scattered back; the
    ``max_objects`` best of a mobile class get the mean and variance GPs, the ``max_landmarks`` best
    of a landmark class the position means only (stage f reads no variance). With ``bucket`` each
    runs at the smallest of a few fixed sizes that holds the candidates present
    (:func:`~gtsjax.core.buckets.bucketed`: a scan with one robot pays for one, not eight); under
    ``vmap`` pass the mapped axis's ``axis_name`` (one bucket for the batch, its largest count),
    or leave it off: a count per element turns the branches into selects that all run. A candidate beyond its
    class's cap gets no pose and must be dropped (the third output is False for it). Background and
    unkept candidates give zeros."""
    n = vectors.shape[0]
    dt = vectors.dtype
    run = (lambda fn, v, n, w: bucketed(fn, v, n, w, axis_name)) if bucket else (lambda fn, v, _n, _w: tuple(fn(v)))
    rel = jnp.zeros((n, 3), dt)
    var = jnp.zeros_like(rel)
    posed = jnp.zeros((n,), bool)
    for k, reg in enumerate(regressors):
        if reg is None:
            continue
        sel = ok & (cls == k)
        if not reg.has_heading:
            idx, chosen = _top(sel, scores[:, k], min(max_landmarks, n))

            def means(v, reg=reg):
                (m,) = reg.predict(v, mean_only=True)
                mx, my = m.astype(dt)
                return (jnp.stack([mx, my, jnp.zeros_like(mx)], -1),)

            (r,) = run(means, vectors[idx], jnp.sum(chosen), 3)
            v = jnp.zeros_like(r)
        else:
            idx, chosen = _top(sel, scores[:, k], min(max_objects, n))
            r, v = run(lambda v, reg=reg: regress_one_class(reg, v), vectors[idx], jnp.sum(chosen), 3)
        got, src = slots_of(idx, chosen, n)
        rows = jnp.concatenate([r, v], -1)[src]
        rel = jnp.where(got[:, None], rows[:, :3], rel)
        var = jnp.where(got[:, None], rows[:, 3:], var)
        posed = posed | got
    return rel, var, posed


def to_sensor_frame(
    origin: Float[Array, "cands 2"],
    heading: Float[Array, " cands"],
    rel: Float[Array, "cands 3"],
    var: Float[Array, "cands 3"],
) -> tuple[Float[Array, "cands 3"], Float[Array, "cands 3 3"]]:
    """From each candidate's ORS to S: ``p = o′ + Rot(θ_j)(x̃, ỹ)``, heading ``θ_j + θ̃`` (eq. 16 with
    the ORS in place of O), and the covariance ``Rot diag(vx, vy) Rotᵀ`` ⊕ ``vθ``."""
    pose = compose(jnp.concatenate([origin, heading[:, None]], -1), rel)
    c, s = jnp.cos(heading), jnp.sin(heading)
    cxx = c**2 * var[:, 0] + s**2 * var[:, 1]
    cyy = s**2 * var[:, 0] + c**2 * var[:, 1]
    cxy = c * s * (var[:, 0] - var[:, 1])
    zero = jnp.zeros_like(cxx)
    cov = jnp.stack([
        jnp.stack([cxx, cxy, zero], -1),
        jnp.stack([cxy, cyy, zero], -1),
        jnp.stack([zero, zero, var[:, 2]], -1),
    ], -2)
    return pose, cov
