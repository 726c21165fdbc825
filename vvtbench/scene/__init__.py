"""Scenes and families: what vibrates and how it is seen, as pure data.

* :mod:`vvtbench.scene.scene`: a scene (TOML, validated; docs/scenes.md) and its overrides.
* :mod:`vvtbench.scene.families`: a base scene plus distributions, drawn by seed into scenes
  (docs/families.md); a draw meshes its geometry with :mod:`vvtbench.simulation`.
"""

from .._aliases import forward

#: ``from vvtbench.scene import NAME`` (the module before it became this package) still works,
#: with a DeprecationWarning naming vvtbench.scene.scene
__getattr__ = forward("vvtbench.scene", "vvtbench.scene.scene", globals())
