"""``rtfem view out.pvd`` (or a run's output folder): a written run replayed in the browser.

A ParaView collection (``.pvd``: ``rtfem simulate``'s ``response.pvd``, a scene's ``<body>/<body>.pvd``)
lists VTU frames at their times; a folder holding one, or one per body in its subfolders (``rtfem
simulate scene.toml -o DIR``), replays them all on one clock. Each frame's surface is drawn where
the file puts the body: its points plus the ``displacement`` field where the points are the
reference (the field data ``rtfem_reference_points`` = 1, ParaView's convention, which rtfem writes),
its points as they are where they are already displaced (``rtfem_reference_points`` = 0, and files
written before the marker); without the marker, the frames themselves say which (points that stay
put while the field changes are a reference). A volume's frames are drawn on its boundary.
The panel's transport plays, pauses, restarts and moves to any time.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ModelError
from ..threads import background
from .app import Served, serve_until_interrupted
from .controls import Transport
from .gltf import SurfaceGlb, colormap

__all__ = ["Track", "read_run", "Replay", "ReplayViewer", "serve_replay", "is_run"]

#: the most bytes of drawn positions a replay holds in memory (float32 surface points of every frame)
MAX_BYTES = 2 * 2**30
MAX_FRAMES = 100_000


@dataclass
class Track:
    """One body's written frames: ``times`` (k,), the drawn surface's ``triangles`` over its
    ``positions`` (k, m, 3) float32 and displacement magnitudes ``magnitudes`` (k, m), and how the
    points were read (``convention``: "reference + displacement", "displaced points" or "points")."""

    name: str
    times: np.ndarray
    triangles: np.ndarray
    positions: np.ndarray
    magnitudes: np.ndarray
    convention: str

    def frame_at(self, t: float) -> int:
        """The last frame at or before ``t`` (the first before the first)."""
        return max(0, int(np.searchsorted(self.times, t + 1e-12, side="right")) - 1)


def is_run(path) -> bool:
    """Whether ``rtfem view PATH`` replays: a .pvd file, or a folder (a run's output)."""
    p = Path(path)
    return p.suffix.lower() == ".pvd" or p.is_dir()


def _collections(path: Path) -> list[Path]:
    """The .pvd files ``path`` names: itself, or a folder's own, else those of its subfolders."""
    if not path.is_dir():
        return [path]
    found = sorted(path.glob("*.pvd"))
    if not found:
        found = sorted(p for sub in sorted(path.iterdir()) if sub.is_dir() for p in sub.glob("*.pvd"))
    if not found:
        raise ModelError(f"{str(path)!r} holds no .pvd collection (nor do its subfolders): give a .pvd file or the "
                         "folder rtfem simulate wrote (-o DIR)")
    return found


def _frames_of(pvd: Path) -> list[tuple[float, Path]]:
    """(time, VTU path) of each DataSet of a .pvd, sorted by time."""
    import xml.etree.ElementTree as ET

    from ..userfiles import read_text

    text = read_text(pvd, "ParaView collection")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ModelError(f"{str(pvd)!r} is not a ParaView collection (XML: {exc})") from None
    frames = []
    for item in root.iter("DataSet"):
        try:
            t = float(item.get("timestep", "0"))
        except ValueError:
            raise ModelError(f"{str(pvd)!r}: a DataSet's timestep {item.get('timestep')!r} is not a number") from None
        if item.get("file") is None or not np.isfinite(t):
            raise ModelError(f"{str(pvd)!r}: a DataSet without a file, or with a time that is not finite")
        frames.append((t, pvd.parent / item.get("file")))
    if not frames:
        raise ModelError(f"{str(pvd)!r} lists no frames (no <DataSet file=...> in its <Collection>)")
    if len(frames) > MAX_FRAMES:
        raise ModelError(f"{str(pvd)!r} lists {len(frames):,} frames, more than the {MAX_FRAMES:,} a replay takes")
    return sorted(frames, key=lambda f: f[0])


def _read_vtu(path: Path):
    """(points (n, 3), cells [(type, (c, k))], displacement (n, 3) or None, the reference marker or None)."""
    import meshio

    from ..userfiles import regular_file

    regular_file(path, "frame")
    try:
        m = meshio.read(str(path))
    except Exception as exc:  # meshio raises many kinds on a bad file
        raise ModelError(f"cannot read the frame {str(path)!r}: {type(exc).__name__}: {exc}") from None
    u = m.point_data.get("displacement")
    u = None if u is None else np.asarray(u, dtype=float)[:, :3]
    mark = m.field_data.get("rtfem_reference_points")
    mark = None if mark is None else int(np.asarray(mark).ravel()[0])
    return np.asarray(m.points, dtype=float)[:, :3], [(c.type, np.asarray(c.data)) for c in m.cells], u, mark


def boundary(cells, n_points: int) -> np.ndarray:
    """The triangles drawn for a frame's cells: its triangles, else the faces of its tetrahedra (their
    corners) that only one tetrahedron has, wound outward."""
    tris = [c[:, :3] for t, c in cells if t in ("triangle", "triangle6")]
    if tris:
        return np.concatenate(tris).astype(np.int64)
    tets = [c[:, :4] for t, c in cells if t in ("tetra", "tetra10")]
    if not tets:
        raise ModelError(f"the frame has no triangles or tetrahedra to draw (cells: {', '.join(t for t, _ in cells)})")
    T = np.concatenate(tets).astype(np.int64)
    faces = np.concatenate([T[:, [1, 2, 3]], T[:, [0, 3, 2]], T[:, [0, 1, 3]], T[:, [0, 2, 1]]])
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    return faces[first[counts == 1]]


def _convention(frames: list) -> str:
    """How to place the points of a track's frames (see the module)."""
    marks = {f[3] for f in frames}
    if marks == {1}:
        return "reference + displacement"
    if marks == {0} or all(f[2] is None for f in frames):
        return "displaced points" if marks == {0} else "points"
    P0 = frames[0][0]
    if len(frames) > 1 and all(np.array_equal(f[0], P0) for f in frames[1:]):
        return "reference + displacement"  # the points stay put while the field is written: a reference
    return "displaced points"  # rtfem before the marker (points + field moved together), or one frame alone


def read_track(pvd: Path, progress=None) -> Track:
    """One .pvd's frames as a :class:`Track` (see the module)."""
    frames = []
    listed = _frames_of(pvd)
    for k, (t, vtu) in enumerate(listed):
        frames.append((*_read_vtu(vtu), t))
        if frames[-1][0].shape != frames[0][0].shape:
            raise ModelError(f"{str(vtu)!r} has {frames[-1][0].shape[0]:,} points, the first frame "
                             f"{frames[0][0].shape[0]:,}: a replay's frames share one mesh")
        if progress is not None and (k % 50 == 49 or k == len(listed) - 1):
            progress(f"{pvd.name}: {k + 1}/{len(listed)} frames")
    convention = _convention(frames)
    tri = boundary(frames[0][1], frames[0][0].shape[0])
    drawn = np.unique(tri)
    if len(frames) * drawn.size * 16 > MAX_BYTES:
        raise ModelError(f"{str(pvd)!r}: {len(frames):,} frames of {drawn.size:,} drawn points need "
                         f"{len(frames) * drawn.size * 16 / 2**30:.1f} GiB, more than a replay holds (2 GiB)")
    positions = np.empty((len(frames), drawn.size, 3), dtype=np.float32)
    magnitudes = np.zeros((len(frames), drawn.size), dtype=np.float32)
    for k, (P, _, u, _, _) in enumerate(frames):
        x = P[drawn]
        if u is not None:
            magnitudes[k] = np.linalg.norm(u[drawn], axis=1)
            if convention == "reference + displacement":
                x = x + u[drawn]
        positions[k] = x
    name = pvd.parent.name if pvd.stem == pvd.parent.name else pvd.stem
    return Track(name, np.array([f[4] for f in frames]), np.searchsorted(drawn, tri), positions, magnitudes, convention)


def read_run(path, progress=None) -> list[Track]:
    """The tracks of a .pvd file or a run's folder (see the module).

    Raises
    ------
    ModelError
        A path that is not there, a folder without a collection, a collection that is not one or
        lists no frames, a frame that cannot be read, frames of different meshes.
    """
    p = Path(os.fspath(path))
    if not p.exists():
        raise ModelError(f"{str(p)!r} does not exist: give a .pvd file or a run's output folder")
    return [read_track(pvd, progress) for pvd in _collections(p)]


class Replay:
    """The replay's clock over the tracks' times (a :class:`~rtfem.viewer.controls.Clock`): the wall
    clock while playing, stopped at the last frame; paused at the first until played."""

    def __init__(self, tracks: list[Track]) -> None:
        self.tracks = tracks
        self.begin = float(min(t.times[0] for t in tracks))
        self.end_time = float(max(t.times[-1] for t in tracks))
        self._t, self._wall, self._playing = self.begin, 0.0, False
        self._lock = threading.Lock()

    def _now(self) -> float:  # under the lock
        if self._playing:
            t = self._t + time.perf_counter() - self._wall
            if t < self.end_time:
                return t
            self._t, self._playing = self.end_time, False
        return self._t

    @property
    def time(self) -> float:
        with self._lock:
            return self._now()

    @property
    def playing(self) -> bool:
        with self._lock:
            self._now()  # stops the clock at the end
            return self._playing

    def play(self) -> None:
        with self._lock:
            t = self._now()
            self._t = self.begin if t >= self.end_time else t  # played at the end: from the start again
            self._wall, self._playing = time.perf_counter(), True

    def pause(self) -> None:
        with self._lock:
            self._t, self._playing = self._now(), False

    def restart(self) -> None:
        self.request_seek(self.begin)

    def request_seek(self, t: float) -> None:
        with self._lock:
            self._t = min(max(float(t), self.begin), self.end_time)
            self._wall = time.perf_counter()

    # the Served protocol: nothing steps behind a replay
    def start(self) -> "Replay":
        return self

    def stop(self) -> None:
        pass


class ReplayViewer(Served):
    """A viser server replaying :class:`Track` s: each body coloured by its displacement magnitude
    (one colour scale for all, the run's largest), the panel's transport and what was read."""

    def __init__(self, tracks: list[Track], *, host: str = "127.0.0.1", port: int = 8080, fps: float = 30.0,
                 source: str = "") -> None:
        from .app import _is_loopback, _need_viser, open_server
        from .camera import VIEW, frame_client, light_scene

        viser = _need_viser()
        self.session = Replay(tracks)
        self.tracks, self.fps = tracks, float(fps)
        self.server, self.host, self.port = open_server(viser, host, port)
        if not _is_loopback(host):
            print(f"rtfem viewer: WARNING: serving on {host}:{self.port} makes the run reachable from other machines "
                  "on the network, and the viewer has no authentication.", file=sys.stderr, flush=True)
        self.url = f"http://{host}:{self.port}"
        self.frames, self.connections = 0, 0
        self.shown = [-1] * len(tracks)  # the frame each track shows
        X = np.concatenate([t.positions.reshape(-1, 3) for t in tracks])
        lo, hi = X.min(axis=0), X.max(axis=0)
        self.centre, self.size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
        self.vmax = max(float(max(t.magnitudes.max() for t in tracks)), 1e-9)
        light_scene(self.server, self.centre, self.size, 0.8 * np.asarray(VIEW) / np.linalg.norm(VIEW))

        def connect(client) -> None:
            self.connections += 1
            frame_client(client, self.centre, 0.5 * self.size, VIEW)
            if self.connections == 1:
                self.session.play()

        self.server.on_client_connect(connect)
        self._glbs = [SurfaceGlb(t.triangles, t.positions.shape[1]) for t in tracks]
        self.meshes = [self.server.scene.add_glb(f"/runs/{k}", self._frame(k, 0)) for k in range(len(tracks))]
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        lines = [f"**{t.name}**: {t.times.size:,} frames from {t.times[0]:g} to {t.times[-1]:g} s, "
                 f"{t.positions.shape[1]:,} surface points; drawn as {t.convention}" for t in tracks]
        gui.add_markdown(f"### rtfem replay\n{source}  \n" + "  \n".join(lines)
                         + f"  \ncoloured by the displacement magnitude, 0 .. {self.vmax * 1e3:.3g} mm")
        step = float(min(np.diff(t.times).min() if t.times.size > 1 else 0.01 for t in tracks)) or 0.01
        self.transport = Transport(gui, self.session, step=step)
        self.stats_md = gui.add_markdown("waiting for the first browser ...")
        self._stop = threading.Event()
        self._thread = background(threading.Thread(target=self._loop, name="rtfem-replay-frames", daemon=True),
                                  self._stop.set)

    def _frame(self, k: int, i: int) -> bytes:
        t = self.tracks[k]
        return self._glbs[k](t.positions[i], colormap(t.magnitudes[i], self.vmax))

    def _loop(self) -> None:
        next_panel = 0.0
        while not self._stop.is_set():
            t0 = time.perf_counter()
            t = self.session.time
            for k, track in enumerate(self.tracks):
                i = track.frame_at(t)
                if i != self.shown[k]:
                    self.meshes[k].glb_data = self._frame(k, i)
                    self.shown[k] = i
                    self.frames += 1
            if t0 >= next_panel:
                state = "playing" if self.session.playing else "paused"
                self.stats_md.content = (f"t = **{t:.3f} s** of {self.session.begin:g} .. {self.session.end_time:g} s; "
                                         f"{state}; frame {self.shown[0] + 1} of {self.tracks[0].times.size}")
                self.transport.refresh()
                next_panel = t0 + 0.25
            time.sleep(max(0.0, 1.0 / self.fps - (time.perf_counter() - t0)))

    def state(self) -> dict:
        """What the browser is being served, for tests and scripts."""
        return {"url": self.url, "time": self.session.time, "playing": self.session.playing,
                "frames_shown": list(self.shown), "frames": self.frames, "clients": len(self.server.get_clients()),
                "tracks": [t.name for t in self.tracks], "conventions": [t.convention for t in self.tracks]}


def serve_replay(path, *, host: str = "127.0.0.1", port: int = 8080, block: bool = True, progress=None) -> ReplayViewer:
    """Read a run (:func:`read_run`), serve its replay and (``block``) run until Ctrl-C."""
    tracks = read_run(path, progress)
    viewer = ReplayViewer(tracks, host=host, port=port, source=f"`{path}`").start()
    if block:
        serve_until_interrupted(viewer)
    return viewer
