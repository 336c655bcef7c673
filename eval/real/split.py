"""Train / held-out view splits for imported captures.

Three rules, all deterministic:

- `every_kth_split`: LLFF's convention (every K-th view, from the first, is
  held out; the training views are spread over the rest);
- `spread_split`: training views spread evenly over the index range,
  held-out views midway between them;
- `cluster_split`: the most alike views (by viewing direction), with
  held-out views inside the training views;
- `ring_split`: for an orbit (camera centres around the object, in any file
  order), training views spread by angle around the ring, held out the views
  between them.
"""

from __future__ import annotations

import numpy as np

from mvgeo.common.errors import InputError

__all__ = ["cluster_split", "every_kth_split", "ring_order", "ring_split", "spread_split"]


def every_kth_split(n: int, test_every: int, train: int | None = None) -> tuple[list[int], list[int]]:
    """Views ``0, K, 2K, ...`` held out; `train` views spread evenly over the others (all when None).

    The sparse-view LLFF protocol (RegNeRF, FreeNeRF): ``test = i % K == 0``, training views at
    ``round(linspace(0, len(rest) - 1, train))`` of the remaining ones.

    Raises:
        InputError: K < 2, or fewer remaining views than `train`.
    """
    if test_every < 2:
        raise InputError(f"--test-every must be >= 2, got {test_every}")
    te = list(range(0, n, test_every))
    rest = [i for i in range(n) if i % test_every]
    if train is None:
        return rest, te
    if train < 2 or train > len(rest):
        raise InputError(f"{n} views with every {test_every}th held out leave {len(rest)} training candidates; "
                         f"cannot take {train}", fix=f"ask for 2..{len(rest)} training views")
    picks = np.unique(np.round(np.linspace(0, len(rest) - 1, train)).astype(int))
    return [rest[int(k)] for k in picks], te


def spread_split(n: int, train: int, test: int) -> tuple[list[int], list[int]]:
    """`train` indices spread evenly over ``0..n-1`` and exactly `test` others, also spread.

    The held-out views are the remaining views at ``round(linspace(0, R - 1, test + 2)[1:-1])`` (R of
    them: midway between, away from both ends). Where that rounding gives the same view twice (few
    remaining views, e.g. ``test`` = R), they are the views at the centres of `test` equal bins of the
    remaining ones instead, ``floor((k + 0.5) R / test)``, which are distinct whenever ``test <= R``.
    """
    if train + test > n or train < 2 or test < 1:
        raise InputError(f"cannot split {n} views into {train} training and {test} held-out views",
                         fix=f"ask for at least 2 training and 1 held-out view, {n} in all at most")
    tr = [int(v) for v in np.unique(np.round(np.linspace(0, n - 1, train)).astype(int))]
    rest = [i for i in range(n) if i not in tr]
    picks = np.unique(np.round(np.linspace(0, len(rest) - 1, test + 2)[1:-1]).astype(int))
    if len(picks) < test:
        picks = ((np.arange(test) + 0.5) * len(rest) // test).astype(int)
    te = [rest[int(v)] for v in picks]
    return tr, te


def cluster_split(view_dirs_world: np.ndarray, train: int, test: int) -> tuple[list[int], list[int]]:
    """The ``train + test`` views that look most alike, with interior held-out views.

    The cluster is the ``train + test`` views whose viewing directions are closest (in angle) to the
    mean viewing direction of all views. Held-out views are taken greedily from the cluster's centre
    outwards. A view is held out when its training neighbours (within 1.5 times the cluster's median
    nearest-neighbour angle; views already held out do not count) surround it: no gap of 150 deg or more
    between their bearings around it, so that it lies inside the training views. Views with no held-out
    neighbour are taken first, then any that are still surrounded.

    Args:
        view_dirs_world: (N, 3) unit viewing directions (camera +z axes in the world frame).
        train, test: split sizes.

    Returns:
        (training indices, held-out indices), each sorted.

    Raises:
        InputError: the split does not fit, or the interior has too few views for `test`.
    """
    d = np.asarray(view_dirs_world, dtype=np.float64)
    n = len(d)
    if train + test > n or train < 2 or test < 1:
        raise InputError(f"cannot split {n} views into {train} training and {test} held-out views",
                         fix=f"ask for at least 2 training and 1 held-out view, {n} in all at most")
    mean = d.mean(axis=0)
    mean /= np.linalg.norm(mean)
    cluster = np.argsort(-(d @ mean), kind="stable")[: train + test]
    dc = d[cluster]
    centre = dc.mean(axis=0)
    angle = np.arccos(np.clip(dc @ dc.T, -1.0, 1.0))
    np.fill_diagonal(angle, np.inf)
    neighbour = angle <= 1.5 * np.median(angle.min(axis=1))
    order = np.argsort(-(dc @ centre), kind="stable")
    held: list[int] = []
    for apart in (True, False):  # first views with no held-out neighbour, then any that are still inside
        for k in order:
            if len(held) == test:
                break
            if k in held or (apart and neighbour[k, held].any()):
                continue
            train_near = [m for m in np.flatnonzero(neighbour[k]) if m not in held]
            if _surrounded(dc[k], dc[train_near]):
                held.append(int(k))
    if len(held) < test:
        raise InputError(f"a cluster of {train + test} views has room for only {len(held)} interior held-out "
                         f"views (asked {test})", fix="hold out fewer views or train on more")
    te = sorted(int(cluster[k]) for k in held)
    tr = sorted(int(i) for i in cluster if int(i) not in te)
    return tr, te


def _surrounded(direction: np.ndarray, others: np.ndarray) -> bool:
    """Whether the directions `others` (K, 3) surround `direction` (3,): all bearing gaps < 150 deg.

    (< 180 deg would admit a view on the segment between two others, on the edge of their hull.)
    """
    if len(others) < 3:
        return False
    helper = np.eye(3)[int(np.argmin(np.abs(direction)))]
    e1 = np.cross(direction, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(direction, e1)
    bearing = np.sort(np.arctan2(others @ e2, others @ e1))
    gaps = np.diff(np.concatenate([bearing, bearing[:1] + 2.0 * np.pi]))
    return bool(gaps.max() < np.radians(150.0))


def ring_order(centres: np.ndarray) -> tuple[list[int], np.ndarray]:
    """(views in ring order without repeated positions, angle of every view in radians) for camera
    centres (N, 3) around a ring: the angle is taken in the centres' best-fit plane (the two leading
    principal directions); a view at the position of an earlier one (within 1e-6 of the ring's
    radius) is left out of the order."""
    c = np.asarray(centres, np.float64) - np.mean(centres, axis=0)
    _, _, vt = np.linalg.svd(c)
    ang = np.arctan2(c @ vt[1], c @ vt[0])
    tol = 1e-6 * max(float(np.linalg.norm(c, axis=1).max()), 1e-300)
    order: list[int] = []
    for v in range(len(c)):
        if all(np.linalg.norm(c[v] - c[u]) > tol for u in order):
            order.append(v)
    order.sort(key=lambda v: ang[v])
    return order, ang


def ring_split(centres: np.ndarray, train: int, test: int | None = None) -> tuple[list[int], list[int]]:
    """`train` views spread around a ring of camera centres (N, 3), and held-out views between them.

    The training views: of the distinct positions in ring order (`ring_order`), the view whose two
    neighbours around the ring are closest is dropped until `train` remain, so the gaps stay as even as
    the capture allows and the ring stays closed. Held out: the dropped views (not the repeated
    positions, which would be a training view seen again), all of them or `test` spread over them.

    Raises:
        InputError: fewer distinct positions than `train` + 1, or fewer candidates than `test`.
    """
    order, ang = ring_order(centres)
    if train < 2 or train >= len(order):
        raise InputError(f"a ring of {len(order)} distinct camera positions cannot give {train} training views "
                         "and a held-out one", fix=f"ask for 2..{len(order) - 1} training views")
    keep = list(order)
    while len(keep) > train:
        a = np.array([ang[v] for v in keep])
        span = (np.roll(a, -1) - np.roll(a, 1)) % (2 * np.pi)  # the two neighbours' separation around each view
        keep.pop(int(np.argmin(span)))
    rest = [v for v in order if v not in keep]
    if test is not None:
        if test < 1 or test > len(rest):
            raise InputError(f"the ring leaves {len(rest)} held-out candidates; cannot take {test}",
                             fix=f"ask for 1..{len(rest)} held-out views")
        rest = [rest[int(k)] for k in np.unique(np.round(np.linspace(0, len(rest) - 1, test)).astype(int))]
    return sorted(keep), sorted(rest)
