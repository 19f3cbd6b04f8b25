"""Peer tests of issue 16 items 4, 6 and 7 against the virtual board:
SYNC counter (0x1019) and TPDO SYNC start value, acquisition locked to SYNC
with the sample time (0x2020) in a TPDO, heartbeat consumer (0x1016) with
the error behaviour (0x1029), and the command RPDO that triggers a
capture (0x2500..0x2502).
"""

import queue
import struct
import threading
import time

from conftest import NODE_ID
from test_peer import abort_code, expected_thetas, wait_until

EMCY = 0x80 + NODE_ID
TPDO1, TPDO2, TPDO3, TPDO4 = (0x180 + NODE_ID, 0x280 + NODE_ID, 0x380 + NODE_ID, 0x480 + NODE_ID)


def frames_of(board, cob_id):
    """A queue receiving (data, timestamp) of every frame with `cob_id`."""
    q = queue.Queue()
    board.network.subscribe(cob_id, lambda can_id, data, ts: q.put((bytes(data), ts)))
    return q


def drain(q):
    out = []
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out


def remap_tpdo(sdo, k, cob_id, mapping=None, trans_type=None, start=None):
    """TPDO k (1-based) invalidated, its mapping (list of (index, sub,
    bits)), transmission type and SYNC start value written, valid again:
    the CiA 301 order the device enforces."""
    comm, mp = sdo[0x1800 + k - 1], sdo[0x1A00 + k - 1]
    comm[1].raw = 0xC0000000 | cob_id
    if mapping is not None:
        mp[0].raw = 0
        for i, (index, sub, bits) in enumerate(mapping, start=1):
            mp[i].raw = (index << 16) | (sub << 8) | bits
        mp[0].raw = len(mapping)
    if trans_type is not None:
        comm[2].raw = trans_type
    if start is not None:
        comm[6].raw = start
    # Bit 30 set: no remote frames (the board answers none and refuses a
    # valid COB-ID that would allow them, 0x06090030).
    comm[1].raw = 0x40000000 | cob_id


def test_sync_counter_and_start_value(board):
    """0x1019 = 4: TPDO1 of type 2 with SYNC start value 2 goes out first at
    the SYNC counting 2, then at every second SYNC; 1 is refused."""
    sdo = board.node.sdo
    assert abort_code(lambda: sdo.download(0x1019, 0, b"\x01")) == 0x06090030
    sdo[0x1019].raw = 4
    # the start value changes only while the TPDO does not exist
    assert abort_code(lambda: sdo.download(0x1800, 6, b"\x02")) == 0x06090030
    remap_tpdo(sdo, 1, TPDO1, trans_type=2, start=2)
    q = frames_of(board, TPDO1)
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)
    drain(q)
    at = []
    for counter in [1, 2, 3, 4, 1, 2, 3, 4]:
        board.network.send_message(0x80, bytes([counter]))
        time.sleep(0.05)
        if drain(q):
            at.append(counter)
    assert at == [2, 4, 2, 4], at
    # a SYNC without its counter: EMCY 0x8240 (unexpected SYNC data length)
    e = frames_of(board, EMCY)
    board.network.send_message(0x80, b"")
    time.sleep(0.1)
    codes = [struct.unpack_from("<H", d)[0] for d, _ in drain(e)]
    assert 0x8240 in codes, codes


def test_sync_locked_acquisition_no_duplicates_no_skips(board):
    """0x2301 sub 1 = 1: one scan per SYNC. At 200 SYNC/s for 2 s every
    TPDO2 carries a sample counter one above the previous one (no sample
    sent twice, none skipped) and TPDO3 carries the sample time 0x2020,
    whose steps follow the SYNC period."""
    sdo = board.node.sdo
    sdo[0x2301][1].raw = 1
    # TPDO3: normal x and the sample time
    remap_tpdo(sdo, 3, TPDO3, [(0x2001, 1, 32), (0x2020, 0, 32)])
    t2, t3 = frames_of(board, TPDO2), frames_of(board, TPDO3)
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.1)
    drain(t2)
    drain(t3)
    period = 0.005
    board.network.sync.start(period)
    time.sleep(2.0)
    board.network.sync.stop()
    time.sleep(0.1)
    counters = [struct.unpack_from("<I", d, 4)[0] for d, _ in drain(t2)]
    times = [struct.unpack_from("<I", d, 4)[0] for d, _ in drain(t3)]
    missed = sdo[0x2301][2].raw
    board.node.nmt.state = "PRE-OPERATIONAL"
    assert len(counters) > 250, len(counters)
    steps = [b - a for a, b in zip(counters, counters[1:])]
    assert set(steps) == {1}, sorted(set(steps))
    assert missed == 0
    dt = [(b - a) & 0xFFFFFFFF for a, b in zip(times, times[1:])]
    mean = sum(dt) / len(dt)
    assert abs(mean - period * 1e6) < 0.1 * period * 1e6, mean
    # without SYNC no sample is taken
    before = sdo[0x2007].raw
    time.sleep(0.2)
    assert sdo[0x2007].raw == before


def heartbeats(board, node, stop, period=0.05):
    def run():
        while not stop.is_set():
            board.network.send_message(0x700 + node, b"\x05")
            time.sleep(period)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def test_heartbeat_consumer_and_error_behaviour(board):
    """0x1016 consumes the controller's heartbeat (node 0x7F, 200 ms): when
    it stops, EMCY 0x8130 names the node and 0x1029 sub 1 = 0 takes the
    board from operational to pre-operational; when it returns, the error
    is reset. A second consumer of the same node is refused."""
    sdo = board.node.sdo
    sdo[0x1016][1].raw = (0x7F << 16) | 200
    assert abort_code(lambda: sdo.download(0x1016, 2, struct.pack("<I", (0x7F << 16) | 300))) == 0x06040043
    assert sdo[0x1029][1].raw == 0
    e = frames_of(board, EMCY)
    stop = threading.Event()
    t = heartbeats(board, 0x7F, stop)
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.6)
    assert not [d for d, _ in drain(e) if d[:2] == b"\x30\x81"]
    stop.set()
    t.join()
    time.sleep(0.5)
    lost = [d for d, _ in drain(e) if d[:2] == b"\x30\x81"]
    assert len(lost) == 1 and lost[0][3] == 0x7F, lost
    assert wait_until(lambda: sdo[0x1001].raw & 0x10 == 0x10)
    sdo[0x1017].raw = 100
    assert board.node.nmt.wait_for_heartbeat(3) == "PRE-OPERATIONAL"
    stop2 = threading.Event()
    t2 = heartbeats(board, 0x7F, stop2)
    time.sleep(0.3)
    stop2.set()
    t2.join()
    resets = [d for d, _ in drain(e) if d[:2] == b"\x00\x00" and d[3:5] == b"\x30\x81"]
    assert len(resets) == 1, resets


def test_rpdo_triggers_a_capture(board):
    """The command RPDO (0x200 + node-id, one byte: 1 = capture) averages
    the next 0x2501 samples into 0x2502; TPDO4 of type 254 mapping the
    captured angles and the capture counter goes out once when it is
    done."""
    sdo = board.node.sdo
    assert sdo[0x1400][1].raw == 0x200 + NODE_ID
    sdo[0x2501].raw = 20
    remap_tpdo(sdo, 4, TPDO4, [(0x2502, 1, 32), (0x2502, 7, 16)], trans_type=254)
    t4 = frames_of(board, TPDO4)
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.2)
    drain(t4)
    board.network.send_message(0x200 + NODE_ID, b"\x01")
    assert wait_until(lambda: not t4.empty(), 2.0), "no TPDO4 after the capture"
    time.sleep(0.2)
    got = drain(t4)
    assert len(got) == 1, got
    theta1, count = struct.unpack("<fH", got[0][0])
    assert count == 1
    assert abs(theta1 - expected_thetas()[0]) < 0.01, theta1
    assert sdo[0x2502][6].raw == 20
    assert sdo[0x2500].raw == 0
