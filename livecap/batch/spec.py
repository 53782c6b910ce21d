"""What a batch job solves and how, typed and frozen: the command line (or a script) builds it on the client,
the workers get it as is. A job's settings are ``livecap solve``'s: ``livecap batch`` parses manifest and
``--solve-options`` flags with the solve command's own parser (livecap/cli/batch.py), so argparse stays in
livecap/cli/ and tests/test_batch_spec.py checks that any flags give the command's settings."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from livecap.modes.per_frame import check_keys
from livecap.modes.registry import DEFAULT_MODE, MODES_AND_AUTO

CHOICES = {"basis": ("rig", "actor"), "start": ("neutral", "free", "fit"), "end": ("neutral", "free", "fit"),
           "missing": ("fill", "exact"), "limits": ("none", "clip", "bound")}
PRIOR_WORDS = ("shapes", "none", "profile")
MOVEMENT_KEYS = ("alpha", "beta", "prior_threshold", "start", "end", "missing", "limits", "window", "lookahead",
                 "trend")


@dataclass(frozen=True)
class SolveSettings:
    """The solver settings of ``livecap solve``'s flags, one field per flag (``--prior-threshold`` is
    ``prior_threshold``); None keeps the mode's own default (its frozen settings dataclass:
    MovementSettings, RobustSettings, QPSettings, ...), which may come from calibration (the ridge)."""

    ridge: float | None = None
    noise_mm: float | None = None  # replaces the calibrated marker noise (livecap.modes.robust.override_noise)
    temporal: float | None = None
    keys: str | None = None
    basis: str = "rig"
    alpha: float | None = None
    beta: float | None = None
    prior: str | None = None  # an animation prior .npz, a weights CSV, or one of PRIOR_WORDS
    prior_threshold: float | None = None
    start: str | None = None
    end: str | None = None
    missing: str | None = None
    limits: str | None = None
    plain: bool = False
    trend: float | None = None
    marker_weights: tuple[tuple[str, float], ...] = ()  # (label or glob, weight), in the order given
    stream: bool = False
    window: int | None = None
    lookahead: int | None = None

    def __post_init__(self) -> None:
        for name, allowed in CHOICES.items():
            value = getattr(self, name)
            if value is not None and value not in allowed:
                raise ValueError(f"{name}: {value!r} is not one of {', '.join(allowed)}")
        if self.noise_mm is not None and not self.noise_mm > 0:
            raise ValueError(f"noise_mm must be positive, got {self.noise_mm}")

    def options(self) -> dict:
        """The options ``build_solver`` takes, equal to what ``livecap solve`` gives the same flags (a weights
        CSV prior is read here, on the worker)."""
        opts: dict = {} if self.ridge is None else {"ridge": self.ridge}
        opts.update(temporal=self.temporal, keys=self.keys, basis=self.basis)
        movement = {k: getattr(self, k) for k in MOVEMENT_KEYS}
        if self.stream:
            movement["stream"] = True
        if self.plain:
            movement["robust"] = False
        prior = self.prior
        if prior is not None and prior not in PRIOR_WORDS and not prior.endswith(".npz"):
            from transport.weights_csv import read_weights_csv

            names, weights, _ = read_weights_csv(prior)
            prior = {"names": names, "weights": weights}
        movement["prior"] = prior
        movement["marker_weights"] = dict(self.marker_weights) or None
        return {**opts, **{k: v for k, v in movement.items() if v is not None}}


def marker_weights(items: Iterable[str]) -> tuple[tuple[str, float], ...]:
    """``LABEL=WEIGHT`` texts (``--marker-weight``) as pairs; ValueError naming the bad one."""
    pairs = []
    for item in items:
        label, sep, value = item.rpartition("=")
        try:
            if not sep or not label:
                raise ValueError
            pairs.append((label, float(value)))
        except ValueError:
            raise ValueError(f"--marker-weight {item!r}: expected LABEL=WEIGHT") from None
    return tuple(pairs)


@dataclass(frozen=True)
class SolveSpec:
    """How to solve a take: ``livecap solve TAKE --rig ... --out ...`` without the take and the output."""

    rig: str
    mode: str = DEFAULT_MODE
    profile: str | None = None  # a calibrated profile; without one the take calibrates on its first seconds
    markers: str | None = None
    neutral_seconds: float = 1.0
    settings: SolveSettings = field(default_factory=SolveSettings)

    def __post_init__(self) -> None:
        if self.mode not in MODES_AND_AUTO:
            raise ValueError(f"mode: unknown solver mode {self.mode!r} (choose from {sorted(MODES_AND_AUTO)})")
        if not self.neutral_seconds > 0:
            raise ValueError(f"neutral_seconds must be positive, got {self.neutral_seconds}")
        check_keys(self.mode, {"keys": self.settings.keys, "basis": self.settings.basis})

    def inputs(self) -> list[Path]:
        """Files besides the take whose change makes a solve stale."""
        rig = Path(self.rig)
        paths = [rig]
        if rig.is_dir():
            paths += [p for p in rig.iterdir() if p.is_file()]
        paths += [Path(p) for p in (self.profile, self.markers, self.settings.keys, self.settings.prior)
                  if p and p not in PRIOR_WORDS]
        if not self.markers and not rig.is_dir():
            paths.append(rig.with_name(rig.stem + ".markers.json"))
        return paths
