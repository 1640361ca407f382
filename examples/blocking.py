"""The blocking facade, for scripts and notebooks without asyncio.

plcstack sim s5lan &
python examples/blocking.py                 # s5lan://127.0.0.1:5010
"""

from __future__ import annotations

import sys

import plcstack.sync
from plcstack.errors import PlcError
from plcstack.values import INT16


def main(url: str) -> None:
    with plcstack.sync.connect(url, timeout=2.0) as plc:
        plc.write("DB10.DW0", [10, 20, 30])
        print("DB10.DW0..2:", plc.read("DB10.DW0", 3))
        plc.write_as("DB10.DW3", INT16, -5)
        print("DB10.DW3 as int16:", plc.read_as("DB10.DW3", INT16))
        try:
            plc.read("D100", 1)  # MELSEC notation on an S5 PLC
        except PlcError as exc:  # the same typed errors as the async client
            print("refused:", exc)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "s5lan://127.0.0.1:5010")
