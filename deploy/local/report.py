"""The mission report: report.json (everything), report.md (for people),
trajectory.png (the flown paths over the world's walls and obstacles),
timeline.png (each behavior's activations, coloured by termination cause)
and trajectory.json (each robot's ground truth samples: [t_sim_s, x, y, z,
flight_state]), written into the run directory.

report.json holds: the launch settings, per robot (`robots`, by robot id, in
launch order) its mission's final status, the timeline of its behavior
activations and terminations (the coordinator's event stream), its
trajectory's summary and planned path, and what its application behaviors
left in belief memory (QR markers found, the other robots' positions, the
saved map and the fraction of the world's free space it covers); per
behavior the paper's columns a, t1, t2, t3 (from each behavior system's
/metrics, labelled with the robot); memory and CPU per process (/proc), and
how many times the launcher restarted it. The first robot's mission,
timeline and trajectory are also at the top level (`mission`, `timeline`,
`trajectory`), as in a single-robot report; `timeline_png` names the
behavior activity chart of every robot.
"""

import json
import math
import os

import plot
from demo import duration_s, short_cause, timestamp_s


def _timeline(behavior_events, t0=None):
    """Activations, terminations, pauses of the behavior events, with
    simulated time relative to `t0` (default: the first event's)."""
    rows = []
    for e in behavior_events:
        kind = next((k for k in ("activated", "finished", "paused", "resumed", "modified",
                                 "situation_changed") if k in e), None)
        if kind is None:
            continue
        t = timestamp_s(e.get("time"))
        if t is not None and t0 is None:
            t0 = t
        row = {"t_s": None if t is None or t0 is None else round(t - t0, 3),
               "sim_time_s": t, "system": e.get("system", ""), "behavior": e.get("behavior", ""),
               "event": kind, "activation_id": e.get("activation_id", "")}
        if kind == "finished":
            f = e["finished"]
            row["cause"] = short_cause(f.get("cause"))
            row["message"] = f.get("message", "")
            row["active_s"] = duration_s(f.get("active_duration"))
        elif kind == "activated":
            row["parameters"] = e["activated"].get("parameters", {})
        rows.append(row)
    return rows


def _first_event_time(behavior_events):
    for e in behavior_events:
        t = timestamp_s(e.get("time"))
        if t is not None:
            return t
    return None


def _follow_path(record, timeline, samples):
    """The waypoints of a FOLLOW_PATH step record, from where the vehicle
    was when it was activated."""
    points = [(p.get("x", 0.0), p.get("y", 0.0), p.get("z", 0.0))
              for p in record.get("parameters", {}).get("path_m", [])]
    activation = record.get("activation_id", "")
    start = next((r["sim_time_s"] for r in timeline
                  if r["activation_id"] == activation and r["event"] == "activated"), None)
    if start is not None and samples:
        first = min(samples, key=lambda s: abs(s[0] - start))
        points.insert(0, (first[1], first[2], first[3]))
    return points


def _planned_path(mission, timeline, samples):
    """The first FOLLOW_PATH step's waypoints (from where the vehicle was
    when the path was activated), and that activation's id."""
    for record in mission.get("steps", []):
        if record.get("behavior") == "FOLLOW_PATH":
            return _follow_path(record, timeline, samples), record.get("activation_id", "")
    return [], ""


def _planned_legs(mission, timeline, samples):
    """Every FOLLOW_PATH step's waypoints (the first attempt of each step),
    for the plot."""
    legs, seen = [], set()
    for record in mission.get("steps", []):
        name = record.get("name", "")
        if record.get("behavior") != "FOLLOW_PATH" or name in seen:
            continue
        seen.add(name)
        legs.append(_follow_path(record, timeline, samples))
    return legs


def _cross_track_errors(samples, path, timeline, activation):
    """The horizontal distances to the planned polyline while the path was
    followed (ground truth); None when that time is unknown (e.g. the
    coordinator's finished event for a system that died has none)."""
    times = {r["event"]: r["sim_time_s"] for r in timeline if r["activation_id"] == activation}
    if len(path) < 2 or times.get("activated") is None or times.get("finished") is None:
        return None

    def distance(px, py):
        best = math.inf
        for (ax, ay, _), (bx, by, _) in zip(path, path[1:]):
            dx, dy = bx - ax, by - ay
            length2 = dx * dx + dy * dy
            t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((px - ax) * dx + (py - ay) * dy)
                                                      / length2))
            best = min(best, math.hypot(px - ax - t * dx, py - ay - t * dy))
        return best

    return [distance(s[1], s[2]) for s in samples
            if times["activated"] <= s[0] <= times["finished"]]


def _error_summary(errors):
    if not errors:
        return None
    return {"rms_m": math.sqrt(sum(e * e for e in errors) / len(errors)),
            "max_m": max(errors), "samples": len(errors)}


def _cross_track(samples, path, timeline, activation):
    """RMS and maximum horizontal cross-track error of one FOLLOW_PATH
    activation (ground truth), or None."""
    return _error_summary(_cross_track_errors(samples, path, timeline, activation))


def _cross_track_every_path(mission, timeline, samples):
    """The same over every FOLLOW_PATH activation of the mission (each
    attempt of each step), pooled; None without one."""
    errors = []
    for record in mission.get("steps", []):
        if record.get("behavior") == "FOLLOW_PATH":
            errors += _cross_track_errors(samples, _follow_path(record, timeline, samples),
                                          timeline, record.get("activation_id", "")) or []
    return _error_summary(errors)


def _position_at(samples, t):
    """The ground-truth position nearest in time to `t`, and how far in
    time it is; None without samples."""
    if not samples or t is None:
        return None
    s = min(samples, key=lambda s: abs(s[0] - t))
    return [s[1], s[2], s[3]], abs(s[0] - t)


def _track_summary(track, samples):
    """Every position of another robot recorded in belief memory, against
    that robot's ground truth at each one's stamp."""
    stamps = [p[0] for p in track if p[0] is not None]
    errors = []
    for stamp, x, y, z in track:
        truth = _position_at(samples, stamp)
        if truth is not None:
            errors.append(math.dist(truth[0], (x, y, z)))
    return {"updates": len(track), "first_stamp_s": min(stamps, default=None),
            "last_stamp_s": max(stamps, default=None),
            "max_altitude_m": max((p[3] for p in track), default=None),
            "max_error_m": max(errors, default=None),
            "rms_error_m": math.sqrt(sum(e * e for e in errors) / len(errors)) if errors
            else None}


def _fmt(value, digits):
    return "-" if value is None else f"{value:.{digits}f}"


def _xyz(p):
    return "-" if p is None else f"({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f})"


def _state(mission):
    return mission.get("state", "MISSION_STATE_UNSPECIFIED").replace("MISSION_STATE_", "")


def _trajectory(samples, mission, timeline):
    planned, follow_activation = _planned_path(mission, timeline, samples)
    distance = sum(math.dist(a[1:4], b[1:4]) for a, b in zip(samples, samples[1:]))
    return {
        "png": "trajectory.png",
        "samples": len(samples),
        "sim_duration_s": samples[-1][0] - samples[0][0] if samples else 0.0,
        "distance_flown_m": distance,
        "max_altitude_m": max((s[3] for s in samples), default=0.0),
        "planned_path_m": [list(p) for p in planned],
        "follow_path_cross_track": _cross_track(samples, planned, timeline, follow_activation),
        "every_follow_path_cross_track": _cross_track_every_path(mission, timeline, samples),
    }


def _findings(robot, findings, world_markers, samples_by_robot):
    """The robot's belief-memory findings, with the markers compared with
    the world file's and the other robots' positions with their ground
    truth at the belief's stamp."""
    out = {}
    if "markers" in findings:
        markers = []
        for m in findings["markers"]:
            row = dict(m)
            truth = world_markers.get(m.get("text"))
            if truth is not None:
                row["world_center_m"] = truth
                row["error_m"] = (math.dist(truth, m["position_m"])
                                  if m.get("position_m") else None)
            markers.append(row)
        out["markers"] = markers
        out["marker_count"] = findings.get("marker_count", len(markers))
        if world_markers:
            found = {m.get("text") for m in markers}
            out["world_markers_not_found"] = sorted(t for t in world_markers if t not in found)
    if "swarm" in findings:
        swarm = json.loads(json.dumps(findings["swarm"]))  # a copy
        tracks = findings.get("swarm_tracks", {})
        for other, position in swarm.get("positions", {}).items():
            truth = _position_at(samples_by_robot.get(other), position.get("stamp_s"))
            if truth is not None and position.get("position_m"):
                position["ground_truth_m"] = truth[0]
                position["ground_truth_dt_s"] = truth[1]
                position["error_m"] = math.dist(truth[0], position["position_m"])
            if tracks.get(other):
                position["track"] = _track_summary(tracks[other], samples_by_robot.get(other))
        out["swarm"] = swarm
    if "map_file" in findings:
        out["map_file"] = findings["map_file"]
    if "map_coverage" in findings:
        out["map_coverage"] = findings["map_coverage"]
    return out


# --- markdown ------------------------------------------------------------------

# Within one position, a step's attempts (and their calls, iterations and
# branches) come before its fallback.
_NODE_WORDS = ("steps", "attempt", "call", "iteration", "branch", "fallback")


def _node_parts(record):
    """A step record's node split at "/" ("steps/2/attempt/1/call/steps/0");
    from its path (steps, then fallback lists) when it has no node."""
    if record.get("node"):
        return record["node"].split("/")
    path = [str(i) for i in record.get("path", [])]
    return (["steps", path[0]] + [p for i in path[1:] for p in ("fallback", i)]) if path else []


def _node_key(record):
    """Orders records depth-first in mission order: the node part by part
    (numbers as numbers), then the record's attempt, so that a call's attempt 1
    and its steps come before its attempt 2, and a parallel step's branches
    one after the other."""
    key = []
    for part in _node_parts(record) + ["attempt", str(record.get("attempt", 0) or 0)]:
        if part.isdigit():
            key.append((1, int(part)))
        else:
            key.append((0, _NODE_WORDS.index(part) if part in _NODE_WORDS else len(_NODE_WORDS)))
    return key


def _node_depth(parts):
    """0 for the mission's own steps, 1 inside a call, a loop's iteration, a
    parallel step's branch or a fallback, and so on."""
    return max(0, sum(1 for p in parts if p in ("steps", "fallback")) - 1)


def _node_group(parts, robot):
    """The innermost group a record is in: "fallback", "iteration i",
    "branch b (robot)" (with ", attempt a" from the second attempt of the
    step that holds it), "call" (only from its second attempt); "" at the
    top."""
    for i in range(len(parts) - 1, -1, -1):
        if parts[i] == "fallback":
            return "fallback"
        if parts[i] == "attempt" and i + 2 < len(parts):
            kind = parts[i + 2]
            label = kind if kind == "call" else f"{kind} {parts[i + 3]}"
            if kind == "branch" and robot:
                label += f" ({robot})"
            if parts[i + 1] != "1":
                label += f", attempt {parts[i + 1]}"
            return "" if label == "call" else label
    return ""


def _record_what(record):
    """What a step record runs: its behavior, "call NAME", its loop ("repeat
    3 times"), "parallel, all of 2 branches" or "wait for ..."."""
    if record.get("behavior"):
        return record["behavior"]
    if record.get("call"):
        return f"call {record['call']}"
    if record.get("loop"):
        return record["loop"]
    if record.get("parallel"):
        return f"parallel, {record['parallel']}"
    if record.get("wait_for"):
        return f"wait for {record['wait_for']}"
    return ""


def mission_tree(mission):
    """The mission's step records as a tree: (record, depth, label) in
    depth-first mission order (records are stored in the order they were
    created, which interleaves parallel branches); the label is the step's
    name (or "step <n>"), after the group it is in (iteration, branch,
    fallback) when it is not at the top."""
    rows = sorted(((_node_key(r), i, r) for i, r in enumerate(mission.get("steps", []))),
                  key=lambda row: (row[0], row[1]))
    tree = []
    for _, _, record in rows:
        parts = _node_parts(record)
        name = record.get("name") or (f"step {parts[-1]}" if parts else "step")
        group = _node_group(parts, record.get("robot_id", ""))
        tree.append((record, _node_depth(parts), f"{group} · {name}" if group else name))
    return tree


def _cell(text):
    """Text for a markdown table's cell."""
    return str(text).replace("|", "\\|").replace("\n", " ")


def _steps_md(mission, h):
    """The mission's step records as a tree (mission_tree): each step
    indented by its depth, with its node; the robot of each for a fleet
    mission."""
    fleet = len(mission.get("robot_ids", [])) > 1
    lines = ["", f"{h} Mission steps", "",
             "Depth-first in mission order; a call's, a loop iteration's, a parallel branch's "
             "and a fallback's steps indented (↳) under the step that runs them.", "",
             "| step | behavior | node | " + ("robot | " if fleet else "")
             + "attempt | state | cause | message |",
             "|---|---|---|" + ("---|" if fleet else "") + "---|---|---|---|"]
    for r, depth, label in mission_tree(mission):
        indent = "\u00a0\u00a0\u00a0\u00a0" * (depth - 1) + "↳ " if depth else ""
        robot = f"{r.get('robot_id', '')} | " if fleet else ""
        lines.append(f"| {indent}{_cell(label)} | {_cell(_record_what(r))} | "
                     f"{'/'.join(_node_parts(r))} | {robot}{r.get('attempt', 1)} | "
                     f"{r.get('state', '').replace('MISSION_STEP_STATE_', '')} | "
                     f"{short_cause(r.get('cause'))} | {_cell(r.get('message', ''))} |")
    return lines


def _timeline_md(timeline, h):
    lines = ["", f"{h} Timeline (the coordinator's event stream; simulated time)", "",
             "| t (s) | behavior | system | event | cause | active (s) | message |",
             "|---:|---|---|---|---|---:|---|"]
    for r in timeline:
        lines.append(f"| {_fmt(r['t_s'], 2)} | {r['behavior']} | {r['system']} | {r['event']} | "
                     f"{r.get('cause', '')} | {_fmt(r.get('active_s'), 2)} | "
                     f"{r.get('message', '')} |")
    return lines


def _behaviors_md(used, h):
    lines = ["", f"{h} Behaviors (the paper's columns, from each system's /metrics)", "",
             "a: activations; t1: mean time of the four monitoring functions per tick, on the "
             "thread's CPU clock (what they cost) and in wall time (with any preemption); "
             "t2: accumulated monitoring time (wall); t3: mean time from Activate to the first "
             "onExecute, and of it the activate call (checkSituation, onActivate).", "",
             "| behavior | system | a | t1 CPU (us) | t1 wall (us) | t2 (ms) | t3 (ms) "
             "| t3 call (ms) | ticks | terminations |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for b in used:
        causes = ", ".join(f"{c} {n}" for c, n in sorted(b["terminations"].items()))
        lines.append(f"| {b['behavior']} | {b['system']} | {b['a']} | "
                     f"{_fmt(b.get('t1_cpu_us'), 2)} | {_fmt(b['t1_us'], 2)} | "
                     f"{_fmt(b['t2_ms'], 3)} | {_fmt(b['t3_ms'], 3)} | "
                     f"{_fmt(b.get('t3_call_ms'), 3)} | "
                     f"{b.get('monitoring_ticks', 0)} | {causes} |")
    return lines


def _processes_md(processes, h):
    lines = ["", f"{h} Processes (/proc at the end of the mission)", "",
             "| process | pid | RSS (MiB) | peak RSS (MiB) | CPU user (s) | CPU system (s) | "
             "threads | exit code | restarts |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for p in processes:
        def mib(key):
            return _fmt(p[key] / 1024, 1) if key in p else "-"
        lines.append(f"| {p['name']} | {p['pid']} | {mib('rss_kib')} | {mib('peak_rss_kib')} | "
                     f"{_fmt(p.get('cpu_user_s'), 2)} | {_fmt(p.get('cpu_system_s'), 2)} | "
                     f"{p.get('threads', '-')} | {p.get('exit_code', '-')} | "
                     f"{p.get('restarts', 0)} |")
    return lines


def _trajectory_bullets(trajectory):
    lines = [f"- {trajectory['samples']} samples over {trajectory['sim_duration_s']:.1f} s of "
             f"simulated time; {trajectory['distance_flown_m']:.1f} m flown; highest altitude "
             f"{trajectory['max_altitude_m']:.2f} m"]
    ct = trajectory["follow_path_cross_track"]
    if ct:
        lines.append(f"- FOLLOW_PATH horizontal cross-track error: RMS {ct['rms_m']:.3f} m, "
                     f"max {ct['max_m']:.3f} m ({ct['samples']} samples)")
    every = trajectory.get("every_follow_path_cross_track")
    if every and every["samples"] != (ct or {}).get("samples"):
        lines.append(f"- over every FOLLOW_PATH: RMS {every['rms_m']:.3f} m, "
                     f"max {every['max_m']:.3f} m ({every['samples']} samples)")
    return lines


def _findings_md(robot, found, h):
    """The sections of what the application behaviors left in belief
    memory; none when they left nothing."""
    lines = []
    if "markers" in found:
        lines += ["", f"{h} QR markers found (belief memory `{robot}/markers`)", ""]
        if found["markers"]:
            lines += ["| text | position (m) | sightings | side (m) | world file's centre (m) | "
                      "distance (m) |", "|---|---|---:|---:|---|---:|"]
            for m in found["markers"]:
                lines.append(f"| {m.get('text', '')} | {_xyz(m.get('position_m'))} | "
                             f"{m.get('sightings', '-')} | {_fmt(m.get('marker_size_m'), 2)} | "
                             f"{_xyz(m.get('world_center_m'))} | {_fmt(m.get('error_m'), 3)} |")
        else:
            lines.append("No marker found.")
        missing = found.get("world_markers_not_found")
        if missing:
            lines += ["", "Markers of the world file not found: "
                      + ", ".join(f"`{t}`" for t in missing) + "."]
    if "swarm" in found:
        swarm = found["swarm"]
        lines += ["", f"{h} Swarm (belief memory `{robot}/swarm/`)", ""]
        positions = swarm.get("positions", {})
        if positions:
            lines += ["| other robot | believed position (m) | stamp (s, sim) | ground truth then "
                      "(m) | distance (m) |", "|---|---|---:|---|---:|"]
            for other, p in sorted(positions.items()):
                lines.append(f"| {other} | {_xyz(p.get('position_m'))} | "
                             f"{_fmt(p.get('stamp_s'), 2)} | {_xyz(p.get('ground_truth_m'))} | "
                             f"{_fmt(p.get('error_m'), 3)} |")
            for other, p in sorted(positions.items()):
                t = p.get("track")
                if t:
                    lines.append("")
                    lines.append(f"- {other}: {t['updates']} positions written from t = "
                                 f"{_fmt(t['first_stamp_s'], 1)} s to "
                                 f"{_fmt(t['last_stamp_s'], 1)} s (highest "
                                 f"{_fmt(t['max_altitude_m'], 2)} m); distance to {other}'s "
                                 f"ground truth at their stamps: RMS {_fmt(t['rms_error_m'], 3)} "
                                 f"m, max {_fmt(t['max_error_m'], 3)} m")
        else:
            lines.append("No other robot's position.")
        lines += ["", f"- messages received: {swarm.get('message_count', 0)}; malformed samples "
                  f"skipped: {swarm.get('malformed_count', 0)}"]
        for m in swarm.get("messages", []):
            lines.append(f"- message {m.get('n')} from `{m.get('from', '')}`: "
                         f"{m.get('text', '')} {json.dumps(m.get('payload'))}")
    if "map_file" in found or "map_coverage" in found:
        lines += ["", f"{h} Map (belief memory `{robot}/map_file`)", "",
                  f"- map file: `{found.get('map_file', '-')}`"]
        coverage = found.get("map_coverage") or {}
        if "mapped_fraction" in coverage:
            lines.append(f"- Mapped fraction of the building's free space: "
                         f"{coverage['mapped_fraction'] * 100:.0f} %")
            lines.append(f"- free cells of the world: {coverage.get('free_cells', '-')}; known "
                         f"free in the map: {coverage.get('known_free_cells', '-')} "
                         f"(`map_coverage`)")
            if "wall_error_mean_m" in coverage:
                lines.append(f"- Wall error of the map: {coverage['wall_error_mean_m']:.3f} m "
                             f"on average, at most {coverage.get('wall_error_max_m', 0):.3f} m "
                             f"({coverage.get('occupied_voxels', '-')} occupied voxels at the "
                             f"scan height, against the world file's surfaces)")
        else:
            lines.append(f"- mapped fraction not measured: "
                         f"{coverage.get('error', 'no measurement')}")
    return lines


def _robot_json(r, world_markers, samples_by_robot):
    mission = r.get("mission") or {}
    timeline = r["timeline"]
    entry = {"robot_id": r["robot_id"], "mission_file": r.get("mission_file", ""),
             "mission": mission, "timeline": timeline,
             "trajectory": _trajectory(r.get("samples", []), mission, timeline)}
    entry.update(_findings(r["robot_id"], r.get("findings", {}), world_markers,
                           samples_by_robot))
    return entry


def _rectangle(cx, cy, along, across, ux, uy):
    """The corners of a rectangle centred on (cx, cy), `along` long in the
    unit direction (ux, uy) and `across` wide."""
    ax_, ay_ = ux * along / 2, uy * along / 2
    nx, ny = -uy * across / 2, ux * across / 2
    return [(cx - ax_ - nx, cy - ay_ - ny), (cx + ax_ - nx, cy + ay_ - ny),
            (cx + ax_ + nx, cy + ay_ + ny), (cx - ax_ + nx, cy - ay_ + ny)]


def world_footprints(path):
    """The plan view of a world file (simulator/worlds/README.md): its
    walls as rectangles (thickness_m wide, reaching thickness_m / 2 past
    each end as the loader builds them, the doors' openings left out) and
    its boxes' outlines (yawed); None when there is no world file or it
    cannot be read. `path` is the world's YAML file, as the launcher resolves
    --world ("" for the default empty field)."""
    if not path:
        return None
    try:
        import yaml  # Debian's python3-yaml
        with open(path) as f:
            data = yaml.safe_load(f) or {}
        walls = []
        for wall in data.get("walls") or []:
            (x0, y0) = [float(v) for v in wall["from_m"]]
            (x1, y1) = [float(v) for v in wall["to_m"]]
            thickness = float(wall.get("thickness_m", 0.2))
            length = math.hypot(x1 - x0, y1 - y0)
            if length <= 0:
                continue
            ux, uy = (x1 - x0) / length, (y1 - y0) / length
            # Along the wall (0 at from_m), the spans between its doors.
            gaps = sorted((float(d["offset_m"]) - float(d["width_m"]) / 2,
                           float(d["offset_m"]) + float(d["width_m"]) / 2)
                          for d in wall.get("doors") or [])
            start = -thickness / 2
            for lo, hi in gaps + [(length + thickness / 2, length + thickness / 2)]:
                if lo > start:
                    middle = (start + lo) / 2
                    walls.append(_rectangle(x0 + ux * middle, y0 + uy * middle, lo - start,
                                            thickness, ux, uy))
                start = max(start, hi)
        boxes = []
        for box in data.get("boxes") or []:
            cx, cy = float(box["center_m"][0]), float(box["center_m"][1])
            sx, sy = float(box["size_m"][0]), float(box["size_m"][1])
            yaw = float(box.get("yaw_rad", 0.0))
            boxes.append(_rectangle(cx, cy, sx, sy, math.cos(yaw), math.sin(yaw)))
        return {"walls": walls, "boxes": boxes}
    except (ImportError, OSError, ValueError, TypeError, KeyError, IndexError,
            AttributeError):
        return None


def _activations(robots, several):
    """Every robot's behavior activations from its timeline, for the
    timeline plot: behavior (the robot's id first when there are several),
    start_s, end_s (None while active), cause (None while active), paused
    intervals, group (the robot's index); simulated time from the first
    event of all. Also the latest time known (events and ground truth
    samples), where the active ones end."""
    times = [row["sim_time_s"] for r in robots for row in r["timeline"]
             if row["sim_time_s"] is not None]
    if not times:
        return [], None
    origin = min(times)
    latest = max(times + [s[0] for r in robots for s in r.get("samples", [])[-1:]])
    activations = []
    for index, r in enumerate(robots):
        by_id = {}
        for row in r["timeline"]:
            if not row["behavior"]:
                continue
            key = row["activation_id"] or f"{row['system']}/{row['behavior']}"
            t = None if row["sim_time_s"] is None else row["sim_time_s"] - origin
            a = by_id.get(key)
            if a is None or row["event"] == "activated":
                a = {"behavior": (f"{r['robot_id']} " if several else "") + row["behavior"],
                     "start_s": t if row["event"] == "activated" else None, "end_s": None,
                     "cause": None, "paused": [], "group": index}
                by_id[key] = a
                activations.append(a)
            if row["event"] == "finished":
                a["end_s"] = t
                a["cause"] = row.get("cause") or "UNSPECIFIED"
            elif row["event"] == "paused":
                a["paused"].append([t, None])
            elif row["event"] == "resumed" and a["paused"] and a["paused"][-1][1] is None:
                a["paused"][-1][1] = t
    for a in activations:
        if a["start_s"] is None:  # activated before the event stream started
            a["start_s"] = 0.0
        for p in a["paused"]:
            if p[1] is None and a["end_s"] is not None:
                p[1] = a["end_s"]
    return activations, latest - origin


def _map_cells(robots):
    """The occupied cells of the first map saved (map_coverage --cells), as
    (x, y) centres and their width; ([], 0.1) without one."""
    for r in robots:
        path = (r.get("findings") or {}).get("map_cells_file")
        if not path:
            continue
        try:
            with open(path) as f:
                data = json.load(f)
            return [tuple(c) for c in data.get("occupied_xy_m", [])], float(data.get("cell_m", 0.1))
        except (OSError, ValueError, TypeError, AttributeError):
            continue
    return [], 0.1


def write(run_dir, settings, robots, behaviors, processes, clean_exit, world_markers=None,
          world_walls=None):
    """Writes report.json, report.md, trajectory.png and timeline.png;
    returns the report dict.

    robots: one dict per robot, in launch order: robot_id, mission_file
    (relative path, or "" without a mission), mission (its final
    MissionStatus dict, or {}), behavior_events, samples (ground truth:
    (t_sim_s, x, y, z, flight_state)), findings (demo.robot_findings, plus
    map_coverage and map_cells_file). world_markers: marker text -> centre
    [x, y, z] from the world file, to compare the markers found with.
    world_walls: the world's walls as plan-view segments, drawn under the
    trajectories (with the saved map's occupied cells) when the world file
    (settings["world_file"]) cannot be read for its walls' and boxes' outlines."""
    world_markers = world_markers or {}
    several = len(robots) > 1
    # One time origin for every robot's timeline: the first event of all.
    t0 = min((t for t in (_first_event_time(r["behavior_events"]) for r in robots)
              if t is not None), default=None) if several else None
    for r in robots:
        r["timeline"] = _timeline(r["behavior_events"], t0)
    samples_by_robot = {r["robot_id"]: r.get("samples", []) for r in robots}
    entries = {r["robot_id"]: _robot_json(r, world_markers, samples_by_robot) for r in robots}
    first = entries[robots[0]["robot_id"]]

    png = os.path.join(run_dir, "trajectory.png")
    lines_xy = [[(s[1], s[2]) for s in r.get("samples", [])] for r in robots]
    planned_xy = []
    for r in robots:
        for leg in _planned_legs(r.get("mission") or {}, r["timeline"], r.get("samples", [])):
            planned_xy.append([(p[0], p[1]) for p in leg])
    colors = plot.vehicle_colors(len(robots))
    cells, cell_m = _map_cells(robots)
    footprints = world_footprints(settings.get("world_file", ""))
    walls = footprints["walls"] if footprints else world_walls or []
    boxes = footprints["boxes"] if footprints else []
    plot.plot_trajectories(png, lines_xy, planned_xy,
                           labels=[r["robot_id"] for r in robots] if several else None,
                           walls=walls, obstacles=boxes, cells=cells, cell_m=cell_m)
    activations, latest_s = _activations(robots, several)
    plot.plot_timeline(os.path.join(run_dir, "timeline.png"), activations, end_s=latest_s)

    used = [b for b in behaviors if b.get("a")]
    report = {"settings": settings, "mission": first["mission"], "timeline": first["timeline"],
              "behaviors": used, "processes": processes, "trajectory": first["trajectory"],
              "timeline_png": "timeline.png", "robots": entries, "clean_shutdown": clean_exit}
    with open(os.path.join(run_dir, "report.json"), "w") as f:
        json.dump(report, f, indent=2)
        f.write("\n")
    # The ground truth itself, to compare runs (tests/bench/stack/determinism_check.py).
    with open(os.path.join(run_dir, "trajectory.json"), "w") as f:
        json.dump({r["robot_id"]: [list(s) for s in r.get("samples", [])] for r in robots}, f)
        f.write("\n")

    shutdown = (f"- wall time {settings.get('wall_s', 0):.1f} s; every process shut down "
                f"{'cleanly' if clean_exit else 'NOT cleanly (see processes)'}")
    scale = settings.get("time_scale")
    scale_text = ("deterministic (time scale max)" if scale == "max"
                  else f"time scale {scale}x")
    world = (f"- simulator {scale_text}, world "
             f"`{settings.get('world') or 'empty field'}`, seed {settings.get('seed')}")
    if settings.get("sensor_config"):
        world += f", sensor config `{settings['sensor_config']}`"
    interrupted = ([f"- the launcher was stopped by {settings['interrupted']} before the "
                    f"mission ended"] if settings.get("interrupted") else [])
    image = ["", f"![x-y trajectory]({first['trajectory']['png']})", ""]
    activity = ["", "## Behavior activity", "", "![behavior activity](timeline.png)", "",
                "One row per behavior" + (" and robot" if several else "")
                + ", in the order of their first activation; one bar per activation, from "
                "its activation to its termination (simulated time from the first event), "
                "coloured by the termination cause: green GOAL_ACHIEVED, orange TIME_OUT, "
                "purple WRONG_PROGRESS, cyan SITUATION_CHANGE, red PROCESS_FAILURE, grey "
                "INTERRUPTED, blue still active; hatched while paused."]
    # What the trajectory plot drew under the paths.
    world_key = "".join(f"; {text}" for text, drawn in (
        ("filled grey: the world's walls", walls),
        ("light grey: the world's boxes (plan view)", boxes),
        ("dark grey: the saved map's occupied cells", cells)) if drawn)
    footer = ["", "Logs of every process: `logs/`; Prometheus targets: "
              "`prometheus_targets.json`."
              + (f" The run's console was {settings['console_url']} (while the stack ran)."
                 if settings.get("console_url") else "")
              + (f" The flight recording is `{settings['recording']}` (MCAP: `behaviorctl replay`,"
                 " the console's Recording view, Foxglove)." if settings.get("recording") else ""),
              ""]
    if settings.get("console_screenshot"):
        footer += ["The console at the end of the run:", "",
                   f"![the operator's console]({settings['console_screenshot']})", ""]

    if not several:
        r, entry = robots[0], first
        mission = entry["mission"]
        lines = [f"# Mission report: {mission.get('name', '?')} ({_state(mission)})", ""]
        lines.append(f"- mission file: `{settings.get('mission', '')}`, robot "
                     f"`{mission.get('robot_id', '')}`, id `{mission.get('mission_id', '')}`")
        lines += [world, shutdown]
        if mission.get("message"):
            lines.append(f"- {mission['message']}")
        lines += interrupted
        lines += _steps_md(mission, "##")
        lines += _timeline_md(entry["timeline"], "##")
        lines += _behaviors_md(used, "##")
        lines += _processes_md(processes, "##")
        lines += activity
        lines += ["", "## Trajectory (simulator ground truth)"] + image
        lines += [f"Blue: flown (green dot: start, red: end); grey dashed: the planned "
                  f"path{world_key}. World frame ENU, metres.", ""]
        lines += _trajectory_bullets(entry["trajectory"])
        lines += _findings_md(r["robot_id"], entry, "##")
    else:
        title = ", ".join(
            f"{r['robot_id']} {(r.get('mission') or {}).get('name', '(no mission)')}"
            + (f" ({_state(r['mission'])})" if r.get("mission") else "") for r in robots)
        lines = [f"# Mission report: {title}", ""]
        lines.append("- robots " + ", ".join(f"`{r['robot_id']}`" for r in robots)
                     + "; mission files: "
                     + ", ".join(f"{r['robot_id']} `{r.get('mission_file') or '-'}`"
                                 for r in robots))
        lines += [world, shutdown] + interrupted
        for r in robots:
            entry = entries[r["robot_id"]]
            mission = entry["mission"]
            if mission:
                lines += ["", f"## {r['robot_id']}: {mission.get('name', '?')} "
                          f"({_state(mission)})", "",
                          f"- mission file: `{entry['mission_file']}`, id "
                          f"`{mission.get('mission_id', '')}`"]
                if mission.get("message"):
                    lines.append(f"- {mission['message']}")
                lines += _steps_md(mission, "###")
            else:
                lines += ["", f"## {r['robot_id']}: no mission"]
            lines += _timeline_md(entry["timeline"], "###")
            lines += _behaviors_md([b for b in used if b.get("robot") == r["robot_id"]], "###")
            lines += ["", "### Trajectory (simulator ground truth)", ""]
            lines += _trajectory_bullets(entry["trajectory"])
            lines += _findings_md(r["robot_id"], entry, "###")
        lines += _processes_md(processes, "##")
        lines += activity
        lines += ["", "## Trajectories (simulator ground truth)"] + image
        legend = ", ".join(f"{r['robot_id']} {plot.color_name(c)}"
                           for r, c in zip(robots, colors))
        lines += [f"Flown: {legend} (green dot: start, red: end); grey dashed: the planned "
                  f"paths{world_key}. World frame ENU, metres.", ""]
    lines += footer
    with open(os.path.join(run_dir, "report.md"), "w") as f:
        f.write("\n".join(lines))
    return report
