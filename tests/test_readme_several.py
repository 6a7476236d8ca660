"""The several-laser block (docs/several-lasers.md, "Several lasers on one field"; in the README until
issue 40) runs as written, in order, from an empty folder (issue 39): its commands are read from that
page itself, so that a change that breaks them fails here.

Each ``gtsjax`` line of the block's fenced code runs in-process (``gtsjax.cli.main``) in a fresh
folder, with smaller settings swapped in where the page's would take minutes (seconds simulated and
evaluated, training caps; ``tests._docs.SMALLER``), and must exit 0 and leave its outputs, holding scans or
rows. ``emulate`` and ``run`` are skipped: they serve and read live lasers until stopped
(``tests/test_several.py`` and ``tests/test_cli_commands.py`` run them). Then docs/grading.md's first
block runs in the same folder, on the model this one trained, as that page says it runs."""

import json
import shlex
from pathlib import Path

from gtsjax.cli import main
from tests._docs import LIVE, blocks, check_outputs, commands, option, smaller

PAGE = Path(__file__).resolve().parents[1] / "docs" / "several-lasers.md"
HEADING = "Several lasers on one field"
# docs/grading.md's first block grades the robots of a match with the model the block above trains, in
# the same folder (as the page says).
GRADING = Path(__file__).resolve().parents[1] / "docs" / "grading.md"
GRADING_HEADING = "Grading a robot's own localisation"


def block_commands(page: Path, heading: str) -> list[list[str]]:
    """The ``gtsjax`` command lines of the first fenced block under the section ``heading`` of ``page``,
    each as its arguments without ``gtsjax``, as bash splits them (``tests._docs.commands``)."""
    block = next((b for b in blocks(page) if b.heading == heading), None)
    assert block, f"no fenced block under {heading!r} in {page.name}"
    return commands(block)


def test_the_block_is_the_pipeline():
    """The block simulates, trains, evaluates and replays (so that the run below tests something)."""
    names = [c[0] for c in block_commands(PAGE, HEADING)]
    assert {"simulate", "plot", "train", "evaluate", "replay"} <= set(names)
    assert names.index("simulate") < names.index("plot") and names.index("train") < names.index("replay")


def test_the_readme_several_laser_block_runs_in_order(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ran = []
    for args in block_commands(PAGE, HEADING):
        if args[0] in LIVE:
            continue
        args = smaller(args)
        assert main(args) == 0, f"gtsjax {shlex.join(args)} failed"
        check_outputs(args, tmp_path)
        ran.append(args[0])
        if args[0] == "simulate":  # a match: one log per laser, OUT-NAME.npz
            assert len(list(tmp_path.glob(f"{Path(option(args, '--out')).stem}-*.npz"))) >= 2
    assert ran.count("simulate") >= 1 and "replay" in ran

    # docs/grading.md's first block, in the same folder: a match with each robot's beliefs, its ground
    # truth by the model above, and every robot graded (robot1 in the mirrored frame, as the page says).
    graded = []
    for args in block_commands(GRADING, GRADING_HEADING):
        args = smaller(args)
        assert main(args) == 0, f"gtsjax {shlex.join(args)} failed"
        check_outputs(args, tmp_path)
        graded.append(args[0])
        if args[0] == "simulate":
            beliefs = Path(option(args, "--out-beliefs"))
            assert len(list(beliefs.glob("robot*.csv"))) == 10 and (beliefs / "put-in.json").is_file()
        elif args[0] == "grade":
            gtd = Path(args[1])
            report = json.loads((gtd.with_name(gtd.stem + "-grade") / "grade.json").read_text())
            robots = {r["robot"]: r for r in report["robots"]}
            assert sorted(robots) == sorted(f"robot{i}" for i in range(1, 11))
            assert robots["robot1"]["unseen_share"] < 0.5, robots["robot1"]  # its frame given: seen
    assert graded == ["simulate", "replay", "grade"]
