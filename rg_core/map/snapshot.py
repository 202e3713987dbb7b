"""A read-only snapshot of a map that readers (queries, saves) use while mapping goes on.

The mapper never edits a Gaussian tensor in place (its optimiser and every add, split or prune make
new tensors) and keyframes are never edited, so a snapshot shares those with the live map and copies
only the containers that hold them (lists and dicts: a few kB). Two parts are edited in place and are
copied when they changed: the feature field (latent rows, MLP weights; N x latent_dim floats plus the
MLPs, 6.4 MB at 100k Gaussians of 16-d) and the embeddings of each keyframe's supervision (a
supervision pass rewrites old keyframes' multi-view means: M x D floats per keyframe; the masks are
never edited and stay shared).

A part that did not change since the previous snapshot is that snapshot's object itself, so the
query caches (grounding/cache.py, keyed by identity) stay warm across snapshots.
"""
from __future__ import annotations

import copy
import threading


def _field_key(f) -> tuple:
    """What identifies a field's state: training, pruning, a sync, a scale or PCA refit change it."""
    return (id(f), f.revision, f.steps, id(f.latents), f.latents._version, len(f.latents), id(f.scale_tf),
            id(f._pca), id(f.stop), f.mapper.supervision is not None and id(f.mapper.supervision.pca.pca))


def _state(obj) -> tuple:
    """Identity of each attribute of `obj`, with torch's in-place version for tensors."""
    return tuple((k, id(v), getattr(v, "_version", None)) for k, v in vars(obj).items())


def _sup_key(s) -> tuple:
    p = s.pca
    return (s.serial, tuple((k, v.serial, _state(v)) for k, v in s.by_keyframe.items()), id(p.pca), p.version,
            len(p.raw), tuple(s.text_embeddings), s.taught_state, s.source)


_EDITED = ("embeddings", "embeddings_view", "model")   # tensors a supervision pass or teaching edits in place


def _copy_keyframe_sup(sup):
    c = copy.copy(sup)
    for name in _EDITED:
        t = getattr(sup, name)
        if t is not None:
            setattr(c, name, t.clone())
    c.seconds = dict(sup.seconds)
    return c


def _copy_supervision(sset, prev):
    """A copy of SupervisionSet `sset` whose per-keyframe records never change; records unchanged
    since `prev` (an earlier copy) are reused."""
    old = prev.by_keyframe if prev is not None else {}
    keys = getattr(prev, "_record_keys", {}) if prev is not None else {}
    s = copy.copy(sset)
    s.by_keyframe, s._record_keys = {}, {}
    for k, sup in sset.by_keyframe.items():
        key = (sup.serial, _state(sup))
        s.by_keyframe[k] = old[k] if k in old and keys.get(k) == key else _copy_keyframe_sup(sup)
        s._record_keys[k] = key
    s.text_embeddings = dict(sset.text_embeddings)
    s.pca = copy.copy(sset.pca)
    s.pca.raw = [c.embeddings for c in s.by_keyframe.values() if len(c.embeddings)]
    return s


def freeze_field(f, mapper):
    """A copy of FeatureField `f` over `mapper` (a snapshot) that answers as `f` does now and never
    changes: its own latent rows and MLP weights, no optimiser state."""
    z = copy.copy(f)
    z.mapper = mapper
    z.lock = threading.RLock()
    z.latents = f.latents.detach().clone()                     # [N, D]: training edits rows in place
    z.language_mlp = copy.deepcopy(f.language_mlp)
    z.instance_mlp = copy.deepcopy(f.instance_mlp)
    z._mlp_optim = None
    z._m = z._v = z._t = None                                   # a snapshot is never trained
    z._spare = {}
    z.sync = lambda: 0                                          # it follows its own snapshot, which never changes
    z._means = f._means
    # The cache's name for this state (cache.map_scopes): what the live field's own entry is made of
    # (its identity, training revision and steps), so rows appended elsewhere keep a region's clusters.
    z.state_token = ("frozen", id(f), f.revision, f.steps)
    return z


def take_snapshot(mapper, previous=None):
    """-> a Mapper sharing `mapper`'s tensors, keyframes and supervision records, frozen as they are
    now; parts unchanged since `previous` (an earlier snapshot of the same map) are reused.
    Call with the map's lock held (between units of mapping work); the field must be in sync."""
    prev = previous if previous is not None and getattr(previous, "_snapshot_of", None) == id(mapper) else None
    snap = copy.copy(mapper)
    snap._snapshot_of = id(mapper)
    snap.optim = None                                           # a snapshot is never optimised
    snap.gaussians = copy.copy(mapper.gaussians)                # the same tensors
    snap.keyframes = list(mapper.keyframes)
    snap.protected = list(mapper.protected)
    snap.totals = dict(mapper.totals)
    snap.seconds = dict(mapper.seconds)
    snap.taught = copy.copy(mapper.taught)
    snap.taught.items = list(mapper.taught.items)
    sset = mapper.supervision
    if sset is None:
        snap.supervision = None
    elif prev is not None and prev._sup_key == _sup_key(sset):
        snap.supervision = prev.supervision
    else:
        snap.supervision = _copy_supervision(sset, prev.supervision if prev is not None else None)
    snap._sup_key = _sup_key(sset) if sset is not None else None
    f = getattr(mapper, "field", None)
    if f is None:
        snap.field, snap._field_key = None, None
    else:
        key = _field_key(f)
        if prev is not None and prev._field_key == key and prev.field is not None:
            snap.field = copy.copy(prev.field)                  # the same frozen rows and weights
            snap.field.mapper = snap
        else:
            snap.field = freeze_field(f, snap)
        snap._field_key = key
    snap.is_snapshot = True
    return snap


def snapshot_bytes(snap, live) -> int:
    """Bytes a snapshot holds that the live map does not share (what it costs in memory)."""
    own = 0
    g, lg = snap.gaussians.tensors(), live.gaussians.tensors()
    for k, t in g.items():
        if lg.get(k) is not t:
            own += t.numel() * t.element_size()
    f, lf = snap.field, getattr(live, "field", None)
    if f is not None and f is not lf:
        own += f.latents.numel() * f.latents.element_size()
        own += sum(p.numel() * p.element_size() for m in (f.language_mlp, f.instance_mlp) for p in m.parameters())
    if snap.supervision is not None and snap.supervision is not live.supervision:
        own += sum(t.numel() * t.element_size() for sup in snap.supervision.by_keyframe.values()
                   for t in (getattr(sup, n) for n in _EDITED) if t is not None)
    return int(own)


