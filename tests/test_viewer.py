"""The Rerun view (issue 19): a demo run's ``.rrd`` reopened with Rerun's own reader, and the web viewer
served by ``gtsjax replay --view web`` drawn by headless Chromium (Debian's, driven by Playwright).
Skipped without the viewer extra or Chromium on a developer's machine; in CI (``CI=true``) they must
run."""

import os
import queue
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from gtsjax.io.gtd import read_gtd
from gtsjax.viewer import LASER_COLOUR, SEEN_COLOUR

from ._utils import CHILD, cli_env
from .conftest import in_ci

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _need(what: bool, why: str) -> None:
    if not what:
        if in_ci():
            pytest.fail(f"{why} (CI=true: the viewer's tests must run)", pytrace=False)
        pytest.skip(why)


def _rerun():
    try:
        import rerun
    except ImportError:
        rerun = None
    _need(rerun is not None, 'the viewer extra is not installed (pip install "gtsjax[viewer]")')
    return rerun


def test_a_demo_runs_rrd_reopens_with_one_track_per_robot(tmp_path):
    """``gtsjax demo --view-save``: Rerun's reader finds the field, the scan, the laser and one track
    entity per track of the GTD CSV (the demo's one robot: one), each with a pose per row of that
    track, and the time series."""
    _rerun()
    from rerun.chunk import RrdReader

    from gtsjax.cli import main

    rrd = tmp_path / "demo.rrd"
    assert main(["demo", "--seconds", "5", "--out-dir", str(tmp_path / "out"), "--quiet", "--view-save",
                 str(rrd)]) == 0
    rows = read_gtd(tmp_path / "out" / "gtd.csv")
    per_entity: dict[str, int] = {}
    for chunk in RrdReader(rrd).stream():
        per_entity[str(chunk.entity_path)] = per_entity.get(str(chunk.entity_path), 0) + chunk.num_rows
    ids = sorted({r.track_id for r in rows})
    assert len(ids) == 1  # one robot, one track
    tracks = sorted({e.split("/")[3] for e in per_entity if e.startswith("/field/tracks/")})
    assert tracks == [f"robot_{i}" for i in ids]
    for i in ids:
        assert per_entity[f"/field/tracks/robot_{i}/pose"] == sum(r.track_id == i for r in rows)
    for e in ("/field", "/field/scan", "/field/laser", "/field/landmarks", "/stats/latency_ms", "/stats/tracks"):
        assert per_entity.get(e, 0) > 0, e  # "/field": the transform that draws the field y up


def _free_ports(n: int = 2) -> list[int]:
    """``n`` distinct ports free now: the sockets are held together, so the system cannot hand the same
    port out twice (two ports taken one after the other could be one port, released and given again:
    the web viewer then refused to serve on its own gRPC port, in a run with three workers)."""
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def _listening() -> dict[int, str]:
    """The IPv4 TCP ports listening on this machine and the address each is bound to, from the
    kernel's table (``/proc/net/tcp``: little-endian hex address, state 0A = LISTEN)."""
    found = {}
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        if state == "0A":
            ip, port = local.split(":")
            found[int(port, 16)] = socket.inet_ntoa(bytes.fromhex(ip)[::-1])
    return found


@pytest.mark.parametrize("host", [None, "0.0.0.0"])
def test_view_web_serves_page_and_data_on_one_address_and_says_it(host, monkeypatch):
    """``--view web`` binds the page and the recording's gRPC proxy to one address, 127.0.0.1 by
    default or ``$GTSJAX_VIEW_HOST``, as the kernel's socket table shows, and its URL names that
    address (this machine's name for every interface) for both; the server stops with the command."""
    _rerun()
    if not Path("/proc/net/tcp").exists():
        pytest.skip("no /proc/net/tcp to read the bound addresses from")
    from gtsjax import viewer
    from gtsjax.cli.demo import demo_model_path
    from gtsjax.io.modelfile import load_model
    from gtsjax.sim import simulate

    _, site = simulate("spl-trajectory", seed=3, n_scans=2)
    model = load_model(demo_model_path()).with_site(site)
    web, grpc = _free_ports()
    if host is None:
        monkeypatch.delenv("GTSJAX_VIEW_HOST", raising=False)
    else:
        monkeypatch.setenv("GTSJAX_VIEW_HOST", host)
    view = viewer.View(model, mode="web", web_port=web, grpc_port=grpc)
    try:
        bound = _listening()
        want = host or "127.0.0.1"
        assert (bound.get(web), bound.get(grpc)) == (want, want)
        shown = socket.gethostname() if host == "0.0.0.0" else "127.0.0.1"
        assert view.url == f"http://{shown}:{web}/?url=rerun+http://{shown}:{grpc}/proxy"
        view.close()
    finally:
        viewer._stop(view.server)
    bound = _listening()
    assert web not in bound and grpc not in bound


@pytest.mark.browser
def test_replay_view_web_draws_in_headless_chromium(tmp_path):
    """``gtsjax replay --view web`` on a short simulated log serves Rerun's web viewer on localhost; headless
    Chromium (software rasteriser, no WebGPU) opens it, the recording loads and the field view draws:
    a screenshot holds the track's colour and the seen landmarks' green, which the viewer's own page
    (loading screen, empty viewer) does not."""
    _rerun()
    _need(CHROMIUM is not None, "Debian's chromium is not installed")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        sync_playwright = None
    _need(sync_playwright is not None, "playwright is not installed")
    from gtsjax.io import save_log, save_site
    from gtsjax.sim import simulate

    log, site = simulate("spl-trajectory", seed=3, n_scans=80)
    save_log(log, tmp_path / "t.npz")
    save_site(site, tmp_path / "site.json")
    web, grpc = _free_ports()
    env = dict(cli_env(), GTSJAX_VIEW_WEB_PORT=str(web), GTSJAX_VIEW_GRPC_PORT=str(grpc))
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen([*CHILD, "replay", str(tmp_path / "t.npz"), "--site",
                             str(tmp_path / "site.json"), "--model", str(root / "gtsjax" / "data" / "demo-model.npz"),
                             "--out", str(tmp_path / "gtd.csv"), "--view", "web"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=root)
    lines: queue.Queue[str] = queue.Queue()  # read in a thread: a silent, stuck replay must not block the test
    threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stdout], daemon=True).start()
    try:
        url, waited = None, []
        t0 = time.monotonic()
        while time.monotonic() - t0 < 240:
            try:
                line = lines.get(timeout=5)
            except queue.Empty:
                assert proc.poll() is None, "".join(waited)
                continue
            waited.append(line)
            if line.startswith("view: "):
                url = line.split(" ", 1)[1].strip()
            if "until Ctrl-C" in line:  # the replay is done; the page serves the whole recording
                break
            assert line or proc.poll() is None, "".join(waited)
        assert url is not None, "".join(waited)
        assert read_gtd(tmp_path / "gtd.csv")
        shot = tmp_path / "view.png"
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=[
                "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync"])
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(url)
            drawn = False
            t1 = time.monotonic()
            while not drawn and time.monotonic() - t1 < 90:
                time.sleep(3)
                page.screenshot(path=str(shot))
                drawn = _drew(shot)
            browser.close()
        assert drawn, f"no field drawn in 90 s (last screenshot {shot})"
        # The field the right way up: the laser, on the side line at y = 4 m, is drawn above the posts
        # (y = 1.3 and 2.7 m), as anyone standing behind the laser sees the field.
        laser_row, posts_row = _rows(shot, LASER_COLOUR), _rows(shot, SEEN_COLOUR)
        assert laser_row < posts_row, (laser_row, posts_row, shot)
        if os.environ.get("GTSJAX_VIEW_SHOT"):  # docs/viewing.md's screenshot: GTSJAX_VIEW_SHOT=docs/view.png
            shutil.copy(shot, os.environ["GTSJAX_VIEW_SHOT"])
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise


def _rows(png: Path, colour) -> float:
    """The mean row (0 at the top) of the screenshot's pixels near ``colour``."""
    from PIL import Image

    a = np.asarray(Image.open(png).convert("RGB")).astype(int)
    rows, _ = np.nonzero(np.all(np.abs(a - np.asarray(colour)) < 40, axis=-1))
    assert rows.size > 5, f"no pixels of {colour} in {png}"
    return float(rows.mean())


def _drew(png: Path) -> bool:
    """The screenshot shows the field: pixels of the first track's colour (``viewer._COLOURS[0]``) and of
    the seen landmarks' green."""
    from PIL import Image

    from gtsjax.viewer import _COLOURS, SEEN_COLOUR

    a = np.asarray(Image.open(png).convert("RGB")).astype(int)
    near = lambda c: np.sum(np.all(np.abs(a - np.asarray(c)) < 40, axis=-1))  # noqa: E731
    return near(_COLOURS[0]) > 20 and near(SEEN_COLOUR) > 20
