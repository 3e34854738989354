"""The map from a haptic device's frame to the organ's, with a clutch."""

from __future__ import annotations

import numpy as np

from ... import validate
from ...errors import ModelError

__all__ = ["Workspace"]


def _rotation(value) -> np.ndarray:
    R = np.eye(3) if value is None else validate.real_array(value, "rotation", 2)
    if R.shape != (3, 3) or np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ModelError("rotation must be a 3x3 rotation matrix (orthonormal columns, determinant +1): its columns "
                         "are the device's axes in the organ's frame")
    return np.array(R, dtype=float)


class Workspace:
    """Where the device's hand is in the organ's frame: x_organ = offset + scale R x_device (m, the
    device's position already in metres in its own frame); a force goes back unscaled and rotated,
    f_device = R^T f_organ. A clutch button re-indexes it: while held, the tool stays where it was
    (and no force is rendered) whatever the hand does; on release the offset has moved so that the
    tool goes on from there (the hand can be brought back to the middle of the device's reach).

    Parameters
    ----------
    scale : organ metres per device metre (> 0): 2 makes a 10 cm hand motion a 20 cm tool motion.
    rotation : (3, 3), the device's axes in the organ's frame (its columns); default identity.
    offset : (3,) the organ-frame point the device's origin maps to (m).
    clutch : the button (0-based) that clutches, or None.

    Raises
    ------
    ModelError
        A scale that is not a positive finite number, a rotation that is not one, an offset that
        is not a point, a clutch that is not a button index 0..31.
    """

    def __init__(self, scale: float = 1.0, rotation=None, offset=(0.0, 0.0, 0.0), *, clutch: int | None = None) -> None:
        self.scale = validate.positive(scale, "scale", "organ metres per device metre")
        self.rotation = _rotation(rotation)
        self.offset = np.array(validate.point(offset, "offset"), dtype=float)
        self.clutch = None if clutch is None else validate.count(clutch, "clutch", 0, 31, what="a button index")

    @classmethod
    def fit(cls, device_box, organ_bounds, *, rotation=None, fill: float = 0.8, clutch: int | None = None) -> "Workspace":
        """The default map: the device's usable workspace centred on the organ's top (the centre of
        its bounding box's upper face, +z up), scaled so that the organ's extent fills ``fill`` of
        the workspace along the tightest axis.

        Parameters
        ----------
        device_box : (lo (3,), hi (3,)), the usable workspace in the device's frame (m).
        organ_bounds : (lo (3,), hi (3,)), the organ's bounding box (m), e.g. ``mesh.bounds()``.
        rotation, clutch : as the constructor.
        fill : the fraction of the workspace the organ fills, 0 < fill <= 1.

        Returns
        -------
        Workspace

        Raises
        ------
        ModelError
            Boxes that are not (lo, hi) points with lo < hi, a fill outside (0, 1].
        """
        R = _rotation(rotation)
        dlo, dhi = (np.asarray(validate.point(p, "device_box"), dtype=float) for p in _pair(device_box, "device_box"))
        olo, ohi = (np.asarray(validate.point(p, "organ_bounds"), dtype=float) for p in _pair(organ_bounds, "organ_bounds"))
        if not (np.all(dhi > dlo) and np.all(ohi > olo)):
            raise ModelError("device_box and organ_bounds must be (lo, hi) with lo < hi on every axis")
        fill = validate.in_range(fill, "fill", 0.0, 1.0, lo_open=True, what="a fraction of the workspace")
        reach = np.abs(R @ (dhi - dlo))  # the workspace's extent along the organ's axes, at scale 1
        scale = float(np.max((ohi - olo) / (fill * reach)))
        top = np.array([(olo[0] + ohi[0]) / 2, (olo[1] + ohi[1]) / 2, ohi[2]])
        return cls(scale, R, top - scale * R @ ((dlo + dhi) / 2), clutch=clutch)

    def to_organ(self, x_device) -> np.ndarray:
        """x_organ (3,) of a device position (m, the device's frame)."""
        return self.offset + self.scale * self.rotation @ np.asarray(x_device, dtype=float)

    def force_to_device(self, f_organ) -> np.ndarray:
        """The force (N) on the device's axes of a force in the organ's frame."""
        return self.rotation.T @ np.asarray(f_organ, dtype=float)

    def packed(self) -> np.ndarray:
        """(14,) scale, R (row-major), offset, the clutch's button mask (0: none): the servo's layout
        (:mod:`rtfem.interaction.devices.servo`)."""
        mask = 0.0 if self.clutch is None else float(1 << self.clutch)
        return np.concatenate([[self.scale], self.rotation.ravel(), self.offset, [mask]])

    def __repr__(self) -> str:
        return (f"Workspace(scale={self.scale:g}, offset={np.round(self.offset, 6).tolist()}, "
                f"clutch={self.clutch})")


def _pair(value, name: str):
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ModelError(f"{name}={validate.show(value)} must be (lo, hi): two points")
    return value
