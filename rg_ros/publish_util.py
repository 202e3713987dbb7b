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


def wait_for_subscribers(pubs: list, timeout: float, settle: float = 0.5) -> bool:
    """Wait up to `timeout` s until every publisher in `pubs` has a subscription, then `settle` s
    more for the subscribers' side of discovery. Returns whether all were matched."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end and any(p.get_subscription_count() == 0 for p in pubs):
        time.sleep(0.05)
    matched = all(p.get_subscription_count() > 0 for p in pubs)
    if matched and timeout > 0:
        time.sleep(settle)
    return matched


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
