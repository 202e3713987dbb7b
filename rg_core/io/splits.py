"""Which frames of a scene are test views: every n-th, or the views a benchmark labelled."""
from __future__ import annotations


def split_every(frames: list, test_every: int = 8) -> tuple[list, list]:
    """(train, test): every `test_every`-th frame (0-based position) is a test view; 0 = none."""
    test = [f for i, f in enumerate(frames) if test_every > 0 and i % test_every == 0]
    held = {id(f) for f in test}
    return [f for f in frames if id(f) not in held], test


def labelled_split(frames: list, labels, test_every: int = 8, labelled_in_train: bool = True) -> tuple[list, list]:
    """(train, test). With labels (ovs_labels.BenchmarkLabels) the labelled views are the test views
    (the benchmark names its split), and with `labelled_in_train` also training views, as LangSplat
    and 3D-OVS train on every image; without labels every `test_every`-th frame is a test view."""
    if labels is None:
        return split_every(frames, test_every)
    test = sorted({id(v.frame): v.frame for v in labels.views}.values(), key=lambda f: f.index)
    held = {id(f) for f in test}
    return (list(frames) if labelled_in_train else [f for f in frames if id(f) not in held]), test
