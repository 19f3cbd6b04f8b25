"""Fixtures of the peer tests: a virtual board (`perpend board`) started on
a free loopback port, and a python-canopen master connected to it through
python-can's slcan interface (``socket://127.0.0.1:PORT``).

Environment:
    PERPEND_BIN   path of the `perpend` binary (default: the workspace's
                  ``$CARGO_TARGET_DIR/debug/perpend`` or ``target/debug/perpend``)
"""

import logging
import os
import pathlib
import queue
import subprocess
import threading
import traceback

import canopen
import pytest
from canopen.sdo.exceptions import SdoAbortedError

ROOT = pathlib.Path(__file__).resolve().parents[2]
EDS = ROOT / "perpend.eds"
NODE_ID = 0x10
PLANE = (0.035, -0.052, 1.0, -40.0)
START_TIMEOUT_S = 20.0


def perpend_bin() -> str:
    if os.environ.get("PERPEND_BIN"):
        return os.environ["PERPEND_BIN"]
    target = os.environ.get("CARGO_TARGET_DIR", str(ROOT / "target"))
    return str(pathlib.Path(target) / "debug" / "perpend")


class RawSdo:
    """Sends hand-made SDO request frames and returns the raw responses, for
    requests the canopen client cannot be made to send (bad toggle, block
    transfer, stalled transfers)."""

    def __init__(self, network: canopen.Network, node_id: int):
        self.network = network
        self.node_id = node_id
        self.responses: "queue.Queue[bytes]" = queue.Queue()
        network.subscribe(0x580 + node_id, self._on_response)

    def _on_response(self, can_id, data, timestamp):
        self.responses.put(bytes(data))

    def request(self, data: bytes, timeout: float = 1.0):
        """Sends `data` (8 bytes) and returns the response, or None."""
        while not self.responses.empty():
            self.responses.get_nowait()
        self.network.send_message(0x600 + self.node_id, bytes(data))
        return self.wait(timeout)

    def wait(self, timeout: float):
        try:
            return self.responses.get(timeout=timeout)
        except queue.Empty:
            return None


def connect_master(port: int) -> canopen.Network:
    """A python-canopen master on the slcan-over-TCP port of a board."""
    network = canopen.Network()
    network.connect(interface="slcan", channel=f"socket://127.0.0.1:{port}", sleep_after_open=0)
    return network


def abort_code(fn) -> int:
    """The abort code of the ``SdoAbortedError`` that ``fn`` raises.

    python-canopen (2.4) leaves the aborted transfer's stream half open,
    referenced from the exception's traceback. When the garbage collector
    finalises it later, in the middle of another transfer, its ``close()``
    sends an end segment while the network's send lock is held, and the
    master stalls (seen: 180 s for a test that takes 2 s, depending on
    which test ran before). Its frames are cleared here, so it is finalised
    now, between transfers."""
    with pytest.raises(SdoAbortedError) as e:
        fn()
    code = e.value.code
    traceback.clear_frames(e.value.__traceback__)
    del e
    return code


class Board:
    """A running virtual board and a master connected to it."""

    def __init__(self, *args: str, node_id: int = NODE_ID, plane=PLANE):
        self.node_id = node_id
        self.plane = plane
        cmd = [
            perpend_bin(),
            "board",
            "--slcan",
            "127.0.0.1:0",
            "--node-id",
            str(node_id),
            "--plane",
            ",".join(repr(float(x)) for x in plane),
            *args,
        ]
        self._start(cmd)
        self.node = self.network.add_node(node_id, str(EDS))
        self.raw = RawSdo(self.network, node_id)

    def _start(self, cmd):
        """Starts `cmd` (a `perpend board`), reads its port from the first
        stdout line ("perpend board: ... on 127.0.0.1:PORT") and connects a
        master to it."""
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
        line = self._first_line()
        self.port = int(line.rsplit(":", 1)[1])
        self.network = connect_master(self.port)

    def release(self):
        """Disconnects the master: the virtual board serves one client, so
        a `perpend node` command can run only while python lets go."""
        self.network.disconnect()

    def reconnect(self):
        """Connects the master again after :meth:`release` (with the node
        added again where the board has a node-id, and a 50 ms LSS window)."""
        self.network = connect_master(self.port)
        self.network.lss.RESPONSE_TIMEOUT = 0.05
        if 1 <= self.node_id <= 127:
            self.node = self.network.add_node(self.node_id, str(EDS))
            self.raw = RawSdo(self.network, self.node_id)

    def perpend(self, *args: str, node_id: bool = True, timeout: float = 60.0) -> subprocess.CompletedProcess:
        """Runs `perpend node ARGS --bus tcp:127.0.0.1:PORT [--node-id N]`
        (the link options last: they are global) with the master released,
        and connects it again afterwards."""
        link = ["--bus", f"tcp:127.0.0.1:{self.port}"]
        if node_id:
            link += ["--node-id", str(self.node_id)]
        self.release()
        try:
            return subprocess.run(
                [perpend_bin(), "--quiet", "node", *args, *link],
                capture_output=True, text=True, timeout=timeout, check=False,
            )
        finally:
            self.reconnect()

    def bootup_queue(self, node_id=None) -> "queue.Queue[float]":
        """A queue that receives the time of every boot-up message of
        `node_id` (default: the board's), subscribed from now on."""
        q: "queue.Queue[float]" = queue.Queue()

        def on_frame(can_id, data, timestamp):
            if len(data) == 1 and data[0] == 0:
                q.put(timestamp)

        self.network.subscribe(0x700 + (node_id or self.node_id), on_frame)
        return q

    def nmt_reset(self, command=0x81, expect_node=None, timeout=5.0):
        """Sends NMT reset node (0x81) or reset communication (0x82) and
        waits for the boot-up message (of `expect_node`, default the
        board's node-id); the listener is in place before the command."""
        q = self.bootup_queue(expect_node)
        self.network.send_message(0, bytes([command, self.node_id]))
        try:
            q.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"no boot-up after NMT {command:#x}") from None

    def _first_line(self) -> str:
        out = []
        t = threading.Thread(target=lambda: out.append(self.proc.stdout.readline()))
        t.daemon = True
        t.start()
        t.join(START_TIMEOUT_S)
        if not out or not out[0].startswith("perpend board:"):
            self.proc.kill()
            self.proc.wait(5)
            self.proc.stdout.close()
            raise RuntimeError(f"perpend board did not start: {out!r}")
        return out[0].strip()

    def close(self):
        try:
            self.network.disconnect()
        finally:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
            if self.proc.stdout:
                self.proc.stdout.close()


@pytest.fixture
def board(request):
    """A board with the default plane; extra arguments from the
    ``board_args`` marker."""
    marker = request.node.get_closest_marker("board_args")
    args = marker.args if marker else ()
    b = Board(*args)
    try:
        yield b
    finally:
        b.close()


@pytest.fixture
def canopen_warnings():
    """Collects WARNING (and worse) log records of canopen and can."""
    records = []

    class Handler(logging.Handler):
        def emit(self, record):
            if record.levelno >= logging.WARNING and record.name.split(".")[0] in ("canopen", "can"):
                records.append(record)

    h = Handler()
    root = logging.getLogger()
    root.addHandler(h)
    try:
        yield records
    finally:
        root.removeHandler(h)


class Cell(Board):
    """Several virtual boards on one bus behind one slcan port (`perpend
    board --serial S1 --serial S2 ...`, a cell of heads) and a master
    without nodes (LSS commissioning adds them)."""

    def __init__(self, serials, *args: str, node_id: int = 0xFF):
        self.serials = list(serials)
        self.node_id = node_id
        cmd = [perpend_bin(), "board", "--slcan", "127.0.0.1:0", "--node-id", str(node_id)]
        for s in self.serials:
            cmd += ["--serial", hex(s)]
        self._start([*cmd, *args])
        # A board answers within a millisecond: no need for canopen's 0.5 s
        # per unanswered fastscan step.
        self.network.lss.RESPONSE_TIMEOUT = 0.05


class Recorder:
    """Every frame the master receives from now on: (can_id, data)."""

    def __init__(self, network: canopen.Network):
        self.frames: "queue.Queue[tuple[int, bytes]]" = queue.Queue()
        import can  # noqa: PLC0415 (python-can, a canopen dependency)

        rec = self

        class _L(can.Listener):
            def on_message_received(self, msg):
                rec.frames.put((msg.arbitration_id, bytes(msg.data)))

        self.listener = _L()
        network.notifier.add_listener(self.listener)

    def drain(self):
        out = []
        while not self.frames.empty():
            out.append(self.frames.get_nowait())
        return out
