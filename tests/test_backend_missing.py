"""A configured reasoning backend whose package is missing (the demo install leaves llama-cpp-python
out) fails with a message naming the command that installs it, also through `rg ground`."""
import importlib.util

import pytest

from rg_core.perception.base import BackendError
from rg_core.perception.reasoning import make_reasoner


def test_missing_llama_cpp_names_the_install_command(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "llama_cpp" else real(name, *a))
    with pytest.raises(BackendError, match=r"install it with `(bash scripts/install_llm.sh|RG_PROFILE=full bash scripts/bootstrap.sh)"):
        make_reasoner("llama_cpp")
