#!/usr/bin/env python3
"""Compare sets of `flownav sim` runs: each set's rates with their 95 % intervals, and each set
against the first on the seeds they share, so that a design is not kept for a difference the
scatter makes on its own.

    bench/compare_runs.py BASE.jsonl OTHER.jsonl [MORE.jsonl ...]

On the shared seeds: Fisher's exact test of the two rates, and, since the same seed run with two
designs is a pair, McNemar's exact test on the seeds where the two differ (it sees a difference
that the scatter between seeds hides from Fisher's) and the paired difference in mission time
with its 95 % interval.

Each file holds the JSON lines of `flownav sim --seeds ...` (bench/nav_report.sh writes them);
lines without a `seed` (the aggregate) are skipped. Per set it prints the runs, reached with its
Clopper-Pearson interval, the runs with a contact with theirs (and those seeds), the mean
mission time, the escapes, `obstacles_held`, the ghost cells, and what the memory held of the
object at each run's first contact (`first_contact.memory`: occupied, guarded, misplaced, faded,
unknown; docs/sim.md). Standard library only.
"""

import json
import sys
from math import comb


def load(path):
    """The runs of a file by seed, or an error naming the file and the line."""
    runs = {}
    with open(path, encoding="utf-8") as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if not line.startswith("{"):
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError as e:
                sys.exit(f"{path}:{n}: not a JSON line ({e}); rerun the set or drop the line")
            if "seed" in row:
                runs[row["seed"]] = row
    if not runs:
        sys.exit(f"{path}: no runs (lines with a \"seed\"); is it the output of `flownav sim --seeds`?")
    return runs


def binom_cdf(k, n, p):
    return sum(comb(n, i) * p**i * (1 - p) ** (n - i) for i in range(k + 1))


def clopper_pearson(k, n, alpha=0.05):
    """The exact two-sided interval of a rate k / n, by bisection on the binomial tails."""

    def solve(f):
        lo, hi = 0.0, 1.0
        for _ in range(60):
            mid = (lo + hi) / 2
            if f(mid):
                lo = mid
            else:
                hi = mid
        return (lo + hi) / 2

    low = 0.0 if k == 0 else solve(lambda p: 1 - binom_cdf(k - 1, n, p) < alpha / 2)
    high = 1.0 if k == n else solve(lambda p: binom_cdf(k, n, p) > alpha / 2)
    return low, high


def fisher(a, n1, b, n2):
    """Two-sided Fisher's exact test of a / n1 against b / n2."""
    k, n = a + b, n1 + n2
    if k == 0 or k == n:
        return 1.0

    def p(x):
        return comb(n1, x) * comb(n2, k - x) / comb(n, k)

    p0 = p(a)
    return sum(p(x) for x in range(max(0, k - n2), min(k, n1) + 1) if p(x) <= p0 * (1 + 1e-9))


def mcnemar(only_a, only_b):
    """Two-sided exact McNemar test on paired runs: `only_a` seeds where the event happened in
    the first set only, `only_b` in the second only (a binomial test of the discordant pairs)."""
    n = only_a + only_b
    if n == 0:
        return 1.0
    k = min(only_a, only_b)
    return min(1.0, 2 * binom_cdf(k, n, 0.5))


def paired_mean(diffs):
    """Mean of paired differences with its 95 % interval (normal approximation: for 30 or more
    pairs)."""
    n = len(diffs)
    m = sum(diffs) / n
    if n < 2:
        return m, float("nan"), float("nan")
    sd = (sum((d - m) ** 2 for d in diffs) / (n - 1)) ** 0.5
    half = 1.96 * sd / n**0.5
    return m, m - half, m + half


def paired(base, runs, shared, event):
    """The seeds where `event(run)` holds in `runs` only and in `base` only, with McNemar's p."""
    only_o = [s for s in shared if event(runs[s]) and not event(base[s])]
    only_b = [s for s in shared if event(base[s]) and not event(runs[s])]
    p = mcnemar(len(only_o), len(only_b))
    return f"{len(only_o)} seeds only here {only_o}, {len(only_b)} only in the first {only_b} (McNemar p = {p:.2f})"


def rate(k, n):
    lo, hi = clopper_pearson(k, n)
    return f"{k} / {n} ({100 * lo:.1f}–{100 * hi:.1f} %)"


def summary(runs):
    rows = list(runs.values())
    n = len(rows)
    reached = sum(1 for r in rows if r.get("reached"))
    touched = sorted(r["seed"] for r in rows if r.get("collisions"))

    def mean(key):
        return sum(r.get(key) or 0 for r in rows) / n

    classes = {}
    for r in rows:
        first = r.get("first_contact") or {}
        if "memory" in first:
            classes[first["memory"]] = classes.get(first["memory"], 0) + 1
    memory = ", ".join(f"{k} {v}" for k, v in sorted(classes.items(), key=lambda kv: (-kv[1], kv[0])))

    return {
        "n": n,
        "reached": reached,
        "touched": touched,
        "line": f"reached {rate(reached, n)}, runs with a contact {rate(len(touched), n)} {touched}, "
        f"mean time {mean('time_s'):.1f} s, escapes {sum(r.get('escapes', 0) for r in rows)}, "
        f"held {100 * mean('obstacles_held'):.1f} %, ghost {100 * mean('cells_ghost'):.1f} %"
        + (f", first contacts: {memory}" if memory else ""),
    }


def main(paths):
    if len(paths) < 1:
        sys.exit(__doc__.strip().splitlines()[4].strip())
    sets = [(p, load(p)) for p in paths]
    for path, runs in sets:
        print(f"{path}: {summary(runs)['line']}")
    base_path, base = sets[0]
    for path, runs in sets[1:]:
        shared = sorted(set(base) & set(runs))
        if not shared:
            print(f"{path} against {base_path}: no seeds in common")
            continue
        b = summary({s: base[s] for s in shared})
        o = summary({s: runs[s] for s in shared})
        n = len(shared)
        print(
            f"{path} against {base_path} on their {n} shared seeds: "
            f"reached {o['reached']} against {b['reached']} (p = {fisher(o['reached'], n, b['reached'], n):.2f}), "
            f"runs with a contact {len(o['touched'])} against {len(b['touched'])} "
            f"(p = {fisher(len(o['touched']), n, len(b['touched']), n):.2f})"
        )
        m, lo, hi = paired_mean([(runs[s].get("time_s") or 0) - (base[s].get("time_s") or 0) for s in shared])
        print(f"  paired: reached: {paired(base, runs, shared, lambda r: bool(r.get('reached')))}")
        print(f"  paired: a contact: {paired(base, runs, shared, lambda r: bool(r.get('collisions')))}")
        print(f"  paired: mission time {m:+.1f} s ({lo:+.1f} to {hi:+.1f} s, 95 %)")


if __name__ == "__main__":
    main(sys.argv[1:])
