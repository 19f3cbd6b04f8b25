"""`perpend node lss` (the host tool's LSS master) against a virtual cell,
checked with python-canopen: the node-ids it gives are the ones the heads
answer SDO and LSS at, and what it lists is what python-canopen's fastscan
finds. The slcan server takes one client at a time, so the python master
disconnects while the `perpend` binary runs (`Cli.run`)."""

import json
import subprocess
import time

import canopen
from canopen.lss import LssMaster

from conftest import EDS, Board, Cell, Recorder, perpend_bin

SERIALS = [0x0C0FFEE3, 0x00000042, 0x80000001]
SERIAL_CS = 0x5D


def run_cli(board: Board, *args: str) -> str:
    """Runs `perpend node <args> --bus tcp:…` (no node-id) with the master
    released; returns stdout (asserting success)."""
    out = board.perpend(*args, node_id=False)
    assert out.returncode == 0, f"{args}: {out.stdout}\n{out.stderr}"
    return out.stdout


class MixedCell(Board):
    """A cell with per-head node-ids: `--serial S[:NODEID]` entries."""

    def __init__(self, *serials: str):
        self.node_id = 0xFF
        cmd = [perpend_bin(), "board", "--slcan", "127.0.0.1:0", "--node-id", "0xFF"]
        for s in serials:
            cmd += ["--serial", s]
        self._start(cmd)
        self.network.lss.RESPONSE_TIMEOUT = 0.05


def sdo_serial(board: Board, node_id: int) -> int:
    node = board.network.add_node(node_id, str(EDS))
    return int.from_bytes(node.sdo.upload(0x1018, 4), "little")


def test_lss_cli_scan_lists_and_assigns_what_python_canopen_sees():
    cell = Cell(SERIALS, node_id=0xFF)
    try:
        listed = json.loads(run_cli(cell, "lss", "scan", "--json"))
        assert [n["serial"] for n in listed["nodes"]] == sorted(SERIALS)
        assert all(n["node_id"] is None for n in listed["nodes"])
        # Listing leaves them non-configured, in waiting state: python's
        # fastscan still finds the smallest.
        ok, ident = cell.network.lss.fast_scan()
        assert ok and ident[3] == min(SERIALS)
        cell.network.lss.send_switch_state_global(LssMaster.WAITING_STATE)
        out = run_cli(cell, "lss", "scan", "--assign", "0x10", "--store")
        for k, s in enumerate(sorted(SERIALS)):
            assert f"serial {s:#010x} -> node-id {0x10 + k}" in out, out
        assert cell.network.lss.fast_scan() == (False, None), "none left"
        # Stored: after a reset node every head boots at its node-id.
        rec = Recorder(cell.network)
        cell.network.send_message(0, bytes([0x81, 0]))
        time.sleep(0.5)
        boots = sorted(i - 0x700 for i, d in rec.drain() if 0x701 <= i <= 0x77F and d == b"\x00")
        assert boots == [0x10, 0x11, 0x12]
        for k, s in enumerate(sorted(SERIALS)):
            assert sdo_serial(cell, 0x10 + k) == s
    finally:
        cell.close()


def test_lss_cli_set_node_id_by_serial_is_what_lss_inquires():
    cell = MixedCell("0x101:16", "0x102:17", hex(SERIALS[0]))
    try:
        out = run_cli(cell, "lss", "set-node-id", "0x30", "--serial", "0x101", "--store", "--reset")
        assert "node-id 16 -> 48 (stored)" in out and "node 48 started" in out, out
        assert sdo_serial(cell, 0x30) == 0x101
        lss = cell.network.lss
        vendor, product, revision = (
            int.from_bytes(cell.network.add_node(0x30, str(EDS)).sdo.upload(0x1018, k), "little")
            for k in (1, 2, 3)
        )
        assert lss.send_switch_state_selective(vendor, product, revision, 0x101)
        assert lss.inquire_node_id() == 0x30
        lss.send_switch_state_global(LssMaster.WAITING_STATE)
        # The non-configured head, by serial: it starts at once.
        out = run_cli(cell, "lss", "set-node-id", "0x31", "--serial", hex(SERIALS[0]))
        assert "node 49 started" in out, out
        assert sdo_serial(cell, 0x31) == SERIALS[0]
        # inquire --node-id reads what python-canopen's LSS inquiry says.
        v = json.loads(run_cli(cell, "--node-id", "17", "lss", "inquire", "--json"))
        assert (v["serial"], v["node_id"]) == (0x102, 17)
        lss = cell.network.lss  # the master connected again
        assert lss.send_switch_state_selective(vendor, product, revision, 0x102)
        assert lss.inquire_lss_address(SERIAL_CS) == 0x102
        lss.send_switch_state_global(LssMaster.WAITING_STATE)
    finally:
        cell.close()
