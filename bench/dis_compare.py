#!/usr/bin/env python3
"""Endpoint error of `flownav flow` and of OpenCV's DIS optical flow at the same block centres.

For each reference pair in the data folder (see its README) the 32x32 tiles of
gt/blocks32_tile.csv are used: flownav runs with `--placement tile` on exactly those tiles and
reports one vector per tile at its centre pixel (x0+16, y0+16); DIS computes dense flow and is
read at the same pixels. EPE = mean |(u, v) - (u_gt, v_gt)| over the selected tiles, counting
every tile whatever flownav's validity flag says (a second column counts only flownav-valid tiles).

Usage (from the repository root, after `cargo build --release`):
    pip install opencv-python-headless numpy
    python3 bench/dis_compare.py [--data DIR] [--flownav target/release/flownav]
"""
import argparse
import csv
import json
import os
import subprocess
import sys
import time

import cv2
import numpy as np


def find_data(arg):
    here = os.path.dirname(os.path.abspath(__file__))
    for d in [arg, os.environ.get("FLOWNAV_DATA"), os.path.join(here, "..", "data"),
              os.path.join(here, "..", "..", "shared", "data"), os.path.join(here, "..", "..", "..", "shared", "data")]:
        if d and os.path.isfile(os.path.join(d, "graf_shift_512", "0000.png")):
            return os.path.abspath(d)
    sys.exit("reference data not found: pass --data DIR or set FLOWNAV_DATA")


def read_tiles(pair_dir):
    rows = list(csv.DictReader(open(os.path.join(pair_dir, "gt", "blocks32_tile.csv"))))
    for r in rows:
        for k in ("row", "col", "x0", "y0", "cx", "cy", "centre_valid", "in_range16", "target_inside"):
            r[k] = int(r[k])
        for k in ("u_centre", "v_centre"):
            r[k] = float(r[k])
    return rows


def flownav_tiles(binary, pair_dir, rows, cols, levels):
    cmd = [binary, "flow", os.path.join(pair_dir, "0000.png"), os.path.join(pair_dir, "0001.png"), "--json",
           "--placement", "tile", "--rows", str(rows), "--cols", str(cols), "--block", "32", "--radius", "16",
           "--pyramid-levels", str(levels)]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    j = json.loads(out)
    assert j["grid"] == [rows, cols]
    return {(i // cols, i % cols): v for i, v in enumerate(j["vectors"])}


def dis_dense(pair_dir, preset):
    a = cv2.imread(os.path.join(pair_dir, "0000.png"), cv2.IMREAD_GRAYSCALE)
    b = cv2.imread(os.path.join(pair_dir, "0001.png"), cv2.IMREAD_GRAYSCALE)
    dis = cv2.DISOpticalFlow_create(preset)
    t0 = time.perf_counter()
    flow = dis.calc(a, b, None)
    return flow, (time.perf_counter() - t0) * 1e3


def epe(tiles, est, select, only_valid=False):
    errs = []
    for t in tiles:
        if not (t["centre_valid"] and select(t)):
            continue
        u, v, valid = est(t)
        if only_valid and not valid:
            continue
        errs.append(np.hypot(u - t["u_centre"], v - t["v_centre"]))
    return (float(np.mean(errs)) if errs else float("nan")), len(errs)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data")
    ap.add_argument("--flownav", default="target/release/flownav")
    args = ap.parse_args()
    data = find_data(args.data)
    print(f"OpenCV {cv2.__version__}, data {data}, flownav {args.flownav}\n")
    print("| pair | tiles | flownav R=16 | flownav 3-level pyramid | DIS medium | DIS fast |")
    print("|---|---|---|---|---|---|")
    for pair in ("graf_shift_512", "motorcycle_stereo"):
        d = os.path.join(data, pair)
        tiles = read_tiles(d)
        rows, cols = max(t["row"] for t in tiles) + 1, max(t["col"] for t in tiles) + 1
        ours = {L: flownav_tiles(args.flownav, d, rows, cols, L) for L in (1, 3)}
        dis = {}
        for name, preset in (("medium", cv2.DISOPTICAL_FLOW_PRESET_MEDIUM), ("fast", cv2.DISOPTICAL_FLOW_PRESET_FAST)):
            dis[name], _ = dis_dense(d, preset)

        def ours_est(L):
            return lambda t: (ours[L][(t["row"], t["col"])]["u"], ours[L][(t["row"], t["col"])]["v"],
                              ours[L][(t["row"], t["col"])]["valid"])

        def dis_est(name):
            return lambda t: (float(dis[name][t["cy"], t["cx"], 0]), float(dis[name][t["cy"], t["cx"], 1]), True)

        sets = [("in range & target inside", lambda t: t["in_range16"] and t["target_inside"]),
                ("all with known GT", lambda t: True)]
        for label, sel in sets:
            cells = []
            for L in (1, 3):
                e, n = epe(tiles, ours_est(L), sel)
                ev, nv = epe(tiles, ours_est(L), sel, only_valid=True)
                cells.append(f"{e:.3f} ({ev:.3f} on {nv} valid)")
            for name in ("medium", "fast"):
                cells.append(f"{epe(tiles, dis_est(name), sel)[0]:.3f}")
            print(f"| {pair} | {label}: {n} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
