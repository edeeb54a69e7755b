"""Tests for memlog.io.image: raw layouts are encoded here with numpy, independently of
the decoder, and compared with what it returns."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from memlog.errors import ImageDecodeError
from memlog.io.image import (
    SUPPORTED_RAW_ENCODINGS,
    decode_bgr,
    decode_gray,
    decode_native,
    is_decodable,
)
from memlog.io.types import ImagePayload

U8 = npt.NDArray[np.uint8]
H, W = 24, 32
BGR_INDEX = {"b": 0, "g": 1, "r": 2}


def scene(noise: int = 6, seed: int = 0, h: int = H, w: int = W) -> U8:
    """Smooth BGR colour gradient plus a little uniform noise (fixed seed)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    b = 30 + 150 * xx / max(w - 1, 1)
    g = 40 + 140 * yy / max(h - 1, 1)
    r = 200 - 120 * (xx + yy) / max(w + h - 2, 1)
    img = np.stack([b, g, r], axis=-1) + rng.integers(0, noise + 1, size=(h, w, 3))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def gray_scene(seed: int = 1) -> U8:
    """Grey image with full-range random values."""
    return np.random.default_rng(seed).integers(0, 256, size=(H, W), dtype=np.uint8)


def raw(encoding: str, packed: bytes, bpp: int, *, pad: int = 0, big: bool = False,
        h: int = H, w: int = W) -> ImagePayload:
    """Raw payload from tightly packed rows, optionally padding each row with 0xAB."""
    row = w * bpp
    assert len(packed) == row * h
    if pad:
        rows = np.frombuffer(packed, np.uint8).reshape(h, row)
        filler = np.full((h, pad), 0xAB, np.uint8)
        packed = np.concatenate([rows, filler], axis=1).tobytes()
    step = row + pad if pad else 0
    return ImagePayload("raw", encoding, packed, w, h, step, big)


def compressed(fmt: str, data: bytes | npt.NDArray[np.uint8]) -> ImagePayload:
    return ImagePayload("compressed", fmt, bytes(data))


def imencode(ext: str, img: npt.NDArray[np.generic], params: list[int] | None = None) -> bytes:
    ok, buf = cv2.imencode(ext, img, params or [])
    assert ok
    return bytes(buf)


def bt601_gray(bgr: U8) -> npt.NDArray[np.float64]:
    b, g, r = (bgr[..., i].astype(np.float64) for i in range(3))
    return 0.299 * r + 0.587 * g + 0.114 * b


# ------------------------------------------------------------- raw encoders

def mosaic(bgr: U8, pattern: str) -> U8:
    """Sample a BGR image on a ROS colour filter array ('rggb' = R G / G B)."""
    out = np.empty(bgr.shape[:2], np.uint8)
    for k, colour in enumerate(pattern):
        dy, dx = divmod(k, 2)
        out[dy::2, dx::2] = bgr[dy::2, dx::2, BGR_INDEX[colour]]
    return out


def yuv422(bgr: U8, order: str) -> tuple[bytes, npt.NDArray[np.float64]]:
    """Pack BGR as 4:2:2 ('uyvy' or 'yuyv') with BT.601 limited range (as cv2 decodes).

    Returns the bytes and the BGR a BT.601 decoder must produce from them.
    """
    b, g, r = (bgr[..., i].astype(np.float64) for i in range(3))
    y = 16 + 0.257 * r + 0.504 * g + 0.098 * b
    u = 128 - 0.148 * r - 0.291 * g + 0.439 * b
    v = 128 + 0.439 * r - 0.368 * g - 0.071 * b
    u2 = (u[:, 0::2] + u[:, 1::2]) / 2
    v2 = (v[:, 0::2] + v[:, 1::2]) / 2
    yq, uq, vq = (np.clip(np.rint(a), 0, 255).astype(np.uint8) for a in (y, u2, v2))
    packed = np.empty((bgr.shape[0], bgr.shape[1] // 2, 4), np.uint8)
    if order == "uyvy":
        packed[..., 0], packed[..., 1], packed[..., 2], packed[..., 3] = (
            uq, yq[:, 0::2], vq, yq[:, 1::2])
    else:
        packed[..., 0], packed[..., 1], packed[..., 2], packed[..., 3] = (
            yq[:, 0::2], uq, yq[:, 1::2], vq)
    yf = yq.astype(np.float64) - 16
    uf = np.repeat(uq.astype(np.float64) - 128, 2, axis=1)
    vf = np.repeat(vq.astype(np.float64) - 128, 2, axis=1)
    expected = np.stack([
        1.164 * yf + 2.018 * uf,
        1.164 * yf - 0.813 * vf - 0.391 * uf,
        1.164 * yf + 1.596 * vf,
    ], axis=-1)
    return packed.tobytes(), np.clip(expected, 0, 255)


LOSSLESS_COLOUR: dict[str, tuple[int, Callable[[U8, U8], bytes]]] = {
    # encoding: (bytes per pixel, encoder(bgr, alpha) -> bytes)
    "bgr8": (3, lambda bgr, a: bgr.tobytes()),
    "8UC3": (3, lambda bgr, a: bgr.tobytes()),
    "rgb8": (3, lambda bgr, a: np.ascontiguousarray(bgr[..., ::-1]).tobytes()),
    "bgra8": (4, lambda bgr, a: np.dstack([bgr, a]).tobytes()),
    "8UC4": (4, lambda bgr, a: np.dstack([bgr, a]).tobytes()),
    "rgba8": (4, lambda bgr, a: np.dstack([bgr[..., ::-1], a]).tobytes()),
}


def encode_raw(encoding: str, pad: int = 0, big: bool = False) -> tuple[ImagePayload, U8]:
    """A payload in ``encoding`` and the 8-bit BGR/grey image it holds."""
    bgr = scene()
    if encoding in LOSSLESS_COLOUR:
        bpp, enc = LOSSLESS_COLOUR[encoding]
        alpha = np.random.default_rng(9).integers(0, 256, (H, W), dtype=np.uint8)
        return raw(encoding, enc(bgr, alpha), bpp, pad=pad), bgr
    gray = gray_scene()
    if encoding in ("mono8", "8UC1"):
        return raw(encoding, gray.tobytes(), 1, pad=pad), gray
    if encoding in ("mono16", "16UC1"):
        low = np.random.default_rng(3).integers(0, 256, (H, W)).astype(np.uint16)
        v16 = gray.astype(np.uint16) * 256 + low
        return raw(encoding, v16.astype(">u2" if big else "<u2").tobytes(), 2,
                   pad=pad, big=big), gray
    if encoding == "32FC1":
        f = (gray.astype(np.float64) / 255).astype(">f4" if big else "<f4")
        return raw(encoding, f.tobytes(), 4, pad=pad, big=big), gray
    if encoding.startswith("bayer_"):
        return raw(encoding, mosaic(bgr, encoding[6:10]).tobytes(), 1, pad=pad), bgr
    order = "uyvy" if encoding in ("uyvy", "yuv422") else "yuyv"
    return raw(encoding, yuv422(bgr, order)[0], 2, pad=pad), bgr


# ------------------------------------------------------------- raw: lossless

def test_supported_list_is_what_the_brief_lists() -> None:
    assert set(SUPPORTED_RAW_ENCODINGS) == {
        "mono8", "mono16", "8UC1", "8UC3", "8UC4", "16UC1", "32FC1", "rgb8", "bgr8",
        "rgba8", "bgra8", "bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8",
        "yuv422", "uyvy", "yuyv", "yuv422_yuy2"}


@pytest.mark.parametrize("encoding", sorted(LOSSLESS_COLOUR))
def test_colour_raw_exact(encoding: str) -> None:
    payload, bgr = encode_raw(encoding)
    out = decode_bgr(payload)
    np.testing.assert_array_equal(out, bgr)
    gray = decode_gray(payload)
    assert np.abs(gray.astype(np.float64) - bt601_gray(bgr)).max() <= 1.0
    native = decode_native(payload)
    assert native.dtype == np.uint8
    assert native.shape == (H, W, LOSSLESS_COLOUR[encoding][0])
    np.testing.assert_array_equal(native[..., :3], bgr)


def test_alpha_is_kept_in_native_as_bgra() -> None:
    bgr = scene()
    alpha = np.arange(H * W, dtype=np.uint8).reshape(H, W)
    payload = raw("rgba8", np.dstack([bgr[..., ::-1], alpha]).tobytes(), 4)
    native = decode_native(payload)
    np.testing.assert_array_equal(native[..., 3], alpha)
    np.testing.assert_array_equal(native[..., :3], bgr)


@pytest.mark.parametrize("encoding", ["mono8", "8UC1"])
def test_mono8_exact_and_replicated(encoding: str) -> None:
    payload, gray = encode_raw(encoding)
    np.testing.assert_array_equal(decode_gray(payload), gray)
    out = decode_bgr(payload)
    for c in range(3):
        np.testing.assert_array_equal(out[..., c], gray)


@pytest.mark.parametrize("big", [False, True], ids=["le", "be"])
@pytest.mark.parametrize("encoding", ["mono16", "16UC1"])
def test_16bit_is_shifted_by_8(encoding: str, big: bool) -> None:
    payload, gray = encode_raw(encoding, big=big)
    np.testing.assert_array_equal(decode_gray(payload), gray)
    np.testing.assert_array_equal(decode_bgr(payload)[..., 1], gray)
    native = decode_native(payload)
    assert native.dtype == np.uint16 and native.shape == (H, W)
    expected16 = np.frombuffer(payload.data, ">u2" if big else "<u2").reshape(H, W)
    np.testing.assert_array_equal(native, expected16)


def test_16bit_extremes() -> None:
    values = np.array([[0, 255, 256, 511, 65280, 65535]], dtype="<u2")
    payload = raw("mono16", values.tobytes(), 2, h=1, w=6)
    np.testing.assert_array_equal(decode_gray(payload), [[0, 0, 1, 1, 255, 255]])


@pytest.mark.parametrize("big", [False, True], ids=["le", "be"])
def test_32fc1_unit_range(big: bool) -> None:
    payload, gray = encode_raw("32FC1", big=big)
    np.testing.assert_array_equal(decode_gray(payload), gray)
    native = decode_native(payload)
    assert native.dtype == np.float32 and native.shape == (H, W)
    np.testing.assert_allclose(native, gray / 255.0, rtol=1e-6)


def test_32fc1_clips_and_zeroes_nan() -> None:
    values = np.array([[np.nan, -1.0, 0.0, 0.5, 1.0, 7.0, np.inf, -np.inf]], dtype="<f4")
    payload = raw("32FC1", values.tobytes(), 4, h=1, w=8)
    np.testing.assert_array_equal(decode_gray(payload), [[0, 0, 0, 128, 255, 255, 255, 0]])


# ------------------------------------------------------------------- bayer

BAYER = ["bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8"]


@pytest.mark.parametrize("encoding", BAYER)
def test_bayer_uniform_colour_maps_channels(encoding: str) -> None:
    """A flat colour must come back as itself: catches a shifted OpenCV code."""
    flat = np.empty((H, W, 3), np.uint8)
    flat[...] = (10, 100, 200)  # B, G, R
    payload = raw(encoding, mosaic(flat, encoding[6:10]).tobytes(), 1)
    out = decode_bgr(payload)
    np.testing.assert_array_equal(out[2:-2, 2:-2], flat[2:-2, 2:-2])


@pytest.mark.parametrize("encoding", BAYER)
def test_bayer_keeps_measured_sites_and_interpolates(encoding: str) -> None:
    payload, bgr = encode_raw(encoding)
    out = decode_bgr(payload)
    pattern = encoding[6:10]
    inner = (slice(2, H - 2), slice(2, W - 2))  # OpenCV copies border rows/cols
    for k, colour in enumerate(pattern):
        dy, dx = divmod(k, 2)
        c = BGR_INDEX[colour]
        measured = np.zeros((H, W), bool)
        measured[dy::2, dx::2] = True
        site = measured[inner]
        np.testing.assert_array_equal(out[inner][..., c][site], bgr[inner][..., c][site])
    diff = np.abs(out[inner].astype(int) - bgr[inner].astype(int))
    assert diff.max() <= 8 and diff.mean() < 2.5


# --------------------------------------------------------------------- yuv

@pytest.mark.parametrize("encoding", ["yuv422", "uyvy", "yuyv", "yuv422_yuy2"])
def test_yuv422(encoding: str) -> None:
    order = "uyvy" if encoding in ("uyvy", "yuv422") else "yuyv"
    bgr = scene(noise=2)
    data, expected = yuv422(bgr, order)
    out = decode_bgr(raw(encoding, data, 2))
    assert np.abs(out.astype(np.float64) - expected).max() <= 2.0
    assert np.abs(out.astype(int) - bgr.astype(int)).max() <= 6


def test_yuv_orders_differ() -> None:
    """Decoding UYVY bytes as YUYV must not give the same picture."""
    data, _ = yuv422(scene(), "uyvy")
    a = decode_bgr(raw("uyvy", data, 2)).astype(int)
    b = decode_bgr(raw("yuyv", data, 2)).astype(int)
    assert np.abs(a - b).mean() > 20


# ------------------------------------------------------------- row padding

PAD_CASES = [(e, False) for e in SUPPORTED_RAW_ENCODINGS] + [
    ("mono16", True), ("16UC1", True), ("32FC1", True)]


@pytest.mark.parametrize(("encoding", "big"), PAD_CASES)
def test_row_padding_is_ignored(encoding: str, big: bool) -> None:
    packed, _ = encode_raw(encoding, big=big)
    padded, _ = encode_raw(encoding, pad=7, big=big)
    assert padded.step == len(packed.data) // H + 7
    for fn in (decode_bgr, decode_gray, decode_native):
        a, b = fn(packed), fn(padded)
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def test_step_zero_equals_exact_step_and_extra_trailing_bytes_ok() -> None:
    bgr = scene()
    tight = ImagePayload("raw", "bgr8", bgr.tobytes(), W, H, W * 3)
    loose = ImagePayload("raw", "bgr8", bgr.tobytes() + b"\0" * 5, W, H, 0)
    np.testing.assert_array_equal(decode_bgr(tight), bgr)
    np.testing.assert_array_equal(decode_bgr(loose), bgr)


def test_encoding_name_case_insensitive() -> None:
    payload, bgr = encode_raw("bgr8")
    upper = ImagePayload("raw", "BGR8", payload.data, W, H)
    np.testing.assert_array_equal(decode_bgr(upper), bgr)


# -------------------------------------------------------------- compressed

def test_png_round_trip_exact() -> None:
    bgr = scene(noise=60)
    payload = compressed("png", imencode(".png", bgr))
    np.testing.assert_array_equal(decode_bgr(payload), bgr)
    assert np.abs(decode_gray(payload).astype(np.float64) - bt601_gray(bgr)).max() <= 1.0


def test_jpeg_within_tolerance() -> None:
    bgr = scene(noise=2)
    payload = compressed("jpeg", imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95]))
    diff = np.abs(decode_bgr(payload).astype(int) - bgr.astype(int))
    assert diff.mean() < 3 and diff.max() < 40


def test_grey_png_replicated() -> None:
    gray = gray_scene()
    payload = compressed("mono8; png compressed mono8", imencode(".png", gray))
    np.testing.assert_array_equal(decode_gray(payload), gray)
    out = decode_bgr(payload)
    assert out.shape == (H, W, 3)
    for c in range(3):
        np.testing.assert_array_equal(out[..., c], gray)
    assert decode_native(payload).shape == (H, W)


def test_16bit_png_scaled() -> None:
    v16 = np.random.default_rng(4).integers(0, 65536, (H, W)).astype(np.uint16)
    payload = compressed("png", imencode(".png", v16))
    np.testing.assert_array_equal(decode_native(payload), v16)
    np.testing.assert_array_equal(decode_gray(payload), (v16 >> 8).astype(np.uint8))
    colour16 = np.dstack([v16, v16[::-1], 65535 - v16])
    out = decode_bgr(compressed("png", imencode(".png", colour16)))
    np.testing.assert_array_equal(out, (colour16 >> 8).astype(np.uint8))


def test_bgra_png_alpha_dropped() -> None:
    bgr = scene()
    bgra = np.dstack([bgr, np.full((H, W), 77, np.uint8)])
    payload = compressed("png", imencode(".png", bgra))
    np.testing.assert_array_equal(decode_bgr(payload), bgr)
    assert decode_native(payload).shape == (H, W, 4)


@pytest.mark.parametrize(
    ("fmt", "ext"),
    [
        ("jpeg", ".jpg"), ("jpg", ".jpg"), ("JPEG", ".jpg"), ("png", ".png"),
        ("bgr8; jpeg compressed bgr8", ".jpg"), ("rgb8; jpeg compressed bgr8", ".jpg"),
        ("rgb8; png compressed rgb8", ".png"), ("bgr8; png compressed bgr8", ".png"),
        ("webp", ".webp"), ("", ".png"), ("", ".jpg"), ("", ".webp"), ("", ".bmp"),
        ("", ".tiff"), ("image/png", ".png"),
    ],
)
def test_format_strings(fmt: str, ext: str) -> None:
    """Colour comes back in BGR whatever the format string says (bytes are sniffed)."""
    bgr = scene(noise=2)
    params = [cv2.IMWRITE_WEBP_QUALITY, 101] if ext == ".webp" else []
    payload = compressed(fmt, imencode(ext, bgr, params))
    assert is_decodable(payload) == (True, "")
    out = decode_bgr(payload)
    tol = 0 if ext in (".png", ".bmp", ".tiff", ".webp") else 12
    assert np.abs(out.astype(int) - bgr.astype(int)).max() <= tol
    # channel order: blue rises along x, red falls; a swap would flip these signs
    assert out[:, -1, 0].mean() - out[:, 0, 0].mean() > 100
    assert out[-1, -1, 2].astype(int) < out[0, 0, 2]


def test_mono8_jpeg_format() -> None:
    gray = np.tile(np.linspace(0, 255, W).astype(np.uint8), (H, 1))
    payload = compressed("mono8; jpeg compressed mono8", imencode(".jpg", gray))
    assert decode_native(payload).ndim == 2
    assert np.abs(decode_gray(payload).astype(int) - gray.astype(int)).max() <= 8


# ------------------------------------------------------------------ errors

def _jpeg() -> bytes:
    return imencode(".jpg", scene())


ERROR_CASES: list[tuple[str, ImagePayload, str]] = [
    ("truncated", ImagePayload("raw", "mono8", b"\0" * 1000, 640, 480),
     r"raw mono8 image 640x480 needs 307200 bytes, message has 1000"),
    ("truncated-step", ImagePayload("raw", "bgr8", b"\0" * (100 * 10 - 1), 30, 10, 100),
     r"needs 1000 bytes, message has 999"),
    ("step-too-small", ImagePayload("raw", "rgb8", b"\0" * 9000, 30, 10, 89),
     r"step 89, less than width\*bytes_per_pixel = 90"),
    ("step-too-small-16", ImagePayload("raw", "mono16", b"\0" * 9000, 30, 10, 59),
     r"step 59.*= 60"),
    ("unknown-encoding", ImagePayload("raw", "rgb16_weird", b"\0" * 100, 5, 5),
     r"encoding 'rgb16_weird' is not supported"),
    ("zero-size", ImagePayload("raw", "mono8", b"", 0, 480), r"invalid size 0x480"),
    ("odd-yuv", ImagePayload("raw", "yuv422", b"\0" * 60, 5, 6), r"width 5 must be even"),
    ("compressedDepth", ImagePayload("compressed", "16UC1; compressedDepth png", _jpeg()),
     r"compressedDepth is not supported \(depth images are not camera frames\)"),
    ("compressedDepth-bare", ImagePayload("compressed", "compressedDepth", b"\x89PNG"),
     r"compressedDepth is not supported"),
    ("garbage-jpeg", ImagePayload("compressed", "jpeg", bytes(range(256)) * 4),
     r"JPEG data"),
    ("garbage-ros-format", ImagePayload("compressed", "bgr8; jpeg compressed bgr8",
                                        b"hello world" * 20), r"JPEG data"),
    ("garbage-unknown", ImagePayload("compressed", "h264", b"\0\0\0\x01gB" * 30),
     r"H264 data"),
    ("garbage-sniffed", ImagePayload("compressed", "", b"not an image at all"),
     r"image data"),
    ("empty", ImagePayload("compressed", "png", b""), r"has no data"),
    ("kind", ImagePayload("video", "h264", b"x"),  # type: ignore[arg-type]
     r"unknown image payload kind 'video'"),
]


@pytest.mark.parametrize(("payload", "pattern"), [c[1:] for c in ERROR_CASES],
                         ids=[c[0] for c in ERROR_CASES])
def test_errors(payload: ImagePayload, pattern: str) -> None:
    for fn in (decode_bgr, decode_gray, decode_native):
        with pytest.raises(ImageDecodeError, match=pattern):
            fn(payload)
    ok, reason = is_decodable(payload)
    assert not ok
    assert reason


def test_is_decodable_reason_matches_raw_error() -> None:
    payload = ImagePayload("raw", "mono8", b"\0" * 1000, 640, 480)
    assert is_decodable(payload) == (
        False, "raw mono8 image 640x480 needs 307200 bytes, message has 1000")


def test_truncated_jpeg_body_with_valid_header() -> None:
    """is_decodable only looks at the header; decoding reports the broken stream."""
    payload = compressed("jpeg", _jpeg()[:20])
    assert is_decodable(payload)[0]
    with pytest.raises(ImageDecodeError, match="JPEG data does not decode"):
        decode_bgr(payload)


@pytest.mark.parametrize("encoding", SUPPORTED_RAW_ENCODINGS)
def test_is_decodable_true_for_valid_raw(encoding: str) -> None:
    payload, _ = encode_raw(encoding, pad=3)
    assert is_decodable(payload) == (True, "")


# ------------------------------------------------------- shapes and layout

SHAPE_CASES = [*SUPPORTED_RAW_ENCODINGS, "png", "jpeg", "png-gray"]


def _shape_payload(name: str) -> ImagePayload:
    if name == "png":
        return compressed("png", imencode(".png", scene()))
    if name == "jpeg":
        return compressed("jpeg", imencode(".jpg", scene()))
    if name == "png-gray":
        return compressed("png", imencode(".png", gray_scene()))
    return encode_raw(name, pad=5)[0]


@pytest.mark.parametrize("name", SHAPE_CASES)
def test_output_shapes_dtypes_contiguity(name: str) -> None:
    payload = _shape_payload(name)
    src = np.frombuffer(payload.data, np.uint8)
    bgr = decode_bgr(payload)
    gray = decode_gray(payload)
    native = decode_native(payload)
    assert bgr.shape == (H, W, 3) and bgr.dtype == np.uint8
    assert gray.shape == (H, W) and gray.dtype == np.uint8
    assert native.shape[:2] == (H, W)
    for arr in (bgr, gray, native):
        assert arr.flags.c_contiguous and arr.flags.writeable
        assert not np.shares_memory(arr, src)


def test_packed_bgr8_output_is_a_copy() -> None:
    bgr = scene()
    data = bytearray(bgr.tobytes())
    payload = ImagePayload("raw", "bgr8", bytes(data), W, H)
    out = decode_bgr(payload)
    out[...] = 0
    np.testing.assert_array_equal(decode_bgr(payload), bgr)
