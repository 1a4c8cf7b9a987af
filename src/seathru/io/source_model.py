"""A posed dataset's own COLMAP model, kept beside ``cameras.json`` (``poses/sparse``).

The poses step keeps the model it computes there; this keeps a source's: a ``colmap``
dataset's model, and the ``sparse/0`` an LLFF dataset holds beside ``poses_bounds.npy`` (the
SeaThru-NeRF release has one). With it the training takes depth supervision from the points and
the medium decision and evaluation their colour along the tracks (``seathru.io.tracks``), as for
a model the pipeline computes.

An LLFF dataset's poses come from ``poses_bounds.npy``, and its model must be in their frame.
LLFF's ``imgs2poses`` writes the poses in the frame of the COLMAP model it read, so for the
release the frames agree; a user may have rerun COLMAP or moved the poses since. The model's
camera centres are therefore aligned to the poses' by a similarity (Umeyama) and the model is
kept, moved into the poses' frame, only when every camera then agrees with its pose
(:data:`AGREEMENT_SHARE` of the cameras' spread, :data:`AGREEMENT_DEG`); a model of other
cameras is left out with the figures that say why.
"""

from __future__ import annotations

import logging
from pathlib import Path
import numpy as np
import pycolmap

from seathru.geometry.poses import compare_trajectories
from seathru.io.colmap import read_model, registered_c2w
from seathru.io.dataset_readers import PosedDataset
from seathru.io.pose_report import SourceModelRecord

log = logging.getLogger(__name__)

#: An LLFF dataset's model is kept when, after the similarity, every camera centre lies within
#: this share of the largest distance between two poses' centres of its pose ...
AGREEMENT_SHARE = 0.02
#: ... and every camera's axes within this angle of its pose's.
AGREEMENT_DEG = 2.0
#: Fewer cameras named in both: the alignment is not checked, the model is not kept.
MIN_SHARED_IMAGES = 3


def _record(model_dir: str, points: int, kept: bool, reason: str, shared: int = 0,
            position: float | None = None, rotation: float | None = None,
            scale: float | None = None) -> SourceModelRecord:
    return {"model": model_dir, "points": points, "kept": kept, "reason": reason,
            "shared_images": shared, "max_position_error_share": position,
            "max_rotation_error_deg": rotation, "scale": scale}


def align_to_poses(model: pycolmap.Reconstruction, dataset: PosedDataset, model_dir: str
                   ) -> SourceModelRecord:
    """Move ``model`` (in place) into the frame of ``dataset``'s poses when its cameras agree
    with them after a similarity; the record says whether they did.

    Args:
        model: a COLMAP model whose registered images are named like the posed views (by
            stem: ``IMG_1.JPG`` in the model is view ``IMG_1``).
        dataset: the posed views (OpenCV c2w in the source's units).
        model_dir: the model's folder, for the record.

    Returns:
        the record; ``kept`` is False (and the model untouched) when fewer than
        :data:`MIN_SHARED_IMAGES` images are shared or a camera disagrees.
    """
    points = int(model.num_points3D())
    poses = {view.name: view.c2w for view in dataset.views}
    pairs = [(c2w, poses[Path(name).stem]) for name, c2w in sorted(registered_c2w(model).items())
             if Path(name).stem in poses]
    if len(pairs) < MIN_SHARED_IMAGES:
        return _record(model_dir, points, False,
                       f"{len(pairs)} of its images are named like a posed view (at least "
                       f"{MIN_SHARED_IMAGES} are needed to check that it is in the poses' "
                       f"frame)", len(pairs))
    comparison = compare_trajectories(np.array([p[0] for p in pairs]),
                                      np.array([p[1] for p in pairs]))
    position = comparison.max_relative_position_error if comparison.extent > 0 else np.inf
    rotation = float(comparison.rotation_errors_deg.max())
    figures = dict(shared=len(pairs), position=round(float(position), 6),
                   rotation=round(rotation, 4), scale=float(comparison.alignment.scale))
    if not (position <= AGREEMENT_SHARE and rotation <= AGREEMENT_DEG):
        return _record(model_dir, points, False,
                       f"its cameras do not match the poses after a similarity (worst camera "
                       f"{100 * position:.1f}% of the cameras' spread and {rotation:.1f} deg "
                       f"off; {100 * AGREEMENT_SHARE:g}% and {AGREEMENT_DEG:g} deg allowed): "
                       f"a model of other cameras", **figures)
    alignment = comparison.alignment
    model.transform(pycolmap.Sim3d(alignment.scale, pycolmap.Rotation3d(alignment.rotation),
                                   alignment.translation))
    return _record(model_dir, points, True,
                   f"its {len(pairs)} shared cameras match the poses after a similarity "
                   f"(worst {100 * position:.2f}% of the cameras' spread, {rotation:.2f} deg)",
                   **figures)


def keep_source_model(dataset: PosedDataset, out: Path) -> SourceModelRecord | None:
    """Write the source's COLMAP model (``dataset.notes['model']``: a ``colmap`` dataset's, or
    the ``sparse/0`` beside an LLFF dataset's ``poses_bounds.npy``) to ``out/sparse`` (binary),
    in the frame of the dataset's poses (:func:`align_to_poses` for LLFF).

    Returns:
        the record, or None when the source has no model.
    """
    model_dir = dataset.notes.get("model")
    if not model_dir:
        return None
    model = read_model(Path(model_dir))
    points = int(model.num_points3D())
    if points == 0:
        return _record(model_dir, 0, False, "the model has no 3D points")
    if dataset.source == "llff":
        record = align_to_poses(model, dataset, model_dir)
    else:
        record = _record(model_dir, points, True, "the poses are the model's own")
    if record["kept"]:
        (out / "sparse").mkdir(parents=True, exist_ok=True)
        model.write(out / "sparse")
    else:
        log.warning("%s: the COLMAP model is not kept: %s", model_dir, record["reason"])
    return record
