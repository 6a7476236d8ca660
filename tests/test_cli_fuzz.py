"""Bad file arguments, every command: one line, exit 2, nothing changed, nothing left (issue 39).

The cases come from :mod:`tests._badfiles`, a seeded generator of damaged logs, sites, models, bags,
journals, CSVs and paths; each runs the command line in-process, as a user would, and must end in
exit status 2 (0 where the case says why its input is acceptable) with no traceback, one ``gtsjax:``
line on stderr that names the file or option, every input byte for byte as it was and no output
left behind (no new file or folder, no ``.part``)."""

import hashlib
import os
import stat
from pathlib import Path

import pytest

from gtsjax.cli import main
from tests._badfiles import cases, write_inputs

CASES = cases()
NAMES = sorted(CASES)


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    """The good inputs in ``inputs/`` and every case's bad file in ``cases/<index>/``, made once."""
    root = tmp_path_factory.mktemp("badfiles")
    (root / "inputs").mkdir()
    write_inputs(root / "inputs")
    for i, name in enumerate(NAMES):
        folder = root / "cases" / str(i)
        folder.mkdir(parents=True)
        case = CASES[name]
        if case.make is not None:
            case.make(root / "inputs", folder / case.file)
    return root


def _digest(folder: Path) -> dict:
    """Every path under ``folder``: a file's SHA-256, else what it is (folder, socket, ...)."""
    out = {}
    for p in sorted(folder.rglob("*")):
        mode = p.lstat().st_mode
        if stat.S_ISREG(mode):
            try:
                out[p] = hashlib.sha256(p.read_bytes()).hexdigest()
            except PermissionError:  # an unreadable case's file, as a user other than root sees it
                out[p] = f"unreadable {p.stat().st_size}"
        else:
            out[p] = stat.S_IFMT(mode)
    return out


@pytest.mark.parametrize("name", NAMES)
def test_a_bad_file_argument_is_one_line(built, tmp_path, capsys, request, name):
    case = CASES[name]
    if not case.root and os.geteuid() == 0:
        pytest.skip("root reads and writes files whatever their mode")
    if case.xfail:
        request.applymarker(pytest.mark.xfail(reason=case.xfail, strict=True))
    d, f = built / "inputs", built / "cases" / str(NAMES.index(name)) / case.file
    fill = lambda s: s.format(d=d, f=f, o=tmp_path)  # noqa: E731
    before = _digest(d) | _digest(f.parent)
    capsys.readouterr()
    code = main([fill(a) for a in case.args])
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err, err
    assert code == case.code, f"exit {code}, expected {case.code} ({case.why}): {err}"
    assert _digest(d) | _digest(f.parent) == before  # every input as it was, nothing added beside them
    assert not [p for p in tmp_path.rglob("*.part")]
    if case.code == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("gtsjax: ") and fill(case.names) in lines[0], lines
        assert list(tmp_path.iterdir()) == []  # nothing written


def test_a_missing_serial_port_is_one_line_before_the_model_is_read(tmp_path, capsys):
    """``run --port /dev/nonexistent`` fails at once: the model given is not even a model file, and the
    line names the port, so nothing was loaded or compiled before the port was checked."""
    (tmp_path / "not-a-model.npz").write_bytes(b"not a zip archive")
    site = tmp_path / "site.json"
    site.write_text('{"landmarks": [{"class": "post", "x": 0, "y": 0}, {"class": "post", "x": 1, "y": 0}, '
                    '{"class": "post", "x": 0, "y": 1}], "sensor_pose": [0.5, 0.5, 0]}')
    before = sorted(tmp_path.iterdir())
    capsys.readouterr()
    for port, fragment in (("/dev/nonexistent", "/dev/nonexistent: no such serial port"),
                           ("nosuch://x", "--port: nosuch://x: invalid URL")):
        code = main(["run", "--port", port, "--site", str(site), "--model", str(tmp_path / "not-a-model.npz"),
                     "--out", str(tmp_path / "gtd.csv")])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and err[0].startswith(f"gtsjax: {fragment}"), err
    assert sorted(tmp_path.iterdir()) == before


def test_the_early_port_check_lets_urls_and_ptys_through():
    """pyserial's URLs (checked without connecting) and a pseudo-terminal pass the early check: whether
    they answer is the link's business."""
    from gtsjax.cli._live import check_ports

    leader, follower = os.openpty()
    try:
        check_ports(["socket://127.0.0.1:9", "loop://", "rfc2217://localhost:1", os.ttyname(follower), "/dev/null"])
    finally:
        os.close(leader)
        os.close(follower)
