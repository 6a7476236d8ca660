"""Bad file arguments, every command: one line, exit 2, nothing changed, nothing left (issue 39).

The cases come from :mod:`tests._badfiles`, a seeded generator of damaged logs, sites, models, bags,
journals, CSVs and paths; each runs the command line in-process, as a user would, and must end in
exit status 2 (0 where the case says why its input is acceptable) with no traceback, one ``gtsjax:``
line on stderr that names the file or option, every input byte for byte as it was and no output
left behind (no new file or folder, no ``.part``)."""

import os

import pytest

from gtsjax.cli import main


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
