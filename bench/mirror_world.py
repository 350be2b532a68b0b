#!/usr/bin/env python3
"""Writes a flownav world or map file mirrored across the x axis (y -> -y): every left turn
becomes a right turn and every door on the left a door on the right. A building the navigation
was never tuned on, from one it was: what it does in one it must do in the other, so a
difference beyond the scatter is a left/right asymmetry in the code. The file's comments are
kept as they were (they describe the original) under a header that says so.

    bench/mirror_world.py mocks/worlds/lshape.toml > /tmp/lshape-m.toml
    bench/mirror_world.py maps/lshape.toml > /tmp/lshape-m-map.toml
    flownav sim --world /tmp/lshape-m.toml --map /tmp/lshape-m-map.toml --mission R5:D10 ...

What changes: every `[x, y]` pair (wall points, places, box and cylinder centres, the random
lane's ends, map positions) becomes `[x, -y]`; `heading_deg`, `yaw_deg` and the start's `y`
change sign; `side = "left"` and `side = "right"` swap. Lengths, widths and door distances
along a wall are unchanged: mirroring keeps every distance. The random obstacles are drawn
across their lane as before, so a seed places them where it does in the original, not
mirrored.
"""
import re
import sys
import tomllib

NUMBER = r"(-?\d+(?:\.\d+)?)"


def number(v: float) -> str:
    return repr(round(v, 6) + 0.0)  # + 0.0: never "-0.0"


def negate_angle(v: float) -> str:
    return number(v if abs(v) == 180.0 else -v)


def mirror_line(line: str) -> str:
    if line.lstrip().startswith("#"):
        return line
    code, hash_, comment = line.partition(" #")
    code = re.sub(
        rf"\[\s*{NUMBER}\s*,\s*{NUMBER}\s*\]", lambda m: f"[{m.group(1)}, {number(-float(m.group(2)))}]", code
    )
    code = re.sub(rf"\b(heading_deg|yaw_deg) = {NUMBER}", lambda m: f"{m.group(1)} = {negate_angle(float(m.group(2)))}", code)
    code = re.sub(rf"(start = \{{[^}}]*\by = ){NUMBER}", lambda m: m.group(1) + number(-float(m.group(2))), code)
    code = re.sub(r'side = "(left|right)"', lambda m: f'side = "{"right" if m.group(1) == "left" else "left"}"', code)
    return code + hash_ + comment


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    path = sys.argv[1]
    text = open(path, encoding="utf-8").read()
    out = "\n".join(mirror_line(line) for line in text.split("\n"))
    try:
        tomllib.loads(out)
    except tomllib.TOMLDecodeError as e:
        print(f"mirror_world: the mirrored {path} is not valid TOML ({e}); is it a flownav world or map?", file=sys.stderr)
        return 1
    header = f"# {path} mirrored across the x axis (y -> -y) by bench/mirror_world.py; the comments below are the original's.\n"
    sys.stdout.write(header + out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
