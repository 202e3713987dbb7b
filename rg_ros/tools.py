"""Console scripts (setup.py entry_points; `ros2 run rg_ros NAME` runs the same through lib/rg_ros/):

  rg-node   [--params FILE] [--name rg_node] [--ros-args -r rgb/image:=... -p name:=value ...]
  rg-ground "query" [--mode auto|explicit|implicit] [--max-results N] [--timeout S] [--service /ground]
  rg-replay SCENE --rate HZ [--loop] [--count N] [--split train|test|all]
  rg-replay BAG [--rate FACTOR] [--loop] [--topics T ...]   (.mcap, .db3 or a rosbag2 folder)
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def _split_ros_args(argv: list[str] | None) -> tuple[list[str], list[str]]:
    """(our arguments, the full argv for rclpy.init: program name + any --ros-args section)."""
    from rclpy.utilities import remove_ros_args

    argv = list(sys.argv[1:] if argv is None else argv)
    ours = remove_ros_args(["prog"] + argv)[1:]
    return ours, ["prog"] + argv


# ------------------------------------------------------------------------------------ rg-node

def node_main(argv: list[str] | None = None) -> int:
    """rg-node = `ros2 run rg_ros rg-node`: names and parameters come from --ros-args (-r, -p,
    --params-file); --params FILE is short for --ros-args --params-file FILE."""
    from .run import StopSignals

    stop = StopSignals()   # first: a Ctrl-C while the models load still ends cleanly
    ours, ros_argv = _split_ros_args(argv)
    ap = argparse.ArgumentParser(prog="rg-node", description="ReasonGrounder mapping + grounding node. Inputs "
                                 "rgb/image, depth/image, rgb/camera_info (pose, odom) and the service 'ground' are "
                                 "relative names: remap them with --ros-args -r rgb/image:=/camera/color/image_raw")
    ap.add_argument("--params", help="ros__parameters YAML (e.g. config/grounding.yaml): --ros-args --params-file")
    ap.add_argument("--name", default=None, help="node name (default rg_node; same as --ros-args -r __node:=NAME)")
    args = ap.parse_args(ours)
    extra = (["-r", f"__node:={args.name}"] if args.name else []) + (["--params-file", args.params] if args.params else [])
    if extra:   # rcl takes any number of --ros-args sections
        ros_argv = ros_argv + ["--ros-args", *extra]
    if args.params and not Path(args.params).is_file():
        print(f"rg-node: {args.params}: parameter file not found", file=sys.stderr)
        return 2
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from .node import GroundingNode
    from .run import spin

    try:
        rclpy.init(args=ros_argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # noqa: BLE001 - rcl's parser: a malformed params file or argument
        print(f"rg-node: cannot start: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    try:
        node = GroundingNode()
    except Exception as exc:  # noqa: BLE001 - bad map file, bad parameter: say why and exit
        print(f"rg-node: cannot start: {type(exc).__name__}: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    return spin(node, stop)


# ---------------------------------------------------------------------------------- rg-ground

def response_to_json(res) -> dict:
    from .convert import pose_to_matrix
    from .pointcloud import from_pointcloud2

    objs = []
    for o in res.objects:
        T = pose_to_matrix(o.pose)
        objs.append({"center": T[:3, 3].tolist(), "rotation": T[:3, :3].round(6).tolist(),
                     "size": [o.size.x, o.size.y, o.size.z], "gaussians": int(o.gaussian_count),
                     "confidence": float(o.confidence), "aabb": [[o.aabb_min.x, o.aabb_min.y, o.aabb_min.z],
                                                                 [o.aabb_max.x, o.aabb_max.y, o.aabb_max.z]]})
    pts, _ = from_pointcloud2(res.cloud)
    return {"success": bool(res.success), "message": res.message, "target": res.target,
            "explanation": res.explanation, "confidence": float(res.confidence), "objects": objs,
            "cloud_points": int(len(pts)), "frame_id": res.cloud.header.frame_id,
            "timings": dict(zip(res.stage_names, map(float, res.stage_seconds)))}


def ground_main(argv: list[str] | None = None) -> int:
    from .params import GROUND_SERVICE

    ours, ros_argv = _split_ros_args(argv)
    ap = argparse.ArgumentParser(prog="rg-ground", description="Call the Ground service; print the response as JSON")
    ap.add_argument("query")
    ap.add_argument("--mode", default="auto", help="auto (default), explicit or implicit")
    ap.add_argument("--max-results", type=int, default=0, help="0 = the node's default")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds for discovery plus the call")
    ap.add_argument("--service", default="/" + GROUND_SERVICE)
    args = ap.parse_args(ours)
    import rclpy
    from rg_interfaces.srv import Ground

    rclpy.init(args=ros_argv)
    node = rclpy.create_node("rg_ground_client")
    try:
        t0 = time.monotonic()
        client = node.create_client(Ground, args.service)
        if not client.wait_for_service(timeout_sec=args.timeout):
            print(json.dumps({"success": False, "message": f"service {args.service} not available after "
                                                           f"{args.timeout:.0f} s"}))
            return 2
        req = Ground.Request(query=args.query, mode=args.mode, max_results=max(args.max_results, 0))
        future = client.call_async(req)
        rclpy.spin_until_future_complete(node, future, timeout_sec=max(args.timeout - (time.monotonic() - t0), 1.0))
        if not future.done():
            print(json.dumps({"success": False, "message": f"no reply within {args.timeout:.0f} s"}))
            return 3
        out = response_to_json(future.result())
        out["seconds"] = round(time.monotonic() - t0, 3)
        print(json.dumps(out))
        return 0 if out["success"] else 1
    except KeyboardInterrupt:
        return 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


# ---------------------------------------------------------------------------------- rg-replay

def replay_main(argv: list[str] | None = None) -> int:
    from .params import INPUTS, NodeParams

    ours, ros_argv = _split_ros_args(argv)
    ap = argparse.ArgumentParser(prog="rg-replay", description="Publish a scene's frames like a bag (rgb8, 16UC1 "
                                 "depth, CameraInfo, PoseStamped and /tf map -> optical frame, one stamp per frame), "
                                 "or play a ROS 2 bag on its recorded topics with its recorded stamps")
    ap.add_argument("scene", help="scene folder (ReasoningGD layout or a capture folder) or a ROS 2 bag")
    ap.add_argument("--rate", type=float, default=None, help="scene: frames per second (default 2); bag: playback "
                                                           "speed factor (default 1 = as recorded)")
    ap.add_argument("--topics", nargs="+", default=None, help="bag: play only these topics (default: all)")
    ap.add_argument("--loop", action="store_true", help="start again after the last frame (stamps keep increasing)")
    ap.add_argument("--count", type=int, default=0, help="stop after this many frames (0 = one pass or forever with --loop)")
    ap.add_argument("--split", choices=("train", "test", "all"), default="train")
    ap.add_argument("--faults", type=int, default=0, metavar="N",
                    help="scene: after every N frames inject a fault in turn: a pose that is not a rotation, a "
                         "10-frame pose/TF gap, a stall of 100 frame periods whose frames then arrive at once with their capture "
                         "stamps (counts logged at the end; 0 = none)")
    ap.add_argument("--wait", type=float, default=5.0, help="seconds to wait for subscribers on every topic before "
                                                              "publishing (then publish anyway, naming the topics without)")
    ap.add_argument("--min-subscribers", type=int, default=1, help="subscriptions every topic waits for (default 1)")
    ap.add_argument("--frame-id", default="camera_color_optical_frame")
    ap.add_argument("--map-frame", default=NodeParams().map_frame)
    ap.add_argument("--color-topic", default=INPUTS["rgb/image"])
    ap.add_argument("--depth-topic", default=INPUTS["depth/image"])
    ap.add_argument("--camera-info-topic", default=INPUTS["rgb/camera_info"])
    ap.add_argument("--pose-topic", default=INPUTS["pose"])
    args = ap.parse_args(ours)
    if args.rate is not None and not args.rate > 0:
        ap.error("--rate must be > 0")
    from rg_core.io.rosbag import is_bag

    from .replay import replay_bag, replay_scene

    return replay_bag(args, ros_argv) if is_bag(args.scene) else replay_scene(args, ros_argv)


if __name__ == "__main__":
    sys.exit({"node": node_main, "ground": ground_main, "replay": replay_main}[sys.argv.pop(1)]())
