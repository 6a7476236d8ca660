"""Reflective tag codes and bands (``gtsjax.tags``, ``gtsjax tags``), against brute force: the distances
by every rotation with ``np.roll``, the design's distance the best over every set of codes on small
bands, and the printed band reread from its own SVG geometry."""

import itertools
import json
import math
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from gtsjax.cli import main
from gtsjax.tags.band import TAPE_COLOUR
from gtsjax.tags.codes import cells_for, design


def brute_distance(a, b) -> int:
    return min(int((np.asarray(a) != np.roll(b, r)).sum()) for r in range(len(b)))


def all_necklaces(n: int) -> list[np.ndarray]:
    """Every code of ``n`` cells with tape and body, one per rotation class, by brute force."""
    seen, out = set(), []
    for bits in itertools.product([0, 1], repeat=n):
        if 0 < sum(bits) < n:
            key = min(tuple(np.roll(bits, r)) for r in range(n))
            if key not in seen:
                seen.add(key)
                out.append(np.array(key, bool))
    return out


def test_cells_span_three_beams_at_the_range():
    beam = math.radians(0.25)
    n = cells_for(0.8, 9.0, beam)
    assert n == 6 and 0.8 / n >= 3 * 9.0 * beam and 0.8 / (n + 1) < 3 * 9.0 * beam


@pytest.mark.parametrize("cells,robots", [(6, 10), (8, 10), (10, 10), (12, 10)])
def test_design_distances_by_brute_force(cells, robots):
    d = design(robots, cells)
    assert d.codes.shape == (robots, cells)
    assert all(0 < c.sum() < cells for c in d.codes)  # tape and body on every band
    pair = min(brute_distance(a, b) for a, b in itertools.combinations(d.codes, 2))
    assert pair == d.distance >= 1  # distinct under every rotation
    assert d.self_distance == min(int((c != np.roll(c, r)).sum()) for c in d.codes for r in range(1, cells))


@pytest.mark.parametrize("cells,robots", [(5, 2), (6, 3), (7, 3), (7, 5), (8, 3), (8, 4), (8, 5)])
def test_design_distance_is_the_best_any_set_reaches(cells, robots):
    codes = all_necklaces(cells)
    dist = np.array([[brute_distance(a, b) for b in codes] for a in codes])
    sets = np.array(list(itertools.combinations(range(len(codes)), robots)))
    pairs = np.array(list(itertools.combinations(range(robots), 2)))
    best = dist[sets[:, pairs[:, 0]], sets[:, pairs[:, 1]]].min(axis=1).max()
    assert design(robots, cells).distance == best


def test_too_few_codes_is_one_line():
    from gtsjax.errors import InputError

    with pytest.raises(InputError, match="fewer than 20 robots"):
        design(20, 5)  # 6 necklaces of 5 cells with tape and body


def _cells_from_svg(path):
    """(x0, x1, tape) of each cell rectangle, read from the SVG's paths, in millimetres."""
    root = ET.parse(path).getroot()
    ns = {"s": "http://www.w3.org/2000/svg"}
    cells = []
    for g in root.iter("{http://www.w3.org/2000/svg}g"):
        if not re.fullmatch(r"cell-\d+", g.get("id", "")):
            continue
        p = g.find("s:path", ns)
        xs = [float(v) for v in re.findall(r"[ML] ([-\d.]+) [-\d.]+", p.get("d"))]
        fill = re.search(r"fill: (#[0-9a-f]{6})", p.get("style")).group(1)
        pt_to_mm = 25.4 / 72
        cells.append((min(xs) * pt_to_mm, max(xs) * pt_to_mm, fill == TAPE_COLOUR))
    return sorted(cells)


def test_tags_command_writes_bands_that_reread_to_their_codes(tmp_path, capsys):
    out = tmp_path / "tags"
    rc = main(["tags", "--robots", "4", "--perimeter", "0.8", "--range", "6", "--names", "a,b,c,d",
               "--out-dir", str(out)])
    assert rc == 0
    spec = json.loads((out / "tags.json").read_text())
    cells = spec["cells"]
    assert cells == cells_for(0.8, 6.0, math.radians(0.25))
    assert [r["name"] for r in spec["robots"]] == ["a", "b", "c", "d"]
    assert (out / "bands.pdf").read_bytes().startswith(b"%PDF")
    for robot in spec["robots"]:
        rects = _cells_from_svg(out / f"{robot['name']}.svg")
        assert len(rects) == cells
        widths = [x1 - x0 for x0, x1, _ in rects]
        np.testing.assert_allclose(widths, 800.0 / cells, atol=0.01)  # 1:1, in millimetres
        assert "".join("1" if t else "0" for *_, t in rects) == robot["code"]
    codes = [np.array([c == "1" for c in r["code"]]) for r in spec["robots"]]
    assert min(brute_distance(a, b) for a, b in itertools.combinations(codes, 2)) == spec["distance"]
    printed = capsys.readouterr().out
    assert all(f"{r['name']}\t{r['code']}" in printed for r in spec["robots"])


@pytest.mark.parametrize("args,message", [
    (["--scanner", "URG-04LX"], "reports no intensity"),
    (["--names", "a,b"], "needs 4 distinct"),
    (["--range", "40"], "at most"),
    # Millimetres for metres: a 23 MB SVG per robot, for minutes each, before.
    (["--perimeter", "800"], "800 looks like millimetres: give metres, 0.8"),
    (["--height", "30"], "30 looks like millimetres: give metres, 0.03"),
    (["--perimeter", "-1"], "not a plausible band length"),
])
def test_tags_command_refuses_in_one_line(tmp_path, capsys, args, message):
    rc = main(["tags", "--robots", "4", "--perimeter", "0.8", "--range", "6", "--out-dir", str(tmp_path / "t"), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0], err
    assert not (tmp_path / "t").exists()


def test_tags_stopped_part_way_leaves_no_bands(tmp_path, capsys, monkeypatch):
    """Ctrl-C while the bands are written (after two of four SVGs, in the PDF): none of the bands, no
    tags.json; a folder that held other files keeps them."""
    import gtsjax.tags.band as band

    out = tmp_path / "t"
    out.mkdir()
    (out / "mine.txt").write_text("kept")

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(band, "bands_pdf", stop)
    rc = main(["tags", "--robots", "4", "--perimeter", "0.8", "--range", "6", "--out-dir", str(out)])
    assert rc == 130 and "interrupted" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]
