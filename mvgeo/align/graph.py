"""Pair graphs over the views: which pairs to predict, connectivity, spanning tree."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from mvgeo.common.errors import ConfigError

#: Above this many images `auto` switches from the complete graph to a window.
COMPLETE_MAX_IMAGES = 24


@dataclass(frozen=True)
class PairGraphSpec:
    """How to choose pairs.

    Attributes:
        kind: "complete" (all pairs), "window" (each image with the next `window`
            images in name order, wrapping around, as for an orbit), or "auto"
            (complete up to `COMPLETE_MAX_IMAGES` images, else a window of 8).
        window: K for "window".
    """

    kind: str = "auto"
    window: int = 8

    @classmethod
    def parse(cls, text: str) -> PairGraphSpec:
        """Parse `complete`, `auto` or `window:K` (the CLI's `--pairs`)."""
        text = text.strip().lower()
        if text in ("complete", "auto"):
            return cls(kind=text)
        m = re.fullmatch(r"window:(\d+)", text)
        if m and int(m.group(1)) >= 1:
            return cls(kind="window", window=int(m.group(1)))
        raise ConfigError(f"unknown pair graph {text!r}", key="pairs", expected="complete, auto or window:K (K >= 1)")


def make_pairs(n_images: int, spec: PairGraphSpec) -> list[tuple[int, int]]:
    """Unordered pairs (i < j) to predict."""
    kind = spec.kind
    if kind == "auto":
        kind = "complete" if n_images <= COMPLETE_MAX_IMAGES else "window"
    if kind == "complete" or (kind == "window" and spec.window >= n_images - 1):
        return [(i, j) for i in range(n_images) for j in range(i + 1, n_images)]
    if kind != "window":
        raise ConfigError(f"unknown pair graph kind {spec.kind!r}", key="pairs", expected="complete, auto, window")
    pairs = set()
    for i in range(n_images):
        for k in range(1, spec.window + 1):
            j = (i + k) % n_images
            if j != i:
                pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


def components(n_images: int, edges: Sequence[tuple[int, int]]) -> list[list[int]]:
    """Connected components (lists of view indices), largest first."""
    if n_images == 0:
        return []
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_images, n_images))
    _, labels = connected_components(adj, directed=False)
    comps = [sorted(np.flatnonzero(labels == c).tolist()) for c in np.unique(labels)]
    return sorted(comps, key=lambda c: (-len(c), c[0]))


def maximum_spanning_tree(n_images: int, edges: Sequence[tuple[int, int]], scores: Sequence[float]) -> list[int]:
    """Indices into `edges` of a maximum spanning tree (forest if disconnected) by score.

    Scores must be positive. Edges are returned in breadth-first order from the
    strongest edge, so each edge after the first touches a view already reached
    (within the first component), ready for chaining.
    """
    if len(edges) == 0:
        return []
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    s = np.asarray(scores, dtype=np.float64)
    # scipy finds a minimum tree over positive weights: map score -> a positive decreasing cost.
    cost = (s.max() + 1.0) - s + 1e-9
    best = {}
    for k, (a, b) in enumerate(e):
        key = (min(a, b), max(a, b))
        if key not in best or s[k] > s[best[key]]:
            best[key] = k
    keys = list(best)
    rows = np.array([k[0] for k in keys])
    cols = np.array([k[1] for k in keys])
    mat = coo_matrix((np.array([cost[best[k]] for k in keys]), (rows, cols)), shape=(n_images, n_images))
    tree = minimum_spanning_tree(mat).tocoo()
    tree_edges = [best[(min(a, b), max(a, b))] for a, b in zip(tree.row, tree.col, strict=True)]
    # BFS order starting from the strongest tree edge.
    tree_edges.sort(key=lambda k: -s[k])
    ordered: list[int] = []
    reached: set[int] = set()
    remaining = list(tree_edges)
    while remaining:
        if not reached:
            k = remaining.pop(0)
            ordered.append(k)
            reached.update(e[k].tolist())
            continue
        for idx, k in enumerate(remaining):
            if e[k, 0] in reached or e[k, 1] in reached:
                ordered.append(remaining.pop(idx))
                reached.update(e[k].tolist())
                break
        else:  # another component: start afresh from its strongest edge
            reached = set()
    return ordered
