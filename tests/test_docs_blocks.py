"""Every fenced block of README.md and docs/ runs in CI as written, or says why it cannot (issue 54, item
4): a synopsis whose file names stand for the user's own, a transcript, a line of output, a command that
needs a laser on a serial port. How each is checked is written on the page, on the line before its
fence (``tests/_docs.py``); a block that says nothing fails here, so that a new block is not left
unrun by default.

The blocks marked for this module run here, each from an empty folder, every ``gtsjax`` line in order
but the live ones, with the smaller settings of ``tests._docs.SMALLER`` (the pages' own caps take
minutes each): every line must exit 0 and leave its outputs."""

import pytest

from tests._docs import LIVE, PAGES, ROOT, blocks, commands, run_commands

HERE = "tests/test_docs_blocks.py"
ALL = [b for page in PAGES for b in blocks(page)]
RUN_HERE = [b for b in ALL if b.mark and b.mark[0] == "run in CI" and b.mark[1].split()[0] == HERE]

# A block run here that trains takes a minute or more on two cores, even with the smaller settings.
pytestmark = pytest.mark.timeout(900)


def test_every_block_says_how_ci_checks_it():
    unmarked = [f"{b.where} (under {b.heading!r})" for b in ALL if b.mark is None]
    assert not unmarked, ("blocks that say neither '<!-- run in CI: FILE -->' nor '<!-- not run in CI: WHY -->' "
                          f"on the line before their fence: {unmarked}")
    for b in ALL:
        kind, what = b.mark
        if kind == "not run in CI":
            assert len(what.split()) >= 4, f"{b.where}: say why it is not run ({what!r})"
            continue
        target = what.split()[0]
        assert (ROOT / target).is_file(), f"{b.where}: {target} does not exist"
        if target == ".ci/run":  # CI runs the README's test command itself, exactly
            assert b.text.strip() in (ROOT / target).read_text(), f"{b.where}: .ci/run does not run {b.text!r}"
        elif target != HERE:  # the test that runs it names the page, so that a change to one finds the other
            assert b.page.name in (ROOT / target).read_text(), f"{b.where}: {target} does not name {b.page.name}"


def test_the_blocks_run_here_are_commands():
    assert len(RUN_HERE) >= 6
    for b in RUN_HERE:
        names = [args[0] for args in commands(b)]
        assert names and set(names) - set(LIVE), b.where


@pytest.mark.parametrize("block", RUN_HERE, ids=lambda b: b.where.replace("docs/", ""))
def test_the_block_runs_as_written(block, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ran = run_commands(block, tmp_path)
    assert ran, f"{block.where}: nothing run"
