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


def test_join_prefetches_waits_for_the_background_imports():
    import sys

    from rg_core import util

    name = "xml.dom.minidom"
    sys.modules.pop(name, None)
    util.prefetch(name)
    util.join_prefetches()
    assert name in sys.modules and util._PREFETCHING == []
    util.join_prefetches()   # nothing left: returns at once
