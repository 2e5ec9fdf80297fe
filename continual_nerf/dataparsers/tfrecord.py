"""TFRecord files and protobuf messages read without TensorFlow or generated protobuf classes.

A TFRecord file is a sequence of records, each `uint64 length`, `uint32 masked crc32c(length)`,
`length` bytes of data, `uint32 masked crc32c(data)` (little endian). A record of a Waymo v1 file is
one serialized `Frame`; `Message` reads the protobuf wire format field by field.
"""

from __future__ import annotations

import struct
from functools import lru_cache
from pathlib import Path
from typing import BinaryIO, Dict, Iterator, List, Tuple, Union, cast

import numpy as np

from continual_nerf.errors import DatasetError

CRC32C_POLYNOMIAL = 0x82F63B78
"""Castagnoli polynomial, bit-reversed (the CRC is computed least significant bit first)."""
CRC_LANE_BYTES = 256
"""Bytes each numpy lane checksums before lanes are combined (a power of two)."""
MASK_DELTA = 0xA282EAD8

VARINT, I64, LEN, I32 = 0, 1, 2, 5
"""Protobuf wire types this reader understands (3 and 4, the deprecated groups, are not used by Waymo)."""


def _byte_table() -> np.ndarray:
    """crc32c register after shifting in one byte, for each byte value, from a zero register."""
    table = np.arange(256, dtype=np.uint32)
    for _ in range(8):
        table = np.where(table & 1, (table >> 1) ^ np.uint32(CRC32C_POLYNOMIAL), table >> 1).astype(np.uint32)
    return table


CRC_TABLE = _byte_table()


def _tables_of(columns: np.ndarray) -> np.ndarray:
    """(4, 256) lookup tables of the GF(2)-linear map whose image of bit i is columns[i]."""
    bits = (np.arange(256)[:, None] >> np.arange(8)) & 1
    return np.stack([np.bitwise_xor.reduce(np.where(bits, columns[8 * k : 8 * k + 8], 0), axis=1) for k in range(4)])


def _apply(tables: np.ndarray, states: np.ndarray) -> np.ndarray:
    return (
        tables[0][states & 0xFF]
        ^ tables[1][(states >> 8) & 0xFF]
        ^ tables[2][(states >> 16) & 0xFF]
        ^ tables[3][states >> 24]
    )


@lru_cache(maxsize=None)
def _zeros_shift(log2_count: int) -> np.ndarray:
    """Tables of the map 'register -> register after 2**log2_count zero bytes' (the map is linear)."""
    basis = np.uint32(1) << np.arange(32, dtype=np.uint32)
    if log2_count == 0:
        return _tables_of(CRC_TABLE[basis & 0xFF] ^ (basis >> 8))
    half = _zeros_shift(log2_count - 1)
    return _tables_of(_apply(half, _apply(half, basis)))


def _shift_zeros(states: np.ndarray, count: int) -> np.ndarray:
    """Registers after `count` zero bytes, by the binary digits of count."""
    for bit in range(count.bit_length()):
        if count >> bit & 1:
            states = _apply(_zeros_shift(bit), states)
    return states


def crc32c(data: bytes) -> int:
    """CRC-32C of `data` (iSCSI, as TFRecord uses it).

    A byte-by-byte Python loop takes minutes on a 1 GB segment, so numpy checksums many lanes of
    the data at once from a zero register, and the lanes are then joined pairwise: the register is
    linear, so register(A + B) = shift(register(A), len(B)) ^ register(B) for zero-started registers,
    where shift feeds len(B) zero bytes. The all-ones start register adds shift(0xFFFFFFFF, len(data)).
    """
    raw = np.frombuffer(data, dtype=np.uint8)
    # leading zero bytes leave a zero register at zero, so padding the front to whole lanes is free
    padded = np.concatenate([np.zeros(-len(raw) % CRC_LANE_BYTES, np.uint8), raw]).reshape(-1, CRC_LANE_BYTES)
    states = np.zeros(len(padded), dtype=np.uint32)
    for column in padded.T:
        states = CRC_TABLE[(states ^ column) & 0xFF] ^ (states >> 8)
    log2_span = CRC_LANE_BYTES.bit_length() - 1
    while len(states) > 1:
        states = np.concatenate([np.zeros(len(states) % 2, np.uint32), states])
        states = _apply(_zeros_shift(log2_span), states[0::2]) ^ states[1::2]
        log2_span += 1
    start = _shift_zeros(np.array([0xFFFFFFFF], dtype=np.uint32), len(raw))
    zero_start = states[0] if len(states) else np.uint32(0)
    return int((start[0] ^ zero_start) ^ np.uint32(0xFFFFFFFF))


def masked_crc32c(data: bytes) -> int:
    """The CRC as TFRecord stores it: rotated right by 15 bits plus a constant."""
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + MASK_DELTA) & 0xFFFFFFFF


def _read_exactly(stream: BinaryIO, size: int, path: Path, record: int, what: str) -> bytes:
    data = stream.read(size)
    if len(data) != size:
        raise DatasetError(f"{path}: record {record} is truncated ({what}: {len(data)} of {size} bytes)")
    return data


def read_records(path: Path) -> Iterator[bytes]:
    """The data of every record of a TFRecord file, one at a time, both CRCs checked."""
    with open(path, "rb") as stream:
        record = 0
        while header := stream.read(12):
            if len(header) < 12:
                raise DatasetError(f"{path}: record {record} is truncated (header: {len(header)} of 12 bytes)")
            length, length_crc = struct.unpack("<QI", header)
            if masked_crc32c(header[:8]) != length_crc:
                raise DatasetError(f"{path}: record {record} has a corrupt length (its CRC does not match)")
            data = _read_exactly(stream, length, path, record, "data")
            (data_crc,) = struct.unpack("<I", _read_exactly(stream, 4, path, record, "data CRC"))
            if masked_crc32c(data) != data_crc:
                raise DatasetError(f"{path}: record {record} has corrupt data (its CRC does not match)")
            yield data
            record += 1


FieldValue = Union[int, memoryview]
"""A varint as an int; a 64-bit, length-delimited or 32-bit field as its raw bytes."""


class Message:
    """The fields of one serialized protobuf message, by field number, in wire order.

    `source` names the file and record in error messages. Sub-messages and bytes are memoryviews of
    the record, so reading a frame copies no image.
    """

    def __init__(self, data: Union[bytes, memoryview], source: str):
        self.source = source
        self.fields: Dict[int, List[Tuple[int, FieldValue]]] = {}
        for number, wire_type, value in self._parse(memoryview(data)):
            self.fields.setdefault(number, []).append((wire_type, value))

    def _error(self, what: str) -> DatasetError:
        return DatasetError(f"{self.source}: malformed protobuf ({what})")

    def _varint(self, data: memoryview, pos: int) -> Tuple[int, int]:
        value, shift = 0, 0
        while pos < len(data):
            byte = data[pos]
            value |= (byte & 0x7F) << shift
            pos += 1
            if not byte & 0x80:
                return value, pos
            shift += 7
        raise self._error("truncated varint")

    def _parse(self, data: memoryview) -> Iterator[Tuple[int, int, FieldValue]]:
        pos = 0
        while pos < len(data):
            key, pos = self._varint(data, pos)
            number, wire_type = key >> 3, key & 7
            if wire_type == VARINT:
                value, pos = self._varint(data, pos)
                yield number, wire_type, value
                continue
            if wire_type == LEN:
                size, pos = self._varint(data, pos)
            elif wire_type in (I64, I32):
                size = 8 if wire_type == I64 else 4
            else:
                raise self._error(f"field {number} has unsupported wire type {wire_type}")
            if pos + size > len(data):
                raise self._error(f"field {number} runs past the end of its message")
            yield number, wire_type, data[pos : pos + size]
            pos += size

    def _values(self, number: int, wire_types: Tuple[int, ...]) -> List[FieldValue]:
        values = []
        for wire_type, value in self.fields.get(number, []):
            if wire_type not in wire_types:
                raise self._error(f"field {number} has wire type {wire_type}, expected one of {wire_types}")
            values.append(value)
        return values

    def has(self, number: int) -> bool:
        return number in self.fields

    def _bytes(self, number: int, wire_types: Tuple[int, ...] = (LEN,)) -> List[memoryview]:
        # every wire type but VARINT is read as raw bytes
        return cast(List[memoryview], self._values(number, wire_types))

    def messages(self, number: int) -> List["Message"]:
        """Every occurrence of a (repeated) message field."""
        return [Message(value, f"{self.source} field {number}") for value in self._bytes(number)]

    def message(self, number: int) -> "Message":
        """A singular message field (the last occurrence wins, as protobuf merges them); empty when absent."""
        values = self._bytes(number)
        return Message(values[-1] if values else b"", f"{self.source} field {number}")

    def integer(self, number: int, default: int = 0) -> int:
        """A singular varint field (int32, int64, enum) read as signed 64-bit."""
        values = cast(List[int], self._values(number, (VARINT,)))  # varints are read as ints
        if not values:
            return default
        value = values[-1]
        return value - (1 << 64) if value >= 1 << 63 else value

    def blob(self, number: int) -> memoryview:
        """A singular bytes or string field; empty when absent."""
        values = self._bytes(number)
        return values[-1] if values else memoryview(b"")

    def doubles(self, number: int) -> np.ndarray:
        """A repeated double field, packed (one length-delimited run) or not (one 64-bit field each)."""
        chunks = self._bytes(number, (I64, LEN))
        if any(len(chunk) % 8 for chunk in chunks):
            raise self._error(f"packed doubles of field {number} are not a multiple of 8 bytes")
        return np.frombuffer(b"".join(chunks), dtype="<f8").astype(np.float64)
