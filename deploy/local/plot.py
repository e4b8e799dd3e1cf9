"""A PNG plot of flown x-y trajectories, in pure Python (zlib only): axes
with metre ticks, the planned paths dashed, each vehicle's flown path solid
in a colour of its own (with a legend when labelled), start and end marked.

    plot_trajectory("trajectory.png", flown=[(x, y), ...], planned=[(x, y), ...])
    plot_trajectories("trajectory.png", [flown1, flown2], [planned1, planned2],
                      labels=["drone1", "drone2"])
"""

import math
import struct
import zlib

WHITE = (255, 255, 255)
GRID = (225, 225, 225)
AXIS = (90, 90, 90)
PLANNED = (150, 150, 150)
WALL = (200, 185, 160)      # the world's walls (tan)
CELL = (60, 60, 60)         # a map's occupied cells (dark grey)
FLOWN = (31, 119, 180)
START = (44, 160, 44)
END = (214, 39, 40)
# One colour per vehicle, the first being FLOWN; START and END are not among
# them.
VEHICLE_COLORS = [(FLOWN, "blue"), ((255, 127, 14), "orange"), ((148, 103, 189), "purple"),
                  ((140, 86, 75), "brown"), ((227, 119, 194), "pink"),
                  ((23, 190, 207), "cyan"), ((188, 189, 34), "olive"), ((0, 0, 0), "black")]

# 3x5 glyphs, rows top to bottom, 3 bits each (bit 2 = left column).
_FONT = {
    "0": (7, 5, 5, 5, 7), "1": (2, 6, 2, 2, 7), "2": (7, 1, 7, 4, 7), "3": (7, 1, 7, 1, 7),
    "4": (5, 5, 7, 1, 1), "5": (7, 4, 7, 1, 7), "6": (7, 4, 7, 5, 7), "7": (7, 1, 1, 1, 1),
    "8": (7, 5, 7, 5, 7), "9": (7, 5, 7, 1, 7), "-": (0, 0, 7, 0, 0), ".": (0, 0, 0, 0, 2),
    "x": (0, 5, 2, 5, 0), "y": (5, 5, 2, 2, 2), "m": (0, 7, 7, 5, 5), "(": (1, 2, 2, 2, 1),
    ")": (4, 2, 2, 2, 4), " ": (0, 0, 0, 0, 0),
    # Letters (one case) and a few more, for the legend's robot ids.
    "a": (2, 5, 7, 5, 5), "b": (6, 5, 6, 5, 6), "c": (7, 4, 4, 4, 7), "d": (6, 5, 5, 5, 6),
    "e": (7, 4, 6, 4, 7), "f": (7, 4, 6, 4, 4), "g": (7, 4, 5, 5, 7), "h": (5, 5, 7, 5, 5),
    "i": (7, 2, 2, 2, 7), "j": (1, 1, 1, 5, 7), "k": (5, 5, 6, 5, 5), "l": (4, 4, 4, 4, 7),
    "n": (6, 5, 5, 5, 5), "o": (2, 5, 5, 5, 2), "p": (6, 5, 6, 4, 4), "q": (2, 5, 5, 6, 3),
    "r": (6, 5, 6, 5, 5), "s": (3, 4, 2, 1, 6), "t": (7, 2, 2, 2, 2), "u": (5, 5, 5, 5, 7),
    "v": (5, 5, 5, 5, 2), "w": (5, 5, 7, 7, 5), "z": (7, 1, 2, 4, 7), "_": (0, 0, 0, 0, 7),
    "/": (1, 1, 2, 4, 4), ":": (0, 2, 0, 2, 0),
}


def write_png(path, width, height, pixels):
    """Writes an 8-bit RGB PNG; `pixels` is a bytearray of width*height*3."""
    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    stride = width * 3
    raw = b"".join(b"\x00" + bytes(pixels[y * stride:(y + 1) * stride]) for y in range(height))
    png = (b"\x89PNG\r\n\x1a\n"
           + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 9))
           + chunk(b"IEND", b""))
    with open(path, "wb") as f:
        f.write(png)


class Canvas:
    def __init__(self, width, height, background=WHITE):
        self.width, self.height = width, height
        self.pixels = bytearray(bytes(background) * (width * height))

    def dot(self, x, y, color, radius=0):
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                if dx * dx + dy * dy > radius * radius + radius:
                    continue
                px, py = int(x) + dx, int(y) + dy
                if 0 <= px < self.width and 0 <= py < self.height:
                    i = (py * self.width + px) * 3
                    self.pixels[i:i + 3] = bytes(color)

    def line(self, x0, y0, x1, y1, color, width=1, dash=0):
        """Line from (x0, y0) to (x1, y1), `width` pixels thick; dashed
        every `dash` pixels when dash > 0."""
        length = max(abs(x1 - x0), abs(y1 - y0), 1e-9)
        steps = int(math.ceil(length))
        radius = max(0, (width - 1) // 2)
        for i in range(steps + 1):
            if dash and (i // dash) % 2:
                continue
            t = i / steps if steps else 0.0
            self.dot(round(x0 + (x1 - x0) * t), round(y0 + (y1 - y0) * t), color, radius)

    def text(self, x, y, string, color, scale=2):
        """Text from the small font, top-left corner at (x, y)."""
        for k, char in enumerate(string):
            glyph = _FONT.get(char, _FONT.get(char.lower(), _FONT[" "]))
            for row, bits in enumerate(glyph):
                for col in range(3):
                    if bits & (4 >> col):
                        for sy in range(scale):
                            for sx in range(scale):
                                self.dot(x + (k * 4 + col) * scale + sx, y + row * scale + sy,
                                         color)

    def save(self, path):
        write_png(path, self.width, self.height, self.pixels)


def _tick_step(span):
    """A round tick spacing giving about 5-10 ticks over `span` metres."""
    raw = span / 6.0
    magnitude = 10 ** math.floor(math.log10(raw))
    for factor in (1, 2, 5, 10):
        if raw <= factor * magnitude:
            return factor * magnitude
    return 10 * magnitude


def _label(value, step):
    decimals = 0 if step >= 1 else min(3, int(math.ceil(-math.log10(step))))
    return f"{value:.{decimals}f}"


def vehicle_colors(count):
    """The RGB colours of `count` vehicles' lines, in order."""
    return [VEHICLE_COLORS[i % len(VEHICLE_COLORS)][0] for i in range(count)]


def color_name(color):
    return next((name for c, name in VEHICLE_COLORS if c == color), str(color))


def plot_trajectory(path, flown, planned=(), size=640, margin=56):
    """Writes the x-y plot of one vehicle (world ENU, x to the right, y up,
    equal scales)."""
    plot_trajectories(path, [flown], [planned], size=size, margin=margin)


def plot_trajectories(path, flown_lines, planned_lines=(), labels=None, size=640, margin=56,
                      walls=(), cells=(), cell_m=0.1):
    """Writes the x-y plot of several vehicles: each of `flown_lines` in its
    colour (vehicle_colors), each of `planned_lines` grey and dashed; a
    legend above the plot when `labels` (one per flown line) are given.
    Under them, the world's `walls` (segments ((x0, y0), (x1, y1)), doors
    left out) in WALL, and a map's occupied `cells` (centres (x, y), `cell_m`
    wide) in CELL: a person sees at a glance where the map put the walls."""
    flown_lines = [list(line) for line in flown_lines]
    planned_lines = [list(line) for line in planned_lines]
    walls = [tuple(w) for w in walls]
    cells = [tuple(c) for c in cells]
    points = [p for line in flown_lines + planned_lines for p in line]
    points += [p for w in walls for p in w] + cells
    if not points:
        points = [(0.0, 0.0)]
    xs = [p[0] for p in points]
    ys = [p[1] for p in points]
    cx, cy = (min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2
    span = max(max(xs) - min(xs), max(ys) - min(ys), 1.0) * 1.15
    inner = size - 2 * margin
    scale = inner / span

    def to_px(p):
        return (margin + (p[0] - cx + span / 2) * scale,
                size - margin - (p[1] - cy + span / 2) * scale)

    canvas = Canvas(size, size)
    step = _tick_step(span)
    x_min, y_min = cx - span / 2, cy - span / 2
    first = math.ceil(x_min / step)
    for k in range(first, first + int(span / step) + 2):
        value = k * step
        if value > x_min + span:
            break
        px = to_px((value, y_min))[0]
        canvas.line(px, margin, px, size - margin, GRID)
        canvas.line(px, size - margin, px, size - margin + 5, AXIS)
        label = _label(value, step)
        canvas.text(px - len(label) * 4, size - margin + 9, label, AXIS)
    first = math.ceil(y_min / step)
    for k in range(first, first + int(span / step) + 2):
        value = k * step
        if value > y_min + span:
            break
        py = to_px((x_min, value))[1]
        canvas.line(margin, py, size - margin, py, GRID)
        canvas.line(margin - 5, py, margin, py, AXIS)
        label = _label(value, step)
        canvas.text(margin - 8 - len(label) * 8, py - 5, label, AXIS)
    canvas.line(margin, margin, margin, size - margin, AXIS)
    canvas.line(margin, size - margin, size - margin, size - margin, AXIS)
    canvas.line(size - margin, margin, size - margin, size - margin, AXIS)
    canvas.line(margin, margin, size - margin, margin, AXIS)
    canvas.text(size // 2 - 20, size - margin + 28, "x (m)", AXIS)
    canvas.text(8, margin - 24, "y (m)", AXIS)

    for a, b in walls:
        pa, pb = to_px(a), to_px(b)
        canvas.line(pa[0], pa[1], pb[0], pb[1], WALL, width=max(3, int(round(0.2 * scale))))
    half = max(1, int(round(0.5 * cell_m * scale)))
    for c in cells:
        pc = to_px(c)
        for dy in range(-half, half):
            for dx in range(-half, half):
                px, py = int(pc[0]) + dx, int(pc[1]) + dy
                if 0 <= px < size and 0 <= py < size:
                    i = (py * size + px) * 3
                    canvas.pixels[i:i + 3] = bytes(CELL)
    for planned in planned_lines:
        planned_px = [to_px(p) for p in planned]
        for a, b in zip(planned_px, planned_px[1:]):
            canvas.line(a[0], a[1], b[0], b[1], PLANNED, width=2, dash=6)
        for p in planned_px:
            canvas.dot(p[0], p[1], PLANNED, radius=4)
    colors = vehicle_colors(len(flown_lines))
    for flown, color in zip(flown_lines, colors):
        flown_px = [to_px(p) for p in flown]
        for a, b in zip(flown_px, flown_px[1:]):
            canvas.line(a[0], a[1], b[0], b[1], color, width=3)
    for flown in flown_lines:  # over every line
        flown_px = [to_px(p) for p in flown]
        if flown_px:
            canvas.dot(flown_px[0][0], flown_px[0][1], START, radius=6)
            canvas.dot(flown_px[-1][0], flown_px[-1][1], END, radius=4)
    if labels:
        x = margin + 60
        for label, color in zip(labels, colors):
            canvas.line(x, margin - 19, x + 24, margin - 19, color, width=3)
            canvas.text(x + 30, margin - 24, label, AXIS)
            x += 30 + len(label) * 8 + 24
    canvas.save(path)
