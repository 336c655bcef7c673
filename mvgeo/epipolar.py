"""Epipolar minimal and linear solvers (numpy float64 kernels).

Frames and conventions: correspondences ``x1 <-> x2`` satisfy
``x2^T E x1 = 0`` (normalised coordinates) and ``u2^T F u1 = 0`` (pixels, our
convention), with ``E = [t]_x R`` for ``cam2_from_cam1 = [R | t]``
(docs/conventions.md). All solvers return **lists of candidate matrices**
with unit Frobenius norm (a minimal problem has several real solutions).

- `essential_5point`: Stewénius–Engels–Nistér formulation: the 4-D null
  space ``E = x X + y Y + z Z + W``, ten cubic constraints (``det E = 0`` and
  ``2 E E^T E - tr(E E^T) E = 0``), Gauss–Jordan elimination of the ten cubic
  monomials, and the eigenvectors of the 10x10 action matrix of ``x`` on the
  quotient basis ``{x^2, y^2, z^2, xy, xz, yz, x, y, z, 1}``. Our own
  implementation (OpenCV's is used only as a test reference).
- `fundamental_7point`: 2-D null space and the real roots of the cubic ``det``.
- `fundamental_8point`: Hartley-normalised linear solution with rank-2 enforcement.
- `essential_from_linear`: linear (>= 8 points) essential estimate projected
  onto the essential manifold (singular values ``(1, 1, 0)``).
- `sampson_distance`: first-order geometric error, in the coordinates' units.
- `decompose_essential`: the four ``(R, t)`` candidates.
"""

from __future__ import annotations

import itertools

import numpy as np

from mvgeo.common.errors import ShapeError, check_shape

__all__ = [
    "essential_5point",
    "fundamental_7point",
    "fundamental_8point",
    "essential_from_linear",
    "project_to_essential",
    "sampson_distance",
    "decompose_essential",
    "fundamental_from_essential",
    "essential_from_fundamental",
    "essential_from_pose",
]

# ---------------------------------------------------------------- polynomial algebra in (x, y, z), degree <= 3
_MONOMIALS = [e for d in range(4) for e in itertools.product(range(4), repeat=3) if sum(e) == d]
_MONOMIALS = sorted(_MONOMIALS, key=lambda e: (-sum(e), [-v for v in e]))  # cubic first
_MONO_INDEX = {e: i for i, e in enumerate(_MONOMIALS)}
_NM = len(_MONOMIALS)  # 20
_LIN = [_MONO_INDEX[(1, 0, 0)], _MONO_INDEX[(0, 1, 0)], _MONO_INDEX[(0, 0, 1)], _MONO_INDEX[(0, 0, 0)]]
_QUAD = [i for i, e in enumerate(_MONOMIALS) if sum(e) <= 2]  # the 10 monomials of degree <= 2
_CUBIC = [i for i, e in enumerate(_MONOMIALS) if sum(e) == 3]
_BASIS = _QUAD  # quotient-ring basis for the action matrix
_BASIS_POS = {_MONOMIALS[i]: k for k, i in enumerate(_BASIS)}
_CUBIC_POS = {_MONOMIALS[i]: k for k, i in enumerate(_CUBIC)}


def _mul_table(left: list[int], right: list[int], out: list[int]) -> np.ndarray:
    """T[a, b, c] = 1 if monomial left[a] * right[b] == out[c]."""
    pos = {_MONOMIALS[i]: k for k, i in enumerate(out)}
    T = np.zeros((len(left), len(right), len(out)))
    for a, i in enumerate(left):
        for b, j in enumerate(right):
            T[a, b, pos[tuple(p + q for p, q in zip(_MONOMIALS[i], _MONOMIALS[j], strict=True))]] = 1.0
    return T


_ALL = list(range(_NM))
_MUL_LL = _mul_table(_LIN, _LIN, _QUAD)  # (4, 4, 10): linear x linear -> quadratic
_MUL_QL = _mul_table(_QUAD, _LIN, _ALL)  # (10, 4, 20): quadratic x linear -> cubic


def _as_points(x, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    check_shape(x, ["N", 2], name)
    return x


def _hom(x: np.ndarray) -> np.ndarray:
    return np.concatenate([x, np.ones(x.shape[:-1] + (1,))], axis=-1)


def essential_5point(x1, x2) -> list[np.ndarray]:
    """Essential matrices from exactly 5 normalised correspondences.

    Args:
        x1: (5, 2) normalised coordinates in camera 1 (``K1^-1 u1``).
        x2: (5, 2) in camera 2.

    Returns:
        Up to 10 real solutions, each (3, 3) with unit Frobenius norm. An empty
        list for degenerate samples (e.g. repeated points).
    """
    x1 = _as_points(x1, "x1")
    x2 = _as_points(x2, "x2")
    if x1.shape[0] != 5 or x2.shape[0] != 5:
        raise ShapeError(f"essential_5point needs exactly 5 correspondences, got {x1.shape[0]}, {x2.shape[0]}")
    Q = np.einsum("ni,nj->nij", _hom(x2), _hom(x1)).reshape(5, 9)
    _, S, Vt = np.linalg.svd(Q, full_matrices=True)
    if S[-1] < 1e-12 * S[0]:
        return []  # rank-deficient sample: the null space is > 4-D
    basis = Vt[5:]  # X, Y, Z, W as rows (9,)
    # E entries as linear polynomials in (x, y, z, 1): E_ij = x X_ij + y Y_ij + z Z_ij + W_ij.
    E = np.moveaxis(basis.reshape(4, 3, 3), 0, -1)  # (3, 3, 4)
    EEt = np.einsum("ika,jkb,abq->ijq", E, E, _MUL_LL)  # (3, 3, 10) quadratic
    EEtE = np.einsum("ikq,kjc,qcr->ijr", EEt, E, _MUL_QL)  # (3, 3, 20) cubic
    tr = EEt[0, 0] + EEt[1, 1] + EEt[2, 2]
    trace_c = 2 * EEtE - np.einsum("q,ijc,qcr->ijr", tr, E, _MUL_QL)
    cof = np.einsum("a,b,abq->q", E[1, 1], E[2, 2], _MUL_LL) - np.einsum("a,b,abq->q", E[1, 2], E[2, 1], _MUL_LL)
    cof1 = np.einsum("a,b,abq->q", E[1, 2], E[2, 0], _MUL_LL) - np.einsum("a,b,abq->q", E[1, 0], E[2, 2], _MUL_LL)
    cof2 = np.einsum("a,b,abq->q", E[1, 0], E[2, 1], _MUL_LL) - np.einsum("a,b,abq->q", E[1, 1], E[2, 0], _MUL_LL)
    det = (np.einsum("q,c,qcr->r", cof, E[0, 0], _MUL_QL) + np.einsum("q,c,qcr->r", cof1, E[0, 1], _MUL_QL)
           + np.einsum("q,c,qcr->r", cof2, E[0, 2], _MUL_QL))
    A = np.vstack([det[None], trace_c.reshape(9, _NM)])  # (10, 20)
    A1 = A[:, _CUBIC]
    A2 = A[:, _BASIS]
    try:
        B = np.linalg.solve(A1, A2)  # cubic_k = -B[k] . basis
    except np.linalg.LinAlgError:
        return []
    if not np.all(np.isfinite(B)):
        return []
    # Action matrix of multiplication by x on the basis: x * b = M b.
    M = np.zeros((10, 10))
    for k, i in enumerate(_BASIS):
        e = _MONOMIALS[i]
        m = (e[0] + 1, e[1], e[2])
        if m in _BASIS_POS:
            M[k, _BASIS_POS[m]] = 1.0
        else:
            M[k] = -B[_CUBIC_POS[m]]
    w, V = np.linalg.eig(M)
    out = []
    ix, iy, iz, i1 = (_BASIS_POS[(1, 0, 0)], _BASIS_POS[(0, 1, 0)], _BASIS_POS[(0, 0, 1)], _BASIS_POS[(0, 0, 0)])
    for k in range(10):
        v = V[:, k]
        # Real solutions: imaginary part negligible relative to the vector (eigvecs are unit norm).
        if abs(w[k].imag) > 1e-8 * max(1.0, abs(w[k].real)) or abs(v[i1]) < 1e-12:
            continue
        sol = (v[[ix, iy, iz]] / v[i1]).real
        Ek = (sol[0] * basis[0] + sol[1] * basis[1] + sol[2] * basis[2] + basis[3]).reshape(3, 3)
        n = np.linalg.norm(Ek)
        if n > 0 and np.isfinite(n):
            out.append(Ek / n)
    return out


def fundamental_7point(u1, u2) -> list[np.ndarray]:
    """Fundamental matrices from exactly 7 correspondences (1 or 3 real solutions).

    Args:
        u1: (7, 2) pixel (or any affine) coordinates in image 1.
        u2: (7, 2) in image 2.

    Returns:
        List of (3, 3) rank-2 matrices with unit Frobenius norm.
    """
    u1 = _as_points(u1, "u1")
    u2 = _as_points(u2, "u2")
    if u1.shape[0] != 7 or u2.shape[0] != 7:
        raise ShapeError("fundamental_7point needs exactly 7 correspondences")
    T1, n1 = _hartley(u1)
    T2, n2 = _hartley(u2)
    Q = np.einsum("ni,nj->nij", _hom(n2), _hom(n1)).reshape(7, 9)
    _, S, Vt = np.linalg.svd(Q, full_matrices=True)
    if S[-1] < 1e-12 * S[0]:
        return []
    F1, F2 = Vt[7].reshape(3, 3), Vt[8].reshape(3, 3)
    # det(a F1 + (1 - a) F2) is a cubic in a: fit it exactly from 4 samples.
    a_s = np.array([-1.0, 0.0, 1.0, 2.0])
    d = [np.linalg.det(a * F1 + (1 - a) * F2) for a in a_s]
    coeffs = np.polyfit(a_s, d, 3)
    out = []
    for r in np.roots(coeffs):
        if abs(r.imag) > 1e-10 * max(1.0, abs(r.real)):
            continue
        Fn = r.real * F1 + (1 - r.real) * F2
        F = T2.T @ Fn @ T1
        n = np.linalg.norm(F)
        if n > 0:
            out.append(F / n)
    return out


def _hartley(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic normalisation: centroid to 0, mean distance sqrt(2). Returns T (3,3) and T u."""
    c = u.mean(axis=0)
    d = np.mean(np.linalg.norm(u - c, axis=1))
    s = np.sqrt(2) / d if d > 0 else 1.0
    T = np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])
    return T, (u - c) * s


def fundamental_8point(u1, u2, *, weights=None) -> np.ndarray:
    """Hartley-normalised (weighted) linear fundamental matrix, rank 2, unit norm.

    Args:
        u1: (N, 2), N >= 8.
        u2: (N, 2).
        weights: (N,) optional non-negative weights (e.g. for IRLS).

    Returns:
        (3, 3).

    Raises:
        ShapeError: fewer than 8 correspondences.
    """
    u1 = _as_points(u1, "u1")
    u2 = _as_points(u2, "u2")
    if u1.shape[0] < 8 or u2.shape != u1.shape:
        raise ShapeError(f"fundamental_8point needs >= 8 matching correspondences, got {u1.shape}, {u2.shape}")
    T1, n1 = _hartley(u1)
    T2, n2 = _hartley(u2)
    Q = np.einsum("ni,nj->nij", _hom(n2), _hom(n1)).reshape(-1, 9)
    if weights is not None:
        Q = Q * np.sqrt(np.asarray(weights, dtype=np.float64))[:, None]
    # Only the right singular vectors are needed: no N x N U (N >= 9 keeps all 9 rows of Vt).
    _, _, Vt = np.linalg.svd(Q, full_matrices=Q.shape[0] < 9)
    Fn = Vt[-1].reshape(3, 3)
    U, S, Vt2 = np.linalg.svd(Fn)
    Fn = U @ np.diag([S[0], S[1], 0.0]) @ Vt2
    F = T2.T @ Fn @ T1
    return F / np.linalg.norm(F)


def project_to_essential(M) -> np.ndarray:
    """Closest essential matrix (singular values (1, 1, 0)), unit Frobenius norm. M: (3, 3)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    E = U @ np.diag([1.0, 1.0, 0.0]) @ Vt
    return E / np.linalg.norm(E)


def essential_from_linear(x1, x2, *, weights=None) -> np.ndarray:
    """Linear essential matrix from >= 8 normalised correspondences, projected to the manifold."""
    F = fundamental_8point(x1, x2, weights=weights)
    return project_to_essential(F)


def sampson_distance(F, u1, u2) -> np.ndarray:
    """Sampson (first-order geometric) distance ``|u2^T F u1| / sqrt(|F u1|_12^2 + |F^T u2|_12^2)``.

    Units are those of the coordinates (pixels for F on pixel coordinates,
    normalised units for E on normalised coordinates). This is the square
    root of OpenCV's ``sampsonDistance``.

    Args:
        F: (3, 3).
        u1: (N, 2).
        u2: (N, 2).

    Returns:
        (N,) non-negative, finite (a zero denominator, i.e. a point at an
        epipole, gives the algebraic error itself).
    """
    F = np.asarray(F, dtype=np.float64)
    check_shape(F, [3, 3], "F")
    h1 = _hom(_as_points(u1, "u1"))
    h2 = _hom(_as_points(u2, "u2"))
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.abs(np.sum(h2 * Fx1, axis=1))
    den2 = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return num / np.sqrt(np.where(den2 > 0, den2, 1.0))


def decompose_essential(E) -> tuple[np.ndarray, np.ndarray]:
    """The four ``cam2_from_cam1`` candidates ``(R, t)`` of an essential matrix.

    Args:
        E: (3, 3).

    Returns:
        ``R (4, 3, 3)`` proper rotations and ``t (4, 3)`` unit translations:
        ``(R1, t), (R1, -t), (R2, t), (R2, -t)``. Pick with a cheirality test.
    """
    E = np.asarray(E, dtype=np.float64)
    check_shape(E, [3, 3], "E")
    U, _, Vt = np.linalg.svd(E)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    R1 = U @ W @ Vt
    R2 = U @ W.T @ Vt
    t = U[:, 2] / np.linalg.norm(U[:, 2])
    return np.stack([R1, R1, R2, R2]), np.stack([t, -t, t, -t])


def essential_from_pose(R, t) -> np.ndarray:
    """``E = [t]_x R`` for ``cam2_from_cam1 = [R | t]`` (not normalised)."""
    t = np.asarray(t, dtype=np.float64)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ np.asarray(R, dtype=np.float64)


def fundamental_from_essential(E, K1, K2) -> np.ndarray:
    """``F = K2^-T E K1^-1`` (pixel coordinates in our convention if K is), unit norm."""
    F = np.linalg.inv(np.asarray(K2, dtype=np.float64)).T @ np.asarray(E) @ np.linalg.inv(np.asarray(K1))
    return F / np.linalg.norm(F)


def essential_from_fundamental(F, K1, K2) -> np.ndarray:
    """``E = K2^T F K1`` (not projected to the manifold), unit norm."""
    E = np.asarray(K2, dtype=np.float64).T @ np.asarray(F) @ np.asarray(K1, dtype=np.float64)
    return E / np.linalg.norm(E)
