"""Running rg_node: stop signals and the executor loop (rg-node = `ros2 run rg_ros rg-node`)."""
from __future__ import annotations

import signal
import threading
from typing import TYPE_CHECKING

from rclpy.executors import (ConditionReachedException, ExternalShutdownException, MultiThreadedExecutor,
                             ShutdownException, TimeoutException)

if TYPE_CHECKING:
    from .node import GroundingNode


class NodeExecutor(MultiThreadedExecutor):
    """rclpy's MultiThreadedExecutor without its busy loop (rclpy 9.1, ros2/rclpy#1452, fixed upstream
    in 10.0.4): a callback handed to the thread pool stays in the executor's task list until a thread
    starts it, so every pass yields it again at once instead of waiting. While one callback runs and
    another waits for a thread, the spinning thread holds a core and the GIL and starves the callbacks
    it schedules (py-spy on rg-node under a 20 Hz stream: ~80 % of its samples). Here a task leaves
    the list when it is handed to a thread; a coroutine that awaits comes back to it (rclpy polls
    those). Callbacks, callback groups and exceptions behave as in the base class."""

    def _spin_once_impl(self, timeout_sec=None, wait_condition=lambda: False) -> None:
        try:
            handler, entity, node = self.wait_for_ready_callbacks(timeout_sec, None, wait_condition)
        except (ExternalShutdownException, ShutdownException, TimeoutException, ConditionReachedException):
            return
        with self._tasks_lock:   # handed to a thread: not yielded again while it waits for one
            self._tasks = [t for t in self._tasks if t[0] is not handler]
        self._futures.append(self._executor.submit(self._run_task, handler, entity, node))
        for future in self._futures[:]:
            if future.done():
                self._futures.remove(future)
                future.result()   # raise a callback's exception here, as the base class does

    def _run_task(self, task, entity, node) -> None:
        task()
        if not task.done():   # a coroutine awaiting a future: back to the list, to be resumed
            with self._tasks_lock:
                self._tasks.append((task, entity, node))
            self.wake()
            return
        task.result()


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

    executor = NodeExecutor(num_threads=6, context=node.context)
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
