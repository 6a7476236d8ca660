"""A second implementation of the pipeline gives the same tracks: the NumPy / scikit-learn / filterpy
reference of ``tests/reference/`` against gtsjax's step, on the same simulated log with the
shipped model. The reference runs in float64 and the step in float32, so ids and counts must be
identical and poses equal to rounding (micrometres; the tolerances leave room for a retrained model)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gtsjax.cli.demo import demo_model_path  # noqa: E402
from gtsjax.core.pipeline import perceive  # noqa: E402
from gtsjax.drivers.batch import process_log  # noqa: E402
from gtsjax.gp import predict_mean  # noqa: E402
from gtsjax.io import to_scans  # noqa: E402
from gtsjax.io.modelfile import load_model  # noqa: E402
from gtsjax.sim import simulate  # noqa: E402
from tests._utils import offset_and_floor, without_offset_and_floor
from tests.reference.gp import sklearn_gp  # noqa: E402
from tests.reference.pipeline import ReferencePipeline, compare_tracks, scans_to_numpy  # noqa: E402
from tests.reference.track import wrap  # noqa: E402


@pytest.fixture(scope="module")
def spl():
    log, site = simulate("spl-trajectory", seed=7, n_scans=300)
    return log, load_model(demo_model_path()).with_site(site)


def test_sklearn_gps_predict_what_the_model_predicts(spl):
    """Each model GP carried into scikit-learn predicts the same mean and variance (the DTC form).
    Compared in float64 (the model's GP cast up), so that the check is of the construction, not of
    float32 rounding in the step."""
    log, model = spl
    rng = np.random.default_rng(0)
    reg = model.pose[model.class_index("robot")]
    for gp in (*model.classifier.gps, *reg.outputs()):
        d = gp.x_mean.shape[0]
        x = np.asarray(gp.x_mean, np.float64) + np.asarray(gp.x_scale, np.float64) * rng.normal(0, 0.7, (40, d))
        ref = sklearn_gp(gp)
        g64 = gp.astype(jnp.float64)
        mean, var = (np.asarray(a) for a in g64.predict(jnp.asarray(x), include_noise=True))
        scale = float(np.exp(np.asarray(gp.params.log_signal_var, np.float64))) ** 0.5
        np.testing.assert_allclose(ref.predict_mean(x), np.asarray(predict_mean(g64, jnp.asarray(x))),
                                   atol=1e-6 * scale)
        rm, rv = ref.predict(x)
        np.testing.assert_allclose(rm, mean, atol=1e-6 * scale)
        np.testing.assert_allclose(rv, var, rtol=1e-4, atol=1e-7 * scale**2)
    for g in reg.shared or ():  # a group of one kernel as one multi-output GPR (one kernel row per input)
        d = g.x_mean.shape[0]
        x = np.asarray(g.x_mean, np.float64) + np.asarray(g.x_scale, np.float64) * rng.normal(0, 0.7, (40, d))
        mean, var = (np.asarray(a).T for a in g.astype(jnp.float64).predict(jnp.asarray(x), include_noise=True))
        rm, rv = sklearn_gp(g).predict(x)
        scale = np.exp(np.asarray(g.log_signal_var, np.float64))[None, :] ** 0.5
        assert np.all(np.abs(rm - mean) <= 1e-6 * scale)
        np.testing.assert_allclose(rv, var, rtol=1e-4, atol=1e-7 * float(scale.max()) ** 2)


def test_reference_gives_the_same_tracks(spl):
    log, model = spl
    scans = to_scans(log, model.n_beams)
    _, out = process_log(model, scans)
    ref = ReferencePipeline(model).run(scans_to_numpy(scans))
    agree = compare_tracks(out, ref)
    assert agree["scans"] == log.n_scans
    assert agree["track_scans_gtsjax"] > 0.8 * log.n_scans  # the robot is tracked: the comparison is not empty
    assert agree["scans_same_ids"] == log.n_scans
    assert agree["track_ids_gtsjax"] == agree["track_ids_reference"]
    assert agree["track_scans_gtsjax"] == agree["track_scans_reference"] == agree["pairs_compared"]
    assert agree["max_pos_diff_m"] < 2e-3
    # Headings to rounding on all but a few rows: at 4.4 s of this log the robot's view splits into two
    # guessed candidates 2 cm apart, whose near-flat outline fits (stage e′) settle 0.2 rad apart in
    # float32 and float64 (sides' probabilities 0.85 against 0.62): one implementation's heading gate
    # takes the read and the other's does not, and the tracks part by 1.2°, together again 0.2° within
    # six scans. The share bounds such episodes; the maximum still catches a side taken wrongly.
    assert agree["share_heading_within_0.2deg"] >= 0.97, agree
    assert agree["max_heading_diff_deg"] < 2.0, agree
    assert agree["max_xy_correlation_diff"] < 0.02
    assert [bool(o.degraded) for o in ref] == [bool(d) for d in np.asarray(out.degraded)]
    # and the transforms agree too (both re-estimated every scan from the detected posts)
    a = np.stack([o.A for o in ref])
    # to the rounding of float32 against the reference's float64 (the least-squares fit on a handful of
    # posts amplifies it; the largest differences fall on sporadic scans): 3e-4 of A is under 2 mm at
    # the far posts, the tracks' own tolerance above.
    np.testing.assert_allclose(np.asarray(out.transform.A, np.float64), a, atol=3e-4)


def test_reference_tracks_several_robots(spl):
    """Three robots crossing: births, assignment and life cycle agree when tracks come close."""
    log, site = simulate("spl-crossing", seed=3, n_scans=220)
    model = spl[1].with_site(site)
    scans = to_scans(log, model.n_beams)
    _, out = process_log(model, scans)
    agree = compare_tracks(out, ReferencePipeline(model).run(scans_to_numpy(scans)))
    assert len(agree["track_ids_gtsjax"]) >= 3
    assert agree["scans_same_ids"] == log.n_scans
    assert agree["track_ids_gtsjax"] == agree["track_ids_reference"]
    assert agree["max_pos_diff_m"] < 2e-3


def test_reference_follows_the_model(spl):
    """The reference reads the model, not constants: a tracker that confirms later confirms later in both."""
    import equinox as eqx

    log, model = spl
    slow = eqx.tree_at(lambda m: m.tracker.n_confirm, model, jnp.asarray(6, jnp.int32))
    scans = to_scans(log.slice(0, 60), model.n_beams)
    _, out = process_log(slow, scans)
    ref = ReferencePipeline(slow).run(scans_to_numpy(scans))
    first_g = int(np.argmax(np.asarray(out.track_mask).any(axis=1)))
    first_r = next(i for i, o in enumerate(ref) if len(o.track_id))
    assert first_g == first_r >= 5


def test_reference_takes_the_pose_offset_off_the_rows_and_adds_the_variance_floor(spl):
    """A tracker with a class's mean error to take off (``pose_offset``: 2 cm ahead, 1 cm to the right,
    3° for the robot) and a variance floor to add (``var_floor``: (1 cm)² to each position variance,
    (2°)² to the heading's): the reference, which moves each confirmed track's pose back along its own
    axes and adds the floor to its filter's variances, reports the same rows; every row is the one
    without them moved back by the offset in the track's frame, with the floor added to its variances,
    and the tracking itself (ids, detections) is unchanged."""
    log, model = spl
    model = without_offset_and_floor(model)
    _, floor, params = offset_and_floor(model)
    shifted = eqx.tree_at(lambda m: m.tracker, model, params)
    scans = to_scans(log.slice(0, 80), model.n_beams)
    _, out = process_log(shifted, scans)
    _, plain = process_log(model, scans)
    agree = compare_tracks(out, ReferencePipeline(shifted).run(scans_to_numpy(scans)))
    assert agree["pairs_compared"] > 40 and agree["scans_same_ids"] == 80
    assert agree["max_pos_diff_m"] < 2e-3 and agree["max_heading_diff_deg"] < 2.0, agree
    # to rounding but for the episode at 4.4 s that ``test_reference_gives_the_same_tracks`` describes
    assert agree["share_heading_within_0.2deg"] >= 0.9 and agree["share_variance_within_5pc"] >= 0.9, agree
    for field in ("track_id", "track_mask", "det_mask"):
        np.testing.assert_array_equal(np.asarray(getattr(out, field)), np.asarray(getattr(plain, field)))
    np.testing.assert_array_equal(np.asarray(out.det_pose), np.asarray(plain.det_pose))
    rows = np.asarray(plain.track_mask)
    a, b = np.asarray(plain.track_pose, np.float64)[rows], np.asarray(out.track_pose, np.float64)[rows]
    assert len(a) > 40
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    d = b[:, :2] - a[:, :2]
    moved = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1)  # in the plain row's frame
    h = np.radians(3.0)
    want = -np.array([np.cos(h) * 0.02 + np.sin(h) * -0.01, -np.sin(h) * 0.02 + np.cos(h) * -0.01])
    np.testing.assert_allclose(moved, np.broadcast_to(want, moved.shape), atol=2e-6)
    np.testing.assert_allclose(wrap(b[:, 2] - a[:, 2]), -h, atol=2e-6)
    added = floor[np.asarray(plain.track_class)[rows]][:, [0, 0, 1]]
    assert np.all(added > 0)  # the robot's rows
    np.testing.assert_allclose(np.asarray(out.track_var)[rows], np.asarray(plain.track_var)[rows] + added, rtol=1e-6)


def test_reference_rejects_what_the_model_rejects(tiny):
    """With a model that has shape envelopes and open-set examples (the tiny one trained in the tests)
    and a person walking among the robots: per scan the same candidates are rejected (the counts of
    detections agree) and the same tracks come out."""
    log, site = simulate("spl-legs", seed=41, n_scans=200)
    model = tiny["model"].with_site(site)
    assert bool(np.any(np.asarray(model.envelope.whole))) and np.isfinite(np.asarray(model.classifier.support.threshold)).any()
    scans = to_scans(log, model.n_beams)
    _, out = process_log(model, scans)
    ref = ReferencePipeline(model).run(scans_to_numpy(scans))
    assert int(np.sum(out.unlike)) + int(np.sum(out.off_envelope)) > 0  # the rejections are exercised
    tracked = np.asarray(model.tracker.tracked)
    n_det = (np.asarray(out.det_mask) & tracked[np.asarray(out.det_class)]).sum(axis=1)
    np.testing.assert_array_equal(n_det, [o.n_detections for o in ref])
    agree = compare_tracks(out, ref)
    assert agree["track_scans_gtsjax"] > 0
    assert agree["scans_same_ids"] == log.n_scans
    assert agree["track_ids_gtsjax"] == agree["track_ids_reference"]


def _as_float64(tree):
    """``tree`` with every float32 array cast to float64 (the model, a scan)."""
    return jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_array(a) and a.dtype == jnp.float32 else a, tree)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_reference_refines_what_the_model_refines(tiny, precision):
    """Stage e′ scan by scan with a model that has a learnt outline (the tiny one), three robots
    crossing: the same candidates refined, the same refined headings, covariances and side
    probabilities as the reference's, and every candidate's side hypotheses the same.

    In float64 (model and scans cast) the step is the reference's computation: every figure agrees to
    round-off. In float32, as it runs live, a candidate whose sides nearly tie can move a side's
    probability by a few thousandths (a four-way tie, 0.28/0.29/0.03/0.40: 4e-3), round-off of the
    fixed Gauss–Newton steps multiplied by the calibrated temperature (6 310 per m² of cost), and
    move that candidate's least likely side's heading by a few milliradians (3.4e-3, p = 0.03)."""
    log, site = simulate("spl-crossing", seed=3, n_scans=40)
    model = tiny["model"].with_site(site)
    assert model.outline is not None and bool(np.any(np.asarray(model.outline.has)))
    scans = to_scans(log, model.n_beams)
    arrays = scans_to_numpy(scans)
    reference = ReferencePipeline(model)
    exact = precision == "float64"
    if exact:
        model, scans = _as_float64(model), _as_float64(scans)
    tol_xy, tol_th, tol_fit, tol_var, tol_side, tol_p = (1e-9, 1e-9, 1e-9, 1e-9, 1e-9, 1e-9) if exact else \
        (2e-5, 5e-3, 5e-3, 2.5e-1, 5e-3, 5e-2)
    # float32 against float64: the tiny model's GP headings (atan2 of two GP means) differ by up to 3.7e-3 rad, a
    # fit started from them as far, a fit's heading variance by up to 20 % and side probabilities by up to 0.027
    # (float32 loses digits in the GP's and the fit's sums; to be looked into). The float64 run holds every
    # figure to 1e-9: that is the check of the method, this one of float32's cost.
    step = jax.jit(lambda scan: perceive(model, scan))
    refined = compared = ties = 0
    for t in range(log.n_scans):
        p = step(jax.tree.map(lambda a, t=t: a[t], scans))
        r = reference.perceive(*(a[t] for a in arrays[:5]))
        kept = np.asarray(p.kept)  # the reference's candidates are the kept ones, in beam order
        np.testing.assert_array_equal(np.asarray(p.cls)[kept], r.cls)
        np.testing.assert_array_equal(np.asarray(p.ok)[kept], r.ok)
        np.testing.assert_array_equal(np.asarray(p.guess)[kept], r.guess)
        done = np.asarray(p.refined)[kept]
        np.testing.assert_array_equal(done, r.sides.refined)
        np.testing.assert_array_equal(np.asarray(p.vague)[kept], r.vague)
        refined += int(done.sum())
        ok = r.ok
        pose = np.asarray(p.pose_s, np.float64)[kept]
        # The GP's positions, or where a fit left the side the GP read (and the class takes the fit's
        # position there), the fit's: float32's Gauss–Newton round-off, as its headings'.
        np.testing.assert_allclose(pose[ok & ~done, :2], r.pose_s[ok & ~done, :2], rtol=0, atol=tol_xy)
        np.testing.assert_allclose(pose[ok & done, :2], r.pose_s[ok & done, :2], rtol=0, atol=tol_xy if exact else 1e-3)
        # In float32, a candidate whose two likeliest sides the reference holds within a factor of three of
        # each other (a near-tie: the tracker's heading mixture takes no side on less) can land its fit on
        # either with float32's last bits, and a vague heading (a variance the tracker takes no heading
        # from) is ill-determined: their headings, variances and side probabilities are compared in float64 only.
        top = np.sort(r.sides.side_logp, axis=-1)[:, ::-1]
        firm = exact | (~(top[:, 1] > top[:, 0] - np.log(3.0)) & ~np.asarray(r.vague, bool))
        np.testing.assert_allclose(wrap(pose[ok & firm, 2] - r.pose_s[ok & firm, 2]), 0.0, atol=tol_th)
        fit = done & firm
        np.testing.assert_allclose(wrap(pose[fit, 2] - r.pose_s[fit, 2]), 0.0, atol=tol_fit)  # the fits' headings
        var = np.asarray(p.cov_s, np.float64)[kept][fit, 2, 2]
        np.testing.assert_allclose(var, r.cov_s[fit, 2, 2], rtol=tol_var)
        # Every side with a probability is one of ours (two sides of equal probability in either order).
        # In float32 a side the reference gives under 1e-3 (nothing in the tracker's heading mixture) may
        # sit on a flatter stretch of its fit's cost: 1.1e-2 rad at p = 4e-5 with one machine's tiny model.
        side = np.asarray(p.side_pose, np.float64)[kept]
        for i in np.flatnonzero(ok):
            for h in np.flatnonzero(np.isfinite(r.sides.side_logp[i])):
                tol = tol_side if exact or r.sides.side_logp[i, h] >= np.log(1e-3) else 4 * tol_side
                assert np.min(np.abs(wrap(side[i, :, 2] - r.sides.side_pose[i, h, 2]))) <= tol, (t, i, h)
        sure = ok & firm
        np.testing.assert_allclose(np.exp(np.asarray(p.side_logp, np.float64)[kept][sure]),
                                   np.exp(r.sides.side_logp[sure]), rtol=0, atol=tol_p)
        compared += int(sure.sum())
        ties += int((ok & ~firm).sum())
    assert refined >= log.n_scans  # the refinement is exercised: most robots in most scans
    assert compared >= 5 * ties  # near-ties are the exception


def test_sklearn_multi_output_gpr_predicts_a_shared_group():
    """A group of GPs of one kernel carried into one multi-output scikit-learn GPR (the reference's
    form for models trained with ``--pose-kernels 1`` or ``2``) predicts every output's mean and
    variance as ``SharedSparseGP`` does, inducing points covering the data or not."""
    from gtsjax import gp

    rng = np.random.default_rng(5)
    x = rng.normal(size=(60, 5))
    y = np.stack([np.sin(x[:, 0]), x[:, 1] * x[:, 2], np.cos(x[:, 3])], 1) + rng.normal(size=(60, 3)) * [0.05, 0.2, 0.01]
    gps = gp.fit_shared(x, y, key=jax.random.key(1), restarts=1, jitter=1e-2)
    xs = rng.normal(size=(25, 5)) * 1.2
    for m, mv in ((60, 12), (30, 10)):
        g = gp.SharedSparseGP.build(gps, m, mv)
        mean, var = (np.asarray(a).T for a in g.predict(jnp.asarray(xs), include_noise=True))
        rm, rv = sklearn_gp(g).predict(xs)
        scale = np.exp(np.asarray(g.log_signal_var))[None, :] ** 0.5
        assert np.all(np.abs(rm - mean) <= 1e-6 * scale)
        np.testing.assert_allclose(rv, var, rtol=1e-6)
