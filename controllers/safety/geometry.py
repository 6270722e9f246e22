"""Collision geometry of one control tick: robots, the transported object and the walls on FCL.

Shapes (arena metres, the plane z = 0 embedded in 3-D for FCL):

* Robot ``i``: an ``fcl.Sphere`` of radius ``r`` centred at ``(x_i, y_i, 0)``. A sphere, not a
  cylinder: sphere-sphere and sphere-box distances are closed forms in FCL, and because every
  centre lies on z = 0 and every other shape is a prism symmetric about z = 0, the nearest points
  lie on z = 0, so the 3-D distance equals the planar disc distance exactly.
* The object: the scenario polygon (M, 2) extruded to a prism ``z in [-L, L]`` (L = 1 m >> r):
  one ``fcl.Convex`` for a convex polygon, or one per convex piece of a simple non-convex one
  (:func:`~controllers.safety.polygon.convex_pieces`; distances outside are exact; a penetration
  depth inside is the depth into one piece, which has the right sign but may be shallower than the
  true depth).
* The walls x = 0, x = W, y = 0, y = H: four thick ``fcl.Box`` slabs just outside the arena
  for the broadphase (not ``fcl.Halfspace``: its distance query crashes python-fcl 0.7); their
  distances are the half-planes' closed form, ``x - r``, ``W - x - r``, ..., which a slab gets
  wrong for a centre past its far face (1 m out: it read clear).

FCL facts this module works around (python-fcl 0.7.0.11): a *signed* distance query runs GJK
even for sphere-box and is off by up to 7e-4 m, while the plain query is exact for sphere-sphere
and sphere-box while they are apart, so the plain query comes first and the signed one (EPA) only
on overlap; EPA never returns for two coincident spheres, so overlapping robot pairs use the
closed form; GJK's nearest points on the object are good to ~1e-5 m, so the object's nearest
point is re-projected exactly onto the edge FCL found.

All shapes sit in one ``fcl.DynamicAABBTreeCollisionManager`` (broadphase). :meth:`CollisionScene.update`
moves the robots (and optionally the object) and calls ``manager.update()``; :meth:`contacts`
asks the broadphase for every overlapping pair (``num_max_contacts`` large, so it does not stop at
the first contact); :meth:`distances` returns signed distances (negative when overlapping) with nearest points and unit normals for *all* robot-robot (P = N(N-1)/2,
pairs ``i < j`` in ``np.triu_indices`` order), robot-object (N x Q: one per robot and convex
piece of the object, robot-major) and robot-wall (N, 4) pairs.

:func:`analytic_distances` computes the same quantities in closed form with numpy (exact for discs,
half-planes and polygons); the tests use it as the oracle and the safety filter can use it as a
faster geometry backend.

Normals always point *towards robot i*: for a pair ``(i, j)`` the unit vector from j to i, for the
object and a wall the outward normal of the obstacle at its nearest point. They are the gradient of
the signed distance with respect to the position of robot i. ``curvature`` is the rate at which that
normal turns (1/rho for a disc or a polygon vertex at centre distance rho, 0 for an edge or a wall);
the barrier derivative needs it.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import fcl
import numpy as np

from controllers.safety.polygon import convex_pieces
from sim.scenario import Scenario

WALL_NORMALS = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
"""(4, 2) inward normals of the walls x = 0, x = W, y = 0, y = H (pointing into the arena)."""

_PRISM_HALF_HEIGHT = 1.0
_TOUCH = 1e-6   # [m] an overlap shallower than this is measured without EPA (CollisionScene._signed)
_WALL_THICKNESS = 1.0


@dataclass
class SceneDistances:
    """Signed distances between shapes (negative = overlap) at one instant, N robots, P pairs.

    Attributes:
        pair_i, pair_j: (P,) robot indices of each pair, ``i < j``.
        pair_distance: (P,) disc-disc signed distance, ``|p_i - p_j| - 2r`` [m].
        pair_normal: (P, 2) unit vector from robot j to robot i.
        pair_points: (P, 2, 2) nearest points on disc i and on disc j [m].
        pair_curvature: (P,) 1 / centre distance [1/m].
        object_distance: (N Q,) disc-object signed distance [m], one per robot and convex piece of
            the object (Q = ``pieces``), robot-major: robot i, piece q at ``Q i + q``.
        object_normal: (N Q, 2) outward normal of the piece at its nearest point (towards the robot).
        object_points: (N Q, 2, 2) nearest points on the disc and on the piece [m].
        object_curvature: (N Q,) 1 / (centre to vertex) when the nearest point is a vertex, else 0.
        wall_distance: (N, 4) disc-wall signed distances to x = 0, x = W, y = 0, y = H [m].
        wall_normal: (4, 2) inward wall normals (:data:`WALL_NORMALS`).
    """

    pair_i: np.ndarray
    pair_j: np.ndarray
    pair_distance: np.ndarray
    pair_normal: np.ndarray
    pair_points: np.ndarray
    pair_curvature: np.ndarray
    object_distance: np.ndarray
    object_normal: np.ndarray
    object_points: np.ndarray
    object_curvature: np.ndarray
    wall_distance: np.ndarray
    wall_normal: np.ndarray
    pieces: int = 1

    def object_clearance(self) -> np.ndarray:
        """(N,) each disc's signed distance to the object (the nearest of its pieces) [m]."""
        return self.object_distance.reshape(-1, self.pieces).min(axis=1)

    def min_clearance(self) -> float:
        """The smallest signed distance over every pair [m] (inf when there is nothing to compare)."""
        parts = [self.pair_distance, self.object_distance, self.wall_distance.ravel()]
        values = np.concatenate([p for p in parts if p.size])
        return float(values.min()) if values.size else float("inf")


def _prism(poly: np.ndarray) -> fcl.Convex:
    """A convex (M, 2) CCW polygon extruded to ``z in [-L, L]`` as an ``fcl.Convex``."""
    m = len(poly)
    low = np.c_[poly, np.full(m, -_PRISM_HALF_HEIGHT)]
    high = np.c_[poly, np.full(m, _PRISM_HALF_HEIGHT)]
    faces = [m, *range(m - 1, -1, -1), m, *range(m, 2 * m)]
    for k in range(m):
        faces += [4, k, (k + 1) % m, m + (k + 1) % m, m + k]
    return fcl.Convex(np.vstack([low, high]), m + 2, np.asarray(faces, dtype=np.int64))


def _unit(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row-normalise (K, 2) vectors; returns (unit vectors, norms). Zero rows become (1, 0)."""
    norm = np.hypot(v[:, 0], v[:, 1])
    safe = np.where(norm > 1e-12, norm, 1.0)
    unit = v / safe[:, None]
    unit[norm <= 1e-12] = (1.0, 0.0)
    return unit, norm


# ----------------------------------------------------------------------------- analytic oracle
_EDGE_CACHE: dict[bytes, tuple[np.ndarray, ...]] = {}


def _polygon_edges(poly: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per-edge constants of an (M, 2) polygon as (1, M) rows, cached by the vertices' bytes
    (the polygon is fixed between re-posings, so every tick reuses them)."""
    key = poly.tobytes() + str(poly.shape).encode()
    hit = _EDGE_CACHE.get(key)
    if hit is None:
        if len(_EDGE_CACHE) >= 64:
            _EDGE_CACHE.clear()
        ax, ay = poly[:, 0].copy(), poly[:, 1].copy()
        bx, by = np.roll(ax, -1), np.roll(ay, -1)
        ex, ey = bx - ax, by - ay
        hit = tuple(row[None] for row in (ax, ay, by, ex, ey, ex * ex + ey * ey, np.where(ey == 0, 1.0, ey)))
        _EDGE_CACHE[key] = hit
    return hit


def point_polygon(points: np.ndarray, poly: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact signed distance of (K, 2) points to a simple polygon (M, 2), negative inside.

    Returns ``(signed (K,), nearest boundary point (K, 2), at_vertex (K,) bool)``. Each point is
    projected onto every edge (clamped to the segment); inside is the crossing-number test.
    Works on x and y planes of shape (K, M): for small K that is cheaper than (K, M, 2) arrays.
    """
    ax, ay, by, ex, ey, len2, ey_safe = _polygon_edges(poly)
    px, py = points[:, 0, None], points[:, 1, None]
    rx, ry = px - ax, py - ay                                        # (K, M)
    t = np.clip((rx * ex + ry * ey) / len2, 0.0, 1.0)
    dx, dy = rx - t * ex, ry - t * ey
    d2 = dx * dx + dy * dy
    k = np.argmin(d2, axis=1)
    rows = np.arange(len(points))
    t_best = t[rows, k]
    nearest = np.empty((len(points), 2))
    nearest[:, 0] = ax[0, k] + t_best * ex[0, k]
    nearest[:, 1] = ay[0, k] + t_best * ey[0, k]
    at_vertex = (t_best <= 0.0) | (t_best >= 1.0)
    straddles = (ay > py) != (by > py)
    x_cross = ax + ry * ex / ey_safe
    inside = (np.count_nonzero(straddles & (px < x_cross), axis=1) % 2) == 1
    dist = np.sqrt(d2[rows, k])
    return np.where(inside, -dist, dist), nearest, at_vertex


@functools.lru_cache(maxsize=64)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(n, 1)``, cached and read-only."""
    pi, pj = np.triu_indices(n, 1)
    pi.flags.writeable = pj.flags.writeable = False
    return pi, pj


def analytic_distances(pos: np.ndarray, radius: float, arena: tuple[float, float],
                       polygon: np.ndarray | Sequence[np.ndarray]) -> SceneDistances:
    """Closed-form :class:`SceneDistances` of (N, 2) disc centres, vectorised with numpy.

    ``polygon``: the object as one (M, 2) polygon, or as a list of its convex pieces (one object
    row per robot and piece)."""
    pieces = [polygon] if isinstance(polygon, np.ndarray) and polygon.ndim == 2 else list(polygon)
    pi, pj = _pairs(len(pos))
    normal, centre_dist = _unit(pos[pi] - pos[pj])
    pair_points = np.stack([pos[pi] - radius * normal, pos[pj] + radius * normal], axis=1)
    per_piece = [point_polygon(pos, np.asarray(piece, dtype=np.float64)) for piece in pieces]
    sd_centre, nearest, at_vertex = (np.stack(x, axis=1).reshape(-1, *x[0].shape[1:])
                                     for x in zip(*per_piece, strict=True))
    centres = np.repeat(pos, len(pieces), axis=0)
    obj_normal, rho = _unit((centres - nearest) * np.where(sd_centre < 0, -1.0, 1.0)[:, None])
    obj_points = np.stack([centres - radius * obj_normal, nearest], axis=1)
    w, h = arena
    walls = np.stack([pos[:, 0], w - pos[:, 0], pos[:, 1], h - pos[:, 1]], axis=1) - radius
    return SceneDistances(
        pair_i=pi, pair_j=pj, pair_distance=centre_dist - 2 * radius, pair_normal=normal,
        pair_points=pair_points, pair_curvature=1.0 / np.maximum(centre_dist, 1e-9),
        object_distance=sd_centre - radius, object_normal=obj_normal, object_points=obj_points,
        object_curvature=np.where(at_vertex & (sd_centre > 0), 1.0 / np.maximum(rho, 1e-9), 0.0),
        wall_distance=walls, wall_normal=WALL_NORMALS.copy(), pieces=len(pieces),
    )


# ----------------------------------------------------------------------------- FCL scene
class CollisionScene:
    """The FCL scene for ``num_robots`` discs, the scenario's object and the four walls.

    Args:
        scenario: arena, robot radius and object polygon (M, 2, counter-clockwise) [m].
        num_robots: N; may differ from ``scenario.num_robots`` (robots joining or leaving).
    """

    def __init__(self, scenario: Scenario, num_robots: int | None = None):
        self.radius = float(scenario.robot_radius)
        self.arena = (float(scenario.arena[0]), float(scenario.arena[1]))
        self.num_robots = int(scenario.num_robots if num_robots is None else num_robots)
        self.polygon_local = scenario.polygon - scenario.object_center   # object frame, centroid at 0
        self.polygon = scenario.polygon.copy()                           # world frame, updated by pose
        self.object_pose = np.array([*scenario.object_center, 0.0])
        self.positions = np.zeros((self.num_robots, 2))
        self.pair_i, self.pair_j = np.triu_indices(self.num_robots, 1)
        self._unsigned = fcl.DistanceRequest(enable_nearest_points=True)
        self._signed_request = fcl.DistanceRequest(enable_nearest_points=True,
                                                   enable_signed_distance=True)

        self.robot_geoms = [fcl.Sphere(self.radius) for _ in range(self.num_robots)]
        self._thinner = fcl.Sphere(self.radius - _TOUCH)
        self.robots = [fcl.CollisionObject(g, fcl.Transform()) for g in self.robot_geoms]
        self.pieces_local = convex_pieces(self.polygon_local)
        self.pieces = self.pieces_local                                  # world frame, by pose
        self.object_geoms = [_prism(p) for p in self.pieces_local]
        self.object_parts = [fcl.CollisionObject(g, fcl.Transform()) for g in self.object_geoms]
        w, h, t = self.arena[0], self.arena[1], _WALL_THICKNESS
        wall_boxes = [((-t / 2, h / 2), (t, h + 2 * t)), ((w + t / 2, h / 2), (t, h + 2 * t)),
                      ((w / 2, -t / 2), (w + 2 * t, t)), ((w / 2, h + t / 2), (w + 2 * t, t))]
        self.wall_geoms = [fcl.Box(sx, sy, 2 * _PRISM_HALF_HEIGHT) for _, (sx, sy) in wall_boxes]
        self.walls = [fcl.CollisionObject(g, fcl.Transform(np.array([cx, cy, 0.0])))
                      for g, ((cx, cy), _) in zip(self.wall_geoms, wall_boxes, strict=True)]
        self._set_object_pose(self.object_pose)
        # Which shape a broadphase contact refers to: the callback hands back the geometry objects.
        self._owner: dict[int, tuple[str, int]] = {}
        for kind, geoms in (("robot", self.robot_geoms), ("object", self.object_geoms),
                            ("wall", self.wall_geoms)):
            for k, g in enumerate(geoms):
                self._owner[id(g)] = (kind, k)
        self.manager = fcl.DynamicAABBTreeCollisionManager()
        self.manager.registerObjects(self.robots + self.object_parts + self.walls)
        self.manager.setup()

    # ------------------------------------------------------------------ state
    def _set_object_pose(self, pose: np.ndarray) -> None:
        c, s = np.cos(pose[2]), np.sin(pose[2])
        rot2 = np.array([[c, -s], [s, c]])
        rot3 = np.eye(3)
        rot3[:2, :2] = rot2
        for part in self.object_parts:
            part.setTransform(fcl.Transform(rot3, np.array([pose[0], pose[1], 0.0])))
        self.polygon = self.polygon_local @ rot2.T + pose[:2]
        self.pieces = [p @ rot2.T + pose[:2] for p in self.pieces_local]
        self.object_pose = np.asarray(pose, dtype=np.float64).copy()

    def object_pieces(self) -> list[np.ndarray]:
        """The object's convex pieces (its FCL parts) as (K, 2) counter-clockwise vertices in the
        world frame [m], at the current pose (the same list until the object moves)."""
        return self.pieces

    def set_object_pose(self, pose: np.ndarray) -> None:
        """Move the object to pose (x, y, theta) [m, rad] alone (the robots stay where they are)."""
        self._set_object_pose(np.asarray(pose, dtype=np.float64))
        self.manager.update()

    def update(self, positions: np.ndarray, object_pose: np.ndarray | None = None) -> None:
        """Move the robots to (N, 2) centres [m] (and the object to pose (x, y, theta) [m, rad])."""
        positions = np.asarray(positions, dtype=np.float64)
        if positions.shape != (self.num_robots, 2):
            raise ValueError(f"positions must have shape (num_robots, 2) = ({self.num_robots}, 2), "
                             f"got {positions.shape}")
        for obj, (x, y) in zip(self.robots, positions, strict=True):
            obj.setTranslation(np.array([x, y, 0.0]))
        if object_pose is not None:
            self._set_object_pose(np.asarray(object_pose, dtype=np.float64))
        self.positions = positions.copy()
        self.manager.update()

    # ------------------------------------------------------------------ queries
    def contacts(self) -> list[tuple[tuple[str, int], tuple[str, int]]]:
        """Every overlapping robot-robot, robot-object and robot-wall pair, from the broadphase.

        Returns sorted pairs such as ``(("robot", 2), ("wall", 0))``; pieces of a non-convex object
        are reported as ``("object", 0)``. Touching within FCL's tolerance counts as overlap.
        """
        total = len(self.robots) + len(self.object_parts) + len(self.walls)
        request = fcl.CollisionRequest(num_max_contacts=total * total)   # pairs only: no EPA (see _signed)
        data = fcl.CollisionData(request=request)
        self.manager.collide(data, fcl.defaultCollisionCallback)
        found: set[tuple[tuple[str, int], tuple[str, int]]] = set()
        for contact in data.result.contacts:
            owners = [self._owner[id(contact.o1)], self._owner[id(contact.o2)]]
            if "robot" not in (owners[0][0], owners[1][0]):
                continue                 # wall-wall corners, object pieces, object-wall
            owners = [("object", 0) if kind == "object" else (kind, k) for kind, k in owners]
            # robot first; two robots in index order
            owners.sort(key=lambda o: (o[0] != "robot", o))
            found.add((owners[0], owners[1]))
        return sorted(found)

    def distances(self) -> SceneDistances:
        """Signed distances, nearest points and normals of every robot pair, object and wall (FCL)."""
        n, r = self.num_robots, self.radius
        pi, pj = self.pair_i, self.pair_j
        pair_d = np.empty(len(pi))
        pair_pts = np.empty((len(pi), 2, 2))
        for k, (i, j) in enumerate(zip(pi, pj, strict=True)):
            pair_d[k], pair_pts[k] = self._signed(self.robots[i], self.robots[j], spheres=True)
        q = len(self.object_parts)
        obj_d, obj_pts = np.empty((n, q)), np.zeros((n, q, 2, 2))
        for i in range(n):
            for k, part in enumerate(self.object_parts):
                obj_d[i, k], obj_pts[i, k] = self._signed(self.robots[i], part)
        # GJK's witness points on the object are good to ~1e-5 m only: keep FCL's choice of the
        # nearest edge and its inside/outside verdict, and project the centre onto that edge.
        at_end = np.empty((n, q), dtype=bool)
        for k, piece in enumerate(self.pieces):
            obj_pts[:, k, 1], at_end[:, k] = self._snap_to_edge(self.positions, obj_pts[:, k, 1], piece)
        obj_d, obj_pts, at_end = obj_d.ravel(), obj_pts.reshape(n * q, 2, 2), at_end.ravel()
        pos = np.repeat(self.positions, q, axis=0)                         # one row per robot and piece
        (w, h), x, y = self.arena, self.positions[:, 0], self.positions[:, 1]
        wall_d = np.stack([x, w - x, y, h - y], axis=1) - r
        normal, centre_dist = _unit(self.positions[pi] - self.positions[pj])
        # Object normal: from the nearest object point towards the centre, flipped when the centre
        # is inside the object (then the nearest boundary point lies ahead of the centre).
        towards = pos - obj_pts[:, 1]
        inside = obj_d + r < 0
        obj_normal, rho = _unit(np.where(inside[:, None], -towards, towards))
        obj_d = np.where(inside, -rho, rho) - r      # exact distance to the snapped point
        on_boundary = rho < 1e-9     # centre on the boundary: point away from the centroid instead
        if np.any(on_boundary):
            obj_normal[on_boundary] = _unit(pos[on_boundary] - self.object_pose[:2])[0]
        obj_pts[:, 0] = pos - r * obj_normal
        at_vertex = at_end & ~inside
        return SceneDistances(
            pair_i=pi, pair_j=pj, pair_distance=pair_d, pair_normal=normal, pair_points=pair_pts,
            pair_curvature=1.0 / np.maximum(centre_dist, 1e-9),
            object_distance=obj_d, object_normal=obj_normal, object_points=obj_pts,
            object_curvature=np.where(at_vertex, 1.0 / np.maximum(rho, 1e-9), 0.0),
            wall_distance=wall_d, wall_normal=WALL_NORMALS.copy(), pieces=q,
        )

    @staticmethod
    def _snap_to_edge(centres: np.ndarray, near: np.ndarray, polygon: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Exact nearest points on the (M, 2) polygon's edges that pass within 1e-4 m of FCL's
        (N, 2) points, and whether each is an end of its edge (the projection was clamped: a
        vertex, as :func:`point_polygon` decides it)."""
        a = polygon[None]
        e = np.roll(polygon, -1, axis=0)[None] - a                       # (1, M, 2)
        len2 = np.sum(e * e, -1)

        def project(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:   # (N, M, 2), (N, M)
            t = np.sum((points[:, None] - a) * e, -1) / len2
            return a + np.clip(t, 0.0, 1.0)[..., None] * e, (t <= 0.0) | (t >= 1.0)

        fcl_gap = np.linalg.norm(near[:, None] - project(near)[0], axis=-1)   # (N, M)
        candidate = fcl_gap <= fcl_gap.min(axis=1, keepdims=True) + 1e-4
        onto, clamped = project(centres)
        centre_gap = np.where(candidate, np.linalg.norm(centres[:, None] - onto, axis=-1), np.inf)
        rows, best = np.arange(len(centres)), np.argmin(centre_gap, axis=1)
        return onto[rows, best], clamped[rows, best]

    def _signed(self, a: fcl.CollisionObject, b: fcl.CollisionObject,
                spheres: bool = False) -> tuple[float, np.ndarray]:
        """Signed distance and (2, 2) nearest points of two shapes.

        The plain query first: it is exact for sphere-sphere and sphere-box while they are apart,
        where the signed query (GJK) is off by up to 7e-4 m. Only on overlap (plain distance -1)
        the signed query (EPA) gives the depth, except for two spheres, where EPA never returns
        for coincident centres: their overlap is the closed form ``|c_a - c_b| - 2 r``; and
        except for shapes that (nearly) touch, where EPA throws a C++ ``std::logic_error`` that
        python-fcl does not catch, aborting the process (a robot touching the object's corner;
        FCL issues #390, #408, #445): when the robot's sphere made ``_TOUCH`` thinner is apart,
        the overlap is that gap less ``_TOUCH`` (within ``_TOUCH`` of zero), without EPA.
        """
        result = fcl.DistanceResult()
        d = fcl.distance(a, b, self._unsigned, result)
        if d <= 0.0:
            if spheres:
                ca, cb = a.getTranslation()[:2], b.getTranslation()[:2]
                gap = cb - ca
                norm = float(np.hypot(*gap))
                unit = gap / norm if norm > 1e-12 else np.array([1.0, 0.0])
                return norm - 2 * self.radius, np.array([ca + self.radius * unit, cb - self.radius * unit])
            thinner = fcl.CollisionObject(self._thinner, fcl.Transform(a.getRotation(), a.getTranslation()))
            result = fcl.DistanceResult()
            d = fcl.distance(thinner, b, self._unsigned, result) - _TOUCH
            if d < -_TOUCH:
                result = fcl.DistanceResult()
                d = fcl.distance(a, b, self._signed_request, result)
        return d, np.array([result.nearest_points[0][:2], result.nearest_points[1][:2]])
