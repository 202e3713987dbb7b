"""The ROS 2 node: subscriptions -> approximate time sync -> MapWorker; /ground, ~/reset, ~/teach,
~/forget, and the map-server services (~/save_map, ~/load_map, ~/pause_mapping, ~/resume_mapping:
map_services.py); masks, clouds, markers and diagnostics out. Thin: message conversion and calls into
rg_core only.

Parameters and names: params.py; the worker it drives: worker_setup.py; inputs: camera_input.py
and tf_input.py (what is missing when none arrive: input_watch.py); clicked points, teaching and
forgetting: teaching.py; publishers and periodic publishing: outputs.py; running it (signals,
executor): run.py.
"""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from std_srvs.srv import Trigger

from rg_core.grounding.result import GroundingResult
from rg_core.perception.query import parse_mode, query_problem

from . import convert as cv
from .camera_input import CameraInput
from .input_watch import InputWatch
from .map_services import MapServices
from .outputs import NodeOutputs
from .params import GROUND_SERVICE, NODE_NAME, check_unknown_params, declare_params
from .teaching import Teaching
from .tf_input import TFInput
from .worker_setup import make_worker


class GroundingNode(CameraInput, TFInput, InputWatch, Teaching, MapServices, NodeOutputs, Node):
    def __init__(self, node_name: str = NODE_NAME, **kwargs):
        """Parameters come from rcl (--ros-args --params-file / -p, or `parameter_overrides`); a bad
        one is a ValueError naming it (rg-node prints it and exits 2). Names are relative (remapping)."""
        super().__init__(node_name, **kwargs)
        self.p = p = declare_params(self)
        if p.torch_threads > 0:
            import torch

            torch.set_num_threads(p.torch_threads)
        if p.gil_switch_interval > 0:   # process-wide: see the parameter's description
            sys.setswitchinterval(p.gil_switch_interval)
        self.worker = make_worker(p, self.get_logger())
        self._state_lock = threading.Lock()
        self._camera: tuple | None = None   # (K, w, h, cam_to_world, frame_id, stamp, depth, rgb) of the latest frame
        self._last_result: GroundingResult | None = None
        self._warned: dict[str, float] = {}
        self.input_errors: dict[str, int] = {}
        self._make_inputs(p)
        self._make_services()
        self._make_teaching(p)
        self._make_outputs(p)
        check_unknown_params(self, qos_only=True)   # qos_overrides.* exist once the entities do
        self._make_timers(p)
        self._make_input_watch(p)
        self.worker.start()
        pose_from = {"tf": f"TF {p.map_frame} <- image frame", "topic": f"PoseStamped {self.topics.get('pose')}",
                     "odometry": f"Odometry {self.topics.get('pose')}"}[p.pose_source]
        self.get_logger().info(
            f"listening: colour {self.topics['color']}, depth {self.topics['depth']}, info {self.topics['info']}, "
            f"pose from {pose_from}; service {self.resolve_service_name(GROUND_SERVICE)}; clicked points "
            f"{self.topics['clicked_point']}; "
            f"features {'on' if p.features else 'off'}")

    def _make_services(self) -> None:
        from rg_interfaces.srv import Ground

        self.create_service(Ground, GROUND_SERVICE, self._on_ground, callback_group=MutuallyExclusiveCallbackGroup())
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=MutuallyExclusiveCallbackGroup())
        self._make_map_services()

    # ------------------------------------------------------------------------------ helpers

    def _warn(self, key: str, msg: str, period: float = 5.0) -> None:
        """Count and log an input problem: the first of each kind at once, then at most every `period` s."""
        n = self.input_errors[key] = self.input_errors.get(key, 0) + 1
        now = time.monotonic()
        if n == 1 or now - self._warned.get(key, 0.0) >= period:
            self._warned[key] = now
            self.get_logger().warning(f"{msg}" + (f" ({n} so far)" if n > 1 else ""))

    def _stamp_now(self):
        return self.get_clock().now().to_msg()

    # ------------------------------------------------------------------------------ services

    def _on_ground(self, request, response):
        t = time.perf_counter()
        try:
            return self._answer_ground(request, response)
        finally:   # what the caller waited (diagnostics: query_latency_s over the last minute)
            self.worker.latency.add(time.perf_counter() - t)

    def _answer_ground(self, request, response):
        p = self.p
        query = request.query
        t = time.perf_counter()
        problem = query_problem(query, p.max_query_chars)   # the node's own limit (a parameter)
        try:
            mode = parse_mode(request.mode)
        except ValueError as exc:
            problem = problem or str(exc)
        if problem:
            result = GroundingResult(False, problem, query=query[:200])
        else:
            with self._state_lock:   # view-dependent words ("left of", "nearest to me"): the robot's camera
                cam = self._camera[3] if self._camera is not None else None
            result = self.worker.ground(query, mode, int(request.max_results) or p.max_results, p.ground_timeout,
                                        cam_to_world=cam)
            if not result.success and result.message.startswith("map is empty"):   # say what has not arrived
                result.message = self.empty_map_message()
        stamp = self._stamp_now()
        try:
            response = cv.result_to_response(result, p.map_frame, stamp, response=response)
        except Exception as exc:  # noqa: BLE001 - a broken result must still get an answer
            self.get_logger().error(f"ground: cannot convert the result: {exc}")
            response.success, response.message = False, f"internal error converting the result: {exc}"
            return response
        log = self.get_logger()
        short = query[:60] + ("..." if len(query) > 60 else "")
        graph = "graph" in result.timings   # the answer built or used the scene graph: publish it if new
        if result.success:
            log.info(f"ground '{short}': {result.message} ({time.perf_counter() - t:.2f} s)")
            self._publish_answer(result, response.cloud, stamp, graph=graph)
        else:
            log.warning(f"ground '{short}' failed: {result.message}")
            if graph:
                self._publish_graph_later(stamp)
        return response

    def _on_reset(self, request, response):
        self.worker.reset()
        self.sync.reset()
        self.tf.clear()
        with self._tf_lock:
            self._tf_pending = []
        with self._state_lock:
            self._last_result = None
        self._publish_reset()
        response.success, response.message = True, "map reset: 0 keyframes, 0 Gaussians"
        self.get_logger().info(response.message)
        return response

    # ------------------------------------------------------------------------------ shutdown

    def shutdown(self, timeout: float = 30.0) -> None:
        """Stop the worker after its current step; save the map if save_on_shutdown."""
        log = self.get_logger()
        self._answers.put(None)   # the answer publisher ends
        if not self.worker.stop(timeout):
            log.warning(f"mapping worker did not stop within {timeout:.0f} s")
        if self.p.save_on_shutdown:
            try:
                out = self.worker.save(Path(self.p.save_path).expanduser())
                log.info(f"map saved on shutdown: {out}")
            except Exception as exc:  # noqa: BLE001
                log.error(f"could not save the map on shutdown: {exc}")
