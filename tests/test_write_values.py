"""The one value grammar of north-side writes: what every north side accepts and refuses."""

from __future__ import annotations

from typing import Any

import pytest

from plcstack.errors import AddressError
from plcstack.north.write_values import (
    NOT_WRITABLE,
    UNKNOWN_TAG,
    WRONG_TYPE,
    WriteValueError,
    bit_of_word_refusal,
    parse_write_value,
    result_code,
)
from plcstack.poll.config import TagConfig
from plcstack.values import BOOL, FLOAT32, INT16, KC, KG, KY, RAW, UINT16, string
from plcstack.values.points import Scale


@pytest.mark.parametrize(
    ("tag", "sent", "written"),
    [
        (TagConfig("n", "D0", INT16), 1201, 1201),
        (TagConfig("n", "D0", INT16), 1201.0, 1201),  # JavaScript's integers
        (TagConfig("n", "D0", INT16), -5.0, -5),
        (TagConfig("b", "M0", BOOL), True, True),
        (TagConfig("b", "M0", BOOL), 0, False),
        (TagConfig("b", "M0", BOOL), 1.0, True),
        (TagConfig("f", "D0", FLOAT32), 3, 3.0),
        (TagConfig("g", "D0", KG), -0.5, -0.5),
        (TagConfig("s", "D0", INT16, scale=Scale(0, 100, 0, 10)), 2, 2.0),
        (TagConfig("y", "D0", KY), [7, 8], (7, 8)),
        (TagConfig("y", "D0", KY), (7, 8), (7, 8)),
        (TagConfig("y", "D0", KY), "7,8", (7, 8)),
        (TagConfig("y", "D0", KY), " 12, 255 ", (12, 255)),
        (TagConfig("y", "D0", KY), [7.0, 8.0], (7, 8)),
        (TagConfig("c", "D0", KC), "AB", "AB"),
        (TagConfig("t", "D0", string(8)), "Hello", "Hello"),
        (TagConfig("r", "D0", RAW), 17, 17),
        (TagConfig("r", "M0", RAW), True, True),
        (TagConfig("a", "D0", UINT16, count=3), [1, 2.0, 3], [1, 2, 3]),
        (TagConfig("ys", "D0", KY, count=2), ["1,2", [3, 4]], [(1, 2), (3, 4)]),
    ],
)
def test_every_north_side_value_form_is_accepted(tag: TagConfig, sent: Any, written: Any) -> None:
    got = parse_write_value(tag, sent)
    assert (got, type(got)) == (written, type(written))
    if isinstance(got, list):
        assert [type(v) for v in got] == [type(v) for v in written]


@pytest.mark.parametrize(
    ("tag", "sent", "words"),
    [
        (TagConfig("n", "D0", INT16), 1201.5, "takes an integer (-32768..32767), not 1201.5"),
        (TagConfig("n", "D0", INT16), True, "takes an integer"),
        (TagConfig("n", "D0", INT16), "12", "not '12'"),
        (TagConfig("n", "D0", INT16), float("nan"), "not nan"),
        (TagConfig("b", "M0", BOOL), 2, "takes true or false, not 2"),
        (TagConfig("f", "D0", FLOAT32), "1.5", "takes a number"),
        (TagConfig("f", "D0", FLOAT32), float("inf"), "takes a number"),
        (TagConfig("y", "D0", KY), "7;8", 'as [high, low] or "high,low"'),
        (TagConfig("y", "D0", KY), [7, 256], "two bytes 0..255"),
        (TagConfig("y", "D0", KY), [7, 8, 9], "two bytes"),
        (TagConfig("c", "D0", KC), 12, "takes a string"),
        (TagConfig("a", "D0", UINT16, count=3), 5, "has 3 values: send a list of 3"),
        (TagConfig("a", "D0", UINT16, count=3), [1, 2], "takes a list of 3 values, got 2"),
        (TagConfig("a", "D0", UINT16, count=3), [1, 2, "x"], "value 2 must be an integer"),
    ],
)
def test_a_value_the_tag_cannot_take_is_refused_with_one_code_and_wording(
    tag: TagConfig, sent: Any, words: str
) -> None:
    with pytest.raises(WriteValueError) as err:
        parse_write_value(tag, sent, plc="press1")
    assert err.value.code == WRONG_TYPE and result_code(err.value) == WRONG_TYPE
    assert words in str(err.value)
    assert str(err.value).startswith(f"press1: write {tag.name}: tag {tag.name!r}")


def test_result_codes_of_the_pollers_own_refusals() -> None:
    assert result_code(AddressError("no tag named 'x'")) == UNKNOWN_TAG
    assert result_code(AddressError("no PLC named 'x' in this poller")) == "unknown_plc"
    assert result_code(AddressError("300 cannot be written as int8: outside")) == WRONG_TYPE
    assert result_code(AddressError("tag 'b' is a bit of a word (D1.3) and is read-only")) == (
        NOT_WRITABLE
    )
    refusal = bit_of_word_refusal("b", "D1.3", plc="press1")
    assert refusal.code == NOT_WRITABLE and "bit of a word (D1.3)" in str(refusal)
