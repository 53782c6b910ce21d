"""What every solve needs before its first frame: the rig with its marker layout, a take's labels
checked against it, and a profile (a saved one, one calibrated on a neutral take, or on the take's own
first seconds). The logic the commands, ``livecap.batch``, ``livecap.review`` and ``livecap.api`` share."""

from __future__ import annotations

from pathlib import Path

from livecap.calibration.animation_prior import AnimationPrior
from livecap.calibration.profile import Profile, calibrate, estimate_neutral
from livecap.calibration.targets import DEFAULT_MAX_GAP_SECONDS, DEFAULT_POSE_SMOOTHING_SECONDS, prepare_targets
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.core.take import Take


def markers_path(rig_path: str | Path) -> Path:
    """A rig's markers.json: inside an OBJ folder, or ``<rig>.markers.json`` beside a .npz."""
    p = Path(rig_path)
    return p / "markers.json" if p.is_dir() else p.with_name(p.stem + ".markers.json")


def load_rig_layout(rig_path: str | Path, markers: str | Path | None = None,
                    mesh: str | None = None) -> tuple[Rig, MarkerLayout]:
    """The rig (any format :func:`transport.rig_files.load_rig` reads) and its markers.json (``markers``,
    else :func:`markers_path`)."""
    from transport.rig_files import load_rig as load_rig_file  # glTF/VRM/USD readers load only for their files

    rig = load_rig_file(rig_path, mesh)
    mpath = Path(markers) if markers else markers_path(rig_path)
    if not mpath.exists():
        raise ValueError(f"{mpath}: no markers.json for rig {rig_path} (give --markers)")
    return rig, MarkerLayout.load(mpath, rig)


def check_profile_for_rig(profile: Profile, rig_path: str | Path, profile_path: str | Path = "profile",
                          markers: str | Path | None = None) -> None:
    """A profile given beside a rig (and a markers.json) must be the one calibrated for them: another rig's
    profile, or markers bound elsewhere, would solve silently badly (issue 35.6). An OBJ folder or .npz is
    checked cheaply (names and neutral only); a glTF/VRM/USD file is read."""
    from livecap.calibration.profile import CalibrationError, check_layout_labels, check_rig_path, rig_fingerprint

    path = Path(rig_path)
    if not path.exists():
        raise ValueError(f"{rig_path}: no such rig (an OBJ folder, .npz, glTF/GLB, VRM or USD file)")
    if path.is_dir() or path.suffix.lower() == ".npz":
        mesh = check_rig_path(profile, rig_path, profile_path)
    else:
        from transport.rig_files import load_rig as load_rig_file

        rig = load_rig_file(rig_path)
        stored = profile.settings.get("rig_fingerprint")
        if list(rig.names) != list(profile.names) or stored not in (None, rig_fingerprint(rig)):
            raise CalibrationError(f"{profile_path}: calibrated against another rig than {rig_path} "
                                   f"({len(profile.names)} shapes, rig {stored}; the file: {rig.n_shapes} shapes, "
                                   f"rig {rig_fingerprint(rig)}): recalibrate, or give its rig")
        mesh = (rig.neutral, rig.triangles)
    if markers:
        check_layout_labels(profile, markers, profile_path, mesh)


def check_labels(take: Take, labels: list[str], take_path, rig_path) -> None:
    """A take that shares no marker label with the rig's ``labels`` is a wrong pairing, not a take with gaps: say so."""
    if not set(take.labels) & set(labels):
        raise ValueError(f"{take_path}: the take shares none of the {len(labels)} marker labels of rig {rig_path} "
                         f"(take: {', '.join(take.labels[:4])}...; rig: {', '.join(labels[:4])}...); give "
                         "a markers.json that binds the take's labels to the rig (--markers)")


def tune_on_take(profile: Profile, take: Take, noise_mm: float | None = None) -> dict:
    """Select the profile's noise level and regularisation from ``take`` (livecap.modes.robust.tune_profile);
    ``noise_mm`` overrides the measured noise."""
    from livecap.modes.robust import tune_profile

    sel, targets, _, _ = prepare_targets(take, profile)
    return tune_profile(profile, targets, sel.valid, take.rate, noise_mm)


def profile_from_take(rig: Rig, layout: MarkerLayout, take: Take, neutral_seconds: float = 1.0,
                      noise_mm: float | None = None) -> Profile:
    """A profile calibrated on the take's first ``neutral_seconds`` and tuned on the whole take: what a solve
    without a saved profile uses."""
    sel = take.select(layout.labels)
    neutral = estimate_neutral(sel, layout.stable, max(1, int(neutral_seconds * take.rate)))
    profile = calibrate(rig, layout, neutral)
    tune_on_take(profile, take, noise_mm)
    return profile


def calibrate_neutral(rig: Rig, layout: MarkerLayout, take: Take, *, take_path: str | Path = "neutral take",
                      rig_path: str | Path = "rig", seconds: float | None = None, warp: str = "rbf",
                      smoothing: float = 0.0, max_gap_seconds: float | None = None,
                      pose_smoothing_seconds: float | None = None, robust_stabilise: bool = True,
                      prior: str | Path | AnimationPrior | None = None,
                      span: tuple[int, int] | None = None) -> Profile:
    """``livecap calibrate`` before tuning: the neutral over the take's first ``seconds`` (all when None)
    or over frames ``span`` = (first, end), the proportion warp, the basis and the animation prior.
    Raises ValueError naming the take for markers
    it never sees, and naming the prior for one of other shapes."""
    check_labels(take, layout.labels, take_path, rig_path)
    sel = take.select(layout.labels)
    absent = [lab for lab, seen in zip(layout.labels, sel.valid.any(0), strict=True) if not seen]
    if absent:
        shared = len(set(take.labels) & set(layout.labels))
        hint = f"; the take shares only {shared} of {layout.n_markers} labels: wrong take?" \
            if shared < layout.n_markers / 2 else ""
        raise ValueError(f"{take_path}: {len(absent)} markers of {rig_path} never seen in the neutral take: "
                         f"{absent[:8]}{hint}")
    frames = max(1, int(round(seconds * take.rate))) if seconds else None
    if span is not None:
        if seconds:
            raise ValueError("give seconds or span, not both")
        sel = sel.slice(*span)
    neutral = estimate_neutral(sel, layout.stable, frames)
    settings = {"max_gap_seconds": DEFAULT_MAX_GAP_SECONDS if max_gap_seconds is None else max_gap_seconds,
                "robust_stabilise": robust_stabilise,
                "pose_smoothing_seconds": DEFAULT_POSE_SMOOTHING_SECONDS if pose_smoothing_seconds is None
                else pose_smoothing_seconds,
                "neutral_take": str(take_path), "neutral_frames": frames or sel.n_frames}
    profile = calibrate(rig, layout, neutral, settings, warp=warp, smoothing=smoothing)
    if prior:  # a path, or an AnimationPrior
        profile.prior = prior if isinstance(prior, AnimationPrior) else AnimationPrior.load(prior)
        try:
            profile.prior.check(profile.names)
        except ValueError as exc:
            raise ValueError(f"{prior if not isinstance(prior, AnimationPrior) else 'prior'}: {exc} "
                             f"(rig {rig_path})") from None
    return profile
