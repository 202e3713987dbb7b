"""Many independent tasks (one per scene) run one after another in this process or on Ray, each
recorded as one JSON file when it finishes, so a rerun resumes (issue 64). Generic: the task is any
importable function of a payload; `rg eval` and `rg synth` pass theirs (rg_core/cli/many.py)."""
from .engines import RAY_INSTALL, EngineError, engine_info, run_tasks
from .results import ResultsDir, Task

__all__ = ["RAY_INSTALL", "EngineError", "ResultsDir", "Task", "engine_info", "run_tasks"]
