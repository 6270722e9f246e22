"""The flight recorder (stack.recorder) and its figure (stack.episode_plot): a real pymunk episode
with a robot frozen mid-way, recorded tick by tick, saved, loaded and drawn; robot modes and the
id columns on hand-built ticks."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.scripted import ScriptedController
from sim.fleet import FleetState
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import make_scenario
from stack.cli import main
from stack.episode_plot import Mode, assigned_distances, plot_episode, robot_modes
from stack.episodes import run_episode
from stack.pipeline import ControlStack, StackConfig
from stack.recorder import EpisodeRecord, EpisodeRecorder, RecordError, load_record
from stack.tick_types import PolicyStatus, TickResult

FROZEN, AT = 1, 10          # robot 1 freezes at tick 10 (silent and deaf)


@pytest.fixture(scope="module")
def frozen_episode():
    """paper-3, scripted, filter + MEC + docking on, robot 1 frozen at tick 10, 60 ticks; the
    TickResults and the world's true positions are captured beside the recorder."""
    sc = make_scenario("paper-3")
    world = PymunkWorld(sc, ModelError(freeze=(FROZEN, AT)))
    stack = ControlStack(sc, ScriptedController(sc), StackConfig())
    results, truth = [], []
    real_tick, real_step = stack.tick, world.step

    def tick(state):
        results.append(real_tick(state))
        return results[-1]

    def step():
        out = real_step()
        truth.append(world.true_state().positions.copy())
        return out

    stack.tick, world.step = tick, step
    recorder = EpisodeRecorder()
    metrics = run_episode(world, stack, 3, 60, recorder=recorder)
    start = PymunkWorld(sc).reset(seed=3).positions
    return sc, recorder.finish({"seed": 3, "metrics": metrics.to_dict()}), results, np.array(truth), start, metrics


def test_the_record_holds_what_the_stack_asked_and_where_the_robots_went(frozen_episode):
    sc, rec, results, truth, start, _ = frozen_episode
    assert (rec.steps, rec.num_robots) == (60, 3) and list(rec.ids) == ["r0", "r1", "r2"]
    np.testing.assert_allclose(rec.time, np.arange(60) * sc.dynamics.dt, atol=1e-12)
    np.testing.assert_array_equal(rec.targets, np.broadcast_to(sc.targets, (60, 3, 2)))
    for name in ("a_nom", "a_safe", "a_cmd", "stale", "docking", "detour"):
        np.testing.assert_array_equal(getattr(rec, name), np.stack([getattr(r, name) for r in results]))
    assert rec.safety_reason.tolist() == [r.safety_reason for r in results]
    assert rec.safety_status.tolist() == [str(r.safety_status) for r in results]
    np.testing.assert_array_equal(rec.positions[1:], truth)
    np.testing.assert_allclose(rec.positions[0], start, atol=0.0)
    assert rec.present.all() and not rec.contacts.any()


def test_the_frozen_robot_is_marked_from_its_tick_and_turns_stale_three_ticks_later(frozen_episode):
    """The world freezes robot 1 from tick 10: the state after tick 9's step is its last report,
    so the stack sees it age 0.05 s a tick and calls it stale once the age reaches 0.15 s
    (``stale_after_s``; 3 ticks, to rounding: tick 12 or 13), from then on to the end."""
    sc, rec, _, _, _, _ = frozen_episode
    assert np.flatnonzero(rec.frozen[:, FROZEN]).tolist() == list(range(AT - 1, 60))
    assert not rec.frozen[:, [0, 2]].any()
    np.testing.assert_array_equal(rec.measured[AT:, FROZEN], np.repeat(rec.measured[AT - 1:AT, FROZEN], 60 - AT, 0))
    first = np.flatnonzero(rec.stale[:, FROZEN])[0]
    assert first in (AT + 2, AT + 3) and rec.stale[first:, FROZEN].all()
    assert not rec.stale[:, [0, 2]].any()
    modes = robot_modes(rec, sc.dynamics.accel_limit)
    assert (modes[first:, FROZEN] == Mode.STALE).all()


def test_a_record_survives_the_file_and_draws(frozen_episode, tmp_path):
    sc, rec, _, _, _, metrics = frozen_episode
    path = rec.save(tmp_path / "deep" / "episode_3.npz")
    back = load_record(path)
    for name in ("ids", "time", "measured", "positions", "a_nom", "a_cmd", "stale", "frozen", "contacts",
                 "safety_status", "safety_reason"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name))
    assert back.meta == rec.meta and back.meta["metrics"]["final_distance"] == metrics.final_distance
    dist, sigma = assigned_distances(back)
    assert dist.shape == (61, 3) and sorted(sigma.tolist()) == [0, 1, 2]
    assert dist[-1].mean() == pytest.approx(metrics.final_distance, abs=1e-9)
    png = plot_episode(back, sc, tmp_path / "episode_3.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 50_000
    assert main(["plot", str(path), "--out", str(tmp_path / "again")]) == 0      # the command redraws it
    assert (tmp_path / "again" / "episode_3.png").stat().st_size > 50_000
    assert main(["plot", str(path), str(tmp_path)]) == 2
    np.savez(tmp_path / "other.npz", time=np.zeros(3))
    with pytest.raises(RecordError, match="not an episode record .*ids"):
        load_record(tmp_path / "other.npz")
    with pytest.raises(RecordError, match="cannot read"):
        load_record(tmp_path / "episode_3.png")


def _tick(rows: int, **flags) -> TickResult:
    a = np.zeros((rows, 2))
    return TickResult(a_nom=flags.pop("a_nom", a), a_safe=flags.pop("a_safe", a), a_cmd=a,
                      policy_status=PolicyStatus.OK, safety_status=None, mec_status=None,
                      **{k: np.asarray(flags.get(k, np.zeros(rows)), dtype=bool) for k in ("stale", "docking", "detour")})


def _state(ids, step: int) -> FleetState:
    n = len(ids)
    pos = np.column_stack([np.arange(n) * 0.1 + 0.2, np.full(n, 0.1 * step + 0.1)])
    return FleetState(time=0.05 * step, step=step, positions=pos, velocities=np.zeros((n, 2)),
                      targets=pos.copy(), object_pose=np.array([0.5, 0.5, 0.0]), robot_ids=tuple(ids))


def test_robots_that_leave_and_join_keep_their_columns():
    """r1 drops off the link after tick 0; r3 joins at tick 2: every robot keeps its column,
    NaN and absent where it had no row."""
    ticks = [("r0", "r1", "r2"), ("r0", "r2"), ("r0", "r2", "r3")]
    rec = EpisodeRecorder()
    rec.start(None, _state(ticks[0], 0))
    for k, ids in enumerate(ticks):
        after = ticks[k + 1] if k + 1 < len(ticks) else ids
        rec.tick(_state(ids, k), _tick(len(ids)), None, _state(after, k + 1), np.zeros((len(after), 3), bool))
    out = rec.finish()
    assert list(out.ids) == ["r0", "r1", "r2", "r3"]
    np.testing.assert_array_equal(out.present, [[1, 1, 1, 0], [1, 0, 1, 0], [1, 0, 1, 1]])
    assert np.isnan(out.measured[1, 1]).all() and np.isnan(out.positions[1:, 1]).all()
    np.testing.assert_allclose(out.measured[2, 3], [0.4, 0.3])       # r3, the third row at step 2
    np.testing.assert_allclose(out.positions[0, :3, 1], 0.1)
    assert (robot_modes(out, 1.0)[~out.present] == Mode.ABSENT).all()


def test_modes_say_which_layer_drove_each_robot():
    """Hand-built tick of five robots: as asked (its 2 m/s^2 only clipped to the 1 m/s^2 norm,
    which the filter does not count), docking, a detour, a docking command the filter changed by
    0.1 m/s^2, and a stale robot."""
    a_nom = np.array([[2.0, 0.0], [0.1, 0.0], [0.0, 0.2], [0.3, 0.0], [0.0, 0.0]])
    a_safe = np.array([[1.0, 0.0], [0.1, 0.0], [0.0, 0.2], [0.2, 0.0], [-0.5, 0.0]])
    flags = {"docking": [0, 1, 0, 1, 0], "detour": [0, 0, 1, 0, 0], "stale": [0, 0, 0, 0, 1]}
    t = _tick(5, a_nom=a_nom, a_safe=a_safe, **flags)
    rec = EpisodeRecord(ids=np.array(["a", "b", "c", "d", "e"]), time=np.zeros(1), measured=np.zeros((1, 5, 2)),
                        targets=np.zeros((1, 5, 2)),
                        positions=np.zeros((2, 5, 2)), a_nom=a_nom[None], a_safe=a_safe[None], a_cmd=a_safe[None],
                        stale=t.stale[None], docking=t.docking[None], detour=t.detour[None],
                        present=np.ones((1, 5), bool), frozen=np.zeros((1, 5), bool),
                        contacts=np.zeros((1, 5, 3), bool), safety_status=np.array([""]),
                        safety_reason=np.array([""]), link_braked=np.zeros((1, 5), bool))
    expected = [Mode.POLICY, Mode.DOCKING, Mode.DETOUR, Mode.FILTER, Mode.STALE]
    assert robot_modes(rec, accel_limit=1.0)[0].tolist() == expected
    assert robot_modes(rec, accel_limit=1.0, tolerance=0.2)[0, 3] == Mode.DOCKING


def test_a_brake_the_link_sent_in_place_is_recorded_as_sent_and_old_records_still_load(tmp_path):
    """Tick 1 of three: the link braked r1 in place of the stack's command (0.3, 0) while the
    robot moved at (0.2, 0) m/s: the record holds the braking law there (-0.2 / 0.05 clipped to
    1 m/s^2: (-1, 0)), flags it, and the figure's mode is LINK; a brake for a state that is not
    the last tick's (one the stack raised on) is left out. A record saved before the array
    existed loads with it all False."""
    rec = EpisodeRecorder()
    states = [_state(("r0", "r1"), k) for k in range(3)]
    for k, state in enumerate(states):
        result = _tick(2)
        result.a_cmd[:] = [0.3, 0.0]
        rec.tick(state, result, None, states[min(k + 1, 2)], np.zeros((2, 3), bool))
        if k == 1:
            rec.link_braked(state, np.array([False, True]), np.array([[0.0, 0.0], [-1.0, 0.0]]))
            rec.link_braked(states[0], np.array([True, True]), np.zeros((2, 2)))
    out = rec.finish()
    np.testing.assert_array_equal(out.link_braked, [[0, 0], [0, 1], [0, 0]])
    np.testing.assert_array_equal(out.a_cmd[:, 1], [[0.3, 0.0], [-1.0, 0.0], [0.3, 0.0]])
    np.testing.assert_array_equal(out.a_cmd[:, 0], np.tile([0.3, 0.0], (3, 1)))
    assert robot_modes(out, 1.0)[1].tolist() == [Mode.POLICY, Mode.LINK]
    path = out.save(tmp_path / "new.npz")
    with np.load(path) as data:
        np.savez(tmp_path / "old.npz", **{k: data[k] for k in data.files if k != "link_braked"})
    old = load_record(tmp_path / "old.npz")
    assert old.link_braked.shape == (3, 2) and not old.link_braked.any()
    np.testing.assert_array_equal(load_record(path).link_braked, out.link_braked)


def test_a_recorded_stack_passes_the_brake_on_and_marks_its_record(tmp_path):
    """formation bridge --record: the bridge's on_sent reaches the stack (its command history
    holds the brake) and the record (the row flagged, a_cmd the braking law)."""
    from stack.recorder import RecordedStack

    sc = make_scenario("paper-3")
    world = PymunkWorld(sc)
    state = world.reset(seed=0)
    stack = RecordedStack(ControlStack(sc, ScriptedController(sc), StackConfig()), tmp_path)
    for _ in range(4):
        stack.tick(state)
        world.send_accelerations(np.zeros((3, 2)))
        state = world.step()
    world.set_state(state.positions, np.array([[0.2, 0.0], [0.0, 0.0], [0.0, 0.1]]))
    state = world.read_state()
    stack.tick(state)
    stack.sent_braking(state, np.array([True, False, True]))
    assert stack.stack.predictor._braked[-1].tolist() == [True, False, True]
    (path,) = stack.close()
    record = load_record(path)
    np.testing.assert_array_equal(record.link_braked[-1], [True, False, True])
    np.testing.assert_allclose(record.a_cmd[-1, [0, 2]], [[-1.0, 0.0], [0.0, -1.0]], atol=1e-9)
    assert not record.link_braked[:-1].any()


def test_what_a_tracker_saw_is_recorded_in_its_own_columns_and_drawn(tmp_path):
    """Three ticks: a person p1 seen on ticks 0 and 2 (its sighting 0.1 s old on tick 2), a box
    seen from tick 1, and a sighting of robot r1 (a tracker that identifies robots), which is
    the robot's own column and not an obstacle's. A record written before these arrays loads
    with none."""
    from sim.fleet import Obstacles

    def seen(k: int) -> Obstacles:
        rows = [("p1", (0.5, 0.9 - 0.1 * k), 0.06, 0.05 * k, None)] if k != 1 else []
        rows += [("box", (0.8, 0.2), 0.03, 0.0, None)] if k >= 1 else []
        rows.append(("sighted-r1", (0.3, 0.4), 0.04, 0.0, "r1"))
        ids, pos, radii, ages, robots = zip(*rows, strict=True)
        return Obstacles(ids, np.array(pos), np.array(radii), np.array(ages), np.zeros(len(ids)), robots)

    rec = EpisodeRecorder(make_scenario("paper-3"))
    for k in range(3):
        state = _state(("r0", "r1"), k)
        state.obstacles = seen(k)
        rec.tick(state, _tick(2))
    out = rec.finish()
    assert out.obstacle_ids.tolist() == ["p1", "box"] and out.obstacles.shape == (3, 2, 4)
    np.testing.assert_allclose(out.obstacles[:, 0], [[0.5, 0.9, 0.06, 0.0], [np.nan] * 4, [0.5, 0.7, 0.06, 0.1]])
    np.testing.assert_allclose(out.obstacles[:, 1], [[np.nan] * 4, [0.8, 0.2, 0.03, 0.0], [0.8, 0.2, 0.03, 0.0]])
    back = load_record(out.save(tmp_path / "seen.npz"))
    np.testing.assert_array_equal(back.obstacles, out.obstacles)
    assert back.obstacle_ids.tolist() == ["p1", "box"]
    png = plot_episode(back, make_scenario("paper-3"), tmp_path / "seen.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with np.load(tmp_path / "seen.npz") as data:
        np.savez(tmp_path / "old.npz", **{k: data[k] for k in data.files if not k.startswith("obstacle")})
    old = load_record(tmp_path / "old.npz")
    assert old.obstacle_ids.shape == (0,) and old.obstacles.shape == (3, 0, 4)
    assert plot_episode(old, make_scenario("paper-3"), tmp_path / "old.png").exists()


def _damage(path, how: str) -> None:
    """Damage the record file at ``path``: emptied (a disk that filled), cut in half (a copy
    that stopped), or one member's compressed bytes overwritten (a bad sector)."""
    import zipfile

    data = bytearray(path.read_bytes())
    if how == "empty":
        data = bytearray()
    elif how == "truncated":
        data = data[:len(data) // 2]
    else:
        with zipfile.ZipFile(path) as zf:
            info = zf.getinfo("positions.npy")
        name_len, extra_len = (int.from_bytes(data[info.header_offset + k:info.header_offset + k + 2], "little")
                               for k in (26, 28))          # the local header's own lengths
        start = info.header_offset + 30 + name_len + extra_len
        data[start + 2:start + 12] = b"\xff" * 10
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("how", ["empty", "truncated", "member"])
def test_a_damaged_record_file_is_a_clear_error_and_plot_exits_2(tmp_path, capsys, how):
    """An empty .npz (EOFError), a cut one (BadZipFile) and one with a damaged member (zlib or
    CRC error) are a RecordError naming the file; `formation plot` exits 2 with that message."""
    rec = EpisodeRecorder(make_scenario("paper-3"))
    for k in range(3):
        rec.tick(_state(("r0", "r1"), k), _tick(2))
    path = rec.finish({"seed": 0}).save(tmp_path / "episode_0.npz")
    assert load_record(path).steps == 3
    _damage(path, how)
    with pytest.raises(RecordError, match=f"{path}: cannot read an episode record .*record the episode again"):
        load_record(path)
    assert main(["plot", str(path), "--out", str(tmp_path / "figs")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {path}: cannot read an episode record") and "Traceback" not in err
    assert not (tmp_path / "figs" / "episode_0.png").exists()


@pytest.mark.parametrize("chunk", [1, 2])
def test_the_link_brake_of_a_chunks_last_tick_is_in_that_chunk(tmp_path, chunk):
    """formation bridge --record-ticks CHUNK: the bridge calls tick(state) and then
    sent_braking(state, braked) for the same tick; the last tick of every chunk holds its brake
    (flag and the braking law in a_cmd) like every other tick, and close() writes the last
    chunk (5 ticks: no tick lost, none twice)."""
    from stack.recorder import RecordedStack

    sc = make_scenario("paper-3")
    stack = RecordedStack(ControlStack(sc, ScriptedController(sc), StackConfig(safety=False, mec=False)),
                          tmp_path, chunk_ticks=chunk)
    velocities = np.array([[0.2, 0.0], [0.0, 0.0], [0.0, 0.1]])
    braked = [np.array([k % 2 == 0, True, False]) for k in range(5)]
    for k in range(5):
        state = FleetState(time=0.05 * k, step=k, positions=np.array(sc.starts, dtype=float), velocities=velocities,
                           targets=np.array(sc.targets, dtype=float), object_pose=np.array([*sc.object_center, 0.0]),
                           robot_ids=("r0", "r1", "r2"))
        stack.tick(state)
        stack.sent_braking(state, braked[k])
    records = [load_record(p) for p in sorted(stack.close())]
    assert [r.steps for r in records] == [chunk] * (5 // chunk) + [5 % chunk] * (5 % chunk > 0)
    assert [r.meta["closed_by"] for r in records] == ["chunk"] * (5 // chunk) + ["exit"] * (5 % chunk > 0)
    link = np.concatenate([r.link_braked for r in records])
    np.testing.assert_array_equal(link, braked)
    a_cmd = np.concatenate([r.a_cmd for r in records])
    brake = stack.stack.brake(velocities)
    np.testing.assert_allclose(a_cmd[link], np.broadcast_to(brake, (5, 3, 2))[link], atol=1e-12)
    assert not np.allclose(a_cmd[~link], np.broadcast_to(brake, (5, 3, 2))[~link])
