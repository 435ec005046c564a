"""CiA 301 (CANopen application layer) numbers every CANopen device shares: the PDO
communication and mapping objects, the predefined connection set's PDO COB-IDs, mapping entries,
SDO abort texts. No vendor and no ROS here: a vendor's own tables (EMCY texts, registers) live in
its map (vendors/<v>_map.py) and are passed in where the link needs them.
"""

from __future__ import annotations

from canopen.sdo.exceptions import SdoAbortedError

# PDO parameter objects [CiA 301 7.5.2.35-38], + n for PDO n + 1 (n = 0..3 here)
RPDO_COMMUNICATION = 0x1400
RPDO_MAPPING = 0x1600
TPDO_COMMUNICATION = 0x1800
TPDO_MAPPING = 0x1A00

# Predefined connection set [CiA 301 7.3.5]: COB-ID = base + node-ID, PDO 1..4
PDO_COB_BASES_RX = (0x200, 0x300, 0x400, 0x500)
PDO_COB_BASES_TX = (0x180, 0x280, 0x380, 0x480)
PDO_INVALID = 1 << 31            # COB-ID bit 31: PDO does not exist / is not valid
PDO_RTR_NOT_ALLOWED = 1 << 30

EMCY_NO_ERROR = 0x0000           # "error reset or no error" [CiA 301 7.2.7.1]


def mapping_entry(index: int, sub: int, bits: int) -> int:
    """Mapping value: bits 31..16 index, 15..8 sub-index, 7..0 length in bits."""
    return (index << 16) | (sub << 8) | bits


def split_mapping_entry(value: int) -> tuple[int, int, int]:
    return value >> 16, (value >> 8) & 0xFF, value & 0xFF


def abort_text(code: int) -> str:
    """'SDO abort 0x06010002 (Attempt to write a read only object)': the CiA 301 texts of the
    canopen library (every abort code the Vector Step manual names is one of them)."""
    return f'SDO abort 0x{code:08X} ({SdoAbortedError.CODES.get(code, "unknown abort code")})'
