"""The viewers' lights and cameras: a first camera for every browser, then each browser's own framed
on the organ beside the panel once it has said its canvas size, and where a point is drawn on it."""

from __future__ import annotations

import threading
import time

import numpy as np

__all__ = ["PANEL_PX", "VIEW", "light_scene", "framing", "frame_client", "project"]

#: the panel's width with its margin at the right of the page (viser's "large" controls), in pixels
PANEL_PX = 400


#: the organ viewer's camera direction from the organ's centre (+z up)
VIEW = (0.1, -0.62, 0.5)


def light_scene(server, centre: np.ndarray, size: float, view=VIEW) -> None:
    """+z up, cheap lights and the first camera looking at ``centre`` from ``size`` times ``view``
    (each browser's own camera is then framed by :func:`frame_client` once it says its size)."""
    sc = server.scene
    sc.set_up_direction("+z")
    # Lights that cost little per pixel: viser's defaults (an environment map sampled at every
    # fragment, cascaded shadow maps drawn every frame) are the most of a frame's work in a
    # browser without a GPU (benchmarks/viewer_browser.py).
    sc.configure_environment_map(hdri=None)
    sc.configure_default_lights(enabled=True, cast_shadow=False)
    sc.add_light_hemisphere("/lights/fill", sky_color=(255, 255, 255), ground_color=(120, 110, 110), intensity=1.5)
    server.initial_camera.look_at = tuple(centre)
    server.initial_camera.position = tuple(centre + size * np.asarray(view, dtype=float))
    server.initial_camera.up = (0.0, 0.0, 1.0)


def framing(centre, radius: float, view, fov: float, width: int, height: int,
            panel: float = PANEL_PX) -> tuple[np.ndarray, np.ndarray]:
    """(camera position, look-at point) for a camera looking along -``view`` (+z up) with vertical
    field of view ``fov`` (rad) on a ``width`` x ``height`` px canvas: a sphere of ``radius`` about
    ``centre`` fits, with a margin, in the part of the canvas left of the panel (``panel`` px at the
    right; a canvas narrower than twice that is used whole), its centre in the middle of that part."""
    v = np.asarray(view, dtype=float)
    v = v / np.linalg.norm(v)
    visible = width - panel if width > 2 * panel else width
    tan_v = np.tan(0.5 * fov)
    tan_fit = min(tan_v, tan_v * visible / height)
    d = 1.08 * radius * np.sqrt(1.0 + tan_fit**2) / tan_fit  # the sphere subtends atan(tan_fit)
    forward = -v
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-6:  # looking straight up or down
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    shift = d * tan_v * (0.5 * (width - visible)) / (0.5 * height)  # the visible part's middle, left of the centre
    look_at = np.asarray(centre, dtype=float) + shift * right
    return look_at + d * v, look_at


def frame_client(client, centre, radius: float, view, timeout: float = 30.0, watch: float = 20.0) -> bool:
    """Frame a newly connected browser's camera (:func:`framing`) once it has said its canvas size
    and field of view; False when it did not within ``timeout`` s (it keeps the initial camera; a
    browser on a loaded machine took over 5 s to say it).

    A camera message the browser sent before the framing reached it puts the first camera back in
    the server's copy, and a browser still setting up its canvas may drop the framing: for
    ``watch`` s a thread sends the framing again whenever the browser reports the first camera
    (a browser on a loaded machine applied the first camera after the framing, and kept it)."""
    cam = client.camera
    t0 = time.perf_counter()
    while cam.update_timestamp == 0.0 or cam.image_width == 0:
        if time.perf_counter() - t0 > timeout:
            return False
        time.sleep(0.05)
    first = np.array(cam.look_at, dtype=float)
    position, look_at = framing(centre, radius, view, cam.fov, cam.image_width, cam.image_height)
    _send_framing(cam, position, look_at)
    if watch > 0:
        old = (np.asarray(centre, dtype=float), first)  # the first camera's look-at, and what the browser first said
        threading.Thread(target=_keep_framed, args=(cam, old, position, look_at, radius, watch),
                         name="rtfem-frame-camera", daemon=True).start()
    return True


def _send_framing(cam, position, look_at) -> float:
    """Set the framed camera on the client; the time it was sent."""
    cam.up_direction = (0.0, 0.0, 1.0)
    # the position first: the client moves it with a transition about its present target, and a
    # target set before it ended up elsewhere (the look-at set last is taken as it is)
    cam.position = tuple(position)
    cam.look_at = tuple(look_at)
    return time.time()


def _keep_framed(cam, old, position, look_at, radius: float, watch: float) -> None:
    """For ``watch`` s, send the framing again whenever the browser reports one of the ``old``
    look-at points after it was sent (see :func:`frame_client`); a look-at of the user's own is left
    alone (it is never one of them to within a thousandth of the organ's radius)."""
    tol = 1e-3 * max(float(radius), 1e-12)  # float32 round-off of the browser's echo is far below this
    sent, t0 = time.time(), time.perf_counter()
    while time.perf_counter() - t0 < watch:
        time.sleep(0.2)
        try:
            stamp, at = cam.update_timestamp, np.asarray(cam.look_at, dtype=float)
            if stamp > sent and min(np.linalg.norm(at - o) for o in old) < tol:
                sent = _send_framing(cam, position, look_at)  # an old message, or the framing dropped
        except Exception:  # the browser went away
            return


def project(client, points) -> np.ndarray:
    """Where ``points`` (k, 3) are drawn on the browser ``client``'s canvas: (k, 2) pixels from its
    top-left corner (a pinhole camera at the client's position, looking at its look-at point, +z up)."""
    cam = client.camera
    p, at = np.asarray(cam.position, dtype=float), np.asarray(cam.look_at, dtype=float)
    f = (at - p) / np.linalg.norm(at - p)
    r = np.cross(f, np.asarray(cam.up_direction, dtype=float))
    r /= np.linalg.norm(r)
    down = np.cross(f, r)
    c = np.atleast_2d(np.asarray(points, dtype=float)) - p
    z = c @ f
    focal = 0.5 * cam.image_height / np.tan(0.5 * cam.fov)
    return np.column_stack([0.5 * cam.image_width + focal * (c @ r) / z, 0.5 * cam.image_height + focal * (c @ down) / z])
