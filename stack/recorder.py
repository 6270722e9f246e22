"""Flight recorder of stack episodes: where each robot went, what the stack asked of it, and why.

:func:`stack.episodes.run_episode` fills an :class:`EpisodeRecorder` tick by tick when given
one; :meth:`EpisodeRecorder.finish` returns an :class:`EpisodeRecord`, which saves to and loads
from one ``.npz`` file (:meth:`EpisodeRecord.save`, :func:`load_record`; no pickled objects) and
draws as a figure (:func:`stack.episode_plot.plot_episode`). ``formation eval --record DIR``
writes both for every episode; ``formation bridge --record DIR`` records every tick it answers
through a :class:`RecordedStack` (a file per fleet episode, stall and chunk of ticks).

Arrays of an episode of S ticks, robots in columns by id (the ids of the first state, then any
that joined, in order of appearance; a robot missing from a tick's rows is NaN / False there):

========================  ==============  =========================================================
``ids``                   (N,) str        robot ids
``time``                  (S,) s          the time of each tick's state
``measured``              (S, N, 2) m     positions the stack was given (NaN: row missing)
``targets``               (S, N, 2) m     each robot's target as the stack was given it
``positions``             (S+1, N, 2) m   true centres where the fleet has a true state (pymunk),
                                          else reported ones; index 0 is the start
``a_nom``                 (S, N, 2) m/s^2 the policy's command (docking and detours included)
``a_safe``                (S, N, 2) m/s^2 after the safety filter
``a_cmd``                 (S, N, 2) m/s^2 what was sent (MEC included; braking for stale rows)
``stale``, ``docking``,   (S, N) bool     :class:`stack.tick_types.TickResult`'s row flags
``detour``, ``present``                   ``present``: the robot had a row in the tick's state
``link_braked``           (S, N) bool     the link sent BRAKE in place of ``a_cmd`` (the bridge's
                                          age rule, a failed or late answer); ``a_cmd`` then
                                          holds the braking law at the measured velocity (a
                                          record written before this array: all False)
``frozen``                (S, N) bool     the world froze the robot (pymunk ``ModelError.freeze``)
``contacts``              (S, N, 3) bool  robot / object / wall contact after each tick (the
                                          fleet's own, else judged on ``positions``)
``safety_status``         (S,) str        the filter's status per tick ("" with the filter off)
``safety_reason``         (S,) str        the filter's reason, when it gives one (which robots the
                                          post-check braked, why the QP failed)
``obstacle_ids``          (K,) str        what a tracker saw that is none of the fleet's robots
                                          (``FleetState.obstacles``), in order of appearance
``obstacles``             (S, K, 4)       x, y [m] where it was seen, radius [m], age of the
                                          sighting [s]; NaN where the tick's state did not hold
                                          it (a record written before these arrays: K = 0)
========================  ==============  =========================================================

``meta`` (a JSON object): the scenario (:meth:`sim.scenario.Scenario.to_dict`), the seed, the
episode's metrics (:class:`stack.episodes.EpisodeMetrics`) and anything the caller adds.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sim.files import atomic_path
from sim.fleet import Fleet, FleetState

ARRAYS = ("ids", "time", "measured", "targets", "positions", "a_nom", "a_safe", "a_cmd", "stale", "docking", "detour",
          "present", "frozen", "contacts", "safety_status", "safety_reason", "link_braked", "obstacle_ids",
          "obstacles")
LATER_ARRAYS = ("link_braked", "obstacle_ids", "obstacles")     # absent from older records (load_record)
OBSTACLE_FIELDS = 4     # x, y, radius, age_s


class RecordError(ValueError):
    """A record file that cannot be read; the message names the file and what is wrong."""


@dataclass
class EpisodeRecord:
    """One recorded episode (module docstring for the arrays' shapes and units)."""

    ids: np.ndarray
    time: np.ndarray
    measured: np.ndarray
    targets: np.ndarray
    positions: np.ndarray
    a_nom: np.ndarray
    a_safe: np.ndarray
    a_cmd: np.ndarray
    stale: np.ndarray
    docking: np.ndarray
    detour: np.ndarray
    present: np.ndarray
    frozen: np.ndarray
    contacts: np.ndarray
    safety_status: np.ndarray
    safety_reason: np.ndarray
    link_braked: np.ndarray
    obstacle_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=str))
    obstacles: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.obstacles is None:
            self.obstacles = np.full((len(self.time), len(self.obstacle_ids), OBSTACLE_FIELDS), np.nan)

    @property
    def steps(self) -> int:
        return len(self.time)

    @property
    def num_robots(self) -> int:
        return len(self.ids)

    def save(self, path: str | Path) -> Path:
        """Write the record to ``path`` (``.npz``), atomically: a crash leaves the old file or none."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {name: getattr(self, name) for name in ARRAYS}
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, meta=np.array(json.dumps(self.meta)), **arrays)
        return path


def record_folder(folder: Path, flag: str) -> Path:
    """``folder`` made ready for records (created if missing); ValueError naming ``flag`` when it
    is a file or cannot be made."""
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{flag} {folder}: exists and is not a folder; give a folder for the records")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"{flag} {folder}: cannot create the folder ({exc.strerror})") from None
    return folder


_UNREADABLE = (OSError, ValueError, EOFError, KeyError, NotImplementedError, RuntimeError, zipfile.BadZipFile,
               zlib.error)
"""What reading a damaged ``.npz`` raises (empty: EOFError, truncated: BadZipFile, a damaged
member: zlib.error or a bad CRC, an unknown compression: NotImplementedError, a member flagged
encrypted: RuntimeError)."""
_AGAIN = "record the episode again (formation eval --record DIR, formation bridge --record DIR)"


def load_record(path: str | Path) -> EpisodeRecord:
    """The :class:`EpisodeRecord` saved at ``path`` (no pickled objects are read)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [name for name in (*ARRAYS, "meta") if name not in data.files and name not in LATER_ARRAYS]
            if missing:
                raise RecordError(f"{path}: not an episode record (no {', '.join(missing)}); "
                                  "write one with formation eval --record DIR")
            arrays = {name: data[name] for name in ARRAYS if name in data.files}
            arrays.setdefault("link_braked", np.zeros(arrays["stale"].shape, dtype=bool))
            meta = json.loads(str(data["meta"]))
    except _UNREADABLE as exc:
        if isinstance(exc, RecordError):
            raise
        raise RecordError(f"{path}: cannot read an episode record ({type(exc).__name__}: {exc}); the file "
                          f"is damaged or no record: {_AGAIN}") from None
    if not isinstance(meta, dict):
        raise RecordError(f"{path}: cannot read an episode record (its meta is a {type(meta).__name__}, "
                          f"not a JSON object): {_AGAIN}")
    return EpisodeRecord(**arrays, meta=meta)


VECTOR_ROWS = ("measured", "targets", "a_nom", "a_safe", "a_cmd")    # (N, 2) per tick, from the state or result
FLAG_ROWS = ("stale", "docking", "detour")                          # (N,) bool per tick, from the result


@dataclass
class _Tick:
    ids: tuple[str, ...]
    time: float
    rows: dict[str, np.ndarray]                   # VECTOR_ROWS and FLAG_ROWS of the tick's rows
    safety_status: str
    safety_reason: str
    state: FleetState | None = None              # the state given (until the next tick)
    after_ids: tuple[str, ...] | None = None     # None: the next tick's measurement tells
    positions: np.ndarray | None = None
    frozen: np.ndarray | None = None
    contacts: np.ndarray | None = None
    obstacles: dict[str, np.ndarray] = field(default_factory=dict)   # id -> (x, y, radius, age_s)


def _sightings(state: FleetState) -> dict[str, np.ndarray]:
    """The obstacles of ``state`` that are none of the fleet's robots, by id."""
    seen = state.obstacles
    if seen is None:
        return {}
    robots = seen.robots or (None,) * len(seen)
    return {name: np.array([*seen.positions[k], seen.radii[k], seen.age_s[k]])
            for k, name in enumerate(seen.ids) if robots[k] is None}


class EpisodeRecorder:
    """Collects one episode's ticks: :meth:`start`, :meth:`tick` per tick, then :meth:`finish`.

    With a fleet (``run_episode``) each tick also gets the fleet after its step: its true state
    where it has one, and its contacts. Without (a controller that sees only what the link
    brings, ``formation bridge --record``), ``positions`` are the measured ones and the
    contacts are judged on them (:func:`sim.metrics.collision_events`) when the scenario is
    known. ``scenario`` (or the fleet's) is stored in the record's meta.
    """

    def __init__(self, scenario=None) -> None:
        self._start: tuple[tuple[str, ...], np.ndarray] | None = None
        self._ticks: list[_Tick] = []
        self._scenario = scenario

    def __len__(self) -> int:
        return len(self._ticks)

    def start(self, fleet: Fleet | None, state: FleetState) -> None:
        """The episode's first state (after the fleet's reset)."""
        self._start = _where(fleet, state)
        self._ticks = []
        self._scenario = getattr(fleet, "scenario", None) or self._scenario

    def tick(self, state: FleetState, result, fleet: Fleet | None = None, after: FleetState | None = None,
             contacts: np.ndarray | None = None) -> None:
        """One tick: the ``state`` the stack was given and its :class:`~stack.tick_types.TickResult`;
        with a fleet, the fleet once it stepped, the state it then reported and the (N', 3) bool
        contacts of that state's rows."""
        if self._start is None:
            self.start(fleet, state)
        status = result.safety_status
        rows = {"measured": np.array(state.positions, dtype=float), "targets": np.array(state.targets, dtype=float),
                **{name: np.array(getattr(result, name), dtype=float) for name in VECTOR_ROWS[2:]},
                **{name: np.array(getattr(result, name), dtype=bool) for name in FLAG_ROWS}}
        if self._ticks:
            self._ticks[-1].state = None
        t = _Tick(ids=tuple(state.robot_ids), time=float(state.time), rows=rows,
                  safety_status="" if status is None else str(status), safety_reason=result.safety_reason,
                  state=state, obstacles=_sightings(state))
        if after is not None:
            t.after_ids, t.positions = _where(fleet, after)
            frozen = getattr(fleet, "frozen", None)
            t.frozen = None if frozen is None else np.array(frozen, dtype=bool)
            t.contacts = None if contacts is None else np.array(contacts, dtype=bool)
        self._ticks.append(t)

    def link_braked(self, state: FleetState, braked: np.ndarray, brake: np.ndarray) -> None:
        """The link sent BRAKE to the rows ``braked`` (N,) bool of ``state`` (the last tick's)
        in place of the stack's command; ``brake`` (N, 2): the braking law at their velocity
        [m/s^2]. A tick not recorded (the stack raised) is left out."""
        if not self._ticks or self._ticks[-1].state is not state:
            return
        rows = self._ticks[-1].rows
        rows["link_braked"] = np.array(braked, dtype=bool)
        rows["a_cmd"] = np.where(rows["link_braked"][:, None], brake, rows["a_cmd"])

    def finish(self, meta: dict[str, Any] | None = None) -> EpisodeRecord:
        """The recorded episode; ``meta`` is stored with it (with the scenario, unless ``meta``
        names one)."""
        if self._start is None:
            raise RuntimeError("EpisodeRecorder.finish before start")
        ticks = self._ticks
        for k, t in enumerate(ticks):                     # measured: the next state is where it went
            if t.after_ids is None:
                nxt = ticks[k + 1] if k + 1 < len(ticks) else t
                t.after_ids, t.positions = nxt.ids, nxt.rows["measured"]
        start_ids, start_pos = self._start
        ids = list(dict.fromkeys([*start_ids, *(i for t in ticks for i in (*t.ids, *t.after_ids))]))
        column = {rid: k for k, rid in enumerate(ids)}
        s, n = len(ticks), len(ids)
        obstacle_ids = list(dict.fromkeys(i for t in ticks for i in t.obstacles))
        obstacle_column = {name: j for j, name in enumerate(obstacle_ids)}

        def table(width: tuple[int, ...], dtype, fill) -> np.ndarray:
            return np.full((s, n, *width), fill, dtype=dtype)

        rec = EpisodeRecord(
            ids=np.array(ids, dtype=str), time=np.array([t.time for t in ticks], dtype=float),
            positions=np.full((s + 1, n, 2), np.nan),
            **{name: table((2,), float, np.nan) for name in VECTOR_ROWS},
            **{name: table((), bool, False) for name in (*FLAG_ROWS, "present", "frozen", "link_braked")},
            contacts=table((3,), bool, False),
            safety_status=np.array([t.safety_status for t in ticks], dtype=str),
            safety_reason=np.array([t.safety_reason for t in ticks], dtype=str),
            obstacle_ids=np.array(obstacle_ids, dtype=str), meta=dict(meta or {}))
        if self._scenario is not None:
            rec.meta.setdefault("scenario", self._scenario.to_dict())
        rec.meta = json.loads(json.dumps(rec.meta))        # as a loaded record holds it
        rec.positions[0, [column[i] for i in start_ids]] = start_pos
        judged = True
        for k, t in enumerate(ticks):
            rows = [column[i] for i in t.ids]
            for name, value in t.rows.items():
                getattr(rec, name)[k, rows] = value
            rec.present[k, rows] = True
            after = [column[i] for i in t.after_ids]
            rec.positions[k + 1, after] = t.positions
            judged &= t.contacts is not None
            if t.contacts is not None:
                rec.contacts[k, after] = t.contacts
            if t.frozen is not None and len(t.frozen) == len(after):
                rec.frozen[k, after] = t.frozen
            for name, seen in t.obstacles.items():
                rec.obstacles[k, obstacle_column[name]] = seen
        if not judged and self._scenario is not None and s:
            rec.contacts = _contacts(rec.positions[1:], self._scenario)
        return rec


class RecordedStack:
    """A :class:`stack.pipeline.ControlStack` whose every tick is recorded (``formation bridge
    --record DIR``); anything else is the stack's own.

    Ticks are recorded as the link brought them (:class:`EpisodeRecorder` without a fleet). A
    record closes when the stack is reset (a new fleet episode, a stall of the bridge), after
    ``chunk_ticks`` ticks (at the next tick, or reset or close, so that the link's brake of its
    last tick, :meth:`sent_braking`, reaches it) and at :meth:`close`, and a writer thread, off the control loop, saves it
    as ``folder/record_KKKKK.npz`` (meta: its index, why it closed, ``meta``). A record that
    cannot be written is reported on stderr and the loop goes on; :meth:`close` waits for the
    writer, so Ctrl-C loses nothing.
    """

    def __init__(self, stack, folder: str | Path, chunk_ticks: int = 1200, meta: dict[str, Any] | None = None):
        if not isinstance(chunk_ticks, int) or chunk_ticks < 1:
            raise ValueError(f"chunk_ticks must be a positive integer, got {chunk_ticks!r}")
        import queue
        import threading

        self.stack, self.folder, self.chunk_ticks = stack, Path(folder), chunk_ticks
        self.meta, self.written, self.failed = dict(meta or {}), [], []
        self._recorder, self._index = EpisodeRecorder(stack.scenario), 0
        self._queue: queue.Queue = queue.Queue()
        self._writer = threading.Thread(target=self._write_all, name="RecordedStack-writer", daemon=True)
        self._writer.start()

    def tick(self, state: FleetState):
        if len(self._recorder) >= self.chunk_ticks:     # closed here, not after the last tick: the
            self._close_record("chunk")                 # link's brake of that tick (sent_braking) is in it
        result = self.stack.tick(state)
        self._recorder.tick(state, result)
        return result

    __call__ = tick

    def sent_braking(self, state: FleetState, braked: np.ndarray) -> None:
        """:meth:`stack.pipeline.ControlStack.sent_braking`, and the record's row marked."""
        self.stack.sent_braking(state, braked)
        self._recorder.link_braked(state, braked, self.stack.brake(state.velocities))

    def reset(self) -> None:
        self._close_record("reset")
        self.stack.reset()

    def close(self) -> list[Path]:
        """Save the running record, wait for the writer; the paths written."""
        self._close_record("exit")
        self._queue.put(None)
        self._writer.join()
        return self.written

    def __getattr__(self, name: str):
        return getattr(self.stack, name)

    def _close_record(self, reason: str) -> None:
        """Hand the running record to the writer (``reason``: why it closed; "chunk" when it is
        full, whatever closes it) and start a new one."""
        if len(self._recorder):
            reason = "chunk" if len(self._recorder) >= self.chunk_ticks else reason
            meta = {**self.meta, "index": self._index, "closed_by": reason}
            self._queue.put((self._recorder, self.folder / f"record_{self._index:05d}.npz", meta))
            self._index += 1
        self._recorder = EpisodeRecorder(self.stack.scenario)

    def _write_all(self) -> None:
        import sys

        while (job := self._queue.get()) is not None:
            recorder, path, meta = job
            try:
                self.written.append(recorder.finish(meta).save(path))
            except Exception as exc:  # a full disk must not stop the fleet's controller
                self.failed.append(str(path))
                print(f"warning: record {path} not written: {exc}", file=sys.stderr, flush=True)


def _contacts(positions: np.ndarray, scenario) -> np.ndarray:
    """(S, N, 3) bool robot / object / wall contact of (S, N, 2) positions (NaN: none)."""
    import torch

    from sim.metrics import collision_events

    pos = torch.from_numpy(np.nan_to_num(positions, nan=-1e3))     # far outside: touches no robot
    ev = collision_events(pos, torch.as_tensor(scenario.polygon, dtype=torch.float64), scenario.robot_radius,
                          scenario.arena)
    out = torch.stack((ev.robot, ev.object, ev.wall), -1).numpy()
    return out & np.isfinite(positions).all(-1)[..., None]


def _where(fleet: Fleet | None, state: FleetState) -> tuple[tuple[str, ...], np.ndarray]:
    """Ids and (N, 2) positions of the fleet now: its true state where it has one."""
    true_state = getattr(fleet, "true_state", None)
    if true_state is not None:
        state = true_state()
    return tuple(state.robot_ids), np.array(state.positions, dtype=float)


__all__ = ["ARRAYS", "EpisodeRecord", "EpisodeRecorder", "RecordError", "RecordedStack", "load_record",
           "record_folder"]
