"""The mission report: report.json (everything), report.md (for people) and
trajectory.png, written into the run directory.

report.json holds: the launch settings, the mission's final status, the
timeline of behavior activations and terminations (the coordinator's event
stream), per behavior the paper's columns a, t1, t2, t3 (from each behavior
system's /metrics), memory and CPU per process (/proc), the trajectory's
summary and the planned path.
"""

import json
import math
import os

import plot
from demo import duration_s, short_cause, timestamp_s


def _timeline(behavior_events):
    """Activations, terminations, pauses of the behavior events, with
    simulated time relative to the first one."""
    rows = []
    t0 = None
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


def _planned_path(mission, timeline, samples):
    """The FOLLOW_PATH waypoints of the mission (from where the vehicle was
    when the path was activated), and that activation's id."""
    for record in mission.get("steps", []):
        if record.get("behavior") != "FOLLOW_PATH":
            continue
        points = [(p.get("x", 0.0), p.get("y", 0.0), p.get("z", 0.0))
                  for p in record.get("parameters", {}).get("path_m", [])]
        activation = record.get("activation_id", "")
        start = next((r["sim_time_s"] for r in timeline
                      if r["activation_id"] == activation and r["event"] == "activated"), None)
        if start is not None and samples:
            first = min(samples, key=lambda s: abs(s[0] - start))
            points.insert(0, (first[1], first[2], first[3]))
        return points, activation
    return [], ""


def _cross_track(samples, path, timeline, activation):
    """RMS and maximum horizontal distance to the planned polyline while the
    path was followed (ground truth)."""
    times = {r["event"]: r["sim_time_s"] for r in timeline if r["activation_id"] == activation}
    if len(path) < 2 or "activated" not in times or "finished" not in times:
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

    errors = [distance(s[1], s[2]) for s in samples
              if times["activated"] <= s[0] <= times["finished"]]
    if not errors:
        return None
    return {"rms_m": math.sqrt(sum(e * e for e in errors) / len(errors)),
            "max_m": max(errors), "samples": len(errors)}


def _fmt(value, digits):
    return "-" if value is None else f"{value:.{digits}f}"


def write(run_dir, settings, mission, behavior_events, behaviors, processes, samples, clean_exit):
    """Writes report.json, report.md and trajectory.png; returns the report
    dict."""
    timeline = _timeline(behavior_events)
    planned, follow_activation = _planned_path(mission, timeline, samples)
    png = os.path.join(run_dir, "trajectory.png")
    plot.plot_trajectory(png, [(s[1], s[2]) for s in samples], [(p[0], p[1]) for p in planned])
    distance = sum(math.dist(a[1:4], b[1:4]) for a, b in zip(samples, samples[1:]))
    trajectory = {
        "png": os.path.basename(png),
        "samples": len(samples),
        "sim_duration_s": samples[-1][0] - samples[0][0] if samples else 0.0,
        "distance_flown_m": distance,
        "max_altitude_m": max((s[3] for s in samples), default=0.0),
        "planned_path_m": [list(p) for p in planned],
        "follow_path_cross_track": _cross_track(samples, planned, timeline, follow_activation),
    }
    used = [b for b in behaviors if b.get("a")]
    report = {"settings": settings, "mission": mission, "timeline": timeline,
              "behaviors": used, "processes": processes, "trajectory": trajectory,
              "clean_shutdown": clean_exit}
    with open(os.path.join(run_dir, "report.json"), "w") as f:
        json.dump(report, f, indent=2)
        f.write("\n")

    state = mission.get("state", "MISSION_STATE_UNSPECIFIED").replace("MISSION_STATE_", "")
    lines = [f"# Mission report: {mission.get('name', '?')} ({state})", ""]
    lines.append(f"- mission file: `{settings.get('mission', '')}`, robot "
                 f"`{mission.get('robot_id', '')}`, id `{mission.get('mission_id', '')}`")
    lines.append(f"- simulator time scale {settings.get('time_scale')}x, world "
                 f"`{settings.get('world') or 'empty field'}`, seed {settings.get('seed')}")
    lines.append(f"- wall time {settings.get('wall_s', 0):.1f} s; every process shut down "
                 f"{'cleanly' if clean_exit else 'NOT cleanly (see processes)'}")
    if mission.get("message"):
        lines.append(f"- {mission['message']}")
    if settings.get("interrupted"):
        lines.append(f"- the launcher was stopped by {settings['interrupted']} before the "
                     f"mission ended")
    lines += ["", "## Mission steps", "", "| step | behavior | attempt | state | cause | message |",
              "|---|---|---|---|---|---|"]
    for r in mission.get("steps", []):
        lines.append(f"| {r.get('name', '')} | {r.get('behavior', '')} | {r.get('attempt', 1)} | "
                     f"{r.get('state', '').replace('MISSION_STEP_STATE_', '')} | "
                     f"{short_cause(r.get('cause'))} | {r.get('message', '')} |")
    lines += ["", "## Timeline (the coordinator's event stream; simulated time)", "",
              "| t (s) | behavior | system | event | cause | active (s) | message |",
              "|---:|---|---|---|---|---:|---|"]
    for r in timeline:
        lines.append(f"| {_fmt(r['t_s'], 2)} | {r['behavior']} | {r['system']} | {r['event']} | "
                     f"{r.get('cause', '')} | {_fmt(r.get('active_s'), 2)} | "
                     f"{r.get('message', '')} |")
    lines += ["", "## Behaviors (the paper's columns, from each system's /metrics)", "",
              "a: activations; t1: mean time of the four monitoring functions per tick; "
              "t2: accumulated monitoring time; t3: mean time from Activate to the first "
              "onExecute.", "",
              "| behavior | system | a | t1 (us) | t2 (ms) | t3 (ms) | ticks | terminations |",
              "|---|---|---:|---:|---:|---:|---:|---|"]
    for b in used:
        causes = ", ".join(f"{c} {n}" for c, n in sorted(b["terminations"].items()))
        lines.append(f"| {b['behavior']} | {b['system']} | {b['a']} | {_fmt(b['t1_us'], 2)} | "
                     f"{_fmt(b['t2_ms'], 3)} | {_fmt(b['t3_ms'], 3)} | "
                     f"{b.get('monitoring_ticks', 0)} | {causes} |")
    lines += ["", "## Processes (/proc at the end of the mission)", "",
              "| process | pid | RSS (MiB) | peak RSS (MiB) | CPU user (s) | CPU system (s) | "
              "threads | exit code |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for p in processes:
        def mib(key):
            return _fmt(p[key] / 1024, 1) if key in p else "-"
        lines.append(f"| {p['name']} | {p['pid']} | {mib('rss_kib')} | {mib('peak_rss_kib')} | "
                     f"{_fmt(p.get('cpu_user_s'), 2)} | {_fmt(p.get('cpu_system_s'), 2)} | "
                     f"{p.get('threads', '-')} | {p.get('exit_code', '-')} |")
    lines += ["", "## Trajectory (simulator ground truth)", "",
              f"![x-y trajectory]({trajectory['png']})", "",
              "Blue: flown (green dot: start, red: end); grey dashed: the planned path. World "
              "frame ENU, metres.", "",
              f"- {trajectory['samples']} samples over {trajectory['sim_duration_s']:.1f} s of "
              f"simulated time; {distance:.1f} m flown; highest altitude "
              f"{trajectory['max_altitude_m']:.2f} m"]
    ct = trajectory["follow_path_cross_track"]
    if ct:
        lines.append(f"- FOLLOW_PATH horizontal cross-track error: RMS {ct['rms_m']:.3f} m, "
                     f"max {ct['max_m']:.3f} m ({ct['samples']} samples)")
    lines += ["", "Logs of every process: `logs/`; Prometheus targets: "
              "`prometheus_targets.json`.", ""]
    with open(os.path.join(run_dir, "report.md"), "w") as f:
        f.write("\n".join(lines))
    return report
