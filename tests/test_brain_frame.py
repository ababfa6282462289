"""A camera frame in a BrainService request (runtime/brain_frame.py): every encoding the API takes
gives the pixels the training cache would have stored, and every bad image is a 400 saying why."""
from __future__ import annotations

import base64
import io
import struct
import warnings
import zlib

import numpy as np
import pytest
from PIL import Image

from hope_models.runtime.brain_frame import MAX_IMAGE_PIXELS, frame_from_request
from hope_models.runtime.brain_input import BrainError

SHAPE = (64, 64, 3)


def _picture(h: int = 480, w: int = 640, seed: int = 0) -> np.ndarray:
    small = np.random.default_rng(seed).integers(0, 255, (h // 40, w // 40, 3), dtype=np.uint8)
    return np.kron(small, np.ones((40, 40, 1), np.uint8))


def _encoded(img: np.ndarray, fmt: str) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, fmt, **({"quality": 90} if fmt == "JPEG" else {}))
    return buf.getvalue()


def _cache_decode(data: bytes, tmp_path, name: str) -> np.ndarray:
    """What the training cache stores for the same image file (hope_models.media.decode_still)."""
    from hope_models.media import decode_still

    path = tmp_path / name
    path.write_bytes(data)
    return decode_still(path, SHAPE[:2])


@pytest.mark.parametrize("fmt", ["JPEG", "PNG"])
def test_an_image_is_decoded_and_resized_as_the_cache_does_it(tmp_path, fmt):
    data = _encoded(_picture(), fmt)
    want = _cache_decode(data, tmp_path, f"x.{fmt.lower()}")
    b64 = base64.b64encode(data).decode()
    for value in (b64, f"data:image/{fmt.lower()};base64,{b64}", {"encoding": fmt.lower(), "data": b64}):
        got = frame_from_request(value, SHAPE)
        assert got.dtype == np.uint8 and np.array_equal(got, want)


def test_raw_arrays_must_already_be_the_models_size():
    img = np.random.default_rng(3).integers(0, 256, SHAPE, dtype=np.uint8)
    raw = {"encoding": "raw", "shape": [64, 64, 3], "data": base64.b64encode(img.tobytes()).decode()}
    assert np.array_equal(frame_from_request(raw, SHAPE), img)
    assert np.array_equal(frame_from_request(img.tolist(), SHAPE), img)
    with pytest.raises(BrainError, match=r"frame.shape: \[32, 32, 3\], the served tokenizer reads \[64, 64, 3\]"):
        frame_from_request({"encoding": "raw", "shape": [32, 32, 3], "data": ""}, SHAPE)
    with pytest.raises(BrainError, match=r"frame.data: 100 bytes, a \[64, 64, 3\] uint8 frame has 12288"):
        frame_from_request({"encoding": "raw", "shape": [64, 64, 3], "data": base64.b64encode(b"x" * 100).decode()},
                           SHAPE)
    with pytest.raises(BrainError, match=r"frame: 2 rows"):
        frame_from_request([[[0, 0, 0]], [[0, 0, 0]]], SHAPE)
    bad = img.astype(int).tolist()
    bad[0][0][0] = 300
    with pytest.raises(BrainError, match="within 0-255"):
        frame_from_request(bad, SHAPE)


def _png_declaring(width: int, height: int) -> bytes:
    """A tiny PNG whose header declares a huge image (CRCs right, so only the size is wrong)."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


@pytest.mark.parametrize("value, message", [
    ("not base64 at all!", "frame: not valid base64"),
    (base64.b64encode(b"GIF89a" + b"\0" * 50).decode(), "not a JPEG or PNG image"),
    (base64.b64encode(_encoded(_picture(), "JPEG")[:2000]).decode(), "undecodable JPEG"),
    (base64.b64encode(_png_declaring(5_000, 5_000)).decode(), f"above the limit of {MAX_IMAGE_PIXELS}"),
    (base64.b64encode(_png_declaring(100_000, 100_000)).decode(), "PNG declares too many pixels"),
    ({"encoding": "gif", "data": ""}, "frame.encoding: expected one of jpeg, png, raw"),
    ({"encoding": "png", "data": "", "extra": 1}, "unknown keys"),
    (42, "frame: expected a base64 JPEG/PNG string"),
    ("", "empty image"),
])
def test_bad_images_are_400_with_the_reason_and_no_warning(value, message):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(BrainError, match=message) as err:
            frame_from_request(value, SHAPE)
    assert err.value.status == 400
