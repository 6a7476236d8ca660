"""``gtsjax train``'s progress (issue 39): training announces every GP fit it will make before any work,
the display counts them "fit k of N" up to the N announced, says which fit runs and about how long
the fits left take, and keeps a line per fit (off with ``--quiet``; no bar where stderr is no terminal).

One small training through the command line (a few dozen examples per class, no tracking check); the
fits expected are listed here by hand from the classes, and the sizes checked against the report's."""

import io
import json

from rich.console import Console

import gtsjax.cli.train as train_cli
from gtsjax.cli import main
from gtsjax.io import save_log, save_site
from gtsjax.sim import simulate
from gtsjax.train import STAGES, TrainConfig, planned_fits


class Recorder(train_cli.FitProgress):
    """The command's display, recording what it was told and what it showed."""

    seen: list = []

    def stage(self, name, fits):
        super().stage(name, fits)
        self.seen.append(("stage", name, [(f["gp"], f["n"], f["weight"]) for f in fits], self.total))

    def fitted(self, info):
        shown = self.bar.tasks[0].description  # what the bar said while this fit ran
        super().fitted(info)
        self.seen.append(("fit", info, self.done, self.total, shown))


def test_train_counts_its_fits_to_the_number_it_announced(tmp_path, monkeypatch, capsys):
    log, site = simulate("spl-train", seed=21, n_scans=200)
    save_log(log, tmp_path / "a.npz")
    save_site(site, tmp_path / "site.json")
    Recorder.seen = []
    monkeypatch.setattr(train_cli, "FitProgress", Recorder)
    code = main(["train", str(tmp_path / "a.npz"), "--site", str(tmp_path / "site.json"), "--out", str(tmp_path / "m.npz"),
                 "--report", str(tmp_path / "r.json"), "--max-per-class", "30", "--max-pose", "40", "--max-landmark", "40",
                 "--inducing", "16", "--inducing-class", "16", "--restarts", "1", "--pose-kernels", "2", "--no-check"])
    err = capsys.readouterr().err
    assert code == 0, err
    rep = json.loads((tmp_path / "r.json").read_text())
    expected = (["post.x", "post.y"] + [f"class.{c}" for c in rep["classes"]]
                + [f"robot.{c}" for c in ("x", "y", "sin", "cos")])
    assert [f["gp"] for f in rep["fits"]] == expected

    stages = [e for e in Recorder.seen if e[0] == "stage"]
    fits = [e for e in Recorder.seen if e[0] == "fit"]
    announced = stages[0][2]
    assert stages[0][1] == "labelling" and [g for g, _, _ in announced] == expected  # before any work: all of them
    assert [s[1] for s in stages] == [s for s in STAGES if s != "tracking check"]  # in order (--no-check)
    n = len(expected)
    assert [(k, total) for _, _, k, total, _ in fits] == [(k, n) for k in range(1, n + 1)]
    assert [info["gp"] for _, info, *_ in fits] == expected
    for _, info, k, total, shown in fits:
        assert shown.startswith(f"fit {k} of {total}: {info['gp']} ({info['n']} examples")
    # Each stage names exactly the fits not yet made, and the sizes those will have (the report's).
    done = 0
    for e in Recorder.seen:
        if e[0] == "fit":
            done += 1
        else:
            assert [g for g, _, _ in e[2]] == expected[done:]
            if e[1] in ("classifier", "pose regressors"):
                assert [m for _, m, _ in e[2]] == [f["n"] for f in rep["fits"][done:]]
    # One kernel for x, y and one for sin, cos: the second output of each pair carries no weight.
    assert [w > 0 for g, _, w in announced if g.startswith("robot.")] == [True, False, True, False]

    lines = [ln for ln in err.splitlines() if "fitted GP" in ln]
    assert [ln.split()[2] for ln in lines] == expected
    assert all(f"(fit {k} of {n}" in ln for k, ln in enumerate(lines, 1))
    assert "━" not in err  # no bar: stderr is no terminal here


def test_the_bar_shows_the_fit_and_the_time_left_and_quiet_shows_nothing():
    """The display fed a run's callbacks by hand: on a terminal the bar names the running fit and
    estimates the fitting left as the seconds per unit of weight of the fits done times the weight
    left; ``bar=False, lines=False`` (``--quiet``) prints nothing."""
    plan = [{"gp": g, "stage": "classifier", "n": 100, "n_fit": 100, "weight": w}
            for g, w in (("class.background", 1.0), ("class.robot", 3.0), ("class.post", 2.0))]
    out = io.StringIO()
    shown = train_cli.FitProgress(Console(file=out, force_terminal=True, width=160), bar=True, lines=True)
    quiet_out = io.StringIO()
    quiet = train_cli.FitProgress(Console(file=quiet_out, force_terminal=True, width=160), bar=False, lines=False)
    with shown, quiet:
        for d in (shown, quiet):
            d.stage("classifier", plan)
            d.fitted({"gp": "class.background", "n": 100, "lml": 1.0, "seconds": 10.0})
        assert shown.seconds_left(after_fit=True) == 10.0 / 1.0 * (3.0 + 2.0)
        table = io.StringIO()
        Console(file=table, width=160).print(shown.bar.make_tasks_table(shown.bar.tasks))
        text = table.getvalue()
        assert "fit 2 of 3: class.robot (100 examples)" in text and "about 0:5" in text
    assert "fitted GP class.background" in out.getvalue() and "(fit 1 of 3; about 0:50 of fitting left)" in out.getvalue()
    assert quiet_out.getvalue() == ""


def test_planned_fits_follow_the_pose_kernels_and_caps():
    """Without training: one entry per GP output whatever the kernel layout, sizes at their caps or at
    the examples available, whichever is fewer."""
    classes, landmarks, mobiles = ("background", "post", "robot"), ("post",), ("robot",)
    for kernels in (1, 2, 4):
        cfg = TrainConfig(pose_kernels=kernels, max_per_class=50, max_pose_examples=300, max_pose_fit=100)
        plan = planned_fits(classes, landmarks, mobiles, cfg, available={"background": 20, "robot": 1000})
        assert [f["gp"] for f in plan] == ["post.x", "post.y", "class.background", "class.post", "class.robot",
                                           "robot.x", "robot.y", "robot.sin", "robot.cos"]
        assert [f["n"] for f in plan if f["gp"].startswith("class.")] == [20 + 50 + 50] * 3
        assert {(f["n"], f["n_fit"]) for f in plan if f["gp"].startswith("robot.")} == {(300, 100)}
        assert sum(f["weight"] > 0 for f in plan if f["gp"].startswith("robot.")) == {1: 1, 2: 2, 4: 4}[kernels]
    with_bg = planned_fits(classes, landmarks, mobiles, TrainConfig(max_per_class=50), background_logs=True)
    assert with_bg[2]["n"] == 12 * 50 + 50 + 4 * 50  # the classifier's caps with background logs


def test_the_time_left_counts_compilation_apart_and_holds_within_twice_the_truth():
    """The estimate fed the fits of a training as a slow machine makes them (synthetic seconds, no
    clock): each fit costs its rows' work at one rate plus, at the first fit of each size, a
    compilation worth many small fits. From the first fit on, the fitting left is estimated within 2×
    of what it then takes."""
    from gtsjax.train import fit_cost, fit_work

    cfg = TrainConfig(max_per_class=600, max_pose_examples=3000, max_pose_fit=1000, max_landmark_examples=300)
    plan = planned_fits(("background", "post", "robot"), ("post",), ("robot",), cfg)
    rate, compile_s = 4e-8, 12.0  # seconds per unit of work; seconds to compile a new size

    def cost(f, seen):
        new = (f["stage"], f["n"], f["n_fit"]) not in seen
        seen.add((f["stage"], f["n"], f["n_fit"]))
        return rate * f["work"] + (compile_s if new else 0.0), (compile_s if new else 0.0)

    seen: set = set()
    truth = [cost(f, seen) if f["weight"] > 0 else (0.0, 0.0) for f in plan]
    assert len({(f["stage"], f["n"]) for f in plan}) >= 3  # sizes enough for compilation to matter
    shown = train_cli.FitProgress(Console(file=io.StringIO(), width=160), bar=False, lines=True)
    shown.stage("labelling", plan)
    for k, (f, (seconds, compiling)) in enumerate(zip(plan, truth, strict=True)):
        shown.fitted({"gp": f["gp"], "n": f["n"], "lml": 0.0, "seconds": seconds, "compile_seconds": compiling})
        left = sum(s for s, _ in truth[k + 1:])
        if left > 0:
            est = shown.seconds_left(after_fit=True)
            assert left / 2 <= est <= 2 * left, (k, f["gp"], est, left)
    assert fit_work(100, 100, 1) < fit_cost(100, 100, 1)


def test_each_stage_ends_in_a_line_and_the_tracking_check_is_announced():
    """With lines on, every stage says when it ends and how long it took, and the tracking check,
    minutes of a large training with no fit to show, says what it runs when it begins."""
    out = io.StringIO()
    shown = train_cli.FitProgress(Console(file=out, width=160), bar=False, lines=True)
    plan = [{"gp": "class.robot", "stage": "classifier", "n": 100, "n_fit": 100, "weight": 1.0, "work": 0.5}]
    for name in STAGES:
        shown.stage(name, plan if name in ("labelling", "classifier") else [])
        if name == "classifier":
            shown.fitted({"gp": "class.robot", "n": 100, "lml": 1.0, "seconds": 2.0, "compile_seconds": 1.0})
    shown.finish()
    shown.finish()  # once
    lines = out.getvalue().splitlines()
    assert [ln.split(":")[0].strip() for ln in lines if "done in" in ln] == list(STAGES)
    assert any(ln.strip().startswith("tracking check: the trained step") for ln in lines)
