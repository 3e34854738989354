"""Devices: where the hand is, and what it feels. The :class:`Device` base (position, force, buttons,
close, a stop reason), a scripted press (:class:`ScriptedDevice`, :class:`Press`), a device behind
two callbacks (:class:`CallbackDevice`) or one shared with another thread (:class:`SharedDevice`,
which the hardware adapters are)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from ... import validate
from ...errors import ModelError

__all__ = ["Device", "ScriptedDevice", "Press", "CallbackDevice", "SharedDevice", "MAILBOX"]

#: SharedDevice's mailbox: position (3, organ frame, m), force on the tool (3, N), forces written
#: (a count the loops advance: the adapters' watchdog reads it), buttons (a bit mask)
MAILBOX = 8


class Device:
    """What a HapticLoop, a Probe's or a tool's loop, and the viewer ask of a device: where the hand
    is (``position(t)``, metres, the organ's frame) and what it feels (``set_force(t, f)``, newtons);
    ``buttons`` (a bit mask, 0 where there are none), ``close()`` (also on leaving a ``with``), and
    ``stop_reason``: None while it renders forces, else why it stopped (the simulation fell
    behind, the device reported an error, it disconnected, it was closed). A user's class with
    ``position`` and ``set_force`` works too; this base gives it the rest."""

    stop_reason: str | None = None

    def position(self, t: float) -> np.ndarray:  # pragma: no cover - every device defines it
        raise NotImplementedError

    def set_force(self, t: float, force: np.ndarray) -> None:  # pragma: no cover - every device defines it
        raise NotImplementedError

    @property
    def buttons(self) -> int:
        """The pressed buttons as a bit mask (bit 0: the first button); 0 without buttons."""
        return 0

    def close(self) -> None:
        """Release the device (no force is rendered after it); closing twice does nothing."""
        if self.stop_reason is None:
            self.stop_reason = "closed"

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ScriptedDevice(Device):
    """A device that follows a script: where the hand is at each time, and a record of the forces
    handed back (``times``, ``forces``).

    Parameters
    ----------
    trajectory : a callable ``t -> (3,)``, the position in metres at time t (s); :meth:`press`
        makes the usual one.
    buttons : a callable ``t -> int``, the buttons held at time t (a bit mask; default none), read
        at the time of the last :meth:`position`.

    Raises
    ------
    ModelError
        ``trajectory`` or ``buttons`` is not callable.
    """

    def __init__(self, trajectory: Callable[[float], np.ndarray], buttons: Callable[[float], int] | None = None) -> None:
        if not callable(trajectory):
            raise ModelError(f"trajectory={validate.show(trajectory)} must be a callable t -> (3,) position")
        if buttons is not None and not callable(buttons):
            raise ModelError(f"buttons={validate.show(buttons)} must be a callable t -> bit mask")
        self.trajectory, self._buttons, self._t = trajectory, buttons, 0.0
        self.forces: list[np.ndarray] = []
        self.times: list[float] = []

    @classmethod
    def press(cls, point, normal, depth: float, duration: float, *, approach: float = 0.002, ramp: float = 0.2,
              release: float = 0.6, repeat: bool = False) -> "ScriptedDevice":
        """A press along the inward normal: from ``approach`` (m) outside the surface point to
        ``depth`` (m) inside over ``ramp * duration``, held until ``release * duration``, backed
        out over ``ramp * duration`` and left outside; ``repeat`` starts again every ``duration``.
        The one scripted press of the CLI, the demo, the examples and the benchmarks."""
        return cls(Press(point, normal, depth, duration, approach, ramp, release, repeat))

    def position(self, t: float) -> np.ndarray:
        self._t = t
        return np.asarray(self.trajectory(t), dtype=float)

    @property
    def buttons(self) -> int:
        return 0 if self._buttons is None else int(self._buttons(self._t))

    def set_force(self, t: float, force: np.ndarray) -> None:
        self.times.append(t)
        self.forces.append(np.array(force))


class Press:
    """The trajectory of :meth:`ScriptedDevice.press`: ``press(t)`` is the probe position (3,) and
    ``press.depth_at(t)`` how far inside the undeformed surface it is (m; negative outside)."""

    def __init__(self, point, normal, depth, duration, approach=0.002, ramp=0.2, release=0.6, repeat=False) -> None:
        self.point = validate.point(point, "point")
        n = validate.vector(normal, "normal", 3)
        if not np.linalg.norm(n) > 0:
            raise ModelError("normal must be a non-zero vector (the surface's outward normal)")
        self.normal = n / np.linalg.norm(n)
        self.depth = validate.number(depth, "depth", "a press depth in m")
        self.duration = validate.positive(duration, "duration", "a time in s")
        self.approach = validate.nonnegative(approach, "approach", "a distance in m")
        self.ramp = validate.in_range(ramp, "ramp", 0.0, 0.5, lo_open=True, what="a fraction of the duration")
        self.release = validate.in_range(release, "release", self.ramp, 1.0 - self.ramp, what="a fraction of the duration")
        self.repeat = validate.flag(repeat, "repeat")

    def depth_at(self, t: float) -> float:
        s = (t % self.duration if self.repeat else t) / self.duration
        if s < self.release:
            level = min(s / self.ramp, 1.0)
        else:
            level = max(0.0, 1.0 - (s - self.release) / self.ramp)
        return -self.approach + (self.depth + self.approach) * level

    def __call__(self, t: float) -> np.ndarray:
        return self.point - self.depth_at(t) * self.normal


class CallbackDevice(Device):
    """A device behind two callables: plug in a real device's driver (or the viewer).

    Parameters
    ----------
    get_position : ``get_position() -> (3,)``, the device's position in metres now.
    set_force : ``set_force(f)``, hands the force (3,) in newtons to the device.

    Raises
    ------
    ModelError
        Either is not callable; a position that is not three finite numbers within 1e6 m, when
        it is read.
    """

    def __init__(self, get_position: Callable[[], np.ndarray], set_force: Callable[[np.ndarray], None]) -> None:
        for name, fn in (("get_position", get_position), ("set_force", set_force)):
            if not callable(fn):
                raise ModelError(f"{name}={validate.show(fn)} must be a callable")
        self._get, self._set = get_position, set_force

    def position(self, t: float) -> np.ndarray:
        return validate.point(self._get(), "the device's position (get_position())")

    def set_force(self, t: float, force: np.ndarray) -> None:
        self._set(force)


class SharedDevice(Device):
    """A device whose position any thread writes (:meth:`move_to`: a device driver's thread, the
    viewer's mouse) and whose force any thread reads (:attr:`force`), through one shared array,
    so a compiled HapticLoop reads and writes it without the GIL.

    Parameters
    ----------
    position : the starting position (3,) in metres.

    Raises
    ------
    ModelError
        A position that is not three finite numbers within 1e6 m (here or in :meth:`move_to`).
    """

    def __init__(self, position=(0.0, 0.0, 0.0)) -> None:
        self.mailbox = np.zeros(MAILBOX)  # see MAILBOX
        self.move_to(position)

    def move_to(self, position) -> None:
        self.mailbox[:3] = validate.point(position, "device position")

    @property
    def force(self) -> np.ndarray:
        """The last force handed to the device (N): what the hand feels."""
        return self.mailbox[3:6].copy()

    def position(self, t: float) -> np.ndarray:
        return self.mailbox[:3].copy()

    def set_force(self, t: float, force: np.ndarray) -> None:
        self.mailbox[3:6] = force
        self.mailbox[6] += 1.0  # a force was written (the compiled loops count it too)

    @property
    def buttons(self) -> int:
        return int(self.mailbox[7])
