import math

import numpy as np
import pytest

import rtfem as rt


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(E=0.0), "E=0.0 must be"),
        (dict(E=-1e3), "E=-1000.0 must be"),
        (dict(E=math.nan), "E=nan"),
        (dict(nu=0.5), "outside"),
        (dict(nu=-1.0), "outside"),
        (dict(nu=0.7), "outside"),
        (dict(thickness=0.0), "thickness"),
        (dict(density=-5.0), "density"),
        (dict(E="soft"), "not a number"),
    ],
)
def test_nonsense_values_rejected(kwargs, match):
    with pytest.raises(rt.ModelError, match=match):
        rt.Material(**kwargs)


def test_derived_quantities():
    m = rt.Material(E=2.6e5, nu=0.3, thickness=0.002, density=1000)
    assert m.G == pytest.approx(1e5)
    assert m.bending_rigidity == pytest.approx(2.6e5 * 8e-9 / (12 * 0.91))
    C = m.plane_stress()
    assert np.allclose(C, C.T)
    assert C[2, 2] == pytest.approx(m.G)
