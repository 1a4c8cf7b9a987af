"""The ingest step's output: ``manifest.json`` (format ``seathru-ingest/1``) and the folder layout.

Folder (``results/<dataset>/ingest``)::

    linear/<stem>.tiff      float32 linear RGB, exposure-normalised and white-balanced
    linear_<N>/<stem>.tiff  the same, area-averaged down by N (LLFF images_N)
    masks/<stem>.png        validity mask (255 valid), masks_<N>/ likewise
    matching/<stem>.png     8-bit sRGB-encoded copy for feature matching
    manifest.json           :class:`IngestManifest`

``manifest.json`` is written by :func:`write_manifest` (the ingest step, through
:func:`build_manifest`) and read by :func:`read_manifest`; :class:`IngestFolder` is how later
steps (``poses``) find the images.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence, TypedDict

import numpy as np

from seathru.errors import PipelineError
from seathru.io.atomic import write_json
from seathru.io.contract import check_contract
from seathru.io.jsonfile import read_json
from seathru.io.image_folder import RejectedFile
from seathru.io.images import list_images
from seathru.io.video import VideoFrameRecord, VideoFrames, VideoRecord
from seathru.io.warnings import StepWarning, step_warning
from seathru.radiometry.linearise import MATCHING_TARGET_MEDIAN

FORMAT = "seathru-ingest/1"
RAW_DECODING = ("LibRaw: per-channel black subtracted, / (white - black), unit WB, raw colour, "
                "gamma (1, 1), 16-bit, no auto brightness, adjust_maximum_thr 0, orientation "
                "from the file")
EXPOSURE_DEFINITION = ("E = t * ISO / N^2 over fields_used; factor = reference / E, reference = "
                       "median E; factor 1 where E is unknown")
MATCHING_ENCODING = "sRGB transfer of clip(scale * linear), 8-bit PNG"
_HINT = "run the 'ingest' step"


class DownscaledImage(TypedDict):
    linear: str                 # linear_<N>/<stem>.tiff
    mask: str                   # masks_<N>/<stem>.png
    width: int
    height: int


class _ManifestImageOptional(TypedDict, total=False):
    video_frame: VideoFrameRecord  # a video's frame (source is the video); absent otherwise
    # EXIF FocalLength and FocalLengthIn35mmFilm where the file records them (the poses step
    # starts COLMAP's focal length from the 35 mm equivalent: seathru.geometry.intrinsics)
    focal_length_mm: float
    focal_length_35mm: float


class ManifestImage(_ManifestImageOptional):
    name: str                   # file stem, the key of every later stage
    source: str                 # file name in the input folder
    source_path: str            # resolved path of the input file
    kind: str                   # raw | linear | srgb
    width: int                  # of linear/<stem>.tiff
    height: int
    source_size: list[int]      # [width, height] as decoded
    linear: str                 # paths relative to the manifest's folder
    mask: str
    matching: str
    matching_size: list[int]
    downscaled: dict[str, DownscaledImage]  # by factor N, as a string
    exposure_time: float | None  # seconds; None = not recorded
    iso: float | None
    f_number: float | None
    exposure_metadata_source: dict[str, str]  # field -> exif | libraw
    exposure_value: float | None  # t * ISO / N^2 over the fields used; None when unknown
    exposure_factor: float      # the image was multiplied by this
    saturated_fraction: float
    black_clipped_fraction: float
    clipped_fraction: float     # invalid in the mask (after dilation and resizing)
    camera_wb_gains: list[float] | None
    colour_matrix: list[list[float]] | None
    decoder: dict[str, Any]     # decoder facts (raw size, black/white levels, flip, ...)
    warnings: list[str]


class MissingFrame(TypedDict):
    name: str                   # the view name the frame would have had
    file: str                   # the file the dataset lists


class _LayoutRecordOptional(TypedDict, total=False):
    masks: int                  # views with a mask of the dataset's own (nerfstudio mask_path)


class LayoutRecord(_LayoutRecordOptional):
    """How the images of a posed dataset were found (``seathru.io.dataset_readers``)."""

    layout: str                 # llff | colmap | nerfstudio
    root: str                   # the dataset folder
    images: str                 # the image folder used, relative to root
    reason: str                 # why: auto's choice or the ingest.images setting
    kind: str | None            # linear where the layout says so (images_wb), else None
    files: int                  # image files found
    missing: list[MissingFrame]  # listed by the dataset, not there (skipped)


class _ManifestInputOptional(TypedDict, total=False):
    layout: LayoutRecord | None  # posed layouts (None otherwise; absent in older manifests)
    videos: list[VideoRecord]   # a folder of videos: one record each (absent otherwise)


class ManifestInput(_ManifestInputOptional):
    folder: str
    given: str
    subdir: str | None
    kind: str
    requested: str
    counts: dict[str, int]
    note: str
    ignored: list[str]


class ManifestSettings(TypedDict):
    kind: str
    colour: str
    wb: str
    wb_percentile: float
    demosaic: str
    half_size: bool
    exposure_normalise: bool
    saturation_threshold: float
    mask_dilation: int
    max_size: int
    matching_max_size: int
    downscale: list[int]
    min_images: int
    stats_pixels_per_image: int
    workers: int
    raw_decoding: str


class _ExposureSummary(TypedDict):
    normalised: bool
    reference: float | None
    fields_used: list[str]


class ExposureSummary(_ExposureSummary, total=False):
    definition: str             # present when normalised


class WhiteBalanceSummary(TypedDict):
    method: str
    gains: list[float]
    gains_space: str
    post_matrix_gains: list[float] | None
    percentile: float | None
    percentile_levels: list[float] | None
    camera_gains: list[float] | None
    sampled_pixels: int


class MatchingSummary(TypedDict):
    exposure_scale: float
    target_median: float
    encoding: str


class IngestManifest(TypedDict):
    format: str                 # FORMAT
    input: ManifestInput
    settings: ManifestSettings
    colour_space: str           # camera raw | srgb-linear | as stored
    values: str                 # what 1.0 means
    exposure: ExposureSummary
    white_balance: WhiteBalanceSummary
    matching: MatchingSummary
    warnings: list[str]
    images: list[ManifestImage]
    rejected: list[RejectedFile]


def transfer_summary(manifest: IngestManifest) -> str:
    """How the images' stored values were decoded to linear, e.g. ``gamma 1.8 (ICC profile
    'ProPhoto RGB'): 24 images`` (RAW files: LibRaw's linear output), and how JPEGs stored
    their colour (``srgb (by kind), colour 4:2:0: 24 images``; ``seathru.io.raw.jpeg_chroma``)."""
    counts: dict[str, int] = {}
    for image in manifest["images"]:
        decoder = image["decoder"]
        curve = ("LibRaw's linear output" if image["kind"] == "raw" else
                 f"{decoder.get('transfer', image['kind'])} "
                 f"({decoder.get('transfer_source', 'by kind')})")
        if decoder.get("chroma"):
            curve += f", colour {decoder['chroma']}"
        counts[curve] = counts.get(curve, 0) + 1
    return "; ".join(f"{curve}: {count} image{'s' * (count != 1)}"
                     for curve, count in counts.items()) or "nothing"


# --- writing --------------------------------------------------------------------------------

def _floats(values: Any) -> list[float] | None:
    return None if values is None else [float(v) for v in values]


def build_manifest(settings: Any, *, folder: Path, given: Path, subdir: str | None,
                   detection: dict[str, Any], decoded: Sequence[Any], finished: Sequence[Any],
                   transform: Any, rejected: list[RejectedFile], downscale: Sequence[int],
                   stats_pixels_per_image: int, workers: int,
                   layout: LayoutRecord | None = None,
                   video: VideoFrames | None = None) -> IngestManifest:
    """The manifest of one ingest run.

    Args:
        settings: the ingest step's ``Settings``.
        folder, given, subdir, detection: the input folder, as resolved, given and selected
            (``seathru.io.image_folder.select_files``).
        decoded, finished: per image, ``seathru.io.decode_pool.Decoded`` and ``Finished``.
        transform: the ``seathru.radiometry.dataset_transform.DatasetTransform``.
        rejected, downscale, stats_pixels_per_image, workers: as used.
        layout: how a posed dataset's images were found (``LayoutImages.record()``).
        video: the frames staged from a folder of videos (``seathru.io.video``), or None.
    """
    values = transform.exposure_values
    images: list[ManifestImage] = []
    for i, (d, f) in enumerate(zip(decoded, finished)):
        matrix = transform.matrices[i]
        images.append({
            "name": d.name, "source": Path(d.source).name,
            "source_path": str(Path(d.source).resolve()), "kind": d.kind,
            "width": d.width, "height": d.height, "source_size": d.source_size,
            "linear": f"linear/{d.name}.tiff", "mask": f"masks/{d.name}.png",
            "matching": f"matching/{d.name}.png", "matching_size": f.matching_size,
            "downscaled": f.downscaled,
            "exposure_time": d.exposure["exposure_time"], "iso": d.exposure["iso"],
            "f_number": d.exposure["f_number"],
            "exposure_metadata_source": d.exposure["source"],
            "exposure_value": None if not np.isfinite(values[i]) else float(values[i]),
            "exposure_factor": float(transform.factors[i]),
            "saturated_fraction": d.saturated_fraction,
            "black_clipped_fraction": d.black_clipped_fraction,
            "clipped_fraction": d.invalid_fraction,
            "camera_wb_gains": d.camera_wb.tolist() if d.camera_wb is not None else None,
            "colour_matrix": matrix.tolist() if matrix is not None else None,
            "decoder": d.metadata,
            "warnings": d.warnings,
        })
        for key in ("focal_length_mm", "focal_length_35mm"):
            if d.exposure.get(key) is not None:
                images[-1][key] = float(d.exposure[key])
        if video is not None and d.name in video.frames:
            frame = video.frames[d.name]
            images[-1].update(source=frame["video"], source_path=video.sources[d.name],
                              video_frame=frame)
    norm = transform.exposure
    exposure: ExposureSummary = (
        {"normalised": True, "reference": norm.reference, "fields_used": list(norm.fields_used),
         "definition": EXPOSURE_DEFINITION} if norm is not None else
        {"normalised": False, "reference": None, "fields_used": []})
    kind = detection["kind"]
    percentile = settings.wb == "percentile"
    return {
        "format": FORMAT,
        "input": {"folder": str(folder.resolve()), "given": str(given), "subdir": subdir,
                  **detection, "layout": layout,
                  **({"videos": video.videos} if video is not None else {})},
        "settings": {
            "kind": settings.kind, "colour": settings.colour, "wb": settings.wb,
            "wb_percentile": settings.wb_percentile, "demosaic": settings.demosaic,
            "half_size": settings.half_size, "exposure_normalise": settings.exposure_normalise,
            "saturation_threshold": settings.saturation_threshold,
            "mask_dilation": settings.mask_dilation, "max_size": settings.max_size,
            "matching_max_size": settings.matching_max_size, "downscale": list(downscale),
            "min_images": settings.min_images, "stats_pixels_per_image": stats_pixels_per_image,
            "workers": workers, "raw_decoding": RAW_DECODING,
        },
        "colour_space": transform.colour_space,
        "values": (f"linear; the dataset's {settings.wb_percentile}th percentile of each channel "
                   "is 1.0" if percentile else
                   "linear; 1.0 = the white level (top code) at the dataset's median exposure, "
                   "times the white balance gains"),
        "exposure": exposure,
        "white_balance": {
            "method": transform.wb_method,
            "gains": _floats(transform.wb_gains),
            "gains_space": "camera raw" if kind == "raw" else "as stored",
            "post_matrix_gains": _floats(transform.post_gains),
            "percentile": settings.wb_percentile if percentile else None,
            "percentile_levels": _floats(transform.percentile_levels),
            "camera_gains": _floats(transform.camera_gains),
            "sampled_pixels": transform.sampled_pixels,
        },
        "matching": {"exposure_scale": transform.matching_scale,
                     "target_median": MATCHING_TARGET_MEDIAN, "encoding": MATCHING_ENCODING},
        "warnings": transform.warnings,
        "images": images,
        "rejected": rejected,
    }


def _decoding_warnings(images: list[ManifestImage]) -> list[StepWarning]:
    """Images with one channel only, and images whose recorded curve is none ingest follows
    (decoded as sRGB): both whether one image or all of them are so."""
    found = []
    decoders = {image["name"]: image.get("decoder") or {} for image in images}
    grey = [name for name, decoder in decoders.items() if decoder.get("grey")]
    if grey:
        found.append(step_warning(
            "ingest", "grey_images",
            f"{len(grey)} of {len(images)} image(s) hold one channel (grey: R = G = B, e.g. "
            f"{grey[0]}): the water's attenuation and colour differ per channel, which grey "
            f"photographs cannot show, so the water fitted to them is one grey haze; use the "
            f"colour originals (or the RAW files) where there are any", images=grey))
    unknown = {name: decoder["transfer_source"] for name, decoder in decoders.items()
               if str(decoder.get("transfer_source", "")).startswith("in place of")}
    if unknown:
        first = next(iter(unknown))
        found.append(step_warning(
            "ingest", "unknown_curve",
            f"{len(unknown)} of {len(images)} image(s) record a curve from stored values to "
            f"light that is none of linear, sRGB or a power curve (first, {first}: sRGB's used "
            f"{unknown[first]}); their values are decoded with sRGB's, so the water fitted to "
            f"them is off by the difference: export linear or sRGB files, or set "
            f"ingest.kind=linear if the values are linear", images=sorted(unknown)))
    return found


def ingest_warnings(manifest: IngestManifest, clipped_share: float) -> list[StepWarning]:
    """What the ingest step's user should look at, from its manifest: rejected files, frames the
    dataset lists that are missing, images whose clipped (invalid) share exceeds
    ``clipped_share``, grey images and curves decoded as sRGB in place of the one recorded,
    camera images none of which records its exposure,
    the per-image warnings of the decoding that not every image has (those describe the
    dataset, e.g. no EXIF at all: the manifest says so) and the dataset warnings."""
    found: list[StepWarning] = []
    rejected = manifest["rejected"]
    if rejected:
        found.append(step_warning(
            "ingest", "rejected_images",
            f"{len(rejected)} file(s) rejected and left out: " + "; ".join(
                f"{r['file']} ({r['reason']})" for r in rejected[:5])
            + (" ..." if len(rejected) > 5 else ""), rejected=rejected))
    layout = manifest["input"].get("layout") or {}
    missing = layout.get("missing") or []
    if missing:
        found.append(step_warning(
            "ingest", "missing_frames",
            f"{len(missing)} frame(s) the {layout['layout']} dataset lists have no image file "
            f"and are skipped: " + ", ".join(m["name"] for m in missing[:10])
            + (" ..." if len(missing) > 10 else ""), missing=missing))
    clipped = {image["name"]: image["clipped_fraction"] for image in manifest["images"]
               if image["clipped_fraction"] > clipped_share}
    if clipped:
        worst = max(clipped, key=clipped.get)
        found.append(step_warning(
            "ingest", "clipped_pixels",
            f"{len(clipped)} of {len(manifest['images'])} image(s) have more than "
            f"{clipped_share:.0%} clipped pixels (worst {worst}: {clipped[worst]:.1%}); they "
            f"are masked out of training, so what only they show is not learnt; lower the "
            f"exposure or drop them (threshold: ingest.warn_clipped_share)",
            images=clipped, threshold=clipped_share))
    found += _decoding_warnings(manifest["images"])
    exposure, images = manifest.get("exposure") or {}, manifest["images"]
    if exposure.get("normalised") and not exposure.get("fields_used") and len(images) > 1 \
            and manifest["input"].get("kind") in ("srgb", "raw"):
        found.append(step_warning(
            "ingest", "no_exposure_metadata",
            f"none of the {len(images)} images records its exposure (EXIF exposure time, ISO, "
            f"f-number): they are taken as exposed alike, and a camera's automatic exposure "
            f"varies between frames, which the model then learns as changes of the scene and "
            f"of the water (the simulated survey's camera JPEGs, up to +-0.5 EV apart: "
            f"held-out 19.6 dB against 28.4 dB with their EXIF, attenuation 19-29% off "
            f"against 3-12%); export the photographs with their metadata, or shoot in manual "
            f"exposure"))
    # a condition every image shares (no EXIF at all) describes the dataset, not an image
    common = set.intersection(*(set(image["warnings"]) for image in manifest["images"])) \
        if manifest["images"] else set()
    per_image = {image["name"]: [w for w in image["warnings"] if w not in common]
                 for image in manifest["images"]}
    per_image = {name: warnings for name, warnings in per_image.items() if warnings}
    if per_image:
        first = next(iter(per_image))
        found.append(step_warning(
            "ingest", "image_warnings", f"{len(per_image)} image(s) decoded with a warning "
            f"(first, {first}: {per_image[first][0]})", images=per_image))
    for text in manifest["warnings"]:
        found.append(step_warning("ingest", "dataset_warning", str(text)))
    return found


def write_manifest(path: str | Path, manifest: IngestManifest) -> None:
    """Write ``manifest.json`` atomically (checked against the contract first)."""
    check_contract(manifest, IngestManifest, path, FORMAT)
    write_json(path, manifest)


# --- reading --------------------------------------------------------------------------------

def read_manifest(path: str | Path, strict: bool = True) -> IngestManifest:
    """The manifest at ``path``.

    ``strict=False`` returns any valid JSON as it is: for readers that only look for optional
    metadata in it (``poses`` looks for focal lengths) and accept a hand-written file.

    Raises:
        PipelineError: naming the file, when it is absent, not JSON, or (strict) not of format
            ``seathru-ingest/1`` or missing a key.
    """
    data = read_json(path, hint=_HINT)
    if strict:
        check_contract(data, IngestManifest, path, FORMAT, _HINT)
    return data


def _by_stem(folder: Path) -> dict[str, Path]:
    files: dict[str, Path] = {}
    for path in list_images(folder):
        if path.stem in files:
            raise PipelineError(f"{folder}: two images share the name {path.stem!r} "
                                f"({files[path.stem].name}, {path.name})")
        files[path.stem] = path
    return files


class IngestFolder:
    """The images of an ingest output folder, by stem.

    ``linear``: ``linear_folder`` (``linear`` or a downscaled ``linear_<N>``); ``masks``: the
    masks at that size; ``matching`` and ``matching_masks``: the full-size matching copies and
    masks; ``manifest``: ``manifest.json`` as read with ``strict=False`` (None when absent).
    """

    def __init__(self, root: Path, linear_folder: str = "linear"):
        self.root = Path(root)
        if not self.root.is_dir():
            raise PipelineError(f"{self.root}: ingest folder not found; run the 'ingest' step")
        self.linear_dir = self.root / linear_folder
        self.linear = _by_stem(self.linear_dir)
        if not self.linear:
            raise PipelineError(f"{self.linear_dir}: no linear images; run the 'ingest' step or "
                                f"pick another --linear-folder")
        self.matching = _by_stem(self.root / "matching")
        # linear_<N>/ comes with masks_<N>/ at the same size
        suffix = linear_folder[len("linear"):] if linear_folder.startswith("linear") else ""
        masks_dir = self.root / f"masks{suffix}"
        self.masks_dir = masks_dir if masks_dir.is_dir() else self.root / "masks"
        self.masks = _by_stem(self.masks_dir)
        self.matching_masks = _by_stem(self.root / "masks")  # full size, like matching/
        manifest = self.root / "manifest.json"
        self.manifest = read_manifest(manifest, strict=False) if manifest.exists() else None

    @property
    def layout(self) -> LayoutRecord | None:
        """How a posed dataset's images were found (the manifest's ``input.layout``), or None."""
        manifest = self.manifest if isinstance(self.manifest, dict) else {}
        layout = (manifest.get("input") or {}).get("layout")
        return layout if isinstance(layout, dict) else None
