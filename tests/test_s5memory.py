import pytest

from plcstack.sim.s5memory import Area, BlockType, S5AccessError, S5Memory


def test_block_header_and_info() -> None:
    mem = S5Memory()
    dw0 = mem.create_block(BlockType.DB, 5, 4, b"\x00\x01\x10\x10")
    addr, header = mem.block_info(BlockType.DB, 5)
    assert addr == dw0 == 0x0100 + 10
    assert header == bytes.fromhex("7070 41 05 80 000000 0009")
    assert mem.read_db_words(5, 0, 2) == [0x0001, 0x1010]


def test_missing_block_and_short_block_errors() -> None:
    mem = S5Memory(default_dbs={10: 8})
    with pytest.raises(S5AccessError) as missing:
        mem.read_block(BlockType.DB, 11, 0, 2)
    assert missing.value.code == 2
    with pytest.raises(S5AccessError) as short:
        mem.read_db_words(10, 7, 2)
    assert short.value.code == 3


def test_compress_moves_blocks_and_keeps_data() -> None:
    mem = S5Memory(default_dbs={1: 100, 2: 4})
    mem.write_db_words(2, 0, [1, 2, 3, 4])
    before, _ = mem.block_info(BlockType.DB, 2)
    mem.delete_block(BlockType.DB, 1)
    mem.compress()
    after, _ = mem.block_info(BlockType.DB, 2)
    assert after == before - 210
    assert mem.read_db_words(2, 0, 4) == [1, 2, 3, 4]
    assert mem.read_absolute(after, 2) == b"\x00\x01"


def test_areas_share_the_absolute_image() -> None:
    mem = S5Memory()
    mem.write_area(Area.FLAGS, 10, b"\xab\xcd")
    assert mem.read_absolute(0xEE00 + 10, 2) == b"\xab\xcd"
    with pytest.raises(S5AccessError):
        mem.read_area(Area.INPUTS, 127, 2)
    assert len(mem.params.to_bytes()) == 50
