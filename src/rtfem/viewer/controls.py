"""The panel's transport: play / pause / restart and a time slider, over a clock that can be
paused, restarted and sent to a time (the scene viewer's :class:`~rtfem.viewer.scene_view.SceneSession`,
the replay's :class:`~rtfem.viewer.replay.Replay`)."""

from __future__ import annotations

import time
from typing import Protocol

__all__ = ["Clock", "Transport"]


class Clock(Protocol):
    """What the transport drives."""

    time: float  # s

    @property
    def playing(self) -> bool: ...

    @property
    def end_time(self) -> float: ...  # s: the slider's end (it grows when the clock runs past it)

    def play(self) -> None: ...

    def pause(self) -> None: ...

    def restart(self) -> None: ...  # back to t = 0, playing or paused as before

    def request_seek(self, t: float) -> None: ...  # go to t (s), playing or paused as before


class Transport:
    """Play, pause and restart buttons and a time slider in a viser panel, over a :class:`Clock`.
    :meth:`refresh` (the frame thread's, a few times a second) moves the slider with the clock; a
    slider moved in the browser sends the clock there."""

    def __init__(self, gui, clock: Clock, *, step: float) -> None:
        self.clock = clock
        self.buttons = gui.add_button_group("playback", ("play", "pause", "restart"))
        self.slider = gui.add_slider("time (s)", min=0.0, max=max(float(clock.end_time), step), step=step,
                                     initial_value=0.0)
        self.seeks = 0
        self._touched = 0.0  # when a browser last moved the slider (monotonic s)

        @self.buttons.on_click
        def _(event) -> None:
            {"play": clock.play, "pause": clock.pause, "restart": clock.restart}[event.target.value]()

        @self.slider.on_update
        def _(event) -> None:
            if event.client is None:  # set by refresh(): the clock's own time
                return
            self.seeks += 1
            self._touched = time.monotonic()
            clock.request_seek(float(self.slider.value))

    #: s after a browser moved the slider during which refresh leaves it where the user put it
    HOLD = 1.0

    def refresh(self) -> None:
        if time.monotonic() - self._touched < self.HOLD:  # not under the user's hand (or a box being typed in)
            return
        t = float(self.clock.time)
        if t > self.slider.max:
            self.slider.max = t
        self.slider.value = round(t / self.slider.step) * self.slider.step
