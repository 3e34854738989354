"""The flat shell triangle: membrane with drilling rotations + DKT bending (paper section 2).

Each triangle carries 6 dof per node, ordered ``(ux, uy, uz, rx, ry, rz)`` in the global
frame. In the element's local frame (x along edge 1-2, z along the normal) the 18x18
stiffness splits into

* membrane action (Eq. 1) on ``(u, v, theta_z)``: Felippa's optimal triangle OPT with
  drilling freedoms (C. A. Felippa, "A study of optimal membrane triangles with drilling
  freedoms", CMAME 192 (2003) 2125-2168), K = K_basic + K_higher-order, with the optimal
  parameters alpha_b = 3/2, beta_1..9 = (1, 2, 1, 0, 1, -1, -1, -1, -2) and
  beta_0 = max((1 - 4 nu^2) / 2, 0.01). A plain constant-strain triangle with a small
  fictitious drilling spring is available as ``membrane="cst"`` for comparison only.
* bending action (Eq. 2) on ``(w, theta_x, theta_y)``: the Discrete Kirchhoff Triangle
  (J.-L. Batoz, K.-J. Bathe, L.-W. Ho, "A study of three-node triangular plate bending
  elements", IJNME 15 (1980) 1771-1812), integrated exactly with the 3-point mid-side rule.

The combined 18x18 local stiffness is turned into the global frame with the block-diagonal
rotation of the paper's "Transformations" paragraph, K_e = T^T k_e T. Everything is
batched over all elements with numpy: no Python loop per element.
"""

from __future__ import annotations

import numpy as np

from .material import Material
from .rotations import cross_matrices

__all__ = [
    "local_frames",
    "membrane_opt",
    "membrane_cst",
    "bending_dkt",
    "local_stiffness",
    "element_stiffness",
    "element_mass",
    "MEMBRANES",
]

MEMBRANES = ("opt", "cst")

#: Felippa's optimal parameters of the OPT template (2003, Eq. 42).
_OPT_ALPHA_B = 1.5
_OPT_BETA = np.array([1.0, 2.0, 1.0, 0.0, 1.0, -1.0, -1.0, -1.0, -2.0])

# local dof positions inside the 18-vector (per node: u v w rx ry rz)
_MEMBRANE_DOFS = np.array([0, 1, 5, 6, 7, 11, 12, 13, 17])
_BENDING_DOFS = np.array([2, 3, 4, 8, 9, 10, 14, 15, 16])


def local_frames(coords: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local frames of triangles.

    Parameters
    ----------
    coords : (E, 3, 3) corner coordinates.

    Returns
    -------
    R : (E, 3, 3) rotation, rows are the local axes e1 (along edge 1-2), e2, e3 (normal)
        expressed in global coordinates, so that x_local = R @ x_global.
    xy : (E, 3, 2) corner coordinates in the local frame (corner 1 at the origin).
    area : (E,) triangle areas.
    """
    p1, p2, p3 = coords[:, 0], coords[:, 1], coords[:, 2]
    a = p2 - p1
    b = p3 - p1
    n = np.cross(a, b)
    twice_area = np.linalg.norm(n, axis=1)
    e1 = a / np.linalg.norm(a, axis=1)[:, None]
    e3 = n / twice_area[:, None]
    e2 = np.cross(e3, e1)
    R = np.stack([e1, e2, e3], axis=1)
    rel = coords - p1[:, None, :]
    xy = np.einsum("eij,ekj->eki", R[:, :2, :], rel)
    return R, xy, 0.5 * twice_area


def _diffs(xy: np.ndarray):
    x, y = xy[..., 0], xy[..., 1]
    x1, x2, x3 = x[:, 0], x[:, 1], x[:, 2]
    y1, y2, y3 = y[:, 0], y[:, 1], y[:, 2]
    return x1, x2, x3, y1, y2, y3


def membrane_opt(xy: np.ndarray, area: np.ndarray, material: Material) -> np.ndarray:
    """OPT membrane stiffness (E, 9, 9), dofs per node ``(u, v, theta_z)``.

    K = V B^T E B + 3/4 beta_0 V T^T (Q4^T E_nat Q4 + Q5^T E_nat Q5 + Q6^T E_nat Q6) T
    (Felippa 2003, Eq. 22, 29-32), with V = A t, E_nat = Te^T E Te.
    """
    x1, x2, x3, y1, y2, y3 = _diffs(xy)
    x12, x23, x31 = x1 - x2, x2 - x3, x3 - x1
    y12, y23, y31 = y1 - y2, y2 - y3, y3 - y1
    x21, x32, x13 = -x12, -x23, -x31
    y21, y32, y13 = -y12, -y23, -y31
    A = area
    ab = _OPT_ALPHA_B
    ne = xy.shape[0]
    z = np.zeros(ne)

    # B = L^T / V: the mean-strain (basic) strain-displacement matrix, Felippa Eq. 22
    B = np.empty((ne, 3, 9))
    B[:, :, 0] = np.stack([y23, z, x32], axis=1)
    B[:, :, 1] = np.stack([z, x32, y23], axis=1)
    B[:, :, 2] = np.stack([y23 * (y13 - y21), x32 * (x31 - x12), 2 * (x31 * y13 - x12 * y21)], axis=1) * (ab / 6)
    B[:, :, 3] = np.stack([y31, z, x13], axis=1)
    B[:, :, 4] = np.stack([z, x13, y31], axis=1)
    B[:, :, 5] = np.stack([y31 * (y21 - y32), x13 * (x12 - x23), 2 * (x12 * y21 - x23 * y32)], axis=1) * (ab / 6)
    B[:, :, 6] = np.stack([y12, z, x21], axis=1)
    B[:, :, 7] = np.stack([z, x21, y12], axis=1)
    B[:, :, 8] = np.stack([y12 * (y32 - y13), x21 * (x23 - x31), 2 * (x23 * y32 - x31 * y13)], axis=1) * (ab / 6)
    B /= (2 * A)[:, None, None]

    # hierarchical (deviatoric) corner rotations: theta_i minus the CST mean rotation, Eq. 16
    row = np.stack([x32, y32, z, x13, y13, z, x21, y21, z], axis=1) / (4 * A)[:, None]
    Tth = np.repeat(row[:, None, :], 3, axis=1)
    Tth[:, [0, 1, 2], [2, 5, 8]] = 1.0

    # strain-gauge rosette transformation: Cartesian strains from natural side strains, Eq. 12
    L21 = x21**2 + y21**2
    L32 = x32**2 + y32**2
    L13 = x13**2 + y13**2
    Te = np.empty((ne, 3, 3))
    Te[:, :, 0] = np.stack([y23 * y13, x23 * x13, y23 * x31 + x32 * y13], axis=1) * L21[:, None]
    Te[:, :, 1] = np.stack([y31 * y21, x31 * x21, y31 * x12 + x13 * y21], axis=1) * L32[:, None]
    Te[:, :, 2] = np.stack([y12 * y32, x12 * x32, y12 * x23 + x21 * y32], axis=1) * L13[:, None]
    Te /= (4 * A**2)[:, None, None]

    # natural corner strains from deviatoric rotations, Eq. 29 (beta index patterns of Q1..Q3)
    b = _OPT_BETA
    pat = (
        np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]]),
        np.array([[8, 6, 7], [2, 0, 1], [5, 3, 4]]),
        np.array([[4, 5, 3], [7, 8, 6], [1, 2, 0]]),
    )
    inv_len = np.stack([1 / L21, 1 / L32, 1 / L13], axis=1) * (2 * A / 3)[:, None]  # (E, 3)
    Q = [b[p][None, :, :] * inv_len[:, :, None] for p in pat]
    Qm = [(Q[0] + Q[1]) / 2, (Q[1] + Q[2]) / 2, (Q[2] + Q[0]) / 2]

    Em = material.plane_stress()
    V = A * material.thickness
    Kb = V[:, None, None] * _triple(B, Em)
    Enat = _triple(Te, Em)
    S = sum(_triple(q, Enat) for q in Qm)
    beta0 = max(0.5 * (1.0 - 4.0 * material.nu**2), 0.01)
    Kh = (0.75 * beta0) * V[:, None, None] * _triple(Tth, S)
    return Kb + Kh


def _triple(B: np.ndarray, D: np.ndarray) -> np.ndarray:
    """B^T D B per element (E, n, n) for B (E, k, n) and D (k, k) or (E, k, k), by batched matmul
    (einsum's three-operand loop took 5x longer)."""
    return np.swapaxes(B, 1, 2) @ (D @ B)


def membrane_cst(
    xy: np.ndarray, area: np.ndarray, material: Material, drilling: float = 1e-3
) -> np.ndarray:
    """Constant-strain triangle + fictitious drilling spring (E, 9, 9), dofs ``(u, v, theta_z)``.

    Not a default: it locks in in-plane bending. The drilling spring is ``drilling`` times
    the mean membrane diagonal times the area, on each corner rotation.
    """
    x1, x2, x3, y1, y2, y3 = _diffs(xy)
    ne = xy.shape[0]
    B = np.zeros((ne, 3, 6))
    b = np.stack([y2 - y3, y3 - y1, y1 - y2], axis=1)
    c = np.stack([x3 - x2, x1 - x3, x2 - x1], axis=1)
    B[:, 0, 0::2] = b
    B[:, 1, 1::2] = c
    B[:, 2, 0::2] = c
    B[:, 2, 1::2] = b
    B /= (2 * area)[:, None, None]
    V = area * material.thickness
    k6 = V[:, None, None] * _triple(B, material.plane_stress())
    K = np.zeros((ne, 9, 9))
    tr = np.array([0, 1, 3, 4, 6, 7])
    K[:, tr[:, None], tr[None, :]] = k6
    kd = drilling * np.einsum("eii->e", k6) / 6.0 * area
    for i in (2, 5, 8):
        K[:, i, i] = kd
    return K


# quadratic 6-node shape functions on the triangle and their derivatives,
# corners 1-3 at (0,0), (1,0), (0,1); mid-sides 4 (2-3), 5 (3-1), 6 (1-2)
def _n6_derivatives(xi: float, eta: float) -> tuple[np.ndarray, np.ndarray]:
    l1 = 1.0 - xi - eta
    dxi = np.array([1 - 4 * l1, 4 * xi - 1, 0.0, 4 * eta, -4 * eta, 4 * (l1 - xi)])
    deta = np.array([1 - 4 * l1, 0.0, 4 * eta - 1, 4 * xi, 4 * (l1 - eta), -4 * xi])
    return dxi, deta


def _dkt_coefficients(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hx, Hy as linear combinations of N1..N6: (E, 9, 6) each (Batoz et al. 1980)."""
    x1, x2, x3, y1, y2, y3 = _diffs(xy)
    # sides k = 4, 5, 6 <-> (i, j) = (2, 3), (3, 1), (1, 2); x_ij = x_i - x_j
    xs = np.stack([x2 - x3, x3 - x1, x1 - x2], axis=1)
    ys = np.stack([y2 - y3, y3 - y1, y1 - y2], axis=1)
    l2 = xs**2 + ys**2
    a = -xs / l2
    b = 0.75 * xs * ys / l2
    c = (0.25 * xs**2 - 0.5 * ys**2) / l2
    d = -ys / l2
    e = (0.25 * ys**2 - 0.5 * xs**2) / l2
    ne = xy.shape[0]
    Hx = np.zeros((ne, 9, 6))
    Hy = np.zeros((ne, 9, 6))
    # corner i (0-based) with the side that starts at it (m) and the side that ends at it (k)
    # corner 1: m = 6 (1-2), k = 5 (3-1); corner 2: m = 4, k = 6; corner 3: m = 5, k = 4
    for i, (m, k) in enumerate(((2, 1), (0, 2), (1, 0))):
        r = 3 * i
        nm, nk = 3 + m, 3 + k  # columns of N4..N6
        Hx[:, r, nm] = 1.5 * a[:, m]
        Hx[:, r, nk] = -1.5 * a[:, k]
        Hx[:, r + 1, nm] = b[:, m]
        Hx[:, r + 1, nk] = b[:, k]
        Hx[:, r + 2, i] = 1.0
        Hx[:, r + 2, nm] = -c[:, m]
        Hx[:, r + 2, nk] = -c[:, k]
        Hy[:, r, nm] = 1.5 * d[:, m]
        Hy[:, r, nk] = -1.5 * d[:, k]
        Hy[:, r + 1, i] = -1.0
        Hy[:, r + 1, nm] = e[:, m]
        Hy[:, r + 1, nk] = e[:, k]
        Hy[:, r + 2, nm] = -b[:, m]
        Hy[:, r + 2, nk] = -b[:, k]
    return Hx, Hy


def dkt_curvature_matrix(xy: np.ndarray, xi: float, eta: float) -> np.ndarray:
    """DKT curvature-displacement matrix (E, 3, 9) at natural point (xi, eta).

    kappa = [beta_x,x ; beta_y,y ; beta_x,y + beta_y,x] with beta_x = theta_y, beta_y = -theta_x
    at the corners (right-handed rotations theta about the local axes).
    """
    Hx, Hy = _dkt_coefficients(xy)
    dxi, deta = _n6_derivatives(xi, eta)
    x1, x2, x3, y1, y2, y3 = _diffs(xy)
    x21, x31, y21, y31 = x2 - x1, x3 - x1, y2 - y1, y3 - y1
    det = x21 * y31 - x31 * y21  # 2A
    hx_xi, hx_eta = Hx @ dxi, Hx @ deta
    hy_xi, hy_eta = Hy @ dxi, Hy @ deta
    # d/dx = (y31 d/dxi - y21 d/deta) / det ; d/dy = (-x31 d/dxi + x21 d/deta) / det
    hx_x = (y31[:, None] * hx_xi - y21[:, None] * hx_eta) / det[:, None]
    hx_y = (-x31[:, None] * hx_xi + x21[:, None] * hx_eta) / det[:, None]
    hy_x = (y31[:, None] * hy_xi - y21[:, None] * hy_eta) / det[:, None]
    hy_y = (-x31[:, None] * hy_xi + x21[:, None] * hy_eta) / det[:, None]
    return np.stack([hx_x, hy_y, hx_y + hy_x], axis=1)


_MIDSIDE = ((0.5, 0.0), (0.5, 0.5), (0.0, 0.5))


def bending_dkt(xy: np.ndarray, area: np.ndarray, material: Material) -> np.ndarray:
    """DKT bending stiffness (E, 9, 9), dofs per node ``(w, theta_x, theta_y)``.

    B is linear in (xi, eta), so B^T D B is quadratic and the mid-side rule is exact.
    """
    Db = material.plane_stress() * (material.thickness**3 / 12.0)
    K = np.zeros((xy.shape[0], 9, 9))
    for xi, eta in _MIDSIDE:
        Bk = dkt_curvature_matrix(xy, xi, eta)
        K += _triple(Bk, Db)
    return K * (area / 3.0)[:, None, None]


def local_stiffness(xy: np.ndarray, area: np.ndarray, material: Material, membrane: str = "opt") -> np.ndarray:
    """The 18x18 local element stiffness (E, 18, 18), dofs per node ``(u, v, w, rx, ry, rz)``."""
    if membrane == "opt":
        km = membrane_opt(xy, area, material)
    elif membrane == "cst":
        km = membrane_cst(xy, area, material)
    else:
        raise ValueError(f"membrane must be one of {MEMBRANES}, got {membrane!r}")
    kb = bending_dkt(xy, area, material)
    K = np.zeros((xy.shape[0], 18, 18))
    K[:, _MEMBRANE_DOFS[:, None], _MEMBRANE_DOFS[None, :]] = km
    K[:, _BENDING_DOFS[:, None], _BENDING_DOFS[None, :]] = kb
    return K


def to_global(K_local: np.ndarray, R: np.ndarray) -> np.ndarray:
    """K_e = T^T k_e T with T = blockdiag(R, R, R, R, R, R) (paper, "Transformations"), block by block:
    each 3-column block of k_e times R, then each 3-row block of that times R^T (batched matmul
    without T's zeros: half the time of T^T k_e T, a third of the 5-index einsum)."""
    E = K_local.shape[0]
    KT = (K_local.reshape(E, 108, 3) @ R).reshape(E, 18, 18)
    return (np.swapaxes(R, 1, 2)[:, None] @ KT.reshape(E, 6, 3, 18)).reshape(E, 18, 18)


def element_stiffness(coords: np.ndarray, material: Material, membrane: str = "opt") -> np.ndarray:
    """Global-frame element stiffness matrices (E, 18, 18) for corner coordinates (E, 3, 3)."""
    R, xy, area = local_frames(coords)
    return to_global(local_stiffness(xy, area, material, membrane), R)


def element_mass(area: np.ndarray, material: Material, rotary_inertia: bool = False) -> np.ndarray:
    """Lumped nodal masses (E, 6): rho t A / 3 on each translation of each corner.

    Rotations are massless unless ``rotary_inertia``: then each rotation carries
    rho t^3/12 * A/3 (isotropic, so it is the same in every frame).
    """
    m = material.density * material.thickness * area / 3.0
    out = np.zeros((area.shape[0], 6))
    out[:, :3] = m[:, None]
    if rotary_inertia:
        out[:, 3:] = (m * material.thickness**2 / 12.0)[:, None]
    return out


# ---------------------------------------------------------------------------------------------
# corotational (geometrically nonlinear) triangle
#
# The element frame follows the deformed nodes (e1 along side 1-2, e3 the normal: the same
# side-aligned frame as :func:`local_frames`); the linear 18x18 local stiffness acts on the
# deformational dofs measured in it (Rankin & Brogan 1986; Felippa & Haugen, CMAME 194 (2005)
# 2285-2335): local translations of corners 2 and 3 relative to corner 1, and corner rotations
# log(R_e Q_i R0^T), the rotation vector of the nodal rotation Q_i relative to the rotation of
# the element frame from R0 to R_e (Felippa & Haugen's choice; its skew part axial(skew(.)),
# sin(theta) n, equal to it up to O(theta^3), softens past 45 degrees and turns back past 90, which
# let a pulled vertex's triads run away: a vertex of the shell liver pulled 2 cm stalled at 1.81
# cm with them, and goes through with the rotation vector at 46 degrees).
# The energy is 1/2 d^T k d; its gradient and exact Hessian come from second-order forward
# differentiation of d (:class:`_Jet`), with the nodal rotations varied by spins w_i
# (Q_i <- exp([w_i]x) Q_i): the consistent tangent, so Newton converges quadratically.


class _Jet:
    """Batched scalars with their gradient and Hessian over n variables (value (E,), g (E, n),
    h (E, n, n)): second-order forward differentiation of + - * / and sqrt."""

    __slots__ = ("v", "g", "h")

    def __init__(self, v, g, h):
        self.v, self.g, self.h = v, g, h

    @classmethod
    def variable(cls, v: np.ndarray, index: int, n: int) -> "_Jet":
        g = np.zeros((v.shape[0], n))
        g[:, index] = 1.0
        return cls(v, g, np.zeros((v.shape[0], n, n)))

    def __add__(self, o):
        if isinstance(o, _Jet):
            return _Jet(self.v + o.v, self.g + o.g, self.h + o.h)
        return _Jet(self.v + o, self.g, self.h)

    __radd__ = __add__

    def __neg__(self):
        return _Jet(-self.v, -self.g, -self.h)

    def __sub__(self, o):
        return self + (-o)

    def __rsub__(self, o):
        return (-self) + o

    def __mul__(self, o):
        if isinstance(o, _Jet):
            ga, gb = self.g, o.g
            outer = ga[:, :, None] * gb[:, None, :]
            h = self.v[:, None, None] * o.h + o.v[:, None, None] * self.h + outer + outer.transpose(0, 2, 1)
            return _Jet(self.v * o.v, self.v[:, None] * gb + o.v[:, None] * ga, h)
        o = np.asarray(o)
        return _Jet(self.v * o, self.g * o[..., None], self.h * o[..., None, None])

    __rmul__ = __mul__

    def _chain(self, f, d1, d2) -> "_Jet":
        g = d1[:, None] * self.g
        h = d1[:, None, None] * self.h + d2[:, None, None] * self.g[:, :, None] * self.g[:, None, :]
        return _Jet(f, g, h)

    def sqrt(self) -> "_Jet":
        f = np.sqrt(self.v)
        return self._chain(f, 0.5 / f, -0.25 / f**3)

    def reciprocal(self) -> "_Jet":
        f = 1.0 / self.v
        return self._chain(f, -f * f, 2 * f**3)

    def __truediv__(self, o):
        return self * (o.reciprocal() if isinstance(o, _Jet) else 1.0 / np.asarray(o))

    def atan_ratio(self) -> "_Jet":
        """atan(sqrt(v)) / sqrt(v) of v >= 0 (1 at 0), with its derivatives: the series below
        v = 0.05, the closed forms above."""
        f, d1, d2 = atan_ratio(self.v)
        return self._chain(f, d1, d2)


def atan_ratio(v: np.ndarray):
    """G(v) = atan(sqrt(v)) / sqrt(v) and its first two derivatives, for v >= 0 (arrays): the
    closed forms G' = (1/(1+v) - G) / 2v, G'' = -(1/(1+v)^2 + 3 G') / 2v, and for v < 0.05 the
    series sum (-v)^k / (2k+1) (16 terms: round-off accurate, where the closed forms cancel)."""
    v = np.asarray(v, float)
    small = v < 0.05
    vs = np.where(small, v, 0.0)
    f = np.zeros_like(v)
    d1 = np.zeros_like(v)
    d2 = np.zeros_like(v)
    for k in range(16):
        c = (-1.0) ** k / (2 * k + 1)
        f += c * vs**k
        if k >= 1:
            d1 += c * k * vs ** (k - 1)
        if k >= 2:
            d2 += c * k * (k - 1) * vs ** (k - 2)
    vb = np.where(small, 1.0, v)
    rb = np.sqrt(vb)
    fb = np.arctan(rb) / rb
    g1 = (1.0 / (1.0 + vb) - fb) / (2.0 * vb)
    g2 = -(1.0 / (1.0 + vb) ** 2 + 3.0 * g1) / (2.0 * vb)
    return np.where(small, f, fb), np.where(small, d1, g1), np.where(small, d2, g2)


def _rotation_vector(y):
    """The rotation vector theta n (log map) of a rotation A from y = (s, c) (jets or arrays):
    s = axial(skew(A)) = sin(theta) n, c = (tr A - 1) / 2 = cos(theta), as
    theta n = 2 G(v) s / (r + c), r = sqrt(|s|^2 + c^2) (1 on rotations), v = |s|^2 / (r + c)^2
    (tan^2(theta/2)): smooth from theta = 0 (where theta / sin(theta) is 0/0) to below 180
    degrees, and a smooth function of (s, c) off the rotations too, so that its derivatives
    composed with those of s and c are those of the rotation vector."""
    s, c = y[:3], y[3]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # a diverged iterate: NaN, refused by the solver
        u = _jdot(s, s)
        den = (u + c * c).sqrt() + c if isinstance(c, _Jet) else np.sqrt(u + c * c) + c
        v = u / (den * den)
        G = v.atan_ratio() if isinstance(v, _Jet) else atan_ratio(v)[0]
        k = 2.0 * G / den
        return [k * si for si in s]


def _jdot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _jcross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


_SPIN = cross_matrices(np.eye(3))  # [e_k]x, (3, 3, 3)
_SPIN2 = 0.5 * (np.einsum("lpq,mqs->lmps", _SPIN, _SPIN) + np.einsum("mpq,lqs->lmps", _SPIN, _SPIN))
_AXIAL = ((2, 1), (0, 2), (1, 0))  # axial(skew(A))_c = (A[p, q] - A[q, p]) / 2

# the 15 differentiation variables z = (a, b, w_1, w_2, w_3) (a = x2 - x1, b = x3 - x1, w_i the
# corner spins) -> the 18 element dofs (x_i, w_i per corner): d/d(dofs) = d/dz @ _P
_P = np.zeros((15, 18))
for _j in range(3):
    _P[_j, [_j, 6 + _j]] = (-1.0, 1.0)
    _P[3 + _j, [_j, 12 + _j]] = (-1.0, 1.0)
    for _i in range(3):
        _P[6 + 3 * _i + _j, 6 * _i + 3 + _j] = 1.0


class CorotationalTriangles:
    """The corotational shell triangles of one mesh: the undeformed frames, local corner
    coordinates and linear local stiffnesses, kept once; :meth:`evaluate` gives the element
    forces, consistent tangents and energies of a deformed configuration."""

    def __init__(self, coords: np.ndarray, material: Material, membrane: str = "opt") -> None:
        self.R0, xy, area = local_frames(coords)
        self.x2, self.x3, self.y3 = xy[:, 1, 0], xy[:, 2, 0], xy[:, 2, 1]
        self.k = local_stiffness(xy, area, material, membrane)

    def deformational(self, x: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """The local deformational dofs d (E, 18) of corners x (E, 3, 3) with rotations Q (E, 3, 3, 3)."""
        R, _, _ = local_frames(x)
        d = np.zeros((x.shape[0], 18))
        a, b = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
        d[:, 6] = np.linalg.norm(a, axis=1) - self.x2
        d[:, 12] = np.einsum("ej,ej->e", R[:, 0], b) - self.x3
        d[:, 13] = np.einsum("ej,ej->e", R[:, 1], b) - self.y3
        for i, A in enumerate(self._relative(R, Q)):
            y = [0.5 * (A[:, p, q] - A[:, q, p]) for p, q in _AXIAL] + [0.5 * (np.trace(A, axis1=1, axis2=2) - 1.0)]
            d[:, 6 * i + 3:6 * i + 6] = np.stack(_rotation_vector(y), axis=1)
        return d

    def local_rotations(self, x: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """The angles (E, 3), in degrees, of each corner's rotation relative to the element frame
        (R Q_i R0^T), whose rotation vector the element takes as its rotational deformation: exact
        up to 180 degrees, where the axis flips (a turn beyond is measured as a smaller one the
        other way)."""
        R, _, _ = local_frames(x)
        return np.stack([np.degrees(np.arccos(np.clip((np.trace(A, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
                         for A in self._relative(R, Q)], axis=1)

    def _relative(self, R: np.ndarray, Q: np.ndarray):
        """Each corner's rotation relative to the element frame, R Q_i R0^T (E, 3, 3), for the
        deformed frames R (E, 3, 3) and corner rotations Q (E, 3, 3, 3)."""
        return (R @ Q[:, i] @ self.R0.transpose(0, 2, 1) for i in range(3))

    def energy(self, x: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Strain energy per element (E,)."""
        d = self.deformational(x, Q)
        return 0.5 * np.einsum("ei,eij,ej->e", d, self.k, d)

    def evaluate(self, x: np.ndarray, Q: np.ndarray, tangent: bool = True):
        """Element forces (E, 18) (node-major: force, then moment about the spin axes), the
        consistent tangents (E, 18, 18) (None unless ``tangent``) and energies (E,), for deformed
        corner positions x (E, 3, 3) and corner rotations Q (E, 3, 3, 3)."""
        E = x.shape[0]
        a0, b0 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
        a = [_Jet.variable(a0[:, j], j, 6) for j in range(3)]
        b = [_Jet.variable(b0[:, j], 3 + j, 6) for j in range(3)]
        la = _jdot(a, a).sqrt()
        e1 = [c / la for c in a]
        n = _jcross(a, b)
        ln = _jdot(n, n).sqrt()
        e3 = [c / ln for c in n]
        e2 = _jcross(e3, e1)
        rows = (e1, e2, e3)
        Rv = np.stack([np.stack([c.v for c in r], 1) for r in rows], 1)  # (E, 3, 3)
        Rg = np.stack([np.stack([c.g for c in r], 1) for r in rows], 1)  # (E, 3, 3, 6)
        Rh = np.stack([np.stack([c.h for c in r], 1) for r in rows], 1)  # (E, 3, 3, 6, 6)
        trans = {6: la - self.x2, 12: _jdot(e1, b) - self.x3, 13: _jdot(e2, b) - self.y3}

        d = np.zeros((E, 18))
        Jz = np.zeros((E, 18, 15))
        for row, jet in trans.items():
            d[:, row] = jet.v
            Jz[:, row, :6] = jet.g
        rot = []
        RX = np.einsum("epq,lqr->eprl", Rv, _SPIN)  # R [e_l]x
        for i in range(3):
            C = Q[:, i] @ self.R0.transpose(0, 2, 1)
            A = Rv @ C
            dA_ab = np.einsum("epqk,eqs->epsk", Rg, C)
            dA_w = np.einsum("eprl,ers->epsl", RX, C)
            w = slice(6 + 3 * i, 9 + 3 * i)
            # y = (axial(skew(A)), (tr A - 1)/2) and its gradient Jy over z; d = theta(y)
            y = np.zeros((E, 4))
            Jy = np.zeros((E, 4, 15))
            for c, (p, q) in enumerate(_AXIAL):
                y[:, c] = 0.5 * (A[:, p, q] - A[:, q, p])
                Jy[:, c, :6] = 0.5 * (dA_ab[:, p, q] - dA_ab[:, q, p])
                Jy[:, c, w] = 0.5 * (dA_w[:, p, q] - dA_w[:, q, p])
            y[:, 3] = 0.5 * (np.trace(A, axis1=1, axis2=2) - 1.0)
            Jy[:, 3, :6] = 0.5 * np.einsum("eppk->ek", dA_ab)
            Jy[:, 3, w] = 0.5 * np.einsum("eppl->el", dA_w)
            theta = _rotation_vector([_Jet.variable(y[:, j], j, 4) for j in range(4)])
            r = slice(6 * i + 3, 6 * i + 6)
            d[:, r] = np.stack([t.v for t in theta], axis=1)
            Dt = np.stack([t.g for t in theta], axis=1)  # (E, 3, 4)
            Jz[:, r] = Dt @ Jy
            rot.append((C, w, Jy, Dt, np.stack([t.h for t in theta], axis=1)))
        g = np.einsum("eij,ej->ei", self.k, d)  # local forces k d
        energy = 0.5 * np.einsum("ei,ei->e", g, d)
        J = Jz @ _P
        forces = np.einsum("eim,ei->em", J, g)
        if not tangent:
            return forces, None, energy

        return forces, self._tangent(g, J, forces, trans, rot, Rv, Rg, Rh), energy

    def _tangent(self, g, J, forces, trans, rot, Rv, Rg, Rh) -> np.ndarray:
        """The consistent tangents (E, 18, 18) of :meth:`evaluate`: the local stiffness through the
        frame's and the rotations' Jacobians, plus the local forces on their second derivatives, and
        the multiplicative spins' correction."""
        E = g.shape[0]
        Hz = np.zeros((E, 15, 15))
        Hz[:, :6, :6] = sum(g[:, row, None, None] * jet.h for row, jet in trans.items())
        for i, (C, w, Jy, Dt, Ht) in enumerate(rot):
            gi = g[:, 6 * i + 3:6 * i + 6]  # (E, 3)
            # sum_c g_c d^2 theta_c = Jy^T (sum_c g_c d^2 theta_c / dy^2) Jy + sum_k gy_k d^2 y_k,
            # gy = Dt^T g: the second part is A's Hessian contracted with weights Wt
            Hz += np.einsum("eak,eab,ebl->ekl", Jy, np.einsum("ec,ecab->eab", gi, Ht), Jy, optimize=True)
            gy = np.einsum("eca,ec->ea", Dt, gi)
            Wt = np.zeros((E, 3, 3))
            for c, (p, q) in enumerate(_AXIAL):
                Wt[:, p, q] += 0.5 * gy[:, c]
                Wt[:, q, p] -= 0.5 * gy[:, c]
            Wt += 0.5 * gy[:, 3, None, None] * np.eye(3)
            RC = np.einsum("eps,eqs->epq", Wt, C)  # sum_ps Wt_ps (R M C)_ps = sum_pqr RC_pr R_pq M_qr
            Hz[:, :6, :6] += np.einsum("epq,epqkl->ekl", RC, Rh)
            mixed = np.einsum("epr,epqk,lqr->ekl", RC, Rg, _SPIN, optimize=True)  # sum Wt (R_k [e_l]x C)
            Hz[:, :6, w] += mixed
            Hz[:, w, :6] += mixed.transpose(0, 2, 1)
            Hz[:, w, w] += np.einsum("epr,epq,lmqr->elm", RC, Rv, _SPIN2, optimize=True)
        K = J.transpose(0, 2, 1) @ (self.k @ J) + _P.T @ Hz @ _P
        # the spins are multiplicative (Q <- exp([w]x) Q): the derivative of the moment residual
        # after the update differs from the Hessian by -1/2 [m]x on each corner's spin block
        for i in range(3):
            m = forces[:, 6 * i + 3:6 * i + 6]
            s = slice(6 * i + 3, 6 * i + 6)
            K[:, s, s] -= 0.5 * np.einsum("ek,kpq->epq", m, _SPIN)
        return K
