#!/usr/bin/env python3
"""End-to-end tests of `mavloc run` from an independent MAVLink implementation (pymavlink),
over UDP loopback only. Usage: daemon.py MAVLOC_BINARY [TEST ...]. Each test starts its own
daemon, bounds every wait, and stops the daemon itself; exit status 0 means all passed."""

import os
import json
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v10 import common as v1  # noqa: E402
from pymavlink.dialects.v20 import common as mav2  # noqa: E402

BIN = sys.argv[1]
GCS = (255, 190)
MAVLOC_COMP = 191
USER_1, USER_2 = 31010, 31011


def free_port():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class Daemon:
    def __init__(self, extra_config="", scheme="udpin", same_as=None, connection=None):
        """A running `mavloc run`; `same_as`: restart with another daemon's folder and port;
        `connection`: `mavlink.connection` instead of `scheme` on a free loopback port."""
        if same_as is None:
            self.dir = tempfile.mkdtemp(prefix="mavloc-e2e-")
            self.port = free_port()
        else:
            self.dir, self.port = same_as.dir, same_as.port
        self.state = os.path.join(self.dir, "state")
        cfg = os.path.join(self.dir, "mavloc.toml")
        if same_as is None:
            with open(cfg, "w") as f:
                f.write(f"""
[daemon]
state_dir = "{self.state}"
pipeline = "area"
[mavlink]
connection = "{connection or f'{scheme}:127.0.0.1:{self.port}'}"
{extra_config}
""")
        self.log = open(os.path.join(self.dir, "mavloc.log"), "a")
        env = dict(os.environ, RUST_LOG="mavloc=info")
        self.proc = subprocess.Popen([BIN, "--config", cfg, "run"], stdout=self.log, stderr=subprocess.STDOUT, env=env)

    def status(self):
        with open(os.path.join(self.state, "status.json")) as f:
            return json.load(f)

    def connect(self):
        c = mavutil.mavlink_connection(f"udpout:127.0.0.1:{self.port}", source_system=GCS[0],
                                       source_component=GCS[1], dialect="common")
        return c

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                return self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                raise AssertionError("mavloc did not exit within 5 s of SIGTERM")
        return self.proc.returncode

    def logtext(self):
        self.log.flush()
        with open(os.path.join(self.dir, "mavloc.log")) as f:
            return f.read()


BACKLOG = {}


def recv(c, types, timeout=5.0, cond=lambda m: True):
    """First message of the given type from mavloc's component satisfying cond. Messages
    passed over are kept, so a later call can still find them."""
    backlog = BACKLOG.setdefault(id(c), [])
    for i, m in enumerate(backlog):
        if m.get_type() == types and cond(m):
            return backlog.pop(i)
    deadline = time.time() + timeout
    while time.time() < deadline:
        m = c.recv_match(blocking=True, timeout=0.2)
        if m is None or m.get_srcComponent() != MAVLOC_COMP:
            continue
        if m.get_type() == types and cond(m):
            return m
        backlog.append(m)
        del backlog[:-500]
    raise AssertionError(f"no {types} from mavloc within {timeout} s")


def hello(c, timeout=10.0):
    """Pokes mavloc until it answers (udpin answers only once it heard us)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        c.mav.heartbeat_send(mav2.MAV_TYPE_GCS, mav2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        m = c.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
        if m is not None and m.get_srcComponent() == MAVLOC_COMP:
            return m
    raise AssertionError("mavloc never sent a heartbeat")


def v1_autopilot_heartbeat():
    """A MAVLink 1 heartbeat from system 1, component 1, as PX4 sends before switching to v2."""
    m = v1.MAVLink(None, srcSystem=1, srcComponent=1)
    msg = m.heartbeat_encode(v1.MAV_TYPE_QUADROTOR, v1.MAV_AUTOPILOT_PX4, 0, 0, v1.MAV_STATE_STANDBY, 3)
    return msg.pack(m)


def param_list(c):
    c.mav.param_request_list_send(1, 0)
    got = {}
    count = None
    deadline = time.time() + 10
    while time.time() < deadline and (count is None or len(got) < count):
        m = c.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
        if m is None or m.get_srcComponent() != MAVLOC_COMP:
            continue
        assert count is None or m.param_count == count, "param_count changed within a list"
        count = m.param_count
        assert 0 <= m.param_index < count, f"index {m.param_index} outside 0..{count}"
        got[m.param_index] = m
    assert count and len(got) == count, f"got {len(got)} of {count} parameters"
    names = [got[i].param_id for i in range(count)]
    assert len(set(names)) == count, "duplicate parameter names"
    assert all(len(n) <= 16 for n in names)
    return got


def test_link_params_commands_garbage_and_peer_loss():
    d = Daemon()
    try:
        c = d.connect()
        hb = hello(c)
        assert hb.type == mav2.MAV_TYPE_ONBOARD_CONTROLLER, hb.type
        assert hb.autopilot == mav2.MAV_AUTOPILOT_INVALID
        assert hb.get_srcSystem() == 1, "adopts the autopilot's system id by default"
        assert hb.system_status == mav2.MAV_STATE_STANDBY, "no autopilot, no frames: not ACTIVE"

        # A MAVLink 1 autopilot heartbeat is accepted: mavloc then asks for streams.
        sock = c.port
        sock.sendto(v1_autopilot_heartbeat(), ("127.0.0.1", d.port))
        st = recv(c, "STATUSTEXT", cond=lambda m: "autopilot found" in m.text)
        req = recv(c, "COMMAND_LONG", cond=lambda m: m.command == mav2.MAV_CMD_SET_MESSAGE_INTERVAL)
        assert req.target_system == 1 and req.target_component == 1
        assert int(req.param1) in (30, 32, 33, 242, 285, 2)

        params = param_list(c)
        by_name = {p.param_id: p for p in params.values()}
        assert "AREA_RATIO" in by_name and "IND_LAND_EN" in by_name

        # A legal set answers the new value; an illegal one the unchanged value and a reason.
        c.mav.param_set_send(1, MAVLOC_COMP, b"AREA_RATIO", 0.7, mav2.MAV_PARAM_TYPE_REAL32)
        pv = recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_RATIO")
        assert abs(pv.param_value - 0.7) < 1e-6, pv.param_value
        c.mav.param_set_send(1, MAVLOC_COMP, b"AREA_RATIO", 5.0, mav2.MAV_PARAM_TYPE_REAL32)
        pv = recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_RATIO")
        assert abs(pv.param_value - 0.7) < 1e-6, "refused set must answer the unchanged value"
        st = recv(c, "STATUSTEXT", cond=lambda m: "AREA_RATIO" in m.text)
        assert st.severity == mav2.MAV_SEVERITY_WARNING
        with open(os.path.join(d.state, "params.json")) as f:
            assert abs(json.load(f)["AREA_RATIO"] - 0.7) < 1e-9, "the tuned value is persisted"

        # Commands: stop and start the area pipeline; unknown command; untrusted sender.
        def command(cmd, p1=0, p2=0, conn=c):
            conn.mav.command_long_send(1, MAVLOC_COMP, cmd, 0, p1, p2, 0, 0, 0, 0, 0)
            return recv(conn, "COMMAND_ACK", cond=lambda m: m.command == cmd).result
        assert command(USER_1, 1, 0) == mav2.MAV_RESULT_ACCEPTED
        assert command(USER_1, 1, 1) == mav2.MAV_RESULT_ACCEPTED
        assert command(USER_1, 7, 1) == mav2.MAV_RESULT_DENIED
        # The map adjusted on command: refused while AREA_ADJ_PRIOR is 0; with it set, the
        # request reaches the pipeline's worker, which says why there is nothing to adjust.
        # (STATUSTEXT carries 50 characters: longer lines come in pieces.)
        assert command(USER_1, 1, 3) == mav2.MAV_RESULT_DENIED
        recv(c, "STATUSTEXT", cond=lambda m: "AREA_ADJ_PRIOR" in m.text)
        c.mav.param_set_send(1, MAVLOC_COMP, b"AREA_ADJ_PRIOR", 1.5, mav2.MAV_PARAM_TYPE_REAL32)
        pv = recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_ADJ_PRIOR")
        assert abs(pv.param_value - 1.5) < 1e-6, pv.param_value
        assert command(USER_1, 1, 3) == mav2.MAV_RESULT_ACCEPTED
        recv(c, "STATUSTEXT", cond=lambda m: "area: asked to; the map is not adjusted" in m.text)
        recv(c, "STATUSTEXT", cond=lambda m: "fewer than 30" in m.text)
        assert command(mav2.MAV_CMD_DO_SET_MODE) == mav2.MAV_RESULT_UNSUPPORTED
        assert command(USER_2) == mav2.MAV_RESULT_IN_PROGRESS
        done = recv(c, "COMMAND_ACK", cond=lambda m: m.command == USER_2)
        assert done.result == mav2.MAV_RESULT_ACCEPTED, "the snapshot is acknowledged once written"
        # A foreign system's command is DENIED; the answer goes to mavloc's peers, never
        # to the intruder's address (no datagram makes its sender a peer).
        intruder = mavutil.mavlink_connection(f"udpout:127.0.0.1:{d.port}", source_system=77,
                                              source_component=190, dialect="common")
        intruder.mav.command_long_send(1, MAVLOC_COMP, USER_1, 0, 1, 0, 0, 0, 0, 0, 0)
        ack = recv(c, "COMMAND_ACK", cond=lambda m: m.command == USER_1 and m.target_system == 77)
        assert ack.result == mav2.MAV_RESULT_DENIED
        assert intruder.recv_match(blocking=True, timeout=1.0) is None, "the intruder heard mavloc"
        intruder.close()

        # Garbage: random bytes, corrupted and truncated frames between valid requests.
        rnd = random.Random(5)
        good = c.mav.param_request_read_encode(1, MAVLOC_COMP, b"AREA_BAND_PX", -1).pack(c.mav)
        for i in range(40):
            junk = bytes(rnd.randrange(256) for _ in range(rnd.randrange(1, 80)))
            bad = bytearray(good)
            bad[rnd.randrange(1, len(bad))] ^= 0xFF
            sock.sendto(junk + bytes(bad) + good[: rnd.randrange(1, len(good))], ("127.0.0.1", d.port))
        sock.sendto(bytes([0xFD]) + bytes(rnd.randrange(256) for _ in range(300)), ("127.0.0.1", d.port))
        c.mav.param_request_read_send(1, MAVLOC_COMP, b"AREA_BAND_PX", -1)
        recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_BAND_PX")
        # status.json (rewritten every second) counts the garbage and still has the
        # autopilot, which one more heartbeat keeps present: its first was seconds ago, and
        # the autopilot is lost 3 s after its last (on a loaded machine the steps above
        # took longer than that, and a single read found it lost).
        sock.sendto(v1_autopilot_heartbeat(), ("127.0.0.1", d.port))
        deadline = time.time() + 2.5
        while True:
            time.sleep(0.2)
            with open(os.path.join(d.state, "status.json")) as f:
                status = json.load(f)
            sk = status["skipped"]
            if (sk["bad_crc"] + sk["truncated"] >= 40 and status["autopilot_found"]) or time.time() > deadline:
                break
        assert sk["bad_crc"] + sk["truncated"] >= 40, sk
        assert status["autopilot_found"] is True, status

        # The peer vanishes for 10 s (its socket closed), then a new one appears.
        c.close()
        time.sleep(10)
        assert d.proc.poll() is None, "mavloc must keep running while its peer is away"
        c2 = d.connect()
        hello(c2)
        c2.mav.param_request_read_send(1, MAVLOC_COMP, b"AREA_RATIO", -1)
        pv = recv(c2, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_RATIO")
        assert abs(pv.param_value - 0.7) < 1e-6
        c2.close()
        assert "autopilot lost" in d.logtext()
    finally:
        code = d.stop()
    assert code == 0, f"exit status {code}"


def key_file(key):
    """A signing key file as mavloc wants it: 64 hex characters, mode 0600."""
    path = os.path.join(tempfile.mkdtemp(prefix="mavloc-key-"), "key")
    with open(path, "w") as f:
        f.write(key.hex() + "\n")
    os.chmod(path, 0o600)
    return path


def test_signing():
    key = bytes(range(32))
    d = Daemon(f'signing_key = "{key_file(key)}"')
    try:
        c = d.connect()
        # With signing on, only a signed frame makes us a peer: unsigned, mavloc is silent.
        c.setup_signing(key, sign_outgoing=False, allow_unsigned_callback=lambda *a: False)
        c.mav.heartbeat_send(mav2.MAV_TYPE_GCS, mav2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        assert c.recv_match(type="HEARTBEAT", blocking=True, timeout=2.5) is None, "an unsigned GCS was answered"
        # Signed: answered, and mavloc's heartbeats arrive signed (we refuse others).
        c.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda *a: False)
        hb = hello(c)
        assert hb is not None
        c.setup_signing(key, sign_outgoing=False, allow_unsigned_callback=lambda *a: False)
        c.mav.param_set_send(1, MAVLOC_COMP, b"AREA_BAND_PX", 80, mav2.MAV_PARAM_TYPE_REAL32)
        pv = recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_BAND_PX")
        recv(c, "STATUSTEXT", cond=lambda m: "unsigned" in m.text)
        c.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda *a: False)
        c.mav.param_set_send(1, MAVLOC_COMP, b"AREA_BAND_PX", 80, mav2.MAV_PARAM_TYPE_REAL32)
        pv2 = recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_BAND_PX")

        def as_int(v):
            import struct
            return struct.unpack("<i", struct.pack("<f", v))[0]
        assert as_int(pv.param_value) == 50, "unsigned set must be refused"
        assert as_int(pv2.param_value) == 80, "signed set must be accepted"
        # Signed with the wrong key: dropped and counted, the value stays.
        c.setup_signing(bytes(32), sign_outgoing=True, allow_unsigned_callback=lambda *a: False)
        c.mav.param_set_send(1, MAVLOC_COMP, b"AREA_BAND_PX", 90, mav2.MAV_PARAM_TYPE_REAL32)
        time.sleep(1.5)
        c.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda *a: False)
        c.mav.param_request_read_send(1, MAVLOC_COMP, b"AREA_BAND_PX", -1)
        pv3 = recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_BAND_PX")
        assert as_int(pv3.param_value) == 80, "a wrongly signed set must be refused"
        with open(os.path.join(d.state, "status.json")) as f:
            assert json.load(f)["skipped"]["bad_signature"] >= 1
        c.close()
    finally:
        code = d.stop()
    assert code == 0
    with open(os.path.join(d.state, "signing-timestamp")) as f:
        lines = f.read().splitlines()
    assert int(lines[0]) > 0, "our own timestamp first"
    assert any(l.split()[1:3] == ["255", "190"] for l in lines[1:]), f"our stream is remembered: {lines}"


def test_sigterm_leaves_complete_results():
    """SIGHUP (an SSH session that ends) leaves the daemon running and talking; SIGTERM
    stops it within 2 s with its state written."""
    d = Daemon()
    c = d.connect()
    hello(c)
    d.proc.send_signal(signal.SIGHUP)
    time.sleep(1.5)
    assert d.proc.poll() is None, f"SIGHUP ended mavloc (exit {d.proc.poll()})"
    # What came before is dropped: the heartbeat must be one sent after the hangup.
    BACKLOG[id(c)] = []
    while c.recv_match(blocking=False) is not None:
        pass
    recv(c, "HEARTBEAT", timeout=3)
    t0 = time.time()
    d.proc.send_signal(signal.SIGTERM)
    code = d.proc.wait(timeout=5)
    took = time.time() - t0
    assert code == 0, f"exit status {code}"
    assert took < 2.0, f"took {took:.2f} s to exit"
    with open(os.path.join(d.state, "status.json")) as f:
        status = json.load(f)
    assert status["link"] == "shutting down"
    assert not [n for n in os.listdir(d.state) if n.endswith(".tmp")], "no temporary files left"
    c.close()


def raw_frame(sysid, build, signing_key=None):
    """The bytes of one MAVLink 2 frame from `sysid`, built by `build(mav)`."""
    m = mav2.MAVLink(None, srcSystem=sysid, srcComponent=190)
    if signing_key is not None:
        m.signing.secret_key = signing_key
        m.signing.link_id = 4
        m.signing.timestamp = int((time.time() - 1420070400) * 100000)
        m.signing.sign_outgoing = True
    return build(m).pack(m)


def test_hostile_peers_on_udpin():
    """Hijack attempts, a list-request and command flood from a foreign id, NaN sets and an
    unknown command: the GCS keeps its link, the attacker hears nothing, the log stays small."""
    d = Daemon()
    try:
        c = d.connect()
        hello(c)
        before = len(d.logtext().splitlines())
        attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        attacker.bind(("127.0.0.1", 0))
        attacker.settimeout(0.2)
        target = ("127.0.0.1", d.port)
        rnd = random.Random(7)
        foreign_hb = raw_frame(42, lambda m: m.heartbeat_encode(mav2.MAV_TYPE_GCS, mav2.MAV_AUTOPILOT_INVALID, 0, 0, 0))
        foreign_list = raw_frame(42, lambda m: m.param_request_list_encode(1, MAVLOC_COMP))
        foreign_cmd = raw_frame(42, lambda m: m.command_long_encode(1, MAVLOC_COMP, USER_1, 0, 1, 0, 0, 0, 0, 0, 0))
        for i in range(2000):
            attacker.sendto(b"", target)
            attacker.sendto(bytes(rnd.randrange(256) for _ in range(rnd.randrange(1, 60))), target)
            attacker.sendto(foreign_hb, target)
            attacker.sendto(foreign_list, target)
            attacker.sendto(foreign_cmd, target)
        # The GCS still hears heartbeats; the attacker hears nothing at all.
        t0 = time.time()
        beats = 0
        values = 0
        while time.time() - t0 < 3.0:
            m = c.recv_match(blocking=True, timeout=0.5)
            if m is None or m.get_srcComponent() != MAVLOC_COMP:
                continue
            beats += m.get_type() == "HEARTBEAT"
            values += m.get_type() == "PARAM_VALUE"
        assert beats >= 2, f"the GCS heard {beats} heartbeats in 3 s"
        assert values == 0, f"{values} PARAM_VALUEs: the foreign list requests were answered"
        heard = 0
        try:
            while True:
                attacker.recv(4096)
                heard += 1
        except socket.timeout:
            pass
        assert heard == 0, f"the attacker received {heard} datagrams"
        # Its list requests were refused, not answered to anyone.
        time.sleep(1.2)
        st = d.status()
        # The kernel drops part of a 10,000-datagram burst on a busy machine: what arrived
        # was refused.
        assert st["counters"]["param_requests_refused"] >= 100, st["counters"]
        assert st["counters"]["commands_refused"] >= 1, st["counters"]
        # 10,000 hostile datagrams cost at most a few dozen log lines (per-sender limit).
        grown = len(d.logtext().splitlines()) - before
        assert grown < 60, f"the log grew by {grown} lines"
        # NaN and infinite sets are refused and answer the unchanged value.
        c.mav.param_request_read_send(1, MAVLOC_COMP, b"AREA_RATIO", -1)
        was = recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_RATIO").param_value
        for bad in (float("nan"), float("inf"), float("-inf")):
            c.mav.param_set_send(1, MAVLOC_COMP, b"AREA_RATIO", bad, mav2.MAV_PARAM_TYPE_REAL32)
            pv = recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_RATIO")
            assert pv.param_value == was, f"{bad} changed AREA_RATIO to {pv.param_value}"
        # An unknown command id gets UNSUPPORTED, not silence.
        c.mav.command_long_send(1, MAVLOC_COMP, 42424, 0, 0, 0, 0, 0, 0, 0, 0)
        assert recv(c, "COMMAND_ACK", cond=lambda m: m.command == 42424).result == mav2.MAV_RESULT_UNSUPPORTED
        attacker.close()
        c.close()
    finally:
        code = d.stop()
    assert code == 0, f"exit status {code}"


def test_spoofed_autopilots_leave_room_for_the_ground_station():
    """Unsigned frames claiming the autopilot's system id from twelve ports (an autopilot
    cannot be told from a forgery without signatures): they hold at most the autopilot's
    share of the peer table, so the ground station arriving after them is served."""
    d = Daemon()
    try:
        spoof = raw_frame(1, lambda m: m.heartbeat_encode(mav2.MAV_TYPE_QUADROTOR, mav2.MAV_AUTOPILOT_PX4, 0, 0, 0))
        spoofers = []
        for _ in range(12):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.settimeout(0.05)
            spoofers.append(s)
        t0 = time.time()
        while time.time() - t0 < 2.0:
            for s in spoofers:
                s.sendto(spoof, ("127.0.0.1", d.port))
            time.sleep(0.2)
        c = d.connect()
        hello(c)
        beats = 0
        t0 = time.time()
        while time.time() - t0 < 3.0:
            for s in spoofers:
                s.sendto(spoof, ("127.0.0.1", d.port))
            m = c.recv_match(type="HEARTBEAT", blocking=True, timeout=0.3)
            beats += m is not None and m.get_srcComponent() == MAVLOC_COMP
        assert beats >= 2, f"the ground station heard {beats} heartbeats in 3 s"
        served = 0
        for s in spoofers:
            try:
                while True:
                    s.recv(4096)
                    served += 1
                    break
            except socket.timeout:
                pass
        assert served <= 4, f"{served} of the 12 spoofing ports were sent to: more than the autopilot's share"
        assert d.status()["peers_refused"] > 0
        for s in spoofers:
            s.close()
        c.close()
    finally:
        code = d.stop()
    assert code == 0, f"exit status {code}"


def test_signed_replay_after_a_crash_is_refused():
    key = bytes(range(1, 33))
    d = Daemon(f'signing_key = "{key_file(key)}"')
    c = d.connect()
    c.setup_signing(key, sign_outgoing=True, link_id=2, allow_unsigned_callback=lambda *a: False)
    hello(c)
    captured = raw_frame(255, lambda m: m.param_set_encode(1, MAVLOC_COMP, b"AREA_RATIO", 0.8,
                                                             mav2.MAV_PARAM_TYPE_REAL32), signing_key=key)
    c.port.sendto(captured, ("127.0.0.1", d.port))
    assert abs(recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_RATIO").param_value - 0.8) < 1e-6
    c.mav.param_set_send(1, MAVLOC_COMP, b"AREA_RATIO", 0.6, mav2.MAV_PARAM_TYPE_REAL32)
    assert abs(recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_RATIO").param_value - 0.6) < 1e-6
    time.sleep(0.3)
    d.proc.kill()  # a crash: nothing saved on the way out
    d.proc.wait(timeout=5)
    d2 = Daemon(same_as=d)
    try:
        hello(c)
        c.port.sendto(captured, ("127.0.0.1", d.port))
        time.sleep(1.0)
        c.mav.param_request_read_send(1, MAVLOC_COMP, b"AREA_RATIO", -1)
        pv = recv(c, "PARAM_VALUE", cond=lambda m: m.param_id == "AREA_RATIO" and m.param_index >= 0)
        assert abs(pv.param_value - 0.6) < 1e-6, f"the replayed set took effect: {pv.param_value}"
        time.sleep(1.2)
        assert d2.status()["skipped"]["bad_signature"] >= 1
        c.close()
    finally:
        code = d2.stop()
    assert code == 0


def test_tcpin_serves_a_reader_beside_a_client_that_never_reads():
    d = Daemon(scheme="tcpin")
    try:
        deadline = time.time() + 10
        while True:
            try:
                stuck = socket.create_connection(("127.0.0.1", d.port), timeout=1)
                break
            except OSError:
                assert time.time() < deadline, "mavloc never listened"
                time.sleep(0.1)
        stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
        stuck.sendall(raw_frame(255, lambda m: m.heartbeat_encode(mav2.MAV_TYPE_GCS, mav2.MAV_AUTOPILOT_INVALID, 0, 0, 0)))
        # The old tcpin served one client at a time: this one would never be heard.
        c = mavutil.mavlink_connection(f"tcp:127.0.0.1:{d.port}", source_system=GCS[0],
                                       source_component=GCS[1], dialect="common")
        hello(c)
        c.mav.param_request_list_send(1, 0)
        t0 = time.time()
        beats = 0
        while time.time() - t0 < 4.0:
            m = c.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
            beats += m is not None and m.get_srcComponent() == MAVLOC_COMP
        assert beats >= 3, f"the reading client heard {beats} heartbeats in 4 s"
        c.close()
        stuck.close()
    finally:
        code = d.stop()
    assert code == 0


def test_a_second_daemon_on_the_same_state_directory_is_refused():
    """One daemon per state directory: a second one (started by hand beside the service)
    exits 1 naming the first's pid, where it ran and wrote its own sets and status over the
    first's; the first goes on."""
    d = Daemon()
    try:
        c = d.connect()
        hello(c)
        second = Daemon(same_as=d)
        try:
            code = second.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            second.proc.kill()
            raise AssertionError("a second daemon on the same state directory kept running")
        assert code == 1, f"exit status {code}"
        text = d.logtext()
        assert f"is in use by another mavloc (pid {d.proc.pid})" in text, text[-2000:]
        assert d.proc.poll() is None, "the first daemon stopped"
        BACKLOG[id(c)] = []
        while c.recv_match(blocking=False) is not None:
            pass
        recv(c, "HEARTBEAT", timeout=3)
        c.close()
    finally:
        assert d.stop() == 0


def test_unusable_state_directory_exits_78_naming_it():
    """/proc/self exists and nobody, root included, can create files in it."""
    d = tempfile.mkdtemp(prefix="mavloc-ro-")
    cfg = os.path.join(d, "mavloc.toml")
    with open(cfg, "w") as f:
        f.write(f'[daemon]\nstate_dir = "/proc/self"\n[mavlink]\nconnection = "udpin:127.0.0.1:{free_port()}"\n')
    p = subprocess.run([BIN, "--config", cfg, "run"], capture_output=True, text=True, timeout=20)
    assert p.returncode == 78, f"exit {p.returncode}: {p.stderr}"
    assert "/proc/self" in p.stderr and "not writable" in p.stderr, p.stderr


def test_corrupt_state_files_are_moved_aside():
    d = Daemon()
    c = d.connect()
    hello(c)
    c.close()
    d.stop()
    with open(os.path.join(d.state, "params.json"), "w") as f:
        f.write("{ not json")
    d2 = Daemon(same_as=d)
    try:
        c = d2.connect()
        hello(c)
        c.close()
    finally:
        code = d2.stop()
    assert code == 0
    aside = [n for n in os.listdir(d.state) if n.startswith("params.json.")]
    assert aside, f"params.json was not moved aside: {os.listdir(d.state)}"


class BlockingReceive:
    """A connection whose `recv_match` waits for its timeout instead of returning at once.
    pymavlink's FTP client polls `recv_match(type=..., timeout=0.1)` without
    `blocking=True`, so the timeout is ignored and the client spins a core for the whole
    transfer (90 % of this test's CPU, which the suite's other tests wait for). Waiting is
    what the timeout asks for; what the client sends and accepts is unchanged."""

    def __init__(self, c):
        self._c = c

    def __getattr__(self, name):
        return getattr(self._c, name)

    def recv_match(self, *args, **kwargs):
        if kwargs.get("timeout") is not None:
            kwargs.setdefault("blocking", True)
        return self._c.recv_match(*args, **kwargs)


def ftp_client(c):
    """pymavlink's own MAVLink FTP client, talking to mavloc."""
    from pymavlink import mavftp
    return mavftp.MAVFTP(BlockingReceive(c), 1, MAVLOC_COMP)


def ftp_get(c, path, local):
    """Downloads `path` from mavloc's MAVLink FTP server with pymavlink's own client."""
    ftp = ftp_client(c)
    ftp.cmd_get([path, local])
    ret = ftp.process_ftp_reply("OpenFileRO", timeout=10)
    assert ret.error_code == 0, f"FTP get {path}: error {ret.error_code}"
    with open(local, "rb") as f:
        return f.read()


def mavlink_crc32(data):
    """MAVLink's CRC32 (mavlink.io/en/guide/crc.html): the CRC-32 polynomial, reflected,
    started at 0 and not inverted at the end; zlib's crc32 is not it."""
    crc = 0
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xEDB88320 if crc & 1 else crc >> 1
    return crc


def ftp_crc(c, path):
    """CalcFileCRC32 for `path` through pymavlink's FTP client, which only logs the value."""
    import logging
    found = []

    class Catch(logging.Handler):
        def emit(self, record):
            if str(record.msg).startswith("crc: "):
                found.append(record.args[1])

    catch = Catch()
    root = logging.getLogger()
    old_level = root.level
    root.addHandler(catch)
    root.setLevel(logging.INFO)
    try:
        ret = ftp_client(c).cmd_crc([path])
    finally:
        root.removeHandler(catch)
        root.setLevel(old_level)
    assert ret.error_code == 0 and found, f"FTP crc {path}: error {ret.error_code}"
    return found[0]


def component_metadata(c, timeout=5.0):
    """COMPONENT_METADATA (397), decoded by hand: pymavlink 2.4.50's dialects predate it,
    so it arrives as UNKNOWN_397 holding the whole MAVLink 2 frame."""
    import struct
    deadline = time.time() + timeout
    while time.time() < deadline:
        m = c.recv_match(type="UNKNOWN_397", blocking=True, timeout=0.2)
        if m is None:
            continue
        raw = bytes(m.data)
        if len(raw) < 12 or raw[0] != 0xFD or raw[7] | raw[8] << 8 | raw[9] << 16 != 397:
            continue
        if raw[6] != MAVLOC_COMP:
            continue
        payload = raw[10:10 + raw[1]].ljust(108, b"\0")  # MAVLink 2 trims trailing zeros
        time_boot_ms, file_crc = struct.unpack("<II", payload[:8])
        return time_boot_ms, file_crc, payload[8:].split(b"\0")[0].decode()
    raise AssertionError(f"no COMPONENT_METADATA from mavloc within {timeout} s")


def test_component_metadata_over_mavlink_ftp():
    """COMPONENT_METADATA names general.json; both files come over MAVLink FTP with the
    CRCs announced, and parameters.json describes every parameter PARAM_VALUE lists; the
    area pipeline's result set is served beside them. The CRCs are MAVLink's CRC32."""
    d = Daemon()
    try:
        c = d.connect()
        hello(c)
        c.mav.command_long_send(1, MAVLOC_COMP, mav2.MAV_CMD_REQUEST_MESSAGE, 0, 397, 0, 0, 0, 0, 0, 0)
        time_boot_ms, file_crc, uri = component_metadata(c)
        assert time_boot_ms > 0
        assert uri.startswith(f"mftp://[;comp={MAVLOC_COMP}]/"), uri
        general_bytes = ftp_get(c, uri.split("]", 1)[1], os.path.join(d.dir, "general.json"))
        assert mavlink_crc32(general_bytes) == file_crc, "general.json's CRC is the one announced"
        assert ftp_crc(c, uri.split("]", 1)[1]) == file_crc, "CalcFileCRC32 gives the same"
        general = json.loads(general_bytes)
        (entry,) = [t for t in general["metadataTypes"] if t["type"] == 1]
        params_bytes = ftp_get(c, entry["uri"].split("]", 1)[1], os.path.join(d.dir, "parameters.json"))
        assert mavlink_crc32(params_bytes) == entry["fileCrc"]
        described = {p["name"]: p for p in json.loads(params_bytes)["parameters"]}
        listed = {v.param_id for v in param_list(c).values()}
        assert set(described) == listed, set(described) ^ listed
        r = described["IND_LAND_R"]
        assert r["units"] == "m" and r["min"] == 0.05 and r["max"] == 100 and r["default"] == 0.6, r
        assert "landing zone radius" in r["shortDesc"], r
        # Read-only: a write is refused, and the files are unchanged.
        ftp = ftp_client(c)
        ftp.cmd_rm(["/mavloc/parameters.json"])
        ret = ftp.process_ftp_reply("RemoveFile", timeout=5)
        assert ret.error_code != 0, "a remove must be refused"
        again = ftp_get(c, entry["uri"].split("]", 1)[1], os.path.join(d.dir, "again.json"))
        assert again == params_bytes
        # The area pipeline's current result set is served too: a snapshot writes one, and
        # within the daemon's next report it is under /mavloc/results/area/, byte for byte.
        c.mav.command_long_send(1, MAVLOC_COMP, USER_2, 0, 0, 0, 0, 0, 0, 0, 0)
        done = recv(c, "COMMAND_ACK", cond=lambda m: m.command == USER_2 and m.result != mav2.MAV_RESULT_IN_PROGRESS)
        assert done.result == mav2.MAV_RESULT_ACCEPTED
        on_disk = open(os.path.join(d.state, "results", "area", "summary.json"), "rb").read()
        deadline = time.time() + 5
        while True:
            try:
                got = ftp_get(c, "/mavloc/results/area/summary.json", os.path.join(d.dir, "summary.json"))
                break
            except AssertionError:
                assert time.time() < deadline, "the result set was not served within 5 s"
                time.sleep(0.5)
        assert got == on_disk, (got[:200], on_disk[:200])
        c.close()
    finally:
        assert d.stop() == 0


class StreamPeer:
    """The autopilot on a byte stream to mavloc (a file descriptor: a terminal's master
    end, a TCP connection), speaking through pymavlink's codec."""

    def __init__(self, fd):
        self.master = fd
        self.mav = mav2.MAVLink(self, srcSystem=1, srcComponent=1)
        self.mav.robust_parsing = True

    def write(self, data):
        os.write(self.master, data)

    def messages(self, timeout):
        """What came from mavloc within `timeout` s."""
        import select
        r, _, _ = select.select([self.master], [], [], timeout)
        if not r:
            return []
        try:
            data = os.read(self.master, 65536)
        except OSError:  # EIO: mavloc has not opened the terminal's other end yet
            time.sleep(timeout)
            return []
        if not data:  # the connection closed
            time.sleep(timeout)
            return []
        return [m for m in (self.mav.parse_buffer(data) or []) if m.get_type() != "BAD_DATA"]

    def recv(self, kind, timeout=5.0, cond=lambda m: True):
        deadline = time.time() + timeout
        while time.time() < deadline:
            for m in self.messages(0.2):
                if m.get_srcComponent() == MAVLOC_COMP and m.get_type() == kind and cond(m):
                    return m
        raise AssertionError(f"no {kind} from mavloc over the stream within {timeout} s")

    def hello(self, timeout=10.0):
        deadline = time.time() + timeout
        while time.time() < deadline:
            self.mav.heartbeat_send(mav2.MAV_TYPE_QUADROTOR, mav2.MAV_AUTOPILOT_PX4, 0, 0, mav2.MAV_STATE_STANDBY)
            try:
                return self.recv("HEARTBEAT", timeout=0.5)
            except AssertionError:
                pass
        raise AssertionError("mavloc sent no heartbeat over the stream")

    def unplug(self):
        os.close(self.master)



class SerialPeer(StreamPeer):
    """The autopilot's end of a pseudo-terminal: mavloc opens the other end as its serial
    device, as it opens a UART to PX4's TELEM2 or a USB CDC port. What is written here goes
    through the terminal's input processing to mavloc, and what mavloc writes comes through
    its output processing: a device left in the terminal's default (cooked) mode turns CR
    into LF, eats ^S/^Q as flow control, and adds a CR before each LF."""

    def __init__(self, link):
        import pty
        master, slave = pty.openpty()
        self.device = os.ttyname(slave)
        os.close(slave)
        if os.path.lexists(link):
            os.remove(link)
        # As udev's /dev/serial/by-id names: a link that follows the device when it comes back.
        os.symlink(self.device, link)
        super().__init__(master)

# The bytes a terminal in its default mode acts on: ^C ^D ^Q ^S ^Z (signals, end of file,
# flow control), CR and LF (translated), DEL; and 0xFD/0xFE, MAVLink's start bytes.
TTY_BYTES = [0x03, 0x04, 0x0A, 0x0D, 0x11, 0x13, 0x1A, 0x7F, 0xFD, 0xFE, 0x00, 0xFF]


def test_serial_link_is_raw_both_ways_and_survives_an_unplug():
    """Over a serial device (a pseudo-terminal behind a by-id style link): held by another
    program at the start, it is said so and waited for; noise instead of frames (a baud
    rate other than the autopilot's) is named as that; frames whose bytes a cooked
    terminal would change arrive whole both ways; the device unplugged is said and waited
    for, mavloc keeps running, and the device plugged back in under the same name carries
    the link again."""
    work = tempfile.mkdtemp(prefix="mavloc-serial-")
    link = os.path.join(work, "usb-PX4_FMU_v6X-if00")
    peer = SerialPeer(link)
    # Another program holds the device (as mavlink-router or ModemManager would): said with
    # its cause, and waited for.
    import fcntl
    holder = os.open(peer.device, os.O_RDWR | os.O_NOCTTY)
    fcntl.flock(holder, fcntl.LOCK_EX | fcntl.LOCK_NB)
    d = Daemon(connection=f"serial:{link}:921600")
    try:
        deadline = time.time() + 10
        while "in use by another program" not in d.logtext():
            assert time.time() < deadline, "a device held by another program was not said: " + d.logtext()[-1500:]
            time.sleep(0.2)
        os.close(holder)
        # At another baud rate than mavloc's, the autopilot's frames arrive as noise: after
        # the wait, mavloc names the baud rate (the first thing to check on a new harness).
        noise = random.Random(7)
        deadline = time.time() + 20
        while "but no MAVLink frame that checks" not in d.logtext():
            assert time.time() < deadline, "noise on the port was not said: " + d.logtext()[-1500:]
            peer.write(bytes(noise.choice([0x00, 0x80, 0xF8, 0x78, 0x86, 0x06]) for _ in range(200)))
            peer.messages(0.2)  # mavloc's own heartbeats, read so the terminal never fills
        said = d.logtext()
        assert "does the autopilot send at 921600 baud" in said and "SER_TEL2_BAUD" in said, said[-1500:]
        peer.hello()
        # Wait for the autopilot to be found, then count from there: what came before mavloc
        # set its end of the terminal up may have been cut.
        deadline = time.time() + 5
        while True:
            # mavloc speaks first on a serial link, so its heartbeat says nothing of ours.
            peer.mav.heartbeat_send(mav2.MAV_TYPE_QUADROTOR, mav2.MAV_AUTOPILOT_PX4, 0, 0, mav2.MAV_STATE_STANDBY)
            try:
                before = d.status()
                if before["autopilot_found"]:
                    break
            except (OSError, ValueError):  # not written yet
                pass
            assert time.time() < deadline, "the autopilot on the serial link was not found"
            time.sleep(0.3)
        errors_before = peer.mav.total_receive_errors
        sent = 300
        for i in range(sent):
            value = [(TTY_BYTES[(i + k) % len(TTY_BYTES)] + 128) % 256 - 128 for k in range(32)]
            peer.mav.memory_vect_send(TTY_BYTES[i % len(TTY_BYTES)] * 257, 1, 0, value)
            if i % 50 == 0:
                time.sleep(0.05)  # about 115 kB/s, what a 921600 baud UART carries
        # mavloc's way out: every parameter, floats of all bit patterns.
        peer.mav.param_request_list_send(1, MAVLOC_COMP)
        got, count = {}, None
        deadline = time.time() + 10
        while time.time() < deadline and (count is None or len(got) < count):
            for m in peer.messages(0.2):
                if m.get_type() == "PARAM_VALUE" and m.get_srcComponent() == MAVLOC_COMP:
                    count = m.param_count
                    got[m.param_index] = m
        assert count and len(got) == count, f"{len(got)} of {count} parameters came through the terminal"
        damaged_out = peer.mav.total_receive_errors - errors_before
        assert damaged_out == 0, f"{damaged_out} frames from mavloc were damaged"
        deadline = time.time() + 5
        while True:
            after = d.status()
            arrived = after["frames_in"] - before["frames_in"]
            if arrived >= sent or time.time() > deadline:
                break
            time.sleep(0.2)
        damaged = {k: after["skipped"][k] - before["skipped"][k] for k in after["skipped"]}
        assert arrived >= sent and not any(damaged.values()), f"{arrived} of {sent} arrived; skipped: {damaged}"

        # Unplugged: the device goes away (its name with it), mavloc says so and keeps running.
        peer.unplug()
        deadline = time.time() + 5
        while "the device went away (unplugged?)" not in d.logtext():
            assert time.time() < deadline, "the unplugged device was not noticed"
            time.sleep(0.2)
        time.sleep(1.5)
        assert d.proc.poll() is None, "mavloc must keep running while its serial device is away"
        # Plugged back in: another terminal under the same name.
        peer = SerialPeer(link)
        peer.hello(timeout=15)  # the retries back off up to 5 s
        text = d.logtext()
        assert "link up again: serial" in text, text[-2000:]
        assert text.count("no such device (unplugged?") == 1, "the missing device was not said, or more than once"
        peer.unplug()
    finally:
        code = d.stop()
    assert code == 0, f"exit status {code}"



def test_tcpout_reconnects_to_a_router_that_restarts():
    """`tcpout` to a TCP server, as mavlink-router's (port 5760) or ArduPilot SITL's: nothing
    listening at first is said (with what to check) and retried; once it listens, the
    autopilot behind it is found; the server restarting (the connection reset, the port
    closed, then open again) is said and the link taken again, mavloc running throughout;
    a connection ended cleanly is said the same way."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    d = Daemon(connection=f"tcpout:127.0.0.1:{port}")

    def serve():
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind(("127.0.0.1", port))
        srv.listen(1)
        srv.settimeout(15)  # the retries back off up to 5 s
        conn, _ = srv.accept()
        srv.close()
        return conn

    try:
        deadline = time.time() + 10
        while "nothing listens there" not in d.logtext():
            assert time.time() < deadline, "a refused connection was not said: " + d.logtext()[-1500:]
            time.sleep(0.2)
        conn = serve()
        peer = StreamPeer(conn.fileno())
        peer.hello()
        deadline = time.time() + 5
        while "autopilot found" not in d.logtext():
            assert time.time() < deadline, "the autopilot behind the router was not found"
            peer.mav.heartbeat_send(mav2.MAV_TYPE_QUADROTOR, mav2.MAV_AUTOPILOT_PX4, 0, 0, mav2.MAV_STATE_STANDBY)
            time.sleep(0.3)
        # The router is killed with mavloc's last bytes unread: the kernel resets the
        # connection instead of ending it, and mavloc's reader or writer meets an error
        # (ECONNRESET or EPIPE, whichever runs first), not an end of file.
        import select
        assert select.select([conn], [], [], 3)[0], "mavloc sent nothing to the autopilot"
        conn.close()
        deadline = time.time() + 5
        while "closed by the peer (" not in d.logtext():
            assert time.time() < deadline, "the reset connection was not said to be closed by the peer: " + d.logtext()[-1500:]
            time.sleep(0.2)
        assert d.proc.poll() is None, "mavloc must keep running while the router is away"
        conn = serve()
        StreamPeer(conn.fileno()).hello()
        assert "link up again: connected to tcp" in d.logtext()
        # Then it stops cleanly: an end of file.
        conn.shutdown(socket.SHUT_WR)
        deadline = time.time() + 5
        while "closed by the peer;" not in d.logtext():
            assert time.time() < deadline, "the ended connection was not noticed: " + d.logtext()[-1500:]
            time.sleep(0.2)
        conn.close()
    finally:
        code = d.stop()
    assert code == 0, f"exit status {code}"

TESTS = {n: f for n, f in globals().items() if n.startswith("test_")}

if __name__ == "__main__":
    chosen = sys.argv[2:] or list(TESTS)
    failed = 0
    for name in chosen:
        t0 = time.time()
        try:
            TESTS[name]()
            print(f"ok   {name} ({time.time() - t0:.1f} s)", flush=True)
        except Exception as e:  # report every failure, then fail the run
            failed += 1
            print(f"FAIL {name}: {type(e).__name__}: {e}", flush=True)
    sys.exit(1 if failed else 0)
