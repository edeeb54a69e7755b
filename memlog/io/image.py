"""Decode camera image messages (compressed streams and raw ROS layouts) to pixels.

Conventions, chosen to match ``cv_bridge`` so frames look the same as in ROS tools:

* Colour output is BGR (OpenCV order); grey sources are replicated to 3 channels by
  :func:`decode_bgr`, colour is turned to grey with ``cv2.COLOR_BGR2GRAY`` by
  :func:`decode_gray`. Alpha is dropped, not composited.
* 16-bit to 8-bit: ``value >> 8`` (cv_bridge scales mono16 -> mono8 by 1/256; it rounds
  where we floor, so results differ by at most one level and 65535 never saturates).
* 32-bit float to 8-bit: the image is taken to be in ``[0, 1]``: clipped, times 255,
  rounded; NaN becomes 0 (cv_bridge's ``convertTo(..., 255)`` does the same).
* Bayer: ROS names the colour filter by its top-left 2x2 block read row-major, OpenCV by
  the second row's 2nd/3rd pixels, so ROS ``bayer_rggb8`` is ``cv2.COLOR_BayerBG2BGR``,
  ``bggr`` -> ``RG``, ``gbrg`` -> ``GR``, ``grbg`` -> ``GB`` (cv_bridge's table).
* Raw rows are read through a strided view honouring ``step``; only the ``width`` pixels
  of each row are copied once into the C-contiguous output.
"""

from __future__ import annotations

from collections.abc import Callable
import struct
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from memlog.runtime import DEFAULT_MAX_PIXELS as _DEFAULT_MAX_PIXELS, current, install
from memlog.errors import ImageDecodeError
from memlog.io.types import ImagePayload

__all__ = [
    "DEFAULT_MAX_PIXELS",
    "SUPPORTED_RAW_ENCODINGS",
    "decode_bgr",
    "decode_bgr_reduced",
    "decode_gray",
    "jpeg_reduction",
    "decode_native",
    "image_size",
    "is_decodable",
    "max_pixels",
    "set_max_pixels",
]

#: Largest image (width x height) memlog decodes unless told otherwise (``--max-pixels``,
#: ``MEMLOG_MAX_PIXELS``): 100 MP is ten times a 4K frame; a frame above it is reported and
#: skipped before any pixel is decoded (a 1 MB PNG can declare 32768x32768 = 1 GP, 3 GB as BGR).
#: (:data:`memlog.runtime.DEFAULT_MAX_PIXELS`.)
DEFAULT_MAX_PIXELS = _DEFAULT_MAX_PIXELS


def max_pixels() -> int:
    """The decoded-pixel cap in force: that of the runtime context (:func:`memlog.runtime.current`;
    ``--max-pixels``, ``MEMLOG_MAX_PIXELS``, else :data:`DEFAULT_MAX_PIXELS`)."""
    return current().max_pixels


def set_max_pixels(n: int) -> None:
    """Set the cap for this process and the worker processes it starts: installs the runtime
    context in force with ``max_pixels=n`` (executors give it to their workers)."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"max pixels must be an integer >= 1, got {n!r}")
    install(current().replace(max_pixels=n))


def _check_pixels(w: int, h: int, what: str) -> None:
    cap = max_pixels()
    if w * h > cap:
        raise ImageDecodeError(f"{what} is {w}x{h} = {w * h / 1e6:.1f} MP, more than the cap of {cap} pixels "
                               "(--max-pixels); not decoded")

Array = npt.NDArray[np.generic]
_Convert = Callable[[Array], Array]


# --------------------------------------------------------------------------- raw


@dataclass(frozen=True)
class _RawLayout:
    """How one ROS raw encoding lays out a pixel and how to bring it to BGR/grey."""

    channels: int  # values per pixel as stored (2 for packed YUV 4:2:2)
    dtype: str  # numpy kind+size without byte order: "u1", "u2", "f4"
    convert: _Convert | None = None  # stored layout -> native (BGR/BGRA/grey)
    even_width: bool = False  # packed 4:2:2 needs pixel pairs

    @property
    def bytes_per_pixel(self) -> int:
        return self.channels * np.dtype(self.dtype).itemsize


def _cvt(code: int) -> _Convert:
    def convert(arr: Array) -> Array:
        return np.asarray(cv2.cvtColor(arr, code))  # type: ignore[arg-type]

    return convert


_RAW_LAYOUTS: dict[str, _RawLayout] = {
    "mono8": _RawLayout(1, "u1"),
    "8UC1": _RawLayout(1, "u1"),
    "8UC3": _RawLayout(3, "u1"),  # cv_bridge treats 8UC3 as bgr8
    "8UC4": _RawLayout(4, "u1"),  # ... and 8UC4 as bgra8
    "bgr8": _RawLayout(3, "u1"),
    "bgra8": _RawLayout(4, "u1"),
    "rgb8": _RawLayout(3, "u1", _cvt(cv2.COLOR_RGB2BGR)),
    "rgba8": _RawLayout(4, "u1", _cvt(cv2.COLOR_RGBA2BGRA)),
    "mono16": _RawLayout(1, "u2"),
    "16UC1": _RawLayout(1, "u2"),
    "32FC1": _RawLayout(1, "f4"),
    # OpenCV's Bayer names are shifted relative to ROS's (see module docstring).
    "bayer_rggb8": _RawLayout(1, "u1", _cvt(cv2.COLOR_BayerBG2BGR)),
    "bayer_bggr8": _RawLayout(1, "u1", _cvt(cv2.COLOR_BayerRG2BGR)),
    "bayer_gbrg8": _RawLayout(1, "u1", _cvt(cv2.COLOR_BayerGR2BGR)),
    "bayer_grbg8": _RawLayout(1, "u1", _cvt(cv2.COLOR_BayerGB2BGR)),
    # ROS "yuv422" is UYVY (U0 Y0 V0 Y1); "yuv422_yuy2" is YUYV (Y0 U0 Y1 V0).
    "yuv422": _RawLayout(2, "u1", _cvt(cv2.COLOR_YUV2BGR_UYVY), even_width=True),
    "uyvy": _RawLayout(2, "u1", _cvt(cv2.COLOR_YUV2BGR_UYVY), even_width=True),
    "yuyv": _RawLayout(2, "u1", _cvt(cv2.COLOR_YUV2BGR_YUYV), even_width=True),
    "yuv422_yuy2": _RawLayout(2, "u1", _cvt(cv2.COLOR_YUV2BGR_YUYV), even_width=True),
}

SUPPORTED_RAW_ENCODINGS: tuple[str, ...] = tuple(_RAW_LAYOUTS)

_LAYOUT_BY_LOWER = {name.lower(): (name, layout) for name, layout in _RAW_LAYOUTS.items()}


@dataclass(frozen=True)
class _RawGeometry:
    name: str
    layout: _RawLayout
    step: int


def _raw_geometry(payload: ImagePayload) -> _RawGeometry:
    """Validate a raw payload's encoding, size, step and length (no pixel access)."""
    found = _LAYOUT_BY_LOWER.get(payload.encoding.strip().lower())
    if found is None:
        raise ImageDecodeError(
            f"raw image encoding {payload.encoding!r} is not supported "
            f"(supported: {', '.join(SUPPORTED_RAW_ENCODINGS)})"
        )
    name, layout = found
    w, h = payload.width, payload.height
    if w <= 0 or h <= 0:
        raise ImageDecodeError(f"raw {name} image has invalid size {w}x{h}")
    _check_pixels(w, h, f"raw {name} image")
    if layout.even_width and w % 2:
        raise ImageDecodeError(f"raw {name} image width {w} must be even (4:2:2 pixel pairs)")
    row_bytes = w * layout.bytes_per_pixel
    step = payload.step or row_bytes  # step 0 means tightly packed
    if step < row_bytes:
        raise ImageDecodeError(
            f"raw {name} image {w}x{h} has step {step}, "
            f"less than width*bytes_per_pixel = {row_bytes}"
        )
    needed = step * h
    if len(payload.data) < needed:
        raise ImageDecodeError(
            f"raw {name} image {w}x{h} needs {needed} bytes, message has {len(payload.data)}"
        )
    return _RawGeometry(name, layout, step)


def _raw_native(payload: ImagePayload) -> Array:
    """Raw payload -> native pixels; may be a read-only view of ``payload.data``."""
    geo = _raw_geometry(payload)
    layout = geo.layout
    dtype = np.dtype(layout.dtype)
    if dtype.itemsize > 1:
        dtype = dtype.newbyteorder(">" if payload.is_bigendian else "<")
    shape: tuple[int, ...] = (payload.height, payload.width)
    strides: tuple[int, ...] = (geo.step, layout.bytes_per_pixel)
    if layout.channels > 1:
        shape += (layout.channels,)
        strides += (dtype.itemsize,)
    view: Array = np.ndarray(shape, dtype=dtype, buffer=payload.data, strides=strides)
    if dtype.itemsize > 1:  # one copy: swaps bytes if needed, aligns, drops padding
        view = view.astype(dtype.newbyteorder("="), order="C")
    if layout.convert is None:
        return view
    try:
        return layout.convert(view)
    except cv2.error as exc:
        raise ImageDecodeError(f"raw {geo.name} image does not convert: {exc}") from exc


# ------------------------------------------------------------------- compressed

# Leading bytes of the streams cv2.imdecode reads in the opencv-python wheels.
_MAGIC: tuple[tuple[str, Callable[[bytes], bool]], ...] = (
    ("JPEG", lambda b: b.startswith(b"\xff\xd8\xff")),
    ("PNG", lambda b: b.startswith(b"\x89PNG\r\n\x1a\n")),
    ("WebP", lambda b: b[:4] == b"RIFF" and b[8:12] == b"WEBP"),
    ("BMP", lambda b: b.startswith(b"BM")),
    ("TIFF", lambda b: b[:4] in (b"II*\x00", b"MM\x00*")),
    ("GIF", lambda b: b[:6] in (b"GIF87a", b"GIF89a")),
    ("JPEG 2000", lambda b: b.startswith((b"\x00\x00\x00\x0cjP  \r\n\x87\n", b"\xff\x4f\xff\x51"))),
    ("PNM", lambda b: len(b) > 2 and b[:1] == b"P" and b[1:2] in b"1234567" and b[2:3].isspace()),
    ("Radiance HDR", lambda b: b.startswith((b"#?RADIANCE", b"#?RGBE"))),
    ("AVIF", lambda b: b[4:12] in (b"ftypavif", b"ftypavis")),
)


def _sniff(data: bytes) -> str | None:
    """Name of the image container ``data`` starts with, or None."""
    head = bytes(data[:16])
    return next((name for name, match in _MAGIC if match(head)), None)


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) an image stream declares in its header, without decoding it: PNG, JPEG,
    GIF, BMP, WebP and PNM; None for other containers or a header that does not parse."""
    b = bytes(data[:64])
    try:
        if b.startswith(b"\x89PNG\r\n\x1a\n") and b[12:16] == b"IHDR":
            w, h = struct.unpack(">II", b[16:24])
            return int(w), int(h)
        if b[:6] in (b"GIF87a", b"GIF89a"):
            w, h = struct.unpack("<HH", b[6:10])
            return int(w), int(h)
        if b.startswith(b"BM") and len(b) >= 26:
            w, h = struct.unpack("<ii", b[18:26])
            return abs(int(w)), abs(int(h))
        if b[:4] == b"RIFF" and b[8:12] == b"WEBP":
            kind = b[12:16]
            if kind == b"VP8 " and b[23:26] == b"\x9d\x01\x2a":
                w, h = struct.unpack("<HH", b[26:30])
                return int(w) & 0x3FFF, int(h) & 0x3FFF
            if kind == b"VP8L" and b[20] == 0x2F:
                bits = int.from_bytes(b[21:25], "little")
                return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
            if kind == b"VP8X":
                return int.from_bytes(b[24:27], "little") + 1, int.from_bytes(b[27:30], "little") + 1
            return None
        if b.startswith(b"\xff\xd8"):
            return _jpeg_size(data)
        if len(b) > 2 and b[:1] == b"P" and b[1:2] in b"1234567" and b[2:3].isspace():
            words = bytes(data[:256]).split(b"\n")
            nums: list[int] = []
            for line in words[1:]:
                line = line.split(b"#", 1)[0]
                nums += [int(x) for x in line.split()]
                if len(nums) >= 2:
                    return nums[0], nums[1]
    except (struct.error, ValueError, IndexError):
        return None
    return None


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """Width and height from the first SOF marker of a JPEG stream (markers walked, not decoded)."""
    at = 2
    n = len(data)
    while at + 4 <= n:
        if data[at] != 0xFF:
            return None
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            at += 2
            continue
        seg = int.from_bytes(data[at + 2 : at + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if at + 9 > n:
                return None
            h = int.from_bytes(data[at + 5 : at + 7], "big")
            w = int.from_bytes(data[at + 7 : at + 9], "big")
            return w, h
        if marker == 0xDA or seg < 2:  # start of scan before any frame header
            return None
        at += 2 + seg
    return None


def _format_codec(fmt: str) -> str:
    """Codec word of a format string: ``"bgr8; jpeg compressed bgr8"`` -> ``"jpeg"``."""
    text = fmt.split(";", 1)[1] if ";" in fmt else fmt
    words = text.split()
    return words[0].lower() if words else ""


def _check_compressed(payload: ImagePayload) -> str:
    """Reject what cannot be a camera frame; return a codec name for messages."""
    if "compresseddepth" in payload.encoding.lower():
        raise ImageDecodeError(
            "compressedDepth is not supported (depth images are not camera frames)"
        )
    if len(payload.data) == 0:
        raise ImageDecodeError(f"compressed image (format {payload.encoding!r}) has no data")
    codec = _format_codec(payload.encoding)
    return codec.upper() if codec else (_sniff(payload.data) or "image")


def _compressed_native(payload: ImagePayload) -> Array:
    """Compressed payload -> pixels as cv2.imdecode gives them (grey, BGR or BGRA).

    The byte stream is sniffed by OpenCV, so the format string only names things in
    messages. For ``"rgb8; jpeg compressed bgr8"`` style formats image_transport's
    compressed plugin converted the image to bgr8 before imencode (the part after
    "compressed" says so) and, on decode, converts imdecode's BGR back to the
    first-named encoding; the stored stream is a normal colour image, so imdecode's
    BGR is already the right colour and we return it unchanged. IMREAD_UNCHANGED keeps
    bit depth and alpha and ignores EXIF rotation (camera frames are stored as taken).
    """
    codec = _check_compressed(payload)
    dims = image_size(payload.data)
    if dims is not None:
        _check_pixels(dims[0], dims[1], f"{codec} image")
    buf = np.frombuffer(payload.data, dtype=np.uint8)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise ImageDecodeError(f"{codec} data does not decode: {exc}") from exc
    if img is None or img.size == 0:
        raise ImageDecodeError(
            f"{codec} data does not decode ({len(payload.data)} bytes, "
            f"format {payload.encoding!r})"
        )
    arr: Array = np.asarray(img)
    if dims is None:  # a container whose header memlog does not parse: check after the fact
        _check_pixels(int(arr.shape[1]), int(arr.shape[0]), f"{codec} image")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    return arr


# ----------------------------------------------------------------- conversions


def _native(payload: ImagePayload) -> Array:
    """Dispatch on ``payload.kind``; the result may still view ``payload.data``."""
    if payload.kind == "compressed":
        return _compressed_native(payload)
    if payload.kind == "raw":
        return _raw_native(payload)
    raise ImageDecodeError(f"unknown image payload kind {payload.kind!r}")


def _to_uint8(arr: Array) -> npt.NDArray[np.uint8]:
    """Bring any decoded depth to uint8 (16-bit: >> 8; float: [0, 1] -> [0, 255])."""
    if arr.dtype == np.uint8:
        return arr.astype(np.uint8, copy=False)
    if arr.dtype == np.uint16:
        return np.asarray(np.right_shift(arr, 8), dtype=np.uint8)
    if arr.dtype.kind == "f":
        clipped = np.clip(np.nan_to_num(np.asarray(arr, np.float64), nan=0.0), 0.0, 1.0)
        return np.asarray(np.rint(clipped * 255.0), dtype=np.uint8)
    raise ImageDecodeError(f"decoded pixels have unsupported type {arr.dtype}")


def _channels(arr: Array) -> int:
    channels = 1 if arr.ndim == 2 else int(arr.shape[2])
    if channels not in (1, 3, 4):
        raise ImageDecodeError(f"decoded image has unsupported shape {arr.shape}")
    return channels


def _owned(arr: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """C-contiguous, writeable array not sharing memory with the payload."""
    return np.require(arr, requirements=["C", "W", "O"])


# ------------------------------------------------------------------------- API


def decode_native(payload: ImagePayload) -> Array:
    """Decoded pixels before 8-bit conversion: grey (HxW), BGR or BGRA (HxWx3/4).

    Keeps the source depth: mono16/16UC1 and 16-bit PNGs stay uint16, 32FC1 stays
    float32 (native byte order). Raises :class:`ImageDecodeError`.
    """
    arr = _native(payload)
    _channels(arr)
    return np.require(arr, requirements=["C", "W", "O"])


def decode_bgr(payload: ImagePayload) -> npt.NDArray[np.uint8]:
    """Decode to an HxWx3 uint8 BGR array (C-contiguous). Raises :class:`ImageDecodeError`."""
    img = _to_uint8(_native(payload))
    channels = _channels(img)
    if channels == 1:
        img = np.asarray(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
    elif channels == 4:
        img = np.asarray(cv2.cvtColor(img, cv2.COLOR_BGRA2BGR), dtype=np.uint8)
    return _owned(img)


#: JPEG DCT-domain scaling of ``cv2.imdecode``: the factor -> the flag (colour output, 8 bits).
_REDUCED_FLAGS = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}


def jpeg_reduction(width: int, height: int, min_width: int, min_height: int) -> int:
    """The largest factor of 1, 2, 4, 8 by which JPEG decoding can scale a ``width`` x ``height``
    frame (libjpeg: ``ceil(width / f)`` x ``ceil(height / f)``) and still give at least
    ``min_width`` x ``min_height``."""
    best = 1
    for f in (2, 4, 8):
        if -(-width // f) >= min_width and -(-height // f) >= min_height:
            best = f
    return best


def decode_bgr_reduced(payload: ImagePayload, min_width: int, min_height: int) -> npt.NDArray[np.uint8]:
    """Decode to BGR like :func:`decode_bgr`, but a JPEG at the smallest of its full, 1/2, 1/4
    or 1/8 size that is still at least ``min_width`` x ``min_height`` (scaled in the DCT domain
    while decoding: less work than decoding in full and resizing); other images in full.

    For consumers that shrink frames to a small input themselves. Pixels differ from resizing
    the full decode, so nothing that must give the SPEC's scores (its 1135 x 1135 frame is
    resized from the full decode) uses it."""
    if payload.kind != "compressed" or _sniff(payload.data) != "JPEG":
        return decode_bgr(payload)
    codec = _check_compressed(payload)
    dims = image_size(payload.data)
    if dims is None:
        return decode_bgr(payload)
    _check_pixels(dims[0], dims[1], f"{codec} image")
    f = jpeg_reduction(dims[0], dims[1], min_width, min_height)
    if f == 1:
        return decode_bgr(payload)
    try:
        img = cv2.imdecode(np.frombuffer(payload.data, dtype=np.uint8), _REDUCED_FLAGS[f])
    except cv2.error as exc:
        raise ImageDecodeError(f"{codec} data does not decode: {exc}") from exc
    if img is None or img.size == 0:
        raise ImageDecodeError(f"{codec} data does not decode ({len(payload.data)} bytes, format {payload.encoding!r})")
    return _owned(np.asarray(img, dtype=np.uint8))


def decode_gray(payload: ImagePayload) -> npt.NDArray[np.uint8]:
    """Decode to an HxW uint8 grey array (C-contiguous). Raises :class:`ImageDecodeError`."""
    img = _to_uint8(_native(payload))
    channels = _channels(img)
    if channels == 3:
        img = np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
    elif channels == 4:
        img = np.asarray(cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY), dtype=np.uint8)
    return _owned(img)


def is_decodable(payload: ImagePayload) -> tuple[bool, str]:
    """Cheap check without decoding pixels: ``(True, "")`` or ``(False, reason)``.

    Raw payloads get the full size/step/length validation; compressed payloads must
    not be compressedDepth and must start like an image stream OpenCV reads (a corrupt
    body behind a valid header is only found by decoding).
    """
    try:
        if payload.kind == "raw":
            _raw_geometry(payload)
        elif payload.kind == "compressed":
            codec = _check_compressed(payload)
            dims = image_size(payload.data)
            if dims is not None:
                _check_pixels(dims[0], dims[1], f"{codec} image")
            if _sniff(payload.data) is None:
                raise ImageDecodeError(
                    f"{codec} data is not a recognised image stream "
                    f"(format {payload.encoding!r}, starts {bytes(payload.data[:8])!r})"
                )
        else:
            raise ImageDecodeError(f"unknown image payload kind {payload.kind!r}")
    except ImageDecodeError as exc:
        return False, str(exc)
    return True, ""
