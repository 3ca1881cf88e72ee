import numpy as np
import pytest

from onfly.memory import (
    HybridMemory,
    MemoryConfig,
    MemoryError,
    SlidingWindowMemory,
    TimeSamplingMemory,
    make_memory,
)


def feat(i, dim=256):
    """A distinct unit feature per integer (orthogonal for i < dim)."""
    f = np.zeros(dim)
    f[i % dim] = 1.0
    return f


def fly_straight(mem, n, step_m=0.5, dim=256, t0=0.0, start=0):
    recs = []
    for i in range(start, start + n):
        recs.append(mem.observe(f"f{i}", t0 + i * 0.5, [i * step_m, 0, 1], 0.0, feat(i, dim)))
    return recs


def test_candidates_come_from_accumulated_translation_and_rotation():
    mem = HybridMemory(MemoryConfig(keyframe_translation_m=1.0, keyframe_rotation_rad=0.5))
    fly_straight(mem, 5, step_m=0.3)  # travel 0.3, 0.6, 0.9, 1.2 -> candidate at f4
    assert [c.frame_id for c in mem._pending] == ["f4"]
    # turning in place: 0.3 rad then 0.6 rad accumulated -> candidate
    mem.observe("r1", 10, [1.2, 0, 1], 0.3, feat(7))
    mem.observe("r2", 11, [1.2, 0, 1], 0.6, feat(8))
    assert [c.frame_id for c in mem._pending] == ["f4", "r2"]


def test_dedup_within_new_set_drops_near_duplicates():
    mem = HybridMemory(MemoryConfig(dedup_eps=0.1))
    a = mem.observe("a", 0, [0, 0, 0], 0, feat(0))
    b = mem.observe("b", 1, [1, 0, 0], 0, feat(0) + 0.01 * feat(1))  # cos dist ~5e-5
    c = mem.observe("c", 2, [2, 0, 0], 0, feat(2))
    kept = mem.dedup([a, b, c])
    assert [k.frame_id for k in kept] == ["a", "c"]


def test_merge_searches_only_the_L_geometrically_nearest_pool_items():
    mem = HybridMemory(MemoryConfig(dedup_eps=0.1, nearest_l=1))
    far = mem.observe("far", 0, [100, 0, 0], 0, feat(0))
    near = mem.observe("near", 1, [0, 0, 0], 0, feat(1))
    mem.merge([far, near])
    # same feature as `far`, but the single nearest pool item is `near` (different): appended
    k1 = mem.observe("k1", 2, [0.1, 0, 0], 0, feat(0))
    assert mem.merge([k1]) == [k1]
    # same feature as `near` and next to it: a duplicate, the pool entry is kept unchanged
    k2 = mem.observe("k2", 3, [-0.05, 0, 0], 0, feat(1))
    assert mem.merge([k2]) == []
    assert [u.frame_id for u in mem.pool] == ["far", "near", "k1"]


def test_one_winner_per_segment_and_winners_stick():
    cfg = MemoryConfig(slots=4, keyframe_translation_m=1.0)
    mem = HybridMemory(cfg)
    fly_straight(mem, 41, step_m=0.5)  # 20 m, candidates every 1 m
    mem.select()
    segs = {k: mem.segment_of(w.odom_m, mem.odom_m) for k, w in mem.winners.items()}
    assert sorted(mem.winners) == [0, 1, 2, 3]
    assert all(k == s for k, s in segs.items())
    # closest to each segment centre (2.5, 7.5, 12.5, 17.5 m), ties to the most recent
    for k, w in mem.winners.items():
        centre = (k + 0.5) * mem.odom_m / 4
        best = min(abs(u.odom_m - centre) for u in mem.pool if mem.segment_of(u.odom_m, mem.odom_m) == k)
        assert abs(w.odom_m - centre) == pytest.approx(best)
    before = dict(mem.winners)
    fly_straight(mem, 2, step_m=0.5, start=41)  # +1 m: segments stretch a little
    mem.select()
    for k, w in mem.winners.items():
        if mem.segment_of(before[k].odom_m, mem.odom_m) == k:
            assert w is before[k], f"segment {k} winner changed while the old one stayed in it"


def test_tie_break_prefers_recent_entries():
    mem = HybridMemory(MemoryConfig(slots=1, dedup_eps=0.01))
    # two pool items equally far from the centre of the only segment
    a = mem.observe("a", 0, [0, 0, 0], 0, feat(0))
    mem.observe("x", 1, [2, 0, 0], 0, feat(1))
    b = mem.observe("b", 2, [4, 0, 0], 0, feat(2))
    mem.observe("y", 3, [4, 0, 0], 0, feat(3))  # odom 4 m, centre 2 m; a at 0, b at 4
    mem.pool = [a, b]
    w = mem.select_winners()
    assert w[0] is b


def common_prefix(a, b):
    n = 0
    for x, y in zip(a, b):
        if x != y:
            break
        n += 1
    return n


def run_calls(mem, calls=60):
    prev, kept, stable = None, [], 0
    for step in range(calls):
        fly_straight(mem, 4, step_m=0.5, start=step * 4)
        m = mem.select()
        q = m[1:-1]
        assert m[0].frame_id == "f0" and m[-1] is mem.latest
        assert len(q) == min(mem.config.slots, mem.latest.seq - 1)  # S once S + 2 frames exist
        assert [r.seq for r in q] == sorted(r.seq for r in q)
        assert len({r.frame_id for r in m}) == len(m)
        ids = [r.frame_id for r in m]
        if prev is not None and step > 2:
            kept.append(common_prefix(ids, prev[:-1]) - 1)  # keyframes kept after o_1
            stable += ids[: len(prev) - 1] == prev[:-1]
        prev = ids
    return stable / len(kept), float(np.mean(kept))


def test_serialization_keeps_prefix_size_and_chronology():
    stable_h, kept_h = run_calls(HybridMemory(MemoryConfig(slots=4)))
    stable_s, kept_s = run_calls(SlidingWindowMemory(MemoryConfig(strategy="sliding", slots=4)))
    # segments stretch as the travelled distance grows, so the last slot changes now and
    # then; the first slots stick
    assert stable_h > 0.5 and kept_h >= 3.0
    assert stable_s == 0.0 and kept_s == 0.0


def test_serialization_keeps_longest_valid_prefix_exactly():
    mem = HybridMemory(MemoryConfig(slots=3))
    recs = [mem.observe(f"f{i}", i, [i, 0, 0], 0, feat(i)) for i in range(8)]
    a, b, c, d = recs[1], recs[2], recs[3], recs[5]
    mem.queue = [a, b, c]
    winners = {0: a, 1: c, 2: d}  # b is no longer a winner: prefix = [a]
    q = mem.serialize(winners)
    assert [r.frame_id for r in q] == ["f1", "f3", "f5"]


def test_hybrid_fills_from_recent_frames_early():
    mem = HybridMemory(MemoryConfig(slots=4))
    fly_straight(mem, 6, step_m=0.01)  # no candidates yet (1 m not reached)
    m = mem.select()
    assert [r.frame_id for r in m] == ["f0", "f1", "f2", "f3", "f4", "f5"]
    mem2 = HybridMemory(MemoryConfig(slots=4))
    fly_straight(mem2, 3, step_m=0.01)
    assert [r.frame_id for r in mem2.select()] == ["f0", "f1", "f2"]


def test_sliding_window_is_the_latest_frames():
    mem = SlidingWindowMemory(MemoryConfig(strategy="sliding", slots=4))
    fly_straight(mem, 20)
    assert [r.frame_id for r in mem.select()] == ["f0", "f15", "f16", "f17", "f18", "f19"]


def test_time_sampling_is_uniform_in_time():
    mem = TimeSamplingMemory(MemoryConfig(strategy="time", slots=4))
    fly_straight(mem, 21)  # t = 0 .. 10 s
    ids = [r.frame_id for r in mem.select()]
    assert ids == ["f0", "f4", "f8", "f12", "f16", "f20"]


def test_factory_and_validation():
    assert isinstance(make_memory(MemoryConfig(strategy="time")), TimeSamplingMemory)
    with pytest.raises(MemoryError, match="strategy must be one of"):
        MemoryConfig(strategy="lru")
    with pytest.raises(MemoryError, match="slots"):
        MemoryConfig(slots=0)
    mem = HybridMemory()
    mem.observe("a", 1.0, [0, 0, 0], 0, feat(0))
    with pytest.raises(MemoryError, match="backwards"):
        mem.observe("b", 0.5, [0, 0, 0], 0, feat(1))
    with pytest.raises(MemoryError, match="finite"):
        mem.observe("c", 2.0, [np.nan, 0, 0], 0, feat(1))


class _BlockingFeature:
    """A feature whose conversion blocks until released: it holds an ``observe`` half-way
    (odometry already advanced, ``latest`` not yet moved) for as long as the test wants."""

    def __init__(self, value) -> None:
        import threading

        self.value = np.asarray(value, float)
        self.entered = threading.Event()
        self.release = threading.Event()

    def __array__(self, dtype=None, copy=None):
        self.entered.set()
        assert self.release.wait(10.0)
        return self.value if dtype is None else self.value.astype(dtype)


@pytest.mark.parametrize("cls", [HybridMemory, SlidingWindowMemory, TimeSamplingMemory])
def test_snapshot_cannot_be_torn_by_a_concurrent_observe(cls):
    import threading

    mem = cls(MemoryConfig(slots=2))
    fly_straight(mem, 8, step_m=0.5)
    before = mem.snapshot()
    assert before.judged.frame_id == "f7" and before.frame_ids[0] == "f0"
    blocking = _BlockingFeature(feat(99))
    writer = threading.Thread(target=lambda: mem.observe("f8", 4.0, [4.0, 0, 1], 0.0, blocking))
    writer.start()
    assert blocking.entered.wait(5.0)  # observe is now half-way through recording f8
    result: list = []
    reader = threading.Thread(target=lambda: result.append(mem.snapshot()))
    try:
        reader.start()
        reader.join(0.3)
        # The snapshot waits for the observe to finish instead of reading a half-recorded frame.
        assert reader.is_alive() and not result
    finally:
        blocking.release.set()
    writer.join(5.0)
    reader.join(5.0)
    snap = result[0]
    assert snap.judged.frame_id == "f8" and snap.judged.odom_m == pytest.approx(4.0)
    seqs = [r.seq for r in snap.records]
    assert seqs == sorted(seqs) and snap.records[0].seq == 0
    # A snapshot is frozen: later frames never change one already handed to a worker.
    fly_straight(mem, 3, step_m=0.5, start=9, t0=0.0)
    assert before.judged.frame_id == "f7" and snap.judged.frame_id == "f8"
    assert isinstance(snap.records, tuple)
