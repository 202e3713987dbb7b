"""The node for 2,000 looped frames with a /ground call every 2 s after a warm-up pass (the short
version of benchmarks/bench_endurance.py), with faults injected by rg-replay (bad poses, pose/TF
gaps, 100-frame bursts) and map saves during queries: no crash, every call and save answered, a
bounded queue, the keyframe budget held, no keyframe lost, and peak memory flat over the last half
unless a keyframe came in there. Query latency over time is reported by the benchmark, not asserted here (it depends on
CPU load); how many injected frames the node saw depends on DDS delivery and is reported, not asserted."""
from __future__ import annotations

import os
import random
import subprocess
import sys
from pathlib import Path

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"   # never multicast onto the network
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
os.environ.setdefault("ROS_LOG_DIR", str(Path(__file__).resolve().parents[1] / ".ros_log"))

import pytest  # noqa: E402

pytest.importorskip("rg_interfaces.srv", reason="rg_interfaces is not installed: scripts/bootstrap.sh builds it from msg/")
pytest.importorskip("diagnostic_msgs.msg", reason="ros-diagnostic-msgs is not installed (requirements.txt)")


def test_long_run_keeps_memory_flat_and_answers_every_call(tmp_path):
    from rg_ros.endurance import EnduranceConfig, plot, run

    scene = tmp_path / "scene"
    subprocess.run([sys.executable, "-m", "rg_core.cli", "synth", str(scene), "--views", "8", "--size", "160x120",
                    "--seed", "5", "--objects", "3", "--json", "--quiet"], check=True, capture_output=True, timeout=300)
    cfg = EnduranceConfig(frames=2000, rate=25.0, faults_every=150, save_every=3)
    cfg.params["max_keyframes"] = 4          # full after the warm-up (kf_min_count 4): new keyframes replace old
    r = run(scene, tmp_path / "work", cfg, progress=False)
    s = r["summary"]
    print(s)
    assert plot(r, tmp_path / "endurance.png", "test").is_file()
    assert not s["crashed"], (tmp_path / "work" / "node.log").read_text()[-3000:]
    assert s["calls"] >= 10 and s["calls_unanswered"] == 0, r["calls"]
    assert s["frames_received"] >= 100, s        # frames arrived (how many of 2,000: up to DDS, not asserted)
    assert s["queue_max"] <= 4, s                 # bounded: the rest is dropped and counted
    assert max(x["keyframes"] or 0 for x in r["samples"]) <= 4, s                    # the budget holds
    # Flat peak memory over the last half unless a keyframe came in there: in 80 s a new keyframe's
    # supervision and field caches land before the one it replaces is freed (the benchmark's 20,000
    # frames: +1.3 %).
    assert s["rss_growth_last_half_pct"] < 5.0 or s["keyframes_added_last_half"] > 0, s
    assert s["faults_injected"] == {"bad_pose": 5, "tf_gap": 4, "burst": 4}, s   # 13 faults in 2,000 frames
    assert s["saves"] >= 3 and s["saves_ok"] == s["saves"], s
    assert s["keyframes_min_after_warmup"] >= min(s["keyframes_at_warmup"], 4) > 0, s     # nothing mapped is lost
    assert all(s[k] is not None for k in ("input_errors", "bad_input", "sync_dropped", "tf_dropped", "keyframes_dropped")), s
    assert s["bad_input"] <= s["input_errors"], s   # queue drops are counted as drops, not as bad input
    from rg_core.map.store import load_map

    assert len(load_map(tmp_path / "work" / "endurance_map.pt").keyframes) > 0


def test_replay_fault_schedule(monkeypatch):
    """rg-replay --faults N: after every N frames a bad pose, then a 10-frame pose gap, then a 100-frame
    unpaced burst, in turn; the pose of a bad-pose frame is no rotation."""
    from types import SimpleNamespace

    from geometry_msgs.msg import PoseStamped

    from rg_core.geometry.conventions import PoseError
    from rg_ros.convert import pose_to_matrix
    from rg_ros.replay import Faults, _paced

    f = Faults(5)
    sent, bad = [], []
    for _ in range(30):
        p = PoseStamped()
        p.pose.orientation.w = 1.0
        sent.append(f.next(p))
        try:
            pose_to_matrix(p)
            bad.append(False)
        except PoseError:
            bad.append(True)
    assert [i for i, b in enumerate(bad) if b] == [4, 29]                  # frames 5 and 30: bad pose
    assert [i for i, s in enumerate(sent) if not s] == list(range(10, 20))  # after frame 10: 10 frames without pose
    assert f.counts == {"bad_pose": 2, "tf_gap": 1, "burst": 1} and f.burst == 100   # burst at 25 (20: in the gap)
    assert Faults(0).next(PoseStamped()) and Faults(0).burst == 0
    # a burst: a stall of 100 frame periods, then its 100 frames at once, each stamped with its
    # capture time (lag before sending: 99 ... 0 periods); the frames after it paced again
    import rg_ros.replay as replay

    pauses = []
    monkeypatch.setattr(replay.time, "sleep", pauses.append)
    f = Faults(0)
    f.burst = 100
    out = list(_paced(list(range(10)), SimpleNamespace(rate=2.0, count=103, loop=True), f))
    assert [x for x, _ in out] == [k % 10 for k in range(103)]
    assert [lag for _, lag in out] == [k / 2.0 for k in range(99, -1, -1)] + [0.0] * 3
    assert pauses[0] == 50.0   # the stall; then one period each after the burst (sleep mocked: no time passes)
    assert pauses[1:] == pytest.approx([0.5, 1.0, 1.5], abs=0.01)


def test_summary_counts_a_replaced_keyframe_as_added():
    """A keyframe replaced at the same view arrives at an unchanged keyframe count: it is still a new
    keyframe (its supervision and field caches), and the memory rule above excuses growth after it."""
    from rg_ros.endurance import summarise

    def sample(rss, kfs, dropped=0, replaced=0):
        return {"t": 1.0, "rss_mb": rss, "keyframes": kfs, "keyframes_dropped": dropped, "keyframes_replaced": replaced,
                "queue": 0, "received": 10, "mapped": 10, "dropped": 0}

    flat = [sample(1000.0, 4)] * 4 + [sample(1001.0, 4)] * 4
    s = summarise(flat, [], False)
    assert s["keyframes_added_last_half"] == 0 and s["rss_growth_last_half_pct"] == pytest.approx(0.1)
    replaced = [sample(1000.0, 4)] * 4 + [sample(1080.0, 4, replaced=1)] * 4
    s = summarise(replaced, [], False)
    assert s["keyframes_added_last_half"] == 1 and s["rss_growth_last_half_pct"] == pytest.approx(8.0)
    dropped = [sample(1000.0, 4)] * 4 + [sample(1000.0, 4, dropped=1)] * 4
    assert summarise(dropped, [], False)["keyframes_added_last_half"] == 1
