"""Reflective tag codes (issue 43): a band of ``N`` cells around a robot at the laser's height, each
cell retro-reflective tape (1) or the body (0), one code per robot.

**Cells.** A cell must span at least :data:`MIN_BEAMS` beams at the farthest range the robots are
seen from, or a reading cannot tell where one cell ends and the next begins: ``N = ⌊perimeter /
(MIN_BEAMS · range · beam angle)⌋`` (at most :data:`MAX_CELLS`; a band of more cells fitting is
made of that many wider ones). For a UTM-30LX (0.25°) at 9 m a cell is 0.118 m: a Nao's 0.8 m band
holds 6.

**Codes.** A laser sees part of the band, from any side, and the heading that says which part it sees
may be on the wrong side (stage e′'s hypotheses); so codes are compared at every rotation. The
*distance* between two robots' codes is the least Hamming distance between one and any rotation of the
other; a code's *self-distance* is the least between it and its own non-trivial rotations (at least 1:
the code says by itself which way round it is). The design picks, among the necklaces of ``N`` cells
(a code and its rotations are one necklace), codes with both tape and body (a band all tape or all
body says nothing of its rotation, and looks like no tag), as far apart as the number of robots
allows: for the largest distance ``d`` at which enough codes are found by a greedy choice (restarted
from each code as the first), preferring codes whose self-distance is large and whose tape covers
about half the band (every side shows both). The choice is deterministic: the same arguments give the
same codes.
"""

import dataclasses
import functools
import math

import numpy as np

from ..errors import InputError

#: The fewest beams a cell spans at the farthest range (the issue's sizing rule).
MIN_BEAMS = 3
#: The most cells a band has: 2¹⁶ codes are enumerated, pairwise over rotations.
MAX_CELLS = 16


def cells_for(perimeter: float, max_range: float, beam_angle: float, min_beams: int = MIN_BEAMS) -> int:
    """How many cells a band of ``perimeter`` metres holds, each spanning ``min_beams`` beams of
    ``beam_angle`` radians at ``max_range`` metres (seen square on), at most :data:`MAX_CELLS`."""
    if not (perimeter > 0 and max_range > 0 and beam_angle > 0):
        raise InputError("tags", "perimeter, range and beam angle must be positive")
    return min(MAX_CELLS, int(math.floor(perimeter / (min_beams * max_range * beam_angle) + 1e-9)))


def rotations(code: np.ndarray) -> np.ndarray:
    """``[N, N]``: the code turned by each number of cells (row ``r`` is ``np.roll(code, r)``)."""
    code = np.asarray(code, bool)
    n = code.shape[-1]
    idx = (np.arange(n)[None, :] - np.arange(n)[:, None]) % n
    return code[..., idx]


def cyclic_distance(a: np.ndarray, b: np.ndarray) -> int:
    """The least Hamming distance between code ``a`` and any rotation of code ``b``."""
    return int((rotations(b) != np.asarray(a, bool)[None, :]).sum(-1).min())


def self_distance(code: np.ndarray) -> int:
    """The least Hamming distance between a code and its non-trivial rotations (0 for a periodic code)."""
    r = rotations(code)
    return int((r[1:] != r[0][None, :]).sum(-1).min()) if r.shape[0] > 1 else 0


@functools.lru_cache(maxsize=8)
def _necklaces(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every necklace of ``n`` cells with both tape and body, as its least rotation (an integer, cell
    ``i`` is bit ``i``): the integers, their rotations ``[K, n]`` and their self-distances."""
    words = np.arange(1 << n, dtype=np.int64)
    mask = (1 << n) - 1
    rots = np.stack([((words >> r) | (words << (n - r))) & mask for r in range(n)], 1)
    canon = words[(rots.min(1) == words) & (words != 0) & (words != mask)]
    crots = rots[np.searchsorted(words, canon)]
    selfd = _popcount(crots[:, 1:] ^ canon[:, None]).min(1) if n > 1 else np.zeros(len(canon), np.int64)
    return canon, crots, selfd


def _popcount(x: np.ndarray) -> np.ndarray:
    """Set bits of each (non-negative, < 2³²) integer: the SWAR count, whole-array."""
    x = np.asarray(x, np.int64)
    x = x - ((x >> 1) & 0x55555555)
    x = (x & 0x33333333) + ((x >> 2) & 0x33333333)
    x = (x + (x >> 4)) & 0x0F0F0F0F
    return ((x * 0x01010101) & 0xFFFFFFFF) >> 24


def _bits(word: int, n: int) -> np.ndarray:
    return np.array([(word >> i) & 1 for i in range(n)], bool)


@dataclasses.dataclass(frozen=True)
class TagDesign:
    """A set of codes: ``codes[k]`` robot ``k``'s band, cell 0 first, going round the robot
    counter-clockwise seen from above; ``distance`` the least cyclic distance between two robots'
    codes; ``self_distance`` the least between a code and its own rotations."""

    codes: np.ndarray  # [robots, cells] bool
    distance: int
    self_distance: int

    @property
    def cells(self) -> int:
        return int(self.codes.shape[1])

    def strings(self) -> list[str]:
        """Each code as a string of ``1`` (tape) and ``0`` (body), cell 0 first."""
        return ["".join("1" if b else "0" for b in c) for c in self.codes]


def design(n_robots: int, n_cells: int) -> TagDesign:
    """Codes for ``n_robots`` robots on bands of ``n_cells`` cells, as far apart as possible (see the
    module). Refused, in one line saying what would do, where there are fewer distinct codes than
    robots."""
    if n_robots < 1:
        raise InputError("tags", "--robots must be at least 1")
    if n_cells < 2:
        raise InputError("tags", f"a band of {n_cells} cell(s) holds no code: the cells are too wide for the "
                                 "perimeter; a longer band, a shorter range or a finer scanner gives more")
    canon, crots, selfd = _necklaces(n_cells)
    if len(canon) < n_robots:
        raise InputError("tags", f"a band of {n_cells} cells has {len(canon)} distinct codes, fewer than {n_robots} "
                                 "robots: a longer band, a shorter range or a finer scanner gives more cells")
    weight = _popcount(canon)
    # Preference: large self-distance, then tape near half the band, then the smaller word (determinism).
    order = np.lexsort((canon, np.abs(2 * weight - n_cells), -selfd))
    # dist[i, j]: the least Hamming distance between necklace i and any rotation of necklace j, in order.
    dist = np.full((len(canon), len(canon)), n_cells, np.uint8)
    c = canon[order]
    for r in range(n_cells):
        np.minimum(dist, _popcount(c[:, None] ^ crots[order][None, :, r]).astype(np.uint8), out=dist)
    for d in range(n_cells, 0, -1):
        # Greedy in order of preference, restarted from each code as the first: the first set found.
        for first in range(len(c)):
            chosen = [first]
            ok = dist[first] >= d
            ok[: first + 1] = False
            while len(chosen) < n_robots and ok.any():
                i = int(np.argmax(ok))
                chosen.append(i)
                ok &= dist[i] >= d
            if len(chosen) == n_robots:
                codes = np.stack([_bits(int(c[i]), n_cells) for i in chosen])
                return TagDesign(codes, int(d) if n_robots > 1 else n_cells, int(selfd[order][chosen].min()))
    raise AssertionError("unreachable: distance 1 holds every distinct necklace")  # pragma: no cover
