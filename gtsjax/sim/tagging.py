"""Which band each simulated robot wears (issue 43, ``docs/tags.md``, "Tags in the simulator").

A scene's robots wear tags where one of its lasers reports intensity (a UTM-30LX; a URG-04LX reports
none, so a scene seen only by URG-04LX lasers is rendered as before, bit for bit). The codes are
:func:`gtsjax.tags.codes.design`'s for the scene's robot count, on bands of
:func:`~gtsjax.tags.codes.cells_for` cells: the outline's perimeter, the finest intensity laser's beam
angle and the farthest a robot is seen from, taken as the farthest point of the field (its bounds)
from any laser that reads intensity, at most that laser's maximum range. Robot ``m`` (the ``m``-th
labelled object) is named ``robot{m+1}``, as the simulated beliefs name it, and wears code ``m``, its
band mounted as designed (cell 0 at the front right corner, no offset). A band mounted turned (what
enrolment measures) is :class:`RobotTags`'s ``offsets``, given in the Python API.
"""

import dataclasses
import math

import numpy as np

from ..errors import InputError
from ..io.site import SiteTags, TagWearer
from ..sensors import SensorModel
from ..tags.codes import cells_for, design
from .scene import Polygon, outline_perimeter, robot_shape, tagged_shape


@dataclasses.dataclass(frozen=True)
class RobotTags:
    """The bands of a scene's robots: ``codes[m]`` robot ``m``'s (``[M, N]`` bool, cell 0 first), mounted
    turned by ``offsets[m]`` cells (its cell 0 over the outline's cell ``offsets[m]``; empty: none is)."""

    outline: str
    codes: np.ndarray
    names: tuple[str, ...]
    perimeter_m: float
    range_m: float
    offsets: tuple[int, ...] = ()

    def offset(self, m: int) -> int:
        """How many cells robot ``m``'s band is turned as mounted."""
        return int(self.offsets[m]) if self.offsets else 0

    def shape(self, m: int) -> Polygon:
        """Robot ``m``'s outline wearing its band."""
        return tagged_shape(self.outline, self.codes[m], self.offset(m))

    def site_entry(self) -> SiteTags:
        """The site file's ``tags`` entry (:class:`~gtsjax.io.site.SiteTags`)."""
        wearers = tuple(TagWearer(n, "".join("1" if b else "0" for b in c), self.offset(m))
                        for m, (n, c) in enumerate(zip(self.names, self.codes, strict=True)))
        return SiteTags(int(self.codes.shape[1]), round(self.perimeter_m, 6), wearers, round(self.range_m, 3))


def robot_names(n_robots: int) -> tuple[str, ...]:
    """The simulator's names of its robots, as :func:`gtsjax.sim.beliefs.simulate_beliefs` gives them."""
    return tuple(f"robot{m + 1}" for m in range(n_robots))


def farthest_range(lasers: list[tuple[float, float]], bounds: tuple[float, float, float, float]) -> float:
    """The farthest point of the field ``bounds`` from any of the ``lasers`` (x, y): a corner."""
    x0, y0, x1, y1 = bounds
    return max(math.dist(p, c) for p in lasers for c in ((x0, y0), (x1, y0), (x1, y1), (x0, y1)))


def wants_tags(tags: bool | None, models: list[SensorModel]) -> bool:
    """Whether a scene seen by ``models`` gets tagged robots: ``None`` (the default) where one of them
    reports intensity; ``True`` asked of lasers none of which does is one line saying so."""
    if tags is None:
        return any(m.has_intensity for m in models)
    if tags and not any(m.has_intensity for m in models):
        names = ", ".join(sorted({m.name for m in models}))
        raise InputError("--tags", f"the {names} reports no intensity, so it cannot see tags: tags need a scanner "
                                   "that does (UTM-30LX)")
    return bool(tags)


def robot_tags(n_robots: int, outline: str, lasers: list[tuple[tuple[float, float], SensorModel]],
               bounds: tuple[float, float, float, float]) -> RobotTags:
    """Codes for ``n_robots`` robots of ``outline`` seen by ``lasers`` (position, scanner) on a field of
    ``bounds``: cells sized for the lasers that read intensity (all of them where none does)."""
    readers = [(p, m) for p, m in lasers if m.has_intensity] or list(lasers)
    rng = max(min(farthest_range([p], bounds), m.range_max) for p, m in readers)
    beam = min(m.angle_increment for _, m in readers)
    perim = outline_perimeter(robot_shape(outline))
    cells = cells_for(perim, rng, beam)
    try:
        d = design(n_robots, cells)
    except InputError as err:
        raise InputError("tags", f"{n_robots} robots seen from up to {rng:.1f} m: {err.problem}") from None
    return RobotTags(outline, d.codes, robot_names(n_robots), perim, rng)
