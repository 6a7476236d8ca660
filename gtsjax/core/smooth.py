"""Fixed-interval smoothing of the tracks after the forward pass (issue 42): the Rauch–Tung–Striebel
backward pass over each track's filtered states (:mod:`.g_kalman`'s extended Kalman filter over
``(x, y, θ, vx, vy, ω)``, its constant-velocity or inflate-only motion model), sequential or parallel
in time.

With ``F``, ``Q`` the motion model over ``dt[t+1]`` and ``m_f``, ``P_f`` the filtered mean and
covariance at step ``t``, the backward recursion is

* ``P_pred = F P_f Fᵀ + Q``, gain ``G = P_f Fᵀ P_pred⁻¹``,
* ``m_s(t) = m_f + G (m_s(t+1) − F m_f)``,
* ``P_s(t) = P_f + G (P_s(t+1) − P_pred) Gᵀ``,

starting from ``m_s = m_f``, ``P_s = P_f`` at a track's last step. :func:`rts_sequential` runs it under a
reversed ``lax.scan``; :func:`rts_associative` writes each step as the affine map
``x_t = E_t x_{t+1} + g_t`` with covariance ``L_t`` (``E = G``, ``g = m_f − E F m_f``,
``L = P_f − E F P_f``; a track's last step is ``(0, m_f, P_f)``) and composes them with
``lax.associative_scan``, O(log T) deep (Särkkä and García-Fernández, *Temporal parallelization of
Bayesian smoothers*, IEEE TAC 66(1), 2021).

**Segments.** ``valid[t]`` says the slot holds a track at step ``t``; a slot may hold several lives one
after another. Step ``t`` is linked to ``t + 1`` where both are valid and ``cut[t + 1]`` is not (a new
life begun in a slot the old one left the scan before): a run of linked steps is one segment, smoothed
on its own (its last valid step starts the backward pass). Invalid steps come back
as they went in.

**Heading.** The filter wraps the heading to (−π, π]; the smoother is linear and needs it continuous
along a segment. Instead of unwrapping a whole segment into one long sequence (a track that spins for
an hour reaches thousands of radians, where float32 keeps a few milliradians), each step works in its
own frame, its filtered heading moved to 0, and the step to the next frame is the wrapped difference of
the filtered headings ``δ_t = wrap(θ_f(t+1) − θ_f(t))``: the same arithmetic as unwrapping by successive
wrapped differences, with numbers no larger than a few radians. The result is moved back and wrapped.
"""

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..precision import exact_products
from .g_kalman import motion_model
from .g_types import NX, TrackerParams
from .geometry import wrap

_HEADING = 2


def _transition(dt: Float[Array, ""], params: TrackerParams, dtype) -> tuple[Float[Array, "6 6"], Float[Array, "6 6"]]:
    """``F`` and ``Q`` of :func:`~.g_kalman.motion_model` over ``dt``, in ``dtype``. The motion model
    builds its constant blocks in float32; a float64 ``dt`` is promoted into them here (scoped, at trace
    time) so that a float64 smoother gets a float64 model, not one rounded to float32."""
    with jax.numpy_dtype_promotion("standard"):
        F, Q = motion_model(dt.astype(dtype), params)
    return F.astype(dtype), Q.astype(dtype)


def _sym(a):
    return 0.5 * (a + a.T)


def _heading_vector(v):
    """``v e_θ``: a state vector with ``v`` as its heading and zeros elsewhere."""
    return jnp.where(jnp.arange(NX, dtype=jnp.int32) == _HEADING, v, 0)


def _gain(P_f: Float[Array, "6 6"], dt_next: Float[Array, ""], params: TrackerParams, extra_next):
    """``F``, ``P_pred = F P_f Fᵀ + Q`` (symmetrised; ``extra_next`` added to its diagonal) and the
    smoother gain ``G = P_f Fᵀ P_pred⁻¹``, by a solve (``P_pred`` and ``P_f`` symmetric:
    ``G = (P_pred⁻¹ F P_f)ᵀ``)."""
    F, Q = _transition(dt_next, params, P_f.dtype)
    P_pred = _sym(F @ P_f @ F.T + Q + jnp.diag(extra_next.astype(P_f.dtype)))
    G = jnp.linalg.solve(P_pred, F @ P_f).T
    return F, P_pred, G


def _local(mean, cov, dt, valid, cut, extra):
    """What each step needs, in its own heading frame: the filtered mean with its heading at 0, the
    heading that frame sits at, whether the step is linked to the next, the next step's ``dt``, the turn
    ``δ_t`` into the next step's frame, and a covariance that is safe to solve with (unlinked steps get
    the identity, so that an empty slot's zeros or NaN never reach a solve)."""
    dtype = mean.dtype
    theta = mean[:, _HEADING]
    link = valid & jnp.concatenate([valid[1:] & ~cut[1:], jnp.zeros(1, bool)])
    dt_next = jnp.concatenate([dt[1:], jnp.zeros(1, dt.dtype)]).astype(dtype)
    dt_next = jnp.where(link, dt_next, 0)
    delta = wrap(jnp.concatenate([theta[1:], theta[-1:]]) - theta)
    delta = jnp.where(link, delta, 0)
    m_loc = jnp.where(valid[:, None], mean.at[:, _HEADING].set(0), 0)
    eye = jnp.eye(NX, dtype=dtype)
    P_safe = jnp.where(link[:, None, None], cov, eye)
    extra_next = jnp.concatenate([extra[1:], jnp.zeros((1, NX), extra.dtype)])
    return m_loc, theta, link, dt_next, delta, P_safe, extra_next


def _global(m_loc, P_s, mean, cov, theta, valid):
    """Smoothed values out of the steps' frames: heading moved back and wrapped; invalid steps as given."""
    out = m_loc.at[:, _HEADING].add(theta)
    out = out.at[:, _HEADING].set(wrap(out[:, _HEADING]))
    return jnp.where(valid[:, None], out, mean), jnp.where(valid[:, None, None], P_s, cov)


@exact_products
def rts_sequential(
    mean: Float[Array, "steps 6"],
    cov: Float[Array, "steps 6 6"],
    dt: Float[Array, " steps"],
    valid: Bool[Array, " steps"],
    params: TrackerParams,
    cut: Bool[Array, " steps"] | None = None,
    extra: Float[Array, "steps 6"] | None = None,
) -> tuple[Float[Array, "steps 6"], Float[Array, "steps 6 6"]]:
    """The RTS smoother over one slot's filtered states (module docstring), one step after another: a
    reversed ``lax.scan`` carrying the next step's smoothed mean (in its own heading frame) and
    covariance. ``dt[t]`` is the time from step ``t − 1`` to ``t`` (``dt[0]`` unused)."""
    cut = jnp.zeros_like(valid) if cut is None else cut
    extra = jnp.zeros_like(mean) if extra is None else extra
    m_loc, theta, link, dt_next, delta, P_safe, extra_next = _local(mean, cov, dt, valid, cut, extra)

    def back(carry, x):
        m_next, P_next = carry
        m_f, P_f, P_ok, dtn, d, lk, ex = x
        F, P_pred, G = _gain(P_ok, dtn, params, ex)
        # the next smoothed state seen from this step's heading frame, less its prediction
        r = m_next + _heading_vector(d) - F @ m_f
        m_s = m_f + G @ r
        P_s = _sym(P_f + G @ (P_next - P_pred) @ G.T)
        m_s, P_s = jnp.where(lk, m_s, m_f), jnp.where(lk, P_s, P_f)
        return (m_s, P_s), (m_s, P_s)

    P_in = jnp.where(valid[:, None, None], cov, 0)
    init = (jnp.zeros(NX, mean.dtype), jnp.zeros((NX, NX), mean.dtype))
    _, (m_s, P_s) = jax.lax.scan(back, init, (m_loc, P_in, P_safe, dt_next, delta, link, extra_next), reverse=True)
    return _global(m_s, P_s, mean, cov, theta, valid)


def _element(m_f, P_f, P_ok, dt_next, delta, link, valid, extra_next, params):
    """One step's element ``(E, g, L)`` of the parallel smoother, in its heading frame:
    ``x_t = E x_{t+1} + g`` with ``x_{t+1}`` in the next step's frame, so ``g = m_f − E (F m_f − δ e_θ)``.
    A segment's last step is ``(0, m_f, P_f)``; an invalid step ``(0, 0, 0)``, which nothing reads."""
    F, P_pred, G = _gain(P_ok, dt_next, params, extra_next)
    g = m_f - G @ (F @ m_f - _heading_vector(delta))
    L = _sym(P_f - G @ P_pred @ G.T)
    zero = jnp.zeros_like(G)
    E = jnp.where(link, G, zero)
    g = jnp.where(link, g, jnp.where(valid, m_f, 0))
    L = jnp.where(link, L, jnp.where(valid, P_f, zero))
    return E, g, L


def _combine(later, earlier):
    """The smoother's associative operator: ``earlier ∘ later`` maps the state after ``later``'s
    span to ``earlier``'s step: ``(E_e E_l, E_e g_l + g_e, E_e L_l E_eᵀ + L_e)``. ``lax.associative_scan``
    with ``reverse=True`` calls ``fn(later, earlier)``."""
    E_l, g_l, L_l = later
    E_e, g_e, L_e = earlier
    return E_e @ E_l, E_e @ g_l + g_e, _sym(E_e @ L_l @ E_e.T) + L_e


@exact_products
def rts_associative(
    mean: Float[Array, "steps 6"],
    cov: Float[Array, "steps 6 6"],
    dt: Float[Array, " steps"],
    valid: Bool[Array, " steps"],
    params: TrackerParams,
    cut: Bool[Array, " steps"] | None = None,
    extra: Float[Array, "steps 6"] | None = None,
) -> tuple[Float[Array, "steps 6"], Float[Array, "steps 6 6"]]:
    """The same smoother as :func:`rts_sequential`, parallel in time: every step's element at once, then
    ``lax.associative_scan`` (reversed) of :func:`_combine`; the composed ``g`` and ``L`` at each step are
    its smoothed mean and covariance (the composition ends at its segment's last step, whose ``E`` is 0)."""
    cut = jnp.zeros_like(valid) if cut is None else cut
    extra = jnp.zeros_like(mean) if extra is None else extra
    m_loc, theta, link, dt_next, delta, P_safe, extra_next = _local(mean, cov, dt, valid, cut, extra)
    P_in = jnp.where(valid[:, None, None], cov, 0)
    element = functools.partial(_element, params=params)
    elems = jax.vmap(element)(m_loc, P_in, P_safe, dt_next, delta, link, valid, extra_next)
    _, m_s, P_s = jax.lax.associative_scan(jax.vmap(_combine), elems, reverse=True)
    return _global(m_s, P_s, mean, cov, theta, valid)


@functools.partial(jax.jit, static_argnames="parallel")
def smooth_tracks(
    mean: Float[Array, "steps tracks 6"],
    cov: Float[Array, "steps tracks 6 6"],
    dt: Float[Array, " steps"],
    valid: Bool[Array, "steps tracks"],
    params: TrackerParams,
    parallel: bool = True,
    cut: Bool[Array, "steps tracks"] | None = None,
    extra: Float[Array, "steps tracks 6"] | None = None,
) -> tuple[Float[Array, "steps tracks 6"], Float[Array, "steps tracks 6 6"]]:
    """Every slot of a replay smoothed, one program for all of them (``vmap`` over the slots, their
    lives told apart by ``valid``): :func:`rts_associative` where ``parallel``, else :func:`rts_sequential`.
    The arrays are the forward pass's, stacked over scans: ``mean[t, m]``, ``cov[t, m]`` filtered;
    ``cut[t, m]``: a life begins at ``t`` in slot ``m`` (where the slot's track id changed);
    ``extra[t, m]``: variances added to the prediction into step ``t`` (where the forward pass threw
    information away: a turn rate forgotten, a heading replaced by another hypothesis's), so that the
    smoother does not read the filter's reset as evidence."""
    f = rts_associative if parallel else rts_sequential
    cut = jnp.zeros_like(valid) if cut is None else cut
    extra = jnp.zeros_like(mean) if extra is None else extra
    return jax.vmap(f, in_axes=(1, 1, None, 1, None, 1, 1), out_axes=1)(mean, cov, dt, valid, params, cut, extra)
