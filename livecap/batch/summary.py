"""The batch's summary: ``summary.json``, ``summary.csv`` and ``summary.html`` (with ``summary.png``:
marker residual per take and the weight range of every shape per take, to spot bad takes at a glance)."""

from __future__ import annotations

import base64
import csv
import html
import json
import math
from pathlib import Path

import numpy as np

COLUMNS = ["take", "actor", "mode", "status", "frames", "duration_s", "seconds", "residual_p50_mm",
           "residual_p95_mm", "missing_share", "at_lower_share", "at_upper_share", "warnings", "error", "output"]


def _cell(row: dict, key: str):
    v = row.get(key, "")
    if isinstance(v, list):
        return "; ".join(map(str, v))
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    return v


class LiveSummary:
    """``summary.csv`` written as takes finish, one flushed row each (a killed batch leaves the rows of what
    it solved); ``write_summary`` rewrites it in the jobs' order at the end."""

    def __init__(self, out_dir: str | Path) -> None:
        self._fh = open(Path(out_dir) / "summary.csv", "w", newline="")
        self._csv = csv.writer(self._fh)
        self._csv.writerow(COLUMNS)
        self._fh.flush()

    def add(self, row: dict) -> None:
        self._csv.writerow([_cell(row, k) for k in COLUMNS])
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()


def write_summary(rows: list[dict], out_dir: str | Path, meta: dict) -> list[Path]:
    out = Path(out_dir)
    clean = [{k: v for k, v in r.items()} for r in rows]
    (out / "summary.json").write_text(json.dumps({**meta, "takes": clean}, indent=1, default=float))
    with open(out / "summary.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS)
        for r in rows:
            w.writerow([_cell(r, k) for k in COLUMNS])
    png = out / "summary.png"
    _plot(rows, png)
    _html(rows, meta, png, out / "summary.html")
    return [out / "summary.json", out / "summary.csv", out / "summary.html", png]


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    solved = [r for r in rows if r.get("status") in ("ok", "skipped")]
    names = solved[0].get("names", []) if solved else []
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(14, max(3.0, 0.28 * len(rows) + 1.5)),
                                   gridspec_kw={"width_ratios": [1, 2]})
    labels = [r["stem"] for r in rows]
    y = np.arange(len(rows))
    p50 = [r.get("residual_p50_mm", np.nan) if r in solved else np.nan for r in rows]
    p95 = [r.get("residual_p95_mm", np.nan) if r in solved else np.nan for r in rows]
    ax1.barh(y, p95, color="#e0a030", label="p95")
    ax1.barh(y, p50, color="#3070b0", label="p50")
    for i, r in enumerate(rows):
        if r.get("status") == "failed":
            ax1.text(0, i, "  FAILED", va="center", color="red", fontsize=8)
    ax1.set_yticks(y, labels, fontsize=7)
    ax1.invert_yaxis()
    ax1.set_xlabel("marker residual (mm RMS per frame)")
    ax1.legend(loc="lower right", fontsize=7)
    if names and all(len(r.get("weight_max", [])) == len(names) and r.get("names") == names for r in solved):
        grid = np.full((len(rows), len(names)), np.nan)
        for i, r in enumerate(rows):
            if r in solved:
                grid[i] = np.asarray(r["weight_max"]) - np.asarray(r["weight_min"])
        im = ax2.imshow(grid, aspect="auto", cmap="viridis", vmin=0.0, interpolation="nearest")
        ax2.set_xticks(np.arange(len(names)), names, rotation=90, fontsize=6)
        ax2.set_yticks(y, labels, fontsize=7)
        fig.colorbar(im, ax=ax2, label="weight range (max - min)")
        ax2.set_title("weight range per shape (dark row: a take that barely moves; bright: saturates)", fontsize=9)
    else:
        ax2.text(0.5, 0.5, "weight ranges: takes solved for different rigs (see summary.json)",
                 ha="center", va="center", transform=ax2.transAxes)
        ax2.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _html(rows: list[dict], meta: dict, png: Path, path: Path) -> None:
    image = base64.b64encode(png.read_bytes()).decode()
    head = "".join(f"<th>{html.escape(c)}</th>" for c in COLUMNS)
    body = []
    for r in rows:
        style = ' style="background:#fdd"' if r.get("status") == "failed" else (
            ' style="background:#ffc"' if r.get("warnings") else "")
        body.append(f"<tr{style}>" + "".join(f"<td>{html.escape(str(_cell(r, c)))}</td>" for c in COLUMNS) + "</tr>")
    failed = sum(r.get("status") == "failed" for r in rows)
    path.write_text(
        "<!doctype html><html><head><meta charset='utf-8'><title>livecap batch</title>"
        "<style>body{font-family:sans-serif}table{border-collapse:collapse;font-size:12px}"
        "td,th{border:1px solid #ccc;padding:2px 6px}</style></head><body>"
        f"<h1>livecap batch: {len(rows)} takes, {failed} failed</h1>"
        f"<p>{html.escape(json.dumps(meta))}</p>"
        f"<img alt='residual and weight range per take' src='data:image/png;base64,{image}'>"
        f"<table><tr>{head}</tr>{''.join(body)}</table></body></html>")
