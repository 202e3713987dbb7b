"""Installs the headless library `rg_core` and the ROS 2 node package `rg_ros` (ament_python)."""
import os
import platform
from pathlib import Path

from setuptools import Extension, find_packages, setup

HERE = Path(__file__).parent
PACKAGE = "rg_ros"


def _simd_flags() -> list[str]:
    """AVX2 + FMA when the machine that builds (and, with `pip install -e`, runs) the kernels has
    them: the backward's channel loops run about 20 % faster. RG_PORTABLE_BUILD=1 leaves them out
    (a build for other machines)."""
    if os.environ.get("RG_PORTABLE_BUILD") == "1" or platform.machine() not in ("x86_64", "AMD64"):
        return []
    try:
        flags = next((ln.split(":", 1)[1].split() for ln in open("/proc/cpuinfo") if ln.startswith("flags")), [])
    except OSError:
        return []
    return ["-mavx2", "-mfma", "-mf16c"] if {"avx2", "fma", "f16c"} <= set(flags) else []


def _requirements(name: str) -> list[str]:
    lines = (HERE / name).read_text().splitlines()
    return [ln.strip() for ln in lines if ln.strip() and not ln.startswith("#")]


setup(
    name=PACKAGE,
    version="0.1.0",
    description="ReasonGrounder-ROS: open-vocabulary 3D visual grounding with hierarchical Gaussian feature splatting",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=["rg_core", "rg_core.*", "rg_ros", "rg_ros.*"]),
    # Data files inside rg_core (the reasoning benchmark's description set, issue 15).
    package_data={"rg_core": ["perception/data/*.json", "perception/data/embeddings/*.npy"]},
    install_requires=_requirements("requirements.txt"),
    # [ray]: many-scene `rg eval --ray` and `rg synth --seeds --ray` (issue 64); rg_core never needs it otherwise
    extras_require={"test": _requirements("requirements-test.txt"), "ray": _requirements("requirements-ray.txt")},
    # The layout `ros2 run` / `ros2 launch` expect under an AMENT_PREFIX_PATH prefix: the ament index
    # marker, share/rg_ros/{package.xml,launch,config}, and executables in lib/rg_ros/ (wrappers that
    # exec the console scripts in bin/). An editable install skips data_files: scripts/bootstrap.sh
    # installs them with `setup.py install_data`.
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"lib/{PACKAGE}", [str(p) for p in sorted(Path("resource/libexec").iterdir())]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", [str(p) for p in sorted(Path("config").glob("*.yaml"))]
         + [str(p) for p in sorted(Path("config").glob("*.rviz"))]),
        (f"share/{PACKAGE}/launch", [str(p) for p in sorted(Path("launch").glob("*.launch.py"))]),
    ],
    # The fast CPU rasterizer: plain C++ with a C ABI, loaded with ctypes (rg_core/render/fast_cpu.py),
    # so it needs no torch headers and compiles in seconds.
    ext_modules=[Extension(
        "rg_core.render._rasterize_cpu", ["rg_core/render/csrc/rasterize_cpu.cpp", "rg_core/render/csrc/project_cpu.cpp"],
        # -ffp-contract=off: no fused multiply-adds the torch twins do not do; a rounding difference in
        # a Gaussian's power moved pixels across the alpha >= 1/255 test (~3 % of random test scenes)
        language="c++", extra_compile_args=["-std=c++17", "-O3", "-fopenmp", "-fno-math-errno", "-ffp-contract=off",
                                            *_simd_flags()],
        extra_link_args=["-fopenmp"])],
    # rg-node / rg-ground / rg-replay: the node, a Ground service call and a scene or bag replayed;
    # `ros2 run rg_ros rg-node` and launch/grounding.launch.py run the same scripts through lib/rg_ros/.
    entry_points={"console_scripts": ["rg = rg_core.cli:main", "rg-node = rg_ros.tools:node_main",
                                      "rg-ground = rg_ros.tools:ground_main", "rg-replay = rg_ros.tools:replay_main"]},
    zip_safe=False,
)
