"""The haptic loop with each device adapter, and the OpenIGTLink round trip, on stand-ins for the
hardware: the stub libHD.so and libdhd.so of tests/stubs (compiled here with the C compiler) and a
fake Haply Inverse Service on loopback, beside a plain SharedDevice as the baseline.

Scene: a 10 cm plate held at its edge (a shell, 20 modes, static correction), a point probe
(200 N/m) in a 1 kHz HapticLoop, Python ticks and compiled ones, for ``--seconds`` each, once
quiet and once with another process keeping a core busy. The device's servo runs at its own
rate on its own thread (the stubs' scheduler, our servo thread, the service's messages),
meeting the loop in the mailbox; the device holds the stylus 2 mm into the plate. Columns: the
loop's compute per tick and its lateness (p50 / p99), ticks skipped, the servo ticks the device
ran, and whether the device stopped.

OpenIGTLink: a pyigtl client moves the tool in and out of the plate 40 times; the round trip is
the time from sending the pose that enters to receiving the first Force message that is not
zero (the bridge sends Force at up to ``--force-rate``).

    python benchmarks/devices.py [--seconds 3]
"""

from __future__ import annotations

import argparse
import ctypes
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import busy_core, print_table  # noqa: E402

import rtfem as rt  # noqa: E402
from rtfem.interaction.devices import Workspace  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the fake Inverse Service and the test helpers


def stub(source: str, out: Path) -> ctypes.CDLL:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise SystemExit("a C compiler is needed to build the stub libraries (apt-get install gcc)")
    subprocess.run([cc, "-shared", "-fPIC", "-O1", "-o", str(out), str(ROOT / "tests" / "stubs" / source), "-lpthread"],
                   check=True)
    lib = ctypes.CDLL(str(out))
    lib.stub_script.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_int), ctypes.c_int]
    return lib


def hold(lib, point) -> None:
    p = np.ascontiguousarray(np.atleast_2d(point), dtype=float)
    lib.stub_reset()
    lib.stub_script(p.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), None, 1)


def scene():
    mesh = rt.meshes.plate(0.1, nx=10)
    model = rt.ShellModel(mesh, rt.Material(E=3e5, nu=0.45, thickness=0.004, density=1060))
    model.fix("boundary")
    sim = rt.ModalSimulator(rt.modal_analysis(model, 20), dt=1e-3, damping=rt.Damping(alpha=30.0), static_correction=True)
    return mesh, sim


def row(name, device, mesh, sim, seconds, compiled, servo_ticks) -> list:
    sim.reset()
    probe = rt.Probe(mesh, sim, radius=0.0, coupling="spring", stiffness=200.0)
    loop = rt.HapticLoop(probe, device, rate=1000.0, compiled=compiled)
    t0 = servo_ticks()
    st = loop.run(seconds)
    comp, late = np.array(st.compute) * 1e6, np.array(st.lateness) * 1e6
    return [name, "compiled" if st.compiled else "Python", st.steps, st.missed,
            f"{np.median(comp):.1f} / {np.percentile(comp, 99):.1f} us",
            f"{np.median(late):.1f} / {np.percentile(late, 99):.1f} us",
            servo_ticks() - t0, getattr(device, "stop_reason", None) or "-"]


def loops(seconds: float, busy: bool) -> list:
    from test_devices import FakeInverseService

    mesh, sim = scene()
    centre = np.array([0.05, 0.05, -0.002])  # 2 mm into the plate, organ frame
    ws = Workspace()  # the device's frame is the organ's here
    rows = []
    with tempfile.TemporaryDirectory() as tmp, busy_core(busy):
        hd, dhd = stub("hd_stub.c", Path(tmp) / "libHD.so"), stub("dhd_stub.c", Path(tmp) / "libdhd.so")
        for compiled in (False, True):
            dev = rt.SharedDevice(centre)
            rows.append(row("SharedDevice (baseline)", dev, mesh, sim, seconds, compiled, lambda: 0))
            hold(hd, centre * 1e3)  # mm
            with rt.devices.OpenHaptics(library=Path(tmp) / "libHD.so", workspace=ws) as dev:
                rows.append(row("OpenHaptics (stub libHD)", dev, mesh, sim, seconds, compiled, lambda d=dev: d.servo.ticks))
            hold(dhd, centre)
            with rt.devices.ForceDimension(library=Path(tmp) / "libdhd.so", workspace=ws) as dev:
                rows.append(row("ForceDimension (stub libdhd)", dev, mesh, sim, seconds, compiled, lambda d=dev: d.servo.ticks))
            service = FakeInverseService(centre[None])
            try:
                with rt.devices.Haply(service.url, workspace=ws, max_force=5.0) as dev:
                    rows.append(row("Haply (fake Inverse Service)", dev, mesh, sim, seconds, compiled,
                                    lambda d=dev: d.servo.ticks))
            finally:
                service.stop()
    return rows


def round_trips(n: int, force_rate: float) -> list[float]:
    import pyigtl

    from test_devices import _free_port, _pose

    mesh, sim = scene()
    port = _free_port()
    times = []
    with rt.devices.IGTLServer(mesh, sim, port=port, tool_radius=0.005, stiffness=300.0, force_rate=force_rate):
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
        try:
            t0 = time.perf_counter()
            while not client.is_connected():
                if time.perf_counter() - t0 > 10:
                    raise SystemExit("the pyigtl client did not connect")
                time.sleep(0.01)
            for _ in range(n):
                client.send_message(_pose(pyigtl, [50.0, 50.0, 30.0]), wait=True)  # out of contact
                time.sleep(0.3)
                client.get_latest_messages()
                t0 = time.perf_counter()
                client.send_message(_pose(pyigtl, [50.0, 50.0, 5.0 - 2.0]), wait=True)  # 2 mm in
                while True:
                    got = [m for m in client.get_latest_messages() if m.device_name == "Force"]
                    if got and np.linalg.norm(np.asarray(got[-1].matrix)[:3, 3]) > 1e-6:
                        times.append(time.perf_counter() - t0)
                        break
                    if time.perf_counter() - t0 > 2.0:
                        raise SystemExit("no force came back within 2 s")
                    time.sleep(0.0002)
        finally:
            client.stop()
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--trips", type=int, default=40)
    ap.add_argument("--force-rate", type=float, nargs="+", default=[100.0, 1000.0])
    args = ap.parse_args()
    headers = ["device", "loop", "ticks", "skipped", "compute p50 / p99", "lateness p50 / p99", "servo ticks", "stopped"]
    for busy in (False, True):
        print(f"\nthe 1 kHz probe loop, {'one core busy' if busy else 'quiet'} ({args.seconds:g} s a row):")
        print_table(headers, loops(args.seconds, busy))
    rows = []
    for rate in args.force_rate:
        t = np.array(round_trips(args.trips, rate)) * 1e3
        rows.append([f"{rate:g} Hz", len(t), f"{np.median(t):.1f} ms", f"{np.percentile(t, 99):.1f} ms", f"{t.max():.1f} ms"])
    print("\nOpenIGTLink round trip on loopback (a pose entering the plate sent -> the first non-zero Force received):")
    print_table(["Force sent at up to", "trips", "p50", "p99", "max"], rows)


if __name__ == "__main__":
    main()
