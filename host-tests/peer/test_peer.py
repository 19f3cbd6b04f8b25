"""Peer tests: a real CANopen master (python-canopen over python-can slcan)
against the virtual board (`perpend board`), which runs the firmware's
application, CANopen device and measurement core on a simulated head.

Each test starts its own board (fixture `board`, conftest.py).
"""

import math
import struct
import time
import warnings

import canopen
import pytest

from conftest import EDS, NODE_ID, PLANE, abort_code

UNLOCK = 0x6C616375  # "ucal"
SAVE = 0x65766173  # "save"
LOAD = 0x64616F6C  # "load"

# status word (0x2005), see crates/perpend-can/src/status.rs
VALID, OUT_OF_RANGE, OPEN_LOOP, OVERCURRENT = 1, 2, 4, 8
DEGRADED = 1 << 16
UNCALIBRATED = 1 << 17
NO_PLANE = 1 << 19


def nibble(status, i):
    return (status >> (4 * i)) & 0xF


def expected_normal(plane=PLANE):
    """Unit normal of the plane oriented towards the head (n_z < 0)."""
    a, b, c, _ = plane
    k = math.sqrt(a * a + b * b + c * c)
    n = (a / k, b / k, c / k)
    return tuple(-x for x in n) if n[2] > 0 else n


def expected_thetas(plane=PLANE):
    """Tian eq. 1-3 in the TCS: theta1 = atan2(n_y, -n_z), theta2 = atan2(-n_x, -n_z)."""
    nx, ny, nz = expected_normal(plane)
    return math.degrees(math.atan2(ny, -nz)), math.degrees(math.atan2(-nx, -nz))


def raw_abort_code(resp):
    assert resp is not None, "no SDO response"
    assert resp[0] == 0x80, f"expected an abort, got {resp.hex()}"
    return struct.unpack_from("<I", resp, 4)[0]


def wait_until(pred, timeout=5.0, step=0.01):
    end = time.time() + timeout
    while time.time() < end:
        if pred():
            return True
        time.sleep(step)
    return pred()


def set_heartbeat(node, ms):
    node.sdo[0x1017].raw = ms


def reset_node(b):
    """NMT reset node and wait for the boot-up message."""
    b.nmt_reset(0x81)


def sync_samples(b, n, pdos=(1, 2, 3, 4)):
    """Sends n SYNCs and collects the decoded TPDO values of each."""
    b.node.tpdo.read(from_od=True)
    out = []
    for _ in range(n):
        stamps = {k: b.node.tpdo[k].timestamp for k in pdos}
        b.network.sync.transmit()
        for k in pdos:
            assert wait_until(lambda k=k: b.node.tpdo[k].timestamp != stamps[k], 2.0), f"TPDO{k}"
        out.append({k: [v.raw for v in b.node.tpdo[k]] for k in pdos})
        time.sleep(0.003)  # a few new samples between SYNCs
    return out


# ---------------------------------------------------------------------------


def test_eds_loads_without_warnings(canopen_warnings):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        od = canopen.import_od(str(EDS), node_id=NODE_ID)
    assert not canopen_warnings, [r.getMessage() for r in canopen_warnings]
    assert od[0x1800][1].default == 0x40000180 + NODE_ID
    assert od[0x2400][1].default == NODE_ID
    assert od[0x2002][1].pdo_mappable
    assert od[0x2300][2].min == 1 and od[0x2300][2].max == 256


def test_identity_and_device_type(board):
    od = canopen.import_od(str(EDS), node_id=NODE_ID)
    sdo = board.node.sdo
    assert sdo[0x1000].raw == od[0x1000].default
    assert sdo[0x1018][1].raw == od[0x1018][1].default
    assert sdo[0x1018][2].raw == od[0x1018][2].default == 0x50455250
    assert sdo[0x1018][3].raw == od[0x1018][3].default
    assert sdo[0x1008].raw == od[0x1008].default  # segmented upload
    assert sdo[0x100A].raw.startswith("perpend ")
    assert sdo[0x1014].raw == 0x80 + NODE_ID
    assert sdo[0x1200][1].raw == 0x600 + NODE_ID


@pytest.mark.board_args("--serial", "0x00C0FFEE")
def test_identity_vendor_serial_and_device_type(board):
    """Issue 16 item 5: vendor-ID set at build time (never 0), serial
    number per board (--serial; the firmware folds the MCU UID), device
    type 0 = no standardized profile (CiA 404 not implemented, docs/can.md)."""
    od = canopen.import_od(str(EDS), node_id=NODE_ID)
    sdo = board.node.sdo
    assert sdo[0x1000].raw == 0x00000000 == od[0x1000].default
    vendor = sdo[0x1018][1].raw
    assert vendor != 0 and vendor == od[0x1018][1].default
    assert sdo[0x1018][4].raw == 0x00C0FFEE
    assert sdo[0x1018][0].raw == 4


def test_nmt_boot_up_and_heartbeat(board):
    node = board.node
    set_heartbeat(node, 50)
    assert node.nmt.wait_for_heartbeat(2) == "PRE-OPERATIONAL"
    node.nmt.state = "OPERATIONAL"
    assert wait_until(lambda: node.nmt.wait_for_heartbeat(2) == "OPERATIONAL", 2)
    node.nmt.state = "STOPPED"
    assert wait_until(lambda: node.nmt.wait_for_heartbeat(2) == "STOPPED", 2)
    # no SDO in stopped
    assert board.raw.request(bytes([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]), 0.3) is None
    node.nmt.state = "PRE-OPERATIONAL"
    assert wait_until(lambda: node.nmt.wait_for_heartbeat(2) == "PRE-OPERATIONAL", 2)
    # reset communication: boot-up, heartbeat period back to its stored value
    board.nmt_reset(0x82)
    assert node.sdo[0x1017].raw == 1000
    # reset node: boot-up again
    set_heartbeat(node, 50)
    reset_node(board)
    assert node.nmt.wait_for_heartbeat(3) == "PRE-OPERATIONAL"


def test_tpdos_on_sync_decoded_through_eds(board):
    node = board.node
    # The mapping the EDS declares is the one the device reports.
    node.tpdo.read(from_od=True)
    from_eds = {
        k: (m.cob_id, m.trans_type, [(v.index, v.subindex, v.length) for v in m])
        for k, m in node.tpdo.map.items()
        if k <= 4
    }
    node.tpdo.read()
    from_dev = {
        k: (m.cob_id, m.trans_type, [(v.index, v.subindex, v.length) for v in m])
        for k, m in node.tpdo.map.items()
        if k <= 4
    }
    assert from_eds == from_dev
    assert from_eds[1] == (0x180 + NODE_ID, 1, [(0x2002, 1, 32), (0x2002, 2, 32)])
    assert from_eds[2][2] == [(0x2005, 0, 32), (0x2007, 0, 32)]
    # nothing in pre-operational
    node.tpdo.read(from_od=True)
    t0 = node.tpdo[1].timestamp
    board.network.sync.transmit()
    time.sleep(0.2)
    assert node.tpdo[1].timestamp == t0
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)
    s = sync_samples(board, 3)
    counters = [x[2][1] for x in s]
    assert counters[0] < counters[1] < counters[2]
    for x in s:
        assert x[2][0] & NO_PLANE == 0
        nz, rms = x[4]
        assert nz < 0 and rms < 0.05


def test_angles_and_normal_match_the_plane(board):
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)
    s = sync_samples(board, 10)
    th1 = sum(x[1][0] for x in s) / len(s)
    th2 = sum(x[1][1] for x in s) / len(s)
    want1, want2 = expected_thetas()
    assert abs(th1 - want1) < 0.01, (th1, want1)
    assert abs(th2 - want2) < 0.01, (th2, want2)
    n = [sum(x[3][0] for x in s), sum(x[3][1] for x in s), sum(x[4][0] for x in s)]
    k = math.sqrt(sum(c * c for c in n))
    dot = sum(a / k * b for a, b in zip(n, expected_normal()))
    assert math.degrees(math.acos(min(1.0, dot))) < 0.01
    # the same over SDO, with the attitude correction (Chen eq. 22: yaw = theta2)
    assert abs(board.node.sdo[0x2003][2].raw - want2) < 0.05
    assert board.node.sdo[0x2005].raw & 0x1111 == 0x1111


def test_sdo_aborts_for_bad_requests(board):
    sdo = board.node.sdo
    # unknown object / sub-index
    assert abort_code(lambda: sdo.upload(0x3000, 0)) == 0x06020000
    assert abort_code(lambda: sdo.upload(0x1018, 9)) == 0x06090011
    # read-only
    assert abort_code(lambda: sdo.download(0x1000, 0, b"\x01\x00\x00\x00")) == 0x06010002
    assert abort_code(lambda: sdo.download(0x2002, 1, b"\x00\x00\x00\x00")) == 0x06010002
    # wrong length (UNSIGNED16 written with 4 bytes)
    assert abort_code(lambda: sdo.download(0x1017, 0, b"\x10\x00\x00\x00")) == 0x06070012
    assert abort_code(lambda: sdo.download(0x2300, 1, b"\x10\x27")) == 0x06070013
    # value range: invalid, too high, too low
    assert abort_code(lambda: sdo.download(0x1800, 2, b"\xf5")) == 0x06090030
    assert abort_code(lambda: sdo.download(0x2300, 1, struct.pack("<I", 200000))) == 0x06090031
    assert abort_code(lambda: sdo.download(0x2300, 1, struct.pack("<I", 50))) == 0x06090032
    assert abort_code(lambda: sdo.download(0x2300, 2, struct.pack("<H", 3))) == 0x06090030
    # store with a wrong signature
    assert abort_code(lambda: sdo.download(0x1010, 1, struct.pack("<I", 1234))) == 0x08000020
    # calibration locked
    assert abort_code(lambda: sdo.download(0x2101, 8, struct.pack("<f", 0.001))) == 0x08000021
    # mapping: PDO valid -> state; not mappable
    assert abort_code(lambda: sdo.download(0x1A00, 0, b"\x00")) == 0x08000022
    sdo[0x1800][1].raw = 0x80000000 | (0x180 + NODE_ID)
    sdo[0x1A00][0].raw = 0
    assert abort_code(lambda: sdo.download(0x1A00, 1, struct.pack("<I", 0x21010120))) == 0x06040041
    raw = board.raw
    # unknown command specifier (block upload)
    assert raw_abort_code(raw.request(bytes([0xA0, 0x08, 0x10, 0, 0, 0, 0, 0]))) == 0x05040001
    # toggle bit not alternated: segmented upload of the device name
    r = raw.request(bytes([0x40, 0x08, 0x10, 0, 0, 0, 0, 0]))
    assert r[0] == 0x41
    assert raw.request(bytes([0x60, 0, 0, 0, 0, 0, 0, 0]))[0] & 0xE0 == 0x00
    assert raw_abort_code(raw.request(bytes([0x60, 0, 0, 0, 0, 0, 0, 0]))) == 0x05030000
    # SDO timeout: a stalled segmented upload is aborted by the server (1 s)
    r = raw.request(bytes([0x40, 0x08, 0x10, 0, 0, 0, 0, 0]))
    assert r[0] == 0x41
    resp = raw.wait(3.0)
    assert raw_abort_code(resp) == 0x05040000
    assert resp[1:4] == bytes([0x08, 0x10, 0])
    # state: configuration in operational
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)
    assert abort_code(lambda: sdo.download(0x2300, 1, struct.pack("<I", 2000))) == 0x08000022
    # the device still answers normally
    assert sdo[0x1000].raw == 0


def test_calibration_store_reset_read_back(board):
    sdo = board.node.sdo
    assert sdo[0x2010].raw == 0
    sdo[0x2010].raw = UNLOCK
    assert sdo[0x2010].raw == 1
    gain = 0.00125
    sdo[0x2101][8].raw = gain
    sdo[0x2202][4].raw = 75.0
    sdo[0x2300][1].raw = 2000
    sdo[0x1010][1].raw = SAVE
    # an unsaved change is lost by the reset
    sdo[0x2101][9].raw = 0.001
    reset_node(board)
    assert abs(sdo[0x2101][8].raw - gain) < 1e-9
    assert sdo[0x2202][4].raw == 75.0
    assert sdo[0x2300][1].raw == 2000
    assert sdo[0x2101][9].raw == 0.0
    # the unlock does not survive the reset
    assert sdo[0x2010].raw == 0
    assert abort_code(lambda: sdo.download(0x2101, 8, struct.pack("<f", 0.002))) == 0x08000021


RANGE = 0x06090030
TABLE_KNOTS = (-6.0, -3.0, 0.0, 2.0, 6.0)  # mm about d_ref, exact in REAL32
TABLE_COEFFS = (0.001, -0.002, 0.0015)  # per mm


def test_linearity_table_through_the_eds_store_and_reset(board):
    """0x2101..0x2104 sub 16..23 (the linearity table) as the EDS describes
    them: knots first, then values; a write that would leave an active
    table with knots out of order is refused and changes nothing; the table
    survives store and reset node, and the board keeps measuring."""
    sdo = board.node.sdo
    od = board.node.object_dictionary
    for index in (0x2101, 0x2102, 0x2103, 0x2104):
        assert sdo[index][0].raw == 25
        assert od[index][16].name == "Linearity table knot 0 mm"
        assert od[index][23].name == "Linearity table value 2 mm"
        assert od[index][24].name == "Spot bias cos mm"
        assert od[index][25].name == "Spot bias sin mm"
    sdo[0x2010].raw = UNLOCK
    # a value on the default knots (all zero) is refused
    assert abort_code(lambda: sdo.download(0x2103, 21, struct.pack("<f", 0.001))) == RANGE
    assert sdo[0x2103][21].raw == 0.0
    for k, v in enumerate(TABLE_KNOTS):
        sdo[0x2103][16 + k].raw = v
    for k, v in enumerate(TABLE_COEFFS):
        sdo[0x2103][21 + k].raw = v
    # knots out of order under the active table
    assert abort_code(lambda: sdo.download(0x2103, 19, struct.pack("<f", 0.0))) == RANGE
    assert sdo[0x2103][19].raw == 2.0
    sdo[0x1010][1].raw = SAVE
    reset_node(board)
    got = [sdo[0x2103][16 + k].raw for k in range(8)]
    want = [struct.unpack("<f", struct.pack("<f", v))[0] for v in TABLE_KNOTS + TABLE_COEFFS]
    assert got == want
    assert [sdo[0x2102][16 + k].raw for k in range(8)] == [0.0] * 8
    # a new sample: the board finds the calibration valid (status bit 21 clear)
    n0 = sdo[0x2007].raw
    assert wait_until(lambda: sdo[0x2007].raw != n0)
    assert sdo[0x2005].raw & (1 << 21) == 0


def test_thermal_time_constant_through_the_eds_store_and_reset(board):
    """0x2105, the head's thermal time constant [s], as the EDS describes
    it (VAR, REAL32, rw, default 0): locked without the unlock, range
    0..86400 (0x06090032 below, 0x06090031 above, 0x06090030 NaN), stored
    with 0x1010 sub 3 and read back after reset node."""
    sdo = board.node.sdo
    od = board.node.object_dictionary
    assert od[0x2105].name == "Thermal time constant s"
    assert od[0x2105].data_type == canopen.objectdictionary.REAL32
    assert od[0x2105].default == 0.0
    assert sdo[0x2105].raw == 0.0
    assert abort_code(lambda: sdo.download(0x2105, 0, struct.pack("<f", 600.0))) == 0x08000021
    sdo[0x2010].raw = UNLOCK
    for bad, code in ((-1.0, 0x06090032), (86400.5, 0x06090031), (float("nan"), RANGE)):
        assert abort_code(lambda: sdo.download(0x2105, 0, struct.pack("<f", bad))) == code
    sdo[0x2105].raw = 612.5
    assert sdo[0x2105].raw == 612.5
    sdo[0x1010][3].raw = SAVE
    sdo[0x2010].raw = UNLOCK
    sdo[0x2105].raw = 5.0  # unsaved: lost by the reset
    reset_node(board)
    assert sdo[0x2105].raw == 612.5
    n0 = sdo[0x2007].raw
    assert wait_until(lambda: sdo[0x2007].raw != n0)
    assert sdo[0x2005].raw & (1 << 21) == 0


def test_restore_defaults_applies_at_reset(board):
    sdo = board.node.sdo
    default_period = canopen.import_od(str(EDS), node_id=NODE_ID)[0x2300][1].default
    sdo[0x2300][1].raw = 5000
    sdo[0x1010][1].raw = SAVE
    sdo[0x1011][1].raw = LOAD
    assert sdo[0x2300][1].raw == 5000  # effective only after the reset
    board.nmt_reset(0x81)
    assert sdo[0x2300][1].raw == default_period


def test_restore_keeps_node_id_and_bit_rate(board):
    """Issue 16 item 2: 0x1011 sub 1 "load" + reset node used to bring the
    node back as 0x20 at 1000 kbit/s; node-id and bit rate (0x2400) are
    layer settings no restore touches."""
    sdo = board.node.sdo
    sdo[0x2400][2].raw = 500
    sdo[0x1017].raw = 250
    sdo[0x1010][1].raw = SAVE
    sdo[0x1011][1].raw = LOAD
    board.nmt_reset(0x81)  # boot-up from the same node-id
    assert sdo[0x2400][1].raw == NODE_ID
    assert sdo[0x2400][2].raw == 500
    assert sdo[0x1017].raw == 1000  # the communication objects are restored
    assert sdo[0x1800][1].raw & 0x7FF == 0x180 + NODE_ID
    # the group sub-indices exist (2: communication, 3: application)
    assert sdo[0x1010][0].raw == 3 and sdo[0x1011][0].raw == 3


def test_event_timer_type_255_sends_ten_frames_a_second(board):
    """Issue 16 item 3: TPDO1 (theta1, theta2) with transmission type 255
    and an event timer of 100 ms: ~10 frames/s; the simulated noise stays
    inside the angle deadband (0x2009 sub 1), so it adds no frames."""
    sdo = board.node.sdo
    # the inhibit time changes only while the PDO does not exist
    assert abort_code(lambda: sdo.download(0x1800, 3, struct.pack("<H", 10))) == 0x06090030
    sdo[0x1800][2].raw = 255
    sdo[0x1800][5].raw = 100
    stamps = []
    board.network.subscribe(0x180 + NODE_ID, lambda can_id, data, ts: stamps.append(ts))
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.5)
    stamps.clear()
    time.sleep(3.0)
    n = len(stamps)
    board.node.nmt.state = "PRE-OPERATIONAL"
    # 30 from the timer; a rare noise excursion beyond the deadband may add one
    assert 27 <= n <= 35, f"{n} TPDO1 frames in 3 s"


def test_writes_in_operational_are_refused(board):
    sdo = board.node.sdo
    sdo[0x2010].raw = UNLOCK
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)
    before = sdo[0x2101][1].raw
    assert abort_code(lambda: sdo.download(0x2101, 1, struct.pack("<f", 1.0))) == 0x08000022
    assert abort_code(lambda: sdo.download(0x2010, 0, struct.pack("<I", UNLOCK))) == 0x08000022
    assert abort_code(lambda: sdo.download(0x2400, 1, b"\x05")) == 0x08000022
    assert sdo[0x2101][1].raw == before
    # state change cleared the unlock
    assert sdo[0x2010].raw == 0


@pytest.mark.board_args("--fault", "3:open")
def test_faulted_sensor_raises_emcy_and_falls_back_to_three(board):
    node = board.node
    code = 0x2111 + 2  # sensor 3, loop current
    # The first EMCY went out before we connected; it is in the history.
    assert node.sdo[0x1001].raw & 0x03 == 0x03  # generic + current
    history = node.sdo[0x1003]
    assert history[0].raw >= 1
    assert any(history[i].raw & 0xFFFF == code for i in range(1, history[0].raw + 1))
    # After a reset the fault is signalled again on the bus.
    node.emcy.reset()
    reset_node(board)
    assert wait_until(lambda: any(e.code == code for e in node.emcy.log), 3), node.emcy.log
    e = next(e for e in node.emcy.log if e.code == code)
    assert e.register & 0x02
    assert e.data[0] == 3 and e.data[1] == OPEN_LOOP
    # Status: sensor 3 open loop, others valid, degraded three-sensor plane.
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)
    s = sync_samples(board, 5)
    for x in s:
        st = x[2][0]
        assert nibble(st, 2) == OPEN_LOOP
        assert [nibble(st, i) & VALID for i in (0, 1, 3)] == [1, 1, 1]
        assert st & DEGRADED and not st & NO_PLANE
    th1 = sum(x[1][0] for x in s) / len(s)
    th2 = sum(x[1][1] for x in s) / len(s)
    want1, want2 = expected_thetas()
    assert abs(th1 - want1) < 0.01 and abs(th2 - want2) < 0.01, (th1, th2, want1, want2)
