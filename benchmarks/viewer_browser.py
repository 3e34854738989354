"""The viewer with a real browser drawing: the default scene pulled in headless chromium.

The scene of ``rtfem view`` (``default_session()``: the liver as a solid of tet10, the reduced
nonlinear model) is served, headless chromium (Debian's, WebGL in software: swiftshader, on the
same cores) opens it and drags the organ from the canvas centre, holds the pull for
``--seconds`` and lets go. The session's rate (steps/s, fraction of real time) and the frames
sent per second are sampled every 0.5 s during the hold; once quiet, once while another process
keeps one core busy; each with the session's stepping thread at the raised priority
(rtfem.threads.raise_priority, where permitted) and at the normal one (RTFEM_PHYSICS_NICE=0). Needs
playwright and a chromium binary (the test extra; apt-get install chromium).

    python benchmarks/viewer_browser.py [--seconds 8] [--viewport 1280x800 960x600] [--priority raised normal]
                                        [--chromium PATH]
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

ARGS = ["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader"]



def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def measure(viewer, chromium: str, seconds: float, viewport=(1280, 800)) -> dict:
    from playwright.sync_api import sync_playwright

    from rtfem.viewer.benchmark import BROWSER_COUNTER

    rates, real, frames = [], [], []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, headless=True, args=ARGS)
        try:
            page = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
            page.add_init_script(BROWSER_COUNTER)
            page.goto(viewer.url)
            page.wait_for_selector("canvas", timeout=60_000)
            time.sleep(3.0)
            box = page.locator("canvas").first.bounding_box()
            x0, y0 = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            page.mouse.move(x0, y0)
            page.mouse.down()
            for i in range(1, 21):
                page.mouse.move(x0 + 3 * i, y0 - 5 * i)
                time.sleep(0.05)
            time.sleep(1.5)  # the rates cover a whole second of the pull
            counts0, t0 = page.evaluate("({...window.__rtfem})"), time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                st = viewer.state()
                rates.append(st["sim_rate"])
                real.append(viewer.session.stats.realtime)
                frames.append(st["frame_rate"])
                time.sleep(0.5)
            counts, t1 = page.evaluate("({...window.__rtfem})"), time.perf_counter()
            grabbed = viewer.state()["grabbed"] is not None
            page.mouse.up()
        finally:
            browser.close()
    return {"grabbed": grabbed, "steps_per_s": float(np.median(rates)), "realtime_p50": float(np.median(real)),
            "realtime_min": float(np.min(real)), "frames_per_s": float(np.median(frames)),
            "drawn_per_s": (counts["drawn"] - counts0["drawn"]) / (t1 - t0),
            "compiled_per_s": (counts["compiled"] - counts0["compiled"]) / (t1 - t0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--viewport", type=lambda v: tuple(int(x) for x in v.split("x")), nargs="+",
                    default=[(1280, 800), (960, 600)], help="browser viewports, WxH (default 1280x800 960x600)")
    ap.add_argument("--priority", nargs="+", choices=["raised", "normal"], default=["raised", "normal"],
                    help="the stepping thread's priority: raised where permitted, normal (default both)")
    ap.add_argument("--chromium", default=shutil.which("chromium") or shutil.which("chromium-browser"))
    args = ap.parse_args()
    if not args.chromium:
        raise SystemExit("no chromium binary: apt-get install chromium, or give --chromium PATH")
    from rtfem.viewer.app import Viewer
    from rtfem.threads import PHYSICS_NICE
    from rtfem.viewer.session import default_session
    from _common import busy_core, print_table

    session = default_session()
    rows = []
    for viewport in args.viewport:
        for busy in (False, True):
            for priority in args.priority:
                os.environ["RTFEM_PHYSICS_NICE"] = "0" if priority == "normal" else str(PHYSICS_NICE)
                with busy_core(busy):
                    viewer = Viewer(session, port=_free_port()).start()
                    try:
                        r = measure(viewer, args.chromium, args.seconds, viewport)
                    finally:
                        viewer.stop()
                        session.release()
                rows.append(_row(viewport, busy, session.stats.priority.split(":")[0], r))
                print(rows[-1], flush=True)
    print()
    print_table(["viewport", "machine", "stepping thread", "grabbed", "steps/s (median)",
                 "real time (median, min of 0.5 s samples)", "frames sent /s", "frames drawn /s", "shaders compiled /s"],
                rows)


def _row(viewport, busy: bool, priority: str, r: dict) -> list:
    return ["%dx%d" % viewport, "one core busy" if busy else "quiet", priority, "yes" if r["grabbed"] else "NO",
            f"{r['steps_per_s']:,.0f}", f"{r['realtime_p50']:.2f} (min {r['realtime_min']:.2f})",
            f"{r['frames_per_s']:.0f}", f"{r['drawn_per_s']:.1f}", f"{r['compiled_per_s']:.1f}"]


if __name__ == "__main__":
    main()
