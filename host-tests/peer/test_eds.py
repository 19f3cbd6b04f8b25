"""The EDS (perpend.eds, written by perpend-can's eds.rs) read by a second
parser: CanFestival's objdictgen (pinned in requirements.txt). It must load
and validate without an error or a warning, generate CanFestival's C object
dictionary, and agree with python-canopen's reading (test_peer.py checks
that one) on every object, sub-index and data type."""

import logging
import sys

import canopen
import pytest

from conftest import EDS, NODE_ID

if sys.version_info < (3, 10):
    pytest.skip("objdictgen needs Python >= 3.10", allow_module_level=True)

from objdictgen.node import Node  # noqa: E402


@pytest.fixture
def odg_log():
    """Every log record objdictgen emits (it reports problems by logging)."""
    records = []

    class Handler(logging.Handler):
        def emit(self, record):
            records.append(record)

    h = Handler(level=logging.DEBUG)
    logger = logging.getLogger("objdictgen")
    old = logger.level
    logger.setLevel(logging.DEBUG)
    logger.addHandler(h)
    try:
        yield records
    finally:
        logger.removeHandler(h)
        logger.setLevel(old)


def problems(records):
    return [f"{r.levelname}: {r.getMessage()}" for r in records if r.levelno >= logging.WARNING]


def test_objdictgen_loads_and_validates_the_eds(odg_log):
    node = Node.LoadFile(EDS)
    node.Validate()
    assert problems(odg_log) == []
    assert node.GetEntry(0x1018)[1] == int(EDS.read_text().split("VendorNumber=")[1].split()[0], 16)


def test_objdictgen_generates_the_canfestival_dictionary(odg_log, tmp_path):
    node = Node.LoadFile(EDS)
    # The C identifier is the integrator's choice (objdictedit asks for it);
    # by default objdictgen takes ProductName, free text in CiA 306.
    node.Name = "perpend"
    node.DumpFile(tmp_path / "perpend.c", filetype="c")
    c = (tmp_path / "perpend.c").read_text()
    assert problems(odg_log) == []
    for index in node.GetIndexes():
        assert f"/* index 0x{index:04X} :" in c, f"{index:#06x} missing from the C dictionary"


def test_both_parsers_read_the_same_dictionary():
    node = Node.LoadFile(EDS)
    od = canopen.import_od(str(EDS), node_id=NODE_ID)
    assert sorted(node.GetIndexes()) == sorted(obj.index for obj in od.values())
    for obj in od.values():
        subs = [obj] if isinstance(obj, canopen.objectdictionary.ODVariable) else obj.values()
        for var in subs:
            info = node.GetSubentryInfos(var.index, var.subindex)
            assert info is not None, (hex(var.index), var.subindex)
            if var.index >= 0x2000:
                # objdictgen types the standard objects by its DS-301 profile
                assert info["type"] == var.data_type, (hex(var.index), var.subindex)


def test_objdictgen_refuses_real_limits_as_written_before(tmp_path):
    # The regression of issue 16: REAL32 limits in decimal notation. The
    # EDS now has them as comments only (CiA 306 makes the keys optional).
    text = EDS.read_text()
    limits = [ln.split("=", 1)[1] for ln in text.splitlines() if ln.startswith(("LowLimit=", "HighLimit="))]
    assert limits, "integer limits are still written"
    for v in limits:
        int(v, 0)  # a REAL limit would raise here
    assert ";Range=" in text, "REAL32 ranges are kept as comments"
    bad = text.replace("[2002sub1]\n", "[2002sub1]\nLowLimit=-1000.0\n", 1)
    path = tmp_path / "old.eds"
    path.write_text(bad)
    with pytest.raises(ValueError, match="LowLimit"):
        Node.LoadFile(path)
