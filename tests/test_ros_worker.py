"""The node's mapping worker without ROS: bounded drop-oldest queue, stop/join, FrameError handling,
lock discipline, reset and save."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from rg_core.config import MapConfig, RGConfig
from rg_ros.frame_queue import Frame, FrameQueue
from rg_ros.worker import MapWorker, WorkerConfig

W, H = 64, 48


def make_frame(stamp: float, x: float = 0.0, **over) -> Frame:
    """A textured wall 1 m in front of a camera shifted by x."""
    v, u = np.mgrid[0:H, 0:W]
    rgb = np.stack([(u * 4) % 256, (v * 5) % 256, ((u + v) * 3) % 256], -1).astype(np.uint8)
    depth = np.full((H, W), 1.0, np.float32)
    K = np.array([[50.0, 0, (W - 1) / 2], [0, 50.0, (H - 1) / 2], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[0, 3] = x
    f = Frame(rgb, depth, K, c2w, stamp, "cam")
    for k, val in over.items():
        setattr(f, k, val)
    return f


def small_cfg() -> RGConfig:
    return RGConfig(map=MapConfig(width=W, iters_per_keyframe=1, final_iters=2))


def wait_for(cond, timeout: float = 20.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


@pytest.fixture
def worker():
    w = MapWorker(small_cfg(), WorkerConfig(queue_size=3, features=False, idle_wait=0.02))
    yield w
    assert w.stop(timeout=20)


def test_queue_is_bounded_and_drops_oldest():
    q = FrameQueue(3)
    assert [q.put(i) for i in range(5)] == [False, False, False, True, True]
    assert len(q) == 3 and q.dropped == 2 and q.put_count == 5
    assert [q.get(0) for _ in range(4)] == [2, 3, 4, None]
    with pytest.raises(ValueError):
        FrameQueue(0)


def test_get_waits_and_wakes():
    q = FrameQueue(2)
    threading.Timer(0.05, q.put, args=("x",)).start()
    t = time.monotonic()
    assert q.get(timeout=5) == "x" and time.monotonic() - t < 2


def test_flood_while_map_is_locked_drops_oldest_and_stays_bounded(worker):
    worker.start()
    with worker.lock:   # what a long optimisation step looks like to the callbacks
        t = time.monotonic()
        dropped = [worker.submit(make_frame(float(i))) for i in range(10)]
        assert time.monotonic() - t < 0.5, "submit blocked on the map lock"
        assert len(worker.queue) <= 3
        assert worker.queue.dropped >= 6 and sum(dropped) == worker.queue.dropped
    # done = every frame that was not dropped has been mapped (an empty queue alone can still mean
    # the last frame is half-way through add_frame: under load that raced and read stamp 8.0)
    assert wait_for(lambda: worker.processed + worker.rejected == worker.queue.put_count - worker.queue.dropped)
    st = worker.stats()
    assert st["dropped"] == worker.queue.dropped and st["queue"] == 0 and st["keyframes"] >= 1
    assert (st["split"], st["pruned"]) == (worker.mapper.totals["split"], worker.mapper.totals["pruned"])
    # the frames that survived are the newest ones
    assert worker.mapper.last_stamp == 9.0


def test_stop_joins_and_is_idempotent():
    w = MapWorker(small_cfg(), WorkerConfig(queue_size=2, features=False))
    assert w.stop(timeout=1)   # never started
    w = MapWorker(small_cfg(), WorkerConfig(queue_size=2, features=False))
    w.start()
    w.submit(make_frame(0.0))
    t = time.monotonic()
    assert w.stop(timeout=20) and not w.alive and time.monotonic() - t < 20
    assert w.stop(timeout=1)
    w.submit(make_frame(1.0))   # after stop: queued, never mapped, no error
    assert "stopped" in w.stats()["worker"]


def test_map_survives_frame_errors(worker):
    worker.start()
    worker.submit(make_frame(0.0))
    assert wait_for(lambda: worker.stats()["mapped"] == 1)
    g0, kf0 = len(worker.mapper.gaussians), len(worker.mapper.keyframes)
    assert g0 > 0 and kf0 == 1
    means = worker.mapper.gaussians.means.detach().clone()
    bad_pose = np.eye(4)
    bad_pose[0, 0] = np.nan
    worker.submit(make_frame(1.0, cam_to_world=bad_pose))
    worker.submit(make_frame(2.0, depth=np.ones((H // 2, W), np.float32)))
    assert wait_for(lambda: worker.stats()["rejected"] == 2)
    st = worker.stats()
    assert "rejected" in st["last_error"] and "depth" in st["last_error"]
    assert len(worker.mapper.gaussians) == g0 and len(worker.mapper.keyframes) == kf0
    assert torch_equal(worker.mapper.gaussians.means, means)
    worker.submit(make_frame(3.0, x=0.5))   # still mapping
    assert wait_for(lambda: worker.stats()["mapped"] == 2) and worker.alive


def torch_equal(a, b) -> bool:
    return bool((a.detach() == b).all())


def test_ground_answers_without_raising(worker):
    assert worker.ground("").message.startswith("empty query")
    r = worker.ground("the mug")
    assert not r.success and "map is empty" in r.message
    worker.start()
    worker.submit(make_frame(0.0))
    assert wait_for(lambda: worker.stats()["keyframes"] == 1)
    r = worker.ground("the mug", timeout=5)
    assert not r.success and r.message   # not supervised / not available: an answer, not an exception


def test_reset_save_and_snapshot(worker, tmp_path):
    from rg_core.map.store import load_map

    worker.start()
    worker.submit(make_frame(0.0))
    assert wait_for(lambda: worker.stats()["mapped"] == 1)
    pts, cols = worker.snapshot(max_points=10, timeout=10)
    assert pts.shape == (10, 3) and cols.shape == (10, 3) and cols.dtype == np.uint8
    path = worker.save(tmp_path / "m.pt")
    assert len(load_map(path).keyframes) == 1
    worker.reset()
    st = worker.stats()
    assert st["keyframes"] == 0 and st["gaussians"] == 0 and st["frames"] == 0
    # the frame accounting outlives a reset (queued frames it clears count as dropped)
    assert st["mapped"] == 1 and st["mapped"] + st["rejected"] + st["dropped"] + st["queue"] == st["received"]
    assert worker.snapshot(timeout=10)[0].shape == (0, 3)
    worker.submit(make_frame(5.0))
    assert wait_for(lambda: worker.stats()["keyframes"] == 1)


def test_perception_failure_keeps_mapping():
    def broken():
        raise ImportError("no such model")

    w = MapWorker(small_cfg(), WorkerConfig(queue_size=2, features=True, idle_wait=0.02), perception_loader=broken)
    w.start()
    try:
        assert wait_for(lambda: w.stats()["perception"].startswith("failed"))
        assert "no such model" in w.stats()["perception"]
        w.submit(make_frame(0.0))
        assert wait_for(lambda: w.stats()["keyframes"] == 1)
    finally:
        assert w.stop(timeout=20)


def test_models_load_once_the_field_answers():
    """The worker's idle step loads the grounder's models once the field first answers (stop set),
    not before and not twice; the first query then finds them loaded. Not started: steps by hand."""
    from types import SimpleNamespace

    from rg_core.perception.text_cache import inner_encoder

    w = MapWorker(small_cfg(), WorkerConfig(queue_size=2, features=True))
    assert not w._load_models()                           # no field yet
    w.field = SimpleNamespace(stop=None)                  # training, not answering yet
    assert not w._load_models() and w._grounder is None
    w.field.stop = {"stopped": "converged"}
    assert w._load_models() and not w._load_models()      # one step, once
    g = w._grounder
    assert g is not None and inner_encoder(g.text_model())._model is not None
    assert inner_encoder(g.reasoner.text)._model is not None


def test_reset_counts_the_frames_it_clears_as_dropped():
    w = MapWorker(small_cfg(), WorkerConfig(queue_size=4, features=False))   # not started: frames stay queued
    for i in range(3):
        w.submit(make_frame(float(i)))
    w.reset()
    st = w.stats()
    assert st["queue"] == 0 and st["dropped"] == 3 and st["received"] == 3 and st["mapped"] == 0


def test_a_waiting_caller_goes_before_new_work(worker):
    """While a service call waits for the map lock the worker starts no new frame or slice: the
    query waits for the step in progress only. Simulated by a caller holding its place in line."""
    worker.start()
    with worker._callers_lock:                   # what _acquire does while it waits for the lock
        worker._callers += 1
        worker._no_callers.clear()
    for i in range(3):
        worker.submit(make_frame(float(i), x=0.3 * i))
    time.sleep(0.5)                              # would map the first frames if the worker did not give way
    assert worker.processed == 0 and len(worker.queue) >= 2   # one may be taken, but it waits too
    with worker._callers_lock:
        worker._callers -= 1
        worker._no_callers.set()
    assert wait_for(lambda: worker.processed + worker.rejected == 3)
    assert worker._acquire(5.0)                  # a real caller gets the lock and gives way again
    worker.lock.release()
    assert worker._callers == 0 and worker._no_callers.is_set()


def test_a_waiting_caller_is_what_ends_a_training_slice(worker):
    """`caller_waits` (the `until` of the worker's training slices) is true exactly while a service
    call waits for the map lock."""
    import threading

    assert not worker.caller_waits()
    worker.lock.acquire()                        # a slice in progress holds the lock
    got = []
    caller = threading.Thread(target=lambda: got.append(worker._acquire(10.0)) or worker.lock.release())
    caller.start()
    assert wait_for(worker.caller_waits)
    worker.lock.release()
    caller.join(10)
    assert got == [True] and not worker.caller_waits()
