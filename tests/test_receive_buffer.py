"""ReceiveBuffer: what is fed comes out once, in order, and ``held`` is empty exactly when
nothing is buffered (the E71 fast path's test for "bytes before this chunk")."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from plcstack.codecs._common import ReceiveBuffer

_WORD = struct.Struct("<H")

#: feed bytes, take n, take n if they start with a prefix, take a prefixed word, take all
_steps = st.lists(
    st.one_of(
        st.tuples(st.just("feed"), st.binary(max_size=40)),
        st.tuples(st.just("take"), st.integers(0, 50)),
        st.tuples(st.just("prefixed"), st.integers(1, 50)),
        st.tuples(st.just("unpacked"), st.just(0)),
        st.tuples(st.just("all"), st.just(0)),
    ),
    max_size=60,
)


@given(_steps)
def test_held_is_empty_exactly_when_nothing_is_buffered(steps: list[tuple[str, object]]) -> None:
    buffer = ReceiveBuffer()
    held = buffer.held
    model = bytearray()  # what a plain bytearray would hold
    for kind, arg in steps:
        if kind == "feed":
            assert isinstance(arg, bytes)
            buffer.feed(arg)
            model += arg
        elif kind == "take":
            assert isinstance(arg, int)
            if arg <= len(model):
                assert buffer.take(arg) == bytes(model[:arg])
                del model[:arg]
            else:  # more than is buffered: refused, and nothing taken
                with pytest.raises(ValueError, match="bytes buffered"):
                    buffer.take(arg)
        elif kind == "prefixed":
            assert isinstance(arg, int)
            prefix = bytes(model[:1])
            out = buffer.take_prefixed(prefix, arg)
            if prefix and arg <= len(model):
                assert out == bytes(model[:arg])
                del model[:arg]
            else:
                assert out is None
        elif kind == "unpacked":
            prefix = bytes(model[:1])
            values = buffer.take_unpacked(prefix, _WORD)
            if prefix and len(model) >= 3:
                assert values == _WORD.unpack_from(model, 1)
                del model[:3]
            else:
                assert values is None
        else:
            assert buffer.take_all() == bytes(model)
            model.clear()
        assert buffer.held is held  # one object for the buffer's life: bound once by codecs
        assert len(buffer) == len(model)
        assert bool(held) == bool(buffer) == bool(model)
