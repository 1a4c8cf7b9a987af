"""The quality policy of structure from motion: which attempts to run, when a model passes, which
one to keep. Pure Python/numpy; the COLMAP runs themselves are in ``seathru.io.sfm``.

A model must register enough images with a low mean reprojection error (:class:`QualityGate`)
and, with the cross-check on, be confirmed by an independent model (the other mapper on the same
matches, or either mapper on the other matcher's matches) agreeing on the poses after a
similarity alignment: repeated texture can give a wrong model with every image registered and a
low reprojection error, and two mappers rarely fail the same way. A model that another
gate-passing model contradicts with a markedly lower reprojection error is set aside even when
confirmed (a scene mapped mirrored by one mapper on both matchers). Until a model is confirmed
the alternatives of :func:`plan_attempts` are tried in turn.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Callable, Literal, get_args

import numpy as np

from seathru.geometry.poses import compare_trajectories

log = logging.getLogger(__name__)

Matcher = Literal["sequential", "exhaustive"]
Mapper = Literal["incremental", "global"]
MATCHERS: tuple[str, ...] = get_args(Matcher)
MAPPERS: tuple[str, ...] = get_args(Mapper)


#: How images share cameras (``poses.camera_mode``): one for all, one per image size, one per
#: image; ``auto`` is ``single`` when the images have one size, ``per-size`` otherwise.
CameraMode = Literal["auto", "single", "per-size", "per-image"]


@dataclass(frozen=True)
class SfmSettings:
    """Everything that changes a COLMAP run; recorded as is in the report."""

    camera_model: str = "SIMPLE_RADIAL"
    camera_mode: str = "single"     # CameraMode; auto is resolved before COLMAP runs
    matcher: str = "sequential"
    overlap: int = 10
    mapper: str = "incremental"
    max_image_size: int = 1600
    max_features: int = 8192
    threads: int = -1
    seed: int = 0
    focal_px: float | None = None   # initial focal length at the matching images' size
    refine_focal: bool = True


@dataclass
class SfmAttempt:
    """One mapping attempt and what it gave (a ``report.json`` ``attempts`` entry)."""

    settings: dict
    role: str = "first"             # first | cross-check | retry
    registered: int = 0
    total: int = 0
    mean_reprojection_px: float | None = None
    num_points: int = 0
    mean_track_length: float | None = None
    seconds: float = 0.0
    passed: bool = False
    unregistered: list[str] = field(default_factory=list)
    error: str | None = None
    agreement: dict | None = None   # the confirming comparison, for the model kept
    comparisons: list[dict] = field(default_factory=list)  # with earlier independent models
    note: str | None = None

    @property
    def registered_fraction(self) -> float:
        return self.registered / self.total if self.total else 0.0

    def to_dict(self) -> dict:
        data = asdict(self)
        data["registered_fraction"] = self.registered_fraction
        return data

    def sort_key(self) -> tuple:
        """Better attempts sort higher: gate passed, more images, lower reprojection error."""
        error = self.mean_reprojection_px if self.mean_reprojection_px is not None else np.inf
        return (self.passed, self.registered, -error)


@dataclass(frozen=True)
class QualityGate:
    """What a model must satisfy to be accepted without retrying.

    The reprojection error limit applies at the resolution SIFT ran at; ``reprojection_scale``
    (matching image size / SIFT size, >= 1, :func:`reprojection_scale`) converts it to the
    model's pixels. Two independent models must agree on the camera poses within
    ``max_disagreement`` of the camera extent and ``max_rotation_disagreement_deg``. A model
    is set aside, confirmed or not, where a gate-passing model that disagrees with it has a
    mean reprojection error ``rival_error_ratio`` times lower (0: never): a scene mapped
    mirrored (the relief inverted, cameras turned about 180 degrees) can register every image
    below the limit and be matched by the same mapper on the other matcher, but it explains
    the matches worse than the right one.
    """

    min_registered_fraction: float = 0.8
    max_reprojection_px: float = 1.0
    reprojection_scale: float = 1.0
    max_disagreement: float = 0.01
    max_rotation_disagreement_deg: float = 1.0
    rival_error_ratio: float = 1.5

    def check(self, attempt: SfmAttempt) -> bool:
        return (attempt.registered > 0
                and attempt.registered_fraction >= self.min_registered_fraction
                and attempt.mean_reprojection_px is not None
                and attempt.mean_reprojection_px
                <= self.max_reprojection_px * self.reprojection_scale)

    def agree(self, agreement: dict | None) -> bool:
        return (agreement is not None
                and agreement["max_centre_deviation"] <= self.max_disagreement
                and agreement["max_rotation_deviation_deg"] <= self.max_rotation_disagreement_deg)

    def outdoes(self, rival: SfmAttempt, attempt: SfmAttempt) -> bool:
        """Whether ``rival``'s mean reprojection error is ``rival_error_ratio`` times lower
        than ``attempt``'s (their poses' disagreement is judged apart)."""
        ours, theirs = attempt.mean_reprojection_px, rival.mean_reprojection_px
        return (self.rival_error_ratio > 0 and ours is not None and theirs is not None
                and theirs * self.rival_error_ratio < ours)


def reprojection_scale(image_size: tuple[int, int] | None, max_image_size: int) -> float:
    """Matching image pixels per SIFT pixel (>= 1): COLMAP reports reprojection errors in the
    matching images' pixels, the gate's limit is meant at the size SIFT ran at.

    ``image_size``: ``(width, height)`` of every matching image (None: sizes differ);
    ``max_image_size``: SIFT's longest side (<= 0: full size).
    """
    longest = max(image_size) if image_size is not None else 0
    return max(1.0, longest / max_image_size) if max_image_size > 0 and longest else 1.0


# -- the plan --------------------------------------------------------------------------------

def alternatives(settings: SfmSettings, cross_check: bool = True,
                 global_available: bool = True) -> list[SfmSettings]:
    """Independent ways to map the same images, the user's first.

    The other mapper on the same matches, then the other matcher (exhaustive for sequential and
    vice versa) with each mapper. Seeds are not a source of independent evidence: with the same
    matches COLMAP's mappers nearly always return the same model whatever the seed.
    ``global_available``: whether this COLMAP has the global mapper.
    """
    mappers = [settings.mapper]
    if global_available and cross_check:
        mappers.append("global" if settings.mapper == "incremental" else "incremental")
    elif settings.mapper == "incremental" and global_available:
        mappers.append("global")
    other_matcher = "exhaustive" if settings.matcher == "sequential" else "sequential"
    return [replace(settings, matcher=matcher, mapper=mapper)
            for matcher in (settings.matcher, other_matcher) for mapper in mappers]


def plan_attempts(settings: SfmSettings, retry: bool = True, cross_check: bool = True,
                  global_available: bool = True) -> list[SfmSettings]:
    """The attempts to run, in order, until one is accepted (without ``retry`` only the user's
    matcher; without either, the user's settings alone)."""
    plan = alternatives(settings, cross_check, global_available)
    if not retry:
        plan = [p for p in plan if p.matcher == settings.matcher] if cross_check else [settings]
    return plan


def independent(a: SfmSettings, b: SfmSettings) -> bool:
    """Two attempts are independent evidence when matcher or mapper differ."""
    return (a.matcher, a.mapper) != (b.matcher, b.mapper)


# -- agreement between models ----------------------------------------------------------------

def pose_agreement(poses: dict[str, np.ndarray], other: dict[str, np.ndarray]) -> dict | None:
    """How far two models of the same images disagree, after a similarity alignment.

    Args:
        poses, other: ``(4, 4)`` camera-to-world poses by image name.

    Returns:
        ``common_images``, the largest camera-centre deviation as a fraction of the camera
        extent (``max_centre_deviation``, largest distance between two camera centres) and the
        largest rotation deviation in degrees (``max_rotation_deviation_deg``), over the images
        both hold; None when fewer than 3 are shared or the cameras coincide.
    """
    common = sorted(set(poses) & set(other))
    if len(common) < 3:
        return None
    comparison = compare_trajectories(np.array([other[n] for n in common]),
                                      np.array([poses[n] for n in common]))
    if comparison.extent <= 0:
        return None
    return {"common_images": len(common),
            "max_centre_deviation": float(comparison.position_errors.max() / comparison.extent),
            "max_rotation_deviation_deg": float(comparison.rotation_errors_deg.max())}


def describe_agreement(agreement: dict | None) -> str:
    if agreement is None:
        return "fewer than 3 images in common"
    return (f"camera centres {agreement['max_centre_deviation']:.2%} of the camera extent, "
            f"rotations {agreement['max_rotation_deviation_deg']:.2f} deg apart")


# -- choosing the model ----------------------------------------------------------------------

@dataclass
class SfmRun:
    """An attempt with the settings it ran and its model (opaque here)."""

    settings: SfmSettings
    attempt: SfmAttempt
    model: Any


def _candidates(runs: list[SfmRun], matcher: str) -> list[SfmRun]:
    passed = [run for run in runs if run.attempt.passed]
    return [run for run in passed if run.settings.matcher == matcher] or passed


def confirmed_run(runs: list[SfmRun], comparisons: dict[tuple[int, int], dict | None],
                  gate: QualityGate, matcher: str,
                  compare: Callable[[Any, Any], dict | None]) -> SfmRun | None:
    """The earliest candidate that an independent gate-passing model agrees with and no
    gate-passing model outdoes (:meth:`QualityGate.outdoes`, disagreeing with it).

    Candidates are the gate-passing runs on the user's ``matcher`` first (for ordered dive
    sets the sequential matches hold fewer false pairs), then the other gate-passing runs: the
    other matcher's two models agreeing with each other outweigh the user's matcher's that
    agree with nothing (a turbid transect: the sequential matcher's two mappers 166 degrees
    apart and each 17 degrees from the exhaustive matcher's, which agreed).
    ``comparisons`` caches ``compare(model_i, model_j)`` (see :func:`pose_agreement`) by run
    indices ``(i, j)``, ``i < j``; each new comparison is also recorded on run ``j``'s attempt.
    The confirmed attempt gets its ``agreement`` and ``note``; one set aside, its ``note``.
    """
    passed = [run for run in runs if run.attempt.passed]

    def agreement(a: SfmRun, b: SfmRun) -> dict | None:
        i, j = sorted((runs.index(a), runs.index(b)))
        if (i, j) not in comparisons:
            found = compare(runs[i].model, runs[j].model)
            comparisons[(i, j)] = found
            runs[j].attempt.comparisons.append({"with_attempt": i + 1, **(found or {})})
            if not gate.agree(found):
                log.warning("attempts %d and %d disagree on the poses (%s)", i + 1, j + 1,
                            describe_agreement(found))
        return comparisons[(i, j)]

    own = _candidates(runs, matcher)
    for candidate in own + [run for run in passed if run not in own]:
        rival = next((run for run in passed if run is not candidate
                      and gate.outdoes(run.attempt, candidate.attempt)
                      and not gate.agree(agreement(candidate, run))), None)
        if rival is not None:
            note = (f"set aside: attempt {runs.index(rival) + 1}, which disagrees with it, "
                    f"reprojects its points with {rival.attempt.mean_reprojection_px:.3g} px "
                    f"against {candidate.attempt.mean_reprojection_px:.3g} px")
            if candidate.attempt.note != note:
                log.warning("attempt %d %s", runs.index(candidate) + 1, note)
            candidate.attempt.note = note
            continue
        for witness in passed:
            if witness is candidate or not independent(candidate.settings, witness.settings):
                continue
            if gate.agree(agreement(candidate, witness)):
                candidate.attempt.agreement = agreement(candidate, witness)
                candidate.attempt.note = (
                    f"confirmed by attempt {runs.index(witness) + 1} ({witness.settings.matcher}"
                    f" matching, {witness.settings.mapper} mapping)")
                return candidate
    return None


def unconfirmed_run(runs: list[SfmRun], matcher: str, cross_check: bool) -> SfmRun:
    """The run to keep when none is confirmed: the candidate with the lowest mean reprojection
    error (marked as failing the gate when a cross-check was asked for), else the best run."""
    candidates = _candidates(runs, matcher)
    if not candidates:
        return max(runs, key=lambda run: run.attempt.sort_key())
    best = min(candidates, key=lambda run: run.attempt.mean_reprojection_px)
    if cross_check:
        best.attempt.passed = False
        best.attempt.note = ("no independent model agreed with it; kept as the candidate with the "
                             "lowest mean reprojection error")
        log.warning("no independent COLMAP model confirmed the poses; keeping attempt %d "
                    "unconfirmed", runs.index(best) + 1)
    return best


#: Below this many images a failed registration is most likely the set's size.
FEW_IMAGES = 10

#: Below this largest median shift of matched features between two photographs (a share of the
#: image diagonal) the camera did not move: 0.01% on copies of one frame, 18-42% between the
#: frames of dives that registered (d3_reef, a simulated transect).
STILL_SHIFT = 0.01

#: From this share of the verified pairs related by a homography alone on, the camera turned
#: about one point or the scene is flat (a panning tripod: every pair; d3_reef: 1 of 63,
#: a one-off count on its exhaustive matches, benchmarks/results/workflow_trials.md).
HOMOGRAPHY_SHARE = 0.9


@dataclass(frozen=True)
class PairMotion:
    """How the photographs move against each other over the verified pairs of a matched COLMAP
    database (``seathru.io.sfm.pair_motion``): ``largest_shift``, the largest of each pair's
    median image displacement of its inlier matches as a share of the image diagonal (near zero
    only where every photograph was taken from one place, on a tripod or a fixed mount: 0.01%
    for copies of one d3_reef frame against 18% for the diver's 20 frames around the coral
    head); ``homography_share``, the share of pairs a homography alone relates (COLMAP's
    planar or panoramic pairs); ``pairs``: how many pairs."""

    largest_shift: float
    homography_share: float
    pairs: int


def _turned_or_flat(motion: PairMotion | None, focal_known: bool | None) -> str:
    """A sentence where nearly every pair is a homography, else ''."""
    if motion is None or motion.homography_share < HOMOGRAPHY_SHARE:
        return ""
    focal = ("" if focal_known else ", where a known focal length (poses.focal_px, or "
             "poses.focal_mm with poses.sensor_width_mm) lets COLMAP tell the two apart")
    return (f" {motion.homography_share:.0%} of the {motion.pairs} matched pairs of photographs "
            f"are related by a homography alone (COLMAP: planar or panoramic): either the "
            f"camera only turned about one point (a panning tripod, a diver turning in place), "
            f"which holds no 3D, so swim along or around the scene instead, or the scene is "
            f"flat (a sand plain seen from above){focal}.")


#: COLMAP keeps an image pair with at least 15 verified (inlier) matches: an image with fewer
#: with every other image has no partner to register with.
FEW_MATCHES = 15


def _unmatched(matched: dict[str, int], features: dict[str, int], total: int) -> str:
    """A sentence naming the views that share too few verified matches with any other view
    (``matched``: the best pair's inliers per view; ``features``: SIFT keypoints per view)."""
    lone = sorted(name for name, inliers in matched.items() if inliers < FEW_MATCHES)
    if not lone:
        return ""
    listed = ", ".join(lone[:10]) + (" ..." if len(lone) > 10 else "")
    which = ("No image shares" if len(lone) == len(matched)
             else f"{len(lone)} of {total} images share")
    counts = [features[name] for name in lone if name in features]
    keypoints = (f" (their SIFT features: median {int(np.median(counts))} an image)"
                 if counts else "")
    return (f" {which} {FEW_MATCHES} verified feature matches with any other image{keypoints}: "
            f"views of open water, bare sand, blur or darkness hold nothing to match, and views "
            f"of another place share nothing with the rest. Photograph the seabed or the reef "
            f"with texture in every frame, or remove those views ({listed}).")


def failure_message(attempts: list[SfmAttempt], chosen: SfmAttempt | None, total: int,
                    gate: QualityGate, matched: dict[str, int] | None = None,
                    features: dict[str, int] | None = None, clahe: bool = True,
                    focal_known: bool | None = None,
                    motion: PairMotion | None = None) -> str:
    """Why no model registers enough images: every attempt, and what to try next (sheet
    syntax). ``matched`` (verified inliers of each image's best pair) and ``features`` (SIFT
    keypoints per image), by image name: to name the views that have nothing to match;
    ``clahe``: whether the matching copies were equalised; ``focal_known``: whether COLMAP
    started from a focal length (the photographs' EXIF or the settings; None: not said);
    ``motion``: how the photographs move against each other (:class:`PairMotion`: a largest
    shift below :data:`STILL_SHIFT` means they were taken from one place, and no COLMAP
    setting helps; pairs that are homographies, a camera turned in place or a flat scene)."""
    registered = chosen.registered if chosen else 0
    tried = "; ".join(
        f"{a.settings['matcher']} matching + {a.settings['mapper']} mapping, seed "
        f"{a.settings['seed']}: {a.registered}/{a.total}" + (f" ({a.error})" if a.error else "")
        for a in attempts)
    unregistered = chosen.unregistered if chosen else []
    listed = ", ".join(unregistered[:20]) + (" ..." if len(unregistered) > 20 else "")
    few = (f" Only {total} images: structure from motion and a NeRF need tens of overlapping "
           f"photographs of the scene (each part seen from three or more positions)."
           if total < FEW_IMAGES else "")
    if motion is not None and motion.largest_shift < STILL_SHIFT:
        return (f"COLMAP registered only {registered} of {total} images: the photographs were "
                f"taken from one place (matched features move at most "
                f"{motion.largest_shift:.2%} of the image diagonal between any two of them, as "
                f"on a tripod or a fixed "
                f"mount). A 3D model needs photographs from several positions: swim along or "
                f"around the scene with each photograph overlapping the next by about two "
                f"thirds, or leave the still frames out. Tried: {tried}")
    return (f"COLMAP registered only {registered} of {total} images in its largest model "
            f"(need {gate.min_registered_fraction:.0%}).{few}"
            f"{_turned_or_flat(motion, focal_known)}"
            f"{_unmatched(matched or {}, features or {}, total)} Tried: {tried}. Try "
            f"{', '.join(_sheet_advice(attempts, clahe, 16384, focal_known))}, or remove images "
            f"that do not overlap the others"
            + (f". Unregistered: {listed}" if unregistered else ""))


def _sheet_advice(attempts: list[SfmAttempt], clahe: bool, max_features: int | None = None,
                  focal_known: bool | None = None) -> list[str]:
    """The poses options worth trying next, in the dataset sheet's syntax: the matchers and
    mappers no attempt used, then the settings no retry changes (``max_features``: a value to
    suggest). Without a starting focal length (``focal_known`` false) giving one comes first:
    COLMAP's own estimate is what a wide-angle lens defeats."""
    focal = "focal length (poses.focal_px, or poses.focal_mm with poses.sensor_width_mm)"
    tried = {(a.settings.get("matcher"), a.settings.get("mapper")) for a in attempts}
    advice = [] if focal_known is not False else [
        f"first a known {focal}: COLMAP had none to start from (none in the photographs' EXIF, "
        f"or images of several sizes), and its own estimate fails most often with wide-angle "
        f"lenses"]
    advice += [f"poses.matcher={m}" for m in MATCHERS if m not in {t[0] for t in tried}]
    advice += [f"poses.mapper={m}" for m in MAPPERS if m not in {t[1] for t in tried}]
    if not attempts or {t[0] for t in tried} == set(MATCHERS):
        advice.append("a larger poses.overlap")
    features = f"poses.max_features={max_features}" if max_features else "more poses.max_features"
    return advice + ["a larger poses.max_image_size (-1: full size)",
                     f"poses.clahe={'false' if clahe else 'true'}", features] + (
        [f"another {focal} (the one used may be wrong: a cropped photograph keeps its "
         f"camera's)"] if focal_known else [f"a known {focal}"] if focal_known is None else [])


def unconfirmed_message(attempts: list[SfmAttempt], chosen: SfmAttempt, gate: QualityGate,
                        clahe: bool = True, kept: bool = False,
                        focal_known: bool | None = None,
                        motion: PairMotion | None = None) -> str:
    """Why the model kept was not confirmed, and which options to try (sheet syntax).

    Names the kept attempt's figures, each failed limit (registered share, mean reprojection
    error) and the worst disagreements between attempts (camera centres as a share of the camera
    extent, rotations in degrees), or that no independent model passed the gate to compare with.
    ``clahe``: whether the matching copies were equalised (the advice is to try the other way);
    ``kept``: the model is kept anyway (``poses.on_unconfirmed=warn``), else the step fails;
    ``focal_known``: whether COLMAP started from a focal length (None: not said); ``motion``:
    how the photographs move against each other (:class:`PairMotion`), to say when nearly
    every pair is a homography.
    """
    index = attempts.index(chosen) + 1 if chosen in attempts else 0
    error = chosen.mean_reprojection_px
    limit = gate.max_reprojection_px * gate.reprojection_scale
    reasons = []
    if chosen.registered_fraction < gate.min_registered_fraction:
        reasons.append(f"only {chosen.registered_fraction:.0%} of the images registered "
                       f"(poses.min_registered {gate.min_registered_fraction:g})")
    if error is None or error > limit:
        reasons.append(f"mean reprojection error {'n/a' if error is None else f'{error:.3g}'} "
                       f"px above {limit:.3g} px (poses.max_reproj_px "
                       f"{gate.max_reprojection_px:g} at SIFT's size)")
    disagreements = sorted(
        ((c.get("max_centre_deviation", np.inf), c.get("max_rotation_deviation_deg", np.inf),
          c["with_attempt"], attempts.index(a) + 1, c)
         for a in attempts for c in a.comparisons
         if not gate.agree(c if "max_centre_deviation" in c else None)),
        key=lambda item: (not np.isfinite(item[0]), -item[0], -item[1]))
    for _, _, first, second, comparison in disagreements[:3]:
        reasons.append(f"attempts {first} and {second} disagree on the poses: "
                       + describe_agreement(comparison if "max_centre_deviation" in comparison
                                            else None))
    if disagreements:
        reasons[-1] += (f" (limits: poses.max_disagreement {gate.max_disagreement:g} of the "
                        f"extent, poses.max_rotation_disagreement_deg "
                        f"{gate.max_rotation_disagreement_deg:g})")
    if not disagreements and not reasons:
        reasons.append("no independent model (the other mapper or matcher) passed the gate to "
                       "confirm it")
    advice = _sheet_advice(attempts, clahe, focal_known=focal_known)
    ending = ("kept because poses.on_unconfirmed=warn: the model is trained on cameras that "
              "may be wrong" if kept else
              "or keep it with poses.on_unconfirmed=warn (the report then shows this)")
    return (f"the camera model was not confirmed: the model kept (attempt {index} of "
            f"{len(attempts)}, {chosen.settings.get('matcher')} matching + "
            f"{chosen.settings.get('mapper')} mapping: {chosen.registered}/{chosen.total} "
            f"registered) is doubtful: {'; '.join(reasons)}."
            f"{_turned_or_flat(motion, focal_known)} Repeated texture (tiles, sand ripples) or "
            f"too little overlap can give a wrong model that looks consistent. Try "
            f"{', '.join(advice)}; {ending}")
