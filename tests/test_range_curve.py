"""``scripts/range_curve.py``'s Cramér–Rao bound (issue 55, lever 7) rests on each beam's range
derivative with respect to the robot's pose, ``(n_x, n_y, n·J(q − c)) / (n·u)``: checked against
finite differences of the simulator's exact ray casting, and the bound against the one a
hand-computed view of a square gives."""

import importlib.util
import math
from pathlib import Path

import numpy as np

from gtsjax.sensors import get_model
from gtsjax.sim.scene import Effects, Mover, Polygon, Scene, render, robot_shape

_spec = importlib.util.spec_from_file_location("range_curve", Path(__file__).resolve().parents[1] / "scripts" / "range_curve.py")
range_curve = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(range_curve)


def _exact(shape, sensor, pose):
    r, _ = render(Scene(movers=[Mover(shape, np.asarray(pose, np.float64)[None])]), sensor, np.zeros((1, 3)),
                  rng=np.random.default_rng(0), effects=Effects(noise=False))
    return r[0].astype(np.float64)


def test_range_derivatives_equal_finite_differences():
    sensor = get_model("URG-04LX")
    for outline, pose in (("nao", (1.2, 0.3, 0.7)), ("box", (2.0, -0.5, 2.5)), ("cart", (0.9, 0.6, -1.9))):
        shape = robot_shape(outline)
        jac = {}
        range_curve.fisher_information(shape, sensor, np.array(pose), jac)
        base = _exact(shape, sensor, pose)
        for k, h in enumerate((2e-3, 2e-3, 2e-3)):  # the rendering is float32: steps of millimetres
            step = np.zeros(3)
            step[k] = h
            up, down = _exact(shape, sensor, np.add(pose, step)), _exact(shape, sensor, np.subtract(pose, step))
            num = (up - down) / (2 * h)
            # beams whose hit stays on one edge either side (one-sided differences agree: no corner crossed)
            fwd, bwd = (up - base) / h, (base - down) / h
            inner = [i for i, b in enumerate(jac["beams"])
                     if min(up[b], down[b]) > 0 and abs(fwd[b] - bwd[b]) < 0.01 * max(1.0, abs(fwd[b]))]
            assert len(inner) >= 5
            np.testing.assert_allclose(num[jac["beams"][inner]], jac["g"][inner, k], rtol=2e-3, atol=2e-4,
                                       err_msg=f"{outline}, pose component {k}")


def test_a_face_seen_alone_leaves_the_position_along_it_unbounded():
    """A wide wall-like box seen face on: only its face is hit; sliding it along the face changes no
    range, so the position's bound is unbounded, while the heading's is finite and equals the line
    fit's, σ² / Σ (s_i − s̄)², s the hits' positions along the face (a face ``d`` from the sensor)."""
    sensor = get_model("URG-04LX")
    half = 0.1
    square = Polygon(np.array([[-half, -half], [half, -half], [half, half], [-half, half]]), np.full(4, 0.6))
    pose = np.array([1.5, 0.0, 0.0])  # its face x = 1.4 turned to the laser
    info = range_curve.fisher_information(square, sensor, pose)
    pos, head = range_curve.bounds(info)
    assert math.isinf(pos)
    r = _exact(square, sensor, pose)
    hit = np.flatnonzero(r > 0)
    a = sensor.angle_min + sensor.angle_increment * hit
    s = r[hit] * np.sin(a)  # where along the face each beam hits
    var = sensor.noise.std(r[hit]) ** 2 + sensor.noise.resolution**2 / 12
    # Heading bound of a line fit in the range direction: weighted, the face's offset marginalised.
    w = 1 / (var * np.cos(a) ** 2)  # a range error δr moves the face by δr·cos(a)
    sw = s - np.sum(w * s) / np.sum(w)
    np.testing.assert_allclose(head, 1 / np.sum(w * sw**2), rtol=0.02)
