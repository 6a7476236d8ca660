"""What reading reflective tags costs the step (issue 43: ≤ 1.2× the step without, no kernel per
identity beyond a fixed-size product).

The shipped demo model on the simulated SPL field (``spl-crossing:2003``, three robots), its step as
the live loop calls it, with and without a tag reader of 10 identities on 8-cell bands (the reader's
arc tables from the model's own learnt outlines, its intensity model a stand-in: what it costs does
not depend on its values, and the URG-04LX's scans carry no intensity to read). Timed per scan
(median, p99), and the compiled step's kernels counted both ways (``kernels.count_kernels``), with the
reader at 10 and at 20 identities: the kernel count must not grow with the identities (not in
``--quick``: three more compilations of the whole step).
"""

import dataclasses

import jax.numpy as jnp
import numpy as np

from gtsjax.core.e_tags import ARC_ANGLES, TagReader, patterns
from gtsjax.core.pipeline import init_state, step
from gtsjax.io.logs import to_scans
from gtsjax.tags.codes import design
from gtsjax.train.tags import BIN_CAP, MIN_CELLS, POINT_CAP, READ_WEIGHT, arc_from_field

from . import _data
from ._harness import LiveCall
from .kernels import compiled_text, count_kernels

SECTION = "tags"


def with_reader(model, n_ids: int):
    """The model reading ``n_ids`` identities' 8-cell bands along its own learnt outlines."""
    o = model.outline
    arc = np.zeros((model.n_classes, ARC_ANGLES), np.float32)
    has = np.asarray(o.has).copy()
    for k in np.flatnonzero(has):
        arc[k] = arc_from_field(np.asarray(o.field[k]), np.asarray(o.lo[k]), float(o.cell[k]))
    d = design(n_ids, 8)
    reader = TagReader(pattern=patterns(d.codes, np.zeros(n_ids)), arc=jnp.asarray(arc), has_arc=jnp.asarray(has),
                       range_exp=jnp.float32(0.5), tape_mean=jnp.float32(9.4), tape_sd=jnp.float32(0.45),
                       body_mean=jnp.float32(8.2), body_sd=jnp.float32(0.5), cells=jnp.int32(8),
                       min_cells=jnp.float32(MIN_CELLS), point_cap=jnp.float32(POINT_CAP),
                       bin_cap=jnp.float32(BIN_CAP), weight=jnp.float32(READ_WEIGHT))
    return dataclasses.replace(model, tags=reader, tag_names=tuple(f"robot{i + 1}" for i in range(n_ids)))


def run(ctx) -> None:
    res = ctx.results
    n = 100 if ctx.quick else 600
    log, site = _data.scenario("spl-crossing", 2003, n)
    plain = _data.demo_model(site)
    tagged = with_reader(plain, 10)
    scans = to_scans(log, plain.n_beams)
    for name, model in (("without", plain), ("with", tagged)):
        call = LiveCall(model, scans)
        res.add(f"tags.step.{name}", "ms", ctx.time_calls(call, n, warmup=20), section=SECTION,
                label=f"live step, URG-04LX, spl-crossing, {name} a tag reader of 10 identities")
    res.ratio("tags.step.with_over_without", "tags.step.with", "tags.step.without",
              meaning="the live step's time with a tag reader / without (issue 43: at most 1.2)")
    if ctx.quick:  # three more compilations of the whole step: the full run's
        return
    scan0 = jax_first(scans)
    counts = {}
    for label, model in (("without", plain), ("10 identities", tagged), ("20 identities", with_reader(plain, 20))):
        counts[label] = count_kernels(compiled_text(lambda s, x, m=model: step(m, s, x), init_state(model), scan0)).total
    res.checks["tags_kernels"] = {"kernels": counts,
                                  "added_by_the_reader": counts["10 identities"] - counts["without"],
                                  "same_for_20_identities": counts["20 identities"] == counts["10 identities"]}


def jax_first(scans):
    """The first scan of a stacked :class:`~gtsjax.core.scan.Scan`."""
    import jax

    return jax.tree.map(lambda a: a[0], scans)
