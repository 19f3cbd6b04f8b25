"""Peer tests of five CiA 301 conformance fixes of perpend-can, as seen on
the bus by a python-canopen master:

1. one EMCY per error event with more than eight errors active at once
   (thirteen, what the board can reach: four loop-current faults of
   ``--fault``, no plane, an invalid configuration written over SDO that
   adds the four reading codes and 0x6300, a lost heartbeat, a SYNC of the
   wrong length and an empty RPDO);
2. the EDS declares as many RPDOs/TPDOs as it describes;
3. 0x1029 sub 1 = 2 stops a pre-operational node on a heartbeat timeout;
4. a TPDO COB-ID that allows remote frames (bit 30 = 0) is refused;
5. a SYNC of the wrong length sends no TPDO and raises EMCY 0x8240.

Not provoked from the bus: more codes than the device's table holds (16),
the overflow path; the unit test `emcy_beyond_the_table_never_floods`
covers it.
"""

import collections
import configparser
import re
import struct
import time

import canopen
import pytest

from conftest import EDS, NODE_ID, Recorder
from test_peer import abort_code, wait_until

EMCY = 0x80 + NODE_ID
TPDO1 = 0x180 + NODE_ID
RPDO1 = 0x200 + NODE_ID
UNLOCK = 0x6C616375  # "ucal"
CONTROLLER = 0x7F  # node-id of the (simulated) heartbeat producer


def emcy_codes(frames):
    """The error codes of the EMCY frames among `frames` ((id, data))."""
    return [struct.unpack_from("<H", d)[0] for i, d in frames if i == EMCY]


def after_bootup(frames):
    """The frames after the board's last boot-up message: EMCYs it sent
    before an NMT reset can reach a loaded master after the recorder
    started (seen in CI), and the bus keeps their order."""
    boots = [k for k, (i, d) in enumerate(frames) if i == 0x700 + NODE_ID and d == b"\x00"]
    return frames[boots[-1] + 1 :] if boots else []


@pytest.mark.board_args(
    "--fault", "1:open", "--fault", "2:overcurrent", "--fault", "3:open", "--fault", "4:overcurrent"
)
def test_one_emcy_per_error_with_thirteen_active(board):
    """Thirteen distinct errors active at once, the sensor ones re-checked
    on every sample: four loop-current faults and no plane; an invalid
    configuration (0x6300) that makes every sensor reading invalid (four
    reading codes, overlapping the current codes for the board's clear
    delay); a lost heartbeat, a SYNC of the wrong length and an empty RPDO.
    Each code is sent exactly once; the only error resets are those of the
    four current codes, once their condition has been gone for the clear
    delay."""
    sdo = board.node.sdo
    rec = Recorder(board.network)
    # Reset node: the errors raised before the recorder are cleared and
    # raised again, now on record.
    board.nmt_reset(0x81)
    sdo[0x1029][1].raw = 1  # no state change on communication errors
    sdo[0x1016][1].raw = (CONTROLLER << 16) | 100
    board.network.send_message(0x700 + CONTROLLER, b"\x7f")  # then silence
    board.network.send_message(0x80, b"\x01")  # 0x1019 = 0: DLC must be 0
    # sensor 3's beam direction zeroed: configuration invalid
    sdo[0x2010].raw = UNLOCK
    for sub in (4, 5, 6):
        sdo[0x2103][sub].raw = 0.0
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.1)
    board.network.send_message(RPDO1, b"")  # empty command RPDO
    frames = []

    def resets():
        frames.extend(rec.drain())
        return [d for i, d in after_bootup(frames) if i == EMCY and d[:2] == b"\x00\x00"]

    assert wait_until(lambda: len(resets()) >= 4, 10.0), emcy_codes(frames)
    time.sleep(0.5)  # a flood would show here
    frames.extend(rec.drain())
    codes = [c for c in emcy_codes(after_bootup(frames)) if c != 0]
    currents = {0x2111, 0x2112, 0x2113, 0x2114}
    want = currents | {0xFF11, 0xFF12, 0xFF13, 0xFF14, 0xFF02, 0x6300, 0x8130, 0x8240, 0x8210}
    trace = [(hex(i), d.hex()) for i, d in frames if i != TPDO1]
    assert sorted(codes) == sorted(want), ([hex(c) for c in codes], trace)
    cleared = {struct.unpack_from("<H", d, 3)[0] for d in resets()}
    assert len(resets()) == 4 and cleared == currents, resets()
    # generic | communication | manufacturer (the current bit is gone)
    assert sdo[0x1001].raw == 0x91
    board.node.nmt.state = "PRE-OPERATIONAL"


def test_eds_pdo_counts_match_its_objects(board):
    """NrOfRXPDO / NrOfTXPDO equal the PDO communication objects the EDS
    describes (configparser and python-canopen's import agree), and the
    board answers for them."""
    cp = configparser.ConfigParser()
    cp.optionxform = str
    cp.read(EDS)
    sections = [s for s in cp.sections() if re.fullmatch(r"[0-9A-F]{4}", s)]
    rx = [s for s in sections if 0x1400 <= int(s, 16) <= 0x15FF]
    tx = [s for s in sections if 0x1800 <= int(s, 16) <= 0x19FF]
    assert int(cp["DeviceInfo"]["NrOfRXPDO"]) == len(rx) == 1
    assert int(cp["DeviceInfo"]["NrOfTXPDO"]) == len(tx) == 4
    od = canopen.import_od(str(EDS), NODE_ID)
    assert [i for i in od.indices if 0x1400 <= i <= 0x15FF] == [int(s, 16) for s in rx]
    assert board.node.sdo[0x1400][1].raw == RPDO1


def test_error_behaviour_stopped_from_pre_operational(board):
    """0x1029 sub 1 = 2: a heartbeat timeout of a consumed node stops the
    board although it is pre-operational; EMCY 0x8130 goes out first."""
    sdo = board.node.sdo
    sdo[0x1017].raw = 100
    sdo[0x1029][1].raw = 2
    sdo[0x1016][1].raw = (CONTROLLER << 16) | 200
    assert board.node.nmt.wait_for_heartbeat(3) == "PRE-OPERATIONAL"
    rec = Recorder(board.network)
    board.network.send_message(0x700 + CONTROLLER, b"\x7f")  # then silence
    time.sleep(0.5)
    assert 0x8130 in emcy_codes(rec.drain())
    assert board.node.nmt.wait_for_heartbeat(3) == "STOPPED"
    board.node.nmt.state = "PRE-OPERATIONAL"


def test_tpdo_cob_id_allowing_rtr_is_refused(board):
    """The board answers no remote frame: making TPDO1 valid with bit 30 = 0
    is refused with 0x06090030 and leaves the COB-ID; with bit 30 it works."""
    sdo = board.node.sdo
    assert sdo[0x1800][1].raw == 0x40000000 | TPDO1
    sdo[0x1800][1].raw = 0xC0000000 | TPDO1
    code = abort_code(lambda: sdo.download(0x1800, 1, struct.pack("<I", TPDO1)))
    assert code == 0x06090030, hex(code)
    assert sdo[0x1800][1].raw == 0xC0000000 | TPDO1
    sdo[0x1800][1].raw = 0x40000000 | TPDO1
    assert sdo[0x1800][1].raw == 0x40000000 | TPDO1


def test_rpdo_cob_id_bit_30_is_dont_care(board):
    """RPDO COB-ID bit 30 is reserved (CiA 301: don't care): accepted either
    way, as CANopenNode does; the RPDO still works on the new identifier."""
    sdo = board.node.sdo
    rpdo = 0x200 + NODE_ID
    sdo[0x1400][1].raw = 0x40000000 | rpdo
    assert sdo[0x1400][1].raw == 0x40000000 | rpdo
    sdo[0x1400][1].raw = 0xC0000000 | rpdo
    sdo[0x1400][1].raw = 0x40000000 | 0x220
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.1)
    board.network.send_message(0x220, bytes([1]))  # capture
    assert wait_until(lambda: sdo[0x2502][7].raw >= 1, 3.0), "no capture from the RPDO"
    board.node.nmt.state = "PRE-OPERATIONAL"


def test_sync_of_wrong_length_is_ignored(board):
    """0x1019 = 0: a SYNC with a data byte sends no TPDO and raises EMCY
    0x8240; the next SYNC without data sends TPDO1 (type 1) again."""
    rec = Recorder(board.network)
    board.node.nmt.state = "OPERATIONAL"
    time.sleep(0.2)
    rec.drain()
    board.network.send_message(0x80, b"\x05")
    time.sleep(0.2)
    got = rec.drain()
    assert not [d for i, d in got if i == TPDO1], got
    assert emcy_codes(got) == [0x8240], got
    board.network.send_message(0x80, b"")
    assert wait_until(lambda: any(i == TPDO1 for i, _ in rec.drain()), 1.0)
    board.node.nmt.state = "PRE-OPERATIONAL"
