"""SDO block download (CiA 301 §7.2.4.3.10) against the virtual board with
python-canopen's block transfer client: a program image through 0x1F50
(CiA 302-3 program data), checked by 0x1F56 (identification: CRC-16-CCITT
in bits 0..15, length in KiB in bits 16..31 with the board's RAM program
store) and 0x1F57 (flash status), started with 0x1F51; block upload is not
implemented and is refused with 0x05040001, and the same object reads by
segmented upload.
"""

import binascii
import struct

import canopen
import pytest

PROGRAM_DATA = 0x1F50
PROGRAM_CONTROL = 0x1F51
IDENT = 0x1F56
FLASH_STATUS = 0x1F57


def image(n: int) -> bytes:
    return bytes((i * 13 + 5) & 0xFF for i in range(n))


def identification(data: bytes) -> int:
    # binascii.crc_hqx is CRC-16-CCITT with polynomial 0x1021, like the
    # block transfer's CRC.
    return ((len(data) + 1023) // 1024) << 16 | binascii.crc_hqx(data, 0)


def block_download(node, data: bytes):
    with node.sdo.open(PROGRAM_DATA, 1, "wb", block_transfer=True, size=len(data),
                       request_crc_support=True) as f:
        f.write(data)


@pytest.mark.parametrize("size", [1, 889, 889 * 3 + 5, 20000])
def test_program_image_by_block_download(board, size):
    data = image(size)
    block_download(board.node, data)
    sdo = board.node.sdo
    assert sdo[IDENT][1].raw == identification(data)
    assert sdo[FLASH_STATUS][1].raw == 0
    sdo[PROGRAM_CONTROL][1].raw = 1
    assert sdo[PROGRAM_CONTROL][1].raw == 1


def test_segmented_download_still_works(board):
    data = image(1500)
    with board.node.sdo.open(PROGRAM_DATA, 1, "wb", size=len(data)) as f:
        f.write(data)
    assert board.node.sdo[IDENT][1].raw == identification(data)


def test_program_download_refused_in_operational(board):
    board.node.nmt.state = "OPERATIONAL"
    with pytest.raises(canopen.SdoAbortedError) as e:
        block_download(board.node, image(100))
    assert e.value.code == 0x08000022


def test_start_without_program_and_clear(board):
    sdo = board.node.sdo
    assert sdo[FLASH_STATUS][1].raw == 2  # no valid program
    with pytest.raises(canopen.SdoAbortedError) as e:
        sdo[PROGRAM_CONTROL][1].raw = 1
    assert e.value.code == 0x08000020
    block_download(board.node, image(3000))
    sdo[PROGRAM_CONTROL][1].raw = 3  # clear
    assert sdo[IDENT][1].raw == 0
    assert sdo[FLASH_STATUS][1].raw == 2


def test_block_upload_falls_back_to_segmented(board):
    name = board.node.sdo.upload(0x1008, 0)
    assert len(name) > 7
    raw = board.raw.request(bytes([0xA4, 0x08, 0x10, 0, 127, 0, 0, 0]))
    assert raw[0] == 0x80
    assert struct.unpack_from("<I", raw, 4)[0] == 0x05040001
    assert board.node.sdo.upload(0x1008, 0) == name
