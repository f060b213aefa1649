#!/usr/bin/env python3
"""Draws ticks of a long-suite trace (`road eval --suite long --trace DIR`) as one PNG, side by
side, with nothing but the standard library: the lanelets (white, centre lines blue with a dot
at their downstream end), the road off every lanelet grey, and each present vehicle's box with
its number and a line from its centre to its nose. A vehicle's colour says what the releases and
guards did to it that tick: red pulled away by the stall release, orange backing off (giving way
or making room), blue held by another guard (braked, stopped short, stopped at the road's edge),
green none.

    python3 scripts/trace_view.py DIR/MAP-seedS.jsonl --ticks 2790,2850,2930 \\
        --agent 0 --radius 12 --out view.png

`--agent A` centres every panel on agent A at the first tick; `--centre X Y` (metres) instead
fixes the centre. Built to read issue 39's long stops: which vehicle stands where, pointing
where, and which rule holds it.
"""

import argparse
import json
import math
import struct
import sys
import zlib

PANEL_PX = 500
GAP_PX = 4
BACKGROUND = (221, 221, 221)
LANELET = (255, 255, 255)
LANELET_EDGE = (170, 170, 170)
CENTRE_LINE = (150, 150, 255)
CENTRE_END = (0, 0, 200)
PULLED_AWAY = (255, 120, 120)
BACKING_OFF = (255, 190, 90)
HELD = (130, 130, 255)
FREE = (120, 200, 120)
INK = (0, 0, 0)

# A 3 × 5 pixel font for the numbers drawn (agent indices and ticks).
DIGITS = {
    "0": "111101101101111", "1": "010110010010111", "2": "111001111100111",
    "3": "111001111001111", "4": "101101111001001", "5": "111100111001111",
    "6": "111100111101111", "7": "111001001001001", "8": "111101111101111",
    "9": "111101111001111", "-": "000000111000000",
}


class Canvas:
    """An RGB raster with a clip range in x (one panel), written as PNG."""

    def __init__(self, width, height):
        self.width, self.height = width, height
        self.clip = (0, width)
        self.pixels = bytearray(bytes(BACKGROUND) * (width * height))

    def put(self, x, y, colour):
        if self.clip[0] <= x < self.clip[1] and 0 <= y < self.height:
            i = 3 * (y * self.width + x)
            self.pixels[i:i + 3] = bytes(colour)

    def fill(self, points, colour):
        """Fills a polygon (even-odd rule, one scan line per pixel row)."""
        ys = [p[1] for p in points]
        for y in range(max(0, int(min(ys))), min(self.height - 1, int(max(ys))) + 1):
            yc = y + 0.5
            xs = sorted(
                x1 + (yc - y1) * (x2 - x1) / (y2 - y1)
                for (x1, y1), (x2, y2) in zip(points, points[1:] + points[:1])
                if (y1 <= yc < y2) or (y2 <= yc < y1)
            )
            for a, b in zip(xs[::2], xs[1::2]):
                for x in range(max(self.clip[0], int(a + 0.5)), min(self.clip[1], int(b + 0.5) + 1)):
                    self.put(x, y, colour)

    def outline(self, points, colour):
        for p, q in zip(points, points[1:] + points[:1]):
            self.line(p, q, colour)

    def line(self, p, q, colour, width=1):
        n = int(max(abs(q[0] - p[0]), abs(q[1] - p[1]))) + 1
        if n > 4 * self.width:
            return
        for i in range(n + 1):
            x = p[0] + (q[0] - p[0]) * i / n
            y = p[1] + (q[1] - p[1]) * i / n
            for dx in range(width):
                for dy in range(width):
                    self.put(int(x) + dx, int(y) + dy, colour)

    def text(self, x, y, digits, scale=2):
        for j, ch in enumerate(digits):
            bits = DIGITS.get(ch)
            if bits is None:
                continue
            for r in range(5):
                for c in range(3):
                    if bits[3 * r + c] == "1":
                        for u in range(scale):
                            for v in range(scale):
                                self.put(int(x) + j * 4 * scale + c * scale + u, int(y) + r * scale + v, INK)

    def png(self):
        rows = b"".join(
            b"\x00" + bytes(self.pixels[3 * y * self.width:3 * (y + 1) * self.width])
            for y in range(self.height)
        )

        def chunk(kind, data):
            crc = zlib.crc32(kind + data) & 0xFFFFFFFF
            return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

        header = struct.pack(">IIBBBBB", self.width, self.height, 8, 2, 0, 0, 0)
        return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
                + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


def read_ticks(trace_path, wanted):
    """The wanted ticks' lines of a trace, each with the sizes known and the agents retired by
    then (agents enter and leave as the session runs)."""
    with open(trace_path.replace(".jsonl", ".map.json")) as f:
        header = json.load(f)
    sizes = dict(enumerate(header["size_m"]))
    retired, frames = set(), {}
    with open(trace_path) as f:
        for number, line in enumerate(f, 1):
            try:
                tick = json.loads(line)
            except json.JSONDecodeError as e:
                sys.exit(f"{trace_path}:{number}: not a JSON line: {e}")
            for agent, size in zip(tick["entered"], tick["entered_size_m"]):
                sizes[agent] = size
                retired.discard(agent)
            retired.update(tick["scene"].get("left", []))
            if tick["tick"] in wanted:
                frames[tick["tick"]] = (tick, dict(sizes), set(retired))
    missing = sorted(set(wanted) - set(frames))
    if missing:
        sys.exit(f"{trace_path}: no tick {missing[0]} in the trace")
    return header["map"], frames


def colour_of(actions):
    if not actions:
        return FREE
    if "pulled_away" in actions:
        return PULLED_AWAY
    if "backed_off" in actions:
        return BACKING_OFF
    return HELD


def draw(trace_path, ticks, centre, radius_m, agent):
    lanelet_map, frames = read_ticks(trace_path, ticks)
    if centre is None:
        poses = frames[ticks[0]][0]["scene"]["poses"]
        if not 0 <= agent < len(poses):
            sys.exit(f"{trace_path}: --agent {agent}: tick {ticks[0]} has agents 0 to {len(poses) - 1}")
        pose = poses[agent]
        centre = (pose["x_m"], pose["y_m"])
    cx, cy = centre
    scale = PANEL_PX / (2 * radius_m)
    near = [
        lanelet for lanelet in lanelet_map["lanelets"]
        if any(abs(p[0] - cx) < radius_m + 30 and abs(p[1] - cy) < radius_m + 30
               for p in lanelet["left_m"] + lanelet["right_m"])
    ]
    canvas = Canvas(len(ticks) * (PANEL_PX + GAP_PX) - GAP_PX, PANEL_PX)
    for panel, tick in enumerate(ticks):
        left = panel * (PANEL_PX + GAP_PX)
        canvas.clip = (left, left + PANEL_PX)

        def px(x, y):
            return (left + (x - cx + radius_m) * scale, (cy + radius_m - y) * scale)

        polygons = [[px(*p) for p in l["left_m"] + l["right_m"][::-1]] for l in near]
        for polygon in polygons:
            canvas.fill(polygon, LANELET)
        for lanelet, polygon in zip(near, polygons):
            canvas.outline(polygon, LANELET_EDGE)
            centre_line = lanelet["centre_m"]
            for a, b in zip(centre_line[::3], centre_line[1::3]):
                canvas.line(px(*a), px(*b), CENTRE_LINE, 2)
                end = px(*b)
                canvas.line((end[0] - 1, end[1] - 1), (end[0] + 1, end[1] + 1), CENTRE_END, 3)
        frame, sizes, retired = frames[tick]
        actions = {}
        for a, action in frame["scene"].get("guarded", []):
            actions.setdefault(a, []).append(action)
        for a, pose in enumerate(frame["scene"]["poses"]):
            x, y = pose["x_m"], pose["y_m"]
            if a in retired or abs(x - cx) > radius_m + 5 or abs(y - cy) > radius_m + 5:
                continue
            length_m, width_m = sizes.get(a, (4.5, 1.8))
            c, s = math.cos(pose["heading_rad"]), math.sin(pose["heading_rad"])
            corners = [(0.5 * length_m * u, 0.5 * width_m * v) for u, v in ((1, 1), (1, -1), (-1, -1), (-1, 1))]
            box = [px(x + u * c - v * s, y + u * s + v * c) for u, v in corners]
            canvas.fill(box, colour_of(actions.get(a)))
            canvas.outline(box, INK)
            canvas.line(px(x, y), px(x + 0.5 * length_m * c, y + 0.5 * length_m * s), INK, 2)
            at = px(x, y)
            canvas.text(at[0] - 4, at[1] - 4, str(a))
        canvas.text(left + 5, 5, str(tick), scale=3)
    return canvas.png()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("trace", help="a session's JSON lines (its .map.json beside it)")
    parser.add_argument("--ticks", required=True, help="ticks to draw, comma-separated")
    parser.add_argument("--agent", type=int, default=0, help="centre on this agent at the first tick")
    parser.add_argument("--centre", type=float, nargs=2, metavar=("X_M", "Y_M"))
    parser.add_argument("--radius", type=float, default=12.0, help="half the panel's width, metres")
    parser.add_argument("--out", required=True, help="the PNG to write")
    args = parser.parse_args()
    try:
        ticks = [int(t) for t in args.ticks.split(",")]
    except ValueError:
        sys.exit(f"--ticks: not comma-separated tick numbers: {args.ticks!r}")
    if not args.radius > 0:
        sys.exit(f"--radius: must be above 0 metres, got {args.radius}")
    png = draw(args.trace, ticks, args.centre, args.radius, args.agent)
    with open(args.out, "wb") as f:
        f.write(png)


if __name__ == "__main__":
    main()
