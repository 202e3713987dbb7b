"""What `rg report` runs: budgets per section (full run and a seconds-long `--tiny` one)."""
from __future__ import annotations

from dataclasses import dataclass, field

SECTIONS = ("mapping", "grounding", "latency", "memory", "savings", "scaling", "stability", "degraded")

STABILITY_K = "stab or extreme or huge or nan or degenerate or scales_from or opacity or depth_ranges or float32 or saturation or zero"


@dataclass
class Budgets:
    """Every knob of a report run; `map_overrides` and `field_overrides` apply to every run's config."""

    map_iters: tuple = (1, 2, 3, 5, 8, 12, 15, 20, 30)
    """iters_per_keyframe of the mapping section, log-spaced (include the default to mark it)."""
    map_overrides: dict = field(default_factory=dict)
    """MapConfig fields changed for every run of the report (tiny: fewer iterations)."""
    photo_overrides: dict = field(default_factory=dict)
    """PhotoMapConfig fields changed for every photo-only fit (a scene without depth; tiny: tens of steps)."""
    field_overrides: dict = field(default_factory=dict)
    """FieldConfig fields changed for every run (tiny: a 2 s ceiling for the stop test and the saving
    that compares it with training the whole ceiling)."""
    field_seconds: tuple = (1.0, 2.0, 3.0, 5.0, 8.0, 13.0, 20.0, 30.0, 50.0, 80.0)
    """Cumulative feature-training budgets of the grounding section (one field, evaluated at each),
    log-spaced; a second field runs the stop test and is marked on the curve."""
    implicit_per_object: int = 1
    latency_sizes: tuple = (5000, 20000, 100000)
    """Map sizes (Gaussians) for query latency; the scene's own map size is added."""
    latency_queries: int = 7
    """Explicit queries timed per map size (median reported)."""
    savings_field_seconds: float = 20.0
    """Field budget of the grounding-side savings and of the degraded inputs."""
    cluster_all_max: int = 20000
    """Larger maps compare 'cluster every Gaussian' on a random subset of this size (HDBSCAN is super-linear)."""
    frames: tuple = (25, 50, 100, 200)
    """Frame counts of the time/memory scaling (streaming, no final refinement)."""
    sizes: tuple = ((160, 120), (320, 240), (640, 480))
    """Image sizes of the scaling (mapped at full width)."""
    size_views: int = 25
    """Views per image-size scene."""
    synth_objects: int = 7
    stability_files: tuple = ("tests/test_render_stability.py", "tests/test_field.py", "tests/test_mapper.py")
    stability_k: str = STABILITY_K
    degraded: tuple = ("depth_noise_1cm", "depth_noise_5cm", "missing_depth_20", "pose_noise_1cm_1deg")
    fresh_process: bool = True
    """Each scaling point in its own process (true peak memory); tiny runs in-process (seconds)."""
    threads: int = 1
    """torch intra-op threads (1 is fastest on small shared CPUs)."""


def full_budgets(**over) -> Budgets:
    return Budgets(**over)


def tiny_budgets(**over) -> Budgets:
    """Seconds, not minutes: the test suite runs this so `rg report` keeps working."""
    base = dict(map_iters=(2, 4), map_overrides={"iters_per_keyframe": 4, "final_iters": 10, "width": 80},
                field_overrides={"seconds": 2.0},
                photo_overrides={"iters": 60, "check_every": 15, "densify_from": 15, "densify_every": 15,
                                 "converge_db": 0.0, "reset_opacity_every": 0, "init_random": 1000},
                field_seconds=(0.5, 1.0), latency_sizes=(300, 1500), latency_queries=2, savings_field_seconds=0.5,
                cluster_all_max=1000, frames=(3, 6), sizes=((64, 48), (128, 96)), size_views=3, synth_objects=2,
                stability_files=("tests/test_render_stability.py",), stability_k="float32 or huge",
                degraded=("depth_noise_1cm",), fresh_process=False)
    base.update(over)
    return Budgets(**base)
