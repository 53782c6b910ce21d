"""A real Live Link Face performance driving the ICT rig, for the suites that measure on real motion.

``livecap.demo.curves_take`` turns ``realdata/performance/<name>.csv`` into a marker take of the ICT rig (60 markers,
53 shapes) with its ground truth and a separate neutral take; the profile is the plain one ``livecap realeval``
calibrates from that neutral take.
"""

from __future__ import annotations

import time


def ict_performance(name: str, settings):
    """(rig, layout, curve take, profile, seconds the calibration took) for performance ``name`` under
    ``settings`` (a ``livecap.demo.curves_take.CurveTakeSettings``); a one-line SystemExit when the file is absent."""
    from livecap.cli.realeval import _realdata, _rig
    from livecap.demo.curves_take import curves_take
    from livecap.offline.real_eval import plain_profile

    path = _realdata() / "performance" / f"{name}.csv"
    if not path.exists():
        raise SystemExit(f"real performance {name}: no {path}")
    rig, layout = _rig("ict")
    ct = curves_take(rig, layout, path, settings)
    t0 = time.perf_counter()
    profile = plain_profile(rig, layout, ct)
    return rig, layout, ct, profile, time.perf_counter() - t0
