#!/usr/bin/env python3
"""The closed loop end to end: `mavloc sim vehicle` and `mavloc run` (sim camera) talking
over UDP loopback through this script, which relays their datagrams as mavlink-router
would and decodes a copy of every one with pymavlink (an independent MAVLink
implementation) to see what each side says.

Usage: closed_loop.py MAVLOC_BINARY MODE SECONDS STATE_DIR [--set KEY=VALUE ...]
       [--vehicle ARG ...] [--gcs-takes-gimbal FROM TO]
MODE is "area" (coastline) or "indoor" (indoor-floor). Prints one JSON object with what was
seen; exit status 0 unless a process failed to start. Every wait is bounded.
With --gcs-takes-gimbal, the script also acts as a ground station (system 255, component
190, as QGroundControl): FROM seconds in it takes the vehicle's gimbal manager with
DO_GIMBAL_MANAGER_CONFIGURE, TO seconds in it lets go (-3)."""

import ctypes
import json
import math
import os
import select
import signal
import socket
import subprocess
import sys
import time

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mav2  # noqa: E402

BIN, MODE, SECONDS, STATE = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
rest = sys.argv[5:]
daemon_sets, vehicle_args = [], []
gcs_take = None
i = 0
while i < len(rest):
    if rest[i] == "--set":
        daemon_sets += ["--set", rest[i + 1]]
        i += 2
    elif rest[i] == "--vehicle":
        vehicle_args.append(rest[i + 1])
        i += 2
    elif rest[i] == "--gcs-takes-gimbal":
        gcs_take = [float(rest[i + 1]), float(rest[i + 2])]
        i += 3
    else:
        sys.exit(f"unexpected argument {rest[i]}")


def bound_socket():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    return s


# The vehicle sends to `from_vehicle`; the daemon listens on a port we pick and we reach
# it from `to_daemon`.
from_vehicle = bound_socket()
to_daemon = bound_socket()
probe = bound_socket()
daemon_port = probe.getsockname()[1]
probe.close()

def die_with_parent():
    # PR_SET_PDEATHSIG: if this script is killed (test timeout), its children go too.
    ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)


scenario = "coastline" if MODE == "area" else "indoor-floor"
os.makedirs(STATE, exist_ok=True)
log = open(os.path.join(STATE, "mavloc.log"), "w")
vlog = open(os.path.join(STATE, "vehicle.log"), "w")
env = dict(os.environ, RUST_LOG="mavloc=info")
daemon = subprocess.Popen(
    [BIN, "run", "--mavlink", f"udpin:127.0.0.1:{daemon_port}",
     "--set", f"daemon.state_dir={STATE}", "--set", f"daemon.pipeline={MODE}",
     "--set", "camera.source=sim", "--set", f"camera.scenario={scenario}"] + daemon_sets,
    stdout=log, stderr=subprocess.STDOUT, env=env, preexec_fn=die_with_parent)
# The vehicle takes off once the daemon's simulated camera has built its world (its log
# says so), as a drone waits on the ground for its companion computer: the build takes 1 s
# on an idle machine and 15 s on a loaded one, and a mission already under way would fly
# past what the test waits for (the landing zone) before the first frame. Bounded: a
# daemon that never says so is judged by what the relay sees.
ready_by = time.time() + 60
while time.time() < ready_by and daemon.poll() is None:
    with open(os.path.join(STATE, "mavloc.log")) as f:
        if "sim camera: world of" in f.read():
            break
    time.sleep(0.1)
seen_ready_s = 60 - (ready_by - time.time())
vehicle = subprocess.Popen(
    [BIN, "sim", "vehicle", "--scenario", scenario,
     "--mavlink", f"udpout:127.0.0.1:{from_vehicle.getsockname()[1]}",
     "--truth-log", os.path.join(STATE, "truth.csv")] + vehicle_args,
    stdout=vlog, stderr=subprocess.STDOUT, preexec_fn=die_with_parent)

# The ground station's own sender: its packets go to the vehicle as the relay's do.
gcs = mav2.MAVLink(None, srcSystem=255, srcComponent=190)
parse_v = mav2.MAVLink(None)
parse_d = mav2.MAVLink(None)
parse_v.robust_parsing = parse_d.robust_parsing = True
vehicle_addr = None
seen = {
    "daemon_messages": {}, "vehicle_messages": {}, "statustext": [], "lmk": 0,
    "vpe": [], "lpn": [], "velocity": [], "land_commands": 0, "land_acks": [], "on_ground": False,
    "named": {}, "daemon_heartbeat_states": [], "commands": {}, "acks": {},
    "pitchyaw_t": [], "gimbal_configure": [], "statustext_t": [], "gcs": [], "gcs_acks": [],
}
start = time.time()
last_lpn = None
last_lpn_v = None
last_yaw = 0.0
while time.time() - start < SECONDS:
    if vehicle.poll() is not None and MODE == "indoor" and seen["on_ground"]:
        break
    if gcs_take and vehicle_addr and len(seen["gcs"]) < 2 and time.time() - start >= gcs_take[len(seen["gcs"])]:
        # First take the gimbal (primary control: this system and component), then let go.
        who = [255, 190] if not seen["gcs"] else [-3, -3]
        msg = gcs.command_long_encode(
            1, 1, mav2.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, 0, who[0], who[1], -1, -1, 0, 0, 0)
        from_vehicle.sendto(msg.pack(gcs), vehicle_addr)
        seen["gcs"].append([time.time() - start, who[0]])
    r, _, _ = select.select([from_vehicle, to_daemon], [], [], 0.1)
    for s in r:
        data, addr = s.recvfrom(4096)
        now = time.time() - start
        if s is from_vehicle:
            vehicle_addr = addr
            to_daemon.sendto(data, ("127.0.0.1", daemon_port))
            for m in parse_v.parse_buffer(data) or []:
                t = m.get_type()
                seen["vehicle_messages"][t] = seen["vehicle_messages"].get(t, 0) + 1
                if t == "LOCAL_POSITION_NED":
                    last_lpn = (m.x, m.y)
                    last_lpn_v = (m.vx, m.vy)
                elif t == "ATTITUDE":
                    last_yaw = m.yaw
                elif t == "COMMAND_ACK":
                    key = f"{m.command}:{m.result}"
                    seen["acks"][key] = seen["acks"].get(key, 0) + 1
                    if m.target_system == 255:
                        seen["gcs_acks"].append([now, m.command, m.result])
                    # Either landing: plain, or precise (23, PX4's NAV_PRECLAND).
                    if m.command in (mav2.MAV_CMD_NAV_LAND, mav2.MAV_CMD_NAV_LAND_LOCAL):
                        seen["land_acks"].append(m.result)
                elif t == "EXTENDED_SYS_STATE" and m.landed_state == mav2.MAV_LANDED_STATE_ON_GROUND:
                    seen["on_ground"] = True
        else:
            if vehicle_addr:
                from_vehicle.sendto(data, vehicle_addr)
            for m in parse_d.parse_buffer(data) or []:
                t = m.get_type()
                seen["daemon_messages"][t] = seen["daemon_messages"].get(t, 0) + 1
                if t == "STATUSTEXT":
                    seen["statustext"].append(m.text)
                    seen["statustext_t"].append([now, m.text])
                elif t == "DEBUG_VECT" and m.name == "LMK":
                    seen["lmk"] += 1
                elif t == "LANDING_TARGET":
                    seen["landing_targets"] = seen.get("landing_targets", 0) + 1
                elif t == "VISION_POSITION_ESTIMATE" or (t == "ODOMETRY" and math.isfinite(m.x)):
                    cov = m.covariance if t == "VISION_POSITION_ESTIMATE" else m.pose_covariance
                    seen["vpe"].append([now, m.x, m.y, cov[0], cov[6]])
                    if last_lpn is not None:
                        seen["lpn"].append(list(last_lpn))
                    if t == "ODOMETRY" and math.isfinite(m.vx) and last_lpn_v is not None:
                        seen["velocity"].append([now, m.vx, m.vy, m.velocity_covariance[0], *last_lpn_v, last_yaw])
                elif t == "NAMED_VALUE_FLOAT":
                    seen["named"][m.name] = m.value
                elif t == "COMMAND_LONG":
                    seen["commands"][str(m.command)] = seen["commands"].get(str(m.command), 0) + 1
                    if m.command == mav2.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE:
                        seen.setdefault("gimbal_configure_param1", []).append(m.param1)
                        seen["gimbal_configure"].append([now, m.param1])
                    elif m.command == mav2.MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW:
                        seen["pitchyaw_t"].append(now)
                    if m.command in (mav2.MAV_CMD_NAV_LAND, mav2.MAV_CMD_NAV_LAND_LOCAL):
                        seen["land_commands"] += 1
                elif t == "HEARTBEAT":
                    seen["daemon_heartbeat_states"].append(m.system_status)

for p in (daemon, vehicle):
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
for p in (daemon, vehicle):
    try:
        p.wait(timeout=5)
    except subprocess.TimeoutExpired:
        p.kill()
seen["daemon_exit"] = daemon.returncode
seen["daemon_ready_s"] = seen_ready_s
seen["elapsed_s"] = time.time() - start
print(json.dumps(seen))
