#!/usr/bin/env python3
"""`make sitl`: mavloc against PX4 SITL (v1.16, SIH, no Gazebo) with the simulated camera.

PX4 is not part of this project: build it yourself, outside it, and give its build folder
(`.../build/px4_sitl_default`) in MAVLOC_PX4_DIR. Without it this says what is missing and
exits 0 (skipped). Everything runs on loopback: as root the harness enters a private
network namespace (only `lo`), since PX4 listens on all interfaces.

Scenario `coastline-mission` (GPS on): PX4 flies the committed mission/coastline.plan
around the lake, its ROI items pointing the gimbal; mavloc runs the area pipeline on
frames rendered from PX4's ground truth (HIL_STATE_QUATERNION). `--aim border`
(`coastline-border`): mavloc points the gimbal at the border it segments. Writes
results/sitl/<scenario>/: report.json, PX4's flight log (.ulg), mavloc's and PX4's logs
and mavloc's state folder.

Usage: sitl.py --px4 DIR --mavloc BIN [--out DIR] [--max-s S] [--aim mission|border]
"""

import argparse
import glob
import json
import os
import shutil
import signal
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def in_private_netns():
    """True when the only interface is lo (/proc/net/dev is per network namespace; /sys
    is not remounted by unshare)."""
    names = [l.split(":")[0].strip() for l in open("/proc/net/dev").read().splitlines()[2:]]
    return names == ["lo"]


def reexec_in_netns():
    if in_private_netns() or os.environ.get("MAVLOC_SITL_NETNS"):
        return
    os.environ["MAVLOC_SITL_NETNS"] = "1"
    if os.geteuid() != 0 or shutil.which("unshare") is None or shutil.which("ip") is None:
        print("sitl: not root (or no unshare/ip): running without a private network namespace; "
              "PX4 listens on all interfaces", file=sys.stderr)
        return
    cmd = " ".join(["ip link set lo up &&", "exec", sys.executable] + [f"'{a}'" for a in sys.argv])
    os.execvp("unshare", ["unshare", "-n", "sh", "-c", cmd])


def read_params(path):
    params = {}
    for line in open(path):
        line = line.split("#", 1)[0].split()
        if len(line) == 2:
            params[line[0]] = line[1]
    return params


def start_px4(px4_dir, params, out):
    rootfs = os.path.join(px4_dir, "rootfs")
    binary = os.path.join(px4_dir, "bin", "px4")
    if not os.access(binary, os.X_OK):
        sys.exit(f"sitl: {binary} is not an executable PX4 build (MAVLOC_PX4_DIR = build/px4_sitl_default)")
    # A cold start: parameters from earlier runs would otherwise persist.
    for f in ("parameters.bson", "parameters_backup.bson", "dataman"):
        try:
            os.remove(os.path.join(rootfs, f))
        except FileNotFoundError:
            pass
    env = dict(os.environ, PX4_SIM_MODEL="sihsim_quadx", PX4_SIMULATOR="sihsim")
    env.update({f"PX4_PARAM_{k}": v for k, v in params.items()})
    log = open(os.path.join(out, "px4.log"), "w")
    started = time.time()
    proc = subprocess.Popen([binary, "-d"], cwd=rootfs, env=env, stdout=log, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL)
    return proc, started


def stop_px4(px4_dir, proc):
    subprocess.run([os.path.join(px4_dir, "bin", "px4-shutdown")], capture_output=True, timeout=10)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=10)


# Mission items that point the gimbal (DO_SET_ROI_LOCATION, DO_SET_ROI_NONE,
# DO_GIMBAL_MANAGER_PITCHYAW): left out when mavloc points it (PX4's navigator would take
# the gimbal back at each one).
GIMBAL_ITEMS = {195, 197, 1000}


def upload_plan(m, plan_path, keep_gimbal_items=True):
    """QGC .plan items -> MISSION_ITEM_INT, by the mission protocol."""
    items = json.load(open(plan_path))["mission"]["items"]
    if not keep_gimbal_items:
        items = [it for it in items if it["command"] not in GIMBAL_ITEMS]
    msgs = []
    for seq, it in enumerate(items):
        p = [0 if v is None else v for v in it["params"]]
        frame = it.get("frame", 3)
        msgs.append((seq, frame, it["command"], p))
    m.mav.mission_count_send(1, 1, len(msgs), 0)
    deadline = time.time() + 30
    while time.time() < deadline:
        r = m.recv_match(type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], blocking=True, timeout=2)
        if r is None:
            continue
        if r.get_type() == "MISSION_ACK":
            if r.type != 0:
                raise RuntimeError(f"mission refused: MISSION_ACK type {r.type}")
            # The last navigation item (ids below 100): DO items after it are never "reached".
            return len(msgs), max(seq for seq, _, cmd, _ in msgs if cmd < 100)
        seq, frame, cmd, p = msgs[r.seq]
        m.mav.mission_item_int_send(1, 1, seq, frame, cmd, 0, 1, p[0], p[1], p[2], p[3],
                                    int(round(p[4] * 1e7)) if frame != 2 else int(p[4]),
                                    int(round(p[5] * 1e7)) if frame != 2 else int(p[5]), p[6], 0)
    raise RuntimeError("mission upload timed out")


def command(m, cmd, *params, timeout=3.0):
    p = list(params) + [0] * (7 - len(params))
    m.mav.command_long_send(1, 1, cmd, 0, *p)
    deadline = time.time() + timeout
    while time.time() < deadline:
        a = m.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.5)
        if a is not None and a.command == cmd:
            return a.result
    return None


def fly_coastline(m, max_s, events, aim):
    from pymavlink import mavutil
    n, last_nav = upload_plan(m, os.path.join(ROOT, "mission", "coastline.plan"), keep_gimbal_items=aim == "mission")
    events.append(f"mission uploaded: {n} items")
    # Arm once PX4's pre-arm checks pass (it says so by accepting).
    t0 = time.time()
    while True:
        r = command(m, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        if r == 0:
            break
        if time.time() - t0 > 90:
            raise RuntimeError(f"PX4 refused to arm for 90 s (last result {r})")
        time.sleep(2)
    events.append(f"armed after {time.time() - t0:.1f} s of trying")
    if command(m, mavutil.mavlink.MAV_CMD_MISSION_START, 0, n - 1) != 0:
        raise RuntimeError("MISSION_START refused")
    start = time.time()
    last = -1

    def disarmed(hb):
        return hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1 \
            and not hb.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED

    # Until the mission's last navigation item is reached, or it lands the vehicle itself
    # (a closing RETURN_TO_LAUNCH is never "reached": PX4 lands and disarms).
    while time.time() - start < max_s:
        r = m.recv_match(type=["MISSION_ITEM_REACHED", "STATUSTEXT", "HEARTBEAT"], blocking=True, timeout=1)
        if r is None:
            continue
        if r.get_type() == "MISSION_ITEM_REACHED":
            last = r.seq
            if last >= last_nav:
                break
        elif r.get_type() == "HEARTBEAT":
            if time.time() - start > 10 and disarmed(r):
                events.append(f"mission: landed and disarmed after {time.time() - start:.0f} s (item {last} reached)")
                return
        else:
            events.append(f"PX4: {r.text}")
    events.append(f"mission: item {last} reached (last navigation item {last_nav}) after {time.time() - start:.0f} s")
    command(m, mavutil.mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH)
    t = time.time()
    while time.time() - t < 120:
        hb = m.recv_match(type="HEARTBEAT", blocking=True, timeout=1)
        if hb is not None and disarmed(hb):
            events.append(f"disarmed {time.time() - t:.0f} s after RTL")
            return
    events.append("not disarmed within 120 s of RTL")


def estimate_vs_truth(ulg):
    """EKF2's local position against SIH's truth over the airborne time (truth more than
    1 m above its start), from PX4's own flight log: RMS and max, horizontal and vertical."""
    import numpy as np
    from pyulog import ULog
    u = ULog(ulg, ["vehicle_local_position", "vehicle_local_position_groundtruth"])
    d = {x.name: x.data for x in u.data_list}
    est, gt = d["vehicle_local_position"], d["vehicle_local_position_groundtruth"]
    t = gt["timestamp"]
    air = -(gt["z"] - gt["z"][0]) > 1.0
    err = {k: np.interp(t, est["timestamp"], est[k])[air] - gt[k][air] for k in "xyz"}
    h = np.hypot(err["x"], err["y"])
    v = np.abs(err["z"])
    return {
        "airborne_s": round(float(air.sum()) / max(1, len(t)) * float(t[-1] - t[0]) * 1e-6, 1),
        "horizontal_rms_m": round(float(np.sqrt((h ** 2).mean())), 3),
        "horizontal_max_m": round(float(h.max()), 3),
        "vertical_rms_m": round(float(np.sqrt((v ** 2).mean())), 3),
        "vertical_max_m": round(float(v.max()), 3),
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--px4", required=True)
    ap.add_argument("--mavloc", required=True)
    ap.add_argument("--out", default=os.path.join(ROOT, "results", "sitl"))
    ap.add_argument("--max-s", type=float, default=600)
    ap.add_argument("--aim", choices=["mission", "border"], default="mission",
                    help="who points the gimbal: the mission's ROI items, or mavloc (gimbal.aim = border)")
    a = ap.parse_args()
    reexec_in_netns()
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    name = f"coastline-{a.aim}"
    out = os.path.join(os.path.abspath(a.out), name)
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    params = read_params(os.path.join(ROOT, "config", "px4", "coastline.params"))
    report = {"scenario": name, "px4_params": params, "private_netns": in_private_netns(), "events": []}
    px4, px4_started = start_px4(a.px4, params, out)
    state = os.path.join(out, "state")
    mlog = open(os.path.join(out, "mavloc.log"), "w")
    mavloc = subprocess.Popen([a.mavloc, "--config", os.path.join(ROOT, "config", "sitl.toml"), "run",
                               "--set", f"daemon.state_dir={state}", "--set", "camera.scenario=coastline",
                               "--set", f"gimbal.aim={a.aim}"],
                              stdout=mlog, stderr=subprocess.STDOUT, env=dict(os.environ, RUST_LOG="mavloc=info"))
    try:
        # The pilot is a ground station on PX4's GCS link (PX4 sends to 14550).
        m = mavutil.mavlink_connection("udpin:127.0.0.1:14550", source_system=255, source_component=190)
        hb = m.wait_heartbeat(timeout=30)
        if hb is None:
            raise RuntimeError("no heartbeat from PX4 within 30 s")
        report["events"].append(f"PX4 heartbeat after {time.time() - px4_started:.1f} s")
        fly_coastline(m, a.max_s, report["events"], a.aim)
        report["ok"] = True
    except Exception as e:  # the report says what failed; the logs are kept
        report["ok"] = False
        report["error"] = f"{type(e).__name__}: {e}"
    finally:
        mavloc.send_signal(signal.SIGTERM)
        try:
            report["mavloc_exit"] = mavloc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            mavloc.kill()
            report["mavloc_exit"] = "killed"
        stop_px4(a.px4, px4)
    logs = sorted(glob.glob(os.path.join(a.px4, "rootfs", "log", "*", "*.ulg")), key=os.path.getmtime)
    if logs and os.path.getmtime(logs[-1]) >= px4_started:
        shutil.copy(logs[-1], os.path.join(out, "px4.ulg"))
        report["ulg"] = "px4.ulg"
    if report.get("ulg"):
        try:
            report["px4_estimate_vs_truth"] = estimate_vs_truth(os.path.join(out, "px4.ulg"))
        except Exception as e:  # a log without the topics: say so, keep the rest
            report["px4_estimate_vs_truth"] = f"not computed: {type(e).__name__}: {e}"
    status = os.path.join(state, "status.json")
    if os.path.exists(status):
        report["mavloc_counters"] = json.load(open(status))["counters"]
    lm = os.path.join(state, "results", "area", "landmarks.csv")
    if os.path.exists(lm):
        report["landmarks"] = max(0, sum(1 for _ in open(lm)) - 1)
    if report.get("landmarks"):
        # Accuracy against the simulated world's true shore: the scenario's ground truth
        # (rendered once, one frame) and `mavloc eval area`.
        truth = os.path.join(out, "truth")
        subprocess.run([a.mavloc, "sim", "render", "--scenario", "coastline", "--frames", "1", "--width", "320",
                        "--height", "180", "--out", truth, "--force"], capture_output=True, check=True)
        r = subprocess.run([a.mavloc, "eval", "area", "--dataset", truth, "--result",
                            os.path.join(state, "results", "area"), "--json"], capture_output=True, text=True)
        if r.returncode == 0:
            e = json.loads(r.stdout)
            report["evaluation"] = e
            report["mean_m"] = e["mean_m"]
            report["median_m"] = e["median_m"]
    json.dump(report, open(os.path.join(out, "report.json"), "w"), indent=2)
    print(json.dumps(report, indent=2))
    return 0 if report.get("ok") else 1


if __name__ == "__main__":
    sys.exit(main())
