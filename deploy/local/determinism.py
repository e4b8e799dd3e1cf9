"""What "the same result" means for two runs of one mission with one seed in
the deterministic mode (--time-scale max): every step ended with the same
termination cause, each step's active time (simulated) agrees within a
tolerance (it is identical in most runs), and the flown paths agree (up to
the first injected fault, in deploy/local/campaign.py: after it the flight
may be chaotic).

The coordinator is outside the simulator's barrier, so when each step
starts can differ by some quanta: the path is compared as a path (the
largest distance from a sample of one run to the other run's track, both
ways), not sample by sample in time. Used by deploy/local/campaign.py
(--check-determinism) and tests/bench/stack/determinism_check.py.
"""

import math

# Step active times agree within this (simulated seconds): five quanta. A step
# that ends by itself lasts the same to a quantum or two; one that ends by
# what happens outside it (a retry started by the coordinator while the
# vehicle falls, ended by the crash) inherits the jitter of its start.
DURATION_TOLERANCE_S = 0.05
# The flown paths agree within this. Within 5 mm in most runs; about one run
# in twenty hovers some seconds longer between two steps and then differs by
# about 10 cm (docs/benchmarks.md), hence the determinism smoke test's 0.25 m.
PATH_TOLERANCE_M = 0.25


def _segment_distance(p, a, b):
    ab = [b[i] - a[i] for i in range(3)]
    ap = [p[i] - a[i] for i in range(3)]
    length2 = sum(c * c for c in ab)
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, sum(ab[i] * ap[i] for i in range(3)) / length2))
    return math.dist(p, [a[i] + ab[i] * t for i in range(3)])


def path_deviation(a, b):
    """The largest distance from a sample of one track to the other track
    (samples (t_s, x, y, z, ...)); inf when one has none."""
    def one_way(points, track):
        worst = 0.0
        for p in points:
            best = min(_segment_distance(p, track[i], track[i + 1])
                       for i in range(len(track) - 1)) if len(track) > 1 else math.dist(p, track[0])
            worst = max(worst, best)
        return worst
    pa = [tuple(s[1:4]) for s in a]
    pb = [tuple(s[1:4]) for s in b]
    if not pa or not pb:
        return float("inf")
    return max(one_way(pa, pb), one_way(pb, pa))


def position_at(samples, t):
    """Linear interpolation of the track at simulated time t (None outside)."""
    for i in range(len(samples) - 1):
        t0, t1 = samples[i][0], samples[i + 1][0]
        if t0 <= t <= t1:
            f = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
            return [samples[i][k] + f * (samples[i + 1][k] - samples[i][k]) for k in (1, 2, 3)]
    return None


def aligned_deviation(a, a_t0, b, b_t0):
    """The largest distance between the two runs' positions at the same
    simulated time since each one's t0 (the first activation)."""
    worst = 0.0
    for s in a:
        other = position_at(b, s[0] - a_t0 + b_t0)
        if other is not None:
            worst = max(worst, math.dist(s[1:4], other))
    return worst


def _same_cause(a, b):
    """Whether two runs' rows of one step ended alike. A recurrent behavior
    ended by the mission (INTERRUPTED) in one run and by itself in the other
    raced the mission's end: after a mission failed, its safety steps (the
    coordinator's, outside the barrier) and the behavior's own monitoring
    (an EKF that sees the crash) both end it, in either order. A recurrent
    behavior that ended the mission itself changes the other steps' causes,
    which are compared strictly."""
    if a["name"] != b["name"]:
        return False
    if a["cause"] == b["cause"]:
        return True
    return (a.get("kind") == "recurrent" and b.get("kind") == "recurrent"
            and "INTERRUPTED" in (a["cause"], b["cause"]))


def compare(a, b, duration_tolerance_s=DURATION_TOLERANCE_S, path_tolerance_m=PATH_TOLERANCE_M):
    """Two runs, each {"steps": [{"name", "cause", "duration_s", "kind"?}...],
    "samples": [(t_s, x, y, z, ...)]}: {"same": bool, "same_causes",
    "duration_diff_s" (the largest), "path_deviation_m", "differences":
    [text]}. The active time of a row of kind "recurrent" (a behavior active
    all mission long, ended by the mission's end) is not compared, nor are
    samples unless both runs have some."""
    differences = []
    causes_a = [(s["name"], s["cause"]) for s in a["steps"]]
    causes_b = [(s["name"], s["cause"]) for s in b["steps"]]
    same_causes = len(causes_a) == len(causes_b) and all(
        _same_cause(sa, sb) for sa, sb in zip(a["steps"], b["steps"]))
    if not same_causes:
        differences.append(f"step causes differ: {causes_a} vs {causes_b}")
    worst = 0.0
    for sa, sb in zip(a["steps"], b["steps"]):
        if sa.get("kind") == "recurrent":
            continue
        da, db = sa.get("duration_s"), sb.get("duration_s")
        if da is None or db is None:
            if (da is None) != (db is None):
                differences.append(f"{sa['name']}: active time {da} vs {db}")
            continue
        worst = max(worst, abs(da - db))
        if abs(da - db) > duration_tolerance_s:
            differences.append(f"{sa['name']}: active {da:.3f} s vs {db:.3f} s")
    path = None
    if a.get("samples") and b.get("samples"):
        path = path_deviation(a["samples"], b["samples"])
        if path > path_tolerance_m:
            differences.append(f"flown paths differ by {path:.3f} m (> {path_tolerance_m} m)")
    return {"same": not differences, "same_causes": same_causes,
            "duration_diff_s": round(worst, 6),
            "path_deviation_m": None if path is None else round(path, 6),
            "differences": differences}
