"""The example scene in the scene viewer at its file's dt (1 ms): does it keep real time?

``rtfem view --example gallbladder``'s session (the liver, the gallbladder hung beneath it, the
cystic plate, the file's grasper and probe on their scripted paths, the viewer's mouse tools parked)
is served at the file's dt = 1 ms and stepped on its thread at the raised priority where permitted;
from 1.5 s of scene time on both scripted tools are in contact. The session's real-time fraction and
its step's median are sampled every 0.5 s for ``--seconds``: with no browser (the viewer's frame
thread only) and with headless chromium drawing the scene (software WebGL on the same cores; where
a chromium binary and playwright are present), quiet and while another process keeps one core busy.

    python benchmarks/scene_viewer.py [--seconds 8] [--dt 0.002] [--busy 2] [--chromium PATH] [--no-browser]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import shutil
import sys
import time
from importlib import resources
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def measure(chromium: str | None, seconds: float, dt: float | None = None) -> dict:
    from viewer_browser import ARGS, _free_port

    from rtfem.interaction.scene_file import load_scene
    from rtfem.viewer.scene_view import SceneSession, serve_scene

    session = SceneSession(load_scene(resources.files("rtfem") / "scenes" / "gallbladder.toml", dt=dt))
    viewer = serve_scene(session, port=_free_port(), block=False, wait_for_client=False)  # from t = 0 now
    session.start()
    real, step_us, frames = [], [], []
    browser = pw = None
    try:
        if chromium:
            from playwright.sync_api import sync_playwright

            pw = sync_playwright().start()
            browser = pw.chromium.launch(executable_path=chromium, headless=True, args=ARGS)
            page = browser.new_page(viewport={"width": 960, "height": 600})
            page.goto(viewer.url)
            page.wait_for_selector("canvas", timeout=60_000)
        while session.scene.time < 1.5:  # the grasper holds the fundus, the probe presses the liver
            time.sleep(0.1)
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            time.sleep(0.5)
            st = viewer.state()
            real.append(st["realtime"])
            step_us.append(session.step_us)
            frames.append(st["frame_rate"])
        forces = session.tool_forces()
    finally:
        if browser is not None:
            browser.close()
        if pw is not None:
            pw.stop()
        session.stop()
        viewer.stop()
    return {"real": np.array(real), "step_us": float(np.median(step_us)), "frames": float(np.median(frames)),
            "touching": forces["grasper"] > 0 and forces["probe"] > 0, "priority": session.priority.split(":")[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--chromium", default=shutil.which("chromium") or shutil.which("chromium-browser"))
    ap.add_argument("--no-browser", action="store_true", help="only the runs without a browser")
    ap.add_argument("--dt", type=float, default=None, help="step the scene at this dt (s; default the file's 1 ms; "
                    "rtfem view takes 2 ms for the example)")
    ap.add_argument("--busy", type=int, default=1, help="processes spinning beside the busy rows (default 1: one core)")
    args = ap.parse_args()
    from _common import busy_core, print_table

    import rtfem as rt

    browsers = [None]
    if args.chromium and not args.no_browser:
        try:
            import playwright  # noqa: F401

            browsers.append(args.chromium)
        except ImportError:
            print("# playwright is not installed: the runs without a browser only")
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} cores; "
          f"the gallbladder example scene in the scene viewer at dt = {(args.dt or 1e-3) * 1e3:g} ms, {args.seconds:g} s "
          "sampled every 0.5 s")
    rows = []
    for chromium in browsers:
        for busy in (False, True):
            with contextlib.ExitStack() as spinning:
                for _ in range(args.busy if busy else 0):
                    spinning.enter_context(busy_core())
                r = measure(chromium, args.seconds, args.dt)
            load = "one core busy" if args.busy == 1 else f"{args.busy} processes busy"
            rows.append(["chromium 960x600" if chromium else "none", load if busy else "quiet", r["priority"],
                         "yes" if r["touching"] else "NO", f"{r['step_us']:.0f}",
                         f"{np.median(r['real']):.2f} (min {r['real'].min():.2f})", f"{r['frames']:.0f}"])
            print(rows[-1], flush=True)
    print()
    print_table(["browser", "machine", "stepping thread", "both tools in contact", "step p50 (us)",
                 "real time (median, min of 0.5 s samples)", "frames sent /s"], rows)


if __name__ == "__main__":
    main()
