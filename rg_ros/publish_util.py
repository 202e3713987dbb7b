"""Start and end of a burst of publishing (rg-replay) without losing its first or last messages.

DDS discovery is asymmetric: a publisher may already count a subscription while the subscriber
has not yet matched the publisher, and a volatile subscriber drops samples that arrive before it
has. At the end, destroying a publisher right after `publish()` loses what a reliable subscriber
has not acknowledged yet. A loaded CPU widens both windows (a replay-loop test lost the first and
last pass that way), so the start waits for the match plus a settle time and the end waits for
the acknowledgements (bounded), instead of fixed sleeps.
"""
from __future__ import annotations

import time


def replay_qos(latched: bool = False):
    """What rg-replay publishes with: reliable, depth 100 (volatile, or transient local for /tf_static).
    Best-effort (SensorDataQoS) subscribers accept it and may lose messages; a subscriber overridden to
    reliable (qos_overrides) with a deep enough history gets every one."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def wait_for_subscribers(pubs: list, timeout: float, settle: float = 0.5, minimum: int = 1) -> list[str]:
    """Wait up to `timeout` s until every publisher in `pubs` has at least `minimum` subscriptions,
    then `settle` s more for the subscribers' side of discovery. Returns the topics still short of
    subscribers (empty when all matched)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end and any(p.get_subscription_count() < minimum for p in pubs):
        time.sleep(0.05)
    short = [p.topic_name for p in pubs if p.get_subscription_count() < minimum]
    if not short and timeout > 0:
        time.sleep(settle)
    return short


def report_unmatched(log, short: list[str], timeout: float, minimum: int) -> None:
    """Say which topics nobody listens to (their messages go nowhere), as `ros2 bag play` users expect."""
    if short:
        log.warning(f"after {timeout:g} s, fewer than {minimum} subscriber(s) on {', '.join(short)}: "
                    "their messages go nowhere (is the node running, with matching names and domain?)")


def flush_publishers(pubs: list, timeout: float = 3.0) -> bool:
    """Wait (at most `timeout` s in all) until every reliable subscriber acknowledged what was
    published; best-effort subscribers acknowledge nothing and are not waited for."""
    from rclpy.duration import Duration

    t_end = time.monotonic() + timeout
    ok = True
    for p in pubs:
        left = max(0.0, t_end - time.monotonic())
        try:
            ok = bool(p.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))) and ok
        except Exception:  # noqa: BLE001 - an RMW without the call: fall back to a short grace period
            time.sleep(0.3)
            return False
    time.sleep(0.1)   # the last datagrams leave the socket
    return ok
