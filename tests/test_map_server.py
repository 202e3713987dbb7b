"""The node's map worker as a map server, without ROS: a query is answered while a save, a supervision
pass or a training slice is held open (each blocked on an event, so nothing depends on timing or CPU
load); one save at a time; load swaps the map with no failed query; pause and resume."""
from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from rg_core.config import RGConfig
from rg_core.map.store import load_map
from rg_ros.map_admin import SaveBusy
from rg_ros.worker import MapWorker, WorkerConfig
from test_ros_worker import make_frame, wait_for

HOLD = 60.0   # s: an event a test forgets to set fails the test instead of hanging it


def cfg() -> RGConfig:
    c = RGConfig()
    return dataclasses.replace(c, ground=dataclasses.replace(c.ground, min_confidence=0.0))


@pytest.fixture
def name(synth_scene):
    return synth_scene.objects[0].name


def make_worker(path, **wc) -> MapWorker:
    w = MapWorker(cfg(), WorkerConfig(**{"queue_size": 4, "features": False, "idle_wait": 0.02, **wc}), load_map(path))
    return w


@pytest.fixture
def worker(minilm_map_file):
    w = make_worker(minilm_map_file)
    yield w
    assert w.stop(timeout=30)


def answered_while(hold: threading.Event, worker: MapWorker, query: str):
    """Ground `query` while `hold` is still unset; the answer must come before it is set."""
    r = worker.ground(query, timeout=HOLD)
    assert not hold.is_set(), "the query waited for the held work"
    return r


def answered_during(w: MapWorker, started: threading.Event, release: threading.Event, query: str, what: str) -> None:
    """Start `w`; once its held unit of work (`what`) has started, `query` is answered before release."""
    try:
        w.start()
        assert started.wait(HOLD), f"no {what} started"
        r = answered_while(release, w, query)
        assert r.success and r.objects, r.message
    finally:
        release.set()
        assert w.stop(timeout=60)


def test_query_and_second_save_answered_while_a_save_is_held_open(worker, name, tmp_path):
    from rg_core.map.store import save_map

    worker.start()
    started, release = threading.Event(), threading.Event()

    def blocked_write(snap, path):
        started.set()
        assert release.wait(HOLD), "never released"
        return save_map(snap, path)

    job = worker.save_async(tmp_path / "a.rgmap", write=blocked_write)
    assert started.wait(HOLD)
    r = answered_while(release, worker, name)
    assert r.success and r.objects, r.message
    with pytest.raises(SaveBusy, match="already saving .*a.rgmap"):
        worker.save_async(tmp_path / "b.rgmap")
    assert worker.stats()["saving"].endswith("a.rgmap")
    release.set()
    out = job.wait(HOLD)
    assert len(load_map(out).keyframes) == len(worker.mapper.keyframes)
    assert not (tmp_path / "b.rgmap").exists()
    assert worker.save(tmp_path / "c.rgmap", timeout=HOLD).exists()   # the next save runs


def test_failed_background_save_says_why_and_leaves_nothing(worker, tmp_path):
    bad = tmp_path / "file"
    bad.write_text("x")
    with pytest.raises(OSError):
        worker.save(bad / "m.rgmap", timeout=HOLD)   # a file where the folder should be
    assert list(tmp_path.iterdir()) == [bad]


def test_query_answered_during_a_training_slice(minilm_map_file, name):
    w = make_worker(minilm_map_file, features=True, train_slice=0.2, train_seconds_max=30.0)
    from rg_core.perception.embed import MiniLMText

    w._perception = ("unused", _TextAsEmbedder(MiniLMText()))   # training needs no masks: supervision is complete
    w._supervised_count = len(w.mapper.supervision.by_keyframe)
    in_slice, release = threading.Event(), threading.Event()
    train = w.field.train

    def held_train(*a, **k):
        in_slice.set()
        assert release.wait(HOLD)
        return train(*a, **k)

    w.field.train = held_train
    answered_during(w, in_slice, release, name, "training slice")


def test_query_answered_during_a_supervision_pass(minilm_map_file, name, synth_scene):
    from rg_core.perception.masks import make_mask_generator

    w = make_worker(minilm_map_file, features=True)
    real = make_mask_generator("rgbd")
    in_pass, release = threading.Event(), threading.Event()

    class HeldGenerator:
        def generate(self, rgb, depth, K):
            in_pass.set()
            assert release.wait(HOLD)
            return real.generate(rgb, depth, K)

    from rg_core.perception.embed import MiniLMText

    w._perception = (HeldGenerator(), _TextAsEmbedder(MiniLMText()))
    w.perception_state = "ready"
    k = max(w.mapper.supervision.by_keyframe)
    del w.mapper.supervision.by_keyframe[k]   # a keyframe without supervision: the next idle step supervises it
    answered_during(w, in_pass, release, name, "supervision pass")


class _TextAsEmbedder:
    """An embedder whose mask embeddings are MiniLM's embedding of a fixed word (the map's space)."""

    def __init__(self, text):
        self.text = text

    def encode_masks(self, rgb, masks):
        e = self.text(["object"])
        return e.repeat(len(masks), 1)

    def encode_texts(self, texts):
        return self.text(texts)


def test_load_swaps_the_map_with_no_failed_query(worker, name, tmp_path, minilm_map_file):
    other = load_map(minilm_map_file)
    keep = np.zeros(len(other.gaussians), bool)
    keep[: len(keep) // 2] = True    # a different map: half the Gaussians
    from rg_core.map.store import save_map

    worker.start()
    half = tmp_path / "half.rgmap"
    n_before = len(worker.mapper.gaussians)
    save_map(worker.mapper, half)
    answers, stop = [], threading.Event()

    def ask():
        while not stop.is_set():
            answers.append(worker.ground(name, timeout=HOLD))

    t = threading.Thread(target=ask)
    t.start()
    try:
        assert wait_for(lambda: len(answers) >= 1, HOLD)
        new = worker.load(half)
        assert wait_for(lambda: len(answers) >= 3, HOLD)
    finally:
        stop.set()
        t.join(HOLD)
    failed = [a.message for a in answers if not a.success]
    assert not failed, failed
    assert worker.mapper is new and worker.stats()["gaussians"] == len(new.gaussians) == n_before
    with pytest.raises(Exception, match="not found"):
        worker.load(tmp_path / "missing.rgmap")
    assert worker.mapper is new                  # a bad file leaves the map as it was
    assert worker.ground(name, timeout=HOLD).success


def test_a_query_while_load_publishes_the_new_map_reads_the_old_one(worker, name, tmp_path, monkeypatch):
    """Load assigns the new map's snapshot in one step: a query arriving while it is being made
    (held open here) reads the old map, never an absent one (CI once saw "map is empty" during load)."""
    from rg_core.map.store import save_map
    from rg_ros import reads

    again = save_map(worker.mapper, tmp_path / "again.rgmap")
    entered, release = threading.Event(), threading.Event()
    real = reads.take_snapshot

    def held(mapper, previous=None):
        entered.set()
        assert release.wait(HOLD)
        return real(mapper, previous)

    monkeypatch.setattr(reads, "take_snapshot", held)
    t = threading.Thread(target=worker.load, args=(again,))
    t.start()
    try:
        assert entered.wait(HOLD), "load published nothing"
        r = answered_while(release, worker, name)
        assert r.success and r.objects, r.message
    finally:
        release.set()
        t.join(HOLD)
    assert worker.ground(name, timeout=HOLD).success


def test_pause_counts_frames_maps_nothing_and_still_answers(minilm_map_file, name):
    w = make_worker(minilm_map_file)
    try:
        w.start()
        g0, mapped0, rejected0 = len(w.mapper.gaussians), w.processed, w.rejected
        assert w.pause() == 0 and w.paused
        for i in range(5):
            assert w.submit(make_frame(1000.0 + i, x=0.3 * i)) is False
        st = w.stats()
        assert st["dropped_paused"] == 5 and st["paused"] and st["received"] - st["dropped"] == w.queue.put_count - w.queue.dropped
        assert len(w.mapper.gaussians) == g0 and w.processed == mapped0 and w.rejected == rejected0
        r = w.ground(name, timeout=HOLD)
        assert r.success, r.message
        w.resume()
        w.submit(make_frame(2000.0))
        assert wait_for(lambda: w.processed + w.rejected == mapped0 + rejected0 + 1, HOLD)   # taken after resume
        assert not w.stats()["paused"]
    finally:
        assert w.stop(timeout=30)


def test_latency_window_and_status_keys(worker, name):
    from rg_ros.reads import LatencyWindow

    lw = LatencyWindow(60.0)
    for i, s in enumerate([0.1] * 18 + [1.0, 2.0]):
        lw.add(s, now=100.0 + i)
    s = lw.summary(now=120.0)
    assert s["n"] == 20 and s["p50"] == 0.1 and s["max"] == 2.0 and 0.1 < s["p95"] <= 1.05
    assert lw.summary(now=1000.0) == {"n": 0}    # older than a minute: gone
    st = worker.stats()
    assert {"snapshot_age_s", "query_latency_s", "paused", "saving"} <= st.keys()
