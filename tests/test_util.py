"""rg_core.util: the thread-count context the report and benchmarks run their sections in."""
import torch

from rg_core.util import torch_threads


def test_torch_threads_sets_and_restores_the_count():
    old = torch.get_num_threads()
    want = 2 if old != 2 else 1
    with torch_threads(want):
        assert torch.get_num_threads() == want
    assert torch.get_num_threads() == old
    with torch_threads(0):   # 0: leave it
        assert torch.get_num_threads() == old
    try:
        with torch_threads(want):
            raise RuntimeError("inside")
    except RuntimeError:
        pass
    assert torch.get_num_threads() == old   # restored after an error too
