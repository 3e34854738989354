"""The simulation behind the scene viewer: a :class:`~rtfem.Scene` stepped in real time on its own
thread, with the mouse as two more tools, paused, played, restarted and sent to a time.

Nothing here needs a browser (:mod:`rtfem.viewer.scene_view` serves it). A restart and a move of
the time slider go through the Driver protocol only: each body's ``get_state``/``set_state``, kept
every :attr:`SceneSession.SNAPSHOT_EVERY` s of scene time, the tools' state beside them; a later
time is reached by stepping from the nearest kept state before it, as fast as the steps run.
"""

from __future__ import annotations

import copy
import threading
import time

import numpy as np

from ..drivers.base import displacements_at
from ..errors import ModelError
from ..interaction.devices.base import SharedDevice
from ..interaction.scene_scalpel import CutJobFailed
from ..threads import raise_priority, runtime
from .session import PhysicsThread

__all__ = ["SceneSession", "snapshot", "rewind", "scripted_end"]

#: the most states a session keeps for the time slider (every SNAPSHOT_EVERY s; beyond, every other one)
MAX_SNAPSHOTS = 2000
#: the time after the scripted paths' last change the slider shows (s), for the scene to settle
SETTLE = 1.0
#: a scripted grip let go this long (s) after its path's last row is taken as held to the end
HOLD = 10.0


def snapshot(scene) -> dict:
    """The scene's state now: its step count and time, each body's driver state (``get_state``),
    each tool's (where it and its hand are, its force, what it holds), the springs' last forces."""
    tools = []
    for t in scene.tools:
        held = None
        if t.held is not None:
            held = copy.copy(t.held)
            held.anchor = np.array(t.held.anchor, dtype=float)
        tools.append({"target": None if t.target is None else np.array(t.target, dtype=float),
                      "proxy": None if t.proxy is None else np.array(t.proxy, dtype=float),
                      "force": np.array(t.force, dtype=float), "held": held,
                      "offsets": None if getattr(t, "offsets", None) is None else np.array(t.offsets)})
    return {"steps": int(scene.steps), "time": float(scene.time), "which": (list(scene.bodies), list(scene.attachments)),
            "springs": dict(scene._spring_forces),  # the next step's start (each replaced, never changed in place)
            "scalpels": [sc.state() for sc in scene.scalpels],
            "bodies": [b.driver.get_state() for b in scene.bodies],
            "loads": [_correction_loads(b.driver) for b in scene.bodies], "tools": tools}


def _correction_loads(driver):
    """The loads a driver's static correction is drawn for (its last step's; not in ``get_state``,
    which holds what the next step needs), or None for a driver without one."""
    current = getattr(driver, "_current_loads", None)
    if current is None:
        return None
    loads, array = current()
    return ({k: np.array(f, dtype=float) for k, f in loads.items()}, None if array is None else array.copy())


def rewind(scene, state: dict) -> None:
    """Put ``scene`` back in a :func:`snapshot`'s state (its contact records cleared; the force
    records of scripted devices, ``times`` and ``forces``, cut at that time). A body cut since is put back
    as it was then (its model, driver and attachments), and so is its scalpel."""
    bodies, attachments = state["which"]
    if [id(x) for x in (*bodies, *attachments)] != [id(x) for x in (*scene.bodies, *scene.attachments)]:
        from ..interaction.scene_scalpel import drop_caches

        drop_caches(scene)
        scene.bodies, scene.attachments = list(bodies), list(attachments)
    for scalpel, s in zip(scene.scalpels, state["scalpels"]):
        scalpel.set_state(s)
    for body in scene.bodies:  # (how far a body moved over its last step is not known across a jump)
        body.__dict__.pop("_last_now", None)
    for body, s, loads in zip(scene.bodies, state["bodies"], state["loads"]):
        body.driver.set_state(s)
        if loads is not None:  # the field drawn from the state: with the correction of that step's loads
            body.driver._loads, body.driver._load_array = loads[0].copy(), loads[1]
    for tool, s in zip(scene.tools, state["tools"]):
        tool.target = None if s["target"] is None else s["target"].copy()
        tool.proxy = None if s["proxy"] is None else s["proxy"].copy()
        tool.force = s["force"].copy()
        tool.held = None if s["held"] is None else copy.copy(s["held"])
        if tool.held is not None:
            tool.held.anchor = s["held"].anchor.copy()
        if s["offsets"] is not None:
            tool.offsets = s["offsets"].copy()
        if getattr(tool.device, "trajectory", None) is not None:  # a scripted hand: its buttons read at that time
            tool.device.position(state["time"])
        times, forces = getattr(tool.device, "times", None), getattr(tool.device, "forces", None)
        if isinstance(times, list) and isinstance(forces, list):
            keep = int(np.searchsorted(np.asarray(times, dtype=float), state["time"], side="right"))
            del times[keep:], forces[keep:]
    scene.steps, scene.time = state["steps"], state["time"]
    scene.contacts, scene._spring_forces = {}, dict(state["springs"])


def scripted_end(scene) -> float:
    """The last time a scripted tool's path or grip changes (s; 0 with none). A grip let go more than
    :data:`HOLD` s after the path's last row is a grip held to the end (the example's ``closed =
    [[0.2, 100.0]]``), not a change to wait for."""
    end = 0.0
    for tool in scene.tools:
        keys = getattr(getattr(tool.device, "trajectory", None), "path", None)
        if keys is None:
            continue
        last = float(np.asarray(keys)[-1, 0])
        closed = np.asarray(getattr(tool.device.trajectory, "closed", np.zeros((0, 2))), dtype=float).reshape(-1, 2)
        changes = np.concatenate([[last], closed.ravel()])
        end = max(end, float(changes[changes <= last + HOLD].max()))
    return end


class SceneSession(PhysicsThread):
    """A :class:`~rtfem.Scene` stepped in real time on its own thread, with the mouse as a grasper
    and a probe (tools "mouse" and "mouse probe", parked far above the scene while unused).

    Parameters
    ----------
    scene : the scene (its bodies, obstacles, attachments and tools), at the time it starts from.
    grasp_radius, grasp_stiffness : the mouse grasper's reach (m) and hold (N/m).
    probe_radius, probe_stiffness : the mouse probe's sphere (m) and coupling (N/m).
    playing : step from the start (False: paused until :meth:`play`; the viewer plays at the
        first browser's connection, so the scripted paths start when someone watches).

    Raises
    ------
    ModelError
        A scene without bodies, or one that already has tools named "mouse" or "mouse probe".
    """

    SNAPSHOT_EVERY = 0.1  # s of scene time between the states kept for the time slider

    def __init__(self, scene, *, grasp_radius: float = 0.008, grasp_stiffness: float = 300.0,
                 probe_radius: float = 0.004, probe_stiffness: float = 300.0, playing: bool = True) -> None:
        if not scene.bodies:
            raise ModelError("the scene has no body to show")
        self.scene = scene
        X = np.concatenate([b.X[b.surface] for b in scene.bodies])
        lo, hi = X.min(axis=0), X.max(axis=0)
        self.centre, self.size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
        self.park = self.centre + np.array([0.0, 0.0, 20.0 * self.size])
        self.hand, self.pointer = SharedDevice(self.park), SharedDevice(self.park)
        self.grasper = scene.add_tool("mouse", self.hand, kind="grasper", radius=grasp_radius, stiffness=grasp_stiffness)
        self.probe = scene.add_tool("mouse probe", self.pointer, kind="probe", radius=probe_radius,
                                    stiffness=probe_stiffness)
        self._thread_name = "rtfem-scene-physics"
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._playing = threading.Event()
        if playing:
            self._playing.set()
        self._every = max(1, int(round(self.SNAPSHOT_EVERY / scene.dt)))
        self._snapshots = {scene.steps: snapshot(scene)}  # steps -> state; the first is where a restart goes
        self._start = scene.steps
        self._seek: float | None = None  # a time the slider asked for, taken by the clock
        self._epoch = 0  # changes at each restart or seek: the clock starts its schedule again
        self.seeking = False
        self.path_end = scripted_end(scene)  # s: when the scripted tools stop (0: none)
        self.end_time = max(self.path_end + SETTLE, 2.0)
        self.error: str | None = None
        self.sim_rate = self.realtime = self.step_us = 0.0
        self.priority = ""  # the stepping thread's scheduling priority (rtfem.threads.raise_priority)

    # ---------------------------------------------------------------- the mouse
    def grab(self, point) -> None:
        """Close the mouse grasper at ``point`` (it takes the nearest body's surface within its radius)."""
        self.hand.move_to(point)
        self.hand.mailbox[7] = 1.0

    def drag(self, target) -> None:
        self.hand.move_to(target)

    def release(self) -> None:
        self.hand.mailbox[7] = 0.0
        self.hand.move_to(self.park)

    def press(self, centre) -> None:
        """Put the mouse probe's centre at ``centre``."""
        self.pointer.move_to(centre)

    def unpress(self) -> None:
        self.pointer.move_to(self.park)

    @property
    def held(self) -> str | None:
        """The body the mouse grasper holds, or None."""
        held = self.grasper.held
        return None if held is None else held.a.name

    def tool_forces(self) -> dict[str, float]:
        """|force| (N) of each tool on the bodies in the last step."""
        return {t.name: float(np.linalg.norm(t.force)) for t in self.scene.tools}

    def surface_displacements(self) -> list[np.ndarray]:
        """Each body's surface displacements (k, 3), read between steps."""
        return self.surfaces()[0]

    def surfaces(self) -> tuple[list[np.ndarray], list]:
        """Each body's surface displacements (k, 3) and the bodies they are of, read between steps
        together (a scalpel's cut replaces its body between two steps)."""
        with self._lock:
            bodies = list(self.scene.bodies)
            return [displacements_at(b.driver, b.surface) for b in bodies], bodies

    # ---------------------------------------------------------------- play, pause, restart, seek
    @property
    def time(self) -> float:
        return float(self.scene.time)

    @property
    def playing(self) -> bool:
        return self._playing.is_set()

    def play(self) -> None:
        self._playing.set()

    def pause(self) -> None:
        """Stop the clock: once this returns no step is under way and none starts (the clock checks the
        flag under the same lock as it steps; it stepped once more after a pause on a slow machine)."""
        with self._lock:
            self._playing.clear()

    def restart(self) -> None:
        """Back to the state the session started from (t = 0 for a fresh scene): the bodies, the
        scripted tools on their paths, the mouse's tools let go; playing or paused as before."""
        self.request_seek(self._snapshots[self._start]["time"])

    def request_seek(self, t: float) -> None:
        """Go to time ``t`` (s): done by the stepping thread before its next step (the newest request
        wins), or here when it does not run."""
        if self._thread is not None and self._thread.is_alive():
            self._seek = float(t)
        else:
            self.seek(t)

    def seek(self, t: float) -> None:
        """Go to time ``t`` (s, from the start to as far as the scene has run or beyond): back to the
        nearest kept state before it and step there (a later time: on from here). The mouse's tools
        are let go."""
        self.release()
        self.unpress()
        dt = self.scene.dt
        target = max(self._start, int(round(float(t) / dt)))
        with self._lock:
            self.seeking = True
            try:
                if target < self.scene.steps:
                    kept = max(k for k in self._snapshots if k <= target)
                    rewind(self.scene, self._snapshots[kept])
                while self.scene.steps < target and not self._stop.is_set():
                    self._step_and_keep()
            finally:
                self.seeking = False
                self._epoch += 1

    def _step_and_keep(self) -> None:
        """One step of the scene, its state kept every SNAPSHOT_EVERY s (under the lock). A scalpel's failed cut
        job is said in the panel and the scene steps on (that step was taken; the next strip's job cuts again)."""
        try:
            self.scene.step()
        except CutJobFailed as exc:
            self.error = str(exc)
        k = self.scene.steps
        if k % self._every == 0 and k not in self._snapshots:
            self._snapshots[k] = snapshot(self.scene)
            if len(self._snapshots) > MAX_SNAPSHOTS:  # keep every other one (and the start)
                for j in sorted(self._snapshots)[1::2]:
                    if j != self._start:
                        del self._snapshots[j]
                self._every *= 2

    # ---------------------------------------------------------------- the clock
    def step(self) -> None:
        with self._lock:
            self._step_and_keep()

    def _run(self) -> None:
        self.priority = raise_priority()
        with runtime():  # one BLAS thread while the scene is stepped (see rtfem.threads)
            self._clock()

    def _clock(self) -> None:
        dt = self.scene.dt
        anchor = None  # (wall time, steps, epoch) the schedule counts from
        window_start, window_steps, computes = time.perf_counter(), 0, []
        try:
            while not self._stop.is_set():
                if self._seek is not None:
                    t, self._seek = self._seek, None
                    self.seek(t)
                if not self._playing.is_set():
                    anchor = None
                    self.sim_rate = self.realtime = 0.0
                    window_start, window_steps, computes = time.perf_counter(), 0, []
                    time.sleep(0.01)
                    continue
                now = time.perf_counter()
                if anchor is None or anchor[2] != self._epoch:
                    anchor = (now, self.scene.steps, self._epoch)
                target = anchor[0] + (self.scene.steps - anchor[1]) * dt
                if target - now > 3e-4:
                    time.sleep(min(target - now - 3e-4, 0.01))
                    continue
                if now - target > 0.1:  # cannot keep up: stop owing steps (the panel says the rate)
                    anchor = (now, self.scene.steps, self._epoch)
                c0 = time.perf_counter()
                with self._lock:
                    if not self._playing.is_set():  # paused since the check above
                        continue
                    self._step_and_keep()
                c1 = time.perf_counter()
                computes.append(c1 - c0)
                window_steps += 1
                if c1 - window_start >= 1.0:
                    self.sim_rate = window_steps / (c1 - window_start)
                    self.realtime, self.step_us = self.sim_rate * dt, float(np.median(computes)) * 1e6
                    window_start, window_steps, computes = c1, 0, []
        except Exception as exc:  # shown in the panel; the viewer keeps serving
            self.error = f"{type(exc).__name__}: {exc}"
