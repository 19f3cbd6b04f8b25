"""Acquisition-to-frame latency of the virtual board, measured by the board.

Start `perpend board --slcan 127.0.0.1:29555 --node-id 16 --plane 0.035,-0.052,1,-40`,
then run this with the peer venv's Python: it starts the node, sends SYNC at
1 kHz for 5 s and counts TPDO 1 frames; when it disconnects the board prints
the latency distribution (sample acquired -> TPDO 1 handed to the socket) on
stderr. A measurement, not a test.
"""
import can, time
bus = can.interface.Bus(interface="slcan", channel="socket://127.0.0.1:29555", bitrate=1000000)
bus.send(can.Message(arbitration_id=0x000, data=[0x01, 16], is_extended_id=False))
time.sleep(0.2)
t0 = time.perf_counter(); n = 0; rx = 0
next_t = t0
while time.perf_counter() - t0 < 5.0:
    now = time.perf_counter()
    if now >= next_t:
        bus.send(can.Message(arbitration_id=0x080, data=[], is_extended_id=False)); n += 1
        next_t += 0.001
    m = bus.recv(timeout=0)
    while m is not None:
        if m.arbitration_id == 0x190: rx += 1
        m = bus.recv(timeout=0)
time.sleep(0.2)
while bus.recv(timeout=0.05) is not None: pass
bus.shutdown()
print("SYNC sent", n, "TPDO1 received", rx)
