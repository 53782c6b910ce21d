"""From solver output to an annotated preview frame: markers onto the rig, weight bars, caption.

The source markers are drawn *retargeted*: each rig marker site at rest plus the actor's
stabilised displacement from neutral, turned into rig axes and units by the calibration
similarity (Seol et al. 2012 §3.2). The line from it to the fitted site is then the residual the
solver left in the marker-space fit (Seol §4, the position term), not the proportion difference
between actor and rig.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from viewer.scene import Similarity

TEXT = (235, 235, 235)  # BGR
DIM = (150, 150, 150)
BAR = (80, 200, 255)  # BGR orange-ish amber
TICK = (255, 255, 255)


def retarget_markers(stabilised: np.ndarray, source_neutral: np.ndarray, rest_sites: np.ndarray,
                     head: Similarity) -> np.ndarray:
    """Source markers in the rig frame: ``site_rest + R_s^T (x - x_neutral) / s``."""
    return rest_sites + head.displacement_to_rig(np.asarray(stabilised) - source_neutral)


def _scale(img: np.ndarray) -> float:
    return img.shape[0] / 480.0


def put_lines(img: np.ndarray, lines: list[str], origin: tuple[int, int] | None = None,
              colour=TEXT, bottom: bool = True) -> None:
    """Text lines (anti-aliased Hershey, dark outline for contrast) at the bottom-left by default."""
    k = _scale(img)
    fs, step = 0.48 * k, int(20 * k)
    x = int(10 * k) if origin is None else origin[0]
    y0 = img.shape[0] - int(10 * k) - step * (len(lines) - 1) if origin is None and bottom else \
        (int(22 * k) if origin is None else origin[1])
    thick = max(1, int(round(k)))
    for i, text in enumerate(lines):
        y = y0 + i * step
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, fs, thick)
        band = img[max(0, y - th - 3): y + base, max(0, x - 3): x + tw + 3]
        band[:] = (band * 0.4).astype(np.uint8)  # dark band behind the text: readable over the face
        cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, fs, colour, thick, cv2.LINE_AA)


def top_shapes(weights: np.ndarray, k: int = 8, also: np.ndarray | None = None) -> np.ndarray:
    """Indices of the ``k`` largest weights (largest of either set when ``also`` is given)."""
    w = np.abs(np.asarray(weights, dtype=np.float64))
    if also is not None:
        w = np.maximum(w, np.abs(also))
    return np.argsort(-w, kind="stable")[:k]


def bar_label_layout(labels: list[str], width: int, k: float) -> tuple[float, int]:
    """Font scale and name-column width (px) that show every label whole: the column is as wide as the
    longest label, and the font shrinks when that would take more than 40 % of the frame's width."""
    fs = 0.36 * k
    widest = max((cv2.getTextSize(lab, cv2.FONT_HERSHEY_SIMPLEX, fs, 1)[0][0] for lab in labels), default=0)
    room = 0.4 * width
    if widest > room:
        fs *= room / widest
        widest = max(cv2.getTextSize(lab, cv2.FONT_HERSHEY_SIMPLEX, fs, 1)[0][0] for lab in labels)
    return fs, int(widest + 6 * k)


def weight_bars(img: np.ndarray, names: list[str], weights: np.ndarray, order: np.ndarray,
                upper: np.ndarray | None = None, reference: np.ndarray | None = None) -> None:
    """A panel of bars (right side) for the shapes in ``order``; ``reference`` adds a white tick."""
    k = _scale(img)
    h, w = img.shape[:2]
    row, bar_w = int(19 * k), int(80 * k)
    fs, name_w = bar_label_layout([names[i] for i in order], w, k)
    x0 = w - bar_w - name_w - int(12 * k)
    y0 = int(12 * k)
    panel = img[y0 - int(4 * k): y0 + row * len(order) + int(2 * k), x0 - int(6 * k): w - int(4 * k)]
    panel[:] = (panel * 0.45).astype(np.uint8)  # darken behind the panel so bars read over the face
    for r, i in enumerate(order):
        y = y0 + r * row
        top = 1.0 if upper is None or upper[i] <= 0 else float(upper[i])
        val = float(weights[i])
        cv2.putText(img, names[i], (x0, y + int(12 * k)), cv2.FONT_HERSHEY_SIMPLEX, fs, TEXT, 1, cv2.LINE_AA)
        bx, by, bh = x0 + name_w, y + int(3 * k), int(11 * k)
        cv2.rectangle(img, (bx, by), (bx + bar_w, by + bh), (70, 70, 70), 1)
        fill = int(round(np.clip(val / top, 0, 1) * bar_w))
        if fill:
            cv2.rectangle(img, (bx, by), (bx + fill, by + bh), BAR, -1)
        if reference is not None:
            tx = bx + int(round(np.clip(reference[i] / top, 0, 1) * bar_w))
            cv2.line(img, (tx, by - int(2 * k)), (tx, by + bh + int(2 * k)), TICK, max(1, int(2 * k)))


@dataclass
class Caption:
    frame: int
    time: float
    solve_ms: float | None = None
    title: str = ""
    extra: str = ""

    def lines(self, marker_rms: float | None = None) -> list[str]:
        first = f"frame {self.frame}   t {self.time:7.3f} s"
        if self.solve_ms is not None:
            first += f"   solve {self.solve_ms:.3f} ms"
        second = []
        if marker_rms is not None and np.isfinite(marker_rms):
            second.append(f"marker residual {marker_rms:.2f} mm rms")
        if self.extra:
            second.append(self.extra)
        return [first] + (["   ".join(second)] if second else [])
