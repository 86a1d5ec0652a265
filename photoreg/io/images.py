"""Image I/O and colour transfer: sRGB <-> linear, 8/16-bit PNG, EXR (OpenEXR), all atomic."""
from __future__ import annotations

import functools
import os
import re
from pathlib import Path

import cv2
import numpy as np

from .atomic import atomic_path


def _srgb_eotf(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


SRGB_TO_LINEAR = _srgb_eotf(np.arange(256, dtype=np.float32) / 255.0)  # each 8-bit code's linear value


def srgb_to_linear(img: np.ndarray) -> np.ndarray:
    """8-bit (or [0,1] float) sRGB -> linear float32 in [0,1] (IEC 61966-2-1 EOTF); 8-bit by table lookup
    (cv2.LUT: 3-4x faster than numpy indexing at 640x480)."""
    if img.dtype == np.uint8:
        return cv2.LUT(img, SRGB_TO_LINEAR.reshape(1, 256))
    return _srgb_eotf(img.astype(np.float32))


def _srgb_oetf8(x: np.ndarray) -> np.ndarray:
    """Linear float32 in [0, 1] -> 8-bit sRGB (IEC 61966-2-1 OETF, rounded): the definition the table follows."""
    y = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.round(y * 255.0), 0, 255).astype(np.uint8)


SRGB_BUCKETS = 1 << 20  # linear [0, 1] in this many equal buckets: x * SRGB_BUCKETS is exact in float32


@functools.cache
def _srgb_table() -> tuple[np.ndarray, np.ndarray]:
    """(code, mixed), one entry per bucket [k, k + 1) / SRGB_BUCKETS (and one for x = 1): the 8-bit code at the
    bucket's low end, and whether the bucket's high end has another (an 8-bit step inside it: 249 of the 2^20)."""
    k = np.arange(SRGB_BUCKETS + 1, dtype=np.float64)
    lo = (k / SRGB_BUCKETS).astype(np.float32)
    hi = np.minimum(np.nextafter(((k + 1) / SRGB_BUCKETS).astype(np.float32), np.float32(0)), np.float32(1))
    code = _srgb_oetf8(lo)
    return code, _srgb_oetf8(hi) != code


def linear_to_srgb(img: np.ndarray) -> np.ndarray:
    """Linear float -> 8-bit sRGB (clipped to [0,1], non-finite values become 0, +inf 255). By table: each value's
    bucket gives its code, and the few values in a bucket that holds an 8-bit step are converted by the definition
    (_srgb_oetf8), so every code is the definition's (the whole formula took 2x as long at 640x480: 9-15 against 5-6
    ms on the 2-core CPU, once per written composite and video frame)."""
    code, mixed = _srgb_table()
    x = np.nan_to_num(np.asarray(img, np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    np.clip(x, 0.0, 1.0, out=x)
    x *= np.float32(SRGB_BUCKETS)   # a power of two: exact, and floor(x) is the bucket
    k = x.astype(np.int32)
    out = np.take(code, k)
    fix = np.take(mixed, k)
    if fix.any():
        out[fix] = _srgb_oetf8(x[fix] / np.float32(SRGB_BUCKETS))
    return out


_FILL = re.compile(rb"\xff*")


def after_fill(data: bytes, i: int) -> int:
    """The index of the first byte at or after i that is not 0xFF (JPEG fill bytes): a regular expression's run in C,
    since a run of millions of them walked a byte at a time took seconds."""
    return _FILL.match(data, i).end()


def jpeg_cut_short(data: bytes) -> bool:
    """Whether JPEG data end before their end-of-image marker: a file cut short, which OpenCV decodes with the
    missing rows grey and only a warning on stderr. Walks the segments from the start (each skipped by its length,
    an EXIF thumbnail with them) and each scan's entropy-coded data to the next marker (stuffed 0xFF00 and restart
    markers are data), so whatever follows the image (some cameras append a video) is never read. Data that are no
    JPEG's structure are left to the decoder (False)."""
    n = len(data)
    if data[:2] != b"\xff\xd8":
        return False
    i = 2
    while True:
        if i >= n:
            return True
        if data[i] != 0xFF:
            return False
        i = after_fill(data, i)            # fill bytes before a marker
        if i >= n:
            return True
        marker = data[i]
        i += 1
        if marker == 0xD9:                 # end of image
            return False
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:
            continue
        if i + 2 > n:
            return True
        i += (data[i] << 8) | data[i + 1]  # the segment's length counts its own two bytes
        if i > n:
            return True
        if marker == 0xDA:                 # a scan: its entropy-coded data run to the next real marker
            while True:
                j = data.find(b"\xff", i)
                if j < 0 or j + 1 >= n:
                    return True
                if data[j + 1] == 0x00 or 0xD0 <= data[j + 1] <= 0xD7:
                    i = j + 2
                    continue
                i = j
                break


# Colour decoded as stored: OpenCV's IMREAD_COLOR turns an image by its EXIF orientation, which depth (read
# unchanged) is not, so a phone's upside-down JPEG came out turned against its depth.
COLOR_FLAGS = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION


def _imread(path: str | os.PathLike, flags: int, what: str) -> np.ndarray:
    """cv2.imdecode of the file with errors that name it: missing, empty, not a readable `what` (OpenCV's own
    errors, e.g. a header claiming a size past its limits, among them), or a JPEG cut short."""
    try:
        data = Path(path).read_bytes()
    except (FileNotFoundError, IsADirectoryError):
        raise FileNotFoundError(f"{path}: no such file") from None
    if not data:
        raise ValueError(f"{path}: empty file (0 bytes)")
    if jpeg_cut_short(data):
        raise ValueError(f"{path}: JPEG data cut short (no end-of-image marker after the last scan)")
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as e:
        raise ValueError(f"{path}: not a readable {what} ({str(e).strip().rpartition(chr(10))[2]})") from None
    if img is None:
        raise ValueError(f"{path}: not a readable {what}")
    return img


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """Any colour image OpenCV reads -> HxWx3 uint8 RGB, its pixels as stored (COLOR_FLAGS); clear error naming
    the file."""
    return cv2.cvtColor(_imread(path, COLOR_FLAGS, "colour image"), cv2.COLOR_BGR2RGB)


DEPTH_EXR_CHANNELS = ("Z", "Y", "R", "depth", "distance")   # a depth EXR's channel where it has several


def _read_exr_depth(path: str | os.PathLike) -> np.ndarray:
    """The depth channel of an OpenEXR file (its only channel, else the first of DEPTH_EXR_CHANNELS it has) as
    float32: OpenCV's EXR reader is disabled in its wheels."""
    import OpenEXR

    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            ch = f.channels()
            names = list(ch) if len(ch) == 1 else [n for n in DEPTH_EXR_CHANNELS if n in ch]
            if not names:
                raise ValueError(f"{path}: depth EXR with channels {', '.join(sorted(ch))}: expected one channel, "
                                 f"or one named {', '.join(DEPTH_EXR_CHANNELS)}")
            return np.asarray(ch[names[0]].pixels, dtype=np.float32)
    except (RuntimeError, OSError) as e:
        raise ValueError(f"{path}: not a readable depth image ({e})") from None


def read_depth_raw(path: str | os.PathLike) -> np.ndarray:
    """Single-channel 16-bit or float depth image in its stored units (not metres); clear error naming the file."""
    if Path(path).suffix.lower() == ".exr":
        if not Path(path).is_file():
            raise FileNotFoundError(f"{path}: no such file")
        return _read_exr_depth(path)
    img = _imread(path, cv2.IMREAD_UNCHANGED, "depth image")
    if img.ndim != 2:
        raise ValueError(f"{path}: depth image has {img.shape[2]} channels, expected 1")
    if img.dtype != np.uint16 and not np.issubdtype(img.dtype, np.floating):
        raise ValueError(f"{path}: depth image is {img.dtype}, expected 16-bit or float")
    return img


# A depth map of another size than its colour image is taken as registered to it at another resolution (the same
# field of view: phones' LiDAR, 256 x 192 under 1920 x 1440 colour) where the two shapes agree within this share.
ASPECT_TOLERANCE = 0.01


def registered_depth(raw: np.ndarray, width: int, height: int, where: str) -> np.ndarray:
    """A depth map registered to a width x height colour image, at the colour's size: as it is where it has that
    size, scaled by the nearest pixel centre (values and holes kept) where it has another of the same shape
    (ASPECT_TOLERANCE); ValueError starting with `where` for another shape."""
    h, w = raw.shape[:2]
    if (h, w) == (height, width):
        return raw
    if abs(w * height - h * width) > ASPECT_TOLERANCE * h * width:
        raise ValueError(f"{where}: depth is {w}x{h} but colour is {width}x{height}, another shape: depth must be "
                         "registered to the colour image")
    return cv2.resize(raw, (width, height), interpolation=cv2.INTER_NEAREST_EXACT)


def write_png_rgb(path: str | os.PathLike, rgb8: np.ndarray) -> None:
    with atomic_path(path, ".png") as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR)):
            raise OSError(f"{path}: could not write PNG")


def write_png16(path: str | os.PathLike, img16: np.ndarray) -> None:
    with atomic_path(path, ".png") as tmp:
        if not cv2.imwrite(str(tmp), img16.astype(np.uint16)):
            raise OSError(f"{path}: could not write 16-bit PNG")


def write_exr(path: str | os.PathLike, rgb: np.ndarray, half: bool = False) -> None:
    """Linear HxWx3 -> OpenEXR (RGB channels): float32, ZIP-compressed; with `half` 16-bit floats (11 significant
    bits: 5e-4 relative, finer than the 8-bit frames a composite comes from), PIZ-compressed (a 640x480 composite
    of TUM: 35 ms and 0.7 MB to write, against 89 ms and 2.1 MB as float32 with ZIP on the 2-core CPU)."""
    import OpenEXR

    header = {"compression": OpenEXR.PIZ_COMPRESSION if half else OpenEXR.ZIP_COMPRESSION,
              "type": OpenEXR.scanlineimage}
    with atomic_path(path, ".exr") as tmp:
        OpenEXR.File(header, {"RGB": np.ascontiguousarray(rgb, dtype=np.float16 if half else np.float32)}).write(
            str(tmp))


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """An OpenEXR image -> HxWx3 float32 RGB (a luminance-only Y image as grey); ValueError naming the file and its
    channels otherwise."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        ch = f.channels()
        for name in ("RGB", "RGBA"):
            if name in ch:
                return np.asarray(ch[name].pixels, dtype=np.float32)[..., :3]
        names = "RGB" if all(c in ch for c in "RGB") else "YYY" if "Y" in ch and not {"RY", "BY"} & set(ch) else None
        if names is None:
            raise ValueError(f"{path}: EXR channels {sorted(ch)}: expected R, G and B (or Y alone)")
        return np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in names], axis=-1)


def read_hdr(path: str | os.PathLike) -> np.ndarray:
    """Radiance .hdr / .exr environment map -> HxWx3 linear float32 RGB."""
    p = Path(path)
    if p.suffix.lower() == ".exr":
        return read_exr(p)
    img = cv2.imread(str(p), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{path}: not a readable HDR image")
    if not np.issubdtype(img.dtype, np.floating):   # an 8- or 16-bit picture: display values, not radiance
        raise ValueError(f"{path}: a {img.dtype} image, not a high dynamic range one: give the environment as Radiance "
                         ".hdr or OpenEXR .exr (linear radiance)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32)
