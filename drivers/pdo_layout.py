"""The layout of one PDO: which objects, in which order, how many bits each, packed little-endian.

The driver packs its RPDOs and unpacks the drive's TPDOs with it; the simulated drive does the
reverse. Signedness comes from the object dictionary, so the same bytes decode the same way on both
ends.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

from canopen import objectdictionary
from canopen.objectdictionary import ObjectDictionary, ODVariable

PDO_MAX_BITS = 64
_STRUCT_CODES = {8: "b", 16: "h", 32: "i", 64: "q"}  # signed; upper case unsigned


@dataclass(frozen=True)
class PdoEntry:
    """One object mapped into a PDO: index, sub-index and length in bits (a 0x16xx/0x1Axx entry)."""

    index: int
    subindex: int
    bits: int

    @property
    def mapping_value(self) -> int:
        """The UNSIGNED32 written to a mapping object: index << 16 | sub-index << 8 | bits."""
        return self.index << 16 | self.subindex << 8 | self.bits

    @classmethod
    def from_mapping_value(cls, value: int) -> PdoEntry:
        return cls(value >> 16 & 0xFFFF, value >> 8 & 0xFF, value & 0xFF)

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.subindex:02X}/{self.bits}"


def od_variable(od: ObjectDictionary, index: int, subindex: int = 0) -> ODVariable:
    """The variable at index:subindex of an object dictionary; KeyError if the dictionary lacks it."""
    obj = od[index]
    if isinstance(obj, ODVariable):
        if subindex != 0:
            raise KeyError(f"0x{index:04X} is a variable: it has no sub-index {subindex}")
        return obj
    return obj[subindex]


@dataclass(frozen=True)
class PdoLayout:
    """The mapped entries of one PDO, with the signedness of each taken from the object dictionary."""

    entries: tuple[PdoEntry, ...]
    signed: tuple[bool, ...]

    @classmethod
    def of(cls, od: ObjectDictionary, entries: Sequence[PdoEntry]) -> PdoLayout:
        """The layout of `entries`; KeyError when one is not in `od`."""
        signed = tuple(
            od_variable(od, e.index, e.subindex).data_type in objectdictionary.SIGNED_TYPES for e in entries
        )
        return cls(tuple(entries), signed)

    @classmethod
    def of_objects(cls, od: ObjectDictionary, objects: Sequence[tuple[int, int]]) -> PdoLayout:
        """The layout of whole objects (index, sub-index), each as long as its data type."""
        entries = [PdoEntry(i, s, len(od_variable(od, i, s))) for i, s in objects]
        return cls.of(od, entries)

    @cached_property
    def bits(self) -> int:
        return sum(e.bits for e in self.entries)

    @cached_property
    def length(self) -> int:  # read with every PDO decoded: once, not a sum each time
        """Bytes on the wire."""
        return (self.bits + 7) // 8

    @cached_property
    def _packing(self) -> tuple[struct.Struct, struct.Struct, tuple[int, ...]] | None:
        """When every entry is a whole 8/16/32/64-bit field, structs that do what `encode` and `decode`
        do bit by bit, in C (both ends pack and unpack a PDO each cycle): the unsigned one for encoding
        (values masked first, as bit packing does), the signed one for decoding, and the masks."""
        if not all(e.bits in _STRUCT_CODES for e in self.entries):
            return None
        codes = [_STRUCT_CODES[e.bits] for e in self.entries]
        signed = "".join(c if s else c.upper() for c, s in zip(codes, self.signed, strict=True))
        unsigned = "".join(c.upper() for c in codes)
        masks = tuple((1 << e.bits) - 1 for e in self.entries)
        return struct.Struct("<" + unsigned), struct.Struct("<" + signed), masks

    def encode(self, values: Sequence[int]) -> bytes:
        """The PDO payload for one value per entry (raw, in the objects' units); saturates nothing."""
        if (packing := self._packing) is not None:
            unsigned, _, masks = packing
            return unsigned.pack(*(int(v) & m for v, m in zip(values, masks, strict=True)))
        packed, offset = 0, 0
        for entry, value in zip(self.entries, values, strict=True):
            packed |= (int(value) & ((1 << entry.bits) - 1)) << offset
            offset += entry.bits
        return packed.to_bytes(self.length, "little")

    def decode(self, data: bytes | bytearray) -> tuple[int, ...]:
        """One raw value per entry from a PDO payload; ValueError if the payload is too short."""
        if len(data) < self.length:
            raise ValueError(f"PDO payload of {len(data)} bytes, the mapping needs {self.length}")
        if (packing := self._packing) is not None:
            return packing[1].unpack_from(data)
        packed = int.from_bytes(bytes(data[: self.length]), "little")
        values, offset = [], 0
        for entry, signed in zip(self.entries, self.signed, strict=True):
            value = packed >> offset & ((1 << entry.bits) - 1)
            if signed and value >> (entry.bits - 1):
                value -= 1 << entry.bits
            values.append(value)
            offset += entry.bits
        return tuple(values)
