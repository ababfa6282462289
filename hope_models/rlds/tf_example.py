"""A small protobuf codec for `tf.train.Example`, so reading TFRecords needs no TensorFlow.

Wire shape (tensorflow/core/example/{example,feature}.proto):
    Example   { Features features = 1; }
    Features  { map<string, Feature> feature = 1; }   -> repeated entry {string key = 1; Feature value = 2;}
    Feature   { oneof kind { BytesList bytes_list = 1; FloatList float_list = 2; Int64List int64_list = 3; } }
    BytesList { repeated bytes value = 1; }
    FloatList { repeated float value = 1 [packed = true]; }
    Int64List { repeated int64 value = 1 [packed = true]; }
Writers may emit packed or unpacked repeated scalars; both are accepted. Unknown fields are
skipped by wire type, as protobuf requires.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any, Mapping

BYTES = "bytes"
FLOAT = "float"
INT64 = "int64"

_KIND_BY_FIELD = {1: BYTES, 2: FLOAT, 3: INT64}
_FIELD_BY_KIND = {v: k for k, v in _KIND_BY_FIELD.items()}


class ExampleDecodeError(ValueError):
    """The payload is not a well-formed tf.train.Example."""


@dataclass(frozen=True)
class Feature:
    kind: str  # BYTES, FLOAT or INT64
    values: list  # bytes, float or int elements


# -- wire primitives ------------------------------------------------------------------------

def _read_varint(buf: bytes, pos: int, end: int) -> tuple[int, int]:
    result = 0
    shift = 0
    while True:
        if pos >= end:
            raise ExampleDecodeError("truncated varint")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, pos
        shift += 7
        if shift > 63:
            raise ExampleDecodeError("varint longer than 10 bytes")


def _iter_fields(buf: bytes, start: int, end: int):
    """Yield (field_number, wire_type, value_or_span). Length-delimited fields give (start, end)."""
    pos = start
    while pos < end:
        key, pos = _read_varint(buf, pos, end)
        field_no, wire = key >> 3, key & 7
        if field_no == 0:
            raise ExampleDecodeError("field number 0")
        if wire == 0:
            value, pos = _read_varint(buf, pos, end)
            yield field_no, wire, value
        elif wire == 1:
            if pos + 8 > end:
                raise ExampleDecodeError("truncated fixed64")
            yield field_no, wire, (pos, pos + 8)
            pos += 8
        elif wire == 2:
            length, pos = _read_varint(buf, pos, end)
            if pos + length > end:
                raise ExampleDecodeError(f"length-delimited field {field_no} runs past the end")
            yield field_no, wire, (pos, pos + length)
            pos += length
        elif wire == 5:
            if pos + 4 > end:
                raise ExampleDecodeError("truncated fixed32")
            yield field_no, wire, (pos, pos + 4)
            pos += 4
        else:
            raise ExampleDecodeError(f"unsupported wire type {wire}")


def _signed64(v: int) -> int:
    return v - (1 << 64) if v >= 1 << 63 else v


def _decode_list(kind: str, buf: bytes, start: int, end: int) -> list:
    values: list = []
    for field_no, wire, val in _iter_fields(buf, start, end):
        if field_no != 1:
            continue
        if kind == BYTES:
            if wire != 2:
                raise ExampleDecodeError("bytes_list value with wrong wire type")
            values.append(bytes(buf[val[0]:val[1]]))
        elif kind == FLOAT:
            if wire == 2:  # packed
                s, e = val
                if (e - s) % 4:
                    raise ExampleDecodeError("packed float list length not a multiple of 4")
                values.extend(struct.unpack_from(f"<{(e - s) // 4}f", buf, s))
            elif wire == 5:
                values.append(struct.unpack_from("<f", buf, val[0])[0])
            else:
                raise ExampleDecodeError("float_list value with wrong wire type")
        else:
            if wire == 2:  # packed
                pos, e = val
                while pos < e:
                    v, pos = _read_varint(buf, pos, e)
                    values.append(_signed64(v))
            elif wire == 0:
                values.append(_signed64(val))
            else:
                raise ExampleDecodeError("int64_list value with wrong wire type")
    return values


def _decode_feature(buf: bytes, start: int, end: int) -> Feature:
    found: Feature | None = None
    for field_no, wire, val in _iter_fields(buf, start, end):
        kind = _KIND_BY_FIELD.get(field_no)
        if kind is None or wire != 2:
            continue
        # oneof: the last one on the wire wins, as in protobuf
        found = Feature(kind, _decode_list(kind, buf, val[0], val[1]))
    return found if found is not None else Feature(BYTES, [])


def decode_example(payload: bytes) -> dict[str, Feature]:
    """Decode one serialized tf.train.Example into {feature name: Feature}."""
    buf = memoryview(payload).tobytes() if not isinstance(payload, bytes) else payload
    features: dict[str, Feature] = {}
    for field_no, wire, val in _iter_fields(buf, 0, len(buf)):
        if field_no != 1 or wire != 2:
            continue
        for f2, w2, entry in _iter_fields(buf, val[0], val[1]):
            if f2 != 1 or w2 != 2:
                continue
            key: str | None = None
            feature = Feature(BYTES, [])
            for f3, w3, v3 in _iter_fields(buf, entry[0], entry[1]):
                if f3 == 1 and w3 == 2:
                    try:
                        key = buf[v3[0]:v3[1]].decode("utf-8")
                    except UnicodeDecodeError:
                        raise ExampleDecodeError("feature name is not UTF-8") from None
                elif f3 == 2 and w3 == 2:
                    feature = _decode_feature(buf, v3[0], v3[1])
            if key is None:
                raise ExampleDecodeError("feature map entry without a key")
            features[key] = feature
    return features


# -- encoding -------------------------------------------------------------------------------

def _varint(v: int) -> bytes:
    if v < 0:
        v += 1 << 64
    out = bytearray()
    while True:
        b = v & 0x7F
        v >>= 7
        if v:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _len_field(field_no: int, data: bytes) -> bytes:
    return _varint((field_no << 3) | 2) + _varint(len(data)) + data


def _infer_feature(name: str, value: Any) -> Feature:
    if isinstance(value, Feature):
        return value
    items = list(value) if isinstance(value, (list, tuple)) else [value]
    if all(isinstance(v, (bytes, bytearray, str)) for v in items):
        return Feature(BYTES, [v.encode("utf-8") if isinstance(v, str) else bytes(v) for v in items])
    if all(isinstance(v, (bool, int)) for v in items):
        return Feature(INT64, [int(v) for v in items])
    if all(isinstance(v, (bool, int, float)) for v in items):
        return Feature(FLOAT, [float(v) for v in items])
    raise TypeError(f"feature {name!r}: cannot encode {value!r} (use bytes/str, ints, floats or Feature)")


def encode_feature(feature: Feature) -> bytes:
    if feature.kind == BYTES:
        inner = b"".join(_len_field(1, v) for v in feature.values)
    elif feature.kind == FLOAT:
        packed = struct.pack(f"<{len(feature.values)}f", *feature.values)
        inner = _len_field(1, packed) if feature.values else b""
    elif feature.kind == INT64:
        packed = b"".join(_varint(int(v)) for v in feature.values)
        inner = _len_field(1, packed) if feature.values else b""
    else:
        raise ValueError(f"unknown feature kind {feature.kind!r}")
    return _len_field(_FIELD_BY_KIND[feature.kind], inner)


def encode_example(features: Mapping[str, Any]) -> bytes:
    """Encode {name: value} as a tf.train.Example. Values: bytes/str (bytes_list), ints/bools
    (int64_list), floats (float_list), lists of one of these, or a Feature for an explicit kind
    (needed for an empty list, whose kind cannot be inferred)."""
    entries: list[bytes] = []
    for name, value in features.items():
        entry = _len_field(1, name.encode("utf-8")) + _len_field(2, encode_feature(_infer_feature(name, value)))
        entries.append(_len_field(1, entry))
    return _len_field(1, b"".join(entries))


def float32_value(x: float) -> float:
    """The shortest decimal that round-trips through float32, as a Python float.

    A float feature holding 0.05 decodes to 0.05000000074505806; producers wrote 0.05, so the
    short form is what the JSON twin of the value says and what a person expects to see."""
    if x != x or x in (float("inf"), float("-inf")):
        return x
    packed = struct.pack("<f", x)
    for digits in range(1, 10):
        candidate = float(f"{x:.{digits}g}")
        if struct.pack("<f", candidate) == packed:
            return candidate
    return x

