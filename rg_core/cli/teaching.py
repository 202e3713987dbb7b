"""`rg point` (the object at a 3D point or a keyframe pixel: its group, boxes and what the map thinks
it is) and `rg teach` (name it, list or forget what was taught): grounding/point.py and teach.py
over a saved map. `rg teach` writes the map in place unless --out names another file; on any error
nothing is written."""
from __future__ import annotations

from pathlib import Path

from .config_args import add_sections
from .grounding import SECTIONS, _add_grounder_args, _grounder_from_args
from .options import add_common


def _point(args, grounder):
    """The map-frame point of --point X Y Z or --view V --pixel U V."""
    from ..grounding.point import check_point, point_at_pixel

    if args.point is not None:
        return check_point(args.point)
    if args.view is None or args.pixel is None:
        raise ValueError("say where: --point X Y Z (map frame, metres) or --view V --pixel U V (a keyframe's pixel)")
    return point_at_pixel(grounder.mapper, args.view, *args.pixel)


def cmd_point(args, cfg) -> dict:
    from ..grounding.point import point_answer

    grounder = _grounder_from_args(args, cfg)
    res = point_answer(grounder, _point(args, grounder))
    if not res.success:
        raise ValueError(res.message)
    return res.to_json()


def cmd_teach(args, cfg) -> dict:
    from ..grounding import teach
    from ..map.store import save_map

    grounder = _grounder_from_args(args, cfg)
    m = grounder.mapper
    if args.list:
        if args.name is not None or args.forget is not None:
            raise ValueError("--list takes no NAME and no --forget")
        return {"map": args.map, "taught": [t.to_json() for t in m.taught]}
    out = {"map": args.map}
    if args.forget is not None:
        if args.name is not None:
            raise ValueError("--forget NAME takes no other NAME")
        gone = teach.forget(grounder, args.forget)
        out["forgotten"] = [t.to_json() for t in gone]
    else:
        if args.name is None:
            raise ValueError("say what it is: rg teach MAP NAME --point X Y Z (or --list, --forget NAME)")
        record, answer = teach.teach(grounder, args.name, point=_point(args, grounder))
        out["taught"] = record.to_json()
        out["answer"] = answer.to_json() if answer is not None else None
    if args.train_seconds > 0 and grounder.field is not None:   # the field learns the names now
        r = grounder.field.train(seconds=args.train_seconds, converge=True, progress=not args.quiet)
        out["field"] = {k: r[k] for k in ("steps", "seconds", "stop") if k in r}
    path = Path(args.out or args.map)
    try:
        save_map(m, path)   # temp file then rename: a failed write leaves the old map as it was
    except OSError as exc:
        raise ValueError(f"cannot write {path}: {exc}; nothing was written") from exc
    out["written"] = str(path)
    out["names"] = m.taught.names()
    return out


def _teach_human(result: dict) -> str:
    lines = []
    if "taught" in result and isinstance(result["taught"], list):
        lines += [f"{t['name']!r}: {t['gaussians']} Gaussians, box {t['aabb'][0]} .. {t['aabb'][1]}"
                  for t in result["taught"]] or ["nothing taught yet"]
        return "\n".join(lines)
    if "forgotten" in result:
        lines.append(f"forgot {len(result['forgotten'])} object(s): "
                     + ", ".join(repr(t["name"]) for t in result["forgotten"]))
    elif result.get("answer"):
        lines.append(result["answer"]["message"])
    if "field" in result:
        f = result["field"]
        lines.append(f"field: {f.get('steps', 0)} steps in {f.get('seconds', 0.0):.1f} s")
    lines.append(f"written {result['written']}; taught: {', '.join(result['names']) or 'nothing'}")
    return "\n".join(lines)


def _point_human(result: dict) -> str:
    names = ", ".join(f"{n} {s:.2f}" for n, s in result.get("names", []))
    return f"{result['message']}\nnames: {names or 'none'}; confidence {result['confidence']:.2f}\n{result['explanation']}"


def _where(p) -> None:
    p.add_argument("--point", nargs=3, type=float, metavar=("X", "Y", "Z"), help="a point in the map frame (metres)")
    p.add_argument("--view", type=int, help="a keyframe (stream index), with --pixel")
    p.add_argument("--pixel", nargs=2, type=float, metavar=("U", "V"), help="a pixel of --view (column, row)")


def add_point(sub) -> None:
    p = sub.add_parser("point", help="the object at a point: its Gaussian group, boxes and what the map thinks it is")
    p.add_argument("map", help="map file from rg map --supervise --train-field S")
    _where(p)
    _add_grounder_args(p)
    add_common(p)
    add_sections(p, SECTIONS)
    p.set_defaults(func=cmd_point, human=_point_human)


def add_teach(sub) -> None:
    p = sub.add_parser("teach", help="name the object at a point (what the models cannot); --list, --forget NAME")
    p.add_argument("map", help="map file; written in place unless --out")
    p.add_argument("name", nargs="?", help="what the object is ('blue mug')")
    _where(p)
    p.add_argument("--out", help="write the taught map here instead of in place")
    p.add_argument("--list", action="store_true", help="list what was taught")
    p.add_argument("--forget", metavar="NAME", help="forget every object taught as NAME")
    p.add_argument("--train-seconds", type=float, default=30.0, metavar="S",
                   help="train the field on the new names for up to S s before writing (its stop test may end "
                        "it sooner; 0: answers come from the taught group until something trains it; default 30)")
    _add_grounder_args(p)
    add_common(p)
    add_sections(p, SECTIONS)
    p.set_defaults(func=cmd_teach, human=_teach_human)
