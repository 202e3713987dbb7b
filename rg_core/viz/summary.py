"""A short human summary of `rg demo`'s result dict (what a person reads; `--json` keeps the object)."""
from __future__ import annotations


def _fmt(v, digits: int = 2) -> str:
    return "(" + ", ".join(f"{float(x):+.{digits}f}" for x in v) + ")"


def demo_summary(result: dict) -> str:
    """Per answer: the query, the target the reasoner chose (and the scene's right object), the
    explanation, the box centre and size (m, map frame) and where the pictures are; then the scene,
    the map file and the stage times. Works on a partial result (no grounding, a failed query)."""
    lines = []
    scene = result.get("scene") or {}
    objs = scene.get("objects") if isinstance(scene, dict) else None
    if objs:
        names = [o.get("name", "?") if isinstance(o, dict) else str(o) for o in objs]
        lines.append(f"scene: {scene.get('views', '?')} views, objects: {', '.join(names)}")
    for kind, a in (result.get("answers") or {}).items():
        lines.append("")
        lines.append(f"{kind} query: {a.get('query', '')!r}")
        expected = a.get("expected")
        right = "" if not expected else (" (right)" if a.get("target") == expected else f" (the scene's object: {expected!r})")
        lines.append(f"  target:      {a.get('target') or '-'}{right}")
        if not a.get("success"):
            lines.append(f"  no answer:   {a.get('message', '')}")
            continue
        lines.append(f"  explanation: {a.get('explanation', '')}")
        o = a["objects"][0]
        lo, hi = o["aabb"]
        size = [h - l for l, h in zip(lo, hi)]
        lines.append(f"  box:         centre {_fmt(o['obb']['center'])} m, size {' x '.join(f'{s:.2f}' for s in size)} m "
                     f"(axis-aligned), {o['gaussians']} Gaussians, confidence {a.get('confidence', 0.0):.2f}")
        if a.get("timings", {}).get("total") is not None:
            lines.append(f"  answered in: {a['timings']['total']:.2f} s")
        if a.get("pictures"):
            lines.append(f"  pictures:    {a['pictures'].get('figure', next(iter(a['pictures'].values())))}")
    lines.append("")
    if result.get("contact_sheet"):
        lines.append(f"contact sheet: {result['contact_sheet']}")
    if result.get("map"):
        lines.append(f"map:           {result['map']} (rg ground {result['map']} \"QUERY\")")
    secs = result.get("seconds") or {}
    if secs:
        lines.append("seconds:       " + ", ".join(f"{k} {float(v):.1f}" for k, v in secs.items()))
    return "\n".join(lines)


def graph_summary(result: dict) -> str:
    """What `rg graph` prints: one line per object, then the on / near relations."""
    objs = result["objects"]
    lines = [f"{result['map']}: {len(objs)} objects (up {result['up']})"]
    for i, o in enumerate(objs):
        also = ", ".join(f"{n} {c:.2f}" for n, c in o["names"][1:])
        size = " x ".join(f"{100 * v:.0f}" for v in o["extent"])
        lines.append(f"  [{i}] {o['name']} {o['names'][0][1]:.2f}{f' (also {also})' if also else ''}: {o['colour']}, "
                     f"centre ({', '.join(f'{v:.2f}' for v in o['centre'])}) m, size {size} cm, {o['gaussians']} Gaussians")
    lines += [f"  {objs[r['subject']]['name']} {r['predicate']} {objs[r['object']]['name']} ({r['distance']:.2f} m)"
              for r in result["relations"]]
    return "\n".join(lines)
