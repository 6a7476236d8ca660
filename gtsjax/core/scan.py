"""The padded scan: what every driver (log replay, live sensor, simulator) hands to the numeric core."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float


class Scan(eqx.Module):
    """One laser scan with a fixed beam count (padded to the sensor model's ``n_beams``).

    Beam ``i`` points at ``angle_min + i * angle_increment`` in the sensor frame S. ``valid`` is
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

    def angles(self) -> Float[Array, "*scans beams"]:
        """Beam angles in S, radians."""
        i = jnp.arange(self.n_beams, dtype=self.ranges.dtype).reshape((1,) * (self.ranges.ndim - 1) + (-1,))
        return self.angle_min[..., None] + i * self.angle_increment[..., None]
