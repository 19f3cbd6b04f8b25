"""`perpend node sdo` and `perpend eds` checked by a second master: what
`perpend node sdo write` writes, python-canopen reads back with its own SDO
client (and the reverse); the EDS `perpend eds` prints, python-canopen's
importer reads as the same dictionary as the committed perpend.eds."""

import configparser
import json
import struct
import subprocess

import canopen

from conftest import EDS, perpend_bin


def node_cmd(board, *args: str) -> subprocess.CompletedProcess:
    """`perpend node ARGS` on the board, python's master released meanwhile
    (the virtual board serves one client at a time)."""
    return board.perpend(*args, timeout=30)


def ok(r: subprocess.CompletedProcess) -> str:
    assert r.returncode == 0, f"{r.args}\n{r.stdout}\n{r.stderr}"
    return r.stdout


def test_sdo_write_is_what_canopen_uploads(board):
    out = ok(node_cmd(board, "sdo", "write", "0x1017", "0", "250"))
    assert "→ 250" in out, out
    assert board.node.sdo.upload(0x1017, 0) == (250).to_bytes(2, "little")
    ok(node_cmd(board, "sdo", "write", "0x2300", "4", "0.2"))
    (limit,) = struct.unpack("<f", board.node.sdo.upload(0x2300, 4))
    assert limit == struct.unpack("<f", struct.pack("<f", 0.2))[0]


def test_sdo_read_shows_what_canopen_downloads(board):
    board.node.sdo.download(0x2009, 1, struct.pack("<f", 0.5))
    v = json.loads(ok(node_cmd(board, "sdo", "read", "0x2009", "1", "--json")))
    assert v["schema"] == "perpend.sdo/1"
    assert (v["value"], v["type"], v["unit"], v["raw_hex"]) == (0.5, "REAL32", "deg", "00 00 00 3f")


def test_a_refused_write_sends_nothing(board):
    before = board.node.sdo.upload(0x2300, 4)
    r = node_cmd(board, "sdo", "write", "0x2300", "4", "200")
    assert r.returncode == 1 and "outside the EDS limits" in r.stderr, r.stderr
    assert board.node.sdo.upload(0x2300, 4) == before


def described(od: canopen.ObjectDictionary):
    """Every entry as (index, sub, name, type, access, min, max, default)."""
    rows = []
    for index in od:
        obj = od[index]
        subs = [obj] if isinstance(obj, canopen.objectdictionary.ODVariable) else [obj[s] for s in obj]
        for v in subs:
            rows.append((index, v.subindex, v.name, v.data_type, v.access_type, v.min, v.max, v.default))
    return rows


def test_perpend_eds_imports_as_the_committed_file(tmp_path):
    out = tmp_path / "printed.eds"
    subprocess.run([perpend_bin(), "eds", "--out", str(out)], check=True)
    printed = canopen.import_od(str(out), node_id=0x10)
    committed = canopen.import_od(str(EDS), node_id=0x10)
    assert described(printed) == described(committed)
    ini = configparser.ConfigParser()
    ini.read(EDS)
    listed = sorted(
        int(v, 16)
        for s in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects")
        for k, v in ini[s].items()
        if k != "supportedobjects"
    )
    assert sorted(printed) == listed
