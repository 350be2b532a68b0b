#!/usr/bin/env python3
"""Writes a copy of a flownav map whose lengths along one axis are off by a factor: what a map
drawn with a tape measure, or from a plan, looks like to a robot. Positions move away from (or
toward) the anchor place along the axis, and the lengths of the edges that run along it scale
with them; everything across the axis (room edges, door openings) is kept.

    bench/scale_map.py maps/office.toml 1.05 --anchor R9 > /tmp/office+5.toml
    flownav sim --map /tmp/office+5.toml --mission R9:D2 ...
"""
import argparse
import math
import re
import sys
import tomllib


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("map")
    ap.add_argument("factor", type=float, help="1.05: the map's lengths are 5 %% longer than the building's")
    ap.add_argument("--anchor", required=True, help="place that stays where it is (the mission's start)")
    ap.add_argument("--axis", choices=["x", "y"], default="x", help="the axis along which lengths are off")
    args = ap.parse_args()
    text = open(args.map, encoding="utf-8").read()
    parsed = tomllib.loads(text)
    places = {p["name"]: p for p in parsed.get("place", [])}
    if args.anchor not in places or "position_m" not in places[args.anchor]:
        print(f"scale_map: place {args.anchor!r} has no position_m in {args.map}", file=sys.stderr)
        return 2
    k = 0 if args.axis == "x" else 1
    origin = places[args.anchor]["position_m"][k]

    def position(m: re.Match) -> str:
        xy = [float(m.group(1)), float(m.group(2))]
        xy[k] = origin + args.factor * (xy[k] - origin)
        return f"position_m = [{xy[0]:.4g}, {xy[1]:.4g}]"

    text = re.sub(r"position_m = \[\s*([-\d.]+)\s*,\s*([-\d.]+)\s*\]", position, text)
    # edges along the axis: their lengths (and the door places on them) scale too
    along = 0.0 if args.axis == "x" else 90.0

    def edge(block: str) -> str:
        h = re.search(r"heading_deg = ([-\d.]+)", block)
        if h is None:
            return block
        if abs(math.sin(math.radians(float(h.group(1)) - along))) > 1e-6:
            return block
        return re.sub(
            r"\b(length_m|at_m) = ([\d.]+)", lambda m: f"{m.group(1)} = {args.factor * float(m.group(2)):.4g}", block
        )

    parts = re.split(r"(?=^\[\[edge\]\])", text, flags=re.M)
    sys.stdout.write("".join(edge(p) if p.startswith("[[edge]]") else p for p in parts))
    return 0


if __name__ == "__main__":
    sys.exit(main())
