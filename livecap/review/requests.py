"""Parse and check the review API's request bodies before anything reaches the session.

Everything here runs on bytes a browser (or any program that found the port) sent, so every
field is checked for type, finiteness and range, and a failure names the field in one line
(:class:`BadRequest`, answered with 400). Strict JSON only: ``NaN``/``Infinity`` are refused.
"""

from __future__ import annotations

import json
import math

import numpy as np

from livecap.review.session import Pin, ReviewSession

MAX_PINS = 64
MAX_GOAL_MM = 1e4  # a pin's goal further than 10 m from the rig's origin is a mistake, not a pose


class BadRequest(ValueError):
    """A request body that cannot be obeyed; the message names the field."""


def _no_constant(name: str) -> float:
    raise BadRequest(f"body: {name} is not JSON (values must be finite numbers)")


def parse(text: str) -> object:
    """Strict JSON: no NaN/Infinity, no nesting deep enough to exhaust the parser."""
    try:
        return json.loads(text, parse_constant=_no_constant)
    except json.JSONDecodeError as exc:
        raise BadRequest(f"body: not JSON ({exc.msg} at {exc.pos})") from None
    except RecursionError:
        raise BadRequest("body: nested too deeply") from None


def _short(v: object) -> str:
    s = json.dumps(v) if isinstance(v, (str, int, float, list, dict, bool, type(None))) else repr(v)
    return s if len(s) <= 40 else s[:37] + "..."


def _object(body: object) -> dict:
    if not isinstance(body, dict):
        raise BadRequest(f"body: must be a JSON object, not {_short(body)}")
    return body


def _int(v: object, field: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise BadRequest(f"{field}: must be an integer, not {_short(v)}")
    return v


def _number(v: object, field: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise BadRequest(f"{field}: must be a finite number, not {_short(v)}")
    return float(v)


def _frame_and_range(body: dict, session: ReviewSession) -> tuple[int, int, int]:
    k = _int(body.get("frame"), "frame")
    if not 0 <= k < session.n_frames:
        raise BadRequest(f"frame: {k} is outside the take (0..{session.n_frames - 1})")
    rng = body.get("range")
    if rng is None:
        return k, k, k
    if not isinstance(rng, list) or len(rng) != 2:
        raise BadRequest(f"range: must be [first, last] frames, not {_short(rng)}")
    a, b = _int(rng[0], "range[0]"), _int(rng[1], "range[1]")
    if not a <= k <= b:
        raise BadRequest(f"range: [{a}, {b}] must contain frame {k}")
    return k, a, b


def edit_request(body: object, session: ReviewSession) -> tuple[int, dict[str, float], int, int]:
    """``{frame, weights: {shape: value}, range}``: each value finite and inside the shape's limits."""
    body = _object(body)
    k, a, b = _frame_and_range(body, session)
    weights = body.get("weights")
    if not isinstance(weights, dict) or not weights:
        raise BadRequest(f"weights: must be an object {{shape: value}}, not {_short(weights)}")
    index = {n: j for j, n in enumerate(session.names)}
    values = {}
    for name, v in weights.items():
        if name not in index:
            raise BadRequest(f"weights: unknown shape {_short(name)}")
        x = _number(v, f"weights.{name}")
        lo, hi = session.profile.lower[index[name]], session.profile.upper[index[name]]
        if not lo <= x <= hi:
            raise BadRequest(f"weights.{name}: {x:g} is outside the shape's limits [{lo:g}, {hi:g}]")
        values[name] = x
    return k, values, a, b


def pose_request(body: object, session: ReviewSession) -> tuple[int, list[Pin], bool, int, int]:
    """``{frame, pins: [{vertex | marker, goal: [x, y, z]}], commit, range}``."""
    body = _object(body)
    k, a, b = _frame_and_range(body, session)
    pins = body.get("pins")
    if not isinstance(pins, list) or not 0 < len(pins) <= MAX_PINS:
        raise BadRequest(f"pins: must be a list of 1..{MAX_PINS} pins, not {_short(pins)}")
    out = []
    for i, p in enumerate(pins):
        field = f"pins[{i}]"
        if not isinstance(p, dict):
            raise BadRequest(f"{field}: must be an object {{vertex | marker, goal}}, not {_short(p)}")
        goal = p.get("goal")
        if not isinstance(goal, list) or len(goal) != 3:
            raise BadRequest(f"{field}.goal: must be [x, y, z] in mm, not {_short(goal)}")
        g = np.array([_number(x, f"{field}.goal") for x in goal])
        if np.max(np.abs(g)) > MAX_GOAL_MM:
            raise BadRequest(f"{field}.goal: {g.tolist()} is further than {MAX_GOAL_MM:g} mm from the rig")
        marker, vertex = p.get("marker"), p.get("vertex")
        if marker is not None:
            if not isinstance(marker, str):
                raise BadRequest(f"{field}.marker: must be a marker label, not {_short(marker)}")
            out.append(Pin(g, marker=marker))
        else:
            out.append(Pin(g, vertex=_int(vertex, f"{field}.vertex")))
    commit = body.get("commit", False)
    if not isinstance(commit, bool):
        raise BadRequest(f"commit: must be true or false, not {_short(commit)}")
    return k, out, commit, a, b


def marker_request(body: object, session: ReviewSession) -> tuple[int, str, list[int], np.ndarray]:
    """``{frame, label, triangle: [v0, v1, v2], point: [x, y, z]}``: drop marker ``label`` on that rig triangle
    at ``point`` (mm, the face as drawn at ``frame``)."""
    body = _object(body)
    k, _, _ = _frame_and_range(body, session)
    label = body.get("label")
    if not isinstance(label, str) or label not in session.layout.labels:
        raise BadRequest(f"label: not a marker of the layout: {_short(label)}")
    tri = body.get("triangle")
    if not isinstance(tri, list) or len(tri) != 3:
        raise BadRequest(f"triangle: must be [v0, v1, v2] vertex indices, not {_short(tri)}")
    corners = [_int(v, f"triangle[{i}]") for i, v in enumerate(tri)]
    point = body.get("point")
    if not isinstance(point, list) or len(point) != 3:
        raise BadRequest(f"point: must be [x, y, z] in mm, not {_short(point)}")
    p = np.array([_number(x, "point") for x in point])
    if np.max(np.abs(p)) > MAX_GOAL_MM:
        raise BadRequest(f"point: {p.tolist()} is further than {MAX_GOAL_MM:g} mm from the rig")
    return k, label, corners, p
