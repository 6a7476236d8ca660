"""The several-laser block (docs/several-lasers.md, "Several lasers on one field"; in the README until
issue 40) runs as written, in order, from an empty folder (issue 39): its commands are read from that
page itself, so that a change that breaks them fails here.

Each ``gtsjax`` line of the block's fenced code runs in-process (``gtsjax.cli.main``) in a fresh
folder, with smaller settings swapped in where the page's would take minutes (seconds simulated and
evaluated, training caps; :data:`SMALLER`), and must exit 0 and leave its outputs, holding scans or
rows. ``emulate`` and ``run`` are skipped: they serve and read live lasers until stopped
(``tests/test_several.py`` and ``tests/test_cli_commands.py`` run them). Then docs/grading.md's first
block runs in the same folder, on the model this one trained, as that page says it runs."""

import json
import re
import shlex
import subprocess
from pathlib import Path

import pytest

from gtsjax.cli import main
from gtsjax.io import load_log
from gtsjax.io.gtd import read_gtd
from gtsjax.io.modelfile import load_model

PAGE = Path(__file__).resolve().parents[1] / "docs" / "several-lasers.md"
HEADING = "# Several lasers on one field"
# docs/grading.md's first block grades the robots of a match with the model the block above trains, in
# the same folder (as the page says).
GRADING = Path(__file__).resolve().parents[1] / "docs" / "grading.md"
GRADING_HEADING = "# Grading a robot's own localisation"
LIVE = ("emulate", "run")  # serve or read lasers until stopped: not run here

# Per command: options whose value is replaced (and added where the line has none) to keep the test to
# about a minute on two cores; nothing else of a line is changed.
SMALLER = {
    "simulate": {"--seconds": "6"},  # grading.md's simulate too (its page runs a minute)
    "evaluate": {"--seconds": "3"},
    "train": {"--max-per-class": "40", "--max-pose": "120", "--max-pose-fit": "60", "--max-landmark": "60",
              "--inducing": "32", "--inducing-class": "32", "--restarts": "1", "--no-check": None},
}


def block_commands(text: str, heading: str = HEADING) -> list[list[str]]:
    """The ``gtsjax`` command lines of the first fenced block under the section's heading, each as its
    arguments without ``gtsjax`` (a trailing ``# comment`` dropped), as bash splits them: a line's
    ``$(...)`` is expanded (``grading.md`` lists its robots with a loop)."""
    start = text.index(heading)
    end = text.find("\n## ", start + 1)
    section = text[start : end if end > 0 else len(text)]
    match = re.search(r"^```[^\n]*\n(.*?)^```", section, re.S | re.M)
    assert match, f"no fenced block under {heading!r}"
    commands = []
    for line in match.group(1).splitlines():
        if not shlex.split(line, comments=True):
            continue
        words = subprocess.run(["bash", "-c", "printf '%s\\0' " + line], capture_output=True, text=True, check=True)
        args = words.stdout.split("\0")[:-1]
        assert args[0] == "gtsjax", f"not a gtsjax command: {line!r}"
        commands.append(args[1:])
    return commands


def smaller(args: list[str]) -> list[str]:
    """``args`` with :data:`SMALLER`'s settings for its command."""
    out = list(args)
    for option, value in SMALLER.get(args[0], {}).items():
        if value is None:
            if option not in out:
                out.append(option)
        elif option in out:
            out[out.index(option) + 1] = value
        else:
            out += [option, value]
    return out


def option(args: list[str], name: str, default: str | None = None) -> str | None:
    return args[args.index(name) + 1] if name in args else default


def test_the_block_is_the_pipeline():
    """The block simulates, trains, evaluates and replays (so that the run below tests something)."""
    names = [c[0] for c in block_commands(PAGE.read_text())]
    assert {"simulate", "plot", "train", "evaluate", "replay"} <= set(names)
    assert names.index("simulate") < names.index("plot") and names.index("train") < names.index("replay")


def test_the_readme_several_laser_block_runs_in_order(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ran = []
    for args in block_commands(PAGE.read_text()):
        if args[0] in LIVE:
            continue
        args = smaller(args)
        before = set(tmp_path.iterdir())
        assert main(args) == 0, f"gtsjax {shlex.join(args)} failed"
        ran.append(args[0])
        new = set(tmp_path.iterdir()) - before
        if args[0] == "simulate":  # a match: one log per laser, OUT-NAME.npz, and its site
            out = Path(option(args, "--out"))
            logs = sorted(tmp_path.glob(f"{out.stem}-*.npz"))
            assert len(logs) >= 2 and all(load_log(p).n_scans > 0 for p in logs), logs
            assert Path(option(args, "--site")).is_file()
        elif args[0] == "plot":
            assert any(p.suffix == ".png" and p.stat().st_size > 0 for p in new), new
        elif args[0] == "train":
            assert load_model(Path(option(args, "--out"))).classes
        elif args[0] == "evaluate":
            assert (Path(option(args, "--out-dir", "eval-out")) / "results.json").stat().st_size > 0
        elif args[0] == "replay":
            assert len(read_gtd(Path(option(args, "--out")))) > 0
        else:
            pytest.fail(f"gtsjax {args[0]}: the test does not know what it should write; teach it")
    assert ran.count("simulate") >= 1 and "replay" in ran

    # docs/grading.md's first block, in the same folder: a match with each robot's beliefs, its ground
    # truth by the model above, and every robot graded (robot1 in the mirrored frame, as the page says).
    graded = []
    for args in block_commands(GRADING.read_text(), GRADING_HEADING):
        args = smaller(args)
        assert main(args) == 0, f"gtsjax {shlex.join(args)} failed"
        graded.append(args[0])
        if args[0] == "simulate":
            beliefs = Path(option(args, "--out-beliefs"))
            assert len(list(beliefs.glob("robot*.csv"))) == 10 and (beliefs / "put-in.json").is_file()
        elif args[0] == "replay":
            assert len(read_gtd(Path(option(args, "--out")))) > 0
        elif args[0] == "grade":
            gtd = Path(args[1])
            report = json.loads((gtd.with_name(gtd.stem + "-grade") / "grade.json").read_text())
            robots = {r["robot"]: r for r in report["robots"]}
            assert sorted(robots) == sorted(f"robot{i}" for i in range(1, 11))
            assert robots["robot1"]["unseen_share"] < 0.5, robots["robot1"]  # its frame given: seen
        else:
            pytest.fail(f"gtsjax {args[0]}: the test does not know what it should write; teach it")
    assert graded == ["simulate", "replay", "grade"]
