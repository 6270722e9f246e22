r"""Detour: a robot stuck away from its target is led round what holds it.

A learned policy never met a robot that stopped for good in its way. When a robot drops from
the link in a corridor the others need, the safety filter keeps them off it, but a policy that
pushes on into it gets nothing through the filter and its robot stands there for the rest of
the episode. Traced (paper-5, an own-target generalist, robot 3 silent from tick 15 in the
corridor above the object): robot 2 stood at the top wall from tick 60 to the end, 0.52 m from
the nearest target, its policy asking 1 m/s^2 up and to the left (into the wall, towards the
gap above the silent robot), the filter answering 0.

**When.** A movable robot that is not docking is *stuck* once it has stayed, for ``after_s`` in a
row, within ``STUCK_DRIFT`` of where that stretch began while asked for at least ``STUCK_PUSH``
(the policy wants it to move, something holds it), and is farther than ``stall_radius`` from
every target (it has not arrived). Where it stays counts, not how fast it goes: traced over Zenoh (paper-5, an
own-target generalist, robot 4 dropped at tick 15 near the top wall), its two neighbours,
pushed into the wall and held off the silent robot by the filter, jittered in place at 2-8
cm/s for the last 11 s, 0.4-0.6 m from their targets, moving 5-17 mm in any second: a 2 cm/s
speed threshold never held them long enough. It then follows a detour until it comes within
``stall_radius`` of a target (where docking's second tier takes it), no path exists, or
``MAX_S`` have passed; a robot that stalls on
its detour is stuck again and replans.

**Path.** On a grid of ``CELL`` over the arena, a cell is free when a robot centred there keeps
``CLEARANCE`` to the walls and the object and ``2 r + CLEARANCE`` to every other robot standing
(slower than ``MOVING_SPEED``, at its centre as the stack sees it: a silent robot where it must
have stopped; a robot on the move will be elsewhere, and the filter keeps the two apart: planned
round, the second of two robots detouring in single file down one corridor found no path) and ``r + CLEARANCE``
to every disc the safety filter last kept round a robot not listening (so the path does not
lead where the filter will not let the robot go); the robot's target is its match under the
least total distance, docking's (:func:`controllers.docking.least_distance_matching`); the path
is the shortest 8-connected one between the free cells nearest the robot and the target
(Dijkstra, :func:`scipy.sparse.csgraph.dijkstra`), planned again every ``REPLAN_TICKS``.

**Law** (per detouring robot, m/s^2; ``w`` the path point ``LOOKAHEAD`` cells ahead, ``d`` the
path length left)::

    v_des = min(SPEED, sqrt(2 BRAKE d)) (w - p) / |w - p|
    a     = clip_norm(GAIN (v_des - v), accel_limit)

The result goes through the safety filter like any command: a detour never bypasses it.
``SPEED`` is 0.3 m/s: at 0.2, the traced run above brought both neighbours round the object
only 60-180 mm short of their targets when its 12 s ended; at 0.3 they were docked, and over 40
fleet-sim + bridge runs with a robot leaving the mean summed distance of the others left went
from 91 to 77 mm, the same 26 runs all home, no contact (docs/safety.md, Detours).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from controllers import docking_kernels
from controllers.docking import least_distance_matching
from controllers.jit import f64
from controllers.safety.geometry import point_polygon
from sim.scenario import clip_norm

CELL = 0.01            # [m] grid spacing
CLEARANCE = 0.03       # [m] kept to walls, object and other robots
STUCK_DRIFT = 0.02     # [m] a held robot stays this close to where it was after_s ago
STUCK_PUSH = 0.2       # [m/s^2]
MAX_S = 8.0            # [s] longest detour before the policy has its robot back
REPLAN_TICKS = 10
LOOKAHEAD = 6          # [cells]
SPEED = 0.3            # [m/s]
BRAKE = 0.5            # [m/s^2]
GAIN = 4.0             # [1/s]
MOVING_SPEED = 0.05    # [m/s] robots faster than this are not planned round (the filter keeps them apart)
_STEPS = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))


class Detour:
    """Per-robot stuck counters and detours, keyed by robot id (module docstring)."""

    def __init__(self, robot_radius: float, accel_limit: float, arena: tuple[float, float],
                 polygon: np.ndarray, dt: float, after_s: float, stall_radius: float):
        self.radius, self.accel_limit, self.dt = float(robot_radius), float(accel_limit), float(dt)
        self.after_ticks = max(1, int(round(after_s / dt)))
        self.stall_radius = float(stall_radius)
        w, h = arena
        xs, ys = np.arange(CELL / 2, w, CELL), np.arange(CELL / 2, h, CELL)
        self.shape = (len(xs), len(ys))
        self.centres = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)   # (X*Y, 2)
        keep = self.radius + CLEARANCE
        walls = np.minimum(np.minimum(self.centres[:, 0], w - self.centres[:, 0]),
                           np.minimum(self.centres[:, 1], h - self.centres[:, 1]))
        self.static_free = (walls >= keep) & (point_polygon(self.centres, np.asarray(polygon, float))[0] >= keep)
        self._edges = _grid_edges(*self.shape)
        self.reset()

    def reset(self) -> None:
        self._stuck: dict[str, int] = {}       # id -> ticks held within STUCK_DRIFT of its anchor
        self._anchor: dict[str, np.ndarray] = {}
        self._paths: dict[str, tuple[np.ndarray, int, int]] = {}   # id -> (path (K, 2), planned at, started at)
        self._tick = 0

    def __call__(self, ids: tuple[str, ...], pos: np.ndarray, vel: np.ndarray, targets: np.ndarray,
                 a_nom: np.ndarray, movable: np.ndarray,
                 discs: Callable[[], np.ndarray | None] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) commands with detouring robots' rows replaced, and (N,) bool of those rows.
        ``pos``, ``vel``, ``targets``, ``a_nom``: (N, 2) [m, m/s, m, m/s^2]; ``movable`` (N,) bool:
        robots that may detour (not stale, silent or docking); ``discs()`` gives (K, 3): centre
        x, y and radius [m] of the safety filter's fixed obstacles (the discs that bound robots
        not listening, grown by what is not known of them), kept clear like robots; asked only
        when a robot plans."""
        self._tick += 1
        n = len(pos)
        detour = np.zeros(n, dtype=bool)
        pushed = ((a_nom * a_nom).sum(1) >= STUCK_PUSH**2) & movable
        if not self._paths and not pushed.any():        # nobody pushed, none on a detour
            if self._stuck:
                self._stuck.clear()
                self._anchor.clear()
            return a_nom, detour
        self._count_held(ids, pos, pushed)
        if not self._paths and max(self._stuck.values(), default=0) < self.after_ticks:
            return a_nom, detour                        # the usual tick: no distance computed
        dist = np.empty((n, n))
        docking_kernels.target_distances(f64(pos), f64(targets), dist)
        match = least_distance_matching(dist)
        near = dist.min(axis=1) <= self.stall_radius
        for i in np.flatnonzero(near):
            self._stuck.pop(ids[i], None)
            self._anchor.pop(ids[i], None)
        wanted = [i for i, rid in enumerate(ids) if movable[i] and not near[i]
                  and (rid in self._paths or self._stuck.get(rid, 0) >= self.after_ticks)]
        keep = {ids[i] for i in wanted}
        self._paths = {rid: p for rid, p in self._paths.items() if rid in keep}
        if not wanted:
            return a_nom, detour
        out = np.array(a_nom, dtype=np.float64)
        for i in wanted:
            path = self._path(ids[i], i, pos, vel, targets[match[i]], discs)
            if path is None:
                continue
            out[i], detour[i] = self._follow(path, pos[i], vel[i]), True
        return out, detour

    def _count_held(self, ids: tuple[str, ...], pos: np.ndarray, pushed: np.ndarray) -> None:
        """Ticks each pushed robot has stayed within ``STUCK_DRIFT`` of its anchor (the first tick
        counts); a robot not pushed, or gone, is forgotten; one that drifted starts over here."""
        for i, rid in enumerate(ids):
            anchor = self._anchor.get(rid)
            if not pushed[i]:
                if anchor is not None:
                    del self._anchor[rid], self._stuck[rid]
            elif anchor is None or ((pos[i] - anchor) ** 2).sum() > STUCK_DRIFT**2:
                self._anchor[rid], self._stuck[rid] = np.array(pos[i], dtype=np.float64), 1
            else:
                self._stuck[rid] += 1
        if len(self._anchor) > np.count_nonzero(pushed):
            present = set(ids)
            for rid in [r for r in self._anchor if r not in present]:
                del self._anchor[rid], self._stuck[rid]

    def _path(self, rid: str, i: int, pos: np.ndarray, vel: np.ndarray, target: np.ndarray,
              discs: Callable[[], np.ndarray | None] | None) -> np.ndarray | None:
        """Robot ``i``'s path (K, 2) [m], planned when it is stuck or its plan is due."""
        planned = self._paths.get(rid)
        if planned is not None and self._tick - planned[2] > MAX_S / self.dt:
            del self._paths[rid]
            self._stuck[rid] = 0
            return None
        if planned is None or self._stuck.get(rid, 0) >= self.after_ticks or self._tick - planned[1] >= REPLAN_TICKS:
            standing = (vel * vel).sum(1) < MOVING_SPEED**2
            standing[i] = False
            path = self.plan(pos[i], target, pos[standing], None if discs is None else discs())
            if path is None:                     # try again in REPLAN_TICKS if still held
                self._paths.pop(rid, None)
                self._stuck[rid] = max(0, self.after_ticks - REPLAN_TICKS)
                return None
            started = self._tick if planned is None else planned[2]
            self._paths[rid] = planned = (path, self._tick, started)
            self._stuck[rid] = 0
        path = planned[0]
        k = int(np.argmin(np.linalg.norm(path - pos[i], axis=1)))       # where along it the robot is
        return path[k:]

    def plan(self, start: np.ndarray, goal: np.ndarray, others: np.ndarray,
             discs: np.ndarray | None = None) -> np.ndarray | None:
        """Shortest free path (K, 2) [m] of cell centres from near ``start`` to near ``goal``
        round the walls, the object, robots at ``others`` (M, 2) and ``discs`` (K, 3: centre,
        radius); None when there is none."""
        free = self.static_free.copy()
        for c in others:
            self._block(free, c[0], c[1], 2 * self.radius + CLEARANCE)
        for x, y, radius in (() if discs is None else discs):
            self._block(free, x, y, self.radius + radius + CLEARANCE)
        cells = np.flatnonzero(free)
        if len(cells) == 0:
            return None
        s = cells[np.argmin(np.linalg.norm(self.centres[cells] - start, axis=1))]
        g = cells[np.argmin(np.linalg.norm(self.centres[cells] - goal, axis=1))]
        if np.linalg.norm(self.centres[g] - goal) > self.stall_radius:
            return None                                  # the target itself is held
        src, dst, cost = self._edges
        ok = free[src] & free[dst]
        graph = coo_matrix((cost[ok], (src[ok], dst[ok])), shape=(len(free), len(free))).tocsr()
        dist, pred = dijkstra(graph, indices=g, return_predecessors=True)
        if not np.isfinite(dist[s]):
            return None
        order = [s]
        while order[-1] != g:
            order.append(pred[order[-1]])
        return np.vstack([self.centres[order], goal])

    def _block(self, free: np.ndarray, x: float, y: float, reach: float) -> None:
        """Mark the cells whose centre lies closer than ``reach`` [m] to ``(x, y)`` as not free,
        in place on ``free`` (X*Y,); only the cells of the square round it are measured."""
        nx, ny = self.shape
        x0, x1 = max(int(math.floor((x - reach) / CELL)) - 1, 0), min(int(math.ceil((x + reach) / CELL)) + 1, nx)
        y0, y1 = max(int(math.floor((y - reach) / CELL)) - 1, 0), min(int(math.ceil((y + reach) / CELL)) + 1, ny)
        if x0 >= x1 or y0 >= y1:
            return
        window = self.centres.reshape(nx, ny, 2)[x0:x1, y0:y1]
        free.reshape(nx, ny)[x0:x1, y0:y1] &= np.hypot(window[..., 0] - x, window[..., 1] - y) >= reach

    def _follow(self, path: np.ndarray, p: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The detour law (module docstring) for a robot at ``p``, ``v`` on ``path``."""
        w = path[min(LOOKAHEAD, len(path) - 1)]
        left = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum() + np.linalg.norm(path[0] - p))
        heading = w - p
        norm = float(np.linalg.norm(heading))
        v_des = np.zeros(2) if norm < 1e-9 else min(SPEED, math.sqrt(2 * BRAKE * left)) * heading / norm
        return clip_norm(GAIN * (v_des - v), self.accel_limit)


def _grid_edges(nx: int, ny: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every 8-connected step inside an ``nx`` x ``ny`` grid (cells numbered row-major over
    ``(x, y)``): ``(from (E,), to (E,), length in cells (E,))``."""
    ix, iy = np.unravel_index(np.arange(nx * ny), (nx, ny))
    src, dst, cost = [], [], []
    for dx, dy in _STEPS:
        jx, jy = ix + dx, iy + dy
        inside = (jx >= 0) & (jx < nx) & (jy >= 0) & (jy < ny)
        src.append(np.flatnonzero(inside))
        dst.append(np.ravel_multi_index((jx[inside], jy[inside]), (nx, ny)))
        cost.append(np.full(np.count_nonzero(inside), math.hypot(dx, dy)))
    return np.concatenate(src), np.concatenate(dst), np.concatenate(cost)


__all__ = ["Detour"]
