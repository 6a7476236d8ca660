"""Training's first labelling pass places each post at its centre (``train.labels.landmark_centres``): the
circle fit against SciPy's robust least squares, and on simulated logs of two sites the map it gives
against the simulator's true sensor pose, the radius it finds against the posts the simulator drew."""

import math

import numpy as np
import pytest

from gtsjax.core.geometry import sensor_to_field
from gtsjax.train import TrainConfig, landmark_centres, run_front_end
from gtsjax.train.bounds import LANDMARK_RADIUS, landmark_rows
from gtsjax.train.labels import circle_centres, estimate_transforms, map_scale


def _beam_points(rng, centre, radius, increment, noise):
    """The returns of beams ``increment`` apart (from the origin) on a circle: points ``[w, 2]`` and a mask."""
    d = float(np.hypot(*centre))
    bearing = math.atan2(centre[1], centre[0])
    half = math.asin(radius / d)
    b = bearing + (np.arange(-int(half / increment) - 1, int(half / increment) + 2) + rng.random()) * increment
    s = d * np.sin(b - bearing)
    hit = np.abs(s) < radius
    t = d * np.cos(b[hit] - bearing) - np.sqrt(radius**2 - s[hit] ** 2) + rng.normal(0, noise, hit.sum())
    pts = np.zeros((16, 2))
    mask = np.zeros(16, bool)
    n = min(hit.sum(), 16)
    pts[:n] = np.stack([t * np.cos(b[hit]), t * np.sin(b[hit])], -1)[:n]
    mask[:n] = True
    return pts, mask


def test_circle_centres_are_scipys_robust_least_squares():
    """Posts of 5 cm at 1-6 m seen through 0.35° beams with 3 mm of range noise, one return in five
    pulled 5 cm towards the laser (a mixed pixel): each centre is SciPy's minimum of the same Cauchy
    loss of the points' distances to the circle (a point SciPy's solver does not move from), no worse
    than the one SciPy reaches from the same start."""
    from scipy.optimize import least_squares

    rng = np.random.default_rng(3)
    radius, robust = 0.05, 0.01
    pts, mask, origin = [], [], []
    for _ in range(40):
        r, a = rng.uniform(1.0, 6.0), rng.uniform(-2.0, 2.0)
        p, m = _beam_points(rng, np.array([r * math.cos(a), r * math.sin(a)]), radius, math.radians(360 / 1024), 0.003)
        if rng.random() < 0.2:
            p[0] *= 1 - 0.05 / np.hypot(*p[0])
        pts.append(p)
        mask.append(m)
        mid = 0.5 * (p[m].min(0) + p[m].max(0))
        origin.append(mid)
    pts, mask, origin = np.asarray(pts), np.asarray(mask), np.asarray(origin)
    got = circle_centres(pts, mask, origin, radius, iterations=30, robust=robust)
    for i in range(len(pts)):
        p = pts[i][mask[i]]

        def residuals(q, p=p):
            return np.linalg.norm(p - q, axis=1) - radius

        def cost(q):
            return float(np.sum(np.log1p((residuals(q) / robust) ** 2)))

        def scipy_fit(start):
            return least_squares(residuals, start, loss="cauchy", f_scale=robust, xtol=1e-12, ftol=1e-12, gtol=1e-12).x

        # a minimum SciPy does not move from, and no worse than SciPy's own from the same start (SciPy's
        # trust region stops in a worse one on one of these posts)
        np.testing.assert_allclose(scipy_fit(got[i]), got[i], atol=1e-5)
        assert cost(got[i]) <= cost(scipy_fit(origin[i] + radius * origin[i] / np.linalg.norm(origin[i]))) + 1e-9


@pytest.mark.parametrize("site", ["spl", "hall"])
def test_the_first_pass_map_is_the_true_map_and_the_radius_the_posts(site):
    """A robot turned on the spot (``gtsjax.sim.recording``): the map from the posts' circle centres puts
    points across the field within 3 mm of where the simulator's true sensor pose puts them (the median
    over scans: each scan's map has noise of its own), and the
    radius found is the simulator's posts' to 3 mm; the map from the candidates' origins (the posts'
    visible surfaces) was a centimetre or more off, and scaled by more than 0.5 %."""
    from gtsjax.sim import recording
    from gtsjax.sim.scenarios import hall_layout, spl_layout

    layout = {"spl": spl_layout, "hall": hall_layout}[site]()
    true_radius = {r for *_, r in layout.landmarks}.pop()
    log, field = recording(site, "turn", seed=3, seconds=20.0)
    cfg = TrainConfig()
    fe = run_front_end(log, cfg.frontend, log.n_beams)
    tf, evidence = landmark_centres(log, fe, field, cfg)
    assert evidence["radius"] == pytest.approx(true_radius, abs=3e-3), evidence
    assert abs(evidence["scale_after"] - 1.0) < 1e-3 < 5e-3 < abs(evidence["scale_before"] - 1.0), evidence

    truth = log.extra["truth_sensor_pose"]  # [T, 3]
    xs, ys = np.meshgrid(np.linspace(1.0, 5.0, 5), np.linspace(0.5, 3.5, 4))
    field_pts = np.stack([xs.ravel(), ys.ravel()], -1)  # across the field, in O

    def worst_error(t):
        ok = ~t["degraded"] & (t["n"] >= 3)
        c, s = np.cos(truth[ok, 2]), np.sin(truth[ok, 2])
        d = field_pts[None] - truth[ok, None, :2]  # the field's points in the true S
        in_s = np.stack([c[:, None] * d[..., 0] + s[:, None] * d[..., 1], -s[:, None] * d[..., 0] + c[:, None] * d[..., 1]], -1)
        got = sensor_to_field(t["A"][ok, None], t["mu_s"][ok, None], t["mu_o"][ok, None], in_s)
        return float(np.max(np.linalg.norm(np.median(got - field_pts[None], axis=0), axis=-1)))  # the bias, not one scan's noise

    assert worst_error(tf) < 3e-3
    assert worst_error(estimate_transforms(fe["origin"], fe["keep"], field, cfg)) > 1e-2
    (row,) = landmark_rows([evidence], ["the recording"], ("post",))
    assert row["source"] == "learnt" and row["value"] == pytest.approx(1e3 * true_radius, abs=3.0) and "warning" not in row


def test_a_map_that_no_radius_makes_rigid_is_the_origins_and_is_warned_about():
    """Landmarks that are not round (no radius in range made the map rigid): the row says the map is
    fitted to the surfaces, by default, and warns with the share of range the labels are off; a map
    within 0.5 % of rigid is not warned about; a log that never saw three landmarks has no row."""
    far = {"radius": math.nan, "scale_before": 1.012, "scale_after": 1.012, "candidates": 900}
    near = dict(far, scale_before=1.003, scale_after=1.003)
    none = dict(far, scale_before=math.nan, scale_after=math.nan)
    rows = landmark_rows([far, near, none], ["a.npz", "b.npz", "c.npz"], ("post",))
    assert len(rows) == 2 and all(r["source"] == "default" and r["value"] == 0.0 for r in rows)
    assert "1.2 % of their range" in rows[0]["warning"] and "a.npz" in rows[0]["warning"]
    assert "warning" not in rows[1] and "b.npz" in rows[1]["evidence"]
    assert rows[0]["hard_range"] is None and rows[0]["plausible"] == list(LANDMARK_RADIUS.plausible)


def test_map_scale_is_the_median_of_the_supported_scans():
    A = np.stack([np.eye(2) * s for s in (1.0, 1.02, 1.01, 3.0)])
    tf = {"A": A, "degraded": np.array([False, False, False, True]), "n": np.array([3, 4, 2, 5])}
    assert map_scale(tf) == pytest.approx(1.01)  # the first two: the third rests on two landmarks, the last is degraded
    assert math.isnan(map_scale(dict(tf, n=np.zeros(4, int))))
