"""The README's screenshot of the Rerun web view: ``gtsjax replay --view web`` on the three crossing
robots (``spl-crossing``, seed 1000) with the shipped model, opened in headless Debian Chromium
(Playwright, software rasteriser), the timeline put at ``--at`` of the run, the page shot.

    python scripts/view_screenshot.py --out docs/view-web.png

Needs the viewer extra, ``playwright`` and Debian's ``chromium``."""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "view-web.png")
    ap.add_argument("--at", type=float, default=0.55, help="where on the timeline (0: start, 1: end)")
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    gtsjax = [sys.executable, "-m", "gtsjax"]
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        subprocess.run(gtsjax + ["simulate", "spl-crossing", "--seed", "1000", "--out", str(d / "c.npz"), "--site",
                                 str(d / "site.json")], check=True, cwd=ROOT)
        proc = subprocess.Popen(gtsjax + ["replay", str(d / "c.npz"), "--site", str(d / "site.json"), "--model",
                                          str(ROOT / "gtsjax" / "data" / "demo-model.npz"), "--out", str(d / "gtd.csv"),
                                          "--view", "web"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                cwd=ROOT, env=dict(os.environ, COLUMNS="200"))
        try:
            url = None
            for line in proc.stdout:
                if line.startswith("view: "):
                    url = line.split(" ", 1)[1].strip()
                if "until Ctrl-C" in line:
                    break
            if url is None:
                raise SystemExit("replay --view web printed no address")
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=shutil.which("chromium"), args=[
                    "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-first-run",
                    "--disable-background-networking", "--disable-component-update", "--disable-sync"])
                page = browser.new_page(viewport={"width": 1400, "height": 820})
                page.goto(url)
                time.sleep(20)  # the page loads the viewer (WebAssembly) and then the recording
                # The timeline's bar runs along the bottom of the page, from after the play controls to
                # before the time field: a click there moves the time cursor.
                left, right, y = 285, 1165, 806
                page.mouse.click(left + args.at * (right - left), y)
                time.sleep(5)
                args.out.parent.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(args.out))
                browser.close()
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
