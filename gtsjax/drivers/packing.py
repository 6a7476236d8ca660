"""A pytree of arrays held as one flat buffer per dtype between compiled calls.

Every array that enters or leaves a compiled call costs the call a few microseconds on the host
(PjRt makes, checks and later frees a buffer for each), whatever its size. The live step's state and
output are a few dozen small arrays, whose buffers alone cost a large share of the whole step
(measured in ``docs/speed.md``). Packed, they are three buffers each way (float32, int32, bool).

:class:`Packing` is the layout, made from any example of the tree (arrays or
``jax.ShapeDtypeStruct``): :meth:`~Packing.pack` inside the compiled function (one concatenation per
dtype), :meth:`~Packing.unpack` inside it again (slices, which XLA folds into their readers), or on
the host with NumPy buffers (views, no copy).
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class Packing:
    """Where each leaf of a pytree lies in the buffers: ``dtypes`` holds one buffer's dtype each, and
    leaf ``i`` (in ``jax.tree`` order) is ``buffers[group[i]][offset[i]:offset[i] + size]`` reshaped
    to ``shapes[i]``."""

    treedef: object
    shapes: tuple[tuple[int, ...], ...]
    dtypes: tuple[np.dtype, ...]
    group: tuple[int, ...]
    offset: tuple[int, ...]

    @classmethod
    def of(cls, tree) -> "Packing":
        """The layout of ``tree``'s structure, shapes and dtypes."""
        leaves, treedef = jax.tree.flatten(tree)
        dts = [np.dtype(leaf.dtype) for leaf in leaves]
        dtypes = tuple(dict.fromkeys(dts))  # in order of first appearance
        used = dict.fromkeys(dtypes, 0)
        group, offset = [], []
        for leaf, dt in zip(leaves, dts, strict=True):
            group.append(dtypes.index(dt))
            offset.append(used[dt])
            used[dt] += math.prod(leaf.shape)
        return cls(treedef, tuple(tuple(leaf.shape) for leaf in leaves), dtypes, tuple(group), tuple(offset))

    def pack(self, tree) -> tuple[jax.Array, ...]:
        """``tree`` (of this layout) as one flat buffer per dtype: traceable, for inside ``jit``."""
        leaves = self.treedef.flatten_up_to(tree)
        return tuple(jnp.concatenate([jnp.ravel(leaf) for leaf, g in zip(leaves, self.group, strict=True) if g == k])
                     for k in range(len(self.dtypes)))

    def unpack(self, buffers):
        """The tree from its buffers (JAX arrays inside ``jit``, or NumPy arrays on the host)."""
        if len(buffers) != len(self.dtypes):
            raise ValueError(f"expected {len(self.dtypes)} buffers ({', '.join(map(str, self.dtypes))}), got {len(buffers)}")
        leaves = [buffers[g][o:o + math.prod(s)].reshape(s)
                  for g, o, s in zip(self.group, self.offset, self.shapes, strict=True)]
        return jax.tree.unflatten(self.treedef, leaves)

    def unpack_host(self, buffers):
        """:meth:`unpack` into NumPy arrays, fetching each buffer from the device once."""
        return self.unpack(tuple(np.asarray(b) for b in buffers))
