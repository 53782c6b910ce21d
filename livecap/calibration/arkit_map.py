"""ARKit's 52 curves (a Live Link Face performance) onto a rig's shapes: what animation priors and the
curves-driven demo takes both need, so it sits below both."""

from __future__ import annotations

import numpy as np

from livecap.core.names import match_names
from transport.arkit import ARKIT_NAMES, arkit_matrix


def arkit_to_rig(names: list[str], mapping: dict | None = None) -> np.ndarray:
    """m x 52 matrix ``A`` with rig weights ``= A @ arkit``: the one place ARKit names meet the rig's.

    Names pair by the project's one matcher (livecap.core.names: a side-less ARKit shape such as
    ``browInnerUp`` drives both sided rig shapes); ``mapping`` (ARKit name -> rig shape(s), the
    file format of ``transport.arkit.load_mapping``) replaces the match of every rig shape it
    names, which then takes the mean of the ARKit shapes mapped onto it.
    """
    A = match_names(ARKIT_NAMES, names).matrix()
    if mapping:
        M = arkit_matrix(names, mapping) > 0  # validates the file's names
        keys = {str(x).lower() for x in mapping}
        mapped = [i for i, a in enumerate(ARKIT_NAMES) if a.lower() in keys]
        for j in np.where(M[mapped].any(0))[0]:
            cols = [i for i in mapped if M[i, j]]
            A[j] = 0.0
            A[j, cols] = 1.0 / len(cols)
    return A
