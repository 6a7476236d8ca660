"""The front end, stages a–c of Fig. 1: segmentation, ORS and characterisation, binary filters.

``front_end(cfg, scan)`` runs one scan (inside the pipeline's step); ``front_end_batch(cfg, scans)``
a stack of scans, mapped in chunks (training's labelling). Both are pure and not jitted: the caller
owns the jit. The configuration's shape-fixing integers are static (changing them recompiles), its
thresholds are arrays (tuning them does not).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..precision import exact_products
from .a_segment import Candidates, segment
from .b_features import Features, characterise_all
from .c_filters import binary_filter
from .scan import Scan

_F32 = jnp.float32
_I32 = jnp.int32


def _f32(x) -> Array:
    return jnp.asarray(x, dtype=_F32)


def _i32(x) -> Array:
    return jnp.asarray(x, dtype=_I32)


def _bool(x) -> Array:
    return jnp.asarray(x, dtype=bool)


class FrontEndConfig(eqx.Module):
    """Settings of stages a–c.

    Static (fix shapes): ``max_candidates`` K, ``window`` L (beams per candidate), ``n_dist`` N_d and
    ``n_intensity`` N_I (profile cells). With L = 96 an object of width w is windowed whole from a
    range of ``w / (L Δθ)`` on: 0.49 m for a 0.3 m robot on a URG-04LX (Δθ = 0.352°), 0.72 m on a
    UTM-30LX (0.25°); closer, it is flagged ``too_long`` and filtered.

    Arrays (tunable without recompiling):

    * ``break_distance`` (m) and ``break_growth`` (m per m of range): segmentation breaks where
      consecutive points are farther apart than ``break_distance + break_growth · min(r_i, r_{i−1})``.
      The defaults (8 cm + 2 cm/m) stay above the beam spacing (0.6 cm/m on the URG-04LX) and its
      ±1 % range noise at a moderate incidence, and below the gap between two robots side by side.
    * ``cells_on_bbox``: profile cells tile the candidate's bounding box (True) or a fixed span
      ``cell_span`` (m) centred on y′ = 0 (False, the default). The paper leaves this open. The fixed
      span is the default because it keeps size and position: a given cell is the same physical
      offset across the ORS for every candidate, which is what the stationary GP of pose regression
      (metric targets in the ORS) can use directly, whereas the bounding-box tiling rescales each
      candidate's shape by its own width (carried separately as ``w``) and spreads a single point
      over every cell. Switching it does not recompile. Validation (``scripts/choose_profile_cells.py``:
      exact pose GPs on 800 robot examples of the SPL training grid, scored on every robot candidate
      of a held-out evaluation log, spl-eval seed 4242)::

          layout                       x̃ RMSE  θ̃ median  θ̃ RMSE  misread > 30°
          fixed span 0.6 m, 10 cells   1.16 cm   3.5°      24.8°    6.2 %
          fixed span 0.4 m, 10 cells   1.19 cm   3.0°      24.2°    6.2 %
          fixed span 0.4 m, 16 cells   1.08 cm   2.4°      24.5°    7.0 %
          bounding box, 10 cells       1.17 cm   2.9°      24.4°    5.7 %

      The layouts are within 1.3 percentage points of one another on what matters downstream, the
      fraction of misread headings (which sets the heading RMSE; the median is the GP's resolution
      on the good ones): the table does not single one out, so the default stays the layout that
      keeps physical size, and a 0.6 m span fits every side of the robot.
    * ``cell_span`` (m, default 0.6: wider than a Nao with its body extension seen from any side).
    * ``sigma_cells``: the kernel σ of eq. 11–12 in cell widths (default 1); ``sigma_min`` (m) floors
      σ (a bounding box of zero width).
    * ``width_min``, ``width_max`` (m) and ``min_points``: the binary filters.
    """

    max_candidates: int = eqx.field(static=True, default=32)
    window: int = eqx.field(static=True, default=96)
    n_dist: int = eqx.field(static=True, default=10)
    n_intensity: int = eqx.field(static=True, default=10)
    break_distance: Float[Array, ""] = eqx.field(converter=_f32, default=0.08)
    break_growth: Float[Array, ""] = eqx.field(converter=_f32, default=0.02)
    cells_on_bbox: Bool[Array, ""] = eqx.field(converter=_bool, default=False)
    cell_span: Float[Array, ""] = eqx.field(converter=_f32, default=0.6)
    sigma_cells: Float[Array, ""] = eqx.field(converter=_f32, default=1.0)
    sigma_min: Float[Array, ""] = eqx.field(converter=_f32, default=0.005)
    width_min: Float[Array, ""] = eqx.field(converter=_f32, default=0.03)
    width_max: Float[Array, ""] = eqx.field(converter=_f32, default=0.8)
    min_points: Int[Array, ""] = eqx.field(converter=_i32, default=3)

    @property
    def n_features(self) -> int:
        return 1 + self.n_dist + self.n_intensity


class FrontEndDiagnostics(eqx.Module):
    """Counts of one scan (a stack adds a leading ``scans`` axis)."""

    n_segments: Int[Array, "*scans"]  # segments found, including those beyond K
    n_overflow: Int[Array, "*scans"]  # segments beyond K, dropped
    n_too_long: Int[Array, "*scans"]  # segments in a slot but longer than L beams, filtered
    n_kept: Int[Array, "*scans"]  # candidates passing the binary filters


class FrontEndOutput(eqx.Module):
    """What stages a–c hand on: the candidate slots, their ORS and vectors, the binary filters' keep
    mask (the site-bounds test comes later, in O, in the pipeline) and the scan's counts."""

    candidates: Candidates
    features: Features
    keep: Bool[Array, "*scans cands"]  # passes the binary filters (stage c), before the bounds test
    diagnostics: FrontEndDiagnostics


@exact_products
def front_end(cfg: FrontEndConfig, scan: Scan) -> FrontEndOutput:
    """Stages a–c on one scan."""
    cands = segment(
        scan,
        max_candidates=cfg.max_candidates,
        window=cfg.window,
        break_distance=cfg.break_distance,
        break_growth=cfg.break_growth,
    )
    feats = characterise_all(
        cands,
        n_dist=cfg.n_dist,
        n_intensity=cfg.n_intensity,
        cells_on_bbox=cfg.cells_on_bbox,
        cell_span=cfg.cell_span,
        sigma_cells=cfg.sigma_cells,
        sigma_min=cfg.sigma_min,
    )
    keep = binary_filter(
        cands.live,
        cands.too_long,
        feats.n_points,
        feats.width,
        width_min=cfg.width_min,
        width_max=cfg.width_max,
        min_points=cfg.min_points,
    )
    diag = FrontEndDiagnostics(
        n_segments=cands.n_segments,
        n_overflow=cands.n_overflow,
        n_too_long=cands.n_too_long,
        n_kept=jnp.sum(keep, dtype=_I32),
    )
    return FrontEndOutput(cands, feats, keep, diag)


def _drop_windows(out: FrontEndOutput) -> FrontEndOutput:
    """The output without its ``[K, L]`` per-beam arrays (candidate windows, ORS points): what batch
    replay keeps by default (the windows are some 110 kB a scan; 1 GB for 10 000 scans)."""
    c, f = out.candidates, out.features
    cands = Candidates(
        index=None,
        mask=None,
        ranges=None,
        angles=None,
        xy=None,
        intensities=None,
        live=c.live,
        too_long=c.too_long,
        start=c.start,
        length=c.length,
        n_segments=c.n_segments,
        n_overflow=c.n_overflow,
        n_too_long=c.n_too_long,
        occluded=c.occluded,
    )
    feats = Features(f.origin, f.heading, None, f.vector, f.n_points, f.width, f.height)
    return FrontEndOutput(cands, feats, out.keep, out.diagnostics)


def front_end_batch(cfg: FrontEndConfig, scans: Scan, chunk: int = 8, windows: bool = False) -> FrontEndOutput:
    """Stages a–c on a stack of scans (leading axis), vmapped over chunks of ``chunk`` scans (small
    chunks keep each chunk's cells × points weights in cache; 8 was fastest on a 2-core CPU).

    With ``windows`` False (the default) the per-beam arrays are left out: the candidates' ``index``,
    ``mask``, ``ranges``, ``angles``, ``xy``, ``intensities`` and the features' ``points`` are None;
    every per-candidate field is there.
    """

    def one(scan):
        out = front_end(cfg, scan)
        return out if windows else _drop_windows(out)

    return jax.lax.map(one, scans, batch_size=chunk)
