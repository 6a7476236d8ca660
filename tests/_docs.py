"""The fenced blocks of README.md and docs/*.md, and running their ``gtsjax`` lines as written (issue 54,
item 4).

Every block says how CI checks it, in an HTML comment on the line before its fence (invisible where
the page is rendered):

- ``<!-- run in CI: tests/test_docs_blocks.py -->``: that module runs the block, in order, from an
  empty folder (:func:`run_commands`), with the smaller settings of :data:`SMALLER` swapped in;
- ``<!-- run in CI: FILE -->``: another test module (or ``.ci/run``) runs it, and names the page;
- ``<!-- not run in CI: WHY -->``: a synopsis with placeholders, a transcript, a line of output, or
  a command that needs a laser on a serial port (each with what runs its like instead).

``tests/test_docs_blocks.py`` fails on a block with neither."""

import dataclasses
import json
import re
import shlex
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MARK = re.compile(r"^<!--\s*(run in CI|not run in CI):\s*(.+?)\s*-->$")
FENCE = re.compile(r"^(`{3,})(.*)$")

# ``emulate`` and ``run`` serve or read lasers until stopped: a block's such lines are not run here
# (``tests/test_several.py``, ``tests/test_cli_commands.py`` and ``tests/test_enrol.py`` run them on the
# emulator over pseudo-terminals).
LIVE = ("emulate", "run")

# Per command: options whose value is replaced (and added where the line has none), so that a block
# that trains runs in about a minute on two cores; nothing else of a line is changed. The pages name
# their own, larger caps and the minutes those take.
SMALLER = {
    "simulate": {"--seconds": "6"},
    "evaluate": {"--seconds": "3"},
    "train": {"--max-per-class": "40", "--max-pose": "120", "--max-pose-fit": "60", "--max-landmark": "60",
              "--inducing": "32", "--inducing-class": "32", "--restarts": "1", "--no-check": None},
}


@dataclasses.dataclass(frozen=True)
class Block:
    page: Path
    line: int  # of the opening fence, 1-based
    heading: str  # the section it is in
    text: str
    mark: "tuple[str, str] | None"  # ("run in CI" | "not run in CI", what follows)

    @property
    def where(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks(page: Path) -> list[Block]:
    """The fenced blocks of ``page``, each with the heading it sits under and its mark."""
    out, heading, fence, start, body, before = [], "", None, 0, [], ""
    for n, line in enumerate(page.read_text().splitlines(), 1):
        if fence is None:
            m = FENCE.match(line)
            if m:
                fence, start, body = m.group(1), n, []
                mark = MARK.match(before.strip())
                opening_mark = (mark.group(1), mark.group(2)) if mark else None
            else:
                if line.startswith("#"):
                    heading = line.lstrip("#").strip()
                if line.strip():
                    before = line
        elif line.strip() == fence:
            out.append(Block(page, start, heading, "\n".join(body) + "\n", opening_mark))
            fence, before = None, ""
        else:
            body.append(line)
    return out


def commands(block: Block) -> list[list[str]]:
    """The block's command lines as bash splits them (a trailing ``\\`` joins the next line; a line's
    ``# comment`` dropped; ``$(...)`` expanded), each without its leading ``gtsjax``."""
    joined = re.sub(r"\\\n", " ", block.text)
    out = []
    for line in joined.splitlines():
        if not shlex.split(line, comments=True):
            continue
        words = subprocess.run(["bash", "-c", "printf '%s\\0' " + line], capture_output=True, text=True, check=True)
        args = words.stdout.split("\0")[:-1]
        assert args[0] == "gtsjax", f"{block.where}: not a gtsjax command: {line!r}"
        out.append(args[1:])
    return out


def smaller(args: list[str]) -> list[str]:
    """``args`` with :data:`SMALLER`'s settings for its command."""
    out = list(args)
    for opt, value in SMALLER.get(args[0], {}).items():
        if value is None:
            if opt not in out:
                out.append(opt)
        elif opt in out:
            out[out.index(opt) + 1] = value
        else:
            out += [opt, value]
    return out


def option(args: list[str], name: str, default: str | None = None) -> str | None:
    return args[args.index(name) + 1] if name in args else default


def check_outputs(args: list[str], folder: Path) -> None:
    """What a block's command ``args`` (run in ``folder``) must have left there: scans, a model, rows,
    a results file, a grade. A command the function does not know fails the test (teach it)."""
    from gtsjax.io import load_log
    from gtsjax.io.gtd import read_gtd
    from gtsjax.io.modelfile import load_model

    cmd = args[0]
    if cmd == "simulate":  # one log, or a match's log per laser (OUT-NAME.npz), and the site
        out = folder / option(args, "--out")
        logs = [out] if out.is_file() else sorted(folder.glob(f"{out.stem}-*.npz"))
        assert logs and all(load_log(p).n_scans > 0 for p in logs), f"gtsjax {shlex.join(args)}: no scans"
        assert (folder / option(args, "--site")).is_file()
    elif cmd == "plot":
        assert any(p.suffix == ".png" and p.stat().st_size > 0 for p in folder.iterdir())
    elif cmd == "train":
        assert load_model(folder / option(args, "--out")).classes
    elif cmd == "evaluate":
        res = json.loads((folder / option(args, "--out-dir", "eval-out") / "results.json").read_text())
        assert res, f"gtsjax {shlex.join(args)}: an empty results.json"
    elif cmd == "replay":
        assert len(read_gtd(folder / option(args, "--out"))) > 0, f"gtsjax {shlex.join(args)}: no rows"
    elif cmd == "grade":
        gtd = folder / args[1]
        assert json.loads((gtd.with_name(gtd.stem + "-grade") / "grade.json").read_text())["robots"]
    else:
        raise AssertionError(f"gtsjax {cmd}: tests/_docs.py does not know what it should write; teach it")


def run_commands(block: Block, folder: Path) -> list[list[str]]:
    """Each of the block's ``gtsjax`` lines but the live ones (:data:`LIVE`), in order, in-process, in
    ``folder`` (the caller's working directory), with :data:`SMALLER`'s settings: each must exit 0 and
    leave its outputs (:func:`check_outputs`). Returns the argument lists run."""
    from gtsjax.cli import main

    ran = []
    for args in commands(block):
        if args[0] in LIVE:
            continue
        args = smaller(args)
        assert main(args) == 0, f"{block.where}: gtsjax {shlex.join(args)} failed"
        check_outputs(args, folder)
        ran.append(args)
    return ran
