"""LSS (CiA 305) against the virtual board, with python-canopen's LssMaster
(`network.lss`): every service on one board, bit-rate switching, and the
commissioning of a cell of four heads by fastscan (docs/can.md, "LSS
commissioning of a cell of four heads")."""

import queue
import time

import canopen
import pytest
from canopen.lss import LssError, LssMaster

from conftest import EDS, NODE_ID, Cell, Recorder

VENDOR, PRODUCT, REVISION, SERIAL = 0x5A, 0x5B, 0x5C, 0x5D


def lss_of(board):
    lss = board.network.lss
    lss.RESPONSE_TIMEOUT = 0.05
    return lss


def boot_ups(rec: Recorder, wait_s: float = 0.3):
    """Node-ids of the boot-up messages recorded after `wait_s`."""
    time.sleep(wait_s)
    return sorted(i - 0x700 for i, d in rec.drain() if 0x701 <= i <= 0x77F and d == b"\x00")


def test_inquire_services_answer_0x1018_and_the_node_id(board):
    lss = lss_of(board)
    with pytest.raises(LssError):
        lss.inquire_node_id()  # waiting state: no answer
    lss.send_switch_state_global(LssMaster.CONFIGURATION_STATE)
    assert lss.inquire_node_id() == NODE_ID
    for k, cs in enumerate((VENDOR, PRODUCT, REVISION, SERIAL), start=1):
        assert lss.inquire_lss_address(cs) == int.from_bytes(board.node.sdo.upload(0x1018, k), "little")
    lss.send_switch_state_global(LssMaster.WAITING_STATE)


def test_configure_node_id_becomes_active_at_reset_communication(board):
    lss = lss_of(board)
    lss.send_switch_state_global(LssMaster.CONFIGURATION_STATE)
    for bad in (0, 128, 0xFE):
        with pytest.raises(LssError, match="LSS Error: 1"):
            lss.configure_node_id(bad)
    lss.configure_node_id(0x22)
    assert lss.inquire_node_id() == NODE_ID, "pending until reset"
    lss.send_switch_state_global(LssMaster.WAITING_STATE)
    board.nmt_reset(0x82, expect_node=0x22)
    node = board.network.add_node(0x22, str(EDS))
    assert node.sdo.upload(0x2400, 1) == b"\x22"
    lss.send_switch_state_global(LssMaster.CONFIGURATION_STATE)
    assert lss.inquire_node_id() == 0x22


def test_configure_bit_timing_refuses_what_the_board_cannot_run(board):
    lss = lss_of(board)
    lss.send_switch_state_global(LssMaster.CONFIGURATION_STATE)
    for index in (0, 2, 3, 4):  # 1000, 500, 250, 125 kbit/s
        lss.configure_bit_timing(index)
    for index in (1, 5, 6, 7, 8, 9):  # 800, reserved, 50, 20, 10, auto
        with pytest.raises(LssError, match="LSS Error: 1"):
            lss.configure_bit_timing(index)


def test_activate_bit_timing_moves_the_board_to_500_kbit(board):
    bus = board.network.bus
    bus.set_bitrate(1_000_000)
    lss = lss_of(board)
    assert board.node.sdo.upload(0x1000, 0)
    lss.send_switch_state_global(LssMaster.CONFIGURATION_STATE)
    lss.configure_bit_timing(2)
    lss.activate_bit_timing(100)  # switch after 100 ms, silent for 200 ms
    time.sleep(0.3)
    board.node.sdo.RESPONSE_TIMEOUT = 0.3
    with pytest.raises(canopen.SdoCommunicationError):
        board.node.sdo.upload(0x1000, 0)  # the master is still at 1 Mbit/s
    bus.set_bitrate(500_000)
    assert board.node.sdo.upload(0x2400, 2) == (500).to_bytes(2, "little")
    lss.send_switch_state_global(LssMaster.WAITING_STATE)


def test_store_configuration_answers_success(board):
    lss = lss_of(board)
    lss.send_switch_state_global(LssMaster.CONFIGURATION_STATE)
    lss.configure_node_id(0x31)
    lss.store_configuration()  # raises LssError on a storage error
    lss.send_switch_state_global(LssMaster.WAITING_STATE)
    board.nmt_reset(0x81, expect_node=0x31)


def test_selective_switch_and_identify_pick_one_head_by_serial():
    cell = Cell([0x1001, 0x1002, 0x1003], node_id=0x20)
    try:
        lss = cell.network.lss
        lss.send_switch_state_global(LssMaster.CONFIGURATION_STATE)
        vendor = lss.inquire_lss_address(VENDOR)
        product = lss.inquire_lss_address(PRODUCT)
        revision = lss.inquire_lss_address(REVISION)
        lss.send_switch_state_global(LssMaster.WAITING_STATE)
        assert lss.send_switch_state_selective(vendor, product, revision, 0x1002)
        assert lss.inquire_lss_address(SERIAL) == 0x1002, "only the selected head answers"
        lss.send_switch_state_global(LssMaster.WAITING_STATE)
        # Identify remote slave: serials 0x1002..0x1003 answer, 0x1004.. none.
        lss.send_identify_remote_slave(vendor, product, 0, 0xFFFFFFFF, 0x1002, 0x1003)
        assert lss.responses.get(timeout=1)[0] == 0x4F
        lss.send_identify_remote_slave(vendor, product, 0, 0xFFFFFFFF, 0x1004, 0x2000)
        with pytest.raises(queue.Empty):
            lss.responses.get(timeout=0.3)
        # All are configured (node 0x20): none answers "non-configured".
        lss.send_identify_non_configured_remote_slave()
        with pytest.raises(queue.Empty):
            lss.responses.get(timeout=0.3)
    finally:
        cell.close()


def commission(cell: Cell, rec: Recorder, first_id: int = 0x10):
    """The commissioning of docs/can.md: fastscan, node-id, store, waiting;
    returns the serials in the order found."""
    lss = cell.network.lss
    found = []
    for k in range(len(cell.serials)):
        ok, ident = lss.fast_scan()
        assert ok, f"head {k}: no non-configured head answered"
        found.append(ident[3])
        # The head found is in configuration state, alone.
        assert lss.inquire_node_id() == 0xFF
        lss.configure_node_id(first_id + k)
        lss.store_configuration()
        rec.drain()
        lss.send_switch_state_global(LssMaster.WAITING_STATE)
        assert boot_ups(rec) == [first_id + k], "it starts at once with its node-id"
    assert lss.fast_scan() == (False, None), "no head left to configure"
    return found


def check_cell(cell: Cell, rec: Recorder, ids, serials):
    """Reset node to all: every head boots with its stored node-id and
    answers SDO with its serial."""
    rec.drain()
    cell.network.send_message(0, bytes([0x81, 0]))
    assert boot_ups(rec, 0.5) == list(ids)
    for node_id, serial in zip(ids, serials):
        node = cell.network.add_node(node_id, str(EDS))
        assert node.sdo.upload(0x1018, 4) == serial.to_bytes(4, "little")
        assert node.sdo.upload(0x2400, 1) == bytes([node_id])


SERIALS = [0x0C0FFEE3, 0x00000042, 0x8000_0001, 0x0C0FFEE1]


def test_commissioning_four_non_configured_heads_by_fastscan():
    cell = Cell(SERIALS, node_id=0xFF)
    try:
        rec = Recorder(cell.network)
        time.sleep(0.5)
        assert rec.drain() == [], "a non-configured head sends nothing"
        found = commission(cell, rec)
        assert found == sorted(SERIALS), "fastscan finds the smallest identity first"
        check_cell(cell, rec, range(0x10, 0x14), found)
    finally:
        cell.close()


def test_commissioning_four_heads_shipped_at_the_same_node_id():
    cell = Cell(SERIALS, node_id=0x20)
    try:
        lss = cell.network.lss
        rec = Recorder(cell.network)
        # All four: forget the node-id (0xFF), store, restart unconfigured.
        lss.send_switch_state_global(LssMaster.CONFIGURATION_STATE)
        lss.configure_node_id(0xFF)
        lss.store_configuration()
        lss.send_switch_state_global(LssMaster.WAITING_STATE)
        rec.drain()
        cell.network.send_message(0, bytes([0x82, 0]))
        time.sleep(0.3)
        assert [f for f in rec.drain() if f[0] != 0x7E4] == [], "unconfigured: silent"
        found = commission(cell, rec)
        check_cell(cell, rec, range(0x10, 0x14), found)
    finally:
        cell.close()
