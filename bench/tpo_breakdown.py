#!/usr/bin/env python3
"""Where OFFIS says `none` with a TPO in view, from the simulator's frame trace.

Counts every step of one or more traced runs (the `frame t=` and `offis t=` lines of
`RUST_LOG=flownav::sim::frames=trace flownav sim ...`, docs/sim.md) and prints:
- the share of steps whose reported TPO equals the truth;
- `tpo_none_share`: of the steps with a TPO in view, the share reported `none` (every step
  counted, so longer runs weigh more than in the mean of the summaries' field);
- `none_named_share`: of the steps with no TPO in view, the share reported as one;
- why each `none` with a TPO in view came about, as shares of the TPO steps:
    no translation    the robot drove slower than 0.02 m/s (a spin on the spot, a stop): the
                      flow holds no depth, the window or the carried points decide;
    window none       this pair named a TPO, the window over the last pairs says `none`;
    no plane          the pair's shape fit holds no plane;
    one plane         one plane, and the classifier names no TPO from it;
    two planes        two planes, and the classifier names no TPO from them;
- the confusion matrix, truth by row, reported by column.

    RUST_LOG=flownav::sim::frames=trace flownav sim --seed 100 --no-log --quiet 2> s100.log
    bench/tpo_breakdown.py s100.log [more.log ...]
"""
import argparse
import re
import sys
from collections import Counter

SHAPES = ["Wall", "Corner", "Door", "Corridor", "None"]
STILL_M_S = 0.02
FIELD = re.compile(r"(\w+)=(\S+)")


def fields(text: str) -> dict:
    return {m.group(1): m.group(2) for m in FIELD.finditer(text)}


def cause(frame: dict, offis: dict) -> str:
    if offis["raw"] != "None":
        return "window none"
    if abs(float(frame["odo_v"])) < STILL_M_S:
        return "no translation"
    return {"0": "no plane", "1": "one plane"}.get(offis["planes"], "two planes")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="+", help="frame traces (stderr of the traced runs)")
    args = ap.parse_args()
    confusion, causes = Counter(), Counter()
    steps = 0
    for path in args.logs:
        frame = None
        try:
            lines = open(path, encoding="utf-8", errors="replace")
        except OSError as e:
            print(f"tpo_breakdown: cannot read {path}: {e.strerror}", file=sys.stderr)
            return 2
        with lines:
            for line in lines:
                if " frame t=" in line:
                    frame = fields(line.split(" frame ", 1)[1])
                elif " offis t=" in line and frame is not None:
                    offis = fields(line.split(" offis ", 1)[1])
                    try:
                        truth, said = frame["true_tpo"], frame["tpo"]
                        confusion[truth, said] += 1
                        if truth != "None" and said == "None":
                            causes[cause(frame, offis)] += 1
                    except KeyError as e:
                        print(f"tpo_breakdown: {path}: a step without the field {e}: is this a frame trace "
                              "(RUST_LOG=flownav::sim::frames=trace)?", file=sys.stderr)
                        return 2
                    steps += 1
                    frame = None
    if steps == 0:
        print("tpo_breakdown: no traced steps found: run the simulator with "
              "RUST_LOG=flownav::sim::frames=trace and pass its standard error", file=sys.stderr)
        return 2
    tpo = sum(n for (t, _), n in confusion.items() if t != "None")
    empty = steps - tpo
    agree = sum(n for (t, p), n in confusion.items() if t == p)
    named = sum(n for (t, p), n in confusion.items() if t == "None" and p != "None")
    print(f"steps {steps}, reported TPO equal to the truth {agree / steps:.3f}")
    print(f"tpo_none_share {sum(causes.values()) / max(tpo, 1):.3f} of {tpo} TPO steps; "
          f"none_named_share {named / max(empty, 1):.3f} of {empty} steps without")
    for c, n in causes.most_common():
        print(f"  {c:<16} {n / max(tpo, 1):.3f}")
    print("truth \\ reported " + " ".join(f"{s:>8}" for s in SHAPES))
    for t in SHAPES:
        print(f"{t:>16}  " + " ".join(f"{confusion[t, p]:>8}" for p in SHAPES))
    return 0


if __name__ == "__main__":
    sys.exit(main())
