"""Rendering: shading a view's pixels under a `Model`, lights and environment light (`shade`),
every view of a capture (`views`) and writing renders as a capture folder (`output`).

May import: `pbrfit.physics`, `pbrfit.io`, `pbrfit.lighting`, `pbrfit.scene`.
"""

from . import output, shade, views
