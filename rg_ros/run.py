"""Running rg_node: stop signals and the executor loop (rg-node = `ros2 run rg_ros rg-node`)."""
from __future__ import annotations

import signal
import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .node import GroundingNode


class StopSignals:
    """SIGINT / SIGTERM set an event instead of raising: a terminal's Ctrl-C, `ros2 launch` (which
    also forwards SIGINT to the process group it already reached, so a second signal comes during
    shutdown) and systemd's SIGTERM all end in one orderly stop. Install before rclpy.init with
    signal_handler_options=NO, so rclpy does not shut the context down under the node."""

    def __init__(self):
        self.event = threading.Event()
        self.signum: int | None = None
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, self._on_signal)

    def _on_signal(self, signum, _frame) -> None:
        if self.signum is None:
            self.signum = signum
        self.event.set()


def spin(node: GroundingNode, stop: StopSignals) -> int:
    """Spin `node` with a multi-threaded executor until a stop signal (or the context ends); then stop
    the worker after its current step, save the map if configured, and return exit code 0."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

    executor = MultiThreadedExecutor(num_threads=6, context=node.context)
    executor.add_node(node)

    def run():
        try:
            executor.spin()
        except ExternalShutdownException:
            pass
        finally:
            stop.event.set()

    thread = threading.Thread(target=run, name="rg-executor", daemon=True)
    thread.start()
    while not stop.event.wait(0.5):
        pass
    why = signal.Signals(stop.signum).name if stop.signum is not None else "context shut down"
    node.get_logger().info(f"shutting down ({why})")
    node.shutdown()
    executor.shutdown(timeout_sec=5)
    thread.join(5)
    context = node.context
    node.destroy_node()
    rclpy.try_shutdown(context=context)
    return 0
