"""Approximate time synchronisation (rg_core.io.sync, used by the node and rg map BAG): pure Python, no ROS needed."""
from __future__ import annotations

import random
import threading

import pytest

from rg_core.io.sync import ApproximateTimeSync, SyncedSet


def test_pairs_within_slop_are_emitted_once():
    s = ApproximateTimeSync(["rgb", "depth"], queue_size=5, slop=0.01)
    assert s.add("rgb", 1.000, "r1") is None
    out = s.add("depth", 1.004, "d1")
    assert isinstance(out, SyncedSet)
    assert out.msgs == ("r1", "d1") and out.stamps == (1.000, 1.004)
    assert out.spread == pytest.approx(0.004)
    assert s.emitted == 1 and s.dropped == {"rgb": 0, "depth": 0}
    assert s.add("rgb", 1.033, "r2") is None   # its partner has not come yet


def test_pairs_outside_slop_wait():
    s = ApproximateTimeSync(["a", "b"], slop=0.01)
    assert s.add("a", 1.0, "a1") is None
    assert s.add("b", 1.02, "b1") is None
    out = s.add("a", 1.021, "a2")
    assert out.msgs == ("a2", "b1")
    assert s.dropped == {"a": 1, "b": 0}   # a1 was passed over


def test_closest_set_is_chosen():
    s = ApproximateTimeSync(["a", "b"], slop=0.05)
    s.add("a", 1.00, "a1")
    s.add("a", 1.03, "a2")
    out = s.add("b", 1.029, "b1")   # both a1 and a2 are within slop; a2 is closer
    assert out.msgs == ("a2", "b1")
    assert s.dropped["a"] == 1


def test_ties_prefer_the_earliest_set():
    s = ApproximateTimeSync(["a", "b"], slop=0.05)
    s.add("a", 1.00, "a1")
    s.add("a", 1.02, "a2")
    assert s.add("b", 1.01, "b1").msgs == ("a1", "b1")


def test_out_of_order_arrival():
    s = ApproximateTimeSync(["a", "b"], queue_size=10, slop=0.005)
    for t in (3.0, 1.0, 2.0):          # a arrives scrambled
        assert s.add("a", t, f"a{t:g}") is None
    assert s.add("b", 2.001, "b2").msgs == ("a2", "b2")
    assert s.dropped == {"a": 1, "b": 0}   # a1 is older than the emitted set
    assert s.add("b", 1.0, "b1") is None   # too late: a set after it has gone out
    assert s.dropped == {"a": 1, "b": 1}
    assert s.add("b", 3.002, "b3").msgs == ("a3", "b3")


def test_full_queue_drops_oldest():
    s = ApproximateTimeSync(["a", "b"], queue_size=3, slop=0.001)
    for k in range(5):
        s.add("a", float(k), k)
    assert s.dropped == {"a": 2, "b": 0}
    assert s.add("b", 0.0, "b0") is None           # its partner was pushed out of the queue
    assert s.add("b", 4.0, "b4").msgs == (4, "b4")
    assert s.dropped == {"a": 4, "b": 1}           # a2, a3 passed over; b0 passed over


def test_three_topics():
    s = ApproximateTimeSync(["rgb", "depth", "pose"], queue_size=10, slop=0.02)
    assert s.add("rgb", 10.00, "r") is None
    assert s.add("depth", 10.01, "d") is None
    assert s.add("pose", 10.05, "p_far") is None      # spread 0.05 > slop
    out = s.add("pose", 10.015, "p")
    assert out.msgs == ("r", "d", "p") and out.spread == pytest.approx(0.015)
    assert s.dropped == {"rgb": 0, "depth": 0, "pose": 0}
    # p_far (10.05) is still queued and can match the next frame
    s.add("rgb", 10.04, "r2")
    assert s.add("depth", 10.045, "d2").msgs == ("r2", "d2", "p_far")


def test_three_topics_stream_with_jitter():
    """30 Hz rgb/depth with 2 ms jitter, 100 Hz poses: every frame pairs with a pose within slop."""
    rng = random.Random(3)
    got = []
    s = ApproximateTimeSync(["rgb", "depth", "pose"], queue_size=10, slop=0.006, callback=got.append)
    events = []
    for k in range(60):
        t = k / 30
        events += [(t + rng.uniform(0, 0.002), "rgb", t), (t + 0.003 + rng.uniform(0, 0.002), "depth", t)]
    for k in range(200):
        events.append((k / 100, "pose", k / 100))
    rng.shuffle(events)
    events.sort(key=lambda e: e[0] + rng.uniform(0, 0.004))   # arrival order: stamp plus latency noise
    for stamp, topic, frame in events:
        s.add(topic, stamp, (topic, frame))
    assert s.emitted == len(got) >= 55
    for out in got:
        assert out.msgs[0][1] == out.msgs[1][1]   # rgb and depth of the same frame
        assert out.spread <= 0.006


def test_callback_and_thread_safety():
    got = []
    s = ApproximateTimeSync(["a", "b"], queue_size=50, slop=0.0001, callback=got.append)

    def feed(topic):
        for k in range(500):
            s.add(topic, k * 0.01, (topic, k))

    threads = [threading.Thread(target=feed, args=(t,)) for t in ("a", "b")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(got) == s.emitted > 0
    for out in got:
        assert out.msgs[0][1] == out.msgs[1][1]
    stamps = [out.stamps[0] for out in got]
    assert stamps == sorted(stamps)
    # every message was either emitted or counted as dropped
    assert s.emitted + s.dropped["a"] + len(s._queues[0]) == 500


def test_bad_arguments():
    with pytest.raises(ValueError, match="two distinct"):
        ApproximateTimeSync(["a"])
    with pytest.raises(ValueError, match="two distinct"):
        ApproximateTimeSync(["a", "a"])
    with pytest.raises(ValueError, match="slop"):
        ApproximateTimeSync(["a", "b"], slop=-1)
    s = ApproximateTimeSync(["a", "b"])
    with pytest.raises(KeyError, match="'c'"):
        s.add("c", 0.0, None)
    with pytest.raises(ValueError, match="finite"):
        s.add("a", float("nan"), None)
    s.add("a", 1.0, 1)
    s.reset()
    assert s.dropped == {"a": 0, "b": 0} and s.add("b", 1.0, 2) is None
