"""The report's figures, drawn with matplotlib (Debian's python3-matplotlib,
Agg backend: no display needed).

trajectory.png: the flown x-y trajectories over the world's walls and
obstacles (filled, in plan view), the planned paths dashed, each vehicle's
flown path solid in a colour of its own, start and end marked, and a saved
map's occupied cells.

timeline.png: the behaviors' activity, a Gantt chart with one row per
behavior and one bar per activation, coloured by its termination cause.

    plot_trajectory("trajectory.png", flown=[(x, y), ...], planned=[(x, y), ...])
    plot_trajectories("trajectory.png", [flown1, flown2], [planned1, planned2],
                      labels=["drone1", "drone2"], walls=[...], obstacles=[...])
    plot_timeline("timeline.png", [{"behavior": "TAKE_OFF", "start_s": 0.4,
                                    "end_s": 6.1, "cause": "GOAL_ACHIEVED"}, ...])
"""

import math

import matplotlib

matplotlib.use("Agg")  # before pyplot: files only, no display

import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

DPI = 100
GRID = (235, 235, 235)
PLANNED = (100, 100, 100)   # the planned paths, dashed
WALL = (150, 150, 150)      # the world's walls (filled)
OBSTACLE = (205, 205, 205)  # the world's boxes (filled, edged in WALL)
CELL = (60, 60, 60)         # a map's occupied cells (dark grey)
FLOWN = (31, 119, 180)
START = (44, 160, 44)
END = (214, 39, 40)
# One colour per vehicle, the first being FLOWN; START and END are not among
# them.
VEHICLE_COLORS = [(FLOWN, "blue"), ((255, 127, 14), "orange"), ((148, 103, 189), "purple"),
                  ((140, 86, 75), "brown"), ((227, 119, 194), "pink"),
                  ((23, 190, 207), "cyan"), ((188, 189, 34), "olive"), ((0, 0, 0), "black")]
# The timeline's bar colour per termination cause (demo.short_cause), in
# the legend's order; ACTIVE: not terminated when the report was written.
CAUSE_COLORS = [("GOAL_ACHIEVED", (44, 160, 44)), ("TIME_OUT", (255, 127, 14)),
                ("WRONG_PROGRESS", (148, 103, 189)), ("SITUATION_CHANGE", (23, 190, 207)),
                ("PROCESS_FAILURE", (214, 39, 40)), ("INTERRUPTED", (150, 150, 150)),
                ("UNSPECIFIED", (140, 86, 75)), ("ACTIVE", (31, 119, 180))]
ACTIVE = "ACTIVE"


def _rgb(color):
    """matplotlib's colour (0..1 floats) of an 8-bit RGB triple."""
    return tuple(c / 255.0 for c in color)


def vehicle_colors(count):
    """The RGB colours of `count` vehicles' lines, in order."""
    return [VEHICLE_COLORS[i % len(VEHICLE_COLORS)][0] for i in range(count)]


def color_name(color):
    return next((name for c, name in VEHICLE_COLORS if c == color), str(color))


def cause_color(cause):
    """The RGB colour of a termination cause's bars (ACTIVE, or None, for
    an activation not terminated; UNSPECIFIED's for an unknown cause)."""
    colors = dict(CAUSE_COLORS)
    return colors.get(cause or ACTIVE, colors["UNSPECIFIED"])


def segment_polygon(a, b, thickness_m=0.2):
    """The plan-view rectangle of a wall segment from `a` to `b`,
    `thickness_m` wide (a degenerate segment gives a square)."""
    (x0, y0), (x1, y1) = a, b
    length = math.hypot(x1 - x0, y1 - y0)
    ux, uy = ((x1 - x0) / length, (y1 - y0) / length) if length > 0 else (1.0, 0.0)
    nx, ny = -uy * thickness_m / 2, ux * thickness_m / 2
    if length <= 0:
        x1, y1 = x0 + ux * thickness_m, y0
    return [(x0 + nx, y0 + ny), (x1 + nx, y1 + ny), (x1 - nx, y1 - ny), (x0 - nx, y0 - ny)]


def _polygons(shapes, thickness_m):
    """Polygons from `shapes`: a polygon (three points or more) as it is, a
    segment (two points) as its rectangle `thickness_m` wide."""
    out = []
    for shape in shapes:
        points = [(float(p[0]), float(p[1])) for p in shape]
        if len(points) == 2:
            points = segment_polygon(points[0], points[1], thickness_m)
        if len(points) >= 3:
            out.append(points)
    return out


def _limits(points, pad_fraction=0.06, minimum_m=1.0):
    """x and y limits around `points` with a margin, each at least
    `minimum_m` wide."""
    xs = [p[0] for p in points] or [0.0]
    ys = [p[1] for p in points] or [0.0]
    pad = max(max(xs) - min(xs), max(ys) - min(ys), minimum_m) * pad_fraction

    def around(values):
        lo, hi = min(values) - pad, max(values) + pad
        if hi - lo < minimum_m:
            middle = (lo + hi) / 2
            lo, hi = middle - minimum_m / 2, middle + minimum_m / 2
        return lo, hi

    return around(xs), around(ys)


def _legend_below(fig, ax, handles, gap_in=0.55):
    """The legend under the x axis's label, `gap_in` inches below the
    axes, four entries a row."""
    if not handles:
        return
    ax.apply_aspect()  # the axes' final box (equal scales shrink it)
    axes_height_in = ax.get_position().height * fig.get_figheight()
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -gap_in / axes_height_in),
              ncol=min(len(handles), 4), frameon=False, fontsize=9)


def _save(fig, path, margin):
    fig.savefig(path, dpi=DPI, bbox_inches="tight", pad_inches=max(margin, 0) / DPI,
                facecolor="white", metadata={"Software": None})
    plt.close(fig)


def plot_trajectory(path, flown, planned=(), size=800, margin=16, **kwargs):
    """Writes the x-y plot of one vehicle (world ENU, x to the right, y up,
    equal scales)."""
    plot_trajectories(path, [flown], [planned], size=size, margin=margin, **kwargs)


def plot_trajectories(path, flown_lines, planned_lines=(), labels=None, size=800, margin=16,
                      walls=(), cells=(), cell_m=0.1, obstacles=(), wall_thickness_m=0.2,
                      title=None):
    """Writes the x-y plot of several vehicles (world ENU, x to the right, y
    up, equal scales): each of `flown_lines` in its colour (vehicle_colors),
    each of `planned_lines` grey and dashed, green dots at the starts and red
    ones at the ends; the legend names each line by its `labels` (one per
    flown line) when given.

    Under them, the world: `walls` filled in WALL, each a polygon (its
    plan-view outline) or a segment ((x0, y0), (x1, y1)) drawn
    `wall_thickness_m` wide (doors left out); `obstacles` (the boxes'
    outlines) filled in OBSTACLE; and a map's occupied `cells` (centres (x,
    y), `cell_m` wide) in CELL: a person sees at a glance where the map put
    the walls. `size` is the figure's width in pixels (its height follows
    the plot's aspect), `margin` the blank border in pixels."""
    flown_lines = [[(float(p[0]), float(p[1])) for p in line] for line in flown_lines]
    planned_lines = [[(float(p[0]), float(p[1])) for p in line] for line in planned_lines]
    wall_polygons = _polygons(walls, wall_thickness_m)
    obstacle_polygons = _polygons(obstacles, wall_thickness_m)
    cells = [(float(c[0]), float(c[1])) for c in cells]
    points = [p for line in flown_lines + planned_lines for p in line]
    points += [p for polygon in wall_polygons + obstacle_polygons for p in polygon] + cells
    (x_lo, x_hi), (y_lo, y_hi) = _limits(points)

    # The figure's height from the data's aspect, within reason; the title
    # and the legend below add to it.
    aspect = min(max((y_hi - y_lo) / (x_hi - x_lo), 0.45), 1.6)
    width_in = max(size, 240) / DPI
    fig, ax = plt.subplots(figsize=(width_in, width_in * aspect + 1.2), dpi=DPI)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlim(x_lo, x_hi)
    ax.set_ylim(y_lo, y_hi)
    ax.grid(True, color=_rgb(GRID), linewidth=0.8, zorder=0)
    ax.set_axisbelow(True)
    ax.set_xlabel("x (m, east)")
    ax.set_ylabel("y (m, north)")
    several = len(flown_lines) > 1
    ax.set_title(title or ("x-y trajectories" if several else "x-y trajectory")
                 + " (simulator ground truth)", fontsize=12)

    handles, world = [], []
    if obstacle_polygons:
        ax.add_collection(PolyCollection(obstacle_polygons, facecolors=_rgb(OBSTACLE),
                                         edgecolors=_rgb(WALL), linewidths=0.8, zorder=1))
        world.append(Patch(facecolor=_rgb(OBSTACLE), edgecolor=_rgb(WALL),
                           label="obstacles (world)"))
    if wall_polygons:
        ax.add_collection(PolyCollection(wall_polygons, facecolors=_rgb(WALL),
                                         edgecolors="none", zorder=2))
        world.insert(0, Patch(facecolor=_rgb(WALL), label="walls (world)"))
    if cells:
        half = cell_m / 2
        squares = [[(x - half, y - half), (x + half, y - half), (x + half, y + half),
                    (x - half, y + half)] for x, y in cells]
        ax.add_collection(PolyCollection(squares, facecolors=_rgb(CELL), edgecolors="none",
                                         antialiaseds=False, zorder=3))
        world.append(Patch(facecolor=_rgb(CELL), label="map: occupied cells"))
    dashes = (0, (5, 4))
    for planned in planned_lines:
        if planned:
            ax.plot([p[0] for p in planned], [p[1] for p in planned], color=_rgb(PLANNED),
                    linestyle=dashes, linewidth=1.3, marker="o", markersize=4, zorder=4)
    # The starts under the flown lines, the ends over them: a dot in the
    # vehicle's colour with a red centre, so that a vehicle that went
    # straight up and down (its line a point in plan view) still shows.
    starts = [line[0] for line in flown_lines if line]
    if starts:
        ax.scatter([p[0] for p in starts], [p[1] for p in starts], s=150, color=_rgb(START),
                   edgecolors="white", linewidths=1.0, zorder=5)
    colors = vehicle_colors(len(flown_lines))
    for k, (flown, color) in enumerate(zip(flown_lines, colors)):
        if not flown:
            continue
        label = labels[k] if labels and k < len(labels) else "flown"
        ax.plot([p[0] for p in flown], [p[1] for p in flown], color=_rgb(color), linewidth=2.2,
                solid_joinstyle="round", solid_capstyle="round", zorder=6)
        ax.scatter([flown[-1][0]], [flown[-1][1]], s=70, color=_rgb(color), edgecolors="none",
                   zorder=7)
        ax.scatter([flown[-1][0]], [flown[-1][1]], s=22, color=_rgb(END), edgecolors="none",
                   zorder=8)
        handles.append(Line2D([], [], color=_rgb(color), linewidth=2.2, label=label))
    if any(planned_lines):
        handles.append(Line2D([], [], color=_rgb(PLANNED), linestyle=dashes, linewidth=1.3,
                              marker="o", markersize=4, label="planned path"))
    if starts:
        handles.append(Line2D([], [], linestyle="none", marker="o", markersize=10,
                              markerfacecolor=_rgb(START), markeredgecolor="white",
                              label="start"))
        handles.append(Line2D([], [], linestyle="none", marker="o", markersize=5,
                              markerfacecolor=_rgb(END), markeredgecolor="none", label="end"))
    handles += world
    _legend_below(fig, ax, handles)
    _save(fig, path, margin)


def plot_timeline(path, activations, end_s=None, size=900, margin=16, title=None):
    """Writes the behaviors' activity as a Gantt chart: one row per behavior
    (rows in the order of their first activation, top to bottom), one bar
    per activation from its activation to its termination, coloured by its
    termination cause (CAUSE_COLORS), its paused intervals hatched; x is
    simulated time in seconds.

    activations: dicts with `behavior` (the row's label: e.g. "TAKE_OFF", or
    "drone2 TAKE_OFF" with several robots), `start_s`, `end_s` (None while
    still active: the bar reaches `end_s`, default the latest time of all),
    `cause` (the short termination cause, None while active) and optionally
    `paused` ([(from_s, to_s), ...], to_s None while paused) and `group`
    (e.g. the robot's index: the rows of a group together, groups in
    increasing order, a line between them)."""
    activations = [a for a in activations if a.get("start_s") is not None
                   or a.get("end_s") is not None]
    times = [t for a in activations for t in (a.get("start_s"), a.get("end_s"))
             if t is not None]
    horizon = max(times + ([end_s] if end_s is not None else []), default=1.0)
    origin = min(times, default=0.0)
    rows, groups = [], []
    for a in sorted(activations, key=lambda a: (a.get("group", 0), a.get("start_s") is None,
                                                a.get("start_s") or 0.0)):
        if a["behavior"] not in rows:
            rows.append(a["behavior"])
            groups.append(a.get("group", 0))
    span = max(horizon - min(origin, 0.0), 1e-3)
    min_width = span * 0.004  # an instant activation stays visible

    height_in = 1.6 + 0.32 * max(len(rows), 1)
    fig, ax = plt.subplots(figsize=(max(size, 320) / DPI, height_in), dpi=DPI)
    used = []
    for a in activations:
        start = a.get("start_s")
        end = a.get("end_s")
        start = end if start is None else start
        end = horizon if end is None else end
        cause = a.get("cause") or ACTIVE  # a cause without end_s: ended, time unknown
        color = cause_color(cause)
        key = cause if cause in dict(CAUSE_COLORS) else "UNSPECIFIED"
        if key not in used:
            used.append(key)
        y = rows.index(a["behavior"])
        ax.barh(y, max(end - start, min_width), left=start, height=0.62, color=_rgb(color),
                edgecolor="white", linewidth=0.8, zorder=2)
        for p_from, p_to in a.get("paused") or []:
            if p_from is None:
                continue
            p_to = end if p_to is None else p_to
            ax.barh(y, max(p_to - p_from, min_width), left=p_from, height=0.62,
                    color="white", alpha=0.55, hatch="////", edgecolor=_rgb(color),
                    linewidth=0, zorder=3)
    for y in range(1, len(rows)):
        if groups[y] != groups[y - 1]:  # between robots
            ax.axhline(y - 0.5, color=_rgb(PLANNED), linewidth=0.8, zorder=1)
    ax.set_yticks(range(len(rows)))
    ax.set_yticklabels(rows, fontsize=9)
    ax.set_ylim(len(rows) - 0.4, -0.6)  # the first activated on top
    ax.set_xlim(min(origin, 0.0), horizon + span * 0.01)
    ax.set_xlabel("simulated time (s)")
    ax.grid(True, axis="x", color=_rgb(GRID), linewidth=0.8, zorder=0)
    ax.set_axisbelow(True)
    ax.set_title(title or "Behavior activity (bars coloured by termination cause)", fontsize=12)
    order = [c for c, _ in CAUSE_COLORS]
    handles = [Patch(facecolor=_rgb(cause_color(c)),
                     label="still active" if c == ACTIVE else c)
               for c in sorted(used, key=order.index)]
    if any(a.get("paused") for a in activations):
        handles.append(Patch(facecolor="white", edgecolor="#808080", hatch="////",
                             label="paused"))
    _legend_below(fig, ax, handles)
    _save(fig, path, margin)
