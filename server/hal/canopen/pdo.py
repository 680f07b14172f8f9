"""Process-data objects: the cyclic CSP exchange of CiA 402 drives, and a codec for their frames.

The layout (CiA 301 §7.4.7 mapping, CiA 402 objects) fits twelve axes in three frames per axis:

    RPDO1 (master → drive, on SYNC): controlword 0x6040, target position 0x607A, mode 0x6060
    TPDO1 (drive → master, on SYNC): statusword 0x6041, position actual 0x6064, torque actual 0x6077
    TPDO2 (drive → master, on SYNC): velocity actual 0x606C, error code 0x603F, mode display 0x6061

The master writes this mapping into each drive over SDO; the simulated drive reads it back from its
own object dictionary, so both ends build the same `PdoCodec` from what is actually mapped.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

from canopen import objectdictionary

from server.hal.canopen import cia402

RPDO_LAYOUT: tuple[tuple[int, ...], ...] = ((cia402.CONTROLWORD, cia402.TARGET_POSITION, cia402.MODES_OF_OPERATION),)
TPDO_LAYOUT: tuple[tuple[int, ...], ...] = (
    (cia402.STATUSWORD, cia402.POSITION_ACTUAL, cia402.TORQUE_ACTUAL),
    (cia402.VELOCITY_ACTUAL, cia402.ERROR_CODE, cia402.MODES_OF_OPERATION_DISPLAY),
)
RPDO_COB_BASE = (0x200, 0x300, 0x400, 0x500)
TPDO_COB_BASE = (0x180, 0x280, 0x380, 0x480)
SYNC_COB_ID = 0x80
CAN_ERR_BUSOFF = 0x00000040  # linux/can/error.h: error class of a bus-off error frame
TRANSMISSION_TYPE_EVERY_SYNC = 1

_STRUCT_CODES = {
    objectdictionary.INTEGER8: "b",
    objectdictionary.UNSIGNED8: "B",
    objectdictionary.INTEGER16: "h",
    objectdictionary.UNSIGNED16: "H",
    objectdictionary.INTEGER32: "i",
    objectdictionary.UNSIGNED32: "I",
}


@dataclass(frozen=True)
class PdoCodec:
    """Packs and unpacks one PDO's frame; `indices` are the mapped objects in frame order."""

    cob_id: int
    indices: tuple[int, ...]
    layout: struct.Struct

    @classmethod
    def from_mapping(cls, cob_id: int, mapped: Sequence[tuple[int, int]], od: objectdictionary.ObjectDictionary):
        """Build from (index, bit length) pairs; every object must be a whole-byte integer."""
        codes = []
        for index, bits in mapped:
            variable = od[index]
            if not isinstance(variable, objectdictionary.ODVariable) or variable.data_type not in _STRUCT_CODES:
                raise ValueError(f"PDO 0x{cob_id:03X}: object 0x{index:04X} is not a mappable integer")
            code = _STRUCT_CODES[variable.data_type]
            if struct.calcsize(code) * 8 != bits:
                raise ValueError(f"PDO 0x{cob_id:03X}: object 0x{index:04X} mapped with {bits} bits")
            codes.append(code)
        layout = struct.Struct("<" + "".join(codes))
        if layout.size > 8:
            raise ValueError(f"PDO 0x{cob_id:03X}: {layout.size} bytes exceed a CAN frame's 8")
        return cls(cob_id, tuple(index for index, _ in mapped), layout)

    def pack(self, values: Sequence[int]) -> bytes:
        return self.layout.pack(*values)

    def unpack(self, data: bytes | bytearray) -> tuple[int, ...]:
        return self.layout.unpack_from(data)


def layout_codecs(
    layout: tuple[tuple[int, ...], ...], cob_bases: Sequence[int], node_id: int, od: objectdictionary.ObjectDictionary
) -> list[PdoCodec]:
    """Codecs for a PDO layout on one node, with the predefined-connection-set COB-IDs."""
    codecs = []
    for number, indices in enumerate(layout):
        mapped = [(index, len(od[index])) for index in indices]
        codecs.append(PdoCodec.from_mapping(cob_bases[number] + node_id, mapped, od))
    return codecs


def frame_bits(data_bytes: int) -> int:
    """Worst-case length of a standard-ID CAN 2.0A frame with bit stuffing, including the 3-bit gap.

    44 fixed bits + 8·n data bits, of which the 34 + 8·n stuffable ones grow by a fifth at worst.
    """
    return 44 + 8 * data_bytes + (34 + 8 * data_bytes - 1) // 4 + 3


def cycle_bus_bits(axis_count: int, od: objectdictionary.ObjectDictionary) -> int:
    """Bits on the wire for one control cycle: one SYNC, every axis's RPDOs and TPDOs."""
    per_axis = sum(
        frame_bits(sum(len(od[index]) for index in indices) // 8) for indices in (*RPDO_LAYOUT, *TPDO_LAYOUT)
    )
    return frame_bits(0) + axis_count * per_axis
