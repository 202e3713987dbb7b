"""Shared fixtures: one small synthetic scene per session, and paths to the shared data."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

# One arithmetic on every x86-64 machine that runs the suite (Intel and AMD, with or without
# AVX-512): the math libraries pick their kernels by CPU, and two kernels round differently, so a
# map trained for a fixed number of steps came out differently on another vendor's CPU. These pin
# each library to kernels that every x86-64 machine here runs alike (AVX2 and FMA, which they all
# have and the project's own C++ is built with; MKL's vendor-neutral branch) and to one thread (a
# reduction splits the same way on any number of cores; scripts/test.sh runs two pytest-xdist
# workers, one a core). Set before
# torch or numpy is imported (pytest imports conftest first); child processes (rg, ros2 launch)
# inherit them.
CPU_PINS = {
    "ATEN_CPU_CAPABILITY": "avx2",            # torch's vectorised ATen kernels
    "MKL_CBWR": "COMPATIBLE",                 # MKL's BLAS under torch: its one branch that is the same on
                                              # Intel and AMD (AVX2 falls back to AUTO on AMD)
    "MKL_DYNAMIC": "FALSE",                   # MKL and OpenMP keep the thread count asked for
    "OMP_DYNAMIC": "FALSE",
    "ONEDNN_MAX_CPU_ISA": "AVX2",             # oneDNN (torch's convolutions)
    "OPENBLAS_CORETYPE": "Haswell",           # numpy's and scipy's OpenBLAS
    "NPY_DISABLE_CPU_FEATURES": "X86_V4,AVX512_ICL,AVX512_SPR",   # numpy's own AVX-512 loops
    "OMP_NUM_THREADS": "1",                   # torch, MKL, OpenBLAS and the C++ rasterizer
}
for _k, _v in CPU_PINS.items():
    os.environ.setdefault(_k, _v)

# pytest-xdist workers (gw0, gw1, ...) each get their own ROS domain: two nodes named rg_node in one
# domain would answer each other's /ground.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")
if _WORKER.startswith("gw"):
    _base = int(os.environ.get("ROS_DOMAIN_ID") or 1)
    os.environ["ROS_DOMAIN_ID"] = str(1 + (_base - 1 + int(_WORKER[2:])) % 101)   # 1-101: never the default 0

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
RGBD = SHARED / "data" / "rgbd"


def small_synth_config(**over):
    from rg_core.config import SynthConfig

    base = dict(views=16, width=160, height=120, objects=5, seed=7, workers=1)
    base.update(over)
    return SynthConfig(**base)


@pytest.fixture(scope="session")
def synth_scene_dir(tmp_path_factory) -> Path:
    """A 16-view 160x120 scene with 5 objects (about 5 s)."""
    from rg_core.synth.generator import default_objects_dir, generate_scene

    out = tmp_path_factory.mktemp("synth") / "scene"
    generate_scene(out, small_synth_config(), default_objects_dir(), progress=False)
    return out


@pytest.fixture(scope="session")
def synth_scene(synth_scene_dir):
    from rg_core.io.scene import read_reasoninggd

    return read_reasoninggd(synth_scene_dir)


def need_rgbd(name: str) -> Path:
    path = RGBD / name
    if not path.is_dir():
        pytest.skip(f"{path} is missing (../shared/data beside the checkout)")
    return path


def photos_only(root: Path, points: int = 1500) -> Path:
    """A ReasoningGD scene folder made photos alone, in place: depth images and `depth_file_path`
    entries removed, points3d.ply thinned to `points` (a seeded sample, a sparse cloud's size)."""
    import json
    import shutil

    import numpy as np

    from rg_core.io.ply import read_ply, write_ply

    shutil.rmtree(root / "depth", ignore_errors=True)
    for name in ("transforms_train.json", "transforms_test.json"):
        d = json.loads((root / name).read_text())
        for f in d["frames"]:
            f.pop("depth_file_path", None)
        (root / name).write_text(json.dumps(d))
    pts, cols = read_ply(root / "points3d.ply")
    sel = np.random.default_rng(0).choice(len(pts), min(points, len(pts)), replace=False)
    write_ply(root / "points3d.ply", pts[sel], cols[sel])
    return root


def assert_load_errors(load, error: type[Exception], folder: Path, cases) -> None:
    """A file loader names what is wrong with a file: for each (file name, text or None for a missing
    file, regex), `load(folder / name)` raises `error` matching regex. One table per loader instead of
    the same write-then-pytest.raises steps in each loader's tests (config, knowledge)."""
    for name, text, match in cases:
        if text is not None:
            (folder / name).write_text(text)
        with pytest.raises(error, match=match):
            load(folder / name)


@pytest.fixture(scope="session")
def conse_embedder():
    """The packaged offline embedder (loads in about 10 s; shared by the session)."""
    pytest.importorskip("efficientnet_lite_pytorch")
    from rg_core.perception.embed import make_embedder

    return make_embedder("conse", top_k=10)


@pytest.fixture(scope="session")
def oracle_field(synth_scene):
    """The session scene mapped at 160 px (stride 2: objects span 10-20 px), ground-truth masks and
    fixed random name vectors as supervision, and a feature field trained 200 steps (one thread)."""
    import torch

    from rg_core.config import FieldConfig, MapConfig
    from rg_core.field import FeatureField
    from rg_core.field.oracle import RandomNameEmbedding, oracle_supervision
    from rg_core.map.mapper import Mapper
    from rg_core.map.run import stream_frames

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        embed = RandomNameEmbedding(dim=96, seed=0)
        mapper = Mapper(MapConfig(width=160, iters_per_keyframe=5, final_iters=0, seed_stride=2))
        stream_frames(mapper, synth_scene.train, progress=False)
        oracle_supervision(mapper, synth_scene.train, synth_scene.objects, embed)
        field = FeatureField(mapper, FieldConfig())
        field.train(iters=200)
    finally:
        torch.set_num_threads(n)
    return field, embed


@pytest.fixture(scope="module")
def grounder(oracle_field, synth_scene):
    """A Grounder over the oracle field with the text reasoner and the scene's names (one per test module:
    a module may change its config)."""
    from rg_core.config import RGConfig
    from rg_core.grounding.pipeline import Grounder
    from rg_core.perception.reasoning import TextReasoner

    field, embed = oracle_field
    return Grounder(field.mapper, field, RGConfig(), reasoner=TextReasoner(), text_encoder=embed,
                    scene_names=[o.name for o in synth_scene.objects])


@pytest.fixture(scope="session")
def minilm_map_file(synth_scene, tmp_path_factory) -> Path:
    """The session scene mapped at 160 px with ground-truth masks named in MiniLM's space (what
    `rg ground` and `rg teach` embed queries with) and a field trained 200 steps, saved to a file:
    tests load their own copy (teaching changes a map)."""
    import torch

    from rg_core.config import FieldConfig, MapConfig
    from rg_core.field import FeatureField
    from rg_core.field.oracle import oracle_supervision
    from rg_core.map.mapper import Mapper
    from rg_core.map.run import stream_frames
    from rg_core.map.store import save_map
    from rg_core.perception.embed import MiniLMText

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        mapper = Mapper(MapConfig(width=160, iters_per_keyframe=5, final_iters=0, seed_stride=2))
        stream_frames(mapper, synth_scene.train, progress=False)
        oracle_supervision(mapper, synth_scene.train, synth_scene.objects, MiniLMText())
        FeatureField(mapper, FieldConfig()).train(iters=200)
    finally:
        torch.set_num_threads(n)
    return save_map(mapper, tmp_path_factory.mktemp("minilm") / "scene.rgmap")
