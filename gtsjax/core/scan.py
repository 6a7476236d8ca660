"""The padded scan: what every driver (log replay, live sensor, simulator) hands to the numeric core;
and a scanner's beams (:class:`Beams`), the one description of its geometry that sensors, logs,
models and scans share."""

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .geometry import relative


def valid_beams(ranges, range_min, range_max):
    """Beams with a return: finite, positive and inside the scanner's ``[range_min, range_max]``. The
    one definition, for logs and live frames alike (the step zeroes every other beam): NumPy arrays on
    the host, JAX arrays inside the live step (plain operators serve both)."""
    r = ranges if hasattr(ranges, "shape") else np.asarray(ranges)
    with np.errstate(invalid="ignore"):
        return ((r - r) == 0) & (r > 0) & (r >= range_min) & (r <= range_max)  # r − r: NaN unless finite


def within(frame, xy, first, last, range_min, range_max):
    """Whether each position ``xy`` ``[n, 2]`` lies within a laser's reach: its bearing in S between
    ``first`` and ``last`` (radians) and its range in ``[range_min, range_max]`` (metres). ``frame``
    places the laser: a :class:`~gtsjax.core.f_maptransform.Transform` (O to S, in the step) or the
    laser's pose ``(x, y, θ)`` in O (on the host, NumPy). The one definition of a laser's reach
    (:meth:`Beams.reach`; the several-laser state keeps each laser's bounds as numbers)."""
    xy_s = frame.to_sensor(xy) if hasattr(frame, "to_sensor") else relative(np.asarray(frame), np.asarray(xy))
    xp = jnp if isinstance(xy_s, jax.Array) else np
    rho = xp.sqrt(xp.sum(xy_s**2, axis=-1))
    bearing = xp.arctan2(xy_s[..., 1], xy_s[..., 0])
    return (bearing >= first) & (bearing <= last) & (rho >= range_min) & (rho <= range_max)


class Beams(eqx.Module):
    """A scanner's beams, the one description of its geometry: beam ``i`` (``0 <= i < count``) points
    at ``angle_min + i * increment`` radians in S, counter-clockwise from its forward axis, and a
    return counts inside ``[range_min, range_max]`` metres.

    Sensor models (:attr:`gtsjax.sensors.SensorModel.beams`), logs (:attr:`gtsjax.io.logs.ScanLog.beams`),
    models (:attr:`gtsjax.core.model.Model.beams`) and scans (:attr:`Scan.beams`) each give theirs as
    one; checking a log or a sensor against a model compares two of them
    (:func:`gtsjax.io.logs.fit_geometry`). On the host the fields are floats and the methods return
    NumPy arrays; in the step ``angle_min`` and ``increment`` may be arrays (a scan's, with a leading
    ``scans`` axis) and the methods return JAX arrays. ``count`` fixes shapes, so it is static.
    """

    angle_min: Any
    increment: Any
    count: int = eqx.field(static=True)
    range_min: Any = 0.0
    range_max: Any = math.inf

    @property
    def angle_max(self):
        """The last beam's angle."""
        return self.angle_min + (self.count - 1) * self.increment

    def angles(self):
        """Every beam's angle in S, radians: ``[count]`` (float64 on the host), or ``[*scans, count]``
        for a scan's arrays."""
        if isinstance(self.angle_min, jax.Array) or isinstance(self.increment, jax.Array):
            a0, da = jnp.asarray(self.angle_min), jnp.asarray(self.increment)
            i = jnp.arange(self.count, dtype=a0.dtype).reshape((1,) * a0.ndim + (-1,))
            return a0[..., None] + i * da[..., None]
        return self.angle_min + np.arange(self.count) * self.increment

    def valid(self, ranges):
        """Which of ``ranges`` hold a return (:func:`valid_beams` in this range window)."""
        return valid_beams(ranges, self.range_min, self.range_max)

    def reach(self, frame, xy, *, margin: float = 0.0):
        """Whether each position ``xy`` ``[n, 2]`` in O lies where this scanner can see, placed by
        ``frame`` (see :func:`within`): between the first and last beams' bearings, and at a range
        within the range window, its far end less ``margin``."""
        return within(frame, xy, self.angle_min, self.angle_max, self.range_min, self.range_max - margin)


class Scan(eqx.Module):
    """One laser scan with a fixed beam count (padded to the sensor model's ``n_beams``).

    Beam ``i`` points at ``angle_min + i * angle_increment`` in the sensor frame S (:attr:`beams`). ``valid`` is
    False for padding and for beams with no return; the ``ranges`` and ``intensities`` of invalid
    beams are 0 and must not be read. ``dt`` is the time since the previous scan, in seconds (the
    absolute float64 stamp stays on the host). A stack of scans is the same type with a leading
    ``scans`` axis on every field.
    """

    ranges: Float[Array, "*scans beams"]
    intensities: Float[Array, "*scans beams"]
    valid: Bool[Array, "*scans beams"]
    angle_min: Float[Array, "*scans"]
    angle_increment: Float[Array, "*scans"]
    dt: Float[Array, "*scans"]

    @property
    def n_beams(self) -> int:
        return self.ranges.shape[-1]

    @property
    def beams(self) -> Beams:
        """The scan's beams: its (per-scan) first angle and step, its padded beam count; no range
        window (the beams without a return are already marked in ``valid``)."""
        return Beams(self.angle_min, self.angle_increment, self.n_beams)

    def angles(self) -> Float[Array, "*scans beams"]:
        """Beam angles in S, radians."""
        return self.beams.angles()
