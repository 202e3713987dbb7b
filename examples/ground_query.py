"""Ground a query in a saved map: the target, the explanation and each Gaussian group's box.

    python examples/ground_query.py MAP.rgmap "a sturdy vessel for hot beverages" [--max-results N]
"""
import argparse

from rg_core.config import load_config
from rg_core.grounding.pipeline import Grounder
from rg_core.map.store import load_map

ap = argparse.ArgumentParser()
ap.add_argument("map")
ap.add_argument("query")
ap.add_argument("--max-results", type=int, default=1)
args = ap.parse_args()

grounder = Grounder.from_map(load_map(args.map), load_config(None), source=args.map)
result = grounder.ground(args.query, max_results=args.max_results)
print(f"success: {result.success}  target: {result.target!r}  confidence: {result.confidence:.2f}")
print(result.message)
print(result.explanation)
for obj in result.objects:   # an oriented box (centre, rotation, extent) and an axis-aligned one, metres
    print(f"  {len(obj.gaussian_ids)} Gaussians, centre {obj.obb_center.round(3).tolist()}, "
          f"size {obj.obb_extent.round(3).tolist()}")
