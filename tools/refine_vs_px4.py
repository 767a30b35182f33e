#!/usr/bin/env python3
"""Are the bundle adjustment's per-frame attitude corrections PX4's attitude error?

    python tools/refine_vs_px4.py RECORDING PX4_ULG ATTITUDE_CSV

RECORDING: a flight recorded by `daemon.record` during `make sitl`; PX4_ULG: that flight's
`px4.ulg` (the harness copies it beside the report); ATTITUDE_CSV: `attitude.csv` of
`mavloc area --trace --set area.attitude_prior_deg=... --dataset RECORDING`.

Each record's `autopilot_time` is PX4's clock, the log's; a recording without it (before
session 32) is joined by the vehicle yaw both hold (the offset with the smallest mean
difference, on a 20 ms grid). PX4's error is its
attitude estimate against SIH's truth, as a small rotation in NED (estimate = exp(e)
truth); a correction d turns the recorded attitude by exp(d), so a perfect one is d = -e.
Prints, about north, east and down: both means and SDs, their correlation over the
corrected frames, and the SD of what is left (-e - d)."""
import csv
import json
import sys

import numpy as np
from pyulog import ULog


def rotations(m, ts):
    """Body -> NED rotation matrices of a ULog attitude topic at times `ts` (s)."""
    q = [np.interp(ts, m["timestamp"] / 1e6, m[f"q[{i}]"]) for i in range(4)]
    n = np.sqrt(sum(v * v for v in q))
    w, x, y, z = (v / n for v in q)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def main(rec, ulg, att):
    records = [json.loads(line) for line in open(f"{rec}/telemetry.jsonl") if line.endswith("\n")]
    t = np.array([r["t"] for r in records])
    yaw_rec = np.unwrap(np.radians([r["measured"]["attitude_deg"][2] for r in records]))
    u = ULog(ulg, ["vehicle_attitude", "vehicle_attitude_groundtruth"])
    d = {x.name: x.data for x in u.data_list}
    a, g = d["vehicle_attitude"], d["vehicle_attitude_groundtruth"]
    ta = a["timestamp"] / 1e6
    yaw_px4 = np.unwrap(np.arctan2(2 * (a["q[0]"] * a["q[3]"] + a["q[1]"] * a["q[2]"]),
                                   1 - 2 * (a["q[2]"] ** 2 + a["q[3]"] ** 2)))
    best = None
    for tau in np.arange(ta[0], ta[-1] - t[-1], 0.02):
        e = np.interp(t + tau, ta, yaw_px4) - yaw_rec
        e -= np.round(np.median(e) / (2 * np.pi)) * 2 * np.pi
        cost = float(np.mean(np.abs(e)))
        if best is None or cost < best[0]:
            best = (cost, tau)
    print(f"by the yaw: PX4 time = recording time + {best[1]:.2f} s (yaw {np.degrees(best[0]):.2f} deg apart on average)")
    ts = t + best[1]
    if all(r.get("autopilot_time") is not None for r in records):
        # Recordings since session 32 carry PX4's own clock (the log's), which needs no guess.
        ts = np.array([r["autopilot_time"] for r in records])
        print(f"joined by autopilot_time (recording time + {np.median(ts - t):.2f} s)")
    E = np.einsum("nij,nkj->nik", rotations(a, ts), rotations(g, ts))
    err = np.degrees(np.stack([(E[:, 2, 1] - E[:, 1, 2]) / 2, (E[:, 0, 2] - E[:, 2, 0]) / 2,
                               (E[:, 1, 0] - E[:, 0, 1]) / 2], -1))
    rows = {int(r["frame"]): [float(r[f"about_{n}_deg"]) for n in ("north", "east", "down")]
            for r in csv.DictReader(open(att))}
    idx = [i for i, r in enumerate(records) if any(rows.get(r["frame"], [0.0]))]
    corr = np.array([rows[records[i]["frame"]] for i in idx])
    want = -err[idx]
    print(f"{len(idx)} frames corrected")
    for k, n in enumerate(("north", "east", "down")):
        c = np.corrcoef(corr[:, k], want[:, k])[0, 1]
        print(f"about {n}: correction {corr[:, k].mean():+.2f} / {corr[:, k].std():.2f} deg, "
              f"-(PX4's error) {want[:, k].mean():+.2f} / {want[:, k].std():.2f} deg (mean / SD); "
              f"correlation {c:+.2f}; left after it {np.std(want[:, k] - corr[:, k]):.2f} deg SD")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])
