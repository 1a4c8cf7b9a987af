"""Decoding camera images to linear RGB: RAW through rawpy/LibRaw, JPEG/PNG/TIFF/WebP through
OpenCV and tifffile, HEIC through pi-heif (libheif), each encoded file by the curve its colour
profile records (``seathru.io.icc``), plus the EXIF exposure metadata ingest needs.

RAW decoding (``decode_raw``) is LibRaw with every automatic adjustment off, so the output is the
demosaiced sensor signal ``(raw - black_c) / (white - black_c)`` per CFA channel c:

- black level per channel subtracted, white level from the file (``adjust_maximum_thr=0``: no
  lowering of the white point from the image content, ``no_auto_bright``: no histogram scaling);
- unit white balance (``user_wb=[1, 1, 1, 1]``; rawpy's default would be daylight multipliers),
  camera raw colour space, linear gamma ``(1, 1)``, 16-bit output. White balance and colour
  conversion are done by ingest afterwards, in float, without clipping;
- LibRaw's demosaic keeps the native sample of every CFA site (all its open-source algorithms:
  checked on the real DNG in tests/test_ingest.py); ``half_size`` bins each 2x2 block instead.
  The default, LINEAR, interpolates each channel from its own samples: the colour-difference
  algorithms (AHD, PPG, DCB, AAHD) copy green's texture into red and blue, and underwater, where
  one channel fades with range faster than green, that biases its water (docs/water.md);
- orientation: decoded with ``user_flip=0`` and rotated with ``seathru.radiometry.linearise.orient``
  using the file's flip (``raw.sizes.flip`` read before postprocessing, which is what rawpy's
  default ``user_flip=None`` applies), so the clipping mask, computed on the raw grid, turns with
  the image.

LibRaw prints some data errors ("Unexpected end of file") on stderr itself; the Python side sees
them as ``rawpy.LibRawError`` subclasses, turned here into ``DecodeError`` with a reason.

rawpy is imported lazily: worker processes set ``OMP_NUM_THREADS`` before LibRaw's OpenMP runtime
loads, and ``seathru --help`` stays fast.
"""

from __future__ import annotations

import functools
import io
import logging
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np
import tifffile
from PIL import Image

from seathru.io import icc
from seathru.radiometry import linearise, stored_encoding

# exifread logs "File format not recognized" at WARNING for every file it cannot parse; a
# missing EXIF block is an expected, recorded case here, not a warning.
logging.getLogger("exifread").setLevel(logging.ERROR)

#: File extensions LibRaw decodes (lower case, with the dot).
RAW_EXTENSIONS = frozenset(
    ".3fr .ari .arw .bay .cap .cr2 .cr3 .crw .dcr .dcs .dng .drf .eip .erf .fff .gpr .iiq .k25 "
    ".kdc .mdc .mef .mos .mrw .nef .nrw .obm .orf .pef .ptx .pxn .r3d .raf .raw .rwl .rw2 .rwz "
    ".sr2 .srf .srw .sti .x3f".split())
#: HEIF containers (a phone's HEIC photographs), decoded by libheif through pi-heif, which
#: applies the container's own rotation and mirroring (the EXIF orientation only repeats them).
HEIF_EXTENSIONS = frozenset({".heic", ".heif", ".hif"})
#: Encoded image extensions (kind decided by the recorded curve or the bit depth for PNG/TIFF).
ENCODED_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff", ".webp",
                                *HEIF_EXTENSIONS})
#: Image formats met on cards and drives that ingest does not read, and what to do instead.
UNREAD_FORMATS = {".avif": "AVIF", ".jxl": "JPEG XL", ".psd": "Photoshop", ".gif": "GIF",
                  ".bmp": "BMP", ".jp2": "JPEG 2000", ".exr": "OpenEXR"}
#: HEIF colour information (nclx) transfer characteristics (ITU-T H.273) ingest can follow.
_NCLX_TRANSFER = {13: "srgb", 8: "linear", 4: "gamma 2.2", 5: "gamma 2.8"}
#: What a file holds: camera RAW, linear values, or values encoded by a display curve (sRGB's,
#: or the power curve the file's colour profile records: ``srgb`` names them all).
ImageKind = Literal["raw", "linear", "srgb"]
#: TIFF tag holding an embedded ICC profile (InterColorProfile).
TIFF_ICC_TAG = 34675
#: The kinds in order of preference when a folder mixes them (RAW+JPEG pairs: raw wins).
KINDS: tuple[str, ...] = get_args(ImageKind)

#: LibRaw demosaic algorithms (rawpy.DemosaicAlgorithm names) in every rawpy build.
Demosaic = Literal["LINEAR", "VNG", "PPG", "AHD", "DCB", "DHT", "AAHD"]
SUPPORTED_DEMOSAIC: tuple[str, ...] = get_args(Demosaic)


class DecodeError(Exception):
    """A file that cannot be used as an image; the message is the reason (the caller names the
    file)."""


@dataclass
class ExifExposure:
    """Exposure and lens metadata; None = not recorded. ``orientation`` is the EXIF value 1-8;
    ``focal_length_mm``, ``focal_length_35mm``: the lens's focal length and its 35 mm
    equivalent (EXIF FocalLength, FocalLengthIn35mmFilm; the poses step starts COLMAP's focal
    length from the latter)."""

    exposure_time: float | None = None
    iso: float | None = None
    f_number: float | None = None
    orientation: int | None = None
    focal_length_mm: float | None = None
    focal_length_35mm: float | None = None
    source: dict[str, str] = field(default_factory=dict)


@dataclass
class DecodedImage:
    """A decoded image, oriented for display.

    ``image``: ``(H, W, 3)`` float32 linear (camera raw colour for RAW, as stored otherwise),
    1.0 = white level / top code. ``saturated`` / ``black_clipped``: ``(H, W)`` bool, before any
    dilation. ``metadata``: JSON-ready facts for the manifest.
    """

    image: np.ndarray
    saturated: np.ndarray
    black_clipped: np.ndarray
    kind: str
    exposure: ExifExposure
    camera_wb: np.ndarray | None = None
    colour_matrix: np.ndarray | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


# --- EXIF -----------------------------------------------------------------------------------

_EXIF_KEYS = {
    "exposure_time": ("EXIF ExposureTime", "Image ExposureTime"),
    "f_number": ("EXIF FNumber", "Image FNumber"),
    "iso": ("EXIF ISOSpeedRatings", "Image ISOSpeedRatings", "EXIF PhotographicSensitivity",
            "EXIF RecommendedExposureIndex", "EXIF ISOSpeed"),
}
_EXIF_LENS_KEYS = {
    "focal_length_mm": ("EXIF FocalLength", "Image FocalLength"),
    "focal_length_35mm": ("EXIF FocalLengthIn35mmFilm", "Image FocalLengthIn35mmFilm"),
}


def _tag_number(tag) -> float | None:
    try:
        value = float(tag.values[0])
    except (AttributeError, IndexError, TypeError, ValueError, ZeroDivisionError):
        return None
    return value if math.isfinite(value) and value > 0 else None


def _open_heif(path: Path, **options):
    import pi_heif

    try:
        return pi_heif.open_heif(path, **options)
    except Exception as exc:  # noqa: BLE001 - libheif's errors come as several types
        raise DecodeError(f"cannot be read as a HEIF image ({type(exc).__name__}: {exc})") from exc


def _exif_tags(path: Path) -> dict:
    import exifread

    if path.suffix.lower() in HEIF_EXTENSIONS:   # the EXIF block is an item of the container
        try:
            block = _open_heif(path).info.get("exif") or b""
        except DecodeError:
            return {}
        stream = io.BytesIO(block[6:] if block.startswith(b"Exif\x00\x00") else block)
        return exifread.process_file(stream, details=False)
    with open(path, "rb") as handle:
        return exifread.process_file(handle, details=False)


def read_exif(path: str | Path) -> tuple[ExifExposure, set[str]]:
    """Exposure time (s), ISO, f-number and orientation from the file's EXIF/TIFF tags (exifread).

    Returns the values and the set of field names whose tag is present (a tag present with a
    0 value, as in the Canon 550D DNG, means 'not recorded' and must not be replaced by a
    decoder default).
    """
    try:
        tags = _exif_tags(Path(path))
    except Exception:  # noqa: BLE001 - exifread raises many types on odd files; EXIF is optional
        tags = {}
    exposure = ExifExposure()
    present: set[str] = set()
    for name, keys in _EXIF_KEYS.items():
        for key in keys:
            if key in tags:
                present.add(name)
                value = _tag_number(tags[key])
                if value is not None:
                    setattr(exposure, name, value)
                    exposure.source[name] = "exif"
                    break
    if "Image Orientation" in tags:
        orientation = _tag_number(tags["Image Orientation"])
        exposure.orientation = int(orientation) if orientation else None
    for name, keys in _EXIF_LENS_KEYS.items():   # 0 = not recorded, as for the exposure
        value = next((v for v in map(_tag_number, (tags[k] for k in keys if k in tags))
                      if v is not None), None)
        setattr(exposure, name, value)
    return exposure, present


# --- RAW ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RawSettings:
    demosaic: str = "LINEAR"
    half_size: bool = False
    saturation_threshold: float = 0.98


def _libraw_message(exc: Exception) -> str:
    message = exc.args[0] if exc.args else ""
    if isinstance(message, bytes):
        message = message.decode("utf-8", "replace")
    return str(message) or type(exc).__name__


def _libraw_reason(exc: Exception) -> str:
    import rawpy

    message = _libraw_message(exc)
    if isinstance(exc, rawpy.LibRawFileUnsupportedError):
        hint = "not a raw format LibRaw supports, or the file is damaged"
    elif isinstance(exc, rawpy.LibRawIOError):
        hint = "read error: the file is truncated or damaged"
    elif isinstance(exc, rawpy.LibRawDataError):
        hint = "corrupt image data"
    elif isinstance(exc, (rawpy.LibRawTooBigError, rawpy.LibRawUnsufficientMemoryError,
                          rawpy.LibRawMemPoolOverflowError)):
        hint = "too large to decode with the memory available"
    else:
        hint = "LibRaw could not decode it"
    return f"{hint} (LibRaw {type(exc).__name__}: {message})"


def _merge_exposure(exif: ExifExposure, present: set[str], other) -> ExifExposure:
    """Fill fields whose EXIF tag is absent from LibRaw's parse (``raw.other``), which also
    covers formats exifread cannot parse (RAF, CR3)."""
    fallback = {"exposure_time": getattr(other, "shutter_speed", None),
                "iso": getattr(other, "iso_speed", None),
                "f_number": getattr(other, "aperture", None)}
    for name, value in fallback.items():
        if name in present or getattr(exif, name) is not None:
            continue
        if value is not None and math.isfinite(float(value)) and float(value) > 0:
            setattr(exif, name, float(value))
            exif.source[name] = "libraw"
    return exif


def decode_raw(path: str | Path, settings: RawSettings = RawSettings()) -> DecodedImage:
    """Decode a camera RAW file to linear camera RGB; raise ``DecodeError`` when it is unusable."""
    import rawpy

    path = Path(path)
    if settings.demosaic not in SUPPORTED_DEMOSAIC:
        raise ValueError(f"demosaic {settings.demosaic!r} is not one of {SUPPORTED_DEMOSAIC}")
    exif, present = read_exif(path)
    file_bytes = path.stat().st_size
    params = rawpy.Params(
        demosaic_algorithm=rawpy.DemosaicAlgorithm[settings.demosaic],
        half_size=settings.half_size, user_wb=[1.0, 1.0, 1.0, 1.0],
        output_color=rawpy.ColorSpace.raw, output_bps=16, gamma=(1.0, 1.0),
        no_auto_bright=True, adjust_maximum_thr=0.0, user_flip=0)
    try:
        with rawpy.imread(str(path)) as raw:
            mosaic = raw.raw_image_visible  # triggers unpack: most damaged files fail here
            sizes = raw.sizes
            flip = int(sizes.flip)  # before postprocess, which overwrites it with user_flip
            black = [float(v) for v in raw.black_level_per_channel]
            white = float(raw.white_level)
            white_c = raw.camera_white_level_per_channel
            if white_c is None or len(white_c) < 4 or min(white_c) <= 0:
                white_c = [white] * 4
            flat = raw.raw_type == rawpy.RawType.Flat and mosaic.ndim == 2
            if flat:
                colors = raw.raw_colors_visible
                saturated_raw, black_raw = linearise.raw_clipping(
                    mosaic, colors, white_c, settings.saturation_threshold)
            else:
                saturated_raw = black_raw = None
            reason = linearise.invalid_raw_reason(mosaic, file_bytes, sizes.raw_width,
                                                  sizes.raw_height, saturated_raw)
            if reason:
                raise DecodeError(reason)
            camera_wb = linearise.camera_wb_gains(raw.camera_whitebalance)
            matrix = linearise.usable_colour_matrix(np.asarray(raw.color_matrix))
            exif = _merge_exposure(exif, present, raw.other)
            pattern = "".join(raw.color_desc.decode()[i] for i in raw.raw_pattern.ravel()) \
                if flat and raw.raw_pattern is not None else None
            image16 = raw.postprocess(params)
    except rawpy.LibRawError as exc:
        raise DecodeError(_libraw_reason(exc)) from exc
    except rawpy.NotSupportedError as exc:
        raise DecodeError(f"not supported by this rawpy build: {exc}") from exc

    reason = linearise.invalid_image_reason(image16)
    if reason:
        raise DecodeError(reason)
    shape = image16.shape[:2]
    if flat and not settings.half_size and saturated_raw.shape == shape:
        saturated, black_clipped = saturated_raw, black_raw
    elif flat and settings.half_size and (
            (saturated_raw.shape[0] + 1) // 2, (saturated_raw.shape[1] + 1) // 2) == shape:
        saturated = linearise.block_any(saturated_raw, shape)
        black_clipped = linearise.block_any(black_raw, shape)
    else:
        # Non-Bayer sensors or unusual geometry: judge saturation on the output instead.
        level = (settings.saturation_threshold * white - min(black)) / max(white - min(black), 1)
        saturated = (image16 >= 65535 * min(level, 1.0)).any(axis=-1)
        black_clipped = np.zeros(shape, dtype=bool)
    # Anything LibRaw clipped at its 16-bit ceiling is saturated too.
    saturated = saturated | (image16 >= 65535).any(axis=-1)

    image = image16.astype(np.float32) / np.float32(65535.0)
    metadata = {
        "raw_size": [int(sizes.raw_width), int(sizes.raw_height)],
        "sensor_size": [int(sizes.width), int(sizes.height)],
        "flip": flip,
        "black_level": black,
        "white_level": white,
        "cfa_pattern": pattern,
        "demosaic": "half_size" if settings.half_size else settings.demosaic,
    }
    return DecodedImage(
        image=linearise.orient(image, flip), saturated=linearise.orient(saturated, flip),
        black_clipped=linearise.orient(black_clipped, flip), kind="raw", exposure=exif,
        camera_wb=camera_wb, colour_matrix=matrix, metadata=metadata)


# --- encoded images (JPEG, PNG, TIFF) -------------------------------------------------------

def _png_bit_depth(path: Path) -> int | None:
    with open(path, "rb") as handle:
        header = handle.read(29)
    if len(header) < 29 or header[:8] != b"\x89PNG\r\n\x1a\n" or header[12:16] != b"IHDR":
        return None
    return struct.unpack("B", header[24:25])[0]


@dataclass(frozen=True)
class RecordedCurve:
    """The curve an encoded file records for its values: ``encoding`` (``linear``, ``srgb``,
    ``gamma <g>``; None where the curve is none of them) and ``source`` (what recorded it)."""

    encoding: str | None
    source: str


def _profile_curve(profile: bytes | None) -> RecordedCurve | None:
    if not profile:
        return None
    name = icc.description(profile)
    source = f"ICC profile {name!r}" if name else "ICC profile"
    curves = icc.channel_curves(profile)
    return RecordedCurve(None if curves is None else stored_encoding.encoding_of_curves(curves),
                         source)


def recorded_curve(path: str | Path) -> RecordedCurve | None:
    """The curve from stored values to linear light that a PNG, TIFF or JPEG records: its
    embedded ICC profile's tone curves (``seathru.io.icc``), else a PNG's ``sRGB`` or ``gAMA``
    chunk; None where it records none (or cannot be read: decoding reports that).

    Example:
        >>> recorded_curve("images_wb/0001.png")  # doctest: +SKIP
        RecordedCurve(encoding='gamma 1.8', source="ICC profile 'ProPhoto RGB'")
    """
    try:
        stat = Path(path).stat()
    except OSError:
        return None
    return _recorded_curve(str(path), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=4096)
def _recorded_curve(name: str, mtime_ns: int, size: int) -> RecordedCurve | None:
    """:func:`recorded_curve`, once per file version: listing a folder asks each file's kind
    several times (subfolder counts, selection) and decoding asks again."""
    path = Path(name)
    suffix = path.suffix.lower()
    try:
        if suffix in (".tif", ".tiff"):
            with tifffile.TiffFile(path) as tif:
                tag = tif.pages[0].tags.get(TIFF_ICC_TAG)
                return _profile_curve(None if tag is None else bytes(tag.value))
        if suffix in HEIF_EXTENSIONS:
            info = dict(_open_heif(path).info)
        else:
            with Image.open(path) as image:
                info = dict(image.info)
    except Exception:  # noqa: BLE001 - an unreadable file is reported when decoding
        return None
    from_profile = _profile_curve(info.get("icc_profile"))
    if from_profile is not None:
        return from_profile
    if suffix in HEIF_EXTENSIONS and info.get("nclx_profile"):
        code = info["nclx_profile"].get("transfer_characteristics")
        return RecordedCurve(_NCLX_TRANSFER.get(code), f"HEIF colour information (transfer {code})")
    if suffix != ".png":
        return None
    if "srgb" in info:
        return RecordedCurve("srgb", "PNG sRGB chunk")
    if info.get("gamma"):
        x = np.linspace(0.0, 1.0, icc.CURVE_SAMPLES)
        curve = x ** (1.0 / float(info["gamma"]))
        return RecordedCurve(stored_encoding.encoding_of_curves(curve[None]),
                             f"PNG gAMA {float(info['gamma']):g}")
    return None


def detect_kind(path: str | Path) -> str | None:
    """``raw``, ``linear`` or ``srgb`` (display-encoded) from the extension and, for PNG and
    TIFF, the curve the file records (:func:`recorded_curve`), else the stored bit depth
    (16-bit or float: linear; 8-bit: sRGB); None for files that are not images by extension."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in RAW_EXTENSIONS:
        return "raw"
    if suffix in (".jpg", ".jpeg", ".webp"):
        return "srgb"
    if suffix not in ENCODED_EXTENSIONS:
        return None
    recorded = recorded_curve(path)
    if recorded is not None:   # a curve none of ours is still not linear's
        return "linear" if recorded.encoding == "linear" else "srgb"
    if suffix in HEIF_EXTENSIONS:
        return "srgb"   # 8- and 10-bit HEIF hold display-encoded values
    try:
        if suffix == ".png":
            return "linear" if (_png_bit_depth(path) or 8) > 8 else "srgb"
        with tifffile.TiffFile(path) as tif:
            return "srgb" if tif.pages[0].dtype == np.uint8 else "linear"
    except Exception:  # noqa: BLE001 - an unreadable header is reported when decoding
        return "srgb" if suffix == ".png" else "linear"


def jpeg_cut_short(data: bytes) -> bool:
    """Whether a JPEG file stops before its end-of-image marker, as a copy cut short does.

    OpenCV's decoder only warns on stderr and fills the missing rows grey. The segments before
    the first scan are skipped by their lengths (an EXIF thumbnail holds an end marker of its
    own); in the scan data a 0xFF byte is always followed by 0x00 or a restart marker, so the
    first 0xFF 0xD9 after the scan header is the image's end. A stream laid out otherwise is
    left to the decoder (False).

    Args:
        data: the file's bytes.

    Returns:
        True where the data ends before the end marker.

    Example:
        >>> ok, jpeg = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
        >>> jpeg_cut_short(jpeg.tobytes()), jpeg_cut_short(jpeg.tobytes()[:-40])
        (False, True)
    """
    if data[:2] != b"\xff\xd8":
        return False
    position = 2
    while position + 4 <= len(data):
        if data[position] != 0xFF:
            return False
        marker = data[position + 1]
        if marker == 0xFF:  # fill byte before a marker
            position += 1
        elif marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            position += 2
        elif marker == 0xD9:  # an end before any scan
            return False
        else:
            end = position + 2 + int.from_bytes(data[position + 2:position + 4], "big")
            if marker == 0xDA:  # start of scan
                return data.find(b"\xff\xd9", end) < 0
            position = end
    return True


def read_stored_array(path: Path) -> np.ndarray:
    """An encoded image file's values as it stores them, ``(H, W, 3)`` uint8, uint16 or float,
    not yet oriented by its EXIF (a HEIF container's own rotation is applied by libheif).

    Raises:
        DecodeError: the file cannot be read, naming why (cut short, damaged, another layout).
    """
    if path.suffix.lower() in HEIF_EXTENSIONS:
        heif = _open_heif(path, convert_hdr_to_8bit=False)
        try:
            # a copy: the array interface points into the HEIF object's own buffer, freed with it
            array = np.array(heif, copy=True)
        except Exception as exc:  # noqa: BLE001 - a damaged HEVC stream fails here
            raise DecodeError(f"its HEIF image data cannot be decoded ({type(exc).__name__}: "
                              f"{exc})") from exc
        bits = int(heif.info.get("bit_depth") or 8)
        if array.dtype == np.uint16 and 8 < bits < 16:   # 10/12-bit codes come shifted to 16
            top = (1 << bits) - 1
            array = np.round((array >> (16 - bits)) * (65535.0 / top)).astype(np.uint16)
    elif path.suffix.lower() in (".tif", ".tiff"):
        try:
            with tifffile.TiffFile(path) as tif:
                array = tif.pages[0].asarray()
        except Exception as exc:  # noqa: BLE001 - tifffile raises many types on damaged files
            raise DecodeError(f"cannot be read as a TIFF ({type(exc).__name__}: {exc})") from exc
        if array.ndim == 3 and array.shape[0] in (3, 4) and array.shape[2] not in (3, 4):
            array = np.moveaxis(array, 0, -1)  # planar-separate TIFF
    else:
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise DecodeError(f"cannot be read ({exc.strerror or exc})") from exc
        if path.suffix.lower() in (".jpg", ".jpeg") and jpeg_cut_short(data):
            raise DecodeError("the JPEG data stops before its end-of-image marker (a copy cut "
                              "short?): the decoder would fill the missing rows grey; copy the "
                              "file again from the camera")
        # never applies EXIF orientation
        array = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if array is None:
            raise DecodeError("cannot be read as an image (corrupt, truncated or unsupported)")
        if array.ndim == 3:
            array = cv2.cvtColor(array, cv2.COLOR_BGRA2RGB if array.shape[2] == 4
                                 else cv2.COLOR_BGR2RGB)
    if array.ndim == 2:
        array = np.repeat(array[..., None], 3, axis=-1)
    if array.ndim != 3 or array.shape[2] < 3:
        raise DecodeError(f"unsupported image layout {array.shape} (expected H x W x 3)")
    return array[..., :3]


def _display_encoding(path: Path) -> tuple[str, str, list[str]]:
    """The curve a display-encoded file is decoded by: the one it records where that is a
    display curve, else sRGB's; with where that came from and any warning."""
    recorded = recorded_curve(path)
    if recorded is None:
        return "srgb", "no curve recorded", []
    if recorded.encoding is None:   # the ingest warnings name these (io.manifest)
        return "srgb", f"in place of the {recorded.source}'s curve", []
    if recorded.encoding == "linear":
        return "srgb", "ingest.kind=srgb", [
            f"its {recorded.source} records linear values, decoded with sRGB's curve as "
            f"ingest.kind=srgb asks"]
    return recorded.encoding, recorded.source, []


def _linear_source(path: Path) -> tuple[str, list[str]]:
    recorded = recorded_curve(path)
    if recorded is None:
        return "no curve recorded", []
    if recorded.encoding == "linear":
        return recorded.source, []
    named = f" ({recorded.encoding})" if recorded.encoding else ""
    return "ingest.kind=linear", [f"its {recorded.source} records a display curve{named}; "
                                  f"read as linear values as ingest.kind=linear asks"]


#: JPEG chroma sampling as Pillow reports it (``JpegImagePlugin.get_sampling``).
CHROMA_SAMPLING = {0: "4:4:4", 1: "4:2:2", 2: "4:2:0"}


def jpeg_chroma(path: str | Path) -> str | None:
    """How a colour JPEG stores its colour: ``"4:4:4"`` (every pixel), ``"4:2:2"`` or
    ``"4:2:0"`` (averaged over 2 x 1 or 2 x 2 pixels in the encoded values, as most cameras
    write it; with a camera's frame-by-frame white balance it took green and blue
    attenuation lower, docs/water.md); None for other files, grey JPEGs or a layout Pillow
    does not name."""
    from PIL import JpegImagePlugin

    try:
        with Image.open(path) as image:
            if image.format != "JPEG" or image.mode == "L":
                return None
            return CHROMA_SAMPLING.get(JpegImagePlugin.get_sampling(image))
    except (OSError, ValueError):
        return None


def read_encoded(path: str | Path, kind: str) -> DecodedImage:
    """Read a JPEG/PNG/TIFF as linear RGB. ``kind='srgb'`` (display-encoded): the stored values
    through the inverse of the curve the file records (an ICC profile's gamma 1.8, say), else of
    sRGB's; ``kind='linear'``: the stored values as they are. Integers map to [0, 1] by their top
    code; the EXIF orientation is applied. The manifest's ``decoder.transfer`` names the curve
    (``seathru.radiometry.stored_encoding``) and ``decoder.transfer_source`` where it came
    from; a colour JPEG's ``decoder.chroma`` how it stores its colour (:func:`jpeg_chroma`)."""
    if kind not in ("linear", "srgb"):
        raise ValueError(f"kind must be 'linear' or 'srgb', not {kind!r}")
    path = Path(path)
    codes = read_stored_array(path)
    if codes.dtype in (np.uint8, np.uint16):
        values = codes.astype(np.float32) / np.float32(np.iinfo(codes.dtype).max)
    elif np.issubdtype(codes.dtype, np.floating):
        values = codes.astype(np.float32)
    else:
        raise DecodeError(f"unsupported sample type {codes.dtype} (use 8/16-bit or float)")
    reason = linearise.invalid_image_reason(values)
    if reason:
        raise DecodeError(reason)
    transfer, source, warnings = (_display_encoding(path) if kind == "srgb"
                                  else ("linear", *_linear_source(path)))
    values = np.asarray(stored_encoding.decode(values, transfer), dtype=np.float32)
    saturated, black_clipped = linearise.encoded_clipping(codes)
    exif, _ = read_exif(path)
    flip = 0 if path.suffix.lower() in HEIF_EXTENSIONS else \
        linearise.exif_orientation_to_flip(exif.orientation)
    grey = bool(np.array_equal(codes[..., 0], codes[..., 1])
                and np.array_equal(codes[..., 1], codes[..., 2]))
    metadata = {"bit_depth": int(codes.dtype.itemsize * 8), "sample_type": str(codes.dtype),
                "flip": flip, "transfer": transfer, "transfer_source": source, "grey": grey}
    chroma = jpeg_chroma(path) if path.suffix.lower() in (".jpg", ".jpeg") else None
    if chroma:
        metadata["chroma"] = chroma
    return DecodedImage(
        image=linearise.orient(values, flip), saturated=linearise.orient(saturated, flip),
        black_clipped=linearise.orient(black_clipped, flip), kind=kind, exposure=exif,
        metadata=metadata, warnings=warnings)
