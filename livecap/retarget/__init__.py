"""ARKit curves (the iPhone's Live Link Face weights) onto any rig, three ways (issue 40, docs/iphone.md):

* by name (:class:`ByName`): where the rig's shape names are ARKit's (up to case, separators, sides);
* by a mapping file (:class:`ByName` with a mapping, ``examples/makehuman_arkit.json``): where they are not;
* by expression transfer (:class:`ExpressionTransfer`): the weights drive the ICT face (ARKit-like
  shapes), its marker sites are read as virtual markers and the target rig is solved from them through
  the usual calibration and solver modes, so a rig with other shapes gets a fitted expression.

Each is prepared once and has a cheap per-frame ``step(arkit)`` and a whole-take ``apply(arkit)``.
"""

from livecap.retarget.by_name import ByName
from livecap.retarget.expression import ExpressionTransfer, TransferSettings

__all__ = ["ByName", "ExpressionTransfer", "TransferSettings"]
