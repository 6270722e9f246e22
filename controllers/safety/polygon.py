"""The object polygon as convex pieces: the unit the filter's object rows and FCL parts work on.

The distance from a point to a union of convex pieces is the least of its distances to the pieces,
so keeping a disc clear of every piece keeps it clear of the object, and each piece's distance is
a convex function of the point, with the gradient the barrier rows need everywhere outside it. A
non-convex object therefore gets one barrier row per piece (:mod:`controllers.safety.barrier`):
a single row for the whole polygon guards only its nearest face, and at a re-entrant corner the
face a robot heads for is not the nearest until too late. Fewer pieces mean fewer rows, so
:func:`convex_pieces` merges the ear-clipping triangles back into convex pieces across their shared
diagonals (Hertel and Mehlhorn 1983: at most four times the fewest convex pieces; an L-shape gives
two, a U three).
"""

from __future__ import annotations

import numpy as np


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def is_convex_ccw(poly: np.ndarray) -> bool:
    """True when the (M, 2) polygon is strictly convex and counter-clockwise."""
    e = np.roll(poly, -1, axis=0) - poly
    cross = e[:, 0] * np.roll(e[:, 1], -1) - e[:, 1] * np.roll(e[:, 0], -1)
    return bool(np.all(cross > 0))


def _ear_clip_indices(poly: np.ndarray) -> list[list[int]]:
    """Vertex indices of the ear-clipping triangles of a simple counter-clockwise polygon."""
    idx = list(range(len(poly)))
    triangles: list[list[int]] = []
    while len(idx) > 3:
        for k in range(len(idx)):
            a, b, c = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            if _cross(poly[a], poly[b], poly[c]) <= 0:
                continue  # reflex corner: not an ear
            others = [poly[m] for m in idx if m not in (a, b, c)]
            if any(_cross(poly[a], poly[b], p) >= 0 and _cross(poly[b], poly[c], p) >= 0
                   and _cross(poly[c], poly[a], p) >= 0 for p in others):
                continue
            triangles.append([a, b, c])
            del idx[k]
            break
        else:
            raise ValueError("object polygon is not simple: ear clipping found no ear")
    triangles.append(idx)
    return triangles


def ear_clip(poly: np.ndarray) -> list[np.ndarray]:
    """Triangulate a simple counter-clockwise polygon (M, 2) into (3, 2) triangles by ear clipping."""
    return [poly[t] for t in _ear_clip_indices(poly)]


def _convex_ring(poly: np.ndarray, ring: list[int]) -> list[int] | None:
    """``ring`` (vertex indices, counter-clockwise) without its straight-through vertices when
    what is left is strictly convex, else None."""
    scale = float(np.ptp(poly, axis=0).max()) ** 2
    kept = [v for k, v in enumerate(ring)
            if abs(_cross(poly[ring[k - 1]], poly[v], poly[ring[(k + 1) % len(ring)]])) > 1e-12 * scale]
    if len(kept) < 3:
        return None
    turns = [_cross(poly[kept[k - 1]], poly[v], poly[kept[(k + 1) % len(kept)]]) for k, v in enumerate(kept)]
    return kept if min(turns) > 0 else None


def _merged(first: list[int], second: list[int]) -> list[int] | None:
    """The ring of two counter-clockwise rings that share an edge (``a -> b`` in ``first``,
    ``b -> a`` in ``second``), or None when they share none."""
    for k in range(len(first)):
        a, b = first[k], first[(k + 1) % len(first)]
        for q in range(len(second)):
            if second[q] == b and second[(q + 1) % len(second)] == a:
                # first from b round to a, then second's vertices strictly between a and b
                ring = [first[(k + 1 + t) % len(first)] for t in range(len(first))]
                ring += [second[(q + 2 + t) % len(second)] for t in range(len(second) - 2)]
                return ring
    return None


def convex_pieces(poly: np.ndarray) -> list[np.ndarray]:
    """The simple counter-clockwise polygon (M, 2) as strictly convex counter-clockwise pieces
    (each (K, 2)) whose union it is: itself when convex, else its ear-clipping triangles merged
    across shared diagonals while the merged ring stays convex (module docstring)."""
    poly = np.asarray(poly, dtype=np.float64)
    if is_convex_ccw(poly):
        return [poly]
    rings = _ear_clip_indices(poly)
    merged = True
    while merged:
        merged = False
        for x in range(len(rings)):
            for y in range(x + 1, len(rings)):
                ring = _merged(rings[x], rings[y])
                ring = None if ring is None else _convex_ring(poly, ring)
                if ring is not None:
                    rings[x] = ring
                    del rings[y]
                    merged = True
                    break
            if merged:
                break
    pieces = [_convex_ring(poly, ring) or ring for ring in rings]
    return [poly[ring] for ring in pieces]


__all__ = ["convex_pieces", "ear_clip", "is_convex_ccw"]
